// Bag-of-words vectors and the direct index, as produced by Vocabulary::Transform().
#pragma once

#include <cstdint>
#include <span>
#include <vector>

namespace placedb {

using WordId = uint32_t;
using NodeId = uint32_t;

struct BowEntry {
  WordId word;
  float weight;
  bool operator==(const BowEntry&) const = default;
};

// Sparse word -> weight vector, sorted by word id, no duplicate words, no zero weights.
using BowVector = std::vector<BowEntry>;

// The direct index of one frame: for each vocabulary node at the chosen level, the ids of the
// frame's features that descend through it (DBoW2's FeatureVector). Geometric verification only
// compares features that share a node. Flattened for compactness: the features of node_ids[i]
// are feature_ids[offsets[i] .. offsets[i+1]); node_ids ascending, feature ids ascending per node.
struct DirectIndex {
  int levels_up = 0;  // nodes are `levels_up` levels above the words (0 = the words themselves)
  std::vector<NodeId> node_ids;
  std::vector<uint32_t> offsets;  // node_ids.size() + 1 entries when non-empty
  std::vector<uint32_t> feature_ids;

  size_t node_count() const { return node_ids.size(); }
  std::span<const uint32_t> features_of(size_t i) const {
    return {feature_ids.data() + offsets[i], feature_ids.data() + offsets[i + 1]};
  }
  bool operator==(const DirectIndex&) const = default;
};

// The direct index of the features of `a` followed by those of `b` (whose ids are shifted by
// `b_offset`, the size of a's feature set); both at the same level.
DirectIndex MergeDirectIndices(const DirectIndex& a, const DirectIndex& b, uint32_t b_offset);

}  // namespace placedb
