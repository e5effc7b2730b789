#include "core/base/stats.h"

#include <gtest/gtest.h>

#include <vector>

namespace placedb {
namespace {

TEST(Percentile, NearestRankOfMeasuredSamples) {
  std::vector<double> samples;
  for (int i = 100; i >= 1; --i) samples.push_back(i);  // any order
  EXPECT_EQ(Percentile(samples, 0.50), 50);
  EXPECT_EQ(Percentile(samples, 0.90), 90);
  EXPECT_EQ(Percentile(samples, 0.99), 99);
  EXPECT_EQ(Percentile(samples, 1.0), 100);
  EXPECT_EQ(Percentile(samples, 0.0), 1);  // the smallest sample, never below it
  EXPECT_EQ(Percentile(samples, 0.001), 1);
  EXPECT_EQ(Percentile(samples, 0.501), 51);  // the next rank up, never interpolated
}

TEST(Percentile, SmallAndEmptySets) {
  EXPECT_EQ(Percentile({}, 0.5), 0);
  EXPECT_EQ(Percentile({7}, 0.5), 7);
  EXPECT_EQ(Percentile({7}, 0.99), 7);
  // Even count: the median is the lower middle sample (rank ceil(n/2)).
  EXPECT_EQ(Percentile({4, 1, 3, 2}, 0.5), 2);
  EXPECT_EQ(Percentile({4, 1, 3, 2}, 0.75), 3);
  EXPECT_EQ(Percentile({4, 1, 3, 2}, 0.76), 4);
  const std::vector<double> sorted = {1.5, 2.5, 3.5};
  EXPECT_EQ(PercentileOfSorted(sorted, 0.5), 2.5);
  EXPECT_EQ(PercentileOfSorted(sorted, 0.34), 2.5);
  EXPECT_EQ(PercentileOfSorted(sorted, 0.33), 1.5);
}

}  // namespace
}  // namespace placedb
