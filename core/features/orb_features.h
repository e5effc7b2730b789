// Local features of one frame: keypoints and their 256-bit binary descriptors.
//
// Two ways in: ExtractOrb() runs OpenCV's ORB on a grayscale image; ValidateFeatures() checks a
// caller's precomputed set (counts agree, positions inside the stated image, sane geometry) so
// that nothing malformed ever reaches the index. Descriptor i belongs to keypoint i.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <vector>

#include "core/base/status.h"
#include "core/features/descriptor.h"

namespace placedb {

struct Keypoint {
  float x = 0;         // pixel column in the full-resolution image
  float y = 0;         // pixel row
  float size = 31;     // diameter of the described patch in full-resolution pixels
  float angle = -1;    // orientation in degrees [0, 360), or -1 when unknown
  float response = 0;  // detector strength
  int32_t octave = 0;  // pyramid level the descriptor was computed on (0 = full resolution)

  bool operator==(const Keypoint&) const = default;
};

struct FeatureSet {
  int image_width = 0;
  int image_height = 0;
  std::vector<Keypoint> keypoints;
  std::vector<Descriptor256> descriptors;  // descriptors[i] describes keypoints[i]

  size_t size() const { return keypoints.size(); }
  bool empty() const { return keypoints.empty(); }
};

struct OrbConfig {
  int max_features = 1000;  // the paper evaluates 300..2000
  float scale_factor = 1.2f;
  int levels = 8;
  int edge_threshold = 31;
  int patch_size = 31;  // also the side of a descriptor's extent at its octave's scale
  int fast_threshold = 20;
};

// Checks an OrbConfig: max_features in [1, 100000], scale_factor in (1, 2], levels in [1, 16],
// patch_size in [2, 255], edge_threshold >= 0.
Status ValidateOrbConfig(const OrbConfig& config);

// An 8-bit grayscale view of `image` (8-bit gray returned as is; BGR and BGRA converted). Empty,
// non-8-bit or 2-channel images are INVALID_ARGUMENT. Shared by every feature extractor.
Result<cv::Mat> ToGray8(const cv::Mat& image);

// Runs ORB on `image` (8-bit grayscale or BGR; BGR is converted). An image with no texture
// yields an empty set, not an error. An empty or non-8-bit image is INVALID_ARGUMENT.
// With `where` (CV_8U, image-sized; empty = everywhere), keypoints are detected only on its
// non-zero pixels; the budget is spent there.
Result<FeatureSet> ExtractOrb(const cv::Mat& image, const OrbConfig& config,
                              const cv::Mat& where = cv::Mat());

// Validates a precomputed set: image size positive (at most 100000 per side), as many
// descriptors as keypoints, every keypoint finite, inside [0, width) x [0, height), size > 0,
// angle -1 or in [0, 360], octave in [0, 31]. The message names the first offending index.
Status ValidateFeatures(const FeatureSet& features);

// Builds a FeatureSet from raw arrays as they arrive on the wire: `descriptor_bytes` must hold
// exactly 32 bytes per keypoint. Validates the result.
Result<FeatureSet> MakeFeatureSet(int image_width, int image_height,
                                  std::vector<Keypoint> keypoints,
                                  const std::vector<uint8_t>& descriptor_bytes);

// Keeps only the features whose index is listed in `keep` (ascending), e.g. the SC set.
FeatureSet SelectFeatures(const FeatureSet& features, const std::vector<uint32_t>& keep);
// The features of `a` followed by those of `b` (same image size).
FeatureSet ConcatFeatures(const FeatureSet& a, const FeatureSet& b);

// OpenCV interop, for verification and tests.
std::vector<cv::KeyPoint> ToCvKeypoints(const std::vector<Keypoint>& keypoints);
cv::Mat ToCvDescriptors(const std::vector<Descriptor256>& descriptors);  // N x 32 CV_8U

}  // namespace placedb
