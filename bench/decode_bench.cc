// placedb image decoding benchmark: prints `name value unit` lines.
//
// The strict decoder (core/decode/image_decoder.h: TurboJPEG with warnings as errors; PNG chunk
// and CRC walk, then libpng with its benign errors made errors) against cv::imdecode on the same
// bytes in the same run, one thread, the two interleaved image by image so both see the same
// machine load:
//  - real 640x480 JPEGs: the rgbd-people camera frames (../shared/data, PNG) encoded at quality
//    90 by OpenCV, and Debian's opencv-doc 640x480 JPEG files as they are;
//  - the same camera frames as PNG (the CRC walk's cost).
// Figures are medians of per-image times (ms); `*_speedup` = imdecode median / strict median.
//
// Usage: placedb-bench-decode [--rounds N]   (default 30)
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "bench/bench_output.h"
#include "core/decode/image_decoder.h"
#include "tools/shared_data.h"

namespace fs = std::filesystem;
using namespace placedb;
using bench::Median;
using bench::NowMs;
using bench::Print;

namespace {

std::vector<std::string> RgbdFrames() {
  std::vector<std::string> paths;
  const fs::path root = fs::path(data::SharedDir()) / "data" / "rgbd-people" / "image";
  std::error_code error;
  for (const auto& entry : fs::recursive_directory_iterator(root, error)) {
    if (entry.path().extension() == ".png") paths.push_back(entry.path().string());
  }
  std::sort(paths.begin(), paths.end());
  return paths;
}

std::vector<std::vector<uint8_t>> Encode(const std::vector<std::string>& paths, const char* ext,
                                         std::vector<int> params) {
  std::vector<std::vector<uint8_t>> out;
  for (const std::string& path : paths) {
    const cv::Mat image = cv::imread(path, cv::IMREAD_COLOR);
    if (image.cols != 640 || image.rows != 480) continue;
    std::vector<uint8_t> bytes;
    if (cv::imencode(ext, image, bytes, params)) out.push_back(std::move(bytes));
  }
  return out;
}

std::vector<std::vector<uint8_t>> DebianJpegs() {
  std::vector<std::vector<uint8_t>> out;
  for (const std::string& path : data::DebianSampleImages()) {
    if (fs::path(path).extension() != ".jpg") continue;
    const cv::Mat header = cv::imread(path, cv::IMREAD_UNCHANGED);
    if (header.cols != 640 || header.rows != 480) continue;
    FILE* file = std::fopen(path.c_str(), "rb");
    if (!file) continue;
    std::vector<uint8_t> bytes(fs::file_size(path));
    const size_t read = std::fread(bytes.data(), 1, bytes.size(), file);
    std::fclose(file);
    if (read == bytes.size()) out.push_back(std::move(bytes));
  }
  return out;
}

// Interleaved timings of the strict decoder and cv::imdecode; false if any image differs or fails.
bool Compare(const std::string& name, const std::vector<std::vector<uint8_t>>& images,
             ColorMode mode, int flags, int rounds) {
  if (images.empty()) {
    std::fprintf(stderr, "%s: no images\n", name.c_str());
    return false;
  }
  std::vector<double> strict, opencv;
  double max_difference = 0;
  for (int round = 0; round < rounds; ++round) {
    for (const std::vector<uint8_t>& bytes : images) {
      // Alternate which goes first, so neither always gets the warm cache.
      for (int turn = 0; turn < 2; ++turn) {
        const bool ours = (turn == 0) == (round % 2 == 0);
        const double start = NowMs();
        cv::Mat image;
        if (ours) {
          auto decoded = DecodeImage(bytes, DecodeOptions{mode, 0});
          if (!decoded.ok()) {
            std::fprintf(stderr, "%s: %s\n", name.c_str(), decoded.status().ToString().c_str());
            return false;
          }
          image = std::move(decoded).value();
          strict.push_back(NowMs() - start);
        } else {
          image = cv::imdecode(bytes, flags);
          opencv.push_back(NowMs() - start);
        }
        if (round == 0 && !ours) {
          auto again = DecodeImage(bytes, DecodeOptions{mode, 0});
          if (!again.ok() || again->size() != image.size() || again->type() != image.type()) {
            return false;
          }
          max_difference = std::max(max_difference, cv::norm(*again, image, cv::NORM_INF));
        }
      }
    }
  }
  Print(name + "_images", double(images.size()), "images");
  Print(name + "_strict_ms", Median(strict), "ms");
  Print(name + "_imdecode_ms", Median(opencv), "ms");
  Print(name + "_speedup", Median(opencv) / Median(strict), "x");
  Print(name + "_max_pixel_difference", max_difference, "levels");
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  int rounds = 30;
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--rounds") == 0 && i + 1 < argc) rounds = std::atoi(argv[++i]);
  }
  cv::setNumThreads(1);
  const std::vector<std::string> frames = RgbdFrames();
  const auto camera_jpegs = Encode(frames, ".jpg", {cv::IMWRITE_JPEG_QUALITY, 90});
  const auto debian_jpegs = DebianJpegs();
  const auto camera_pngs = Encode(frames, ".png", {});
  bool ok = true;
  ok &= Compare("decode_jpeg640_camera_gray", camera_jpegs, ColorMode::kGray, cv::IMREAD_GRAYSCALE,
                rounds);
  ok &= Compare("decode_jpeg640_camera_color", camera_jpegs, ColorMode::kColor, cv::IMREAD_COLOR,
                rounds);
  ok &= Compare("decode_jpeg640_debian_gray", debian_jpegs, ColorMode::kGray, cv::IMREAD_GRAYSCALE,
                rounds);
  ok &= Compare("decode_jpeg640_debian_color", debian_jpegs, ColorMode::kColor, cv::IMREAD_COLOR,
                rounds);
  ok &= Compare("decode_png640_camera_color", camera_pngs, ColorMode::kColor, cv::IMREAD_COLOR,
                rounds);

  // The header read the wire layer does before decoding (the pixel limit check).
  std::vector<double> header;
  for (int round = 0; round < rounds; ++round) {
    for (const auto& bytes : camera_jpegs) {
      const double start = NowMs();
      auto info = ReadImageInfo(bytes);
      header.push_back(NowMs() - start);
      if (!info.ok()) ok = false;
    }
  }
  Print("decode_jpeg_header_ms", Median(header), "ms");
  return ok ? 0 : 1;
}
