// Shared helpers for tests: where the real data lives, the default vocabulary, dataset readers.
#pragma once

#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/features/orb_features.h"
#include "core/vocabulary/float_vocabulary.h"  // SiftVocabulary(): test_vocabulary.cc
#include "core/vocabulary/vocabulary.h"        // DefaultVocabulary() lives in test_vocabulary.cc
#include "tools/shared_data.h"

namespace placedb::testing {

using data::HaveSharedData;  // ../shared/data present
using data::SharedDir;       // ../shared (PLACEDB_SHARED_DIR), may not exist
std::string DefaultVocabularyPath();
// Loads the default vocabulary once per process (fails the test if it is missing).
std::shared_ptr<const Vocabulary> DefaultVocabulary();
// A vocabulary with the default's tree and one word weight changed: another checksum.
std::shared_ptr<const Vocabulary> OtherVocabulary();
// The SIFT vocabulary trained on Debian's sample images (tools/rgbd_data.h, fixture
// sift_vocabulary), loaded once; null (and the test failed) when it cannot be loaded.
std::shared_ptr<const FloatVocabulary> SiftVocabulary();

// A fresh empty directory under the system temp dir, removed at process exit.
std::string MakeTempDir(const std::string& prefix);

cv::Mat ReadGray(const std::string& path);  // fails the test if unreadable
// The bytes of a file (ReadWholeFile); fails the test and returns "" if it cannot be read.
std::string ReadFileBytes(const std::string& path);
// A loopback TCP port nothing listens on (bound, then released): for a server to start on, or
// for a client to fail to reach.
int UnusedLoopbackPort();

// CamVid (../shared/data/camvid).
struct CamVidFrame {
  std::string sequence;  // "0001TP", ...
  int frame = 0;         // video frame number (30 fps)
  std::string image_path;
  std::string label_path;
};
std::vector<CamVidFrame> CamVidFrames();  // sorted by sequence, then frame
// CamVid class ids that are dynamic objects: Car 8, Pedestrian 9, Bicyclist 10.
cv::Mat CamVidDynamicMask(const CamVidFrame& frame);  // CV_8U 255 = dynamic

// RTAB-Map loop (../shared/data/rtabmap-loop): frames 1..84 and the 84x84 ground truth.
using data::RtabmapFramePath;  // 1-based
cv::Mat RtabmapGroundTruth();  // data::RtabmapGroundTruth, failing the test unless it is 84x84

// Debian sample images (opencv-doc, darknet), as used for the default vocabulary.
using data::DebianSampleImages;

// ORB features of an image file with the given feature budget.
FeatureSet ExtractFile(const std::string& path, int max_features = 1000);

}  // namespace placedb::testing
