// core/dynamics/place_dynamics.h: one frame's statistics, the merge (associative, commutative,
// exact) and the binary form.
#include "core/dynamics/place_dynamics.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

namespace placedb {
namespace {

constexpr int64_t kSecond = 1'000'000'000;
// 2024-01-01 00:00:00 UTC, a Monday.
constexpr int64_t kMonday2024 = int64_t(1704067200) * kSecond;
constexpr int64_t kNow = kMonday2024 + int64_t(30) * 86400 * kSecond;

DynamicBox Box(int class_id) {
  DynamicBox box;
  box.class_id = class_id;
  box.rect = cv::Rect2f(0, 0, 10, 10);
  return box;
}

TEST(PlaceDynamicsTest, OneFrameFillsEveryField) {
  const int64_t t = kMonday2024 + int64_t(2) * 86400 * kSecond + int64_t(9) * 3600 * kSecond +
                    int64_t(1800) * kSecond;  // Wednesday 09:30
  const PlaceDynamics d = MakeObservation(0.25, {Box(0), Box(0), Box(2)}, t, kNow);
  EXPECT_EQ(d.observations, 1u);
  EXPECT_EQ(d.coverage_ppm_sum, 250000u);
  EXPECT_EQ(d.coverage_ppm_max, 250000u);
  EXPECT_DOUBLE_EQ(d.mean_coverage(), 0.25);
  EXPECT_EQ(d.last_timestamp_ns, t);
  EXPECT_EQ(d.last_coverage_ppm, 250000u);
  EXPECT_EQ(d.untimed, 0u);
  EXPECT_EQ(d.future, 0u);
  ASSERT_EQ(d.classes.size(), 2u);
  EXPECT_EQ(d.classes.at(0), (ClassCount{1, 2}));
  EXPECT_EQ(d.classes.at(2), (ClassCount{1, 1}));
  EXPECT_EQ(HourBinOf(t), 2 * 24 + 9);
  for (int i = 0; i < kHourBins; ++i) {
    EXPECT_EQ(d.hours[size_t(i)].observations, i == 2 * 24 + 9 ? 1u : 0u) << i;
  }
  EXPECT_EQ(d.hours[2 * 24 + 9].coverage_ppm_sum, 250000u);
}

TEST(PlaceDynamicsTest, WeekdaysAndHoursInUtc) {
  EXPECT_EQ(HourBinOf(kMonday2024), 0);                                       // Monday 00:00
  EXPECT_EQ(HourBinOf(kMonday2024 + int64_t(86400 * 7 - 1) * kSecond), 167);  // Sunday 23:59:59
  EXPECT_EQ(HourBinOf(int64_t(1) * kSecond), 3 * 24);  // 1970-01-01 was a Thursday
}

TEST(PlaceDynamicsTest, BadTimestampsAreCountedNotBinned) {
  for (int64_t bad : {int64_t(0), int64_t(-5) * kSecond}) {
    const PlaceDynamics d = MakeObservation(0.5, {}, bad, kNow);
    EXPECT_EQ(d.untimed, 1u) << bad;
    EXPECT_EQ(d.observations, 1u);
    EXPECT_EQ(d.coverage_ppm_sum, 500000u);
    EXPECT_EQ(d.last_timestamp_ns, 0);
    for (const HourBin& bin : d.hours) EXPECT_EQ(bin.observations, 0u);
  }
  const PlaceDynamics future = MakeObservation(0.5, {}, kNow + kFutureToleranceNs + 1, kNow);
  EXPECT_EQ(future.future, 1u);
  EXPECT_EQ(future.untimed, 0u);
  EXPECT_EQ(future.last_timestamp_ns, 0);
  for (const HourBin& bin : future.hours) EXPECT_EQ(bin.observations, 0u);
  // Within the clock-skew tolerance it is an ordinary observation.
  const PlaceDynamics skewed = MakeObservation(0.5, {}, kNow + kFutureToleranceNs, kNow);
  EXPECT_EQ(skewed.future, 0u);
  EXPECT_EQ(skewed.last_timestamp_ns, kNow + kFutureToleranceNs);
}

TEST(PlaceDynamicsTest, UnknownClassesAndBadCoverage) {
  const PlaceDynamics d =
      MakeObservation(std::numeric_limits<double>::quiet_NaN(),
                      {Box(-1), Box(kMaxClassId + 1), Box(kMaxClassId)}, kMonday2024, kNow);
  EXPECT_EQ(d.unknown_class_boxes, 2u);
  ASSERT_EQ(d.classes.size(), 1u);
  EXPECT_EQ(d.classes.at(kMaxClassId), (ClassCount{1, 1}));
  EXPECT_EQ(d.coverage_ppm_sum, 0u);
  EXPECT_EQ(MakeObservation(1.5, {}, kMonday2024, kNow).coverage_ppm_max, kCoverageScale);
  EXPECT_EQ(MakeObservation(-0.5, {}, kMonday2024, kNow).coverage_ppm_max, 0u);
}

TEST(PlaceDynamicsTest, MergeSumsAndKeepsTheNewest) {
  PlaceDynamics d = MakeObservation(0.1, {Box(0)}, kMonday2024 + 3600 * kSecond, kNow);
  Merge(&d, MakeObservation(0.4, {Box(0), Box(2)}, kMonday2024, kNow));
  Merge(&d, MakeObservation(0.7, {}, 0, kNow));
  EXPECT_EQ(d.observations, 3u);
  EXPECT_NEAR(d.mean_coverage(), 0.4, 1e-9);
  EXPECT_DOUBLE_EQ(d.max_coverage(), 0.7);
  EXPECT_EQ(d.last_timestamp_ns, kMonday2024 + 3600 * kSecond);  // untimed never "last"
  EXPECT_DOUBLE_EQ(d.last_coverage(), 0.1);
  EXPECT_EQ(d.untimed, 1u);
  EXPECT_EQ(d.classes.at(0), (ClassCount{2, 2}));
  EXPECT_EQ(d.classes.at(2), (ClassCount{1, 1}));
  EXPECT_EQ(d.hours[0].observations, 1u);
  EXPECT_EQ(d.hours[1].observations, 1u);
}

// Random frames merged in random orders and random groupings (as RocksDB's partial merges and
// compactions may) give identical statistics and identical bytes.
TEST(PlaceDynamicsTest, MergeIsAssociativeAndCommutative) {
  std::mt19937 random(16);
  std::uniform_real_distribution<double> coverage(0, 1);
  std::uniform_int_distribution<int> cls(-2, 9);
  std::uniform_int_distribution<int64_t> when(-kSecond, kNow + 2 * kFutureToleranceNs);
  std::vector<PlaceDynamics> frames;
  for (int i = 0; i < 200; ++i) {
    std::vector<DynamicBox> boxes(size_t(random() % 4));
    for (DynamicBox& box : boxes) box = Box(cls(random));
    // Repeated timestamps too, so ties in `last` are exercised.
    const int64_t t = i % 10 == 0 ? kMonday2024 : when(random);
    frames.push_back(MakeObservation(coverage(random), boxes, t, kNow));
  }
  PlaceDynamics sequential;
  for (const PlaceDynamics& f : frames) Merge(&sequential, f);
  EXPECT_EQ(sequential.observations, 200u);
  for (int trial = 0; trial < 20; ++trial) {
    std::vector<PlaceDynamics> parts = frames;
    std::shuffle(parts.begin(), parts.end(), random);
    // Random pairwise reductions: a tree of partial merges.
    while (parts.size() > 1) {
      const size_t i = random() % (parts.size() - 1);
      Merge(&parts[i], parts[i + 1]);
      parts.erase(parts.begin() + long(i) + 1);
    }
    EXPECT_EQ(parts[0], sequential) << "trial " << trial;
    EXPECT_EQ(EncodeDynamics(parts[0]), EncodeDynamics(sequential));
  }
}

TEST(PlaceDynamicsTest, EncodingRoundTrips) {
  PlaceDynamics d;
  EXPECT_EQ(*DecodeDynamics(EncodeDynamics(d)), d);
  for (int i = 0; i < 50; ++i) {
    Merge(&d, MakeObservation(i / 50.0, {Box(i % 3), Box(-1)},
                              i % 7 ? kMonday2024 + int64_t(i) * 3000 * kSecond : 0, kNow));
  }
  auto decoded = DecodeDynamics(EncodeDynamics(d));
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(*decoded, d);
}

TEST(PlaceDynamicsTest, DamagedBytesAreCorruption) {
  PlaceDynamics d = MakeObservation(0.3, {Box(0), Box(2)}, kMonday2024, kNow);
  const std::string bytes = EncodeDynamics(d);
  for (size_t n = 0; n < bytes.size(); ++n) {
    auto decoded = DecodeDynamics(bytes.substr(0, n));
    ASSERT_FALSE(decoded.ok()) << n;
    EXPECT_EQ(decoded.status().code(), StatusCode::kCorruption) << n;
  }
  EXPECT_EQ(DecodeDynamics(bytes + "x").status().code(), StatusCode::kCorruption);
  std::string version = bytes;
  version[0] = 9;
  EXPECT_EQ(DecodeDynamics(version).status().code(), StatusCode::kCorruption);
  // A coverage maximum above 1 (varint of 2,000,000 in place of 300,000).
  PlaceDynamics high = d;
  high.coverage_ppm_max = 2 * kCoverageScale;
  EXPECT_EQ(DecodeDynamics(EncodeDynamics(high)).status().code(), StatusCode::kCorruption);
}

}  // namespace
}  // namespace placedb
