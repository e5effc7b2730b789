// core/pose/camera.h: validation names the field; undistortion and back-projection invert the
// models' projections.
#include "core/pose/camera.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <string>
#include <vector>

namespace placedb {
namespace {

Camera Valid() {
  return PinholeCamera(640, 480, 525, 526, 319.5, 239.5);
}

void ExpectInvalid(const Camera& camera, const std::string& field) {
  const Status status = camera.Validate("query.camera");
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument) << status.ToString();
  EXPECT_NE(status.message().find("query.camera." + field), std::string::npos) << status.ToString();
}

TEST(CameraTest, ValidCamerasPass) {
  EXPECT_TRUE(Valid().Validate().ok());
  Camera radtan = Valid();
  radtan.distortion_model = "plumb_bob";
  radtan.distortion = {0.1, -0.2, 0.001, 0.002, 0.05};
  EXPECT_TRUE(radtan.Validate().ok());
  radtan.distortion.pop_back();
  EXPECT_TRUE(radtan.Validate().ok());
  Camera fisheye = Valid();
  fisheye.distortion_model = "fisheye";
  fisheye.distortion = {0.01, -0.02, 0.003, -0.001};
  EXPECT_TRUE(fisheye.Validate().ok());
  EXPECT_EQ(fisheye.model(), DistortionModel::kEquidistant);
}

TEST(CameraTest, BadIntrinsicsNameTheField) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  for (double bad : {0.0, -500.0, nan, inf}) {
    Camera c = Valid();
    c.fx = bad;
    ExpectInvalid(c, "fx");
    c = Valid();
    c.fy = bad;
    ExpectInvalid(c, "fy");
  }
  Camera c = Valid();
  c.cx = 640;  // outside [0, 640)
  ExpectInvalid(c, "cx");
  c = Valid();
  c.cy = -1;
  ExpectInvalid(c, "cy");
  c = Valid();
  c.cy = nan;
  ExpectInvalid(c, "cy");
  c = Valid();
  c.width = 0;
  ExpectInvalid(c, "width");
  c = Valid();
  c.height = -4;
  ExpectInvalid(c, "height");
}

TEST(CameraTest, UnknownModelAndWrongCoefficientCountsNameTheField) {
  Camera c = Valid();
  c.distortion_model = "kannala_brandt8";
  ExpectInvalid(c, "distortion_model");
  EXPECT_FALSE(ParseDistortionModel("rational_polynomial").ok());
  c = Valid();
  c.distortion = {0.1};  // "none" takes none
  ExpectInvalid(c, "distortion");
  c.distortion_model = "plumb_bob";
  c.distortion = {0.1, 0.2, 0.3};
  ExpectInvalid(c, "distortion");
  c.distortion_model = "equidistant";
  c.distortion = {0.1, 0.2, 0.3, 0.4, 0.5};
  ExpectInvalid(c, "distortion");
  c.distortion = {0.1, std::numeric_limits<double>::quiet_NaN(), 0.3, 0.4};
  ExpectInvalid(c, "distortion[1]");
}

// Pixels distorted by OpenCV's forward models come back to the ideal pinhole pixels.
TEST(CameraTest, UndistortInvertsBothModels) {
  for (const std::string model : {"plumb_bob", "equidistant"}) {
    Camera c = Valid();
    c.distortion_model = model;
    c.distortion = model == "plumb_bob" ? std::vector<double>{-0.28, 0.07, 0.0008, -0.0005, 0}
                                        : std::vector<double>{0.02, -0.01, 0.004, -0.001};
    ASSERT_TRUE(c.Validate().ok());
    std::vector<cv::Point3d> rays;
    for (double x = -0.5; x <= 0.5; x += 0.25) {
      for (double y = -0.4; y <= 0.4; y += 0.2) rays.push_back({x, y, 1});
    }
    std::vector<cv::Point2d> distorted;
    const cv::Mat d(c.distortion);
    if (model == "plumb_bob") {
      cv::projectPoints(rays, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), c.K(), d, distorted);
    } else {
      cv::fisheye::projectPoints(rays, distorted, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), c.K(), d);
    }
    const auto normalised = NormalizePixels(c, distorted);
    const auto ideal = UndistortPixels(c, distorted);
    for (size_t i = 0; i < rays.size(); ++i) {
      EXPECT_NEAR(normalised[i].x, rays[i].x, 1e-5) << model << " " << i;
      EXPECT_NEAR(normalised[i].y, rays[i].y, 1e-5) << model << " " << i;
      EXPECT_NEAR(ideal[i].x, c.fx * rays[i].x + c.cx, 5e-3) << model << " " << i;
      EXPECT_NEAR(ideal[i].y, c.fy * rays[i].y + c.cy, 5e-3) << model << " " << i;
      const cv::Point3d p = BackProject(c, distorted[i], 2.5);
      EXPECT_NEAR(p.x, rays[i].x * 2.5, 1e-4);
      EXPECT_NEAR(p.y, rays[i].y * 2.5, 1e-4);
      EXPECT_DOUBLE_EQ(p.z, 2.5);
    }
  }
}

TEST(CameraTest, BackProjectPinhole) {
  const Camera c = Valid();
  const cv::Point3d p = BackProject(c, {319.5 + 525, 239.5 - 526}, 2.0);
  EXPECT_NEAR(p.x, 2.0, 1e-12);
  EXPECT_NEAR(p.y, -2.0, 1e-12);
  EXPECT_EQ(p.z, 2.0);
}

}  // namespace
}  // namespace placedb
