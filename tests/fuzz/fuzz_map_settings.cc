// A map's stored settings: the service settings JSON (MapRegistry::DecodeSettings), the map
// info's nesting of the database config (DecodeDatabaseConfig) and service JSON, and the
// CreateMap configuration a client sends (MapOptionsFromProto). The first byte picks one.
// Invariants: no crash; whatever decodes re-encodes and decodes to the same value; options
// accepted from the wire pass the storage layer's own validation (CreateMap re-checks them).
#include <spdlog/spdlog.h>

#include <cstddef>
#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <string_view>
#include <utility>

#include "core/storage/codec.h"
#include "proto/convert_config.h"
#include "proto/placedb.pb.h"
#include "server/backend/map_registry.h"
#include "tests/fuzz/fuzz_support.h"

namespace placedb {
namespace {

using fuzz::Fail;
using server::MapRegistry;

void FuzzServiceSettings(const std::string& text) {
  const wire::ServiceMapSettings settings = MapRegistry::DecodeSettings("fuzz", text);
  const std::string encoded = MapRegistry::EncodeSettings(settings);
  PLACEDB_FUZZ_CHECK(MapRegistry::DecodeSettings("fuzz", encoded) == settings,
                     "service settings: decode(encode(settings)) != settings");
}

// What DataDirectory's map info holds: {"database": {...}, "service": "<json text>", ...}.
void FuzzMapInfo(const std::string& text) {
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (j.is_discarded() || !j.is_object()) return;
  if (auto it = j.find("database"); it != j.end()) {
    auto config = DecodeDatabaseConfig(it->dump());
    if (config.ok()) {
      const std::string encoded = EncodeDatabaseConfig(*config);
      auto again = DecodeDatabaseConfig(encoded);
      if (!again.ok()) Fail("database config: its own encoding does not decode", again.status());
      PLACEDB_FUZZ_CHECK(EncodeDatabaseConfig(*again) == encoded,
                         "database config: re-encoding changed the JSON");
    }
  }
  if (auto it = j.find("service"); it != j.end() && it->is_string()) {
    FuzzServiceSettings(it->get<std::string>());
  }
}

void FuzzCreateMap(std::string_view bytes, FeatureType type) {
  v1::CreateMapRequest request;
  if (!request.ParseFromArray(bytes.data(), int(bytes.size()))) return;
  constexpr uint32_t kMaxDescriptors = 2000;
  const wire::MapVocabulary vocabulary{.name = "default", .feature_type = type};
  wire::ServiceMapSettings settings;
  auto options =
      wire::MapOptionsFromProto(request.config(), kMaxDescriptors, vocabulary, &settings);
  if (!options.ok()) {
    const StatusCode code = options.status().code();
    PLACEDB_FUZZ_CHECK(
        code == StatusCode::kInvalidArgument || code == StatusCode::kResourceExhausted,
        "MapOptionsFromProto: unexpected error code " + options.status().ToString());
    return;
  }
  if (Status valid = ValidateDatabaseConfig(options->database); !valid.ok()) {
    Fail("MapOptionsFromProto accepted options the database refuses", valid);
  }
  // The effective configuration (GetMap's answer) must be accepted back, and be a fixed point
  // from then on. (Not after the first trip: the proto's float fields round the core's doubles,
  // e.g. depth.format.metres_per_unit 0.001.)
  auto trip = [&](const MapOptions& in, const wire::ServiceMapSettings& in_settings,
                  wire::ServiceMapSettings* out_settings) {
    v1::MapConfig effective;
    wire::MapConfigToProto(in, in_settings, vocabulary.name, &effective);
    auto out = wire::MapOptionsFromProto(effective, kMaxDescriptors, vocabulary, out_settings);
    if (!out.ok()) Fail("the effective map config is refused", out.status());
    return std::move(out).value();
  };
  wire::ServiceMapSettings settings2;
  wire::ServiceMapSettings settings3;
  const MapOptions options2 = trip(*options, settings, &settings2);
  const MapOptions options3 = trip(options2, settings2, &settings3);
  PLACEDB_FUZZ_CHECK(settings2 == settings && settings3 == settings,
                     "map config round trip changed the service settings");
  const std::string before = EncodeDatabaseConfig(options2.database);
  const std::string after = EncodeDatabaseConfig(options3.database);
  PLACEDB_FUZZ_CHECK(after == before, "map config round trip changed the database config from\n" +
                                          before + "\nto\n" + after);
  PLACEDB_FUZZ_CHECK(options3.store_invalid == options->store_invalid,
                     "map config round trip changed store_invalid");
}

}  // namespace
}  // namespace placedb

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  spdlog::set_level(spdlog::level::off);  // damaged settings are logged; not the point here
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  if (size == 0) return 0;
  const std::string_view payload(reinterpret_cast<const char*>(data) + 1, size - 1);
  switch (data[0] % 4) {
    case 0:
      FuzzServiceSettings(std::string(payload));
      break;
    case 1:
      FuzzMapInfo(std::string(payload));
      break;
    case 2:
      FuzzCreateMap(payload, FeatureType::kOrb);
      break;
    case 3:
      FuzzCreateMap(payload, FeatureType::kSift);
      break;
  }
  return 0;
}
