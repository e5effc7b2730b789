// Observations as the service receives them: the bytes are a placedb.v1.IngestRequest (first
// byte even) or QueryRequest (odd), parsed by protobuf, then what the handlers do with them:
// CheckFeatureType against an ORB and a SIFT map, wire::DecodeObservation (grayscale and, for
// server-side detection, colour) with small limits, and QueryOptionsFromProto. Invariants: no
// crash; errors name the field or the limit; what decodes respects the limits
// (observation_checks.h).
#include <cstddef>
#include <cstdint>

#include "proto/convert_config.h"
#include "proto/convert_frame.h"
#include "proto/placedb.pb.h"
#include "tests/fuzz/fuzz_support.h"
#include "tests/fuzz/observation_checks.h"

namespace placedb {
namespace {

void FuzzObservation(const wire::v1::Observation& observation, bool color) {
  for (const FeatureType type : {FeatureType::kOrb, FeatureType::kSift}) {
    const Status s = wire::CheckFeatureType(observation, type, "fuzz", "observation");
    PLACEDB_FUZZ_CHECK(s.ok() || s.code() == StatusCode::kInvalidArgument,
                       "CheckFeatureType: unexpected error " + s.ToString());
  }
  fuzz::DecodeAndCheck(observation, color);
}

}  // namespace
}  // namespace placedb

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  if (size == 0) return 0;
  const uint8_t mode = data[0];
  const bool color = mode & 2;
  if (mode & 1) {
    wire::v1::QueryRequest request;
    if (!request.ParseFromArray(data + 1, int(size - 1))) return 0;
    (void)wire::QueryOptionsFromProto(request.options(), request.observation().agent_id());
    FuzzObservation(request.observation(), color);
  } else {
    wire::v1::IngestRequest request;
    if (!request.ParseFromArray(data + 1, int(size - 1))) return 0;
    if (request.has_header()) {
      (void)wire::QueryOptionsFromProto(request.header().matches(), "");
    } else {
      FuzzObservation(request.observation(), color);
    }
  }
  return 0;
}
