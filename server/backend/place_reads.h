// The read RPCs of placedb.v1 on one open map (GetPlace, ListPlaces, GetDynamics), shared by the
// single-node backend (server/backend/local_backend.cc) and cluster mode's shard
// (server/cluster/shard.h), so both answer them the same way.
//
// Errors are values with the code the RPC returns (proto/status.h ToGrpc): INVALID_ARGUMENT for
// a bad request field (named), NOT_FOUND for an absent place, the storage's codes otherwise.
// Read-only: nothing changes. Thread-safe as PlaceMap's readers are.
#pragma once

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

}  // namespace placedb::server
