// Log injection (finding 7 of issue 34) on a real server over loopback: client-supplied strings
// holding newlines, carriage returns, terminal escapes and U+2028 (an agent id, a
// vocabulary name echoed by an error, a snapshot id, a map name) reach the log only escaped
// (core/base/text.h, ForLog): every record the server writes is one line.
// (Invalid UTF-8 cannot arrive here: protobuf refuses it in string fields; TextTest covers it.)
#include <gtest/gtest.h>
#include <spdlog/sinks/base_sink.h>
#include <spdlog/spdlog.h>

#include <chrono>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

// Keeps every record as the default logger's pattern formats it (the line a log file gets).
class CaptureSink final : public spdlog::sinks::base_sink<std::mutex> {
 public:
  std::vector<std::string> records() {
    std::lock_guard lock(mutex_);
    return records_;
  }

 protected:
  void sink_it_(const spdlog::details::log_msg& message) override {
    spdlog::memory_buf_t formatted;
    formatter_->format(message, formatted);
    records_.emplace_back(formatted.data(), formatted.size());
  }
  void flush_() override {}

 private:
  std::vector<std::string> records_;
};

class LogInjectionTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    previous_ = spdlog::default_logger();
    sink_ = std::make_shared<CaptureSink>();
    auto logger = std::make_shared<spdlog::logger>("capture", sink_);
    logger->set_level(spdlog::level::info);
    spdlog::set_default_logger(logger);  // before the server starts: no thread logs meanwhile
  }
  void TearDown() override {
    ServerTest::TearDown();  // the server stopped: no thread logs any more
    spdlog::set_default_logger(previous_);
  }

  // Waits (30 s at most: a hang, not a timing) for a record holding `text`.
  bool AwaitRecord(const std::string& text) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    do {
      for (const std::string& record : sink_->records()) {
        if (record.find(text) != std::string::npos) return true;
      }
      std::this_thread::yield();
    } while (std::chrono::steady_clock::now() < deadline);
    return false;
  }

  std::shared_ptr<spdlog::logger> previous_;
  std::shared_ptr<CaptureSink> sink_;
};

TEST_F(LogInjectionTest, ClientStringsReachTheLogEscapedOnOneLine) {
  StartServer(Config());
  const std::string forged = "\n2030-01-01T00:00:00.000+0000 info FORGED\r\x1b[2J\xe2\x80\xa8";
  const std::string escaped = "\\n2030-01-01T00:00:00.000+0000 info FORGED\\r\\x1b[2J\\u2028";

  // An agent id: logged when the stream closes.
  CreateMap("lab");
  std::vector<v1::Observation> frames;
  for (int i = 1; i <= 3; ++i) frames.push_back(RtabmapObservation(i, "robot" + forged));
  const IngestOutcome ingested = IngestAll(stub_.get(), "lab", frames);
  EXPECT_TRUE(ingested.status.ok()) << ingested.status.error_message();
  // A vocabulary name, echoed by the error the rpc error line logs.
  v1::MapConfig config;
  config.set_vocabulary("nope" + forged);
  EXPECT_EQ(CreateMapStatus("other", config).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  // A snapshot id and a map name, refused.
  v1::DeleteSnapshotRequest del;
  del.set_id("snap" + forged);
  v1::DeleteSnapshotResponse deleted;
  grpc::ClientContext delete_context;
  EXPECT_FALSE(stub_->DeleteSnapshot(&delete_context, del, &deleted).ok());
  EXPECT_EQ(CreateMapStatus("map" + forged).error_code(), grpc::StatusCode::INVALID_ARGUMENT);

  // The records were written, escaped...
  EXPECT_TRUE(AwaitRecord("agent=robot" + escaped)) << "no ingest stream closed record";
  EXPECT_TRUE(AwaitRecord("'nope" + escaped + "'")) << "no CreateMap error record";
  EXPECT_TRUE(AwaitRecord("method=DeleteSnapshot")) << "no DeleteSnapshot error record";
  EXPECT_TRUE(AwaitRecord("map name \\\"map\\\\x0a")) << "no CreateMap name error record";
  // ...and no record holds a raw line break, escape or invalid byte from the client.
  const std::vector<std::string> records = sink_->records();
  ASSERT_FALSE(records.empty());
  for (const std::string& record : records) {
    ASSERT_FALSE(record.empty());
    EXPECT_EQ(record.find('\n'), record.size() - 1) << record;  // only the record's own end
    EXPECT_EQ(record.find('\r'), std::string::npos) << record;
    EXPECT_EQ(record.find('\x1b'), std::string::npos) << record;
    EXPECT_EQ(record.find("\xe2\x80\xa8"), std::string::npos) << record;  // LINE SEPARATOR
  }
}

}  // namespace
}  // namespace placedb::server_testing
