// Box refinement (core/filter/box_masks.h) on real CamVid frames: every labelled car and
// pedestrian's bounding box is refined and compared with the object's own label pixels.
#include "core/filter/box_masks.h"

#include <gtest/gtest.h>

#include <cstdio>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/base/timing.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

struct Totals {
  double box_pixels = 0, box_on_object = 0;      // whole boxes
  double mask_pixels = 0, mask_on_object = 0;    // refined masks
  double object_pixels = 0, object_covered = 0;  // of the objects' pixels, inside the mask
  size_t boxes = 0, segmented = 0;
  double ms = 0;
};

// Refines the bounding boxes of the dynamic label components (>= 400 px) of every 20th frame.
Totals RefineCamVid(BoxRefinement method) {
  Totals totals;
  const auto frames = testing::CamVidFrames();
  EXPECT_GT(frames.size(), 600u);
  for (size_t f = 0; f < frames.size(); f += 20) {
    const cv::Mat image = cv::imread(frames[f].image_path, cv::IMREAD_COLOR);
    const cv::Mat dynamic = testing::CamVidDynamicMask(frames[f]);
    cv::Mat labels, stats, centroids;
    const int count = cv::connectedComponentsWithStats(dynamic, labels, stats, centroids, 8);
    for (int c = 1; c < count; ++c) {
      const int* s = stats.ptr<int>(c);
      if (s[cv::CC_STAT_AREA] < 400) continue;
      const cv::Rect rect(s[cv::CC_STAT_LEFT], s[cv::CC_STAT_TOP], s[cv::CC_STAT_WIDTH],
                          s[cv::CC_STAT_HEIGHT]);
      DynamicObjects objects;
      objects.boxes.push_back({2, 0.9f, cv::Rect2f(rect)});
      BoxRefinementConfig config;
      config.method = method;
      Stopwatch watch;
      auto refined = RefineBoxesToMasks(objects, image, image.cols, image.rows, config);
      totals.ms += watch.ElapsedMs();
      EXPECT_TRUE(refined.ok()) << refined.status().ToString();
      if (!refined.ok()) continue;
      EXPECT_EQ(refined->boxes.size(), 1u);
      EXPECT_TRUE(refined->objects.boxes.empty());
      const cv::Mat object = labels == c;
      const cv::Mat mask = refined->objects.mask != 0;
      totals.box_pixels += rect.area();
      totals.box_on_object += cv::countNonZero(object(rect));
      totals.mask_pixels += cv::countNonZero(mask);
      totals.mask_on_object += cv::countNonZero(mask & object);
      totals.object_pixels += cv::countNonZero(object);
      totals.object_covered += cv::countNonZero(mask & object);
      ++totals.boxes;
      totals.segmented += refined->boxes[0].segmented ? 1 : 0;
    }
  }
  return totals;
}

TEST(BoxMasks, GrabCutKeepsTheObjectAndGivesBackTheBackground) {
  const Totals grabcut = RefineCamVid(BoxRefinement::kGrabCut);
  const Totals shape = RefineCamVid(BoxRefinement::kShape);
  ASSERT_GT(grabcut.boxes, 30u);
  const double box_precision = grabcut.box_on_object / grabcut.box_pixels;
  const double grabcut_precision = grabcut.mask_on_object / grabcut.mask_pixels;
  const double shape_precision = shape.mask_on_object / shape.mask_pixels;
  const double grabcut_recall = grabcut.object_covered / grabcut.object_pixels;
  const double shape_recall = shape.object_covered / shape.object_pixels;
  std::printf(
      "[box_masks] %zu boxes (%zu segmented): on-object share of marked pixels: box %.3f, "
      "shape %.3f, grabcut %.3f; object pixels kept dynamic: shape %.3f, grabcut %.3f; "
      "marked pixels / box pixels: shape %.3f, grabcut %.3f; ms per box: shape %.3f, "
      "grabcut %.3f\n",
      grabcut.boxes, grabcut.segmented, box_precision, shape_precision, grabcut_precision,
      shape_recall, grabcut_recall, shape.mask_pixels / shape.box_pixels,
      grabcut.mask_pixels / grabcut.box_pixels, shape.ms / double(shape.boxes),
      grabcut.ms / double(grabcut.boxes));
  // Refinement gives back background that the whole box would drop, and keeps most of the
  // object dynamic.
  EXPECT_GT(shape_precision, box_precision);
  EXPECT_GT(grabcut_precision, shape_precision);
  EXPECT_LT(grabcut.mask_pixels, 0.9 * grabcut.box_pixels);
  EXPECT_GT(grabcut_recall, 0.8);
  EXPECT_GT(shape_recall, 0.8);
  EXPECT_GE(grabcut.segmented * 10, grabcut.boxes);  // tight label boxes: often the prior stands
}

TEST(BoxMasks, DeterministicWhateverRanBeforeOnTheThread) {
  const auto frames = testing::CamVidFrames();
  ASSERT_FALSE(frames.empty());
  const cv::Mat image = cv::imread(frames[40].image_path, cv::IMREAD_COLOR);
  DynamicObjects objects;
  objects.boxes.push_back({0, 0.8f, cv::Rect2f(100, 80, 90, 160)});
  objects.boxes.push_back({2, 0.8f, cv::Rect2f(250, 180, 150, 100)});
  BoxRefinementConfig grabcut;
  grabcut.method = BoxRefinement::kGrabCut;
  auto first = RefineBoxesToMasks(objects, image, image.cols, image.rows, grabcut);
  ASSERT_TRUE(first.ok());
  cv::theRNG().state = 12345;  // another user of OpenCV's RNG on this thread
  (void)cv::theRNG().next();
  auto second = RefineBoxesToMasks(objects, image, image.cols, image.rows, grabcut);
  ASSERT_TRUE(second.ok());
  EXPECT_EQ(cv::countNonZero(first->objects.mask != second->objects.mask), 0);
}

TEST(BoxMasks, ShapeWithoutPixelsKeepsTheInputMaskAndRejectsBadInput) {
  DynamicObjects objects;
  objects.mask = cv::Mat::zeros(100, 200, CV_8U);
  objects.mask(cv::Rect(0, 0, 10, 10)).setTo(1);
  objects.boxes.push_back({0, 0.9f, cv::Rect2f(100, 0, 40, 100)});  // a person: an ellipse
  BoxRefinementConfig config;  // GrabCut, but no image: the shape prior stands in
  config.method = BoxRefinement::kGrabCut;
  auto refined = RefineBoxesToMasks(objects, cv::Mat(), 200, 100, config);
  ASSERT_TRUE(refined.ok()) << refined.status().ToString();
  const cv::Mat& mask = refined->objects.mask;
  EXPECT_EQ(cv::countNonZero(mask(cv::Rect(0, 0, 10, 10))), 100);  // the input mask stays
  EXPECT_EQ(mask.at<uint8_t>(50, 120), 255);                       // the box's centre
  EXPECT_EQ(mask.at<uint8_t>(1, 101), 0);                          // its corner is background
  EXPECT_FALSE(refined->boxes[0].segmented);
  EXPECT_NEAR(refined->boxes[0].object_fraction, 3.14159 / 4, 0.03);

  config.method = BoxRefinement::kNone;
  auto unchanged = RefineBoxesToMasks(objects, cv::Mat(), 200, 100, config);
  ASSERT_TRUE(unchanged.ok());
  EXPECT_EQ(unchanged->objects.boxes.size(), 1u);

  objects.boxes[0].rect.width = std::numeric_limits<float>::quiet_NaN();
  EXPECT_EQ(RefineBoxesToMasks(objects, cv::Mat(), 200, 100, {}).status().code(),
            StatusCode::kInvalidArgument);
  objects.boxes.clear();
  EXPECT_EQ(RefineBoxesToMasks(objects, cv::Mat(10, 10, CV_8UC3), 200, 100, {}).status().code(),
            StatusCode::kInvalidArgument);
  BoxRefinementConfig bad;
  bad.max_side = 2;
  EXPECT_EQ(ValidateBoxRefinementConfig(bad).code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseBoxRefinement("grabcut").value(), BoxRefinement::kGrabCut);
  EXPECT_FALSE(ParseBoxRefinement("watershed").ok());
}

}  // namespace
}  // namespace placedb
