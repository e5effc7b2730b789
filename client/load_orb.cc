// The load tester's --mode features extractor (client/commands/load.h): core's ExtractOrb with the
// map's ORB settings, installed before main() in every program that links this object (the
// OBJECT library placedb_load_orb). The one engine module the CLI's programs link: ORB, no
// storage and no detector.
#include <opencv2/core.hpp>

#include "client/commands/load.h"
#include "core/features/orb_features.h"
#include "proto/convert_features.h"

namespace placedb::client {

namespace {

OrbConfig OrbFromMap(const v1::OrbSettings& s) {
  OrbConfig orb;
  if (s.has_max_features()) orb.max_features = s.max_features();
  if (s.has_scale_factor()) orb.scale_factor = s.scale_factor();
  if (s.has_levels()) orb.levels = s.levels();
  if (s.has_edge_threshold()) orb.edge_threshold = s.edge_threshold();
  if (s.has_patch_size()) orb.patch_size = s.patch_size();
  if (s.has_fast_threshold()) orb.fast_threshold = s.fast_threshold();
  return orb;
}

Status ExtractLoadFeatures(const cv::Mat& gray, const v1::OrbSettings& settings,
                           v1::Features* out) {
  auto features = ExtractOrb(gray, OrbFromMap(settings));
  if (!features.ok()) return features.status();
  wire::FeaturesToProto(*features, out);
  return Status::Ok();
}

[[maybe_unused]] const bool installed = (SetLoadFeatureExtractor(&ExtractLoadFeatures), true);

}  // namespace

}  // namespace placedb::client
