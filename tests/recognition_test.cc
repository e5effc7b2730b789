// Recognition on real data: does the right place rank first?
//  - RTAB-Map loop: database = the first pass (frames 1-40), queries = the revisit (41-84),
//    correct = top-1 is marked in ground_truth.bmp.
//  - CamVid adjacent frames: database = even positions of each sequence, queries = odd positions,
//    correct = top-1 is a database frame of the same sequence within 1 s (30 video frames).
//    Run without filtering (BoBW) and with the label maps as exact dynamic masks (BoBW+DO).
// The default vocabulary was trained on Debian's sample images only, never on these frames.
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>

#include "core/pipeline/place_database.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

using testing::CamVidFrame;

struct Rate {
  int correct = 0;
  int queries = 0;
  double percent() const { return queries ? 100.0 * correct / queries : 0.0; }
};

std::unique_ptr<PlaceDatabase> MakeDatabase(const DatabaseConfig& config) {
  auto db = PlaceDatabase::Create(testing::DefaultVocabulary(), config);
  EXPECT_TRUE(db.ok()) << db.status().ToString();
  return db.ok() ? std::move(db).value() : nullptr;
}

Rate RunRtabmapLoop(const DatabaseConfig& config, bool require_verified) {
  auto db = MakeDatabase(config);
  if (!db) return {};
  cv::Mat truth = testing::RtabmapGroundTruth();
  for (int frame = 1; frame <= 40; ++frame) {
    Observation observation;
    observation.image = testing::ReadGray(testing::RtabmapFramePath(frame));
    observation.metadata.sequence = uint64_t(frame);
    auto added = db->Add(observation);  // a bare corridor view may be refused as invalid
    EXPECT_TRUE(added.ok()) << "frame " << frame;
  }
  Rate rate;
  for (int frame = 41; frame <= 84; ++frame) {
    Observation observation;
    observation.image = testing::ReadGray(testing::RtabmapFramePath(frame));
    auto result = db->Query(observation, {});
    EXPECT_TRUE(result.ok());
    ++rate.queries;
    if (!result.ok() || result->matches.empty()) continue;
    const Match& best = result->matches[0];
    const int matched_frame = int(best.metadata.sequence);
    if (truth.at<uint8_t>(frame - 1, matched_frame - 1) > 0 &&
        (!require_verified || best.verified)) {
      ++rate.correct;
    }
  }
  return rate;
}

TEST(Recognition, RtabmapLoopRevisitsRankFirst) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  DatabaseConfig config;
  config.orb.max_features = 1000;
  const Rate plain = RunRtabmapLoop(config, false);
  std::printf("[recognition] rtabmap-loop top-1, no verification: %d/%d = %.1f %%\n", plain.correct,
              plain.queries, plain.percent());
  EXPECT_GE(plain.percent(), 80.0);

  config.verification.mode = VerificationMode::kExhaustive;
  const Rate verified = RunRtabmapLoop(config, true);
  std::printf(
      "[recognition] rtabmap-loop top-1 verified (exhaustive, >= %d inliers): %d/%d = %.1f %%\n",
      config.verification.min_inliers, verified.correct, verified.queries, verified.percent());
  EXPECT_GE(verified.percent(), 70.0);
}

struct CamVidRates {
  Rate all;
  Rate covered10;  // queries with more than 10 % dynamic coverage
};

CamVidRates RunCamVidAdjacent(const DatabaseConfig& config, bool use_masks) {
  const std::vector<CamVidFrame> frames = testing::CamVidFrames();
  EXPECT_EQ(frames.size(), 701u);
  auto db = MakeDatabase(config);
  if (!db) return {};
  std::vector<const CamVidFrame*> queries;
  std::string sequence;
  int position = 0;
  auto observe = [&](const CamVidFrame& frame) {
    Observation observation;
    observation.image = testing::ReadGray(frame.image_path);
    observation.metadata.agent_id = frame.sequence;
    observation.metadata.sequence = uint64_t(frame.frame);
    if (use_masks) observation.dynamic.mask = testing::CamVidDynamicMask(frame);
    return observation;
  };
  for (const CamVidFrame& frame : frames) {
    if (frame.sequence != sequence) {
      sequence = frame.sequence;
      position = 0;
    }
    if (position++ % 2 == 0) {
      auto added = db->Add(observe(frame));
      EXPECT_TRUE(added.ok());
    } else {
      queries.push_back(&frame);
    }
  }
  CamVidRates rates;
  for (const CamVidFrame* frame : queries) {
    Observation observation = observe(*frame);
    const double coverage =
        cv::countNonZero(testing::CamVidDynamicMask(*frame)) / double(observation.image.total());
    auto result = db->Query(observation, {});
    EXPECT_TRUE(result.ok());
    bool correct = false;
    if (result.ok() && !result->matches.empty()) {
      const Match& best = result->matches[0];
      correct = best.metadata.agent_id == frame->sequence &&
                std::abs(int64_t(best.metadata.sequence) - frame->frame) <= 30;
    }
    ++rates.all.queries;
    rates.all.correct += correct;
    if (coverage > 0.10) {
      ++rates.covered10.queries;
      rates.covered10.correct += correct;
    }
  }
  return rates;
}

TEST(Recognition, CamVidAdjacentFramesRankFirstWithAndWithoutFiltering) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  DatabaseConfig config;
  config.orb.max_features = 1000;
  const CamVidRates plain = RunCamVidAdjacent(config, false);
  config.filter.method = FilterMethod::kExactCoverage;
  config.filter.sensitivity_threshold = 0.25f;
  const CamVidRates filtered = RunCamVidAdjacent(config, true);
  std::printf(
      "[recognition] camvid adjacent top-1, ORB 1000: BoBW %d/%d = %.1f %%, "
      "BoBW+DO (label masks, exact 25 %%) %d/%d = %.1f %%\n",
      plain.all.correct, plain.all.queries, plain.all.percent(), filtered.all.correct,
      filtered.all.queries, filtered.all.percent());
  std::printf(
      "[recognition] camvid queries with > 10 %% dynamic coverage: BoBW %d/%d = %.1f %%, "
      "BoBW+DO %d/%d = %.1f %%\n",
      plain.covered10.correct, plain.covered10.queries, plain.covered10.percent(),
      filtered.covered10.correct, filtered.covered10.queries, filtered.covered10.percent());
  EXPECT_GE(plain.all.percent(), 75.0);
  EXPECT_GE(filtered.all.percent(), 75.0);
}

}  // namespace
}  // namespace placedb
