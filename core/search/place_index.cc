#include "core/search/place_index.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <mutex>
#include <string>
#include <type_traits>
#include <utility>

#include "core/base/parallel.h"

namespace placedb {

namespace {

// Slot capacities of the slab size classes: exact up to 8, then four steps per doubling (at
// most 25% above the previous class, about 10% slack on average).
constexpr std::array<uint32_t, 36> kSlabCapacities = {
    1,  2,  3,  4,  5,   6,   7,   8,   10,  12,  14,  16,  20,  24,  28,  32,  40,  48,
    56, 64, 80, 96, 112, 128, 160, 192, 224, 256, 320, 384, 448, 512, 640, 768, 896, 1024};
constexpr uint32_t kNoSlot = 0xFFFFFFFFu;
constexpr uint32_t kPagePostings = 8192;  // 32 KiB pages of 4-byte postings
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

// Float halves the accumulator's cache footprint (a segment's 2^16 entries: 256 KB instead of
// 512 KB, which fits a core's L2 with room to spare) and is ample for the scores that are plain
// sums. L2 needs double:
// 1 - sqrt(1 - x) turns float rounding of x ~ 1 (6e-8) into an error of 2.4e-4. So does KL,
// whose result is a difference of two sums of ~25.
template <ScoringType kType>
using AccumulatorOf =
    std::conditional_t<kType == ScoringType::kL2 || kType == ScoringType::kKL, double, float>;

}  // namespace

namespace {

// Score order of an accumulated sum: the scorings whose FinalizeScore decreases with the sum
// (L1, KL) rank by its negation, so a larger key is always a better place and the candidates
// can be compared before finalising (which only the top k need).
constexpr bool SumDecreasesScore(ScoringType type) {
  return type == ScoringType::kL1 || type == ScoringType::kKL;
}

// A candidate in a worker's top k: the order key of its sum (SumDecreasesScore) and its place.
struct KeyedPlace {
  double key;
  PlaceId place;
};

// Heap order: "less" is "better", so a heap's front is the worst of the kept candidates.
inline bool Better(const KeyedPlace& a, const KeyedPlace& b) {
  return a.key != b.key ? a.key > b.key : a.place < b.place;
}

// A place of the bonus list met while scoring: its sum over the scored words and its bonus,
// finalised once the skipped words (if any) have been added.
struct BonusCandidate {
  PlaceId place;
  double accumulated;
  double bonus;
};

// How many candidates a query that skips frequent words rescores with them, for a top k: the
// true top k ranks lower by the other words alone, but rarely below a few times k.
size_t RescoredCandidates(size_t top_k) {
  return std::max<size_t>(4 * top_k, 100);
}

}  // namespace

// One worker's scratch: a segment's dense accumulator (2^16 entries, zero between segments), the
// runs of the segment being scored, and the worker's candidates over all its segments. Reused
// across queries so a steady-state query allocates only its result.
struct InvertedIndex::QueryScratch {
  std::vector<float> float_score;
  std::vector<double> double_score;  // for the scorings that need double
  std::vector<PostingRun> runs;
  std::vector<KeyedPlace> top;                   // heap of at most top_k, worst first
  std::vector<BonusCandidate> bonus_candidates;  // places of the bonus list, not finalised

  template <typename T>
  T* score() {
    std::vector<T>* scores;
    if constexpr (std::is_same_v<T, float>) {
      scores = &float_score;
    } else {
      scores = &double_score;
    }
    if (scores->empty()) scores->resize(size_t(1) << kSegmentBits, T(0));
    return scores->data();
  }
};

struct InvertedIndex::QueryContext {
  const BowVector* bow;
  size_t top_k;
  const std::function<bool(PlaceId)>* accept;  // never empty here: null when absent
  std::span<const ScoredPlace> bonus;          // sorted by place, each once, indexed places only
  double query_constant;
  bool serialise_accept;  // several workers: one accept call at a time
  mutable std::mutex accept_mutex;

  bool Accept(PlaceId place) const {
    if (accept == nullptr) return true;
    if (!serialise_accept) return (*accept)(place);
    std::lock_guard lock(accept_mutex);
    return (*accept)(place);
  }
};

uint16_t InvertedIndex::EncodeWeight(float weight) {
  uint32_t bits;
  std::memcpy(&bits, &weight, sizeof bits);
  const uint32_t sign = (bits >> 16) & 0x8000u;
  // Adding half a unit of the 10-bit mantissa rounds to nearest; a carry bumps the exponent,
  // which is still the right value.
  const uint32_t rounded = (bits & 0x7FFFFFFFu) + 0x1000u;
  const uint32_t biased_exponent = rounded >> 23;
  if (biased_exponent < 103) return 0;                         // below 2^-24: stored as zero
  if (biased_exponent > 133) return uint16_t(sign | 0x7FFFu);  // Add rejects these first
  return uint16_t(sign | ((rounded >> 13) - (102u << 10)));
}

InvertedIndex::Segment::Segment(uint32_t word_count)
    : lists(word_count),
      class_pages(kSlabCapacities.size(), 0),
      class_live_slots(kSlabCapacities.size(), 0),
      free_slots(kSlabCapacities.size()),
      bump(kSlabCapacities.size(), kNoSlot) {}

InvertedIndex::InvertedIndex(uint32_t word_count, ScoringType scoring)
    : scoring_(scoring), word_count_(word_count), word_places_(word_count, 0) {
  static_assert(sizeof(WordList) == 8 && sizeof(Posting) == 4);
}

InvertedIndex::Posting* InvertedIndex::Segment::Data(const WordList& list) {
  if (list.location & kBigListBit) return big_lists[list.location & ~kBigListBit].data();
  return pages[list.location / kPagePostings].data() + list.location % kPagePostings;
}

const InvertedIndex::Posting* InvertedIndex::Segment::Data(const WordList& list) const {
  if (list.location & kBigListBit) return big_lists[list.location & ~kBigListBit].data();
  return pages[list.location / kPagePostings].data() + list.location % kPagePostings;
}

uint32_t InvertedIndex::Segment::Capacity(const WordList& list) const {
  if (list.size == 0) return 0;
  if (list.location & kBigListBit) {
    return uint32_t(big_lists[list.location & ~kBigListBit].size());
  }
  return kSlabCapacities[page_class[list.location / kPagePostings]];
}

uint32_t InvertedIndex::Segment::AllocateSlot(int size_class) {
  ++class_live_slots[size_t(size_class)];
  std::vector<uint32_t>& class_free_slots = free_slots[size_t(size_class)];
  if (!class_free_slots.empty()) {
    const uint32_t slot = class_free_slots.back();
    class_free_slots.pop_back();
    return slot;
  }
  const uint32_t capacity = kSlabCapacities[size_t(size_class)];
  uint32_t& next_slot = bump[size_t(size_class)];
  if (next_slot == kNoSlot) {
    uint32_t page;
    if (!free_pages.empty()) {
      page = free_pages.back();
      free_pages.pop_back();
      pages[page].resize(kPagePostings);
      page_class[page] = uint8_t(size_class);
    } else {
      page = uint32_t(pages.size());
      pages.emplace_back(kPagePostings);
      page_class.push_back(uint8_t(size_class));
    }
    ++class_pages[size_t(size_class)];
    next_slot = page * kPagePostings;
  }
  const uint32_t slot = next_slot;
  const uint32_t next_offset = slot % kPagePostings + capacity;
  next_slot = next_offset + capacity <= kPagePostings ? slot + capacity : kNoSlot;
  return slot;
}

void InvertedIndex::Segment::Release(WordList* list) {
  if (list->location & kBigListBit) {
    const uint32_t index = list->location & ~kBigListBit;
    std::vector<Posting>().swap(big_lists[index]);  // frees the block
    free_big_lists.push_back(index);
  } else {
    const uint8_t size_class = page_class[list->location / kPagePostings];
    free_slots[size_class].push_back(list->location);
    --class_live_slots[size_class];
  }
  list->location = 0;
}

void InvertedIndex::Segment::CompactIfFragmented() {
  for (size_t c = 0; c < kSlabCapacities.size(); ++c) {
    if (class_pages[c] == 0) continue;
    const size_t garbage = free_slots[c].size() * kSlabCapacities[c];
    // An unused class gives its pages back at once (no list to move). Otherwise wait for at least
    // two pages to gain, and an eighth of the class: rare, and amortised by the relocations that
    // created the garbage.
    if (class_live_slots[c] == 0 ||
        (garbage >= 2 * kPagePostings && garbage * 8 >= size_t(class_pages[c]) * kPagePostings)) {
      CompactSizeClass(int(c));
    }
  }
}

void InvertedIndex::Segment::CompactSizeClass(int size_class) {
  const size_t c = size_t(size_class);
  const uint32_t capacity = kSlabCapacities[c];
  // The class's live slots in address order. Slots sit at multiples of the capacity within a
  // page, so packing them forward never overlaps a slot not yet moved.
  std::vector<std::pair<uint32_t, WordId>> live;
  for (WordId word = 0; class_live_slots[c] > 0 && word < lists.size(); ++word) {
    const WordList& list = lists[word];
    if (list.size > 0 && !(list.location & kBigListBit) &&
        page_class[list.location / kPagePostings] == size_class) {
      live.emplace_back(list.location, word);
    }
  }
  std::sort(live.begin(), live.end());
  std::vector<uint32_t> class_page_list;
  for (uint32_t page = 0; page < page_class.size(); ++page) {
    if (page_class[page] == size_class) class_page_list.push_back(page);
  }
  size_t page_index = 0;
  uint32_t offset = 0;
  for (const auto& [location, word] : live) {
    if (offset + capacity > kPagePostings) {
      ++page_index;
      offset = 0;
    }
    const uint32_t destination = class_page_list[page_index] * kPagePostings + offset;
    if (destination != location) {
      std::memmove(pages[class_page_list[page_index]].data() + offset,
                   pages[location / kPagePostings].data() + location % kPagePostings,
                   lists[word].size * sizeof(Posting));
      lists[word].location = destination;
    }
    offset += capacity;
  }
  const size_t used_pages = live.empty() ? 0 : page_index + 1;
  for (size_t i = used_pages; i < class_page_list.size(); ++i) {
    std::vector<Posting>().swap(pages[class_page_list[i]]);
    page_class[class_page_list[i]] = kFreePage;
    free_pages.push_back(class_page_list[i]);
  }
  class_pages[c] = uint32_t(used_pages);
  bump[c] = used_pages > 0 && offset + capacity <= kPagePostings
                ? class_page_list[page_index] * kPagePostings + offset
                : kNoSlot;
  std::vector<uint32_t>().swap(free_slots[c]);
}

void InvertedIndex::Segment::Relocate(WordList* list, uint32_t capacity) {
  const bool had_storage = Capacity(*list) > 0;
  const bool was_big = had_storage && (list->location & kBigListBit);
  uint32_t location;
  Posting* destination;
  std::vector<Posting> big;
  if (capacity <= kMaxSlabCapacity) {
    location = AllocateSlot(SizeClassFor(capacity));
    destination = pages[location / kPagePostings].data() + location % kPagePostings;
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
    big_lists[list->location & ~kBigListBit] = std::move(big);
    return;
  }
  if (had_storage) Release(list);
  uint32_t index;
  if (!free_big_lists.empty()) {
    index = free_big_lists.back();
    free_big_lists.pop_back();
    big_lists[index] = std::move(big);
  } else {
    index = uint32_t(big_lists.size());
    big_lists.push_back(std::move(big));
  }
  list->location = kBigListBit | index;
}

// Inserts keeping the list sorted by offset. Returns false when a posting for the place was
// already there (left behind by a Remove with a mismatched vector) and was overwritten.
bool InvertedIndex::Segment::InsertPosting(WordList* list, Posting posting) {
  uint32_t index = list->size;
  if (list->size > 0) {
    const Posting* data = Data(*list);
    if (data[list->size - 1].offset >= posting.offset) {  // not the usual append
      const Posting* at =
          std::lower_bound(data, data + list->size, posting.offset,
                           [](const Posting& p, uint32_t offset) { return p.offset < offset; });
      index = uint32_t(at - data);
      if (at->offset == posting.offset) {
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

void InvertedIndex::Segment::ErasePosting(WordList* list, uint32_t index) {
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

size_t InvertedIndex::Segment::MemoryBytes() const {
  // Everything the segment holds on the heap, at capacity: list headers, pages (released ones
  // hold nothing), big lists and the allocator's bookkeeping.
  size_t bytes = lists.capacity() * sizeof(WordList);
  bytes += pages.capacity() * sizeof(std::vector<Posting>);
  for (const auto& page : pages) bytes += page.capacity() * sizeof(Posting);
  bytes += big_lists.capacity() * sizeof(std::vector<Posting>);
  for (const auto& list : big_lists) bytes += list.capacity() * sizeof(Posting);
  bytes += free_slots.capacity() * sizeof(std::vector<uint32_t>);
  for (const auto& slots : free_slots) bytes += slots.capacity() * sizeof(uint32_t);
  bytes += page_class.capacity() + free_pages.capacity() * sizeof(uint32_t) +
           (class_pages.capacity() + class_live_slots.capacity() + bump.capacity() +
            free_big_lists.capacity()) *
               sizeof(uint32_t);
  return bytes;
}

Status InvertedIndex::ValidateBow(const BowVector& bow, size_t word_count) {
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
    if (std::fabs(bow[i].weight) >= InvertedIndex::kMaxWeight) {
      return Status::InvalidArgument(field(i) + ".weight = " + std::to_string(bow[i].weight) +
                                     " is outside the index's range (magnitude below " +
                                     std::to_string(InvertedIndex::kMaxWeight) +
                                     "): normalise the vector for its scoring");
    }
  }
  return Status::Ok();
}

Status InvertedIndex::Add(PlaceId place, const BowVector& bow) {
  if (Contains(place)) {
    return Status::AlreadyExists("place " + std::to_string(place) + " is already indexed");
  }
  PLACEDB_RETURN_IF_ERROR(ValidateBow(bow, word_count_));
  const size_t segment_index = place >> kSegmentBits;
  const uint16_t offset = uint16_t(place & ((1u << kSegmentBits) - 1));
  if (segment_index < segments_.size()) {
    // Slab locations are 31-bit; each new posting needs at most one new page.
    const Segment& segment = segments_[segment_index];
    if (segment.pages.size() + bow.size() > kBigListBit / kPagePostings) {
      return Status::ResourceExhausted("inverted index: posting storage of segment " +
                                       std::to_string(segment_index) + " is full");
    }
  }
  if (segment_index >= segments_.size()) segments_.resize(segment_index + 1);
  Segment& segment = segments_[segment_index];
  if (segment.lists.empty()) segment = Segment(word_count_);
  if (place >= present_.size()) present_.resize(size_t(place) + 1, 0);
  // Each word's list is a likely cache miss twice (header, then its tail): prefetch ahead.
  constexpr size_t kAhead = 8;
  for (size_t i = 0; i < bow.size(); ++i) {
    if (i + 2 * kAhead < bow.size()) __builtin_prefetch(&segment.lists[bow[i + 2 * kAhead].word]);
    if (i + kAhead < bow.size()) {
      const WordList& ahead = segment.lists[bow[i + kAhead].word];
      if (ahead.size > 0) __builtin_prefetch(segment.Data(ahead) + ahead.size - 1, 1);
    }
    if (segment.InsertPosting(&segment.lists[bow[i].word],
                              Posting{offset, EncodeWeight(bow[i].weight)})) {
      ++posting_count_;
      ++word_places_[bow[i].word];
    }
  }
  present_[place] = 1;
  ++place_count_;
  ++segment.place_count;
  segment.scan_limit = std::max(segment.scan_limit, uint32_t(offset) + 1);
  segment.CompactIfFragmented();
  return Status::Ok();
}

Status InvertedIndex::Remove(PlaceId place, const BowVector& bow) {
  if (!Contains(place)) {
    return Status::NotFound("place " + std::to_string(place) + " is not indexed");
  }
  PLACEDB_RETURN_IF_ERROR(ValidateBow(bow, word_count_));
  Segment& segment = segments_[place >> kSegmentBits];
  const uint32_t offset = place & ((1u << kSegmentBits) - 1);
  // Find every posting first so that a mismatched vector changes nothing.
  auto find = [&](const WordList& list) -> uint32_t {
    if (list.size == 0) return kNoSlot;
    const Posting* data = segment.Data(list);
    const Posting* at =
        std::lower_bound(data, data + list.size, offset,
                         [](const Posting& p, uint32_t wanted) { return p.offset < wanted; });
    return at != data + list.size && at->offset == offset ? uint32_t(at - data) : kNoSlot;
  };
  for (size_t i = 0; i < bow.size(); ++i) {
    if (find(segment.lists[bow[i].word]) == kNoSlot) {
      return Status::InvalidArgument("bow[" + std::to_string(i) +
                                     "].word = " + std::to_string(bow[i].word) +
                                     " has no posting for place " + std::to_string(place) +
                                     ": pass the vector the place was added with");
    }
  }
  for (const BowEntry& entry : bow) {
    WordList& list = segment.lists[entry.word];
    segment.ErasePosting(&list, find(list));
    --posting_count_;
    --word_places_[entry.word];
  }
  present_[place] = 0;
  --place_count_;
  if (--segment.place_count == 0) {
    // An emptied segment gives back its word table too (8 bytes per word). Postings left by a
    // Remove with a mismatched vector cannot exist: Remove checks every word first.
    segment = Segment();
  } else {
    segment.CompactIfFragmented();
  }
  return Status::Ok();
}

Result<InvertedIndex::DetachedSegment> InvertedIndex::BuildSegment(
    uint32_t word_count, std::span<const BulkPlace> places) {
  DetachedSegment built;
  built.word_count_ = word_count;
  if (places.empty()) return built;
  built.index_ = places.front().place >> kSegmentBits;
  // Pass 1: check every place as Add would, and count each word's postings.
  std::vector<uint32_t> counts(word_count, 0);
  for (size_t i = 0; i < places.size(); ++i) {
    const PlaceId place = places[i].place;
    if ((place >> kSegmentBits) != built.index_ || (i > 0 && place <= places[i - 1].place)) {
      return Status::InvalidArgument("place " + std::to_string(place) + " does not follow place " +
                                     std::to_string(places[i > 0 ? i - 1 : 0].place) +
                                     " in segment " + std::to_string(built.index_) +
                                     ": a bulk-built segment takes increasing ids of one segment");
    }
    PLACEDB_RETURN_IF_ERROR(ValidateBow(*places[i].bow, word_count));
    for (const BowEntry& entry : *places[i].bow) ++counts[entry.word];
    built.posting_count_ += places[i].bow->size();
  }
  // Pass 2: give each word's run its final storage once, in word order.
  Segment& segment = built.segment_;
  segment = Segment(word_count);
  for (WordId word = 0; word < word_count; ++word) {
    if (counts[word] == 0) continue;
    built.words_.push_back(word);
    // Slab locations are 31-bit; each run needs at most one new page.
    if (segment.pages.size() >= kBigListBit / kPagePostings) {
      return Status::ResourceExhausted("inverted index: posting storage of segment " +
                                       std::to_string(built.index_) + " is full");
    }
    // Slab runs get Add's class; a longer run gets exactly its size, where Add would leave up
    // to 1/8 headroom (a later Add to it grows it as Add grows any run).
    segment.Relocate(&segment.lists[word],
                     counts[word] <= kMaxSlabCapacity ? CapacityFor(counts[word]) : counts[word]);
  }
  // Pass 3: a counting sort. Places come in increasing id order, so each run fills front to
  // back, already sorted by offset; `size` is the run's write cursor.
  for (const BulkPlace& bulk : places) {
    const uint16_t offset = uint16_t(bulk.place & ((1u << kSegmentBits) - 1));
    for (const BowEntry& entry : *bulk.bow) {
      WordList& list = segment.lists[entry.word];
      segment.Data(list)[list.size++] = Posting{offset, EncodeWeight(entry.weight)};
    }
    built.places_.push_back(bulk.place);
  }
  segment.place_count = uint32_t(places.size());
  segment.scan_limit = (places.back().place & ((1u << kSegmentBits) - 1)) + 1;
  return built;
}

Status InvertedIndex::Install(DetachedSegment&& built) {
  if (built.places_.empty()) return Status::Ok();
  if (built.word_count_ != word_count_) {
    return Status::FailedPrecondition("segment " + std::to_string(built.index_) +
                                      " was built for " + std::to_string(built.word_count_) +
                                      " words, the index has " + std::to_string(word_count_));
  }
  const uint32_t first_offset = built.places_.front() & ((1u << kSegmentBits) - 1);
  const bool append = built.index_ < segments_.size() && segments_[built.index_].place_count > 0;
  if (append) {
    const Segment& target = segments_[built.index_];
    if (target.scan_limit > first_offset) {
      return Status::FailedPrecondition(
          "segment " + std::to_string(built.index_) + " already holds places from id " +
          std::to_string((PlaceId(built.index_) << kSegmentBits) + target.scan_limit - 1) +
          " down: built places install only above the highest id ever added there");
    }
    // Each appended run needs at most one new page (slab locations are 31-bit).
    if (target.pages.size() + built.words_.size() > kBigListBit / kPagePostings) {
      return Status::ResourceExhausted("inverted index: posting storage of segment " +
                                       std::to_string(built.index_) + " is full");
    }
  }
  if (built.index_ >= segments_.size()) segments_.resize(size_t(built.index_) + 1);
  const PlaceId last = built.places_.back();
  if (last >= present_.size()) present_.resize(size_t(last) + 1, 0);
  for (PlaceId place : built.places_) present_[place] = 1;
  for (WordId word : built.words_) word_places_[word] += built.segment_.lists[word].size;
  place_count_ += built.places_.size();
  posting_count_ += built.posting_count_;
  if (!append) {
    segments_[built.index_] = std::move(built.segment_);  // the usual case: nothing to copy
  } else {
    // Append each run after the target's (all its offsets are lower), growing like Add.
    Segment& target = segments_[built.index_];
    for (WordId word : built.words_) {
      const WordList& from = built.segment_.lists[word];
      WordList& to = target.lists[word];
      if (to.size + from.size > target.Capacity(to)) {
        target.Relocate(&to, CapacityFor(to.size + from.size));
      }
      std::memcpy(target.Data(to) + to.size, built.segment_.Data(from),
                  from.size * sizeof(Posting));
      to.size += from.size;
    }
    target.place_count += built.segment_.place_count;
    target.scan_limit = built.segment_.scan_limit;
    target.CompactIfFragmented();
  }
  built = DetachedSegment();
  return Status::Ok();
}

bool InvertedIndex::Contains(PlaceId place) const {
  return place < present_.size() && present_[place] != 0;
}

template <ScoringType kType>
void InvertedIndex::ScoreSegment(uint32_t segment_index, const QueryContext& query,
                                 QueryScratch* scratch) const {
  using Accumulator = AccumulatorOf<kType>;
  const Segment& segment = segments_[segment_index];
  Accumulator* score = scratch->score<Accumulator>();
  std::vector<PostingRun>& runs = scratch->runs;
  runs.clear();
  const BowVector& bow = *query.bow;
  constexpr size_t kAhead = 16;
  for (size_t i = 0; i < bow.size(); ++i) {
    if (i + kAhead < bow.size() && bow[i + kAhead].word < word_count_) {
      __builtin_prefetch(&segment.lists[bow[i + kAhead].word]);
    }
    if (bow[i].word >= word_count_) continue;  // not a word of this vocabulary: shares nothing
    const WordList& list = segment.lists[bow[i].word];
    if (list.size > 0) runs.push_back({segment.Data(list), list.size, bow[i].weight});
  }
  // Prefetch a few runs ahead: most runs are short, so each would otherwise start with a miss.
  constexpr size_t kPrefetchDistance = 8;
  for (size_t r = 0; r < runs.size(); ++r) {
    if (r + kPrefetchDistance < runs.size()) {
      __builtin_prefetch(runs[r + kPrefetchDistance].postings);
    }
    const Posting* postings = runs[r].postings;
    const uint32_t size = runs[r].size;
    const Accumulator q = runs[r].query_weight;
    if constexpr (kType == ScoringType::kL1) {
      // |q - c| - |q| - |c| is -2 min(q, c) when both are >= 0 and 0 when their signs differ:
      // one min per posting instead of three absolute values (the hot loop of the paper's score).
      if (q >= 0) {
        for (uint32_t i = 0; i < size; ++i) {
          const float c = std::max(DecodeWeight(postings[i].weight), 0.0f);
          score[postings[i].offset] += -2.0f * std::min(q, c);
        }
      } else {
        for (uint32_t i = 0; i < size; ++i) {
          const float c = std::min(DecodeWeight(postings[i].weight), 0.0f);
          score[postings[i].offset] += 2.0f * std::max(q, c);
        }
      }
    } else {
      for (uint32_t i = 0; i < size; ++i) {
        score[postings[i].offset] += Term<kType, Accumulator>(q, DecodeWeight(postings[i].weight));
      }
    }
  }

  const PlaceId base = segment_index << kSegmentBits;
  // The bonus list's places of this segment: finalised apart (their bonus is added after
  // FinalizeScore), and taken out of the accumulator so the scan below skips them.
  auto bonus_begin =
      std::lower_bound(query.bonus.begin(), query.bonus.end(), base,
                       [](const ScoredPlace& b, PlaceId place) { return b.place < place; });
  for (auto it = bonus_begin;
       it != query.bonus.end() && (it->place >> kSegmentBits) == segment_index; ++it) {
    const Accumulator accumulated = std::exchange(score[it->place - base], Accumulator(0));
    if (!query.Accept(it->place)) continue;
    scratch->bonus_candidates.push_back({it->place, double(accumulated), it->score});
  }

  // A zero sum marks a place that shares no word (a sum of terms that is exactly zero scores
  // like one). Only candidates that beat the worker's current k-th reach present_ and accept.
  std::vector<KeyedPlace>& top = scratch->top;
  const size_t k = query.top_k;
  for (uint32_t offset = 0; offset < segment.scan_limit; ++offset) {
    const Accumulator accumulated = score[offset];
    if (accumulated == 0) continue;
    score[offset] = 0;
    const KeyedPlace candidate{
        SumDecreasesScore(kType) ? -double(accumulated) : double(accumulated), base + offset};
    if (top.size() == k && !Better(candidate, top.front())) continue;
    if (!present_[candidate.place] || !query.Accept(candidate.place)) continue;
    if (top.size() == k) {
      std::pop_heap(top.begin(), top.end(), Better);
      top.pop_back();
    }
    top.push_back(candidate);
    std::push_heap(top.begin(), top.end(), Better);
  }
}

std::vector<ScoredPlace> InvertedIndex::Query(const BowVector& bow, size_t top_k,
                                              const std::function<bool(PlaceId)>& accept,
                                              std::span<const ScoredPlace> bonus, int threads,
                                              double max_word_share) const {
  std::vector<ScoredPlace> result;
  if (top_k == 0 || place_count_ == 0) return result;

  std::vector<uint32_t> live_segments;
  for (uint32_t s = 0; s < segments_.size(); ++s) {
    if (segments_[s].place_count > 0) live_segments.push_back(s);
  }
  const int workers = int(std::min<size_t>(size_t(std::max(threads, 1)), live_segments.size()));

  // Per calling thread, one scratch per worker; a nested Query (from inside `accept`) must not
  // share them, so it gets its own.
  thread_local std::vector<QueryScratch> thread_scratch;
  thread_local bool thread_scratch_in_use = false;
  std::vector<QueryScratch> nested_scratch;
  const bool nested = thread_scratch_in_use;
  std::vector<QueryScratch>& scratch = nested ? nested_scratch : thread_scratch;
  if (scratch.size() < size_t(workers)) scratch.resize(size_t(workers));
  struct ScratchGuard {
    bool nested;
    ~ScratchGuard() {
      if (!nested) thread_scratch_in_use = false;
    }
  } guard{nested};
  thread_scratch_in_use = true;
  for (int w = 0; w < workers; ++w) {
    scratch[size_t(w)].top.clear();
    scratch[size_t(w)].bonus_candidates.clear();
  }

  // The bonus list sorted by place, each place once (the first entry wins), indexed places only.
  std::vector<ScoredPlace> sorted_bonus;
  for (const ScoredPlace& b : bonus) {
    if (Contains(b.place)) sorted_bonus.push_back(b);
  }
  std::stable_sort(sorted_bonus.begin(), sorted_bonus.end(),
                   [](const ScoredPlace& a, const ScoredPlace& b) { return a.place < b.place; });
  sorted_bonus.erase(
      std::unique(sorted_bonus.begin(), sorted_bonus.end(),
                  [](const ScoredPlace& a, const ScoredPlace& b) { return a.place == b.place; }),
      sorted_bonus.end());

  // The words scored: all of them, or those held by at most max_word_share of the places.
  BowVector kept_words, skipped_words;
  const BowVector* scored_words = &bow;
  if (max_word_share < 1.0) {
    const double most_places = max_word_share * double(place_count_);
    for (const BowEntry& entry : bow) {
      if (entry.word >= word_count_) continue;  // shares nothing
      (double(word_places_[entry.word]) <= most_places ? kept_words : skipped_words)
          .push_back(entry);
    }
    scored_words = &kept_words;
  }
  // Skipping words: more candidates by the other words, then each rescored with the skipped ones.
  const size_t candidates = skipped_words.empty() ? top_k : RescoredCandidates(top_k);
  QueryContext context{scored_words,
                       candidates,
                       accept ? &accept : nullptr,
                       sorted_bonus,
                       QueryConstant(scoring_, bow),
                       workers > 1,
                       {}};
  auto score_segment = [&](size_t task, int worker) {
    QueryScratch* worker_scratch = &scratch[size_t(worker)];
    const uint32_t segment = live_segments[task];
    switch (scoring_) {
      case ScoringType::kL1:
        ScoreSegment<ScoringType::kL1>(segment, context, worker_scratch);
        break;
      case ScoringType::kL2:
        ScoreSegment<ScoringType::kL2>(segment, context, worker_scratch);
        break;
      case ScoringType::kChiSquare:
        ScoreSegment<ScoringType::kChiSquare>(segment, context, worker_scratch);
        break;
      case ScoringType::kKL:
        ScoreSegment<ScoringType::kKL>(segment, context, worker_scratch);
        break;
      case ScoringType::kBhattacharyya:
        ScoreSegment<ScoringType::kBhattacharyya>(segment, context, worker_scratch);
        break;
      case ScoringType::kDotProduct:
        ScoreSegment<ScoringType::kDotProduct>(segment, context, worker_scratch);
        break;
    }
  };
  ParallelFor(live_segments.size(), workers, score_segment);

  // Each worker kept its own top k (and all bonus places): the answer is the best k of their
  // union, whatever segments each worker happened to score.
  // Rescoring the skipped words starts from the best `candidates` of that union, so the
  // candidates, like the answer, do not depend on the thread count.
  const bool decreasing = SumDecreasesScore(scoring_);
  std::vector<KeyedPlace> kept;
  for (int w = 0; w < workers; ++w) {
    kept.insert(kept.end(), scratch[size_t(w)].top.begin(), scratch[size_t(w)].top.end());
  }
  if (kept.size() > candidates) {
    std::partial_sort(kept.begin(), kept.begin() + std::ptrdiff_t(candidates), kept.end(), Better);
    kept.resize(candidates);
  }
  // The candidates with their sums over the scored words (bonus places with their bonus), then
  // the skipped words' terms added, in place order (one pass over each run per segment).
  struct Candidate {
    PlaceId place;
    double accumulated;
    double bonus;
    bool from_bonus;
  };
  std::vector<Candidate> found;
  for (const KeyedPlace& place : kept) {
    found.push_back({place.place, decreasing ? -place.key : place.key, 0.0, false});
  }
  for (int w = 0; w < workers; ++w) {
    for (const BonusCandidate& b : scratch[size_t(w)].bonus_candidates) {
      found.push_back({b.place, b.accumulated, b.bonus, true});
    }
  }
  if (!skipped_words.empty()) {
    std::sort(found.begin(), found.end(),
              [](const Candidate& a, const Candidate& b) { return a.place < b.place; });
    std::vector<PlaceId> places(found.size());
    std::vector<double> sums(found.size(), 0.0);
    for (size_t i = 0; i < found.size(); ++i) places[i] = found[i].place;
    AddSkippedWords(skipped_words, places, sums);
    for (size_t i = 0; i < found.size(); ++i) found[i].accumulated += sums[i];
  }
  for (const Candidate& c : found) {
    if (!c.from_bonus) {
      result.push_back({c.place, FinalizeScore(scoring_, c.accumulated, context.query_constant)});
      continue;
    }
    const double shared =
        c.accumulated != 0 ? FinalizeScore(scoring_, c.accumulated, context.query_constant) : 0;
    result.push_back({c.place, shared + c.bonus});
  }
  auto better = [](const ScoredPlace& a, const ScoredPlace& b) {
    return a.score != b.score ? a.score > b.score : a.place < b.place;
  };
  std::sort(result.begin(), result.end(), better);
  if (result.size() > top_k) result.resize(top_k);
  return result;
}

namespace {

// The first posting in [from, end) whose offset is >= `offset` (postings sorted by offset;
// `run` is the run's start, from which positions are interpolated).
template <typename Posting>
const Posting* FindOffset(const Posting* run, const Posting* from, const Posting* end,
                          uint16_t offset) {
  const auto before = [](const Posting& p, uint16_t wanted) { return p.offset < wanted; };
  const size_t size = size_t(end - run);
  const Posting* guess = run + ((size_t(offset) * size) >> 16);
  if (guess < from) guess = from;
  if (guess >= end) guess = end - 1;
  size_t step = 1;
  if (guess->offset < offset) {  // gallop forward: the answer is after guess
    const Posting* low = guess;
    while (size_t(end - low) > step && low[step].offset < offset) {
      low += step;
      step *= 2;
    }
    const Posting* high = size_t(end - low) > step ? low + step + 1 : end;
    return std::lower_bound(low + 1, high, offset, before);
  }
  const Posting* high = guess;  // gallop backward: the answer is at or before guess
  while (size_t(high - from) > step && (high - step)->offset >= offset) {
    high -= step;
    step *= 2;
  }
  const Posting* low = size_t(high - from) > step ? high - step : from;
  return std::lower_bound(low, high + 1, offset, before);
}

}  // namespace

void InvertedIndex::AddSkippedWords(const BowVector& skipped, std::span<const PlaceId> places,
                                    std::span<double> sums) const {
  constexpr PlaceId kOffsetMask = (PlaceId(1) << kSegmentBits) - 1;
  std::vector<PostingRun> runs;
  for (size_t first = 0; first < places.size();) {
    const PlaceId segment_index = places[first] >> kSegmentBits;
    size_t last = first;
    while (last < places.size() && places[last] >> kSegmentBits == segment_index) ++last;
    const Segment& segment = segments_[segment_index];
    // Every lookup below is a likely cache miss (a frequent word's run is long, the candidates
    // few): resolve the runs, then prefetch a few runs ahead where each candidate should be, so
    // that the misses overlap.
    runs.clear();
    constexpr size_t kAhead = 16;
    for (size_t w = 0; w < skipped.size(); ++w) {
      if (w + kAhead < skipped.size()) __builtin_prefetch(&segment.lists[skipped[w + kAhead].word]);
      const WordList& list = segment.lists[skipped[w].word];
      if (list.size > 0) runs.push_back({segment.Data(list), list.size, skipped[w].weight});
    }
    const auto guess = [](const PostingRun& run, PlaceId place) {
      return run.postings + ((size_t(place & kOffsetMask) * run.size) >> 16);
    };
    constexpr size_t kRunsAhead = 4;
    for (size_t r = 0; r < std::min(kRunsAhead, runs.size()); ++r) {
      for (size_t i = first; i < last; ++i) __builtin_prefetch(guess(runs[r], places[i]));
    }
    for (size_t r = 0; r < runs.size(); ++r) {
      if (r + kRunsAhead < runs.size()) {
        for (size_t i = first; i < last; ++i) {
          __builtin_prefetch(guess(runs[r + kRunsAhead], places[i]));
        }
      }
      // The places ascend, so each search starts where the previous one ended. A frequent
      // word's offsets spread evenly over the segment: start from the interpolated position and
      // gallop, a few cache lines instead of a binary search's dozen misses in a long run.
      const Posting* posting = runs[r].postings;
      const Posting* end = posting + runs[r].size;
      for (size_t i = first; i < last && posting != end; ++i) {
        const uint16_t offset = uint16_t(places[i] & kOffsetMask);
        posting = FindOffset(runs[r].postings, posting, end, offset);
        if (posting != end && posting->offset == offset) {
          sums[i] += ScoreTerm(scoring_, runs[r].query_weight, DecodeWeight(posting->weight));
        }
      }
    }
    first = last;
  }
}

size_t InvertedIndex::MemoryBytes() const {
  size_t bytes =
      segments_.capacity() * sizeof(Segment) + word_places_.capacity() * sizeof(uint32_t);
  for (const Segment& segment : segments_) bytes += segment.MemoryBytes();
  bytes += present_.capacity();
  return bytes;
}

}  // namespace placedb
