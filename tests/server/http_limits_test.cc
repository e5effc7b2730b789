// The HTTP listeners' limits (server/net/http_endpoint.h, server/console/console.h) against a real
// server on loopback, with raw sockets (findings 4 and 5 of issue 34): refusals come from the
// headers while the body stays unread (401 for refused credentials, 413 for a Content-Length over
// the limit), chunked and length-less bodies are bounded, slow clients beyond the threads do not
// block the console or /metrics, and a client that trickles is cut off at the connection's
// deadline. Every wait is for a condition, with a deadline far beyond what it needs: a hang, not
// a timing. The ingest rate beside hostile clients is printed as `name value unit` lines.
#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "server/auth/tokens.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

using Clock = std::chrono::steady_clock;

// Generous: the server answers these in milliseconds; only a server that waits for the body (or
// for its per-read timeout, set far beyond) misses them.
constexpr auto kAnswerDeadline = std::chrono::seconds(60);
constexpr uint32_t kLongTimeoutMs = 180000;  // per read: never reached by a passing test

int Connect(int port) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(uint16_t(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (fd < 0 || connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
    ADD_FAILURE() << "cannot connect to port " << port;
    if (fd >= 0) close(fd);
    return -1;
  }
  return fd;
}

// Sends what the socket takes now (never blocking); the bytes sent, -1 when the peer is gone.
ssize_t SendSome(int fd, std::string_view data) {
  size_t sent = 0;
  while (sent < data.size()) {
    const ssize_t n = send(fd, data.data() + sent, data.size() - sent, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (n > 0) {
      sent += size_t(n);
    } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
      break;
    } else if (n < 0 && errno != EINTR) {
      return -1;
    }
  }
  return ssize_t(sent);
}

struct Answer {
  std::string bytes;    // what arrived
  bool closed = false;  // the server closed the connection (EOF or reset)
  int status() const {
    int code = 0;
    return std::sscanf(bytes.c_str(), "HTTP/1.%*d %d", &code) == 1 ? code : 0;
  }
};

// What the server sends until it closes the connection or `deadline` passes.
Answer ReadUntilClosed(int fd, Clock::time_point deadline) {
  Answer answer;
  char buffer[4096];
  while (Clock::now() < deadline) {
    pollfd entry{fd, POLLIN, 0};
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    if (poll(&entry, 1, int(std::max<int64_t>(1, left.count()))) <= 0) continue;
    const ssize_t n = recv(fd, buffer, sizeof buffer, 0);
    if (n > 0) {
      answer.bytes.append(buffer, size_t(n));
      continue;
    }
    if (n < 0 && errno == EINTR) continue;
    answer.closed = true;  // EOF, or a reset once the answer was read
    break;
  }
  return answer;
}

std::string Post(const std::string& path, uint64_t content_length,
                 const std::string& extra_headers = "") {
  return "POST " + path +
         " HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
         "Content-Length: " +
         std::to_string(content_length) + "\r\n" + extra_headers + "\r\n";
}

class HttpLimitsTest : public ServerTest {
 protected:
  ServerConfig ConsoleConfig() {
    ServerConfig config = Config();
    config.console_listen = "127.0.0.1:0";
    config.console_request_timeout_ms = kLongTimeoutMs;
    return config;
  }
  // A tokens file with an admin whose token is returned.
  std::string WriteTokens(ServerConfig* config) {
    const std::string token = *server::auth::GenerateToken();
    server::auth::TokensFile file;
    server::auth::Principal admin;
    admin.name = "admin";
    admin.token_sha256 = server::auth::HashToken(token);
    admin.admin = true;
    EXPECT_TRUE(file.Add(admin).ok());
    config->security.tokens_file = root_ + "/tokens.yaml";
    EXPECT_TRUE(file.Save(config->security.tokens_file).ok());
    return token;
  }
};

// Frames per second of one authenticated Ingest stream of `frames` RTAB-Map frames.
double IngestRate(v1::PlaceDb::Stub* stub, const std::string& map, const std::string& token,
                  int first, int frames) {
  v1::IngestHeader header;
  header.set_map(map);
  std::vector<v1::Observation> observations;
  for (int i = 0; i < frames; ++i) {
    observations.push_back(RtabmapObservation(1 + (first + i) % 80, "agent"));
  }
  const auto start = Clock::now();
  const IngestOutcome outcome = IngestWithHeader(stub, header, observations, "Bearer " + token);
  const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
  EXPECT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  return frames / seconds;
}

// Finding 4: a caller whose token is refused gets 401 from its headers, while its body is still
// on the way (the server neither reads nor parses it), and four of them sending 16 MiB bodies in
// a loop leave authenticated ingest going.
TEST_F(HttpLimitsTest, RefusedCredentialsAreAnsweredBeforeTheBodyIsRead) {
  ServerConfig config = ConsoleConfig();
  const std::string token = WriteTokens(&config);
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  const int port = server_->console_port();
  {
    grpc::ClientContext context;
    context.AddMetadata("authorization", "Bearer " + token);
    v1::CreateMapRequest request;
    request.set_name("office");
    v1::MapDescription description;
    ASSERT_TRUE(stub_->CreateMap(&context, request, &description).ok());
  }

  const uint64_t body_bytes = config.console_max_request_bytes - 1024;  // within the limit
  const std::string wrong = "Authorization: Bearer " + *server::auth::GenerateToken() + "\r\n";
  for (const std::string& credentials :
       {std::string(), wrong, std::string("Authorization: x\r\n")}) {
    SCOPED_TRACE(credentials);
    const int fd = Connect(port);
    ASSERT_GE(fd, 0);
    // The headers and the body's first 64 KiB: the rest never comes.
    ASSERT_GT(SendSome(fd, Post("/api/v1/GetMap", body_bytes, credentials) + "{\"name\": \"" +
                               std::string(64 * 1024, 'x')),
              0);
    const Answer answer = ReadUntilClosed(fd, Clock::now() + kAnswerDeadline);
    close(fd);
    EXPECT_EQ(answer.status(), 401) << answer.bytes;
    EXPECT_NE(answer.bytes.find("UNAUTHENTICATED"), std::string::npos) << answer.bytes;
    EXPECT_TRUE(answer.closed);
  }
  // A method off the console's list is refused from the headers too.
  {
    const int fd = Connect(port);
    ASSERT_GE(fd, 0);
    ASSERT_GT(SendSome(fd, Post("/api/v1/DeleteMap", body_bytes, wrong)), 0);
    const Answer answer = ReadUntilClosed(fd, Clock::now() + kAnswerDeadline);
    close(fd);
    EXPECT_EQ(answer.status(), 404) << answer.bytes;
  }

  // Authenticated ingest alone, then beside four clients posting 16 MiB bodies with bad tokens.
  const double alone = IngestRate(stub_.get(), "office", token, 0, 40);
  std::atomic<bool> stop{false};
  std::atomic<int> refused{0}, other{0};
  const std::string body = "{\"name\": \"" + std::string(body_bytes - 12, 'x') + "\"}";
  const std::string request = Post("/api/v1/GetMap", body.size(), wrong) + body;
  std::vector<std::thread> hostile;
  for (int c = 0; c < 4; ++c) {
    hostile.emplace_back([&] {
      while (!stop.load()) {
        const int fd = Connect(port);
        if (fd < 0) return;
        size_t offset = 0;
        Answer answer;
        const auto deadline = Clock::now() + kAnswerDeadline;
        // Sends while the socket takes it; stops at the answer (or when the server is gone).
        while (Clock::now() < deadline) {
          // 64 KiB at a time, as a client's writes go, and the answer looked for in between.
          const ssize_t sent =
              offset < request.size()
                  ? SendSome(fd, std::string_view(request).substr(offset, 64 * 1024))
                  : 0;
          if (sent < 0) break;
          offset += size_t(sent);
          pollfd entry{fd, POLLIN, 0};
          if (poll(&entry, 1, 100) > 0) break;
        }
        answer = ReadUntilClosed(fd, deadline);
        close(fd);
        (answer.status() == 401 ? refused : other)++;
      }
    });
  }
  // At least one refusal each before measuring: the hostile clients are at work.
  const auto deadline = Clock::now() + kAnswerDeadline;
  while (refused.load() < 4 && other.load() == 0 && Clock::now() < deadline) {
    pollfd none{-1, 0, 0};
    poll(&none, 0, 10);
  }
  const double beside = IngestRate(stub_.get(), "office", token, 40, 40);
  stop = true;
  for (std::thread& t : hostile) t.join();
  EXPECT_GE(refused.load(), 4);
  EXPECT_EQ(other.load(), 0) << "answers other than 401 to a bad token";
  std::printf("console_auth_ingest_alone %.1f frames/s\n", alone);
  std::printf("console_auth_ingest_beside_4_unauthenticated_16MiB_posters %.1f frames/s\n", beside);
  std::printf("console_auth_refused_requests %d requests\n", refused.load());
}

// Finding 5: a Content-Length over the limit is answered 413 at once, nothing of the body sent;
// a chunked body over the limit is cut off; a POST with no length has no body.
TEST_F(HttpLimitsTest, BodiesOverTheLimitAreRefusedWithoutBeingRead) {
  ServerConfig config = ConsoleConfig();
  config.console_max_request_bytes = 64 * 1024;
  config.metrics_listen = "127.0.0.1:0";
  config.metrics_request_timeout_ms = kLongTimeoutMs;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  const int console = server_->console_port();

  {
    const int fd = Connect(console);
    ASSERT_GE(fd, 0);
    ASSERT_GT(SendSome(fd, Post("/api/v1/GetMap", 100000000000ull)), 0);
    const Answer answer = ReadUntilClosed(fd, Clock::now() + kAnswerDeadline);
    close(fd);
    EXPECT_EQ(answer.status(), 413) << answer.bytes;
    EXPECT_NE(answer.bytes.find("RESOURCE_EXHAUSTED"), std::string::npos) << answer.bytes;
    EXPECT_TRUE(answer.closed);
  }
  {
    // /metrics reads no body either: its answer comes from the headers.
    const int fd = Connect(server_->metrics_port());
    ASSERT_GE(fd, 0);
    ASSERT_GT(SendSome(fd,
                       "POST /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                       "Content-Length: 100000000000\r\n\r\n"),
              0);
    const Answer answer = ReadUntilClosed(fd, Clock::now() + kAnswerDeadline);
    close(fd);
    EXPECT_EQ(answer.status(), 405) << answer.bytes;
    EXPECT_TRUE(answer.closed);
  }
  {
    // 128 KiB of chunks, never the last one: read up to the limit, then refused.
    const int fd = Connect(console);
    ASSERT_GE(fd, 0);
    std::string chunked =
        "POST /api/v1/GetMap HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        "Transfer-Encoding: chunked\r\n\r\n";
    for (int i = 0; i < 32; ++i) chunked += "1000\r\n" + std::string(4096, ' ') + "\r\n";
    ASSERT_GT(SendSome(fd, chunked), 0);
    const Answer answer = ReadUntilClosed(fd, Clock::now() + kAnswerDeadline);
    close(fd);
    EXPECT_GE(answer.status(), 400) << answer.bytes;
    EXPECT_TRUE(answer.closed);
  }
  {
    // Neither Content-Length nor chunked: no body (httplib read until the client closed).
    const int fd = Connect(console);
    ASSERT_GE(fd, 0);
    ASSERT_GT(SendSome(fd,
                       "POST /api/v1/ListMaps HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                       "Content-Type: application/json\r\n\r\n"),
              0);
    const Answer answer = ReadUntilClosed(fd, Clock::now() + kAnswerDeadline);
    close(fd);
    EXPECT_EQ(answer.status(), 200) << answer.bytes;
  }
}

// Finding 5: more slow clients than threads on both endpoints, and the console's pages and
// /metrics still answer; a client that trickles within the per-read timeout is cut off at the
// connection's deadline.
TEST_F(HttpLimitsTest, SlowClientsBeyondTheThreadsDoNotBlockTheEndpoints) {
  ServerConfig config = ConsoleConfig();
  config.console_threads = 2;
  config.metrics_listen = "127.0.0.1:0";
  config.metrics_threads = 2;
  config.metrics_request_timeout_ms = kLongTimeoutMs;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  std::vector<int> slow;
  for (const int port : {server_->console_port(), server_->metrics_port()}) {
    for (int i = 0; i < 8; ++i) {  // 4x the threads; each sends part of its request line
      const int fd = Connect(port);
      ASSERT_GE(fd, 0);
      ASSERT_GT(SendSome(fd, "GET /met"), 0);
      slow.push_back(fd);
    }
  }
  // Answered long before the slow clients' reads time out (kLongTimeoutMs).
  const auto started = Clock::now();
  const int scrape = Connect(server_->metrics_port());
  ASSERT_GE(scrape, 0);
  ASSERT_GT(SendSome(scrape, "GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"), 0);
  const Answer metrics = ReadUntilClosed(scrape, Clock::now() + kAnswerDeadline);
  close(scrape);
  EXPECT_EQ(metrics.status(), 200) << metrics.bytes.substr(0, 200);
  EXPECT_NE(metrics.bytes.find("placedb_"), std::string::npos);
  const int page = Connect(server_->console_port());
  ASSERT_GE(page, 0);
  ASSERT_GT(SendSome(page, "GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"), 0);
  const Answer index = ReadUntilClosed(page, Clock::now() + kAnswerDeadline);
  close(page);
  EXPECT_EQ(index.status(), 200) << index.bytes.substr(0, 200);
  std::printf("http_answer_beside_16_slow_clients %.3f s\n",
              std::chrono::duration<double>(Clock::now() - started).count());
  for (const int fd : slow) close(fd);
}

TEST_F(HttpLimitsTest, ATricklerIsCutOffAtTheConnectionDeadline) {
  ServerConfig config = ConsoleConfig();
  config.console_request_timeout_ms = 2000;  // per read, and for the whole connection
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  const int fd = Connect(server_->console_port());
  ASSERT_GE(fd, 0);
  ASSERT_GT(SendSome(fd, "GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "), 0);
  // A byte every 100 ms, well within the per-read timeout, until the server closes.
  const auto started = Clock::now();
  const auto deadline = started + kAnswerDeadline;
  bool closed = false;
  int trickled = 0;
  while (!closed && Clock::now() < deadline) {
    pollfd entry{fd, POLLIN, 0};
    if (poll(&entry, 1, 100) > 0) {
      char byte;
      closed = recv(fd, &byte, 1, 0) <= 0;
      continue;
    }
    closed = send(fd, "a", 1, MSG_NOSIGNAL) < 0;
    ++trickled;
  }
  close(fd);
  EXPECT_TRUE(closed) << "a client trickling " << trickled << " bytes was never cut off";
  std::printf("http_trickler_cut_after %.3f s\n",
              std::chrono::duration<double>(Clock::now() - started).count());
}

}  // namespace
}  // namespace placedb::server_testing
