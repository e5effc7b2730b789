// Per-place dynamic-object statistics (issue 16): what the dynamic objects seen at a place say
// about it (how much of the view they cover, which classes, at which hours).
//
// The model is a commutative monoid: a frame becomes one PlaceDynamics (MakeObservation), and
// statistics combine by Merge(), which is associative and commutative and exact (coverage is kept
// in integer parts per million, never as a floating-point sum), so any grouping of partial merges
// gives the same bytes. That is what lets storage keep them with a RocksDB merge operator: every
// acknowledged frame adds its delta in the place's own write batch, with no read-modify-write.
//
// A frame's inputs are what the pipeline already computed: FrameCounts::dynamic_coverage (the
// share of the image's pixels on dynamic objects, DynamicFilter) and the boxes it used
// (PlaceDatabase::SelectBoxes: the map's dynamic classes at or above min_box_confidence), plus
// the frame's timestamp.
//
// Bad input is counted, never guessed:
//  - timestamp zero or negative: `untimed`; a timestamp more than kFutureToleranceNs past `now`:
//    `future`. Such a frame counts everywhere except the hour x weekday histogram and `last`.
//  - coverage not finite is 0, outside [0, 1] is clamped (the filter never produces either).
//  - a class id outside [0, kMaxClassId] goes to `unknown_class_boxes`, not to a class.
// The histogram is in UTC (hour 0-23, weekday 0 = Monday .. 6 = Sunday).
//
// This module knows nothing of storage or gRPC. Not thread-safe: values, like ints.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/detect/dynamic_objects.h"

namespace placedb {

inline constexpr int kMaxClassId = 1000;  // DatabaseConfig::dynamic_classes' own bound
inline constexpr int64_t kFutureToleranceNs = int64_t(24) * 3600 * 1'000'000'000;  // clock skew
inline constexpr uint32_t kCoverageScale = 1'000'000;  // coverage in parts per million
inline constexpr int kHours = 24;
inline constexpr int kWeekdays = 7;
inline constexpr int kHourBins = kHours * kWeekdays;

struct ClassCount {
  uint64_t frames = 0;  // observations in which the class was seen at least once
  uint64_t boxes = 0;   // its boxes over all observations
  bool operator==(const ClassCount&) const = default;
};

struct HourBin {
  uint64_t observations = 0;
  uint64_t coverage_ppm_sum = 0;
  bool operator==(const HourBin&) const = default;
};

struct PlaceDynamics {
  uint64_t observations = 0;
  uint64_t coverage_ppm_sum = 0;  // mean = sum / observations
  uint32_t coverage_ppm_max = 0;
  // The newest timed observation (greatest timestamp; ties: greatest coverage). 0 when none.
  int64_t last_timestamp_ns = 0;
  uint32_t last_coverage_ppm = 0;
  uint64_t untimed = 0;  // timestamp zero or negative
  uint64_t future = 0;   // timestamp too far past the ingesting server's clock
  uint64_t unknown_class_boxes = 0;
  std::map<int, ClassCount> classes;  // by class id (COCO: person 0, car 2, ...)
  // Index: weekday * 24 + hour (UTC). Only timed, plausible observations.
  std::array<HourBin, kHourBins> hours{};

  bool empty() const { return observations == 0; }
  double mean_coverage() const;  // 0 when empty
  double max_coverage() const { return coverage_ppm_max / double(kCoverageScale); }
  double last_coverage() const { return last_coverage_ppm / double(kCoverageScale); }
  bool operator==(const PlaceDynamics&) const = default;
};

// One frame's statistics. `now_unix_ns`: the ingesting server's clock, to recognise future
// timestamps.
PlaceDynamics MakeObservation(double dynamic_coverage, const std::vector<DynamicBox>& boxes,
                              int64_t timestamp_ns, int64_t now_unix_ns);

// into += other. Associative, commutative, exact.
void Merge(PlaceDynamics* into, const PlaceDynamics& other);

// The UTC bin of a (positive) timestamp: weekday * 24 + hour.
int HourBinOf(int64_t timestamp_ns);

// Binary form: a version byte (1), then varints (class map and the non-empty histogram bins
// sparse, in ascending order), last_timestamp_ns as a zigzag varint. Decoding is bounds-checked
// and CORRUPTION on anything malformed (truncated, trailing bytes, a bin or class out of range,
// classes or bins not strictly ascending, a max above the scale).
std::string EncodeDynamics(const PlaceDynamics& dynamics);
Result<PlaceDynamics> DecodeDynamics(std::string_view bytes);

}  // namespace placedb
