// MapBackend (server/backend/map_backend.h) over this server's own maps: the MapRegistry of the
// data directory, its snapshot store, and the PlaceMaps themselves (group commit, loop closure,
// vocabulary switches). Role "single".
//
// Storage errors are counted in placedb_storage_errors_total{map,kind} (Metrics::StorageError)
// where they happen; every answer is otherwise left to the service.
// Thread safety: as MapBackend's.
#pragma once

#include "server/backend/map_backend.h"
#include "server/config.h"
#include "server/metrics.h"

namespace placedb::server {

// A map's state as GetMap and ListMaps show it (also the worker's copies: MapRegistry entries).
v1::MapState MapStateOf(const MapEntry& entry);
// GetMap's description of an open, damaged or unavailable map.
void DescribeMap(const MapEntry& entry, v1::MapDescription* out);

class LocalBackend final : public MapBackend {
 public:
  // `maps`, `metrics` and `config` outlive the backend.
  LocalBackend(const ServerConfig& config, MapRegistry* maps, Metrics* metrics)
      : config_(config), maps_(maps), metrics_(metrics) {}

  const char* role() const override { return "single"; }
  grpc::Status CreateMap(const MapCreation& creation, Deadline deadline,
                         v1::MapDescription* response) override;
  grpc::Status GetMap(const std::string& name, Deadline deadline,
                      v1::MapDescription* response) override;
  grpc::Status ListMaps(Deadline deadline, v1::ListMapsResponse* response) override;
  grpc::Status DeleteMap(const std::string& name, Deadline deadline) override;
  grpc::Status RecoverMap(const v1::RecoverMapRequest& request,
                          v1::RecoverMapResponse* response) override;
  grpc::Status ScrubMap(const std::string& name, v1::ScrubReport* response) override;
  grpc::Status AdaptVocabulary(const v1::AdaptVocabularyRequest& request, Deadline deadline,
                               const std::atomic<bool>* cancel,
                               v1::MapVocabulary* response) override;
  grpc::Status RevertVocabulary(const std::string& name, Deadline deadline,
                                const std::atomic<bool>* cancel,
                                v1::MapVocabulary* response) override;
  Result<std::shared_ptr<const MapEntry>> Map(const std::string& name,
                                              const std::string& field) override;
  grpc::Status GetPlace(const v1::GetPlaceRequest& request, Deadline deadline,
                        v1::Place* response) override;
  grpc::Status ListPlaces(const v1::ListPlacesRequest& request, Deadline deadline,
                          v1::ListPlacesResponse* response) override;
  grpc::Status DeletePlace(const v1::DeletePlaceRequest& request, Deadline deadline) override;
  grpc::Status GetDynamics(const v1::GetDynamicsRequest& request, Deadline deadline,
                           v1::GetDynamicsResponse* response) override;
  grpc::Status Query(const MapEntry& map, const ProcessedFrame& frame,
                     const PlaceMetadata& metadata, const v1::QueryRequest& request,
                     Deadline deadline, v1::QueryResponse* out, StageTimings* timings) override;
  std::unique_ptr<IngestSession> OpenIngest(std::shared_ptr<const MapEntry> map) override;
  grpc::Status WatchLoopClosures(const v1::WatchLoopClosuresRequest& request,
                                 const std::function<bool(const v1::LoopConstraint&)>& write,
                                 const std::function<grpc::Status()>& stop) override;
  grpc::Status Snapshots(std::shared_ptr<SnapshotStore>* store) override;
  grpc::Status CreateSnapshot(const std::string& map, SnapshotInfo* info) override;
  grpc::Status ListSnapshots(std::vector<SnapshotInfo>* out) override;
  grpc::Status DeleteSnapshot(const std::string& id) override;
  grpc::Status WriteSnapshotArchive(
      const std::string& id, size_t chunk_bytes,
      const std::function<Status(const SnapshotInfo& info, uint64_t bytes)>& start,
      const std::function<Status(std::string_view)>& sink) override;
  grpc::Status RestoreSnapshot(const v1::RestoreSnapshotRequest& request,
                               v1::MapDescription* response) override;
  grpc::Status ImportSnapshot(const std::string& path, SnapshotInfo* info) override;
  void RefreshGauges() override;

 private:
  const ServerConfig& config_;
  MapRegistry* const maps_;
  Metrics* const metrics_;
};

}  // namespace placedb::server
