// What PlaceDbService (server/service.h) delegates to in cluster mode's worker role (issue 18,
// docs/cluster.md): the maps live on shards and their places in JetStream streams, so map
// admin, search, storing and place reads go through this interface; decoding, detection,
// extraction, filtering, the transform and the agent's stream state (Algorithm 1, loop closure)
// stay the service's own pipeline, run on the worker's local copy of the map (Map()); loop
// closure reads the places it needs through FetchPlaces / AgentPlaces.
//
// The implementation is server/cluster/worker.h (placedb_cluster, built with libnats); the
// service only knows this interface, so a single-node build needs none of the engines.
//
// Errors are gRPC statuses with the codes the single server uses (NOT_FOUND, ALREADY_EXISTS,
// INVALID_ARGUMENT) plus UNAVAILABLE when an engine or every replica is unreachable.
// Thread safety: every method may be called concurrently.
#pragma once

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "core/base/status.h"
#include "core/pipeline/place_database.h"
#include "core/storage/map_store.h"
#include "proto/placedb.pb.h"
#include "server/map_registry.h"

namespace placedb::server {

class ClusterBackend {
 public:
  using Deadline = std::chrono::system_clock::time_point;
  virtual ~ClusterBackend() = default;

  // GetServerInfo's role ("worker").
  virtual const char* role() const = 0;

  // CreateMap once the service has checked the request and resolved its options (the map's
  // effective configuration is stored in etcd as `config`): ALREADY_EXISTS when the name is
  // taken. `response` describes the new map.
  virtual grpc::Status CreateMap(const std::string& name, const v1::MapConfig& config,
                                 Deadline deadline, v1::MapDescription* response) = 0;
  virtual grpc::Status GetMap(const std::string& name, Deadline deadline,
                              v1::MapDescription* response) = 0;
  virtual grpc::Status ListMaps(Deadline deadline, v1::ListMapsResponse* response) = 0;
  virtual grpc::Status DeleteMap(const std::string& name, Deadline deadline) = 0;

  // The worker's local copy of a cluster map, for the frame pipeline: the map's configuration and
  // vocabulary, and the agents' stream state; it never holds places. NOT_FOUND (`field` named)
  // when the cluster has no such map.
  virtual Result<std::shared_ptr<const MapEntry>> Map(const std::string& name,
                                                      const std::string& field) = 0;

  // Searches `frame` on a replica of `map` that has applied at least `min_sequence` (retried once
  // on the other replica when the first is unreachable). Fills `out`'s matches and sequence (the
  // replica's applied sequence).
  virtual grpc::Status Search(const std::string& map, const ProcessedFrame& frame,
                              const PlaceMetadata& metadata, const v1::MatchOptions& options,
                              uint64_t min_sequence, Deadline deadline, v1::QueryResponse* out) = 0;

  // Publishes `frame` as a place of `map` with `message_id` (de-duplication) and returns its
  // place id (the stream sequence; the original one for a duplicate) once JetStream has
  // acknowledged it; retried with the same id until `deadline`, then UNAVAILABLE (nothing was
  // acknowledged; the record may still be stored: a retry with the same id finds it). An invalid
  // frame is published as such (counted by the replicas) and answers 0.
  virtual Result<uint64_t> Publish(const std::string& map, const ProcessedFrame& frame,
                                   const PlaceMetadata& metadata, const std::string& message_id,
                                   Deadline deadline) = 0;

  // `frame`'s statistics as one more observation of `place` (a CountObservation record): a query
  // hit (MapConfig.dynamics.count_query_hits_above; `message_id` empty: no de-duplication, as on
  // a single server a retried Query counts again) or a stream frame merged by loop closure's
  // rehearsal (the frame's message id: a resent frame counts once). Acknowledged before it
  // returns; UNAVAILABLE as Publish.
  virtual Status CountObservation(const std::string& map, uint32_t place,
                                  const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                  const std::string& message_id, Deadline deadline) = 0;

  // Loop closure on a worker (the detector lives on the worker, the places on the replicas): the
  // BoW vectors of `ids` (and, with `features`, their SC features and direct index), read from a
  // replica that has applied `min_sequence` and the highest of them (a place id is its stream
  // sequence, so that replica has every one that still exists). A place that does not exist
  // (removed) is absent from the result. UNAVAILABLE / DEADLINE_EXCEEDED as Search.
  virtual Result<std::vector<std::pair<PlaceId, PlacePayload>>> FetchPlaces(
      const std::string& map, const std::vector<PlaceId>& ids, bool features, uint64_t min_sequence,
      Deadline deadline) = 0;
  // Every place of `agent_id` in `map` (id, observation sequence, BoW vector), any order, read
  // from replicas that have applied at least `min_sequence` and everything the map's stream held
  // when the call began (so places the agent stored through another worker are included), a
  // page at a time (each page retried on the other replica as Search). For a new detector's
  // replay (PlaceSource::AgentPlaces).
  virtual Result<std::vector<PlaceSource::AgentPlace>> AgentPlaces(const std::string& map,
                                                                   const std::string& agent_id,
                                                                   uint64_t min_sequence,
                                                                   Deadline deadline) = 0;

  // DeletePlace: NOT_FOUND when a replica (that applied the id) does not have the place; else a
  // DeletePlace record, acknowledged before it returns (the replicas remove it when applying).
  virtual grpc::Status DeletePlace(const v1::DeletePlaceRequest& request, Deadline deadline) = 0;

  // Issue 29: one replica learns a vocabulary from its stored places (options as the request's);
  // the worker publishes it to the map's stream in parts, then one switch record at which every
  // replica switches (re-indexing online), and answers once a replica has switched, with its
  // record. The worker's own copy of the map follows. FAILED_PRECONDITION when the map is too
  // small to learn from or already switching through this worker; UNAVAILABLE as Publish.
  virtual grpc::Status AdaptVocabulary(const v1::AdaptVocabularyRequest& request, Deadline deadline,
                                       v1::MapVocabulary* response) = 0;
  // The replicas' previous vocabulary back, through one switch record (they store its bytes).
  // FAILED_PRECONDITION when the map never switched.
  virtual grpc::Status RevertVocabulary(const std::string& name, Deadline deadline,
                                        v1::MapVocabulary* response) = 0;

  // Place reads, answered by a replica (retried once on the other).
  virtual grpc::Status GetPlace(const v1::GetPlaceRequest& request, Deadline deadline,
                                v1::Place* response) = 0;
  virtual grpc::Status ListPlaces(const v1::ListPlacesRequest& request, Deadline deadline,
                                  v1::ListPlacesResponse* response) = 0;
  virtual grpc::Status GetDynamics(const v1::GetDynamicsRequest& request, Deadline deadline,
                                   v1::GetDynamicsResponse* response) = 0;
};

}  // namespace placedb::server
