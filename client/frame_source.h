// Frames for ingest and the load tester, from SOURCE arguments:
//   - a folder: its image files (.jpg .jpeg .png .bmp .pgm .ppm .pnm .tif .tiff .webp) in natural
//     order ("2.jpg" before "10.jpg"), not recursive; optionally only the names matching a glob;
//   - a text file list (.txt .lst .list): one path per line, relative to the list's folder, blank
//     lines and lines starting with '#' skipped;
//   - a video file (anything else OpenCV's VideoCapture opens): every K-th frame, JPEG-encoded;
//   - a single image file.
// JPEG and PNG files are sent as their bytes; other image formats are decoded and re-encoded as
// PNG (the API takes JPEG or PNG).
#pragma once

#include <cstddef>
#include <memory>
#include <optional>
#include <string>
#include <vector>

namespace cv {
class VideoCapture;
}

namespace placedb::client {

struct Frame {
  size_t index = 0;   // 0-based position in the whole input
  std::string name;   // "DIR/12.jpg", or "video.mp4#120" for video frames
  std::string bytes;  // JPEG or PNG
};

class FrameSource {
 public:
  // Expands the SOURCE arguments (checks that they exist and that videos open). `glob` (fnmatch,
  // e.g. "*.jpg"; empty = every image) filters folder entries by name. Null and *error on the
  // first bad argument.
  static std::unique_ptr<FrameSource> Open(const std::vector<std::string>& sources, int video_every,
                                           const std::string& glob, std::string* error);
  ~FrameSource();

  // Frames in total, when known: exact for images, estimated from the frame count videos declare.
  std::optional<size_t> total() const { return total_; }

  // The next frame; false at the end. A frame that cannot be read is reported by *error (and
  // `frame->name` says which); call again to go on with the next one.
  bool Next(Frame* frame, std::string* error);

 private:
  struct Item {
    std::string path;
    bool video = false;
  };
  FrameSource() = default;

  std::vector<Item> items_;
  size_t next_item_ = 0;
  int video_every_ = 1;
  std::unique_ptr<cv::VideoCapture> video_;  // the video item being read
  std::string video_path_;
  long video_frame_ = 0;
  size_t next_index_ = 0;
  std::optional<size_t> total_;
};

// Reads an image file as JPEG or PNG bytes (converting other formats). False + *error otherwise.
bool ReadImageBytes(const std::string& path, std::string* bytes, std::string* error);

// Whether the bytes start like a JPEG or PNG file.
bool IsJpegOrPng(const std::string& bytes);

}  // namespace placedb::client
