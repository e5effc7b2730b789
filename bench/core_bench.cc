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
//  - one thread for every timed figure; medians over repeated runs.
//
// Usage: placedb-bench-core --vocabulary FILE [--places 1000,10000,100000] [--views N]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/files.h"
#include "core/features/orb_features.h"
#include "core/search/place_index.h"
#include "core/search/scoring.h"
#include "core/vocabulary/vocabulary.h"

namespace fs = std::filesystem;
using namespace placedb;
using bench::Median;
using bench::Print;

namespace {

double NowMs() {
  return std::chrono::duration<double, std::milli>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

std::vector<std::string> SourceImages(const std::string& shared) {
  std::vector<std::string> paths;
  auto add_dir = [&](const std::string& dir, size_t every) {
    auto found = ListImageFiles(dir);
    if (!found.ok()) return;
    for (size_t i = 0; i < found->size(); i += every) paths.push_back((*found)[i]);
  };
  add_dir("/usr/share/doc/opencv-doc/examples/data", 1);
  add_dir("/usr/share/darknet/data", 1);
  add_dir(shared + "/data/camvid/images", 3);
  return paths;
}

// A seeded random view of `image`: crop, rotation, scale, brightness/contrast, at 640x480.
cv::Mat RandomView(const cv::Mat& image, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> angle(-15, 15), scale(1.0, 1.4), gain(0.7, 1.3),
      bias(-30, 30), shift(-0.1, 0.1);
  cv::Mat base;
  cv::resize(image, base, cv::Size(640, 480));
  const cv::Point2f centre(320 + float(shift(rng) * 640), 240 + float(shift(rng) * 480));
  cv::Mat warp = cv::getRotationMatrix2D(centre, angle(rng), scale(rng));
  cv::Mat view;
  cv::warpAffine(base, view, warp, base.size(), cv::INTER_LINEAR, cv::BORDER_REFLECT);
  view.convertTo(view, -1, gain(rng), bias(rng));
  return view;
}

}  // namespace

int main(int argc, char** argv) {
  std::string vocabulary_path;
  std::string shared = PLACEDB_SHARED_DIR;
  std::vector<size_t> sweep = {1000, 10000, 100000};
  size_t view_count = 1500;
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
      vocabulary_path = next();
    } else if (arg == "--shared") {
      shared = next();
    } else if (arg == "--views") {
      view_count = std::stoul(next());
    } else if (arg == "--places") {
      sweep.clear();
      std::stringstream list(next());
      for (std::string item; std::getline(list, item, ',');) sweep.push_back(std::stoul(item));
    } else {
      std::fprintf(stderr,
                   "usage: placedb-bench-core --vocabulary FILE [--places 1000,10000,100000] "
                   "[--views N] [--shared DIR]\n");
      return 2;
    }
  }
  if (vocabulary_path.empty()) {
    std::fprintf(stderr, "--vocabulary FILE is required\n");
    return 2;
  }

  // --- vocabulary load -------------------------------------------------------------------
  std::vector<double> load_ms;
  std::shared_ptr<const Vocabulary> vocabulary;
  for (int run = 0; run < 7; ++run) {
    const double start = NowMs();
    auto loaded = Vocabulary::LoadBinary(vocabulary_path);
    load_ms.push_back(NowMs() - start);
    if (!loaded.ok()) {
      std::fprintf(stderr, "%s\n", loaded.status().ToString().c_str());
      return 1;
    }
    vocabulary = *loaded;
  }
  std::printf("# vocabulary: k=%d L=%d, %u words, %u nodes, %.1f MB\n", vocabulary->branching(),
              vocabulary->depth(), vocabulary->word_count(), vocabulary->node_count(),
              vocabulary->memory_bytes() / 1e6);
  Print("vocabulary_load_binary", Median(load_ms), "ms");
  {
    const std::string text = (fs::temp_directory_path() / "placedb-bench-vocab.txt").string();
    if (!vocabulary->ExportDbow2Text(text).ok()) return 1;
    const double start = NowMs();
    auto imported = Vocabulary::ImportDbow2Text(text);
    Print("baseline_vocabulary_load_dbow2_text", NowMs() - start, "ms");
    fs::remove(text);
    if (!imported.ok() || (*imported)->checksum() != vocabulary->checksum()) {
      std::fprintf(stderr, "text round trip changed the vocabulary\n");
      return 1;
    }
  }

  // --- real views --------------------------------------------------------------------------
  const std::vector<std::string> sources = SourceImages(shared);
  if (sources.empty()) {
    std::fprintf(stderr, "no source images (install opencv-doc and darknet)\n");
    return 1;
  }
  OrbConfig orb;
  orb.max_features = 1000;
  std::vector<FeatureSet> views(view_count);
  {
    std::vector<std::thread> workers;
    const unsigned threads = std::max(1u, std::thread::hardware_concurrency());
    for (unsigned t = 0; t < threads; ++t) {
      workers.emplace_back([&, t] {
        for (size_t v = t; v < view_count; v += threads) {
          std::mt19937_64 rng(v);
          cv::Mat image = cv::imread(sources[v % sources.size()], cv::IMREAD_GRAYSCALE);
          if (image.empty()) continue;
          cv::Mat view = v < sources.size() ? RandomView(image, rng) : RandomView(image, rng);
          auto features = ExtractOrb(view, orb);
          if (features.ok()) views[v] = std::move(features).value();
        }
      });
    }
    for (auto& worker : workers) worker.join();
  }
  std::erase_if(views, [](const FeatureSet& f) { return f.size() < 100; });
  size_t descriptor_total = 0;
  for (const auto& view : views) descriptor_total += view.size();
  std::printf(
      "# workload: %zu real views (640x480, ORB 1000) from %zu source images, %.0f "
      "descriptors per view on average\n",
      views.size(), sources.size(), double(descriptor_total) / double(views.size()));

  // --- transform ---------------------------------------------------------------------------
  {
    std::vector<double> bow_ms, direct_ms, naive_ms;
    BowVector bow;
    DirectIndex direct;
    for (size_t v = 0; v < std::min<size_t>(views.size(), 400); ++v) {
      const auto& descriptors = views[v].descriptors;
      double start = NowMs();
      vocabulary->Transform(descriptors, &bow, nullptr, 0);
      bow_ms.push_back(NowMs() - start);
      start = NowMs();
      vocabulary->Transform(descriptors, &bow, &direct, 2);
      direct_ms.push_back(NowMs() - start);
      // Baseline: the same BoW vector built one descriptor at a time (WordOf, then sort and
      // merge), as a straightforward tree walk does.
      start = NowMs();
      BowVector naive;
      naive.reserve(descriptors.size());
      for (const auto& d : descriptors) {
        const WordId word = vocabulary->WordOf(d);
        naive.push_back({word, vocabulary->WordWeight(word)});
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
      naive_ms.push_back(NowMs() - start);
      if (naive.size() != bow.size()) {
        std::fprintf(stderr, "baseline transform disagrees with Transform\n");
        return 1;
      }
    }
    Print("transform_per_image", Median(bow_ms), "ms");
    Print("transform_per_image_with_direct_index_level2", Median(direct_ms), "ms");
    Print("baseline_transform_per_image_one_at_a_time", Median(naive_ms), "ms");
  }

  // --- size sweep: query top-10 and index memory ------------------------------------------
  std::sort(sweep.begin(), sweep.end());
  InvertedIndex index(vocabulary->word_count(), ScoringType::kL1);
  std::vector<BowVector> stored;  // kept only while small, for the brute-force baseline
  std::mt19937_64 rng(12345);
  size_t places = 0;
  uint64_t stored_descriptors = 0;
  BowVector bow;
  for (size_t target : sweep) {
    while (places < target) {
      const FeatureSet& view = views[places % views.size()];
      std::vector<Descriptor256> noisy;
      noisy.reserve(view.size());
      std::uniform_int_distribution<int> bit(0, 255);
      std::uniform_real_distribution<double> keep(0, 1);
      for (const auto& d : view.descriptors) {
        if (places >= views.size() && keep(rng) > 0.9) continue;
        Descriptor256 copy = d;
        if (places >= views.size()) {
          for (int f = 0; f < 4; ++f) {
            const int b = bit(rng);
            copy.words[size_t(b / 64)] ^= uint64_t(1) << (b % 64);
          }
        }
        noisy.push_back(copy);
      }
      vocabulary->Transform(noisy, &bow, nullptr, 0);
      NormalizeForScoring(&bow, ScoringType::kL1);
      stored_descriptors += noisy.size();
      if (!index.Add(PlaceId(places + 1), bow).ok()) return 1;
      if (target <= 10000) stored.push_back(bow);
      ++places;
    }
    // Queries: fresh random views of the sources (not stored).
    std::vector<double> query_ms, brute_ms;
    for (int q = 0; q < 60; ++q) {
      const FeatureSet& view = views[size_t(q * 7919) % views.size()];
      BowVector query;
      vocabulary->Transform(view.descriptors, &query, nullptr, 0);
      NormalizeForScoring(&query, ScoringType::kL1);
      double start = NowMs();
      auto top = index.Query(query, 10);
      query_ms.push_back(NowMs() - start);
      if (top.empty()) return 1;
      if (target <= 10000 && q < 10) {
        start = NowMs();
        std::vector<double> scores(stored.size());
        for (size_t p = 0; p < stored.size(); ++p)
          scores[p] = Score(query, stored[p], ScoringType::kL1);
        std::partial_sort(scores.begin(), scores.begin() + std::min<size_t>(10, scores.size()),
                          scores.end(), std::greater<>());
        brute_ms.push_back(NowMs() - start);
      }
    }
    const std::string n = std::to_string(target);
    Print("query_top10_at_" + n + "_places", Median(query_ms), "ms");
    if (!brute_ms.empty()) {
      Print("baseline_query_top10_linear_scan_at_" + n + "_places", Median(brute_ms), "ms");
    }
    Print("index_bytes_per_descriptor_at_" + n + "_places",
          double(index.MemoryBytes()) / double(stored_descriptors), "bytes");
    Print("postings_per_descriptor_at_" + n + "_places",
          double(index.posting_count()) / double(stored_descriptors), "ratio");
  }
  return 0;
}
