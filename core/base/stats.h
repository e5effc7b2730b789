// Order statistics over measured samples (latencies, throughputs).
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

namespace placedb {

// The nearest-rank percentile of ascending `sorted` samples: the smallest sample with at least
// `fraction` (0..1) of the samples at or below it; never interpolated, so it is always a measured
// value. 0 for no samples.
inline double PercentileOfSorted(const std::vector<double>& sorted, double fraction) {
  if (sorted.empty()) return 0;
  const size_t rank = size_t(std::ceil(fraction * double(sorted.size())));
  return sorted[std::clamp<size_t>(rank, 1, sorted.size()) - 1];
}

// PercentileOfSorted of `samples` in any order.
inline double Percentile(std::vector<double> samples, double fraction) {
  std::sort(samples.begin(), samples.end());
  return PercentileOfSorted(samples, fraction);
}

}  // namespace placedb
