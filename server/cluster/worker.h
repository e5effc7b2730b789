// The frame-worker role of cluster mode (issue 18, docs/cluster.md): the MapBackend
// (server/backend/map_backend.h) the public placedb.v1 service reaches its maps through on a
// worker.
//
// What a worker does, per call:
// - CreateMap: etcd transaction create-if-absent on maps/<map> (ALREADY_EXISTS), then the map's
//   JetStream stream (EnsureStream: stream_replicas replicas, 2-minute duplicate window); a
//   stream that cannot be made removes the key again (UNAVAILABLE). Then it waits (bounded) for
//   the coordinator's placement, so that the first frames find a replica. GetMap/ListMaps read
//   etcd (linearizable); DeleteMap deletes the map's keys (map, placement, applied) in one
//   transaction, then the stream.
// - Ingest (PlaceDbService runs the pipeline on Map()'s local copy; OpenIngest's session, in
//   server/cluster/ingest_session.cc, does the rest): search on a replica that has applied the
//   stream's last place (Search), then Publish: one MapRecord (the shard's codec,
//   server/cluster/map_record.h) with message id <agent_id>/<sequence>, acknowledged to the agent
//   only after the PubAck; place id = the PubAck's sequence. A duplicate's PubAck names the
//   first publish's record: the answer follows that record, read back from the stream (a place,
//   a merged frame's observation or an invalid frame), not this worker's processing. A
//   publish that fails is retried with the same id until the deadline; then UNAVAILABLE and
//   nothing is acknowledged.
// - Query, GetPlace, ListPlaces, GetDynamics: Shard RPCs on a replica from the placement: the
//   least lagging one whose applied sequence (etcd applied/<map>/<shard>, as the view last saw
//   it) is >= min_sequence; UNAVAILABLE or DEADLINE_EXCEEDED from it: once more on another
//   replica (counted in placedb_cluster_retries_total{call}). GetPlace of an id no replica has
//   reported applying yet (a place just acknowledged) waits, at most 5 s, until one has, then
//   asks again: read-your-writes for place ids.
// - DeletePlace: NOT_FOUND unless a replica has the place, then a DeletePlace record.
// - Query hits (maps with dynamics.count_query_hits_above): the worker publishes a
//   CountObservation record after the search, acknowledged before the query's answer.
// - ScrubMap, RecoverMap (issue 35): Shard RPCs on every live replica (shard_admin.cc), one
//   report covering them all; a damaged replica is rebuilt from a healthy one or the stream.
// - Snapshots (issue 35): CreateSnapshot streams the most applied replica's checkpoint (Shard.
//   Checkpoint, applier paused), verifies it here (SnapshotStore::Import), and stores it in the
//   cluster (server/cluster/snapshot_archives.h: chunks in a JetStream stream, manifest in etcd);
//   List/Download/Delete read the cluster's, an upload is checked here and stored likewise;
//   RestoreSnapshot makes a map (MakeMap) whose replicas restore the archive and whose stream
//   continues after the snapshot's records, so place ids stay the snapshot's.
//   This worker's local snapshot store only spools and checks archives;
// - WatchLoopClosures: relayed from the most applied replica's log (a frame's constraints travel
//   as a LoopConstraints record after its place); when that replica's stream fails, from the
//   next one, from the last sequence relayed + 1;
//   CreateMap with a vocabulary_policy: FAILED_PRECONDITION (no worker runs the policy).
// - FetchPlaces / AgentPlaces: loop closure's reads (below), Shard RPCs through OnReplica.
//
// Per-agent state and what a failover costs: the agent's stream state (depth Algorithm 1, the
// loop-closure detector) lives in this worker's local copy of the map, in memory, with the
// agent's Ingest stream on this worker; nothing of it is replicated. Loop closure
// (IngestHeader.loop_closure) runs the single-node detector (PlaceMap::CloseLoop) here: storing a
// frame = publishing it (message id <agent_id>/<sequence>, place id = the PubAck's sequence), a
// frame merged by rehearsal = a CountObservation record at the place it merged into (same
// message id), and every place the detector reads comes from a replica: its long-term memory's
// BoW vectors and the loop target's features (FetchPlaces, from a replica that applied the id),
// and, at the agent's first loop-closure frame of each Ingest stream, all the agent's places for
// the replay into a new detector (AgentPlaces, from replicas that applied the stream's last
// sequence; paged). A new detector per stream, also on the same worker: one kept from an earlier
// stream could lack places the agent stored through another worker since.
// When the worker dies, the agent's SDK reconnects to another worker: Algorithm 1 warms up again
// (its first frames after a reconnect are treated as after a server restart, docs/rgbd.md); the
// loop-closure detector is rebuilt by the replay (measured by worker_test: about 1950 places in
// 61-91 ms on this 2-core machine, load 3.6-16), without the old detector's weights and loop links,
// as after a single server's restart; and frames answered with an error (or never answered) are
// resent with their sequence: their message id finds the record already published, within the
// stream's duplicate window (2 minutes), and the answer is that record's (the same place id, or
// merged into the same place, or invalid), even where the new worker's Algorithm 1 or detector
// decided otherwise. A detector that added a place for such a frame is rebuilt by a replay at
// the agent's next frame.
//
// The worker's local copies of the maps (its data_dir) hold no places: they carry the map's
// configuration, vocabulary and the agents' stream state. They are a cache: removed at startup
// and re-made when a map is re-created under the same name (etcd create revision).
//
// The coordinator (server/cluster/placement.h) runs in every worker; one is elected.
//
// Threading: thread-safe (every method may be called concurrently).
#pragma once

#include <grpcpp/channel.h>
#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <deque>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>

#include "core/base/thread_annotations.h"
#include "server/backend/map_backend.h"
#include "server/backend/map_registry.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/placement.h"
#include "server/cluster/snapshot_archives.h"
#include "server/config.h"
#include "server/metrics.h"

namespace placedb::server {

// A frame's or a call's time for retries in the cluster: its deadline, at most 15 s from now (a
// stream has no deadline of its own; JetStream's leader elections take ~5-9 s).
inline MapBackend::Deadline Patient(MapBackend::Deadline deadline) {
  return std::min(deadline, std::chrono::system_clock::now() + std::chrono::seconds(15));
}

class ClusterWorker final : public MapBackend {
 public:
  // Connects to etcd and NATS (config.cluster), starts the view and the coordinator, and empties
  // `local` (the worker's cache of map copies). IO_ERROR when an engine cannot be reached.
  static Result<std::unique_ptr<ClusterWorker>> Start(const ServerConfig& config,
                                                      MapRegistry* local, Metrics* metrics);
  ~ClusterWorker() override;

  // ---- MapBackend
  const char* role() const override { return "worker"; }
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
  void RefreshGauges() override {}  // the shards export the maps' figures

  // ---- The worker's own calls (the ingest session's and the tests')
  // Searches `frame` on a replica of `map` that has applied at least `min_sequence` (retried once
  // on the other replica when the first is unreachable). Fills `out`'s matches and sequence (the
  // replica's applied sequence).
  grpc::Status Search(const std::string& map, const ProcessedFrame& frame,
                      const PlaceMetadata& metadata, const v1::MatchOptions& options,
                      uint64_t min_sequence, Deadline deadline, v1::QueryResponse* out);
  // What a map's stream holds for an ingested frame: the record its message id names, which the
  // frame's answer follows. When the id was in the stream already (a frame resent after a
  // failover whose first answer was lost) that is the first publish's record, read back from the
  // stream, whatever this worker decided for the frame this time.
  struct FrameRecord {
    enum class Kind { kPlace, kMerged, kInvalid };
    Kind kind = Kind::kPlace;
    uint32_t place = 0;      // kPlace: the place id; kMerged: the place it counted for (0: none)
    std::string rejection;   // kInvalid: why the frame was not stored
    bool duplicate = false;  // the record is an earlier publish's (this one was not stored)
  };
  // Publishes `frame` as a place of `map` (an invalid frame as such, counted by the replicas)
  // with `message_id` (de-duplication) and returns the stream's record of it once JetStream has
  // acknowledged it: place id = the stream sequence. Retried with the same id until `deadline`,
  // then UNAVAILABLE (nothing was acknowledged; the record may still be stored: a retry with the
  // same id finds it).
  Result<FrameRecord> Publish(const std::string& map, const ProcessedFrame& frame,
                              const PlaceMetadata& metadata, const std::string& message_id,
                              Deadline deadline);
  // `frame`'s statistics as one more observation of `place` (a CountObservation record): a query
  // hit (`message_id` empty: no de-duplication, as on a single server a retried Query counts
  // again) or a stream frame merged by loop closure's rehearsal (the frame's message id: a resent
  // frame counts once, and the answer is the stream's record, as Publish's). Acknowledged before
  // it returns; UNAVAILABLE as Publish.
  Result<FrameRecord> CountObservation(const std::string& map, uint32_t place,
                                       const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                       const std::string& message_id, Deadline deadline);
  // Issue 32: an ingested frame's loop constraints (query_place set) as one LoopConstraints
  // record for the replicas' loop-closure logs; `message_id` de-duplicates. Acknowledged before
  // it returns; UNAVAILABLE as Publish.
  Status PublishLoops(const std::string& map, const std::vector<LoopConstraint>& loops,
                      const std::string& message_id, Deadline deadline);
  // Loop closure's reads: the BoW vectors of `ids` (and, with `features`, their SC features and
  // direct index), from a replica that has applied `min_sequence` and the highest of them (a
  // place id is its stream sequence). A removed place is absent from the result.
  Result<std::vector<std::pair<PlaceId, PlacePayload>>> FetchPlaces(const std::string& map,
                                                                    const std::vector<PlaceId>& ids,
                                                                    bool features,
                                                                    uint64_t min_sequence,
                                                                    Deadline deadline);
  // Every place of `agent_id` in `map` (id, observation sequence, BoW vector), from replicas that
  // have applied at least `min_sequence` and everything the stream held when the call began, a
  // page at a time: a new detector's replay (PlaceSource::AgentPlaces).
  Result<std::vector<PlaceSource::AgentPlace>> AgentPlaces(const std::string& map,
                                                           const std::string& agent_id,
                                                           uint64_t min_sequence,
                                                           Deadline deadline);

  // For tests: the coordinator of this worker leads.
  bool coordinating() const { return coordinator_ && coordinator_->leading(); }

  // Issue 35, compaction (compaction.cc, docs/cluster.md "Compaction"). While this worker's
  // coordinator leads, a thread checks every map's stream about every second and compacts one
  // that holds more than cluster.compact_after_records records or compact_after_bytes bytes
  // beyond its base. One compaction of `map`, now: a new base (the most applied live replica's
  // checkpoint, verified here as CreateSnapshot's, stored as MapBase by compare-and-swap on
  // bases/<map> and the coordinator key), then the stream purged below min(base, applied of every
  // live replica in the placement) + 1, then the previous base's chunks deleted.
  // FAILED_PRECONDITION when this worker does not coordinate or another compaction won; the
  // engines' errors.
  struct Compaction {
    uint64_t base = 0;            // the map's base sequence now
    uint64_t first_sequence = 0;  // the stream's first sequence after the purge
    bool new_base = false;        // a new base was stored (else the purge alone, or nothing)
  };
  // `take_base` false: the purge alone (below the current base: a lagging replica caught up).
  Result<Compaction> CompactMap(const std::string& map, bool take_base = true)
      EXCLUDES(compact_mutex_);

 private:
  ClusterWorker(const ServerConfig& config, MapRegistry* local);

  static int64_t NowUnixMs() {
    return std::chrono::duration_cast<std::chrono::milliseconds>(
               std::chrono::system_clock::now().time_since_epoch())
        .count();
  }
  // A file in the local snapshot store's folder for an archive on its way (`what`: "cluster",
  // "compaction"; a dot-file, so SnapshotStore::Open removes it after a crash), removed when it
  // goes.
  struct ScratchFile {
    ScratchFile(const std::string& folder, const std::string& what) {
      static std::atomic<uint64_t> made{0};
      path = folder + "/." + what + "-" + std::to_string(::getpid()) + "-" + std::to_string(++made);
    }
    ~ScratchFile() { std::remove(path.c_str()); }
    ScratchFile(const ScratchFile&) = delete;
    ScratchFile& operator=(const ScratchFile&) = delete;
    std::string path;
  };

  // CreateMap's path, also RestoreSnapshot's: maps/<name> create-if-absent with `info`
  // (ALREADY_EXISTS), the map's stream, and (restored: info.snapshot_base > 0) the stream's next
  // sequence set to base + 1 while it is empty; then a wait for the placement.
  grpc::Status MakeMap(const std::string& name, const cluster::MapRecordInfo& info,
                       Deadline deadline, v1::MapDescription* response);
  // An archive checked as a single server checks it (SnapshotStore::Import into this worker's
  // local store, then removed there: the cluster keeps it), with what a restore needs of it:
  // `manifest`'s info, and with `open` its map's base and configuration (restored here under a
  // scratch name to read them: an upload's).
  grpc::Status CheckArchive(const std::string& path, bool open,
                            cluster::SnapshotManifest* manifest);
  // The map as etcd has it (the view, else a linearizable read): NOT_FOUND naming `field`.
  Result<cluster::MapView> Lookup(const std::string& name, const std::string& field);
  // The replicas to try for a read, best first: applied >= min_sequence first (most applied
  // first), then the others. Each: shard id and address. UNAVAILABLE when the map has none live.
  struct Replica {
    std::string shard;
    std::string address;
    uint64_t applied = 0;
  };
  Result<std::vector<Replica>> Replicas(const std::string& map, uint64_t min_sequence);
  std::shared_ptr<grpc::Channel> ChannelTo(const std::string& address) EXCLUDES(mutex_);
  // Runs `call(channel, attempt deadline)` on the best replica, and once more when it answers
  // UNAVAILABLE or DEADLINE_EXCEEDED, on the best other replica of the view as it is then
  // (counted as a retry of `what`); with two replicas the first attempt gets half the time left
  // before `deadline`.
  template <typename Call>
  grpc::Status OnReplica(const char* what, const std::string& map, uint64_t min_sequence,
                         Deadline deadline, Call&& call);
  // One record on the map's stream, retried with the same id until `deadline`.
  Result<cluster::PubAck> PublishRecord(const std::string& map, const std::string& data,
                                        const std::string& message_id, Deadline deadline);
  // The frame record at `sequence` of the map's stream, which a duplicate PubAck of the frame's
  // `message_id` named (read back, retried as PublishRecord until `deadline`). INTERNAL when it
  // is not that message or not a frame's record.
  Result<FrameRecord> RecordedFrame(const std::string& map, uint64_t sequence,
                                    const std::string& message_id, Deadline deadline);
  void Describe(const std::string& name, const cluster::MapView& view,
                v1::MapDescription* out) const;
  // Issue 29. A replica's vocabulary record (Shard.GetVocabulary) once it applied
  // `min_sequence`, and with `bytes` the current vocabulary's bytes.
  grpc::Status ReplicaVocabulary(const std::string& map, uint64_t min_sequence, bool bytes,
                                 Deadline deadline, v1::MapVocabulary* record,
                                 std::string* vocabulary);
  // The switch record at `sequence` applied by a replica: its record in `response`, and the
  // worker's copy of the map follows (`vocabulary`: the switch's, when the caller has it).
  grpc::Status AwaitSwitch(const std::string& map, uint64_t sequence, const AnyVocabulary* next,
                           Deadline deadline, v1::MapVocabulary* response);
  // AdaptVocabulary's and RevertVocabulary's start: the map exists (NOT_FOUND), this call holds
  // its one switch through this worker (FAILED_PRECONDITION while another runs; released with
  // `slot`), the call's time (30 min without a deadline) and where the map's stream ended.
  struct SwitchStart {
    std::shared_ptr<void> slot;
    Deadline until;
    uint64_t stream_last = 0;
  };
  Result<SwitchStart> StartSwitch(const std::string& name, Deadline deadline) EXCLUDES(mutex_);
  // Until every live replica of `map` has built the switch to `checksum` ahead of its record
  // (Shard.Status), at most until `until`: the switch record then costs the replicas only the
  // places applied since (one that has not built it builds it then, holding its records back).
  void AwaitPrepared(const std::string& map, uint64_t checksum, Deadline until);
  // The worker's copy of `map` takes the vocabulary `checksum` its replicas switched to (after
  // `min_sequence`): fetched from a replica unless `next` is it. Logged, not failed: frames
  // processed with an older vocabulary are transformed again by the replicas.
  void FollowVocabulary(const std::string& map, uint64_t checksum, uint64_t min_sequence,
                        const AnyVocabulary* next, Deadline deadline) EXCLUDES(follow_mutex_);

  // The most applied live replica's checkpoint of `map` (Shard.Checkpoint: its applier paused)
  // into the file `spool`, verified as a single server verifies a snapshot (CheckArchive):
  // `manifest`'s info, base (the checkpoint's applied sequence) and configuration. CreateSnapshot's
  // and compaction's.
  grpc::Status TakeCheckpoint(const std::string& map, const cluster::MapView& view,
                              const std::string& spool, Deadline deadline,
                              cluster::SnapshotManifest* manifest);
  void CompactLoop() EXCLUDES(compact_mutex_);
  // The purge point of `map`: min(base, the applied sequence of every live replica in its
  // placement) + 1; 0 when a live replica has not reported yet.
  uint64_t PurgeBelow(const cluster::MapView& view, uint64_t base) const;

  const ServerConfig& config_;
  const ClusterSettings& cluster_;
  MapRegistry* const local_;
  cluster::InternalTls tls_;  // cluster.internal_tls: shards, NATS and etcd over mutual TLS
  std::unique_ptr<cluster::EtcdClient> etcd_;
  std::unique_ptr<cluster::JetStream> jetstream_;
  std::unique_ptr<cluster::ClusterView> view_;
  std::unique_ptr<cluster::Coordinator> coordinator_;
  std::unique_ptr<cluster::SnapshotArchives> archives_;  // issue 35: the cluster's snapshots
  std::string id_;  // this worker's (hostname:pid[.n]), the coordinator's name

  prometheus::Histogram* publish_seconds_ = nullptr;
  prometheus::Family<prometheus::Counter>* retries_ = nullptr;
  // Compaction (set by the coordinating worker; by map).
  prometheus::Family<prometheus::Gauge>* stream_bytes_ = nullptr;
  prometheus::Family<prometheus::Gauge>* stream_records_ = nullptr;
  prometheus::Family<prometheus::Gauge>* base_sequence_ = nullptr;
  prometheus::Family<prometheus::Counter>* compactions_ = nullptr;
  prometheus::Family<prometheus::Counter>* compaction_failures_ = nullptr;

  // One compaction at a time through this worker; the loop's stop.
  Mutex compact_mutex_;
  CondVar compact_cv_;
  bool compact_stopping_ GUARDED_BY(compact_mutex_) = false;
  bool compacting_ GUARDED_BY(compact_mutex_) = false;
  // Per map: (when, the stream's last sequence then), sampled by the loop and CompactMap; a purge
  // stays at or below the newest sample older than cluster.compact_keep_s (none: no purge yet).
  void NoteStreamEnd(const std::string& map, uint64_t last_sequence) EXCLUDES(history_mutex_);
  uint64_t StoredBefore(const std::string& map, std::chrono::steady_clock::time_point when)
      EXCLUDES(history_mutex_);
  Mutex history_mutex_;
  std::map<std::string, std::deque<std::pair<std::chrono::steady_clock::time_point, uint64_t>>>
      stream_history_ GUARDED_BY(history_mutex_);
  // A map whose compaction failed is tried again after this (the loop's thread only).
  std::map<std::string, std::chrono::steady_clock::time_point> compact_retry_;
  std::thread compactor_;

  Mutex local_mutex_;  // serialises making local copies
  // Local copy made from the map key of this create revision.
  std::map<std::string, int64_t> local_revision_ GUARDED_BY(local_mutex_);
  Mutex mutex_;
  std::map<std::string, std::shared_ptr<grpc::Channel>> channels_ GUARDED_BY(mutex_);
  // Maps whose vocabulary this worker is switching (one switch per map at a time).
  std::set<std::string> switching_ GUARDED_BY(mutex_);
  Mutex follow_mutex_;  // one FollowVocabulary at a time
  // When following a map's vocabulary last failed: tried again 30 s later, not at every frame.
  std::map<std::string, std::chrono::steady_clock::time_point> follow_failed_
      GUARDED_BY(follow_mutex_);
};

}  // namespace placedb::server
