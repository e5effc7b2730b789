// Frames for ingest and the load tester, from SOURCE arguments:
//   - a folder: its image files (.jpg .jpeg .png .bmp .pgm .ppm .pnm .tif .tiff .webp) in natural
//     order ("2.jpg" before "10.jpg"), not recursive; optionally only the names matching a glob;
//   - a text file list (.txt .lst .list): one path per line, relative to the list's folder, blank
//     lines and lines starting with '#' skipped;
//   - a video file (anything else OpenCV's VideoCapture opens): every K-th frame, JPEG-encoded;
//   - a single image file.
// JPEG and PNG files are sent as their bytes; other image formats are decoded and re-encoded as
// PNG (the API takes JPEG or PNG). Videos and formats other than JPEG and PNG need a build with
// OpenCV's image I/O (PLACEDB_CLI_OPENCV_IO, client/image_io.h); without it they are refused
// with a message saying so.
//
// Depth images (ingest --depth DIR, query --depth FILE) are paired with colour frames by file
// stem: for "DIR_C/12.jpg" the depth is "DIR/12.png" (else .pgm, .tif, .tiff). A 16-bit
// single-channel PNG is sent as it is (DepthImage.png16); other 16-bit images (PGM, TIFF) are
// re-encoded as 16-bit PNG, float32 TIFFs sent as raw float32.
#pragma once

#include <cstddef>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "client/image_io.h"
#include "proto/placedb.pb.h"

namespace placedb::client {

namespace v1 = ::placedb::v1;

struct Frame {
  size_t index = 0;   // 0-based position in the whole input
  std::string name;   // "DIR/12.jpg", or "video.mp4#120" for video frames
  std::string bytes;  // JPEG or PNG
  std::string path;   // the image file; "" for video frames
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

  // The image files, in input order (video items left out), and the videos.
  std::vector<std::string> image_paths() const;
  std::vector<std::string> video_paths() const;

 private:
  struct Item {
    std::string path;
    bool video = false;
  };
  FrameSource() = default;

  std::vector<Item> items_;
  size_t next_item_ = 0;
  int video_every_ = 1;
  std::unique_ptr<VideoReader> video_;  // the video item being read
  std::string video_path_;
  long video_frame_ = 0;
  size_t next_index_ = 0;
  std::optional<size_t> total_;
};

// Reads an image file as JPEG or PNG bytes (converting other formats). False + *error otherwise.
bool ReadImageBytes(const std::string& path, std::string* bytes, std::string* error);

// The depth image of a colour frame: DEPTH_DIR/<stem of colour_path> + .png, .pgm, .tif or .tiff
// (the first that exists). "" + *error ("no depth image for frame ...: looked for ...") when none.
std::string FindDepthImage(const std::string& depth_dir, const std::string& colour_path,
                           std::string* error);

// Reads a depth image into `depth` (png16 or raw_float32; scale and intrinsics untouched).
// Accepted: 16-bit single-channel PNG (sent as it is), 16-bit PGM / TIFF / ... (re-encoded as
// 16-bit PNG), single-channel float32 (TIFF; raw float32). False + *error otherwise.
bool ReadDepthImage(const std::string& path, v1::DepthImage* depth, std::string* error);

// "fx,fy,cx,cy" in pixels: fx, fy > 0, cx, cy >= 0. False + *error otherwise.
bool ParseIntrinsics(const std::string& text, v1::Intrinsics* intrinsics, std::string* error);
// --camera "fx,fy,cx,cy": a pinhole camera of the frames' size (relative poses, issue 32).
bool ParseCamera(const std::string& text, v1::Camera* camera, std::string* error);

}  // namespace placedb::client
