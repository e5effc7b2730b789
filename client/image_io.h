// The CLI's one way to read and write image files and to read videos (frame sources, recordings,
// `load --mode features`, the dynamics chart).
//
// JPEG and PNG (8-bit gray, BGR, BGRA; 16-bit PNG) are decoded by core/decode's strict decoder,
// the server's own (TurboJPEG, libpng), and PNG is written with libpng: every build reads and
// writes them, with no OpenCV image I/O. Other image formats (BMP, PGM/PPM, TIFF, WebP, ...)
// and videos go through OpenCV's imgcodecs and videoio only in builds configured with
// -DPLACEDB_CLI_OPENCV_IO=ON (the default); the container image is built with it OFF (those two
// OpenCV libraries pull in GDAL, FFmpeg, GStreamer and more: deploy/README.md), and there such a
// file is refused with a message naming it and what the build reads (NotReadableMessage).
#pragma once

#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <string_view>

namespace placedb::client {

// Whether this build reads other image formats and videos through OpenCV (PLACEDB_CLI_OPENCV_IO).
bool HasOpenCvImageIo();

// What a build reads, for messages: "JPEG and PNG images only" or "JPEG and PNG images, other
// image formats and videos through OpenCV".
std::string ReadableFormats(bool opencv_io);

// The refusal of `path` by a build without OpenCV image I/O; `what` says what the file is
// ("an image in a format other than JPEG or PNG", "a video"). Names the file, what the build
// reads and the build option that adds the rest.
std::string NotReadableMessage(const std::string& path, std::string_view what);

enum class ImageRead {
  kColor,      // 8-bit BGR
  kGray,       // 8-bit single channel
  kUnchanged,  // as stored: 1, 3 (BGR) or 4 (BGRA) channels, 8 or 16 bits (cv::IMREAD_UNCHANGED)
};

// Whether the bytes start like a JPEG or PNG file.
bool IsJpegOrPng(std::string_view bytes);

// Decodes JPEG or PNG bytes (core/decode: strict; the same pixels as cv::imdecode). False and
// *error (the decoder's message) otherwise.
bool DecodeImageBytes(std::string_view bytes, ImageRead mode, cv::Mat* image, std::string* error);

// Reads an image file: JPEG and PNG (by content, not name) through DecodeImageBytes; anything
// else through OpenCV when the build has it, else refused (NotReadableMessage). False + *error.
bool ReadImageFile(const std::string& path, ImageRead mode, cv::Mat* image, std::string* error);
// The same for the bytes of `path`, already read.
bool DecodeImageFileBytes(const std::string& path, std::string_view bytes, ImageRead mode,
                          cv::Mat* image, std::string* error);

// PNG bytes of an 8-bit 1-, 3- (BGR) or 4-channel (BGRA) image or a 16-bit single-channel one
// (libpng). False + *error for other types.
bool EncodePng(const cv::Mat& image, std::string* png, std::string* error);

// Writes `image` to `path`: PNG (by the extension, case-insensitive) in every build, other
// formats through OpenCV when the build has it. False + *error.
bool WriteImageFile(const std::string& path, const cv::Mat& image, std::string* error);

// A video's frames (OpenCV's videoio; only in builds with PLACEDB_CLI_OPENCV_IO). Open() fails
// with NotReadableMessage in builds without it.
class VideoReader {
 public:
  static std::unique_ptr<VideoReader> Open(const std::string& path, std::string* error);
  virtual ~VideoReader() = default;
  // The frame count the file declares, if any.
  virtual std::optional<double> DeclaredFrames() const = 0;
  // Skips one frame without decoding it; false at the end.
  virtual bool Skip() = 0;
  // The next frame as JPEG bytes (quality 90); false at the end or on a frame that cannot be
  // encoded (then *error is set).
  virtual bool NextJpeg(std::string* jpeg, std::string* error) = 0;
};

}  // namespace placedb::client
