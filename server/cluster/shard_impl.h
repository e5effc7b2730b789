// Shard::Impl and the replicas it holds, shared by the shard's files: shard.cc (lifecycle, the
// maps' streams, applying, catch-up) and shard_reads.cc (the Shard RPCs workers read through:
// search, places, vocabularies, checkpoints). Private to server/cluster/.
#pragma once

#include <grpcpp/grpcpp.h>
#include <prometheus/gauge.h>

#include <atomic>
#include <deque>
#include <map>
#include <memory>
#include <string>
#include <thread>

#include "core/base/text.h"
#include "core/base/thread_annotations.h"
#include "core/storage/replica_apply.h"
#include "core/storage/snapshots.h"
#include "proto/cluster.grpc.pb.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/placement.h"
#include "server/cluster/shard.h"
#include "server/cluster/snapshot_archives.h"

namespace placedb::cluster {

namespace pv1 = ::placedb::v1;
namespace cv1 = ::placedb::cluster::v1;

// maps/<map>: {"config": <placedb.v1.MapConfig as proto JSON>, "stream": name, ...}.
struct MapMeta {
  pv1::MapConfig config;
  std::string stream;
  std::string snapshot;  // issue 35: restored from this cluster snapshot (its replicas start there)
};

inline grpc::Status GrpcError(grpc::StatusCode code, const std::string& message) {
  return grpc::Status(code, message);
}

// One map this shard holds.
struct Replica {
  std::string name;
  std::string stream;
  std::string subject;
  FeatureType type = FeatureType::kOrb;
  // Set once by the reconcile thread before the consumer starts; read-only afterwards. `map`
  // serves the reads (shard_reads.cc); the stream's records reach it through `apply` alone
  // (the same map), so applying cannot touch the rest of it.
  std::shared_ptr<PlaceMap> map;
  ReplicaApply* apply = nullptr;
  std::unique_ptr<OrderedConsumer> consumer;  // the reconcile thread's
  std::atomic<bool> broken{false};            // the applier stopped on an error
  // Issue 35 (compaction): the stream delivered a record above applied + 1 (the records between
  // were purged: it starts after the map's base). Nothing was skipped: the applier stopped, and
  // the next reconcile rebuilds the replica from the base (or a newer peer checkpoint).
  std::atomic<bool> gap{false};
  std::atomic<uint64_t> stream_last{0};
  // maps/<map>'s create revision this replica belongs to (Impl::mutex_ for writes after the map
  // is shared; the run thread sets it before opening).
  std::atomic<int64_t> create_revision{0};
  // Held while records are applied, and while a checkpoint for a new replica is taken (its
  // manifest's place count must be the checkpoint's).
  Mutex apply_mutex;
  // The consumer's delivery thread queues the records it receives; the applier thread applies
  // whatever has queued up meanwhile as one batch (ReplicaApply::ApplyBatch: one synced write), so
  // a replica behind the stream catches up in large steps and an idle one applies each record at
  // once. A full queue holds the delivery thread (JetStream's flow control does the rest).
  struct Queued {
    uint64_t sequence = 0;
    std::string data;
  };
  Mutex queue_mutex;
  CondVar queue_cv;  // a record queued, room made, or stopping
  std::deque<Queued> queue GUARDED_BY(queue_mutex);
  size_t queued_bytes GUARDED_BY(queue_mutex) = 0;
  bool stopping GUARDED_BY(queue_mutex) = false;
  std::thread applier;  // started with the first consumer, joined by StopApplier
  // Issue 29: builds a switch of vocabulary once its PrepareVocabulary is applied, while the
  // applier goes on (ReplicaApply::PrepareVocabularySwitch); one at a time, joined by StopApplier.
  std::thread preparing;
  std::atomic<bool> preparing_done{true};
  std::string problem;        // Impl::mutex_: why it is not applying ("" when it is)
  bool damaged = false;       // Impl::mutex_: not opened because its storage is damaged
  std::string restored_from;  // Impl::mutex_: the peer whose checkpoint it started from
};

class Shard::Impl {
 public:
  explicit Impl(ShardOptions options) : options_(std::move(options)) {}
  ~Impl() { Stop(); }

  Status Init();
  void Stop();

  // RPCs (ShardService).
  grpc::Status Search(grpc::ServerContext* context, const cv1::SearchRequest& request,
                      cv1::SearchResponse* response);
  grpc::Status FetchPlaces(grpc::ServerContext* context, const cv1::FetchPlacesRequest& request,
                           cv1::FetchPlacesResponse* response);
  grpc::Status ListAgentPlaces(grpc::ServerContext* context,
                               const cv1::ListAgentPlacesRequest& request,
                               cv1::ListAgentPlacesResponse* response);
  // Issue 29: a vocabulary learned from this replica's places; the map's record and vocabulary.
  grpc::Status LearnVocabulary(grpc::ServerContext* context,
                               const cv1::LearnVocabularyRequest& request,
                               grpc::ServerWriter<cv1::VocabularyChunk>* writer);
  grpc::Status GetVocabulary(grpc::ServerContext* context, const cv1::GetVocabularyRequest& request,
                             grpc::ServerWriter<cv1::VocabularyChunk>* writer);
  Result<std::shared_ptr<PlaceMap>> MapOf(const std::string& map) const EXCLUDES(mutex_);
  bool stopping() const EXCLUDES(mutex_) {
    MutexLock lock(mutex_);
    return stopping_;
  }
  grpc::Status Checkpoint(const cv1::CheckpointRequest& request,
                          grpc::ServerWriter<cv1::CheckpointChunk>* writer);
  std::vector<ReplicaStatus> StatusOfReplicas() const EXCLUDES(mutex_);
  // Admin (shard_admin.cc): this replica's scrub; the rebuild of a damaged replica.
  grpc::Status ScrubReplica(const cv1::ReplicaRequest& request, pv1::ScrubReport* response)
      EXCLUDES(mutex_);
  grpc::Status RecoverReplica(const cv1::RecoverReplicaRequest& request,
                              pv1::ReplicaRecovery* response) EXCLUDES(mutex_, lifecycle_mutex_);

  const ShardOptions options_;
  int port_ = 0;

 private:
  // Waits until `map` (held here as `m`) applied `min_sequence`: bounded by the call's deadline
  // (30 s without one); DEADLINE_EXCEEDED naming both sequences, UNAVAILABLE while stopping.
  grpc::Status AwaitApplied(grpc::ServerContext* context, const std::string& map, const PlaceMap& m,
                            uint64_t min_sequence) EXCLUDES(mutex_);
  // The replica of `map` held here (MapOf's errors), once it applied `min_sequence`
  // (AwaitApplied's): the start of every read that honours a minimum sequence.
  grpc::Status AppliedMap(grpc::ServerContext* context, const std::string& map,
                          uint64_t min_sequence, std::shared_ptr<PlaceMap>* out) EXCLUDES(mutex_);
  std::string Key(const std::string& suffix) const {
    return "/placedb/" + options_.cluster_name + "/" + suffix;
  }
  Status Register();
  void Run() EXCLUDES(mutex_, lifecycle_mutex_);
  void Reconcile() EXCLUDES(mutex_) REQUIRES(lifecycle_mutex_);
  void Report() EXCLUDES(mutex_);
  // Opens (or creates) the replica's map and starts its applier; records the problem otherwise.
  void Open(const std::shared_ptr<Replica>& replica, const MapMeta& meta) EXCLUDES(mutex_);
  void StartApplier(const std::shared_ptr<Replica>& replica) EXCLUDES(mutex_);
  // Catch-up of a new replica: restores the map from the checkpoint of the live replica that
  // applied the most (Checkpoint RPC, verified by SnapshotStore::Import); returns the peer's id.
  // NOT_FOUND when no live peer has applied more than `newer_than` (the map's base, when it has
  // one: restoring the base then costs no peer anything).
  Result<std::string> RestoreFromPeer(const std::string& map, int64_t create_revision,
                                      uint64_t newer_than) EXCLUDES(mutex_);
  // Issue 35: a cluster archive (a snapshot's, for a map restored from it with no peer to copy
  // yet; or the map's compaction base) read from the cluster (SnapshotArchives::Read, size and
  // SHA-256 checked) and imported as a peer's checkpoint is. `what` names it in the log.
  Status RestoreFromArchive(const std::string& map, const SnapshotManifest& manifest,
                            const std::string& what) EXCLUDES(mutex_);
  // The cluster's archives (snapshots, compaction bases), for reading: made where they are read.
  SnapshotArchives Archives() const {
    return SnapshotArchives(js_.get(), etcd_.get(), options_.cluster_name,
                            /*stream_replicas=*/0);  // reads only
  }
  // The archive spooled at `spool` verified (SnapshotStore::Import) and restored as `map`.
  Status ImportAsMap(const std::string& spool, const std::string& map);
  Result<AnyVocabulary> VocabularyFor(const MapInfo& info) const;
  // DATA_DIR/cluster-maps/<hex of the name>: the create revision of maps/<map> the local copy
  // was made for.
  std::string GenerationFile(const std::string& map) const {
    return dir_->path() + "/cluster-maps/" + HexOf(map);
  }
  void Drop(const std::string& name) EXCLUDES(mutex_);
  // The consumer's callback: queues the record (waits while the queue is full); drops it while
  // the replica is broken (it restarts from applied + 1).
  static void Enqueue(Replica* replica, uint64_t sequence, std::string_view data);
  // The replica's applier thread: applies queued records in batches until StopApplier.
  void ApplyQueued(Replica* replica) EXCLUDES(mutex_);
  // Stops and joins the applier thread (after the consumer is gone).
  static void StopApplier(Replica* replica);
  // Starts building the switch to vocabulary `checksum` from its `parts` (a PrepareVocabulary
  // record the applier just applied), unless a preparation is running: the switch record then
  // builds it.
  void PrepareSwitch(Replica* replica, uint64_t checksum, uint32_t parts);
  void SetProblem(Replica* replica, const std::string& problem) EXCLUDES(mutex_);

  std::unique_ptr<DataDirectory> dir_;
  std::unique_ptr<SnapshotStore> snapshots_;
  std::unique_ptr<JetStream> js_;
  std::unique_ptr<EtcdClient> etcd_;
  std::unique_ptr<LeaseKeeper> keeper_;  // the run thread's (and Init's)
  std::unique_ptr<Watcher> maps_watch_, placement_watch_;
  std::unique_ptr<grpc::Server> server_;
  std::unique_ptr<grpc::Service> service_;
  prometheus::Family<prometheus::Gauge>* applied_gauge_ = nullptr;
  prometheus::Family<prometheus::Gauge>* lag_gauge_ = nullptr;

  // Held while replicas are opened, restored or dropped: by the run thread's reconcile, and by
  // a recovery that rebuilds a replica (it must not race a reconcile opening the same map).
  // Taken before mutex_.
  Mutex lifecycle_mutex_;
  mutable Mutex mutex_;
  CondVar wake_;        // the run thread: a watch event, stop
  CondVar applied_cv_;  // Search: a record was applied
  bool stopping_ GUARDED_BY(mutex_) = false;
  bool dirty_ GUARDED_BY(mutex_) = true;
  bool watch_ended_ GUARDED_BY(mutex_) = false;
  std::map<std::string, std::shared_ptr<Replica>> replicas_ GUARDED_BY(mutex_);
  std::thread thread_;
};

}  // namespace placedb::cluster
