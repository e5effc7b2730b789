#include "server/net/http_endpoint.h"

#include <fcntl.h>
#include <httplib.h>
#include <netdb.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <exception>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <type_traits>
#include <utility>
#include <vector>

#include "core/base/text.h"
#include "core/base/thread_annotations.h"
#include "server/net/transport_security.h"

namespace placedb::server {

namespace {

using Clock = std::chrono::steady_clock;

// A request's line and headers, at most: httplib bounds each line but neither their count nor
// their total.
constexpr size_t kMaxHeaderBytes = 64 * 1024;

// What the connections of one endpoint share: its limits, the handler slots and the open sockets.
class EndpointState {
 public:
  explicit EndpointState(const HttpEndpointSettings& settings)
      : timeout_(std::chrono::milliseconds(settings.request_timeout_ms)),
        max_body_(settings.max_request_bytes),
        free_handlers_(std::max(settings.threads, 1)) {}

  Clock::duration timeout() const { return timeout_; }
  uint64_t max_body() const { return max_body_; }

  // One of the `threads` handler slots, waiting until `deadline` at most (slots are held by
  // connections that have deadlines too).
  bool AcquireHandler(Clock::time_point deadline) {
    MutexLock lock(mutex_);
    while (free_handlers_ == 0) {
      if (!changed_.WaitUntil(mutex_, deadline) && free_handlers_ == 0) return false;
    }
    --free_handlers_;
    return true;
  }
  void ReleaseHandler() {
    MutexLock lock(mutex_);
    ++free_handlers_;
    changed_.NotifyAll();
  }

  // The open sockets, for Cut(); one opened after Cut() is cut at once.
  void Opened(int socket) {
    MutexLock lock(mutex_);
    open_.insert(socket);
    if (cut_) ::shutdown(socket, SHUT_RD);
  }
  void Closing(int socket) {
    MutexLock lock(mutex_);
    open_.erase(socket);
  }
  // Reads of every open connection end (EOF); writes still work, so an answer being written is
  // finished.
  void Cut() {
    MutexLock lock(mutex_);
    cut_ = true;
    for (int socket : open_) ::shutdown(socket, SHUT_RD);
  }

 private:
  const Clock::duration timeout_;
  const uint64_t max_body_;
  Mutex mutex_;
  CondVar changed_;
  int free_handlers_ GUARDED_BY(mutex_);
  std::set<int> open_ GUARDED_BY(mutex_);
  bool cut_ GUARDED_BY(mutex_) = false;
};

// One accepted connection as httplib's Stream: a non-blocking socket (with its TLS session once
// Handshake() succeeded) whose every wait ends at the per-operation timeout or at the deadline,
// whichever comes first, and which hands out at most kMaxHeaderBytes before LimitBody() and the
// body's limit after it. The deadline is the request's (`timeout` after the accept: handshake,
// headers and body) until the first write, then the answer's (`timeout` after that write): the
// handler's own time counts for neither, so a busy machine does not cut answers short.
class Connection final : public httplib::Stream {
 public:
  Connection(int socket, const EndpointState& state)
      : socket_(socket), timeout_(state.timeout()), deadline_(Clock::now() + state.timeout()) {
    ::fcntl(socket_, F_SETFL, ::fcntl(socket_, F_GETFL) | O_NONBLOCK);
  }
  ~Connection() override {
    if (ssl_) SSL_free(ssl_);
  }
  Connection(const Connection&) = delete;
  Connection& operator=(const Connection&) = delete;

  Clock::time_point deadline() const { return deadline_; }
  SSL* ssl() const { return ssl_; }

  // The TLS handshake (nothing else is read or written before it).
  bool Handshake(SSL_CTX* context) {
    ssl_ = SSL_new(context);
    if (!ssl_ || SSL_set_fd(ssl_, socket_) != 1) return false;
    while (true) {
      const int done = SSL_accept(ssl_);
      if (done == 1) return true;
      if (!WaitForSsl(done)) return false;
    }
  }
  // Best effort: a close_notify to a peer that behaved, never waiting for its own.
  void CloseTls() {
    if (ssl_) SSL_shutdown(ssl_);
  }

  // The headers have been read: from now on at most `limit` more bytes are handed out.
  void LimitBody(uint64_t limit) { left_ = limit; }

  bool is_readable() const override {
    return begin_ < end_ || (ssl_ && SSL_pending(ssl_) > 0) || Wait(POLLIN);
  }
  bool is_writable() const override { return Wait(POLLOUT); }

  ssize_t read(char* out, size_t size) override {
    if (size == 0) return 0;
    if (left_ == 0) return -1;  // over the header or body limit: httplib refuses the request
    if (begin_ == end_) {
      const ssize_t got = Receive(buffer_, sizeof buffer_);
      if (got <= 0) return got;
      begin_ = 0;
      end_ = size_t(got);
    }
    const size_t n = std::min({size, end_ - begin_, size_t(std::min<uint64_t>(left_, SIZE_MAX))});
    std::copy(buffer_ + begin_, buffer_ + begin_ + n, out);
    begin_ += n;
    left_ -= n;
    return ssize_t(n);
  }

  ssize_t write(const char* data, size_t size) override {
    if (size == 0) return 0;
    if (!answering_) {
      answering_ = true;
      deadline_ = Clock::now() + timeout_;
    }
    while (true) {
      if (Clock::now() >= deadline_) return -1;
      if (ssl_) {
        const int sent = SSL_write(ssl_, data, int(std::min<size_t>(size, INT32_MAX)));
        if (sent > 0) return sent;
        if (!WaitForSsl(sent)) return -1;
        continue;
      }
      const ssize_t sent = ::send(socket_, data, size, MSG_NOSIGNAL);
      if (sent >= 0) return sent;
      if (errno == EINTR) continue;
      if ((errno != EAGAIN && errno != EWOULDBLOCK) || !Wait(POLLOUT)) return -1;
    }
  }

  void get_remote_ip_and_port(std::string& ip, int& port) const override {
    Address(::getpeername, &ip, &port);
  }
  void get_local_ip_and_port(std::string& ip, int& port) const override {
    Address(::getsockname, &ip, &port);
  }
  socket_t socket() const override { return socket_; }

 private:
  // Until `events` are ready on the socket: false at the per-operation timeout, the connection's
  // deadline, or an error.
  bool Wait(short events) const {
    while (true) {
      const auto now = Clock::now();
      if (now >= deadline_) return false;
      const auto wait = std::min(timeout_, deadline_ - now);
      pollfd entry{socket_, events, 0};
      const int ready =
          ::poll(&entry, 1, int(std::chrono::ceil<std::chrono::milliseconds>(wait).count()));
      if (ready > 0) return true;
      if (ready == 0) return false;  // the per-operation timeout (or the deadline)
      if (errno != EINTR) return false;
    }
  }
  // After an SSL call returned `result`: waits for what it needs; false when it failed.
  bool WaitForSsl(int result) const {
    switch (SSL_get_error(ssl_, result)) {
      case SSL_ERROR_WANT_READ:
        return Wait(POLLIN);
      case SSL_ERROR_WANT_WRITE:
        return Wait(POLLOUT);
      default:
        return false;
    }
  }
  // Some bytes into `out`: > 0, 0 at the end of the stream, -1 on an error, timeout or deadline.
  ssize_t Receive(char* out, size_t size) {
    while (true) {
      if (Clock::now() >= deadline_) return -1;
      if (ssl_) {
        const int got = SSL_read(ssl_, out, int(std::min<size_t>(size, INT32_MAX)));
        if (got > 0) return got;
        if (SSL_get_error(ssl_, got) == SSL_ERROR_ZERO_RETURN) return 0;
        if (!WaitForSsl(got)) return -1;
        continue;
      }
      const ssize_t got = ::recv(socket_, out, size, 0);
      if (got >= 0) return got;
      if (errno == EINTR) continue;
      if ((errno != EAGAIN && errno != EWOULDBLOCK) || !Wait(POLLIN)) return -1;
    }
  }
  void Address(int (*name_of)(int, sockaddr*, socklen_t*), std::string* ip, int* port) const {
    sockaddr_storage address{};
    socklen_t length = sizeof address;
    char host[NI_MAXHOST] = {}, service[NI_MAXSERV] = {};
    if (name_of(socket_, reinterpret_cast<sockaddr*>(&address), &length) != 0 ||
        ::getnameinfo(reinterpret_cast<sockaddr*>(&address), length, host, sizeof host, service,
                      sizeof service, NI_NUMERICHOST | NI_NUMERICSERV) != 0) {
      return;
    }
    *ip = host;
    *port = std::atoi(service);
  }

  const int socket_;
  const Clock::duration timeout_;
  Clock::time_point deadline_;
  bool answering_ = false;  // deadline_ is the answer's
  SSL* ssl_ = nullptr;
  uint64_t left_ = kMaxHeaderBytes;  // bytes still handed out: of the headers, then the body
  char buffer_[4096];
  size_t begin_ = 0, end_ = 0;  // buffer_'s bytes not handed out yet
};

// How much of a request's body may be read (its headers just parsed); refusals read none:
// httplib answers 413 without reading when Content-Length is over the payload limit it was given
// (max_body), and the stream gives it nothing to skip.
uint64_t BodyAllowance(httplib::Request& request, uint64_t max_body) {
  if (request.has_header("Content-Length")) {
    const std::string& text = request.get_header_value("Content-Length");
    char* end = nullptr;
    errno = 0;
    const unsigned long long length = std::strtoull(text.c_str(), &end, 10);
    if (text.empty() || *end != '\0' || errno == ERANGE || text[0] == '-') return 0;
    return length > max_body ? 0 : length;
  }
  if (request.get_header_value("Transfer-Encoding").find("chunked") != std::string::npos) {
    return max_body;  // framing included: a body over the limit fails to read (400)
  }
  // No declared body: none (httplib would read until the client closes).
  request.set_header("Content-Length", "0");
  return 0;
}

// httplib's task queue for an endpoint: each accepted connection on its own thread, at most
// `max_connections` at once; enqueue (called by httplib's accepting thread) waits for one to end,
// so that more connections wait in the kernel's listen backlog instead of piling up accepted.
class ConnectionThreads final : public httplib::TaskQueue {
 public:
  explicit ConnectionThreads(int max_connections) : free_(std::max(max_connections, 1)) {}
  ~ConnectionThreads() override { shutdown(); }

  void enqueue(std::function<void()> job) override {
    MutexLock lock(mutex_);
    while (free_ == 0) changed_.Wait(mutex_);  // each connection ends by its deadline
    --free_;
    for (std::thread::id id : finished_) {
      threads_[id].join();  // it has left Finished(): returning
      threads_.erase(id);
    }
    finished_.clear();
    std::thread thread([this, job = std::move(job)] {
      // A client that closes early makes a write (SSL_write has no MSG_NOSIGNAL) raise SIGPIPE
      // in this thread: an error return instead.
      sigset_t pipe;
      sigemptyset(&pipe);
      sigaddset(&pipe, SIGPIPE);
      pthread_sigmask(SIG_BLOCK, &pipe, nullptr);
      job();  // serves one connection and closes it
      Finished();
    });
    threads_.emplace(thread.get_id(), std::move(thread));
  }

  // Waits for the open connections (httplib calls it once its accept loop ended).
  void shutdown() override {
    std::map<std::thread::id, std::thread> threads;
    {
      MutexLock lock(mutex_);
      threads.swap(threads_);
      finished_.clear();
    }
    for (auto& [id, thread] : threads) thread.join();
  }

 private:
  void Finished() {
    MutexLock lock(mutex_);
    ++free_;
    finished_.push_back(std::this_thread::get_id());
    changed_.NotifyAll();
  }

  Mutex mutex_;
  CondVar changed_;
  int free_ GUARDED_BY(mutex_);
  std::map<std::thread::id, std::thread> threads_ GUARDED_BY(mutex_);
  std::vector<std::thread::id> finished_ GUARDED_BY(mutex_);  // threads to join
};

// httplib's Server or SSLServer serving each connection through Connection (httplib's own
// process_and_close_socket, a virtual of Debian's 0.11.4, bounds each read but not a
// connection's total time nor what it reads), with its listening socket (a protected member)
// reachable: httplib listens with a backlog of 5, raised after the bind so that connections
// beyond the threads wait for one instead of having their SYNs dropped.
template <class Base>
class HttpServer final : public Base {
 public:
  template <class... Args>
  explicit HttpServer(std::shared_ptr<EndpointState> state, Args&&... args)
      : Base(std::forward<Args>(args)...), state_(std::move(state)) {}
  void RaiseBacklog() { ::listen(this->svr_sock_, SOMAXCONN); }

 private:
  bool process_and_close_socket(socket_t socket) override {
    state_->Opened(socket);
    bool served = false;
    {
      Connection connection(socket, *state_);
      bool handler = false;
      bool secure = true;
      if constexpr (std::is_same_v<Base, httplib::SSLServer>) {
        secure = connection.Handshake(this->ssl_context());
      }
      if (secure) {
        bool closed = false;  // httplib's "the client asked to close": it is closed anyway
        served = this->process_request(
            connection, /*close_connection=*/true, closed, [&](httplib::Request& request) {
              request.ssl = connection.ssl();
              connection.LimitBody(BodyAllowance(request, state_->max_body()));
              // Past its headers: routing, the body and the handler take one of the slots.
              handler = state_->AcquireHandler(connection.deadline());
              if (!handler) connection.LimitBody(0);
            });
        if (served) connection.CloseTls();
      }
      if (handler) state_->ReleaseHandler();
    }
    state_->Closing(socket);
    ::shutdown(socket, SHUT_RDWR);
    ::close(socket);
    return served;
  }

  const std::shared_ptr<EndpointState> state_;
};

// "host:port" or "[v6]:port" -> (host, port); nullopt otherwise.
std::optional<std::pair<std::string, int>> SplitListenAddress(const std::string& listen) {
  std::string host, port;
  if (!listen.empty() && listen[0] == '[') {
    const auto close = listen.find("]:");
    if (close == std::string::npos) return std::nullopt;
    host = listen.substr(1, close - 1);
    port = listen.substr(close + 2);
  } else {
    const auto colon = listen.rfind(':');
    if (colon == std::string::npos) return std::nullopt;
    host = listen.substr(0, colon);
    port = listen.substr(colon + 1);
  }
  if (host.empty() || port.empty() || port.size() > 5 ||
      port.find_first_not_of("0123456789") != std::string::npos || std::stoi(port) > 65535) {
    return std::nullopt;
  }
  return std::make_pair(host, std::stoi(port));
}

}  // namespace

std::string HttpPeerName(const httplib::Request& request) {
  const std::string& address = request.remote_addr;
  const std::string port = std::to_string(request.remote_port);
  if (address.find(':') != std::string::npos) return "ipv6:[" + address + "]:" + port;
  return "ipv4:" + address + ":" + port;
}

HttpEndpoint::~HttpEndpoint() {
  Stop();
}

Status HttpEndpoint::Serve(const HttpEndpointSettings& settings,
                           const std::function<void(httplib::Server&)>& routes) {
  Stop();
  const std::string& name = settings.name;
  const auto address = SplitListenAddress(settings.listen);
  if (!address) {
    return Status::InvalidArgument(name + ": '" + settings.listen +
                                   "' is not host:port or [v6]:port");
  }
  auto state = std::make_shared<EndpointState>(settings);
  std::unique_ptr<httplib::Server> http;
  std::function<void()> raise_backlog;
  if (settings.tls) {
    Status tls_status;
    const TlsSettings tls = *settings.tls;
    auto https = std::make_unique<HttpServer<httplib::SSLServer>>(
        state, [&tls_status, &tls](SSL_CTX& context) {
          tls_status = ConfigureSslContext(&context, tls);
          return tls_status.ok();
        });
    raise_backlog = [server = https.get()] { server->RaiseBacklog(); };
    http = std::move(https);
    if (!http->is_valid()) {
      if (tls_status.ok()) tls_status = Status::Internal("cannot create an SSL context");
      return tls_status.WithContext(name + " (HTTPS)");
    }
  } else {
    auto plain = std::make_unique<HttpServer<httplib::Server>>(state);
    raise_backlog = [server = plain.get()] { server->RaiseBacklog(); };
    http = std::move(plain);
  }

  const int max_connections = settings.max_connections;
  http->new_task_queue = [max_connections] { return new ConnectionThreads(max_connections); };
  // One request per connection ("Connection: close"): an idle kept-alive connection would hold a
  // thread. Timeouts are Connection's; the payload limit makes httplib answer 413 for a
  // Content-Length over it (reading nothing: Connection hands it no body to skip).
  http->set_keep_alive_max_count(1);
  http->set_payload_max_length(size_t(settings.max_request_bytes));
  // SO_REUSEADDR only: httplib's default also sets SO_REUSEPORT, with which a second server of
  // the same user would share the port instead of failing to bind it.
  http->set_socket_options([](socket_t socket) {
    const int yes = 1;
    setsockopt(socket, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
  });
  // Exceptions from a handler are logged, and answered 500 without their text (httplib's
  // default would put it in a header).
  http->set_exception_handler(
      [name](const httplib::Request&, httplib::Response& response, std::exception_ptr error) {
        try {
          if (error) std::rethrow_exception(error);
        } catch (const std::exception& e) {
          // The text may quote the request (a JSON parser's "last read: ..."): escaped.
          spdlog::error("{}: request failed: {}", name, ForLog(e.what()));
        } catch (...) {
          spdlog::error("{}: request failed", name);
        }
        response.status = 500;
      });
  routes(*http);

  const int port =
      address->second == 0
          ? http->bind_to_any_port(address->first)
          : (http->bind_to_port(address->first, address->second) ? address->second : -1);
  if (port <= 0) {
    return Status::IoError(name + ": cannot listen on " + settings.listen +
                           " (address in use, or not a local address?)");
  }
  raise_backlog();
  // Listening since the bind: connections made before the loop starts wait in the backlog.
  httplib::Server* server = http.get();
  auto loop_ended = std::make_shared<std::atomic<bool>>(false);
  thread_ = std::thread([server, loop_ended] {
    server->listen_after_bind();
    loop_ended->store(true);
  });
  // httplib's stop() does nothing until the loop has marked itself running, so a Stop() right
  // after Start() would leave the loop, and the join, waiting forever: wait for that mark here.
  while (!server->is_running() && !loop_ended->load()) {
    std::this_thread::sleep_for(std::chrono::microseconds(100));
  }
  http_ = std::move(http);
  cut_connections_ = [state] { state->Cut(); };
  port_ = port;
  return Status::Ok();
}

void HttpEndpoint::Stop() {
  if (cut_connections_) cut_connections_();
  cut_connections_ = nullptr;
  if (http_) http_->stop();
  if (thread_.joinable()) thread_.join();
  http_.reset();
  port_ = 0;
}

}  // namespace placedb::server
