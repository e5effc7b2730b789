#include "client/commands/places.h"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <nlohmann/json.hpp>
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
  CLI::App* place = app.add_subcommand("place", "get or delete one stored place");
  place->require_subcommand(1);
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
