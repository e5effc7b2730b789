// Checks shared by the Observation and image targets: what wire::DecodeObservation promises.
#pragma once

#include <cstdint>
#include <string>

#include "proto/convert_frame.h"
#include "tests/fuzz/fuzz_support.h"

namespace placedb::fuzz {

// Small limits keep every execution fast; the server's are larger, the checks the same.
inline constexpr wire::FrameLimits kFuzzFrameLimits{
    .max_image_pixels = 256 * 256, .max_descriptors_per_frame = 512, .max_boxes_per_frame = 16};

// Decodes `observation` and checks the result against the limits: errors are INVALID_ARGUMENT
// naming a field under "observation" or RESOURCE_EXHAUSTED naming a limit; what decodes has
// pixels or features within the limits, at most the box limit of agent boxes, and a mask of the
// frame's size.
inline void DecodeAndCheck(const wire::v1::Observation& observation, bool color) {
  auto decoded = wire::DecodeObservation(observation, kFuzzFrameLimits, color, "observation");
  if (!decoded.ok()) {
    const Status& s = decoded.status();
    if (s.code() == StatusCode::kInvalidArgument) {
      PLACEDB_FUZZ_CHECK(s.message().rfind("observation", 0) == 0,
                         "INVALID_ARGUMENT does not name the field: " + s.message());
    } else {
      PLACEDB_FUZZ_CHECK(s.code() == StatusCode::kResourceExhausted,
                         "DecodeObservation: unexpected error " + s.ToString());
    }
    return;
  }
  const Observation& out = decoded->observation;
  int width = 0;
  int height = 0;
  if (decoded->has_pixels) {
    PLACEDB_FUZZ_CHECK(!out.image.empty(), "pixels promised but the image is empty");
    PLACEDB_FUZZ_CHECK(out.image.depth() == CV_8U && out.image.channels() == (color ? 3 : 1),
                       "decoded image is not 8-bit " + std::string(color ? "BGR" : "gray"));
    width = out.image.cols;
    height = out.image.rows;
  } else {
    PLACEDB_FUZZ_CHECK(out.features.has_value(), "neither pixels nor features");
    PLACEDB_FUZZ_CHECK(out.features->size() <= kFuzzFrameLimits.max_descriptors_per_frame,
                       "more features than limits.max_descriptors_per_frame");
    width = out.features->image_width();
    height = out.features->image_height();
  }
  PLACEDB_FUZZ_CHECK(width > 0 && height > 0, "a decoded frame without a size");
  if (decoded->has_pixels) {
    PLACEDB_FUZZ_CHECK(uint64_t(width) * uint64_t(height) <= kFuzzFrameLimits.max_image_pixels,
                       "an image larger than limits.max_image_pixels");
  }
  PLACEDB_FUZZ_CHECK(decoded->agent_boxes.size() <= kFuzzFrameLimits.max_boxes_per_frame,
                     "more boxes than limits.max_boxes_per_frame");
  if (!out.dynamic.mask.empty()) {
    PLACEDB_FUZZ_CHECK(out.dynamic.mask.cols == width && out.dynamic.mask.rows == height &&
                           out.dynamic.mask.type() == CV_8UC1,
                       "the mask is not an 8-bit image of the frame's size");
  }
}

}  // namespace placedb::fuzz
