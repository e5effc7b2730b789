#include "core/search/place_index.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <string>
#include <type_traits>
#include <unordered_map>
#include <utility>

namespace placedb {

namespace {

// Slot capacities of the slab size classes: exact up to 8, then four steps per doubling (at
// most 25% above the previous class, about 10% slack on average).
constexpr std::array<uint32_t, 36> kSlabCapacities = {
    1,  2,  3,  4,  5,   6,   7,   8,   10,  12,  14,  16,  20,  24,  28,  32,  40,  48,
    56, 64, 80, 96, 112, 128, 160, 192, 224, 256, 320, 384, 448, 512, 640, 768, 896, 1024};
constexpr uint32_t kNoSlot = 0xFFFFFFFFu;
constexpr uint32_t kPagePostings = 8192;  // 64 KiB pages
constexpr uint32_t kMaxSlabCapacity = kSlabCapacities.back();
constexpr uint32_t kBigListBit = 0x80000000u;  // WordList::location of a list that owns a vector
constexpr uint8_t kFreePage = 0xFF;            // page_class_ of a released page

// Smallest size class holding `size` postings (size <= the largest slab capacity).
int SizeClassFor(uint32_t size) {
  return int(std::lower_bound(kSlabCapacities.begin(), kSlabCapacities.end(), size) -
             kSlabCapacities.begin());
}

// Capacity to allocate for a list that must hold `size` postings: the fitting slab class, or
// 1/8 headroom for long lists (they hold most postings, so their slack is what counts).
uint32_t CapacityFor(uint32_t size) {
  if (size <= kMaxSlabCapacity) return kSlabCapacities[size_t(SizeClassFor(size))];
  return size + size / 8;
}

// The per-posting score term of each scoring, resolved at compile time so the hot loop has no
// switch and no call. Mirrors ScoreTerm() in scoring.cc (the brute-force tests hold them equal).
template <ScoringType kType, typename T>
inline T Term(T q, T c) {
  if constexpr (kType == ScoringType::kL1) {
    return std::fabs(q - c) - std::fabs(q) - std::fabs(c);
  } else if constexpr (kType == ScoringType::kL2 || kType == ScoringType::kDotProduct) {
    return q * c;
  } else if constexpr (kType == ScoringType::kChiSquare) {
    return q + c > 0 ? q * c / (q + c) : T(0);
  } else if constexpr (kType == ScoringType::kKL) {
    return T(ScoreTerm(kType, float(q), float(c)));  // a log per posting dominates anyway
  } else {
    return q > 0 && c > 0 ? std::sqrt(q * c) : T(0);
  }
}

// Float halves the accumulator's cache footprint (at 100k places 400 KB instead of 800 KB fits a
// core's L2 with room to spare) and is ample for the scores that are plain sums. L2 needs double:
// 1 - sqrt(1 - x) turns float rounding of x ~ 1 (6e-8) into an error of 2.4e-4. So does KL,
// whose result is a difference of two sums of ~25.
template <ScoringType kType>
using AccumulatorOf =
    std::conditional_t<kType == ScoringType::kL2 || kType == ScoringType::kKL, double, float>;

bool NeedsDoubleAccumulator(ScoringType type) {
  return type == ScoringType::kL2 || type == ScoringType::kKL;
}

}  // namespace

// Per-thread query scratch: a dense accumulator by place id and the places it touched. Reused
// across queries so a steady-state query allocates only its result.
struct InvertedIndex::QueryScratch {
  std::vector<float> float_score;    // by place id, zero when untouched
  std::vector<double> double_score;  // the same, for the scorings that need double
  std::vector<PlaceId> touched;      // places whose score went from zero (may repeat)
  std::vector<uint8_t> listed;       // by place id: dedups `touched` while finalising
  std::vector<PostingRun> runs;
  std::vector<ScoredPlace> candidates;
  bool in_use = false;  // a nested Query (from inside `accept`) must not share this scratch

  template <typename T>
  std::vector<T>& score() {
    if constexpr (std::is_same_v<T, float>) {
      return float_score;
    } else {
      return double_score;
    }
  }
};

InvertedIndex::InvertedIndex(uint32_t word_count, ScoringType scoring)
    : scoring_(scoring),
      lists_(word_count),
      class_pages_(kSlabCapacities.size(), 0),
      class_live_slots_(kSlabCapacities.size(), 0),
      free_slots_(kSlabCapacities.size()),
      bump_(kSlabCapacities.size(), kNoSlot) {
  static_assert(sizeof(WordList) == 8 && sizeof(Posting) == 8);
}

InvertedIndex::Posting* InvertedIndex::Data(const WordList& list) {
  if (list.location & kBigListBit) return big_lists_[list.location & ~kBigListBit].data();
  return pages_[list.location / kPagePostings].data() + list.location % kPagePostings;
}

const InvertedIndex::Posting* InvertedIndex::Data(const WordList& list) const {
  if (list.location & kBigListBit) return big_lists_[list.location & ~kBigListBit].data();
  return pages_[list.location / kPagePostings].data() + list.location % kPagePostings;
}

uint32_t InvertedIndex::Capacity(const WordList& list) const {
  if (list.size == 0) return 0;
  if (list.location & kBigListBit) {
    return uint32_t(big_lists_[list.location & ~kBigListBit].size());
  }
  return kSlabCapacities[page_class_[list.location / kPagePostings]];
}

uint32_t InvertedIndex::AllocateSlot(int size_class) {
  ++class_live_slots_[size_t(size_class)];
  std::vector<uint32_t>& free_slots = free_slots_[size_t(size_class)];
  if (!free_slots.empty()) {
    const uint32_t slot = free_slots.back();
    free_slots.pop_back();
    return slot;
  }
  const uint32_t capacity = kSlabCapacities[size_t(size_class)];
  uint32_t& bump = bump_[size_t(size_class)];
  if (bump == kNoSlot) {
    uint32_t page;
    if (!free_pages_.empty()) {
      page = free_pages_.back();
      free_pages_.pop_back();
      pages_[page].resize(kPagePostings);
      page_class_[page] = uint8_t(size_class);
    } else {
      page = uint32_t(pages_.size());
      pages_.emplace_back(kPagePostings);
      page_class_.push_back(uint8_t(size_class));
    }
    ++class_pages_[size_t(size_class)];
    bump = page * kPagePostings;
  }
  const uint32_t slot = bump;
  const uint32_t next_offset = slot % kPagePostings + capacity;
  bump = next_offset + capacity <= kPagePostings ? slot + capacity : kNoSlot;
  return slot;
}

void InvertedIndex::Release(WordList* list) {
  if (list->location & kBigListBit) {
    const uint32_t index = list->location & ~kBigListBit;
    std::vector<Posting>().swap(big_lists_[index]);  // frees the block
    free_big_lists_.push_back(index);
  } else {
    const uint8_t size_class = page_class_[list->location / kPagePostings];
    free_slots_[size_class].push_back(list->location);
    --class_live_slots_[size_class];
  }
  list->location = 0;
}

void InvertedIndex::CompactIfFragmented() {
  for (size_t c = 0; c < kSlabCapacities.size(); ++c) {
    if (class_pages_[c] == 0) continue;
    const size_t garbage = free_slots_[c].size() * kSlabCapacities[c];
    // An unused class gives its pages back at once (no list to move). Otherwise wait for at least
    // two pages to gain, and an eighth of the class: rare, and amortised by the relocations that
    // created the garbage.
    if (class_live_slots_[c] == 0 ||
        (garbage >= 2 * kPagePostings && garbage * 8 >= size_t(class_pages_[c]) * kPagePostings)) {
      CompactSizeClass(int(c));
    }
  }
}

void InvertedIndex::CompactSizeClass(int size_class) {
  const size_t c = size_t(size_class);
  const uint32_t capacity = kSlabCapacities[c];
  // The class's live slots in address order. Slots sit at multiples of the capacity within a
  // page, so packing them forward never overlaps a slot not yet moved.
  std::vector<std::pair<uint32_t, WordId>> live;
  for (WordId word = 0; class_live_slots_[c] > 0 && word < lists_.size(); ++word) {
    const WordList& list = lists_[word];
    if (list.size > 0 && !(list.location & kBigListBit) &&
        page_class_[list.location / kPagePostings] == size_class) {
      live.emplace_back(list.location, word);
    }
  }
  std::sort(live.begin(), live.end());
  std::vector<uint32_t> pages;
  for (uint32_t page = 0; page < page_class_.size(); ++page) {
    if (page_class_[page] == size_class) pages.push_back(page);
  }
  size_t page_index = 0;
  uint32_t offset = 0;
  for (const auto& [location, word] : live) {
    if (offset + capacity > kPagePostings) {
      ++page_index;
      offset = 0;
    }
    const uint32_t destination = pages[page_index] * kPagePostings + offset;
    if (destination != location) {
      std::memmove(pages_[pages[page_index]].data() + offset,
                   pages_[location / kPagePostings].data() + location % kPagePostings,
                   lists_[word].size * sizeof(Posting));
      lists_[word].location = destination;
    }
    offset += capacity;
  }
  const size_t used_pages = live.empty() ? 0 : page_index + 1;
  for (size_t i = used_pages; i < pages.size(); ++i) {
    std::vector<Posting>().swap(pages_[pages[i]]);
    page_class_[pages[i]] = kFreePage;
    free_pages_.push_back(pages[i]);
  }
  class_pages_[c] = uint32_t(used_pages);
  bump_[c] = used_pages > 0 && offset + capacity <= kPagePostings
                 ? pages[page_index] * kPagePostings + offset
                 : kNoSlot;
  std::vector<uint32_t>().swap(free_slots_[c]);
}

void InvertedIndex::Relocate(WordList* list, uint32_t capacity) {
  const bool had_storage = Capacity(*list) > 0;
  const bool was_big = had_storage && (list->location & kBigListBit);
  uint32_t location;
  Posting* destination;
  std::vector<Posting> big;
  if (capacity <= kMaxSlabCapacity) {
    location = AllocateSlot(SizeClassFor(capacity));
    destination = pages_[location / kPagePostings].data() + location % kPagePostings;
  } else {
    big.resize(capacity);  // the vector's size is the list's capacity
    destination = big.data();
    location = kNoSlot;  // assigned below, once the old list is out of the way
  }
  if (had_storage) std::memcpy(destination, Data(*list), list->size * sizeof(Posting));

  if (location != kNoSlot) {
    if (had_storage) Release(list);
    list->location = location;
    return;
  }
  if (was_big) {  // keep the list's big-list index, swap in the resized block
    big_lists_[list->location & ~kBigListBit] = std::move(big);
    return;
  }
  if (had_storage) Release(list);
  uint32_t index;
  if (!free_big_lists_.empty()) {
    index = free_big_lists_.back();
    free_big_lists_.pop_back();
    big_lists_[index] = std::move(big);
  } else {
    index = uint32_t(big_lists_.size());
    big_lists_.push_back(std::move(big));
  }
  list->location = kBigListBit | index;
}

// Inserts keeping the list sorted by place. Returns false when a posting for the place was
// already there (left behind by a Remove with a mismatched vector) and was overwritten.
bool InvertedIndex::InsertPosting(WordList* list, Posting posting) {
  uint32_t index = list->size;
  if (list->size > 0) {
    const Posting* data = Data(*list);
    if (data[list->size - 1].place >= posting.place) {  // not the usual append
      const Posting* at =
          std::lower_bound(data, data + list->size, posting.place,
                           [](const Posting& p, PlaceId place) { return p.place < place; });
      index = uint32_t(at - data);
      if (at->place == posting.place) {
        Data(*list)[index].weight = posting.weight;
        return false;
      }
    }
  }
  if (list->size == Capacity(*list)) Relocate(list, CapacityFor(list->size + 1));
  Posting* data = Data(*list);
  std::memmove(data + index + 1, data + index, (list->size - index) * sizeof(Posting));
  data[index] = posting;
  ++list->size;
  return true;
}

void InvertedIndex::ErasePosting(WordList* list, uint32_t index) {
  Posting* data = Data(*list);
  std::memmove(data + index, data + index + 1, (list->size - index - 1) * sizeof(Posting));
  --list->size;
  if (list->size == 0) {
    Release(list);
    return;
  }
  // Shrink only once half empty, so alternating adds and removes cannot thrash.
  if (list->size <= Capacity(*list) / 2) {
    Relocate(list, CapacityFor(list->size));
  }
}

namespace {

Status ValidateBow(const BowVector& bow, size_t word_count) {
  auto field = [](size_t i) { return "bow[" + std::to_string(i) + "]"; };
  for (size_t i = 0; i < bow.size(); ++i) {
    if (bow[i].word >= word_count) {
      return Status::InvalidArgument(field(i) + ".word = " + std::to_string(bow[i].word) +
                                     " is outside the vocabulary of " + std::to_string(word_count) +
                                     " words");
    }
    if (i > 0 && bow[i].word <= bow[i - 1].word) {
      return Status::InvalidArgument(
          field(i) + ".word = " + std::to_string(bow[i].word) + " does not follow " + field(i - 1) +
          ".word = " + std::to_string(bow[i - 1].word) + ": words must be sorted and unique");
    }
    if (!std::isfinite(bow[i].weight)) {
      return Status::InvalidArgument(field(i) + ".weight is not finite");
    }
  }
  return Status::Ok();
}

}  // namespace

Status InvertedIndex::Add(PlaceId place, const BowVector& bow) {
  if (Contains(place)) {
    return Status::AlreadyExists("place " + std::to_string(place) + " is already indexed");
  }
  PLACEDB_RETURN_IF_ERROR(ValidateBow(bow, lists_.size()));
  // Slab locations are 31-bit; each new posting needs at most one new page.
  if (pages_.size() + bow.size() > kBigListBit / kPagePostings) {
    return Status::ResourceExhausted("inverted index: posting storage is full (" +
                                     std::to_string(posting_count_) + " postings)");
  }
  if (place >= present_.size()) present_.resize(size_t(place) + 1, 0);
  // Each word's list is a likely cache miss twice (header, then its tail): prefetch ahead.
  constexpr size_t kAhead = 8;
  for (size_t i = 0; i < bow.size(); ++i) {
    if (i + 2 * kAhead < bow.size()) __builtin_prefetch(&lists_[bow[i + 2 * kAhead].word]);
    if (i + kAhead < bow.size()) {
      const WordList& ahead = lists_[bow[i + kAhead].word];
      if (ahead.size > 0) __builtin_prefetch(Data(ahead) + ahead.size - 1, 1);
    }
    if (InsertPosting(&lists_[bow[i].word], Posting{place, bow[i].weight})) ++posting_count_;
  }
  present_[place] = 1;
  ++place_count_;
  CompactIfFragmented();
  return Status::Ok();
}

Status InvertedIndex::Remove(PlaceId place, const BowVector& bow) {
  if (!Contains(place)) {
    return Status::NotFound("place " + std::to_string(place) + " is not indexed");
  }
  PLACEDB_RETURN_IF_ERROR(ValidateBow(bow, lists_.size()));
  // Find every posting first so that a mismatched vector changes nothing.
  auto find = [&](const WordList& list) -> uint32_t {
    if (list.size == 0) return kNoSlot;
    const Posting* data = Data(list);
    const Posting* at = std::lower_bound(data, data + list.size, place,
                                         [](const Posting& p, PlaceId id) { return p.place < id; });
    return at != data + list.size && at->place == place ? uint32_t(at - data) : kNoSlot;
  };
  for (size_t i = 0; i < bow.size(); ++i) {
    if (find(lists_[bow[i].word]) == kNoSlot) {
      return Status::InvalidArgument("bow[" + std::to_string(i) +
                                     "].word = " + std::to_string(bow[i].word) +
                                     " has no posting for place " + std::to_string(place) +
                                     ": pass the vector the place was added with");
    }
  }
  for (const BowEntry& entry : bow) {
    WordList& list = lists_[entry.word];
    ErasePosting(&list, find(list));
    --posting_count_;
  }
  present_[place] = 0;
  --place_count_;
  CompactIfFragmented();
  return Status::Ok();
}

bool InvertedIndex::Contains(PlaceId place) const {
  return place < present_.size() && present_[place] != 0;
}

template <ScoringType kType>
void InvertedIndex::Accumulate(const std::vector<PostingRun>& runs, QueryScratch* scratch) {
  using Accumulator = AccumulatorOf<kType>;
  Accumulator* score = scratch->score<Accumulator>().data();
  std::vector<PlaceId>& touched = scratch->touched;
  // Prefetch a few runs ahead: most runs are short, so each would otherwise start with a miss.
  constexpr size_t kPrefetchDistance = 8;
  for (size_t r = 0; r < runs.size(); ++r) {
    if (r + kPrefetchDistance < runs.size()) {
      __builtin_prefetch(runs[r + kPrefetchDistance].postings);
    }
    const Posting* postings = runs[r].postings;
    const uint32_t size = runs[r].size;
    const Accumulator q = runs[r].query_weight;
    for (uint32_t i = 0; i < size; ++i) {
      // A zero accumulator marks an untouched place: no separate flag to load in this loop.
      // (A sum that returns to exactly 0 re-lists its place; Query drops the duplicate, and a
      // place whose terms sum to 0 scores exactly like one sharing no word.)
      Accumulator& accumulated = score[postings[i].place];
      if (accumulated == 0) touched.push_back(postings[i].place);
      accumulated += Term<kType, Accumulator>(q, postings[i].weight);
    }
  }
}

std::vector<ScoredPlace> InvertedIndex::Query(const BowVector& bow, size_t top_k,
                                              const std::function<bool(PlaceId)>& accept,
                                              std::span<const ScoredPlace> bonus) const {
  std::vector<ScoredPlace> result;
  if (top_k == 0 || place_count_ == 0) return result;

  thread_local QueryScratch thread_scratch;
  QueryScratch nested_scratch;
  QueryScratch& scratch = thread_scratch.in_use ? nested_scratch : thread_scratch;
  scratch.in_use = true;
  struct ScratchGuard {
    QueryScratch* scratch;
    ~ScratchGuard() { scratch->in_use = false; }
  } guard{&scratch};
  // Every place id in a posting is below present_.size().
  const bool wide = NeedsDoubleAccumulator(scoring_);
  if (wide && scratch.double_score.size() < present_.size()) {
    scratch.double_score.resize(present_.size(), 0.0);
  }
  if (!wide && scratch.float_score.size() < present_.size()) {
    scratch.float_score.resize(present_.size(), 0.0f);
  }
  if (scratch.listed.size() < present_.size()) {
    scratch.listed.resize(present_.size(), 0);
  }
  scratch.touched.clear();
  scratch.runs.clear();
  for (const BowEntry& entry : bow) {
    if (entry.word >= lists_.size()) continue;  // not a word of this vocabulary: shares nothing
    const WordList& list = lists_[entry.word];
    if (list.size > 0) scratch.runs.push_back({Data(list), list.size, entry.weight});
  }
  switch (scoring_) {
    case ScoringType::kL1:
      Accumulate<ScoringType::kL1>(scratch.runs, &scratch);
      break;
    case ScoringType::kL2:
      Accumulate<ScoringType::kL2>(scratch.runs, &scratch);
      break;
    case ScoringType::kChiSquare:
      Accumulate<ScoringType::kChiSquare>(scratch.runs, &scratch);
      break;
    case ScoringType::kKL:
      Accumulate<ScoringType::kKL>(scratch.runs, &scratch);
      break;
    case ScoringType::kBhattacharyya:
      Accumulate<ScoringType::kBhattacharyya>(scratch.runs, &scratch);
      break;
    case ScoringType::kDotProduct:
      Accumulate<ScoringType::kDotProduct>(scratch.runs, &scratch);
      break;
  }

  // Finalise and leave the accumulator zeroed for the next query, before any user callback.
  const double query_constant = QueryConstant(scoring_, bow);
  std::vector<ScoredPlace>& candidates = scratch.candidates;
  candidates.clear();
  for (const PlaceId place : scratch.touched) {
    if (scratch.listed[place]) continue;
    scratch.listed[place] = 1;
    double accumulated;
    if (wide) {
      accumulated = std::exchange(scratch.double_score[place], 0.0);
    } else {
      accumulated = std::exchange(scratch.float_score[place], 0.0f);
    }
    // Postings of a removed place can only survive a Remove given the wrong vector; never
    // return such a place.
    if (present_[place]) {
      candidates.push_back({place, FinalizeScore(scoring_, accumulated, query_constant)});
    }
  }
  if (!bonus.empty()) {
    // The bonus list is short (the short-term tier): index it, not the candidates.
    std::unordered_map<PlaceId, double> extra;
    for (const ScoredPlace& b : bonus) {
      if (b.place < present_.size() && present_[b.place]) extra.emplace(b.place, b.score);
    }
    for (ScoredPlace& candidate : candidates) {
      auto it = extra.find(candidate.place);
      if (it == extra.end()) continue;
      candidate.score += it->second;
      extra.erase(it);
    }
    for (const ScoredPlace& b : bonus) {  // places that share no word with `bow`
      if (extra.count(b.place)) candidates.push_back(b);
    }
  }
  for (const PlaceId place : scratch.touched) scratch.listed[place] = 0;
  if (accept) {
    std::erase_if(candidates, [&](const ScoredPlace& c) { return !accept(c.place); });
  }

  auto better = [](const ScoredPlace& a, const ScoredPlace& b) {
    return a.score != b.score ? a.score > b.score : a.place < b.place;
  };
  const size_t k = std::min(top_k, candidates.size());
  if (k < candidates.size()) {
    std::nth_element(candidates.begin(), candidates.begin() + ptrdiff_t(k), candidates.end(),
                     better);
  }
  std::sort(candidates.begin(), candidates.begin() + ptrdiff_t(k), better);
  result.assign(candidates.begin(), candidates.begin() + ptrdiff_t(k));
  return result;
}

size_t InvertedIndex::MemoryBytes() const {
  // Everything the index holds on the heap, at capacity: list headers, pages (released ones
  // hold nothing), big lists, the allocator's bookkeeping and the place table.
  size_t bytes = lists_.capacity() * sizeof(WordList);
  bytes += pages_.capacity() * sizeof(std::vector<Posting>);
  for (const auto& page : pages_) bytes += page.capacity() * sizeof(Posting);
  bytes += big_lists_.capacity() * sizeof(std::vector<Posting>);
  for (const auto& list : big_lists_) bytes += list.capacity() * sizeof(Posting);
  bytes += free_slots_.capacity() * sizeof(std::vector<uint32_t>);
  for (const auto& slots : free_slots_) bytes += slots.capacity() * sizeof(uint32_t);
  bytes += page_class_.capacity() + free_pages_.capacity() * sizeof(uint32_t) +
           (class_pages_.capacity() + class_live_slots_.capacity() + bump_.capacity() +
            free_big_lists_.capacity()) *
               sizeof(uint32_t);
  bytes += present_.capacity();
  return bytes;
}

}  // namespace placedb
