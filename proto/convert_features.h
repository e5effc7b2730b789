// Features out: an agent's precomputed features (ORB or SIFT keypoints + descriptors) and a
// place's features as placedb.v1 messages. Only the engine's features module: the load tester
// links this (placedb_wire_features) without the rest of the engine. Features in are decoded and
// validated with the whole observation: proto/convert_frame.h.
#pragma once

#include <google/protobuf/repeated_ptr_field.h>

#include <vector>

#include "core/features/local_features.h"
#include "core/features/orb_features.h"
#include "core/features/sift_features.h"
#include "proto/placedb.pb.h"

namespace placedb::wire {

namespace v1 = ::placedb::v1;

void KeypointListToProto(const std::vector<Keypoint>& keypoints,
                         google::protobuf::RepeatedPtrField<v1::Keypoint>* out);  // appends
// Precomputed features as an agent sends them: 32-byte ORB descriptors, or 128 little-endian
// float32 per SIFT keypoint.
void FeaturesToProto(const FeatureSet& features, v1::Features* out);
void SiftFeaturesToProto(const FloatFeatureSet& features, v1::SiftFeatures* out);
// A place's features into the field of their family: `features` (ORB) or `sift_features`.
void PlaceFeaturesToProto(const LocalFeatures& features, v1::Place* out);

}  // namespace placedb::wire
