#include "core/filter/dynamic_filter.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <opencv2/imgproc.hpp>
#include <string>

// Coordinate conventions used throughout this file:
//  - A DynamicBox rect follows cv::Rect: pixel (c, r) spans [c, c+1) x [r, r+1), so a box covers
//    the pixels whose centres (c + 0.5, r + 0.5) lie in [x, x + w) x [y, y + h). A mask
//    component's bounding rectangle (left, top, width, height) is therefore used as is.
//  - A keypoint (x, y) follows cv::KeyPoint: integer coordinates are pixel centres, so the
//    keypoint sits in pixel (round(x), round(y)) and at (x + 0.5, y + 0.5) in box coordinates.

namespace placedb {

namespace {

// A descriptor's extent is sampled on at most this many points per side: ORB's default patch
// side, i.e. one sample per pixel of the keypoint's pyramid level for the default extractor
// (the stride is then size / 31 = the octave's scale). Smaller patches get one sample per
// full-resolution pixel.
constexpr int kMaxSamplesPerSide = 31;

int RoundToPixel(double v) {
  return static_cast<int>(std::floor(v + 0.5));
}

// A box reduced to what the classifiers need: its clipped continuous extent (for the corner
// distances of heuristic 2) and the half-open pixel ranges it covers (for membership tests).
struct ClippedBox {
  double x0 = 0, y0 = 0, x1 = 0, y1 = 0;  // continuous, [x0, x1) x [y0, y1)
  int col_begin = 0, col_end = 0;         // pixel columns [col_begin, col_end)
  int row_begin = 0, row_end = 0;         // pixel rows [row_begin, row_end)

  bool empty() const { return col_begin >= col_end || row_begin >= row_end; }
  bool ContainsPixel(int col, int row) const {
    return col >= col_begin && col < col_end && row >= row_begin && row < row_end;
  }
};

// Clips a (validated, finite) rectangle to the image [0, width) x [0, height). Done in double
// so that huge or far-away boxes cannot overflow the integer conversion.
ClippedBox ClipBox(double x, double y, double w, double h, int width, int height) {
  ClippedBox box;
  box.x0 = std::clamp(x, 0.0, double(width));
  box.x1 = std::clamp(x + w, 0.0, double(width));
  box.y0 = std::clamp(y, 0.0, double(height));
  box.y1 = std::clamp(y + h, 0.0, double(height));
  // Pixel c is covered when its centre c + 0.5 lies in [x0, x1): c in [ceil(x0 - 0.5),
  // ceil(x1 - 0.5)).
  box.col_begin = int(std::ceil(box.x0 - 0.5));
  box.col_end = int(std::ceil(box.x1 - 0.5));
  box.row_begin = int(std::ceil(box.y0 - 0.5));
  box.row_end = int(std::ceil(box.y1 - 0.5));
  return box;
}

bool BoxIsWellFormed(const DynamicBox& box) {
  const cv::Rect2f& r = box.rect;
  return std::isfinite(r.x) && std::isfinite(r.y) && std::isfinite(r.width) &&
         std::isfinite(r.height) && r.width >= 0 && r.height >= 0;
}

bool MaskIsUsable(const cv::Mat& mask, int width, int height) {
  return mask.dims == 2 && mask.type() == CV_8UC1 && mask.cols == width && mask.rows == height;
}

Status ValidateObjects(const DynamicObjects& objects, int width, int height) {
  if (!objects.mask.empty() && !MaskIsUsable(objects.mask, width, height)) {
    return Status::InvalidArgument(
        "mask must be a single-channel 8-bit (CV_8UC1) image of the frame's size " +
        std::to_string(width) + "x" + std::to_string(height) + ", got " +
        std::to_string(objects.mask.cols) + "x" + std::to_string(objects.mask.rows) + " with " +
        std::to_string(objects.mask.channels()) + " channel(s) of depth " +
        std::to_string(objects.mask.depth()));
  }
  for (size_t i = 0; i < objects.boxes.size(); ++i) {
    if (!BoxIsWellFormed(objects.boxes[i])) {
      const cv::Rect2f& r = objects.boxes[i].rect;
      return Status::InvalidArgument(
          "boxes[" + std::to_string(i) + "] must have finite coordinates and a non-negative " +
          "width and height, got (" + std::to_string(r.x) + ", " + std::to_string(r.y) + ", " +
          std::to_string(r.width) + ", " + std::to_string(r.height) + ")");
    }
  }
  return Status::Ok();
}

// The pixel a keypoint lies on, clamped into the image (validated keypoints are inside already;
// the clamp only guards rounding at the far border).
cv::Point KeypointPixel(const Keypoint& kp, int width, int height) {
  return {std::clamp(RoundToPixel(kp.x), 0, width - 1),
          std::clamp(RoundToPixel(kp.y), 0, height - 1)};
}

// Boxes for heuristic 2: the given boxes, clipped, plus the bounding rectangles of the mask's
// 8-connected components (a mask carries no boxes of its own).
std::vector<ClippedBox> HeuristicBoxes(const DynamicObjects& objects, int width, int height) {
  std::vector<ClippedBox> boxes;
  for (const DynamicBox& box : objects.boxes) {
    ClippedBox clipped =
        ClipBox(box.rect.x, box.rect.y, box.rect.width, box.rect.height, width, height);
    if (!clipped.empty()) boxes.push_back(clipped);
  }
  if (!objects.mask.empty()) {
    cv::Mat labels, stats, centroids;
    const int count =
        cv::connectedComponentsWithStats(objects.mask != 0, labels, stats, centroids, 8, CV_32S);
    for (int label = 1; label < count; ++label) {  // label 0 is the background
      const int* s = stats.ptr<int>(label);
      boxes.push_back(ClipBox(s[cv::CC_STAT_LEFT], s[cv::CC_STAT_TOP], s[cv::CC_STAT_WIDTH],
                              s[cv::CC_STAT_HEIGHT], width, height));
    }
  }
  return boxes;
}

// Heuristic 2: inside a box and more than r from each of its four corners, r being the distance
// to the extent's furthest point (half the patch diagonal). Then the disc of radius r around the
// keypoint cannot hold a box corner, so the patch crosses at most the box's straight edges.
bool CornerDistanceIsDynamic(const Keypoint& kp, const cv::Point& pixel,
                             const std::vector<ClippedBox>& boxes) {
  const double r = 0.5 * double(kp.size) * std::numbers::sqrt2;
  const double r2 = r * r;
  const double px = double(kp.x) + 0.5;  // into box coordinates
  const double py = double(kp.y) + 0.5;
  for (const ClippedBox& box : boxes) {
    if (!box.ContainsPixel(pixel.x, pixel.y)) continue;
    bool far_from_all = true;
    for (double cx : {box.x0, box.x1}) {
      for (double cy : {box.y0, box.y1}) {
        const double dx = px - cx;
        const double dy = py - cy;
        if (dx * dx + dy * dy <= r2) far_from_all = false;
      }
    }
    if (far_from_all) return true;
  }
  return false;
}

// Sum of the region over pixel columns [c0, c1) and rows [r0, r1), from its integral image
// (CV_32S or CV_64F; exact either way: the sums are integers below 2^53).
double RectSum(const cv::Mat& integral, int c0, int r0, int c1, int r1) {
  if (integral.depth() == CV_32S) {
    return double(int64_t(integral.at<int>(r1, c1)) - integral.at<int>(r0, c1) -
                  integral.at<int>(r1, c0) + integral.at<int>(r0, c0));
  }
  return integral.at<double>(r1, c1) - integral.at<double>(r0, c1) - integral.at<double>(r1, c0) +
         integral.at<double>(r0, c0);
}

// The sampling grid of one keypoint's extent: n x n points, `stride` apart, centred on the
// keypoint and rotated like ORB's sampling pattern (column += u cos - v sin, row += u sin +
// v cos for an offset (u, v) in the patch frame). Positions are in 32.32 fixed point so that a
// sample maps to the same pixel whichever block of the grid it is counted in, and so that the
// pixel bounds of a block follow exactly from its four corner samples (positions are linear in
// the grid indices and rounding is monotonic).
class ExtentSampler {
 public:
  ExtentSampler(const Keypoint& kp, const cv::Mat& region, const cv::Mat& integral)
      : region_(region), integral_(integral) {
    samples_ = std::clamp(int(std::lround(kp.size)), 1, kMaxSamplesPerSide);
    const double stride = double(kp.size) / samples_;
    double cos_a = 1, sin_a = 0;
    if (kp.angle != -1.0f) {
      const double radians = double(kp.angle) * std::numbers::pi / 180.0;
      cos_a = std::cos(radians);
      sin_a = std::sin(radians);
    }
    const double half = 0.5 * (samples_ - 1) * stride;  // offset of the outermost samples
    // Sample (i, j) has patch offset (u, v) = (i * stride - half, j * stride - half).
    x00_ = ToFixed(kp.x - half * cos_a + half * sin_a);
    y00_ = ToFixed(kp.y - half * sin_a - half * cos_a);
    dx_i_ = ToFixed(stride * cos_a);
    dy_i_ = ToFixed(stride * sin_a);
    dx_j_ = ToFixed(-stride * sin_a);
    dy_j_ = ToFixed(stride * cos_a);
  }

  int samples_per_side() const { return samples_; }

  // Dynamic samples among i in [i0, i1), j in [j0, j1). Blocks whose pixel bounds hold no
  // dynamic pixel, or only dynamic pixels, are settled by the integral image; the rest are split
  // into quarters down to 8 x 8 samples, which are then walked one by one. A patch crossing one
  // straight edge thus visits only the blocks along that edge.
  int CountDynamic(int i0, int i1, int j0, int j1) const {
    const int corner_cols[4] = {Col(i0, j0), Col(i1 - 1, j0), Col(i0, j1 - 1), Col(i1 - 1, j1 - 1)};
    const int corner_rows[4] = {Row(i0, j0), Row(i1 - 1, j0), Row(i0, j1 - 1), Row(i1 - 1, j1 - 1)};
    const int col0 = *std::min_element(corner_cols, corner_cols + 4);
    const int col1 = *std::max_element(corner_cols, corner_cols + 4);  // inclusive
    const int row0 = *std::min_element(corner_rows, corner_rows + 4);
    const int row1 = *std::max_element(corner_rows, corner_rows + 4);
    const int c0 = std::max(col0, 0), c1 = std::min(col1, region_.cols - 1);
    const int r0 = std::max(row0, 0), r1 = std::min(row1, region_.rows - 1);
    if (c0 > c1 || r0 > r1) return 0;  // entirely outside the image: static
    const double sum = RectSum(integral_, c0, r0, c1 + 1, r1 + 1);
    if (sum == 0) return 0;
    const bool inside_image = c0 == col0 && c1 == col1 && r0 == row0 && r1 == row1;
    if (inside_image && sum == 255.0 * double(c1 - c0 + 1) * double(r1 - r0 + 1)) {
      return (i1 - i0) * (j1 - j0);
    }
    if (i1 - i0 <= kLeafSide && j1 - j0 <= kLeafSide) return Walk(i0, i1, j0, j1);
    const int im = i1 - i0 > 1 ? (i0 + i1) / 2 : i1;  // a side of one sample is not split
    const int jm = j1 - j0 > 1 ? (j0 + j1) / 2 : j1;
    int count = CountDynamic(i0, im, j0, jm);
    if (im < i1) count += CountDynamic(im, i1, j0, jm);
    if (jm < j1) count += CountDynamic(i0, im, jm, j1);
    if (im < i1 && jm < j1) count += CountDynamic(im, i1, jm, j1);
    return count;
  }

 private:
  static constexpr int kFractionBits = 32;
  static constexpr int kLeafSide = 8;

  static int64_t ToFixed(double v) { return std::llround(std::ldexp(v, kFractionBits)); }
  // Rounds to the nearest pixel, halves up (arithmetic shift = floor).
  static int Pixel(int64_t fixed) {
    return int((fixed + (int64_t(1) << (kFractionBits - 1))) >> kFractionBits);
  }
  int Col(int i, int j) const { return Pixel(x00_ + i * dx_i_ + j * dx_j_); }
  int Row(int i, int j) const { return Pixel(y00_ + i * dy_i_ + j * dy_j_); }

  int Walk(int i0, int i1, int j0, int j1) const {
    const unsigned width = unsigned(region_.cols), height = unsigned(region_.rows);
    int count = 0;
    for (int j = j0; j < j1; ++j) {
      int64_t x = x00_ + i0 * dx_i_ + j * dx_j_;
      int64_t y = y00_ + i0 * dy_i_ + j * dy_j_;
      for (int i = i0; i < i1; ++i, x += dx_i_, y += dy_i_) {
        const int col = Pixel(x), row = Pixel(y);
        // Samples outside the image are static.
        if (unsigned(col) < width && unsigned(row) < height) {
          count += region_.ptr<uint8_t>(row)[col] != 0;
        }
      }
    }
    return count;
  }

  const cv::Mat& region_;
  const cv::Mat& integral_;
  int samples_ = 1;
  int64_t x00_ = 0, y00_ = 0;                          // sample (0, 0)
  int64_t dx_i_ = 0, dy_i_ = 0, dx_j_ = 0, dy_j_ = 0;  // steps along i and along j
};

// The fraction of a keypoint's extent on dynamic pixels. `region` is the rasterised dynamic
// region (255 = dynamic) and `integral` its integral image.
float ExtentCoverage(const Keypoint& kp, const cv::Mat& region, const cv::Mat& integral) {
  const ExtentSampler sampler(kp, region, integral);
  const int n = sampler.samples_per_side();
  return float(double(sampler.CountDynamic(0, n, 0, n)) / (double(n) * n));
}

}  // namespace

const char* FilterMethodName(FilterMethod method) {
  switch (method) {
    case FilterMethod::kNone:
      return "none";
    case FilterMethod::kKeypointInBox:
      return "keypoint_in_box";
    case FilterMethod::kCornerDistance:
      return "corner_distance";
    case FilterMethod::kExactCoverage:
      return "exact_coverage";
  }
  return "unknown";
}

Result<FilterMethod> ParseFilterMethod(const std::string& name) {
  for (FilterMethod method : {FilterMethod::kNone, FilterMethod::kKeypointInBox,
                              FilterMethod::kCornerDistance, FilterMethod::kExactCoverage}) {
    if (name == FilterMethodName(method)) return method;
  }
  return Status::InvalidArgument("filter method \"" + name +
                                 "\" is unknown; expected one of none, keypoint_in_box, "
                                 "corner_distance, exact_coverage");
}

Status ValidateFilterConfig(const FilterConfig& config) {
  switch (config.method) {
    case FilterMethod::kNone:
    case FilterMethod::kKeypointInBox:
    case FilterMethod::kCornerDistance:
    case FilterMethod::kExactCoverage:
      break;
    default:
      return Status::InvalidArgument("filter.method has an unknown value " +
                                     std::to_string(int(config.method)));
  }
  // Written so that NaN fails too.
  if (!(config.sensitivity_threshold >= 0.0f && config.sensitivity_threshold < 1.0f)) {
    return Status::InvalidArgument("filter.sensitivity_threshold must be in [0, 1), got " +
                                   std::to_string(config.sensitivity_threshold));
  }
  if (config.place_threshold < 0) {
    return Status::InvalidArgument("filter.place_threshold must be >= 0, got " +
                                   std::to_string(config.place_threshold));
  }
  return Status::Ok();
}

cv::Mat RasterizeDynamicRegion(const DynamicObjects& objects, int width, int height) {
  if (width <= 0 || height <= 0) return {};
  cv::Mat region(height, width, CV_8U, cv::Scalar(0));
  // Malformed input has no Status channel here: ClassifyDescriptors rejects it before calling,
  // and direct callers get the well-formed part (bad boxes and a mismatched mask are skipped).
  for (const DynamicBox& box : objects.boxes) {
    if (!BoxIsWellFormed(box)) continue;
    const ClippedBox clipped =
        ClipBox(box.rect.x, box.rect.y, box.rect.width, box.rect.height, width, height);
    if (clipped.empty()) continue;
    region(cv::Range(clipped.row_begin, clipped.row_end),
           cv::Range(clipped.col_begin, clipped.col_end))
        .setTo(255);
  }
  if (!objects.mask.empty() && MaskIsUsable(objects.mask, width, height)) {
    for (int row = 0; row < height; ++row) {
      const uint8_t* in = objects.mask.ptr<uint8_t>(row);
      uint8_t* out = region.ptr<uint8_t>(row);
      for (int col = 0; col < width; ++col) out[col] |= in[col] != 0 ? 255 : 0;
    }
  }
  return region;
}

cv::Rect BoxPixelRect(const cv::Rect2f& rect, int width, int height) {
  const ClippedBox clipped = ClipBox(rect.x, rect.y, rect.width, rect.height, width, height);
  if (clipped.empty()) return {};
  return {clipped.col_begin, clipped.row_begin, clipped.col_end - clipped.col_begin,
          clipped.row_end - clipped.row_begin};
}

Result<FilterResult> ClassifyDescriptors(const LocalFeatures& features,
                                         const DynamicObjects& objects,
                                         const FilterConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateFilterConfig(config));
  PLACEDB_RETURN_IF_ERROR(features.Validate());
  const int width = features.image_width();
  const int height = features.image_height();
  const std::vector<Keypoint>& keypoints = features.keypoints();
  PLACEDB_RETURN_IF_ERROR(ValidateObjects(objects, width, height));

  const size_t count = features.size();
  FilterResult result;
  if (config.method == FilterMethod::kExactCoverage) result.coverage.assign(count, 0.0f);
  const bool have_objects = !objects.boxes.empty() || !objects.mask.empty();
  if (config.method == FilterMethod::kNone || !have_objects) {
    result.static_indices.resize(count);
    for (size_t i = 0; i < count; ++i) result.static_indices[i] = uint32_t(i);
    result.valid = result.static_indices.size() > size_t(config.place_threshold);
    return result;
  }

  const cv::Mat region = RasterizeDynamicRegion(objects, width, height);
  result.frame_dynamic_coverage = double(cv::countNonZero(region)) / (double(width) * height);

  // Per-method state, built only for the method in use.
  std::vector<ClippedBox> heuristic_boxes;
  cv::Mat integral;
  if (config.method == FilterMethod::kCornerDistance) {
    heuristic_boxes = HeuristicBoxes(objects, width, height);
  } else if (config.method == FilterMethod::kExactCoverage && result.frame_dynamic_coverage > 0) {
    // Sums reach 255 x pixel count: 32-bit suffices below about 8.4 megapixels.
    const bool fits_int32 = 255.0 * width * height < 2147483647.0;
    cv::integral(region, integral, fits_int32 ? CV_32S : CV_64F);
  }

  result.static_indices.reserve(count);
  for (size_t i = 0; i < count; ++i) {
    const Keypoint& kp = keypoints[i];
    const cv::Point pixel = KeypointPixel(kp, width, height);
    bool dynamic = false;
    switch (config.method) {
      case FilterMethod::kKeypointInBox:
        // Heuristic 1: the region holds every box and mask pixel.
        dynamic = region.ptr<uint8_t>(pixel.y)[pixel.x] != 0;
        break;
      case FilterMethod::kCornerDistance:
        dynamic = CornerDistanceIsDynamic(kp, pixel, heuristic_boxes);
        break;
      case FilterMethod::kExactCoverage:
        if (!integral.empty()) result.coverage[i] = ExtentCoverage(kp, region, integral);
        dynamic = result.coverage[i] > config.sensitivity_threshold;
        break;
      case FilterMethod::kNone:
        break;
    }
    (dynamic ? result.dynamic_indices : result.static_indices).push_back(uint32_t(i));
  }
  result.valid = result.static_indices.size() > size_t(config.place_threshold);
  return result;
}

}  // namespace placedb
