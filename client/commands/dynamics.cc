#include "client/commands/dynamics.h"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <map>
#include <sstream>
#include <vector>

#include "client/commands/common.h"
#include "client/dynamics_chart.h"
#include "client/format.h"
#include "client/image_io.h"
#include "proto/names.h"

namespace placedb::client {

namespace {

constexpr const char* kWeekdayNames[] = {"mon", "tue", "wed", "thu", "fri", "sat", "sun"};

// "8-10" -> (8, 10); false when not two hours 0..23.
bool ParseHours(const std::string& text, uint32_t* first, uint32_t* last) {
  const size_t dash = text.find('-');
  if (dash == std::string::npos) return false;
  try {
    size_t used = 0;
    const int a = std::stoi(text.substr(0, dash), &used);
    if (used != dash) return false;
    const std::string rest = text.substr(dash + 1);
    const int b = std::stoi(rest, &used);
    if (used != rest.size() || a < 0 || a > 23 || b < 0 || b > 23) return false;
    *first = uint32_t(a);
    *last = uint32_t(b);
    return true;
  } catch (const std::exception&) {
    return false;
  }
}

// "mon,fri" -> bits; 0 when a name is unknown.
uint32_t ParseWeekdays(const std::string& text) {
  uint32_t bits = 0;
  std::stringstream list(text);
  for (std::string day; std::getline(list, day, ',');) {
    const auto* found = std::find(std::begin(kWeekdayNames), std::end(kWeekdayNames), day);
    if (found == std::end(kWeekdayNames)) return 0;
    bits |= 1u << (found - std::begin(kWeekdayNames));
  }
  return bits;
}

// "1.5,2[,0]" -> the point; false unless two or three numbers.
bool ParsePoint(const std::string& text, v1::Pose* point) {
  std::vector<double> values;
  std::stringstream list(text);
  for (std::string part; std::getline(list, part, ',');) {
    try {
      size_t used = 0;
      values.push_back(std::stod(part, &used));
      if (used != part.size()) return false;
    } catch (const std::exception&) {
      return false;
    }
  }
  if (values.size() < 2 || values.size() > 3) return false;
  point->set_x(values[0]);
  point->set_y(values[1]);
  point->set_z(values.size() == 3 ? values[2] : 0);
  return true;
}

std::string ClassLabel(int class_id) {
  return wire::DynamicClassName(class_id);
}

// "person 12, car 4": each class with the frames it was seen in.
std::string FormatClasses(const v1::DynamicStatistics& statistics) {
  std::string text;
  for (const v1::DynamicClassCount& c : statistics.classes()) {
    text +=
        (text.empty() ? "" : ", ") + ClassLabel(c.class_id()) + " " + std::to_string(c.frames());
  }
  return text.empty() ? "-" : text;
}

std::string Percent(double share) {
  return FormatDouble(100.0 * share, 1) + "%";
}

// The page's places' thumbnails (GetPlace include_thumbnail), decoded; places without one (maps
// that keep none, places removed meanwhile) are left out and drawn as placeholders.
grpc::Status FetchThumbnails(const Connection& connection, const std::string& map,
                             const v1::GetDynamicsResponse& page,
                             std::map<uint32_t, cv::Mat>* thumbnails) {
  for (int i = 0; i < page.places_size() && i < kDynamicsChartMaxBars; ++i) {
    v1::GetPlaceRequest request;
    request.set_map(map);
    request.set_place_id(page.places(i).place_id());
    request.set_include_thumbnail(true);
    auto context = connection.NewContext();
    v1::Place place;
    const grpc::Status status = connection.stub()->GetPlace(context.get(), request, &place);
    if (status.error_code() == grpc::StatusCode::NOT_FOUND) continue;
    if (!status.ok()) return status;
    const std::string& jpeg = place.thumbnail().jpeg();
    if (jpeg.empty()) continue;
    cv::Mat decoded;
    std::string error;
    if (DecodeImageBytes(jpeg, ImageRead::kColor, &decoded, &error))
      (*thumbnails)[place.place_id()] = decoded;
  }
  return grpc::Status::OK;
}

std::string MeasureName(const v1::GetDynamicsRequest& request) {
  switch (request.measure()) {
    case v1::DYNAMICS_MEASURE_CLASS_SHARE:
      return "share of frames with " + ClassLabel(request.class_id());
    case v1::DYNAMICS_MEASURE_HOUR_WINDOW:
      return "mean coverage " + std::to_string(request.first_hour()) + "-" +
             std::to_string(request.last_hour()) + " h UTC";
    default:
      return "mean coverage";
  }
}

int WriteChart(const Connection& connection, const DynamicsFlags& flags,
               const v1::GetDynamicsRequest& request, const v1::GetDynamicsResponse& response,
               CliIo& io) {
  std::map<uint32_t, cv::Mat> thumbnails;
  const grpc::Status fetched = FetchThumbnails(connection, flags.map, response, &thumbnails);
  if (!fetched.ok()) return RpcFailed(io, fetched);
  const cv::Mat chart =
      DrawDynamicsChart("map '" + flags.map + "'", MeasureName(request), response, thumbnails);
  std::string error;
  if (!WriteImageFile(flags.png, chart, &error)) return UsageError(io, "--png: " + error);
  return kExitOk;
}

}  // namespace

CLI::App* RegisterDynamics(CLI::App& app, DynamicsFlags* flags) {
  CLI::App* command = app.add_subcommand(
      "dynamics", "a map's dynamic-object statistics and its places ranked by coverage");
  command->add_option("MAP", flags->map, "map name")->required();
  command->add_option("--class", flags->class_label,
                      "rank by the share of frames with this class (COCO name or id)");
  command->add_option("--hours", flags->hours,
                      "rank by mean coverage in these UTC hours, FIRST-LAST (22-2 wraps midnight)");
  command->add_option("--weekdays", flags->weekdays, "with --hours: mon,tue,... (default: all)");
  command->add_option("--limit", flags->limit, "places per page (1..1000)");
  command->add_option("--offset", flags->offset, "first place of the page");
  command->add_option("--min-observations", flags->min_observations,
                      "leave out places observed fewer times (in the window)");
  command->add_option("--near", flags->near,
                      "only places whose pose lies within --radius of X,Y[,Z] (the poses' units)");
  command->add_option("--radius", flags->radius, "with --near: the distance");
  command->add_option("--png", flags->png,
                      "also draw coverage by hour, weekday x hour, and the page's top places "
                      "(with thumbnails) into this PNG file");
  return command;
}

int RunDynamics(const Connection& connection, const DynamicsFlags& flags, bool json, CliIo& io) {
  v1::GetDynamicsRequest request;
  request.set_map(flags.map);
  request.set_limit(flags.limit);
  request.set_offset(flags.offset);
  request.set_min_observations(flags.min_observations);
  request.set_include_statistics(true);
  if (!flags.class_label.empty() && !flags.hours.empty()) {
    return UsageError(io, "--class and --hours rank differently: give one");
  }
  if (!flags.class_label.empty()) {
    request.set_measure(v1::DYNAMICS_MEASURE_CLASS_SHARE);
    auto id = wire::ParseDynamicClass(flags.class_label);
    if (id.ok()) {
      request.set_class_id(*id);
    } else {
      try {
        size_t used = 0;
        request.set_class_id(std::stoi(flags.class_label, &used));
        if (used != flags.class_label.size()) throw std::invalid_argument("trailing");
      } catch (const std::exception&) {
        return UsageError(io, "--class: '" + flags.class_label + "' is not a COCO class");
      }
    }
  } else if (!flags.hours.empty()) {
    request.set_measure(v1::DYNAMICS_MEASURE_HOUR_WINDOW);
    uint32_t first = 0, last = 0;
    if (!ParseHours(flags.hours, &first, &last)) {
      return UsageError(io, "--hours: expected FIRST-LAST with hours 0..23, e.g. 8-10");
    }
    request.set_first_hour(first);
    request.set_last_hour(last);
    if (!flags.weekdays.empty()) {
      const uint32_t bits = ParseWeekdays(flags.weekdays);
      if (bits == 0) return UsageError(io, "--weekdays: expected names among mon,...,sun");
      request.set_weekdays(bits);
    }
  } else if (!flags.weekdays.empty()) {
    return UsageError(io, "--weekdays needs --hours");
  }
  if (flags.near.empty() != (flags.radius == 0)) {
    return UsageError(io, "--near X,Y[,Z] and --radius R go together");
  }
  if (!flags.near.empty()) {
    if (!ParsePoint(flags.near, request.mutable_near())) {
      return UsageError(io, "--near: expected X,Y or X,Y,Z, e.g. 12.5,-3");
    }
    request.set_near_radius(flags.radius);
  }
  auto context = connection.NewContext();
  v1::GetDynamicsResponse response;
  const grpc::Status status = connection.stub()->GetDynamics(context.get(), request, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(response) << '\n';
    if (!flags.png.empty()) return WriteChart(connection, flags, request, response, io);
    return kExitOk;
  }
  const v1::DynamicStatistics& map = response.map();
  PrintKeyValues(
      io.out, "dynamic objects in map '" + flags.map + "'",
      {{"frames", std::to_string(map.observations())},
       {"coverage",
        "mean " + Percent(map.mean_coverage()) + ", max " + Percent(map.max_coverage())},
       {"classes (frames)", FormatClasses(map)},
       {"untimed / future", std::to_string(map.untimed()) + " / " + std::to_string(map.future())},
       {"invalid frames", std::to_string(response.invalid().observations()) + ", mean coverage " +
                              Percent(response.invalid().mean_coverage())}});
  Table table({">RANK", ">PLACE", ">SCORE", ">FRAMES", ">MEAN", ">MAX", "LAST SEEN", "CLASSES"});
  uint64_t rank = flags.offset;
  for (const v1::RankedPlace& place : response.places()) {
    const v1::DynamicStatistics& s = place.statistics();
    table.Add({std::to_string(++rank), std::to_string(place.place_id()),
               FormatDouble(place.score(), 3), std::to_string(place.support()),
               Percent(s.mean_coverage()), Percent(s.max_coverage()),
               FormatUnixNs(s.last_timestamp_ns()), FormatClasses(s)});
  }
  io.out << '\n';
  if (table.empty()) {
    io.out << "no place ranked on this page (" << response.ranked() << " ranked in all)\n";
  } else {
    table.Print(io.out);
    io.out << response.ranked() << " places ranked";
    if (response.next_offset()) io.out << "; next page: --offset " << response.next_offset();
    io.out << '\n';
  }
  if (!flags.png.empty()) return WriteChart(connection, flags, request, response, io);
  return kExitOk;
}

}  // namespace placedb::client
