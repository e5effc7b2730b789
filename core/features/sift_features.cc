#include "core/features/sift_features.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <numeric>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <string>

namespace placedb {

namespace {

constexpr int kMaxImageSide = 100000;
constexpr float kMaxDescriptorMagnitude = 1e6f;

std::string Index(const char* name, size_t i) {
  return std::string(name) + "[" + std::to_string(i) + "]";
}

// Keypoints only, with placeholder descriptors: what ValidateFeatures and the DC/SC classifiers
// of dynamic_filter.h look at.
FeatureSet KeypointsOnly(const FloatFeatureSet& features) {
  FeatureSet set;
  set.image_width = features.image_width;
  set.image_height = features.image_height;
  set.keypoints = features.keypoints;
  set.descriptors.resize(features.keypoints.size());
  return set;
}

// OpenCV's SIFT packs octave (signed, low byte), layer (next byte) into KeyPoint::octave.
int UnpackedOctavePlusOne(int packed) {
  int octave = packed & 255;
  if (octave >= 128) octave -= 256;  // -1: the up-sampled first octave
  return std::clamp(octave + 1, 0, 31);
}

}  // namespace

Status ValidateSiftConfig(const SiftConfig& config) {
  if (config.max_features < 0 || config.max_features > 100000) {
    return Status::InvalidArgument("sift.max_features must be in [0, 100000], got " +
                                   std::to_string(config.max_features));
  }
  if (config.octave_layers < 1 || config.octave_layers > 8) {
    return Status::InvalidArgument("sift.octave_layers must be in [1, 8], got " +
                                   std::to_string(config.octave_layers));
  }
  if (!(config.contrast_threshold > 0 && config.contrast_threshold < 1)) {
    return Status::InvalidArgument("sift.contrast_threshold must be in (0, 1), got " +
                                   std::to_string(config.contrast_threshold));
  }
  if (!(config.edge_threshold > 1 && config.edge_threshold <= 100)) {
    return Status::InvalidArgument("sift.edge_threshold must be in (1, 100], got " +
                                   std::to_string(config.edge_threshold));
  }
  if (!(config.sigma > 0 && config.sigma <= 10)) {
    return Status::InvalidArgument("sift.sigma must be in (0, 10], got " +
                                   std::to_string(config.sigma));
  }
  return Status::Ok();
}

Result<FloatFeatureSet> ExtractSift(const cv::Mat& image, const SiftConfig& config,
                                    const cv::Mat& mask) {
  PLACEDB_RETURN_IF_ERROR(ValidateSiftConfig(config));
  auto gray_result = ToGray8(image);
  if (!gray_result.ok()) return gray_result.status();
  const cv::Mat& gray = *gray_result;
  if (!mask.empty() && (mask.type() != CV_8UC1 || mask.size() != gray.size())) {
    return Status::InvalidArgument("mask must be CV_8U and " + std::to_string(gray.cols) + "x" +
                                   std::to_string(gray.rows) + " like the image");
  }
  // A fresh detector per call, as ExtractOrb: cheap next to detection, and thread-safe.
  cv::Ptr<cv::SIFT> sift =
      cv::SIFT::create(config.max_features, config.octave_layers, config.contrast_threshold,
                       config.edge_threshold, config.sigma);
  std::vector<cv::KeyPoint> cv_keypoints;
  cv::Mat cv_descriptors;
  sift->detectAndCompute(gray, mask.empty() ? cv::noArray() : cv::InputArray(mask), cv_keypoints,
                         cv_descriptors);

  // Strongest first (OpenCV's order is by octave when max_features is 0).
  std::vector<size_t> order(cv_keypoints.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    return cv_keypoints[a].response > cv_keypoints[b].response;
  });

  FloatFeatureSet features;
  features.image_width = gray.cols;
  features.image_height = gray.rows;
  features.keypoints.reserve(order.size());
  features.descriptors.reserve(order.size() * kSiftDimensions);
  for (size_t i : order) {
    const cv::KeyPoint& kp = cv_keypoints[i];
    // OpenCV keeps keypoints inside the image; a value on the far border after rounding in the
    // up-sampled octave would fail validation, so drop rather than fail.
    if (!(kp.pt.x >= 0 && kp.pt.y >= 0 && kp.pt.x < float(gray.cols) &&
          kp.pt.y < float(gray.rows))) {
      continue;
    }
    float angle = kp.angle;
    if (!(angle >= 0 && angle < 360)) angle = angle < 0 ? -1.0f : 0.0f;
    features.keypoints.push_back(Keypoint{kp.pt.x, kp.pt.y, std::max(kp.size, 1e-3f), angle,
                                          kp.response, UnpackedOctavePlusOne(kp.octave)});
    const float* row = cv_descriptors.ptr<float>(int(i));
    features.descriptors.insert(features.descriptors.end(), row, row + kSiftDimensions);
  }
  return features;
}

Status ValidateFloatFeatures(const FloatFeatureSet& features) {
  if (features.descriptors.size() != features.keypoints.size() * kSiftDimensions) {
    return Status::InvalidArgument("descriptors: " + std::to_string(features.descriptors.size()) +
                                   " floats for " + std::to_string(features.keypoints.size()) +
                                   " keypoints; there must be exactly " +
                                   std::to_string(kSiftDimensions) + " per keypoint");
  }
  const int w = features.image_width;
  const int h = features.image_height;
  if (w <= 0 || h <= 0 || w > kMaxImageSide || h > kMaxImageSide) {
    return Status::InvalidArgument("image size must be positive and at most " +
                                   std::to_string(kMaxImageSide) + " per side, got " +
                                   std::to_string(w) + "x" + std::to_string(h));
  }
  PLACEDB_RETURN_IF_ERROR(ValidateFeatures(KeypointsOnly(features)));
  for (size_t i = 0; i < features.descriptors.size(); ++i) {
    const float v = features.descriptors[i];
    if (!std::isfinite(v) || std::abs(v) > kMaxDescriptorMagnitude) {
      return Status::InvalidArgument(Index("descriptors", i / kSiftDimensions) + "[" +
                                     std::to_string(i % kSiftDimensions) +
                                     "] must be finite with magnitude at most 1e6");
    }
  }
  return Status::Ok();
}

Result<FloatFeatureSet> MakeFloatFeatureSet(int image_width, int image_height,
                                            std::vector<Keypoint> keypoints,
                                            std::span<const uint8_t> descriptor_bytes) {
  constexpr size_t kRowBytes = kSiftDimensions * sizeof(float);
  if (descriptor_bytes.size() != keypoints.size() * kRowBytes) {
    return Status::InvalidArgument("descriptors: " + std::to_string(descriptor_bytes.size()) +
                                   " bytes for " + std::to_string(keypoints.size()) +
                                   " keypoints; expected " + std::to_string(kRowBytes) +
                                   " bytes (128 little-endian float32) per keypoint");
  }
  FloatFeatureSet features;
  features.image_width = image_width;
  features.image_height = image_height;
  features.keypoints = std::move(keypoints);
  features.descriptors.resize(features.keypoints.size() * kSiftDimensions);
  if constexpr (std::endian::native == std::endian::little) {
    if (!descriptor_bytes.empty()) {
      std::memcpy(features.descriptors.data(), descriptor_bytes.data(), descriptor_bytes.size());
    }
  } else {
    for (size_t i = 0; i < features.descriptors.size(); ++i) {
      uint32_t bits = 0;
      for (int b = 0; b < 4; ++b) bits |= uint32_t(descriptor_bytes[4 * i + b]) << (8 * b);
      features.descriptors[i] = std::bit_cast<float>(bits);
    }
  }
  PLACEDB_RETURN_IF_ERROR(ValidateFloatFeatures(features));
  return features;
}

FloatFeatureSet SelectFloatFeatures(const FloatFeatureSet& features,
                                    const std::vector<uint32_t>& keep) {
  FloatFeatureSet out;
  out.image_width = features.image_width;
  out.image_height = features.image_height;
  out.keypoints.reserve(keep.size());
  out.descriptors.reserve(keep.size() * kSiftDimensions);
  for (uint32_t i : keep) {
    if (i >= features.size()) continue;
    out.keypoints.push_back(features.keypoints[i]);
    const auto d = features.descriptor(i);
    out.descriptors.insert(out.descriptors.end(), d.begin(), d.end());
  }
  return out;
}

cv::Mat ToCvFloatDescriptors(const FloatFeatureSet& features) {
  cv::Mat out(int(features.size()), kSiftDimensions, CV_32F);
  if (!features.descriptors.empty()) {
    std::memcpy(out.data, features.descriptors.data(), features.descriptors.size() * sizeof(float));
  }
  return out;
}

}  // namespace placedb
