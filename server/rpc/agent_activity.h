// What each agent did to each map since the server started (issue 20's live console): frames
// answered, places stored, the recent ingest rate, the last place and frame time. In memory
// only, never persisted: a restart starts from zero.
//
// Bounded: at most `max_agents_per_map` agents per map; a new agent beyond that evicts the agent
// whose last frame is oldest. Maps are forgotten when deleted (Forget()), so memory is
// O(maps x max_agents_per_map), about 200 bytes per agent.
//
// The rate is frames answered in the last 10 s divided by 10: ten one-second buckets per agent
// (by the steady clock's whole seconds), so a frame leaves the window 9-10 s after it came. An
// agent that stopped reads 0 once its last frame is out of the window.
//
// Thread safety: every method may be called concurrently (one mutex; Record is a few
// arithmetic operations under it).
#pragma once

#include <array>
#include <chrono>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "core/base/thread_annotations.h"

namespace placedb::server {

// How an ingested frame was answered.
enum class FrameOutcome {
  kStored,   // a new place
  kMerged,   // loop closure merged it into an existing place
  kInvalid,  // too little static structure: not stored
  kRefused,  // an error answer (bad input, over a limit, cancelled, storage error)
};

struct AgentActivitySnapshot {
  std::string agent_id;
  uint64_t frames = 0;  // answered, whatever the outcome
  uint64_t places = 0;  // stored as new places
  double frames_per_second = 0;
  uint32_t last_place_id = 0;  // the last stored or merged-into place; 0 = none yet
  int64_t last_frame_unix_ms = 0;
};

class AgentActivity {
 public:
  using Clock = std::chrono::steady_clock;
  static constexpr int kWindowSeconds = 10;

  explicit AgentActivity(size_t max_agents_per_map = 64);

  // Counts one answered frame of `agent` on `map`. `place_id`: the place stored or merged into
  // (0 otherwise). `now` drives the rate; `unix_ms` is reported as the last frame's time.
  void Record(const std::string& map, const std::string& agent, FrameOutcome outcome,
              uint32_t place_id, Clock::time_point now, int64_t unix_ms) EXCLUDES(mutex_);
  // The map's agents, by agent id; empty for a map with none. Changes nothing.
  std::vector<AgentActivitySnapshot> Of(const std::string& map, Clock::time_point now) const
      EXCLUDES(mutex_);
  // Drops the map's agents (the map was deleted).
  void Forget(const std::string& map) EXCLUDES(mutex_);

 private:
  struct Agent {
    AgentActivitySnapshot totals;                  // frames_per_second unused here
    std::array<int64_t, kWindowSeconds> second{};  // the steady second each bucket counts
    std::array<uint32_t, kWindowSeconds> count{};
  };
  const size_t max_agents_per_map_;
  mutable Mutex mutex_;
  std::map<std::string, std::map<std::string, Agent>> maps_ GUARDED_BY(mutex_);
};

}  // namespace placedb::server
