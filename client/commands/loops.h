// `placedb loops watch|export MAP` (docs/cli.md, "loops"): a map's loop-closure log
// (WatchLoopClosures, issue 32).
//   watch: one line per constraint (--json: one JSON object per line), from --from on; --follow
//          keeps waiting for new ones (Ctrl-C ends it).
//   export: the log as a pose-graph file: g2o (VERTEX_SE3:QUAT for every place a constraint names,
//          at the pose its agent sent, identity when none; EDGE_SE3:QUAT per metric constraint,
//          T_place_query with its information), tum (one line per metric constraint:
//          "t_place t_query tx ty tz qx qy qz qw", seconds) or csv (every constraint, every field,
//          monocular ones included). Constraints without a metric pose are left out of g2o and
//          tum (their translation has no scale); the count is reported on stderr.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
}  // namespace CLI

namespace placedb::client {

struct LoopsFlags {
  std::string map;
  uint64_t from = 1;
  bool follow = false;  // watch
  std::vector<std::string> agents;
  bool inter_agent_only = false;
  uint64_t min_sequence_gap = 0;
  std::string format;  // export: g2o, tum or csv
  std::string out;     // export: the file ("" or "-": stdout)
};

struct LoopsCommands {
  CLI::App* watch = nullptr;
  CLI::App* export_ = nullptr;
};

LoopsCommands RegisterLoops(CLI::App& app, LoopsFlags* flags);

int LoopsWatch(const Connection& connection, const LoopsFlags& flags, bool json, CliIo& io);
int LoopsExport(const Connection& connection, const LoopsFlags& flags, CliIo& io);

// The rotation of a row-major 4x4 rigid transform as a unit quaternion {qx, qy, qz, qw}, qw >= 0.
std::array<double, 4> QuaternionOf(const double* transform);

}  // namespace placedb::client
