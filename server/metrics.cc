#include "server/metrics.h"

#include <httplib.h>
#include <openssl/evp.h>
#include <prometheus/collectable.h>
#include <prometheus/text_serializer.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cctype>
#include <string>
#include <utility>
#include <vector>

#include "server/net/http_endpoint.h"

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
  HttpEndpointSettings settings;
  settings.name = "metrics endpoint";
  settings.listen = endpoint.listen;
  settings.threads = endpoint.threads;
  settings.request_timeout_ms = endpoint.request_timeout_ms;
  settings.tls = endpoint.tls;
  // Everything is answered here, before httplib's routing (which would read a body first).
  const std::string path = endpoint.path;
  const auto authorize = endpoint.authorize;
  const std::shared_ptr<prometheus::Collectable> collectable = collectable_;
  auto routes = [path, authorize, collectable](httplib::Server& http) {
    http.set_pre_routing_handler([path, authorize, collectable](const httplib::Request& request,
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
        if (authorize && (!credentials || !authorize(HttpPeerName(request), credentials->first,
                                                     credentials->second))) {
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
  };
  auto http = std::make_unique<HttpEndpoint>();
  PLACEDB_RETURN_IF_ERROR(http->Serve(settings, routes));
  http_ = std::move(http);
  port_ = http_->port();
  return Status::Ok();
}

void Metrics::StopServing() {
  if (http_) http_->Stop();
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
