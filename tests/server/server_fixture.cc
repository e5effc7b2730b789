#include "tests/server/server_fixture.h"

#include <arpa/inet.h>
#include <grpc/grpc.h>
#include <grpcpp/generic/generic_stub.h>
#include <netinet/in.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <future>
#include <opencv2/imgcodecs.hpp>
#include <sstream>
#include <thread>

#include "core/features/orb_features.h"
#include "core/features/sift_features.h"
#include "proto/convert_result.h"
#include "tests/test_support.h"

namespace placedb::server_testing {

grpc::Status HealthCheck(const std::shared_ptr<grpc::Channel>& channel, std::string* serving) {
  grpc::GenericStub generic(channel);
  grpc::Slice empty("");  // an empty HealthCheckRequest: the whole server
  grpc::ByteBuffer request(&empty, 1), response;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  std::promise<grpc::Status> done;
  generic.UnaryCall(&context, "/grpc.health.v1.Health/Check", grpc::StubOptions(), &request,
                    &response, [&](grpc::Status s) { done.set_value(s); });
  const grpc::Status result = done.get_future().get();
  std::vector<grpc::Slice> slices;
  (void)response.Dump(&slices);
  serving->clear();
  for (const auto& s : slices) serving->append(reinterpret_cast<const char*>(s.begin()), s.size());
  return result;
}
namespace {

// gRPC stays initialised for the whole process. Otherwise every test's teardown runs gRPC's
// library shutdown, which in a process holding both clients and a server can wait ~10 s for an
// executor thread's poll to time out (not something the server binary does: it exits in ms).
// (In this file, which every service test links through ServerTest or the frame builders.)
const bool kGrpcInitialised = [] {
  grpc_init();
  return true;
}();

}  // namespace

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
  observation.mutable_encoded_image()->set_data(testing::ReadFileBytes(path));
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

v1::Features FeaturesOf(const v1::Observation& observation) {
  const std::string& bytes = observation.encoded_image().data();
  cv::Mat gray = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())),
                              cv::IMREAD_GRAYSCALE);
  auto features = ExtractOrb(gray, OrbConfig{});
  EXPECT_TRUE(features.ok()) << features.status().ToString();
  v1::Features out;
  wire::FeaturesToProto(*features, &out);
  return out;
}

v1::SiftFeatures SiftFeaturesOf(const v1::Observation& observation) {
  const std::string& bytes = observation.encoded_image().data();
  cv::Mat gray = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())),
                              cv::IMREAD_GRAYSCALE);
  auto features = ExtractSift(gray, SiftConfig{});
  EXPECT_TRUE(features.ok()) << features.status().ToString();
  v1::SiftFeatures out;
  wire::SiftFeaturesToProto(*features, &out);
  return out;
}

v1::Observation RgbdObservation(const rgbd::RgbdFrame& frame, const std::string& agent,
                                uint64_t sequence) {
  v1::Observation observation;
  observation.set_agent_id(agent);
  observation.set_sequence(sequence);
  observation.mutable_encoded_image()->set_data(testing::ReadFileBytes(frame.image_path));
  const cv::Mat depth = cv::imread(frame.depth_path, cv::IMREAD_UNCHANGED | cv::IMREAD_ANYDEPTH);
  EXPECT_EQ(depth.type(), CV_16UC1) << frame.depth_path;
  observation.mutable_depth()->set_png16(EncodePng(depth));
  return observation;
}

IngestOutcome IngestWithHeader(v1::PlaceDb::Stub* stub, const v1::IngestHeader& header,
                               const std::vector<v1::Observation>& observations,
                               const std::string& authorization) {
  grpc::ClientContext context;
  if (!authorization.empty()) context.AddMetadata("authorization", authorization);
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
                        const v1::MatchOptions* matches) {
  v1::IngestHeader header;
  header.set_map(map);
  if (matches) *header.mutable_matches() = *matches;
  return IngestWithHeader(stub, header, observations);
}

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

std::string HttpGet(int port, const std::string& path, const std::string& headers) {
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
  const std::string request = "GET " + path + " HTTP/1.0\r\nHost: 127.0.0.1\r\n" + headers + "\r\n";
  EXPECT_EQ(send(fd, request.data(), request.size(), 0), ssize_t(request.size()));
  std::string reply;
  char buffer[4096];
  ssize_t n;
  while ((n = recv(fd, buffer, sizeof buffer, 0)) > 0) reply.append(buffer, size_t(n));
  close(fd);
  return reply;
}

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
                   const std::map<std::string, std::string>& labels) {
  std::string key = name + "{";
  for (const auto& [k, v] : labels) key += k + "=" + v + ",";
  key += "}";
  auto it = metrics.find(key);
  return it == metrics.end() ? std::nan("") : it->second;
}

double AwaitMetric(int port, const std::string& name,
                   const std::map<std::string, std::string>& labels, double value) {
  double seen = 0;
  for (int attempt = 0; attempt < 3000; ++attempt) {
    seen = MetricValue(ParseMetrics(HttpGet(port, "/metrics")), name, labels);
    if (seen == value) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return seen;
}

size_t ThreadCount() {
  size_t n = 0;
  for ([[maybe_unused]] const auto& entry :
       std::filesystem::directory_iterator("/proc/self/task")) {
    ++n;
  }
  return n;
}

void ServerTest::SetUp() {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  vocabulary_ = testing::DefaultVocabulary();
  ASSERT_TRUE(vocabulary_);
  root_ = testing::MakeTempDir("placedb-server");
  spdlog::set_level(spdlog::level::warn);
}

void ServerTest::TearDown() {
  StopServer();
}

ServerConfig ServerTest::Config() const {
  ServerConfig config;
  config.listen = "127.0.0.1:0";
  config.metrics_listen = "";  // on only where scraped
  config.console_listen = "";  // on only where browsed
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

void ServerTest::StartServer(const ServerConfig& config, ServerDeps deps) {
  deps.vocabularies.emplace("default", vocabulary_);
  auto started = Server::Start(config, deps);
  ASSERT_TRUE(started.ok()) << started.status().ToString();
  server_ = std::move(started).value();
  channel_ = grpc::CreateChannel("127.0.0.1:" + std::to_string(server_->port()),
                                 grpc::InsecureChannelCredentials());
  stub_ = v1::PlaceDb::NewStub(channel_);
}

void ServerTest::StopServer() {
  stub_.reset();
  channel_.reset();
  server_.reset();
}

v1::MapDescription ServerTest::CreateMap(const std::string& name, const v1::MapConfig& config) {
  grpc::ClientContext context;
  v1::CreateMapRequest request;
  request.set_name(name);
  *request.mutable_config() = config;
  v1::MapDescription description;
  const grpc::Status status = stub_->CreateMap(&context, request, &description);
  EXPECT_TRUE(status.ok()) << status.error_message();
  return description;
}

grpc::Status ServerTest::CreateMapStatus(const std::string& name, const v1::MapConfig& config) {
  grpc::ClientContext context;
  v1::CreateMapRequest request;
  request.set_name(name);
  *request.mutable_config() = config;
  v1::MapDescription description;
  return stub_->CreateMap(&context, request, &description);
}

v1::MapStats ServerTest::Stats(const std::string& map) {
  grpc::ClientContext context;
  v1::GetMapRequest request;
  request.set_name(map);
  v1::MapDescription description;
  const grpc::Status status = stub_->GetMap(&context, request, &description);
  EXPECT_TRUE(status.ok()) << status.error_message();
  return description.stats();
}

grpc::Status ServerTest::Query(const std::string& map, const v1::Observation& observation,
                               v1::QueryResponse* response, size_t top_k) {
  grpc::ClientContext context;
  v1::QueryRequest request;
  request.set_map(map);
  *request.mutable_observation() = observation;
  request.mutable_options()->set_top_k(uint32_t(top_k));
  return stub_->Query(&context, request, response);
}

std::map<std::string, double> ServerTest::Scrape() {
  return ParseMetrics(HttpGet(server_->metrics_port(), "/metrics"));
}

}  // namespace placedb::server_testing
