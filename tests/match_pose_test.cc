// Relative poses on verified matches (issue 32) through PlaceDatabase and the features codec:
// slambook2-rgbd places stored with their camera and depth, queried with depth (metric PnP) and
// without (the essential matrix), against pose.txt; places or frames without a camera say why;
// a bad camera is INVALID_ARGUMENT and stores nothing; the geometry survives the stored value.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "core/pipeline/place_database.h"
#include "core/pose/relative_pose.h"
#include "core/storage/codec.h"
#include "tests/slambook_truth.h"
#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace placedb {
namespace {

#define REQUIRE_SHARED_DATA()                                                          \
  do {                                                                                 \
    if (!rgbd::HaveSharedData()) FAIL() << "missing " << rgbd::SharedDir() << "/data"; \
  } while (false)

using testing::SlambookCamera;
using testing::SlambookPoses;

// 2000 ORB features, as relative_pose_test: at 1000 slambook2's wide pairs keep too few inliers
// for a pose. Exhaustive verification; frames carry no dynamic objects.
DatabaseConfig PoseConfig() {
  DatabaseConfig config;
  config.orb.max_features = 2000;
  config.verification.mode = VerificationMode::kExhaustive;
  config.depth.stream_filter = false;  // Algorithm 1 is not what this tests
  return config;
}

std::unique_ptr<PlaceDatabase> MakeDatabase() {
  auto created = PlaceDatabase::Create(testing::DefaultVocabulary(), PoseConfig());
  EXPECT_TRUE(created.ok()) << created.status().ToString();
  return created.ok() ? std::move(created).value() : nullptr;
}

// slambook2 frame `index` (0-based): gray pixels, optionally its depth and camera.
Observation SlambookObservation(size_t index, bool depth, bool camera) {
  const auto frames = rgbd::SlambookFrames();
  Observation observation;
  observation.image = testing::ReadGray(frames.at(index).image_path);
  if (depth) {
    const cv::Mat raw = cv::imread(frames.at(index).depth_path, cv::IMREAD_UNCHANGED);
    EXPECT_EQ(raw.type(), CV_16U) << frames.at(index).depth_path;
    observation.depth = DepthObservation{raw, {}, {}};
  }
  if (camera) observation.camera = SlambookCamera();
  observation.metadata.agent_id = "slambook";
  observation.metadata.sequence = index + 1;
  return observation;
}

QueryOptions Verified() {
  QueryOptions options;
  options.top_k = 4;
  options.verified_only = true;
  return options;
}

// Places 1, 3 and 5 of slambook2 (stored as ids 1, 2, 3) with depth and camera; queries 2 and 4.
constexpr size_t kPlaceFrames[] = {0, 2, 4};
constexpr size_t kQueryFrames[] = {1, 3};

struct PoseError {
  size_t query_frame = 0;  // 1-based, as slambook2 names them
  size_t place_frame = 0;
  double rotation_deg = 0;
  double translation_m = 0;
  double direction_deg = 0;
};

struct PoseRefusal {
  size_t query_frame = 0;
  size_t place_frame = 0;
  std::string reason;  // Match::pose_unavailable
};

// Queries frames 2 and 4 against the stored places; the error of every verified match's pose.
// With `refusals`, a match without a pose is recorded there instead of failing the test.
std::vector<PoseError> CheckPoses(const PlaceDatabase& database, bool query_depth,
                                  bool expect_metric,
                                  std::vector<PoseRefusal>* refusals = nullptr) {
  const std::vector<Transform> truth = SlambookPoses();
  EXPECT_EQ(truth.size(), 5u);
  std::vector<PoseError> errors;
  for (size_t query : kQueryFrames) {
    auto result = database.Query(SlambookObservation(query, query_depth, true), Verified());
    EXPECT_TRUE(result.ok()) << result.status().ToString();
    if (!result.ok() || truth.size() != 5) continue;
    for (const Match& match : result->matches) {
      const size_t place_frame = kPlaceFrames[match.place - 1];
      SCOPED_TRACE("query frame " + std::to_string(query + 1) + " place frame " +
                   std::to_string(place_frame + 1));
      if (!match.relative_pose && refusals != nullptr) {
        std::printf("query %zu place %zu: no pose: %s\n", query + 1, place_frame + 1,
                    match.pose_unavailable.c_str());
        refusals->push_back({query + 1, place_frame + 1, match.pose_unavailable});
        continue;
      }
      EXPECT_TRUE(match.relative_pose.has_value()) << match.pose_unavailable;
      if (!match.relative_pose) continue;
      EXPECT_TRUE(match.pose_unavailable.empty());
      const RelativePose& pose = *match.relative_pose;
      EXPECT_EQ(pose.metric, expect_metric);
      EXPECT_GE(pose.inliers, 12);
      const Transform expected =
          ComposeTransforms(InvertTransform(truth[place_frame]), truth[query]);
      PoseError error{query + 1, place_frame + 1, RotationErrorDeg(pose.transform, expected),
                      TranslationErrorM(pose.transform, expected),
                      TranslationDirectionErrorDeg(pose.transform, expected)};
      std::printf(
          "query %zu place %zu: %s, %d inliers, rotation %.2f deg, translation %.3f m, "
          "direction %.2f deg\n",
          error.query_frame, error.place_frame, PoseSolverName(pose.solver), pose.inliers,
          error.rotation_deg, error.translation_m, error.direction_deg);
      errors.push_back(error);
    }
  }
  return errors;
}

double Median(std::vector<double> values) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  return values[values.size() / 2];
}

void StorePlaces(PlaceDatabase* database, bool depth, bool camera) {
  for (size_t frame : kPlaceFrames) {
    auto added = database->Add(SlambookObservation(frame, depth, camera));
    ASSERT_TRUE(added.ok()) << added.status().ToString();
    ASSERT_TRUE(added->stored) << added->rejection;
  }
}

TEST(MatchPoseTest, RgbdQueriesGetMetricPosesThatMatchTheGroundTruth) {
  REQUIRE_SHARED_DATA();
  auto database = MakeDatabase();
  ASSERT_TRUE(database);
  StorePlaces(database.get(), /*depth=*/true, /*camera=*/true);
  const std::vector<PoseError> errors =
      CheckPoses(*database, /*query_depth=*/true, /*expect_metric=*/true);
  // Every place verifies against both queries here (the wide pairs too, at 2000 ORB).
  EXPECT_GE(errors.size(), 4u);
  // relative_pose_test's bounds for the same data (its table: at most 1.22 deg, 9.9 cm; through
  // the pipeline, measured: at most 0.87 deg and 6.1 cm).
  for (const PoseError& e : errors) {
    SCOPED_TRACE("query " + std::to_string(e.query_frame) + " place " +
                 std::to_string(e.place_frame));
    EXPECT_LT(e.rotation_deg, 2.0);
    EXPECT_LT(e.translation_m, 0.12);
  }
}

// Without depth on either side the essential matrix gives rotation and direction. Measured
// (docs/poses.md): the close pairs (4-7 degrees, 0.2-0.7 m apart) within 0.65 degrees and 3.4 of
// direction; the wide ones are weak as monocular geometry is. Verification with both cameras
// fits the essential matrix, and from its inliers query 2 / place 5 and query 4 / place 1 are
// within 1.6 degrees and 5.4 of direction (they were 2.3 / 11 and 11 / 29 from the fundamental
// matrix's inliers); query 2 / place 1 (25 deg, 0.4 m) is left 4.5 degrees loose in direction
// by its own information, so the solver refuses it and the match says why.
TEST(MatchPoseTest, MonocularPlacesAndQueriesGetRotationAndDirection) {
  REQUIRE_SHARED_DATA();
  auto database = MakeDatabase();
  ASSERT_TRUE(database);
  StorePlaces(database.get(), /*depth=*/false, /*camera=*/true);
  std::vector<PoseRefusal> refusals;
  const std::vector<PoseError> errors =
      CheckPoses(*database, /*query_depth=*/false, /*expect_metric=*/false, &refusals);
  EXPECT_EQ(errors.size() + refusals.size(), 6u);
  auto close = [](size_t query, size_t place) {
    return (query == 2 && place == 3) || (query == 4 && (place == 3 || place == 5));
  };
  std::vector<double> rotations, directions;
  int close_pairs = 0;
  for (const PoseError& e : errors) {
    SCOPED_TRACE("query " + std::to_string(e.query_frame) + " place " +
                 std::to_string(e.place_frame));
    rotations.push_back(e.rotation_deg);
    directions.push_back(e.direction_deg);
    close_pairs += close(e.query_frame, e.place_frame);
    // Every pose it gives is a usable constraint; the close pairs more so.
    EXPECT_LT(e.rotation_deg, close(e.query_frame, e.place_frame) ? 1.0 : 2.0);
    EXPECT_LT(e.direction_deg, close(e.query_frame, e.place_frame) ? 6.0 : 8.0);
  }
  EXPECT_EQ(close_pairs, 3);
  for (const PoseRefusal& r : refusals) {
    SCOPED_TRACE("query " + std::to_string(r.query_frame) + " place " +
                 std::to_string(r.place_frame));
    EXPECT_FALSE(close(r.query_frame, r.place_frame));
    EXPECT_NE(r.reason.find("essential: a weak two-view geometry"), std::string::npos) << r.reason;
  }
  std::printf(
      "monocular: %zu poses (rotation error median %.2f deg, direction error median %.2f "
      "deg), %zu refused as weak\n",
      errors.size(), Median(rotations), Median(directions), refusals.size());
}

TEST(MatchPoseTest, WithoutACameraOnEitherSideTheMatchSaysWhy) {
  REQUIRE_SHARED_DATA();
  auto database = MakeDatabase();
  ASSERT_TRUE(database);
  StorePlaces(database.get(), /*depth=*/true, /*camera=*/false);
  // The depth alone gives no camera: the stored places have none.
  auto asked = database->Query(SlambookObservation(1, true, true), Verified());
  ASSERT_TRUE(asked.ok()) << asked.status().ToString();
  ASSERT_FALSE(asked->matches.empty());
  for (const Match& match : asked->matches) {
    EXPECT_FALSE(match.relative_pose.has_value());
    EXPECT_NE(match.pose_unavailable.find("stored without a camera"), std::string::npos)
        << match.pose_unavailable;
  }
  // A query without a camera computes no pose (and says so).
  auto plain = database->Query(SlambookObservation(1, false, false), Verified());
  ASSERT_TRUE(plain.ok()) << plain.status().ToString();
  ASSERT_FALSE(plain->matches.empty());
  for (const Match& match : plain->matches) {
    EXPECT_FALSE(match.relative_pose.has_value());
    EXPECT_NE(match.pose_unavailable.find("the frame has no camera"), std::string::npos)
        << match.pose_unavailable;
  }
  // relative_poses off: neither a pose nor a reason.
  QueryOptions off = Verified();
  off.relative_poses = false;
  auto skipped = database->Query(SlambookObservation(1, true, true), off);
  ASSERT_TRUE(skipped.ok());
  for (const Match& match : skipped->matches) {
    EXPECT_FALSE(match.relative_pose.has_value());
    EXPECT_TRUE(match.pose_unavailable.empty());
  }
}

TEST(MatchPoseTest, ABadCameraIsInvalidArgumentNamingTheFieldAndStoresNothing) {
  REQUIRE_SHARED_DATA();
  auto database = MakeDatabase();
  ASSERT_TRUE(database);
  struct Case {
    const char* what;
    void (*spoil)(Camera*);
    const char* field;
  };
  const Case cases[] = {
      {"zero focal length", [](Camera* c) { c->fx = 0; }, "camera.fx"},
      {"negative focal length", [](Camera* c) { c->fy = -500; }, "camera.fy"},
      {"NaN principal point", [](Camera* c) { c->cx = std::nan(""); }, "camera.cx"},
      {"unknown model", [](Camera* c) { c->distortion_model = "kannala_brandt8"; },
       "camera.distortion_model"},
      {"wrong coefficient count",
       [](Camera* c) {
         c->distortion_model = "plumb_bob";
         c->distortion = {0.1, 0.01};
       },
       "camera.distortion"},
      {"another image size",
       [](Camera* c) {
         c->width = 320;
         c->height = 240;
         c->cx /= 2;
         c->cy /= 2;
       },
       "camera.width/height"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    Observation observation = SlambookObservation(0, true, true);
    c.spoil(&*observation.camera);
    auto added = database->Add(observation);
    ASSERT_FALSE(added.ok());
    EXPECT_EQ(added.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(added.status().message().find(c.field), std::string::npos)
        << added.status().ToString();
    auto queried = database->Query(observation, Verified());
    ASSERT_FALSE(queried.ok());
    EXPECT_EQ(queried.status().code(), StatusCode::kInvalidArgument);
  }
  EXPECT_EQ(database->Stats().places, 0u);
  // A camera of size 0x0 is the frame's size.
  Observation sized = SlambookObservation(0, true, true);
  sized.camera->width = sized.camera->height = 0;
  auto added = database->Add(sized);
  ASSERT_TRUE(added.ok()) << added.status().ToString();
  EXPECT_TRUE(added->stored);
}

TEST(MatchPoseTest, TheStoredFeaturesValueKeepsTheGeometry) {
  FeatureSet orb;
  orb.image_width = 640;
  orb.image_height = 480;
  for (int i = 0; i < 3; ++i) {
    orb.keypoints.push_back({float(10 * i), float(20 * i), 31, 0, 1, i});
    orb.descriptors.push_back(Descriptor256());
  }
  const DirectIndex direct;
  FrameGeometry geometry;
  geometry.camera = PinholeCamera(640, 480, 500, 501, 320, 240);
  geometry.camera->distortion_model = "plumb_bob";
  geometry.camera->distortion = {0.1, -0.2, 0.001, 0.002, 0.01};
  geometry.depth_m = {1.5f, 0.0f, 7.25f};

  // Without geometry the value is the version-1 value it always was.
  const std::string plain = EncodeLocalFeatures(LocalFeatures(orb), direct);
  EXPECT_EQ(plain, EncodeFeatures(orb, direct));
  EXPECT_EQ(uint8_t(plain[0]), 1);
  LocalFeatures decoded;
  DirectIndex decoded_direct;
  FrameGeometry decoded_geometry;
  ASSERT_TRUE(
      DecodeLocalFeatures(plain, FeatureType::kOrb, &decoded, &decoded_direct, &decoded_geometry)
          .ok());
  EXPECT_TRUE(decoded_geometry.empty());

  const std::string with = EncodeLocalFeatures(LocalFeatures(orb), direct, geometry);
  EXPECT_EQ(uint8_t(with[0]), 2);
  ASSERT_TRUE(
      DecodeLocalFeatures(with, FeatureType::kOrb, &decoded, &decoded_direct, &decoded_geometry)
          .ok());
  EXPECT_EQ(decoded_geometry, geometry);
  EXPECT_EQ(decoded.keypoints().size(), 3u);
  // Readers that do not ask for the geometry still read the features.
  ASSERT_TRUE(DecodeLocalFeatures(with, FeatureType::kOrb, &decoded, &decoded_direct).ok());
  // A depth array of the wrong size, or a damaged camera, is corruption, never a silent pose.
  FrameGeometry short_depth = geometry;
  short_depth.depth_m.pop_back();
  const std::string bad_depth = EncodeLocalFeatures(LocalFeatures(orb), direct, short_depth);
  EXPECT_EQ(DecodeLocalFeatures(bad_depth, FeatureType::kOrb, &decoded, &decoded_direct,
                                &decoded_geometry)
                .code(),
            StatusCode::kCorruption);
  FrameGeometry bad_camera = geometry;
  bad_camera.camera->fx = -1;
  const std::string damaged = EncodeLocalFeatures(LocalFeatures(orb), direct, bad_camera);
  const Status refused =
      DecodeLocalFeatures(damaged, FeatureType::kOrb, &decoded, &decoded_direct, &decoded_geometry);
  EXPECT_EQ(refused.code(), StatusCode::kCorruption);
  EXPECT_NE(refused.message().find("camera"), std::string::npos) << refused.ToString();
  // Truncated anywhere in the geometry: corruption.
  for (size_t cut = plain.size(); cut < with.size(); ++cut) {
    EXPECT_FALSE(DecodeLocalFeatures(std::string_view(with).substr(0, cut), FeatureType::kOrb,
                                     &decoded, &decoded_direct, &decoded_geometry)
                     .ok())
        << cut;
  }
}

}  // namespace
}  // namespace placedb
