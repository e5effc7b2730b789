// The one port the public placedb.v1 service (server/rpc/) reaches its maps through: admin,
// place reads, search, storing, snapshots. Two implementations, one per role:
// - LocalBackend (server/backend/local_backend.h): this server's own maps (MapRegistry over the
//   data directory): role "single".
// - ClusterWorker (server/cluster/worker.h): cluster mode's worker role, whose maps live on the
//   shards and whose places travel through the maps' JetStream streams: role "worker".
// The handlers never ask which one they hold: decoding, detection, extraction, filtering, the
// transform and the agent's stream state (Algorithm 1) are the service's own pipeline, run on
// Map()'s entry (the map itself, or the worker's place-less local copy); what follows the
// pipeline (search, store, loop closure) goes through this port.
//
// Errors are gRPC statuses with the single server's codes (NOT_FOUND, ALREADY_EXISTS,
// INVALID_ARGUMENT, FAILED_PRECONDITION) and UNAVAILABLE when an engine or every replica is
// unreachable. Every method is served by both (issue 35: ScrubMap, RecoverMap and the snapshots
// through workers, docs/cluster.md "Admin through workers"). A call that fails changes nothing the
// caller can observe, except where a method says otherwise.
//
// Thread safety: every method of MapBackend may be called concurrently. An IngestSession belongs
// to one Ingest stream and is called from one thread at a time, in the stream's order.
#pragma once

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/pipeline/place_database.h"
#include "core/storage/map_store.h"
#include "core/storage/snapshots.h"
#include "proto/convert_config.h"
#include "proto/placedb.pb.h"
#include "server/backend/map_registry.h"

namespace placedb::server {

// What one Ingest stream stores and searches, after the service's pipeline has prepared each
// frame and advanced the agent's stream state. Read-your-writes: a search sees every place
// stored earlier in the same session.
class IngestSession {
 public:
  using Deadline = std::chrono::system_clock::time_point;
  virtual ~IngestSession() = default;

  // The frame's matches (IngestRequest's MatchOptions) into `out`; search and verification
  // times into `timings`.
  virtual grpc::Status Search(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                              const v1::MatchOptions& options, Deadline deadline,
                              google::protobuf::RepeatedPtrField<v1::Match>* out,
                              StageTimings* timings) = 0;
  // Stores the frame as a place (an invalid one is counted as such and answers stored = false).
  // The outcome may come later (group commit): the frame is answered once it is there. Its
  // `message_id` (agent/sequence, empty = none) de-duplicates a frame resent after a reconnect
  // where the role supports it (cluster mode).
  virtual std::shared_ptr<PendingCommit> Store(ProcessedFrame frame, const PlaceMetadata& metadata,
                                               const std::string& message_id,
                                               Deadline deadline) = 0;
  // Loop-closure mode (IngestHeader.loop_closure), a valid frame: the agent's detector, then,
  // unless rehearsal merges the frame into an earlier place, the durable store, whose result
  // goes to `stored` (a merged frame counts as one more observation of its place).
  virtual Result<LoopClosureOutcome> CloseLoop(const ProcessedFrame& frame,
                                               const PlaceMetadata& metadata,
                                               const std::string& message_id, Deadline deadline,
                                               AddResult* stored) = 0;
};

// What a session's Search() found for the frame it is handling (its verified matches as loop
// constraints, core/storage/loop_log.h), until the Store() or CloseLoop() of the same frame takes
// them. Keyed by the frame's metadata: what a failed frame left behind is never another's.
class FoundLoops {
 public:
  void Set(const PlaceMetadata& frame, std::vector<LoopConstraint> found) {
    found_ = std::move(found);
    frame_ = frame;
  }
  std::vector<LoopConstraint> Take(const PlaceMetadata& frame) {
    std::vector<LoopConstraint> found;
    if (frame_ && *frame_ == frame) found.swap(found_);
    found_.clear();
    frame_.reset();
    return found;
  }

 private:
  std::vector<LoopConstraint> found_;
  std::optional<PlaceMetadata> frame_;
};

// A CreateMap request the service has checked and resolved.
struct MapCreation {
  std::string name;
  MapOptions options;
  ServiceMapSettings settings;
  std::string vocabulary_requested;  // MapConfig.vocabulary as sent ("" = the default)
  std::string vocabulary;            // the configured vocabulary it resolved to
};

class MapBackend {
 public:
  using Deadline = std::chrono::system_clock::time_point;
  virtual ~MapBackend() = default;

  // GetServerInfo's role: "single" or "worker".
  virtual const char* role() const = 0;

  // ---- Maps
  // ALREADY_EXISTS when the name is taken; `response` describes the new map.
  virtual grpc::Status CreateMap(const MapCreation& creation, Deadline deadline,
                                 v1::MapDescription* response) = 0;
  // Damaged and unavailable maps are described too (their state is what an operator looks for).
  virtual grpc::Status GetMap(const std::string& name, Deadline deadline,
                              v1::MapDescription* response) = 0;
  virtual grpc::Status ListMaps(Deadline deadline, v1::ListMapsResponse* response) = 0;
  virtual grpc::Status DeleteMap(const std::string& name, Deadline deadline) = 0;
  virtual grpc::Status RecoverMap(const v1::RecoverMapRequest& request,
                                  v1::RecoverMapResponse* response) = 0;
  virtual grpc::Status ScrubMap(const std::string& name, v1::ScrubReport* response) = 0;
  // Issue 29: a vocabulary learned from the map's stored places, switched to online; `cancel`
  // (a shutdown) stops it with the map on its old vocabulary.
  virtual grpc::Status AdaptVocabulary(const v1::AdaptVocabularyRequest& request, Deadline deadline,
                                       const std::atomic<bool>* cancel,
                                       v1::MapVocabulary* response) = 0;
  virtual grpc::Status RevertVocabulary(const std::string& name, Deadline deadline,
                                        const std::atomic<bool>* cancel,
                                        v1::MapVocabulary* response) = 0;
  // The map a frame is prepared on: its configuration, vocabulary and the agents' stream state.
  // NOT_FOUND (`field` named) when there is no such map; FAILED_PRECONDITION / CORRUPTION when
  // it is unavailable or damaged.
  virtual Result<std::shared_ptr<const MapEntry>> Map(const std::string& name,
                                                      const std::string& field) = 0;

  // ---- Places
  virtual grpc::Status GetPlace(const v1::GetPlaceRequest& request, Deadline deadline,
                                v1::Place* response) = 0;
  virtual grpc::Status ListPlaces(const v1::ListPlacesRequest& request, Deadline deadline,
                                  v1::ListPlacesResponse* response) = 0;
  // NOT_FOUND when the place does not exist.
  virtual grpc::Status DeletePlace(const v1::DeletePlaceRequest& request, Deadline deadline) = 0;
  virtual grpc::Status GetDynamics(const v1::GetDynamicsRequest& request, Deadline deadline,
                                   v1::GetDynamicsResponse* response) = 0;

  // ---- Query and Ingest
  // A valid query frame's matches (request.options, request.min_sequence) into `out`'s matches;
  // a map that counts query hits (MapConfig.dynamics) has the hit durable before this returns.
  // Search and verification times into `timings`.
  virtual grpc::Status Query(const MapEntry& map, const ProcessedFrame& frame,
                             const PlaceMetadata& metadata, const v1::QueryRequest& request,
                             Deadline deadline, v1::QueryResponse* out, StageTimings* timings) = 0;
  // One Ingest stream's session on `map` (Map()'s entry).
  virtual std::unique_ptr<IngestSession> OpenIngest(std::shared_ptr<const MapEntry> map) = 0;

  // ---- Loop-closure log (core/storage/loop_log.h)
  // WatchLoopClosures: the map's log to `write` as StreamLoopLog (server/backend/place_reads.h)
  // says, `stop` asked between reads and waits. NOT_FOUND naming `map` for an unknown map,
  // FAILED_PRECONDITION / CORRUPTION when it is unavailable.
  virtual grpc::Status WatchLoopClosures(
      const v1::WatchLoopClosuresRequest& request,
      const std::function<bool(const v1::LoopConstraint&)>& write,
      const std::function<grpc::Status()>& stop) = 0;

  // ---- Snapshots (server/rpc/snapshots.cc). A single server keeps them in its data directory,
  // a worker in the cluster (server/cluster/snapshot_archives.h): any worker sees them all.
  // The store uploads are spooled into and checked against (room on disk): UNAVAILABLE once it
  // is closed.
  virtual grpc::Status Snapshots(std::shared_ptr<SnapshotStore>* store) = 0;
  virtual grpc::Status CreateSnapshot(const std::string& map, SnapshotInfo* info) = 0;
  // Newest first.
  virtual grpc::Status ListSnapshots(std::vector<SnapshotInfo>* out) = 0;
  // NOT_FOUND naming the id when there is no such snapshot.
  virtual grpc::Status DeleteSnapshot(const std::string& id) = 0;
  // Snapshot `id`'s archive: `start` with its description and size first, then its bytes to
  // `sink` in pieces of at most `chunk_bytes`; an error of either stops it and is returned.
  // NOT_FOUND naming the id; DATA_LOSS when the archive read back is not what was stored (the
  // receiver must discard what it got).
  virtual grpc::Status WriteSnapshotArchive(
      const std::string& id, size_t chunk_bytes,
      const std::function<Status(const SnapshotInfo& info, uint64_t bytes)>& start,
      const std::function<Status(std::string_view)>& sink) = 0;
  virtual grpc::Status RestoreSnapshot(const v1::RestoreSnapshotRequest& request,
                                       v1::MapDescription* response) = 0;
  // An archive spooled at `path` (an upload), checked and added to the store.
  virtual grpc::Status ImportSnapshot(const std::string& path, SnapshotInfo* info) = 0;

  // The per-map gauges (places, bytes on disk, damage), before each metrics scrape: nothing
  // where the role holds no places (a worker: the shards export them).
  virtual void RefreshGauges() = 0;
};

}  // namespace placedb::server
