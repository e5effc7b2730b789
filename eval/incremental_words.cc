#include "eval/incremental_words.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <unordered_map>

namespace placedb::eval {

IncrementalWords::IncrementalWords(const Vocabulary& buckets, IncrementalWordsOptions options)
    : tree_(buckets), options_(options), bucket_words_(buckets.node_count()) {}

uint32_t IncrementalWords::BucketOf(const Descriptor256& descriptor) const {
  uint32_t node = 0;
  for (int level = 0; level < options_.bucket_levels && tree_.ChildCount(node) != 0; ++level) {
    const uint32_t first = tree_.FirstChild(node);
    uint32_t best = first;
    int best_distance = std::numeric_limits<int>::max();
    for (uint32_t child = first; child < first + tree_.ChildCount(node); ++child) {
      const int distance = HammingDistance(descriptor, tree_.NodeDescriptor(child));
      if (distance < best_distance) {
        best_distance = distance;
        best = child;
      }
    }
    node = best;
  }
  return node;
}

int64_t IncrementalWords::Match(uint32_t bucket, const Descriptor256& descriptor) const {
  int best = std::numeric_limits<int>::max();
  int second = std::numeric_limits<int>::max();
  int64_t best_word = -1;
  for (uint32_t word : bucket_words_[bucket]) {
    const int distance = HammingDistance(descriptor, words_[word].descriptor);
    if (distance < best) {
      second = best;
      best = distance;
      best_word = word;
    } else if (distance < second) {
      second = distance;
    }
  }
  if (best_word < 0 || best > options_.max_distance) return -1;
  // A single word in the bucket has no second: the distance bound alone decides.
  if (second != std::numeric_limits<int>::max() && double(best) >= options_.ratio * second) {
    return -1;
  }
  return best_word;
}

void IncrementalWords::AddPlace(uint32_t place, std::span<const Descriptor256> descriptors) {
  std::unordered_map<uint32_t, uint32_t> counts;
  for (const Descriptor256& descriptor : descriptors) {
    const uint32_t bucket = BucketOf(descriptor);
    int64_t word = Match(bucket, descriptor);
    if (word >= 0) {
      ++merged_;
      if (options_.merge_and) {
        Descriptor256& kept = words_[size_t(word)].descriptor;
        for (size_t i = 0; i < kept.words.size(); ++i) kept.words[i] &= descriptor.words[i];
      }
    } else {
      word = int64_t(words_.size());
      words_.push_back({descriptor, {}});
      bucket_words_[bucket].push_back(uint32_t(word));
    }
    ++counts[uint32_t(word)];
  }
  for (const auto& [word, count] : counts) words_[word].places.emplace_back(place, count);
  places_ = std::max(places_, place + 1);
  norms_.clear();
}

const std::vector<double>& IncrementalWords::PlaceNorms() const {
  if (norms_.size() != places_) {  // places were added since: idf changed
    norms_.assign(places_, 0.0);
    for (const Word& word : words_) {
      const double idf = Idf(word);
      for (const auto& [place, count] : word.places) norms_[place] += double(count) * idf;
    }
  }
  return norms_;
}

double IncrementalWords::Idf(const Word& word) const {
  return std::log(double(places_) / double(std::max<size_t>(1, word.places.size())));
}

std::vector<std::pair<uint32_t, double>> IncrementalWords::Query(
    std::span<const Descriptor256> descriptors, size_t top_k) const {
  // The query's tf-idf vector, L1-normalised.
  std::unordered_map<uint32_t, double> query;
  for (const Descriptor256& descriptor : descriptors) {
    const int64_t word = Match(BucketOf(descriptor), descriptor);
    if (word >= 0) query[uint32_t(word)] += 1.0;
  }
  double query_norm = 0;
  for (auto& [word, weight] : query) {
    weight *= Idf(words_[word]);
    query_norm += std::abs(weight);
  }
  if (query_norm == 0) return {};
  // The DBoW L1 score over shared words, on L1-normalised tf-idf vectors:
  // s = 1 - 0.5 |q - p|_1 = 0.5 sum over shared words of (|q_i| + |p_i| - |q_i - p_i|).
  const std::vector<double>& norms = PlaceNorms();
  std::unordered_map<uint32_t, double> scores;
  for (const auto& [word, weight] : query) {
    const double q = weight / query_norm;
    const double idf = Idf(words_[word]);
    for (const auto& [place, count] : words_[word].places) {
      if (norms[place] == 0) continue;
      const double p = double(count) * idf / norms[place];
      scores[place] += std::abs(q) + std::abs(p) - std::abs(q - p);
    }
  }
  std::vector<std::pair<uint32_t, double>> ranked;
  ranked.reserve(scores.size());
  for (const auto& [place, score] : scores) ranked.emplace_back(place, 0.5 * score);
  const size_t keep = std::min(top_k, ranked.size());
  std::partial_sort(ranked.begin(), ranked.begin() + std::ptrdiff_t(keep), ranked.end(),
                    [](const auto& a, const auto& b) {
                      return a.second != b.second ? a.second > b.second : a.first < b.first;
                    });
  ranked.resize(keep);
  return ranked;
}

}  // namespace placedb::eval
