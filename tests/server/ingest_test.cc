// The Ingest stream: agents streaming at once (also under ThreadSanitizer: the Concurrent* tests),
// responses in order under the tightest limits, a frame's matches against the map before it,
// depth frames (Algorithm 1's state per agent), loop-closure mode and server-side detection.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <sys/mount.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "tests/server/server_fixture.h"
#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace placedb::server_testing {
namespace {

// Several agents stream at once: A and B the RTAB-Map loop's first pass (alternate frames), C
// CamVid frames with their dynamic masks into the same map, D CamVid frames with boxes into
// another map. Then the revisit (frames 41-84) is queried. Run under ThreadSanitizer too.
TEST_F(ServerTest, ConcurrentAgentsIngestThenRevisitsRankFirst) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("loop");
  CreateMap("street");

  std::vector<v1::Observation> agent_a, agent_b, agent_c, agent_d;
  for (int frame = 1; frame <= 40; ++frame) {
    (frame % 2 ? agent_a : agent_b)
        .push_back(RtabmapObservation(frame, frame % 2 ? "agent-a" : "agent-b"));
  }
  const auto camvid = testing::CamVidFrames();
  ASSERT_GT(camvid.size(), 100u);
  for (size_t i = 0; i < camvid.size(); i += 25) {
    v1::Observation c = JpegObservation(camvid[i].image_path, "agent-c", uint64_t(camvid[i].frame));
    c.set_dynamic_mask_png(EncodePng(testing::CamVidDynamicMask(camvid[i])));
    agent_c.push_back(std::move(c));
    const size_t j = std::min(i + 12, camvid.size() - 1);
    v1::Observation d = JpegObservation(camvid[j].image_path, "agent-d", uint64_t(camvid[j].frame));
    // Boxes around the labelled cars / pedestrians / cyclists (the largest 16).
    cv::Mat labels, stats, centroids;
    const int n = cv::connectedComponentsWithStats(testing::CamVidDynamicMask(camvid[j]), labels,
                                                   stats, centroids);
    std::vector<cv::Rect> rects;
    for (int k = 1; k < n; ++k) {
      rects.emplace_back(stats.at<int>(k, cv::CC_STAT_LEFT), stats.at<int>(k, cv::CC_STAT_TOP),
                         stats.at<int>(k, cv::CC_STAT_WIDTH), stats.at<int>(k, cv::CC_STAT_HEIGHT));
    }
    std::sort(rects.begin(), rects.end(),
              [](const cv::Rect& a, const cv::Rect& b) { return a.area() > b.area(); });
    for (size_t k = 0; k < rects.size() && k < 16; ++k) {
      v1::Box* box = d.add_boxes();
      box->set_class_name("car");
      box->set_confidence(0.9f);
      box->mutable_rect()->set_x(float(rects[k].x));
      box->mutable_rect()->set_y(float(rects[k].y));
      box->mutable_rect()->set_width(float(rects[k].width));
      box->mutable_rect()->set_height(float(rects[k].height));
    }
    agent_d.push_back(std::move(d));
  }

  IngestOutcome outcome_a, outcome_b, outcome_c, outcome_d;
  {
    std::thread a([&] { outcome_a = IngestAll(stub_.get(), "loop", agent_a); });
    std::thread b([&] { outcome_b = IngestAll(stub_.get(), "loop", agent_b); });
    std::thread c([&] { outcome_c = IngestAll(stub_.get(), "loop", agent_c); });
    std::thread d([&] { outcome_d = IngestAll(stub_.get(), "street", agent_d); });
    a.join();
    b.join();
    c.join();
    d.join();
  }
  std::set<uint32_t> loop_ids;
  uint64_t street_dropped = 0;
  for (auto* outcome : {&outcome_a, &outcome_b, &outcome_c, &outcome_d}) {
    ASSERT_TRUE(outcome->status.ok()) << outcome->status.error_message();
  }
  for (const auto& [outcome, sent] :
       {std::pair{&outcome_a, &agent_a}, std::pair{&outcome_b, &agent_b},
        std::pair{&outcome_c, &agent_c}, std::pair{&outcome_d, &agent_d}}) {
    ASSERT_EQ(outcome->responses.size(), sent->size());
    for (size_t i = 0; i < sent->size(); ++i) {
      const v1::IngestResponse& response = outcome->responses[i];
      EXPECT_EQ(response.index(), i) << "responses out of order";
      EXPECT_EQ(response.sequence(), (*sent)[i].sequence());
      EXPECT_FALSE(response.has_error()) << response.error().message();
      EXPECT_GT(response.timings().total_ms(), 0);
      EXPECT_GT(response.timings().decode_ms(), 0);
      if (outcome == &outcome_d) {
        street_dropped += response.counts().dynamic();
        continue;
      }
      if (response.stored()) {
        EXPECT_TRUE(loop_ids.insert(response.place_id()).second);
      }
    }
  }
  // Every loop frame is stored, but for a blurred one or two with no ORB corners (frame 19),
  // which are refused as invalid with the reason.
  size_t loop_stored = 0;
  for (const auto* outcome : {&outcome_a, &outcome_b}) {
    for (const auto& response : outcome->responses) {
      loop_stored += response.stored();
      if (!response.stored()) {
        EXPECT_NE(response.rejection().find("placeThreshold"), std::string::npos)
            << "frame " << response.sequence() << ": " << response.error().message();
      }
    }
  }
  EXPECT_GE(loop_stored, 38u);
  EXPECT_GT(street_dropped, 0u) << "the agent's boxes dropped nothing";
  uint64_t masked_dropped = 0;
  for (const auto& response : outcome_c.responses) masked_dropped += response.counts().dynamic();
  EXPECT_GT(masked_dropped, 0u) << "the masks dropped nothing";
  EXPECT_EQ(Stats("loop").places(), loop_ids.size());

  // The revisit: the top match is a ground-truth loop closure for a large majority.
  const cv::Mat truth = testing::RtabmapGroundTruth();
  int correct = 0, queries = 0;
  for (int frame = 41; frame <= 84; ++frame) {
    const v1::Observation observation = RtabmapObservation(frame, "agent-q");
    v1::QueryResponse response;
    const grpc::Status status = Query("loop", observation, &response);
    ASSERT_TRUE(status.ok()) << status.error_message();
    ++queries;
    if (response.matches().empty()) continue;
    const v1::Match& best = response.matches(0);
    const std::string& agent = best.metadata().agent_id();
    if ((agent == "agent-a" || agent == "agent-b") &&
        truth.at<uint8_t>(frame - 1, int(best.metadata().sequence()) - 1) > 0) {
      ++correct;
    }
    // Precomputed features give the very same ranking as the image.
    if (frame % 8 == 0) {
      v1::Observation features_only;
      *features_only.mutable_features() = FeaturesOf(observation);
      v1::QueryResponse from_features;
      ASSERT_TRUE(Query("loop", features_only, &from_features).ok());
      ASSERT_EQ(from_features.matches_size(), response.matches_size());
      for (int m = 0; m < response.matches_size(); ++m) {
        EXPECT_EQ(from_features.matches(m).place_id(), response.matches(m).place_id());
        EXPECT_DOUBLE_EQ(from_features.matches(m).score(), response.matches(m).score());
      }
      EXPECT_LT(from_features.timings().extract_ms(), response.timings().extract_ms());
    }
  }
  std::printf("[server] rtabmap-loop revisits top-1 over gRPC: %d/%d\n", correct, queries);
  EXPECT_GE(correct, queries * 3 / 4);
}

// A frame's matches are the map before it was added: ingest frames one stream, asking for them.
TEST_F(ServerTest, IngestWithMatchesReturnsTheMapBeforeTheFrame) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  std::vector<v1::Observation> observations;
  for (int frame = 1; frame <= 10; ++frame) observations.push_back(RtabmapObservation(frame, "a"));
  observations.push_back(RtabmapObservation(3, "a"));  // the same image again
  v1::Observation own_only = RtabmapObservation(4, "b");
  own_only.mutable_matches()->set_top_k(1);  // overrides the header's top_k
  observations.push_back(own_only);
  v1::MatchOptions matches;
  matches.set_top_k(20);
  const IngestOutcome outcome = IngestAll(stub_.get(), "m", observations, &matches);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), observations.size());
  std::set<uint32_t> before;
  for (size_t i = 0; i < outcome.responses.size(); ++i) {
    const v1::IngestResponse& response = outcome.responses[i];
    ASSERT_TRUE(response.stored()) << i;
    EXPECT_EQ(size_t(response.matches_size()), i < 11 ? before.size() : 1u) << i;
    for (const v1::Match& match : response.matches()) {
      EXPECT_TRUE(before.count(match.place_id()))
          << "frame " << i << " matched place " << match.place_id() << " not stored before it";
    }
    before.insert(response.place_id());
  }
  EXPECT_TRUE(outcome.responses[0].matches().empty());
  // The repeated image finds its first copy first, with a perfect score.
  const v1::IngestResponse& again = outcome.responses[10];
  ASSERT_FALSE(again.matches().empty());
  EXPECT_EQ(again.matches(0).place_id(), outcome.responses[2].place_id());
  // The index stores weights within 1/2048 relative: an L1 self-match within that of 1.
  EXPECT_NEAR(again.matches(0).score(), 1.0, 1.0 / 2048 + 1e-5);
  EXPECT_EQ(again.matches(0).metadata().sequence(), 3u);
  EXPECT_EQ(outcome.responses[11].matches(0).place_id(), outcome.responses[3].place_id());
  // Ingest without asking returns no matches.
  const IngestOutcome quiet = IngestAll(stub_.get(), "m", {RtabmapObservation(5, "a")});
  ASSERT_EQ(quiet.responses.size(), 1u);
  EXPECT_TRUE(quiet.responses[0].matches().empty());
  // Stored metadata round-trips through GetPlace, features on request.
  grpc::ClientContext context;
  v1::GetPlaceRequest request;
  request.set_map("m");
  request.set_place_id(outcome.responses[4].place_id());
  request.set_include_features(true);
  v1::Place place;
  ASSERT_TRUE(stub_->GetPlace(&context, request, &place).ok());
  EXPECT_EQ(place.metadata().sequence(), 5u);
  EXPECT_EQ(place.metadata().pose().x(), 5);
  EXPECT_EQ(uint32_t(place.features().keypoints_size()), place.counts().kept());
  EXPECT_EQ(place.features().descriptors().size(), size_t(place.features().keypoints_size()) * 32);
}

// The tightest pipeline (one worker, one queued frame, one unanswered frame per stream) still
// answers every frame of concurrent streams, in order; a stream over the limit is refused.
TEST_F(ServerTest, ConcurrentStreamsUnderTightLimitsKeepOrderAndRefuseExtraStreams) {
  ServerConfig config = Config();
  config.threads = 1;
  config.limits.max_queued_frames = 1;
  config.limits.max_inflight_per_stream = 1;
  config.limits.max_concurrent_streams = 2;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  CreateMap("m");

  // Two streams held open (each has had a frame answered, so both count).
  struct Open {
    grpc::ClientContext context;
    std::unique_ptr<grpc::ClientReaderWriter<v1::IngestRequest, v1::IngestResponse>> stream;
  };
  std::vector<std::unique_ptr<Open>> open;
  for (int i = 0; i < 2; ++i) {
    auto o = std::make_unique<Open>();
    o->stream = stub_->Ingest(&o->context);
    v1::IngestRequest request;
    request.mutable_header()->set_map("m");
    ASSERT_TRUE(o->stream->Write(request));
    *request.mutable_observation() = RtabmapObservation(1 + i, "held");
    ASSERT_TRUE(o->stream->Write(request));
    v1::IngestResponse response;
    ASSERT_TRUE(o->stream->Read(&response));
    open.push_back(std::move(o));
  }
  const IngestOutcome refused = IngestAll(stub_.get(), "m", {RtabmapObservation(3, "x")});
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(refused.status.error_message().find("max_concurrent_streams"), std::string::npos);
  for (auto& o : open) {
    o->stream->WritesDone();
    v1::IngestResponse response;
    while (o->stream->Read(&response)) {
    }
    EXPECT_TRUE(o->stream->Finish().ok());
  }
  open.clear();

  // Now two busy streams through the one worker: every frame answered, in order.
  std::vector<v1::Observation> first, second;
  for (int frame = 1; frame <= 12; ++frame) {
    first.push_back(RtabmapObservation(frame, "a"));
    second.push_back(RtabmapObservation(frame + 20, "b"));
  }
  IngestOutcome a, b;
  std::thread ta([&] { a = IngestAll(stub_.get(), "m", first); });
  std::thread tb([&] { b = IngestAll(stub_.get(), "m", second); });
  ta.join();
  tb.join();
  for (const IngestOutcome* outcome : {&a, &b}) {
    ASSERT_TRUE(outcome->status.ok()) << outcome->status.error_message();
    ASSERT_EQ(outcome->responses.size(), 12u);
    for (size_t i = 0; i < 12; ++i) {
      EXPECT_EQ(outcome->responses[i].index(), i);
      EXPECT_FALSE(outcome->responses[i].has_error()) << outcome->responses[i].error().message();
    }
  }
  // Within a stream, places are stored in the order the frames were sent.
  for (const IngestOutcome* outcome : {&a, &b}) {
    uint32_t last = 0;
    for (const auto& response : outcome->responses) {
      if (!response.stored()) continue;
      EXPECT_GT(response.place_id(), last);
      last = response.place_id();
    }
  }
}

// RGB-D frames (colour + 16-bit depth in mm): every ingest response carries Algorithm 1's state
// for its agent's stream, and the counts add up. A static room (slambook2), then the rgbd-people
// frames (their level comes and goes around the room's), the room again, then the room with
// something approaching: a block at 1.2 m over a sixth of the depth image, frame after frame. The
// level deviates for good, and from the 7th such frame on the layer that appeared is removed.
TEST_F(ServerTest, DepthFramesReportAlgorithmOneAndCountsAddUp) {
  const auto room = rgbd::SlambookFrames();
  const auto people = rgbd::RgbdPeopleFrames();
  ASSERT_EQ(room.size(), 5u);
  ASSERT_EQ(people.size(), 8u);
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("rgbd");
  std::vector<v1::Observation> observations;
  uint64_t sequence = 0;
  for (int pass = 0; pass < 2; ++pass) {
    for (const auto& frame : room) {
      observations.push_back(RgbdObservation(frame, "kinect", ++sequence));
    }
  }
  for (int pass = 0; pass < 2; ++pass) {
    for (const auto& frame : people) {
      observations.push_back(RgbdObservation(frame, "kinect", ++sequence));
    }
  }
  for (const auto& frame : room) {  // back to the room: the deviation count starts afresh
    observations.push_back(RgbdObservation(frame, "kinect", ++sequence));
  }
  const size_t approaching = observations.size();
  for (int i = 0; i < 10; ++i) {
    const rgbd::RgbdFrame& frame = room[size_t(i) % room.size()];
    v1::Observation observation = RgbdObservation(frame, "kinect", ++sequence);
    cv::Mat depth = cv::imread(frame.depth_path, cv::IMREAD_UNCHANGED | cv::IMREAD_ANYDEPTH);
    depth(cv::Rect(190, 140, 260, 200)).setTo(cv::Scalar(1200));
    observation.mutable_depth()->set_png16(EncodePng(depth));
    observations.push_back(std::move(observation));
  }
  const IngestOutcome outcome = IngestAll(stub_.get(), "rgbd", observations);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), observations.size());
  uint64_t stored = 0, removing = 0, removed = 0;
  bool deviated = false;
  for (size_t i = 0; i < outcome.responses.size(); ++i) {
    const v1::IngestResponse& response = outcome.responses[i];
    ASSERT_FALSE(response.has_error()) << i << ": " << response.error().message();
    ASSERT_TRUE(response.has_depth()) << i;
    const v1::DepthState& depth = response.depth();
    EXPECT_EQ(depth.frame(), i);
    EXPECT_EQ(depth.warming_up(), i < 3) << i;
    EXPECT_GT(depth.mean_depth_m(), 0.5) << i;
    EXPECT_GT(depth.valid_fraction(), 0.3) << i;
    const v1::FrameCounts& counts = response.counts();
    EXPECT_EQ(counts.total(), counts.dynamic() + counts.depth_removed() + counts.kept()) << i;
    if (!depth.removing()) {
      EXPECT_EQ(counts.depth_removed(), 0u) << i;
    }
    if (depth.removing()) {
      ++removing;
      EXPECT_GE(i, approaching + 6) << "removal before the 7th deviating frame";
      EXPECT_LE(depth.band_near_m(), 1.2f);
      EXPECT_GE(depth.band_far_m(), 1.2f);
      EXPECT_FALSE(depth.band_source().empty());
      EXPECT_GT(counts.depth_removed(), 0u) << i;
    }
    if (i >= approaching) {
      EXPECT_TRUE(depth.deviating()) << i;
      EXPECT_LT(depth.difference_m(), -0.15) << i;
    }
    removed += counts.depth_removed();
    deviated |= depth.deviating();
    EXPECT_GT(response.timings().depth_ms(), 0) << i;
    stored += response.stored();
  }
  EXPECT_TRUE(deviated);
  EXPECT_GE(removing, 3u) << "a lasting deviation must switch removal on";
  EXPECT_GT(removed, 0u);
  const v1::MapStats stats = Stats("rgbd");
  EXPECT_EQ(stats.places(), stored);
  EXPECT_EQ(stats.streams(), 1u);

  // A query from the agent applies its stream's current decision without advancing it.
  v1::QueryResponse response;
  for (int again = 0; again < 2; ++again) {
    ASSERT_TRUE(Query("rgbd", observations.back(), &response).ok());
    ASSERT_TRUE(response.has_depth());
    EXPECT_EQ(response.depth().frame(), observations.size() - 1) << "a query advanced the stream";
    EXPECT_TRUE(response.depth().removing());
    EXPECT_GT(response.counts().depth_removed(), 0u);
    EXPECT_EQ(
        response.counts().total(),
        response.counts().dynamic() + response.counts().depth_removed() + response.counts().kept());
  }

  // Depth of another resolution with the same aspect ratio, raw float32 with intrinsics: fine.
  v1::Observation half = RgbdObservation(people[0], "other", 1);
  cv::Mat depth = cv::imread(people[0].depth_path, cv::IMREAD_UNCHANGED | cv::IMREAD_ANYDEPTH);
  cv::Mat small;
  cv::resize(depth, small, cv::Size(320, 240), 0, 0, cv::INTER_NEAREST);
  half.mutable_depth()->set_png16(EncodePng(small));
  ASSERT_TRUE(Query("rgbd", half, &response).ok());
  EXPECT_TRUE(response.valid());
  EXPECT_EQ(response.counts().total(), response.counts().dynamic() + response.counts().kept());
  v1::Observation metres = RgbdObservation(people[0], "other", 2);
  cv::Mat values;
  depth.convertTo(values, CV_32F, 0.001);
  v1::RawDepth* raw = metres.mutable_depth()->mutable_raw_float32();
  raw->set_width(uint32_t(values.cols));
  raw->set_height(uint32_t(values.rows));
  raw->set_data(std::string(reinterpret_cast<const char*>(values.data), values.total() * 4));
  v1::Intrinsics* intrinsics = metres.mutable_depth()->mutable_intrinsics();
  intrinsics->set_fx(525);
  intrinsics->set_fy(525);
  intrinsics->set_cx(319.5);
  intrinsics->set_cy(239.5);
  ASSERT_TRUE(Query("rgbd", metres, &response).ok());
  intrinsics->set_fx(-1);
  const grpc::Status bad = Query("rgbd", metres, &response);
  EXPECT_EQ(bad.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(bad.error_message().find("observation.depth.intrinsics.fx"), std::string::npos)
      << bad.error_message();
}

// Loop-closure mode over gRPC on the RTAB-Map loop (ORB, default vocabulary): every valid frame
// gets the detector's answer; loops are found, each one a true revisit by the dataset's ground
// truth; frames merged by rehearsal are not stored.
TEST_F(ServerTest, LoopClosureIngestFindsTrueLoopsAndStoresNoMergedFrame) {
  const cv::Mat truth = rgbd::RtabmapGroundTruth();
  ASSERT_EQ(truth.rows, 84);
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  CreateMap("loop");
  std::vector<v1::Observation> observations;
  for (int frame = 1; frame <= 84; ++frame) observations.push_back(RtabmapObservation(frame, "a"));
  v1::IngestHeader header;
  header.set_map("loop");
  header.set_loop_closure(true);
  header.mutable_matches()->set_top_k(3);
  const IngestOutcome outcome = IngestWithHeader(stub_.get(), header, observations);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), 84u);

  std::map<uint32_t, std::vector<int>> frames_of;  // place -> frames it became / merged
  uint64_t stored = 0, merged = 0, loops = 0, false_loops = 0, rejected = 0;
  for (int t = 1; t <= 84; ++t) {
    const v1::IngestResponse& response = outcome.responses[size_t(t - 1)];
    ASSERT_FALSE(response.has_error()) << t << ": " << response.error().message();
    if (!response.stored() && !response.has_loop_closure()) {
      EXPECT_FALSE(response.rejection().empty()) << t;  // an invalid frame: not in the detector
      continue;
    }
    ASSERT_TRUE(response.has_loop_closure()) << t;
    const v1::LoopClosure& lc = response.loop_closure();
    EXPECT_EQ(lc.place_id(), response.place_id()) << t;
    EXPECT_NE(response.place_id(), 0u) << t;
    if (lc.merged()) {
      ++merged;
      EXPECT_FALSE(response.stored()) << t;
      EXPECT_TRUE(response.rejection().empty()) << t;
      ASSERT_TRUE(frames_of.count(lc.place_id())) << "merged into an unknown place, frame " << t;
    } else {
      EXPECT_TRUE(response.stored()) << t;
      ++stored;
    }
    if (t > 1) {
      EXPECT_FALSE(response.matches().empty()) << t;
    }
    if (lc.loop_rejected()) {
      ++rejected;
      EXPECT_FALSE(lc.loop_found()) << t;
      EXPECT_LT(lc.loop_inliers(), 15) << t;
    }
    if (lc.loop_found()) {
      ++loops;
      ASSERT_TRUE(frames_of.count(lc.loop_place_id())) << t;
      EXPECT_GT(lc.loop_posterior(), 0);
      EXPECT_GE(lc.loop_inliers(), 15) << t;  // verified by default (min_inliers)
      // The revisited place looks like the newest frame merged into it.
      const int f = frames_of[lc.loop_place_id()].back();
      const bool correct = truth.at<uint8_t>(t - 1, f - 1) == 255;
      false_loops += !correct;
      EXPECT_TRUE(correct) << "frame " << t << " closed a loop with place " << lc.loop_place_id()
                           << " (frame " << f << "), not a revisit";
    }
    frames_of[lc.place_id()].push_back(t);
  }
  EXPECT_GT(loops, 0u) << "the RTAB-Map loop returns to its start";
  EXPECT_EQ(false_loops, 0u);
  const v1::MapStats stats = Stats("loop");
  EXPECT_EQ(stats.places(), stored) << "merged frames must not be stored";
  EXPECT_EQ(stats.loops_accepted(), loops);
  EXPECT_EQ(stats.loops_rejected(), rejected);
  EXPECT_EQ(stats.streams(), 1u);
  EXPECT_GT(stats.loop_working_memory(), 0u);
  std::printf(
      "loop closure over gRPC: 84 frames -> %llu stored, %llu merged, %llu loops (%llu taken "
      "back by verification)\n",
      static_cast<unsigned long long>(stored), static_cast<unsigned long long>(merged),
      static_cast<unsigned long long>(loops), static_cast<unsigned long long>(rejected));

  // Rehearsal: a frame seen again right away is merged into the place it repeats, not stored.
  CreateMap("rehearsal");
  header.set_map("rehearsal");
  header.clear_matches();
  const IngestOutcome repeated = IngestWithHeader(
      stub_.get(), header,
      {RtabmapObservation(1, "a"), RtabmapObservation(1, "a"), RtabmapObservation(1, "a"),
       RtabmapObservation(20, "a"), RtabmapObservation(20, "a")});
  ASSERT_TRUE(repeated.status.ok()) << repeated.status.error_message();
  ASSERT_EQ(repeated.responses.size(), 5u);
  uint64_t repeated_stored = 0;
  for (size_t i = 0; i < 5; ++i) {
    const v1::IngestResponse& response = repeated.responses[i];
    ASSERT_TRUE(response.has_loop_closure()) << i << response.error().message();
    repeated_stored += response.stored();
    if (i == 1 || i == 2 || i == 4) {
      EXPECT_TRUE(response.loop_closure().merged()) << i;
      EXPECT_FALSE(response.stored()) << i;
      EXPECT_TRUE(response.rejection().empty()) << i;
      EXPECT_EQ(response.place_id(), repeated.responses[i - 1].place_id()) << i;
    }
  }
  EXPECT_TRUE(repeated.responses[0].stored());
  EXPECT_EQ(Stats("rehearsal").places(), repeated_stored);

  using Labels = std::map<std::string, std::string>;
  const auto metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_loop_closures_total", Labels{{"map", "loop"}}),
            double(loops));
  if (merged > 0) {
    EXPECT_EQ(MetricValue(metrics, "placedb_frames_merged_total", Labels{{"map", "loop"}}),
              double(merged));
  }
  EXPECT_EQ(MetricValue(metrics, "placedb_frames_merged_total", Labels{{"map", "rehearsal"}}),
            double(5 - repeated_stored));
  EXPECT_EQ(MetricValue(metrics, "placedb_frames_ingested_total", Labels{{"map", "loop"}}),
            double(stored));
  EXPECT_GT(MetricValue(metrics, "placedb_stage_seconds_count", Labels{{"stage", "loop_closure"}}),
            0);

  // Without loop_closure in the header, the same map stores every valid frame as before.
  const IngestOutcome plain = IngestAll(stub_.get(), "loop", {RtabmapObservation(1, "b")});
  ASSERT_EQ(plain.responses.size(), 1u);
  EXPECT_TRUE(plain.responses[0].stored());
  EXPECT_FALSE(plain.responses[0].has_loop_closure());
}

// Server-side detection (YOLOX-Nano): boxes from the server, or merged with the agent's.
TEST_F(ServerTest, ServerSideDetectionDropsDescriptorsOnPeopleAndCars) {
  const std::string model = testing::SharedDir() + "/models/yolox_nano.onnx";
  ASSERT_TRUE(std::ifstream(model).good()) << model << " is required";
  ServerConfig config = Config();
  config.detector.model = model;
  config.metrics_listen = "127.0.0.1:0";
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);
  CreateMap("server", server_boxes);
  v1::MapConfig both;
  both.mutable_detection()->set_box_source(v1::BOX_SOURCE_BOTH);
  CreateMap("both", both);

  // CamVid frames with the most labelled dynamic pixels.
  auto camvid = testing::CamVidFrames();
  std::vector<std::pair<double, size_t>> busy;
  for (size_t i = 0; i < camvid.size(); i += 10) {
    busy.emplace_back(cv::countNonZero(testing::CamVidDynamicMask(camvid[i])), i);
  }
  std::sort(busy.rbegin(), busy.rend());
  std::vector<v1::Observation> frames;
  for (size_t k = 0; k < 3; ++k) {
    frames.push_back(JpegObservation(camvid[busy[k].second].image_path, "a", k));
  }
  const IngestOutcome outcome = IngestAll(stub_.get(), "server", frames);
  ASSERT_TRUE(outcome.status.ok());
  int boxes = 0;
  for (const auto& response : outcome.responses) {
    EXPECT_FALSE(response.has_error()) << response.error().message();
    EXPECT_GT(response.timings().detect_ms(), 0);
    boxes += response.boxes_used_size();
    for (const auto& box : response.boxes_used()) {
      EXPECT_TRUE(box.class_name() == "person" || box.class_name() == "car" ||
                  box.class_name() == "bicycle" || box.class_name() == "motorcycle" ||
                  box.class_name() == "bus" || box.class_name() == "truck")
          << box.class_name();
    }
  }
  EXPECT_GT(boxes, 0) << "YOLOX found nothing on CamVid's busiest frames";
  EXPECT_GT(Stats("server").descriptors_dropped(), 0u);

  // BOTH: an agent box the detector cannot know about is kept next to the server's.
  v1::Observation with_agent_box = frames[0];
  v1::Box* box = with_agent_box.add_boxes();
  box->set_class_name("truck");
  box->set_confidence(0.99f);
  box->mutable_rect()->set_width(50);
  box->mutable_rect()->set_height(50);
  const IngestOutcome merged = IngestAll(stub_.get(), "both", {with_agent_box});
  ASSERT_EQ(merged.responses.size(), 1u);
  EXPECT_EQ(merged.responses[0].boxes_used_size(), outcome.responses[0].boxes_used_size() + 1);
  // Features alone cannot be detected on: a query uses the boxes sent with it (a stored place's
  // features are static already: the console's stored-place query), storing them is refused for
  // SERVER; BOTH takes the agent's boxes alone.
  v1::Observation features_only;
  *features_only.mutable_features() = FeaturesOf(frames[0]);
  v1::QueryResponse response;
  EXPECT_TRUE(Query("server", features_only, &response).ok());
  EXPECT_TRUE(Query("both", features_only, &response).ok());
  const IngestOutcome refused = IngestAll(stub_.get(), "server", {features_only});
  ASSERT_EQ(refused.responses.size(), 1u);
  EXPECT_TRUE(refused.responses[0].has_error());
  EXPECT_EQ(refused.responses[0].error().code(), int(grpc::StatusCode::INVALID_ARGUMENT))
      << refused.responses[0].error().message();

  const auto metrics = Scrape();
  EXPECT_GE(MetricValue(metrics, "placedb_detector_seconds_count"), 4);
  grpc::ClientContext context;
  v1::ServerInfo info;
  ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
  EXPECT_NE(info.detector().find("yolox_nano.onnx"), std::string::npos) << info.detector();
}

// A full disk (the data directory on a small tmpfs; root only): frames the map cannot store are
// answered RESOURCE_EXHAUSTED ("disk full", naming the map and no path) on a stream that stays
// open, counted by placedb_storage_errors_total; reads answer; once space returns the next
// stream's frames are stored.
TEST_F(ServerTest, FullDiskRefusesFramesOnAnOpenStreamAndIngestResumes) {
  if (geteuid() != 0) GTEST_SKIP() << "mounting a tmpfs needs root";
  const std::string mount_point = root_ + "/tmpfs";
  std::filesystem::create_directories(mount_point);
  if (mount("tmpfs", mount_point.c_str(), "tmpfs", 0, "size=96m") != 0) {
    GTEST_SKIP() << "cannot mount a tmpfs: " << std::strerror(errno);
  }
  struct Unmount {
    std::string dir;
    ~Unmount() { umount2(dir.c_str(), MNT_DETACH); }
  } unmount{mount_point};
  ServerConfig config = Config();
  config.data_dir = mount_point + "/data";
  config.metrics_listen = "127.0.0.1:0";
  StartServer(config);
  CreateMap("full");

  std::vector<v1::Observation> frames;  // precomputed features: the server only stores
  for (int i = 1; i <= 12; ++i) {
    v1::Observation observation = RtabmapObservation(i, "agent");
    *observation.mutable_features() = FeaturesOf(observation);
    frames.push_back(std::move(observation));
  }
  // Leave 12 MB: past the memtables plus the 8 MiB reserve, new places are refused.
  struct statvfs info {};
  ASSERT_EQ(statvfs(mount_point.c_str(), &info), 0);
  const size_t free_mib = size_t(info.f_bavail) * info.f_frsize >> 20;
  ASSERT_GT(free_mib, 20u);
  const std::string filler = mount_point + "/filler";
  {
    std::ofstream out(filler, std::ios::binary);
    const std::string block(size_t(1) << 20, 'x');
    for (size_t i = 0; i + 12 < free_mib; ++i)
      out.write(block.data(), std::streamsize(block.size()));
    ASSERT_TRUE(out.good());
  }
  std::vector<v1::Observation> observations;
  for (size_t n = 0; n < 400; ++n) {
    observations.push_back(frames[n % frames.size()]);
    observations.back().set_sequence(n);
  }
  const IngestOutcome outcome = IngestAll(stub_.get(), "full", observations);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();  // not ended
  ASSERT_EQ(outcome.responses.size(), observations.size());
  std::vector<uint32_t> stored;
  size_t refused = 0;
  for (const v1::IngestResponse& response : outcome.responses) {
    if (response.has_error()) {
      ++refused;
      EXPECT_EQ(response.error().code(), int(grpc::StatusCode::RESOURCE_EXHAUSTED));
      EXPECT_EQ(response.error().message().rfind("storing: disk full: map 'full': ", 0), 0u)
          << response.error().message();
      EXPECT_EQ(response.error().message().find(mount_point), std::string::npos);
    } else if (response.stored()) {
      stored.push_back(response.place_id());
    }
  }
  ASSERT_FALSE(stored.empty());
  ASSERT_GT(refused, 0u);
  EXPECT_EQ(MetricValue(Scrape(), "placedb_storage_errors_total",
                        {{"map", "full"}, {"kind", "disk_full"}}),
            double(refused));
  for (uint32_t id : stored) {
    v1::GetPlaceRequest request;
    request.set_map("full");
    request.set_place_id(id);
    v1::Place place;
    grpc::ClientContext context;
    EXPECT_TRUE(stub_->GetPlace(&context, request, &place).ok()) << "place " << id;
  }
  v1::QueryResponse found;
  ASSERT_TRUE(Query("full", frames[0], &found).ok());
  EXPECT_FALSE(found.matches().empty());

  ASSERT_TRUE(std::filesystem::remove(filler));
  const IngestOutcome resumed = IngestAll(stub_.get(), "full", frames);
  ASSERT_TRUE(resumed.status.ok()) << resumed.status.error_message();
  size_t stored_after = 0;
  for (const v1::IngestResponse& response : resumed.responses) {
    EXPECT_FALSE(response.has_error()) << response.error().message();
    stored_after += response.stored();
  }
  EXPECT_GT(stored_after, 0u);
  EXPECT_EQ(Stats("full").places(), stored.size() + stored_after);
}

}  // namespace
}  // namespace placedb::server_testing
