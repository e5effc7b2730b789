// The gRPC service end to end: an in-process server on a loopback port, a real RocksDB in a temp
// directory, the default vocabulary, real frames (RTAB-Map loop, CamVid) sent as JPEG bytes.
#include "server/server.h"

#include <arpa/inet.h>
#include <grpc/grpc.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <fstream>
#include <future>
#include <map>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>
#include <thread>

#include "core/detect/detector.h"
#include "core/features/sift_features.h"
#include "core/storage/map_store.h"
#include "proto/placedb.grpc.pb.h"
#include "server/config.h"
#include "server/convert.h"
#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace placedb {
namespace {

namespace v1 = ::placedb::v1;
using server::Server;
using server::ServerConfig;
using server::ServerDeps;

// gRPC stays initialised for the whole process. Otherwise every test's teardown runs gRPC's
// library shutdown, which in a process holding both clients and a server can wait ~10 s for an
// executor thread's poll to time out (not something the server binary does: it exits in ms).
const bool kGrpcInitialised = [] {
  grpc_init();
  return true;
}();

// ---- Helpers ------------------------------------------------------------------------------------

// The checkout (this file is tests/server_test.cc in it).
std::string SourceDir() {
  const std::string file = __FILE__;
  return file.substr(0, file.rfind("/tests/"));
}

std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  EXPECT_TRUE(in) << "cannot read " << path;
  std::stringstream bytes;
  bytes << in.rdbuf();
  return bytes.str();
}

std::string EncodePng(const cv::Mat& image) {
  std::vector<uint8_t> bytes;
  EXPECT_TRUE(cv::imencode(".png", image, bytes));
  return std::string(bytes.begin(), bytes.end());
}

v1::Observation JpegObservation(const std::string& path, const std::string& agent,
                                uint64_t sequence) {
  v1::Observation observation;
  observation.set_agent_id(agent);
  observation.set_sequence(sequence);
  observation.set_timestamp_ns(int64_t(sequence) * 100'000'000);
  observation.mutable_encoded_image()->set_data(ReadBytes(path));
  return observation;
}

v1::Observation RtabmapObservation(int frame, const std::string& agent) {
  v1::Observation observation =
      JpegObservation(testing::RtabmapFramePath(frame), agent, uint64_t(frame));
  if (frame % 5 == 0) {
    v1::Pose* pose = observation.mutable_pose();
    pose->set_x(frame);
    pose->set_y(2);
    pose->set_qw(1);
  }
  return observation;
}

// Features of `observation`'s JPEG exactly as the server computes them for a default map.
v1::Features FeaturesOf(const v1::Observation& observation) {
  const std::string& bytes = observation.encoded_image().data();
  cv::Mat gray = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())),
                              cv::IMREAD_GRAYSCALE);
  auto features = ExtractOrb(gray, OrbConfig{});
  EXPECT_TRUE(features.ok()) << features.status().ToString();
  v1::Features out;
  server::FeaturesToProto(*features, &out);
  return out;
}

struct IngestOutcome {
  std::vector<v1::IngestResponse> responses;
  grpc::Status status;
};

// One Ingest stream: writes the header and every observation from one thread while reading
// responses on this one, as a real agent does.
IngestOutcome IngestWithHeader(v1::PlaceDb::Stub* stub, const v1::IngestHeader& header,
                               const std::vector<v1::Observation>& observations) {
  grpc::ClientContext context;
  auto stream = stub->Ingest(&context);
  std::thread writer([&] {
    v1::IngestRequest first;
    *first.mutable_header() = header;
    if (!stream->Write(first)) return;
    for (const v1::Observation& observation : observations) {
      v1::IngestRequest request;
      *request.mutable_observation() = observation;
      if (!stream->Write(request)) return;
    }
    stream->WritesDone();
  });
  IngestOutcome out;
  v1::IngestResponse response;
  while (stream->Read(&response)) out.responses.push_back(response);
  writer.join();
  out.status = stream->Finish();
  return out;
}

IngestOutcome IngestAll(v1::PlaceDb::Stub* stub, const std::string& map,
                        const std::vector<v1::Observation>& observations,
                        const v1::MatchOptions* matches = nullptr) {
  v1::IngestHeader header;
  header.set_map(map);
  if (matches) *header.mutable_matches() = *matches;
  return IngestWithHeader(stub, header, observations);
}

// ---- Metrics scraping ---------------------------------------------------------------------------

std::string HttpGet(int port, const std::string& path) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  EXPECT_GE(fd, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(uint16_t(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
    ADD_FAILURE() << "cannot connect to the metrics port " << port;
    close(fd);
    return "";
  }
  const std::string request = "GET " + path + " HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n";
  EXPECT_EQ(send(fd, request.data(), request.size(), 0), ssize_t(request.size()));
  std::string reply;
  char buffer[4096];
  ssize_t n;
  while ((n = recv(fd, buffer, sizeof buffer, 0)) > 0) reply.append(buffer, size_t(n));
  close(fd);
  return reply;
}

// Prometheus text format -> "name{k=v,...}" (labels sorted) -> value.
std::map<std::string, double> ParseMetrics(const std::string& reply) {
  std::map<std::string, double> out;
  const auto body_start = reply.find("\r\n\r\n");
  EXPECT_NE(body_start, std::string::npos) << reply;
  EXPECT_NE(reply.find(" 200 "), std::string::npos) << reply.substr(0, 200);
  std::istringstream body(reply.substr(body_start + 4));
  std::string line;
  while (std::getline(body, line)) {
    if (line.empty() || line[0] == '#') continue;
    std::string name = line;
    std::map<std::string, std::string> labels;
    std::string rest;
    if (const auto brace = line.find('{'); brace != std::string::npos) {
      name = line.substr(0, brace);
      const auto end = line.find('}', brace);
      std::string inner = line.substr(brace + 1, end - brace - 1);
      size_t i = 0;
      while (i < inner.size()) {
        const auto eq = inner.find('=', i);
        const auto q1 = inner.find('"', eq);
        const auto q2 = inner.find('"', q1 + 1);
        labels[inner.substr(i, eq - i)] = inner.substr(q1 + 1, q2 - q1 - 1);
        i = q2 + 1;
        if (i < inner.size() && inner[i] == ',') ++i;
      }
      rest = line.substr(end + 1);
    } else {
      const auto space = line.find(' ');
      name = line.substr(0, space);
      rest = line.substr(space);
    }
    std::string key = name + "{";
    for (const auto& [k, v] : labels) key += k + "=" + v + ",";
    key += "}";
    out[key] = std::stod(rest);
  }
  return out;
}

double MetricValue(const std::map<std::string, double>& metrics, const std::string& name,
                   const std::map<std::string, std::string>& labels = {}) {
  std::string key = name + "{";
  for (const auto& [k, v] : labels) key += k + "=" + v + ",";
  key += "}";
  auto it = metrics.find(key);
  return it == metrics.end() ? std::nan("") : it->second;
}

// ---- Fixture ------------------------------------------------------------------------------------

class ServerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    vocabulary_ = testing::DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
    root_ = testing::MakeTempDir("placedb-server");
    spdlog::set_level(spdlog::level::warn);
  }

  void TearDown() override { StopServer(); }

  ServerConfig Config() const {
    ServerConfig config;
    config.listen = "127.0.0.1:0";
    config.metrics_listen = "";  // on only where scraped: stopping civetweb takes up to 2 s
    config.data_dir = root_ + "/data";
    config.threads = 2;
    config.vocabularies = {{"default", testing::DefaultVocabularyPath()}};
    config.shutdown_deadline_s = 10;
    config.limits.max_image_pixels = 2'000'000;
    config.limits.max_message_bytes = 4 << 20;
    config.limits.max_boxes_per_frame = 16;
    config.limits.max_descriptors_per_frame = 2000;
    return config;
  }

  void StartServer(const ServerConfig& config, ServerDeps deps = {}) {
    deps.vocabularies.emplace("default", vocabulary_);
    auto started = Server::Start(config, deps);
    ASSERT_TRUE(started.ok()) << started.status().ToString();
    server_ = std::move(started).value();
    channel_ = grpc::CreateChannel("127.0.0.1:" + std::to_string(server_->port()),
                                   grpc::InsecureChannelCredentials());
    stub_ = v1::PlaceDb::NewStub(channel_);
  }

  void StopServer() {
    stub_.reset();
    channel_.reset();
    server_.reset();
  }

  v1::MapDescription CreateMap(const std::string& name, const v1::MapConfig& config = {}) {
    grpc::ClientContext context;
    v1::CreateMapRequest request;
    request.set_name(name);
    *request.mutable_config() = config;
    v1::MapDescription description;
    const grpc::Status status = stub_->CreateMap(&context, request, &description);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return description;
  }

  grpc::Status CreateMapStatus(const std::string& name, const v1::MapConfig& config = {}) {
    grpc::ClientContext context;
    v1::CreateMapRequest request;
    request.set_name(name);
    *request.mutable_config() = config;
    v1::MapDescription description;
    return stub_->CreateMap(&context, request, &description);
  }

  v1::MapStats Stats(const std::string& map) {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name(map);
    v1::MapDescription description;
    const grpc::Status status = stub_->GetMap(&context, request, &description);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return description.stats();
  }

  grpc::Status Query(const std::string& map, const v1::Observation& observation,
                     v1::QueryResponse* response, size_t top_k = 10) {
    grpc::ClientContext context;
    v1::QueryRequest request;
    request.set_map(map);
    *request.mutable_observation() = observation;
    request.mutable_options()->set_top_k(uint32_t(top_k));
    return stub_->Query(&context, request, response);
  }

  std::map<std::string, double> Scrape() {
    return ParseMetrics(HttpGet(server_->metrics_port(), "/metrics"));
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
  std::unique_ptr<Server> server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::PlaceDb::Stub> stub_;
};

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
  EXPECT_NEAR(again.matches(0).score(), 1.0, 1e-5);
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

// Every bad input gets its code, names what is wrong, and changes nothing stored.
TEST_F(ServerTest, BadInputGetsItsCodeAndLeavesTheMapIntact) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  {
    const IngestOutcome good =
        IngestAll(stub_.get(), "m", {RtabmapObservation(1, "a"), RtabmapObservation(2, "a")});
    ASSERT_TRUE(good.status.ok());
  }
  const v1::MapStats before = Stats("m");
  ASSERT_EQ(before.places(), 2u);

  const v1::Observation good = RtabmapObservation(7, "a");
  const v1::Features features = FeaturesOf(good);
  ASSERT_GT(features.keypoints_size(), 10);
  struct Case {
    std::string name;
    v1::Observation observation;
    grpc::StatusCode code;
    std::string message;  // must appear in the error message
  };
  std::vector<Case> cases;
  auto add = [&](std::string name, grpc::StatusCode code, std::string message,
                 const std::function<void(v1::Observation*)>& edit) {
    v1::Observation observation = good;
    edit(&observation);
    cases.push_back({std::move(name), std::move(observation), code, std::move(message)});
  };
  add("garbage image bytes", grpc::StatusCode::INVALID_ARGUMENT, "observation.encoded_image.data",
      [](v1::Observation* o) { o->mutable_encoded_image()->set_data("definitely not an image"); });
  add("damaged JPEG", grpc::StatusCode::INVALID_ARGUMENT, "JPEG", [](v1::Observation* o) {
    o->mutable_encoded_image()->set_data(std::string("\xFF\xD8\xFF\xE0\x00\x10", 6) +
                                         std::string(200, '\x11'));
  });
  add("no frame", grpc::StatusCode::INVALID_ARGUMENT, "encoded_image, raw_image, features or",
      [](v1::Observation* o) { o->clear_frame(); });
  add("keypoint outside the image", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.features.keypoints[3].x: 700 lies outside the 512x384 image",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_keypoints(3)->set_x(700);
      });
  add("descriptor bytes not a multiple of 32", grpc::StatusCode::INVALID_ARGUMENT, "multiple of 32",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_descriptors()->pop_back();
      });
  add("mismatched counts", grpc::StatusCode::INVALID_ARGUMENT, "descriptors for",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_keypoints()->RemoveLast();
      });
  add("non-finite keypoint", grpc::StatusCode::INVALID_ARGUMENT, "keypoints[0].size",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_keypoints(0)->set_size(std::nanf(""));
      });
  add("too many descriptors", grpc::StatusCode::RESOURCE_EXHAUSTED, "max_descriptors_per_frame",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        while (o->features().keypoints_size() <= 2000) {
          *o->mutable_features()->add_keypoints() = features.keypoints(0);
          o->mutable_features()->mutable_descriptors()->append(
              features.descriptors().substr(0, 32));
        }
      });
  add("too many boxes", grpc::StatusCode::RESOURCE_EXHAUSTED, "max_boxes_per_frame",
      [](v1::Observation* o) {
        for (int i = 0; i < 17; ++i) {
          v1::Box* box = o->add_boxes();
          box->set_class_id(0);
          box->set_confidence(0.5f);
          box->mutable_rect()->set_width(10);
          box->mutable_rect()->set_height(10);
        }
      });
  add("too many pixels", grpc::StatusCode::RESOURCE_EXHAUSTED, "max_image_pixels",
      [](v1::Observation* o) {
        o->mutable_encoded_image()->set_data(EncodePng(cv::Mat::zeros(1500, 1500, CV_8U)));
      });
  add("unknown box class", grpc::StatusCode::INVALID_ARGUMENT, "observation.boxes[0].class_name",
      [](v1::Observation* o) {
        v1::Box* box = o->add_boxes();
        box->set_class_name("unicorn");
        box->set_confidence(0.5f);
        box->mutable_rect()->set_width(10);
      });
  add("box confidence out of range", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.boxes[0].confidence", [](v1::Observation* o) {
        v1::Box* box = o->add_boxes();
        box->set_class_id(2);
        box->set_confidence(1.5f);
        box->mutable_rect()->set_width(10);
      });
  add("raw pixels of the wrong size", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.raw_image.data", [](v1::Observation* o) {
        v1::RawImage* raw = o->mutable_raw_image();
        raw->set_width(64);
        raw->set_height(48);
        raw->set_format(v1::PIXEL_FORMAT_BGR8);
        raw->set_data(std::string(64 * 48, '\0'));
      });
  add("mask of the wrong size", grpc::StatusCode::INVALID_ARGUMENT, "observation.dynamic_mask_png",
      [](v1::Observation* o) {
        o->set_dynamic_mask_png(EncodePng(cv::Mat::zeros(10, 10, CV_8U)));
      });
  add("depth of another aspect ratio", grpc::StatusCode::INVALID_ARGUMENT, "observation.depth",
      [](v1::Observation* o) {
        o->mutable_depth()->set_png16(EncodePng(cv::Mat::zeros(64, 64, CV_16U)));
      });
  add("depth intrinsics outside the image", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.depth.intrinsics.cx", [](v1::Observation* o) {
        o->mutable_depth()->set_png16(EncodePng(cv::Mat::zeros(48, 64, CV_16U)));
        v1::Intrinsics* k = o->mutable_depth()->mutable_intrinsics();
        k->set_fx(500);
        k->set_fy(500);
        k->set_cx(900);
        k->set_cy(200);
      });
  add("SIFT features on an ORB map", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.sift_features", [](v1::Observation* o) {
        v1::SiftFeatures* sift = o->mutable_sift_features();
        sift->set_image_width(512);
        sift->set_image_height(384);
      });
  add("8-bit depth", grpc::StatusCode::INVALID_ARGUMENT, "16-bit", [](v1::Observation* o) {
    o->mutable_depth()->set_png16(EncodePng(cv::Mat::zeros(480, 640, CV_8U)));
  });
  add("non-finite pose", grpc::StatusCode::INVALID_ARGUMENT, "observation.pose",
      [](v1::Observation* o) { o->mutable_pose()->set_x(std::nan("")); });

  // Each case through Query and through an Ingest stream of bad frames only.
  std::vector<v1::Observation> bad;
  for (const Case& c : cases) {
    v1::QueryResponse response;
    const grpc::Status status = Query("m", c.observation, &response);
    EXPECT_EQ(status.error_code(), c.code) << c.name << ": " << status.error_message();
    EXPECT_NE(status.error_message().find(c.message), std::string::npos)
        << c.name << ": '" << status.error_message() << "' does not mention " << c.message;
    bad.push_back(c.observation);
  }
  const IngestOutcome ingested = IngestAll(stub_.get(), "m", bad);
  EXPECT_TRUE(ingested.status.ok())
      << "a bad frame must not end the stream: " << ingested.status.error_message();
  ASSERT_EQ(ingested.responses.size(), cases.size());
  for (size_t i = 0; i < cases.size(); ++i) {
    const v1::IngestResponse& response = ingested.responses[i];
    EXPECT_FALSE(response.stored()) << cases[i].name;
    EXPECT_EQ(response.error().code(), int(cases[i].code)) << cases[i].name;
    EXPECT_NE(response.error().message().find(cases[i].message), std::string::npos)
        << cases[i].name << ": " << response.error().message();
  }

  // Tiny images are answered (no corners: not a valid place), not refused; a side of 1 pixel is
  // refused (OpenCV's ORB cannot take it).
  v1::QueryResponse response;
  {
    v1::Observation dot;
    dot.mutable_encoded_image()->set_data(EncodePng(cv::Mat(1, 7, CV_8U, cv::Scalar(5))));
    const grpc::Status status = Query("m", dot, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(status.error_message().find("too small"), std::string::npos);
  }
  for (const auto& [w, h] : {std::pair{2, 2}, std::pair{8, 6}, std::pair{40, 3}}) {
    v1::Observation tiny;
    tiny.mutable_encoded_image()->set_data(
        EncodePng(cv::Mat(h, w, CV_8UC3, cv::Scalar(9, 99, 199))));
    ASSERT_TRUE(Query("m", tiny, &response).ok()) << w << "x" << h;
    EXPECT_FALSE(response.valid());
    EXPECT_NE(response.rejection().find("placeThreshold"), std::string::npos);
    v1::Observation raw;
    raw.mutable_raw_image()->set_width(uint32_t(w));
    raw.mutable_raw_image()->set_height(uint32_t(h));
    raw.mutable_raw_image()->set_format(v1::PIXEL_FORMAT_RGB8);
    raw.mutable_raw_image()->set_data(std::string(size_t(w * h * 3), '\x40'));
    ASSERT_TRUE(Query("m", raw, &response).ok()) << w << "x" << h;
  }

  // Maps, names and the stream protocol.
  EXPECT_EQ(Query("nowhere", good, &response).error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(IngestAll(stub_.get(), "nowhere", {good}).status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(CreateMapStatus("m").error_code(), grpc::StatusCode::ALREADY_EXISTS);
  const grpc::Status bad_name = CreateMapStatus("../evil");
  EXPECT_EQ(bad_name.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(bad_name.error_message().rfind("name:", 0), 0u) << bad_name.error_message();
  EXPECT_EQ(Query("../evil", good, &response).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  v1::MapConfig unknown_vocabulary;
  unknown_vocabulary.set_vocabulary("klingon");
  const grpc::Status vocabulary = CreateMapStatus("x", unknown_vocabulary);
  EXPECT_EQ(vocabulary.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(vocabulary.error_message().find("config.vocabulary"), std::string::npos);
  v1::MapConfig bad_orb;
  bad_orb.mutable_orb()->set_max_features(-3);
  const grpc::Status orb = CreateMapStatus("x", bad_orb);
  EXPECT_EQ(orb.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(orb.error_message().find("config.orb.max_features"), std::string::npos);
  v1::MapConfig too_many_features;
  too_many_features.mutable_orb()->set_max_features(5000);
  EXPECT_EQ(CreateMapStatus("x", too_many_features).error_code(),
            grpc::StatusCode::RESOURCE_EXHAUSTED);
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);
  EXPECT_EQ(CreateMapStatus("x", server_boxes).error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  {
    grpc::ClientContext context;
    auto stream = stub_->Ingest(&context);
    v1::IngestRequest request;
    *request.mutable_observation() = good;  // no header first
    stream->Write(request);
    stream->WritesDone();
    v1::IngestResponse ignored;
    while (stream->Read(&ignored)) {
    }
    EXPECT_EQ(stream->Finish().error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  }
  {
    grpc::ClientContext context;  // a message over limits.max_message_bytes
    v1::QueryRequest request;
    request.set_map("m");
    request.mutable_observation()->mutable_encoded_image()->set_data(std::string(5 << 20, 'x'));
    EXPECT_EQ(stub_->Query(&context, request, &response).error_code(),
              grpc::StatusCode::RESOURCE_EXHAUSTED);
  }
  {
    grpc::ClientContext context;
    v1::GetPlaceRequest request;
    request.set_map("m");
    request.set_place_id(999);
    v1::Place place;
    EXPECT_EQ(stub_->GetPlace(&context, request, &place).error_code(), grpc::StatusCode::NOT_FOUND);
  }
  {
    grpc::ClientContext context;
    v1::DeleteMapRequest request;
    request.set_name("nowhere");
    v1::DeleteMapResponse deleted;
    EXPECT_EQ(stub_->DeleteMap(&context, request, &deleted).error_code(),
              grpc::StatusCode::NOT_FOUND);
  }

  const v1::MapStats after = Stats("m");
  EXPECT_EQ(after.places(), before.places());
  EXPECT_EQ(after.descriptors_kept(), before.descriptors_kept());
  EXPECT_EQ(after.descriptors_dropped(), before.descriptors_dropped());
  EXPECT_EQ(after.invalid_rejected(), before.invalid_rejected());
  grpc::ClientContext context;
  v1::ListMapsResponse maps;
  ASSERT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
  ASSERT_EQ(maps.maps_size(), 1) << "a refused CreateMap left a map behind";
}

// Streams are open and busy when the server shuts down: every place it acknowledged is on disk.
TEST_F(ServerTest, ShutdownWithOpenStreamsLosesNoAcknowledgedPlace) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 20; ++frame) frames.push_back(RtabmapObservation(frame, "a"));

  std::mutex mutex;
  std::condition_variable acked_cv;
  std::vector<uint32_t> acked;
  std::atomic<bool> stop{false};
  std::vector<grpc::Status> finals(2);
  std::vector<std::thread> agents;
  for (int agent = 0; agent < 2; ++agent) {
    agents.emplace_back([&, agent] {
      grpc::ClientContext context;
      auto stream = stub_->Ingest(&context);
      std::thread writer([&] {
        v1::IngestRequest header;
        header.mutable_header()->set_map("m");
        if (!stream->Write(header)) return;
        for (size_t i = size_t(agent); !stop; ++i) {
          v1::IngestRequest request;
          *request.mutable_observation() = frames[i % frames.size()];
          if (!stream->Write(request)) return;
        }
        stream->WritesDone();
      });
      v1::IngestResponse response;
      while (stream->Read(&response)) {
        if (response.stored()) {
          std::lock_guard lock(mutex);
          acked.push_back(response.place_id());
          acked_cv.notify_all();
        }
      }
      stop = true;
      writer.join();
      finals[size_t(agent)] = stream->Finish();
    });
  }
  // Also an idle stream (header only) and one that never sent its header: neither may hold up
  // the shutdown until its deadline.
  grpc::ClientContext idle_context, silent_context;
  auto idle = stub_->Ingest(&idle_context);
  v1::IngestRequest header;
  header.mutable_header()->set_map("m");
  ASSERT_TRUE(idle->Write(header));
  auto silent = stub_->Ingest(&silent_context);
  {
    std::unique_lock lock(mutex);
    ASSERT_TRUE(
        acked_cv.wait_for(lock, std::chrono::seconds(60), [&] { return acked.size() >= 12; }));
  }
  const auto shutdown_started = std::chrono::steady_clock::now();
  server_->Shutdown();  // streams still open and sending
  const double shutdown_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - shutdown_started).count();
  EXPECT_LT(shutdown_s, 5.0) << "shutdown waited for idle streams (deadline is 10 s)";
  for (auto& agent : agents) agent.join();
  v1::IngestResponse ignored;
  EXPECT_FALSE(idle->Read(&ignored));
  EXPECT_FALSE(idle->Finish().ok());
  EXPECT_FALSE(silent->Read(&ignored));
  EXPECT_FALSE(silent->Finish().ok());
  for (const grpc::Status& status : finals) {
    EXPECT_TRUE(status.error_code() == grpc::StatusCode::UNAVAILABLE ||
                status.error_code() == grpc::StatusCode::CANCELLED)
        << int(status.error_code()) << " " << status.error_message();
  }
  StopServer();

  auto directory = DataDirectory::Open(root_ + "/data");
  ASSERT_TRUE(directory.ok()) << directory.status().ToString();
  auto map = (*directory)->OpenMap("m", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  std::lock_guard lock(mutex);
  EXPECT_GE((*map)->Stats().database.places, acked.size());
  for (uint32_t id : acked) EXPECT_TRUE((*map)->GetPlace(id).ok()) << "acknowledged place " << id;
  std::printf(
      "[server] shutdown with 2 busy streams in %.3f s: %zu acknowledged places, %zu on "
      "disk\n",
      shutdown_s, acked.size(), (*map)->Stats().database.places);
}

// A detector that blocks until released: holds a frame in the middle of the pipeline.
class GateDetector final : public Detector {
 public:
  Result<std::vector<DynamicBox>> Detect(const cv::Mat& image) const override {
    std::unique_lock lock(mutex_);
    entered_ = true;
    changed_.notify_all();
    changed_.wait(lock, [&] { return open_; });
    return std::vector<DynamicBox>{
        {0, 0.9f, cv::Rect2f(0, 0, image.cols / 4.0f, image.rows / 4.0f)}};
  }
  void WaitEntered() const {
    std::unique_lock lock(mutex_);
    changed_.wait(lock, [&] { return entered_; });
  }
  void Open() const {
    std::lock_guard lock(mutex_);
    open_ = true;
    changed_.notify_all();
  }
  std::string model_name() const override { return "gate"; }
  std::string Describe() const override { return "gate (test)"; }
  int input_size() const override { return 416; }
  const DetectorConfig& config() const override { return config_; }

 private:
  DetectorConfig config_;
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;
  mutable bool entered_ = false;
  mutable bool open_ = false;
};

grpc::Status HealthCheck(const std::shared_ptr<grpc::Channel>& channel, std::string* status) {
  grpc::GenericStub generic(channel);
  grpc::Slice empty("");  // an empty HealthCheckRequest: the whole server
  grpc::ByteBuffer request(&empty, 1), response;
  grpc::ClientContext context;
  std::promise<grpc::Status> done;
  generic.UnaryCall(&context, "/grpc.health.v1.Health/Check", grpc::StubOptions(), &request,
                    &response, [&](grpc::Status s) { done.set_value(s); });
  const grpc::Status result = done.get_future().get();
  std::vector<grpc::Slice> slices;
  (void)response.Dump(&slices);
  status->clear();
  for (const auto& s : slices) status->append(reinterpret_cast<const char*>(s.begin()), s.size());
  return result;
}

// A frame in the middle of the pipeline when shutdown starts is still stored and answered; while
// it finishes, health says NOT_SERVING and new calls are refused.
TEST_F(ServerTest, ShutdownFinishesInFlightFramesAndReportsNotServing) {
  auto gate = std::make_shared<GateDetector>();
  ServerDeps deps;
  deps.detector = gate;
  ASSERT_NO_FATAL_FAILURE(StartServer(Config(), deps));
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);
  CreateMap("m", server_boxes);

  IngestOutcome outcome;
  std::thread agent([&] { outcome = IngestAll(stub_.get(), "m", {RtabmapObservation(1, "a")}); });
  gate->WaitEntered();  // the frame is being detected
  std::thread stopper([&] { server_->Shutdown(); });
  // Draining: health is NOT_SERVING (2) and new work is refused.
  std::string health;
  for (int i = 0; i < 500; ++i) {
    ASSERT_TRUE(HealthCheck(channel_, &health).ok());
    if (health == std::string("\x08\x02", 2)) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  EXPECT_EQ(health, std::string("\x08\x02", 2));
  v1::QueryResponse response;
  EXPECT_EQ(Query("m", RtabmapObservation(2, "a"), &response).error_code(),
            grpc::StatusCode::UNAVAILABLE);
  gate->Open();
  stopper.join();
  agent.join();
  ASSERT_EQ(outcome.responses.size(), 1u) << outcome.status.error_message();
  EXPECT_TRUE(outcome.responses[0].stored());
  EXPECT_EQ(outcome.responses[0].boxes_used_size(), 1);
  EXPECT_GT(outcome.responses[0].timings().detect_ms(), 0);
  StopServer();
  auto directory = DataDirectory::Open(root_ + "/data");
  ASSERT_TRUE(directory.ok());
  auto map = (*directory)->OpenMap("m", vocabulary_);
  ASSERT_TRUE(map.ok());
  EXPECT_TRUE((*map)->GetPlace(outcome.responses[0].place_id()).ok());
}

// /metrics over HTTP counts what was sent.
TEST_F(ServerTest, MetricsEndpointCountsWhatWasSent) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  CreateMap("m");
  std::vector<v1::Observation> observations;
  for (int frame = 1; frame <= 6; ++frame) observations.push_back(RtabmapObservation(frame, "a"));
  v1::Observation covered = RtabmapObservation(7, "a");  // a person over everything: invalid
  v1::Box* box = covered.add_boxes();
  box->set_class_name("person");
  box->set_confidence(0.9f);
  box->mutable_rect()->set_width(640);
  box->mutable_rect()->set_height(480);
  observations.push_back(covered);
  v1::Observation broken = RtabmapObservation(8, "a");
  broken.mutable_encoded_image()->set_data("broken");
  observations.push_back(broken);
  const IngestOutcome outcome = IngestAll(stub_.get(), "m", observations);
  ASSERT_TRUE(outcome.status.ok());
  ASSERT_EQ(outcome.responses.size(), 8u);
  EXPECT_FALSE(outcome.responses[6].stored());
  EXPECT_NE(outcome.responses[6].rejection().find("placeThreshold"), std::string::npos);
  EXPECT_TRUE(outcome.responses[7].has_error());
  double kept = 0, dropped = 0;
  for (const auto& response : outcome.responses) {
    kept += response.counts().kept();
    dropped += response.counts().dynamic();
  }
  v1::QueryResponse response;
  ASSERT_TRUE(Query("m", RtabmapObservation(41, "q"), &response).ok());
  ASSERT_TRUE(Query("m", RtabmapObservation(42, "q"), &response).ok());
  EXPECT_EQ(Query("m", broken, &response).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name("missing");
    v1::MapDescription description;
    EXPECT_EQ(stub_->GetMap(&context, request, &description).error_code(),
              grpc::StatusCode::NOT_FOUND);
  }

  const auto metrics = Scrape();
  ASSERT_FALSE(metrics.empty());
  using Labels = std::map<std::string, std::string>;
  EXPECT_EQ(MetricValue(metrics, "placedb_rpc_requests_total",
                        Labels{{"method", "Ingest"}, {"code", "OK"}}),
            1);
  EXPECT_EQ(MetricValue(metrics, "placedb_rpc_requests_total",
                        Labels{{"method", "Query"}, {"code", "OK"}}),
            2);
  EXPECT_EQ(MetricValue(metrics, "placedb_rpc_requests_total",
                        Labels{{"method", "Query"}, {"code", "INVALID_ARGUMENT"}}),
            1);
  EXPECT_EQ(MetricValue(metrics, "placedb_rpc_requests_total",
                        Labels{{"method", "GetMap"}, {"code", "NOT_FOUND"}}),
            1);
  EXPECT_EQ(MetricValue(metrics, "placedb_rpc_requests_total",
                        Labels{{"method", "CreateMap"}, {"code", "OK"}}),
            1);
  EXPECT_EQ(MetricValue(metrics, "placedb_frames_ingested_total", Labels{{"map", "m"}}), 6);
  EXPECT_EQ(MetricValue(metrics, "placedb_frames_rejected_total",
                        Labels{{"map", "m"}, {"reason", "invalid_place"}}),
            1);
  EXPECT_EQ(MetricValue(metrics, "placedb_frames_rejected_total",
                        Labels{{"map", "m"}, {"reason", "invalid_argument"}}),
            1);
  EXPECT_EQ(
      MetricValue(metrics, "placedb_descriptors_total", Labels{{"map", "m"}, {"class", "static"}}),
      kept);
  EXPECT_EQ(
      MetricValue(metrics, "placedb_descriptors_total", Labels{{"map", "m"}, {"class", "dynamic"}}),
      dropped);
  EXPECT_GT(dropped, 0);
  EXPECT_EQ(MetricValue(metrics, "placedb_places", Labels{{"map", "m"}}), 6);
  EXPECT_GT(MetricValue(metrics, "placedb_map_on_disk_bytes", Labels{{"map", "m"}}), 0);
  EXPECT_EQ(MetricValue(metrics, "placedb_streams_in_flight"), 0);
  EXPECT_EQ(MetricValue(metrics, "placedb_queue_depth"), 0);
  // One "total" observation per processed frame: 7 ingested (6 stored + 1 invalid), 2 queries.
  EXPECT_EQ(MetricValue(metrics, "placedb_stage_seconds_count", Labels{{"stage", "total"}}), 9);
  EXPECT_EQ(MetricValue(metrics, "placedb_stage_seconds_count", Labels{{"stage", "store"}}), 7);
  EXPECT_EQ(MetricValue(metrics, "placedb_stage_seconds_count", Labels{{"stage", "extract"}}), 9);
  EXPECT_EQ(MetricValue(metrics, "placedb_detector_seconds_count"), 0);

  // A deleted map's series go away.
  {
    grpc::ClientContext context;
    v1::DeleteMapRequest request;
    request.set_name("m");
    v1::DeleteMapResponse deleted;
    ASSERT_TRUE(stub_->DeleteMap(&context, request, &deleted).ok());
  }
  const auto later = Scrape();
  EXPECT_TRUE(std::isnan(MetricValue(later, "placedb_places", Labels{{"map", "m"}})));
  EXPECT_TRUE(
      std::isnan(MetricValue(later, "placedb_frames_ingested_total", Labels{{"map", "m"}})));
}

// The standard health service says SERVING; tiny deadlines end calls with DEADLINE_EXCEEDED.
TEST_F(ServerTest, HealthServingAndDeadlines) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  auto check = [&](const std::string& service) {
    grpc::GenericStub generic(channel_);
    std::string request;  // grpc.health.v1.HealthCheckRequest { string service = 1; }
    if (!service.empty()) request = std::string("\x0A", 1) + char(service.size()) + service;
    grpc::Slice slice(request);
    grpc::ByteBuffer request_buffer(&slice, 1), response_buffer;
    grpc::ClientContext context;
    std::promise<grpc::Status> done;
    generic.UnaryCall(&context, "/grpc.health.v1.Health/Check", grpc::StubOptions(),
                      &request_buffer, &response_buffer,
                      [&](grpc::Status status) { done.set_value(status); });
    const grpc::Status status = done.get_future().get();
    EXPECT_TRUE(status.ok()) << status.error_message();
    std::vector<grpc::Slice> slices;
    (void)response_buffer.Dump(&slices);
    std::string bytes;
    for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
    return bytes;  // HealthCheckResponse { ServingStatus status = 1; } SERVING = 1
  };
  EXPECT_EQ(check(""), std::string("\x08\x01", 2));
  EXPECT_EQ(check("placedb.v1.PlaceDb"), std::string("\x08\x01", 2));

  // Server reflection lists the API (ServerReflectionRequest { list_services = 7 }).
  {
    grpc::GenericStub generic(channel_);
    grpc::CompletionQueue cq;
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    auto call = generic.PrepareCall(
        &context, "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo", &cq);
    auto next = [&](intptr_t expected) {
      void* tag = nullptr;
      bool ok = false;
      EXPECT_TRUE(cq.Next(&tag, &ok));
      EXPECT_EQ(reinterpret_cast<intptr_t>(tag), expected);
      return ok;
    };
    call->StartCall(reinterpret_cast<void*>(1));
    ASSERT_TRUE(next(1));
    grpc::Slice slice(std::string("\x3a\x00", 2));
    grpc::ByteBuffer request(&slice, 1), reply;
    call->Write(request, reinterpret_cast<void*>(2));
    ASSERT_TRUE(next(2));
    call->Read(&reply, reinterpret_cast<void*>(3));
    ASSERT_TRUE(next(3));
    std::vector<grpc::Slice> slices;
    (void)reply.Dump(&slices);
    std::string bytes;
    for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
    EXPECT_NE(bytes.find("placedb.v1.PlaceDb"), std::string::npos);
    EXPECT_NE(bytes.find("grpc.health.v1.Health"), std::string::npos);
    call->WritesDone(reinterpret_cast<void*>(4));
    next(4);
    grpc::Status status;
    call->Finish(&status, reinterpret_cast<void*>(5));
    next(5);
    EXPECT_TRUE(status.ok()) << status.error_message();
  }

  CreateMap("m");
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::microseconds(1));
    v1::QueryRequest request;
    request.set_map("m");
    *request.mutable_observation() = RtabmapObservation(1, "a");
    v1::QueryResponse response;
    EXPECT_EQ(stub_->Query(&context, request, &response).error_code(),
              grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  {
    // A stream whose deadline passes while it sends.
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(400));
    auto stream = stub_->Ingest(&context);
    std::thread writer([&] {
      v1::IngestRequest header;
      header.mutable_header()->set_map("m");
      if (!stream->Write(header)) return;
      for (int i = 0; i < 10000; ++i) {
        v1::IngestRequest request;
        *request.mutable_observation() = RtabmapObservation(1 + i % 40, "a");
        if (!stream->Write(request)) return;
      }
    });
    v1::IngestResponse response;
    while (stream->Read(&response)) {
    }
    writer.join();
    EXPECT_EQ(stream->Finish().error_code(), grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  // The server is still healthy and serving afterwards.
  v1::QueryResponse response;
  EXPECT_TRUE(Query("m", RtabmapObservation(2, "a"), &response).ok());
  grpc::ClientContext context;
  v1::ServerInfo info;
  ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
  EXPECT_EQ(info.version(), PLACEDB_VERSION);
  ASSERT_EQ(info.vocabularies_size(), 1);
  EXPECT_EQ(info.vocabularies(0).checksum(), vocabulary_->checksum_hex());
  EXPECT_EQ(info.detector(), "off");
  EXPECT_EQ(info.limits().max_boxes_per_frame(), 16u);
  EXPECT_EQ(info.limits().worker_threads(), 2u);
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

// Maps reopen with the vocabulary whose checksum they recorded; one whose vocabulary is not
// configured is listed as unavailable (not fatal) until it is.
TEST_F(ServerTest, RestartReopensMapsWithTheirOwnVocabulary) {
  VocabularyTree tree = vocabulary_->ToTree();
  for (size_t i = 0; i < tree.word_id.size(); ++i) {
    if (tree.word_id[i] >= 0) {
      tree.weight[i] += 1.0f;
      break;
    }
  }
  auto other = Vocabulary::FromTree(tree);
  ASSERT_TRUE(other.ok()) << other.status().ToString();
  ServerConfig config = Config();
  config.vocabularies["other"] = "(preloaded)";
  ServerDeps deps;
  deps.vocabularies["other"] = *other;
  ASSERT_NO_FATAL_FAILURE(StartServer(config, deps));
  v1::MapConfig with_other;
  with_other.set_vocabulary("other");
  with_other.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
  with_other.mutable_filter()->set_method(v1::FILTER_METHOD_EXACT_COVERAGE);
  const v1::MapDescription created = CreateMap("other-map", with_other);
  EXPECT_EQ(created.config().vocabulary(), "other");
  EXPECT_EQ(created.config().verification().mode(), v1::VERIFICATION_MODE_EXHAUSTIVE);
  EXPECT_EQ(created.config().orb().max_features(), 1000);  // defaults filled in
  EXPECT_EQ(created.config().detection().box_source(), v1::BOX_SOURCE_AGENT);
  EXPECT_EQ(created.config().detection().classes_size(), 6);
  CreateMap("default-map");
  ASSERT_TRUE(IngestAll(stub_.get(), "other-map", {RtabmapObservation(1, "a")}).status.ok());
  ASSERT_TRUE(IngestAll(stub_.get(), "default-map", {RtabmapObservation(2, "a")}).status.ok());
  StopServer();

  // Without "other": its map is unavailable, the rest serves.
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  {
    grpc::ClientContext context;
    v1::ListMapsResponse maps;
    ASSERT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
    ASSERT_EQ(maps.maps_size(), 2);
    EXPECT_EQ(maps.maps(0).name(), "default-map");
    EXPECT_TRUE(maps.maps(0).available());
    EXPECT_EQ(maps.maps(0).places(), 1u);
    EXPECT_EQ(maps.maps(1).name(), "other-map");
    EXPECT_FALSE(maps.maps(1).available());
    EXPECT_NE(maps.maps(1).unavailable_reason().find((*other)->checksum_hex()), std::string::npos)
        << maps.maps(1).unavailable_reason();
  }
  v1::QueryResponse response;
  const grpc::Status unavailable = Query("other-map", RtabmapObservation(1, "a"), &response);
  EXPECT_EQ(unavailable.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(unavailable.error_message().find("not configured"), std::string::npos);
  EXPECT_TRUE(Query("default-map", RtabmapObservation(2, "a"), &response).ok());
  ASSERT_FALSE(response.matches().empty());
  EXPECT_NEAR(response.matches(0).score(), 1.0, 1e-5);
  StopServer();

  // With it again: available, with its configuration and places.
  ASSERT_NO_FATAL_FAILURE(StartServer(config, deps));
  grpc::ClientContext context;
  v1::GetMapRequest request;
  request.set_name("other-map");
  v1::MapDescription description;
  ASSERT_TRUE(stub_->GetMap(&context, request, &description).ok());
  EXPECT_EQ(description.config().vocabulary(), "other");
  EXPECT_EQ(description.config().filter().method(), v1::FILTER_METHOD_EXACT_COVERAGE);
  EXPECT_EQ(description.stats().places(), 1u);
  EXPECT_EQ(description.vocabulary_checksum(), (*other)->checksum_hex());
  ASSERT_TRUE(Query("other-map", RtabmapObservation(1, "a"), &response).ok());
  ASSERT_FALSE(response.matches().empty());
  EXPECT_GT(response.matches(0).inliers(), 12);
}

// ---- RGB-D: SIFT maps, depth, loop closure ------------------------------------------------------

// The Debian SIFT vocabulary (the sift_vocabulary ctest fixture builds it), loaded once.
std::shared_ptr<const FloatVocabulary> SiftVocabulary() {
  static const std::shared_ptr<const FloatVocabulary> vocabulary = [] {
    auto loaded = rgbd::LoadOrTrainSiftVocabulary(rgbd::SiftVocabularyPath());
    EXPECT_TRUE(loaded.ok()) << loaded.status().ToString();
    return loaded.ok() ? *loaded : nullptr;
  }();
  return vocabulary;
}

// The server's configuration with the SIFT vocabulary as "sift" (preloaded by StartServerWithSift).
ServerConfig WithSift(ServerConfig config) {
  config.vocabularies["sift"] = rgbd::SiftVocabularyPath();
  return config;
}

ServerDeps SiftDeps() {
  ServerDeps deps;
  deps.vocabularies.emplace("sift", SiftVocabulary());
  return deps;
}

v1::MapConfig SiftMapConfig() {
  v1::MapConfig config;
  config.set_vocabulary("sift");
  config.set_feature_type(v1::FEATURE_TYPE_SIFT);
  return config;
}

// SIFT of `observation`'s JPEG exactly as the server computes it for a default SIFT map.
v1::SiftFeatures SiftFeaturesOf(const v1::Observation& observation) {
  const std::string& bytes = observation.encoded_image().data();
  cv::Mat gray = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())),
                              cv::IMREAD_GRAYSCALE);
  auto features = ExtractSift(gray, SiftConfig{});
  EXPECT_TRUE(features.ok()) << features.status().ToString();
  v1::SiftFeatures out;
  server::SiftFeaturesToProto(*features, &out);
  return out;
}

// An rgbd-people / slambook2 frame: the colour image as PNG bytes, depth as a 16-bit PNG (mm).
v1::Observation RgbdObservation(const rgbd::RgbdFrame& frame, const std::string& agent,
                                uint64_t sequence) {
  v1::Observation observation;
  observation.set_agent_id(agent);
  observation.set_sequence(sequence);
  observation.mutable_encoded_image()->set_data(ReadBytes(frame.image_path));
  const cv::Mat depth = cv::imread(frame.depth_path, cv::IMREAD_UNCHANGED | cv::IMREAD_ANYDEPTH);
  EXPECT_EQ(depth.type(), CV_16UC1) << frame.depth_path;
  observation.mutable_depth()->set_png16(EncodePng(depth));
  return observation;
}

// A SIFT map: created on the float vocabulary, frames ingested as images, queried back (as images
// and as precomputed SIFT) with exhaustive verification, stored SIFT features read back.
TEST_F(ServerTest, SiftMapIngestsImagesAndFindsThemVerified) {
  ASSERT_TRUE(SiftVocabulary());
  ASSERT_NO_FATAL_FAILURE(StartServer(WithSift(Config()), SiftDeps()));
  {
    grpc::ClientContext context;
    v1::ServerInfo info;
    ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
    std::map<std::string, v1::FeatureType> kinds;
    for (const auto& vocabulary : info.vocabularies()) {
      kinds[vocabulary.name()] = vocabulary.feature_type();
    }
    EXPECT_EQ(kinds["default"], v1::FEATURE_TYPE_ORB);
    EXPECT_EQ(kinds["sift"], v1::FEATURE_TYPE_SIFT);
  }
  v1::MapConfig config;
  config.set_vocabulary("sift");  // feature_type unspecified: the vocabulary's kind
  config.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
  const v1::MapDescription created = CreateMap("sift-map", config);
  EXPECT_EQ(created.config().feature_type(), v1::FEATURE_TYPE_SIFT);
  EXPECT_EQ(created.config().sift().max_features(), 1000);  // effective values filled in
  EXPECT_NEAR(created.config().sift().contrast_threshold(), 0.04, 1e-9);
  EXPECT_NEAR(created.config().depth().threshold_m(), 0.15, 1e-6);
  EXPECT_EQ(created.config().depth().band_policy(), v1::BAND_POLICY_APPEARED_LAYER);
  EXPECT_NEAR(created.config().loop_closure().loop_threshold(), 0.12, 1e-9);
  EXPECT_EQ(created.vocabulary_checksum(), SiftVocabulary()->checksum_hex());

  std::vector<v1::Observation> observations;
  for (int frame = 1; frame <= 24; ++frame) observations.push_back(RtabmapObservation(frame, "a"));
  const IngestOutcome outcome = IngestAll(stub_.get(), "sift-map", observations);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), observations.size());
  std::vector<size_t> stored;
  for (size_t i = 0; i < outcome.responses.size(); ++i) {
    const v1::IngestResponse& response = outcome.responses[i];
    ASSERT_FALSE(response.has_error()) << i << ": " << response.error().message();
    EXPECT_EQ(
        response.counts().total(),
        response.counts().dynamic() + response.counts().depth_removed() + response.counts().kept());
    EXPECT_GT(response.timings().extract_ms(), 0);
    if (response.stored()) stored.push_back(i);
  }
  // The corridor is low-texture for SIFT: most frames, not necessarily all, are places.
  ASSERT_GE(stored.size(), 12u);
  EXPECT_EQ(Stats("sift-map").places(), stored.size());

  int verified = 0;
  for (size_t k = 0; k < stored.size(); k += 3) {
    const size_t i = stored[k];
    v1::QueryResponse response;
    ASSERT_TRUE(Query("sift-map", observations[i], &response, 3).ok());
    ASSERT_TRUE(response.valid()) << response.rejection();
    ASSERT_FALSE(response.matches().empty());
    EXPECT_EQ(response.matches(0).place_id(), outcome.responses[i].place_id()) << "frame " << i + 1;
    EXPECT_NEAR(response.matches(0).score(), 1.0, 1e-5);
    verified += response.matches(0).verified();
    EXPECT_GT(response.matches(0).inliers(), 0);
    // Precomputed SIFT: the same ranking as the image.
    v1::Observation features_only;
    *features_only.mutable_sift_features() = SiftFeaturesOf(observations[i]);
    v1::QueryResponse from_features;
    ASSERT_TRUE(Query("sift-map", features_only, &from_features, 3).ok());
    ASSERT_EQ(from_features.matches_size(), response.matches_size());
    for (int m = 0; m < response.matches_size(); ++m) {
      EXPECT_EQ(from_features.matches(m).place_id(), response.matches(m).place_id());
      EXPECT_NEAR(from_features.matches(m).score(), response.matches(m).score(), 1e-9);
    }
  }
  EXPECT_EQ(verified, int((stored.size() + 2) / 3)) << "every self-match is verified";

  // Stored SIFT features on request: 512 bytes per kept keypoint.
  grpc::ClientContext context;
  v1::GetPlaceRequest request;
  request.set_map("sift-map");
  request.set_place_id(outcome.responses[stored[0]].place_id());
  request.set_include_features(true);
  v1::Place place;
  ASSERT_TRUE(stub_->GetPlace(&context, request, &place).ok());
  EXPECT_FALSE(place.has_features());
  EXPECT_EQ(uint32_t(place.sift_features().keypoints_size()), place.counts().kept());
  EXPECT_EQ(place.sift_features().descriptors().size(),
            size_t(place.sift_features().keypoints_size()) * 512);

  // ORB features cannot go into a SIFT map.
  v1::Observation orb_only;
  *orb_only.mutable_features() = FeaturesOf(observations[0]);
  v1::QueryResponse response;
  const grpc::Status wrong_type = Query("sift-map", orb_only, &response);
  EXPECT_EQ(wrong_type.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(wrong_type.error_message().find("observation.features"), std::string::npos)
      << wrong_type.error_message();
}

// A map's feature type must be its vocabulary's kind.
TEST_F(ServerTest, FeatureTypeMustMatchTheVocabulary) {
  ASSERT_TRUE(SiftVocabulary());
  ASSERT_NO_FATAL_FAILURE(StartServer(WithSift(Config()), SiftDeps()));
  v1::MapConfig sift_on_orb;
  sift_on_orb.set_feature_type(v1::FEATURE_TYPE_SIFT);  // on "default", a binary vocabulary
  const grpc::Status refused = CreateMapStatus("x", sift_on_orb);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(refused.error_message().rfind("config.feature_type", 0), 0u) << refused.error_message();
  v1::MapConfig orb_on_sift;
  orb_on_sift.set_vocabulary("sift");
  orb_on_sift.set_feature_type(v1::FEATURE_TYPE_ORB);
  EXPECT_EQ(CreateMapStatus("x", orb_on_sift).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  v1::MapConfig too_many = SiftMapConfig();
  too_many.mutable_sift()->set_max_features(5000);  // over limits.max_descriptors_per_frame 2000
  const grpc::Status budget = CreateMapStatus("x", too_many);
  EXPECT_EQ(budget.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(budget.error_message().find("config.sift.max_features"), std::string::npos);
  v1::MapConfig bad_sift = SiftMapConfig();
  bad_sift.mutable_sift()->set_octave_layers(0);
  const grpc::Status layers = CreateMapStatus("x", bad_sift);
  EXPECT_EQ(layers.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(layers.error_message().find("config.sift.octave_layers"), std::string::npos);
  v1::MapConfig bad_depth;
  bad_depth.mutable_depth()->set_threshold_m(-1);
  const grpc::Status depth = CreateMapStatus("x", bad_depth);
  EXPECT_EQ(depth.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(depth.error_message().rfind("config.depth.threshold_m", 0), 0u)
      << depth.error_message();
  v1::MapConfig bad_band;
  bad_band.mutable_depth()->mutable_rise_band()->set_near_m(3);
  bad_band.mutable_depth()->mutable_rise_band()->set_far_m(2);
  EXPECT_NE(CreateMapStatus("x", bad_band).error_message().find("config.depth.rise_band"),
            std::string::npos);
  v1::MapConfig bad_loop;
  bad_loop.mutable_loop_closure()->set_loop_threshold(1.5);
  const grpc::Status loop = CreateMapStatus("x", bad_loop);
  EXPECT_EQ(loop.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(loop.error_message().rfind("config.loop_closure.loop_threshold", 0), 0u)
      << loop.error_message();
  // All = the limit: a SIFT map never extracts more than a frame may carry.
  v1::MapConfig all = SiftMapConfig();
  all.mutable_sift()->set_max_features(0);
  EXPECT_EQ(CreateMap("all", all).config().sift().max_features(), 2000);
  // Settings round-trip.
  v1::MapConfig tuned;
  tuned.mutable_depth()->set_threshold_m(0.3f);
  tuned.mutable_depth()->set_band_policy(v1::BAND_POLICY_FIXED);
  tuned.mutable_depth()->set_stream_filter(false);
  tuned.mutable_loop_closure()->set_short_term_memory(12);
  const v1::MapDescription described = CreateMap("tuned", tuned);
  EXPECT_EQ(described.config().feature_type(), v1::FEATURE_TYPE_ORB);
  EXPECT_NEAR(described.config().depth().threshold_m(), 0.3, 1e-6);
  EXPECT_EQ(described.config().depth().band_policy(), v1::BAND_POLICY_FIXED);
  EXPECT_FALSE(described.config().depth().stream_filter());
  EXPECT_EQ(described.config().loop_closure().short_term_memory(), 12);
  grpc::ClientContext context;
  v1::ListMapsResponse maps;
  ASSERT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
  EXPECT_EQ(maps.maps_size(), 2) << "a refused CreateMap left a map behind";
  for (const v1::MapSummary& summary : maps.maps()) {
    grpc::ClientContext get_context;
    v1::GetMapRequest get;
    get.set_name(summary.name());
    v1::MapDescription description;
    ASSERT_TRUE(stub_->GetMap(&get_context, get, &description).ok());
    EXPECT_NE(summary.feature_type(), v1::FEATURE_TYPE_UNSPECIFIED) << summary.name();
    EXPECT_EQ(summary.feature_type(), description.config().feature_type()) << summary.name();
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

// Bad SIFT features and unregistrable depth are refused with the field named, storing nothing.
TEST_F(ServerTest, BadSiftFeaturesAndDepthAreRefused) {
  ASSERT_TRUE(SiftVocabulary());
  ASSERT_NO_FATAL_FAILURE(StartServer(WithSift(Config()), SiftDeps()));
  CreateMap("sift-map", SiftMapConfig());
  const v1::Observation good = RtabmapObservation(3, "a");
  const v1::SiftFeatures features = SiftFeaturesOf(good);
  ASSERT_GT(features.keypoints_size(), 30);
  struct Case {
    std::string name;
    v1::Observation observation;
    std::string message;
  };
  std::vector<Case> cases;
  auto add = [&](std::string name, std::string message,
                 const std::function<void(v1::Observation*)>& edit) {
    v1::Observation observation = good;
    edit(&observation);
    cases.push_back({std::move(name), std::move(observation), std::move(message)});
  };
  add("descriptor bytes not a multiple of 512", "observation.sift_features.descriptors",
      [&](v1::Observation* o) {
        *o->mutable_sift_features() = features;
        o->mutable_sift_features()->mutable_descriptors()->resize(features.descriptors().size() -
                                                                  4);
      });
  add("one descriptor too few", "observation.sift_features.descriptors", [&](v1::Observation* o) {
    *o->mutable_sift_features() = features;
    o->mutable_sift_features()->mutable_descriptors()->resize(features.descriptors().size() - 512);
  });
  add("keypoint outside the image", "observation.sift_features.keypoints[3].x",
      [&](v1::Observation* o) {
        *o->mutable_sift_features() = features;
        o->mutable_sift_features()->mutable_keypoints(3)->set_x(9999);
      });
  add("non-finite descriptor value", "observation.sift_features", [&](v1::Observation* o) {
    *o->mutable_sift_features() = features;
    const float nan = std::nanf("");
    o->mutable_sift_features()->mutable_descriptors()->replace(
        512 * 2 + 4 * 7, 4, reinterpret_cast<const char*>(&nan), 4);
  });
  add("depth with another aspect ratio", "observation.depth", [](v1::Observation* o) {
    o->mutable_depth()->set_png16(EncodePng(cv::Mat(300, 300, CV_16U, cv::Scalar(1500))));
  });
  add("sift features with depth of another aspect ratio", "observation.depth",
      [&](v1::Observation* o) {
        *o->mutable_sift_features() = features;
        o->mutable_depth()->set_png16(EncodePng(cv::Mat(100, 50, CV_16U, cv::Scalar(1500))));
      });
  std::vector<v1::Observation> bad;
  for (const Case& c : cases) {
    v1::QueryResponse response;
    const grpc::Status status = Query("sift-map", c.observation, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << c.name;
    EXPECT_NE(status.error_message().find(c.message), std::string::npos)
        << c.name << ": " << status.error_message();
    bad.push_back(c.observation);
  }
  const IngestOutcome outcome = IngestAll(stub_.get(), "sift-map", bad);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), cases.size());
  for (size_t i = 0; i < cases.size(); ++i) {
    const v1::IngestResponse& response = outcome.responses[i];
    EXPECT_FALSE(response.stored()) << cases[i].name;
    EXPECT_EQ(response.error().code(), int(grpc::StatusCode::INVALID_ARGUMENT)) << cases[i].name;
    EXPECT_NE(response.error().message().find(cases[i].message), std::string::npos)
        << cases[i].name << ": " << response.error().message();
  }
  const v1::MapStats stats = Stats("sift-map");
  EXPECT_EQ(stats.places(), 0u);
  EXPECT_EQ(stats.invalid_rejected(), 0u);
  EXPECT_EQ(stats.streams(), 0u) << "a refused frame must not touch the agent's stream state";
  // The good frame itself goes in.
  const IngestOutcome fine = IngestAll(stub_.get(), "sift-map", {good});
  ASSERT_EQ(fine.responses.size(), 1u);
  EXPECT_TRUE(fine.responses[0].stored())
      << fine.responses[0].rejection() << fine.responses[0].error().message();
}

// An embedded-default vocabulary whose file is missing is a warning (maps that need it are
// unavailable); one the operator named is a startup error.
TEST_F(ServerTest, MissingEmbeddedSiftVocabularyIsAWarningUnlessConfigured) {
  ServerConfig config = Config();
  config.vocabularies["sift"] = root_ + "/nowhere/sift-debian.pdbfv";
  config.optional_vocabularies = {"sift"};
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  const grpc::Status missing = CreateMapStatus("s", SiftMapConfig());
  EXPECT_EQ(missing.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(missing.error_message().find("not loaded"), std::string::npos)
      << missing.error_message();
  {
    grpc::ClientContext context;
    v1::ServerInfo info;
    ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
    ASSERT_EQ(info.vocabularies_size(), 1);
    EXPECT_EQ(info.vocabularies(0).name(), "default");
  }
  StopServer();
  config.optional_vocabularies.clear();
  auto refused = Server::Start(config, {});
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.status().message().find("vocabulary 'sift'"), std::string::npos)
      << refused.status().ToString();

  // Which entries are optional: the embedded ones as embedded (also when a file repeats them).
  const char* plain[] = {"placedb-server"};
  auto defaults = server::ParseCommandLine(1, plain, [](const char*) { return nullptr; });
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->config.vocabularies.at("sift"), "var/vocabulary/sift-debian.pdbfv");
  EXPECT_TRUE(defaults->config.optional_vocabularies.count("sift"));
  const char* flagged[] = {"placedb-server", "--vocabulary", "sift=/data/sift.pdbfv"};
  auto flag = server::ParseCommandLine(3, flagged, [](const char*) { return nullptr; });
  ASSERT_TRUE(flag.ok());
  EXPECT_FALSE(flag->config.optional_vocabularies.count("sift"));
  ServerConfig from_file;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(ServerConfig{}), &from_file).ok());
  EXPECT_TRUE(from_file.optional_vocabularies.count("sift"));
  ASSERT_TRUE(server::ApplyConfigYaml(
                  "vocabularies:\n  default: a.pdbv\n  sift: /data/sift.pdbfv\n", &from_file)
                  .ok());
  EXPECT_FALSE(from_file.optional_vocabularies.count("sift"));
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
  // Features alone cannot be detected on: refused for SERVER, agent boxes only for BOTH.
  v1::Observation features_only;
  *features_only.mutable_features() = FeaturesOf(frames[0]);
  v1::QueryResponse response;
  EXPECT_EQ(Query("server", features_only, &response).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_TRUE(Query("both", features_only, &response).ok());

  const auto metrics = Scrape();
  EXPECT_GE(MetricValue(metrics, "placedb_detector_seconds_count"), 4);
  grpc::ClientContext context;
  v1::ServerInfo info;
  ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
  EXPECT_NE(info.detector().find("yolox_nano.onnx"), std::string::npos) << info.detector();
}

// A detector model that does not load: detection is off (and says why) unless it is required.
TEST_F(ServerTest, DetectorThatFailsToLoadIsOffUnlessRequired) {
  ServerConfig config = Config();
  config.detector.model = root_ + "/no-such-model.onnx";
  config.detector.required = true;
  auto refused = Server::Start(config, {{{"default", vocabulary_}}, nullptr});
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kNotFound) << refused.status().ToString();

  config.detector.required = false;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  grpc::ClientContext context;
  v1::ServerInfo info;
  ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
  EXPECT_EQ(info.detector().rfind("off: NOT_FOUND", 0), 0u) << info.detector();
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_BOTH);
  EXPECT_EQ(CreateMapStatus("m", server_boxes).error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  // Maps on agents' boxes work as ever.
  CreateMap("m");
  const IngestOutcome outcome = IngestAll(stub_.get(), "m", {RtabmapObservation(1, "a")});
  ASSERT_EQ(outcome.responses.size(), 1u);
  EXPECT_TRUE(outcome.responses[0].stored());
}

// ---- The binary ---------------------------------------------------------------------------------

// build/tests/server_test -> build/server/placedb-server
std::string ServerBinary() {
  char self[4096];
  const ssize_t n = readlink("/proc/self/exe", self, sizeof self - 1);
  if (n <= 0) return "";
  std::string path(self, size_t(n));
  path = path.substr(0, path.rfind('/'));  // build/tests
  return path.substr(0, path.rfind('/')) + "/server/placedb-server";
}

int FreePort() {
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

// SIGTERM with streams open: the process drains, flushes and exits 0; the places are on disk.
TEST(ServerBinaryTest, SigtermShutsDownGracefullyWithExitZero) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  const std::string binary = ServerBinary();
  ASSERT_EQ(access(binary.c_str(), X_OK), 0) << binary << " is not built";
  const std::string root = testing::MakeTempDir("placedb-binary");
  const std::string address = "127.0.0.1:" + std::to_string(FreePort());
  const std::string vocabulary = "default=" + testing::DefaultVocabularyPath();
  const std::string data = root + "/data";
  std::vector<std::string> args = {binary,     "--listen",         address, "--data-dir",
                                   data,       "--metrics-listen", "off",   "--vocabulary",
                                   vocabulary, "--log-level",      "warn"};
  std::vector<char*> argv;
  for (std::string& arg : args) argv.push_back(arg.data());
  argv.push_back(nullptr);
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    execv(binary.c_str(), argv.data());
    _exit(127);
  }
  grpc::ChannelArguments channel_args;  // retry quickly while the child starts
  channel_args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 50);
  channel_args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 50);
  channel_args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 200);
  auto channel =
      grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), channel_args);
  const bool connected =
      channel->WaitForConnected(std::chrono::system_clock::now() + std::chrono::seconds(20));
  if (!connected) kill(pid, SIGKILL);
  ASSERT_TRUE(connected) << "placedb-server did not start listening on " << address;
  auto stub = v1::PlaceDb::NewStub(channel);
  {
    grpc::ClientContext context;
    v1::CreateMapRequest request;
    request.set_name("m");
    v1::MapDescription description;
    ASSERT_TRUE(stub->CreateMap(&context, request, &description).ok());
  }
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 5; ++frame) frames.push_back(RtabmapObservation(frame, "a"));
  const IngestOutcome outcome = IngestAll(stub.get(), "m", frames);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  grpc::ClientContext idle_context;  // an open, idle stream must not hold up the exit
  auto idle = stub->Ingest(&idle_context);
  v1::IngestRequest header;
  header.mutable_header()->set_map("m");
  ASSERT_TRUE(idle->Write(header));

  const auto signalled = std::chrono::steady_clock::now();
  ASSERT_EQ(kill(pid, SIGTERM), 0);
  int status = 0;
  pid_t done = 0;
  while ((done = waitpid(pid, &status, WNOHANG)) == 0 &&
         std::chrono::steady_clock::now() - signalled < std::chrono::seconds(20)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (done == 0) kill(pid, SIGKILL);
  ASSERT_EQ(done, pid) << "placedb-server did not exit within 20 s of SIGTERM";
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  EXPECT_LT(std::chrono::steady_clock::now() - signalled, std::chrono::seconds(5));
  v1::IngestResponse ignored;
  EXPECT_FALSE(idle->Read(&ignored));
  (void)idle->Finish();

  auto directory = DataDirectory::Open(data);
  ASSERT_TRUE(directory.ok()) << directory.status().ToString();
  auto map = (*directory)->OpenMap("m", testing::DefaultVocabulary());
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  for (const auto& response : outcome.responses) {
    if (response.stored()) {
      EXPECT_TRUE((*map)->GetPlace(response.place_id()).ok());
    }
  }
  EXPECT_EQ((*map)->Stats().database.places, 5u);
}

// ---- Configuration ------------------------------------------------------------------------------

TEST(ServerConfigTest, FileThenEnvironmentThenFlags) {
  const std::string dir = testing::MakeTempDir("placedb-config");
  const std::string path = dir + "/placedb.yaml";
  std::ofstream(path) << "listen: 0.0.0.0:6000\n"
                         "data_dir: /srv/placedb\n"
                         "threads: 3\n"
                         "vocabularies:\n  default: a.pdbv\n  indoor: b.pdbv\n"
                         "limits:\n  max_boxes_per_frame: 9\n"
                         "storage:\n  sync: group_commit\n";
  std::map<std::string, std::string> env = {{"PLACEDB_DATA_DIR", "/env/data"},
                                            {"PLACEDB_METRICS_PORT", "9999"}};
  auto getenv = [&](const char* name) -> const char* {
    auto it = env.find(name);
    return it == env.end() ? nullptr : it->second.c_str();
  };
  const char* argv[] = {"placedb-server", "--config",       path.c_str(),  "--threads", "5",
                        "--vocabulary",   "outdoor=c.pdbv", "--max-boxes", "11"};
  auto parsed = server::ParseCommandLine(9, argv, getenv);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  ASSERT_FALSE(parsed->exit_code);
  const ServerConfig& c = parsed->config;
  EXPECT_EQ(c.listen, "0.0.0.0:6000");          // file
  EXPECT_EQ(c.data_dir, "/env/data");           // environment over file
  EXPECT_EQ(c.metrics_listen, "0.0.0.0:9999");  // environment (port only)
  EXPECT_EQ(c.threads, 5);                      // flag over file
  EXPECT_EQ(c.limits.max_boxes_per_frame, 11u);
  EXPECT_EQ(c.storage.sync, SyncMode::kGroupCommit);
  EXPECT_EQ(c.vocabularies.size(), 3u);
  EXPECT_EQ(c.vocabularies.at("indoor"), "b.pdbv");
  EXPECT_EQ(c.vocabularies.at("outdoor"), "c.pdbv");

  // Round trip through --print-config's YAML.
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(c), &again).ok());
  EXPECT_EQ(server::ConfigToYaml(again), server::ConfigToYaml(c));

  ServerConfig bad;
  const Status typo = server::ApplyConfigYaml("limits:\n  max_boxes: 3\n", &bad);
  EXPECT_EQ(typo.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(typo.message().find("limits.max_boxes"), std::string::npos) << typo.message();
  EXPECT_FALSE(server::ApplyConfigYaml("threads: many\n", &bad).ok());
  ServerConfig no_default;
  no_default.vocabularies = {{"indoor", "b.pdbv"}};
  EXPECT_NE(server::ValidateServerConfig(no_default).message().find("default"), std::string::npos);
  // The example config in the repository is valid.
  ServerConfig example;
  EXPECT_TRUE(server::ApplyConfigFile(SourceDir() + "/server/placedb.yaml", &example).ok());
  EXPECT_TRUE(server::ValidateServerConfig(example).ok());
}

TEST(ServerConvertTest, ImageHeadersAreReadWithoutDecoding) {
  auto png = server::ReadImageHeader(EncodePng(cv::Mat::zeros(30, 40, CV_8U)));
  ASSERT_TRUE(png.ok());
  EXPECT_EQ(png->width, 40);
  EXPECT_EQ(png->height, 30);
  std::vector<uint8_t> jpeg;
  ASSERT_TRUE(cv::imencode(".jpg", cv::Mat::zeros(70, 90, CV_8UC3), jpeg));
  auto header = server::ReadImageHeader(std::string(jpeg.begin(), jpeg.end()));
  ASSERT_TRUE(header.ok()) << header.status().ToString();
  EXPECT_EQ(header->width, 90);
  EXPECT_EQ(header->height, 70);
  EXPECT_FALSE(server::ReadImageHeader("GIF89a").ok());
  EXPECT_FALSE(server::ReadImageHeader(std::string(jpeg.begin(), jpeg.begin() + 20)).ok());
}

}  // namespace
}  // namespace placedb
