// What carrying the inlier pairs out of geometric verification costs (issue 20's query
// correspondences): exhaustive verification of consecutive RTAB-Map frames, counting only (the
// default path, the same-run baseline) and collecting the pairs, alternating round by round.
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "bench/bench_output.h"
#include "core/features/orb_features.h"
#include "core/search/geometric_verifier.h"
#include "tools/shared_data.h"

int main() {
  using namespace placedb;
  constexpr int kFrames = 20;
  constexpr int kRounds = 31;
  std::vector<FeatureSet> frames;
  for (int frame = 1; frame <= kFrames; ++frame) {
    const cv::Mat image = cv::imread(data::RtabmapFramePath(frame), cv::IMREAD_GRAYSCALE);
    auto features = ExtractOrb(image, OrbConfig{});
    if (image.empty() || !features.ok()) {
      std::fprintf(stderr, "cannot read RTAB-Map frame %d (../shared/data)\n", frame);
      return 1;
    }
    frames.push_back(std::move(features).value());
  }
  VerificationConfig config;
  config.mode = VerificationMode::kExhaustive;
  std::vector<double> counting_ms, collecting_ms;
  long inliers = 0, pairs = 0;
  for (int round = 0; round < kRounds; ++round) {
    // Alternating which goes first, so neither always runs on a warmer cache.
    for (const bool second : {false, true}) {
      const bool collect = second != (round % 2 == 1);
      const double start = bench::NowMs();
      for (int i = 0; i + 1 < kFrames; ++i) {
        auto verified = VerifyGeometry(frames[i], {}, frames[i + 1], {}, config, collect);
        if (!verified.ok()) return 1;
        if (collect && round == 0) {
          inliers += verified->inliers;
          pairs += long(verified->inlier_pairs.size());
        }
      }
      (collect ? collecting_ms : counting_ms).push_back((bench::NowMs() - start) / (kFrames - 1));
    }
  }
  if (pairs != inliers) {
    std::fprintf(stderr, "collected %ld pairs for %ld inliers\n", pairs, inliers);
    return 1;
  }
  const double counting = bench::Median(counting_ms);
  const double collecting = bench::Median(collecting_ms);
  bench::Print("verify_exhaustive_count_only", counting, "ms");
  bench::Print("verify_exhaustive_collect_inliers", collecting, "ms");
  bench::Print("collect_inliers_overhead", 100.0 * (collecting - counting) / counting, "%");
  bench::Print("mean_inliers_per_pair", double(inliers) / (kFrames - 1), "inliers");
  return 0;
}
