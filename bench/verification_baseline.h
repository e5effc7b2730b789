// The default verifier before the change that introduced this file (commit af886a8), kept only
// as the same-run baseline of placedb-bench-verification: exhaustive ORB matching over descriptors
// blocked 8 at a time as 64-bit words (AVX-512 VPOPCNTDQ, one query descriptor per block, index
// blends), the ratio test, and OpenCV's USAC_FAST fundamental matrix with the configured
// iterations. A copy of that code (fundamental matrix only: no cameras, no inlier pairs); the
// library no longer has it.
#pragma once

#include "core/base/status.h"
#include "core/features/orb_features.h"
#include "core/search/geometric_verifier.h"

namespace placedb::bench {

// VerifyGeometry as it was, for config.mode == kExhaustive and !config.legacy.
Result<VerificationResult> VerifyPreviousDefault(const FeatureSet& query,
                                                 const FeatureSet& candidate,
                                                 const VerificationConfig& config);

}  // namespace placedb::bench
