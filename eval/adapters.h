// Adapters: real datasets -> the harness's dataset format (eval/dataset.h, docs/evaluation.md).
// They point at the source images where they are (nothing is copied) and derive ground truth,
// masks, boxes and dynamic coverage from the source's own annotations.
#pragma once

#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/filter/dynamic_filter.h"
#include "eval/dataset.h"

namespace placedb::eval {

// ---- CamVid --------------------------------------------------------------------------------

// CamVid label ids of dynamic objects and the COCO classes they stand for:
// Car 8 -> car 2, Pedestrian 9 -> person 0, Bicyclist 10 -> bicycle 1.
inline constexpr int kCamVidCar = 8;
inline constexpr int kCamVidPedestrian = 9;
inline constexpr int kCamVidBicyclist = 10;
std::vector<int> CamVidDynamicLabels();  // {8, 9, 10}
int CamVidLabelToCoco(int label);        // -1 for a static label

struct CamVidFrame {
  std::string sequence;  // "0001TP", "0006R0", "0016E5", "Seq05VD"
  int frame = 0;         // video frame number at 30 fps ("f00930" -> 930)
  std::string stem;      // "0006R0_f00930": the image file's name without extension
  std::string image_path;
  std::string label_path;
};
// The frames of `camvid_dir` (images/SEQ_FRAME.jpg, labels/SEQ_FRAME.png), sorted by sequence
// then frame number. NOT_FOUND when the directory has no images/.
Result<std::vector<CamVidFrame>> ListCamVid(const std::string& camvid_dir);

// Boxes of the dynamic objects of a CamVid label map: the bounding rectangles of the
// 8-connected components of each dynamic label with at least `min_area` pixels, confidence 1.
std::vector<DynamicBox> BoxesFromLabels(const cv::Mat& labels, int min_area);

// One CamVid frame as a dataset entry: absolute image path, the label map as mask (with
// mask_values 8, 9, 10), boxes from the label map, coverage, agent = sequence, sequence = frame
// number, timestamp = frame / 30 s.
Result<Entry> CamVidEntry(const CamVidFrame& frame, int min_box_area);

struct CamVidAdjacencyOptions {
  std::string camvid_dir;
  std::vector<std::string> sequences;  // empty = all
  int max_frames_per_sequence = 0;     // > 0: only the first N frames of each sequence
  int window_frames = 30;              // correct = same sequence, |frame difference| <= this
  int min_box_area = 20;
};
// Database = every other frame of each sequence (positions 0, 2, ...), queries = the frames in
// between; ground truth = the database frames of the same sequence within window_frames (1 s).
Result<Dataset> PrepareCamVidAdjacency(const CamVidAdjacencyOptions& options);

struct CamVidStop {
  std::string sequence;
  int first_begin, first_end;    // the first visit (database), frame numbers inclusive
  int second_begin, second_end;  // the second visit (queries)
};
// The two stops of ../shared/README.md: Seq05VD 01920-02250 vs 02520-02850, 0016E5 04830-05070
// vs 05430-05700.
std::vector<CamVidStop> DefaultCamVidStops();

struct CamVidStopsOptions {
  std::string camvid_dir;
  std::vector<CamVidStop> stops = DefaultCamVidStops();
  // Frames of the stop's sequence from first_begin - guard to second_end + guard that belong to
  // neither visit show the same place (the vehicle waits, approaches or leaves): they are left
  // out of the database entirely, so they are neither distractors nor ground truth.
  int guard_frames = 300;
  bool distractors = true;  // every other CamVid frame joins the database as a distractor
  int min_box_area = 20;
};
// Database = the first visit of every stop (+ distractors), queries = the second visits; ground
// truth of a query = every frame of the first visit of the same stop.
Result<Dataset> PrepareCamVidStops(const CamVidStopsOptions& options);

// ---- RTAB-Map loop ------------------------------------------------------------------------

struct RtabmapOptions {
  std::string directory;   // 1.jpg .. 84.jpg and ground_truth.bmp
  int database_last = 40;  // database = frames 1..database_last, queries = the rest
};
// Ground truth from ground_truth.bmp (row = query frame - 1, column = database frame - 1, 255 =
// same place). No masks or boxes (the corridor has none annotated): coverage is unknown (0).
Result<Dataset> PrepareRtabmap(const RtabmapOptions& options);

// ---- Generic folders ----------------------------------------------------------------------

struct FolderOptions {
  std::string database_dir;  // images (IsImageFile), in natural order
  std::string queries_dir;
  // CSV with columns `query,database`: file names (or stems) relative to the folders, one row
  // per matching pair. A query without rows has an empty ground truth.
  std::string ground_truth_csv;
  std::string database_masks_dir;  // optional: <stem>.png, non-zero = dynamic
  std::string queries_masks_dir;   // optional
  // Optional CSV `image,class,confidence,x,y,width,height` (image = database/NAME or
  // queries/NAME, NAME a file name or stem; class = COCO id or name): oracle boxes.
  std::string boxes_csv;
};
Result<Dataset> PrepareFolder(const FolderOptions& options);

}  // namespace placedb::eval
