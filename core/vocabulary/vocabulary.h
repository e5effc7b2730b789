// The vocabulary: a hierarchical tree of binary words (k branches, L levels) with TF-IDF weights.
//
// Layout: nodes are numbered breadth-first and the children of a node are contiguous, so one
// descent step is k Hamming distances over k adjacent 32-byte descriptors. All arrays live in one
// 64-byte-aligned block; the binary file is a fixed header followed by that block verbatim, so a
// load is one read plus a checksum pass, and the checksum (of the block) is the vocabulary's
// identity. A Vocabulary is immutable once built; share it as shared_ptr<const Vocabulary>:
// databases reference it, they never copy it.
//
// Formats:
//  - binary ".pdbv" (this project, versioned, checksummed): SaveBinary/LoadBinary;
//  - DBoW2/DBoW3 text, the format of ORB-SLAM's ORBvoc.txt: ImportDbow2Text/ExportDbow2Text.
//    Word ids follow the order of the leaves in the text file, so BoW vectors equal DBoW2's.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/features/descriptor.h"
#include "core/vocabulary/bow.h"
#include "core/vocabulary/weighting.h"

namespace placedb {

// A pointer-free description of a tree, used to build a Vocabulary (by the trainer and the text
// importer). Node 0 is the root; every other node names its parent, which must come earlier.
struct VocabularyTree {
  int branching = 10;  // k
  int depth = 6;       // L: words are at most L levels below the root
  ScoringType scoring = ScoringType::kL1;
  WeightingType weighting = WeightingType::kTfIdf;
  std::vector<uint32_t> parent;           // parent[0] is ignored
  std::vector<Descriptor256> descriptor;  // descriptor[0] is ignored
  std::vector<float> weight;              // word weight (idf) of leaves; ignored for inner nodes
  std::vector<int32_t> word_id;           // 0..W-1 for leaves (each once), -1 for inner nodes
};

class Vocabulary {
 public:
  static constexpr uint32_t kNoWord = 0xFFFFFFFFu;

  // Validates the tree (parents precede children, leaves are exactly the nodes with word ids,
  // word ids are 0..W-1 each once, at most `branching` children per node, depth <= L) and lays
  // it out breadth-first. INVALID_ARGUMENT naming the first problem otherwise.
  static Result<std::shared_ptr<const Vocabulary>> FromTree(const VocabularyTree& tree);

  static Result<std::shared_ptr<const Vocabulary>> LoadBinary(const std::string& path);
  Status SaveBinary(const std::string& path) const;  // atomic: temp file + rename
  // The bytes SaveBinary writes, and their parser (the checks of LoadBinary, without a path in
  // the messages): how a map stores the vocabulary it learned (core/storage).
  std::string SerializeBinary() const;
  static Result<std::shared_ptr<const Vocabulary>> ParseBinary(std::string_view bytes);
  static Result<std::shared_ptr<const Vocabulary>> ImportDbow2Text(const std::string& path);
  Status ExportDbow2Text(const std::string& path) const;
  // Picks the format from the file's first bytes (binary magic, else DBoW2 text).
  static Result<std::shared_ptr<const Vocabulary>> Load(const std::string& path);

  ~Vocabulary();
  Vocabulary(const Vocabulary&) = delete;
  Vocabulary& operator=(const Vocabulary&) = delete;

  int branching() const { return branching_; }
  int depth() const { return depth_; }
  ScoringType default_scoring() const { return scoring_; }
  WeightingType weighting() const { return weighting_; }
  uint32_t node_count() const { return node_count_; }
  uint32_t word_count() const { return word_count_; }
  uint64_t checksum() const { return checksum_; }  // identity of the vocabulary's contents
  std::string checksum_hex() const;                // 16 lowercase hex digits
  size_t memory_bytes() const { return block_bytes_; }

  // The leaf reached by greedy descent (ties go to the lower node id).
  WordId WordOf(const Descriptor256& descriptor) const;
  float WordWeight(WordId word) const { return word_weight_[word]; }
  NodeId NodeOfWord(WordId word) const { return word_node_[word]; }

  // Quantises `descriptors` into a weighted BoW vector (weighting() applied, not normalised:
  // see NormalizeForScoring) and, when `direct` is given, the direct index at `levels_up` levels
  // above the words (>= depth() puts every feature under the root: exhaustive matching).
  void Transform(std::span<const Descriptor256> descriptors, BowVector* bow, DirectIndex* direct,
                 int levels_up) const;

  // Node-level access for export and tests.
  const Descriptor256& NodeDescriptor(NodeId node) const { return node_descriptor_[node]; }
  NodeId FirstChild(NodeId node) const { return first_child_[node]; }
  uint32_t ChildCount(NodeId node) const { return child_count_[node]; }
  WordId NodeWord(NodeId node) const { return node_word_[node]; }

  // Rebuilds the pointer-free tree (in breadth-first numbering), e.g. to edit or re-export.
  VocabularyTree ToTree() const;

 private:
  Vocabulary() = default;

  // Byte offsets of the arrays inside the block; a pure function of the counts, so the binary
  // loader can check a file's size before reading it.
  struct BlockLayout {
    size_t meta = 0;
    size_t node_descriptor = 0;
    size_t first_child = 0;
    size_t child_count = 0;
    size_t node_word = 0;
    size_t word_weight = 0;
    size_t word_node = 0;
    size_t total = 0;
  };
  static BlockLayout LayoutFor(uint64_t node_count, uint64_t word_count);
  // CORRUPTION unless the block's size fits the counts and `total_bytes` = header + block.
  static Status CheckBlockSize(uint32_t node_count, uint32_t word_count, uint64_t block_bytes,
                               uint64_t total_bytes);

  // A vocabulary owning a block sized for the counts (zeroed unless a file is about to fill it),
  // every array pointer bound, the parameters stored both in the members and in the block's
  // leading meta record (so the checksum covers them). Fails only on allocation.
  static Result<std::unique_ptr<Vocabulary>> Allocate(int branching, int depth, ScoringType scoring,
                                                      WeightingType weighting, uint32_t node_count,
                                                      uint32_t word_count, bool zero_fill = true);
  // Checks a block that came from outside (a file): meta record agrees with the members, child
  // ranges in bounds and breadth-first (which makes it a tree), depth <= L, word <-> node maps.
  // CORRUPTION naming the problem. Parents and levels are implied by the breadth-first layout,
  // so the block does not store them (less to read and to check).
  Status ValidateBlock() const;
  template <typename T>
  T* MutableArray(const T* array) const {
    return const_cast<T*>(array);
  }

  std::vector<uint32_t> Parents() const;  // parent of every node (the root's is 0)
  // An order to list the nodes in DBoW2 text (the root excluded) that reads back as this tree:
  // each node after its parent, siblings in the tree's order (which breaks distance ties in
  // Transform), and leaves in word-id order (the format numbers words by leaf line). Empty when
  // the word numbering allows no such order; DBoW2's files and our trainer's trees always do.
  std::vector<uint32_t> TextExportOrder() const;

  // Lockstep greedy descent of `count` descriptors: leaf node of each, and (when `group` is
  // given) the node at `group_level` on its path, or the leaf when that is shallower.
  void Descend(const Descriptor256* descriptors, size_t count, uint32_t* leaf, uint32_t* group,
               int group_level) const;

  int branching_ = 0;
  int depth_ = 0;
  ScoringType scoring_ = ScoringType::kL1;
  WeightingType weighting_ = WeightingType::kTfIdf;
  uint32_t node_count_ = 0;
  uint32_t word_count_ = 0;
  uint64_t checksum_ = 0;

  // One aligned allocation holding every array below, in this order, after a 64-byte meta record.
  std::byte* block_ = nullptr;
  size_t block_bytes_ = 0;
  size_t block_alignment_ = 64;
  const Descriptor256* node_descriptor_ = nullptr;  // [node_count]
  const uint32_t* first_child_ = nullptr;           // [node_count]; children are contiguous
  const uint32_t* child_count_ = nullptr;           // [node_count]; 0 for leaves
  const uint32_t* node_word_ = nullptr;             // [node_count]; kNoWord for inner nodes
  const float* word_weight_ = nullptr;              // [word_count]
  const uint32_t* word_node_ = nullptr;             // [word_count]
};

// A fast 64-bit hash over bytes (4 independent multiply-rotate lanes); used for checksums.
uint64_t Checksum64(const void* data, size_t bytes, uint64_t seed = 0);

}  // namespace placedb
