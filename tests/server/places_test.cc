// ListPlaces on a real server holding RTAB-Map frames from two agents: paging visits every place
// once, newest first; the agent and time filters; deleted places are skipped; bad paging is
// INVALID_ARGUMENT naming the field and changes nothing. And GetMap's per-agent activity while
// two agents ingest at once.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <opencv2/core.hpp>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "server/rpc/agent_activity.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

constexpr int kFrames = 16;

// Frame i (1-based) is agent "a" for odd i, "b" for even i; timestamp i x 100 ms.
std::string AgentOf(int frame) {
  return frame % 2 == 1 ? "a" : "b";
}

class PlacesTest : public ServerTest {
 protected:
  // Ingests the frames in one stream; returns the place id of each frame (index frame - 1).
  std::vector<uint32_t> IngestFrames() {
    std::vector<v1::Observation> observations;
    for (int frame = 1; frame <= kFrames; ++frame) {
      observations.push_back(RtabmapObservation(frame, AgentOf(frame)));
    }
    const IngestOutcome outcome = IngestAll(stub_.get(), "m", observations);
    EXPECT_TRUE(outcome.status.ok()) << outcome.status.error_message();
    std::vector<uint32_t> ids;
    for (const v1::IngestResponse& response : outcome.responses) {
      EXPECT_TRUE(response.stored()) << response.rejection();
      ids.push_back(response.place_id());
    }
    EXPECT_EQ(ids.size(), size_t(kFrames));
    return ids;
  }

  grpc::Status List(const v1::ListPlacesRequest& request, v1::ListPlacesResponse* response) {
    grpc::ClientContext context;
    return stub_->ListPlaces(&context, request, response);
  }

  // Every page from the newest to the end; the ids in the order received.
  std::vector<uint32_t> WalkAll(v1::ListPlacesRequest request, int* pages = nullptr) {
    std::vector<uint32_t> ids;
    request.set_before_place_id(0);
    for (int page = 1;; ++page) {
      v1::ListPlacesResponse response;
      const grpc::Status status = List(request, &response);
      EXPECT_TRUE(status.ok()) << status.error_message();
      if (!status.ok() || page > 1000) break;
      EXPECT_LE(response.places_size(), int(request.limit() == 0 ? 100 : request.limit()));
      for (const v1::Place& place : response.places()) ids.push_back(place.place_id());
      if (pages) *pages = page;
      if (response.next_before_place_id() == 0) break;
      EXPECT_LT(response.next_before_place_id(),
                request.before_place_id() == 0 ? UINT32_MAX : request.before_place_id());
      request.set_before_place_id(response.next_before_place_id());
    }
    return ids;
  }
};

// Descending order of `ids`, filtered by `keep` on the frame (1-based) each id came from.
template <typename Keep>
std::vector<uint32_t> Expected(const std::vector<uint32_t>& ids, Keep keep) {
  std::vector<uint32_t> expected;
  for (int frame = int(ids.size()); frame >= 1; --frame) {
    if (keep(frame)) expected.push_back(ids[frame - 1]);
  }
  return expected;
}

TEST_F(PlacesTest, PagesVisitEveryPlaceOnceNewestFirst) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  const std::vector<uint32_t> ids = IngestFrames();
  ASSERT_EQ(ids.size(), size_t(kFrames));

  v1::ListPlacesRequest request;
  request.set_map("m");
  request.set_limit(3);
  int pages = 0;
  const std::vector<uint32_t> walked = WalkAll(request, &pages);
  EXPECT_EQ(walked, Expected(ids, [](int) { return true; }));
  EXPECT_EQ(pages, (kFrames + 2) / 3);
  EXPECT_EQ(std::set<uint32_t>(walked.begin(), walked.end()).size(), walked.size());

  // The first page carries each place's record: metadata, counts.
  v1::ListPlacesResponse first;
  ASSERT_TRUE(List(request, &first).ok());
  ASSERT_EQ(first.places_size(), 3);
  const v1::Place& newest = first.places(0);
  EXPECT_EQ(newest.place_id(), ids.back());
  EXPECT_EQ(newest.metadata().agent_id(), AgentOf(kFrames));
  EXPECT_EQ(newest.metadata().sequence(), uint64_t(kFrames));
  EXPECT_EQ(newest.metadata().timestamp_ns(), int64_t(kFrames) * 100'000'000);
  EXPECT_GT(newest.counts().kept(), 20u);
  EXPECT_EQ(newest.metadata().pose().x(), kFrames % 5 == 0 ? double(kFrames) : 0.0);
  EXPECT_FALSE(newest.has_features());  // records only
  EXPECT_EQ(first.next_before_place_id(), first.places(2).place_id());

  // The default limit (0 = 100) holds them all in one page.
  request.set_limit(0);
  v1::ListPlacesResponse all;
  ASSERT_TRUE(List(request, &all).ok());
  EXPECT_EQ(all.places_size(), kFrames);
  EXPECT_EQ(all.next_before_place_id(), 0u);

  // A before id past the newest starts at the newest.
  request.set_before_place_id(1'000'000);
  v1::ListPlacesResponse past;
  ASSERT_TRUE(List(request, &past).ok());
  EXPECT_EQ(past.places_size(), kFrames);

  // Paging past the end: nothing, and no next.
  for (uint32_t before : {ids.front(), 1u}) {
    request.set_before_place_id(before);
    v1::ListPlacesResponse end;
    ASSERT_TRUE(List(request, &end).ok());
    EXPECT_EQ(end.places_size(), 0) << "before " << before;
    EXPECT_EQ(end.next_before_place_id(), 0u) << "before " << before;
  }
}

TEST_F(PlacesTest, AgentAndTimeWindowFilter) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  const std::vector<uint32_t> ids = IngestFrames();
  ASSERT_EQ(ids.size(), size_t(kFrames));

  v1::ListPlacesRequest request;
  request.set_map("m");
  request.set_limit(2);
  request.set_agent_id("b");
  std::vector<uint32_t> walked = WalkAll(request);
  EXPECT_EQ(walked, Expected(ids, [](int frame) { return AgentOf(frame) == "b"; }));
  EXPECT_EQ(walked.size(), size_t(kFrames / 2));

  request.set_agent_id("nobody");
  EXPECT_TRUE(WalkAll(request).empty());

  // [frame 5's time, frame 12's time): frames 5..11.
  request.set_agent_id("");
  request.set_from_timestamp_ns(5 * 100'000'000);
  request.set_to_timestamp_ns(12 * 100'000'000);
  walked = WalkAll(request);
  EXPECT_EQ(walked, Expected(ids, [](int frame) { return frame >= 5 && frame < 12; }));

  // Both: agent "a" from frame 9 on (no upper bound).
  request.set_agent_id("a");
  request.set_to_timestamp_ns(0);
  request.set_from_timestamp_ns(9 * 100'000'000);
  walked = WalkAll(request);
  EXPECT_EQ(walked, Expected(ids, [](int frame) { return frame >= 9 && AgentOf(frame) == "a"; }));
}

TEST_F(PlacesTest, DeletedPlacesAreSkipped) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  const std::vector<uint32_t> ids = IngestFrames();
  ASSERT_EQ(ids.size(), size_t(kFrames));
  // The newest, one in the middle and the oldest.
  const std::set<int> deleted_frames = {1, 7, kFrames};
  for (int frame : deleted_frames) {
    grpc::ClientContext context;
    v1::DeletePlaceRequest request;
    request.set_map("m");
    request.set_place_id(ids[frame - 1]);
    v1::DeletePlaceResponse response;
    ASSERT_TRUE(stub_->DeletePlace(&context, request, &response).ok());
  }
  v1::ListPlacesRequest request;
  request.set_map("m");
  request.set_limit(4);
  EXPECT_EQ(WalkAll(request),
            Expected(ids, [&](int frame) { return deleted_frames.count(frame) == 0; }));
}

TEST_F(PlacesTest, BadPagingIsInvalidArgumentNamingTheField) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  {
    const IngestOutcome outcome =
        IngestAll(stub_.get(), "m", {RtabmapObservation(1, "a"), RtabmapObservation(2, "b")});
    ASSERT_TRUE(outcome.status.ok());
  }
  const v1::MapStats before = Stats("m");
  ASSERT_EQ(before.places(), 2u);

  struct Case {
    const char* name;
    v1::ListPlacesRequest request;
    grpc::StatusCode code;
    const char* message;
  };
  std::vector<Case> cases;
  auto add = [&](const char* name, grpc::StatusCode code, const char* message, auto edit) {
    v1::ListPlacesRequest request;
    request.set_map("m");
    edit(&request);
    cases.push_back({name, request, code, message});
  };
  add("limit over 1000", grpc::StatusCode::INVALID_ARGUMENT, "limit: must be 1-1000",
      [](v1::ListPlacesRequest* r) { r->set_limit(1001); });
  add("negative from", grpc::StatusCode::INVALID_ARGUMENT, "from_timestamp_ns: must not be",
      [](v1::ListPlacesRequest* r) { r->set_from_timestamp_ns(-1); });
  add("negative to", grpc::StatusCode::INVALID_ARGUMENT, "to_timestamp_ns: must not be",
      [](v1::ListPlacesRequest* r) { r->set_to_timestamp_ns(-5); });
  add("reversed window", grpc::StatusCode::INVALID_ARGUMENT,
      "to_timestamp_ns: must be after from_timestamp_ns", [](v1::ListPlacesRequest* r) {
        r->set_from_timestamp_ns(500);
        r->set_to_timestamp_ns(400);
      });
  add("empty window", grpc::StatusCode::INVALID_ARGUMENT,
      "to_timestamp_ns: must be after from_timestamp_ns", [](v1::ListPlacesRequest* r) {
        r->set_from_timestamp_ns(500);
        r->set_to_timestamp_ns(500);
      });
  add("unknown map", grpc::StatusCode::NOT_FOUND, "nowhere",
      [](v1::ListPlacesRequest* r) { r->set_map("nowhere"); });
  add("no map", grpc::StatusCode::INVALID_ARGUMENT, "map",
      [](v1::ListPlacesRequest* r) { r->clear_map(); });
  for (const Case& c : cases) {
    v1::ListPlacesResponse response;
    const grpc::Status status = List(c.request, &response);
    EXPECT_EQ(status.error_code(), c.code) << c.name << ": " << status.error_message();
    EXPECT_NE(status.error_message().find(c.message), std::string::npos)
        << c.name << ": " << status.error_message();
    EXPECT_EQ(response.places_size(), 0) << c.name;
  }
  // The limit's edge is accepted.
  v1::ListPlacesRequest edge;
  edge.set_map("m");
  edge.set_limit(1000);
  v1::ListPlacesResponse response;
  ASSERT_TRUE(List(edge, &response).ok());
  EXPECT_EQ(response.places_size(), 2);
  EXPECT_EQ(Stats("m").places(), before.places());
}

int64_t UnixMsNow() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// Two agents ingest at once, each on its own stream; agent "a" also sends a frame that is refused
// (not an image) and one that is invalid (all dynamic). GetMap counts every answered frame.
TEST_F(PlacesTest, AgentActivityCountsEveryAnsweredFrame) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  std::vector<v1::Observation> frames_a, frames_b;
  for (int frame = 1; frame <= 12; ++frame) {
    (frame % 2 ? frames_a : frames_b).push_back(RtabmapObservation(frame, AgentOf(frame)));
  }
  v1::Observation refused = RtabmapObservation(20, "a");
  refused.mutable_encoded_image()->set_data("not an image");
  frames_a.insert(frames_a.begin() + 2, refused);
  v1::Observation invalid = RtabmapObservation(21, "a");
  invalid.set_dynamic_mask_png(EncodePng(cv::Mat(384, 512, CV_8U, cv::Scalar(255))));
  frames_a.insert(frames_a.begin() + 4, invalid);

  const int64_t started_ms = UnixMsNow();
  IngestOutcome outcome_a, outcome_b;
  {
    std::thread a([&] { outcome_a = IngestAll(stub_.get(), "m", frames_a); });
    std::thread b([&] { outcome_b = IngestAll(stub_.get(), "m", frames_b); });
    a.join();
    b.join();
  }
  const int64_t ended_ms = UnixMsNow();
  ASSERT_TRUE(outcome_a.status.ok()) << outcome_a.status.error_message();
  ASSERT_TRUE(outcome_b.status.ok()) << outcome_b.status.error_message();
  ASSERT_EQ(outcome_a.responses.size(), frames_a.size());
  ASSERT_EQ(outcome_b.responses.size(), frames_b.size());
  EXPECT_TRUE(outcome_a.responses[2].has_error());
  EXPECT_FALSE(outcome_a.responses[4].stored());
  EXPECT_FALSE(outcome_a.responses[4].has_error());

  grpc::ClientContext context;
  v1::GetMapRequest request;
  request.set_name("m");
  v1::MapDescription map;
  ASSERT_TRUE(stub_->GetMap(&context, request, &map).ok());
  ASSERT_EQ(map.agents_size(), 2);
  const v1::AgentActivity& a = map.agents(0);
  const v1::AgentActivity& b = map.agents(1);
  EXPECT_EQ(a.agent_id(), "a");
  EXPECT_EQ(b.agent_id(), "b");
  EXPECT_EQ(a.frames(), 8u);
  EXPECT_EQ(a.places(), 6u);
  EXPECT_EQ(b.frames(), 6u);
  EXPECT_EQ(b.places(), 6u);
  EXPECT_EQ(a.last_place_id(), outcome_a.responses.back().place_id());
  EXPECT_EQ(b.last_place_id(), outcome_b.responses.back().place_id());
  for (const v1::AgentActivity* agent : {&a, &b}) {
    EXPECT_GE(agent->last_frame_unix_ms(), started_ms) << agent->agent_id();
    EXPECT_LE(agent->last_frame_unix_ms(), ended_ms) << agent->agent_id();
    // Every frame is in the window unless the run took over 9 s: never more than them all.
    EXPECT_GT(agent->frames_per_second(), 0) << agent->agent_id();
    EXPECT_LE(agent->frames_per_second(), double(agent->frames()) / 10) << agent->agent_id();
  }

  // A deleted map's agents go with it.
  grpc::ClientContext delete_context;
  v1::DeleteMapRequest remove;
  remove.set_name("m");
  v1::DeleteMapResponse removed;
  ASSERT_TRUE(stub_->DeleteMap(&delete_context, remove, &removed).ok());
  CreateMap("m");
  grpc::ClientContext again_context;
  v1::MapDescription fresh;
  ASSERT_TRUE(stub_->GetMap(&again_context, request, &fresh).ok());
  EXPECT_EQ(fresh.agents_size(), 0);
}

// The tracker alone, on a clock the test sets: the 10 s window and the per-map agent bound.
TEST(AgentActivityTest, WindowAndEvictionFollowTheClock) {
  using server::AgentActivity;
  using server::FrameOutcome;
  AgentActivity activity(/*max_agents_per_map=*/2);
  const AgentActivity::Clock::time_point t0{std::chrono::hours(1)};
  const auto at = [&](double seconds) {
    return t0 + std::chrono::duration_cast<AgentActivity::Clock::duration>(
                    std::chrono::duration<double>(seconds));
  };
  for (int i = 0; i < 20; ++i) {
    activity.Record("m", "a", FrameOutcome::kStored, uint32_t(i + 1), at(i * 0.5), 1000 + i);
  }
  activity.Record("m", "b", FrameOutcome::kRefused, 0, at(9.5), 2000);
  auto agents = activity.Of("m", at(9.9));
  ASSERT_EQ(agents.size(), 2u);
  EXPECT_EQ(agents[0].frames, 20u);
  EXPECT_DOUBLE_EQ(agents[0].frames_per_second, 2.0);  // 20 frames in seconds 0-9
  EXPECT_EQ(agents[0].last_place_id, 20u);
  EXPECT_EQ(agents[1].places, 0u);
  EXPECT_EQ(agents[1].last_place_id, 0u);
  // Second 12: seconds 0-2 have left the window (6 of a's frames).
  agents = activity.Of("m", at(12.1));
  EXPECT_DOUBLE_EQ(agents[0].frames_per_second, 1.4);
  EXPECT_EQ(agents[0].frames, 20u);  // totals never leave
  EXPECT_TRUE(activity.Of("other", at(12)).empty());

  // A third agent evicts the one whose last frame is oldest ("a", at 1019 ms).
  activity.Record("m", "c", FrameOutcome::kInvalid, 0, at(13), 3000);
  agents = activity.Of("m", at(13));
  ASSERT_EQ(agents.size(), 2u);
  EXPECT_EQ(agents[0].agent_id, "b");
  EXPECT_EQ(agents[1].agent_id, "c");
  activity.Forget("m");
  EXPECT_TRUE(activity.Of("m", at(13)).empty());
}

}  // namespace
}  // namespace placedb::server_testing
