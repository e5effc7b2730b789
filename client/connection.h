// A connection to a placedb server: the channel (plaintext, or TLS with --tls, presenting a client
// certificate with --cert/--key for mutual TLS), the PlaceDb stub, and call contexts carrying the
// deadline and the bearer token.
//
//   ConnectionOptions options{.address = "localhost:50051"};
//   auto connection = Connection::Open(options);       // nullopt + error: unreadable CA file
//   auto context = connection->NewContext();            // deadline = now + timeout_s
//   connection->stub()->GetServerInfo(context.get(), {}, &info);
#pragma once

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <memory>
#include <optional>
#include <string>

#include "proto/placedb.grpc.pb.h"

namespace placedb::client {

namespace v1 = ::placedb::v1;
using Clock = std::chrono::steady_clock;

// Process exit codes of every command.
enum ExitCode : int {
  kExitOk = 0,
  kExitRpcError = 1,  // an RPC failed (message printed with the gRPC code name)
  kExitUsage = 2,     // bad command line or unreadable local input
  kExitDamage = 3,    // `maps scrub` found damage
};

struct ConnectionOptions {
  std::string address = "localhost:50051";  // gRPC target (host:port, [v6]:port, dns:///..., unix:)
  double timeout_s = 30;                    // deadline of each unary RPC; 0 = none
  bool tls = false;                         // grpc::SslCredentials instead of plaintext
  std::string ca_cert;                      // PEM roots for TLS; empty = the system's
  std::string cert;                         // PEM client certificate (chain) for mutual TLS
  std::string key;                          // its PEM private key (unencrypted)
  std::string token;                        // sent as "authorization: Bearer <token>"
};

// The channel credentials `options` describe: plaintext without tls; otherwise TLS trusting
// ca_cert (or the system's roots) and presenting cert + key when both are set. cert or key alone,
// or cert/key without tls, is a usage error. Reads the files; on failure returns null and sets
// *error, naming the flag (--ca-cert, --cert, --key) and the problem. Every client (CLI, load
// tester, evaluation harness) connects through this.
std::shared_ptr<grpc::ChannelCredentials> MakeChannelCredentials(const ConnectionOptions& options,
                                                                 std::string* error);

class Connection {
 public:
  // Reads the TLS files (MakeChannelCredentials); on failure returns nullopt and sets *error.
  static std::optional<Connection> Open(const ConnectionOptions& options, std::string* error);

  // A context for one call: the bearer token, and the deadline for unary calls (streams get none:
  // an Ingest stream lasts as long as its frames).
  std::unique_ptr<grpc::ClientContext> NewContext(bool unary = true) const;

  v1::PlaceDb::Stub* stub() const { return stub_.get(); }
  const std::shared_ptr<grpc::Channel>& channel() const { return channel_; }
  const ConnectionOptions& options() const { return options_; }

 private:
  ConnectionOptions options_;
  std::shared_ptr<grpc::Channel> channel_;
  std::shared_ptr<v1::PlaceDb::Stub> stub_;
};

// The gRPC target for --address: a bare port ("50051") means localhost on that port (gRPC would
// take it for a host name and fail to resolve it); anything else is used as given.
std::string ServerTarget(const std::string& address);

// "NOT_FOUND: map 'x' not found".
std::string Describe(const grpc::Status& status);
// Describe, and when the call never reached a server (connection refused, a name that does not
// resolve: gRPC's UNAVAILABLE, not a server's own) a second line asking whether placedb-server
// runs at `address`.
std::string DescribeFailure(const grpc::Status& status, const std::string& address);

// OK when the map GetMap described is served (AVAILABLE or RECOVERED); else why not, as the
// calls on it would answer: DATA_LOSS (DAMAGED) or FAILED_PRECONDITION (UNAVAILABLE), with the
// reason. GetMap describes such maps instead of failing.
grpc::Status MapServingStatus(const v1::MapDescription& map);

// grpc.health.v1.Health/Check. Returns the RPC status; on OK, *serving_status is the
// HealthCheckResponse.ServingStatus name ("SERVING", "NOT_SERVING", "UNKNOWN", "SERVICE_UNKNOWN").
grpc::Status CheckHealth(const Connection& connection, const std::string& service,
                         std::string* serving_status);

}  // namespace placedb::client
