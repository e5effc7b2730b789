// DataDirectory (map_store.h): the data directory and its maps: creating, opening (checked
// against ACKED), reading a map's info, recovering a damaged map (RecoverMap), listing, deleting,
// restoring a checkpoint, closing.
#include <rocksdb/cache.h>
#include <rocksdb/db.h>
#include <rocksdb/write_batch.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <system_error>

#include "core/base/files.h"
#include "core/base/map_name.h"
#include "core/storage/ack_tracking.h"
#include "core/storage/map_integrity.h"
#include "core/storage/map_storage.h"
#include "core/storage/map_store.h"

namespace fs = std::filesystem;

namespace placedb {

// The storage internals (map_storage.h) and their helpers, unqualified as in the rest of the
// module.
using namespace detail;

namespace {

constexpr char kMarkerFile[] = "PLACEDB_DATA_DIR";
constexpr char kMarkerText[] = "placedb data directory, format 1\n";
constexpr char kMapFormat[] = "placedb-map-1";

int64_t NowUnixMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

}  // namespace

namespace detail {

std::string EncodeInfo(const MapInfo& info) {
  nlohmann::json j;
  j["name"] = info.name;
  j["database"] = nlohmann::json::parse(EncodeDatabaseConfig(info.options.database));
  j["store_invalid"] = info.options.store_invalid;
  const ThumbnailSettings& thumbnails = info.options.thumbnails;
  j["thumbnails"] = {{"enabled", thumbnails.enabled},
                     {"max_side", thumbnails.max_side},
                     {"jpeg_quality", thumbnails.jpeg_quality}};
  // Only when set, so a map that never counted query hits has the same info as before.
  if (info.options.count_query_hits_above > 0) {
    j["count_query_hits_above"] = info.options.count_query_hits_above;
  }
  j["service"] = info.options.service_json;
  j["vocabulary_checksum"] = info.vocabulary_checksum;
  j["created_unix_ms"] = info.created_unix_ms;
  return j.dump();
}

Result<MapInfo> DecodeInfo(const std::string& text) {
  nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (j.is_discarded() || !j.is_object()) return Status::Corruption("map info is not valid JSON");
  MapInfo info;
  try {
    info.name = j.at("name").get<std::string>();
    auto config = DecodeDatabaseConfig(j.at("database").dump());
    if (!config.ok()) return config.status();
    info.options.database = *config;
    info.options.store_invalid = j.at("store_invalid").get<bool>();
    info.options.count_query_hits_above = j.value("count_query_hits_above", 0.0);
    info.options.service_json = j.value("service", std::string());
    // Maps made before issue 20 have no thumbnail settings: off.
    if (j.contains("thumbnails")) {
      const nlohmann::json& t = j.at("thumbnails");
      ThumbnailSettings& thumbnails = info.options.thumbnails;
      thumbnails.enabled = t.at("enabled").get<bool>();
      thumbnails.max_side = t.at("max_side").get<uint32_t>();
      thumbnails.jpeg_quality = t.at("jpeg_quality").get<uint32_t>();
      PLACEDB_RETURN_IF_ERROR(ValidateThumbnailSettings(thumbnails).WithContext("map info"));
    }
    info.vocabulary_checksum = j.at("vocabulary_checksum").get<uint64_t>();
    info.created_unix_ms = j.at("created_unix_ms").get<int64_t>();
  } catch (const nlohmann::json::exception& e) {
    return Status::Corruption(std::string("map info: ") + e.what());
  }
  info.vocabulary.current.checksum = info.vocabulary_checksum;
  info.vocabulary.since_unix_ms = info.created_unix_ms;
  return info;
}

}  // namespace detail

DataDirectory::DataDirectory(std::string path, StorageOptions options, DirectoryLock lock)
    : path_(std::move(path)), options_(options), lock_(std::move(lock)) {
  block_cache_ = rocksdb::NewLRUCache(options_.block_cache_bytes);
}

DataDirectory::~DataDirectory() {
  MutexLock lock(mutex_);
  open_.clear();
}

Result<std::unique_ptr<DataDirectory>> DataDirectory::Open(const std::string& path,
                                                           StorageOptions options) {
  if (options.group_commit_delay_ms < 0 || options.group_commit_delay_ms > 1000) {
    return Status::InvalidArgument("group_commit_delay_ms must be in [0, 1000]");
  }
  std::error_code ec;
  const fs::path root(path);
  const fs::path marker = root / kMarkerFile;
  if (fs::exists(root, ec) && !fs::is_directory(root, ec)) {
    return Status::FailedPrecondition(path + " exists and is not a directory");
  }
  if (fs::exists(marker, ec)) {
    auto text = ReadWholeFile(marker.string());
    if (!text.ok()) return text.status();
    if (*text != kMarkerText) {
      return Status::Corruption(marker.string() + " is damaged or from another placedb version");
    }
  } else {
    if (fs::exists(root, ec) && !fs::is_empty(root, ec)) {
      return Status::FailedPrecondition(path +
                                        " is not empty and is not a placedb data directory (no " +
                                        kMarkerFile + "); refusing to touch it");
    }
    fs::create_directories(root / "maps", ec);
    if (ec) return Status::IoError("creating " + path + ": " + ec.message());
    std::ofstream out(marker);
    out << kMarkerText;
    out.close();
    if (!out) return Status::IoError("writing " + marker.string());
  }
  // Locked before anything below writes (maps/): the marker's checks above only read.
  auto lock = DirectoryLock::Acquire(path);
  if (!lock.ok()) return lock.status();
  fs::create_directories(root / "maps", ec);
  if (ec) return Status::IoError("creating " + (root / "maps").string() + ": " + ec.message());
  return std::unique_ptr<DataDirectory>(new DataDirectory(path, options, std::move(lock).value()));
}

std::string DataDirectory::MapPath(const std::string& name) const {
  return (fs::path(path_) / "maps" / name).string();
}

namespace {

// What a map's RocksDB holds, to compare with ACKED.
struct Contents {
  uint64_t writes = 0;    // acknowledged-write counter (kWritesKey)
  PlaceId max_place = 0;  // highest stored place id
  PlaceId floor = 0;      // id_floor: ids below were handed out (removals)
};

Result<Contents> ReadContents(MapStorage& storage) {
  Contents contents;
  std::string value;
  auto s = storage.db->Get({}, storage.cf(kMeta), kWritesKey, &value);
  if (!s.IsNotFound()) {
    PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading the write counter"));
    rocksdb::Slice slice(value);
    contents.writes = CounterMergeOperator::Decode(&slice);
  }
  s = storage.db->Get({}, storage.cf(kMeta), kIdFloorKey, &value);
  if (s.ok()) {
    auto floor = DecodePlaceKey(value);
    if (floor.ok()) contents.floor = *floor;
  } else if (!s.IsNotFound()) {
    PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading the id floor"));
  }
  rocksdb::ReadOptions options;
  options.fill_cache = false;
  std::unique_ptr<rocksdb::Iterator> places(storage.db->NewIterator(options, storage.cf(kPlaces)));
  places->SeekToLast();
  if (places->Valid()) {
    auto id = DecodePlaceKey(places->key().ToStringView());
    if (id.ok()) contents.max_place = *id;
  }
  PLACEDB_RETURN_IF_ERROR(FromRocks(places->status(), "reading the last place"));
  return contents;
}

// Fills `damage` with what `present` lacks of `acked`; false when nothing acknowledged is missing.
bool FindLoss(const AckState& acked, const Contents& present, MapDamage* damage) {
  if (present.writes >= acked.writes) return false;
  damage->writes_lost = acked.writes - present.writes;
  const PlaceId accounted =
      std::max<PlaceId>(present.max_place, present.floor ? present.floor - 1 : 0);
  if (acked.max_place > accounted) {
    damage->first_lost = accounted + 1;
    damage->last_lost = PlaceId(acked.max_place);
    damage->places_lost = damage->last_lost - damage->first_lost + 1;
  }
  return true;
}

std::string LossText(const MapDamage& damage) {
  std::string text = std::to_string(damage.writes_lost) + " acknowledged write" +
                     (damage.writes_lost == 1 ? " is" : "s are") + " missing";
  if (damage.places_lost > 0) {
    text += ": " + std::to_string(damage.places_lost) + " place" +
            (damage.places_lost == 1 ? " (id " + std::to_string(damage.first_lost) + ")"
                                     : "s (ids " + std::to_string(damage.first_lost) + ".." +
                                           std::to_string(damage.last_lost) + ")");
  } else {
    text += " (removals or stored invalid frames; no place id is missing)";
  }
  return text;
}

// The map's write-ahead log files and their sizes, for reasons: "maps/lab/000012.log (5 bytes)";
// empty logs only when no other is left.
std::string WalFiles(const std::string& path, const std::string& name) {
  std::vector<std::pair<std::string, uintmax_t>> logs;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(path, ec)) {
    if (entry.path().extension() != ".log") continue;
    std::error_code size_ec;
    const auto size = entry.file_size(size_ec);
    logs.push_back({"maps/" + name + "/" + entry.path().filename().string(), size_ec ? 0 : size});
  }
  std::sort(logs.begin(), logs.end());
  if (logs.empty()) return "no write-ahead log file is left";
  const bool any_data = std::any_of(logs.begin(), logs.end(), [](auto& l) { return l.second; });
  std::string text;
  for (const auto& [file, size] : logs) {
    if (any_data && size == 0) continue;
    text += (text.empty() ? "" : ", ") + file + " (" + std::to_string(size) + " bytes)";
  }
  return text;
}

Result<std::vector<MapDamage>> ReadHistory(MapStorage& storage) {
  std::vector<MapDamage> history;
  std::string text;
  auto s = storage.db->Get({}, storage.cf(kMeta), kDamageHistoryKey, &text);
  if (s.IsNotFound()) return history;
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading the damage history"));
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (!j.is_array()) return Status::Corruption("the damage history is not a JSON array");
  try {
    for (const auto& item : j) {
      MapDamage damage;
      damage.reason = item.at("reason").get<std::string>();
      damage.writes_lost = item.at("writes_lost").get<uint64_t>();
      damage.places_lost = item.at("places_lost").get<uint64_t>();
      damage.first_lost = item.at("first_lost").get<PlaceId>();
      damage.last_lost = item.at("last_lost").get<PlaceId>();
      damage.recovered_unix_ms = item.at("recovered_unix_ms").get<int64_t>();
      // Added by issue 34: absent from older entries.
      damage.records_lost = item.value("records_lost", uint64_t(0));
      damage.bow_lost = item.value("bow_lost", uint64_t(0));
      damage.features_lost = item.value("features_lost", uint64_t(0));
      damage.quarantine = item.value("quarantine", std::string());
      history.push_back(std::move(damage));
    }
  } catch (const nlohmann::json::exception& e) {
    return Status::Corruption(std::string("damage history: ") + e.what());
  }
  return history;
}

std::string EncodeHistory(const std::vector<MapDamage>& history) {
  nlohmann::json j = nlohmann::json::array();
  for (const MapDamage& damage : history) {
    j.push_back({{"reason", damage.reason},
                 {"writes_lost", damage.writes_lost},
                 {"places_lost", damage.places_lost},
                 {"first_lost", damage.first_lost},
                 {"last_lost", damage.last_lost},
                 {"recovered_unix_ms", damage.recovered_unix_ms},
                 {"records_lost", damage.records_lost},
                 {"bow_lost", damage.bow_lost},
                 {"features_lost", damage.features_lost},
                 {"quarantine", damage.quarantine}});
  }
  return j.dump();
}

// `where`: the map's directory relative to the data directory, for messages.
Result<MapInfo> ReadInfo(MapStorage& storage, const std::string& where) {
  std::string format, info_text;
  auto s = storage.db->Get({}, storage.cf(kMeta), kFormatKey, &format);
  if (s.IsNotFound() || (s.ok() && format != kMapFormat)) {
    return Status::Corruption(where + " is a RocksDB database but not a placedb map (format '" +
                              format + "')");
  }
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading map format"));
  s = storage.db->Get({}, storage.cf(kMeta), kInfoKey, &info_text);
  if (s.IsNotFound()) return Status::Corruption(where + ": the map info record is missing");
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading map info"));
  auto info = DecodeInfo(info_text);
  if (!info.ok()) return info.status().WithContext(where + ": the map info record is damaged");
  PLACEDB_RETURN_IF_ERROR(ReadVocabularyRecord(storage, &*info).WithContext(where));
  return info;
}

// The vocabulary a map opens with: the one it stores (issue 29), else `vocabulary_for`'s.
Result<AnyVocabulary> MapVocabulary(MapStorage& storage, const MapInfo& info,
                                    const DataDirectory::VocabularyFor& vocabulary_for) {
  auto stored = ReadStoredVocabulary(storage, info);
  if (!stored.ok()) return stored.status();
  if (*stored) return std::move(**stored);
  auto given = vocabulary_for(info);
  if (!given.ok()) return given.status();
  if (!*given) {
    return Status::InvalidArgument("vocabulary is missing (map '" + info.name +
                                   "' does not store its own)");
  }
  return given;
}

}  // namespace

Result<std::shared_ptr<PlaceMap>> DataDirectory::CreateMap(const std::string& name,
                                                           const MapOptions& options,
                                                           AnyVocabulary vocabulary) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  if (!vocabulary) return Status::InvalidArgument("vocabulary is missing");
  PLACEDB_RETURN_IF_ERROR(ValidateDatabaseConfig(options.database));
  PLACEDB_RETURN_IF_ERROR(ValidateThumbnailSettings(options.thumbnails));
  const FeatureType type = options.database.feature_type;
  if (vocabulary.feature_type() != type) {
    return Status::InvalidArgument("map '" + name + "': feature_type " + FeatureTypeName(type) +
                                   " needs a " + VocabularyKindName(type) +
                                   " vocabulary; this one is " + vocabulary.kind());
  }
  MutexLock lock(mutex_);
  const std::string path = MapPath(name);
  if (fs::exists(path)) return Status::AlreadyExists("map '" + name + "' already exists");
  auto storage = OpenStorage(path, /*create=*/true, options_, block_cache_);
  if (!storage.ok()) return storage.status();
  MapInfo info;
  info.name = name;
  info.options = options;
  info.vocabulary_checksum = vocabulary.checksum();
  info.created_unix_ms = NowUnixMs();
  rocksdb::WriteBatch batch;
  batch.Put((*storage)->cf(kMeta), kFormatKey, kMapFormat);
  batch.Put((*storage)->cf(kMeta), kInfoKey, EncodeInfo(info));
  rocksdb::WriteOptions sync;
  sync.sync = true;
  Status written = FromRocks((*storage)->db->Write(sync, &batch), "writing map info");
  // The info goes to an SST at once: a lost or deleted WAL can then cost places, never the
  // map's identity.
  if (written.ok()) {
    written = FromRocks((*storage)->db->Flush(rocksdb::FlushOptions(), (*storage)->handles),
                        "flushing map info");
  }
  if (written.ok()) written = CreateAcked(path, {});
  if (written.ok() && options_.acked_file) {
    auto acks = AckTracker::Open(path, {2, 0, 0});
    written = acks.status();
    if (acks.ok()) (*storage)->acks = std::move(acks).value();
  }
  if (!written.ok()) {
    storage->reset();
    std::error_code ec;
    fs::remove_all(path, ec);
    return written;
  }
  std::shared_ptr<PlaceMap> map(
      new PlaceMap(std::move(info), path, std::move(storage).value(), std::move(vocabulary)));
  PLACEDB_RETURN_IF_ERROR(map->Load());
  open_[name] = map;
  return map;
}

std::string DataDirectory::Relative(const std::string& text) const {
  std::string out = text;
  std::error_code ec;
  for (const std::string& form : {fs::absolute(path_, ec).lexically_normal().string(),
                                  fs::weakly_canonical(path_, ec).string(), path_}) {
    if (form.empty()) continue;
    const std::string prefix = form.back() == '/' ? form : form + "/";
    for (size_t at = out.find(prefix); at != std::string::npos; at = out.find(prefix, at)) {
      out.erase(at, prefix.size());
    }
  }
  return out;
}

namespace {

// A map path that cannot be a RocksDB database: CORRUPTION naming it; NOT_FOUND when absent.
Status CheckMapPath(const std::string& path, const std::string& name) {
  std::error_code ec;
  const auto status = fs::symlink_status(path, ec);
  if (!fs::exists(status)) return Status::NotFound("map '" + name + "' not found");
  const std::string where = "maps/" + name;
  if (!fs::is_directory(fs::status(path, ec))) {
    return Status::Corruption(where + " is a file, not a map directory");
  }
  if (!fs::exists(fs::path(path) / "CURRENT", ec)) {
    return Status::Corruption(where + "/CURRENT is missing: RocksDB cannot tell which MANIFEST " +
                              "describes the map");
  }
  // CURRENT names the MANIFEST; one deleted (or a CURRENT naming another) is damage that repair
  // mends, not a map that is merely unavailable.
  auto current = ReadWholeFile((fs::path(path) / "CURRENT").string());
  if (current.ok()) {
    std::string manifest = *current;
    while (!manifest.empty() && (manifest.back() == '\n' || manifest.back() == '\r')) {
      manifest.pop_back();
    }
    const bool plain =
        !manifest.empty() && manifest.size() <= 64 &&
        manifest.find_first_not_of("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-") == std::string::npos;
    if (!plain || !fs::exists(fs::path(path) / manifest, ec)) {
      return Status::Corruption(
          where + "/CURRENT names " +
          (plain ? manifest + ", which is missing" : std::string("no MANIFEST file")) +
          ": RocksDB cannot read the map's file list");
    }
  }
  return Status::Ok();
}

}  // namespace

Result<MapInfo> DataDirectory::ReadMapInfo(const std::string& name) const {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  MutexLock lock(mutex_);
  if (auto it = open_.find(name); it != open_.end()) return it->second->info();
  const std::string path = MapPath(name);
  const std::string where = "maps/" + name;
  PLACEDB_RETURN_IF_ERROR(CheckMapPath(path, name));
  // Read-only open: safe while nothing else has the map open (we hold the lock).
  auto storage = OpenReadOnly(path, block_cache_, Recovery::kPointInTime);
  if (!storage.ok()) {
    return Status(storage.status().code(), Relative(storage.status().message()));
  }
  auto info = ReadInfo(**storage, where);
  if (!info.ok() && info.status().code() == StatusCode::kCorruption) {
    // The info record lost with acknowledged writes: the WAL holding it is gone.
    auto acked = ReadAcked((fs::path(path) / kAckedFile).string());
    auto contents = ReadContents(**storage);
    MapDamage damage;
    if (acked.ok() && contents.ok() && FindLoss(*acked, *contents, &damage)) {
      return Status::Corruption(info.status().message() + "; " + LossText(damage) + "; " +
                                WalFiles(path, name));
    }
  }
  return info;
}

Result<std::shared_ptr<PlaceMap>> DataDirectory::OpenMap(const std::string& name,
                                                         AnyVocabulary vocabulary,
                                                         MapDamage* damage) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  MutexLock lock(mutex_);
  if (auto it = open_.find(name); it != open_.end()) {
    PLACEDB_RETURN_IF_ERROR(it->second->CheckVocabulary(vocabulary));
    return it->second;
  }
  MapDamage found;
  auto map = OpenLocked(
      name, [&](const MapInfo&) -> Result<AnyVocabulary> { return vocabulary; }, &found);
  if (!map.ok()) {
    if (damage) *damage = found;
    return map.status();
  }
  open_[name] = *map;
  return map;
}

Result<std::shared_ptr<PlaceMap>> DataDirectory::OpenLocked(const std::string& name,
                                                            const VocabularyFor& vocabulary_for,
                                                            MapDamage* damage) {
  const std::string path = MapPath(name);
  const std::string where = "maps/" + name;
  auto damaged = [&](const std::string& reason) {
    damage->reason = reason;
    return Status::Corruption("map '" + name + "' is damaged: " + reason);
  };
  if (Status checked = CheckMapPath(path, name); !checked.ok()) {
    if (checked.code() != StatusCode::kCorruption) return checked;
    return damaged(checked.message());
  }
  const std::string acked_file = (fs::path(path) / kAckedFile).string();
  auto acked = ReadAcked(acked_file);
  if (acked.ok() && options_.acked_file) {
    // A read-write open deletes the files its MANIFEST does not name: from a MANIFEST cut short
    // it would delete the SST files flushed after the cut before the loss could be seen. So what
    // the map holds is compared with ACKED read-only first; a read-only open that fails is left
    // to the read-write path below, which names the problem.
    auto readonly = OpenReadOnly(path, block_cache_, Recovery::kStrict);
    if (readonly.ok()) {
      auto contents = ReadContents(**readonly);
      readonly->reset();
      if (contents.ok() && FindLoss(*acked, *contents, damage)) {
        return damaged(where + ": " + LossText(*damage) +
                       "; the write-ahead log ends early or was deleted (" + WalFiles(path, name) +
                       ")");
      }
    }
  }
  std::string note;
  auto storage = OpenStorage(path, /*create=*/false, options_, block_cache_, Recovery::kStrict);
  if (!storage.ok()) {
    if (storage.status().code() != StatusCode::kCorruption &&
        storage.status().code() != StatusCode::kIoError) {
      return storage.status().WithContext("map '" + name + "'");
    }
    // RocksDB's reader does not say which log a bad record is in: name the logs.
    std::string error = Relative(storage.status().message());
    const std::string prefix = "opening the map's RocksDB: ";
    if (error.rfind(prefix, 0) == 0) error.erase(0, prefix.size());
    if (error.find(where + "/") == std::string::npos) error = WalFiles(path, name) + ": " + error;
    // Is only an unacknowledged tail damaged (a torn write at power loss)? Count what
    // point-in-time recovery keeps, without changing any file.
    auto readonly = OpenReadOnly(path, block_cache_, Recovery::kPointInTime);
    if (!readonly.ok()) {
      std::string again = Relative(readonly.status().message());
      if (again.rfind(prefix, 0) == 0) again.erase(0, prefix.size());
      return damaged(error + "; point-in-time recovery cannot open it either" +
                     (again == error ? "" : ": " + again));
    }
    auto contents = ReadContents(**readonly);
    readonly->reset();
    if (!contents.ok()) return damaged(error + "; " + Relative(contents.status().message()));
    if (!acked.ok()) {
      return damaged(error + "; " + where + "/" + acked.status().message() +
                     ", so whether acknowledged writes were lost cannot be told");
    }
    if (FindLoss(*acked, *contents, damage)) return damaged(error + "; " + LossText(*damage));
    storage = OpenStorage(path, /*create=*/false, options_, block_cache_, Recovery::kPointInTime);
    if (!storage.ok()) return damaged(Relative(storage.status().message()));
    note = "tolerated " + error + ": only unacknowledged writes were lost";
  }
  auto contents = ReadContents(**storage);
  if (!contents.ok()) return damaged(Relative(contents.status().message()));
  if (!acked.ok()) {
    if (acked.status().code() != StatusCode::kNotFound || contents->writes != 0) {
      return damaged(where + "/" + acked.status().message() + " (" +
                     std::to_string(contents->writes) +
                     " acknowledged writes are stored), so whether any were lost cannot be told");
    }
    // A map made before ACKED existed: counting starts now.
    PLACEDB_RETURN_IF_ERROR(CreateAcked(path, {0, 0, contents->max_place}));
    acked = AckState{2, 0, contents->max_place};
  }
  if (options_.acked_file && FindLoss(*acked, *contents, damage)) {
    return damaged(where + ": " + LossText(*damage) +
                   "; the write-ahead log ends early or was deleted (" + WalFiles(path, name) +
                   ")");
  }
  auto info = ReadInfo(**storage, where);
  if (!info.ok()) {
    if (info.status().code() == StatusCode::kCorruption) return damaged(info.status().message());
    return info.status();
  }
  auto history = ReadHistory(**storage);
  if (!history.ok()) return damaged(where + ": " + history.status().message());
  auto vocabulary = MapVocabulary(**storage, *info, vocabulary_for);
  if (!vocabulary.ok()) {
    if (vocabulary.status().code() == StatusCode::kCorruption) {
      return damaged(where + ": " + vocabulary.status().message());
    }
    return vocabulary.status();
  }
  // Writes kept beyond the acknowledged ones (in flight at a crash) are durable now that RocksDB
  // has recovered them: ACKED counts them, so that losing them later is seen too.
  AckState start = *acked;
  start.writes = std::max(start.writes, contents->writes);
  start.max_place = std::max<uint64_t>(start.max_place, contents->max_place);
  auto tracker = AckTracker::Open(path, *acked);
  if (!tracker.ok()) return tracker.status().WithContext(where);
  if (start.writes != acked->writes || start.max_place != acked->max_place) {
    PLACEDB_RETURN_IF_ERROR((*tracker)->Raise(start).WithContext(where));
  }
  if (options_.acked_file) (*storage)->acks = std::move(tracker).value();
  std::shared_ptr<PlaceMap> map(
      new PlaceMap(std::move(info).value(), path, std::move(storage).value(), *vocabulary));
  map->damage_history_ = std::move(history).value();
  map->open_note_ = note;
  PLACEDB_RETURN_IF_ERROR(map->CheckVocabulary(*vocabulary));
  if (Status loaded = map->Load(); !loaded.ok()) {
    if (loaded.code() == StatusCode::kCorruption || loaded.code() == StatusCode::kIoError) {
      return damaged(Relative(loaded.message()));
    }
    return loaded;
  }
  return map;
}

namespace {

// `from` (a checkpoint, or a map's directory) into the new folder `to`: SST files hard-linked
// when `link` (copied when the file system refuses the link), the rest copied. RocksDB never
// changes an SST file once written, so a link is a copy that costs nothing.
Status LinkOrCopyCheckpoint(const std::string& from, const std::string& to, bool link) {
  std::error_code ec;
  fs::create_directories(to, ec);
  if (ec) return Status::IoError("creating " + to + ": " + ec.message());
  for (auto it = fs::recursive_directory_iterator(from, ec); !ec && it != fs::end(it);
       it.increment(ec)) {
    const fs::path target = fs::path(to) / fs::relative(it->path(), from);
    if (it->is_directory()) {
      fs::create_directories(target, ec);
    } else if (link && it->path().extension() == ".sst") {
      fs::create_hard_link(it->path(), target, ec);
      if (ec == std::errc::cross_device_link || ec == std::errc::operation_not_permitted) {
        ec.clear();
        fs::copy_file(it->path(), target, ec);
      }
    } else {
      fs::copy_file(it->path(), target, ec);
    }
    if (ec) return Status::IoError("copying " + it->path().string() + ": " + ec.message());
  }
  if (ec) return Status::IoError("listing " + from + ": " + ec.message());
  return Status::Ok();
}

// Bytes LinkOrCopyCheckpoint(`from`, ..., true) copies: every file but the SST files.
uint64_t CopiedBytes(const std::string& from) {
  uint64_t bytes = 0;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(from, ec); !ec && it != fs::end(it);
       it.increment(ec)) {
    if (it->is_regular_file(ec) && it->path().extension() != ".sst") {
      bytes += it->file_size(ec);
    }
  }
  return bytes;
}

}  // namespace

Result<std::shared_ptr<PlaceMap>> DataDirectory::RecoverMap(const std::string& name,
                                                            const VocabularyFor& vocabulary_for,
                                                            MapDamage* accepted) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  MutexLock lock(mutex_);
  if (open_.count(name)) {
    return Status::FailedPrecondition("map '" + name + "' is open, so it is not damaged");
  }
  const std::string path = MapPath(name);
  const std::string where = "maps/" + name;
  MapDamage loss;
  {
    // Not damaged after all (e.g. the operator put a file back): open it, record nothing.
    auto map = OpenLocked(name, vocabulary_for, &loss);
    if (map.ok()) {
      open_[name] = *map;
      if (accepted) *accepted = MapDamage();
      return map;
    }
    if (loss.reason.empty()) return map.status();  // not damage: vocabulary, I/O, ...
  }
  std::error_code ec;
  if (!fs::is_directory(path, ec)) {
    return Status::FailedPrecondition(where + " is a file, not a map directory: move it away " +
                                      "and restore the map from a checkpoint");
  }
  auto acked = ReadAcked((fs::path(path) / kAckedFile).string());

  // 1. The files as they are, kept before anything changes them: RocksDB deletes the files a
  // MANIFEST does not name when it opens a map for writing, and repair moves files it cannot
  // read aside. Nothing below touches the quarantine.
  const std::string quarantine_name = "quarantine/" + name + "-" + std::to_string(NowUnixMs());
  const std::string quarantine = (fs::path(path_) / quarantine_name).string();
  PLACEDB_RETURN_IF_ERROR(CheckRoomFor(path_, 3 * CopiedBytes(path), options_.disk_reserve_bytes,
                                       "recovering map '" + name + "'"));
  if (Status kept = LinkOrCopyCheckpoint(path, quarantine, /*link=*/true); !kept.ok()) {
    fs::remove_all(quarantine, ec);
    return Status(kept.code(), Relative(kept.message()))
        .WithContext("keeping map '" + name + "'s files before recovering it");
  }

  // 2. Each way of recovering on its own copy; the one that keeps the most places wins, so a
  // recovery never keeps fewer places than another would (point-in-time recovery from a cut
  // MANIFEST can open with half of the map, where repair keeps all of it).
  struct Candidate {
    std::string method;
    std::string directory;
    Status status;
    Contents contents;
    PlaceAudit audit;
  };
  std::vector<Candidate> candidates;
  for (const bool repair : {false, true}) {
    MapDamage unused;
    if (repair && !candidates.empty() && candidates[0].status.ok() && acked.ok() &&
        !FindLoss(*acked, candidates[0].contents, &unused) && candidates[0].audit.clean()) {
      break;  // nothing acknowledged is missing: repair cannot keep more
    }
    Candidate candidate;
    candidate.method = repair ? "RocksDB repair (MANIFEST rebuilt from the SST and WAL files)"
                              : "point-in-time recovery";
    candidate.directory =
        (fs::path(path_) / "maps" / (".recovering-" + name + (repair ? "-repair" : "-pit")))
            .string();
    fs::remove_all(candidate.directory, ec);
    candidate.status = LinkOrCopyCheckpoint(quarantine, candidate.directory, /*link=*/true);
    if (candidate.status.ok() && repair) {
      candidate.status =
          FromRocks(rocksdb::RepairDB(candidate.directory,
                                      RecoveryOptions(Recovery::kPointInTime, candidate.directory),
                                      Families(block_cache_)),
                    "RocksDB repair");
      // Repair sets a table it cannot read whole (one corrupt block) aside into lost/, with every
      // intact place in it: that drops what is not proven damaged, so it is not taken.
      std::string set_aside;
      for (const auto& entry : fs::directory_iterator(fs::path(candidate.directory) / "lost", ec)) {
        const std::string extension = entry.path().extension().string();
        if (extension == ".sst" || extension == ".ldb") {
          set_aside +=
              (set_aside.empty() ? "" : ", ") + where + "/" + entry.path().filename().string();
        }
      }
      ec.clear();
      if (candidate.status.ok() && !set_aside.empty()) {
        candidate.status = Status::FailedPrecondition(
            "it would set aside " + set_aside +
            " whole (unreadable: a corrupt block), with every intact place in it");
      }
    }
    if (candidate.status.ok()) {
      // Repair keeps only the column families that hold data: the empty ones are made again.
      auto storage = OpenStorage(candidate.directory, /*create=*/false, options_, block_cache_,
                                 Recovery::kPointInTime, /*create_families=*/repair);
      candidate.status = storage.status();
      if (storage.ok()) {
        auto contents = ReadContents(**storage);
        auto info = contents.ok() ? ReadInfo(**storage, where).status() : contents.status();
        auto audit = info.ok() ? AuditPlaces(**storage) : Result<PlaceAudit>(info);
        candidate.status = audit.status();
        if (audit.ok()) {
          candidate.contents = *contents;
          candidate.audit = std::move(audit).value();
        }
      }
    }
    if (!candidate.status.ok()) {
      candidate.status = Status(candidate.status.code(), Relative(candidate.status.message()));
    }
    candidates.push_back(std::move(candidate));
  }
  const auto remove_candidates = [&] {
    for (const Candidate& candidate : candidates) fs::remove_all(candidate.directory, ec);
  };
  const Candidate* best = nullptr;
  for (const Candidate& candidate : candidates) {
    if (candidate.status.ok() && (!best || candidate.audit.servable > best->audit.servable)) {
      best = &candidate;
    }
  }
  if (!best) {
    std::string reasons;
    for (const Candidate& candidate : candidates) {
      reasons += "; " + candidate.method + ": " + candidate.status.message();
    }
    remove_candidates();
    fs::remove_all(quarantine, ec);  // the map's own files were not changed
    return Status::FailedPrecondition("map '" + name + "' cannot be recovered" + reasons +
                                      "; restore it from a checkpoint");
  }
  std::string method = best->method;
  for (const Candidate& candidate : candidates) {
    if (&candidate != best && candidate.status.ok()) {
      method += " (kept " + std::to_string(best->audit.servable) + " places; " + candidate.method +
                " would have kept " + std::to_string(candidate.audit.servable) + ")";
    }
  }
  const Contents contents = best->contents;
  const PlaceAudit audit = best->audit;

  // 3. The recovered copy takes the map's place; the files it replaces are in the quarantine.
  const std::string replaced = (fs::path(path_) / "maps" / (".replaced-" + name)).string();
  fs::remove_all(replaced, ec);
  fs::rename(path, replaced, ec);
  if (!ec) {
    fs::rename(best->directory, path, ec);
    if (ec) {
      std::error_code back;
      fs::rename(replaced, path, back);
    }
  }
  if (ec) {
    remove_candidates();
    fs::remove_all(quarantine, ec);
    return Status::IoError("recovering map '" + name + "': " + ec.message());
  }
  fs::remove_all(replaced, ec);
  remove_candidates();
  // Any failure from here puts the map's files back as they were: it stays damaged.
  const auto put_back = [&](Status status) {
    std::error_code ignored;
    fs::remove_all(path, ignored);
    if (Status copied = LinkOrCopyCheckpoint(quarantine, path, /*link=*/true); copied.ok()) {
      fs::remove_all(quarantine, ignored);
    } else {
      status = status.WithContext("the map's files as they were are in " + quarantine_name);
    }
    return status;
  };

  auto storage = OpenStorage(path, /*create=*/false, options_, block_cache_, Recovery::kPointInTime,
                             /*create_families=*/true);
  if (!storage.ok()) {
    return put_back(Status::Corruption(
        "map '" + name + "' cannot be recovered: " + Relative(storage.status().message())));
  }
  MapStorage& recovered = **storage;
  rocksdb::WriteOptions sync;
  sync.sync = true;
  if (!audit.unservable.empty()) {
    // What is left of places that cannot be found any more (the quarantine keeps it).
    rocksdb::WriteBatch batch;
    for (const PlaceId id : audit.unservable) {
      for (const Cf cf : {kPlaces, kBow, kFeatures, kDynamics, kThumbnails}) {
        batch.Delete(recovered.cf(cf), PlaceKey(id));
      }
    }
    if (Status dropped = FromRocks(recovered.db->Write(sync, &batch), "dropping unservable places");
        !dropped.ok()) {
      storage->reset();
      return put_back(dropped.WithContext("map '" + name + "'"));
    }
  }
  MapDamage counted;
  if (acked.ok()) {
    FindLoss(*acked, contents, &counted);
    CountLostPlaces(audit, contents.floor, acked->max_place, &counted);
  }
  counted.records_lost = audit.records_lost;
  counted.bow_lost = audit.bow_lost;
  counted.features_lost = audit.features_lost;
  counted.quarantine = quarantine_name;
  counted.reason =
      loss.reason + "; recovered with " + method +
      // What was kept differs from what opening counted when repair read a log further.
      (counted.writes_lost > 0 &&
               (counted.writes_lost != loss.writes_lost || counted.places_lost != loss.places_lost)
           ? "; " + LossText(counted)
           : std::string()) +
      AuditText(audit) +
      (acked.ok() ? ""
                  : "; the count of lost writes is unknown (" + acked.status().message() + ")") +
      "; the files as they were are kept in " + quarantine_name;
  counted.recovered_unix_ms = NowUnixMs();
  auto info = ReadInfo(recovered, where);
  if (!info.ok()) {
    storage->reset();
    return put_back(Status::FailedPrecondition("map '" + name +
                                               "' cannot be recovered: " + info.status().message() +
                                               "; restore it from a checkpoint"));
  }
  auto history = ReadHistory(recovered);
  std::vector<MapDamage> entries = history.ok() ? *history : std::vector<MapDamage>();
  if (!history.ok()) counted.reason += "; the earlier damage history was unreadable";
  entries.push_back(counted);
  auto vocabulary = MapVocabulary(recovered, *info, vocabulary_for);
  if (!vocabulary.ok()) {
    storage->reset();
    return put_back(vocabulary.status());
  }
  std::shared_ptr<PlaceMap> map(
      new PlaceMap(std::move(info).value(), path, std::move(storage).value(), *vocabulary));
  Status usable = map->CheckVocabulary(*vocabulary);
  // The index first: if a block it needs is corrupt, the map stays damaged and nothing is
  // recorded.
  if (usable.ok()) {
    if (Status loaded = map->Load(); !loaded.ok()) {
      usable = Status::FailedPrecondition(
          "map '" + name + "' cannot be recovered this way: " + Relative(loaded.message()) +
          "; restore it from a checkpoint");
    }
  }
  if (!usable.ok()) {
    map.reset();
    return put_back(usable);
  }
  MapStorage& storage_ref = *map->storage_;
  PLACEDB_RETURN_IF_ERROR(FromRocks(
      storage_ref.db->Put(sync, storage_ref.cf(kMeta), kDamageHistoryKey, EncodeHistory(entries)),
      "recording the recovery"));
  // What the map holds now is what counts as acknowledged from here on.
  const AckState start{
      0, contents.writes,
      std::max<uint64_t>(contents.max_place, contents.floor ? contents.floor - 1 : 0)};
  PLACEDB_RETURN_IF_ERROR(CreateAcked(path, start).WithContext(where));
  auto tracker = AckTracker::Open(path, {start.generation + 2, start.writes, start.max_place});
  if (!tracker.ok()) return tracker.status().WithContext(where);
  storage_ref.acks = std::move(tracker).value();
  map->damage_history_ = std::move(entries);
  open_[name] = map;
  if (accepted) *accepted = counted;
  return map;
}

std::vector<std::string> DataDirectory::ListMaps() const {
  std::vector<std::string> names;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(fs::path(path_) / "maps", ec)) {
    const std::string name = entry.path().filename().string();
    // Files too: a file where a map's directory should be is damage to show, not to hide.
    if (ValidateMapName(name).ok()) names.push_back(name);
  }
  std::sort(names.begin(), names.end());
  return names;
}

Status DataDirectory::DeleteMap(const std::string& name) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  MutexLock lock(mutex_);
  const std::string path = MapPath(name);
  std::error_code exists_ec;
  // A damaged map may be a file where its directory should be: it is deleted the same way.
  if (!fs::exists(fs::symlink_status(path, exists_ec))) {
    return Status::NotFound("map '" + name + "' not found");
  }
  static std::atomic<uint64_t> counter{0};
  const std::string trash =
      (fs::path(path_) / "maps" /
       (".deleted-" + name + "-" + std::to_string(NowUnixMs()) + "-" + std::to_string(counter++)))
          .string();
  if (auto it = open_.find(name); it != open_.end()) {
    // Holders keep a PlaceMap that answers NOT_FOUND from now on; its database closes here,
    // after in-flight calls finish, so the files and the name are free at once.
    WriterLock closing(it->second->lifecycle_);
    it->second->closed_ = true;
    if (it->second->loops_) it->second->loops_->Close();  // watchers end now
    it->second->storage_->Close();
    open_.erase(it);
  }
  std::error_code ec;
  fs::rename(path, trash, ec);
  if (ec) return Status::IoError("deleting map '" + name + "': " + ec.message());
  fs::remove_all(trash, ec);
  if (ec) return Status::IoError("removing " + trash + ": " + ec.message());
  return Status::Ok();
}

Status DataDirectory::RestoreMap(const std::string& name, const std::string& checkpoint) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  if (!fs::exists(fs::path(checkpoint) / "CURRENT")) {
    return Status::InvalidArgument(checkpoint + " is not a map checkpoint (no CURRENT file)");
  }
  MutexLock lock(mutex_);
  const std::string path = MapPath(name);
  if (fs::exists(path)) return Status::AlreadyExists("map '" + name + "' already exists");
  const std::string staging = (fs::path(path_) / "maps" / (".restoring-" + name)).string();
  std::error_code ec;
  fs::remove_all(staging, ec);
  if (Status copied = LinkOrCopyCheckpoint(checkpoint, staging, options_.restore_hard_links);
      !copied.ok()) {
    fs::remove_all(staging, ec);
    return copied;
  }
  Status valid;
  {
    // Validate before it becomes visible: it must open as a placedb map; rename it inside.
    auto storage = OpenStorage(staging, false, options_, block_cache_);
    valid = storage.status();
    if (valid.ok()) {
      auto info = ReadInfo(**storage, Relative(staging));
      valid = info.status();
      if (valid.ok()) {
        MapInfo renamed = *info;
        renamed.name = name;
        rocksdb::WriteOptions sync;
        sync.sync = true;
        valid = FromRocks(
            (*storage)->db->Put(sync, (*storage)->cf(kMeta), kInfoKey, EncodeInfo(renamed)),
            "renaming the restored map");
      }
      // A checkpoint holds RocksDB's files only: what it holds is what counts as acknowledged.
      auto contents = valid.ok() ? ReadContents(**storage) : Result<Contents>(valid);
      if (contents.ok()) {
        valid = CreateAcked(
            staging,
            {0, contents->writes,
             std::max<uint64_t>(contents->max_place, contents->floor ? contents->floor - 1 : 0)});
      } else {
        valid = contents.status();
      }
    }
  }
  if (!valid.ok()) {
    fs::remove_all(staging, ec);
    return valid.WithContext("restoring from " + checkpoint);
  }
  fs::rename(staging, path, ec);
  if (ec) return Status::IoError("restoring map '" + name + "': " + ec.message());
  return Status::Ok();
}

void DataDirectory::CloseMap(const std::string& name) {
  MutexLock lock(mutex_);
  open_.erase(name);
}

}  // namespace placedb
