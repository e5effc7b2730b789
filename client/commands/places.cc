#include "client/commands/places.h"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstring>
#include <ctime>
#include <fstream>
#include <iomanip>
#include <nlohmann/json.hpp>
#include <sstream>
#include <tuple>
#include <utility>
#include <vector>

#include "client/commands/common.h"
#include "client/format.h"

namespace placedb::client {

namespace {

using Rows = std::vector<std::pair<std::string, std::string>>;

std::string FormatPose(const v1::PlaceMetadata& metadata) {
  if (!metadata.has_pose()) return "-";
  const v1::Pose& p = metadata.pose();
  return "x " + FormatDouble(p.x(), 3) + ", y " + FormatDouble(p.y(), 3) + ", z " +
         FormatDouble(p.z(), 3) + "; q (" + FormatDouble(p.qx(), 3) + ", " +
         FormatDouble(p.qy(), 3) + ", " + FormatDouble(p.qz(), 3) + ", " + FormatDouble(p.qw(), 3) +
         ")";
}

// A little-endian float32 from 4 bytes (SiftFeatures.descriptors).
float LittleEndianFloat(const char* bytes) {
  uint32_t bits = 0;
  for (int b = 3; b >= 0; --b) bits = (bits << 8) | uint8_t(bytes[b]);
  float value = 0;
  std::memcpy(&value, &bits, sizeof value);
  return value;
}

// SIFT maps: the count, then the first keypoints with the start of their descriptors.
void AddSiftRows(const v1::SiftFeatures& sift, Rows* rows) {
  Rows& table = *rows;
  table.push_back({"features", std::to_string(sift.keypoints_size()) + " static SIFT keypoints, " +
                                   std::to_string(sift.descriptors().size()) +
                                   " descriptor bytes (128 float32 each), image " +
                                   std::to_string(sift.image_width()) + "x" +
                                   std::to_string(sift.image_height())});
  constexpr int kShown = 5, kValues = 8;
  const size_t per_keypoint = 128 * 4;
  for (int i = 0; i < std::min(kShown, sift.keypoints_size()); ++i) {
    const v1::Keypoint& k = sift.keypoints(i);
    std::string text = "(" + FormatDouble(k.x(), 1) + ", " + FormatDouble(k.y(), 1) + ") size " +
                       FormatDouble(k.size(), 1) + " angle " + FormatDouble(k.angle(), 1) +
                       " response " + FormatDouble(k.response(), 4) + " octave " +
                       std::to_string(k.octave());
    if (sift.descriptors().size() >= (size_t(i) + 1) * per_keypoint) {
      text += "; [";
      for (int v = 0; v < kValues; ++v) {
        const float value =
            LittleEndianFloat(sift.descriptors().data() + size_t(i) * per_keypoint + size_t(v) * 4);
        // OpenCV's SIFT values are whole numbers in [0, 255]; others keep 3 decimals.
        text += (v ? " " : "") + FormatDouble(value, value == std::round(value) ? 0 : 3);
      }
      text += " ...]";
    }
    table.push_back({"keypoint " + std::to_string(i), text});
  }
  if (sift.keypoints_size() > kShown) {
    table.push_back(
        {"", "... " + std::to_string(sift.keypoints_size() - kShown) + " more (--json for all)"});
  }
}

}  // namespace

PlaceCommands RegisterPlace(CLI::App& app, PlaceFlags* flags) {
  PlaceCommands commands;
  CLI::App* place = app.add_subcommand("place", "list, get or delete stored places");
  place->alias("places");
  place->require_subcommand(1);
  commands.list = place->add_subcommand("list", "a page of a map's places, newest first");
  commands.list->add_option("MAP", flags->map, "map name")->required();
  commands.list->add_option("--agent", flags->agent, "only this agent's places");
  commands.list->add_option("--from", flags->from,
                            "only places observed at or after this time (unix ns or UTC ISO 8601)");
  commands.list->add_option("--to", flags->to, "only places observed before this time");
  commands.list->add_option("--limit", flags->limit, "places per page, 1-1000 (default 100)");
  commands.list->add_option("--before", flags->before,
                            "resume below this place id (the previous page's next)");
  commands.get = place->add_subcommand("get", "a place's metadata, counts and boxes");
  commands.get->add_option("MAP", flags->map, "map name")->required();
  commands.get->add_option("ID", flags->id, "place id")->required();
  commands.get->add_flag("--features", flags->features, "include the stored static features");
  commands.get->add_option("--thumbnail", flags->thumbnail,
                           "write the place's thumbnail (JPEG, dynamic objects blurred) to FILE");
  commands.remove = place->add_subcommand("delete", "remove a place durably");
  commands.remove->add_option("MAP", flags->map, "map name")->required();
  commands.remove->add_option("ID", flags->id, "place id")->required();
  return commands;
}

int PlaceGet(const Connection& connection, const std::string& map, uint32_t id, bool features,
             bool json, CliIo& io, const std::string& thumbnail_file) {
  auto context = connection.NewContext();
  v1::GetPlaceRequest request;
  request.set_map(map);
  request.set_place_id(id);
  request.set_include_features(features);
  request.set_include_thumbnail(!thumbnail_file.empty());
  v1::Place place;
  const grpc::Status status = connection.stub()->GetPlace(context.get(), request, &place);
  if (!status.ok()) return RpcFailed(io, status);
  if (!thumbnail_file.empty()) {
    if (!place.has_thumbnail()) {
      io.err << "error: place " << id << " in map '" << map
             << "' has no thumbnail (the map keeps none, or its frame had no pixels)\n";
      return kExitRpcError;
    }
    std::ofstream out(thumbnail_file, std::ios::binary | std::ios::trunc);
    out.write(place.thumbnail().jpeg().data(), std::streamsize(place.thumbnail().jpeg().size()));
    out.close();
    if (!out) return UsageError(io, "cannot write " + thumbnail_file);
  }
  if (json) {
    io.out << ProtoJson(place) << '\n';
    return kExitOk;
  }
  Rows table;
  table.push_back({"agent", place.metadata().agent_id()});
  table.push_back({"sequence", std::to_string(place.metadata().sequence())});
  table.push_back({"timestamp", FormatUnixNs(place.metadata().timestamp_ns())});
  table.push_back({"pose", FormatPose(place.metadata())});
  table.push_back({"descriptors", FormatCounts(place.counts())});
  for (const v1::UsedBox& box : place.boxes_used()) table.push_back({"box used", FormatBox(box)});
  if (features && place.has_sift_features()) {
    AddSiftRows(place.sift_features(), &table);
  } else if (features) {
    table.push_back({"features", std::to_string(place.features().keypoints_size()) +
                                     " static keypoints, " +
                                     std::to_string(place.features().descriptors().size()) +
                                     " descriptor bytes, image " +
                                     std::to_string(place.features().image_width()) + "x" +
                                     std::to_string(place.features().image_height())});
  }
  if (place.has_thumbnail()) {
    const v1::Thumbnail& t = place.thumbnail();
    table.push_back({"thumbnail", std::to_string(t.width()) + "x" + std::to_string(t.height()) +
                                      " of " + std::to_string(t.source_width()) + "x" +
                                      std::to_string(t.source_height()) + ", " +
                                      std::to_string(t.jpeg().size()) + " bytes, " +
                                      std::to_string(t.dropped_keypoints_size()) +
                                      " dropped keypoints, written to " + thumbnail_file});
  }
  PrintKeyValues(io.out, "place " + std::to_string(place.place_id()) + " in map '" + map + "'",
                 table);
  return kExitOk;
}

Result<int64_t> ParseTimeFlag(const std::string& text, const std::string& flag) {
  const auto bad = [&] {
    return Status::InvalidArgument(flag + ": '" + text +
                                   "' is neither unix nanoseconds nor a UTC time like "
                                   "2026-11-24T07:30:00Z");
  };
  if (text.empty()) return bad();
  if (std::all_of(text.begin(), text.end(), [](char c) { return c >= '0' && c <= '9'; })) {
    int64_t value = 0;
    const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (error != std::errc() || end != text.data() + text.size()) return bad();  // out of range
    return value;
  }
  std::tm tm{};
  std::istringstream in(text);
  in >> std::get_time(&tm, "%Y-%m-%dT%H:%M:%S");
  if (in.fail()) return bad();
  int64_t fraction_ns = 0;
  if (in.peek() == '.') {
    in.get();
    int digits = 0;
    while (std::isdigit(in.peek())) {
      const int digit = in.get() - '0';
      if (digits++ < 9) fraction_ns = fraction_ns * 10 + digit;
    }
    if (digits == 0) return bad();
    for (; digits < 9; ++digits) fraction_ns *= 10;
  }
  if (in.get() != 'Z' || in.peek() != std::char_traits<char>::eof()) return bad();
  const int64_t seconds = int64_t(timegm(&tm));
  if (seconds < 0) return bad();
  return seconds * 1'000'000'000 + fraction_ns;
}

int PlaceList(const Connection& connection, const PlaceFlags& flags, bool json, CliIo& io) {
  v1::ListPlacesRequest request;
  request.set_map(flags.map);
  request.set_agent_id(flags.agent);
  request.set_limit(flags.limit);
  request.set_before_place_id(flags.before);
  // Bad times are the caller's to fix before anything is sent; the server checks the rest.
  for (const auto& [text, flag, set] :
       {std::tuple{&flags.from, "--from", &v1::ListPlacesRequest::set_from_timestamp_ns},
        std::tuple{&flags.to, "--to", &v1::ListPlacesRequest::set_to_timestamp_ns}}) {
    if (text->empty()) continue;
    auto parsed = ParseTimeFlag(*text, flag);
    if (!parsed.ok()) return UsageError(io, parsed.status().message());
    (request.*set)(*parsed);
  }
  auto context = connection.NewContext();
  v1::ListPlacesResponse response;
  const grpc::Status status = connection.stub()->ListPlaces(context.get(), request, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(response) << '\n';
    return kExitOk;
  }
  Table table({">ID", "AGENT", ">SEQUENCE", "OBSERVED", ">KEPT", ">DROPPED", ">BOXES"});
  for (const v1::Place& place : response.places()) {
    table.Add({std::to_string(place.place_id()), place.metadata().agent_id(),
               std::to_string(place.metadata().sequence()),
               FormatUnixNs(place.metadata().timestamp_ns()), std::to_string(place.counts().kept()),
               std::to_string(place.counts().dynamic()), std::to_string(place.boxes_used_size())});
  }
  if (table.empty()) {
    io.out << "no places in this page\n";
  } else {
    table.Print(io.out);
  }
  if (response.next_before_place_id() != 0) {
    // A page may be short (each call examines a bounded range of ids): keep going until none.
    io.out << "next page: --before " << response.next_before_place_id() << '\n';
  }
  return kExitOk;
}

int PlaceDelete(const Connection& connection, const std::string& map, uint32_t id, bool json,
                CliIo& io) {
  auto context = connection.NewContext();
  v1::DeletePlaceRequest request;
  request.set_map(map);
  request.set_place_id(id);
  v1::DeletePlaceResponse response;
  const grpc::Status status = connection.stub()->DeletePlace(context.get(), request, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << nlohmann::json({{"deleted", {{"map", map}, {"place_id", id}}}}).dump(2) << '\n';
  } else {
    io.out << "deleted place " << id << " from map '" << map << "'\n";
  }
  return kExitOk;
}

}  // namespace placedb::client
