#include "core/search/loop_closure.h"

#include <algorithm>
#include <cmath>

#include "core/base/timing.h"

namespace placedb {

// ---- LongTermMemory --------------------------------------------------------------------------

Status InMemoryLongTermMemory::Store(PlaceId place, const BowVector& bow) {
  bows_[place] = bow;
  return Status::Ok();
}

Result<BowVector> InMemoryLongTermMemory::Fetch(PlaceId place) {
  auto it = bows_.find(place);
  if (it == bows_.end()) {
    return Status::NotFound("place " + std::to_string(place) + " is not in long-term memory");
  }
  return it->second;
}

void InMemoryLongTermMemory::Release(PlaceId place) {
  bows_.erase(place);
}

// ---- Configuration ---------------------------------------------------------------------------

Status ValidateLoopClosureConfig(const LoopClosureConfig& c) {
  auto probability = [](double p) { return p >= 0 && p <= 1; };
  if (!probability(c.loop_threshold)) {
    return Status::InvalidArgument("loop_threshold must be in [0, 1], got " +
                                   std::to_string(c.loop_threshold));
  }
  if (!(c.rehearsal_threshold >= 0) || !std::isfinite(c.rehearsal_threshold)) {
    return Status::InvalidArgument("rehearsal_threshold must be >= 0 (above 1 disables it)");
  }
  if (c.short_term_memory < 0 || c.short_term_memory > 100000) {
    return Status::InvalidArgument("short_term_memory must be in [0, 100000], got " +
                                   std::to_string(c.short_term_memory));
  }
  if (!probability(c.no_loop_stay) || !probability(c.loop_to_no_loop)) {
    return Status::InvalidArgument("no_loop_stay and loop_to_no_loop must be in [0, 1]");
  }
  if (!(c.transition_sigma > 0) || !std::isfinite(c.transition_sigma)) {
    return Status::InvalidArgument("transition_sigma must be positive");
  }
  if (c.transition_radius < 0 || c.transition_radius > 1000) {
    return Status::InvalidArgument("transition_radius must be in [0, 1000]");
  }
  if (!(c.min_similarity_excess >= 0 && c.min_similarity_excess <= 1)) {
    return Status::InvalidArgument("min_similarity_excess must be in [0, 1]");
  }
  if (c.min_candidates < 1 || c.min_candidates > 100000) {
    return Status::InvalidArgument("min_candidates must be in [1, 100000]");
  }
  if (c.hypothesis_radius < 0 || c.hypothesis_radius > 1000) {
    return Status::InvalidArgument("hypothesis_radius must be in [0, 1000]");
  }
  if (!(c.time_budget_ms >= 0) || !std::isfinite(c.time_budget_ms)) {
    return Status::InvalidArgument("time_budget_ms must be >= 0");
  }
  if (c.retrieval_radius < 0 || c.retrieval_radius > 100) {
    return Status::InvalidArgument("retrieval_radius must be in [0, 100]");
  }
  if (c.max_retrieved < 0 || c.max_retrieved > 10000) {
    return Status::InvalidArgument("max_retrieved must be in [0, 10000]");
  }
  // The likelihood needs a score in [0, 1]: mu / sigma only means something for those.
  if (c.scoring == ScoringType::kKL || c.scoring == ScoringType::kDotProduct) {
    return Status::InvalidArgument(std::string("scoring ") + ScoringName(c.scoring) +
                                   " is not a normalised similarity; use l1, l2, chi2 or "
                                   "bhattacharyya");
  }
  return Status::Ok();
}

const char* SimilarityMeasureName(SimilarityMeasure measure) {
  return measure == SimilarityMeasure::kScore ? "score" : "word_overlap";
}

Result<SimilarityMeasure> ParseSimilarityMeasure(const std::string& name) {
  if (name == "word_overlap") return SimilarityMeasure::kWordOverlap;
  if (name == "score") return SimilarityMeasure::kScore;
  return Status::InvalidArgument("unknown similarity \"" + name +
                                 "\" (expected word_overlap or score)");
}

const char* MemoryTierName(MemoryTier tier) {
  switch (tier) {
    case MemoryTier::kShortTerm:
      return "short_term";
    case MemoryTier::kWorking:
      return "working";
    case MemoryTier::kLongTerm:
      return "long_term";
  }
  return "unknown";
}

// ---- Detector --------------------------------------------------------------------------------

Result<std::unique_ptr<LoopClosureDetector>> LoopClosureDetector::Create(
    uint32_t word_count, const LoopClosureConfig& config, std::shared_ptr<LongTermMemory> ltm) {
  PLACEDB_RETURN_IF_ERROR(ValidateLoopClosureConfig(config));
  if (word_count == 0) return Status::InvalidArgument("word_count must be positive");
  if (ltm == nullptr) ltm = std::make_shared<InMemoryLongTermMemory>();
  return std::unique_ptr<LoopClosureDetector>(
      new LoopClosureDetector(word_count, config, std::move(ltm)));
}

LoopClosureDetector::LoopClosureDetector(uint32_t word_count, const LoopClosureConfig& config,
                                         std::shared_ptr<LongTermMemory> ltm)
    : config_(config),
      word_count_(word_count),
      ltm_(std::move(ltm)),
      index_(word_count, config.likelihood_similarity == SimilarityMeasure::kWordOverlap
                             ? ScoringType::kDotProduct
                             : config.scoring),
      places_(1),
      tier_(1, uint8_t(MemoryTier::kShortTerm)),
      chain_(1, {kNoPlace, kNoPlace}),
      has_loops_(1, 0),
      posterior_(1, 0.0) {
  const int radius = std::max(config.transition_radius, 0);
  gaussian_.resize(size_t(radius) + 1);
  for (int d = 0; d <= radius; ++d) {
    gaussian_[size_t(d)] = std::exp(-double(d) * double(d) /
                                    (2.0 * config.transition_sigma * config.transition_sigma));
  }
}

const BowVector& LoopClosureDetector::IndexForm(const BowVector& bow) const {
  if (config_.likelihood_similarity != SimilarityMeasure::kWordOverlap) return bow;
  index_form_ = bow;
  for (auto& entry : index_form_) entry.weight = 1.0f;
  return index_form_;
}

double LoopClosureDetector::Similarity(SimilarityMeasure measure, const BowVector& a,
                                       const BowVector& b) const {
  if (measure == SimilarityMeasure::kScore) return Score(a, b, config_.scoring);
  size_t shared = 0;
  for (size_t i = 0, j = 0; i < a.size() && j < b.size();) {
    if (a[i].word < b[j].word) {
      ++i;
    } else if (b[j].word < a[i].word) {
      ++j;
    } else {
      ++shared;
      ++i;
      ++j;
    }
  }
  const size_t larger = std::max(a.size(), b.size());
  return larger == 0 ? 0.0 : double(shared) / double(larger);
}

void LoopClosureDetector::Neighbourhood(PlaceId from, int radius,
                                        std::vector<std::pair<PlaceId, int>>* out) const {
  out->clear();
  if (visit_mark_.size() < places_.size()) visit_mark_.resize(places_.size(), 0);
  if (++visit_generation_ == 0) {
    std::fill(visit_mark_.begin(), visit_mark_.end(), 0);
    visit_generation_ = 1;
  }
  out->push_back({from, 0});
  visit_mark_[from] = visit_generation_;
  for (size_t head = 0; head < out->size(); ++head) {
    // Not a structured binding: clang 14 cannot capture one in the lambda below.
    const PlaceId id = (*out)[head].first;
    const int d = (*out)[head].second;
    if (d >= radius) continue;
    auto visit = [&](PlaceId next) {
      if (next == kNoPlace || visit_mark_[next] == visit_generation_) return;
      visit_mark_[next] = visit_generation_;
      out->push_back({next, d + 1});
    };
    visit(chain_[id][0]);
    visit(chain_[id][1]);
    if (has_loops_[id]) {
      for (PlaceId next : places_[id].loops) visit(next);
    }
  }
}

void LoopClosureDetector::MoveToWorking(PlaceId id) {
  Place& place = places_[id];
  // The vector is normalised and in range (checked on entry), so Add cannot fail but on a bug.
  Status added = index_.Add(id, IndexForm(place.bow));
  (void)added;
  tier_[id] = uint8_t(MemoryTier::kWorking);
  place.wm_slot = wm_.size();
  wm_.push_back(id);
  transfer_order_.insert({place.weight, id});
  posterior_[id] = 0;
}

bool LoopClosureDetector::MoveToLongTerm(PlaceId id, Status* status) {
  Place& place = places_[id];
  Status stored = ltm_->Store(id, place.bow);
  if (!stored.ok()) {
    if (status->ok())
      *status = stored.WithContext("moving place " + std::to_string(id) + " to LTM");
    return false;
  }
  Status removed = index_.Remove(id, IndexForm(place.bow));
  (void)removed;
  transfer_order_.erase({place.weight, id});
  const PlaceId last = wm_.back();
  wm_[place.wm_slot] = last;
  places_[last].wm_slot = place.wm_slot;
  wm_.pop_back();
  BowVector().swap(place.bow);
  tier_[id] = uint8_t(MemoryTier::kLongTerm);
  posterior_[id] = 0;
  ++long_term_;
  ++transferred_;
  return true;
}

bool LoopClosureDetector::Retrieve(PlaceId id, Status* status) {
  auto bow = ltm_->Fetch(id);
  if (!bow.ok()) {
    if (status->ok()) *status = bow.status().WithContext("retrieving place " + std::to_string(id));
    return false;
  }
  places_[id].bow = std::move(*bow);
  ltm_->Release(id);
  --long_term_;
  ++retrieved_;
  MoveToWorking(id);
  return true;
}

Status LoopClosureDetector::CheckBow(const BowVector& input) const {
  for (size_t i = 0; i < input.size(); ++i) {
    if (input[i].word >= word_count_) {
      return Status::InvalidArgument(
          "bow[" + std::to_string(i) + "].word = " + std::to_string(input[i].word) +
          " is outside the " + std::to_string(word_count_) + "-word vocabulary");
    }
    if (i > 0 && input[i].word <= input[i - 1].word) {
      return Status::InvalidArgument("bow must be sorted by word without duplicates (entry " +
                                     std::to_string(i) + ")");
    }
    if (!std::isfinite(input[i].weight) || input[i].weight <= 0) {
      return Status::InvalidArgument("bow[" + std::to_string(i) + "].weight must be positive");
    }
  }
  return Status::Ok();
}

PlaceId LoopClosureDetector::AddPlace(BowVector bow, uint64_t frame_tag) {
  const PlaceId id = PlaceId(places_.size());
  Place place;
  place.bow = std::move(bow);
  place.frames.push_back(frame_tag);
  // Linked to the newest place (the previous frame's), whatever its tier.
  const PlaceId before = places_.size() > 1 ? id - 1 : kNoPlace;
  if (before != kNoPlace) chain_[before][1] = id;
  places_.push_back(std::move(place));
  tier_.push_back(uint8_t(MemoryTier::kShortTerm));
  chain_.push_back({before, kNoPlace});
  has_loops_.push_back(0);
  posterior_.push_back(0.0);
  stm_.push_back(id);
  while (int(stm_.size()) > config_.short_term_memory) {
    const PlaceId oldest = stm_.front();
    stm_.erase(stm_.begin());
    MoveToWorking(oldest);
  }
  return id;
}

void LoopClosureDetector::TransferExcess(size_t excess,
                                         const std::function<bool(PlaceId)>& is_protected,
                                         std::vector<PlaceId>* transferred, Status* status) {
  std::vector<PlaceId> chosen;
  for (auto it = transfer_order_.begin(); it != transfer_order_.end() && chosen.size() < excess;
       ++it) {
    if (!is_protected(it->second)) chosen.push_back(it->second);
  }
  for (PlaceId id : chosen) {
    if (MoveToLongTerm(id, status) && transferred) transferred->push_back(id);
  }
}

Result<PlaceId> LoopClosureDetector::Replay(const BowVector& input, uint64_t frame_tag) {
  PLACEDB_RETURN_IF_ERROR(CheckBow(input));
  if (input.empty()) return Status::InvalidArgument("cannot replay an empty BoW vector");
  BowVector bow = input;
  NormalizeForScoring(&bow, config_.scoring);
  const PlaceId id = AddPlace(std::move(bow), frame_tag);
  ++frames_;
  if (config_.max_working_memory > 0 && wm_.size() > config_.max_working_memory) {
    Status status;
    TransferExcess(
        wm_.size() - config_.max_working_memory, [](PlaceId) { return false; }, nullptr, &status);
    PLACEDB_RETURN_IF_ERROR(status);
  }
  return id;
}

Result<LoopClosureUpdate> LoopClosureDetector::Update(const BowVector& input, uint64_t frame_tag) {
  Stopwatch total;
  LoopClosureUpdate update;
  PLACEDB_RETURN_IF_ERROR(CheckBow(input));
  ++frames_;
  if (input.empty()) {
    update.skipped = true;
    update.total_ms = total.ElapsedMs();
    return update;
  }
  BowVector bow = input;
  NormalizeForScoring(&bow, config_.scoring);

  Stopwatch lap;
  update.place = RehearseOrAddPlace(std::move(bow), frame_tag, &update.merged);
  update.memory_ms += lap.Lap();

  update.candidates = wm_.size();
  std::vector<ScoredPlace> scored = SearchWorkingMemory(places_[update.place].bow);
  update.search_ms = lap.Lap();

  FilterStep(&scored, &update);
  update.filter_ms = lap.Lap();

  RetrieveNeighbours(&update);
  TransferOverBounds(total, &update);
  update.memory_ms += lap.Lap();
  update.total_ms = total.ElapsedMs();
  return update;
}

PlaceId LoopClosureDetector::RehearseOrAddPlace(BowVector bow, uint64_t frame_tag, bool* merged) {
  const PlaceId previous = stm_.empty() ? kNoPlace : stm_.back();
  if (previous != kNoPlace && config_.rehearsal_threshold <= 1.0 &&
      Similarity(config_.rehearsal_similarity, bow, places_[previous].bow) >=
          config_.rehearsal_threshold) {
    Place& place = places_[previous];
    place.weight += 1;
    place.bow = std::move(bow);
    place.frames.push_back(frame_tag);
    *merged = true;
    ++merged_;
    return previous;
  }
  return AddPlace(std::move(bow), frame_tag);
}

std::vector<ScoredPlace> LoopClosureDetector::SearchWorkingMemory(const BowVector& bow) const {
  const size_t n = wm_.size();
  std::vector<ScoredPlace> scored;
  if (n > 0) {
    scored = index_.Query(IndexForm(bow), n);
    if (config_.likelihood_similarity == SimilarityMeasure::kWordOverlap) {
      // Shared-word counts -> shared / words of the larger vector.
      const double words = double(bow.size());
      for (auto& s : scored) {
        s.score /= std::max(words, double(places_[s.place].bow.size()));
      }
    }
  }
  return scored;
}

void LoopClosureDetector::FilterStep(std::vector<ScoredPlace>* scored, LoopClosureUpdate* update) {
  const size_t n = wm_.size();
  if (n == 0) {
    no_loop_ = 1.0;
    update->no_loop_posterior = 1.0;
    return;
  }
  // Dense by place id but only WM entries are touched: the cost follows |WM|, not the map.
  thread_local std::vector<double> place_likelihood;
  thread_local std::vector<double> score_of;
  thread_local std::vector<double> predicted;
  const double no_loop_likelihood = Observe(scored, &place_likelihood, &score_of);
  const double predicted_no_loop = Predict(&predicted);
  UpdatePosterior(place_likelihood, no_loop_likelihood, predicted, predicted_no_loop);
  update->no_loop_posterior = no_loop_;

  const PlaceId best = BestHypothesis();
  update->best = best;
  update->best_score = score_of[best];
  const double hypothesis = HypothesisPosterior(best);
  update->best_posterior = hypothesis;
  // Only a place this very observation favours over "no loop" (its likelihood above the
  // no-loop likelihood, hence also > 1) can be accepted: without evidence the transition model
  // alone drifts belief onto places (half the mass at equilibrium when every likelihood is 1),
  // which with few WM places exceeds T_loop on its own.
  update->best_likelihood = place_likelihood[best];
  update->no_loop_likelihood = no_loop_likelihood;
  if (hypothesis > config_.loop_threshold && place_likelihood[best] > 1.0 &&
      place_likelihood[best] > no_loop_likelihood && n >= size_t(config_.min_candidates) &&
      score_of[best] >= config_.min_similarity_excess) {
    update->loop = best;
    AddLoopLink(update->place, best);
  }
}

double LoopClosureDetector::Observe(std::vector<ScoredPlace>* scored,
                                    std::vector<double>* place_likelihood,
                                    std::vector<double>* score_of) const {
  const size_t n = wm_.size();
  // With a baseline, the WM's typical similarity (the median, places that share no word
  // counting 0) is first subtracted: a fixed vocabulary gives every frame of one building a
  // common floor of shared words, which the mu/sigma normalisation would otherwise read as "no
  // place stands out".
  double baseline = 0;
  if (config_.likelihood_baseline == LikelihoodBaseline::kMedian && scored->size() * 2 > n) {
    thread_local std::vector<double> values;
    values.clear();
    for (const auto& s : *scored) values.push_back(s.score);
    values.resize(n, 0.0);  // untouched places: 0
    std::nth_element(values.begin(), values.begin() + std::ptrdiff_t(n / 2), values.end());
    baseline = values[n / 2];
  }
  for (auto& s : *scored) s.score = std::max(0.0, s.score - baseline);
  double sum = 0, sum_sq = 0;
  for (const auto& s : *scored) {
    sum += s.score;
    sum_sq += s.score * s.score;
  }
  const double mean = sum / double(n);
  const double sigma = std::sqrt(std::max(0.0, sum_sq / double(n) - mean * mean));
  const double no_loop_likelihood = sigma > 1e-12 && mean > 0 ? mean / sigma + 1.0 : 1.0;
  place_likelihood->resize(places_.size());
  score_of->resize(places_.size());
  for (PlaceId i : wm_) {
    (*place_likelihood)[i] = 1.0;
    (*score_of)[i] = 0.0;
  }
  for (const auto& s : *scored) {
    (*score_of)[s.place] = s.score;
    if (mean > 0 && s.score >= mean + sigma)
      (*place_likelihood)[s.place] = (s.score - sigma) / mean;
  }
  return no_loop_likelihood;
}

double LoopClosureDetector::Predict(std::vector<double>* predicted) const {
  const size_t n = wm_.size();
  predicted->resize(places_.size());
  double places_mass = 0;
  for (PlaceId j : wm_) places_mass += posterior_[j];
  const double uniform = (1.0 - config_.no_loop_stay) * no_loop_ / double(n);
  for (PlaceId i : wm_) (*predicted)[i] = uniform;
  double predicted_no_loop =
      config_.no_loop_stay * no_loop_ + config_.loop_to_no_loop * places_mass;
  std::vector<std::pair<PlaceId, int>> hood;
  for (PlaceId j : wm_) {
    const double pj = posterior_[j];
    if (pj <= 0) continue;
    // The Gaussian is normalised over the WM and LTM neighbours; the LTM share goes to "no
    // loop" (the robot may be at a place WM no longer holds). Renormalising over the WM
    // neighbours alone would let a place whose neighbours were transferred keep all its belief
    // and hoard it frame after frame. STM neighbours (the newest places, reached through the
    // previous place or a fresh loop link) are no hypotheses and are left out.
    Neighbourhood(j, config_.transition_radius, &hood);
    double norm = 0;
    for (const auto& [i, d] : hood) {
      if (tier(i) != MemoryTier::kShortTerm) norm += gaussian_[size_t(d)];
    }
    const double spread = pj * (1.0 - config_.loop_to_no_loop) / norm;
    for (const auto& [i, d] : hood) {
      if (tier(i) == MemoryTier::kWorking) {
        (*predicted)[i] += spread * gaussian_[size_t(d)];
      } else if (tier(i) == MemoryTier::kLongTerm) {
        predicted_no_loop += spread * gaussian_[size_t(d)];
      }
    }
  }
  return predicted_no_loop;
}

void LoopClosureDetector::UpdatePosterior(const std::vector<double>& place_likelihood,
                                          double no_loop_likelihood,
                                          const std::vector<double>& predicted,
                                          double predicted_no_loop) {
  double total_mass = no_loop_likelihood * predicted_no_loop;
  for (PlaceId i : wm_) {
    posterior_[i] = place_likelihood[i] * predicted[i];
    total_mass += posterior_[i];
  }
  if (total_mass > 0) {
    no_loop_ = no_loop_likelihood * predicted_no_loop / total_mass;
    for (PlaceId i : wm_) posterior_[i] /= total_mass;
  } else {
    no_loop_ = 1.0;
    for (PlaceId i : wm_) posterior_[i] = 0;
  }
}

PlaceId LoopClosureDetector::BestHypothesis() const {
  PlaceId best = kNoPlace;
  for (PlaceId i : wm_) {
    if (best == kNoPlace || posterior_[i] > posterior_[best] ||
        (posterior_[i] == posterior_[best] && i < best)) {
      best = i;
    }
  }
  return best;
}

double LoopClosureDetector::HypothesisPosterior(PlaceId best) const {
  double hypothesis = posterior_[best];
  if (config_.hypothesis_radius > 0) {
    std::vector<std::pair<PlaceId, int>> hood;
    Neighbourhood(best, config_.hypothesis_radius, &hood);
    hypothesis = 0;
    for (const auto& [i, d] : hood) {
      if (tier(i) == MemoryTier::kWorking) hypothesis += posterior_[i];
    }
  }
  return hypothesis;
}

void LoopClosureDetector::AddLoopLink(PlaceId place, PlaceId loop) {
  Place& here = places_[place];
  if (std::find(here.loops.begin(), here.loops.end(), loop) == here.loops.end()) {
    here.loops.push_back(loop);
    places_[loop].loops.push_back(place);
    has_loops_[place] = 1;
    has_loops_[loop] = 1;
  }
  ++loops_;
}

void LoopClosureDetector::RetrieveNeighbours(LoopClosureUpdate* update) {
  if (update->best == kNoPlace || config_.max_retrieved <= 0 || config_.retrieval_radius <= 0 ||
      long_term_ == 0) {
    return;
  }
  std::vector<std::pair<PlaceId, int>> hood;
  Neighbourhood(update->best, config_.retrieval_radius, &hood);
  std::stable_sort(hood.begin(), hood.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second < b.second : a.first < b.first;
  });
  for (const auto& [id, d] : hood) {
    if (int(update->retrieved.size()) >= config_.max_retrieved) break;
    if (tier(id) != MemoryTier::kLongTerm) continue;
    if (Retrieve(id, &update->memory_status)) update->retrieved.push_back(id);
  }
}

void LoopClosureDetector::TransferOverBounds(const Stopwatch& total, LoopClosureUpdate* update) {
  size_t excess = 0;
  if (config_.max_working_memory > 0 && wm_.size() > config_.max_working_memory) {
    excess = wm_.size() - config_.max_working_memory;
  }
  const double elapsed = total.ElapsedMs();
  if (config_.time_budget_ms > 0 && elapsed > config_.time_budget_ms && !wm_.empty()) {
    const double over = (elapsed - config_.time_budget_ms) / elapsed;
    excess = std::max(excess, size_t(std::ceil(double(wm_.size()) * over)));
  }
  if (excess > 0) {
    auto is_protected = [&](PlaceId id) {
      return id == update->best || (update->loop && id == *update->loop) ||
             std::find(update->retrieved.begin(), update->retrieved.end(), id) !=
                 update->retrieved.end();
    };
    TransferExcess(excess, is_protected, &update->transferred, &update->memory_status);
  }
}

Status LoopClosureDetector::RejectLoop(PlaceId place, PlaceId loop) {
  if (place == kNoPlace || loop == kNoPlace || place >= places_.size() || loop >= places_.size()) {
    return Status::NotFound("no loop link " + std::to_string(place) + " -> " +
                            std::to_string(loop));
  }
  auto& from = places_[place].loops;
  auto it = std::find(from.begin(), from.end(), loop);
  if (it == from.end()) {
    return Status::NotFound("no loop link " + std::to_string(place) + " -> " +
                            std::to_string(loop));
  }
  from.erase(it);
  auto& to = places_[loop].loops;
  to.erase(std::remove(to.begin(), to.end(), place), to.end());
  has_loops_[place] = !from.empty();
  has_loops_[loop] = !to.empty();
  --loops_;
  ++rejected_;
  return Status::Ok();
}

std::optional<PlaceInfo> LoopClosureDetector::Get(PlaceId id) const {
  if (id == kNoPlace || id >= places_.size()) return std::nullopt;
  const Place& place = places_[id];
  PlaceInfo info;
  info.id = id;
  info.tier = tier(id);
  info.weight = place.weight;
  info.frames = place.frames;
  for (PlaceId n : chain_[id]) {
    if (n != kNoPlace) info.neighbours.push_back(n);
  }
  info.loops = place.loops;
  return info;
}

double LoopClosureDetector::Posterior(PlaceId id) const {
  if (id == kNoPlace || id >= places_.size()) return 0;
  return tier(id) == MemoryTier::kWorking ? posterior_[id] : 0;
}

LoopClosureStats LoopClosureDetector::Stats() const {
  LoopClosureStats stats;
  stats.places = places_.size() - 1;
  stats.short_term = stm_.size();
  stats.working = wm_.size();
  stats.long_term = long_term_;
  stats.frames = frames_;
  stats.merged = merged_;
  stats.loops = loops_;
  stats.rejected = rejected_;
  stats.retrieved = retrieved_;
  stats.transferred = transferred_;
  stats.index_bytes = index_.MemoryBytes();
  return stats;
}

}  // namespace placedb
