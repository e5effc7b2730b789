// Geometric verification of a candidate match (the paper's Table II "Geom" settings).
//
// Putative correspondences are found by Hamming distance (ORB) or L2 distance (SIFT) with a ratio
// test, either only between
// features that share a direct-index node (kDirectIndex: DBoW2's "level" check, `levels_up`
// counted from the words, so 0 = same word) or between all features (kExhaustive). A fundamental
// matrix is then fitted by RANSAC (OpenCV) and the candidate is verified when its inlier count
// reaches `min_inliers`. When both images' cameras are known (VerificationCameras), the model is
// the essential matrix instead, on undistorted normalised points: 5 degrees of freedom instead of
// 7, so fewer chance agreements between unrelated images, and lens distortion no longer bends the
// epipolar lines the threshold is measured from.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/features/local_features.h"
#include "core/pose/camera.h"
#include "core/vocabulary/bow.h"

namespace placedb {

enum class VerificationMode { kDisabled, kDirectIndex, kExhaustive };

const char* VerificationModeName(VerificationMode mode);
Result<VerificationMode> ParseVerificationMode(
    const std::string& name);  // disabled|direct|exhaustive

struct VerificationConfig {
  VerificationMode mode = VerificationMode::kDisabled;
  int levels_up = 2;  // direct-index level for kDirectIndex
  // Verified when inliers >= this. DBoW2 uses 12; unrelated real image pairs reach 9-10 inliers
  // by chance here, so the default keeps a margin.
  int min_inliers = 15;
  int max_hamming = 64;              // a putative match must be at most this far (of 256 bits)
  float ratio = 0.8f;                // best < ratio * second best, else ambiguous and dropped
  double ransac_threshold_px = 2.0;  // max distance to the epipolar line
  double ransac_confidence = 0.99;
  // The most RANSAC samples. The default path's fundamental-matrix fit (USAC_FAST, which refines
  // its best model) stops at min(this, 100): measured to give nearly the same inliers as 500 in a
  // third of the time (geometric_verifier.cc, kUsacMaxIterations); legacy and the essential
  // matrix use this value as it is.
  int ransac_max_iterations = 500;
  int candidates = 0;  // verify only the best N candidates; 0 = all returned
  // Spatial re-ranking (Philbin et al. 2007): the verified candidates move ahead of the others,
  // most inliers first; the rest keep their BoW order. Off: verification only marks them (what
  // DBoW2 does).
  bool rerank = true;
  // The verifier before issue 31: putative matches one distance at a time and OpenCV's
  // FM_RANSAC. Kept only so that the drift test, the benchmark and placedb-eval can run it beside
  // the default: ORB matching over descriptors blocked 16 at a time, two query descriptors per
  // block (AVX-512 VPOPCNTDQ and VBMI2 when the CPU has them and the environment has no
  // PLACEDB_NO_AVX512, else one distance at a time; the same putative matches bit for bit) and
  // OpenCV's USAC_FAST fit (inlier counts within the tolerance tests/verifier_drift_test.cc
  // states).
  bool legacy = false;
};

Status ValidateVerificationConfig(const VerificationConfig& config);

// One RANSAC inlier: a query feature index and a candidate feature index.
struct InlierPair {
  uint32_t query = 0;
  uint32_t candidate = 0;
  bool operator==(const InlierPair&) const = default;
};

struct VerificationResult {
  int putative_matches = 0;
  int inliers = 0;
  bool verified = false;
  // With `collect_inliers`: the `inliers` pairs, each index used once (else empty).
  std::vector<InlierPair> inlier_pairs;
  // Where the time went (steady clock, milliseconds): putative matching (distances and ratio
  // test) and the robust fit.
  double matching_ms = 0;
  double ransac_ms = 0;
};

// The cameras of the two images, when the caller knows both (a frame's and a stored place's,
// issue 32); either missing means the fundamental matrix. Views: the cameras must outlive the
// call and be valid (Camera::Validate).
struct VerificationCameras {
  const Camera* query = nullptr;
  const Camera* candidate = nullptr;
  bool known() const { return query != nullptr && candidate != nullptr; }
};

// Verifies `candidate` against `query` (features of one family: INVALID_ARGUMENT otherwise).
// Putative matches: ORB by Hamming distance (at most max_hamming), SIFT by L2 distance; both
// with the ratio test. For kDirectIndex both direct indices must have been built at
// config.levels_up (INVALID_ARGUMENT otherwise); kExhaustive ignores them. Fewer than 8
// putative matches means 0 inliers (a fundamental matrix needs 8 points). `collect_inliers`
// also returns the inlier pairs (to draw them); the count is the same either way. With both
// `cameras` (and not `legacy`) the fit is an essential matrix (OpenCV's USAC_FAST on undistorted
// normalised points; the threshold in pixels divided by the mean focal length).
Result<VerificationResult> VerifyGeometry(
    const LocalFeatures& query, const DirectIndex& query_direct, const LocalFeatures& candidate,
    const DirectIndex& candidate_direct, const VerificationConfig& config,
    bool collect_inliers = false, const VerificationCameras& cameras = {});

}  // namespace placedb
