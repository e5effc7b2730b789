// The inverted index: word -> postings (place, weight), the heart of a query.
//
// Layout (issue 17: a million places on one node). The place-id space is cut into segments of
// 2^16 consecutive ids. Each segment holds, per word, one run of 4-byte postings sorted by place:
// a 16-bit id offset within the segment and a 16-bit quantised weight (EncodeWeight). That
// halves the 8-byte (id + float) postings of a single flat index, and a query scores one segment
// at a time into a dense accumulator of 2^16 entries (256 KB of floats: it stays in L2) instead
// of one the size of the whole id space (4 MB at 1M places, a cache miss per posting).
// Segments are independent, so one query can score them on several threads (`threads` of
// Query); each segment's result does not depend on which thread scored it, so the answer is
// the same for every thread count.
//
// Storage per segment: runs of up to 1024 postings are slots in shared 32 KiB pages (one size
// class per page, classes <= 25% apart: no per-list heap block or power-of-two slack); longer
// runs own a vector with 1/8 headroom. Ids arriving in increasing order (ingest, reopen) append
// to the end of their run: amortised O(1) per posting; out-of-order ids insert in place. Remove
// erases a place's postings using its BoW vector; emptied slots are compacted per size class.
//
// Not internally synchronised: PlaceDatabase serialises writers and lets readers share (Query is
// const and touches only per-thread scratch).
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
  // Weights are stored as 16-bit codes: sign, 5-bit exponent, 10-bit mantissa rounded to
  // nearest, so |decoded - w| <= kWeightRelativeError * |w| for kMinWeight <= |w| <
  // kMaxWeight. Smaller magnitudes are stored as 0 (absolute error < kMinWeight, far below any
  // BoW weight: 1 descriptor in 10^5 with idf 0.1 still weighs 1e-6); Add rejects larger ones.
  // Normalised vectors (NormalizeForScoring) have weights <= 1; unnormalised dot-product
  // weights are tf-idf values, bounded by the vocabulary's largest idf.
  static constexpr double kWeightRelativeError = 1.0 / 2048;
  static constexpr float kMinWeight = 1.0f / (1 << 24);  // 2^-24
  static constexpr float kMaxWeight = 64.0f;             // 2^6
  static uint16_t EncodeWeight(float weight);
  static float DecodeWeight(uint16_t code) {
    const uint32_t magnitude = code & 0x7FFFu;
    // Exponent field 1..31 stands for 2^-24..2^6: rebias by 127 - 25 = 102.
    const uint32_t bits = (uint32_t(code & 0x8000u) << 16) | ((magnitude + (102u << 10)) << 13);
    float value;
    __builtin_memcpy(&value, &bits, sizeof value);
    return magnitude != 0 ? value : 0.0f;
  }
  // The weight the index stores for `weight` (what Query scores with).
  static float QuantizedWeight(float weight) { return DecodeWeight(EncodeWeight(weight)); }

  static constexpr int kSegmentBits = 16;  // place ids per segment: 2^16

  InvertedIndex(uint32_t word_count, ScoringType scoring);

  ScoringType scoring() const { return scoring_; }

  // `bow` must be normalised for scoring() (NormalizeForScoring). ALREADY_EXISTS if the place is
  // indexed; INVALID_ARGUMENT for a word id outside the vocabulary, unsorted or repeated words,
  // or a weight that is not finite or not below kMaxWeight in magnitude. On error nothing
  // changes. Cheapest (an append per word) when ids arrive in increasing order.
  Status Add(PlaceId place, const BowVector& bow);
  // Removes the postings of `place`; `bow` must be the vector it was added with. NOT_FOUND if
  // the place is not indexed; INVALID_ARGUMENT (and nothing changes) for another vector.
  Status Remove(PlaceId place, const BowVector& bow);
  bool Contains(PlaceId place) const;

  // The top `top_k` places by score, best first (ties: lower place id first), scored with the
  // stored (quantised) weights: each score is within the bound that kWeightRelativeError
  // implies for its scoring of the exact Score(). Places for which `accept` returns false are
  // skipped; `accept` is only asked about places that would enter the top k, never from two
  // threads at once, but possibly from a helper thread while the caller waits inside Query.
  // `bow` normalised like in Add. `bonus` adds to the score of indexed places (each listed
  // once), also of places that share no word with `bow`: the short-term tier's dynamic-word
  // similarity (core/pipeline/place_database.h). `threads` > 1 lets this one query score segments
  // on up to that many threads (only an index of more than one segment, i.e. ids >= 65536, uses
  // them); the result is identical for every value. `max_word_share` < 1 skips the query's
  // words held by more than that share of the indexed places while scanning (DBoW's idf
  // log(N / n_i) makes them nearly worthless, and their long runs are most of a query's work):
  // the best max(4 top_k, 100) places by the other words (and every bonus place) are then
  // rescored with the skipped words too (a binary search of each skipped word's run in the
  // place's segment), so every returned score is the exact one; only which places become
  // candidates is approximate (`accept` is asked about those candidates). 1 (the default)
  // skips nothing.
  std::vector<ScoredPlace> Query(const BowVector& bow, size_t top_k,
                                 const std::function<bool(PlaceId)>& accept = {},
                                 std::span<const ScoredPlace> bonus = {}, int threads = 1,
                                 double max_word_share = 1.0) const;

  // Bulk building (reopening a map, PlaceMap::Load): one whole segment built off the index from
  // its places, then installed. The result answers every query exactly like the same places
  // added one by one with Add (same runs, same quantisation); it holds no garbage slots, a run
  // of up to 1024 postings gets the slab class Add ends with and a longer one exactly its size
  // (Add leaves up to 1/8 headroom), so it never takes more memory than Add would.
  class DetachedSegment;
  struct BulkPlace {
    PlaceId place;
    const BowVector* bow;  // normalised as for Add
  };
  // Builds the segment of `places`: all in one segment (same id >> kSegmentBits), ids strictly
  // increasing, gaps allowed. Each place is checked like Add checks it (its vector first to last
  // place: the first problem is the error, with Add's message); INVALID_ARGUMENT for ids out of
  // order or in different segments. Touches nothing shared: any thread, any number at once.
  static Result<DetachedSegment> BuildSegment(uint32_t word_count,
                                              std::span<const BulkPlace> places);
  // Installs a built segment: into an empty segment it is moved in, O(words with postings in it
  // + its places); into one that holds places, all below the built ids, its runs are appended
  // (copied, runs growing as with Add). FAILED_PRECONDITION (nothing changes) if the segment
  // already holds or held an id at or above the lowest built one, or the built segment is for
  // another vocabulary size. Needs the same exclusion as Add.
  Status Install(DetachedSegment&& segment);

  size_t place_count() const { return place_count_; }
  size_t posting_count() const { return posting_count_; }
  // Heap bytes of postings, per-word run headers, segment bookkeeping and the place table.
  size_t MemoryBytes() const;

 private:
  struct Posting {
    uint16_t offset;  // place id - segment's first id
    uint16_t weight;  // EncodeWeight
  };
  // A word's run in one segment, sorted by offset. 8 bytes per word and segment.
  struct WordList {
    uint32_t location = 0;  // page * postings per page + offset, or high bit | big-list index
    uint32_t size = 0;      // 0: no storage held
  };
  // The postings of 2^16 consecutive place ids: a slab allocator of runs, one run per word.
  struct Segment {
    Segment() = default;  // unused: holds nothing
    explicit Segment(uint32_t word_count);
    Posting* Data(const WordList& list);
    const Posting* Data(const WordList& list) const;
    uint32_t Capacity(const WordList& list) const;
    // Moves `list` into storage for at least `capacity` postings (slab slot or big list).
    void Relocate(WordList* list, uint32_t capacity);
    void Release(WordList* list);
    uint32_t AllocateSlot(int size_class);
    // Slots freed by lists that grew, shrank or emptied are reused by their size class only;
    // once a class holds too many, it is packed into fewer pages and the rest are returned.
    void CompactIfFragmented();
    void CompactSizeClass(int size_class);
    bool InsertPosting(WordList* list, Posting posting);
    void ErasePosting(WordList* list, uint32_t index);
    size_t MemoryBytes() const;

    std::vector<WordList> lists;                    // by word id
    std::vector<std::vector<Posting>> pages;        // kPagePostings postings each
    std::vector<uint8_t> page_class;                // size class of each page (or free)
    std::vector<uint32_t> free_pages;               // released page numbers, reused first
    std::vector<uint32_t> class_pages;              // by size class: pages in use
    std::vector<uint32_t> class_live_slots;         // by size class: slots holding a list
    std::vector<std::vector<uint32_t>> free_slots;  // by size class: released slot locations
    std::vector<uint32_t> bump;                     // by size class: next unused slot, or kNoSlot
    std::vector<std::vector<Posting>> big_lists;    // vector size = list capacity
    std::vector<uint32_t> free_big_lists;
    uint32_t place_count = 0;
    uint32_t scan_limit = 0;  // 1 + the highest offset ever added: the accumulator's used part
  };
  // The postings of one query word in one segment, resolved before the scoring pass so that
  // their cache misses overlap instead of stalling it one word at a time.
  struct PostingRun {
    const Posting* postings;
    uint32_t size;
    float query_weight;
  };
  struct QueryScratch;  // one worker's accumulator and candidates, defined in place_index.cc
  struct QueryContext;  // one query's inputs and shared state, defined in place_index.cc
  template <ScoringType kType>
  void ScoreSegment(uint32_t segment, const QueryContext& query, QueryScratch* scratch) const;

  // Query's rescoring: adds to sums[i] the ScoreTerm of each of `skipped`'s words that
  // places[i] holds. `places` ascending (each segment's runs are then walked once, forward).
  void AddSkippedWords(const BowVector& skipped, std::span<const PlaceId> places,
                       std::span<double> sums) const;

  // Add's check of a vector against a vocabulary of `word_count` words.
  static Status ValidateBow(const BowVector& bow, size_t word_count);

  ScoringType scoring_;
  uint32_t word_count_;
  std::vector<Segment> segments_;      // by place id >> kSegmentBits
  std::vector<uint32_t> word_places_;  // by word id: places holding the word (all segments)
  std::vector<uint8_t> present_;       // by place id
  size_t place_count_ = 0;
  size_t posting_count_ = 0;
};

// A segment built by InvertedIndex::BuildSegment, not yet installed. Movable only.
class InvertedIndex::DetachedSegment {
 public:
  DetachedSegment() = default;
  DetachedSegment(DetachedSegment&&) = default;
  DetachedSegment& operator=(DetachedSegment&&) = default;

  size_t place_count() const { return places_.size(); }
  size_t posting_count() const { return posting_count_; }

 private:
  friend class InvertedIndex;
  uint32_t word_count_ = 0;
  uint32_t index_ = 0;           // place id >> kSegmentBits
  std::vector<PlaceId> places_;  // ascending
  std::vector<WordId> words_;    // ascending: the words holding postings in it
  Segment segment_;
  size_t posting_count_ = 0;
};

}  // namespace placedb
