// ClusterWorker's admin calls (server/cluster/worker.h): ScrubMap and RecoverMap on every live
// replica, and snapshots kept in the cluster (server/cluster/snapshot_archives.h).
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>

#include "core/base/map_name.h"
#include "core/base/text.h"
#include "core/base/timing.h"
#include "proto/cluster.grpc.pb.h"
#include "proto/convert_config.h"
#include "proto/status.h"
#include "server/cluster/worker.h"

namespace placedb::server {

using Clock = std::chrono::system_clock;
using wire::ToGrpc;

namespace {

// Admin calls have no deadline of their own: a large map's scrub, rebuild, checkpoint or archive
// transfer takes minutes.
constexpr auto kAdminTime = std::chrono::minutes(30);

std::string StatusText(const grpc::Status& status) {
  return wire::FromGrpc(status).ToString();
}

}  // namespace

grpc::Status ClusterWorker::ScrubMap(const std::string& name, v1::ScrubReport* response) {
  auto view = Lookup(name, "name");
  if (!view.ok()) return ToGrpc(view.status());
  auto replicas = Replicas(name, 0);
  if (!replicas.ok()) return ToGrpc(replicas.status());
  // Every live replica: one's damage is never hidden by another's clean report.
  bool clean = true;
  grpc::Status last;
  size_t answered = 0;
  cluster::v1::ReplicaRequest request;
  request.set_map(name);
  for (const Replica& replica : *replicas) {
    v1::ReplicaScrubReport* part = response->add_replicas();
    part->set_shard(replica.shard);
    grpc::ClientContext context;
    context.set_deadline(Clock::now() + kAdminTime);
    const grpc::Status status = cluster::v1::Shard::NewStub(ChannelTo(replica.address))
                                    ->ScrubMap(&context, request, part->mutable_report());
    if (!status.ok()) {
      part->clear_report();
      part->set_error(StatusText(status));
      clean = false;
      last = status;
      if (status.error_code() == grpc::StatusCode::DATA_LOSS) {
        ++answered;  // damaged: that is its report
        v1::ScrubReport::DamagedFile* file = response->add_damaged_files();
        file->set_file("shard " + replica.shard);
        file->set_reason(status.error_message());
      }
      continue;
    }
    ++answered;
    const v1::ScrubReport& report = part->report();
    response->set_places_checked(response->places_checked() + report.places_checked());
    response->set_files_checked(response->files_checked() + report.files_checked());
    for (const auto& damaged : report.damaged_places()) {
      auto* out = response->add_damaged_places();
      out->set_place_id(damaged.place_id());
      out->set_reason("shard " + replica.shard + ": " + damaged.reason());
    }
    for (const auto& damaged : report.damaged_files()) {
      auto* out = response->add_damaged_files();
      out->set_file(damaged.file());
      out->set_reason("shard " + replica.shard + ": " + damaged.reason());
    }
    clean = clean && report.clean();
  }
  if (answered == 0) return last;  // no replica could be scrubbed: that is the answer
  response->set_clean(clean);
  spdlog::log(clean ? spdlog::level::info : spdlog::level::err,
              "map '{}' scrubbed on {} replicas: {}", ForLog(name), replicas->size(),
              clean ? "no damage" : "not clean");
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::RecoverMap(const v1::RecoverMapRequest& request,
                                       v1::RecoverMapResponse* response) {
  const std::string& name = request.name();
  if (!request.accept_data_loss()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "accept_data_loss: must be set: recovering map '" + name +
                            "' rebuilds its damaged replicas");
  }
  auto view = Lookup(name, "name");
  if (!view.ok()) return ToGrpc(view.status());
  auto replicas = Replicas(name, 0);
  if (!replicas.ok()) return ToGrpc(replicas.status());
  cluster::v1::RecoverReplicaRequest ask;
  ask.set_map(name);
  ask.set_accept_data_loss(true);
  std::string found;  // what each damaged replica had and became
  grpc::Status last;
  size_t damaged = 0, failed = 0;
  // One replica after the other: a rebuilt one restores from a peer that is not being rebuilt.
  for (const Replica& replica : *replicas) {
    v1::ReplicaRecovery* part = response->add_replicas();
    grpc::ClientContext context;
    context.set_deadline(Clock::now() + kAdminTime);
    const grpc::Status status =
        cluster::v1::Shard::NewStub(ChannelTo(replica.address))->RecoverMap(&context, ask, part);
    part->set_shard(replica.shard);
    if (!status.ok()) {
      part->set_error(StatusText(status));
      last = status;
      ++failed;
      continue;
    }
    if (!part->damaged()) continue;
    ++damaged;
    if (!found.empty()) found += "; ";
    found += "shard " + replica.shard + ": " + part->found() + " -> ";
    if (!part->error().empty()) {
      found += "NOT rebuilt: " + part->error();
      ++failed;
    } else {
      found += part->restored_from().empty()
                   ? "rebuilt from the map's stream"
                   : "rebuilt from the checkpoint of shard " + part->restored_from();
    }
  }
  if (damaged == 0) {
    if (failed > 0) return last;
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "map '" + name + "' is not damaged (" + std::to_string(replicas->size()) +
                            " live replicas scrubbed clean)");
  }
  // Nothing acknowledged is lost: a rebuilt replica has every record of the stream again.
  v1::MapDamage* accepted = response->mutable_accepted();
  accepted->set_reason(found);
  accepted->set_recovered_unix_ms(NowUnixMs());
  spdlog::log(failed > 0 ? spdlog::level::err : spdlog::level::warn, "map '{}' recovered: {}",
              ForLog(name), found);
  (void)GetMap(name, Clock::now() + std::chrono::seconds(10), response->mutable_map());
  return grpc::Status::OK;
}

// ---- Snapshots (issue 35)
// ------------------------------------------------------------------------

grpc::Status ClusterWorker::Snapshots(std::shared_ptr<SnapshotStore>* store) {
  *store = local_->snapshots();
  if (!*store) return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is shutting down");
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::CheckArchive(const std::string& path, bool open,
                                         cluster::SnapshotManifest* manifest) {
  std::shared_ptr<SnapshotStore> store;
  if (grpc::Status kept = Snapshots(&store); !kept.ok()) return kept;
  auto imported = local_->ImportSnapshot(path);
  if (!imported.ok()) return wire::HidePaths(ToGrpc(imported.status()), config_.data_dir);
  struct Forget {
    SnapshotStore* store;
    std::string id;
    ~Forget() { (void)store->Delete(id); }
  } forget{store.get(), imported->id};
  manifest->info = *imported;
  if (!open) return grpc::Status::OK;
  // An upload: where its places end and its configuration, from the map itself.
  static std::atomic<uint64_t> checks{0};
  const std::string scratch = "placedb-snapshot-check-" + std::to_string(++checks);
  auto entry = local_->RestoreSnapshot(imported->id, scratch);
  if (!entry.ok()) return wire::HidePaths(ToGrpc(entry.status()), config_.data_dir);
  const PlaceMap& map = *(*entry)->map;
  manifest->base = std::max<uint64_t>(map.applied_sequence(), map.database()->next_id() - 1);
  v1::MapConfig config;
  wire::MapConfigToProto(map.info().options, (*entry)->settings, (*entry)->vocabulary_name,
                         &config);
  google::protobuf::util::JsonPrintOptions print;
  print.preserve_proto_field_names = true;
  const bool printed =
      google::protobuf::util::MessageToJsonString(config, &manifest->config_json, print).ok();
  if (Status removed = local_->Delete(scratch); !removed.ok()) {
    spdlog::warn("worker: the scratch map '{}' stays: {}", scratch, removed.ToString());
  }
  if (!printed) return grpc::Status(grpc::StatusCode::INTERNAL, "cannot encode the configuration");
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::CreateSnapshot(const std::string& map, SnapshotInfo* info) {
  auto view = Lookup(map, "map");
  if (!view.ok()) return ToGrpc(view.status());
  std::shared_ptr<SnapshotStore> store;
  if (grpc::Status kept = Snapshots(&store); !kept.ok()) return kept;
  const Deadline deadline = Clock::now() + kAdminTime;
  const Stopwatch started;
  ScratchFile spool(store->path(), "cluster");
  cluster::SnapshotManifest manifest;
  if (grpc::Status taken = TakeCheckpoint(map, *view, spool.path, deadline, &manifest);
      !taken.ok()) {
    return taken;
  }
  const double checkpoint_s = started.ElapsedMs() / 1e3;
  // 3. Stored in the cluster.
  if (Status put = archives_->Put(spool.path, &manifest, deadline); !put.ok()) return ToGrpc(put);
  *info = manifest.info;
  spdlog::info(
      "snapshot '{}' of cluster map '{}' at record {}: {} places, archive {} bytes (checkpoint "
      "and verification {:.2f} s, storing {:.2f} s)",
      info->id, ForLog(map), manifest.base, info->places, manifest.archive_bytes, checkpoint_s,
      started.ElapsedMs() / 1e3 - checkpoint_s);
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::ListSnapshots(std::vector<SnapshotInfo>* out) {
  auto listed = archives_->List();
  if (!listed.ok()) return ToGrpc(listed.status());
  for (cluster::SnapshotManifest& manifest : *listed) out->push_back(std::move(manifest.info));
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::DeleteSnapshot(const std::string& id) {
  return ToGrpc(archives_->Delete(id));
}

grpc::Status ClusterWorker::WriteSnapshotArchive(
    const std::string& id, size_t chunk_bytes,
    const std::function<Status(const SnapshotInfo& info, uint64_t bytes)>& start,
    const std::function<Status(std::string_view)>& sink) {
  auto manifest = archives_->Get(id);
  if (!manifest.ok()) return ToGrpc(manifest.status());
  if (Status started = start(manifest->info, manifest->archive_bytes); !started.ok()) {
    return ToGrpc(started);
  }
  return ToGrpc(
      archives_->Read(*manifest, Clock::now() + kAdminTime, [&](std::string_view stored) -> Status {
        for (size_t at = 0; at < stored.size(); at += chunk_bytes) {
          PLACEDB_RETURN_IF_ERROR(sink(stored.substr(at, chunk_bytes)));
        }
        return Status::Ok();
      }));
}

grpc::Status ClusterWorker::ImportSnapshot(const std::string& path, SnapshotInfo* info) {
  cluster::SnapshotManifest manifest;
  if (grpc::Status checked = CheckArchive(path, true, &manifest); !checked.ok()) return checked;
  if (Status put = archives_->Put(path, &manifest, Clock::now() + kAdminTime); !put.ok()) {
    return ToGrpc(put);
  }
  *info = manifest.info;
  return grpc::Status::OK;
}

grpc::Status ClusterWorker::RestoreSnapshot(const v1::RestoreSnapshotRequest& request,
                                            v1::MapDescription* response) {
  const std::string& name = request.new_map();
  if (Status valid = ValidateMapName(name); !valid.ok()) {
    return ToGrpc(valid.WithContext("new_map"));
  }
  auto manifest = archives_->Get(request.id());
  if (!manifest.ok()) return ToGrpc(manifest.status());
  // What the map needs of the workers (its vocabulary), refused before anything is made.
  v1::MapConfig config;
  if (!google::protobuf::util::JsonStringToMessage(manifest->config_json, &config).ok()) {
    return grpc::Status(grpc::StatusCode::DATA_LOSS,
                        "snapshot '" + request.id() + "': its map configuration does not parse");
  }
  if (auto vocabulary = local_->ResolveVocabulary(config.vocabulary()); !vocabulary.ok()) {
    return ToGrpc(Status::FailedPrecondition("snapshot '" + request.id() + "' of map '" +
                                             manifest->info.map +
                                             "': " + vocabulary.status().message()));
  }
  const Stopwatch started;
  cluster::MapRecordInfo info{.config_json = manifest->config_json,
                              .stream = cluster::StreamName(cluster_.name, name),
                              .created_unix_ms = NowUnixMs(),
                              .snapshot = request.id(),
                              .snapshot_base = manifest->base};
  const Deadline deadline = Clock::now() + kAdminTime;
  if (grpc::Status made = MakeMap(name, info, deadline, response); !made.ok()) return made;
  // Answered once a replica serves the snapshot's places (restored the archive; an empty
  // snapshot: placed).
  const auto served = [&](const std::optional<cluster::MapView>& view) {
    if (!view) return true;  // deleted meanwhile
    for (const auto& [shard, applied] : view->applied) {
      if (applied >= manifest->base) return true;
    }
    return false;
  };
  // Bounded; and not waited for once the snapshot is gone (its replicas cannot restore it then:
  // GetMap shows them unavailable).
  const auto until = std::chrono::steady_clock::now() + kAdminTime;
  bool restored = false;
  while (!restored && std::chrono::steady_clock::now() < until) {
    restored = view_->WaitFor(
        name, served, std::min(until, std::chrono::steady_clock::now() + std::chrono::seconds(5)));
    if (!restored && archives_->Get(request.id()).status().code() == StatusCode::kNotFound) break;
  }
  spdlog::info("snapshot '{}' restored as cluster map '{}' (stream from {}): {} in {:.2f} s",
               request.id(), ForLog(name), manifest->base + 1,
               restored ? "a replica serves it" : "no replica reported it yet",
               started.ElapsedMs() / 1e3);
  return GetMap(name, deadline, response);
}

}  // namespace placedb::server
