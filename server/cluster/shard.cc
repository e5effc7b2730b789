#include "server/cluster/shard.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <prometheus/gauge.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <set>
#include <thread>

#include "core/base/text.h"
#include "core/base/thread_annotations.h"
#include "core/base/timing.h"
#include "core/storage/codec.h"
#include "core/storage/snapshots.h"
#include "proto/cluster.grpc.pb.h"
#include "proto/convert_config.h"
#include "proto/convert_result.h"
#include "proto/status.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/map_record.h"
#include "server/cluster/placement.h"
#include "server/metrics.h"
#include "server/place_reads.h"

namespace placedb::cluster {

namespace {

namespace pv1 = ::placedb::v1;
namespace cv1 = ::placedb::cluster::v1;
using Clock = std::chrono::steady_clock;
using wire::ToGrpc;

// maps/<map>: {"config": <placedb.v1.MapConfig as proto JSON>, "stream": name, ...}.
struct MapMeta {
  pv1::MapConfig config;
  std::string stream;
};

Result<MapMeta> ParseMapMeta(const std::string& text) {
  auto json = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded() || !json.is_object() || !json.contains("stream") ||
      !json["stream"].is_string() || !json.contains("config")) {
    return Status::InvalidArgument("maps/ value is not {\"config\": ..., \"stream\": ...}");
  }
  MapMeta meta;
  meta.stream = json["stream"].get<std::string>();
  const std::string config =
      json["config"].is_string() ? json["config"].get<std::string>() : json["config"].dump();
  auto parsed = google::protobuf::util::JsonStringToMessage(config, &meta.config);
  if (!parsed.ok()) {
    return Status::InvalidArgument("maps/ value's config: " + std::string(parsed.message()));
  }
  return meta;
}

// placement/<map>: {"epoch": N, "replicas": ["shard-a", ...]}.
Result<std::vector<std::string>> ParseReplicas(const std::string& text) {
  auto json = nlohmann::json::parse(text, nullptr, false);
  if (json.is_discarded() || !json.is_object() || !json.contains("replicas") ||
      !json["replicas"].is_array()) {
    return Status::InvalidArgument("placement/ value is not {\"epoch\": N, \"replicas\": [...]}");
  }
  std::vector<std::string> out;
  for (const auto& replica : json["replicas"]) {
    if (replica.is_string()) out.push_back(replica.get<std::string>());
  }
  return out;
}

grpc::Status GrpcError(grpc::StatusCode code, const std::string& message) {
  return grpc::Status(code, message);
}

}  // namespace

// One map this shard holds.
struct Replica {
  std::string name;
  std::string stream;
  std::string subject;
  FeatureType type = FeatureType::kOrb;
  // Set once by the reconcile thread before the consumer starts; read-only afterwards.
  std::shared_ptr<PlaceMap> map;
  std::unique_ptr<OrderedConsumer> consumer;  // the reconcile thread's
  std::atomic<bool> broken{false};            // the applier stopped on an error
  std::atomic<uint64_t> stream_last{0};
  // maps/<map>'s create revision this replica belongs to (Impl::mutex_ for writes after the map
  // is shared; the run thread sets it before opening).
  std::atomic<int64_t> create_revision{0};
  // Held while records are applied, and while a checkpoint for a new replica is taken (its
  // manifest's place count must be the checkpoint's).
  Mutex apply_mutex;
  // The consumer's delivery thread queues the records it receives; the applier thread applies
  // whatever has queued up meanwhile as one batch (PlaceMap::ApplyBatch: one synced write), so a
  // replica behind the stream catches up in large steps and an idle one applies each record at
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
  // applier goes on (PlaceMap::PrepareVocabularySwitch); one at a time, joined by StopApplier.
  std::thread preparing;
  std::atomic<bool> preparing_done{true};
  std::string problem;        // Impl::mutex_: why it is not applying ("" when it is)
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
  grpc::Status Checkpoint(const cv1::CheckpointRequest& request,
                          grpc::ServerWriter<cv1::CheckpointChunk>* writer);
  std::vector<ReplicaStatus> StatusOfReplicas() const EXCLUDES(mutex_);

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
  void Run() EXCLUDES(mutex_);
  void Reconcile() EXCLUDES(mutex_);
  void Report() EXCLUDES(mutex_);
  // Opens (or creates) the replica's map and starts its applier; records the problem otherwise.
  void Open(const std::shared_ptr<Replica>& replica, const MapMeta& meta) EXCLUDES(mutex_);
  void StartApplier(const std::shared_ptr<Replica>& replica) EXCLUDES(mutex_);
  // Catch-up of a new replica: restores the map from the checkpoint of the live replica that
  // applied the most (Checkpoint RPC, verified by SnapshotStore::Import); returns the peer's id.
  // NOT_FOUND when no live peer has applied anything.
  Result<std::string> RestoreFromPeer(const std::string& map, int64_t create_revision)
      EXCLUDES(mutex_);
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

  mutable Mutex mutex_;
  CondVar wake_;        // the run thread: a watch event, stop
  CondVar applied_cv_;  // Search: a record was applied
  bool stopping_ GUARDED_BY(mutex_) = false;
  bool dirty_ GUARDED_BY(mutex_) = true;
  bool watch_ended_ GUARDED_BY(mutex_) = false;
  std::map<std::string, std::shared_ptr<Replica>> replicas_ GUARDED_BY(mutex_);
  std::thread thread_;
};

namespace {

class ShardService final : public cv1::Shard::Service {
 public:
  ShardService(Shard::Impl* impl, std::string shard_id)
      : impl_(impl), shard_id_(std::move(shard_id)) {}

  grpc::Status Search(grpc::ServerContext* context, const cv1::SearchRequest* request,
                      cv1::SearchResponse* response) override {
    return impl_->Search(context, *request, response);
  }
  grpc::Status GetPlace(grpc::ServerContext*, const pv1::GetPlaceRequest* request,
                        pv1::Place* response) override {
    auto map = impl_->MapOf(request->map());
    if (!map.ok()) return ToGrpc(map.status());
    return ToGrpc(server::ReadPlace(**map, *request, response));
  }
  grpc::Status ListPlaces(grpc::ServerContext*, const pv1::ListPlacesRequest* request,
                          pv1::ListPlacesResponse* response) override {
    auto map = impl_->MapOf(request->map());
    if (!map.ok()) return ToGrpc(map.status());
    return ToGrpc(server::ListPlacesOf(**map, *request, response));
  }
  grpc::Status GetDynamics(grpc::ServerContext*, const pv1::GetDynamicsRequest* request,
                           pv1::GetDynamicsResponse* response) override {
    auto map = impl_->MapOf(request->map());
    if (!map.ok()) return ToGrpc(map.status());
    return ToGrpc(server::ReadDynamics(**map, *request, response));
  }
  grpc::Status Status(grpc::ServerContext*, const cv1::StatusRequest*,
                      cv1::StatusResponse* response) override {
    response->set_shard_id(shard_id_);
    for (const ReplicaStatus& replica : impl_->StatusOfReplicas()) {
      cv1::MapStatus* out = response->add_maps();
      out->set_map(replica.map);
      out->set_applied_sequence(replica.applied_sequence);
      out->set_stream_last_sequence(replica.stream_last_sequence);
      out->set_places(replica.places);
      out->set_state(replica.state);
      out->set_prepared_vocabulary(replica.prepared_vocabulary);
    }
    return grpc::Status::OK;
  }
  grpc::Status Checkpoint(grpc::ServerContext*, const cv1::CheckpointRequest* request,
                          grpc::ServerWriter<cv1::CheckpointChunk>* writer) override {
    return impl_->Checkpoint(*request, writer);
  }
  grpc::Status FetchPlaces(grpc::ServerContext* context, const cv1::FetchPlacesRequest* request,
                           cv1::FetchPlacesResponse* response) override {
    return impl_->FetchPlaces(context, *request, response);
  }
  grpc::Status ListAgentPlaces(grpc::ServerContext* context,
                               const cv1::ListAgentPlacesRequest* request,
                               cv1::ListAgentPlacesResponse* response) override {
    return impl_->ListAgentPlaces(context, *request, response);
  }
  grpc::Status LearnVocabulary(grpc::ServerContext* context,
                               const cv1::LearnVocabularyRequest* request,
                               grpc::ServerWriter<cv1::VocabularyChunk>* writer) override {
    return impl_->LearnVocabulary(context, *request, writer);
  }
  grpc::Status GetVocabulary(grpc::ServerContext* context, const cv1::GetVocabularyRequest* request,
                             grpc::ServerWriter<cv1::VocabularyChunk>* writer) override {
    return impl_->GetVocabulary(context, *request, writer);
  }

 private:
  Shard::Impl* const impl_;
  const std::string shard_id_;
};

}  // namespace

Status Shard::Impl::Init() {
  const ShardOptions& o = options_;
  if (o.shard_id.empty()) return Status::InvalidArgument("cluster.shard_id: is required");
  if (o.nats.empty()) return Status::InvalidArgument("cluster.nats: is required");
  if (o.etcd.empty()) return Status::InvalidArgument("cluster.etcd: is required");
  if (o.data_dir.empty()) return Status::InvalidArgument("data_dir: is required");
  if (!o.vocabularies.count("default")) {
    return Status::InvalidArgument("vocabularies: \"default\" is required");
  }
  auto dir = DataDirectory::Open(o.data_dir, o.storage);
  if (!dir.ok()) return dir.status();
  dir_ = std::move(dir).value();
  auto snapshots = SnapshotStore::Open(dir_.get());
  if (!snapshots.ok()) return snapshots.status();
  snapshots_ = std::move(snapshots).value();
  JetStreamOptions js;
  js.servers = o.nats;
  js.client_name = "placedb-shard-" + o.shard_id;
  auto connected = JetStream::Connect(js);
  if (!connected.ok()) return connected.status();
  js_ = std::move(connected).value();
  EtcdOptions etcd;
  etcd.endpoints = o.etcd;
  auto client = EtcdClient::Create(etcd);
  if (!client.ok()) return client.status();
  etcd_ = std::move(client).value();

  if (o.metrics) {
    applied_gauge_ = &prometheus::BuildGauge()
                          .Name("placedb_shard_applied_sequence")
                          .Help("The last stream sequence a map's replica on this shard applied")
                          .Register(*o.metrics->registry());
    lag_gauge_ = &prometheus::BuildGauge()
                      .Name("placedb_shard_lag_records")
                      .Help("Records of a map's stream its replica has not applied yet")
                      .Register(*o.metrics->registry());
  }

  service_ = std::make_unique<ShardService>(this, o.shard_id);
  grpc::ServerBuilder builder;
  builder.AddListeningPort(o.internal_listen, grpc::InsecureServerCredentials(), &port_);
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);  // a port in use is an error (server.cc)
  builder.RegisterService(service_.get());
  builder.SetMaxReceiveMessageSize(64 << 20);
  builder.SetMaxSendMessageSize(64 << 20);
  server_ = builder.BuildAndStart();
  if (!server_ || port_ == 0) {
    return Status::IoError("cluster.internal_listen " + o.internal_listen + ": cannot listen");
  }

  PLACEDB_RETURN_IF_ERROR(Register());
  // Watches only wake the reconcile, which reads the keys itself: nothing is lost when a watch
  // ends (it is restarted) or events are coalesced.
  auto now = etcd_->Get(Key("maps/"), true);
  if (!now.ok()) return now.status();
  const auto wake = [this](const std::vector<WatchEvent>&) {
    MutexLock lock(mutex_);
    dirty_ = true;
    wake_.NotifyAll();
  };
  const auto ended = [this](const Status& why) {
    spdlog::warn("shard {}: etcd watch ended: {}", options_.shard_id, why.ToString());
    MutexLock lock(mutex_);
    watch_ended_ = true;
    dirty_ = true;
    wake_.NotifyAll();
  };
  maps_watch_ = etcd_->Watch(Key("maps/"), now->revision + 1, wake, ended);
  placement_watch_ = etcd_->Watch(Key("placement/"), now->revision + 1, wake, ended);
  thread_ = std::thread([this] { Run(); });
  return Status::Ok();
}

Status Shard::Impl::Register() {
  auto lease = etcd_->GrantLease(options_.lease_ttl_s);
  if (!lease.ok()) return lease.status().WithContext("registering shard " + options_.shard_id);
  const std::string address =
      options_.advertise.empty()
          ? options_.internal_listen.substr(0, options_.internal_listen.rfind(':')) + ":" +
                std::to_string(port_)
          : options_.advertise;
  nlohmann::json value = {{"address", address}};
  auto put = etcd_->Put(Key("shards/" + options_.shard_id), value.dump(), lease->id);
  if (!put.ok()) return put.status().WithContext("registering shard " + options_.shard_id);
  keeper_ = etcd_->KeepAlive(*lease, [this](const placedb::Status& why) {
    spdlog::warn("shard {}: lease lost ({}); registering again", options_.shard_id, why.ToString());
    MutexLock lock(mutex_);
    wake_.NotifyAll();
  });
  return Status::Ok();
}

void Shard::Impl::Stop() {
  {
    MutexLock lock(mutex_);
    if (stopping_) return;
    stopping_ = true;
    wake_.NotifyAll();
    applied_cv_.NotifyAll();
  }
  if (server_) server_->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
  if (thread_.joinable()) thread_.join();
  if (maps_watch_) maps_watch_->Stop();
  if (placement_watch_) placement_watch_->Stop();
  if (keeper_) keeper_->Stop();
  std::map<std::string, std::shared_ptr<Replica>> replicas;
  {
    MutexLock lock(mutex_);
    replicas.swap(replicas_);
  }
  // Consumers first (their callbacks feed the appliers), then the appliers, then the maps.
  for (auto& [name, replica] : replicas) {
    replica->consumer.reset();
    StopApplier(replica.get());
  }
  replicas.clear();
  if (server_) server_->Wait();
  snapshots_.reset();
  dir_.reset();
}

void Shard::Impl::Run() {
  auto last_report = Clock::now() - options_.report_interval;
  for (;;) {
    {
      MutexLock lock(mutex_);
      if (stopping_) return;
      if (watch_ended_) {
        watch_ended_ = false;
        lock.Unlock();
        // Restarted from now: the reconcile below reads the current keys anyway.
        auto now = etcd_->Get(Key("maps/"), true);
        if (now.ok()) {
          const auto wake = [this](const std::vector<WatchEvent>&) {
            MutexLock inner(mutex_);
            dirty_ = true;
            wake_.NotifyAll();
          };
          const auto ended = [this](const Status&) {
            MutexLock inner(mutex_);
            watch_ended_ = true;
            wake_.NotifyAll();
          };
          maps_watch_ = etcd_->Watch(Key("maps/"), now->revision + 1, wake, ended);
          placement_watch_ = etcd_->Watch(Key("placement/"), now->revision + 1, wake, ended);
        } else {
          MutexLock relock(mutex_);
          watch_ended_ = true;  // etcd unreachable: try again next round
        }
        lock.Lock();
      }
      dirty_ = false;
    }
    if (keeper_ && keeper_->lost()) {
      keeper_->Stop();
      keeper_.reset();
    }
    if (!keeper_) {
      if (Status registered = Register(); !registered.ok()) {
        spdlog::warn("shard {}: {}", options_.shard_id, registered.ToString());
      }
    }
    Reconcile();
    if (Clock::now() - last_report >= options_.report_interval) {
      Report();
      last_report = Clock::now();
    }
    MutexLock lock(mutex_);
    const auto until =
        Clock::now() + std::min(options_.reconcile_interval, options_.report_interval);
    while (!stopping_ && !dirty_ && !(keeper_ && keeper_->lost()) && Clock::now() < until) {
      wake_.WaitUntil(mutex_, until);
    }
  }
}

void Shard::Impl::Reconcile() {
  auto maps = etcd_->Get(Key("maps/"), true);
  auto placements = etcd_->Get(Key("placement/"), true);
  // etcd unreachable: keep applying and serving what is held (the placement is frozen).
  if (!maps.ok() || !placements.ok()) return;
  std::map<std::string, std::string> map_values;
  std::map<std::string, int64_t> map_revisions;  // create revisions: a map's generation
  const std::string maps_prefix = Key("maps/");
  for (const KeyValue& kv : maps->kvs) {
    map_values[kv.key.substr(maps_prefix.size())] = kv.value;
    map_revisions[kv.key.substr(maps_prefix.size())] = kv.create_revision;
  }
  std::set<std::string> mine;
  const std::string placement_prefix = Key("placement/");
  for (const KeyValue& kv : placements->kvs) {
    auto replicas = ParseReplicas(kv.value);
    if (!replicas.ok()) continue;
    if (std::find(replicas->begin(), replicas->end(), options_.shard_id) != replicas->end()) {
      mine.insert(kv.key.substr(placement_prefix.size()));
    }
  }
  std::vector<std::string> drop;
  {
    MutexLock lock(mutex_);
    for (const auto& [name, replica] : replicas_) {
      // Also a replica of a map deleted and re-created under its name (another stream).
      if (!mine.count(name) || !map_values.count(name) ||
          (replica->create_revision != 0 && replica->create_revision != map_revisions[name])) {
        drop.push_back(name);
      }
    }
  }
  for (const std::string& name : drop) Drop(name);
  for (const std::string& name : mine) {
    auto value = map_values.find(name);
    if (value == map_values.end()) continue;  // placed before maps/<map> is visible
    std::shared_ptr<Replica> replica;
    {
      MutexLock lock(mutex_);
      auto& slot = replicas_[name];
      if (!slot) {
        slot = std::make_shared<Replica>();
        slot->name = name;
        slot->subject = StreamSubject(options_.cluster_name, name);
      }
      replica = slot;
    }
    if (!replica->map) {
      auto meta = ParseMapMeta(value->second);
      if (!meta.ok()) {
        SetProblem(replica.get(), "unavailable: " + meta.status().ToString());
        continue;
      }
      replica->create_revision = map_revisions[name];
      Open(replica, *meta);
    } else if (replica->broken || !replica->consumer) {
      StartApplier(replica);
    }
  }
}

void Shard::Impl::Open(const std::shared_ptr<Replica>& replica, const MapMeta& meta) {
  const std::string vocabulary_name =
      meta.config.vocabulary().empty() ? "default" : meta.config.vocabulary();
  auto vocabulary = options_.vocabularies.find(vocabulary_name);
  if (vocabulary == options_.vocabularies.end()) {
    SetProblem(replica.get(),
               "unavailable: vocabulary '" + vocabulary_name + "' is not configured here");
    return;
  }
  // The local copy's generation (written when it was made): a copy of a map deleted and
  // re-created meanwhile (the shard was down) is deleted, not resumed on the new stream.
  const std::string generation_file = GenerationFile(replica->name);
  const int64_t revision = replica->create_revision;
  {
    std::ifstream in(generation_file);
    int64_t stored = 0;
    if (in >> stored && stored != revision) {
      spdlog::info("shard {}: map '{}' was re-created: deleting the local copy", options_.shard_id,
                   replica->name);
      if (Status deleted = dir_->DeleteMap(replica->name);
          !deleted.ok() && deleted.code() != StatusCode::kNotFound) {
        SetProblem(replica.get(), "unavailable: " + deleted.ToString());
        return;
      }
    }
  }
  const auto listed = dir_->ListMaps();
  Stopwatch opening;
  Result<std::shared_ptr<PlaceMap>> map = Status::Internal("not opened");
  std::string restored_from;
  if (std::find(listed.begin(), listed.end(), replica->name) == listed.end()) {
    // A new replica: from a live peer's checkpoint when there is one (then only the records
    // after it are applied); on any failure from an empty map, replaying the whole stream (it
    // keeps every record), which is slower but as correct.
    auto peer = RestoreFromPeer(replica->name, revision);
    if (peer.ok()) {
      restored_from = *peer;
    } else if (peer.status().code() != StatusCode::kNotFound) {
      spdlog::warn("shard {}: map '{}': no checkpoint from a peer ({}); replaying the stream",
                   options_.shard_id, replica->name, peer.status().ToString());
    }
  }
  if (std::find(listed.begin(), listed.end(), replica->name) != listed.end() ||
      !restored_from.empty()) {
    map = dir_->OpenMap(replica->name, vocabulary->second);
  } else {
    wire::ServiceMapSettings settings;
    auto map_options = wire::MapOptionsFromProto(
        meta.config, options_.max_descriptors_per_frame,
        wire::MapVocabulary{vocabulary_name, vocabulary->second.feature_type()}, &settings);
    if (!map_options.ok()) {
      SetProblem(replica.get(), "unavailable: " + map_options.status().ToString());
      return;
    }
    map = dir_->CreateMap(replica->name, *map_options, vocabulary->second);
  }
  if (!map.ok()) {
    SetProblem(replica.get(), "unavailable: " + map.status().ToString());
    return;
  }
  replica->stream = meta.stream;
  replica->type = (*map)->info().options.database.feature_type;
  {
    std::error_code ignored;
    std::filesystem::create_directories(dir_->path() + "/cluster-maps", ignored);
    std::ofstream out(generation_file, std::ios::trunc);
    out << revision << "\n";
  }
  {
    MutexLock lock(mutex_);
    replica->map = std::move(map).value();
    replica->restored_from = restored_from;
  }
  spdlog::info("shard {}: holding map '{}' (applied {}; made ready in {:.2f} s)", options_.shard_id,
               replica->name, replica->map->applied_sequence(), opening.ElapsedMs() / 1e3);
  StartApplier(replica);
}

void Shard::Impl::StartApplier(const std::shared_ptr<Replica>& replica) {
  replica->consumer.reset();     // a broken one: stopped before its successor starts
  Replica* raw = replica.get();  // outlives its consumer and applier (Drop and Stop end them)
  {
    // What a broken replica's consumer queued is stale: the new one starts at applied + 1.
    MutexLock lock(raw->queue_mutex);
    raw->queue.clear();
    raw->queued_bytes = 0;
  }
  replica->broken = false;
  if (!replica->applier.joinable())
    replica->applier = std::thread([this, raw] { ApplyQueued(raw); });
  auto consumer = js_->Consume(
      replica->stream, replica->subject, replica->map->applied_sequence() + 1,
      [raw](uint64_t sequence, std::string_view data) { Enqueue(raw, sequence, data); });
  if (!consumer.ok()) {
    // It may have queued records before it failed (jetstream.h): they apply in order from
    // applied + 1, and the next start (the next reconcile) skips what they applied.
    SetProblem(raw, "unavailable: " + consumer.status().ToString());
    return;
  }
  replica->consumer = std::move(consumer).value();
  SetProblem(raw, "");
}

// At most this much in one ApplyBatch, and queued per replica.
constexpr size_t kApplyBatchRecords = 256;
constexpr size_t kQueuedBytes = size_t(64) << 20;

void Shard::Impl::Enqueue(Replica* replica, uint64_t sequence, std::string_view data) {
  MutexLock lock(replica->queue_mutex);
  while (!replica->stopping && !replica->broken && !replica->queue.empty() &&
         replica->queued_bytes + data.size() > kQueuedBytes) {
    replica->queue_cv.Wait(replica->queue_mutex);
  }
  if (replica->stopping || replica->broken) return;  // restarted from applied + 1
  replica->queue.push_back({sequence, std::string(data)});
  replica->queued_bytes += data.size();
  replica->queue_cv.NotifyAll();
}

void Shard::Impl::StopApplier(Replica* replica) {
  {
    MutexLock lock(replica->queue_mutex);
    replica->stopping = true;
    replica->queue_cv.NotifyAll();
  }
  // A preparation stops first: an applier waiting for it would wait for the whole build.
  if (replica->map) replica->map->CancelPreparedSwitch();
  if (replica->applier.joinable()) replica->applier.join();
  if (replica->preparing.joinable()) {
    replica->map->CancelPreparedSwitch();
    replica->preparing.join();
  }
}

void Shard::Impl::PrepareSwitch(Replica* replica, uint64_t checksum, uint32_t parts) {
  if (!replica->preparing_done) return;  // the switch record builds this one itself
  if (replica->preparing.joinable()) replica->preparing.join();
  replica->preparing_done = false;
  replica->preparing = std::thread([this, replica, checksum, parts] {
    {
      MutexLock lock(replica->queue_mutex);
      if (replica->stopping) {
        replica->preparing_done = true;
        return;
      }
    }
    Stopwatch clock;
    const Status prepared = replica->map->PrepareVocabularySwitch(checksum, parts);
    if (prepared.ok()) {
      spdlog::info("shard {}: map '{}': switch to vocabulary {} prepared in {:.1f} s",
                   options_.shard_id, replica->name, Hex64(checksum), clock.ElapsedMs() / 1000);
    } else {
      spdlog::warn(
          "shard {}: map '{}': switch to vocabulary {} not prepared ({}); its record "
          "builds it",
          options_.shard_id, replica->name, Hex64(checksum), prepared.ToString());
    }
    replica->preparing_done = true;
  });
}

void Shard::Impl::ApplyQueued(Replica* replica) {
  std::vector<Replica::Queued> taken;
  std::vector<MapLogRecord> records;
  std::vector<PlaceMap::SequencedRecord> batch;
  for (;;) {
    taken.clear();
    {
      MutexLock lock(replica->queue_mutex);
      while (!replica->stopping && replica->queue.empty()) {
        replica->queue_cv.Wait(replica->queue_mutex);
      }
      if (replica->stopping) return;
      while (!replica->queue.empty() && taken.size() < kApplyBatchRecords) {
        replica->queued_bytes -= replica->queue.front().data.size();
        taken.push_back(std::move(replica->queue.front()));
        replica->queue.pop_front();
      }
      replica->queue_cv.NotifyAll();  // room for the delivery thread
    }
    // Decoded up to the first record that does not decode: the ones before it still apply.
    records.clear();
    Status failure;
    uint64_t failed_at = 0;
    for (const Replica::Queued& queued : taken) {
      auto record = DecodeMapRecord(queued.data, replica->type);
      if (!record.ok()) {
        failure = record.status();
        failed_at = queued.sequence;
        break;
      }
      records.push_back(std::move(record).value());
    }
    batch.clear();
    for (size_t i = 0; i < records.size(); ++i) batch.push_back({taken[i].sequence, &records[i]});
    Result<size_t> applied = size_t(0);
    if (!batch.empty()) {
      MutexLock lock(replica->apply_mutex);
      applied = replica->map->ApplyBatch(batch);
    }
    if (!applied.ok()) {
      failure = applied.status();
      failed_at = replica->map->applied_sequence() + 1;
    }
    for (const PlaceMap::SequencedRecord& r : batch) {
      if (r.record->kind == MapLogRecord::Kind::kPrepareVocabulary &&
          r.sequence <= replica->map->applied_sequence()) {
        PrepareSwitch(replica, r.record->vocabulary_source.checksum, r.record->vocabulary_parts);
      }
    }
    {
      MutexLock lock(mutex_);
      applied_cv_.NotifyAll();
    }
    if (failure.ok()) continue;
    // Stopped: nothing is skipped; the next reconcile starts over from applied + 1.
    {
      MutexLock lock(replica->queue_mutex);
      replica->broken = true;
      replica->queue.clear();
      replica->queued_bytes = 0;
      replica->queue_cv.NotifyAll();
    }
    const std::string problem =
        "failed: record " + std::to_string(failed_at) + ": " + failure.ToString();
    spdlog::error("shard {}: map '{}': {}", options_.shard_id, replica->name, problem);
    SetProblem(replica, problem);
  }
}

void Shard::Impl::SetProblem(Replica* replica, const std::string& problem) {
  MutexLock lock(mutex_);
  replica->problem = problem;
}

void Shard::Impl::Drop(const std::string& name) {
  std::shared_ptr<Replica> replica;
  {
    MutexLock lock(mutex_);
    auto it = replicas_.find(name);
    if (it == replicas_.end()) return;
    replica = it->second;
    replicas_.erase(it);
  }
  replica->consumer.reset();
  StopApplier(replica.get());
  const bool opened = replica->map != nullptr;
  replica->map.reset();
  if (opened) {
    // No longer placed here (or the map was deleted): the local copy goes.
    if (Status deleted = dir_->DeleteMap(name); !deleted.ok()) {
      spdlog::warn("shard {}: deleting map '{}': {}", options_.shard_id, name, deleted.ToString());
    }
    spdlog::info("shard {}: dropped map '{}'", options_.shard_id, name);
  }
  std::remove(GenerationFile(name).c_str());
  (void)etcd_->Delete(Key("applied/" + name + "/" + options_.shard_id));
  if (applied_gauge_) {
    applied_gauge_->Remove(&applied_gauge_->Add({{"map", name}, {"shard", options_.shard_id}}));
    lag_gauge_->Remove(&lag_gauge_->Add({{"map", name}, {"shard", options_.shard_id}}));
  }
}

void Shard::Impl::Report() {
  std::vector<std::shared_ptr<Replica>> replicas;
  {
    MutexLock lock(mutex_);
    for (const auto& [name, replica] : replicas_) {
      if (replica->map) replicas.push_back(replica);
    }
  }
  for (const auto& replica : replicas) {
    const uint64_t applied = replica->map->applied_sequence();
    if (auto info = js_->GetStreamInfo(replica->stream); info.ok()) {
      replica->stream_last = info->last_sequence;
    }
    (void)etcd_->Put(Key("applied/" + replica->name + "/" + options_.shard_id),
                     std::to_string(applied));
    if (applied_gauge_) {
      const prometheus::Labels labels = {{"map", replica->name}, {"shard", options_.shard_id}};
      applied_gauge_->Add(labels).Set(double(applied));
      const uint64_t last = replica->stream_last.load();
      lag_gauge_->Add(labels).Set(last > applied ? double(last - applied) : 0.0);
    }
  }
}

Result<AnyVocabulary> Shard::Impl::VocabularyFor(const MapInfo& info) const {
  if (info.vocabulary.stored()) return AnyVocabulary();  // the map opens with its own (issue 29)
  for (const auto& [name, vocabulary] : options_.vocabularies) {
    if (vocabulary.checksum() == info.vocabulary_checksum) return vocabulary;
  }
  return Status::FailedPrecondition("map '" + info.name +
                                    "': no configured vocabulary has its checksum");
}

Result<std::string> Shard::Impl::RestoreFromPeer(const std::string& map, int64_t create_revision) {
  auto applied = etcd_->Get(Key("applied/" + map + "/"), true);
  if (!applied.ok()) return applied.status();
  auto shards = etcd_->Get(Key("shards/"), true);
  if (!shards.ok()) return shards.status();
  std::map<std::string, std::string> live;  // id -> address
  const std::string shards_prefix = Key("shards/");
  for (const KeyValue& kv : shards->kvs) {
    auto json = nlohmann::json::parse(kv.value, nullptr, false);
    if (json.is_object() && json.contains("address") && json["address"].is_string()) {
      live[kv.key.substr(shards_prefix.size())] = json["address"].get<std::string>();
    }
  }
  std::string peer;
  uint64_t best = 0;
  const std::string applied_prefix = Key("applied/" + map + "/");
  for (const KeyValue& kv : applied->kvs) {
    const std::string id = kv.key.substr(applied_prefix.size());
    const uint64_t sequence = std::strtoull(kv.value.c_str(), nullptr, 10);
    if (id != options_.shard_id && live.count(id) && sequence > best) {
      best = sequence;
      peer = id;
    }
  }
  if (peer.empty()) return Status::NotFound("no live replica of '" + map + "' has applied records");
  auto stub =
      cv1::Shard::NewStub(grpc::CreateChannel(live[peer], grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::minutes(10));
  cv1::CheckpointRequest request;
  request.set_map(map);
  request.set_create_revision(create_revision);
  const std::string spool = dir_->path() + "/.catchup-" + HexOf(map) + ".pdbsnap";
  struct Remove {
    std::string path;
    ~Remove() { std::remove(path.c_str()); }
  } remove{spool};
  uint64_t expected = 0, received = 0;
  Stopwatch phase;  // each phase's time, in the log line: where a slow catch-up spends it
  {
    std::ofstream out(spool, std::ios::binary | std::ios::trunc);
    auto reader = stub->Checkpoint(&context, request);
    cv1::CheckpointChunk chunk;
    bool first = true;
    while (reader->Read(&chunk)) {
      if (first) expected = chunk.archive_bytes();
      first = false;
      out.write(chunk.data().data(), std::streamsize(chunk.data().size()));
      received += chunk.data().size();
    }
    const grpc::Status finished = reader->Finish();
    if (!finished.ok()) {
      return Status::IoError("checkpoint of '" + map + "' from " + peer + ": " +
                             finished.error_message());
    }
    out.flush();
    if (!out) return Status::IoError("spooling the checkpoint of '" + map + "' failed");
  }
  if (received != expected) {
    return Status::Corruption("checkpoint of '" + map + "' from " + peer + ": " +
                              std::to_string(received) + " of " + std::to_string(expected) +
                              " bytes");
  }
  const double fetch_ms = phase.Lap();
  auto imported =
      snapshots_->Import(spool, [this](const MapInfo& info) { return VocabularyFor(info); });
  if (!imported.ok()) return imported.status();
  const double import_ms = phase.Lap();
  Status restored = snapshots_->Restore(imported->id, map);
  (void)snapshots_->Delete(imported->id);
  if (!restored.ok()) return restored;
  spdlog::info(
      "shard {}: map '{}' restored from the checkpoint of {} ({} bytes; fetch {:.2f} s, import and "
      "verify {:.2f} s, restore {:.2f} s)",
      options_.shard_id, map, peer, received, fetch_ms / 1e3, import_ms / 1e3, phase.Lap() / 1e3);
  return peer;
}

Result<std::shared_ptr<PlaceMap>> Shard::Impl::MapOf(const std::string& map) const {
  MutexLock lock(mutex_);
  auto it = replicas_.find(map);
  if (it == replicas_.end()) {
    return Status::NotFound("map '" + map + "' is not held by shard " + options_.shard_id);
  }
  if (!it->second->map) {
    return Status::IoError("map '" + map + "' on shard " + options_.shard_id +
                           " is not open: " + it->second->problem);
  }
  return it->second->map;
}

grpc::Status Shard::Impl::AwaitApplied(grpc::ServerContext* context, const std::string& map,
                                       const PlaceMap& m, uint64_t min_sequence) {
  // Bounded by the call's deadline (30 s without one).
  const auto remaining = context->deadline() - std::chrono::system_clock::now();
  const auto until =
      Clock::now() + std::min<std::chrono::system_clock::duration>(
                         remaining, std::chrono::duration_cast<std::chrono::system_clock::duration>(
                                        std::chrono::seconds(30)));
  MutexLock lock(mutex_);
  while (m.applied_sequence() < min_sequence) {
    if (stopping_) return GrpcError(grpc::StatusCode::UNAVAILABLE, "shard is stopping");
    if (Clock::now() >= until || context->IsCancelled()) {
      return GrpcError(grpc::StatusCode::DEADLINE_EXCEEDED,
                       "map '" + map + "' on shard " + options_.shard_id + " applied " +
                           std::to_string(m.applied_sequence()) + " < min_sequence " +
                           std::to_string(min_sequence));
    }
    applied_cv_.WaitUntil(mutex_, std::min(until, Clock::now() + std::chrono::milliseconds(200)));
  }
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::AppliedMap(grpc::ServerContext* context, const std::string& map,
                                     uint64_t min_sequence, std::shared_ptr<PlaceMap>* out) {
  auto held = MapOf(map);
  if (!held.ok()) return ToGrpc(held.status());
  if (grpc::Status applied = AwaitApplied(context, map, **held, min_sequence); !applied.ok()) {
    return applied;
  }
  *out = std::move(held).value();
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::Search(grpc::ServerContext* context, const cv1::SearchRequest& request,
                                 cv1::SearchResponse* response) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  PlaceMap& m = *map;
  ProcessedFrame frame;
  if (Status decoded = FrameFromSearchRequest(request, m.options().database.feature_type, &frame);
      !decoded.ok()) {
    return GrpcError(grpc::StatusCode::INVALID_ARGUMENT, decoded.message());
  }
  QueryOptions options = wire::QueryOptionsFromProto(request.options(), request.agent_id());
  options.search_threads = options_.search.threads;
  options.max_word_share = options_.search.max_word_share;
  options.skip_words_min_places = options_.search.skip_words_min_places;
  options.timestamp_ns = request.timestamp_ns();
  const uint64_t applied = m.applied_sequence();  // every place up to it is searched
  const uint64_t vocabulary = m.vocabulary().checksum();
  if (frame.vocabulary_checksum == 0) frame.vocabulary_checksum = vocabulary;  // an older worker
  QueryResult result = m.Search(frame, options);
  response->set_vocabulary_checksum(vocabulary);
  response->set_valid(result.valid);
  response->set_rejection(result.rejection);
  wire::MatchesToProto(result.matches, response->mutable_matches());
  response->set_applied_sequence(applied);
  response->set_search_ms(result.timings.search_ms);
  response->set_verify_ms(result.timings.verify_ms);
  return grpc::Status::OK;
}

namespace {

// A vocabulary's bytes in chunks after `first` (which carries the description).
grpc::Status StreamVocabulary(cv1::VocabularyChunk first, const std::string& bytes,
                              grpc::ServerWriter<cv1::VocabularyChunk>* writer) {
  constexpr size_t kChunk = 1 << 20;
  size_t at = 0;
  do {
    const size_t n = std::min(kChunk, bytes.size() - at);
    first.set_data(bytes.substr(at, n));
    if (!writer->Write(first)) return GrpcError(grpc::StatusCode::CANCELLED, "caller went away");
    first.Clear();
    at += n;
  } while (at < bytes.size());
  return grpc::Status::OK;
}

}  // namespace

grpc::Status Shard::Impl::LearnVocabulary(grpc::ServerContext* context,
                                          const cv1::LearnVocabularyRequest& request,
                                          grpc::ServerWriter<cv1::VocabularyChunk>* writer) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  AdaptOptions options;  // one thread at nice 10: this replica keeps serving meanwhile
  if (request.seed() != 0) options.learning.seed = request.seed();
  options.learning.max_sample_descriptors = request.max_sample_descriptors();
  options.learning.branching = int(std::min<uint32_t>(request.branching(), 1u << 16));
  options.learning.depth = int(std::min<uint32_t>(request.depth(), 1u << 16));
  const uint64_t applied = map->applied_sequence();
  auto learned = map->LearnVocabulary(options);
  if (!learned.ok()) return ToGrpc(learned.status());
  spdlog::info(
      "shard {}: map '{}': learned vocabulary {} from {} places ({} descriptors) at "
      "sequence {} in {:.1f} s",
      options_.shard_id, request.map(), learned->vocabulary.checksum_hex(),
      learned->source.places_offered, learned->source.descriptors_sampled, applied,
      learned->source.learn_ms / 1000);
  cv1::VocabularyChunk first;
  wire::VocabularySourceToProto(learned->source, first.mutable_vocabulary()->mutable_current());
  first.mutable_vocabulary()->set_map(request.map());
  first.set_applied_sequence(applied);
  return StreamVocabulary(std::move(first), learned->vocabulary.Serialize(), writer);
}

grpc::Status Shard::Impl::GetVocabulary(grpc::ServerContext* context,
                                        const cv1::GetVocabularyRequest& request,
                                        grpc::ServerWriter<cv1::VocabularyChunk>* writer) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  // The vocabulary first: a switch between the two reads shows the older record with it, never
  // bytes newer than the record.
  const AnyVocabulary vocabulary = map->vocabulary();
  const uint64_t applied = map->applied_sequence();
  VocabularyRecord record = map->info().vocabulary;
  if (record.current.checksum != vocabulary.checksum()) {
    return GrpcError(grpc::StatusCode::UNAVAILABLE,
                     "map '" + request.map() + "' is switching its vocabulary; ask again");
  }
  cv1::VocabularyChunk first;
  wire::VocabularyRecordToProto(record, map->switching_vocabulary(), first.mutable_vocabulary());
  first.mutable_vocabulary()->set_map(request.map());
  first.set_applied_sequence(applied);
  return StreamVocabulary(std::move(first), request.bytes() ? vocabulary.Serialize() : "", writer);
}

grpc::Status Shard::Impl::FetchPlaces(grpc::ServerContext* context,
                                      const cv1::FetchPlacesRequest& request,
                                      cv1::FetchPlacesResponse* response) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  const PlaceMap& m = *map;
  response->set_applied_sequence(m.applied_sequence());
  for (const uint32_t id : request.place_ids()) {
    cv1::FetchedPlace* out = nullptr;
    if (request.features()) {
      auto place = m.GetPlace(id);
      if (place.status().code() == StatusCode::kNotFound) continue;
      if (!place.ok()) return ToGrpc(place.status());
      out = response->add_places();
      out->set_bow(EncodeBow(place->payload.bow));
      out->set_features(EncodeLocalFeatures(place->payload.features, place->payload.direct));
    } else {
      auto bow = m.GetBow(id);
      if (bow.status().code() == StatusCode::kNotFound) continue;
      if (!bow.ok()) return ToGrpc(bow.status());
      out = response->add_places();
      out->set_bow(EncodeBow(*bow));
    }
    out->set_place_id(id);
  }
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::ListAgentPlaces(grpc::ServerContext* context,
                                          const cv1::ListAgentPlacesRequest& request,
                                          cv1::ListAgentPlacesResponse* response) {
  if (request.agent_id().empty()) {
    return GrpcError(grpc::StatusCode::INVALID_ARGUMENT, "agent_id: is required");
  }
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  const PlaceMap& m = *map;
  response->set_applied_sequence(m.applied_sequence());
  const size_t limit = request.limit() == 0 ? 256 : std::min<size_t>(request.limit(), 1024);
  PlaceFilter filter;
  filter.agent_id = request.agent_id();
  // A bounded walk per page (ids of other agents count too): the caller pages on.
  const PlacePage page =
      m.database()->ListPlacesBefore(request.before_place_id(), limit, filter, size_t(1) << 16);
  for (const auto& record : page.places) {
    auto bow = m.GetBow(record->id);
    if (bow.status().code() == StatusCode::kNotFound) continue;  // removed meanwhile
    if (!bow.ok()) return ToGrpc(bow.status());
    cv1::AgentPlace* out = response->add_places();
    out->set_place_id(record->id);
    out->set_sequence(record->metadata.sequence);
    out->set_bow(EncodeBow(*bow));
  }
  response->set_next_before_place_id(page.next_before);
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::Checkpoint(const cv1::CheckpointRequest& request,
                                     grpc::ServerWriter<cv1::CheckpointChunk>* writer) {
  auto map = MapOf(request.map());
  if (!map.ok()) return ToGrpc(map.status());
  int64_t held_revision = 0;
  std::shared_ptr<Replica> replica;
  {
    MutexLock lock(mutex_);
    auto it = replicas_.find(request.map());
    if (it != replicas_.end()) {
      replica = it->second;
      held_revision = replica->create_revision;
    }
  }
  if (!replica) return ToGrpc(Status::NotFound("map '" + request.map() + "' is not held here"));
  if (request.create_revision() != 0 && held_revision != request.create_revision()) {
    return GrpcError(grpc::StatusCode::FAILED_PRECONDITION,
                     "map '" + request.map() + "' on shard " + options_.shard_id +
                         " is of create revision " + std::to_string(held_revision) + ", not " +
                         std::to_string(request.create_revision()));
  }
  // Unverified here: the new replica's Import verifies (opens and scrubs) what it received.
  Stopwatch phase;
  uint64_t applied = 0;
  Result<SnapshotInfo> created = Status::Internal("no checkpoint");
  {
    MutexLock lock(replica->apply_mutex);
    applied = (*map)->applied_sequence();
    created = snapshots_->CreateForTransfer(**map);
  }
  if (!created.ok()) return ToGrpc(created.status());
  const double create_ms = phase.Lap();
  struct Cleanup {
    SnapshotStore* store;
    std::string id;
    ~Cleanup() { (void)store->Delete(id); }
  } cleanup{snapshots_.get(), created->id};
  auto bytes = snapshots_->ArchiveBytes(created->id);
  if (!bytes.ok()) return ToGrpc(bytes.status());
  bool first = true;
  Status written = snapshots_->WriteArchive(created->id, 1 << 20, [&](std::string_view data) {
    cv1::CheckpointChunk chunk;
    if (first) {
      chunk.set_applied_sequence(applied);
      chunk.set_archive_bytes(*bytes);
      first = false;
    }
    chunk.set_data(std::string(data));
    if (!writer->Write(chunk)) return Status::IoError("the receiver went away");
    return Status::Ok();
  });
  spdlog::info(
      "shard {}: checkpoint of map '{}' at {} for a new replica: {} bytes (made in {:.2f} s, "
      "sent in {:.2f} s): {}",
      options_.shard_id, request.map(), applied, *bytes, create_ms / 1e3, phase.Lap() / 1e3,
      written.ok() ? "sent" : written.ToString());
  return ToGrpc(written);
}

std::vector<ReplicaStatus> Shard::Impl::StatusOfReplicas() const {
  std::vector<ReplicaStatus> out;
  MutexLock lock(mutex_);
  for (const auto& [name, replica] : replicas_) {
    ReplicaStatus status;
    status.map = name;
    status.stream_last_sequence = replica->stream_last.load();
    if (replica->map) {
      status.applied_sequence = replica->map->applied_sequence();
      status.places = replica->map->database()->Stats().places;
      status.prepared_vocabulary = replica->map->prepared_vocabulary();
    }
    status.state = replica->problem.empty() ? "applying" : replica->problem;
    status.restored_from = replica->restored_from;
    out.push_back(std::move(status));
  }
  return out;
}

Result<std::unique_ptr<Shard>> Shard::Start(ShardOptions options) {
  auto impl = std::make_unique<Impl>(std::move(options));
  PLACEDB_RETURN_IF_ERROR(impl->Init());
  return std::unique_ptr<Shard>(new Shard(std::move(impl)));
}

Shard::Shard(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Shard::~Shard() = default;

int Shard::internal_port() const {
  return impl_->port_;
}
const std::string& Shard::shard_id() const {
  return impl_->options_.shard_id;
}
std::vector<ReplicaStatus> Shard::Replicas() const {
  return impl_->StatusOfReplicas();
}
Result<std::shared_ptr<PlaceMap>> Shard::Map(const std::string& map) const {
  return impl_->MapOf(map);
}

}  // namespace placedb::cluster
