// Trains a vocabulary by hierarchical k-means over binary descriptors.
//
// Each node's descriptors are split into k clusters: k-means++ seeding (Hamming distance),
// Lloyd iterations with bitwise-majority centres, recursion to depth L. A cluster that ends up
// empty is dropped (never a crash); a node with at most k distinct descriptors gets one child per
// distinct descriptor and stops. Word weights are idf = ln(N / n_i) over the training images.
// Deterministic for a given seed whatever the thread count: each node draws from its own RNG
// stream derived from (seed, node path), and parallel work is reduced in a fixed order.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <vector>

#include "core/base/status.h"
#include "core/features/descriptor.h"
#include "core/vocabulary/vocabulary.h"
#include "core/vocabulary/weighting.h"

namespace placedb {

struct TrainerConfig {
  int branching = 10;  // k, in [2, 64]
  int depth = 6;       // L, in [1, 10]
  uint64_t seed = 1;
  int threads = 0;          // 0 = all hardware threads
  int max_iterations = 10;  // Lloyd iterations per node (stops early when assignments settle)
  WeightingType weighting = WeightingType::kTfIdf;
  ScoringType scoring = ScoringType::kL1;  // recorded as the vocabulary's default
};

// Called now and then with a fraction in [0, 1] and a short phase name.
using TrainerProgress = std::function<void(double fraction, const char* phase)>;

// `images[i]` holds the descriptors of training image i. INVALID_ARGUMENT for a bad config or
// when there are fewer descriptors than `branching`.
Result<std::shared_ptr<const Vocabulary>> TrainVocabulary(
    const std::vector<std::vector<Descriptor256>>& images, const TrainerConfig& config,
    const TrainerProgress& progress = {});

}  // namespace placedb
