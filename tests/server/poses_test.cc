// Relative poses through the service (issue 32): a stream's camera (IngestHeader.camera) kept
// with every place and its keypoint depths, across a restart; Query matches carrying the pose,
// its information and the pose stage's time; a frame without a camera told why; bad cameras
// refused naming the field, with nothing stored.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

v1::Camera SlambookCamera() {
  const CameraIntrinsics k = rgbd::SlambookIntrinsics();
  v1::Camera camera;  // 0x0: the frames' size
  camera.set_fx(k.fx);
  camera.set_fy(k.fy);
  camera.set_cx(k.cx);
  camera.set_cy(k.cy);
  return camera;
}

class PosesTest : public ServerTest {
 protected:
  // 2000 ORB features and exhaustive verification (slambook2's wide pairs need them, as in
  // match_pose_test); Algorithm 1 is not what this tests.
  void CreateRoom() {
    v1::MapConfig config;
    config.mutable_orb()->set_max_features(2000);
    config.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
    config.mutable_depth()->set_stream_filter(false);
    CreateMap("room", config);
  }

  v1::QueryResponse QueryVerified(const v1::Observation& observation) {
    grpc::ClientContext context;
    v1::QueryRequest request;
    request.set_map("room");
    *request.mutable_observation() = observation;
    request.mutable_options()->set_top_k(3);
    request.mutable_options()->set_verified_only(true);
    v1::QueryResponse response;
    const grpc::Status status = stub_->Query(&context, request, &response);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return response;
  }

  v1::Place GetPlaceWithFeatures(uint32_t id) {
    grpc::ClientContext context;
    v1::GetPlaceRequest request;
    request.set_map("room");
    request.set_place_id(id);
    request.set_include_features(true);
    v1::Place place;
    const grpc::Status status = stub_->GetPlace(&context, request, &place);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return place;
  }

  void ExpectStoredGeometry(uint32_t id) {
    SCOPED_TRACE("place " + std::to_string(id));
    const v1::Place place = GetPlaceWithFeatures(id);
    ASSERT_TRUE(place.has_camera());
    const v1::Camera expected = SlambookCamera();
    EXPECT_EQ(place.camera().width(), 640u);  // the frame's size, resolved when stored
    EXPECT_EQ(place.camera().height(), 480u);
    EXPECT_EQ(place.camera().fx(), expected.fx());
    EXPECT_EQ(place.camera().cy(), expected.cy());
    EXPECT_EQ(place.camera().distortion_model(), "none");
    ASSERT_EQ(place.keypoint_depth_m_size(), place.features().keypoints_size());
    int with_depth = 0;
    for (float depth : place.keypoint_depth_m()) {
      EXPECT_GE(depth, 0.0f);
      with_depth += depth > 0 ? 1 : 0;
    }
    // slambook2's room is within the sensor's range almost everywhere.
    EXPECT_GT(with_depth, place.keypoint_depth_m_size() / 2);
  }
};

TEST_F(PosesTest, AStreamCameraIsKeptWithEveryPlaceAndQueriesGetPoses) {
  StartServer(Config());
  CreateRoom();
  const auto frames = rgbd::SlambookFrames();
  ASSERT_EQ(frames.size(), 5u);
  v1::IngestHeader header;
  header.set_map("room");
  *header.mutable_camera() = SlambookCamera();
  const IngestOutcome outcome = IngestWithHeader(
      stub_.get(), header,
      {RgbdObservation(frames[0], "robot", 1), RgbdObservation(frames[2], "robot", 3),
       RgbdObservation(frames[4], "robot", 5)});
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), 3u);
  for (const v1::IngestResponse& response : outcome.responses) {
    ASSERT_TRUE(response.stored()) << response.rejection() << response.error().message();
  }
  for (uint32_t id = 1; id <= 3; ++id) ExpectStoredGeometry(id);

  // Frame 2 with its depth and camera: every verified match carries a metric pose.
  v1::Observation query = RgbdObservation(frames[1], "robot", 2);
  *query.mutable_camera() = SlambookCamera();
  const v1::QueryResponse answer = QueryVerified(query);
  ASSERT_GE(answer.matches_size(), 2);
  for (const v1::Match& match : answer.matches()) {
    SCOPED_TRACE("place " + std::to_string(match.place_id()));
    ASSERT_TRUE(match.has_relative_pose()) << match.pose_unavailable();
    const v1::RelativePose& pose = match.relative_pose();
    EXPECT_EQ(pose.transform_size(), 16);
    EXPECT_EQ(pose.information_size(), 36);
    EXPECT_TRUE(pose.metric());
    EXPECT_EQ(pose.solver().rfind("pnp_", 0), 0u) << pose.solver();
    EXPECT_GE(pose.inliers(), 12);
    EXPECT_GT(pose.rms_error_px(), 0.0);
    // A rigid transform: the rotation's rows are unit vectors, the last row is 0 0 0 1.
    for (int row = 0; row < 3; ++row) {
      double norm = 0;
      for (int col = 0; col < 3; ++col) norm += std::pow(pose.transform(row * 4 + col), 2);
      EXPECT_NEAR(norm, 1.0, 1e-9);
    }
    EXPECT_EQ(pose.transform(15), 1.0);
    // The information is symmetric with a positive diagonal.
    for (int i = 0; i < 6; ++i) {
      EXPECT_GT(pose.information(i * 6 + i), 0.0);
      for (int j = 0; j < 6; ++j) {
        EXPECT_NEAR(pose.information(i * 6 + j), pose.information(j * 6 + i),
                    1e-6 * std::abs(pose.information(i * 6 + i)) + 1e-9);
      }
    }
    EXPECT_TRUE(match.pose_unavailable().empty());
  }
  EXPECT_GT(answer.timings().pose_ms(), 0.0);

  // Without a camera (and without depth intrinsics) the frame gets no pose, and is told why.
  const v1::QueryResponse plain = QueryVerified(RgbdObservation(frames[1], "robot", 2));
  ASSERT_GE(plain.matches_size(), 1);
  for (const v1::Match& match : plain.matches()) {
    EXPECT_FALSE(match.has_relative_pose());
    EXPECT_NE(match.pose_unavailable().find("the frame has no camera"), std::string::npos)
        << match.pose_unavailable();
  }

  // The geometry is in the stored value: it survives a restart.
  StopServer();
  StartServer(Config());
  for (uint32_t id = 1; id <= 3; ++id) ExpectStoredGeometry(id);
  const v1::QueryResponse again = QueryVerified(query);
  ASSERT_EQ(again.matches_size(), answer.matches_size());
  for (int i = 0; i < again.matches_size(); ++i) {
    EXPECT_TRUE(again.matches(i).has_relative_pose()) << again.matches(i).pose_unavailable();
  }
}

// Loop closure on the RTAB-Map loop with a stream camera (no depth: its intrinsics are not
// published, so a plausible pinhole camera stands in): every accepted loop carries its relative
// pose (the essential matrix's rotation and direction), or says why it has none.
TEST_F(PosesTest, AcceptedLoopsCarryTheirPose) {
  StartServer(Config());
  CreateMap("loop");
  std::vector<v1::Observation> observations;
  for (int frame = 1; frame <= 84; ++frame) observations.push_back(RtabmapObservation(frame, "a"));
  v1::IngestHeader header;
  header.set_map("loop");
  header.set_loop_closure(true);
  header.mutable_camera()->set_fx(500);
  header.mutable_camera()->set_fy(500);
  header.mutable_camera()->set_cx(320);
  header.mutable_camera()->set_cy(240);
  const IngestOutcome outcome = IngestWithHeader(stub_.get(), header, observations);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  int loops = 0, posed = 0;
  for (const v1::IngestResponse& response : outcome.responses) {
    ASSERT_FALSE(response.has_error()) << response.error().message();
    const v1::LoopClosure& loop = response.loop_closure();
    if (!loop.loop_found()) {
      EXPECT_FALSE(loop.has_loop_pose());
      continue;
    }
    ++loops;
    SCOPED_TRACE("frame " + std::to_string(response.sequence()) + " -> place " +
                 std::to_string(loop.loop_place_id()));
    if (!loop.has_loop_pose()) {
      EXPECT_FALSE(loop.loop_pose_unavailable().empty());
      continue;
    }
    ++posed;
    EXPECT_TRUE(loop.loop_pose_unavailable().empty());
    EXPECT_EQ(loop.loop_pose().transform_size(), 16);
    EXPECT_EQ(loop.loop_pose().information_size(), 36);
    EXPECT_FALSE(loop.loop_pose().metric());  // no depth: rotation and direction
    EXPECT_EQ(loop.loop_pose().solver(), "essential");
    EXPECT_GE(loop.loop_pose().inliers(), 12);
  }
  EXPECT_GT(loops, 0);
  EXPECT_GT(posed, 0);
  std::printf("loop closure: %d accepted loops, %d with a pose\n", loops, posed);
}

TEST_F(PosesTest, ABadCameraIsInvalidArgumentNamingTheFieldAndNothingIsStored) {
  StartServer(Config());
  CreateRoom();
  const auto frames = rgbd::SlambookFrames();
  ASSERT_FALSE(frames.empty());

  // Query: zero, negative and NaN intrinsics, an unknown model, the wrong size.
  struct Case {
    const char* what;
    void (*spoil)(v1::Camera*);
    const char* field;
  };
  const Case cases[] = {
      {"zero fx", [](v1::Camera* c) { c->set_fx(0); }, "observation.camera.fx"},
      {"negative fy", [](v1::Camera* c) { c->set_fy(-1); }, "observation.camera.fy"},
      {"NaN cx", [](v1::Camera* c) { c->set_cx(std::nan("")); }, "observation.camera.cx"},
      {"unknown model", [](v1::Camera* c) { c->set_distortion_model("kannala_brandt8"); },
       "observation.camera.distortion_model"},
      {"coefficients without a model", [](v1::Camera* c) { c->add_distortion(0.1); },
       "observation.camera.distortion"},
      {"another size",
       [](v1::Camera* c) {
         c->set_width(320);
         c->set_height(240);
         c->set_cx(160);
         c->set_cy(120);
       },
       "observation.camera.width/height"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    v1::Observation observation = RgbdObservation(frames[0], "robot", 1);
    v1::Camera camera = SlambookCamera();
    c.spoil(&camera);
    *observation.mutable_camera() = camera;
    v1::QueryResponse response;
    const grpc::Status status = Query("room", observation, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(status.error_message().find(c.field), std::string::npos) << status.error_message();

    // The same frame ingested: refused, the stream goes on.
    const IngestOutcome outcome = IngestAll(stub_.get(), "room", {observation});
    ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
    ASSERT_EQ(outcome.responses.size(), 1u);
    EXPECT_FALSE(outcome.responses[0].stored());
    EXPECT_EQ(outcome.responses[0].error().code(), int(grpc::StatusCode::INVALID_ARGUMENT));
    EXPECT_NE(outcome.responses[0].error().message().find("camera"), std::string::npos)
        << outcome.responses[0].error().message();
  }

  // A bad stream camera ends the stream at its header.
  v1::IngestHeader header;
  header.set_map("room");
  *header.mutable_camera() = SlambookCamera();
  header.mutable_camera()->set_fx(std::nan(""));
  const IngestOutcome refused =
      IngestWithHeader(stub_.get(), header, {RgbdObservation(frames[0], "robot", 1)});
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(refused.status.error_message().find("header.camera.fx"), std::string::npos)
      << refused.status.error_message();

  EXPECT_EQ(Stats("room").places(), 0u);
}

}  // namespace
}  // namespace placedb::server_testing
