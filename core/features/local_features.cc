#include "core/features/local_features.h"

namespace placedb {

const char* FeatureTypeName(FeatureType type) {
  return type == FeatureType::kSift ? "sift" : "orb";
}

Result<FeatureType> ParseFeatureType(const std::string& name) {
  if (name == "orb") return FeatureType::kOrb;
  if (name == "sift") return FeatureType::kSift;
  return Status::InvalidArgument("feature type: unknown name '" + name +
                                 "'; expected one of orb, sift");
}

LocalFeatures LocalFeatures::Empty(FeatureType type, int width, int height) {
  auto make = [&](auto set) {
    set.image_width = width;
    set.image_height = height;
    return LocalFeatures(std::move(set));
  };
  return type == FeatureType::kSift ? make(FloatFeatureSet{}) : make(FeatureSet{});
}

int LocalFeatures::image_width() const {
  return std::visit([](const auto& set) { return set.image_width; }, set_);
}

int LocalFeatures::image_height() const {
  return std::visit([](const auto& set) { return set.image_height; }, set_);
}

const std::vector<Keypoint>& LocalFeatures::keypoints() const {
  return std::visit([](const auto& set) -> const std::vector<Keypoint>& { return set.keypoints; },
                    set_);
}

Status LocalFeatures::Validate() const {
  if (const FeatureSet* set = orb()) return ValidateFeatures(*set);
  return ValidateFloatFeatures(*sift());
}

LocalFeatures LocalFeatures::Select(const std::vector<uint32_t>& keep) const {
  if (const FeatureSet* set = orb()) return SelectFeatures(*set, keep);
  return SelectFloatFeatures(*sift(), keep);
}

Result<LocalFeatures> LocalFeatures::Concat(const LocalFeatures& a, const LocalFeatures& b) {
  if (a.type() != b.type()) {
    return Status::InvalidArgument(std::string("cannot join ") + FeatureTypeName(a.type()) +
                                   " and " + FeatureTypeName(b.type()) + " features");
  }
  return std::visit(
      [&](const auto& first) -> LocalFeatures {
        using Set = std::decay_t<decltype(first)>;
        const Set& second = std::get<Set>(b.set_);
        Set joined = first;
        joined.keypoints.insert(joined.keypoints.end(), second.keypoints.begin(),
                                second.keypoints.end());
        joined.descriptors.insert(joined.descriptors.end(), second.descriptors.begin(),
                                  second.descriptors.end());
        return joined;
      },
      a.set_);
}

size_t LocalFeatures::MemoryBytes() const {
  return std::visit(
      [](const auto& set) {
        return set.keypoints.capacity() * sizeof(Keypoint) +
               set.descriptors.capacity() * sizeof(set.descriptors[0]);
      },
      set_);
}

namespace {

class OrbExtractor final : public FeatureExtractor {
 public:
  explicit OrbExtractor(const OrbConfig& config) : config_(config) {}
  FeatureType type() const override { return FeatureType::kOrb; }
  Result<LocalFeatures> Extract(const cv::Mat& image, const cv::Mat& mask) const override {
    auto features = ExtractOrb(image, config_, mask);
    if (!features.ok()) return features.status();
    return LocalFeatures(std::move(features).value());
  }
  bool budgets_static_pixels() const override { return true; }
  bool verifies_dynamic_features() const override { return true; }

 private:
  const OrbConfig config_;
};

class SiftExtractor final : public FeatureExtractor {
 public:
  explicit SiftExtractor(const SiftConfig& config) : config_(config) {}
  FeatureType type() const override { return FeatureType::kSift; }
  Result<LocalFeatures> Extract(const cv::Mat& image, const cv::Mat& mask) const override {
    auto features = ExtractSift(image, config_, mask);
    if (!features.ok()) return features.status();
    return LocalFeatures(std::move(features).value());
  }
  bool budgets_static_pixels() const override { return false; }
  bool verifies_dynamic_features() const override { return false; }

 private:
  const SiftConfig config_;
};

}  // namespace

Result<std::unique_ptr<const FeatureExtractor>> FeatureExtractor::Create(FeatureType type,
                                                                         const OrbConfig& orb,
                                                                         const SiftConfig& sift) {
  switch (type) {
    case FeatureType::kOrb:
      PLACEDB_RETURN_IF_ERROR(ValidateOrbConfig(orb));
      return std::unique_ptr<const FeatureExtractor>(new OrbExtractor(orb));
    case FeatureType::kSift:
      PLACEDB_RETURN_IF_ERROR(ValidateSiftConfig(sift));
      return std::unique_ptr<const FeatureExtractor>(new SiftExtractor(sift));
  }
  return Status::InvalidArgument("feature_type " + std::to_string(int(type)) +
                                 " is not a feature type");
}

}  // namespace placedb
