#include "client/format.h"

#include <google/protobuf/util/json_util.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <numeric>

#include "core/base/stats.h"

namespace placedb::client {

LatencySummary Summarize(std::vector<double> samples) {
  LatencySummary summary;
  summary.count = samples.size();
  if (samples.empty()) return summary;
  std::sort(samples.begin(), samples.end());
  summary.mean = std::accumulate(samples.begin(), samples.end(), 0.0) / double(samples.size());
  summary.p50 = PercentileOfSorted(samples, 0.50);
  summary.p90 = PercentileOfSorted(samples, 0.90);
  summary.p99 = PercentileOfSorted(samples, 0.99);
  summary.max = samples.back();
  return summary;
}

nlohmann::json ToJson(const LatencySummary& summary) {
  auto round3 = [](double v) { return std::round(v * 1000.0) / 1000.0; };
  return {{"count", summary.count},     {"mean", round3(summary.mean)},
          {"p50", round3(summary.p50)}, {"p90", round3(summary.p90)},
          {"p99", round3(summary.p99)}, {"max", round3(summary.max)}};
}

const std::vector<StageField>& StageFields() {
  static const std::vector<StageField> fields = {
      {"queue", &v1::StageTimings::queue_ms},
      {"decode", &v1::StageTimings::decode_ms},
      {"detect", &v1::StageTimings::detect_ms},
      {"extract", &v1::StageTimings::extract_ms},
      {"depth", &v1::StageTimings::depth_ms},
      {"refine", &v1::StageTimings::refine_ms},
      {"filter", &v1::StageTimings::filter_ms},
      {"transform", &v1::StageTimings::transform_ms},
      {"search", &v1::StageTimings::search_ms},
      {"verify", &v1::StageTimings::verify_ms},
      {"pose", &v1::StageTimings::pose_ms},
      {"store", &v1::StageTimings::store_ms},
      {"loop_closure", &v1::StageTimings::loop_closure_ms},
      {"total", &v1::StageTimings::total_ms}};
  return fields;
}

std::string FormatTimings(const v1::StageTimings& timings) {
  std::string text;
  for (const StageField& field : StageFields()) {
    const double ms = (timings.*field.get)();
    if (ms <= 0 && std::string(field.name) != "total") continue;
    if (!text.empty()) text += "  ";
    text += std::string(field.name) + " " + FormatDouble(ms, 2);
  }
  return text;
}

std::string FormatDouble(double value, int decimals) {
  char buffer[64];
  std::snprintf(buffer, sizeof buffer, "%.*f", decimals, value);
  return buffer;
}

std::string FormatBytes(uint64_t bytes) {
  static const char* const kUnits[] = {"B", "KiB", "MiB", "GiB", "TiB"};
  double value = double(bytes);
  size_t unit = 0;
  while (value >= 1024 && unit + 1 < std::size(kUnits)) {
    value /= 1024;
    ++unit;
  }
  return unit == 0 ? std::to_string(bytes) + " B" : FormatDouble(value, 1) + " " + kUnits[unit];
}

std::string FormatDuration(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0) return "?";
  if (seconds < 60) return FormatDouble(seconds, 1) + "s";
  const int64_t whole = int64_t(seconds + 0.5);
  char buffer[64];
  if (whole < 3600) {
    std::snprintf(buffer, sizeof buffer, "%lldm%02llds", (long long)(whole / 60),
                  (long long)(whole % 60));
  } else {
    std::snprintf(buffer, sizeof buffer, "%lldh%02lldm", (long long)(whole / 3600),
                  (long long)(whole % 3600 / 60));
  }
  return buffer;
}

std::string FormatUnixNs(int64_t unix_ns) {
  if (unix_ns == 0) return "-";
  const std::time_t seconds = std::time_t(unix_ns / 1'000'000'000);
  const int millis = int((unix_ns % 1'000'000'000) / 1'000'000);
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  char buffer[64];
  std::snprintf(buffer, sizeof buffer, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", utc.tm_year + 1900,
                utc.tm_mon + 1, utc.tm_mday, utc.tm_hour, utc.tm_min, utc.tm_sec, std::abs(millis));
  return buffer;
}

std::string FormatUnixMs(int64_t unix_ms) {
  return FormatUnixNs(unix_ms * 1'000'000);
}

namespace {

std::string SignedMetres(double metres) {
  return (metres >= 0 ? "+" : "") + FormatDouble(metres, 2) + " m";
}

std::string Band(const v1::DepthState& depth) {
  std::string text =
      FormatDouble(depth.band_near_m(), 2) + "-" + FormatDouble(depth.band_far_m(), 2) + " m";
  return depth.band_source().empty() ? text : depth.band_source() + " " + text;
}

}  // namespace

std::string FormatDepthState(const v1::DepthState& depth) {
  std::string text = "frame " + std::to_string(depth.frame()) + ": mean " +
                     FormatDouble(depth.mean_depth_m(), 2) + " m";
  if (depth.warming_up()) {
    text += ", warming up";
  } else {
    text += ", static " + FormatDouble(depth.static_level_m(), 2) + " m (" +
            SignedMetres(depth.difference_m()) + ")";
  }
  text += ", count " + std::to_string(depth.count());
  if (depth.removing()) {
    text += ", removing " + Band(depth);
  } else if (depth.deviating()) {
    text += ", deviating";
  }
  text += ", " + FormatDouble(depth.valid_fraction() * 100, 0) + "% valid";
  return text;
}

std::string FormatDepthRemoval(const v1::FrameCounts& counts, const v1::DepthState& depth) {
  if (counts.depth_removed() == 0) return "";
  return "depth -" + std::to_string(counts.depth_removed()) + " (" + Band(depth) + ")";
}

std::string FormatRelativePose(const v1::RelativePose& pose) {
  if (pose.transform_size() != 16)
    return "(malformed: " + std::to_string(pose.transform_size()) + " transform values)";
  const auto& t = pose.transform();
  // The rotation angle from the trace of R (clamped against rounding).
  const double trace = t[0] + t[5] + t[10];
  const double angle_deg =
      std::acos(std::clamp((trace - 1.0) / 2.0, -1.0, 1.0)) * 180.0 / 3.14159265358979323846;
  std::string text = "t (" + FormatDouble(t[3], 3) + ", " + FormatDouble(t[7], 3) + ", " +
                     FormatDouble(t[11], 3) + (pose.metric() ? ") m, " : ") (direction), ");
  text += FormatDouble(angle_deg, 2) + " deg, " + pose.solver() + ", " +
          std::to_string(pose.inliers()) + " inliers, rms " + FormatDouble(pose.rms_error_px(), 2) +
          " px";
  return text;
}

std::string FormatLoopClosure(const v1::LoopClosure& loop) {
  // The agent's first loop-closure frame since the server started replays its earlier places.
  const std::string replayed =
      loop.replayed() > 0 ? " [" + std::to_string(loop.replayed()) + " earlier places replayed]"
                          : "";
  if (loop.merged()) return "merged into " + std::to_string(loop.place_id()) + replayed;
  if (loop.loop_found()) {
    return "loop: place " + std::to_string(loop.loop_place_id()) + " (posterior " +
           FormatDouble(loop.loop_posterior(), 3) +
           (loop.loop_inliers() > 0 ? ", " + std::to_string(loop.loop_inliers()) + " inliers"
                                    : std::string()) +
           ")" + (loop.has_loop_pose() ? ", pose " + FormatRelativePose(loop.loop_pose()) : "") +
           replayed;
  }
  if (loop.loop_rejected()) {
    return "loop to place " + std::to_string(loop.rejected_place_id()) + " failed verification (" +
           std::to_string(loop.loop_inliers()) + " inliers)" + replayed;
  }
  if (loop.best_place_id() == 0) return "no loop" + replayed;
  return "no loop (best place " + std::to_string(loop.best_place_id()) + ", posterior " +
         FormatDouble(loop.best_posterior(), 3) + ")" + replayed;
}

nlohmann::json DepthStateJson(const v1::DepthState& depth) {
  return {{"frame", depth.frame()},
          {"mean_depth_m", depth.mean_depth_m()},
          {"static_level_m", depth.static_level_m()},
          {"difference_m", depth.difference_m()},
          {"count", depth.count()},
          {"warming_up", depth.warming_up()},
          {"deviating", depth.deviating()},
          {"removing", depth.removing()},
          // float32 on the wire: rounded, so 1.2 prints as 1.2 and not 1.2000000476837158
          {"band_near_m", std::round(double(depth.band_near_m()) * 1e4) / 1e4},
          {"band_far_m", std::round(double(depth.band_far_m()) * 1e4) / 1e4},
          {"band_source", depth.band_source()},
          {"valid_fraction", depth.valid_fraction()}};
}

nlohmann::json LoopClosureJson(const v1::LoopClosure& loop) {
  return {{"merged", loop.merged()},
          {"place_id", loop.place_id()},
          {"loop_found", loop.loop_found()},
          {"loop_place_id", loop.loop_place_id()},
          {"loop_posterior", loop.loop_posterior()},
          {"best_place_id", loop.best_place_id()},
          {"best_posterior", loop.best_posterior()},
          {"candidates", loop.candidates()},
          {"retrieved", loop.retrieved()},
          {"transferred", loop.transferred()},
          {"replayed", loop.replayed()},
          {"loop_inliers", loop.loop_inliers()},
          {"loop_rejected", loop.loop_rejected()},
          {"rejected_place_id", loop.rejected_place_id()}};
}

Table::Table(std::vector<std::string> headers) {
  for (std::string& header : headers) {
    const bool right = !header.empty() && header[0] == '>';
    right_.push_back(right);
    headers_.push_back(right ? header.substr(1) : header);
  }
}

void Table::Add(std::vector<std::string> row) {
  row.resize(headers_.size());
  rows_.push_back(std::move(row));
}

void Table::Print(std::ostream& out, const std::string& indent, bool header) const {
  std::vector<size_t> width(headers_.size());
  for (size_t c = 0; c < headers_.size(); ++c) width[c] = headers_[c].size();
  for (const auto& row : rows_) {
    for (size_t c = 0; c < row.size(); ++c) width[c] = std::max(width[c], row[c].size());
  }
  auto line = [&](const std::vector<std::string>& cells) {
    std::string text = indent;
    for (size_t c = 0; c < cells.size(); ++c) {
      const std::string pad(width[c] - cells[c].size(), ' ');
      if (c > 0) text += "  ";
      text += right_[c] ? pad + cells[c] : cells[c] + pad;
    }
    while (!text.empty() && text.back() == ' ') text.pop_back();
    out << text << '\n';
  };
  if (header) line(headers_);
  for (const auto& row : rows_) line(row);
}

void PrintKeyValues(std::ostream& out, const std::string& title,
                    const std::vector<std::pair<std::string, std::string>>& rows) {
  out << title << '\n';
  Table table({"", ""});
  for (const auto& [key, value] : rows) table.Add({key, value});
  table.Print(out, "  ", /*header=*/false);
}

std::string ProtoJson(const google::protobuf::Message& message, bool one_line) {
  google::protobuf::util::JsonPrintOptions options;
  options.add_whitespace = !one_line;
  options.always_print_primitive_fields = true;
  options.preserve_proto_field_names = true;
  std::string json;
  (void)google::protobuf::util::MessageToJsonString(message, &json, options);
  while (!json.empty() && json.back() == '\n') json.pop_back();
  return json;
}

}  // namespace placedb::client
