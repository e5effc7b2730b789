// Acknowledging a map's writes. INTERNAL to core/storage (not part of the public API): the WAL
// group sync of SyncMode::kGroupCommit (GroupCommitter) and the ACKED file, the acknowledged
// high-water mark a map is compared with when it opens (AckState, AckTracker; docs/storage.md,
// "Damage").
#pragma once

#include <rocksdb/status.h>

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <thread>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "core/storage/map_store.h"

namespace rocksdb {
class DB;
}  // namespace rocksdb

namespace placedb::detail {

inline constexpr char kAckedFile[] = "ACKED";

// Acknowledges unsynced writes once a WAL sync that began after them has finished, so that
// concurrent writers share one fsync at most every `delay`.
class GroupCommitter {
 public:
  GroupCommitter(rocksdb::DB* db, std::chrono::milliseconds delay);
  ~GroupCommitter();

  rocksdb::Status WaitDurable();

 private:
  void Run();

  rocksdb::DB* db_;
  const std::chrono::milliseconds delay_;
  Mutex mutex_;
  CondVar wake_syncer_;
  CondVar synced_cv_;
  uint64_t requested_ GUARDED_BY(mutex_) = 0;
  uint64_t synced_ GUARDED_BY(mutex_) = 0;
  bool stopping_ GUARDED_BY(mutex_) = false;
  rocksdb::Status last_status_ GUARDED_BY(mutex_);
  std::thread thread_;
};

// ACKED: the acknowledged high-water mark, independent of RocksDB's files. Two 40-byte slots at
// offsets 0 and 512 (different sectors), written alternately with pwrite + fdatasync, so a torn
// write leaves the other slot intact; the valid slot with the higher generation wins.
// Slot: "PDBACK01", generation, acknowledged writes, highest acknowledged place id, FNV-1a 64 of
// the 32 bytes before it; integers little-endian.
struct AckState {
  uint64_t generation = 0;
  uint64_t writes = 0;
  uint64_t max_place = 0;
};

// NOT_FOUND when the file is missing; CORRUPTION when neither slot is valid.
Result<AckState> ReadAcked(const std::string& file);

// Creates (or replaces) ACKED holding `state` in both slots, durably.
Status CreateAcked(const std::string& map_path, AckState state);

// Records acknowledged writes in ACKED before they are acknowledged. Concurrent writers share
// one fdatasync: a writer that finds a sync in progress waits for the next one, which a leader
// among the waiters makes for all of them.
class AckTracker {
 public:
  static Result<std::unique_ptr<AckTracker>> Open(const std::string& map_path, AckState state);
  ~AckTracker();

  // Makes ACKED count at least `state` (writes a map recovered beyond its acknowledged ones).
  Status Raise(const AckState& state);

  // Returns once ACKED counts this write (`place`: its id, 0 for other writes; `writes`: how many
  // acknowledged writes it is, e.g. a group of places in one batch) durably.
  Status Acknowledge(PlaceId place, uint64_t writes = 1);

 private:
  AckTracker(int fd, AckState state) : fd_(fd), generation_(state.generation), pending_(state) {}

  const int fd_;
  Mutex mutex_;
  CondVar synced_cv_;
  uint64_t generation_ GUARDED_BY(mutex_);
  AckState pending_ GUARDED_BY(mutex_);  // everything acknowledged or being acknowledged
  uint64_t requested_ GUARDED_BY(mutex_) = 0;
  uint64_t durable_ GUARDED_BY(mutex_) = 0;
  bool syncing_ GUARDED_BY(mutex_) = false;
  Status last_status_ GUARDED_BY(mutex_);
};

}  // namespace placedb::detail
