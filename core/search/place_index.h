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
#include <span>
#include <vector>

#include "core/base/status.h"
#include "core/search/scoring.h"
#include "core/vocabulary/bow.h"

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
  // `accept` returns false are skipped. `bow` normalised like in Add. `bonus` adds to the score
  // of indexed places (each listed once), also of places that share no word with `bow`: the
  // short-term tier's dynamic-word similarity (core/place_database.h).
  std::vector<ScoredPlace> Query(const BowVector& bow, size_t top_k,
                                 const std::function<bool(PlaceId)>& accept = {},
                                 std::span<const ScoredPlace> bonus = {}) const;

  size_t place_count() const { return place_count_; }
  size_t posting_count() const { return posting_count_; }
  // Heap bytes of postings, per-word lists and the place table.
  size_t MemoryBytes() const;

 private:
  struct Posting {
    PlaceId place;
    float weight;
  };
  // A word's postings, sorted by place id, live in one contiguous run. Runs of up to 1024
  // postings are slots in shared 64 KiB pages (one size class per page, classes ~19% apart: no
  // per-list heap block, allocator header or power-of-two slack); longer runs own a vector with
  // 1/8 headroom. 8 bytes per word: 4 MB for a 500k-word vocabulary, not 12 MB of vector headers.
  struct WordList {
    uint32_t location = 0;  // page * postings per page + offset, or high bit | big-list index
    uint32_t size = 0;      // 0: no storage held
  };
  Posting* Data(const WordList& list);
  const Posting* Data(const WordList& list) const;
  uint32_t Capacity(const WordList& list) const;
  // Moves `list` into storage for at least `capacity` postings (slab slot or big list).
  void Relocate(WordList* list, uint32_t capacity);
  void Release(WordList* list);
  uint32_t AllocateSlot(int size_class);
  // Slots freed by lists that grew, shrank or emptied are reused by their size class only; once
  // a class holds too many, it is packed into fewer pages and the rest are returned.
  void CompactIfFragmented();
  void CompactSizeClass(int size_class);
  bool InsertPosting(WordList* list, Posting posting);
  void ErasePosting(WordList* list, uint32_t index);
  // The postings of one query word, resolved before the scoring pass so that their cache misses
  // overlap instead of stalling it one word at a time.
  struct PostingRun {
    const Posting* postings;
    uint32_t size;
    float query_weight;
  };
  struct QueryScratch;  // per-thread accumulator, defined in place_index.cc
  template <ScoringType kType>
  static void Accumulate(const std::vector<PostingRun>& runs, QueryScratch* scratch);

  ScoringType scoring_;
  std::vector<WordList> lists_;                    // by word id
  std::vector<std::vector<Posting>> pages_;        // 8192 postings each
  std::vector<uint8_t> page_class_;                // size class of each page (or free)
  std::vector<uint32_t> free_pages_;               // released page numbers, reused first
  std::vector<uint32_t> class_pages_;              // by size class: pages in use
  std::vector<uint32_t> class_live_slots_;         // by size class: slots holding a list
  std::vector<std::vector<uint32_t>> free_slots_;  // by size class: released slot locations
  std::vector<uint32_t> bump_;                     // by size class: next unused slot, or kNoSlot
  std::vector<std::vector<Posting>> big_lists_;    // vector size = list capacity
  std::vector<uint32_t> free_big_lists_;
  std::vector<uint8_t> present_;  // by place id
  size_t place_count_ = 0;
  size_t posting_count_ = 0;
};

}  // namespace placedb
