// `placedb ingest MAP SOURCE...`: frames from folders, lists or videos streamed into a map by one
// or several agents (round-robin), with progress and a summary; optionally with depth images
// (--depth DIR, paired by file stem) and per-agent loop closure (--loop-closure).
#pragma once

#include <string>
#include <vector>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
}  // namespace CLI

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
  // RGB-D (docs/rgbd.md): depth images paired with the frames by file stem ("" = none).
  std::string depth_dir;
  float depth_scale = 0;      // DepthImage.scale, metres per unit (0 = the map's)
  std::string intrinsics;     // "fx,fy,cx,cy" ("" = none)
  std::string camera;         // "fx,fy,cx,cy": IngestHeader.camera ("" = none)
  bool loop_closure = false;  // IngestHeader.loop_closure: per-agent Bayesian loop closure
};

// Adds `ingest` to `app`, its options bound to *options; returns the subcommand.
CLI::App* RegisterIngest(CLI::App& app, IngestOptions* options);

int RunIngest(const Connection& connection, const IngestOptions& options, bool json, CliIo& io);

}  // namespace placedb::client
