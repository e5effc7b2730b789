// placedb.v1.PlaceDb on the synchronous gRPC API, with the frame pipeline on a bounded pool: one
// service class, its handlers one file per RPC group (server/rpc/maps.cc, places.cc, query.cc,
// ingest.cc, snapshots.cc, info.cc; service.cc: calls in flight, drain, the watchdog). Every map
// is reached through one MapBackend (server/backend/map_backend.h): this server's own maps or a
// cluster worker's; no handler asks which.
//
// Ingest: the call's handler thread reads and hands each observation to the stream's
// IngestPipeline (server/ingest/ingest_pipeline.h), which prepares it on the WorkerPool (decode,
// detect, extract, depth, filter, transform) and completes it in stream order: the agent's stream
// state (Algorithm 1 on depth, PlaceMap::AdvanceStream), search and store (or, in loop-closure
// mode, PlaceMap::CloseLoop), so a frame's matches are the map before that frame, and its place id
// is stored before the next frame's search. The pipeline's delivery thread writes the responses in
// order. The handler reads its next message only when the stream has fewer than
// max_inflight_per_stream frames unanswered and the pool's queue has room: backpressure reaches
// the client through HTTP/2 flow control.
//
// Cancellation and deadlines are checked between stages; a cancelled frame is never stored.
//
// Open streams are bounded and reclaimed (snapshot downloads and uploads too, with the same
// limit, timeouts and metric reasons: a download whose client takes no chunk, an upload whose
// client sends none, for stream_idle_timeout_ms): an Ingest call counts against
// limits.max_concurrent_streams from the moment its handler runs (over the limit it is refused
// at once with RESOURCE_EXHAUSTED, freeing the thread), and the service's watchdog thread
// cancels a stream whose header is late (stream_header_timeout_ms), one that is idle (no frame
// in flight and nothing received for stream_idle_timeout_ms) and one whose client has not taken
// an answer for stream_idle_timeout_ms. A frame being processed never makes its stream idle.
#pragma once

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>

#include "core/base/thread_annotations.h"
#include "core/detect/detector.h"
#include "proto/placedb.grpc.pb.h"
#include "server/backend/map_backend.h"
#include "server/backend/map_registry.h"
#include "server/config.h"
#include "server/ingest/memory_budget.h"
#include "server/ingest/worker_pool.h"
#include "server/metrics.h"
#include "server/rpc/agent_activity.h"
#include "server/rpc/ingest_stream_io.h"

namespace placedb::server {

// The handlers, checked against the proto by the generated interface; gRPC reaches them through
// ParsingService (server/rpc/parsing_service.h), which parses the requests itself.
class PlaceDbService final : public v1::PlaceDb::Service {
 public:
  // `detector` null = server-side detection off; `detector_status` then says why ("off", or
  // "off: <error>" when a configured model failed to load). Frames and queries are charged to
  // `budget` (limits.memory_budget_bytes) from their read to their answer.
  // `query_pool` (optional, default `pool`): the workers Query runs on. `backend`: the maps
  // (LocalBackend over `maps`, or a cluster worker); `maps` also holds the server's configured
  // vocabularies.
  PlaceDbService(const ServerConfig& config, MapRegistry* maps, MapBackend* backend,
                 WorkerPool* pool, Metrics* metrics, const Detector* detector,
                 std::string detector_status, MemoryBudget* budget,
                 WorkerPool* query_pool = nullptr);
  ~PlaceDbService() override;

  grpc::Status CreateMap(grpc::ServerContext* context, const v1::CreateMapRequest* request,
                         v1::MapDescription* response) override;
  grpc::Status GetMap(grpc::ServerContext* context, const v1::GetMapRequest* request,
                      v1::MapDescription* response) override;
  grpc::Status ListMaps(grpc::ServerContext* context, const v1::ListMapsRequest* request,
                        v1::ListMapsResponse* response) override;
  grpc::Status DeleteMap(grpc::ServerContext* context, const v1::DeleteMapRequest* request,
                         v1::DeleteMapResponse* response) override;
  grpc::Status RecoverMap(grpc::ServerContext* context, const v1::RecoverMapRequest* request,
                          v1::RecoverMapResponse* response) override;
  grpc::Status ScrubMap(grpc::ServerContext* context, const v1::ScrubMapRequest* request,
                        v1::ScrubReport* response) override;
  grpc::Status AdaptVocabulary(grpc::ServerContext* context,
                               const v1::AdaptVocabularyRequest* request,
                               v1::MapVocabulary* response) override;
  grpc::Status RevertVocabulary(grpc::ServerContext* context,
                                const v1::RevertVocabularyRequest* request,
                                v1::MapVocabulary* response) override;
  // Ingest (the generated Ingest is not overridden: ParsingService reads the stream's raw
  // messages); a message that fails to parse ends the stream with its error.
  grpc::Status IngestStream(grpc::ServerContext* context, IngestStreamIo* io);
  grpc::Status Query(grpc::ServerContext* context, const v1::QueryRequest* request,
                     v1::QueryResponse* response) override;
  grpc::Status GetPlace(grpc::ServerContext* context, const v1::GetPlaceRequest* request,
                        v1::Place* response) override;
  // Newest first, PlaceDatabase::ListPlacesBefore's bounded walk (wire::PlaceListing).
  grpc::Status ListPlaces(grpc::ServerContext* context, const v1::ListPlacesRequest* request,
                          v1::ListPlacesResponse* response) override;
  grpc::Status DeletePlace(grpc::ServerContext* context, const v1::DeletePlaceRequest* request,
                           v1::DeletePlaceResponse* response) override;
  grpc::Status GetDynamics(grpc::ServerContext* context, const v1::GetDynamicsRequest* request,
                           v1::GetDynamicsResponse* response) override;
  grpc::Status GetServerInfo(grpc::ServerContext* context, const v1::GetServerInfoRequest* request,
                             v1::ServerInfo* response) override;

  // Snapshots (MapRegistry's SnapshotStore). The streaming two are reached through
  // ParsingService, which parses and serialises the chunks: `write` returns false once the
  // client is gone; `read` fills the next chunk and sets *done at the stream's end, or returns
  // INVALID_ARGUMENT for a message that is not a valid SnapshotChunk.
  grpc::Status CreateSnapshot(grpc::ServerContext* context,
                              const v1::CreateSnapshotRequest* request,
                              v1::Snapshot* response) override;
  grpc::Status ListSnapshots(grpc::ServerContext* context, const v1::ListSnapshotsRequest* request,
                             v1::ListSnapshotsResponse* response) override;
  grpc::Status DeleteSnapshot(grpc::ServerContext* context,
                              const v1::DeleteSnapshotRequest* request,
                              v1::DeleteSnapshotResponse* response) override;
  grpc::Status RestoreSnapshot(grpc::ServerContext* context,
                               const v1::RestoreSnapshotRequest* request,
                               v1::MapDescription* response) override;
  grpc::Status DownloadSnapshotStream(grpc::ServerContext* context,
                                      const v1::DownloadSnapshotRequest* request,
                                      const std::function<bool(const v1::SnapshotChunk&)>& write);
  // WatchLoopClosures (loops.cc), reached through ParsingService like the snapshot streams.
  grpc::Status WatchLoopClosuresStream(grpc::ServerContext* context,
                                       const v1::WatchLoopClosuresRequest* request,
                                       const std::function<bool(const v1::LoopConstraint&)>& write);
  grpc::Status UploadSnapshotStream(
      grpc::ServerContext* context,
      const std::function<grpc::Status(v1::SnapshotChunk*, bool* done)>& read,
      v1::Snapshot* response);

  // Shutdown, first step: new streams and calls are refused with UNAVAILABLE, streams stop
  // reading; every frame already read is still processed, stored and answered, then its stream
  // ends (an idle stream is cancelled right away, since its handler is blocked reading).
  void BeginDrain();
  // Waits until no call is being served (after BeginDrain), or until `deadline`. True if idle.
  bool WaitIdle(std::chrono::steady_clock::time_point deadline);
  // GetServerInfo's console_url (server/console): set once, before the server serves calls.
  void SetConsoleUrl(std::string url) { console_url_ = std::move(url); }
  // Sets the per-map gauges (places, bytes on disk, damage); run before each metrics scrape.
  void RefreshMapGauges();
  // A request refused before its handler (ParsingService: not a valid message, or denied by
  // authentication/authorization): counted and logged as every answer.
  grpc::Status RefuseMalformed(const char* method, grpc::ServerContext* context,
                               grpc::Status status);

  // One Ingest call or snapshot transfer as the watchdog sees it, from its handler's start
  // (call_support.h); WatchScope lists it (admission against max_concurrent_streams).
  struct Watch;
  class WatchScope;
  struct Stream;  // one open Ingest call past its header (ingest.cc)
  struct Slot;    // one observation of a stream (ingest.cc)
  struct Work;    // one frame's processing state (call_support.h)

 private:
  // Decode, detect, extract, [depth], filter, transform: the first half of a frame, on a worker.
  // `role`: kStream (Ingest: the agent's stream state is advanced later, in order) or kQuery.
  // `keep_dropped_keypoints`: the frame keeps its DC keypoints (to answer with them).
  grpc::Status Prepare(grpc::ServerContext* context, const MapEntry& map,
                       const v1::Observation& observation, const std::string& field, FrameRole role,
                       Work* work, bool keep_dropped_keypoints = false);
  // The second half of an Ingest frame (the agent's stream state: Algorithm 1; search when
  // asked; then store, or loop closure + store in loop-closure mode, through the stream's
  // IngestSession). The stream's pipeline runs it in stream order, one frame at a time.
  void Complete(Stream* stream, Slot* slot);
  // The rest of a completed frame's answer, on the stream's delivery thread before it is written
  // (or when it is skipped): waits until its place is durable and indexed (group commit), fills
  // in the outcome (stored or not, its place, loop closure's), and counts it. Idempotent;
  // nothing for a frame never completed.
  void Settle(Stream* stream, Slot* slot);
  // Sizes a frame's reservation (its read's, from the pipeline) to the frame, waiting up to
  // limits.memory_wait_ms; RESOURCE_EXHAUSTED naming the budget when it does not fit.
  grpc::Status ChargeFrame(grpc::ServerContext* context, const MapEntry& map,
                           const v1::Observation& observation, const char* what,
                           MemoryBudget::Reservation* reservation);
  grpc::Status Finish(const char* method, grpc::ServerContext* context, grpc::Status status);
  grpc::Status Unavailable() const;
  void ObserveStages(const StageTimings& timings);
  // The watchdog thread: every tick, cancels the streams past one of their timeouts.
  void Watchdog() EXCLUDES(streams_mutex_);
  void ReclaimExpired(std::chrono::steady_clock::time_point now) REQUIRES(streams_mutex_);

  const ServerConfig& config_;
  MapRegistry* const maps_;
  WorkerPool* const pool_;
  WorkerPool* const query_pool_;  // Query's workers (pool_ when none of its own)
  Metrics* const metrics_;
  const Detector* const detector_;  // null: server-side detection off
  const std::string detector_status_;
  MemoryBudget* const budget_;
  // Per map and agent, every Ingest frame Complete() answers; GetMap's MapDescription.agents.
  AgentActivity activity_;
  std::string console_url_;    // written before serving, read-only after
  MapBackend* const backend_;  // the maps: this server's or the cluster's

  // Counts calls being served (RAII CallScope in every handler), for WaitIdle().
  class CallScope;
  Mutex calls_mutex_;
  CondVar calls_idle_;
  size_t calls_in_flight_ GUARDED_BY(calls_mutex_) = 0;

  // Taken before a stream's own mutex (BeginDrain), never after.
  Mutex streams_mutex_;
  std::set<Stream*> streams_ GUARDED_BY(streams_mutex_);
  // Every Ingest call being served, header or not: what max_concurrent_streams counts and the
  // watchdog scans. A Watch's own mutex is taken after streams_mutex_, never before.
  std::set<Watch*> watches_ GUARDED_BY(streams_mutex_);
  bool draining_ GUARDED_BY(streams_mutex_) = false;
  std::atomic<bool> draining_flag_{false};            // draining_ for readers that take no lock
  bool stopping_ GUARDED_BY(streams_mutex_) = false;  // the destructor: the watchdog ends
  CondVar watchdog_wake_;                             // with streams_mutex_
  std::thread watchdog_;                              // last: starts once the state above exists
};

}  // namespace placedb::server
