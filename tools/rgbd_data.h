// Data access shared by the RGB-D tests, the SIFT vocabulary tool and the RGB-D benchmark:
// ../shared/data readers (rgbd-people, slambook2-rgbd, rtabmap-loop) and the SIFT vocabulary
// trained on Debian's sample images only (opencv-doc, darknet), never on evaluation data.
// No GoogleTest here: errors come back as Status values.
#pragma once

#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/features/sift_features.h"
#include "core/filter/depth_filter.h"
#include "core/vocabulary/float_vocabulary.h"
#include "tools/shared_data.h"

namespace placedb::rgbd {

using data::HaveSharedData;
using data::SharedDir;  // $PLACEDB_SHARED_DIR or the configured ../shared

struct RgbdFrame {
  std::string name;        // "test1/1534837737.203029" or "slambook/1"
  std::string image_path;  // colour
  std::string depth_path;  // 16-bit, millimetres
};

// rgbd-people: 8 frames 640x480 in sequence order (test1..test4, by timestamp).
std::vector<RgbdFrame> RgbdPeopleFrames();
// slambook2-rgbd: 5 frames of a static room, 1..5.
std::vector<RgbdFrame> SlambookFrames();
// The slambook2 RGB-D camera (its chapter 5 intrinsics), depth in millimetres.
CameraIntrinsics SlambookIntrinsics();

// rtabmap-loop frame paths (1-based) and its 84x84 ground truth (empty Mat when unreadable).
using data::RtabmapFramePath;
using data::RtabmapGroundTruth;

// OpenCV's and darknet's sample images (the default vocabulary's training set), sorted.
using data::DebianSampleImages;

// Where the YOLOX model is (configured models dir, else ../shared/models), or "" if absent.
std::string YoloxModelPath();

// Reads a 16-bit depth image and converts it to metres (CV_32F, 0 = invalid).
Result<cv::Mat> ReadDepthMetres(const std::string& path, const DepthFormat& format = {});

struct SiftVocabularyOptions {
  int branching = 10;
  int depth = 4;
  uint64_t seed = 1;
  int threads = 2;
  int features_per_image = 1000;
};

// Trains on every Debian sample image (each at full size and at half size).
Result<std::shared_ptr<const FloatVocabulary>> TrainDebianSiftVocabulary(
    const SiftVocabularyOptions& options, size_t* descriptors_used = nullptr);

// The configured SIFT vocabulary path (PLACEDB_SIFT_VOCABULARY or the build default).
std::string SiftVocabularyPath();
// Loads `path`; when it is missing or does not load, trains with `options` and saves it there.
Result<std::shared_ptr<const FloatVocabulary>> LoadOrTrainSiftVocabulary(
    const std::string& path, const SiftVocabularyOptions& options = {});

// ---- A person walking up to the camera, for Algorithm 1 -----------------------------------

// The front-facing person of rgbd-people test2 (second frame): colour, depth (metres), mask of
// the largest connected region nearer than 2 m, and its median depth. Empty without the data.
struct PersonSprite {
  cv::Mat bgr, metres, mask;
  float depth = 0;
};
PersonSprite LoadPersonSprite();

struct Composite {
  cv::Mat bgr, metres, person;  // person: pixels where the person is visible (255)
};
// The room (colour + depth in metres, with ~0.5 % depth jitter and a little image noise from
// `rng`) with the person at distance z (metres; z <= 0: no person), scaled about the principal
// point (z0 / z, depths shifted by z - z0) and composited by z-buffer.
Composite ComposePerson(const PersonSprite& sprite, const cv::Mat& room_bgr,
                        const cv::Mat& room_metres, const CameraIntrinsics& k, double z,
                        cv::RNG* rng);

}  // namespace placedb::rgbd
