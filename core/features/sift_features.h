// SIFT as a second feature type: keypoints + 128-float descriptors (Deng et al. use SIFT for its
// robustness to viewpoint and lighting change).
//
// ExtractSift() runs OpenCV's SIFT (cv::SIFT, OpenCV >= 4.4) on an 8-bit image;
// MakeFloatFeatureSet() and ValidateFloatFeatures() check a caller's precomputed set exactly as
// features.h does for ORB (counts agree, keypoints inside the stated image, finite values).
// Descriptors are stored row-major, 128 floats per keypoint, in one contiguous array.
//
// Keypoint conventions (shared with features.h): x, y are pixel centres in the full-resolution
// image; size is OpenCV's SIFT keypoint diameter; angle in [0, 360). OpenCV packs octave, layer and
// scale into KeyPoint::octave and numbers the up-sampled first octave -1: here `octave` is the
// unpacked octave + 1, so 0 is the up-sampled level and 1 the input resolution.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <span>
#include <vector>

#include "core/base/status.h"
#include "core/features/orb_features.h"

namespace placedb {

inline constexpr int kSiftDimensions = 128;

struct FloatFeatureSet {
  int image_width = 0;
  int image_height = 0;
  std::vector<Keypoint> keypoints;
  std::vector<float> descriptors;  // keypoints.size() * kSiftDimensions, row-major

  size_t size() const { return keypoints.size(); }
  bool empty() const { return keypoints.empty(); }
  std::span<const float> descriptor(size_t i) const {
    return {descriptors.data() + i * kSiftDimensions, size_t(kSiftDimensions)};
  }
};

struct SiftConfig {
  // Keep the strongest this many keypoints (0 = all; OpenCV's nfeatures). Deng et al. report
  // ~3400 features per 960x540 Kinect v2 frame; 1000 keeps the RGB-D path within budget.
  int max_features = 1000;
  int octave_layers = 3;             // Lowe's s
  double contrast_threshold = 0.04;  // Lowe's (divided by octave_layers inside OpenCV)
  double edge_threshold = 10;        // Lowe's r
  double sigma = 1.6;
};

// max_features in [0, 100000], octave_layers in [1, 8], contrast_threshold in (0, 1),
// edge_threshold in (1, 100], sigma in (0, 10].
Status ValidateSiftConfig(const SiftConfig& config);

// Runs SIFT on `image` (8-bit gray, BGR or BGRA). `mask`, when given, is CV_8U image-sized and
// restricts detection to its non-zero pixels. A textureless image yields an empty set. Keypoints
// come in decreasing response order (ties: OpenCV's order).
Result<FloatFeatureSet> ExtractSift(const cv::Mat& image, const SiftConfig& config,
                                    const cv::Mat& mask = {});

// Validates a precomputed set: image size positive (at most 100000 per side), 128 floats per
// keypoint, every keypoint as ValidateFeatures requires, every descriptor value finite with
// |v| <= 1e6. The message names the first offending index.
Status ValidateFloatFeatures(const FloatFeatureSet& features);

// Builds a set from raw arrays as they arrive on the wire (`descriptor_bytes`: 512 bytes per
// keypoint, little-endian IEEE-754 float32) and validates it.
Result<FloatFeatureSet> MakeFloatFeatureSet(int image_width, int image_height,
                                            std::vector<Keypoint> keypoints,
                                            std::span<const uint8_t> descriptor_bytes);

// Keeps only the features listed in `keep` (ascending indices).
FloatFeatureSet SelectFloatFeatures(const FloatFeatureSet& features,
                                    const std::vector<uint32_t>& keep);

// OpenCV interop: N x 128 CV_32F (a copy).
cv::Mat ToCvFloatDescriptors(const FloatFeatureSet& features);

}  // namespace placedb
