// The `placedb` CLI and load tester against a real server: an in-process placedb_server on a
// loopback port with a real RocksDB in a temp directory, the default vocabulary, real frames
// (RTAB-Map loop). Every command runs through RunCli() (the binary's entry function) with string
// streams, checking outputs and exit codes.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>
#include <sstream>

#include "client/cli.h"
#include "client/format.h"
#include "client/frame_source.h"
#include "client/loopback.h"
#include "server/config.h"
#include "server/server.h"
#include "tests/test_support.h"

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

// A port on which nothing listens (bound, then released).
int ClosedPort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  EXPECT_EQ(bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
  socklen_t length = sizeof address;
  getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length);
  close(fd);
  return ntohs(address.sin_port);
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
    config.data_dir = root_ + "/data";
    config.threads = 2;
    config.vocabularies = {{"default", testing::DefaultVocabularyPath()}};
    config.shutdown_deadline_s = 10;
    server::ServerDeps deps;
    deps.vocabularies.emplace("default", vocabulary);
    auto started = server::Server::Start(config, deps);
    ASSERT_TRUE(started.ok()) << started.status().ToString();
    server_ = std::move(started).value();
    address_ = "127.0.0.1:" + std::to_string(server_->port());
  }

  void TearDown() override { server_.reset(); }

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

// The human summary, per-frame matches, progress lines when stderr is not a terminal, a list
// file and a video as sources, and a stream refused for an unknown map.
TEST_F(ClientTest, IngestSummaryListsAndVideos) {
  ASSERT_EQ(Cli({"maps", "create", "m"}).code, 0);
  CliRun run = Cli({"ingest", "m", FramesDir(1, 4), "--matches", "--agent-id", "robot"});
  ASSERT_EQ(run.code, 0) << run.err;
  for (const char* text :
       {"ingested 4 of 4 frames into 'm' with 1 agent", "stored", "rejected", "errors     0",
        "latency", "p50", "p99", "1.jpg -> place", "4.jpg -> place"}) {
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

  const std::string nowhere = "127.0.0.1:" + std::to_string(ClosedPort());
  CliRun unreachable = RunPlacedb({"--address", nowhere, "--timeout", "5", "health"});
  EXPECT_EQ(unreachable.code, 2);
  EXPECT_EQ(unreachable.out, "UNREACHABLE\n");
  EXPECT_NE(unreachable.err.find("UNAVAILABLE"), std::string::npos) << unreachable.err;
  const json down = ParseJson(RunPlacedb({"--address", nowhere, "--json", "health"}));
  EXPECT_EQ(down["status"], "UNREACHABLE");
  // Other commands against nothing: an RPC error.
  EXPECT_EQ(RunPlacedb({"--address", nowhere, "maps", "list"}).code, 1);
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

// ---- helpers ------------------------------------------------------------------------------------

TEST(ClientFormatTest, NaturalOrderAndPercentiles) {
  std::vector<std::string> names = {"10.jpg",      "2.jpg", "1.jpg",   "frame_011.png",
                                    "frame_9.png", "b.jpg", "a10.jpg", "a9.jpg"};
  std::sort(names.begin(), names.end(), client::NaturalLess);
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

}  // namespace
}  // namespace placedb
