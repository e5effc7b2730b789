#include "core/search/geometric_verifier.h"

#include <cmath>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace placedb {

namespace {

// A fundamental matrix needs at least 8 correspondences (OpenCV's RANSAC fits 7-point samples
// but refuses fewer than 8 points).
constexpr int kMinPointsForFundamental = 8;

struct ModeEntry {
  VerificationMode mode;
  const char* name;
};
constexpr ModeEntry kModes[] = {
    {VerificationMode::kDisabled, "disabled"},
    {VerificationMode::kDirectIndex, "direct"},
    {VerificationMode::kExhaustive, "exhaustive"},
};

// Best and second-best distance (Hamming, or L2 for float descriptors) from one query feature to
// the candidate features seen.
template <typename Distance>
struct NearestTwo {
  Distance best = std::numeric_limits<Distance>::max();
  Distance second = std::numeric_limits<Distance>::max();
  uint32_t best_candidate = 0;

  void Offer(Distance distance, uint32_t candidate) {
    if (distance < best) {
      second = best;
      best = distance;
      best_candidate = candidate;
    } else if (distance < second) {
      second = distance;
    }
  }
};

struct Match {
  uint32_t query;
  uint32_t candidate;
};

Status ValidateDirectIndex(const DirectIndex& direct, size_t feature_count, const char* which) {
  const std::string name = std::string(which) + " direct index";
  if (direct.node_ids.empty()) {
    if (!direct.feature_ids.empty() || direct.offsets.size() > 1) {
      return Status::InvalidArgument(name + ": feature_ids or offsets without node_ids");
    }
    return Status::Ok();
  }
  if (direct.offsets.size() != direct.node_ids.size() + 1) {
    return Status::InvalidArgument(name + ": offsets has " + std::to_string(direct.offsets.size()) +
                                   " entries for " + std::to_string(direct.node_ids.size()) +
                                   " nodes; expected one more than nodes");
  }
  if (direct.offsets.front() != 0 || direct.offsets.back() != direct.feature_ids.size()) {
    return Status::InvalidArgument(name + ": offsets must run from 0 to feature_ids.size() (" +
                                   std::to_string(direct.feature_ids.size()) + ")");
  }
  for (size_t i = 0; i < direct.node_ids.size(); ++i) {
    if (direct.offsets[i] > direct.offsets[i + 1]) {
      return Status::InvalidArgument(name + ": offsets[" + std::to_string(i + 1) +
                                     "] is below offsets[" + std::to_string(i) + "]");
    }
    if (i > 0 && direct.node_ids[i] <= direct.node_ids[i - 1]) {
      return Status::InvalidArgument(name + ": node_ids[" + std::to_string(i) +
                                     "] is not above node_ids[" + std::to_string(i - 1) +
                                     "]; node ids must ascend");
    }
  }
  for (size_t i = 0; i < direct.feature_ids.size(); ++i) {
    if (direct.feature_ids[i] >= feature_count) {
      return Status::InvalidArgument(name + ": feature_ids[" + std::to_string(i) + "] = " +
                                     std::to_string(direct.feature_ids[i]) + " but the frame has " +
                                     std::to_string(feature_count) + " features");
    }
  }
  return Status::Ok();
}

// Keeps the unambiguous nearest neighbours within `max_distance`, then only the closest query per
// candidate feature.
template <typename Distance>
std::vector<Match> SelectMatches(const std::vector<NearestTwo<Distance>>& nearest, float ratio,
                                 Distance max_distance, size_t candidate_count) {
  constexpr uint32_t kNone = std::numeric_limits<uint32_t>::max();
  constexpr Distance kUnseen = std::numeric_limits<Distance>::max();
  std::vector<uint32_t> owner(candidate_count, kNone);  // candidate feature -> query feature
  for (uint32_t q = 0; q < nearest.size(); ++q) {
    const NearestTwo<Distance>& n = nearest[q];
    if (n.best == kUnseen || n.best > max_distance) continue;
    if (n.second != kUnseen && !(double(n.best) < double(ratio) * double(n.second))) {
      continue;  // ambiguous: the runner-up is nearly as close
    }
    uint32_t& current = owner[n.best_candidate];
    // Ties keep the lower query index, which was seen first.
    if (current == kNone || n.best < nearest[current].best) current = q;
  }
  std::vector<Match> matches;
  for (uint32_t c = 0; c < candidate_count; ++c) {
    if (owner[c] != kNone) matches.push_back({owner[c], c});
  }
  return matches;
}

// The inlier count; `pairs` (optional) receives the inliers themselves.
int CountFundamentalInliers(const std::vector<Keypoint>& query,
                            const std::vector<Keypoint>& candidate,
                            const std::vector<Match>& matches, const VerificationConfig& config,
                            std::vector<InlierPair>* pairs) {
  if (int(matches.size()) < kMinPointsForFundamental) return 0;
  std::vector<cv::Point2f> query_points;
  std::vector<cv::Point2f> candidate_points;
  query_points.reserve(matches.size());
  candidate_points.reserve(matches.size());
  for (const Match& m : matches) {
    query_points.emplace_back(query[m.query].x, query[m.query].y);
    candidate_points.emplace_back(candidate[m.candidate].x, candidate[m.candidate].y);
  }
  try {
    cv::Mat mask;
    const cv::Mat fundamental = cv::findFundamentalMat(
        query_points, candidate_points, cv::FM_RANSAC, config.ransac_threshold_px,
        config.ransac_confidence, config.ransac_max_iterations, mask);
    if (fundamental.empty() || mask.empty()) return 0;
    const int inliers = cv::countNonZero(mask);
    if (pairs) {
      pairs->reserve(size_t(inliers));
      const uint8_t* inlier = mask.ptr<uint8_t>();
      for (size_t i = 0; i < matches.size(); ++i) {
        if (inlier[i]) pairs->push_back({matches[i].query, matches[i].candidate});
      }
    }
    return inliers;
  } catch (const cv::Exception&) {
    return 0;  // degenerate configuration (e.g. all points coincide): nothing verified
  }
}

// The verification shared by both descriptor kinds: putative matches by `distance(q, c)` (all
// pairs, or pairs sharing a direct-index node), ratio test, RANSAC fundamental matrix.
template <typename Distance, typename DistanceFn>
Result<VerificationResult> Verify(const std::vector<Keypoint>& query,
                                  const DirectIndex& query_direct,
                                  const std::vector<Keypoint>& candidate,
                                  const DirectIndex& candidate_direct,
                                  const VerificationConfig& config, bool collect_inliers,
                                  Distance max_distance, const DistanceFn& distance) {
  std::vector<NearestTwo<Distance>> nearest(query.size());
  if (config.mode == VerificationMode::kExhaustive) {
    for (uint32_t q = 0; q < query.size(); ++q) {
      for (uint32_t c = 0; c < candidate.size(); ++c) nearest[q].Offer(distance(q, c), c);
    }
  } else {
    if (query_direct.levels_up != config.levels_up ||
        candidate_direct.levels_up != config.levels_up) {
      return Status::InvalidArgument(
          "direct index levels_up (query " + std::to_string(query_direct.levels_up) +
          ", candidate " + std::to_string(candidate_direct.levels_up) +
          ") must equal verification.levels_up = " + std::to_string(config.levels_up));
    }
    PLACEDB_RETURN_IF_ERROR(ValidateDirectIndex(query_direct, query.size(), "query"));
    PLACEDB_RETURN_IF_ERROR(ValidateDirectIndex(candidate_direct, candidate.size(), "candidate"));
    // Both node lists ascend: walk them together and compare features only within shared nodes.
    size_t i = 0;
    size_t j = 0;
    while (i < query_direct.node_count() && j < candidate_direct.node_count()) {
      if (query_direct.node_ids[i] < candidate_direct.node_ids[j]) {
        ++i;
      } else if (candidate_direct.node_ids[j] < query_direct.node_ids[i]) {
        ++j;
      } else {
        for (const uint32_t q : query_direct.features_of(i)) {
          for (const uint32_t c : candidate_direct.features_of(j)) {
            nearest[q].Offer(distance(q, c), c);
          }
        }
        ++i;
        ++j;
      }
    }
  }
  const std::vector<Match> matches =
      SelectMatches(nearest, config.ratio, max_distance, candidate.size());
  VerificationResult result;
  result.putative_matches = int(matches.size());
  result.inliers = CountFundamentalInliers(query, candidate, matches, config,
                                           collect_inliers ? &result.inlier_pairs : nullptr);
  result.verified = result.inliers >= config.min_inliers;
  return result;
}

}  // namespace

const char* VerificationModeName(VerificationMode mode) {
  for (const auto& entry : kModes) {
    if (entry.mode == mode) return entry.name;
  }
  return "unknown";
}

Result<VerificationMode> ParseVerificationMode(const std::string& name) {
  for (const auto& entry : kModes) {
    if (name == entry.name) return entry.mode;
  }
  return Status::InvalidArgument("verification mode: unknown name '" + name +
                                 "'; expected one of disabled, direct, exhaustive");
}

Status ValidateVerificationConfig(const VerificationConfig& config) {
  const std::string prefix = "verification.";
  if (config.mode != VerificationMode::kDisabled && config.mode != VerificationMode::kDirectIndex &&
      config.mode != VerificationMode::kExhaustive) {
    return Status::InvalidArgument(prefix + "mode " + std::to_string(int(config.mode)) +
                                   " is not a verification mode");
  }
  if (config.levels_up < 0) {
    return Status::InvalidArgument(prefix + "levels_up must be >= 0, got " +
                                   std::to_string(config.levels_up));
  }
  if (config.min_inliers < kMinPointsForFundamental) {
    return Status::InvalidArgument(prefix + "min_inliers must be >= 8 (a fundamental matrix " +
                                   "needs 8 points), got " + std::to_string(config.min_inliers));
  }
  if (config.max_hamming < 0 || config.max_hamming > Descriptor256::kBits) {
    return Status::InvalidArgument(prefix + "max_hamming must be in [0, 256], got " +
                                   std::to_string(config.max_hamming));
  }
  if (!(config.ratio > 0.0f && config.ratio <= 1.0f)) {
    return Status::InvalidArgument(prefix + "ratio must be in (0, 1], got " +
                                   std::to_string(config.ratio));
  }
  if (!(config.ransac_threshold_px > 0.0) || !std::isfinite(config.ransac_threshold_px)) {
    return Status::InvalidArgument(prefix + "ransac_threshold_px must be positive, got " +
                                   std::to_string(config.ransac_threshold_px));
  }
  if (!(config.ransac_confidence > 0.0 && config.ransac_confidence < 1.0)) {
    return Status::InvalidArgument(prefix + "ransac_confidence must be in (0, 1), got " +
                                   std::to_string(config.ransac_confidence));
  }
  if (config.ransac_max_iterations < 1) {
    return Status::InvalidArgument(prefix + "ransac_max_iterations must be positive, got " +
                                   std::to_string(config.ransac_max_iterations));
  }
  if (config.candidates < 0) {
    return Status::InvalidArgument(prefix + "candidates must be >= 0 (0 = all), got " +
                                   std::to_string(config.candidates));
  }
  return Status::Ok();
}

namespace {

// Putative matches by Hamming distance (at most max_hamming), then RANSAC.
Result<VerificationResult> VerifyBinary(const FeatureSet& query, const DirectIndex& query_direct,
                                        const FeatureSet& candidate,
                                        const DirectIndex& candidate_direct,
                                        const VerificationConfig& config, bool collect_inliers) {
  if (query.descriptors.size() != query.keypoints.size()) {
    return Status::InvalidArgument("query features: " + std::to_string(query.descriptors.size()) +
                                   " descriptors for " + std::to_string(query.keypoints.size()) +
                                   " keypoints");
  }
  if (candidate.descriptors.size() != candidate.keypoints.size()) {
    return Status::InvalidArgument(
        "candidate features: " + std::to_string(candidate.descriptors.size()) +
        " descriptors for " + std::to_string(candidate.keypoints.size()) + " keypoints");
  }

  return Verify<int>(query.keypoints, query_direct, candidate.keypoints, candidate_direct, config,
                     collect_inliers, config.max_hamming, [&](uint32_t q, uint32_t c) {
                       return HammingDistance(query.descriptors[q], candidate.descriptors[c]);
                     });
}

// Putative matches by L2 distance (max_hamming does not apply), then RANSAC.
Result<VerificationResult> VerifyFloat(const FloatFeatureSet& query,
                                       const DirectIndex& query_direct,
                                       const FloatFeatureSet& candidate,
                                       const DirectIndex& candidate_direct,
                                       const VerificationConfig& config, bool collect_inliers) {
  const auto check = [](const FloatFeatureSet& set, const char* which) {
    if (set.descriptors.size() != set.keypoints.size() * size_t(kSiftDimensions)) {
      return Status::InvalidArgument(
          std::string(which) + " features: " + std::to_string(set.descriptors.size()) +
          " floats for " + std::to_string(set.keypoints.size()) + " keypoints");
    }
    return Status::Ok();
  };
  PLACEDB_RETURN_IF_ERROR(check(query, "query"));
  PLACEDB_RETURN_IF_ERROR(check(candidate, "candidate"));
  // L2 distance, Lowe's ratio test on it; no absolute cap (SIFT distances depend on the scale
  // of the descriptors, the ratio does not).
  return Verify<float>(query.keypoints, query_direct, candidate.keypoints, candidate_direct, config,
                       collect_inliers, std::numeric_limits<float>::infinity(),
                       [&](uint32_t q, uint32_t c) {
                         const float* a = query.descriptor(q).data();
                         const float* b = candidate.descriptor(c).data();
                         float sum = 0;
                         for (int k = 0; k < kSiftDimensions; ++k)
                           sum += (a[k] - b[k]) * (a[k] - b[k]);
                         return std::sqrt(sum);
                       });
}

}  // namespace

Result<VerificationResult> VerifyGeometry(const LocalFeatures& query,
                                          const DirectIndex& query_direct,
                                          const LocalFeatures& candidate,
                                          const DirectIndex& candidate_direct,
                                          const VerificationConfig& config, bool collect_inliers) {
  PLACEDB_RETURN_IF_ERROR(ValidateVerificationConfig(config));
  if (config.mode == VerificationMode::kDisabled) return VerificationResult{};
  if (query.orb() && candidate.orb()) {
    return VerifyBinary(*query.orb(), query_direct, *candidate.orb(), candidate_direct, config,
                        collect_inliers);
  }
  if (query.sift() && candidate.sift()) {
    return VerifyFloat(*query.sift(), query_direct, *candidate.sift(), candidate_direct, config,
                       collect_inliers);
  }
  return Status::InvalidArgument(std::string("cannot verify ") + FeatureTypeName(query.type()) +
                                 " features against " + FeatureTypeName(candidate.type()) +
                                 " features");
}

}  // namespace placedb
