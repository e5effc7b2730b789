#include "core/thumbnail/thumbnail.h"

#include <turbojpeg.h>

#include <algorithm>
#include <cmath>
#include <memory>
#include <opencv2/imgproc.hpp>

namespace placedb {

Status ValidateThumbnailSettings(const ThumbnailSettings& settings) {
  if (settings.max_side < kMinThumbnailSide || settings.max_side > kMaxThumbnailSide) {
    return Status::InvalidArgument(
        "thumbnails.max_side must be in [" + std::to_string(kMinThumbnailSide) + ", " +
        std::to_string(kMaxThumbnailSide) + "], got " + std::to_string(settings.max_side));
  }
  if (settings.jpeg_quality < 1 || settings.jpeg_quality > 100) {
    return Status::InvalidArgument("thumbnails.jpeg_quality must be in [1, 100], got " +
                                   std::to_string(settings.jpeg_quality));
  }
  return Status::Ok();
}

cv::Size ThumbnailSize(int width, int height, uint32_t max_side) {
  const int longest = std::max(width, height);
  if (longest <= int(max_side)) return {width, height};
  const double scale = double(max_side) / longest;
  return {std::max(1, int(std::lround(width * scale))),
          std::max(1, int(std::lround(height * scale)))};
}

cv::Mat ReduceFrame(const cv::Mat& image, uint32_t max_side) {
  const cv::Size size = ThumbnailSize(image.cols, image.rows, max_side);
  if (size == image.size()) return image.clone();
  cv::Mat reduced;
  cv::resize(image, reduced, size, 0, 0, cv::INTER_AREA);
  return reduced;
}

cv::Rect ThumbnailBoxRect(const cv::Rect2f& box, cv::Size source, cv::Size reduced) {
  if (!(std::isfinite(box.x) && std::isfinite(box.y) && std::isfinite(box.width) &&
        std::isfinite(box.height)) ||
      box.width <= 0 || box.height <= 0 || source.width <= 0 || source.height <= 0) {
    return {};
  }
  const double sx = double(reduced.width) / source.width;
  const double sy = double(reduced.height) / source.height;
  const double x0 = std::clamp(std::floor(box.x * sx), 0.0, double(reduced.width));
  const double y0 = std::clamp(std::floor(box.y * sy), 0.0, double(reduced.height));
  const double x1 =
      std::clamp(std::ceil((double(box.x) + box.width) * sx), 0.0, double(reduced.width));
  const double y1 =
      std::clamp(std::ceil((double(box.y) + box.height) * sy), 0.0, double(reduced.height));
  if (x1 <= x0 || y1 <= y0) return {};
  return cv::Rect(int(x0), int(y0), int(x1 - x0), int(y1 - y0));
}

void BlurBox(cv::Mat* image, const cv::Rect& rect) {
  const cv::Rect clipped = rect & cv::Rect(0, 0, image->cols, image->rows);
  if (clipped.empty()) return;
  cv::Mat region = (*image)(clipped);
  const int longest = std::max(clipped.width, clipped.height);
  const double factor = std::min(1.0, double(kBlurCells) / longest);
  const cv::Size cells(std::max(1, int(std::lround(clipped.width * factor))),
                       std::max(1, int(std::lround(clipped.height * factor))));
  cv::Mat few;
  cv::resize(region, few, cells, 0, 0, cv::INTER_AREA);
  cv::Mat smooth;
  cv::resize(few, smooth, clipped.size(), 0, 0, cv::INTER_LINEAR);
  const double sigma = std::max(1.0, 0.5 * longest / kBlurCells);
  cv::GaussianBlur(smooth, smooth, cv::Size(0, 0), sigma, sigma, cv::BORDER_REPLICATE);
  smooth.copyTo(region);
}

Result<std::string> EncodeJpeg(const cv::Mat& image, int quality) {
  if (image.empty() || (image.type() != CV_8UC1 && image.type() != CV_8UC3)) {
    return Status::InvalidArgument("JPEG encoding takes a non-empty 8-bit gray or BGR image");
  }
  if (quality < 1 || quality > 100) {
    return Status::InvalidArgument("JPEG quality must be in [1, 100], got " +
                                   std::to_string(quality));
  }
  struct Destroy {
    void operator()(void* handle) const { tjDestroy(handle); }
  };
  std::unique_ptr<void, Destroy> handle(tjInitCompress());
  if (!handle) return Status::Internal("TurboJPEG: cannot create a compressor");
  const bool gray = image.channels() == 1;
  unsigned char* bytes = nullptr;
  unsigned long size = 0;
  const int failed = tjCompress2(handle.get(), image.data, image.cols, int(image.step), image.rows,
                                 gray ? TJPF_GRAY : TJPF_BGR, &bytes, &size,
                                 gray ? TJSAMP_GRAY : TJSAMP_420, quality, 0);
  std::unique_ptr<unsigned char, void (*)(unsigned char*)> owned(bytes, tjFree);
  if (failed != 0) {
    return Status::Internal(std::string("TurboJPEG: ") + tjGetErrorStr2(handle.get()));
  }
  return std::string(reinterpret_cast<const char*>(bytes), size);
}

Result<Thumbnail> MakeThumbnail(const cv::Mat& image, const std::vector<DynamicBox>& boxes,
                                std::vector<Keypoint> dropped, const ThumbnailSettings& settings,
                                const cv::Mat& mask) {
  PLACEDB_RETURN_IF_ERROR(ValidateThumbnailSettings(settings));
  if (image.empty() || image.depth() != CV_8U ||
      (image.channels() != 1 && image.channels() != 3 && image.channels() != 4)) {
    return Status::InvalidArgument("a thumbnail needs a non-empty 8-bit gray, BGR or BGRA image");
  }
  if (!mask.empty() && (mask.type() != CV_8UC1 || mask.size() != image.size())) {
    return Status::InvalidArgument("a thumbnail's dynamic mask must be CV_8U and image-sized");
  }
  cv::Mat reduced = ReduceFrame(image, settings.max_side);
  if (reduced.channels() == 4) cv::cvtColor(reduced, reduced, cv::COLOR_BGRA2BGR);
  for (const DynamicBox& box : boxes) {
    BlurBox(&reduced, ThumbnailBoxRect(box.rect, image.size(), reduced.size()));
  }
  if (!mask.empty() && cv::countNonZero(mask) > 0) {
    // Any dynamic pixel marks its reduced pixel (a maximum, not an average, so thin parts stay).
    cv::Mat marked;
    if (mask.size() == reduced.size()) {
      marked = mask != 0;
    } else {
      cv::Mat dynamic = mask != 0;
      cv::Mat grown;
      const int step = int(std::ceil(double(mask.cols) / reduced.cols));
      cv::dilate(dynamic, grown, cv::Mat::ones(step, step, CV_8U));
      cv::resize(grown, marked, reduced.size(), 0, 0, cv::INTER_NEAREST);
    }
    cv::Mat components, stats, centroids;
    const int count = cv::connectedComponentsWithStats(marked, components, stats, centroids, 8);
    for (int c = 1; c < count; ++c) {
      const int* s = stats.ptr<int>(c);
      BlurBox(&reduced, cv::Rect(s[cv::CC_STAT_LEFT] - 1, s[cv::CC_STAT_TOP] - 1,
                                 s[cv::CC_STAT_WIDTH] + 2, s[cv::CC_STAT_HEIGHT] + 2));
    }
  }
  auto jpeg = EncodeJpeg(reduced, int(settings.jpeg_quality));
  if (!jpeg.ok()) return jpeg.status();
  Thumbnail thumbnail;
  thumbnail.jpeg = std::move(jpeg).value();
  thumbnail.width = uint32_t(reduced.cols);
  thumbnail.height = uint32_t(reduced.rows);
  thumbnail.source_width = uint32_t(image.cols);
  thumbnail.source_height = uint32_t(image.rows);
  thumbnail.dropped_keypoints = std::move(dropped);
  return thumbnail;
}

}  // namespace placedb
