// An HTTP or HTTPS listener of placedb-server (cpp-httplib), shared by the metrics endpoint and
// the web console: bounded workers, per-request timeouts, the TLS files of TlsSettings, a bind
// that fails instead of sharing a port, and its own accept thread.
//
// Workers: `threads` of them, each serving one connection and one request at a time (no
// keep-alive: the answer closes the connection); more connections wait in the listen backlog, so
// a slow client takes one worker, never the endpoint. `request_timeout_ms` bounds each read and
// write of a connection (a TLS handshake's too), and the wait for its request's first byte (in
// whole seconds, at least 1).
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>

#include "core/base/status.h"
#include "server/config.h"

namespace httplib {
class Server;
struct Request;
}  // namespace httplib

namespace placedb::server {

struct HttpEndpointSettings {
  std::string name;    // for errors and logs: "metrics endpoint", "console"
  std::string listen;  // host:port or [v6]:port; port 0 picks one
  int threads = 4;
  uint32_t request_timeout_ms = 5000;
  // Bodies larger than this are refused with 413 before they are read (0: httplib's default).
  uint64_t max_request_bytes = 0;
  // Set: HTTPS only, TLS 1.2 or later with these files, and with tls->mutual() a client
  // certificate signed by one of its CAs is required at the handshake.
  std::optional<TlsSettings> tls;
};

class HttpEndpoint {
 public:
  HttpEndpoint() = default;
  ~HttpEndpoint();  // Stop()
  HttpEndpoint(const HttpEndpoint&) = delete;
  HttpEndpoint& operator=(const HttpEndpoint&) = delete;

  // Binds and starts serving; `routes` installs the handlers on the server before it binds.
  // Exceptions from a handler are logged and answered 500 without their text. INVALID_ARGUMENT
  // for a listen address that is not host:port; IO_ERROR when it cannot be bound (in use:
  // SO_REUSEPORT is not set, so a second server cannot share the port); with TLS, the errors of
  // LoadTlsFiles (server/transport_security.h) for bad files. On failure nothing is served.
  Status Serve(const HttpEndpointSettings& settings,
               const std::function<void(httplib::Server&)>& routes);
  int port() const { return port_; }  // the bound port; 0 when not serving
  // Stops accepting and waits for the connections being served (each ends within its timeouts).
  void Stop();

 private:
  std::unique_ptr<httplib::Server> http_;  // an httplib::SSLServer with settings.tls
  std::thread thread_;                     // http_'s accept loop
  int port_ = 0;
};

// A client's address as gRPC writes a peer ("ipv4:10.0.0.7:53122", "ipv6:[::1]:40112"), so
// that audit lines read the same for RPCs and HTTP requests.
std::string HttpPeerName(const httplib::Request& request);

}  // namespace placedb::server
