#include "rgbd/rgbd_support.h"

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace fs = std::filesystem;

namespace placedb::rgbd {

std::string SharedDir() {
  if (const char* env = std::getenv("PLACEDB_SHARED_DIR")) return env;
  return PLACEDB_SHARED_DIR_RGBD;
}

bool HaveSharedData() {
  return fs::is_directory(SharedDir() + "/data");
}

std::vector<RgbdFrame> RgbdPeopleFrames() {
  std::vector<RgbdFrame> frames;
  const fs::path root = fs::path(SharedDir()) / "data" / "rgbd-people";
  if (!fs::is_directory(root / "image")) return frames;
  for (const auto& sequence : fs::directory_iterator(root / "image")) {
    if (!sequence.is_directory()) continue;
    for (const auto& entry : fs::directory_iterator(sequence.path())) {
      if (entry.path().extension() != ".png") continue;
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

std::string RtabmapFramePath(int frame) {
  return SharedDir() + "/data/rtabmap-loop/" + std::to_string(frame) + ".jpg";
}

cv::Mat RtabmapGroundTruth() {
  return cv::imread(SharedDir() + "/data/rtabmap-loop/ground_truth.bmp", cv::IMREAD_GRAYSCALE);
}

std::vector<std::string> DebianSampleImages() {
  std::vector<std::string> paths;
  for (const char* dir : {"/usr/share/doc/opencv-doc/examples/data", "/usr/share/darknet/data"}) {
    if (!fs::is_directory(dir)) continue;
    for (const auto& entry : fs::directory_iterator(dir)) {
      const auto ext = entry.path().extension().string();
      if (ext == ".jpg" || ext == ".png") paths.push_back(entry.path().string());
    }
  }
  std::sort(paths.begin(), paths.end());
  return paths;
}

std::string YoloxModelPath() {
  for (const std::string& dir : {std::string(PLACEDB_MODELS_DIR_RGBD), SharedDir() + "/models"}) {
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

}  // namespace placedb::rgbd
