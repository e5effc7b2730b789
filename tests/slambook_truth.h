// slambook2-rgbd as the pose tests use it (relative_pose_test, match_pose_test): its camera and
// its ground-truth poses.
#pragma once

#include <fstream>
#include <vector>

#include "core/pose/camera.h"
#include "core/pose/relative_pose.h"
#include "tools/rgbd_data.h"

namespace placedb::testing {

// The slambook2 RGB-D camera (tools/rgbd_data.h), 640x480, no distortion.
inline Camera SlambookCamera() {
  const CameraIntrinsics k = rgbd::SlambookIntrinsics();
  return PinholeCamera(640, 480, k.fx, k.fy, k.cx, k.cy);
}

// pose.txt: one camera-to-world pose per frame, "x y z qx qy qz qw" (empty when unreadable).
inline std::vector<Transform> SlambookPoses() {
  std::ifstream in(rgbd::SharedDir() + "/data/slambook2-rgbd/pose.txt");
  std::vector<Transform> poses;
  double x, y, z, qx, qy, qz, qw;
  while (in >> x >> y >> z >> qx >> qy >> qz >> qw) {
    poses.push_back(TransformFromTranslationQuaternion({x, y, z}, {qx, qy, qz, qw}));
  }
  return poses;
}

}  // namespace placedb::testing
