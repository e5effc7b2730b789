#include "core/vocabulary/float_vocabulary.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <numeric>
#include <thread>

#include "core/base/parallel.h"
#include "core/vocabulary/bow_builder.h"
#include "core/vocabulary/vocabulary.h"  // Checksum64

namespace placedb {

float SquaredL2(const float* a, const float* b, int n) {
  // Eight independent accumulators: the compiler keeps them in vector registers.
  float acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  int i = 0;
  for (; i + 8 <= n; i += 8) {
    for (int j = 0; j < 8; ++j) {
      const float d = a[i + j] - b[i + j];
      acc[j] += d * d;
    }
  }
  float sum = ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]));
  for (; i < n; ++i) {
    const float d = a[i] - b[i];
    sum += d * d;
  }
  return sum;
}

namespace {

constexpr char kMagic[8] = {'P', 'D', 'B', 'F', 'V', 'O', 'C', '1'};
constexpr uint32_t kFormatVersion = 1;
constexpr uint32_t kEndianMarker = 0x01020304u;
constexpr int kMaxDimensions = 4096;
constexpr size_t kAssignChunk = 4096;

#pragma pack(push, 1)
struct FileHeader {
  char magic[8];
  uint32_t version;
  uint32_t endian;
  uint32_t dimensions;
  uint32_t branching;
  uint32_t depth;
  uint32_t scoring;
  uint32_t weighting;
  uint32_t node_count;
  uint32_t word_count;
  uint32_t reserved;
  uint64_t payload_bytes;
  uint64_t checksum;
};
#pragma pack(pop)
static_assert(sizeof(FileHeader) == 64);

// SplitMix64: the per-node RNG streams.
uint64_t Mix(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

class NodeRng {
 public:
  NodeRng(uint64_t seed, uint64_t node) : state_(Mix(seed ^ Mix(node + 0x51ED))) {}
  uint64_t Next() { return state_ = Mix(state_); }
  double Uniform() { return double(Next() >> 11) * 0x1.0p-53; }  // [0, 1)
  size_t Below(size_t n) { return size_t(Next() % n); }

 private:
  uint64_t state_;
};

uint32_t NearestCentre(const float* point, const std::vector<float>& centres, int dims) {
  const uint32_t count = uint32_t(centres.size() / size_t(dims));
  uint32_t best = 0;
  float best_d = std::numeric_limits<float>::infinity();
  for (uint32_t c = 0; c < count; ++c) {
    const float d = SquaredL2(point, centres.data() + size_t(c) * size_t(dims), dims);
    if (d < best_d) {
      best_d = d;
      best = c;
    }
  }
  return best;
}

// labels[i] = nearest centre of point points[i]. Fixed chunks, so the result does not depend on
// the thread count (each label is computed independently anyway).
void Assign(const float* data, int dims, const std::vector<uint32_t>& points,
            const std::vector<float>& centres, int threads, std::vector<uint32_t>* labels) {
  labels->resize(points.size());
  const size_t chunks = (points.size() + kAssignChunk - 1) / kAssignChunk;
  ParallelFor(chunks, threads, [&](size_t chunk, int) {
    const size_t end = std::min(points.size(), (chunk + 1) * kAssignChunk);
    for (size_t i = chunk * kAssignChunk; i < end; ++i) {
      (*labels)[i] = NearestCentre(data + size_t(points[i]) * size_t(dims), centres, dims);
    }
  });
}

struct Cluster {
  std::vector<float> centre;
  std::vector<uint32_t> members;
};

struct Clustering {
  std::vector<Cluster> clusters;
  bool exhausted = false;  // every cluster holds identical descriptors: children are leaves
};

// k-means++ then Lloyd on one node's members.
Clustering ClusterNode(const float* data, int dims, const std::vector<uint32_t>& members, int k,
                       const FloatTrainerConfig& config, NodeRng* rng, int threads) {
  Clustering out;
  // The points the centres are fitted on: all members, or a deterministic random sample.
  std::vector<uint32_t> fit = members;
  const bool sampled = config.max_fit_samples > 0 && members.size() > config.max_fit_samples;
  if (sampled) {
    for (size_t i = 0; i < config.max_fit_samples; ++i) {
      std::swap(fit[i], fit[i + rng->Below(fit.size() - i)]);
    }
    fit.resize(config.max_fit_samples);
  }
  const size_t n = fit.size();
  auto point = [&](uint32_t index) { return data + size_t(index) * size_t(dims); };

  // k-means++ seeding (squared L2).
  std::vector<float> centres;
  centres.reserve(size_t(k) * size_t(dims));
  const uint32_t first = fit[rng->Below(n)];
  centres.insert(centres.end(), point(first), point(first) + dims);
  std::vector<double> d2(n);
  for (size_t i = 0; i < n; ++i) d2[i] = SquaredL2(point(fit[i]), centres.data(), dims);
  bool exhausted = false;
  for (int c = 1; c < k; ++c) {
    double total = 0;
    for (double v : d2) total += v;
    if (!(total > 0)) {
      exhausted = true;  // fewer than k distinct descriptors
      break;
    }
    const double target = rng->Uniform() * total;
    double cumulative = 0;
    size_t pick = n - 1;
    for (size_t i = 0; i < n; ++i) {
      cumulative += d2[i];
      if (cumulative > target && d2[i] > 0) {
        pick = i;
        break;
      }
    }
    while (pick > 0 && d2[pick] == 0) --pick;  // rounding at the very end: a non-zero one
    const float* chosen = point(fit[pick]);
    centres.insert(centres.end(), chosen, chosen + dims);
    const float* centre = centres.data() + size_t(c) * size_t(dims);
    for (size_t i = 0; i < n; ++i) {
      d2[i] = std::min(d2[i], double(SquaredL2(point(fit[i]), centre, dims)));
    }
  }

  // Lloyd iterations; an empty cluster is dropped.
  std::vector<uint32_t> labels, previous;
  if (!exhausted) {
    for (int iteration = 0; iteration < config.max_iterations; ++iteration) {
      Assign(data, dims, fit, centres, threads, &labels);
      if (labels == previous) break;
      const size_t count = centres.size() / size_t(dims);
      std::vector<double> sums(count * size_t(dims), 0.0);
      std::vector<size_t> sizes(count, 0);
      for (size_t i = 0; i < n; ++i) {
        const float* p = point(fit[i]);
        double* sum = sums.data() + size_t(labels[i]) * size_t(dims);
        for (int d = 0; d < dims; ++d) sum[d] += p[d];
        ++sizes[labels[i]];
      }
      std::vector<float> next;
      next.reserve(centres.size());
      for (size_t c = 0; c < count; ++c) {
        if (sizes[c] == 0) continue;
        for (int d = 0; d < dims; ++d) {
          next.push_back(float(sums[c * size_t(dims) + size_t(d)] / double(sizes[c])));
        }
      }
      const bool dropped = next.size() != centres.size();
      centres = std::move(next);
      previous = std::move(labels);
      if (dropped) previous.clear();  // labels refer to the old numbering
    }
  }
  // Final assignment of every member.
  Assign(data, dims, members, centres, threads, &labels);
  const size_t count = centres.size() / size_t(dims);
  std::vector<Cluster> clusters(count);
  for (size_t c = 0; c < count; ++c) {
    clusters[c].centre.assign(centres.begin() + std::ptrdiff_t(c * size_t(dims)),
                              centres.begin() + std::ptrdiff_t((c + 1) * size_t(dims)));
  }
  for (size_t i = 0; i < members.size(); ++i) clusters[labels[i]].members.push_back(members[i]);
  for (auto& cluster : clusters) {
    if (!cluster.members.empty()) out.clusters.push_back(std::move(cluster));
  }
  out.exhausted = exhausted && !sampled;
  return out;
}

bool WriteAll(std::ofstream& out, const void* data, size_t bytes) {
  out.write(static_cast<const char*>(data), std::streamsize(bytes));
  return bool(out);
}

}  // namespace

Status ValidateFloatTrainerConfig(const FloatTrainerConfig& config) {
  if (config.branching < 2 || config.branching > 64) {
    return Status::InvalidArgument("branching must be in [2, 64], got " +
                                   std::to_string(config.branching));
  }
  if (config.depth < 1 || config.depth > 10) {
    return Status::InvalidArgument("depth must be in [1, 10], got " + std::to_string(config.depth));
  }
  if (config.threads < 0) return Status::InvalidArgument("threads must be >= 0");
  if (config.max_iterations < 1 || config.max_iterations > 1000) {
    return Status::InvalidArgument("max_iterations must be in [1, 1000], got " +
                                   std::to_string(config.max_iterations));
  }
  if (config.max_fit_samples != 0 && config.max_fit_samples < size_t(config.branching)) {
    return Status::InvalidArgument("max_fit_samples must be 0 or at least branching");
  }
  return Status::Ok();
}

Result<std::shared_ptr<const FloatVocabulary>> FloatVocabulary::Train(
    const std::vector<std::vector<float>>& images, int dimensions, const FloatTrainerConfig& config,
    const FloatTrainerProgress& progress) {
  PLACEDB_RETURN_IF_ERROR(ValidateFloatTrainerConfig(config));
  if (dimensions < 1 || dimensions > kMaxDimensions) {
    return Status::InvalidArgument("dimensions must be in [1, 4096], got " +
                                   std::to_string(dimensions));
  }
  const size_t dims = size_t(dimensions);
  size_t total = 0;
  for (size_t i = 0; i < images.size(); ++i) {
    if (images[i].size() % dims != 0) {
      return Status::InvalidArgument("images[" + std::to_string(i) + "] holds " +
                                     std::to_string(images[i].size()) +
                                     " floats, not a multiple of " + std::to_string(dims));
    }
    for (float v : images[i]) {
      if (!std::isfinite(v)) {
        return Status::InvalidArgument("images[" + std::to_string(i) + "] has a non-finite value");
      }
    }
    total += images[i].size() / dims;
  }
  if (total < size_t(config.branching)) {
    return Status::InvalidArgument("need at least " + std::to_string(config.branching) +
                                   " descriptors to train, got " + std::to_string(total));
  }
  if (total > 0xFFFFFFF0u) return Status::InvalidArgument("too many training descriptors");
  const int threads =
      config.threads == 0 ? int(std::max(1u, std::thread::hardware_concurrency())) : config.threads;

  std::vector<float> data;
  data.reserve(total * dims);
  for (const auto& image : images) data.insert(data.end(), image.begin(), image.end());

  std::unique_ptr<FloatVocabulary> v(new FloatVocabulary());
  v->dimensions_ = dimensions;
  v->branching_ = config.branching;
  v->depth_ = config.depth;
  v->scoring_ = config.scoring;
  v->weighting_ = config.weighting;
  // The root.
  v->first_child_.push_back(0);
  v->child_count_.push_back(0);
  v->centres_.assign(dims, 0.0f);

  struct Work {
    uint32_t node;
    std::vector<uint32_t> members;
  };
  std::vector<Work> level_work(1);
  level_work[0].node = 0;
  level_work[0].members.resize(total);
  std::iota(level_work[0].members.begin(), level_work[0].members.end(), 0u);
  for (int level = 0; level < config.depth && !level_work.empty(); ++level) {
    if (progress) progress(double(level) / double(config.depth + 1), "clustering");
    std::vector<Work> next_work;
    for (Work& work : level_work) {
      NodeRng rng(config.seed, work.node);
      Clustering clustering = ClusterNode(data.data(), dimensions, work.members, config.branching,
                                          config, &rng, threads);
      const uint32_t first = uint32_t(v->child_count_.size());
      v->first_child_[work.node] = first;
      v->child_count_[work.node] = uint32_t(clustering.clusters.size());
      for (auto& cluster : clustering.clusters) {
        const uint32_t child = uint32_t(v->child_count_.size());
        v->first_child_.push_back(0);
        v->child_count_.push_back(0);
        v->centres_.insert(v->centres_.end(), cluster.centre.begin(), cluster.centre.end());
        const bool leaf =
            clustering.exhausted || level + 1 >= config.depth || cluster.members.size() <= 1;
        if (!leaf) next_work.push_back(Work{child, std::move(cluster.members)});
      }
      std::vector<uint32_t>().swap(work.members);
    }
    level_work = std::move(next_work);
  }

  // Words: the leaves in breadth-first order.
  const uint32_t nodes = uint32_t(v->child_count_.size());
  v->node_word_.assign(nodes, kNoWord);
  for (uint32_t node = 0; node < nodes; ++node) {
    if (v->child_count_[node] == 0) {
      v->node_word_[node] = uint32_t(v->word_node_.size());
      v->word_node_.push_back(node);
    }
  }

  // idf over the training images.
  if (progress) progress(double(config.depth) / double(config.depth + 1), "weighting");
  const size_t words = v->word_node_.size();
  std::vector<uint32_t> images_with(words, 0);
  std::vector<uint32_t> last_image(words, 0xFFFFFFFFu);
  size_t offset = 0;
  for (size_t i = 0; i < images.size(); ++i) {
    const size_t count = images[i].size() / dims;
    for (size_t j = 0; j < count; ++j) {
      const WordId word = v->WordOf(data.data() + (offset + j) * dims);
      if (last_image[word] != uint32_t(i)) {
        last_image[word] = uint32_t(i);
        ++images_with[word];
      }
    }
    offset += count;
  }
  const double n_images = double(std::max<size_t>(images.size(), 1));
  v->word_weight_.resize(words);
  for (size_t w = 0; w < words; ++w) {
    switch (config.weighting) {
      case WeightingType::kTfIdf:
      case WeightingType::kIdf:
        v->word_weight_[w] =
            float(std::log(n_images / double(std::max<uint32_t>(1, images_with[w]))));
        break;
      case WeightingType::kTf:
      case WeightingType::kBinary:
        v->word_weight_[w] = 1.0f;
        break;
    }
  }
  v->checksum_ = v->ComputeChecksum();
  if (progress) progress(1.0, "done");
  return std::shared_ptr<const FloatVocabulary>(std::move(v));
}

uint32_t FloatVocabulary::Descend(const float* descriptor, int group_level, uint32_t* group) const {
  uint32_t node = 0;
  if (group != nullptr) *group = 0;
  for (int level = 1; child_count_[node] != 0; ++level) {
    const uint32_t first = first_child_[node];
    const uint32_t count = child_count_[node];
    uint32_t best = first;
    float best_d = std::numeric_limits<float>::infinity();
    for (uint32_t c = first; c < first + count; ++c) {
      const float d =
          SquaredL2(descriptor, centres_.data() + size_t(c) * size_t(dimensions_), dimensions_);
      if (d < best_d) {
        best_d = d;
        best = c;
      }
    }
    node = best;
    if (group != nullptr && level <= group_level) *group = best;
  }
  return node;
}

WordId FloatVocabulary::WordOf(const float* descriptor) const {
  return node_word_[Descend(descriptor, 0, nullptr)];
}

void FloatVocabulary::Transform(std::span<const float> descriptors, BowVector* bow,
                                DirectIndex* direct, int levels_up) const {
  const size_t n = descriptors.size() / size_t(dimensions_);
  levels_up = ClearTransformOutputs(bow, direct, levels_up);
  if (n == 0) return;
  const int group_level = std::max(0, depth_ - levels_up);
  std::vector<uint32_t> leaf(n), group(direct != nullptr ? n : 0);
  for (size_t i = 0; i < n; ++i) {
    leaf[i] = Descend(descriptors.data() + i * size_t(dimensions_), group_level,
                      direct != nullptr ? &group[i] : nullptr);
  }
  if (bow != nullptr) {
    for (uint32_t& node : leaf) node = node_word_[node];  // leaves -> their words
    BuildBowVector(leaf, word_weight_.data(), weighting_, bow);
  }
  if (direct != nullptr) BuildDirectIndex(group, direct);
}

std::string FloatVocabulary::checksum_hex() const {
  char buffer[17];
  std::snprintf(buffer, sizeof(buffer), "%016llx", static_cast<unsigned long long>(checksum_));
  return buffer;
}

size_t FloatVocabulary::memory_bytes() const {
  return (first_child_.size() + child_count_.size() + node_word_.size() + word_node_.size()) * 4 +
         (word_weight_.size() + centres_.size()) * sizeof(float);
}

uint64_t FloatVocabulary::ComputeChecksum() const {
  const uint32_t params[5] = {uint32_t(dimensions_), uint32_t(branching_), uint32_t(depth_),
                              uint32_t(scoring_), uint32_t(weighting_)};
  uint64_t h = Checksum64(params, sizeof(params), 0x70646266766f6331ull);
  auto chain = [&h](const auto& v) {
    h = Checksum64(v.data(), v.size() * sizeof(v[0]), h ^ (uint64_t(v.size()) << 1));
  };
  chain(first_child_);
  chain(child_count_);
  chain(node_word_);
  chain(word_node_);
  chain(word_weight_);
  chain(centres_);
  return h;
}

std::string FloatVocabulary::Serialize() const {
  FileHeader header{};
  std::memcpy(header.magic, kMagic, sizeof(kMagic));
  header.version = kFormatVersion;
  header.endian = kEndianMarker;
  header.dimensions = uint32_t(dimensions_);
  header.branching = uint32_t(branching_);
  header.depth = uint32_t(depth_);
  header.scoring = uint32_t(scoring_);
  header.weighting = uint32_t(weighting_);
  header.node_count = node_count();
  header.word_count = word_count();
  header.payload_bytes =
      uint64_t(node_count()) * 12 + uint64_t(word_count()) * 8 + uint64_t(centres_.size()) * 4;
  header.checksum = checksum_;
  std::string bytes;
  bytes.reserve(sizeof(header) + header.payload_bytes);
  auto append = [&bytes](const void* data, size_t size) {
    bytes.append(static_cast<const char*>(data), size);
  };
  append(&header, sizeof(header));
  append(first_child_.data(), first_child_.size() * 4);
  append(child_count_.data(), child_count_.size() * 4);
  append(node_word_.data(), node_word_.size() * 4);
  append(word_node_.data(), word_node_.size() * 4);
  append(word_weight_.data(), word_weight_.size() * 4);
  append(centres_.data(), centres_.size() * 4);
  return bytes;
}

Status FloatVocabulary::Save(const std::string& path) const {
  const std::string bytes = Serialize();
  const std::string temp = path + ".tmp";
  {
    std::ofstream out(temp, std::ios::binary | std::ios::trunc);
    if (!out) return Status::IoError("cannot open " + temp + " for writing");
    bool ok = WriteAll(out, bytes.data(), bytes.size());
    out.flush();
    if (!ok || !out) {
      std::error_code ec;
      std::filesystem::remove(temp, ec);
      return Status::IoError("writing " + temp + " failed");
    }
  }
  std::error_code ec;
  std::filesystem::rename(temp, path, ec);
  if (ec) {
    std::filesystem::remove(temp, ec);
    return Status::IoError("renaming " + temp + " to " + path + " failed");
  }
  return Status::Ok();
}

Result<std::shared_ptr<const FloatVocabulary>> FloatVocabulary::Load(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return Status::NotFound("no vocabulary at " + path);
  std::ifstream in(path, std::ios::binary);
  if (!in) return Status::IoError("cannot open " + path);
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) return Status::IoError("reading " + path + " failed");
  auto parsed = Parse(bytes);
  if (!parsed.ok()) {
    return Status(parsed.status().code(), path + ": " + parsed.status().message());
  }
  return parsed;
}

Result<std::shared_ptr<const FloatVocabulary>> FloatVocabulary::Parse(std::string_view bytes) {
  FileHeader header{};
  if (bytes.size() < sizeof(header)) return Status::Corruption("shorter than the 64-byte header");
  std::memcpy(&header, bytes.data(), sizeof(header));
  if (std::memcmp(header.magic, kMagic, sizeof(kMagic)) != 0) {
    return Status::Corruption("not a float vocabulary (bad magic)");
  }
  if (header.version != kFormatVersion) {
    return Status::Corruption("unsupported version " + std::to_string(header.version));
  }
  if (header.endian != kEndianMarker) {
    return Status::Corruption("written on a machine of the other byte order");
  }
  if (header.dimensions < 1 || header.dimensions > uint32_t(kMaxDimensions) ||
      header.branching < 2 || header.branching > 64 || header.depth < 1 || header.depth > 10 ||
      header.scoring > uint32_t(ScoringType::kDotProduct) ||
      header.weighting > uint32_t(WeightingType::kBinary) || header.node_count < 1 ||
      header.word_count < 1 || header.word_count > header.node_count) {
    return Status::Corruption("header parameters out of range");
  }
  const uint64_t payload = uint64_t(header.node_count) * 12 + uint64_t(header.word_count) * 8 +
                           uint64_t(header.node_count) * header.dimensions * 4;
  if (header.payload_bytes != payload || bytes.size() != sizeof(header) + payload) {
    return Status::Corruption("file size " + std::to_string(bytes.size()) +
                              " does not match its header (expected " +
                              std::to_string(sizeof(header) + payload) + ")");
  }
  std::unique_ptr<FloatVocabulary> v(new FloatVocabulary());
  v->dimensions_ = int(header.dimensions);
  v->branching_ = int(header.branching);
  v->depth_ = int(header.depth);
  v->scoring_ = ScoringType(header.scoring);
  v->weighting_ = WeightingType(header.weighting);
  const size_t nodes = header.node_count;
  const size_t words = header.word_count;
  size_t offset = sizeof(header);
  auto read = [&](auto* vector, size_t count) {
    vector->resize(count);
    const size_t size = count * sizeof((*vector)[0]);
    if (size) std::memcpy(vector->data(), bytes.data() + offset, size);
    offset += size;
  };
  read(&v->first_child_, nodes);
  read(&v->child_count_, nodes);
  read(&v->node_word_, nodes);
  read(&v->word_node_, words);
  read(&v->word_weight_, words);
  read(&v->centres_, nodes * header.dimensions);
  v->checksum_ = v->ComputeChecksum();
  if (v->checksum_ != header.checksum) {
    return Status::Corruption("checksum mismatch (file damaged)");
  }
  PLACEDB_RETURN_IF_ERROR(v->Validate());
  return std::shared_ptr<const FloatVocabulary>(std::move(v));
}

Status FloatVocabulary::Validate() const {
  const uint32_t nodes = node_count();
  // Breadth-first with contiguous children: the children of successive inner nodes follow each
  // other from node 1 on, which also makes it a tree.
  uint32_t next = 1;
  std::vector<uint8_t> level(nodes, 0);
  for (uint32_t node = 0; node < nodes; ++node) {
    const uint32_t count = child_count_[node];
    if (count > uint32_t(branching_)) {
      return Status::Corruption("node " + std::to_string(node) + " has more than k children");
    }
    if (count == 0) continue;
    if (first_child_[node] != next || uint64_t(next) + count > nodes) {
      return Status::Corruption("node " + std::to_string(node) + ": children out of order");
    }
    for (uint32_t c = next; c < next + count; ++c) {
      level[c] = uint8_t(level[node] + 1);
      if (level[c] > depth_) return Status::Corruption("tree deeper than its depth");
    }
    next += count;
  }
  if (next != nodes) return Status::Corruption("nodes unreachable from the root");
  std::vector<uint8_t> seen(word_count(), 0);
  for (uint32_t node = 0; node < nodes; ++node) {
    const bool leaf = child_count_[node] == 0;
    const uint32_t word = node_word_[node];
    if (leaf != (word != kNoWord)) {
      return Status::Corruption("node " + std::to_string(node) + ": leaf/word mismatch");
    }
    if (!leaf) continue;
    if (word >= word_count() || seen[word] || word_node_[word] != node) {
      return Status::Corruption("node " + std::to_string(node) + ": bad word id");
    }
    seen[word] = 1;
  }
  for (uint8_t s : seen) {
    if (!s) return Status::Corruption("a word without a node");
  }
  for (float w : word_weight_) {
    if (!std::isfinite(w) || w < 0) return Status::Corruption("a word weight is not finite");
  }
  for (float c : centres_) {
    if (!std::isfinite(c)) return Status::Corruption("a centre is not finite");
  }
  return Status::Ok();
}

}  // namespace placedb
