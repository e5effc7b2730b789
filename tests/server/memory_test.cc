// The memory budget (limits.memory_budget_bytes) on a real server: frames and queries that do not
// fit are refused with RESOURCE_EXHAUSTED naming the budget and nothing is stored for them; the
// stream goes on; once the load is gone frames are accepted again, and the budget's in-use figure
// (also on /metrics) returns to its fixed part. The Concurrent* test also runs under TSan.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <thread>
#include <vector>

#include "server/ingest/memory_budget.h"
#include "server/rpc/frame_memory.h"
#include "tests/server/server_fixture.h"
#include "tests/test_support.h"

namespace placedb::server_testing {
namespace {

using server::MemoryBudget;
constexpr uint64_t kMiB = uint64_t(1) << 20;

// A CamVid frame scaled to 1600x1200 (under the fixture's 2 Mpx limit), as JPEG: a small message
// (well under max_message_bytes) that decodes and extracts to about 20 MiB.
v1::Observation LargeFrame(size_t index, const std::string& agent, uint64_t sequence) {
  const auto frames = testing::CamVidFrames();
  const cv::Mat image = cv::imread(frames.at(index * 40).image_path, cv::IMREAD_COLOR);
  EXPECT_FALSE(image.empty());
  cv::Mat large;
  cv::resize(image, large, cv::Size(1600, 1200));
  std::vector<uint8_t> jpeg;
  EXPECT_TRUE(cv::imencode(".jpg", large, jpeg, {cv::IMWRITE_JPEG_QUALITY, 90}));
  v1::Observation observation;
  observation.set_agent_id(agent);
  observation.set_sequence(sequence);
  observation.mutable_encoded_image()->set_data(std::string(jpeg.begin(), jpeg.end()));
  return observation;
}

bool NamesTheBudget(const std::string& message) {
  return message.find("memory budget exhausted: limits.memory_budget_bytes = ") !=
             std::string::npos &&
         message.find("retry later") != std::string::npos;
}

class ServerMemoryTest : public ServerTest {
 protected:
  // Starts a server whose budget has `variable` bytes beyond its fixed part: the process at
  // startup (given as 100 MiB: this test process's own size varies) and an 8 MiB block cache.
  // Reads (4 MiB, the fixture's max_message_bytes) leave a quarter of `variable` free for frames
  // already read.
  void StartWithBudget(uint64_t variable, uint32_t wait_ms) {
    ServerConfig config = Config();
    config.metrics_listen = "127.0.0.1:0";
    config.storage.block_cache_bytes = 8 * kMiB;
    config.limits.memory_budget_bytes = 108 * kMiB + variable;
    config.limits.memory_wait_ms = wait_ms;
    ServerDeps deps;
    deps.resident_bytes = 100 * kMiB;
    ASSERT_NO_FATAL_FAILURE(StartServer(config, deps));
    EXPECT_EQ(server_->memory_budget().fixed(), 108 * kMiB);
  }
  MemoryBudget& Budget() { return server_->memory_budget(); }
};

TEST_F(ServerMemoryTest, FramesThatDoNotFitAreRefusedNamingTheBudgetThenAcceptedOnceThereIsRoom) {
  ASSERT_NO_FATAL_FAILURE(StartWithBudget(56 * kMiB, /*wait_ms=*/0));
  CreateMap("m");
  MemoryBudget& budget = Budget();
  const uint64_t fixed = budget.fixed();
  EXPECT_EQ(budget.in_use(), fixed);

  // Other work holds all but a read (4 MiB) and the quarter reads leave free (~12 MiB): the
  // read is granted, the frame it brings (~20 MiB decoded and extracted) is not.
  const uint64_t kept = (budget.limit() - fixed) / 4;
  ASSERT_LT(kept, 16 * kMiB);
  auto load = budget.TryReserve(budget.limit() - fixed - 4 * kMiB - kept, "the test's load");
  ASSERT_TRUE(load.ok());
  const IngestOutcome refused =
      IngestAll(stub_.get(), "m", {LargeFrame(0, "a", 1), LargeFrame(1, "a", 2)});
  ASSERT_TRUE(refused.status.ok()) << refused.status.error_message();  // the stream went on
  ASSERT_EQ(refused.responses.size(), 2u);
  for (const v1::IngestResponse& response : refused.responses) {
    ASSERT_TRUE(response.has_error());
    EXPECT_EQ(response.error().code(), int(grpc::StatusCode::RESOURCE_EXHAUSTED));
    EXPECT_TRUE(NamesTheBudget(response.error().message())) << response.error().message();
    EXPECT_FALSE(response.stored());
  }
  v1::QueryResponse query;
  const grpc::Status query_status = Query("m", LargeFrame(0, "a", 3), &query);
  EXPECT_EQ(query_status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_TRUE(NamesTheBudget(query_status.error_message())) << query_status.error_message();
  EXPECT_EQ(Stats("m").places(), 0u);                 // nothing stored for them
  EXPECT_EQ(budget.in_use(), fixed + load->bytes());  // nothing leaked by the refusals

  // The load ends: the same frames are accepted (one at a time: the budget holds about two).
  load->Release();
  for (size_t frame = 0; frame < 2; ++frame) {
    const IngestOutcome accepted = IngestAll(stub_.get(), "m", {LargeFrame(frame, "a", 4 + frame)});
    ASSERT_TRUE(accepted.status.ok()) << accepted.status.error_message();
    ASSERT_EQ(accepted.responses.size(), 1u);
    EXPECT_FALSE(accepted.responses[0].has_error()) << accepted.responses[0].error().message();
    EXPECT_TRUE(accepted.responses[0].stored());
  }
  EXPECT_TRUE(Query("m", LargeFrame(0, "a", 6), &query).ok());
  EXPECT_EQ(Stats("m").places(), 2u);

  // Every reservation was returned: in use = the fixed part, here and on /metrics.
  EXPECT_EQ(budget.in_use(), fixed);
  EXPECT_EQ(budget.reservations(), 0u);
  const auto metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_memory_budget_bytes", {{"kind", "limit"}}),
            double(budget.limit()));
  EXPECT_EQ(MetricValue(metrics, "placedb_memory_budget_bytes", {{"kind", "fixed"}}),
            double(fixed));
  EXPECT_EQ(MetricValue(metrics, "placedb_memory_budget_bytes", {{"kind", "in_use"}}),
            double(fixed));
}

// Streams of large frames at once over a budget that holds two: each frame is stored or refused
// naming the budget, every frame is answered, and the budget returns to its fixed part.
TEST_F(ServerMemoryTest, ConcurrentStreamsOverASmallBudgetEitherStoreOrRefuseAndReturnIt) {
  ASSERT_NO_FATAL_FAILURE(StartWithBudget(48 * kMiB, /*wait_ms=*/100));
  CreateMap("m");
  MemoryBudget& budget = Budget();
  const uint64_t fixed = budget.fixed();

  constexpr int kStreams = 4, kFrames = 3;
  std::vector<IngestOutcome> outcomes(kStreams);
  std::vector<std::thread> streams;
  for (int s = 0; s < kStreams; ++s) {
    streams.emplace_back([&, s] {
      std::vector<v1::Observation> frames;
      for (int f = 0; f < kFrames; ++f) {
        frames.push_back(LargeFrame(size_t(f), "agent-" + std::to_string(s), uint64_t(f)));
      }
      outcomes[size_t(s)] = IngestAll(stub_.get(), "m", frames);
    });
  }
  for (std::thread& stream : streams) stream.join();
  uint64_t stored = 0;
  for (const IngestOutcome& outcome : outcomes) {
    ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
    ASSERT_EQ(outcome.responses.size(), size_t(kFrames));
    for (const v1::IngestResponse& response : outcome.responses) {
      if (response.has_error()) {
        EXPECT_EQ(response.error().code(), int(grpc::StatusCode::RESOURCE_EXHAUSTED));
        EXPECT_TRUE(NamesTheBudget(response.error().message())) << response.error().message();
      } else {
        EXPECT_TRUE(response.stored());
        ++stored;
      }
    }
  }
  EXPECT_GT(stored, 0u);
  EXPECT_EQ(Stats("m").places(), stored);
  EXPECT_EQ(budget.in_use(), fixed);
  EXPECT_EQ(budget.reservations(), 0u);
}

// The fixed part (the process at startup, the block cache) must leave room for a few messages:
// checked at startup, when it is known.
TEST_F(ServerMemoryTest, ABudgetTheProcessAndCacheFillAreRefusedAtStartup) {
  ServerConfig config = Config();
  config.storage.block_cache_bytes = 8 * kMiB;
  config.limits.memory_budget_bytes = 8 * kMiB + 4 * config.limits.max_message_bytes;
  ASSERT_TRUE(server::ValidateServerConfig(config).ok());  // the values alone are fine
  ServerDeps deps;
  deps.vocabularies.emplace("default", vocabulary_);
  auto started = Server::Start(config, deps);
  ASSERT_FALSE(started.ok());
  EXPECT_EQ(started.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(started.status().message().find("limits.memory_budget_bytes = 25165824 is too small: "
                                            "the process at startup"),
            std::string::npos)
      << started.status().message();
}

// What a frame costs the budget, from its message and image headers only.
TEST(ServerFrameMemoryTest, EstimateIsTheMessagePlusPixelsTimesTheStagesFactors) {
  v1::Observation observation = LargeFrame(0, "a", 1);
  const uint64_t pixels = 1600 * 1200;
  const uint64_t message = observation.ByteSizeLong();
  EXPECT_EQ(server::EstimateFrameBytes(observation, FeatureType::kOrb, false),
            message + pixels * (1 + 10));
  EXPECT_EQ(server::EstimateFrameBytes(observation, FeatureType::kOrb, true),
            message + pixels * (4 + 10));
  EXPECT_EQ(server::EstimateFrameBytes(observation, FeatureType::kSift, false),
            message + pixels * (1 + 240));
  // A registered 16-bit depth image at half resolution.
  observation.mutable_depth()->set_png16(EncodePng(cv::Mat(600, 800, CV_16U, cv::Scalar(1000))));
  EXPECT_EQ(server::EstimateFrameBytes(observation, FeatureType::kOrb, false),
            observation.ByteSizeLong() + pixels * (1 + 10) + 800 * 600 * 6);
  // An unreadable header counts as its bytes: decoding refuses it without allocating.
  v1::Observation broken;
  broken.mutable_encoded_image()->set_data("not an image");
  EXPECT_EQ(server::EstimateFrameBytes(broken, FeatureType::kOrb, false), broken.ByteSizeLong());
}

// limits.memory_budget_bytes: file < PLACEDB_MEMORY_BUDGET_BYTES < --memory-budget-bytes, and a
// budget too small for the block cache and a few messages is refused naming the key.
TEST(ServerMemoryConfigTest, BudgetFromFileEnvironmentAndFlagAndItsFloor) {
  const std::string dir = testing::MakeTempDir("placedb-memory-config");
  const std::string path = dir + "/placedb.yaml";
  std::ofstream(path) << "limits:\n  memory_budget_bytes: 536870912\n  memory_wait_ms: 250\n";
  std::map<std::string, std::string> env;
  auto getenv = [&](const char* name) -> const char* {
    auto it = env.find(name);
    return it == env.end() ? nullptr : it->second.c_str();
  };
  const char* file_only[] = {"placedb-server", "--config", path.c_str()};
  auto parsed = server::ParseCommandLine(3, file_only, getenv);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->config.limits.memory_budget_bytes, 512 * kMiB);
  EXPECT_EQ(parsed->config.limits.memory_wait_ms, 250u);
  env["PLACEDB_MEMORY_BUDGET_BYTES"] = "805306368";
  parsed = server::ParseCommandLine(3, file_only, getenv);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->config.limits.memory_budget_bytes, 768 * kMiB);
  const char* with_flag[] = {"placedb-server", "--config", path.c_str(), "--memory-budget-bytes",
                             "2147483648"};
  parsed = server::ParseCommandLine(5, with_flag, getenv);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->config.limits.memory_budget_bytes, 2048 * kMiB);
  // Round trip through --print-config's YAML.
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(parsed->config), &again).ok());
  EXPECT_EQ(again.limits.memory_budget_bytes, 2048 * kMiB);
  EXPECT_EQ(again.limits.memory_wait_ms, 250u);

  env["PLACEDB_MEMORY_BUDGET_BYTES"] = "1GiB";
  EXPECT_EQ(server::ParseCommandLine(3, file_only, getenv).status().code(),
            StatusCode::kInvalidArgument);
  ServerConfig small;
  small.limits.memory_budget_bytes = 100 * kMiB;  // < 64 MiB cache + 4 x 16 MiB messages
  const Status refused = server::ValidateServerConfig(small);
  EXPECT_EQ(refused.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(refused.message().find("limits.memory_budget_bytes"), std::string::npos)
      << refused.message();
}

}  // namespace
}  // namespace placedb::server_testing
