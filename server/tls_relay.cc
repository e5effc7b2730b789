#include "server/tls_relay.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <openssl/err.h>
#include <openssl/ssl.h>
#include <signal.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>

#include "server/transport_security.h"

namespace placedb::server {

namespace {

using SteadyClock = std::chrono::steady_clock;

// Bounds each following read and write of `fd` by what is left until `deadline`; false once it
// has passed.
bool LimitTo(int fd, SteadyClock::time_point deadline) {
  const auto left =
      std::chrono::duration_cast<std::chrono::microseconds>(deadline - SteadyClock::now());
  if (left.count() <= 0) return false;
  timeval tv{};
  tv.tv_sec = time_t(left.count() / 1000000);
  tv.tv_usec = suseconds_t(left.count() % 1000000);
  return setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv) == 0 &&
         setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof tv) == 0;
}

bool SendAll(int fd, const char* data, size_t size) {
  while (size > 0) {
    const ssize_t sent = send(fd, data, size, MSG_NOSIGNAL);
    if (sent < 0 && errno == EINTR) continue;
    if (sent <= 0) return false;
    data += sent;
    size -= size_t(sent);
  }
  return true;
}

}  // namespace

Result<std::unique_ptr<TlsRelay>> TlsRelay::Start(const Options& options) {
  std::unique_ptr<TlsRelay> relay(new TlsRelay(options));
  SSL_CTX* ctx = SSL_CTX_new(TLS_server_method());
  if (!ctx) return Status::Internal("metrics TLS: cannot create an SSL context");
  relay->ssl_ctx_ = ctx;
  PLACEDB_RETURN_IF_ERROR(ConfigureSslContext(ctx, options.tls));

  std::string host, port;
  const std::string& listen = options.listen;
  if (!listen.empty() && listen[0] == '[') {
    const auto close = listen.find("]:");
    if (close == std::string::npos)
      return Status::InvalidArgument("'" + listen + "' is not [v6]:port");
    host = listen.substr(1, close - 1);
    port = listen.substr(close + 2);
  } else {
    const auto colon = listen.rfind(':');
    if (colon == std::string::npos)
      return Status::InvalidArgument("'" + listen + "' is not host:port");
    host = listen.substr(0, colon);
    port = listen.substr(colon + 1);
  }
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  addrinfo* found = nullptr;
  if (const int error =
          getaddrinfo(host.empty() ? nullptr : host.c_str(), port.c_str(), &hints, &found);
      error != 0) {
    return Status::InvalidArgument("cannot resolve '" + listen + "': " + gai_strerror(error));
  }
  std::string why = "no address";
  for (addrinfo* a = found; a && relay->listen_fd_ < 0; a = a->ai_next) {
    const int fd = socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
    if (fd < 0) continue;
    const int one = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    if (bind(fd, a->ai_addr, a->ai_addrlen) == 0 && ::listen(fd, 128) == 0) {
      relay->listen_fd_ = fd;
    } else {
      why = std::strerror(errno);
      close(fd);
    }
  }
  freeaddrinfo(found);
  if (relay->listen_fd_ < 0) return Status::IoError("cannot listen on " + listen + ": " + why);
  sockaddr_storage bound{};
  socklen_t size = sizeof bound;
  if (getsockname(relay->listen_fd_, reinterpret_cast<sockaddr*>(&bound), &size) != 0) {
    return Status::IoError("cannot read the port bound for " + listen);
  }
  relay->port_ =
      ntohs(bound.ss_family == AF_INET6 ? reinterpret_cast<const sockaddr_in6*>(&bound)->sin6_port
                                        : reinterpret_cast<const sockaddr_in*>(&bound)->sin_port);
  TlsRelay* r = relay.get();
  relay->acceptor_ = std::thread([r] { r->AcceptLoop(); });
  return relay;
}

TlsRelay::~TlsRelay() {
  stopping_ = true;
  if (listen_fd_ >= 0) shutdown(listen_fd_, SHUT_RDWR);  // wakes accept()
  {
    MutexLock lock(mutex_);
    changed_.NotifyAll();  // wakes an acceptor waiting for a free slot
  }
  if (acceptor_.joinable()) acceptor_.join();
  {
    MutexLock lock(mutex_);
    for (const int fd : open_fds_) shutdown(fd, SHUT_RDWR);  // their reads and writes fail now
    while (active_ > 0) changed_.Wait(mutex_);
  }
  if (listen_fd_ >= 0) close(listen_fd_);
  if (ssl_ctx_) SSL_CTX_free(static_cast<SSL_CTX*>(ssl_ctx_));
}

void TlsRelay::AcceptLoop() {
  while (!stopping_) {
    {
      MutexLock lock(mutex_);
      while (active_ >= options_.threads && !stopping_) changed_.Wait(mutex_);
    }
    if (stopping_) break;
    const int fd = accept4(listen_fd_, nullptr, nullptr, SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno == EMFILE || errno == ENFILE)
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
      continue;  // stopping_, or a connection that went away before it was accepted
    }
    {
      MutexLock lock(mutex_);
      if (stopping_) {
        close(fd);
        break;
      }
      ++active_;
      open_fds_.insert(fd);
    }
    // Detached: the destructor waits for active_ to reach 0, which each thread's last step is.
    std::thread([this, fd] { Serve(fd); }).detach();
  }
}

void TlsRelay::Serve(int client_fd) {
  // A peer that closes early makes a write raise SIGPIPE in this thread: an error return instead.
  sigset_t pipe;
  sigemptyset(&pipe);
  sigaddset(&pipe, SIGPIPE);
  pthread_sigmask(SIG_BLOCK, &pipe, nullptr);

  const auto deadline = SteadyClock::now() + std::chrono::milliseconds(options_.timeout_ms);
  SSL* ssl = SSL_new(static_cast<SSL_CTX*>(ssl_ctx_));
  bool ok = ssl && SSL_set_fd(ssl, client_fd) == 1 && LimitTo(client_fd, deadline) &&
            SSL_accept(ssl) == 1;  // mutual TLS: no or a bad client certificate fails here
  if (!ok) {
    // Debug only: anything that connects (a port scan) would fill the log.
    const char* reason = ERR_reason_error_string(ERR_peek_error());
    spdlog::debug("metrics HTTPS: handshake failed: {}", reason ? reason : "connection closed");
  }
  std::string request;
  char buffer[16 << 10];
  while (ok && request.find("\r\n\r\n") == std::string::npos) {
    if (request.size() > options_.max_request_bytes || !LimitTo(client_fd, deadline)) {
      ok = false;
      break;
    }
    const int got = SSL_read(ssl, buffer, int(sizeof buffer));
    if (got <= 0) {
      ok = false;
      break;
    }
    request.append(buffer, size_t(got));
  }
  int backend = -1;
  if (ok) {
    backend = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(uint16_t(options_.backend_port));
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ok = backend >= 0 && LimitTo(backend, deadline) &&
         connect(backend, reinterpret_cast<sockaddr*>(&address), sizeof address) == 0 &&
         SendAll(backend, request.data(), request.size());
  }
  // The backend answers one request and closes (keep-alive off): pass everything on until then.
  while (ok) {
    if (!LimitTo(backend, deadline) || !LimitTo(client_fd, deadline)) {
      ok = false;
      break;
    }
    const ssize_t got = recv(backend, buffer, sizeof buffer, 0);
    if (got < 0 && errno == EINTR) continue;
    if (got <= 0) break;
    ok = SSL_write(ssl, buffer, int(got)) == int(got);
  }
  if (ok) SSL_shutdown(ssl);
  if (ssl) SSL_free(ssl);
  ERR_clear_error();
  if (backend >= 0) close(backend);
  MutexLock lock(mutex_);
  open_fds_.erase(client_fd);
  close(client_fd);
  --active_;
  changed_.NotifyAll();
}

}  // namespace placedb::server
