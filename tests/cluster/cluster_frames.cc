#include "tests/cluster/cluster_frames.h"

#include "tests/cluster/engines.h"

namespace placedb::server_testing {

const std::vector<v1::Features>& FeatureFrames(int n) {
  static std::vector<v1::Features> features;
  while (int(features.size()) < n) {
    features.push_back(FeaturesOf(RtabmapObservation(int(features.size()) + 1, "x")));
  }
  return features;
}

v1::Observation FeatureObservation(int frame, const std::string& agent) {
  v1::Observation observation;
  observation.set_agent_id(agent);
  observation.set_sequence(uint64_t(frame));
  observation.set_timestamp_ns(int64_t(frame) * 100'000'000);
  const int source = (frame - 1) % 84 + 1;
  *observation.mutable_features() = FeatureFrames(source)[size_t(source - 1)];
  return observation;
}

int FreePort(const std::string& host) {
  auto ports = cluster::testing::FreePorts(host, 1);
  return ports.ok() ? (*ports)[0] : 0;
}

}  // namespace placedb::server_testing
