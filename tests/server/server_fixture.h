// What every service test (tests/server/<rpc>_test.cc) shares: the ServerTest fixture (an
// in-process server on a loopback port, a real RocksDB in a temp directory, the default
// vocabulary), frames built from the real datasets (RTAB-Map loop, CamVid, RGB-D) sent as image
// bytes, one Ingest stream as an agent runs it, the Debian SIFT vocabulary and a /metrics scraper.
#pragma once

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/detect/detector.h"
#include "core/vocabulary/float_vocabulary.h"
#include "core/vocabulary/vocabulary.h"
#include "proto/placedb.grpc.pb.h"
#include "server/config.h"
#include "server/server.h"
#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace placedb::server_testing {

namespace v1 = ::placedb::v1;
using server::Server;
using server::ServerConfig;
using server::ServerDeps;

// ---- Frames -------------------------------------------------------------------------------------

std::string EncodePng(const cv::Mat& image);

// The JPEG file at `path` as an observation of `agent` (timestamp: sequence x 100 ms).
v1::Observation JpegObservation(const std::string& path, const std::string& agent,
                                uint64_t sequence);
// RTAB-Map loop frame `frame` (1-based, sequence = frame), with a pose on every 5th frame.
v1::Observation RtabmapObservation(int frame, const std::string& agent);
// Features of `observation`'s JPEG exactly as the server computes them for a default map.
v1::Features FeaturesOf(const v1::Observation& observation);
// SIFT of `observation`'s JPEG exactly as the server computes it for a default SIFT map.
v1::SiftFeatures SiftFeaturesOf(const v1::Observation& observation);
// An rgbd-people / slambook2 frame: the colour image as PNG bytes, depth as a 16-bit PNG (mm).
v1::Observation RgbdObservation(const rgbd::RgbdFrame& frame, const std::string& agent,
                                uint64_t sequence);

// ---- Ingest streams -----------------------------------------------------------------------------

// A server-side detector that blocks until released: holds a frame in the middle of the pipeline.
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

// grpc.health.v1.Health/Check of the whole server, through the generic stub (no health stubs
// are generated here). *serving = the response's raw bytes.
grpc::Status HealthCheck(const std::shared_ptr<grpc::Channel>& channel, std::string* serving);

struct IngestOutcome {
  std::vector<v1::IngestResponse> responses;
  grpc::Status status;
};

// One Ingest stream: writes the header and every observation from one thread while reading
// responses on this one, as a real agent does; `authorization` ("" = none) is sent as metadata.
IngestOutcome IngestWithHeader(v1::PlaceDb::Stub* stub, const v1::IngestHeader& header,
                               const std::vector<v1::Observation>& observations,
                               const std::string& authorization = "");
// The same with a header naming only `map` (and `matches` if given).
IngestOutcome IngestAll(v1::PlaceDb::Stub* stub, const std::string& map,
                        const std::vector<v1::Observation>& observations,
                        const v1::MatchOptions* matches = nullptr);

// ---- SIFT maps ----------------------------------------------------------------------------------

// The Debian SIFT vocabulary (the sift_vocabulary ctest fixture builds it), loaded once.
using placedb::testing::SiftVocabulary;
// The server's configuration with the SIFT vocabulary as "sift" (preloaded by SiftDeps()).
ServerConfig WithSift(ServerConfig config);
ServerDeps SiftDeps();
v1::MapConfig SiftMapConfig();  // a map on "sift" with SIFT features

// ---- Metrics scraping ---------------------------------------------------------------------------

// `headers`: extra header lines, each ending in "\r\n".
std::string HttpGet(int port, const std::string& path, const std::string& headers = "");
// Prometheus text format -> "name{k=v,...}" (labels sorted) -> value.
std::map<std::string, double> ParseMetrics(const std::string& reply);
// The value of one series, NaN if absent.
double MetricValue(const std::map<std::string, double>& metrics, const std::string& name,
                   const std::map<std::string, std::string>& labels = {});

// Polls /metrics until `name{labels}` equals `value` (a call's end reaches the client a moment
// before its handler has unlisted it); the last value seen. 30 s at most: a hang, not a timing.
double AwaitMetric(int port, const std::string& name,
                   const std::map<std::string, std::string>& labels, double value);
// Threads of this process (the server runs in it).
size_t ThreadCount();

// ---- Fixture ------------------------------------------------------------------------------------

class ServerTest : public ::testing::Test {
 protected:
  void SetUp() override;
  void TearDown() override;

  // Loopback on a free port, metrics off, two workers, the default vocabulary and tight limits.
  ServerConfig Config() const;
  // Starts the server with `deps` plus the default vocabulary, and connects stub_ to it.
  void StartServer(const ServerConfig& config, ServerDeps deps = {});
  void StopServer();

  v1::MapDescription CreateMap(const std::string& name, const v1::MapConfig& config = {});
  grpc::Status CreateMapStatus(const std::string& name, const v1::MapConfig& config = {});
  v1::MapStats Stats(const std::string& map);
  grpc::Status Query(const std::string& map, const v1::Observation& observation,
                     v1::QueryResponse* response, size_t top_k = 10);
  std::map<std::string, double> Scrape();  // /metrics (config.metrics_listen must be on)

  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
  std::unique_ptr<Server> server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::PlaceDb::Stub> stub_;
};

}  // namespace placedb::server_testing
