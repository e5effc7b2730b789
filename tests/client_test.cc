// The `placedb` CLI and load tester against a real server: an in-process placedb_server on a
// loopback port with a real RocksDB in a temp directory, the default vocabulary (plus the Debian
// SIFT vocabulary for SiftClientTest), real frames (RTAB-Map loop, rgbd-people, slambook2-rgbd).
// Every command runs through RunCli() (the binary's entry function) with string streams, checking
// outputs and exit codes.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>
#include <regex>
#include <set>
#include <sstream>

#include "client/cli.h"
#include "client/commands/places.h"
#include "client/dynamics_chart.h"
#include "client/format.h"
#include "client/frame_source.h"
#include "client/loopback.h"
#include "core/base/files.h"
#include "server/config.h"
#include "server/server.h"
#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace placedb {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

struct CliRun {
  int code = -1;
  std::string out;
  std::string err;
};

// Runs `placedb ARGS...` in-process.
CliRun RunPlacedb(const std::vector<std::string>& args, const std::string& stdin_text = "",
                  bool stdin_is_tty = false) {
  std::vector<const char*> argv = {"placedb"};
  for (const std::string& arg : args) argv.push_back(arg.c_str());
  std::ostringstream out, err;
  std::istringstream in(stdin_text);
  client::CliIo io{out, err, in, /*err_is_tty=*/false, stdin_is_tty};
  CliRun run;
  run.code = client::RunCli(int(argv.size()), argv.data(), io);
  run.out = out.str();
  run.err = err.str();
  return run;
}

json ParseJson(const CliRun& run) {
  json doc = json::parse(run.out, nullptr, /*allow_exceptions=*/false);
  EXPECT_FALSE(doc.is_discarded()) << "not JSON:\n" << run.out << "\nstderr:\n" << run.err;
  return doc;
}

class ClientTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    auto vocabulary = testing::DefaultVocabulary();
    ASSERT_TRUE(vocabulary);
    checksum_ = vocabulary->checksum_hex();
    root_ = testing::MakeTempDir("placedb-client");
    spdlog::set_level(spdlog::level::warn);

    server::ServerConfig config;
    config.listen = "127.0.0.1:0";
    config.metrics_listen = "";
    config.console_listen = "";
    config.data_dir = root_ + "/data";
    config.threads = 2;
    config.vocabularies = {{"default", testing::DefaultVocabularyPath()}};
    config.shutdown_deadline_s = 10;
    Configure(&config);
    server::ServerDeps deps;
    deps.vocabularies.emplace("default", vocabulary);
    auto started = server::Server::Start(config, deps);
    ASSERT_TRUE(started.ok()) << started.status().ToString();
    server_ = std::move(started).value();
    address_ = "127.0.0.1:" + std::to_string(server_->port());
  }

  void TearDown() override { server_.reset(); }

  // For derived fixtures: more vocabularies, other settings.
  virtual void Configure(server::ServerConfig* /*config*/) {}

  // `placedb --address <this server> ARGS...`
  CliRun Cli(std::vector<std::string> args, const std::string& stdin_text = "",
             bool stdin_is_tty = false) {
    args.insert(args.begin(), {"--address", address_});
    return RunPlacedb(args, stdin_text, stdin_is_tty);
  }

  // A folder holding RTAB-Map frames first..last under their own names (symlinks).
  std::string FramesDir(int first, int last) {
    const std::string dir = root_ + "/frames-" + std::to_string(first) + "-" + std::to_string(last);
    fs::create_directories(dir);
    for (int frame = first; frame <= last; ++frame) {
      fs::create_symlink(testing::RtabmapFramePath(frame),
                         dir + "/" + std::to_string(frame) + ".jpg");
    }
    return dir;
  }

  std::string root_;
  std::string address_;
  std::string checksum_;
  std::unique_ptr<server::Server> server_;
};

// ---- maps ---------------------------------------------------------------------------------------

TEST_F(ClientTest, MapsCreateListShowDelete) {
  CliRun created = Cli({"maps",
                        "create",
                        "loop",
                        "--features",
                        "800",
                        "--detection",
                        "on",
                        "--classes",
                        "person,car",
                        "--confidence",
                        "0.4",
                        "--box-source",
                        "agent",
                        "--filter",
                        "exact_coverage",
                        "--sensitivity",
                        "0.3",
                        "--place-threshold",
                        "25",
                        "--scoring",
                        "l2",
                        "--verify",
                        "exhaustive",
                        "--level",
                        "1",
                        "--min-inliers",
                        "12",
                        "--store-invalid"});
  ASSERT_EQ(created.code, 0) << created.err;
  EXPECT_NE(created.out.find("created map 'loop'"), std::string::npos) << created.out;
  EXPECT_NE(created.out.find("exact_coverage"), std::string::npos) << created.out;

  // The effective configuration, as the server reports it.
  CliRun shown = Cli({"maps", "show", "loop", "--json"});
  ASSERT_EQ(shown.code, 0) << shown.err;
  const json map = ParseJson(shown);
  EXPECT_EQ(map["name"], "loop");
  EXPECT_EQ(map["vocabulary_checksum"], checksum_);
  const json& config = map["config"];
  EXPECT_EQ(config["orb"]["max_features"], 800);
  EXPECT_EQ(config["detection"]["enabled"], true);
  EXPECT_EQ(config["detection"]["classes"], json({"person", "car"}));
  EXPECT_NEAR(config["detection"]["min_confidence"].get<double>(), 0.4, 1e-6);
  EXPECT_EQ(config["detection"]["box_source"], "BOX_SOURCE_AGENT");
  EXPECT_EQ(config["filter"]["method"], "FILTER_METHOD_EXACT_COVERAGE");
  EXPECT_NEAR(config["filter"]["sensitivity_threshold"].get<double>(), 0.3, 1e-6);
  EXPECT_EQ(config["filter"]["place_threshold"], 25);
  EXPECT_EQ(config["scoring"], "SCORING_L2");
  EXPECT_EQ(config["verification"]["mode"], "VERIFICATION_MODE_EXHAUSTIVE");
  EXPECT_EQ(config["verification"]["levels_up"], 1);
  EXPECT_EQ(config["verification"]["min_inliers"], 12);
  EXPECT_EQ(config["store_invalid"], true);
  EXPECT_EQ(map["stats"]["places"], "0");  // proto3 JSON: 64-bit integers are strings

  shown = Cli({"maps", "show", "loop"});
  ASSERT_EQ(shown.code, 0) << shown.err;
  for (const char* text : {"map loop", "statistics", "places", "l2", "min_inliers 12",
                           "classes person,car", "store_invalid  yes"}) {
    EXPECT_NE(shown.out.find(text), std::string::npos) << text << " missing from\n" << shown.out;
  }

  ASSERT_EQ(Cli({"maps", "create", "second"}).code, 0);
  CliRun listed = Cli({"maps", "list"});
  ASSERT_EQ(listed.code, 0) << listed.err;
  EXPECT_NE(listed.out.find("NAME"), std::string::npos);
  EXPECT_NE(listed.out.find("loop"), std::string::npos);
  EXPECT_NE(listed.out.find("second"), std::string::npos);
  const json maps = ParseJson(Cli({"--json", "maps", "list"}));
  ASSERT_EQ(maps["maps"].size(), 2u);
  for (const json& m : maps["maps"]) EXPECT_EQ(m["available"], true);

  // Errors carry the gRPC code name and exit 1.
  CliRun again = Cli({"maps", "create", "loop"});
  EXPECT_EQ(again.code, 1);
  EXPECT_NE(again.err.find("ALREADY_EXISTS"), std::string::npos) << again.err;
  CliRun bad_name = Cli({"maps", "create", "../evil"});
  EXPECT_EQ(bad_name.code, 1);
  EXPECT_NE(bad_name.err.find("INVALID_ARGUMENT"), std::string::npos) << bad_name.err;
  CliRun missing = Cli({"maps", "show", "nope"});
  EXPECT_EQ(missing.code, 1);
  EXPECT_NE(missing.err.find("NOT_FOUND"), std::string::npos) << missing.err;

  // Deleting asks first: refused without a terminal, declined, then confirmed.
  CliRun unconfirmed = Cli({"maps", "delete", "second"});
  EXPECT_EQ(unconfirmed.code, 2);
  EXPECT_NE(unconfirmed.err.find("--yes"), std::string::npos) << unconfirmed.err;
  EXPECT_EQ(Cli({"maps", "delete", "second"}, "n\n", /*stdin_is_tty=*/true).code, 2);
  EXPECT_EQ(ParseJson(Cli({"maps", "list", "--json"}))["maps"].size(), 2u);
  CliRun confirmed = Cli({"maps", "delete", "second"}, "y\n", /*stdin_is_tty=*/true);
  EXPECT_EQ(confirmed.code, 0) << confirmed.err;
  CliRun deleted = Cli({"maps", "delete", "loop", "--yes"});
  EXPECT_EQ(deleted.code, 0) << deleted.err;
  EXPECT_NE(deleted.out.find("deleted map 'loop'"), std::string::npos);
  EXPECT_EQ(Cli({"maps", "list"}).out, "no maps\n");
  CliRun gone = Cli({"maps", "delete", "loop", "-y"});
  EXPECT_EQ(gone.code, 1);
  EXPECT_NE(gone.err.find("NOT_FOUND"), std::string::npos) << gone.err;
}

// ---- ingest, query, place -----------------------------------------------------------------------

// Frames 1..20 of the loop as two agents; a revisit frame then finds a ground-truth match, and the
// matched place can be read and deleted.
// A damaged map (its ACKED file deleted) is listed as DAMAGED; `maps scrub` on it fails with
// DATA_LOSS; `maps recover` refuses without --accept-data-loss, recovers with it, and `maps
// scrub` then finds nothing (exit 0; exit 3 is for damage found, covered by the service tests).
// ---- snapshots ----------------------------------------------------------------------------------

TEST_F(ClientTest, SnapshotsCreateDownloadUploadRestoreDelete) {
  ASSERT_EQ(Cli({"maps", "create", "lab"}).code, 0);
  ASSERT_EQ(Cli({"ingest", "lab", FramesDir(1, 10), "--json"}).code, 0);
  const std::string places = ParseJson(Cli({"maps", "show", "lab", "--json"}))["stats"]["places"];

  CliRun created = Cli({"snapshots", "create", "lab", "--json"});
  ASSERT_EQ(created.code, 0) << created.err;
  const json snapshot = ParseJson(created);
  const std::string id = snapshot["id"];
  EXPECT_EQ(snapshot["map"], "lab");
  EXPECT_EQ(snapshot["places"], places);
  CliRun listed = Cli({"snapshots", "list"});
  ASSERT_EQ(listed.code, 0);
  EXPECT_NE(listed.out.find(id), std::string::npos) << listed.out;

  const std::string file = root_ + "/lab.pdbsnap";
  CliRun downloaded = Cli({"snapshots", "download", id, file});
  ASSERT_EQ(downloaded.code, 0) << downloaded.err;
  EXPECT_NE(downloaded.err.find("progress: "), std::string::npos) << downloaded.err;
  EXPECT_GT(fs::file_size(file), 0u);
  EXPECT_EQ(Cli({"snapshots", "download", id, file}).code, 2);  // never overwrites
  // A download of an unknown snapshot leaves no file.
  EXPECT_NE(Cli({"snapshots", "download", "nope", root_ + "/nope.pdbsnap"}).code, 0);
  EXPECT_FALSE(fs::exists(root_ + "/nope.pdbsnap"));

  ASSERT_EQ(Cli({"snapshots", "delete", id}).code, 0);
  EXPECT_EQ(ParseJson(Cli({"snapshots", "list", "--json"})).value("snapshots", json::array()),
            json::array());
  CliRun uploaded = Cli({"snapshots", "upload", file, "--json"});
  ASSERT_EQ(uploaded.code, 0) << uploaded.err;
  EXPECT_EQ(ParseJson(uploaded)["id"], id);
  CliRun restored = Cli({"snapshots", "restore", id, "lab-copy"});
  ASSERT_EQ(restored.code, 0) << restored.err;
  EXPECT_EQ(ParseJson(Cli({"maps", "show", "lab-copy", "--json"}))["stats"]["places"], places);
  EXPECT_NE(Cli({"snapshots", "restore", id, "lab-copy"}).code, 0);  // exists

  // A damaged archive is refused with DATA_LOSS's message.
  std::string bytes;
  {
    std::ifstream in(file, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), {});
  }
  bytes.resize(bytes.size() / 2);
  std::ofstream(root_ + "/half.pdbsnap", std::ios::binary) << bytes;
  CliRun refused = Cli({"snapshots", "upload", root_ + "/half.pdbsnap"});
  EXPECT_NE(refused.code, 0);
  EXPECT_NE(refused.err.find("DATA_LOSS"), std::string::npos) << refused.err;
}

TEST_F(ClientTest, MapsRecoverAndScrub) {
  ASSERT_EQ(Cli({"maps", "create", "lab"}).code, 0);
  CliRun ingested = Cli({"ingest", "lab", FramesDir(1, 6)});
  ASSERT_EQ(ingested.code, 0) << ingested.err;
  server_.reset();
  ASSERT_TRUE(fs::remove(root_ + "/data/maps/lab/ACKED"));
  {
    server::ServerConfig config;
    config.listen = "127.0.0.1:0";
    config.metrics_listen = "";
    config.console_listen = "";
    config.data_dir = root_ + "/data";
    config.threads = 2;
    config.vocabularies = {{"default", testing::DefaultVocabularyPath()}};
    server::ServerDeps deps;
    deps.vocabularies.emplace("default", testing::DefaultVocabulary());
    auto started = server::Server::Start(config, deps);
    ASSERT_TRUE(started.ok()) << started.status().ToString();
    server_ = std::move(started).value();
    address_ = "127.0.0.1:" + std::to_string(server_->port());
  }
  CliRun listed = Cli({"maps", "list"});
  ASSERT_EQ(listed.code, 0) << listed.err;
  EXPECT_NE(listed.out.find("DAMAGED: maps/lab/ACKED is missing"), std::string::npos) << listed.out;
  EXPECT_EQ(listed.out.find(root_), std::string::npos) << listed.out;
  CliRun shown = Cli({"maps", "show", "lab"});
  ASSERT_EQ(shown.code, 0) << shown.err;
  EXPECT_NE(shown.out.find("placedb maps recover lab --accept-data-loss"), std::string::npos)
      << shown.out;
  CliRun refused = Cli({"maps", "scrub", "lab"});
  EXPECT_EQ(refused.code, 1);
  EXPECT_NE(refused.err.find("DATA_LOSS"), std::string::npos) << refused.err;
  CliRun ingest = Cli({"ingest", "lab", FramesDir(7, 8)});
  EXPECT_EQ(ingest.code, 1);
  EXPECT_NE(ingest.err.find("DATA_LOSS: map 'lab' is damaged"), std::string::npos) << ingest.err;
  CliRun unconfirmed = Cli({"maps", "recover", "lab"});
  EXPECT_EQ(unconfirmed.code, 2);
  EXPECT_NE(unconfirmed.err.find("--accept-data-loss"), std::string::npos) << unconfirmed.err;
  CliRun recovered = Cli({"maps", "recover", "lab", "--accept-data-loss"});
  ASSERT_EQ(recovered.code, 0) << recovered.err;
  EXPECT_NE(recovered.out.find("recovered map 'lab': 0 places lost"), std::string::npos)
      << recovered.out;
  listed = Cli({"maps", "list"});
  EXPECT_NE(listed.out.find("recovered (0 places lost)"), std::string::npos) << listed.out;
  CliRun scrubbed = Cli({"maps", "scrub", "lab", "--json"});
  ASSERT_EQ(scrubbed.code, 0) << scrubbed.err;
  const json report = ParseJson(scrubbed);
  EXPECT_EQ(report["clean"], true);
  EXPECT_GT(std::stoi(report["places_checked"].get<std::string>()), 0);
}

// `maps adapt-vocabulary` learns a vocabulary from the map's places and switches to it; `maps
// show` says which vocabulary, where it came from and the previous one; `maps
// revert-vocabulary` goes back; a map too small to learn from is refused with the reason.
TEST_F(ClientTest, MapsAdaptAndRevertVocabulary) {
  ASSERT_EQ(Cli({"maps", "create", "lab"}).code, 0);
  ASSERT_EQ(Cli({"ingest", "lab", FramesDir(1, 30)}).code, 0);
  const json before = ParseJson(Cli({"maps", "show", "lab", "--json"}));
  CliRun adapted = Cli({"maps", "adapt-vocabulary", "lab", "--branching", "8", "--depth", "4",
                        "--max-sample", "20000"});
  ASSERT_EQ(adapted.code, 0) << adapted.err;
  EXPECT_NE(adapted.out.find("map 'lab' switched to the learned vocabulary"), std::string::npos)
      << adapted.out;
  EXPECT_NE(adapted.out.find("(k=8 L=4"), std::string::npos) << adapted.out;
  CliRun shown = Cli({"maps", "show", "lab"});
  ASSERT_EQ(shown.code, 0) << shown.err;
  EXPECT_NE(shown.out.find("vocabulary"), std::string::npos);
  EXPECT_NE(shown.out.find("current     learned"), std::string::npos) << shown.out;
  EXPECT_NE(shown.out.find("previous    file " + before["vocabulary_checksum"].get<std::string>()),
            std::string::npos)
      << shown.out;
  const json after = ParseJson(Cli({"maps", "show", "lab", "--json"}));
  EXPECT_EQ(after["vocabulary"]["generation"], "1");
  EXPECT_EQ(after["vocabulary"]["current"]["origin"], "learned");
  EXPECT_NE(after["vocabulary_checksum"], before["vocabulary_checksum"]);

  CliRun reverted = Cli({"maps", "revert-vocabulary", "lab", "--json"});
  ASSERT_EQ(reverted.code, 0) << reverted.err;
  const json back = ParseJson(reverted);
  EXPECT_EQ(back["current"]["checksum"], before["vocabulary_checksum"]);
  EXPECT_EQ(back["previous"]["origin"], "learned");

  ASSERT_EQ(Cli({"maps", "create", "small"}).code, 0);
  ASSERT_EQ(Cli({"ingest", "small", FramesDir(1, 2)}).code, 0);
  CliRun refused = Cli({"maps", "adapt-vocabulary", "small"});
  EXPECT_EQ(refused.code, 1);
  EXPECT_NE(refused.err.find("too small to learn a vocabulary from"), std::string::npos)
      << refused.err;
}

TEST_F(ClientTest, IngestFolderAsTwoAgentsThenQueryFindsTheRevisit) {
  ASSERT_EQ(Cli({"maps", "create", "loop"}).code, 0);
  const std::string frames = FramesDir(1, 20);

  CliRun ingested = Cli({"ingest", "loop", frames, "--agents", "2", "--json"});
  ASSERT_EQ(ingested.code, 0) << ingested.err;
  const json summary = ParseJson(ingested);
  EXPECT_EQ(summary["agents"], json({"cli-1", "cli-2"}));
  EXPECT_EQ(summary["frames"], 20);
  EXPECT_EQ(summary["answered"], 20);
  const int stored = summary["stored"].get<int>();
  EXPECT_GE(stored, 18);  // a blurred frame or two may have too few static descriptors
  EXPECT_EQ(stored + summary["rejected"]["total"].get<int>(), 20);
  EXPECT_EQ(summary["errors"]["frames"], 0);
  EXPECT_TRUE(summary["stream_errors"].empty());
  EXPECT_GT(summary["frames_per_s"].get<double>(), 0);
  EXPECT_GT(summary["latency_ms"]["p50"].get<double>(), 0);
  EXPECT_LE(summary["latency_ms"]["p50"].get<double>(), summary["latency_ms"]["p99"].get<double>());
  // Natural order, dealt round-robin; the sequence is the position in the input.
  ASSERT_EQ(summary["results"].size(), 20u);
  for (int k = 0; k < 20; ++k) {
    const json& r = summary["results"][size_t(k)];
    EXPECT_EQ(r["name"], frames + "/" + std::to_string(k + 1) + ".jpg");
    EXPECT_EQ(r["agent"], k % 2 == 0 ? "cli-1" : "cli-2");
    EXPECT_EQ(r["sequence"], k);
    if (r["stored"].get<bool>()) {
      EXPECT_TRUE(r.contains("place_id"));
    } else {
      EXPECT_NE(r["rejection"].get<std::string>().find("placeThreshold"), std::string::npos);
    }
  }
  EXPECT_EQ(ParseJson(Cli({"maps", "show", "loop", "--json"}))["stats"]["places"],
            std::to_string(stored));

  // A revisit frame (41..84) whose ground truth matches one of frames 1..20.
  const cv::Mat truth = testing::RtabmapGroundTruth();
  int revisit = 0;
  for (int frame = 41; frame <= 84 && revisit == 0; ++frame) {
    for (int j = 1; j <= 20; ++j) {
      if (truth.at<uint8_t>(frame - 1, j - 1)) revisit = frame;
    }
  }
  ASSERT_GT(revisit, 0);
  CliRun queried =
      Cli({"query", "loop", testing::RtabmapFramePath(revisit), "--top-k", "3", "--json"});
  ASSERT_EQ(queried.code, 0) << queried.err;
  const json result = ParseJson(queried);
  EXPECT_EQ(result["valid"], true);
  ASSERT_FALSE(result["matches"].empty());
  const json& top = result["matches"][0];
  const int matched_frame = std::stoi(top["metadata"]["sequence"].get<std::string>()) + 1;
  EXPECT_TRUE(truth.at<uint8_t>(revisit - 1, matched_frame - 1))
      << "frame " << revisit << " matched frame " << matched_frame;
  EXPECT_GT(result["timings"]["total_ms"].get<double>(), 0);

  CliRun table = Cli({"query", "loop", testing::RtabmapFramePath(revisit), "--top-k", "3"});
  ASSERT_EQ(table.code, 0) << table.err;
  for (const char* text : {"RANK", "PLACE", "SCORE", "AGENT", "SEQUENCE", "TIMESTAMP", "INLIERS",
                           "VERIFIED", "timings (ms):", "extract", "total"}) {
    EXPECT_NE(table.out.find(text), std::string::npos) << text << " missing from\n" << table.out;
  }

  // The matched place: get, delete, gone.
  const std::string id = std::to_string(top["place_id"].get<int>());
  CliRun got = Cli({"place", "get", "loop", id, "--json"});
  ASSERT_EQ(got.code, 0) << got.err;
  const json place = ParseJson(got);
  EXPECT_EQ(place["metadata"]["agent_id"], top["metadata"]["agent_id"]);
  EXPECT_EQ(place["metadata"]["sequence"], top["metadata"]["sequence"]);
  EXPECT_GT(place["counts"]["kept"].get<int>(), 20);
  CliRun human = Cli({"place", "get", "loop", id, "--features"});
  ASSERT_EQ(human.code, 0) << human.err;
  EXPECT_NE(human.out.find("static keypoints"), std::string::npos) << human.out;
  EXPECT_EQ(Cli({"place", "delete", "loop", id}).code, 0);
  CliRun missing = Cli({"place", "get", "loop", id});
  EXPECT_EQ(missing.code, 1);
  EXPECT_NE(missing.err.find("NOT_FOUND"), std::string::npos) << missing.err;
  EXPECT_EQ(Cli({"place", "delete", "loop", id}).code, 1);
  EXPECT_EQ(ParseJson(Cli({"maps", "show", "loop", "--json"}))["stats"]["places"],
            std::to_string(stored - 1));
}

// `places list` pages newest first (JSON and table), filters by agent, refuses bad paging;
// `maps get` shows the agents' activity; `query --correspondences` carries the inliers.
TEST_F(ClientTest, PlacesListAgentsAndCorrespondences) {
  ASSERT_EQ(Cli({"maps", "create", "loop", "--verify", "exhaustive"}).code, 0);
  CliRun ingested = Cli({"ingest", "loop", FramesDir(1, 10), "--agents", "2", "--json"});
  ASSERT_EQ(ingested.code, 0) << ingested.err;
  const int stored = ParseJson(ingested)["stored"].get<int>();
  ASSERT_GE(stored, 8);

  // Every page until no next: each place once, ids descending.
  std::vector<int> ids;
  std::string before;
  for (int page = 0; page < 20; ++page) {
    std::vector<std::string> args = {"places", "list", "loop", "--limit", "3", "--json"};
    if (!before.empty()) args.insert(args.end(), {"--before", before});
    CliRun listed = Cli(args);
    ASSERT_EQ(listed.code, 0) << listed.err;
    const json response = ParseJson(listed);
    for (const json& place : response["places"]) ids.push_back(place["place_id"].get<int>());
    const int next = response["next_before_place_id"].get<int>();
    if (next == 0) break;
    before = std::to_string(next);
  }
  ASSERT_EQ(int(ids.size()), stored);
  EXPECT_TRUE(std::is_sorted(ids.rbegin(), ids.rend()));
  EXPECT_EQ(std::adjacent_find(ids.begin(), ids.end()), ids.end());

  const json second = ParseJson(Cli({"place", "list", "loop", "--agent", "cli-2", "--json"}));
  ASSERT_FALSE(second["places"].empty());
  for (const json& place : second["places"]) EXPECT_EQ(place["metadata"]["agent_id"], "cli-2");

  CliRun table = Cli({"places", "list", "loop", "--limit", "2"});
  ASSERT_EQ(table.code, 0) << table.err;
  for (const char* text : {"ID", "AGENT", "OBSERVED", "KEPT", "DROPPED", "next page: --before"}) {
    EXPECT_NE(table.out.find(text), std::string::npos) << text << " missing from\n" << table.out;
  }
  CliRun too_many = Cli({"places", "list", "loop", "--limit", "1001"});
  EXPECT_EQ(too_many.code, 1);
  EXPECT_NE(too_many.err.find("limit"), std::string::npos) << too_many.err;
  CliRun bad_time = Cli({"places", "list", "loop", "--from", "yesterday"});
  EXPECT_EQ(bad_time.code, 2);
  EXPECT_NE(bad_time.err.find("--from"), std::string::npos) << bad_time.err;
  // An ISO window that ends before any frame was taken holds nothing.
  const json empty = ParseJson(
      Cli({"places", "list", "loop", "--to", "1970-01-01T00:00:00.000000001Z", "--json"}));
  EXPECT_TRUE(empty["places"].empty()) << empty.dump();

  const json map = ParseJson(Cli({"maps", "get", "loop", "--json"}));
  ASSERT_EQ(map["agents"].size(), 2u);
  EXPECT_EQ(map["agents"][0]["agent_id"], "cli-1");
  EXPECT_EQ(map["agents"][0]["frames"], "5");  // uint64 as a string (proto3 JSON)
  EXPECT_EQ(map["agents"][1]["frames"], "5");
  CliRun shown = Cli({"maps", "show", "loop"});
  ASSERT_EQ(shown.code, 0) << shown.err;
  for (const char* text : {"agents (since the server started)", "FRAMES/S", "cli-1", "cli-2"}) {
    EXPECT_NE(shown.out.find(text), std::string::npos) << text << " missing from\n" << shown.out;
  }

  CliRun queried = Cli({"query", "loop", testing::RtabmapFramePath(5), "--top-k", "2",
                        "--correspondences", "--json"});
  ASSERT_EQ(queried.code, 0) << queried.err;
  const json result = ParseJson(queried);
  ASSERT_FALSE(result["matches"].empty());
  const json& top = result["matches"][0];
  ASSERT_EQ(top["verified"], true);
  EXPECT_EQ(int(top["correspondences"].size()), top["inliers"].get<int>());
  EXPECT_EQ(result["query_keypoints"].size(), size_t(result["counts"]["kept"].get<int>()));
  EXPECT_EQ(result["image_width"], 512);
  const json plain = ParseJson(Cli({"query", "loop", testing::RtabmapFramePath(5), "--json"}));
  EXPECT_TRUE(plain["matches"][0]["correspondences"].empty());
  EXPECT_TRUE(plain["query_keypoints"].empty());
}

TEST(ClientFlagsTest, TimeFlagsAreNanosecondsOrUtcIso) {
  EXPECT_EQ(*client::ParseTimeFlag("1732400000000000000", "--from"), 1732400000000000000);
  EXPECT_EQ(*client::ParseTimeFlag("2024-11-23T22:13:20Z", "--from"), 1732400000000000000);
  EXPECT_EQ(*client::ParseTimeFlag("2024-11-23T22:13:20.25Z", "--to"), 1732400000250000000);
  for (const char* bad : {"", "yesterday", "2024-11-23", "2024-11-23T22:13:20", "-5",
                          "2024-11-23T22:13:20.Z", "99999999999999999999"}) {
    auto parsed = client::ParseTimeFlag(bad, "--to");
    ASSERT_FALSE(parsed.ok()) << bad;
    EXPECT_NE(parsed.status().message().find("--to"), std::string::npos);
  }
}

// `maps create --thumbnails --thumbnail-size N` and `place get MAP ID --thumbnail FILE`: the map
// keeps thumbnails of that size and the CLI writes a place's JPEG; a map without thumbnails has
// none to write (exit 1), and a size without --thumbnails or out of range is refused.
TEST_F(ClientTest, PlaceGetWritesTheThumbnail) {
  CliRun created = Cli({"maps", "create", "pics", "--thumbnails", "--thumbnail-size", "160"});
  ASSERT_EQ(created.code, 0) << created.err;
  const json config = ParseJson(Cli({"maps", "show", "pics", "--json"}))["config"];
  EXPECT_EQ(config["thumbnails"]["enabled"], true);
  EXPECT_EQ(config["thumbnails"]["max_side"], 160);
  CliRun shown = Cli({"maps", "show", "pics"});
  EXPECT_NE(shown.out.find("on, 160 px, quality 75"), std::string::npos) << shown.out;
  CliRun ingested = Cli({"ingest", "pics", FramesDir(1, 4), "--json"});
  ASSERT_EQ(ingested.code, 0) << ingested.err;
  const std::string file = root_ + "/place.jpg";
  CliRun got = Cli({"place", "get", "pics", "1", "--thumbnail", file});
  ASSERT_EQ(got.code, 0) << got.err;
  EXPECT_NE(got.out.find("160x120 of 512x384"), std::string::npos) << got.out;
  const cv::Mat written = cv::imread(file, cv::IMREAD_UNCHANGED);
  ASSERT_FALSE(written.empty());
  EXPECT_EQ(written.size(), cv::Size(160, 120));

  ASSERT_EQ(Cli({"maps", "create", "plain"}).code, 0);
  ASSERT_EQ(Cli({"ingest", "plain", FramesDir(5, 6)}).code, 0);
  CliRun none = Cli({"place", "get", "plain", "1", "--thumbnail", root_ + "/none.jpg"});
  EXPECT_EQ(none.code, 1);
  EXPECT_NE(none.err.find("has no thumbnail"), std::string::npos) << none.err;
  EXPECT_FALSE(fs::exists(root_ + "/none.jpg"));
  EXPECT_EQ(Cli({"maps", "create", "x", "--thumbnail-size", "100"}).code, 2);
  CliRun too_big = Cli({"maps", "create", "x", "--thumbnails", "--thumbnail-size", "4096"});
  EXPECT_EQ(too_big.code, 1);
  EXPECT_NE(too_big.err.find("config.thumbnails.max_side"), std::string::npos) << too_big.err;
}

// `placedb dynamics`: the map's statistics and a ranked page, as a table or JSON; bad flags are
// usage errors, an unknown map an RPC error.
TEST_F(ClientTest, DynamicsShowsTheMapAndRanksItsPlaces) {
  ASSERT_EQ(Cli({"maps", "create", "dyn"}).code, 0);
  CliRun ingested = Cli({"ingest", "dyn", FramesDir(1, 8), "--json"});
  ASSERT_EQ(ingested.code, 0) << ingested.err;
  const int stored = ParseJson(ingested)["stored"].get<int>();
  ASSERT_GT(stored, 3);
  CliRun got = Cli({"dynamics", "dyn", "--limit", "3", "--json"});
  ASSERT_EQ(got.code, 0) << got.err;
  const json page = ParseJson(got);
  EXPECT_EQ(page["map"]["observations"], std::to_string(stored));  // 64-bit: a JSON string
  EXPECT_EQ(page["ranked"], std::to_string(stored));
  EXPECT_EQ(page["places"].size(), 3u);
  EXPECT_EQ(page["next_offset"], 3);
  CliRun table = Cli({"dynamics", "dyn", "--hours", "0-23"});  // every frame is in the window
  ASSERT_EQ(table.code, 0) << table.err;
  for (const char* text : {"frames", "coverage", "RANK", "PLACE", "SCORE", "LAST SEEN"}) {
    EXPECT_NE(table.out.find(text), std::string::npos) << text << " missing from\n" << table.out;
  }
  EXPECT_EQ(Cli({"dynamics", "dyn", "--class", "car"}).code, 0);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--hours", "22-2", "--weekdays", "sat,sun"}).code, 0);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--hours", "8-25"}).code, 2);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--class", "unicorn"}).code, 2);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--weekdays", "mon"}).code, 2);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--class", "car", "--hours", "1-2"}).code, 2);
  EXPECT_EQ(Cli({"dynamics", "nowhere"}).code, 1);
  // Near a point far from every frame: nothing is ranked.
  CliRun near = Cli({"dynamics", "dyn", "--near", "1e6,1e6,0", "--radius", "5", "--json"});
  ASSERT_EQ(near.code, 0) << near.err;
  EXPECT_TRUE(ParseJson(near)["places"].empty());
  EXPECT_EQ(ParseJson(near)["ranked"], "0");
  EXPECT_EQ(Cli({"dynamics", "dyn", "--near", "1", "--radius", "5"}).code, 2);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--radius", "5"}).code, 2);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--near", "1,2"}).code, 2);
  EXPECT_EQ(Cli({"dynamics", "dyn", "--near", "1,2", "--radius", "-1"}).code, 1);
}

// `placedb dynamics --png`: the chart is written with its fixed size, after the table; a file
// that cannot be written is a usage error naming it.
TEST_F(ClientTest, DynamicsWritesAChartPng) {
  ASSERT_EQ(Cli({"maps", "create", "dyn"}).code, 0);
  ASSERT_EQ(Cli({"ingest", "dyn", FramesDir(1, 6)}).code, 0);
  const std::string png = root_ + "/dynamics.png";
  CliRun drawn = Cli({"dynamics", "dyn", "--png", png});
  ASSERT_EQ(drawn.code, 0) << drawn.err;
  EXPECT_NE(drawn.out.find("RANK"), std::string::npos) << "the table is still printed";
  const cv::Mat chart = cv::imread(png, cv::IMREAD_UNCHANGED);
  ASSERT_FALSE(chart.empty()) << png << " does not decode";
  EXPECT_EQ(chart.cols, 960);
  EXPECT_EQ(chart.rows, 960);
  EXPECT_EQ(chart.channels(), 3);
  // Not a blank image: the bars and heat map are drawn.
  cv::Scalar mean, deviation;
  cv::meanStdDev(chart, mean, deviation);
  EXPECT_GT(deviation[0], 10.0);
  // By class and as JSON too.
  EXPECT_EQ(Cli({"dynamics", "dyn", "--class", "person", "--json", "--png", png}).code, 0);
  const std::string nowhere = root_ + "/no/such/dir/dynamics.png";
  CliRun bad = Cli({"dynamics", "dyn", "--png", nowhere});
  EXPECT_EQ(bad.code, 2);
  EXPECT_NE(bad.err.find("cannot write " + nowhere), std::string::npos) << bad.err;
  EXPECT_FALSE(std::filesystem::exists(nowhere));
}

// The chart itself (no server): a place with a thumbnail gets it beside its bar, the others a
// grey placeholder; hours without frames stay grey, the hour with frames is coloured.
TEST(DynamicsChart, ThumbnailsBesideTheirBarsAndEmptyHoursGrey) {
  v1::GetDynamicsResponse page;
  page.mutable_map()->set_observations(3);
  page.mutable_map()->set_mean_coverage(0.2);
  v1::HourCoverage* bin = page.mutable_map()->add_hours();
  bin->set_weekday(2);
  bin->set_hour(9);
  bin->set_observations(3);
  bin->set_mean_coverage(0.2);
  for (uint32_t id : {7u, 8u}) {
    v1::RankedPlace* place = page.add_places();
    place->set_place_id(id);
    place->set_score(id == 7 ? 0.3 : 0.1);
    place->set_support(1);
  }
  const cv::Mat red(48, 64, CV_8UC3, cv::Scalar(0, 0, 255));
  const cv::Mat chart = client::DrawDynamicsChart("m", "mean coverage", page, {{7u, red}});
  ASSERT_EQ(chart.cols, client::kDynamicsChartWidth);
  ASSERT_EQ(chart.rows, client::kDynamicsChartHeight);
  // The first bar's slot (its top left is 4 px below the bars' area, 20 px from the left).
  auto pixel = [&](int x, int y) { return chart.at<cv::Vec3b>(y, x); };
  EXPECT_EQ(pixel(40, 580), cv::Vec3b(0, 0, 255)) << "place 7's thumbnail";
  const int row = (client::kDynamicsChartHeight - 580) / client::kDynamicsChartMaxBars;
  EXPECT_EQ(pixel(30, 580 + row + 10), cv::Vec3b(200, 200, 200)) << "place 8's placeholder";
  // Heat map: Wednesday (row 2) at 09 h coloured, 10 h grey (cells of 860/24 x 22 px from 70, 340).
  const double cell = (client::kDynamicsChartWidth - 30 - 70) / 24.0;
  EXPECT_NE(pixel(70 + int(9.5 * cell), 340 + 2 * 22 + 10), cv::Vec3b(200, 200, 200));
  EXPECT_EQ(pixel(70 + int(10.5 * cell), 340 + 2 * 22 + 10), cv::Vec3b(200, 200, 200));
}

// The human summary, per-frame matches, progress lines when stderr is not a terminal, a list
// file and a video as sources, and a stream refused for an unknown map.
TEST_F(ClientTest, IngestSummaryListsAndVideos) {
  ASSERT_EQ(Cli({"maps", "create", "m"}).code, 0);
  CliRun run = Cli({"ingest", "m", FramesDir(1, 4), "--matches", "--agent-id", "robot"});
  ASSERT_EQ(run.code, 0) << run.err;
  for (const char* text :
       {"sent 4 of 4 frames to 'm' with 1 agent", ", 4 answered", "stored", "rejected",
        "errors     0", "latency", "p50", "p99", "1.jpg -> place", "4.jpg -> place"}) {
    EXPECT_NE(run.out.find(text), std::string::npos) << text << " missing from\n" << run.out;
  }
  EXPECT_NE(run.err.find("progress: 4/4 frames (100%)"), std::string::npos) << run.err;

  // A list file (relative paths, comments) and a video (every 2nd frame).
  const std::string list = root_ + "/list.txt";
  {
    std::ofstream out(list);
    out << "# frames\n"
        << fs::relative(testing::RtabmapFramePath(30), root_).string() << "\n\n"
        << testing::RtabmapFramePath(31) << "\n";
  }
  const std::string video = root_ + "/clip.avi";
  {
    const cv::Mat first = cv::imread(testing::RtabmapFramePath(21));
    cv::VideoWriter writer(video, cv::VideoWriter::fourcc('M', 'J', 'P', 'G'), 10, first.size());
    ASSERT_TRUE(writer.isOpened());
    for (int frame = 21; frame <= 26; ++frame)
      writer.write(cv::imread(testing::RtabmapFramePath(frame)));
  }
  std::string error;
  auto source = client::FrameSource::Open({list, video}, 2, "", &error);
  ASSERT_TRUE(source) << error;
  ASSERT_TRUE(source->total());
  EXPECT_EQ(*source->total(), 5u);  // 2 listed + 3 of 6 video frames
  std::vector<std::string> names;
  client::Frame frame;
  while (source->Next(&frame, &error)) {
    EXPECT_TRUE(error.empty()) << error;
    EXPECT_TRUE(client::IsJpegOrPng(frame.bytes));
    names.push_back(frame.name);
  }
  ASSERT_EQ(names.size(), 5u);
  EXPECT_TRUE(fs::equivalent(names[0], testing::RtabmapFramePath(30))) << names[0];
  EXPECT_EQ(names[1], testing::RtabmapFramePath(31));
  EXPECT_EQ(names[2], video + "#0");
  EXPECT_EQ(names[3], video + "#2");
  EXPECT_EQ(names[4], video + "#4");
  const json summary =
      ParseJson(Cli({"ingest", "m", list, video, "--video-every", "2", "--agents", "2", "--json"}));
  EXPECT_EQ(summary["frames"], 5);
  EXPECT_EQ(summary["answered"], 5);
  EXPECT_EQ(summary["errors"]["frames"], 0);

  CliRun unknown = Cli({"ingest", "nope", FramesDir(5, 6), "--agents", "2"});
  EXPECT_EQ(unknown.code, 1);
  EXPECT_NE(unknown.err.find("NOT_FOUND"), std::string::npos) << unknown.err;
  EXPECT_EQ(Cli({"ingest", "m", root_ + "/no-such-folder"}).code, 2);
}

// ---- info, health, usage ------------------------------------------------------------------------

TEST_F(ClientTest, InfoAndHealth) {
  CliRun info = Cli({"info"});
  ASSERT_EQ(info.code, 0) << info.err;
  for (const char* text : {"placedb server " PLACEDB_VERSION, "detector  off", "VOCABULARY",
                           "default", "limits", "worker_threads"}) {
    EXPECT_NE(info.out.find(text), std::string::npos) << text << " missing from\n" << info.out;
  }
  EXPECT_NE(info.out.find(checksum_), std::string::npos);
  const json doc = ParseJson(Cli({"info", "--json"}));
  EXPECT_EQ(doc["version"], PLACEDB_VERSION);
  EXPECT_EQ(doc["vocabularies"][0]["checksum"], checksum_);
  EXPECT_EQ(doc["limits"]["worker_threads"], 2);

  CliRun health = Cli({"health"});
  EXPECT_EQ(health.code, 0) << health.err;
  EXPECT_EQ(health.out, "SERVING\n");
  EXPECT_EQ(Cli({"health", "--service", "placedb.v1.PlaceDb"}).code, 0);
  EXPECT_EQ(Cli({"health", "--service", "no.such.Service"}).code, 1);
  // Tokens and TLS options are accepted (the server does not check tokens yet).
  EXPECT_EQ(Cli({"--token", "secret", "health"}).code, 0);

  const std::string nowhere = "127.0.0.1:" + std::to_string(placedb::testing::UnusedLoopbackPort());
  CliRun unreachable = RunPlacedb({"--address", nowhere, "--timeout", "5", "health"});
  EXPECT_EQ(unreachable.code, 2);
  EXPECT_EQ(unreachable.out, "UNREACHABLE\n");
  EXPECT_NE(unreachable.err.find("UNAVAILABLE"), std::string::npos) << unreachable.err;
  const json down = ParseJson(RunPlacedb({"--address", nowhere, "--json", "health"}));
  EXPECT_EQ(down["status"], "UNREACHABLE");
  // Other commands against nothing: an RPC error that says what to check (it was gRPC's text
  // alone).
  const CliRun listed = RunPlacedb({"--address", nowhere, "maps", "list"});
  EXPECT_EQ(listed.code, 1);
  EXPECT_NE(listed.err.find("is placedb-server running at " + nowhere + "?"), std::string::npos)
      << listed.err;
  EXPECT_NE(unreachable.err.find("is placedb-server running at " + nowhere + "?"),
            std::string::npos)
      << unreachable.err;
  // A server's own answer names no such doubt.
  const CliRun missing = Cli({"maps", "show", "no-such-map"});
  EXPECT_EQ(missing.code, 1);
  EXPECT_EQ(missing.err.find("is placedb-server running"), std::string::npos) << missing.err;
  // A bare port is this machine's (it was a DNS error).
  const std::string port = address_.substr(address_.rfind(':') + 1);
  const CliRun by_port = RunPlacedb({"--address", port, "health"});
  EXPECT_EQ(by_port.code, 0) << by_port.err;
  EXPECT_EQ(by_port.out, "SERVING\n");
}

TEST_F(ClientTest, UsageErrorsExitTwo) {
  EXPECT_EQ(Cli({}).code, 2);
  EXPECT_EQ(Cli({"frobnicate"}).code, 2);
  EXPECT_EQ(Cli({"maps"}).code, 2);
  EXPECT_EQ(Cli({"maps", "create"}).code, 2);
  EXPECT_EQ(Cli({"maps", "create", "m", "--filter", "bogus"}).code, 2);
  EXPECT_EQ(Cli({"maps", "create", "m", "--features", "many"}).code, 2);
  EXPECT_EQ(Cli({"ingest", "m"}).code, 2);
  EXPECT_EQ(Cli({"ingest", "m", FramesDir(1, 2), "--agents", "0"}).code, 2);
  EXPECT_EQ(Cli({"query", "m", root_ + "/missing.jpg"}).code, 2);
  EXPECT_EQ(Cli({"place", "get", "m", "not-a-number"}).code, 2);
  EXPECT_EQ(Cli({"load", FramesDir(3, 4), "--rate", "5", "--total-rate", "10"}).code, 2);
  // A malformed boxes file is the caller's mistake too.
  ASSERT_EQ(Cli({"maps", "create", "m"}).code, 0);
  const std::string boxes = root_ + "/boxes.json";
  std::ofstream(boxes) << R"([{"class": "person", "rect": [1, 2]}])";
  CliRun bad_boxes = Cli({"query", "m", testing::RtabmapFramePath(1), "--boxes", boxes});
  EXPECT_EQ(bad_boxes.code, 2);
  EXPECT_NE(bad_boxes.err.find("boxes[0]"), std::string::npos) << bad_boxes.err;
  // Good boxes are sent and used.
  std::ofstream(boxes) << R"({"boxes": [{"class": "person", "confidence": 0.9,
                                          "rect": {"x": 10, "y": 10, "width": 200, "height": 150}},
                                         {"class_id": 2, "rect": [300, 50, 80, 60]}]})";
  const json used =
      ParseJson(Cli({"query", "m", testing::RtabmapFramePath(1), "--boxes", boxes, "--json"}));
  ASSERT_EQ(used["boxes_used"].size(), 2u);
  EXPECT_EQ(used["boxes_used"][0]["class_name"], "person");
  EXPECT_EQ(used["boxes_used"][1]["class_name"], "car");
  EXPECT_GT(used["counts"]["dynamic"].get<int>(), 0);

  CliRun help = Cli({"--help"});
  EXPECT_EQ(help.code, 0);
  EXPECT_NE(help.out.find("Usage"), std::string::npos);
  CliRun not_found = Cli({"query", "nope", testing::RtabmapFramePath(1)});
  EXPECT_EQ(not_found.code, 1);
  EXPECT_NE(not_found.err.find("NOT_FOUND"), std::string::npos) << not_found.err;
}

// ---- load tester --------------------------------------------------------------------------------

TEST_F(ClientTest, LoadTesterShortRunWritesAJsonReport) {
  const std::string frames = FramesDir(1, 20);
  const std::string report_path = root_ + "/load.json";
  CliRun run = Cli({"load", frames, "--agents", "2", "--frames", "30", "--query-ratio", "0.2",
                    "--json-out", report_path});
  ASSERT_EQ(run.code, 0) << run.err << run.out;
  for (const char* text : {"placedb load", "ingest", "query", "P50 MS", "P99 MS", "server stages",
                           "extract", "errors   none"}) {
    EXPECT_NE(run.out.find(text), std::string::npos) << text << " missing from\n" << run.out;
  }
  std::ifstream in(report_path);
  ASSERT_TRUE(in) << report_path;
  const json report = json::parse(in);
  EXPECT_EQ(report["target"], address_);
  EXPECT_EQ(report["agents"], 2);
  EXPECT_EQ(report["mode"], "encoded");
  EXPECT_EQ(report["source_frames"], 20);
  EXPECT_EQ(report["frames"], 30);
  EXPECT_TRUE(report["errors"].empty()) << report["errors"];
  const json& ingest = report["rpc"]["ingest"];
  const json& query = report["rpc"]["query"];
  EXPECT_EQ(query["count"], 6);  // 20% of 30
  EXPECT_EQ(ingest["count"], 24);
  EXPECT_EQ(ingest["ok"], 24);
  EXPECT_EQ(query["ok"], 6);
  EXPECT_EQ(ingest["stored"].get<int>() + ingest["rejected"].get<int>(), 24);
  EXPECT_GT(report["throughput_fps"].get<double>(), 1.0);
  EXPECT_GT(report["elapsed_s"].get<double>(), 0.0);
  for (const json* kind : {&ingest, &query}) {
    const json& latency = (*kind)["latency_ms"];
    EXPECT_GT(latency["p50"].get<double>(), 0);
    EXPECT_LE(latency["p50"].get<double>(), latency["p90"].get<double>());
    EXPECT_LE(latency["p90"].get<double>(), latency["p99"].get<double>());
    EXPECT_LE(latency["p99"].get<double>(), latency["max"].get<double>());
    const json& stages = (*kind)["stages_ms"];
    for (const char* stage : {"queue", "decode", "extract", "transform", "total"}) {
      ASSERT_TRUE(stages.contains(stage)) << stage;
    }
    EXPECT_GT(stages["extract"]["p50"].get<double>(), 0);
    // The server's total cannot exceed the client's round trip (one clock is inside the other).
    EXPECT_LE(stages["total"]["max"].get<double>(), latency["max"].get<double>() + 1.0);
  }
  EXPECT_GT(ingest["stages_ms"]["store"]["p50"].get<double>(), 0);
  // The temporary map is gone.
  EXPECT_EQ(Cli({"maps", "list"}).out, "no maps\n");

  // Precomputed features into a named map, paced, bounded by time: nothing is extracted there.
  CliRun features = Cli({"load", frames, "--mode", "features", "--map", "index", "--agents", "2",
                         "--total-rate", "40", "--duration", "0.5", "--json"});
  ASSERT_EQ(features.code, 0) << features.err;
  const json paced = ParseJson(features);
  EXPECT_EQ(paced["map"], "index");
  EXPECT_EQ(paced["temporary_map"], false);
  EXPECT_NEAR(paced["rate"]["total_fps"].get<double>(), 40, 1e-9);
  EXPECT_GE(paced["frames"].get<int>(), 10);
  EXPECT_LE(paced["frames"].get<int>(), 22);
  // No ORB on the server: what is left of "extract" is the validation of the keypoints.
  EXPECT_LT(paced["rpc"]["ingest"]["stages_ms"]["extract"]["p50"].get<double>(), 0.2);
  const json index = ParseJson(Cli({"maps", "show", "index", "--json"}));
  EXPECT_GT(std::stoi(index["stats"]["places"].get<std::string>()), 5);
}

TEST_F(ClientTest, LoadTesterRefusesTargetsThatAreNotLoopback) {
  const std::string frames = FramesDir(1, 2);
  for (const char* target :
       {"192.0.2.1:50051", "10.1.2.3:1", "[2001:db8::1]:50051", "ipv4:127.0.0.1:1,192.0.2.7:2"}) {
    CliRun run = RunPlacedb({"--address", target, "load", frames, "--frames", "2"});
    EXPECT_EQ(run.code, 2) << target;
    EXPECT_NE(run.err.find("loopback"), std::string::npos) << run.err;
    EXPECT_TRUE(run.out.empty()) << run.out;
  }
  std::string why;
  for (const char* target : {"localhost:50051", "127.0.0.1:1", "127.1.2.3:1", "[::1]:50051",
                             "ipv4:127.0.0.1:1", "dns:///localhost:1", "unix:/tmp/placedb.sock"}) {
    EXPECT_TRUE(client::IsLoopbackTarget(target, &why)) << target << ": " << why;
  }
  EXPECT_FALSE(client::IsLoopbackTarget("no-such-host.invalid:1", &why));
  EXPECT_NE(why.find("cannot resolve"), std::string::npos) << why;
}

// ---- RGB-D: depth, loop closure, SIFT maps (docs/rgbd.md)
// ----------------------------------------

std::string RgbdPeopleDir() {
  return testing::SharedDir() + "/data/rgbd-people";
}
std::string SlambookDir() {
  return testing::SharedDir() + "/data/slambook2-rgbd";
}

// A 16-bit depth image with a gradient (millimetres), distinct per `seed`.
cv::Mat DepthMillimetres(int seed) {
  cv::Mat depth(48, 64, CV_16UC1);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x)
      depth.at<uint16_t>(y, x) = uint16_t(500 + seed + 40 * x + y);
  }
  return depth;
}

cv::Mat DecodeDepth(const std::string& png16) {
  return cv::imdecode(cv::Mat(1, int(png16.size()), CV_8U, const_cast<char*>(png16.data())),
                      cv::IMREAD_UNCHANGED);
}

bool SameImage(const cv::Mat& a, const cv::Mat& b) {
  return a.type() == b.type() && a.size() == b.size() && cv::countNonZero(a != b) == 0;
}

// Pairing by file stem and the encodings sent: a 16-bit PNG as it is, a 16-bit PGM re-encoded as
// 16-bit PNG (values kept), a float32 TIFF as raw float32; a missing depth names its frame.
TEST(ClientDepthTest, PairsDepthImagesByStemAndEncodesThem) {
  const std::string root = testing::MakeTempDir("placedb-client-depth");
  fs::create_directories(root + "/colour");
  fs::create_directories(root + "/depth");
  const cv::Mat colour(48, 64, CV_8UC3, cv::Scalar(40, 80, 120));
  for (const char* name : {"1.jpg", "2.png", "frame_3.jpg", "4.jpg"}) {
    ASSERT_TRUE(cv::imwrite(root + "/colour/" + name, colour));
  }
  ASSERT_TRUE(cv::imwrite(root + "/depth/1.png", DepthMillimetres(1)));
  ASSERT_TRUE(cv::imwrite(root + "/depth/2.pgm", DepthMillimetres(2)));
  cv::Mat metres;
  DepthMillimetres(3).convertTo(metres, CV_32F, 0.001);
  ASSERT_TRUE(cv::imwrite(root + "/depth/frame_3.tif", metres));
  ASSERT_TRUE(cv::imwrite(root + "/depth/8bit.png", cv::Mat(48, 64, CV_8UC1, cv::Scalar(7))));

  std::string error;
  auto source = client::FrameSource::Open({root + "/colour"}, 1, "", &error);
  ASSERT_TRUE(source) << error;
  const std::vector<std::string> paths = source->image_paths();
  // Natural order: "4.jpg" before "frame_3.jpg".
  ASSERT_EQ(paths,
            (std::vector<std::string>{root + "/colour/1.jpg", root + "/colour/2.png",
                                      root + "/colour/4.jpg", root + "/colour/frame_3.jpg"}));
  EXPECT_TRUE(source->video_paths().empty());
  EXPECT_EQ(client::FindDepthImage(root + "/depth", paths[0], &error), root + "/depth/1.png");
  EXPECT_EQ(client::FindDepthImage(root + "/depth", paths[1], &error), root + "/depth/2.pgm");
  EXPECT_EQ(client::FindDepthImage(root + "/depth", paths[3], &error), root + "/depth/frame_3.tif");
  EXPECT_EQ(client::FindDepthImage(root + "/depth", paths[2], &error), "");
  EXPECT_NE(error.find("no depth image for frame " + root + "/colour/4.jpg"), std::string::npos)
      << error;
  EXPECT_NE(error.find(root + "/depth/4.png"), std::string::npos) << error;

  // 16-bit PNG: the file's own bytes.
  v1::DepthImage png;
  ASSERT_TRUE(client::ReadDepthImage(root + "/depth/1.png", &png, &error)) << error;
  ASSERT_EQ(png.data_case(), v1::DepthImage::kPng16);
  EXPECT_EQ(png.png16(), testing::ReadFileBytes(root + "/depth/1.png"));
  // 16-bit PGM: re-encoded as a 16-bit PNG with the same values.
  v1::DepthImage pgm;
  ASSERT_TRUE(client::ReadDepthImage(root + "/depth/2.pgm", &pgm, &error)) << error;
  ASSERT_EQ(pgm.data_case(), v1::DepthImage::kPng16);
  ASSERT_EQ(pgm.png16().compare(0, 8, "\x89PNG\r\n\x1a\n"), 0);
  EXPECT_EQ(uint8_t(pgm.png16()[24]), 16);  // IHDR bit depth
  EXPECT_TRUE(SameImage(DecodeDepth(pgm.png16()), DepthMillimetres(2)));
  // The real 16-bit PGMs of slambook2-rgbd too.
  v1::DepthImage room;
  ASSERT_TRUE(client::ReadDepthImage(SlambookDir() + "/depth/1.pgm", &room, &error)) << error;
  EXPECT_TRUE(SameImage(DecodeDepth(room.png16()),
                        cv::imread(SlambookDir() + "/depth/1.pgm", cv::IMREAD_UNCHANGED)));
  // float32 TIFF: raw little-endian float32.
  v1::DepthImage raw;
  ASSERT_TRUE(client::ReadDepthImage(root + "/depth/frame_3.tif", &raw, &error)) << error;
  ASSERT_EQ(raw.data_case(), v1::DepthImage::kRawFloat32);
  EXPECT_EQ(raw.raw_float32().width(), 64u);
  EXPECT_EQ(raw.raw_float32().height(), 48u);
  ASSERT_EQ(raw.raw_float32().data().size(), 64u * 48u * 4u);
  float first = 0;
  std::memcpy(&first, raw.raw_float32().data().data(), 4);  // x86: little-endian
  EXPECT_FLOAT_EQ(first, metres.at<float>(0, 0));
  // An 8-bit image is no depth image.
  v1::DepthImage eight;
  EXPECT_FALSE(client::ReadDepthImage(root + "/depth/8bit.png", &eight, &error));
  EXPECT_NE(error.find("16-bit or float32"), std::string::npos) << error;

  v1::Intrinsics k;
  ASSERT_TRUE(client::ParseIntrinsics("518, 519,325.5,253.5", &k, &error)) << error;
  EXPECT_EQ(k.fx(), 518);
  EXPECT_EQ(k.fy(), 519);
  EXPECT_EQ(k.cx(), 325.5);
  EXPECT_EQ(k.cy(), 253.5);
  for (const char* bad : {"", "1,2,3", "1,2,3,4,5", "0,1,2,3", "a,b,c,d", "1,1,-1,2", "1,,2,3"}) {
    EXPECT_FALSE(client::ParseIntrinsics(bad, &k, &error)) << bad;
  }
}

// Local depth problems are usage errors found before anything is sent.
TEST_F(ClientTest, IngestDepthProblemsAreUsageErrors) {
  ASSERT_EQ(Cli({"maps", "create", "m"}).code, 0);
  const std::string colour = root_ + "/colour";
  const std::string depth = root_ + "/depth";
  fs::create_directories(colour);
  fs::create_directories(depth);
  for (int frame : {1, 2, 3}) {
    fs::create_symlink(testing::RtabmapFramePath(frame),
                       colour + "/" + std::to_string(frame) + ".jpg");
  }
  const cv::Size size = cv::imread(testing::RtabmapFramePath(1)).size();
  for (int frame : {1, 3}) {
    ASSERT_TRUE(cv::imwrite(depth + "/" + std::to_string(frame) + ".png",
                            cv::Mat(size, CV_16UC1, cv::Scalar(1500))));
  }
  CliRun missing = Cli({"ingest", "m", colour, "--depth", depth});
  EXPECT_EQ(missing.code, 2);
  EXPECT_NE(missing.err.find("no depth image for frame " + colour + "/2.jpg"), std::string::npos)
      << missing.err;
  EXPECT_EQ(ParseJson(Cli({"maps", "show", "m", "--json"}))["stats"]["places"], "0");

  EXPECT_EQ(Cli({"ingest", "m", colour, "--depth-scale", "0.001"}).code, 2);
  EXPECT_EQ(Cli({"ingest", "m", colour, "--intrinsics", "500,500,320,240"}).code, 2);
  EXPECT_EQ(Cli({"ingest", "m", colour, "--depth", root_ + "/nowhere"}).code, 2);
  fs::remove(colour + "/2.jpg");
  EXPECT_EQ(Cli({"ingest", "m", colour, "--depth", depth, "--intrinsics", "1,2"}).code, 2);
  EXPECT_EQ(Cli({"query", "m", testing::RtabmapFramePath(1), "--depth-scale", "0.001"}).code, 2);
  EXPECT_EQ(Cli({"query", "m", testing::RtabmapFramePath(1), "--depth", root_ + "/none.png"}).code,
            2);

  // The pairs that exist go through (the server checks the depth against the frame).
  const json summary = ParseJson(Cli({"ingest", "m", colour, "--depth", depth, "--json"}));
  EXPECT_EQ(summary["frames"], 2);
  EXPECT_EQ(summary["answered"], 2);
  EXPECT_EQ(summary["local_errors"], 0);
  EXPECT_EQ(summary["errors"]["frames"], 0) << summary.dump(2);
}

// The RGB-D create flags end up in the map's configuration; show and info print them.
TEST_F(ClientTest, CreateRgbdFlagsSetTheMapConfig) {
  CliRun created = Cli({"maps",
                        "create",
                        "rgbd",
                        "--feature-type",
                        "orb",
                        "--no-refine-boxes",
                        "--depth-scale",
                        "0.0002",
                        "--depth-threshold",
                        "0.2",
                        "--band-policy",
                        "nearest_layer",
                        "--loop-threshold",
                        "0.2",
                        "--rehearsal-threshold",
                        "0.3",
                        "--stm",
                        "10",
                        "--max-wm",
                        "100",
                        "--wm-time-budget-ms",
                        "5"});
  ASSERT_EQ(created.code, 0) << created.err;
  json map = ParseJson(Cli({"maps", "show", "rgbd", "--json"}));
  json config = map["config"];
  EXPECT_EQ(config["feature_type"], "FEATURE_TYPE_ORB");
  EXPECT_EQ(config["depth"]["refine_boxes"], false);
  EXPECT_EQ(config["depth"]["stream_filter"], true);  // the server's default
  EXPECT_NEAR(config["depth"]["scale"].get<double>(), 0.0002, 1e-9);
  EXPECT_NEAR(config["depth"]["threshold_m"].get<double>(), 0.2, 1e-6);
  EXPECT_EQ(config["depth"]["band_policy"], "BAND_POLICY_NEAREST_LAYER");
  EXPECT_EQ(config["depth"]["mean_all_pixels"], false);
  EXPECT_NEAR(config["loop_closure"]["loop_threshold"].get<double>(), 0.2, 1e-9);
  EXPECT_NEAR(config["loop_closure"]["rehearsal_threshold"].get<double>(), 0.3, 1e-9);
  EXPECT_EQ(config["loop_closure"]["short_term_memory"], 10);
  EXPECT_EQ(config["loop_closure"]["max_working_memory"], 100);
  EXPECT_NEAR(config["loop_closure"]["time_budget_ms"].get<double>(), 5, 1e-9);
  for (const char* stat : {"streams", "loop_working_memory", "loop_long_term", "loops_accepted"}) {
    EXPECT_EQ(map["stats"][stat], "0") << stat;
  }

  CliRun shown = Cli({"maps", "show", "rgbd"});
  ASSERT_EQ(shown.code, 0) << shown.err;
  for (const char* text :
       {"features  ", "orb", "refine_boxes off", "scale 0.0002", "depth filter", "threshold 0.20 m",
        "band nearest_layer", "loop closure", "loop_threshold 0.200", "rehearsal_threshold 0.300",
        "stm 10", "max_wm 100", "time_budget 5.0 ms", "streams", "loop working memory",
        "loop long-term", "loops accepted"}) {
    EXPECT_NE(shown.out.find(text), std::string::npos) << text << " missing from\n" << shown.out;
  }

  // --paper-literal: the mean over all pixels and the fixed bands; the stream filter off.
  ASSERT_EQ(Cli({"maps", "create", "paper", "--paper-literal", "--no-depth-filter"}).code, 0);
  config = ParseJson(Cli({"maps", "show", "paper", "--json"}))["config"];
  EXPECT_EQ(config["depth"]["mean_all_pixels"], true);
  EXPECT_EQ(config["depth"]["band_policy"], "BAND_POLICY_FIXED");
  EXPECT_EQ(config["depth"]["stream_filter"], false);
  EXPECT_EQ(config["depth"]["refine_boxes"], true);
  // Default-created maps: the vocabulary's kind.
  EXPECT_EQ(config["feature_type"], "FEATURE_TYPE_ORB");

  EXPECT_EQ(Cli({"maps", "create", "x", "--paper-literal", "--band-policy", "fixed"}).code, 2);
  EXPECT_EQ(Cli({"maps", "create", "x", "--band-policy", "widest"}).code, 2);
  EXPECT_EQ(Cli({"maps", "create", "x", "--feature-type", "surf"}).code, 2);
  EXPECT_EQ(Cli({"maps", "create", "x", "--loop-threshold", "2"}).code, 2);
  // The default vocabulary is binary: a SIFT map on it is refused by the server.
  CliRun mismatch = Cli({"maps", "create", "x", "--feature-type", "sift"});
  EXPECT_EQ(mismatch.code, 1);
  EXPECT_NE(mismatch.err.find("INVALID_ARGUMENT"), std::string::npos) << mismatch.err;

  CliRun info = Cli({"info"});
  ASSERT_EQ(info.code, 0) << info.err;
  EXPECT_NE(info.out.find("FEATURES"), std::string::npos) << info.out;
  const json server = ParseJson(Cli({"info", "--json"}));
  EXPECT_EQ(server["vocabularies"][0]["feature_type"], "FEATURE_TYPE_ORB");
}

// One agent through the RTAB-Map loop with loop closure: every valid frame reports its
// loop-closure outcome; the summary adds up; accepted loops are (mostly) ground-truth revisits.
TEST_F(ClientTest, IngestLoopClosureOnTheRtabmapLoop) {
  ASSERT_EQ(Cli({"maps", "create", "loop"}).code, 0);
  const std::string folder = testing::SharedDir() + "/data/rtabmap-loop";
  CliRun run = Cli({"ingest", "loop", folder, "--glob", "*.jpg", "--loop-closure", "--json"});
  ASSERT_EQ(run.code, 0) << run.err;
  const json summary = ParseJson(run);
  EXPECT_EQ(summary["loop_closure"], true);
  EXPECT_EQ(summary["frames"], 84);
  EXPECT_EQ(summary["answered"], 84);
  const int stored = summary["stored"].get<int>();
  const int merged = summary["merged"].get<int>();
  const int rejected = summary["rejected"]["total"].get<int>();
  const int errors = summary["errors"]["frames"].get<int>() + summary["local_errors"].get<int>();
  EXPECT_EQ(stored + merged + rejected + errors, 84) << summary.dump(2);
  EXPECT_EQ(errors, 0);
  EXPECT_GT(stored, 20);

  const cv::Mat truth = testing::RtabmapGroundTruth();
  std::map<int, int> frame_of_place;  // place id -> 1-based frame that created it
  int counted_merged = 0, loops = 0, true_loops = 0, with_loop_closure = 0;
  ASSERT_EQ(summary["results"].size(), 84u);
  for (const json& r : summary["results"]) {
    const int frame = r["sequence"].get<int>() + 1;
    EXPECT_EQ(r["name"], folder + "/" + std::to_string(frame) + ".jpg");
    if (r.contains("error")) continue;
    if (!r.contains("loop_closure")) {
      // Only frames that are not valid places skip the loop-closure update.
      EXPECT_FALSE(r["stored"].get<bool>()) << r.dump();
      EXPECT_TRUE(r.contains("rejection")) << r.dump();
      continue;
    }
    ++with_loop_closure;
    const json& lc = r["loop_closure"];
    for (const char* key :
         {"merged", "place_id", "loop_found", "loop_place_id", "loop_posterior", "best_place_id",
          "best_posterior", "candidates", "retrieved", "transferred"}) {
      EXPECT_TRUE(lc.contains(key)) << key;
    }
    if (lc["merged"].get<bool>()) {
      ++counted_merged;
      EXPECT_EQ(r["merged_into"], lc["place_id"]);
      EXPECT_FALSE(r["stored"].get<bool>()) << r.dump();
    } else {
      EXPECT_TRUE(r["stored"].get<bool>()) << r.dump();
      EXPECT_EQ(r["place_id"], lc["place_id"]);
      frame_of_place[lc["place_id"].get<int>()] = frame;
    }
    if (lc["loop_found"].get<bool>()) {
      ++loops;
      EXPECT_GE(lc["loop_posterior"].get<double>(), 0.12 - 1e-9) << r.dump();  // T_loop default
      const auto place = frame_of_place.find(lc["loop_place_id"].get<int>());
      ASSERT_NE(place, frame_of_place.end()) << "loop to an unknown place: " << r.dump();
      true_loops += truth.at<uint8_t>(frame - 1, place->second - 1) != 0;
    }
  }
  EXPECT_EQ(with_loop_closure, stored + merged);
  EXPECT_EQ(counted_merged, merged);
  EXPECT_EQ(summary["loops_found"], loops);
  // docs/rgbd.md: ORB closes 34 loops on this sequence, none false (standalone detector).
  EXPECT_GE(loops, 10);
  EXPECT_GE(true_loops * 10, loops * 8) << true_loops << " of " << loops << " loops are revisits";

  const json map = ParseJson(Cli({"maps", "show", "loop", "--json"}));
  EXPECT_EQ(map["stats"]["places"], std::to_string(stored));
  EXPECT_EQ(map["stats"]["loops_accepted"], std::to_string(loops));
  EXPECT_EQ(map["stats"]["streams"], "1");
  EXPECT_GT(std::stoll(map["stats"]["loop_working_memory"].get<std::string>()), 0);

  // Text mode: a line per frame, then the loop-closure summary line.
  ASSERT_EQ(Cli({"maps", "create", "text"}).code, 0);
  CliRun text = Cli({"ingest", "text", FramesDir(1, 6), "--loop-closure"});
  ASSERT_EQ(text.code, 0) << text.err;
  EXPECT_NE(text.out.find("1.jpg -> place 1; no loop"), std::string::npos) << text.out;
  EXPECT_NE(text.out.find("merged     "), std::string::npos) << text.out;
  EXPECT_NE(text.out.find("loop closure: 6 frames, "), std::string::npos) << text.out;
  EXPECT_NE(text.out.find(" loops found\n"), std::string::npos) << text.out;
}

// The loop-closure log (issue 32): slambook2's room ingested with depth, its camera and matches;
// `loops watch` prints each constraint, `loops export` writes g2o, TUM and CSV with the poses the
// log holds.
TEST_F(ClientTest, LoopsWatchAndExportG2oTumCsv) {
  ASSERT_EQ(Cli({"maps", "create", "room", "--features", "2000", "--verify", "exhaustive"}).code,
            0);
  CliRun ingested =
      Cli({"ingest", "room", SlambookDir() + "/color", "--depth", SlambookDir() + "/depth",
           "--camera", "518,519,325.5,253.5", "--matches", "--top-k", "4", "--agent-id", "robot"});
  ASSERT_EQ(ingested.code, 0) << ingested.err;

  CliRun watched = Cli({"loops", "watch", "room", "--json"});
  ASSERT_EQ(watched.code, 0) << watched.err;
  std::vector<json> log;
  std::istringstream lines(watched.out);
  for (std::string line; std::getline(lines, line);) log.push_back(json::parse(line));
  // 5 frames, each verified against the earlier ones of the small room.
  ASSERT_GE(log.size(), 4u);
  std::set<int> places;
  size_t metric = 0;
  for (size_t i = 0; i < log.size(); ++i) {
    EXPECT_EQ(log[i]["sequence"], std::to_string(i + 1));  // uint64 in proto JSON: a string
    places.insert(log[i]["place_id"].get<int>());
    places.insert(log[i]["query_place_id"].get<int>());
    if (log[i].contains("relative_pose") && log[i]["relative_pose"].value("metric", false))
      ++metric;
  }
  EXPECT_EQ(metric, log.size()) << "depth on both sides: every pose metric";
  CliRun text = Cli({"loops", "watch", "room", "--from", "2"});
  ASSERT_EQ(text.code, 0) << text.err;
  EXPECT_EQ(text.out.rfind("#2 match robot/", 0), 0u) << text.out;
  EXPECT_NE(text.out.find(" m, "), std::string::npos) << text.out;  // a metric pose printed
  EXPECT_TRUE(Cli({"loops", "watch", "room", "--inter-agent-only"}).out.empty());

  const std::string g2o = root_ + "/room.g2o";
  CliRun exported = Cli({"loops", "export", "room", "--format", "g2o", "--out", g2o});
  ASSERT_EQ(exported.code, 0) << exported.err;
  EXPECT_NE(exported.err.find("exported " + std::to_string(metric) + " of " +
                              std::to_string(log.size()) + " constraints"),
            std::string::npos)
      << exported.err;
  std::ifstream g2o_file(g2o);
  size_t vertices = 0, edges = 0;
  for (std::string line; std::getline(g2o_file, line);) {
    std::istringstream fields(line);
    std::string tag;
    fields >> tag;
    std::vector<double> values;
    for (double v; fields >> v;) values.push_back(v);
    if (tag == "VERTEX_SE3:QUAT") {
      ++vertices;
      EXPECT_EQ(values.size(), 8u) << line;  // id, x y z, qx qy qz qw
    } else if (tag == "EDGE_SE3:QUAT") {
      ASSERT_EQ(values.size(), 2u + 7u + 21u) << line;
      const json& c = log[edges++];
      EXPECT_EQ(int(values[0]), c["place_id"].get<int>());
      EXPECT_EQ(int(values[1]), c["query_place_id"].get<int>());
      EXPECT_NEAR(values[2], c["relative_pose"]["transform"][3].get<double>(), 1e-6);
      const double qnorm = std::sqrt(values[5] * values[5] + values[6] * values[6] +
                                     values[7] * values[7] + values[8] * values[8]);
      EXPECT_NEAR(qnorm, 1.0, 1e-6);
      EXPECT_GT(values[9], 0.0);  // information: positive on the diagonal
    } else {
      EXPECT_EQ(tag.rfind("#", 0), 0u) << line;
    }
  }
  EXPECT_EQ(vertices, places.size());
  EXPECT_EQ(edges, metric);

  CliRun tum = Cli({"loops", "export", "room", "--format", "tum"});
  ASSERT_EQ(tum.code, 0) << tum.err;
  EXPECT_EQ(size_t(std::count(tum.out.begin(), tum.out.end(), '\n')), 1 + metric);
  CliRun csv = Cli({"loops", "export", "room", "--format", "csv", "--agent", "robot"});
  ASSERT_EQ(csv.code, 0) << csv.err;
  EXPECT_EQ(size_t(std::count(csv.out.begin(), csv.out.end(), '\n')), 1 + log.size());
  EXPECT_EQ(csv.out.rfind("sequence,source,query_place_id,", 0), 0u);

  EXPECT_EQ(Cli({"loops", "export", "nowhere", "--format", "csv"}).code, 1);
  EXPECT_EQ(Cli({"loops", "export", "room", "--format", "kml"}).code, 2);
}

// rgbd-people (people walking in front of the camera) and the slambook2 room (16-bit PGM depth,
// intrinsics): every frame comes back with its Algorithm 1 state; a query shows its agent's.
TEST_F(ClientTest, IngestAndQueryWithDepth) {
  ASSERT_EQ(Cli({"maps", "create", "rgbd"}).code, 0);
  CliRun run = Cli({"ingest", "rgbd", RgbdPeopleDir() + "/image/test1", "--depth",
                    RgbdPeopleDir() + "/depth/test1", "--agent-id", "walker", "--json"});
  ASSERT_EQ(run.code, 0) << run.err;
  json summary = ParseJson(run);
  EXPECT_EQ(summary["frames"], 2);
  EXPECT_EQ(summary["errors"]["frames"], 0);
  ASSERT_TRUE(summary.contains("depth"));
  ASSERT_EQ(summary["results"].size(), 2u);
  for (size_t k = 0; k < 2; ++k) {
    const json& r = summary["results"][k];
    ASSERT_TRUE(r.contains("depth")) << r.dump();
    const json& d = r["depth"];
    EXPECT_EQ(d["frame"], k);
    EXPECT_GT(d["mean_depth_m"].get<double>(), 0.5);
    EXPECT_LT(d["mean_depth_m"].get<double>(), 12);
    EXPECT_GT(d["valid_fraction"].get<double>(), 0.3);
    EXPECT_EQ(d["warming_up"], true);  // 2 frames: Algorithm 1 warms up over the first 3
    EXPECT_EQ(r["counts"]["depth_removed"], 0);
  }

  // The slambook2 room: 16-bit PGM depth converted, intrinsics sent, human output.
  CliRun room =
      Cli({"ingest", "rgbd", SlambookDir() + "/color", "--depth", SlambookDir() + "/depth",
           "--intrinsics", "518,519,325.5,253.5", "--agent-id", "room"});
  ASSERT_EQ(room.code, 0) << room.err;
  EXPECT_NE(room.out.find("sent 5 of 5 frames"), std::string::npos) << room.out;
  EXPECT_NE(room.out.find("depth      0 descriptors removed by Algorithm 1 in 0 frames"),
            std::string::npos)
      << room.out;
  summary = ParseJson(Cli({"ingest", "rgbd", SlambookDir() + "/color", "--depth",
                           SlambookDir() + "/depth", "--agent-id", "room-2", "--json"}));
  ASSERT_EQ(summary["results"].size(), 5u);
  for (size_t k = 0; k < 5; ++k) {
    const json& r = summary["results"][k];
    ASSERT_TRUE(r.contains("depth")) << r.dump();
    EXPECT_EQ(r["depth"]["frame"], k);
    if (k >= 3) {
      EXPECT_EQ(r["depth"]["warming_up"], false) << r.dump();
      EXPECT_GT(r["depth"]["static_level_m"].get<double>(), 0) << r.dump();
    }
  }
  const json map = ParseJson(Cli({"maps", "show", "rgbd", "--json"}));
  EXPECT_EQ(map["stats"]["streams"], "3");  // walker, room, room-2

  // A query with depth: the depth is sent (a depth image of another aspect ratio is refused);
  // the agent's Algorithm 1 decision is applied without advancing its stream, and reported when
  // it applies (the server leaves QueryResponse.depth unset while the agent is not removing).
  const std::string image = RgbdPeopleDir() + "/image/test2/1534837743.228972.png";
  const std::string depth = RgbdPeopleDir() + "/depth/test2/1534837743.228972.png";
  CliRun queried_run =
      Cli({"query", "rgbd", image, "--depth", depth, "--agent-id", "walker", "--json"});
  ASSERT_EQ(queried_run.code, 0) << queried_run.err;
  const json queried = ParseJson(queried_run);
  EXPECT_EQ(queried["valid"], true);
  EXPECT_EQ(queried["counts"]["depth_removed"], 0);
  if (queried.contains("depth")) {
    EXPECT_GT(queried["depth"]["mean_depth_m"].get<double>(), 0.5);
    CliRun text = Cli({"query", "rgbd", image, "--depth", depth, "--agent-id", "walker"});
    ASSERT_EQ(text.code, 0) << text.err;
    EXPECT_NE(text.out.find("depth: frame "), std::string::npos) << text.out;
  }
  EXPECT_EQ(ParseJson(Cli({"maps", "show", "rgbd", "--json"}))["stats"]["streams"], "3");
  const std::string square = root_ + "/square.png";
  ASSERT_TRUE(cv::imwrite(square, cv::Mat(100, 100, CV_16UC1, cv::Scalar(1500))));
  CliRun refused = Cli({"query", "rgbd", image, "--depth", square});
  EXPECT_EQ(refused.code, 1);
  EXPECT_NE(refused.err.find("INVALID_ARGUMENT"), std::string::npos) << refused.err;
}

// A person walks up to the camera in the slambook2 room (rgbd::ComposePerson, the generated
// sequence of depth_filter_test: frames 0-14 empty, 15-59 the person from 5.0 m to 0.6 m, 60-74
// gone), written as colour PNGs and 16-bit millimetre depth PNGs: Algorithm 1 on the ingest
// stream switches removal on, and ingest shows and counts it.
TEST_F(ClientTest, IngestWithDepthShowsAlgorithmOneRemoval) {
  const rgbd::PersonSprite sprite = rgbd::LoadPersonSprite();
  ASSERT_FALSE(sprite.bgr.empty()) << "cannot load the person sprite";
  const auto rooms = rgbd::SlambookFrames();
  ASSERT_FALSE(rooms.empty());
  const cv::Mat room_bgr = cv::imread(rooms[0].image_path, cv::IMREAD_COLOR);
  auto room_metres = rgbd::ReadDepthMetres(rooms[0].depth_path);
  ASSERT_TRUE(room_metres.ok()) << room_metres.status().ToString();
  const std::string colour = root_ + "/walk/colour";
  const std::string depth = root_ + "/walk/depth";
  fs::create_directories(colour);
  fs::create_directories(depth);
  cv::RNG rng(7);
  constexpr int kFrames = 75, kEnter = 15, kLeave = 60;
  for (int t = 0; t < kFrames; ++t) {
    const double z = t >= kEnter && t < kLeave ? 5.0 - 0.1 * (t - kEnter) : 0;
    const rgbd::Composite frame =
        rgbd::ComposePerson(sprite, room_bgr, *room_metres, rgbd::SlambookIntrinsics(), z, &rng);
    cv::Mat millimetres;
    frame.metres.convertTo(millimetres, CV_16U, 1000.0);
    ASSERT_TRUE(cv::imwrite(colour + "/" + std::to_string(t) + ".png", frame.bgr));
    ASSERT_TRUE(cv::imwrite(depth + "/" + std::to_string(t) + ".png", millimetres));
  }
  ASSERT_EQ(Cli({"maps", "create", "walk"}).code, 0);

  const json summary =
      ParseJson(Cli({"ingest", "walk", colour, "--depth", depth, "--agent-id", "a", "--json"}));
  ASSERT_EQ(summary["results"].size(), size_t(kFrames));
  EXPECT_EQ(summary["errors"]["frames"], 0);
  int first_removing = -1, last_removing = -1;
  int64_t removed = 0, frames_removing = 0;
  for (const json& r : summary["results"]) {
    ASSERT_TRUE(r.contains("depth")) << r.dump();
    const int t = r["sequence"].get<int>();
    EXPECT_EQ(r["depth"]["frame"], t);
    if (r["depth"]["removing"].get<bool>()) {
      if (first_removing < 0) first_removing = t;
      last_removing = t;
      EXPECT_LT(r["depth"]["band_near_m"].get<double>(), r["depth"]["band_far_m"].get<double>());
    }
    const int64_t n = r["counts"]["depth_removed"].get<int64_t>();
    removed += n;
    frames_removing += n > 0;
  }
  // docs/rgbd.md: removal from frame 53 (the person at 1.2 m) until they leave at 60.
  EXPECT_GE(first_removing, kEnter + 7);
  EXPECT_LE(first_removing, kLeave - 1);
  EXPECT_LE(last_removing, kLeave);
  EXPECT_GT(removed, 0);
  EXPECT_EQ(summary["depth"]["descriptors_removed"], removed);
  EXPECT_EQ(summary["depth"]["frames_removing"], frames_removing);

  // Text: a line for each frame with removal, and the summary line.
  CliRun text = Cli({"ingest", "walk", colour, "--depth", depth, "--agent-id", "b"});
  ASSERT_EQ(text.code, 0) << text.err;
  EXPECT_NE(text.out.find(".png -> place "), std::string::npos) << text.out;
  EXPECT_NE(text.out.find("; depth -"), std::string::npos) << text.out;
  EXPECT_NE(text.out.find(" m)\n"), std::string::npos) << text.out;
  EXPECT_NE(text.out.find("  depth      " + std::to_string(removed) +
                          " descriptors removed by Algorithm 1 in " +
                          std::to_string(frames_removing) + " frames"),
            std::string::npos)
      << text.out;
}

// A server with the Debian SIFT vocabulary as "sift" beside the default ORB one.
class SiftClientTest : public ClientTest {
 protected:
  void Configure(server::ServerConfig* config) override {
    const std::string path = rgbd::SiftVocabularyPath();
    auto vocabulary = rgbd::LoadOrTrainSiftVocabulary(path);  // trained once if missing (~30 s)
    ASSERT_TRUE(vocabulary.ok()) << vocabulary.status().ToString();
    config->vocabularies["sift"] = path;
  }
};

TEST_F(SiftClientTest, SiftMapCreateIngestAndFeatures) {
  const json server = ParseJson(Cli({"info", "--json"}));
  std::map<std::string, std::string> kinds;
  for (const json& v : server["vocabularies"]) {
    kinds[v["name"].get<std::string>()] = v["feature_type"].get<std::string>();
  }
  EXPECT_EQ(kinds["default"], "FEATURE_TYPE_ORB");
  EXPECT_EQ(kinds["sift"], "FEATURE_TYPE_SIFT");
  CliRun info = Cli({"info"});
  EXPECT_NE(info.out.find("sift"), std::string::npos) << info.out;

  CliRun created = Cli({"maps", "create", "s", "--vocabulary", "sift", "--feature-type", "sift",
                        "--sift-features", "500"});
  ASSERT_EQ(created.code, 0) << created.err;
  EXPECT_NE(created.out.find("max_features 500, octave_layers"), std::string::npos) << created.out;
  const json config = ParseJson(Cli({"maps", "show", "s", "--json"}))["config"];
  EXPECT_EQ(config["vocabulary"], "sift");
  EXPECT_EQ(config["feature_type"], "FEATURE_TYPE_SIFT");
  EXPECT_EQ(config["sift"]["max_features"], 500);
  // The kind follows the vocabulary when not given; a mismatch is refused.
  ASSERT_EQ(Cli({"maps", "create", "s2", "--vocabulary", "sift"}).code, 0);
  EXPECT_EQ(ParseJson(Cli({"maps", "show", "s2", "--json"}))["config"]["feature_type"],
            "FEATURE_TYPE_SIFT");
  CliRun mismatch = Cli({"maps", "create", "s3", "--vocabulary", "sift", "--feature-type", "orb"});
  EXPECT_EQ(mismatch.code, 1);
  EXPECT_NE(mismatch.err.find("INVALID_ARGUMENT"), std::string::npos) << mismatch.err;

  // Images in, SIFT extracted by the server; a stored place's SIFT features out.
  const json summary = ParseJson(Cli({"ingest", "s", SlambookDir() + "/color", "--json"}));
  EXPECT_EQ(summary["errors"]["frames"], 0);
  ASSERT_GT(summary["stored"].get<int>(), 0) << summary.dump(2);
  int id = 0;
  for (const json& r : summary["results"]) {
    if (r["stored"].get<bool>() && id == 0) id = r["place_id"].get<int>();
  }
  CliRun got = Cli({"place", "get", "s", std::to_string(id), "--features"});
  ASSERT_EQ(got.code, 0) << got.err;
  EXPECT_NE(got.out.find("static SIFT keypoints"), std::string::npos) << got.out;
  EXPECT_NE(got.out.find("keypoint 0"), std::string::npos) << got.out;
  const json place =
      ParseJson(Cli({"place", "get", "s", std::to_string(id), "--features", "--json"}));
  const json& sift = place["sift_features"];
  ASSERT_FALSE(sift["keypoints"].empty()) << place.dump().substr(0, 2000);
  EXPECT_LE(sift["keypoints"].size(), 500u);
  EXPECT_EQ(sift["image_width"], 640);
  const json queried = ParseJson(Cli({"query", "s", SlambookDir() + "/color/3.png", "--json"}));
  ASSERT_FALSE(queried["matches"].empty());

  // The load tester's features mode extracts ORB: refused for a SIFT map.
  CliRun load = Cli({"load", SlambookDir() + "/color", "--map", "s", "--mode", "features"});
  EXPECT_EQ(load.code, 2);
  EXPECT_NE(load.err.find("SIFT map"), std::string::npos) << load.err;
}

// ---- helpers ------------------------------------------------------------------------------------

TEST(ClientFormatTest, NaturalOrderAndPercentiles) {
  std::vector<std::string> names = {"10.jpg",      "2.jpg", "1.jpg",   "frame_011.png",
                                    "frame_9.png", "b.jpg", "a10.jpg", "a9.jpg"};
  std::sort(names.begin(), names.end(), NaturalLess);
  EXPECT_EQ(names, (std::vector<std::string>{"1.jpg", "2.jpg", "10.jpg", "a9.jpg", "a10.jpg",
                                             "b.jpg", "frame_9.png", "frame_011.png"}));
  std::vector<double> samples;
  for (int i = 100; i >= 1; --i) samples.push_back(i);
  const client::LatencySummary s = client::Summarize(samples);
  EXPECT_EQ(s.count, 100u);
  EXPECT_EQ(s.p50, 50);
  EXPECT_EQ(s.p90, 90);
  EXPECT_EQ(s.p99, 99);
  EXPECT_EQ(s.max, 100);
  EXPECT_DOUBLE_EQ(s.mean, 50.5);
  EXPECT_EQ(client::Summarize({}).count, 0u);
  bool unix_socket = false;
  EXPECT_EQ(client::TargetHost("[::1]:5", &unix_socket), "::1");
  EXPECT_EQ(client::TargetHost("dns:///example.org:443", &unix_socket), "example.org");
  EXPECT_EQ(client::TargetHost("host", &unix_socket), "host");
  EXPECT_EQ(client::TargetHost("unix:/x", &unix_socket), "");
  EXPECT_TRUE(unix_socket);
}

// Usage errors exit 2 (as placedb-server and placedb-load), and ranges are ones a reader can
// read: no 309-digit bounds (CLI11's NonNegativeNumber / PositiveNumber print DBL_MAX).
TEST(CliUsage, RangesAreSaneAndUsageErrorsExit2) {
  const std::regex long_number("[0-9]{20,}");
  const std::vector<std::vector<std::string>> lines = {
      {"ingest", "m", "/nonexistent", "--rate", "-1"},
      {"ingest", "m", "/nonexistent", "--depth-scale", "0"},
      {"ingest", "m", "/nonexistent", "--video-every", "0"},
      {"query", "m", "x.jpg", "--depth-scale", "-1"},
      {"--timeout", "-1", "health"},
      {"load", "/nonexistent", "--duration", "-1"},
      {"load", "/nonexistent", "--total-rate", "-1"},
      {"maps", "create", "m", "--depth-threshold", "0"},
      {"maps", "create", "m", "--rehearsal-threshold", "-1"},
      {"maps", "create", "m", "--wm-time-budget-ms", "-1"},
      {"--bogus"}};
  for (const std::vector<std::string>& args : lines) {
    const CliRun run = RunPlacedb(args);
    EXPECT_EQ(run.code, 2) << args[args.size() - 2] << ": " << run.err;
    EXPECT_FALSE(std::regex_search(run.err, long_number)) << run.err;
  }
  EXPECT_NE(RunPlacedb(lines[0]).err.find("--rate: Value -1 not in range 0"), std::string::npos)
      << RunPlacedb(lines[0]).err;
  // The --box-source default as CreateMap applies it.
  const CliRun help = RunPlacedb({"maps", "create", "--help"});
  EXPECT_NE(help.out.find("default: server when the server has a detector"), std::string::npos)
      << help.out;
}

}  // namespace
}  // namespace placedb
