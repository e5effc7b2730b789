// Issue 31: what re-ranking the 10 best candidates costs per query, split into feature loading,
// putative matching and the robust fit, for the default verifier and the one before issue 31
// (VerificationConfig::legacy: one Hamming distance at a time, OpenCV FM_RANSAC) in the same run.
//
// Workload: CamVid frames (480x360), every other frame a database place and the others queries,
// ORB at each --orb budget, the default vocabulary; each query's 10 best places by BoW score
// (verification off) are its candidates, verified exhaustively ("Geo-6"), one thread. Feature
// loading is decoding each candidate's stored features value and BoW value (core/storage/codec.h,
// what RocksPayloadStore::Get decodes; the RocksDB read itself is not included). Each query runs
// the old and the new path alternately, --rounds times, keeping each one's fastest. Figures are
// medians (p50) and p90 over the queries of the sum over their 10 candidates; agreement lines
// compare the new path's ranking with the old one's on the same candidates.
//
// Usage: placedb-bench-verification [--vocabulary FILE] [--queries N] [--orb 1000,2000]
//        [--rounds N]
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
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
  double loading = 0, matching = 0, ransac = 0, total = 0;
};

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
    Split old_split, new_split;
    std::vector<double> old_total, new_total, old_matching, new_matching, old_ransac, new_ransac,
        loading;
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
      std::vector<VerificationResult> results[2];
      Split best[2] = {{1e30, 1e30, 1e30, 1e30}, {1e30, 1e30, 1e30, 1e30}};
      for (int r = 0; r < rounds; ++r) {
        for (int path = 0; path < 2; ++path) {
          VerificationConfig verification;
          verification.mode = VerificationMode::kExhaustive;
          verification.legacy = path == 0;
          Split split;
          std::vector<VerificationResult> got;
          const double start = NowMs();
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
          if (split.total < best[path].total) best[path] = split;
          results[path] = std::move(got);
        }
      }
      old_total.push_back(best[0].total);
      old_matching.push_back(best[0].matching);
      old_ransac.push_back(best[0].ransac);
      new_total.push_back(best[1].total);
      new_matching.push_back(best[1].matching);
      new_ransac.push_back(best[1].ransac);
      ++queries;
      const std::vector<size_t> old_rank = Ranking(results[0]);
      const std::vector<size_t> new_rank = Ranking(results[1]);
      if (!candidates.empty() && old_rank[0] == new_rank[0] &&
          results[0][old_rank[0]].verified == results[1][new_rank[0]].verified) {
        ++same_top1;
      }
      if (old_rank == new_rank) ++same_ranking;
      for (size_t i = 0; i < candidates.size(); ++i) {
        ++pairs;
        inlier_diff_sum += std::abs(results[1][i].inliers - results[0][i].inliers);
        inlier_old_sum += results[0][i].inliers;
        inlier_new_sum += results[1][i].inliers;
        verified_old += results[0][i].verified;
        verified_new += results[1][i].verified;
        verified_flips += results[0][i].verified != results[1][i].verified;
      }
    }
    const std::string prefix = "verify10_orb" + std::to_string(budget) + "_";
    Print(prefix + "queries", queries, "queries");
    Print(prefix + "loading_p50_ms", Median(loading), "ms");
    for (int path = 0; path < 2; ++path) {
      const std::string name = prefix + (path == 0 ? "old_" : "new_");
      const auto& total = path == 0 ? old_total : new_total;
      Print(name + "p50_ms", Median(total), "ms");
      Print(name + "p90_ms", Percentile(total, 0.9), "ms");
      Print(name + "matching_p50_ms", Median(path == 0 ? old_matching : new_matching), "ms");
      Print(name + "ransac_p50_ms", Median(path == 0 ? old_ransac : new_ransac), "ms");
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
