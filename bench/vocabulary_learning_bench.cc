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
//  - the service's switch (--online-places, default 10000): a map of that many such places on
//    RocksDB in a temp directory (group commit), then PlaceMap::AdaptVocabulary while one thread
//    queries it without pause (top-10 of other noisy views); its phases' times, the queries'
//    p50/p99 during the switch beside the same queries on the idle map just before (baseline),
//    and top-10 latency after the switch beside before it. Once with the re-index on 1 thread,
//    once on 2 (the machine's cores), each on a fresh copy of the map.
//
// Usage: placedb-bench-vocabulary-learning --vocabulary FILE [--places 10000,100000]
//        [--online-places 10000] [--workdir DIR]
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/parallel.h"
#include "core/features/orb_features.h"
#include "core/search/place_index.h"
#include "core/storage/map_store.h"
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

double Percentile(std::vector<double> values, double fraction) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  return values[std::min(values.size() - 1, size_t(fraction * double(values.size())))];
}

// A frame of place `id` as a map takes it: its features only; the map transforms it (a frame of
// no vocabulary yet).
ProcessedFrame FrameOf(const std::vector<FeatureSet>& views, uint64_t id, uint64_t salt = 0) {
  ProcessedFrame frame;
  frame.valid = true;
  FeatureSet features = MakePlace(views, id, salt);
  frame.counts.static_ = uint32_t(features.size());
  frame.counts.total = frame.counts.static_;
  frame.static_features = std::move(features);
  return frame;
}

void Fail(const Status& status, const char* what) {
  if (status.ok()) return;
  std::fprintf(stderr, "%s: %s\n", what, status.ToString().c_str());
  std::exit(1);
}

// Queries `map` from one thread until `stop`, each with the next of `queries`; their latencies.
std::vector<double> QueryUntil(const PlaceMap& map, const std::vector<ProcessedFrame>& queries,
                               const std::atomic<bool>& stop, size_t at_least) {
  std::vector<double> ms;
  QueryOptions options;
  options.top_k = 10;
  for (size_t q = 0; !stop.load() || ms.size() < at_least; ++q) {
    const double start = NowMs();
    const QueryResult result = map.Search(queries[q % queries.size()], options);
    ms.push_back(NowMs() - start);
    if (!result.valid || result.matches.empty()) {
      std::fprintf(stderr, "a query found nothing: %s\n", result.rejection.c_str());
      std::exit(1);
    }
  }
  return ms;
}

// The service's switch on a map of `places` places (see the workload above).
void OnlineSwitch(const std::shared_ptr<const Vocabulary>& fixed,
                  const std::vector<FeatureSet>& views, size_t places, const std::string& workdir) {
  const std::string n = std::to_string(places);
  namespace fs = std::filesystem;
  const std::string root = workdir + "/placedb-bench-switch-" + std::to_string(::getpid());
  fs::remove_all(root);
  StorageOptions storage;
  storage.sync = SyncMode::kGroupCommit;
  std::vector<ProcessedFrame> queries;
  for (uint64_t q = 0; q < 200; ++q) queries.push_back(FrameOf(views, (q * 7919) % places + 1, 77));
  {
    auto dir = DataDirectory::Open(root + "/template", storage);
    Fail(dir.status(), "data directory");
    auto map = (*dir)->CreateMap("map", {}, AnyVocabulary(fixed));
    Fail(map.status(), "map");
    const double fill_start = NowMs();
    constexpr size_t kWindow = 64;
    std::vector<std::shared_ptr<PendingCommit>> window;
    for (size_t id = 1; id <= places; ++id) {
      PlaceMetadata metadata;
      metadata.sequence = id;
      window.push_back((*map)->Enqueue(FrameOf(views, id), metadata));
      if (window.size() == kWindow || id == places) {
        for (const auto& pending : window) Fail(pending->Wait().status(), "storing a place");
        window.clear();
      }
    }
    Print("online_fill_seconds_at_" + n + "_places", (NowMs() - fill_start) / 1e3, "s");
  }
  for (const int threads : {1, 2}) {
    const std::string suffix = "_" + std::to_string(threads) + "_threads_at_" + n + "_places";
    const std::string copy = root + "/copy";
    fs::remove_all(copy);
    fs::copy(root + "/template", copy, fs::copy_options::recursive);
    fs::remove(copy + "/LOCK");
    auto dir = DataDirectory::Open(copy, storage);
    Fail(dir.status(), "data directory copy");
    auto opened = (*dir)->OpenMap("map", AnyVocabulary(fixed));
    Fail(opened.status(), "opening the map");
    PlaceMap& map = **opened;
    std::atomic<bool> stop{true};
    const std::vector<double> idle = QueryUntil(map, queries, stop, 400);
    stop = false;
    std::vector<double> during;
    std::thread querying([&] { during = QueryUntil(map, queries, stop, 1); });
    AdaptOptions options;
    options.threads = threads;
    options.learning.threads = threads;
    const double start = NowMs();
    double learned_at = 0, reindexed_at = 0, caught_up_at = 0, switched_at = 0;
    options.on_phase = [&](VocabularyPhase phase) {
      const double now = NowMs() - start;
      if (phase == VocabularyPhase::kLearned) learned_at = now;
      if (phase == VocabularyPhase::kReindexed) reindexed_at = now;
      if (phase == VocabularyPhase::kCaughtUp) caught_up_at = now;
      if (phase == VocabularyPhase::kSwitched) switched_at = now;
    };
    auto record = map.AdaptVocabulary(options);
    const double total = NowMs() - start;
    stop = true;
    querying.join();
    Fail(record.status(), "adapting the vocabulary");
    Print("switch_learn_seconds" + suffix, learned_at / 1e3, "s");
    Print("switch_reindex_seconds" + suffix, (reindexed_at - learned_at) / 1e3, "s");
    Print("switch_catch_up_and_write_seconds" + suffix, (switched_at - reindexed_at) / 1e3, "s");
    Print("switch_writers_held_ms" + suffix, total - caught_up_at + 0.0, "ms");
    Print("switch_total_seconds" + suffix, total / 1e3, "s");
    Print("switch_sampled_descriptors" + suffix, double(record->current.descriptors_sampled),
          "descriptors");
    Print("switch_learned_depth" + suffix, record->current.depth, "levels");
    Print("baseline_idle_query_p50" + suffix, Percentile(idle, 0.5), "ms");
    Print("baseline_idle_query_p99" + suffix, Percentile(idle, 0.99), "ms");
    Print("query_p50_during_switch" + suffix, Percentile(during, 0.5), "ms");
    Print("query_p99_during_switch" + suffix, Percentile(during, 0.99), "ms");
    Print("queries_during_switch" + suffix, double(during.size()), "queries");
    stop = true;
    Print("query_p50_after_switch" + suffix, Percentile(QueryUntil(map, queries, stop, 400), 0.5),
          "ms");
    Print("peak_rss_after_switch" + suffix, PeakRssMb(), "MB");
  }
  fs::remove_all(root);
}

int Main(int argc, char** argv) {
  std::string vocabulary_path;
  std::vector<size_t> sizes = {10000, 100000};
  std::vector<size_t> online = {10000};
  std::string workdir = std::filesystem::temp_directory_path().string();
  const auto parse_list = [](const std::string& list) {
    std::vector<size_t> values;
    for (size_t start = 0; start <= list.size();) {
      const size_t comma = std::min(list.find(',', start), list.size());
      values.push_back(std::stoul(list.substr(start, comma - start)));
      start = comma + 1;
    }
    return values;
  };
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--vocabulary" && i + 1 < argc) {
      vocabulary_path = argv[++i];
    } else if (arg == "--online-places" && i + 1 < argc) {
      online = parse_list(argv[++i]);
    } else if (arg == "--workdir" && i + 1 < argc) {
      workdir = argv[++i];
    } else if (arg == "--places" && i + 1 < argc) {
      sizes.clear();
      std::string list = argv[++i];
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = std::min(list.find(',', start), list.size());
        sizes.push_back(std::stoul(list.substr(start, comma - start)));
        start = comma + 1;
      }
    } else {
      std::fprintf(stderr,
                   "usage: %s --vocabulary FILE [--places 10000,100000] [--online-places 10000] "
                   "[--workdir DIR]\n",
                   argv[0]);
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
  for (size_t places : online) {
    if (places > 0) OnlineSwitch(*fixed, views, places, workdir);
  }
  return 0;
}

}  // namespace
}  // namespace placedb

int main(int argc, char** argv) {
  return placedb::Main(argc, argv);
}
