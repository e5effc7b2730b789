// SIFT features (core/features/sift_features.h) and the float vocabulary
// (core/vocabulary/float_vocabulary.h): extraction and validation on real images, hierarchical
// k-means on controlled data, determinism, the file format and its corruption checks, and the
// Debian-trained SIFT vocabulary.
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <set>
#include <string>
#include <vector>

#include "core/base/files.h"
#include "core/features/sift_features.h"
#include "core/search/scoring.h"
#include "core/vocabulary/float_vocabulary.h"
#include "tools/rgbd_data.h"

namespace placedb {
namespace {

namespace fs = std::filesystem;

const std::string kOpenCvData = "/usr/share/doc/opencv-doc/examples/data/";

cv::Mat ReadGray(const std::string& path) {
  cv::Mat image = cv::imread(path, cv::IMREAD_GRAYSCALE);
  EXPECT_FALSE(image.empty()) << "cannot read " << path << " (install opencv-doc)";
  return image;
}

std::string TempPath(const std::string& name) {
  const fs::path dir =
      fs::temp_directory_path() / ("placedb-sift-test-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  return (dir / name).string();
}

// ---- SIFT extraction -------------------------------------------------------------------------

TEST(Sift, ExtractsValidStrongestFirstFeatures) {
  const cv::Mat image = ReadGray(kOpenCvData + "box_in_scene.png");
  ASSERT_FALSE(image.empty());
  SiftConfig config;
  config.max_features = 500;
  auto features = ExtractSift(image, config);
  ASSERT_TRUE(features.ok()) << features.status().ToString();
  EXPECT_GT(features->size(), 300u);
  EXPECT_LE(features->size(), 510u);  // OpenCV may keep ties at the cut
  EXPECT_EQ(features->image_width, image.cols);
  EXPECT_EQ(features->image_height, image.rows);
  EXPECT_EQ(features->descriptors.size(), features->size() * kSiftDimensions);
  EXPECT_TRUE(ValidateFloatFeatures(*features).ok());
  for (size_t i = 1; i < features->size(); ++i) {
    EXPECT_GE(features->keypoints[i - 1].response, features->keypoints[i].response);
  }
  std::set<int> octaves;
  for (const auto& kp : features->keypoints) octaves.insert(kp.octave);
  EXPECT_GT(octaves.size(), 2u) << "features from several octaves";
  EXPECT_EQ(*octaves.begin() >= 0, true);
  // SIFT descriptors: non-negative, at most 255 after OpenCV's quantisation scale.
  const auto [lo, hi] =
      std::minmax_element(features->descriptors.begin(), features->descriptors.end());
  EXPECT_GE(*lo, 0.0f);
  EXPECT_LE(*hi, 255.0f);
}

TEST(Sift, MaskColourAndTexturelessImages) {
  const cv::Mat gray = ReadGray(kOpenCvData + "box_in_scene.png");
  ASSERT_FALSE(gray.empty());
  cv::Mat mask = cv::Mat::zeros(gray.size(), CV_8U);
  mask(cv::Rect(0, 0, gray.cols / 2, gray.rows)).setTo(255);
  auto left = ExtractSift(gray, SiftConfig{}, mask);
  ASSERT_TRUE(left.ok());
  ASSERT_FALSE(left->empty());
  for (const auto& kp : left->keypoints) EXPECT_LT(kp.x, gray.cols / 2 + 1);

  cv::Mat bgr = cv::imread(kOpenCvData + "box_in_scene.png", cv::IMREAD_COLOR);
  auto from_bgr = ExtractSift(bgr, SiftConfig{});
  auto from_gray = ExtractSift(gray, SiftConfig{});
  ASSERT_TRUE(from_bgr.ok() && from_gray.ok());
  EXPECT_EQ(from_bgr->size(), from_gray->size());

  auto flat = ExtractSift(cv::Mat(240, 320, CV_8U, cv::Scalar(128)), SiftConfig{});
  ASSERT_TRUE(flat.ok());
  EXPECT_TRUE(flat->empty());

  EXPECT_EQ(ExtractSift(cv::Mat(), SiftConfig{}).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ExtractSift(cv::Mat(10, 10, CV_16U), SiftConfig{}).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(ExtractSift(gray, SiftConfig{}, cv::Mat(5, 5, CV_8U)).status().code(),
            StatusCode::kInvalidArgument);
  SiftConfig bad;
  bad.octave_layers = 0;
  EXPECT_EQ(ExtractSift(gray, bad).status().code(), StatusCode::kInvalidArgument);
  bad = SiftConfig{};
  bad.contrast_threshold = 0;
  EXPECT_EQ(ValidateSiftConfig(bad).code(), StatusCode::kInvalidArgument);
}

TEST(Sift, DescriptorsMatchTheSameObjectInAnotherView) {
  const cv::Mat box = ReadGray(kOpenCvData + "box.png");
  const cv::Mat scene = ReadGray(kOpenCvData + "box_in_scene.png");
  ASSERT_FALSE(box.empty() || scene.empty());
  auto a = ExtractSift(box, SiftConfig{});
  auto b = ExtractSift(scene, SiftConfig{});
  ASSERT_TRUE(a.ok() && b.ok());
  cv::BFMatcher matcher(cv::NORM_L2);
  std::vector<std::vector<cv::DMatch>> knn;
  matcher.knnMatch(ToCvFloatDescriptors(*a), ToCvFloatDescriptors(*b), knn, 2);
  int good = 0;
  for (const auto& m : knn) good += m.size() == 2 && m[0].distance < 0.75f * m[1].distance;
  std::printf(
      "box.png vs box_in_scene.png: %zu and %zu SIFT features, %d pass Lowe's ratio "
      "test\n",
      a->size(), b->size(), good);
  EXPECT_GE(good, 40);
}

TEST(Sift, PrecomputedSetsAreValidated) {
  std::vector<Keypoint> keypoints(2);
  keypoints[0] = {10, 20, 4, 90, 0.1f, 1};
  keypoints[1] = {30, 40, 8, -1, 0.2f, 2};
  std::vector<float> values(2 * kSiftDimensions);
  for (size_t i = 0; i < values.size(); ++i) values[i] = float(i % 50);
  std::vector<uint8_t> bytes(values.size() * 4);
  for (size_t i = 0; i < values.size(); ++i) {
    const uint32_t bits = std::bit_cast<uint32_t>(values[i]);
    for (int k = 0; k < 4; ++k) bytes[4 * i + k] = uint8_t(bits >> (8 * k));  // little-endian
  }
  auto set = MakeFloatFeatureSet(64, 48, keypoints, bytes);
  ASSERT_TRUE(set.ok()) << set.status().ToString();
  EXPECT_EQ(set->descriptors, values);
  EXPECT_EQ(set->descriptor(1)[0], values[kSiftDimensions]);

  auto short_bytes = std::vector<uint8_t>(bytes.begin(), bytes.end() - 4);
  EXPECT_EQ(MakeFloatFeatureSet(64, 48, keypoints, short_bytes).status().code(),
            StatusCode::kInvalidArgument);
  auto outside = keypoints;
  outside[1].x = 64;
  auto status = MakeFloatFeatureSet(64, 48, outside, bytes).status();
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("keypoints[1]"), std::string::npos) << status.message();
  FloatFeatureSet nan = *set;
  nan.descriptors[kSiftDimensions + 5] = std::nanf("");
  status = ValidateFloatFeatures(nan);
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("descriptors[1][5]"), std::string::npos) << status.message();
  FloatFeatureSet uneven = *set;
  uneven.descriptors.pop_back();
  EXPECT_EQ(ValidateFloatFeatures(uneven).code(), StatusCode::kInvalidArgument);
  FloatFeatureSet no_size = *set;
  no_size.image_width = 0;
  EXPECT_EQ(ValidateFloatFeatures(no_size).code(), StatusCode::kInvalidArgument);

  const FloatFeatureSet second = SelectFloatFeatures(*set, {1});
  ASSERT_EQ(second.size(), 1u);
  EXPECT_EQ(second.keypoints[0], keypoints[1]);
  EXPECT_TRUE(std::equal(second.descriptors.begin(), second.descriptors.end(),
                         values.begin() + kSiftDimensions));

  DynamicObjects objects;
  objects.boxes.push_back({0, 0.9f, cv::Rect2f(0, 0, 20, 30)});
  auto split = ClassifyDescriptors(*set, objects, FilterConfig{});
  ASSERT_TRUE(split.ok()) << split.status().ToString();
  EXPECT_EQ(split->dynamic_indices, (std::vector<uint32_t>{0}));
  EXPECT_EQ(split->static_indices, (std::vector<uint32_t>{1}));
}

// ---- Float vocabulary on controlled data -----------------------------------------------------

// `clusters` well separated Gaussian blobs in `dims` dimensions; image i holds `per_image`
// samples of blob (i + j) % clusters for j = 0..per_image-1.
std::vector<std::vector<float>> Blobs(int clusters, int dims, int images, int per_image,
                                      uint32_t seed, std::vector<std::vector<float>>* centres) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.0f, 1.0f);
  std::uniform_real_distribution<float> where(0.0f, 200.0f);
  centres->assign(size_t(clusters), std::vector<float>(size_t(dims)));
  for (auto& c : *centres) {
    for (auto& v : c) v = where(rng);
  }
  std::vector<std::vector<float>> out(static_cast<size_t>(images));
  for (int i = 0; i < images; ++i) {
    for (int j = 0; j < per_image; ++j) {
      const auto& c = (*centres)[size_t((i + j) % clusters)];
      for (int d = 0; d < dims; ++d) out[size_t(i)].push_back(c[size_t(d)] + noise(rng));
    }
  }
  return out;
}

TEST(FloatVocabulary, KMeansSeparatesBlobsIntoWords) {
  std::vector<std::vector<float>> centres;
  const auto images = Blobs(8, 16, 40, 5, 3, &centres);
  FloatTrainerConfig config;
  config.branching = 8;
  config.depth = 1;
  auto vocabulary = FloatVocabulary::Train(images, 16, config);
  ASSERT_TRUE(vocabulary.ok()) << vocabulary.status().ToString();
  const auto& v = **vocabulary;
  EXPECT_EQ(v.word_count(), 8u);
  EXPECT_EQ(v.node_count(), 9u);
  // Every blob centre is its own word, and each training sample lands on its blob's word.
  std::set<WordId> words;
  for (const auto& c : centres) words.insert(v.WordOf(c.data()));
  EXPECT_EQ(words.size(), 8u);
  for (const auto& image : images) {
    for (size_t k = 0; k + 16 <= image.size(); k += 16) {
      float best = 1e30f;
      size_t nearest = 0;
      for (size_t c = 0; c < centres.size(); ++c) {
        const float d = SquaredL2(image.data() + k, centres[c].data(), 16);
        if (d < best) {
          best = d;
          nearest = c;
        }
      }
      EXPECT_EQ(v.WordOf(image.data() + k), v.WordOf(centres[nearest].data()));
    }
  }
  // Image i holds blobs i..i+4 (mod 8): every blob is in 25 of the 40 images, idf ln(40/25).
  for (WordId w = 0; w < v.word_count(); ++w) {
    EXPECT_NEAR(v.WordWeight(w), std::log(40.0 / 25.0), 1e-5);
  }
}

TEST(FloatVocabulary, TransformGivesTfIdfVectorsAndDirectIndex) {
  std::vector<std::vector<float>> centres;
  const auto images = Blobs(27, 8, 30, 20, 5, &centres);
  FloatTrainerConfig config;
  config.branching = 3;
  config.depth = 3;
  auto vocabulary = FloatVocabulary::Train(images, 8, config);
  ASSERT_TRUE(vocabulary.ok());
  const auto& v = **vocabulary;
  EXPECT_LE(v.word_count(), 27u);
  EXPECT_GE(v.word_count(), 20u);
  // A frame: blob 0 three times, blob 1 once.
  std::vector<float> frame;
  for (int c : {0, 0, 0, 1})
    frame.insert(frame.end(), centres[size_t(c)].begin(), centres[size_t(c)].end());
  BowVector bow;
  DirectIndex direct;
  v.Transform(frame, &bow, &direct, 0);
  const WordId w0 = v.WordOf(centres[0].data());
  const WordId w1 = v.WordOf(centres[1].data());
  ASSERT_NE(w0, w1);
  ASSERT_EQ(bow.size(), 2u);
  EXPECT_LT(bow[0].word, bow[1].word);
  for (const auto& e : bow) {
    const double tf = e.word == w0 ? 0.75 : 0.25;
    EXPECT_NEAR(e.weight, tf * v.WordWeight(e.word), 1e-6);
  }
  // Direct index at the words: two groups, features {0,1,2} and {3}.
  ASSERT_EQ(direct.node_count(), 2u);
  EXPECT_EQ(direct.offsets.back(), 4u);
  // levels_up >= depth: everything under the root.
  v.Transform(frame, nullptr, &direct, 3);
  ASSERT_EQ(direct.node_count(), 1u);
  EXPECT_EQ(direct.node_ids[0], 0u);
  EXPECT_EQ(direct.features_of(0).size(), 4u);
  // A partial trailing row is ignored; nothing in, nothing out.
  frame.push_back(1.0f);
  v.Transform(frame, &bow, nullptr, 0);
  EXPECT_EQ(bow.size(), 2u);
  v.Transform({}, &bow, nullptr, 0);
  EXPECT_TRUE(bow.empty());
}

TEST(FloatVocabulary, DeterministicForASeedAtAnyThreadCount) {
  std::vector<std::vector<float>> centres;
  const auto images = Blobs(50, 32, 60, 200, 11, &centres);  // 12000 descriptors: 3 chunks
  FloatTrainerConfig config;
  config.branching = 6;
  config.depth = 3;
  config.max_fit_samples = 5000;
  config.threads = 1;
  auto one = FloatVocabulary::Train(images, 32, config);
  config.threads = 2;
  auto two = FloatVocabulary::Train(images, 32, config);
  config.threads = 1;
  auto again = FloatVocabulary::Train(images, 32, config);
  config.seed = 2;
  auto other = FloatVocabulary::Train(images, 32, config);
  ASSERT_TRUE(one.ok() && two.ok() && again.ok() && other.ok());
  EXPECT_EQ((*one)->checksum(), (*two)->checksum());
  EXPECT_EQ((*one)->checksum(), (*again)->checksum());
  EXPECT_NE((*one)->checksum(), (*other)->checksum());
}

TEST(FloatVocabulary, SurvivesDuplicatesAndRejectsBadInput) {
  // Every descriptor identical: one child under the root, one word.
  std::vector<std::vector<float>> same(5, std::vector<float>(4 * 10, 7.0f));
  FloatTrainerConfig config;
  config.branching = 4;
  config.depth = 3;
  auto v = FloatVocabulary::Train(same, 4, config);
  ASSERT_TRUE(v.ok()) << v.status().ToString();
  EXPECT_EQ((*v)->word_count(), 1u);
  // Three distinct values with k = 4: three words.
  std::vector<std::vector<float>> three = {{1, 1, 2, 2, 3, 3, 1, 1, 2, 2}};
  auto t = FloatVocabulary::Train(three, 2, config);
  ASSERT_TRUE(t.ok());
  EXPECT_EQ((*t)->word_count(), 3u);

  EXPECT_EQ(FloatVocabulary::Train({{1, 2, 3}}, 2, config).status().code(),
            StatusCode::kInvalidArgument);  // not a multiple of dims
  EXPECT_EQ(FloatVocabulary::Train({{1, 2}}, 2, config).status().code(),
            StatusCode::kInvalidArgument);  // fewer descriptors than k
  EXPECT_EQ(
      FloatVocabulary::Train({{1, std::nanf(""), 3, 4, 5, 6, 7, 8}}, 2, config).status().code(),
      StatusCode::kInvalidArgument);
  config.branching = 1;
  EXPECT_EQ(ValidateFloatTrainerConfig(config).code(), StatusCode::kInvalidArgument);
  config = FloatTrainerConfig{};
  config.depth = 11;
  EXPECT_EQ(ValidateFloatTrainerConfig(config).code(), StatusCode::kInvalidArgument);
}

TEST(FloatVocabulary, SaveLoadRoundTripAndCorruption) {
  std::vector<std::vector<float>> centres;
  const auto images = Blobs(30, 16, 20, 40, 9, &centres);
  FloatTrainerConfig config;
  config.branching = 5;
  config.depth = 2;
  auto trained = FloatVocabulary::Train(images, 16, config);
  ASSERT_TRUE(trained.ok());
  const std::string path = TempPath("roundtrip.pdbfv");
  ASSERT_TRUE((*trained)->Save(path).ok());
  auto loaded = FloatVocabulary::Load(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
  EXPECT_EQ((*loaded)->checksum(), (*trained)->checksum());
  EXPECT_EQ((*loaded)->word_count(), (*trained)->word_count());
  EXPECT_EQ((*loaded)->dimensions(), 16);
  for (const auto& c : centres)
    EXPECT_EQ((*loaded)->WordOf(c.data()), (*trained)->WordOf(c.data()));
  EXPECT_FALSE(fs::exists(path + ".tmp"));

  auto read = ReadWholeFile(path);
  ASSERT_TRUE(read.ok()) << read.status().ToString();
  const std::string bytes = std::move(*read);
  auto write = [&](const std::string& name, const std::string& content) {
    const std::string p = TempPath(name);
    std::ofstream(p, std::ios::binary) << content;
    return p;
  };
  std::string flipped = bytes;
  flipped[bytes.size() - 7] ^= 0x10;  // a centre
  EXPECT_EQ(FloatVocabulary::Load(write("flipped.pdbfv", flipped)).status().code(),
            StatusCode::kCorruption);
  EXPECT_EQ(FloatVocabulary::Load(write("short.pdbfv", bytes.substr(0, bytes.size() - 4)))
                .status()
                .code(),
            StatusCode::kCorruption);
  EXPECT_EQ(FloatVocabulary::Load(write("header.pdbfv", bytes.substr(0, 30))).status().code(),
            StatusCode::kCorruption);
  std::string magic = bytes;
  magic[0] = 'X';
  EXPECT_EQ(FloatVocabulary::Load(write("magic.pdbfv", magic)).status().code(),
            StatusCode::kCorruption);
  EXPECT_EQ(FloatVocabulary::Load(TempPath("absent.pdbfv")).status().code(), StatusCode::kNotFound);
  EXPECT_EQ((*trained)->Save("/nonexistent-dir/x.pdbfv").code(), StatusCode::kIoError);
}

// ---- The Debian-trained SIFT vocabulary (fixture sift_vocabulary) ----------------------------

TEST(DebianSiftVocabulary, LoadsAndSeparatesPlaces) {
  auto vocabulary = rgbd::LoadOrTrainSiftVocabulary(rgbd::SiftVocabularyPath());
  ASSERT_TRUE(vocabulary.ok()) << vocabulary.status().ToString();
  const auto& v = **vocabulary;
  std::printf("SIFT vocabulary %s: k=%d L=%d, %u words, %u nodes, %.1f MB, checksum %s\n",
              rgbd::SiftVocabularyPath().c_str(), v.branching(), v.depth(), v.word_count(),
              v.node_count(), v.memory_bytes() / 1e6, v.checksum_hex().c_str());
  EXPECT_EQ(v.dimensions(), kSiftDimensions);
  EXPECT_GT(v.word_count(), 2000u);
  // The same object seen twice scores above unrelated images.
  auto bow_of = [&](const std::string& name) {
    auto f = ExtractSift(ReadGray(kOpenCvData + name), SiftConfig{});
    EXPECT_TRUE(f.ok());
    BowVector bow;
    v.Transform(f->descriptors, &bow, nullptr, 0);
    NormalizeForScoring(&bow, ScoringType::kL1);
    return bow;
  };
  const BowVector box = bow_of("box.png");
  const BowVector scene = bow_of("box_in_scene.png");
  const double same_object = Score(box, scene, ScoringType::kL1);
  for (const char* other : {"fruits.jpg", "baboon.jpg", "building.jpg"}) {
    const double unrelated = Score(box, bow_of(other), ScoringType::kL1);
    std::printf("L1 score box.png vs box_in_scene.png %.4f, vs %s %.4f\n", same_object, other,
                unrelated);
    EXPECT_GT(same_object, unrelated) << other;
  }
  EXPECT_NEAR(Score(box, box, ScoringType::kL1), 1.0, 1e-6);
}

}  // namespace
}  // namespace placedb
