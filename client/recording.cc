#include "client/recording.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <deque>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>
#include <set>
#include <sstream>

#include "client/frame_source.h"
#include "client/image_io.h"
#include "client/rosbag_reader.h"
#include "core/base/text.h"

namespace fs = std::filesystem;

namespace placedb::client {

namespace {

constexpr std::string_view kPngSignature = "\x89PNG\r\n\x1a\n";
constexpr const char* kImage = "sensor_msgs/Image";
constexpr const char* kCompressed = "sensor_msgs/CompressedImage";
constexpr const char* kCameraInfo = "sensor_msgs/CameraInfo";
// Colour frames held while waiting for the depth image that may pair with them, and depth images
// held for colour frames still to come (the Python SDK's bounds).
constexpr size_t kMaxPendingFrames = 64;
constexpr size_t kMaxHeldDepths = 256;

int64_t SecondsToNs(double seconds) {
  return int64_t(std::llround(seconds * 1e9));
}

std::string FileHead(const std::string& path, size_t bytes) {
  std::ifstream in(path, std::ios::binary);
  std::string head(bytes, '\0');
  in.read(head.data(), std::streamsize(bytes));
  head.resize(size_t(std::max<std::streamsize>(0, in.gcount())));
  return head;
}

bool IsRos2Folder(const fs::path& path) {
  std::error_code ec;
  if (fs::is_regular_file(path / "metadata.yaml", ec)) return true;
  for (const auto& entry : fs::directory_iterator(path, ec)) {
    const std::string ext = entry.path().extension().string();
    if (ext == ".db3" || ext == ".mcap") return true;
  }
  return false;
}

std::string Ros2Refusal(const std::string& path, const std::string& kind) {
  return path + ": a ROS 2 bag (" + kind +
         "). placedb reads ROS 1 bags; Debian 12 packages no reader of ROS 2 bags. Convert it "
         "to a ROS 1 bag, or export its images to a TUM-style folder (rgb.txt, depth.txt)";
}

bool IsPng16Gray(std::string_view bytes) {
  return bytes.size() >= 26 && bytes.substr(0, 8) == kPngSignature && uint8_t(bytes[24]) == 16 &&
         uint8_t(bytes[25]) == 0;
}

// The image's rows without their padding, the first `kept` of each pixel's `bytes_per_pixel`
// bytes (alpha dropped).
bool PackRows(const RosImage& image, size_t bytes_per_pixel, size_t kept, std::string* out,
              std::string* error) {
  const size_t row = size_t(image.width) * bytes_per_pixel;
  if (image.width == 0 || image.height == 0) {
    *error = "an empty image (" + std::to_string(image.width) + " x " +
             std::to_string(image.height) + ")";
    return false;
  }
  // Each row holds at least a byte, so height and row are bounded by the data: the product below
  // cannot overflow.
  if (image.height > image.data.size() || row > image.data.size() || image.step < row ||
      image.data.size() < size_t(image.step) * (image.height - 1) + row) {
    *error = std::to_string(image.data.size()) + " bytes with step " + std::to_string(image.step) +
             " for " + std::to_string(image.width) + " x " + std::to_string(image.height) + " " +
             image.encoding + " (rows need " + std::to_string(row) + " bytes)";
    return false;
  }
  out->resize(size_t(image.width) * image.height * kept);
  char* target = out->data();
  for (uint32_t y = 0; y < image.height; ++y) {
    const char* source = image.data.data() + size_t(y) * image.step;
    if (kept == bytes_per_pixel) {
      std::memcpy(target, source, row);
      target += row;
      continue;
    }
    for (uint32_t x = 0; x < image.width; ++x, source += bytes_per_pixel, target += kept) {
      std::memcpy(target, source, kept);
    }
  }
  return true;
}

// A colour message as the observation's image.
bool ColourImage(const BagMessage& message, v1::Observation* observation, std::string* error) {
  if (message.type == kCompressed) {
    RosCompressedImage compressed;
    if (!ParseRosCompressedImage(message.data, &compressed, error)) return false;
    if (!IsJpegOrPng(compressed.data)) {
      *error = "CompressedImage format '" + compressed.format + "' is neither JPEG nor PNG";
      return false;
    }
    observation->mutable_encoded_image()->set_data(std::move(compressed.data));
    return true;
  }
  RosImage image;
  if (!ParseRosImage(message.data, &image, error)) return false;
  const std::string encoding = AsciiLower(image.encoding);
  v1::PixelFormat format = v1::PIXEL_FORMAT_UNSPECIFIED;
  size_t bytes_per_pixel = 0, kept = 0;
  if (encoding == "rgb8" || encoding == "rgba8") {
    format = v1::PIXEL_FORMAT_RGB8;
    bytes_per_pixel = encoding == "rgb8" ? 3 : 4;
    kept = 3;
  } else if (encoding == "bgr8" || encoding == "bgra8") {
    format = v1::PIXEL_FORMAT_BGR8;
    bytes_per_pixel = encoding == "bgr8" ? 3 : 4;
    kept = 3;
  } else if (encoding == "mono8" || encoding == "8uc1") {
    format = v1::PIXEL_FORMAT_GRAY8;
    bytes_per_pixel = kept = 1;
  } else {
    *error = "encoding '" + image.encoding +
             "'; colour frames may be rgb8, bgr8, rgba8, bgra8, mono8 (or 8UC1), or a "
             "sensor_msgs/CompressedImage (JPEG / PNG)";
    return false;
  }
  v1::RawImage* raw = observation->mutable_raw_image();
  if (!PackRows(image, bytes_per_pixel, kept, raw->mutable_data(), error)) return false;
  raw->set_width(image.width);
  raw->set_height(image.height);
  raw->set_format(format);
  return true;
}

// A depth message as a DepthImage (16-bit: millimetres, 32FC1: metres).
bool DepthImage(const BagMessage& message, v1::DepthImage* depth, std::string* error) {
  if (message.type == kCompressed) {
    RosCompressedImage compressed;
    if (!ParseRosCompressedImage(message.data, &compressed, error)) return false;
    // image_transport's compressedDepth: a 12-byte header (format, quantisation), then a PNG;
    // for 16UC1 that PNG holds the millimetres themselves.
    const std::string format = AsciiLower(compressed.format);
    const bool sixteen = format.rfind("16uc1", 0) == 0 || format.rfind("mono16", 0) == 0;
    std::string_view png = compressed.data;
    if (sixteen && png.size() > 12 && png.substr(12, 8) == kPngSignature) png.remove_prefix(12);
    if (!IsPng16Gray(png)) {
      *error = "CompressedImage format '" + compressed.format +
               "': depth may be a 16-bit grayscale PNG (png or 16UC1 compressedDepth); 32FC1 "
               "compressedDepth (quantised inverse depth) is not read";
      return false;
    }
    depth->set_png16(std::string(png));
    depth->set_scale(0.001f);
    return true;
  }
  RosImage image;
  if (!ParseRosImage(message.data, &image, error)) return false;
  const std::string encoding = AsciiLower(image.encoding);
  const bool sixteen = encoding == "16uc1" || encoding == "mono16";
  if (!sixteen && encoding != "32fc1") {
    *error = "encoding '" + image.encoding +
             "'; depth images may be 16UC1 or mono16 (millimetres) or 32FC1 (metres)";
    return false;
  }
  std::string pixels;
  const size_t size = sixteen ? 2 : 4;
  if (!PackRows(image, size, size, &pixels, error)) return false;
  if (image.big_endian) {
    for (size_t i = 0; i < pixels.size(); i += size) std::reverse(&pixels[i], &pixels[i] + size);
  }
  if (!sixteen) {  // little-endian float32 is what the wire takes
    v1::RawDepth* raw = depth->mutable_raw_float32();
    raw->set_width(image.width);
    raw->set_height(image.height);
    raw->set_data(std::move(pixels));
    depth->set_scale(1.0f);
    return true;
  }
  cv::Mat mm(int(image.height), int(image.width), CV_16UC1);
  for (int y = 0; y < mm.rows; ++y) {
    uint16_t* row = mm.ptr<uint16_t>(y);
    for (int x = 0; x < mm.cols; ++x) {
      const size_t at = (size_t(y) * image.width + size_t(x)) * 2;
      row[x] = uint16_t(uint8_t(pixels[at]) | (uint8_t(pixels[at + 1]) << 8));
    }
  }
  std::string png;
  if (!EncodePng(mm, &png, error)) {
    *error = "cannot encode it as a 16-bit PNG: " + *error;
    return false;
  }
  depth->set_png16(std::move(png));
  depth->set_scale(0.001f);
  return true;
}

// Observation.camera from a CameraInfo (the Python SDK's Camera.from_camera_info); false + the
// model when placedb does not take it.
bool CameraFromInfo(const RosCameraInfo& info, v1::Camera* camera, std::string* refused_model) {
  std::string model = info.distortion_model;
  std::vector<double> coefficients = info.d;
  const auto all_zero = [](auto begin, auto end) {
    return std::all_of(begin, end, [](double v) { return v == 0; });
  };
  if (model == "rational_polynomial" && coefficients.size() >= 5 &&
      all_zero(coefficients.begin() + 5, coefficients.end())) {
    model = "plumb_bob";
    coefficients.resize(5);
  }
  if ((model == "plumb_bob" || model == "equidistant") &&
      all_zero(coefficients.begin(), coefficients.end())) {
    model.clear();
    coefficients.clear();
  }
  if (model != "" && model != "none" && model != "plumb_bob" && model != "equidistant") {
    *refused_model = model;
    return false;
  }
  camera->set_width(info.width);
  camera->set_height(info.height);
  camera->set_fx(info.k[0]);
  camera->set_fy(info.k[4]);
  camera->set_cx(info.k[2]);
  camera->set_cy(info.k[5]);
  camera->set_distortion_model(model);
  for (const double value : coefficients) camera->add_distortion(value);
  return true;
}

class BagRecording : public Recording {
 public:
  static std::unique_ptr<Recording> Open(const std::string& path, const RecordingOptions& options,
                                         std::string* error);
  std::string description() const override { return bag_->path() + " " + options_.topic; }
  size_t expected_frames() const override { return expected_; }
  bool Next(RecordedFrame* frame, std::string* error) override;

 private:
  struct Stamped {
    int64_t stamp_ns = 0;
    BagMessage message;
    size_t index = 0;  // colour frames: the position in the topic
  };
  bool Emit(bool final, RecordedFrame* frame, std::string* error);
  void ReadCameraInfo(const BagMessage& message);
  int64_t StampOf(const BagMessage& message);

  std::unique_ptr<BagReader> bag_;
  RecordingOptions options_;
  int64_t offset_ns_ = 0;
  size_t expected_ = 0;
  std::deque<Stamped> colours_;
  std::deque<Stamped> depths_;
  size_t colour_count_ = 0;
  bool at_end_ = false;
  std::optional<v1::Camera> camera_;
  std::optional<v1::Intrinsics> intrinsics_;
};

std::unique_ptr<Recording> BagRecording::Open(const std::string& path,
                                              const RecordingOptions& options, std::string* error) {
  std::unique_ptr<BagRecording> recording(new BagRecording());
  recording->options_ = options;
  recording->offset_ns_ = SecondsToNs(options.max_offset_s);
  if (options.topic.empty()) {
    *error = path + " is a ROS 1 bag: --topic names its colour image topic";
    return nullptr;
  }
  recording->bag_ = BagReader::Open(path, error);
  if (!recording->bag_) return nullptr;
  const std::vector<BagTopic> topics = recording->bag_->topics();
  std::string image_topics;
  for (const BagTopic& topic : topics) {
    if (topic.type == kImage || topic.type == kCompressed) {
      image_topics += (image_topics.empty() ? "" : ", ") + topic.topic + " (" + topic.type + ", " +
                      std::to_string(topic.messages) + " messages)";
    }
  }
  const auto check = [&](const std::string& flag, const std::string& name,
                         std::initializer_list<const char*> types) -> const BagTopic* {
    const auto it = std::find_if(topics.begin(), topics.end(),
                                 [&](const BagTopic& t) { return t.topic == name; });
    if (it == topics.end()) {
      *error = flag + " " + name + ": not in " + path +
               "; its image topics: " + (image_topics.empty() ? "none" : image_topics);
      return nullptr;
    }
    if (std::none_of(types.begin(), types.end(), [&](const char* t) { return it->type == t; })) {
      std::string expected;
      for (const char* t : types) expected += (expected.empty() ? "" : " or ") + std::string(t);
      *error = flag + " " + name + " in " + path + ": " + it->type + ", expected " + expected;
      return nullptr;
    }
    return &*it;
  };
  const BagTopic* colour = check("--topic", options.topic, {kImage, kCompressed});
  if (colour == nullptr) return nullptr;
  if (!options.depth_topic.empty()) {
    if (options.depth_topic == options.topic) {
      *error = "--depth-topic " + options.depth_topic + ": the colour topic itself";
      return nullptr;
    }
    if (!check("--depth-topic", options.depth_topic, {kImage, kCompressed})) return nullptr;
  }
  if (!options.camera_info_topic.empty() &&
      !check("--camera-info-topic", options.camera_info_topic, {kCameraInfo})) {
    return nullptr;
  }
  recording->expected_ = colour->messages;
  std::set<std::string> wanted = {options.topic};
  if (!options.depth_topic.empty()) wanted.insert(options.depth_topic);
  if (!options.camera_info_topic.empty()) wanted.insert(options.camera_info_topic);
  recording->bag_->Select(wanted);
  return recording;
}

int64_t BagRecording::StampOf(const BagMessage& message) {
  // Image, CompressedImage and CameraInfo all start with a std_msgs/Header: seq, then the stamp.
  int64_t stamp = 0;
  if (message.data.size() >= 12) {
    uint32_t secs = 0, nsecs = 0;
    for (int i = 3; i >= 0; --i) secs = (secs << 8) | uint8_t(message.data[4 + size_t(i)]);
    for (int i = 3; i >= 0; --i) nsecs = (nsecs << 8) | uint8_t(message.data[8 + size_t(i)]);
    stamp = int64_t(secs) * 1'000'000'000 + nsecs;
  }
  if (stamp != 0) return stamp;
  ++stats_.receive_time_stamps;
  return message.receive_time_ns;
}

void BagRecording::ReadCameraInfo(const BagMessage& message) {
  RosCameraInfo info;
  std::string ignored;
  if (!ParseRosCameraInfo(message.data, &info, &ignored) || !(info.k[0] > 0 && info.k[4] > 0)) {
    return;  // uncalibrated (K all zero) or damaged: the previous one stays
  }
  v1::Intrinsics intrinsics;
  intrinsics.set_fx(info.k[0]);
  intrinsics.set_fy(info.k[4]);
  intrinsics.set_cx(info.k[2]);
  intrinsics.set_cy(info.k[5]);
  intrinsics_ = intrinsics;
  v1::Camera camera;
  std::string model;
  if (CameraFromInfo(info, &camera, &model)) {
    camera_ = camera;
  } else {
    camera_.reset();  // frames still go in, without relative poses
    stats_.refused_model = model;
  }
}

bool BagRecording::Next(RecordedFrame* frame, std::string* error) {
  error->clear();
  for (;;) {
    if (Emit(at_end_, frame, error)) return true;
    if (at_end_) return false;
    BagMessage message;
    if (!bag_->Next(&message, error)) {
      if (!error->empty()) return false;
      at_end_ = true;
      continue;
    }
    if (message.topic == options_.camera_info_topic) {
      ReadCameraInfo(message);
    } else if (message.topic == options_.topic) {
      const int64_t stamp = StampOf(message);
      colours_.push_back({stamp, std::move(message), colour_count_++});
    } else {
      const int64_t stamp = StampOf(message);
      depths_.push_back({stamp, std::move(message), 0});
      if (depths_.size() > kMaxHeldDepths) depths_.pop_front();
    }
  }
}

bool BagRecording::Emit(bool final, RecordedFrame* frame, std::string* error) {
  if (colours_.empty()) return false;
  const int64_t stamp = colours_.front().stamp_ns;
  // A later depth image has a later stamp: once one lies beyond stamp + offset, no better one
  // for this frame can come.
  const bool has_depth = !options_.depth_topic.empty();
  const bool waiting = has_depth && !final && colours_.size() <= kMaxPendingFrames;
  if (waiting && !(!depths_.empty() && depths_.back().stamp_ns > stamp + offset_ns_)) return false;
  Stamped colour = std::move(colours_.front());
  colours_.pop_front();
  frame->index = colour.index;
  frame->name = bag_->path() + " " + options_.topic + " #" + std::to_string(colour.index);
  frame->observation.Clear();
  frame->observation.set_timestamp_ns(stamp);
  if (!ColourImage(colour.message, &frame->observation, error)) {
    *error = bag_->path() + ": " + options_.topic + " message " + std::to_string(colour.index) +
             ": " + *error;
    return true;
  }
  if (camera_) *frame->observation.mutable_camera() = *camera_;
  if (!camera_ && !stats_.refused_model.empty()) ++stats_.camera_refused;
  if (has_depth) {
    const Stamped* nearest = nullptr;
    for (const Stamped& depth : depths_) {
      if (!nearest || std::llabs(depth.stamp_ns - stamp) < std::llabs(nearest->stamp_ns - stamp)) {
        nearest = &depth;
      }
    }
    if (nearest && std::llabs(nearest->stamp_ns - stamp) <= offset_ns_) {
      v1::DepthImage* depth = frame->observation.mutable_depth();
      if (!DepthImage(nearest->message, depth, error)) {
        *error = bag_->path() + ": " + options_.depth_topic + " at " +
                 std::to_string(nearest->stamp_ns) + " ns: " + *error;
        frame->observation.clear_depth();
        return true;
      }
      if (options_.depth_scale > 0) depth->set_scale(options_.depth_scale);
      if (intrinsics_) {
        *depth->mutable_intrinsics() = *intrinsics_;
      } else if (options_.intrinsics) {
        *depth->mutable_intrinsics() = *options_.intrinsics;
      }
      ++stats_.depth_paired;
    } else {
      ++stats_.depth_missing;
    }
    while (!depths_.empty() && depths_.front().stamp_ns < stamp - offset_ns_) depths_.pop_front();
  }
  Count(*frame);
  return true;
}

// ---- TUM RGB-D folders ---------------------------------------------------------------------

struct ListRow {
  int64_t ns = 0;
  std::vector<std::string> columns;  // after the timestamp
};

// A TUM list's rows sorted by time ('#' lines skipped); false + *error naming the line.
bool ReadList(const fs::path& path, size_t columns, std::vector<ListRow>* rows,
              std::string* error) {
  std::ifstream in(path);
  if (!in) {
    *error = path.string() + ": cannot read";
    return false;
  }
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    std::istringstream fields(line);
    std::string stamp;
    if (!(fields >> stamp) || stamp[0] == '#') continue;
    ListRow row;
    std::string column;
    while (row.columns.size() < columns && fields >> column) row.columns.push_back(column);
    if (row.columns.size() < columns) {
      *error = path.string() + ":" + std::to_string(number) + ": " +
               std::to_string(row.columns.size() + 1) + " columns, expected a timestamp and " +
               std::to_string(columns) + " more";
      return false;
    }
    if (!ParseSecondsToNs(stamp, &row.ns)) {
      *error = path.string() + ":" + std::to_string(number) + ": '" + stamp +
               "' is not a timestamp in seconds";
      return false;
    }
    rows->push_back(std::move(row));
  }
  std::stable_sort(rows->begin(), rows->end(),
                   [](const ListRow& a, const ListRow& b) { return a.ns < b.ns; });
  return true;
}

// The index of the time nearest t in sorted `times`, within offset_ns.
std::optional<size_t> Nearest(const std::vector<int64_t>& times, int64_t t, int64_t offset_ns) {
  const size_t i = size_t(std::lower_bound(times.begin(), times.end(), t) - times.begin());
  std::optional<size_t> best;
  for (const size_t j : {i - 1, i}) {
    if (j >= times.size() || std::llabs(times[j] - t) > offset_ns) continue;
    if (!best || std::llabs(times[j] - t) < std::llabs(times[*best] - t)) best = j;
  }
  return best;
}

class TumRecording : public Recording {
 public:
  static std::unique_ptr<Recording> Open(const std::string& folder, const RecordingOptions& options,
                                         std::string* error);
  std::string description() const override { return folder_ + " (TUM)"; }
  size_t expected_frames() const override { return plan_.size(); }
  bool Next(RecordedFrame* frame, std::string* error) override;

 private:
  struct Planned {
    int64_t ns = 0;
    std::string image;
    std::string depth;  // "" = none within max_offset
    std::optional<v1::Pose> pose;
  };
  std::string folder_;
  RecordingOptions options_;
  bool has_depth_ = false, has_poses_ = false;
  std::vector<Planned> plan_;
  size_t next_ = 0;
};

std::unique_ptr<Recording> TumRecording::Open(const std::string& folder,
                                              const RecordingOptions& options, std::string* error) {
  if (!options.topic.empty() || !options.depth_topic.empty() ||
      !options.camera_info_topic.empty()) {
    *error = folder +
             " is a TUM RGB-D folder: --topic, --depth-topic and --camera-info-topic are "
             "for ROS bags";
    return nullptr;
  }
  std::unique_ptr<TumRecording> recording(new TumRecording());
  recording->folder_ = folder;
  recording->options_ = options;
  const fs::path root(folder);
  std::vector<ListRow> colours, depths, truth;
  if (!ReadList(root / "rgb.txt", 1, &colours, error)) return nullptr;
  if (colours.empty()) {
    *error = (root / "rgb.txt").string() + ": lists no frames";
    return nullptr;
  }
  std::error_code ec;
  recording->has_depth_ = fs::is_regular_file(root / "depth.txt", ec);
  recording->has_poses_ = fs::is_regular_file(root / "groundtruth.txt", ec);
  if (recording->has_depth_ && !ReadList(root / "depth.txt", 1, &depths, error)) return nullptr;
  if (recording->has_poses_ && !ReadList(root / "groundtruth.txt", 7, &truth, error)) {
    return nullptr;
  }
  std::vector<int64_t> depth_times, pose_times;
  for (const ListRow& row : depths) depth_times.push_back(row.ns);
  std::vector<v1::Pose> poses;
  for (const ListRow& row : truth) {
    double v[7];
    for (size_t i = 0; i < 7; ++i) {
      char* end = nullptr;
      v[i] = std::strtod(row.columns[i].c_str(), &end);
      if (end == row.columns[i].c_str() || *end != '\0' || !std::isfinite(v[i])) {
        *error = (root / "groundtruth.txt").string() + ": the sample at " + std::to_string(row.ns) +
                 " ns is not tx ty tz qx qy qz qw";
        return nullptr;
      }
    }
    v1::Pose pose;
    pose.set_x(v[0]);
    pose.set_y(v[1]);
    pose.set_z(v[2]);
    pose.set_qx(v[3]);
    pose.set_qy(v[4]);
    pose.set_qz(v[5]);
    pose.set_qw(v[6]);
    pose_times.push_back(row.ns);
    poses.push_back(pose);
  }
  const int64_t offset_ns = SecondsToNs(options.max_offset_s);
  const int64_t gap_ns = SecondsToNs(options.max_pose_gap_s);
  // Every file a frame will read must exist before anything is sent.
  for (const ListRow& row : colours) {
    Planned planned;
    planned.ns = row.ns;
    planned.image = (root / row.columns[0]).string();
    if (!fs::is_regular_file(planned.image, ec)) {
      *error = (root / "rgb.txt").string() + ": " + row.columns[0] + " (at " +
               std::to_string(row.ns) + " ns) does not exist";
      return nullptr;
    }
    if (const auto j = Nearest(depth_times, row.ns, offset_ns)) {
      planned.depth = (root / depths[*j].columns[0]).string();
      if (!fs::is_regular_file(planned.depth, ec)) {
        *error = (root / "depth.txt").string() + ": " + depths[*j].columns[0] + " does not exist";
        return nullptr;
      }
    }
    if (!poses.empty())
      planned.pose = InterpolatePose(pose_times, poses, row.ns, offset_ns, gap_ns);
    recording->plan_.push_back(std::move(planned));
  }
  return recording;
}

bool TumRecording::Next(RecordedFrame* frame, std::string* error) {
  error->clear();
  if (next_ >= plan_.size()) return false;
  const Planned& planned = plan_[next_];
  frame->index = next_++;
  frame->name = planned.image;
  frame->observation.Clear();
  frame->observation.set_timestamp_ns(planned.ns);
  std::string bytes;
  if (!ReadImageBytes(planned.image, &bytes, error)) return true;
  frame->observation.mutable_encoded_image()->set_data(std::move(bytes));
  if (!planned.depth.empty()) {
    v1::DepthImage* depth = frame->observation.mutable_depth();
    if (!ReadDepthImage(planned.depth, depth, error)) return true;
    depth->set_scale(options_.depth_scale > 0 ? options_.depth_scale : kTumDepthScale);
    if (options_.intrinsics) *depth->mutable_intrinsics() = *options_.intrinsics;
    ++stats_.depth_paired;
  } else if (has_depth_) {
    ++stats_.depth_missing;
  }
  if (planned.pose) {
    *frame->observation.mutable_pose() = *planned.pose;
    ++stats_.poses;
  } else if (has_poses_) {
    ++stats_.poses_missing;
  }
  Count(*frame);
  return true;
}

}  // namespace

void Recording::Count(const RecordedFrame& frame) {
  ++stats_.frames;
  if (frame.observation.has_camera()) ++stats_.cameras;
  const int64_t t = frame.observation.timestamp_ns();
  if (!stats_.first_ns) stats_.first_ns = t;
  stats_.last_ns = t;
}

bool Recording::IsRecording(const std::string& path) {
  std::error_code ec;
  const fs::path p(path);
  if (fs::is_directory(p, ec)) return fs::is_regular_file(p / "rgb.txt", ec) || IsRos2Folder(p);
  if (!fs::is_regular_file(p, ec)) return false;
  const std::string ext = AsciiLower(p.extension().string());
  if (ext == ".bag" || ext == ".mcap" || ext == ".db3") return true;
  return FileHead(path, 13) == "#ROSBAG V2.0\n";
}

std::unique_ptr<Recording> Recording::Open(const std::string& path, const RecordingOptions& options,
                                           std::string* error) {
  if (!(options.max_offset_s >= 0) || !(options.max_pose_gap_s >= 0)) {
    *error = "--max-offset and --max-pose-gap are seconds >= 0";
    return nullptr;
  }
  std::error_code ec;
  const fs::path p(path);
  if (fs::is_directory(p, ec)) {
    if (fs::is_regular_file(p / "rgb.txt", ec)) return TumRecording::Open(path, options, error);
    *error = Ros2Refusal(path, "a rosbag2 folder");
    return nullptr;
  }
  const std::string head = FileHead(path, 16);
  if (head.rfind("\x89MCAP0\r\n", 0) == 0) {
    *error = Ros2Refusal(path, "MCAP");
    return nullptr;
  }
  if (head.rfind(std::string("SQLite format 3\0", 16), 0) == 0) {
    *error = Ros2Refusal(path, "rosbag2 SQLite .db3");
    return nullptr;
  }
  return BagRecording::Open(path, options, error);
}

bool ParseSecondsToNs(const std::string& text, int64_t* ns) {
  const size_t dot = text.find('.');
  std::string whole = text.substr(0, dot);
  const std::string fraction = dot == std::string::npos ? "" : text.substr(dot + 1);
  const bool negative = !whole.empty() && whole[0] == '-';
  if (!whole.empty() && (whole[0] == '-' || whole[0] == '+')) whole.erase(0, 1);
  const auto digits = [](const std::string& s) {
    return std::all_of(s.begin(), s.end(), [](char c) { return c >= '0' && c <= '9'; });
  };
  // Beyond 9e9 s (year 2255) the nanoseconds would not fit an int64.
  if (whole.empty() || whole.size() > 10 || !digits(whole) || !digits(fraction) ||
      fraction.size() > 9 || std::stoll(whole) >= 9'000'000'000) {
    return false;
  }
  int64_t value = std::stoll(whole) * 1'000'000'000;
  int64_t part = 0;
  for (size_t i = 0; i < 9; ++i) part = part * 10 + (i < fraction.size() ? fraction[i] - '0' : 0);
  value += part;
  *ns = negative ? -value : value;
  return true;
}

std::optional<v1::Pose> InterpolatePose(const std::vector<int64_t>& times,
                                        const std::vector<v1::Pose>& poses, int64_t t,
                                        int64_t max_offset_ns, int64_t max_gap_ns) {
  const size_t i = size_t(std::lower_bound(times.begin(), times.end(), t) - times.begin());
  if (i < times.size() && times[i] == t) return poses[i];
  if (i > 0 && i < times.size() && times[i] - times[i - 1] <= max_gap_ns) {
    const v1::Pose& a = poses[i - 1];
    const v1::Pose& b = poses[i];
    const double u = double(t - times[i - 1]) / double(times[i] - times[i - 1]);
    double qa[4] = {a.qx(), a.qy(), a.qz(), a.qw()};
    double qb[4] = {b.qx(), b.qy(), b.qz(), b.qw()};
    const auto normalise = [](double* q) {
      const double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
      if (n > 0) {
        for (int k = 0; k < 4; ++k) q[k] /= n;
      }
    };
    normalise(qa);
    normalise(qb);
    double dot = qa[0] * qb[0] + qa[1] * qb[1] + qa[2] * qb[2] + qa[3] * qb[3];
    if (dot < 0) {  // the shorter way round
      for (double& v : qb) v = -v;
      dot = -dot;
    }
    double q[4];
    if (dot > 0.9995) {  // nearly equal: linear, then normalised
      for (int k = 0; k < 4; ++k) q[k] = qa[k] + u * (qb[k] - qa[k]);
    } else {
      const double angle = std::acos(dot);
      const double wa = std::sin((1 - u) * angle) / std::sin(angle);
      const double wb = std::sin(u * angle) / std::sin(angle);
      for (int k = 0; k < 4; ++k) q[k] = wa * qa[k] + wb * qb[k];
    }
    normalise(q);
    v1::Pose pose;
    pose.set_x(a.x() + u * (b.x() - a.x()));
    pose.set_y(a.y() + u * (b.y() - a.y()));
    pose.set_z(a.z() + u * (b.z() - a.z()));
    pose.set_qx(q[0]);
    pose.set_qy(q[1]);
    pose.set_qz(q[2]);
    pose.set_qw(q[3]);
    return pose;
  }
  if (const auto j = Nearest(times, t, max_offset_ns)) return poses[*j];
  return std::nullopt;
}

}  // namespace placedb::client
