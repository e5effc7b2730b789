#include "server/backend/place_reads.h"

#include <algorithm>
#include <chrono>
#include <optional>

#include "proto/convert_config.h"
#include "proto/convert_dynamics.h"
#include "proto/convert_frame.h"
#include "proto/convert_result.h"
#include "proto/status.h"

namespace placedb::server {

Status ReadPlace(const PlaceMap& map, const v1::GetPlaceRequest& request, v1::Place* response) {
  if (request.place_id() == 0) {
    return Status::InvalidArgument("place_id: is required (ids start at 1)");
  }
  auto place = map.GetPlace(request.place_id());
  if (!place.ok()) return place.status();
  wire::PlaceRecordToProto(place->record, response);
  if (request.include_features()) {
    wire::PlaceFeaturesToProto(place->payload.features, response);
    const FrameGeometry& geometry = place->payload.geometry;
    if (geometry.camera) wire::CameraToProto(*geometry.camera, response->mutable_camera());
    response->mutable_keypoint_depth_m()->Add(geometry.depth_m.begin(), geometry.depth_m.end());
  }
  auto dynamics = map.GetDynamics(request.place_id());
  if (!dynamics.ok()) return dynamics.status();
  wire::DynamicsToProto(*dynamics, response->mutable_dynamics());
  if (request.include_thumbnail()) {
    auto thumbnail = map.GetThumbnail(request.place_id());
    if (!thumbnail.ok()) return thumbnail.status();
    if (thumbnail->has_value()) wire::ThumbnailToProto(**thumbnail, response->mutable_thumbnail());
  }
  return Status::Ok();
}

Status ListPlacesOf(const PlaceMap& map, const v1::ListPlacesRequest& request,
                    v1::ListPlacesResponse* response) {
  auto listing = wire::PlaceListingFromProto(request);
  if (!listing.ok()) return listing.status();
  const PlacePage page = map.database()->ListPlacesBefore(listing->before, listing->limit,
                                                          listing->filter, listing->max_examined);
  response->mutable_places()->Reserve(int(page.places.size()));
  for (const auto& record : page.places) wire::PlaceRecordToProto(*record, response->add_places());
  response->set_next_before_place_id(page.next_before);
  return Status::Ok();
}

Status ReadDynamics(const PlaceMap& map, const v1::GetDynamicsRequest& request,
                    v1::GetDynamicsResponse* response) {
  auto options = wire::RankOptionsFromProto(request);
  if (!options.ok()) return options.status();
  auto aggregate = map.MapDynamics();
  if (!aggregate.ok()) return aggregate.status();
  wire::DynamicsToProto(*aggregate, response->mutable_map());
  auto invalid = map.InvalidDynamics();
  if (!invalid.ok()) return invalid.status();
  wire::DynamicsToProto(*invalid, response->mutable_invalid());
  // One pass over the map's places; the ranking keeps offset + limit entries.
  DynamicsRanking ranking(*options);
  const Status scanned = map.ForEachPlaceDynamics([&](PlaceId id, const PlaceDynamics& d) {
    if (options->near.active()) {  // the poses are in the places' records (memory)
      const auto record = map.database()->Get(id);
      if (!record || !record->metadata.pose ||
          !options->near.Contains(record->metadata.pose->position)) {
        return true;
      }
    }
    ranking.Add(id, d);
    return true;
  });
  if (!scanned.ok()) return scanned;
  for (const RankedPlace& ranked : ranking.Page()) {
    v1::RankedPlace* out = response->add_places();
    out->set_place_id(ranked.place);
    out->set_score(ranked.score);
    out->set_support(ranked.support);
    if (request.include_statistics()) {
      auto d = map.GetDynamics(ranked.place);
      if (d.status().code() == StatusCode::kNotFound) continue;  // removed meanwhile
      if (!d.ok()) return d.status();
      wire::DynamicsToProto(*d, out->mutable_statistics());
    }
  }
  response->set_ranked(ranking.ranked());
  const uint64_t end = uint64_t(options->offset) + options->limit;
  response->set_next_offset(end < ranking.ranked() ? uint32_t(end) : 0);
  return Status::Ok();
}

grpc::Status StreamLoopLog(const std::string& name, const PlaceMap& map,
                           const v1::WatchLoopClosuresRequest& request,
                           const std::function<bool(const v1::LoopConstraint&)>& write,
                           const std::function<grpc::Status()>& stop) {
  constexpr size_t kReadBatch = 256;
  // A follower looks at the client and the server's shutdown this often while nothing is found
  // (a new constraint wakes it at once).
  constexpr auto kFollowPoll = std::chrono::milliseconds(250);
  LoopFilter filter;
  filter.agents.assign(request.agents().begin(), request.agents().end());
  filter.inter_agent_only = request.inter_agent_only();
  filter.min_sequence_gap = request.min_sequence_gap();
  uint64_t next = std::max<uint64_t>(request.from_sequence(), 1);
  uint64_t delivered = 0;          // the last constraint sent
  std::optional<uint64_t> marked;  // the last caught_up_to sent
  const grpc::Status gone(grpc::StatusCode::CANCELLED, "the client went away");
  v1::LoopConstraint message;
  while (true) {
    if (grpc::Status stopped = stop(); !stopped.ok()) return stopped;
    uint64_t scanned = 0;
    auto constraints = map.ReadLoops(next, kReadBatch, filter, &scanned);
    if (!constraints.ok()) return wire::ToGrpc(constraints.status());
    for (const LoopConstraint& constraint : *constraints) {
      message.Clear();
      wire::LoopConstraintToProto(constraint, &message);
      if (!write(message)) return gone;
      delivered = constraint.sequence;
    }
    next = scanned + 1;
    if (constraints->size() == kReadBatch) continue;  // more in the log
    if (!request.follow()) return grpc::Status::OK;
    if (!marked || scanned > std::max(delivered, *marked)) {
      message.Clear();
      message.set_caught_up_to(scanned);
      if (!write(message)) return gone;
      marked = scanned;
    }
    bool deleted = false;
    map.WaitForLoops(scanned, std::chrono::steady_clock::now() + kFollowPoll, &deleted);
    if (deleted) {
      return grpc::Status(grpc::StatusCode::NOT_FOUND, "map '" + name + "' was deleted");
    }
  }
}

}  // namespace placedb::server
