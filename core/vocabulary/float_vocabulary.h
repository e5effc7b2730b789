// A vocabulary of float words (SIFT): the role of vocabulary.h for real-valued descriptors.
//
// A hierarchical k-means tree (k branches, L levels) with Euclidean (L2) distance, trained here:
// at every node k-means++ seeding then Lloyd iterations with mean centres, recursion to depth L.
// Word weights are idf = ln(N / n_i) over the training images. Transform() quantises descriptors by
// greedy descent (nearest child centre by squared L2, ties to the lower node id) into the same
// BowVector / DirectIndex types as the binary vocabulary, so scoring.h and the InvertedIndex work
// unchanged on SIFT.
//
// Determinism: the same training data and seed give the same tree, bit for bit, at any thread
// count. Nodes are numbered breadth-first (children contiguous); every node draws from its own RNG
// stream derived from (seed, node id); the parallel assignment step works on fixed chunks whose
// partial sums are reduced in chunk order.
//
// File format ".pdbfv": a 64-byte header (magic "PDBFVOC1", version, endianness marker, the
// parameters and counts, payload size, checksum) followed by the arrays verbatim. A load checks
// sizes, the checksum and the tree structure (CORRUPTION naming the problem). The checksum covers
// the parameters and the arrays and is the vocabulary's identity, as for the binary vocabulary.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/vocabulary/bow.h"
#include "core/vocabulary/weighting.h"

namespace placedb {

struct FloatTrainerConfig {
  int branching = 10;  // k, in [2, 64]
  int depth = 5;       // L, in [1, 10]
  uint64_t seed = 1;
  int threads = 1;          // threads for the assignment step; 0 = all hardware threads
  int max_iterations = 10;  // Lloyd iterations per node (stops early when assignments settle)
  // Centres of a node are fitted on at most this many of its descriptors (a deterministic random
  // sample), then every descriptor is assigned to them; 0 = fit on all.
  size_t max_fit_samples = 50000;
  WeightingType weighting = WeightingType::kTfIdf;
  ScoringType scoring = ScoringType::kL1;  // recorded as the vocabulary's default
};

Status ValidateFloatTrainerConfig(const FloatTrainerConfig& config);

using FloatTrainerProgress = std::function<void(double fraction, const char* phase)>;

class FloatVocabulary {
 public:
  static constexpr uint32_t kNoWord = 0xFFFFFFFFu;

  // `images[i]` holds the descriptors of training image i, `dimensions` floats each, row-major.
  // INVALID_ARGUMENT for a bad config, a size that is not a multiple of `dimensions`, a
  // non-finite value, or fewer descriptors than `branching`.
  static Result<std::shared_ptr<const FloatVocabulary>> Train(
      const std::vector<std::vector<float>>& images, int dimensions,
      const FloatTrainerConfig& config, const FloatTrainerProgress& progress = {});

  static Result<std::shared_ptr<const FloatVocabulary>> Load(const std::string& path);
  Status Save(const std::string& path) const;  // atomic: temp file + rename
  // The bytes Save writes, and their parser (Load's checks; messages without the path): how a
  // map stores the vocabulary it learned (core/storage).
  std::string Serialize() const;
  static Result<std::shared_ptr<const FloatVocabulary>> Parse(std::string_view bytes);

  FloatVocabulary(const FloatVocabulary&) = delete;
  FloatVocabulary& operator=(const FloatVocabulary&) = delete;

  int dimensions() const { return dimensions_; }
  int branching() const { return branching_; }
  int depth() const { return depth_; }
  ScoringType default_scoring() const { return scoring_; }
  WeightingType weighting() const { return weighting_; }
  uint32_t node_count() const { return uint32_t(child_count_.size()); }
  uint32_t word_count() const { return uint32_t(word_node_.size()); }
  uint64_t checksum() const { return checksum_; }
  std::string checksum_hex() const;
  size_t memory_bytes() const;

  // The word reached by greedy descent. `descriptor` holds dimensions() floats.
  WordId WordOf(const float* descriptor) const;
  float WordWeight(WordId word) const { return word_weight_[word]; }
  NodeId NodeOfWord(WordId word) const { return word_node_[word]; }

  // Quantises `descriptors` (a multiple of dimensions() floats; a trailing partial row is
  // ignored) into a weighted BoW vector (weighting() applied, not normalised: see
  // NormalizeForScoring) and, when `direct` is given, the direct index at `levels_up` levels above
  // the words (>= depth() puts every feature under the root). Same contract as
  // Vocabulary::Transform.
  void Transform(std::span<const float> descriptors, BowVector* bow, DirectIndex* direct,
                 int levels_up) const;

  // Node-level access for tests.
  std::span<const float> NodeCentre(NodeId node) const {
    return {centres_.data() + size_t(node) * size_t(dimensions_), size_t(dimensions_)};
  }
  NodeId FirstChild(NodeId node) const { return first_child_[node]; }
  uint32_t ChildCount(NodeId node) const { return child_count_[node]; }
  WordId NodeWord(NodeId node) const { return node_word_[node]; }

 private:
  FloatVocabulary() = default;
  // Structure and values of a vocabulary from outside (a file): CORRUPTION naming the problem.
  Status Validate() const;
  uint64_t ComputeChecksum() const;
  // The leaf of `descriptor`, and the node at `group_level` on its path (or the leaf when that
  // is shallower).
  uint32_t Descend(const float* descriptor, int group_level, uint32_t* group) const;

  int dimensions_ = 0;
  int branching_ = 0;
  int depth_ = 0;
  ScoringType scoring_ = ScoringType::kL1;
  WeightingType weighting_ = WeightingType::kTfIdf;
  uint64_t checksum_ = 0;
  std::vector<uint32_t> first_child_;  // [nodes]; children are contiguous, breadth-first
  std::vector<uint32_t> child_count_;  // [nodes]; 0 for leaves
  std::vector<uint32_t> node_word_;    // [nodes]; kNoWord for inner nodes
  std::vector<uint32_t> word_node_;    // [words]
  std::vector<float> word_weight_;     // [words]
  std::vector<float> centres_;         // [nodes * dimensions]; the root's is zero
};

// Squared Euclidean distance between two `n`-float vectors.
float SquaredL2(const float* a, const float* b, int n);

}  // namespace placedb
