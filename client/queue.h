// A bounded blocking queue between a producer (frame reader) and an agent's stream writer.
#pragma once

#include <condition_variable>
#include <deque>
#include <mutex>
#include <optional>

namespace placedb::client {

template <typename T>
class BoundedQueue {
 public:
  explicit BoundedQueue(size_t capacity) : capacity_(capacity == 0 ? 1 : capacity) {}

  // Blocks while full. False when the queue was aborted (the item is dropped).
  bool Push(T item) {
    std::unique_lock lock(mutex_);
    changed_.wait(lock, [&] { return items_.size() < capacity_ || aborted_; });
    if (aborted_) return false;
    items_.push_back(std::move(item));
    changed_.notify_all();
    return true;
  }

  // Blocks while empty; nullopt once finished and drained, or aborted.
  std::optional<T> Pop() {
    std::unique_lock lock(mutex_);
    changed_.wait(lock, [&] { return !items_.empty() || finished_ || aborted_; });
    if (aborted_ || items_.empty()) return std::nullopt;
    T item = std::move(items_.front());
    items_.pop_front();
    changed_.notify_all();
    return item;
  }

  // No more pushes: Pop drains what is left, then returns nullopt.
  void Finish() {
    std::lock_guard lock(mutex_);
    finished_ = true;
    changed_.notify_all();
  }

  // The consumer is gone: pushes fail, pops return nullopt, queued items are dropped. Returns how
  // many were dropped.
  size_t Abort() {
    std::lock_guard lock(mutex_);
    aborted_ = true;
    const size_t dropped = items_.size();
    items_.clear();
    changed_.notify_all();
    return dropped;
  }

 private:
  const size_t capacity_;
  std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<T> items_;
  bool finished_ = false;
  bool aborted_ = false;
};

}  // namespace placedb::client
