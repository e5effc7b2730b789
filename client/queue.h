// A bounded blocking queue between a producer (frame reader) and an agent's stream writer.
#pragma once

#include <deque>
#include <optional>

#include "core/base/thread_annotations.h"

namespace placedb::client {

template <typename T>
class BoundedQueue {
 public:
  explicit BoundedQueue(size_t capacity) : capacity_(capacity == 0 ? 1 : capacity) {}

  // Blocks while full. False when the queue was aborted (the item is dropped).
  bool Push(T item) {
    MutexLock lock(mutex_);
    while (items_.size() >= capacity_ && !aborted_) changed_.Wait(mutex_);
    if (aborted_) return false;
    items_.push_back(std::move(item));
    changed_.NotifyAll();
    return true;
  }

  // Blocks while empty; nullopt once finished and drained, or aborted.
  std::optional<T> Pop() {
    MutexLock lock(mutex_);
    while (items_.empty() && !finished_ && !aborted_) changed_.Wait(mutex_);
    if (aborted_ || items_.empty()) return std::nullopt;
    T item = std::move(items_.front());
    items_.pop_front();
    changed_.NotifyAll();
    return item;
  }

  // No more pushes: Pop drains what is left, then returns nullopt.
  void Finish() {
    MutexLock lock(mutex_);
    finished_ = true;
    changed_.NotifyAll();
  }

  // The consumer is gone: pushes fail, pops return nullopt, queued items are dropped. Returns how
  // many were dropped.
  size_t Abort() {
    MutexLock lock(mutex_);
    aborted_ = true;
    const size_t dropped = items_.size();
    items_.clear();
    changed_.NotifyAll();
    return dropped;
  }

 private:
  const size_t capacity_;
  Mutex mutex_;
  CondVar changed_;
  std::deque<T> items_ GUARDED_BY(mutex_);
  bool finished_ GUARDED_BY(mutex_) = false;
  bool aborted_ GUARDED_BY(mutex_) = false;
};

}  // namespace placedb::client
