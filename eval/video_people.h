// The hard revisits' second source of objects (eval/revisits.h): people segmented out of a
// fixed-camera video.
#pragma once

#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"

namespace placedb::eval {

// People walking past a fixed camera, cut out by background subtraction: a per-pixel temporal
// median background over every `median_every`-th frame, |frame - background| (largest channel)
// above `threshold` except cast shadows (every channel darker than the background by a similar
// ratio), morphological open then close, holes filled, one pixel eroded off the outline (it
// blends with the ground), then the connected components of person-like size and shape (taller
// than wide, not touching the frame border) of every `every`-th frame whose height is within
// `max_height_deviation` of the height a person has where their feet are (a line fitted over
// all components: not two people one behind the other, not half a person). Each cutout's mask
// is exactly the shape that is pasted.
struct VideoPeopleOptions {
  int median_every = 5;
  int every = 15;
  int threshold = 30;
  int min_area = 500;       // pixels
  int min_height = 45;      // pixels
  double min_aspect = 1.7;  // height / width (lower: two people side by side)
  double max_aspect = 4.5;
  double min_fill = 0.35;  // area / bounding-box area
  // A foreground pixel is a shadow when every channel's frame / background ratio is within
  // [min, max] and the ratios differ by at most `spread`.
  double shadow_min_ratio = 0.35;
  double shadow_max_ratio = 0.92;
  double shadow_max_spread = 0.12;
  double max_height_deviation = 0.2;  // 0 = no height check
};
struct VideoCutout {
  std::string name;  // "vtest_f00300#2"
  int frame = 0;
  cv::Rect rect;  // in the video frame
  cv::Mat patch;  // BGR crop of rect
  cv::Mat mask;   // CV_8U 255 = the person, within rect
};
// NOT_FOUND when the video cannot be opened (the message names Debian's opencv-doc).
Result<std::vector<VideoCutout>> SegmentVideoPeople(const std::string& video_path,
                                                    const VideoPeopleOptions& options = {});

}  // namespace placedb::eval
