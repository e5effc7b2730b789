// Results out: the core's frame counts, boxes, matches, timings, depth state and loop-closure
// outcome as placedb.v1 messages (features: proto/convert_features.h, included here). Observations
// in: proto/convert_frame.h.
#pragma once

#include <google/protobuf/repeated_ptr_field.h>

#include <vector>

#include "core/base/timing.h"
#include "core/detect/dynamic_objects.h"
#include "core/filter/depth_filter.h"
#include "core/pipeline/place_database.h"
#include "core/storage/loop_log.h"
#include "proto/convert_features.h"
#include "proto/placedb.pb.h"

namespace placedb::wire {

namespace v1 = ::placedb::v1;

void CountsToProto(const FrameCounts& counts, v1::FrameCounts* out);
void BoxesToProto(const std::vector<DynamicBox>& boxes,
                  google::protobuf::RepeatedPtrField<v1::UsedBox>* out);
void MetadataToProto(const PlaceMetadata& metadata, v1::PlaceMetadata* out);
// Each match with its correspondences when the core filled them.
void MatchesToProto(const std::vector<Match>& matches,
                    google::protobuf::RepeatedPtrField<v1::Match>* out);
// A verified match's pose (core/pose/relative_pose.h): the transform and information row-major.
void RelativePoseToProto(const RelativePose& pose, v1::RelativePose* out);
void TimingsToProto(const StageTimings& timings, double queue_ms, v1::StageTimings* out);
// A place's record: id, metadata, counts and boxes used (no features, no dynamics).
void PlaceRecordToProto(const PlaceRecord& record, v1::Place* out);
void DepthStateToProto(const DepthFrameState& state, v1::DepthState* out);
void LoopClosureToProto(const LoopClosureOutcome& outcome, v1::LoopClosure* out);
// Matches a replica answered (cluster mode's Ingest) back as the core's, for the loop-closure
// log: place, score, inliers, verified, metadata, relative pose and pose_unavailable (a pose
// with the wrong number of values or an unknown solver is left out; no correspondences).
std::vector<Match> MatchesFromProto(const google::protobuf::RepeatedPtrField<v1::Match>& matches);
// One entry of a map's loop-closure log (WatchLoopClosures).
void LoopConstraintToProto(const LoopConstraint& constraint, v1::LoopConstraint* out);
// A place's thumbnail: the JPEG, its and its source frame's sizes, the dropped keypoints.
void ThumbnailToProto(const Thumbnail& thumbnail, v1::Thumbnail* out);

// What every answer about a frame says of it (QueryResponse and IngestResponse alike): its
// counts, the boxes used, and the agent's depth state when Algorithm 1 applied to it.
template <typename Response>
void FrameAnswerToProto(const ProcessedFrame& frame, Response* out) {
  CountsToProto(frame.counts, out->mutable_counts());
  BoxesToProto(frame.boxes_used, out->mutable_boxes_used());
  if (frame.depth_state) DepthStateToProto(*frame.depth_state, out->mutable_depth());
}

}  // namespace placedb::wire
