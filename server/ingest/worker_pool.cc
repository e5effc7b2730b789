#include "server/ingest/worker_pool.h"

#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <exception>

namespace placedb::server {

WorkerPool::WorkerPool(int threads, size_t capacity, std::function<void(size_t)> on_depth, int nice)
    : threads_(std::max(threads, 1)),
      capacity_(std::max<size_t>(capacity, 1)),
      nice_(nice),
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
    MutexLock lock(mutex_);
    while (!stopping_ && queue_.size() >= capacity_) {
      const auto now = Clock::now();
      if (now >= until) return SubmitResult::kFull;
      if (give_up && give_up()) return SubmitResult::kGaveUp;
      has_room_.WaitUntil(mutex_, std::min(until, now + kPoll));
    }
    if (stopping_) return SubmitResult::kStopped;
    queue_.push_back(std::move(task));
    // Under the lock, so reports of the depth arrive in the order the depth changed.
    if (on_depth_) on_depth_(queue_.size());
  }
  has_task_.NotifyOne();
  return SubmitResult::kQueued;
}

void WorkerPool::Run() {
  // On Linux a thread's nice value is its own (PRIO_PROCESS with the thread id).
  if (nice_ > 0) (void)setpriority(PRIO_PROCESS, id_t(gettid()), nice_);
  while (true) {
    Task task;
    {
      MutexLock lock(mutex_);
      while (!stopping_ && queue_.empty()) has_task_.Wait(mutex_);
      if (queue_.empty()) return;  // stopping and drained
      task = std::move(queue_.front());
      queue_.pop_front();
      if (on_depth_) on_depth_(queue_.size());
    }
    has_room_.NotifyOne();
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
    MutexLock lock(mutex_);
    stopping_ = true;
  }
  has_task_.NotifyAll();
  has_room_.NotifyAll();
  MutexLock join_lock(join_mutex_);
  for (auto& worker : workers_) {
    if (worker.joinable()) worker.join();
  }
  workers_.clear();
}

size_t WorkerPool::queue_depth() const {
  MutexLock lock(mutex_);
  return queue_.size();
}

}  // namespace placedb::server
