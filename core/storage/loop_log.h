// A map's loop-closure log (issue 32): every loop constraint found while ingesting, durable and
// numbered, for a pose-graph back end that follows the map (WatchLoopClosures, `placedb loops
// export`).
//
// A constraint is one verified match of an ingested frame against a place stored before it: a
// match the frame's MatchOptions asked for (LoopSource::kMatch) or the loop its agent's Bayesian
// detector accepted (kLoopClosure; when both name the same place, one constraint of that
// source). It names both frames (the place the frame became, or was merged into by rehearsal, and
// the matched place, each with its agent, sequence, capture time and pose as sent) and carries
// the relative pose T_place_query with its information matrix when both sides have cameras
// (core/pose/relative_pose.h).
//
// Sequences are 1, 2, 3, ... in the order the constraints became durable; a reader that resumes
// from the sequence after the last one it saw misses none and sees none twice. A frame's
// constraints are written with its place in one atomic batch when the place goes through the
// commit queue, and in a batch of their own right after the place otherwise (loop-closure
// frames); either way before the frame is answered: an acknowledged frame's constraints are in
// the log. A crash between a loop-closure frame's place and its constraints loses them together
// with the frame's acknowledgement (the agent resends it). Constraints are history: removing a
// place later does not remove them.
//
// Stored in the map's "loops" column family, key = the sequence (8 bytes big-endian), value =
// JSON (EncodeLoopConstraint). Snapshots carry the family with the rest of the map.
//
// Thread safety: every method may be called concurrently. Write() serialises appends (numbering
// and writing under one mutex, so the order of sequences is the order of durability); Read() runs
// on RocksDB's own consistency and sees only published sequences.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "core/pipeline/place_database.h"
#include "core/pose/relative_pose.h"

namespace rocksdb {
class ColumnFamilyHandle;
class DB;
class WriteBatch;
}  // namespace rocksdb

namespace placedb {

enum class LoopSource : uint8_t {
  kMatch = 1,        // a verified match of the frame's MatchOptions
  kLoopClosure = 2,  // the loop the agent's Bayesian detector accepted (and verified)
};
const char* LoopSourceName(LoopSource source);  // "match", "loop_closure"

struct LoopConstraint {
  uint64_t sequence = 0;  // the log's (0 until written)
  LoopSource source = LoopSource::kMatch;
  PlaceId query_place = 0;  // the ingested frame's place (stored, or merged into)
  bool merged = false;      // the frame was merged into query_place by rehearsal
  PlaceMetadata query;      // the ingested frame's agent, sequence, capture time, pose
  PlaceId place = 0;        // the matched, earlier place
  PlaceMetadata place_metadata;
  double score = 0;  // the match's score; a detector's loop: its posterior
  int inliers = 0;
  std::optional<RelativePose> pose;  // T_place_query (inlier_indices are not kept)
  std::string pose_unavailable;      // why there is no pose
  int64_t found_unix_ns = 0;         // when the server found it (wall clock)

  bool inter_agent() const { return query.agent_id != place_metadata.agent_id; }
};

// What a reader wants; the default takes every constraint.
struct LoopFilter {
  // Empty: every agent; else only constraints with one of these agents on either side.
  std::vector<std::string> agents;
  bool inter_agent_only = false;
  // Constraints within one agent only when the two frames' sequences differ by at least this
  // (a frame matching its agent's previous frames is odometry, not a loop). 0: all.
  uint64_t min_sequence_gap = 0;
  bool Accepts(const LoopConstraint& constraint) const;
};

// An ingested frame's verified matches (`frame` its metadata) as constraints of source kMatch,
// found now; query_place is set when they are written.
std::vector<LoopConstraint> LoopConstraintsOf(const PlaceMetadata& frame,
                                              const std::vector<Match>& matches);

// A loop-closure frame's constraints: `found` (its verified matches) with the loop its agent's
// detector accepted (`outcome.loop`; it replaces a verified match of the same place; its
// place_metadata is left for the writer to fill), each marked merged when rehearsal merged the
// frame.
void AddDetectorLoop(const LoopClosureOutcome& outcome, const PlaceMetadata& frame,
                     std::vector<LoopConstraint>* found);

// The value stored for a constraint, and back (CORRUPTION naming the sequence when damaged).
std::string EncodeLoopConstraint(const LoopConstraint& constraint);
Result<LoopConstraint> DecodeLoopConstraint(uint64_t sequence, const std::string& value);

class LoopLog {
 public:
  // `family` null: a map opened read-only from before the log (no constraints, none written).
  // Reads the last sequence stored; CORRUPTION when a key is not a sequence.
  static Result<std::unique_ptr<LoopLog>> Open(rocksdb::DB* db,
                                               rocksdb::ColumnFamilyHandle* family);

  // Numbers `constraints` (sets their `sequence`), puts them into `batch` and calls `write`,
  // which writes the batch durably; the constraints are published (readable, waiters woken) only
  // when it succeeds. With no constraints, just `write`. A failed write publishes nothing;
  // numbering goes on after the last sequence the database holds (so replicas applying the same
  // records number them alike).
  Status Write(std::vector<LoopConstraint>* constraints, rocksdb::WriteBatch* batch,
               const std::function<Status()>& write) EXCLUDES(mutex_);

  // Up to `max` constraints the filter accepts, from sequence `from` on, in order. `*scanned`
  // receives the last sequence looked at (filtered-out ones included): resume from *scanned + 1.
  Result<std::vector<LoopConstraint>> Read(uint64_t from, size_t max, const LoopFilter& filter,
                                           uint64_t* scanned) const EXCLUDES(mutex_);

  uint64_t last_sequence() const EXCLUDES(mutex_);
  // Blocks until a constraint after `sequence` is published, `deadline` passes or the log is
  // closed; returns last_sequence().
  uint64_t WaitBeyond(uint64_t sequence, std::chrono::steady_clock::time_point deadline) const
      EXCLUDES(mutex_);
  // Wakes every waiter for good (the map is closing).
  void Close() EXCLUDES(mutex_);
  bool closed() const EXCLUDES(mutex_);

 private:
  LoopLog(rocksdb::DB* db, rocksdb::ColumnFamilyHandle* family, uint64_t last);

  rocksdb::DB* const db_;
  rocksdb::ColumnFamilyHandle* const family_;
  mutable Mutex mutex_;
  mutable CondVar published_cv_;
  uint64_t next_ GUARDED_BY(mutex_);       // the next sequence to hand out
  uint64_t published_ GUARDED_BY(mutex_);  // every sequence up to it is durable and readable
  bool closed_ GUARDED_BY(mutex_) = false;
};

}  // namespace placedb
