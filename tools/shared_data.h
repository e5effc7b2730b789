// Where the data outside the repository is: ../shared (data and models; $PLACEDB_SHARED_DIR
// overrides the configured path) and Debian's own sample images (opencv-doc, darknet), which the
// default vocabularies are trained on. One place for the tests, the benchmarks, the evaluation and
// the vocabulary tools. Plain code: no GoogleTest, errors show as empty results.
#pragma once

#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace placedb::data {

std::string SharedDir();  // $PLACEDB_SHARED_DIR, else the configured ../shared; may not exist
bool HaveSharedData();    // SharedDir()/data is a directory

// RTAB-Map loop (SharedDir()/data/rtabmap-loop): frame paths (1-based) and the 84x84 ground
// truth, (i, j) = 255 when frames i+1 and j+1 show the same place (empty Mat when unreadable).
std::string RtabmapFramePath(int frame);
cv::Mat RtabmapGroundTruth();

// OpenCV's and darknet's sample images (.jpg, .png), sorted; empty when neither is installed.
std::vector<std::string> DebianSampleImages();

}  // namespace placedb::data
