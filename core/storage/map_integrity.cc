// A map's integrity: PlaceMap::VerifyIntegrity (the column families agree with each other and
// with the index), PlaceMap::Scrub (every place read and decoded, every SST block verified) and
// RecoverMap's audit of the places left (map_integrity.h).
#include "core/storage/map_integrity.h"

#include <rocksdb/convenience.h>
#include <rocksdb/db.h>

#include <algorithm>
#include <memory>

#include "core/base/parallel.h"

namespace placedb {

// The storage internals (map_storage.h) and their helpers, unqualified as in the rest of the
// module.
using namespace detail;

Status PlaceMap::VerifyIntegrity() const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  rocksdb::ReadOptions options;
  options.fill_cache = false;
  std::vector<std::unique_ptr<rocksdb::Iterator>> its;
  for (Cf cf : {kPlaces, kBow, kFeatures}) {
    its.emplace_back(storage_->db->NewIterator(options, storage_->cf(cf)));
    its.back()->SeekToFirst();
  }
  size_t count = 0;
  for (; its[0]->Valid(); ++count) {
    const std::string key = its[0]->key().ToString();
    for (size_t i = 1; i < its.size(); ++i) {
      if (!its[i]->Valid() || its[i]->key() != key) {
        return Status::Corruption("place " + its[0]->key().ToString(true) +
                                  " is not complete in every column family");
      }
    }
    auto record = DecodePlaceRecord(its[0]->value().ToStringView());
    if (!record.ok()) return record.status();
    auto bow = DecodeBow(its[1]->value().ToStringView());
    if (!bow.ok()) return bow.status();
    PlacePayload payload;
    PLACEDB_RETURN_IF_ERROR(DecodePayloadFeatures(info_.options.database.feature_type,
                                                  its[2]->value().ToStringView(), &payload)
                                .WithContext("place " + std::to_string(record->id)));
    if (payload.features.size() != record->counts.static_) {
      return Status::Corruption("place " + std::to_string(record->id) +
                                ": stored features disagree with its counts");
    }
    if (!database_->Get(record->id)) {
      return Status::Corruption("place " + std::to_string(record->id) +
                                " is stored but not indexed");
    }
    for (auto& it : its) it->Next();
  }
  for (auto& it : its) {
    if (it->Valid()) return Status::Corruption("a column family holds entries without a place");
    PLACEDB_RETURN_IF_ERROR(FromRocks(it->status(), "scanning"));
  }
  if (count != database_->Stats().places) {
    return Status::Corruption("index holds " + std::to_string(database_->Stats().places) +
                              " places, disk " + std::to_string(count));
  }
  // Statistics: the aggregates and place keys, each value decoding. A place's entry may
  // outlive the place only by a removal racing a merged frame's count (see CloseLoop).
  std::unique_ptr<rocksdb::Iterator> dynamics(
      storage_->db->NewIterator(options, storage_->cf(kDynamics)));
  for (dynamics->SeekToFirst(); dynamics->Valid(); dynamics->Next()) {
    const std::string where = "statistics of key " + dynamics->key().ToString(true);
    if (!IsAggregateKey(dynamics->key())) {
      PLACEDB_RETURN_IF_ERROR(DecodePlaceKey(dynamics->key().ToStringView()).status());
    }
    PLACEDB_RETURN_IF_ERROR(
        DecodeDynamics(dynamics->value().ToStringView()).status().WithContext(where));
  }
  PLACEDB_RETURN_IF_ERROR(FromRocks(dynamics->status(), "scanning statistics"));
  // Thumbnails: written and deleted in the place's own batches, so each belongs to a place.
  std::unique_ptr<rocksdb::Iterator> thumbnails(
      storage_->db->NewIterator(options, storage_->cf(kThumbnails)));
  for (thumbnails->SeekToFirst(); thumbnails->Valid(); thumbnails->Next()) {
    auto id = DecodePlaceKey(thumbnails->key().ToStringView());
    if (!id.ok()) return id.status().WithContext("thumbnail key");
    if (!database_->Get(*id)) {
      return Status::Corruption("a thumbnail of place " + std::to_string(*id) +
                                ", which does not exist");
    }
    PLACEDB_RETURN_IF_ERROR(DecodeThumbnail(thumbnails->value().ToStringView())
                                .status()
                                .WithContext("place " + std::to_string(*id)));
  }
  return FromRocks(thumbnails->status(), "scanning thumbnails");
}

Result<ScrubReport> PlaceMap::Scrub(int threads) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  auto relative = [&](const std::string& text) { return RelativeTo(text, path_, info_.name); };
  std::vector<rocksdb::LiveFileMetaData> files;
  storage_->db->GetLiveFilesMetaData(&files);
  const std::vector<PlaceId> places = database_->ListPlaces();
  const rocksdb::Options options(DatabaseOptions(""), rocksdb::ColumnFamilyOptions());
  rocksdb::ReadOptions verify;
  verify.fill_cache = false;
  verify.verify_checksums = true;
  const FeatureType type = info_.options.database.feature_type;

  // Tasks: one per live SST file (every block, whichever family), then runs of places (each
  // value read and decoded). Each task fills its own slot; the slots are joined in task order,
  // so the report does not depend on the thread count.
  constexpr size_t kPlacesPerTask = 256;
  const size_t place_tasks = (places.size() + kPlacesPerTask - 1) / kPlacesPerTask;
  struct Found {
    std::vector<ScrubReport::File> files;
    std::vector<ScrubReport::Place> places;
  };
  std::vector<Found> found(files.size() + place_tasks);
  auto check_file = [&](const rocksdb::LiveFileMetaData& file, Found* out) {
    const std::string file_path = file.db_path + file.name;
    const rocksdb::Status s =
        rocksdb::VerifySstFileChecksum(options, rocksdb::EnvOptions(), verify, file_path);
    if (!s.ok()) out->files.push_back({relative(file_path), relative(s.ToString())});
  };
  auto check_place = [&](PlaceId id, Found* out) {
    const std::string key = PlaceKey(id);
    std::string record_bytes, bow_bytes, feature_bytes;
    auto fail = [&](const std::string& reason) { out->places.push_back({id, relative(reason)}); };
    Status read =
        FromRocks(storage_->db->Get(verify, storage_->cf(kPlaces), key, &record_bytes), "record");
    if (!read.ok()) return fail(read.ToString());
    auto record = DecodePlaceRecord(record_bytes);
    if (!record.ok() || record->id != id) {
      return fail(record.ok() ? "record holds id " + std::to_string(record->id)
                              : "record: " + record.status().ToString());
    }
    read = FromRocks(storage_->db->Get(verify, storage_->cf(kBow), key, &bow_bytes), "BoW vector");
    if (!read.ok()) return fail(read.ToString());
    if (auto bow = DecodeBow(bow_bytes); !bow.ok()) {
      return fail("BoW vector: " + bow.status().ToString());
    }
    read = FromRocks(storage_->db->Get(verify, storage_->cf(kFeatures), key, &feature_bytes),
                     "features");
    if (!read.ok()) return fail(read.ToString());
    PlacePayload payload;
    if (Status decoded = DecodePayloadFeatures(type, feature_bytes, &payload); !decoded.ok()) {
      return fail("features: " + decoded.ToString());
    }
    if (payload.features.size() != record->counts.static_) {
      return fail("features: " + std::to_string(payload.features.size()) +
                  " stored, the record counts " + std::to_string(record->counts.static_));
    }
    std::string dynamics_bytes;  // absent for places stored before the map kept statistics
    rocksdb::Status got = storage_->db->Get(verify, storage_->cf(kDynamics), key, &dynamics_bytes);
    if (!got.IsNotFound()) {
      read = FromRocks(got, "statistics");
      if (!read.ok()) {
        fail(read.ToString());
      } else if (auto d = DecodeDynamics(dynamics_bytes); !d.ok()) {
        fail("statistics: " + d.status().ToString());
      }
    }
    std::string thumbnail_bytes;  // absent when the map kept none for the place
    got = storage_->db->Get(verify, storage_->cf(kThumbnails), key, &thumbnail_bytes);
    if (!got.IsNotFound()) {
      read = FromRocks(got, "thumbnail");
      if (!read.ok()) {
        fail(read.ToString());
      } else if (auto t = DecodeThumbnail(thumbnail_bytes); !t.ok()) {
        fail("thumbnail: " + t.status().ToString());
      }
    }
  };
  ParallelFor(found.size(), threads, [&](size_t task, int) {
    if (task < files.size()) return check_file(files[task], &found[task]);
    const size_t first = (task - files.size()) * kPlacesPerTask;
    const size_t last = std::min(places.size(), first + kPlacesPerTask);
    for (size_t i = first; i < last; ++i) check_place(places[i], &found[task]);
  });

  ScrubReport report;
  report.files_checked = files.size();
  report.places_checked = places.size();
  for (Found& f : found) {
    for (auto& file : f.files) report.damaged_files.push_back(std::move(file));
    for (auto& place : f.places) report.damaged_places.push_back(std::move(place));
  }
  return report;
}

namespace detail {

void CountLostPlaces(const PlaceAudit& audit, PlaceId floor, uint64_t acked_max,
                     MapDamage* damage) {
  damage->places_lost = 0;
  damage->first_lost = damage->last_lost = 0;
  auto add = [&](uint64_t first, uint64_t last) {
    first = std::max<uint64_t>({first, floor, 1});
    last = std::min<uint64_t>(last, acked_max);
    if (first > last) return;
    if (damage->places_lost == 0) damage->first_lost = PlaceId(first);
    damage->last_lost = PlaceId(last);
    damage->places_lost += last - first + 1;
  };
  for (const auto& [first, last] : audit.gaps) add(first, last);
  add(uint64_t(audit.highest) + 1, acked_max);
}

Result<PlaceAudit> AuditPlaces(MapStorage& storage) {
  rocksdb::ReadOptions options;
  options.fill_cache = false;
  std::unique_ptr<rocksdb::Iterator> its[3];
  const Cf families[3] = {kPlaces, kBow, kFeatures};
  for (int i = 0; i < 3; ++i) {
    its[i].reset(storage.db->NewIterator(options, storage.cf(families[i])));
    its[i]->SeekToFirst();
  }
  PlaceAudit audit;
  while (true) {
    const rocksdb::Iterator* lowest = nullptr;
    for (const auto& it : its) {
      if (it->Valid() && (!lowest || it->key().compare(lowest->key()) < 0)) lowest = it.get();
    }
    if (!lowest) break;
    const std::string key = lowest->key().ToString();
    bool has[3];
    for (int i = 0; i < 3; ++i) {
      has[i] = its[i]->Valid() && its[i]->key() == key;
      if (has[i]) its[i]->Next();
    }
    auto id = DecodePlaceKey(key);
    if (!id.ok()) return id.status().WithContext("a place key of the map");
    if (!has[0]) {
      ++audit.records_lost;
      audit.unservable.push_back(*id);
    } else if (!has[1]) {
      ++audit.bow_lost;
      audit.unservable.push_back(*id);
    } else {
      ++audit.servable;
      if (*id > audit.highest + 1) audit.gaps.emplace_back(audit.highest + 1, *id - 1);
      audit.highest = *id;
      if (!has[2]) {
        if (audit.features_lost++ == 0) audit.first_without_features = *id;
        audit.last_without_features = *id;
      }
    }
  }
  for (int i = 0; i < 3; ++i) {
    PLACEDB_RETURN_IF_ERROR(
        FromRocks(its[i]->status(), std::string("reading ") + kColumnFamilies[families[i]]));
  }
  return audit;
}

std::string AuditText(const PlaceAudit& audit) {
  std::string text;
  if (audit.features_lost > 0) {
    text += "; " + std::to_string(audit.features_lost) + " place" +
            (audit.features_lost == 1 ? "" : "s") + " lost their features (ids " +
            std::to_string(audit.first_without_features) + ".." +
            std::to_string(audit.last_without_features) +
            "): still found by search, not verifiable, reading them is DATA_LOSS";
  }
  if (audit.bow_lost + audit.records_lost > 0) {
    text += "; dropped " + std::to_string(audit.bow_lost) + " place(s) that lost their BoW vector" +
            " and " + std::to_string(audit.records_lost) + " that lost their record";
  }
  return text;
}

}  // namespace detail

}  // namespace placedb
