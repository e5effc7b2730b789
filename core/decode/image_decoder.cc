#include "core/decode/image_decoder.h"

#include <png.h>
#include <turbojpeg.h>
#include <zlib.h>

#include <cstring>
#include <memory>
#include <vector>

namespace placedb {

namespace {

uint32_t ReadBe32(const uint8_t* p) {
  return (uint32_t(p[0]) << 24) | (uint32_t(p[1]) << 16) | (uint32_t(p[2]) << 8) | uint32_t(p[3]);
}

constexpr uint8_t kPngSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1A, '\n'};
// The PNG specification's bound on widths, heights and chunk lengths.
constexpr uint32_t kPngMaxValue = 0x7FFFFFFFu;

bool IsPng(std::span<const uint8_t> bytes) {
  return bytes.size() >= 8 && std::memcmp(bytes.data(), kPngSignature, 8) == 0;
}
bool IsJpeg(std::span<const uint8_t> bytes) {
  return bytes.size() >= 3 && bytes[0] == 0xFF && bytes[1] == 0xD8 && bytes[2] == 0xFF;
}

std::string ChunkName(const uint8_t* type) {
  std::string name;
  for (int i = 0; i < 4; ++i) {
    const char c = char(type[i]);
    name += ((c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z')) ? c : '?';
  }
  return name;
}

Status SizeLimit(uint64_t width, uint64_t height, uint64_t max_pixels, ImageFormat format) {
  // Both sides are below 2^32 here, so the product fits.
  if (max_pixels != 0 && width * height > max_pixels) {
    return Status::ResourceExhausted(std::string(ImageFormatName(format)) + " header claims a " +
                                     std::to_string(width) + "x" + std::to_string(height) +
                                     " image = " + std::to_string(width * height) +
                                     " pixels, over the limit of " + std::to_string(max_pixels));
  }
  return Status::Ok();
}

// ---- PNG ----------------------------------------------------------------------------------------

// Walks every chunk: complete, CRC-correct, IHDR first, at least one IDAT, IEND last and nothing
// after it. libpng itself only warns about damaged ancillary chunks and ignores what follows
// IEND; here both are refusals.
Result<ImageInfo> CheckPngStructure(std::span<const uint8_t> bytes) {
  const uint8_t* p = bytes.data();
  const size_t n = bytes.size();
  size_t pos = 8;
  ImageInfo info;
  info.format = ImageFormat::kPng;
  bool seen_idat = false;
  for (int index = 0;; ++index) {
    if (n - pos < 8) {
      return Status::InvalidArgument(index == 0
                                         ? "PNG data is truncated (it ends before its IHDR chunk)"
                                         : "PNG data is truncated (it ends at byte " +
                                               std::to_string(n) + " without an IEND chunk)");
    }
    const uint32_t length = ReadBe32(p + pos);
    const uint8_t* type = p + pos + 4;
    const std::string name = ChunkName(type);
    if (length > kPngMaxValue) {
      return Status::InvalidArgument("PNG data is corrupt (the chunk at byte " +
                                     std::to_string(pos) + " claims " + std::to_string(length) +
                                     " bytes)");
    }
    // length <= 2^31 - 1 and pos <= n: no overflow in these sums.
    if (uint64_t(n - pos) < uint64_t(length) + 12) {
      return Status::InvalidArgument("PNG data is truncated (the " + name + " chunk at byte " +
                                     std::to_string(pos) + " needs " +
                                     std::to_string(uint64_t(length) + 12) + " bytes, " +
                                     std::to_string(n - pos) + " remain)");
    }
    const uint8_t* data = type + 4;
    const uint32_t stored_crc = ReadBe32(data + length);
    uLong crc = crc32(0L, Z_NULL, 0);
    crc = crc32(crc, type, 4);
    crc = crc32(crc, data, uInt(length));  // length < 2^31 fits in uInt
    if (uint32_t(crc) != stored_crc) {
      return Status::InvalidArgument("PNG data is corrupt (the " + name + " chunk at byte " +
                                     std::to_string(pos) + " fails its CRC check)");
    }
    if (index == 0) {
      if (std::memcmp(type, "IHDR", 4) != 0 || length != 13) {
        return Status::InvalidArgument(
            "PNG data is corrupt (it does not start with an IHDR chunk)");
      }
      const uint32_t width = ReadBe32(data);
      const uint32_t height = ReadBe32(data + 4);
      if (width == 0 || height == 0 || width > kPngMaxValue || height > kPngMaxValue) {
        return Status::InvalidArgument("PNG header claims a " + std::to_string(width) + "x" +
                                       std::to_string(height) + " image");
      }
      info.width = width;
      info.height = height;
    } else if (std::memcmp(type, "IHDR", 4) == 0) {
      return Status::InvalidArgument("PNG data is corrupt (a second IHDR chunk at byte " +
                                     std::to_string(pos) + ")");
    }
    if (std::memcmp(type, "IDAT", 4) == 0) seen_idat = true;
    pos += size_t(length) + 12;
    if (std::memcmp(type, "IEND", 4) == 0) {
      if (!seen_idat) {
        return Status::InvalidArgument("PNG data is corrupt (no IDAT chunk: no image data)");
      }
      if (pos != n) {
        return Status::InvalidArgument("PNG data has " + std::to_string(n - pos) +
                                       " bytes after its IEND chunk (trailing data is refused)");
      }
      return info;
    }
  }
}

// The header alone, for ReadImageInfo: the IHDR chunk, CRC-checked.
Result<ImageInfo> ReadPngInfo(std::span<const uint8_t> bytes) {
  if (bytes.size() < 33) {
    return Status::InvalidArgument("PNG data is truncated (it ends before its IHDR chunk ends)");
  }
  // The first chunk through the structure check, stopping after it: IEND-less data is fine here.
  const uint8_t* p = bytes.data();
  if (ReadBe32(p + 8) != 13 || std::memcmp(p + 12, "IHDR", 4) != 0) {
    return Status::InvalidArgument("PNG data is corrupt (it does not start with an IHDR chunk)");
  }
  uLong crc = crc32(0L, Z_NULL, 0);
  crc = crc32(crc, p + 12, 17);
  if (uint32_t(crc) != ReadBe32(p + 29)) {
    return Status::InvalidArgument("PNG data is corrupt (the IHDR chunk fails its CRC check)");
  }
  const uint32_t width = ReadBe32(p + 16);
  const uint32_t height = ReadBe32(p + 20);
  if (width == 0 || height == 0 || width > kPngMaxValue || height > kPngMaxValue) {
    return Status::InvalidArgument("PNG header claims a " + std::to_string(width) + "x" +
                                   std::to_string(height) + " image");
  }
  return ImageInfo{ImageFormat::kPng, width, height};
}

// libpng reads the bytes (already checked by the chunk walk) from memory; its errors, and its
// "benign" errors (too much or too little image data, bad CRC, ...), which png_set_benign_errors
// makes errors, end the decode with the first message.
struct PngSource {
  std::span<const uint8_t> bytes;
  size_t pos = 0;
  std::string error;
};

void PngErrorFn(png_structp png, png_const_charp message) {
  auto* source = static_cast<PngSource*>(png_get_error_ptr(png));
  if (source->error.empty()) source->error = message ? message : "unknown error";
  png_longjmp(png, 1);
}

// Plain warnings concern the ancillary data libpng is told to skip; nothing about the pixels.
void PngWarningFn(png_structp, png_const_charp) {}

void PngReadFn(png_structp png, png_bytep out, size_t length) {
  auto* source = static_cast<PngSource*>(png_get_io_ptr(png));
  if (source->bytes.size() - source->pos < length)
    png_error(png, "read beyond the end of the data");
  std::memcpy(out, source->bytes.data() + source->pos, length);
  source->pos += length;
}

// One decode's state: everything a longjmp out of libpng must leave intact lives here, in the
// caller's frame, so the frame with setjmp holds nothing that needs destroying.
struct PngJob {
  PngSource source;
  png_structp png = nullptr;
  png_infop info = nullptr;
  png_infop end = nullptr;
  cv::Mat image;
  std::vector<png_bytep> rows;
  ~PngJob() {
    if (png) png_destroy_read_struct(&png, &info, &end);
  }
};

// The decode itself, with cv::imdecode's choice of output and libpng transforms for each mode,
// so the pixels are the same as OpenCV's (also libpng). False with job->source.error on failure.
bool RunPng(PngJob* job, ColorMode mode) {
  png_structp png = job->png;
  if (setjmp(png_jmpbuf(png))) return false;
  png_set_read_fn(png, &job->source, PngReadFn);
  png_set_benign_errors(png, 0);
  // Ancillary chunks that cannot change the pixels OpenCV returns are skipped, and with them
  // their own failure modes. (gAMA, sRGB, cHRM and iCCP stay: libpng's RGB-to-gray conversion,
  // OpenCV's for gray frames, works in linear light when it knows the gamma.)
  static const png_byte kSkipped[] =
      "bKGD\0eXIf\0hIST\0iTXt\0oFFs\0pCAL\0pHYs\0sBIT\0sCAL\0sPLT\0"
      "sTER\0tEXt\0tIME\0zTXt";
  png_set_keep_unknown_chunks(png, PNG_HANDLE_CHUNK_NEVER, kSkipped, int(sizeof(kSkipped) / 5));
  png_read_info(png, job->info);
  png_uint_32 width = 0, height = 0;
  int bit_depth = 0, color_type = 0;
  png_get_IHDR(png, job->info, &width, &height, &bit_depth, &color_type, nullptr, nullptr, nullptr);
  const bool has_color = (color_type & PNG_COLOR_MASK_COLOR) != 0;

  int channels = 1, depth = CV_8U;
  if (mode == ColorMode::kColor) {
    channels = 3;
  } else if (mode == ColorMode::kUnchanged) {
    if (color_type == PNG_COLOR_TYPE_RGB || color_type == PNG_COLOR_TYPE_PALETTE) {
      channels = png_get_valid(png, job->info, PNG_INFO_tRNS) ? 4 : 3;
    } else if (color_type == PNG_COLOR_TYPE_GRAY_ALPHA || color_type == PNG_COLOR_TYPE_RGB_ALPHA) {
      channels = 4;
    }
    if (bit_depth == 16) depth = CV_16U;
  }
  if (depth == CV_8U && bit_depth == 16) {
    png_set_strip_16(png);
  } else if (bit_depth == 16) {
    png_set_swap(png);  // PNG is big-endian; cv::Mat holds native (little-endian) values
  }
  if (channels < 4) {
    png_set_strip_alpha(png);
  } else {
    png_set_tRNS_to_alpha(png);
  }
  if (color_type == PNG_COLOR_TYPE_PALETTE) png_set_palette_to_rgb(png);
  if (!has_color && bit_depth < 8) png_set_expand_gray_1_2_4_to_8(png);
  if (channels > 1 && has_color) {
    png_set_bgr(png);
  } else if (channels > 1) {
    png_set_gray_to_rgb(png);
  } else {
    png_set_rgb_to_gray(png, 1, 0.299, 0.587);  // OpenCV's weights
  }
  png_set_interlace_handling(png);
  png_read_update_info(png, job->info);

  job->image.create(int(height), int(width), CV_MAKETYPE(depth, channels));
  // The transforms must produce exactly the rows allocated: never write past them.
  if (png_get_rowbytes(png, job->info) != job->image.step[0] ||
      png_get_channels(png, job->info) != channels) {
    job->source.error = "unexpected row layout after conversion";
    return false;
  }
  job->rows.resize(height);
  for (png_uint_32 y = 0; y < height; ++y) job->rows[y] = job->image.ptr<png_byte>(int(y));
  png_read_image(png, job->rows.data());
  png_read_end(png, job->end);
  return true;
}

Result<cv::Mat> DecodePng(std::span<const uint8_t> bytes, const DecodeOptions& options) {
  auto layout = CheckPngStructure(bytes);
  if (!layout.ok()) return layout.status();
  const ImageInfo& info = *layout;
  PLACEDB_RETURN_IF_ERROR(SizeLimit(info.width, info.height, options.max_pixels, info.format));
  PngJob job;
  job.source.bytes = bytes;
  job.png = png_create_read_struct(PNG_LIBPNG_VER_STRING, &job.source, PngErrorFn, PngWarningFn);
  if (job.png) job.info = png_create_info_struct(job.png);
  if (job.png) job.end = png_create_info_struct(job.png);
  if (!job.png || !job.info || !job.end) return Status::Internal("libpng: cannot create a reader");
  if (!RunPng(&job, options.mode)) {
    return Status::InvalidArgument("PNG data is corrupt (libpng: " + job.source.error + ")");
  }
  return std::move(job.image);
}

// ---- JPEG ---------------------------------------------------------------------------------------

struct TjDeleter {
  void operator()(void* handle) const { tjDestroy(handle); }
};
using TjHandle = std::unique_ptr<void, TjDeleter>;

// "JPEG data is truncated (libjpeg: Premature end of JPEG file)" or "... is corrupt (...)".
Status JpegError(tjhandle handle) {
  std::string reason = tjGetErrorStr2(handle);
  // TurboJPEG prefixes its own function name to some messages; the library's words are the point.
  for (const char* prefix : {"tjDecompressHeader3(): ", "tjDecompress2(): "}) {
    if (reason.rfind(prefix, 0) == 0) reason.erase(0, std::strlen(prefix));
  }
  const bool truncated = reason.find("Premature end") != std::string::npos;
  return Status::InvalidArgument(std::string("JPEG data is ") +
                                 (truncated ? "truncated" : "corrupt") + " (libjpeg: " + reason +
                                 ")");
}

Result<ImageInfo> ReadJpegInfo(tjhandle handle, std::span<const uint8_t> bytes, int* colorspace) {
  int width = 0, height = 0, subsampling = 0;
  if (tjDecompressHeader3(handle, bytes.data(), static_cast<unsigned long>(bytes.size()), &width,
                          &height, &subsampling, colorspace) != 0) {
    return JpegError(handle);
  }
  if (width <= 0 || height <= 0) {
    return Status::InvalidArgument("JPEG header claims a " + std::to_string(width) + "x" +
                                   std::to_string(height) + " image");
  }
  return ImageInfo{ImageFormat::kJpeg, uint32_t(width), uint32_t(height)};
}

Result<cv::Mat> DecodeJpeg(std::span<const uint8_t> bytes, const DecodeOptions& options) {
  TjHandle handle(tjInitDecompress());
  if (!handle) return Status::Internal("TurboJPEG: cannot create a decompressor");
  int colorspace = 0;
  auto info = ReadJpegInfo(handle.get(), bytes, &colorspace);
  if (!info.ok()) return info.status();
  PLACEDB_RETURN_IF_ERROR(SizeLimit(info->width, info->height, options.max_pixels, info->format));
  if (colorspace == TJCS_CMYK || colorspace == TJCS_YCCK) {
    return Status::InvalidArgument("JPEG data is CMYK, which is not supported (send RGB or gray)");
  }
  const bool gray = options.mode == ColorMode::kGray ||
                    (options.mode == ColorMode::kUnchanged && colorspace == TJCS_GRAY);
  cv::Mat image(int(info->height), int(info->width), gray ? CV_8UC1 : CV_8UC3);
  // Warnings stop the decode (a damaged file is refused, not patched with grey); progressive
  // files are limited to 500 scans (a crafted file cannot make a decode quadratic); the accurate
  // integer IDCT is libjpeg's default and OpenCV's choice too.
  const int flags = TJFLAG_STOPONWARNING | TJFLAG_LIMITSCANS | TJFLAG_ACCURATEDCT;
  if (tjDecompress2(handle.get(), bytes.data(), static_cast<unsigned long>(bytes.size()),
                    image.data, image.cols, int(image.step[0]), image.rows,
                    gray ? TJPF_GRAY : TJPF_BGR, flags) != 0) {
    return JpegError(handle.get());
  }
  return image;
}

}  // namespace

const char* ImageFormatName(ImageFormat format) {
  return format == ImageFormat::kPng ? "PNG" : "JPEG";
}

bool CheckedMul(uint64_t a, uint64_t b, uint64_t* out) {
  uint64_t product = 0;
  if (__builtin_mul_overflow(a, b, &product)) return false;
  *out = product;
  return true;
}

Result<uint64_t> RawImageBytes(uint64_t width, uint64_t height, uint64_t bytes_per_pixel) {
  uint64_t pixels = 0, bytes = 0;
  if (!CheckedMul(width, height, &pixels) || !CheckedMul(pixels, bytes_per_pixel, &bytes)) {
    return Status::InvalidArgument(std::to_string(width) + "x" + std::to_string(height) + " x " +
                                   std::to_string(bytes_per_pixel) +
                                   " bytes per pixel does not fit in 64 bits");
  }
  return bytes;
}

Result<ImageInfo> ReadImageInfo(std::span<const uint8_t> bytes) {
  if (IsPng(bytes)) return ReadPngInfo(bytes);
  if (IsJpeg(bytes)) {
    TjHandle handle(tjInitDecompress());
    if (!handle) return Status::Internal("TurboJPEG: cannot create a decompressor");
    int colorspace = 0;
    return ReadJpegInfo(handle.get(), bytes, &colorspace);
  }
  return Status::InvalidArgument(bytes.empty() ? "no image data (0 bytes)"
                                               : "not a JPEG or PNG image");
}

Result<cv::Mat> DecodeImage(std::span<const uint8_t> bytes, const DecodeOptions& options) {
  if (IsPng(bytes)) return DecodePng(bytes, options);
  if (IsJpeg(bytes)) return DecodeJpeg(bytes, options);
  return Status::InvalidArgument(bytes.empty() ? "no image data (0 bytes)"
                                               : "not a JPEG or PNG image");
}

}  // namespace placedb
