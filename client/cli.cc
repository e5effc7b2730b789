#include "client/cli.h"

#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <fstream>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>

#include "client/connection.h"
#include "client/format.h"
#include "client/frame_source.h"
#include "client/ingest.h"
#include "client/load.h"

namespace placedb::client {

namespace {

// ---- Helpers ------------------------------------------------------------------------------------

int RpcFailed(CliIo& io, const grpc::Status& status) {
  io.err << "error: " << Describe(status) << '\n';
  return kExitRpcError;
}

int UsageError(CliIo& io, const std::string& message) {
  io.err << "error: " << message << '\n';
  return kExitUsage;
}

// Box refinement spellings from the generated enum's own names (BOX_REFINEMENT_GRABCUT ->
// "grabcut"), so a value added to the proto is a CLI value too.
const std::map<std::string, v1::BoxRefinement>& BoxRefinementNames() {
  static const std::map<std::string, v1::BoxRefinement> names = [] {
    std::map<std::string, v1::BoxRefinement> out;
    const std::string prefix = "BOX_REFINEMENT_";
    for (int i = v1::BoxRefinement_MIN; i <= v1::BoxRefinement_MAX; ++i) {
      if (!v1::BoxRefinement_IsValid(i) || i == v1::BOX_REFINEMENT_UNSPECIFIED) continue;
      std::string name = v1::BoxRefinement_Name(v1::BoxRefinement(i)).substr(prefix.size());
      for (char& c : name) c = char(std::tolower(static_cast<unsigned char>(c)));
      out.emplace(name, v1::BoxRefinement(i));
    }
    return out;
  }();
  return names;
}

// Short CLI spellings of the API enums.
const std::map<std::string, v1::FilterMethod>& FilterNames() {
  static const std::map<std::string, v1::FilterMethod> names = {
      {"none", v1::FILTER_METHOD_NONE},
      {"keypoint_in_box", v1::FILTER_METHOD_KEYPOINT_IN_BOX},
      {"corner_distance", v1::FILTER_METHOD_CORNER_DISTANCE},
      {"exact_coverage", v1::FILTER_METHOD_EXACT_COVERAGE}};
  return names;
}
const std::map<std::string, v1::Scoring>& ScoringNames() {
  static const std::map<std::string, v1::Scoring> names = {
      {"l1", v1::SCORING_L1},
      {"l2", v1::SCORING_L2},
      {"chi_square", v1::SCORING_CHI_SQUARE},
      {"kl", v1::SCORING_KL},
      {"bhattacharyya", v1::SCORING_BHATTACHARYYA},
      {"dot_product", v1::SCORING_DOT_PRODUCT}};
  return names;
}
const std::map<std::string, v1::VerificationMode>& VerifyNames() {
  static const std::map<std::string, v1::VerificationMode> names = {
      {"disabled", v1::VERIFICATION_MODE_DISABLED},
      {"direct", v1::VERIFICATION_MODE_DIRECT_INDEX},
      {"exhaustive", v1::VERIFICATION_MODE_EXHAUSTIVE}};
  return names;
}
const std::map<std::string, v1::FeatureType>& FeatureTypeNames() {
  static const std::map<std::string, v1::FeatureType> names = {{"orb", v1::FEATURE_TYPE_ORB},
                                                               {"sift", v1::FEATURE_TYPE_SIFT}};
  return names;
}
const std::map<std::string, v1::BandPolicy>& BandPolicyNames() {
  static const std::map<std::string, v1::BandPolicy> names = {
      {"fixed", v1::BAND_POLICY_FIXED},
      {"nearest_layer", v1::BAND_POLICY_NEAREST_LAYER},
      {"appeared_layer", v1::BAND_POLICY_APPEARED_LAYER}};
  return names;
}
const std::map<std::string, v1::BoxSource>& BoxSourceNames() {
  static const std::map<std::string, v1::BoxSource> names = {{"agent", v1::BOX_SOURCE_AGENT},
                                                             {"server", v1::BOX_SOURCE_SERVER},
                                                             {"both", v1::BOX_SOURCE_BOTH}};
  return names;
}

template <typename Map>
std::vector<std::string> Keys(const Map& map) {
  std::vector<std::string> keys;
  for (const auto& [key, value] : map) keys.push_back(key);
  return keys;
}

std::string Join(const std::vector<std::string>& items, const std::string& separator) {
  std::string text;
  for (const std::string& item : items) text += (text.empty() ? "" : separator) + item;
  return text;
}

std::string FormatPose(const v1::PlaceMetadata& metadata) {
  if (!metadata.has_pose()) return "-";
  const v1::Pose& p = metadata.pose();
  return "x " + FormatDouble(p.x(), 3) + ", y " + FormatDouble(p.y(), 3) + ", z " +
         FormatDouble(p.z(), 3) + "; q (" + FormatDouble(p.qx(), 3) + ", " +
         FormatDouble(p.qy(), 3) + ", " + FormatDouble(p.qz(), 3) + ", " + FormatDouble(p.qw(), 3) +
         ")";
}

std::string FormatBox(const v1::UsedBox& box) {
  return box.class_name() + " " + FormatDouble(box.confidence(), 2) + " [" +
         FormatDouble(box.rect().x(), 0) + " " + FormatDouble(box.rect().y(), 0) + " " +
         FormatDouble(box.rect().width(), 0) + "x" + FormatDouble(box.rect().height(), 0) + "]";
}

std::string FormatCounts(const v1::FrameCounts& counts) {
  return std::to_string(counts.total()) + " descriptors: " + std::to_string(counts.kept()) +
         " static kept, " + std::to_string(counts.dynamic()) + " dynamic dropped" +
         (counts.depth_removed() > 0
              ? ", " + std::to_string(counts.depth_removed()) + " removed by depth"
              : std::string()) +
         " (" + FormatDouble(counts.dynamic_coverage() * 100, 1) + "% of the image dynamic)";
}

std::string Metres(double metres) {
  return FormatDouble(metres, 2) + " m";
}

// A little-endian float32 from 4 bytes (SiftFeatures.descriptors).
float LittleEndianFloat(const char* bytes) {
  uint32_t bits = 0;
  for (int b = 3; b >= 0; --b) bits = (bits << 8) | uint8_t(bytes[b]);
  float value = 0;
  std::memcpy(&value, &bits, sizeof value);
  return value;
}

// Depth options shared by `query`: --depth FILE, --depth-scale, --intrinsics.
struct DepthFlags {
  std::string file;
  float scale = 0;
  std::string intrinsics;
};

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

// ---- Commands -----------------------------------------------------------------------------------

struct CreateFlags {
  std::string name;
  std::string vocabulary;
  int features = 0;
  std::string detection;
  std::string classes;  // comma-separated
  float confidence = 0;
  std::string box_source;
  std::string filter;
  float sensitivity = 0;
  int place_threshold = 0;
  std::string scoring;
  std::string verify;
  int level = 0;
  int min_inliers = 0;
  int candidates = 0;
  bool store_invalid = false;
  // Feature type (SIFT maps need a float vocabulary) and SIFT.
  std::string feature_type;
  int sift_features = 0;
  // Depth (docs/rgbd.md).
  bool no_refine_boxes = false;
  bool no_depth_filter = false;
  // Monocular box refinement, the short-term tier and re-ranking.
  std::string box_refinement;
  std::string short_term;  // on | off
  double short_term_horizon_s = 0;
  CLI::Option* short_term_horizon_option = nullptr;
  std::string rerank;         // on | off
  std::string static_budget;  // on | off
  float depth_scale = 0;
  float depth_threshold = 0;
  std::string band_policy;
  bool paper_literal = false;  // mean over all pixels + fixed bands
  // Loop closure (ingest streams with --loop-closure).
  double loop_threshold = 0;
  double rehearsal_threshold = 0;
  int stm = 0;
  uint32_t max_wm = 0;
  double wm_time_budget_ms = 0;
  bool no_verify_loops = false;
  // Which were given (unset fields take the server's defaults).
  CLI::Option* features_option = nullptr;
  CLI::Option* sift_features_option = nullptr;
  CLI::Option* depth_scale_option = nullptr;
  CLI::Option* depth_threshold_option = nullptr;
  CLI::Option* loop_threshold_option = nullptr;
  CLI::Option* rehearsal_threshold_option = nullptr;
  CLI::Option* stm_option = nullptr;
  CLI::Option* max_wm_option = nullptr;
  CLI::Option* wm_time_budget_option = nullptr;
  CLI::Option* confidence_option = nullptr;
  CLI::Option* sensitivity_option = nullptr;
  CLI::Option* place_threshold_option = nullptr;
  CLI::Option* level_option = nullptr;
  CLI::Option* min_inliers_option = nullptr;
  CLI::Option* candidates_option = nullptr;
};

void PrintMap(const v1::MapDescription& map, CliIo& io) {
  const v1::MapConfig& c = map.config();
  const v1::MapStats& s = map.stats();
  std::vector<std::pair<std::string, std::string>> config;
  config.push_back({"created", FormatUnixMs(map.created_unix_ms())});
  config.push_back({"vocabulary", (c.vocabulary().empty() ? "default" : c.vocabulary()) +
                                      " (checksum " + map.vocabulary_checksum() + ")"});
  config.push_back({"features", c.feature_type() == v1::FEATURE_TYPE_UNSPECIFIED
                                    ? std::string("(the vocabulary's)")
                                    : FeatureTypeName(c.feature_type())});
  if (c.feature_type() != v1::FEATURE_TYPE_SIFT) {
    const v1::OrbSettings& orb = c.orb();
    config.push_back({"orb", "max_features " + std::to_string(orb.max_features()) +
                                 ", scale_factor " + FormatDouble(orb.scale_factor(), 2) +
                                 ", levels " + std::to_string(orb.levels()) + ", edge_threshold " +
                                 std::to_string(orb.edge_threshold()) + ", patch_size " +
                                 std::to_string(orb.patch_size()) + ", fast_threshold " +
                                 std::to_string(orb.fast_threshold())});
  }
  if (c.feature_type() == v1::FEATURE_TYPE_SIFT) {
    const v1::SiftSettings& sift = c.sift();
    config.push_back({"sift", "max_features " +
                                  (sift.max_features() == 0 && sift.has_max_features()
                                       ? std::string("all")
                                       : std::to_string(sift.max_features())) +
                                  ", octave_layers " + std::to_string(sift.octave_layers()) +
                                  ", contrast_threshold " +
                                  FormatDouble(sift.contrast_threshold(), 3) + ", edge_threshold " +
                                  FormatDouble(sift.edge_threshold(), 1) + ", sigma " +
                                  FormatDouble(sift.sigma(), 2)});
  }
  const v1::DetectionSettings& d = c.detection();
  std::vector<std::string> classes(d.classes().begin(), d.classes().end());
  config.push_back({"detection", std::string(d.enabled() ? "on" : "off") + ", box_source " +
                                     BoxSourceName(d.box_source()) + ", min_confidence " +
                                     FormatDouble(d.min_confidence(), 2) + ", classes " +
                                     (classes.empty() ? "(default)" : Join(classes, ","))});
  const v1::FilterSettings& f = c.filter();
  config.push_back({"filter", FilterName(f.method()) + ", sensitivity " +
                                  FormatDouble(f.sensitivity_threshold(), 2) +
                                  ", place_threshold " + std::to_string(f.place_threshold())});
  std::string refinement = "shape";
  for (const auto& [name, value] : BoxRefinementNames()) {
    if (value == f.box_refinement()) refinement = name;
  }
  config.push_back({"refine_boxes",
                    refinement + ", static_budget " + (f.static_feature_budget() ? "on" : "off")});
  const v1::ShortTermSettings& st = f.short_term();
  config.push_back({"short_term", st.enabled()
                                      ? "on, horizon " + FormatDouble(st.horizon_s(), 0) +
                                            " s, max_places " + std::to_string(st.max_places()) +
                                            ", weight " + FormatDouble(st.weight(), 2)
                                      : std::string("off")});
  config.push_back({"scoring", ScoringName(c.scoring())});
  const v1::VerificationSettings& v = c.verification();
  config.push_back(
      {"verification",
       VerificationName(v.mode()) + ", level " + std::to_string(v.levels_up()) + ", min_inliers " +
           std::to_string(v.min_inliers()) + ", candidates " +
           (v.candidates() == 0 ? std::string("all") : std::to_string(v.candidates())) +
           ", rerank " + (v.rerank() ? "on" : "off")});
  config.push_back({"store_invalid", c.store_invalid() ? "yes" : "no"});
  const v1::DepthSettings& depth = c.depth();
  auto on_off = [](bool has, bool value) { return has ? (value ? "on" : "off") : "-"; };
  config.push_back({"depth", std::string("refine_boxes ") +
                                 on_off(depth.has_refine_boxes(), depth.refine_boxes()) +
                                 ", scale " + FormatDouble(depth.scale(), 4) + " m/unit, range " +
                                 FormatDouble(depth.min_depth_m(), 2) + "-" +
                                 FormatDouble(depth.max_depth_m(), 2) + " m, use_range " +
                                 on_off(depth.has_use_range(), depth.use_range()) +
                                 ", features without depth " +
                                 (depth.remove_features_without_depth() ? "removed" : "kept")});
  config.push_back(
      {"depth filter",
       std::string(on_off(depth.has_stream_filter(), depth.stream_filter())) + ", mean over " +
           (depth.mean_all_pixels() ? "all pixels" : "valid pixels") + ", threshold " +
           Metres(depth.threshold_m()) + ", persistence " + std::to_string(depth.persistence()) +
           ", static_window " + std::to_string(depth.static_window()) + ", band " +
           BandPolicyName(depth.band_policy()) + " (rise " +
           FormatDouble(depth.rise_band().near_m(), 2) + "-" +
           FormatDouble(depth.rise_band().far_m(), 2) + " m, fall " +
           FormatDouble(depth.fall_band().near_m(), 2) + "-" +
           FormatDouble(depth.fall_band().far_m(), 2) + " m), rebaseline " +
           (depth.rebaseline_after() == 0 ? std::string("never")
                                          : "after " + std::to_string(depth.rebaseline_after()))});
  const v1::LoopClosureSettings& loop = c.loop_closure();
  config.push_back(
      {"loop closure",
       "loop_threshold " + FormatDouble(loop.loop_threshold(), 3) + ", rehearsal_threshold " +
           FormatDouble(loop.rehearsal_threshold(), 3) + ", stm " +
           std::to_string(loop.short_term_memory()) + ", max_wm " +
           (loop.max_working_memory() == 0 ? std::string("unbounded")
                                           : std::to_string(loop.max_working_memory())) +
           ", time_budget " +
           (loop.time_budget_ms() == 0 ? std::string("none")
                                       : FormatDouble(loop.time_budget_ms(), 1) + " ms") +
           ", min_candidates " + std::to_string(loop.min_candidates()) + ", verify " +
           (loop.verify() ? "on" : "off")});
  PrintKeyValues(io.out, "map " + map.name(), config);
  std::vector<std::pair<std::string, std::string>> stats;
  stats.push_back({"places", std::to_string(s.places())});
  stats.push_back({"descriptors kept", std::to_string(s.descriptors_kept())});
  stats.push_back({"descriptors dropped", std::to_string(s.descriptors_dropped())});
  stats.push_back({"invalid rejected", std::to_string(s.invalid_rejected())});
  stats.push_back({"invalid stored", std::to_string(s.invalid_stored())});
  stats.push_back({"bytes on disk", FormatBytes(s.bytes_on_disk())});
  stats.push_back({"bytes in memory", FormatBytes(s.bytes_in_memory())});
  stats.push_back({"streams", std::to_string(s.streams())});
  stats.push_back({"loop working memory", std::to_string(s.loop_working_memory())});
  stats.push_back({"loop long-term", std::to_string(s.loop_long_term())});
  stats.push_back({"loops accepted", std::to_string(s.loops_accepted())});
  stats.push_back(
      {"loops rejected", std::to_string(s.loops_rejected()) + "  (failed verification)"});
  PrintKeyValues(io.out, "statistics", stats);
}

int MapsCreate(const Connection& connection, const CreateFlags& flags, bool json, CliIo& io) {
  v1::CreateMapRequest request;
  request.set_name(flags.name);
  v1::MapConfig* config = request.mutable_config();
  config->set_vocabulary(flags.vocabulary);
  if (!flags.feature_type.empty()) {
    config->set_feature_type(FeatureTypeNames().at(flags.feature_type));
  }
  if (flags.features_option->count()) config->mutable_orb()->set_max_features(flags.features);
  if (flags.sift_features_option->count()) {
    config->mutable_sift()->set_max_features(flags.sift_features);
  }
  v1::DepthSettings* depth = config->mutable_depth();
  if (flags.no_refine_boxes) depth->set_refine_boxes(false);
  if (flags.no_depth_filter) depth->set_stream_filter(false);
  if (flags.depth_scale_option->count()) depth->set_scale(flags.depth_scale);
  if (flags.depth_threshold_option->count()) depth->set_threshold_m(flags.depth_threshold);
  if (!flags.band_policy.empty()) depth->set_band_policy(BandPolicyNames().at(flags.band_policy));
  if (flags.paper_literal) {  // Algorithm 1 as written: the mean over all pixels, fixed bands
    depth->set_mean_all_pixels(true);
    depth->set_band_policy(v1::BAND_POLICY_FIXED);
  }
  v1::LoopClosureSettings* loop = config->mutable_loop_closure();
  if (flags.loop_threshold_option->count()) loop->set_loop_threshold(flags.loop_threshold);
  if (flags.rehearsal_threshold_option->count()) {
    loop->set_rehearsal_threshold(flags.rehearsal_threshold);
  }
  if (flags.stm_option->count()) loop->set_short_term_memory(flags.stm);
  if (flags.max_wm_option->count()) loop->set_max_working_memory(flags.max_wm);
  if (flags.wm_time_budget_option->count()) loop->set_time_budget_ms(flags.wm_time_budget_ms);
  if (flags.no_verify_loops) loop->set_verify(false);
  v1::DetectionSettings* detection = config->mutable_detection();
  if (!flags.detection.empty()) detection->set_enabled(flags.detection == "on");
  size_t start = 0;
  while (start < flags.classes.size()) {
    size_t comma = flags.classes.find(',', start);
    if (comma == std::string::npos) comma = flags.classes.size();
    const std::string name = flags.classes.substr(start, comma - start);
    if (!name.empty()) detection->add_classes(name);
    start = comma + 1;
  }
  if (flags.confidence_option->count()) detection->set_min_confidence(flags.confidence);
  if (!flags.box_source.empty()) {
    detection->set_box_source(BoxSourceNames().at(flags.box_source));
  }
  v1::FilterSettings* filter = config->mutable_filter();
  if (!flags.filter.empty()) filter->set_method(FilterNames().at(flags.filter));
  if (flags.sensitivity_option->count()) filter->set_sensitivity_threshold(flags.sensitivity);
  if (flags.place_threshold_option->count()) filter->set_place_threshold(flags.place_threshold);
  if (!flags.box_refinement.empty()) {
    filter->set_box_refinement(BoxRefinementNames().at(flags.box_refinement));
  }
  if (!flags.short_term.empty()) {
    filter->mutable_short_term()->set_enabled(flags.short_term == "on");
  }
  if (!flags.static_budget.empty()) {
    filter->set_static_feature_budget(flags.static_budget == "on");
  }
  if (flags.short_term_horizon_option->count()) {
    filter->mutable_short_term()->set_horizon_s(flags.short_term_horizon_s);
  }
  if (!flags.scoring.empty()) config->set_scoring(ScoringNames().at(flags.scoring));
  v1::VerificationSettings* verification = config->mutable_verification();
  if (!flags.verify.empty()) verification->set_mode(VerifyNames().at(flags.verify));
  if (flags.level_option->count()) verification->set_levels_up(flags.level);
  if (flags.min_inliers_option->count()) verification->set_min_inliers(flags.min_inliers);
  if (flags.candidates_option->count()) verification->set_candidates(flags.candidates);
  if (!flags.rerank.empty()) verification->set_rerank(flags.rerank == "on");
  config->set_store_invalid(flags.store_invalid);

  auto context = connection.NewContext();
  v1::MapDescription map;
  const grpc::Status status = connection.stub()->CreateMap(context.get(), request, &map);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(map) << '\n';
  } else {
    io.out << "created map '" << map.name() << "'\n";
    PrintMap(map, io);
  }
  return kExitOk;
}

int MapsList(const Connection& connection, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::ListMapsResponse response;
  const grpc::Status status = connection.stub()->ListMaps(context.get(), {}, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(response) << '\n';
    return kExitOk;
  }
  if (response.maps_size() == 0) {
    io.out << "no maps\n";
    return kExitOk;
  }
  Table table({"NAME", ">PLACES", "VOCABULARY", "FEATURES", "STATUS"});
  for (const v1::MapSummary& map : response.maps()) {
    table.Add({map.name(), map.available() ? std::to_string(map.places()) : "-",
               map.vocabulary().empty() ? "-" : map.vocabulary(),
               map.available() ? FeatureTypeName(map.feature_type()) : "-",
               map.available() ? "available" : "unavailable: " + map.unavailable_reason()});
  }
  table.Print(io.out);
  return kExitOk;
}

int MapsShow(const Connection& connection, const std::string& name, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::GetMapRequest request;
  request.set_name(name);
  v1::MapDescription map;
  const grpc::Status status = connection.stub()->GetMap(context.get(), request, &map);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(map) << '\n';
  } else {
    PrintMap(map, io);
  }
  return kExitOk;
}

int MapsDelete(const Connection& connection, const std::string& name, bool yes, bool json,
               CliIo& io) {
  if (!yes) {
    if (!io.in_is_tty) {
      return UsageError(io, "refusing to delete map '" + name +
                                "' without --yes (standard input is not a terminal to ask on)");
    }
    io.err << "delete map '" << name << "' and all its places? [y/N] " << std::flush;
    std::string answer;
    std::getline(io.in, answer);
    if (answer != "y" && answer != "Y" && answer != "yes") {
      return UsageError(io, "not confirmed: map '" + name + "' was not deleted");
    }
  }
  auto context = connection.NewContext();
  v1::DeleteMapRequest request;
  request.set_name(name);
  v1::DeleteMapResponse response;
  const grpc::Status status = connection.stub()->DeleteMap(context.get(), request, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << nlohmann::json({{"deleted", name}}).dump(2) << '\n';
  } else {
    io.out << "deleted map '" << name << "'\n";
  }
  return kExitOk;
}

struct QueryFlags {
  std::string map;
  std::string image;
  int top_k = 10;
  std::string boxes;
  bool verified_only = false;
  std::string agent_id = "cli";
  bool exclude_same_agent = false;
  DepthFlags depth;
};

int Query(const Connection& connection, const QueryFlags& flags, bool json, CliIo& io) {
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
  request.mutable_options()->set_top_k(uint32_t(flags.top_k));
  request.mutable_options()->set_verified_only(flags.verified_only);
  request.mutable_options()->set_exclude_same_agent(flags.exclude_same_agent);

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
  }
  for (const v1::UsedBox& box : response.boxes_used()) {
    io.out << "box used: " << FormatBox(box) << '\n';
  }
  io.out << "timings (ms): " << FormatTimings(response.timings()) << "; round trip "
         << FormatDouble(round_trip_ms, 2) << '\n';
  return kExitOk;
}

int PlaceGet(const Connection& connection, const std::string& map, uint32_t id, bool features,
             bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::GetPlaceRequest request;
  request.set_map(map);
  request.set_place_id(id);
  request.set_include_features(features);
  v1::Place place;
  const grpc::Status status = connection.stub()->GetPlace(context.get(), request, &place);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(place) << '\n';
    return kExitOk;
  }
  std::vector<std::pair<std::string, std::string>> table;
  table.push_back({"agent", place.metadata().agent_id()});
  table.push_back({"sequence", std::to_string(place.metadata().sequence())});
  table.push_back({"timestamp", FormatUnixNs(place.metadata().timestamp_ns())});
  table.push_back({"pose", FormatPose(place.metadata())});
  table.push_back({"descriptors", FormatCounts(place.counts())});
  for (const v1::UsedBox& box : place.boxes_used()) table.push_back({"box used", FormatBox(box)});
  if (features && place.has_sift_features()) {
    // SIFT maps: the count, then the first keypoints with the start of their descriptors.
    const v1::SiftFeatures& sift = place.sift_features();
    table.push_back({"features", std::to_string(sift.keypoints_size()) +
                                     " static SIFT keypoints, " +
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
          const float value = LittleEndianFloat(sift.descriptors().data() +
                                                size_t(i) * per_keypoint + size_t(v) * 4);
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
  } else if (features) {
    table.push_back({"features", std::to_string(place.features().keypoints_size()) +
                                     " static keypoints, " +
                                     std::to_string(place.features().descriptors().size()) +
                                     " descriptor bytes, image " +
                                     std::to_string(place.features().image_width()) + "x" +
                                     std::to_string(place.features().image_height())});
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

int Info(const Connection& connection, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::ServerInfo info;
  const grpc::Status status = connection.stub()->GetServerInfo(context.get(), {}, &info);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(info) << '\n';
    return kExitOk;
  }
  io.out << "placedb server " << info.version() << " at " << connection.options().address
         << "\n  detector  " << info.detector() << "\n\n";
  Table vocabularies(
      {"VOCABULARY", "FEATURES", ">WORDS", ">NODES", ">K", ">L", ">MEMORY", "CHECKSUM", "PATH"});
  for (const v1::VocabularyInfo& v : info.vocabularies()) {
    vocabularies.Add(
        {v.name(),
         v.feature_type() == v1::FEATURE_TYPE_UNSPECIFIED ? std::string("-")
                                                          : FeatureTypeName(v.feature_type()),
         std::to_string(v.words()), std::to_string(v.nodes()), std::to_string(v.branching()),
         std::to_string(v.depth()), FormatBytes(v.memory_bytes()), v.checksum(), v.path()});
  }
  vocabularies.Print(io.out);
  const v1::Limits& l = info.limits();
  std::vector<std::pair<std::string, std::string>> limits;
  limits.push_back({"max_message_bytes", FormatBytes(l.max_message_bytes())});
  limits.push_back({"max_image_pixels", std::to_string(l.max_image_pixels())});
  limits.push_back({"max_descriptors_per_frame", std::to_string(l.max_descriptors_per_frame())});
  limits.push_back({"max_boxes_per_frame", std::to_string(l.max_boxes_per_frame())});
  limits.push_back({"max_concurrent_streams", std::to_string(l.max_concurrent_streams())});
  limits.push_back({"max_queued_frames", std::to_string(l.max_queued_frames())});
  limits.push_back({"max_inflight_per_stream", std::to_string(l.max_inflight_per_stream())});
  limits.push_back({"worker_threads", std::to_string(l.worker_threads())});
  io.out << '\n';
  PrintKeyValues(io.out, "limits", limits);
  return kExitOk;
}

// 0 SERVING, 1 anything else the server says, 2 unreachable.
int Health(const Connection& connection, const std::string& service, bool json, CliIo& io) {
  std::string serving;
  const grpc::Status status = CheckHealth(connection, service, &serving);
  int code = kExitOk;
  std::string state = serving;
  if (!status.ok()) {
    const bool unreachable = status.error_code() == grpc::StatusCode::UNAVAILABLE ||
                             status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED;
    state = unreachable                                          ? "UNREACHABLE"
            : status.error_code() == grpc::StatusCode::NOT_FOUND ? "SERVICE_UNKNOWN"
                                                                 : "ERROR";
    code = unreachable ? 2 : 1;
    io.err << "error: " << Describe(status) << '\n';
  } else if (serving != "SERVING") {
    code = 1;
  }
  if (json) {
    nlohmann::json out = {
        {"address", connection.options().address}, {"service", service}, {"status", state}};
    if (!status.ok()) out["error"] = Describe(status);
    io.out << out.dump(2) << '\n';
  } else {
    io.out << state << '\n';
  }
  return code;
}

}  // namespace

// ---- The command line ---------------------------------------------------------------------------

int RunCli(int argc, const char* const* argv, CliIo& io) {
  CLI::App app{"placedb: the command line of the placedb place-recognition database (docs/cli.md)",
               "placedb"};
  app.fallthrough();  // global options anywhere, also after the subcommand
  app.require_subcommand(1);
  app.set_version_flag("--version", PLACEDB_VERSION);

  ConnectionOptions connection_options;
  bool json = false;
  app.add_option("--address", connection_options.address, "server address (HOST:PORT)")
      ->envname("PLACEDB_ADDRESS")
      ->capture_default_str();
  app.add_option("--timeout", connection_options.timeout_s,
                 "deadline of each unary RPC, seconds (0 = none)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_flag("--json", json, "machine-readable output (JSON on stdout)");
  app.add_flag("--tls", connection_options.tls,
               "connect with TLS (the server does not offer it yet)");
  app.add_option("--ca-cert", connection_options.ca_cert,
                 "PEM root certificates for --tls (default: the system's)")
      ->check(CLI::ExistingFile);
  app.add_option("--token", connection_options.token,
                 "sent as 'authorization: Bearer TOKEN' (the server does not check it yet)")
      ->envname("PLACEDB_TOKEN");

  // maps
  CLI::App* maps = app.add_subcommand("maps", "create, list, show and delete maps");
  maps->require_subcommand(1);
  CreateFlags create_flags;
  CLI::App* create = maps->add_subcommand("create", "create a durable map");
  create->add_option("NAME", create_flags.name, "map name")->required();
  create->add_option("--vocabulary", create_flags.vocabulary,
                     "vocabulary name from the server's config (default: default)");
  create_flags.features_option = create->add_option("--features", create_flags.features,
                                                    "ORB features per frame (default 1000)");
  create
      ->add_option("--detection", create_flags.detection,
                   "whether boxes mark dynamic objects (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  create->add_option("--classes", create_flags.classes,
                     "dynamic COCO classes, comma-separated (default person,bicycle,car,"
                     "motorcycle,bus,truck)");
  create_flags.confidence_option = create->add_option("--confidence", create_flags.confidence,
                                                      "minimum box confidence (default 0.2)");
  create
      ->add_option("--box-source", create_flags.box_source, "where boxes come from (default agent)")
      ->check(CLI::IsMember(Keys(BoxSourceNames())));
  create
      ->add_option("--filter", create_flags.filter,
                   "dynamic-descriptor filter (default keypoint_in_box)")
      ->check(CLI::IsMember(Keys(FilterNames())));
  create_flags.sensitivity_option =
      create->add_option("--sensitivity", create_flags.sensitivity,
                         "exact_coverage threshold in [0, 1) (default 0.25)");
  create_flags.place_threshold_option =
      create->add_option("--place-threshold", create_flags.place_threshold,
                         "a frame is a place iff static descriptors > N (default 20)");
  create
      ->add_option("--refine-boxes", create_flags.box_refinement,
                   "narrow boxes to their objects without depth (default shape)")
      ->check(CLI::IsMember(Keys(BoxRefinementNames())));
  create
      ->add_option("--short-term", create_flags.short_term,
                   "keep recent places' dynamic words in memory (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  create_flags.short_term_horizon_option =
      create->add_option("--short-term-horizon", create_flags.short_term_horizon_s,
                         "short-term horizon in seconds (default 60)");
  create
      ->add_option("--static-budget", create_flags.static_budget,
                   "spend the ORB budget on static pixels when objects are known (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  create
      ->add_option("--rerank", create_flags.rerank,
                   "re-rank verified candidates by inliers (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  create->add_option("--scoring", create_flags.scoring, "score (default l1)")
      ->check(CLI::IsMember(Keys(ScoringNames())));
  create->add_option("--verify", create_flags.verify, "geometric verification (default disabled)")
      ->check(CLI::IsMember(Keys(VerifyNames())));
  create_flags.level_option = create->add_option("--level", create_flags.level,
                                                 "direct-index level above the words (default 2)");
  create_flags.min_inliers_option = create->add_option(
      "--min-inliers", create_flags.min_inliers, "inliers to call a match verified (default 15)");
  create_flags.candidates_option = create->add_option("--candidates", create_flags.candidates,
                                                      "candidates to verify (default 0 = all)");
  create->add_flag("--store-invalid", create_flags.store_invalid,
                   "keep invalid observations as metadata");
  create
      ->add_option("--feature-type", create_flags.feature_type,
                   "orb or sift; must agree with the vocabulary (default: the vocabulary's kind)")
      ->check(CLI::IsMember(Keys(FeatureTypeNames())));
  create_flags.sift_features_option =
      create
          ->add_option("--sift-features", create_flags.sift_features,
                       "SIFT features per frame (default 1000, 0 = all)")
          ->check(CLI::NonNegativeNumber);
  create->add_flag("--no-refine-boxes", create_flags.no_refine_boxes,
                   "with depth, a box stays dynamic as a whole (default: only the object's own "
                   "depth layer)");
  create->add_flag("--no-depth-filter", create_flags.no_depth_filter,
                   "no Algorithm 1 on ingest streams with depth");
  create_flags.depth_scale_option = create
                                        ->add_option("--depth-scale", create_flags.depth_scale,
                                                     "metres per png16 depth unit (default 0.001)")
                                        ->check(CLI::PositiveNumber);
  create_flags.depth_threshold_option =
      create
          ->add_option("--depth-threshold", create_flags.depth_threshold,
                       "Algorithm 1: |V_current - V_static| that deviates, metres (default 0.15)")
          ->check(CLI::PositiveNumber);
  CLI::Option* band_policy =
      create
          ->add_option("--band-policy", create_flags.band_policy,
                       "depth band removed while deviating (default appeared_layer)")
          ->check(CLI::IsMember(Keys(BandPolicyNames())));
  create
      ->add_flag("--paper-literal", create_flags.paper_literal,
                 "Algorithm 1 as written: mean over all pixels, fixed bands")
      ->excludes(band_policy);
  create_flags.loop_threshold_option =
      create
          ->add_option("--loop-threshold", create_flags.loop_threshold,
                       "loop closure: posterior to accept a loop, T_loop (default 0.12)")
          ->check(CLI::Range(0.0, 1.0));
  create_flags.rehearsal_threshold_option =
      create
          ->add_option(
              "--rehearsal-threshold", create_flags.rehearsal_threshold,
              "loop closure: similarity merging a frame into the previous place (default 0.20; > 1 "
              "disables rehearsal)")
          ->check(CLI::NonNegativeNumber);
  create_flags.stm_option = create
                                ->add_option("--stm", create_flags.stm,
                                             "loop closure: short-term memory, places (default "
                                             "30)")
                                ->check(CLI::NonNegativeNumber);
  create_flags.max_wm_option =
      create->add_option("--max-wm", create_flags.max_wm,
                         "loop closure: working-memory bound, places (default 0 = unbounded)");
  create_flags.wm_time_budget_option =
      create
          ->add_option("--wm-time-budget-ms", create_flags.wm_time_budget_ms,
                       "loop closure: time budget per update, ms (default 0 = none)")
          ->check(CLI::NonNegativeNumber);
  create->add_flag("--no-verify-loops", create_flags.no_verify_loops,
                   "loop closure: keep loops the filter accepts without geometric verification");
  CLI::App* list = maps->add_subcommand("list", "list the maps");
  std::string show_name;
  CLI::App* show = maps->add_subcommand("show", "a map's configuration and statistics");
  show->add_option("NAME", show_name, "map name")->required();
  std::string delete_name;
  bool delete_yes = false;
  CLI::App* remove = maps->add_subcommand("delete", "delete a map and all its places");
  remove->add_option("NAME", delete_name, "map name")->required();
  remove->add_flag("--yes,-y", delete_yes, "do not ask for confirmation");

  // ingest
  IngestOptions ingest_options;
  CLI::App* ingest = app.add_subcommand("ingest", "stream frames into a map");
  ingest->add_option("MAP", ingest_options.map, "map name")->required();
  ingest
      ->add_option("SOURCE", ingest_options.sources,
                   "image folders, image lists (.txt), videos or images")
      ->required();
  ingest
      ->add_option("--agents", ingest_options.agents,
                   "agents (Ingest streams) sharing the frames round-robin")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  ingest
      ->add_option("--agent-id", ingest_options.agent_id,
                   "agent id (with several agents: ID-1 ... ID-N)")
      ->capture_default_str();
  ingest->add_option("--video-every", ingest_options.video_every, "every K-th video frame")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  ingest->add_option("--glob", ingest_options.glob,
                     "only folder entries whose name matches (e.g. '*.jpg')");
  ingest->add_flag("--matches", ingest_options.matches,
                   "ask for each frame's matches against the map before it");
  ingest->add_option("--top-k", ingest_options.top_k, "matches per frame with --matches")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  ingest->add_option("--rate", ingest_options.rate, "frames/s per agent (0 = as fast as accepted)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  ingest
      ->add_option("--sequence-start", ingest_options.sequence_start,
                   "Observation.sequence of the first frame")
      ->capture_default_str();
  ingest->add_option("--window", ingest_options.window, "unanswered frames per stream")
      ->check(CLI::Range(1, 1024))
      ->capture_default_str();
  ingest->add_option("--depth", ingest_options.depth_dir,
                     "depth images, paired with the frames by file stem (12.jpg -> DIR/12.png, "
                     ".pgm, .tif): 16-bit (millimetres by default) or float32 metres");
  ingest
      ->add_option("--depth-scale", ingest_options.depth_scale,
                   "metres per depth unit (default: the map's, 0.001 for 16-bit)")
      ->check(CLI::PositiveNumber);
  ingest->add_option("--intrinsics", ingest_options.intrinsics,
                     "colour camera intrinsics fx,fy,cx,cy in pixels (sent with the depth)");
  ingest->add_flag("--loop-closure", ingest_options.loop_closure,
                   "Bayesian loop closure per agent: prints each frame's loop or merge");

  // query
  QueryFlags query_flags;
  CLI::App* query = app.add_subcommand("query", "ranked matches of an image against a map");
  query->add_option("MAP", query_flags.map, "map name")->required();
  query->add_option("IMAGE", query_flags.image, "image file")->required();
  query->add_option("--top-k", query_flags.top_k, "matches to return")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  query->add_option("--boxes", query_flags.boxes,
                    "dynamic-object boxes, JSON: [{\"class\": \"person\", \"confidence\": 0.9, "
                    "\"rect\": [x, y, w, h]}, ...]");
  query->add_flag("--verified-only", query_flags.verified_only,
                  "drop candidates that fail geometric verification");
  query->add_option("--agent-id", query_flags.agent_id, "the querying agent")
      ->capture_default_str();
  query->add_flag("--exclude-same-agent", query_flags.exclude_same_agent,
                  "skip places stored by --agent-id");
  query->add_option("--depth", query_flags.depth.file,
                    "depth image registered to IMAGE (16-bit PNG/PGM/TIFF or float32 TIFF)");
  query
      ->add_option("--depth-scale", query_flags.depth.scale,
                   "metres per depth unit (default: the map's, 0.001 for 16-bit)")
      ->check(CLI::PositiveNumber);
  query->add_option("--intrinsics", query_flags.depth.intrinsics,
                    "colour camera intrinsics fx,fy,cx,cy in pixels (sent with the depth)");

  // place
  CLI::App* place = app.add_subcommand("place", "get or delete one stored place");
  place->require_subcommand(1);
  std::string place_map;
  uint32_t place_id = 0;
  bool place_features = false;
  CLI::App* place_get = place->add_subcommand("get", "a place's metadata, counts and boxes");
  place_get->add_option("MAP", place_map, "map name")->required();
  place_get->add_option("ID", place_id, "place id")->required();
  place_get->add_flag("--features", place_features, "include the stored static features");
  CLI::App* place_delete = place->add_subcommand("delete", "remove a place durably");
  place_delete->add_option("MAP", place_map, "map name")->required();
  place_delete->add_option("ID", place_id, "place id")->required();

  // info, health
  CLI::App* info = app.add_subcommand("info", "server version, vocabularies, detector, limits");
  std::string health_service;
  CLI::App* health = app.add_subcommand(
      "health", "grpc.health.v1 Check: exit 0 SERVING, 1 otherwise, 2 unreachable");
  health->add_option("--service", health_service,
                     "service to check (default \"\": the whole server)");

  // load
  LoadOptions load_options;
  CLI::App* load =
      app.add_subcommand("load", "load-test a server on this machine (loopback targets only)");
  load->add_option("SOURCE", load_options.sources,
                   "image folders, image lists (.txt), videos or images (preloaded, cycled)")
      ->required();
  load->add_option("--agents", load_options.agents, "concurrent agents (Ingest streams)")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  load->add_option("--map", load_options.map,
                   "map to load (created when missing); default: a temporary map, deleted after");
  load->add_flag("--keep-map", load_options.keep_map, "keep the temporary map");
  load->add_option("--mode", load_options.mode,
                   "encoded: send the images; features: ORB extracted once here, loads the index "
                   "alone")
      ->check(CLI::IsMember({"encoded", "features"}))
      ->capture_default_str();
  CLI::Option* rate = load->add_option("--rate", load_options.rate,
                                       "target frames/s per agent (0 = as fast as accepted)")
                          ->check(CLI::NonNegativeNumber);
  load->add_option("--total-rate", load_options.total_rate, "target frames/s of all agents")
      ->check(CLI::NonNegativeNumber)
      ->excludes(rate);
  load->add_option("--frames", load_options.frames,
                   "stop after N frames in total (default: one pass over the sources)");
  load->add_option("--duration", load_options.duration_s, "stop after S seconds")
      ->check(CLI::NonNegativeNumber);
  load->add_option("--query-ratio", load_options.query_ratio,
                   "fraction of the frames sent as Query instead of ingested")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  load->add_option("--top-k", load_options.top_k, "matches per query")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  load->add_flag("--matches", load_options.matches, "ingest with matches (search, then store)");
  load->add_option("--window", load_options.window, "unanswered frames per agent")
      ->check(CLI::Range(1, 1024))
      ->capture_default_str();
  load->add_option("--json-out", load_options.json_out, "write the report as JSON");
  load->add_option("--video-every", load_options.video_every, "every K-th video frame")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  load->add_option("--glob", load_options.glob,
                   "only folder entries whose name matches (e.g. '*.jpg')");
  load->add_option("--max-source-frames", load_options.max_source_frames,
                   "distinct frames to preload")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e, io.out, io.err);
    return code == 0 ? kExitOk : kExitUsage;
  }

  if (load->parsed()) return RunLoad(connection_options, load_options, json, io);

  std::string error;
  std::optional<Connection> connection = Connection::Open(connection_options, &error);
  if (!connection) return UsageError(io, error);

  if (create->parsed()) return MapsCreate(*connection, create_flags, json, io);
  if (list->parsed()) return MapsList(*connection, json, io);
  if (show->parsed()) return MapsShow(*connection, show_name, json, io);
  if (remove->parsed()) return MapsDelete(*connection, delete_name, delete_yes, json, io);
  if (ingest->parsed()) return RunIngest(*connection, ingest_options, json, io);
  if (query->parsed()) return Query(*connection, query_flags, json, io);
  if (place_get->parsed()) {
    return PlaceGet(*connection, place_map, place_id, place_features, json, io);
  }
  if (place_delete->parsed()) return PlaceDelete(*connection, place_map, place_id, json, io);
  if (info->parsed()) return Info(*connection, json, io);
  if (health->parsed()) return Health(*connection, health_service, json, io);
  return UsageError(io, "no command given (see --help)");
}

int CliMain(int argc, const char* const* argv) {
  CliIo io{std::cout, std::cerr, std::cin, isatty(STDERR_FILENO) != 0, isatty(STDIN_FILENO) != 0};
  const int code = RunCli(argc, argv, io);
  std::cout.flush();
  return code;
}

}  // namespace placedb::client
