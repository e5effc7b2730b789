// Binary encodings of what a map persists. Every value starts with a one-byte format version so
// records can evolve; decoding is bounds-checked and returns CORRUPTION, never reads past the
// end or trusts a length. Keys are big-endian so RocksDB's byte order is numeric order.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include "core/bow.h"
#include "core/features.h"
#include "core/place_database.h"
#include "core/status.h"

namespace placedb {

// Place-id keys: 4 bytes big-endian.
std::string PlaceKey(PlaceId id);
Result<PlaceId> DecodePlaceKey(std::string_view key);
// 8-byte big-endian keys (invalid-observation log).
std::string U64Key(uint64_t value);
Result<uint64_t> DecodeU64Key(std::string_view key);

std::string EncodePlaceRecord(const PlaceRecord& record);
Result<PlaceRecord> DecodePlaceRecord(std::string_view bytes);

// BoW: word ids delta-coded as varints, weights as float32.
std::string EncodeBow(const BowVector& bow);
Result<BowVector> DecodeBow(std::string_view bytes);

// SC keypoints, descriptors and the direct index (what verification needs).
std::string EncodeFeatures(const FeatureSet& features, const DirectIndex& direct);
Status DecodeFeatures(std::string_view bytes, FeatureSet* features, DirectIndex* direct);

// Map configuration as JSON (readable with `ldb`, tolerant of added fields).
std::string EncodeDatabaseConfig(const DatabaseConfig& config);
Result<DatabaseConfig> DecodeDatabaseConfig(std::string_view json);

// An invalid observation kept as metadata only.
struct InvalidObservation {
  uint64_t serial = 0;  // order of arrival in this map
  PlaceMetadata metadata;
  FrameCounts counts;
  std::vector<DynamicBox> boxes_used;
  std::string reason;
};
std::string EncodeInvalidObservation(const InvalidObservation& observation);
Result<InvalidObservation> DecodeInvalidObservation(std::string_view bytes);

}  // namespace placedb
