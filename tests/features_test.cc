// ORB extraction on real images, validation of precomputed features, selection and OpenCV
// interop.
#include <gtest/gtest.h>

#include <cmath>
#include <exception>
#include <limits>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <vector>

#include "core/features/local_features.h"
#include "core/features/orb_features.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

using ::placedb::testing::CamVidFrames;
using ::placedb::testing::DebianSampleImages;
using ::placedb::testing::HaveSharedData;
using ::placedb::testing::ReadGray;
using ::placedb::testing::SharedDir;

// Real images with plenty of texture, from the Debian packages every developer machine has.
std::vector<std::string> TexturedSampleImages() {
  std::vector<std::string> chosen;
  for (const std::string& path : DebianSampleImages()) {
    for (const char* name :
         {"/person.jpg", "/horses.jpg", "/baboon.jpg", "/graf1.png", "/building.jpg"}) {
      if (path.ends_with(name)) chosen.push_back(path);
    }
  }
  return chosen;
}

// Fails (never skips) when the Debian sample images are missing.
std::vector<std::string> RequireSampleImages() {
  std::vector<std::string> images = TexturedSampleImages();
  EXPECT_GE(images.size(), 3u)
      << "the Debian sample images are missing: install the opencv-doc and darknet packages "
         "(/usr/share/doc/opencv-doc/examples/data, /usr/share/darknet/data)";
  return images;
}

// Fails (never skips) when ../shared/data is missing.
std::vector<testing::CamVidFrame> RequireCamVid() {
  EXPECT_TRUE(HaveSharedData()) << "shared data not found at " << SharedDir()
                                << "/data; set PLACEDB_SHARED_DIR to the shared directory";
  std::vector<testing::CamVidFrame> frames;
  try {
    frames = CamVidFrames();
  } catch (const std::exception& e) {
    ADD_FAILURE() << "CamVidFrames() could not list " << SharedDir()
                  << "/data/camvid/images (tests/test_support.cc): " << e.what();
  }
  EXPECT_EQ(frames.size(), 701u) << "CamVid frames missing under " << SharedDir()
                                 << "/data/camvid/images";
  return frames;
}

Descriptor256 PatternDescriptor(uint64_t seed) {
  Descriptor256 d;
  for (int w = 0; w < 4; ++w) d.words[w] = seed * 0x9E3779B97F4A7C15ull + uint64_t(w);
  return d;
}

// A valid hand-made set: `count` keypoints on a diagonal of a 640x480 image.
FeatureSet HandMadeFeatures(int count) {
  FeatureSet features;
  features.image_width = 640;
  features.image_height = 480;
  for (int i = 0; i < count; ++i) {
    Keypoint kp;
    kp.x = 10.0f + 20.0f * float(i);
    kp.y = 5.0f + 15.0f * float(i);
    kp.size = 31.0f * std::pow(1.2f, float(i % 8));
    kp.angle = i % 2 == 0 ? -1.0f : 37.5f * float(i);
    kp.response = 0.001f * float(i);
    kp.octave = i % 8;
    features.keypoints.push_back(kp);
    features.descriptors.push_back(PatternDescriptor(uint64_t(i)));
  }
  return features;
}

// Every property ExtractOrb promises about one extracted set.
void ExpectWellFormed(const FeatureSet& features, const cv::Mat& image, const OrbConfig& config,
                      const std::string& what) {
  SCOPED_TRACE(what);
  EXPECT_EQ(features.image_width, image.cols);
  EXPECT_EQ(features.image_height, image.rows);
  ASSERT_EQ(features.descriptors.size(), features.keypoints.size());
  EXPECT_LE(int(features.size()), config.max_features);
  EXPECT_TRUE(ValidateFeatures(features).ok()) << ValidateFeatures(features).ToString();
  for (size_t i = 0; i < features.size(); ++i) {
    const Keypoint& kp = features.keypoints[i];
    ASSERT_GE(kp.x, 0.0f) << i;
    ASSERT_GE(kp.y, 0.0f) << i;
    ASSERT_LT(kp.x, float(image.cols)) << i;
    ASSERT_LT(kp.y, float(image.rows)) << i;
    ASSERT_GE(kp.octave, 0) << i;
    ASSERT_LT(kp.octave, config.levels) << i;
    // The extent side the filter relies on: patch_size at the octave's scale.
    const float expected_size =
        float(config.patch_size) * std::pow(config.scale_factor, float(kp.octave));
    ASSERT_NEAR(kp.size, expected_size, 1e-3f * expected_size) << i;
    ASSERT_TRUE(kp.angle >= 0.0f && kp.angle < 360.0f) << i << ": " << kp.angle;
  }
}

TEST(ExtractOrb, RespectsTheFeatureBudgetOnRealImages) {
  const std::vector<std::string> images = RequireSampleImages();
  for (const std::string& path : images) {
    const cv::Mat image = ReadGray(path);
    for (int budget : {300, 1000, 2000}) {
      OrbConfig config;
      config.max_features = budget;
      auto features = ExtractOrb(image, config);
      ASSERT_TRUE(features.ok()) << features.status().ToString();
      ExpectWellFormed(*features, image, config, path + " @" + std::to_string(budget));
      // Textured photographs fill most of the budget; an extractor returning a handful would
      // starve the vocabulary.
      EXPECT_GE(int(features->size()), budget / 2) << path << " @" << budget;
    }
  }
}

TEST(ExtractOrb, UsesSeveralOctavesAndRespectsCustomPyramids) {
  const std::vector<std::string> images = RequireSampleImages();
  ASSERT_FALSE(images.empty());
  const cv::Mat image = ReadGray(images.front());
  OrbConfig config;
  config.max_features = 1500;
  config.levels = 4;
  config.scale_factor = 1.5f;
  config.patch_size = 25;
  config.edge_threshold = 25;
  auto features = ExtractOrb(image, config);
  ASSERT_TRUE(features.ok()) << features.status().ToString();
  ExpectWellFormed(*features, image, config, images.front());
  std::vector<int> per_octave(config.levels, 0);
  for (const Keypoint& kp : features->keypoints) ++per_octave[kp.octave];
  for (int level = 0; level < config.levels; ++level) {
    EXPECT_GT(per_octave[level], 0) << "no keypoint on octave " << level;
  }
}

TEST(ExtractOrb, CamVidFramesGiveFullBudgets) {
  const std::vector<testing::CamVidFrame> frames = RequireCamVid();
  ASSERT_FALSE(frames.empty());
  // The first frame of each sequence.
  std::string last_sequence;
  int checked = 0;
  for (const testing::CamVidFrame& frame : frames) {
    if (frame.sequence == last_sequence) continue;
    last_sequence = frame.sequence;
    const cv::Mat image = ReadGray(frame.image_path);
    EXPECT_EQ(image.cols, 480);
    EXPECT_EQ(image.rows, 360);
    OrbConfig config;
    auto features = ExtractOrb(image, config);
    ASSERT_TRUE(features.ok()) << features.status().ToString();
    ExpectWellFormed(*features, image, config, frame.image_path);
    EXPECT_GE(int(features->size()), config.max_features * 3 / 4) << frame.image_path;
    ++checked;
  }
  EXPECT_EQ(checked, 4);
}

TEST(ExtractOrb, ColourAndGrayInputsGiveTheSameFeatures) {
  const std::vector<std::string> images = RequireSampleImages();
  ASSERT_FALSE(images.empty());
  const cv::Mat bgr = cv::imread(images.front(), cv::IMREAD_COLOR);
  ASSERT_FALSE(bgr.empty());
  cv::Mat gray, bgra;
  cv::cvtColor(bgr, gray, cv::COLOR_BGR2GRAY);
  cv::cvtColor(bgr, bgra, cv::COLOR_BGR2BGRA);
  const OrbConfig config;
  auto from_gray = ExtractOrb(gray, config);
  auto from_bgr = ExtractOrb(bgr, config);
  auto from_bgra = ExtractOrb(bgra, config);
  ASSERT_TRUE(from_gray.ok() && from_bgr.ok() && from_bgra.ok());
  ASSERT_GT(from_gray->size(), 100u);
  EXPECT_EQ(from_bgr->keypoints, from_gray->keypoints);
  EXPECT_EQ(from_bgr->descriptors, from_gray->descriptors);
  EXPECT_EQ(from_bgra->keypoints, from_gray->keypoints);
  EXPECT_EQ(from_bgra->descriptors, from_gray->descriptors);
}

TEST(ExtractOrb, IsDeterministicAndMatchesOpenCv) {
  const std::vector<std::string> images = RequireSampleImages();
  ASSERT_FALSE(images.empty());
  const cv::Mat image = ReadGray(images.back());
  const OrbConfig config;
  auto first = ExtractOrb(image, config);
  auto second = ExtractOrb(image, config);
  ASSERT_TRUE(first.ok() && second.ok());
  EXPECT_EQ(first->keypoints, second->keypoints);
  EXPECT_EQ(first->descriptors, second->descriptors);

  // The same ORB run directly: ExtractOrb must hand its results over unchanged.
  cv::Ptr<cv::ORB> orb = cv::ORB::create(config.max_features, config.scale_factor, config.levels,
                                         config.edge_threshold, 0, 2, cv::ORB::HARRIS_SCORE,
                                         config.patch_size, config.fast_threshold);
  std::vector<cv::KeyPoint> cv_keypoints;
  cv::Mat cv_descriptors;
  orb->detectAndCompute(image, cv::noArray(), cv_keypoints, cv_descriptors);
  ASSERT_EQ(cv_keypoints.size(), first->size());
  const std::vector<cv::KeyPoint> converted = ToCvKeypoints(first->keypoints);
  for (size_t i = 0; i < cv_keypoints.size(); ++i) {
    EXPECT_EQ(converted[i].pt, cv_keypoints[i].pt) << i;
    EXPECT_EQ(converted[i].size, cv_keypoints[i].size) << i;
    EXPECT_EQ(converted[i].angle, cv_keypoints[i].angle) << i;
    EXPECT_EQ(converted[i].octave, cv_keypoints[i].octave) << i;
  }
  const cv::Mat descriptors = ToCvDescriptors(first->descriptors);
  ASSERT_EQ(descriptors.size(), cv_descriptors.size());
  EXPECT_EQ(cv::norm(descriptors, cv_descriptors, cv::NORM_HAMMING), 0.0);
}

TEST(ExtractOrb, TexturelessImageGivesAnEmptySet) {
  const cv::Mat flat(240, 320, CV_8U, cv::Scalar(128));
  auto features = ExtractOrb(flat, OrbConfig{});
  ASSERT_TRUE(features.ok()) << features.status().ToString();
  EXPECT_TRUE(features->empty());
  EXPECT_EQ(features->image_width, 320);
  EXPECT_EQ(features->image_height, 240);
}

TEST(ExtractOrb, RejectsUnsupportedImages) {
  const OrbConfig config;
  auto empty = ExtractOrb(cv::Mat(), config);
  ASSERT_FALSE(empty.ok());
  EXPECT_EQ(empty.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(empty.status().message().find("empty"), std::string::npos);

  auto deep = ExtractOrb(cv::Mat(100, 100, CV_16U, cv::Scalar(1000)), config);
  ASSERT_FALSE(deep.ok());
  EXPECT_EQ(deep.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(deep.status().message().find("8-bit"), std::string::npos);

  auto floating = ExtractOrb(cv::Mat(100, 100, CV_32F, cv::Scalar(0.5)), config);
  ASSERT_FALSE(floating.ok());
  EXPECT_EQ(floating.status().code(), StatusCode::kInvalidArgument);

  auto two_channels = ExtractOrb(cv::Mat(100, 100, CV_8UC2, cv::Scalar(1, 2)), config);
  ASSERT_FALSE(two_channels.ok());
  EXPECT_EQ(two_channels.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(two_channels.status().message().find("channels"), std::string::npos);
}

TEST(ExtractOrb, RejectsInvalidConfigs) {
  const cv::Mat image(100, 100, CV_8U, cv::Scalar(0));
  struct Case {
    const char* field;
    void (*mutate)(OrbConfig&);
  };
  const Case cases[] = {
      {"max_features", [](OrbConfig& c) { c.max_features = 0; }},
      {"max_features", [](OrbConfig& c) { c.max_features = 100001; }},
      {"scale_factor", [](OrbConfig& c) { c.scale_factor = 1.0f; }},
      {"scale_factor", [](OrbConfig& c) { c.scale_factor = 2.5f; }},
      {"scale_factor", [](OrbConfig& c) { c.scale_factor = std::nanf(""); }},
      {"levels", [](OrbConfig& c) { c.levels = 0; }},
      {"levels", [](OrbConfig& c) { c.levels = 17; }},
      {"patch_size", [](OrbConfig& c) { c.patch_size = 1; }},
      {"patch_size", [](OrbConfig& c) { c.patch_size = 256; }},
      {"edge_threshold", [](OrbConfig& c) { c.edge_threshold = -1; }},
      {"fast_threshold", [](OrbConfig& c) { c.fast_threshold = 0; }},
  };
  for (const Case& c : cases) {
    OrbConfig config;
    c.mutate(config);
    const Status status = ValidateOrbConfig(config);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument) << c.field;
    EXPECT_NE(status.message().find(c.field), std::string::npos) << status.message();
    auto extracted = ExtractOrb(image, config);
    EXPECT_FALSE(extracted.ok()) << c.field;
  }
  EXPECT_TRUE(ValidateOrbConfig(OrbConfig{}).ok());
}

TEST(ValidateFeatures, AcceptsValidSetsIncludingEmptyOnes) {
  EXPECT_TRUE(ValidateFeatures(HandMadeFeatures(8)).ok())
      << ValidateFeatures(HandMadeFeatures(8)).ToString();
  EXPECT_TRUE(ValidateFeatures(HandMadeFeatures(0)).ok());
  FeatureSet edges = HandMadeFeatures(2);
  edges.keypoints[0].x = 0;
  edges.keypoints[0].y = 0;
  edges.keypoints[1].x = 639.99f;
  edges.keypoints[1].y = 479.99f;
  edges.keypoints[1].angle = 360.0f;
  edges.keypoints[1].octave = 31;
  EXPECT_TRUE(ValidateFeatures(edges).ok()) << ValidateFeatures(edges).ToString();
}

TEST(ValidateFeatures, NamesTheFieldAndIndexOfEveryInvalidCase) {
  struct Case {
    const char* name;
    void (*mutate)(FeatureSet&);
    const char* expected;  // must appear in the message
  };
  const Case cases[] = {
      {"zero width", [](FeatureSet& f) { f.image_width = 0; }, "image size"},
      {"zero height", [](FeatureSet& f) { f.image_height = 0; }, "image size"},
      {"negative width", [](FeatureSet& f) { f.image_width = -5; }, "image size"},
      {"huge image", [](FeatureSet& f) { f.image_width = 100001; }, "image size"},
      {"count mismatch", [](FeatureSet& f) { f.descriptors.pop_back(); }, "descriptors"},
      {"x beyond width", [](FeatureSet& f) { f.keypoints[3].x = 640.0f; }, "keypoints[3]"},
      {"negative x", [](FeatureSet& f) { f.keypoints[2].x = -0.5f; }, "keypoints[2]"},
      {"y beyond height", [](FeatureSet& f) { f.keypoints[4].y = 480.0f; }, "keypoints[4]"},
      {"negative y", [](FeatureSet& f) { f.keypoints[1].y = -1.0f; }, "keypoints[1]"},
      {"NaN x", [](FeatureSet& f) { f.keypoints[5].x = std::nanf(""); }, "keypoints[5]"},
      {"NaN size", [](FeatureSet& f) { f.keypoints[0].size = std::nanf(""); }, "keypoints[0]"},
      {"infinite response",
       [](FeatureSet& f) { f.keypoints[6].response = std::numeric_limits<float>::infinity(); },
       "keypoints[6]"},
      {"zero size", [](FeatureSet& f) { f.keypoints[2].size = 0.0f; }, "keypoints[2].size"},
      {"negative size", [](FeatureSet& f) { f.keypoints[3].size = -31.0f; }, "keypoints[3].size"},
      {"angle below -1", [](FeatureSet& f) { f.keypoints[4].angle = -2.0f; }, "keypoints[4].angle"},
      {"angle -0.5", [](FeatureSet& f) { f.keypoints[4].angle = -0.5f; }, "keypoints[4].angle"},
      {"angle above 360", [](FeatureSet& f) { f.keypoints[7].angle = 360.5f; },
       "keypoints[7].angle"},
      {"negative octave", [](FeatureSet& f) { f.keypoints[1].octave = -1; }, "keypoints[1].octave"},
      {"octave above 31", [](FeatureSet& f) { f.keypoints[6].octave = 32; }, "keypoints[6].octave"},
  };
  for (const Case& c : cases) {
    FeatureSet features = HandMadeFeatures(8);
    c.mutate(features);
    const Status status = ValidateFeatures(features);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument) << c.name;
    EXPECT_NE(status.message().find(c.expected), std::string::npos)
        << c.name << ": " << status.message();
  }
}

TEST(ValidateFeatures, ReportsTheFirstOffendingIndex) {
  FeatureSet features = HandMadeFeatures(8);
  features.keypoints[6].size = 0;
  features.keypoints[2].x = 1e6f;
  const Status status = ValidateFeatures(features);
  EXPECT_NE(status.message().find("keypoints[2]"), std::string::npos) << status.message();
}

std::vector<uint8_t> DescriptorBytes(const FeatureSet& features) {
  std::vector<uint8_t> bytes(features.size() * Descriptor256::kBytes);
  for (size_t i = 0; i < features.size(); ++i) {
    features.descriptors[i].ToBytes(&bytes[i * Descriptor256::kBytes]);
  }
  return bytes;
}

TEST(MakeFeatureSet, BuildsTheSetFromWireArrays) {
  const FeatureSet original = HandMadeFeatures(8);
  auto built = MakeFeatureSet(640, 480, original.keypoints, DescriptorBytes(original));
  ASSERT_TRUE(built.ok()) << built.status().ToString();
  EXPECT_EQ(built->image_width, 640);
  EXPECT_EQ(built->image_height, 480);
  EXPECT_EQ(built->keypoints, original.keypoints);
  EXPECT_EQ(built->descriptors, original.descriptors);

  auto empty = MakeFeatureSet(640, 480, {}, {});
  ASSERT_TRUE(empty.ok()) << empty.status().ToString();
  EXPECT_TRUE(empty->empty());
}

TEST(MakeFeatureSet, RejectsMalformedWireArrays) {
  const FeatureSet original = HandMadeFeatures(8);
  std::vector<uint8_t> bytes = DescriptorBytes(original);

  std::vector<uint8_t> ragged = bytes;
  ragged.pop_back();
  auto not_multiple = MakeFeatureSet(640, 480, original.keypoints, ragged);
  ASSERT_FALSE(not_multiple.ok());
  EXPECT_EQ(not_multiple.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(not_multiple.status().message().find("descriptors"), std::string::npos);
  EXPECT_NE(not_multiple.status().message().find("multiple of 32"), std::string::npos)
      << not_multiple.status().message();

  std::vector<uint8_t> short_bytes(bytes.begin(), bytes.end() - Descriptor256::kBytes);
  auto mismatch = MakeFeatureSet(640, 480, original.keypoints, short_bytes);
  ASSERT_FALSE(mismatch.ok());
  EXPECT_EQ(mismatch.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(mismatch.status().message().find("7 descriptors for 8 keypoints"), std::string::npos)
      << mismatch.status().message();

  auto zero_size = MakeFeatureSet(0, 480, original.keypoints, bytes);
  ASSERT_FALSE(zero_size.ok());
  EXPECT_NE(zero_size.status().message().find("image size"), std::string::npos);

  std::vector<Keypoint> outside = original.keypoints;
  outside[5].y = 480.5f;
  auto out_of_image = MakeFeatureSet(640, 480, outside, bytes);
  ASSERT_FALSE(out_of_image.ok());
  EXPECT_NE(out_of_image.status().message().find("keypoints[5]"), std::string::npos)
      << out_of_image.status().message();

  std::vector<Keypoint> bad_angle = original.keypoints;
  bad_angle[3].angle = std::nanf("");
  auto nan_angle = MakeFeatureSet(640, 480, bad_angle, bytes);
  ASSERT_FALSE(nan_angle.ok());
  EXPECT_NE(nan_angle.status().message().find("keypoints[3]"), std::string::npos);
}

TEST(SelectFeatures, KeepsTheListedIndicesInOrder) {
  const FeatureSet features = HandMadeFeatures(8);
  const FeatureSet selected = SelectFeatures(features, {0, 3, 4, 7});
  EXPECT_EQ(selected.image_width, features.image_width);
  EXPECT_EQ(selected.image_height, features.image_height);
  ASSERT_EQ(selected.size(), 4u);
  const uint32_t kept[] = {0, 3, 4, 7};
  for (size_t i = 0; i < 4; ++i) {
    EXPECT_EQ(selected.keypoints[i], features.keypoints[kept[i]]);
    EXPECT_EQ(selected.descriptors[i], features.descriptors[kept[i]]);
  }
  EXPECT_TRUE(ValidateFeatures(selected).ok());

  const FeatureSet none = SelectFeatures(features, {});
  EXPECT_TRUE(none.empty());
  EXPECT_EQ(none.image_width, 640);
  const FeatureSet all = SelectFeatures(features, {0, 1, 2, 3, 4, 5, 6, 7});
  EXPECT_EQ(all.keypoints, features.keypoints);
  EXPECT_EQ(all.descriptors, features.descriptors);
}

// A valid hand-made SIFT set of `count` keypoints (HandMadeFeatures' positions).
FloatFeatureSet HandMadeSiftFeatures(int count) {
  const FeatureSet orb = HandMadeFeatures(count);
  FloatFeatureSet features;
  features.image_width = orb.image_width;
  features.image_height = orb.image_height;
  features.keypoints = orb.keypoints;
  for (int i = 0; i < count * kSiftDimensions; ++i) features.descriptors.push_back(float(i % 97));
  return features;
}

TEST(LocalFeatures, OperationsFollowTheFamily) {
  const FeatureSet orb = HandMadeFeatures(8);
  const LocalFeatures features = orb;
  EXPECT_EQ(features.type(), FeatureType::kOrb);
  ASSERT_NE(features.orb(), nullptr);
  EXPECT_EQ(features.sift(), nullptr);
  EXPECT_EQ(features.size(), 8u);
  EXPECT_EQ(features.image_width(), 640);
  EXPECT_EQ(features.image_height(), 480);
  EXPECT_EQ(features.keypoints(), orb.keypoints);
  EXPECT_TRUE(features.Validate().ok());

  const LocalFeatures selected = features.Select({1, 4, 6});
  ASSERT_NE(selected.orb(), nullptr);
  EXPECT_EQ(selected.orb()->keypoints, SelectFeatures(orb, {1, 4, 6}).keypoints);
  EXPECT_EQ(selected.orb()->descriptors, SelectFeatures(orb, {1, 4, 6}).descriptors);

  auto joined = LocalFeatures::Concat(selected, features.Select({0}));
  ASSERT_TRUE(joined.ok()) << joined.status().ToString();
  ASSERT_NE(joined->orb(), nullptr);
  EXPECT_EQ(joined->orb()->keypoints, SelectFeatures(orb, {1, 4, 6, 0}).keypoints);
  EXPECT_EQ(joined->orb()->descriptors, SelectFeatures(orb, {1, 4, 6, 0}).descriptors);

  const FloatFeatureSet float_set = HandMadeSiftFeatures(5);
  const LocalFeatures sift = float_set;
  EXPECT_EQ(sift.type(), FeatureType::kSift);
  EXPECT_EQ(sift.orb(), nullptr);
  EXPECT_TRUE(sift.Validate().ok()) << sift.Validate().ToString();
  const LocalFeatures sift_selected = sift.Select({0, 3});
  ASSERT_NE(sift_selected.sift(), nullptr);
  EXPECT_EQ(sift_selected.sift()->descriptors, SelectFloatFeatures(float_set, {0, 3}).descriptors);
  auto sift_joined = LocalFeatures::Concat(sift_selected, sift.Select({4}));
  ASSERT_TRUE(sift_joined.ok());
  EXPECT_EQ(sift_joined->sift()->descriptors,
            SelectFloatFeatures(float_set, {0, 3, 4}).descriptors);

  // Families do not mix, and validation is the family's own.
  EXPECT_EQ(LocalFeatures::Concat(features, sift).status().code(), StatusCode::kInvalidArgument);
  FloatFeatureSet broken = float_set;
  broken.descriptors[130] = std::nanf("");
  const Status invalid = LocalFeatures(broken).Validate();
  EXPECT_EQ(invalid.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(invalid.ToString(), ValidateFloatFeatures(broken).ToString());

  const LocalFeatures empty = LocalFeatures::Empty(FeatureType::kSift, 64, 48);
  EXPECT_EQ(empty.type(), FeatureType::kSift);
  EXPECT_TRUE(empty.empty());
  EXPECT_EQ(empty.image_width(), 64);
  EXPECT_EQ(empty.image_height(), 48);
}

TEST(FeatureExtractor, RunsTheFamilysExtractor) {
  const std::vector<std::string> images = RequireSampleImages();
  ASSERT_FALSE(images.empty());
  const cv::Mat image = ReadGray(images.front());
  cv::Mat left = cv::Mat::zeros(image.size(), CV_8U);
  left(cv::Rect(0, 0, image.cols / 2, image.rows)).setTo(255);
  OrbConfig orb;
  orb.max_features = 300;
  SiftConfig sift;
  sift.max_features = 200;

  auto orb_extractor = FeatureExtractor::Create(FeatureType::kOrb, orb, sift);
  ASSERT_TRUE(orb_extractor.ok()) << orb_extractor.status().ToString();
  EXPECT_EQ((*orb_extractor)->type(), FeatureType::kOrb);
  for (const cv::Mat& mask : {cv::Mat(), left}) {
    auto extracted = (*orb_extractor)->Extract(image, mask);
    auto expected = ExtractOrb(image, orb, mask);
    ASSERT_TRUE(extracted.ok() && expected.ok());
    ASSERT_NE(extracted->orb(), nullptr);
    EXPECT_GT(extracted->size(), 50u);
    EXPECT_EQ(extracted->orb()->keypoints, expected->keypoints);
    EXPECT_EQ(extracted->orb()->descriptors, expected->descriptors);
  }

  auto sift_extractor = FeatureExtractor::Create(FeatureType::kSift, orb, sift);
  ASSERT_TRUE(sift_extractor.ok()) << sift_extractor.status().ToString();
  EXPECT_EQ((*sift_extractor)->type(), FeatureType::kSift);
  auto extracted = (*sift_extractor)->Extract(image, left);
  auto expected = ExtractSift(image, sift, left);
  ASSERT_TRUE(extracted.ok() && expected.ok());
  ASSERT_NE(extracted->sift(), nullptr);
  EXPECT_GT(extracted->size(), 50u);
  EXPECT_EQ(extracted->sift()->keypoints, expected->keypoints);
  EXPECT_EQ(extracted->sift()->descriptors, expected->descriptors);

  // Only the pipeline's measured ORB behaviours are on.
  EXPECT_TRUE((*orb_extractor)->budgets_static_pixels());
  EXPECT_TRUE((*orb_extractor)->verifies_dynamic_features());
  EXPECT_FALSE((*sift_extractor)->budgets_static_pixels());
  EXPECT_FALSE((*sift_extractor)->verifies_dynamic_features());

  // The family's config is validated; the other family's is not its concern.
  OrbConfig bad_orb;
  bad_orb.max_features = 0;
  EXPECT_EQ(FeatureExtractor::Create(FeatureType::kOrb, bad_orb, sift).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_TRUE(FeatureExtractor::Create(FeatureType::kSift, bad_orb, sift).ok());
  EXPECT_EQ(FeatureExtractor::Create(FeatureType(7), orb, sift).status().code(),
            StatusCode::kInvalidArgument);
}

TEST(OpenCvInterop, KeypointsAndDescriptorsRoundTrip) {
  const FeatureSet features = HandMadeFeatures(8);
  const std::vector<cv::KeyPoint> cv_keypoints = ToCvKeypoints(features.keypoints);
  ASSERT_EQ(cv_keypoints.size(), features.size());
  for (size_t i = 0; i < features.size(); ++i) {
    const Keypoint& kp = features.keypoints[i];
    const Keypoint back{cv_keypoints[i].pt.x,  cv_keypoints[i].pt.y,     cv_keypoints[i].size,
                        cv_keypoints[i].angle, cv_keypoints[i].response, cv_keypoints[i].octave};
    EXPECT_EQ(back, kp) << i;
  }

  const cv::Mat bytes = ToCvDescriptors(features.descriptors);
  EXPECT_EQ(bytes.rows, 8);
  EXPECT_EQ(bytes.cols, Descriptor256::kBytes);
  EXPECT_EQ(bytes.type(), CV_8U);
  for (int i = 0; i < bytes.rows; ++i) {
    EXPECT_EQ(Descriptor256::FromBytes(bytes.ptr<uint8_t>(i)), features.descriptors[size_t(i)]);
  }
  // Byte i holds bits 8i..8i+7 of the 256-bit string, as OpenCV's ORB writes them.
  Descriptor256 one_bit;
  one_bit.words[1] = 1ull << 9;  // bit 73 = byte 9, bit 1
  const cv::Mat single = ToCvDescriptors({one_bit});
  for (int b = 0; b < Descriptor256::kBytes; ++b) {
    EXPECT_EQ(single.at<uint8_t>(0, b), b == 9 ? 2 : 0) << b;
  }
  EXPECT_TRUE(ToCvKeypoints({}).empty());
  EXPECT_EQ(ToCvDescriptors({}).rows, 0);
}

TEST(OpenCvInterop, HammingDistanceAgreesWithOpenCvOnRealDescriptors) {
  const std::vector<std::string> images = RequireSampleImages();
  ASSERT_FALSE(images.empty());
  const FeatureSet features = testing::ExtractFile(images.front(), 300);
  ASSERT_GT(features.size(), 10u);
  const cv::Mat bytes = ToCvDescriptors(features.descriptors);
  for (size_t i = 0; i + 1 < features.size(); i += 7) {
    const int expected = int(cv::norm(bytes.row(int(i)), bytes.row(int(i + 1)), cv::NORM_HAMMING));
    EXPECT_EQ(HammingDistance(features.descriptors[i], features.descriptors[i + 1]), expected);
  }
}

}  // namespace
}  // namespace placedb

namespace placedb {
namespace {

TEST(ExtractOrbEdgeCases, TinyImagesGiveNoFeaturesNotACrash) {
  for (const cv::Size size :
       {cv::Size(1, 1), cv::Size(1, 480), cv::Size(640, 1), cv::Size(2, 2), cv::Size(5, 7)}) {
    auto features = ExtractOrb(cv::Mat(size, CV_8U, cv::Scalar(128)), OrbConfig{});
    ASSERT_TRUE(features.ok()) << size << ": " << features.status().ToString();
    EXPECT_TRUE(features->empty());
    EXPECT_EQ(features->image_width, size.width);
  }
}

}  // namespace
}  // namespace placedb
