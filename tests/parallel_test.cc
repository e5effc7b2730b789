#include "core/base/parallel.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <set>
#include <stdexcept>
#include <thread>
#include <vector>

namespace placedb {
namespace {

TEST(ParallelFor, RunsEveryTaskOnce) {
  for (int threads : {-1, 0, 1, 2, 4, 16}) {
    for (size_t tasks : {size_t{0}, size_t{1}, size_t{3}, size_t{1000}}) {
      std::vector<std::atomic<int>> runs(tasks);
      ParallelFor(tasks, threads, [&](size_t task, int) { ++runs[task]; });
      for (size_t t = 0; t < tasks; ++t) {
        EXPECT_EQ(runs[t].load(), 1) << "task " << t << ", " << threads << " threads";
      }
    }
  }
}

TEST(ParallelFor, WorkersAreNumberedFromTheCaller) {
  const std::thread::id caller = std::this_thread::get_id();
  std::mutex mutex;
  std::set<int> workers;
  std::atomic<bool> caller_is_zero{true};
  // More tasks than threads, each slow enough that every worker gets some.
  ParallelFor(64, 4, [&](size_t, int worker) {
    if ((std::this_thread::get_id() == caller) != (worker == 0)) caller_is_zero = false;
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
    std::lock_guard lock(mutex);
    workers.insert(worker);
  });
  EXPECT_TRUE(caller_is_zero);
  ASSERT_FALSE(workers.empty());
  EXPECT_GE(*workers.begin(), 0);
  EXPECT_LE(*workers.rbegin(), 3);
  // Fewer tasks than threads: no more workers than tasks.
  std::set<int> few;
  ParallelFor(2, 8, [&](size_t, int worker) {
    std::lock_guard lock(mutex);
    few.insert(worker);
  });
  EXPECT_LE(*few.rbegin(), 1);
}

TEST(ParallelFor, RethrowsTheTasksExceptionOnTheCaller) {
  for (int threads : {1, 4}) {
    std::atomic<int> started{0};
    // Tasks slow enough that all 2000 would take far longer than stopping does.
    EXPECT_THROW(ParallelFor(2000, threads,
                             [&](size_t task, int) {
                               ++started;
                               if (task == 5) throw std::out_of_range("task 5");
                               std::this_thread::sleep_for(std::chrono::microseconds(200));
                             }),
                 std::out_of_range);
    EXPECT_LT(started.load(), 2000) << "tasks kept being handed out after the failure";
  }
}

}  // namespace
}  // namespace placedb
