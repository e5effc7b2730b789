// VocabularyLearner (core/vocabulary/vocabulary_learning.h): a map's vocabulary learned from its
// own stored places, sampled with bounded memory, independently of the order places come in.
#include "core/vocabulary/vocabulary_learning.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdint>
#include <random>
#include <vector>

#include "core/features/sift_features.h"

namespace placedb {
namespace {

// Place `id`'s descriptors: noisy copies of a few of 40 "structures", so that places share words.
FeatureSet OrbPlace(uint64_t id, int count) {
  std::mt19937_64 structures(7);
  std::vector<Descriptor256> centres(40);
  for (Descriptor256& centre : centres) {
    for (uint64_t& word : centre.words) word = structures();
  }
  std::mt19937_64 rng(id * 7919 + 1);
  FeatureSet set;
  set.image_width = 640;
  set.image_height = 480;
  for (int i = 0; i < count; ++i) {
    Descriptor256 d = centres[rng() % centres.size()];
    for (int flip = 0; flip < 12; ++flip) {
      const unsigned bit = unsigned(rng() % 256);
      d.words[bit / 64] ^= uint64_t(1) << (bit % 64);
    }
    Keypoint keypoint;
    keypoint.x = float(rng() % 640);
    keypoint.y = float(rng() % 480);
    set.keypoints.push_back(keypoint);
    set.descriptors.push_back(d);
  }
  return set;
}

FloatFeatureSet SiftPlace(uint64_t id, int count) {
  std::mt19937_64 rng(id * 104729 + 3);
  std::uniform_real_distribution<float> value(0.0f, 1.0f);
  FloatFeatureSet set;
  set.image_width = 640;
  set.image_height = 480;
  for (int i = 0; i < count; ++i) {
    Keypoint keypoint;
    keypoint.x = float(rng() % 640);
    keypoint.y = float(rng() % 480);
    set.keypoints.push_back(keypoint);
    for (int d = 0; d < kSiftDimensions; ++d) set.descriptors.push_back(value(rng));
  }
  return set;
}

LearningOptions SmallOptions() {
  LearningOptions options;
  options.min_descriptors = 1000;
  options.min_places = 10;
  options.threads = 2;
  return options;
}

TEST(VocabularyLearning, ShapeFollowsTheAmountOfData) {
  EXPECT_EQ(LearnedVocabularyShape(500).depth, 4);
  EXPECT_EQ(LearnedVocabularyShape(5'000).depth, 5);
  EXPECT_EQ(LearnedVocabularyShape(20'000).depth, 6);
  EXPECT_EQ(LearnedVocabularyShape(100'000).depth, 6);
  EXPECT_EQ(LearnedVocabularyShape(1'600'000).depth, 6);
  EXPECT_EQ(LearnedVocabularyShape(50'000'000).depth, 6);
  EXPECT_EQ(LearnedVocabularyShape(100'000).branching, 10);
}

TEST(VocabularyLearning, LearnsABinaryVocabularyFromStoredPlaces) {
  VocabularyLearner learner(FeatureType::kOrb, SmallOptions());
  for (uint64_t id = 1; id <= 60; ++id) ASSERT_TRUE(learner.Offer(id, OrbPlace(id, 100)).ok());
  auto learned = learner.Learn();
  ASSERT_TRUE(learned.ok()) << learned.status().ToString();
  EXPECT_EQ(learned->vocabulary.feature_type(), FeatureType::kOrb);
  EXPECT_EQ(learned->places_offered, 60u);
  EXPECT_EQ(learned->descriptors_offered, 6000u);
  EXPECT_EQ(learned->descriptors_sampled, 6000u);  // under the bound: every place
  EXPECT_EQ(learned->shape.depth, 5);              // 6000 descriptors
  EXPECT_EQ(learned->vocabulary.depth(), 5);
  EXPECT_GT(learned->vocabulary.word_count(), 40u);

  // The map's places quantise with it: one place's own descriptors land on words it shares
  // with itself (a second transform is identical) and the vector is not empty.
  BowVector a, b;
  ASSERT_TRUE(learned->vocabulary.Transform(OrbPlace(5, 100), &a, nullptr, 0).ok());
  ASSERT_TRUE(learned->vocabulary.Transform(OrbPlace(5, 100), &b, nullptr, 0).ok());
  EXPECT_FALSE(a.empty());
  EXPECT_EQ(a, b);
}

TEST(VocabularyLearning, TheSampleIsBoundedAndDependsOnNeitherOrderNorThreads) {
  LearningOptions options = SmallOptions();
  options.max_sample_descriptors = 2000;
  std::vector<uint64_t> ids;
  for (uint64_t id = 1; id <= 200; ++id) ids.push_back(id);

  auto learn = [&](const std::vector<uint64_t>& order) {
    VocabularyLearner learner(FeatureType::kOrb, options);
    for (uint64_t id : order) {
      EXPECT_TRUE(learner.Offer(id, OrbPlace(id, 50)).ok());
      // Never more than the bound plus the place just offered.
      EXPECT_LE(learner.descriptors_sampled(), options.max_sample_descriptors);
    }
    auto learned = learner.Learn();
    EXPECT_TRUE(learned.ok()) << learned.status().ToString();
    return std::move(learned).value();
  };
  const LearnedVocabulary ascending = learn(ids);
  std::vector<uint64_t> shuffled = ids;
  std::shuffle(shuffled.begin(), shuffled.end(), std::mt19937(3));
  const LearnedVocabulary mixed = learn(shuffled);

  EXPECT_EQ(ascending.descriptors_offered, 10000u);
  EXPECT_LE(ascending.descriptors_sampled, 2000u);
  // Halving stops at the largest threshold that fits: at least a quarter of the bound is kept.
  EXPECT_GE(ascending.descriptors_sampled, 500u);
  EXPECT_EQ(ascending.places_sampled, mixed.places_sampled);
  EXPECT_EQ(ascending.descriptors_sampled, mixed.descriptors_sampled);
  EXPECT_EQ(ascending.vocabulary.checksum(), mixed.vocabulary.checksum());

  // Nor on the thread count: replicas of a map learn byte-identical vocabularies.
  options.threads = 1;
  const LearnedVocabulary one_thread = learn(shuffled);
  EXPECT_EQ(one_thread.vocabulary.checksum(), ascending.vocabulary.checksum());
  EXPECT_EQ(one_thread.vocabulary.Serialize(), ascending.vocabulary.Serialize());
  options.threads = 2;

  // Another seed samples other places (and so learns another vocabulary).
  options.seed = 2;
  const LearnedVocabulary reseeded = learn(ids);
  EXPECT_NE(reseeded.vocabulary.checksum(), ascending.vocabulary.checksum());
}

TEST(VocabularyLearning, AMapTooSmallIsAClearError) {
  VocabularyLearner learner(FeatureType::kOrb, LearningOptions{});  // 5000 descriptors, 10 places
  for (uint64_t id = 1; id <= 3; ++id) ASSERT_TRUE(learner.Offer(id, OrbPlace(id, 100)).ok());
  auto learned = learner.Learn();
  ASSERT_FALSE(learned.ok());
  EXPECT_EQ(learned.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(learned.status().message().find("too small to learn a vocabulary from: 300 stored "
                                            "descriptors in 3 places"),
            std::string::npos)
      << learned.status().ToString();
}

TEST(VocabularyLearning, FeaturesOfTheOtherFamilyAreRefused) {
  VocabularyLearner learner(FeatureType::kOrb, SmallOptions());
  const Status refused = learner.Offer(1, SiftPlace(1, 10));
  EXPECT_EQ(refused.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(learner.places_offered(), 0u);
  EXPECT_EQ(learner.descriptors_sampled(), 0u);
}

TEST(VocabularyLearning, BadOptionsAreRefused) {
  LearningOptions options;
  options.depth = 11;
  EXPECT_EQ(ValidateLearningOptions(options).code(), StatusCode::kInvalidArgument);
  options = {};
  options.branching = 1;
  EXPECT_EQ(ValidateLearningOptions(options).code(), StatusCode::kInvalidArgument);
  options = {};
  options.max_sample_descriptors = 10;
  EXPECT_EQ(ValidateLearningOptions(options).code(), StatusCode::kInvalidArgument);
}

TEST(VocabularyLearning, SiftMapsLearnAFloatVocabulary) {
  LearningOptions options = SmallOptions();
  options.depth = 3;
  VocabularyLearner learner(FeatureType::kSift, options);
  for (uint64_t id = 1; id <= 20; ++id) ASSERT_TRUE(learner.Offer(id, SiftPlace(id, 60)).ok());
  auto learned = learner.Learn();
  ASSERT_TRUE(learned.ok()) << learned.status().ToString();
  EXPECT_EQ(learned->vocabulary.feature_type(), FeatureType::kSift);
  EXPECT_EQ(learned->vocabulary.depth(), 3);
  EXPECT_EQ(learned->descriptors_sampled, 1200u);
}

// A map stores what it learned as bytes (AnyVocabulary::Serialize); damage is reported, never
// loaded.
TEST(VocabularyLearning, ALearnedVocabularyRoundTripsThroughItsBytes) {
  for (FeatureType type : {FeatureType::kOrb, FeatureType::kSift}) {
    LearningOptions options = SmallOptions();
    options.depth = 3;
    VocabularyLearner learner(type, options);
    for (uint64_t id = 1; id <= 20; ++id) {
      if (type == FeatureType::kOrb) {
        ASSERT_TRUE(learner.Offer(id, OrbPlace(id, 60)).ok());
      } else {
        ASSERT_TRUE(learner.Offer(id, SiftPlace(id, 60)).ok());
      }
    }
    auto learned = learner.Learn();
    ASSERT_TRUE(learned.ok()) << learned.status().ToString();
    const std::string bytes = learned->vocabulary.Serialize();
    auto parsed = AnyVocabulary::Parse(bytes);
    ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
    EXPECT_EQ(parsed->feature_type(), type);
    EXPECT_EQ(parsed->checksum(), learned->vocabulary.checksum());
    EXPECT_EQ(parsed->Serialize(), bytes);

    std::string damaged = bytes;
    damaged[damaged.size() - 5] ^= 0x10;
    auto refused = AnyVocabulary::Parse(damaged);
    EXPECT_EQ(refused.status().code(), StatusCode::kCorruption) << refused.status().ToString();
    EXPECT_EQ(
        AnyVocabulary::Parse(std::string_view(bytes).substr(0, bytes.size() - 32)).status().code(),
        StatusCode::kCorruption);
  }
  EXPECT_FALSE(AnyVocabulary::Parse("").ok());
  EXPECT_FALSE(AnyVocabulary::Parse(std::string_view()).ok());
}

}  // namespace
}  // namespace placedb
