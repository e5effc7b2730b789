// Conversion of map configurations, statistics and match options between the placedb.v1 wire
// types and the core's. What arrives is validated before the core sees it: INVALID_ARGUMENT
// messages name the offending field as a path into the request ("config.depth.threshold_m: must
// be positive, got -1"), RESOURCE_EXHAUSTED messages name the limit. Every proto <-> core enum
// mapping of the API lives here; their names are proto/names.h.
#pragma once

#include <algorithm>
#include <cstdint>
#include <string>

#include "core/base/status.h"
#include "core/detect/detector.h"
#include "core/pipeline/place_database.h"
#include "core/storage/map_store.h"
#include "proto/placedb.pb.h"

namespace placedb::wire {

namespace v1 = ::placedb::v1;

// What the service keeps per map besides the core's database config (in the map's own info,
// MapOptions::service_json: see server/backend/map_registry.h).
struct ServiceMapSettings {
  BoxSource box_source = BoxSource::kAgent;
  bool detection_enabled = true;
  // MapConfig.vocabulary_policy (issue 29): 0 = off.
  uint64_t adapt_after_descriptors = 0;
  double regrow_factor = 0;
  bool operator==(const ServiceMapSettings&) const = default;
};

// The vocabulary a new map will use: its kind fixes the map's feature type.
struct MapVocabulary {
  std::string name;  // for messages
  FeatureType feature_type = FeatureType::kOrb;
};

// Defaults for unset fields; INVALID_ARGUMENT "config.<field>: ..." for bad values (a
// feature_type the vocabulary cannot quantise: "config.feature_type: ..."), and
// RESOURCE_EXHAUSTED when the map's feature budget (config.orb.max_features for ORB maps,
// config.sift.max_features for SIFT maps) exceeds `max_descriptors_per_frame` (the server's
// limits.max_descriptors_per_frame). A SIFT max_features of 0 ("all") is taken as that limit.
// An UNSPECIFIED detection.box_source is agent here (the server picks its detector when it has
// one). `settings` receives the detection policy.
Result<MapOptions> MapOptionsFromProto(const v1::MapConfig& config,
                                       uint32_t max_descriptors_per_frame,
                                       const MapVocabulary& vocabulary,
                                       ServiceMapSettings* settings);
// Every effective value filled in (feature type, ORB, SIFT, depth, loop closure, ...): what
// MapOptionsFromProto turns back into the same options.
void MapConfigToProto(const MapOptions& options, const ServiceMapSettings& settings,
                      const std::string& vocabulary_name, v1::MapConfig* out);
void MapStatsToProto(const MapStats& stats, v1::MapStats* out);
void MapDamageToProto(const MapDamage& damage, v1::MapDamage* out);
void ScrubReportToProto(const ScrubReport& report, v1::ScrubReport* out);
// A map's vocabulary record (issue 29); `switching`: a switch is running. `out->map` is left
// to the caller.
void VocabularyRecordToProto(const VocabularyRecord& record, bool switching,
                             v1::MapVocabulary* out);
void VocabularySourceToProto(const VocabularySource& source, v1::VocabularySource* out);
// And back (cluster mode's records and shard answers): INVALID_ARGUMENT naming `field` for a
// checksum that is not 16 hex digits.
Result<VocabularySource> VocabularySourceFromProto(const v1::VocabularySource& source,
                                                   const std::string& field);
Result<VocabularyRecord> VocabularyRecordFromProto(const v1::MapVocabulary& record,
                                                   const std::string& field);

// The proto <-> core enum mappings. FromProto takes UNSPECIFIED as the default the proto
// documents; values outside the enum are INVALID_ARGUMENT naming `field`.
v1::FeatureType FeatureTypeToProto(FeatureType type);
v1::FilterMethod FilterToProto(FilterMethod method);
Result<FilterMethod> FilterFromProto(v1::FilterMethod method, const std::string& field);
v1::BoxRefinement BoxRefinementToProto(BoxRefinement method);
Result<BoxRefinement> BoxRefinementFromProto(v1::BoxRefinement method, const std::string& field);
v1::Scoring ScoringToProto(ScoringType scoring);
Result<ScoringType> ScoringFromProto(v1::Scoring scoring, const std::string& field);
v1::VerificationMode VerificationToProto(VerificationMode mode);
Result<VerificationMode> VerificationFromProto(v1::VerificationMode mode, const std::string& field);
v1::BoxSource BoxSourceToProto(BoxSource source);
Result<BoxSource> BoxSourceFromProto(v1::BoxSource source, const std::string& field);
v1::BandPolicy BandPolicyToProto(BandPolicy policy);
Result<BandPolicy> BandPolicyFromProto(v1::BandPolicy policy, const std::string& field);

// top_k 0 -> 10, capped at 1000; exclude_same_agent skips `agent_id`'s places;
// include_correspondences as given.
// A vocabulary's learning options from a request that asks for one (v1::AdaptVocabularyRequest,
// cluster's LearnVocabularyRequest: the same four fields). 0 = the default; the tree's shape is
// clamped to 65536 so a huge value cannot overflow (the learner refuses what is out of range).
template <typename Request>
LearningOptions LearningOptionsFromProto(const Request& request) {
  LearningOptions options;
  if (request.seed() != 0) options.seed = request.seed();
  options.max_sample_descriptors = request.max_sample_descriptors();
  options.branching = int(std::min<uint32_t>(request.branching(), 1u << 16));
  options.depth = int(std::min<uint32_t>(request.depth(), 1u << 16));
  return options;
}

QueryOptions QueryOptionsFromProto(const v1::MatchOptions& options, const std::string& agent_id);

// A ListPlaces request as PlaceDatabase::ListPlacesBefore takes it.
struct PlaceListing {
  PlaceFilter filter;
  PlaceId before = 0;
  size_t limit = 100;
  // Ids examined per call, whatever the filter: the bound on one call's work (10 000 reader-lock
  // lookups take well under a millisecond), and why a page may be short with a next id.
  size_t max_examined = 10000;
};

// limit 0 -> 100. INVALID_ARGUMENT naming the field: limit over 1000, a negative timestamp, or
// to_timestamp_ns not after from_timestamp_ns when both are set.
Result<PlaceListing> PlaceListingFromProto(const v1::ListPlacesRequest& request);

}  // namespace placedb::wire
