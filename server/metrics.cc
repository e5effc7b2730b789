#include "server/metrics.h"

#include <prometheus/collectable.h>
#include <prometheus/exposer.h>

#include <exception>

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
      places_(
          BuildGauge().Name("placedb_places").Help("Places stored in a map").Register(*registry_)),
      disk_bytes_(BuildGauge()
                      .Name("placedb_map_on_disk_bytes")
                      .Help("Bytes of a map's files on disk")
                      .Register(*registry_)),
      streams_(BuildGauge()
                   .Name("placedb_streams_in_flight")
                   .Help("Open Ingest streams")
                   .Register(*registry_)
                   .Add({})),
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
      detector_seconds_(detector_.Add({}, SecondsBuckets())) {}

Metrics::~Metrics() {
  StopServing();
}

Status Metrics::Serve(const std::string& listen, const std::string& path,
                      std::function<void()> before_scrape) {
  collectable_ = std::make_shared<RefreshingCollectable>(registry_, std::move(before_scrape));
  try {
    exposer_ = std::make_unique<prometheus::Exposer>(listen, /*num_threads=*/1);
  } catch (const std::exception& e) {
    return Status::IoError("metrics endpoint: cannot listen on " + listen + ": " + e.what());
  }
  exposer_->RegisterCollectable(collectable_, path);
  const std::vector<int> ports = exposer_->GetListeningPorts();
  port_ = ports.empty() ? 0 : ports.front();
  return Status::Ok();
}

void Metrics::StopServing() {
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

void Metrics::SetMapGauges(const std::string& map, double places, double bytes_on_disk) {
  places_.Add({{"map", map}}).Set(places);
  disk_bytes_.Add({{"map", map}}).Set(bytes_on_disk);
}

void Metrics::ForgetMap(const std::string& map) {
  // Family::Add returns the existing series for known labels, so this finds them to remove.
  // Only the label sets this class creates are removed (rejection reasons are a closed set).
  places_.Remove(&places_.Add({{"map", map}}));
  disk_bytes_.Remove(&disk_bytes_.Add({{"map", map}}));
  ingested_.Remove(&ingested_.Add({{"map", map}}));
  merged_.Remove(&merged_.Add({{"map", map}}));
  loops_.Remove(&loops_.Add({{"map", map}}));
  loops_rejected_.Remove(&loops_rejected_.Add({{"map", map}}));
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
void Metrics::SetQueueDepth(size_t depth) {
  queue_depth_.Set(double(depth));
}

void Metrics::SetMemoryBudget(uint64_t limit, uint64_t fixed, uint64_t in_use) {
  memory_budget_.Add({{"kind", "limit"}}).Set(double(limit));
  memory_budget_.Add({{"kind", "fixed"}}).Set(double(fixed));
  memory_budget_.Add({{"kind", "in_use"}}).Set(double(in_use));
}

}  // namespace placedb::server
