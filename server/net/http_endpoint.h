// An HTTP or HTTPS listener of placedb-server (cpp-httplib), shared by the metrics endpoint and
// the web console: bounded connections and handlers, a deadline per connection, bodies bounded
// before they are read, the TLS files of TlsSettings, a bind that fails instead of sharing a
// port, and its own accept thread.
//
// Connections: up to `max_connections` are served at once, each on its own thread (more wait in
// the listen backlog); one request per connection (the answer closes it). Past its headers a
// request waits for one of `threads` handler slots (routing, reading the body, the handler): a
// client that trickles its headers holds a connection thread, never a handler, so slow clients
// cannot keep the endpoint from answering others until there are max_connections of them. (A
// request whose deadline passes while it waits for a slot is still routed, without a slot and
// with no body: at most max_connections handlers run then.)
//
// Time: every read and write (a TLS handshake's too) waits at most `request_timeout_ms`; the
// whole request (handshake, headers, body) must arrive within `request_timeout_ms` of the accept,
// and the whole answer be written within `request_timeout_ms` of its first byte: a client that
// trickles a byte at a time within the per-read timeout is cut off at that deadline, and so is
// one that reads its answer as slowly. (The handler's own time counts for neither: a loaded
// machine does not cut answers short.) Stop() cuts the reading side of every open connection, so
// it does not wait for slow clients.
//
// Bodies: the headers may take 64 KiB; the body is read only as far as its request declares and
// the limit allows, and nothing of it before the routes' pre-routing handler accepted the request
// (httplib runs that handler before it reads a body). A Content-Length over max_request_bytes is
// answered 413 from the headers, without reading the body; a chunked body is read up to
// max_request_bytes (its framing included), beyond that the read fails (400); a request with
// neither Content-Length nor chunked encoding has no body (RFC 9112 6.3), instead of httplib's
// read-until-close. A refused body stays unread: the answer closes the connection.
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
  std::string name;                    // for errors and logs: "metrics endpoint", "console"
  std::string listen;                  // host:port or [v6]:port; port 0 picks one
  int threads = 4;                     // requests past their headers at once (see above)
  int max_connections = 64;            // connections served at once, each on its own thread
  uint32_t request_timeout_ms = 5000;  // per read or write, for a request and for its answer
  // The largest body a request may send (0: none); a larger Content-Length is answered 413 from
  // the headers, before any of the body is read.
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
  // LoadTlsFiles (server/net/transport_security.h) for bad files. On failure nothing is served.
  Status Serve(const HttpEndpointSettings& settings,
               const std::function<void(httplib::Server&)>& routes);
  int port() const { return port_; }  // the bound port; 0 when not serving
  // Stops accepting, cuts the reading side of the open connections (a request being handled
  // still gets its answer) and waits for them.
  void Stop();

 private:
  std::unique_ptr<httplib::Server> http_;  // an httplib::SSLServer with settings.tls
  std::function<void()> cut_connections_;  // shuts the reading side of every open connection
  std::thread thread_;                     // http_'s accept loop
  int port_ = 0;
};

// A client's address as gRPC writes a peer ("ipv4:10.0.0.7:53122", "ipv6:[::1]:40112"), so
// that audit lines read the same for RPCs and HTTP requests.
std::string HttpPeerName(const httplib::Request& request);

}  // namespace placedb::server
