// What a detector reports and the filter consumes: the dynamic objects of one frame, as boxes
// (COCO class, confidence) and/or a pixel mask. Agents may send these instead of frames.
#pragma once

#include <opencv2/core.hpp>
#include <vector>

namespace placedb {

struct DynamicBox {
  int class_id = -1;        // COCO id (person 0, bicycle 1, car 2, motorcycle 3, bus 5, truck 7)
  float confidence = 1.0f;  // detector score in [0, 1]
  cv::Rect2f rect;          // full-resolution pixels; may extend past the image, it is clipped
};

// What is known about the dynamic objects of one frame. Either part may be empty.
struct DynamicObjects {
  std::vector<DynamicBox> boxes;
  cv::Mat mask;  // optional CV_8U, image-sized; non-zero = dynamic pixel
};

}  // namespace placedb
