// Durable maps: place databases persisted in RocksDB (see docs/storage.md for the layout).
//
// A DataDirectory holds many maps, each its own RocksDB instance under maps/<name>/. A PlaceMap
// is a PlaceDatabase (the in-memory serving index) whose places are written to RocksDB first:
// one atomic WriteBatch per place (record, BoW vector, SC features + direct index), acknowledged
// only once the write-ahead log is synced. DC descriptors are never written; their counts are.
// Reopening a map rebuilds the inverted index from the stored BoW vectors; features stay on disk
// and are read only for the candidates being verified.
//
// Dynamic-object statistics (issue 16, core/dynamics/place_dynamics.h) live in the map's
// "dynamics" column family, one value per place plus the map's aggregate, kept by a merge
// operator: a stored frame's statistics are merge operands in the place's own batch, a frame
// loop-closure rehearsal merges into a place is one more acknowledged batch of operands. No
// read-modify-write, so concurrent writers never lose an update, and what is acknowledged is
// counted. They are read on demand from RocksDB (nothing in memory) and never reach the
// PlaceDatabase: descriptors and ranking are the same with or without them.
//
// Thumbnails (issue 20, core/thumbnail/thumbnail.h), when the map keeps them, live in the
// "thumbnails" column family: one value per place, made by Process() on the caller's thread,
// written in the place's own batch (acknowledged = stored), deleted with the place, read on
// demand (GetThumbnail).
//
// Damage is never silent (docs/storage.md, "Damage"): every acknowledged write is counted twice,
// in the map's RocksDB (a merge counter inside the write's own batch) and in a small checksummed
// file beside it (ACKED, fdatasync'ed before the write is acknowledged). Opening a map compares
// the two; a map that lost acknowledged writes, or whose files RocksDB cannot read, does not
// open: OpenMap answers CORRUPTION naming the file (relative to the data directory) and what is
// wrong. RecoverMap is the operator's explicit choice to accept the loss; the map then carries
// the loss in its damage history for good.
//
// Thread safety: a PlaceMap takes concurrent Add/Query/Remove calls. A DataDirectory serialises
// create/open/delete. DeleteMap() waits for in-flight calls on the map, closes it and removes
// its files; holders of the PlaceMap then get NOT_FOUND ("map was deleted"), never a crash.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <thread>
#include <unordered_map>
#include <vector>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "core/dynamics/place_dynamics.h"
#include "core/pipeline/place_database.h"
#include "core/storage/codec.h"
#include "core/storage/directory_lock.h"
#include "core/storage/loop_log.h"
#include "core/storage/replica_apply.h"
#include "core/vocabulary/any_vocabulary.h"
#include "core/vocabulary/vocabulary.h"
#include "core/vocabulary/vocabulary_learning.h"

namespace rocksdb {
class WriteBatch;
}  // namespace rocksdb

namespace placedb {

namespace detail {
struct MapStorage;  // RocksDB handles of one map (map_storage.h)
}  // namespace detail

enum class SyncMode {
  kEveryWrite,   // each place's batch is written with sync=true (RocksDB groups concurrent ones)
  kGroupCommit,  // batches are written unsynced; a syncer fsyncs the WAL at most every
                 // group_commit_delay_ms and only then acknowledges the places it covered
};

struct StorageOptions {
  SyncMode sync = SyncMode::kEveryWrite;
  int group_commit_delay_ms = 5;
  size_t block_cache_bytes = size_t(64) << 20;  // shared by all maps of the directory
  // Count acknowledged writes in ACKED (docs/storage.md, "Damage"). Off only to measure its
  // cost: writes are then not counted and opening a map does not check for lost writes.
  bool acked_file = true;
  // Keep dynamic-object statistics (issue 16). Off only to measure their cost: frames are then
  // not counted, and a map's statistics stay behind what it stored.
  bool dynamics = true;
  // New places (and invalid observations) are refused with RESOURCE_EXHAUSTED ("disk full") while
  // the map's file system has less free space than its memtables plus this: RocksDB then never
  // runs out of space in the middle of a write or flush. 0 = only when a write actually fails
  // for lack of space. Removals are not held back.
  uint64_t disk_reserve_bytes = uint64_t(8) << 20;
  // RestoreMap hard-links a checkpoint's SST files (immutable in RocksDB) instead of copying
  // them. Off only to measure the difference: restore then copies every file.
  bool restore_hard_links = true;
  // Threads that rebuild the index when a map opens. 1 = one sequential scan of `places` and
  // `bow` on the opening thread, which decodes and indexes each place in turn (the baseline of
  // placedb-bench-storage --only reopen). N > 1 = N threads each read, decode and build the
  // index of ranges of place ids (load_range_ids) while the opening thread only moves the built
  // ranges into the index, in id order: 2 (the default; 0 = 2) keeps both cores of a 2-core
  // machine busy.
  unsigned load_threads = 2;
  // Place ids per range a load thread reads and builds the index of at a time (rounded down to
  // a power of two, at most 65536; 0 = 65536): ranges align with the index's id segments, and a
  // whole segment is moved into the index without copying. Smaller ranges are appended to their
  // segment (copied); tests use them to have many range boundaries in a small map.
  uint32_t load_range_ids = 65536;
};

struct MapOptions {
  DatabaseConfig database;
  // Keep invalid observations as metadata only (no descriptors), to see where the robot saw
  // nothing usable. Off by default: invalid observations are counted, not stored.
  bool store_invalid = false;
  // Keep a small JPEG per place (its frame reduced, dynamic objects blurred; core/thumbnail), in
  // the "thumbnails" column family, written in the place's own batch. Only frames with pixels
  // have one. Validated by CreateMap (ValidateThumbnailSettings).
  ThumbnailSettings thumbnails;
  // A query whose best match scores above this (Match::score, the map's scoring) counts as one
  // more observation of that place's dynamic objects (CountQueryHit); 0 = off, the default.
  // Queries then write: the map's creator chose it.
  double count_query_hits_above = 0;
  // Settings of the layer above (the service's detection policy), stored with the map's info so
  // they are written atomically with it and travel with checkpoints. Opaque to storage.
  std::string service_json;
};

struct MapStats {
  DatabaseStats database;        // places, descriptors kept/dropped, invalid, memory
  uint64_t invalid_stored = 0;   // invalid observations kept as metadata
  uint64_t bytes_on_disk = 0;    // every file of the map's directory
  uint64_t bytes_in_memory = 0;  // index + records + payload cache
};

// Where one of a map's vocabularies came from (issue 29).
struct VocabularySource {
  // "file": a vocabulary file of the server (the one the map was created with);
  // "learned": learned from the map's own stored static descriptors (AdaptVocabulary).
  std::string origin = "file";
  uint64_t checksum = 0;   // AnyVocabulary::checksum()
  uint32_t branching = 0;  // k
  uint32_t depth = 0;      // L
  uint64_t words = 0;
  int64_t learned_unix_ms = 0;  // when it was learned (0 for a file's)
  // What a learned vocabulary was learned from (LearnedVocabulary's counts; 0 for a file's).
  uint64_t places_offered = 0;
  uint64_t descriptors_offered = 0;
  uint64_t places_sampled = 0;
  uint64_t descriptors_sampled = 0;
  double learn_ms = 0;  // reading the stored descriptors and training
  bool operator==(const VocabularySource&) const = default;
};

// A map's vocabulary and the one before it. Generation 0 is the vocabulary the map was created
// with, not stored with the map (the server gives it at open by its checksum). Every switch
// (AdaptVocabulary, RevertVocabulary) makes the next generation, stored with the map: it opens
// without any vocabulary file, and snapshots and checkpoints carry it.
struct VocabularyRecord {
  uint64_t generation = 0;
  VocabularySource current;
  std::optional<VocabularySource> previous;  // RevertVocabulary's target
  int64_t since_unix_ms = 0;                 // when `current` became the map's
  uint64_t places_reindexed = 0;             // by the switch that made it the map's
  double reindex_ms = 0;                     // that switch's re-index, catch-up and write
  bool stored() const { return generation > 0; }
  bool operator==(const VocabularyRecord&) const = default;
};

struct MapInfo {
  std::string name;
  MapOptions options;                // options.database.feature_type: the vocabulary's kind
  uint64_t vocabulary_checksum = 0;  // AnyVocabulary::checksum(), binary or float
  int64_t created_unix_ms = 0;
  VocabularyRecord vocabulary;  // current.checksum == vocabulary_checksum
};

// A switch of a map's vocabulary (PlaceMap::AdaptVocabulary / RevertVocabulary) in order; each
// phase is durable when reported. A crash before kSwitched leaves the old vocabulary, from
// kSwitched on the new one.
enum class VocabularyPhase {
  kLearned,    // the vocabulary is learned (AdaptVocabulary) or read (RevertVocabulary)
  kReindexed,  // every place stored at the start is in the new BoW family and index
  kCaughtUp,   // places stored or removed meanwhile too; writers are held from here
  kSwitched,   // the switch's batch is durable: the map has the new vocabulary
  kCleaned,    // the previous vocabulary's BoW family is gone; writers resume after this
};

struct AdaptOptions {
  LearningOptions learning;
  // Threads learning (unless learning.threads says otherwise) and transforming places with the
  // new vocabulary; 0 = the machine's cores. 1 by default: at the lowered priority below a second
  // one finds no idle core while queries run (placedb-bench-vocabulary-learning, 100k places on
  // 2 cores: 31.5 s with 1 thread, 32.1 s with 2).
  int threads = 1;
  // The switch runs on a thread this much nicer than the caller (Linux: per thread; its threads
  // inherit it), so queries and ingest keep the CPU they need; 0 = on the calling thread. Same
  // bench: query p99 during the switch 5.65 ms, idle 5.66 ms (at nice 0: 10.2 ms against 3.7).
  int nice = 10;
  // Checked between chunks of places and before writers are held: once true, the switch stops
  // with CANCELLED and the map keeps its vocabulary (a server shutting down). Null = never.
  const std::atomic<bool>* cancel = nullptr;
  // Called at each phase on the switching thread (tests crash the process there).
  std::function<void(VocabularyPhase)> on_phase;
};

// Acknowledged writes a map lost, and why. Reasons name the file relative to the data directory
// ("maps/lab/000012.log: ..."), never an absolute path.
struct MapDamage {
  std::string reason;
  uint64_t writes_lost = 0;  // acknowledged writes (places, removals, stored invalid frames)
  // Acknowledged place ids missing: first..last (0 when none). With concurrent writers the range
  // may also hold ids whose writes were in flight and never acknowledged (an upper bound).
  uint64_t places_lost = 0;
  PlaceId first_lost = 0;
  PlaceId last_lost = 0;
  int64_t recovered_unix_ms = 0;  // when the operator accepted it (history entries)
  // What RecoverMap's scan of the places that remain found missing (each place counted once, by
  // its first missing part). A place without its record or BoW vector cannot be found: what is
  // left of it is dropped from the map. A place without its features is still found by search
  // but cannot be verified; reading it is CORRUPTION (DATA_LOSS).
  uint64_t records_lost = 0;
  uint64_t bow_lost = 0;
  uint64_t features_lost = 0;
  // Where RecoverMap kept the map's files as they were before it changed anything, relative to
  // the data directory ("quarantine/lab-1764320000000"); empty when nothing was changed.
  std::string quarantine;
};

// PlaceMap::Scrub's findings.
struct ScrubReport {
  struct Place {
    PlaceId id = 0;
    std::string reason;
  };
  struct File {
    std::string file;  // relative to the data directory
    std::string reason;
  };
  uint64_t places_checked = 0;
  uint64_t files_checked = 0;
  std::vector<Place> damaged_places;
  std::vector<File> damaged_files;
  bool clean() const { return damaged_places.empty() && damaged_files.empty(); }
};

// A persisted place with its payload read back from disk.
struct StoredPlace {
  PlaceRecord record;
  PlacePayload payload;
};

// Cluster mode (issue 18): one record of a replicated map's log (its JetStream stream), decoded
// (server/cluster/map_record.h), for PlaceMap::ApplyAt. Every replica applies the same records in
// stream order and so holds the same places under the same ids.
struct MapLogRecord {
  enum class Kind {
    kAddPlace,          // `frame` (valid: SC bow, features, direct index, counts, boxes, thumbnail,
                        // DC part) + `metadata` becomes place id = the record's sequence
    kDeletePlace,       // `place` removed (absent: nothing but the applied sequence changes)
    kCountObservation,  // `dynamics` added to `place` (0 or absent: the map's aggregate only)
    kInvalidFrame,      // counted; kept as metadata (frame.counts, frame.boxes_used,
                        // frame.rejection, `metadata`) when the map stores invalid frames
    // Issue 29: a vocabulary learned once (on one replica) reaches every replica through the
    // stream, in parts (a vocabulary is larger than a stream message), then one record switches.
    kVocabularyPart,     // `vocabulary_part` stored with the map until its switch
    kSwitchVocabulary,   // the map switches to `vocabulary_source` here, at this sequence: from
                         // its parts, or from the bytes the map stores (its previous vocabulary)
    kPrepareVocabulary,  // nothing but the applied sequence: the replica's host starts building
                         // the switch to `vocabulary_source.checksum` (PrepareVocabularySwitch)
    kLoopConstraints,    // issue 32: `loops` (query_place set) into the map's loop-closure log
  };
  Kind kind = Kind::kAddPlace;
  // An AddPlace frame's vocabulary_checksum says which vocabulary made its BoW vector (0: the
  // map's current one); a frame of another is transformed again when applied.
  ProcessedFrame frame;
  PlaceMetadata metadata;
  PlaceId place = 0;
  // The frame's statistics operand, made once by the publisher (it carries its arrival time), so
  // every replica stores the same bytes. nullopt: none.
  std::optional<PlaceDynamics> dynamics;
  struct VocabularyPart {
    uint64_t checksum = 0;  // of the whole vocabulary (AnyVocabulary::checksum)
    uint32_t index = 0;     // 0-based
    uint32_t count = 0;     // parts of the vocabulary
    std::string bytes;      // AnyVocabulary::Serialize()'s bytes [index * part size, ...)
  };
  VocabularyPart vocabulary_part;
  // kSwitchVocabulary: the vocabulary (its checksum) and where it came from; `vocabulary_parts`
  // parts were published before (0: the map stores its bytes: a revert). kPrepareVocabulary:
  // the checksum and parts alone.
  VocabularySource vocabulary_source;
  uint32_t vocabulary_parts = 0;
  // kLoopConstraints: logged in order (their place_metadata is the replica's record of the
  // place when it has one).
  std::vector<LoopConstraint> loops;
};

// A vocabulary learned from a map's stored places, not yet the map's (PlaceMap::LearnVocabulary).
struct MapLearnedVocabulary {
  AnyVocabulary vocabulary;
  VocabularySource source;  // origin "learned", with what it was learned from
};

// A place handed to a map's commit queue (PlaceMap::Enqueue): its outcome once the group it was
// written in is durable (WAL synced, counted in ACKED) and it is indexed, or why it failed.
// Thread safety: any thread may wait; the map's committer completes it once.
class PendingCommit {
 public:
  // Blocks until the outcome is known. Every call returns the same outcome.
  const Result<AddResult>& Wait() const EXCLUDES(mutex_);
  bool done() const EXCLUDES(mutex_);
  // The committer's, once: wakes every waiter.
  void Complete(Result<AddResult> outcome) EXCLUDES(mutex_);

 private:
  mutable Mutex mutex_;
  mutable CondVar done_cv_;
  bool done_ GUARDED_BY(mutex_) = false;
  // Written once under mutex_ before done_ is set; read-only afterwards.
  Result<AddResult> outcome_ = Status::Internal("not committed yet");
};

// What opening a map spent rebuilding its index (PlaceMap::Load), for benchmarks and logs.
struct OpenTimings {
  unsigned threads = 1;       // StorageOptions::load_threads
  double total_ms = 0;        // the whole rebuild
  double read_decode_ms = 0;  // reading and decoding `places` + `bow`, summed over the threads
  // The index: PlaceDatabase::Restore on the opening thread (1 thread), or building segments
  // (summed over the workers) plus installing them on the opening thread (more threads).
  double index_ms = 0;
};

class PlaceMap final : public ReplicaApply {
 public:
  ~PlaceMap();  // flushes and closes RocksDB
  PlaceMap(const PlaceMap&) = delete;
  PlaceMap& operator=(const PlaceMap&) = delete;

  // A copy: the vocabulary's part changes when the map switches vocabularies.
  MapInfo info() const EXCLUDES(state_mutex_);
  // The map's options, fixed when it was created: no copy, no lock (per-frame callers).
  const MapOptions& options() const { return info_.options; }
  // The serving index. A switch of vocabulary replaces it; the holder keeps the one it got.
  std::shared_ptr<const PlaceDatabase> database() const EXCLUDES(state_mutex_);
  AnyVocabulary vocabulary() const EXCLUDES(state_mutex_);
  // Losses the operator accepted with DataDirectory::RecoverMap, oldest first; kept for good
  // (a map with any is shown as recovered).
  const std::vector<MapDamage>& damage_history() const { return damage_history_; }
  // What opening the map tolerated, for the operator's log ("" when nothing): a torn tail of
  // the write-ahead log that held no acknowledged write.
  const std::string& open_note() const { return open_note_; }
  // What the rebuild of the index cost when the map was opened (or created).
  const OpenTimings& open_timings() const { return open_timings_; }

  // FAILED_PRECONDITION naming both checksums (and kinds) when `vocabulary` is not the map's.
  // A map that stores its own vocabulary (VocabularyRecord::stored) uses it: any `vocabulary`
  // (also none) is OK.
  Status CheckVocabulary(const AnyVocabulary& vocabulary) const EXCLUDES(state_mutex_);

  // Issue 29: learns a vocabulary from the map's stored static descriptors (VocabularyLearner,
  // `options.learning`) and makes it the map's: every place is transformed again into a new BoW
  // family and index built beside the live ones while queries and writes go on; places stored
  // or removed meanwhile are caught up, then one synced batch switches (generation, vocabulary,
  // previous vocabulary, record, info) and the new index replaces the old in memory. Writers
  // wait only for the catch-up's last places and the switch. A crash leaves the old vocabulary
  // or the new one, never a mix (VocabularyPhase). Agents' stream state and the short-term tier
  // start again (as after a reopen); frames processed with the old vocabulary are transformed
  // again when committed or searched. Returns the new record.
  // Errors, the map unchanged: FAILED_PRECONDITION when the map is too small to learn from
  // (naming what it has and what is needed), when a switch is already running, or for a
  // replica of a cluster map; INVALID_ARGUMENT for bad learning options; NOT_FOUND when the map
  // is deleted meanwhile; the storage's write errors.
  Result<VocabularyRecord> AdaptVocabulary(const AdaptOptions& options = {});
  // Makes the previous vocabulary the map's again, the same way (the current one becomes the
  // previous). FAILED_PRECONDITION when there is none (the map never switched); CORRUPTION when
  // the stored previous vocabulary is damaged.
  Result<VocabularyRecord> RevertVocabulary(const AdaptOptions& options = {});
  // AdaptVocabulary's first half: learns a vocabulary from the map's stored static descriptors
  // and returns it without switching (cluster mode: one replica learns, every replica switches
  // through the stream). Also on a replica. Errors as AdaptVocabulary's; nothing changes.
  Result<MapLearnedVocabulary> LearnVocabulary(const AdaptOptions& options = {}) const;
  // AdaptVocabulary's second half with a vocabulary from elsewhere (`source` says where; its
  // checksum must be `vocabulary`'s): re-index, catch up, switch, as AdaptVocabulary. For a
  // cluster worker's place-less copy of a map following its replicas. FAILED_PRECONDITION on a
  // replica (it switches through ApplyAt) or during another switch; INVALID_ARGUMENT for a
  // vocabulary of the other feature type or a checksum that is not its.
  Result<VocabularyRecord> InstallVocabulary(AnyVocabulary vocabulary, VocabularySource source,
                                             const AdaptOptions& options = {});
  bool switching_vocabulary() const { return switching_.load(); }
  // Cluster replicas (ReplicaApply, core/storage/replica_apply.h); the preparation runs on one
  // thread at nice 10.
  Status PrepareVocabularySwitch(uint64_t checksum, uint32_t parts) override;
  uint64_t prepared_vocabulary() const override { return prepared_checksum_.load(); }
  void CancelPreparedSwitch() override;

  // Process (as the agent's next stream frame) + AdvanceStream + (when valid) durable write +
  // index. An invalid frame is counted, and stored as metadata when the map's store_invalid is
  // set. Returns once durable.
  Result<AddResult> Add(const Observation& observation);
  // Stores an already processed frame (ingest-with-matches searches first, then commits).
  Result<AddResult> Commit(const ProcessedFrame& frame, const PlaceMetadata& metadata);
  // Commit() without waiting (group commit, docs/storage.md "Group commit"): checks the frame
  // and reserves its id now (so ids follow the order of Enqueue() calls), encodes its batch on
  // the caller's thread and hands it to the map's committer thread, which writes every queued
  // place in one WriteBatch, syncs it once, counts the group in ACKED with one fdatasync, and
  // only then indexes each place and completes its PendingCommit. A failed write fails every
  // place of its group and stores none of them (one atomic batch). A frame refused by the
  // checks, an invalid frame (StoreInvalid) and a deleted map are answered synchronously: the
  // returned commit is already done. Places enqueued by one thread are durable and indexed in
  // that order; a caller that must search after its own places waits for the last one first.
  // `found`: the frame's loop constraints (loop_log.h; verified matches against earlier places),
  // numbered and written in the place's batch with query_place set to its id.
  std::shared_ptr<PendingCommit> Enqueue(ProcessedFrame frame, PlaceMetadata metadata,
                                         std::vector<LoopConstraint> found = {});
  // Stream frames (kStream) of a map that keeps thumbnails get theirs here (on the caller's
  // thread, outside any lock of the map); Commit() stores it with the place.
  // `keep_dropped_keypoints` fills `dropped_keypoints`.
  Result<ProcessedFrame> Process(const Observation& observation, FrameRole role = FrameRole::kQuery,
                                 bool keep_dropped_keypoints = false) const {
    return database()->Process(observation, role, ThumbnailsFor(role), keep_dropped_keypoints);
  }
  // See PlaceDatabase::AdvanceStream: the agent's frames in order.
  Status AdvanceStream(ProcessedFrame* frame, const std::string& agent_id);
  // Loop closure for an ingest stream (PlaceDatabase::CloseLoop) with Commit() as the store: a
  // frame that rehearsal does not merge is written durably; `added` then receives the commit's
  // result (stored = false when merged). The long-term memory of the agent's detector is this
  // map's RocksDB payloads.
  // `found` (the frame's verified matches) and the detector's accepted loop are written to the
  // loop log (loop_log.h) right after the place, before this returns; a failure to log them is
  // this call's error (the place is stored).
  Result<LoopClosureOutcome> CloseLoop(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                       AddResult* added, std::vector<LoopConstraint> found = {});
  // The loop log (loop_log.h): up to `max` constraints `filter` accepts from sequence `from` on;
  // `*scanned` receives the last sequence looked at. NOT_FOUND once the map is deleted;
  // CORRUPTION naming the sequence when a stored constraint is damaged.
  Result<std::vector<LoopConstraint>> ReadLoops(uint64_t from, size_t max, const LoopFilter& filter,
                                                uint64_t* scanned) const EXCLUDES(lifecycle_);
  uint64_t last_loop_sequence() const { return loops_->last_sequence(); }
  // Blocks until a constraint after `sequence` is logged, `deadline` passes or the map is deleted
  // (then `*deleted` is set); returns last_loop_sequence().
  uint64_t WaitForLoops(uint64_t sequence, std::chrono::steady_clock::time_point deadline,
                        bool* deleted) const;
  // Cluster mode's worker, whose local copy of the map holds no places: PlaceDatabase::CloseLoop
  // with the caller's `store` (publishing the frame) and `source` (the map's replicas); nothing
  // is written to this map, also not a merged frame's statistics (the caller records them).
  Result<LoopClosureOutcome> CloseLoop(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                       const std::function<Result<PlaceId>()>& store,
                                       PlaceSource* source);
  // See PlaceDatabase::ResetLoopClosure.
  void ResetLoopClosure(const std::string& agent_id);
  Result<QueryResult> Query(const Observation& observation, const QueryOptions& options) const;
  // A query's best match as one more observation of its place (issue 16): when the map counts
  // query hits (MapOptions::count_query_hits_above > 0) and `result` is valid with its best
  // match scoring above the setting, `frame`'s statistics (timestamp from `metadata`) are added
  // to that place and the map's aggregate in one acknowledged write, as a frame merged by
  // rehearsal is. True when counted; false (nothing written) when off, invalid, without a match
  // or not above. A place removed meanwhile: only the aggregate counts the frame. Errors are the
  // write's (RESOURCE_EXHAUSTED when the disk is full, IO_ERROR); nothing is counted then.
  Result<bool> CountQueryHit(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                             const QueryResult& result);
  // An invalid result with the reason when the map was deleted meanwhile.
  QueryResult Search(const ProcessedFrame& frame, const QueryOptions& options) const;

  Result<StoredPlace> GetPlace(PlaceId id) const;  // NOT_FOUND if absent
  // The place's BoW vector alone (read from disk, as loop closure's long-term memory reads it).
  // NOT_FOUND if absent.
  Result<BowVector> GetBow(PlaceId id) const;
  // Cluster mode (ReplicaApply, core/storage/replica_apply.h): the stream's records, applied.
  Result<bool> ApplyAt(uint64_t sequence, const MapLogRecord& record) override;
  Result<size_t> ApplyBatch(std::span<const SequencedRecord> records) override;
  uint64_t applied_sequence() const override { return applied_sequence_.load(); }

  Status RemovePlace(PlaceId id);  // durable before it returns
  std::vector<InvalidObservation> InvalidObservations(size_t limit) const;

  // The place's dynamic-object statistics: every frame stored at it or merged into it. Empty
  // for a place stored before the map kept statistics. NOT_FOUND when the place does not exist;
  // CORRUPTION (naming the place) when the stored value does not decode.
  Result<PlaceDynamics> GetDynamics(PlaceId id) const;
  // The map's aggregate: every acknowledged frame stored or merged, also at places removed since
  // (the map's history: a removal cannot subtract a maximum).
  Result<PlaceDynamics> MapDynamics() const;
  // The frames refused as invalid (no place; often too covered by objects): their own
  // aggregate, not in MapDynamics(). Counted like the invalid-frame counter: in a batch that
  // is synced only when the map stores invalid observations (MapOptions::store_invalid).
  Result<PlaceDynamics> InvalidDynamics() const;
  // Calls `visit` with every existing place that has statistics, ascending id, until it returns
  // false; one place at a time in memory (rankings keep only their top entries).
  Status ForEachPlaceDynamics(
      const std::function<bool(PlaceId, const PlaceDynamics&)>& visit) const;
  // The place's thumbnail, read from disk (nothing is kept in memory); nullopt when the place has
  // none (thumbnails off when it was stored, or a frame without pixels). NOT_FOUND when the place
  // does not exist; CORRUPTION (naming the place) when the stored value does not decode.
  Result<std::optional<Thumbnail>> GetThumbnail(PlaceId id) const;
  MapStats Stats() const;

  // An online, consistent copy of the map into `directory` (which must not exist), made with
  // RocksDB checkpoints (hard links where possible). Restore it with DataDirectory::RestoreMap.
  Status Checkpoint(const std::string& directory) const;
  // Scans every column family and checks they agree (each place has its BoW and features, and
  // nothing else is stored). Used by crash tests; cheap enough for an operator's fsck.
  Status VerifyIntegrity() const;
  // Reads every place (record, BoW vector, features; each decoded) and verifies every block of
  // every SST file. Damage goes into the report (files in RocksDB's order, places by id), not
  // the status; the status is an error only when the scrub itself cannot run (map deleted).
  // Changes nothing. `threads` > 1 checks files and runs of places in parallel (the report is
  // the same): a snapshot's verification uses the machine's cores, a live map's ScrubMap one.
  Result<ScrubReport> Scrub(int threads = 1) const;

 private:
  friend class DataDirectory;
  PlaceMap(MapInfo info, std::string path, std::unique_ptr<detail::MapStorage> storage,
           AnyVocabulary vocabulary);
  // Rebuilds the serving index from disk: with StorageOptions::load_threads > 1, that many
  // threads each read and decode one index segment's ids (2^16) and build its part of the index
  // off the database (at most 2 segments ahead), the calling thread installs them in id order;
  // with 1, the calling thread scans and restores place by place. A read error is CORRUPTION naming
  // the file; the first problem in id order is the one reported, whatever the thread count.
  Status Load();
  // Commit() for a caller that already holds lifecycle_ shared and checked `closed_`
  // (CloseLoop's store callback: the shared lock must not be taken twice).
  Result<AddResult> CommitLocked(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                 std::vector<LoopConstraint> found = {})
      REQUIRES_SHARED(lifecycle_);
  // `found` with query_place = `place`, written to the loop log in a batch of their own.
  Status LogLoops(PlaceId place, std::vector<LoopConstraint> found) REQUIRES_SHARED(lifecycle_);
  Result<AddResult> StoreInvalid(const ProcessedFrame& frame, const PlaceMetadata& metadata);
  // One acknowledged write adding `frame`'s statistics to `place` (0 or removed: the map's
  // aggregate only) and to the aggregate: frames merged by rehearsal, counted query hits.
  Status CountObservationAt(PlaceId place, const ProcessedFrame& frame,
                            const PlaceMetadata& metadata, const std::string& what)
      REQUIRES_SHARED(lifecycle_);
  Status Deleted() const;
  // The settings Process() makes thumbnails with: the map's, for stream frames, when enabled.
  const ThumbnailSettings* ThumbnailsFor(FrameRole role) const {
    return role == FrameRole::kStream && info_.options.thumbnails.enabled
               ? &info_.options.thumbnails
               : nullptr;
  }
  // An aggregate of the dynamics family (MapDynamics, InvalidDynamics); `what` for messages.
  Result<PlaceDynamics> ReadAggregate(const char* key, const std::string& what) const;
  // Place `id`'s value in a per-place column family (`family`: its index in map_storage.h's
  // list); nullopt when the place has none. NOT_FOUND for an absent place; `what` for messages.
  Result<std::optional<std::string>> ReadPlaceValue(PlaceId id, size_t family,
                                                    const std::string& what) const;

  // The frame as this map's vocabulary makes it: `frame` itself, or a copy in `*copy`
  // transformed again (it was processed before a switch of vocabulary).
  Result<const ProcessedFrame*> OfCurrentVocabulary(const ProcessedFrame& frame,
                                                    std::optional<ProcessedFrame>* copy) const
      REQUIRES_SHARED(lifecycle_);
  // FAILED_PRECONDITION unless this is the only switch running (`only_switch`) on a map that is
  // not a cluster replica.
  Status MaySwitch(bool only_switch) const;
  // CANCELLED once options.cancel is set.
  Status Cancelled(const AdaptOptions& options) const;
  // AdaptVocabulary / RevertVocabulary on the thread that does the work.
  Result<VocabularyRecord> AdaptVocabularyNow(const AdaptOptions& options);
  Result<VocabularyRecord> RevertVocabularyNow(const AdaptOptions& options);
  // AdaptVocabulary / RevertVocabulary after the vocabulary is known: re-index, catch up,
  // switch (vocabulary_switch.cc). `record` says where `next` came from. `at_sequence` (a
  // replica's kSwitchVocabulary record): the applied sequence written in the switch's batch.
  Result<VocabularyRecord> SwitchVocabulary(AnyVocabulary next, VocabularyRecord record,
                                            const AdaptOptions& options,
                                            std::optional<uint64_t> at_sequence = std::nullopt)
      EXCLUDES(lifecycle_);
  // A switch in three steps (vocabulary_switch.cc): the new family and index; every place
  // re-indexed and caught up with writers going on; the rest with them held, and the switch.
  struct PreparedSwitch;
  struct PreparedSwitchDeleter {  // where PreparedSwitch is complete (vocabulary_switch.cc)
    void operator()(PreparedSwitch* build) const;
  };
  using PreparedSwitchPtr = std::unique_ptr<PreparedSwitch, PreparedSwitchDeleter>;
  Result<PreparedSwitchPtr> BeginSwitch(AnyVocabulary next) EXCLUDES(lifecycle_);
  Status BuildSwitch(PreparedSwitch& build, const AdaptOptions& options) EXCLUDES(lifecycle_);
  Result<VocabularyRecord> FinishSwitch(PreparedSwitch& build, VocabularyRecord record,
                                        const AdaptOptions& options,
                                        std::optional<uint64_t> at_sequence) EXCLUDES(lifecycle_);
  // At most `limit` places the live index and the new one differ by, into the new one and
  // `batch` (its family's changes); `changed` says how many.
  Status CatchUp(PreparedSwitch& build, rocksdb::WriteBatch* batch, size_t limit, size_t* changed)
      REQUIRES_SHARED(lifecycle_);
  // The vocabulary `checksum` from the bytes the map stores, or its `parts` parts; CORRUPTION
  // (prefixed by `what`) when missing or not that vocabulary.
  Result<AnyVocabulary> StoredVocabularyFor(uint64_t checksum, uint32_t parts,
                                            const std::string& what) const EXCLUDES(lifecycle_);
  // ApplyBatch's parts: a run of records without a switch (lifecycle_ held shared), and a
  // kSwitchVocabulary record (its own holds).
  Result<size_t> ApplyRun(std::span<const SequencedRecord> records) REQUIRES(apply_mutex_)
      EXCLUDES(lifecycle_);
  Status ApplySwitch(uint64_t sequence, const MapLogRecord& record) REQUIRES(apply_mutex_)
      EXCLUDES(lifecycle_);

  // A place's values as Enqueue encodes them on the caller's thread, and their entries in a
  // batch (record, BoW value, features, statistics, thumbnail) once its id is known.
  struct PlaceEntries {
    std::string features, bow, dynamics, thumbnail;
  };
  PlaceEntries EncodeEntries(const ProcessedFrame& frame, const PlaceMetadata& metadata) const;
  void PutEntries(PlaceId id, const PlaceMetadata& metadata, const ProcessedFrame& frame,
                  const PlaceEntries& entries, rocksdb::WriteBatch* batch) const;

  // The commit queue (Enqueue): places encoded, ids reserved, waiting for the next group.
  struct QueuedPlace;
  struct CommitQueue;
  void RunCommitter();  // the committer thread: one group at a time until stopped
  void CommitGroup(std::vector<QueuedPlace>* group, rocksdb::WriteBatch* batch)
      EXCLUDES(lifecycle_);
  void StopCommitter();  // commits what is queued, then joins the thread

  MapInfo info_;
  std::vector<MapDamage> damage_history_;
  std::string open_note_;
  OpenTimings open_timings_;
  std::string path_;
  std::unique_ptr<detail::MapStorage> storage_;
  // The vocabulary, the serving index and info_'s vocabulary fields are replaced only by a
  // switch of vocabulary, holding lifecycle_ exclusively and state_mutex_: code under a
  // lifecycle_ hold reads them directly, other code through the accessors (state_mutex_).
  mutable Mutex state_mutex_;
  AnyVocabulary vocabulary_;
  std::shared_ptr<PlaceDatabase> database_;
  std::atomic<bool> switching_{false};  // one AdaptVocabulary/RevertVocabulary at a time
  // Operations hold it shared; DeleteMap takes it exclusively, so in-flight work ends before
  // the database closes and later calls see `closed_`.
  mutable SharedMutex lifecycle_;
  bool closed_ GUARDED_BY(lifecycle_) = false;
  std::unique_ptr<CommitQueue> commits_;  // its committer thread lives as long as the map
  std::unique_ptr<LoopLog> loops_;        // set by Load(); closed (waiters woken) with the map
  // ApplyAt/ApplyBatch: one caller at a time; the applied sequence is readable without it.
  Mutex apply_mutex_;
  // A replica's switch prepared ahead of its record (PrepareVocabularySwitch); held while one
  // is built, so ApplySwitch waits for a preparation in progress. After apply_mutex_.
  Mutex prepare_mutex_;
  PreparedSwitchPtr prepared_ GUARDED_BY(prepare_mutex_);
  std::atomic<uint64_t> prepared_checksum_{0};
  std::atomic<bool> prepare_cancel_{false};
  std::atomic<uint64_t> applied_sequence_{0};
};

// RESOURCE_EXHAUSTED ("disk full", naming `what`) unless the file system holding `path` has
// `bytes` free beyond `reserve_bytes` (StorageOptions::disk_reserve_bytes); OK when its free space
// cannot be read.
Status CheckRoomFor(const std::string& path, uint64_t bytes, uint64_t reserve_bytes,
                    const std::string& what);

class DataDirectory {
 public:
  // Creates the directory when missing. A non-empty directory without placedb's marker file,
  // or with a damaged one, is refused (FAILED_PRECONDITION / CORRUPTION), never touched. The
  // directory stays locked (DirectoryLock) while the DataDirectory lives: a second Open() of
  // it, from any process, is FAILED_PRECONDITION naming the holder's pid.
  static Result<std::unique_ptr<DataDirectory>> Open(const std::string& path,
                                                     StorageOptions options = {});
  ~DataDirectory();

  const std::string& path() const { return path_; }
  const StorageOptions& options() const { return options_; }

  // Every method below that takes a map name refuses an invalid one (ValidateMapName,
  // core/base/map_name.h) with INVALID_ARGUMENT before touching the disk.
  Result<std::shared_ptr<PlaceMap>> CreateMap(const std::string& name, const MapOptions& options,
                                              AnyVocabulary vocabulary);
  // Reads a map's stored info without opening it for writing (e.g. to pick its vocabulary).
  // Changes nothing on disk. CORRUPTION naming the file when the map is damaged (a file where
  // the map's directory should be, CURRENT or MANIFEST missing or unreadable, the info record
  // lost).
  Result<MapInfo> ReadMapInfo(const std::string& name) const;
  // Opens (or returns the already open) map; FAILED_PRECONDITION if `vocabulary` is not the
  // one the map was built with. CORRUPTION when the map is damaged: RocksDB cannot read a file
  // (even an unacknowledged torn tail is accepted only when no acknowledged write is missing),
  // acknowledged writes are missing, ACKED is missing or unreadable, or a block the index
  // needs is corrupt. The reason names the file; `damage` (optional) receives it with the
  // counts when they could be established. A damaged map is not opened for writing; the files
  // are left as they are, except that a successful read-write open of a map whose WAL lost its
  // tail has already replayed what was left.
  // A map that stores its own vocabulary (issue 29) opens with it whatever `vocabulary` is (it
  // may be empty). A stored vocabulary that is damaged is CORRUPTION (the map is damaged).
  Result<std::shared_ptr<PlaceMap>> OpenMap(const std::string& name, AnyVocabulary vocabulary,
                                            MapDamage* damage = nullptr);
  // The operator's explicit choice to accept a damaged map's losses: reopens it with
  // point-in-time recovery (RocksDB's RepairDB when its MANIFEST or CURRENT is unusable),
  // counts the acknowledged writes lost against ACKED, records that in the map's damage history
  // (persisted) and opens it. `accepted` receives the loss (zero counts when nothing was lost).
  // FAILED_PRECONDITION when the map is open (it is not damaged) or cannot be recovered this way
  // (a corrupt SST block, a lost info record: restore a checkpoint; a file in place of the map's
  // directory); on failure the map stays damaged and its history unchanged (RepairDB may have
  // rebuilt the MANIFEST). A map that opens normally after all is returned, nothing recorded.
  // `vocabulary_for` picks the map's vocabulary from its stored info (which may be unreadable
  // until the recovery has run).
  using VocabularyFor = std::function<Result<AnyVocabulary>(const MapInfo&)>;
  Result<std::shared_ptr<PlaceMap>> RecoverMap(const std::string& name,
                                               const VocabularyFor& vocabulary_for,
                                               MapDamage* accepted = nullptr);
  // Sorted. Every valid map name under maps/, also a file where a map's directory should be
  // (so damage is listed, not hidden).
  std::vector<std::string> ListMaps() const;
  // Also a damaged map, and a file in place of a map's directory.
  Status DeleteMap(const std::string& name);
  // A checkpoint made by PlaceMap::Checkpoint in as map `name` (which must not exist): its SST
  // files are hard-linked (RocksDB never changes an SST; the map's compactions unlink its own
  // names only, so the checkpoint stays whole), copied when the link fails (another file system:
  // EXDEV, or EPERM); every other file is copied. On failure nothing is left under maps/.
  Status RestoreMap(const std::string& name, const std::string& checkpoint_directory);
  // Closes a map (it stays on disk); holders of the shared_ptr keep it until they let go.
  void CloseMap(const std::string& name);

 private:
  DataDirectory(std::string path, StorageOptions options, DirectoryLock lock);
  std::string MapPath(const std::string& name) const;
  // OpenMap without the lookup; fills damage->reason when the map is damaged.
  Result<std::shared_ptr<PlaceMap>> OpenLocked(const std::string& name,
                                               const VocabularyFor& vocabulary_for,
                                               MapDamage* damage) REQUIRES(mutex_);
  // "maps/<name>/..." for messages: no absolute paths.
  std::string Relative(const std::string& text) const;

  const std::string path_;
  const StorageOptions options_;
  const DirectoryLock lock_;
  std::shared_ptr<void> block_cache_;  // rocksdb::Cache, shared by every map
  // Taken before a map's lifecycle lock (DeleteMap closes the map under both).
  mutable Mutex mutex_;
  std::unordered_map<std::string, std::shared_ptr<PlaceMap>> open_ GUARDED_BY(mutex_);
};

}  // namespace placedb
