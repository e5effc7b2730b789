// HTTPS in front of a plaintext HTTP endpoint on loopback: the metrics endpoint's TLS.
//
// Why not civetweb's own HTTPS: Debian's civetweb 1.15 loads OpenSSL at run time by name and was
// built against the OpenSSL 1.1 API; OpenSSL 3 no longer exports SSL_get_peer_certificate, so
// civetweb calls a null pointer after every completed handshake (the process crashes). Here
// OpenSSL is linked normally: each connection's handshake (TLS 1.2+, and with mutual TLS a
// client certificate verified against the client CAs) happens in this relay, which then passes
// one HTTP request to the backend (civetweb on 127.0.0.1, keep-alive off) and its whole answer
// back. The backend sees the relay as its client (peer 127.0.0.1); its port is plaintext and
// reachable by other users of this machine (never from the network).
//
//   auto relay = TlsRelay::Start({.listen = "0.0.0.0:9464", .backend_port = 41234, .tls = tls});
//   relay->port();   // the bound port (listen may say 0)
//   relay.reset();   // stops accepting, closes open connections, waits for their threads
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <set>
#include <string>
#include <thread>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "server/config.h"

namespace placedb::server {

class TlsRelay {
 public:
  struct Options {
    std::string listen;    // host:port or [v6]:port; port 0 picks one
    int backend_port = 0;  // plaintext HTTP on 127.0.0.1
    TlsSettings tls;       // enabled(); mutual() = client certificates required
    int threads = 4;       // connections served at once; more wait in the listen backlog
    // A connection's handshake, request and answer must all be done within this.
    uint32_t timeout_ms = 5000;
    size_t max_request_bytes = 16 << 10;  // a longer request header is refused (closed)
  };
  // Listens and starts serving. Errors: LoadTlsFiles's (server/transport_security.h) for the
  // files, INVALID_ARGUMENT for an address that does not resolve, IO_ERROR when it cannot bind.
  static Result<std::unique_ptr<TlsRelay>> Start(const Options& options);
  ~TlsRelay();

  int port() const { return port_; }

 private:
  explicit TlsRelay(Options options) : options_(std::move(options)) {}
  void AcceptLoop();
  void Serve(int client_fd);

  const Options options_;
  void* ssl_ctx_ = nullptr;  // SSL_CTX
  int listen_fd_ = -1;
  int port_ = 0;
  std::atomic<bool> stopping_{false};
  std::thread acceptor_;

  Mutex mutex_;
  CondVar changed_;
  std::set<int> open_fds_ GUARDED_BY(mutex_);  // connections being served (shut down on stop)
  int active_ GUARDED_BY(mutex_) = 0;          // handler threads still running
};

}  // namespace placedb::server
