// Issue 35, compaction: a map's stream stays bounded. Run by the worker whose coordinator leads
// (docs/cluster.md "Compaction"): that is one process at a time, and the one that has everything
// a compaction needs already (the shards' internal API for a checkpoint, the verification
// CreateSnapshot does, the cluster's archives, JetStream, the placement and applied reports in
// its view). A coordinator deposed meanwhile cannot store a base: the base's etcd write compares
// the coordinator key's value with this worker's id (as the placement writes do) and bases/<map>'s
// mod revision as read; the purge follows only a base known durable, never beyond it.
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>

#include "core/base/text.h"
#include "proto/status.h"
#include "server/cluster/worker.h"

namespace placedb::server {

namespace {

using SteadyClock = std::chrono::steady_clock;

constexpr auto kCompactPeriod = std::chrono::seconds(1);
constexpr auto kCompactRetry = std::chrono::seconds(10);
constexpr auto kCompactTime = std::chrono::minutes(30);

}  // namespace

void ClusterWorker::NoteStreamEnd(const std::string& map, uint64_t last_sequence) {
  const auto now = SteadyClock::now();
  const auto keep = std::chrono::seconds(cluster_.compact_keep_s);
  MutexLock lock(history_mutex_);
  auto& samples = stream_history_[map];
  samples.emplace_back(now, last_sequence);
  // Older samples go, but the newest one older than `keep` stays (the purge's limit).
  while (samples.size() > 1 && samples[1].first <= now - keep) samples.pop_front();
}

uint64_t ClusterWorker::StoredBefore(const std::string& map, SteadyClock::time_point when) {
  MutexLock lock(history_mutex_);
  uint64_t out = 0;
  auto it = stream_history_.find(map);
  if (it == stream_history_.end()) return 0;
  for (const auto& [at, last] : it->second) {
    if (at <= when) out = std::max(out, last);
  }
  return out;
}

uint64_t ClusterWorker::PurgeBelow(const cluster::MapView& view, uint64_t base) const {
  if (base == 0 || !view.placement) return 0;
  // A live replica without a report yet is restoring (from this base or a newer peer
  // checkpoint: it needs nothing below the purge point); one that is down restores the base
  // when it returns (its applier finds the gap).
  const std::map<std::string, std::string> live = view_->Shards();
  uint64_t low = base;
  for (const std::string& shard : view.placement->replicas) {
    if (!live.count(shard)) continue;
    if (auto applied = view.applied.find(shard); applied != view.applied.end()) {
      low = std::min(low, applied->second);
    }
  }
  return low + 1;
}

Result<ClusterWorker::Compaction> ClusterWorker::CompactMap(const std::string& map,
                                                            bool take_base) {
  {
    MutexLock lock(compact_mutex_);
    if (compacting_) {
      return Status::FailedPrecondition("a compaction runs through this worker already");
    }
    compacting_ = true;
  }
  struct Done {
    ClusterWorker* self;
    ~Done() {
      MutexLock lock(self->compact_mutex_);
      self->compacting_ = false;
    }
  } done{this};
  if (!coordinating()) {
    return Status::FailedPrecondition(
        "this worker does not coordinate: compaction is the coordinator's");
  }
  auto view = Lookup(map, "map");
  if (!view.ok()) return view.status();
  auto stream = jetstream_->GetStreamInfo(view->info.stream);
  if (!stream.ok()) return stream.status().WithContext("compacting map '" + map + "'");
  NoteStreamEnd(map, stream->last_sequence);
  auto held = archives_->GetBase(map);
  if (!held.ok()) return held.status();
  // A base of an earlier map of the name (its DeleteMap failed to remove it) is replaced.
  const bool current = held->has_value() && (**held).create_revision == view->create_revision;
  Compaction out;
  out.base = current ? (**held).manifest.base : 0;
  out.first_sequence = stream->first_sequence;
  const auto started = SteadyClock::now();
  const Deadline deadline = std::chrono::system_clock::now() + kCompactTime;

  if (take_base && stream->last_sequence > out.base) {
    std::shared_ptr<SnapshotStore> store;
    if (grpc::Status kept = Snapshots(&store); !kept.ok()) return wire::FromGrpc(kept);
    ScratchFile spool(store->path(), "compaction");
    cluster::MapBase next;
    next.create_revision = view->create_revision;
    if (grpc::Status taken = TakeCheckpoint(map, *view, spool.path, deadline, &next.manifest);
        !taken.ok()) {
      return wire::FromGrpc(taken, "compacting map '" + map + "': the checkpoint");
    }
    if (next.manifest.base > out.base) {
      const cluster::ClusterKeys& keys = view_->keys();
      std::vector<cluster::Compare> guards = {
          cluster::Compare::ValueIs(keys.Coordinator(), id_),
          cluster::Compare{keys.Map(map),
                           cluster::Compare::Target::kCreateRevision,
                           cluster::Compare::Op::kEqual,
                           view->create_revision,
                           {}}};
      PLACEDB_RETURN_IF_ERROR(archives_->PutBase(map, spool.path, &next,
                                                 held->has_value() ? (**held).mod_revision : 0,
                                                 std::move(guards), deadline));
      out.new_base = true;
      out.base = next.manifest.base;
      spdlog::info(
          "compaction of map '{}': new base at record {} ({} places, {} bytes) in {:.2f} s",
          ForLog(map), out.base, next.manifest.info.places, next.manifest.archive_bytes,
          std::chrono::duration<double>(SteadyClock::now() - started).count());
    }
  }
  // The purge, below a durable base only, and never below what a live replica has not applied
  // (the view's applied reports: at most the replicas' own, never ahead of them).
  if (auto now = view_->Map(map); now && now->create_revision == view->create_revision) {
    // Records younger than compact_keep_s stay: a resent frame's duplicate PubAck names one.
    const uint64_t old_enough =
        cluster_.compact_keep_s == 0
            ? stream->last_sequence
            : StoredBefore(map, SteadyClock::now() - std::chrono::seconds(cluster_.compact_keep_s));
    const uint64_t below = std::min(PurgeBelow(*now, out.base), old_enough + 1);
    if (below > stream->first_sequence) {
      PLACEDB_RETURN_IF_ERROR(jetstream_->PurgeStream(view->info.stream, "", below)
                                  .WithContext("compacting map '" + map + "'"));
      out.first_sequence = below;
      spdlog::info("compaction of map '{}': stream purged below record {} (base {})", ForLog(map),
                   below, out.base);
    }
  }
  // The previous base goes once the new one is durable (a replica reading it meanwhile fails
  // its read and restores the new one at its next reconcile).
  if (out.new_base && held->has_value()) {
    if (Status deleted = archives_->DeleteChunks((**held).manifest); !deleted.ok()) {
      spdlog::warn("compaction of map '{}': the previous base's chunks stay: {}", ForLog(map),
                   deleted.ToString());
    }
  }
  return out;
}

void ClusterWorker::CompactLoop() {
  for (;;) {
    {
      MutexLock lock(compact_mutex_);
      const auto until = SteadyClock::now() + kCompactPeriod;
      while (!compact_stopping_ && SteadyClock::now() < until) {
        compact_cv_.WaitUntil(compact_mutex_, until);
      }
      if (compact_stopping_) return;
    }
    if (!coordinating()) continue;
    for (const auto& [name, view] : view_->Maps()) {
      {
        MutexLock lock(compact_mutex_);
        if (compact_stopping_) return;
      }
      auto stream = jetstream_->GetStreamInfo(view.info.stream);
      if (!stream.ok()) continue;
      auto held = archives_->GetBase(name);
      if (!held.ok()) continue;
      const uint64_t base = held->has_value() && (**held).create_revision == view.create_revision
                                ? (**held).manifest.base
                                : 0;
      NoteStreamEnd(name, stream->last_sequence);
      const prometheus::Labels labels = {{"map", name}};
      stream_bytes_->Add(labels).Set(double(stream->bytes));
      stream_records_->Add(labels).Set(double(stream->messages));
      base_sequence_->Add(labels).Set(double(base));
      // Beyond the base: the records after it, and their share of the stored bytes.
      const uint64_t records = stream->last_sequence > base ? stream->last_sequence - base : 0;
      const uint64_t bytes =
          stream->messages == 0
              ? 0
              : uint64_t(double(stream->bytes) * double(std::min(records, stream->messages)) /
                         double(stream->messages));
      const bool due =
          (cluster_.compact_after_records > 0 &&
           records > uint64_t(cluster_.compact_after_records)) ||
          (cluster_.compact_after_bytes > 0 && bytes > uint64_t(cluster_.compact_after_bytes));
      // A purge held back by a lagging replica is done once it caught up.
      const uint64_t old_enough =
          cluster_.compact_keep_s == 0
              ? stream->last_sequence
              : StoredBefore(name,
                             SteadyClock::now() - std::chrono::seconds(cluster_.compact_keep_s));
      const bool purgeable =
          std::min(PurgeBelow(view, base), old_enough + 1) > stream->first_sequence;
      if (!due && !purgeable) continue;
      if (auto retry = compact_retry_.find(name);
          retry != compact_retry_.end() && SteadyClock::now() < retry->second) {
        continue;
      }
      auto compacted = CompactMap(name, due);
      if (compacted.ok()) {
        compact_retry_.erase(name);
        if (compacted->new_base) compactions_->Add({}).Increment();
        base_sequence_->Add(labels).Set(double(compacted->base));
        if (auto after = jetstream_->GetStreamInfo(view.info.stream); after.ok()) {
          stream_bytes_->Add(labels).Set(double(after->bytes));
          stream_records_->Add(labels).Set(double(after->messages));
        }
      } else {
        compaction_failures_->Add({}).Increment();
        compact_retry_[name] = SteadyClock::now() + kCompactRetry;
        spdlog::warn("compaction of map '{}' failed (tried again in {} s): {}", ForLog(name),
                     std::chrono::duration_cast<std::chrono::seconds>(kCompactRetry).count(),
                     compacted.status().ToString());
      }
    }
  }
}

}  // namespace placedb::server
