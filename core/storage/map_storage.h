// Storage internals shared by the files that implement map_store.h. INTERNAL: not part of the
// public API, included only by core/storage/*.cc (callers use map_store.h). A map's column
// families and keys, RocksDB's status as placedb's, the merge counter, a map's RocksDB handles and
// writes (MapStorage), the payload store the serving index reads places through, and opening a
// map's RocksDB (OpenStorage, OpenReadOnly).
#pragma once

#include <rocksdb/db.h>
#include <rocksdb/merge_operator.h>
#include <rocksdb/write_batch.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/storage/ack_tracking.h"
#include "core/storage/codec.h"
#include "core/storage/map_store.h"

namespace placedb::detail {

// Meta keys in the default column family.
inline constexpr char kFormatKey[] = "format";
inline constexpr char kInfoKey[] = "info";
inline constexpr char kIdFloorKey[] = "id_floor";  // ids below this were handed out once
inline constexpr char kInvalidCountKey[] = "invalid_rejected";  // merge counter
// Merge counter, +1 in every batch that is acknowledged (places, removals, stored invalid
// frames): what the database holds, compared at open with ACKED (what was acknowledged).
inline constexpr char kWritesKey[] = "acked_writes";
inline constexpr char kDamageHistoryKey[] = "damage_history";  // JSON array of accepted losses
// Cluster mode: the last stream sequence applied (U64Key), written in each applied record's batch.
inline constexpr uint64_t kMaxPlaceId = std::numeric_limits<PlaceId>::max();
inline constexpr char kAppliedSequenceKey[] = "applied_sequence";
// Set by PlaceMap::ApplyAt on its own thread around PlaceDatabase::Remove: the removal's batch
// (RocksPayloadStore::Erase) then also records the applied sequence, atomically with it.
inline thread_local const std::string* t_applying_sequence = nullptr;

// Issue 29, a map's own vocabulary (vocabulary_switch.cc). The generation of the BoW family in
// use (U64Key; absent: 0, the "bow" family). Generation g > 0 lives in the family "bow.<g>",
// whose values carry each place's direct index (EncodeBowWithDirect). Written in the switch's
// batch with the record and the info, so a map has the old vocabulary or the new one, never a
// mix.
inline constexpr char kVocabularyGenerationKey[] = "vocabulary_generation";
// Where the vocabulary came from (VocabularyRecord as JSON): it names the current and the
// previous vocabularies by checksum.
inline constexpr char kVocabularyRecordKey[] = "vocabulary_record";
// "vocabulary.<16 hex digits>": the bytes (AnyVocabulary::Serialize) of the vocabulary with
// that checksum, written before the switch's batch (so the switch itself writes little) and
// kept for the current and previous vocabularies only. A map whose record names a stored
// generation opens with its own and needs no vocabulary file.
inline constexpr char kVocabularyBytesPrefix[] = "vocabulary.";
std::string VocabularyBytesKey(uint64_t checksum);
// "vocabulary_part.<16 hex digits>.<8 digits>": a cluster replica's part of a vocabulary
// (MapLogRecord::kVocabularyPart) until the switch that installs it removes them.
inline constexpr char kVocabularyPartPrefix[] = "vocabulary_part.";
std::string VocabularyPartKey(uint64_t checksum, uint32_t index);
inline constexpr char kGenerationFamilyPrefix[] = "bow.";
// "bow.<generation>"; generation 0 is the "bow" family.
std::string GenerationFamilyName(uint64_t generation);
// The generation a family name holds ("bow" -> 0, "bow.<g>" -> g), nullopt for other names.
std::optional<uint64_t> GenerationOfFamily(const std::string& name);

inline const char* const kColumnFamilies[] = {rocksdb::kDefaultColumnFamilyName.c_str(),
                                              "places",
                                              "bow",
                                              "features",
                                              "invalid",
                                              "dynamics",
                                              "thumbnails",
                                              "loops"};
// kDynamics was added by issue 16, kThumbnails by issue 20, kLoops (loop_log.h) by issue 32: maps
// made before lack the family,
// which a read-write open creates (empty) and a read-only open does without (its handle is
// null). Only these "late" families are ever created on an existing map (LateFamiliesMissing).
enum Cf { kMeta = 0, kPlaces, kBow, kFeatures, kInvalid, kDynamics, kThumbnails, kLoops, kCfCount };
inline constexpr Cf kLateFamilies[] = {kDynamics, kThumbnails, kLoops};

// In kDynamics: the map's aggregate (every acknowledged observation, also of places removed
// since). Place keys are 4 bytes, so this 3-byte key is never one.
inline constexpr char kMapDynamicsKey[] = "map";
// In kDynamics: the aggregate of the frames refused as invalid (no place: too few static
// features, often because objects covered the view). Not part of the map's aggregate.
inline constexpr char kInvalidDynamicsKey[] = "invalid";

inline bool IsAggregateKey(const rocksdb::Slice& key) {
  return key == kMapDynamicsKey || key == kInvalidDynamicsKey;
}

// RocksDB's status as placedb's; `context` prefixes the message. NoSpace is RESOURCE_EXHAUSTED.
Status FromRocks(const rocksdb::Status& s, const std::string& context);

// Adds little-endian uint64 operands: the invalid-observation counter, updated without a read.
class CounterMergeOperator : public rocksdb::AssociativeMergeOperator {
 public:
  bool Merge(const rocksdb::Slice&, const rocksdb::Slice* existing, const rocksdb::Slice& value,
             std::string* new_value, rocksdb::Logger*) const override {
    uint64_t total = Decode(existing) + Decode(&value);
    new_value->assign(reinterpret_cast<const char*>(&total), sizeof total);
    return true;
  }
  const char* Name() const override { return "placedb.CounterAdd"; }
  static uint64_t Decode(const rocksdb::Slice* slice) {
    uint64_t v = 0;
    if (slice && slice->size() == sizeof v) std::memcpy(&v, slice->data(), sizeof v);
    return v;
  }
};

// A CounterMergeOperator operand: adds `v`.
std::string CounterOperand(uint64_t v);

// Bytes an unprivileged writer may still use on the file system holding `path`; none when it
// cannot be read.
std::optional<uint64_t> AvailableBytes(const std::string& path);

// `directory`: the map's RocksDB directory, created here when missing, for its info log; empty
// for options that open no database (SST checksum verification).
rocksdb::DBOptions DatabaseOptions(const std::string& directory);

// Replaces `map_path` (as given, and absolute) in `text` with "maps/<name>": client-visible
// messages never carry the server's absolute paths.
std::string RelativeTo(std::string text, const std::string& map_path, const std::string& name);

// A frame's statistics: what the pipeline measured (coverage, the boxes it used) and when.
PlaceDynamics FrameDynamics(const ProcessedFrame& frame, const PlaceMetadata& metadata);

// A place's features value, decoded by the map's feature type.
Status DecodePayloadFeatures(FeatureType type, std::string_view bytes, PlacePayload* payload);

struct MapStorage {
  // Set before the map is shared and reset only by Close(), under the owning PlaceMap's
  // lifecycle_ exclusively; every other use holds it shared. Not GUARDED_BY: the payload store
  // reads them inside PlaceDatabase calls made under the caller's hold, which the analysis
  // cannot follow.
  std::unique_ptr<rocksdb::DB> db;
  std::vector<rocksdb::ColumnFamilyHandle*> handles;
  SyncMode sync = SyncMode::kEveryWrite;
  std::unique_ptr<GroupCommitter> committer;
  std::unique_ptr<AckTracker> acks;  // null only while a map is being created or recovered
  std::string map_name;              // for messages: never the directory's path
  // Atomics: counters updated under a shared hold by concurrent writers.
  std::atomic<uint64_t> next_invalid_serial{1};
  std::atomic<uint64_t> invalid_stored{0};
  // After a NoSpace error (a write's, or a flush's reported by the listener) RocksDB refuses
  // writes until DB::Resume() succeeds: the next write tries it once there is room, so writes
  // resume as soon as there is space again.
  std::atomic<bool> resume_needed{false};
  std::atomic<bool> resuming{false};  // one DB::Resume() at a time
  std::string path;                   // the map's directory: its file system's free space
  uint64_t reserve_bytes = 0;         // StorageOptions::disk_reserve_bytes
  bool dynamics = true;               // StorageOptions::dynamics
  unsigned load_threads = 2;          // StorageOptions::load_threads (0 taken as 2)
  uint32_t load_range_ids = 65536;    // StorageOptions::load_range_ids (a power of two)

  // The BoW family in use (issue 29): handles[kBow] for generation 0, else the generation's
  // family. Switched (with bow_generation) only under the owning map's lifecycle_ exclusively;
  // read under a shared hold, as the handles are.
  std::atomic<rocksdb::ColumnFamilyHandle*> active_bow{nullptr};
  std::atomic<uint64_t> bow_generation{0};
  // Every "bow.<g>" family open (the active one, and the one an adaptation is filling); created
  // and dropped under a shared hold by the one adaptation at a time, closed by Close().
  Mutex generation_mutex;
  std::vector<std::pair<uint64_t, rocksdb::ColumnFamilyHandle*>> generation_handles
      GUARDED_BY(generation_mutex);
  rocksdb::ColumnFamilyOptions generation_options;  // the "bow" family's, set at open

  rocksdb::ColumnFamilyHandle* cf(Cf which) const {
    if (which == kBow) {
      if (rocksdb::ColumnFamilyHandle* active = active_bow.load(std::memory_order_acquire)) {
        return active;
      }
    }
    return handles[size_t(which)];
  }

  // The BoW value of a place stored now: with its direct index once the map has its own
  // vocabulary (generation > 0), as EncodeBow before.
  std::string BowValue(const BowVector& bow, const DirectIndex& direct) const {
    return bow_generation.load() > 0 ? EncodeBowWithDirect(bow, direct) : EncodeBow(bow);
  }

  void Close() {
    committer.reset();
    acks.reset();
    if (db) {
      {
        MutexLock lock(generation_mutex);
        for (auto& [generation, handle] : generation_handles) {
          (void)db->DestroyColumnFamilyHandle(handle);
        }
        generation_handles.clear();
      }
      active_bow = nullptr;
      for (auto* handle : handles) {
        if (handle) (void)db->DestroyColumnFamilyHandle(handle);
      }
      handles.clear();
      (void)db->Close();
      db.reset();
    }
  }
  ~MapStorage() { Close(); }

  Status DiskFull(const std::string& what) const {
    return Status::ResourceExhausted("disk full: map '" + map_name + "': " + what +
                                     " failed (its data directory has no space left; free "
                                     "space, then retry)");
  }

  // Free space of the file system beyond what flushing the memtables takes, compared to
  // `margin`. True when the free space cannot be read.
  bool HasRoom(uint64_t margin) const {
    const std::optional<uint64_t> available = AvailableBytes(path);
    if (!available) return true;
    uint64_t memtables = 0;
    db->GetAggregatedIntProperty(rocksdb::DB::Properties::kCurSizeAllMemTables, &memtables);
    return *available >= memtables + margin;
  }

  Status WriteError(const rocksdb::Status& s, const std::string& what) {
    if (s.IsNoSpace()) {
      resume_needed = true;
      return DiskFull(what);
    }
    return FromRocks(s, what);
  }

  // What a write is: whether the free-space reserve holds it back, and whether it is synced and
  // counted as acknowledged (ACKED and the database's own count).
  enum class Kind {
    kAddition,  // a new place or invalid observation: held back by the reserve
    kRemoval,   // never held back by the reserve, so space can be freed
    kCounter,   // rides on the next synced write: neither synced nor acknowledged
  };

  // Adds one frame's statistics to its place's and to the map's (merge operands: no read).
  void AddDynamics(rocksdb::WriteBatch* batch, PlaceId place, const PlaceDynamics& delta) {
    if (!dynamics) return;
    const std::string operand = EncodeDynamics(delta);
    if (place != 0) batch->Merge(cf(kDynamics), PlaceKey(place), operand);
    batch->Merge(cf(kDynamics), kMapDynamicsKey, operand);
  }
  // An invalid frame's statistics, to the invalid frames' aggregate only.
  void AddInvalidDynamics(rocksdb::WriteBatch* batch, const PlaceDynamics& delta) {
    if (dynamics) batch->Merge(cf(kDynamics), kInvalidDynamicsKey, EncodeDynamics(delta));
  }

  // `what` names the operation for messages ("storing place 12"); `place`: the id of the place
  // the batch stores, 0 for other writes.
  // `writes`: how many acknowledged writes the batch holds (a group of places is one batch).
  Status Write(rocksdb::WriteBatch* batch, const std::string& what, Kind kind, PlaceId place = 0,
               uint64_t writes = 1) {
    if (resume_needed) PLACEDB_RETURN_IF_ERROR(Resume(what));
    if (kind == Kind::kAddition && reserve_bytes > 0 && !HasRoom(reserve_bytes)) {
      return DiskFull(what);
    }
    const bool acknowledged = kind != Kind::kCounter;
    // Counted in the batch itself, so the database holds exactly the writes it kept.
    if (acknowledged) batch->Merge(cf(kMeta), kWritesKey, CounterOperand(writes));
    rocksdb::WriteOptions options;
    options.sync = acknowledged && sync == SyncMode::kEveryWrite;
    if (rocksdb::Status s = db->Write(options, batch); !s.ok()) return WriteError(s, what);
    if (!acknowledged) return Status::Ok();
    if (committer) {
      if (rocksdb::Status s = committer->WaitDurable(); !s.ok()) return WriteError(s, what);
    }
    // Durable in the WAL; ACKED counts it before anyone is told.
    if (acks) return acks->Acknowledge(place, writes).WithContext(what);
    return Status::Ok();
  }

  Status Resume(const std::string& what) {
    // Writers that come while another resumes are refused, not queued: should a Resume never
    // return, it holds one worker, not every writer of the map.
    bool idle = false;
    if (!resuming.compare_exchange_strong(idle, true)) return DiskFull(what);
    struct Done {
      std::atomic<bool>& resuming;
      ~Done() { resuming = false; }
    } done{resuming};
    if (!resume_needed) return Status::Ok();  // another writer resumed meanwhile
    // Resume flushes the memtables into new files. One that fails for lack of space was seen to
    // leave the next DB::Resume() of RocksDB 7.8 waiting for good, so it is only tried once the
    // memtables fit with room to spare.
    if (!HasRoom(std::max(reserve_bytes, uint64_t(8) << 20))) return DiskFull(what);
    const rocksdb::Status s = db->Resume();
    if (s.ok()) {
      resume_needed = false;
      return Status::Ok();
    }
    if (s.IsNoSpace() || s.IsBusy()) return DiskFull(what);
    return FromRocks(s, what + " (resuming after a full disk)");
  }
};

// Payloads live in RocksDB: read on demand for verification and for loop closure's long-term
// memory, deleted durably on removal.
class RocksPayloadStore final : public PayloadStore {
 public:
  RocksPayloadStore(MapStorage* storage, FeatureType type) : storage_(storage), type_(type) {}

  // The map wrote the payload in the place's batch before indexing it.
  Status Put(PlaceId, std::shared_ptr<const PlacePayload>) override { return Status::Ok(); }
  bool KeepsPayloads() const override { return false; }  // the place's batch holds them

  // The vector alone: loop closure's long-term memory needs no features.
  Result<BowVector> GetBow(PlaceId id) const override {
    std::string bow_bytes;
    auto s =
        storage_->db->Get(rocksdb::ReadOptions(), storage_->cf(kBow), PlaceKey(id), &bow_bytes);
    if (s.IsNotFound()) return Status::NotFound("place " + std::to_string(id) + " not found");
    PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading place " + std::to_string(id)));
    auto bow = DecodeBow(bow_bytes);
    if (!bow.ok()) return bow.status().WithContext("place " + std::to_string(id));
    return bow;
  }

  // A place's BoW vector and features are written and deleted in one batch: features missing
  // while the vector is still there is damage (CORRUPTION), never "not found". Only then is the
  // vector read again (a removal between the two reads), so verification's reads cost no more.
  Result<std::shared_ptr<const PlacePayload>> Get(PlaceId id) const override {
    const std::string key = PlaceKey(id);
    std::string bow_bytes, feature_bytes;
    rocksdb::ReadOptions options;
    auto s = storage_->db->Get(options, storage_->cf(kBow), key, &bow_bytes);
    if (s.IsNotFound()) return Status::NotFound("place " + std::to_string(id) + " not found");
    PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading place " + std::to_string(id)));
    s = storage_->db->Get(options, storage_->cf(kFeatures), key, &feature_bytes);
    if (s.IsNotFound()) {
      std::string again;
      if (storage_->db->Get(options, storage_->cf(kBow), key, &again).IsNotFound()) {
        return Status::NotFound("place " + std::to_string(id) + " not found");  // removed
      }
      return Status::Corruption("place " + std::to_string(id) +
                                ": its features are missing (lost with a file of the map; "
                                "ScrubMap lists the places affected)");
    }
    PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading features of place " + std::to_string(id)));
    auto payload = std::make_shared<PlacePayload>();
    std::optional<DirectIndex> direct;
    PLACEDB_RETURN_IF_ERROR(DecodeBowValue(bow_bytes, &payload->bow, &direct)
                                .WithContext("place " + std::to_string(id)));
    PLACEDB_RETURN_IF_ERROR(DecodePayloadFeatures(type_, feature_bytes, payload.get())
                                .WithContext("place " + std::to_string(id)));
    if (direct) {
      // The map's own vocabulary: the direct index stored with the vector is this vocabulary's.
      if (!DirectIndexFits(*direct, payload->features.size())) {
        return Status::Corruption("place " + std::to_string(id) +
                                  ": its direct index names features it does not have");
      }
      payload->direct = std::move(*direct);
    }
    return std::shared_ptr<const PlacePayload>(std::move(payload));
  }

  // Called under the database's writer lock, so removals are serialised and id_floor only grows.
  Status Erase(PlaceId id) override {
    // The index an adaptation builds beside the live one (issue 29) drops places that were
    // removed meanwhile from itself only: the live map removed them durably already.
    if (!erases_.load()) return Status::Ok();
    rocksdb::WriteBatch batch;
    const std::string key = PlaceKey(id);
    batch.Delete(storage_->cf(kPlaces), key);
    batch.Delete(storage_->cf(kBow), key);
    batch.Delete(storage_->cf(kFeatures), key);
    batch.Delete(storage_->cf(kDynamics), key);  // the map's aggregate keeps its history
    batch.Delete(storage_->cf(kThumbnails), key);
    std::string floor;
    auto s = storage_->db->Get({}, storage_->cf(kMeta), kIdFloorKey, &floor);
    PlaceId current = 0;
    if (s.ok()) {
      auto decoded = DecodePlaceKey(floor);
      if (decoded.ok()) current = *decoded;
    }
    if (id + 1 > current) batch.Put(storage_->cf(kMeta), kIdFloorKey, PlaceKey(id + 1));
    if (t_applying_sequence) {
      batch.Put(storage_->cf(kMeta), kAppliedSequenceKey, *t_applying_sequence);
    }
    return storage_->Write(&batch, "removing place " + std::to_string(id),
                           MapStorage::Kind::kRemoval);
  }

  size_t MemoryBytes() const override { return 0; }

  // Off while the index this store serves is being built beside the live one; on once it is.
  void set_erases(bool erases) { erases_ = erases; }

 private:
  MapStorage* storage_;
  const FeatureType type_;
  std::atomic<bool> erases_{true};
};

// A map's info record (the meta family's "info") as JSON, and back (data_directory.cc).
std::string EncodeInfo(const MapInfo& info);
Result<MapInfo> DecodeInfo(const std::string& text);

// Issue 29 (vocabulary_switch.cc): the vocabulary record as JSON (kVocabularyRecordKey), and
// back (CORRUPTION naming the key that is wrong).
std::string EncodeVocabularyRecord(const VocabularyRecord& record);
Result<VocabularyRecord> DecodeVocabularyRecord(std::string_view json);
// Fills info->vocabulary from the stored record; without one (generation 0), a file's
// vocabulary named by the info's checksum, since the map was created.
Status ReadVocabularyRecord(MapStorage& storage, MapInfo* info);
// The vocabulary a map stores (nullopt when it stores none: generation 0). CORRUPTION when the
// stored bytes are damaged or are not the vocabulary the info names.
Result<std::optional<AnyVocabulary>> ReadStoredVocabulary(MapStorage& storage, const MapInfo& info);

// How an existing map's RocksDB is opened.
enum class Recovery {
  kStrict,       // kAbsoluteConsistency + WAL tracking: any damage is an error
  kPointInTime,  // RocksDB's default: stop replaying the WAL at the first bad record
};

// The map's column families in Cf order, with their options; `cache_void` is the data
// directory's block cache (a rocksdb::Cache).
std::vector<rocksdb::ColumnFamilyDescriptor> Families(const std::shared_ptr<void>& cache_void);

// `path`: the map's directory, for its info log; empty for read-only opens (which write none).
rocksdb::DBOptions RecoveryOptions(Recovery recovery, const std::string& path);

// Opens the map's RocksDB at `path` for writing (`create`: a new map, which must not exist),
// with `options`' settings (sync mode and group commit, disk reserve, dynamics, load threads).
// `create_families`: also create column families that are missing (recovery).
Result<std::unique_ptr<MapStorage>> OpenStorage(const std::string& path, bool create,
                                                const StorageOptions& options,
                                                const std::shared_ptr<void>& cache_void,
                                                Recovery recovery = Recovery::kStrict,
                                                bool create_families = false);

// Issue 29: creates the family of vocabulary generation `generation` (added to
// generation_handles); drops one (nothing when it is not open); clears a family's place keys
// with one range deletion (the "bow" family once a later generation is active).
Result<rocksdb::ColumnFamilyHandle*> CreateGenerationFamily(MapStorage& storage,
                                                            uint64_t generation);
Status DropGenerationFamily(MapStorage& storage, uint64_t generation);
Status ClearFamily(MapStorage& storage, rocksdb::ColumnFamilyHandle* family);

// Read-only: changes no file (a WAL is replayed into memory only).
Result<std::unique_ptr<MapStorage>> OpenReadOnly(const std::string& path,
                                                 const std::shared_ptr<void>& cache_void,
                                                 Recovery recovery);

}  // namespace placedb::detail
