// Ranking places by their dynamic-object statistics (issue 16's GetDynamics): by mean coverage,
// by how often a class is seen, or by mean coverage within an hour-of-day window (UTC), with
// paging by offset.
//
// A place's score under a measure:
//  - kMeanCoverage: mean dynamic coverage over all its observations;
//  - kClassShare: the share of its observations in which `class_id` was seen (0..1);
//  - kHourWindow: mean coverage over its observations whose UTC hour lies in
//    [first_hour, last_hour] (inclusive; first_hour > last_hour wraps past midnight, 22-2), on the
//    weekdays in `weekdays` (bit 0 = Monday .. bit 6 = Sunday).
// Its support is the number of observations the score rests on (all, or those in the window);
// places with no support, or less than `min_observations`, are left out. Order: score descending,
// ties by ascending place id, so pages are stable while the map does not change.
//
// `near` (optional) keeps only places whose position lies within a radius of a point; the
// ranking does not see positions (they are the places' metadata), so its caller applies
// DynamicsNear::Contains before Add().
//
// DynamicsRanking keeps only offset + limit entries however many places it is shown (a bounded
// heap), so ranking a large map needs no list of every place. Not thread-safe.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/dynamics/place_dynamics.h"

namespace placedb {

enum class DynamicsMeasure { kMeanCoverage, kClassShare, kHourWindow };

inline constexpr uint32_t kMaxDynamicsPage = 1000;

// Places near a point: Euclidean distance of positions (x y z, in the poses' own units) at most
// `radius`. Inactive when radius is 0.
struct DynamicsNear {
  std::array<double, 3> centre{};
  double radius = 0;
  bool active() const { return radius > 0; }
  bool Contains(const std::array<double, 3>& position) const;
};

struct DynamicsRankOptions {
  DynamicsMeasure measure = DynamicsMeasure::kMeanCoverage;
  int class_id = -1;   // kClassShare: required, in [0, kMaxClassId]
  int first_hour = 0;  // kHourWindow: 0..23
  int last_hour = 23;
  uint8_t weekdays = 0x7f;  // kHourWindow: at least one of the 7 bits
  uint64_t min_observations = 1;
  uint32_t offset = 0;
  uint32_t limit = 50;  // 1..kMaxDynamicsPage
  DynamicsNear near;    // radius finite and >= 0, centre finite
};

// INVALID_ARGUMENT naming the field.
Status ValidateDynamicsRankOptions(const DynamicsRankOptions& options);

struct RankedPlace {
  uint32_t place = 0;
  double score = 0;
  uint64_t support = 0;
  bool operator==(const RankedPlace&) const = default;
};

// The score of `dynamics` under `options` and its support (0 when nothing to rank on).
double DynamicsScore(const PlaceDynamics& dynamics, const DynamicsRankOptions& options,
                     uint64_t* support);

class DynamicsRanking {
 public:
  // `options` must be valid (ValidateDynamicsRankOptions).
  explicit DynamicsRanking(const DynamicsRankOptions& options);

  void Add(uint32_t place, const PlaceDynamics& dynamics);

  // Places ranked (those with enough support), whatever the page.
  uint64_t ranked() const { return ranked_; }
  // The page: entries offset .. offset + limit - 1 of the order, best first; empty past the end.
  std::vector<RankedPlace> Page() const;

 private:
  DynamicsRankOptions options_;
  uint64_t ranked_ = 0;
  std::vector<RankedPlace> heap_;  // the best offset + limit so far; worst on top
};

}  // namespace placedb
