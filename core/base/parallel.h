// Parallel loops over independent tasks.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <exception>
#include <mutex>
#include <system_error>
#include <thread>
#include <vector>

namespace placedb {

// Runs fn(task, worker) once for every task in [0, tasks), on up to `threads` threads (values
// below 1 mean 1); the calling thread is worker 0 and the others are numbered 1.., so a worker
// index can select per-thread scratch. Tasks are handed out in increasing order as workers free
// up: fn must not depend on which worker runs a task or in what order tasks finish. If the
// system refuses a thread, the remaining workers drain the tasks. The first exception thrown by
// fn stops the handing out of tasks and is rethrown on the caller once every worker has stopped.
template <typename Fn>
void ParallelFor(size_t tasks, int threads, const Fn& fn) {
  const size_t workers = std::min<size_t>(size_t(std::max(threads, 1)), tasks);
  if (workers <= 1) {
    for (size_t task = 0; task < tasks; ++task) fn(task, 0);
    return;
  }
  std::atomic<size_t> next{0};
  std::atomic<bool> failed{false};
  std::exception_ptr error;
  std::mutex error_mutex;
  auto work = [&](int worker) {
    try {
      for (size_t task; !failed.load(std::memory_order_relaxed) &&
                        (task = next.fetch_add(1, std::memory_order_relaxed)) < tasks;) {
        fn(task, worker);
      }
    } catch (...) {
      std::lock_guard lock(error_mutex);
      if (!error) error = std::current_exception();
      failed = true;
    }
  };
  std::vector<std::thread> pool;
  pool.reserve(workers - 1);
  for (size_t w = 1; w < workers; ++w) {
    try {
      pool.emplace_back(work, int(w));
    } catch (const std::system_error&) {
      break;  // fewer threads than asked: the work queue still drains
    }
  }
  work(0);
  for (std::thread& thread : pool) thread.join();
  if (error) std::rethrow_exception(error);
}

}  // namespace placedb
