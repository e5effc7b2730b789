// What one observation costs the memory budget (server/ingest/memory_budget.h) while the server
// holds it: its message, the images it decodes to and the working memory of feature extraction,
// estimated from the message and the images' headers before anything is decoded.
// docs/service.md ("Memory budget") lists the factors.
#pragma once

#include <cstdint>

#include "core/features/local_features.h"
#include "proto/placedb.pb.h"

namespace placedb::server {

// Estimated peak bytes of preparing `observation` (the parsed message included) on a map of
// `feature_type`; `color` when it is decoded in colour (server-side detection, GrabCut). An image
// whose header cannot be read counts as its bytes only: decoding refuses it anyway.
uint64_t EstimateFrameBytes(const v1::Observation& observation, FeatureType feature_type,
                            bool color);

// What a prepared frame keeps until its answer is written (its static features and BoW vector;
// the message and the pixels are gone by then): the most limits.max_descriptors_per_frame SIFT
// descriptors take, rounded up.
inline constexpr uint64_t kPreparedFrameBytes = uint64_t(1) << 20;

}  // namespace placedb::server
