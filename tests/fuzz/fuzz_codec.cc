// Every decoder of core/storage/codec.h on arbitrary bytes (the first byte picks the decoder):
// no crash, no sanitizer report, and for what decodes, a canonical round trip: encoding the
// decoded value and decoding that again succeeds and encodes to the same bytes (a stored record
// read back and rewritten is not changed by the rewrite).
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "core/storage/codec.h"
#include "tests/fuzz/fuzz_support.h"

namespace placedb {
namespace {

using fuzz::Fail;

// Decode(Encode(value)) must succeed and re-encode to the same bytes.
template <typename Decode, typename Encode>
void CheckRoundTrip(const char* name, const std::string& encoded, Decode decode, Encode encode) {
  auto again = decode(encoded);
  if (!again.ok()) Fail(std::string(name) + ": its own encoding does not decode", again.status());
  if (encode(*again) != encoded) Fail(std::string(name) + ": re-encoding changed the bytes");
}

void FuzzKeys(std::string_view bytes) {
  if (auto id = DecodePlaceKey(bytes); id.ok()) {
    PLACEDB_FUZZ_CHECK(PlaceKey(*id) == bytes, "PlaceKey(DecodePlaceKey(key)) != key");
  }
  if (auto value = DecodeU64Key(bytes); value.ok()) {
    PLACEDB_FUZZ_CHECK(U64Key(*value) == bytes, "U64Key(DecodeU64Key(key)) != key");
  }
}

void FuzzPlaceRecord(std::string_view bytes) {
  auto record = DecodePlaceRecord(bytes);
  if (!record.ok()) return;
  CheckRoundTrip("PlaceRecord", EncodePlaceRecord(*record), DecodePlaceRecord,
                 [](const PlaceRecord& r) { return EncodePlaceRecord(r); });
}

void FuzzBow(std::string_view bytes) {
  auto bow = DecodeBow(bytes);
  if (!bow.ok()) return;
  CheckRoundTrip("BowVector", EncodeBow(*bow), DecodeBow,
                 [](const BowVector& b) { return EncodeBow(b); });
}

void FuzzFeatures(std::string_view bytes) {
  FeatureSet features;
  DirectIndex direct;
  FrameGeometry geometry;  // a version-2 value's camera and depths (issue 32)
  if (!DecodeFeatures(bytes, &features, &direct, &geometry).ok()) return;
  const std::string encoded = EncodeFeatures(features, direct, geometry);
  FeatureSet features2;
  DirectIndex direct2;
  FrameGeometry geometry2;
  if (Status s = DecodeFeatures(encoded, &features2, &direct2, &geometry2); !s.ok()) {
    Fail("FeatureSet: its own encoding does not decode", s);
  }
  PLACEDB_FUZZ_CHECK(EncodeFeatures(features2, direct2, geometry2) == encoded,
                     "FeatureSet: re-encoding changed the bytes");
}

void FuzzFloatFeatures(std::string_view bytes) {
  FloatFeatureSet features;
  DirectIndex direct;
  FrameGeometry geometry;
  if (!DecodeFloatFeatures(bytes, &features, &direct, &geometry).ok()) return;
  const std::string encoded = EncodeFloatFeatures(features, direct, geometry);
  FloatFeatureSet features2;
  DirectIndex direct2;
  FrameGeometry geometry2;
  if (Status s = DecodeFloatFeatures(encoded, &features2, &direct2, &geometry2); !s.ok()) {
    Fail("FloatFeatureSet: its own encoding does not decode", s);
  }
  PLACEDB_FUZZ_CHECK(EncodeFloatFeatures(features2, direct2, geometry2) == encoded,
                     "FloatFeatureSet: re-encoding changed the bytes");
}

void FuzzLocalFeatures(std::string_view bytes, FeatureType type) {
  LocalFeatures features;
  DirectIndex direct;
  FrameGeometry geometry;
  if (!DecodeLocalFeatures(bytes, type, &features, &direct, &geometry).ok()) return;
  PLACEDB_FUZZ_CHECK(features.type() == type, "LocalFeatures: decoded the other family");
  const std::string encoded = EncodeLocalFeatures(features, direct, geometry);
  LocalFeatures features2;
  DirectIndex direct2;
  FrameGeometry geometry2;
  if (Status s = DecodeLocalFeatures(encoded, type, &features2, &direct2, &geometry2); !s.ok()) {
    Fail("LocalFeatures: its own encoding does not decode", s);
  }
  PLACEDB_FUZZ_CHECK(EncodeLocalFeatures(features2, direct2, geometry2) == encoded,
                     "LocalFeatures: re-encoding changed the bytes");
}

void FuzzDatabaseConfig(std::string_view bytes) {
  auto config = DecodeDatabaseConfig(bytes);
  if (!config.ok()) {
    PLACEDB_FUZZ_CHECK(config.status().code() == StatusCode::kCorruption ||
                           config.status().code() == StatusCode::kInvalidArgument,
                       "DatabaseConfig: unexpected error code");
    return;
  }
  CheckRoundTrip("DatabaseConfig", EncodeDatabaseConfig(*config), DecodeDatabaseConfig,
                 [](const DatabaseConfig& c) { return EncodeDatabaseConfig(c); });
}

void FuzzInvalidObservation(std::string_view bytes) {
  auto observation = DecodeInvalidObservation(bytes);
  if (!observation.ok()) return;
  CheckRoundTrip("InvalidObservation", EncodeInvalidObservation(*observation),
                 DecodeInvalidObservation,
                 [](const InvalidObservation& o) { return EncodeInvalidObservation(o); });
}

void FuzzThumbnail(std::string_view bytes) {
  auto thumbnail = DecodeThumbnail(bytes);
  if (!thumbnail.ok()) {
    PLACEDB_FUZZ_CHECK(thumbnail.status().code() == StatusCode::kCorruption,
                       "Thumbnail: a value that does not decode must be CORRUPTION");
    return;
  }
  CheckRoundTrip("Thumbnail", EncodeThumbnail(*thumbnail), DecodeThumbnail,
                 [](const Thumbnail& t) { return EncodeThumbnail(t); });
}

}  // namespace
}  // namespace placedb

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  if (size == 0) return 0;
  // A view of libFuzzer's exactly sized buffer: ASan sees any read past its end.
  const std::string_view payload(reinterpret_cast<const char*>(data) + 1, size - 1);
  switch (data[0] % 10) {
    case 0:
      FuzzKeys(payload);
      break;
    case 1:
      FuzzPlaceRecord(payload);
      break;
    case 2:
      FuzzBow(payload);
      break;
    case 3:
      FuzzFeatures(payload);
      break;
    case 4:
      FuzzFloatFeatures(payload);
      break;
    case 5:
      FuzzLocalFeatures(payload, FeatureType::kOrb);
      break;
    case 6:
      FuzzLocalFeatures(payload, FeatureType::kSift);
      break;
    case 7:
      FuzzDatabaseConfig(payload);
      break;
    case 8:
      FuzzInvalidObservation(payload);
      break;
    case 9:
      FuzzThumbnail(payload);
      break;
  }
  return 0;
}
