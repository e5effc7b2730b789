// The inverted index: word -> postings (place, weight), the heart of a query.
//
// A query walks the postings of its words and accumulates each place's score in a dense
// per-thread array (no hashing, no allocation in steady state), then keeps the top k with a
// partial sort. Postings are 8 bytes (place id + float weight) kept contiguous per word; removal
// erases a place's postings using its BoW vector. Not internally synchronised: PlaceDatabase
// serialises writers and lets readers share (Query is const and touches only thread-local
// scratch).
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "core/bow.h"
#include "core/scoring.h"
#include "core/status.h"

namespace placedb {

using PlaceId = uint32_t;

struct ScoredPlace {
  PlaceId place;
  double score;
};

class InvertedIndex {
 public:
  InvertedIndex(uint32_t word_count, ScoringType scoring);

  ScoringType scoring() const { return scoring_; }

  // `bow` must be normalised for scoring() (NormalizeForScoring). ALREADY_EXISTS if the place is
  // indexed; INVALID_ARGUMENT for a word id outside the vocabulary.
  Status Add(PlaceId place, const BowVector& bow);
  // Removes the postings of `place`; `bow` must be the vector it was added with. NOT_FOUND if
  // the place is not indexed.
  Status Remove(PlaceId place, const BowVector& bow);
  bool Contains(PlaceId place) const;

  // The top `top_k` places by score, best first (ties: lower place id first). Places for which
  // `accept` returns false are skipped. `bow` normalised like in Add.
  std::vector<ScoredPlace> Query(const BowVector& bow, size_t top_k,
                                 const std::function<bool(PlaceId)>& accept = {}) const;

  size_t place_count() const { return place_count_; }
  size_t posting_count() const { return posting_count_; }
  // Heap bytes of postings, per-word lists and the place table.
  size_t MemoryBytes() const;

 private:
  struct Posting {
    PlaceId place;
    float weight;
  };
  ScoringType scoring_;
  std::vector<std::vector<Posting>> postings_;  // by word id, each sorted by place id
  std::vector<uint8_t> present_;                // by place id
  size_t place_count_ = 0;
  size_t posting_count_ = 0;
};

}  // namespace placedb
