// Damage through the service: a map that lost acknowledged places is listed and described as
// DAMAGED with a reason naming the file (never an absolute path), counted in /metrics, refused
// with DATA_LOSS, recovered only with accept_data_loss, and then shown as RECOVERED with the
// exact number of places lost, across restarts. ScrubMap finds a corrupt SST block, and the
// place in it answers GetPlace with DATA_LOSS.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "tests/raw_map.h"
#include "tests/server/server_fixture.h"

namespace fs = std::filesystem;

namespace placedb::server_testing {
namespace {

std::vector<v1::Observation> Frames(int first, int last) {
  std::vector<v1::Observation> frames;
  for (int i = first; i <= last; ++i) frames.push_back(RtabmapObservation(i, "robot"));
  return frames;
}

class DamageServerTest : public ServerTest {
 protected:
  ServerConfig MetricsConfig() const {
    ServerConfig config = Config();
    config.metrics_listen = "127.0.0.1:0";
    return config;
  }

  std::string MapDir(const std::string& name) const { return root_ + "/data/maps/" + name; }

  uint64_t Ingest(const std::string& map, int first, int last) {
    const IngestOutcome outcome = IngestAll(stub_.get(), map, Frames(first, last));
    EXPECT_TRUE(outcome.status.ok()) << outcome.status.error_message();
    uint64_t stored = 0;
    for (const auto& response : outcome.responses) stored += response.stored() ? 1 : 0;
    return stored;
  }

  v1::MapSummary Summary(const std::string& name) {
    grpc::ClientContext context;
    v1::ListMapsResponse maps;
    EXPECT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
    for (const auto& map : maps.maps()) {
      if (map.name() == name) return map;
    }
    ADD_FAILURE() << "map " << name << " is not listed";
    return {};
  }

  grpc::Status GetMap(const std::string& name, v1::MapDescription* map) {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name(name);
    return stub_->GetMap(&context, request, map);
  }

  grpc::Status Recover(const std::string& name, bool accept, v1::RecoverMapResponse* response) {
    grpc::ClientContext context;
    v1::RecoverMapRequest request;
    request.set_name(name);
    request.set_accept_data_loss(accept);
    return stub_->RecoverMap(&context, request, response);
  }

  grpc::Status Scrub(const std::string& name, v1::ScrubReport* report) {
    grpc::ClientContext context;
    v1::ScrubMapRequest request;
    request.set_name(name);
    return stub_->ScrubMap(&context, request, report);
  }

  grpc::Status GetPlace(const std::string& map, uint32_t id, v1::Place* place) {
    grpc::ClientContext context;
    v1::GetPlaceRequest request;
    request.set_map(map);
    request.set_place_id(id);
    request.set_include_features(true);
    return stub_->GetPlace(&context, request, place);
  }
};

TEST_F(DamageServerTest, LostPlacesAreDataLossUntilRecoveredThenCountedForGood) {
  ASSERT_NO_FATAL_FAILURE(StartServer(MetricsConfig()));
  CreateMap("lab");
  CreateMap("intact");
  const uint64_t early = Ingest("lab", 1, 12);
  ASSERT_GT(early, 5u);
  ASSERT_GT(Ingest("intact", 1, 6), 0u);
  StopServer();
  // The map's files as they are now; later the WAL holding what follows is "lost".
  const std::string saved = root_ + "/lab-early";
  fs::copy(MapDir("lab"), saved, fs::copy_options::recursive);
  ASSERT_NO_FATAL_FAILURE(StartServer(MetricsConfig()));
  const uint64_t late = Ingest("lab", 13, 24);
  ASSERT_GT(late, 5u);
  StopServer();
  std::string acked;
  {
    std::ifstream in(MapDir("lab") + "/ACKED", std::ios::binary);
    acked.assign(std::istreambuf_iterator<char>(in), {});
  }
  fs::remove_all(MapDir("lab"));
  fs::copy(saved, MapDir("lab"), fs::copy_options::recursive);
  std::ofstream(MapDir("lab") + "/ACKED", std::ios::binary | std::ios::trunc) << acked;

  ASSERT_NO_FATAL_FAILURE(StartServer(MetricsConfig()));
  const v1::MapSummary damaged = Summary("lab");
  EXPECT_EQ(damaged.state(), v1::MAP_STATE_DAMAGED);
  EXPECT_FALSE(damaged.available());
  EXPECT_EQ(damaged.places_lost(), late);
  EXPECT_NE(damaged.unavailable_reason().find("maps/lab"), std::string::npos)
      << damaged.unavailable_reason();
  EXPECT_EQ(damaged.unavailable_reason().find(root_), std::string::npos);
  EXPECT_EQ(Summary("intact").state(), v1::MAP_STATE_AVAILABLE);
  {
    v1::MapDescription map;
    ASSERT_TRUE(GetMap("lab", &map).ok());
    EXPECT_EQ(map.state(), v1::MAP_STATE_DAMAGED);
    EXPECT_EQ(map.damage().places_lost(), late);
    EXPECT_EQ(map.damage().first_lost_place(), early + 1);
    EXPECT_EQ(map.damage().last_lost_place(), early + late);
  }
  auto metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_map_damaged", {{"map", "lab"}}), 1);
  EXPECT_EQ(MetricValue(metrics, "placedb_map_places_lost", {{"map", "lab"}}), double(late));
  EXPECT_EQ(MetricValue(metrics, "placedb_map_damaged", {{"map", "intact"}}), 0);

  // Served by nothing until recovered: DATA_LOSS with the reason.
  v1::QueryResponse response;
  const grpc::Status query = Query("lab", RtabmapObservation(3, "robot"), &response);
  EXPECT_EQ(query.error_code(), grpc::StatusCode::DATA_LOSS);
  EXPECT_NE(query.error_message().find("acknowledged"), std::string::npos) << query.error_message();
  const IngestOutcome ingest = IngestAll(stub_.get(), "lab", Frames(30, 30));
  EXPECT_EQ(ingest.status.error_code(), grpc::StatusCode::DATA_LOSS)
      << ingest.status.error_message();
  v1::Place place;
  EXPECT_EQ(GetPlace("lab", 1, &place).error_code(), grpc::StatusCode::DATA_LOSS);

  // Only with the explicit choice.
  v1::RecoverMapResponse recovered;
  EXPECT_EQ(Recover("lab", false, &recovered).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(Recover("intact", true, &recovered).error_code(),
            grpc::StatusCode::FAILED_PRECONDITION);
  ASSERT_TRUE(Recover("lab", true, &recovered).ok());
  EXPECT_EQ(recovered.accepted().places_lost(), late);
  EXPECT_EQ(recovered.map().state(), v1::MAP_STATE_RECOVERED);
  EXPECT_EQ(recovered.map().stats().places(), early);
  EXPECT_EQ(Summary("lab").state(), v1::MAP_STATE_RECOVERED);
  EXPECT_TRUE(Query("lab", RtabmapObservation(3, "robot"), &response).ok());
  EXPECT_TRUE(GetPlace("lab", 1, &place).ok());
  // It takes new places again.
  EXPECT_EQ(Ingest("lab", 30, 32), 3u);
  metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_map_damaged", {{"map", "lab"}}), 0);
  EXPECT_EQ(MetricValue(metrics, "placedb_map_places_lost", {{"map", "lab"}}), double(late));
  StopServer();

  // The loss stays on record across restarts.
  ASSERT_NO_FATAL_FAILURE(StartServer(MetricsConfig()));
  const v1::MapSummary after = Summary("lab");
  EXPECT_EQ(after.state(), v1::MAP_STATE_RECOVERED);
  EXPECT_EQ(after.places_lost(), late);
  EXPECT_EQ(after.places(), early + 3);
  v1::MapDescription map;
  ASSERT_TRUE(GetMap("lab", &map).ok());
  ASSERT_EQ(map.damage_history_size(), 1);
  EXPECT_EQ(map.damage_history(0).places_lost(), late);
  EXPECT_GT(map.damage_history(0).recovered_unix_ms(), 0);
}

TEST_F(DamageServerTest, ScrubFindsACorruptBlockAndGetPlaceSaysDataLoss) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("lab");
  const uint64_t stored = Ingest("lab", 1, 24);
  ASSERT_GT(stored, 10u);
  v1::ScrubReport report;
  ASSERT_TRUE(Scrub("lab", &report).ok());
  EXPECT_TRUE(report.clean());
  EXPECT_EQ(report.places_checked(), stored);
  StopServer();  // flushes every place to SST files

  // The largest SST file holds the features; garble a block in its middle.
  const std::string garbled = testing::GarbleLargestSst(MapDir("lab"));
  ASSERT_FALSE(garbled.empty());
  const std::string sst = "maps/lab/" + garbled;

  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  EXPECT_EQ(Summary("lab").state(), v1::MAP_STATE_AVAILABLE);  // features are not read at open
  report.Clear();
  ASSERT_TRUE(Scrub("lab", &report).ok());
  EXPECT_FALSE(report.clean());
  EXPECT_EQ(report.places_checked(), stored);
  ASSERT_EQ(report.damaged_files_size(), 1);
  EXPECT_EQ(report.damaged_files(0).file(), sst);
  ASSERT_GE(report.damaged_places_size(), 1);
  for (const auto& damaged : report.damaged_places()) {
    v1::Place place;
    const grpc::Status read = GetPlace("lab", damaged.place_id(), &place);
    EXPECT_EQ(read.error_code(), grpc::StatusCode::DATA_LOSS) << read.error_message();
    EXPECT_NE(read.error_message().find(sst), std::string::npos) << read.error_message();
    EXPECT_EQ(read.error_message().find(root_), std::string::npos) << read.error_message();
  }
}

// Issue 34: a map whose MANIFEST was deleted is DAMAGED (not "unavailable"), so RecoverMap
// takes it; repair keeps every place; the answer names the quarantine holding the files as they
// were. Then the features files deleted: recovery counts the places that lost them, and reading
// one is DATA_LOSS, never NOT_FOUND.
TEST_F(DamageServerTest, DeletedManifestAndFeaturesAreRecoveredAndCounted) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("lab");
  const uint64_t stored = Ingest("lab", 1, 16);
  ASSERT_GT(stored, 5u);
  StopServer();  // flushes every place to SST files
  for (const auto& entry : fs::directory_iterator(MapDir("lab"))) {
    if (entry.path().filename().string().starts_with("MANIFEST-")) fs::remove(entry.path());
  }
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  const v1::MapSummary damaged = Summary("lab");
  EXPECT_EQ(damaged.state(), v1::MAP_STATE_DAMAGED) << damaged.unavailable_reason();
  EXPECT_NE(damaged.unavailable_reason().find("maps/lab/CURRENT"), std::string::npos)
      << damaged.unavailable_reason();
  v1::RecoverMapResponse recovered;
  const grpc::Status recover = Recover("lab", true, &recovered);
  ASSERT_TRUE(recover.ok()) << recover.error_message();
  EXPECT_EQ(recovered.accepted().places_lost(), 0u);
  EXPECT_EQ(recovered.map().stats().places(), stored);
  EXPECT_TRUE(recovered.accepted().quarantine().starts_with("quarantine/lab-"))
      << recovered.accepted().quarantine();
  EXPECT_TRUE(fs::is_directory(root_ + "/data/" + recovered.accepted().quarantine()));
  StopServer();

  // Every features file gone (the places' records and BoW vectors stay).
  const std::vector<std::string> features = testing::SstFilesOf(MapDir("lab"), "features");
  ASSERT_FALSE(features.empty());
  for (const std::string& file : features) fs::remove(file);
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  EXPECT_EQ(Summary("lab").state(), v1::MAP_STATE_DAMAGED);
  ASSERT_TRUE(Recover("lab", true, &recovered).ok());
  EXPECT_EQ(recovered.accepted().features_lost(), stored);
  EXPECT_EQ(recovered.map().stats().places(), stored);
  v1::Place place;
  const grpc::Status read = GetPlace("lab", 1, &place);
  EXPECT_EQ(read.error_code(), grpc::StatusCode::DATA_LOSS) << read.error_message();
  // Still found by search.
  v1::QueryResponse response;
  EXPECT_TRUE(Query("lab", RtabmapObservation(3, "robot"), &response).ok());
}

}  // namespace
}  // namespace placedb::server_testing
