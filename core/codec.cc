#include "core/codec.h"

#include <cstring>
#include <nlohmann/json.hpp>

namespace placedb {

namespace {

constexpr uint8_t kFormatV1 = 1;

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
    std::memcpy(out, in_.data() + pos_, n);
    pos_ += n;
    return true;
  }
  bool Done() const { return pos_ == in_.size(); }
  Status Error(const std::string& detail = "truncated or malformed") const {
    return Status::Corruption(std::string(what_) + ": " + detail + " at byte " +
                              std::to_string(pos_) + " of " + std::to_string(in_.size()));
  }
  Status Version() {
    uint8_t version = 0;
    if (!U8(&version)) return Error();
    if (version != kFormatV1) {
      return Status::Corruption(std::string(what_) + ": unknown format version " +
                                std::to_string(version));
    }
    return Status::Ok();
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

void WriteCounts(Writer& w, const FrameCounts& c) {
  w.U32(c.total);
  w.U32(c.dynamic);
  w.U32(c.static_);
  w.F64(c.dynamic_coverage);
}

bool ReadCounts(Reader& r, FrameCounts* c) {
  return r.U32(&c->total) && r.U32(&c->dynamic) && r.U32(&c->static_) &&
         r.F64(&c->dynamic_coverage) && c->dynamic + uint64_t(c->static_) == c->total;
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
  w.U8(kFormatV1);
  w.U32(record.id);
  WriteMetadata(w, record.metadata);
  WriteCounts(w, record.counts);
  WriteBoxes(w, record.boxes_used);
  return w.Take();
}

Result<PlaceRecord> DecodePlaceRecord(std::string_view bytes) {
  Reader r(bytes, "place record");
  PLACEDB_RETURN_IF_ERROR(r.Version());
  PlaceRecord record;
  if (!r.U32(&record.id) || !ReadMetadata(r, &record.metadata) || !ReadCounts(r, &record.counts) ||
      !ReadBoxes(r, &record.boxes_used) || !r.Done()) {
    return r.Error();
  }
  return record;
}

std::string EncodeBow(const BowVector& bow) {
  Writer w;
  w.U8(kFormatV1);
  w.Varint(bow.size());
  WordId previous = 0;
  for (const BowEntry& e : bow) {
    w.Varint(e.word - previous);
    w.F32(e.weight);
    previous = e.word;
  }
  return w.Take();
}

Result<BowVector> DecodeBow(std::string_view bytes) {
  Reader r(bytes, "bow vector");
  PLACEDB_RETURN_IF_ERROR(r.Version());
  uint64_t n = 0;
  if (!r.Count(&n, 5)) return r.Error();
  BowVector bow(n);
  uint64_t word = 0;
  for (size_t i = 0; i < n; ++i) {
    uint64_t delta = 0;
    if (!r.Varint(&delta) || !r.F32(&bow[i].weight)) return r.Error();
    if (i > 0 && delta == 0) return r.Error("word ids not strictly increasing");
    word += delta;
    if (word > 0xFFFFFFFEull) return r.Error("word id out of range");
    bow[i].word = WordId(word);
  }
  if (!r.Done()) return r.Error("trailing bytes");
  return bow;
}

std::string EncodeFeatures(const FeatureSet& features, const DirectIndex& direct) {
  Writer w;
  w.U8(kFormatV1);
  w.U32(uint32_t(features.image_width));
  w.U32(uint32_t(features.image_height));
  w.Varint(features.size());
  for (const Keypoint& kp : features.keypoints) {
    w.F32(kp.x);
    w.F32(kp.y);
    w.F32(kp.size);
    w.F32(kp.angle);
    w.F32(kp.response);
    w.U8(uint8_t(kp.octave));
  }
  for (const Descriptor256& d : features.descriptors) w.Raw(d.bytes(), Descriptor256::kBytes);
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
  return w.Take();
}

Status DecodeFeatures(std::string_view bytes, FeatureSet* features, DirectIndex* direct) {
  Reader r(bytes, "features");
  PLACEDB_RETURN_IF_ERROR(r.Version());
  uint32_t width = 0, height = 0;
  uint64_t n = 0;
  if (!r.U32(&width) || !r.U32(&height) || !r.Count(&n, 21 + 32)) return r.Error();
  features->image_width = int(width);
  features->image_height = int(height);
  features->keypoints.resize(n);
  features->descriptors.resize(n);
  for (Keypoint& kp : features->keypoints) {
    uint8_t octave = 0;
    if (!r.F32(&kp.x) || !r.F32(&kp.y) || !r.F32(&kp.size) || !r.F32(&kp.angle) ||
        !r.F32(&kp.response) || !r.U8(&octave)) {
      return r.Error();
    }
    kp.octave = octave;
  }
  for (Descriptor256& d : features->descriptors) {
    uint8_t raw[Descriptor256::kBytes];
    if (!r.Raw(raw, sizeof raw)) return r.Error();
    d = Descriptor256::FromBytes(raw);
  }
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
    node += delta;
    direct->node_ids[i] = NodeId(node);
    for (uint64_t j = 0; j < count; ++j) {
      uint64_t id = 0;
      if (!r.Varint(&id) || id >= n) return r.Error("direct index names a missing feature");
      direct->feature_ids.push_back(uint32_t(id));
    }
    direct->offsets.push_back(uint32_t(direct->feature_ids.size()));
  }
  if (nodes == 0) direct->offsets.clear();
  if (!r.Done()) return r.Error("trailing bytes");
  return ValidateFeatures(*features).WithContext("stored features");
}

std::string EncodeDatabaseConfig(const DatabaseConfig& c) {
  nlohmann::json j;
  j["format"] = 1;
  j["orb"] = {{"max_features", c.orb.max_features},
              {"scale_factor", c.orb.scale_factor},
              {"levels", c.orb.levels},
              {"edge_threshold", c.orb.edge_threshold},
              {"patch_size", c.orb.patch_size},
              {"fast_threshold", c.orb.fast_threshold}};
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
                       {"candidates", v.candidates}};
  return j.dump();
}

Result<DatabaseConfig> DecodeDatabaseConfig(std::string_view text) {
  nlohmann::json j = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) return Status::Corruption("map config is not valid JSON");
  DatabaseConfig c;
  try {
    if (j.at("format").get<int>() != 1) return Status::Corruption("map config: unknown format");
    const auto& orb = j.at("orb");
    c.orb.max_features = orb.at("max_features");
    c.orb.scale_factor = orb.at("scale_factor");
    c.orb.levels = orb.at("levels");
    c.orb.edge_threshold = orb.at("edge_threshold");
    c.orb.patch_size = orb.at("patch_size");
    c.orb.fast_threshold = orb.at("fast_threshold");
    const auto& filter = j.at("filter");
    auto method = ParseFilterMethod(filter.at("method").get<std::string>());
    if (!method.ok()) return method.status().WithContext("map config");
    c.filter.method = *method;
    c.filter.sensitivity_threshold = filter.at("sensitivity_threshold");
    c.filter.place_threshold = filter.at("place_threshold");
    c.dynamic_classes = j.at("dynamic_classes").get<std::vector<int>>();
    c.min_box_confidence = j.at("min_box_confidence");
    auto scoring = ParseScoring(j.at("scoring").get<std::string>());
    if (!scoring.ok()) return scoring.status().WithContext("map config");
    c.scoring = *scoring;
    const auto& v = j.at("verification");
    auto mode = ParseVerificationMode(v.at("mode").get<std::string>());
    if (!mode.ok()) return mode.status().WithContext("map config");
    c.verification.mode = *mode;
    c.verification.levels_up = v.at("levels_up");
    c.verification.min_inliers = v.at("min_inliers");
    c.verification.max_hamming = v.at("max_hamming");
    c.verification.ratio = v.at("ratio");
    c.verification.ransac_threshold_px = v.at("ransac_threshold_px");
    c.verification.ransac_confidence = v.at("ransac_confidence");
    c.verification.ransac_max_iterations = v.at("ransac_max_iterations");
    c.verification.candidates = v.at("candidates");
  } catch (const nlohmann::json::exception& e) {
    return Status::Corruption(std::string("map config: ") + e.what());
  }
  PLACEDB_RETURN_IF_ERROR(ValidateDatabaseConfig(c).WithContext("map config"));
  return c;
}

std::string EncodeInvalidObservation(const InvalidObservation& o) {
  Writer w;
  w.U8(kFormatV1);
  w.U64(o.serial);
  WriteMetadata(w, o.metadata);
  WriteCounts(w, o.counts);
  WriteBoxes(w, o.boxes_used);
  w.String(o.reason);
  return w.Take();
}

Result<InvalidObservation> DecodeInvalidObservation(std::string_view bytes) {
  Reader r(bytes, "invalid observation");
  PLACEDB_RETURN_IF_ERROR(r.Version());
  InvalidObservation o;
  if (!r.U64(&o.serial) || !ReadMetadata(r, &o.metadata) || !ReadCounts(r, &o.counts) ||
      !ReadBoxes(r, &o.boxes_used) || !r.String(&o.reason) || !r.Done()) {
    return r.Error();
  }
  return o;
}

}  // namespace placedb
