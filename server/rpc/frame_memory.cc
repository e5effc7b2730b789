#include "server/rpc/frame_memory.h"

#include "core/decode/image_decoder.h"
#include "proto/convert_frame.h"

namespace placedb::server {

namespace {

// Working memory of extraction per pixel of the (gray) frame. ORB: OpenCV's 8-level pyramid with
// its borders and the blurred copy descriptors are computed on (~7 bytes per pixel), the static
// mask and FAST scores. SIFT (OpenCV 4.6 doubles the image first): 6 Gaussian + 5 DoG float
// images per octave, the first octave at 4x the pixels (176 bytes per pixel), x4/3 for the
// octaves after it.
constexpr uint64_t kOrbWorkPerPixel = 10;
constexpr uint64_t kSiftWorkPerPixel = 240;

uint64_t Pixels(const std::string& encoded) {
  auto header = ReadImageInfo({reinterpret_cast<const uint8_t*>(encoded.data()), encoded.size()});
  if (!header.ok()) return 0;
  return uint64_t(header->width) * uint64_t(header->height);
}

}  // namespace

uint64_t EstimateFrameBytes(const v1::Observation& observation, FeatureType feature_type,
                            bool color) {
  uint64_t bytes = observation.ByteSizeLong();  // the parsed message's strings
  uint64_t pixels = 0;                          // of the frame extraction runs on
  switch (observation.frame_case()) {
    case v1::Observation::kEncodedImage:
      pixels = Pixels(observation.encoded_image().data());
      bytes += pixels * (color ? 4 : 1);  // decoded (colour + its gray copy, or gray)
      break;
    case v1::Observation::kRawImage:
      pixels = uint64_t(observation.raw_image().width()) * observation.raw_image().height();
      bytes += pixels * (color ? 4 : 1) + observation.raw_image().data().size();  // Mat + gray
      break;
    case v1::Observation::kFeatures:
    case v1::Observation::kSiftFeatures:
      bytes += observation.ByteSizeLong();  // keypoints and descriptors decoded once more
      break;
    case v1::Observation::FRAME_NOT_SET:
      break;
  }
  bytes += pixels * (feature_type == FeatureType::kSift ? kSiftWorkPerPixel : kOrbWorkPerPixel);
  if (!observation.dynamic_mask_png().empty()) {
    bytes += 2 * Pixels(observation.dynamic_mask_png());  // decoded + the refined mask
  }
  if (observation.has_depth()) {
    const v1::DepthImage& depth = observation.depth();
    const uint64_t depth_pixels = depth.has_raw_float32() ? uint64_t(depth.raw_float32().width()) *
                                                                depth.raw_float32().height()
                                                          : Pixels(depth.png16());
    bytes += depth_pixels * 6;  // 16-bit decoded + float metres
  }
  return bytes;
}

}  // namespace placedb::server
