// Image bytes through the decode path the service uses for them (wire::DecodeObservation, which
// reads the PNG/JPEG header (core/decode), checks the pixel limit, then decodes). The first byte
// picks the field: the frame (encoded_image, grayscale or colour for server-side detection), the
// dynamic mask PNG, or the 16-bit depth PNG; for the last two the frame is an empty feature set of
// the size the image's header states, so size checks pass and the decoder runs. Invariants: no
// crash; errors name the field or limit; decoded images respect the limits and the header's pixel
// count (the limit is checked on the header before decoding, so the two must agree).
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/decode/image_decoder.h"
#include "proto/convert_frame.h"
#include "proto/placedb.pb.h"
#include "tests/fuzz/fuzz_support.h"
#include "tests/fuzz/observation_checks.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  if (size == 0) return 0;
  const std::string bytes(reinterpret_cast<const char*>(data) + 1, size - 1);
  const auto header = ReadImageInfo({data + 1, size - 1});
  wire::v1::Observation observation;
  const int mode = data[0] % 4;
  bool color = false;
  switch (mode) {
    case 1:
      color = true;
      [[fallthrough]];
    case 0: {
      observation.mutable_encoded_image()->set_data(bytes);
      auto decoded =
          wire::DecodeObservation(observation, fuzz::kFuzzFrameLimits, color, "observation");
      if (decoded.ok()) {
        PLACEDB_FUZZ_CHECK(header.ok(), "an image without a readable header decoded");
        const cv::Mat& image = decoded->observation.image;
        PLACEDB_FUZZ_CHECK(uint64_t(image.cols) * uint64_t(image.rows) ==
                               uint64_t(header->width) * uint64_t(header->height),
                           "decoded " + std::to_string(image.cols) + "x" +
                               std::to_string(image.rows) + " but the header says " +
                               std::to_string(header->width) + "x" +
                               std::to_string(header->height));
      }
      break;
    }
    case 2:
    case 3: {
      if (!header.ok()) return 0;  // no frame size to pair the mask or depth with
      wire::v1::Features* frame = observation.mutable_features();
      frame->set_image_width(uint32_t(header->width));
      frame->set_image_height(uint32_t(header->height));
      if (mode == 2) {
        observation.set_dynamic_mask_png(bytes);
      } else {
        observation.mutable_depth()->set_png16(bytes);
      }
      break;
    }
  }
  fuzz::DecodeAndCheck(observation, color);
  return 0;
}
