// The read RPCs of placedb.v1 on one open map (GetPlace, ListPlaces, GetDynamics,
// WatchLoopClosures), shared by the
// single-node backend (server/backend/local_backend.cc) and cluster mode's shard
// (server/cluster/shard.h), so both answer them the same way.
//
// Errors are values with the code the RPC returns (proto/status.h ToGrpc): INVALID_ARGUMENT for
// a bad request field (named), NOT_FOUND for an absent place, the storage's codes otherwise.
// Read-only: nothing changes. Thread-safe as PlaceMap's readers are.
#pragma once

#include <grpcpp/support/status.h>

#include <functional>
#include <string>

#include "core/base/status.h"
#include "core/storage/map_store.h"
#include "proto/placedb.pb.h"

namespace placedb::server {

namespace v1 = ::placedb::v1;

Status ReadPlace(const PlaceMap& map, const v1::GetPlaceRequest& request, v1::Place* response);
Status ListPlacesOf(const PlaceMap& map, const v1::ListPlacesRequest& request,
                    v1::ListPlacesResponse* response);
Status ReadDynamics(const PlaceMap& map, const v1::GetDynamicsRequest& request,
                    v1::GetDynamicsResponse* response);

// WatchLoopClosures on map `name` (core/storage/loop_log.h): the constraints request.filters
// accept, from request.from_sequence on, in order, to `write` (false: the client is gone,
// CANCELLED). Without request.follow, OK at the log's end. With it: a message with only
// caught_up_to once caught up (and again when filtered-out constraints moved the position past
// the last one sent), then each new constraint once durable; `stop` is asked before every read
// and at least every 250 ms while waiting, and a non-OK answer ends the stream with it. NOT_FOUND
// when the map is deleted meanwhile; CORRUPTION naming the sequence for a damaged constraint.
grpc::Status StreamLoopLog(const std::string& name, const PlaceMap& map,
                           const v1::WatchLoopClosuresRequest& request,
                           const std::function<bool(const v1::LoopConstraint&)>& write,
                           const std::function<grpc::Status()>& stop);

}  // namespace placedb::server
