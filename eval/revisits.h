// The revisit builder: the paper's Synthia setting (the same place seen again with *different*
// dynamic objects) made from real CamVid frames.
//
// Places are CamVid frames with little dynamic coverage, chosen far apart in time and checked to
// be visually distinct (ORB + RANSAC against every place already chosen). Each place is visited
// `visits` times; every visit applies
//   - a small random homography (the viewpoint: a jittered inner quadrilateral of the frame is
//     mapped onto the whole frame, so no border is invented),
//   - real dynamic objects cut out of OTHER CamVid frames by their label masks (Car, Pedestrian,
//     Bicyclist connected components), pasted near their original image position (so cars stay
//     on the road) until the visit's dynamic coverage reaches a target drawn from
//     [min_coverage, max_coverage] (an object too large for what is left is scaled down, never
//     below half size),
//   - a photometric change (per-channel gain, bias, gamma, sensor noise).
// Each visit's mask is exact: the background's own dynamic pixels (warped) plus every pixel a
// pasted object changed. Boxes are the background's components and the pasted objects' rectangles.
// Visit 0 of every place goes to the database; visits 1.. are queries whose ground truth is the
// place's visit 0. Everything derives from `seed`: the same options give byte-identical files.
//
// The hard variant (HardRevisitOptions(), `placedb-eval prepare revisits-hard`) models a street
// visited twice whose parked cars and pedestrians are part of the place: backgrounds keep their
// own dynamic objects (up to 25 % coverage) in every visit and the oracle mask and boxes mark
// ONLY the pasted, changing objects; pasted objects come from other sequences and, half of them,
// from people segmented out of OpenCV's vtest.avi by background subtraction; they are placed at
// random on the ground (Road / Pavement labels of the warped background) with random scales and
// a perspective-consistent size; viewpoint and light change more.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "eval/dataset.h"
#include "eval/video_people.h"

namespace placedb::eval {

struct RevisitOptions {
  std::string camvid_dir;
  std::string out_dir;  // images/ and masks/ are written here; the dataset's directory
  int places = 60;
  int visits = 2;              // >= 2: visit 0 -> database, the others -> queries
  double min_coverage = 0.10;  // each visit's target coverage is uniform in [min, max], <= 0.6
  double max_coverage = 0.40;
  uint64_t seed = 1;
  // Backgrounds: at most this much dynamic coverage of their own.
  double max_background_coverage = 0.05;
  // Backgrounds: at least this fraction of Road + Pavement pixels (room to stand on for random
  // placement; 0 = any).
  double min_ground_fraction = 0;
  // Backgrounds of one sequence at least this many video frames apart (30 fps).
  int min_separation_frames = 150;
  // A candidate background sharing at least this many RANSAC inliers (ORB 500, fundamental
  // matrix) with an accepted one shows the same place and is skipped.
  int max_shared_inliers = 30;
  double viewpoint = 1.0;     // scales the homography jitter (0 = none)
  double photometric = 1.0;   // scales the photometric change (0 = none)
  int min_object_area = 300;  // pixels of a donor component
  // Donor objects come from other sequences, or from frames of the same sequence at least this
  // far from the background (so a visit never pastes the background's own cars back).
  int donor_exclusion_frames = 300;
  // Donor objects from other sequences only (donor_exclusion_frames is then moot).
  bool donors_from_other_sequences = false;
  int jpeg_quality = 95;

  // ---- What the oracle marks ----
  // true: the mask and boxes include the background's own dynamic objects (warped) besides the
  // pasted ones, and coverage counts both. false: they are part of the place (present in every
  // visit): the mask, boxes and coverage are the pasted objects' only, and the background's own
  // objects are listed in the entry's `source` text ("background objects (static here): ...").
  bool mask_background_objects = true;

  // ---- Placement ----
  // false: near the donor's original position (bottom kept, centre moved up to 15 % of the
  // width). true: at random on the ground of the warped background. A random scale in
  // [min_scale, max_scale] (clipped to fit the frame and the coverage still needed) sets the
  // object's size, and perspective its bottom row: the bottom's distance below the horizon (the
  // first row whose Road + Pavement labels cover 2 % of the width) is the object's height over
  // 1.1-1.4 for people (walking or cycling), over the height / distance ratio it had in its own
  // frame for vehicles (bounded to 0.6-2.5); an object cut by the bottom edge stays on it, one
  // cut by the left or right edge on that edge; otherwise a random column where it fits. The
  // bottom must be in the lower 3/4 of the frame, on Road (cars, cyclists) or Road / Pavement
  // (pedestrians). At most 40 % of an object is shared with other pasted objects or hidden by
  // nearer objects of the background; objects are drawn far to near (hidden where an object of
  // the background stands nearer); boxes are the visible part of each object.
  bool random_placement = false;
  double min_scale = 0.9;  // random scale of a CamVid donor object
  double max_scale = 1.1;

  // ---- A second donor source: people of a fixed-camera video (vtest.avi) ----
  // Empty = none. People are segmented by background subtraction (SegmentVideoPeople) and pasted
  // as COCO person at a height of [min, max] x the frame height (random_placement only).
  std::string video_people;
  double video_share = 0.5;  // fraction of the pasted objects drawn from the video
  double video_min_height = 0.15;
  double video_max_height = 0.60;

  // ---- Viewpoint and light (each scaled by `viewpoint` / `photometric`) ----
  // Inner quadrilateral corners: margin +- jitter of the width / height in from each edge.
  double viewpoint_margin = 0.08;
  double viewpoint_jitter = 0.05;
  double gain_range = 0.25;       // gain uniform in 1 +- this (+- 5 % per channel)
  double bias_range = 20;         // bias uniform in +- this (grey levels)
  double log_gamma_range = 0.22;  // gamma = exp(uniform +- this)
  double max_noise_sigma = 3;     // Gaussian sensor noise, sigma uniform in [0, this]
  double max_blur_sigma = 0;      // Gaussian blur, sigma uniform in [0, this] (0 = no blur)
};

// Debian's copy of OpenCV's vtest.avi (package opencv-doc).
inline constexpr const char* kDebianVtestPath = "/usr/share/doc/opencv-doc/examples/data/vtest.avi";

// The hard preset: backgrounds up to 25 % coverage (at least 22 % Road + Pavement) whose own
// objects stay in every visit and are
// not marked (mask_background_objects false), random placement at 0.5-1.6x, donors from other
// sequences only, half of the objects people from kDebianVtestPath, inner quadrilateral 5-20 %,
// gain 0.6-1.4, bias +-30, gamma exp(+-0.35), noise sigma 0-4, blur sigma 0-1.
RevisitOptions HardRevisitOptions();

// Per visit: what was asked and what was made.
struct VisitInfo {
  std::string id;
  int place = 0;
  int visit = 0;
  std::string background;  // CamVid stem
  double requested_coverage = 0;
  double measured_coverage = 0;  // of the written mask
  int objects = 0;               // pasted (visible)
  int video_objects = 0;         // of which people from the video
  int background_objects = 0;    // the background's own (marked only with
                                 // mask_background_objects)
  cv::Mat homography;            // the viewpoint: background pixel -> visit pixel (3x3, CV_64F)
};

struct RevisitResult {
  Dataset dataset;  // directory = out_dir; not yet saved (SaveDataset writes dataset.json)
  std::vector<VisitInfo> visits;
};

// INVALID_ARGUMENT for bad options, NOT_FOUND without CamVid, FAILED_PRECONDITION when fewer
// than `places` distinct backgrounds exist under the constraints (the message says how many),
// or when `video_people` is set but absent (the message names Debian's opencv-doc and
// --no-vtest).
Result<RevisitResult> BuildRevisits(const RevisitOptions& options);

}  // namespace placedb::eval
