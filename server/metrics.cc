#include "server/metrics.h"

#include <httplib.h>
#include <openssl/evp.h>
#include <prometheus/collectable.h>
#include <prometheus/text_serializer.h>
#include <pthread.h>
#include <signal.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>

#include <algorithm>
#include <cctype>
#include <deque>
#include <exception>
#include <string>
#include <utility>
#include <vector>

#include "core/base/thread_annotations.h"
#include "server/transport_security.h"

namespace placedb::server {

namespace {

using prometheus::BuildCounter;
using prometheus::BuildGauge;
using prometheus::BuildHistogram;

// Seconds, 0.25 ms .. ~33 s in factors of ~2.
prometheus::Histogram::BucketBoundaries SecondsBuckets() {
  prometheus::Histogram::BucketBoundaries buckets;
  for (double b = 0.00025; b < 40; b *= 2) buckets.push_back(b);
  return buckets;
}

// The registry, with a hook that runs before every collection.
class RefreshingCollectable final : public prometheus::Collectable {
 public:
  RefreshingCollectable(std::shared_ptr<prometheus::Registry> registry,
                        std::function<void()> before)
      : registry_(std::move(registry)), before_(std::move(before)) {}
  std::vector<prometheus::MetricFamily> Collect() const override {
    if (before_) before_();
    return registry_->Collect();
  }

 private:
  std::shared_ptr<prometheus::Registry> registry_;
  std::function<void()> before_;
};

// httplib's task queue for the endpoint: `threads` workers, and enqueue (called by httplib's
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

// The credentials of an `Authorization: Basic <base64 of user:password>` header (RFC 7617; the
// scheme is case-insensitive); nullopt for another scheme, base64 that is not canonical
// (alphabet, length a multiple of 4, padding only at the end) or a decoded text without ':'.
std::optional<std::pair<std::string, std::string>> ParseBasicAuth(const std::string& header) {
  constexpr std::string_view kScheme = "basic ";
  if (header.size() <= kScheme.size()) return std::nullopt;
  for (size_t i = 0; i < kScheme.size(); ++i) {
    if (std::tolower(static_cast<unsigned char>(header[i])) != kScheme[i]) return std::nullopt;
  }
  std::string encoded = header.substr(kScheme.size());
  const auto first = encoded.find_first_not_of(' ');
  const auto last = encoded.find_last_not_of(' ');
  if (first == std::string::npos) return std::nullopt;
  encoded = encoded.substr(first, last - first + 1);
  if (encoded.size() % 4 != 0) return std::nullopt;
  const size_t padding = encoded.size() - (encoded.find_last_not_of('=') + 1);
  if (padding > 2) return std::nullopt;
  for (size_t i = 0; i + padding < encoded.size(); ++i) {
    const unsigned char c = static_cast<unsigned char>(encoded[i]);
    if (!std::isalnum(c) && c != '+' && c != '/') return std::nullopt;
  }
  // EVP_DecodeBlock writes 3 bytes per 4 characters, padding included (as zero bytes).
  std::string decoded(encoded.size() / 4 * 3, '\0');
  const int size =
      EVP_DecodeBlock(reinterpret_cast<unsigned char*>(decoded.data()),
                      reinterpret_cast<const unsigned char*>(encoded.data()), int(encoded.size()));
  if (size < 0 || size_t(size) != decoded.size()) return std::nullopt;
  decoded.resize(decoded.size() - padding);
  const auto colon = decoded.find(':');
  if (colon == std::string::npos) return std::nullopt;
  return std::make_pair(decoded.substr(0, colon), decoded.substr(colon + 1));
}

// A scraper's address as gRPC writes a peer ("ipv4:10.0.0.7:53122", "ipv6:[::1]:40112"), so
// that audit lines read the same for RPCs and scrapes.
std::string PeerName(const httplib::Request& request) {
  const std::string& address = request.remote_addr;
  const std::string port = std::to_string(request.remote_port);
  if (address.find(':') != std::string::npos) return "ipv6:[" + address + "]:" + port;
  return "ipv4:" + address + ":" + port;
}

}  // namespace

Metrics::Metrics()
    : registry_(std::make_shared<prometheus::Registry>()),
      requests_(BuildCounter()
                    .Name("placedb_rpc_requests_total")
                    .Help("RPCs served, by method and final gRPC status code")
                    .Register(*registry_)),
      stages_(BuildHistogram()
                  .Name("placedb_stage_seconds")
                  .Help("Time per pipeline stage of one frame (decode, detect, extract, depth, "
                        "filter, transform, search, verify, store, loop_closure, total)")
                  .Register(*registry_)),
      detector_(BuildHistogram()
                    .Name("placedb_detector_seconds")
                    .Help("Server-side object detection time per frame")
                    .Register(*registry_)),
      ingested_(BuildCounter()
                    .Name("placedb_frames_ingested_total")
                    .Help("Ingested frames stored as places")
                    .Register(*registry_)),
      rejected_(BuildCounter()
                    .Name("placedb_frames_rejected_total")
                    .Help("Ingested frames not stored, by reason (invalid_place: too few static "
                          "descriptors; otherwise the lower-case gRPC code of the error)")
                    .Register(*registry_)),
      descriptors_(BuildCounter()
                       .Name("placedb_descriptors_total")
                       .Help("Descriptors of processed ingested frames, by class (dynamic: "
                             "dropped, depth_removed: dropped by the depth filter, static: kept)")
                       .Register(*registry_)),
      merged_(BuildCounter()
                  .Name("placedb_frames_merged_total")
                  .Help("Ingested frames merged into the previous place by loop-closure "
                        "rehearsal (not stored)")
                  .Register(*registry_)),
      loops_(BuildCounter()
                 .Name("placedb_loop_closures_total")
                 .Help("Loop closures accepted on ingest streams in loop-closure mode")
                 .Register(*registry_)),
      loops_rejected_(BuildCounter()
                          .Name("placedb_loop_closures_rejected_total")
                          .Help("Loop closures the Bayesian filter accepted that failed geometric "
                                "verification (not reported as loops)")
                          .Register(*registry_)),
      storage_errors_(BuildCounter()
                          .Name("placedb_storage_errors_total")
                          .Help("Failed storage operations of a map, by kind (disk_full, "
                                "io_error, corruption)")
                          .Register(*registry_)),
      places_(
          BuildGauge().Name("placedb_places").Help("Places stored in a map").Register(*registry_)),
      disk_bytes_(BuildGauge()
                      .Name("placedb_map_on_disk_bytes")
                      .Help("Bytes of a map's files on disk")
                      .Register(*registry_)),
      dynamic_coverage_(BuildGauge()
                            .Name("placedb_map_dynamic_coverage")
                            .Help("Mean share of the view covered by dynamic objects over the "
                                  "frames a map stored or merged (0..1)")
                            .Register(*registry_)),
      damaged_(BuildGauge()
                   .Name("placedb_map_damaged")
                   .Help("1 while a map is damaged (not served until recovered), else 0")
                   .Register(*registry_)),
      places_lost_(BuildGauge()
                       .Name("placedb_map_places_lost")
                       .Help("Acknowledged places a map is missing (damaged) or lost for good "
                             "(recovered)")
                       .Register(*registry_)),
      streams_(BuildGauge()
                   .Name("placedb_streams_in_flight")
                   .Help("Open streams: Ingest, snapshot downloads and uploads")
                   .Register(*registry_)
                   .Add({})),
      streams_reclaimed_(BuildCounter()
                             .Name("placedb_ingest_streams_closed_total")
                             .Help("Ingest streams and snapshot transfers the server closed, by "
                                   "reason (header_timeout: no IngestHeader in time, "
                                   "idle_timeout: nothing received for too long with no frame in "
                                   "flight, write_timeout: the client did not take an answer or "
                                   "chunk for too long)")
                             .Register(*registry_)),
      queue_depth_(BuildGauge()
                       .Name("placedb_queue_depth")
                       .Help("Frames waiting for a worker")
                       .Register(*registry_)
                       .Add({})),
      memory_budget_(BuildGauge()
                         .Name("placedb_memory_budget_bytes")
                         .Help("The memory budget (limits.memory_budget_bytes), by kind: limit, "
                               "fixed (caches), in_use (fixed + requests in flight)")
                         .Register(*registry_)),
      detector_seconds_(detector_.Add({}, SecondsBuckets())),
      auth_denied_(BuildCounter()
                       .Name("placedb_auth_denied_total")
                       .Help("Calls and scrapes refused by authentication or authorization, by "
                             "reason and method (an RPC's name, or metrics)")
                       .Register(*registry_)),
      tokens_reloads_(BuildCounter()
                          .Name("placedb_tokens_reloads_total")
                          .Help("Reloads of the tokens file, by result (ok, or error: the "
                                "previous principals were kept)")
                          .Register(*registry_)),
      snapshots_(BuildGauge()
                     .Name("placedb_snapshots")
                     .Help("Snapshots kept in the data directory, by kind (count; bytes: their "
                           "checkpoints' files)")
                     .Register(*registry_)),
      snapshot_transfer_(BuildCounter()
                             .Name("placedb_snapshot_transfer_bytes_total")
                             .Help("Snapshot archive bytes sent (download) and received (upload)")
                             .Register(*registry_)),
      snapshot_seconds_(BuildHistogram()
                            .Name("placedb_snapshot_seconds")
                            .Help("Time of successful snapshot operations, by operation (create, "
                                  "import: both with verification; restore)")
                            .Register(*registry_)) {
  // Present from the start (at 0), so that a rate over them is defined before the first close.
  for (const char* reason : {"header_timeout", "idle_timeout", "write_timeout"}) {
    streams_reclaimed_.Add({{"reason", reason}});
  }
  for (const char* direction : {"download", "upload"}) {
    snapshot_transfer_.Add({{"direction", direction}});
  }
}

Metrics::~Metrics() {
  StopServing();
}

Status Metrics::Serve(const Endpoint& endpoint, std::function<void()> before_scrape) {
  StopServing();
  collectable_ = std::make_shared<RefreshingCollectable>(registry_, std::move(before_scrape));
  const auto address = SplitListenAddress(endpoint.listen);
  if (!address) {
    return Status::InvalidArgument("metrics endpoint: '" + endpoint.listen +
                                   "' is not host:port or [v6]:port");
  }
  std::unique_ptr<httplib::Server> http;
  std::function<void()> raise_backlog;
  if (endpoint.tls) {
    Status tls_status;
    const TlsSettings tls = *endpoint.tls;
    auto https =
        std::make_unique<HttpServer<httplib::SSLServer>>([&tls_status, &tls](SSL_CTX& context) {
          tls_status = ConfigureSslContext(&context, tls);
          return tls_status.ok();
        });
    raise_backlog = [server = https.get()] { server->RaiseBacklog(); };
    http = std::move(https);
    if (!http->is_valid()) {
      if (tls_status.ok()) tls_status = Status::Internal("cannot create an SSL context");
      return tls_status.WithContext("metrics endpoint (HTTPS)");
    }
  } else {
    auto plain = std::make_unique<HttpServer<httplib::Server>>();
    raise_backlog = [server = plain.get()] { server->RaiseBacklog(); };
    http = std::move(plain);
  }

  const int threads = endpoint.threads;
  http->new_task_queue = [threads] { return new EndpointWorkers(threads); };
  // One request per connection ("Connection: close"): an idle kept-alive connection would hold a
  // worker. The wait for a request's first byte is in whole seconds (httplib's keep-alive
  // timeout); every read and write after it is bounded by request_timeout_ms.
  http->set_keep_alive_max_count(1);
  http->set_keep_alive_timeout(std::max<time_t>(1, (endpoint.request_timeout_ms + 999) / 1000));
  const auto timeout = std::chrono::milliseconds(endpoint.request_timeout_ms);
  http->set_read_timeout(timeout);
  http->set_write_timeout(timeout);
  // SO_REUSEADDR only: httplib's default also sets SO_REUSEPORT, with which a second server of
  // the same user would share the port instead of failing to bind it.
  http->set_socket_options([](socket_t socket) {
    const int yes = 1;
    setsockopt(socket, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
  });
  // Exceptions from a scrape are logged, and answered 500 without their text (httplib's default
  // would put it in a header).
  http->set_exception_handler(
      [](const httplib::Request&, httplib::Response& response, std::exception_ptr error) {
        try {
          if (error) std::rethrow_exception(error);
        } catch (const std::exception& e) {
          spdlog::error("metrics endpoint: scrape failed: {}", e.what());
        } catch (...) {
          spdlog::error("metrics endpoint: scrape failed");
        }
        response.status = 500;
      });

  // Everything is answered here, before httplib's routing (which would read a body first).
  const std::string path = endpoint.path;
  const auto authorize = endpoint.authorize;
  const std::shared_ptr<prometheus::Collectable> collectable = collectable_;
  http->set_pre_routing_handler([path, authorize, collectable](const httplib::Request& request,
                                                               httplib::Response& response) {
    if (request.path != path) {
      response.status = 404;
    } else if (request.method != "GET") {
      response.status = 405;
      response.set_header("Allow", "GET");
    } else {
      std::optional<std::pair<std::string, std::string>> credentials;
      if (authorize && request.has_header("Authorization")) {
        credentials = ParseBasicAuth(request.get_header_value("Authorization"));
      }
      if (authorize && (!credentials ||
                        !authorize(PeerName(request), credentials->first, credentials->second))) {
        response.status = 401;
        response.set_header("WWW-Authenticate", "Basic realm=\"placedb\"");
      } else {
        response.status = 200;
        response.set_content(prometheus::TextSerializer().Serialize(collectable->Collect()),
                             "text/plain; version=0.0.4; charset=utf-8");
      }
    }
    return httplib::Server::HandlerResponse::Handled;
  });

  const int port =
      address->second == 0
          ? http->bind_to_any_port(address->first)
          : (http->bind_to_port(address->first, address->second) ? address->second : -1);
  if (port <= 0) {
    return Status::IoError("metrics endpoint: cannot listen on " + endpoint.listen +
                           " (address in use, or not a local address?)");
  }
  raise_backlog();
  // Listening since the bind: connections made before the loop starts wait in the backlog.
  httplib::Server* server = http.get();
  http_thread_ = std::thread([server] { server->listen_after_bind(); });
  http_ = std::move(http);
  port_ = port;
  return Status::Ok();
}

void Metrics::StopServing() {
  if (http_) http_->stop();
  if (http_thread_.joinable()) http_thread_.join();
  http_.reset();
  port_ = 0;
}

void Metrics::CountRequest(const std::string& method, const std::string& code) {
  requests_.Add({{"method", method}, {"code", code}}).Increment();
}

void Metrics::ObserveStage(const std::string& stage, double seconds) {
  stages_.Add({{"stage", stage}}, SecondsBuckets()).Observe(seconds);
}

void Metrics::ObserveDetector(double seconds) {
  detector_seconds_.Observe(seconds);
}

void Metrics::FrameIngested(const std::string& map) {
  ingested_.Add({{"map", map}}).Increment();
}

void Metrics::FrameRejected(const std::string& map, const std::string& reason) {
  rejected_.Add({{"map", map}, {"reason", reason}}).Increment();
}

void Metrics::CountDescriptors(const std::string& map, uint64_t dynamic, uint64_t depth_removed,
                               uint64_t static_count) {
  descriptors_.Add({{"map", map}, {"class", "dynamic"}}).Increment(double(dynamic));
  descriptors_.Add({{"map", map}, {"class", "depth_removed"}}).Increment(double(depth_removed));
  descriptors_.Add({{"map", map}, {"class", "static"}}).Increment(double(static_count));
}

void Metrics::FrameMerged(const std::string& map) {
  merged_.Add({{"map", map}}).Increment();
}

void Metrics::LoopClosed(const std::string& map) {
  loops_.Add({{"map", map}}).Increment();
}

void Metrics::LoopRejected(const std::string& map) {
  loops_rejected_.Add({{"map", map}}).Increment();
}

namespace {
// The kinds a storage error is counted under (Metrics::StorageError), in one place for
// ForgetMap.
constexpr std::pair<StatusCode, const char*> kStorageErrorKinds[] = {
    {StatusCode::kResourceExhausted, "disk_full"},
    {StatusCode::kIoError, "io_error"},
    {StatusCode::kCorruption, "corruption"}};
}  // namespace

void Metrics::StorageError(const std::string& map, const Status& status) {
  for (const auto& [code, kind] : kStorageErrorKinds) {
    if (status.code() == code) storage_errors_.Add({{"map", map}, {"kind", kind}}).Increment();
  }
}

void Metrics::SetMapGauges(const std::string& map, double places, double bytes_on_disk) {
  places_.Add({{"map", map}}).Set(places);
  disk_bytes_.Add({{"map", map}}).Set(bytes_on_disk);
}

void Metrics::SetMapDynamicCoverage(const std::string& map, double mean_coverage) {
  dynamic_coverage_.Add({{"map", map}}).Set(mean_coverage);
}

void Metrics::SetMapDamage(const std::string& map, bool damaged, double places_lost) {
  damaged_.Add({{"map", map}}).Set(damaged ? 1 : 0);
  places_lost_.Add({{"map", map}}).Set(places_lost);
}

void Metrics::ForgetMap(const std::string& map) {
  // Family::Add returns the existing series for known labels, so this finds them to remove.
  // Only the label sets this class creates are removed (rejection reasons are a closed set).
  places_.Remove(&places_.Add({{"map", map}}));
  disk_bytes_.Remove(&disk_bytes_.Add({{"map", map}}));
  dynamic_coverage_.Remove(&dynamic_coverage_.Add({{"map", map}}));
  damaged_.Remove(&damaged_.Add({{"map", map}}));
  places_lost_.Remove(&places_lost_.Add({{"map", map}}));
  ingested_.Remove(&ingested_.Add({{"map", map}}));
  merged_.Remove(&merged_.Add({{"map", map}}));
  loops_.Remove(&loops_.Add({{"map", map}}));
  loops_rejected_.Remove(&loops_rejected_.Add({{"map", map}}));
  for (const auto& [code, kind] : kStorageErrorKinds) {
    storage_errors_.Remove(&storage_errors_.Add({{"map", map}, {"kind", kind}}));
  }
  for (const char* cls : {"dynamic", "depth_removed", "static"}) {
    descriptors_.Remove(&descriptors_.Add({{"map", map}, {"class", cls}}));
  }
  for (const char* reason :
       {"invalid_place", "cancelled", "unknown", "invalid_argument", "deadline_exceeded",
        "not_found", "already_exists", "permission_denied", "resource_exhausted",
        "failed_precondition", "aborted", "out_of_range", "unimplemented", "internal",
        "unavailable", "data_loss", "unauthenticated"}) {
    rejected_.Remove(&rejected_.Add({{"map", map}, {"reason", reason}}));
  }
}

void Metrics::StreamOpened() {
  streams_.Increment();
}
void Metrics::StreamClosed() {
  streams_.Decrement();
}
void Metrics::StreamReclaimed(const std::string& reason) {
  streams_reclaimed_.Add({{"reason", reason}}).Increment();
}
void Metrics::SetSnapshotGauges(double count, double bytes) {
  snapshots_.Add({{"kind", "count"}}).Set(count);
  snapshots_.Add({{"kind", "bytes"}}).Set(bytes);
}
void Metrics::SnapshotBytesSent(uint64_t bytes) {
  snapshot_transfer_.Add({{"direction", "download"}}).Increment(double(bytes));
}
void Metrics::SnapshotBytesReceived(uint64_t bytes) {
  snapshot_transfer_.Add({{"direction", "upload"}}).Increment(double(bytes));
}
void Metrics::ObserveSnapshot(const std::string& operation, double seconds) {
  snapshot_seconds_.Add({{"operation", operation}}, SecondsBuckets()).Observe(seconds);
}
void Metrics::SetQueueDepth(size_t depth) {
  queue_depth_.Set(double(depth));
}

void Metrics::SetMemoryBudget(uint64_t limit, uint64_t fixed, uint64_t in_use) {
  memory_budget_.Add({{"kind", "limit"}}).Set(double(limit));
  memory_budget_.Add({{"kind", "fixed"}}).Set(double(fixed));
  memory_budget_.Add({{"kind", "in_use"}}).Set(double(in_use));
}

void Metrics::AuthDenied(const std::string& reason, const std::string& method) {
  auth_denied_.Add({{"reason", reason}, {"method", method}}).Increment();
}

void Metrics::TokensReloaded(bool ok) {
  tokens_reloads_.Add({{"result", ok ? "ok" : "error"}}).Increment();
}

}  // namespace placedb::server
