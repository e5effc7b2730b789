// Bayesian loop-closure detection for one agent stream, with bounded working memory.
//
// The design follows RTAB-Map (Labbe & Michaud 2013), which Deng et al. build on; docs/rgbd.md
// states every choice. Each frame arrives as a BoW vector (vocabulary.h or float_vocabulary.h).
//
//  - Places and STM. A frame becomes a new place, linked to the previous one, unless it is nearly
//    identical to the previous place (similarity >= T_rehearsal, default 20 %): then it is merged
//    into it (rehearsal: the place takes the newer appearance and its weight grows by one). The
//    newest `short_term_memory` places (STM, default 30) are never loop candidates; the oldest
//    STM place moves to working memory (WM) as the next one arrives.
//  - The filter. Hypotheses: S_t = -1 (no loop) and S_t = i for every WM place. Prediction
//    (equation 2 of Deng et al.): p(-1|-1) = 0.9, p(i|-1) = 0.1 / |WM|; p(-1|j) = 0.1, and the
//    other 0.9 of p(.|j) spread over j's graph neighbourhood by a discretised Gaussian of the
//    link distance (sigma 1.6, radius 16). Observation (equation 1): similarities s_i from the
//    inverted index (normalised score in [0, 1]), their mean mu and deviation sigma over WM;
//    likelihood (s_i - sigma) / mu when s_i >= mu + sigma, else 1; no-loop likelihood
//    mu / sigma + 1. Posterior = likelihood x prediction, normalised. A loop is accepted when
//    the best place's posterior exceeds T_loop (default 12 %) and this frame's observation
//    favours it over "no loop" (its likelihood > 1 and > the no-loop likelihood); it adds a
//    loop link. Beyond RTAB-Map (default on): the WM's median similarity is subtracted before
//    the normalisation (see LikelihoodBaseline).
//  - Memory management. WM is bounded by a place count and/or a per-update time budget: when
//    over, the WM places of lowest weight (then oldest) move to long-term memory (LTM): kept in
//    the graph, removed from the index, their BoW handed to a LongTermMemory store. After each
//    update the LTM neighbours of the best hypothesis come back (retrieval) and compete from the
//    next frame on. Search cost therefore depends on the WM bound, not on the map's size.
//
// Not thread-safe: one detector per agent stream, frames in order.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/base/status.h"
#include "core/search/place_index.h"
#include "core/search/scoring.h"
#include "core/vocabulary/bow.h"

namespace placedb {

class Stopwatch;  // core/base/timing.h

inline constexpr PlaceId kNoPlace = 0;

// Where the BoW vectors of places in long-term memory live. The detector calls Store() when a
// place leaves WM, Fetch() when it is retrieved and then Release() (the WM owns it again). A
// persistent map, which stores every place's vector anyway, can make Store/Release no-ops.
class LongTermMemory {
 public:
  virtual ~LongTermMemory() = default;
  virtual Status Store(PlaceId place, const BowVector& bow) = 0;
  virtual Result<BowVector> Fetch(PlaceId place) = 0;  // NOT_FOUND when unknown
  virtual void Release(PlaceId place) = 0;
};

class InMemoryLongTermMemory final : public LongTermMemory {
 public:
  Status Store(PlaceId place, const BowVector& bow) override;
  Result<BowVector> Fetch(PlaceId place) override;
  void Release(PlaceId place) override;
  size_t size() const { return bows_.size(); }

 private:
  std::unordered_map<PlaceId, BowVector> bows_;
};

// How two places' BoW vectors compare, in [0, 1].
enum class SimilarityMeasure {
  kWordOverlap,  // shared words / words of the larger vector (RTAB-Map's similarity)
  kScore,        // the configured scoring (scoring.h) on the TF-IDF vectors
};
const char* SimilarityMeasureName(SimilarityMeasure measure);
Result<SimilarityMeasure> ParseSimilarityMeasure(
    const std::string& name);  // "word_overlap", "score"

enum class LikelihoodBaseline {
  kNone,    // RTAB-Map's normalisation on the raw similarities
  kMedian,  // subtract the WM's median similarity first
};

struct LoopClosureConfig {
  // The similarity behind the likelihood and behind rehearsal (scoring: for kScore).
  SimilarityMeasure likelihood_similarity = SimilarityMeasure::kWordOverlap;
  SimilarityMeasure rehearsal_similarity = SimilarityMeasure::kWordOverlap;
  LikelihoodBaseline likelihood_baseline = LikelihoodBaseline::kMedian;
  ScoringType scoring = ScoringType::kL1;
  double loop_threshold = 0.12;       // T_loop
  double rehearsal_threshold = 0.20;  // T_rehearsal; > 1 disables rehearsal
  int short_term_memory = 30;         // STM size in places
  double no_loop_stay = 0.9;          // p(S_t = -1 | S_t-1 = -1)
  double loop_to_no_loop = 0.1;       // p(S_t = -1 | S_t-1 = j)
  double transition_sigma = 1.6;      // places (link distance)
  int transition_radius = 16;         // places
  // Acceptance looks at the posterior summed over the best place and its neighbours within this
  // link distance (0: the best place alone).
  int hypothesis_radius = 0;
  // No loop is accepted while WM holds fewer candidates than this: the likelihood's mean and
  // deviation are not estimates yet, and the uniform transition alone gives each of a handful
  // of places a posterior near T_loop.
  int min_candidates = 8;
  // ... nor one whose similarity exceeds the baseline by less than this: the normalisation is
  // scale-free, so among places sharing nothing a single shared word would otherwise look like
  // overwhelming evidence.
  double min_similarity_excess = 0.02;
  // Working memory: at most this many places (0 = unbounded) ...
  size_t max_working_memory = 0;
  // ... and/or an update that took longer than this (0 = no budget) transfers places to LTM in
  // proportion to the overshoot.
  double time_budget_ms = 0;
  int retrieval_radius = 1;  // LTM neighbours of the best hypothesis within this link distance
  int max_retrieved = 2;     // ... at most this many per update
};

Status ValidateLoopClosureConfig(const LoopClosureConfig& config);

enum class MemoryTier { kShortTerm, kWorking, kLongTerm };
const char* MemoryTierName(MemoryTier tier);

struct PlaceInfo {
  PlaceId id = kNoPlace;
  MemoryTier tier = MemoryTier::kShortTerm;
  int weight = 0;                   // frames merged into it by rehearsal
  std::vector<uint64_t> frames;     // caller's frame tags, oldest first; the last is its look
  std::vector<PlaceId> neighbours;  // temporal links
  std::vector<PlaceId> loops;       // accepted loop links
};

struct LoopClosureUpdate {
  bool skipped = false;           // empty BoW vector: nothing stored, filter untouched
  PlaceId place = kNoPlace;       // the place this frame created or was merged into
  bool merged = false;            // rehearsal merged the frame into the previous place
  std::optional<PlaceId> loop;    // accepted loop closure
  PlaceId best = kNoPlace;        // best WM hypothesis (whether accepted or not)
  double best_posterior = 0;      // its posterior (summed per hypothesis_radius)
  double best_score = 0;          // its similarity above the WM baseline
  double best_likelihood = 0;     // its observation likelihood (1 = not singled out)
  double no_loop_likelihood = 0;  // mu / sigma + 1
  double no_loop_posterior = 1;
  size_t candidates = 0;             // WM places searched
  std::vector<PlaceId> retrieved;    // LTM -> WM in this update
  std::vector<PlaceId> transferred;  // WM -> LTM in this update
  Status memory_status;              // first LTM store/fetch error, if any (the update still ran)
  double search_ms = 0;              // inverted-index similarity
  double filter_ms = 0;              // prediction + posterior
  double memory_ms = 0;              // STM, retrieval, transfer
  double total_ms = 0;
};

struct LoopClosureStats {
  size_t places = 0;
  size_t short_term = 0;
  size_t working = 0;
  size_t long_term = 0;
  uint64_t frames = 0;
  uint64_t merged = 0;
  uint64_t loops = 0;
  uint64_t rejected = 0;  // accepted by the filter, then taken back (RejectLoop)
  uint64_t retrieved = 0;
  uint64_t transferred = 0;
  size_t index_bytes = 0;
};

class LoopClosureDetector {
 public:
  // `word_count`: the vocabulary's word count. Without `ltm`, an in-memory store is used.
  static Result<std::unique_ptr<LoopClosureDetector>> Create(
      uint32_t word_count, const LoopClosureConfig& config,
      std::shared_ptr<LongTermMemory> ltm = nullptr);

  // One frame: `bow` as Transform() produced it (normalised here), `frame_tag` any caller id
  // (sequence number, timestamp). INVALID_ARGUMENT for a word outside the vocabulary.
  Result<LoopClosureUpdate> Update(const BowVector& bow, uint64_t frame_tag);
  // Rebuilds memory from places stored earlier (e.g. a reopened map), oldest first: `bow` becomes
  // a new place linked to the previous one, without rehearsal and without a filter update; the
  // working-memory size bound applies (transferred places go to the LongTermMemory). Weights and
  // loop links of the earlier run are not known here. INVALID_ARGUMENT as Update, and for an
  // empty vector.
  Result<PlaceId> Replay(const BowVector& bow, uint64_t frame_tag);
  // Takes back the loop the last Update() accepted from `place` to `loop` (e.g. it failed
  // geometric verification): the link is removed and the loop is counted as rejected instead.
  // NOT_FOUND when there is no such link.
  Status RejectLoop(PlaceId place, PlaceId loop);

  std::optional<PlaceInfo> Get(PlaceId place) const;
  double Posterior(PlaceId place) const;  // 0 for places outside WM
  LoopClosureStats Stats() const;
  const LoopClosureConfig& config() const { return config_; }

 private:
  // Cold per-place data. The hot part (tier, temporal links) lives in compact arrays by id:
  // every update walks the neighbourhoods of all WM places, and with most of a large map in LTM
  // those walks would otherwise miss the cache on every step.
  struct Place {
    int weight = 0;
    BowVector bow;  // normalised for config.scoring; empty in LTM
    std::vector<uint64_t> frames;
    std::vector<PlaceId> loops;
    size_t wm_slot = 0;  // position in wm_ while in WM
  };
  MemoryTier tier(PlaceId id) const { return MemoryTier(tier_[id]); }
  Status CheckBow(const BowVector& bow) const;
  // A new STM place linked to the newest one; the oldest STM place moves to WM when STM is full.
  PlaceId AddPlace(BowVector normalised_bow, uint64_t frame_tag);
  // Moves up to `excess` WM places (lowest weight, then oldest; not `is_protected`) to LTM.
  void TransferExcess(size_t excess, const std::function<bool(PlaceId)>& is_protected,
                      std::vector<PlaceId>* transferred, Status* status);

  // The steps of Update(), in order.
  // STM and rehearsal: merges a frame nearly identical to the previous place into it (newer look,
  // weight + 1), so a robot standing still does not fill memory; else AddPlace. Sets `merged`.
  PlaceId RehearseOrAddPlace(BowVector normalised_bow, uint64_t frame_tag, bool* merged);
  // The likelihood's similarities: WM places sharing a word with `bow`, in [0, 1].
  std::vector<ScoredPlace> SearchWorkingMemory(const BowVector& bow) const;
  // One Bayes filter step over WM and the loop decision; empties the filter when WM is empty.
  void FilterStep(std::vector<ScoredPlace>* scored, LoopClosureUpdate* update);
  // Observation (equation 1): baseline-subtracted scores and likelihoods by id; returns the
  // no-loop likelihood mu / sigma + 1.
  double Observe(std::vector<ScoredPlace>* scored, std::vector<double>* place_likelihood,
                 std::vector<double>* score_of) const;
  // Prediction (equation 2) from the previous posterior: WM beliefs by id; returns "no loop"'s.
  double Predict(std::vector<double>* predicted) const;
  // Posterior = likelihood x prediction, normalised over "no loop" and WM.
  void UpdatePosterior(const std::vector<double>& place_likelihood, double no_loop_likelihood,
                       const std::vector<double>& predicted, double predicted_no_loop);
  // The WM place of highest posterior (ties: lower id); WM must not be empty.
  PlaceId BestHypothesis() const;
  // The posterior acceptance compares with T_loop: summed over WM within hypothesis_radius.
  double HypothesisPosterior(PlaceId best) const;
  // An accepted loop: links both places (once) and counts it.
  void AddLoopLink(PlaceId place, PlaceId loop);
  // Retrieval: LTM neighbours of the best hypothesis back to WM, so a revisit can compete.
  void RetrieveNeighbours(LoopClosureUpdate* update);
  // Transfer: WM back within its place bound and, after an update over budget, its time budget;
  // the best hypothesis, the accepted loop and the retrieved places stay.
  void TransferOverBounds(const Stopwatch& total, LoopClosureUpdate* update);

  LoopClosureDetector(uint32_t word_count, const LoopClosureConfig& config,
                      std::shared_ptr<LongTermMemory> ltm);

  void MoveToWorking(PlaceId id);
  // WM -> LTM; false (and `status` set) when the store refused.
  bool MoveToLongTerm(PlaceId id, Status* status);
  bool Retrieve(PlaceId id, Status* status);
  // Places within `radius` links of `from` (any tier), with their distance, nearest first.
  void Neighbourhood(PlaceId from, int radius, std::vector<std::pair<PlaceId, int>>* out) const;
  double Similarity(SimilarityMeasure measure, const BowVector& a, const BowVector& b) const;
  // What the index holds for a place: its vector, or all weights 1 for kWordOverlap (the index
  // then scores shared-word counts with the dot product).
  const BowVector& IndexForm(const BowVector& bow) const;

  const LoopClosureConfig config_;
  const uint32_t word_count_;
  std::shared_ptr<LongTermMemory> ltm_;
  InvertedIndex index_;                               // WM places only
  std::vector<Place> places_;                         // by id; index 0 unused
  std::vector<uint8_t> tier_;                         // by id: MemoryTier
  std::vector<std::array<PlaceId, 2>> chain_;         // by id: previous and next place (temporal)
  std::vector<uint8_t> has_loops_;                    // by id
  std::vector<PlaceId> stm_;                          // oldest first
  std::vector<PlaceId> wm_;                           // unordered
  std::set<std::pair<int, PlaceId>> transfer_order_;  // WM places by (weight, id)
  std::vector<double> posterior_;                     // by id; WM places only
  double no_loop_ = 1.0;
  std::vector<double> gaussian_;  // by distance
  mutable std::vector<uint32_t> visit_mark_;
  mutable uint32_t visit_generation_ = 0;
  mutable BowVector index_form_;
  uint64_t frames_ = 0, merged_ = 0, loops_ = 0, rejected_ = 0, retrieved_ = 0, transferred_ = 0;
  size_t long_term_ = 0;
};

}  // namespace placedb
