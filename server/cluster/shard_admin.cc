// The Shard's admin RPCs (server/cluster/shard.h): ScrubMap and RecoverMap of one replica.
#include <grpcpp/grpcpp.h>
#include <spdlog/spdlog.h>

#include "core/base/text.h"
#include "core/base/timing.h"
#include "proto/convert_config.h"
#include "proto/status.h"
#include "server/cluster/shard_impl.h"

namespace placedb::cluster {

using wire::ToGrpc;

namespace {

// What a scrub found, in one line (the recovery's `found`).
std::string DamageOf(const ScrubReport& report) {
  std::string out = std::to_string(report.damaged_places.size()) + " of " +
                    std::to_string(report.places_checked) + " places and " +
                    std::to_string(report.damaged_files.size()) + " of " +
                    std::to_string(report.files_checked) + " files damaged";
  if (!report.damaged_files.empty()) {
    out += "; first: " + report.damaged_files[0].file + ": " + report.damaged_files[0].reason;
  } else if (!report.damaged_places.empty()) {
    out += "; first: place " + std::to_string(report.damaged_places[0].id) + ": " +
           report.damaged_places[0].reason;
  }
  return out;
}

}  // namespace

grpc::Status Shard::Impl::ScrubReplica(const cv1::ReplicaRequest& request,
                                       pv1::ScrubReport* response) {
  std::shared_ptr<PlaceMap> map;
  {
    MutexLock lock(mutex_);
    auto it = replicas_.find(request.map());
    if (it == replicas_.end()) {
      return GrpcError(grpc::StatusCode::NOT_FOUND,
                       "map '" + request.map() + "' is not held by shard " + options_.shard_id);
    }
    if (it->second->damaged) {
      return GrpcError(
          grpc::StatusCode::DATA_LOSS,
          "map '" + request.map() + "' on shard " + options_.shard_id + ": " + it->second->problem);
    }
    map = it->second->map;
    if (!map) {
      return GrpcError(grpc::StatusCode::UNAVAILABLE, "map '" + request.map() + "' on shard " +
                                                          options_.shard_id +
                                                          " is not open: " + it->second->problem);
    }
  }
  // Online, as on a single server: the applier goes on (a scrub reads a consistent view).
  auto report = map->Scrub(/*threads=*/2);
  if (!report.ok()) return ToGrpc(report.status());
  wire::ScrubReportToProto(*report, response);
  if (!report->clean()) {
    spdlog::error("shard {}: map '{}' scrubbed: {}", options_.shard_id, ForLog(request.map()),
                  DamageOf(*report));
  }
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::RecoverReplica(const cv1::RecoverReplicaRequest& request,
                                         pv1::ReplicaRecovery* response) {
  const std::string& name = request.map();
  response->set_shard(options_.shard_id);
  if (!request.accept_data_loss()) {
    return GrpcError(
        grpc::StatusCode::INVALID_ARGUMENT,
        "accept_data_loss: must be set: recovering map '" + name + "' replaces a damaged replica");
  }
  // No reconcile opens or drops replicas meanwhile; the applier is stopped by the Drop below
  // before anything is deleted, so no record is applied to a replica being rebuilt.
  MutexLock lifecycle(lifecycle_mutex_);
  std::shared_ptr<PlaceMap> map;
  std::string found;
  {
    MutexLock lock(mutex_);
    auto it = replicas_.find(name);
    if (it == replicas_.end()) {
      return GrpcError(grpc::StatusCode::NOT_FOUND,
                       "map '" + name + "' is not held by shard " + options_.shard_id);
    }
    map = it->second->map;
    if (!map && !it->second->damaged) {
      return GrpcError(grpc::StatusCode::UNAVAILABLE,
                       "map '" + name + "' on shard " + options_.shard_id +
                           " is not open but not damaged: " + it->second->problem);
    }
    if (!map) found = it->second->problem;
  }
  if (map) {
    auto report = map->Scrub(/*threads=*/2);
    if (!report.ok()) return ToGrpc(report.status());
    if (report->clean()) return grpc::Status::OK;  // not damaged: left alone
    found = DamageOf(*report);
  }
  map.reset();
  response->set_damaged(true);
  response->set_found(found);
  spdlog::warn("shard {}: map '{}' is damaged ({}): rebuilding the replica", options_.shard_id,
               ForLog(name), found);
  Stopwatch clock;
  // As a replica that leaves this shard, then comes back: Drop stops its consumer and applier
  // and deletes the local copy (a damaged one is not open: deleted here), the reconcile makes it
  // again from a live peer's checkpoint (verified on import, so a damaged peer's is refused) or
  // by replaying the map's stream, which holds every acknowledged record.
  Drop(name);
  const auto listed = dir_->ListMaps();
  if (std::find(listed.begin(), listed.end(), name) != listed.end()) {
    if (Status deleted = dir_->DeleteMap(name); !deleted.ok()) {
      response->set_error("deleting the damaged copy: " + deleted.ToString());
      return grpc::Status::OK;
    }
  }
  Reconcile();
  MutexLock lock(mutex_);
  auto it = replicas_.find(name);
  if (it == replicas_.end() || !it->second->map) {
    response->set_error(it == replicas_.end() ? "no longer placed here" : it->second->problem);
    return grpc::Status::OK;
  }
  response->set_rebuilt(true);
  response->set_restored_from(it->second->restored_from);
  response->set_applied_sequence(it->second->apply->applied_sequence());
  spdlog::warn("shard {}: map '{}' rebuilt in {:.2f} s from {} (applied {})", options_.shard_id,
               ForLog(name), clock.ElapsedMs() / 1e3,
               it->second->restored_from.empty() ? std::string("its stream")
                                                 : "the checkpoint of " + it->second->restored_from,
               it->second->apply->applied_sequence());
  return grpc::Status::OK;
}

}  // namespace placedb::cluster
