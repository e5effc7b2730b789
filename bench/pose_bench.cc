// Issue 32: what a relative pose costs per verified candidate, beside what verifying it costs.
//
// Workload: the slambook2 RGB-D frames (640x480, ../shared/data/slambook2-rgbd), ORB at --orb
// features (1000), each keypoint's depth from its frame's depth image (3x3 median, millimetres).
// Every ordered pair of frames is a (query, candidate) match: the baseline is the exhaustive
// geometric verification of the pair (core/search/geometric_verifier.h, putative matching + the
// fundamental-matrix fit, collecting the inlier pairs), and for the candidates it verifies the
// pose from those inlier pairs: PnP with the candidate's depth (RGB-D), PnP with both frames'
// depths (the joint refinement) and the essential matrix (monocular, depth ignored). Each round
// runs the three alternately over all pairs, --rounds rounds; figures are the median round's mean
// per verified candidate.
//
// Usage: placedb-bench-pose [--orb 1000] [--rounds 31]
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "bench/bench_output.h"
#include "core/pose/relative_pose.h"
#include "core/search/geometric_verifier.h"
#include "tools/rgbd_data.h"

using namespace placedb;

int main(int argc, char** argv) {
  int orb = 1000, rounds = 31;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (std::strcmp(argv[i], "--orb") == 0) {
      orb = std::atoi(argv[i + 1]);
    } else if (std::strcmp(argv[i], "--rounds") == 0) {
      rounds = std::atoi(argv[i + 1]);
    } else {
      std::fprintf(stderr, "usage: placedb-bench-pose [--orb N] [--rounds N]\n");
      return 2;
    }
  }
  const auto frames = rgbd::SlambookFrames();
  if (frames.size() != 5) {
    std::fprintf(stderr, "missing %s/data/slambook2-rgbd\n", rgbd::SharedDir().c_str());
    return 1;
  }
  const CameraIntrinsics k = rgbd::SlambookIntrinsics();
  const Camera camera = PinholeCamera(640, 480, k.fx, k.fy, k.cx, k.cy);
  OrbConfig config;
  config.max_features = orb;
  std::vector<FeatureSet> features;
  std::vector<std::vector<float>> depths;
  for (const auto& frame : frames) {
    auto extracted = ExtractOrb(cv::imread(frame.image_path, cv::IMREAD_GRAYSCALE), config);
    auto metres = rgbd::ReadDepthMetres(frame.depth_path);
    if (!extracted.ok() || !metres.ok()) {
      std::fprintf(stderr, "cannot read %s\n", frame.name.c_str());
      return 1;
    }
    depths.push_back(SampleFeatureDepths(*metres, 640, 480, extracted->keypoints, 1));
    features.push_back(std::move(extracted).value());
  }

  VerificationConfig verification;
  verification.mode = VerificationMode::kExhaustive;
  RelativePoseConfig essential;
  essential.method = PoseMethod::kEssential;
  std::vector<double> verify_ms, pnp_ms, joint_ms, essential_ms;
  int pairs = 0, verified = 0, pnp_ok = 0, joint_ok = 0, essential_ok = 0;
  double inliers = 0, keypoints = 0;
  for (int round = 0; round < rounds; ++round) {
    double verify_sum = 0, pnp_sum = 0, joint_sum = 0, essential_sum = 0;
    int round_verified = 0;
    for (size_t q = 0; q < features.size(); ++q) {
      for (size_t c = 0; c < features.size(); ++c) {
        if (q == c) continue;
        double start = bench::NowMs();
        auto result = VerifyGeometry(features[q], {}, features[c], {}, verification, true);
        verify_sum += bench::NowMs() - start;
        if (!result.ok()) return 1;
        if (round == 0) {
          ++pairs;
          keypoints += double(features[q].size() + features[c].size()) / 2;
        }
        if (!result->verified) continue;
        ++round_verified;
        std::vector<KeypointMatch> matches;
        for (const auto& pair : result->inlier_pairs)
          matches.push_back({pair.query, pair.candidate});
        const PoseFrame query{camera, features[q].keypoints, {}};
        const PoseFrame place{camera, features[c].keypoints, depths[c]};
        start = bench::NowMs();
        auto pnp = EstimateRelativePose(query, place, matches);
        pnp_sum += bench::NowMs() - start;
        start = bench::NowMs();
        auto joint =
            EstimateRelativePose({camera, features[q].keypoints, depths[q]}, place, matches);
        joint_sum += bench::NowMs() - start;
        start = bench::NowMs();
        auto mono = EstimateRelativePose(query, place, matches, essential);
        essential_sum += bench::NowMs() - start;
        if (round == 0) {
          ++verified;
          inliers += result->inliers;
          pnp_ok += pnp.ok() ? 1 : 0;
          if (!pnp.ok()) {
            std::fprintf(stderr, "query %zu candidate %zu, PnP: %s\n", q + 1, c + 1,
                         pnp.status().ToString().c_str());
          }
          joint_ok += joint.ok() ? 1 : 0;
          essential_ok += mono.ok() ? 1 : 0;
        }
      }
    }
    if (round_verified == 0) {
      std::fprintf(stderr, "no pair verified\n");
      return 1;
    }
    verify_ms.push_back(verify_sum / round_verified);
    pnp_ms.push_back(pnp_sum / round_verified);
    joint_ms.push_back(joint_sum / round_verified);
    essential_ms.push_back(essential_sum / round_verified);
  }
  const std::string tag = "_orb" + std::to_string(orb);
  bench::Print("pose_pairs" + tag, pairs, "pairs");
  bench::Print("pose_verified_candidates" + tag, verified, "pairs");
  bench::Print("pose_mean_keypoints" + tag, keypoints / pairs, "keypoints");
  bench::Print("pose_mean_verification_inliers" + tag, inliers / verified, "inliers");
  bench::Print("pose_pnp_solved" + tag, pnp_ok, "pairs");
  bench::Print("pose_pnp_both_depths_solved" + tag, joint_ok, "pairs");
  bench::Print("pose_essential_solved" + tag, essential_ok, "pairs");
  // Baseline: exhaustive verification of every pair, per verified candidate.
  bench::Print("verify_exhaustive_per_verified_candidate" + tag, bench::Median(verify_ms), "ms");
  bench::Print("pose_pnp_per_verified_candidate" + tag, bench::Median(pnp_ms), "ms");
  bench::Print("pose_pnp_both_depths_per_verified_candidate" + tag, bench::Median(joint_ms), "ms");
  bench::Print("pose_essential_per_verified_candidate" + tag, bench::Median(essential_ms), "ms");
  return 0;
}
