// Ingest streams are bounded and reclaimed: a stream counts against max_concurrent_streams from
// the moment it opens, header or not; the server closes streams whose header is late or that are
// idle, never one with a frame in flight; health and unary calls answer while the limit is
// exhausted, and the server's threads stay bounded.
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <filesystem>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <string>
#include <thread>
#include <vector>

#include "core/detect/detector.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

using Labels = std::map<std::string, std::string>;

// A channel with its own TCP connection: a distinct argument keeps gRPC from sharing subchannels.
std::shared_ptr<grpc::Channel> OwnConnection(int port, int index) {
  grpc::ChannelArguments arguments;
  arguments.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  arguments.SetInt("placedb.test.connection", index);
  auto channel = grpc::CreateCustomChannel("127.0.0.1:" + std::to_string(port),
                                           grpc::InsecureChannelCredentials(), arguments);
  EXPECT_TRUE(
      channel->WaitForConnected(std::chrono::system_clock::now() + std::chrono::seconds(30)));
  return channel;
}

// An Ingest call that opens and sends nothing (the async API: 500 of them need no threads here).
struct SilentStream {
  grpc::ClientContext context;
  std::unique_ptr<grpc::ClientAsyncReaderWriter<v1::IngestRequest, v1::IngestResponse>> call;
  grpc::Status status;
  bool finished = false;
};

// 500 streams that never send their header, over 50 connections, against a limit of 8: 8 are
// admitted and held until the header timeout, the other 492 are refused at once; meanwhile
// health and unary calls answer and the server holds about one thread per admitted stream.
// Then the 8 are cancelled and counted, and new streams are admitted again.
TEST_F(ServerTest, IdleStreamsAreBoundedAndReclaimed) {
  constexpr int kConnections = 50, kStreams = 500;
  constexpr uint32_t kLimit = 8;
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  config.limits.max_concurrent_streams = kLimit;
  // Long enough that the checks below run while the admitted streams are held (they take well
  // under a second); the test asserts it (placedb_streams_in_flight) rather than assuming it.
  config.limits.stream_header_timeout_ms = 5000;
  config.limits.stream_idle_timeout_ms = 5000;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  CreateMap("m");

  std::vector<std::shared_ptr<grpc::Channel>> channels;
  std::vector<std::unique_ptr<v1::PlaceDb::Stub>> stubs;
  for (int i = 0; i < kConnections; ++i) {
    channels.push_back(OwnConnection(server_->port(), i));
    stubs.push_back(v1::PlaceDb::NewStub(channels.back()));
  }
  const size_t threads_before = ThreadCount();

  // Tags: 2i = stream i started, 2i + 1 = stream i finished.
  grpc::CompletionQueue cq;
  std::vector<std::unique_ptr<SilentStream>> streams;
  for (int i = 0; i < kStreams; ++i) {
    auto stream = std::make_unique<SilentStream>();
    stream->context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(120));
    stream->call = stubs[size_t(i % kConnections)]->PrepareAsyncIngest(&stream->context, &cq);
    stream->call->StartCall(reinterpret_cast<void*>(intptr_t(2 * i)));
    stream->call->Finish(&stream->status, reinterpret_cast<void*>(intptr_t(2 * i + 1)));
    streams.push_back(std::move(stream));
  }
  std::map<grpc::StatusCode, int> outcomes;
  int finished = 0;
  auto next = [&] {
    void* tag = nullptr;
    bool ok = false;
    ASSERT_TRUE(cq.Next(&tag, &ok));
    const auto value = reinterpret_cast<intptr_t>(tag);
    if (value % 2 == 1) {
      SilentStream& stream = *streams[size_t(value / 2)];
      ASSERT_FALSE(stream.finished);
      stream.finished = true;
      ++outcomes[stream.status.error_code()];
      ++finished;
      if (stream.status.error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED &&
          outcomes[grpc::StatusCode::RESOURCE_EXHAUSTED] == 1) {
        EXPECT_NE(stream.status.error_message().find("limits.max_concurrent_streams = 8"),
                  std::string::npos)
            << stream.status.error_message();
      }
    }
  };
  // Every refusal comes at once; the admitted streams are held.
  while (outcomes[grpc::StatusCode::RESOURCE_EXHAUSTED] < kStreams - int(kLimit) &&
         finished < kStreams) {
    ASSERT_NO_FATAL_FAILURE(next());
  }
  EXPECT_EQ(outcomes[grpc::StatusCode::RESOURCE_EXHAUSTED], kStreams - int(kLimit));

  // While the limit is exhausted: bounded threads, health, unary calls, and one more stream is
  // refused.
  const size_t threads_during = ThreadCount();
  std::string serving;
  EXPECT_TRUE(HealthCheck(channel_, &serving).ok());
  EXPECT_EQ(serving, std::string("\x08\x01", 2));  // SERVING
  {
    grpc::ClientContext context;
    v1::ListMapsResponse maps;
    EXPECT_TRUE(stub_->ListMaps(&context, v1::ListMapsRequest(), &maps).ok());
    EXPECT_EQ(maps.maps_size(), 1);
  }
  {
    grpc::ClientContext context;
    v1::ServerInfo info;
    EXPECT_TRUE(stub_->GetServerInfo(&context, v1::GetServerInfoRequest(), &info).ok());
  }
  v1::QueryResponse query;
  EXPECT_TRUE(Query("m", RtabmapObservation(1, "q"), &query).ok());
  {
    grpc::ClientContext context;
    auto extra = stub_->Ingest(&context);
    EXPECT_EQ(extra->Finish().error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  }
  // Still held after all that (so the checks above ran while the limit was exhausted).
  auto metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_streams_in_flight"), kLimit);
  EXPECT_EQ(finished, kStreams - int(kLimit));
  // One handler thread per admitted stream, plus a few of gRPC's pollers and the scrape's
  // worker; without the early admission a refused-late stream holds a thread up to gRPC's
  // thread quota (max_concurrent_streams + max_concurrent_unary + 8 = 80 here).
  EXPECT_LE(threads_during, threads_before + kLimit + 12)
      << "before " << threads_before << ", during " << threads_during;

  // The admitted streams are cancelled at the header timeout.
  while (finished < kStreams) ASSERT_NO_FATAL_FAILURE(next());
  EXPECT_EQ(outcomes[grpc::StatusCode::CANCELLED], int(kLimit));
  EXPECT_EQ(outcomes.size(), 2u);
  metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_ingest_streams_closed_total",
                        Labels{{"reason", "header_timeout"}}),
            kLimit);
  EXPECT_EQ(MetricValue(metrics, "placedb_ingest_streams_closed_total",
                        Labels{{"reason", "idle_timeout"}}),
            0);
  EXPECT_EQ(AwaitMetric(server_->metrics_port(), "placedb_streams_in_flight", {}, 0), 0);
  metrics = Scrape();
  // Refused by the handler (the rest of the burst may be refused by gRPC's thread quota before
  // reaching it, which the metric does not see).
  const double refused_here =
      MetricValue(metrics, "placedb_rpc_requests_total",
                  Labels{{"method", "Ingest"}, {"code", "RESOURCE_EXHAUSTED"}});
  EXPECT_GE(refused_here, 2);  // at least the extra stream and one of the burst
  EXPECT_LE(refused_here, kStreams - int(kLimit) + 1);
  std::printf(
      "[server] %d idle streams over %d connections, limit %u: threads %zu before, %zu "
      "while held, %zu after\n",
      kStreams, kConnections, kLimit, threads_before, threads_during, ThreadCount());

  // Reclaimed: new streams are admitted and work.
  const IngestOutcome outcome = IngestAll(stubs[0].get(), "m", {RtabmapObservation(2, "a")});
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), 1u);
  EXPECT_TRUE(outcome.responses[0].stored());
  cq.Shutdown();
  void* tag;
  bool ok;
  while (cq.Next(&tag, &ok)) {
  }
}

// A stream that sent its header and then nothing is closed as idle; a stream whose frame is being
// processed for longer than the idle timeout is not. No timing is assumed: the idle stream opens
// after the busy stream's frame was read, so by the time the watchdog closes it the busy stream
// has been quiet longer, and the watchdog has looked at it in the same pass or an earlier one.
TEST_F(ServerTest, IdleStreamIsClosedButConcurrentFrameInFlightKeepsItsStream) {
  auto gate = std::make_shared<GateDetector>();
  ServerDeps deps;
  deps.detector = gate;
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  config.limits.stream_header_timeout_ms = 60000;
  config.limits.stream_idle_timeout_ms = 1000;
  ASSERT_NO_FATAL_FAILURE(StartServer(config, deps));
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);
  CreateMap("m", server_boxes);

  // The busy stream: its frame waits in the detector.
  grpc::ClientContext busy_context;
  auto busy = stub_->Ingest(&busy_context);
  v1::IngestRequest header;
  header.mutable_header()->set_map("m");
  ASSERT_TRUE(busy->Write(header));
  v1::IngestRequest frame;
  *frame.mutable_observation() = RtabmapObservation(1, "a");
  ASSERT_TRUE(busy->Write(frame));
  gate->WaitEntered();

  // The idle stream: a header, then nothing.
  grpc::ClientContext idle_context;
  auto idle = stub_->Ingest(&idle_context);
  ASSERT_TRUE(idle->Write(header));
  v1::IngestResponse response;
  EXPECT_FALSE(idle->Read(&response));
  const grpc::Status idle_status = idle->Finish();
  EXPECT_EQ(idle_status.error_code(), grpc::StatusCode::CANCELLED) << idle_status.error_message();

  auto metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_ingest_streams_closed_total",
                        Labels{{"reason", "idle_timeout"}}),
            1);
  EXPECT_EQ(AwaitMetric(server_->metrics_port(), "placedb_streams_in_flight", {}, 1),
            1);  // the busy one

  // The busy stream is still open: its frame is answered and stored, and it ends OK.
  ASSERT_TRUE(busy->WritesDone());
  gate->Open();
  ASSERT_TRUE(busy->Read(&response));
  EXPECT_TRUE(response.stored()) << response.error().message();
  EXPECT_FALSE(busy->Read(&response));
  const grpc::Status busy_status = busy->Finish();
  EXPECT_TRUE(busy_status.ok()) << busy_status.error_message();
  metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_ingest_streams_closed_total",
                        Labels{{"reason", "idle_timeout"}}),
            1);
  EXPECT_EQ(MetricValue(metrics, "placedb_ingest_streams_closed_total",
                        Labels{{"reason", "header_timeout"}}),
            0);
}

// A client that sends frames but takes no answers: once HTTP/2 flow control holds the server's
// answer, the stream is busy (frames in flight), not idle, and is closed as write_timeout.
TEST_F(ServerTest, ClientThatTakesNoAnswersIsClosed) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  config.limits.stream_header_timeout_ms = 60000;
  config.limits.stream_idle_timeout_ms = 1000;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  CreateMap("m");
  // A small receive window that does not grow: a few answers fill it.
  grpc::ChannelArguments arguments;
  arguments.SetInt(GRPC_ARG_HTTP2_BDP_PROBE, 0);
  arguments.SetInt(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES, 1024);
  arguments.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  auto channel = grpc::CreateCustomChannel("127.0.0.1:" + std::to_string(server_->port()),
                                           grpc::InsecureChannelCredentials(), arguments);
  auto stub = v1::PlaceDb::NewStub(channel);
  grpc::ClientContext context;
  auto stream = stub->Ingest(&context);
  v1::IngestRequest request;
  request.mutable_header()->set_map("m");
  ASSERT_TRUE(stream->Write(request));
  // A tiny image: cheap to process, answered with a rejection (too few static descriptors).
  cv::Mat image(64, 64, CV_8UC1);
  cv::randu(image, 0, 255);
  *request.mutable_observation() = v1::Observation();
  request.mutable_observation()->set_agent_id("a");
  request.mutable_observation()->mutable_encoded_image()->set_data(EncodePng(image));
  int written = 0;
  while (written < 100000 && stream->Write(request)) ++written;
  // Writing fails once the server has closed the stream; the answers that got through must be
  // read before Finish() (the synchronous client's Finish waits for unread messages).
  v1::IngestResponse answer;
  int answers = 0;
  while (stream->Read(&answer)) ++answers;
  EXPECT_LT(answers, written);
  const grpc::Status status = stream->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED) << status.error_message();
  const auto metrics = Scrape();
  EXPECT_EQ(MetricValue(metrics, "placedb_ingest_streams_closed_total",
                        Labels{{"reason", "write_timeout"}}),
            1);
  EXPECT_EQ(MetricValue(metrics, "placedb_ingest_streams_closed_total",
                        Labels{{"reason", "idle_timeout"}}),
            0);
  std::printf(
      "[server] a client that reads nothing: %d frames written, %d answers taken before the "
      "server closed it\n",
      written, answers);
}

}  // namespace
}  // namespace placedb::server_testing
