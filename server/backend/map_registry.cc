#include "server/backend/map_registry.h"

#include <spdlog/spdlog.h>

#include <nlohmann/json.hpp>

#include "core/base/map_name.h"
#include "core/base/text.h"

namespace placedb::server {

MapRegistry::MapRegistry(std::unique_ptr<DataDirectory> directory,
                         std::vector<VocabularyEntry> vocabularies,
                         std::vector<MissingVocabulary> missing)
    : directory_(std::move(directory)),
      vocabularies_(std::move(vocabularies)),
      missing_(std::move(missing)) {}

MapRegistry::~MapRegistry() {
  CloseAll();
}

Result<std::unique_ptr<MapRegistry>> MapRegistry::Open(const std::string& data_dir,
                                                       const StorageOptions& storage,
                                                       std::vector<VocabularyEntry> vocabularies,
                                                       std::vector<MissingVocabulary> missing,
                                                       SnapshotOptions snapshots) {
  auto directory = DataDirectory::Open(data_dir, storage);
  if (!directory.ok()) return directory.status().WithContext("data directory " + data_dir);
  std::unique_ptr<MapRegistry> registry(
      new MapRegistry(std::move(directory).value(), std::move(vocabularies), std::move(missing)));
  // Not shared yet, so uncontended; held because Load() and maps_ require them.
  MutexLock create_lock(registry->create_mutex_);
  auto store = SnapshotStore::Open(registry->directory_.get(), snapshots);
  if (!store.ok()) return store.status().WithContext("snapshots of " + data_dir);
  {
    MutexLock lock(registry->mutex_);
    registry->snapshots_ = std::move(store).value();
  }
  for (const std::string& name : registry->directory_->ListMaps()) {
    auto entry = registry->Load(name);
    if (entry->map) {
      spdlog::info("map '{}' opened: vocabulary '{}', features {}, {} places", name,
                   entry->vocabulary_name,
                   FeatureTypeName(entry->map->database()->config().feature_type),
                   entry->map->database()->Stats().places);
      if (!entry->map->open_note().empty()) {
        spdlog::warn("map '{}': {}", name, entry->map->open_note());
      }
      if (entry->places_lost() > 0 || !entry->map->damage_history().empty()) {
        spdlog::warn("map '{}' was recovered from damage earlier: {} acknowledged places lost",
                     name, entry->places_lost());
      }
    } else if (entry->damaged) {
      spdlog::error("map '{}' is DAMAGED and not served: {}", name, entry->unavailable_reason);
    } else {
      spdlog::warn("map '{}' unavailable: {}", name, entry->unavailable_reason);
    }
    MutexLock lock(registry->mutex_);
    registry->maps_[name] = std::move(entry);
  }
  return registry;
}

const VocabularyEntry* MapRegistry::FindVocabulary(const std::string& name) const {
  for (const VocabularyEntry& entry : vocabularies_) {
    if (entry.name == name) return &entry;
  }
  return nullptr;
}

std::string MapRegistry::VocabularyNameOf(uint64_t checksum) const {
  for (const VocabularyEntry& entry : vocabularies_) {
    if (entry.vocabulary.checksum() == checksum) return entry.name;
  }
  return "";
}

std::string MapRegistry::VocabularyNameFor(const MapInfo& info) const {
  const std::string configured = VocabularyNameOf(info.vocabulary_checksum);
  return configured.empty() ? "learned" : configured;
}

void MapRegistry::VocabularySwitched(const std::string& name) {
  MutexLock lock(mutex_);
  auto it = maps_.find(name);
  if (it == maps_.end() || !it->second->map) return;
  auto entry = std::make_shared<MapEntry>(*it->second);
  entry->vocabulary_name = VocabularyNameFor(entry->map->info());
  it->second = std::move(entry);
}

std::string MapRegistry::MissingNote() const {
  std::string note;
  for (const MissingVocabulary& missing : missing_) {
    note += (note.empty() ? "; not loaded: " : ", ") + missing.name + " (" + missing.path + ": " +
            missing.reason + ")";
  }
  return note;
}

Result<const VocabularyEntry*> MapRegistry::ResolveVocabulary(const std::string& name) const {
  const std::string vocab_name = name.empty() ? "default" : name;
  if (const VocabularyEntry* vocabulary = FindVocabulary(vocab_name)) return vocabulary;
  for (const MissingVocabulary& missing : missing_) {
    if (missing.name == vocab_name) {
      return Status::FailedPrecondition("config.vocabulary: '" + vocab_name +
                                        "' is configured but not loaded: " + missing.path + ": " +
                                        missing.reason + " (tools/setup.sh builds it)");
    }
  }
  std::string configured;
  for (const VocabularyEntry& entry : vocabularies_) {
    configured += (configured.empty() ? "" : ", ") + entry.name;
  }
  return Status::InvalidArgument("config.vocabulary: '" + vocab_name +
                                 "' is not configured (configured: " + configured + ")");
}

uint64_t MapEntry::places_lost() const {
  if (!map) return damage.places_lost;
  uint64_t lost = 0;
  for (const MapDamage& accepted : map->damage_history()) lost += accepted.places_lost;
  return lost;
}

Result<const VocabularyEntry*> MapRegistry::VocabularyFor(const MapInfo& info) const {
  for (const VocabularyEntry& candidate : vocabularies_) {
    if (candidate.vocabulary.checksum() == info.vocabulary_checksum) return &candidate;
  }
  std::string configured;
  for (const VocabularyEntry& candidate : vocabularies_) {
    configured += (configured.empty() ? "" : ", ") + candidate.name + "=" +
                  candidate.vocabulary.checksum_hex();
  }
  return Status::FailedPrecondition("built with vocabulary " + Hex64(info.vocabulary_checksum) +
                                    ", which is not configured (configured: " + configured +
                                    MissingNote() +
                                    "); add it under `vocabularies` in the server config");
}

std::shared_ptr<const MapEntry> MapRegistry::Load(const std::string& name) {
  auto entry = std::make_shared<MapEntry>();
  entry->name = name;
  auto damaged = [&](const std::string& reason) {
    entry->damaged = true;
    entry->damage.reason = reason;
    entry->unavailable_reason = reason;
    return entry;
  };
  auto info = directory_->ReadMapInfo(name);
  if (!info.ok()) {
    if (info.status().code() == StatusCode::kCorruption) return damaged(info.status().message());
    entry->unavailable_reason = "cannot read its info: " + info.status().ToString();
    return entry;
  }
  // A map that stores its own vocabulary (issue 29) opens with it: no file needed.
  const bool stored = info->vocabulary.stored();
  auto vocabulary = VocabularyFor(*info);
  if (!stored && !vocabulary.ok()) {
    entry->unavailable_reason = vocabulary.status().message();
    return entry;
  }
  MapDamage damage;
  auto map =
      directory_->OpenMap(name, stored ? AnyVocabulary() : (*vocabulary)->vocabulary, &damage);
  if (!map.ok()) {
    if (!damage.reason.empty()) {
      damaged(damage.reason);
      entry->damage = damage;
      return entry;
    }
    entry->unavailable_reason = "cannot be opened: " + map.status().ToString();
    return entry;
  }
  entry->map = std::move(map).value();
  entry->vocabulary_name = VocabularyNameFor(entry->map->info());
  entry->settings = DecodeSettings(name, entry->map->info().options.service_json);
  return entry;
}

Result<std::shared_ptr<const MapEntry>> MapRegistry::Get(const std::string& name,
                                                         const std::string& field) const {
  auto entry = Find(name, field);
  if (!entry.ok()) return entry;
  if ((*entry)->damaged) {
    return Status::Corruption("map '" + name + "' is damaged: " + (*entry)->unavailable_reason +
                              " (see `placedb maps recover`)");
  }
  if (!(*entry)->map) {
    return Status::FailedPrecondition("map '" + name +
                                      "' is unavailable: " + (*entry)->unavailable_reason);
  }
  return entry;
}

Result<std::shared_ptr<const MapEntry>> MapRegistry::Find(const std::string& name,
                                                          const std::string& field) const {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name).WithContext(field));
  MutexLock lock(mutex_);
  auto it = maps_.find(name);
  if (it == maps_.end()) return Status::NotFound("map '" + name + "' not found");
  return it->second;
}

Result<std::shared_ptr<const MapEntry>> MapRegistry::Recover(const std::string& name,
                                                             bool accept_data_loss,
                                                             MapDamage* accepted) {
  auto existing = Find(name, "name");
  if (!existing.ok()) return existing.status();
  if (!accept_data_loss) {
    return Status::InvalidArgument(
        "accept_data_loss: must be set: recovering map '" + name +
        "' drops for good whatever cannot be read (" +
        ((*existing)->damaged ? (*existing)->unavailable_reason : std::string("not damaged")) +
        ")");
  }
  MutexLock create_lock(create_mutex_);
  if (!directory_) return Status::IoError("the data directory is closed (shutting down)");
  {
    MutexLock lock(mutex_);
    auto it = maps_.find(name);
    if (it == maps_.end()) return Status::NotFound("map '" + name + "' not found");
    if (!it->second->damaged) {
      return Status::FailedPrecondition(
          "map '" + name + "' is not damaged" +
          (it->second->map ? std::string()
                           : ": it is unavailable: " + it->second->unavailable_reason));
    }
  }
  std::string vocabulary_name;
  auto map = directory_->RecoverMap(
      name,
      [&](const MapInfo& info) -> Result<AnyVocabulary> {
        auto vocabulary = VocabularyFor(info);
        if (!vocabulary.ok()) return vocabulary.status();
        vocabulary_name = (*vocabulary)->name;
        return (*vocabulary)->vocabulary;
      },
      accepted);
  if (!map.ok()) return map.status();
  auto entry = std::make_shared<MapEntry>();
  entry->name = name;
  entry->map = std::move(map).value();
  entry->vocabulary_name =
      vocabulary_name.empty() ? VocabularyNameFor(entry->map->info()) : vocabulary_name;
  entry->settings = DecodeSettings(name, entry->map->info().options.service_json);
  MutexLock lock(mutex_);
  maps_[name] = entry;
  return std::shared_ptr<const MapEntry>(entry);
}

Result<std::shared_ptr<const MapEntry>> MapRegistry::Create(const std::string& name,
                                                            const MapOptions& options,
                                                            const std::string& vocabulary_name,
                                                            const ServiceMapSettings& settings) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name).WithContext("name"));
  auto resolved = ResolveVocabulary(vocabulary_name);
  if (!resolved.ok()) return resolved.status();
  const VocabularyEntry* vocabulary = *resolved;
  const std::string& vocab_name = vocabulary->name;
  MutexLock create_lock(create_mutex_);
  if (!directory_) return Status::IoError("the data directory is closed (shutting down)");
  {
    MutexLock lock(mutex_);
    if (maps_.count(name)) return Status::AlreadyExists("map '" + name + "' already exists");
  }
  MapOptions stored = options;
  stored.service_json = EncodeSettings(settings);
  auto map = directory_->CreateMap(name, stored, vocabulary->vocabulary);
  if (!map.ok()) return map.status();
  auto entry = std::make_shared<MapEntry>();
  entry->name = name;
  entry->map = std::move(map).value();
  entry->vocabulary_name = vocab_name;
  entry->settings = settings;
  MutexLock lock(mutex_);
  maps_[name] = entry;
  return std::shared_ptr<const MapEntry>(entry);
}

Status MapRegistry::Delete(const std::string& name) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name).WithContext("name"));
  MutexLock create_lock(create_mutex_);
  if (!directory_) return Status::IoError("the data directory is closed (shutting down)");
  {
    MutexLock lock(mutex_);
    if (!maps_.count(name)) return Status::NotFound("map '" + name + "' not found");
  }
  // The directory refuses further writes to the map; in-flight holders keep it until done.
  PLACEDB_RETURN_IF_ERROR(directory_->DeleteMap(name));
  {
    MutexLock lock(mutex_);
    maps_.erase(name);
  }
  return Status::Ok();
}

std::vector<std::shared_ptr<const MapEntry>> MapRegistry::List() const {
  MutexLock lock(mutex_);
  std::vector<std::shared_ptr<const MapEntry>> out;
  out.reserve(maps_.size());
  for (const auto& [name, entry] : maps_) out.push_back(entry);
  return out;
}

void MapRegistry::CloseAll() {
  MutexLock create_lock(create_mutex_);
  std::map<std::string, std::shared_ptr<const MapEntry>> maps;
  std::shared_ptr<SnapshotStore> snapshots;
  {
    MutexLock lock(mutex_);
    maps.swap(maps_);
    snapshots.swap(snapshots_);
  }
  snapshots.reset();  // a download in flight keeps the store (it reads only its own files)
  maps.clear();       // the last holder of each map flushes and closes its RocksDB
  directory_.reset();
}

DataDirectory::VocabularyFor MapRegistry::AnyVocabularyFor() const {
  return [this](const MapInfo& info) -> Result<AnyVocabulary> {
    // A map that stores its vocabulary (issue 29) opens with it: none is needed.
    if (info.vocabulary.stored()) return AnyVocabulary();
    auto vocabulary = VocabularyFor(info);
    if (!vocabulary.ok()) return vocabulary.status();
    return (*vocabulary)->vocabulary;
  };
}

std::shared_ptr<SnapshotStore> MapRegistry::snapshots() const {
  MutexLock lock(mutex_);
  return snapshots_;
}

// Create and Import take no create_mutex_: they do not use the DataDirectory (SnapshotStore's
// header), the entry keeps the map (a DeleteMap meanwhile makes the checkpoint NOT_FOUND), and
// CreateMap/DeleteMap need not wait for a verification.
Result<SnapshotInfo> MapRegistry::CreateSnapshot(const std::string& map) {
  auto entry = Get(map, "map");
  if (!entry.ok()) return entry.status();
  auto store = snapshots();
  if (!store) return Status::IoError("the data directory is closed (shutting down)");
  return store->Create(*(*entry)->map, AnyVocabularyFor());
}

Result<SnapshotInfo> MapRegistry::ImportSnapshot(const std::string& archive_path) {
  auto store = snapshots();
  if (!store) return Status::IoError("the data directory is closed (shutting down)");
  return store->Import(archive_path, AnyVocabularyFor());
}

Result<std::shared_ptr<const MapEntry>> MapRegistry::RestoreSnapshot(const std::string& id,
                                                                     const std::string& new_map) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(new_map).WithContext("new_map"));
  MutexLock create_lock(create_mutex_);
  auto store = snapshots();
  if (!directory_ || !store) return Status::IoError("the data directory is closed (shutting down)");
  {
    MutexLock lock(mutex_);
    if (maps_.count(new_map)) return Status::AlreadyExists("map '" + new_map + "' already exists");
  }
  PLACEDB_RETURN_IF_ERROR(store->Restore(id, new_map));
  auto entry = Load(new_map);
  // What the map needs of this server, said here rather than by every query later.
  std::string missing = entry->map ? MissingFor(*entry) : entry->unavailable_reason;
  if (!missing.empty()) {
    entry.reset();  // the map's files close once no holder is left
    if (Status removed = directory_->DeleteMap(new_map); !removed.ok()) {
      spdlog::error("restored map '{}' cannot be removed again: {}", new_map, removed.ToString());
    }
    return Status::FailedPrecondition("snapshot '" + id + "' restored as map '" + new_map +
                                      "' would not work on this server: " + missing +
                                      "; nothing was restored");
  }
  MutexLock lock(mutex_);
  maps_[new_map] = entry;
  return std::shared_ptr<const MapEntry>(entry);
}

void MapRegistry::SetDetector(bool available, const std::string& status) {
  std::vector<std::shared_ptr<const MapEntry>> maps;
  {
    MutexLock lock(mutex_);
    detector_ = available;
    detector_status_ = status;
    for (const auto& [name, entry] : maps_) maps.push_back(entry);
  }
  for (const auto& entry : maps) {
    if (!entry->map) continue;
    if (const std::string missing = MissingFor(*entry); !missing.empty()) {
      spdlog::error("map '{}' cannot be ingested into nor queried on this server: {}", entry->name,
                    missing);
    }
  }
}

std::string MapRegistry::MissingFor(const MapEntry& entry) const {
  const ServiceMapSettings& settings = entry.settings;
  if (settings.detection_enabled && settings.box_source != BoxSource::kAgent) {
    MutexLock lock(mutex_);
    if (!detector_) {
      return "map '" + entry.name + "' takes dynamic-object boxes from the server's detector " +
             "(box_source " + BoxSourceName(settings.box_source) +
             "), which this server does not have (detector " +
             (detector_status_.empty() ? std::string("off") : detector_status_) +
             "): configure detector.model (placedb-server --detector-model), or restore it on a "
             "server with a detector";
    }
  }
  return "";
}

ServiceMapSettings MapRegistry::DecodeSettings(const std::string& name, const std::string& text) {
  ServiceMapSettings settings;
  if (text.empty()) return settings;
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (j.is_discarded() || !j.is_object()) {
    spdlog::warn("map '{}': its service settings are damaged; using defaults", name);
    return settings;
  }
  if (j.contains("box_source") && j["box_source"].is_string()) {
    auto source = ParseBoxSource(j["box_source"].get<std::string>());
    if (source.ok()) settings.box_source = *source;
  }
  if (j.contains("detection_enabled") && j["detection_enabled"].is_boolean()) {
    settings.detection_enabled = j["detection_enabled"].get<bool>();
  }
  // Issue 29; absent in maps made before: off.
  if (j.contains("adapt_after_descriptors") && j["adapt_after_descriptors"].is_number_unsigned()) {
    settings.adapt_after_descriptors = j["adapt_after_descriptors"].get<uint64_t>();
  }
  if (j.contains("regrow_factor") && j["regrow_factor"].is_number()) {
    settings.regrow_factor = j["regrow_factor"].get<double>();
  }
  return settings;
}

std::string MapRegistry::EncodeSettings(const ServiceMapSettings& settings) {
  nlohmann::json j;
  j["format"] = 1;
  j["box_source"] = BoxSourceName(settings.box_source);
  j["detection_enabled"] = settings.detection_enabled;
  // Only when set, so a map without a policy keeps the settings it had.
  if (settings.adapt_after_descriptors > 0) {
    j["adapt_after_descriptors"] = settings.adapt_after_descriptors;
  }
  if (settings.regrow_factor > 0) j["regrow_factor"] = settings.regrow_factor;
  return j.dump();
}

}  // namespace placedb::server
