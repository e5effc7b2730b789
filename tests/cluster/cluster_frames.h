// What the cluster tests that ingest through workers share (worker_test, cluster_hosts_test):
// precomputed feature frames of the RTAB-Map loop (ingest measures the cluster, not ORB
// extraction) and a free TCP port for a process to listen on.
#pragma once

#include <string>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {

// Precomputed features of RTAB-Map frames 1..n (extracted once, then kept; not thread-safe:
// call it once from the main thread before agents use FeatureObservation).
const std::vector<v1::Features>& FeatureFrames(int n);

// Frame `frame` of `agent` (sequence = frame) with precomputed features; frames beyond the
// sequence's 84 repeat its features (a robot passing again).
v1::Observation FeatureObservation(int frame, const std::string& agent);

// A TCP port free on `host` (an IPv4 address of the caller's network namespace) when asked,
// below the ephemeral range as cluster::testing::FreePorts picks them (a server killed and
// restarted on it finds it free); 0 when none could be bound.
int FreePort(const std::string& host = "127.0.0.1");

}  // namespace placedb::server_testing
