#include "server/rpc/agent_activity.h"

#include <algorithm>

namespace placedb::server {

namespace {

int64_t SecondOf(AgentActivity::Clock::time_point now) {
  return std::chrono::duration_cast<std::chrono::seconds>(now.time_since_epoch()).count();
}

}  // namespace

AgentActivity::AgentActivity(size_t max_agents_per_map)
    : max_agents_per_map_(std::max<size_t>(1, max_agents_per_map)) {}

void AgentActivity::Record(const std::string& map, const std::string& agent, FrameOutcome outcome,
                           uint32_t place_id, Clock::time_point now, int64_t unix_ms) {
  const int64_t second = SecondOf(now);
  MutexLock lock(mutex_);
  std::map<std::string, Agent>& agents = maps_[map];
  auto it = agents.find(agent);
  if (it == agents.end()) {
    if (agents.size() >= max_agents_per_map_) {
      // The agent whose last frame is oldest makes room.
      auto oldest =
          std::min_element(agents.begin(), agents.end(), [](const auto& a, const auto& b) {
            return a.second.totals.last_frame_unix_ms < b.second.totals.last_frame_unix_ms;
          });
      agents.erase(oldest);
    }
    it = agents.emplace(agent, Agent{}).first;
    it->second.totals.agent_id = agent;
  }
  Agent& entry = it->second;
  ++entry.totals.frames;
  if (outcome == FrameOutcome::kStored) ++entry.totals.places;
  if (place_id != 0) entry.totals.last_place_id = place_id;
  entry.totals.last_frame_unix_ms = unix_ms;
  const size_t bucket = size_t(((second % kWindowSeconds) + kWindowSeconds) % kWindowSeconds);
  if (entry.second[bucket] != second) {
    entry.second[bucket] = second;
    entry.count[bucket] = 0;
  }
  ++entry.count[bucket];
}

std::vector<AgentActivitySnapshot> AgentActivity::Of(const std::string& map,
                                                     Clock::time_point now) const {
  const int64_t second = SecondOf(now);
  std::vector<AgentActivitySnapshot> out;
  MutexLock lock(mutex_);
  auto found = maps_.find(map);
  if (found == maps_.end()) return out;
  out.reserve(found->second.size());
  for (const auto& [id, agent] : found->second) {
    AgentActivitySnapshot snapshot = agent.totals;
    uint64_t recent = 0;
    for (int i = 0; i < kWindowSeconds; ++i) {
      if (second - agent.second[i] < kWindowSeconds) recent += agent.count[i];
    }
    snapshot.frames_per_second = double(recent) / kWindowSeconds;
    out.push_back(std::move(snapshot));
  }
  return out;
}

void AgentActivity::Forget(const std::string& map) {
  MutexLock lock(mutex_);
  maps_.erase(map);
}

}  // namespace placedb::server
