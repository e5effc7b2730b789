#include "server/ingest/memory_budget.h"

#include <utility>

namespace placedb::server {

namespace {

constexpr auto kPoll = std::chrono::milliseconds(50);

std::string Mib(uint64_t bytes) {
  // Rounded up, so a non-empty charge never reads as 0 MiB.
  return std::to_string((bytes + (uint64_t(1) << 20) - 1) >> 20) + " MiB";
}

}  // namespace

MemoryBudget::MemoryBudget(uint64_t limit_bytes, std::string name)
    : limit_(limit_bytes), name_(std::move(name)) {}

// ---- Reservation --------------------------------------------------------------------------------

MemoryBudget::Reservation::Reservation(Reservation&& other) noexcept
    : budget_(std::exchange(other.budget_, nullptr)), bytes_(std::exchange(other.bytes_, 0)) {}

MemoryBudget::Reservation& MemoryBudget::Reservation::operator=(Reservation&& other) noexcept {
  if (this != &other) {
    Release();
    budget_ = std::exchange(other.budget_, nullptr);
    bytes_ = std::exchange(other.bytes_, 0);
  }
  return *this;
}

bool MemoryBudget::Reservation::TryResize(uint64_t bytes) {
  return Resize(bytes, Clock::time_point::min());
}

bool MemoryBudget::Reservation::Resize(uint64_t bytes, Clock::time_point until,
                                       const std::function<bool()>& give_up) {
  if (!budget_) return bytes == 0;
  if (bytes <= bytes_) {
    const uint64_t freed = bytes_ - bytes;
    bytes_ = bytes;
    if (freed > 0) budget_->Give(freed, /*last=*/false);
    return true;
  }
  const uint64_t more = bytes - bytes_;
  MutexLock lock(budget_->mutex_);
  if (!budget_->WaitToFitLocked(more, until, give_up, /*growth=*/true)) return false;
  budget_->in_use_ += more;
  bytes_ = bytes;
  return true;
}

void MemoryBudget::Reservation::Release() {
  if (!budget_) return;
  budget_->Give(bytes_, /*last=*/true);
  budget_ = nullptr;
  bytes_ = 0;
}

// ---- MemoryBudget -------------------------------------------------------------------------------

Status MemoryBudget::ReserveFixed(const std::string& what, uint64_t bytes) {
  MutexLock lock(mutex_);
  if (!FitsLocked(bytes)) {
    return Status::ResourceExhausted(name_ + " = " + std::to_string(limit_) +
                                     " is too small: " + what + " alone takes " + Mib(bytes) +
                                     " and " + Mib(in_use_) + " is already fixed");
  }
  in_use_ += bytes;
  fixed_ += bytes;
  return Status::Ok();
}

Result<MemoryBudget::Reservation> MemoryBudget::TryReserve(uint64_t bytes,
                                                           const std::string& what) {
  return Reserve(bytes, what, Clock::time_point::min());
}

Result<MemoryBudget::Reservation> MemoryBudget::Reserve(uint64_t bytes, const std::string& what,
                                                        Clock::time_point until,
                                                        const std::function<bool()>& give_up,
                                                        uint64_t keep_free) {
  MutexLock lock(mutex_);
  if (!WaitToFitLocked(bytes, until, give_up, /*growth=*/false, keep_free)) {
    return ExhaustedLocked(bytes, what);
  }
  in_use_ += bytes;
  ++reservations_;
  return Reservation(this, bytes);
}

bool MemoryBudget::WaitToFitLocked(uint64_t more, Clock::time_point until,
                                   const std::function<bool()>& give_up, bool growth,
                                   uint64_t keep_free) {
  // Bytes beyond what the fixed charges leave can never be granted: no point waiting.
  if (more + keep_free > limit_ - fixed_) return false;
  if (GrantableLocked(more, growth, keep_free)) return true;
  if (growth) ++growing_;
  bool granted = true;
  while (!GrantableLocked(more, growth, keep_free)) {
    const auto now = Clock::now();
    bool giving_up = now >= until;
    if (!giving_up && give_up) {
      // Outside the lock: `give_up` may take the caller's locks, which may be held around a
      // release.
      mutex_.Unlock();
      giving_up = give_up();
      mutex_.Lock();
      if (GrantableLocked(more, growth, keep_free)) break;
    }
    if (giving_up) {
      granted = false;
      break;
    }
    // Releases notify; `give_up` has no wake-up hook, so it is polled.
    released_.WaitUntil(mutex_, std::min(until, now + kPoll));
  }
  if (growth && --growing_ == 0) released_.NotifyAll();  // new reservations may go again
  return granted;
}

void MemoryBudget::Give(uint64_t bytes, bool last) {
  MutexLock lock(mutex_);
  in_use_ -= bytes;
  if (last) --reservations_;
  if (bytes > 0) released_.NotifyAll();
}

Status MemoryBudget::Exhausted(uint64_t bytes, const std::string& what) const {
  MutexLock lock(mutex_);
  return ExhaustedLocked(bytes, what);
}

Status MemoryBudget::ExhaustedLocked(uint64_t bytes, const std::string& what) const {
  std::string message = "memory budget exhausted: " + name_ + " = " + std::to_string(limit_) +
                        ", " + Mib(in_use_) + " in use (" + Mib(fixed_) + " fixed, " +
                        Mib(in_use_ - fixed_) + " by " + std::to_string(reservations_) +
                        " requests in flight); " + what + " needs " + Mib(bytes);
  if (bytes > limit_ - fixed_) {
    return Status::ResourceExhausted(message + ", more than the budget can ever grant (" +
                                     Mib(limit_ - fixed_) + " beyond its fixed part)");
  }
  return Status::ResourceExhausted(message + "; retry later");
}

uint64_t MemoryBudget::in_use() const {
  MutexLock lock(mutex_);
  return in_use_;
}

uint64_t MemoryBudget::fixed() const {
  MutexLock lock(mutex_);
  return fixed_;
}

size_t MemoryBudget::reservations() const {
  MutexLock lock(mutex_);
  return reservations_;
}

}  // namespace placedb::server
