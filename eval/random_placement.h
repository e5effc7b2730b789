// Random placement, the hard revisits' way of pasting objects into a visit
// (RevisitOptions::random_placement, eval/revisits.h): objects stand on the ground of the warped
// background at a random column, sized by perspective, drawn far to near and hidden where a nearer
// object of the background stands. Internal to the revisit builder.
#pragma once

#include <opencv2/core.hpp>
#include <set>
#include <string>
#include <vector>

#include "core/detect/dynamic_objects.h"
#include "eval/revisit_rng.h"
#include "eval/revisits.h"

namespace placedb::eval {

// CamVid's ground labels: where a pasted object may stand.
inline constexpr int kCamVidRoad = 3;
inline constexpr int kCamVidPavement = 4;

// Where the horizon is, roughly: the first row whose ground (Road, Pavement) covers 2 % of the
// width (the street's far end), kept within [0.35, 0.75] of the height; half the height when
// there is no ground. Too low where something hides the far end: sizes below are bounded.
int HorizonRow(const cv::Mat& labels);

// An object to paste: a BGR patch, its binary shape, its COCO class and, for a CamVid object,
// where it stood in its own frame (its perspective).
struct Cutout {
  cv::Mat patch;  // BGR
  cv::Mat mask;   // CV_8U 255 = the object
  int area = 0;   // of mask
  int coco = 0;
  bool vehicle = false;  // stands on Road (cars, bicycles); people on Road or Pavement
  bool upright = false;  // a person (walking or cycling): about 1.7 m tall
  bool from_video = false;
  std::string name;
  int source_bottom = 0;   // CamVid: the row below the object's last row in its frame
  int source_horizon = 0;  // CamVid: HorizonRow of its frame
  bool cut_left = false, cut_right = false, cut_bottom = false;  // by its frame's edges
};

// What one visit's random placement pasted.
struct PasteResult {
  cv::Mat painted;                // CV_8U 255 = a pixel a pasted object changed
  std::vector<DynamicBox> boxes;  // the visible part of each pasted object
  std::string names;
  int objects = 0, video_objects = 0;  // visible
};

// Random placement of one visit (RevisitOptions::random_placement): plans objects until the
// coverage of `mask` (what is already marked) plus what they will change reaches the target,
// then draws them far to near, each hidden where a nearer object of the background stands.
PasteResult PasteAtRandom(cv::Mat& image, const cv::Mat& labels, const cv::Mat& background_dynamic,
                          const cv::Mat& mask, const std::vector<const Cutout*>& still,
                          const std::vector<const Cutout*>& video, std::set<const Cutout*>& used,
                          double target, const RevisitOptions& options, Rng& rng);

}  // namespace placedb::eval
