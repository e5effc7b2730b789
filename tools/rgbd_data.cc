#include "tools/rgbd_data.h"

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/base/files.h"

namespace fs = std::filesystem;

namespace placedb::rgbd {

std::vector<RgbdFrame> RgbdPeopleFrames() {
  std::vector<RgbdFrame> frames;
  const fs::path root = fs::path(SharedDir()) / "data" / "rgbd-people";
  if (!fs::is_directory(root / "image")) return frames;
  for (const auto& sequence : fs::directory_iterator(root / "image")) {
    if (!sequence.is_directory()) continue;
    for (const auto& entry : fs::directory_iterator(sequence.path())) {
      if (!IsImageFile(entry.path())) continue;
      const std::string seq = sequence.path().filename().string();
      const std::string stem = entry.path().stem().string();
      RgbdFrame frame;
      frame.name = seq + "/" + stem;
      frame.image_path = entry.path().string();
      frame.depth_path = (root / "depth" / seq / (stem + ".png")).string();
      frames.push_back(frame);
    }
  }
  std::sort(frames.begin(), frames.end(),
            [](const RgbdFrame& a, const RgbdFrame& b) { return a.name < b.name; });
  return frames;
}

std::vector<RgbdFrame> SlambookFrames() {
  std::vector<RgbdFrame> frames;
  const fs::path root = fs::path(SharedDir()) / "data" / "slambook2-rgbd";
  for (int i = 1; i <= 5; ++i) {
    const fs::path color = root / "color" / (std::to_string(i) + ".png");
    if (!fs::exists(color)) continue;
    frames.push_back({"slambook/" + std::to_string(i), color.string(),
                      (root / "depth" / (std::to_string(i) + ".pgm")).string()});
  }
  return frames;
}

CameraIntrinsics SlambookIntrinsics() {
  return {518.0, 519.0, 325.5, 253.5};
}

std::string YoloxModelPath() {
  for (const std::string& dir : {std::string(PLACEDB_MODELS_DIR), SharedDir() + "/models"}) {
    const std::string path = dir + "/yolox_nano.onnx";
    if (fs::exists(path)) return path;
  }
  return "";
}

Result<cv::Mat> ReadDepthMetres(const std::string& path, const DepthFormat& format) {
  cv::Mat raw = cv::imread(path, cv::IMREAD_ANYDEPTH);
  if (raw.empty()) return Status::NotFound("cannot read depth image " + path);
  return DepthToMetres(raw, format);
}

Result<std::shared_ptr<const FloatVocabulary>> TrainDebianSiftVocabulary(
    const SiftVocabularyOptions& options, size_t* descriptors_used) {
  const auto paths = DebianSampleImages();
  if (paths.empty()) {
    return Status::NotFound(
        "no Debian sample images: install opencv-doc and darknet (apt-get install opencv-doc "
        "darknet)");
  }
  SiftConfig sift;
  sift.max_features = options.features_per_image;
  std::vector<std::vector<float>> images;
  size_t total = 0;
  for (const auto& path : paths) {
    cv::Mat gray = cv::imread(path, cv::IMREAD_GRAYSCALE);
    if (gray.empty() || gray.cols < 32 || gray.rows < 32) continue;
    // Full size and half size: more descriptors, and words for the coarser scales a robot sees
    // of the same structures.
    cv::Mat half;
    cv::resize(gray, half, cv::Size(), 0.5, 0.5, cv::INTER_AREA);
    for (const cv::Mat* image : {&gray, &half}) {
      auto features = ExtractSift(*image, sift);
      if (!features.ok() || features->empty()) continue;
      total += features->size();
      images.push_back(std::move(features->descriptors));
    }
  }
  if (descriptors_used != nullptr) *descriptors_used = total;
  FloatTrainerConfig config;
  config.branching = options.branching;
  config.depth = options.depth;
  config.seed = options.seed;
  config.threads = options.threads;
  return FloatVocabulary::Train(images, kSiftDimensions, config);
}

std::string SiftVocabularyPath() {
  if (const char* env = std::getenv("PLACEDB_SIFT_VOCABULARY")) return env;
  return PLACEDB_SIFT_VOCABULARY;
}

Result<std::shared_ptr<const FloatVocabulary>> LoadOrTrainSiftVocabulary(
    const std::string& path, const SiftVocabularyOptions& options) {
  if (fs::exists(path)) {
    auto loaded = FloatVocabulary::Load(path);
    if (loaded.ok()) return loaded;
  }
  auto trained = TrainDebianSiftVocabulary(options);
  if (!trained.ok()) return trained.status();
  std::error_code ec;
  fs::create_directories(fs::path(path).parent_path(), ec);
  PLACEDB_RETURN_IF_ERROR((*trained)->Save(path));
  return trained;
}

// The front-facing person of rgbd-people test2 (second frame): the largest connected region
// nearer than 2 m (the floor behind starts at 2.1 m in that frame).
PersonSprite LoadPersonSprite() {
  PersonSprite s;
  for (const auto& frame : rgbd::RgbdPeopleFrames()) {
    if (frame.name != "test2/1534837744.426981") continue;
    s.bgr = cv::imread(frame.image_path, cv::IMREAD_COLOR);
    auto metres = rgbd::ReadDepthMetres(frame.depth_path);
    if (!metres.ok() || s.bgr.empty()) return {};
    s.metres = *metres;
  }
  if (s.bgr.empty()) return s;
  cv::Mat near = (s.metres > 0) & (s.metres < 2.0f);
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(near, labels, stats, centroids);
  int best = 0;
  for (int i = 1; i < n; ++i) {
    if (best == 0 || stats.at<int>(i, cv::CC_STAT_AREA) > stats.at<int>(best, cv::CC_STAT_AREA)) {
      best = i;
    }
  }
  s.mask = labels == best;
  std::vector<float> depths;
  for (int r = 0; r < s.mask.rows; ++r) {
    for (int c = 0; c < s.mask.cols; ++c) {
      if (s.mask.at<uint8_t>(r, c)) depths.push_back(s.metres.at<float>(r, c));
    }
  }
  std::nth_element(depths.begin(), depths.begin() + std::ptrdiff_t(depths.size() / 2),
                   depths.end());
  s.depth = depths[depths.size() / 2];
  return s;
}

// The person at distance z (metres) in front of the room, by pinhole scaling about the principal
// point (scale z0 / z, depths shifted by z - z0) and a z-buffer against the room's depth.
Composite ComposePerson(const PersonSprite& sprite, const cv::Mat& room_bgr,
                        const cv::Mat& room_metres, const CameraIntrinsics& k, double z,
                        cv::RNG* rng) {
  Composite c;
  c.bgr = room_bgr.clone();
  c.metres = room_metres.clone();
  // Sensor noise: ~0.5 % depth jitter, a little image noise.
  cv::Mat jitter(c.metres.size(), CV_32F);
  rng->fill(jitter, cv::RNG::NORMAL, 0.0, 0.005);
  cv::Mat valid = c.metres > 0;
  c.metres = c.metres.mul(1.0f + jitter);
  c.metres.setTo(0, ~valid);
  cv::Mat noise(c.bgr.size(), CV_16SC3);
  rng->fill(noise, cv::RNG::NORMAL, 0, 2);
  cv::Mat noisy;
  c.bgr.convertTo(noisy, CV_16SC3);
  noisy += noise;
  noisy.convertTo(c.bgr, CV_8UC3);
  c.person = cv::Mat::zeros(c.bgr.size(), CV_8U);
  if (z <= 0) return c;
  const double s = sprite.depth / z;
  const double sprite_cx = sprite.bgr.cols / 2.0, sprite_cy = sprite.bgr.rows / 2.0;
  cv::Mat affine =
      (cv::Mat_<double>(2, 3) << s, 0, k.cx - sprite_cx * s, 0, s, k.cy - sprite_cy * s);
  cv::Mat bgr, metres, mask;
  cv::warpAffine(sprite.bgr, bgr, affine, c.bgr.size(), cv::INTER_LINEAR);
  cv::warpAffine(sprite.metres, metres, affine, c.bgr.size(), cv::INTER_NEAREST);
  cv::warpAffine(sprite.mask, mask, affine, c.bgr.size(), cv::INTER_NEAREST);
  const float shift = float(z) - sprite.depth;
  for (int r = 0; r < c.bgr.rows; ++r) {
    for (int col = 0; col < c.bgr.cols; ++col) {
      if (!mask.at<uint8_t>(r, col)) continue;
      const float d = metres.at<float>(r, col);
      if (d <= 0) continue;
      const float person_depth = d + shift;
      const float room = c.metres.at<float>(r, col);
      if (room > 0 && room <= person_depth) continue;  // the room is in front
      c.metres.at<float>(r, col) = person_depth;
      c.bgr.at<cv::Vec3b>(r, col) = bgr.at<cv::Vec3b>(r, col);
      c.person.at<uint8_t>(r, col) = 255;
    }
  }
  return c;
}

}  // namespace placedb::rgbd
