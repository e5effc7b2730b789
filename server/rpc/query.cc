// Query, and the first half of every frame (decode, detect, extract, depth, filter, transform)
// that Query and Ingest share: Prepare.
#include <future>

#include "core/detect/detector.h"
#include "proto/convert_config.h"
#include "proto/convert_frame.h"
#include "proto/convert_result.h"
#include "proto/status.h"
#include "server/rpc/call_support.h"
#include "server/rpc/frame_memory.h"

namespace placedb::server {

using wire::CheckFeatureType;
using wire::DecodeObservation;
using wire::TimingsToProto;
using wire::ToGrpc;

namespace {

// Colour for the detector, and for GrabCut when the map refines the agent's boxes with it.
bool DecodesInColor(const MapEntry& map, const v1::Observation& observation) {
  const ServiceMapSettings& settings = map.settings;
  const bool server_boxes = settings.detection_enabled && settings.box_source != BoxSource::kAgent;
  // A map that keeps thumbnails keeps them in colour.
  return server_boxes || map.map->options().thumbnails.enabled ||
         (settings.detection_enabled && observation.boxes_size() > 0 &&
          map.map->database()->config().box_refinement.method == BoxRefinement::kGrabCut);
}

}  // namespace

grpc::Status PlaceDbService::ChargeFrame(grpc::ServerContext* context, const MapEntry& map,
                                         const v1::Observation& observation, const char* what,
                                         MemoryBudget::Reservation* reservation) {
  const uint64_t bytes = EstimateFrameBytes(observation, map.map->database()->config().feature_type,
                                            DecodesInColor(map, observation));
  const auto until = QueueWaitUntil(context, config_.limits.memory_wait_ms);
  const auto expired = [context] { return Expired(context); };
  if (*reservation) {
    if (reservation->Resize(bytes, until, expired)) return grpc::Status::OK;
  } else if (auto reserved = budget_->Reserve(bytes, what, until, expired); reserved.ok()) {
    *reservation = std::move(reserved).value();
    return grpc::Status::OK;
  }
  if (Expired(context)) return Cancelled(context, "while waiting for memory");
  return ToGrpc(budget_->Exhausted(bytes, what));
}

grpc::Status PlaceDbService::Prepare(grpc::ServerContext* context, const MapEntry& map,
                                     const v1::Observation& observation, const std::string& field,
                                     FrameRole role, Work* work, bool keep_dropped_keypoints) {
  const auto expired = [&] { return work->expiry ? (*work->expiry)() : Expired(context); };
  if (expired()) return Cancelled(context, "before decoding");
  const ServiceMapSettings& settings = map.settings;
  if (Status typed = CheckFeatureType(observation, map.map->database()->config().feature_type,
                                      map.name, field);
      !typed.ok()) {
    return ToGrpc(typed);
  }
  const bool server_boxes = settings.detection_enabled && settings.box_source != BoxSource::kAgent;
  if (server_boxes && !detector_) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "map '" + map.name + "' takes boxes from the server's detector (" +
                            BoxSourceName(settings.box_source) +
                            "), which is off on this server (configure detector.model)");
  }
  Stopwatch stage;
  const bool color = DecodesInColor(map, observation);
  auto decoded = DecodeObservation(observation, config_.limits.frame(), color, field);
  if (!decoded.ok()) return ToGrpc(decoded.status());
  work->timings.decode_ms = stage.Lap();
  Observation& frame = decoded->observation;

  if (server_boxes) {
    if (!decoded->has_pixels) {
      // A query with features uses the observation's boxes, as kBoth does: a stored place's
      // features (GetPlace include_features, the console's "stored place") are static already.
      // Storing features the detector never saw is refused.
      if (settings.box_source == BoxSource::kServer && role != FrameRole::kQuery) {
        return Invalid(field +
                       (observation.frame_case() == v1::Observation::kSiftFeatures
                            ? ".sift_features"
                            : ".features") +
                       ": map '" + map.name +
                       "' detects dynamic objects on the server (box_source server), which needs "
                       "pixels: send encoded_image or raw_image");
      }
      // kBoth (or a query) without pixels: the agent's boxes alone.
    } else {
      if (expired()) return Cancelled(context, "before detection");
      auto boxes = detector_->Detect(frame.image);
      if (!boxes.ok()) return ToGrpc(boxes.status(), "server-side detection");
      work->timings.detect_ms = stage.Lap();
      metrics_->ObserveDetector(work->timings.detect_ms / 1000.0);
      frame.dynamic.boxes =
          settings.box_source == BoxSource::kServer
              ? std::move(boxes).value()
              : MergeBoxes(decoded->agent_boxes, *boxes, config_.detector.merge_iou);
    }
  }

  if (expired()) return Cancelled(context, "before feature extraction");
  auto processed = map.map->Process(frame, role, keep_dropped_keypoints);
  if (!processed.ok()) return ToGrpc(processed.status(), field);
  work->frame = std::move(processed).value();
  work->timings.extract_ms = work->frame.timings.extract_ms;
  work->timings.depth_ms = work->frame.timings.depth_ms;
  work->timings.refine_ms = work->frame.timings.refine_ms;
  work->timings.filter_ms = work->frame.timings.filter_ms;
  work->timings.transform_ms = work->frame.timings.transform_ms;
  work->metadata = std::move(frame.metadata);
  return grpc::Status::OK;
}

grpc::Status PlaceDbService::Query(grpc::ServerContext* context, const v1::QueryRequest* request,
                                   v1::QueryResponse* response) {
  CallScope scope(this);
  const Clock::time_point arrived = Clock::now();
  if (draining_flag_) return Finish("Query", context, Unavailable());
  auto entry = backend_->Map(request->map(), "map");
  if (!entry.ok()) return Finish("Query", context, ToGrpc(entry.status()));
  if (!request->has_observation()) {
    return Finish("Query", context, Invalid("observation: is required"));
  }
  const MapEntry& map = **entry;
  // The request is in memory already (gRPC read it before calling us): charged from here on.
  MemoryBudget::Reservation memory;
  if (grpc::Status charged =
          ChargeFrame(context, map, request->observation(), "this query", &memory);
      !charged.ok()) {
    return Finish("Query", context, charged);
  }
  std::promise<grpc::Status> promise;
  std::future<grpc::Status> done = promise.get_future();
  double queue_ms = 0;
  auto task = [&] {
    queue_ms = MsSince(arrived);
    Work work;
    grpc::Status status = Guarded("processing the observation", [&] {
      return Prepare(context, map, request->observation(), "observation", FrameRole::kQuery, &work,
                     request->options().include_correspondences());
    });
    if (status.ok() && Expired(context)) status = Cancelled(context, "before searching");
    if (status.ok()) {
      status = Guarded("searching", [&] {
        const ProcessedFrame& frame = work.frame;
        if (frame.valid) {  // an invalid frame has nothing to search with
          const grpc::Status searched = backend_->Query(
              map, frame, work.metadata, *request, DeadlineOf(context), response, &work.timings);
          if (!searched.ok()) return searched;
        }
        wire::FrameAnswerToProto(frame, response);
        response->set_valid(frame.valid);
        response->set_rejection(frame.rejection);
        if (request->options().include_correspondences()) {
          // What the correspondences index, and what to draw them on.
          wire::KeypointListToProto(frame.static_features.keypoints(),
                                    response->mutable_query_keypoints());
          wire::KeypointListToProto(frame.dropped_keypoints,
                                    response->mutable_query_dropped_keypoints());
          response->set_image_width(uint32_t(frame.static_features.image_width()));
          response->set_image_height(uint32_t(frame.static_features.image_height()));
        }
        work.timings.total_ms = MsSince(arrived);
        TimingsToProto(work.timings, queue_ms, response->mutable_timings());
        ObserveStages(work.timings);
        return grpc::Status::OK;
      });
    }
    promise.set_value(status);
  };
  switch (query_pool_->Submit(task, QueueWaitUntil(context, config_.limits.unary_queue_wait_ms),
                              [context] { return Expired(context); })) {
    case WorkerPool::SubmitResult::kQueued:
      break;
    case WorkerPool::SubmitResult::kFull:
      if (context->deadline() <= std::chrono::system_clock::now()) {
        return Finish("Query", context, Cancelled(context, "while waiting for a worker"));
      }
      return Finish(
          "Query", context,
          grpc::Status(
              grpc::StatusCode::RESOURCE_EXHAUSTED,
              "limits.max_queued_frames = " + std::to_string(config_.limits.max_queued_frames) +
                  ": every worker is busy and the queue stayed full for " +
                  std::to_string(config_.limits.unary_queue_wait_ms) + " ms; retry with backoff"));
    case WorkerPool::SubmitResult::kGaveUp:
      return Finish("Query", context, Cancelled(context, "while waiting for a worker"));
    case WorkerPool::SubmitResult::kStopped:
      return Finish("Query", context, Unavailable());
  }
  return Finish("Query", context, done.get());
}

}  // namespace placedb::server
