#include "tests/cluster/cluster_frames.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

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
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return 0;
  sockaddr_in address{};
  address.sin_family = AF_INET;
  socklen_t length = sizeof(address);
  int port = 0;
  if (::inet_pton(AF_INET, host.c_str(), &address.sin_addr) == 1 &&
      ::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0 &&
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) == 0) {
    port = ntohs(address.sin_port);
  }
  ::close(fd);
  return port;
}

}  // namespace placedb::server_testing
