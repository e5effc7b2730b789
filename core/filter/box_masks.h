// Monocular box refinement: from a detector's boxes to the objects' own pixels.
//
// A detector box is loose: on street data about half of its pixels lie on the object (the rest is
// road, wall or sky around a person's limbs, a car's roof line), and with the paper's
// keypoint-in-box rule every static descriptor in that slack is dropped with the object. The
// union of a frame's boxes can cover half again as much as its objects. RefineBoxesToMasks()
// turns each box into a mask of the object inside it, which dynamic_filter.h then uses like any
// mask (the input mask, if any, is kept as is):
//  - kShape: a class shape prior, no pixels needed (works with precomputed features): an ellipse
//    inscribed in the box for people and two-wheelers, a rounded rectangle (superellipse) for
//    vehicles. It only removes the box's corners.
//  - kGrabCut: colour segmentation of the box (OpenCV's GrabCut) on a small copy of the box with
//    a margin of context: the margin is certain background, the shape prior is probable object,
//    the box corners outside it probable background. A segmentation that keeps too little or
//    almost all of the box is not trusted and the shape prior stands instead. Needs the image;
//    without one (precomputed features) the shape prior is used.
// With depth, core/filter/depth_filter.h's RefineDynamicObjects() is the better refinement and runs
// instead (place_database.cc chooses).
#pragma once

#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/filter/dynamic_filter.h"

namespace placedb {

enum class BoxRefinement { kNone, kShape, kGrabCut };

const char* BoxRefinementName(BoxRefinement method);  // "none", "shape", "grabcut"
Result<BoxRefinement> ParseBoxRefinement(const std::string& name);

struct BoxRefinementConfig {
  // The default: measured as accurate as GrabCut in recognition (docs/evaluation.md) at 1 % of
  // its cost.
  BoxRefinement method = BoxRefinement::kShape;
  // GrabCut runs on the box plus this margin (a fraction of the box's side on each side, clipped
  // to the image), scaled so that its longer side is at most max_side pixels.
  float context = 0.15f;
  int max_side = 64;
  int iterations = 3;
  // A segmentation keeping less than min_fraction or more than max_fraction of the box's pixels
  // is not trusted: the shape prior is used for that box.
  float min_fraction = 0.15f;
  float max_fraction = 0.97f;
  // The segmented object is dilated by this many full-resolution pixels: silhouette edges and
  // the descriptors that straddle them are dynamic too.
  int dilate_px = 2;
};

Status ValidateBoxRefinementConfig(const BoxRefinementConfig& config);

struct BoxMask {
  DynamicBox box;
  bool segmented = false;      // kGrabCut's segmentation was used (false: the shape prior)
  double object_fraction = 0;  // of the box's pixels, marked dynamic
};

struct BoxRefinementResult {
  DynamicObjects objects;  // no boxes: their masks, united with the input mask
  std::vector<BoxMask> boxes;
};

// Refines every box of `objects` for a width x height frame. `image` (8-bit gray or BGR, width x
// height) may be empty: kGrabCut then falls back to kShape. kNone returns `objects` unchanged
// (boxes stay boxes). INVALID_ARGUMENT for a bad config, a mask or image of the wrong size or
// type, or a box that is not a finite rectangle.
Result<BoxRefinementResult> RefineBoxesToMasks(const DynamicObjects& objects, const cv::Mat& image,
                                               int width, int height,
                                               const BoxRefinementConfig& config);

}  // namespace placedb
