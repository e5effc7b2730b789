// core/dynamics/dynamics_ranking.h: scores, the bounded ranking and its pages.
#include "core/dynamics/dynamics_ranking.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

namespace placedb {
namespace {

constexpr int64_t kSecond = 1'000'000'000;
constexpr int64_t kHourNs = 3600 * kSecond;
constexpr int64_t kMonday2024 = int64_t(1704067200) * kSecond;  // 00:00 UTC
constexpr int64_t kNow = kMonday2024 + int64_t(365) * 24 * kHourNs;

DynamicBox Box(int class_id) {
  DynamicBox box;
  box.class_id = class_id;
  return box;
}

// Observations at Monday `hour`:00 UTC with `coverage`, one box of `class_id` when >= 0.
PlaceDynamics Seen(std::initializer_list<std::pair<int, double>> hour_coverage, int class_id = -1) {
  PlaceDynamics d;
  for (const auto& [hour, coverage] : hour_coverage) {
    std::vector<DynamicBox> boxes;
    if (class_id >= 0) boxes.push_back(Box(class_id));
    Merge(&d, MakeObservation(coverage, boxes, kMonday2024 + hour * kHourNs, kNow));
  }
  return d;
}

std::vector<uint32_t> Ids(const std::vector<RankedPlace>& page) {
  std::vector<uint32_t> ids;
  for (const RankedPlace& entry : page) ids.push_back(entry.place);
  return ids;
}

TEST(DynamicsRankingTest, MeanCoverageBestFirstTiesByIdAndPaging) {
  DynamicsRankOptions options;
  options.limit = 2;
  DynamicsRanking ranking(options);
  ranking.Add(1, Seen({{8, 0.1}, {9, 0.3}}));  // 0.2
  ranking.Add(2, Seen({{8, 0.6}}));            // 0.6
  ranking.Add(3, Seen({{8, 0.2}}));            // 0.2, ties with 1: id order
  ranking.Add(4, PlaceDynamics());             // nothing observed: not ranked
  ranking.Add(5, Seen({{8, 0.05}}));
  EXPECT_EQ(ranking.ranked(), 4u);
  const auto page = ranking.Page();
  EXPECT_EQ(Ids(page), (std::vector<uint32_t>{2, 1}));
  EXPECT_NEAR(page[0].score, 0.6, 1e-9);
  EXPECT_EQ(page[1].support, 2u);

  options.offset = 2;
  DynamicsRanking second(options);
  for (uint32_t id : {5u, 3u, 2u, 1u}) {  // another order of arrival: the same pages
    second.Add(id, id == 1   ? Seen({{8, 0.1}, {9, 0.3}})
                   : id == 2 ? Seen({{8, 0.6}})
                   : id == 3 ? Seen({{8, 0.2}})
                             : Seen({{8, 0.05}}));
  }
  EXPECT_EQ(Ids(second.Page()), (std::vector<uint32_t>{3, 5}));

  options.offset = 4;  // past the end: an empty page, not an error
  DynamicsRanking past(options);
  past.Add(1, Seen({{8, 0.1}}));
  EXPECT_TRUE(past.Page().empty());
  EXPECT_EQ(past.ranked(), 1u);
}

TEST(DynamicsRankingTest, ClassShareCountsFramesWithTheClass) {
  DynamicsRankOptions options;
  options.measure = DynamicsMeasure::kClassShare;
  options.class_id = 2;  // car
  PlaceDynamics parking = Seen({{8, 0.4}, {9, 0.4}}, 2);
  Merge(&parking, Seen({{10, 0.0}}));  // a third frame without a car: 2 / 3
  uint64_t support = 0;
  EXPECT_NEAR(DynamicsScore(parking, options, &support), 2.0 / 3.0, 1e-12);
  EXPECT_EQ(support, 3u);
  DynamicsRanking ranking(options);
  ranking.Add(7, parking);
  ranking.Add(8, Seen({{8, 0.9}}, 0));  // people only: share 0, still ranked (observed)
  ranking.Add(9, Seen({{8, 0.1}}, 2));  // a car every time
  EXPECT_EQ(Ids(ranking.Page()), (std::vector<uint32_t>{9, 7, 8}));
}

TEST(DynamicsRankingTest, HourWindowWrapsPastMidnightAndFiltersWeekdays) {
  DynamicsRankOptions options;
  options.measure = DynamicsMeasure::kHourWindow;
  options.first_hour = 22;
  options.last_hour = 2;
  const PlaceDynamics night = Seen({{23, 0.8}, {1, 0.4}, {12, 0.0}});
  uint64_t support = 0;
  EXPECT_NEAR(DynamicsScore(night, options, &support), 0.6, 1e-12);
  EXPECT_EQ(support, 2u);
  const PlaceDynamics noon = Seen({{12, 0.9}});
  DynamicsRanking ranking(options);
  ranking.Add(1, night);
  ranking.Add(2, noon);  // never seen in the window: not ranked
  EXPECT_EQ(ranking.ranked(), 1u);
  EXPECT_EQ(Ids(ranking.Page()), (std::vector<uint32_t>{1}));
  options.weekdays = 0x02;  // Tuesday only: the Monday observations are outside
  EXPECT_EQ(DynamicsScore(night, options, &support), 0);
  EXPECT_EQ(support, 0u);
  options.weekdays = 0x7f;
  options.min_observations = 3;  // too little support
  DynamicsRanking strict(options);
  strict.Add(1, night);
  EXPECT_EQ(strict.ranked(), 0u);
}

// The bounded heap gives exactly the pages of a full sort, for any measure and offset.
TEST(DynamicsRankingTest, PagesAgreeWithAFullSort) {
  std::mt19937 random(7);
  std::uniform_real_distribution<double> coverage(0, 1);
  std::vector<PlaceDynamics> places(300);
  for (PlaceDynamics& place : places) {
    const int frames = int(random() % 6);
    for (int f = 0; f < frames; ++f) {
      std::vector<DynamicBox> boxes;
      if (random() % 2) boxes.push_back(Box(int(random() % 3)));
      // Coarse coverage so that ties occur.
      Merge(&place, MakeObservation(double(random() % 5) / 4.0, boxes,
                                    kMonday2024 + int64_t(random() % 168) * kHourNs, kNow));
    }
  }
  std::vector<DynamicsRankOptions> cases(3);
  cases[1].measure = DynamicsMeasure::kClassShare;
  cases[1].class_id = 1;
  cases[2].measure = DynamicsMeasure::kHourWindow;
  cases[2].first_hour = 20;
  cases[2].last_hour = 3;
  cases[2].weekdays = 0x15;
  for (DynamicsRankOptions options : cases) {
    ASSERT_TRUE(ValidateDynamicsRankOptions(options).ok());
    std::vector<RankedPlace> all;
    for (size_t i = 0; i < places.size(); ++i) {
      RankedPlace entry{uint32_t(i + 1), 0, 0};
      entry.score = DynamicsScore(places[i], options, &entry.support);
      if (entry.support > 0) all.push_back(entry);
    }
    std::sort(all.begin(), all.end(), [](const RankedPlace& a, const RankedPlace& b) {
      return a.score != b.score ? a.score > b.score : a.place < b.place;
    });
    ASSERT_GT(all.size(), 50u);
    for (uint32_t offset : {0u, 7u, 40u, uint32_t(all.size()) - 3, uint32_t(all.size()) + 5}) {
      options.offset = offset;
      options.limit = 25;
      DynamicsRanking ranking(options);
      for (size_t i = 0; i < places.size(); ++i) ranking.Add(uint32_t(i + 1), places[i]);
      EXPECT_EQ(ranking.ranked(), all.size());
      std::vector<RankedPlace> expected;
      for (size_t k = offset; k < all.size() && k < size_t(offset) + 25; ++k) {
        expected.push_back(all[k]);
      }
      EXPECT_EQ(ranking.Page(), expected) << "offset " << offset;
    }
  }
}

TEST(DynamicsRankingTest, BadOptionsAreInvalidArgument) {
  auto code = [](DynamicsRankOptions options) {
    return ValidateDynamicsRankOptions(options).code();
  };
  DynamicsRankOptions options;
  EXPECT_EQ(code(options), StatusCode::kOk);
  options.limit = 0;
  EXPECT_EQ(code(options), StatusCode::kInvalidArgument);
  options.limit = kMaxDynamicsPage + 1;
  EXPECT_EQ(code(options), StatusCode::kInvalidArgument);
  options = {};
  options.measure = DynamicsMeasure::kClassShare;  // no class
  EXPECT_EQ(code(options), StatusCode::kInvalidArgument);
  options.class_id = kMaxClassId + 1;
  EXPECT_EQ(code(options), StatusCode::kInvalidArgument);
  options = {};
  options.measure = DynamicsMeasure::kHourWindow;
  options.last_hour = 24;
  EXPECT_EQ(code(options), StatusCode::kInvalidArgument);
  options.last_hour = 10;
  options.weekdays = 0;
  EXPECT_EQ(code(options), StatusCode::kInvalidArgument);
}

// Places near a point: a ball (inclusive), in all three coordinates; bad centres and radii
// are INVALID_ARGUMENT naming the field.
TEST(DynamicsRankingTest, NearIsABallAroundThePoint) {
  DynamicsNear near;
  EXPECT_FALSE(near.active());
  near.centre = {1, 2, 3};
  near.radius = 5;
  EXPECT_TRUE(near.active());
  EXPECT_TRUE(near.Contains({1, 2, 3}));
  EXPECT_TRUE(near.Contains({4, 6, 3}));   // exactly 5 away
  EXPECT_FALSE(near.Contains({4, 6, 4}));  // sqrt(26) away
  EXPECT_FALSE(near.Contains({1, 2, 8.01}));
  DynamicsRankOptions options;
  options.near = near;
  EXPECT_TRUE(ValidateDynamicsRankOptions(options).ok());
  options.near.radius = -1;
  EXPECT_NE(ValidateDynamicsRankOptions(options).message().find("near_radius"), std::string::npos);
  options.near.radius = std::numeric_limits<double>::infinity();
  EXPECT_EQ(ValidateDynamicsRankOptions(options).code(), StatusCode::kInvalidArgument);
  options.near.radius = 1;
  options.near.centre[1] = std::nan("");
  EXPECT_NE(ValidateDynamicsRankOptions(options).message().find("near"), std::string::npos);
}

}  // namespace
}  // namespace placedb
