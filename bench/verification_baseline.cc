// See verification_baseline.h: the previous default verifier, copied for the same-run baseline.
#include "bench/verification_baseline.h"

#include <immintrin.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <limits>
#include <numeric>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <span>
#include <vector>

namespace placedb::bench {

namespace {

constexpr int kMinPointsForFundamental = 8;

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

// Exhaustive ORB matching, the fast path. The candidate descriptors are laid out in blocks of
// kLanes (word w of the block's descriptors contiguous), so that one query descriptor is compared
// with kLanes candidates at once. Each lane keeps its own best and second-best (lane l sees
// candidates l, l + kLanes, ... in ascending order, as the one-at-a-time loop does); the lanes are
// merged at the end into exactly what NearestTwo::Offer over all candidates in order gives: the
// smallest distance (lowest index on ties) and the second smallest of the multiset.
constexpr size_t kLanes = 8;

struct BlockedDescriptors {
  size_t count = 0;
  std::vector<uint64_t> words;  // blocks * 4 * kLanes; lanes past `count` are zero (masked out)
};

// The descriptors `ids` (in that order) of `descriptors`; a lane's position maps back through
// `ids`.
void Block(const std::vector<Descriptor256>& descriptors, std::span<const uint32_t> ids,
           BlockedDescriptors* blocked) {
  blocked->count = ids.size();
  const size_t blocks = (ids.size() + kLanes - 1) / kLanes;
  blocked->words.assign(blocks * 4 * kLanes, 0);
  for (size_t c = 0; c < ids.size(); ++c) {
    const size_t block = c / kLanes;
    const size_t lane = c % kLanes;
    for (size_t w = 0; w < 4; ++w) {
      blocked->words[(block * 4 + w) * kLanes + lane] = descriptors[ids[c]].words[w];
    }
  }
}

// Merges per-lane (best, best index, second) into one NearestTwo<int>.
// Lane positions are mapped back to candidate features through `ids`.
NearestTwo<int> MergeLanes(const int64_t* best, const int64_t* index, const int64_t* second,
                           std::span<const uint32_t> ids) {
  NearestTwo<int> merged;
  size_t winner = kLanes;
  for (size_t l = 0; l < kLanes; ++l) {
    if (best[l] > 256) continue;  // the lane saw nothing
    if (winner == kLanes || best[l] < best[winner] ||
        (best[l] == best[winner] && index[l] < index[winner])) {
      winner = l;
    }
  }
  if (winner == kLanes) return merged;
  merged.best = int(best[winner]);
  merged.best_candidate = ids[size_t(index[winner])];
  int64_t runner_up = second[winner];
  for (size_t l = 0; l < kLanes; ++l) {
    if (l != winner && best[l] < runner_up) runner_up = best[l];
  }
  if (runner_up <= 256) merged.second = int(runner_up);
  return merged;
}

// nearest[q] for every q of `query_ids` against the blocked candidates `candidate_ids`.
void NearestScalar(const std::vector<Descriptor256>& query, std::span<const uint32_t> query_ids,
                   const BlockedDescriptors& candidates, std::span<const uint32_t> candidate_ids,
                   std::vector<NearestTwo<int>>& nearest) {
  const size_t blocks = candidates.words.size() / (4 * kLanes);
  for (const uint32_t q : query_ids) {
    int64_t best[kLanes], second[kLanes], index[kLanes];
    std::fill_n(best, kLanes, 1 << 20);
    std::fill_n(second, kLanes, 1 << 20);
    std::fill_n(index, kLanes, 0);
    const uint64_t* words = query[q].words.data();
    for (size_t b = 0; b < blocks; ++b) {
      const uint64_t* block = candidates.words.data() + b * 4 * kLanes;
      for (size_t l = 0; l < kLanes; ++l) {
        const size_t c = b * kLanes + l;
        if (c >= candidates.count) break;
        const int64_t d = std::popcount(words[0] ^ block[l]) +
                          std::popcount(words[1] ^ block[kLanes + l]) +
                          std::popcount(words[2] ^ block[2 * kLanes + l]) +
                          std::popcount(words[3] ^ block[3 * kLanes + l]);
        if (d < best[l]) {
          second[l] = best[l];
          best[l] = d;
          index[l] = int64_t(c);
        } else if (d < second[l]) {
          second[l] = d;
        }
      }
    }
    nearest[q] = MergeLanes(best, index, second, candidate_ids);
  }
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define PLACEDB_VERIFIER_AVX512 1
__attribute__((target("avx512f,avx512vpopcntdq"))) void NearestAvx512(
    const std::vector<Descriptor256>& query, std::span<const uint32_t> query_ids,
    const BlockedDescriptors& candidates, std::span<const uint32_t> candidate_ids,
    std::vector<NearestTwo<int>>& nearest) {
  const size_t blocks = candidates.words.size() / (4 * kLanes);
  const size_t full_blocks = candidates.count / kLanes;
  const __mmask8 tail_mask = __mmask8((1u << (candidates.count % kLanes)) - 1u);
  const __m512i far = _mm512_set1_epi64(1 << 20);
  const __m512i step = _mm512_set1_epi64(int64_t(kLanes));
  const __m512i first_index = _mm512_setr_epi64(0, 1, 2, 3, 4, 5, 6, 7);
  const uint64_t* words = candidates.words.data();
  for (const uint32_t q : query_ids) {
    const __m512i q0 = _mm512_set1_epi64(int64_t(query[q].words[0]));
    const __m512i q1 = _mm512_set1_epi64(int64_t(query[q].words[1]));
    const __m512i q2 = _mm512_set1_epi64(int64_t(query[q].words[2]));
    const __m512i q3 = _mm512_set1_epi64(int64_t(query[q].words[3]));
    __m512i best = far;
    __m512i second = far;
    __m512i best_index = _mm512_setzero_si512();
    __m512i index = first_index;
    for (size_t b = 0; b < blocks; ++b) {
      const uint64_t* block = words + b * 4 * kLanes;
      __m512i d = _mm512_popcnt_epi64(_mm512_xor_si512(q0, _mm512_loadu_si512(block)));
      d = _mm512_add_epi64(
          d, _mm512_popcnt_epi64(_mm512_xor_si512(q1, _mm512_loadu_si512(block + kLanes))));
      d = _mm512_add_epi64(
          d, _mm512_popcnt_epi64(_mm512_xor_si512(q2, _mm512_loadu_si512(block + 2 * kLanes))));
      d = _mm512_add_epi64(
          d, _mm512_popcnt_epi64(_mm512_xor_si512(q3, _mm512_loadu_si512(block + 3 * kLanes))));
      if (b >= full_blocks) d = _mm512_mask_mov_epi64(far, tail_mask, d);
      const __mmask8 closer = _mm512_cmplt_epi64_mask(d, best);
      // second = min(second, max(best, d)), by masks (GCC 12's min/max intrinsics warn).
      const __m512i larger = _mm512_mask_mov_epi64(d, closer, best);
      second = _mm512_mask_mov_epi64(second, _mm512_cmplt_epi64_mask(larger, second), larger);
      best = _mm512_mask_mov_epi64(best, closer, d);
      best_index = _mm512_mask_mov_epi64(best_index, closer, index);
      index = _mm512_add_epi64(index, step);
    }
    alignas(64) int64_t lane_best[kLanes], lane_index[kLanes], lane_second[kLanes];
    _mm512_store_si512(lane_best, best);
    _mm512_store_si512(lane_index, best_index);
    _mm512_store_si512(lane_second, second);
    nearest[q] = MergeLanes(lane_best, lane_index, lane_second, candidate_ids);
  }
}

bool HaveAvx512Popcount() {
  static const bool have = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vpopcntdq") &&
           std::getenv("PLACEDB_NO_AVX512") == nullptr;
  }();
  return have;
}
#endif

// nearest[q] for the query features `query_ids` against the candidate features `candidate_ids`,
// exactly as NearestTwo::Offer over `candidate_ids` in order gives.
void NearestBlocked(const std::vector<Descriptor256>& query, std::span<const uint32_t> query_ids,
                    const std::vector<Descriptor256>& candidate,
                    std::span<const uint32_t> candidate_ids, BlockedDescriptors* scratch,
                    std::vector<NearestTwo<int>>& nearest) {
  Block(candidate, candidate_ids, scratch);
#ifdef PLACEDB_VERIFIER_AVX512
  if (HaveAvx512Popcount()) {
    NearestAvx512(query, query_ids, *scratch, candidate_ids, nearest);
    return;
  }
#endif
  NearestScalar(query, query_ids, *scratch, candidate_ids, nearest);
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

// The inlier count: OpenCV's USAC_FAST fundamental matrix with config.ransac_max_iterations
// samples; matches that stay where they are count when they outnumber what the fit explains.
int CountInliers(const std::vector<Keypoint>& query, const std::vector<Keypoint>& candidate,
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
  // Matches whose point stays where it is: the same viewpoint (a query with a stored place's own
  // image, a robot standing still) fits the identity, a motion no fundamental matrix pins down:
  // USAC_FAST then finds no model (FM_RANSAC happened to accept one). They are inliers when they
  // outnumber what the fit explains.
  cv::Mat still;
  int still_count = 0;
  {
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
    cv::Mat model;  // the fundamental matrix
    if (still_count < int(matches.size())) {
      model = cv::findFundamentalMat(query_points, candidate_points, cv::USAC_FAST,
                                     config.ransac_threshold_px, config.ransac_confidence,
                                     config.ransac_max_iterations, mask);
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

}  // namespace

Result<VerificationResult> VerifyPreviousDefault(const FeatureSet& query,
                                                 const FeatureSet& candidate,
                                                 const VerificationConfig& config) {
  const auto start = std::chrono::steady_clock::now();
  std::vector<NearestTwo<int>> nearest(query.size());
  std::vector<uint32_t> query_ids(query.size()), candidate_ids(candidate.size());
  std::iota(query_ids.begin(), query_ids.end(), 0u);
  std::iota(candidate_ids.begin(), candidate_ids.end(), 0u);
  BlockedDescriptors scratch;
  NearestBlocked(query.descriptors, query_ids, candidate.descriptors, candidate_ids, &scratch,
                 nearest);
  const std::vector<Match> matches =
      SelectMatches(nearest, config.ratio, config.max_hamming, candidate.size());
  VerificationResult result;
  result.matching_ms = ElapsedMs(start);
  const auto fit = std::chrono::steady_clock::now();
  result.putative_matches = int(matches.size());
  result.inliers = CountInliers(query.keypoints, candidate.keypoints, matches, config, nullptr);
  result.verified = result.inliers >= config.min_inliers;
  result.ransac_ms = ElapsedMs(fit);
  return result;
}

}  // namespace placedb::bench
