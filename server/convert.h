// Translation between the placedb.v1 wire types and the core's types for frames and results (the
// status mapping and map configurations: proto/status.h, proto/convert_config.h). Everything
// that arrives is validated here before the core sees it; INVALID_ARGUMENT messages name the
// offending field as a path into the request ("observation.features.keypoints[3].x: 700 lies
// outside the 640x480 image"), RESOURCE_EXHAUSTED messages name the limit
// ("limits.max_boxes_per_frame").
#pragma once

#include <grpcpp/support/status.h>

#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/detect/detector.h"
#include "core/pipeline/place_database.h"
#include "core/storage/map_store.h"
#include "proto/convert_config.h"
#include "proto/placedb.pb.h"
#include "proto/status.h"
#include "server/config.h"

namespace placedb::server {

namespace v1 = ::placedb::v1;

// The status mapping and the configuration conversions are the wire library's (proto/).
using wire::GrpcCodeLabel;
using wire::GrpcCodeName;
using wire::ToGrpc;

using wire::FeatureTypeToProto;
using wire::MapConfigToProto;
using wire::MapOptionsFromProto;
using wire::MapStatsToProto;
using wire::MapVocabulary;
using wire::QueryOptionsFromProto;
using wire::ServiceMapSettings;

// ---- Observations -------------------------------------------------------------------------------

struct DecodedObservation {
  // Pixels (gray or BGR) or features (ORB or SIFT), agent boxes, mask, depth (raw CV_16U for
  // png16, CV_32F for raw_float32, with the frame's scale and intrinsics), metadata.
  Observation observation;
  std::vector<DynamicBox> agent_boxes;
  bool has_pixels = false;
};

// Validates and decodes `observation`; `field` is its path in the request ("observation").
// `color` asks for BGR pixels (server-side detection) instead of grayscale. Depth must be
// decodable, within the limits, finite and non-negative (NaN = no depth), and registrable to the
// frame (the same aspect ratio: it may be smaller); its intrinsics are checked against the frame.
Result<DecodedObservation> DecodeObservation(const v1::Observation& observation,
                                             const Limits& limits, bool color,
                                             const std::string& field);

// Width and height from a PNG or JPEG header without decoding; INVALID_ARGUMENT otherwise.
struct ImageHeader {
  enum class Format { kPng, kJpeg } format;
  int width = 0;
  int height = 0;
};
Result<ImageHeader> ReadImageHeader(const std::string& bytes);

// ---- Results ------------------------------------------------------------------------------------

void CountsToProto(const FrameCounts& counts, v1::FrameCounts* out);
void BoxesToProto(const std::vector<DynamicBox>& boxes,
                  google::protobuf::RepeatedPtrField<v1::UsedBox>* out);
void MetadataToProto(const PlaceMetadata& metadata, v1::PlaceMetadata* out);
void MatchesToProto(const std::vector<Match>& matches,
                    google::protobuf::RepeatedPtrField<v1::Match>* out);
void TimingsToProto(const StageTimings& timings, double queue_ms, v1::StageTimings* out);
void FeaturesToProto(const FeatureSet& features, v1::Features* out);
void SiftFeaturesToProto(const FloatFeatureSet& features, v1::SiftFeatures* out);
// A place's features into the field of their family: `features` (ORB) or `sift_features`.
void PlaceFeaturesToProto(const LocalFeatures& features, v1::Place* out);
void DepthStateToProto(const DepthFrameState& state, v1::DepthState* out);
void LoopClosureToProto(const LoopClosureOutcome& outcome, v1::LoopClosure* out);

}  // namespace placedb::server
