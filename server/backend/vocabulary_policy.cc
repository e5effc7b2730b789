#include "server/backend/vocabulary_policy.h"

#include <spdlog/spdlog.h>

#include "core/base/text.h"

namespace placedb::server {

bool PolicyWantsAdaptation(const ServiceMapSettings& settings, const VocabularyRecord& record,
                           uint64_t descriptors, uint64_t last_attempt) {
  if (last_attempt > 0 && descriptors < last_attempt + last_attempt / 10) return false;
  if (record.generation == 0) {
    return settings.adapt_after_descriptors > 0 && descriptors >= settings.adapt_after_descriptors;
  }
  if (record.current.origin != "learned" || settings.regrow_factor <= 1) return false;
  return double(descriptors) >= settings.regrow_factor * double(record.current.descriptors_offered);
}

VocabularyPolicyRunner::VocabularyPolicyRunner(MapRegistry* maps,
                                               std::chrono::milliseconds interval)
    : maps_(maps), interval_(interval) {}

VocabularyPolicyRunner::~VocabularyPolicyRunner() {
  Stop();
}

void VocabularyPolicyRunner::Start() {
  thread_ = std::thread([this] { Run(); });
}

void VocabularyPolicyRunner::Stop() {
  stopping_ = true;
  {
    MutexLock lock(mutex_);
    stop_ = true;
  }
  wake_.NotifyAll();
  if (thread_.joinable()) thread_.join();
}

void VocabularyPolicyRunner::Run() {
  while (true) {
    {
      MutexLock lock(mutex_);
      const auto until = std::chrono::steady_clock::now() + interval_;
      while (!stop_ && std::chrono::steady_clock::now() < until) wake_.WaitUntil(mutex_, until);
      if (stop_) return;
    }
    CheckMaps();
  }
}

void VocabularyPolicyRunner::CheckMaps() {
  for (const auto& entry : maps_->List()) {
    if (stopping_.load()) return;
    if (!entry->map) continue;
    const ServiceMapSettings& settings = entry->settings;
    if (settings.adapt_after_descriptors == 0 && settings.regrow_factor <= 1) continue;
    const uint64_t descriptors = entry->map->database()->Stats().descriptors_kept;
    const VocabularyRecord record = entry->map->info().vocabulary;
    const auto failed = failed_at_.find(entry->name);
    if (!PolicyWantsAdaptation(settings, record, descriptors,
                               failed == failed_at_.end() ? 0 : failed->second)) {
      continue;
    }
    spdlog::info("map '{}': its vocabulary policy learns a vocabulary ({} static descriptors)",
                 ForLog(entry->name), descriptors);
    AdaptOptions options;
    options.cancel = &stopping_;
    auto switched = entry->map->AdaptVocabulary(options);
    if (!switched.ok()) {
      if (switched.status().code() != StatusCode::kCancelled) failed_at_[entry->name] = descriptors;
      spdlog::warn("map '{}': its vocabulary policy could not switch: {}", ForLog(entry->name),
                   switched.status().ToString());
      continue;
    }
    failed_at_.erase(entry->name);
    maps_->VocabularySwitched(entry->name);
    spdlog::info(
        "map '{}' switched by its vocabulary policy to learned vocabulary {} (k={} L={}, from {} "
        "descriptors of {} places) in {:.1f} s (generation {})",
        ForLog(entry->name), Hex64(switched->current.checksum), switched->current.branching,
        switched->current.depth, switched->current.descriptors_sampled,
        switched->current.places_sampled,
        (switched->current.learn_ms + switched->reindex_ms) / 1000, switched->generation);
  }
}

}  // namespace placedb::server
