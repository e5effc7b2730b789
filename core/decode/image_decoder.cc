#include "core/decode/image_decoder.h"

#include <turbojpeg.h>
#include <zlib.h>

#include <cstring>
#include <memory>
#include <opencv2/imgcodecs.hpp>
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

// What the chunk walk learns: the header and where the compressed image data is.
struct PngLayout {
  ImageInfo info;
  uint8_t bit_depth = 0;
  uint8_t color_type = 0;
  bool interlaced = false;
  std::vector<std::span<const uint8_t>> idat;  // every IDAT chunk's data, in order
};

// Walks every chunk: complete, CRC-correct, IHDR first, at least one IDAT, IEND last and nothing
// after it. libpng itself only warns about damaged ancillary chunks and ignores what follows
// IEND; here both are refusals.
Result<PngLayout> CheckPngStructure(std::span<const uint8_t> bytes) {
  const uint8_t* p = bytes.data();
  const size_t n = bytes.size();
  size_t pos = 8;
  PngLayout layout;
  ImageInfo& info = layout.info;
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
      layout.bit_depth = data[8];
      layout.color_type = data[9];
      layout.interlaced = data[12] != 0;
    } else if (std::memcmp(type, "IHDR", 4) == 0) {
      return Status::InvalidArgument("PNG data is corrupt (a second IHDR chunk at byte " +
                                     std::to_string(pos) + ")");
    }
    if (std::memcmp(type, "IDAT", 4) == 0) {
      seen_idat = true;
      layout.idat.emplace_back(data, length);
    }
    pos += size_t(length) + 12;
    if (std::memcmp(type, "IEND", 4) == 0) {
      if (!seen_idat) {
        return Status::InvalidArgument("PNG data is corrupt (no IDAT chunk: no image data)");
      }
      if (pos != n) {
        return Status::InvalidArgument("PNG data has " + std::to_string(n - pos) +
                                       " bytes after its IEND chunk (trailing data is refused)");
      }
      return layout;
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

// Bytes of one filtered row (filter byte included) of `width` pixels.
uint64_t PngRowBytes(uint64_t width, uint64_t bits_per_pixel) {
  return 1 + (width * bits_per_pixel + 7) / 8;
}

// The exact size of the decompressed image data the header promises (Adam7: seven sub-images).
Result<uint64_t> PngExpectedBytes(const PngLayout& layout) {
  int channels = 0;
  const uint8_t depth = layout.bit_depth;
  switch (layout.color_type) {
    case 0:  // gray
      channels = (depth == 1 || depth == 2 || depth == 4 || depth == 8 || depth == 16) ? 1 : 0;
      break;
    case 3:  // palette
      channels = (depth == 1 || depth == 2 || depth == 4 || depth == 8) ? 1 : 0;
      break;
    case 2:  // RGB
      channels = (depth == 8 || depth == 16) ? 3 : 0;
      break;
    case 4:  // gray + alpha
      channels = (depth == 8 || depth == 16) ? 2 : 0;
      break;
    case 6:  // RGBA
      channels = (depth == 8 || depth == 16) ? 4 : 0;
      break;
    default:
      break;
  }
  if (channels == 0) {
    return Status::InvalidArgument("PNG header is invalid (colour type " +
                                   std::to_string(layout.color_type) + " with bit depth " +
                                   std::to_string(depth) + ")");
  }
  const uint64_t bits = uint64_t(channels) * depth;
  const uint64_t w = layout.info.width, h = layout.info.height;  // < 2^31 each: no overflow below
  if (!layout.interlaced) return h * PngRowBytes(w, bits);
  static constexpr int kPasses[7][4] = {{0, 0, 8, 8}, {4, 0, 8, 8}, {0, 4, 4, 8}, {2, 0, 4, 4},
                                        {0, 2, 2, 4}, {1, 0, 2, 2}, {0, 1, 1, 2}};
  uint64_t total = 0;
  for (const auto& [x0, y0, dx, dy] : kPasses) {
    const uint64_t pw = w > uint64_t(x0) ? (w - uint64_t(x0) + uint64_t(dx) - 1) / uint64_t(dx) : 0;
    const uint64_t ph = h > uint64_t(y0) ? (h - uint64_t(y0) + uint64_t(dy) - 1) / uint64_t(dy) : 0;
    if (pw != 0 && ph != 0) total += ph * PngRowBytes(pw, bits);
  }
  return total;
}

// Inflates the IDAT stream without keeping it: it must be valid zlib data (its checksum too) and
// hold exactly the bytes the header promises. libpng only warns about surplus data, so a header
// rewritten (with its CRC) to fewer rows would otherwise decode.
Status CheckPngImageData(const PngLayout& layout) {
  auto expected = PngExpectedBytes(layout);
  if (!expected.ok()) return expected.status();
  z_stream z{};
  if (inflateInit(&z) != Z_OK) return Status::Internal("zlib: cannot initialise inflate");
  struct End {
    z_stream* z;
    ~End() { inflateEnd(z); }
  } end{&z};
  std::vector<unsigned char> scratch_buffer(size_t(1) << 18);
  unsigned char* scratch = scratch_buffer.data();
  uint64_t produced = 0;
  bool finished = false;
  for (size_t chunk = 0; chunk < layout.idat.size(); ++chunk) {
    z.next_in = const_cast<Bytef*>(layout.idat[chunk].data());
    z.avail_in = uInt(layout.idat[chunk].size());
    while (z.avail_in > 0 && !finished) {
      z.next_out = scratch;
      z.avail_out = uInt(scratch_buffer.size());
      const int result = inflate(&z, Z_NO_FLUSH);
      produced += scratch_buffer.size() - z.avail_out;
      if (produced > *expected) {
        return Status::InvalidArgument("PNG data holds more image data than its header's " +
                                       std::to_string(layout.info.width) + "x" +
                                       std::to_string(layout.info.height) + " image");
      }
      if (result == Z_STREAM_END) {
        finished = true;
      } else if (result != Z_OK) {
        return Status::InvalidArgument(std::string("PNG data is corrupt (zlib: ") +
                                       (z.msg ? z.msg : "inflate failed") + ")");
      }
    }
    if (finished && (z.avail_in > 0 || chunk + 1 < layout.idat.size())) {
      return Status::InvalidArgument("PNG data has data after the end of its compressed image");
    }
  }
  if (!finished) {
    return Status::InvalidArgument("PNG data is truncated (its compressed image data ends early)");
  }
  if (produced != *expected) {
    return Status::InvalidArgument("PNG data holds less image data than its header's " +
                                   std::to_string(layout.info.width) + "x" +
                                   std::to_string(layout.info.height) + " image needs");
  }
  return Status::Ok();
}

Result<cv::Mat> DecodePng(std::span<const uint8_t> bytes, const DecodeOptions& options) {
  auto layout = CheckPngStructure(bytes);
  if (!layout.ok()) return layout.status();
  const ImageInfo* info = &layout->info;
  PLACEDB_RETURN_IF_ERROR(SizeLimit(info->width, info->height, options.max_pixels, info->format));
  PLACEDB_RETURN_IF_ERROR(CheckPngImageData(*layout));
  int flags = cv::IMREAD_COLOR;
  if (options.mode == ColorMode::kGray) flags = cv::IMREAD_GRAYSCALE;
  if (options.mode == ColorMode::kUnchanged) flags = cv::IMREAD_UNCHANGED;
  cv::Mat image;
  try {
    if (bytes.size() > size_t(INT32_MAX)) {
      return Status::InvalidArgument("PNG data of " + std::to_string(bytes.size()) +
                                     " bytes is too large");
    }
    const cv::Mat buffer(1, int(bytes.size()), CV_8U, const_cast<uint8_t*>(bytes.data()));
    image = cv::imdecode(buffer, flags);
  } catch (const cv::Exception& e) {
    return Status::InvalidArgument(std::string("PNG data cannot be decoded (") + e.what() + ")");
  }
  if (image.empty()) {
    // The chunks are intact, so the compressed image data itself is wrong (libpng's reason goes
    // to stderr only).
    return Status::InvalidArgument(
        "PNG data is corrupt (its compressed image data does not decode)");
  }
  if (uint32_t(image.cols) != info->width || uint32_t(image.rows) != info->height) {
    return Status::InvalidArgument(
        "PNG data decoded to " + std::to_string(image.cols) + "x" + std::to_string(image.rows) +
        ", its header says " + std::to_string(info->width) + "x" + std::to_string(info->height));
  }
  return image;
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
