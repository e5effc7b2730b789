// The server's memory budget (limits.memory_budget_bytes): a byte count that every large,
// request-driven allocation is charged to before it is made, so that a flood of calls is refused
// (RESOURCE_EXHAUSTED naming the budget) or held back instead of growing the process without
// bound. docs/service.md ("Memory budget") explains what is charged and the arithmetic.
//
// Two kinds of charges:
// - fixed: what the server holds whatever the load (its resident size at startup, RocksDB's block
//   cache). Reserved once with ReserveFixed(), never released; they only shrink what is left for
//   requests.
// - reservations: RAII handles for one request's bytes (an Ingest stream's pending read, a
//   frame from the moment it is read until its answer is written, a Query). A reservation can
//   shrink (always) or grow (only if the growth fits) while it lives, and gives its bytes back
//   when destroyed.
//
// The budget never grants more than its limit: in_use() <= limit() at all times (fixed charges
// are checked against the limit at startup). Thread-safe; waiters are woken on every release.
// A reservation waiting to grow (a request already read) goes before new reservations.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <string>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"

namespace placedb::server {

class MemoryBudget {
 public:
  using Clock = std::chrono::steady_clock;

  // `name` is the configuration key refusals name ("limits.memory_budget_bytes").
  explicit MemoryBudget(uint64_t limit_bytes, std::string name = "limits.memory_budget_bytes");
  MemoryBudget(const MemoryBudget&) = delete;
  MemoryBudget& operator=(const MemoryBudget&) = delete;

  // One request's bytes. Move-only; empty (0 bytes, no budget) when default-constructed.
  // Methods of one reservation must not be called concurrently (it belongs to one request).
  class Reservation {
   public:
    Reservation() = default;
    ~Reservation() { Release(); }
    Reservation(Reservation&& other) noexcept;
    Reservation& operator=(Reservation&& other) noexcept;
    Reservation(const Reservation&) = delete;
    Reservation& operator=(const Reservation&) = delete;

    uint64_t bytes() const { return bytes_; }
    explicit operator bool() const { return budget_ != nullptr; }

    // Shrinking always succeeds; growing succeeds only if the difference fits now. False (and
    // nothing changed) otherwise. On an empty reservation: false unless `bytes` is 0.
    bool TryResize(uint64_t bytes);
    // Like TryResize, but waits for the growth to fit until `until`, polling `give_up` (may be
    // empty) every 50 ms. Shrinking returns at once.
    bool Resize(uint64_t bytes, Clock::time_point until, const std::function<bool()>& give_up = {});
    // Gives the bytes back now; the reservation is empty afterwards. Idempotent.
    void Release();

   private:
    friend class MemoryBudget;
    Reservation(MemoryBudget* budget, uint64_t bytes) : budget_(budget), bytes_(bytes) {}
    MemoryBudget* budget_ = nullptr;
    uint64_t bytes_ = 0;
  };

  // Startup: charges a cache that lives as long as the server. RESOURCE_EXHAUSTED naming the
  // budget when the fixed charges alone exceed the limit.
  Status ReserveFixed(const std::string& what, uint64_t bytes) EXCLUDES(mutex_);

  // `bytes` now, or RESOURCE_EXHAUSTED (Exhausted()) when it does not fit.
  Result<Reservation> TryReserve(uint64_t bytes, const std::string& what) EXCLUDES(mutex_);
  // Waits for `bytes` to fit until `until`, polling `give_up` (may be empty; called without the
  // budget's lock, so it may take locks held around a release) every 50 ms.
  // RESOURCE_EXHAUSTED (Exhausted()) when `until` passes or `give_up` said so; at once when
  // `bytes` exceeds what the budget can ever grant (the limit minus the fixed charges).
  // `keep_free`: granted only if that much stays free after it (room kept for others, e.g. the
  // frames already read, which grow their reservations).
  Result<Reservation> Reserve(uint64_t bytes, const std::string& what, Clock::time_point until,
                              const std::function<bool()>& give_up = {}, uint64_t keep_free = 0)
      EXCLUDES(mutex_);

  // The refusal for `bytes` wanted by `what` ("this frame"), naming the budget, its use and the
  // number of live reservations: "memory budget exhausted: limits.memory_budget_bytes =
  // 1073741824, 1012 MiB in use (104 MiB fixed, 908 MiB by 31 requests in flight); this frame
  // needs 36 MiB; retry later".
  Status Exhausted(uint64_t bytes, const std::string& what) const EXCLUDES(mutex_);

  uint64_t limit() const { return limit_; }
  const std::string& name() const { return name_; }
  uint64_t in_use() const EXCLUDES(mutex_);  // fixed + reservations
  uint64_t fixed() const EXCLUDES(mutex_);
  size_t reservations() const EXCLUDES(mutex_);  // live, non-empty reservations

 private:
  bool FitsLocked(uint64_t more) const REQUIRES(mutex_) { return more <= limit_ - in_use_; }
  // A growing reservation is a request already in memory: it goes before new ones, which would
  // otherwise take every release in smaller pieces and starve it.
  bool GrantableLocked(uint64_t more, bool growth, uint64_t keep_free) const REQUIRES(mutex_) {
    return FitsLocked(more + keep_free) && (growth || growing_ == 0);
  }
  Status ExhaustedLocked(uint64_t bytes, const std::string& what) const REQUIRES(mutex_);
  // Waits until `more` fits, `until` passes or `give_up` says so; true if it fits. New
  // reservations (not `growth`) also wait while a growing one waits.
  bool WaitToFitLocked(uint64_t more, Clock::time_point until, const std::function<bool()>& give_up,
                       bool growth, uint64_t keep_free = 0) REQUIRES(mutex_);
  void Give(uint64_t bytes, bool last) EXCLUDES(mutex_);

  const uint64_t limit_;
  const std::string name_;
  mutable Mutex mutex_;
  CondVar released_;
  uint64_t in_use_ GUARDED_BY(mutex_) = 0;
  uint64_t fixed_ GUARDED_BY(mutex_) = 0;
  size_t reservations_ GUARDED_BY(mutex_) = 0;
  size_t growing_ GUARDED_BY(mutex_) = 0;  // reservations waiting to grow
};

}  // namespace placedb::server
