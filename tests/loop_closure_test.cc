// Bayesian loop-closure detection with bounded working memory (core/search/loop_closure.h).
//
// Synthetic BoW streams check each rule (rehearsal, STM, the filter, transfer and retrieval);
// then the RTAB-Map loop (../shared/data/rtabmap-loop, frames 1..84 in order as one stream, the
// loop wrapping at 81-84 -> 1-5) with SIFT (float vocabulary trained on Debian's sample images
// only) and with ORB (the default binary vocabulary): no accepted loop may contradict
// ground_truth.bmp, and recall is printed. PLACEDB_LC_TRACE=1 prints every update.
#include "core/search/loop_closure.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <vector>

#include "core/features/orb_features.h"
#include "core/features/sift_features.h"
#include "core/search/scoring.h"
#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace placedb {
namespace {

constexpr uint32_t kWords = 100000;

// A synthetic "place appearance": 150 distinctive words drawn from a per-place RNG, of which
// neighbouring places share a third (the view overlaps, as consecutive frames of a route do),
// plus 40 words from a pool of 2000 frequent ones that every place draws from (floors, walls,
// texture common to a building): unrelated places share a few words, as real frames do.
BowVector PlaceBow(uint32_t place, uint32_t salt = 0, double keep = 1.0) {
  std::map<WordId, float> words;
  auto draw = [&](uint32_t seed, int count, WordId first, WordId last) {
    std::mt19937 rng(seed * 7919u + 13u);
    std::uniform_int_distribution<WordId> word(first, last);
    for (int i = 0; i < count; ++i) words[word(rng)] += 1.0f;
  };
  draw(place, 100, 2000, kWords - 1);
  draw(place + 1000003u, 25, 2000, kWords - 1);  // shared with place + 1
  if (place > 0) draw(place - 1 + 1000003u, 25, 2000, kWords - 1);
  draw(place + 5000011u + salt * 7u, 40, 0, 1999);  // frequent words, different each visit
  // Revisits: drop a fraction of the words and add noise words.
  std::mt19937 noise(salt * 104729u + place);
  std::uniform_real_distribution<double> u(0, 1);
  std::uniform_int_distribution<WordId> word(0, kWords - 1);
  BowVector bow;
  for (const auto& [w, v] : words) {
    if (u(noise) < keep) bow.push_back({w, v});
  }
  if (keep < 1.0) {
    for (int i = 0; i < int(150 * (1 - keep)); ++i) {
      const WordId w = word(noise);
      auto it = std::lower_bound(bow.begin(), bow.end(), w,
                                 [](const BowEntry& e, WordId x) { return e.word < x; });
      if (it == bow.end() || it->word != w) bow.insert(it, {w, 1.0f});
    }
  }
  return bow;
}

std::unique_ptr<LoopClosureDetector> MakeDetector(const LoopClosureConfig& config,
                                                  uint32_t words = kWords) {
  auto created = LoopClosureDetector::Create(words, config);
  EXPECT_TRUE(created.ok()) << created.status().ToString();
  return created.ok() ? std::move(*created) : nullptr;
}

// ---- Rules on synthetic streams ------------------------------------------------------------

TEST(LoopClosure, ConfigAndInputAreValidated) {
  EXPECT_TRUE(ValidateLoopClosureConfig(LoopClosureConfig{}).ok());
  auto bad = [](auto edit) {
    LoopClosureConfig c;
    edit(c);
    return LoopClosureDetector::Create(kWords, c).status().code();
  };
  EXPECT_EQ(bad([](auto& c) { c.loop_threshold = 1.5; }), StatusCode::kInvalidArgument);
  EXPECT_EQ(bad([](auto& c) { c.short_term_memory = -1; }), StatusCode::kInvalidArgument);
  EXPECT_EQ(bad([](auto& c) { c.transition_sigma = 0; }), StatusCode::kInvalidArgument);
  EXPECT_EQ(bad([](auto& c) { c.scoring = ScoringType::kDotProduct; }),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(LoopClosureDetector::Create(0, LoopClosureConfig{}).status().code(),
            StatusCode::kInvalidArgument);

  auto detector = MakeDetector(LoopClosureConfig{}, 100);
  ASSERT_NE(detector, nullptr);
  EXPECT_EQ(detector->Update({{5, 1.0f}, {100, 1.0f}}, 0).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(detector->Update({{5, 1.0f}, {3, 1.0f}}, 0).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(detector->Update({{5, -1.0f}}, 0).status().code(), StatusCode::kInvalidArgument);
  auto empty = detector->Update({}, 0);
  ASSERT_TRUE(empty.ok());
  EXPECT_TRUE(empty->skipped);
  EXPECT_EQ(detector->Stats().places, 0u);
}

TEST(LoopClosure, RehearsalMergesNearIdenticalConsecutiveFrames) {
  auto detector = MakeDetector(LoopClosureConfig{});
  ASSERT_NE(detector, nullptr);
  auto a = detector->Update(PlaceBow(1), 10);
  auto b = detector->Update(PlaceBow(1, 1, 0.9), 11);  // 90 % of the words: merged
  auto c = detector->Update(PlaceBow(50), 12);         // another place: new
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  EXPECT_FALSE(a->merged);
  EXPECT_TRUE(b->merged);
  EXPECT_EQ(b->place, a->place);
  EXPECT_FALSE(c->merged);
  EXPECT_NE(c->place, a->place);
  const auto info = detector->Get(a->place);
  ASSERT_TRUE(info.has_value());
  EXPECT_EQ(info->weight, 1);
  EXPECT_EQ(info->frames, (std::vector<uint64_t>{10, 11}));
  EXPECT_EQ(info->neighbours, (std::vector<PlaceId>{c->place}));
  EXPECT_EQ(info->tier, MemoryTier::kShortTerm);
  EXPECT_EQ(detector->Stats().merged, 1u);

  LoopClosureConfig off;
  off.rehearsal_threshold = 2.0;  // disabled
  auto no_rehearsal = MakeDetector(off);
  ASSERT_TRUE(no_rehearsal->Update(PlaceBow(1), 0).ok());
  EXPECT_FALSE(no_rehearsal->Update(PlaceBow(1), 1)->merged);
}

TEST(LoopClosure, ShortTermMemoryPlacesAreNeverCandidates) {
  LoopClosureConfig config;
  config.short_term_memory = 5;
  config.rehearsal_threshold = 2.0;
  auto detector = MakeDetector(config);
  ASSERT_NE(detector, nullptr);
  for (uint32_t p = 0; p < 5; ++p) ASSERT_TRUE(detector->Update(PlaceBow(p * 10), p).ok());
  // Place 0 is still in STM: seeing it again cannot close a loop, there are no candidates.
  auto again = detector->Update(PlaceBow(0, 1, 0.8), 5);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->candidates, 1u);  // place 1 (frame 0) just left STM
  EXPECT_EQ(detector->Stats().short_term, 5u);
  EXPECT_EQ(detector->Stats().working, 1u);
}

TEST(LoopClosure, RevisitedRouteClosesLoopsOnTheRightPlaces) {
  LoopClosureConfig config;
  config.short_term_memory = 10;
  auto detector = MakeDetector(config);
  ASSERT_NE(detector, nullptr);
  // A route of 60 places, then the first 25 again with 30 % of the words changed.
  std::vector<PlaceId> place_of(60);
  for (uint32_t p = 0; p < 60; ++p) {
    auto u = detector->Update(PlaceBow(p), p);
    ASSERT_TRUE(u.ok());
    ASSERT_FALSE(u->merged);
    EXPECT_FALSE(u->loop.has_value())
        << "first pass, place " << p << " -> place " << u->best << " s=" << u->best_score
        << " L=" << u->best_likelihood << " L(no loop)=" << u->no_loop_likelihood
        << " p=" << u->best_posterior << " candidates " << u->candidates;
    place_of[p] = u->place;
  }
  int loops = 0, wrong = 0, first_loop = -1;
  for (uint32_t p = 0; p < 25; ++p) {
    auto u = detector->Update(PlaceBow(p, 7, 0.7), 100 + p);
    ASSERT_TRUE(u.ok());
    if (u->loop) {
      ++loops;
      if (first_loop < 0) first_loop = int(p);
      // The right place or an immediate neighbour.
      const PlaceId expected = place_of[p];
      if (*u->loop + 1 < expected || *u->loop > expected + 1) ++wrong;
    }
  }
  std::printf("synthetic revisit: %d of 25 frames closed a loop (first at revisit %d), %d wrong\n",
              loops, first_loop, wrong);
  EXPECT_EQ(wrong, 0);
  EXPECT_GE(loops, 20);
  EXPECT_LE(first_loop, 3);
}

TEST(LoopClosure, WorkingMemoryBoundKeepsSearchFlatAndRetrievesNeighbours) {
  LoopClosureConfig config;
  config.short_term_memory = 10;
  config.max_working_memory = 40;
  auto detector = MakeDetector(config);
  ASSERT_NE(detector, nullptr);
  // Place 100 is rehearsed five times (the robot stayed there): weight 5 keeps it in WM.
  constexpr uint32_t kHeavy = 100;
  constexpr uint32_t kPlaces = 3000;
  std::vector<PlaceId> place_of(kPlaces);
  std::vector<double> bucket_ms;
  double sum = 0;
  int in_bucket = 0;
  uint64_t frame = 0;
  std::printf("%8s %8s %8s %10s\n", "places", "WM", "LTM", "update_ms");
  for (uint32_t p = 0; p < kPlaces; ++p) {
    const int repeats = p == kHeavy ? 6 : 1;
    for (int r = 0; r < repeats; ++r) {
      auto u = detector->Update(PlaceBow(p, r, r == 0 ? 1.0 : 0.9), frame++);
      ASSERT_TRUE(u.ok());
      place_of[p] = u->place;
      EXPECT_LE(detector->Stats().working, config.max_working_memory);
      sum += u->total_ms;
      ++in_bucket;
    }
    if ((p + 1) % 500 == 0) {
      const auto stats = detector->Stats();
      bucket_ms.push_back(sum / in_bucket);
      std::printf("%8zu %8zu %8zu %10.4f\n", stats.places, stats.working, stats.long_term,
                  sum / in_bucket);
      sum = 0;
      in_bucket = 0;
    }
  }
  const auto heavy = detector->Get(place_of[kHeavy]);
  ASSERT_TRUE(heavy.has_value());
  EXPECT_EQ(heavy->weight, 5);
  EXPECT_EQ(heavy->tier, MemoryTier::kWorking);
  EXPECT_EQ(detector->Get(place_of[kHeavy + 1])->tier, MemoryTier::kLongTerm);
  EXPECT_EQ(detector->Get(place_of[kHeavy - 1])->tier, MemoryTier::kLongTerm);
  EXPECT_GT(detector->Stats().long_term, kPlaces - 100);

  // Back at the heavy place: it is the best hypothesis, and its LTM neighbours come back.
  auto back = detector->Update(PlaceBow(kHeavy, 9, 0.8), frame++);
  ASSERT_TRUE(back.ok());
  EXPECT_EQ(back->best, place_of[kHeavy]);
  std::set<PlaceId> retrieved(back->retrieved.begin(), back->retrieved.end());
  EXPECT_TRUE(retrieved.count(place_of[kHeavy + 1])) << "next place not retrieved";
  EXPECT_TRUE(retrieved.count(place_of[kHeavy - 1])) << "previous place not retrieved";
  EXPECT_EQ(detector->Get(place_of[kHeavy + 1])->tier, MemoryTier::kWorking);
  // Walking on along the old route: each step matches a retrieved place and retrieves the next.
  std::set<PlaceId> loops_to;
  if (back->loop) loops_to.insert(*back->loop);
  for (uint32_t p = kHeavy + 1; p <= kHeavy + 6; ++p) {
    auto u = detector->Update(PlaceBow(p, 9, 0.8), frame++);
    ASSERT_TRUE(u.ok());
    EXPECT_EQ(u->best, place_of[p]) << "step " << p;
    if (u->loop) loops_to.insert(*u->loop);
  }
  std::printf(
      "retrieved around the heavy place: %zu places; loops closed while walking the old "
      "route: %zu\n",
      back->retrieved.size(), loops_to.size());
  EXPECT_GE(loops_to.size(), 4u);
  for (PlaceId id : loops_to) {
    EXPECT_GE(id, place_of[kHeavy]);
    EXPECT_LE(id, place_of[kHeavy + 6]);
  }
  // Flat: no time assertions (shared machines), but the figures above show it.
  EXPECT_EQ(bucket_ms.size(), kPlaces / 500);
}

// A detector rebuilt from stored places (a reopened map) closes loops on them like the one that
// saw them live.
TEST(LoopClosure, ReplayedPlacesAreLoopCandidates) {
  LoopClosureConfig config;
  config.short_term_memory = 5;
  config.max_working_memory = 30;
  auto live = MakeDetector(config);
  auto rebuilt = MakeDetector(config);
  ASSERT_TRUE(live && rebuilt);
  for (uint32_t p = 0; p < 60; ++p) {
    ASSERT_TRUE(live->Update(PlaceBow(p), p).ok());
    auto replayed = rebuilt->Replay(PlaceBow(p), p);
    ASSERT_TRUE(replayed.ok());
    EXPECT_EQ(*replayed, PlaceId(p + 1));
  }
  const auto stats = rebuilt->Stats();
  EXPECT_EQ(stats.places, 60u);
  EXPECT_EQ(stats.short_term, 5u);
  EXPECT_EQ(stats.working, 30u);  // the bound applies while replaying: the oldest went to LTM
  EXPECT_EQ(stats.long_term, 25u);
  EXPECT_EQ(stats.loops, 0u);
  EXPECT_EQ(rebuilt->Get(2)->neighbours, (std::vector<PlaceId>{1, 3}));
  // Revisit places 40-47 (in WM in both): both close loops onto them.
  for (auto* detector : {live.get(), rebuilt.get()}) {
    int loops = 0;
    for (uint32_t p = 40; p < 48; ++p) {
      auto u = detector->Update(PlaceBow(p, 3, 0.8), 1000 + p);
      ASSERT_TRUE(u.ok());
      if (u->loop) {
        ++loops;
        EXPECT_GE(*u->loop, PlaceId(40));
        EXPECT_LE(*u->loop, PlaceId(49));
      }
    }
    EXPECT_GE(loops, 4);
  }
  EXPECT_EQ(rebuilt->Replay(BowVector{}, 0).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(rebuilt->Replay(BowVector{{kWords, 1.0f}}, 0).status().code(),
            StatusCode::kInvalidArgument);
}

TEST(LoopClosure, RejectedLoopLosesItsLink) {
  auto detector = MakeDetector(LoopClosureConfig{});
  ASSERT_TRUE(detector);
  for (uint32_t p = 0; p < 60; ++p) ASSERT_TRUE(detector->Update(PlaceBow(p), p).ok());
  std::optional<std::pair<PlaceId, PlaceId>> accepted;
  for (uint32_t p = 10; p < 20 && !accepted; ++p) {
    auto u = detector->Update(PlaceBow(p, 5, 0.8), 100 + p);
    ASSERT_TRUE(u.ok());
    if (u->loop) accepted = std::make_pair(u->place, *u->loop);
  }
  ASSERT_TRUE(accepted.has_value()) << "no loop accepted on the revisit";
  const auto [place, loop] = *accepted;
  const uint64_t loops = detector->Stats().loops;
  ASSERT_EQ(detector->Get(place)->loops, std::vector<PlaceId>{loop});
  EXPECT_TRUE(detector->RejectLoop(place, loop).ok());
  EXPECT_TRUE(detector->Get(place)->loops.empty());
  EXPECT_TRUE(detector->Get(loop)->loops.empty());
  EXPECT_EQ(detector->Stats().loops, loops - 1);
  EXPECT_EQ(detector->Stats().rejected, 1u);
  EXPECT_EQ(detector->RejectLoop(place, loop).code(), StatusCode::kNotFound);
  EXPECT_EQ(detector->RejectLoop(place, 100000).code(), StatusCode::kNotFound);
}

TEST(LoopClosure, TimeBudgetTransfersPlaces) {
  LoopClosureConfig config;
  config.short_term_memory = 5;
  config.time_budget_ms = 1e-6;  // every update is over budget
  auto detector = MakeDetector(config);
  ASSERT_NE(detector, nullptr);
  size_t transferred = 0;
  for (uint32_t p = 0; p < 50; ++p) {
    auto u = detector->Update(PlaceBow(p), p);
    ASSERT_TRUE(u.ok());
    transferred += u->transferred.size();
  }
  EXPECT_GT(transferred, 30u);
  EXPECT_LE(detector->Stats().working, 5u);
}

// A long-term memory that refuses to store: places stay in WM and the update says why.
class RefusingMemory final : public LongTermMemory {
 public:
  Status Store(PlaceId, const BowVector&) override { return Status::IoError("disk full"); }
  Result<BowVector> Fetch(PlaceId place) override {
    return Status::NotFound("no place " + std::to_string(place));
  }
  void Release(PlaceId) override {}
};

TEST(LoopClosure, LongTermMemoryErrorsKeepPlacesInWorkingMemory) {
  LoopClosureConfig config;
  config.short_term_memory = 2;
  config.max_working_memory = 3;
  auto created = LoopClosureDetector::Create(kWords, config, std::make_shared<RefusingMemory>());
  ASSERT_TRUE(created.ok());
  auto& detector = *created;
  Status last;
  for (uint32_t p = 0; p < 10; ++p) {
    auto u = detector->Update(PlaceBow(p), p);
    ASSERT_TRUE(u.ok());
    if (!u->memory_status.ok()) last = u->memory_status;
  }
  EXPECT_EQ(last.code(), StatusCode::kIoError);
  EXPECT_EQ(detector->Stats().working, 8u);
  EXPECT_EQ(detector->Stats().long_term, 0u);
}

// ---- The RTAB-Map loop -----------------------------------------------------------------------

struct LoopRun {
  int accepted = 0;
  int false_positives = 0;
  int positives = 0;       // frames with a ground-truth match among non-STM places
  int true_positives = 0;  // of those, frames that accepted a correct loop
  double mean_update_ms = 0;
  size_t places = 0, merged = 0, retrieved = 0, transferred = 0;
};

// Frames 1..84 in order; `bows[i]` is frame i+1's BoW vector.
LoopRun RunRtabmapLoop(const std::vector<BowVector>& bows, uint32_t words,
                       const LoopClosureConfig& config, const std::string& label) {
  LoopRun run;
  const cv::Mat truth = rgbd::RtabmapGroundTruth();
  EXPECT_EQ(truth.rows, 84);
  if (truth.rows != 84) return run;
  auto detector = MakeDetector(config, words);
  if (!detector) return run;
  double total_ms = 0;
  for (int t = 1; t <= int(bows.size()); ++t) {
    auto u = detector->Update(bows[size_t(t - 1)], uint64_t(t));
    EXPECT_TRUE(u.ok()) << u.status().ToString();
    if (!u.ok()) return run;
    total_ms += u->total_ms;
    if (std::getenv("PLACEDB_LC_TRACE") != nullptr) {
      // The best ground-truth place's similarity against the best other place's.
      const BowVector& q = bows[size_t(t - 1)];
      BowVector qn = q;
      NormalizeForScoring(&qn, config.scoring);
      double gt_best = 0, other_best = 0;
      int gt_frame = 0, other_frame = 0;
      for (int j = 1; j < t - 30; ++j) {
        BowVector c = bows[size_t(j - 1)];
        if (c.empty()) continue;
        NormalizeForScoring(&c, config.scoring);
        const double s = Score(qn, c, config.scoring);
        if (truth.at<uint8_t>(t - 1, j - 1) == 255) {
          if (s > gt_best) gt_best = s, gt_frame = j;
        } else if (s > other_best) {
          other_best = s, other_frame = j;
        }
      }
      std::printf(
          "[%s] t=%2d words=%4zu cand=%3zu best=%3u s=%.3f L=%.2f p=%.3f noloop=%.3f | "
          "gt f%2d %.3f other f%2d %.3f\n",
          label.c_str(), t, q.size(), u->candidates, u->best, u->best_score, u->best_likelihood,
          u->best_posterior, u->no_loop_posterior, gt_frame, gt_best, other_frame, other_best);
    }
    // Could this frame close a loop? Some place outside STM shows a ground-truth match.
    bool positive = false;
    for (PlaceId id = 1; id <= detector->Stats().places; ++id) {
      const auto info = detector->Get(id);
      if (!info || info->tier == MemoryTier::kShortTerm) continue;
      for (uint64_t f : info->frames) positive |= truth.at<uint8_t>(t - 1, int(f) - 1) == 255;
    }
    run.positives += positive;
    if (!u->loop) continue;
    ++run.accepted;
    const auto matched = detector->Get(*u->loop);
    // The matched place looks like its latest frame (rehearsal keeps the newest appearance).
    const int f = int(matched->frames.back());
    const bool correct = truth.at<uint8_t>(t - 1, f - 1) == 255;
    run.false_positives += !correct;
    run.true_positives += correct && positive;
    std::printf("[%s] frame %2d -> place %3u (frame %2d%s) p=%.3f s=%.3f %s\n", label.c_str(), t,
                *u->loop, f, matched->frames.size() > 1 ? ", merged" : "", u->best_posterior,
                u->best_score, correct ? "ok" : "FALSE POSITIVE");
  }
  const auto stats = detector->Stats();
  run.mean_update_ms = total_ms / double(bows.size());
  run.places = stats.places;
  run.merged = stats.merged;
  run.retrieved = stats.retrieved;
  run.transferred = stats.transferred;
  std::printf(
      "[%s] %zu frames -> %zu places (%zu merged by rehearsal); loops accepted %d, false "
      "positives %d, recall %d/%d = %.1f%%; mean update %.3f ms; WM->LTM %zu, LTM->WM "
      "%zu\n",
      label.c_str(), bows.size(), run.places, run.merged, run.accepted, run.false_positives,
      run.true_positives, run.positives, 100.0 * run.true_positives / std::max(1, run.positives),
      run.mean_update_ms, run.transferred, run.retrieved);
  return run;
}

const std::vector<BowVector>& SiftBows(uint32_t* words) {
  static uint32_t word_count = 0;
  static const std::vector<BowVector> bows = [] {
    std::vector<BowVector> out;
    auto vocabulary = rgbd::LoadOrTrainSiftVocabulary(rgbd::SiftVocabularyPath());
    EXPECT_TRUE(vocabulary.ok()) << vocabulary.status().ToString();
    if (!vocabulary.ok()) return out;
    word_count = (*vocabulary)->word_count();
    for (int t = 1; t <= 84; ++t) {
      cv::Mat image = cv::imread(rgbd::RtabmapFramePath(t), cv::IMREAD_GRAYSCALE);
      EXPECT_FALSE(image.empty()) << rgbd::RtabmapFramePath(t);
      auto features = ExtractSift(image, SiftConfig{});
      EXPECT_TRUE(features.ok());
      BowVector bow;
      (*vocabulary)->Transform(features->descriptors, &bow, nullptr, 0);
      out.push_back(std::move(bow));
    }
    return out;
  }();
  *words = word_count;
  return bows;
}

const std::vector<BowVector>& OrbBows(uint32_t* words) {
  static uint32_t word_count = 0;
  static const std::vector<BowVector> bows = [] {
    std::vector<BowVector> out;
    auto vocabulary = testing::DefaultVocabulary();
    if (!vocabulary) return out;
    word_count = vocabulary->word_count();
    for (int t = 1; t <= 84; ++t) {
      const FeatureSet features = testing::ExtractFile(rgbd::RtabmapFramePath(t), 1000);
      BowVector bow;
      vocabulary->Transform(features.descriptors, &bow, nullptr, 0);
      out.push_back(std::move(bow));
    }
    return out;
  }();
  *words = word_count;
  return bows;
}

#define REQUIRE_RTABMAP()                                                              \
  do {                                                                                 \
    if (!rgbd::HaveSharedData()) FAIL() << "missing " << rgbd::SharedDir() << "/data"; \
  } while (false)

TEST(RtabmapLoop, SiftNoFalsePositives) {
  REQUIRE_RTABMAP();
  uint32_t words = 0;
  const auto& bows = SiftBows(&words);
  ASSERT_EQ(bows.size(), 84u);
  const LoopRun run = RunRtabmapLoop(bows, words, LoopClosureConfig{}, "sift");
  EXPECT_EQ(run.false_positives, 0);
  EXPECT_GT(run.positives, 40);
  EXPECT_GE(2 * run.true_positives, run.positives) << "recall below 50 %";
}

TEST(RtabmapLoop, OrbNoFalsePositives) {
  REQUIRE_RTABMAP();
  uint32_t words = 0;
  const auto& bows = OrbBows(&words);
  ASSERT_EQ(bows.size(), 84u);
  const LoopRun run = RunRtabmapLoop(bows, words, LoopClosureConfig{}, "orb");
  EXPECT_EQ(run.false_positives, 0);
  EXPECT_GT(run.positives, 40);
  EXPECT_GE(2 * run.true_positives, run.positives) << "recall below 50 %";
}

TEST(RtabmapLoop, BoundedWorkingMemoryStillClosesTheLoop) {
  REQUIRE_RTABMAP();
  uint32_t words = 0;
  const auto& bows = SiftBows(&words);
  ASSERT_EQ(bows.size(), 84u);
  // Every place has weight ~0 here, so the oldest leave WM first: exactly the places the loop
  // returns to. Loops then come only through retrieval around the best hypothesis.
  for (size_t bound : {10, 20}) {
    LoopClosureConfig config;
    config.max_working_memory = bound;
    const LoopRun run = RunRtabmapLoop(bows, words, config, "sift-wm" + std::to_string(bound));
    EXPECT_EQ(run.false_positives, 0);
    EXPECT_GT(run.transferred, 0u);
  }
}

}  // namespace
}  // namespace placedb
