#include "client/image_io.h"

#include <png.h>

#include <bit>
#include <csetjmp>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <span>
#include <vector>

#include "core/base/files.h"
#include "core/base/text.h"
#include "core/decode/image_decoder.h"

#if PLACEDB_CLI_OPENCV_IO
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>
#endif

namespace placedb::client {

namespace {

ColorMode ToColorMode(ImageRead mode) {
  switch (mode) {
    case ImageRead::kGray:
      return ColorMode::kGray;
    case ImageRead::kUnchanged:
      return ColorMode::kUnchanged;
    case ImageRead::kColor:
      break;
  }
  return ColorMode::kColor;
}

#if PLACEDB_CLI_OPENCV_IO
int ToImreadFlags(ImageRead mode) {
  switch (mode) {
    case ImageRead::kGray:
      return cv::IMREAD_GRAYSCALE;
    case ImageRead::kUnchanged:
      return cv::IMREAD_UNCHANGED;
    case ImageRead::kColor:
      break;
  }
  return cv::IMREAD_COLOR;
}
#endif

// Bytes of a file that is not JPEG or PNG: OpenCV's decoders, or refused.
bool DecodeOtherFormat(const std::string& path, std::string_view bytes, ImageRead mode,
                       cv::Mat* image, std::string* error) {
#if PLACEDB_CLI_OPENCV_IO
  cv::Mat decoded;
  try {
    decoded = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())),
                           ToImreadFlags(mode));
  } catch (const cv::Exception&) {
    decoded.release();
  }
  if (decoded.empty()) {
    *error = path + " is not an image OpenCV can decode";
    return false;
  }
  *image = decoded;
  return true;
#else
  (void)bytes;
  (void)mode;
  (void)image;
  *error = NotReadableMessage(path, "an image in a format other than JPEG or PNG");
  return false;
#endif
}

// libpng writing into a string. Errors longjmp back to RunPngWrite's setjmp: everything that
// must survive it lives in PngWriteJob, in the caller's frame.
struct PngSink {
  std::string* out = nullptr;
  std::string error;
};

void PngWriteFn(png_structp png, png_bytep data, size_t length) {
  auto* sink = static_cast<PngSink*>(png_get_io_ptr(png));
  sink->out->append(reinterpret_cast<const char*>(data), length);
}

void PngFlushFn(png_structp) {}

void PngWriteErrorFn(png_structp png, png_const_charp message) {
  auto* sink = static_cast<PngSink*>(png_get_error_ptr(png));
  if (sink->error.empty()) sink->error = message ? message : "unknown error";
  png_longjmp(png, 1);
}

void PngWriteWarningFn(png_structp, png_const_charp) {}

struct PngWriteJob {
  PngSink sink;
  png_structp png = nullptr;
  png_infop info = nullptr;
  std::vector<png_bytep> rows;
  ~PngWriteJob() {
    if (png) png_destroy_write_struct(&png, &info);
  }
};

bool RunPngWrite(PngWriteJob* job, const cv::Mat& image, int color_type, int bit_depth) {
  png_structp png = job->png;
  if (setjmp(png_jmpbuf(png))) return false;
  png_set_write_fn(png, &job->sink, PngWriteFn, PngFlushFn);
  png_set_compression_level(png, 1);  // what cv::imencode uses: fast, frames are sent once
  png_set_IHDR(png, job->info, png_uint_32(image.cols), png_uint_32(image.rows), bit_depth,
               color_type, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, job->info);
  if (image.channels() >= 3) png_set_bgr(png);  // OpenCV's order is BGR(A)
  if constexpr (std::endian::native == std::endian::little) {
    if (bit_depth == 16) png_set_swap(png);  // PNG stores 16-bit samples big-endian
  }
  png_write_image(png, job->rows.data());
  png_write_end(png, nullptr);
  return true;
}

bool HasExtension(const std::string& path, const char* extension) {
  return AsciiLower(std::filesystem::path(path).extension().string()) == extension;
}

#if PLACEDB_CLI_OPENCV_IO
class OpenCvVideoReader : public VideoReader {
 public:
  explicit OpenCvVideoReader(const std::string& path) : capture_(path) {}
  bool opened() const { return capture_.isOpened(); }

  std::optional<double> DeclaredFrames() const override {
    const double declared = capture_.get(cv::CAP_PROP_FRAME_COUNT);
    if (declared > 0) return declared;
    return std::nullopt;
  }
  bool Skip() override { return capture_.grab(); }
  bool NextJpeg(std::string* jpeg, std::string* error) override {
    cv::Mat image;
    if (!capture_.read(image) || image.empty()) return false;
    std::vector<uint8_t> encoded;
    if (!cv::imencode(".jpg", image, encoded, {cv::IMWRITE_JPEG_QUALITY, 90})) {
      *error = "cannot encode the frame as JPEG";
      jpeg->clear();
      return true;
    }
    jpeg->assign(encoded.begin(), encoded.end());
    return true;
  }

 private:
  mutable cv::VideoCapture capture_;  // get() is not const in OpenCV
};
#endif

}  // namespace

bool HasOpenCvImageIo() {
  return PLACEDB_CLI_OPENCV_IO != 0;
}

std::string ReadableFormats(bool opencv_io) {
  return opencv_io ? "JPEG and PNG images, other image formats and videos through OpenCV"
                   : "JPEG and PNG images only";
}

std::string NotReadableMessage(const std::string& path, std::string_view what) {
  return path + " is " + std::string(what) + ": this placedb build reads " +
         ReadableFormats(false) +
         " (it was built with -DPLACEDB_CLI_OPENCV_IO=OFF, as the container image is, without "
         "OpenCV's image and video I/O); convert it to JPEG or PNG, or use a build with "
         "PLACEDB_CLI_OPENCV_IO=ON";
}

bool IsJpegOrPng(std::string_view bytes) {
  return (bytes.size() >= 3 && uint8_t(bytes[0]) == 0xFF && uint8_t(bytes[1]) == 0xD8 &&
          uint8_t(bytes[2]) == 0xFF) ||
         (bytes.size() >= 8 && bytes.substr(0, 8) == std::string_view("\x89PNG\r\n\x1a\n", 8));
}

bool DecodeImageBytes(std::string_view bytes, ImageRead mode, cv::Mat* image, std::string* error) {
  DecodeOptions options;
  options.mode = ToColorMode(mode);
  auto decoded = DecodeImage(
      std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()),
      options);
  if (!decoded.ok()) {
    *error = decoded.status().message();
    return false;
  }
  *image = std::move(*decoded);
  return true;
}

bool DecodeImageFileBytes(const std::string& path, std::string_view bytes, ImageRead mode,
                          cv::Mat* image, std::string* error) {
  if (!IsJpegOrPng(bytes)) return DecodeOtherFormat(path, bytes, mode, image, error);
  if (DecodeImageBytes(bytes, mode, image, error)) return true;
  *error = path + ": " + *error;
  return false;
}

bool ReadImageFile(const std::string& path, ImageRead mode, cv::Mat* image, std::string* error) {
  auto contents = ReadWholeFile(path);
  if (!contents.ok()) {
    *error = contents.status().message();
    return false;
  }
  return DecodeImageFileBytes(path, *contents, mode, image, error);
}

bool EncodePng(const cv::Mat& image, std::string* png, std::string* error) {
  int color_type = -1;
  switch (image.channels()) {
    case 1:
      color_type = PNG_COLOR_TYPE_GRAY;
      break;
    case 3:
      color_type = PNG_COLOR_TYPE_RGB;
      break;
    case 4:
      color_type = PNG_COLOR_TYPE_RGB_ALPHA;
      break;
  }
  const bool eight = image.depth() == CV_8U;
  const bool sixteen_gray = image.depth() == CV_16U && image.channels() == 1;
  if (image.empty() || color_type < 0 || (!eight && !sixteen_gray)) {
    *error =
        "PNG is written from 8-bit gray, BGR or BGRA images or 16-bit gray ones (this one "
        "has " +
        std::to_string(image.channels()) + " channel(s) of OpenCV depth " +
        std::to_string(image.depth()) + ", " + std::to_string(image.cols) + "x" +
        std::to_string(image.rows) + ")";
    return false;
  }
  png->clear();
  PngWriteJob job;
  job.sink.out = png;
  job.png =
      png_create_write_struct(PNG_LIBPNG_VER_STRING, &job.sink, PngWriteErrorFn, PngWriteWarningFn);
  if (job.png) job.info = png_create_info_struct(job.png);
  if (!job.png || !job.info) {
    *error = "libpng: out of memory";
    return false;
  }
  job.rows.resize(size_t(image.rows));
  for (int y = 0; y < image.rows; ++y) job.rows[size_t(y)] = const_cast<png_bytep>(image.ptr(y));
  if (!RunPngWrite(&job, image, color_type, eight ? 8 : 16)) {
    *error = "libpng: " + job.sink.error;
    png->clear();
    return false;
  }
  return true;
}

bool WriteImageFile(const std::string& path, const cv::Mat& image, std::string* error) {
  if (HasExtension(path, ".png")) {
    std::string png;
    if (!EncodePng(image, &png, error)) return false;
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out.write(png.data(), std::streamsize(png.size()));
    out.close();
    if (!out) {
      *error = "cannot write " + path;
      return false;
    }
    return true;
  }
#if PLACEDB_CLI_OPENCV_IO
  bool written = false;
  try {
    written = cv::imwrite(path, image);
  } catch (const cv::Exception&) {  // e.g. an extension OpenCV has no encoder for
    written = false;
  }
  if (!written) *error = "cannot write " + path;
  return written;
#else
  *error = "cannot write " + path + ": this placedb build writes PNG images only (built with " +
           "-DPLACEDB_CLI_OPENCV_IO=OFF, as the container image is); name it .png";
  return false;
#endif
}

std::unique_ptr<VideoReader> VideoReader::Open(const std::string& path, std::string* error) {
#if PLACEDB_CLI_OPENCV_IO
  auto reader = std::make_unique<OpenCvVideoReader>(path);
  if (!reader->opened()) {
    *error = "cannot open video " + path;
    return nullptr;
  }
  return reader;
#else
  *error = NotReadableMessage(path, "a video (not a folder, an image list or an image file)");
  return nullptr;
#endif
}

}  // namespace placedb::client
