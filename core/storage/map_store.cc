#include "core/storage/map_store.h"

#include <fcntl.h>
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
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <cerrno>
#include <chrono>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <span>
#include <system_error>
#include <thread>
#include <unordered_set>

#include "core/base/files.h"
#include "core/base/map_name.h"
#include "core/base/parallel.h"

namespace fs = std::filesystem;

namespace placedb {

namespace {

// Bytes an unprivileged writer may still use on the file system holding `path`; none when it
// cannot be read.
std::optional<uint64_t> AvailableBytes(const std::string& path) {
  struct statvfs info {};
  if (statvfs(path.c_str(), &info) != 0) return std::nullopt;
  return uint64_t(info.f_bavail) * info.f_frsize;
}

constexpr char kMarkerFile[] = "PLACEDB_DATA_DIR";
constexpr char kMarkerText[] = "placedb data directory, format 1\n";
constexpr char kMapFormat[] = "placedb-map-1";

// Meta keys in the default column family.
constexpr char kFormatKey[] = "format";
constexpr char kInfoKey[] = "info";
constexpr char kIdFloorKey[] = "id_floor";               // ids below this were handed out once
constexpr char kInvalidCountKey[] = "invalid_rejected";  // merge counter
// Merge counter, +1 in every batch that is acknowledged (places, removals, stored invalid
// frames): what the database holds, compared at open with ACKED (what was acknowledged).
constexpr char kWritesKey[] = "acked_writes";
constexpr char kDamageHistoryKey[] = "damage_history";  // JSON array of accepted losses
// Cluster mode: the last stream sequence applied (U64Key), written in each applied record's batch.
constexpr uint64_t kMaxPlaceId = std::numeric_limits<PlaceId>::max();
constexpr char kAppliedSequenceKey[] = "applied_sequence";
// Set by PlaceMap::ApplyAt on its own thread around PlaceDatabase::Remove: the removal's batch
// (RocksPayloadStore::Erase) then also records the applied sequence, atomically with it.
thread_local const std::string* t_applying_sequence = nullptr;
constexpr char kAckedFile[] = "ACKED";

const char* const kColumnFamilies[] = {rocksdb::kDefaultColumnFamilyName.c_str(),
                                       "places",
                                       "bow",
                                       "features",
                                       "invalid",
                                       "dynamics",
                                       "thumbnails"};
// kDynamics was added by issue 16, kThumbnails by issue 20: maps made before lack the family,
// which a read-write open creates (empty) and a read-only open does without (its handle is
// null). Only these "late" families are ever created on an existing map (LateFamiliesMissing).
enum Cf { kMeta = 0, kPlaces, kBow, kFeatures, kInvalid, kDynamics, kThumbnails, kCfCount };
constexpr Cf kLateFamilies[] = {kDynamics, kThumbnails};

// In kDynamics: the map's aggregate (every acknowledged observation, also of places removed
// since). Place keys are 4 bytes, so this 3-byte key is never one.
constexpr char kMapDynamicsKey[] = "map";
// In kDynamics: the aggregate of the frames refused as invalid (no place: too few static
// features, often because objects covered the view). Not part of the map's aggregate.
constexpr char kInvalidDynamicsKey[] = "invalid";

bool IsAggregateKey(const rocksdb::Slice& key) {
  return key == kMapDynamicsKey || key == kInvalidDynamicsKey;
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

// `directory`: the map's RocksDB directory, created here when missing, for its info log; empty
// for options that open no database (SST checksum verification).
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

// Replaces `map_path` (as given, and absolute) in `text` with "maps/<name>": client-visible
// messages never carry the server's absolute paths.
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

int64_t NowUnixNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
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

// ACKED: the acknowledged high-water mark, independent of RocksDB's files. Two 40-byte slots at
// offsets 0 and 512 (different sectors), written alternately with pwrite + fdatasync, so a torn
// write leaves the other slot intact; the valid slot with the higher generation wins.
// Slot: "PDBACK01", generation, acknowledged writes, highest acknowledged place id, FNV-1a 64 of
// the 32 bytes before it; integers little-endian.
struct AckState {
  uint64_t generation = 0;
  uint64_t writes = 0;
  uint64_t max_place = 0;
};

constexpr char kAckMagic[8] = {'P', 'D', 'B', 'A', 'C', 'K', '0', '1'};
constexpr size_t kAckSlotBytes = 40;
constexpr off_t kAckSlotOffset[2] = {0, 512};
constexpr size_t kAckFileBytes = 1024;

uint64_t Fnv1a(const unsigned char* data, size_t size) {
  uint64_t hash = 0xcbf29ce484222325ull;
  for (size_t i = 0; i < size; ++i) hash = (hash ^ data[i]) * 0x100000001b3ull;
  return hash;
}

void PutLe64(unsigned char* out, uint64_t v) {
  for (int i = 0; i < 8; ++i) out[i] = static_cast<unsigned char>(v >> (8 * i));
}

uint64_t GetLe64(const unsigned char* in) {
  uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | in[i];
  return v;
}

std::string Errno(const std::string& what) {
  return what + ": " + std::strerror(errno);
}

Status WriteAckSlot(int fd, const AckState& state) {
  unsigned char slot[kAckSlotBytes];
  std::memcpy(slot, kAckMagic, 8);
  PutLe64(slot + 8, state.generation);
  PutLe64(slot + 16, state.writes);
  PutLe64(slot + 24, state.max_place);
  PutLe64(slot + 32, Fnv1a(slot, 32));
  const off_t offset = kAckSlotOffset[state.generation % 2];
  // A full disk is RESOURCE_EXHAUSTED, as for RocksDB's own writes (FromRocks).
  auto failed = [](const std::string& what) {
    const std::string message = Errno(what);
    return errno == ENOSPC || errno == EDQUOT ? Status::ResourceExhausted(message)
                                              : Status::IoError(message);
  };
  if (pwrite(fd, slot, sizeof slot, offset) != ssize_t(sizeof slot)) {
    return failed("writing ACKED");
  }
  if (fdatasync(fd) != 0) return failed("syncing ACKED");
  return Status::Ok();
}

// NOT_FOUND when the file is missing; CORRUPTION when neither slot is valid.
Result<AckState> ReadAcked(const std::string& file) {
  const int fd = open(file.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return Status::NotFound("ACKED is missing");
    return Status::IoError(Errno("opening ACKED"));
  }
  unsigned char bytes[kAckFileBytes] = {};
  const ssize_t n = pread(fd, bytes, sizeof bytes, 0);
  close(fd);
  if (n < 0) return Status::IoError(Errno("reading ACKED"));
  std::optional<AckState> best;
  for (off_t offset : kAckSlotOffset) {
    if (n < offset + ssize_t(kAckSlotBytes)) continue;
    const unsigned char* slot = bytes + offset;
    if (std::memcmp(slot, kAckMagic, 8) != 0 || GetLe64(slot + 32) != Fnv1a(slot, 32)) continue;
    AckState state{GetLe64(slot + 8), GetLe64(slot + 16), GetLe64(slot + 24)};
    if (!best || state.generation > best->generation) best = state;
  }
  if (!best) {
    return Status::Corruption("ACKED is damaged: " + std::to_string(n) +
                              " bytes, no record passes its checksum");
  }
  return *best;
}

Status SyncDirectory(const std::string& directory) {
  const int fd = open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) return Status::IoError(Errno("opening " + directory));
  const int synced = fsync(fd);
  close(fd);
  if (synced != 0) return Status::IoError(Errno("syncing " + directory));
  return Status::Ok();
}

// Creates (or replaces) ACKED holding `state` in both slots, durably.
Status CreateAcked(const std::string& map_path, AckState state) {
  const std::string file = (fs::path(map_path) / kAckedFile).string();
  const std::string staging = file + ".tmp";
  const int fd = open(staging.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return Status::IoError(Errno("creating ACKED"));
  Status written;
  // Full size up front: later slot writes never change the size, so fdatasync stays cheap.
  if (ftruncate(fd, off_t(kAckFileBytes)) != 0) written = Status::IoError(Errno("sizing ACKED"));
  for (int i = 0; i < 2 && written.ok(); ++i, ++state.generation) {
    written = WriteAckSlot(fd, state);
  }
  close(fd);
  if (written.ok() && rename(staging.c_str(), file.c_str()) != 0) {
    written = Status::IoError(Errno("installing ACKED"));
  }
  if (written.ok()) written = SyncDirectory(map_path);
  return written;
}

// Records acknowledged writes in ACKED before they are acknowledged. Concurrent writers share
// one fdatasync: a writer that finds a sync in progress waits for the next one, which a leader
// among the waiters makes for all of them.
class AckTracker {
 public:
  static Result<std::unique_ptr<AckTracker>> Open(const std::string& map_path, AckState state) {
    const std::string file = (fs::path(map_path) / kAckedFile).string();
    const int fd = open(file.c_str(), O_WRONLY | O_CLOEXEC);
    if (fd < 0) return Status::IoError(Errno("opening ACKED for writing"));
    return std::unique_ptr<AckTracker>(new AckTracker(fd, state));
  }
  ~AckTracker() { close(fd_); }

  // Makes ACKED count at least `state` (writes a map recovered beyond its acknowledged ones).
  Status Raise(const AckState& state) {
    MutexLock lock(mutex_);
    while (syncing_) synced_cv_.Wait(mutex_);
    pending_.writes = std::max(pending_.writes, state.writes);
    pending_.max_place = std::max(pending_.max_place, state.max_place);
    AckState next = pending_;
    next.generation = ++generation_;
    return WriteAckSlot(fd_, next);
  }

  // Returns once ACKED counts this write (`place`: its id, 0 for other writes; `writes`: how many
  // acknowledged writes it is, e.g. a group of places in one batch) durably.
  Status Acknowledge(PlaceId place, uint64_t writes = 1) {
    MutexLock lock(mutex_);
    pending_.writes += writes;
    pending_.max_place = std::max<uint64_t>(pending_.max_place, place);
    const uint64_t ticket = ++requested_;
    while (durable_ < ticket) {
      if (syncing_) {
        synced_cv_.Wait(mutex_);
        continue;
      }
      syncing_ = true;
      const uint64_t target = requested_;
      AckState next = pending_;
      next.generation = ++generation_;
      lock.Unlock();
      const Status written = WriteAckSlot(fd_, next);
      lock.Lock();
      syncing_ = false;
      last_status_ = written;
      durable_ = target;
      synced_cv_.NotifyAll();
    }
    return last_status_;
  }

 private:
  AckTracker(int fd, AckState state) : fd_(fd), generation_(state.generation), pending_(state) {}

  const int fd_;
  Mutex mutex_;
  CondVar synced_cv_;
  uint64_t generation_ GUARDED_BY(mutex_);
  AckState pending_ GUARDED_BY(mutex_);  // everything acknowledged or being acknowledged
  uint64_t requested_ GUARDED_BY(mutex_) = 0;
  uint64_t durable_ GUARDED_BY(mutex_) = 0;
  bool syncing_ GUARDED_BY(mutex_) = false;
  Status last_status_ GUARDED_BY(mutex_);
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

  rocksdb::ColumnFamilyHandle* cf(Cf which) const { return handles[size_t(which)]; }

  void Close() {
    committer.reset();
    acks.reset();
    if (db) {
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

 private:
  MapStorage* storage_;
  const FeatureType type_;
};

// A frame's statistics: what the pipeline measured (coverage, the boxes it used) and when.
PlaceDynamics FrameDynamics(const ProcessedFrame& frame, const PlaceMetadata& metadata) {
  return MakeObservation(frame.counts.dynamic_coverage, frame.boxes_used, metadata.timestamp_ns,
                         NowUnixNs());
}

// One place as Load reads it back: its record and BoW vector, checked against each other.
struct LoadedPlace {
  PlaceRecord record;
  BowVector bow;
};

// Reads the `places` and `bow` families for PlaceMap::Load, with every check Load makes: each
// record has a BoW vector under the same key, its key is its id, no BoW vector lacks a record,
// both decode; an unreadable block is the iterator's error (RocksDB names the file). Either one
// scan of the whole key range restoring place by place (LoadSequential), or ranges of place ids
// read, decoded and built into index segments by worker threads while the calling thread
// installs them in id order (LoadSegments). Both rebuild the same database and stop at the same
// first problem.
class PlaceLoader {
 public:
  using Visit = std::function<Status(LoadedPlace&&)>;

  PlaceLoader(const MapStorage& storage, const std::string& map_name)
      : storage_(storage),
        map_name_(map_name),
        range_ids_(std::min(storage.load_range_ids, PlaceId(1) << InvertedIndex::kSegmentBits)) {
    options_.fill_cache = false;  // a full scan would only evict the verification working set
  }

  // `read_ms` receives the time spent reading and decoding (outside `visit`).
  Status LoadSequential(const Visit& visit, double* read_ms) const {
    Stopwatch clock;
    double visiting = 0;
    const auto timed = [&](LoadedPlace&& place) {
      Stopwatch inside;
      Status status = visit(std::move(place));
      visiting += inside.ElapsedMs();
      return status;
    };
    Iterators its = NewIterators();
    Status status = ReadRange(its, std::nullopt, std::nullopt, timed);
    *read_ms += clock.ElapsedMs() - visiting;
    return status;
  }

  // The bulk path: `workers` threads each read and decode the places of a range of
  // load_range_ids ids (aligned; by default one whole index segment, 2^16 ids) and build its
  // part of the index (PlaceDatabase::PrepareRestore); the calling thread installs the ranges in
  // id order (PlaceDatabase::RestoreRange). At most kRangeWindow ranges are read ahead of the
  // one being installed: a full segment of a 1M-place map is ~370 MB of decoded vectors plus
  // its postings. The first problem in id order is the one reported, as LoadSequential would:
  // a place PrepareRestore refuses comes before the read problem that ended its segment.
  // `read_ms` and `build_ms` receive the workers' times, summed; `install_ms` the calling
  // thread's.
  Status LoadSegments(unsigned workers, PlaceDatabase& database, double* read_ms, double* build_ms,
                      double* install_ms) const {
    std::optional<PlaceId> first, last;
    FirstAndLast(&first, &last);
    const auto restore_one = [&](LoadedPlace&& place) {
      Stopwatch installing;
      Status restored = database.Restore(std::move(place.record), place.bow);
      *install_ms += installing.ElapsedMs();
      return restored;
    };
    // An empty family or a key that is not a place id: one scan reports it as it always has.
    if (!first || !last || *last < *first) return LoadSequential(restore_one, read_ms);
    struct Built {
      Result<PlaceDatabase::RestoredSegment> prepared = Status::Internal("not read");
      Status read_status = Status::Ok();  // the first problem, found after the places read
    };
    std::vector<double> worker_read_ms(workers, 0.0), worker_build_ms(workers, 0.0);
    bool started = false;
    Status status = RunRangesInOrder<Built>(
        *first, *last, range_ids_, workers, kRangeWindow,
        [&](Iterators& its, std::optional<PlaceId> begin, std::optional<PlaceId> end,
            unsigned worker) -> Built {
          Stopwatch clock;
          std::vector<PlaceRecord> records;
          std::vector<BowVector> bows;
          Built built;
          built.read_status = ReadRange(its, begin, end, [&](LoadedPlace&& place) {
            records.push_back(std::move(place.record));
            bows.push_back(std::move(place.bow));
            return Status::Ok();
          });
          worker_read_ms[worker] += clock.ElapsedMs();
          Stopwatch building;
          built.prepared = database.PrepareRestore(std::move(records), bows);
          worker_build_ms[worker] += building.ElapsedMs();
          return built;  // the decoded vectors are freed here: the index holds the postings
        },
        [&](Built&& built) -> Status {
          if (!built.prepared.ok()) return built.prepared.status();
          Stopwatch installing;
          Status installed = database.RestoreRange(std::move(built.prepared).value());
          *install_ms += installing.ElapsedMs();
          PLACEDB_RETURN_IF_ERROR(installed);
          return built.read_status;
        },
        &started);
    if (!started) return LoadSequential(restore_one, read_ms);
    for (double ms : worker_read_ms) *read_ms += ms;
    for (double ms : worker_build_ms) *build_ms += ms;
    return status;
  }

 private:
  // Ranges read and built ahead of the one being installed.
  static constexpr size_t kRangeWindow = 2;

  struct Iterators {
    std::unique_ptr<rocksdb::Iterator> places, bows;
  };

  // The first and last keys of `places` as ids (nullopt: none, or not a place id).
  void FirstAndLast(std::optional<PlaceId>* first, std::optional<PlaceId>* last) const {
    Iterators its = NewIterators();
    its.places->SeekToFirst();
    if (its.places->Valid()) *first = KeyId(its.places->key());
    its.places->SeekToLast();
    if (its.places->Valid()) *last = KeyId(its.places->key());
  }

  // Cuts [first, last] into ranges of `range_ids` aligned ids (the first range has no lower
  // bound and the last no upper bound, so every key is in exactly one range); `workers`
  // threads run `produce(iterators, begin, end, worker)` on them, at most `window` ranges ahead
  // of the one `consume` is taking; `consume` runs on the calling thread, in range order, until
  // it returns an error (returned). `*started` is false when no thread could be started
  // (nothing was consumed then).
  template <typename Produced, typename Produce, typename Consume>
  Status RunRangesInOrder(PlaceId first, PlaceId last, PlaceId range_ids, unsigned workers,
                          size_t window, const Produce& produce, const Consume& consume,
                          bool* started) const {
    const size_t base = first / range_ids;
    const size_t ranges = last / range_ids - base + 1;
    const auto begin_of = [&](size_t r) -> std::optional<PlaceId> {
      if (r == 0 || r >= ranges) return std::nullopt;
      return PlaceId((base + r) * range_ids);
    };
    std::vector<std::optional<Produced>> results(ranges);
    Mutex mutex;
    CondVar changed;
    size_t consuming = 0;  // guarded by mutex
    bool stop = false;     // guarded by mutex
    std::atomic<size_t> next{0};
    const auto work = [&](unsigned worker) {
      Iterators its = NewIterators();
      for (size_t r; (r = next.fetch_add(1)) < ranges;) {
        {
          MutexLock lock(mutex);
          while (!stop && r >= consuming + window) changed.Wait(mutex);
          if (stop) return;
        }
        Produced produced = produce(its, begin_of(r), begin_of(r + 1), worker);
        MutexLock lock(mutex);
        results[r] = std::move(produced);
        changed.NotifyAll();
      }
    };
    std::vector<std::thread> pool;
    for (unsigned w = 0; w < workers; ++w) {
      try {
        pool.emplace_back(work, w);
      } catch (const std::system_error&) {
        break;  // fewer workers than asked: they still take every range
      }
    }
    *started = !pool.empty();
    if (pool.empty()) return Status::Ok();
    Status status = Status::Ok();
    for (size_t r = 0; r < ranges && status.ok(); ++r) {
      std::optional<Produced> produced;
      {
        MutexLock lock(mutex);
        while (!results[r]) changed.Wait(mutex);
        produced = std::move(results[r]);
        results[r].reset();
        consuming = r + 1;
        changed.NotifyAll();
      }
      status = consume(std::move(*produced));
    }
    {
      MutexLock lock(mutex);
      stop = true;
      changed.NotifyAll();
    }
    for (std::thread& thread : pool) thread.join();
    return status;
  }

  Iterators NewIterators() const {
    return {
        std::unique_ptr<rocksdb::Iterator>(
            storage_.db->NewIterator(options_, storage_.cf(kPlaces))),
        std::unique_ptr<rocksdb::Iterator>(storage_.db->NewIterator(options_, storage_.cf(kBow)))};
  }

  static std::optional<PlaceId> KeyId(const rocksdb::Slice& key) {
    auto id = DecodePlaceKey(key.ToStringView());
    if (!id.ok()) return std::nullopt;
    return *id;
  }

  // The places with keys in [begin, end) (nullopt: unbounded), in key order.
  Status ReadRange(Iterators& its, std::optional<PlaceId> begin, std::optional<PlaceId> end,
                   const Visit& visit) const {
    const std::string end_key = end ? PlaceKey(*end) : std::string();
    const auto in_range = [&](const rocksdb::Slice& key) {
      return !end || key.compare(rocksdb::Slice(end_key)) < 0;
    };
    rocksdb::Iterator& places = *its.places;
    rocksdb::Iterator& bows = *its.bows;
    if (begin) {
      const std::string begin_key = PlaceKey(*begin);
      places.Seek(begin_key);
      bows.Seek(begin_key);
    } else {
      places.SeekToFirst();
      bows.SeekToFirst();
    }
    for (; places.Valid() && in_range(places.key()); places.Next(), bows.Next()) {
      // An unreadable block ends an iterator: report it (it names the file), not a missing
      // vector.
      PLACEDB_RETURN_IF_ERROR(FromRocks(bows.status(), "scanning BoW vectors"));
      if (!bows.Valid() || places.key() != bows.key()) {
        return Status::Corruption("map '" + map_name_ + "': place " + places.key().ToString(true) +
                                  " has no BoW vector");
      }
      // A value that does not decode is named by its place (its key, as above).
      auto record = DecodePlaceRecord(places.value().ToStringView());
      if (!record.ok()) {
        return record.status().WithContext("map '" + map_name_ + "': place " +
                                           places.key().ToString(true));
      }
      auto bow = DecodeBow(bows.value().ToStringView());
      if (!bow.ok()) {
        return bow.status().WithContext("map '" + map_name_ + "': place " +
                                        places.key().ToString(true));
      }
      auto key = DecodePlaceKey(places.key().ToStringView());
      if (!key.ok() || *key != record->id) {
        return Status::Corruption("map '" + map_name_ + "': place key and record disagree");
      }
      PLACEDB_RETURN_IF_ERROR(visit({std::move(record).value(), std::move(bow).value()}));
    }
    PLACEDB_RETURN_IF_ERROR(FromRocks(places.status(), "scanning places"));
    if (bows.Valid() && in_range(bows.key())) {
      return Status::Corruption("map '" + map_name_ + "': BoW vector without a place record");
    }
    return FromRocks(bows.status(), "scanning BoW vectors");
  }

  const MapStorage& storage_;
  const std::string& map_name_;
  const PlaceId range_ids_;  // a power of two <= 2^16: a range lies in one index segment
  rocksdb::ReadOptions options_;
};

}  // namespace

const Result<AddResult>& PendingCommit::Wait() const {
  MutexLock lock(mutex_);
  while (!done_) done_cv_.Wait(mutex_);
  return outcome_;
}

bool PendingCommit::done() const {
  MutexLock lock(mutex_);
  return done_;
}

void PendingCommit::Complete(Result<AddResult> outcome) {
  {
    MutexLock lock(mutex_);
    outcome_ = std::move(outcome);
    done_ = true;
  }
  done_cv_.NotifyAll();
}

// A place waiting in the commit queue: its entries are already in the queue's batch.
struct PlaceMap::QueuedPlace {
  ProcessedFrame frame;
  PlaceMetadata metadata;
  PlaceId id = 0;
  std::shared_ptr<PendingCommit> pending;
  Stopwatch since_enqueued;
};

struct PlaceMap::CommitQueue {
  Mutex mutex;
  CondVar wake;
  std::vector<QueuedPlace> queued GUARDED_BY(mutex);
  // The queued places' entries, in Enqueue() order: the next group's one atomic batch.
  rocksdb::WriteBatch batch GUARDED_BY(mutex);
  bool stopping GUARDED_BY(mutex) = false;
  // Started with the map, not by the first Enqueue(): a thread inherits its creator's nice value,
  // and the first Enqueue() may come from a lowered-priority ingest worker; the committer holds
  // the index's write lock while it inserts, so it keeps the normal priority.
  std::thread thread;
};

PlaceMap::PlaceMap(MapInfo info, std::string path, std::unique_ptr<MapStorage> storage,
                   AnyVocabulary vocabulary)
    : info_(std::move(info)),
      path_(std::move(path)),
      storage_(std::move(storage)),
      vocabulary_(std::move(vocabulary)),
      commits_(std::make_unique<CommitQueue>()) {
  commits_->thread = std::thread([this] { RunCommitter(); });
}

PlaceMap::~PlaceMap() {
  StopCommitter();
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
  Stopwatch total;
  auto db = PlaceDatabase::Create(
      vocabulary_, info_.options.database,
      std::make_shared<RocksPayloadStore>(storage_.get(), info_.options.database.feature_type));
  if (!db.ok()) return db.status();
  database_ = std::move(db).value();
  rocksdb::ReadOptions options;
  options.fill_cache = false;  // a full scan would only evict the verification working set
  open_timings_ = OpenTimings();
  open_timings_.threads = storage_->load_threads;
  PlaceLoader loader(*storage_, info_.name);
  const auto restore = [&](LoadedPlace&& place) {
    Stopwatch indexing;
    Status restored = database_->Restore(std::move(place.record), place.bow);
    open_timings_.index_ms += indexing.ElapsedMs();
    return restored;
  };
  // More than one thread: whole index segments are read, decoded and built by load_threads
  // workers (the opening thread only installs them); one: the scan of today, place by place.
  PLACEDB_RETURN_IF_ERROR(
      storage_->load_threads > 1
          ? loader.LoadSegments(storage_->load_threads, *database_, &open_timings_.read_decode_ms,
                                &open_timings_.index_ms, &open_timings_.index_ms)
          : loader.LoadSequential(restore, &open_timings_.read_decode_ms));
  open_timings_.total_ms = total.ElapsedMs();

  std::string value;
  if (storage_->db->Get({}, storage_->cf(kMeta), kIdFloorKey, &value).ok()) {
    auto floor = DecodePlaceKey(value);
    if (!floor.ok()) return floor.status().WithContext("map '" + info_.name + "' id floor");
    database_->ReserveIdsBelow(*floor);
  }
  if (storage_->db->Get({}, storage_->cf(kMeta), kAppliedSequenceKey, &value).ok()) {
    auto applied = DecodeU64Key(value);
    if (!applied.ok())
      return applied.status().WithContext("map '" + info_.name + "' applied sequence");
    applied_sequence_ = *applied;
    database_->ReserveIdsBelow(PlaceId(std::min<uint64_t>(*applied + 1, kMaxPlaceId)));
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
  auto frame =
      database_->Process(observation, FrameRole::kStream, ThumbnailsFor(FrameRole::kStream));
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
  if (!committed && outcome->merged) {
    // Merged into the previous place by rehearsal: only its statistics are written, durably
    // (acknowledged means counted).
    PLACEDB_RETURN_IF_ERROR(
        CountObservationAt(outcome->place, frame, metadata,
                           "counting a frame merged into place " + std::to_string(outcome->place)));
  }
  if (!committed) {
    // Merged into the previous place by rehearsal: no place written.
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

Result<LoopClosureOutcome> PlaceMap::CloseLoop(const ProcessedFrame& frame,
                                               const PlaceMetadata& metadata,
                                               const std::function<Result<PlaceId>()>& store,
                                               PlaceSource* source) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return database_->CloseLoop(frame, metadata, store, source);
}

void PlaceMap::ResetLoopClosure(const std::string& agent_id) {
  ReaderLock alive(lifecycle_);
  if (!closed_) database_->ResetLoopClosure(agent_id);
}

Status PlaceMap::CountObservationAt(PlaceId place, const ProcessedFrame& frame,
                                    const PlaceMetadata& metadata, const std::string& what) {
  if (!storage_->dynamics) return Status::Ok();
  // A place removed meanwhile keeps none (the map's aggregate still counts the frame); a removal
  // racing this write may leave an entry without a place, which readers skip.
  rocksdb::WriteBatch batch;
  storage_->AddDynamics(&batch, database_->Get(place) ? place : 0, FrameDynamics(frame, metadata));
  return storage_->Write(&batch, what, MapStorage::Kind::kAddition);
}

Result<bool> PlaceMap::CountQueryHit(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                     const QueryResult& result) {
  const double above = info_.options.count_query_hits_above;
  if (above <= 0 || !result.valid || result.matches.empty()) return false;
  const Match& best = result.matches.front();
  if (!(best.score > above)) return false;
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  PLACEDB_RETURN_IF_ERROR(CountObservationAt(
      best.place, frame, metadata, "counting a query hit at place " + std::to_string(best.place)));
  return true;
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
  if (storage_->dynamics) storage_->AddInvalidDynamics(&batch, FrameDynamics(frame, metadata));
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
        storage_->Write(&batch, "storing an invalid observation", MapStorage::Kind::kAddition));
    ++storage_->invalid_stored;
  } else {
    // Only a counter: not worth an fsync of its own; it rides on the next synced write.
    PLACEDB_RETURN_IF_ERROR(
        storage_->Write(&batch, "counting an invalid frame", MapStorage::Kind::kCounter));
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
  if (storage_->dynamics) storage_->AddDynamics(&batch, record.id, FrameDynamics(frame, metadata));
  if (frame.thumbnail && info_.options.thumbnails.enabled) {
    batch.Put(storage_->cf(kThumbnails), key, EncodeThumbnail(*frame.thumbnail));
  }
  PLACEDB_RETURN_IF_ERROR(storage_->Write(&batch, "storing place " + std::to_string(record.id),
                                          MapStorage::Kind::kAddition, record.id));
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

std::shared_ptr<PendingCommit> PlaceMap::Enqueue(ProcessedFrame frame, PlaceMetadata metadata) {
  auto pending = std::make_shared<PendingCommit>();
  ReaderLock alive(lifecycle_);
  if (closed_) {
    pending->Complete(Deleted());
    return pending;
  }
  // What Commit() refuses or stores at once is answered at once, exactly as Commit() does.
  const DatabaseConfig& config = info_.options.database;
  if (frame.stream_pending || !frame.valid || frame.static_features.type() != config.feature_type ||
      frame.direct.levels_up != config.verification.levels_up) {
    pending->Complete(CommitLocked(frame, metadata));
    return pending;
  }
  QueuedPlace place;
  place.pending = pending;
  // Encoded here, on the caller's thread, so that callers encode in parallel; the committer
  // only writes.
  PlaceRecord record;
  record.metadata = metadata;
  record.counts = frame.counts;
  record.boxes_used = frame.boxes_used;
  std::string features = EncodeLocalFeatures(frame.static_features, frame.direct);
  std::string bow = EncodeBow(frame.bow);
  std::string dynamics;
  if (storage_->dynamics) dynamics = EncodeDynamics(FrameDynamics(frame, metadata));
  std::string thumbnail;
  const bool has_thumbnail = frame.thumbnail && info_.options.thumbnails.enabled;
  if (has_thumbnail) thumbnail = EncodeThumbnail(*frame.thumbnail);
  CommitQueue& queue = *commits_;
  {
    MutexLock lock(queue.mutex);
    // Reserved under the queue's lock: ids follow the order of the places in the batch.
    record.id = database_->ReserveId();
    place.id = record.id;
    const std::string key = PlaceKey(record.id);
    queue.batch.Put(storage_->cf(kPlaces), key, EncodePlaceRecord(record));
    queue.batch.Put(storage_->cf(kBow), key, bow);
    queue.batch.Put(storage_->cf(kFeatures), key, features);
    if (storage_->dynamics) {
      queue.batch.Merge(storage_->cf(kDynamics), key, dynamics);
      queue.batch.Merge(storage_->cf(kDynamics), kMapDynamicsKey, dynamics);
    }
    if (has_thumbnail) queue.batch.Put(storage_->cf(kThumbnails), key, thumbnail);
    place.frame = std::move(frame);
    place.metadata = std::move(metadata);
    queue.queued.push_back(std::move(place));
  }
  queue.wake.NotifyOne();
  return pending;
}

void PlaceMap::RunCommitter() {
  CommitQueue& queue = *commits_;
  std::vector<QueuedPlace> group;
  MutexLock lock(queue.mutex);
  while (true) {
    while (!queue.stopping && queue.queued.empty()) queue.wake.Wait(queue.mutex);
    if (queue.queued.empty()) return;  // stopping, and everything queued is committed
    // Everything queued so far is one group; what arrives meanwhile is the next one.
    group.clear();
    group.swap(queue.queued);
    rocksdb::WriteBatch batch;
    std::swap(batch, queue.batch);
    lock.Unlock();
    CommitGroup(&group, &batch);
    lock.Lock();
  }
}

void PlaceMap::CommitGroup(std::vector<QueuedPlace>* group, rocksdb::WriteBatch* batch) {
  ReaderLock alive(lifecycle_);
  Status written;
  if (closed_) {
    written = Deleted();
  } else {
    PlaceId highest = 0;
    for (const QueuedPlace& place : *group) highest = std::max(highest, place.id);
    const std::string what =
        group->size() == 1
            ? "storing place " + std::to_string(highest)
            : "storing " + std::to_string(group->size()) + " places (group commit, ids " +
                  std::to_string(group->front().id) + ".." + std::to_string(highest) + ")";
    written = storage_->Write(batch, what, MapStorage::Kind::kAddition, highest, group->size());
  }
  for (QueuedPlace& place : *group) {
    if (!written.ok()) {
      place.pending->Complete(written);
      continue;
    }
    // Durable: now make it searchable.
    auto id = database_->Insert(place.frame, place.metadata, place.id);
    if (!id.ok()) {
      place.pending->Complete(id.status());
      continue;
    }
    AddResult result;
    result.stored = true;
    result.id = *id;
    result.counts = place.frame.counts;
    result.boxes_used = std::move(place.frame.boxes_used);
    result.timings = place.frame.timings;
    result.depth_state = std::move(place.frame.depth_state);
    result.timings.store_ms = place.since_enqueued.ElapsedMs();
    result.timings.total_ms += result.timings.store_ms;
    place.pending->Complete(std::move(result));
  }
  group->clear();  // the frames' memory goes now, not with the next group
}

void PlaceMap::StopCommitter() {
  if (!commits_) return;
  {
    MutexLock lock(commits_->mutex);
    commits_->stopping = true;
  }
  commits_->wake.NotifyAll();
  if (commits_->thread.joinable()) commits_->thread.join();
}

Result<bool> PlaceMap::ApplyAt(uint64_t sequence, const MapLogRecord& record) {
  const SequencedRecord one{sequence, &record};
  auto applied = ApplyBatch(std::span<const SequencedRecord>(&one, 1));
  if (!applied.ok()) return applied.status();
  return *applied == 1;
}

Result<size_t> PlaceMap::ApplyBatch(std::span<const SequencedRecord> records) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  MutexLock apply(apply_mutex_);
  const DatabaseConfig& config = info_.options.database;
  size_t applied = 0;
  // The run being gathered: one RocksDB batch, written and synced once (DeletePlace ends a
  // run: the index's removal writes its own batch).
  rocksdb::WriteBatch batch;
  std::vector<SequencedRecord> run;
  std::unordered_set<PlaceId> run_places;  // places the run adds: a CountObservation may name one
  PlaceId run_max_place = 0;
  auto flush = [&]() -> Status {
    if (run.empty()) return Status::Ok();
    const uint64_t first = run.front().sequence, last = run.back().sequence;
    const std::string what =
        run.size() == 1 ? "applying record " + std::to_string(last)
                        : "applying records " + std::to_string(first) + ".." + std::to_string(last);
    batch.Put(storage_->cf(kMeta), kAppliedSequenceKey, U64Key(last));
    PLACEDB_RETURN_IF_ERROR(
        storage_->Write(&batch, what, MapStorage::Kind::kAddition, run_max_place, run.size()));
    // Durable: now make the places searchable and count what was counted. The applied sequence
    // moves only after that: a reader that waited for it (a shard's read with a minimum
    // sequence) must find every place up to it.
    Status indexed;
    for (const SequencedRecord& r : run) {
      const MapLogRecord& record = *r.record;
      if (record.kind == MapLogRecord::Kind::kAddPlace) {
        auto id = database_->Insert(record.frame, record.metadata, PlaceId(r.sequence));
        if (!id.ok()) {
          indexed = id.status().WithContext("applying record " + std::to_string(r.sequence));
          break;
        }
      } else if (record.kind == MapLogRecord::Kind::kInvalidFrame) {
        if (info_.options.store_invalid) {
          ++storage_->invalid_stored;
          uint64_t next = storage_->next_invalid_serial.load();
          while (next <= r.sequence &&
                 !storage_->next_invalid_serial.compare_exchange_weak(next, r.sequence + 1)) {
          }
        }
        database_->CountInvalid();
      }
    }
    // Ids follow the stream: the next place id is above every sequence applied.
    database_->ReserveIdsBelow(PlaceId(std::min<uint64_t>(last + 1, kMaxPlaceId)));
    // Stored is applied, also when the index refused a place (reported: the replica stops).
    applied_sequence_ = last;
    PLACEDB_RETURN_IF_ERROR(indexed);
    applied += run.size();
    run.clear();
    run_places.clear();
    run_max_place = 0;
    batch.Clear();
    return Status::Ok();
  };
  uint64_t last = applied_sequence_.load();
  for (const SequencedRecord& r : records) {
    if (r.sequence <= last) continue;  // applied before (or repeated in `records`)
    const uint64_t sequence = r.sequence;
    const MapLogRecord& record = *r.record;
    const std::string what = "applying record " + std::to_string(sequence);
    // A record the map cannot take: the run before it is applied, it and the rest are not.
    auto refuse = [&](const std::string& why) -> Status {
      PLACEDB_RETURN_IF_ERROR(flush());
      return Status::InvalidArgument(what + ": " + why);
    };
    switch (record.kind) {
      case MapLogRecord::Kind::kAddPlace: {
        const ProcessedFrame& frame = record.frame;
        // Checked before writing: a batch the index then refused would leave an unindexed place.
        if (sequence >= kMaxPlaceId) return refuse("sequence beyond the place-id range");
        if (!frame.valid) return refuse("AddPlace of an invalid frame");
        if (frame.static_features.type() != config.feature_type) {
          return refuse("frame's features are " +
                        std::string(FeatureTypeName(frame.static_features.type())) +
                        ", the map's are " + FeatureTypeName(config.feature_type));
        }
        if (frame.direct.levels_up != config.verification.levels_up) {
          return refuse("frame's direct index is at level " +
                        std::to_string(frame.direct.levels_up) + ", the map uses " +
                        std::to_string(config.verification.levels_up));
        }
        PlaceRecord stored;
        stored.id = PlaceId(sequence);
        stored.metadata = record.metadata;
        stored.counts = frame.counts;
        stored.boxes_used = frame.boxes_used;
        const std::string key = PlaceKey(stored.id);
        batch.Put(storage_->cf(kPlaces), key, EncodePlaceRecord(stored));
        batch.Put(storage_->cf(kBow), key, EncodeBow(frame.bow));
        batch.Put(storage_->cf(kFeatures), key,
                  EncodeLocalFeatures(frame.static_features, frame.direct));
        if (storage_->dynamics && record.dynamics) {
          storage_->AddDynamics(&batch, stored.id, *record.dynamics);
        }
        if (frame.thumbnail && info_.options.thumbnails.enabled) {
          batch.Put(storage_->cf(kThumbnails), key, EncodeThumbnail(*frame.thumbnail));
        }
        run_places.insert(stored.id);
        run_max_place = stored.id;
        break;
      }
      case MapLogRecord::Kind::kDeletePlace: {
        PLACEDB_RETURN_IF_ERROR(flush());
        const std::string applied_value = U64Key(sequence);
        if (record.place != 0 && database_->Get(record.place)) {
          // The removal's own batch carries the applied sequence (RocksPayloadStore::Erase).
          t_applying_sequence = &applied_value;
          Status removed = database_->Remove(record.place);
          t_applying_sequence = nullptr;
          PLACEDB_RETURN_IF_ERROR(removed.WithContext(what));
        } else {
          rocksdb::WriteBatch alone;
          alone.Put(storage_->cf(kMeta), kAppliedSequenceKey, applied_value);
          PLACEDB_RETURN_IF_ERROR(storage_->Write(&alone, what, MapStorage::Kind::kRemoval));
        }
        applied_sequence_ = sequence;
        database_->ReserveIdsBelow(PlaceId(std::min<uint64_t>(sequence + 1, kMaxPlaceId)));
        ++applied;
        last = sequence;
        continue;  // not part of a run
      }
      case MapLogRecord::Kind::kCountObservation:
        if (storage_->dynamics && record.dynamics) {
          const bool known =
              record.place != 0 && (run_places.count(record.place) || database_->Get(record.place));
          storage_->AddDynamics(&batch, known ? record.place : 0, *record.dynamics);
        }
        break;
      case MapLogRecord::Kind::kInvalidFrame: {
        batch.Merge(storage_->cf(kMeta), kInvalidCountKey, CounterOperand(1));
        if (storage_->dynamics && record.dynamics) {
          storage_->AddInvalidDynamics(&batch, *record.dynamics);
        }
        if (info_.options.store_invalid) {
          // The sequence is the serial: the same on every replica, in arrival order.
          InvalidObservation observation;
          observation.serial = sequence;
          observation.metadata = record.metadata;
          observation.counts = record.frame.counts;
          observation.boxes_used = record.frame.boxes_used;
          observation.reason = record.frame.rejection;
          batch.Put(storage_->cf(kInvalid), U64Key(sequence),
                    EncodeInvalidObservation(observation));
        }
        break;
      }
    }
    run.push_back(r);
    last = sequence;
  }
  PLACEDB_RETURN_IF_ERROR(flush());
  return applied;
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
  if (!payload.ok()) {
    // A corrupt block is DATA_LOSS naming the file, relative to the data directory.
    return Status(payload.status().code(),
                  RelativeTo(payload.status().message(), path_, info_.name));
  }
  return StoredPlace{*record, **payload};
}

Result<BowVector> PlaceMap::GetBow(PlaceId id) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  if (!database_->Get(id)) {
    return Status::NotFound("place " + std::to_string(id) + " not found in map '" + info_.name +
                            "'");
  }
  RocksPayloadStore payloads(storage_.get(), info_.options.database.feature_type);
  auto bow = payloads.GetBow(id);
  if (!bow.ok()) {
    return Status(bow.status().code(), RelativeTo(bow.status().message(), path_, info_.name));
  }
  return bow;
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

Result<std::optional<std::string>> PlaceMap::ReadPlaceValue(PlaceId id, size_t family,
                                                            const std::string& what) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  if (!database_->Get(id)) {
    return Status::NotFound("place " + std::to_string(id) + " not found in map '" + info_.name +
                            "'");
  }
  std::string value;
  auto s = storage_->db->Get({}, storage_->cf(Cf(family)), PlaceKey(id), &value);
  if (s.IsNotFound()) return std::optional<std::string>();
  if (Status read = FromRocks(s, "reading the " + what + " of place " + std::to_string(id));
      !read.ok()) {
    return Status(read.code(), RelativeTo(read.message(), path_, info_.name));
  }
  return std::optional<std::string>(std::move(value));
}

Result<PlaceDynamics> PlaceMap::GetDynamics(PlaceId id) const {
  auto value = ReadPlaceValue(id, kDynamics, "statistics");
  if (!value.ok()) return value.status();
  if (!*value) return PlaceDynamics();
  auto decoded = DecodeDynamics(**value);
  if (!decoded.ok()) return decoded.status().WithContext("place " + std::to_string(id));
  return decoded;
}

Result<std::optional<Thumbnail>> PlaceMap::GetThumbnail(PlaceId id) const {
  auto value = ReadPlaceValue(id, kThumbnails, "thumbnail");
  if (!value.ok()) return value.status();
  if (!*value) return std::optional<Thumbnail>();
  auto decoded = DecodeThumbnail(**value);
  if (!decoded.ok()) return decoded.status().WithContext("place " + std::to_string(id));
  return std::optional<Thumbnail>(std::move(decoded).value());
}

Result<PlaceDynamics> PlaceMap::ReadAggregate(const char* key, const std::string& what) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  std::string value;
  auto s = storage_->db->Get({}, storage_->cf(kDynamics), key, &value);
  if (s.IsNotFound()) return PlaceDynamics();
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading " + what));
  auto decoded = DecodeDynamics(value);
  if (!decoded.ok()) return decoded.status().WithContext("map '" + info_.name + "': " + what);
  return decoded;
}

Result<PlaceDynamics> PlaceMap::MapDynamics() const {
  return ReadAggregate(kMapDynamicsKey, "the map's statistics");
}

Result<PlaceDynamics> PlaceMap::InvalidDynamics() const {
  return ReadAggregate(kInvalidDynamicsKey, "the invalid frames' statistics");
}

Status PlaceMap::ForEachPlaceDynamics(
    const std::function<bool(PlaceId, const PlaceDynamics&)>& visit) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  rocksdb::ReadOptions options;
  options.fill_cache = false;
  std::unique_ptr<rocksdb::Iterator> it(
      storage_->db->NewIterator(options, storage_->cf(kDynamics)));
  for (it->SeekToFirst(); it->Valid(); it->Next()) {
    if (IsAggregateKey(it->key())) continue;
    auto id = DecodePlaceKey(it->key().ToStringView());
    if (!id.ok()) return id.status().WithContext("statistics key");
    if (!database_->Get(*id)) continue;  // removed while a merged frame was being counted
    auto decoded = DecodeDynamics(it->value().ToStringView());
    if (!decoded.ok()) return decoded.status().WithContext("place " + std::to_string(*id));
    if (!visit(*id, *decoded)) return Status::Ok();
  }
  return FromRocks(it->status(), "scanning statistics");
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

// ---------------------------------------------------------------------------------------------

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

// How an existing map's RocksDB is opened.
enum class Recovery {
  kStrict,       // kAbsoluteConsistency + WAL tracking: any damage is an error
  kPointInTime,  // RocksDB's default: stop replaying the WAL at the first bad record
};

std::vector<rocksdb::ColumnFamilyDescriptor> Families(const std::shared_ptr<void>& cache_void) {
  auto cache = std::static_pointer_cast<rocksdb::Cache>(cache_void);
  std::vector<rocksdb::ColumnFamilyDescriptor> families;
  for (int cf = 0; cf < kCfCount; ++cf) {
    families.emplace_back(kColumnFamilies[cf], FamilyOptions(Cf(cf), cache));
  }
  return families;
}

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

// `path`: the map's directory, for its info log; empty for read-only opens (which write none).
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

Result<std::unique_ptr<MapStorage>> OpenStorage(const std::string& path, bool create,
                                                const StorageOptions& options,
                                                const std::shared_ptr<void>& cache_void,
                                                Recovery recovery = Recovery::kStrict,
                                                bool create_families = false) {
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
  rocksdb::DB* raw = nullptr;
  rocksdb::Status s =
      rocksdb::DB::Open(db_options, path, Families(cache_void), &storage->handles, &raw);
  if (!s.ok()) return FromRocks(s, "opening the map's RocksDB");
  storage->db.reset(raw);
  storage->sync = options.sync;
  if (options.sync == SyncMode::kGroupCommit) {
    storage->committer = std::make_unique<GroupCommitter>(
        raw, std::chrono::milliseconds(options.group_commit_delay_ms));
  }
  return storage;
}

// Read-only: changes no file (a WAL is replayed into memory only).
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
  rocksdb::Status s = rocksdb::DB::OpenForReadOnly(RecoveryOptions(recovery, ""), path, families,
                                                   &storage->handles, &raw);
  if (!s.ok()) return FromRocks(s, "opening the map's RocksDB");
  storage->db.reset(raw);
  for (Cf cf : missing) storage->handles.insert(storage->handles.begin() + cf, nullptr);
  return storage;
}

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
  return info;
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
  if (!vocabulary) return Status::InvalidArgument("vocabulary is missing");
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
  auto vocabulary = vocabulary_for(*info);
  if (!vocabulary.ok()) return vocabulary.status();
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

// Walks the keys of `places`, `bow` and `features` together (each in id order). RocksDB
// iterators read the values too: recovery reads the whole map once. A block that does not read
// is an error (CORRUPTION naming the file).
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

// "N places lost their features (ids a..b): ..." and the dropped ones, for the damage reason.
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
  auto vocabulary = vocabulary_for(*info);
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

Status CheckRoomFor(const std::string& path, uint64_t bytes, uint64_t reserve_bytes,
                    const std::string& what) {
  const std::optional<uint64_t> available = AvailableBytes(path);
  if (!available || *available >= bytes + reserve_bytes) return Status::Ok();
  return Status::ResourceExhausted("disk full: " + what + " needs " + std::to_string(bytes) +
                                   " bytes; the data directory has " + std::to_string(*available) +
                                   " free, " + std::to_string(reserve_bytes) +
                                   " of them reserved (storage.disk_reserve_bytes)");
}

void DataDirectory::CloseMap(const std::string& name) {
  MutexLock lock(mutex_);
  open_.erase(name);
}

}  // namespace placedb
