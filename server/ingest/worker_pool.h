// A fixed set of worker threads behind a bounded queue: the server's frame pipeline runs here
// (decode, detect, extract, filter, transform, search, verify, store), so CPU use is bounded by
// the thread count whatever the number of open calls, and memory by the queue capacity.
//
// Submit() blocks while the queue is full: that is the backpressure of Ingest streams (the
// stream's handler does not read its next message until its current one is queued). Callers that
// must not wait forever pass a deadline and a give-up predicate (e.g. "call cancelled").
#pragma once

#include <chrono>
#include <cstddef>
#include <deque>
#include <functional>
#include <thread>
#include <vector>

#include "core/base/thread_annotations.h"

namespace placedb::server {

class WorkerPool {
 public:
  using Clock = std::chrono::steady_clock;
  using Task = std::function<void()>;

  enum class SubmitResult { kQueued, kFull, kGaveUp, kStopped };

  // `threads` >= 1 workers, at most `capacity` >= 1 tasks waiting (running ones not counted).
  // `on_depth` (optional) is told the number of waiting tasks whenever it changes, in order; it
  // runs under the pool's lock, so it must be cheap and must not call back into the pool.
  // `nice` > 0: every worker lowers its own CPU priority by that much at start (setpriority on
  // the thread, Linux; never raised back, so no privilege is needed), e.g. ingest workers beside a
  // query pool at the normal priority. A refusal is ignored (the workers run at the normal one).
  WorkerPool(int threads, size_t capacity, std::function<void(size_t)> on_depth = {}, int nice = 0);
  ~WorkerPool();  // Stop()
  WorkerPool(const WorkerPool&) = delete;
  WorkerPool& operator=(const WorkerPool&) = delete;

  // Queues `task`, waiting for room until `until`; `give_up` is polled every few milliseconds
  // while waiting. kFull when `until` passed first, kGaveUp when `give_up` said so, kStopped
  // after Stop(). The task is dropped unless kQueued.
  SubmitResult Submit(Task task, Clock::time_point until = Clock::time_point::max(),
                      const std::function<bool()>& give_up = {});
  SubmitResult TrySubmit(Task task) { return Submit(std::move(task), Clock::time_point::min()); }

  // Refuses new tasks, runs every queued one, joins the workers. Idempotent.
  void Stop();

  size_t queue_depth() const;
  size_t capacity() const { return capacity_; }
  int threads() const { return threads_; }

 private:
  void Run() EXCLUDES(mutex_);

  const int threads_;
  const size_t capacity_;
  const int nice_;
  const std::function<void(size_t)> on_depth_;
  mutable Mutex mutex_;
  CondVar has_task_;
  CondVar has_room_;
  std::deque<Task> queue_ GUARDED_BY(mutex_);
  bool stopping_ GUARDED_BY(mutex_) = false;
  Mutex join_mutex_;  // one Stop() joins, concurrent ones wait for it
  std::vector<std::thread> workers_ GUARDED_BY(join_mutex_);
};

}  // namespace placedb::server
