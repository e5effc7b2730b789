// A map's own vocabulary through the service (issue 29): AdaptVocabulary and RevertVocabulary
// on a real server over loopback, GetMap/ListMaps showing the vocabulary, queries during and
// after the switch, the map reopened by a restarted server and restored from a snapshot (no
// server has a file of the learned vocabulary), and the errors.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <thread>

#include "server/backend/vocabulary_policy.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

class VocabularyServerTest : public ServerTest {
 protected:
  static std::unique_ptr<grpc::ClientContext> Context() {
    return std::make_unique<grpc::ClientContext>();
  }

  grpc::Status Adapt(const std::string& map, v1::MapVocabulary* vocabulary) {
    v1::AdaptVocabularyRequest request;
    request.set_name(map);
    request.set_branching(8);  // small and quick: the shape is not what this test is about
    request.set_depth(4);
    request.set_max_sample_descriptors(20000);
    return stub_->AdaptVocabulary(Context().get(), request, vocabulary);
  }

  grpc::Status Revert(const std::string& map, v1::MapVocabulary* vocabulary) {
    v1::RevertVocabularyRequest request;
    request.set_name(map);
    return stub_->RevertVocabulary(Context().get(), request, vocabulary);
  }

  v1::MapDescription Describe(const std::string& map) {
    v1::GetMapRequest request;
    request.set_name(map);
    v1::MapDescription description;
    const grpc::Status status = stub_->GetMap(Context().get(), request, &description);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return description;
  }

  // Frames 1..n of the loop stored in `map`; returns each frame's place.
  std::vector<uint32_t> Ingest(const std::string& map, int n) {
    std::vector<v1::Observation> frames;
    for (int i = 1; i <= n; ++i) frames.push_back(RtabmapObservation(i, "robot"));
    IngestOutcome outcome = IngestAll(stub_.get(), map, frames);
    EXPECT_TRUE(outcome.status.ok()) << outcome.status.error_message();
    std::vector<uint32_t> places;
    for (const v1::IngestResponse& response : outcome.responses) {
      places.push_back(response.stored() ? response.place_id() : 0);
    }
    return places;
  }

  // Each stored frame queried again finds its own place first.
  void ExpectFramesFindTheirPlaces(const std::string& map, const std::vector<uint32_t>& places) {
    for (size_t i = 0; i < places.size(); ++i) {
      if (places[i] == 0) continue;  // not stored (an invalid view)
      v1::QueryResponse response;
      const grpc::Status status = Query(map, RtabmapObservation(int(i) + 1, "query"), &response, 1);
      ASSERT_TRUE(status.ok()) << status.error_message();
      ASSERT_GT(response.matches_size(), 0) << "frame " << i + 1;
      EXPECT_EQ(response.matches(0).place_id(), places[i]) << "frame " << i + 1;
    }
  }
};

TEST_F(VocabularyServerTest, AdaptShowRevertAcrossRestartsAndSnapshots) {
  StartServer(Config());
  CreateMap("lab");
  const std::vector<uint32_t> places = Ingest("lab", 30);
  const v1::MapDescription before = Describe("lab");
  EXPECT_EQ(before.vocabulary().generation(), 0u);
  EXPECT_EQ(before.vocabulary().current().origin(), "file");
  EXPECT_EQ(before.vocabulary().current().checksum(), before.vocabulary_checksum());
  EXPECT_FALSE(before.vocabulary().has_previous());
  EXPECT_EQ(before.config().vocabulary(), "default");

  // Queries keep being answered while the map switches.
  std::atomic<bool> done{false};
  std::atomic<int> answered{0}, failed{0};
  std::thread querying([&] {
    while (!done.load()) {
      v1::QueryResponse response;
      if (Query("lab", RtabmapObservation(5, "query"), &response, 1).ok()) {
        ++answered;
      } else {
        ++failed;
      }
    }
  });
  v1::MapVocabulary adapted;
  const grpc::Status status = Adapt("lab", &adapted);
  done = true;
  querying.join();
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(failed.load(), 0);
  EXPECT_GT(answered.load(), 0);
  EXPECT_EQ(adapted.map(), "lab");
  EXPECT_EQ(adapted.generation(), 1u);
  EXPECT_EQ(adapted.current().origin(), "learned");
  EXPECT_EQ(adapted.current().branching(), 8u);
  EXPECT_EQ(adapted.current().depth(), 4u);
  EXPECT_GT(adapted.current().descriptors_sampled(), 5000u);
  EXPECT_EQ(adapted.previous().origin(), "file");
  EXPECT_EQ(adapted.previous().checksum(), before.vocabulary_checksum());
  const v1::MapDescription after = Describe("lab");
  EXPECT_EQ(after.vocabulary_checksum(), adapted.current().checksum());
  EXPECT_EQ(after.vocabulary().SerializeAsString(), adapted.SerializeAsString());
  EXPECT_EQ(after.config().vocabulary(), "learned");
  ExpectFramesFindTheirPlaces("lab", places);

  // A snapshot carries the vocabulary: a second server without it restores and answers.
  v1::CreateSnapshotRequest create;
  create.set_map("lab");
  v1::Snapshot snapshot;
  ASSERT_TRUE(stub_->CreateSnapshot(Context().get(), create, &snapshot).ok());

  // A restarted server opens the map with the vocabulary it stores.
  StopServer();
  StartServer(Config());
  const v1::MapDescription reopened = Describe("lab");
  EXPECT_EQ(reopened.state(), v1::MAP_STATE_AVAILABLE) << reopened.unavailable_reason();
  EXPECT_EQ(reopened.vocabulary().SerializeAsString(), adapted.SerializeAsString());
  ExpectFramesFindTheirPlaces("lab", places);
  v1::RestoreSnapshotRequest restore;
  restore.set_id(snapshot.id());
  restore.set_new_map("copy");
  v1::MapDescription restored;
  const grpc::Status restored_status = stub_->RestoreSnapshot(Context().get(), restore, &restored);
  ASSERT_TRUE(restored_status.ok()) << restored_status.error_message();
  EXPECT_EQ(restored.vocabulary_checksum(), adapted.current().checksum());
  ExpectFramesFindTheirPlaces("copy", places);

  // One command back.
  v1::MapVocabulary reverted;
  const grpc::Status revert_status = Revert("lab", &reverted);
  ASSERT_TRUE(revert_status.ok()) << revert_status.error_message();
  EXPECT_EQ(reverted.generation(), 2u);
  EXPECT_EQ(reverted.current().checksum(), before.vocabulary_checksum());
  EXPECT_EQ(reverted.previous().checksum(), adapted.current().checksum());
  EXPECT_EQ(Describe("lab").config().vocabulary(), "default");
  ExpectFramesFindTheirPlaces("lab", places);
}

TEST_F(VocabularyServerTest, ErrorsLeaveTheLiveVocabulary) {
  StartServer(Config());
  CreateMap("small");
  Ingest("small", 3);
  const std::string checksum = Describe("small").vocabulary_checksum();
  v1::MapVocabulary vocabulary;
  grpc::Status status = Adapt("small", &vocabulary);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(status.error_message().find("too small to learn a vocabulary from"), std::string::npos)
      << status.error_message();
  status = Revert("small", &vocabulary);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(status.error_message().find("no previous vocabulary"), std::string::npos);
  EXPECT_EQ(Describe("small").vocabulary_checksum(), checksum);
  EXPECT_EQ(Describe("small").vocabulary().generation(), 0u);
  EXPECT_EQ(Adapt("nope", &vocabulary).error_code(), grpc::StatusCode::NOT_FOUND);
  v1::AdaptVocabularyRequest bad;
  bad.set_name("small");
  bad.set_depth(40);
  EXPECT_EQ(stub_->AdaptVocabulary(Context().get(), bad, &vocabulary).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
}

// MapConfig.vocabulary_policy: the server learns a map's vocabulary by itself once it holds
// enough descriptors, and again once it has grown by the regrow factor.
TEST_F(VocabularyServerTest, ThePolicyAdaptsAMapAsItGrows) {
  ServerConfig config = Config();
  config.vocabulary_policy_interval_ms = 50;
  StartServer(config);
  v1::MapConfig bad;
  bad.mutable_vocabulary_policy()->set_adapt_after_descriptors(100);
  const grpc::Status refused = CreateMapStatus("bad", bad);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(refused.error_message().find("config.vocabulary_policy.adapt_after_descriptors"),
            std::string::npos)
      << refused.error_message();

  v1::MapConfig policy;
  policy.mutable_vocabulary_policy()->set_adapt_after_descriptors(10000);
  policy.mutable_vocabulary_policy()->set_regrow_factor(2);
  const v1::MapDescription created = CreateMap("grows", policy);
  EXPECT_EQ(created.config().vocabulary_policy().adapt_after_descriptors(), 10000u);
  // Waits (up to a deadline) for the map's vocabulary generation to reach `generation`.
  const auto wait_for_generation = [&](uint64_t generation) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
    v1::MapDescription map = Describe("grows");
    while (map.vocabulary().generation() < generation &&
           std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      map = Describe("grows");
    }
    return map;
  };
  std::vector<v1::Observation> first, more;
  for (int i = 1; i <= 30; ++i) first.push_back(RtabmapObservation(i, "robot"));
  for (int i = 31; i <= 84; ++i) more.push_back(RtabmapObservation(i, "robot"));
  ASSERT_TRUE(IngestAll(stub_.get(), "grows", first).status.ok());
  const uint64_t kept = Stats("grows").descriptors_kept();
  ASSERT_GE(kept, 10000u);  // the policy's threshold is passed
  const v1::MapDescription adapted = wait_for_generation(1);
  ASSERT_EQ(adapted.vocabulary().generation(), 1u) << "the policy did not adapt the map";
  EXPECT_EQ(adapted.vocabulary().current().origin(), "learned");
  // The policy's thread checks on its own clock: under load it may start while the stream's last
  // frames are still being stored, so it learns from at least the threshold, at most what the
  // stream stored (seen once in a ctest -j2 run: 11,711 of 12,701).
  EXPECT_GE(adapted.vocabulary().current().descriptors_offered(), 10000u);
  EXPECT_LE(adapted.vocabulary().current().descriptors_offered(), kept);
  ASSERT_TRUE(IngestAll(stub_.get(), "grows", more).status.ok());
  ASSERT_GE(Stats("grows").descriptors_kept(), 2 * kept);
  const v1::MapDescription regrown = wait_for_generation(2);
  ASSERT_EQ(regrown.vocabulary().generation(), 2u) << "the policy did not learn again";
  EXPECT_EQ(regrown.vocabulary().current().origin(), "learned");
  // Regrown at regrow_factor times what the first learning read (again on the thread's clock).
  EXPECT_GE(regrown.vocabulary().current().descriptors_offered(),
            2 * adapted.vocabulary().current().descriptors_offered());
  EXPECT_EQ(regrown.vocabulary().previous().checksum(), adapted.vocabulary().current().checksum());
}

TEST(VocabularyPolicyTest, DecidesByGrowthAndRespectsARevert) {
  wire::ServiceMapSettings settings;
  settings.adapt_after_descriptors = 10000;
  settings.regrow_factor = 2;
  VocabularyRecord created;  // generation 0: the file's vocabulary
  EXPECT_FALSE(server::PolicyWantsAdaptation(settings, created, 9999, 0));
  EXPECT_TRUE(server::PolicyWantsAdaptation(settings, created, 10000, 0));
  // A failed attempt at 10000 descriptors: again only after a tenth more.
  EXPECT_FALSE(server::PolicyWantsAdaptation(settings, created, 10999, 10000));
  EXPECT_TRUE(server::PolicyWantsAdaptation(settings, created, 11000, 10000));
  VocabularyRecord learned;
  learned.generation = 1;
  learned.current.origin = "learned";
  learned.current.descriptors_offered = 10000;
  EXPECT_FALSE(server::PolicyWantsAdaptation(settings, learned, 19999, 0));
  EXPECT_TRUE(server::PolicyWantsAdaptation(settings, learned, 20000, 0));
  // An operator switched back to the file's vocabulary: the policy leaves the map alone.
  VocabularyRecord reverted;
  reverted.generation = 2;
  reverted.current.origin = "file";
  reverted.previous = learned.current;
  EXPECT_FALSE(server::PolicyWantsAdaptation(settings, reverted, 1000000, 0));
  wire::ServiceMapSettings off;
  EXPECT_FALSE(server::PolicyWantsAdaptation(off, created, 1000000, 0));
  EXPECT_FALSE(server::PolicyWantsAdaptation(off, learned, 1000000, 0));
}

}  // namespace
}  // namespace placedb::server_testing
