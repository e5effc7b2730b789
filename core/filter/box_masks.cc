#include "core/filter/box_masks.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

namespace placedb {

namespace {

// Superellipse exponent of a class's shape prior: people and two-wheelers are narrower than
// their box at the top and bottom (an ellipse), vehicles fill it but for rounded corners.
double ShapeExponent(int class_id) {
  switch (class_id) {
    case 0:  // person
    case 1:  // bicycle
    case 3:  // motorcycle
      return 2.0;
    default:  // car, bus, truck and anything else: a rounded rectangle
      return 4.0;
  }
}

// Marks the shape prior of a box whose pixels are `box` (in `out`'s coordinates) in `out`
// (CV_8U) with `value`.
void DrawShape(const cv::Rect& box, int class_id, uint8_t value, cv::Mat* out) {
  const double p = ShapeExponent(class_id);
  const double cx = box.x + 0.5 * box.width;
  const double cy = box.y + 0.5 * box.height;
  const double hx = std::max(0.5 * box.width, 0.5);
  const double hy = std::max(0.5 * box.height, 0.5);
  for (int r = box.y; r < box.y + box.height; ++r) {
    uint8_t* row = out->ptr<uint8_t>(r);
    const double v = std::pow(std::abs((r + 0.5 - cy) / hy), p);
    for (int c = box.x; c < box.x + box.width; ++c) {
      const double u = std::pow(std::abs((c + 0.5 - cx) / hx), p);
      if (u + v <= 1.0) row[c] = value;
    }
  }
}

bool Finite(const cv::Rect2f& r) {
  return std::isfinite(r.x) && std::isfinite(r.y) && std::isfinite(r.width) &&
         std::isfinite(r.height) && r.width >= 0 && r.height >= 0;
}

// Restores OpenCV's thread-local RNG on scope exit. GrabCut seeds its colour models with
// k-means, which draws from that RNG: seeding it per box makes a box's mask a function of the
// box and the pixels alone, whatever ran before on the thread.
class ScopedRngSeed {
 public:
  explicit ScopedRngSeed(uint64_t seed) : saved_(cv::theRNG().state) {
    cv::theRNG().state = seed ? seed : 1;
  }
  ~ScopedRngSeed() { cv::theRNG().state = saved_; }
  ScopedRngSeed(const ScopedRngSeed&) = delete;
  ScopedRngSeed& operator=(const ScopedRngSeed&) = delete;

 private:
  uint64_t saved_;
};

// GrabCut of one box; on success `object` (box-sized CV_8U, 255 = object) is filled.
bool SegmentBox(const cv::Mat& bgr, const cv::Rect& box, int class_id,
                const BoxRefinementConfig& config, cv::Mat* object) {
  const cv::Rect image(0, 0, bgr.cols, bgr.rows);
  const int mx = int(std::lround(config.context * box.width));
  const int my = int(std::lround(config.context * box.height));
  const cv::Rect context =
      cv::Rect(box.x - mx, box.y - my, box.width + 2 * mx, box.height + 2 * my) & image;
  const double scale =
      std::min(1.0, double(config.max_side) / double(std::max(context.width, context.height)));
  cv::Mat small;
  cv::resize(bgr(context), small, cv::Size(), scale, scale, cv::INTER_AREA);
  if (small.cols < 4 || small.rows < 4) return false;
  // The box in `small`'s coordinates.
  const cv::Rect inner = cv::Rect(int(std::floor((box.x - context.x) * scale)),
                                  int(std::floor((box.y - context.y) * scale)),
                                  std::max(1, int(std::lround(box.width * scale))),
                                  std::max(1, int(std::lround(box.height * scale)))) &
                         cv::Rect(0, 0, small.cols, small.rows);
  cv::Mat labels(small.size(), CV_8U, cv::Scalar(cv::GC_BGD));
  labels(inner).setTo(cv::GC_PR_BGD);
  DrawShape(inner, class_id, cv::GC_PR_FGD, &labels);
  cv::Mat probable_object;
  cv::compare(labels, cv::GC_PR_FGD, probable_object, cv::CMP_EQ);
  const int foreground = cv::countNonZero(probable_object);
  const int background = int(labels.total()) - foreground;
  if (foreground < 8 || background < 8) return false;
  const uint64_t seed = (uint64_t(uint32_t(box.x)) << 48) ^ (uint64_t(uint32_t(box.y)) << 32) ^
                        (uint64_t(uint32_t(box.width)) << 16) ^ uint64_t(uint32_t(box.height));
  ScopedRngSeed rng(seed * 0x9E3779B97F4A7C15ull);
  try {
    cv::Mat bgd_model, fgd_model;
    cv::grabCut(small, labels, cv::Rect(), bgd_model, fgd_model, config.iterations,
                cv::GC_INIT_WITH_MASK);
  } catch (const cv::Exception&) {
    return false;  // degenerate colour models (e.g. a flat patch): the shape prior stands
  }
  // Object = GC_FGD (1) or GC_PR_FGD (3): the labels' lowest bit. (Plain functions, not
  // cv::MatExpr, whose lazily created operator objects live in uninstrumented OpenCV where
  // ThreadSanitizer cannot see their initialisation.)
  cv::Mat fg;
  cv::bitwise_and(labels, cv::Scalar(1), fg);
  fg.convertTo(fg, CV_8U, 255.0);
  cv::Mat full;
  cv::resize(fg, full, context.size(), 0, 0, cv::INTER_LINEAR);
  cv::threshold(full, full, 127, 255, cv::THRESH_BINARY);
  if (config.dilate_px > 0) {
    const int k = 2 * config.dilate_px + 1;
    cv::dilate(full, full, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(k, k)));
  }
  *object = full(box - context.tl()).clone();
  return true;
}

}  // namespace

const char* BoxRefinementName(BoxRefinement method) {
  switch (method) {
    case BoxRefinement::kNone:
      return "none";
    case BoxRefinement::kShape:
      return "shape";
    case BoxRefinement::kGrabCut:
      return "grabcut";
  }
  return "unknown";
}

Result<BoxRefinement> ParseBoxRefinement(const std::string& name) {
  for (BoxRefinement method :
       {BoxRefinement::kNone, BoxRefinement::kShape, BoxRefinement::kGrabCut}) {
    if (name == BoxRefinementName(method)) return method;
  }
  return Status::InvalidArgument("box refinement \"" + name + "\": use none, shape or grabcut");
}

Status ValidateBoxRefinementConfig(const BoxRefinementConfig& config) {
  if (config.method != BoxRefinement::kNone && config.method != BoxRefinement::kShape &&
      config.method != BoxRefinement::kGrabCut) {
    return Status::InvalidArgument("box_refinement.method " + std::to_string(int(config.method)) +
                                   " is not a refinement method");
  }
  if (!(config.context >= 0.0f && config.context <= 1.0f)) {
    return Status::InvalidArgument("box_refinement.context must be in [0, 1]");
  }
  if (config.max_side < 16 || config.max_side > 1024) {
    return Status::InvalidArgument("box_refinement.max_side must be in [16, 1024]");
  }
  if (config.iterations < 1 || config.iterations > 20) {
    return Status::InvalidArgument("box_refinement.iterations must be in [1, 20]");
  }
  if (!(config.min_fraction >= 0.0f && config.min_fraction < config.max_fraction &&
        config.max_fraction <= 1.0f)) {
    return Status::InvalidArgument("box_refinement needs 0 <= min_fraction < max_fraction <= 1");
  }
  if (config.dilate_px < 0 || config.dilate_px > 32) {
    return Status::InvalidArgument("box_refinement.dilate_px must be in [0, 32]");
  }
  return Status::Ok();
}

Result<BoxRefinementResult> RefineBoxesToMasks(const DynamicObjects& objects, const cv::Mat& image,
                                               int width, int height,
                                               const BoxRefinementConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateBoxRefinementConfig(config));
  if (width <= 0 || height <= 0) return Status::InvalidArgument("image size must be positive");
  if (!objects.mask.empty() && (objects.mask.type() != CV_8UC1 || objects.mask.cols != width ||
                                objects.mask.rows != height)) {
    return Status::InvalidArgument("mask must be CV_8U and " + std::to_string(width) + "x" +
                                   std::to_string(height));
  }
  if (!image.empty() && (image.cols != width || image.rows != height || image.depth() != CV_8U ||
                         (image.channels() != 1 && image.channels() != 3))) {
    return Status::InvalidArgument("image for box refinement must be 8-bit gray or BGR and " +
                                   std::to_string(width) + "x" + std::to_string(height));
  }
  for (size_t i = 0; i < objects.boxes.size(); ++i) {
    if (!Finite(objects.boxes[i].rect)) {
      return Status::InvalidArgument("boxes[" + std::to_string(i) + "] is not a finite rectangle");
    }
  }
  BoxRefinementResult out;
  if (config.method == BoxRefinement::kNone || objects.boxes.empty()) {
    out.objects = objects;
    for (const DynamicBox& box : objects.boxes) out.boxes.push_back({box, false, 1.0});
    return out;
  }
  cv::Mat mask(height, width, CV_8U, cv::Scalar(0));
  if (!objects.mask.empty()) cv::compare(objects.mask, 0, mask, cv::CMP_NE);
  cv::Mat bgr;
  if (config.method == BoxRefinement::kGrabCut && !image.empty()) {
    if (image.channels() == 3) {
      bgr = image;
    } else {
      cv::cvtColor(image, bgr, cv::COLOR_GRAY2BGR);
    }
  }
  for (const DynamicBox& box : objects.boxes) {
    BoxMask refined;
    refined.box = box;
    const cv::Rect pixels = BoxPixelRect(box.rect, width, height);
    if (pixels.area() == 0) {
      out.boxes.push_back(refined);
      continue;
    }
    cv::Mat object;
    if (!bgr.empty() && SegmentBox(bgr, pixels, box.class_id, config, &object)) {
      const double fraction = double(cv::countNonZero(object)) / double(pixels.area());
      if (fraction >= config.min_fraction && fraction <= config.max_fraction) {
        refined.segmented = true;
        refined.object_fraction = fraction;
        cv::Mat target = mask(pixels);
        target.setTo(255, object);
        out.boxes.push_back(refined);
        continue;
      }
    }
    cv::Mat shape(pixels.size(), CV_8U, cv::Scalar(0));
    DrawShape(cv::Rect(0, 0, pixels.width, pixels.height), box.class_id, 255, &shape);
    refined.object_fraction = double(cv::countNonZero(shape)) / double(pixels.area());
    cv::Mat target = mask(pixels);
    target.setTo(255, shape);
    out.boxes.push_back(refined);
  }
  out.objects.mask = mask;
  return out;
}

}  // namespace placedb
