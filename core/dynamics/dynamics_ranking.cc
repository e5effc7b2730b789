#include "core/dynamics/dynamics_ranking.h"

#include <algorithm>
#include <cmath>

namespace placedb {

namespace {

// Better-first order: score descending, then place ascending.
bool Better(const RankedPlace& a, const RankedPlace& b) {
  return a.score != b.score ? a.score > b.score : a.place < b.place;
}

bool InWindow(int hour, int first, int last) {
  return first <= last ? hour >= first && hour <= last : hour >= first || hour <= last;
}

}  // namespace

Status ValidateDynamicsRankOptions(const DynamicsRankOptions& options) {
  if (options.measure == DynamicsMeasure::kClassShare &&
      (options.class_id < 0 || options.class_id > kMaxClassId)) {
    return Status::InvalidArgument("class_id: " + std::to_string(options.class_id) +
                                   " is not a class id (0.." + std::to_string(kMaxClassId) + ")");
  }
  if (options.measure == DynamicsMeasure::kHourWindow) {
    for (int hour : {options.first_hour, options.last_hour}) {
      if (hour < 0 || hour >= kHours) {
        return Status::InvalidArgument("hours: " + std::to_string(hour) +
                                       " is not an hour of the day (0..23)");
      }
    }
    if ((options.weekdays & 0x7f) == 0 || (options.weekdays & 0x80)) {
      return Status::InvalidArgument("weekdays: choose one or more of the 7 days (bits 0..6)");
    }
  }
  const auto& c = options.near.centre;
  if (!std::isfinite(c[0]) || !std::isfinite(c[1]) || !std::isfinite(c[2])) {
    return Status::InvalidArgument("near: the position must be finite");
  }
  if (!std::isfinite(options.near.radius) || options.near.radius < 0) {
    return Status::InvalidArgument("near_radius: must be a finite distance >= 0");
  }
  if (options.limit == 0 || options.limit > kMaxDynamicsPage) {
    return Status::InvalidArgument("limit: must be in 1.." + std::to_string(kMaxDynamicsPage));
  }
  return Status::Ok();
}

bool DynamicsNear::Contains(const std::array<double, 3>& position) const {
  const double dx = position[0] - centre[0];
  const double dy = position[1] - centre[1];
  const double dz = position[2] - centre[2];
  return dx * dx + dy * dy + dz * dz <= radius * radius;
}

double DynamicsScore(const PlaceDynamics& d, const DynamicsRankOptions& options,
                     uint64_t* support) {
  switch (options.measure) {
    case DynamicsMeasure::kMeanCoverage:
      *support = d.observations;
      return d.mean_coverage();
    case DynamicsMeasure::kClassShare: {
      *support = d.observations;
      if (d.observations == 0) return 0;
      auto it = d.classes.find(options.class_id);
      return it == d.classes.end() ? 0 : double(it->second.frames) / double(d.observations);
    }
    case DynamicsMeasure::kHourWindow: {
      uint64_t observations = 0, sum = 0;
      for (int day = 0; day < kWeekdays; ++day) {
        if (!(options.weekdays & (1u << day))) continue;
        for (int hour = 0; hour < kHours; ++hour) {
          if (!InWindow(hour, options.first_hour, options.last_hour)) continue;
          const HourBin& bin = d.hours[size_t(day * kHours + hour)];
          observations += bin.observations;
          sum += bin.coverage_ppm_sum;
        }
      }
      *support = observations;
      return observations ? double(sum) / double(observations) / double(kCoverageScale) : 0;
    }
  }
  *support = 0;
  return 0;
}

DynamicsRanking::DynamicsRanking(const DynamicsRankOptions& options) : options_(options) {}

void DynamicsRanking::Add(uint32_t place, const PlaceDynamics& dynamics) {
  RankedPlace entry;
  entry.place = place;
  entry.score = DynamicsScore(dynamics, options_, &entry.support);
  if (entry.support == 0 || entry.support < options_.min_observations) return;
  ++ranked_;
  const size_t keep = size_t(options_.offset) + options_.limit;
  // With Better as the heap's "less", the top is the worst kept entry.
  if (heap_.size() < keep) {
    heap_.push_back(entry);
    std::push_heap(heap_.begin(), heap_.end(), Better);
  } else if (Better(entry, heap_.front())) {
    std::pop_heap(heap_.begin(), heap_.end(), Better);
    heap_.back() = entry;
    std::push_heap(heap_.begin(), heap_.end(), Better);
  }
}

std::vector<RankedPlace> DynamicsRanking::Page() const {
  std::vector<RankedPlace> sorted = heap_;
  std::sort(sorted.begin(), sorted.end(), Better);
  if (sorted.size() <= options_.offset) return {};
  return std::vector<RankedPlace>(sorted.begin() + options_.offset, sorted.end());
}

}  // namespace placedb
