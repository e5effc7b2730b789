// LocalFeatures: one frame's local features of one family, the type every stage above
// core/features/ passes around, and the extractor that makes them.
//
// A map is typed by its feature family (FeatureType): ORB (binary 256-bit descriptors,
// orb_features.h) or SIFT (128 floats, sift_features.h). LocalFeatures holds the image size,
// the keypoints and the descriptor block of exactly one family; its operations (validation,
// selection, concatenation) dispatch here, so the pipeline, filtering, verification and storage
// handle "the features" without asking which family they are. Code that needs the descriptors
// themselves (quantisation, matching, encoding) reads them through orb() / sift().
//
// FeatureExtractor::Create() picks the family's extractor once per map; Extract() runs it on an
// image, optionally restricted to a mask.
#pragma once

#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <variant>
#include <vector>

#include "core/base/status.h"
#include "core/features/orb_features.h"
#include "core/features/sift_features.h"

namespace placedb {

enum class FeatureType { kOrb, kSift };

const char* FeatureTypeName(FeatureType type);                  // "orb", "sift"
Result<FeatureType> ParseFeatureType(const std::string& name);  // "orb", "sift"

class LocalFeatures {
 public:
  LocalFeatures() = default;  // an empty ORB set
  // Implicit on purpose: a FeatureSet or FloatFeatureSet is a LocalFeatures of its family.
  LocalFeatures(FeatureSet orb) : set_(std::move(orb)) {}         // NOLINT
  LocalFeatures(FloatFeatureSet sift) : set_(std::move(sift)) {}  // NOLINT
  // No features, of `type`, for a width x height image.
  static LocalFeatures Empty(FeatureType type, int width, int height);

  FeatureType type() const { return set_.index() == 0 ? FeatureType::kOrb : FeatureType::kSift; }
  int image_width() const;
  int image_height() const;
  const std::vector<Keypoint>& keypoints() const;
  size_t size() const { return keypoints().size(); }
  bool empty() const { return keypoints().empty(); }

  // The family's own set; null when the features are of the other family.
  const FeatureSet* orb() const { return std::get_if<FeatureSet>(&set_); }
  const FloatFeatureSet* sift() const { return std::get_if<FloatFeatureSet>(&set_); }

  // ValidateFeatures or ValidateFloatFeatures, by family.
  Status Validate() const;
  // The features whose index is listed in `keep` (ascending), same family and image size.
  LocalFeatures Select(const std::vector<uint32_t>& keep) const;
  // The features of `a` followed by those of `b`: same family (INVALID_ARGUMENT otherwise) and
  // image size (a's is kept).
  static Result<LocalFeatures> Concat(const LocalFeatures& a, const LocalFeatures& b);
  // Heap bytes of the keypoints and descriptors (capacity).
  size_t MemoryBytes() const;

 private:
  std::variant<FeatureSet, FloatFeatureSet> set_;
};

class FeatureExtractor {
 public:
  // The extractor of `type`, configured by the family's config (the other one is ignored);
  // INVALID_ARGUMENT for a bad config or an unknown type.
  static Result<std::unique_ptr<const FeatureExtractor>> Create(FeatureType type,
                                                                const OrbConfig& orb,
                                                                const SiftConfig& sift);
  virtual ~FeatureExtractor() = default;

  virtual FeatureType type() const = 0;
  // Features of `image` (8-bit gray, BGR or BGRA); with `mask` (CV_8U, image-sized; empty =
  // everywhere) detected only on its non-zero pixels. A textureless image yields an empty set.
  virtual Result<LocalFeatures> Extract(const cv::Mat& image, const cv::Mat& mask = {}) const = 0;

  // What the pipeline does per family, asked here so that it never branches on the family.
  // Both are measured for ORB only (docs/evaluation.md); SIFT keeps its whole-frame behaviour.
  // With dynamic objects known, spend the feature budget on the static pixels
  // (DatabaseConfig::static_feature_budget) instead of extracting the whole frame.
  virtual bool budgets_static_pixels() const = 0;
  // The short-term tier verifies recent places on SC + DC features (the objects both frames
  // saw), so keep the DC features and their direct index; otherwise only the DC words.
  virtual bool verifies_dynamic_features() const = 0;
};

}  // namespace placedb
