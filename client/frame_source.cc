#include "client/frame_source.h"

#include <fnmatch.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>

#include "client/format.h"
#include "client/image_io.h"
#include "core/base/files.h"
#include "core/base/text.h"

namespace fs = std::filesystem;

namespace placedb::client {

namespace {

std::string LowerExtension(const fs::path& path) {
  return AsciiLower(path.extension().string());
}

bool IsListExtension(const std::string& ext) {
  return ext == ".txt" || ext == ".lst" || ext == ".list";
}

std::string Trim(const std::string& text) {
  const auto begin = text.find_first_not_of(" \t\r\n");
  if (begin == std::string::npos) return "";
  const auto end = text.find_last_not_of(" \t\r\n");
  return text.substr(begin, end - begin + 1);
}

}  // namespace

bool ReadImageBytes(const std::string& path, std::string* bytes, std::string* error) {
  auto contents = ReadWholeFile(path);
  if (!contents.ok()) {
    *error = contents.status().message();
    return false;
  }
  *bytes = std::move(*contents);
  if (IsJpegOrPng(*bytes)) return true;
  cv::Mat image;
  if (!DecodeImageFileBytes(path, *bytes, ImageRead::kUnchanged, &image, error)) return false;
  if (image.depth() != CV_8U)
    image.convertTo(image, CV_8U, image.depth() == CV_16U ? 1 / 257.0 : 1);
  std::string png;
  if (!EncodePng(image, &png, error)) {
    *error = "cannot re-encode " + path + " as PNG: " + *error;
    return false;
  }
  *bytes = std::move(png);
  return true;
}

std::string FindDepthImage(const std::string& depth_dir, const std::string& colour_path,
                           std::string* error) {
  const std::string stem = fs::path(colour_path).stem().string();
  std::string tried;
  for (const char* ext : {".png", ".pgm", ".tif", ".tiff"}) {
    const fs::path candidate = fs::path(depth_dir) / (stem + ext);
    std::error_code ec;
    if (fs::is_regular_file(candidate, ec)) return candidate.string();
    tried += (tried.empty() ? "" : ", ") + candidate.string();
  }
  *error = "no depth image for frame " + colour_path + ": looked for " + tried;
  return "";
}

bool ReadDepthImage(const std::string& path, v1::DepthImage* depth, std::string* error) {
  auto contents = ReadWholeFile(path);
  if (!contents.ok()) {
    *error = "depth image: " + contents.status().message();
    return false;
  }
  std::string bytes = std::move(*contents);
  // A PNG's IHDR: bit depth at byte 24, colour type at 25 (0 = greyscale).
  const bool png = bytes.size() >= 26 && bytes.compare(0, 8, "\x89PNG\r\n\x1a\n") == 0;
  if (png && uint8_t(bytes[24]) == 16 && uint8_t(bytes[25]) == 0) {
    depth->set_png16(std::move(bytes));
    return true;
  }
  cv::Mat image;
  if (!DecodeImageFileBytes(path, bytes, ImageRead::kUnchanged, &image, error)) {
    *error = "depth image: " + *error;
    return false;
  }
  if (image.channels() != 1 || (image.depth() != CV_16U && image.depth() != CV_32F)) {
    *error = "depth image " + path + " must be single-channel 16-bit or float32 (it has " +
             std::to_string(image.channels()) + " channel(s) of " +
             (image.depth() == CV_8U ? "8-bit" : "type " + std::to_string(image.depth())) + ")";
    return false;
  }
  if (image.depth() == CV_16U) {
    std::string encoded;
    if (!EncodePng(image, &encoded, error)) {
      *error = "cannot re-encode depth image " + path + " as 16-bit PNG: " + *error;
      return false;
    }
    depth->set_png16(std::move(encoded));
    return true;
  }
  v1::RawDepth* raw = depth->mutable_raw_float32();
  raw->set_width(uint32_t(image.cols));
  raw->set_height(uint32_t(image.rows));
  std::string data(size_t(image.total()) * 4, '\0');
  size_t offset = 0;
  for (int row = 0; row < image.rows; ++row) {
    const float* values = image.ptr<float>(row);
    for (int col = 0; col < image.cols; ++col) {
      uint32_t bits = 0;
      std::memcpy(&bits, &values[col], 4);
      for (int b = 0; b < 4; ++b) data[offset++] = char((bits >> (8 * b)) & 0xFF);  // LE
    }
  }
  raw->set_data(std::move(data));
  return true;
}

bool ParseCamera(const std::string& text, v1::Camera* camera, std::string* error) {
  v1::Intrinsics k;
  if (!ParseIntrinsics(text, &k, error)) {
    if (error->rfind("--intrinsics", 0) == 0) error->replace(0, 12, "--camera");
    return false;
  }
  camera->set_fx(k.fx());
  camera->set_fy(k.fy());
  camera->set_cx(k.cx());
  camera->set_cy(k.cy());
  return true;
}

bool ParseIntrinsics(const std::string& text, v1::Intrinsics* intrinsics, std::string* error) {
  std::vector<double> values;
  size_t start = 0;
  while (start <= text.size()) {
    size_t comma = text.find(',', start);
    if (comma == std::string::npos) comma = text.size();
    const std::string item = Trim(text.substr(start, comma - start));
    char* end = nullptr;
    const double value = item.empty() ? NAN : std::strtod(item.c_str(), &end);
    if (item.empty() || end != item.c_str() + item.size() || !std::isfinite(value)) {
      *error = "--intrinsics: expected fx,fy,cx,cy (4 numbers, pixels), got '" + text + "'";
      return false;
    }
    values.push_back(value);
    start = comma + 1;
  }
  if (values.size() != 4) {
    *error = "--intrinsics: expected fx,fy,cx,cy (4 numbers, pixels), got '" + text + "'";
    return false;
  }
  if (values[0] <= 0 || values[1] <= 0 || values[2] < 0 || values[3] < 0) {
    *error = "--intrinsics: fx and fy must be > 0, cx and cy >= 0 (got '" + text + "')";
    return false;
  }
  intrinsics->set_fx(values[0]);
  intrinsics->set_fy(values[1]);
  intrinsics->set_cx(values[2]);
  intrinsics->set_cy(values[3]);
  return true;
}

FrameSource::~FrameSource() = default;

std::vector<std::string> FrameSource::image_paths() const {
  std::vector<std::string> paths;
  for (const Item& item : items_) {
    if (!item.video) paths.push_back(item.path);
  }
  return paths;
}

std::vector<std::string> FrameSource::video_paths() const {
  std::vector<std::string> paths;
  for (const Item& item : items_) {
    if (item.video) paths.push_back(item.path);
  }
  return paths;
}

std::unique_ptr<FrameSource> FrameSource::Open(const std::vector<std::string>& sources,
                                               int video_every, const std::string& glob,
                                               std::string* error) {
  std::unique_ptr<FrameSource> source(new FrameSource());
  source->video_every_ = std::max(1, video_every);
  size_t total = 0;
  bool exact = true;
  auto add_image = [&](const std::string& path) {
    source->items_.push_back({path, false});
    ++total;
  };
  for (const std::string& arg : sources) {
    std::error_code ec;
    const fs::path path(arg);
    if (fs::is_directory(path, ec)) {
      auto images = ListImageFiles(arg);
      if (!images.ok()) {
        *error = images.status().message();
        return nullptr;
      }
      size_t matched = 0;
      for (const std::string& image : *images) {
        const std::string name = fs::path(image).filename().string();
        if (!glob.empty() && fnmatch(glob.c_str(), name.c_str(), 0) != 0) continue;
        add_image(image);
        ++matched;
      }
      if (matched == 0) {
        *error = arg + " holds no image files" + (glob.empty() ? "" : " matching " + glob);
        return nullptr;
      }
      continue;
    }
    if (!fs::is_regular_file(path, ec)) {
      *error = arg + ": no such file or directory";
      return nullptr;
    }
    const std::string ext = LowerExtension(path);
    if (IsListExtension(ext)) {
      std::ifstream in(arg);
      if (!in) {
        *error = "cannot read " + arg;
        return nullptr;
      }
      const fs::path base = path.parent_path();
      std::string line;
      int line_number = 0;
      while (std::getline(in, line)) {
        ++line_number;
        line = Trim(line);
        if (line.empty() || line[0] == '#') continue;
        fs::path entry(line);
        if (entry.is_relative()) entry = (base / entry).lexically_normal();
        if (!fs::is_regular_file(entry, ec)) {
          *error =
              arg + ":" + std::to_string(line_number) + ": " + entry.string() + ": no such file";
          return nullptr;
        }
        add_image(entry.string());
      }
      continue;
    }
    if (IsImageFile(path)) {
      add_image(arg);
      continue;
    }
    std::string video_error;
    const std::unique_ptr<VideoReader> probe = VideoReader::Open(arg, &video_error);
    if (!probe) {
      *error = HasOpenCvImageIo() ? arg +
                                        " is neither a folder, an image list, an image nor a "
                                        "video OpenCV can open"
                                  : video_error;  // this build reads no videos: it says so
      return nullptr;
    }
    if (const std::optional<double> declared = probe->DeclaredFrames()) {
      total += size_t(std::ceil(*declared / source->video_every_));
    } else {
      exact = false;
    }
    source->items_.push_back({arg, true});
  }
  if (source->items_.empty()) {
    *error = "no frames: give a folder, a list, an image or a video";
    return nullptr;
  }
  if (exact || total > 0) source->total_ = total;
  return source;
}

bool FrameSource::Next(Frame* frame, std::string* error) {
  error->clear();
  while (next_item_ < items_.size() || video_) {
    if (video_) {
      // Skip to the next K-th frame without decoding the ones in between.
      while (video_frame_ % video_every_ != 0) {
        if (!video_->Skip()) break;
        ++video_frame_;
      }
      std::string jpeg, encode_error;
      if (video_frame_ % video_every_ != 0 || !video_->NextJpeg(&jpeg, &encode_error)) {
        video_.reset();
        continue;
      }
      const long number = video_frame_++;
      frame->index = next_index_++;
      frame->name = video_path_ + "#" + std::to_string(number);
      frame->path.clear();
      if (!encode_error.empty()) {
        *error = "cannot encode " + frame->name + " as JPEG";
        frame->bytes.clear();
        return true;
      }
      frame->bytes = std::move(jpeg);
      return true;
    }
    const Item& item = items_[next_item_++];
    if (item.video) {
      std::string open_error;
      video_ = VideoReader::Open(item.path, &open_error);
      video_path_ = item.path;
      video_frame_ = 0;
      if (!video_) {
        *error = open_error;
        frame->name = item.path;
        frame->path.clear();
        frame->bytes.clear();
        return true;
      }
      continue;
    }
    frame->index = next_index_++;
    frame->name = item.path;
    frame->path = item.path;
    if (!ReadImageBytes(item.path, &frame->bytes, error)) frame->bytes.clear();
    return true;
  }
  return false;
}

}  // namespace placedb::client
