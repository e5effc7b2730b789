// Map-learned vocabularies (issue 29): what learning one and re-indexing a map with it cost, and
// what it does to query latency, each beside a baseline measured in the same run.
//
// Workload (stated on stdout too):
//  - real views: the RTAB-Map loop's frames (../shared/data/rtabmap-loop), ORB with 1000 features;
//  - a map of N places: place i is view (i mod views) with a random 90 % of its descriptors kept
//    and 4 random bits of each flipped (seeded by i: the same place every time it is made), as in
//    placedb-bench-core; places are made on the fly, never all held in memory;
//  - learning: every place offered to a VocabularyLearner (default options: at most 1M
//    descriptors sampled, the shape from the amount of data), then trained on 2 threads;
//  - re-indexing: every place transformed with the learned vocabulary and added to an inverted
//    index, on 2 threads (transform) + 1 (index), as a map switching vocabularies does in memory;
//    baseline: the same with the fixed (default) vocabulary, i.e. building the map's index;
//  - query: top-10 over the N places with each vocabulary, queries = 200 other noisy views;
//  - peak memory: the process's VmHWM after each step (it only grows: sizes run smallest first).
//
// Usage: placedb-bench-vocabulary-learning --vocabulary FILE [--places 10000,100000]
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <string>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/parallel.h"
#include "core/features/orb_features.h"
#include "core/search/place_index.h"
#include "core/vocabulary/vocabulary.h"
#include "core/vocabulary/vocabulary_learning.h"
#include "core/vocabulary/weighting.h"
#include "tools/shared_data.h"

namespace placedb {
namespace {

using bench::Median;
using bench::NowMs;
using bench::PeakRssMb;
using bench::Print;

// Place `id` of the synthetic map (see the workload above); `salt` makes queries differ.
FeatureSet MakePlace(const std::vector<FeatureSet>& views, uint64_t id, uint64_t salt = 0) {
  const FeatureSet& view = views[id % views.size()];
  std::mt19937_64 rng(id * 0x9E3779B97F4A7C15ull + salt);
  FeatureSet place;
  place.image_width = view.image_width;
  place.image_height = view.image_height;
  for (size_t i = 0; i < view.size(); ++i) {
    if (rng() % 10 == 0) continue;
    Descriptor256 d = view.descriptors[i];
    for (int flip = 0; flip < 4; ++flip) {
      const unsigned bit = unsigned(rng() % 256);
      d.words[bit / 64] ^= uint64_t(1) << (bit % 64);
    }
    place.keypoints.push_back(view.keypoints[i]);
    place.descriptors.push_back(d);
  }
  return place;
}

BowVector Transform(const Vocabulary& vocabulary, const FeatureSet& place) {
  BowVector bow;
  vocabulary.Transform(place.descriptors, &bow, nullptr, 0);
  NormalizeForScoring(&bow, ScoringType::kL1);
  return bow;
}

// Transforms every place with `vocabulary` (2 threads, in blocks) and indexes it; ms.
double BuildIndex(const Vocabulary& vocabulary, const std::vector<FeatureSet>& views, size_t places,
                  InvertedIndex* index) {
  const double start = NowMs();
  constexpr size_t kBlock = 4096;
  std::vector<BowVector> block;
  for (size_t first = 0; first < places; first += kBlock) {
    const size_t count = std::min(kBlock, places - first);
    block.assign(count, {});
    ParallelFor(count, 2, [&](size_t i, int) {
      block[i] = Transform(vocabulary, MakePlace(views, first + i + 1));
    });
    for (size_t i = 0; i < count; ++i) {
      const Status added = index->Add(PlaceId(first + i + 1), block[i]);
      if (!added.ok()) {
        std::fprintf(stderr, "index: %s\n", added.ToString().c_str());
        std::exit(1);
      }
    }
  }
  return NowMs() - start;
}

double QueryMs(const Vocabulary& vocabulary, const std::vector<FeatureSet>& views,
               const InvertedIndex& index, size_t places) {
  std::vector<double> ms;
  for (uint64_t q = 0; q < 200; ++q) {
    const BowVector bow = Transform(vocabulary, MakePlace(views, (q * 7919) % places + 1, 77));
    const double start = NowMs();
    const auto top = index.Query(bow, 10);
    ms.push_back(NowMs() - start);
    if (top.empty()) {
      std::fprintf(stderr, "a query found nothing\n");
      std::exit(1);
    }
  }
  return Median(ms);
}

int Main(int argc, char** argv) {
  std::string vocabulary_path;
  std::vector<size_t> sizes = {10000, 100000};
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--vocabulary" && i + 1 < argc) {
      vocabulary_path = argv[++i];
    } else if (arg == "--places" && i + 1 < argc) {
      sizes.clear();
      std::string list = argv[++i];
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = std::min(list.find(',', start), list.size());
        sizes.push_back(std::stoul(list.substr(start, comma - start)));
        start = comma + 1;
      }
    } else {
      std::fprintf(stderr, "usage: %s --vocabulary FILE [--places 10000,100000]\n", argv[0]);
      return 2;
    }
  }
  std::sort(sizes.begin(), sizes.end());
  auto fixed = Vocabulary::Load(vocabulary_path);
  if (!fixed.ok()) {
    std::fprintf(stderr, "%s\n", fixed.status().ToString().c_str());
    return 1;
  }
  OrbConfig orb;
  orb.max_features = 1000;
  std::vector<FeatureSet> views;
  for (int frame = 1; frame <= 84; ++frame) {
    const cv::Mat gray = cv::imread(data::RtabmapFramePath(frame), cv::IMREAD_GRAYSCALE);
    if (gray.empty()) continue;
    auto features = ExtractOrb(gray, orb);
    if (features.ok() && !features->empty()) views.push_back(std::move(features).value());
  }
  if (views.size() < 20) {
    std::fprintf(stderr, "no RTAB-Map loop frames under %s\n", data::SharedDir().c_str());
    return 1;
  }
  size_t descriptors = 0;
  for (const FeatureSet& view : views) descriptors += view.size();
  std::printf(
      "# workload: places made from %zu RTAB-Map views (ORB 1000, %.0f descriptors each), 90 %% "
      "kept, 4 bits flipped; fixed vocabulary %u words\n",
      views.size(), double(descriptors) / double(views.size()), (*fixed)->word_count());

  for (size_t places : sizes) {
    const std::string n = std::to_string(places);
    // Learning: offering is the map's scan (each place once), then training.
    LearningOptions options;
    options.threads = 2;
    VocabularyLearner learner(FeatureType::kOrb, options);
    const double offer_start = NowMs();
    for (size_t id = 1; id <= places; ++id) {
      const Status offered = learner.Offer(id, MakePlace(views, id));
      if (!offered.ok()) {
        std::fprintf(stderr, "%s\n", offered.ToString().c_str());
        return 1;
      }
    }
    const double offer_ms = NowMs() - offer_start;
    auto learned = learner.Learn();
    if (!learned.ok()) {
      std::fprintf(stderr, "%s\n", learned.status().ToString().c_str());
      return 1;
    }
    const Vocabulary& vocabulary = *learned->vocabulary.binary();
    Print("learn_scan_seconds_at_" + n + "_places", offer_ms / 1e3, "s");
    Print("learn_train_seconds_at_" + n + "_places", learned->train_ms / 1e3, "s");
    Print("learn_sampled_descriptors_at_" + n + "_places", double(learned->descriptors_sampled),
          "descriptors");
    Print("learned_words_at_" + n + "_places", vocabulary.word_count(), "words");
    Print("learned_depth_at_" + n + "_places", vocabulary.depth(), "levels");
    Print("peak_rss_after_learning_at_" + n + "_places", PeakRssMb(), "MB");

    InvertedIndex relearned(vocabulary.word_count(), ScoringType::kL1);
    const double reindex_ms = BuildIndex(vocabulary, views, places, &relearned);
    Print("reindex_seconds_at_" + n + "_places", reindex_ms / 1e3, "s");
    Print("learn_and_reindex_seconds_at_" + n + "_places",
          (offer_ms + learned->train_ms + reindex_ms) / 1e3, "s");
    Print("peak_rss_after_reindex_at_" + n + "_places", PeakRssMb(), "MB");
    const double learned_query = QueryMs(vocabulary, views, relearned, places);
    Print("query_top10_learned_vocabulary_at_" + n + "_places", learned_query, "ms");
    Print("index_memory_learned_vocabulary_at_" + n + "_places",
          double(relearned.MemoryBytes()) / 1e6, "MB");
    InvertedIndex index((*fixed)->word_count(), ScoringType::kL1);
    const double build_ms = BuildIndex(**fixed, views, places, &index);
    Print("baseline_index_build_fixed_vocabulary_seconds_at_" + n + "_places", build_ms / 1e3, "s");
    Print("baseline_query_top10_fixed_vocabulary_at_" + n + "_places",
          QueryMs(**fixed, views, index, places), "ms");
    Print("baseline_index_memory_fixed_vocabulary_at_" + n + "_places",
          double(index.MemoryBytes()) / 1e6, "MB");
  }
  return 0;
}

}  // namespace
}  // namespace placedb

int main(int argc, char** argv) {
  return placedb::Main(argc, argv);
}
