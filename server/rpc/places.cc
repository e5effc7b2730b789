// Places: GetPlace, ListPlaces, DeletePlace, GetDynamics.
#include "proto/status.h"
#include "server/rpc/call_support.h"

namespace placedb::server {

grpc::Status PlaceDbService::GetPlace(grpc::ServerContext* context,
                                      const v1::GetPlaceRequest* request, v1::Place* response) {
  CallScope scope(this);
  return Finish("GetPlace", context, backend_->GetPlace(*request, DeadlineOf(context), response));
}

grpc::Status PlaceDbService::ListPlaces(grpc::ServerContext* context,
                                        const v1::ListPlacesRequest* request,
                                        v1::ListPlacesResponse* response) {
  CallScope scope(this);
  return Finish("ListPlaces", context,
                backend_->ListPlaces(*request, DeadlineOf(context), response));
}

grpc::Status PlaceDbService::DeletePlace(grpc::ServerContext* context,
                                         const v1::DeletePlaceRequest* request,
                                         v1::DeletePlaceResponse*) {
  CallScope scope(this);
  if (draining_flag_) return Finish("DeletePlace", context, Unavailable());
  if (request->place_id() == 0) {
    // After the map: an unknown map is the caller's first problem.
    if (auto entry = backend_->Map(request->map(), "map"); !entry.ok()) {
      return Finish("DeletePlace", context, wire::ToGrpc(entry.status()));
    }
    return Finish("DeletePlace", context, Invalid("place_id: is required (ids start at 1)"));
  }
  return Finish("DeletePlace", context, backend_->DeletePlace(*request, DeadlineOf(context)));
}

grpc::Status PlaceDbService::GetDynamics(grpc::ServerContext* context,
                                         const v1::GetDynamicsRequest* request,
                                         v1::GetDynamicsResponse* response) {
  CallScope scope(this);
  return Finish("GetDynamics", context,
                backend_->GetDynamics(*request, DeadlineOf(context), response));
}

}  // namespace placedb::server
