#include "server/http_endpoint.h"

#include <httplib.h>
#include <pthread.h>
#include <signal.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <deque>
#include <exception>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "core/base/thread_annotations.h"
#include "server/transport_security.h"

namespace placedb::server {

namespace {

// httplib's task queue for an endpoint: `threads` workers, and enqueue (called by httplib's
// accepting thread with each accepted connection) waits until one of them is free. Connections
// beyond the workers therefore wait in the kernel's listen backlog instead of piling up accepted
// (each holding a descriptor) in an unbounded queue, as httplib's own ThreadPool would.
class EndpointWorkers final : public httplib::TaskQueue {
 public:
  explicit EndpointWorkers(int threads) : free_(std::max(threads, 1)) {
    for (int i = 0; i < free_; ++i) workers_.emplace_back([this] { Work(); });
  }
  ~EndpointWorkers() override { shutdown(); }

  void enqueue(std::function<void()> job) override {
    MutexLock lock(mutex_);
    while (free_ == 0) changed_.Wait(mutex_);  // a worker frees up within the request timeout
    --free_;
    jobs_.push_back(std::move(job));
    changed_.NotifyAll();
  }

  // Runs the queued jobs, then joins the workers (httplib calls it once its accept loop ended).
  void shutdown() override {
    {
      MutexLock lock(mutex_);
      stopping_ = true;
      changed_.NotifyAll();
    }
    for (std::thread& worker : workers_) {
      if (worker.joinable()) worker.join();
    }
  }

 private:
  void Work() {
    // A scraper that closes early makes a write (SSL_write has no MSG_NOSIGNAL) raise SIGPIPE in
    // this thread: an error return instead.
    sigset_t pipe;
    sigemptyset(&pipe);
    sigaddset(&pipe, SIGPIPE);
    pthread_sigmask(SIG_BLOCK, &pipe, nullptr);
    MutexLock lock(mutex_);
    while (true) {
      while (jobs_.empty() && !stopping_) changed_.Wait(mutex_);
      if (jobs_.empty()) return;  // stopping_
      std::function<void()> job = std::move(jobs_.front());
      jobs_.pop_front();
      lock.Unlock();
      job();  // serves one connection and closes it
      lock.Lock();
      ++free_;
      changed_.NotifyAll();
    }
  }

  Mutex mutex_;
  CondVar changed_;
  int free_ GUARDED_BY(mutex_);  // workers neither busy nor promised to a queued job
  std::deque<std::function<void()>> jobs_ GUARDED_BY(mutex_);
  bool stopping_ GUARDED_BY(mutex_) = false;
  std::vector<std::thread> workers_;
};

// httplib's Server or SSLServer, with its listening socket (a protected member) reachable: httplib
// listens with a backlog of 5, raised after the bind so that connections beyond the workers wait
// for one instead of having their SYNs dropped (their clients would retry only after seconds).
template <class Base>
class HttpServer final : public Base {
 public:
  using Base::Base;
  void RaiseBacklog() { ::listen(this->svr_sock_, SOMAXCONN); }
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
  std::unique_ptr<httplib::Server> http;
  std::function<void()> raise_backlog;
  if (settings.tls) {
    Status tls_status;
    const TlsSettings tls = *settings.tls;
    auto https =
        std::make_unique<HttpServer<httplib::SSLServer>>([&tls_status, &tls](SSL_CTX& context) {
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
    auto plain = std::make_unique<HttpServer<httplib::Server>>();
    raise_backlog = [server = plain.get()] { server->RaiseBacklog(); };
    http = std::move(plain);
  }

  const int threads = settings.threads;
  http->new_task_queue = [threads] { return new EndpointWorkers(threads); };
  // One request per connection ("Connection: close"): an idle kept-alive connection would hold a
  // worker. The wait for a request's first byte is in whole seconds (httplib's keep-alive
  // timeout); every read and write after it is bounded by request_timeout_ms.
  http->set_keep_alive_max_count(1);
  http->set_keep_alive_timeout(std::max<time_t>(1, (settings.request_timeout_ms + 999) / 1000));
  const auto timeout = std::chrono::milliseconds(settings.request_timeout_ms);
  http->set_read_timeout(timeout);
  http->set_write_timeout(timeout);
  if (settings.max_request_bytes > 0) {
    http->set_payload_max_length(size_t(settings.max_request_bytes));
  }
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
          spdlog::error("{}: request failed: {}", name, e.what());
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
  port_ = port;
  return Status::Ok();
}

void HttpEndpoint::Stop() {
  if (http_) http_->stop();
  if (thread_.joinable()) thread_.join();
  http_.reset();
  port_ = 0;
}

}  // namespace placedb::server
