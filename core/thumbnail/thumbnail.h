// Per-place thumbnails (issue 20): a small JPEG of a stored place's frame, for the web console.
//
// The frame is reduced so that its longest side is `max_side` (never enlarged), each dynamic-object
// box the filter used (and each region of an agent's dynamic mask) is blurred in the reduced image
// so that nobody in it can be recognised (fleets film people), and the result is JPEG-encoded
// with TurboJPEG. The keypoints the filter
// dropped as dynamic are kept beside the JPEG, in the source frame's pixels, so a viewer can draw
// them scaled by width / source_width.
//
// The blur ("BlurBox"): the box's pixels are averaged down to at most kBlurCells samples along
// its longer side, enlarged back bilinearly and smoothed with a Gaussian of half a cell. Averaging
// to a handful of samples destroys the detail for good (a face in a person box becomes about one
// sample; a plain Gaussian with a known kernel can partly be deconvolved); the interpolation and
// the Gaussian leave no mosaic edges, so the region is smooth and cheap for the JPEG.
//
// Pure functions, no global state: safe from any number of threads.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/detect/dynamic_objects.h"
#include "core/features/orb_features.h"

namespace placedb {

constexpr uint32_t kDefaultThumbnailSide = 320;
constexpr uint32_t kDefaultThumbnailQuality = 75;
constexpr uint32_t kMinThumbnailSide = 16;
constexpr uint32_t kMaxThumbnailSide = 1024;
// Samples along a blurred box's longer side.
constexpr int kBlurCells = 8;

// A map's thumbnail settings (MapOptions::thumbnails). Off by default.
struct ThumbnailSettings {
  bool enabled = false;
  uint32_t max_side = kDefaultThumbnailSide;         // longest side in pixels, 16..1024
  uint32_t jpeg_quality = kDefaultThumbnailQuality;  // 1..100
  bool operator==(const ThumbnailSettings&) const = default;
};

// INVALID_ARGUMENT naming the field ("thumbnails.max_side must be in [16, 1024], got 8"), also
// when thumbnails are off (stored settings stay valid when they are turned on).
Status ValidateThumbnailSettings(const ThumbnailSettings& settings);

struct Thumbnail {
  std::string jpeg;  // baseline JPEG, gray or colour as the frame was decoded
  uint32_t width = 0;
  uint32_t height = 0;
  uint32_t source_width = 0;
  uint32_t source_height = 0;
  std::vector<Keypoint> dropped_keypoints;  // DC keypoints, source-frame pixels
  bool operator==(const Thumbnail&) const = default;
};

// The reduced size of a width x height frame: the longest side becomes max_side (frames already
// smaller keep their size), each side rounded, at least 1.
cv::Size ThumbnailSize(int width, int height, uint32_t max_side);
// The frame reduced to ThumbnailSize (area averaging), before any blur.
cv::Mat ReduceFrame(const cv::Mat& image, uint32_t max_side);
// The pixels of the reduced image (`reduced` size, from a `source` sized frame) that `box`
// covers, rounded outwards so that the whole object is blurred; clipped, empty when outside.
cv::Rect ThumbnailBoxRect(const cv::Rect2f& box, cv::Size source, cv::Size reduced);
// Blurs `rect` of `image` in place (see the file comment); empty rects are left alone.
void BlurBox(cv::Mat* image, const cv::Rect& rect);

// The JPEG bytes of an 8-bit gray or BGR image (4:2:0 for colour), quality 1..100.
// INVALID_ARGUMENT for other image types; INTERNAL when TurboJPEG fails.
Result<std::string> EncodeJpeg(const cv::Mat& image, int quality);

// The thumbnail of `image` (8-bit gray, BGR or BGRA; non-empty) with every box of `boxes` (the
// boxes the filter used, source pixels) blurred, and `dropped` kept as they are. A dynamic-object
// `mask` (CV_8U, image-sized, non-zero = dynamic; an agent may send one instead of boxes) is
// blurred too: the bounding rectangle of each of its connected regions in the reduced image.
// INVALID_ARGUMENT for an empty image or one of another type, a mask of another type or size,
// or bad settings.
Result<Thumbnail> MakeThumbnail(const cv::Mat& image, const std::vector<DynamicBox>& boxes,
                                std::vector<Keypoint> dropped, const ThumbnailSettings& settings,
                                const cv::Mat& mask = cv::Mat());

}  // namespace placedb
