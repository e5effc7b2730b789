// Issue 31: what re-ranking the 10 best candidates costs per query, split into feature loading,
// putative matching and the robust fit, for the default verifier (`new_` lines) and the one before
// issue 31 (VerificationConfig::legacy: one Hamming distance at a time, OpenCV FM_RANSAC; `old_`
// lines) in the same run. Against an earlier default, run it through bench/compare.py
// (--base-rev REV --only verification: both builds alternating).
//
// Workload: CamVid frames (480x360), every other frame a database place and the others queries,
// ORB at each --orb budget, the default vocabulary; each query's 10 best places by BoW score
// (verification off) are its candidates, verified exhaustively ("Geo-6"), one thread. Feature
// loading is decoding each candidate's stored features value and BoW value (core/storage/codec.h,
// what RocksPayloadStore::Get decodes; the RocksDB read itself is not included). Each query runs
// both paths alternately (which goes first rotates from round to round), --rounds times,
// keeping each one's fastest. Figures are medians (p50) and p90 over the queries of the sum over
// their 10 candidates, in wall time and in the thread's CPU time (`cpu_`: what other processes on
// a loaded machine do not add); agreement lines compare the new path's ranking with the old
// one's.
//
// Usage: placedb-bench-verification [--vocabulary FILE] [--queries N] [--orb 1000,2000]
//        [--rounds N]
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <map>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgcodecs.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "bench/bench_output.h"
#include "core/pipeline/place_database.h"
#include "core/storage/codec.h"

using namespace placedb;
using bench::Median;
using bench::NowMs;
using bench::Print;

namespace {

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  return values[std::min(values.size() - 1, size_t(p * double(values.size() - 1) + 0.5))];
}

struct Split {
  double loading = 0, matching = 0, ransac = 0, total = 0, cpu = 0;
};

double CpuMs() {
  timespec now{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &now);
  return double(now.tv_sec) * 1e3 + double(now.tv_nsec) * 1e-6;
}

// The verified ranking of candidates (as PlaceDatabase::Query re-ranks): verified first by
// inliers, the others in BoW order.
std::vector<size_t> Ranking(const std::vector<VerificationResult>& results) {
  std::vector<size_t> order(results.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    if (results[a].verified != results[b].verified) return results[a].verified;
    return results[a].verified && results[a].inliers > results[b].inliers;
  });
  return order;
}

}  // namespace

int main(int argc, char** argv) {
  std::string vocabulary_path = PLACEDB_DEFAULT_VOCABULARY;
  size_t query_count = 60;
  int rounds = 3;
  std::vector<int> budgets = {1000, 2000};
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string flag = argv[i];
    if (flag == "--vocabulary") vocabulary_path = argv[i + 1];
    if (flag == "--queries") query_count = size_t(std::atoi(argv[i + 1]));
    if (flag == "--rounds") rounds = std::max(1, std::atoi(argv[i + 1]));
    if (flag == "--orb") {
      budgets.clear();
      std::stringstream list(argv[i + 1]);
      std::string item;
      while (std::getline(list, item, ',')) budgets.push_back(std::atoi(item.c_str()));
    }
  }
  cv::setNumThreads(1);
  auto vocabulary = Vocabulary::Load(vocabulary_path);
  if (!vocabulary.ok()) {
    std::fprintf(stderr, "vocabulary: %s\n", vocabulary.status().ToString().c_str());
    return 1;
  }
  std::vector<std::string> frames;
  const std::string camvid = std::string(PLACEDB_SHARED_DIR) + "/data/camvid/images";
  if (std::filesystem::is_directory(camvid)) {
    for (const auto& entry : std::filesystem::directory_iterator(camvid)) {
      frames.push_back(entry.path());
    }
  }
  std::sort(frames.begin(), frames.end());  // by sequence, then frame
  if (frames.empty()) {
    std::fprintf(stderr, "no CamVid frames (../shared/data/camvid)\n");
    return 1;
  }
  // Database: even positions; queries: odd positions spread over the whole set.
  std::vector<cv::Mat> images;
  for (const auto& frame : frames) images.push_back(cv::imread(frame, cv::IMREAD_GRAYSCALE));
  std::vector<size_t> query_positions;
  const size_t odd = frames.size() / 2;
  const size_t step = std::max<size_t>(1, odd / std::max<size_t>(1, query_count));
  for (size_t k = 0; k < odd && query_positions.size() < query_count; k += step) {
    query_positions.push_back(2 * k + 1);
  }
  std::printf(
      "# %zu CamVid places, %zu queries, 10 candidates each, exhaustive, 1 thread, "
      "rounds %d\n",
      (frames.size() + 1) / 2, query_positions.size(), rounds);

  for (const int budget : budgets) {
    DatabaseConfig config;
    config.orb.max_features = budget;
    config.verification.mode = VerificationMode::kDisabled;
    auto db = PlaceDatabase::Create(*vocabulary, config);
    if (!db.ok()) return 1;
    std::map<PlaceId, ProcessedFrame> places;
    std::map<PlaceId, std::pair<std::string, std::string>> stored;  // features, BoW values
    auto process = [&](size_t position) {
      Observation observation;
      observation.image = images[position];
      observation.metadata.agent_id = "bench";
      observation.metadata.sequence = position;
      observation.metadata.timestamp_ns = int64_t(position) * 1'000'000'000;
      return (*db)->Process(observation);
    };
    for (size_t p = 0; p < frames.size(); p += 2) {
      auto frame = process(p);
      if (!frame.ok()) return 1;
      if (!frame->valid) continue;
      auto id = (*db)->Insert(*frame, PlaceMetadata{"bench", p, int64_t(p) * 1'000'000'000, {}});
      if (!id.ok()) return 1;
      stored[*id] = {EncodeLocalFeatures(frame->static_features, frame->direct),
                     EncodeBow(frame->bow)};
      places[*id] = std::move(frame).value();
    }
    // Paths: 0 = legacy (old_), 1 = the default (new_).
    constexpr int kPaths = 2;
    const char* const kNames[kPaths] = {"old_", "new_"};
    std::vector<double> total[kPaths], cpu[kPaths], matching[kPaths], ransac[kPaths], loading;
    int same_top1 = 0, queries = 0, same_ranking = 0;
    double inlier_diff_sum = 0, inlier_old_sum = 0, inlier_new_sum = 0;
    int pairs = 0, verified_old = 0, verified_new = 0, verified_flips = 0;
    for (const size_t position : query_positions) {
      auto query = process(position);
      if (!query.ok() || !query->valid) continue;
      QueryOptions options;
      options.top_k = 10;
      Observation observation;
      observation.image = images[position];
      auto answer = (*db)->Query(observation, options);
      if (!answer.ok()) return 1;
      std::vector<PlaceId> candidates;
      for (const Match& m : answer->matches) candidates.push_back(m.place);
      // Feature loading: decode the candidates' stored values.
      double best_loading = 1e30;
      for (int r = 0; r < rounds; ++r) {
        const double start = NowMs();
        for (const PlaceId id : candidates) {
          PlacePayload payload;
          std::optional<DirectIndex> direct;
          if (!DecodeBowValue(stored[id].second, &payload.bow, &direct).ok() ||
              !DecodeLocalFeatures(stored[id].first, FeatureType::kOrb, &payload.features,
                                   &payload.direct)
                   .ok()) {
            return 1;
          }
        }
        best_loading = std::min(best_loading, NowMs() - start);
      }
      loading.push_back(best_loading);
      std::vector<VerificationResult> results[kPaths];
      Split best[kPaths];
      for (Split& b : best) b = {1e30, 1e30, 1e30, 1e30, 1e30};
      for (int r = 0; r < rounds; ++r) {
        for (int k = 0; k < kPaths; ++k) {
          const int path = (r + k) % kPaths;
          VerificationConfig verification;
          verification.mode = VerificationMode::kExhaustive;
          verification.legacy = path == 0;
          Split split;
          std::vector<VerificationResult> got;
          const double start = NowMs();
          const double start_cpu = CpuMs();
          for (const PlaceId id : candidates) {
            const ProcessedFrame& place = places.at(id);
            auto verified = VerifyGeometry(query->static_features, query->direct,
                                           place.static_features, place.direct, verification);
            if (!verified.ok()) return 1;
            split.matching += verified->matching_ms;
            split.ransac += verified->ransac_ms;
            got.push_back(std::move(verified).value());
          }
          split.total = NowMs() - start;
          split.cpu = CpuMs() - start_cpu;
          if (split.total < best[path].total) best[path] = split;
          results[path] = std::move(got);
        }
      }
      for (int path = 0; path < kPaths; ++path) {
        total[path].push_back(best[path].total);
        cpu[path].push_back(best[path].cpu);
        matching[path].push_back(best[path].matching);
        ransac[path].push_back(best[path].ransac);
      }
      ++queries;
      const std::vector<size_t> old_rank = Ranking(results[0]);
      const std::vector<size_t> new_rank = Ranking(results[1]);
      if (!candidates.empty() && old_rank[0] == new_rank[0] &&
          results[0][old_rank[0]].verified == results[1][new_rank[0]].verified) {
        ++same_top1;
      }
      if (old_rank == new_rank) ++same_ranking;
      for (size_t i = 0; i < candidates.size(); ++i) {
        const VerificationResult& o = results[0][i];
        const VerificationResult& n = results[1][i];
        ++pairs;
        inlier_diff_sum += std::abs(n.inliers - o.inliers);
        inlier_old_sum += o.inliers;
        inlier_new_sum += n.inliers;
        verified_old += o.verified;
        verified_new += n.verified;
        verified_flips += o.verified != n.verified;
      }
    }
    const std::string prefix = "verify10_orb" + std::to_string(budget) + "_";
    Print(prefix + "queries", queries, "queries");
    Print(prefix + "loading_p50_ms", Median(loading), "ms");
    for (int path = 0; path < kPaths; ++path) {
      const std::string name = prefix + kNames[path];
      Print(name + "p50_ms", Median(total[path]), "ms");
      Print(name + "p90_ms", Percentile(total[path], 0.9), "ms");
      Print(name + "cpu_p50_ms", Median(cpu[path]), "ms");
      Print(name + "matching_p50_ms", Median(matching[path]), "ms");
      Print(name + "ransac_p50_ms", Median(ransac[path]), "ms");
    }
    Print(prefix + "same_top1", 100.0 * same_top1 / std::max(1, queries), "%");
    Print(prefix + "same_ranking", 100.0 * same_ranking / std::max(1, queries), "%");
    Print(prefix + "inlier_mean_abs_diff", inlier_diff_sum / std::max(1, pairs), "inliers");
    Print(prefix + "inlier_mean_old", inlier_old_sum / std::max(1, pairs), "inliers");
    Print(prefix + "inlier_mean_new", inlier_new_sum / std::max(1, pairs), "inliers");
    Print(prefix + "verified_old", verified_old, "candidates");
    Print(prefix + "verified_new", verified_new, "candidates");
    Print(prefix + "verified_flips", verified_flips, "candidates");
  }
  return 0;
}
