#include "core/features/orb_features.h"

#include <cmath>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <string>

namespace placedb {

namespace {
constexpr int kMaxImageSide = 100000;

std::string Index(const char* what, size_t i) {
  return std::string(what) + "[" + std::to_string(i) + "]";
}
}  // namespace

Status ValidateOrbConfig(const OrbConfig& config) {
  if (config.max_features < 1 || config.max_features > 100000) {
    return Status::InvalidArgument("orb.max_features must be in [1, 100000], got " +
                                   std::to_string(config.max_features));
  }
  if (!(config.scale_factor > 1.0f && config.scale_factor <= 2.0f)) {
    return Status::InvalidArgument("orb.scale_factor must be in (1, 2], got " +
                                   std::to_string(config.scale_factor));
  }
  if (config.levels < 1 || config.levels > 16) {
    return Status::InvalidArgument("orb.levels must be in [1, 16], got " +
                                   std::to_string(config.levels));
  }
  if (config.patch_size < 2 || config.patch_size > 255) {
    return Status::InvalidArgument("orb.patch_size must be in [2, 255], got " +
                                   std::to_string(config.patch_size));
  }
  if (config.edge_threshold < 0) {
    return Status::InvalidArgument("orb.edge_threshold must be >= 0");
  }
  if (config.fast_threshold < 1 || config.fast_threshold > 255) {
    return Status::InvalidArgument("orb.fast_threshold must be in [1, 255]");
  }
  return Status::Ok();
}

Result<cv::Mat> ToGray8(const cv::Mat& image) {
  if (image.empty()) return Status::InvalidArgument("image is empty");
  if (image.depth() != CV_8U) return Status::InvalidArgument("image must be 8-bit");
  cv::Mat gray;
  if (image.channels() == 1) {
    gray = image;
  } else if (image.channels() == 3) {
    cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  } else if (image.channels() == 4) {
    cv::cvtColor(image, gray, cv::COLOR_BGRA2GRAY);
  } else {
    return Status::InvalidArgument("image must have 1, 3 or 4 channels, got " +
                                   std::to_string(image.channels()));
  }
  return gray;
}

Result<FeatureSet> ExtractOrb(const cv::Mat& image, const OrbConfig& config, const cv::Mat& where) {
  PLACEDB_RETURN_IF_ERROR(ValidateOrbConfig(config));
  auto gray_result = ToGray8(image);
  if (!gray_result.ok()) return gray_result.status();
  const cv::Mat& gray = *gray_result;
  if (!where.empty() && (where.type() != CV_8UC1 || where.size() != gray.size())) {
    return Status::InvalidArgument("ORB detection mask must be CV_8U and the image's size");
  }
  // A fresh detector per call: cv::ORB keeps per-call buffers, so sharing one across threads
  // would need a lock; construction is cheap next to detection.
  cv::Ptr<cv::ORB> orb = cv::ORB::create(config.max_features, config.scale_factor, config.levels,
                                         config.edge_threshold, 0, 2, cv::ORB::HARRIS_SCORE,
                                         config.patch_size, config.fast_threshold);
  FeatureSet features;
  features.image_width = gray.cols;
  features.image_height = gray.rows;
  // ORB's pyramid cannot shrink an image with a side under 2 pixels (OpenCV throws); such an
  // image has no features to find anyway.
  if (gray.cols < 2 || gray.rows < 2) return features;
  std::vector<cv::KeyPoint> cv_keypoints;
  cv::Mat cv_descriptors;
  try {
    orb->detectAndCompute(gray, where, cv_keypoints, cv_descriptors);  // empty: no mask
  } catch (const cv::Exception& e) {
    return Status::InvalidArgument(std::string("ORB extraction failed on a ") +
                                   std::to_string(gray.cols) + "x" + std::to_string(gray.rows) +
                                   " image: " + e.what());
  }

  features.keypoints.reserve(cv_keypoints.size());
  features.descriptors.reserve(cv_keypoints.size());
  for (size_t i = 0; i < cv_keypoints.size(); ++i) {
    const cv::KeyPoint& kp = cv_keypoints[i];
    features.keypoints.push_back(
        Keypoint{kp.pt.x, kp.pt.y, kp.size, kp.angle, kp.response, kp.octave});
    features.descriptors.push_back(Descriptor256::FromBytes(cv_descriptors.ptr<uint8_t>(int(i))));
  }
  return features;
}

Status ValidateFeatures(const FeatureSet& features) {
  const int w = features.image_width;
  const int h = features.image_height;
  if (w <= 0 || h <= 0 || w > kMaxImageSide || h > kMaxImageSide) {
    return Status::InvalidArgument("image size must be positive and at most " +
                                   std::to_string(kMaxImageSide) + " per side, got " +
                                   std::to_string(w) + "x" + std::to_string(h));
  }
  if (features.descriptors.size() != features.keypoints.size()) {
    return Status::InvalidArgument("descriptors: " + std::to_string(features.descriptors.size()) +
                                   " descriptors for " + std::to_string(features.keypoints.size()) +
                                   " keypoints; there must be exactly one per keypoint");
  }
  for (size_t i = 0; i < features.keypoints.size(); ++i) {
    const Keypoint& kp = features.keypoints[i];
    if (!std::isfinite(kp.x) || !std::isfinite(kp.y) || !std::isfinite(kp.size) ||
        !std::isfinite(kp.angle) || !std::isfinite(kp.response)) {
      return Status::InvalidArgument(Index("keypoints", i) + " has a non-finite value");
    }
    if (kp.x < 0 || kp.y < 0 || kp.x >= float(w) || kp.y >= float(h)) {
      return Status::InvalidArgument(Index("keypoints", i) + " at (" + std::to_string(kp.x) + ", " +
                                     std::to_string(kp.y) + ") lies outside the " +
                                     std::to_string(w) + "x" + std::to_string(h) + " image");
    }
    if (kp.size <= 0 || kp.size > float(kMaxImageSide)) {
      return Status::InvalidArgument(Index("keypoints", i) + ".size must be positive, got " +
                                     std::to_string(kp.size));
    }
    if (kp.angle != -1.0f && (kp.angle < 0 || kp.angle > 360)) {
      return Status::InvalidArgument(Index("keypoints", i) +
                                     ".angle must be -1 or in [0, 360], got " +
                                     std::to_string(kp.angle));
    }
    if (kp.octave < 0 || kp.octave > 31) {
      return Status::InvalidArgument(Index("keypoints", i) + ".octave must be in [0, 31], got " +
                                     std::to_string(kp.octave));
    }
  }
  return Status::Ok();
}

Result<FeatureSet> MakeFeatureSet(int image_width, int image_height,
                                  std::vector<Keypoint> keypoints,
                                  const std::vector<uint8_t>& descriptor_bytes) {
  if (descriptor_bytes.size() % Descriptor256::kBytes != 0) {
    return Status::InvalidArgument("descriptors: " + std::to_string(descriptor_bytes.size()) +
                                   " bytes is not a multiple of 32 (256-bit descriptors)");
  }
  const size_t count = descriptor_bytes.size() / Descriptor256::kBytes;
  if (count != keypoints.size()) {
    return Status::InvalidArgument("descriptors: " + std::to_string(count) + " descriptors for " +
                                   std::to_string(keypoints.size()) +
                                   " keypoints; there must be exactly one per keypoint");
  }
  FeatureSet features;
  features.image_width = image_width;
  features.image_height = image_height;
  features.keypoints = std::move(keypoints);
  features.descriptors.resize(count);
  for (size_t i = 0; i < count; ++i) {
    features.descriptors[i] =
        Descriptor256::FromBytes(&descriptor_bytes[i * Descriptor256::kBytes]);
  }
  PLACEDB_RETURN_IF_ERROR(ValidateFeatures(features));
  return features;
}

FeatureSet ConcatFeatures(const FeatureSet& a, const FeatureSet& b) {
  FeatureSet joined = a;
  joined.keypoints.insert(joined.keypoints.end(), b.keypoints.begin(), b.keypoints.end());
  joined.descriptors.insert(joined.descriptors.end(), b.descriptors.begin(), b.descriptors.end());
  return joined;
}

FeatureSet SelectFeatures(const FeatureSet& features, const std::vector<uint32_t>& keep) {
  FeatureSet selected;
  selected.image_width = features.image_width;
  selected.image_height = features.image_height;
  selected.keypoints.reserve(keep.size());
  selected.descriptors.reserve(keep.size());
  for (uint32_t i : keep) {
    selected.keypoints.push_back(features.keypoints[i]);
    selected.descriptors.push_back(features.descriptors[i]);
  }
  return selected;
}

std::vector<cv::KeyPoint> ToCvKeypoints(const std::vector<Keypoint>& keypoints) {
  std::vector<cv::KeyPoint> out;
  out.reserve(keypoints.size());
  for (const Keypoint& kp : keypoints) {
    out.emplace_back(cv::Point2f(kp.x, kp.y), kp.size, kp.angle, kp.response, kp.octave);
  }
  return out;
}

cv::Mat ToCvDescriptors(const std::vector<Descriptor256>& descriptors) {
  cv::Mat out(int(descriptors.size()), Descriptor256::kBytes, CV_8U);
  for (size_t i = 0; i < descriptors.size(); ++i) descriptors[i].ToBytes(out.ptr<uint8_t>(int(i)));
  return out;
}

}  // namespace placedb
