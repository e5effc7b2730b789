// Dynamic-object filtering: the paper's DC/SC split (Munoz & Dexter, sections III and IV-B/C).
//
// A descriptor's *extent* is the set of pixels it was computed from. For ORB that is the
// patch_size x patch_size patch around the keypoint, scaled by its octave (keypoint.size is that
// side in full-resolution pixels) and rotated by keypoint.angle. A descriptor is DC (dynamic
// class) when the fraction of its extent lying on dynamic objects EXCEEDS the sensitivity
// threshold, otherwise SC (static class). A frame is a valid place representation when
// |SC| > place_threshold (the paper's equation 6).
//
// Methods:
//  - kKeypointInBox: the paper's first heuristic, implied threshold 1/4: DC iff the keypoint lies
//    inside a dynamic box (or on a dynamic mask pixel).
//  - kCornerDistance: the paper's second heuristic, implied threshold 1/2: DC iff the keypoint
//    lies inside a box and more than r pixels from each of its corners, where r is the distance
//    from the keypoint to the furthest point of its extent (half the patch diagonal).
//  - kExactCoverage: measures the covered fraction of the extent on the rasterised dynamic region
//    (boxes and/or mask) and compares it with `sensitivity_threshold`, any value in [0, 1).
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/detect/dynamic_objects.h"
#include "core/features/local_features.h"

namespace placedb {

enum class FilterMethod { kNone, kKeypointInBox, kCornerDistance, kExactCoverage };

const char* FilterMethodName(FilterMethod method);
// Parses "none", "keypoint_in_box", "corner_distance", "exact_coverage".
Result<FilterMethod> ParseFilterMethod(const std::string& name);

struct FilterConfig {
  FilterMethod method = FilterMethod::kKeypointInBox;
  // Used by kExactCoverage only; the heuristics carry their own (1/4 and 1/2).
  float sensitivity_threshold = 0.25f;
  // A frame is valid when its SC count is strictly greater than this.
  int place_threshold = 20;
};

Status ValidateFilterConfig(const FilterConfig& config);

struct FilterResult {
  std::vector<uint32_t> static_indices;   // SC: indices into the FeatureSet, ascending
  std::vector<uint32_t> dynamic_indices;  // DC: indices into the FeatureSet, ascending
  // Per-descriptor fraction of the extent on dynamic objects; filled by kExactCoverage only.
  std::vector<float> coverage;
  double frame_dynamic_coverage = 0;  // fraction of the image's pixels on dynamic objects
  bool valid = false;                 // |SC| > place_threshold

  size_t total() const { return static_indices.size() + dynamic_indices.size(); }
};

// Classifies every descriptor of `features` (either family: the classifiers look only at the
// keypoints and the image size) as DC or SC. The features must be valid (LocalFeatures::Validate).
// A mask must be CV_8U and exactly image-sized (INVALID_ARGUMENT otherwise); boxes are clipped to
// the image. With no boxes and no mask (or kNone) every descriptor is SC and the frame coverage
// is 0.
Result<FilterResult> ClassifyDescriptors(const LocalFeatures& features,
                                         const DynamicObjects& objects, const FilterConfig& config);

// The union of boxes and mask as an image-sized CV_8U mask (255 = dynamic).
cv::Mat RasterizeDynamicRegion(const DynamicObjects& objects, int width, int height);

// The pixels a (finite, non-negative) box covers, clipped to the width x height image: those
// whose centres lie in the box, as every filter method counts them. Empty when none.
cv::Rect BoxPixelRect(const cv::Rect2f& rect, int width, int height);

}  // namespace placedb
