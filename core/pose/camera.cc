#include "core/pose/camera.h"

#include <cmath>
#include <opencv2/calib3d.hpp>
#include <sstream>

namespace placedb {

namespace {

struct ModelName {
  const char* name;
  DistortionModel model;
};
constexpr ModelName kModelNames[] = {
    {"none", DistortionModel::kNone},
    {"", DistortionModel::kNone},
    {"plumb_bob", DistortionModel::kRadialTangential},
    {"radtan", DistortionModel::kRadialTangential},
    {"radial-tangential", DistortionModel::kRadialTangential},
    {"equidistant", DistortionModel::kEquidistant},
    {"fisheye", DistortionModel::kEquidistant},
};

std::string Num(double v) {
  std::ostringstream out;
  out << v;
  return out.str();
}

cv::Mat Coefficients(const Camera& camera) {
  return cv::Mat(camera.distortion, /*copyData=*/true).reshape(1, 1);
}

}  // namespace

const char* DistortionModelName(DistortionModel model) {
  switch (model) {
    case DistortionModel::kNone:
      return "none";
    case DistortionModel::kRadialTangential:
      return "plumb_bob";
    case DistortionModel::kEquidistant:
      return "equidistant";
  }
  return "none";
}

Result<DistortionModel> ParseDistortionModel(const std::string& name) {
  for (const auto& entry : kModelNames) {
    if (name == entry.name) return entry.model;
  }
  return Status::InvalidArgument(
      "unknown distortion model '" + name +
      "' (known: none, plumb_bob|radtan|radial-tangential, equidistant|fisheye)");
}

DistortionModel Camera::model() const {
  auto parsed = ParseDistortionModel(distortion_model);
  return parsed.ok() ? *parsed : DistortionModel::kNone;
}

bool Camera::IsPinhole() const {
  if (model() == DistortionModel::kNone) return true;
  for (double k : distortion) {
    if (k != 0) return false;
  }
  return true;
}

Status Camera::Validate(const std::string& field) const {
  constexpr int kMaxSide = 100000;
  if (width < 1 || width > kMaxSide) {
    return Status::InvalidArgument(field + ".width = " + std::to_string(width) +
                                   ": must be in [1, 100000]");
  }
  if (height < 1 || height > kMaxSide) {
    return Status::InvalidArgument(field + ".height = " + std::to_string(height) +
                                   ": must be in [1, 100000]");
  }
  for (const auto& [name, value] : {std::pair{"fx", fx}, std::pair{"fy", fy}}) {
    if (!std::isfinite(value) || value <= 0) {
      return Status::InvalidArgument(field + "." + name + " = " + Num(value) +
                                     ": a focal length must be finite and positive (pixels)");
    }
  }
  if (!std::isfinite(cx) || cx < 0 || cx >= width) {
    return Status::InvalidArgument(field + ".cx = " + Num(cx) + ": the principal point must lie " +
                                   "inside the image, in [0, " + std::to_string(width) + ")");
  }
  if (!std::isfinite(cy) || cy < 0 || cy >= height) {
    return Status::InvalidArgument(field + ".cy = " + Num(cy) + ": the principal point must lie " +
                                   "inside the image, in [0, " + std::to_string(height) + ")");
  }
  auto parsed = ParseDistortionModel(distortion_model);
  if (!parsed.ok()) {
    return Status::InvalidArgument(field + ".distortion_model: " + parsed.status().message());
  }
  const size_t n = distortion.size();
  bool count_ok = false;
  const char* expected = "";
  switch (*parsed) {
    case DistortionModel::kNone:
      count_ok = n == 0;
      expected = "none";
      break;
    case DistortionModel::kRadialTangential:
      count_ok = n == 4 || n == 5;
      expected = "4 (k1 k2 p1 p2) or 5 (k1 k2 p1 p2 k3)";
      break;
    case DistortionModel::kEquidistant:
      count_ok = n == 4;
      expected = "4 (k1 k2 k3 k4)";
      break;
  }
  if (!count_ok) {
    return Status::InvalidArgument(field + ".distortion has " + std::to_string(n) +
                                   " coefficients; model '" + distortion_model + "' takes " +
                                   expected);
  }
  for (size_t i = 0; i < n; ++i) {
    if (!std::isfinite(distortion[i])) {
      return Status::InvalidArgument(field + ".distortion[" + std::to_string(i) +
                                     "] = " + Num(distortion[i]) + ": must be finite");
    }
  }
  return Status::Ok();
}

Camera PinholeCamera(int width, int height, double fx, double fy, double cx, double cy) {
  Camera camera;
  camera.width = width;
  camera.height = height;
  camera.fx = fx;
  camera.fy = fy;
  camera.cx = cx;
  camera.cy = cy;
  return camera;
}

std::vector<cv::Point2d> UndistortPixels(const Camera& camera,
                                         const std::vector<cv::Point2d>& pixels) {
  if (camera.IsPinhole() || pixels.empty()) return pixels;
  std::vector<cv::Point2d> out;
  const cv::Matx33d k = camera.K();
  if (camera.model() == DistortionModel::kEquidistant) {
    cv::fisheye::undistortPoints(
        pixels, out, k, Coefficients(camera), cv::noArray(), k,
        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 30, 1e-10));
  } else {
    // OpenCV's default is 5 fixed-point iterations: not enough near the corners of a strongly
    // distorted lens (0.01 px off); iterate to convergence instead.
    cv::undistortPoints(
        pixels, out, k, Coefficients(camera), cv::noArray(), k,
        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 30, 1e-10));
  }
  return out;
}

double MeanFocalLength(const Camera& a, const Camera& b) {
  return (std::sqrt(a.fx * a.fy) + std::sqrt(b.fx * b.fy)) / 2;
}

std::vector<cv::Point2d> NormalizePixels(const Camera& camera,
                                         const std::vector<cv::Point2d>& pixels) {
  std::vector<cv::Point2d> out = UndistortPixels(camera, pixels);
  for (auto& p : out) p = {(p.x - camera.cx) / camera.fx, (p.y - camera.cy) / camera.fy};
  return out;
}

cv::Point3d BackProject(const Camera& camera, const cv::Point2d& pixel, double depth_m) {
  cv::Point2d ideal = pixel;
  if (!camera.IsPinhole()) ideal = UndistortPixels(camera, {pixel})[0];
  return {(ideal.x - camera.cx) / camera.fx * depth_m, (ideal.y - camera.cy) / camera.fy * depth_m,
          depth_m};
}

}  // namespace placedb
