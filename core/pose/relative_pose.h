// Relative pose of a verified match (issue 32): the rigid transform between the query frame's
// camera and the matched place's camera, with its uncertainty, as a pose-graph back end (g2o,
// GTSAM, Ceres) takes a loop-closure constraint.
//
// Input: each side's Camera (camera.h), its keypoints (pixels, full resolution), optionally one
// depth per keypoint (metres along the optical axis, as RGB-D sensors report it; 0 or NaN = no
// depth for that keypoint), and the matched keypoint index pairs (e.g. geometric verification's
// inlier pairs, core/search/geometric_verifier.h). Distortion is removed first (cameras may
// differ: a fleet's agents need not share one).
//
// Two solvers, chosen per call (RelativePoseConfig::method, kAuto by default):
//   - PnP, metric 6-DoF, when at least `min_inliers` matches have depth on one side: the
//     keypoints with depth are back-projected to 3-D in their camera, cv::solvePnPRansac (P3P
//     minimal samples, cheaper than AP3P here at the same accuracy; `ransac_threshold_px` on
//     the other side's reprojection) finds the pose and its inliers, then cv::solvePnPRefineLM
//     refines it on the inliers; the inliers are re-selected at the refined pose and refined once
//     more; a last Gauss-Newton refinement weighs each reprojection by its keypoint's pyramid scale
//     (`octave_scale_factor`). With depth only on the query side the inverse problem is solved (3-D
//     in the query, 2-D in the place), which yields the same transform directly. With depth on both
//     sides, the side with more matched depths carries the RANSAC (the place on a tie) and the
//     other side's depths join the last refinement (both reprojections, inliers re-selected at each
//     step). On slambook2 (docs/poses.md) the weighting and the joint refinement bring the worst
//     translation error from 11.8 cm (one side's depth, unweighted) to 7.3 cm (both depths).
//   - Essential matrix, monocular: both sides normalised (intrinsics and distortion removed),
//     cv::findEssentialMat (5-point samples in OpenCV's USAC with MAGSAC++: on the synthetic test
//     a third of plain RANSAC's rotation error; the threshold in pixels scaled by the focal
//     length) and cv::recoverPose (the cheirality check), then Levenberg-Marquardt on the
//     inliers' Sampson distances: rotation and translation direction; `metric` is false and the
//     translation has unit length (the scale is unknown). A pose its own information leaves
//     loose (`max_rotation_sigma_deg`, `max_direction_sigma_deg`) is refused: too little
//     parallax for two views to say where the camera went.
//
// Convention, once for the whole module:
//   transform = T_place_query, the 4x4 rigid transform (row-major) that maps a point expressed in
//   the QUERY camera's frame into the PLACE camera's frame: p_place = R * p_query + t. Its
//   translation is the query camera's centre seen from the place camera. Camera frames are
//   OpenCV's: x right, y down, z forward. With camera-to-world poses T_w_place and T_w_query (TUM
//   and slambook style), T_place_query = T_w_place^-1 * T_w_query.
//
//   information = the 6x6 inverse covariance (row-major) of a perturbation on the right,
//   T_place_query = T_estimate * [Exp(dtheta) | dt], in the order [dt (metres, query frame),
//   dtheta (rotation vector, radians)]: translation first, as g2o's EDGE_SE3:QUAT. (g2o's rotation
//   error is the quaternion's vector part, about dtheta / 2: multiply the rotation rows and
//   columns by 2 to write it there.) It is J^T J / sigma^2 over the inliers, J the Jacobian of the
//   pixel residuals at the solution and sigma^2 their variance estimated from the same residuals
//   (not below `min_pixel_sigma`^2; PnP's residuals are divided by their keypoints' scales). The
//   3-D points are taken as exact: depth noise is not in it.
//   For the essential solver the residual is the Sampson distance and the translation rows
//   refer to the unit-length translation: the matrix is singular along the translation itself
//   (the scale is unobservable) and meaningful only as a 5-DoF constraint.
//
// Errors are values: INVALID_ARGUMENT for malformed input, naming the field (a camera field,
// "place.depth_m has 10 values for 12 keypoints", "matches[3].query = 900 ...");
// FAILED_PRECONDITION when the input is well-formed but yields no pose (too few matches or matches
// with depth, too few inliers, a degenerate configuration); the caller keeps the match without a
// pose. Deterministic: OpenCV's RANSAC seeds its generator the same way on every call.
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/features/orb_features.h"
#include "core/pose/camera.h"

namespace placedb {

// One side of the match: a view of the caller's arrays (kept alive for the call).
struct PoseFrame {
  Camera camera;
  std::span<const Keypoint> keypoints;  // only x, y are used
  std::span<const float> depth_m;       // empty, or exactly one per keypoint
};

// A matched pair: keypoint indices into the query's and the place's keypoints.
struct KeypointMatch {
  uint32_t query = 0;
  uint32_t place = 0;
  bool operator==(const KeypointMatch&) const = default;
};

enum class PoseMethod {
  kAuto,       // PnP with enough depth on either side, else the essential matrix
  kPnp,        // metric only: FAILED_PRECONDITION without enough depth
  kEssential,  // ignore depth: rotation + translation direction
};

// Which solver produced a pose.
enum class PoseSolver {
  kPnpPlaceDepth,  // RANSAC on 3-D from the place's depth, reprojected into the query image
  kPnpQueryDepth,  // RANSAC on 3-D from the query's depth, reprojected into the place image
  kEssential,
};
const char* PoseSolverName(PoseSolver solver);  // "pnp_place_depth", "pnp_query_depth", "essential"

struct RelativePoseConfig {
  PoseMethod method = PoseMethod::kAuto;
  // Fewer inliers (or fewer usable matches to start with) is FAILED_PRECONDITION. PnP needs 4
  // points and the 5-point essential solver 5; this keeps a margin against chance agreements.
  int min_inliers = 12;
  // RANSAC inlier threshold in pixels: reprojection error (PnP) or Sampson distance (essential,
  // converted with the mean focal length of both cameras).
  double ransac_threshold_px = 3.0;
  double ransac_confidence = 0.999;
  int ransac_max_iterations = 500;
  // Depths outside [min_depth_m, max_depth_m] count as none (sensor limits, far noisy readings).
  float min_depth_m = 0.1f;
  float max_depth_m = 12.0f;
  // Floor of the residual standard deviation used for the information matrix (pixels), so that
  // a lucky fit with tiny residuals does not claim an absurd certainty.
  double min_pixel_sigma = 0.5;
  // The features' pyramid scale factor (ORB's OrbConfig::scale_factor, 1.2 by default; 2 for
  // SIFT's octaves; 1 = no weighting). PnP's final refinement divides each reprojection error by
  // the keypoint's scale, factor^octave, and scales its inlier threshold alike: a keypoint found
  // on a coarser level is localised that much less precisely (ORB-SLAM's weighting).
  double octave_scale_factor = 1.2;
  // The essential solver refuses (FAILED_PRECONDITION) a pose whose information leaves the
  // rotation or the translation's direction more uncertain than this at one sigma (degrees): a
  // weak two-view geometry. On slambook2's pairs 4-7 degrees apart the information says 0.03-0.06
  // and 0.4 degrees; on the fundamental matrix's inliers, the wide pairs it refused (13-25
  // degrees, 1-2 m, 57-101 inliers) were 1.2-11 degrees off in rotation and 5-29 in direction
  // (docs/poses.md).
  double max_rotation_sigma_deg = 0.5;
  double max_direction_sigma_deg = 2.0;
};

// INVALID_ARGUMENT naming the field: thresholds and confidence in range, min_inliers >= 5, ...
Status ValidateRelativePoseConfig(const RelativePoseConfig& config);

struct RelativePose {
  std::array<double, 16> transform{1, 0, 0, 0, 0, 1, 0, 0,
                                   0, 0, 1, 0, 0, 0, 0, 1};  // T_place_query
  bool metric = false;  // true: translation in metres (PnP); false: unit direction (essential)
  PoseSolver solver = PoseSolver::kEssential;
  int correspondences = 0;  // matches the solver used (PnP: those with depth on either side)
  int inliers = 0;
  std::vector<uint32_t> inlier_indices;  // indices into the matches, ascending
  // RMS over the inliers, pixels: reprojection error (PnP, in the image the 3-D points project
  // into; both directions' residuals with depth on both sides) or
  // Sampson distance (essential: the first-order two-view reprojection error).
  double rms_error_px = 0;
  std::array<double, 36> information{};  // 6x6 row-major, [dt, dtheta] (see the header comment)

  double at(int row, int col) const { return transform[row * 4 + col]; }
  std::array<double, 3> translation() const { return {at(0, 3), at(1, 3), at(2, 3)}; }
  // The rotation as a unit quaternion {qx, qy, qz, qw}, qw >= 0 (Pose's order in the pipeline).
  std::array<double, 4> quaternion() const;
  // The rotation angle, degrees.
  double rotation_deg() const;
};

// The relative pose T_place_query of `matches` between `query` and `place` (see the header
// comment). INVALID_ARGUMENT: a camera (fields "query.camera.fx", ...), a depth array of the
// wrong size ("query.depth_m", "place.depth_m") or a negative / infinite depth, a match index out
// of range ("matches[i].query"), a non-finite matched keypoint, a bad config.
Result<RelativePose> EstimateRelativePose(const PoseFrame& query, const PoseFrame& place,
                                          std::span<const KeypointMatch> matches,
                                          const RelativePoseConfig& config = {});

// Helpers for tests and callers: 4x4 row-major products and inverses of rigid transforms, and the
// rotation angle (degrees) and translation-direction angle (degrees) between two transforms.
using Transform = std::array<double, 16>;
Transform ComposeTransforms(const Transform& a, const Transform& b);  // a * b
Transform InvertTransform(const Transform& t);
// T from a translation (x y z) and a unit quaternion (qx qy qz qw; normalised here).
Transform TransformFromTranslationQuaternion(const std::array<double, 3>& t,
                                             const std::array<double, 4>& q);
double RotationErrorDeg(const Transform& a, const Transform& b);   // angle of R_a^T R_b
double TranslationErrorM(const Transform& a, const Transform& b);  // |t_a - t_b|
// Angle between the translations' directions (degrees); 0 when either is zero.
double TranslationDirectionErrorDeg(const Transform& a, const Transform& b);

}  // namespace placedb
