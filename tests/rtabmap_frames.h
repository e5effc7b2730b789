// The RTAB-Map loop's frames processed by a database, for the storage tests that write real
// places (crash, damage, disk full). Header-only: those tests link core/pipeline through storage,
// the shared test libraries do not.
#pragma once

#include <gtest/gtest.h>

#include <cstddef>
#include <limits>
#include <string>
#include <vector>

#include "core/pipeline/place_database.h"
#include "tests/test_support.h"

namespace placedb::testing {

// RTAB-Map loop frame `index` (1-based) as agent `agent`'s observation: sequence = index, captured
// index x 0.5 s after the epoch.
inline Observation RtabmapFrame(int index, const std::string& agent) {
  Observation observation;
  observation.image = ReadGray(RtabmapFramePath(index));
  observation.metadata.agent_id = agent;
  observation.metadata.sequence = uint64_t(index);
  observation.metadata.timestamp_ns = int64_t(index) * 500'000'000;
  return observation;
}

// The valid places among frames 1-84, in order, at most `max_places` of them (a few bare corridor
// views are invalid places). A frame that fails to process fails the test.
inline std::vector<ProcessedFrame> ProcessRtabmapFrames(
    const PlaceDatabase& db, size_t max_places = std::numeric_limits<size_t>::max()) {
  std::vector<ProcessedFrame> frames;
  for (int i = 1; i <= 84 && frames.size() < max_places; ++i) {
    Observation observation;
    observation.image = ReadGray(RtabmapFramePath(i));
    auto frame = db.Process(observation);
    EXPECT_TRUE(frame.ok()) << "frame " << i << ": " << frame.status().ToString();
    if (frame.ok() && frame->valid) frames.push_back(*frame);
  }
  return frames;
}

}  // namespace placedb::testing
