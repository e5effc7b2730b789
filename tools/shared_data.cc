#include "tools/shared_data.h"

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>

#include "core/base/files.h"

namespace fs = std::filesystem;

namespace placedb::data {

std::string SharedDir() {
  if (const char* env = std::getenv("PLACEDB_SHARED_DIR")) return env;
  return PLACEDB_SHARED_DIR;
}

bool HaveSharedData() {
  return fs::is_directory(SharedDir() + "/data");
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
      if (IsImageFile(entry.path())) paths.push_back(entry.path().string());
    }
  }
  std::sort(paths.begin(), paths.end());
  return paths;
}

}  // namespace placedb::data
