// Binary encodings of what a map persists. Every value starts with a one-byte format version so
// records can evolve; decoding is bounds-checked and returns CORRUPTION, never reads past the
// end or trusts a length. Keys are big-endian so RocksDB's byte order is numeric order.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "core/base/status.h"
#include "core/features/local_features.h"
#include "core/pipeline/place_database.h"
#include "core/thumbnail/thumbnail.h"
#include "core/vocabulary/bow.h"

namespace placedb {

// Place-id keys: 4 bytes big-endian.
std::string PlaceKey(PlaceId id);
Result<PlaceId> DecodePlaceKey(std::string_view key);
// 8-byte big-endian keys (invalid-observation log).
std::string U64Key(uint64_t value);
Result<uint64_t> DecodeU64Key(std::string_view key);

// Version 2 (written): counts include depth_removed. Version 1 (read): no depth_removed (0).
std::string EncodePlaceRecord(const PlaceRecord& record);
Result<PlaceRecord> DecodePlaceRecord(std::string_view bytes);

// BoW: word ids delta-coded as varints, weights as float32 (version 1). A map whose vocabulary
// was adapted (issue 29) keeps each place's direct index of that vocabulary beside its vector
// (version 2: the vector, then the direct index as in the features value): the one in the
// features value belongs to the vocabulary the place was stored with.
std::string EncodeBow(const BowVector& bow);
std::string EncodeBowWithDirect(const BowVector& bow, const DirectIndex& direct);
// Either version; `direct` (optional) receives the direct index of a version-2 value, nullopt
// for version 1.
Status DecodeBowValue(std::string_view bytes, BowVector* bow, std::optional<DirectIndex>* direct);
Result<BowVector> DecodeBow(std::string_view bytes);  // either version, the vector only
// Whether every feature the direct index names is below `features` (a version-2 value's index
// is checked against its place's features once both are read).
bool DirectIndexFits(const DirectIndex& direct, size_t features);

// SC keypoints, descriptors and the direct index (what verification needs), ORB maps:
// 32-byte binary descriptors. Version 1 without geometry; a place with a camera or keypoint
// depths (issue 32) is version 2, the geometry appended: flags, the camera, one float32 depth per
// keypoint. Both versions decode; `geometry` (optional) receives it (empty for version 1). A
// stored camera that fails Camera::Validate, or a negative or non-finite depth, is CORRUPTION.
std::string EncodeFeatures(const FeatureSet& features, const DirectIndex& direct,
                           const FrameGeometry& geometry = {});
Status DecodeFeatures(std::string_view bytes, FeatureSet* features, DirectIndex* direct,
                      FrameGeometry* geometry = nullptr);

// The same for SIFT maps: keypoints as for ORB, then 128 float32 (little-endian) per keypoint,
// then the direct index (and the geometry in version 2). Their own version bytes (0x81, 0x82), so
// neither decoder takes the other's payload.
std::string EncodeFloatFeatures(const FloatFeatureSet& features, const DirectIndex& direct,
                                const FrameGeometry& geometry = {});
Status DecodeFloatFeatures(std::string_view bytes, FloatFeatureSet* features, DirectIndex* direct,
                           FrameGeometry* geometry = nullptr);

// A map's features value, by the features' family (EncodeFeatures or EncodeFloatFeatures), and
// back: `type` is the map's feature type, so a payload of the other family is CORRUPTION.
std::string EncodeLocalFeatures(const LocalFeatures& features, const DirectIndex& direct,
                                const FrameGeometry& geometry = {});
Status DecodeLocalFeatures(std::string_view bytes, FeatureType type, LocalFeatures* features,
                           DirectIndex* direct, FrameGeometry* geometry = nullptr);

// Map configuration as JSON (readable with `ldb`, tolerant of added fields). Format 2 adds
// feature_type, sift, depth and loop_closure; a missing key takes its default, so format-1
// configs (ORB maps made before RGB-D) decode unchanged. A value of the wrong type is
// CORRUPTION naming its key; a value out of range is INVALID_ARGUMENT naming it.
std::string EncodeDatabaseConfig(const DatabaseConfig& config);
Result<DatabaseConfig> DecodeDatabaseConfig(std::string_view json);

// An invalid observation kept as metadata only. Version 2 (written) carries depth_removed;
// version 1 is still read.
struct InvalidObservation {
  uint64_t serial = 0;  // order of arrival in this map
  PlaceMetadata metadata;
  FrameCounts counts;
  std::vector<DynamicBox> boxes_used;
  std::string reason;
};
std::string EncodeInvalidObservation(const InvalidObservation& observation);
Result<InvalidObservation> DecodeInvalidObservation(std::string_view bytes);

// A place's thumbnail (version 1): width, height, source width and height (varints), the dropped
// keypoints (count, then 21 bytes each as in the features value), the JPEG (length, bytes). The
// decoder checks every length, that nothing follows, that the sizes are sane (1..1024, within
// the source, source sides up to 2^20) and that the JPEG's header says width x height: CORRUPTION
// otherwise.
std::string EncodeThumbnail(const Thumbnail& thumbnail);
Result<Thumbnail> DecodeThumbnail(std::string_view bytes);

}  // namespace placedb
