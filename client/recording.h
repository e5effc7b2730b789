// Recordings as frames that carry their own capture times (never the wall clock), as the Python
// SDK's placedb.read_bag / read_tum read them (client/python/placedb/recordings.py):
//
//   - a ROS 1 bag (client/rosbag_reader.h): the colour frames of one topic, sensor_msgs/Image
//     (rgb8, bgr8, rgba8, bgra8, mono8 / 8UC1: sent as raw pixels, alpha dropped) or
//     sensor_msgs/CompressedImage (JPEG / PNG bytes as they are). Each frame's timestamp is its
//     header stamp (a stamp of 0: the bag's receive time, counted). A depth topic, registered to
//     the colour image: sensor_msgs/Image 16UC1 / mono16 (millimetres, sent as a 16-bit PNG,
//     scale 0.001) or 32FC1 (metres, raw float32, scale 1), or a CompressedImage holding a 16-bit
//     PNG (also image_transport's compressedDepth); each frame gets the depth image whose stamp is
//     nearest its own within max_offset (else none, counted). A sensor_msgs/CameraInfo topic: the
//     latest one read before a frame gives its Observation.camera (K, D, distortion model; a
//     rational_polynomial whose k4..k6 are 0 is plumb_bob; an unknown model gives no camera,
//     counted) and its depth's intrinsics (K). ROS 2 bags (MCAP, SQLite, rosbag2 folders) are
//     refused, saying so.
//   - a TUM RGB-D folder (rgb.txt, optional depth.txt and groundtruth.txt, "timestamp ..." lines,
//     '#' comments): rgb.txt's timestamps (decimal seconds, read exactly to the nanosecond) as
//     capture times; the depth image nearest each frame within max_offset (as a bag's; unlike
//     TUM's associate.py one depth image may serve two frames); the pose interpolated at the
//     frame's time between the two ground-truth samples around it when they are at most
//     max_pose_gap apart (position linearly, orientation by slerp), else the nearest sample within
//     max_offset, else none (counted). Depth PNGs are TUM's 5000 units per metre unless
//     depth_scale says otherwise.
//
// Everything a recording needs (topics and their types, list files, the files they name) is
// checked by Open(), before a frame is read.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "proto/placedb.pb.h"

namespace placedb::client {

namespace v1 = ::placedb::v1;

// TUM RGB-D's depth PNGs hold 5000 units per metre.
inline constexpr float kTumDepthScale = 1.0f / 5000.0f;

struct RecordingOptions {
  // Bags: the colour topic (required), the depth and camera-info topics ("" = none).
  std::string topic;
  std::string depth_topic;
  std::string camera_info_topic;
  double max_offset_s = 0.02;   // a frame and its depth (TUM: also its nearest pose)
  double max_pose_gap_s = 0.1;  // TUM: ground-truth samples interpolated across at most this
  float depth_scale = 0;        // metres per depth unit; 0 = the recording's own (see above)
  std::optional<v1::Intrinsics> intrinsics;  // sent with depth when the recording has none
};

// What one pass over a recording read.
struct RecordingStats {
  size_t frames = 0;               // colour frames handed out
  size_t depth_paired = 0;         // with a depth image within max_offset
  size_t depth_missing = 0;        // none within max_offset although the recording has depth
  size_t poses = 0;                // with a pose (TUM ground truth)
  size_t poses_missing = 0;        // outside the ground truth's times
  size_t cameras = 0;              // with a camera from the camera-info topic
  size_t camera_refused = 0;       // camera info of a distortion model placedb does not take
  std::string refused_model;       // that model
  size_t receive_time_stamps = 0;  // header stamp 0: the bag's receive time instead
  std::optional<int64_t> first_ns, last_ns;
};

struct RecordedFrame {
  size_t index = 0;  // 0-based among the recording's colour frames
  std::string name;  // "run.bag /camera/image_raw #3", "FOLDER/rgb/1305031102.175304.png"
  // The frame's image (encoded_image or raw_image), timestamp_ns, and, when the recording has
  // them, depth, camera and pose; agent and sequence are the caller's.
  v1::Observation observation;
};

class Recording {
 public:
  // Whether `path` is a recording rather than an image, list, video or image folder: a file that
  // starts like a ROS 1 or ROS 2 bag (or ends in .bag), a rosbag2 folder, or a folder holding
  // rgb.txt.
  static bool IsRecording(const std::string& path);
  // Null + *error naming the file, topic or line when it cannot be read as asked (an unknown
  // topic lists the bag's image topics; a ROS 2 bag says that it is one).
  static std::unique_ptr<Recording> Open(const std::string& path, const RecordingOptions& options,
                                         std::string* error);
  virtual ~Recording() = default;

  // "run.bag /camera/image_raw", "rgbd_dataset_freiburg1_xyz (TUM)".
  virtual std::string description() const = 0;
  // The colour frames the recording holds.
  virtual size_t expected_frames() const = 0;
  // The next frame: true with *error empty; true with *error set when this frame cannot be read
  // (frame->name says which; call again for the next); false at the end, with *error set when
  // the recording itself is damaged from here on.
  virtual bool Next(RecordedFrame* frame, std::string* error) = 0;
  const RecordingStats& stats() const { return stats_; }

 protected:
  void Count(const RecordedFrame& frame);
  RecordingStats stats_;
};

// Unix nanoseconds of decimal seconds ("1305031102.175304"), exactly; false when it is not one.
bool ParseSecondsToNs(const std::string& text, int64_t* ns);

// The pose at time t from samples sorted by time (see the TUM rules above); nullopt when none.
std::optional<v1::Pose> InterpolatePose(const std::vector<int64_t>& times,
                                        const std::vector<v1::Pose>& poses, int64_t t,
                                        int64_t max_offset_ns, int64_t max_gap_ns);

}  // namespace placedb::client
