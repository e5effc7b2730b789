// The commit queue of a PlaceMap (commit_queue.h): PendingCommit, PlaceMap::Enqueue and the
// committer thread that writes each group of queued places in one synced batch, then indexes
// them and completes their commits.
#include "core/storage/commit_queue.h"

#include <rocksdb/write_batch.h>

#include <algorithm>
#include <utility>

#include "core/storage/map_storage.h"

namespace placedb {

// The storage internals (map_storage.h) and their helpers, unqualified as in the rest of the
// module.
using namespace detail;

const Result<AddResult>& PendingCommit::Wait() const {
  MutexLock lock(mutex_);
  while (!done_) done_cv_.Wait(mutex_);
  return outcome_;
}

bool PendingCommit::done() const {
  MutexLock lock(mutex_);
  return done_;
}

void PendingCommit::Complete(Result<AddResult> outcome) {
  {
    MutexLock lock(mutex_);
    outcome_ = std::move(outcome);
    done_ = true;
  }
  done_cv_.NotifyAll();
}

PlaceMap::PlaceEntries PlaceMap::EncodeEntries(const ProcessedFrame& frame,
                                               const PlaceMetadata& metadata) const {
  PlaceEntries entries;
  entries.features = EncodeLocalFeatures(frame.static_features, frame.direct, frame.geometry);
  entries.bow = storage_->BowValue(frame.bow, frame.direct);
  if (storage_->dynamics) entries.dynamics = EncodeDynamics(FrameDynamics(frame, metadata));
  if (frame.thumbnail && info_.options.thumbnails.enabled) {
    entries.thumbnail = EncodeThumbnail(*frame.thumbnail);
  }
  return entries;
}

void PlaceMap::PutEntries(PlaceId id, const PlaceMetadata& metadata, const ProcessedFrame& frame,
                          const PlaceEntries& entries, rocksdb::WriteBatch* batch) const {
  PlaceRecord record;
  record.id = id;
  record.metadata = metadata;
  record.counts = frame.counts;
  record.boxes_used = frame.boxes_used;
  const std::string key = PlaceKey(id);
  batch->Put(storage_->cf(kPlaces), key, EncodePlaceRecord(record));
  batch->Put(storage_->cf(kBow), key, entries.bow);
  batch->Put(storage_->cf(kFeatures), key, entries.features);
  if (storage_->dynamics) {
    batch->Merge(storage_->cf(kDynamics), key, entries.dynamics);
    batch->Merge(storage_->cf(kDynamics), kMapDynamicsKey, entries.dynamics);
  }
  if (!entries.thumbnail.empty()) batch->Put(storage_->cf(kThumbnails), key, entries.thumbnail);
}

std::shared_ptr<PendingCommit> PlaceMap::Enqueue(ProcessedFrame frame, PlaceMetadata metadata,
                                                 std::vector<LoopConstraint> found) {
  auto pending = std::make_shared<PendingCommit>();
  ReaderLock alive(lifecycle_);
  if (closed_) {
    pending->Complete(Deleted());
    return pending;
  }
  // Processed before a switch of vocabulary: transformed again with the map's.
  {
    std::optional<ProcessedFrame> copy;
    auto current = OfCurrentVocabulary(frame, &copy);
    if (!current.ok()) {
      pending->Complete(current.status());
      return pending;
    }
    if (copy) frame = std::move(*copy);
  }
  // What Commit() refuses or stores at once is answered at once, exactly as Commit() does.
  const DatabaseConfig& config = info_.options.database;
  if (frame.stream_pending || !frame.valid || frame.static_features.type() != config.feature_type ||
      frame.direct.levels_up != config.verification.levels_up) {
    pending->Complete(CommitLocked(frame, metadata, std::move(found)));
    return pending;
  }
  QueuedPlace place;
  place.found = std::move(found);
  place.pending = pending;
  place.generation = storage_->bow_generation.load();
  // Encoded here, on the caller's thread, so that callers encode in parallel; the committer
  // only writes.
  PlaceEntries entries = EncodeEntries(frame, metadata);
  CommitQueue& queue = *commits_;
  {
    MutexLock lock(queue.mutex);
    // Reserved under the queue's lock: ids follow the order of the places in the batch.
    place.id = database_->ReserveId();
    PutEntries(place.id, metadata, frame, entries, &queue.batch);
    place.frame = std::move(frame);
    place.metadata = std::move(metadata);
    queue.queued.push_back(std::move(place));
  }
  queue.wake.NotifyOne();
  return pending;
}

void PlaceMap::RunCommitter() {
  CommitQueue& queue = *commits_;
  std::vector<QueuedPlace> group;
  MutexLock lock(queue.mutex);
  while (true) {
    while (!queue.stopping && queue.queued.empty()) queue.wake.Wait(queue.mutex);
    if (queue.queued.empty()) return;  // stopping, and everything queued is committed
    // Everything queued so far is one group; what arrives meanwhile is the next one.
    group.clear();
    group.swap(queue.queued);
    rocksdb::WriteBatch batch;
    std::swap(batch, queue.batch);
    lock.Unlock();
    CommitGroup(&group, &batch);
    lock.Lock();
  }
}

void PlaceMap::CommitGroup(std::vector<QueuedPlace>* group, rocksdb::WriteBatch* batch) {
  ReaderLock alive(lifecycle_);
  Status written;
  if (closed_) {
    written = Deleted();
  } else {
    // Enqueued before a switch of vocabulary: their BoW values and family are the old
    // vocabulary's. The frames are transformed again and the group's batch made anew.
    const uint64_t generation = storage_->bow_generation.load();
    if (std::any_of(group->begin(), group->end(),
                    [&](const QueuedPlace& place) { return place.generation != generation; })) {
      rocksdb::WriteBatch again;
      for (QueuedPlace& place : *group) {
        std::optional<ProcessedFrame> copy;
        auto current = OfCurrentVocabulary(place.frame, &copy);
        if (!current.ok()) {
          written = current.status();
          break;
        }
        if (copy) place.frame = std::move(*copy);
        place.generation = generation;
        PutEntries(place.id, place.metadata, place.frame,
                   EncodeEntries(place.frame, place.metadata), &again);
      }
      std::swap(*batch, again);
    }
  }
  if (written.ok() && !closed_) {
    PlaceId highest = 0;
    for (const QueuedPlace& place : *group) highest = std::max(highest, place.id);
    const std::string what =
        group->size() == 1
            ? "storing place " + std::to_string(highest)
            : "storing " + std::to_string(group->size()) + " places (group commit, ids " +
                  std::to_string(group->front().id) + ".." + std::to_string(highest) + ")";
    // The places' loop constraints go in the same batch: logged if and only if stored.
    std::vector<LoopConstraint> found;
    for (QueuedPlace& place : *group) {
      for (LoopConstraint& constraint : place.found) {
        constraint.query_place = place.id;
        found.push_back(std::move(constraint));
      }
    }
    written = loops_->Write(&found, batch, [&] {
      return storage_->Write(batch, what, MapStorage::Kind::kAddition, highest, group->size());
    });
  }
  for (QueuedPlace& place : *group) {
    if (!written.ok()) {
      place.pending->Complete(written);
      continue;
    }
    // Durable: now make it searchable.
    auto id = database_->Insert(place.frame, place.metadata, place.id);
    if (!id.ok()) {
      place.pending->Complete(id.status());
      continue;
    }
    AddResult result;
    result.stored = true;
    result.id = *id;
    result.counts = place.frame.counts;
    result.boxes_used = std::move(place.frame.boxes_used);
    result.timings = place.frame.timings;
    result.depth_state = std::move(place.frame.depth_state);
    result.timings.store_ms = place.since_enqueued.ElapsedMs();
    result.timings.total_ms += result.timings.store_ms;
    place.pending->Complete(std::move(result));
  }
  group->clear();  // the frames' memory goes now, not with the next group
}

void PlaceMap::StopCommitter() {
  if (!commits_) return;
  {
    MutexLock lock(commits_->mutex);
    commits_->stopping = true;
  }
  commits_->wake.NotifyAll();
  if (commits_->thread.joinable()) commits_->thread.join();
}

}  // namespace placedb
