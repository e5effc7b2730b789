// The maps a server serves: a DataDirectory, the configured vocabularies, and for every map its
// vocabulary name and service settings (or why it is unavailable).
//
// On startup every map of the data directory is opened with the configured vocabulary whose
// checksum the map recorded (DataDirectory::ReadMapInfo). A vocabulary is binary (ORB maps) or
// float (SIFT maps): AnyVocabulary. A map whose vocabulary is not configured (or is an embedded
// default whose file is missing), or that fails to open, is listed as unavailable with the
// reason; it is not fatal. A map whose files are damaged or that lost acknowledged places
// (DataDirectory::OpenMap's CORRUPTION) is listed as damaged, logged at error level naming the
// file, and refused with CORRUPTION (DATA_LOSS) until Recover accepts the loss.
//
// Service settings the core's database config has no field for (box source, detection on/off)
// are stored as JSON in the map's own info (MapOptions::service_json): written atomically with
// the map, carried by checkpoints, deleted with it. Missing means the defaults.
//
// Every method taking a map name checks it first (ValidateMapName, core/base/map_name.h):
// INVALID_ARGUMENT prefixed with the request field ("name: map name ... is invalid ..."), before
// any lookup or storage access.
//
// Thread safety: all methods may be called concurrently; create/delete are serialised.
#pragma once

#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/base/thread_annotations.h"
#include "core/storage/map_store.h"
#include "core/storage/snapshots.h"
#include "core/vocabulary/any_vocabulary.h"
#include "proto/convert_config.h"

namespace placedb::server {

using wire::ServiceMapSettings;

struct VocabularyEntry {
  std::string name;
  std::string path;
  AnyVocabulary vocabulary;  // binary (ORB) or float (SIFT)
};

// A vocabulary of the embedded defaults the server runs without (its file is missing).
struct MissingVocabulary {
  std::string name;
  std::string path;
  std::string reason;
};

struct MapEntry {
  std::string name;
  std::shared_ptr<PlaceMap> map;  // null when unavailable
  std::string vocabulary_name;
  ServiceMapSettings settings;
  std::string unavailable_reason;
  bool damaged = false;  // unavailable because damaged; `damage` says how
  MapDamage damage;
  // Places lost: found missing (damaged) or accepted as lost (the map's damage history).
  uint64_t places_lost() const;
};

class MapRegistry {
 public:
  // Opens (or creates) the data directory and every map in it.
  // `missing`: configured vocabularies that could not be loaded but are not fatal (named in the
  // messages of maps and CreateMap calls that need them).
  static Result<std::unique_ptr<MapRegistry>> Open(const std::string& data_dir,
                                                   const StorageOptions& storage,
                                                   std::vector<VocabularyEntry> vocabularies,
                                                   std::vector<MissingVocabulary> missing = {},
                                                   SnapshotOptions snapshots = {});
  ~MapRegistry();

  // NOT_FOUND when the map does not exist; FAILED_PRECONDITION (with the reason) when it exists
  // but is unavailable; CORRUPTION (with the reason) when it is damaged. `field` names the
  // request field holding the name.
  Result<std::shared_ptr<const MapEntry>> Get(const std::string& name,
                                              const std::string& field) const;
  // The entry whatever its state (GetMap shows damaged maps too); NOT_FOUND when absent.
  Result<std::shared_ptr<const MapEntry>> Find(const std::string& name,
                                               const std::string& field) const;
  // DataDirectory::RecoverMap for a damaged map: INVALID_ARGUMENT unless `accept_data_loss`;
  // FAILED_PRECONDITION when the map is not damaged or cannot be recovered (it stays damaged).
  // `accepted` receives the loss accepted. The entry is replaced by the recovered map's.
  Result<std::shared_ptr<const MapEntry>> Recover(const std::string& name, bool accept_data_loss,
                                                  MapDamage* accepted);
  // INVALID_ARGUMENT for a bad name (`field` prefix) or unknown vocabulary; ALREADY_EXISTS.
  Result<std::shared_ptr<const MapEntry>> Create(const std::string& name, const MapOptions& options,
                                                 const std::string& vocabulary_name,
                                                 const ServiceMapSettings& settings);
  Status Delete(const std::string& name);
  std::vector<std::shared_ptr<const MapEntry>> List() const;  // sorted by name

  // Snapshots (core/storage/snapshots.h) of the served maps, verified with the configured
  // vocabularies. Restore is serialised with Create/Delete of maps and the restored map is served
  // at once; CreateSnapshot and ImportSnapshot (checkpoint, verification) hold up neither.
  // IO_ERROR once closed (shutting down). Restore checks what the restored map needs of this
  // server (MissingFor: a vocabulary, the detector) and refuses with FAILED_PRECONDITION naming
  // it, the map not kept, rather than serve a map whose every query would fail.
  Result<SnapshotInfo> CreateSnapshot(const std::string& map);
  Result<SnapshotInfo> ImportSnapshot(const std::string& archive_path);
  Result<std::shared_ptr<const MapEntry>> RestoreSnapshot(const std::string& id,
                                                          const std::string& new_map);
  // The store itself for List/Get/Delete/WriteArchive (null once closed); holders keep it.
  std::shared_ptr<SnapshotStore> snapshots() const;

  const std::vector<VocabularyEntry>& vocabularies() const { return vocabularies_; }
  const VocabularyEntry* FindVocabulary(const std::string& name) const;
  // The vocabulary a CreateMap names ("" = "default"); INVALID_ARGUMENT "config.vocabulary: ..."
  // when it is not configured, FAILED_PRECONDITION when it is configured but its file is missing.
  Result<const VocabularyEntry*> ResolveVocabulary(const std::string& name) const;
  std::string VocabularyNameOf(uint64_t checksum) const;  // "" when not configured
  // The name a map's vocabulary is shown by: the configured vocabulary with its checksum, else
  // "learned" (a vocabulary the map learned and stores, issue 29).
  std::string VocabularyNameFor(const MapInfo& info) const;
  // After AdaptVocabulary / RevertVocabulary switched the map's vocabulary: its entry names the
  // new one. Nothing when the map is gone.
  void VocabularySwitched(const std::string& name) EXCLUDES(mutex_);

  // Whether this server has a detector for maps that take boxes from it (box_source server or
  // both, detection on), and why not (`status`, e.g. "off: ..."); until called, it is assumed to
  // have one. Logs, at error level, every served map that needs one when there is none.
  void SetDetector(bool available, const std::string& status) EXCLUDES(mutex_);
  // What `entry`'s map needs that this server lacks, as a sentence naming it and the fix; ""
  // when it has everything.
  std::string MissingFor(const MapEntry& entry) const EXCLUDES(mutex_);

  // Releases every map (RocksDB flushes and closes once the last in-flight holder lets go).
  void CloseAll();

  // The service's per-map settings, kept in the map's own info (MapOptions::service_json).
  // Damaged or unknown values decode as the defaults (logged). Public for tests/fuzz.
  static ServiceMapSettings DecodeSettings(const std::string& name, const std::string& text);
  static std::string EncodeSettings(const ServiceMapSettings& settings);

 private:
  MapRegistry(std::unique_ptr<DataDirectory> directory, std::vector<VocabularyEntry> vocabularies,
              std::vector<MissingVocabulary> missing);
  std::string MissingNote() const;  // "; not loaded: sift (path: reason)" or ""
  std::shared_ptr<const MapEntry> Load(const std::string& name) REQUIRES(create_mutex_);
  // The configured vocabulary whose checksum the map recorded; FAILED_PRECONDITION naming the
  // configured ones otherwise.
  Result<const VocabularyEntry*> VocabularyFor(const MapInfo& info) const;
  // The configured vocabulary for a map's info, as core's VocabularyFor wants it (none for a
  // map that stores its own).
  DataDirectory::VocabularyFor AnyVocabularyFor() const;
  std::unique_ptr<DataDirectory> directory_ GUARDED_BY(create_mutex_);  // null once closed
  const std::vector<VocabularyEntry> vocabularies_;
  const std::vector<MissingVocabulary> missing_;
  Mutex create_mutex_;  // serialises Create/Delete
  mutable Mutex mutex_ ACQUIRED_AFTER(create_mutex_);
  std::map<std::string, std::shared_ptr<const MapEntry>> maps_ GUARDED_BY(mutex_);
  std::shared_ptr<SnapshotStore> snapshots_ GUARDED_BY(mutex_);  // null once closed
  bool detector_ GUARDED_BY(mutex_) = true;                      // SetDetector
  std::string detector_status_ GUARDED_BY(mutex_);
};

}  // namespace placedb::server
