// A map's RocksDB (map_storage.h): its column families' options and merge operators, its info
// log, the status mapping, MapStorage's disk-full listener, opening a map's RocksDB, and
// CheckRoomFor (map_store.h).
#include "core/storage/map_storage.h"

#include <rocksdb/cache.h>
#include <rocksdb/filter_policy.h>
#include <rocksdb/listener.h>
#include <rocksdb/table.h>
#include <sys/statvfs.h>

#include <bit>
#include <chrono>
#include <cstdarg>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <system_error>

namespace fs = std::filesystem;

namespace placedb {

namespace detail {

std::optional<uint64_t> AvailableBytes(const std::string& path) {
  struct statvfs info {};
  if (statvfs(path.c_str(), &info) != 0) return std::nullopt;
  return uint64_t(info.f_bavail) * info.f_frsize;
}

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

namespace {

// Merges PlaceDynamics (core/dynamics): each acknowledged frame adds its own statistics to its
// place's and to the map's in the frame's batch. The merge is exact, associative and commutative,
// so RocksDB may combine operands in any grouping (partial merges in compactions). A value that
// does not decode fails the merge: RocksDB then reports Corruption (reads) or a background error
// (compaction) instead of silently dropping statistics.
class DynamicsMergeOperator : public rocksdb::AssociativeMergeOperator {
 public:
  bool Merge(const rocksdb::Slice&, const rocksdb::Slice* existing, const rocksdb::Slice& value,
             std::string* new_value, rocksdb::Logger* logger) const override {
    auto operand = DecodeDynamics(value.ToStringView());
    if (!operand.ok()) {
      rocksdb::Log(logger, "dynamics merge: %s", operand.status().ToString().c_str());
      return false;
    }
    if (!existing) {
      new_value->assign(value.data(), value.size());
      return true;
    }
    auto total = DecodeDynamics(existing->ToStringView());
    if (!total.ok()) {
      rocksdb::Log(logger, "dynamics merge: %s", total.status().ToString().c_str());
      return false;
    }
    placedb::Merge(&*total, *operand);
    *new_value = EncodeDynamics(*total);
    return true;
  }
  const char* Name() const override { return "placedb.DynamicsMerge"; }
};

}  // namespace

std::string CounterOperand(uint64_t v) {
  return std::string(reinterpret_cast<const char*>(&v), 8);
}

namespace {

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
    case kThumbnails:
      // JPEG is compressed already.
      options.compression = rocksdb::kNoCompression;
      options.write_buffer_size = size_t(4) << 20;
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
  if (cf == kDynamics) options.merge_operator = std::make_shared<DynamicsMergeOperator>();
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

}  // namespace

rocksdb::DBOptions DatabaseOptions(const std::string& directory) {
  rocksdb::DBOptions options;
  if (!directory.empty()) {
    std::error_code ec;
    fs::create_directories(directory, ec);
    options.info_log = std::make_shared<InfoLog>((fs::path(directory) / "LOG").string());
  }
  options.IncreaseParallelism(2);
  options.paranoid_checks = true;
  options.max_open_files = 256;
  options.keep_log_file_num = 3;
  options.max_total_wal_size = size_t(128) << 20;
  options.avoid_flush_during_shutdown = false;
  // A missing or shortened WAL is reported by RocksDB at open (not only by ACKED's count).
  options.track_and_verify_wals_in_manifest = true;
  return options;
}

std::string RelativeTo(std::string text, const std::string& map_path, const std::string& name) {
  const std::string relative = "maps/" + name;
  std::error_code ec;
  std::vector<std::string> forms = {fs::absolute(map_path, ec).lexically_normal().string(),
                                    fs::weakly_canonical(map_path, ec).string(), map_path};
  for (const std::string& form : forms) {
    if (form.empty()) continue;
    for (size_t at = text.find(form); at != std::string::npos;
         at = text.find(form, at + relative.size())) {
      text.replace(at, form.size(), relative);
    }
  }
  return text;
}

namespace {

int64_t NowUnixNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

}  // namespace

PlaceDynamics FrameDynamics(const ProcessedFrame& frame, const PlaceMetadata& metadata) {
  return MakeObservation(frame.counts.dynamic_coverage, frame.boxes_used, metadata.timestamp_ns,
                         NowUnixNs());
}

Status DecodePayloadFeatures(FeatureType type, std::string_view bytes, PlacePayload* payload) {
  return DecodeLocalFeatures(bytes, type, &payload->features, &payload->direct, &payload->geometry);
}

namespace {

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

}  // namespace

std::vector<rocksdb::ColumnFamilyDescriptor> Families(const std::shared_ptr<void>& cache_void) {
  auto cache = std::static_pointer_cast<rocksdb::Cache>(cache_void);
  std::vector<rocksdb::ColumnFamilyDescriptor> families;
  for (int cf = 0; cf < kCfCount; ++cf) {
    families.emplace_back(kColumnFamilies[cf], FamilyOptions(Cf(cf), cache));
  }
  return families;
}

std::string GenerationFamilyName(uint64_t generation) {
  if (generation == 0) return kColumnFamilies[kBow];
  return kGenerationFamilyPrefix + std::to_string(generation);
}

std::optional<uint64_t> GenerationOfFamily(const std::string& name) {
  if (name == kColumnFamilies[kBow]) return 0;
  const std::string prefix = kGenerationFamilyPrefix;
  if (name.size() <= prefix.size() || name.compare(0, prefix.size(), prefix) != 0) {
    return std::nullopt;
  }
  uint64_t generation = 0;
  for (size_t i = prefix.size(); i < name.size(); ++i) {
    if (name[i] < '0' || name[i] > '9' || generation > (UINT64_MAX - 9) / 10) return std::nullopt;
    generation = generation * 10 + uint64_t(name[i] - '0');
  }
  if (generation == 0) return std::nullopt;
  return generation;
}

Result<rocksdb::ColumnFamilyHandle*> CreateGenerationFamily(MapStorage& storage,
                                                            uint64_t generation) {
  rocksdb::ColumnFamilyHandle* handle = nullptr;
  const rocksdb::Status s = storage.db->CreateColumnFamily(
      storage.generation_options, GenerationFamilyName(generation), &handle);
  if (!s.ok()) return storage.WriteError(s, "creating the BoW family of a new vocabulary");
  MutexLock lock(storage.generation_mutex);
  storage.generation_handles.emplace_back(generation, handle);
  return handle;
}

Status DropGenerationFamily(MapStorage& storage, uint64_t generation) {
  rocksdb::ColumnFamilyHandle* handle = nullptr;
  {
    MutexLock lock(storage.generation_mutex);
    for (auto it = storage.generation_handles.begin(); it != storage.generation_handles.end();
         ++it) {
      if (it->first == generation) {
        handle = it->second;
        storage.generation_handles.erase(it);
        break;
      }
    }
  }
  if (!handle) return Status::Ok();
  const rocksdb::Status dropped = storage.db->DropColumnFamily(handle);
  (void)storage.db->DestroyColumnFamilyHandle(handle);
  return FromRocks(
      dropped, "dropping the BoW family of vocabulary generation " + std::to_string(generation));
}

Status ClearFamily(MapStorage& storage, rocksdb::ColumnFamilyHandle* family) {
  std::unique_ptr<rocksdb::Iterator> it(storage.db->NewIterator({}, family));
  it->SeekToFirst();
  if (!it->Valid()) return FromRocks(it->status(), "scanning a BoW family");
  // Place keys are 4 bytes: every one sorts below this 5-byte key.
  const std::string end(5, '\xff');
  return FromRocks(storage.db->DeleteRange({}, family, it->key(), end),
                   "clearing the BoW family of the previous vocabulary");
}

// The late families (kLateFamilies: added by later issues) the map at `path` lacks, when every

namespace {

// The late families (kLateFamilies: added by later issues) the map at `path` lacks, when every
// other family is there (a map made before them); empty otherwise. Any other family missing is
// damage, left for the open to report.
std::vector<Cf> LateFamiliesMissing(const std::string& path) {
  std::vector<std::string> present;
  if (!rocksdb::DB::ListColumnFamilies(rocksdb::DBOptions(), path, &present).ok()) return {};
  std::vector<Cf> missing;
  for (int cf = 0; cf < kCfCount; ++cf) {
    if (std::find(present.begin(), present.end(), kColumnFamilies[cf]) != present.end()) continue;
    if (std::find(std::begin(kLateFamilies), std::end(kLateFamilies), Cf(cf)) ==
        std::end(kLateFamilies)) {
      return {};
    }
    missing.push_back(Cf(cf));
  }
  return missing;
}

}  // namespace

rocksdb::DBOptions RecoveryOptions(Recovery recovery, const std::string& path) {
  const bool read_only = path.empty();
  rocksdb::DBOptions options = DatabaseOptions(path);
  if (recovery == Recovery::kStrict) {
    options.wal_recovery_mode = rocksdb::WALRecoveryMode::kAbsoluteConsistency;
  } else {
    options.wal_recovery_mode = rocksdb::WALRecoveryMode::kPointInTimeRecovery;
    // A read-write point-in-time open drops the MANIFEST's WAL records, so that a damaged or
    // missing log does not stop it. A read-only open must keep tracking on: turning it off makes
    // RocksDB 7.8 clear those records, which it cannot do read-only (Debian's build then fails
    // an assertion and aborts the process).
    if (!read_only) options.track_and_verify_wals_in_manifest = false;
  }
  return options;
}

namespace {

// The "bow.<g>" families of the map at `path` (issue 29), ascending; none for a new map.
std::vector<uint64_t> GenerationFamiliesAt(const std::string& path) {
  std::vector<std::string> present;
  std::vector<uint64_t> generations;
  if (!rocksdb::DB::ListColumnFamilies(rocksdb::DBOptions(), path, &present).ok()) return {};
  for (const std::string& name : present) {
    if (auto generation = GenerationOfFamily(name); generation && *generation > 0) {
      generations.push_back(*generation);
    }
  }
  std::sort(generations.begin(), generations.end());
  return generations;
}

// Descriptors of `generations`' families, after the fixed ones.
void AddGenerationFamilies(const std::vector<uint64_t>& generations,
                           const rocksdb::ColumnFamilyOptions& options,
                           std::vector<rocksdb::ColumnFamilyDescriptor>* families) {
  for (uint64_t generation : generations) {
    families->emplace_back(GenerationFamilyName(generation), options);
  }
}

// After the open: the generation families' handles (at the end of `handles`) moved to
// generation_handles, the stored generation made the active one. A read-write open drops the
// families of other generations (an adaptation a crash interrupted, or the previous
// vocabulary's whose drop it interrupted) and clears "bow" when a later generation is active.
Status SelectGeneration(MapStorage& storage, const std::vector<uint64_t>& generations,
                        bool read_write) {
  {
    MutexLock lock(storage.generation_mutex);
    for (size_t i = 0; i < generations.size(); ++i) {
      storage.generation_handles.emplace_back(
          generations[i], storage.handles[storage.handles.size() - generations.size() + i]);
    }
  }
  storage.handles.resize(storage.handles.size() - generations.size());
  std::string value;
  uint64_t active = 0;
  const rocksdb::Status s =
      storage.db->Get({}, storage.handles[kMeta], kVocabularyGenerationKey, &value);
  if (s.ok()) {
    auto decoded = DecodeU64Key(value);
    if (!decoded.ok()) return decoded.status().WithContext("the map's vocabulary generation");
    active = *decoded;
  } else if (!s.IsNotFound()) {
    return FromRocks(s, "reading the map's vocabulary generation");
  }
  storage.bow_generation = active;
  if (active > 0) {
    rocksdb::ColumnFamilyHandle* handle = nullptr;
    {
      MutexLock lock(storage.generation_mutex);
      for (auto& [generation, family] : storage.generation_handles) {
        if (generation == active) handle = family;
      }
    }
    if (!handle) {
      return Status::Corruption("the BoW family of the map's vocabulary (" +
                                GenerationFamilyName(active) + ") is missing");
    }
    storage.active_bow = handle;
  }
  if (!read_write) return Status::Ok();
  for (uint64_t generation : generations) {
    if (generation != active) PLACEDB_RETURN_IF_ERROR(DropGenerationFamily(storage, generation));
  }
  if (active > 0) PLACEDB_RETURN_IF_ERROR(ClearFamily(storage, storage.handles[kBow]));
  return Status::Ok();
}

}  // namespace

Result<std::unique_ptr<MapStorage>> OpenStorage(const std::string& path, bool create,
                                                const StorageOptions& options,
                                                const std::shared_ptr<void>& cache_void,
                                                Recovery recovery, bool create_families) {
  rocksdb::DBOptions db_options = RecoveryOptions(recovery, path);
  db_options.create_if_missing = create;
  db_options.error_if_exists = create;
  // A map made before issue 16 (20) gets its (empty) dynamics (thumbnails) family; no other
  // family is ever created on an existing map unless the caller says so (recovery).
  db_options.create_missing_column_families =
      create || create_families || !LateFamiliesMissing(path).empty();
  auto storage = std::make_unique<MapStorage>();
  storage->map_name = fs::path(path).filename().string();
  storage->path = path;
  storage->reserve_bytes = options.disk_reserve_bytes;
  storage->dynamics = options.dynamics;
  storage->load_threads = options.load_threads == 0 ? 2 : options.load_threads;
  storage->load_range_ids =
      options.load_range_ids == 0 ? 65536 : std::bit_floor(options.load_range_ids);
  db_options.listeners.push_back(std::make_shared<DiskFullListener>(storage.get()));
  storage->generation_options =
      FamilyOptions(kBow, std::static_pointer_cast<rocksdb::Cache>(cache_void));
  const std::vector<uint64_t> generations =
      create ? std::vector<uint64_t>() : GenerationFamiliesAt(path);
  std::vector<rocksdb::ColumnFamilyDescriptor> families = Families(cache_void);
  AddGenerationFamilies(generations, storage->generation_options, &families);
  rocksdb::DB* raw = nullptr;
  rocksdb::Status s = rocksdb::DB::Open(db_options, path, families, &storage->handles, &raw);
  if (!s.ok()) return FromRocks(s, "opening the map's RocksDB");
  storage->db.reset(raw);
  PLACEDB_RETURN_IF_ERROR(SelectGeneration(*storage, generations, /*read_write=*/true));
  storage->sync = options.sync;
  if (options.sync == SyncMode::kGroupCommit) {
    storage->committer = std::make_unique<GroupCommitter>(
        raw, std::chrono::milliseconds(options.group_commit_delay_ms));
  }
  return storage;
}

Result<std::unique_ptr<MapStorage>> OpenReadOnly(const std::string& path,
                                                 const std::shared_ptr<void>& cache_void,
                                                 Recovery recovery) {
  auto storage = std::make_unique<MapStorage>();
  rocksdb::DB* raw = nullptr;
  // A map made before issue 16 (20) is read without its dynamics (thumbnails) family (null
  // handle; read-only users never touch it).
  const std::vector<Cf> missing = LateFamiliesMissing(path);
  std::vector<rocksdb::ColumnFamilyDescriptor> families = Families(cache_void);
  for (auto cf = missing.rbegin(); cf != missing.rend(); ++cf) {
    families.erase(families.begin() + *cf);
  }
  storage->generation_options =
      FamilyOptions(kBow, std::static_pointer_cast<rocksdb::Cache>(cache_void));
  const std::vector<uint64_t> generations = GenerationFamiliesAt(path);
  AddGenerationFamilies(generations, storage->generation_options, &families);
  rocksdb::Status s = rocksdb::DB::OpenForReadOnly(RecoveryOptions(recovery, ""), path, families,
                                                   &storage->handles, &raw);
  if (!s.ok()) return FromRocks(s, "opening the map's RocksDB");
  storage->db.reset(raw);
  for (Cf cf : missing) {
    storage->handles.insert(storage->handles.begin() + cf, nullptr);
  }
  PLACEDB_RETURN_IF_ERROR(SelectGeneration(*storage, generations, /*read_write=*/false));
  return storage;
}

}  // namespace detail

Status CheckRoomFor(const std::string& path, uint64_t bytes, uint64_t reserve_bytes,
                    const std::string& what) {
  const std::optional<uint64_t> available = detail::AvailableBytes(path);
  if (!available || *available >= bytes + reserve_bytes) return Status::Ok();
  return Status::ResourceExhausted("disk full: " + what + " needs " + std::to_string(bytes) +
                                   " bytes; the data directory has " + std::to_string(*available) +
                                   " free, " + std::to_string(reserve_bytes) +
                                   " of them reserved (storage.disk_reserve_bytes)");
}

}  // namespace placedb
