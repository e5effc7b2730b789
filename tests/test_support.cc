#include "tests/test_support.h"

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <random>

#include "core/base/files.h"

namespace fs = std::filesystem;

namespace placedb::testing {

namespace {
std::vector<std::string>& TempDirs() {
  static std::vector<std::string> dirs;
  return dirs;
}
void RemoveTempDirs() {
  for (const auto& dir : TempDirs()) {
    std::error_code ec;
    fs::remove_all(dir, ec);
  }
}
}  // namespace

std::string MakeTempDir(const std::string& prefix) {
  static std::once_flag once;
  // Construct the list before registering the handler, so it is destroyed after the handler ran.
  std::call_once(once, [] {
    TempDirs();
    std::atexit(RemoveTempDirs);
  });
  std::string pattern = (fs::temp_directory_path() / (prefix + "-XXXXXX")).string();
  std::vector<char> buffer(pattern.begin(), pattern.end());
  buffer.push_back('\0');
  char* made = mkdtemp(buffer.data());
  EXPECT_NE(made, nullptr) << "mkdtemp " << pattern;
  std::string dir = made ? made : pattern;
  TempDirs().push_back(dir);
  return dir;
}

std::string ReadFileBytes(const std::string& path) {
  auto bytes = ReadWholeFile(path);
  EXPECT_TRUE(bytes.ok()) << bytes.status().ToString();
  return bytes.ok() ? std::move(*bytes) : std::string();
}

int UnusedLoopbackPort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  EXPECT_EQ(bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
  socklen_t length = sizeof address;
  getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length);
  close(fd);
  return ntohs(address.sin_port);
}

cv::Mat ReadGray(const std::string& path) {
  cv::Mat image = cv::imread(path, cv::IMREAD_GRAYSCALE);
  EXPECT_FALSE(image.empty()) << "cannot read " << path;
  return image;
}

std::vector<CamVidFrame> CamVidFrames() {
  std::vector<CamVidFrame> frames;
  const std::string root = SharedDir() + "/data/camvid";
  if (!fs::is_directory(root + "/images")) return frames;
  for (const auto& entry : fs::directory_iterator(root + "/images")) {
    const std::string stem = entry.path().stem().string();  // SEQ_FRAME
    const auto underscore = stem.rfind('_');
    if (!IsImageFile(entry.path()) || underscore == std::string::npos) continue;
    CamVidFrame frame;
    frame.sequence = stem.substr(0, underscore);
    // Frame numbers: "0001TP_006690", but "0006R0_f00930" in one sequence.
    const std::string number = stem.substr(underscore + 1);
    const size_t digits = number.find_first_of("0123456789");
    if (digits == std::string::npos) continue;
    frame.frame = std::stoi(number.substr(digits));
    frame.image_path = entry.path().string();
    frame.label_path = root + "/labels/" + stem + ".png";
    frames.push_back(frame);
  }
  std::sort(frames.begin(), frames.end(), [](const CamVidFrame& a, const CamVidFrame& b) {
    return std::tie(a.sequence, a.frame) < std::tie(b.sequence, b.frame);
  });
  return frames;
}

cv::Mat CamVidDynamicMask(const CamVidFrame& frame) {
  cv::Mat labels = cv::imread(frame.label_path, cv::IMREAD_GRAYSCALE);
  EXPECT_FALSE(labels.empty()) << "cannot read " << frame.label_path;
  cv::Mat mask = (labels == 8) | (labels == 9) | (labels == 10);
  return mask;
}

cv::Mat RtabmapGroundTruth() {
  cv::Mat truth = data::RtabmapGroundTruth();
  EXPECT_EQ(truth.rows, 84);
  EXPECT_EQ(truth.cols, 84);
  return truth;
}

FeatureSet ExtractFile(const std::string& path, int max_features) {
  OrbConfig config;
  config.max_features = max_features;
  auto features = ExtractOrb(ReadGray(path), config);
  EXPECT_TRUE(features.ok()) << features.status().ToString();
  return features.ok() ? *features : FeatureSet{};
}

}  // namespace placedb::testing
