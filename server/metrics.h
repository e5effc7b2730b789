// Prometheus metrics of the service (prometheus-cpp; docs/service.md lists them).
//
// Per-map gauges (places, bytes on disk) are refreshed when the endpoint is scraped, through a
// callback, so they are never stale and cost nothing between scrapes.
#pragma once

#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>

#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "core/base/status.h"
#include "server/config.h"

namespace placedb::server {

class HttpEndpoint;

class Metrics {
 public:
  Metrics();
  ~Metrics();

  // How the endpoint serves HTTP (server/net/http_endpoint.h: cpp-httplib, plaintext or HTTPS,
  // `threads` workers, one request per connection, `request_timeout_ms` per read and write).
  struct Endpoint {
    std::string listen;  // host:port or [v6]:port; port 0 picks one
    std::string path;    // the only path served (GET); other paths 404, other methods 405
    int threads = 4;
    uint32_t request_timeout_ms = 5000;
    // Set: HTTPS only, TLS 1.2 or later with these files, and with tls->mutual() a client
    // certificate signed by one of its CAs is required at the handshake.
    std::optional<TlsSettings> tls;
    // When set, every scrape needs HTTP basic auth that this accepts (`peer`: the scraper's
    // address as "ipv4:a.b.c.d:port" or "ipv6:[...]:port", for the audit line). Without an
    // `Authorization: Basic` header, or with one that does not decode to user:password, the
    // answer is 401 without asking (server/auth/call_auth.h, AuthorizeScrape).
    std::function<bool(const std::string& peer, const std::string& user,
                       const std::string& password)>
        authorize;
  };
  // Serves the metrics: each scrape runs `before_scrape` (to refresh the per-map gauges), then
  // answers the registry in Prometheus' text format. INVALID_ARGUMENT for a listen address that
  // is not host:port; IO_ERROR when it cannot be bound (in use: SO_REUSEPORT is not set, so a
  // second server cannot share the port); with TLS, the errors of LoadTlsFiles
  // (server/net/transport_security.h) for bad files. On failure nothing is served.
  Status Serve(const Endpoint& endpoint, std::function<void()> before_scrape);
  int port() const { return port_; }  // the bound port; 0 when not serving
  // Stops accepting and waits for the connections being served (each ends within its timeouts).
  void StopServing();

  const std::shared_ptr<prometheus::Registry>& registry() const { return registry_; }

  // `code` is the canonical upper-case gRPC code name ("OK", "INVALID_ARGUMENT", ...).
  void CountRequest(const std::string& method, const std::string& code);
  // Stage: decode, detect, extract, depth, filter, transform, search, verify, store,
  // loop_closure, total.
  void ObserveStage(const std::string& stage, double seconds);
  void ObserveDetector(double seconds);
  void FrameIngested(const std::string& map);
  void FrameRejected(const std::string& map, const std::string& reason);
  // A processed ingested frame's descriptors: dynamic (DC, dropped), depth_removed (Algorithm 1)
  // and static (kept).
  void CountDescriptors(const std::string& map, uint64_t dynamic, uint64_t depth_removed,
                        uint64_t static_count);
  // Loop-closure mode: a frame merged into the previous place by rehearsal (not stored), and
  // an accepted loop closure.
  void FrameMerged(const std::string& map);
  void LoopClosed(const std::string& map);
  void LoopRejected(const std::string& map);  // accepted by the filter, failed verification
  // A failed write (or storage read) of a map, by kind: disk_full (RESOURCE_EXHAUSTED), io_error,
  // corruption; other codes are not storage errors and are not counted.
  void StorageError(const std::string& map, const Status& status);
  void SetMapGauges(const std::string& map, double places, double bytes_on_disk);
  // placedb_map_dynamic_coverage: the mean share of the view dynamic objects covered, over
  // every frame the map stored or merged (its dynamic-object statistics, issue 16).
  void SetMapDynamicCoverage(const std::string& map, double mean_coverage);
  // A map's damage (docs/storage.md, "Damage"): placedb_map_damaged 1 while it is damaged, and
  // placedb_map_places_lost, the acknowledged places found missing (damaged) or accepted as
  // lost (recovered).
  void SetMapDamage(const std::string& map, bool damaged, double places_lost);
  void ForgetMap(const std::string& map);  // a deleted map's series go away
  void StreamOpened();
  void StreamClosed();
  // The server closed an Ingest stream or a snapshot transfer: "header_timeout" (Ingest only),
  // "idle_timeout" or "write_timeout".
  void StreamReclaimed(const std::string& reason);
  // Snapshots: placedb_snapshots{kind="count"|"bytes"} (the snapshot store, set before each
  // scrape), placedb_snapshot_transfer_bytes_total{direction="download"|"upload"} (archive bytes
  // sent and received) and placedb_snapshot_seconds{operation="create"|"import"|"restore"}
  // (successful operations, verification included).
  void SetSnapshotGauges(double count, double bytes);
  void SnapshotBytesSent(uint64_t bytes);
  void SnapshotBytesReceived(uint64_t bytes);
  void ObserveSnapshot(const std::string& operation, double seconds);
  void SetQueueDepth(size_t depth);
  // The memory budget (limits.memory_budget_bytes): its limit, fixed part and bytes in use.
  void SetMemoryBudget(uint64_t limit, uint64_t fixed, uint64_t in_use);
  // A call or scrape refused by authentication/authorization (docs/security.md, "Audit"):
  // placedb_auth_denied_total{reason,method}; `method` is the RPC's name or "metrics".
  void AuthDenied(const std::string& reason, const std::string& method);
  // A reload of the tokens file: placedb_tokens_reloads_total{result="ok"|"error"}.
  void TokensReloaded(bool ok);

 private:
  std::shared_ptr<prometheus::Registry> registry_;
  prometheus::Family<prometheus::Counter>& requests_;
  prometheus::Family<prometheus::Histogram>& stages_;
  prometheus::Family<prometheus::Histogram>& detector_;
  prometheus::Family<prometheus::Counter>& ingested_;
  prometheus::Family<prometheus::Counter>& rejected_;
  prometheus::Family<prometheus::Counter>& descriptors_;
  prometheus::Family<prometheus::Counter>& merged_;
  prometheus::Family<prometheus::Counter>& loops_;
  prometheus::Family<prometheus::Counter>& loops_rejected_;
  prometheus::Family<prometheus::Counter>& storage_errors_;
  prometheus::Family<prometheus::Gauge>& places_;
  prometheus::Family<prometheus::Gauge>& disk_bytes_;
  prometheus::Family<prometheus::Gauge>& dynamic_coverage_;
  prometheus::Family<prometheus::Gauge>& damaged_;
  prometheus::Family<prometheus::Gauge>& places_lost_;
  prometheus::Gauge& streams_;
  prometheus::Family<prometheus::Counter>& streams_reclaimed_;
  prometheus::Gauge& queue_depth_;
  prometheus::Family<prometheus::Gauge>& memory_budget_;
  prometheus::Histogram& detector_seconds_;
  prometheus::Family<prometheus::Counter>& auth_denied_;
  prometheus::Family<prometheus::Counter>& tokens_reloads_;
  prometheus::Family<prometheus::Gauge>& snapshots_;
  prometheus::Family<prometheus::Counter>& snapshot_transfer_;
  prometheus::Family<prometheus::Histogram>& snapshot_seconds_;
  std::shared_ptr<prometheus::Collectable> collectable_;  // registry + refresh callback
  std::unique_ptr<HttpEndpoint> http_;                    // server/net/http_endpoint.h
  int port_ = 0;
};

}  // namespace placedb::server
