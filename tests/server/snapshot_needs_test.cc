// What a restored map needs of its server (issue 33): a snapshot of a map that takes its boxes
// from the server's detector, restored on a server without one, is refused at restore with
// FAILED_PRECONDITION naming the detector (nothing restored), not served to fail every query;
// with a detector the same snapshot restores and answers. Real servers on loopback, real frames.
#include <gtest/gtest.h>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

// A server-side detector that finds nothing: enough for maps whose boxes come from the server.
class EmptyDetector final : public Detector {
 public:
  Result<std::vector<DynamicBox>> Detect(const cv::Mat&) const override {
    return std::vector<DynamicBox>{};
  }
  std::string model_name() const override { return "empty"; }
  std::string Describe() const override { return "empty (test)"; }
  int input_size() const override { return 416; }
  const DetectorConfig& config() const override { return config_; }

 private:
  DetectorConfig config_;
};

class SnapshotNeedsTest : public ServerTest {
 protected:
  ServerDeps WithDetector() {
    ServerDeps deps;
    deps.detector = std::make_shared<EmptyDetector>();
    return deps;
  }
  grpc::Status Restore(const std::string& id, const std::string& map) {
    grpc::ClientContext context;
    v1::RestoreSnapshotRequest restore;
    restore.set_id(id);
    restore.set_new_map(map);
    v1::MapDescription restored;
    return stub_->RestoreSnapshot(&context, restore, &restored);
  }
  grpc::Status GetMap(const std::string& map) {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name(map);
    v1::MapDescription description;
    return stub_->GetMap(&context, request, &description);
  }
};

TEST_F(SnapshotNeedsTest, RestoreWithoutTheDetectorAMapNeedsIsRefusedNamingIt) {
  ServerConfig config = Config();
  StartServer(config, WithDetector());
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_enabled(true);
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);
  CreateMap("lab", server_boxes);
  std::vector<v1::Observation> frames;
  for (int i = 1; i <= 12; ++i) frames.push_back(RtabmapObservation(i, "robot"));
  ASSERT_TRUE(IngestAll(stub_.get(), "lab", frames).status.ok());
  v1::Snapshot snapshot;
  {
    grpc::ClientContext context;
    v1::CreateSnapshotRequest create;
    create.set_map("lab");
    const grpc::Status status = stub_->CreateSnapshot(&context, create, &snapshot);
    ASSERT_TRUE(status.ok()) << status.error_message();
  }
  StopServer();

  // The same data directory on a server whose detector is off.
  StartServer(config);
  const grpc::Status refused = Restore(snapshot.id(), "lab-copy");
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << refused.error_message();
  EXPECT_NE(refused.error_message().find("detector"), std::string::npos) << refused.error_message();
  EXPECT_NE(refused.error_message().find("box_source server"), std::string::npos)
      << refused.error_message();
  EXPECT_NE(refused.error_message().find("nothing was restored"), std::string::npos)
      << refused.error_message();
  EXPECT_EQ(GetMap("lab-copy").error_code(), grpc::StatusCode::NOT_FOUND);
  // The map opened at startup says the same on a query (FAILED_PRECONDITION naming the detector).
  v1::QueryResponse response;
  const grpc::Status query = Query("lab", RtabmapObservation(5, "query"), &response);
  EXPECT_EQ(query.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << query.error_message();
  EXPECT_NE(query.error_message().find("detector"), std::string::npos) << query.error_message();
  StopServer();

  // With a detector the same snapshot restores under the same name (nothing was left behind)
  // and answers.
  StartServer(config, WithDetector());
  const grpc::Status restored = Restore(snapshot.id(), "lab-copy");
  ASSERT_TRUE(restored.ok()) << restored.error_message();
  ASSERT_TRUE(Query("lab-copy", RtabmapObservation(5, "query"), &response).ok());
  ASSERT_FALSE(response.matches().empty());
  EXPECT_EQ(response.matches(0).metadata().sequence(), 5u);
}

// A map that takes the agents' boxes needs no detector: it restores on a server without one.
TEST_F(SnapshotNeedsTest, AMapOfAgentBoxesRestoresWithoutADetector) {
  StartServer(Config());
  CreateMap("agents");
  std::vector<v1::Observation> frames;
  for (int i = 1; i <= 6; ++i) frames.push_back(RtabmapObservation(i, "robot"));
  ASSERT_TRUE(IngestAll(stub_.get(), "agents", frames).status.ok());
  v1::Snapshot snapshot;
  grpc::ClientContext context;
  v1::CreateSnapshotRequest create;
  create.set_map("agents");
  ASSERT_TRUE(stub_->CreateSnapshot(&context, create, &snapshot).ok());
  const grpc::Status restored = Restore(snapshot.id(), "agents-copy");
  EXPECT_TRUE(restored.ok()) << restored.error_message();
}

}  // namespace
}  // namespace placedb::server_testing
