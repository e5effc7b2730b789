// Progress on stderr: a redrawn bar with rate and ETA on a terminal, a line every few seconds
// otherwise (logs, CI).
#pragma once

#include <atomic>
#include <optional>
#include <ostream>
#include <string>
#include <thread>

#include "client/connection.h"
#include "core/base/thread_annotations.h"

namespace placedb::client {

class Progress {
 public:
  enum class Unit { kFrames, kBytes };  // what Add() counts ("12 frames", "1.5 MiB")
  // `total` (in `unit`) enables the percentage and the ETA.
  Progress(std::ostream& err, bool tty, std::optional<size_t> total, double line_interval_s = 2.0,
           Unit unit = Unit::kFrames);
  ~Progress();

  void Add(size_t n = 1) { done_.fetch_add(n, std::memory_order_relaxed); }
  // Prints a line (a warning) without garbling the bar.
  void Message(const std::string& line);
  // Final update; idempotent.
  void Stop();

 private:
  void Loop() EXCLUDES(mutex_);
  std::string Render(bool final) const;
  std::string Amount(size_t n) const;  // "12 frames", "1.5 MiB"
  std::string Rate(double per_second) const;

  std::ostream& err_ GUARDED_BY(mutex_);
  const bool tty_;
  const std::optional<size_t> total_;
  const double line_interval_s_;
  const Unit unit_;
  const Clock::time_point start_ = Clock::now();
  std::atomic<size_t> done_{0};  // atomic: Add() takes no lock
  Mutex mutex_;
  CondVar wake_;
  bool stopped_ GUARDED_BY(mutex_) = false;
  size_t drawn_width_ GUARDED_BY(mutex_) = 0;
  std::thread thread_;
};

}  // namespace placedb::client
