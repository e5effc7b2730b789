#include "core/vocabulary/vocabulary_learning.h"

#include <algorithm>
#include <cmath>
#include <string>
#include <utility>

#include "core/base/timing.h"
#include "core/features/sift_features.h"
#include "core/vocabulary/float_vocabulary.h"
#include "core/vocabulary/vocabulary_trainer.h"

namespace placedb {
namespace {

uint64_t Mix(uint64_t x) {  // splitmix64's finaliser: a fixed, well-spread hash of a place id
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

uint64_t DefaultSample(FeatureType type) {
  return type == FeatureType::kSift ? 200'000 : 1'000'000;
}

}  // namespace

VocabularyShape LearnedVocabularyShape(uint64_t descriptors) {
  VocabularyShape shape;
  shape.branching = 10;
  // One level more than the 10^L words the descriptors could fill, so that the leaves get down to
  // single structures; beyond 10^5 descriptors L = 6 (deeper measured the same: the tree stops
  // where the data runs out).
  const double levels = descriptors > 0 ? std::ceil(std::log10(double(descriptors))) + 1 : 0.0;
  shape.depth = int(std::clamp(levels, 4.0, 6.0));
  return shape;
}

Status ValidateLearningOptions(const LearningOptions& options) {
  if (options.branching != 0 && (options.branching < 2 || options.branching > 64)) {
    return Status::InvalidArgument("branching: must be 0 (from the data) or in [2, 64], got " +
                                   std::to_string(options.branching));
  }
  if (options.depth != 0 && (options.depth < 1 || options.depth > 10)) {
    return Status::InvalidArgument("depth: must be 0 (from the data) or in [1, 10], got " +
                                   std::to_string(options.depth));
  }
  if (options.max_sample_descriptors != 0 && options.max_sample_descriptors < 1000) {
    return Status::InvalidArgument("max_sample_descriptors: must be 0 (the default) or >= 1000");
  }
  if (options.max_sample_descriptors != 0 &&
      options.min_descriptors > options.max_sample_descriptors) {
    return Status::InvalidArgument("min_descriptors: above max_sample_descriptors");
  }
  if (options.threads < 0) return Status::InvalidArgument("threads: must be >= 0");
  return Status::Ok();
}

size_t VocabularyLearner::Place::size() const {
  return binary.empty() ? floating.size() / size_t(kSiftDimensions) : binary.size();
}

VocabularyLearner::VocabularyLearner(FeatureType type, LearningOptions options)
    : type_(type),
      options_(options),
      max_sample_(options.max_sample_descriptors ? options.max_sample_descriptors
                                                 : DefaultSample(type)) {}

Status VocabularyLearner::Offer(uint64_t place_id, const LocalFeatures& features) {
  if (features.type() != type_) {
    return Status::InvalidArgument(std::string("place ") + std::to_string(place_id) + ": " +
                                   FeatureTypeName(features.type()) +
                                   " features offered to a learner of " + FeatureTypeName(type_));
  }
  ++places_offered_;
  descriptors_offered_ += features.size();
  if (features.empty()) return Status::Ok();
  const uint64_t hash = Mix(Mix(options_.seed) ^ place_id);
  // Kept while hash < 2^64 / 2^shift, i.e. its top `shift` bits are zero.
  if (threshold_shift_ > 0 && (hash >> (64 - threshold_shift_)) != 0) return Status::Ok();
  Place place;
  place.hash = hash;
  place.id = place_id;
  if (const FeatureSet* orb = features.orb()) {
    place.binary = orb->descriptors;
  } else {
    place.floating = features.sift()->descriptors;
  }
  descriptors_sampled_ += place.size();
  sample_.push_back(std::move(place));
  while (descriptors_sampled_ > max_sample_ && threshold_shift_ < 63) Evict();
  return Status::Ok();
}

void VocabularyLearner::Evict() {
  ++threshold_shift_;
  const int shift = 64 - threshold_shift_;
  std::erase_if(sample_, [&](const Place& place) {
    if ((place.hash >> shift) == 0) return false;
    descriptors_sampled_ -= place.size();
    return true;
  });
}

Result<LearnedVocabulary> VocabularyLearner::Learn(const LearningProgress& progress) const {
  PLACEDB_RETURN_IF_ERROR(ValidateLearningOptions(options_));
  if (descriptors_offered_ < options_.min_descriptors || places_offered_ < options_.min_places) {
    return Status::FailedPrecondition(
        "too small to learn a vocabulary from: " + std::to_string(descriptors_offered_) +
        " stored descriptors in " + std::to_string(places_offered_) + " places; at least " +
        std::to_string(options_.min_descriptors) + " descriptors in " +
        std::to_string(options_.min_places) + " places are needed");
  }
  // Id order: the trainers see the same images in the same order whatever order they came in.
  std::vector<const Place*> places;
  places.reserve(sample_.size());
  for (const Place& place : sample_) places.push_back(&place);
  std::sort(places.begin(), places.end(),
            [](const Place* a, const Place* b) { return a->id < b->id; });

  LearnedVocabulary learned;
  learned.places_offered = places_offered_;
  learned.descriptors_offered = descriptors_offered_;
  learned.places_sampled = places.size();
  learned.descriptors_sampled = descriptors_sampled_;
  learned.shape = LearnedVocabularyShape(descriptors_sampled_);
  if (options_.branching) learned.shape.branching = options_.branching;
  if (options_.depth) learned.shape.depth = options_.depth;

  // Both trainers take the same settings.
  auto configure = [&](auto* config) {
    config->branching = learned.shape.branching;
    config->depth = learned.shape.depth;
    config->seed = options_.seed;
    config->threads = options_.threads;
    config->weighting = options_.weighting;
    config->scoring = options_.scoring;
  };
  Stopwatch watch;
  if (type_ == FeatureType::kOrb) {
    std::vector<std::vector<Descriptor256>> images;
    images.reserve(places.size());
    for (const Place* place : places) images.push_back(place->binary);
    TrainerConfig config;
    configure(&config);
    auto trained = TrainVocabulary(images, config, progress);
    if (!trained.ok()) return trained.status().WithContext("learning a vocabulary");
    learned.vocabulary = AnyVocabulary(std::move(trained).value());
  } else {
    std::vector<std::vector<float>> images;
    images.reserve(places.size());
    for (const Place* place : places) images.push_back(place->floating);
    FloatTrainerConfig config;
    configure(&config);
    auto trained = FloatVocabulary::Train(images, kSiftDimensions, config, progress);
    if (!trained.ok()) return trained.status().WithContext("learning a vocabulary");
    learned.vocabulary = AnyVocabulary(std::move(trained).value());
  }
  learned.train_ms = watch.ElapsedMs();
  return learned;
}

}  // namespace placedb
