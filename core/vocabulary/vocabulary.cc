// Vocabulary: breadth-first layout in one aligned block, greedy descent, Transform, checksum.
#include "core/vocabulary/vocabulary.h"

#include <sys/mman.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <new>
#include <string>

#include "core/vocabulary/bow_builder.h"

namespace placedb {

namespace {

constexpr size_t kArrayAlignment = 64;
// Blocks this large get 2 MiB alignment and transparent huge pages: a 30 MB vocabulary then
// faults in 15 pages instead of 7500, which is most of a load's time otherwise.
constexpr size_t kHugePageBytes = size_t{2} << 20;

// The block starts with this record so that the checksum covers the parameters too.
struct BlockMeta {
  uint32_t tag;  // kMetaTag: tells a block from garbage early in validation
  int32_t branching;
  int32_t depth;
  int32_t scoring;
  int32_t weighting;
  uint32_t node_count;
  uint32_t word_count;
  uint8_t reserved[36];
};
static_assert(sizeof(BlockMeta) == 64);
constexpr uint32_t kMetaTag = 0x4D42444Cu;  // "LDBM"

constexpr size_t AlignUp(size_t value, size_t alignment) {
  return (value + alignment - 1) / alignment * alignment;
}

bool ValidScoring(int value) {
  return value >= 0 && value <= 5;
}
bool ValidWeighting(int value) {
  return value >= 0 && value <= 3;
}

// The child of a node closest to `d`, ties to the lower id. Branch-free: the minimum of
// (distance << 16 | child index) is the nearest child with the lowest index, and the running
// minimum of random distances would mispredict a branch about twice per node.
inline uint32_t NearestChild(const Descriptor256& d, const Descriptor256* children, uint32_t first,
                             uint32_t count) {
  uint32_t best = uint32_t(HammingDistance(d, children[first])) << 16;
  for (uint32_t c = 1; c < count; ++c) {
    best = std::min(best, (uint32_t(HammingDistance(d, children[first + c])) << 16) | c);
  }
  return first + (best & 0xFFFFu);
}

void PrefetchRange(const void* begin, size_t bytes) {
  const auto* p = static_cast<const char*>(begin);
  const uintptr_t first_line = reinterpret_cast<uintptr_t>(p) & ~uintptr_t{63};
  const uintptr_t last = reinterpret_cast<uintptr_t>(p) + bytes;
  for (uintptr_t line = first_line; line < last; line += 64) {
    __builtin_prefetch(reinterpret_cast<const void*>(line), 0, 3);
  }
}

}  // namespace

Vocabulary::~Vocabulary() {
  if (block_ != nullptr) ::operator delete(block_, std::align_val_t(block_alignment_));
}

std::string Vocabulary::checksum_hex() const {
  static constexpr char kHex[] = "0123456789abcdef";
  std::string hex(16, '0');
  for (int i = 0; i < 16; ++i) hex[15 - i] = kHex[(checksum_ >> (4 * i)) & 0xF];
  return hex;
}

Vocabulary::BlockLayout Vocabulary::LayoutFor(uint64_t node_count, uint64_t word_count) {
  BlockLayout layout;
  size_t offset = 0;
  auto take = [&offset](uint64_t bytes) {
    const size_t at = offset;
    offset = AlignUp(offset + size_t(bytes), kArrayAlignment);
    return at;
  };
  layout.meta = take(sizeof(BlockMeta));
  layout.node_descriptor = take(node_count * sizeof(Descriptor256));
  layout.first_child = take(node_count * 4);
  layout.child_count = take(node_count * 4);
  layout.node_word = take(node_count * 4);
  layout.word_weight = take(word_count * 4);
  layout.word_node = take(word_count * 4);
  layout.total = offset;
  return layout;
}

Result<std::unique_ptr<Vocabulary>> Vocabulary::Allocate(int branching, int depth,
                                                         ScoringType scoring,
                                                         WeightingType weighting,
                                                         uint32_t node_count, uint32_t word_count,
                                                         bool zero_fill) {
  const BlockLayout layout = LayoutFor(node_count, word_count);
  std::unique_ptr<Vocabulary> vocabulary(new (std::nothrow) Vocabulary());
  if (!vocabulary) return Status::ResourceExhausted("out of memory allocating a vocabulary");
  const size_t alignment = layout.total >= 4 * kHugePageBytes ? kHugePageBytes : kArrayAlignment;
  const size_t bytes = AlignUp(layout.total, alignment);
  void* block = ::operator new(bytes, std::align_val_t(alignment), std::nothrow);
  if (block == nullptr) {
    return Status::ResourceExhausted("out of memory allocating a " + std::to_string(bytes) +
                                     "-byte vocabulary block");
  }
  if (alignment == kHugePageBytes) madvise(block, bytes, MADV_HUGEPAGE);  // a hint only
  // Zeroed so that padding is deterministic: the checksum covers every byte.
  if (zero_fill) std::memset(block, 0, layout.total);

  Vocabulary& v = *vocabulary;
  v.block_ = static_cast<std::byte*>(block);
  v.block_alignment_ = alignment;
  v.block_bytes_ = layout.total;
  v.branching_ = branching;
  v.depth_ = depth;
  v.scoring_ = scoring;
  v.weighting_ = weighting;
  v.node_count_ = node_count;
  v.word_count_ = word_count;
  v.node_descriptor_ = reinterpret_cast<const Descriptor256*>(v.block_ + layout.node_descriptor);
  v.first_child_ = reinterpret_cast<const uint32_t*>(v.block_ + layout.first_child);
  v.child_count_ = reinterpret_cast<const uint32_t*>(v.block_ + layout.child_count);
  v.node_word_ = reinterpret_cast<const uint32_t*>(v.block_ + layout.node_word);
  v.word_weight_ = reinterpret_cast<const float*>(v.block_ + layout.word_weight);
  v.word_node_ = reinterpret_cast<const uint32_t*>(v.block_ + layout.word_node);

  BlockMeta meta{};
  meta.tag = kMetaTag;
  meta.branching = branching;
  meta.depth = depth;
  meta.scoring = static_cast<int32_t>(scoring);
  meta.weighting = static_cast<int32_t>(weighting);
  meta.node_count = node_count;
  meta.word_count = word_count;
  std::memcpy(v.block_ + layout.meta, &meta, sizeof(meta));
  return vocabulary;
}

Status Vocabulary::ValidateBlock() const {
  BlockMeta meta;
  std::memcpy(&meta, block_, sizeof(meta));
  if (meta.tag != kMetaTag || meta.branching != branching_ || meta.depth != depth_ ||
      meta.scoring != static_cast<int32_t>(scoring_) ||
      meta.weighting != static_cast<int32_t>(weighting_) || meta.node_count != node_count_ ||
      meta.word_count != word_count_) {
    return Status::Corruption("the block's parameter record disagrees with the header");
  }
  if (node_count_ < 2 || word_count_ < 1) {
    return Status::Corruption("a vocabulary needs a root with children");
  }
  // Breadth-first with contiguous children: the children of node i start right after those of
  // the previous inner node, and every node after the root lies in an earlier node's range.
  // That makes the arrays a tree (one parent each, parents first, no cycles), and the levels are
  // the successive runs of children.
  uint64_t next_child = 1;
  uint64_t level_end = 1;  // end of the current level's node range
  int level = 0;
  uint32_t leaves = 0;
  auto node_error = [](uint64_t node, const char* problem) {
    return Status::Corruption("node " + std::to_string(node) + " " + problem);
  };
  const uint32_t* child_count = child_count_;
  const uint32_t* first_child = first_child_;
  const uint32_t* node_word = node_word_;
  const uint32_t* word_node = word_node_;
  const uint32_t node_count = node_count_;
  const uint32_t word_count = word_count_;
  for (uint32_t node = 0; node < node_count; ++node) {
    if (node != 0 && node >= next_child) return node_error(node, "has no parent");
    if (node == level_end) {
      level_end = next_child;
      if (++level > depth_) return node_error(node, "is deeper than L");
    }
    const uint32_t count = child_count[node];
    if (count == 0) {
      const uint32_t word = node_word[node];
      if (word >= word_count) return node_error(node, "is a leaf without a valid word");
      if (word_node[word] != node)
        return node_error(node, "and its word do not point at each other");
      ++leaves;
      continue;
    }
    if (node_word[node] != kNoWord) return node_error(node, "has children and a word");
    if (count > uint32_t(branching_)) return node_error(node, "has more than k children");
    if (first_child[node] != next_child || next_child + count > node_count) {
      return node_error(node, "has an out-of-order or out-of-range child range");
    }
    next_child += count;
  }
  if (next_child != node_count_) return Status::Corruption("some nodes have no parent");
  if (leaves != word_count_)
    return Status::Corruption("the number of leaves is not the word count");
  for (uint32_t word = 0; word < word_count_; ++word) {
    if (!std::isfinite(word_weight_[word])) {
      return Status::Corruption("word " + std::to_string(word) + " has a non-finite weight");
    }
  }
  return Status::Ok();
}

Result<std::shared_ptr<const Vocabulary>> Vocabulary::FromTree(const VocabularyTree& tree) {
  if (tree.branching < 2 || tree.branching > 1024) {
    return Status::InvalidArgument("branching (k) must be in [2, 1024], got " +
                                   std::to_string(tree.branching));
  }
  if (tree.depth < 1 || tree.depth > 32) {
    return Status::InvalidArgument("depth (L) must be in [1, 32], got " +
                                   std::to_string(tree.depth));
  }
  if (!ValidScoring(static_cast<int>(tree.scoring))) {
    return Status::InvalidArgument("unknown scoring type " +
                                   std::to_string(static_cast<int>(tree.scoring)));
  }
  if (!ValidWeighting(static_cast<int>(tree.weighting))) {
    return Status::InvalidArgument("unknown weighting type " +
                                   std::to_string(static_cast<int>(tree.weighting)));
  }
  const size_t n = tree.parent.size();
  if (n < 2) return Status::InvalidArgument("the tree needs a root and at least one word");
  if (n >= size_t{kNoWord}) return Status::InvalidArgument("the tree has too many nodes");
  if (tree.descriptor.size() != n || tree.weight.size() != n || tree.word_id.size() != n) {
    return Status::InvalidArgument("tree arrays differ in size: parent " + std::to_string(n) +
                                   ", descriptor " + std::to_string(tree.descriptor.size()) +
                                   ", weight " + std::to_string(tree.weight.size()) + ", word_id " +
                                   std::to_string(tree.word_id.size()));
  }

  // Children in id order, as a CSR list; levels.
  std::vector<uint32_t> child_count(n, 0);
  std::vector<uint8_t> level(n, 0);
  for (size_t i = 1; i < n; ++i) {
    const uint32_t p = tree.parent[i];
    if (p >= i) {
      return Status::InvalidArgument("node " + std::to_string(i) + " has parent " +
                                     std::to_string(p) + ", which does not come before it");
    }
    if (++child_count[p] > uint32_t(tree.branching)) {
      return Status::InvalidArgument("node " + std::to_string(p) + " has more than k = " +
                                     std::to_string(tree.branching) + " children");
    }
    if (level[p] + 1 > tree.depth) {
      return Status::InvalidArgument("node " + std::to_string(i) +
                                     " is deeper than L = " + std::to_string(tree.depth));
    }
    level[i] = uint8_t(level[p] + 1);
  }
  size_t words = 0;
  for (size_t i = 0; i < n; ++i) {
    const bool leaf = child_count[i] == 0;
    if (leaf != (tree.word_id[i] >= 0)) {
      return Status::InvalidArgument(
          "node " + std::to_string(i) +
          (leaf ? " has no children but no word id" : " has children but a word id"));
    }
    if (leaf) ++words;
  }
  std::vector<uint32_t> word_seen(words, kNoWord);
  for (size_t i = 0; i < n; ++i) {
    if (tree.word_id[i] < 0) continue;
    const auto word = size_t(tree.word_id[i]);
    if (word >= words) {
      return Status::InvalidArgument("node " + std::to_string(i) + " has word id " +
                                     std::to_string(word) + " but there are only " +
                                     std::to_string(words) + " leaves");
    }
    if (word_seen[word] != kNoWord) {
      return Status::InvalidArgument("word id " + std::to_string(word) + " is used by nodes " +
                                     std::to_string(word_seen[word]) + " and " + std::to_string(i));
    }
    word_seen[word] = uint32_t(i);
    if (!std::isfinite(tree.weight[i])) {
      return Status::InvalidArgument("node " + std::to_string(i) + " has a non-finite weight");
    }
  }

  std::vector<uint32_t> child_begin(n + 1, 0);
  for (size_t i = 0; i < n; ++i) child_begin[i + 1] = child_begin[i] + child_count[i];
  std::vector<uint32_t> children(n > 0 ? n - 1 : 0);
  {
    std::vector<uint32_t> fill(child_begin.begin(), child_begin.end() - 1);
    for (size_t i = 1; i < n; ++i) children[fill[tree.parent[i]]++] = uint32_t(i);
  }

  // Breadth-first order: the queue itself is the new numbering (new id = queue position), and
  // it keeps siblings in their original id order, which is what "ties to the lower id" means.
  std::vector<uint32_t> order;
  order.reserve(n);
  order.push_back(0);
  for (size_t head = 0; head < order.size(); ++head) {
    const uint32_t old = order[head];
    for (uint32_t c = child_begin[old]; c < child_begin[old + 1]; ++c) {
      order.push_back(children[c]);
    }
  }

  auto allocated = Allocate(tree.branching, tree.depth, tree.scoring, tree.weighting, uint32_t(n),
                            uint32_t(words));
  if (!allocated.ok()) return allocated.status();
  std::unique_ptr<Vocabulary> v = std::move(allocated).value();
  auto* descriptor = v->MutableArray(v->node_descriptor_);
  auto* first_child = v->MutableArray(v->first_child_);
  auto* count = v->MutableArray(v->child_count_);
  auto* node_word = v->MutableArray(v->node_word_);
  auto* word_weight = v->MutableArray(v->word_weight_);
  auto* word_node = v->MutableArray(v->word_node_);
  uint32_t next_child = 1;
  for (size_t id = 0; id < n; ++id) {
    const uint32_t old = order[id];
    if (id != 0) descriptor[id] = tree.descriptor[old];
    count[id] = child_count[old];
    // Leaves point where their children would start: keeps first_child monotonic.
    first_child[id] = next_child;
    next_child += child_count[old];
    if (child_count[old] == 0) {
      const auto word = uint32_t(tree.word_id[old]);
      node_word[id] = word;
      word_node[word] = uint32_t(id);
      word_weight[word] = tree.weight[old];
    } else {
      node_word[id] = kNoWord;
    }
  }
  v->checksum_ = Checksum64(v->block_, v->block_bytes_);
  return std::shared_ptr<const Vocabulary>(std::move(v));
}

std::vector<uint32_t> Vocabulary::Parents() const {
  std::vector<uint32_t> parent(node_count_, 0);
  for (uint32_t node = 0; node < node_count_; ++node) {
    const uint32_t first = first_child_[node];
    for (uint32_t c = 0; c < child_count_[node]; ++c) parent[first + c] = node;
  }
  return parent;
}

VocabularyTree Vocabulary::ToTree() const {
  VocabularyTree tree;
  tree.branching = branching_;
  tree.depth = depth_;
  tree.scoring = scoring_;
  tree.weighting = weighting_;
  tree.parent = Parents();
  tree.descriptor.assign(node_descriptor_, node_descriptor_ + node_count_);
  tree.weight.assign(node_count_, 0.0f);
  tree.word_id.assign(node_count_, -1);
  for (uint32_t word = 0; word < word_count_; ++word) {
    tree.weight[word_node_[word]] = word_weight_[word];
    tree.word_id[word_node_[word]] = int32_t(word);
  }
  return tree;
}

WordId Vocabulary::WordOf(const Descriptor256& descriptor) const {
  uint32_t node = 0;
  while (child_count_[node] != 0) {
    node = NearestChild(descriptor, node_descriptor_, first_child_[node], child_count_[node]);
  }
  return node_word_[node];
}

void Vocabulary::Descend(const Descriptor256* descriptors, size_t count, uint32_t* leaf,
                         uint32_t* group, int group_level) const {
  // Lanes descend one level per pass, round robin: while one lane computes, the children block
  // prefetched for the others arrives, so the cache misses of the deep levels overlap. Prefetching
  // a node's children also fetches their (contiguous) child ranges, which the next pass reads.
  constexpr size_t kLanes = 16;
  uint32_t node[kLanes];
  for (size_t base = 0; base < count; base += kLanes) {
    const size_t lanes = std::min(kLanes, count - base);
    std::fill(node, node + lanes, 0u);
    if (group != nullptr) std::fill(group + base, group + base + lanes, 0u);
    for (int level = 1;; ++level) {
      bool moved = false;
      for (size_t j = 0; j < lanes; ++j) {
        const uint32_t current = node[j];
        const uint32_t children = child_count_[current];
        if (children == 0) continue;
        const uint32_t best =
            NearestChild(descriptors[base + j], node_descriptor_, first_child_[current], children);
        node[j] = best;
        if (group != nullptr && level <= group_level) group[base + j] = best;
        const uint32_t next_children = child_count_[best];
        if (next_children != 0) {
          const uint32_t next_first = first_child_[best];
          PrefetchRange(node_descriptor_ + next_first, next_children * sizeof(Descriptor256));
          PrefetchRange(first_child_ + next_first, next_children * 4);
          PrefetchRange(child_count_ + next_first, next_children * 4);
        } else {
          __builtin_prefetch(node_word_ + best, 0, 3);
        }
        moved = true;
      }
      if (!moved) break;
    }
    std::copy(node, node + lanes, leaf + base);
  }
}

void Vocabulary::Transform(std::span<const Descriptor256> descriptors, BowVector* bow,
                           DirectIndex* direct, int levels_up) const {
  const size_t n = descriptors.size();
  levels_up = ClearTransformOutputs(bow, direct, levels_up);
  if (n == 0) return;

  thread_local std::vector<uint32_t> leaf;
  thread_local std::vector<uint32_t> group;
  leaf.resize(n);
  if (direct != nullptr) group.resize(n);
  Descend(descriptors.data(), n, leaf.data(), direct != nullptr ? group.data() : nullptr,
          std::max(0, depth_ - levels_up));
  if (bow != nullptr) {
    for (uint32_t& node : leaf) node = node_word_[node];  // leaves -> their words
    BuildBowVector(leaf, word_weight_, weighting_, bow);
  }
  if (direct != nullptr) BuildDirectIndex(group, direct);
}

}  // namespace placedb
