#include "core/search/geometric_verifier.h"

#include <immintrin.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <numeric>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <optional>
#include <span>
#include <string>
#include <vector>

namespace placedb {

namespace {

// A fundamental matrix needs at least 8 correspondences (OpenCV's RANSAC fits 7-point samples
// but refuses fewer than 8 points).
constexpr int kMinPointsForFundamental = 8;

// The default path's fundamental-matrix fit draws at most this many samples (fewer when
// ransac_max_iterations is lower). Most of the fit's time went to unrelated candidates: a few dozen
// putative matches, about 10 chance inliers, and the full 500 samples because their inlier ratio
// never lets RANSAC's confidence stop it. USAC_FAST's local optimisation refines the best model
// found, so fewer samples give nearly the same count: on 400 CamVid pairs at 2000 ORB
// (placedb-bench-verification's workload) 100 instead of 500 moved the inliers by 0.5 on average
// (of 291), changed the verified decision for 1 pair and no query's re-ranked best, and took the
// fit from 3.9 to 1.4 ms per query (CPU time, p50; at 1000 ORB 0.1 inliers, 1 pair, 1.7 -> 1.1 ms).
constexpr int kUsacMaxIterations = 100;

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

double ElapsedMs(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since)
      .count();
}

// Exhaustive ORB matching, the fast path. Each query feature needs the smallest Hamming distance
// to the candidate features (the lowest candidate position on ties) and the second smallest of
// the multiset: exactly what NearestTwo::Offer over the candidates in order gives.
//
// With AVX-512 (VPOPCNTDQ, VBMI2) the candidate descriptors are laid out in blocks of kLanes as
// 32-bit words (word w of the block's 16 descriptors contiguous), one 512-bit register per word.
// Each lane keeps a key, distance << kPositionBits | candidate position, so that one unsigned
// minimum orders by distance and then by position (the position only grows within a lane, as in
// the one-at-a-time loop); a lane's best and second-best keys are kept by min/max without
// compares or blends. kQueryGroup query descriptors are matched per loaded candidate block. On
// this machine (AMD EPYC, Zen 4) 16 lanes of keys with 2 queries per block took 1.14 ms per
// 2000 x 2000 features against 1.48 ms for the previous 8 lanes of 64-bit distances with index
// blends and one query per block (a micro-benchmark, CPU time, minimum of 12 alternated runs).
constexpr size_t kLanes = 16;
constexpr size_t kWords = Descriptor256::kBytes / 4;  // 32-bit words per descriptor
constexpr int kPositionBits = 23;                     // 256 << 23 still fits in 32 bits
constexpr uint32_t kPositionMask = (1u << kPositionBits) - 1;
constexpr uint32_t kFarKey = 0xFFFFFFFFu;  // a lane that saw nothing: distance 511 > 256
// Below this many candidates in a direct-index node the one-at-a-time loop is used.
constexpr size_t kMinBlocked = 8;

// Offers `candidate_ids` in order, one distance at a time, to nearest[q] of each of `query_ids`
// (the reference; the path without AVX-512).
void NearestScalar(const std::vector<Descriptor256>& query, std::span<const uint32_t> query_ids,
                   const std::vector<Descriptor256>& candidate,
                   std::span<const uint32_t> candidate_ids, std::vector<NearestTwo<int>>& nearest) {
  for (const uint32_t q : query_ids) {
    NearestTwo<int>& n = nearest[q];
    for (const uint32_t c : candidate_ids) {
      n.Offer(HammingDistance(query[q], candidate[c]), c);
    }
  }
}

struct BlockedDescriptors {
  size_t count = 0;
  std::vector<uint32_t> words;  // blocks * kWords * kLanes; lanes past `count` are masked out
};

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define PLACEDB_VERIFIER_AVX512 1

// The descriptors `ids` (in that order) of `descriptors`; a lane's position maps back through
// `ids`.
void Block(const std::vector<Descriptor256>& descriptors, std::span<const uint32_t> ids,
           BlockedDescriptors* blocked) {
  blocked->count = ids.size();
  const size_t blocks = (ids.size() + kLanes - 1) / kLanes;
  blocked->words.assign(blocks * kWords * kLanes, 0);
  for (size_t c = 0; c < ids.size(); ++c) {
    uint32_t words[kWords];
    std::memcpy(words, descriptors[ids[c]].words.data(), sizeof(words));
    uint32_t* lane = blocked->words.data() + (c / kLanes) * kWords * kLanes + c % kLanes;
    for (size_t w = 0; w < kWords; ++w) lane[w * kLanes] = words[w];
  }
}

// Folds `later` (the nearest two among candidates offered after those `n` saw) into `n`, as
// offering them one by one would: a feature listed under two direct-index nodes sees both.
void Fold(const NearestTwo<int>& later, NearestTwo<int>& n) {
  if (later.best < n.best) {
    n.second = std::min(n.best, later.second);
    n.best = later.best;
    n.best_candidate = later.best_candidate;
  } else {
    n.second = std::min(n.second, later.best);
  }
}

constexpr size_t kQueryGroup = 2;

// Merges the lanes' best and second-best keys into one NearestTwo<int>; lane positions map back
// to candidate features through `ids`.
NearestTwo<int> MergeLanes(const uint32_t* best, const uint32_t* second,
                           std::span<const uint32_t> ids) {
  NearestTwo<int> merged;
  size_t winner = 0;
  for (size_t l = 1; l < kLanes; ++l) {
    if (best[l] < best[winner]) winner = l;
  }
  if (best[winner] == kFarKey) return merged;
  merged.best = int(best[winner] >> kPositionBits);
  merged.best_candidate = ids[best[winner] & kPositionMask];
  uint32_t runner_up = second[winner] >> kPositionBits;
  for (size_t l = 0; l < kLanes; ++l) {
    if (l != winner) runner_up = std::min(runner_up, best[l] >> kPositionBits);
  }
  if (runner_up <= uint32_t(Descriptor256::kBits)) merged.second = int(runner_up);
  return merged;
}

#define PLACEDB_AVX512_TARGET __attribute__((target("avx512f,avx512vpopcntdq,avx512vbmi2")))

// One candidate block against `Group` query descriptors (their words at `query_words`, kWords
// each): the keys of the block's lanes (`positions`: each lane's position << (32 -
// kPositionBits); lanes outside `valid` get kFarKey) folded into each query's best and second.
template <size_t Group>
PLACEDB_AVX512_TARGET inline __attribute__((always_inline)) void Step(
    const uint32_t* block, __m512i positions, __mmask16 valid, const uint32_t* const* query_words,
    __m512i* best, __m512i* second) {
  __m512i x[kWords];
  for (size_t w = 0; w < kWords; ++w) x[w] = _mm512_loadu_si512(block + w * kLanes);
  for (size_t g = 0; g < Group; ++g) {
    __m512i count[kWords];
    for (size_t w = 0; w < kWords; ++w) {
      count[w] =
          _mm512_popcnt_epi32(_mm512_xor_si512(x[w], _mm512_set1_epi32(int(query_words[g][w]))));
    }
    const __m512i distance =
        _mm512_add_epi32(_mm512_add_epi32(_mm512_add_epi32(count[0], count[1]),
                                          _mm512_add_epi32(count[2], count[3])),
                         _mm512_add_epi32(_mm512_add_epi32(count[4], count[5]),
                                          _mm512_add_epi32(count[6], count[7])));
    __m512i key = _mm512_shldi_epi32(distance, positions, kPositionBits);
    key = _mm512_mask_mov_epi32(_mm512_set1_epi32(int(kFarKey)), valid, key);
    // Zero-masked forms with a full mask: the plain ones make GCC 12 warn (undefined source).
    second[g] =
        _mm512_maskz_min_epu32(0xFFFF, second[g], _mm512_maskz_max_epu32(0xFFFF, best[g], key));
    best[g] = _mm512_maskz_min_epu32(0xFFFF, best[g], key);
  }
}

template <size_t Group>
PLACEDB_AVX512_TARGET void NearestGroup(const std::vector<Descriptor256>& query,
                                        const uint32_t* group_ids,
                                        const BlockedDescriptors& candidates,
                                        std::span<const uint32_t> candidate_ids,
                                        std::vector<NearestTwo<int>>& nearest) {
  const uint32_t* query_words[Group];
  __m512i best[Group], second[Group];
  for (size_t g = 0; g < Group; ++g) {
    query_words[g] = reinterpret_cast<const uint32_t*>(query[group_ids[g]].words.data());
    best[g] = _mm512_set1_epi32(int(kFarKey));
    second[g] = best[g];
  }
  const size_t full_blocks = candidates.count / kLanes;
  const __m512i step = _mm512_set1_epi32(int(kLanes << (32 - kPositionBits)));
  __m512i positions = _mm512_slli_epi32(
      _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15), 32 - kPositionBits);
  const uint32_t* block = candidates.words.data();
  for (size_t b = 0; b < full_blocks; ++b, block += kWords * kLanes) {
    Step<Group>(block, positions, __mmask16(0xFFFF), query_words, best, second);
    positions = _mm512_add_epi32(positions, step);
  }
  if (const size_t tail = candidates.count % kLanes; tail != 0) {
    Step<Group>(block, positions, __mmask16((1u << tail) - 1u), query_words, best, second);
  }
  for (size_t g = 0; g < Group; ++g) {
    alignas(64) uint32_t lane_best[kLanes], lane_second[kLanes];
    _mm512_store_si512(lane_best, best[g]);
    _mm512_store_si512(lane_second, second[g]);
    Fold(MergeLanes(lane_best, lane_second, candidate_ids), nearest[group_ids[g]]);
  }
}

PLACEDB_AVX512_TARGET void NearestAvx512(const std::vector<Descriptor256>& query,
                                         std::span<const uint32_t> query_ids,
                                         const BlockedDescriptors& candidates,
                                         std::span<const uint32_t> candidate_ids,
                                         std::vector<NearestTwo<int>>& nearest) {
  size_t i = 0;
  for (; i + kQueryGroup <= query_ids.size(); i += kQueryGroup) {
    NearestGroup<kQueryGroup>(query, query_ids.data() + i, candidates, candidate_ids, nearest);
  }
  for (; i < query_ids.size(); ++i) {
    NearestGroup<1>(query, query_ids.data() + i, candidates, candidate_ids, nearest);
  }
}

bool HaveAvx512Popcount() {
  static const bool have = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vpopcntdq") &&
           __builtin_cpu_supports("avx512vbmi2") && std::getenv("PLACEDB_NO_AVX512") == nullptr;
  }();
  return have;
}
#endif

// Offers the candidate features `candidate_ids` (in order) to nearest[q] of each query feature of
// `query_ids`: exactly what NearestTwo::Offer one distance at a time gives.
void NearestAll(const std::vector<Descriptor256>& query, std::span<const uint32_t> query_ids,
                const std::vector<Descriptor256>& candidate,
                std::span<const uint32_t> candidate_ids,
                [[maybe_unused]] BlockedDescriptors* scratch,
                std::vector<NearestTwo<int>>& nearest) {
#ifdef PLACEDB_VERIFIER_AVX512
  if (HaveAvx512Popcount() && candidate_ids.size() <= kPositionMask) {
    Block(candidate, candidate_ids, scratch);
    NearestAvx512(query, query_ids, *scratch, candidate_ids, nearest);
    return;
  }
#endif
  NearestScalar(query, query_ids, candidate, candidate_ids, nearest);
}

// The ORB fast path's nearest neighbours: all pairs (kExhaustive), or the pairs within each
// shared direct-index node (the direct indices already validated).
std::vector<NearestTwo<int>> NearestFast(const FeatureSet& query, const DirectIndex& query_direct,
                                         const FeatureSet& candidate,
                                         const DirectIndex& candidate_direct,
                                         const VerificationConfig& config) {
  std::vector<NearestTwo<int>> nearest(query.size());
  BlockedDescriptors scratch;
  if (config.mode == VerificationMode::kExhaustive) {
    std::vector<uint32_t> query_ids(query.size()), candidate_ids(candidate.size());
    std::iota(query_ids.begin(), query_ids.end(), 0u);
    std::iota(candidate_ids.begin(), candidate_ids.end(), 0u);
    NearestAll(query.descriptors, query_ids, candidate.descriptors, candidate_ids, &scratch,
               nearest);
    return nearest;
  }
  size_t i = 0;
  size_t j = 0;
  while (i < query_direct.node_count() && j < candidate_direct.node_count()) {
    if (query_direct.node_ids[i] < candidate_direct.node_ids[j]) {
      ++i;
    } else if (candidate_direct.node_ids[j] < query_direct.node_ids[i]) {
      ++j;
    } else {
      const std::span<const uint32_t> query_ids = query_direct.features_of(i);
      const std::span<const uint32_t> candidate_ids = candidate_direct.features_of(j);
      if (candidate_ids.size() >= kMinBlocked) {
        NearestAll(query.descriptors, query_ids, candidate.descriptors, candidate_ids, &scratch,
                   nearest);
      } else {
        NearestScalar(query.descriptors, query_ids, candidate.descriptors, candidate_ids, nearest);
      }
      ++i;
      ++j;
    }
  }
  return nearest;
}

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

// The essential matrix between two calibrated views (USAC_FAST), its inliers in `mask`; empty
// when none fits. The threshold is the pixel one over the mean focal length.
cv::Mat FitEssential(const Camera& query_camera, const Camera& candidate_camera,
                     const std::vector<cv::Point2f>& query_points,
                     const std::vector<cv::Point2f>& candidate_points,
                     const VerificationConfig& config, cv::Mat* mask) {
  if (query_points.size() < 5) return {};
  const auto normalised = [](const Camera& camera, const std::vector<cv::Point2f>& points) {
    std::vector<cv::Point2d> pixels(points.begin(), points.end());
    return NormalizePixels(camera, pixels);
  };
  const std::vector<cv::Point2d> q = normalised(query_camera, query_points);
  const std::vector<cv::Point2d> c = normalised(candidate_camera, candidate_points);
  const double focal = MeanFocalLength(query_camera, candidate_camera);
  cv::Mat essential =
      cv::findEssentialMat(q, c, 1.0, cv::Point2d(0, 0), cv::USAC_FAST, config.ransac_confidence,
                           config.ransac_threshold_px / focal, config.ransac_max_iterations, *mask);
  if (essential.rows != 3 || essential.cols != 3) return {};
  return essential;
}

// The inlier count; `pairs` (optional) receives the inliers themselves. The default path fits
// with OpenCV's USAC_FAST (LO-RANSAC with SPRT: it stops a hopeless model early and refines the
// best one), at most kUsacMaxIterations samples for the fundamental matrix; legacy with FM_RANSAC.
// Measured on CamVid (placedb-bench-verification), USAC_PROSAC with the matches ordered by Hamming
// distance was as fast but drifted several times more from the legacy inlier counts. With both
// cameras the model is the essential matrix on undistorted normalised points.
int CountInliers(const std::vector<Keypoint>& query, const std::vector<Keypoint>& candidate,
                 const std::vector<Match>& matches, const VerificationConfig& config,
                 const VerificationCameras& cameras, std::vector<InlierPair>* pairs) {
  if (int(matches.size()) < kMinPointsForFundamental) return 0;
  std::vector<cv::Point2f> query_points;
  std::vector<cv::Point2f> candidate_points;
  query_points.reserve(matches.size());
  candidate_points.reserve(matches.size());
  for (const Match& m : matches) {
    query_points.emplace_back(query[m.query].x, query[m.query].y);
    candidate_points.emplace_back(candidate[m.candidate].x, candidate[m.candidate].y);
  }
  // Matches whose point stays where it is: the same viewpoint (a query with a stored place's own
  // image, a robot standing still) fits the identity, a motion no fundamental matrix pins down:
  // USAC_FAST then finds no model (FM_RANSAC happened to accept one). They are inliers when they
  // outnumber what the fit explains.
  cv::Mat still;
  int still_count = 0;
  if (!config.legacy) {
    // Constructed, not a cv::MatExpr: OpenCV initialises the expression machinery lazily, which
    // ThreadSanitizer reports as a race between concurrent verifications.
    still = cv::Mat(int(matches.size()), 1, CV_8U, cv::Scalar(0));
    const float limit = float(config.ransac_threshold_px * config.ransac_threshold_px);
    for (size_t i = 0; i < matches.size(); ++i) {
      const cv::Point2f d = query_points[i] - candidate_points[i];
      if (d.x * d.x + d.y * d.y <= limit) {
        still.at<uint8_t>(int(i)) = 1;
        ++still_count;
      }
    }
  }
  try {
    cv::Mat mask;
    cv::Mat model;  // the fundamental matrix, or the essential matrix with both cameras
    if (still_count < int(matches.size())) {
      if (cameras.known() && !config.legacy) {
        model = FitEssential(*cameras.query, *cameras.candidate, query_points, candidate_points,
                             config, &mask);
      } else {
        model = cv::findFundamentalMat(
            query_points, candidate_points, config.legacy ? int(cv::FM_RANSAC) : int(cv::USAC_FAST),
            config.ransac_threshold_px, config.ransac_confidence,
            config.legacy ? config.ransac_max_iterations
                          : std::min(config.ransac_max_iterations, kUsacMaxIterations),
            mask);
      }
    }
    if (model.empty() || mask.empty() || cv::countNonZero(mask) < still_count) {
      if (still_count < kMinPointsForFundamental) return 0;
      mask = still;
    }
    const int inliers = cv::countNonZero(mask);
    if (pairs) {
      pairs->reserve(size_t(inliers));
      const uint8_t* inlier = mask.ptr<uint8_t>();
      for (size_t i = 0; i < matches.size(); ++i) {
        if (inlier[i]) pairs->push_back({matches[i].query, matches[i].candidate});
      }
      // In candidate order whatever order the fit saw.
      std::sort(pairs->begin(), pairs->end(),
                [](const InlierPair& a, const InlierPair& b) { return a.candidate < b.candidate; });
    }
    return inliers;
  } catch (const cv::Exception&) {
    // A degenerate configuration (e.g. all points on one spot): only points that stay count.
    if (still_count < kMinPointsForFundamental) return 0;
    if (pairs) {
      for (size_t i = 0; i < matches.size(); ++i) {
        if (still.at<uint8_t>(int(i))) pairs->push_back({matches[i].query, matches[i].candidate});
      }
      std::sort(pairs->begin(), pairs->end(),
                [](const InlierPair& a, const InlierPair& b) { return a.candidate < b.candidate; });
    }
    return still_count;
  }
}

// The verification shared by both descriptor kinds: putative matches by `distance(q, c)` (all
// pairs, or pairs sharing a direct-index node), ratio test, RANSAC fundamental matrix.
// `fast_nearest()` returns the nearest neighbours by a faster route (the same ones), or nullopt.
template <typename Distance, typename DistanceFn, typename FastNearestFn>
Result<VerificationResult> Verify(const std::vector<Keypoint>& query,
                                  const DirectIndex& query_direct,
                                  const std::vector<Keypoint>& candidate,
                                  const DirectIndex& candidate_direct,
                                  const VerificationConfig& config, bool collect_inliers,
                                  const VerificationCameras& cameras, Distance max_distance,
                                  const DistanceFn& distance, const FastNearestFn& fast_nearest) {
  const auto start = std::chrono::steady_clock::now();
  std::vector<NearestTwo<Distance>> nearest(query.size());
  std::optional<std::vector<NearestTwo<Distance>>> fast;
  if (config.mode == VerificationMode::kDirectIndex) {
    if (query_direct.levels_up != config.levels_up ||
        candidate_direct.levels_up != config.levels_up) {
      return Status::InvalidArgument(
          "direct index levels_up (query " + std::to_string(query_direct.levels_up) +
          ", candidate " + std::to_string(candidate_direct.levels_up) +
          ") must equal verification.levels_up = " + std::to_string(config.levels_up));
    }
    PLACEDB_RETURN_IF_ERROR(ValidateDirectIndex(query_direct, query.size(), "query"));
    PLACEDB_RETURN_IF_ERROR(ValidateDirectIndex(candidate_direct, candidate.size(), "candidate"));
  }
  if (!config.legacy) fast = fast_nearest();
  if (fast) {
    nearest = std::move(*fast);
  } else if (config.mode == VerificationMode::kExhaustive) {
    for (uint32_t q = 0; q < query.size(); ++q) {
      for (uint32_t c = 0; c < candidate.size(); ++c) nearest[q].Offer(distance(q, c), c);
    }
  } else {
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
  result.matching_ms = ElapsedMs(start);
  const auto fit = std::chrono::steady_clock::now();
  result.putative_matches = int(matches.size());
  result.inliers = CountInliers(query, candidate, matches, config, cameras,
                                collect_inliers ? &result.inlier_pairs : nullptr);
  result.verified = result.inliers >= config.min_inliers;
  result.ransac_ms = ElapsedMs(fit);
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
                                        const VerificationConfig& config, bool collect_inliers,
                                        const VerificationCameras& cameras) {
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

  return Verify<int>(
      query.keypoints, query_direct, candidate.keypoints, candidate_direct, config, collect_inliers,
      cameras, config.max_hamming,
      [&](uint32_t q, uint32_t c) {
        return HammingDistance(query.descriptors[q], candidate.descriptors[c]);
      },
      [&] {
        return std::optional<std::vector<NearestTwo<int>>>(
            NearestFast(query, query_direct, candidate, candidate_direct, config));
      });
}

// Putative matches by L2 distance (max_hamming does not apply), then RANSAC.
Result<VerificationResult> VerifyFloat(const FloatFeatureSet& query,
                                       const DirectIndex& query_direct,
                                       const FloatFeatureSet& candidate,
                                       const DirectIndex& candidate_direct,
                                       const VerificationConfig& config, bool collect_inliers,
                                       const VerificationCameras& cameras) {
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
  return Verify<float>(
      query.keypoints, query_direct, candidate.keypoints, candidate_direct, config, collect_inliers,
      cameras, std::numeric_limits<float>::infinity(),
      [&](uint32_t q, uint32_t c) {
        const float* a = query.descriptor(q).data();
        const float* b = candidate.descriptor(c).data();
        float sum = 0;
        for (int k = 0; k < kSiftDimensions; ++k) sum += (a[k] - b[k]) * (a[k] - b[k]);
        return std::sqrt(sum);
      },
      [] { return std::optional<std::vector<NearestTwo<float>>>(); });
}

}  // namespace

Result<VerificationResult> VerifyGeometry(const LocalFeatures& query,
                                          const DirectIndex& query_direct,
                                          const LocalFeatures& candidate,
                                          const DirectIndex& candidate_direct,
                                          const VerificationConfig& config, bool collect_inliers,
                                          const VerificationCameras& cameras) {
  PLACEDB_RETURN_IF_ERROR(ValidateVerificationConfig(config));
  if (config.mode == VerificationMode::kDisabled) return VerificationResult{};
  if (query.orb() && candidate.orb()) {
    return VerifyBinary(*query.orb(), query_direct, *candidate.orb(), candidate_direct, config,
                        collect_inliers, cameras);
  }
  if (query.sift() && candidate.sift()) {
    return VerifyFloat(*query.sift(), query_direct, *candidate.sift(), candidate_direct, config,
                       collect_inliers, cameras);
  }
  return Status::InvalidArgument(std::string("cannot verify ") + FeatureTypeName(query.type()) +
                                 " features against " + FeatureTypeName(candidate.type()) +
                                 " features");
}

}  // namespace placedb
