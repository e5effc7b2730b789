// `placedb ingest MAP SOURCE...`: frames from folders, lists or videos streamed into a map by one
// or several agents (round-robin), with progress and a summary; optionally with depth images
// (--depth DIR, paired by file stem) and per-agent loop closure (--loop-closure). Or one recording
// (client/recording.h): a ROS 1 bag (--topic, --depth-topic, --camera-info-topic) or a TUM RGB-D
// folder, whose frames carry their capture times (and depth, camera, poses) from the recording;
// other frames are stamped with the wall clock when they are sent.
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
  // Recordings (a ROS 1 bag or a TUM RGB-D folder as the one SOURCE): the bag's topics, and the
  // pairing tolerances in seconds.
  std::string topic;
  std::string depth_topic;
  std::string camera_info_topic;
  double max_offset = 0.02;   // a frame and its depth image (TUM: also its nearest pose)
  double max_pose_gap = 0.1;  // TUM: ground-truth samples interpolated across at most this
};

// Adds `ingest` to `app`, its options bound to *options; returns the subcommand.
CLI::App* RegisterIngest(CLI::App& app, IngestOptions* options);

int RunIngest(const Connection& connection, const IngestOptions& options, bool json, CliIo& io);

}  // namespace placedb::client
