// PlaceDbService's own life: construction, the calls in flight, their answers counted and logged,
// drain and the streams' watchdog. The handlers: maps.cc, places.cc, query.cc, ingest.cc,
// snapshots.cc, info.cc (this folder).
#include "server/rpc/service.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <string>

#include "proto/status.h"
#include "server/rpc/call_support.h"

namespace placedb::server {

using wire::GrpcCodeName;
using wire::HidePaths;

PlaceDbService::PlaceDbService(const ServerConfig& config, MapRegistry* maps, MapBackend* backend,
                               WorkerPool* pool, Metrics* metrics, const Detector* detector,
                               std::string detector_status, MemoryBudget* budget,
                               WorkerPool* query_pool)
    : config_(config),
      maps_(maps),
      pool_(pool),
      query_pool_(query_pool ? query_pool : pool),
      metrics_(metrics),
      detector_(detector),
      detector_status_(std::move(detector_status)),
      budget_(budget),
      backend_(backend),
      watchdog_([this] { Watchdog(); }) {
  // Maps that need the detector say so at startup and restore (MapRegistry::MissingFor).
  if (maps_) maps_->SetDetector(detector_ != nullptr, detector_status_);
}

PlaceDbService::~PlaceDbService() {
  {
    MutexLock lock(streams_mutex_);
    stopping_ = true;
    watchdog_wake_.NotifyAll();
  }
  watchdog_.join();
}

bool PlaceDbService::WaitIdle(std::chrono::steady_clock::time_point deadline) {
  MutexLock lock(calls_mutex_);
  while (calls_in_flight_ != 0) {
    if (!calls_idle_.WaitUntil(calls_mutex_, deadline)) return calls_in_flight_ == 0;
  }
  return true;
}

grpc::Status PlaceDbService::Finish(const char* method, grpc::ServerContext* context,
                                    grpc::Status status) {
  metrics_->CountRequest(method, GrpcCodeName(status.error_code()));
  if (!status.ok()) {
    spdlog::warn("rpc error method={} code={} peer={} message=\"{}\"", method,
                 GrpcCodeName(status.error_code()), Peer(context), ForLog(status.error_message()));
  }
  return HidePaths(status, config_.data_dir);  // the log keeps the server's paths, not the client
}

grpc::Status PlaceDbService::Unavailable() const {
  return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is shutting down");
}

void PlaceDbService::ObserveStages(const StageTimings& t) {
  auto observe = [&](const char* stage, double ms) { metrics_->ObserveStage(stage, ms / 1000.0); };
  if (t.decode_ms > 0) observe("decode", t.decode_ms);
  if (t.detect_ms > 0) observe("detect", t.detect_ms);
  observe("extract", t.extract_ms);
  if (t.depth_ms > 0) observe("depth", t.depth_ms);
  if (t.refine_ms > 0) observe("refine", t.refine_ms);
  observe("filter", t.filter_ms);
  if (t.transform_ms > 0) observe("transform", t.transform_ms);
  if (t.search_ms > 0) observe("search", t.search_ms);
  if (t.verify_ms > 0) observe("verify", t.verify_ms);
  if (t.pose_ms > 0) observe("pose", t.pose_ms);
  if (t.store_ms > 0) observe("store", t.store_ms);
  if (t.loop_closure_ms > 0) observe("loop_closure", t.loop_closure_ms);
  observe("total", t.total_ms);
}

grpc::Status PlaceDbService::RefuseMalformed(const char* method, grpc::ServerContext* context,
                                             grpc::Status status) {
  CallScope scope(this);
  return Finish(method, context, std::move(status));
}

// ---- Shutdown and gauges ------------------------------------------------------------------------

void PlaceDbService::Watchdog() {
  const Limits& limits = config_.limits;
  // A tenth of the shorter timeout: a stream is closed within 10% after its time is up.
  const auto tick =
      std::clamp(std::chrono::milliseconds(
                     std::min(limits.stream_header_timeout_ms, limits.stream_idle_timeout_ms) / 10),
                 std::chrono::milliseconds(10), std::chrono::milliseconds(1000));
  MutexLock lock(streams_mutex_);
  while (!stopping_) {
    ReclaimExpired(Clock::now());
    watchdog_wake_.WaitFor(streams_mutex_, tick);
  }
}

void PlaceDbService::ReclaimExpired(Clock::time_point now) {
  const Limits& limits = config_.limits;
  const auto header_timeout = std::chrono::milliseconds(limits.stream_header_timeout_ms);
  const auto idle_timeout = std::chrono::milliseconds(limits.stream_idle_timeout_ms);
  for (Watch* watch : watches_) {
    MutexLock lock(watch->mutex);
    if (watch->closed_reason) continue;  // already cancelled; its handler is on its way out
    const bool ingest = std::string_view(watch->method) == "Ingest";
    if (!watch->header) {
      if (now - watch->opened < header_timeout) continue;
      watch->closed_reason = "header_timeout";
      watch->closed_why = "no IngestHeader within limits.stream_header_timeout_ms = " +
                          std::to_string(limits.stream_header_timeout_ms) + " ms";
    } else if (watch->writing_since && now - *watch->writing_since >= idle_timeout) {
      // Not idle (an answer is pending), but the client stopped reading: flow control holds the
      // write and, through it, the stream's thread and slot.
      watch->closed_reason = "write_timeout";
      watch->closed_why = std::string("the client took no ") + (ingest ? "answer" : "chunk") +
                          " within limits.stream_idle_timeout_ms = " +
                          std::to_string(limits.stream_idle_timeout_ms) + " ms";
    } else if (watch->in_flight == 0 && now - watch->quiet_since >= idle_timeout) {
      watch->closed_reason = "idle_timeout";
      watch->closed_why =
          std::string(ingest ? "no frame in flight and nothing received" : "nothing received") +
          " within limits.stream_idle_timeout_ms = " +
          std::to_string(limits.stream_idle_timeout_ms) + " ms";
    } else {
      continue;
    }
    // The synchronous API has no way to end a call whose handler is blocked in Read() or
    // Write() but to cancel it: the client sees CANCELLED; this log line and the metric say why.
    metrics_->StreamReclaimed(watch->closed_reason);  // counted before the client can see it
    watch->context->TryCancel();
    spdlog::warn("{} stream closed by the server peer={} reason={}: {} (open {:.3f}s)",
                 watch->method, watch->peer, watch->closed_reason, watch->closed_why,
                 std::chrono::duration<double>(now - watch->opened).count());
  }
}

void PlaceDbService::RefreshMapGauges() {
  backend_->RefreshGauges();
}

}  // namespace placedb::server
