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
#include "server/backend/place_reads.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/map_record.h"
#include "server/cluster/placement.h"
#include "server/cluster/shard_impl.h"
#include "server/metrics.h"

namespace placedb::cluster {

namespace {
using Clock = std::chrono::steady_clock;
using wire::ToGrpc;

Result<MapMeta> ParseMapMeta(const std::string& text) {
  auto json = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded() || !json.is_object() || !json.contains("stream") ||
      !json["stream"].is_string() || !json.contains("config")) {
    return Status::InvalidArgument("maps/ value is not {\"config\": ..., \"stream\": ...}");
  }
  MapMeta meta;
  meta.stream = json["stream"].get<std::string>();
  if (json.contains("snapshot") && json["snapshot"].is_string()) {
    meta.snapshot = json["snapshot"].get<std::string>();
  }
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

}  // namespace

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
  grpc::Status WatchLoopClosures(grpc::ServerContext* context,
                                 const pv1::WatchLoopClosuresRequest* request,
                                 grpc::ServerWriter<pv1::LoopConstraint>* writer) override {
    auto map = impl_->MapOf(request->map());
    if (!map.ok()) return ToGrpc(map.status());
    return server::StreamLoopLog(
        request->map(), **map, *request,
        [writer](const pv1::LoopConstraint& message) { return writer->Write(message); },
        [&]() -> grpc::Status {
          if (context->IsCancelled()) {
            return grpc::Status(grpc::StatusCode::CANCELLED, "the worker went away");
          }
          if (impl_->stopping()) {
            return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the shard is stopping");
          }
          return grpc::Status::OK;
        });
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
  grpc::Status ScrubMap(grpc::ServerContext*, const cv1::ReplicaRequest* request,
                        pv1::ScrubReport* response) override {
    return impl_->ScrubReplica(*request, response);
  }
  grpc::Status RecoverMap(grpc::ServerContext*, const cv1::RecoverReplicaRequest* request,
                          pv1::ReplicaRecovery* response) override {
    return impl_->RecoverReplica(*request, response);
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
  js.tls = o.tls;
  auto connected = JetStream::Connect(js);
  if (!connected.ok()) return connected.status();
  js_ = std::move(connected).value();
  EtcdOptions etcd;
  etcd.endpoints = o.etcd;
  etcd.tls = o.tls;
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
  builder.AddListeningPort(o.internal_listen, InternalServerCredentials(o.tls), &port_);
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
    {
      MutexLock lifecycle(lifecycle_mutex_);
      Reconcile();
    }
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
      } else if (replica->gap) {
        // Compaction purged records it has not applied: made again as a new replica below (from
        // the base or a newer peer checkpoint), as RecoverMap rebuilds one.
        spdlog::warn(
            "shard {}: map '{}': its stream no longer holds the records after {}: rebuilding it "
            "from the map's base or a peer's checkpoint",
            options_.shard_id, name, replica->apply ? replica->apply->applied_sequence() : 0);
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
    // A new replica: from the map's base (issue 35: compaction) or a live peer's checkpoint,
    // whichever is newer (then only the records after it are applied); a map restored from a
    // cluster snapshot, from the snapshot; otherwise from an empty map, replaying the whole
    // stream. When the stream was purged meanwhile, the applier finds the gap and the replica is
    // made again from the base: nothing is skipped.
    std::optional<MapBase> base;
    if (auto read = Archives().GetBase(replica->name); !read.ok()) {
      spdlog::warn("shard {}: map '{}': {}", options_.shard_id, replica->name,
                   read.status().ToString());
    } else if (read->has_value() && (*read)->create_revision == revision) {
      base = std::move(*read);
    }
    auto peer = RestoreFromPeer(replica->name, revision, base ? base->manifest.base : 0);
    Status from_base = Status::NotFound("no base");
    if (peer.ok()) {
      restored_from = *peer;
    } else if (base) {
      from_base = RestoreFromArchive(
          replica->name, base->manifest,
          "its base (records up to " + std::to_string(base->manifest.base) + ")");
      if (from_base.ok()) {
        restored_from = "base " + std::to_string(base->manifest.base);
      } else {
        spdlog::warn("shard {}: map '{}': restoring its base: {}", options_.shard_id, replica->name,
                     from_base.ToString());
      }
    }
    if (!restored_from.empty()) {
      // restored
    } else if (!meta.snapshot.empty()) {
      // A restored map's stream starts after its snapshot's records: no replay from 1.
      auto manifest = Archives().Get(meta.snapshot);
      Status restored = manifest.ok() ? RestoreFromArchive(replica->name, *manifest,
                                                           "snapshot '" + meta.snapshot + "'")
                                      : manifest.status();
      if (!restored.ok()) {
        SetProblem(replica.get(),
                   "unavailable: restoring snapshot '" + meta.snapshot +
                       "': " + restored.ToString() +
                       (peer.status().code() == StatusCode::kNotFound
                            ? std::string()
                            : "; no peer's checkpoint: " + peer.status().ToString()));
        return;
      }
      restored_from = "snapshot " + meta.snapshot;
    } else if (base) {
      // A compacted stream cannot be replayed from 1: tried again at the next reconcile.
      SetProblem(replica.get(), "unavailable: restoring the map's base: " + from_base.ToString() +
                                    (peer.status().code() == StatusCode::kNotFound
                                         ? std::string()
                                         : "; no peer's checkpoint: " + peer.status().ToString()));
      return;
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
    // Damage is told apart: RecoverMap rebuilds such a replica (shard_admin.cc).
    const bool damaged = map.status().code() == StatusCode::kCorruption;
    {
      MutexLock lock(mutex_);
      replica->damaged = damaged;
    }
    SetProblem(replica.get(), (damaged ? "damaged: " : "unavailable: ") + map.status().ToString());
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
    replica->damaged = false;
    replica->apply = replica->map.get();
    replica->restored_from = restored_from;
  }
  spdlog::info("shard {}: holding map '{}' (applied {}; made ready in {:.2f} s)", options_.shard_id,
               replica->name, replica->apply->applied_sequence(), opening.ElapsedMs() / 1e3);
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
  // Issue 35: a replica whose next record was purged (compaction, while it was down) is made
  // again from the base at the next reconcile; an empty purged stream delivers nothing, so the
  // applier's own check would not see it.
  if (auto info = js_->GetStreamInfo(replica->stream);
      info.ok() && replica->apply->applied_sequence() + 1 < info->first_sequence) {
    replica->gap = true;
    SetProblem(raw, "failed: the stream starts at record " + std::to_string(info->first_sequence) +
                        ", this replica applied up to " +
                        std::to_string(replica->apply->applied_sequence()) +
                        ": the records between were compacted away (rebuilding from the base)");
    MutexLock lock(mutex_);
    dirty_ = true;
    return;
  }
  if (!replica->applier.joinable())
    replica->applier = std::thread([this, raw] { ApplyQueued(raw); });
  auto consumer = js_->Consume(
      replica->stream, replica->subject, replica->apply->applied_sequence() + 1,
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
  if (replica->apply) replica->apply->CancelPreparedSwitch();
  if (replica->applier.joinable()) replica->applier.join();
  if (replica->preparing.joinable()) {
    replica->apply->CancelPreparedSwitch();
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
    const Status prepared = replica->apply->PrepareVocabularySwitch(checksum, parts);
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
  std::vector<ReplicaApply::SequencedRecord> batch;
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
    // Issue 35: the ordered consumer delivers every stored record in order, so a sequence above
    // the next one expected means the stream was purged below it (compaction) while this replica
    // had not applied those records: applied up to the gap, then stopped and rebuilt.
    uint64_t expected = replica->apply->applied_sequence() + 1;
    for (const Replica::Queued& queued : taken) {
      if (queued.sequence > expected) {
        failure = Status::FailedPrecondition(
            "the stream delivered record " + std::to_string(queued.sequence) + " after " +
            std::to_string(expected - 1) + ": the records between were compacted away");
        failed_at = expected;
        replica->gap = true;
        break;
      }
      expected = std::max(expected, queued.sequence + 1);
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
      applied = replica->apply->ApplyBatch(batch);
    }
    if (!applied.ok()) {
      failure = applied.status();
      failed_at = replica->apply->applied_sequence() + 1;
    }
    for (const ReplicaApply::SequencedRecord& r : batch) {
      if (r.record->kind == MapLogRecord::Kind::kPrepareVocabulary &&
          r.sequence <= replica->apply->applied_sequence()) {
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
  replica->apply = nullptr;
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
    const uint64_t applied = replica->apply->applied_sequence();
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

Result<std::string> Shard::Impl::RestoreFromPeer(const std::string& map, int64_t create_revision,
                                                 uint64_t newer_than) {
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
  uint64_t best = newer_than;
  const std::string applied_prefix = Key("applied/" + map + "/");
  for (const KeyValue& kv : applied->kvs) {
    const std::string id = kv.key.substr(applied_prefix.size());
    const uint64_t sequence = std::strtoull(kv.value.c_str(), nullptr, 10);
    if (id != options_.shard_id && live.count(id) && sequence > best) {
      best = sequence;
      peer = id;
    }
  }
  if (peer.empty()) {
    return Status::NotFound("no live replica of '" + map + "' has applied records" +
                            (newer_than ? " after " + std::to_string(newer_than) : ""));
  }
  auto stub = cv1::Shard::NewStub(
      grpc::CreateChannel(live[peer], InternalChannelCredentials(options_.tls)));
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
  Stopwatch phase;  // each phase's time, in the log line: where a slow catch-up spends it
  auto fetched = FetchCheckpoint(stub.get(), &context, request, spool, peer);
  if (!fetched.ok()) return fetched.status();
  const double fetch_ms = phase.Lap();
  PLACEDB_RETURN_IF_ERROR(ImportAsMap(spool, map));
  spdlog::info(
      "shard {}: map '{}' restored from the checkpoint of {} ({} bytes; fetch {:.2f} s, import, "
      "verify and restore {:.2f} s)",
      options_.shard_id, map, peer, fetched->bytes, fetch_ms / 1e3, phase.Lap() / 1e3);
  return peer;
}

Status Shard::Impl::ImportAsMap(const std::string& spool, const std::string& map) {
  auto imported =
      snapshots_->Import(spool, [this](const MapInfo& info) { return VocabularyFor(info); });
  if (!imported.ok()) return imported.status();
  Status restored = snapshots_->Restore(imported->id, map);
  (void)snapshots_->Delete(imported->id);
  return restored;
}

Status Shard::Impl::RestoreFromArchive(const std::string& map, const SnapshotManifest& manifest,
                                       const std::string& what) {
  const std::string spool = dir_->path() + "/.archive-" + HexOf(map) + ".pdbsnap";
  struct Remove {
    std::string path;
    ~Remove() { std::remove(path.c_str()); }
  } remove{spool};
  Stopwatch phase;
  PLACEDB_RETURN_IF_ERROR(Archives().ReadToFile(
      manifest, spool, std::chrono::system_clock::now() + std::chrono::minutes(30)));
  const double fetch_ms = phase.Lap();
  PLACEDB_RETURN_IF_ERROR(ImportAsMap(spool, map));
  spdlog::info(
      "shard {}: map '{}' restored from {} ({} bytes, records up to {}; fetch {:.2f} s, import, "
      "verify and restore {:.2f} s)",
      options_.shard_id, map, what, manifest.archive_bytes, manifest.base, fetch_ms / 1e3,
      phase.Lap() / 1e3);
  return Status::Ok();
}

std::vector<ReplicaStatus> Shard::Impl::StatusOfReplicas() const {
  std::vector<ReplicaStatus> out;
  MutexLock lock(mutex_);
  for (const auto& [name, replica] : replicas_) {
    ReplicaStatus status;
    status.map = name;
    status.stream_last_sequence = replica->stream_last.load();
    if (replica->map) {
      status.applied_sequence = replica->apply->applied_sequence();
      status.places = replica->map->database()->Stats().places;
      status.prepared_vocabulary = replica->apply->prepared_vocabulary();
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
