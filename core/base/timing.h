// Per-stage timings reported with every add and query.
#pragma once

#include <chrono>

namespace placedb {

struct StageTimings {
  double decode_ms = 0;        // filled by the service (image decoding)
  double detect_ms = 0;        // filled by the service (object detection)
  double extract_ms = 0;       // feature extraction (0 for precomputed features)
  double depth_ms = 0;         // RGB-D: depth decoding, box refinement, Algorithm 1
  double refine_ms = 0;        // monocular box refinement (core/filter/box_masks.h)
  double filter_ms = 0;        // DC/SC classification
  double transform_ms = 0;     // BoW vector + direct index
  double search_ms = 0;        // inverted-index query
  double verify_ms = 0;        // geometric verification
  double pose_ms = 0;          // relative poses of the verified matches (core/pose)
  double store_ms = 0;         // inserting into the index (and, with storage, persisting)
  double loop_closure_ms = 0;  // the agent's Bayesian loop-closure update
  double total_ms = 0;
};

class Stopwatch {
 public:
  Stopwatch() : start_(std::chrono::steady_clock::now()) {}
  double ElapsedMs() const {
    return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_)
        .count();
  }
  // Milliseconds since the last Lap() (or construction).
  double Lap() {
    auto now = std::chrono::steady_clock::now();
    double ms = std::chrono::duration<double, std::milli>(now - start_).count();
    start_ = now;
    return ms;
  }

 private:
  std::chrono::steady_clock::time_point start_;
};

}  // namespace placedb
