// `placedb ingest MAP SOURCE...`: frames from folders, lists or videos streamed into a map by one
// or several agents (round-robin), with progress and a summary.
#pragma once

#include <string>
#include <vector>

#include "client/cli.h"
#include "client/connection.h"

namespace placedb::client {

struct IngestOptions {
  std::string map;
  std::vector<std::string> sources;
  int agents = 1;                // Ingest streams; frame k goes to agent k % agents
  std::string agent_id = "cli";  // with several agents: "<id>-1" ... "<id>-N"
  int video_every = 1;           // every K-th video frame
  std::string glob;              // folder entries: only names matching (e.g. "*.jpg")
  bool matches = false;          // ask for each frame's matches against the map before it
  int top_k = 3;                 // with matches
  double rate = 0;               // frames per second per agent; 0 = as fast as accepted
  uint64_t sequence_start = 0;   // Observation.sequence of the first frame
  size_t window = 8;             // unanswered frames per stream
};

int RunIngest(const Connection& connection, const IngestOptions& options, bool json, CliIo& io);

}  // namespace placedb::client
