// Learning a map's vocabulary from its own stored static descriptors (issue 29).
//
// A map's places are offered one at a time (Offer), each with its stored SC features; query
// frames never are. The learner keeps a sample of whole places, bounded in descriptors, then
// trains a word tree on it (Learn): the binary trainer for ORB maps, the float one for SIFT.
//
// The sample is a property of the set of places, not of the order they are offered in or of the
// thread count: place `id` is in it when hash(seed, id) < T, where T is the largest threshold of
// the form 2^-j at which the selected places fit in `max_sample_descriptors`. The learner starts
// with T = 1 and halves T (evicting what falls above it) whenever the sample overflows, so memory
// never exceeds the bound plus one place. Replicas of a map hold the same places under the same
// ids, so they sample, and (the trainers being deterministic) learn, the same vocabulary.
//
// Whole places, not single descriptors, are sampled so that each sampled place is a training
// image and the word weights (idf = ln(N / n_i)) are estimated over places as the map will use
// them.
//
// The tree's shape follows the amount of data (LearnedVocabularyShape): a deep tree on little
// data is harmless (a node with at most k distinct descriptors stops), but a shallow tree on much
// data merges distinct structures into one word.
//
// Thread safety: a VocabularyLearner is used by one thread at a time.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "core/base/status.h"
#include "core/features/descriptor.h"
#include "core/features/local_features.h"
#include "core/vocabulary/any_vocabulary.h"
#include "core/vocabulary/weighting.h"

namespace placedb {

struct VocabularyShape {
  int branching = 10;  // k
  int depth = 5;       // L
};

// The shape learned for `descriptors` training descriptors: k = 10 and L = ceil(log10(n)) + 1,
// within [4, 6]: 5 below 10^4 descriptors, else 6 (docs/evaluation.md, "Map-learned vocabulary",
// has the measurements behind it: deeper trees won at NoGeom at every size measured).
VocabularyShape LearnedVocabularyShape(uint64_t descriptors);

struct LearningOptions {
  uint64_t seed = 1;
  // Bound on the sampled descriptors (memory: 32 bytes each for ORB, 512 for SIFT); 0 = the
  // default of the feature type: 1,000,000 ORB (32 MB), 200,000 SIFT (100 MB).
  uint64_t max_sample_descriptors = 0;
  // A map with fewer stored descriptors or places than this is too small to learn from.
  uint64_t min_descriptors = 5000;
  uint64_t min_places = 10;
  // 0 = LearnedVocabularyShape(sampled descriptors).
  int branching = 0;
  int depth = 0;
  int threads = 0;  // 0 = all hardware threads
  WeightingType weighting = WeightingType::kTfIdf;
  ScoringType scoring = ScoringType::kL1;
};

// INVALID_ARGUMENT naming the field.
Status ValidateLearningOptions(const LearningOptions& options);

// What a learned vocabulary was learned from.
struct LearnedVocabulary {
  AnyVocabulary vocabulary;
  VocabularyShape shape;
  uint64_t places_offered = 0;
  uint64_t descriptors_offered = 0;
  uint64_t places_sampled = 0;
  uint64_t descriptors_sampled = 0;
  double train_ms = 0;
};

using LearningProgress = std::function<void(double fraction, const char* phase)>;

class VocabularyLearner {
 public:
  // `type`: the map's feature type (ORB -> binary vocabulary, SIFT -> float).
  VocabularyLearner(FeatureType type, LearningOptions options);

  // Offers a stored place's static features (keys are the map's place ids: each offered once).
  // INVALID_ARGUMENT when they are not of the learner's feature type; nothing is kept then.
  Status Offer(uint64_t place_id, const LocalFeatures& features);

  uint64_t places_offered() const { return places_offered_; }
  uint64_t descriptors_offered() const { return descriptors_offered_; }
  uint64_t descriptors_sampled() const { return descriptors_sampled_; }

  // Trains on the sample. FAILED_PRECONDITION "too small to learn from" (naming what was
  // offered and what is needed) below min_descriptors / min_places. Leaves the learner as it is.
  Result<LearnedVocabulary> Learn(const LearningProgress& progress = {}) const;

 private:
  struct Place {
    uint64_t hash = 0;
    uint64_t id = 0;
    std::vector<Descriptor256> binary;  // ORB
    std::vector<float> floating;        // SIFT, kSiftDimensions per descriptor
    size_t size() const;
  };
  void Evict();  // halves the threshold and drops the places above it

  FeatureType type_;
  LearningOptions options_;
  uint64_t max_sample_ = 0;
  // Places are kept while hash < 2^64 >> threshold_shift_.
  int threshold_shift_ = 0;
  std::vector<Place> sample_;
  uint64_t places_offered_ = 0;
  uint64_t descriptors_offered_ = 0;
  uint64_t descriptors_sampled_ = 0;
};

}  // namespace placedb
