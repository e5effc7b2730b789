#include "server/worker_pool.h"

#include <algorithm>
#include <cstdio>
#include <exception>

namespace placedb::server {

WorkerPool::WorkerPool(int threads, size_t capacity, std::function<void(size_t)> on_depth)
    : threads_(std::max(threads, 1)),
      capacity_(std::max<size_t>(capacity, 1)),
      on_depth_(std::move(on_depth)) {
  workers_.reserve(size_t(threads_));
  for (int i = 0; i < threads_; ++i) workers_.emplace_back([this] { Run(); });
}

WorkerPool::~WorkerPool() {
  Stop();
}

WorkerPool::SubmitResult WorkerPool::Submit(Task task, Clock::time_point until,
                                            const std::function<bool()>& give_up) {
  // Poll `give_up` at this period while waiting for room (cancellation has no wake-up hook).
  constexpr auto kPoll = std::chrono::milliseconds(20);
  {
    std::unique_lock lock(mutex_);
    while (!stopping_ && queue_.size() >= capacity_) {
      const auto now = Clock::now();
      if (now >= until) return SubmitResult::kFull;
      if (give_up && give_up()) return SubmitResult::kGaveUp;
      has_room_.wait_until(lock, std::min(until, now + kPoll));
    }
    if (stopping_) return SubmitResult::kStopped;
    queue_.push_back(std::move(task));
    // Under the lock, so reports of the depth arrive in the order the depth changed.
    if (on_depth_) on_depth_(queue_.size());
  }
  has_task_.notify_one();
  return SubmitResult::kQueued;
}

void WorkerPool::Run() {
  while (true) {
    Task task;
    {
      std::unique_lock lock(mutex_);
      has_task_.wait(lock, [&] { return stopping_ || !queue_.empty(); });
      if (queue_.empty()) return;  // stopping and drained
      task = std::move(queue_.front());
      queue_.pop_front();
      if (on_depth_) on_depth_(queue_.size());
    }
    has_room_.notify_one();
    try {
      task();  // tasks handle their own errors; this only keeps a worker alive
    } catch (const std::exception& e) {
      std::fprintf(stderr, "placedb worker: task threw: %s\n", e.what());
    } catch (...) {
      std::fprintf(stderr, "placedb worker: task threw\n");
    }
  }
}

void WorkerPool::Stop() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  has_task_.notify_all();
  has_room_.notify_all();
  std::lock_guard join_lock(join_mutex_);
  for (auto& worker : workers_) {
    if (worker.joinable()) worker.join();
  }
  workers_.clear();
}

size_t WorkerPool::queue_depth() const {
  std::lock_guard lock(mutex_);
  return queue_.size();
}

}  // namespace placedb::server
