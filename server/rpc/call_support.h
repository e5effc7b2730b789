// What every handler of PlaceDbService (server/rpc/service.h) shares, one file per RPC group:
// the call's expiry and cancellation, its peer for the log, exceptions turned into INTERNAL, the
// frame being processed (Work), the in-flight call count (CallScope) and the watchdog's view of a
// stream (Watch, WatchScope). Internal to server/rpc/.
#pragma once

#include <grpcpp/grpcpp.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <limits>
#include <optional>
#include <string>

#include "core/base/text.h"
#include "server/rpc/service.h"

namespace placedb::server {

using Clock = std::chrono::steady_clock;

inline double MsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

// Whether the call is over: cancelled by the client (or by us), or past its deadline. gRPC's own
// deadline timer fires asynchronously, so the deadline is also checked here directly: work never
// starts a stage after the deadline.
inline bool Expired(const grpc::ServerContext* context) {
  return context->IsCancelled() || context->deadline() <= std::chrono::system_clock::now();
}

// Expired() for an Ingest stream's many checks (each frame's stages, the pipeline's waits). On
// the synchronous server IsCancelled() polls the call's completion queue (a pollset pass and a
// futex wait): asked 4 times per frame it took about a tenth of the server's CPU under a
// features-only ingest. So it is asked at most once per kCancelCheckInterval per stream; the
// deadline is still checked every time, and a cancellation is seen at most that much later.
class StreamExpiry {
 public:
  explicit StreamExpiry(const grpc::ServerContext* context) : context_(context) {}
  bool operator()() const {
    if (cancelled_.load(std::memory_order_relaxed)) return true;
    if (context_->deadline() <= std::chrono::system_clock::now()) return true;
    const int64_t now = std::chrono::duration_cast<std::chrono::nanoseconds>(
                            std::chrono::steady_clock::now().time_since_epoch())
                            .count();
    int64_t last = checked_ns_.load(std::memory_order_relaxed);
    // Checked recently, or another thread is checking right now.
    if (now - last < kCancelCheckInterval.count() ||
        !checked_ns_.compare_exchange_strong(last, now, std::memory_order_relaxed)) {
      return false;
    }
    if (!context_->IsCancelled()) return false;
    cancelled_.store(true, std::memory_order_relaxed);
    return true;
  }

 private:
  static constexpr std::chrono::nanoseconds kCancelCheckInterval = std::chrono::milliseconds(2);
  const grpc::ServerContext* const context_;
  mutable std::atomic<int64_t> checked_ns_{std::numeric_limits<int64_t>::min() / 2};
  mutable std::atomic<bool> cancelled_{false};
};

// CANCELLED, or DEADLINE_EXCEEDED when the call's deadline has passed.
inline grpc::Status Cancelled(const grpc::ServerContext* context, const char* where) {
  // The client cancels at its deadline, which can reach us a moment before our own clock says
  // the deadline passed: within 100 ms counts as the deadline.
  if (context->deadline() <= std::chrono::system_clock::now() + std::chrono::milliseconds(100)) {
    return grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                        std::string("deadline exceeded; work dropped ") + where);
  }
  return grpc::Status(grpc::StatusCode::CANCELLED,
                      std::string("call cancelled; work dropped ") + where);
}

// How long a unary call may wait for room in the queue: the configured wait, cut short by the
// call's deadline.
inline Clock::time_point QueueWaitUntil(const grpc::ServerContext* context, uint32_t wait_ms) {
  auto wait = std::chrono::duration_cast<Clock::duration>(std::chrono::milliseconds(wait_ms));
  const auto deadline = context->deadline();
  const auto now = std::chrono::system_clock::now();
  if (deadline <= now) return Clock::now();
  if (deadline - now < wait) {
    wait = std::chrono::duration_cast<Clock::duration>(deadline - now);
  }
  return Clock::now() + wait;
}

inline grpc::Status Invalid(const std::string& message) {
  return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, message);
}

// The caller's address as a log line shows it (ForLog, like every client-supplied string).
inline std::string Peer(const grpc::ServerContext* context) {
  return ForLog(context->peer());
}

// Runs `body`, turning an exception (OpenCV throws cv::Exception; allocation can fail) into
// INTERNAL, so that a worker never dies and every frame still gets its answer.
template <typename Body>
grpc::Status Guarded(const char* what, Body&& body) {
  try {
    return body();
  } catch (const std::exception& e) {
    spdlog::error("{}: unexpected exception: {}", what, ForLog(e.what()));
    return grpc::Status(grpc::StatusCode::INTERNAL, std::string(what) + ": " + e.what());
  } catch (...) {
    spdlog::error("{}: unexpected exception", what);
    return grpc::Status(grpc::StatusCode::INTERNAL, std::string(what) + ": unexpected exception");
  }
}

// The call's deadline, for the backend.
inline MapBackend::Deadline DeadlineOf(const grpc::ServerContext* context) {
  return context->deadline();
}

// One frame through the pipeline.
struct PlaceDbService::Work {
  // An Ingest frame's: its stream's cached Expired() (null: ask the context, as queries do).
  const StreamExpiry* expiry = nullptr;
  StageTimings timings;
  ProcessedFrame frame;
  PlaceMetadata metadata;
};

class PlaceDbService::CallScope {
 public:
  explicit CallScope(PlaceDbService* service) : service_(service) {
    MutexLock lock(service_->calls_mutex_);
    ++service_->calls_in_flight_;
  }
  ~CallScope() {
    MutexLock lock(service_->calls_mutex_);
    if (--service_->calls_in_flight_ == 0) service_->calls_idle_.NotifyAll();
  }
  CallScope(const CallScope&) = delete;
  CallScope& operator=(const CallScope&) = delete;

 private:
  PlaceDbService* service_;
};

// One Ingest call (or snapshot transfer) as the watchdog sees it: listed in watches_ from the
// handler's start to its end. The handler thread, the stream's frames (on workers and the
// delivery thread) and the watchdog share it under its own mutex.
struct PlaceDbService::Watch {
  Watch(grpc::ServerContext* context, const char* method)
      : context(context), method(method), peer(Peer(context)), opened(Clock::now()) {}

  void HeaderArrived() {
    MutexLock lock(mutex);
    header = true;
    quiet_since = Clock::now();
  }
  // A frame was read (a Slot made): the stream is busy until it is answered or dropped.
  void FrameRead() {
    MutexLock lock(mutex);
    ++in_flight;
    quiet_since = Clock::now();
  }
  void FrameDone() {
    MutexLock lock(mutex);
    if (--in_flight == 0) quiet_since = Clock::now();  // idle from the last answer on
  }
  // Around AwaitRoom(): while the server holds the stream back (its frames in flight, the
  // memory budget), the silence is the server's doing, not the client's.
  void HeldBack() {
    MutexLock lock(mutex);
    ++in_flight;
  }
  void Released() { FrameDone(); }
  // An upload's chunk arrived.
  void Received() {
    MutexLock lock(mutex);
    quiet_since = Clock::now();
  }
  // Around the delivery thread's Write(), which blocks while the client takes no answers.
  void Writing() {
    MutexLock lock(mutex);
    writing_since = Clock::now();
  }
  void Written() {
    MutexLock lock(mutex);
    writing_since.reset();
    quiet_since = Clock::now();
  }
  // Why the watchdog closed the stream, once it did: CANCELLED, naming the limit.
  std::optional<grpc::Status> Closed() {
    MutexLock lock(mutex);
    if (!closed_reason) return std::nullopt;
    return grpc::Status(grpc::StatusCode::CANCELLED, "closed by the server: " + closed_why);
  }

  grpc::ServerContext* const context;
  const char* const method;  // "Ingest", "DownloadSnapshot", "UploadSnapshot", "WatchLoopClosures"
  const std::string peer;
  const Clock::time_point opened;
  Mutex mutex;
  bool header GUARDED_BY(mutex) = false;
  // Since when nothing happened: opened, or the last message read, answer written, or frame
  // answered.
  Clock::time_point quiet_since GUARDED_BY(mutex) = opened;
  size_t in_flight GUARDED_BY(mutex) = 0;  // frames read, not yet answered or dropped
  std::optional<Clock::time_point> writing_since GUARDED_BY(mutex);  // an answer being written
  const char* closed_reason GUARDED_BY(mutex) = nullptr;             // the metric's label
  std::string closed_why GUARDED_BY(mutex);
};

// Lists a Watch for the scope's life (max_concurrent_streams, the watchdog, the streams gauge);
// not listed, with status() UNAVAILABLE while draining or RESOURCE_EXHAUSTED over the limit.
class PlaceDbService::WatchScope {
 public:
  WatchScope(PlaceDbService* service, Watch* watch) : service_(service), watch_(watch) {
    const size_t limit = service_->config_.limits.max_concurrent_streams;
    {
      MutexLock lock(service_->streams_mutex_);
      if (service_->draining_) {
        status_ = service_->Unavailable();
        return;
      }
      if (service_->watches_.size() >= limit) {
        status_ = grpc::Status(
            grpc::StatusCode::RESOURCE_EXHAUSTED,
            "limits.max_concurrent_streams = " + std::to_string(limit) +
                " streams (Ingest, snapshot downloads and uploads, loop-closure watches) are open; "
                "retry later");
        return;
      }
      service_->watches_.insert(watch_);
    }
    service_->metrics_->StreamOpened();
  }
  // Unlisted before the Watch goes: the watchdog reaches it only through the set.
  ~WatchScope() {
    if (!status_.ok()) return;
    {
      MutexLock lock(service_->streams_mutex_);
      service_->watches_.erase(watch_);
    }
    service_->metrics_->StreamClosed();
  }
  WatchScope(const WatchScope&) = delete;
  WatchScope& operator=(const WatchScope&) = delete;
  const grpc::Status& status() const { return status_; }

 private:
  PlaceDbService* const service_;
  Watch* const watch_;
  grpc::Status status_;
};

}  // namespace placedb::server
