#include "server/cluster/worker.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <thread>

#include "core/base/map_name.h"
#include "core/base/text.h"
#include "core/base/timing.h"
#include "core/storage/codec.h"
#include "proto/cluster.grpc.pb.h"
#include "proto/convert_config.h"
#include "proto/status.h"
#include "server/cluster/map_record.h"

namespace placedb::server {

namespace {

using Clock = std::chrono::system_clock;
using wire::ToGrpc;
using ShardStub = cluster::v1::Shard::Stub;

// What OnReplica runs for one Shard RPC: `rpc` with `request`, its answer in `response` (cleared
// before each attempt).
template <typename Request, typename Response>
auto ShardRpc(grpc::Status (ShardStub::*rpc)(grpc::ClientContext*, const Request&, Response*),
              const Request& request, Response* response) {
  return [rpc, &request, response](const std::shared_ptr<grpc::Channel>& channel,
                                   MapBackend::Deadline until) {
    grpc::ClientContext context;
    context.set_deadline(until);
    response->Clear();
    const auto stub = cluster::v1::Shard::NewStub(channel);
    return (stub.get()->*rpc)(&context, request, response);
  };
}

std::chrono::milliseconds Remaining(MapBackend::Deadline deadline) {
  return std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
}

std::string Hostname() {
  char name[256] = {};
  if (gethostname(name, sizeof(name) - 1) != 0) return "worker";
  return name;
}

// hostname:pid, and a number when one process runs several workers (tests).
std::string WorkerId() {
  static std::atomic<int> made{0};
  const int n = made++;
  // Appended piece by piece: GCC 12 warns falsely (-Wrestrict) on "." + std::to_string().
  std::string id = Hostname();
  id += ':';
  id += std::to_string(getpid());
  if (n > 0) {
    id += '.';
    id += std::to_string(n);
  }
  return id;
}

Result<v1::MapConfig> ConfigOf(const cluster::MapRecordInfo& info) {
  v1::MapConfig config;
  const auto parsed = google::protobuf::util::JsonStringToMessage(info.config_json, &config);
  if (!parsed.ok()) {
    return Status::Corruption("the map's configuration in etcd does not parse: " +
                              std::string(parsed.message()));
  }
  return config;
}

}  // namespace

ClusterWorker::ClusterWorker(const ServerConfig& config, MapRegistry* local)
    : config_(config), cluster_(config.cluster), local_(local), id_(WorkerId()) {}

Result<std::unique_ptr<ClusterWorker>> ClusterWorker::Start(const ServerConfig& config,
                                                            MapRegistry* local, Metrics* metrics) {
  std::unique_ptr<ClusterWorker> worker(new ClusterWorker(config, local));
  const ClusterSettings& c = config.cluster;
  if (c.internal_tls) {
    auto tls = cluster::LoadInternalTls(config.tls, c.internal_ca_file);
    if (!tls.ok()) return tls.status();
    worker->tls_ = std::move(tls).value();
    spdlog::info("worker: shards, NATS and etcd over mutual TLS (cluster.internal_tls)");
  }
  cluster::EtcdOptions etcd;
  etcd.endpoints = c.etcd;
  etcd.tls = worker->tls_;
  auto client = cluster::EtcdClient::Create(etcd);
  if (!client.ok()) return client.status();
  worker->etcd_ = std::move(client).value();
  cluster::JetStreamOptions nats;
  for (const std::string& url : c.nats) {
    nats.servers.push_back(url.rfind("nats://", 0) == 0 ? url : "nats://" + url);
  }
  nats.client_name = "placedb-worker " + worker->id_;
  nats.tls = worker->tls_;
  auto jetstream = cluster::JetStream::Connect(nats);
  if (!jetstream.ok()) return jetstream.status().WithContext("cluster.nats");
  worker->jetstream_ = std::move(jetstream).value();
  auto view = cluster::ClusterView::Start(worker->etcd_.get(), c.name);
  if (!view.ok()) return view.status().WithContext("cluster.etcd");
  worker->view_ = std::move(view).value();
  cluster::CoordinatorOptions coordinator;
  coordinator.self = worker->id_;
  coordinator.replicas = c.replicas;
  coordinator.replace_after = std::chrono::seconds(c.replace_after_s);
  worker->coordinator_ = std::make_unique<cluster::Coordinator>(
      worker->etcd_.get(), worker->view_.get(), std::move(coordinator));

  worker->archives_ = std::make_unique<cluster::SnapshotArchives>(
      worker->jetstream_.get(), worker->etcd_.get(), c.name, c.stream_replicas);

  // The local copies are a cache of the cluster's maps: stale ones go.
  for (const auto& entry : local->List()) {
    if (Status deleted = local->Delete(entry->name); !deleted.ok()) {
      spdlog::warn("worker: cannot remove the stale local copy of map '{}': {}", entry->name,
                   deleted.ToString());
    }
  }

  prometheus::Registry& registry = *metrics->registry();
  prometheus::Histogram::BucketBoundaries buckets;
  for (double b = 0.00025; b < 40; b *= 2) buckets.push_back(b);
  worker->publish_seconds_ =
      &prometheus::BuildHistogram()
           .Name("placedb_cluster_publish_seconds")
           .Help(
               "Worker: one record's publish to its map's stream until JetStream's "
               "acknowledgement, retries included")
           .Register(registry)
           .Add({}, buckets);
  worker->retries_ = &prometheus::BuildCounter()
                          .Name("placedb_cluster_retries_total")
                          .Help(
                              "Worker: calls tried again (on another replica, or a publish "
                              "with the same message id), by call")
                          .Register(registry);
  worker->stream_bytes_ = &prometheus::BuildGauge()
                               .Name("placedb_cluster_stream_bytes")
                               .Help("Coordinator: bytes a map's stream stores (compaction)")
                               .Register(registry);
  worker->stream_records_ = &prometheus::BuildGauge()
                                 .Name("placedb_cluster_stream_records")
                                 .Help("Coordinator: records a map's stream stores (compaction)")
                                 .Register(registry);
  worker->base_sequence_ =
      &prometheus::BuildGauge()
           .Name("placedb_cluster_base_sequence")
           .Help("Coordinator: the stream sequence a map's compaction base holds records up to")
           .Register(registry);
  worker->compactions_ = &prometheus::BuildCounter()
                              .Name("placedb_cluster_compactions_total")
                              .Help("Worker: map compactions that stored a new base")
                              .Register(registry);
  worker->compaction_failures_ = &prometheus::BuildCounter()
                                      .Name("placedb_cluster_compaction_failures_total")
                                      .Help("Worker: map compactions that failed")
                                      .Register(registry);
  worker->compactions_->Add({});  // exported at 0 from the start
  worker->compaction_failures_->Add({});
  if (c.compact_after_records > 0 || c.compact_after_bytes > 0) {
    ClusterWorker* raw = worker.get();
    worker->compactor_ = std::thread([raw] { raw->CompactLoop(); });
  }
  spdlog::info("cluster worker {}: cluster '{}', etcd {}, nats {} ({})", worker->id_, c.name,
               c.etcd.size(), c.nats.size(), worker->jetstream_->ConnectedUrl());
  return worker;
}

ClusterWorker::~ClusterWorker() {
  {
    MutexLock lock(compact_mutex_);
    compact_stopping_ = true;
    compact_cv_.NotifyAll();
  }
  if (compactor_.joinable()) compactor_.join();
  if (coordinator_) coordinator_->Stop();
  if (view_) view_->Stop();
}

// ---- Maps ---------------------------------------------------------------------------------------

Result<cluster::MapView> ClusterWorker::Lookup(const std::string& name, const std::string& field) {
  if (Status valid = ValidateMapName(name); !valid.ok()) return valid.WithContext(field);
  if (auto view = view_->Map(name)) return std::move(view).value();
  // Not in the view (yet): a map made a moment ago by another worker is in etcd already.
  auto read = etcd_->Get(view_->keys().Map(name));
  if (!read.ok()) return read.status();
  if (read->kvs.empty()) {
    return Status::NotFound(field + ": map '" + name + "' does not exist");
  }
  auto info = cluster::DecodeMapInfo(read->kvs[0].value);
  if (!info.ok()) return info.status();
  cluster::MapView out;
  out.info = std::move(info).value();
  out.create_revision = read->kvs[0].create_revision;
  return out;
}

void ClusterWorker::Describe(const std::string& name, const cluster::MapView& view,
                             v1::MapDescription* out) const {
  out->set_name(name);
  out->set_state(v1::MAP_STATE_AVAILABLE);
  out->set_created_unix_ms(view.info.created_unix_ms);
  auto config = ConfigOf(view.info);
  if (!config.ok()) {
    out->set_state(v1::MAP_STATE_UNAVAILABLE);
    out->set_unavailable_reason(config.status().ToString());
    return;
  }
  *out->mutable_config() = *config;
  if (const VocabularyEntry* vocabulary = local_->FindVocabulary(config->vocabulary())) {
    out->set_vocabulary_checksum(vocabulary->vocabulary.checksum_hex());
  }
  // Places: the most applied replica's sequence is an upper bound of the place ids; the exact
  // count is the replicas' (Shard.Status).
}

grpc::Status ClusterWorker::CreateMap(const MapCreation& creation, Deadline deadline,
                                      v1::MapDescription* response) {
  if (creation.settings.adapt_after_descriptors != 0 || creation.settings.regrow_factor != 0) {
    // Refused rather than stored and ignored: no worker runs the policy (docs/cluster.md).
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "config.vocabulary_policy: not run in cluster mode; call "
                        "AdaptVocabulary (placedb maps adapt-vocabulary) instead");
  }
  const std::string& name = creation.name;
  // The effective configuration (every field filled in) is what the cluster stores: workers
  // and shards build the same map options from it.
  v1::MapConfig config;
  wire::MapConfigToProto(creation.options, creation.settings, creation.vocabulary, &config);
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.preserve_proto_field_names = true;
  if (!google::protobuf::util::MessageToJsonString(config, &json, print).ok()) {
    return grpc::Status(grpc::StatusCode::INTERNAL, "cannot encode the map's configuration");
  }
  cluster::MapRecordInfo info{.config_json = json,
                              .stream = cluster::StreamName(cluster_.name, name),
                              .created_unix_ms = NowUnixMs(),
                              .snapshot = {},
                              .snapshot_base = 0};
  return MakeMap(name, info, deadline, response);
}

grpc::Status ClusterWorker::MakeMap(const std::string& name, const cluster::MapRecordInfo& info,
                                    Deadline deadline, v1::MapDescription* response) {
  const std::string key = view_->keys().Map(name);
  auto created = etcd_->Txn({cluster::Compare::Absent(key)},
                            {cluster::TxnOp::Put(key, cluster::EncodeMapInfo(info))});
  if (!created.ok()) return ToGrpc(created.status(), "creating the map in etcd");
  if (!created->succeeded) {
    return grpc::Status(grpc::StatusCode::ALREADY_EXISTS, "name: map '" + name + "' exists");
  }
  cluster::StreamConfig stream;
  stream.name = info.stream;
  stream.subjects = {cluster::StreamSubject(cluster_.name, name)};
  stream.replicas = cluster_.stream_replicas;
  stream.max_message_bytes = int32_t(std::min<uint64_t>(config_.limits.max_message_bytes, 8 << 20));
  if (Status made = jetstream_->EnsureStream(stream); !made.ok()) {
    // No stream, no map: the key goes again (a failure here leaves a map whose stream the next
    // CreateMap of the name would make: EnsureStream is idempotent).
    (void)etcd_->Delete(key);
    return ToGrpc(made, "creating the map's stream " + stream.name);
  }
  if (info.snapshot_base > 0) {
    // A restored map's records continue after its snapshot's: the empty stream's next sequence
    // becomes base + 1 (JetStream's purge up to a sequence). A stream that holds records (left
    // by a map of the name whose deletion did not remove it) is no start: the map goes again.
    Status started = jetstream_->PurgeStream(stream.name, "", info.snapshot_base + 1);
    if (started.ok()) {
      auto now = jetstream_->GetStreamInfo(stream.name);
      if (!now.ok()) {
        started = now.status();
      } else if (now->messages != 0 || now->last_sequence != info.snapshot_base) {
        started = Status::IoError("the stream " + stream.name + " held records (last " +
                                  std::to_string(now->last_sequence) +
                                  "): removed with the map; try again");
      }
    }
    if (!started.ok()) {
      (void)etcd_->Delete(key);
      (void)jetstream_->DeleteStream(stream.name);
      return ToGrpc(started, "starting the restored map's stream after the snapshot");
    }
  }
  // The first frames search a replica: wait (bounded) for the coordinator's placement.
  const auto until =
      std::chrono::steady_clock::now() +
      std::min<std::chrono::milliseconds>(
          std::chrono::seconds(10), std::max(Remaining(deadline), std::chrono::milliseconds(0)));
  if (!view_->Shards().empty() &&
      !view_->WaitFor(
          name, [](const std::optional<cluster::MapView>& v) { return v && v->placement; },
          until)) {
    spdlog::warn("cluster map '{}' created without a placement yet (no live shard?)", name);
  }
  cluster::MapView view;
  view.info = info;
  Describe(name, view, response);
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::GetMap(const std::string& name, Deadline deadline,
                                   v1::MapDescription* response) {
  // Linearizable: a map just deleted elsewhere is NOT_FOUND here at once.
  if (Status valid = ValidateMapName(name); !valid.ok()) return ToGrpc(valid.WithContext("name"));
  auto read = etcd_->Get(view_->keys().Map(name));
  if (!read.ok()) return ToGrpc(read.status());
  if (read->kvs.empty()) {
    return grpc::Status(grpc::StatusCode::NOT_FOUND, "name: map '" + name + "' does not exist");
  }
  auto info = cluster::DecodeMapInfo(read->kvs[0].value);
  if (!info.ok()) return ToGrpc(info.status());
  cluster::MapView view;
  view.info = std::move(info).value();
  Describe(name, view, response);
  // Places: the most applied replica's count (Shard.Status), when one answers within 2 s; the
  // description stands without it.
  const Deadline status_deadline = std::min(deadline, Clock::now() + std::chrono::seconds(2));
  const cluster::v1::StatusRequest status_request;
  cluster::v1::StatusResponse status;
  const grpc::Status asked = OnReplica("Status", name, 0, status_deadline,
                                       ShardRpc(&ShardStub::Status, status_request, &status));
  if (asked.ok()) {
    for (const cluster::v1::MapStatus& map : status.maps()) {
      if (map.map() == name) response->mutable_stats()->set_places(map.places());
    }
  }
  // Its vocabulary as a replica has it (issue 29: it may have learned its own), likewise.
  v1::MapVocabulary vocabulary;
  if (ReplicaVocabulary(name, 0, false, status_deadline, &vocabulary, nullptr).ok()) {
    vocabulary.set_map(name);
    response->set_vocabulary_checksum(vocabulary.current().checksum());
    response->mutable_vocabulary()->Swap(&vocabulary);
  }
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::ListMaps(Deadline, v1::ListMapsResponse* response) {
  const std::string prefix = view_->keys().root + "maps/";
  auto read = etcd_->Get(prefix, /*prefix=*/true);
  if (!read.ok()) return ToGrpc(read.status());
  for (const cluster::KeyValue& kv : read->kvs) {
    v1::MapSummary* summary = response->add_maps();
    summary->set_name(kv.key.substr(prefix.size()));
    auto info = cluster::DecodeMapInfo(kv.value);
    auto config = info.ok() ? ConfigOf(*info) : Result<v1::MapConfig>(info.status());
    summary->set_available(config.ok());
    summary->set_state(config.ok() ? v1::MAP_STATE_AVAILABLE : v1::MAP_STATE_UNAVAILABLE);
    if (!config.ok()) {
      summary->set_unavailable_reason(config.status().ToString());
      continue;
    }
    summary->set_vocabulary(config->vocabulary());
    summary->set_feature_type(config->feature_type());
  }
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::DeleteMap(const std::string& name, Deadline) {
  if (Status valid = ValidateMapName(name); !valid.ok()) return ToGrpc(valid.WithContext("name"));
  const cluster::ClusterKeys& keys = view_->keys();
  const std::string key = keys.Map(name);
  auto deleted = etcd_->Txn(
      {cluster::Compare{
          key, cluster::Compare::Target::kCreateRevision, cluster::Compare::Op::kGreater, 0, {}}},
      {cluster::TxnOp::Delete(key), cluster::TxnOp::Delete(keys.Placement(name)),
       cluster::TxnOp::Delete(keys.AppliedPrefix(name), /*prefix=*/true)});
  if (!deleted.ok()) return ToGrpc(deleted.status(), "deleting the map in etcd");
  if (!deleted->succeeded) {
    return grpc::Status(grpc::StatusCode::NOT_FOUND, "name: map '" + name + "' does not exist");
  }
  // Its compaction base (issue 35): a re-created map never takes it (its create revision differs).
  if (Status dropped = archives_->DeleteBase(name); !dropped.ok()) {
    spdlog::warn("cluster map '{}' deleted, but not its base: {}", ForLog(name),
                 dropped.ToString());
  }
  // The map is gone for every worker now; its stream after it (a failure leaves an orphan stream
  // that a CreateMap of the name takes over: EnsureStream).
  const std::string stream = cluster::StreamName(cluster_.name, name);
  if (Status dropped = jetstream_->DeleteStream(stream);
      !dropped.ok() && dropped.code() != StatusCode::kNotFound) {
    spdlog::warn("cluster map '{}' deleted, but not its stream {}: {}", name, stream,
                 dropped.ToString());
  }
  MutexLock lock(local_mutex_);
  if (local_revision_.erase(name)) (void)local_->Delete(name);
  return grpc::Status::OK;
}

Result<std::shared_ptr<const MapEntry>> ClusterWorker::Map(const std::string& name,
                                                           const std::string& field) {
  auto view = Lookup(name, field);
  if (!view.ok()) return view.status();
  MutexLock lock(local_mutex_);
  auto known = local_revision_.find(name);
  if (known != local_revision_.end() && known->second == view->create_revision) {
    return local_->Get(name, field);
  }
  // First frame of this map here, or the map was re-created: a fresh local copy.
  if (known != local_revision_.end()) {
    (void)local_->Delete(name);
    local_revision_.erase(known);
  }
  auto config = ConfigOf(view->info);
  if (!config.ok()) return config.status();
  auto vocabulary = local_->ResolveVocabulary(config->vocabulary());
  if (!vocabulary.ok()) return vocabulary.status();
  ServiceMapSettings settings;
  auto options = wire::MapOptionsFromProto(
      *config, config_.limits.max_descriptors_per_frame,
      wire::MapVocabulary{(*vocabulary)->name, (*vocabulary)->vocabulary.feature_type()},
      &settings);
  if (!options.ok()) return options.status();
  auto entry = local_->Create(name, *options, config->vocabulary(), settings);
  if (entry.status().code() == StatusCode::kAlreadyExists) {
    (void)local_->Delete(name);  // left by a run that did not clean up
    entry = local_->Create(name, *options, config->vocabulary(), settings);
  }
  if (!entry.ok())
    return entry.status().WithContext("the worker's local copy of map '" + name + "'");
  local_revision_[name] = view->create_revision;
  return entry;
}

// ---- Replicas -----------------------------------------------------------------------------------

Result<std::vector<ClusterWorker::Replica>> ClusterWorker::Replicas(const std::string& map,
                                                                    uint64_t min_sequence) {
  auto view = view_->Map(map);
  if (!view) return Status::NotFound("map: map '" + map + "' does not exist");
  if (!view->placement || view->placement->replicas.empty()) {
    return Status::IoError("map '" + map + "' has no replica placed yet (no live shard?)");
  }
  const std::map<std::string, std::string> live = view_->Shards();
  std::vector<Replica> out;
  for (const std::string& shard : view->placement->replicas) {
    auto address = live.find(shard);
    if (address == live.end()) continue;
    auto applied = view->applied.find(shard);
    out.push_back({shard, address->second, applied == view->applied.end() ? 0 : applied->second});
  }
  if (out.empty()) {
    return Status::IoError("no live replica of map '" + map + "' (its shards are down)");
  }
  // Caught up first, then the least lagging; a replica that has not caught up still answers
  // (Shard.Search waits, bounded, for min_sequence).
  std::stable_sort(out.begin(), out.end(), [&](const Replica& a, const Replica& b) {
    const bool a_ready = a.applied >= min_sequence, b_ready = b.applied >= min_sequence;
    if (a_ready != b_ready) return a_ready;
    return a.applied > b.applied;
  });
  return out;
}

std::shared_ptr<grpc::Channel> ClusterWorker::ChannelTo(const std::string& address) {
  MutexLock lock(mutex_);
  auto& channel = channels_[address];
  if (!channel) {
    grpc::ChannelArguments arguments;
    arguments.SetMaxReceiveMessageSize(64 << 20);
    arguments.SetMaxSendMessageSize(64 << 20);
    // A shard that restarts is dialled again quickly.
    arguments.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 100);
    arguments.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
    channel =
        grpc::CreateCustomChannel(address, cluster::InternalChannelCredentials(tls_), arguments);
  }
  return channel;
}

template <typename Call>
grpc::Status ClusterWorker::OnReplica(const char* what, const std::string& map,
                                      uint64_t min_sequence, Deadline deadline, Call&& call) {
  auto replicas = Replicas(map, min_sequence);
  if (!replicas.ok()) return ToGrpc(replicas.status());
  grpc::Status status;
  std::string failed;  // the shard of the first attempt
  for (int attempt = 0; attempt < 2; ++attempt) {
    const Replica* replica = nullptr;
    if (attempt == 0) {
      replica = &replicas->front();
    } else {
      // The view as it is now (the first attempt may have taken a while: a replaced replica, a
      // shard gone), without the one that just failed.
      replicas = Replicas(map, min_sequence);
      if (!replicas.ok()) return status;
      for (const Replica& other : *replicas) {
        if (other.shard != failed) {
          replica = &other;
          break;
        }
      }
      if (!replica) return status;
      retries_->Add({{"call", what}}).Increment();
    }
    // The first attempt gets half the time left when another replica could answer (a hung
    // replica must leave it time); the last gets the rest. No deadline: 10 s per attempt.
    const auto now = Clock::now();
    Deadline until = deadline == Deadline::max() ? now + std::chrono::seconds(10) : deadline;
    if (attempt == 0 && replicas->size() > 1 && until > now) until = now + (until - now) / 2;
    status = call(ChannelTo(replica->address), until);
    if (status.error_code() != grpc::StatusCode::UNAVAILABLE &&
        status.error_code() != grpc::StatusCode::DEADLINE_EXCEEDED) {
      return status;
    }
    spdlog::warn("{} on map '{}': shard '{}' ({}) answered {}: {}", what, map, replica->shard,
                 replica->address, int(status.error_code()), ForLog(status.error_message()));
    failed = replica->shard;
  }
  return status;
}

// ---- Publishing ---------------------------------------------------------------------------------

Result<cluster::PubAck> ClusterWorker::PublishRecord(const std::string& map,
                                                     const std::string& data,
                                                     const std::string& message_id,
                                                     Deadline deadline) {
  const std::string subject = cluster::StreamSubject(cluster_.name, map);
  const auto started = std::chrono::steady_clock::now();
  Status last = Status::IoError("the call's deadline had passed before the first attempt");
  for (int attempt = 0;; ++attempt) {
    const auto left = Remaining(deadline);
    if (left <= std::chrono::milliseconds(0)) break;
    if (attempt > 0) retries_->Add({{"call", "Publish"}}).Increment();
    // One attempt waits at most 2 s for its PubAck: a leader election takes several.
    auto ack =
        jetstream_->Publish(subject, data, message_id,
                            std::min<std::chrono::milliseconds>(left, std::chrono::seconds(2)));
    if (ack.ok()) {
      publish_seconds_->Observe(
          std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count());
      return *ack;
    }
    last = ack.status();
    if (last.code() != StatusCode::kIoError) return last;  // not a transient failure
    std::this_thread::sleep_for(std::min<std::chrono::milliseconds>(
        std::chrono::milliseconds(100),
        std::max(Remaining(deadline), std::chrono::milliseconds(0))));
  }
  return Status::IoError("map '" + map + "': JetStream acknowledged no publish of " +
                         (message_id.empty() ? std::string("the record") : message_id) +
                         " before the deadline (nothing was acknowledged; resend the frame with "
                         "the same sequence): " +
                         last.ToString());
}

// ---- Shard calls (placedb.cluster.v1.Shard) -----------------------------------------------------

grpc::Status ClusterWorker::Search(const std::string& map, const ProcessedFrame& frame,
                                   const PlaceMetadata& metadata, const v1::MatchOptions& options,
                                   uint64_t min_sequence, Deadline deadline,
                                   v1::QueryResponse* out) {
  cluster::v1::SearchRequest request;
  request.set_map(map);
  request.set_min_sequence(min_sequence);
  // The frame as the pipeline left it (the shard's codec: server/cluster/map_record.h).
  cluster::FrameToSearchRequest(frame, &request);
  *request.mutable_options() = options;
  request.set_agent_id(metadata.agent_id);
  request.set_timestamp_ns(metadata.timestamp_ns);
  cluster::v1::SearchResponse response;
  const grpc::Status status = OnReplica("Search", map, min_sequence, deadline,
                                        ShardRpc(&ShardStub::Search, request, &response));
  if (!status.ok()) return status;
  out->mutable_matches()->Swap(response.mutable_matches());
  out->set_sequence(response.applied_sequence());
  if (response.vocabulary_checksum() != 0 &&
      response.vocabulary_checksum() != frame.vocabulary_checksum) {
    // The replicas switched vocabulary: this worker's next frames are processed with theirs.
    FollowVocabulary(map, response.vocabulary_checksum(), response.applied_sequence(), nullptr,
                     deadline);
  }
  return grpc::Status::OK;
}

Result<ClusterWorker::FrameRecord> ClusterWorker::RecordedFrame(const std::string& map,
                                                                uint64_t sequence,
                                                                const std::string& message_id,
                                                                Deadline deadline) {
  const std::string what = "map '" + map + "': the stream's record " + std::to_string(sequence) +
                           " of " + message_id + " (a duplicate's)";
  auto entry = local_->Get(map, "map");  // the map's feature type, to decode the record
  if (!entry.ok()) return entry.status();
  const FeatureType type = (*entry)->map->options().database.feature_type;
  const std::string stream = cluster::StreamName(cluster_.name, map);
  Result<cluster::StoredMessage> read = Status::IoError("the deadline had passed");
  while (Remaining(deadline) > std::chrono::milliseconds(0)) {
    read = jetstream_->GetMessage(stream, sequence);
    if (read.ok() || read.status().code() != StatusCode::kIoError) break;
    retries_->Add({{"call", "GetMessage"}}).Increment();
    std::this_thread::sleep_for(std::min<std::chrono::milliseconds>(
        std::chrono::milliseconds(100),
        std::max(Remaining(deadline), std::chrono::milliseconds(0))));
  }
  if (!read.ok()) return read.status().WithContext(what);
  if (read->message_id != message_id) {
    return Status::Internal(what + ": that record is message '" + read->message_id + "'");
  }
  auto record = cluster::DecodeMapRecord(read->data, type);
  if (!record.ok()) return record.status().WithContext(what);
  FrameRecord out;
  out.duplicate = true;
  switch (record->kind) {
    case MapLogRecord::Kind::kAddPlace:
      out.kind = FrameRecord::Kind::kPlace;
      out.place = uint32_t(sequence);
      return out;
    case MapLogRecord::Kind::kCountObservation:
      out.kind = FrameRecord::Kind::kMerged;
      out.place = uint32_t(record->place);
      return out;
    case MapLogRecord::Kind::kInvalidFrame:
      out.kind = FrameRecord::Kind::kInvalid;
      out.rejection = record->frame.rejection;
      return out;
    default:
      return Status::Internal(what + ": not a frame's record (kind " +
                              std::to_string(int(record->kind)) + ")");
  }
}

Result<ClusterWorker::FrameRecord> ClusterWorker::CountObservation(
    const std::string& map, uint32_t place, const ProcessedFrame& frame,
    const PlaceMetadata& metadata, const std::string& message_id, Deadline deadline) {
  auto ack = PublishRecord(map, cluster::EncodeCountObservation(place, frame, metadata), message_id,
                           deadline);
  if (!ack.ok()) return ack.status();
  if (ack->duplicate) return RecordedFrame(map, ack->sequence, message_id, deadline);
  FrameRecord out;
  out.kind = FrameRecord::Kind::kMerged;
  out.place = place;
  return out;
}

Status ClusterWorker::PublishLoops(const std::string& map, const std::vector<LoopConstraint>& loops,
                                   const std::string& message_id, Deadline deadline) {
  auto published = PublishRecord(map, cluster::EncodeLoopConstraints(loops), message_id, deadline);
  return published.ok() ? Status::Ok() : published.status();
}

Result<std::vector<std::pair<PlaceId, PlacePayload>>> ClusterWorker::FetchPlaces(
    const std::string& map, const std::vector<PlaceId>& ids, bool features, uint64_t min_sequence,
    Deadline deadline) {
  std::vector<std::pair<PlaceId, PlacePayload>> out;
  if (ids.empty()) return out;
  auto entry = local_->Get(map, "map");  // the map's feature type, to decode the features
  if (!entry.ok()) return entry.status();
  const FeatureType type = (*entry)->map->options().database.feature_type;
  cluster::v1::FetchPlacesRequest request;
  request.set_map(map);
  request.set_min_sequence(
      std::max<uint64_t>(min_sequence, *std::max_element(ids.begin(), ids.end())));
  for (const PlaceId id : ids) request.add_place_ids(id);
  request.set_features(features);
  cluster::v1::FetchPlacesResponse response;
  const grpc::Status status = OnReplica("FetchPlaces", map, request.min_sequence(), deadline,
                                        ShardRpc(&ShardStub::FetchPlaces, request, &response));
  if (!status.ok()) return wire::FromGrpc(status);
  for (const cluster::v1::FetchedPlace& place : response.places()) {
    const std::string what = "place " + std::to_string(place.place_id()) + " from a replica";
    PlacePayload payload;
    auto bow = DecodeBow(place.bow());
    if (!bow.ok()) return bow.status().WithContext(what);
    payload.bow = std::move(bow).value();
    if (features) {
      PLACEDB_RETURN_IF_ERROR(DecodeLocalFeatures(place.features(), type, &payload.features,
                                                  &payload.direct, &payload.geometry)
                                  .WithContext(what));
    }
    out.emplace_back(place.place_id(), std::move(payload));
  }
  return out;
}

Result<std::vector<PlaceSource::AgentPlace>> ClusterWorker::AgentPlaces(const std::string& map,
                                                                        const std::string& agent_id,
                                                                        uint64_t min_sequence,
                                                                        Deadline deadline) {
  // Places stored through another worker (before a failover) are in the stream, not necessarily
  // in `min_sequence`: read where the stream ends now.
  auto info = jetstream_->GetStreamInfo(cluster::StreamName(cluster_.name, map));
  if (!info.ok()) return info.status().WithContext("map '" + map + "': its stream");
  min_sequence = std::max(min_sequence, info->last_sequence);
  std::vector<PlaceSource::AgentPlace> out;
  if (min_sequence == 0) return out;  // an empty stream: no places (nor a replica needed yet)
  cluster::v1::ListAgentPlacesRequest request;
  request.set_map(map);
  request.set_min_sequence(min_sequence);
  request.set_agent_id(agent_id);
  request.set_limit(512);
  while (true) {
    cluster::v1::ListAgentPlacesResponse response;
    const grpc::Status status =
        OnReplica("ListAgentPlaces", map, min_sequence, deadline,
                  ShardRpc(&ShardStub::ListAgentPlaces, request, &response));
    if (!status.ok()) return wire::FromGrpc(status);
    for (const cluster::v1::AgentPlace& place : response.places()) {
      auto bow = DecodeBow(place.bow());
      if (!bow.ok()) {
        return bow.status().WithContext("place " + std::to_string(place.place_id()) +
                                        " from a replica");
      }
      out.push_back({place.place_id(), place.sequence(), std::move(bow).value()});
    }
    if (response.next_before_place_id() == 0) break;
    request.set_before_place_id(response.next_before_place_id());
  }
  return out;
}

// ---- Vocabulary switches (issue 29) -------------------------------------------------------------

namespace {

// A vocabulary's part on the stream: well below NATS' default 1 MiB payload and any stream's
// max message size.
constexpr size_t kVocabularyPartBytes = 512 << 10;

// Reads a Shard vocabulary stream: the first chunk's description, every chunk's bytes.
template <typename Request>
auto VocabularyStream(std::unique_ptr<grpc::ClientReader<cluster::v1::VocabularyChunk>> (
                          ShardStub::*rpc)(grpc::ClientContext*, const Request&),
                      const Request& request, v1::MapVocabulary* record, std::string* bytes) {
  return [rpc, &request, record, bytes](const std::shared_ptr<grpc::Channel>& channel,
                                        MapBackend::Deadline until) {
    grpc::ClientContext context;
    context.set_deadline(until);
    record->Clear();
    if (bytes) bytes->clear();
    const auto stub = cluster::v1::Shard::NewStub(channel);
    auto reader = (stub.get()->*rpc)(&context, request);
    cluster::v1::VocabularyChunk chunk;
    for (bool first = true; reader->Read(&chunk); first = false) {
      if (first) record->Swap(chunk.mutable_vocabulary());
      if (bytes) *bytes += chunk.data();
    }
    return reader->Finish();
  };
}

// Without a deadline a switch may take long (a large map's re-index on its replicas).
MapBackend::Deadline SwitchDeadline(MapBackend::Deadline deadline) {
  return deadline == MapBackend::Deadline::max() ? Clock::now() + std::chrono::minutes(30)
                                                 : deadline;
}

}  // namespace

grpc::Status ClusterWorker::ReplicaVocabulary(const std::string& map, uint64_t min_sequence,
                                              bool bytes, Deadline deadline,
                                              v1::MapVocabulary* record, std::string* vocabulary) {
  cluster::v1::GetVocabularyRequest request;
  request.set_map(map);
  request.set_min_sequence(min_sequence);
  request.set_bytes(bytes);
  return OnReplica(
      "GetVocabulary", map, min_sequence, deadline,
      VocabularyStream(&ShardStub::GetVocabulary, request, record, bytes ? vocabulary : nullptr));
}

void ClusterWorker::FollowVocabulary(const std::string& map, uint64_t checksum,
                                     uint64_t min_sequence, const AnyVocabulary* next,
                                     Deadline deadline) {
  MutexLock lock(follow_mutex_);
  auto entry = local_->Get(map, "map");
  if (!entry.ok() || (*entry)->map->vocabulary().checksum() == checksum) return;
  const auto now = std::chrono::steady_clock::now();
  if (auto failed = follow_failed_.find(map);
      failed != follow_failed_.end() && now - failed->second < std::chrono::seconds(30)) {
    return;
  }
  follow_failed_[map] = now;  // until it succeeds
  AnyVocabulary fetched;
  VocabularySource source;
  if (next && next->checksum() == checksum) {
    fetched = *next;
  } else {
    v1::MapVocabulary record;
    std::string bytes;
    const grpc::Status asked =
        ReplicaVocabulary(map, min_sequence, true, deadline, &record, &bytes);
    auto parsed = asked.ok() ? AnyVocabulary::Parse(bytes) : wire::FromGrpc(asked);
    if (!parsed.ok()) {
      spdlog::warn("map '{}': this worker's copy keeps its vocabulary ({}); its replicas' is {}",
                   ForLog(map), parsed.status().ToString(), Hex64(checksum));
      return;
    }
    fetched = std::move(parsed).value();
  }
  // Where it came from, as the replicas have it (the worker's copy only shows it in logs).
  source.origin = "learned";
  source.checksum = fetched.checksum();
  source.branching = uint32_t(fetched.branching());
  source.depth = uint32_t(fetched.depth());
  source.words = fetched.word_count();
  AdaptOptions options;
  options.nice = 0;  // a copy without places: nothing to re-index
  auto installed = (*entry)->map->InstallVocabulary(fetched, source, options);
  if (!installed.ok()) {
    spdlog::warn("map '{}': this worker's copy did not take vocabulary {}: {}", ForLog(map),
                 fetched.checksum_hex(), installed.status().ToString());
    return;
  }
  follow_failed_.erase(map);
  local_->VocabularySwitched(map);
  spdlog::info("map '{}': this worker now processes frames with vocabulary {}", ForLog(map),
               fetched.checksum_hex());
}

Result<ClusterWorker::SwitchStart> ClusterWorker::StartSwitch(const std::string& name,
                                                              Deadline deadline) {
  auto view = Lookup(name, "name");
  if (!view.ok()) return view.status();
  SwitchStart start;
  {
    MutexLock lock(mutex_);
    if (!switching_.insert(name).second) {
      return Status::FailedPrecondition("map '" + name +
                                        "' is already switching its vocabulary; wait for it");
    }
  }
  start.slot = std::shared_ptr<void>(nullptr, [this, name](void*) {
    MutexLock release(mutex_);
    switching_.erase(name);
  });
  start.until = SwitchDeadline(deadline);
  auto stream = jetstream_->GetStreamInfo(cluster::StreamName(cluster_.name, name));
  if (!stream.ok()) return stream.status().WithContext("map '" + name + "': its stream");
  start.stream_last = stream->last_sequence;
  return start;
}

void ClusterWorker::AwaitPrepared(const std::string& map, uint64_t checksum, Deadline until) {
  const cluster::v1::StatusRequest request;
  while (Clock::now() < until) {
    auto replicas = Replicas(map, 0);
    if (!replicas.ok()) return;
    size_t prepared = 0;
    for (const Replica& replica : *replicas) {
      grpc::ClientContext context;
      context.set_deadline(std::min(until, Clock::now() + std::chrono::seconds(2)));
      cluster::v1::StatusResponse status;
      const auto stub = cluster::v1::Shard::NewStub(ChannelTo(replica.address));
      if (!stub->Status(&context, request, &status).ok()) continue;
      for (const cluster::v1::MapStatus& held : status.maps()) {
        if (held.map() == map && held.prepared_vocabulary() == checksum) ++prepared;
      }
    }
    if (prepared == replicas->size()) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  spdlog::warn(
      "map '{}': not every replica prepared the switch to vocabulary {} in time; it is "
      "published anyway",
      ForLog(map), Hex64(checksum));
}

grpc::Status ClusterWorker::AwaitSwitch(const std::string& map, uint64_t sequence,
                                        const AnyVocabulary* next, Deadline deadline,
                                        v1::MapVocabulary* response) {
  // A replica answers once it applied the switch's record, i.e. switched.
  const grpc::Status asked = ReplicaVocabulary(map, sequence, false, deadline, response, nullptr);
  if (!asked.ok()) {
    return grpc::Status(
        asked.error_code(),
        "the switch is record " + std::to_string(sequence) +
            " of the map's stream; no replica reported it applied: " + asked.error_message());
  }
  response->set_map(map);
  if (auto checksum = ParseHex64(response->current().checksum())) {
    FollowVocabulary(map, *checksum, sequence, next, deadline);
  }
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::AdaptVocabulary(const v1::AdaptVocabularyRequest& request,
                                            Deadline deadline, const std::atomic<bool>*,
                                            v1::MapVocabulary* response) {
  const std::string& name = request.name();
  auto started = StartSwitch(name, deadline);
  if (!started.ok()) return ToGrpc(started.status());
  const Deadline until = started->until;
  // 1. One replica learns, once it applied everything the stream held when the call began
  // (every place acknowledged before it is learned from).
  cluster::v1::LearnVocabularyRequest learn;
  learn.set_map(name);
  learn.set_min_sequence(started->stream_last);
  learn.set_seed(request.seed());
  learn.set_max_sample_descriptors(request.max_sample_descriptors());
  learn.set_branching(request.branching());
  learn.set_depth(request.depth());
  v1::MapVocabulary learned;
  std::string bytes;
  grpc::Status status =
      OnReplica("LearnVocabulary", name, learn.min_sequence(), until,
                VocabularyStream(&ShardStub::LearnVocabulary, learn, &learned, &bytes));
  if (!status.ok()) return status;
  auto next = AnyVocabulary::Parse(bytes);
  auto source = wire::VocabularySourceFromProto(learned.current(), "learned");
  if (!next.ok() || !source.ok() || next->checksum() != source->checksum) {
    return grpc::Status(
        grpc::StatusCode::INTERNAL,
        "map '" + name + "': the vocabulary a replica learned did not arrive whole");
  }
  // 2. Its parts, then the switch, on the map's stream: every replica switches at the switch's
  // sequence. Message ids make a retried publish a duplicate, not a second copy.
  const std::string id = "vocabulary/" + next->checksum_hex() + "/" + std::to_string(NowUnixMs());
  const std::vector<std::string> parts =
      cluster::EncodeVocabularyParts(*next, kVocabularyPartBytes);
  for (size_t i = 0; i < parts.size(); ++i) {
    auto published = PublishRecord(name, parts[i], id + "/" + std::to_string(i), until);
    if (!published.ok()) return ToGrpc(published.status());
  }
  const uint32_t count = uint32_t(parts.size());
  auto prepare = PublishRecord(name, cluster::EncodePrepareVocabulary(next->checksum(), count),
                               id + "/prepare", until);
  if (!prepare.ok()) return ToGrpc(prepare.status());
  AwaitPrepared(name, next->checksum(), Clock::now() + (until - Clock::now()) * 3 / 4);
  auto ack =
      PublishRecord(name, cluster::EncodeSwitchVocabulary(*source, count), id + "/switch", until);
  if (!ack.ok()) return ToGrpc(ack.status());
  spdlog::info(
      "map '{}': vocabulary {} learned on a replica ({} places, {:.1f} s), published in "
      "{} parts; the replicas switch at record {}",
      ForLog(name), next->checksum_hex(), source->places_offered, source->learn_ms / 1000,
      parts.size(), ack->sequence);
  // 3. Answered once a replica has switched.
  return AwaitSwitch(name, ack->sequence, &*next, until, response);
}

grpc::Status ClusterWorker::RevertVocabulary(const std::string& name, Deadline deadline,
                                             const std::atomic<bool>*,
                                             v1::MapVocabulary* response) {
  auto started = StartSwitch(name, deadline);
  if (!started.ok()) return ToGrpc(started.status());
  const Deadline until = started->until;
  // The previous vocabulary as the replicas have it after everything published so far.
  v1::MapVocabulary now;
  grpc::Status status = ReplicaVocabulary(name, started->stream_last, false, until, &now, nullptr);
  if (!status.ok()) return status;
  if (!now.has_previous()) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "map '" + name +
                            "' has no previous vocabulary: it never switched "
                            "vocabularies");
  }
  auto source = wire::VocabularySourceFromProto(now.previous(), "previous");
  if (!source.ok()) return ToGrpc(source.status());
  const std::string id =
      "vocabulary/" + Hex64(source->checksum) + "/" + std::to_string(NowUnixMs());
  auto prepare = PublishRecord(name, cluster::EncodePrepareVocabulary(source->checksum, 0),
                               id + "/prepare", until);
  if (!prepare.ok()) return ToGrpc(prepare.status());
  AwaitPrepared(name, source->checksum, Clock::now() + (until - Clock::now()) * 3 / 4);
  auto ack =
      PublishRecord(name, cluster::EncodeSwitchVocabulary(*source, 0), id + "/switch", until);
  if (!ack.ok()) return ToGrpc(ack.status());
  spdlog::info("map '{}': the replicas switch back to vocabulary {} at record {}", ForLog(name),
               Hex64(source->checksum), ack->sequence);
  return AwaitSwitch(name, ack->sequence, nullptr, until, response);
}

grpc::Status ClusterWorker::DeletePlace(const v1::DeletePlaceRequest& request, Deadline deadline) {
  deadline = Patient(deadline);
  // Does it exist? (A replica that applied the id answers; NOT_FOUND stands.)
  v1::GetPlaceRequest get;
  get.set_map(request.map());
  get.set_place_id(request.place_id());
  v1::Place place;
  if (grpc::Status found = GetPlace(get, deadline, &place); !found.ok()) return found;
  auto published = PublishRecord(request.map(), cluster::EncodeDeletePlace(request.place_id()),
                                 /*message_id=*/"", deadline);
  return published.ok() ? grpc::Status::OK : ToGrpc(published.status(), "deleting the place");
}

grpc::Status ClusterWorker::GetPlace(const v1::GetPlaceRequest& request, Deadline deadline,
                                     v1::Place* response) {
  // A place id is a stream sequence: a replica that applied it has it (or it was removed).
  auto read = [&] {
    return OnReplica("GetPlace", request.map(), request.place_id(), deadline,
                     ShardRpc(&ShardStub::GetPlace, request, response));
  };
  grpc::Status status = read();
  if (status.error_code() != grpc::StatusCode::NOT_FOUND || request.place_id() == 0) {
    return status;
  }
  // Read-your-writes: a place just acknowledged may not be applied yet. When no replica has
  // reported applying its id, wait (bounded) until one does, then ask again.
  const uint64_t id = request.place_id();
  auto applied = [id](const std::optional<cluster::MapView>& view) {
    if (!view) return true;  // deleted: the NOT_FOUND stands
    for (const auto& [shard, sequence] : view->applied) {
      if (sequence >= id) return true;
    }
    return false;
  };
  if (applied(view_->Map(request.map()))) return status;
  const auto left = std::max(Remaining(deadline), std::chrono::milliseconds(0));
  if (!view_->WaitFor(request.map(), applied,
                      std::chrono::steady_clock::now() +
                          std::min<std::chrono::milliseconds>(left, std::chrono::seconds(5)))) {
    return status;
  }
  return read();
}

grpc::Status ClusterWorker::ListPlaces(const v1::ListPlacesRequest& request, Deadline deadline,
                                       v1::ListPlacesResponse* response) {
  return OnReplica("ListPlaces", request.map(), 0, deadline,
                   ShardRpc(&ShardStub::ListPlaces, request, response));
}

grpc::Status ClusterWorker::GetDynamics(const v1::GetDynamicsRequest& request, Deadline deadline,
                                        v1::GetDynamicsResponse* response) {
  return OnReplica("GetDynamics", request.map(), 0, deadline,
                   ShardRpc(&ShardStub::GetDynamics, request, response));
}

Result<ClusterWorker::FrameRecord> ClusterWorker::Publish(const std::string& map,
                                                          const ProcessedFrame& frame,
                                                          const PlaceMetadata& metadata,
                                                          const std::string& message_id,
                                                          Deadline deadline) {
  // Encoded once: a retry publishes the same bytes (the same statistics' arrival time).
  const std::string record = frame.valid ? cluster::EncodeAddPlace(frame, metadata)
                                         : cluster::EncodeInvalidFrame(frame, metadata);
  auto ack = PublishRecord(map, record, message_id, deadline);
  if (!ack.ok()) return ack.status();
  // A duplicate: the stream holds the frame's first publish, which may differ from this one (a
  // new worker's Algorithm 1 or detector decided otherwise); the answer is that record's.
  if (ack->duplicate) return RecordedFrame(map, ack->sequence, message_id, deadline);
  FrameRecord out;
  if (frame.valid) {
    out.kind = FrameRecord::Kind::kPlace;
    out.place = uint32_t(ack->sequence);
  } else {
    out.kind = FrameRecord::Kind::kInvalid;
    out.rejection = frame.rejection;
  }
  return out;
}

grpc::Status ClusterWorker::Query(const MapEntry& map, const ProcessedFrame& frame,
                                  const PlaceMetadata& metadata, const v1::QueryRequest& request,
                                  Deadline deadline, v1::QueryResponse* out, StageTimings*) {
  const grpc::Status searched =
      Search(map.name, frame, metadata, request.options(), request.min_sequence(), deadline, out);
  if (!searched.ok()) return searched;
  // A map that counts query hits (PlaceMap::CountQueryHit's rule): durable before the answer,
  // as on a single server.
  const double above = map.map->options().count_query_hits_above;
  if (above > 0 && out->matches_size() > 0 && out->matches(0).score() > above) {
    auto counted = CountObservation(map.name, out->matches(0).place_id(), frame, metadata,
                                    /*message_id=*/"", Patient(deadline));
    if (!counted.ok()) return ToGrpc(counted.status(), "counting the query hit");
  }
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::WatchLoopClosures(
    const v1::WatchLoopClosuresRequest& request,
    const std::function<bool(const v1::LoopConstraint&)>& write,
    const std::function<grpc::Status()>& stop) {
  auto view = Lookup(request.map(), "map");
  if (!view.ok()) return ToGrpc(view.status());
  // Relayed from the most applied live replica. Replicas apply the same records in the same
  // order and number the constraints alike, so when one fails the next goes on from the last
  // sequence relayed + 1: nothing missed, nothing twice.
  v1::WatchLoopClosuresRequest next = request;
  uint64_t from = std::max<uint64_t>(request.from_sequence(), 1);
  std::string failed;  // the shard whose stream failed last
  grpc::Status last;
  for (int attempt = 0;; ++attempt) {
    if (grpc::Status stopped = stop(); !stopped.ok()) return stopped;
    if (attempt > 0) {
      // Not a spin while every replica is down: a pause that still watches the client.
      if (!request.follow() && attempt >= 10) return last;
      for (int i = 0; i < 4; ++i) {
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
        if (grpc::Status stopped = stop(); !stopped.ok()) return stopped;
      }
      retries_->Add({{"call", "WatchLoopClosures"}}).Increment();
    }
    auto replicas = Replicas(request.map(), 0);
    if (!replicas.ok()) {
      last = ToGrpc(replicas.status());
      continue;
    }
    const Replica* replica = &replicas->front();
    for (const Replica& other : *replicas) {
      if (other.shard != failed) {
        replica = &other;
        break;
      }
    }
    next.set_from_sequence(from);
    grpc::ClientContext context;
    const auto stub = cluster::v1::Shard::NewStub(ChannelTo(replica->address));
    auto reader = stub->WatchLoopClosures(&context, next);
    // The relay blocks in Read() while the replica has nothing to send: a watcher cancels it
    // when the client goes or the server drains.
    Mutex watch_mutex;
    CondVar watch_cv;
    bool relay_done = false;
    std::atomic<bool> stopped{false};
    std::thread watcher([&] {
      MutexLock lock(watch_mutex);
      while (!relay_done) {
        if (!stop().ok()) {
          stopped = true;
          context.TryCancel();
          return;
        }
        watch_cv.WaitFor(watch_mutex, std::chrono::milliseconds(250));
      }
    });
    v1::LoopConstraint message;
    bool client_gone = false;
    while (reader->Read(&message)) {
      if (message.sequence() != 0) {
        from = message.sequence() + 1;
      } else {
        from = std::max(from, message.caught_up_to() + 1);
      }
      if (!write(message)) {
        client_gone = true;
        context.TryCancel();
        break;
      }
    }
    const grpc::Status status = reader->Finish();
    {
      MutexLock lock(watch_mutex);
      relay_done = true;
    }
    watch_cv.NotifyAll();
    watcher.join();
    if (client_gone) return grpc::Status(grpc::StatusCode::CANCELLED, "the client went away");
    if (stopped) return stop();
    if (status.ok()) return status;  // not following: the log's end
    switch (status.error_code()) {
      case grpc::StatusCode::UNAVAILABLE:
      case grpc::StatusCode::DEADLINE_EXCEEDED:
      case grpc::StatusCode::CANCELLED:  // the shard stopping or restarting
      case grpc::StatusCode::UNKNOWN:
      case grpc::StatusCode::INTERNAL:
        spdlog::warn(
            "WatchLoopClosures on map '{}': shard '{}' ({}) ended the relay with {}: {}; "
            "going on from sequence {} on another replica",
            request.map(), replica->shard, replica->address, int(status.error_code()),
            ForLog(status.error_message()), from);
        failed = replica->shard;
        last = status;
        continue;
      default:
        return status;  // NOT_FOUND (deleted), CORRUPTION, ...
    }
  }
}

grpc::Status ClusterWorker::TakeCheckpoint(const std::string& map, const cluster::MapView& view,
                                           const std::string& spool, Deadline deadline,
                                           cluster::SnapshotManifest* manifest) {
  const Stopwatch started;
  // 1. The most applied replica's checkpoint (its applier paused meanwhile: Shard.Checkpoint).
  cluster::v1::CheckpointRequest request;
  request.set_map(map);
  request.set_create_revision(view.create_revision);
  cluster::FetchedCheckpoint fetched;
  const grpc::Status got = OnReplica(
      "Checkpoint", map, 0, deadline,
      [&](const std::shared_ptr<grpc::Channel>& channel, Deadline until) {
        grpc::ClientContext context;
        context.set_deadline(until);
        const auto stub = cluster::v1::Shard::NewStub(channel);
        auto read = cluster::FetchCheckpoint(stub.get(), &context, request, spool, "a replica");
        if (!read.ok()) return ToGrpc(read.status());
        fetched = *read;
        return grpc::Status::OK;
      });
  if (!got.ok()) return got;
  const double fetch_s = started.ElapsedMs() / 1e3;
  // 2. Verified here, as a single server verifies a snapshot it makes.
  if (grpc::Status checked = CheckArchive(spool, false, manifest); !checked.ok()) return checked;
  manifest->base = fetched.applied;
  manifest->config_json = view.info.config_json;
  spdlog::info(
      "checkpoint of cluster map '{}' at record {}: {} bytes (fetched {:.2f} s, verified "
      "{:.2f} s)",
      ForLog(map), fetched.applied, fetched.bytes, fetch_s, started.ElapsedMs() / 1e3 - fetch_s);
  return grpc::Status::OK;
}

}  // namespace placedb::server
