#include "core/pose/relative_pose.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <opencv2/calib3d.hpp>
#include <sstream>

namespace placedb {

namespace {

std::string Num(double v) {
  std::ostringstream out;
  out << v;
  return out.str();
}

std::string Fixed2(double v) {
  std::ostringstream out;
  out.setf(std::ios::fixed);
  out.precision(2);
  out << v;
  return out.str();
}

using Mat6 = cv::Matx<double, 6, 6>;

cv::Matx33d Skew(const cv::Vec3d& v) {
  return {0, -v[2], v[1], v[2], 0, -v[0], -v[1], v[0], 0};
}

Transform FromRt(const cv::Matx33d& r, const cv::Vec3d& t) {
  return {r(0, 0), r(0, 1), r(0, 2), t[0], r(1, 0), r(1, 1), r(1, 2), t[1],
          r(2, 0), r(2, 1), r(2, 2), t[2], 0,       0,       0,       1};
}

cv::Matx33d RotationOf(const Transform& t) {
  return {t[0], t[1], t[2], t[4], t[5], t[6], t[8], t[9], t[10]};
}

double AngleDeg(const cv::Matx33d& r) {
  const double c = std::clamp((cv::trace(r) - 1) / 2, -1.0, 1.0);
  return std::acos(c) * 180.0 / CV_PI;
}

bool DepthUsable(float d, const RelativePoseConfig& config) {
  return std::isfinite(d) && d >= config.min_depth_m && d <= config.max_depth_m;
}

Status ValidateFrame(const PoseFrame& frame, const char* side) {
  PLACEDB_RETURN_IF_ERROR(frame.camera.Validate(std::string(side) + ".camera"));
  if (!frame.depth_m.empty() && frame.depth_m.size() != frame.keypoints.size()) {
    return Status::InvalidArgument(std::string(side) + ".depth_m has " +
                                   std::to_string(frame.depth_m.size()) + " values for " +
                                   std::to_string(frame.keypoints.size()) +
                                   " keypoints: give one per keypoint (0 = none) or none at all");
  }
  for (size_t i = 0; i < frame.depth_m.size(); ++i) {
    const float d = frame.depth_m[i];
    if (d < 0 || std::isinf(d)) {
      return Status::InvalidArgument(std::string(side) + ".depth_m[" + std::to_string(i) +
                                     "] = " + Num(d) +
                                     ": a depth is a finite distance >= 0 in metres (0 or NaN = "
                                     "none)");
    }
  }
  return Status::Ok();
}

// Pixel residual statistics at a pose: squared residual norms of every correspondence.
struct PnpProblem {
  std::vector<cv::Point3d> object;  // 3-D, in the depth side's camera frame
  std::vector<cv::Point2d> image;   // undistorted pixels in the other side's image
  std::vector<uint32_t> match;      // index into the caller's matches
  cv::Matx33d k;                    // the image side's pinhole intrinsics
  // The image-side keypoint's scale (octave_scale_factor^octave): its localisation error grows
  // with it, so residuals are divided by it (ORB-SLAM weighs its reprojections the same way).
  std::vector<double> scale;
};

template <typename T>
std::vector<T> Pick(const std::vector<T>& values, const std::vector<int>& which) {
  std::vector<T> out;
  out.reserve(which.size());
  for (int i : which) out.push_back(values[i]);
  return out;
}

void StoreInformation(const Mat6& info, RelativePose* pose) {
  for (int r = 0; r < 6; ++r) {
    for (int c = 0; c < 6; ++c) pose->information[r * 6 + c] = info(r, c);
  }
}

Status TooFewInliers(int inliers, int of, const RelativePoseConfig& config, const char* solver) {
  return Status::FailedPrecondition(
      std::string(solver) + ": only " + std::to_string(inliers) + " of " + std::to_string(of) +
      " correspondences agree on a pose (min_inliers " + std::to_string(config.min_inliers) +
      "): degenerate or wrong match");
}

// The matches with a usable depth on the place side (place_depth) or on the query side, as 3-D
// points in that side's camera frame and undistorted pixels in the other side's image.
PnpProblem MakePnpProblem(const PoseFrame& query, const PoseFrame& place,
                          std::span<const KeypointMatch> matches, bool place_depth,
                          const RelativePoseConfig& config) {
  const PoseFrame& depth_side = place_depth ? place : query;
  const PoseFrame& image_side = place_depth ? query : place;
  PnpProblem problem;
  problem.k = image_side.camera.K();
  if (depth_side.depth_m.empty()) return problem;
  std::vector<cv::Point2d> depth_px, image_px;
  std::vector<float> depths;
  for (size_t i = 0; i < matches.size(); ++i) {
    const uint32_t d_index = place_depth ? matches[i].place : matches[i].query;
    const uint32_t i_index = place_depth ? matches[i].query : matches[i].place;
    const float d = depth_side.depth_m[d_index];
    if (!DepthUsable(d, config)) continue;
    depth_px.push_back({depth_side.keypoints[d_index].x, depth_side.keypoints[d_index].y});
    image_px.push_back({image_side.keypoints[i_index].x, image_side.keypoints[i_index].y});
    problem.scale.push_back(std::pow(config.octave_scale_factor,
                                     std::clamp(image_side.keypoints[i_index].octave, 0, 31)));
    depths.push_back(d);
    problem.match.push_back(uint32_t(i));
  }
  const auto rays = NormalizePixels(depth_side.camera, depth_px);
  problem.object.resize(rays.size());
  for (size_t i = 0; i < rays.size(); ++i) {
    problem.object[i] = {rays[i].x * depths[i], rays[i].y * depths[i], double(depths[i])};
  }
  problem.image = UndistortPixels(image_side.camera, image_px);
  return problem;
}

// A set of 3-D -> 2-D correspondences seen from T_place_query = [R | t]: with the place's depth
// the points are in the place frame and reproject into the query (x = R^T (p - t)), with the
// query's depth they are in the query frame and reproject into the place (x = R p + t).
struct PoseState {
  cv::Matx33d r = cv::Matx33d::eye();
  cv::Vec3d t = cv::Vec3d(0, 0, 0);
};

cv::Vec3d ImageSidePoint(const PoseState& s, const cv::Point3d& object, bool place_depth) {
  const cv::Vec3d p(object.x, object.y, object.z);
  return place_depth ? s.r.t() * (p - s.t) : s.r * p + s.t;
}

// Squared reprojection errors divided by the keypoint's scale squared.
std::vector<double> SquaredResiduals(const PnpProblem& p, bool place_depth, const PoseState& s) {
  std::vector<double> out(p.object.size());
  for (size_t i = 0; i < p.object.size(); ++i) {
    const cv::Vec3d x = ImageSidePoint(s, p.object[i], place_depth);
    if (x[2] <= 1e-9) {
      out[i] = std::numeric_limits<double>::infinity();
      continue;
    }
    const double u = p.k(0, 0) * x[0] / x[2] + p.k(0, 2) - p.image[i].x;
    const double v = p.k(1, 1) * x[1] / x[2] + p.k(1, 2) - p.image[i].y;
    out[i] = (u * u + v * v) / (p.scale[i] * p.scale[i]);
  }
  return out;
}

// Adds the inliers' normal equations for the right perturbation [dt, dtheta] of T_place_query
// (header comment) to `h` and `g`.
void Linearize(const PnpProblem& p, bool place_depth, const PoseState& s,
               const std::vector<int>& inliers, Mat6* h, cv::Vec<double, 6>* g) {
  for (int i : inliers) {
    const cv::Vec3d object(p.object[i].x, p.object[i].y, p.object[i].z);
    const cv::Vec3d x = ImageSidePoint(s, p.object[i], place_depth);
    const double iz = 1.0 / x[2];
    const double fx = p.k(0, 0), fy = p.k(1, 1);
    const cv::Vec2d residual(fx * x[0] * iz + p.k(0, 2) - p.image[i].x,
                             fy * x[1] * iz + p.k(1, 2) - p.image[i].y);
    const cv::Matx<double, 2, 3> dproj(fx * iz, 0, -fx * x[0] * iz * iz, 0, fy * iz,
                                       -fy * x[1] * iz * iz);
    cv::Matx33d dx_dt, dx_dtheta;
    if (place_depth) {
      // x = Delta^-1 * x_hat -> dx/ddt = -I, dx/ddtheta = [x]_x.
      dx_dt = -cv::Matx33d::eye();
      dx_dtheta = Skew(x);
    } else {
      // x = R (p + dtheta x p + dt) + t -> R, -R [p]_x.
      dx_dt = s.r;
      dx_dtheta = -(s.r * Skew(object));
    }
    const cv::Matx<double, 2, 3> jt = dproj * dx_dt;
    const cv::Matx<double, 2, 3> jr = dproj * dx_dtheta;
    cv::Matx<double, 2, 6> j;
    for (int row = 0; row < 2; ++row) {
      for (int c = 0; c < 3; ++c) {
        j(row, c) = jt(row, c);
        j(row, c + 3) = jr(row, c);
      }
    }
    const double w = 1.0 / (p.scale[i] * p.scale[i]);
    *h += j.t() * j * w;
    *g += j.t() * residual * w;
  }
}

std::vector<int> Inliers(const std::vector<double>& squared, double threshold2) {
  std::vector<int> out;
  for (int i = 0; i < int(squared.size()); ++i) {
    if (squared[i] <= threshold2) out.push_back(i);
  }
  return out;
}

// `primary`: the correspondences of the side with more depth (RANSAC runs on them); `secondary`:
// those with depth on the other side (empty when it has none), used by the joint refinement.
Result<RelativePose> SolvePnp(const PnpProblem& primary, const PnpProblem& secondary,
                              bool depth_on_place, int correspondences,
                              const RelativePoseConfig& config) {
  const int n = int(primary.object.size());
  cv::Mat rvec, tvec;
  std::vector<int> inliers;
  bool found = false;
  try {
    found =
        cv::solvePnPRansac(primary.object, primary.image, primary.k, cv::noArray(), rvec, tvec,
                           false, config.ransac_max_iterations, float(config.ransac_threshold_px),
                           config.ransac_confidence, inliers, cv::SOLVEPNP_P3P);
  } catch (const cv::Exception& e) {
    return Status::FailedPrecondition(std::string("pnp: degenerate correspondences (") + e.what() +
                                      ")");
  }
  if (!found || int(inliers.size()) < config.min_inliers) {
    return TooFewInliers(int(inliers.size()), n, config, "pnp");
  }
  const double threshold2 = config.ransac_threshold_px * config.ransac_threshold_px;
  // Levenberg-Marquardt on the inliers (OpenCV's), the inliers re-selected at the refined pose,
  // refined once more.
  PoseState state;
  for (int pass = 0; pass < 2; ++pass) {
    cv::solvePnPRefineLM(Pick(primary.object, inliers), Pick(primary.image, inliers), primary.k,
                         cv::noArray(), rvec, tvec);
    cv::Matx33d r = cv::Matx33d::eye();
    cv::Rodrigues(rvec, r);
    const cv::Vec3d t(tvec);
    // The solver maps the 3-D side into the image side: T_query_place with the place's depth.
    state = depth_on_place ? PoseState{r.t(), -(r.t() * t)} : PoseState{r, t};
    std::vector<int> next = Inliers(SquaredResiduals(primary, depth_on_place, state), threshold2);
    if (int(next.size()) < config.min_inliers) {
      return TooFewInliers(int(next.size()), n, config, "pnp");
    }
    if (next == inliers) break;
    inliers = std::move(next);
  }

  // The final refinement: Gauss-Newton with a Levenberg damping over the reprojections divided
  // by their keypoints' scales, of both sides when both have depth (inliers re-selected at each
  // step's pose, the threshold scaled like the residuals).
  std::vector<int> secondary_inliers;
  {
    const double lambda = 1e-4;
    for (int iteration = 0; iteration < 10; ++iteration) {
      inliers = Inliers(SquaredResiduals(primary, depth_on_place, state), threshold2);
      secondary_inliers = Inliers(SquaredResiduals(secondary, !depth_on_place, state), threshold2);
      Mat6 h = Mat6::zeros();
      cv::Vec<double, 6> g = cv::Vec<double, 6>::all(0);
      Linearize(primary, depth_on_place, state, inliers, &h, &g);
      Linearize(secondary, !depth_on_place, state, secondary_inliers, &h, &g);
      Mat6 damped = h;
      for (int d = 0; d < 6; ++d) damped(d, d) *= 1 + lambda;
      cv::Vec<double, 6> delta;
      if (!cv::solve(damped, -g, delta, cv::DECOMP_CHOLESKY)) break;
      cv::Matx33d dr = cv::Matx33d::eye();
      cv::Rodrigues(cv::Vec3d(delta[3], delta[4], delta[5]), dr);
      const cv::Vec3d t_next = state.r * cv::Vec3d(delta[0], delta[1], delta[2]) + state.t;
      const cv::Matx33d r_next = state.r * dr;
      state.r = r_next;
      state.t = t_next;
      if (cv::norm(delta) < 1e-10) break;
    }
    inliers = Inliers(SquaredResiduals(primary, depth_on_place, state), threshold2);
    secondary_inliers = Inliers(SquaredResiduals(secondary, !depth_on_place, state), threshold2);
    if (int(inliers.size()) < config.min_inliers) {
      return TooFewInliers(int(inliers.size()), n, config, "pnp");
    }
  }

  RelativePose pose;
  pose.metric = true;
  pose.solver = depth_on_place ? PoseSolver::kPnpPlaceDepth : PoseSolver::kPnpQueryDepth;
  pose.correspondences = correspondences;
  pose.transform = FromRt(state.r, state.t);
  const auto squared = SquaredResiduals(primary, depth_on_place, state);
  const auto secondary_squared = SquaredResiduals(secondary, !depth_on_place, state);
  double ssr = 0, pixels_ssr = 0;  // scaled (the weighted problem's) and in pixels
  for (int i : inliers) {
    ssr += squared[i];
    pixels_ssr += squared[i] * primary.scale[i] * primary.scale[i];
    pose.inlier_indices.push_back(primary.match[i]);
  }
  for (int i : secondary_inliers) {
    ssr += secondary_squared[i];
    pixels_ssr += secondary_squared[i] * secondary.scale[i] * secondary.scale[i];
    pose.inlier_indices.push_back(secondary.match[i]);
  }
  const int residuals = int(inliers.size() + secondary_inliers.size());
  std::sort(pose.inlier_indices.begin(), pose.inlier_indices.end());
  pose.inlier_indices.erase(std::unique(pose.inlier_indices.begin(), pose.inlier_indices.end()),
                            pose.inlier_indices.end());
  pose.inliers = int(pose.inlier_indices.size());
  pose.rms_error_px = std::sqrt(pixels_ssr / residuals);

  // Information of the right perturbation of T_place_query (header comment).
  const double sigma2 = std::max(ssr / std::max(1, 2 * residuals - 6),
                                 config.min_pixel_sigma * config.min_pixel_sigma);
  Mat6 info = Mat6::zeros();
  cv::Vec<double, 6> unused = cv::Vec<double, 6>::all(0);
  Linearize(primary, depth_on_place, state, inliers, &info, &unused);
  Linearize(secondary, !depth_on_place, state, secondary_inliers, &info, &unused);
  StoreInformation(info * (1.0 / sigma2), &pose);
  return pose;
}

// Sampson distance (pixels) of x_place^T F x_query = 0, F from the pose and both cameras.
double Sampson(const cv::Matx33d& f, const cv::Point2d& q, const cv::Point2d& p) {
  const cv::Vec3d xq(q.x, q.y, 1), xp(p.x, p.y, 1);
  const cv::Vec3d fq = f * xq;
  const cv::Vec3d ftp = f.t() * xp;
  const double e = xp.dot(fq);
  const double d = fq[0] * fq[0] + fq[1] * fq[1] + ftp[0] * ftp[0] + ftp[1] * ftp[1];
  return d > 0 ? e / std::sqrt(d) : 0;
}

cv::Matx33d Fundamental(const cv::Matx33d& r, const cv::Vec3d& t, const cv::Matx33d& kq_inv,
                        const cv::Matx33d& kp_inv) {
  return kp_inv.t() * (Skew(t) * r) * kq_inv;
}

// The normal equations J^T J and J^T s of the inliers' Sampson distances s at [r | t], for the
// right perturbation [dt, dtheta] (numerical Jacobian, central differences).
void SampsonNormalEquations(const std::vector<cv::Point2d>& q_px,
                            const std::vector<cv::Point2d>& p_px, const std::vector<int>& inliers,
                            const cv::Matx33d& kq_inv, const cv::Matx33d& kp_inv,
                            const cv::Matx33d& r, const cv::Vec3d& t, Mat6* h,
                            cv::Vec<double, 6>* g) {
  constexpr double kStep = 1e-6;
  std::array<cv::Matx33d, 6> f_plus, f_minus;
  for (int k = 0; k < 6; ++k) {
    for (int sign = -1; sign <= 1; sign += 2) {
      cv::Vec3d dt(0, 0, 0), dtheta(0, 0, 0);
      (k < 3 ? dt : dtheta)[k % 3] = sign * kStep;
      cv::Matx33d dr = cv::Matx33d::eye();
      cv::Rodrigues(dtheta, dr);
      (sign > 0 ? f_plus : f_minus)[k] = Fundamental(r * dr, r * dt + t, kq_inv, kp_inv);
    }
  }
  const cv::Matx33d f = Fundamental(r, t, kq_inv, kp_inv);
  *h = Mat6::zeros();
  *g = cv::Vec<double, 6>::all(0);
  for (int i : inliers) {
    cv::Vec<double, 6> j;
    for (int k = 0; k < 6; ++k) {
      j[k] = (Sampson(f_plus[k], q_px[i], p_px[i]) - Sampson(f_minus[k], q_px[i], p_px[i])) /
             (2 * kStep);
    }
    *h += j * j.t();
    *g += j * Sampson(f, q_px[i], p_px[i]);
  }
}

// Levenberg-Marquardt on the inliers' Sampson distances from the RANSAC pose (the best minimal
// sample's, not the least-squares one): t kept at unit length (its scale is the one direction no
// residual sees; the damping keeps it still). On the synthetic scenes it takes a third off the
// rotation and direction errors (docs/poses.md).
void RefineEssential(const std::vector<cv::Point2d>& q_px, const std::vector<cv::Point2d>& p_px,
                     const std::vector<int>& inliers, const cv::Matx33d& kq_inv,
                     const cv::Matx33d& kp_inv, cv::Matx33d* r, cv::Vec3d* t, double* ssr) {
  auto cost = [&](const cv::Matx33d& rr, const cv::Vec3d& tt) {
    const cv::Matx33d f = Fundamental(rr, tt, kq_inv, kp_inv);
    double sum = 0;
    for (int i : inliers) {
      const double s = Sampson(f, q_px[i], p_px[i]);
      sum += s * s;
    }
    return sum;
  };
  double current = cost(*r, *t);
  double lambda = 1e-3;
  for (int iteration = 0; iteration < 5; ++iteration) {
    Mat6 h;
    cv::Vec<double, 6> g;
    SampsonNormalEquations(q_px, p_px, inliers, kq_inv, kp_inv, *r, *t, &h, &g);
    bool improved = false;
    while (lambda < 1e6) {
      Mat6 damped = h;
      for (int d = 0; d < 6; ++d) damped(d, d) += lambda * std::max(h(d, d), 1e-12);
      cv::Vec<double, 6> delta;
      if (!cv::solve(damped, -g, delta, cv::DECOMP_SVD)) break;
      cv::Matx33d dr = cv::Matx33d::eye();
      cv::Rodrigues(cv::Vec3d(delta[3], delta[4], delta[5]), dr);
      const cv::Matx33d r_next = *r * dr;
      cv::Vec3d t_next = *r * cv::Vec3d(delta[0], delta[1], delta[2]) + *t;
      t_next *= 1.0 / cv::norm(t_next);
      const double next = cost(r_next, t_next);
      if (next < current) {
        *r = r_next;
        *t = t_next;
        improved = current - next > 1e-6 * current;
        current = next;
        lambda = std::max(lambda / 10, 1e-9);
        break;
      }
      lambda *= 10;
    }
    if (!improved) break;
  }
  *ssr = current;
}

// The 1-sigma uncertainty (degrees) of the rotation and of the translation's direction that an
// essential pose's information claims: the root of the covariance's rotation and translation
// blocks' traces (pseudo-inverse: the unit translation's length is not a degree of freedom).
struct EssentialUncertainty {
  double rotation_deg = 0;
  double direction_deg = 0;
};
EssentialUncertainty UncertaintyOf(const Mat6& information) {
  cv::Mat covariance;
  cv::invert(cv::Mat(information), covariance, cv::DECOMP_SVD);
  const auto trace = [&](int from) {
    return covariance.at<double>(from, from) + covariance.at<double>(from + 1, from + 1) +
           covariance.at<double>(from + 2, from + 2);
  };
  return {std::sqrt(std::max(0.0, trace(3))) * 180 / CV_PI,
          std::sqrt(std::max(0.0, trace(0))) * 180 / CV_PI};
}

Result<RelativePose> SolveEssential(const PoseFrame& query, const PoseFrame& place,
                                    std::span<const KeypointMatch> matches,
                                    const RelativePoseConfig& config) {
  const int n = int(matches.size());
  if (n < std::max(5, config.min_inliers)) {
    return Status::FailedPrecondition("essential: " + std::to_string(n) +
                                      " matches are too few for a relative pose (min_inliers " +
                                      std::to_string(config.min_inliers) + ")");
  }
  std::vector<cv::Point2d> q_px(n), p_px(n);
  for (int i = 0; i < n; ++i) {
    const Keypoint& a = query.keypoints[matches[i].query];
    const Keypoint& b = place.keypoints[matches[i].place];
    q_px[i] = {a.x, a.y};
    p_px[i] = {b.x, b.y};
  }
  q_px = UndistortPixels(query.camera, q_px);
  p_px = UndistortPixels(place.camera, p_px);
  std::vector<cv::Point2d> q_n(n), p_n(n);
  for (int i = 0; i < n; ++i) {
    q_n[i] = {(q_px[i].x - query.camera.cx) / query.camera.fx,
              (q_px[i].y - query.camera.cy) / query.camera.fy};
    p_n[i] = {(p_px[i].x - place.camera.cx) / place.camera.fx,
              (p_px[i].y - place.camera.cy) / place.camera.fy};
  }
  const double focal = MeanFocalLength(query.camera, place.camera);
  cv::Mat mask, e_mat;
  cv::Matx33d r;
  cv::Vec3d t;
  try {
    e_mat = cv::findEssentialMat(q_n, p_n, 1.0, cv::Point2d(0, 0), cv::USAC_MAGSAC,
                                 config.ransac_confidence, config.ransac_threshold_px / focal,
                                 config.ransac_max_iterations, mask);
    if (e_mat.rows != 3 || e_mat.cols != 3) {
      return Status::FailedPrecondition("essential: no essential matrix fits the " +
                                        std::to_string(n) + " matches (degenerate)");
    }
    cv::Mat r_mat, t_mat;
    cv::recoverPose(e_mat, q_n, p_n, r_mat, t_mat, 1.0, cv::Point2d(0, 0), mask);
    r = cv::Matx33d(r_mat);
    t = cv::Vec3d(t_mat);
  } catch (const cv::Exception& e) {
    return Status::FailedPrecondition(std::string("essential: degenerate correspondences (") +
                                      e.what() + ")");
  }
  // Inliers: within the Sampson threshold at the recovered pose and in front of both cameras
  // (recoverPose's mask).
  const cv::Matx33d f = Fundamental(r, t, query.camera.K().inv(), place.camera.K().inv());
  RelativePose pose;
  pose.metric = false;
  pose.solver = PoseSolver::kEssential;
  pose.correspondences = n;
  double ssr = 0;
  std::vector<int> inliers;
  for (int i = 0; i < n; ++i) {
    if (mask.at<uchar>(i) == 0) continue;
    const double s = Sampson(f, q_px[i], p_px[i]);
    if (std::abs(s) > config.ransac_threshold_px) continue;
    inliers.push_back(i);
    ssr += s * s;
  }
  if (int(inliers.size()) < config.min_inliers) {
    return TooFewInliers(int(inliers.size()), n, config, "essential");
  }
  RefineEssential(q_px, p_px, inliers, query.camera.K().inv(), place.camera.K().inv(), &r, &t,
                  &ssr);
  pose.inliers = int(inliers.size());
  for (int i : inliers) pose.inlier_indices.push_back(uint32_t(i));
  pose.rms_error_px = std::sqrt(ssr / pose.inliers);
  pose.transform = FromRt(r, t);

  // Information: the Sampson distances' normal equations at the refined pose over their variance
  // (the translation rows refer to the unit-length translation).
  const double sigma2 = std::max(ssr / std::max(1, pose.inliers - 5),
                                 config.min_pixel_sigma * config.min_pixel_sigma);
  Mat6 info;
  cv::Vec<double, 6> unused;
  SampsonNormalEquations(q_px, p_px, inliers, query.camera.K().inv(), place.camera.K().inv(), r, t,
                         &info, &unused);
  info *= 1.0 / sigma2;
  // A weak two-view geometry (little parallax, few or clustered inliers) fits its inliers as well
  // as a good one but leaves the pose loose; a pose graph would take it at its word.
  const EssentialUncertainty uncertainty = UncertaintyOf(info);
  if (uncertainty.rotation_deg > config.max_rotation_sigma_deg ||
      uncertainty.direction_deg > config.max_direction_sigma_deg) {
    return Status::FailedPrecondition(
        "essential: a weak two-view geometry (" + std::to_string(pose.inliers) +
        " inliers leave the rotation uncertain by " + Fixed2(uncertainty.rotation_deg) +
        " deg and the translation's direction by " + Fixed2(uncertainty.direction_deg) +
        " deg at one sigma; limits " + Num(config.max_rotation_sigma_deg) + " and " +
        Num(config.max_direction_sigma_deg) + " deg): too little parallax for a monocular pose");
  }
  StoreInformation(info, &pose);
  return pose;
}

}  // namespace

const char* PoseSolverName(PoseSolver solver) {
  switch (solver) {
    case PoseSolver::kPnpPlaceDepth:
      return "pnp_place_depth";
    case PoseSolver::kPnpQueryDepth:
      return "pnp_query_depth";
    case PoseSolver::kEssential:
      return "essential";
  }
  return "essential";
}

Status ValidateRelativePoseConfig(const RelativePoseConfig& config) {
  if (config.min_inliers < 5 || config.min_inliers > 100000) {
    return Status::InvalidArgument("min_inliers = " + std::to_string(config.min_inliers) +
                                   ": must be in [5, 100000]");
  }
  if (!(config.ransac_threshold_px > 0 && config.ransac_threshold_px <= 100)) {
    return Status::InvalidArgument("ransac_threshold_px = " + Num(config.ransac_threshold_px) +
                                   ": must be in (0, 100]");
  }
  if (!(config.ransac_confidence > 0 && config.ransac_confidence < 1)) {
    return Status::InvalidArgument("ransac_confidence = " + Num(config.ransac_confidence) +
                                   ": must be in (0, 1)");
  }
  if (config.ransac_max_iterations < 1 || config.ransac_max_iterations > 1000000) {
    return Status::InvalidArgument(
        "ransac_max_iterations = " + std::to_string(config.ransac_max_iterations) +
        ": must be in [1, 1000000]");
  }
  if (!(config.min_depth_m >= 0 && config.max_depth_m > config.min_depth_m &&
        std::isfinite(config.max_depth_m))) {
    return Status::InvalidArgument("min_depth_m / max_depth_m = " + Num(config.min_depth_m) +
                                   " / " + Num(config.max_depth_m) +
                                   ": need 0 <= min_depth_m < max_depth_m, finite");
  }
  if (!(config.octave_scale_factor >= 1 && config.octave_scale_factor <= 4)) {
    return Status::InvalidArgument("octave_scale_factor = " + Num(config.octave_scale_factor) +
                                   ": must be in [1, 4]");
  }
  for (const auto& [name, value] :
       {std::pair{"max_rotation_sigma_deg", config.max_rotation_sigma_deg},
        std::pair{"max_direction_sigma_deg", config.max_direction_sigma_deg}}) {
    if (!(value > 0 && value <= 180)) {
      return Status::InvalidArgument(std::string(name) + " = " + Num(value) +
                                     ": must be in (0, 180]");
    }
  }
  if (!(config.min_pixel_sigma > 0 && std::isfinite(config.min_pixel_sigma))) {
    return Status::InvalidArgument("min_pixel_sigma = " + Num(config.min_pixel_sigma) +
                                   ": must be finite and positive");
  }
  return Status::Ok();
}

Result<RelativePose> EstimateRelativePose(const PoseFrame& query, const PoseFrame& place,
                                          std::span<const KeypointMatch> matches,
                                          const RelativePoseConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateRelativePoseConfig(config));
  PLACEDB_RETURN_IF_ERROR(ValidateFrame(query, "query"));
  PLACEDB_RETURN_IF_ERROR(ValidateFrame(place, "place"));
  int query_depths = 0, place_depths = 0;
  for (size_t i = 0; i < matches.size(); ++i) {
    const KeypointMatch& m = matches[i];
    if (m.query >= query.keypoints.size()) {
      return Status::InvalidArgument(
          "matches[" + std::to_string(i) + "].query = " + std::to_string(m.query) +
          " but the query has " + std::to_string(query.keypoints.size()) + " keypoints");
    }
    if (m.place >= place.keypoints.size()) {
      return Status::InvalidArgument(
          "matches[" + std::to_string(i) + "].place = " + std::to_string(m.place) +
          " but the place has " + std::to_string(place.keypoints.size()) + " keypoints");
    }
    for (const auto& [side, kp, index] :
         {std::tuple{"query", &query.keypoints[m.query], m.query},
          std::tuple{"place", &place.keypoints[m.place], m.place}}) {
      if (!std::isfinite(kp->x) || !std::isfinite(kp->y)) {
        return Status::InvalidArgument(std::string(side) + ".keypoints[" + std::to_string(index) +
                                       "] is not finite");
      }
    }
    if (!query.depth_m.empty() && DepthUsable(query.depth_m[m.query], config)) ++query_depths;
    if (!place.depth_m.empty() && DepthUsable(place.depth_m[m.place], config)) ++place_depths;
  }

  const int best_depths = std::max(query_depths, place_depths);
  const bool pnp = config.method == PoseMethod::kPnp ||
                   (config.method == PoseMethod::kAuto && best_depths >= config.min_inliers);
  if (!pnp) return SolveEssential(query, place, matches, config);
  if (best_depths < config.min_inliers) {
    return Status::FailedPrecondition(
        "pnp: " + std::to_string(best_depths) + " of " + std::to_string(matches.size()) +
        " matches have a usable depth on one side, fewer than min_inliers " +
        std::to_string(config.min_inliers));
  }

  // The side with more matched depths carries the 3-D points (the place on a tie); the other
  // side's depths join the refinement.
  const bool depth_on_place = place_depths >= query_depths;
  const PnpProblem primary = MakePnpProblem(query, place, matches, depth_on_place, config);
  const PnpProblem secondary = MakePnpProblem(query, place, matches, !depth_on_place, config);
  int correspondences = 0;
  for (const auto& m : matches) {
    const bool q = !query.depth_m.empty() && DepthUsable(query.depth_m[m.query], config);
    const bool p = !place.depth_m.empty() && DepthUsable(place.depth_m[m.place], config);
    correspondences += (q || p) ? 1 : 0;
  }
  return SolvePnp(primary, secondary, depth_on_place, correspondences, config);
}

std::array<double, 4> RelativePose::quaternion() const {
  const cv::Matx33d r = RotationOf(transform);
  cv::Vec3d rvec;
  cv::Rodrigues(r, rvec);
  const double angle = cv::norm(rvec);
  if (angle < 1e-15) return {0, 0, 0, 1};
  const cv::Vec3d axis = rvec * (1.0 / angle);
  const double s = std::sin(angle / 2);
  return {axis[0] * s, axis[1] * s, axis[2] * s, std::cos(angle / 2)};
}

double RelativePose::rotation_deg() const {
  return AngleDeg(RotationOf(transform));
}

Transform ComposeTransforms(const Transform& a, const Transform& b) {
  Transform out{};
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) {
      double sum = 0;
      for (int k = 0; k < 4; ++k) sum += a[r * 4 + k] * b[k * 4 + c];
      out[r * 4 + c] = sum;
    }
  }
  return out;
}

Transform InvertTransform(const Transform& t) {
  const cv::Matx33d r = RotationOf(t);
  const cv::Vec3d tr(t[3], t[7], t[11]);
  return FromRt(r.t(), -(r.t() * tr));
}

Transform TransformFromTranslationQuaternion(const std::array<double, 3>& t,
                                             const std::array<double, 4>& q) {
  const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const double x = q[0] / norm, y = q[1] / norm, z = q[2] / norm, w = q[3] / norm;
  const cv::Matx33d r(1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                      2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                      2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y));
  return FromRt(r, cv::Vec3d(t[0], t[1], t[2]));
}

double RotationErrorDeg(const Transform& a, const Transform& b) {
  return AngleDeg(RotationOf(a).t() * RotationOf(b));
}

double TranslationErrorM(const Transform& a, const Transform& b) {
  return cv::norm(cv::Vec3d(a[3] - b[3], a[7] - b[7], a[11] - b[11]));
}

double TranslationDirectionErrorDeg(const Transform& a, const Transform& b) {
  const cv::Vec3d ta(a[3], a[7], a[11]), tb(b[3], b[7], b[11]);
  const double na = cv::norm(ta), nb = cv::norm(tb);
  if (na == 0 || nb == 0) return 0;
  return std::acos(std::clamp(ta.dot(tb) / (na * nb), -1.0, 1.0)) * 180.0 / CV_PI;
}

}  // namespace placedb
