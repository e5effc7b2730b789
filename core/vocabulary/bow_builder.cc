#include "core/vocabulary/bow_builder.h"

#include <algorithm>
#include <cstdint>
#include <vector>

namespace placedb {

int ClearTransformOutputs(BowVector* bow, DirectIndex* direct, int levels_up) {
  if (bow != nullptr) bow->clear();
  if (direct != nullptr) {
    levels_up = std::max(levels_up, 0);
    direct->levels_up = levels_up;
    direct->node_ids.clear();
    direct->offsets.clear();
    direct->feature_ids.clear();
  }
  return levels_up;
}

void BuildBowVector(std::span<const WordId> feature_words, const float* word_weights,
                    WeightingType weighting, BowVector* bow) {
  bow->clear();
  const size_t n = feature_words.size();
  if (n == 0) return;
  thread_local std::vector<WordId> sorted;
  sorted.assign(feature_words.begin(), feature_words.end());
  std::sort(sorted.begin(), sorted.end());
  bow->reserve(n);
  const double inverse_n = 1.0 / double(n);
  for (size_t i = 0; i < n;) {
    const WordId word = sorted[i];
    size_t j = i + 1;
    while (j < n && sorted[j] == word) ++j;
    const double occurrences = double(j - i);
    double weight = 0;
    switch (weighting) {
      case WeightingType::kTfIdf:
        weight = occurrences * word_weights[word] * inverse_n;
        break;
      case WeightingType::kTf:
        weight = occurrences * inverse_n;
        break;
      case WeightingType::kIdf:
        weight = word_weights[word];
        break;
      case WeightingType::kBinary:
        weight = 1.0;
        break;
    }
    if (weight > 0) bow->push_back(BowEntry{word, float(weight)});
    i = j;
  }
}

void BuildDirectIndex(std::span<const NodeId> feature_nodes, DirectIndex* direct) {
  direct->node_ids.clear();
  direct->offsets.clear();
  direct->feature_ids.clear();
  const size_t n = feature_nodes.size();
  if (n == 0) return;
  // (node << 32 | feature) pairs: one sort gives both the grouping and ascending feature ids.
  thread_local std::vector<uint64_t> keyed;
  keyed.resize(n);
  for (size_t i = 0; i < n; ++i) keyed[i] = (uint64_t(feature_nodes[i]) << 32) | i;
  std::sort(keyed.begin(), keyed.end());
  direct->feature_ids.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const auto node = NodeId(keyed[i] >> 32);
    if (i == 0 || node != direct->node_ids.back()) {
      direct->node_ids.push_back(node);
      direct->offsets.push_back(uint32_t(i));
    }
    direct->feature_ids[i] = uint32_t(keyed[i]);
  }
  direct->offsets.push_back(uint32_t(n));
}

DirectIndex MergeDirectIndices(const DirectIndex& a, const DirectIndex& b, uint32_t b_offset) {
  DirectIndex merged;
  merged.levels_up = a.levels_up;
  merged.offsets.push_back(0);
  size_t i = 0, j = 0;
  while (i < a.node_ids.size() || j < b.node_ids.size()) {
    const bool take_a =
        j >= b.node_ids.size() || (i < a.node_ids.size() && a.node_ids[i] <= b.node_ids[j]);
    const bool take_b =
        i >= a.node_ids.size() || (j < b.node_ids.size() && b.node_ids[j] <= a.node_ids[i]);
    merged.node_ids.push_back(take_a ? a.node_ids[i] : b.node_ids[j]);
    if (take_a) {
      for (uint32_t f : a.features_of(i)) merged.feature_ids.push_back(f);
      ++i;
    }
    if (take_b) {
      for (uint32_t f : b.features_of(j)) merged.feature_ids.push_back(f + b_offset);
      ++j;
    }
    merged.offsets.push_back(uint32_t(merged.feature_ids.size()));
  }
  if (merged.node_ids.empty()) merged.offsets.clear();
  return merged;
}

}  // namespace placedb
