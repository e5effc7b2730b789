// `placedb load` / `placedb-load`: a load tester for a server on this machine. N agents stream
// frames (encoded images, or ORB features extracted once locally so only the index is loaded) at
// a target rate or as fast as the server takes them, bounded by a frame count or a duration, and
// optionally mix in queries. Reports throughput and latency percentiles per RPC kind and per
// server stage, and errors by status code; a table on stdout, JSON with --json-out.
//
// Refuses any target that does not resolve to loopback only (client/loopback.h).
#pragma once

#include <string>
#include <vector>

#include "client/cli.h"
#include "client/connection.h"
#include "core/base/status.h"
#include "proto/placedb.pb.h"

namespace CLI {
class App;
}  // namespace CLI

namespace cv {
class Mat;
}  // namespace cv

namespace placedb::client {

struct LoadOptions {
  std::vector<std::string> sources;  // frames, preloaded (see client/frame_source.h)
  int video_every = 1;
  std::string glob;                 // folder entries: only names matching (e.g. "*.jpg")
  size_t max_source_frames = 2000;  // distinct frames preloaded; the run cycles through them
  std::string map;                  // empty: a temporary map, deleted afterwards
  bool keep_map = false;            // keep the temporary map
  int agents = 2;
  std::string mode = "encoded";  // "encoded" | "features"
  double rate = 0;               // per agent, frames/s (0 = unpaced)
  double total_rate = 0;         // all agents together, frames/s (overrides rate)
  uint64_t frames = 0;           // bound: frames (ingest + query) in total; 0 = no bound
  double duration_s = 0;         // bound: seconds; 0 = no bound. Neither: one pass
  double query_ratio = 0;        // fraction of the frames sent as Query instead of ingested
  int top_k = 10;                // queries (and ingest matches when matches is set)
  bool matches = false;          // ingest with matches (search before store)
  size_t window = 8;             // unanswered frames per stream
  std::string json_out;          // report file
  std::string agent_prefix = "load";
};

// --mode features: the frame's ORB features (gray pixels, the map's ORB settings) into `out`, as
// an agent sends them. The CLI's libraries link the API only, no engine module: a program gets
// this mode by linking placedb_load_orb (client/load_orb.cc, core's ExtractOrb), which installs
// its extractor before main(); placedb and placedb-load do. Without one, --mode features is a
// usage error.
using LoadFeatureExtractor = Status (*)(const cv::Mat& gray, const v1::OrbSettings& settings,
                                        v1::Features* out);
void SetLoadFeatureExtractor(LoadFeatureExtractor extractor);

// Adds `load` to `app`, its options bound to *options; returns the subcommand.
CLI::App* RegisterLoad(CLI::App& app, LoadOptions* options);

// Opens its own connection: the target is checked to be loopback first.
int RunLoad(const ConnectionOptions& connection_options, const LoadOptions& options, bool json,
            CliIo& io);

}  // namespace placedb::client
