// MemoryBudget: fixed charges, reservations (RAII, resize, move), refusals naming the budget, and
// waiting for room (also under ThreadSanitizer: the MemoryBudgetConcurrency tests).
#include "server/ingest/memory_budget.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <random>
#include <string>
#include <thread>
#include <utility>
#include <vector>

namespace placedb::server {
namespace {

using namespace std::chrono_literals;
constexpr uint64_t kMiB = uint64_t(1) << 20;

MemoryBudget::Clock::time_point In(std::chrono::milliseconds wait) {
  return MemoryBudget::Clock::now() + wait;
}

TEST(MemoryBudgetTest, ReservationsAreReturnedWhenTheyEnd) {
  MemoryBudget budget(100 * kMiB);
  ASSERT_TRUE(budget.ReserveFixed("storage.block_cache_bytes", 30 * kMiB).ok());
  EXPECT_EQ(budget.fixed(), 30 * kMiB);
  {
    auto a = budget.TryReserve(50 * kMiB, "this frame");
    ASSERT_TRUE(a.ok());
    EXPECT_EQ(a->bytes(), 50 * kMiB);
    EXPECT_EQ(budget.in_use(), 80 * kMiB);
    EXPECT_EQ(budget.reservations(), 1u);
    // Moving hands the bytes over; they are returned once, by the last owner.
    MemoryBudget::Reservation moved = std::move(a).value();
    EXPECT_EQ(budget.in_use(), 80 * kMiB);
    MemoryBudget::Reservation other;
    other = std::move(moved);
    EXPECT_FALSE(moved);
    EXPECT_EQ(budget.in_use(), 80 * kMiB);
    EXPECT_EQ(budget.reservations(), 1u);
  }
  EXPECT_EQ(budget.in_use(), 30 * kMiB);
  EXPECT_EQ(budget.reservations(), 0u);

  auto b = budget.TryReserve(70 * kMiB, "this frame");  // exactly what is left
  ASSERT_TRUE(b.ok());
  b->Release();
  b->Release();  // idempotent
  EXPECT_EQ(budget.in_use(), 30 * kMiB);
  EXPECT_EQ(budget.reservations(), 0u);
}

TEST(MemoryBudgetTest, ResizeShrinksAlwaysAndGrowsOnlyIntoRoom) {
  MemoryBudget budget(100 * kMiB);
  auto a = budget.TryReserve(40 * kMiB, "a");
  auto b = budget.TryReserve(40 * kMiB, "b");
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_FALSE(a->TryResize(70 * kMiB));  // 30 more do not fit beside b
  EXPECT_EQ(a->bytes(), 40 * kMiB);
  EXPECT_EQ(budget.in_use(), 80 * kMiB);
  EXPECT_TRUE(a->TryResize(60 * kMiB));  // 20 more do
  EXPECT_EQ(budget.in_use(), 100 * kMiB);
  EXPECT_TRUE(b->TryResize(1 * kMiB));
  EXPECT_EQ(budget.in_use(), 61 * kMiB);
  EXPECT_TRUE(b->TryResize(0));  // empty, still alive
  EXPECT_EQ(budget.reservations(), 2u);
  MemoryBudget::Reservation none;
  EXPECT_FALSE(none.TryResize(1));
  EXPECT_TRUE(none.TryResize(0));
}

TEST(MemoryBudgetTest, ARefusalNamesTheBudgetAndItsUse) {
  MemoryBudget budget(1 << 30);
  ASSERT_TRUE(budget.ReserveFixed("storage.block_cache_bytes", 64 * kMiB).ok());
  std::vector<MemoryBudget::Reservation> frames;
  for (int i = 0; i < 31; ++i) {
    auto frame = budget.TryReserve(30 * kMiB, "this frame");
    ASSERT_TRUE(frame.ok());
    frames.push_back(std::move(frame).value());
  }
  auto refused = budget.TryReserve(36 * kMiB, "this frame");
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kResourceExhausted);
  EXPECT_EQ(refused.status().message(),
            "memory budget exhausted: limits.memory_budget_bytes = 1073741824, 994 MiB in use "
            "(64 MiB fixed, 930 MiB by 31 requests in flight); this frame needs 36 MiB; retry "
            "later");
  // More than the budget can ever grant is said so (waiting would not help).
  auto never = budget.Reserve(2000 * kMiB, "this frame", In(10s));
  ASSERT_FALSE(never.ok());
  EXPECT_NE(never.status().message().find("more than the budget can ever grant (960 MiB beyond "
                                          "its fixed part)"),
            std::string::npos)
      << never.status().message();
  EXPECT_EQ(budget.in_use(), 994 * kMiB);
}

TEST(MemoryBudgetTest, FixedChargesMustFitTheLimit) {
  MemoryBudget budget(100 * kMiB);
  ASSERT_TRUE(budget.ReserveFixed("storage.block_cache_bytes", 64 * kMiB).ok());
  const Status status = budget.ReserveFixed("vocabulary 'default'", 40 * kMiB);
  EXPECT_EQ(status.code(), StatusCode::kResourceExhausted);
  EXPECT_NE(status.message().find("limits.memory_budget_bytes = 104857600 is too small: "
                                  "vocabulary 'default' alone takes 40 MiB"),
            std::string::npos)
      << status.message();
  EXPECT_EQ(budget.fixed(), 64 * kMiB);
  EXPECT_FALSE(budget.TryReserve(40 * kMiB, "this frame").ok());
  EXPECT_TRUE(budget.TryReserve(36 * kMiB, "this frame").ok());
}

TEST(MemoryBudgetTest, AWaitEndsWhenItsTimeIsUpOrItsCallerGivesUp) {
  MemoryBudget budget(10 * kMiB);
  auto all = budget.TryReserve(10 * kMiB, "a");
  ASSERT_TRUE(all.ok());
  EXPECT_FALSE(budget.Reserve(1 * kMiB, "b", In(100ms)).ok());
  std::atomic<int> polls{0};
  auto gave_up = budget.Reserve(1 * kMiB, "b", MemoryBudget::Clock::time_point::max(),
                                [&] { return ++polls >= 3; });
  ASSERT_FALSE(gave_up.ok());
  EXPECT_EQ(gave_up.status().code(), StatusCode::kResourceExhausted);
  EXPECT_GE(polls.load(), 3);
  EXPECT_FALSE(all->Resize(11 * kMiB, In(50ms)));
  EXPECT_EQ(budget.in_use(), 10 * kMiB);
}

TEST(MemoryBudgetTest, AReservationCanBeAskedToLeaveRoomForOthers) {
  MemoryBudget budget(100 * kMiB);
  ASSERT_TRUE(budget.ReserveFixed("cache", 20 * kMiB).ok());
  auto held = budget.TryReserve(50 * kMiB, "held");
  ASSERT_TRUE(held.ok());
  // 30 MiB free: 16 more leave 14, not the 20 asked for.
  EXPECT_FALSE(budget.Reserve(16 * kMiB, "read", In(50ms), {}, 20 * kMiB).ok());
  auto read = budget.Reserve(10 * kMiB, "read", In(50ms), {}, 20 * kMiB);
  ASSERT_TRUE(read.ok());
  // What is kept free is for others: a plain reservation or a growth may take it.
  EXPECT_TRUE(held->TryResize(65 * kMiB));
  EXPECT_EQ(budget.in_use(), 95 * kMiB);
  // Asking to keep more than the budget can ever leave is refused at once.
  EXPECT_FALSE(
      budget.Reserve(1, "read", MemoryBudget::Clock::time_point::max(), {}, 80 * kMiB).ok());
}

// ---- Waiting for room (also run under TSan) ----------------------------------------------------

TEST(MemoryBudgetConcurrency, AWaiterIsGrantedOnceAReservationIsReturned) {
  MemoryBudget budget(10 * kMiB);
  auto held = budget.TryReserve(8 * kMiB, "held");
  ASSERT_TRUE(held.ok());
  std::atomic<bool> granted{false};
  std::thread waiter([&] {
    auto got = budget.Reserve(5 * kMiB, "waiter", MemoryBudget::Clock::time_point::max());
    EXPECT_TRUE(got.ok());
    granted = true;
  });
  std::this_thread::sleep_for(200ms);
  EXPECT_FALSE(granted.load());  // 5 MiB do not fit beside 8
  held->Release();
  waiter.join();
  EXPECT_TRUE(granted.load());
  EXPECT_EQ(budget.in_use(), 0u);  // the waiter's reservation ended with its thread
}

TEST(MemoryBudgetConcurrency, AGrowingReservationGoesBeforeNewOnes) {
  MemoryBudget budget(10 * kMiB);
  auto growing = budget.TryReserve(4 * kMiB, "read frame");
  auto held = budget.TryReserve(6 * kMiB, "held");
  ASSERT_TRUE(growing.ok() && held.ok());
  std::atomic<bool> grown{false}, fresh_granted{false};
  std::thread grower([&] {
    EXPECT_TRUE(growing->Resize(8 * kMiB, MemoryBudget::Clock::time_point::max()));
    grown = true;
  });
  // Wait until the grower is waiting: a new 2 MiB reservation that would fit... is not granted.
  std::this_thread::sleep_for(200ms);
  std::thread fresh([&] {
    auto got = budget.Reserve(2 * kMiB, "new read", MemoryBudget::Clock::time_point::max());
    EXPECT_TRUE(got.ok());
    fresh_granted = true;
    // Holds it until the end of the thread.
  });
  held->TryResize(4 * kMiB);  // 2 MiB free: enough for the new one, not for the growth
  std::this_thread::sleep_for(200ms);
  EXPECT_FALSE(fresh_granted.load());
  EXPECT_FALSE(grown.load());
  held->Release();  // 6 MiB free: the growth (4) first, then the new one (2)
  grower.join();
  fresh.join();
  EXPECT_TRUE(grown.load());
  EXPECT_TRUE(fresh_granted.load());
  EXPECT_EQ(budget.in_use(), 8 * kMiB);
}

TEST(MemoryBudgetConcurrency, ConcurrentReservationsNeverExceedTheLimitAndAllReturn) {
  constexpr uint64_t kLimit = 64 * kMiB;
  MemoryBudget budget(kLimit);
  ASSERT_TRUE(budget.ReserveFixed("cache", 8 * kMiB).ok());
  std::atomic<int> granted{0}, refused{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 6; ++t) {
    threads.emplace_back([&, t] {
      std::mt19937 random(uint32_t(t) + 1);
      std::uniform_int_distribution<uint64_t> size(1, 24 * kMiB);
      for (int i = 0; i < 300; ++i) {
        auto reserved = i % 2 ? budget.TryReserve(size(random), "frame")
                              : budget.Reserve(size(random), "frame", In(5ms));
        if (!reserved.ok()) {
          ++refused;
          continue;
        }
        ++granted;
        EXPECT_LE(budget.in_use(), kLimit);
        reserved->TryResize(size(random));
        EXPECT_LE(budget.in_use(), kLimit);
        if (i % 3 == 0) reserved->TryResize(0);
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  EXPECT_GT(granted.load(), 0);
  EXPECT_EQ(granted + refused, 1800);
  EXPECT_EQ(budget.in_use(), 8 * kMiB);
  EXPECT_EQ(budget.reservations(), 0u);
}

}  // namespace
}  // namespace placedb::server
