// placedb core benchmark: prints one `name value unit` line per figure, each with its baseline
// measured in the same run.
//
// Workload (stated on stdout too):
//  - real views: Debian sample images (opencv-doc, darknet) and CamVid frames, resized to
//    640x480, plus seeded random crops / rotations / brightness-contrast changes of them, ORB with
//    1000 features (about 930-1000 descriptors per view);
//  - size sweep: each place is one real view's descriptor set, multiplied by keeping a random
//    90 % of its descriptors and flipping 4 random bits in each (a cheap stand-in for re-imaging
//    that keeps real descriptor statistics), transformed by the vocabulary, L1-normalised.
//  - one thread for every timed figure except the `_2threads` query; medians over repeated runs.
//  - index figures: top-10 query on 1 and 2 threads, index bytes per stored descriptor, the top-1
//    and top-10 agreement of the (quantised) index with the exact ranking, build time and the
//    process's peak memory (VmHWM) at each size; places are added in id order.
//  - the frequent-word skip (max_word_share 0.03) against the exact scan on new random views of
//    the sources (`revisit`) and on RTAB-Map loop frames (`unrelated`): time and agreement.
//
// Usage: placedb-bench-core --vocabulary FILE [--places 1000,10000,100000,1000000] [--views N]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "bench/source_views.h"
#include "core/base/files.h"
#include "core/base/parallel.h"
#include "core/features/orb_features.h"
#include "core/search/place_index.h"
#include "core/search/scoring.h"
#include "core/vocabulary/vocabulary.h"

namespace fs = std::filesystem;
using namespace placedb;
using bench::ExtractViews;
using bench::Median;
using bench::NowMs;
using bench::PeakRssMb;
using bench::Print;
using bench::SourceImages;

namespace {

struct Options {
  std::string vocabulary_path;
  std::string shared = PLACEDB_SHARED_DIR;
  std::vector<size_t> sweep = {1000, 10000, 100000};
  size_t view_count = 1500;
};

// The command line; an exit code when the program must stop (usage error).
std::optional<int> ParseOptions(int argc, char** argv, Options* options) {
  for (int i = 1; i < argc; ++i) {
    std::string arg = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", arg.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (arg == "--vocabulary") {
      options->vocabulary_path = next();
    } else if (arg == "--shared") {
      options->shared = next();
    } else if (arg == "--views") {
      options->view_count = std::stoul(next());
    } else if (arg == "--places") {
      options->sweep.clear();
      std::stringstream list(next());
      for (std::string item; std::getline(list, item, ',');) {
        options->sweep.push_back(std::stoul(item));
      }
    } else {
      std::fprintf(stderr,
                   "usage: placedb-bench-core --vocabulary FILE [--places 1000,10000,100000] "
                   "[--views N] [--shared DIR]\n");
      return 2;
    }
  }
  if (options->vocabulary_path.empty()) {
    std::fprintf(stderr, "--vocabulary FILE is required\n");
    return 2;
  }
  return std::nullopt;
}

// Binary load time (median of 7), with the vocabulary it loaded; nullptr after an error.
std::shared_ptr<const Vocabulary> BenchVocabularyLoad(const std::string& path) {
  std::vector<double> load_ms;
  std::shared_ptr<const Vocabulary> vocabulary;
  for (int run = 0; run < 7; ++run) {
    const double start = NowMs();
    auto loaded = Vocabulary::LoadBinary(path);
    load_ms.push_back(NowMs() - start);
    if (!loaded.ok()) {
      // The benchmark times the binary format; a DBoW2 text file converts in one command.
      std::fprintf(stderr,
                   "placedb-bench-core: %s\n(a DBoW2 text vocabulary? convert it first: "
                   "placedb-vocab convert --in %s --out FILE.pdbv)\n",
                   loaded.status().ToString().c_str(), path.c_str());
      return nullptr;
    }
    vocabulary = *loaded;
  }
  std::printf("# vocabulary: k=%d L=%d, %u words, %u nodes, %.1f MB\n", vocabulary->branching(),
              vocabulary->depth(), vocabulary->word_count(), vocabulary->node_count(),
              vocabulary->memory_bytes() / 1e6);
  Print("vocabulary_load_binary", Median(load_ms), "ms");
  return vocabulary;
}

// The baseline for the binary load: the same vocabulary through DBoW2 text, which must round
// trip unchanged. False after an error.
bool BenchDbow2TextLoad(const Vocabulary& vocabulary) {
  const std::string text = (fs::temp_directory_path() / "placedb-bench-vocab.txt").string();
  if (const Status exported = vocabulary.ExportDbow2Text(text); !exported.ok()) {
    std::fprintf(stderr, "placedb-bench-core: %s\n", exported.ToString().c_str());
    return false;
  }
  const double start = NowMs();
  auto imported = Vocabulary::ImportDbow2Text(text);
  Print("baseline_vocabulary_load_dbow2_text", NowMs() - start, "ms");
  fs::remove(text);
  if (!imported.ok() || (*imported)->checksum() != vocabulary.checksum()) {
    std::fprintf(stderr, "text round trip changed the vocabulary\n");
    return false;
  }
  return true;
}

// The transform's baseline: the same BoW vector built one descriptor at a time (WordOf, then
// sort and merge), as a straightforward tree walk does.
BowVector TransformOneAtATime(const Vocabulary& vocabulary,
                              const std::vector<Descriptor256>& descriptors) {
  BowVector naive;
  naive.reserve(descriptors.size());
  for (const auto& d : descriptors) {
    const WordId word = vocabulary.WordOf(d);
    naive.push_back({word, vocabulary.WordWeight(word)});
  }
  std::sort(naive.begin(), naive.end(),
            [](const BowEntry& a, const BowEntry& b) { return a.word < b.word; });
  size_t out = 0;
  for (size_t i = 0; i < naive.size(); ++i) {
    if (out > 0 && naive[out - 1].word == naive[i].word) {
      naive[out - 1].weight += naive[i].weight;
    } else {
      naive[out++] = naive[i];
    }
  }
  naive.resize(out);
  for (auto& entry : naive) entry.weight /= float(descriptors.size());
  return naive;
}

// Transform time per image (up to 400 views), with and without a direct index, against the
// one-at-a-time baseline. False when the baseline disagrees.
bool BenchTransform(const Vocabulary& vocabulary, const std::vector<FeatureSet>& views) {
  std::vector<double> bow_ms, direct_ms, naive_ms;
  BowVector bow;
  DirectIndex direct;
  for (size_t v = 0; v < std::min<size_t>(views.size(), 400); ++v) {
    const auto& descriptors = views[v].descriptors;
    double start = NowMs();
    vocabulary.Transform(descriptors, &bow, nullptr, 0);
    bow_ms.push_back(NowMs() - start);
    start = NowMs();
    vocabulary.Transform(descriptors, &bow, &direct, 2);
    direct_ms.push_back(NowMs() - start);
    start = NowMs();
    const BowVector naive = TransformOneAtATime(vocabulary, descriptors);
    naive_ms.push_back(NowMs() - start);
    if (naive.size() != bow.size()) {
      std::fprintf(stderr, "baseline transform disagrees with Transform\n");
      return false;
    }
  }
  Print("transform_per_image", Median(bow_ms), "ms");
  Print("transform_per_image_with_direct_index_level2", Median(direct_ms), "ms");
  Print("baseline_transform_per_image_one_at_a_time", Median(naive_ms), "ms");
  return true;
}

// The size sweep's growing map, and (while small) the vectors the linear-scan baseline scores.
struct SweepMap {
  explicit SweepMap(uint32_t word_count) : index(word_count, ScoringType::kL1) {}
  InvertedIndex index;
  std::vector<BowVector> stored;  // kept only while small, for the brute-force baseline
  size_t places = 0;
  uint64_t stored_descriptors = 0;
  double build_ms = 0;  // wall time of GrowTo so far (views to BoW vectors, index adds)
  double add_ms = 0;    // of which InvertedIndex::Add
};

// The BoW vector of place `place` (ids from 1): its view for the first pass over the views, then
// a noisy copy of it (90 % of the descriptors, 4 bit flips each) so that places stay distinct.
// Seeded by the place id, so any place can be rebuilt exactly (the exact-ranking check) without
// keeping a second copy of the map. Returns the number of descriptors.
size_t PlaceBow(PlaceId place, const Vocabulary& vocabulary, const std::vector<FeatureSet>& views,
                BowVector* bow) {
  const size_t index = size_t(place) - 1;
  const FeatureSet& view = views[index % views.size()];
  const bool copy = index >= views.size();
  std::mt19937_64 rng(place);
  std::vector<Descriptor256> noisy;
  noisy.reserve(view.size());
  std::uniform_int_distribution<int> bit(0, 255);
  std::uniform_real_distribution<double> keep(0, 1);
  for (const auto& d : view.descriptors) {
    if (copy && keep(rng) > 0.9) continue;
    Descriptor256 changed = d;
    if (copy) {
      for (int f = 0; f < 4; ++f) {
        const int b = bit(rng);
        changed.words[size_t(b / 64)] ^= uint64_t(1) << (b % 64);
      }
    }
    noisy.push_back(changed);
  }
  vocabulary.Transform(noisy, bow, nullptr, 0);
  NormalizeForScoring(bow, ScoringType::kL1);
  return noisy.size();
}

// Adds places up to `target`, their vectors built on 2 threads in batches and added in id order
// (as ingest and reopen add). False after an error.
bool GrowTo(size_t target, const Vocabulary& vocabulary, const std::vector<FeatureSet>& views,
            SweepMap* map) {
  const double start = NowMs();
  constexpr size_t kBatch = 512;
  std::vector<BowVector> batch(kBatch);
  std::vector<size_t> descriptors(kBatch);
  while (map->places < target) {
    const size_t count = std::min(kBatch, target - map->places);
    const PlaceId first = PlaceId(map->places + 1);
    ParallelFor(count, 2, [&](size_t i, int) {
      descriptors[i] = PlaceBow(PlaceId(first + i), vocabulary, views, &batch[i]);
    });
    for (size_t i = 0; i < count; ++i) {
      map->stored_descriptors += descriptors[i];
      const double add_start = NowMs();
      if (!map->index.Add(PlaceId(first + i), batch[i]).ok()) return false;
      map->add_ms += NowMs() - add_start;
      if (target <= 10000) map->stored.push_back(batch[i]);
    }
    map->places += count;
  }
  map->build_ms += NowMs() - start;
  return true;
}

// CPU time of this thread, in ms.
double ThreadCpuMs() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return double(ts.tv_sec) * 1e3 + double(ts.tv_nsec) / 1e6;
}

// Agreement of the index's top 1 / top 10 with the exact ranking (unquantised weights, double
// sums: Score()) on one query, without a second copy of the map: a stored weight is within a
// relative kWeightRelativeError of the exact one, so with L1-normalised places a score is within
// kWeightRelativeError (plus float rounding of the sum) of the exact one, and the exact top 10
// can only hold places whose index score is within twice that of the index's 10th. Those are
// rebuilt (PlaceBow) and scored exactly. False when the window reaches past the index's top 200
// (the check would be incomplete).
struct Agreement {
  double top1 = 0;
  double top10 = 0;
  size_t rescored = 0;
  std::vector<PlaceId> exact_top10;  // best first
};
bool AgreeWithExact(const BowVector& query, const Vocabulary& vocabulary,
                    const std::vector<FeatureSet>& views, const SweepMap& map,
                    Agreement* agreement) {
  constexpr double kSumRounding = 1e-4;  // float sums of ~1000 terms <= 1 each, generously
  const double margin = 2 * (InvertedIndex::kWeightRelativeError + kSumRounding);
  const std::vector<ScoredPlace> wide = map.index.Query(query, 200);
  if (wide.size() < 10) return false;
  const double floor = wide[9].score - margin;
  if (wide.size() == 200 && wide.back().score >= floor) return false;
  std::vector<ScoredPlace> exact;
  BowVector bow;
  for (const ScoredPlace& candidate : wide) {
    if (candidate.score < floor) break;
    PlaceBow(candidate.place, vocabulary, views, &bow);
    exact.push_back({candidate.place, Score(query, bow, ScoringType::kL1)});
  }
  std::sort(exact.begin(), exact.end(), [](const ScoredPlace& a, const ScoredPlace& b) {
    return a.score != b.score ? a.score > b.score : a.place < b.place;
  });
  agreement->top1 = exact[0].place == wide[0].place ? 1 : 0;
  size_t shared = 0;
  for (size_t i = 0; i < 10; ++i) {
    for (size_t j = 0; j < 10; ++j) shared += exact[i].place == wide[j].place ? 1 : 0;
  }
  agreement->top10 = double(shared) / 10;
  agreement->rescored = exact.size();
  for (size_t i = 0; i < 10; ++i) agreement->exact_top10.push_back(exact[i].place);
  return true;
}

// The server's frequent-word skip (max_word_share 0.03, its default from 100,000 places) against
// the exact scan on harder queries than a stored view: `kind` names them. Per query the index's
// exhaustive top 10 is the reference (it equals the exact ranking: the lines above); prints the
// skip's top-1 and top-10 agreement with it and both paths' times (1 thread, alternating).
void BenchSkipAgreement(const std::string& kind, const std::vector<BowVector>& queries,
                        const SweepMap& map) {
  std::vector<double> exact_ms, skip_ms;
  double top1 = 0, top10 = 0;
  for (size_t q = 0; q < queries.size(); ++q) {
    std::vector<ScoredPlace> answer[2];
    for (int path = 0; path < 2; ++path) {
      const int skip = int((path + q) % 2);
      const double start = NowMs();
      answer[skip] = map.index.Query(queries[q], 10, {}, {}, 1, skip == 1 ? 0.03 : 1.0);
      (skip == 1 ? skip_ms : exact_ms).push_back(NowMs() - start);
    }
    if (answer[0].empty() || answer[1].empty()) continue;
    top1 += answer[0][0].place == answer[1][0].place ? 1 : 0;
    for (const ScoredPlace& got : answer[1]) {
      for (const ScoredPlace& want : answer[0]) top10 += got.place == want.place ? 0.1 : 0;
    }
  }
  const std::string at = kind + "_at_" + std::to_string(map.places) + "_places";
  const double n = double(std::max<size_t>(queries.size(), 1));
  Print("query_top10_exact_" + at, Median(exact_ms), "ms");
  Print("query_top10_skip_words_over_3pct_" + at, Median(skip_ms), "ms");
  Print("top1_agreement_skip_words_over_3pct_" + at, top1 / n, "ratio");
  Print("top10_agreement_skip_words_over_3pct_" + at, top10 / n, "ratio");
}

// Top-10 query time at this size on 1 and 2 threads (60 queries; the linear scan on 10 of them
// while the map is small), agreement with the exact ranking (20 queries), the index's memory and
// the process's peak memory. False when a query finds nothing.
bool BenchQueries(size_t target, const Vocabulary& vocabulary, const std::vector<FeatureSet>& views,
                  const SweepMap& map) {
  // Queries: fresh random views of the sources (not stored).
  std::vector<double> query_ms, query_cpu_ms, query2_ms, brute_ms;
  // Skipping the words held by more than this share of the places (InvertedIndex::Query's
  // max_word_share): query time and agreement with the exact ranking, against the lines above.
  constexpr double kSkipShares[] = {0.10, 0.03};
  std::vector<double> skip_ms[std::size(kSkipShares)];
  // The smallest share on 2 threads: the server's settings for large maps combined.
  std::vector<double> skip_2threads_ms;
  double skip_top1[std::size(kSkipShares)] = {}, skip_top10[std::size(kSkipShares)] = {};
  double top1 = 0, top10 = 0, rescored = 0;
  int agreement_queries = 0, incomplete = 0;
  for (int q = 0; q < 60; ++q) {
    const FeatureSet& view = views[size_t(q * 7919) % views.size()];
    BowVector query;
    vocabulary.Transform(view.descriptors, &query, nullptr, 0);
    NormalizeForScoring(&query, ScoringType::kL1);
    const double cpu_start = ThreadCpuMs();
    double start = NowMs();
    auto top = map.index.Query(query, 10);
    query_ms.push_back(NowMs() - start);
    query_cpu_ms.push_back(ThreadCpuMs() - cpu_start);
    if (top.empty()) return false;
    start = NowMs();
    auto top_2threads = map.index.Query(query, 10, {}, {}, 2);
    query2_ms.push_back(NowMs() - start);
    if (top_2threads.size() != top.size() || top_2threads[0].place != top[0].place) {
      std::fprintf(stderr, "2-thread query disagrees with 1-thread query\n");
      return false;
    }
    if (target <= 10000 && q < 10) {
      start = NowMs();
      std::vector<double> scores(map.stored.size());
      for (size_t p = 0; p < map.stored.size(); ++p)
        scores[p] = Score(query, map.stored[p], ScoringType::kL1);
      std::partial_sort(scores.begin(), scores.begin() + std::min<size_t>(10, scores.size()),
                        scores.end(), std::greater<>());
      brute_ms.push_back(NowMs() - start);
    }
    std::vector<std::vector<ScoredPlace>> skipping_tops;
    for (size_t v = 0; v < std::size(kSkipShares); ++v) {
      start = NowMs();
      skipping_tops.push_back(map.index.Query(query, 10, {}, {}, 1, kSkipShares[v]));
      skip_ms[v].push_back(NowMs() - start);
    }
    start = NowMs();
    map.index.Query(query, 10, {}, {}, 2, kSkipShares[std::size(kSkipShares) - 1]);
    skip_2threads_ms.push_back(NowMs() - start);
    if (q < 20) {
      Agreement agreement;
      if (AgreeWithExact(query, vocabulary, views, map, &agreement)) {
        top1 += agreement.top1;
        top10 += agreement.top10;
        rescored += double(agreement.rescored);
        ++agreement_queries;
        for (size_t v = 0; v < std::size(kSkipShares); ++v) {
          const std::vector<ScoredPlace>& got = skipping_tops[v];
          if (!got.empty() && got[0].place == agreement.exact_top10[0]) skip_top1[v] += 1;
          for (const ScoredPlace& s : got) {
            skip_top10[v] +=
                std::count(agreement.exact_top10.begin(), agreement.exact_top10.end(), s.place) /
                10.0;
          }
        }
      } else {
        ++incomplete;
      }
    }
  }
  const std::string n = std::to_string(target);
  Print("query_top10_at_" + n + "_places", Median(query_ms), "ms");
  // The same query's CPU time: on a shared machine, wall time also counts waiting for a core.
  Print("query_top10_cpu_at_" + n + "_places", Median(query_cpu_ms), "ms");
  Print("query_top10_2threads_at_" + n + "_places", Median(query2_ms), "ms");
  if (!brute_ms.empty()) {
    Print("baseline_query_top10_linear_scan_at_" + n + "_places", Median(brute_ms), "ms");
  }
  if (agreement_queries > 0) {
    std::printf(
        "# exact ranking at %s places: %d queries, %.1f places rescored per query, %d "
        "skipped (window past the top 200)\n",
        n.c_str(), agreement_queries, rescored / agreement_queries, incomplete);
    Print("top1_agreement_with_exact_at_" + n + "_places", top1 / agreement_queries, "ratio");
    Print("top10_agreement_with_exact_at_" + n + "_places", top10 / agreement_queries, "ratio");
  }
  for (size_t v = 0; v < std::size(kSkipShares); ++v) {
    const std::string variant =
        "skip_words_over_" + std::to_string(int(kSkipShares[v] * 100 + 0.5)) + "pct_at_" + n;
    Print("query_top10_" + variant + "_places", Median(skip_ms[v]), "ms");
    if (agreement_queries > 0) {
      Print("top1_agreement_" + variant + "_places", skip_top1[v] / agreement_queries, "ratio");
      Print("top10_agreement_" + variant + "_places", skip_top10[v] / agreement_queries, "ratio");
    }
  }
  Print("query_top10_2threads_skip_words_over_" +
            std::to_string(int(kSkipShares[std::size(kSkipShares) - 1] * 100 + 0.5)) + "pct_at_" +
            n + "_places",
        Median(skip_2threads_ms), "ms");
  Print("index_bytes_per_descriptor_at_" + n + "_places",
        double(map.index.MemoryBytes()) / double(map.stored_descriptors), "bytes");
  Print("postings_per_descriptor_at_" + n + "_places",
        double(map.index.posting_count()) / double(map.stored_descriptors), "ratio");
  Print("index_memory_at_" + n + "_places", double(map.index.MemoryBytes()) / 1e6, "MB");
  Print("build_seconds_at_" + n + "_places", map.build_ms / 1e3, "s");
  Print("index_add_per_place_at_" + n + "_places", 1e3 * map.add_ms / double(map.places), "us");
  Print("peak_rss_at_" + n + "_places", PeakRssMb(), "MB");
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  Options options;
  if (auto exit_code = ParseOptions(argc, argv, &options)) return *exit_code;

  // --- vocabulary load -------------------------------------------------------------------
  const std::shared_ptr<const Vocabulary> vocabulary = BenchVocabularyLoad(options.vocabulary_path);
  if (vocabulary == nullptr || !BenchDbow2TextLoad(*vocabulary)) return 1;

  // --- real views --------------------------------------------------------------------------
  const std::vector<std::string> sources = SourceImages(options.shared, /*camvid=*/true);
  if (sources.empty()) {
    std::fprintf(stderr, "no source images (install opencv-doc and darknet)\n");
    return 1;
  }
  const std::vector<FeatureSet> views = ExtractViews(sources, options.view_count);
  size_t descriptor_total = 0;
  for (const auto& view : views) descriptor_total += view.size();
  std::printf(
      "# workload: %zu real views (640x480, ORB 1000) from %zu source images, %.0f "
      "descriptors per view on average\n",
      views.size(), sources.size(), double(descriptor_total) / double(views.size()));

  // Harder queries than a stored view, for the frequent-word skip's agreement: new random views
  // of the sources (seeds no stored view used: a revisit from another viewpoint), and frames of a
  // place the map does not hold (the RTAB-Map loop's, every other one).
  std::vector<BowVector> revisit_queries, unrelated_queries;
  {
    OrbConfig orb;
    orb.max_features = 1000;
    auto add = [&](const cv::Mat& image, std::vector<BowVector>* queries) {
      auto features = ExtractOrb(image, orb);
      if (!features.ok() || features->size() < 100) return;
      BowVector bow;
      vocabulary->Transform(features->descriptors, &bow, nullptr, 0);
      NormalizeForScoring(&bow, ScoringType::kL1);
      queries->push_back(std::move(bow));
    };
    for (size_t q = 0; q < 30; ++q) {
      std::mt19937_64 rng(1'000'000 + q);
      const cv::Mat image = cv::imread(sources[(q * 7) % sources.size()], cv::IMREAD_GRAYSCALE);
      if (!image.empty()) add(bench::RandomView(image, rng), &revisit_queries);
    }
    if (auto frames = ListImageFiles(options.shared + "/data/rtabmap-loop"); frames.ok()) {
      for (size_t i = 0; i < frames->size(); i += 2) {
        const cv::Mat image = cv::imread((*frames)[i], cv::IMREAD_GRAYSCALE);
        if (!image.empty()) add(image, &unrelated_queries);
      }
    }
    std::printf("# skip agreement queries: %zu new views of the sources, %zu RTAB-Map frames\n",
                revisit_queries.size(), unrelated_queries.size());
  }

  // --- transform ---------------------------------------------------------------------------
  if (!BenchTransform(*vocabulary, views)) return 1;

  // --- size sweep: query top-10 and index memory ------------------------------------------
  std::vector<size_t> sweep = options.sweep;
  std::sort(sweep.begin(), sweep.end());
  SweepMap map(vocabulary->word_count());
  for (size_t target : sweep) {
    if (!GrowTo(target, *vocabulary, views, &map)) return 1;
    if (!BenchQueries(target, *vocabulary, views, map)) return 1;
    BenchSkipAgreement("revisit", revisit_queries, map);
    if (!unrelated_queries.empty()) BenchSkipAgreement("unrelated", unrelated_queries, map);
  }
  return 0;
}
