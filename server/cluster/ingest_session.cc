// ClusterWorker::OpenIngest (server/cluster/worker.h): one Ingest stream on a worker. Storing is
// publishing (place id = the stream sequence JetStream acknowledged); searches go to a replica
// that has applied the stream's last place (read-your-writes); loop closure runs the agent's
// detector on the worker's local copy of the map, reading the places it needs from replicas.

#include <spdlog/spdlog.h>

#include <optional>
#include <set>

#include "core/base/text.h"
#include "core/base/timing.h"
#include "proto/convert_result.h"
#include "proto/status.h"
#include "server/cluster/worker.h"

namespace placedb::server {

namespace {

using wire::ToGrpc;
using FrameRecord = ClusterWorker::FrameRecord;

// Loop closure's places on a worker, whose local copy of the map holds none: read from the map's
// replicas, for one frame of an Ingest stream (`min_sequence`: the stream's last place;
// `deadline`: the frame's).
class ReplicaPlaces final : public PlaceSource {
 public:
  ReplicaPlaces(ClusterWorker* worker, std::string map, uint64_t min_sequence,
                MapBackend::Deadline deadline)
      : worker_(worker), map_(std::move(map)), min_sequence_(min_sequence), deadline_(deadline) {}

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
    return worker_->AgentPlaces(map_, agent_id, min_sequence_, deadline_);
  }

 private:
  Result<PlacePayload> Fetch(PlaceId place, bool features) {
    auto fetched = worker_->FetchPlaces(map_, {place}, features, min_sequence_, deadline_);
    if (!fetched.ok()) return fetched.status();
    if (fetched->empty()) {
      return Status::NotFound("place " + std::to_string(place) + " not found in map '" + map_ +
                              "'");
    }
    return std::move(fetched->front().second);
  }

  ClusterWorker* const worker_;
  const std::string map_;
  const uint64_t min_sequence_;
  const MapBackend::Deadline deadline_;
};

std::shared_ptr<PendingCommit> Completed(Result<AddResult> outcome) {
  auto pending = std::make_shared<PendingCommit>();
  pending->Complete(std::move(outcome));
  return pending;
}

class ClusterIngestSession final : public IngestSession {
 public:
  ClusterIngestSession(ClusterWorker* worker, std::shared_ptr<const MapEntry> map)
      : worker_(worker), map_(std::move(map)) {}

  grpc::Status Search(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                      const v1::MatchOptions& options, Deadline deadline,
                      google::protobuf::RepeatedPtrField<v1::Match>* out, StageTimings*) override {
    v1::QueryResponse found;
    const grpc::Status searched = worker_->Search(map_->name, frame, metadata, options,
                                                  last_sequence_, Patient(deadline), &found);
    if (!searched.ok()) return searched;
    out->Swap(found.mutable_matches());
    found_.Set(metadata, LoopConstraintsOf(metadata, wire::MatchesFromProto(*out)));
    return grpc::Status::OK;
  }

  std::shared_ptr<PendingCommit> Store(ProcessedFrame frame, const PlaceMetadata& metadata,
                                       const std::string& message_id, Deadline deadline) override {
    Stopwatch publish;
    auto published = worker_->Publish(map_->name, frame, metadata, message_id, Patient(deadline));
    if (!published.ok()) return Completed(published.status().WithContext("publishing"));
    AddResult added;
    added.timings.store_ms = publish.Lap();
    std::vector<LoopConstraint> loops = found_.Take(metadata);
    // The answer follows the stream's record (a resent frame's first publish, see Publish).
    const FrameRecord& record = *published;
    switch (record.kind) {
      case FrameRecord::Kind::kPlace:
        added.stored = true;
        added.id = record.place;
        last_sequence_ = std::max<uint64_t>(last_sequence_, record.place);
        break;
      case FrameRecord::Kind::kMerged:
        // Only a loop-closure stream merges: this frame was first sent in one (a stream without
        // loop closure has no merged answer to give).
        added.rejection = "merged into place " + std::to_string(record.place) +
                          " by loop closure when this frame was first sent";
        break;
      case FrameRecord::Kind::kInvalid:
        added.rejection = record.rejection;
        break;
    }
    if (record.place != 0) {  // an invalid frame logs no loops (as on a single node)
      const Status logged =
          PublishLoops(record.place, std::move(loops), message_id, Patient(deadline));
      if (!logged.ok()) return Completed(logged);
      added.timings.store_ms += publish.Lap();
    }
    return Completed(std::move(added));
  }

  Result<LoopClosureOutcome> CloseLoop(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                       const std::string& message_id, Deadline deadline,
                                       AddResult* stored) override {
    deadline = Patient(deadline);
    const MapEntry& map = *map_;
    // The agent's detector lives in the local copy (per-agent state, with its Ingest stream); the
    // places it reads are the replicas'. Storing = publishing.
    ReplicaPlaces source(worker_, map.name, last_sequence_, deadline);
    if (loop_agents_.insert(metadata.agent_id).second) {
      // The agent's first frame in this stream: a detector this worker kept from an earlier
      // stream of the agent may lack the places it stored through other workers since; a new one
      // replays them all from a replica.
      map.map->ResetLoopClosure(metadata.agent_id);
    }
    double store_ms = 0;
    std::optional<FrameRecord> record;  // the stream's record of the frame
    auto store = [&]() -> Result<PlaceId> {
      Stopwatch publish;
      auto published = worker_->Publish(map.name, frame, metadata, message_id, deadline);
      store_ms = publish.Lap();
      if (!published.ok()) return published.status();
      record = *published;
      // The detector binds its new place to this id: none (0, as for a failed store) when the
      // stream's record of the frame is not a place.
      return PlaceId(record->kind == FrameRecord::Kind::kPlace ? record->place : 0);
    };
    auto outcome = map.map->CloseLoop(frame, metadata, store, &source);
    if (!outcome.ok()) return outcome.status();
    if (outcome->replayed > 0) {
      spdlog::info(
          "loop closure map={} agent={}: {} earlier places replayed from a replica in {:.1f} ms",
          ForLog(map.name), ForLog(metadata.agent_id), outcome->replayed, outcome->replay_ms);
    }
    if (outcome->merged) {
      // As on a single node: nothing stored, the frame counted as one more observation of the
      // place it was merged into (its message id: a resent frame counts once).
      Stopwatch count;
      auto counted = worker_->CountObservation(map.name, outcome->place, frame, metadata,
                                               message_id, deadline);
      store_ms = count.Lap();
      if (!counted.ok()) return counted.status().WithContext("counting the merged frame");
      record = *counted;
    }
    if (!record) return Status::Internal("loop closure stored the frame without publishing it");
    if (record->duplicate && !outcome->merged) {
      // The detector added a place for a frame the stream had already: either not a place at all
      // (its first publish was merged or invalid) or one its replay holds already. Rebuilt from
      // the agent's places at its next frame, the detector holds each of them once, as after a
      // failover.
      map.map->ResetLoopClosure(metadata.agent_id);
    }
    std::vector<LoopConstraint> loops = found_.Take(metadata);
    // The answer follows the stream's record (a resent frame's first publish, see Publish).
    switch (record->kind) {
      case FrameRecord::Kind::kPlace:
        outcome->merged = false;
        outcome->place = record->place;
        stored->stored = true;
        stored->id = record->place;
        last_sequence_ = std::max<uint64_t>(last_sequence_, record->place);
        break;
      case FrameRecord::Kind::kMerged:
        outcome->merged = true;
        outcome->place = record->place;
        break;
      case FrameRecord::Kind::kInvalid: {
        // First published as an invalid frame: answered as one (no place, no loop), with what
        // this call cost the detector.
        LoopClosureOutcome none;
        none.replayed = outcome->replayed;
        none.replay_ms = outcome->replay_ms;
        none.update_ms = outcome->update_ms;
        *outcome = std::move(none);
        stored->rejection = record->rejection;
        stored->timings.store_ms = store_ms;
        return outcome;
      }
    }
    AddDetectorLoop(*outcome, metadata, &loops);
    Stopwatch logging;
    const Status logged = PublishLoops(outcome->place, std::move(loops), message_id, deadline);
    if (!logged.ok()) return logged;
    stored->timings.store_ms = store_ms + logging.Lap();
    return outcome;
  }

 private:
  // The frame's loop constraints (its place `place`) as one record after its place's, for every
  // replica's loop-closure log; the frame's message id + "/loops" de-duplicates a resent frame's.
  Status PublishLoops(PlaceId place, std::vector<LoopConstraint> loops,
                      const std::string& message_id, Deadline deadline) {
    if (loops.empty()) return Status::Ok();
    for (LoopConstraint& constraint : loops) constraint.query_place = place;
    const Status published = worker_->PublishLoops(
        map_->name, loops, message_id.empty() ? message_id : message_id + "/loops", deadline);
    return published.WithContext("publishing the frame's loop constraints (place " +
                                 std::to_string(place) + ")");
  }

  ClusterWorker* const worker_;
  const std::shared_ptr<const MapEntry> map_;
  FoundLoops found_;                   // Search()'s, for the frame's Store() or CloseLoop()
  uint64_t last_sequence_ = 0;         // the stream's last place id: its searches' min_sequence
  std::set<std::string> loop_agents_;  // whose detector this stream has (re)started
};

}  // namespace

std::unique_ptr<IngestSession> ClusterWorker::OpenIngest(std::shared_ptr<const MapEntry> map) {
  return std::make_unique<ClusterIngestSession>(this, std::move(map));
}

}  // namespace placedb::server
