#include "proto/convert_frame.h"

#include <cmath>
#include <cstring>
#include <opencv2/imgproc.hpp>
#include <span>
#include <utility>

#include "core/decode/image_decoder.h"
#include "core/detect/detector.h"
#include "core/features/orb_features.h"
#include "core/features/sift_features.h"
#include "core/filter/depth_filter.h"
#include "proto/field_errors.h"

namespace placedb::wire {

using internal::Invalid;
using internal::Num;

namespace {

// Sizes are printed from their unsigned wire values: 4000000000 stays 4000000000.
std::string Dims(uint64_t width, uint64_t height) {
  return std::to_string(width) + "x" + std::to_string(height);
}

// The largest side of any image, mask, depth or feature frame (before the pixel limit).
constexpr uint64_t kMaxSide = 100000;

Status CheckPixels(uint64_t width, uint64_t height, const FrameLimits& limits,
                   const std::string& field) {
  uint64_t pixels = 0;
  if (!CheckedMul(width, height, &pixels) || pixels > limits.max_image_pixels) {
    return Status::ResourceExhausted(
        field + ": " + Dims(width, height) +
        (pixels != 0 ? " = " + std::to_string(pixels) + " pixels" : std::string(" pixels")) +
        " exceed limits.max_image_pixels = " + std::to_string(limits.max_image_pixels));
  }
  return Status::Ok();
}

// "<what> must be in [1, 100000], got 4000000000x1": both sides checked before any product.
Status CheckSides(uint64_t width, uint64_t height, const std::string& field) {
  if (width == 0 || height == 0 || width > kMaxSide || height > kMaxSide) {
    return Invalid(field,
                   "must be in [1, " + std::to_string(kMaxSide) + "], got " + Dims(width, height));
  }
  return Status::Ok();
}

// The exact byte count of a raw image (core/decode: overflow-checked), or INVALID_ARGUMENT
// naming `data_field` when `size` differs.
Status CheckRawBytes(uint64_t width, uint64_t height, uint64_t bytes_per_pixel, size_t size,
                     const std::string& data_field) {
  auto expected = RawImageBytes(width, height, bytes_per_pixel);
  if (!expected.ok()) return Invalid(data_field, expected.status().message());
  if (uint64_t(size) != *expected) {
    return Invalid(data_field, std::to_string(size) + " bytes, expected " + Dims(width, height) +
                                   " x " + std::to_string(bytes_per_pixel) + " = " +
                                   std::to_string(*expected));
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

// Decodes JPEG/PNG bytes strictly (core/decode/image_decoder.h: damaged, truncated or
// inconsistent data is refused) after checking the header against the pixel limit, so a small
// file claiming a huge image is refused before any allocation.
Result<cv::Mat> DecodeImageBytes(const std::string& bytes, ColorMode mode,
                                 const FrameLimits& limits, const std::string& field,
                                 bool png_only) {
  const std::span<const uint8_t> data(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
  auto info = ReadImageInfo(data);
  if (!info.ok()) return Invalid(field, info.status().message());
  if (png_only && info->format != ImageFormat::kPng) return Invalid(field, "must be a PNG image");
  PLACEDB_RETURN_IF_ERROR(CheckPixels(info->width, info->height, limits, field));
  auto image = DecodeImage(data, DecodeOptions{mode, limits.max_image_pixels});
  if (!image.ok()) return Status(image.status().code(), field + ": " + image.status().message());
  return image;
}

// The frame's size as a features message states it.
Status FeatureImageSize(uint32_t width, uint32_t height, const FrameLimits& limits,
                        const std::string& field) {
  PLACEDB_RETURN_IF_ERROR(CheckSides(width, height, field + ".image_width/image_height"));
  return CheckPixels(width, height, limits, field + ".image_width/image_height");
}

Status CheckKeypointCount(size_t count, const FrameLimits& limits, const std::string& field) {
  if (count > limits.max_descriptors_per_frame) {
    return Status::ResourceExhausted(field + ".keypoints: " + std::to_string(count) +
                                     " keypoints exceed limits.max_descriptors_per_frame = " +
                                     std::to_string(limits.max_descriptors_per_frame));
  }
  return Status::Ok();
}

// Keypoints of a features message, each checked with its path in the message.
Result<std::vector<Keypoint>> KeypointsFromProto(
    const google::protobuf::RepeatedPtrField<v1::Keypoint>& keypoints, int width, int height,
    const std::string& field) {
  std::vector<Keypoint> out;
  out.reserve(size_t(keypoints.size()));
  for (int i = 0; i < keypoints.size(); ++i) {
    const v1::Keypoint& k = keypoints.Get(i);
    // The field path is built for an error only, not allocated for every keypoint of a frame.
    const auto at = [&] { return field + ".keypoints[" + std::to_string(i) + "]"; };
    for (auto [name, value] :
         {std::pair{".x", k.x()}, std::pair{".y", k.y()}, std::pair{".size", k.size()},
          std::pair{".angle", k.angle()}, std::pair{".response", k.response()}}) {
      if (!Finite(value)) return Invalid(at() + name, "is not finite");
    }
    if (k.x() < 0 || k.x() >= float(width)) {
      return Invalid(at() + ".x",
                     Num(k.x()) + " lies outside the " + Dims(width, height) + " image");
    }
    if (k.y() < 0 || k.y() >= float(height)) {
      return Invalid(at() + ".y",
                     Num(k.y()) + " lies outside the " + Dims(width, height) + " image");
    }
    if (k.size() <= 0) return Invalid(at() + ".size", "must be positive");
    if (k.angle() != -1 && (k.angle() < 0 || k.angle() > 360)) {
      return Invalid(at() + ".angle", "must be -1 or in [0, 360], got " + Num(k.angle()));
    }
    if (k.octave() < 0 || k.octave() > 31) {
      return Invalid(at() + ".octave", "must be in [0, 31], got " + std::to_string(k.octave()));
    }
    out.push_back(Keypoint{k.x(), k.y(), k.size(), k.angle(), k.response(), k.octave()});
  }
  return out;
}

Result<FeatureSet> FeaturesFromProto(const v1::Features& f, const FrameLimits& limits,
                                     const std::string& field) {
  PLACEDB_RETURN_IF_ERROR(FeatureImageSize(f.image_width(), f.image_height(), limits, field));
  const size_t count = size_t(f.keypoints_size());
  PLACEDB_RETURN_IF_ERROR(CheckKeypointCount(count, limits, field));
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
  auto keypoints = KeypointsFromProto(f.keypoints(), width, height, field);
  if (!keypoints.ok()) return keypoints.status();
  FeatureSet features;
  features.image_width = width;
  features.image_height = height;
  features.keypoints = std::move(keypoints).value();
  features.descriptors.reserve(count);
  for (size_t i = 0; i < count; ++i) {
    features.descriptors.push_back(Descriptor256::FromBytes(
        reinterpret_cast<const uint8_t*>(bytes.data()) + i * size_t(Descriptor256::kBytes)));
  }
  // The core's own checks too (it names fields relative to the feature set).
  if (Status valid = ValidateFeatures(features); !valid.ok()) {
    return Invalid(field, valid.message());
  }
  return features;
}

Result<FloatFeatureSet> SiftFeaturesFromProto(const v1::SiftFeatures& f, const FrameLimits& limits,
                                              const std::string& field) {
  PLACEDB_RETURN_IF_ERROR(FeatureImageSize(f.image_width(), f.image_height(), limits, field));
  const size_t count = size_t(f.keypoints_size());
  PLACEDB_RETURN_IF_ERROR(CheckKeypointCount(count, limits, field));
  constexpr size_t kRowBytes = size_t(kSiftDimensions) * sizeof(float);
  const std::string& bytes = f.descriptors();
  if (bytes.size() % kRowBytes != 0) {
    return Invalid(field + ".descriptors",
                   std::to_string(bytes.size()) +
                       " bytes is not a multiple of 512 (one descriptor of 128 little-endian "
                       "float32 per keypoint)");
  }
  if (bytes.size() / kRowBytes != count) {
    return Invalid(field + ".descriptors", std::to_string(bytes.size() / kRowBytes) +
                                               " descriptors for " + std::to_string(count) +
                                               " keypoints");
  }
  const int width = int(f.image_width());
  const int height = int(f.image_height());
  auto keypoints = KeypointsFromProto(f.keypoints(), width, height, field);
  if (!keypoints.ok()) return keypoints.status();
  // Decodes the descriptors and runs the core's checks (finite values; it names the index).
  auto features = MakeFloatFeatureSet(
      width, height, std::move(keypoints).value(),
      std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()));
  if (!features.ok()) return Invalid(field, features.status().message());
  return features;
}

Status IntrinsicsFromProto(const v1::Intrinsics& k, int width, int height, const std::string& field,
                           CameraIntrinsics* out) {
  for (auto [name, value] : {std::pair{".fx", k.fx()}, std::pair{".fy", k.fy()}}) {
    if (!std::isfinite(value) || !(value > 0)) {
      return Invalid(field + name, "focal length must be positive and finite, got " + Num(value));
    }
  }
  if (!std::isfinite(k.cx()) || k.cx() < 0 || k.cx() > width) {
    return Invalid(field + ".cx", Num(k.cx()) + " lies outside the " + Dims(width, height) +
                                      " image (the colour image's principal point)");
  }
  if (!std::isfinite(k.cy()) || k.cy() < 0 || k.cy() > height) {
    return Invalid(field + ".cy", Num(k.cy()) + " lies outside the " + Dims(width, height) +
                                      " image (the colour image's principal point)");
  }
  *out = CameraIntrinsics{k.fx(), k.fy(), k.cx(), k.cy()};
  // The core's own check too.
  if (Status valid = ValidateIntrinsics(*out, width, height); !valid.ok()) {
    return Invalid(field, valid.message());
  }
  return Status::Ok();
}

// A depth image as the core takes it: the raw values (CV_16U for png16, CV_32F for
// raw_float32), the frame's scale and intrinsics. `width` x `height` is the colour frame's size.
Result<DepthObservation> DepthFromProto(const v1::DepthImage& depth, const FrameLimits& limits,
                                        int width, int height, const std::string& field) {
  if (!std::isfinite(depth.scale()) || depth.scale() < 0) {
    return Invalid(field + ".scale", "must be >= 0 (0 = the map's depth scale)");
  }
  DepthObservation out;
  switch (depth.data_case()) {
    case v1::DepthImage::kPng16: {
      auto image = DecodeImageBytes(depth.png16(), ColorMode::kUnchanged, limits, field + ".png16",
                                    /*png_only=*/true);
      if (!image.ok()) return image.status();
      if (image->type() != CV_16UC1) {
        return Invalid(field + ".png16", "must be a 16-bit single-channel PNG");
      }
      out.raw = std::move(image).value();
      break;
    }
    case v1::DepthImage::kRawFloat32: {
      const v1::RawDepth& raw = depth.raw_float32();
      PLACEDB_RETURN_IF_ERROR(
          CheckSides(raw.width(), raw.height(), field + ".raw_float32.width/height"));
      PLACEDB_RETURN_IF_ERROR(
          CheckPixels(raw.width(), raw.height(), limits, field + ".raw_float32"));
      PLACEDB_RETURN_IF_ERROR(CheckRawBytes(raw.width(), raw.height(), sizeof(float),
                                            raw.data().size(), field + ".raw_float32.data"));
      // Both sides are <= 100000 (CheckSides): they fit in an int.
      cv::Mat values(int(raw.height()), int(raw.width()), CV_32F);
      std::memcpy(values.data, raw.data().data(), raw.data().size());
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
      out.raw = std::move(values);
      break;
    }
    default:
      return Invalid(field, "png16 or raw_float32 is required");
  }
  if (Status registered = CheckDepthRegistration(out.raw.cols, out.raw.rows, width, height);
      !registered.ok()) {
    return Invalid(field, registered.message());
  }
  if (depth.scale() > 0) out.metres_per_unit = double(depth.scale());
  if (depth.has_intrinsics()) {
    CameraIntrinsics intrinsics;
    PLACEDB_RETURN_IF_ERROR(
        IntrinsicsFromProto(depth.intrinsics(), width, height, field + ".intrinsics", &intrinsics));
    out.intrinsics = intrinsics;
  }
  return out;
}

}  // namespace

Result<Camera> CameraFromProto(const v1::Camera& c, int frame_width, int frame_height,
                               const std::string& field) {
  if (c.width() > 100000 || c.height() > 100000) {
    return Invalid(
        field + ".width/height",
        "must be in [1, 100000] (or both 0: the frame's size), got " + Dims(c.width(), c.height()));
  }
  Camera camera;
  camera.width = int(c.width());
  camera.height = int(c.height());
  camera.fx = c.fx();
  camera.fy = c.fy();
  camera.cx = c.cx();
  camera.cy = c.cy();
  camera.distortion_model = c.distortion_model().empty() ? "none" : c.distortion_model();
  camera.distortion.assign(c.distortion().begin(), c.distortion().end());
  const bool frame_size = camera.width == 0 && camera.height == 0;
  if (frame_size && frame_width > 0) {
    camera.width = frame_width;
    camera.height = frame_height;
  }
  if (frame_size && frame_width == 0) {
    // A stream's camera before any frame: every check but the principal point's upper bound.
    Camera unsized = camera;
    unsized.width = unsized.height = 100000;
    PLACEDB_RETURN_IF_ERROR(unsized.Validate(field));
    return camera;
  }
  PLACEDB_RETURN_IF_ERROR(camera.Validate(field));
  if (frame_width > 0 && (camera.width != frame_width || camera.height != frame_height)) {
    return Invalid(field + ".width/height",
                   Dims(camera.width, camera.height) + " is not the frame's " +
                       Dims(frame_width, frame_height) +
                       " (intrinsics must be of the image the keypoints are in; 0x0 = the "
                       "frame's size)");
  }
  return camera;
}

void CameraToProto(const Camera& camera, v1::Camera* out) {
  out->set_width(uint32_t(camera.width));
  out->set_height(uint32_t(camera.height));
  out->set_fx(camera.fx);
  out->set_fy(camera.fy);
  out->set_cx(camera.cx);
  out->set_cy(camera.cy);
  out->set_distortion_model(camera.distortion_model);
  for (double v : camera.distortion) out->add_distortion(v);
}

Status CheckFeatureType(const v1::Observation& observation, FeatureType map_type,
                        const std::string& map_name, const std::string& field) {
  if (map_type == FeatureType::kSift && observation.frame_case() == v1::Observation::kFeatures) {
    return Invalid(field + ".features",
                   "map '" + map_name +
                       "' is a SIFT map (feature_type SIFT): send sift_features or pixels "
                       "(encoded_image, raw_image), not ORB features");
  }
  if (map_type == FeatureType::kOrb && observation.frame_case() == v1::Observation::kSiftFeatures) {
    return Invalid(field + ".sift_features",
                   "map '" + map_name +
                       "' is an ORB map (feature_type ORB): send features or pixels "
                       "(encoded_image, raw_image), not SIFT features");
  }
  return Status::Ok();
}

Result<DecodedObservation> DecodeObservation(const v1::Observation& o, const FrameLimits& limits,
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
      auto image =
          DecodeImageBytes(o.encoded_image().data(), color ? ColorMode::kColor : ColorMode::kGray,
                           limits, field + ".encoded_image.data", /*png_only=*/false);
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
      PLACEDB_RETURN_IF_ERROR(CheckSides(raw.width(), raw.height(), at + ".width/height"));
      PLACEDB_RETURN_IF_ERROR(CheckPixels(raw.width(), raw.height(), limits, at));
      PLACEDB_RETURN_IF_ERROR(CheckRawBytes(raw.width(), raw.height(), uint64_t(channels),
                                            raw.data().size(), at + ".data"));
      // Both sides are <= 100000 (CheckSides): they fit in an int.
      const cv::Mat view(int(raw.height()), int(raw.width()), channels == 1 ? CV_8UC1 : CV_8UC3,
                         const_cast<char*>(raw.data().data()));
      if (raw.format() == v1::PIXEL_FORMAT_RGB8) {
        cv::cvtColor(view, obs.image, color ? cv::COLOR_RGB2BGR : cv::COLOR_RGB2GRAY);
      } else if (raw.format() == v1::PIXEL_FORMAT_BGR8 && !color) {
        cv::cvtColor(view, obs.image, cv::COLOR_BGR2GRAY);
      } else if (raw.format() == v1::PIXEL_FORMAT_GRAY8 && color) {
        // The detector takes 3 channels: a gray frame is given to it as gray BGR (found by
        // fuzz_observation: GRAY8 on a map with server-side detection).
        cv::cvtColor(view, obs.image, cv::COLOR_GRAY2BGR);
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
      break;
    }
    case v1::Observation::kSiftFeatures: {
      auto features = SiftFeaturesFromProto(o.sift_features(), limits, field + ".sift_features");
      if (!features.ok()) return features.status();
      obs.features = std::move(features).value();
      break;
    }
    default:
      return Invalid(field,
                     "one of encoded_image, raw_image, features or sift_features is required");
  }
  if (obs.features.has_value()) {
    width = obs.features->image_width();
    height = obs.features->image_height();
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
    auto mask = DecodeImageBytes(o.dynamic_mask_png(), ColorMode::kGray, limits, at,
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
    obs.depth = std::move(depth).value();
  }
  if (o.has_camera()) {
    auto camera = CameraFromProto(o.camera(), width, height, field + ".camera");
    if (!camera.ok()) return camera.status();
    obs.camera = std::move(camera).value();
  }
  obs.dynamic.boxes = out.agent_boxes;
  return out;
}

void AgentBoxToProto(const DynamicBox& box, v1::Box* out) {
  out->set_class_id(box.class_id);
  out->set_confidence(box.confidence);
  out->mutable_rect()->set_x(box.rect.x);
  out->mutable_rect()->set_y(box.rect.y);
  out->mutable_rect()->set_width(box.rect.width);
  out->mutable_rect()->set_height(box.rect.height);
}

}  // namespace placedb::wire
