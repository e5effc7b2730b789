// The loop-closure log through the service (issue 32): WatchLoopClosures delivers every verified
// match found while ingesting, and every loop the agents' detectors accepted, exactly once and in
// order, to a consumer killed and resumed many times while four agents ingest into two maps; the
// log survives a restart and goes on numbering; filters; an unknown or deleted map.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "tests/join_on_exit.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

// What a constraint says, for comparing the log with the Ingest answers.
using ConstraintKey = std::tuple<std::string, uint64_t, uint32_t, uint32_t, int>;
// (query agent, query sequence, query place, matched place, source)

ConstraintKey KeyOf(const v1::LoopConstraint& c) {
  return {c.query().agent_id(), c.query().sequence(), c.query_place_id(), c.place_id(),
          int(c.source())};
}

struct Session {
  std::vector<v1::LoopConstraint> constraints;
  grpc::Status status;
  uint64_t caught_up_to = 0;  // the last marker seen
};

// One WatchLoopClosures call: reads until `take` constraints arrived (then cancels it: the
// consumer is killed), or the stream ends.
Session Watch(v1::PlaceDb::Stub* stub, v1::WatchLoopClosuresRequest request, size_t take) {
  Session session;
  grpc::ClientContext context;
  // A bound, not a timing: a stream that never delivers fails the test instead of hanging it.
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::minutes(2));
  auto reader = stub->WatchLoopClosures(&context, request);
  v1::LoopConstraint message;
  while (session.constraints.size() < take && reader->Read(&message)) {
    if (message.sequence() == 0) {
      session.caught_up_to = message.caught_up_to();
      continue;
    }
    session.constraints.push_back(message);
  }
  if (session.constraints.size() >= take) context.TryCancel();
  session.status = reader->Finish();
  return session;
}

// Everything from `from` on, without following.
Session ReadAll(v1::PlaceDb::Stub* stub, const std::string& map, uint64_t from = 1,
                bool inter_agent_only = false) {
  v1::WatchLoopClosuresRequest request;
  request.set_map(map);
  request.set_from_sequence(from);
  request.set_inter_agent_only(inter_agent_only);
  Session session = Watch(stub, request, SIZE_MAX);
  EXPECT_TRUE(session.status.ok()) << session.status.error_message();
  return session;
}

// The constraints the Ingest answers announce: each verified match (a detector's loop of the
// same place counts once, as a loop closure) and each accepted loop, keyed like the log's.
std::multiset<ConstraintKey> Announced(const std::vector<v1::Observation>& sent,
                                       const std::vector<v1::IngestResponse>& responses) {
  std::multiset<ConstraintKey> announced;
  EXPECT_EQ(sent.size(), responses.size());
  for (size_t i = 0; i < std::min(sent.size(), responses.size()); ++i) {
    const v1::IngestResponse& r = responses[i];
    EXPECT_FALSE(r.has_error()) << i << ": " << r.error().message();
    const std::string& agent = sent[i].agent_id();
    const uint64_t sequence = sent[i].sequence();
    const uint32_t loop = r.loop_closure().loop_found() ? r.loop_closure().loop_place_id() : 0;
    for (const v1::Match& match : r.matches()) {
      if (!match.verified() || match.place_id() == loop) continue;
      announced.insert({agent, sequence, r.place_id(), match.place_id(), v1::LOOP_SOURCE_MATCH});
    }
    if (loop != 0) {
      announced.insert({agent, sequence, r.place_id(), loop, v1::LOOP_SOURCE_LOOP_CLOSURE});
    }
  }
  return announced;
}

class LoopsTest : public ServerTest {
 protected:
  // Exhaustive verification: Ingest's matches are verified, so they are constraints.
  void CreateVerifyingMap(const std::string& name) {
    v1::MapConfig config;
    config.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
    CreateMap(name, config);
  }

  v1::Camera RtabmapCamera() {
    const std::string bytes = RtabmapObservation(1, "x").encoded_image().data();
    const cv::Mat image =
        cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())),
                     cv::IMREAD_GRAYSCALE);
    v1::Camera camera;  // a plausible pinhole: the essential-matrix pose needs one
    camera.set_fx(image.cols * 0.8);
    camera.set_fy(image.cols * 0.8);
    camera.set_cx(image.cols / 2.0);
    camera.set_cy(image.rows / 2.0);
    return camera;
  }
};

TEST_F(LoopsTest, FourAgentsTwoMapsAConsumerKilledTwentyTimesGetsEveryConstraintOnce) {
  StartServer(Config());
  CreateVerifyingMap("north");
  CreateVerifyingMap("south");

  // north: agent a drives the loop's first half, b the second (which comes back to a's start),
  // each with its detector on and a camera. south: c and d take alternate frames of the whole
  // loop, no detector, no camera.
  struct Agent {
    std::string map, name;
    bool loop_closure = false, camera = false;
    std::vector<v1::Observation> frames;
    IngestOutcome outcome;
  };
  std::vector<Agent> agents(4);
  agents[0] = {"north", "a", true, true, {}, {}};
  agents[1] = {"north", "b", true, true, {}, {}};
  agents[2] = {"south", "c", false, false, {}, {}};
  agents[3] = {"south", "d", false, false, {}, {}};
  for (int frame = 1; frame <= 84; ++frame) {
    agents[frame <= 42 ? 0 : 1].frames.push_back(
        RtabmapObservation(frame, frame <= 42 ? "a" : "b"));
    agents[frame % 2 ? 2 : 3].frames.push_back(RtabmapObservation(frame, frame % 2 ? "c" : "d"));
  }
  const v1::Camera camera = RtabmapCamera();

  std::atomic<int> ingesting{4};
  std::vector<std::thread> threads;
  testing::JoinOnExit join;
  join.Add(threads);
  for (Agent& agent : agents) {
    threads.emplace_back([&, agent = &agent] {
      v1::IngestHeader header;
      header.set_map(agent->map);
      header.mutable_matches()->set_top_k(3);
      header.set_loop_closure(agent->loop_closure);
      if (agent->camera) *header.mutable_camera() = camera;
      agent->outcome = IngestWithHeader(stub_.get(), header, agent->frames);
      --ingesting;
    });
  }

  // One consumer per map, killed after 1-4 constraints and resumed from the last one + 1, 20
  // times each while the agents ingest; then what is left.
  std::map<std::string, std::vector<v1::LoopConstraint>> consumed;
  std::map<std::string, int> kills;
  for (const std::string map : {"north", "south"}) {
    threads.emplace_back([&, map] {
      std::mt19937 random(map == "north" ? 7 : 11);
      std::vector<v1::LoopConstraint>& got = consumed[map];
      for (int round = 0; round < 20; ++round) {
        v1::WatchLoopClosuresRequest request;
        request.set_map(map);
        request.set_from_sequence(got.empty() ? 1 : got.back().sequence() + 1);
        request.set_follow(true);
        Session session = Watch(stub_.get(), request, 1 + random() % 4);
        if (session.status.error_code() != grpc::StatusCode::CANCELLED) {
          ADD_FAILURE() << map << " round " << round << ": " << session.status.error_message();
          return;
        }
        ++kills[map];
        got.insert(got.end(), session.constraints.begin(), session.constraints.end());
      }
    });
  }
  join.JoinAll();
  for (const Agent& agent : agents) {
    ASSERT_TRUE(agent.outcome.status.ok())
        << agent.name << ": " << agent.outcome.status.error_message();
  }

  for (const std::string map : {"north", "south"}) {
    SCOPED_TRACE(map);
    EXPECT_EQ(kills[map], 20);
    std::vector<v1::LoopConstraint>& got = consumed[map];
    const Session rest = ReadAll(stub_.get(), map, got.empty() ? 1 : got.back().sequence() + 1);
    got.insert(got.end(), rest.constraints.begin(), rest.constraints.end());

    // In order, none missing, none twice: 1, 2, ..., n.
    for (size_t i = 0; i < got.size(); ++i) {
      ASSERT_EQ(got[i].sequence(), i + 1) << "position " << i;
    }
    // Exactly what the Ingest answers announced.
    std::multiset<ConstraintKey> logged, announced;
    for (const v1::LoopConstraint& c : got) logged.insert(KeyOf(c));
    for (const Agent& agent : agents) {
      if (agent.map != map) continue;
      const auto of_agent = Announced(agent.frames, agent.outcome.responses);
      announced.insert(of_agent.begin(), of_agent.end());
    }
    EXPECT_EQ(logged, announced);
    const size_t inter = size_t(std::count_if(got.begin(), got.end(), [](const auto& c) {
      return c.query().agent_id() != c.place().agent_id();
    }));
    EXPECT_GT(inter, 0u);
    EXPECT_GT(got.size(), inter);  // and intra-agent ones
    std::printf("%s: %zu constraints, %zu inter-agent\n", map.c_str(), got.size(), inter);
    // The filter: the inter-agent ones alone, same order.
    const Session only = ReadAll(stub_.get(), map, 1, /*inter_agent_only=*/true);
    ASSERT_EQ(only.constraints.size(), inter);
    for (const v1::LoopConstraint& c : only.constraints) {
      EXPECT_NE(c.query().agent_id(), c.place().agent_id());
      EXPECT_EQ(c.SerializeAsString(), got[c.sequence() - 1].SerializeAsString());
    }
  }

  // north's constraints carry the poses the Ingest answers had (both sides had cameras); the
  // detector's loops are there too.
  std::map<std::pair<uint64_t, uint32_t>, const v1::Match*> match_of;  // (a/b seq, place)
  for (int i : {0, 1}) {
    const Agent& agent = agents[size_t(i)];
    for (size_t f = 0; f < agent.frames.size(); ++f) {
      for (const v1::Match& m : agent.outcome.responses[f].matches()) {
        match_of[{agent.frames[f].sequence(), m.place_id()}] = &m;
      }
    }
  }
  size_t posed = 0, loops = 0;
  for (const v1::LoopConstraint& c : consumed["north"]) {
    if (c.source() == v1::LOOP_SOURCE_LOOP_CLOSURE) ++loops;
    if (!c.has_relative_pose()) {
      EXPECT_FALSE(c.pose_unavailable().empty()) << c.sequence();
      continue;
    }
    ++posed;
    EXPECT_EQ(c.relative_pose().transform_size(), 16);
    EXPECT_EQ(c.relative_pose().information_size(), 36);
    auto it = match_of.find({c.query().sequence(), c.place_id()});
    if (c.source() == v1::LOOP_SOURCE_MATCH && it != match_of.end()) {
      ASSERT_TRUE(it->second->has_relative_pose());
      for (int k = 0; k < 16; ++k) {
        EXPECT_EQ(c.relative_pose().transform(k), it->second->relative_pose().transform(k));
      }
    }
  }
  EXPECT_GT(posed, 0u);
  EXPECT_GT(loops, 0u);
  for (const v1::LoopConstraint& c : consumed["south"]) {
    EXPECT_FALSE(c.has_relative_pose());
    EXPECT_NE(c.pose_unavailable().find("camera"), std::string::npos) << c.pose_unavailable();
  }

  // A restart: the log is whole and goes on numbering.
  const size_t north_count = consumed["north"].size();
  StopServer();
  StartServer(Config());
  const Session again = ReadAll(stub_.get(), "north");
  ASSERT_EQ(again.constraints.size(), north_count);
  for (size_t i = 0; i < north_count; ++i) {
    EXPECT_EQ(again.constraints[i].SerializeAsString(), consumed["north"][i].SerializeAsString());
  }
  v1::MatchOptions matches;
  matches.set_top_k(3);
  const IngestOutcome one = IngestAll(stub_.get(), "north", {RtabmapObservation(2, "e")}, &matches);
  ASSERT_TRUE(one.status.ok()) << one.status.error_message();
  const Session after = ReadAll(stub_.get(), "north", north_count + 1);
  ASSERT_FALSE(after.constraints.empty());
  EXPECT_EQ(after.constraints.front().sequence(), north_count + 1);
  EXPECT_EQ(after.constraints.front().query().agent_id(), "e");
}

TEST_F(LoopsTest, AFollowerSeesNewConstraintsAndEndsWhenTheMapIsDeleted) {
  StartServer(Config());
  CreateVerifyingMap("hall");
  v1::MatchOptions matches;
  matches.set_top_k(3);

  // Caught up on an empty log: the marker says so.
  v1::WatchLoopClosuresRequest request;
  request.set_map("hall");
  request.set_follow(true);
  grpc::ClientContext context;
  auto reader = stub_->WatchLoopClosures(&context, request);
  v1::LoopConstraint message;
  ASSERT_TRUE(reader->Read(&message));
  EXPECT_EQ(message.sequence(), 0u);
  EXPECT_EQ(message.caught_up_to(), 0u);

  // Frames 1-3 then 1 again by another agent: the revisit is delivered to the follower.
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 3; ++frame) frames.push_back(RtabmapObservation(frame, "a"));
  ASSERT_TRUE(IngestAll(stub_.get(), "hall", frames, &matches).status.ok());
  const IngestOutcome revisit =
      IngestAll(stub_.get(), "hall", {RtabmapObservation(1, "b")}, &matches);
  ASSERT_TRUE(revisit.status.ok());
  bool saw_revisit = false;
  while (!saw_revisit && reader->Read(&message)) {
    if (message.sequence() == 0) continue;
    saw_revisit = message.query().agent_id() == "b" && message.place().agent_id() == "a";
  }
  ASSERT_TRUE(saw_revisit);

  // Deleting the map ends the stream with NOT_FOUND.
  grpc::ClientContext delete_context;
  v1::DeleteMapRequest remove;
  remove.set_name("hall");
  v1::DeleteMapResponse removed;
  ASSERT_TRUE(stub_->DeleteMap(&delete_context, remove, &removed).ok());
  while (reader->Read(&message)) {
  }
  const grpc::Status ended = reader->Finish();
  EXPECT_EQ(ended.error_code(), grpc::StatusCode::NOT_FOUND) << ended.error_message();
  EXPECT_NE(ended.error_message().find("hall"), std::string::npos) << ended.error_message();
}

TEST_F(LoopsTest, AFollowerEndsUnavailableWhenTheServerShutsDown) {
  StartServer(Config());
  CreateVerifyingMap("hall");
  v1::WatchLoopClosuresRequest request;
  request.set_map("hall");
  request.set_follow(true);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::minutes(2));
  auto reader = stub_->WatchLoopClosures(&context, request);
  v1::LoopConstraint message;
  ASSERT_TRUE(reader->Read(&message));  // caught up: the stream is open and waiting
  StopServer();                         // returns once the follower has ended
  while (reader->Read(&message)) {
  }
  const grpc::Status ended = reader->Finish();
  EXPECT_EQ(ended.error_code(), grpc::StatusCode::UNAVAILABLE) << ended.error_message();
}

TEST_F(LoopsTest, UnknownMapIsNotFound) {
  StartServer(Config());
  const Session session = [&] {
    v1::WatchLoopClosuresRequest request;
    request.set_map("nowhere");
    return Watch(stub_.get(), request, SIZE_MAX);
  }();
  EXPECT_EQ(session.status.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_NE(session.status.error_message().find("nowhere"), std::string::npos)
      << session.status.error_message();
}

}  // namespace
}  // namespace placedb::server_testing
