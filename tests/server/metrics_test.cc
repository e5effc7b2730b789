// The /metrics endpoint (Prometheus text over HTTP): what was sent, counted by method, code,
// map and stage; a deleted map's series go away; slow HTTP clients cannot block it; only its
// path and GET are served; basic auth headers are parsed strictly; a port in use is an error.
#include "server/metrics.h"

#include <arpa/inet.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cmath>
#include <map>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

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

// A loopback TCP connection to `port` whose reads give up after `receive_timeout_s`; -1 if it
// cannot connect.
int Connect(int port, int receive_timeout_s) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return -1;
  timeval timeout{};
  timeout.tv_sec = receive_timeout_s;
  setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(uint16_t(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
    close(fd);
    return -1;
  }
  return fd;
}

// A client that starts a request and never finishes its header.
int OpenSlowConnection(int port) {
  const int fd = Connect(port, 60);
  const std::string partial = "GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\n";
  if (fd >= 0) {
    EXPECT_EQ(send(fd, partial.data(), partial.size(), 0), ssize_t(partial.size()));
  }
  return fd;
}

// Reads until the server closes the connection. False when a read gave up (timed out) first.
bool ReadUntilClosed(int fd, std::string* reply) {
  char buffer[4096];
  while (true) {
    const ssize_t n = recv(fd, buffer, sizeof buffer, 0);
    if (n > 0) {
      reply->append(buffer, size_t(n));
      continue;
    }
    if (n == 0 || errno == ECONNRESET) return true;
    return false;  // EAGAIN: the receive timeout
  }
}

// Slow clients hold at most metrics_threads - 1 of the endpoint's workers: a scrape still gets
// through while they are open. (With one worker, the scrape waits for the first slow client's
// request timeout, here far longer than the scrape's own receive timeout.)
TEST_F(ServerTest, MetricsEndpointServesWhileSlowClientsHoldConnections) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  config.metrics_threads = 4;
  config.metrics_request_timeout_ms = 120000;  // the slow clients stay for the whole test
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  std::vector<int> slow;
  for (int i = 0; i < config.metrics_threads - 1; ++i) {
    slow.push_back(OpenSlowConnection(server_->metrics_port()));
    ASSERT_GE(slow.back(), 0);
  }
  for (int round = 0; round < 3; ++round) {
    const int fd = Connect(server_->metrics_port(), 30);
    ASSERT_GE(fd, 0);
    const std::string request = "GET /metrics HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n";
    ASSERT_EQ(send(fd, request.data(), request.size(), 0), ssize_t(request.size()));
    std::string reply;
    EXPECT_TRUE(ReadUntilClosed(fd, &reply)) << "the scrape was blocked by the slow clients";
    close(fd);
    const auto metrics = ParseMetrics(reply);
    EXPECT_EQ(MetricValue(metrics, "placedb_streams_in_flight"), 0);
  }
  for (int fd : slow) close(fd);
}

// A client that never finishes its request is disconnected after metrics_request_timeout_ms.
TEST_F(ServerTest, MetricsEndpointClosesSlowConnections) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  config.metrics_request_timeout_ms = 300;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  const int fd = OpenSlowConnection(server_->metrics_port());
  ASSERT_GE(fd, 0);
  std::string reply;
  EXPECT_TRUE(ReadUntilClosed(fd, &reply)) << "still open after 60 s";
  close(fd);
  EXPECT_EQ(reply.find("placedb_"), std::string::npos) << reply;  // never served
  EXPECT_FALSE(Scrape().empty());                                 // and the endpoint goes on
}

// Sends `request` on a new connection and reads the whole answer.
std::string Exchange(int port, const std::string& request) {
  const int fd = Connect(port, 30);
  EXPECT_GE(fd, 0);
  if (fd < 0) return "";
  EXPECT_EQ(send(fd, request.data(), request.size(), 0), ssize_t(request.size()));
  std::string reply;
  EXPECT_TRUE(ReadUntilClosed(fd, &reply));
  close(fd);
  return reply;
}

// The status code of an HTTP answer ("200"); empty when there is none.
std::string HttpCode(const std::string& reply) {
  return reply.rfind("HTTP/1.", 0) == 0 && reply.size() > 12 ? reply.substr(9, 3) : "";
}

// A plaintext endpoint on `listen` serving /metrics.
server::Metrics::Endpoint PlainEndpoint(const std::string& listen) {
  server::Metrics::Endpoint endpoint;
  endpoint.listen = listen;
  endpoint.path = "/metrics";
  return endpoint;
}

// Only the configured path, and only GET; the scrape refreshes first.
TEST(MetricsEndpointTest, ServesItsPathToGetOnly) {
  server::Metrics metrics;
  int refreshes = 0;
  ASSERT_TRUE(metrics.Serve(PlainEndpoint("127.0.0.1:0"), [&refreshes] { ++refreshes; }).ok());
  const int port = metrics.port();
  ASSERT_GT(port, 0);
  const std::string scrape = Exchange(port, "GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n");
  EXPECT_EQ(HttpCode(scrape), "200");
  EXPECT_NE(scrape.find("# TYPE placedb_queue_depth gauge"), std::string::npos) << scrape;
  EXPECT_NE(scrape.find("Connection: close"), std::string::npos) << scrape;  // no keep-alive
  EXPECT_EQ(refreshes, 1);
  EXPECT_EQ(HttpCode(Exchange(port, "GET /metrics?x=1 HTTP/1.0\r\n\r\n")), "200");
  EXPECT_EQ(HttpCode(Exchange(port, "GET /other HTTP/1.0\r\n\r\n")), "404");
  EXPECT_EQ(HttpCode(Exchange(port, "GET /metrics/x HTTP/1.0\r\n\r\n")), "404");
  const std::string post = Exchange(port, "POST /metrics HTTP/1.0\r\nContent-Length: 3\r\n\r\nabc");
  EXPECT_EQ(HttpCode(post), "405");
  EXPECT_NE(post.find("Allow: GET"), std::string::npos) << post;
  EXPECT_EQ(refreshes, 2);  // the refused requests did not collect
  metrics.StopServing();
  EXPECT_EQ(metrics.port(), 0);
}

// Stopping right after serving ends the accept loop: httplib ignores stop() until its loop has
// marked itself running, a race that once hung a server's shutdown. A watchdog turns a hang
// into a failure instead of a test timeout.
TEST(MetricsEndpointTest, StopsRightAfterServing) {
  std::atomic<int> rounds_done = 0;
  std::thread watchdog([&rounds_done] {
    for (int waited_s = 0; rounds_done.load() >= 0; ++waited_s) {
      if (waited_s >= 120) {
        std::fprintf(stderr, "Stop() hung after %d rounds\n", rounds_done.load());
        std::_Exit(1);
      }
      std::this_thread::sleep_for(std::chrono::seconds(1));
    }
  });
  for (int round = 0; round < 300; ++round) {
    server::Metrics metrics;
    ASSERT_TRUE(metrics.Serve(PlainEndpoint("127.0.0.1:0"), nullptr).ok());
    metrics.StopServing();
    EXPECT_EQ(metrics.port(), 0);
    rounds_done = round + 1;
  }
  EXPECT_EQ(rounds_done.load(), 300);
  rounds_done = -1;
  watchdog.join();
}

// A port another endpoint holds is IO_ERROR (not shared), and the first one goes on serving.
TEST(MetricsEndpointTest, APortInUseIsAnIoError) {
  server::Metrics first;
  ASSERT_TRUE(first.Serve(PlainEndpoint("127.0.0.1:0"), nullptr).ok());
  server::Metrics second;
  const std::string listen = "127.0.0.1:" + std::to_string(first.port());
  const Status status = second.Serve(PlainEndpoint(listen), nullptr);
  EXPECT_EQ(status.code(), StatusCode::kIoError) << status.ToString();
  EXPECT_NE(status.message().find(listen), std::string::npos) << status.ToString();
  EXPECT_EQ(second.port(), 0);
  EXPECT_EQ(HttpCode(Exchange(first.port(), "GET /metrics HTTP/1.0\r\n\r\n")), "200");
  EXPECT_EQ(second.Serve(PlainEndpoint("127.0.0.1"), nullptr).code(), StatusCode::kInvalidArgument);
}

// Basic auth: only a well-formed "Basic base64(user:password)" reaches the check, with the
// scraper's address; everything else is 401 with the challenge.
TEST(MetricsEndpointTest, BasicAuthIsParsedStrictly) {
  server::Metrics metrics;
  std::vector<std::tuple<std::string, std::string, std::string>> asked;
  server::Metrics::Endpoint endpoint = PlainEndpoint("127.0.0.1:0");
  endpoint.authorize = [&asked](const std::string& peer, const std::string& user,
                                const std::string& password) {
    asked.emplace_back(peer, user, password);
    return password == "secret" || user == "a";
  };
  ASSERT_TRUE(metrics.Serve(endpoint, nullptr).ok());
  const int port = metrics.port();
  auto status = [port](const std::string& authorization) {
    const std::string reply = Exchange(port, "GET /metrics HTTP/1.0\r\n" + authorization + "\r\n");
    const std::string code = HttpCode(reply);
    if (code == "401") {
      EXPECT_NE(reply.find("WWW-Authenticate: Basic realm=\"placedb\""), std::string::npos)
          << reply;
    }
    return code;
  };
  EXPECT_EQ(status(""), "401");
  EXPECT_EQ(status("Authorization: Bearer cHJvbTpzZWNyZXQ=\r\n"), "401");
  EXPECT_EQ(status("Authorization: Basic\r\n"), "401");
  EXPECT_EQ(status("Authorization: Basic !!!!\r\n"), "401");
  EXPECT_EQ(status("Authorization: Basic cHJvbTpzZWNyZXQ\r\n"), "401");   // length not 4n
  EXPECT_EQ(status("Authorization: Basic cHJv=TpzZWNyZXQ=\r\n"), "401");  // '=' inside
  EXPECT_EQ(status("Authorization: Basic cHJvbTpzZWNyZXQ===\r\n"), "401");
  EXPECT_EQ(status("Authorization: Basic cHJvbXNlY3JldA==\r\n"), "401");  // "promsecret": no ':'
  EXPECT_TRUE(asked.empty());  // none of those reached the check
  EXPECT_EQ(status("Authorization: Basic cHJvbTp3cm9uZw==\r\n"), "401");  // prom:wrong
  EXPECT_EQ(status("Authorization: Basic cHJvbTpzZWNyZXQ=\r\n"), "200");  // prom:secret
  EXPECT_EQ(status("Authorization: basic  cHJvbTpzZWNyZXQ=\r\n"), "200");
  EXPECT_EQ(status("Authorization: Basic cHJvbTpzZTpjcmV0\r\n"), "401");  // prom:se:cret
  // No padding, two and one padding characters: the password has no trailing bytes.
  EXPECT_EQ(status("Authorization: Basic YTpi\r\n"), "200");      // a:b
  EXPECT_EQ(status("Authorization: Basic YTpiYw==\r\n"), "200");  // a:bc
  EXPECT_EQ(status("Authorization: Basic YTpiY2Q=\r\n"), "200");  // a:bcd
  using Asked = std::tuple<std::string, std::string, std::string>;
  ASSERT_EQ(asked.size(), 7u);
  EXPECT_EQ(std::get<0>(asked[0]).rfind("ipv4:127.0.0.1:", 0), 0u) << std::get<0>(asked[0]);
  auto without_peer = [](const Asked& a) { return std::make_pair(std::get<1>(a), std::get<2>(a)); };
  EXPECT_EQ(without_peer(asked[0]), std::make_pair(std::string("prom"), std::string("wrong")));
  EXPECT_EQ(without_peer(asked[1]), std::make_pair(std::string("prom"), std::string("secret")));
  EXPECT_EQ(without_peer(asked[2]), std::make_pair(std::string("prom"), std::string("secret")));
  EXPECT_EQ(without_peer(asked[3]), std::make_pair(std::string("prom"), std::string("se:cret")));
  EXPECT_EQ(without_peer(asked[4]), std::make_pair(std::string("a"), std::string("b")));
  EXPECT_EQ(without_peer(asked[5]), std::make_pair(std::string("a"), std::string("bc")));
  EXPECT_EQ(without_peer(asked[6]), std::make_pair(std::string("a"), std::string("bcd")));
}

}  // namespace
}  // namespace placedb::server_testing
