// Similarity between bag-of-words vectors: the paper's L1 score (its equation 5) and the other
// DBoW2 scorings. Every score here is "higher is more similar". Enum values equal DBoW2's, so
// the numbers in a DBoW2 text vocabulary header map directly.
#pragma once

#include "core/vocabulary/weighting.h"

namespace placedb {

// Scores two vectors already normalised for `type`. Symmetric except for KL.
double Score(const BowVector& query, const BowVector& candidate, ScoringType type);

// The same score decomposed for an inverted index, which only sees words both vectors share:
//   score = FinalizeScore(type, sum over shared words of ScoreTerm(type, q_i, c_i), QueryConstant)
// Equal to Score() up to float rounding.
double ScoreTerm(ScoringType type, float query_weight, float candidate_weight);
double QueryConstant(ScoringType type, const BowVector& query);
double FinalizeScore(ScoringType type, double accumulated, double query_constant);

}  // namespace placedb
