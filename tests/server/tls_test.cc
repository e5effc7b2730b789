// TLS and mutual TLS on the gRPC port and on /metrics, the TLS files' startup errors, the
// certificate names of a mutual-TLS caller, the clients' --cert/--key, and the loopback-only
// default of a server that does not authenticate its callers. Certificates are made at test time
// with the openssl CLI (tests/tls_certificates.h); the openssl CLI is also the TLS 1.1 client.
#include <arpa/inet.h>
#include <grpcpp/generic/async_generic_service.h>
#include <grpcpp/generic/generic_stub.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <spdlog/sinks/base_sink.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <future>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <vector>

#include "client/cli.h"
#include "client/connection.h"
#include "server/net/transport_security.h"
#include "tests/server/server_fixture.h"
#include "tests/tls_certificates.h"

namespace placedb::server_testing {
namespace {

using client::Connection;
using client::ConnectionOptions;
using server::TlsSettings;
using testing::SharedTestCertificates;
using testing::TestCertificates;

TlsSettings ServerTls(bool mutual) {
  const TestCertificates& c = SharedTestCertificates();
  return {.cert_file = c.server_cert,
          .key_file = c.server_key,
          .client_ca_file = mutual ? c.ca_cert : ""};
}

// GetServerInfo through a client::Connection to localhost:port with `options`' TLS settings.
grpc::Status GetInfo(int port, ConnectionOptions options) {
  options.address = "localhost:" + std::to_string(port);
  options.timeout_s = 10;
  std::string error;
  std::optional<Connection> connection = Connection::Open(options, &error);
  if (!connection) return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, error);
  v1::ServerInfo info;
  auto context = connection->NewContext();
  return connection->stub()->GetServerInfo(context.get(), {}, &info);
}

ConnectionOptions Trusting(const std::string& ca) {
  ConnectionOptions options;
  options.tls = true;
  options.ca_cert = ca;
  return options;
}
ConnectionOptions Presenting(const std::string& ca, const std::string& cert,
                             const std::string& key) {
  ConnectionOptions options = Trusting(ca);
  options.cert = cert;
  options.key = key;
  return options;
}

class TlsTest : public ServerTest {
 protected:
  // TLS (mutual or not) on the gRPC port, and metrics over HTTPS on a free loopback port.
  ServerConfig HttpsMetricsConfig(bool mutual) const {
    ServerConfig config = Config();
    config.tls = ServerTls(mutual);
    config.metrics_listen = "127.0.0.1:0";
    config.metrics_tls = true;
    return config;
  }
  // A tokens file with one admin principal, "ops" (token "test"); its path.
  std::string AdminTokensFile() const {
    const std::string tokens = root_ + "/tokens.yaml";
    std::ofstream(tokens) << "principals:\n  - name: ops\n    token_sha256: "
                             "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08\n"
                             "    admin: true\n";
    return tokens;
  }
  // `openssl s_client` to 127.0.0.1:port with `arguments`, sending `input`; its exit status.
  int SClient(int port, const std::string& arguments, const std::string& input,
              std::string* output) {
    const std::string input_file = root_ + "/s_client-input";
    std::ofstream(input_file) << input;
    return testing::RunShell("timeout 30 openssl s_client -connect 127.0.0.1:" +
                                 std::to_string(port) + " " + arguments + " < '" + input_file + "'",
                             output);
  }
  // GET /metrics over HTTPS with openssl s_client; returns what it printed.
  std::string HttpsGet(int port, const std::string& client_arguments) {
    std::string output;
    SClient(port,
            "-quiet -verify_return_error -CAfile '" + SharedTestCertificates().ca_cert + "' " +
                client_arguments,
            "GET /metrics HTTP/1.0\r\nHost: localhost\r\n\r\n", &output);
    return output;
  }
};

TEST_F(TlsTest, TlsServerAnswersClientsThatTrustItsCaOnly) {
  const TestCertificates& c = SharedTestCertificates();
  ServerConfig config = Config();
  config.tls = ServerTls(/*mutual=*/false);
  StartServer(config);
  const int port = server_->port();

  EXPECT_TRUE(GetInfo(port, Trusting(c.ca_cert)).ok());
  // A plaintext client gets no answer from a TLS port.
  EXPECT_EQ(GetInfo(port, ConnectionOptions{}).error_code(), grpc::StatusCode::UNAVAILABLE);
  // A client that does not trust the server's CA refuses the handshake.
  EXPECT_EQ(GetInfo(port, Trusting(c.other_ca_cert)).error_code(), grpc::StatusCode::UNAVAILABLE);
  // Without mutual TLS a client certificate is not needed, and one is accepted.
  EXPECT_TRUE(GetInfo(port, Presenting(c.ca_cert, c.client_cert, c.client_key)).ok());
}

TEST_F(TlsTest, MutualTlsRefusesClientsWithoutAGoodCertificateAtTheHandshake) {
  const TestCertificates& c = SharedTestCertificates();
  ServerConfig config = Config();
  config.tls = ServerTls(/*mutual=*/true);
  StartServer(config);
  const int port = server_->port();

  EXPECT_EQ(GetInfo(port, Trusting(c.ca_cert)).error_code(), grpc::StatusCode::UNAVAILABLE);
  // The same name, signed by another CA.
  EXPECT_EQ(
      GetInfo(port, Presenting(c.ca_cert, c.other_client_cert, c.other_client_key)).error_code(),
      grpc::StatusCode::UNAVAILABLE);
  EXPECT_TRUE(GetInfo(port, Presenting(c.ca_cert, c.client_cert, c.client_key)).ok());
}

// A server with the credentials Server::Start uses, whose one generic method answers with the
// caller's certificate names (PeerCertificateNames of its auth context), one per line.
class NamesServer {
 public:
  explicit NamesServer(const TlsSettings& tls) {
    auto credentials = server::MakeServerCredentials(tls);
    EXPECT_TRUE(credentials.ok()) << credentials.status().ToString();
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:0", *credentials, &port_);
    builder.RegisterCallbackGenericService(&service_);
    server_ = builder.BuildAndStart();
  }
  ~NamesServer() { server_->Shutdown(); }
  int port() const { return port_; }

 private:
  class Service : public grpc::CallbackGenericService {
    grpc::ServerGenericBidiReactor* CreateReactor(
        grpc::GenericCallbackServerContext* context) override {
      std::string names;
      for (const std::string& name : server::PeerCertificateNames(*context->auth_context())) {
        names += name + "\n";
      }
      class Reactor : public grpc::ServerGenericBidiReactor {
       public:
        explicit Reactor(const std::string& names) {
          Finish(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "names:\n" + names));
        }
        void OnDone() override { delete this; }
      };
      return new Reactor(names);
    }
  };
  Service service_;
  std::unique_ptr<grpc::Server> server_;
  int port_ = 0;
};

// The names NamesServer reports for a caller connecting with `options`.
std::string CallerNames(int port, ConnectionOptions options) {
  options.address = "localhost:" + std::to_string(port);
  std::string error;
  std::optional<Connection> connection = Connection::Open(options, &error);
  EXPECT_TRUE(connection) << error;
  if (!connection) return "";
  grpc::GenericStub stub(connection->channel());
  grpc::Slice empty("");
  grpc::ByteBuffer request(&empty, 1), response;
  auto context = connection->NewContext();
  std::promise<grpc::Status> done;
  stub.UnaryCall(context.get(), "/test.Names/Get", grpc::StubOptions(), &request, &response,
                 [&done](grpc::Status status) { done.set_value(std::move(status)); });
  const grpc::Status status = done.get_future().get();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << status.error_message();
  return status.error_message();
}

TEST_F(TlsTest, TheServerSeesAMutualTlsCallersCertificateNames) {
  const TestCertificates& c = SharedTestCertificates();
  {
    NamesServer server(ServerTls(/*mutual=*/true));
    EXPECT_EQ(CallerNames(server.port(), Presenting(c.ca_cert, c.client_cert, c.client_key)),
              "names:\nrobot-8.fleet.internal\nspiffe://fleet/robot-8\n");
    const auto [cert, key] = testing::IssueClientCertificate(
        c, "robot-9", "robot-9.fleet.internal", {"robot-9.example", "robot-9.fleet.internal"});
    EXPECT_EQ(CallerNames(server.port(), Presenting(c.ca_cert, cert, key)),
              "names:\nrobot-9.fleet.internal\nrobot-9.example\n");
  }
  {
    // Plain TLS, and plaintext: no certificate, no names.
    NamesServer tls(ServerTls(/*mutual=*/false));
    EXPECT_EQ(CallerNames(tls.port(), Trusting(c.ca_cert)), "names:\n");
    NamesServer plaintext(TlsSettings{});
    EXPECT_EQ(CallerNames(plaintext.port(), ConnectionOptions{}), "names:\n");
  }
}

TEST_F(TlsTest, Tls11IsRefused) {
  const TestCertificates& c = SharedTestCertificates();
  ServerConfig config = HttpsMetricsConfig(/*mutual=*/false);
  StartServer(config);
  // The client allows TLS 1.1 whatever the system's OpenSSL policy (Debian's requires 1.2).
  const std::string legacy = "OPENSSL_CONF=/dev/null ";
  const std::string tls11 = "-tls1_1 -cipher 'ALL:@SECLEVEL=0'";
  for (const int port : {server_->port(), server_->metrics_port()}) {
    SCOPED_TRACE(port == server_->port() ? "gRPC" : "metrics");
    std::string output;
    // The control: the same client with TLS 1.2 completes the handshake.
    ASSERT_EQ(testing::RunShell(legacy + "timeout 30 openssl s_client -connect 127.0.0.1:" +
                                    std::to_string(port) + " -tls1_2 -alpn h2 -CAfile '" +
                                    c.ca_cert + "' -verify_return_error < /dev/null",
                                &output),
              0)
        << output;
    EXPECT_NE(testing::RunShell(legacy + "timeout 30 openssl s_client -connect 127.0.0.1:" +
                                    std::to_string(port) + " " + tls11 + " < /dev/null",
                                &output),
              0)
        << output;
    EXPECT_EQ(output.find("Cipher is (NONE)") != std::string::npos, true) << output;
  }
  // The metrics endpoint says why (gRPC closes the connection without an alert).
  std::string output;
  testing::RunShell(legacy + "timeout 30 openssl s_client -connect 127.0.0.1:" +
                        std::to_string(server_->metrics_port()) + " " + tls11 + " < /dev/null",
                    &output);
  EXPECT_NE(output.find("alert protocol version"), std::string::npos) << output;
}

TEST_F(TlsTest, MetricsOverHttps) {
  const TestCertificates& c = SharedTestCertificates();
  ServerConfig config = HttpsMetricsConfig(/*mutual=*/false);
  StartServer(config);
  const int port = server_->metrics_port();
  ASSERT_GT(port, 0);
  EXPECT_NE(HttpsGet(port, "").find("placedb_queue_depth"), std::string::npos);
  // Plain HTTP gets no metrics (the handshake fails on the request line).
  EXPECT_EQ(HttpGet(port, "/metrics").find("placedb_queue_depth"), std::string::npos);
  // A client that does not trust the server's CA gets nothing either.
  std::string output;
  EXPECT_NE(SClient(port, "-quiet -verify_return_error -CAfile '" + c.other_ca_cert + "'",
                    "GET /metrics HTTP/1.0\r\n\r\n", &output),
            0);
  EXPECT_EQ(output.find("placedb_queue_depth"), std::string::npos) << output;
}

// Connections that never start their handshake hold the endpoint's workers for at most
// metrics_request_timeout_ms: a scrape behind them is still answered.
TEST_F(TlsTest, IdleConnectionsDoNotBlockHttpsMetrics) {
  ServerConfig config = HttpsMetricsConfig(/*mutual=*/false);
  config.metrics_threads = 2;
  config.metrics_request_timeout_ms = 300;
  StartServer(config);
  const int port = server_->metrics_port();
  std::vector<int> idle;
  for (int i = 0; i < config.metrics_threads + 1; ++i) {
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(uint16_t(port));
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ASSERT_EQ(connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
    idle.push_back(fd);
  }
  EXPECT_NE(HttpsGet(port, "").find("placedb_queue_depth"), std::string::npos);
  for (const int fd : idle) close(fd);
}

TEST_F(TlsTest, MutualTlsMetricsRequireAClientCertificate) {
  const TestCertificates& c = SharedTestCertificates();
  ServerConfig config = HttpsMetricsConfig(/*mutual=*/true);
  StartServer(config);
  const int port = server_->metrics_port();
  EXPECT_EQ(HttpsGet(port, "").find("placedb_queue_depth"), std::string::npos);
  EXPECT_EQ(HttpsGet(port, "-cert '" + c.other_client_cert + "' -key '" + c.other_client_key + "'")
                .find("placedb_queue_depth"),
            std::string::npos);
  EXPECT_NE(HttpsGet(port, "-cert '" + c.client_cert + "' -key '" + c.client_key + "'")
                .find("placedb_queue_depth"),
            std::string::npos);
}

// A scraper that resumes its TLS session (as curl does for a second URL) is answered: the
// resumed session keeps its verified client certificate.
TEST_F(TlsTest, MutualTlsMetricsAnswerAResumedSession) {
  const TestCertificates& c = SharedTestCertificates();
  ServerConfig config = HttpsMetricsConfig(/*mutual=*/true);
  StartServer(config);
  const int port = server_->metrics_port();
  const std::string session = root_ + "/tls-session.pem";
  const std::string client = "-cert '" + c.client_cert + "' -key '" + c.client_key + "' ";
  ASSERT_NE(HttpsGet(port, client + "-sess_out '" + session + "'").find("placedb_queue_depth"),
            std::string::npos);
  ASSERT_TRUE(std::filesystem::exists(session));
  std::string output;
  SClient(port,
          "-ign_eof -verify_return_error -CAfile '" + c.ca_cert + "' " + client + "-sess_in '" +
              session + "'",
          "GET /metrics HTTP/1.0\r\nHost: localhost\r\n\r\n", &output);
  EXPECT_NE(output.find("Reused, TLS"), std::string::npos) << output;
  EXPECT_NE(output.find("placedb_queue_depth"), std::string::npos) << output;
}

TEST_F(TlsTest, BadTlsFilesAreClearStartupErrors) {
  const TestCertificates& c = SharedTestCertificates();
  const std::string key_text = testing::ReadFileBytes(c.server_key);
  // A line of the key's base64: must never appear in a message.
  const std::string key_line = key_text.substr(key_text.find('\n') + 1, 40);
  const std::string encrypted_key = root_ + "/encrypted.key";
  std::string output;
  ASSERT_EQ(testing::RunShell("openssl pkey -in '" + c.server_key +
                                  "' -aes256 -passout pass:x -out '" + encrypted_key + "'",
                              &output),
            0)
      << output;
  struct Case {
    TlsSettings tls;
    StatusCode code;
    std::vector<std::string> says;
  };
  const std::string missing = root_ + "/missing.pem";
  const std::vector<Case> cases = {
      {{missing, c.server_key, ""}, StatusCode::kNotFound, {"tls.cert_file", missing}},
      {{c.server_cert, missing, ""}, StatusCode::kNotFound, {"tls.key_file", missing}},
      {{c.not_pem, c.server_key, ""},
       StatusCode::kInvalidArgument,
       {"tls.cert_file", c.not_pem, "no PEM certificate"}},
      {{c.server_cert, c.not_pem, ""},
       StatusCode::kInvalidArgument,
       {"tls.key_file", c.not_pem, "not a PEM private key"}},
      {{c.server_cert, c.client_key, ""},
       StatusCode::kInvalidArgument,
       {"tls.key_file", c.client_key, "does not belong to the certificate", c.server_cert}},
      {{c.server_cert, encrypted_key, ""},
       StatusCode::kInvalidArgument,
       {"tls.key_file", "encrypted"}},
      {{c.server_cert, c.server_key, missing},
       StatusCode::kNotFound,
       {"tls.client_ca_file", missing}},
      {{c.server_cert, c.server_key, c.not_pem},
       StatusCode::kInvalidArgument,
       {"tls.client_ca_file", "no PEM certificate"}},
      {{root_, c.server_key, ""}, StatusCode::kIoError, {"tls.cert_file", root_}},
  };
  for (const Case& test : cases) {
    ServerConfig config = Config();
    config.tls = test.tls;
    auto started = Server::Start(config);
    ASSERT_FALSE(started.ok());
    const Status& status = started.status();
    EXPECT_EQ(status.code(), test.code) << status.ToString();
    for (const std::string& part : test.says) {
      EXPECT_NE(status.message().find(part), std::string::npos) << status.ToString();
    }
    EXPECT_EQ(status.message().find(key_line), std::string::npos) << status.ToString();
    EXPECT_EQ(status.message().find("PRIVATE KEY"), std::string::npos) << status.ToString();
  }
  // The metrics endpoint's HTTPS reads the same files: the same check, before anything listens.
  ServerConfig config = Config();
  config.tls = {c.server_cert, c.client_key, ""};
  config.metrics_listen = "127.0.0.1:0";
  config.metrics_tls = true;
  auto started = Server::Start(config);
  ASSERT_FALSE(started.ok());
  EXPECT_NE(started.status().message().find("does not belong"), std::string::npos);
}

TEST(LoopbackTest, WhichAddressesAreLoopback) {
  for (const char* address :
       {"127.0.0.1:50051", "127.1.2.3:0", "localhost:50051", "LOCALHOST:1", "[::1]:50051",
        "[::ffff:127.0.0.1]:9", "unix:/tmp/placedb.sock", "127.0.0.1:9464,[::1]:9464"}) {
    EXPECT_TRUE(server::IsLoopbackAddress(address)) << address;
  }
  for (const char* address :
       {"0.0.0.0:50051", "[::]:50051", "10.0.0.5:50051", "placedb.internal:50051", "9464", "+9464",
        ":50051", "", "127.0.0.1:9464,0.0.0.0:9465", "[::ffff:10.0.0.1]:9", "128.0.0.1:1"}) {
    EXPECT_FALSE(server::IsLoopbackAddress(address)) << address;
  }
}

TEST_F(TlsTest, WithoutAuthenticationTheServerStaysOnLoopback) {
  for (const bool metrics : {false, true}) {
    ServerConfig config = Config();
    (metrics ? config.metrics_listen : config.listen) = "0.0.0.0:0";
    auto refused = Server::Start(config);
    ASSERT_FALSE(refused.ok());
    EXPECT_EQ(refused.status().code(), StatusCode::kInvalidArgument);
    const std::string& message = refused.status().message();
    EXPECT_NE(message.find(metrics ? "metrics_listen = 0.0.0.0:0" : "listen = 0.0.0.0:0"),
              std::string::npos)
        << message;
    EXPECT_NE(message.find("security.allow_unauthenticated_remote"), std::string::npos) << message;
    EXPECT_NE(message.find("--allow-unauthenticated-remote"), std::string::npos) << message;

    config.security.allow_unauthenticated_remote = true;
    auto allowed = Server::Start(config);
    EXPECT_TRUE(allowed.ok()) << allowed.status().ToString();
  }
  // Loopback needs no option.
  auto loopback = Server::Start(Config());
  EXPECT_TRUE(loopback.ok()) << loopback.status().ToString();
}

TEST_F(TlsTest, AuthenticatedServersMayListenBeyondLoopback) {
  const TestCertificates& c = SharedTestCertificates();
  {
    // Mutual TLS authenticates gRPC callers; metrics over mutual TLS too.
    ServerConfig config = Config();
    config.listen = "0.0.0.0:0";
    config.tls = ServerTls(/*mutual=*/true);
    {
      auto started = Server::Start(config);
      ASSERT_TRUE(started.ok()) << started.status().ToString();
      EXPECT_TRUE(
          GetInfo((*started)->port(), Presenting(c.ca_cert, c.client_cert, c.client_key)).ok());
    }
    config.metrics_listen = "0.0.0.0:0";
    config.listen = "127.0.0.1:0";
    config.metrics_tls = true;
    {
      auto started = Server::Start(config);
      EXPECT_TRUE(started.ok()) << started.status().ToString();
    }
    // Plaintext metrics beyond loopback are open to anyone, mutual TLS on gRPC or not.
    config.metrics_tls = false;
    auto started = Server::Start(config);
    ASSERT_FALSE(started.ok());
    EXPECT_NE(started.status().message().find("metrics_listen = 0.0.0.0:0"), std::string::npos);
  }
  {
    // A tokens file authenticates both (the metrics with HTTP basic auth).
    ServerConfig config = Config();
    config.security.tokens_file = AdminTokensFile();
    config.listen = "0.0.0.0:0";
    config.metrics_listen = "0.0.0.0:0";
    auto started = Server::Start(config);
    EXPECT_TRUE(started.ok()) << started.status().ToString();
  }
}

// Keeps the text of every record logged while it is the default logger.
class RecordingSink final : public spdlog::sinks::base_sink<std::mutex> {
 public:
  std::string text() {
    std::lock_guard lock(mutex_);
    return text_;
  }

 protected:
  void sink_it_(const spdlog::details::log_msg& message) override {
    text_.append(message.payload.data(), message.payload.size());
    text_ += '\n';
  }
  void flush_() override {}

 private:
  std::string text_;
};

// Finding 8 of issue 34: tokens over plaintext beyond loopback start with a loud warning naming
// each such listener; TLS or loopback, none.
TEST_F(TlsTest, TokensInClearTextBeyondLoopbackAreWarnedAbout) {
  ServerConfig config = Config();
  config.security.tokens_file = AdminTokensFile();
  config.listen = "0.0.0.0:0";
  config.metrics_listen = "0.0.0.0:0";
  config.console_listen = "127.0.0.1:0";

  const std::vector<std::string> warnings = server::CleartextTokenWarnings(config);
  ASSERT_EQ(warnings.size(), 2u);
  EXPECT_NE(warnings[0].find("gRPC on 0.0.0.0:0 takes bearer tokens over plaintext"),
            std::string::npos)
      << warnings[0];
  EXPECT_NE(warnings[1].find("metrics on 0.0.0.0:0"), std::string::npos) << warnings[1];
  {
    ServerConfig quiet = config;
    quiet.listen = "127.0.0.1:0";
    quiet.metrics_listen = "[::1]:0";
    EXPECT_TRUE(server::CleartextTokenWarnings(quiet).empty());
    quiet.console_listen = "0.0.0.0:0";
    ASSERT_EQ(server::CleartextTokenWarnings(quiet).size(), 1u);
    quiet.console_tls = true;
    quiet.tls = ServerTls(/*mutual=*/false);
    quiet.listen = "0.0.0.0:0";
    EXPECT_TRUE(server::CleartextTokenWarnings(quiet).empty());
    ServerConfig tokenless = config;
    tokenless.security.tokens_file.clear();
    tokenless.security.allow_unauthenticated_remote = true;
    EXPECT_TRUE(server::CleartextTokenWarnings(tokenless).empty());
  }

  // A real start logs it (before the slow part and again after the startup summary).
  const std::shared_ptr<spdlog::logger> previous = spdlog::default_logger();
  auto sink = std::make_shared<RecordingSink>();
  spdlog::set_default_logger(std::make_shared<spdlog::logger>("recording", sink));
  {
    auto started = Server::Start(config);
    EXPECT_TRUE(started.ok()) << started.status().ToString();
  }
  spdlog::set_default_logger(previous);  // the server is gone: nothing logs any more
  const std::string log = sink->text();
  size_t count = 0;
  for (size_t at = 0;
       (at = log.find("SECURITY WARNING: gRPC on 0.0.0.0:0", at)) != std::string::npos; ++at) {
    ++count;
  }
  EXPECT_EQ(count, 2u) << log;
  EXPECT_NE(log.find("SECURITY WARNING: metrics on 0.0.0.0:0"), std::string::npos) << log;
}

// The CLI (the code the placedb binary runs) against a mutual-TLS server.
TEST_F(TlsTest, TheCliPresentsItsClientCertificate) {
  const TestCertificates& c = SharedTestCertificates();
  ServerConfig config = Config();
  config.tls = ServerTls(/*mutual=*/true);
  StartServer(config);
  const std::string address = "localhost:" + std::to_string(server_->port());
  auto run = [&](std::vector<std::string> flags, std::string* out_text) {
    std::vector<std::string> args = {"placedb", "--address", address, "--timeout", "10"};
    args.insert(args.end(), flags.begin(), flags.end());
    args.push_back("info");
    std::vector<const char*> argv;
    for (const std::string& a : args) argv.push_back(a.c_str());
    std::ostringstream out, err;
    std::istringstream in;
    client::CliIo io{out, err, in, false, false};
    const int code = client::RunCli(int(argv.size()), argv.data(), io);
    *out_text = out.str() + err.str();
    return code;
  };
  std::string text;
  EXPECT_EQ(
      run({"--tls", "--ca-cert", c.ca_cert, "--cert", c.client_cert, "--key", c.client_key}, &text),
      client::kExitOk)
      << text;
  EXPECT_EQ(run({"--tls", "--ca-cert", c.ca_cert}, &text), client::kExitRpcError) << text;
  EXPECT_NE(text.find("UNAVAILABLE"), std::string::npos) << text;
  EXPECT_EQ(run({"--tls", "--ca-cert", c.ca_cert, "--cert", c.client_cert}, &text),
            client::kExitUsage)
      << text;
  EXPECT_NE(text.find("--cert needs --key"), std::string::npos) << text;
  EXPECT_EQ(run({"--cert", c.client_cert, "--key", c.client_key}, &text), client::kExitUsage)
      << text;
  EXPECT_NE(text.find("needs --tls"), std::string::npos) << text;
}

}  // namespace
}  // namespace placedb::server_testing
