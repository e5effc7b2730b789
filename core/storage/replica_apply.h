// What a cluster replica applies its map's stream through (issue 18): records at stream
// sequences, the applied sequence a restarted replica resumes after, and a switch of vocabulary
// built ahead of its record (issue 29). PlaceMap (core/storage/map_store.h) implements it; the
// map-shard role (server/cluster/shard.h) applies the stream through it and nothing else, so
// what a replica may do to its map is this list.
//
// Thread safety: ApplyAt and ApplyBatch may be called from any thread; calls on one map are
// serialised (one record or batch at a time). Reads of the map (queries, places) go on while
// records are applied and see a place once it is indexed, after its write. applied_sequence(),
// prepared_vocabulary() and CancelPreparedSwitch() may be called from any thread at any time.
// PrepareVocabularySwitch runs beside ApplyAt/ApplyBatch (that is its purpose).
#pragma once

#include <cstdint>
#include <span>

#include "core/base/status.h"

namespace placedb {

struct MapLogRecord;  // one decoded record of a map's stream (core/storage/map_store.h)

class ReplicaApply {
 public:
  // One record and the stream sequence it was delivered at.
  struct SequencedRecord {
    uint64_t sequence = 0;
    const MapLogRecord* record = nullptr;
  };

  virtual ~ReplicaApply() = default;

  // Applies `record` at stream sequence `sequence`. An AddPlace is stored with place id =
  // `sequence`; every record (also the ones that store no place) writes the map's applied
  // sequence = `sequence` in the same batch, synced and counted like a commit, so a restarted
  // replica resumes from applied_sequence() + 1 and applying a record again is harmless. Returns
  // true when applied, false (nothing written) when `sequence` <= applied_sequence(). Sequences
  // may skip (a record that never reached the map); the next place id follows the applied
  // sequence. A kSwitchVocabulary record switches the map's vocabulary (queries go on
  // meanwhile; the record's sequence is written in the switch's batch, so a crash leaves the old
  // vocabulary, applied below it, or the new one).
  // Errors, nothing changed (applied sequence included): CORRUPTION when a switch's parts are
  // missing or do not make the named vocabulary; INVALID_ARGUMENT for a record the map cannot
  // take (an invalid frame as AddPlace, the wrong feature type or direct-index level, a sequence
  // beyond the place-id range); NOT_FOUND when the map was deleted; the storage's write errors.
  // Not meant to be mixed with a map's own writes (Add, Commit, Enqueue, RemovePlace).
  virtual Result<bool> ApplyAt(uint64_t sequence, const MapLogRecord& record) = 0;

  // ApplyAt for consecutive records in ascending sequence, storing what one ApplyAt per record
  // would, but each run of records between DeletePlace records written as one synced batch (the
  // applied sequence = the run's last): how a replica keeps up with a fast stream. Records at or
  // below applied_sequence() are skipped. Returns how many were applied.
  // Errors: a record the map cannot take (INVALID_ARGUMENT, CORRUPTION as ApplyAt's): the
  // records before it are applied, it and the ones after are not; a write error: the failing
  // run's records are not applied. Either way applied_sequence() says where the map stands, and
  // applying again from applied_sequence() + 1 is correct.
  virtual Result<size_t> ApplyBatch(std::span<const SequencedRecord> records) = 0;

  // The last sequence applied (persisted; 0 for a map that never applied one). It moves once
  // the records up to it are searchable, not merely stored: a reader that waited for a sequence
  // finds every place up to it.
  virtual uint64_t applied_sequence() const = 0;

  // Builds the switch to vocabulary `checksum` from its `parts` stored parts (kVocabularyPart
  // records; 0: bytes the map stores whole) while records go on being applied, so that the
  // kSwitchVocabulary record for it only catches up with the places applied since. Blocks until
  // built: call it on a thread of its own. Nothing of it is durable (a reopened map builds the
  // switch when it applies the record); OK without building anything when `checksum` is the
  // map's vocabulary already.
  // Errors, nothing prepared: FAILED_PRECONDITION during another switch; CORRUPTION as
  // ApplyAt's switch; CANCELLED by CancelPreparedSwitch.
  virtual Status PrepareVocabularySwitch(uint64_t checksum, uint32_t parts) = 0;

  // The vocabulary a prepared switch waits for its record with (0: none).
  virtual uint64_t prepared_vocabulary() const = 0;

  // Stops a preparation in progress (it returns CANCELLED) and drops a prepared switch: a
  // replica closing. Waits for the preparation to stop; nothing to do without one.
  virtual void CancelPreparedSwitch() = 0;
};

}  // namespace placedb
