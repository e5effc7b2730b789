#include "client/progress.h"

#include <algorithm>

#include "client/format.h"

namespace placedb::client {

Progress::Progress(std::ostream& err, bool tty, std::optional<size_t> total, double line_interval_s,
                   Unit unit)
    : err_(err), tty_(tty), total_(total), line_interval_s_(line_interval_s), unit_(unit) {
  thread_ = std::thread([this] { Loop(); });
}

Progress::~Progress() {
  Stop();
}

std::string Progress::Amount(size_t n) const {
  return unit_ == Unit::kBytes ? FormatBytes(n) : std::to_string(n) + " frames";
}

std::string Progress::Rate(double per_second) const {
  return unit_ == Unit::kBytes ? FormatBytes(uint64_t(per_second)) + "/s"
                               : FormatDouble(per_second, 1) + " frames/s";
}

std::string Progress::Render(bool final) const {
  const size_t done = done_.load(std::memory_order_relaxed);
  const double elapsed = std::chrono::duration<double>(Clock::now() - start_).count();
  const double rate = elapsed > 0 ? double(done) / elapsed : 0;
  std::string text;
  if (total_ && *total_ > 0) {
    const double fraction = std::min(1.0, double(done) / double(*total_));
    if (tty_) {
      const int width = 24;
      const int filled = int(fraction * width);
      text.push_back('[');
      text.append(size_t(filled), '#');
      text.append(size_t(width - filled), '-');
      text.append("] ");
    }
    text +=
        (unit_ == Unit::kBytes ? FormatBytes(done) + "/" + FormatBytes(*total_)
                               : std::to_string(done) + "/" + std::to_string(*total_) + " frames") +
        " (" + FormatDouble(fraction * 100, 0) + "%), " + Rate(rate);
    if (!final && rate > 0 && done < *total_) {
      text += ", ETA " + FormatDuration(double(*total_ - done) / rate);
    }
  } else {
    text += Amount(done) + ", " + Rate(rate);
  }
  text += ", " + FormatDuration(elapsed) + " elapsed";
  return text;
}

void Progress::Loop() {
  MutexLock lock(mutex_);
  const auto interval =
      tty_ ? std::chrono::duration<double>(0.1) : std::chrono::duration<double>(line_interval_s_);
  while (!stopped_) {
    wake_.WaitFor(mutex_, interval);
    if (stopped_) break;
    const std::string text = Render(false);
    if (tty_) {
      err_ << '\r' << text
           << std::string(drawn_width_ > text.size() ? drawn_width_ - text.size() : 0, ' ')
           << std::flush;
      drawn_width_ = text.size();
    } else {
      err_ << "progress: " << text << '\n' << std::flush;
    }
  }
}

void Progress::Message(const std::string& line) {
  MutexLock lock(mutex_);
  if (tty_ && drawn_width_ > 0) {
    err_ << '\r' << std::string(drawn_width_, ' ') << '\r';
    drawn_width_ = 0;
  }
  err_ << line << '\n' << std::flush;
}

void Progress::Stop() {
  {
    MutexLock lock(mutex_);
    if (stopped_) return;
    stopped_ = true;
  }
  wake_.NotifyAll();
  thread_.join();
  MutexLock lock(mutex_);
  const std::string text = Render(true);
  if (tty_) {
    err_ << '\r' << text
         << std::string(drawn_width_ > text.size() ? drawn_width_ - text.size() : 0, ' ') << '\n';
  } else {
    err_ << "progress: " << text << '\n';
  }
  err_ << std::flush;
}

}  // namespace placedb::client
