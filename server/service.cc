#include "server/service.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <future>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "core/base/map_name.h"
#include "core/base/text.h"
#include "core/base/timing.h"
#include "core/storage/snapshots.h"
#include "proto/convert_config.h"
#include "proto/convert_dynamics.h"
#include "proto/convert_frame.h"
#include "proto/convert_result.h"
#include "proto/status.h"
#include "server/frame_memory.h"
#include "server/ingest_pipeline.h"
#include "server/place_reads.h"

namespace placedb::server {

// The wire library (proto/): status codes, configurations, observations in, results out.
using wire::GrpcCodeLabel;
using wire::GrpcCodeName;
using wire::HidePaths;
using wire::ToGrpc;

using wire::DynamicsToProto;
using wire::FeatureTypeToProto;
using wire::MapConfigToProto;
using wire::MapOptionsFromProto;
using wire::MapStatsToProto;
using wire::MapVocabulary;
using wire::QueryOptionsFromProto;
using wire::RankOptionsFromProto;

using wire::CheckFeatureType;
using wire::DecodeObservation;

using wire::BoxesToProto;
using wire::CountsToProto;
using wire::DepthStateToProto;
using wire::LoopClosureToProto;
using wire::MatchesToProto;
using wire::MetadataToProto;
using wire::PlaceFeaturesToProto;
using wire::TimingsToProto;

namespace {

using Clock = std::chrono::steady_clock;

double MsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

// The operator's search settings (config `search`), the same for every caller.
void ApplySearchSettings(const SearchSettings& search, QueryOptions* options) {
  options->search_threads = search.threads;
  options->max_word_share = search.max_word_share;
  options->skip_words_min_places = search.skip_words_min_places;
}

// Whether the call is over: cancelled by the client (or by us), or past its deadline. gRPC's own
// deadline timer fires asynchronously, so the deadline is also checked here directly: work never
// starts a stage after the deadline.
bool Expired(const grpc::ServerContext* context) {
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
grpc::Status Cancelled(const grpc::ServerContext* context, const char* where) {
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
Clock::time_point QueueWaitUntil(const grpc::ServerContext* context, uint32_t wait_ms) {
  auto wait = std::chrono::duration_cast<Clock::duration>(std::chrono::milliseconds(wait_ms));
  const auto deadline = context->deadline();
  const auto now = std::chrono::system_clock::now();
  if (deadline <= now) return Clock::now();
  if (deadline - now < wait) {
    wait = std::chrono::duration_cast<Clock::duration>(deadline - now);
  }
  return Clock::now() + wait;
}

grpc::Status Invalid(const std::string& message) {
  return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, message);
}

// The caller's address as a log line shows it (ForLog, like every client-supplied string).
std::string Peer(const grpc::ServerContext* context) {
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

}  // namespace

// One frame through the pipeline.
struct PlaceDbService::Work {
  // An Ingest frame's: its stream's cached Expired() (null: ask the context, as queries do).
  const StreamExpiry* expiry = nullptr;
  StageTimings timings;
  ProcessedFrame frame;
  PlaceMetadata metadata;
};

PlaceDbService::PlaceDbService(const ServerConfig& config, MapRegistry* maps, WorkerPool* pool,
                               Metrics* metrics, const Detector* detector,
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

Result<std::shared_ptr<const MapEntry>> PlaceDbService::GetMapEntry(
    const std::string& name, const std::string& field) const {
  return cluster_ ? cluster_->Map(name, field) : maps_->Get(name, field);
}

namespace {

// How long one Ingest frame's search and publish may retry (the call's deadline if sooner).
constexpr std::chrono::seconds kClusterPatience{15};

// What a cluster worker does not serve (yet): the maps' storage is the shards'.
grpc::Status NotInCluster(const char* what) {
  return grpc::Status(grpc::StatusCode::UNIMPLEMENTED,
                      std::string(what) +
                          " is not served by a cluster worker (docs/cluster.md, \"What cluster "
                          "mode does not do\")");
}

ClusterBackend::Deadline DeadlineOf(const grpc::ServerContext* context) {
  return context->deadline();
}

// Loop closure's places on a cluster worker, whose local copy of the map holds none: read from
// the map's replicas through the ClusterBackend, for one frame of an Ingest stream
// (`min_sequence`: the stream's last place; `deadline`: the frame's).
class ReplicaPlaces final : public PlaceSource {
 public:
  ReplicaPlaces(ClusterBackend* cluster, std::string map, uint64_t min_sequence,
                ClusterBackend::Deadline deadline)
      : cluster_(cluster), map_(std::move(map)), min_sequence_(min_sequence), deadline_(deadline) {}

  Result<BowVector> GetBow(PlaceId place) override {
    auto fetched = Fetch(place, /*features=*/false);
    if (!fetched.ok()) return fetched.status();
    return std::move(fetched->bow);
  }
  Result<std::shared_ptr<const PlacePayload>> GetPayload(PlaceId place) override {
    auto fetched = Fetch(place, /*features=*/true);
    if (!fetched.ok()) return fetched.status();
    return std::shared_ptr<const PlacePayload>(
        std::make_shared<PlacePayload>(std::move(fetched).value()));
  }
  Result<std::vector<AgentPlace>> AgentPlaces(const std::string& agent_id) override {
    return cluster_->AgentPlaces(map_, agent_id, min_sequence_, deadline_);
  }

 private:
  Result<PlacePayload> Fetch(PlaceId place, bool features) {
    auto fetched = cluster_->FetchPlaces(map_, {place}, features, min_sequence_, deadline_);
    if (!fetched.ok()) return fetched.status();
    if (fetched->empty()) {
      return Status::NotFound("place " + std::to_string(place) + " not found in map '" + map_ +
                              "'");
    }
    return std::move(fetched->front().second);
  }

  ClusterBackend* const cluster_;
  const std::string map_;
  const uint64_t min_sequence_;
  const ClusterBackend::Deadline deadline_;
};

}  // namespace

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
  if (t.store_ms > 0) observe("store", t.store_ms);
  if (t.loop_closure_ms > 0) observe("loop_closure", t.loop_closure_ms);
  observe("total", t.total_ms);
}

// ---- Maps ---------------------------------------------------------------------------------------

namespace {

v1::MapState StateOf(const MapEntry& entry) {
  if (entry.damaged) return v1::MAP_STATE_DAMAGED;
  if (!entry.map) return v1::MAP_STATE_UNAVAILABLE;
  return entry.map->damage_history().empty() ? v1::MAP_STATE_AVAILABLE : v1::MAP_STATE_RECOVERED;
}

void Describe(const MapEntry& entry, v1::MapDescription* out) {
  out->set_name(entry.name);
  out->set_state(StateOf(entry));
  out->set_places_lost(entry.places_lost());
  if (!entry.map) {
    out->set_unavailable_reason(entry.unavailable_reason);
    if (entry.damaged) wire::MapDamageToProto(entry.damage, out->mutable_damage());
    return;
  }
  for (const MapDamage& accepted : entry.map->damage_history()) {
    wire::MapDamageToProto(accepted, out->add_damage_history());
  }
  const MapInfo& info = entry.map->info();
  MapConfigToProto(info.options, entry.settings, entry.vocabulary_name, out->mutable_config());
  MapStatsToProto(entry.map->Stats(), out->mutable_stats());
  out->set_vocabulary_checksum(entry.map->database()->vocabulary().checksum_hex());
  out->set_created_unix_ms(info.created_unix_ms);
  wire::VocabularyRecordToProto(info.vocabulary, entry.map->switching_vocabulary(),
                                out->mutable_vocabulary());
  out->mutable_vocabulary()->set_map(entry.name);
}

}  // namespace

grpc::Status PlaceDbService::CreateMap(grpc::ServerContext* context,
                                       const v1::CreateMapRequest* request,
                                       v1::MapDescription* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("CreateMap", context, Unavailable());
  // The name before anything else: a bad one is the caller's first problem to hear about.
  if (Status valid = ValidateMapName(request->name()); !valid.ok()) {
    return Finish("CreateMap", context, ToGrpc(valid.WithContext("name")));
  }
  // The vocabulary next: its kind is the map's feature type.
  auto vocabulary = maps_->ResolveVocabulary(request->config().vocabulary());
  if (!vocabulary.ok()) return Finish("CreateMap", context, ToGrpc(vocabulary.status()));
  ServiceMapSettings settings;
  auto options = MapOptionsFromProto(
      request->config(), config_.limits.max_descriptors_per_frame,
      MapVocabulary{(*vocabulary)->name, (*vocabulary)->vocabulary.feature_type()}, &settings);
  if (!options.ok()) return Finish("CreateMap", context, ToGrpc(options.status()));
  // Unspecified box source: the server's detector when it has one, else the agent's boxes. The
  // choice is stored with the map, so it does not change if the server's detector does.
  if (request->config().detection().box_source() == v1::BOX_SOURCE_UNSPECIFIED && detector_ &&
      settings.detection_enabled) {
    settings.box_source = BoxSource::kServer;
  }
  if (settings.detection_enabled && settings.box_source != BoxSource::kAgent && !detector_) {
    return Finish("CreateMap", context,
                  grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                               "config.detection.box_source: " +
                                   std::string(BoxSourceName(settings.box_source)) +
                                   " needs server-side detection, which is off on this server "
                                   "(configure detector.model)"));
  }
  if (cluster_) {
    if (settings.adapt_after_descriptors != 0 || settings.regrow_factor != 0) {
      // Refused rather than stored and ignored: no worker runs the policy (docs/cluster.md).
      return Finish("CreateMap", context,
                    grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                                 "config.vocabulary_policy: not run in cluster mode; call "
                                 "AdaptVocabulary (placedb maps adapt-vocabulary) instead"));
    }
    // The effective configuration (every field filled in) is what the cluster stores: workers
    // and shards build the same map options from it.
    v1::MapConfig effective;
    MapConfigToProto(*options, settings, (*vocabulary)->name, &effective);
    const grpc::Status created =
        cluster_->CreateMap(request->name(), effective, DeadlineOf(context), response);
    if (created.ok()) {
      spdlog::info("cluster map '{}' created: vocabulary '{}', box source {}, peer={}",
                   ForLog(request->name()), (*vocabulary)->name, BoxSourceName(settings.box_source),
                   Peer(context));
    }
    return Finish("CreateMap", context, created);
  }
  auto entry = maps_->Create(request->name(), *options, request->config().vocabulary(), settings);
  if (!entry.ok()) return Finish("CreateMap", context, ToGrpc(entry.status()));
  Describe(**entry, response);
  spdlog::info("map '{}' created: vocabulary '{}', features {}, box source {}, peer={}",
               ForLog(request->name()), (*entry)->vocabulary_name,
               FeatureTypeName(options->database.feature_type), BoxSourceName(settings.box_source),
               Peer(context));
  return Finish("CreateMap", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::GetMap(grpc::ServerContext* context, const v1::GetMapRequest* request,
                                    v1::MapDescription* response) {
  CallScope scope(this);
  if (cluster_) {
    // The agents below: those this worker served.
    const grpc::Status described = cluster_->GetMap(request->name(), DeadlineOf(context), response);
    if (!described.ok()) return Finish("GetMap", context, described);
  } else {
    // Damaged and unavailable maps are described too: their state is what an operator looks for.
    auto entry = maps_->Find(request->name(), "name");
    if (!entry.ok()) return Finish("GetMap", context, ToGrpc(entry.status()));
    Describe(**entry, response);
  }
  for (const AgentActivitySnapshot& agent : activity_.Of(request->name(), Clock::now())) {
    v1::AgentActivity* out = response->add_agents();
    out->set_agent_id(agent.agent_id);
    out->set_frames(agent.frames);
    out->set_places(agent.places);
    out->set_frames_per_second(agent.frames_per_second);
    out->set_last_place_id(agent.last_place_id);
    out->set_last_frame_unix_ms(agent.last_frame_unix_ms);
  }
  return Finish("GetMap", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::ListMaps(grpc::ServerContext* context, const v1::ListMapsRequest*,
                                      v1::ListMapsResponse* response) {
  CallScope scope(this);
  if (cluster_) {
    return Finish("ListMaps", context, cluster_->ListMaps(DeadlineOf(context), response));
  }
  for (const auto& entry : maps_->List()) {
    v1::MapSummary* summary = response->add_maps();
    summary->set_name(entry->name);
    summary->set_available(entry->map != nullptr);
    summary->set_unavailable_reason(HidePaths(entry->unavailable_reason, config_.data_dir));
    summary->set_vocabulary(entry->vocabulary_name);
    summary->set_state(StateOf(*entry));
    summary->set_places_lost(entry->places_lost());
    if (entry->map) {
      summary->set_places(entry->map->database()->Stats().places);
      summary->set_feature_type(FeatureTypeToProto(entry->map->database()->config().feature_type));
    }
  }
  return Finish("ListMaps", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::DeleteMap(grpc::ServerContext* context,
                                       const v1::DeleteMapRequest* request,
                                       v1::DeleteMapResponse*) {
  CallScope scope(this);
  if (draining_flag_) return Finish("DeleteMap", context, Unavailable());
  if (cluster_) {
    const grpc::Status deleted = cluster_->DeleteMap(request->name(), DeadlineOf(context));
    if (deleted.ok()) {
      activity_.Forget(request->name());
      spdlog::info("cluster map '{}' deleted, peer={}", ForLog(request->name()), Peer(context));
    }
    return Finish("DeleteMap", context, deleted);
  }
  if (Status deleted = maps_->Delete(request->name()); !deleted.ok()) {
    return Finish("DeleteMap", context, ToGrpc(deleted));
  }
  metrics_->ForgetMap(request->name());
  activity_.Forget(request->name());
  spdlog::info("map '{}' deleted, peer={}", ForLog(request->name()), Peer(context));
  return Finish("DeleteMap", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::RecoverMap(grpc::ServerContext* context,
                                        const v1::RecoverMapRequest* request,
                                        v1::RecoverMapResponse* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("RecoverMap", context, Unavailable());
  if (cluster_) return Finish("RecoverMap", context, NotInCluster("RecoverMap"));
  MapDamage accepted;
  auto entry = maps_->Recover(request->name(), request->accept_data_loss(), &accepted);
  if (!entry.ok()) return Finish("RecoverMap", context, ToGrpc(entry.status()));
  Describe(**entry, response->mutable_map());
  wire::MapDamageToProto(accepted, response->mutable_accepted());
  // Error level when anything was lost: an operator's log search for damage must find it.
  spdlog::log(accepted.writes_lost > 0 ? spdlog::level::err : spdlog::level::warn,
              "map '{}' recovered with data loss accepted: {} acknowledged places lost ({} "
              "writes); {}; peer={}",
              ForLog(request->name()), accepted.places_lost, accepted.writes_lost,
              accepted.reason.empty() ? std::string("it was not damaged") : accepted.reason,
              Peer(context));
  return Finish("RecoverMap", context, grpc::Status::OK);
}

namespace {

std::string SourceText(const VocabularySource& source) {
  std::string text = source.origin + " vocabulary " + Hex64(source.checksum) +
                     " (k=" + std::to_string(source.branching) +
                     " L=" + std::to_string(source.depth) + ", " + std::to_string(source.words) +
                     " words";
  if (source.origin == "learned") {
    text += ", from " + std::to_string(source.descriptors_sampled) + " descriptors of " +
            std::to_string(source.places_sampled) + " places";
  }
  return text + ")";
}

}  // namespace

grpc::Status PlaceDbService::AdaptVocabulary(grpc::ServerContext* context,
                                             const v1::AdaptVocabularyRequest* request,
                                             v1::MapVocabulary* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("AdaptVocabulary", context, Unavailable());
  if (cluster_) {
    spdlog::info("cluster map '{}': learning a vocabulary on a replica, peer={}",
                 ForLog(request->name()), Peer(context));
    const grpc::Status switched =
        cluster_->AdaptVocabulary(*request, DeadlineOf(context), response);
    return Finish("AdaptVocabulary", context, switched);
  }
  auto entry = maps_->Get(request->name(), "name");
  if (!entry.ok()) return Finish("AdaptVocabulary", context, ToGrpc(entry.status()));
  AdaptOptions options;
  if (request->seed() != 0) options.learning.seed = request->seed();
  options.learning.max_sample_descriptors = request->max_sample_descriptors();
  options.learning.branching = int(std::min<uint32_t>(request->branching(), 1u << 16));
  options.learning.depth = int(std::min<uint32_t>(request->depth(), 1u << 16));
  options.cancel = &draining_flag_;  // a shutdown cancels it: the map keeps its vocabulary
  spdlog::info("map '{}': learning a vocabulary from its stored places, peer={}",
               ForLog(request->name()), Peer(context));
  auto record = (*entry)->map->AdaptVocabulary(options);
  if (!record.ok()) {
    spdlog::warn("map '{}': vocabulary not adapted: {}", ForLog(request->name()),
                 record.status().ToString());
    return Finish("AdaptVocabulary", context, ToGrpc(record.status()));
  }
  maps_->VocabularySwitched(request->name());
  wire::VocabularyRecordToProto(*record, false, response);
  response->set_map(request->name());
  spdlog::info(
      "map '{}' switched to {}: learned in {:.1f} s, {} places re-indexed in {:.1f} s "
      "(generation {}), peer={}",
      ForLog(request->name()), SourceText(record->current), record->current.learn_ms / 1000,
      record->places_reindexed, record->reindex_ms / 1000, record->generation, Peer(context));
  return Finish("AdaptVocabulary", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::RevertVocabulary(grpc::ServerContext* context,
                                              const v1::RevertVocabularyRequest* request,
                                              v1::MapVocabulary* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("RevertVocabulary", context, Unavailable());
  if (cluster_) {
    const grpc::Status switched =
        cluster_->RevertVocabulary(request->name(), DeadlineOf(context), response);
    return Finish("RevertVocabulary", context, switched);
  }
  auto entry = maps_->Get(request->name(), "name");
  if (!entry.ok()) return Finish("RevertVocabulary", context, ToGrpc(entry.status()));
  AdaptOptions options;
  options.cancel = &draining_flag_;  // as for AdaptVocabulary
  auto record = (*entry)->map->RevertVocabulary(options);
  if (!record.ok()) {
    spdlog::warn("map '{}': vocabulary not reverted: {}", ForLog(request->name()),
                 record.status().ToString());
    return Finish("RevertVocabulary", context, ToGrpc(record.status()));
  }
  maps_->VocabularySwitched(request->name());
  wire::VocabularyRecordToProto(*record, false, response);
  response->set_map(request->name());
  spdlog::info("map '{}' reverted to {}: {} places re-indexed in {:.1f} s (generation {}), peer={}",
               ForLog(request->name()), SourceText(record->current), record->places_reindexed,
               record->reindex_ms / 1000, record->generation, Peer(context));
  return Finish("RevertVocabulary", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::ScrubMap(grpc::ServerContext* context,
                                      const v1::ScrubMapRequest* request,
                                      v1::ScrubReport* response) {
  CallScope scope(this);
  if (cluster_) return Finish("ScrubMap", context, NotInCluster("ScrubMap"));
  auto entry = maps_->Get(request->name(), "name");
  if (!entry.ok()) return Finish("ScrubMap", context, ToGrpc(entry.status()));
  auto report = (*entry)->map->Scrub();
  if (!report.ok()) return Finish("ScrubMap", context, ToGrpc(report.status()));
  wire::ScrubReportToProto(*report, response);
  if (report->clean()) {
    spdlog::info("map '{}' scrubbed: {} places, {} files, no damage", ForLog(request->name()),
                 report->places_checked, report->files_checked);
  } else {
    spdlog::error("map '{}' scrubbed: {} of {} places and {} of {} files damaged{}{}",
                  ForLog(request->name()), report->damaged_places.size(), report->places_checked,
                  report->damaged_files.size(), report->files_checked,
                  report->damaged_files.empty() ? "" : "; first: ",
                  report->damaged_files.empty()
                      ? ""
                      : report->damaged_files[0].file + ": " + report->damaged_files[0].reason);
  }
  return Finish("ScrubMap", context, grpc::Status::OK);
}

// ---- Places -------------------------------------------------------------------------------------

grpc::Status PlaceDbService::GetPlace(grpc::ServerContext* context,
                                      const v1::GetPlaceRequest* request, v1::Place* response) {
  CallScope scope(this);
  if (cluster_) {
    return Finish("GetPlace", context, cluster_->GetPlace(*request, DeadlineOf(context), response));
  }
  auto entry = maps_->Get(request->map(), "map");
  if (!entry.ok()) return Finish("GetPlace", context, ToGrpc(entry.status()));
  return Finish("GetPlace", context, ToGrpc(ReadPlace(*(*entry)->map, *request, response)));
}

grpc::Status PlaceDbService::ListPlaces(grpc::ServerContext* context,
                                        const v1::ListPlacesRequest* request,
                                        v1::ListPlacesResponse* response) {
  CallScope scope(this);
  if (cluster_) {
    return Finish("ListPlaces", context,
                  cluster_->ListPlaces(*request, DeadlineOf(context), response));
  }
  auto entry = maps_->Get(request->map(), "map");
  if (!entry.ok()) return Finish("ListPlaces", context, ToGrpc(entry.status()));
  return Finish("ListPlaces", context, ToGrpc(ListPlacesOf(*(*entry)->map, *request, response)));
}

grpc::Status PlaceDbService::DeletePlace(grpc::ServerContext* context,
                                         const v1::DeletePlaceRequest* request,
                                         v1::DeletePlaceResponse*) {
  CallScope scope(this);
  if (draining_flag_) return Finish("DeletePlace", context, Unavailable());
  if (cluster_) {
    if (request->place_id() == 0) {
      return Finish("DeletePlace", context, Invalid("place_id: is required (ids start at 1)"));
    }
    return Finish("DeletePlace", context,
                  cluster_->DeletePlace(
                      *request, std::min(DeadlineOf(context),
                                         std::chrono::system_clock::now() + kClusterPatience)));
  }
  auto entry = maps_->Get(request->map(), "map");
  if (!entry.ok()) return Finish("DeletePlace", context, ToGrpc(entry.status()));
  if (request->place_id() == 0) {
    return Finish("DeletePlace", context, Invalid("place_id: is required (ids start at 1)"));
  }
  const Status removed = (*entry)->map->RemovePlace(request->place_id());
  metrics_->StorageError((*entry)->name, removed);
  return Finish("DeletePlace", context, ToGrpc(removed));
}

// ---- Dynamic-object statistics
// -------------------------------------------------------------------

grpc::Status PlaceDbService::GetDynamics(grpc::ServerContext* context,
                                         const v1::GetDynamicsRequest* request,
                                         v1::GetDynamicsResponse* response) {
  CallScope scope(this);
  if (cluster_) {
    return Finish("GetDynamics", context,
                  cluster_->GetDynamics(*request, DeadlineOf(context), response));
  }
  auto entry = maps_->Get(request->map(), "map");
  if (!entry.ok()) return Finish("GetDynamics", context, ToGrpc(entry.status()));
  return Finish("GetDynamics", context, ToGrpc(ReadDynamics(*(*entry)->map, *request, response)));
}

// ---- Server info --------------------------------------------------------------------------------

grpc::Status PlaceDbService::GetServerInfo(grpc::ServerContext* context,
                                           const v1::GetServerInfoRequest*,
                                           v1::ServerInfo* response) {
  CallScope scope(this);
  response->set_version(PLACEDB_VERSION);
  for (const VocabularyEntry& entry : maps_->vocabularies()) {
    v1::VocabularyInfo* info = response->add_vocabularies();
    info->set_name(entry.name);
    info->set_path(HidePaths(entry.path, config_.data_dir));  // the file name: no server paths
    info->set_checksum(entry.vocabulary.checksum_hex());
    info->set_words(entry.vocabulary.word_count());
    info->set_nodes(entry.vocabulary.node_count());
    info->set_branching(entry.vocabulary.branching());
    info->set_depth(entry.vocabulary.depth());
    info->set_memory_bytes(entry.vocabulary.memory_bytes());
    info->set_feature_type(FeatureTypeToProto(entry.vocabulary.feature_type()));
  }
  response->set_detector(
      HidePaths(detector_ ? detector_->Describe() : detector_status_, config_.data_dir));
  response->set_console_url(console_url_);
  response->set_role(cluster_ ? cluster_->role() : "single");
  const Limits& l = config_.limits;
  v1::Limits* limits = response->mutable_limits();
  limits->set_max_message_bytes(l.max_message_bytes);
  limits->set_max_image_pixels(l.max_image_pixels);
  limits->set_max_descriptors_per_frame(l.max_descriptors_per_frame);
  limits->set_max_boxes_per_frame(l.max_boxes_per_frame);
  limits->set_max_concurrent_streams(l.max_concurrent_streams);
  limits->set_max_queued_frames(l.max_queued_frames);
  limits->set_max_inflight_per_stream(l.max_inflight_per_stream);
  limits->set_worker_threads(uint32_t(pool_->threads()));
  return Finish("GetServerInfo", context, grpc::Status::OK);
}

// ---- The frame pipeline -------------------------------------------------------------------------

namespace {

// Colour for the detector, and for GrabCut when the map refines the agent's boxes with it.
bool DecodesInColor(const MapEntry& map, const v1::Observation& observation) {
  const ServiceMapSettings& settings = map.settings;
  const bool server_boxes = settings.detection_enabled && settings.box_source != BoxSource::kAgent;
  // A map that keeps thumbnails keeps them in colour.
  return server_boxes || map.map->options().thumbnails.enabled ||
         (settings.detection_enabled && observation.boxes_size() > 0 &&
          map.map->database()->config().box_refinement.method == BoxRefinement::kGrabCut);
}

}  // namespace

grpc::Status PlaceDbService::ChargeFrame(grpc::ServerContext* context, const MapEntry& map,
                                         const v1::Observation& observation, const char* what,
                                         MemoryBudget::Reservation* reservation) {
  const uint64_t bytes = EstimateFrameBytes(observation, map.map->database()->config().feature_type,
                                            DecodesInColor(map, observation));
  const auto until = QueueWaitUntil(context, config_.limits.memory_wait_ms);
  const auto expired = [context] { return Expired(context); };
  if (*reservation) {
    if (reservation->Resize(bytes, until, expired)) return grpc::Status::OK;
  } else if (auto reserved = budget_->Reserve(bytes, what, until, expired); reserved.ok()) {
    *reservation = std::move(reserved).value();
    return grpc::Status::OK;
  }
  if (Expired(context)) return Cancelled(context, "while waiting for memory");
  return ToGrpc(budget_->Exhausted(bytes, what));
}

grpc::Status PlaceDbService::Prepare(grpc::ServerContext* context, const MapEntry& map,
                                     const v1::Observation& observation, const std::string& field,
                                     FrameRole role, Work* work, bool keep_dropped_keypoints) {
  const auto expired = [&] { return work->expiry ? (*work->expiry)() : Expired(context); };
  if (expired()) return Cancelled(context, "before decoding");
  const ServiceMapSettings& settings = map.settings;
  if (Status typed = CheckFeatureType(observation, map.map->database()->config().feature_type,
                                      map.name, field);
      !typed.ok()) {
    return ToGrpc(typed);
  }
  const bool server_boxes = settings.detection_enabled && settings.box_source != BoxSource::kAgent;
  if (server_boxes && !detector_) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "map '" + map.name + "' takes boxes from the server's detector (" +
                            BoxSourceName(settings.box_source) +
                            "), which is off on this server (configure detector.model)");
  }
  Stopwatch stage;
  const bool color = DecodesInColor(map, observation);
  auto decoded = DecodeObservation(observation, config_.limits.frame(), color, field);
  if (!decoded.ok()) return ToGrpc(decoded.status());
  work->timings.decode_ms = stage.Lap();
  Observation& frame = decoded->observation;

  if (server_boxes) {
    if (!decoded->has_pixels) {
      // A query with features uses the observation's boxes, as kBoth does: a stored place's
      // features (GetPlace include_features, the console's "stored place") are static already.
      // Storing features the detector never saw is refused.
      if (settings.box_source == BoxSource::kServer && role != FrameRole::kQuery) {
        return Invalid(field +
                       (observation.frame_case() == v1::Observation::kSiftFeatures
                            ? ".sift_features"
                            : ".features") +
                       ": map '" + map.name +
                       "' detects dynamic objects on the server (box_source server), which needs "
                       "pixels: send encoded_image or raw_image");
      }
      // kBoth (or a query) without pixels: the agent's boxes alone.
    } else {
      if (expired()) return Cancelled(context, "before detection");
      auto boxes = detector_->Detect(frame.image);
      if (!boxes.ok()) return ToGrpc(boxes.status(), "server-side detection");
      work->timings.detect_ms = stage.Lap();
      metrics_->ObserveDetector(work->timings.detect_ms / 1000.0);
      frame.dynamic.boxes =
          settings.box_source == BoxSource::kServer
              ? std::move(boxes).value()
              : MergeBoxes(decoded->agent_boxes, *boxes, config_.detector.merge_iou);
    }
  }

  if (expired()) return Cancelled(context, "before feature extraction");
  auto processed = map.map->Process(frame, role, keep_dropped_keypoints);
  if (!processed.ok()) return ToGrpc(processed.status(), field);
  work->frame = std::move(processed).value();
  work->timings.extract_ms = work->frame.timings.extract_ms;
  work->timings.depth_ms = work->frame.timings.depth_ms;
  work->timings.refine_ms = work->frame.timings.refine_ms;
  work->timings.filter_ms = work->frame.timings.filter_ms;
  work->timings.transform_ms = work->frame.timings.transform_ms;
  work->metadata = std::move(frame.metadata);
  return grpc::Status::OK;
}

// ---- Query --------------------------------------------------------------------------------------

grpc::Status PlaceDbService::Query(grpc::ServerContext* context, const v1::QueryRequest* request,
                                   v1::QueryResponse* response) {
  CallScope scope(this);
  const Clock::time_point arrived = Clock::now();
  if (draining_flag_) return Finish("Query", context, Unavailable());
  auto entry = GetMapEntry(request->map(), "map");
  if (!entry.ok()) return Finish("Query", context, ToGrpc(entry.status()));
  if (!request->has_observation()) {
    return Finish("Query", context, Invalid("observation: is required"));
  }
  const MapEntry& map = **entry;
  // The request is in memory already (gRPC read it before calling us): charged from here on.
  MemoryBudget::Reservation memory;
  if (grpc::Status charged =
          ChargeFrame(context, map, request->observation(), "this query", &memory);
      !charged.ok()) {
    return Finish("Query", context, charged);
  }
  std::promise<grpc::Status> promise;
  std::future<grpc::Status> done = promise.get_future();
  double queue_ms = 0;
  auto task = [&] {
    queue_ms = MsSince(arrived);
    Work work;
    grpc::Status status = Guarded("processing the observation", [&] {
      return Prepare(context, map, request->observation(), "observation", FrameRole::kQuery, &work,
                     request->options().include_correspondences());
    });
    if (status.ok() && Expired(context)) status = Cancelled(context, "before searching");
    if (status.ok() && cluster_) {
      status = Guarded("searching the cluster", [&] {
        if (work.frame.valid) {  // an invalid frame has nothing to search with
          const grpc::Status searched =
              cluster_->Search(map.name, work.frame, work.metadata, request->options(),
                               request->min_sequence(), DeadlineOf(context), response);
          if (!searched.ok()) return searched;
          // A map that counts query hits (PlaceMap::CountQueryHit's rule): durable before the
          // answer, as on a single server.
          const double above = map.map->options().count_query_hits_above;
          if (above > 0 && response->matches_size() > 0 && response->matches(0).score() > above) {
            if (Status counted = cluster_->CountObservation(
                    map.name, response->matches(0).place_id(), work.frame, work.metadata,
                    /*message_id=*/"",
                    std::min(DeadlineOf(context),
                             std::chrono::system_clock::now() + kClusterPatience));
                !counted.ok()) {
              return ToGrpc(counted, "counting the query hit");
            }
          }
        }
        response->set_valid(work.frame.valid);
        response->set_rejection(work.frame.rejection);
        CountsToProto(work.frame.counts, response->mutable_counts());
        BoxesToProto(work.frame.boxes_used, response->mutable_boxes_used());
        if (work.frame.depth_state) {
          DepthStateToProto(*work.frame.depth_state, response->mutable_depth());
        }
        work.timings.total_ms = MsSince(arrived);
        TimingsToProto(work.timings, queue_ms, response->mutable_timings());
        ObserveStages(work.timings);
        return grpc::Status::OK;
      });
    } else if (status.ok())
      status = Guarded("searching", [&] {
        QueryOptions options =
            QueryOptionsFromProto(request->options(), request->observation().agent_id());
        ApplySearchSettings(config_.search, &options);
        options.timestamp_ns = request->observation().timestamp_ns();
        QueryResult result = map.map->Search(work.frame, options);
        // A map that counts query hits (MapConfig.dynamics): durable before the answer.
        if (auto counted = map.map->CountQueryHit(work.frame, work.metadata, result);
            !counted.ok()) {
          metrics_->StorageError(map.name, counted.status());
          return ToGrpc(counted.status());
        }
        work.timings.search_ms = result.timings.search_ms;
        work.timings.verify_ms = result.timings.verify_ms;
        response->set_valid(result.valid);
        response->set_rejection(result.rejection);
        CountsToProto(result.counts, response->mutable_counts());
        BoxesToProto(result.boxes_used, response->mutable_boxes_used());
        MatchesToProto(result.matches, response->mutable_matches());
        if (options.include_correspondences) {
          // What the correspondences index, and what to draw them on.
          wire::KeypointListToProto(work.frame.static_features.keypoints(),
                                    response->mutable_query_keypoints());
          wire::KeypointListToProto(work.frame.dropped_keypoints,
                                    response->mutable_query_dropped_keypoints());
          response->set_image_width(uint32_t(work.frame.static_features.image_width()));
          response->set_image_height(uint32_t(work.frame.static_features.image_height()));
        }
        // The agent's current Algorithm 1 decision, when it applied to this frame.
        if (work.frame.depth_state) {
          DepthStateToProto(*work.frame.depth_state, response->mutable_depth());
        }
        work.timings.total_ms = MsSince(arrived);
        TimingsToProto(work.timings, queue_ms, response->mutable_timings());
        ObserveStages(work.timings);
        return grpc::Status::OK;
      });
    promise.set_value(status);
  };
  switch (query_pool_->Submit(task, QueueWaitUntil(context, config_.limits.unary_queue_wait_ms),
                              [context] { return Expired(context); })) {
    case WorkerPool::SubmitResult::kQueued:
      break;
    case WorkerPool::SubmitResult::kFull:
      if (context->deadline() <= std::chrono::system_clock::now()) {
        return Finish("Query", context, Cancelled(context, "while waiting for a worker"));
      }
      return Finish(
          "Query", context,
          grpc::Status(
              grpc::StatusCode::RESOURCE_EXHAUSTED,
              "limits.max_queued_frames = " + std::to_string(config_.limits.max_queued_frames) +
                  ": every worker is busy and the queue stayed full for " +
                  std::to_string(config_.limits.unary_queue_wait_ms) + " ms; retry with backoff"));
    case WorkerPool::SubmitResult::kGaveUp:
      return Finish("Query", context, Cancelled(context, "while waiting for a worker"));
    case WorkerPool::SubmitResult::kStopped:
      return Finish("Query", context, Unavailable());
  }
  return Finish("Query", context, done.get());
}

// ---- Ingest -------------------------------------------------------------------------------------

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
  const char* const method;  // "Ingest", "DownloadSnapshot", "UploadSnapshot"
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
        status_ = grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                               "limits.max_concurrent_streams = " + std::to_string(limit) +
                                   " streams (Ingest, snapshot downloads and uploads) are open; "
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

// One open Ingest call: the handler thread reads, the pipeline does the rest.
struct PlaceDbService::Stream {
  grpc::ServerContext* context = nullptr;
  Watch* watch = nullptr;
  std::shared_ptr<const MapEntry> map;
  std::optional<v1::MatchOptions> header_matches;
  bool loop_closure = false;           // IngestHeader.loop_closure
  IngestPipeline* pipeline = nullptr;  // set before the stream is listed in streams_
  grpc::Status refusal;                // why the pool refused the last frame (handler thread)
  // The stream's last place handed to the map's commit queue (Complete() only): a frame that
  // searches waits for it first, so it sees every earlier place of its stream.
  std::shared_ptr<PendingCommit> last_commit;
  // Cluster mode: the stream's last place id (stream sequence), the min_sequence of its searches.
  uint64_t last_sequence = 0;
  // Cluster mode, loop closure: the agents whose detector this stream has (re)started. Complete()
  // only (stream order, one frame at a time).
  std::set<std::string> loop_agents;
  std::optional<StreamExpiry> expiry_check;  // set with `context`
  bool expiry() const { return (*expiry_check)(); }

  // For the close log line, read after the pipeline is closed. `frames` and `agents`: the handler
  // thread; the outcomes: Settle(), on the pipeline's delivery thread, one frame at a time.
  uint64_t frames = 0, stored = 0, merged = 0, rejected = 0, errors = 0;
  std::vector<std::string> agents;  // first few distinct agent ids
};

// One observation of a stream, from its arrival to its response.
struct PlaceDbService::Slot final : IngestPipeline::Frame {
  // Made when the observation has been read; destroyed once answered (or dropped): while it
  // exists, its stream is never idle.
  Slot(PlaceDbService* service, Stream* stream) : service(service), stream(stream) {
    stream->watch->FrameRead();
  }
  ~Slot() override {
    service->Settle(stream, this);  // a skipped frame's place is still waited for and counted
    stream->watch->FrameDone();
  }
  Slot(const Slot&) = delete;
  Slot& operator=(const Slot&) = delete;

  void Prepare() override {
    queue_ms = MsSince(arrived);
    work.expiry = &*stream->expiry_check;
    status = Guarded("processing the observation", [&] {
      return service->Prepare(stream->context, *stream->map, request->observation(), "observation",
                              FrameRole::kStream, &work);
    });
    request.reset();  // the decoded frame is all that is needed now
    memory.TryResize(std::min(memory.bytes(), kPreparedFrameBytes));  // shrinking never fails
  }
  void Refused(IngestPipeline::Admission why) override {
    status = why == IngestPipeline::Admission::kPoolStopped
                 ? service->Unavailable()
                 : Cancelled(stream->context, "while waiting for a worker");
    request.reset();
    stream->refusal = status;
  }
  void Complete() override { service->Complete(stream, this); }

  PlaceDbService* const service;
  Stream* const stream;
  uint64_t index = 0;
  uint64_t sequence = 0;
  std::string agent_id;  // the observation's, for the agent's activity
  Clock::time_point arrived;
  double queue_ms = 0;
  std::unique_ptr<v1::IngestRequest> request;  // freed once decoded
  grpc::Status status;                         // the outcome so far
  std::optional<v1::MatchOptions> matches;
  Work work;                    // freed once settled
  v1::IngestResponse response;  // Complete()'s and Settle()'s, for the writer
  // Set by Complete() when the place went to the map's commit queue; Settle() waits for it.
  std::shared_ptr<PendingCommit> commit;
  bool completed = false;  // Complete() ran (a dropped frame never completes)
  bool settled = false;    // Settle() ran (delivery thread)
  // The frame's share of the memory budget, from its read until its answer is written (the
  // pipeline destroys the slot after delivering it).
  MemoryBudget::Reservation memory;
};

void PlaceDbService::Complete(Stream* stream, Slot* slot) {
  v1::IngestResponse& response = slot->response;
  response.set_sequence(slot->sequence);
  response.set_index(slot->index);
  if (slot->status.ok() && stream->expiry()) {
    slot->status = Cancelled(stream->context, "before storing");
  }
  if (!slot->status.ok()) {
    response.mutable_error()->set_code(int(slot->status.error_code()));
    response.mutable_error()->set_message(
        HidePaths(slot->status.error_message(), config_.data_dir));
    metrics_->FrameRejected(stream->map->name, GrpcCodeLabel(slot->status.error_code()));
    if (slot->status.error_code() != grpc::StatusCode::CANCELLED &&
        slot->status.error_code() != grpc::StatusCode::DEADLINE_EXCEEDED) {
      spdlog::warn("ingest frame error map={} index={} sequence={} code={} message=\"{}\"",
                   ForLog(stream->map->name), slot->index, slot->sequence,
                   GrpcCodeName(slot->status.error_code()), ForLog(slot->status.error_message()));
    }
  } else {
    Work& work = slot->work;
    const MapEntry& map = *stream->map;
    ProcessedFrame& frame = work.frame;
    Result<AddResult> added = Status::Internal("not stored");
    std::optional<LoopClosureOutcome> loop;
    bool clustered = false;  // cluster mode: CompleteInCluster() answered
    const grpc::Status second_half = Guarded("searching and storing", [&] {
      // The agent's stream state, in its order: Algorithm 1 on depth, then validity and the
      // BoW vector (a no-op for frames without depth).
      if (Status advanced = map.map->AdvanceStream(&frame, work.metadata.agent_id);
          !advanced.ok()) {
        return ToGrpc(advanced, "observation");
      }
      work.timings.depth_ms = frame.timings.depth_ms;
      work.timings.transform_ms = frame.timings.transform_ms;
      if (cluster_) {
        clustered = true;
        return CompleteInCluster(stream, slot);
      }
      const bool searches = frame.valid && (slot->matches || stream->loop_closure);
      if (searches && stream->last_commit) {
        // A place is stored and searchable before the next frame of its stream searches.
        (void)stream->last_commit->Wait();  // a failure is its own frame's answer
        stream->last_commit.reset();
      }
      if (slot->matches && frame.valid) {
        QueryOptions options = QueryOptionsFromProto(*slot->matches, work.metadata.agent_id);
        ApplySearchSettings(config_.search, &options);
        options.timestamp_ns = work.metadata.timestamp_ns;
        QueryResult result = map.map->Search(frame, options);
        work.timings.search_ms = result.timings.search_ms;
        work.timings.verify_ms = result.timings.verify_ms;
        MatchesToProto(result.matches, response.mutable_matches());
      }
      if (stream->loop_closure && frame.valid) {
        // The agent's loop-closure detector, then (unless rehearsal merges the frame into the
        // previous place) the durable write.
        AddResult committed;  // the commit's result and its store_ms (none when merged)
        auto outcome = map.map->CloseLoop(frame, work.metadata, &committed);
        if (!outcome.ok()) {
          metrics_->StorageError(map.name, outcome.status());
          return ToGrpc(outcome.status(), "loop closure");
        }
        work.timings.loop_closure_ms = outcome->update_ms;
        loop = std::move(outcome).value();
        added = std::move(committed);
        return grpc::Status::OK;
      }
      if (frame.valid) {
        // Group commit: the worker goes on; the answer waits for durability (Settle()).
        CountsToProto(frame.counts, response.mutable_counts());
        BoxesToProto(frame.boxes_used, response.mutable_boxes_used());
        if (frame.depth_state) DepthStateToProto(*frame.depth_state, response.mutable_depth());
        metrics_->CountDescriptors(map.name, frame.counts.dynamic, frame.counts.depth_removed,
                                   frame.counts.static_);
        slot->commit = map.map->Enqueue(std::move(frame), work.metadata);
        stream->last_commit = slot->commit;
        return grpc::Status::OK;
      }
      added = map.map->Commit(frame, work.metadata);
      if (added.ok()) return grpc::Status::OK;
      metrics_->StorageError(map.name, added.status());
      return ToGrpc(added.status(), "storing");
    });
    if (!second_half.ok()) {
      slot->status = second_half;
      response.clear_matches();
      response.mutable_error()->set_code(int(slot->status.error_code()));
      response.mutable_error()->set_message(
          HidePaths(slot->status.error_message(), config_.data_dir));
      metrics_->FrameRejected(map.name, GrpcCodeLabel(slot->status.error_code()));
      spdlog::warn("ingest frame error map={} index={} code={} message=\"{}\"", ForLog(map.name),
                   slot->index, GrpcCodeName(slot->status.error_code()),
                   ForLog(slot->status.error_message()));
    } else if (slot->commit) {
      // Answered by Settle(), once durable.
    } else if (clustered) {
      work.timings.total_ms = MsSince(slot->arrived);
      TimingsToProto(work.timings, slot->queue_ms, response.mutable_timings());
      ObserveStages(work.timings);
    } else {
      CountsToProto(frame.counts, response.mutable_counts());
      BoxesToProto(frame.boxes_used, response.mutable_boxes_used());
      if (frame.depth_state) DepthStateToProto(*frame.depth_state, response.mutable_depth());
      work.timings.store_ms = added->timings.store_ms;
      metrics_->CountDescriptors(map.name, frame.counts.dynamic, frame.counts.depth_removed,
                                 frame.counts.static_);
      if (loop) {
        LoopClosureToProto(*loop, response.mutable_loop_closure());
        if (loop->loop) metrics_->LoopClosed(map.name);
        if (loop->loop_rejected) metrics_->LoopRejected(map.name);
      }
      if (loop && loop->merged) {
        // Rehearsal: the frame is the place it was merged into; nothing new is stored.
        response.set_stored(false);
        response.set_place_id(loop->place);
        metrics_->FrameMerged(map.name);
      } else {
        response.set_stored(added->stored);
        if (added->stored) {
          response.set_place_id(added->id);
          metrics_->FrameIngested(map.name);
        } else {
          response.set_rejection(added->rejection);
          metrics_->FrameRejected(map.name, "invalid_place");
        }
      }
      work.timings.total_ms = MsSince(slot->arrived);
      TimingsToProto(work.timings, slot->queue_ms, response.mutable_timings());
      ObserveStages(work.timings);
    }
  }
  slot->completed = true;
  if (!slot->commit) slot->work = Work();  // the frame's data need not wait for the writer
}

grpc::Status PlaceDbService::CompleteInCluster(Stream* stream, Slot* slot) {
  v1::IngestResponse& response = slot->response;
  Work& work = slot->work;
  const MapEntry& map = *stream->map;
  ProcessedFrame& frame = work.frame;
  // The deadline of one frame's search and publish: the call's, at most kClusterPatience
  // from now (a stream has no deadline of its own; JetStream's leader elections take ~5-9 s).
  const auto deadline =
      std::min(stream->context->deadline(), std::chrono::system_clock::now() + kClusterPatience);
  if (slot->matches && frame.valid) {
    // Read-your-writes: a replica that has applied this stream's last place.
    v1::QueryResponse found;
    const grpc::Status searched = cluster_->Search(map.name, frame, work.metadata, *slot->matches,
                                                   stream->last_sequence, deadline, &found);
    if (!searched.ok()) return searched;
    response.mutable_matches()->Swap(found.mutable_matches());
  }
  // De-duplication across reconnects and workers: the agent's id and frame number.
  std::string message_id = slot->agent_id + "/" + std::to_string(slot->sequence);
  if (slot->agent_id.empty() && slot->sequence == 0) message_id.clear();  // none: no de-dup
  if (stream->loop_closure && frame.valid) {
    return CloseLoopInCluster(stream, slot, message_id, deadline);
  }
  Stopwatch publish;
  auto published = cluster_->Publish(map.name, frame, work.metadata, message_id, deadline);
  work.timings.store_ms = publish.Lap();
  if (!published.ok()) return ToGrpc(published.status(), "publishing");
  CountsToProto(frame.counts, response.mutable_counts());
  BoxesToProto(frame.boxes_used, response.mutable_boxes_used());
  if (frame.depth_state) DepthStateToProto(*frame.depth_state, response.mutable_depth());
  metrics_->CountDescriptors(map.name, frame.counts.dynamic, frame.counts.depth_removed,
                             frame.counts.static_);
  if (frame.valid) {
    response.set_stored(true);
    response.set_place_id(uint32_t(*published));
    stream->last_sequence = std::max(stream->last_sequence, *published);
    metrics_->FrameIngested(map.name);
  } else {
    response.set_stored(false);
    response.set_rejection(frame.rejection);
    metrics_->FrameRejected(map.name, "invalid_place");
  }
  return grpc::Status::OK;
}

grpc::Status PlaceDbService::CloseLoopInCluster(Stream* stream, Slot* slot,
                                                const std::string& message_id,
                                                ClusterBackend::Deadline deadline) {
  v1::IngestResponse& response = slot->response;
  Work& work = slot->work;
  const MapEntry& map = *stream->map;
  const ProcessedFrame& frame = work.frame;
  // The agent's detector lives in the local copy (per-agent state, with its Ingest stream); the
  // places it reads are the replicas'. Storing = publishing, as without loop closure.
  ReplicaPlaces source(cluster_, map.name, stream->last_sequence, deadline);
  if (stream->loop_agents.insert(work.metadata.agent_id).second) {
    // The agent's first frame in this stream: a detector this worker kept from an earlier stream
    // of the agent may lack the places it stored through other workers since; a new one replays
    // them all from a replica.
    map.map->ResetLoopClosure(work.metadata.agent_id);
  }
  double store_ms = 0;
  auto store = [&]() -> Result<PlaceId> {
    Stopwatch publish;
    auto published = cluster_->Publish(map.name, frame, work.metadata, message_id, deadline);
    store_ms = publish.Lap();
    if (!published.ok()) return published.status();
    return PlaceId(*published);
  };
  auto outcome = map.map->CloseLoop(frame, work.metadata, store, &source);
  work.timings.store_ms = store_ms;
  if (!outcome.ok()) return ToGrpc(outcome.status(), "loop closure");
  work.timings.loop_closure_ms = outcome->update_ms;
  if (outcome->replayed > 0) {
    spdlog::info(
        "loop closure map={} agent={}: {} earlier places replayed from a replica in {:.1f} "
        "ms",
        ForLog(map.name), ForLog(work.metadata.agent_id), outcome->replayed, outcome->replay_ms);
  }
  if (outcome->merged) {
    // As on a single node: nothing stored, the frame counted as one more observation of the
    // place it was merged into (its message id: a resent frame counts once).
    Stopwatch count;
    const Status counted = cluster_->CountObservation(map.name, outcome->place, frame,
                                                      work.metadata, message_id, deadline);
    work.timings.store_ms = count.Lap();
    if (!counted.ok()) return ToGrpc(counted, "counting the merged frame");
  }
  CountsToProto(frame.counts, response.mutable_counts());
  BoxesToProto(frame.boxes_used, response.mutable_boxes_used());
  if (frame.depth_state) DepthStateToProto(*frame.depth_state, response.mutable_depth());
  metrics_->CountDescriptors(map.name, frame.counts.dynamic, frame.counts.depth_removed,
                             frame.counts.static_);
  LoopClosureToProto(*outcome, response.mutable_loop_closure());
  if (outcome->loop) metrics_->LoopClosed(map.name);
  if (outcome->loop_rejected) metrics_->LoopRejected(map.name);
  if (outcome->merged) {
    response.set_stored(false);
    response.set_place_id(outcome->place);
    metrics_->FrameMerged(map.name);
  } else {
    response.set_stored(true);
    response.set_place_id(outcome->place);
    stream->last_sequence = std::max<uint64_t>(stream->last_sequence, outcome->place);
    metrics_->FrameIngested(map.name);
  }
  return grpc::Status::OK;
}

void PlaceDbService::Settle(Stream* stream, Slot* slot) {
  if (!slot->completed || slot->settled) return;
  slot->settled = true;
  v1::IngestResponse& response = slot->response;
  if (slot->commit) {
    const std::string& map_name = stream->map->name;
    const Result<AddResult>& added = slot->commit->Wait();
    if (!added.ok()) {
      metrics_->StorageError(map_name, added.status());
      slot->status = ToGrpc(added.status(), "storing");
      response.clear_counts();
      response.clear_boxes_used();
      response.clear_depth();
      response.clear_matches();
      response.mutable_error()->set_code(int(slot->status.error_code()));
      response.mutable_error()->set_message(
          HidePaths(slot->status.error_message(), config_.data_dir));
      metrics_->FrameRejected(map_name, GrpcCodeLabel(slot->status.error_code()));
      spdlog::warn("ingest frame error map={} index={} code={} message=\"{}\"", ForLog(map_name),
                   slot->index, GrpcCodeName(slot->status.error_code()),
                   ForLog(slot->status.error_message()));
    } else {
      Work& work = slot->work;
      work.timings.store_ms = added->timings.store_ms;
      response.set_stored(added->stored);
      response.set_place_id(added->id);
      metrics_->FrameIngested(map_name);
      work.timings.total_ms = MsSince(slot->arrived);
      TimingsToProto(work.timings, slot->queue_ms, response.mutable_timings());
      ObserveStages(work.timings);
    }
    slot->commit.reset();
  }
  slot->work = Work();  // the response may wait for a slow reader; the frame's data need not
  FrameOutcome outcome = FrameOutcome::kInvalid;
  if (!slot->status.ok()) {
    ++stream->errors;
    outcome = FrameOutcome::kRefused;
  } else if (response.stored()) {
    ++stream->stored;
    outcome = FrameOutcome::kStored;
  } else if (response.loop_closure().merged()) {
    ++stream->merged;
    outcome = FrameOutcome::kMerged;
  } else {
    ++stream->rejected;
  }
  activity_.Record(stream->map->name, slot->agent_id, outcome,
                   slot->status.ok() ? response.place_id() : 0, Clock::now(),
                   std::chrono::duration_cast<std::chrono::milliseconds>(
                       std::chrono::system_clock::now().time_since_epoch())
                       .count());
}

grpc::Status PlaceDbService::RefuseMalformed(const char* method, grpc::ServerContext* context,
                                             grpc::Status status) {
  CallScope scope(this);
  return Finish(method, context, std::move(status));
}

grpc::Status PlaceDbService::IngestStream(grpc::ServerContext* context, IngestStreamIo* io) {
  CallScope scope(this);
  const Clock::time_point opened = Clock::now();
  const Limits& limits = config_.limits;

  // Admission first: a stream holds a handler thread from now on, header or not, so it counts
  // against the limit from now on; over it, the thread is freed at once.
  Watch watch(context, "Ingest");
  const WatchScope listed(this, &watch);
  if (!listed.status().ok()) return Finish("Ingest", context, listed.status());

  // The header names the map. The watchdog cancels the call if it does not come in time.
  v1::IngestRequest first;
  const bool read_header = io->Read(&first);
  if (read_header) watch.HeaderArrived();
  if (!read_header && !io->ReadError().ok()) return Finish("Ingest", context, io->ReadError());
  if (!read_header) {
    if (auto closed = watch.Closed()) return Finish("Ingest", context, *closed);
    return Finish("Ingest", context,
                  Expired(context) ? Cancelled(context, "before the header")
                                   : Invalid("the stream ended before its IngestHeader"));
  }
  if (!first.has_header()) {
    return Finish("Ingest", context,
                  Invalid("header: the first message of an Ingest stream must be an IngestHeader"));
  }
  auto entry = GetMapEntry(first.header().map(), "header.map");
  if (!entry.ok()) return Finish("Ingest", context, ToGrpc(entry.status()));

  Stream stream;
  stream.context = context;
  stream.expiry_check.emplace(context);
  stream.watch = &watch;
  stream.map = *entry;
  if (first.header().has_matches()) stream.header_matches = first.header().matches();
  stream.loop_closure = first.header().loop_closure();
  // Declared after `stream`, so closed before it: its frames point to the stream. Made under the
  // lock that lists the stream, so a drain never sees a listed stream without its pipeline.
  std::optional<IngestPipeline> admitted;
  {
    MutexLock lock(streams_mutex_);
    if (draining_) return Finish("Ingest", context, Unavailable());
    admitted.emplace(
        pool_, limits.max_inflight_per_stream,
        IngestPipeline::Callbacks{.deliver =
                                      [this, io, &watch](IngestPipeline::Frame& frame) {
                                        auto& slot = static_cast<Slot&>(frame);
                                        Settle(slot.stream, &slot);
                                        // Timed: a client that takes no answers blocks here.
                                        watch.Writing();
                                        const bool written =
                                            io->Write(static_cast<Slot&>(frame).response);
                                        watch.Written();
                                        return written;
                                      },
                                  .expired = [&stream] { return stream.expiry(); },
                                  // Unblocks a handler waiting in Read().
                                  .interrupt = [context] { context->TryCancel(); }},
        // Reads never take the last quarter of the budget: streams waiting for their next
        // message would otherwise hold it all, and the frames read could not grow into it.
        IngestPipeline::Memory{.budget = budget_,
                               .read_bytes = limits.max_message_bytes,
                               .keep_free = (budget_->limit() - budget_->fixed()) / 4});
    stream.pipeline = &*admitted;
    streams_.insert(&stream);
  }
  IngestPipeline& pipeline = *admitted;
  spdlog::info("ingest stream opened peer={} map={} loop_closure={}", Peer(context),
               ForLog(stream.map->name), stream.loop_closure);

  grpc::Status status = grpc::Status::OK;
  uint64_t index = 0;
  while (true) {
    // Backpressure, per stream: no more than max_inflight_per_stream unanswered frames.
    watch.HeldBack();
    const auto room = pipeline.AwaitRoom();
    watch.Released();
    if (room != IngestPipeline::Room::kReady) {
      status = room == IngestPipeline::Room::kDraining ? Unavailable()
                                                       : Cancelled(context, "(stream closed)");
      break;
    }
    auto request = std::make_unique<v1::IngestRequest>();
    if (!io->Read(request.get())) {
      if (!io->ReadError().ok()) {
        status = io->ReadError();  // the frames before it are still answered
      } else if (Expired(context)) {
        status = pipeline.draining() ? Unavailable() : Cancelled(context, "(stream cancelled)");
      }
      break;
    }
    if (!request->has_observation()) {
      status = Invalid("message " + std::to_string(index + 1) +
                       ": after the header, every message must be an observation");
      break;
    }
    auto slot = std::make_unique<Slot>(this, &stream);
    slot->index = index++;
    slot->arrived = Clock::now();
    slot->sequence = request->observation().sequence();
    slot->agent_id = request->observation().agent_id();
    if (request->observation().has_matches()) {
      slot->matches = request->observation().matches();
    } else {
      slot->matches = stream.header_matches;
    }
    std::string agent = request->observation().agent_id();
    // The read's reservation, sized to the frame; a frame that does not fit is answered with
    // RESOURCE_EXHAUSTED and the stream goes on.
    slot->memory = pipeline.TakeReadReservation();
    slot->status =
        ChargeFrame(context, *stream.map, request->observation(), "this frame", &slot->memory);
    const bool charged = slot->status.ok();
    if (charged) {
      slot->request = std::move(request);
    } else {
      request.reset();
      slot->memory.Release();
    }
    // Global backpressure is inside: Submit() waits for room in the pool's queue.
    const IngestPipeline::Admission admission =
        charged ? pipeline.Submit(std::move(slot)) : pipeline.Reject(std::move(slot));
    if (admission == IngestPipeline::Admission::kDraining) {
      status = Unavailable();  // refused unread: the client sees it was never answered
      break;
    }
    ++stream.frames;
    if (stream.agents.size() < 4 &&
        std::find(stream.agents.begin(), stream.agents.end(), agent) == stream.agents.end()) {
      stream.agents.push_back(std::move(agent));
    }
    if (admission != IngestPipeline::Admission::kQueued) {
      status = stream.refusal;  // the frame itself was answered with the same error
      break;
    }
  }

  // Every frame read is completed and answered (or dropped if the client is gone) before the
  // call returns: the workers reference this stream.
  pipeline.Close();
  {
    MutexLock lock(streams_mutex_);
    streams_.erase(&stream);
  }
  if (auto closed = watch.Closed()) status = *closed;
  std::string agents;
  for (const std::string& agent : stream.agents) agents += (agents.empty() ? "" : ",") + agent;
  spdlog::info(
      "ingest stream closed peer={} map={} agent={} frames={} stored={} merged={} rejected={} "
      "errors={} duration={:.3f}s status={}",
      Peer(context), ForLog(stream.map->name), ForLog(agents), stream.frames, stream.stored,
      stream.merged, stream.rejected, stream.errors, MsSince(opened) / 1000.0,
      GrpcCodeName(status.error_code()));
  return Finish("Ingest", context, status);
}

// ---- Shutdown and gauges ------------------------------------------------------------------------

void PlaceDbService::BeginDrain() {
  MutexLock lock(streams_mutex_);
  draining_ = true;
  draining_flag_ = true;
  for (Watch* watch : watches_) {
    MutexLock watch_lock(watch->mutex);
    if (!watch->header) watch->context->TryCancel();  // blocked reading its header
    // An upload still reading (not importing): the client sends it again to another server.
    if (std::string_view(watch->method) == "UploadSnapshot" && watch->in_flight == 0) {
      watch->context->TryCancel();
    }
  }
  // An idle stream's handler is blocked in Read() and is cancelled now; a busy one once its last
  // frame is answered (IngestPipeline::Drain).
  for (Stream* stream : streams_) stream->pipeline->Drain();
}

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
  // A cluster worker's local copies hold no places: the shards export the maps' figures.
  if (cluster_) return;
  if (auto store = maps_->snapshots()) {
    double bytes = 0;
    const auto snapshots = store->List();
    for (const SnapshotInfo& info : snapshots) bytes += double(info.bytes);
    metrics_->SetSnapshotGauges(double(snapshots.size()), bytes);
  }
  for (const auto& entry : maps_->List()) {
    metrics_->SetMapDamage(entry->name, entry->damaged, double(entry->places_lost()));
    if (!entry->map) continue;
    const MapStats stats = entry->map->Stats();
    metrics_->SetMapGauges(entry->name, double(stats.database.places), double(stats.bytes_on_disk));
    // A read error leaves the gauge as it was; the map's RPCs report it.
    if (auto dynamics = entry->map->MapDynamics(); dynamics.ok()) {
      metrics_->SetMapDynamicCoverage(entry->name, dynamics->mean_coverage());
    }
  }
}

// ---- Snapshots ----------------------------------------------------------------------------------

namespace {

void SnapshotToProto(const SnapshotInfo& info, v1::Snapshot* out) {
  out->set_id(info.id);
  out->set_map(info.map);
  out->set_created_unix_ms(info.created_unix_ms);
  out->set_feature_type(info.feature_type);
  out->set_vocabulary_checksum(info.vocabulary_checksum);
  out->set_places(info.places);
  out->set_bytes(info.bytes);
}

constexpr size_t kSnapshotChunkBytes = size_t(256) << 10;  // well under any max_message_bytes

}  // namespace

grpc::Status PlaceDbService::CreateSnapshot(grpc::ServerContext* context,
                                            const v1::CreateSnapshotRequest* request,
                                            v1::Snapshot* response) {
  CallScope scope(this);
  if (cluster_) return Finish("CreateSnapshot", context, NotInCluster("CreateSnapshot"));
  if (draining_flag_) return Finish("CreateSnapshot", context, Unavailable());
  const Clock::time_point start = Clock::now();
  auto info = maps_->CreateSnapshot(request->map());
  if (!info.ok()) {
    return Finish("CreateSnapshot", context, HidePaths(ToGrpc(info.status()), config_.data_dir));
  }
  metrics_->ObserveSnapshot("create", MsSince(start) / 1000.0);
  SnapshotToProto(*info, response);
  spdlog::info("snapshot '{}' of map '{}' created: {} places, {} bytes, peer={}", ForLog(info->id),
               ForLog(info->map), info->places, info->bytes, Peer(context));
  return Finish("CreateSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::ListSnapshots(grpc::ServerContext* context,
                                           const v1::ListSnapshotsRequest*,
                                           v1::ListSnapshotsResponse* response) {
  CallScope scope(this);
  if (cluster_) return Finish("ListSnapshots", context, NotInCluster("ListSnapshots"));
  auto store = maps_->snapshots();
  if (!store) return Finish("ListSnapshots", context, Unavailable());
  for (const SnapshotInfo& info : store->List()) SnapshotToProto(info, response->add_snapshots());
  return Finish("ListSnapshots", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::DeleteSnapshot(grpc::ServerContext* context,
                                            const v1::DeleteSnapshotRequest* request,
                                            v1::DeleteSnapshotResponse*) {
  CallScope scope(this);
  if (cluster_) return Finish("DeleteSnapshot", context, NotInCluster("DeleteSnapshot"));
  auto store = maps_->snapshots();
  if (!store || draining_flag_) return Finish("DeleteSnapshot", context, Unavailable());
  if (Status deleted = store->Delete(request->id()); !deleted.ok()) {
    return Finish("DeleteSnapshot", context,
                  HidePaths(ToGrpc(deleted.WithContext("id")), config_.data_dir));
  }
  spdlog::info("snapshot '{}' deleted, peer={}", ForLog(request->id()), Peer(context));
  return Finish("DeleteSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::RestoreSnapshot(grpc::ServerContext* context,
                                             const v1::RestoreSnapshotRequest* request,
                                             v1::MapDescription* response) {
  CallScope scope(this);
  if (cluster_) return Finish("RestoreSnapshot", context, NotInCluster("RestoreSnapshot"));
  if (draining_flag_) return Finish("RestoreSnapshot", context, Unavailable());
  if (Status valid = ValidateSnapshotId(request->id()); !valid.ok()) {
    return Finish("RestoreSnapshot", context, ToGrpc(valid.WithContext("id")));
  }
  const Clock::time_point start = Clock::now();
  auto entry = maps_->RestoreSnapshot(request->id(), request->new_map());
  if (!entry.ok()) {
    return Finish("RestoreSnapshot", context, HidePaths(ToGrpc(entry.status()), config_.data_dir));
  }
  metrics_->ObserveSnapshot("restore", MsSince(start) / 1000.0);
  Describe(**entry, response);
  spdlog::info("snapshot '{}' restored as map '{}', peer={}", ForLog(request->id()),
               ForLog(request->new_map()), Peer(context));
  return Finish("RestoreSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::DownloadSnapshotStream(
    grpc::ServerContext* context, const v1::DownloadSnapshotRequest* request,
    const std::function<bool(const v1::SnapshotChunk&)>& write) {
  CallScope scope(this);
  if (cluster_) return Finish("DownloadSnapshot", context, NotInCluster("DownloadSnapshot"));
  auto store = maps_->snapshots();
  if (!store || draining_flag_) return Finish("DownloadSnapshot", context, Unavailable());
  // A stream like Ingest's: counted against max_concurrent_streams, and cancelled by the watchdog
  // when the client takes no chunk for stream_idle_timeout_ms. Never idle otherwise: every pause
  // between writes is the server reading its files.
  Watch watch(context, "DownloadSnapshot");
  const WatchScope listed(this, &watch);
  if (!listed.status().ok()) return Finish("DownloadSnapshot", context, listed.status());
  watch.HeaderArrived();  // the request is the whole header
  watch.HeldBack();
  auto info = store->Get(request->id());
  if (!info.ok()) {
    return Finish("DownloadSnapshot", context,
                  HidePaths(ToGrpc(info.status().WithContext("id")), config_.data_dir));
  }
  auto size = store->ArchiveBytes(request->id());
  if (!size.ok()) {
    return Finish("DownloadSnapshot", context, HidePaths(ToGrpc(size.status()), config_.data_dir));
  }
  bool first = true;
  bool drained = false;
  Status written = store->WriteArchive(
      request->id(), kSnapshotChunkBytes, [&](std::string_view bytes) -> Status {
        if (context->IsCancelled()) return Status::Cancelled("the client cancelled the download");
        if (draining_flag_) {  // shutting down: the client downloads again from the start
          drained = true;
          return Status::Cancelled("the server is shutting down");
        }
        v1::SnapshotChunk chunk;
        if (first) {
          SnapshotToProto(*info, chunk.mutable_snapshot());
          chunk.set_archive_bytes(*size);
          first = false;
        }
        chunk.set_data(std::string(bytes));
        watch.Writing();
        const bool sent = write(chunk);
        watch.Written();
        if (!sent) return Status::Cancelled("the client went away during the download");
        metrics_->SnapshotBytesSent(bytes.size());
        return Status::Ok();
      });
  if (auto closed = watch.Closed()) return Finish("DownloadSnapshot", context, *closed);
  if (drained) return Finish("DownloadSnapshot", context, Unavailable());
  if (!written.ok()) {
    return Finish("DownloadSnapshot", context, HidePaths(ToGrpc(written), config_.data_dir));
  }
  spdlog::info("snapshot '{}' downloaded: {} bytes, peer={}", ForLog(request->id()), *size,
               Peer(context));
  return Finish("DownloadSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::UploadSnapshotStream(
    grpc::ServerContext* context,
    const std::function<grpc::Status(v1::SnapshotChunk*, bool* done)>& read,
    v1::Snapshot* response) {
  CallScope scope(this);
  if (cluster_) return Finish("UploadSnapshot", context, NotInCluster("UploadSnapshot"));
  auto store = maps_->snapshots();
  if (!store || draining_flag_) return Finish("UploadSnapshot", context, Unavailable());
  // A stream like Ingest's: counted against max_concurrent_streams, and cancelled by the watchdog
  // when no chunk arrives for stream_idle_timeout_ms (the import after the last one is the
  // server's work: not idle).
  Watch watch(context, "UploadSnapshot");
  const WatchScope listed(this, &watch);
  if (!listed.status().ok()) return Finish("UploadSnapshot", context, listed.status());
  watch.HeaderArrived();
  // The archive is spooled into a dot-file of the snapshots folder (removed on every path, and by
  // SnapshotStore::Open after a crash), then imported.
  static std::atomic<uint64_t> uploads{0};
  const std::string spool =
      store->path() + "/.upload-" + std::to_string(::getpid()) + "-" + std::to_string(++uploads);
  struct Spool {
    std::string path;
    ~Spool() { std::remove(path.c_str()); }
  } cleanup{spool};
  std::ofstream out(spool, std::ios::binary | std::ios::trunc);
  if (!out) return Finish("UploadSnapshot", context, ToGrpc(Status::IoError("cannot spool")));
  uint64_t expected = 0;
  uint64_t received = 0;
  // The archive's first bytes, checked once they hold kUploadHeadBytes: an upload that is no
  // archive, or whose framing is over a limit (a 1 GiB SNAPSHOT.json), is refused there instead
  // of after spooling up to limits.max_snapshot_bytes. Import checks everything again.
  constexpr size_t kUploadHeadBytes = 4096;
  std::string head;
  bool head_checked = false;
  for (size_t n = 0;; ++n) {
    v1::SnapshotChunk chunk;
    bool done = false;
    if (grpc::Status status = read(&chunk, &done); !status.ok()) {
      return Finish("UploadSnapshot", context, status);
    }
    if (auto closed = watch.Closed()) return Finish("UploadSnapshot", context, *closed);
    if (context->IsCancelled()) {
      return Finish("UploadSnapshot", context,
                    draining_flag_ ? Unavailable() : Cancelled(context, "during the upload"));
    }
    if (done) break;
    watch.Received();
    const uint64_t limit = config_.limits.max_snapshot_bytes;
    if (n == 0 && chunk.archive_bytes() > 0) {
      expected = chunk.archive_bytes();
      // Refused before any byte is spooled: over the limit, or more than the disk can take.
      if (expected > limit) {
        return Finish("UploadSnapshot", context,
                      grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                                   "archive_bytes: " + std::to_string(expected) +
                                       " bytes announced, over limits.max_snapshot_bytes = " +
                                       std::to_string(limit)));
      }
      if (Status room = store->CheckRoomForImport(expected); !room.ok()) {
        return Finish("UploadSnapshot", context, ToGrpc(room.WithContext("archive_bytes")));
      }
    }
    received += chunk.data().size();
    metrics_->SnapshotBytesReceived(chunk.data().size());
    if (received > limit) {
      return Finish("UploadSnapshot", context,
                    grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                                 "the upload is longer than limits.max_snapshot_bytes = " +
                                     std::to_string(limit)));
    }
    if (expected && received > expected) {
      return Finish("UploadSnapshot", context,
                    ToGrpc(Status::InvalidArgument("archive_bytes: the upload is longer than the " +
                                                   std::to_string(expected) + " bytes announced")));
    }
    if (!head_checked) {
      head.append(chunk.data(), 0, kUploadHeadBytes - head.size());
      if (head.size() == kUploadHeadBytes) {
        head_checked = true;
        if (Status sound = CheckSnapshotArchiveHead(head); !sound.ok()) {
          return Finish("UploadSnapshot", context, ToGrpc(sound));
        }
      }
    }
    out.write(chunk.data().data(), std::streamsize(chunk.data().size()));
    if (!out) {
      return Finish("UploadSnapshot", context, ToGrpc(Status::IoError("spooling the upload")));
    }
  }
  out.close();
  if (expected && received != expected) {
    return Finish(
        "UploadSnapshot", context,
        ToGrpc(Status::Corruption("the upload is truncated: " + std::to_string(received) + " of " +
                                  std::to_string(expected) + " bytes announced")));
  }
  watch.HeldBack();  // verifying: the server's work, not the client's silence
  const Clock::time_point start = Clock::now();
  auto info = maps_->ImportSnapshot(spool);
  if (!info.ok()) {
    return Finish("UploadSnapshot", context, HidePaths(ToGrpc(info.status()), config_.data_dir));
  }
  metrics_->ObserveSnapshot("import", MsSince(start) / 1000.0);
  SnapshotToProto(*info, response);
  spdlog::info("snapshot '{}' of map '{}' uploaded: {} places, {} bytes, peer={}", ForLog(info->id),
               ForLog(info->map), info->places, received, Peer(context));
  return Finish("UploadSnapshot", context, grpc::Status::OK);
}

}  // namespace placedb::server
