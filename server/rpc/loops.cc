// WatchLoopClosures: a map's loop-closure log (core/storage/loop_log.h) as a server stream,
// through the backend (server/backend/place_reads.h StreamLoopLog on this server's maps).
#include "proto/status.h"
#include "server/rpc/call_support.h"

namespace placedb::server {

grpc::Status PlaceDbService::WatchLoopClosuresStream(
    grpc::ServerContext* context, const v1::WatchLoopClosuresRequest* request,
    const std::function<bool(const v1::LoopConstraint&)>& write) {
  static constexpr char kMethod[] = "WatchLoopClosures";
  CallScope scope(this);
  if (draining_flag_) return Finish(kMethod, context, Unavailable());
  // A stream like Ingest's (max_concurrent_streams; a client that takes nothing is closed), but
  // a follower's silence while nothing is found is the server's, never idle.
  Watch watch(context, kMethod);
  const WatchScope listed(this, &watch);
  if (!listed.status().ok()) return Finish(kMethod, context, listed.status());
  watch.HeaderArrived();
  watch.HeldBack();
  auto send = [&](const v1::LoopConstraint& message) {
    watch.Writing();
    const bool sent = write(message);
    watch.Written();
    return sent;
  };
  auto stop = [&]() -> grpc::Status {
    if (auto closed = watch.Closed()) return *closed;
    if (context->IsCancelled()) return Cancelled(context, "while following the loop log");
    if (draining_flag_) return Unavailable();
    return grpc::Status::OK;
  };
  const grpc::Status status = backend_->WatchLoopClosures(*request, send, stop);
  return Finish(kMethod, context, wire::HidePaths(status, config_.data_dir));
}

}  // namespace placedb::server
