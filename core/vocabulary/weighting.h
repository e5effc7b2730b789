// How a vocabulary weights words and which norm a bag-of-words vector is normalised to. The
// vocabulary records both (DBoW2's text header carries them as these numbers); search/scoring.h
// scores vectors normalised here.
#pragma once

#include <string>

#include "core/base/status.h"
#include "core/vocabulary/bow.h"

namespace placedb {

enum class ScoringType : int {
  kL1 = 0,             // 1 - 0.5 * |v/|v|_1 - w/|w|_1|_1, in [0, 1]
  kL2 = 1,             // 1 - sqrt(1 - <v, w>) on L2-normalised vectors, in [0, 1]
  kChiSquare = 2,      // 1 - 0.5 * chi2(v, w) on L1-normalised vectors, in [0, 1]
  kKL = 3,             // -KL(v || w) on L1-normalised vectors (missing words count as 1e-12)
  kBhattacharyya = 4,  // sum sqrt(v_i w_i) on L1-normalised vectors, in [0, 1]
  kDotProduct = 5,     // <v, w>, unnormalised
};

enum class WeightingType : int { kTfIdf = 0, kTf = 1, kIdf = 2, kBinary = 3 };

const char* ScoringName(ScoringType type);
Result<ScoringType> ParseScoring(const std::string& name);  // "l1", "l2", "chi2", "kl", ...
const char* WeightingName(WeightingType type);

// Normalises in place as `type` requires (L1 or L2 norm, or nothing for the dot product).
void NormalizeForScoring(BowVector* bow, ScoringType type);

}  // namespace placedb
