// core/decode/image_decoder.h on real images (../shared/data) and on damaged copies of them made
// here: cut short, random bytes over the scan data, a frame header that claims another size, a
// damaged CRC, trailing data. Good images decode to the pixels cv::imdecode gives.
#include <gtest/gtest.h>
#include <turbojpeg.h>
#include <zlib.h>

#include <cstdint>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <span>
#include <string>

#include "core/decode/image_decoder.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

std::span<const uint8_t> Span(const std::string& bytes) {
  return {reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()};
}

std::string CamVidJpeg() {
  return testing::ReadFileBytes(testing::SharedDir() + "/data/camvid/images/0001TP_006690.jpg");
}
std::string RgbdColorPng() {
  return testing::ReadFileBytes(testing::SharedDir() +
                                "/data/rgbd-people/image/test1/1534837737.203029.png");
}
std::string RgbdDepthPng() {
  return testing::ReadFileBytes(testing::SharedDir() +
                                "/data/rgbd-people/depth/test1/1534837737.203029.png");
}

// Offset of the first byte after the first marker `code` (0xFF code) in a JPEG, or npos.
size_t AfterMarker(const std::string& jpeg, uint8_t code) {
  for (size_t i = 2; i + 1 < jpeg.size(); ++i) {
    if (uint8_t(jpeg[i]) == 0xFF && uint8_t(jpeg[i + 1]) == code) return i + 2;
  }
  return std::string::npos;
}

void PutBe16(std::string* bytes, size_t at, uint32_t value) {
  (*bytes)[at] = char((value >> 8) & 0xFF);
  (*bytes)[at + 1] = char(value & 0xFF);
}

// Random bytes over the middle half of the entropy-coded data after the SOS segment.
std::string RandomScan(const std::string& jpeg, uint32_t seed) {
  std::string out = jpeg;
  const size_t sos = AfterMarker(jpeg, 0xDA);
  const size_t scan = sos + ((size_t(uint8_t(jpeg[sos])) << 8) | uint8_t(jpeg[sos + 1]));
  const size_t scan_bytes = jpeg.size() - 2 - scan;  // up to the EOI marker
  std::mt19937 rng(seed);
  for (size_t i = scan + scan_bytes / 4; i < scan + 3 * scan_bytes / 4; ++i) {
    out[i] = char(rng() & 0xFF);
  }
  return out;
}

// The baseline frame header (SOF0) with its height and width replaced.
std::string WithJpegSize(const std::string& jpeg, uint32_t width, uint32_t height) {
  std::string out = jpeg;
  const size_t sof = AfterMarker(jpeg, 0xC0);
  EXPECT_NE(sof, std::string::npos) << "not a baseline JPEG";
  PutBe16(&out, sof + 3, height);
  PutBe16(&out, sof + 5, width);
  return out;
}

void PutBe32(std::string* bytes, size_t at, uint32_t value) {
  for (int i = 0; i < 4; ++i) (*bytes)[at + size_t(i)] = char((value >> (24 - 8 * i)) & 0xFF);
}

// A PNG chunk: length, type, data, CRC.
std::string Chunk(const char* type, const std::string& data) {
  std::string chunk(4, '\0');
  PutBe32(&chunk, 0, uint32_t(data.size()));
  chunk += type;
  chunk += data;
  const uLong crc = crc32(crc32(0L, Z_NULL, 0), reinterpret_cast<const Bytef*>(chunk.data() + 4),
                          uInt(chunk.size() - 4));
  std::string tail(4, '\0');
  PutBe32(&tail, 0, uint32_t(crc));
  return chunk + tail;
}

// An Adam7-interlaced 8-bit PNG of `image` (gray or BGR), written here: OpenCV writes none.
// `drop` bytes are left out at the end of the image data (compressed correctly all the same).
std::string InterlacedPng(const cv::Mat& image, size_t drop = 0) {
  const int channels = image.channels();
  std::string raw;
  static constexpr int kPasses[7][4] = {{0, 0, 8, 8}, {4, 0, 8, 8}, {0, 4, 4, 8}, {2, 0, 4, 4},
                                        {0, 2, 2, 4}, {1, 0, 2, 2}, {0, 1, 1, 2}};
  for (const auto& [x0, y0, dx, dy] : kPasses) {
    if (x0 >= image.cols || y0 >= image.rows) continue;
    for (int y = y0; y < image.rows; y += dy) {
      raw += '\0';  // filter: none
      for (int x = x0; x < image.cols; x += dx) {
        const uint8_t* pixel = image.ptr<uint8_t>(y) + x * channels;
        if (channels == 1) {
          raw += char(pixel[0]);
        } else {
          raw += {char(pixel[2]), char(pixel[1]), char(pixel[0])};  // PNG is RGB
        }
      }
    }
  }
  raw.resize(raw.size() - drop);
  uLongf size = compressBound(uLong(raw.size()));
  std::string compressed(size, '\0');
  EXPECT_EQ(compress2(reinterpret_cast<Bytef*>(compressed.data()), &size,
                      reinterpret_cast<const Bytef*>(raw.data()), uLong(raw.size()), 6),
            Z_OK);
  compressed.resize(size);
  std::string header(13, '\0');
  PutBe32(&header, 0, uint32_t(image.cols));
  PutBe32(&header, 4, uint32_t(image.rows));
  header[8] = 8;                      // bit depth
  header[9] = channels == 1 ? 0 : 2;  // gray or RGB
  header[12] = 1;                     // Adam7
  return std::string("\x89PNG\r\n\x1A\n", 8) + Chunk("IHDR", header) + Chunk("IDAT", compressed) +
         Chunk("IEND", "");
}

std::string Code(const Status& status) {
  return StatusCodeName(status.code());
}

class DecodeTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    jpeg_ = CamVidJpeg();
    png_ = RgbdColorPng();
    ASSERT_FALSE(jpeg_.empty());
    ASSERT_FALSE(png_.empty());
  }
  std::string jpeg_, png_;
};

// The largest absolute difference between two images of the same size and type.
double MaxDifference(const cv::Mat& a, const cv::Mat& b) {
  EXPECT_EQ(a.size(), b.size());
  EXPECT_EQ(a.type(), b.type());
  if (a.size() != b.size() || a.type() != b.type()) return 1e9;
  return cv::norm(a, b, cv::NORM_INF);
}

TEST_F(DecodeTest, GoodJpegDecodesToOpenCvsPixels) {
  // Both decoders are libjpeg-turbo (OpenCV's imgcodecs links Debian's libjpeg62-turbo) with the
  // same accurate integer IDCT, fancy upsampling and colour conversion, so the pixels agree
  // exactly; a bound of 1 would only admit rounding differences in an upsampler, none is needed
  // here, and anything larger would be a different decode.
  for (auto [mode, flags] : {std::pair{ColorMode::kColor, cv::IMREAD_COLOR},
                             std::pair{ColorMode::kGray, cv::IMREAD_GRAYSCALE},
                             std::pair{ColorMode::kUnchanged, cv::IMREAD_UNCHANGED}}) {
    auto decoded = DecodeImage(Span(jpeg_), DecodeOptions{mode, 0});
    ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
    const cv::Mat reference =
        cv::imdecode(cv::Mat(1, int(jpeg_.size()), CV_8U, jpeg_.data()), flags);
    EXPECT_EQ(MaxDifference(*decoded, reference), 0.0) << "mode " << int(mode);
  }
  auto gray = DecodeImage(Span(jpeg_), DecodeOptions{ColorMode::kGray, 0});
  ASSERT_TRUE(gray.ok());
  EXPECT_EQ(gray->type(), CV_8UC1);
  EXPECT_EQ(gray->cols, 480);
  EXPECT_EQ(gray->rows, 360);
}

TEST_F(DecodeTest, GrayJpegStaysGrayWhenUnchanged) {
  // A gray JPEG of a real camera frame, encoded here (OpenCV's encoder, libjpeg-turbo).
  const cv::Mat gray = cv::imread(testing::SharedDir() + "/data/camvid/images/0001TP_006690.jpg",
                                  cv::IMREAD_GRAYSCALE);
  std::vector<uint8_t> encoded;
  ASSERT_TRUE(cv::imencode(".jpg", gray, encoded));
  auto decoded =
      DecodeImage(std::span<const uint8_t>(encoded), DecodeOptions{ColorMode::kUnchanged, 0});
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->type(), CV_8UC1);
  EXPECT_EQ(MaxDifference(*decoded, cv::imdecode(encoded, cv::IMREAD_UNCHANGED)), 0.0);
}

TEST_F(DecodeTest, GoodPngDecodesToOpenCvsPixels) {
  for (auto [mode, flags] : {std::pair{ColorMode::kColor, cv::IMREAD_COLOR},
                             std::pair{ColorMode::kGray, cv::IMREAD_GRAYSCALE}}) {
    auto decoded = DecodeImage(Span(png_), DecodeOptions{mode, 0});
    ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
    const cv::Mat reference = cv::imdecode(cv::Mat(1, int(png_.size()), CV_8U, png_.data()), flags);
    EXPECT_EQ(MaxDifference(*decoded, reference), 0.0);
  }
  // A 16-bit depth PNG keeps its depth.
  const std::string depth = RgbdDepthPng();
  auto decoded = DecodeImage(Span(depth), DecodeOptions{ColorMode::kUnchanged, 0});
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->type(), CV_16UC1);
  EXPECT_EQ(MaxDifference(*decoded, cv::imdecode(cv::Mat(1, int(depth.size()), CV_8U,
                                                         const_cast<char*>(depth.data())),
                                                 cv::IMREAD_UNCHANGED)),
            0.0);
}

TEST_F(DecodeTest, TruncatedJpegIsRefused) {
  for (size_t keep : {jpeg_.size() / 2, jpeg_.size() - 2, size_t(200)}) {
    const std::string cut = jpeg_.substr(0, keep);
    auto decoded = DecodeImage(Span(cut), DecodeOptions{});
    ASSERT_FALSE(decoded.ok()) << "kept " << keep << " of " << jpeg_.size() << " bytes";
    EXPECT_EQ(Code(decoded.status()), "INVALID_ARGUMENT");
    EXPECT_EQ(decoded.status().message().rfind("JPEG data is", 0), 0u)
        << decoded.status().message();
  }
  const std::string half = jpeg_.substr(0, jpeg_.size() / 2);
  EXPECT_EQ(DecodeImage(Span(half), DecodeOptions{}).status().message(),
            "JPEG data is truncated (libjpeg: Premature end of JPEG file)");
  // cv::imdecode stores what it could decode: this is the damage the decoder exists for.
  EXPECT_FALSE(cv::imdecode(cv::Mat(1, int(half.size()), CV_8U, const_cast<char*>(half.data())),
                            cv::IMREAD_COLOR)
                   .empty());
}

TEST_F(DecodeTest, RandomScanDataIsRefused) {
  for (uint32_t seed = 1; seed <= 20; ++seed) {
    const std::string damaged = RandomScan(jpeg_, seed);
    ASSERT_NE(damaged, jpeg_);
    auto decoded = DecodeImage(Span(damaged), DecodeOptions{ColorMode::kGray, 0});
    ASSERT_FALSE(decoded.ok()) << "seed " << seed;
    EXPECT_EQ(Code(decoded.status()), "INVALID_ARGUMENT");
    EXPECT_EQ(decoded.status().message().rfind("JPEG data is corrupt (libjpeg: ", 0), 0u)
        << decoded.status().message();
  }
}

TEST_F(DecodeTest, FrameHeaderWithAnotherSizeIsRefused) {
  // The data is 480x360: a header claiming more rows runs out of data, fewer rows leaves data
  // unread before the end marker, another width desynchronises the entropy decoder.
  for (auto [width, height] : {std::pair{480u, 720u}, std::pair{480u, 180u}, std::pair{960u, 360u},
                               std::pair{240u, 360u}, std::pair{480u, 352u}}) {
    const std::string damaged = WithJpegSize(jpeg_, width, height);
    auto decoded = DecodeImage(Span(damaged), DecodeOptions{});
    ASSERT_FALSE(decoded.ok()) << width << "x" << height;
    EXPECT_EQ(Code(decoded.status()), "INVALID_ARGUMENT");
    EXPECT_EQ(decoded.status().message().rfind("JPEG data is", 0), 0u)
        << decoded.status().message();
  }
}

TEST_F(DecodeTest, PixelLimitIsCheckedFromTheHeaderBeforeDecoding) {
  // 60000x60000 claimed by a 100 kB file: refused as over the limit, not as truncated (it is never
  // decoded, so no 10 GB buffer is allocated).
  const std::string huge = WithJpegSize(jpeg_, 60000, 60000);
  auto decoded = DecodeImage(Span(huge), DecodeOptions{ColorMode::kColor, 10'000'000});
  ASSERT_FALSE(decoded.ok());
  EXPECT_EQ(Code(decoded.status()), "RESOURCE_EXHAUSTED");
  EXPECT_NE(decoded.status().message().find("60000x60000 image = 3600000000 pixels"),
            std::string::npos)
      << decoded.status().message();
  // The limit is inclusive.
  EXPECT_TRUE(DecodeImage(Span(jpeg_), DecodeOptions{ColorMode::kGray, 480 * 360}).ok());
  EXPECT_EQ(Code(DecodeImage(Span(jpeg_), DecodeOptions{ColorMode::kGray, 480 * 360 - 1}).status()),
            "RESOURCE_EXHAUSTED");
  EXPECT_EQ(Code(DecodeImage(Span(png_), DecodeOptions{ColorMode::kGray, 640 * 480 - 1}).status()),
            "RESOURCE_EXHAUSTED");
}

TEST_F(DecodeTest, DamagedPngIsRefused) {
  auto refused = [](const std::string& bytes, const std::string& expected_start) {
    auto decoded = DecodeImage(Span(bytes), DecodeOptions{});
    if (decoded.ok()) return std::string("decoded");
    if (decoded.status().code() != StatusCode::kInvalidArgument) return decoded.status().ToString();
    if (decoded.status().message().rfind(expected_start, 0) != 0) return decoded.status().message();
    return std::string("refused");
  };
  EXPECT_EQ(refused(png_.substr(0, png_.size() / 2), "PNG data is truncated (the IDAT chunk"),
            "refused");
  EXPECT_EQ(refused(png_.substr(0, png_.size() - 12), "PNG data is truncated (it ends at byte"),
            "refused");
  EXPECT_EQ(refused(png_.substr(0, 20), "PNG data is truncated"), "refused");
  // One flipped bit in the middle of the image data: its chunk's CRC no longer matches.
  std::string flipped = png_;
  flipped[png_.size() / 2] = char(flipped[png_.size() / 2] ^ 0x10);
  EXPECT_EQ(refused(flipped, "PNG data is corrupt (the IDAT chunk at byte"), "refused");
  // A header claiming another size (the IHDR's CRC catches it).
  std::string resized = png_;
  PutBe16(&resized, 16 + 2, 1280);
  EXPECT_EQ(refused(resized, "PNG data is corrupt (the IHDR chunk at byte 8 fails its CRC check)"),
            "refused");
  // A header rewritten to another size with a matching CRC: the image data holds more (or fewer)
  // bytes than it promises (libpng only warns about surplus data unless its benign errors are
  // errors; cv::imdecode decodes 240 rows of it).
  for (uint32_t height : {240u, 479u, 481u}) {
    std::string rewritten = png_;
    PutBe32(&rewritten, 20, height);
    const uLong crc =
        crc32(crc32(0L, Z_NULL, 0), reinterpret_cast<const Bytef*>(rewritten.data() + 12), 17);
    PutBe32(&rewritten, 29, uint32_t(crc));
    EXPECT_EQ(
        refused(rewritten, height < 480 ? "PNG data is corrupt (libpng: IDAT: Too much image data)"
                                        : "PNG data is corrupt (libpng: Not enough image data)"),
        "refused")
        << height;
  }
  // Trailing data after IEND is refused (the policy: image_decoder.h).
  EXPECT_EQ(refused(png_ + "garbage", "PNG data has 7 bytes after its IEND chunk"), "refused");
  EXPECT_EQ(refused(png_ + png_, "PNG data has"), "refused");
}

TEST_F(DecodeTest, InterlacedPngDecodes) {
  // Odd sizes exercise every Adam7 pass's rounding; the pixels are a real frame's.
  const cv::Mat frame = cv::imread(testing::SharedDir() + "/data/camvid/images/0001TP_006690.jpg");
  ASSERT_FALSE(frame.empty());
  for (const cv::Size size :
       {cv::Size(37, 23), cv::Size(1, 1), cv::Size(5, 9), cv::Size(480, 360)}) {
    for (const bool gray : {true, false}) {
      cv::Mat image = frame(cv::Rect(cv::Point(0, 0), size)).clone();
      if (gray) cv::cvtColor(image, image, cv::COLOR_BGR2GRAY);
      const std::string png = InterlacedPng(image);
      auto decoded =
          DecodeImage(Span(png), DecodeOptions{gray ? ColorMode::kGray : ColorMode::kColor, 0});
      ASSERT_TRUE(decoded.ok()) << size << " " << decoded.status().ToString();
      EXPECT_EQ(MaxDifference(*decoded, image), 0.0) << size;
      // One byte less of image data is refused.
      auto short_data = DecodeImage(Span(InterlacedPng(image, 1)), DecodeOptions{});
      ASSERT_FALSE(short_data.ok()) << size;
      EXPECT_EQ(short_data.status().message(),
                "PNG data is corrupt (libpng: Not enough image data)");
    }
  }
}

// `image` (BGR) encoded by TurboJPEG as `pixel_format` with `flags` (progressive, ...).
std::string TurboJpeg(const cv::Mat& image, int pixel_format, int flags) {
  tjhandle handle = tjInitCompress();
  unsigned char* buffer = nullptr;
  unsigned long size = 0;
  cv::Mat source = image;
  if (pixel_format == TJPF_CMYK) {
    // CMYK pixels: the BGR frame's complement and a zero K plane, enough for a real CMYK file.
    cv::Mat bgra;
    cv::cvtColor(image, bgra, cv::COLOR_BGR2BGRA);
    source = cv::Scalar::all(255) - bgra;
    source.forEach<cv::Vec4b>([](cv::Vec4b& p, const int*) { p[3] = 0; });
  }
  const int ok = tjCompress2(handle, source.data, source.cols, int(source.step[0]), source.rows,
                             pixel_format, &buffer, &size, TJSAMP_420, 90, flags);
  EXPECT_EQ(ok, 0) << tjGetErrorStr2(handle);
  std::string bytes(reinterpret_cast<const char*>(buffer), size);
  tjFree(buffer);
  tjDestroy(handle);
  return bytes;
}

TEST_F(DecodeTest, ProgressiveJpegDecodesAndCmykIsRefused) {
  const cv::Mat frame = cv::imread(testing::SharedDir() + "/data/camvid/images/0001TP_006690.jpg");
  ASSERT_FALSE(frame.empty());
  const std::string progressive = TurboJpeg(frame, TJPF_BGR, TJFLAG_PROGRESSIVE);
  auto decoded = DecodeImage(Span(progressive), DecodeOptions{ColorMode::kColor, 0});
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(MaxDifference(*decoded, cv::imdecode(cv::Mat(1, int(progressive.size()), CV_8U,
                                                         const_cast<char*>(progressive.data())),
                                                 cv::IMREAD_COLOR)),
            0.0);
  // Cut short, a progressive file is refused too (its later scans are missing).
  const std::string cut = progressive.substr(0, progressive.size() * 3 / 4);
  EXPECT_EQ(DecodeImage(Span(cut), DecodeOptions{}).status().message(),
            "JPEG data is truncated (libjpeg: Premature end of JPEG file)");

  const std::string cmyk = TurboJpeg(frame, TJPF_CMYK, 0);
  auto refused = DecodeImage(Span(cmyk), DecodeOptions{});
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().message(),
            "JPEG data is CMYK, which is not supported (send RGB or gray)");
}

TEST_F(DecodeTest, TrailingBytesAfterJpegEndAreAccepted) {
  // Camera firmware appends trailers after EOI; the image itself is complete.
  auto decoded = DecodeImage(Span(jpeg_ + "trailer"), DecodeOptions{ColorMode::kGray, 0});
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  auto reference = DecodeImage(Span(jpeg_), DecodeOptions{ColorMode::kGray, 0});
  ASSERT_TRUE(reference.ok());
  EXPECT_EQ(MaxDifference(*decoded, *reference), 0.0);
}

TEST_F(DecodeTest, OtherBytesAreRefused) {
  for (const std::string& bytes :
       {std::string(), std::string("GIF89a"), std::string("\xFF\xD8\xFF", 3), std::string(100, 'x'),
        std::string("\x89PNG\r\n\x1A\n", 8)}) {
    auto decoded = DecodeImage(Span(bytes), DecodeOptions{});
    ASSERT_FALSE(decoded.ok()) << bytes.size() << " bytes";
    EXPECT_EQ(Code(decoded.status()), "INVALID_ARGUMENT") << decoded.status().message();
    EXPECT_FALSE(decoded.status().message().empty());
  }
  EXPECT_EQ(DecodeImage(Span(std::string("GIF89a")), DecodeOptions{}).status().message(),
            "not a JPEG or PNG image");
}

TEST_F(DecodeTest, HeaderInfoWithoutDecoding) {
  auto jpeg = ReadImageInfo(Span(jpeg_));
  ASSERT_TRUE(jpeg.ok()) << jpeg.status().ToString();
  EXPECT_EQ(jpeg->format, ImageFormat::kJpeg);
  EXPECT_EQ(jpeg->width, 480u);
  EXPECT_EQ(jpeg->height, 360u);
  auto png = ReadImageInfo(Span(png_));
  ASSERT_TRUE(png.ok()) << png.status().ToString();
  EXPECT_EQ(png->format, ImageFormat::kPng);
  EXPECT_EQ(png->width, 640u);
  EXPECT_EQ(png->height, 480u);
  // Only the header is needed: half a file still has one.
  EXPECT_TRUE(ReadImageInfo(Span(png_.substr(0, png_.size() / 2))).ok());
  EXPECT_FALSE(ReadImageInfo(Span(png_.substr(0, 30))).ok());
}

TEST(RawImageBytesTest, OverflowIsAnErrorNotAWrap) {
  auto bytes = RawImageBytes(640, 480, 3);
  ASSERT_TRUE(bytes.ok());
  EXPECT_EQ(*bytes, 921600u);
  EXPECT_EQ(*RawImageBytes(4'000'000'000u, 4'000'000'000u, 1), 16'000'000'000'000'000'000u);
  auto wrapped = RawImageBytes(4'294'967'295u, 4'294'967'295u, 3);
  ASSERT_FALSE(wrapped.ok());
  EXPECT_EQ(wrapped.status().message(),
            "4294967295x4294967295 x 3 bytes per pixel does not fit in 64 bits");
  uint64_t product = 7;
  EXPECT_FALSE(CheckedMul(uint64_t(1) << 32, uint64_t(1) << 32, &product));
  EXPECT_EQ(product, 7u);
  EXPECT_TRUE(CheckedMul(uint64_t(1) << 31, uint64_t(1) << 32, &product));
  EXPECT_EQ(product, uint64_t(1) << 63);
}

}  // namespace
}  // namespace placedb
