#include "proto/convert_features.h"

#include <cstring>
#include <string>

namespace placedb::wire {

namespace {

// The keypoints of either family's message (both carry v1::Keypoint).
template <typename Out>
void KeypointsToProto(const std::vector<Keypoint>& keypoints, Out* out) {
  KeypointListToProto(keypoints, out->mutable_keypoints());
}

}  // namespace

void KeypointListToProto(const std::vector<Keypoint>& keypoints,
                         google::protobuf::RepeatedPtrField<v1::Keypoint>* out) {
  out->Reserve(out->size() + int(keypoints.size()));
  for (const Keypoint& k : keypoints) {
    v1::Keypoint* kp = out->Add();
    kp->set_x(k.x);
    kp->set_y(k.y);
    kp->set_size(k.size);
    kp->set_angle(k.angle);
    kp->set_response(k.response);
    kp->set_octave(k.octave);
  }
}

void FeaturesToProto(const FeatureSet& features, v1::Features* out) {
  out->set_image_width(uint32_t(features.image_width));
  out->set_image_height(uint32_t(features.image_height));
  KeypointsToProto(features.keypoints, out);
  std::string* bytes = out->mutable_descriptors();
  bytes->resize(features.descriptors.size() * size_t(Descriptor256::kBytes));
  for (size_t i = 0; i < features.descriptors.size(); ++i) {
    features.descriptors[i].ToBytes(reinterpret_cast<uint8_t*>(bytes->data()) +
                                    i * size_t(Descriptor256::kBytes));
  }
}

void SiftFeaturesToProto(const FloatFeatureSet& features, v1::SiftFeatures* out) {
  out->set_image_width(uint32_t(features.image_width));
  out->set_image_height(uint32_t(features.image_height));
  KeypointsToProto(features.keypoints, out);
  // 128 little-endian float32 per keypoint.
  std::string* bytes = out->mutable_descriptors();
  bytes->resize(features.descriptors.size() * sizeof(float));
  auto* p = reinterpret_cast<uint8_t*>(bytes->data());
  for (float v : features.descriptors) {
    uint32_t u = 0;
    std::memcpy(&u, &v, sizeof u);
    p[0] = uint8_t(u);
    p[1] = uint8_t(u >> 8);
    p[2] = uint8_t(u >> 16);
    p[3] = uint8_t(u >> 24);
    p += 4;
  }
}

void PlaceFeaturesToProto(const LocalFeatures& features, v1::Place* out) {
  if (const FeatureSet* orb = features.orb()) {
    FeaturesToProto(*orb, out->mutable_features());
  } else {
    SiftFeaturesToProto(*features.sift(), out->mutable_sift_features());
  }
}

}  // namespace placedb::wire
