// Builds BoW vectors and direct indices from per-feature quantisation results. Shared by every
// vocabulary kind (binary words, float words), which differ only in how they descend their tree.
#pragma once

#include <span>

#include "core/vocabulary/bow.h"
#include "core/vocabulary/weighting.h"

namespace placedb {

// Empties what a Transform fills (either may be null). With a direct index, `levels_up` is
// clamped to >= 0 and recorded in it; the (possibly clamped) value is returned.
int ClearTransformOutputs(BowVector* bow, DirectIndex* direct, int levels_up);

// `feature_words[i]` is the word of feature i; `word_weights` the vocabulary's per-word weights.
// DBoW2 semantics: TF-IDF = occurrences * idf / n, TF = occurrences / n, IDF = idf once,
// BINARY = 1 once; words whose weight is not positive (idf 0: seen in every training image)
// carry nothing and are left out. The result is sorted by word id and not normalised.
void BuildBowVector(std::span<const WordId> feature_words, const float* word_weights,
                    WeightingType weighting, BowVector* bow);

// `feature_nodes[i]` is the direct-index node of feature i. Fills node_ids (ascending), offsets
// and feature_ids (ascending per node); leaves direct->levels_up to the caller.
void BuildDirectIndex(std::span<const NodeId> feature_nodes, DirectIndex* direct);

}  // namespace placedb
