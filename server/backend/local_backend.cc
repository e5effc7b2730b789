#include "server/backend/local_backend.h"

#include <spdlog/spdlog.h>

#include <algorithm>

#include "core/base/text.h"
#include "core/storage/snapshots.h"
#include "proto/convert_config.h"
#include "proto/convert_dynamics.h"
#include "proto/convert_result.h"
#include "proto/status.h"
#include "server/backend/place_reads.h"

namespace placedb::server {

using wire::HidePaths;
using wire::ToGrpc;

namespace {

// The operator's search settings (config `search`), the same for every caller.
void ApplySearchSettings(const SearchSettings& search, QueryOptions* options) {
  options->search_threads = search.threads;
  options->max_word_share = search.max_word_share;
  options->skip_words_min_places = search.skip_words_min_places;
}

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

// One Ingest stream on a local map: stored through the map's commit queue (group commit).
class LocalIngestSession final : public IngestSession {
 public:
  LocalIngestSession(const ServerConfig& config, Metrics* metrics,
                     std::shared_ptr<const MapEntry> map)
      : config_(config), metrics_(metrics), map_(std::move(map)) {}

  grpc::Status Search(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                      const v1::MatchOptions& options, Deadline,
                      google::protobuf::RepeatedPtrField<v1::Match>* out,
                      StageTimings* timings) override {
    AwaitLastPlace();
    QueryOptions query = wire::QueryOptionsFromProto(options, metadata.agent_id);
    ApplySearchSettings(config_.search, &query);
    query.timestamp_ns = metadata.timestamp_ns;
    QueryResult result = map_->map->Search(frame, query);
    timings->search_ms = result.timings.search_ms;
    timings->verify_ms = result.timings.verify_ms;
    timings->pose_ms = result.timings.pose_ms;
    wire::MatchesToProto(result.matches, out);
    found_.Set(metadata, LoopConstraintsOf(metadata, result.matches));
    return grpc::Status::OK;
  }

  std::shared_ptr<PendingCommit> Store(ProcessedFrame frame, const PlaceMetadata& metadata,
                                       const std::string&, Deadline) override {
    // Group commit: the caller goes on; its answer waits for durability (and the frame's loop
    // constraints are logged with its place).
    last_commit_ = map_->map->Enqueue(std::move(frame), metadata, found_.Take(metadata));
    return last_commit_;
  }

  Result<LoopClosureOutcome> CloseLoop(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                       const std::string&, Deadline, AddResult* stored) override {
    AwaitLastPlace();
    auto outcome = map_->map->CloseLoop(frame, metadata, stored, found_.Take(metadata));
    if (!outcome.ok()) metrics_->StorageError(map_->name, outcome.status());
    return outcome;
  }

 private:
  // A place is stored and searchable before the next frame of its stream searches.
  void AwaitLastPlace() {
    if (!last_commit_) return;
    (void)last_commit_->Wait();  // a failure is its own frame's answer
    last_commit_.reset();
  }

  const ServerConfig& config_;
  Metrics* const metrics_;
  const std::shared_ptr<const MapEntry> map_;
  std::shared_ptr<PendingCommit> last_commit_;  // the stream's last place handed to the queue
  FoundLoops found_;                            // Search()'s, for the frame's Store()
};

}  // namespace

v1::MapState MapStateOf(const MapEntry& entry) {
  if (entry.damaged) return v1::MAP_STATE_DAMAGED;
  if (!entry.map) return v1::MAP_STATE_UNAVAILABLE;
  return entry.map->damage_history().empty() ? v1::MAP_STATE_AVAILABLE : v1::MAP_STATE_RECOVERED;
}

void DescribeMap(const MapEntry& entry, v1::MapDescription* out) {
  out->set_name(entry.name);
  out->set_state(MapStateOf(entry));
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
  wire::MapConfigToProto(info.options, entry.settings, entry.vocabulary_name,
                         out->mutable_config());
  wire::MapStatsToProto(entry.map->Stats(), out->mutable_stats());
  out->set_vocabulary_checksum(entry.map->database()->vocabulary().checksum_hex());
  out->set_created_unix_ms(info.created_unix_ms);
  wire::VocabularyRecordToProto(info.vocabulary, entry.map->switching_vocabulary(),
                                out->mutable_vocabulary());
  out->mutable_vocabulary()->set_map(entry.name);
}

grpc::Status LocalBackend::CreateMap(const MapCreation& creation, Deadline,
                                     v1::MapDescription* response) {
  auto entry = maps_->Create(creation.name, creation.options, creation.vocabulary_requested,
                             creation.settings);
  if (!entry.ok()) return ToGrpc(entry.status());
  DescribeMap(**entry, response);
  return grpc::Status::OK;
}

grpc::Status LocalBackend::GetMap(const std::string& name, Deadline, v1::MapDescription* response) {
  auto entry = maps_->Find(name, "name");
  if (!entry.ok()) return ToGrpc(entry.status());
  DescribeMap(**entry, response);
  return grpc::Status::OK;
}

grpc::Status LocalBackend::ListMaps(Deadline, v1::ListMapsResponse* response) {
  for (const auto& entry : maps_->List()) {
    v1::MapSummary* summary = response->add_maps();
    summary->set_name(entry->name);
    summary->set_available(entry->map != nullptr);
    summary->set_unavailable_reason(HidePaths(entry->unavailable_reason, config_.data_dir));
    summary->set_vocabulary(entry->vocabulary_name);
    summary->set_state(MapStateOf(*entry));
    summary->set_places_lost(entry->places_lost());
    if (entry->map) {
      summary->set_places(entry->map->database()->Stats().places);
      summary->set_feature_type(
          wire::FeatureTypeToProto(entry->map->database()->config().feature_type));
    }
  }
  return grpc::Status::OK;
}

grpc::Status LocalBackend::DeleteMap(const std::string& name, Deadline) {
  if (Status deleted = maps_->Delete(name); !deleted.ok()) return ToGrpc(deleted);
  metrics_->ForgetMap(name);
  return grpc::Status::OK;
}

grpc::Status LocalBackend::RecoverMap(const v1::RecoverMapRequest& request,
                                      v1::RecoverMapResponse* response) {
  MapDamage accepted;
  auto entry = maps_->Recover(request.name(), request.accept_data_loss(), &accepted);
  if (!entry.ok()) return ToGrpc(entry.status());
  DescribeMap(**entry, response->mutable_map());
  wire::MapDamageToProto(accepted, response->mutable_accepted());
  // Error level when anything was lost: an operator's log search for damage must find it.
  spdlog::log(accepted.writes_lost > 0 ? spdlog::level::err : spdlog::level::warn,
              "map '{}' recovered with data loss accepted: {} acknowledged places lost ({} "
              "writes); {}",
              ForLog(request.name()), accepted.places_lost, accepted.writes_lost,
              accepted.reason.empty() ? std::string("it was not damaged") : accepted.reason);
  return grpc::Status::OK;
}

grpc::Status LocalBackend::ScrubMap(const std::string& name, v1::ScrubReport* response) {
  auto entry = maps_->Get(name, "name");
  if (!entry.ok()) return ToGrpc(entry.status());
  auto report = (*entry)->map->Scrub();
  if (!report.ok()) return ToGrpc(report.status());
  wire::ScrubReportToProto(*report, response);
  if (report->clean()) {
    spdlog::info("map '{}' scrubbed: {} places, {} files, no damage", ForLog(name),
                 report->places_checked, report->files_checked);
  } else {
    spdlog::error("map '{}' scrubbed: {} of {} places and {} of {} files damaged{}{}", ForLog(name),
                  report->damaged_places.size(), report->places_checked,
                  report->damaged_files.size(), report->files_checked,
                  report->damaged_files.empty() ? "" : "; first: ",
                  report->damaged_files.empty()
                      ? ""
                      : report->damaged_files[0].file + ": " + report->damaged_files[0].reason);
  }
  return grpc::Status::OK;
}

grpc::Status LocalBackend::AdaptVocabulary(const v1::AdaptVocabularyRequest& request, Deadline,
                                           const std::atomic<bool>* cancel,
                                           v1::MapVocabulary* response) {
  auto entry = maps_->Get(request.name(), "name");
  if (!entry.ok()) return ToGrpc(entry.status());
  AdaptOptions options;
  options.learning = wire::LearningOptionsFromProto(request);
  options.cancel = cancel;
  spdlog::info("map '{}': learning a vocabulary from its stored places", ForLog(request.name()));
  auto record = (*entry)->map->AdaptVocabulary(options);
  if (!record.ok()) {
    spdlog::warn("map '{}': vocabulary not adapted: {}", ForLog(request.name()),
                 record.status().ToString());
    return ToGrpc(record.status());
  }
  maps_->VocabularySwitched(request.name());
  wire::VocabularyRecordToProto(*record, false, response);
  response->set_map(request.name());
  spdlog::info(
      "map '{}' switched to {}: learned in {:.1f} s, {} places re-indexed in {:.1f} s "
      "(generation {})",
      ForLog(request.name()), SourceText(record->current), record->current.learn_ms / 1000,
      record->places_reindexed, record->reindex_ms / 1000, record->generation);
  return grpc::Status::OK;
}

grpc::Status LocalBackend::RevertVocabulary(const std::string& name, Deadline,
                                            const std::atomic<bool>* cancel,
                                            v1::MapVocabulary* response) {
  auto entry = maps_->Get(name, "name");
  if (!entry.ok()) return ToGrpc(entry.status());
  AdaptOptions options;
  options.cancel = cancel;
  auto record = (*entry)->map->RevertVocabulary(options);
  if (!record.ok()) {
    spdlog::warn("map '{}': vocabulary not reverted: {}", ForLog(name), record.status().ToString());
    return ToGrpc(record.status());
  }
  maps_->VocabularySwitched(name);
  wire::VocabularyRecordToProto(*record, false, response);
  response->set_map(name);
  spdlog::info("map '{}' reverted to {}: {} places re-indexed in {:.1f} s (generation {})",
               ForLog(name), SourceText(record->current), record->places_reindexed,
               record->reindex_ms / 1000, record->generation);
  return grpc::Status::OK;
}

Result<std::shared_ptr<const MapEntry>> LocalBackend::Map(const std::string& name,
                                                          const std::string& field) {
  return maps_->Get(name, field);
}

grpc::Status LocalBackend::GetPlace(const v1::GetPlaceRequest& request, Deadline,
                                    v1::Place* response) {
  auto entry = maps_->Get(request.map(), "map");
  if (!entry.ok()) return ToGrpc(entry.status());
  return ToGrpc(ReadPlace(*(*entry)->map, request, response));
}

grpc::Status LocalBackend::ListPlaces(const v1::ListPlacesRequest& request, Deadline,
                                      v1::ListPlacesResponse* response) {
  auto entry = maps_->Get(request.map(), "map");
  if (!entry.ok()) return ToGrpc(entry.status());
  return ToGrpc(ListPlacesOf(*(*entry)->map, request, response));
}

grpc::Status LocalBackend::DeletePlace(const v1::DeletePlaceRequest& request, Deadline) {
  auto entry = maps_->Get(request.map(), "map");
  if (!entry.ok()) return ToGrpc(entry.status());
  const Status removed = (*entry)->map->RemovePlace(request.place_id());
  metrics_->StorageError((*entry)->name, removed);
  return ToGrpc(removed);
}

grpc::Status LocalBackend::GetDynamics(const v1::GetDynamicsRequest& request, Deadline,
                                       v1::GetDynamicsResponse* response) {
  auto entry = maps_->Get(request.map(), "map");
  if (!entry.ok()) return ToGrpc(entry.status());
  return ToGrpc(ReadDynamics(*(*entry)->map, request, response));
}

grpc::Status LocalBackend::Query(const MapEntry& map, const ProcessedFrame& frame,
                                 const PlaceMetadata& metadata, const v1::QueryRequest& request,
                                 Deadline, v1::QueryResponse* out, StageTimings* timings) {
  QueryOptions options = wire::QueryOptionsFromProto(request.options(), metadata.agent_id);
  ApplySearchSettings(config_.search, &options);
  options.timestamp_ns = request.observation().timestamp_ns();
  QueryResult result = map.map->Search(frame, options);
  // A map that counts query hits (MapConfig.dynamics): durable before the answer.
  if (auto counted = map.map->CountQueryHit(frame, metadata, result); !counted.ok()) {
    metrics_->StorageError(map.name, counted.status());
    return ToGrpc(counted.status());
  }
  timings->search_ms = result.timings.search_ms;
  timings->verify_ms = result.timings.verify_ms;
  timings->pose_ms = result.timings.pose_ms;
  wire::MatchesToProto(result.matches, out->mutable_matches());
  return grpc::Status::OK;
}

std::unique_ptr<IngestSession> LocalBackend::OpenIngest(std::shared_ptr<const MapEntry> map) {
  return std::make_unique<LocalIngestSession>(config_, metrics_, std::move(map));
}

grpc::Status LocalBackend::WatchLoopClosures(
    const v1::WatchLoopClosuresRequest& request,
    const std::function<bool(const v1::LoopConstraint&)>& write,
    const std::function<grpc::Status()>& stop) {
  auto entry = maps_->Get(request.map(), "map");
  if (!entry.ok()) return ToGrpc(entry.status());
  return StreamLoopLog((*entry)->name, *(*entry)->map, request, write, stop);
}

grpc::Status LocalBackend::Snapshots(std::shared_ptr<SnapshotStore>* store) {
  *store = maps_->snapshots();
  if (!*store) return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is shutting down");
  return grpc::Status::OK;
}

grpc::Status LocalBackend::CreateSnapshot(const std::string& map, SnapshotInfo* info) {
  auto created = maps_->CreateSnapshot(map);
  if (!created.ok()) return HidePaths(ToGrpc(created.status()), config_.data_dir);
  *info = std::move(created).value();
  return grpc::Status::OK;
}

grpc::Status LocalBackend::ListSnapshots(std::vector<SnapshotInfo>* out) {
  std::shared_ptr<SnapshotStore> store;
  if (grpc::Status kept = Snapshots(&store); !kept.ok()) return kept;
  *out = store->List();
  return grpc::Status::OK;
}

grpc::Status LocalBackend::DeleteSnapshot(const std::string& id) {
  std::shared_ptr<SnapshotStore> store;
  if (grpc::Status kept = Snapshots(&store); !kept.ok()) return kept;
  if (Status deleted = store->Delete(id); !deleted.ok()) {
    return HidePaths(ToGrpc(deleted.WithContext("id")), config_.data_dir);
  }
  return grpc::Status::OK;
}

grpc::Status LocalBackend::WriteSnapshotArchive(
    const std::string& id, size_t chunk_bytes,
    const std::function<Status(const SnapshotInfo& info, uint64_t bytes)>& start,
    const std::function<Status(std::string_view)>& sink) {
  std::shared_ptr<SnapshotStore> store;
  if (grpc::Status kept = Snapshots(&store); !kept.ok()) return kept;
  auto info = store->Get(id);
  if (!info.ok()) return HidePaths(ToGrpc(info.status().WithContext("id")), config_.data_dir);
  auto size = store->ArchiveBytes(id);
  if (!size.ok()) return HidePaths(ToGrpc(size.status()), config_.data_dir);
  if (Status started = start(*info, *size); !started.ok()) return ToGrpc(started);
  return HidePaths(ToGrpc(store->WriteArchive(id, chunk_bytes, sink)), config_.data_dir);
}

grpc::Status LocalBackend::RestoreSnapshot(const v1::RestoreSnapshotRequest& request,
                                           v1::MapDescription* response) {
  auto entry = maps_->RestoreSnapshot(request.id(), request.new_map());
  if (!entry.ok()) return HidePaths(ToGrpc(entry.status()), config_.data_dir);
  DescribeMap(**entry, response);
  return grpc::Status::OK;
}

grpc::Status LocalBackend::ImportSnapshot(const std::string& path, SnapshotInfo* info) {
  auto imported = maps_->ImportSnapshot(path);
  if (!imported.ok()) return HidePaths(ToGrpc(imported.status()), config_.data_dir);
  *info = std::move(imported).value();
  return grpc::Status::OK;
}

void LocalBackend::RefreshGauges() {
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

}  // namespace placedb::server
