// The per-map vocabulary policy (MapConfig.vocabulary_policy, issue 29): maps that learn their own
// vocabulary by themselves as they grow. One background thread checks every map at an interval
// and switches those the policy says are due, one at a time, with PlaceMap::AdaptVocabulary at
// its defaults (a lowered priority, one thread: queries and ingest go on).
//
// Thread safety: Start and Stop from one thread (the server's start and shutdown); the thread
// reads the registry, which is thread-safe.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <string>
#include <thread>
#include <unordered_map>

#include "core/base/thread_annotations.h"
#include "core/storage/map_store.h"
#include "proto/convert_config.h"
#include "server/backend/map_registry.h"

namespace placedb::server {

// Whether `settings`' policy wants a map holding `descriptors` static descriptors, with
// vocabulary `record`, to learn one now: created with a file's vocabulary and never switched
// (an operator's revert is respected) at adapt_after_descriptors; learned, at regrow_factor times
// what it was learned from. `last_attempt`: the descriptors when an attempt last failed (0 =
// none): a failed map is tried again only once it has grown by a tenth.
bool PolicyWantsAdaptation(const ServiceMapSettings& settings, const VocabularyRecord& record,
                           uint64_t descriptors, uint64_t last_attempt);

class VocabularyPolicyRunner {
 public:
  VocabularyPolicyRunner(MapRegistry* maps, std::chrono::milliseconds interval);
  ~VocabularyPolicyRunner();  // Stop()
  VocabularyPolicyRunner(const VocabularyPolicyRunner&) = delete;
  VocabularyPolicyRunner& operator=(const VocabularyPolicyRunner&) = delete;

  void Start();
  // Cancels a switch in progress (the map keeps its vocabulary) and joins the thread.
  void Stop() EXCLUDES(mutex_);

 private:
  void Run() EXCLUDES(mutex_);
  void CheckMaps();  // on the thread

  MapRegistry* const maps_;
  const std::chrono::milliseconds interval_;
  std::atomic<bool> stopping_{false};  // also the running switch's cancel flag
  Mutex mutex_;
  CondVar wake_;
  bool stop_ GUARDED_BY(mutex_) = false;
  std::thread thread_;
  // The thread's own: descriptors at each map's last failed attempt.
  std::unordered_map<std::string, uint64_t> failed_at_;
};

}  // namespace placedb::server
