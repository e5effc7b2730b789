#include "core/storage/map_store.h"

#include <rocksdb/cache.h>
#include <rocksdb/convenience.h>
#include <rocksdb/db.h>
#include <rocksdb/filter_policy.h>
#include <rocksdb/listener.h>
#include <rocksdb/merge_operator.h>
#include <rocksdb/table.h>
#include <rocksdb/utilities/checkpoint.h>
#include <rocksdb/write_batch.h>
#include <sys/statvfs.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdarg>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>

#include "core/base/files.h"

namespace fs = std::filesystem;

namespace placedb {

namespace {

constexpr char kMarkerFile[] = "PLACEDB_DATA_DIR";
constexpr char kMarkerText[] = "placedb data directory, format 1\n";
constexpr char kMapFormat[] = "placedb-map-1";

// Meta keys in the default column family.
constexpr char kFormatKey[] = "format";
constexpr char kInfoKey[] = "info";
constexpr char kIdFloorKey[] = "id_floor";               // ids below this were handed out once
constexpr char kInvalidCountKey[] = "invalid_rejected";  // merge counter

const char* const kColumnFamilies[] = {rocksdb::kDefaultColumnFamilyName.c_str(), "places", "bow",
                                       "features", "invalid"};
enum Cf { kMeta = 0, kPlaces, kBow, kFeatures, kInvalid, kCfCount };

Status FromRocks(const rocksdb::Status& s, const std::string& context) {
  if (s.ok()) return Status::Ok();
  const std::string message = context + ": " + s.ToString();
  if (s.IsNotFound()) return Status::NotFound(message);
  if (s.IsCorruption()) return Status::Corruption(message);
  // NoSpace is an IOError with a subcode: checked first.
  if (s.IsNoSpace() || s.IsMemoryLimit()) return Status::ResourceExhausted(message);
  if (s.IsIOError()) return Status::IoError(message);
  if (s.IsInvalidArgument()) return Status::Corruption(message);  // e.g. missing column family
  return Status::Internal(message);
}

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

std::string CounterOperand(uint64_t v) {
  return std::string(reinterpret_cast<const char*>(&v), 8);
}

// Options chosen for this workload; docs/storage.md explains each.
rocksdb::ColumnFamilyOptions FamilyOptions(Cf cf, const std::shared_ptr<rocksdb::Cache>& cache) {
  rocksdb::ColumnFamilyOptions options;
  rocksdb::BlockBasedTableOptions table;
  table.block_cache = cache;
  table.filter_policy.reset(rocksdb::NewBloomFilterPolicy(10));
  table.cache_index_and_filter_blocks = true;
  table.pin_l0_filter_and_index_blocks_in_cache = true;
  switch (cf) {
    case kFeatures:
      // 32-byte descriptors are near-random bits: compression costs CPU and saves nothing.
      options.compression = rocksdb::kNoCompression;
      options.write_buffer_size = size_t(32) << 20;
      table.block_size = 16 * 1024;  // one place's features is ~50 KB: fewer, larger blocks
      break;
    case kBow:
      // Already compact (delta varints + float32); read sequentially only on open.
      options.compression = rocksdb::kNoCompression;
      options.write_buffer_size = size_t(16) << 20;
      break;
    default:
      options.compression = rocksdb::kLZ4Compression;  // strings and small records
      options.write_buffer_size = size_t(4) << 20;
      break;
  }
  options.max_write_buffer_number = 3;
  options.level_compaction_dynamic_level_bytes = true;
  options.table_factory.reset(rocksdb::NewBlockBasedTableFactory(table));
  if (cf == kMeta) options.merge_operator = std::make_shared<CounterMergeOperator>();
  return options;
}

// RocksDB's info log (`LOG` in the map's directory), written without RocksDB's own file writer:
// once a write to that one has failed (a full disk), its next line trips an assertion, and
// Debian's librocksdb 7.8 is built with assertions, so a full disk aborted the process. Lines
// that cannot be written are dropped; the previous log is kept as LOG.old.
class InfoLog final : public rocksdb::Logger {
 public:
  explicit InfoLog(const std::string& path) {
    std::error_code ec;
    fs::rename(path, path + ".old", ec);
    file_ = std::fopen(path.c_str(), "w");
  }
  ~InfoLog() override {
    if (!closed_) {
      closed_ = true;
      (void)CloseImpl();
    }
  }
  using rocksdb::Logger::Logv;
  void Logv(const char* format, va_list ap) override {
    if (!file_) return;
    char line[2048];
    const auto now = std::chrono::system_clock::now();
    const std::time_t seconds = std::chrono::system_clock::to_time_t(now);
    std::tm utc{};
    gmtime_r(&seconds, &utc);
    const auto micros =
        std::chrono::duration_cast<std::chrono::microseconds>(now.time_since_epoch()).count() %
        1000000;
    int n = std::snprintf(line, sizeof line, "%04d/%02d/%02d-%02d:%02d:%02d.%06lld ",
                          utc.tm_year + 1900, utc.tm_mon + 1, utc.tm_mday, utc.tm_hour, utc.tm_min,
                          utc.tm_sec, static_cast<long long>(micros));
    const int body = std::vsnprintf(line + n, sizeof line - size_t(n) - 1, format, ap);
    if (body > 0) n = std::min(n + body, int(sizeof line) - 2);
    if (line[n - 1] != '\n') line[n++] = '\n';
    if (std::fwrite(line, 1, size_t(n), file_) != size_t(n) || std::fflush(file_) != 0) {
      std::clearerr(file_);  // a full disk: drop the line, try again with the next
    }
  }

 protected:
  rocksdb::Status CloseImpl() override {
    if (file_) std::fclose(file_);
    file_ = nullptr;
    return rocksdb::Status::OK();
  }

 private:
  std::FILE* file_ = nullptr;
};

// `directory`: the map's RocksDB directory, created here when missing (for the info log).
rocksdb::DBOptions DatabaseOptions(const std::string& directory) {
  rocksdb::DBOptions options;
  std::error_code ec;
  fs::create_directories(directory, ec);
  options.info_log = std::make_shared<InfoLog>((fs::path(directory) / "LOG").string());
  options.IncreaseParallelism(2);
  options.paranoid_checks = true;
  options.max_open_files = 256;
  options.keep_log_file_num = 3;
  options.max_total_wal_size = size_t(128) << 20;
  options.avoid_flush_during_shutdown = false;
  return options;
}

uint64_t DirectoryBytes(const std::string& path) {
  uint64_t total = 0;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(path, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    std::error_code size_ec;
    if (it->is_regular_file(size_ec)) {
      const auto size = it->file_size(size_ec);
      if (!size_ec) total += size;
    }
  }
  return total;
}

int64_t NowUnixMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string EncodeInfo(const MapInfo& info) {
  nlohmann::json j;
  j["name"] = info.name;
  j["database"] = nlohmann::json::parse(EncodeDatabaseConfig(info.options.database));
  j["store_invalid"] = info.options.store_invalid;
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
    info.options.service_json = j.value("service", std::string());
    info.vocabulary_checksum = j.at("vocabulary_checksum").get<uint64_t>();
    info.created_unix_ms = j.at("created_unix_ms").get<int64_t>();
  } catch (const nlohmann::json::exception& e) {
    return Status::Corruption(std::string("map info: ") + e.what());
  }
  return info;
}

std::string Hex(uint64_t v) {
  char buffer[17];
  std::snprintf(buffer, sizeof buffer, "%016llx", static_cast<unsigned long long>(v));
  return buffer;
}

// Acknowledges unsynced writes once a WAL sync that began after them has finished, so that
// concurrent writers share one fsync at most every `delay`.
class GroupCommitter {
 public:
  GroupCommitter(rocksdb::DB* db, std::chrono::milliseconds delay)
      : db_(db), delay_(delay), thread_([this] { Run(); }) {}
  ~GroupCommitter() {
    {
      MutexLock lock(mutex_);
      stopping_ = true;
    }
    wake_syncer_.NotifyAll();
    thread_.join();
  }

  rocksdb::Status WaitDurable() {
    MutexLock lock(mutex_);
    const uint64_t ticket = ++requested_;
    wake_syncer_.NotifyOne();
    while (synced_ < ticket) synced_cv_.Wait(mutex_);
    return last_status_;
  }

 private:
  void Run() {
    MutexLock lock(mutex_);
    while (true) {
      while (!stopping_ && requested_ <= synced_) wake_syncer_.Wait(mutex_);
      if (requested_ == synced_ && stopping_) return;
      if (!stopping_) {
        // Let more writers join this sync, bounded by the configured delay.
        const auto deadline = std::chrono::steady_clock::now() + delay_;
        while (!stopping_ && wake_syncer_.WaitUntil(mutex_, deadline)) {
        }
      }
      const uint64_t target = requested_;
      lock.Unlock();
      const rocksdb::Status synced = db_->SyncWAL();
      lock.Lock();
      last_status_ = synced;
      synced_ = target;
      synced_cv_.NotifyAll();
    }
  }

  rocksdb::DB* db_;
  const std::chrono::milliseconds delay_;
  Mutex mutex_;
  CondVar wake_syncer_;
  CondVar synced_cv_;
  uint64_t requested_ GUARDED_BY(mutex_) = 0;
  uint64_t synced_ GUARDED_BY(mutex_) = 0;
  bool stopping_ GUARDED_BY(mutex_) = false;
  rocksdb::Status last_status_ GUARDED_BY(mutex_);
  std::thread thread_;
};

}  // namespace

namespace detail {
struct MapStorage {
  // Set before the map is shared and reset only by Close(), under the owning PlaceMap's
  // lifecycle_ exclusively; every other use holds it shared. Not GUARDED_BY: the payload store
  // reads them inside PlaceDatabase calls made under the caller's hold, which the analysis
  // cannot follow.
  std::unique_ptr<rocksdb::DB> db;
  std::vector<rocksdb::ColumnFamilyHandle*> handles;
  SyncMode sync = SyncMode::kEveryWrite;
  std::unique_ptr<GroupCommitter> committer;
  std::string map_name;  // for messages: never the directory's path
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

  rocksdb::ColumnFamilyHandle* cf(Cf which) const { return handles[size_t(which)]; }

  void Close() {
    committer.reset();
    if (db) {
      for (auto* handle : handles) (void)db->DestroyColumnFamilyHandle(handle);
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
    struct statvfs info {};
    if (statvfs(path.c_str(), &info) != 0) return true;
    uint64_t memtables = 0;
    db->GetAggregatedIntProperty(rocksdb::DB::Properties::kCurSizeAllMemTables, &memtables);
    return uint64_t(info.f_bavail) * info.f_frsize >= memtables + margin;
  }

  Status WriteError(const rocksdb::Status& s, const std::string& what) {
    if (s.IsNoSpace()) {
      resume_needed = true;
      return DiskFull(what);
    }
    return FromRocks(s, what);
  }

  // `what` names the operation for messages ("storing place 12"). `adds` = false for removals,
  // which the reserve does not hold back. `durable` = false: a write that may ride on the next
  // synced one (counters).
  Status Write(rocksdb::WriteBatch* batch, const std::string& what, bool adds,
               bool durable = true) {
    if (resume_needed) PLACEDB_RETURN_IF_ERROR(Resume(what));
    if (adds && reserve_bytes > 0 && !HasRoom(reserve_bytes)) return DiskFull(what);
    rocksdb::WriteOptions options;
    options.sync = durable && sync == SyncMode::kEveryWrite;
    if (rocksdb::Status s = db->Write(options, batch); !s.ok()) return WriteError(s, what);
    if (durable && committer) {
      if (rocksdb::Status s = committer->WaitDurable(); !s.ok()) return WriteError(s, what);
    }
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

// Keeps RocksDB's own NoSpace recovery off: it waits for free space of a whole write buffer
// (32 MB here), polls every few seconds and meanwhile refuses DB::Resume(). MapStorage::Write
// resumes on the next write instead.
class DiskFullListener : public rocksdb::EventListener {
 public:
  explicit DiskFullListener(MapStorage* storage) : storage_(storage) {}
  void OnBackgroundError(rocksdb::BackgroundErrorReason, rocksdb::Status* error) override {
    if (error->IsNoSpace()) storage_->resume_needed = true;
  }
  void OnErrorRecoveryBegin(rocksdb::BackgroundErrorReason, rocksdb::Status,
                            bool* auto_recovery) override {
    *auto_recovery = false;
  }

 private:
  MapStorage* const storage_;  // outlives the DB: MapStorage::Close() closes it first
};

}  // namespace detail

using detail::DiskFullListener;
using detail::MapStorage;

namespace {

// A place's features value, decoded by the map's feature type.
Status DecodePayloadFeatures(FeatureType type, std::string_view bytes, PlacePayload* payload) {
  return DecodeLocalFeatures(bytes, type, &payload->features, &payload->direct);
}

// Payloads live in RocksDB: read on demand for verification and for loop closure's long-term
// memory, deleted durably on removal.
class RocksPayloadStore final : public PayloadStore {
 public:
  RocksPayloadStore(MapStorage* storage, FeatureType type) : storage_(storage), type_(type) {}

  // The map wrote the payload in the place's batch before indexing it.
  Status Put(PlaceId, std::shared_ptr<const PlacePayload>) override { return Status::Ok(); }

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

  Result<std::shared_ptr<const PlacePayload>> Get(PlaceId id) const override {
    const std::string key = PlaceKey(id);
    std::string bow_bytes, feature_bytes;
    rocksdb::ReadOptions options;
    auto s = storage_->db->Get(options, storage_->cf(kBow), key, &bow_bytes);
    if (s.IsNotFound()) return Status::NotFound("place " + std::to_string(id) + " not found");
    PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading place " + std::to_string(id)));
    PLACEDB_RETURN_IF_ERROR(
        FromRocks(storage_->db->Get(options, storage_->cf(kFeatures), key, &feature_bytes),
                  "reading features of place " + std::to_string(id)));
    auto payload = std::make_shared<PlacePayload>();
    auto bow = DecodeBow(bow_bytes);
    if (!bow.ok()) return bow.status().WithContext("place " + std::to_string(id));
    payload->bow = std::move(bow).value();
    PLACEDB_RETURN_IF_ERROR(DecodePayloadFeatures(type_, feature_bytes, payload.get())
                                .WithContext("place " + std::to_string(id)));
    return std::shared_ptr<const PlacePayload>(std::move(payload));
  }

  // Called under the database's writer lock, so removals are serialised and id_floor only grows.
  Status Erase(PlaceId id) override {
    rocksdb::WriteBatch batch;
    const std::string key = PlaceKey(id);
    batch.Delete(storage_->cf(kPlaces), key);
    batch.Delete(storage_->cf(kBow), key);
    batch.Delete(storage_->cf(kFeatures), key);
    std::string floor;
    auto s = storage_->db->Get({}, storage_->cf(kMeta), kIdFloorKey, &floor);
    PlaceId current = 0;
    if (s.ok()) {
      auto decoded = DecodePlaceKey(floor);
      if (decoded.ok()) current = *decoded;
    }
    if (id + 1 > current) batch.Put(storage_->cf(kMeta), kIdFloorKey, PlaceKey(id + 1));
    return storage_->Write(&batch, "removing place " + std::to_string(id), /*adds=*/false);
  }

  size_t MemoryBytes() const override { return 0; }

 private:
  MapStorage* storage_;
  const FeatureType type_;
};

}  // namespace

PlaceMap::PlaceMap(MapInfo info, std::string path, std::unique_ptr<MapStorage> storage,
                   AnyVocabulary vocabulary)
    : info_(std::move(info)),
      path_(std::move(path)),
      storage_(std::move(storage)),
      vocabulary_(std::move(vocabulary)) {}

PlaceMap::~PlaceMap() {
  database_.reset();
  if (storage_ && storage_->db) {
    rocksdb::FlushOptions flush;
    (void)storage_->db->Flush(flush, storage_->handles);
  }
}

Status PlaceMap::Deleted() const {
  return Status::NotFound("map '" + info_.name + "' was deleted");
}

Result<QueryResult> PlaceMap::Query(const Observation& observation,
                                    const QueryOptions& options) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return database_->Query(observation, options);
}

QueryResult PlaceMap::Search(const ProcessedFrame& frame, const QueryOptions& options) const {
  ReaderLock alive(lifecycle_);
  if (closed_) {
    QueryResult result;
    result.rejection = Deleted().message();
    return result;
  }
  return database_->Search(frame, options);
}

Status PlaceMap::CheckVocabulary(const AnyVocabulary& vocabulary) const {
  if (!vocabulary) return Status::InvalidArgument("vocabulary is missing");
  const FeatureType type = info_.options.database.feature_type;
  if (vocabulary.feature_type() == type && vocabulary.checksum() == info_.vocabulary_checksum) {
    return Status::Ok();
  }
  return Status::FailedPrecondition("map '" + info_.name + "' was built with " +
                                    VocabularyKindName(type) + " vocabulary " +
                                    Hex(info_.vocabulary_checksum) + ", not " + vocabulary.kind() +
                                    " vocabulary " + vocabulary.checksum_hex());
}

Status PlaceMap::Load() {
  auto db = PlaceDatabase::Create(
      vocabulary_, info_.options.database,
      std::make_shared<RocksPayloadStore>(storage_.get(), info_.options.database.feature_type));
  if (!db.ok()) return db.status();
  database_ = std::move(db).value();
  rocksdb::ReadOptions options;
  options.fill_cache = false;  // a full scan would only evict the verification working set
  std::unique_ptr<rocksdb::Iterator> places(
      storage_->db->NewIterator(options, storage_->cf(kPlaces)));
  std::unique_ptr<rocksdb::Iterator> bows(storage_->db->NewIterator(options, storage_->cf(kBow)));
  places->SeekToFirst();
  bows->SeekToFirst();
  for (; places->Valid(); places->Next(), bows->Next()) {
    if (!bows->Valid() || places->key() != bows->key()) {
      return Status::Corruption("map '" + info_.name + "': place " + places->key().ToString(true) +
                                " has no BoW vector");
    }
    auto record = DecodePlaceRecord(places->value().ToStringView());
    if (!record.ok()) return record.status().WithContext("map '" + info_.name + "'");
    auto bow = DecodeBow(bows->value().ToStringView());
    if (!bow.ok()) return bow.status().WithContext("map '" + info_.name + "'");
    auto key = DecodePlaceKey(places->key().ToStringView());
    if (!key.ok() || *key != record->id) {
      return Status::Corruption("map '" + info_.name + "': place key and record disagree");
    }
    PLACEDB_RETURN_IF_ERROR(database_->Restore(std::move(record).value(), *bow));
  }
  PLACEDB_RETURN_IF_ERROR(FromRocks(places->status(), "scanning places"));
  if (bows->Valid()) {
    return Status::Corruption("map '" + info_.name + "': BoW vector without a place record");
  }
  PLACEDB_RETURN_IF_ERROR(FromRocks(bows->status(), "scanning BoW vectors"));

  std::string value;
  if (storage_->db->Get({}, storage_->cf(kMeta), kIdFloorKey, &value).ok()) {
    auto floor = DecodePlaceKey(value);
    if (!floor.ok()) return floor.status().WithContext("map '" + info_.name + "' id floor");
    database_->ReserveIdsBelow(*floor);
  }
  if (storage_->db->Get({}, storage_->cf(kMeta), kInvalidCountKey, &value).ok()) {
    rocksdb::Slice slice(value);
    database_->CountInvalid(CounterMergeOperator::Decode(&slice));
  }
  std::unique_ptr<rocksdb::Iterator> invalid(
      storage_->db->NewIterator(options, storage_->cf(kInvalid)));
  invalid->SeekToLast();
  if (invalid->Valid()) {
    auto serial = DecodeU64Key(invalid->key().ToStringView());
    if (!serial.ok()) return serial.status().WithContext("invalid-observation log");
    storage_->next_invalid_serial = *serial + 1;
    uint64_t count = 0;
    for (invalid->SeekToFirst(); invalid->Valid(); invalid->Next()) ++count;
    storage_->invalid_stored = count;
  }
  return FromRocks(invalid->status(), "scanning invalid observations");
}

Result<AddResult> PlaceMap::Add(const Observation& observation) {
  // Extraction runs outside the lifecycle lock (it touches no storage), so deleting the map
  // does not wait for it.
  auto frame = database_->Process(observation, FrameRole::kStream);
  if (!frame.ok()) return frame.status();
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  PLACEDB_RETURN_IF_ERROR(database_->AdvanceStream(&*frame, observation.metadata.agent_id));
  return CommitLocked(*frame, observation.metadata);
}

Status PlaceMap::AdvanceStream(ProcessedFrame* frame, const std::string& agent_id) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return database_->AdvanceStream(frame, agent_id);
}

Result<LoopClosureOutcome> PlaceMap::CloseLoop(const ProcessedFrame& frame,
                                               const PlaceMetadata& metadata, AddResult* added) {
  AddResult local;
  AddResult& result = added ? *added : local;
  result = AddResult();
  // One shared hold for the whole call: the store callback commits with CommitLocked() and the
  // long-term memory reads payloads from RocksDB, both under this hold. Taking the shared lock
  // again inside could deadlock behind a waiting DeleteMap (std::shared_mutex is not
  // reentrant and may block new readers while a writer waits).
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  bool committed = false;
  auto store = [&]() REQUIRES_SHARED(lifecycle_) -> Result<PlaceId> {
    auto stored = CommitLocked(frame, metadata);
    if (!stored.ok()) return stored.status();
    committed = true;
    result = *stored;
    if (!stored->stored) {
      return Status::Internal("loop closure: the frame was not stored" +
                              (stored->rejection.empty() ? "" : ": " + stored->rejection));
    }
    return stored->id;
  };
  auto outcome = database_->CloseLoop(frame, metadata, store);
  if (!outcome.ok()) return outcome.status();
  if (!committed) {
    // Merged into the previous place by rehearsal: nothing written.
    result.stored = false;
    result.id = 0;
    result.counts = frame.counts;
    result.boxes_used = frame.boxes_used;
    result.timings = frame.timings;
    result.depth_state = frame.depth_state;
  }
  result.timings.loop_closure_ms = outcome->update_ms;
  result.timings.total_ms += outcome->update_ms;
  return outcome;
}

Result<AddResult> PlaceMap::StoreInvalid(const ProcessedFrame& frame,
                                         const PlaceMetadata& metadata) {
  AddResult result;
  result.depth_state = frame.depth_state;
  result.counts = frame.counts;
  result.boxes_used = frame.boxes_used;
  result.timings = frame.timings;
  result.rejection = frame.rejection;
  Stopwatch store;
  rocksdb::WriteBatch batch;
  batch.Merge(storage_->cf(kMeta), kInvalidCountKey, CounterOperand(1));
  if (info_.options.store_invalid) {
    InvalidObservation observation;
    observation.serial = storage_->next_invalid_serial.fetch_add(1);
    observation.metadata = metadata;
    observation.counts = frame.counts;
    observation.boxes_used = frame.boxes_used;
    observation.reason = frame.rejection;
    batch.Put(storage_->cf(kInvalid), U64Key(observation.serial),
              EncodeInvalidObservation(observation));
    PLACEDB_RETURN_IF_ERROR(
        storage_->Write(&batch, "storing an invalid observation", /*adds=*/true));
    ++storage_->invalid_stored;
  } else {
    // Only a counter: not worth an fsync of its own; it rides on the next synced write.
    PLACEDB_RETURN_IF_ERROR(
        storage_->Write(&batch, "counting an invalid frame", /*adds=*/true, /*durable=*/false));
  }
  database_->CountInvalid();
  result.timings.store_ms = store.ElapsedMs();
  result.timings.total_ms += result.timings.store_ms;
  return result;
}

Result<AddResult> PlaceMap::Commit(const ProcessedFrame& frame, const PlaceMetadata& metadata) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return CommitLocked(frame, metadata);
}

Result<AddResult> PlaceMap::CommitLocked(const ProcessedFrame& frame,
                                         const PlaceMetadata& metadata) {
  if (frame.stream_pending) {
    return Status::FailedPrecondition(
        "the frame's stream stage is pending: call AdvanceStream before committing it");
  }
  if (!frame.valid) return StoreInvalid(frame, metadata);
  // Checked before writing: a batch the index then refused would leave an unindexed place.
  const DatabaseConfig& config = info_.options.database;
  if (frame.static_features.type() != config.feature_type) {
    return Status::InvalidArgument(std::string("frame's features are ") +
                                   FeatureTypeName(frame.static_features.type()) +
                                   ", the map's are " + FeatureTypeName(config.feature_type));
  }
  if (frame.direct.levels_up != config.verification.levels_up) {
    return Status::InvalidArgument("frame's direct index is at level " +
                                   std::to_string(frame.direct.levels_up) + ", the map uses " +
                                   std::to_string(config.verification.levels_up));
  }
  Stopwatch store;
  PlaceRecord record;
  record.id = database_->ReserveId();
  record.metadata = metadata;
  record.counts = frame.counts;
  record.boxes_used = frame.boxes_used;
  const std::string key = PlaceKey(record.id);
  rocksdb::WriteBatch batch;
  batch.Put(storage_->cf(kPlaces), key, EncodePlaceRecord(record));
  batch.Put(storage_->cf(kBow), key, EncodeBow(frame.bow));
  batch.Put(storage_->cf(kFeatures), key, EncodeLocalFeatures(frame.static_features, frame.direct));
  PLACEDB_RETURN_IF_ERROR(
      storage_->Write(&batch, "storing place " + std::to_string(record.id), /*adds=*/true));
  // Durable: now make it searchable.
  auto id = database_->Insert(frame, metadata, record.id);
  if (!id.ok()) return id.status();
  AddResult result;
  result.stored = true;
  result.id = *id;
  result.counts = frame.counts;
  result.boxes_used = frame.boxes_used;
  result.timings = frame.timings;
  result.depth_state = frame.depth_state;
  result.timings.store_ms = store.ElapsedMs();
  result.timings.total_ms += result.timings.store_ms;
  return result;
}

Result<StoredPlace> PlaceMap::GetPlace(PlaceId id) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  auto record = database_->Get(id);
  if (!record)
    return Status::NotFound("place " + std::to_string(id) + " not found in map '" + info_.name +
                            "'");
  RocksPayloadStore payloads(storage_.get(), info_.options.database.feature_type);
  auto payload = payloads.Get(id);
  if (!payload.ok()) return payload.status();
  return StoredPlace{*record, **payload};
}

Status PlaceMap::RemovePlace(PlaceId id) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return database_->Remove(id);
}

std::vector<InvalidObservation> PlaceMap::InvalidObservations(size_t limit) const {
  std::vector<InvalidObservation> out;
  ReaderLock alive(lifecycle_);
  if (closed_) return out;
  std::unique_ptr<rocksdb::Iterator> it(storage_->db->NewIterator({}, storage_->cf(kInvalid)));
  for (it->SeekToFirst(); it->Valid() && out.size() < limit; it->Next()) {
    auto decoded = DecodeInvalidObservation(it->value().ToStringView());
    if (decoded.ok()) out.push_back(std::move(decoded).value());
  }
  return out;
}

MapStats PlaceMap::Stats() const {
  MapStats stats;
  stats.database = database_->Stats();
  stats.invalid_stored = storage_->invalid_stored;
  ReaderLock alive(lifecycle_);
  if (closed_) return stats;
  stats.bytes_on_disk = DirectoryBytes(path_);
  uint64_t memtables = 0;
  storage_->db->GetAggregatedIntProperty(rocksdb::DB::Properties::kCurSizeAllMemTables, &memtables);
  stats.bytes_in_memory = stats.database.index_bytes + stats.database.record_bytes +
                          stats.database.payload_bytes + memtables;
  return stats;
}

Status PlaceMap::Checkpoint(const std::string& directory) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  if (fs::exists(directory)) {
    return Status::AlreadyExists("checkpoint directory " + directory + " already exists");
  }
  rocksdb::Checkpoint* raw = nullptr;
  PLACEDB_RETURN_IF_ERROR(
      FromRocks(rocksdb::Checkpoint::Create(storage_->db.get(), &raw), "creating a checkpoint"));
  std::unique_ptr<rocksdb::Checkpoint> checkpoint(raw);
  // log_size_for_flush = 0: flush memtables so the checkpoint needs no WAL replay.
  return FromRocks(checkpoint->CreateCheckpoint(directory, 0), "checkpoint into " + directory);
}

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
  return Status::Ok();
}

// ---------------------------------------------------------------------------------------------

DataDirectory::DataDirectory(std::string path, StorageOptions options)
    : path_(std::move(path)), options_(options) {
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
  fs::create_directories(root / "maps", ec);
  if (ec) return Status::IoError("creating " + (root / "maps").string() + ": " + ec.message());
  return std::unique_ptr<DataDirectory>(new DataDirectory(path, options));
}

Status DataDirectory::ValidateMapName(const std::string& name) {
  if (name.empty() || name.size() > 64) {
    return Status::InvalidArgument("map name must be 1-64 characters, got " +
                                   std::to_string(name.size()));
  }
  if (!std::isalnum(static_cast<unsigned char>(name[0]))) {
    return Status::InvalidArgument("map name '" + name + "' must start with a letter or digit");
  }
  for (char c : name) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_' && c != '.' && c != '-') {
      return Status::InvalidArgument("map name '" + name +
                                     "' may only hold letters, digits, '_', '.' and '-'");
    }
  }
  return Status::Ok();
}

std::string DataDirectory::MapPath(const std::string& name) const {
  return (fs::path(path_) / "maps" / name).string();
}

namespace {

Result<std::unique_ptr<MapStorage>> OpenStorage(const std::string& path, const std::string& name,
                                                bool create, const StorageOptions& options,
                                                const std::shared_ptr<void>& cache_void) {
  auto cache = std::static_pointer_cast<rocksdb::Cache>(cache_void);
  rocksdb::DBOptions db_options = DatabaseOptions(path);
  db_options.create_if_missing = create;
  db_options.error_if_exists = create;
  db_options.create_missing_column_families = create;
  std::vector<rocksdb::ColumnFamilyDescriptor> families;
  for (int cf = 0; cf < kCfCount; ++cf) {
    families.emplace_back(kColumnFamilies[cf], FamilyOptions(Cf(cf), cache));
  }
  auto storage = std::make_unique<MapStorage>();
  storage->map_name = name;
  storage->path = path;
  storage->reserve_bytes = options.disk_reserve_bytes;
  db_options.listeners.push_back(std::make_shared<DiskFullListener>(storage.get()));
  rocksdb::DB* raw = nullptr;
  rocksdb::Status s = rocksdb::DB::Open(db_options, path, families, &storage->handles, &raw);
  if (!s.ok()) return FromRocks(s, "opening map at " + path);
  storage->db.reset(raw);
  storage->sync = options.sync;
  if (options.sync == SyncMode::kGroupCommit) {
    storage->committer = std::make_unique<GroupCommitter>(
        raw, std::chrono::milliseconds(options.group_commit_delay_ms));
  }
  return storage;
}

Result<MapInfo> ReadInfo(MapStorage& storage, const std::string& path) {
  std::string format, info_text;
  auto s = storage.db->Get({}, storage.cf(kMeta), kFormatKey, &format);
  if (s.IsNotFound() || (s.ok() && format != kMapFormat)) {
    return Status::Corruption(path + " is a RocksDB database but not a placedb map (format '" +
                              format + "')");
  }
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading map format"));
  PLACEDB_RETURN_IF_ERROR(
      FromRocks(storage.db->Get({}, storage.cf(kMeta), kInfoKey, &info_text), "reading map info"));
  return DecodeInfo(info_text);
}

}  // namespace

Result<std::shared_ptr<PlaceMap>> DataDirectory::CreateMap(const std::string& name,
                                                           const MapOptions& options,
                                                           AnyVocabulary vocabulary) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  if (!vocabulary) return Status::InvalidArgument("vocabulary is missing");
  PLACEDB_RETURN_IF_ERROR(ValidateDatabaseConfig(options.database));
  const FeatureType type = options.database.feature_type;
  if (vocabulary.feature_type() != type) {
    return Status::InvalidArgument("map '" + name + "': feature_type " + FeatureTypeName(type) +
                                   " needs a " + VocabularyKindName(type) +
                                   " vocabulary; this one is " + vocabulary.kind());
  }
  MutexLock lock(mutex_);
  const std::string path = MapPath(name);
  if (fs::exists(path)) return Status::AlreadyExists("map '" + name + "' already exists");
  auto storage = OpenStorage(path, name, /*create=*/true, options_, block_cache_);
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

Result<MapInfo> DataDirectory::ReadMapInfo(const std::string& name) const {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  MutexLock lock(mutex_);
  if (auto it = open_.find(name); it != open_.end()) return it->second->info();
  const std::string path = MapPath(name);
  if (!fs::is_directory(path)) return Status::NotFound("map '" + name + "' not found");
  // Read-only open: safe while nothing else has the map open (we hold the lock).
  rocksdb::DBOptions db_options = DatabaseOptions(path);
  std::vector<rocksdb::ColumnFamilyDescriptor> families;
  auto cache = std::static_pointer_cast<rocksdb::Cache>(block_cache_);
  for (int cf = 0; cf < kCfCount; ++cf) {
    families.emplace_back(kColumnFamilies[cf], FamilyOptions(Cf(cf), cache));
  }
  MapStorage storage;
  rocksdb::DB* raw = nullptr;
  PLACEDB_RETURN_IF_ERROR(
      FromRocks(rocksdb::DB::OpenForReadOnly(db_options, path, families, &storage.handles, &raw),
                "opening map '" + name + "'"));
  storage.db.reset(raw);
  return ReadInfo(storage, path);
}

Result<std::shared_ptr<PlaceMap>> DataDirectory::OpenMap(const std::string& name,
                                                         AnyVocabulary vocabulary) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  if (!vocabulary) return Status::InvalidArgument("vocabulary is missing");
  MutexLock lock(mutex_);
  if (auto it = open_.find(name); it != open_.end()) {
    PLACEDB_RETURN_IF_ERROR(it->second->CheckVocabulary(vocabulary));
    return it->second;
  }
  const std::string path = MapPath(name);
  if (!fs::is_directory(path)) return Status::NotFound("map '" + name + "' not found");
  if (!fs::exists(fs::path(path) / "CURRENT")) {
    return Status::Corruption(path + " is not a RocksDB database (no CURRENT file)");
  }
  auto storage = OpenStorage(path, name, /*create=*/false, options_, block_cache_);
  if (!storage.ok()) return storage.status();
  auto info = ReadInfo(**storage, path);
  if (!info.ok()) return info.status();
  std::shared_ptr<PlaceMap> map(
      new PlaceMap(std::move(info).value(), path, std::move(storage).value(), vocabulary));
  PLACEDB_RETURN_IF_ERROR(map->CheckVocabulary(vocabulary));
  PLACEDB_RETURN_IF_ERROR(map->Load());
  open_[name] = map;
  return map;
}

std::vector<std::string> DataDirectory::ListMaps() const {
  std::vector<std::string> names;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(fs::path(path_) / "maps", ec)) {
    const std::string name = entry.path().filename().string();
    if (entry.is_directory() && ValidateMapName(name).ok()) names.push_back(name);
  }
  std::sort(names.begin(), names.end());
  return names;
}

Status DataDirectory::DeleteMap(const std::string& name) {
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(name));
  MutexLock lock(mutex_);
  const std::string path = MapPath(name);
  if (!fs::is_directory(path)) return Status::NotFound("map '" + name + "' not found");
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
  fs::copy(checkpoint, staging, fs::copy_options::recursive, ec);
  if (ec) return Status::IoError("copying " + checkpoint + ": " + ec.message());
  Status valid;
  {
    // Validate before it becomes visible: it must open as a placedb map; rename it inside.
    auto storage = OpenStorage(staging, name, false, options_, block_cache_);
    valid = storage.status();
    if (valid.ok()) {
      auto info = ReadInfo(**storage, staging);
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
