// A PlaceMap's commit queue (PlaceMap::Enqueue; docs/storage.md, "Group commit"): the queued
// places and the queue its committer thread takes them from. INTERNAL to core/storage, not part
// of the public API: shared by place_map.cc (the map starts and stops the committer) and
// commit_queue.cc.
#pragma once

#include <rocksdb/write_batch.h>

#include <memory>
#include <thread>
#include <vector>

#include "core/base/thread_annotations.h"
#include "core/base/timing.h"
#include "core/storage/map_store.h"

namespace placedb {

// A place waiting in the commit queue: its entries are already in the queue's batch.
struct PlaceMap::QueuedPlace {
  ProcessedFrame frame;
  PlaceMetadata metadata;
  PlaceId id = 0;
  // The vocabulary generation its entries were encoded with: a switch of vocabulary between
  // Enqueue and the write has the committer encode them again (PlaceMap::CommitGroup).
  uint64_t generation = 0;
  std::shared_ptr<PendingCommit> pending;
  Stopwatch since_enqueued;
  std::vector<LoopConstraint> found;  // its loop constraints, written in the group's batch
};

struct PlaceMap::CommitQueue {
  Mutex mutex;
  CondVar wake;
  std::vector<QueuedPlace> queued GUARDED_BY(mutex);
  // The queued places' entries, in Enqueue() order: the next group's one atomic batch.
  rocksdb::WriteBatch batch GUARDED_BY(mutex);
  bool stopping GUARDED_BY(mutex) = false;
  // Started with the map, not by the first Enqueue(): a thread inherits its creator's nice value,
  // and the first Enqueue() may come from a lowered-priority ingest worker; the committer holds
  // the index's write lock while it inserts, so it keeps the normal priority.
  std::thread thread;
};

}  // namespace placedb
