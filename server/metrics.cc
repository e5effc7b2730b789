#include "server/metrics.h"

#include <prometheus/collectable.h>
#include <prometheus/exposer.h>

#include <exception>
#include <string>
#include <vector>

#include "server/tls_relay.h"

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
                   .Help("Open Ingest streams")
                   .Register(*registry_)
                   .Add({})),
      streams_reclaimed_(BuildCounter()
                             .Name("placedb_ingest_streams_closed_total")
                             .Help("Ingest streams the server closed, by reason (header_timeout: "
                                   "no IngestHeader in time, idle_timeout: nothing received for "
                                   "too long with no frame in flight, write_timeout: the client "
                                   "did not take an answer for too long)")
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
                          .Register(*registry_)) {
  // Present from the start (at 0), so that a rate over them is defined before the first close.
  for (const char* reason : {"header_timeout", "idle_timeout", "write_timeout"}) {
    streams_reclaimed_.Add({{"reason", reason}});
  }
}

Metrics::~Metrics() {
  StopServing();
}

Status Metrics::Serve(const Endpoint& endpoint, std::function<void()> before_scrape) {
  collectable_ = std::make_shared<RefreshingCollectable>(registry_, std::move(before_scrape));
  // civetweb's options (civetweb 1.15): a connection holds a worker while it is open, and
  // request_timeout_ms bounds every read and write of a request, so a client that never finishes
  // its request header loses its connection instead of holding a worker for good. No keep-alive:
  // a scraper's idle connection would hold a worker too.
  // HTTPS: civetweb serves plaintext on loopback behind a TLS relay (server/tls_relay.h says why).
  const std::string http_listen = endpoint.tls ? "127.0.0.1:0" : endpoint.listen;
  std::vector<std::string> options = {
      "listening_ports",    http_listen,
      "num_threads",        std::to_string(endpoint.threads),
      "request_timeout_ms", std::to_string(endpoint.request_timeout_ms),
      "enable_keep_alive",  "no",
  };
  try {
    exposer_ = std::make_unique<prometheus::Exposer>(std::move(options));
  } catch (const std::exception& e) {
    return Status::IoError("metrics endpoint: cannot listen on " + http_listen + ": " + e.what());
  }
  exposer_->RegisterCollectable(collectable_, endpoint.path);
  if (endpoint.authorize) exposer_->RegisterAuth(endpoint.authorize, "placedb", endpoint.path);
  const std::vector<int> ports = exposer_->GetListeningPorts();
  port_ = ports.empty() ? 0 : ports.front();
  if (endpoint.tls) {
    auto relay = TlsRelay::Start({.listen = endpoint.listen,
                                  .backend_port = port_,
                                  .tls = *endpoint.tls,
                                  .threads = endpoint.threads,
                                  .timeout_ms = endpoint.request_timeout_ms});
    if (!relay.ok()) {
      StopServing();
      return relay.status().WithContext("metrics endpoint (HTTPS)");
    }
    tls_relay_ = std::move(relay).value();
    port_ = tls_relay_->port();
  }
  return Status::Ok();
}

void Metrics::StopServing() {
  tls_relay_.reset();
  exposer_.reset();
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

void Metrics::SetMapDamage(const std::string& map, bool damaged, double places_lost) {
  damaged_.Add({{"map", map}}).Set(damaged ? 1 : 0);
  places_lost_.Add({{"map", map}}).Set(places_lost);
}

void Metrics::ForgetMap(const std::string& map) {
  // Family::Add returns the existing series for known labels, so this finds them to remove.
  // Only the label sets this class creates are removed (rejection reasons are a closed set).
  places_.Remove(&places_.Add({{"map", map}}));
  disk_bytes_.Remove(&disk_bytes_.Add({{"map", map}}));
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
