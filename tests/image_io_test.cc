// client/image_io.h, the CLI's image files and videos, built both ways from the same source:
// image_io_test links the build's setting of PLACEDB_CLI_OPENCV_IO (ON by default),
// image_io_jpeg_png_only_test image_io.cc compiled with it OFF (what the container image's CLI
// runs), so both are tested without a second build of the project. JPEG and PNG must give the
// pixels cv::imread gives on real images (opencv-doc's samples, ../shared's depth PNGs), in both
// builds; PNG written by EncodePng must decode to the image written; everything else is read by
// the OpenCV build and refused by the other with a message naming the file and what it reads.
#include "client/image_io.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <memory>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <string>
#include <vector>

#include "tests/test_support.h"

#ifndef PLACEDB_TEST_OPENCV_IO
#error "PLACEDB_TEST_OPENCV_IO (0 or 1): which build of client/image_io.cc this test links"
#endif
// One suite name per build, so that ctest tells the two binaries' tests apart.
#if PLACEDB_TEST_OPENCV_IO
#define ImageIo ImageIoWithOpenCv
#else
#define ImageIo ImageIoJpegPngOnly
#endif

namespace placedb::client {
namespace {

namespace fs = std::filesystem;

constexpr bool kOpenCvIo = PLACEDB_TEST_OPENCV_IO != 0;
const std::string kSamples = "/usr/share/doc/opencv-doc/examples/data/";

double MaxDifference(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size() || a.type() != b.type()) return -1;
  return cv::norm(a, b, cv::NORM_INF);
}

// ReadImageFile gives cv::imread's pixels in each mode.
void ExpectSameAsImread(const std::string& path) {
  SCOPED_TRACE(path);
  ASSERT_TRUE(fs::exists(path)) << "missing test image " << path;
  const std::pair<ImageRead, int> modes[] = {{ImageRead::kColor, cv::IMREAD_COLOR},
                                             {ImageRead::kGray, cv::IMREAD_GRAYSCALE},
                                             {ImageRead::kUnchanged, cv::IMREAD_UNCHANGED}};
  for (const auto& [mode, flags] : modes) {
    SCOPED_TRACE(flags);
    cv::Mat ours;
    std::string error;
    ASSERT_TRUE(ReadImageFile(path, mode, &ours, &error)) << error;
    const cv::Mat reference = cv::imread(path, flags);
    ASSERT_FALSE(reference.empty());
    EXPECT_EQ(ours.type(), reference.type());
    EXPECT_EQ(MaxDifference(ours, reference), 0.0);
  }
}

TEST(ImageIo, TheBuildSaysWhatItReads) {
  EXPECT_EQ(HasOpenCvImageIo(), kOpenCvIo);
  EXPECT_EQ(ReadableFormats(false), "JPEG and PNG images only");
  EXPECT_NE(ReadableFormats(true).find("videos"), std::string::npos);
}

TEST(ImageIo, JpegIsDecodedAsOpenCvDecodesIt) {
  ExpectSameAsImread(kSamples + "aloeL.jpg");
  ExpectSameAsImread(kSamples + "building.jpg");
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  ExpectSameAsImread(testing::SharedDir() + "/data/rtabmap-loop/1.jpg");
  ExpectSameAsImread(testing::SharedDir() + "/data/camvid/images/0001TP_006690.jpg");
}

TEST(ImageIo, PngIsDecodedAsOpenCvDecodesIt) {
  ExpectSameAsImread(kSamples + "graf1.png");        // 8-bit RGB
  ExpectSameAsImread(kSamples + "box.png");          // 8-bit gray
  ExpectSameAsImread(kSamples + "opencv-logo.png");  // 8-bit RGBA
  ExpectSameAsImread(kSamples + "mask.png");         // 8-bit gray + alpha
}

TEST(ImageIo, SixteenBitDepthPngKeepsItsValues) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  const std::string depth_dir = testing::SharedDir() + "/data/rgbd-people/depth/test1";
  ASSERT_TRUE(fs::is_directory(depth_dir));
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(depth_dir)) files.push_back(entry.path());
  ASSERT_FALSE(files.empty());
  std::sort(files.begin(), files.end());
  files.resize(std::min<size_t>(files.size(), 3));
  for (const std::string& path : files) {
    SCOPED_TRACE(path);
    cv::Mat ours;
    std::string error;
    ASSERT_TRUE(ReadImageFile(path, ImageRead::kUnchanged, &ours, &error)) << error;
    EXPECT_EQ(ours.type(), CV_16UC1);
    const cv::Mat reference = cv::imread(path, cv::IMREAD_UNCHANGED);
    EXPECT_EQ(MaxDifference(ours, reference), 0.0);
    double max_value = 0;
    cv::minMaxLoc(ours, nullptr, &max_value);
    EXPECT_GT(max_value, 255) << "a depth image uses the 16 bits";
  }
}

TEST(ImageIo, DamagedJpegIsRefusedNamingTheFile) {
  const std::string bytes = testing::ReadFileBytes(kSamples + "aloeL.jpg");
  ASSERT_GT(bytes.size(), 1000u);
  const std::string dir = testing::MakeTempDir("image_io");
  const std::string path = dir + "/half.jpg";
  {
    std::ofstream out(path, std::ios::binary);
    out.write(bytes.data(), std::streamsize(bytes.size() / 2));
  }
  cv::Mat image;
  std::string error;
  EXPECT_FALSE(ReadImageFile(path, ImageRead::kColor, &image, &error));
  EXPECT_NE(error.find(path), std::string::npos) << error;
  EXPECT_NE(error.find("truncated"), std::string::npos) << error;
}

TEST(ImageIo, EncodedPngDecodesToTheImageWritten) {
  const cv::Mat bgr = cv::imread(kSamples + "aloeL.jpg", cv::IMREAD_COLOR);
  ASSERT_FALSE(bgr.empty());
  cv::Mat gray, bgra, depth;
  cv::cvtColor(bgr, gray, cv::COLOR_BGR2GRAY);
  cv::cvtColor(bgr, bgra, cv::COLOR_BGR2BGRA);
  gray.convertTo(depth, CV_16U, 257.0);                // every bit of the 16 in use
  const cv::Mat roi = bgr(cv::Rect(10, 20, 101, 57));  // rows with a stride wider than the row
  for (const cv::Mat& image : {bgr, gray, bgra, depth, roi}) {
    SCOPED_TRACE(image.type());
    std::string png, error;
    ASSERT_TRUE(EncodePng(image, &png, &error)) << error;
    EXPECT_TRUE(IsJpegOrPng(png));
    const cv::Mat decoded =
        cv::imdecode(cv::Mat(1, int(png.size()), CV_8U, png.data()), cv::IMREAD_UNCHANGED);
    EXPECT_EQ(MaxDifference(decoded, image), 0.0);
    cv::Mat ours;
    ASSERT_TRUE(DecodeImageBytes(png, ImageRead::kUnchanged, &ours, &error)) << error;
    EXPECT_EQ(MaxDifference(ours, image), 0.0);
  }
  std::string png, error;
  EXPECT_FALSE(EncodePng(cv::Mat(4, 4, CV_32FC1, cv::Scalar(1)), &png, &error));
  EXPECT_NE(error.find("16-bit gray"), std::string::npos) << error;
  EXPECT_FALSE(EncodePng(cv::Mat(), &png, &error));
}

TEST(ImageIo, PngFilesAreWrittenByEveryBuild) {
  const std::string dir = testing::MakeTempDir("image_io");
  const cv::Mat bgr = cv::imread(kSamples + "graf1.png", cv::IMREAD_COLOR);
  std::string error;
  ASSERT_TRUE(WriteImageFile(dir + "/chart.PNG", bgr, &error)) << error;
  EXPECT_EQ(MaxDifference(cv::imread(dir + "/chart.PNG", cv::IMREAD_UNCHANGED), bgr), 0.0);
  EXPECT_FALSE(WriteImageFile(dir + "/no-such-dir/chart.png", bgr, &error));
  EXPECT_NE(error.find("no-such-dir/chart.png"), std::string::npos) << error;
  const bool jpeg_written = WriteImageFile(dir + "/chart.jpg", bgr, &error);
  EXPECT_EQ(jpeg_written, kOpenCvIo) << error;
  if (!kOpenCvIo) {
    EXPECT_NE(error.find(dir + "/chart.jpg"), std::string::npos) << error;
    EXPECT_NE(error.find("PNG images only"), std::string::npos) << error;
  }
}

// A BMP (rtabmap-loop's ground truth, else one written here) and a 16-bit PGM depth image.
TEST(ImageIo, OtherFormatsNeedOpenCvAndAreRefusedClearlyWithout) {
  const std::string dir = testing::MakeTempDir("image_io");
  std::string bmp = testing::SharedDir() + "/data/rtabmap-loop/ground_truth.bmp";
  if (!fs::exists(bmp)) {
    bmp = dir + "/gray.bmp";
    ASSERT_TRUE(cv::imwrite(bmp, cv::imread(kSamples + "box.png", cv::IMREAD_GRAYSCALE)));
  }
  std::vector<std::string> others = {bmp};
  const std::string pgm = testing::SharedDir() + "/data/slambook2-rgbd/depth/1.pgm";
  if (fs::exists(pgm)) others.push_back(pgm);
  for (const std::string& path : others) {
    SCOPED_TRACE(path);
    cv::Mat image;
    std::string error;
    const bool read = ReadImageFile(path, ImageRead::kUnchanged, &image, &error);
    if (kOpenCvIo) {
      ASSERT_TRUE(read) << error;
      EXPECT_EQ(MaxDifference(image, cv::imread(path, cv::IMREAD_UNCHANGED)), 0.0);
    } else {
      EXPECT_FALSE(read);
      EXPECT_EQ(error, path +
                           " is an image in a format other than JPEG or PNG: this placedb build "
                           "reads JPEG and PNG images only (it was built with "
                           "-DPLACEDB_CLI_OPENCV_IO=OFF, as the container image is, without "
                           "OpenCV's image and video I/O); convert it to JPEG or PNG, or use a "
                           "build with PLACEDB_CLI_OPENCV_IO=ON");
    }
  }
}

TEST(ImageIo, VideosNeedOpenCvAndAreRefusedClearlyWithout) {
  const std::string video = kSamples + "vtest.avi";
  ASSERT_TRUE(fs::exists(video));
  std::string error;
  const std::unique_ptr<VideoReader> reader = VideoReader::Open(video, &error);
  if (!kOpenCvIo) {
    EXPECT_EQ(reader, nullptr);
    EXPECT_EQ(error.rfind(video + " is a video (not a folder, an image list or an image file): "
                                  "this placedb build reads JPEG and PNG images only",
                          0),
              0u)
        << error;
    EXPECT_NE(error.find("PLACEDB_CLI_OPENCV_IO=OFF"), std::string::npos) << error;
    return;
  }
  ASSERT_NE(reader, nullptr) << error;
  cv::VideoCapture capture(video);
  ASSERT_TRUE(capture.isOpened());
  EXPECT_EQ(reader->DeclaredFrames().value_or(-1), capture.get(cv::CAP_PROP_FRAME_COUNT));
  EXPECT_TRUE(reader->Skip());
  std::string jpeg;
  ASSERT_TRUE(reader->NextJpeg(&jpeg, &error)) << error;
  EXPECT_TRUE(error.empty()) << error;
  cv::Mat frame;
  ASSERT_TRUE(DecodeImageBytes(jpeg, ImageRead::kColor, &frame, &error)) << error;
  EXPECT_EQ(frame.cols, int(capture.get(cv::CAP_PROP_FRAME_WIDTH)));
  EXPECT_EQ(frame.rows, int(capture.get(cv::CAP_PROP_FRAME_HEIGHT)));
}

}  // namespace
}  // namespace placedb::client
