// Group commit behind the Ingest stream (issue 17): streams of precomputed features hand their
// places to the map's commit queue, and each frame is answered only once its place is durable and
// indexed. Concurrent streams keep their own order and the id semantics, and every acknowledged
// place is readable at once and after a restart. Run under ThreadSanitizer too.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <map>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "tests/server/server_fixture.h"
#include "tests/test_support.h"

namespace placedb::server_testing {
namespace {

constexpr int kStreams = 4;
constexpr int kFramesPerStream = 21;  // RTAB-Map frames 1..84, one in four per stream

v1::Place GetPlace(v1::PlaceDb::Stub* stub, const std::string& map, uint32_t id,
                   grpc::Status* status) {
  grpc::ClientContext context;
  v1::GetPlaceRequest request;
  request.set_map(map);
  request.set_place_id(id);
  v1::Place place;
  *status = stub->GetPlace(&context, request, &place);
  return place;
}

TEST_F(ServerTest, ConcurrentFeatureStreamsKeepOrderIdsAndDurability) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("fleet");
  std::vector<std::vector<v1::Observation>> sent(kStreams);
  for (int s = 0; s < kStreams; ++s) {
    for (int i = 0; i < kFramesPerStream; ++i) {
      v1::Observation observation =
          RtabmapObservation(1 + i * kStreams + s, "agent-" + std::to_string(s));
      *observation.mutable_features() = FeaturesOf(observation);  // no pixels: store only
      sent[s].push_back(std::move(observation));
    }
  }
  std::vector<IngestOutcome> outcomes(kStreams);
  {
    std::vector<std::thread> streams;
    for (int s = 0; s < kStreams; ++s) {
      streams.emplace_back([&, s] { outcomes[s] = IngestAll(stub_.get(), "fleet", sent[s]); });
    }
    for (auto& stream : streams) stream.join();
  }

  // Every stored place: its stream, sequence and agent.
  std::map<uint32_t, std::pair<uint64_t, std::string>> stored;
  for (int s = 0; s < kStreams; ++s) {
    const IngestOutcome& outcome = outcomes[s];
    ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
    ASSERT_EQ(outcome.responses.size(), sent[s].size());
    uint32_t previous = 0;
    for (size_t i = 0; i < outcome.responses.size(); ++i) {
      const v1::IngestResponse& response = outcome.responses[i];
      EXPECT_EQ(response.index(), i) << "stream " << s << ": responses out of order";
      EXPECT_EQ(response.sequence(), sent[s][i].sequence());
      EXPECT_FALSE(response.has_error()) << response.error().message();
      if (!response.stored()) continue;  // a frame too blurred for a place (frame 19)
      // Ids follow the stream's order, and no two places share one.
      EXPECT_GT(response.place_id(), previous) << "stream " << s << ", frame " << i;
      previous = response.place_id();
      EXPECT_GT(response.timings().store_ms(), 0);
      EXPECT_EQ(response.counts().total(), uint32_t(sent[s][i].features().keypoints_size()));
      EXPECT_GT(response.counts().kept(), 0u);
      EXPECT_TRUE(
          stored
              .emplace(response.place_id(), std::pair{sent[s][i].sequence(), sent[s][i].agent_id()})
              .second)
          << "place id " << response.place_id() << " given twice";
    }
  }
  ASSERT_GE(stored.size(), size_t(kStreams * kFramesPerStream - 2));

  auto check_every_place = [&](const char* when) {
    for (const auto& [id, expected] : stored) {
      grpc::Status status;
      const v1::Place place = GetPlace(stub_.get(), "fleet", id, &status);
      ASSERT_TRUE(status.ok()) << when << ": place " << id << ": " << status.error_message();
      EXPECT_EQ(place.metadata().sequence(), expected.first) << when << ": place " << id;
      EXPECT_EQ(place.metadata().agent_id(), expected.second) << when << ": place " << id;
    }
    EXPECT_EQ(Stats("fleet").places(), stored.size()) << when;
  };
  // Acknowledged = indexed and readable at once.
  ASSERT_NO_FATAL_FAILURE(check_every_place("after the streams"));
  // ... and durable: the same after the server is stopped and the map reopened.
  StopServer();
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  ASSERT_NO_FATAL_FAILURE(check_every_place("after a restart"));
}

}  // namespace
}  // namespace placedb::server_testing
