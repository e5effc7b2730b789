// Camera: the pinhole intrinsics and lens distortion of one agent's camera, as a relative pose
// needs them (issue 32).
//
// The fields follow ROS's sensor_msgs/CameraInfo so that an agent can send what its driver
// publishes: the image size, the focal lengths and principal point in pixels, a distortion model
// by name and its coefficients:
//
//   model name                                 coefficients (in this order)
//   "none" (or "")                             none
//   "plumb_bob", "radtan", "radial-tangential" k1 k2 p1 p2, or k1 k2 p1 p2 k3 (OpenCV's and ROS's
//                                              Brown-Conrady model)
//   "equidistant", "fisheye"                   k1 k2 k3 k4 (Kannala-Brandt, OpenCV's cv::fisheye)
//
// Validate() checks everything before any use and names the offending field (with the caller's
// prefix, e.g. "query.camera.fx"). Pixel coordinates are (x = column, y = row), the centre of the
// top-left pixel at (0, 0) (OpenCV's and ORB's keypoint convention).
#pragma once

#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"

namespace placedb {

enum class DistortionModel {
  kNone,
  kRadialTangential,  // plumb_bob: k1 k2 p1 p2 [k3]
  kEquidistant,       // fisheye: k1 k2 k3 k4
};

// "none", "plumb_bob", "equidistant": the canonical names (what a stored camera records).
const char* DistortionModelName(DistortionModel model);
// Any of the names in the table above; INVALID_ARGUMENT naming the accepted names otherwise.
Result<DistortionModel> ParseDistortionModel(const std::string& name);

struct Camera {
  int width = 0;          // image size in pixels
  int height = 0;         // (the keypoints' image, full resolution)
  double fx = 0, fy = 0;  // focal lengths, pixels
  double cx = 0, cy = 0;  // principal point, pixels
  std::string distortion_model = "none";
  std::vector<double> distortion;  // the model's coefficients, in the order of the table above

  // OK, or INVALID_ARGUMENT naming the first bad field under `field`: width and height in
  // [1, 100000]; fx, fy finite and > 0; cx in [0, width), cy in [0, height) (finite); a known
  // model name; exactly the model's number of coefficients (4 or 5 for plumb_bob), each finite.
  Status Validate(const std::string& field = "camera") const;

  // The distortion model (only meaningful after Validate() passed; kNone for an unknown name).
  DistortionModel model() const;
  // True when the model is "none" or every coefficient is 0: pixels are already pinhole.
  bool IsPinhole() const;
  cv::Matx33d K() const { return {fx, 0, cx, 0, fy, cy, 0, 0, 1}; }
  bool operator==(const Camera&) const = default;
};

// Pinhole camera with no distortion.
Camera PinholeCamera(int width, int height, double fx, double fy, double cx, double cy);

// Undistorts pixel points of `camera` into the ideal pinhole image of the same intrinsics (the
// pixel where an undistorted lens would have imaged the ray): cv::undistortPoints for plumb_bob,
// cv::fisheye::undistortPoints for equidistant, a copy for pinhole cameras. The camera must be
// valid (Validate()).
std::vector<cv::Point2d> UndistortPixels(const Camera& camera,
                                         const std::vector<cv::Point2d>& pixels);

// The mean of two cameras' geometric-mean focal lengths (pixels): what converts a pixel threshold
// into normalised image coordinates for a two-view fit across both.
double MeanFocalLength(const Camera& a, const Camera& b);

// Normalised image coordinates ((x - cx) / fx, (y - cy) / fy after undistortion): the ray
// direction (x, y, 1) in the camera frame. The camera must be valid.
std::vector<cv::Point2d> NormalizePixels(const Camera& camera,
                                         const std::vector<cv::Point2d>& pixels);

// The 3-D point in the camera frame (x right, y down, z forward along the optical axis; metres)
// seen at `pixel` with depth `depth_m` measured along the optical axis (z, what RGB-D sensors
// report). The camera must be valid.
cv::Point3d BackProject(const Camera& camera, const cv::Point2d& pixel, double depth_m);

}  // namespace placedb
