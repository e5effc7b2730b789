// Per-agent stream state of a PlaceDatabase: Algorithm 1 (depth_filter.h) and the Bayesian
// loop-closure detector (loop_closure.h) of every agent that sends frames, keyed by agent id.
//
// Each stream has its own mutex; the caller holds it while it runs the stream's stages, so one
// agent's frames serialise while different agents run in parallel. The loop-closure detector's
// long-term memory is the database's PayloadStore: a place that leaves working memory costs
// nothing extra (its BoW vector is in its payload already, on disk for a persistent map) and is
// read back when it is retrieved.
//
// State is in memory only: after a restart (or a reopened map) Algorithm 1 warms up again in 3
// frames, and PlaceDatabase::CloseLoop replays the agent's stored places into a new detector.
// On a cluster worker the places are not in the database: CloseLoop then reads them (long-term
// memory, verification, replay) from a PlaceSource instead of the payloads.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/base/thread_annotations.h"
#include "core/filter/depth_filter.h"
#include "core/search/loop_closure.h"

namespace placedb {

class PayloadStore;
class PlaceSource;

// Long-term memory backed by the database's payloads. The detector's place ids are bound to
// database places once stored; a detector place that was never stored (its store failed) keeps
// its vector here in memory instead.
class PayloadLongTermMemory final : public LongTermMemory {
 public:
  explicit PayloadLongTermMemory(std::shared_ptr<PayloadStore> payloads)
      : payloads_(std::move(payloads)) {}
  Status Store(PlaceId detector_place, const BowVector& bow) override;
  Result<BowVector> Fetch(PlaceId detector_place) override;
  void Release(PlaceId detector_place) override;

  void Bind(PlaceId detector_place, PlaceId place);
  PlaceId Bound(PlaceId detector_place) const;  // 0 when unbound
  // Bound places are read from `source` instead of the payloads while it is set (CloseLoop sets
  // it for the length of one call with a PlaceSource; null: the payloads).
  void set_source(PlaceSource* source) { source_ = source; }

 private:
  // No lock of its own: only its stream's detector and CloseLoop use it, under the stream's
  // mutex (AgentStream::ltm is GUARDED_BY it).
  std::shared_ptr<PayloadStore> payloads_;
  PlaceSource* source_ = nullptr;
  std::vector<PlaceId> bound_;  // detector place -> database place
  std::unordered_map<PlaceId, BowVector> unbound_;
};

struct AgentStream {
  Mutex mutex;  // held while a stage of this stream runs
  std::optional<DepthStreamFilter> depth GUARDED_BY(mutex);
  // Algorithm 1's latest decision (for queries)
  std::optional<DepthFrameState> last_depth GUARDED_BY(mutex);
  std::unique_ptr<LoopClosureDetector> loop GUARDED_BY(mutex);
  std::shared_ptr<PayloadLongTermMemory> ltm GUARDED_BY(mutex);
};

class AgentStreams {
 public:
  // The stream of `agent_id`, created on first use.
  std::shared_ptr<AgentStream> Get(const std::string& agent_id);
  std::shared_ptr<AgentStream> Find(const std::string& agent_id) const;  // null when absent
  bool Erase(const std::string& agent_id);
  std::vector<std::shared_ptr<AgentStream>> All() const;

 private:
  mutable Mutex mutex_;
  std::unordered_map<std::string, std::shared_ptr<AgentStream>> streams_ GUARDED_BY(mutex_);
};

}  // namespace placedb
