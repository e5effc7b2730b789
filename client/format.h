// Output helpers shared by the commands: latency statistics, human units, aligned tables, and the
// proto3 JSON of a response (enum names: proto/names.h).
#pragma once

#include <google/protobuf/message.h>

#include <cstdint>
#include <map>
#include <nlohmann/json.hpp>
#include <ostream>
#include <string>
#include <vector>

#include "proto/names.h"
#include "proto/placedb.pb.h"

namespace placedb::client {

namespace v1 = ::placedb::v1;

// Percentiles by nearest rank over every sample (no sampling, no interpolation).
struct LatencySummary {
  size_t count = 0;
  double mean = 0, p50 = 0, p90 = 0, p99 = 0, max = 0;
};
LatencySummary Summarize(std::vector<double> samples);
nlohmann::json ToJson(const LatencySummary& summary);

// The StageTimings fields, in pipeline order, with accessors.
struct StageField {
  const char* name;  // "queue", "decode", ..., "total"
  double (v1::StageTimings::*get)() const;
};
const std::vector<StageField>& StageFields();
// "queue 0.02  decode 3.10  ...  total 17.52" (ms); stages that took no time are left out.
std::string FormatTimings(const v1::StageTimings& timings);

std::string FormatDouble(double value, int decimals);
std::string FormatBytes(uint64_t bytes);     // "1.5 MiB"
std::string FormatDuration(double seconds);  // "1m05s", "3.2s"
std::string FormatUnixNs(int64_t unix_ns);   // "2025-11-22T00:40:12.123Z", "-" for 0
std::string FormatUnixMs(int64_t unix_ms);

// The depth state of a frame (Algorithm 1, docs/rgbd.md):
//   "frame 12: mean 2.31 m, static 2.45 m (-0.14 m), count 3, removing 1.20-1.60 m
//    (appeared_layer), 97% valid"
std::string FormatDepthState(const v1::DepthState& depth);
// The short form for per-frame lines, "" when nothing was removed: "depth -37 (appeared_layer
// 1.20-1.60 m)".
std::string FormatDepthRemoval(const v1::FrameCounts& counts, const v1::DepthState& depth);
// "loop: place 3 (posterior 0.412)", "merged into 11", "no loop (best place 3, posterior 0.051)".
std::string FormatLoopClosure(const v1::LoopClosure& loop);
// "t (-0.201, -0.084, 0.407) m, 25.81 deg, pnp_place_depth, 92 inliers, rms 1.95 px": the
// translation (metres, or a unit direction for an essential-matrix pose) and rotation angle.
std::string FormatRelativePose(const v1::RelativePose& pose);
// The same, as JSON objects with numbers as numbers (ingest's --json output).
nlohmann::json DepthStateJson(const v1::DepthState& depth);
nlohmann::json LoopClosureJson(const v1::LoopClosure& loop);

// A left/right aligned text table.
class Table {
 public:
  // A header starting with '>' is right-aligned (numbers); the '>' is not printed.
  explicit Table(std::vector<std::string> headers);
  void Add(std::vector<std::string> row);
  void Print(std::ostream& out, const std::string& indent = "", bool header = true) const;
  bool empty() const { return rows_.empty(); }

 private:
  std::vector<std::string> headers_;
  std::vector<bool> right_;
  std::vector<std::vector<std::string>> rows_;
};

// "title" then "  key  value" lines with the values aligned.
void PrintKeyValues(std::ostream& out, const std::string& title,
                    const std::vector<std::pair<std::string, std::string>>& rows);

// The message in proto3 JSON, field names as in the proto, defaults included, indented (or on one
// line, for JSON lines). (64-bit integers are strings, per the proto3 JSON mapping.)
std::string ProtoJson(const google::protobuf::Message& message, bool one_line = false);

}  // namespace placedb::client
