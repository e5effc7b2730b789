#include "client/commands/query.h"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <array>
#include <fstream>
#include <nlohmann/json.hpp>

#include "client/commands/common.h"
#include "client/format.h"
#include "client/frame_source.h"

namespace placedb::client {

namespace {

bool AddDepth(const DepthFlags& flags, v1::Observation* observation, std::string* error) {
  if (flags.file.empty()) {
    if (flags.scale != 0 || !flags.intrinsics.empty()) {
      *error = "--depth-scale and --intrinsics describe a depth image: they need --depth FILE";
      return false;
    }
    return true;
  }
  v1::DepthImage* depth = observation->mutable_depth();
  if (!ReadDepthImage(flags.file, depth, error)) return false;
  depth->set_scale(flags.scale);
  if (!flags.intrinsics.empty() &&
      !ParseIntrinsics(flags.intrinsics, depth->mutable_intrinsics(), error)) {
    return false;
  }
  return true;
}

// Boxes for `query --boxes FILE.json`: a list (or {"boxes": [...]}) of
//   {"class": "person" | 0, "confidence": 0.9, "rect": [x, y, w, h]}
// ("class_name"/"class_id" are accepted too, and "rect" may be {"x","y","width","height"}).
bool ReadBoxes(const std::string& path, v1::Observation* observation, std::string* error) {
  std::ifstream in(path);
  if (!in) {
    *error = "--boxes: cannot read " + path;
    return false;
  }
  nlohmann::json doc = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded()) {
    *error = path + ": not valid JSON";
    return false;
  }
  if (doc.is_object() && doc.contains("boxes")) doc = doc["boxes"];
  if (!doc.is_array()) {
    *error = path + ": expected a list of boxes (or {\"boxes\": [...]})";
    return false;
  }
  for (size_t i = 0; i < doc.size(); ++i) {
    const nlohmann::json& b = doc[i];
    const std::string where = path + ": boxes[" + std::to_string(i) + "]";
    if (!b.is_object()) {
      *error = where + ": expected an object";
      return false;
    }
    v1::Box* box = observation->add_boxes();
    const nlohmann::json* label = nullptr;
    for (const char* key : {"class", "class_name", "class_id"}) {
      if (b.contains(key)) label = &b[key];
    }
    if (label == nullptr) {
      *error = where + ": needs \"class\" (a COCO name or id)";
      return false;
    }
    if (label->is_string()) {
      box->set_class_name(label->get<std::string>());
    } else if (label->is_number_integer()) {
      box->set_class_id(label->get<int>());
    } else {
      *error = where + ": \"class\" must be a name or an integer id";
      return false;
    }
    const nlohmann::json confidence = b.value("confidence", nlohmann::json(1.0));
    if (!confidence.is_number()) {
      *error = where + ": \"confidence\" must be a number";
      return false;
    }
    box->set_confidence(confidence.get<float>());
    std::array<double, 4> rect{};
    const nlohmann::json r = b.contains("rect") ? b["rect"] : b;
    if (r.is_array() && r.size() == 4 &&
        std::all_of(r.begin(), r.end(), [](const auto& v) { return v.is_number(); })) {
      for (size_t k = 0; k < 4; ++k) rect[k] = r[k].get<double>();
    } else if (r.is_object() && r.contains("x") && r.contains("y") && r.contains("width") &&
               r.contains("height") && r["x"].is_number() && r["y"].is_number() &&
               r["width"].is_number() && r["height"].is_number()) {
      rect = {r["x"].get<double>(), r["y"].get<double>(), r["width"].get<double>(),
              r["height"].get<double>()};
    } else {
      *error = where + ": needs \"rect\": [x, y, width, height]";
      return false;
    }
    box->mutable_rect()->set_x(float(rect[0]));
    box->mutable_rect()->set_y(float(rect[1]));
    box->mutable_rect()->set_width(float(rect[2]));
    box->mutable_rect()->set_height(float(rect[3]));
  }
  return true;
}

}  // namespace

CLI::App* RegisterQuery(CLI::App& app, QueryFlags* flags) {
  CLI::App* query = app.add_subcommand("query", "ranked matches of an image against a map");
  query->add_option("MAP", flags->map, "map name")->required();
  query->add_option("IMAGE", flags->image, "image file")->required();
  query->add_option("--top-k", flags->top_k, "matches to return")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  query->add_option("--boxes", flags->boxes,
                    "dynamic-object boxes, JSON: [{\"class\": \"person\", \"confidence\": 0.9, "
                    "\"rect\": [x, y, w, h]}, ...]");
  query->add_flag("--verified-only", flags->verified_only,
                  "drop candidates that fail geometric verification (verified on request on a map "
                  "that does not verify)");
  query->add_option("--agent-id", flags->agent_id, "the querying agent")->capture_default_str();
  query->add_flag("--exclude-same-agent", flags->exclude_same_agent,
                  "skip places stored by --agent-id");
  query->add_flag("--correspondences", flags->correspondences,
                  "verified matches' inlier keypoint pairs and the query's keypoints (--json)");
  query->add_option("--depth", flags->depth.file,
                    "depth image registered to IMAGE (16-bit PNG/PGM/TIFF or float32 TIFF)");
  query
      ->add_option("--depth-scale", flags->depth.scale,
                   "metres per depth unit (default: the map's, 0.001 for 16-bit)")
      ->check(CLI::Range(1e-6, 100.0));
  query->add_option("--intrinsics", flags->depth.intrinsics,
                    "colour camera intrinsics fx,fy,cx,cy in pixels (sent with the depth)");
  query->add_option("--camera", flags->camera,
                    "the camera fx,fy,cx,cy in pixels (pinhole, IMAGE's size): each verified "
                    "match's relative pose to its place (with --depth or --intrinsics too)");
  return query;
}

int RunQuery(const Connection& connection, const QueryFlags& flags, bool json, CliIo& io) {
  v1::QueryRequest request;
  request.set_map(flags.map);
  v1::Observation* observation = request.mutable_observation();
  std::string error;
  std::string bytes;
  if (!ReadImageBytes(flags.image, &bytes, &error)) return UsageError(io, error);
  observation->mutable_encoded_image()->set_data(std::move(bytes));
  observation->set_agent_id(flags.agent_id);
  if (!flags.boxes.empty() && !ReadBoxes(flags.boxes, observation, &error)) {
    return UsageError(io, error);
  }
  if (!AddDepth(flags.depth, observation, &error)) return UsageError(io, error);
  if (!flags.camera.empty() && !ParseCamera(flags.camera, observation->mutable_camera(), &error)) {
    return UsageError(io, error);
  }
  request.mutable_options()->set_top_k(uint32_t(flags.top_k));
  request.mutable_options()->set_verified_only(flags.verified_only);
  request.mutable_options()->set_exclude_same_agent(flags.exclude_same_agent);
  request.mutable_options()->set_include_correspondences(flags.correspondences);

  auto context = connection.NewContext();
  v1::QueryResponse response;
  const Clock::time_point start = Clock::now();
  const grpc::Status status = connection.stub()->Query(context.get(), request, &response);
  const double round_trip_ms =
      std::chrono::duration<double, std::milli>(Clock::now() - start).count();
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(response) << '\n';
    return kExitOk;
  }
  io.out << "query " << flags.image << " in map '" << flags.map
         << "': " << FormatCounts(response.counts()) << '\n';
  if (response.has_depth()) {
    io.out << "depth: " << FormatDepthState(response.depth());
    const std::string removal = FormatDepthRemoval(response.counts(), response.depth());
    if (!removal.empty()) io.out << "; " << removal;
    io.out << '\n';
  }
  if (!response.valid()) {
    io.out << "not a valid place: " << response.rejection() << '\n';
  } else if (response.matches_size() == 0) {
    io.out << "no matches\n";
  } else {
    Table table(
        {">RANK", ">PLACE", ">SCORE", "AGENT", ">SEQUENCE", "TIMESTAMP", ">INLIERS", "VERIFIED"});
    int rank = 0;
    for (const v1::Match& match : response.matches()) {
      table.Add({std::to_string(++rank), std::to_string(match.place_id()),
                 FormatDouble(match.score(), 4), match.metadata().agent_id(),
                 std::to_string(match.metadata().sequence()),
                 FormatUnixNs(match.metadata().timestamp_ns()), std::to_string(match.inliers()),
                 match.verified() ? "yes" : "no"});
    }
    table.Print(io.out);
    for (const v1::Match& match : response.matches()) {
      if (match.has_relative_pose()) {
        io.out << "pose of place " << match.place_id() << ": "
               << FormatRelativePose(match.relative_pose()) << '\n';
      } else if (match.verified() && !match.pose_unavailable().empty()) {
        io.out << "no pose for place " << match.place_id() << ": " << match.pose_unavailable()
               << '\n';
      }
    }
    if (std::any_of(response.matches().begin(), response.matches().end(),
                    [](const v1::Match& match) { return match.score() > 1.0; })) {
      io.out << "scores above 1: the short-term bonus: a place observed within the map's "
                "short-term horizon (60 s by default) of this query's timestamp scores on its "
                "static words plus weight x the similarity of the objects both frames saw "
                "(filter.short_term; docs/cli.md, \"Scores\")\n";
    }
  }
  if (flags.correspondences) {
    io.out << "keypoints: " << response.query_keypoints_size() << " kept, "
           << response.query_dropped_keypoints_size() << " dropped, image "
           << response.image_width() << "x" << response.image_height()
           << " (--json for the correspondences)\n";
  }
  for (const v1::UsedBox& box : response.boxes_used()) {
    io.out << "box used: " << FormatBox(box) << '\n';
  }
  io.out << "timings (ms): " << FormatTimings(response.timings()) << "; round trip "
         << FormatDouble(round_trip_ms, 2) << '\n';
  return kExitOk;
}

}  // namespace placedb::client
