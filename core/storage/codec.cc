#include "core/storage/codec.h"

#include <algorithm>
#include <cfloat>
#include <climits>
#include <cmath>
#include <cstring>
#include <nlohmann/json.hpp>

#include "core/decode/image_decoder.h"

namespace placedb {

namespace {

// Format-version bytes. Each value type has its own sequence.
constexpr uint8_t kFormatV1 = 1;
constexpr uint8_t kRecordV2 = 2;            // place record: counts with depth_removed
constexpr uint8_t kInvalidV2 = 2;           // invalid observation: counts with depth_removed
constexpr uint8_t kFeaturesV1 = 1;          // ORB features: 32-byte descriptors
constexpr uint8_t kFloatFeaturesV1 = 0x81;  // SIFT features: 128 float32 per keypoint
// Version 2 of either appends the place's geometry (camera, keypoint depths; issue 32).
constexpr uint8_t kFeaturesV2 = 2;
constexpr uint8_t kFloatFeaturesV2 = 0x82;
constexpr uint8_t kBowWithDirectV2 = 2;  // BoW vector followed by its direct index
// JSON map config: 1 (ORB only), 2 (RGB-D), 3 (box refinement, short-term tier, re-ranking).
constexpr int kConfigFormat = 3;

class Writer {
 public:
  void U8(uint8_t v) { out_.push_back(char(v)); }
  void U32(uint32_t v) { Raw(&v, 4); }  // little-endian hosts only (checked below)
  void U64(uint64_t v) { Raw(&v, 8); }
  void I32(int32_t v) { Raw(&v, 4); }
  void I64(int64_t v) { Raw(&v, 8); }
  void F32(float v) { Raw(&v, 4); }
  void F64(double v) { Raw(&v, 8); }
  void Varint(uint64_t v) {
    while (v >= 0x80) {
      out_.push_back(char(uint8_t(v) | 0x80));
      v >>= 7;
    }
    out_.push_back(char(v));
  }
  void String(const std::string& s) {
    Varint(s.size());
    out_.append(s);
  }
  void Raw(const void* data, size_t n) { out_.append(static_cast<const char*>(data), n); }
  std::string Take() { return std::move(out_); }

 private:
  std::string out_;
};

class Reader {
 public:
  Reader(std::string_view in, const char* what) : in_(in), what_(what) {}

  bool U8(uint8_t* v) { return Raw(v, 1); }
  bool U32(uint32_t* v) { return Raw(v, 4); }
  bool U64(uint64_t* v) { return Raw(v, 8); }
  bool I32(int32_t* v) { return Raw(v, 4); }
  bool I64(int64_t* v) { return Raw(v, 8); }
  bool F32(float* v) { return Raw(v, 4); }
  bool F64(double* v) { return Raw(v, 8); }
  bool Varint(uint64_t* v) {
    uint64_t result = 0;
    for (int shift = 0; shift <= 63; shift += 7) {
      if (pos_ >= in_.size()) return false;
      const uint8_t byte = uint8_t(in_[pos_++]);
      result |= uint64_t(byte & 0x7F) << shift;
      if (!(byte & 0x80)) {
        *v = result;
        return true;
      }
    }
    return false;
  }
  // A count of items each at least `min_item_bytes` long: refuses counts the input cannot hold.
  bool Count(uint64_t* n, size_t min_item_bytes) {
    return Varint(n) && *n <= (in_.size() - pos_) / std::max<size_t>(min_item_bytes, 1);
  }
  bool String(std::string* s) {
    uint64_t n = 0;
    if (!Count(&n, 1)) return false;
    s->assign(in_.substr(pos_, n));
    pos_ += n;
    return true;
  }
  bool Raw(void* out, size_t n) {
    if (in_.size() - pos_ < n) return false;
    if (n == 0) return true;  // `out` may be an empty vector's null data(): memcpy forbids it
    std::memcpy(out, in_.data() + pos_, n);
    pos_ += n;
    return true;
  }
  bool Done() const { return pos_ == in_.size(); }
  Status Error(const std::string& detail = "truncated or malformed") const {
    return Status::Corruption(std::string(what_) + ": " + detail + " at byte " +
                              std::to_string(pos_) + " of " + std::to_string(in_.size()));
  }
  // Reads the version byte; CORRUPTION unless it is in [oldest, newest].
  Status Version(uint8_t oldest, uint8_t newest, uint8_t* version) {
    if (!U8(version)) return Error();
    if (*version < oldest || *version > newest) {
      return Status::Corruption(std::string(what_) + ": unknown format version " +
                                std::to_string(*version));
    }
    return Status::Ok();
  }
  Status Version(uint8_t only = kFormatV1) {
    uint8_t version = 0;
    return Version(only, only, &version);
  }

 private:
  std::string_view in_;
  size_t pos_ = 0;
  const char* what_;
};

static_assert(std::endian::native == std::endian::little,
              "placedb's encodings assume little-endian");

void WriteMetadata(Writer& w, const PlaceMetadata& m) {
  w.String(m.agent_id);
  w.U64(m.sequence);
  w.I64(m.timestamp_ns);
  w.U8(m.pose.has_value() ? 1 : 0);
  if (m.pose) {
    for (double v : m.pose->position) w.F64(v);
    for (double v : m.pose->orientation) w.F64(v);
  }
}

bool ReadMetadata(Reader& r, PlaceMetadata* m) {
  uint8_t has_pose = 0;
  if (!r.String(&m->agent_id) || !r.U64(&m->sequence) || !r.I64(&m->timestamp_ns) ||
      !r.U8(&has_pose) || has_pose > 1) {
    return false;
  }
  if (has_pose) {
    Pose pose;
    for (double& v : pose.position) {
      if (!r.F64(&v)) return false;
    }
    for (double& v : pose.orientation) {
      if (!r.F64(&v)) return false;
    }
    m->pose = pose;
  }
  return true;
}

// Version 2 appends depth_removed; version 1 has none (0).
void WriteCounts(Writer& w, const FrameCounts& c) {
  w.U32(c.total);
  w.U32(c.dynamic);
  w.U32(c.static_);
  w.F64(c.dynamic_coverage);
  w.U32(c.depth_removed);
}

bool ReadCounts(Reader& r, FrameCounts* c, uint8_t version) {
  if (!r.U32(&c->total) || !r.U32(&c->dynamic) || !r.U32(&c->static_) ||
      !r.F64(&c->dynamic_coverage)) {
    return false;
  }
  c->depth_removed = 0;
  if (version >= 2 && !r.U32(&c->depth_removed)) return false;
  return uint64_t(c->dynamic) + c->depth_removed + c->static_ == c->total;
}

void WriteBoxes(Writer& w, const std::vector<DynamicBox>& boxes) {
  w.Varint(boxes.size());
  for (const DynamicBox& b : boxes) {
    w.I32(b.class_id);
    w.F32(b.confidence);
    w.F32(b.rect.x);
    w.F32(b.rect.y);
    w.F32(b.rect.width);
    w.F32(b.rect.height);
  }
}

bool ReadBoxes(Reader& r, std::vector<DynamicBox>* boxes) {
  uint64_t n = 0;
  if (!r.Count(&n, 24)) return false;
  boxes->resize(n);
  for (DynamicBox& b : *boxes) {
    if (!r.I32(&b.class_id) || !r.F32(&b.confidence) || !r.F32(&b.rect.x) || !r.F32(&b.rect.y) ||
        !r.F32(&b.rect.width) || !r.F32(&b.rect.height)) {
      return false;
    }
  }
  return true;
}

// Keypoints: 21 bytes each (5 float32 + octave byte).
constexpr size_t kKeypointBytes = 21;

void WriteKeypoints(Writer& w, const std::vector<Keypoint>& keypoints) {
  for (const Keypoint& kp : keypoints) {
    w.F32(kp.x);
    w.F32(kp.y);
    w.F32(kp.size);
    w.F32(kp.angle);
    w.F32(kp.response);
    w.U8(uint8_t(kp.octave));
  }
}

bool ReadKeypoints(Reader& r, std::vector<Keypoint>* keypoints) {
  for (Keypoint& kp : *keypoints) {
    uint8_t octave = 0;
    if (!r.F32(&kp.x) || !r.F32(&kp.y) || !r.F32(&kp.size) || !r.F32(&kp.angle) ||
        !r.F32(&kp.response) || !r.U8(&octave)) {
      return false;
    }
    kp.octave = octave;
  }
  return true;
}

void WriteDirect(Writer& w, const DirectIndex& direct) {
  w.U8(uint8_t(direct.levels_up));
  w.Varint(direct.node_ids.size());
  NodeId previous = 0;
  for (size_t i = 0; i < direct.node_ids.size(); ++i) {
    w.Varint(direct.node_ids[i] - previous);
    previous = direct.node_ids[i];
    const auto ids = direct.features_of(i);
    w.Varint(ids.size());
    for (uint32_t id : ids) w.Varint(id);
  }
}

// `features`: how many features the direct index may name.
Status ReadDirect(Reader& r, uint64_t features, DirectIndex* direct) {
  uint8_t levels_up = 0;
  uint64_t nodes = 0;
  if (!r.U8(&levels_up) || !r.Count(&nodes, 2)) return r.Error();
  direct->levels_up = levels_up;
  direct->node_ids.resize(nodes);
  direct->offsets.assign(1, 0);
  direct->feature_ids.clear();
  uint64_t node = 0;
  for (size_t i = 0; i < nodes; ++i) {
    uint64_t delta = 0, count = 0;
    if (!r.Varint(&delta) || !r.Count(&count, 1)) return r.Error();
    // Checked before adding, as for BoW word ids: a 64-bit delta could wrap `node`.
    if (delta > 0xFFFFFFFFull - node) return r.Error("direct index node id out of range");
    node += delta;
    direct->node_ids[i] = NodeId(node);
    for (uint64_t j = 0; j < count; ++j) {
      uint64_t id = 0;
      if (!r.Varint(&id) || id >= features) return r.Error("direct index names a missing feature");
      direct->feature_ids.push_back(uint32_t(id));
    }
    direct->offsets.push_back(uint32_t(direct->feature_ids.size()));
  }
  if (nodes == 0) direct->offsets.clear();
  return Status::Ok();
}

// The geometry section of a version-2 features value: a flags byte (1: camera, 2: depths), the
// camera (width, height, fx, fy, cx, cy, model name, coefficients), then one float32 depth per
// keypoint.
constexpr uint8_t kGeometryCamera = 1;
constexpr uint8_t kGeometryDepth = 2;

void WriteGeometry(Writer& w, const FrameGeometry& geometry) {
  w.U8(uint8_t((geometry.camera ? kGeometryCamera : 0) |
               (geometry.depth_m.empty() ? 0 : kGeometryDepth)));
  if (const auto& camera = geometry.camera) {
    w.U32(uint32_t(camera->width));
    w.U32(uint32_t(camera->height));
    for (double v : {camera->fx, camera->fy, camera->cx, camera->cy}) w.F64(v);
    w.String(camera->distortion_model);
    w.Varint(camera->distortion.size());
    for (double v : camera->distortion) w.F64(v);
  }
  if (!geometry.depth_m.empty()) {
    w.Raw(geometry.depth_m.data(), geometry.depth_m.size() * sizeof(float));
  }
}

// `keypoints`: how many depths a depth section holds. Ends the value.
Status ReadGeometry(Reader& r, size_t keypoints, FrameGeometry* geometry) {
  uint8_t flags = 0;
  if (!r.U8(&flags)) return r.Error();
  if (flags & ~(kGeometryCamera | kGeometryDepth)) return r.Error("unknown geometry flags");
  if (flags & kGeometryCamera) {
    Camera camera;
    uint32_t width = 0, height = 0;
    uint64_t coefficients = 0;
    if (!r.U32(&width) || !r.U32(&height) || !r.F64(&camera.fx) || !r.F64(&camera.fy) ||
        !r.F64(&camera.cx) || !r.F64(&camera.cy) || !r.String(&camera.distortion_model) ||
        !r.Count(&coefficients, sizeof(double))) {
      return r.Error();
    }
    camera.width = int(std::min<uint32_t>(width, INT_MAX));
    camera.height = int(std::min<uint32_t>(height, INT_MAX));
    camera.distortion.resize(coefficients);
    for (double& v : camera.distortion) {
      if (!r.F64(&v)) return r.Error();
    }
    if (Status valid = camera.Validate("camera"); !valid.ok()) {
      return Status::Corruption("features: the stored camera is invalid: " + valid.message());
    }
    geometry->camera = std::move(camera);
  }
  if (flags & kGeometryDepth) {
    geometry->depth_m.resize(keypoints);
    if (!r.Raw(geometry->depth_m.data(), keypoints * sizeof(float))) return r.Error();
    for (float depth : geometry->depth_m) {
      if (!(depth >= 0) || !std::isfinite(depth))
        return r.Error("a stored keypoint depth is invalid");
    }
  }
  return Status::Ok();
}

// ---- JSON config -----------------------------------------------------------------------------

using Json = nlohmann::json;

const char* BaselineName(LikelihoodBaseline baseline) {
  return baseline == LikelihoodBaseline::kNone ? "none" : "median";
}

Result<LikelihoodBaseline> ParseBaseline(const std::string& name) {
  if (name == "none") return LikelihoodBaseline::kNone;
  if (name == "median") return LikelihoodBaseline::kMedian;
  return Status::InvalidArgument("unknown likelihood baseline \"" + name +
                                 "\" (expected none or median)");
}

Json BandJson(const DepthBand& band) {
  return {{"near_m", band.near_m}, {"far_m", band.far_m}};
}

Json EncodeDepth(const DepthConfig& d) {
  const RefineConfig& r = d.refine;
  const DepthFilterConfig& f = d.filter;
  const NearestLayerConfig& n = f.nearest_layer;
  const AppearedLayerConfig& a = f.appeared_layer;
  Json filter = {{"format",
                  {{"metres_per_unit", f.format.metres_per_unit},
                   {"float_metres_per_unit", f.format.float_metres_per_unit},
                   {"min_depth_m", f.format.min_depth_m},
                   {"max_depth_m", f.format.max_depth_m}}},
                 {"mean_mode", MeanDepthModeName(f.mean_mode)},
                 {"threshold_m", f.threshold_m},
                 {"persistence", f.persistence},
                 {"static_window", f.static_window},
                 {"warmup_frames", f.warmup_frames},
                 {"band_policy", BandPolicyName(f.band_policy)},
                 {"rise_band", BandJson(f.rise_band)},
                 {"fall_band", BandJson(f.fall_band)},
                 {"nearest_layer",
                  {{"bin_m", n.bin_m},
                   {"bin_noise_fraction", n.bin_noise_fraction},
                   {"min_gap_m", n.min_gap_m},
                   {"max_extent_m", n.max_extent_m},
                   {"min_layer_fraction", n.min_layer_fraction},
                   {"max_layer_fraction", n.max_layer_fraction}}},
                 {"appeared_layer",
                  {{"bin_m", a.bin_m},
                   {"min_bin_excess", a.min_bin_excess},
                   {"merge_gap_m", a.merge_gap_m},
                   {"min_layer_fraction", a.min_layer_fraction},
                   {"margin_m", a.margin_m}}},
                 {"feature_window_radius", f.feature_window_radius},
                 {"remove_features_without_depth", f.remove_features_without_depth},
                 {"use_range", f.use_range},
                 {"rebaseline_after", f.rebaseline_after}};
  return {{"refine_boxes", d.refine_boxes},
          {"refine",
           {{"bin_m", r.bin_m},
            {"min_mode_fraction", r.min_mode_fraction},
            {"edge_ratio", r.edge_ratio},
            {"min_half_extent_m", r.min_half_extent_m},
            {"max_half_extent_m", r.max_half_extent_m},
            {"min_component_fraction", r.min_component_fraction},
            {"dilate_px", r.dilate_px},
            {"min_valid_fraction", r.min_valid_fraction}}},
          {"stream_filter", d.stream_filter},
          {"filter", std::move(filter)}};
}

Json EncodeLoopClosure(const LoopClosureConfig& l) {
  return {{"likelihood_similarity", SimilarityMeasureName(l.likelihood_similarity)},
          {"rehearsal_similarity", SimilarityMeasureName(l.rehearsal_similarity)},
          {"likelihood_baseline", BaselineName(l.likelihood_baseline)},
          {"scoring", ScoringName(l.scoring)},
          {"loop_threshold", l.loop_threshold},
          {"rehearsal_threshold", l.rehearsal_threshold},
          {"short_term_memory", l.short_term_memory},
          {"no_loop_stay", l.no_loop_stay},
          {"loop_to_no_loop", l.loop_to_no_loop},
          {"transition_sigma", l.transition_sigma},
          {"transition_radius", l.transition_radius},
          {"hypothesis_radius", l.hypothesis_radius},
          {"min_candidates", l.min_candidates},
          {"min_similarity_excess", l.min_similarity_excess},
          {"max_working_memory", uint64_t(l.max_working_memory)},
          {"time_budget_ms", l.time_budget_ms},
          {"retrieval_radius", l.retrieval_radius},
          {"max_retrieved", l.max_retrieved}};
}

// Reads the members of one JSON object into config fields, keeping the first error. A missing
// member keeps the field's default unless it is required; a member of the wrong type is
// CORRUPTION, an out-of-range number or an unknown name INVALID_ARGUMENT, both naming the key
// by its path ("depth.filter.threshold_m").
class Fields {
 public:
  Fields(const Json* object, std::string path, Status* error)
      : object_(object), path_(std::move(path)), error_(error) {}

  // A nested object; absent (every read keeps its default) when missing and not required.
  Fields Object(const char* key, bool required = false) {
    const Json* value = Find(key, required);
    if (value && !value->is_object()) {
      Fail(Status::Corruption(Name(key) + ": expected an object, got " + value->type_name()));
      value = nullptr;
    }
    return Fields(value, Name(key), error_);
  }

  void Get(const char* key, int* out, bool required = false) {
    int64_t v = 0;
    if (Integer(key, required, INT_MIN, INT_MAX, &v)) *out = int(v);
  }
  void Get(const char* key, int64_t* out, bool required = false) {
    int64_t v = 0;
    if (Integer(key, required, INT64_MIN, INT64_MAX, &v)) *out = v;
  }
  void Get(const char* key, uint32_t* out, bool required = false) {
    int64_t v = 0;
    if (Integer(key, required, 0, UINT32_MAX, &v)) *out = uint32_t(v);
  }
  void Get(const char* key, size_t* out, bool required = false) {
    const Json* value = Find(key, required);
    if (!value) return;
    if (!value->is_number_integer()) return TypeError(key, "an integer", *value);
    if (value->is_number_unsigned()) {
      *out = size_t(value->get<uint64_t>());
    } else if (value->get<int64_t>() >= 0) {
      *out = size_t(value->get<int64_t>());
    } else {
      Fail(Status::InvalidArgument(Name(key) + " must not be negative"));
    }
  }
  void Get(const char* key, double* out, bool required = false) {
    const Json* value = Find(key, required);
    if (!value) return;
    if (!value->is_number()) return TypeError(key, "a number", *value);
    *out = value->get<double>();
  }
  void Get(const char* key, float* out, bool required = false) {
    const Json* value = Find(key, required);
    if (!value) return;
    if (!value->is_number()) return TypeError(key, "a number", *value);
    const double v = value->get<double>();
    if (std::isfinite(v) && std::fabs(v) > double(FLT_MAX)) {
      return Fail(Status::InvalidArgument(Name(key) + " is out of range for a float"));
    }
    *out = float(v);
  }
  void Get(const char* key, bool* out, bool required = false) {
    const Json* value = Find(key, required);
    if (!value) return;
    if (!value->is_boolean()) return TypeError(key, "true or false", *value);
    *out = value->get<bool>();
  }
  void Get(const char* key, std::vector<int>* out, bool required = false) {
    const Json* value = Find(key, required);
    if (!value) return;
    if (!value->is_array()) return TypeError(key, "an array of integers", *value);
    std::vector<int> items;
    for (const Json& item : *value) {
      if (!item.is_number_integer() ||
          (item.is_number_unsigned()
               ? item.get<uint64_t>() > uint64_t(INT_MAX)
               : (item.get<int64_t>() < INT_MIN || item.get<int64_t>() > INT_MAX))) {
        return Fail(Status::Corruption(Name(key) + ": expected an array of integers"));
      }
      items.push_back(int(item.get<int64_t>()));
    }
    *out = std::move(items);
  }
  void Get(const char* key, DepthBand* out, bool required = false) {
    Fields band = Object(key, required);
    band.Get("near_m", &out->near_m, /*required=*/band.present());
    band.Get("far_m", &out->far_m, /*required=*/band.present());
  }
  // An enum by name through its Parse function.
  template <typename E, typename Parse>
  void Enum(const char* key, E* out, Parse parse, bool required = false) {
    const Json* value = Find(key, required);
    if (!value) return;
    if (!value->is_string()) return TypeError(key, "a name", *value);
    auto parsed = parse(value->get<std::string>());
    if (!parsed.ok()) return Fail(parsed.status().WithContext(Name(key)));
    *out = *parsed;
  }

  bool present() const { return object_ != nullptr; }

 private:
  std::string Name(const char* key) const { return path_.empty() ? key : path_ + "." + key; }

  const Json* Find(const char* key, bool required) {
    if (!error_->ok()) return nullptr;
    if (!object_) {
      // A required member of an absent optional section: the section's absence is allowed.
      return nullptr;
    }
    auto it = object_->find(key);
    if (it == object_->end()) {
      if (required) Fail(Status::Corruption(Name(key) + " is missing"));
      return nullptr;
    }
    return &*it;
  }

  bool Integer(const char* key, bool required, int64_t min, int64_t max, int64_t* out) {
    const Json* value = Find(key, required);
    if (!value) return false;
    if (!value->is_number_integer()) {
      TypeError(key, "an integer", *value);
      return false;
    }
    if (value->is_number_unsigned()
            ? value->get<uint64_t>() > uint64_t(max)
            : (value->get<int64_t>() < min || value->get<int64_t>() > max)) {
      Fail(Status::InvalidArgument(Name(key) + " is out of range"));
      return false;
    }
    *out = value->get<int64_t>();
    return true;
  }

  void TypeError(const char* key, const char* expected, const Json& value) {
    Fail(Status::Corruption(Name(key) + ": expected " + expected + ", got " + value.type_name()));
  }
  void Fail(Status status) {
    if (error_->ok()) *error_ = std::move(status);
  }

  const Json* object_;
  std::string path_;
  Status* error_;
};

void DecodeDepth(Fields depth, DepthConfig* d) {
  depth.Get("refine_boxes", &d->refine_boxes);
  Fields refine = depth.Object("refine");
  RefineConfig& r = d->refine;
  refine.Get("bin_m", &r.bin_m);
  refine.Get("min_mode_fraction", &r.min_mode_fraction);
  refine.Get("edge_ratio", &r.edge_ratio);
  refine.Get("min_half_extent_m", &r.min_half_extent_m);
  refine.Get("max_half_extent_m", &r.max_half_extent_m);
  refine.Get("min_component_fraction", &r.min_component_fraction);
  refine.Get("dilate_px", &r.dilate_px);
  refine.Get("min_valid_fraction", &r.min_valid_fraction);
  depth.Get("stream_filter", &d->stream_filter);

  Fields filter = depth.Object("filter");
  DepthFilterConfig& f = d->filter;
  Fields format = filter.Object("format");
  format.Get("metres_per_unit", &f.format.metres_per_unit);
  format.Get("float_metres_per_unit", &f.format.float_metres_per_unit);
  format.Get("min_depth_m", &f.format.min_depth_m);
  format.Get("max_depth_m", &f.format.max_depth_m);
  filter.Enum("mean_mode", &f.mean_mode, ParseMeanDepthMode);
  filter.Get("threshold_m", &f.threshold_m);
  filter.Get("persistence", &f.persistence);
  filter.Get("static_window", &f.static_window);
  filter.Get("warmup_frames", &f.warmup_frames);
  filter.Enum("band_policy", &f.band_policy, ParseBandPolicy);
  filter.Get("rise_band", &f.rise_band);
  filter.Get("fall_band", &f.fall_band);
  Fields nearest = filter.Object("nearest_layer");
  NearestLayerConfig& n = f.nearest_layer;
  nearest.Get("bin_m", &n.bin_m);
  nearest.Get("bin_noise_fraction", &n.bin_noise_fraction);
  nearest.Get("min_gap_m", &n.min_gap_m);
  nearest.Get("max_extent_m", &n.max_extent_m);
  nearest.Get("min_layer_fraction", &n.min_layer_fraction);
  nearest.Get("max_layer_fraction", &n.max_layer_fraction);
  Fields appeared = filter.Object("appeared_layer");
  AppearedLayerConfig& a = f.appeared_layer;
  appeared.Get("bin_m", &a.bin_m);
  appeared.Get("min_bin_excess", &a.min_bin_excess);
  appeared.Get("merge_gap_m", &a.merge_gap_m);
  appeared.Get("min_layer_fraction", &a.min_layer_fraction);
  appeared.Get("margin_m", &a.margin_m);
  filter.Get("feature_window_radius", &f.feature_window_radius);
  filter.Get("remove_features_without_depth", &f.remove_features_without_depth);
  filter.Get("use_range", &f.use_range);
  filter.Get("rebaseline_after", &f.rebaseline_after);
}

void DecodeLoopClosure(Fields loop, LoopClosureConfig* l) {
  loop.Enum("likelihood_similarity", &l->likelihood_similarity, ParseSimilarityMeasure);
  loop.Enum("rehearsal_similarity", &l->rehearsal_similarity, ParseSimilarityMeasure);
  loop.Enum("likelihood_baseline", &l->likelihood_baseline, ParseBaseline);
  loop.Enum("scoring", &l->scoring, ParseScoring);
  loop.Get("loop_threshold", &l->loop_threshold);
  loop.Get("rehearsal_threshold", &l->rehearsal_threshold);
  loop.Get("short_term_memory", &l->short_term_memory);
  loop.Get("no_loop_stay", &l->no_loop_stay);
  loop.Get("loop_to_no_loop", &l->loop_to_no_loop);
  loop.Get("transition_sigma", &l->transition_sigma);
  loop.Get("transition_radius", &l->transition_radius);
  loop.Get("hypothesis_radius", &l->hypothesis_radius);
  loop.Get("min_candidates", &l->min_candidates);
  loop.Get("min_similarity_excess", &l->min_similarity_excess);
  loop.Get("max_working_memory", &l->max_working_memory);
  loop.Get("time_budget_ms", &l->time_budget_ms);
  loop.Get("retrieval_radius", &l->retrieval_radius);
  loop.Get("max_retrieved", &l->max_retrieved);
}

}  // namespace

std::string PlaceKey(PlaceId id) {
  std::string key(4, '\0');
  for (int i = 0; i < 4; ++i) key[size_t(i)] = char(uint8_t(id >> (24 - 8 * i)));
  return key;
}

Result<PlaceId> DecodePlaceKey(std::string_view key) {
  if (key.size() != 4)
    return Status::Corruption("place key must be 4 bytes, got " + std::to_string(key.size()));
  PlaceId id = 0;
  for (char c : key) id = (id << 8) | uint8_t(c);
  return id;
}

std::string U64Key(uint64_t value) {
  std::string key(8, '\0');
  for (int i = 0; i < 8; ++i) key[size_t(i)] = char(uint8_t(value >> (56 - 8 * i)));
  return key;
}

Result<uint64_t> DecodeU64Key(std::string_view key) {
  if (key.size() != 8)
    return Status::Corruption("key must be 8 bytes, got " + std::to_string(key.size()));
  uint64_t value = 0;
  for (char c : key) value = (value << 8) | uint8_t(c);
  return value;
}

std::string EncodePlaceRecord(const PlaceRecord& record) {
  Writer w;
  w.U8(kRecordV2);
  w.U32(record.id);
  WriteMetadata(w, record.metadata);
  WriteCounts(w, record.counts);
  WriteBoxes(w, record.boxes_used);
  return w.Take();
}

Result<PlaceRecord> DecodePlaceRecord(std::string_view bytes) {
  Reader r(bytes, "place record");
  uint8_t version = 0;
  PLACEDB_RETURN_IF_ERROR(r.Version(kFormatV1, kRecordV2, &version));
  PlaceRecord record;
  if (!r.U32(&record.id) || !ReadMetadata(r, &record.metadata) ||
      !ReadCounts(r, &record.counts, version) || !ReadBoxes(r, &record.boxes_used) || !r.Done()) {
    return r.Error();
  }
  return record;
}

namespace {

void WriteBow(Writer& w, const BowVector& bow) {
  w.Varint(bow.size());
  WordId previous = 0;
  for (const BowEntry& e : bow) {
    w.Varint(e.word - previous);
    w.F32(e.weight);
    previous = e.word;
  }
}

Status ReadBow(Reader& r, BowVector* bow) {
  uint64_t n = 0;
  if (!r.Count(&n, 5)) return r.Error();
  bow->resize(n);
  uint64_t word = 0;
  for (size_t i = 0; i < n; ++i) {
    uint64_t delta = 0;
    if (!r.Varint(&delta) || !r.F32(&(*bow)[i].weight)) return r.Error();
    if (i > 0 && delta == 0) return r.Error("word ids not strictly increasing");
    // Checked before adding: a 64-bit delta could wrap `word` below the previous id (found by
    // tests/fuzz/fuzz_codec).
    if (delta > 0xFFFFFFFEull - word) return r.Error("word id out of range");
    word += delta;
    (*bow)[i].word = WordId(word);
  }
  return Status::Ok();
}

}  // namespace

std::string EncodeBow(const BowVector& bow) {
  Writer w;
  w.U8(kFormatV1);
  WriteBow(w, bow);
  return w.Take();
}

std::string EncodeBowWithDirect(const BowVector& bow, const DirectIndex& direct) {
  Writer w;
  w.U8(kBowWithDirectV2);
  WriteBow(w, bow);
  WriteDirect(w, direct);
  return w.Take();
}

Status DecodeBowValue(std::string_view bytes, BowVector* bow, std::optional<DirectIndex>* direct) {
  Reader r(bytes, "bow vector");
  uint8_t version = 0;
  PLACEDB_RETURN_IF_ERROR(r.Version(kFormatV1, kBowWithDirectV2, &version));
  PLACEDB_RETURN_IF_ERROR(ReadBow(r, bow));
  if (version == kFormatV1) {
    if (!r.Done()) return r.Error("trailing bytes");
    if (direct) direct->reset();
    return Status::Ok();
  }
  // The features it names are checked against the place's features when both are read
  // (DirectIndexFits): the vector alone does not know how many there are.
  DirectIndex index;
  PLACEDB_RETURN_IF_ERROR(ReadDirect(r, uint64_t(1) << 32, &index));
  if (!r.Done()) return r.Error("trailing bytes");
  if (direct) *direct = std::move(index);
  return Status::Ok();
}

Result<BowVector> DecodeBow(std::string_view bytes) {
  BowVector bow;
  PLACEDB_RETURN_IF_ERROR(DecodeBowValue(bytes, &bow, nullptr));
  return bow;
}

bool DirectIndexFits(const DirectIndex& direct, size_t features) {
  return std::all_of(direct.feature_ids.begin(), direct.feature_ids.end(),
                     [&](uint32_t id) { return id < features; });
}

std::string EncodeFeatures(const FeatureSet& features, const DirectIndex& direct,
                           const FrameGeometry& geometry) {
  Writer w;
  w.U8(geometry.empty() ? kFeaturesV1 : kFeaturesV2);
  w.U32(uint32_t(features.image_width));
  w.U32(uint32_t(features.image_height));
  w.Varint(features.size());
  WriteKeypoints(w, features.keypoints);
  for (const Descriptor256& d : features.descriptors) w.Raw(d.bytes(), Descriptor256::kBytes);
  WriteDirect(w, direct);
  if (!geometry.empty()) WriteGeometry(w, geometry);
  return w.Take();
}

Status DecodeFeatures(std::string_view bytes, FeatureSet* features, DirectIndex* direct,
                      FrameGeometry* geometry) {
  if (!bytes.empty() &&
      (uint8_t(bytes[0]) == kFloatFeaturesV1 || uint8_t(bytes[0]) == kFloatFeaturesV2)) {
    return Status::Corruption(
        "features: a float (SIFT) feature payload where ORB features were "
        "expected");
  }
  Reader r(bytes, "features");
  uint8_t version = 0;
  PLACEDB_RETURN_IF_ERROR(r.Version(kFeaturesV1, kFeaturesV2, &version));
  uint32_t width = 0, height = 0;
  uint64_t n = 0;
  if (!r.U32(&width) || !r.U32(&height) || !r.Count(&n, kKeypointBytes + Descriptor256::kBytes)) {
    return r.Error();
  }
  features->image_width = int(width);
  features->image_height = int(height);
  features->keypoints.resize(n);
  features->descriptors.resize(n);
  if (!ReadKeypoints(r, &features->keypoints)) return r.Error();
  for (Descriptor256& d : features->descriptors) {
    uint8_t raw[Descriptor256::kBytes];
    if (!r.Raw(raw, sizeof raw)) return r.Error();
    d = Descriptor256::FromBytes(raw);
  }
  PLACEDB_RETURN_IF_ERROR(ReadDirect(r, n, direct));
  FrameGeometry stored;
  if (version == kFeaturesV2) PLACEDB_RETURN_IF_ERROR(ReadGeometry(r, n, &stored));
  if (!r.Done()) return r.Error("trailing bytes");
  if (geometry) *geometry = std::move(stored);
  if (Status valid = ValidateFeatures(*features); !valid.ok()) {
    return Status::Corruption("features: stored features are invalid: " + valid.message());
  }
  return Status::Ok();
}

std::string EncodeFloatFeatures(const FloatFeatureSet& features, const DirectIndex& direct,
                                const FrameGeometry& geometry) {
  Writer w;
  w.U8(geometry.empty() ? kFloatFeaturesV1 : kFloatFeaturesV2);
  w.U32(uint32_t(features.image_width));
  w.U32(uint32_t(features.image_height));
  w.Varint(features.size());
  WriteKeypoints(w, features.keypoints);
  // 128 float32 per keypoint, little-endian (the host order, checked above).
  const size_t floats = std::min(features.descriptors.size(), features.size() * kSiftDimensions);
  w.Raw(features.descriptors.data(), floats * sizeof(float));
  for (size_t i = floats; i < features.size() * kSiftDimensions; ++i) w.F32(0);
  WriteDirect(w, direct);
  if (!geometry.empty()) WriteGeometry(w, geometry);
  return w.Take();
}

Status DecodeFloatFeatures(std::string_view bytes, FloatFeatureSet* features, DirectIndex* direct,
                           FrameGeometry* geometry) {
  if (!bytes.empty() && (uint8_t(bytes[0]) == kFeaturesV1 || uint8_t(bytes[0]) == kFeaturesV2)) {
    return Status::Corruption(
        "float features: a binary (ORB) feature payload where SIFT "
        "features were expected");
  }
  Reader r(bytes, "float features");
  uint8_t version = 0;
  PLACEDB_RETURN_IF_ERROR(r.Version(kFloatFeaturesV1, kFloatFeaturesV2, &version));
  constexpr size_t kDescriptorBytes = kSiftDimensions * sizeof(float);
  uint32_t width = 0, height = 0;
  uint64_t n = 0;
  if (!r.U32(&width) || !r.U32(&height) || !r.Count(&n, kKeypointBytes + kDescriptorBytes)) {
    return r.Error();
  }
  features->image_width = int(width);
  features->image_height = int(height);
  features->keypoints.resize(n);
  if (!ReadKeypoints(r, &features->keypoints)) return r.Error();
  // n is bounded by the input's length (Count), so n * 512 cannot overflow.
  features->descriptors.resize(n * kSiftDimensions);
  if (!r.Raw(features->descriptors.data(), n * kDescriptorBytes)) return r.Error();
  PLACEDB_RETURN_IF_ERROR(ReadDirect(r, n, direct));
  FrameGeometry stored;
  if (version == kFloatFeaturesV2) PLACEDB_RETURN_IF_ERROR(ReadGeometry(r, n, &stored));
  if (!r.Done()) return r.Error("trailing bytes");
  if (geometry) *geometry = std::move(stored);
  if (Status valid = ValidateFloatFeatures(*features); !valid.ok()) {
    return Status::Corruption("float features: stored features are invalid: " + valid.message());
  }
  return Status::Ok();
}

std::string EncodeLocalFeatures(const LocalFeatures& features, const DirectIndex& direct,
                                const FrameGeometry& geometry) {
  if (const FeatureSet* orb = features.orb()) return EncodeFeatures(*orb, direct, geometry);
  return EncodeFloatFeatures(*features.sift(), direct, geometry);
}

Status DecodeLocalFeatures(std::string_view bytes, FeatureType type, LocalFeatures* features,
                           DirectIndex* direct, FrameGeometry* geometry) {
  if (type == FeatureType::kSift) {
    FloatFeatureSet sift;
    PLACEDB_RETURN_IF_ERROR(DecodeFloatFeatures(bytes, &sift, direct, geometry));
    *features = std::move(sift);
  } else {
    FeatureSet orb;
    PLACEDB_RETURN_IF_ERROR(DecodeFeatures(bytes, &orb, direct, geometry));
    *features = std::move(orb);
  }
  return Status::Ok();
}

std::string EncodeDatabaseConfig(const DatabaseConfig& c) {
  Json j;
  j["format"] = kConfigFormat;
  j["feature_type"] = FeatureTypeName(c.feature_type);
  j["orb"] = {{"max_features", c.orb.max_features},
              {"scale_factor", c.orb.scale_factor},
              {"levels", c.orb.levels},
              {"edge_threshold", c.orb.edge_threshold},
              {"patch_size", c.orb.patch_size},
              {"fast_threshold", c.orb.fast_threshold}};
  j["sift"] = {{"max_features", c.sift.max_features},
               {"octave_layers", c.sift.octave_layers},
               {"contrast_threshold", c.sift.contrast_threshold},
               {"edge_threshold", c.sift.edge_threshold},
               {"sigma", c.sift.sigma}};
  j["filter"] = {{"method", FilterMethodName(c.filter.method)},
                 {"sensitivity_threshold", c.filter.sensitivity_threshold},
                 {"place_threshold", c.filter.place_threshold}};
  j["dynamic_classes"] = c.dynamic_classes;
  j["min_box_confidence"] = c.min_box_confidence;
  j["scoring"] = ScoringName(c.scoring);
  const VerificationConfig& v = c.verification;
  j["verification"] = {{"mode", VerificationModeName(v.mode)},
                       {"levels_up", v.levels_up},
                       {"min_inliers", v.min_inliers},
                       {"max_hamming", v.max_hamming},
                       {"ratio", v.ratio},
                       {"ransac_threshold_px", v.ransac_threshold_px},
                       {"ransac_confidence", v.ransac_confidence},
                       {"ransac_max_iterations", v.ransac_max_iterations},
                       {"candidates", v.candidates},
                       {"rerank", v.rerank}};
  const BoxRefinementConfig& b = c.box_refinement;
  j["box_refinement"] = {{"method", BoxRefinementName(b.method)},
                         {"context", b.context},
                         {"max_side", b.max_side},
                         {"iterations", b.iterations},
                         {"min_fraction", b.min_fraction},
                         {"max_fraction", b.max_fraction},
                         {"dilate_px", b.dilate_px}};
  j["static_feature_budget"] = c.static_feature_budget;
  j["short_term"] = {{"enabled", c.short_term.enabled},
                     {"horizon_ns", c.short_term.horizon_ns},
                     {"max_places", c.short_term.max_places},
                     {"weight", c.short_term.weight}};
  j["depth"] = EncodeDepth(c.depth);
  j["loop_closure"] = EncodeLoopClosure(c.loop_closure);
  j["verify_loops"] = c.verify_loops;
  return j.dump();
}

Result<DatabaseConfig> DecodeDatabaseConfig(std::string_view text) {
  Json j = Json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) return Status::Corruption("map config is not valid JSON");
  DatabaseConfig c;
  Status error;
  Fields root(&j, "", &error);
  int format = 0;
  root.Get("format", &format, /*required=*/true);
  if (error.ok() && (format < 1 || format > kConfigFormat)) {
    return Status::Corruption("map config: unknown format " + std::to_string(format));
  }
  // Format 1 (before RGB-D) has none of feature_type, sift, depth, loop_closure: the defaults
  // (an ORB map without depth settings) are exactly what those maps did.
  root.Enum("feature_type", &c.feature_type, ParseFeatureType);
  Fields orb = root.Object("orb", /*required=*/true);
  orb.Get("max_features", &c.orb.max_features, true);
  orb.Get("scale_factor", &c.orb.scale_factor, true);
  orb.Get("levels", &c.orb.levels, true);
  orb.Get("edge_threshold", &c.orb.edge_threshold, true);
  orb.Get("patch_size", &c.orb.patch_size, true);
  orb.Get("fast_threshold", &c.orb.fast_threshold, true);
  Fields sift = root.Object("sift");
  sift.Get("max_features", &c.sift.max_features);
  sift.Get("octave_layers", &c.sift.octave_layers);
  sift.Get("contrast_threshold", &c.sift.contrast_threshold);
  sift.Get("edge_threshold", &c.sift.edge_threshold);
  sift.Get("sigma", &c.sift.sigma);
  Fields filter = root.Object("filter", true);
  filter.Enum("method", &c.filter.method, ParseFilterMethod, true);
  filter.Get("sensitivity_threshold", &c.filter.sensitivity_threshold, true);
  filter.Get("place_threshold", &c.filter.place_threshold, true);
  root.Get("dynamic_classes", &c.dynamic_classes, true);
  root.Get("min_box_confidence", &c.min_box_confidence, true);
  root.Enum("scoring", &c.scoring, ParseScoring, true);
  Fields v = root.Object("verification", true);
  v.Enum("mode", &c.verification.mode, ParseVerificationMode, true);
  v.Get("levels_up", &c.verification.levels_up, true);
  v.Get("min_inliers", &c.verification.min_inliers, true);
  v.Get("max_hamming", &c.verification.max_hamming, true);
  v.Get("ratio", &c.verification.ratio, true);
  v.Get("ransac_threshold_px", &c.verification.ransac_threshold_px, true);
  v.Get("ransac_confidence", &c.verification.ransac_confidence, true);
  v.Get("ransac_max_iterations", &c.verification.ransac_max_iterations, true);
  v.Get("candidates", &c.verification.candidates, true);
  // Maps written before format 3 keep what they did: whole boxes, the whole frame's feature
  // budget, no tier, no re-ranking.
  c.verification.rerank = false;
  c.static_feature_budget = false;
  root.Get("static_feature_budget", &c.static_feature_budget, format >= 3);
  c.box_refinement.method = BoxRefinement::kNone;
  c.short_term.enabled = false;
  v.Get("rerank", &c.verification.rerank, format >= 3);
  Fields b = root.Object("box_refinement", format >= 3);
  b.Enum("method", &c.box_refinement.method, ParseBoxRefinement, format >= 3);
  b.Get("context", &c.box_refinement.context);
  b.Get("max_side", &c.box_refinement.max_side);
  b.Get("iterations", &c.box_refinement.iterations);
  b.Get("min_fraction", &c.box_refinement.min_fraction);
  b.Get("max_fraction", &c.box_refinement.max_fraction);
  b.Get("dilate_px", &c.box_refinement.dilate_px);
  Fields st = root.Object("short_term", format >= 3);
  st.Get("enabled", &c.short_term.enabled, format >= 3);
  st.Get("horizon_ns", &c.short_term.horizon_ns);
  st.Get("max_places", &c.short_term.max_places);
  st.Get("weight", &c.short_term.weight);
  DecodeDepth(root.Object("depth"), &c.depth);
  DecodeLoopClosure(root.Object("loop_closure"), &c.loop_closure);
  root.Get("verify_loops", &c.verify_loops);
  if (!error.ok()) return error.WithContext("map config");
  PLACEDB_RETURN_IF_ERROR(ValidateDatabaseConfig(c).WithContext("map config"));
  return c;
}

std::string EncodeInvalidObservation(const InvalidObservation& o) {
  Writer w;
  w.U8(kInvalidV2);
  w.U64(o.serial);
  WriteMetadata(w, o.metadata);
  WriteCounts(w, o.counts);
  WriteBoxes(w, o.boxes_used);
  w.String(o.reason);
  return w.Take();
}

Result<InvalidObservation> DecodeInvalidObservation(std::string_view bytes) {
  Reader r(bytes, "invalid observation");
  uint8_t version = 0;
  PLACEDB_RETURN_IF_ERROR(r.Version(kFormatV1, kInvalidV2, &version));
  InvalidObservation o;
  if (!r.U64(&o.serial) || !ReadMetadata(r, &o.metadata) || !ReadCounts(r, &o.counts, version) ||
      !ReadBoxes(r, &o.boxes_used) || !r.String(&o.reason) || !r.Done()) {
    return r.Error();
  }
  return o;
}

std::string EncodeThumbnail(const Thumbnail& t) {
  Writer w;
  w.U8(kFormatV1);
  w.Varint(t.width);
  w.Varint(t.height);
  w.Varint(t.source_width);
  w.Varint(t.source_height);
  w.Varint(t.dropped_keypoints.size());
  WriteKeypoints(w, t.dropped_keypoints);
  w.String(t.jpeg);
  return w.Take();
}

Result<Thumbnail> DecodeThumbnail(std::string_view bytes) {
  Reader r(bytes, "thumbnail");
  PLACEDB_RETURN_IF_ERROR(r.Version());
  Thumbnail t;
  uint64_t width = 0, height = 0, source_width = 0, source_height = 0, dropped = 0;
  if (!r.Varint(&width) || !r.Varint(&height) || !r.Varint(&source_width) ||
      !r.Varint(&source_height) || !r.Count(&dropped, kKeypointBytes)) {
    return r.Error();
  }
  t.dropped_keypoints.resize(dropped);
  if (!ReadKeypoints(r, &t.dropped_keypoints) || !r.String(&t.jpeg) || !r.Done()) {
    return r.Error();
  }
  if (width < 1 || height < 1 || width > kMaxThumbnailSide || height > kMaxThumbnailSide ||
      source_width < width || source_height < height || source_width > (1u << 20) ||
      source_height > (1u << 20)) {
    return Status::Corruption("thumbnail: sizes " + std::to_string(width) + "x" +
                              std::to_string(height) + " of " + std::to_string(source_width) + "x" +
                              std::to_string(source_height) + " are not a thumbnail's");
  }
  t.width = uint32_t(width);
  t.height = uint32_t(height);
  t.source_width = uint32_t(source_width);
  t.source_height = uint32_t(source_height);
  auto info =
      ReadImageInfo(std::span(reinterpret_cast<const uint8_t*>(t.jpeg.data()), t.jpeg.size()));
  if (!info.ok() || info->format != ImageFormat::kJpeg || info->width != t.width ||
      info->height != t.height) {
    return Status::Corruption("thumbnail: the JPEG's header does not describe a " +
                              std::to_string(width) + "x" + std::to_string(height) + " JPEG" +
                              (info.ok() ? "" : " (" + info.status().message() + ")"));
  }
  return t;
}

}  // namespace placedb
