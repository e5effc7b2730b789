// Per-place thumbnails (core/thumbnail/thumbnail.h) on real frames: CamVid with the boxes of its
// labelled cars, pedestrians and cyclists, and the RTAB-Map corridor; the thumbnail codec
// (core/storage/codec.h); the pipeline's thumbnail (PlaceDatabase::Process).
#include "core/thumbnail/thumbnail.h"

#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <span>

#include "core/decode/image_decoder.h"
#include "core/pipeline/place_database.h"
#include "core/storage/codec.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

// The bounding boxes of a CamVid frame's dynamic label components of at least `min_area` pixels
// (as the evaluation builds them), as person boxes.
std::vector<DynamicBox> CamVidBoxes(const testing::CamVidFrame& frame, int min_area = 400) {
  const cv::Mat dynamic = testing::CamVidDynamicMask(frame);
  cv::Mat labels, stats, centroids;
  const int count = cv::connectedComponentsWithStats(dynamic, labels, stats, centroids, 8);
  std::vector<DynamicBox> boxes;
  for (int c = 1; c < count; ++c) {
    const int* s = stats.ptr<int>(c);
    if (s[cv::CC_STAT_AREA] < min_area) continue;
    boxes.push_back({0, 0.9f,
                     cv::Rect2f(float(s[cv::CC_STAT_LEFT]), float(s[cv::CC_STAT_TOP]),
                                float(s[cv::CC_STAT_WIDTH]), float(s[cv::CC_STAT_HEIGHT]))});
  }
  return boxes;
}

double LaplacianVariance(const cv::Mat& image) {
  cv::Mat gray = image;
  if (image.channels() == 3) cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  cv::Mat laplacian;
  cv::Laplacian(gray, laplacian, CV_64F);
  cv::Scalar mean, stddev;
  cv::meanStdDev(laplacian, mean, stddev);
  return stddev[0] * stddev[0];
}

cv::Mat DecodeJpeg(const std::string& jpeg) {
  auto decoded =
      DecodeImage(std::span(reinterpret_cast<const uint8_t*>(jpeg.data()), jpeg.size()), {});
  EXPECT_TRUE(decoded.ok()) << decoded.status().ToString();
  return decoded.ok() ? *decoded : cv::Mat();
}

ThumbnailSettings On(uint32_t max_side = kDefaultThumbnailSide) {
  ThumbnailSettings settings;
  settings.enabled = true;
  settings.max_side = max_side;
  return settings;
}

// Inside every box the thumbnail is smooth (its Laplacian variance far below the same region of
// the unblurred reduced frame); outside the boxes it is the reduced frame within JPEG error.
TEST(Thumbnail, CamVidBoxesAreBlurredAndTheRestIsTheReducedFrame) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  const auto frames = testing::CamVidFrames();
  ASSERT_GT(frames.size(), 600u);
  size_t frames_checked = 0, regions_checked = 0;
  double worst_ratio = 0, worst_outside = 0, worst_outside_100 = 0;
  for (size_t f = 0; f < frames.size(); f += 35) {
    const std::vector<DynamicBox> boxes = CamVidBoxes(frames[f]);
    if (boxes.empty()) continue;
    const cv::Mat image = cv::imread(frames[f].image_path, cv::IMREAD_COLOR);
    ASSERT_FALSE(image.empty());
    auto thumbnail = MakeThumbnail(image, boxes, {}, On());
    ASSERT_TRUE(thumbnail.ok()) << thumbnail.status().ToString();
    const cv::Size size = ThumbnailSize(image.cols, image.rows, kDefaultThumbnailSide);
    EXPECT_EQ(size, cv::Size(320, 240));
    EXPECT_EQ(thumbnail->width, uint32_t(size.width));
    EXPECT_EQ(thumbnail->height, uint32_t(size.height));
    EXPECT_EQ(thumbnail->source_width, uint32_t(image.cols));
    EXPECT_EQ(thumbnail->source_height, uint32_t(image.rows));
    const cv::Mat decoded = DecodeJpeg(thumbnail->jpeg);
    ASSERT_EQ(decoded.size(), size);
    ASSERT_EQ(decoded.channels(), 3);
    const cv::Mat reduced = ReduceFrame(image, kDefaultThumbnailSide);

    cv::Mat blurred = cv::Mat::zeros(size, CV_8U);
    for (const DynamicBox& box : boxes) {
      const cv::Rect rect = ThumbnailBoxRect(box.rect, image.size(), size);
      ASSERT_FALSE(rect.empty());
      blurred(rect).setTo(255);
      // The interior (JPEG blocks at the border mix both sides); regions with detail only.
      const cv::Rect inner(rect.x + 2, rect.y + 2, rect.width - 4, rect.height - 4);
      if (inner.width < 6 || inner.height < 6) continue;
      const double before = LaplacianVariance(reduced(inner));
      if (before < 30) continue;  // nothing to hide (a flat car roof)
      const double after = LaplacianVariance(decoded(inner));
      EXPECT_LT(after, 0.2 * before) << frames[f].image_path << " box " << rect;
      worst_ratio = std::max(worst_ratio, after / before);
      ++regions_checked;
    }
    // Outside: beyond a JPEG block of the blurred regions, the reduced frame within JPEG error.
    cv::Mat outside;
    cv::dilate(blurred, outside, cv::Mat::ones(17, 17, CV_8U));
    outside = outside == 0;
    ASSERT_GT(cv::countNonZero(outside), size.area() / 10);
    // At quality 75 (the default) and at 100, where JPEG's own error is small.
    ThumbnailSettings best = On();
    best.jpeg_quality = 100;
    auto exact = MakeThumbnail(image, boxes, {}, best);
    ASSERT_TRUE(exact.ok());
    for (const cv::Mat& got : {decoded, DecodeJpeg(exact->jpeg)}) {
      cv::Mat difference;
      cv::absdiff(got, reduced, difference);
      const double mean_error = cv::mean(difference, outside)[0];
      EXPECT_LT(mean_error, got.data == decoded.data ? 8.0 : 2.0) << frames[f].image_path;
      if (got.data == decoded.data) {
        worst_outside = std::max(worst_outside, mean_error);
      } else {
        worst_outside_100 = std::max(worst_outside_100, mean_error);
      }
    }
    ++frames_checked;
  }
  EXPECT_GT(frames_checked, 10u);
  EXPECT_GT(regions_checked, 20u);
  std::printf("thumbnail_frames %zu\nthumbnail_blurred_regions %zu\n", frames_checked,
              regions_checked);
  std::printf(
      "thumbnail_worst_laplacian_ratio %.4f\nthumbnail_worst_outside_error_q75 %.2f\n"
      "thumbnail_worst_outside_error_q100 %.2f\n",
      worst_ratio, worst_outside, worst_outside_100);
}

// An agent's dynamic mask (here CamVid's own label mask, without boxes) is blurred too: each of
// its regions' bounding rectangles in the thumbnail is smooth.
TEST(Thumbnail, CamVidMaskRegionsAreBlurred) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  const auto frames = testing::CamVidFrames();
  size_t regions = 0;
  for (size_t f = 0; f < frames.size(); f += 70) {
    const cv::Mat mask = testing::CamVidDynamicMask(frames[f]);
    const cv::Mat image = cv::imread(frames[f].image_path, cv::IMREAD_COLOR);
    auto thumbnail = MakeThumbnail(image, {}, {}, On(), mask);
    ASSERT_TRUE(thumbnail.ok()) << thumbnail.status().ToString();
    const cv::Mat decoded = DecodeJpeg(thumbnail->jpeg);
    const cv::Mat reduced = ReduceFrame(image, kDefaultThumbnailSide);
    for (const DynamicBox& box : CamVidBoxes(frames[f])) {
      const cv::Rect rect = ThumbnailBoxRect(box.rect, image.size(), decoded.size());
      const cv::Rect inner(rect.x + 2, rect.y + 2, rect.width - 4, rect.height - 4);
      if (inner.width < 6 || inner.height < 6) continue;
      const double before = LaplacianVariance(reduced(inner));
      if (before < 30) continue;
      EXPECT_LT(LaplacianVariance(decoded(inner)), 0.2 * before) << frames[f].image_path;
      ++regions;
    }
  }
  EXPECT_GT(regions, 5u);
  EXPECT_EQ(MakeThumbnail(cv::Mat(100, 100, CV_8UC3, cv::Scalar::all(9)), {}, {}, On(),
                          cv::Mat(50, 50, CV_8U))
                .status()
                .code(),
            StatusCode::kInvalidArgument);
}

TEST(Thumbnail, SizesGrayFramesAndSmallFrames) {
  const cv::Mat gray = testing::ReadGray(testing::RtabmapFramePath(1));
  auto thumbnail = MakeThumbnail(gray, {}, {}, On(100));
  ASSERT_TRUE(thumbnail.ok()) << thumbnail.status().ToString();
  const cv::Mat decoded = DecodeJpeg(thumbnail->jpeg);
  EXPECT_EQ(decoded.channels(), 3);  // decoded as colour; the JPEG itself is gray
  EXPECT_EQ(std::max(decoded.cols, decoded.rows), 100);
  EXPECT_EQ(uint32_t(decoded.cols), thumbnail->width);
  EXPECT_EQ(thumbnail->width, uint32_t(std::lround(gray.cols * 100.0 / gray.cols)));
  // A frame smaller than max_side keeps its size: never enlarged.
  const cv::Mat small = gray(cv::Rect(0, 0, 200, 120)).clone();
  auto same = MakeThumbnail(small, {}, {}, On());
  ASSERT_TRUE(same.ok());
  EXPECT_EQ(same->width, 200u);
  EXPECT_EQ(same->height, 120u);
  // Boxes past the image, or empty, blur what lies inside the image or nothing.
  const std::vector<DynamicBox> odd = {{0, 1.0f, cv::Rect2f(-50, -50, 80, 80)},
                                       {0, 1.0f, cv::Rect2f(5000, 10, 20, 20)},
                                       {0, 1.0f, cv::Rect2f(10, 10, 0, 0)}};
  EXPECT_TRUE(MakeThumbnail(gray, odd, {}, On()).ok());
  EXPECT_EQ(ThumbnailBoxRect(odd[1].rect, gray.size(), {320, 240}), cv::Rect());
  EXPECT_EQ(ThumbnailBoxRect(odd[2].rect, gray.size(), {320, 240}), cv::Rect());
  EXPECT_EQ(MakeThumbnail(cv::Mat(), {}, {}, On()).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(MakeThumbnail(cv::Mat(10, 10, CV_32F), {}, {}, On()).status().code(),
            StatusCode::kInvalidArgument);
}

TEST(Thumbnail, SettingsOutOfRangeNameTheirField) {
  ThumbnailSettings settings;
  EXPECT_TRUE(ValidateThumbnailSettings(settings).ok());
  for (uint32_t side : {16u, 1024u}) {
    settings.max_side = side;
    EXPECT_TRUE(ValidateThumbnailSettings(settings).ok()) << side;
  }
  for (uint32_t side : {0u, 15u, 1025u}) {
    settings.max_side = side;
    const Status status = ValidateThumbnailSettings(settings);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
    EXPECT_NE(status.message().find("thumbnails.max_side"), std::string::npos) << status.message();
  }
  settings.max_side = 320;
  for (uint32_t quality : {0u, 101u}) {
    settings.jpeg_quality = quality;
    const Status status = ValidateThumbnailSettings(settings);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
    EXPECT_NE(status.message().find("thumbnails.jpeg_quality"), std::string::npos);
  }
}

Thumbnail SampleThumbnail() {
  const cv::Mat gray = testing::ReadGray(testing::RtabmapFramePath(7));
  std::vector<Keypoint> dropped = {{12.5f, 40.25f, 31, 90, 0.002f, 1},
                                   {600, 470, 44.6f, -1, 0.5f, 3}};
  auto thumbnail = MakeThumbnail(gray, {{0, 0.9f, cv::Rect2f(10, 20, 100, 200)}}, dropped, On(64));
  EXPECT_TRUE(thumbnail.ok()) << thumbnail.status().ToString();
  return thumbnail.ok() ? *thumbnail : Thumbnail();
}

TEST(ThumbnailCodec, RoundTripsAndEveryTruncationIsCorruption) {
  const Thumbnail thumbnail = SampleThumbnail();
  const std::string good = EncodeThumbnail(thumbnail);
  auto decoded = DecodeThumbnail(good);
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(*decoded, thumbnail);
  EXPECT_EQ(good.size(), thumbnail.jpeg.size() + 2 * 21 + 1 + 4 + 1 + 2 + 1 + 1);
  for (size_t cut = 0; cut < good.size(); ++cut) {
    auto truncated = DecodeThumbnail(std::string_view(good).substr(0, cut));
    ASSERT_FALSE(truncated.ok()) << "cut at " << cut;
    EXPECT_EQ(truncated.status().code(), StatusCode::kCorruption) << "cut at " << cut;
  }
  EXPECT_EQ(DecodeThumbnail(good + '\0').status().code(), StatusCode::kCorruption);
  std::string version = good;
  version[0] = 2;
  EXPECT_EQ(DecodeThumbnail(version).status().code(), StatusCode::kCorruption);
  // Sizes that disagree with the JPEG, or are no thumbnail's.
  for (auto change : std::vector<void (*)(Thumbnail*)>{
           [](Thumbnail* t) { t->width += 1; },
           [](Thumbnail* t) { t->height = 0; },
           [](Thumbnail* t) { t->source_width = t->width - 1; },
           [](Thumbnail* t) { t->jpeg[t->jpeg.size() / 2] ^= 0x5a, t->jpeg[0] = 'x'; },
       }) {
    Thumbnail bad = thumbnail;
    change(&bad);
    EXPECT_EQ(DecodeThumbnail(EncodeThumbnail(bad)).status().code(), StatusCode::kCorruption);
  }
}

// The pipeline makes the thumbnail of a frame with pixels when asked: the DC keypoints are its
// dropped ones; precomputed features and thumbnails off make none.
TEST(ThumbnailPipeline, ProcessKeepsTheDroppedKeypoints) {
  auto db = PlaceDatabase::Create(testing::DefaultVocabulary(), {});
  ASSERT_TRUE(db.ok()) << db.status().ToString();
  Observation observation;
  observation.image = cv::imread(testing::RtabmapFramePath(30), cv::IMREAD_COLOR);
  observation.dynamic.boxes.push_back({0, 0.9f, cv::Rect2f(100, 50, 200, 300)});
  observation.dynamic.boxes.push_back({56, 0.9f, cv::Rect2f(400, 50, 100, 100)});  // a chair
  const ThumbnailSettings settings = On();
  auto frame = (*db)->Process(observation, FrameRole::kStream, &settings);
  ASSERT_TRUE(frame.ok()) << frame.status().ToString();
  ASSERT_TRUE(frame->thumbnail.has_value());
  EXPECT_GT(frame->counts.dynamic, 0u);
  EXPECT_EQ(frame->thumbnail->dropped_keypoints.size(), frame->counts.dynamic);
  for (const Keypoint& k : frame->thumbnail->dropped_keypoints) {
    EXPECT_TRUE(cv::Rect2f(100, 50, 200, 300).contains({k.x, k.y})) << k.x << ", " << k.y;
  }
  EXPECT_EQ(frame->boxes_used.size(), 1u) << "a chair is not a dynamic class";
  EXPECT_EQ(frame->thumbnail->width, 320u);

  EXPECT_FALSE((*db)->Process(observation, FrameRole::kStream)->thumbnail.has_value());
  ThumbnailSettings off = settings;
  off.enabled = false;
  EXPECT_FALSE((*db)->Process(observation, FrameRole::kStream, &off)->thumbnail.has_value());
  Observation precomputed;
  precomputed.features = LocalFeatures(testing::ExtractFile(testing::RtabmapFramePath(30)));
  precomputed.dynamic = observation.dynamic;
  auto without_pixels = (*db)->Process(precomputed, FrameRole::kStream, &settings);
  ASSERT_TRUE(without_pixels.ok()) << without_pixels.status().ToString();
  EXPECT_GT(without_pixels->counts.dynamic, 0u);
  EXPECT_FALSE(without_pixels->thumbnail.has_value());
}

}  // namespace
}  // namespace placedb
