#include "server/convert.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace placedb::server {

// ---- Status -------------------------------------------------------------------------------------

grpc::StatusCode ToGrpcCode(StatusCode code) {
  switch (code) {
    case StatusCode::kOk:
      return grpc::StatusCode::OK;
    case StatusCode::kInvalidArgument:
      return grpc::StatusCode::INVALID_ARGUMENT;
    case StatusCode::kNotFound:
      return grpc::StatusCode::NOT_FOUND;
    case StatusCode::kAlreadyExists:
      return grpc::StatusCode::ALREADY_EXISTS;
    case StatusCode::kFailedPrecondition:
      return grpc::StatusCode::FAILED_PRECONDITION;
    case StatusCode::kResourceExhausted:
      return grpc::StatusCode::RESOURCE_EXHAUSTED;
    case StatusCode::kCorruption:
      return grpc::StatusCode::DATA_LOSS;
    case StatusCode::kIoError:
      return grpc::StatusCode::UNAVAILABLE;
    case StatusCode::kInternal:
      return grpc::StatusCode::INTERNAL;
    case StatusCode::kCancelled:
      return grpc::StatusCode::CANCELLED;
  }
  return grpc::StatusCode::INTERNAL;
}

grpc::Status ToGrpc(const Status& status) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(ToGrpcCode(status.code()), status.message());
}

grpc::Status ToGrpc(const Status& status, const std::string& context) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(ToGrpcCode(status.code()), context + ": " + status.message());
}

const char* GrpcCodeName(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return "OK";
    case grpc::StatusCode::CANCELLED:
      return "CANCELLED";
    case grpc::StatusCode::UNKNOWN:
      return "UNKNOWN";
    case grpc::StatusCode::INVALID_ARGUMENT:
      return "INVALID_ARGUMENT";
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return "DEADLINE_EXCEEDED";
    case grpc::StatusCode::NOT_FOUND:
      return "NOT_FOUND";
    case grpc::StatusCode::ALREADY_EXISTS:
      return "ALREADY_EXISTS";
    case grpc::StatusCode::PERMISSION_DENIED:
      return "PERMISSION_DENIED";
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return "RESOURCE_EXHAUSTED";
    case grpc::StatusCode::FAILED_PRECONDITION:
      return "FAILED_PRECONDITION";
    case grpc::StatusCode::ABORTED:
      return "ABORTED";
    case grpc::StatusCode::OUT_OF_RANGE:
      return "OUT_OF_RANGE";
    case grpc::StatusCode::UNIMPLEMENTED:
      return "UNIMPLEMENTED";
    case grpc::StatusCode::INTERNAL:
      return "INTERNAL";
    case grpc::StatusCode::UNAVAILABLE:
      return "UNAVAILABLE";
    case grpc::StatusCode::DATA_LOSS:
      return "DATA_LOSS";
    case grpc::StatusCode::UNAUTHENTICATED:
      return "UNAUTHENTICATED";
    default:
      return "UNKNOWN";
  }
}

std::string GrpcCodeLabel(grpc::StatusCode code) {
  std::string name = GrpcCodeName(code);
  std::transform(name.begin(), name.end(), name.begin(),
                 [](unsigned char c) { return char(std::tolower(c)); });
  return name;
}

// ---- Maps ---------------------------------------------------------------------------------------

namespace {

Status Invalid(const std::string& field, const std::string& what) {
  return Status::InvalidArgument(field + ": " + what);
}

// 700, 0.25, 1e+20: numbers in messages as a person writes them.
std::string Num(double v) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%g", v);
  return buffer;
}

Result<FilterMethod> FilterFromProto(v1::FilterMethod method) {
  switch (method) {
    case v1::FILTER_METHOD_UNSPECIFIED:
    case v1::FILTER_METHOD_KEYPOINT_IN_BOX:
      return FilterMethod::kKeypointInBox;
    case v1::FILTER_METHOD_NONE:
      return FilterMethod::kNone;
    case v1::FILTER_METHOD_CORNER_DISTANCE:
      return FilterMethod::kCornerDistance;
    case v1::FILTER_METHOD_EXACT_COVERAGE:
      return FilterMethod::kExactCoverage;
    default:
      return Invalid("config.filter.method", "unknown value " + std::to_string(int(method)));
  }
}

v1::FilterMethod FilterToProto(FilterMethod method) {
  switch (method) {
    case FilterMethod::kNone:
      return v1::FILTER_METHOD_NONE;
    case FilterMethod::kKeypointInBox:
      return v1::FILTER_METHOD_KEYPOINT_IN_BOX;
    case FilterMethod::kCornerDistance:
      return v1::FILTER_METHOD_CORNER_DISTANCE;
    case FilterMethod::kExactCoverage:
      return v1::FILTER_METHOD_EXACT_COVERAGE;
  }
  return v1::FILTER_METHOD_UNSPECIFIED;
}

Result<ScoringType> ScoringFromProto(v1::Scoring scoring) {
  switch (scoring) {
    case v1::SCORING_UNSPECIFIED:
    case v1::SCORING_L1:
      return ScoringType::kL1;
    case v1::SCORING_L2:
      return ScoringType::kL2;
    case v1::SCORING_CHI_SQUARE:
      return ScoringType::kChiSquare;
    case v1::SCORING_KL:
      return ScoringType::kKL;
    case v1::SCORING_BHATTACHARYYA:
      return ScoringType::kBhattacharyya;
    case v1::SCORING_DOT_PRODUCT:
      return ScoringType::kDotProduct;
    default:
      return Invalid("config.scoring", "unknown value " + std::to_string(int(scoring)));
  }
}

v1::Scoring ScoringToProto(ScoringType scoring) {
  switch (scoring) {
    case ScoringType::kL1:
      return v1::SCORING_L1;
    case ScoringType::kL2:
      return v1::SCORING_L2;
    case ScoringType::kChiSquare:
      return v1::SCORING_CHI_SQUARE;
    case ScoringType::kKL:
      return v1::SCORING_KL;
    case ScoringType::kBhattacharyya:
      return v1::SCORING_BHATTACHARYYA;
    case ScoringType::kDotProduct:
      return v1::SCORING_DOT_PRODUCT;
  }
  return v1::SCORING_UNSPECIFIED;
}

Result<VerificationMode> VerificationFromProto(v1::VerificationMode mode) {
  switch (mode) {
    case v1::VERIFICATION_MODE_UNSPECIFIED:
    case v1::VERIFICATION_MODE_DISABLED:
      return VerificationMode::kDisabled;
    case v1::VERIFICATION_MODE_DIRECT_INDEX:
      return VerificationMode::kDirectIndex;
    case v1::VERIFICATION_MODE_EXHAUSTIVE:
      return VerificationMode::kExhaustive;
    default:
      return Invalid("config.verification.mode", "unknown value " + std::to_string(int(mode)));
  }
}

v1::VerificationMode VerificationToProto(VerificationMode mode) {
  switch (mode) {
    case VerificationMode::kDisabled:
      return v1::VERIFICATION_MODE_DISABLED;
    case VerificationMode::kDirectIndex:
      return v1::VERIFICATION_MODE_DIRECT_INDEX;
    case VerificationMode::kExhaustive:
      return v1::VERIFICATION_MODE_EXHAUSTIVE;
  }
  return v1::VERIFICATION_MODE_UNSPECIFIED;
}

Result<BoxSource> BoxSourceFromProto(v1::BoxSource source) {
  switch (source) {
    case v1::BOX_SOURCE_UNSPECIFIED:
    case v1::BOX_SOURCE_AGENT:
      return BoxSource::kAgent;
    case v1::BOX_SOURCE_SERVER:
      return BoxSource::kServer;
    case v1::BOX_SOURCE_BOTH:
      return BoxSource::kBoth;
    default:
      return Invalid("config.detection.box_source", "unknown value " + std::to_string(int(source)));
  }
}

v1::BoxSource BoxSourceToProto(BoxSource source) {
  switch (source) {
    case BoxSource::kAgent:
      return v1::BOX_SOURCE_AGENT;
    case BoxSource::kServer:
      return v1::BOX_SOURCE_SERVER;
    case BoxSource::kBoth:
      return v1::BOX_SOURCE_BOTH;
  }
  return v1::BOX_SOURCE_UNSPECIFIED;
}

}  // namespace

Result<MapOptions> MapOptionsFromProto(const v1::MapConfig& c, const Limits& limits,
                                       ServiceMapSettings* settings) {
  MapOptions options;
  DatabaseConfig& d = options.database;
  const v1::OrbSettings& orb = c.orb();
  if (orb.has_max_features()) d.orb.max_features = orb.max_features();
  if (orb.has_scale_factor()) d.orb.scale_factor = orb.scale_factor();
  if (orb.has_levels()) d.orb.levels = orb.levels();
  if (orb.has_edge_threshold()) d.orb.edge_threshold = orb.edge_threshold();
  if (orb.has_patch_size()) d.orb.patch_size = orb.patch_size();
  if (orb.has_fast_threshold()) d.orb.fast_threshold = orb.fast_threshold();

  const v1::DetectionSettings& det = c.detection();
  settings->detection_enabled = !det.has_enabled() || det.enabled();
  auto source = BoxSourceFromProto(det.box_source());
  if (!source.ok()) return source.status();
  settings->box_source = *source;
  if (det.has_min_confidence()) d.min_box_confidence = det.min_confidence();
  if (!(d.min_box_confidence >= 0.0f && d.min_box_confidence <= 1.0f)) {
    return Invalid("config.detection.min_confidence",
                   "must be in [0, 1], got " + Num(det.min_confidence()));
  }
  if (det.classes_size() > 0) {
    d.dynamic_classes.clear();
    for (int i = 0; i < det.classes_size(); ++i) {
      auto id = CocoClassId(det.classes(i));
      if (!id.ok()) {
        return Invalid("config.detection.classes[" + std::to_string(i) + "]",
                       id.status().message());
      }
      if (std::find(d.dynamic_classes.begin(), d.dynamic_classes.end(), *id) ==
          d.dynamic_classes.end()) {
        d.dynamic_classes.push_back(*id);
      }
    }
  }
  // Detection off: no box selects any class, so boxes never reach the filter (a mask still does).
  if (!settings->detection_enabled) d.dynamic_classes.clear();

  const v1::FilterSettings& f = c.filter();
  auto method = FilterFromProto(f.method());
  if (!method.ok()) return method.status();
  d.filter.method = *method;
  if (f.has_sensitivity_threshold()) d.filter.sensitivity_threshold = f.sensitivity_threshold();
  if (f.has_place_threshold()) d.filter.place_threshold = f.place_threshold();

  auto scoring = ScoringFromProto(c.scoring());
  if (!scoring.ok()) return scoring.status();
  d.scoring = *scoring;

  const v1::VerificationSettings& v = c.verification();
  auto mode = VerificationFromProto(v.mode());
  if (!mode.ok()) return mode.status();
  d.verification.mode = *mode;
  if (v.has_levels_up()) d.verification.levels_up = v.levels_up();
  if (v.has_min_inliers()) d.verification.min_inliers = v.min_inliers();
  if (v.has_candidates()) d.verification.candidates = v.candidates();
  if (d.verification.candidates < 0) {
    return Invalid("config.verification.candidates", "must be >= 0");
  }
  options.store_invalid = c.store_invalid();

  // The core's messages name fields relative to the DatabaseConfig ("orb.max_features ...").
  if (Status valid = ValidateDatabaseConfig(d); !valid.ok()) {
    return Status::InvalidArgument("config." + valid.message());
  }
  if (uint64_t(d.orb.max_features) > limits.max_descriptors_per_frame) {
    return Status::ResourceExhausted(
        "config.orb.max_features = " + std::to_string(d.orb.max_features) +
        " exceeds limits.max_descriptors_per_frame = " +
        std::to_string(limits.max_descriptors_per_frame));
  }
  return options;
}

void MapConfigToProto(const MapOptions& options, const ServiceMapSettings& settings,
                      const std::string& vocabulary_name, v1::MapConfig* out) {
  const DatabaseConfig& d = options.database;
  out->set_vocabulary(vocabulary_name);
  v1::OrbSettings* orb = out->mutable_orb();
  orb->set_max_features(d.orb.max_features);
  orb->set_scale_factor(d.orb.scale_factor);
  orb->set_levels(d.orb.levels);
  orb->set_edge_threshold(d.orb.edge_threshold);
  orb->set_patch_size(d.orb.patch_size);
  orb->set_fast_threshold(d.orb.fast_threshold);
  v1::DetectionSettings* det = out->mutable_detection();
  det->set_enabled(settings.detection_enabled);
  for (int id : d.dynamic_classes) det->add_classes(CocoClassName(id));
  det->set_min_confidence(d.min_box_confidence);
  det->set_box_source(BoxSourceToProto(settings.box_source));
  v1::FilterSettings* f = out->mutable_filter();
  f->set_method(FilterToProto(d.filter.method));
  f->set_sensitivity_threshold(d.filter.sensitivity_threshold);
  f->set_place_threshold(d.filter.place_threshold);
  out->set_scoring(ScoringToProto(d.scoring));
  v1::VerificationSettings* v = out->mutable_verification();
  v->set_mode(VerificationToProto(d.verification.mode));
  v->set_levels_up(d.verification.levels_up);
  v->set_min_inliers(d.verification.min_inliers);
  v->set_candidates(d.verification.candidates);
  out->set_store_invalid(options.store_invalid);
}

void MapStatsToProto(const MapStats& stats, v1::MapStats* out) {
  out->set_places(stats.database.places);
  out->set_descriptors_kept(stats.database.descriptors_kept);
  out->set_descriptors_dropped(stats.database.descriptors_dropped);
  out->set_invalid_rejected(stats.database.invalid_rejected);
  out->set_invalid_stored(stats.invalid_stored);
  out->set_bytes_on_disk(stats.bytes_on_disk);
  out->set_bytes_in_memory(stats.bytes_in_memory);
}

// ---- Observations -------------------------------------------------------------------------------

namespace {

uint32_t ReadBe32(const unsigned char* p) {
  return (uint32_t(p[0]) << 24) | (uint32_t(p[1]) << 16) | (uint32_t(p[2]) << 8) | uint32_t(p[3]);
}
uint32_t ReadBe16(const unsigned char* p) {
  return (uint32_t(p[0]) << 8) | uint32_t(p[1]);
}

std::string Dims(int width, int height) {
  return std::to_string(width) + "x" + std::to_string(height);
}

Status CheckPixels(uint64_t width, uint64_t height, const Limits& limits,
                   const std::string& field) {
  if (width * height > limits.max_image_pixels) {
    return Status::ResourceExhausted(
        field + ": " + std::to_string(width) + "x" + std::to_string(height) + " = " +
        std::to_string(width * height) +
        " pixels exceed limits.max_image_pixels = " + std::to_string(limits.max_image_pixels));
  }
  return Status::Ok();
}

bool Finite(float v) {
  return std::isfinite(v);
}

Result<DynamicBox> BoxFromProto(const v1::Box& box, const std::string& field) {
  DynamicBox out;
  switch (box.label_case()) {
    case v1::Box::kClassId:
      if (box.class_id() < 0 || box.class_id() >= kCocoClassCount) {
        return Invalid(field + ".class_id",
                       std::to_string(box.class_id()) + " is not a COCO class id (0-79)");
      }
      out.class_id = box.class_id();
      break;
    case v1::Box::kClassName: {
      auto id = CocoClassId(box.class_name());
      if (!id.ok()) return Invalid(field + ".class_name", id.status().message());
      out.class_id = *id;
      break;
    }
    default:
      return Invalid(field, "class_id or class_name is required");
  }
  if (!Finite(box.confidence()) || box.confidence() < 0 || box.confidence() > 1) {
    return Invalid(field + ".confidence", Num(box.confidence()) + " is not in [0, 1]");
  }
  out.confidence = box.confidence();
  const v1::Rect& r = box.rect();
  if (!box.has_rect()) return Invalid(field + ".rect", "is required");
  if (!Finite(r.x()) || !Finite(r.y()) || !Finite(r.width()) || !Finite(r.height())) {
    return Invalid(field + ".rect", "has a non-finite value");
  }
  if (r.width() < 0 || r.height() < 0) {
    return Invalid(field + ".rect", "width and height must be >= 0, got " + Num(r.width()) + " x " +
                                        Num(r.height()));
  }
  out.rect = cv::Rect2f(r.x(), r.y(), r.width(), r.height());
  return out;
}

Result<Pose> PoseFromProto(const v1::Pose& p, const std::string& field) {
  for (double v : {p.x(), p.y(), p.z(), p.qx(), p.qy(), p.qz(), p.qw()}) {
    if (!std::isfinite(v)) return Invalid(field, "has a non-finite value");
  }
  Pose pose;
  pose.position = {p.x(), p.y(), p.z()};
  if (p.qx() == 0 && p.qy() == 0 && p.qz() == 0 && p.qw() == 0) {
    pose.orientation = {0, 0, 0, 1};
  } else {
    pose.orientation = {p.qx(), p.qy(), p.qz(), p.qw()};
  }
  return pose;
}

// Decodes JPEG/PNG bytes after checking the header against the pixel limit (so a small file
// claiming a huge image is refused before any allocation).
Result<cv::Mat> DecodeImageBytes(const std::string& bytes, int flags, const Limits& limits,
                                 const std::string& field, bool png_only) {
  auto header = ReadImageHeader(bytes);
  if (!header.ok()) return Invalid(field, header.status().message());
  if (png_only && header->format != ImageHeader::Format::kPng) {
    return Invalid(field, "must be a PNG image");
  }
  PLACEDB_RETURN_IF_ERROR(
      CheckPixels(uint64_t(header->width), uint64_t(header->height), limits, field));
  cv::Mat image;
  try {
    const cv::Mat buffer(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data()));
    image = cv::imdecode(buffer, flags);
  } catch (const cv::Exception& e) {
    return Invalid(field, std::string("cannot be decoded: ") + e.what());
  }
  if (image.empty()) {
    return Invalid(field, std::string("cannot be decoded (damaged or truncated ") +
                              (header->format == ImageHeader::Format::kPng ? "PNG" : "JPEG") + ")");
  }
  PLACEDB_RETURN_IF_ERROR(CheckPixels(uint64_t(image.cols), uint64_t(image.rows), limits, field));
  return image;
}

Result<FeatureSet> FeaturesFromProto(const v1::Features& f, const Limits& limits,
                                     const std::string& field) {
  if (f.image_width() == 0 || f.image_height() == 0 || f.image_width() > 100000 ||
      f.image_height() > 100000) {
    return Invalid(
        field + ".image_width/image_height",
        "must be in [1, 100000], got " + Dims(int(f.image_width()), int(f.image_height())));
  }
  PLACEDB_RETURN_IF_ERROR(
      CheckPixels(f.image_width(), f.image_height(), limits, field + ".image_width/image_height"));
  const size_t count = size_t(f.keypoints_size());
  if (count > limits.max_descriptors_per_frame) {
    return Status::ResourceExhausted(field + ".keypoints: " + std::to_string(count) +
                                     " keypoints exceed limits.max_descriptors_per_frame = " +
                                     std::to_string(limits.max_descriptors_per_frame));
  }
  const std::string& bytes = f.descriptors();
  if (bytes.size() % size_t(Descriptor256::kBytes) != 0) {
    return Invalid(field + ".descriptors", std::to_string(bytes.size()) +
                                               " bytes is not a multiple of 32 (one 256-bit "
                                               "descriptor per keypoint)");
  }
  if (bytes.size() / size_t(Descriptor256::kBytes) != count) {
    return Invalid(field + ".descriptors",
                   std::to_string(bytes.size() / size_t(Descriptor256::kBytes)) +
                       " descriptors for " + std::to_string(count) + " keypoints");
  }
  const int width = int(f.image_width());
  const int height = int(f.image_height());
  FeatureSet features;
  features.image_width = width;
  features.image_height = height;
  features.keypoints.reserve(count);
  features.descriptors.reserve(count);
  for (size_t i = 0; i < count; ++i) {
    const v1::Keypoint& k = f.keypoints(int(i));
    const std::string at = field + ".keypoints[" + std::to_string(i) + "]";
    for (auto [name, value] :
         {std::pair{".x", k.x()}, std::pair{".y", k.y()}, std::pair{".size", k.size()},
          std::pair{".angle", k.angle()}, std::pair{".response", k.response()}}) {
      if (!Finite(value)) return Invalid(at + name, "is not finite");
    }
    if (k.x() < 0 || k.x() >= float(width)) {
      return Invalid(at + ".x", Num(k.x()) + " lies outside the " + Dims(width, height) + " image");
    }
    if (k.y() < 0 || k.y() >= float(height)) {
      return Invalid(at + ".y", Num(k.y()) + " lies outside the " + Dims(width, height) + " image");
    }
    if (k.size() <= 0) return Invalid(at + ".size", "must be positive");
    if (k.angle() != -1 && (k.angle() < 0 || k.angle() > 360)) {
      return Invalid(at + ".angle", "must be -1 or in [0, 360], got " + Num(k.angle()));
    }
    if (k.octave() < 0 || k.octave() > 31) {
      return Invalid(at + ".octave", "must be in [0, 31], got " + std::to_string(k.octave()));
    }
    features.keypoints.push_back(
        Keypoint{k.x(), k.y(), k.size(), k.angle(), k.response(), k.octave()});
    features.descriptors.push_back(Descriptor256::FromBytes(
        reinterpret_cast<const uint8_t*>(bytes.data()) + i * size_t(Descriptor256::kBytes)));
  }
  // The core's own checks too (it names fields relative to the feature set).
  if (Status valid = ValidateFeatures(features); !valid.ok()) {
    return Invalid(field, valid.message());
  }
  return features;
}

Result<cv::Mat> DepthFromProto(const v1::DepthImage& depth, const Limits& limits, int width,
                               int height, const std::string& field) {
  if (!std::isfinite(depth.scale()) || depth.scale() < 0) {
    return Invalid(field + ".scale", "must be >= 0 (0 = the encoding's default)");
  }
  cv::Mat metres;
  switch (depth.data_case()) {
    case v1::DepthImage::kPng16: {
      auto image = DecodeImageBytes(depth.png16(), cv::IMREAD_UNCHANGED | cv::IMREAD_ANYDEPTH,
                                    limits, field + ".png16", /*png_only=*/true);
      if (!image.ok()) return image.status();
      if (image->type() != CV_16UC1) {
        return Invalid(field + ".png16", "must be a 16-bit single-channel PNG");
      }
      image->convertTo(metres, CV_32F, depth.scale() > 0 ? depth.scale() : 0.001);
      break;
    }
    case v1::DepthImage::kRawFloat32: {
      const v1::RawDepth& raw = depth.raw_float32();
      if (raw.width() == 0 || raw.height() == 0) {
        return Invalid(field + ".raw_float32", "width and height must be positive");
      }
      PLACEDB_RETURN_IF_ERROR(
          CheckPixels(raw.width(), raw.height(), limits, field + ".raw_float32"));
      const uint64_t expected = uint64_t(raw.width()) * raw.height() * 4;
      if (raw.data().size() != expected) {
        return Invalid(field + ".raw_float32.data", std::to_string(raw.data().size()) +
                                                        " bytes, expected " +
                                                        Dims(int(raw.width()), int(raw.height())) +
                                                        " x 4 = " + std::to_string(expected));
      }
      cv::Mat values(int(raw.height()), int(raw.width()), CV_32F);
      std::memcpy(values.data, raw.data().data(), expected);
      for (int y = 0; y < values.rows; ++y) {
        const float* row = values.ptr<float>(y);
        for (int x = 0; x < values.cols; ++x) {
          if (std::isinf(row[x]) || row[x] < 0) {
            return Invalid(field + ".raw_float32.data",
                           "value at (" + std::to_string(x) + ", " + std::to_string(y) +
                               ") is negative or infinite (NaN marks no depth)");
          }
        }
      }
      metres = depth.scale() > 0 ? cv::Mat(values * depth.scale()) : values;
      break;
    }
    default:
      return Invalid(field, "png16 or raw_float32 is required");
  }
  if (metres.cols != width || metres.rows != height) {
    return Invalid(field, Dims(metres.cols, metres.rows) + " does not match the " +
                              Dims(width, height) + " image");
  }
  return metres;
}

}  // namespace

Result<ImageHeader> ReadImageHeader(const std::string& bytes) {
  const auto* p = reinterpret_cast<const unsigned char*>(bytes.data());
  const size_t n = bytes.size();
  static const unsigned char kPng[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1A, '\n'};
  if (n >= 8 && std::memcmp(p, kPng, 8) == 0) {
    if (n < 24 || std::memcmp(p + 12, "IHDR", 4) != 0) {
      return Status::InvalidArgument("truncated PNG (no IHDR header)");
    }
    const uint32_t width = ReadBe32(p + 16);
    const uint32_t height = ReadBe32(p + 20);
    if (width == 0 || height == 0 || width > (1u << 30) || height > (1u << 30)) {
      return Status::InvalidArgument("PNG header claims a " + std::to_string(width) + "x" +
                                     std::to_string(height) + " image");
    }
    return ImageHeader{ImageHeader::Format::kPng, int(width), int(height)};
  }
  if (n >= 3 && p[0] == 0xFF && p[1] == 0xD8 && p[2] == 0xFF) {
    size_t i = 2;
    while (i + 4 <= n) {
      if (p[i] != 0xFF) return Status::InvalidArgument("damaged JPEG (bad marker)");
      while (i < n && p[i] == 0xFF) ++i;  // fill bytes
      if (i >= n) break;
      const unsigned char marker = p[i++];
      if (marker == 0xD8 || marker == 0x01 || (marker >= 0xD0 && marker <= 0xD7)) continue;
      if (marker == 0xD9 || marker == 0xDA) break;  // end / scan before any frame header
      if (i + 2 > n) break;
      const uint32_t length = ReadBe16(p + i);
      if (length < 2) return Status::InvalidArgument("damaged JPEG (bad segment length)");
      const bool sof =
          (marker >= 0xC0 && marker <= 0xCF) && marker != 0xC4 && marker != 0xC8 && marker != 0xCC;
      if (sof) {
        if (i + 7 > n) break;
        const uint32_t height = ReadBe16(p + i + 3);
        const uint32_t width = ReadBe16(p + i + 5);
        if (width == 0 || height == 0) {
          return Status::InvalidArgument("JPEG header claims a " + std::to_string(width) + "x" +
                                         std::to_string(height) + " image");
        }
        return ImageHeader{ImageHeader::Format::kJpeg, int(width), int(height)};
      }
      i += length;
    }
    return Status::InvalidArgument("damaged or truncated JPEG (no frame header)");
  }
  return Status::InvalidArgument("not a JPEG or PNG image");
}

Result<DecodedObservation> DecodeObservation(const v1::Observation& o, const Limits& limits,
                                             bool color, const std::string& field) {
  DecodedObservation out;
  Observation& obs = out.observation;
  obs.metadata.agent_id = o.agent_id();
  obs.metadata.sequence = o.sequence();
  obs.metadata.timestamp_ns = o.timestamp_ns();
  if (o.agent_id().size() > 256) {
    return Invalid(field + ".agent_id", "longer than 256 bytes");
  }
  if (o.has_pose()) {
    auto pose = PoseFromProto(o.pose(), field + ".pose");
    if (!pose.ok()) return pose.status();
    obs.metadata.pose = *pose;
  }

  if (size_t(o.boxes_size()) > limits.max_boxes_per_frame) {
    return Status::ResourceExhausted(
        field + ".boxes: " + std::to_string(o.boxes_size()) +
        " boxes exceed limits.max_boxes_per_frame = " + std::to_string(limits.max_boxes_per_frame));
  }
  out.agent_boxes.reserve(size_t(o.boxes_size()));
  for (int i = 0; i < o.boxes_size(); ++i) {
    auto box = BoxFromProto(o.boxes(i), field + ".boxes[" + std::to_string(i) + "]");
    if (!box.ok()) return box.status();
    out.agent_boxes.push_back(*box);
  }

  int width = 0, height = 0;
  switch (o.frame_case()) {
    case v1::Observation::kEncodedImage: {
      auto image = DecodeImageBytes(o.encoded_image().data(),
                                    color ? cv::IMREAD_COLOR : cv::IMREAD_GRAYSCALE, limits,
                                    field + ".encoded_image.data", /*png_only=*/false);
      if (!image.ok()) return image.status();
      obs.image = std::move(image).value();
      out.has_pixels = true;
      break;
    }
    case v1::Observation::kRawImage: {
      const v1::RawImage& raw = o.raw_image();
      const std::string at = field + ".raw_image";
      int channels = 0;
      switch (raw.format()) {
        case v1::PIXEL_FORMAT_GRAY8:
          channels = 1;
          break;
        case v1::PIXEL_FORMAT_BGR8:
        case v1::PIXEL_FORMAT_RGB8:
          channels = 3;
          break;
        default:
          return Invalid(at + ".format", "GRAY8, BGR8 or RGB8 is required");
      }
      if (raw.width() == 0 || raw.height() == 0 || raw.width() > 100000 || raw.height() > 100000) {
        return Invalid(at + ".width/height",
                       "must be in [1, 100000], got " + Dims(int(raw.width()), int(raw.height())));
      }
      PLACEDB_RETURN_IF_ERROR(CheckPixels(raw.width(), raw.height(), limits, at));
      const uint64_t expected = uint64_t(raw.width()) * raw.height() * uint64_t(channels);
      if (raw.data().size() != expected) {
        return Invalid(at + ".data", std::to_string(raw.data().size()) + " bytes, expected " +
                                         Dims(int(raw.width()), int(raw.height())) + " x " +
                                         std::to_string(channels) + " = " +
                                         std::to_string(expected));
      }
      const cv::Mat view(int(raw.height()), int(raw.width()), channels == 1 ? CV_8UC1 : CV_8UC3,
                         const_cast<char*>(raw.data().data()));
      if (raw.format() == v1::PIXEL_FORMAT_RGB8) {
        cv::cvtColor(view, obs.image, color ? cv::COLOR_RGB2BGR : cv::COLOR_RGB2GRAY);
      } else if (raw.format() == v1::PIXEL_FORMAT_BGR8 && !color) {
        cv::cvtColor(view, obs.image, cv::COLOR_BGR2GRAY);
      } else {
        obs.image = view.clone();  // the request's bytes do not outlive the call
      }
      out.has_pixels = true;
      break;
    }
    case v1::Observation::kFeatures: {
      auto features = FeaturesFromProto(o.features(), limits, field + ".features");
      if (!features.ok()) return features.status();
      obs.features = std::move(features).value();
      width = obs.features->image_width;
      height = obs.features->image_height;
      break;
    }
    default:
      return Invalid(field, "one of encoded_image, raw_image or features is required");
  }
  if (out.has_pixels) {
    width = obs.image.cols;
    height = obs.image.rows;
    // OpenCV's ORB throws on an image with a side of 1 pixel (its pyramid scales it to 0): such
    // a frame cannot hold a place anyway.
    if (width < 2 || height < 2) {
      return Invalid(
          field + (o.frame_case() == v1::Observation::kRawImage ? ".raw_image" : ".encoded_image"),
          "a " + Dims(width, height) + " image is too small (at least 2 pixels each way)");
    }
  }

  if (!o.dynamic_mask_png().empty()) {
    const std::string at = field + ".dynamic_mask_png";
    auto mask = DecodeImageBytes(o.dynamic_mask_png(), cv::IMREAD_GRAYSCALE, limits, at,
                                 /*png_only=*/true);
    if (!mask.ok()) return mask.status();
    if (mask->cols != width || mask->rows != height) {
      return Invalid(at, Dims(mask->cols, mask->rows) + " mask does not match the " +
                             Dims(width, height) + " image");
    }
    obs.dynamic.mask = std::move(mask).value();
  }
  if (o.has_depth()) {
    auto depth = DepthFromProto(o.depth(), limits, width, height, field + ".depth");
    if (!depth.ok()) return depth.status();
    out.depth_m = std::move(depth).value();
  }
  obs.dynamic.boxes = out.agent_boxes;
  return out;
}

// ---- Results ------------------------------------------------------------------------------------

void CountsToProto(const FrameCounts& counts, v1::FrameCounts* out) {
  out->set_total(counts.total);
  out->set_dynamic(counts.dynamic);
  out->set_kept(counts.static_);
  out->set_dynamic_coverage(counts.dynamic_coverage);
}

void BoxesToProto(const std::vector<DynamicBox>& boxes,
                  google::protobuf::RepeatedPtrField<v1::UsedBox>* out) {
  out->Reserve(int(boxes.size()));
  for (const DynamicBox& box : boxes) {
    v1::UsedBox* b = out->Add();
    b->set_class_id(box.class_id);
    b->set_class_name(CocoClassName(box.class_id));
    b->set_confidence(box.confidence);
    b->mutable_rect()->set_x(box.rect.x);
    b->mutable_rect()->set_y(box.rect.y);
    b->mutable_rect()->set_width(box.rect.width);
    b->mutable_rect()->set_height(box.rect.height);
  }
}

void MetadataToProto(const PlaceMetadata& metadata, v1::PlaceMetadata* out) {
  out->set_agent_id(metadata.agent_id);
  out->set_sequence(metadata.sequence);
  out->set_timestamp_ns(metadata.timestamp_ns);
  if (metadata.pose) {
    v1::Pose* p = out->mutable_pose();
    p->set_x(metadata.pose->position[0]);
    p->set_y(metadata.pose->position[1]);
    p->set_z(metadata.pose->position[2]);
    p->set_qx(metadata.pose->orientation[0]);
    p->set_qy(metadata.pose->orientation[1]);
    p->set_qz(metadata.pose->orientation[2]);
    p->set_qw(metadata.pose->orientation[3]);
  }
}

void MatchesToProto(const std::vector<Match>& matches,
                    google::protobuf::RepeatedPtrField<v1::Match>* out) {
  out->Reserve(int(matches.size()));
  for (const Match& match : matches) {
    v1::Match* m = out->Add();
    m->set_place_id(match.place);
    m->set_score(match.score);
    m->set_inliers(match.inliers);
    m->set_verified(match.verified);
    MetadataToProto(match.metadata, m->mutable_metadata());
  }
}

void TimingsToProto(const StageTimings& t, double queue_ms, v1::StageTimings* out) {
  out->set_queue_ms(queue_ms);
  out->set_decode_ms(t.decode_ms);
  out->set_detect_ms(t.detect_ms);
  out->set_extract_ms(t.extract_ms);
  out->set_filter_ms(t.filter_ms);
  out->set_transform_ms(t.transform_ms);
  out->set_search_ms(t.search_ms);
  out->set_verify_ms(t.verify_ms);
  out->set_store_ms(t.store_ms);
  out->set_total_ms(t.total_ms);
}

void FeaturesToProto(const FeatureSet& features, v1::Features* out) {
  out->set_image_width(uint32_t(features.image_width));
  out->set_image_height(uint32_t(features.image_height));
  out->mutable_keypoints()->Reserve(int(features.keypoints.size()));
  for (const Keypoint& k : features.keypoints) {
    v1::Keypoint* kp = out->add_keypoints();
    kp->set_x(k.x);
    kp->set_y(k.y);
    kp->set_size(k.size);
    kp->set_angle(k.angle);
    kp->set_response(k.response);
    kp->set_octave(k.octave);
  }
  std::string* bytes = out->mutable_descriptors();
  bytes->resize(features.descriptors.size() * size_t(Descriptor256::kBytes));
  for (size_t i = 0; i < features.descriptors.size(); ++i) {
    features.descriptors[i].ToBytes(reinterpret_cast<uint8_t*>(bytes->data()) +
                                    i * size_t(Descriptor256::kBytes));
  }
}

QueryOptions QueryOptionsFromProto(const v1::MatchOptions& options, const std::string& agent_id) {
  QueryOptions out;
  out.top_k = options.top_k() == 0 ? 10 : std::min<size_t>(options.top_k(), 1000);
  out.verified_only = options.verified_only();
  if (options.exclude_same_agent()) {
    out.accept = [agent_id](const PlaceRecord& record) {
      return record.metadata.agent_id != agent_id;
    };
  }
  return out;
}

}  // namespace placedb::server
