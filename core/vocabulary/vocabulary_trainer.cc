// Hierarchical k-means over binary descriptors, level by level.
//
// The tree grows breadth-first: all nodes of one level are split before the next level starts,
// and children are numbered in parent order, so the node ids come out breadth-first with
// contiguous children and word ids in breadth-first leaf order (what the DBoW2 text format
// preserves). Each node owns a contiguous range of a working copy of the descriptors; splitting
// it reorders the range by cluster so that the children own sub-ranges.
//
// Threads: large nodes (the top levels) are split one at a time with their passes over the
// descriptors cut into fixed-size chunks; the many small nodes below are split in parallel, one
// per thread. Neither changes a result: chunking is fixed, every reduction is an integer sum,
// and each node draws from its own random stream keyed by its path from the root.
#include "core/vocabulary/vocabulary_trainer.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstring>
#include <new>
#include <string>
#include <thread>

#include "core/base/parallel.h"

namespace placedb {

namespace {

constexpr size_t kChunk = 4096;            // descriptors per parallel task
constexpr size_t kLargeNode = 8 * kChunk;  // nodes this big are split with all threads
constexpr uint8_t kUnassigned = 0xFF;      // branching <= 64 fits in a byte
constexpr uint64_t kStreamSalt = 0x6c8e9cf570932bd5ull;

// A counter-based random stream: value i is a hash of i keyed by the stream's key.
class RandomStream {
 public:
  explicit RandomStream(uint64_t key) : key_(key) {}
  uint64_t Next() {
    const uint64_t counter = counter_++;
    return Checksum64(&counter, sizeof(counter), key_);
  }
  // Uniform in [0, bound) (bound > 0), by the high half of a 128-bit product.
  uint64_t Below(uint64_t bound) {
    return uint64_t((static_cast<unsigned __int128>(Next()) * bound) >> 64);
  }

 private:
  uint64_t key_;
  uint64_t counter_ = 0;
};

uint64_t ChildKey(uint64_t parent_key, uint64_t child_index) {
  const uint64_t words[2] = {parent_key, child_index};
  return Checksum64(words, sizeof(words), kStreamSalt);
}

// kSpread[v] has byte j = bit j of v (bit j of descriptor byte i is descriptor bit 8i+j).
constexpr std::array<uint64_t, 256> MakeSpread() {
  std::array<uint64_t, 256> table{};
  for (int v = 0; v < 256; ++v) {
    for (int j = 0; j < 8; ++j) table[size_t(v)] |= uint64_t((v >> j) & 1) << (8 * j);
  }
  return table;
}
constexpr std::array<uint64_t, 256> kSpread = MakeSpread();

// Per-cluster bit counts of descriptors, for bitwise-majority centres. Counting is SWAR: a
// cluster keeps 256 8-bit counters packed in 32 words, and adding a descriptor adds, per byte,
// a table word holding that byte's 8 bits one per lane: 32 additions instead of 256. The lanes
// are flushed into 32-bit counts every 255 additions, before a lane can overflow. Only clusters
// touched since the last drain cost anything, which matters for the many tiny nodes.
class BitCounter {
 public:
  explicit BitCounter(int clusters)
      : lanes_(size_t(clusters) * kLaneWords, 0),
        pending_(size_t(clusters), 0),
        counts_(size_t(clusters) * Descriptor256::kBits, 0),
        members_(size_t(clusters), 0),
        touched_flag_(size_t(clusters), 0) {}

  void Add(int cluster, const Descriptor256& d) {
    const auto c = size_t(cluster);
    if (!touched_flag_[c]) {
      touched_flag_[c] = 1;
      touched_.push_back(cluster);
    }
    uint64_t* lanes = &lanes_[c * kLaneWords];
    const uint8_t* bytes = d.bytes();
    for (int i = 0; i < kLaneWords; ++i) lanes[i] += kSpread[bytes[i]];
    if (++pending_[c] == 255) FlushLanes(c);
  }

  // Adds this counter's totals into `counts` (clusters x 256) and `members`, and clears it.
  void DrainInto(uint32_t* counts, uint64_t* members) {
    for (int cluster : touched_) {
      const auto c = size_t(cluster);
      FlushLanes(c);
      uint32_t* own = &counts_[c * Descriptor256::kBits];
      uint32_t* out = counts + c * Descriptor256::kBits;
      for (int b = 0; b < Descriptor256::kBits; ++b) out[b] += own[b];
      std::fill(own, own + Descriptor256::kBits, 0u);
      members[c] += members_[c];
      members_[c] = 0;
      touched_flag_[c] = 0;
    }
    touched_.clear();
  }

 private:
  static constexpr int kLaneWords = Descriptor256::kBytes;

  void FlushLanes(size_t c) {
    if (pending_[c] == 0) return;
    uint64_t* lanes = &lanes_[c * kLaneWords];
    uint32_t* counts = &counts_[c * Descriptor256::kBits];
    for (int i = 0; i < kLaneWords; ++i) {
      for (int j = 0; j < 8; ++j) counts[8 * i + j] += uint32_t((lanes[i] >> (8 * j)) & 0xFF);
      lanes[i] = 0;
    }
    members_[c] += pending_[c];
    pending_[c] = 0;
  }

  std::vector<uint64_t> lanes_;
  std::vector<uint32_t> pending_;
  std::vector<uint32_t> counts_;
  std::vector<uint64_t> members_;
  std::vector<uint8_t> touched_flag_;
  std::vector<int> touched_;
};

// Scratch owned by one thread, reused across nodes. `totals` and `members` are all zero between
// uses (the centre update clears what it used).
struct Workspace {
  explicit Workspace(int clusters)
      : counter(clusters),
        totals(size_t(clusters) * Descriptor256::kBits, 0),
        members(size_t(clusters), 0) {}
  BitCounter counter;
  std::vector<uint32_t> totals;
  std::vector<uint64_t> members;
};

struct SplitResult {
  enum class Kind { kLeaf, kLeafChildren, kClusters };
  Kind kind = Kind::kLeaf;
  std::vector<Descriptor256> centres;  // the children's descriptors, in child order (kLeaf: the
                                       // node's only distinct descriptor)
  std::vector<uint32_t> sizes;         // kClusters: descriptors per child (contiguous, in order)
};

class Trainer {
 public:
  Trainer(const TrainerConfig& config, int threads, std::vector<Descriptor256> data)
      : config_(config),
        threads_(threads),
        k_(config.branching),
        data_(std::move(data)),
        scratch_(data_.size()),
        assignment_(data_.size(), kUnassigned),
        distance_(data_.size(), 0),
        workspaces_(size_t(threads), Workspace(config.branching)) {}

  // Splits the node owning data_[begin, end) using `threads` threads and workspaces
  // [first_workspace, first_workspace + threads).
  SplitResult Split(size_t begin, size_t end, uint64_t key, int threads, size_t first_workspace) {
    SplitResult result;
    // Few distinct descriptors: no clustering needed (and k-means++ could not find k seeds).
    std::vector<Descriptor256> distinct;
    for (size_t i = begin; i < end && distinct.size() <= size_t(k_); ++i) {
      if (std::find(distinct.begin(), distinct.end(), data_[i]) == distinct.end()) {
        distinct.push_back(data_[i]);
      }
    }
    if (distinct.size() == 1) {  // all equal: the node is a word itself (the root gets a child)
      result.centres = std::move(distinct);
      return result;
    }
    if (distinct.size() <= size_t(k_)) {
      result.kind = SplitResult::Kind::kLeafChildren;
      result.centres = std::move(distinct);
      return result;
    }

    const size_t n = end - begin;
    const size_t chunks = (n + kChunk - 1) / kChunk;
    auto chunk_range = [&](size_t chunk) {
      const size_t first = begin + chunk * kChunk;
      return std::pair<size_t, size_t>(first, std::min(end, first + kChunk));
    };
    RandomStream random(key);

    // k-means++ seeding with squared Hamming distances; integer sums make the draw exact.
    std::vector<Descriptor256> centres;
    centres.reserve(size_t(k_));
    centres.push_back(data_[begin + random.Below(n)]);
    std::vector<uint64_t> chunk_sum(chunks, 0);
    for (;;) {
      const Descriptor256 latest = centres.back();
      const bool first_pass = centres.size() == 1;
      ParallelFor(chunks, threads, [&](size_t chunk, int) {
        const auto [from, to] = chunk_range(chunk);
        uint64_t sum = 0;
        for (size_t i = from; i < to; ++i) {
          const int d = HammingDistance(data_[i], latest);
          const auto squared = uint32_t(d * d);
          if (first_pass || squared < distance_[i]) distance_[i] = squared;
          sum += distance_[i];
        }
        chunk_sum[chunk] = sum;
      });
      if (centres.size() == size_t(k_)) break;
      uint64_t total = 0;
      for (uint64_t sum : chunk_sum) total += sum;
      if (total == 0) break;  // cannot happen with > k distinct descriptors; be safe anyway
      uint64_t target = random.Below(total);
      size_t chunk = 0;
      while (target >= chunk_sum[chunk]) target -= chunk_sum[chunk++];
      size_t pick = chunk_range(chunk).first;
      while (target >= distance_[pick]) target -= distance_[pick++];
      centres.push_back(data_[pick]);
    }
    const int clusters = int(centres.size());

    // Lloyd iterations: nearest centre (ties to the lower index), then bitwise-majority centres
    // (ties per bit to 0). Stops when no assignment changes.
    std::fill(assignment_.begin() + ptrdiff_t(begin), assignment_.begin() + ptrdiff_t(end),
              kUnassigned);
    std::vector<uint64_t> chunk_changes(chunks, 0);
    Workspace& reducer = workspaces_[first_workspace];
    for (int iteration = 0; iteration < config_.max_iterations; ++iteration) {
      ParallelFor(chunks, threads, [&](size_t chunk, int worker) {
        const auto [from, to] = chunk_range(chunk);
        BitCounter& counter = workspaces_[first_workspace + size_t(worker)].counter;
        uint64_t changes = 0;
        for (size_t i = from; i < to; ++i) {
          const Descriptor256& d = data_[i];
          int best = 0;
          int best_distance = HammingDistance(d, centres[0]);
          for (int c = 1; c < clusters; ++c) {
            const int distance = HammingDistance(d, centres[size_t(c)]);
            if (distance < best_distance) {
              best_distance = distance;
              best = c;
            }
          }
          if (assignment_[i] != best) {
            assignment_[i] = uint8_t(best);
            ++changes;
          }
          counter.Add(best, d);
        }
        chunk_changes[chunk] = changes;
      });
      // Integer sums: the same totals whichever worker counted which chunk.
      for (int w = 0; w < threads; ++w) {
        workspaces_[first_workspace + size_t(w)].counter.DrainInto(reducer.totals.data(),
                                                                   reducer.members.data());
      }
      uint64_t changes = 0;
      for (uint64_t c : chunk_changes) changes += c;
      const bool settled = iteration > 0 && changes == 0;
      for (int c = 0; c < clusters; ++c) {
        uint64_t& members = reducer.members[size_t(c)];
        if (members == 0) continue;  // keep the old centre; dropped if still empty at the end
        uint32_t* bit_counts = &reducer.totals[size_t(c) * Descriptor256::kBits];
        if (!settled) {
          Descriptor256 centre;
          for (int b = 0; b < Descriptor256::kBits; ++b) {
            if (2 * uint64_t(bit_counts[b]) > members) {
              centre.words[size_t(b / 64)] |= uint64_t{1} << (b % 64);
            }
          }
          centres[size_t(c)] = centre;
        }
        std::fill(bit_counts, bit_counts + Descriptor256::kBits, 0u);
        members = 0;
      }
      if (settled) break;  // the centres already are these clusters' majorities
    }

    // Reorder the range by cluster (stable) so each child owns a contiguous sub-range; empty
    // clusters are dropped.
    std::vector<size_t> offset(size_t(clusters) + 1, 0);
    for (size_t i = begin; i < end; ++i) ++offset[size_t(assignment_[i]) + 1];
    for (int c = 0; c < clusters; ++c) offset[size_t(c) + 1] += offset[size_t(c)];
    result.kind = SplitResult::Kind::kClusters;
    for (int c = 0; c < clusters; ++c) {
      const size_t size = offset[size_t(c) + 1] - offset[size_t(c)];
      if (size == 0) continue;
      result.centres.push_back(centres[size_t(c)]);
      result.sizes.push_back(uint32_t(size));
    }
    for (size_t i = begin; i < end; ++i) scratch_[begin + offset[assignment_[i]]++] = data_[i];
    std::copy(scratch_.begin() + ptrdiff_t(begin), scratch_.begin() + ptrdiff_t(end),
              data_.begin() + ptrdiff_t(begin));
    return result;
  }

  // Grows the tree level by level; returns it without word weights.
  VocabularyTree Grow(const TrainerProgress& progress) {
    VocabularyTree tree;
    tree.branching = config_.branching;
    tree.depth = config_.depth;
    tree.parent.push_back(0);
    tree.descriptor.push_back(Descriptor256{});

    struct Pending {
      uint32_t id;
      size_t begin;
      size_t end;
      uint64_t key;
    };
    std::vector<Pending> level_nodes = {{0, 0, data_.size(), ChildKey(config_.seed, 0)}};
    const double total_work = double(data_.size()) * config_.depth;
    double done_work = 0;
    for (int level = 0; level < config_.depth && !level_nodes.empty(); ++level) {
      std::vector<SplitResult> results(level_nodes.size());
      std::vector<size_t> small;
      for (size_t i = 0; i < level_nodes.size(); ++i) {
        const Pending& node = level_nodes[i];
        if (node.end - node.begin >= kLargeNode) {
          results[i] = Split(node.begin, node.end, node.key, threads_, 0);
          done_work += double(node.end - node.begin);
          if (progress) progress(0.9 * done_work / total_work, "clustering");
        } else {
          small.push_back(i);
        }
      }
      ParallelFor(small.size(), threads_, [&](size_t task, int worker) {
        const Pending& node = level_nodes[small[task]];
        results[small[task]] = Split(node.begin, node.end, node.key, 1, size_t(worker));
      });
      for (size_t i : small) done_work += double(level_nodes[i].end - level_nodes[i].begin);
      if (progress) progress(0.9 * done_work / total_work, "clustering");

      std::vector<Pending> next;
      for (size_t i = 0; i < level_nodes.size(); ++i) {
        const Pending& node = level_nodes[i];
        const SplitResult& result = results[i];
        if (result.kind == SplitResult::Kind::kLeaf && level != 0) continue;
        size_t offset = node.begin;
        for (size_t c = 0; c < result.centres.size(); ++c) {
          const auto id = uint32_t(tree.parent.size());
          tree.parent.push_back(node.id);
          tree.descriptor.push_back(result.centres[c]);
          if (result.kind != SplitResult::Kind::kClusters) continue;
          const size_t size = result.sizes[c];
          if (level + 1 < config_.depth) {
            next.push_back({id, offset, offset + size, ChildKey(node.key, c)});
          }
          offset += size;
        }
      }
      level_nodes = std::move(next);
    }
    // Leaves are the nodes without children; number them in id (breadth-first) order.
    const size_t n = tree.parent.size();
    std::vector<uint8_t> inner(n, 0);
    for (size_t i = 1; i < n; ++i) inner[tree.parent[i]] = 1;
    tree.word_id.assign(n, -1);
    tree.weight.assign(n, 0.0f);
    int32_t words = 0;
    for (size_t i = 0; i < n; ++i) {
      if (!inner[i]) tree.word_id[i] = words++;
    }
    return tree;
  }

 private:
  const TrainerConfig config_;
  const int threads_;
  const int k_;
  std::vector<Descriptor256> data_;
  std::vector<Descriptor256> scratch_;
  std::vector<uint8_t> assignment_;
  std::vector<uint32_t> distance_;
  std::vector<Workspace> workspaces_;  // one per thread
};

Status ValidateConfig(const TrainerConfig& config) {
  if (config.branching < 2 || config.branching > 64) {
    return Status::InvalidArgument("branching (k) must be in [2, 64], got " +
                                   std::to_string(config.branching));
  }
  if (config.depth < 1 || config.depth > 10) {
    return Status::InvalidArgument("depth (L) must be in [1, 10], got " +
                                   std::to_string(config.depth));
  }
  if (config.threads < 0 || config.threads > 1024) {
    return Status::InvalidArgument("threads must be in [0, 1024] (0 = all cores), got " +
                                   std::to_string(config.threads));
  }
  if (config.max_iterations < 1 || config.max_iterations > 1000) {
    return Status::InvalidArgument("max_iterations must be in [1, 1000], got " +
                                   std::to_string(config.max_iterations));
  }
  const int weighting = static_cast<int>(config.weighting);
  if (weighting < 0 || weighting > 3) {
    return Status::InvalidArgument("unknown weighting type " + std::to_string(weighting));
  }
  const int scoring = static_cast<int>(config.scoring);
  if (scoring < 0 || scoring > 5) {
    return Status::InvalidArgument("unknown scoring type " + std::to_string(scoring));
  }
  return Status::Ok();
}

Result<std::shared_ptr<const Vocabulary>> Train(
    const std::vector<std::vector<Descriptor256>>& images, const TrainerConfig& config,
    const TrainerProgress& progress) {
  PLACEDB_RETURN_IF_ERROR(ValidateConfig(config));
  size_t total = 0;
  for (const auto& image : images) total += image.size();
  if (total < size_t(config.branching)) {
    return Status::InvalidArgument(
        "training needs at least k = " + std::to_string(config.branching) + " descriptors, got " +
        std::to_string(total));
  }
  if (total >= size_t{0xFFFFFFFFu}) {
    return Status::InvalidArgument("too many training descriptors: " + std::to_string(total));
  }
  int threads = config.threads;
  if (threads == 0) threads = int(std::max(1u, std::thread::hardware_concurrency()));

  std::vector<Descriptor256> data;
  data.reserve(total);
  for (const auto& image : images) data.insert(data.end(), image.begin(), image.end());
  if (progress) progress(0.0, "clustering");
  VocabularyTree tree = Trainer(config, threads, std::move(data)).Grow(progress);

  // Word weights: idf = ln(N / n_i), n_i = training images with a descriptor quantised to word
  // i by the same greedy descent Transform uses. TF and BINARY weight every word 1, as DBoW2.
  if (progress) progress(0.9, "weighting");
  tree.weighting = WeightingType::kBinary;  // Transform then lists each word once per image
  auto unweighted = Vocabulary::FromTree(tree);
  if (!unweighted.ok()) return unweighted.status().WithContext("training produced a bad tree");
  const Vocabulary& quantiser = **unweighted;
  const size_t words = quantiser.word_count();
  const int workers = int(std::min<size_t>(size_t(threads), std::max<size_t>(images.size(), 1)));
  std::vector<std::vector<uint32_t>> images_with_word(size_t(workers),
                                                      std::vector<uint32_t>(words, 0));
  ParallelFor(images.size(), threads, [&](size_t image, int worker) {
    BowVector bow;
    quantiser.Transform(images[image], &bow, nullptr, 0);
    for (const BowEntry& entry : bow) ++images_with_word[size_t(worker)][entry.word];
  });
  const bool idf =
      config.weighting == WeightingType::kTfIdf || config.weighting == WeightingType::kIdf;
  const double image_count = double(images.size());
  std::vector<float> word_weight(words);
  for (size_t word = 0; word < words; ++word) {
    uint64_t with_word = 0;
    for (const auto& counts : images_with_word) with_word += counts[word];
    // A word no training image reaches (possible: clusters are not Voronoi cells of the final
    // tree) is treated as the rarest: seen once.
    const double weight =
        idf ? std::log(image_count / double(std::max<uint64_t>(with_word, 1))) : 1.0;
    word_weight[word] = float(weight);
  }
  for (size_t node = 0; node < tree.word_id.size(); ++node) {
    if (tree.word_id[node] >= 0) tree.weight[node] = word_weight[size_t(tree.word_id[node])];
  }
  tree.weighting = config.weighting;
  tree.scoring = config.scoring;
  auto vocabulary = Vocabulary::FromTree(tree);
  if (progress) progress(1.0, "done");
  return vocabulary;
}

}  // namespace

Result<std::shared_ptr<const Vocabulary>> TrainVocabulary(
    const std::vector<std::vector<Descriptor256>>& images, const TrainerConfig& config,
    const TrainerProgress& progress) {
  try {
    return Train(images, config, progress);
  } catch (const std::bad_alloc&) {
    return Status::ResourceExhausted("out of memory while training the vocabulary");
  }
}

}  // namespace placedb
