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
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/status.h"
#include "eval/dataset.h"

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
  int jpeg_quality = 95;
};

// Per visit: what was asked and what was made.
struct VisitInfo {
  std::string id;
  int place = 0;
  int visit = 0;
  std::string background;  // CamVid stem
  double requested_coverage = 0;
  double measured_coverage = 0;  // of the written mask
  int objects = 0;               // pasted
};

struct RevisitResult {
  Dataset dataset;  // directory = out_dir; not yet saved (SaveDataset writes dataset.json)
  std::vector<VisitInfo> visits;
};

// INVALID_ARGUMENT for bad options, NOT_FOUND without CamVid, FAILED_PRECONDITION when fewer
// than `places` distinct backgrounds exist under the constraints (the message says how many).
Result<RevisitResult> BuildRevisits(const RevisitOptions& options);

}  // namespace placedb::eval
