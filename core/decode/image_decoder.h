// Strict image decoding: encoded bytes (JPEG, PNG) or raw pixels from an untrusted sender into a
// cv::Mat, or INVALID_ARGUMENT saying what is wrong with them.
//
// "Strict" means an image is either decoded exactly as its bytes say or refused: nothing is
// guessed or filled in. JPEG goes through libjpeg-turbo's TurboJPEG API with every libjpeg warning
// treated as an error (truncated data, corrupt entropy-coded data, data left over before a marker:
// the signs of a header that does not match its data); libjpeg's own message is quoted. PNG's
// chunk structure is walked first (every chunk complete and its CRC correct, an IHDR first, IDAT
// data, an IEND last, no byte after it), then libpng decodes it with its "benign" errors made
// errors (image data that holds more or less than the header's size: a header rewritten with a
// matching CRC), with cv::imdecode's conversions, so the pixels are OpenCV's. Any other format is
// refused. The size in the header is
// checked against the pixel limit before anything is allocated, so a small file that claims a
// huge image costs nothing. JPEG has no checksum: a few damaged scan bytes that libjpeg
// resynchronises over are not detected (docs/service.md has the rates).
//
// Policies (docs/service.md, "Images"):
// - Bytes after a JPEG's EOI marker are accepted (camera firmware appends trailers there); bytes
//   after a PNG's IEND chunk are refused (no PNG writer emits them: they mean two files
//   concatenated or a damaged transfer).
// - JPEG EXIF orientation is not applied: the pixels are returned as stored, so the frame, its
//   mask and its depth keep the sizes the sender wrote.
// - CMYK/YCCK JPEGs are refused (no camera sends them; libjpeg cannot convert them to BGR).
//
// Everything here is a pure function of its arguments (no files, no global state), safe to call
// from any number of threads, and meant to be fuzzed.
#pragma once

#include <cstddef>
#include <cstdint>
#include <opencv2/core.hpp>
#include <span>
#include <string>

#include "core/base/status.h"

namespace placedb {

enum class ImageFormat { kJpeg, kPng };
const char* ImageFormatName(ImageFormat format);  // "JPEG", "PNG"

// What a decoded image holds.
enum class ColorMode {
  kColor,      // 8-bit BGR (CV_8UC3), whatever the stored colour type
  kGray,       // 8-bit single channel (CV_8UC1)
  kUnchanged,  // as stored: 1, 3 (BGR) or 4 (BGRA) channels; 8 bits, or 16 bits (CV_16U) for
               // 16-bit PNGs
};

// Format and size read from the header alone (nothing decoded).
struct ImageInfo {
  ImageFormat format = ImageFormat::kJpeg;
  uint32_t width = 0;
  uint32_t height = 0;
};

struct DecodeOptions {
  ColorMode mode = ColorMode::kColor;
  // Refuse images of more than this many pixels (width * height), from the header, before any
  // allocation: RESOURCE_EXHAUSTED. 0 = no limit of ours (libjpeg's and libpng's own remain).
  uint64_t max_pixels = 0;
};

// The format and size from the header: INVALID_ARGUMENT for anything that is not the start of a
// well-formed JPEG or PNG ("PNG data is truncated (...)", "not a JPEG or PNG image").
Result<ImageInfo> ReadImageInfo(std::span<const uint8_t> bytes);

// Decodes `bytes` strictly (see above). Errors: INVALID_ARGUMENT naming the problem ("JPEG data
// is truncated (libjpeg: Premature end of JPEG file)"); RESOURCE_EXHAUSTED when the header's size
// exceeds options.max_pixels. Never throws.
Result<cv::Mat> DecodeImage(std::span<const uint8_t> bytes, const DecodeOptions& options);

// The exact byte count of a raw image of width x height pixels of `bytes_per_pixel` bytes each,
// computed without overflow: INVALID_ARGUMENT if the product does not fit in 64 bits. (Callers
// bound width and height first; this is the arithmetic those bounds must not be relied on for.)
Result<uint64_t> RawImageBytes(uint64_t width, uint64_t height, uint64_t bytes_per_pixel);

// *out = a * b; false (and *out untouched) if the product does not fit in 64 bits.
bool CheckedMul(uint64_t a, uint64_t b, uint64_t* out);

}  // namespace placedb
