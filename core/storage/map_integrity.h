// Checking a map's places for damage: RecoverMap's audit of what is left of them. INTERNAL to
// core/storage, not part of the public API (defined in map_integrity.cc with PlaceMap's
// VerifyIntegrity and Scrub; used by data_directory.cc).
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "core/base/status.h"
#include "core/storage/map_storage.h"
#include "core/storage/map_store.h"

namespace placedb::detail {

// What RecoverMap's scan of a map's places finds: the places it can serve (record and BoW
// vector), and the parts lost.
struct PlaceAudit {
  uint64_t servable = 0;
  uint64_t records_lost = 0;   // a BoW vector (or features) without its record
  uint64_t bow_lost = 0;       // a record without its BoW vector
  uint64_t features_lost = 0;  // servable, but no features
  PlaceId first_without_features = 0;
  PlaceId last_without_features = 0;
  std::vector<PlaceId> unservable;  // the records_lost and bow_lost places, to drop
  // The ids no servable place has, below the highest servable one: [first, last] runs.
  std::vector<std::pair<PlaceId, PlaceId>> gaps;
  PlaceId highest = 0;  // the highest servable id

  bool clean() const { return records_lost + bow_lost + features_lost == 0; }
};

// The acknowledged place ids (up to `acked_max`) that `audit`'s map no longer serves, with its
// count and range: the ids from `floor` (the id floor: ids below it may have been removed, which
// leaves the same gap) that no servable place has. A repaired log can keep places after a lost
// one, so the lost ids are not always the last ones.
void CountLostPlaces(const PlaceAudit& audit, PlaceId floor, uint64_t acked_max, MapDamage* damage);

// Walks the keys of `places`, `bow` and `features` together (each in id order). RocksDB
// iterators read the values too: recovery reads the whole map once. A block that does not read
// is an error (CORRUPTION naming the file).
Result<PlaceAudit> AuditPlaces(MapStorage& storage);

// "N places lost their features (ids a..b): ..." and the dropped ones, for the damage reason.
std::string AuditText(const PlaceAudit& audit);

}  // namespace placedb::detail
