#include "core/pipeline/agent_streams.h"

#include "core/pipeline/place_database.h"

namespace placedb {

Status PayloadLongTermMemory::Store(PlaceId detector_place, const BowVector& bow) {
  if (Bound(detector_place) != 0) return Status::Ok();  // its payload holds the vector already
  unbound_[detector_place] = bow;
  return Status::Ok();
}

Result<BowVector> PayloadLongTermMemory::Fetch(PlaceId detector_place) {
  if (auto it = unbound_.find(detector_place); it != unbound_.end()) return it->second;
  const PlaceId place = Bound(detector_place);
  if (place == 0) {
    return Status::NotFound("loop-closure place " + std::to_string(detector_place) +
                            " has no stored vector");
  }
  auto bow = source_ ? source_->GetBow(place) : payloads_->GetBow(place);
  if (!bow.ok()) return bow.status().WithContext("retrieving place " + std::to_string(place));
  return bow;
}

void PayloadLongTermMemory::Release(PlaceId detector_place) {
  unbound_.erase(detector_place);
}

void PayloadLongTermMemory::Bind(PlaceId detector_place, PlaceId place) {
  if (bound_.size() <= detector_place) bound_.resize(size_t(detector_place) + 1, 0);
  bound_[detector_place] = place;
}

PlaceId PayloadLongTermMemory::Bound(PlaceId detector_place) const {
  return detector_place < bound_.size() ? bound_[detector_place] : 0;
}

std::shared_ptr<AgentStream> AgentStreams::Get(const std::string& agent_id) {
  MutexLock lock(mutex_);
  auto& stream = streams_[agent_id];
  if (!stream) stream = std::make_shared<AgentStream>();
  return stream;
}

std::shared_ptr<AgentStream> AgentStreams::Find(const std::string& agent_id) const {
  MutexLock lock(mutex_);
  auto it = streams_.find(agent_id);
  return it == streams_.end() ? nullptr : it->second;
}

bool AgentStreams::Erase(const std::string& agent_id) {
  MutexLock lock(mutex_);
  return streams_.erase(agent_id) > 0;
}

std::vector<std::shared_ptr<AgentStream>> AgentStreams::All() const {
  MutexLock lock(mutex_);
  std::vector<std::shared_ptr<AgentStream>> all;
  all.reserve(streams_.size());
  for (const auto& [agent, stream] : streams_) all.push_back(stream);
  return all;
}

}  // namespace placedb
