// `placedb query MAP IMAGE` (docs/cli.md, "query"): ranked matches of one image, optionally with
// the agent's dynamic-object boxes (--boxes FILE.json) and a registered depth image (--depth).
#pragma once

#include <string>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
}  // namespace CLI

namespace placedb::client {

// --depth FILE, --depth-scale, --intrinsics.
struct DepthFlags {
  std::string file;
  float scale = 0;
  std::string intrinsics;
};

struct QueryFlags {
  std::string map;
  std::string image;
  int top_k = 10;
  std::string boxes;
  bool verified_only = false;
  std::string agent_id = "cli";
  bool exclude_same_agent = false;
  // Verified matches' inlier correspondences and the query's kept/dropped keypoints (in --json;
  // the table says how many).
  bool correspondences = false;
  DepthFlags depth;
  std::string camera;  // --camera fx,fy,cx,cy: verified matches then carry their relative pose
};

// Adds `query` to `app`, its options bound to *flags; returns the subcommand.
CLI::App* RegisterQuery(CLI::App& app, QueryFlags* flags);

int RunQuery(const Connection& connection, const QueryFlags& flags, bool json, CliIo& io);

}  // namespace placedb::client
