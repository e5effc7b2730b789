// Similarity between bag-of-words vectors: the paper's L1 score (its equation 5) and the other
// DBoW2 scorings. Every score here is "higher is more similar". Enum values equal DBoW2's, so
// the numbers in a DBoW2 text vocabulary header map directly.
#pragma once

#include <string>

#include "core/bow.h"
#include "core/status.h"

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

// Scores two vectors already normalised for `type`. Symmetric except for KL.
double Score(const BowVector& query, const BowVector& candidate, ScoringType type);

// The same score decomposed for an inverted index, which only sees words both vectors share:
//   score = FinalizeScore(type, sum over shared words of ScoreTerm(type, q_i, c_i), QueryConstant)
// Equal to Score() up to float rounding.
double ScoreTerm(ScoringType type, float query_weight, float candidate_weight);
double QueryConstant(ScoringType type, const BowVector& query);
double FinalizeScore(ScoringType type, double accumulated, double query_constant);

}  // namespace placedb
