// Observations in: a placedb.v1 Observation validated and decoded into the core's Observation
// (pixels or precomputed features, agent boxes, mask, depth, metadata). Nothing reaches the core
// unchecked: INVALID_ARGUMENT messages name the offending field as a path into the request
// ("observation.features.keypoints[3].x: 700 lies outside the 640x480 image"), RESOURCE_EXHAUSTED
// messages name the limit ("limits.max_boxes_per_frame"). Results out: proto/convert_result.h.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/detect/dynamic_objects.h"
#include "core/features/local_features.h"
#include "core/pipeline/place_database.h"
#include "proto/placedb.pb.h"

namespace placedb::wire {

namespace v1 = ::placedb::v1;

// The limits an observation is checked against. Their values and defaults are the server's
// configuration (server/config.h Limits::frame(), keys `limits.*`); messages name those keys.
struct FrameLimits {
  uint64_t max_image_pixels = 0;           // width * height of any image, mask, depth
  uint32_t max_descriptors_per_frame = 0;  // keypoints of precomputed features
  uint32_t max_boxes_per_frame = 0;        // agent boxes
};

struct DecodedObservation {
  // Pixels (gray or BGR) or features (ORB or SIFT), agent boxes, mask, depth (raw CV_16U for
  // png16, CV_32F for raw_float32, with the frame's scale and intrinsics), metadata.
  Observation observation;
  std::vector<DynamicBox> agent_boxes;
  bool has_pixels = false;
};

// Validates and decodes `observation`; `field` is its path in the request ("observation").
// Images are decoded strictly (core/decode/image_decoder.h): truncated, corrupt or inconsistent
// JPEG/PNG data is INVALID_ARGUMENT ("observation.encoded_image.data: JPEG data is truncated
// (libjpeg: Premature end of JPEG file)"); sizes are checked before any arithmetic and reported
// as sent ("image_width/image_height: must be in [1, 100000], got 4000000000x1").
// `color` asks for BGR pixels (server-side detection) instead of grayscale. Depth must be
// decodable, within the limits, finite and non-negative (NaN = no depth), and registrable to the
// frame (the same aspect ratio: it may be smaller); its intrinsics are checked against the frame.
Result<DecodedObservation> DecodeObservation(const v1::Observation& observation,
                                             const FrameLimits& limits, bool color,
                                             const std::string& field);

// A Camera message as the core's Camera (core/pose/camera.h), checked (INVALID_ARGUMENT naming
// the field under `field`). Width and height 0 take the frame's size; otherwise they must be it.
// With the frame's size unknown (0x0: an Ingest header's stream camera) the checks that need it
// wait for each frame.
Result<Camera> CameraFromProto(const v1::Camera& camera, int frame_width, int frame_height,
                               const std::string& field);
void CameraToProto(const Camera& camera, v1::Camera* out);

// An agent's box as an observation's `boxes` entry (class id, confidence, rect): what
// DecodeObservation reads back into `agent_boxes`.
void AgentBoxToProto(const DynamicBox& box, v1::Box* out);

// A map is typed by its feature: precomputed features of the other family cannot be quantised.
// INVALID_ARGUMENT "<field>.features: map '<map_name>' is a SIFT map ..." (or ".sift_features"
// for an ORB map); pixels suit either.
Status CheckFeatureType(const v1::Observation& observation, FeatureType map_type,
                        const std::string& map_name, const std::string& field);

}  // namespace placedb::wire
