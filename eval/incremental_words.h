// The incremental alternative to a learned vocabulary (issue 29, item 5), for placedb-eval only:
// binary words added and merged online as places arrive, after Garcia-Fidalgo & Ortiz's iBoW-LCD
// (2018). Each stored descriptor is matched against the words so far (two nearest by Hamming
// distance, Lowe's ratio test); a match is merged into its word (the word's image list grows),
// a descriptor without one becomes a new word. Places are then tf-idf vectors over these words,
// scored with L1 as the map scores; a query's descriptors are matched the same way, without
// adding words.
//
// iBoW-LCD finds the nearest words with obindex2's randomized trees. Here the search is exact
// within a bucket: the node `bucket_levels` below the root of a fixed vocabulary that the
// descriptor descends to (greedy, as a transform does). Both are approximate nearest-neighbour
// searches; the bucket is the cheaper one to get right in an evaluation. Only what retrieval
// ranks is compared (NoGeom): the words carry no direct index for verification.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "core/features/descriptor.h"
#include "core/vocabulary/vocabulary.h"

namespace placedb::eval {

struct IncrementalWordsOptions {
  double ratio = 0.8;      // best / second-best distance below this: a match
  int max_distance = 64;   // and the best at most this many bits away
  int bucket_levels = 4;   // depth of the fixed vocabulary's bucket nodes
  bool merge_and = false;  // merged word = bitwise AND of word and descriptor (obindex2's AND
                           // policy); false: the word keeps its first descriptor
};

// One thread at a time (Query fills a cache).
class IncrementalWords {
 public:
  IncrementalWords(const Vocabulary& buckets, IncrementalWordsOptions options);

  // Adds place `place` (0-based, dense): its descriptors join or found words.
  void AddPlace(uint32_t place, std::span<const Descriptor256> descriptors);
  // The best `top_k` places, best first, as (place, L1 score).
  std::vector<std::pair<uint32_t, double>> Query(std::span<const Descriptor256> descriptors,
                                                 size_t top_k) const;

  size_t word_count() const { return words_.size(); }
  uint64_t merged() const { return merged_; }

 private:
  struct Word {
    Descriptor256 descriptor;
    std::vector<std::pair<uint32_t, uint32_t>> places;  // (place, occurrences), ascending place
  };
  uint32_t BucketOf(const Descriptor256& descriptor) const;
  // The matching word of `descriptor` in its bucket, or -1.
  int64_t Match(uint32_t bucket, const Descriptor256& descriptor) const;
  double Idf(const Word& word) const;
  // Each place's L1 norm of its tf-idf vector, computed once after the last AddPlace.
  const std::vector<double>& PlaceNorms() const;

  const Vocabulary& tree_;
  IncrementalWordsOptions options_;
  std::vector<Word> words_;
  std::vector<std::vector<uint32_t>> bucket_words_;  // by bucket node id
  uint32_t places_ = 0;
  mutable std::vector<double> norms_;  // PlaceNorms(); cleared by AddPlace
  uint64_t merged_ = 0;
};

}  // namespace placedb::eval
