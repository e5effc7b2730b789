// `placedb dynamics MAP [--class NAME|ID] [--hours FIRST-LAST] [--weekdays mon,...] [--limit N]
// [--offset N] [--min-observations N] [--near X,Y[,Z] --radius R] [--png FILE]` (issue 16): a map's
// dynamic-object statistics and its places ranked by mean coverage, by how often a class is seen,
// or by coverage in an hour window (UTC), one page at a time (GetDynamics). --png also draws the
// page (client/dynamics_chart.h), with each place's thumbnail when the map keeps one; a file that
// cannot be written is a usage error (exit 2) after the table is printed.
#pragma once

#include <cstdint>
#include <string>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
}  // namespace CLI

namespace placedb::client {

struct DynamicsFlags {
  std::string map;
  std::string class_label;  // a COCO name ("person") or id; ranks by class share
  std::string hours;        // "8-10" (UTC, inclusive; "22-2" wraps midnight)
  std::string weekdays;     // "mon,tue,..."; with --hours
  uint32_t limit = 20;
  uint32_t offset = 0;
  uint64_t min_observations = 1;
  std::string png;   // write the chart here too ("" = no chart)
  std::string near;  // "X,Y[,Z]": only places whose pose lies within `radius` of it
  double radius = 0;
};

CLI::App* RegisterDynamics(CLI::App& app, DynamicsFlags* flags);
int RunDynamics(const Connection& connection, const DynamicsFlags& flags, bool json, CliIo& io);

}  // namespace placedb::client
