#include "client/commands/enum_flags.h"

#include <cctype>

namespace placedb::client {

// Box refinement spellings from the generated enum's own names (BOX_REFINEMENT_GRABCUT ->
// "grabcut"), so a value added to the proto is a CLI value too.
const std::map<std::string, v1::BoxRefinement>& BoxRefinementNames() {
  static const std::map<std::string, v1::BoxRefinement> names = [] {
    std::map<std::string, v1::BoxRefinement> out;
    const std::string prefix = "BOX_REFINEMENT_";
    for (int i = v1::BoxRefinement_MIN; i <= v1::BoxRefinement_MAX; ++i) {
      if (!v1::BoxRefinement_IsValid(i) || i == v1::BOX_REFINEMENT_UNSPECIFIED) continue;
      std::string name = v1::BoxRefinement_Name(v1::BoxRefinement(i)).substr(prefix.size());
      for (char& c : name) c = char(std::tolower(static_cast<unsigned char>(c)));
      out.emplace(name, v1::BoxRefinement(i));
    }
    return out;
  }();
  return names;
}

// Short CLI spellings of the API enums.
const std::map<std::string, v1::FilterMethod>& FilterNames() {
  static const std::map<std::string, v1::FilterMethod> names = {
      {"none", v1::FILTER_METHOD_NONE},
      {"keypoint_in_box", v1::FILTER_METHOD_KEYPOINT_IN_BOX},
      {"corner_distance", v1::FILTER_METHOD_CORNER_DISTANCE},
      {"exact_coverage", v1::FILTER_METHOD_EXACT_COVERAGE}};
  return names;
}
const std::map<std::string, v1::Scoring>& ScoringNames() {
  static const std::map<std::string, v1::Scoring> names = {
      {"l1", v1::SCORING_L1},
      {"l2", v1::SCORING_L2},
      {"chi_square", v1::SCORING_CHI_SQUARE},
      {"kl", v1::SCORING_KL},
      {"bhattacharyya", v1::SCORING_BHATTACHARYYA},
      {"dot_product", v1::SCORING_DOT_PRODUCT}};
  return names;
}
const std::map<std::string, v1::VerificationMode>& VerifyNames() {
  static const std::map<std::string, v1::VerificationMode> names = {
      {"disabled", v1::VERIFICATION_MODE_DISABLED},
      {"direct", v1::VERIFICATION_MODE_DIRECT_INDEX},
      {"exhaustive", v1::VERIFICATION_MODE_EXHAUSTIVE}};
  return names;
}
const std::map<std::string, v1::FeatureType>& FeatureTypeNames() {
  static const std::map<std::string, v1::FeatureType> names = {{"orb", v1::FEATURE_TYPE_ORB},
                                                               {"sift", v1::FEATURE_TYPE_SIFT}};
  return names;
}
const std::map<std::string, v1::BandPolicy>& BandPolicyNames() {
  static const std::map<std::string, v1::BandPolicy> names = {
      {"fixed", v1::BAND_POLICY_FIXED},
      {"nearest_layer", v1::BAND_POLICY_NEAREST_LAYER},
      {"appeared_layer", v1::BAND_POLICY_APPEARED_LAYER}};
  return names;
}
const std::map<std::string, v1::BoxSource>& BoxSourceNames() {
  static const std::map<std::string, v1::BoxSource> names = {{"agent", v1::BOX_SOURCE_AGENT},
                                                             {"server", v1::BOX_SOURCE_SERVER},
                                                             {"both", v1::BOX_SOURCE_BOTH}};
  return names;
}

}  // namespace placedb::client
