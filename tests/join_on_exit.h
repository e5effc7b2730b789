// JoinOnExit: a test's threads joined when its scope ends, so that a failed assertion fails the
// test instead of aborting the binary. Header-only, no dependencies: for every test target.
#pragma once

#include <functional>
#include <thread>
#include <utility>
#include <vector>

namespace placedb::testing {

// Joins a test's threads when its scope ends, after running `stop` (which sets whatever the
// threads watch to end early): an assertion that returns while they run then fails the test
// cleanly, where a joinable std::thread's destructor would std::terminate the whole binary.
class JoinOnExit {
 public:
  explicit JoinOnExit(std::function<void()> stop = [] {}) : stop_(std::move(stop)) {}
  ~JoinOnExit() { JoinAll(); }
  JoinOnExit(const JoinOnExit&) = delete;
  JoinOnExit& operator=(const JoinOnExit&) = delete;

  void Add(std::thread& thread) { threads_.push_back(&thread); }
  // The threads `threads` holds when the scope ends (it may still grow).
  void Add(std::vector<std::thread>& threads) { groups_.push_back(&threads); }
  // `stop`, then joins every thread not joined yet (also what the destructor does).
  void JoinAll() {
    stop_();
    for (std::vector<std::thread>* group : groups_) {
      for (std::thread& thread : *group) {
        if (thread.joinable()) thread.join();
      }
    }
    for (std::thread* thread : threads_) {
      if (thread->joinable()) thread->join();
    }
  }

 private:
  std::function<void()> stop_;
  std::vector<std::thread*> threads_;
  std::vector<std::vector<std::thread>*> groups_;
};

}  // namespace placedb::testing
