#include "core/storage/snapshots.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "core/base/files.h"
#include "core/base/map_name.h"
#include "core/features/local_features.h"
#include "core/storage/sha256.h"

namespace placedb {
namespace {

namespace fs = std::filesystem;

constexpr char kMagic[8] = {'P', 'D', 'B', 'S', 'N', 'A', 'P', '\n'};
constexpr uint32_t kVersion = 1;
constexpr char kManifest[] = "SNAPSHOT.json";
constexpr char kCheckpoint[] = "checkpoint";
constexpr size_t kMaxPath = 1024;
constexpr size_t kDigestBytes = 32;
// The archive's header, the end record and the digest: what follows the last entry.
constexpr size_t kHeaderBytes = sizeof kMagic + 8;

int64_t NowUnixMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string EncodeManifest(const SnapshotInfo& info) {
  nlohmann::json j = {{"format", kVersion},
                      {"id", info.id},
                      {"map", info.map},
                      {"created_unix_ms", info.created_unix_ms},
                      {"feature_type", info.feature_type},
                      {"vocabulary_checksum", info.vocabulary_checksum},
                      {"places", info.places}};
  return j.dump(2) + "\n";
}

Result<SnapshotInfo> DecodeManifest(const std::string& text) {
  nlohmann::json j = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) {
    return Status::InvalidArgument(std::string(kManifest) + " is not a JSON object");
  }
  SnapshotInfo info;
  try {
    if (j.at("format").get<uint32_t>() != kVersion) {
      return Status::InvalidArgument(std::string(kManifest) + ": unsupported format " +
                                     j.at("format").dump());
    }
    info.id = j.at("id").get<std::string>();
    info.map = j.at("map").get<std::string>();
    info.created_unix_ms = j.at("created_unix_ms").get<int64_t>();
    info.feature_type = j.at("feature_type").get<std::string>();
    info.vocabulary_checksum = j.at("vocabulary_checksum").get<uint64_t>();
    info.places = j.at("places").get<uint64_t>();
  } catch (const nlohmann::json::exception& e) {
    return Status::InvalidArgument(std::string(kManifest) + ": " + e.what());
  }
  PLACEDB_RETURN_IF_ERROR(ValidateSnapshotId(info.id).WithContext(kManifest));
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(info.map).WithContext(kManifest));
  return info;
}

uint64_t DirectoryBytes(const std::string& path) {
  uint64_t total = 0;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(path, ec); !ec && it != fs::end(it);
       it.increment(ec)) {
    if (it->is_regular_file(ec)) total += it->file_size(ec);
  }
  return total;
}

// The archive's entries in order: the manifest, then the checkpoint's files sorted by path.
Result<std::vector<std::string>> EntryPaths(const std::string& snapshot_dir) {
  std::vector<std::string> files;
  std::error_code ec;
  const fs::path root(snapshot_dir);
  for (auto it = fs::recursive_directory_iterator(root / kCheckpoint, ec); !ec && it != fs::end(it);
       it.increment(ec)) {
    if (it->is_regular_file(ec)) files.push_back(fs::relative(it->path(), root).generic_string());
  }
  if (ec) return Status::IoError("listing " + snapshot_dir + ": " + ec.message());
  std::sort(files.begin(), files.end());
  files.insert(files.begin(), kManifest);
  return files;
}

// A path from an archive is acceptable when it is the manifest or a plain relative file under
// checkpoint/ (no "", ".", ".." parts, no absolute path, no backslash).
bool SafeEntryPath(const std::string& path) {
  if (path == kManifest) return true;
  if (path.size() > kMaxPath || path.find('\\') != std::string::npos) return false;
  if (path.rfind(std::string(kCheckpoint) + "/", 0) != 0) return false;
  size_t start = 0;
  while (start <= path.size()) {
    size_t end = path.find('/', start);
    if (end == std::string::npos) end = path.size();
    const std::string part = path.substr(start, end - start);
    if (part.empty() || part == "." || part == "..") return false;
    start = end + 1;
  }
  return true;
}

template <typename T>
void PutLe(std::string* out, T value) {
  for (size_t i = 0; i < sizeof(T); ++i) out->push_back(char((uint64_t(value) >> (8 * i)) & 0xff));
}

template <typename T>
T GetLe(const char* bytes) {
  uint64_t value = 0;
  for (size_t i = 0; i < sizeof(T); ++i) value |= uint64_t(uint8_t(bytes[i])) << (8 * i);
  return T(value);
}

// Reads an archive sequentially, hashing every byte it hands out. Skip passes over bytes without
// reading or hashing them (the framing check's pass).
class ArchiveReader {
 public:
  // `in` holds `size` bytes from its current position.
  ArchiveReader(std::unique_ptr<std::istream> in, uint64_t size)
      : in_(std::move(in)), size_(size) {}
  bool is_open() const { return in_ && bool(*in_); }
  // CORRUPTION ("truncated") when fewer than `n` bytes remain.
  Status Read(size_t n, std::string* out, bool hash = true) {
    if (n > size_ - offset_) return Truncated();
    out->resize(n);
    if (n > 0 && !in_->read(out->data(), std::streamsize(n))) return Truncated();
    offset_ += n;
    if (hash) sha_.Update(*out);
    return Status::Ok();
  }
  Status Skip(uint64_t n) {
    if (n > size_ - offset_) return Truncated();
    if (!in_->seekg(std::streamoff(n), std::ios::cur)) return Truncated();
    offset_ += n;
    return Status::Ok();
  }
  bool AtEnd() const { return offset_ == size_; }
  std::string Digest() { return sha_.Final(); }
  uint64_t offset() const { return offset_; }

 private:
  Status Truncated() const {
    return Status::Corruption("the archive is truncated (ends after " + std::to_string(size_) +
                              " bytes)");
  }

  std::unique_ptr<std::istream> in_;
  const uint64_t size_;
  Sha256 sha_;
  uint64_t offset_ = 0;
};

// One archive entry as its framing states it.
struct EntryFraming {
  uint64_t index = 0;  // 1-based
  std::string path;    // checked by SafeEntryPath
  uint64_t size = 0;   // bytes that follow; at most kMaxSnapshotManifestBytes for the manifest
};

// Reads the archive's header and every entry's framing up to and including the end record's kind
// byte, checking the format and the limits as it goes: each limit is checked from the field that
// states it, before anything it sizes is read. `body` must consume each entry's bytes (read or
// skip them). *entries and *total: the entries walked and the sum of their sizes.
Status WalkArchive(ArchiveReader& reader, const std::function<Status(const EntryFraming&)>& body,
                   uint64_t* entries, uint64_t* total) {
  std::string bytes;
  if (Status s = reader.Read(kHeaderBytes, &bytes); !s.ok()) {
    return Status::InvalidArgument("not a placedb snapshot archive (too short)");
  }
  if (std::memcmp(bytes.data(), kMagic, sizeof kMagic) != 0) {
    return Status::InvalidArgument("not a placedb snapshot archive (bad magic)");
  }
  const uint32_t version = GetLe<uint32_t>(bytes.data() + sizeof kMagic);
  if (version != kVersion) {
    return Status::InvalidArgument("snapshot archive version " + std::to_string(version) +
                                   " is not supported (this server reads version " +
                                   std::to_string(kVersion) + ")");
  }
  *entries = 0;
  *total = 0;
  for (;;) {
    PLACEDB_RETURN_IF_ERROR(reader.Read(1, &bytes));
    const uint8_t kind = uint8_t(bytes[0]);
    if (kind == 0) return Status::Ok();
    if (kind != 1) {
      return Status::InvalidArgument("unknown entry kind " + std::to_string(kind) + " at byte " +
                                     std::to_string(reader.offset() - 1));
    }
    EntryFraming entry;
    entry.index = ++*entries;
    if (entry.index > kMaxSnapshotArchiveEntries) {
      return Status::InvalidArgument("the archive has more than " +
                                     std::to_string(kMaxSnapshotArchiveEntries) +
                                     " entries (the limit of a snapshot archive)");
    }
    PLACEDB_RETURN_IF_ERROR(reader.Read(2, &bytes));
    const uint16_t length = GetLe<uint16_t>(bytes.data());
    if (length > kMaxPath) {
      return Status::InvalidArgument("archive entry " + std::to_string(entry.index) +
                                     " has a path of " + std::to_string(length) +
                                     " bytes (at most " + std::to_string(kMaxPath) + ")");
    }
    PLACEDB_RETURN_IF_ERROR(reader.Read(length, &entry.path));
    if (!SafeEntryPath(entry.path) || (entry.index == 1) != (entry.path == kManifest)) {
      return Status::InvalidArgument("archive entry " + std::to_string(entry.index) +
                                     " has an unacceptable path " + QuoteForMessage(entry.path));
    }
    PLACEDB_RETURN_IF_ERROR(reader.Read(8, &bytes));
    entry.size = GetLe<uint64_t>(bytes.data());
    if (entry.index == 1 && entry.size > kMaxSnapshotManifestBytes) {
      return Status::InvalidArgument(
          std::string(kManifest) + " is " + std::to_string(entry.size) + " bytes, over the " +
          std::to_string(kMaxSnapshotManifestBytes) + "-byte limit of a snapshot manifest");
    }
    PLACEDB_RETURN_IF_ERROR(body(entry));
    *total += entry.size;
  }
}

}  // namespace

Status ValidateSnapshotId(std::string_view id) {
  if (id.empty() || id.size() > 200) {
    return Status::InvalidArgument("snapshot id must have 1 to 200 characters");
  }
  if (id.front() == '.') return Status::InvalidArgument("snapshot id must not start with '.'");
  for (char c : id) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '_' && c != '-') {
      return Status::InvalidArgument("snapshot id " + QuoteForMessage(id, 200) +
                                     " may hold only letters, digits, '.', '_' and '-'");
    }
  }
  return Status::Ok();
}

Status CheckSnapshotArchiveHead(std::string_view head) {
  if (head.size() < kHeaderBytes) return Status::Ok();  // too short to tell
  ArchiveReader reader(std::make_unique<std::istringstream>(std::string(head)), head.size());
  uint64_t entries = 0, total = 0;
  Status walked = WalkArchive(
      reader, [&](const EntryFraming& entry) { return reader.Skip(entry.size); }, &entries, &total);
  // CORRUPTION here only means that `head` ends before the archive does: nothing known yet.
  return walked.code() == StatusCode::kInvalidArgument ? walked : Status::Ok();
}

SnapshotStore::SnapshotStore(DataDirectory* directory, SnapshotOptions options, std::string path)
    : directory_(directory),
      storage_(directory->options()),
      options_(options),
      path_(std::move(path)) {}

Result<std::unique_ptr<SnapshotStore>> SnapshotStore::Open(DataDirectory* directory,
                                                           SnapshotOptions options) {
  const std::string path = (fs::path(directory->path()) / "snapshots").string();
  std::error_code ec;
  fs::create_directories(path, ec);
  if (ec) return Status::IoError("creating " + path + ": " + ec.message());
  // Leftovers of interrupted operations: dot-folders and dot-files are never snapshots.
  for (const auto& entry : fs::directory_iterator(path, ec)) {
    if (entry.path().filename().string().front() == '.') fs::remove_all(entry.path(), ec);
  }
  return std::unique_ptr<SnapshotStore>(new SnapshotStore(directory, options, path));
}

std::string SnapshotStore::Scratch(const std::string& what) {
  return (fs::path(path_) / ("." + what + "-" + std::to_string(NowUnixMs()) + "-" +
                             std::to_string(++scratch_counter_)))
      .string();
}

std::string SnapshotStore::UniqueId(const std::string& map, int64_t unix_ms) const {
  const std::string base = map + "-" + std::to_string(unix_ms);
  std::string id = base;
  for (int n = 2; fs::exists(fs::path(path_) / id); ++n) id = base + "-" + std::to_string(n);
  return id;
}

Status SnapshotStore::Verify(const std::string& checkpoint, const std::string& scratch,
                             const DataDirectory::VocabularyFor& vocabulary,
                             SnapshotInfo* info) const {
  Status status;
  {
    StorageOptions storage = storage_;
    storage.block_cache_bytes = size_t(8) << 20;
    storage.disk_reserve_bytes = 0;
    auto scratch_dir = DataDirectory::Open(scratch, storage);
    if (!scratch_dir.ok()) return scratch_dir.status().WithContext("verifying the snapshot");
    status = (*scratch_dir)->RestoreMap("verify", checkpoint);
    if (status.ok()) {
      auto stored = (*scratch_dir)->ReadMapInfo("verify");
      status = stored.status();
      if (status.ok()) {
        auto map_vocabulary = vocabulary(*stored);
        status = map_vocabulary.status();
        if (status.ok()) {
          auto map = (*scratch_dir)->OpenMap("verify", *map_vocabulary);
          status = map.status();
          if (status.ok()) {
            // The machine's cores (at most 4): a verification is what a restore or a new
            // cluster replica waits for.
            const int threads = int(std::clamp(std::thread::hardware_concurrency(), 1u, 4u));
            auto scrub = (*map)->Scrub(threads);
            status = scrub.status();
            if (status.ok() && !scrub->clean()) {
              const std::string what = !scrub->damaged_files.empty()
                                           ? scrub->damaged_files.front().file + ": " +
                                                 scrub->damaged_files.front().reason
                                           : "place " +
                                                 std::to_string(scrub->damaged_places.front().id) +
                                                 ": " + scrub->damaged_places.front().reason;
              status = Status::Corruption("the snapshot's map is damaged: " + what);
            }
            if (status.ok()) {
              info->places = (*map)->Stats().database.places;
              info->feature_type = FeatureTypeName(stored->options.database.feature_type);
              info->vocabulary_checksum = stored->vocabulary_checksum;
            }
          }
        }
      }
    }
  }
  std::error_code ec;
  fs::remove_all(scratch, ec);
  return status.WithContext("verifying the snapshot");
}

Result<SnapshotInfo> SnapshotStore::Create(const PlaceMap& map,
                                           const DataDirectory::VocabularyFor& vocabulary) {
  return MakeSnapshot(map, "snapshot of map '",
                      [&](const std::string& checkpoint, SnapshotInfo* info) {
                        std::string scratch;
                        {
                          MutexLock lock(mutex_);
                          scratch = Scratch("verify");
                        }
                        return Verify(checkpoint, scratch, vocabulary, info);
                      });
}

Result<SnapshotInfo> SnapshotStore::CreateForTransfer(const PlaceMap& map) {
  return MakeSnapshot(
      map, "checkpoint for a transfer of map '", [&](const std::string&, SnapshotInfo* info) {
        // No writers meanwhile: the caller's promise.
        info->places = map.Stats().database.places;
        info->feature_type = FeatureTypeName(map.info().options.database.feature_type);
        info->vocabulary_checksum = map.info().vocabulary_checksum;
        return Status::Ok();
      });
}

Result<SnapshotInfo> SnapshotStore::MakeSnapshot(
    const PlaceMap& map, const std::string& what,
    const std::function<Status(const std::string& checkpoint, SnapshotInfo* info)>& describe) {
  SnapshotInfo info;
  info.map = map.info().name;
  info.created_unix_ms = NowUnixMs();
  std::string staging;
  {
    MutexLock lock(mutex_);
    staging = Scratch("creating");
  }
  // The checkpoint and its description need no lock: they use their own dot-folders only, so
  // List, Get, Delete and downloads go on meanwhile.
  std::error_code ec;
  fs::create_directories(staging, ec);
  if (ec) return Status::IoError("creating " + staging + ": " + ec.message());
  const std::string checkpoint = (fs::path(staging) / kCheckpoint).string();
  Status status = map.Checkpoint(checkpoint);
  if (status.ok()) status = describe(checkpoint, &info);
  if (status.ok()) {
    info.bytes = DirectoryBytes(checkpoint);
    MutexLock lock(mutex_);
    info.id = UniqueId(info.map, info.created_unix_ms);
    status = StoreLocked(staging, info);
    if (status.ok()) ApplyRetention(info.map);
  }
  if (!status.ok()) {
    fs::remove_all(staging, ec);
    return status.WithContext(what + info.map + "'");
  }
  return info;
}

Status SnapshotStore::StoreLocked(const std::string& staging, const SnapshotInfo& info) {
  {
    std::ofstream out(fs::path(staging) / kManifest, std::ios::binary | std::ios::trunc);
    out << EncodeManifest(info);
    out.flush();
    if (!out) return Status::IoError("writing the snapshot's manifest");
  }
  std::error_code ec;
  fs::rename(staging, fs::path(path_) / info.id, ec);
  if (ec) return Status::IoError("storing snapshot " + info.id + ": " + ec.message());
  return Status::Ok();
}

void SnapshotStore::ApplyRetention(const std::string& map) {
  if (options_.keep_per_map == 0) return;
  std::vector<SnapshotInfo> of_map;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(path_, ec)) {
    auto info = GetLocked(entry.path().filename().string());
    if (info.ok() && info->map == map) of_map.push_back(*info);
  }
  if (of_map.size() <= options_.keep_per_map) return;
  std::sort(of_map.begin(), of_map.end(), [](const SnapshotInfo& a, const SnapshotInfo& b) {
    return a.created_unix_ms != b.created_unix_ms ? a.created_unix_ms > b.created_unix_ms
                                                  : a.id > b.id;
  });
  for (size_t i = options_.keep_per_map; i < of_map.size(); ++i) {
    fs::remove_all(fs::path(path_) / of_map[i].id, ec);
  }
}

Result<SnapshotInfo> SnapshotStore::GetLocked(const std::string& id) const {
  PLACEDB_RETURN_IF_ERROR(ValidateSnapshotId(id));
  const fs::path dir = fs::path(path_) / id;
  auto text = ReadWholeFile((dir / kManifest).string());
  if (!text.ok()) {
    if (text.status().code() == StatusCode::kNotFound) {
      return Status::NotFound("snapshot '" + id + "' not found");
    }
    return text.status();
  }
  auto info = DecodeManifest(*text);
  if (!info.ok()) return Status::Corruption("snapshot '" + id + "': " + info.status().message());
  info->bytes = DirectoryBytes((dir / kCheckpoint).string());
  return info;
}

Result<SnapshotInfo> SnapshotStore::Get(const std::string& id) const {
  MutexLock lock(mutex_);
  return GetLocked(id);
}

std::vector<SnapshotInfo> SnapshotStore::List() const {
  MutexLock lock(mutex_);
  std::vector<SnapshotInfo> out;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(path_, ec)) {
    const std::string name = entry.path().filename().string();
    if (name.front() == '.') continue;
    auto info = GetLocked(name);
    if (info.ok()) out.push_back(*info);
  }
  std::sort(out.begin(), out.end(), [](const SnapshotInfo& a, const SnapshotInfo& b) {
    return a.created_unix_ms != b.created_unix_ms ? a.created_unix_ms > b.created_unix_ms
                                                  : a.id > b.id;
  });
  return out;
}

Status SnapshotStore::Delete(const std::string& id) {
  MutexLock lock(mutex_);
  PLACEDB_RETURN_IF_ERROR(GetLocked(id).status());
  const std::string trash = Scratch("deleting");
  std::error_code ec;
  fs::rename(fs::path(path_) / id, trash, ec);
  if (ec) return Status::IoError("deleting snapshot '" + id + "': " + ec.message());
  fs::remove_all(trash, ec);
  return Status::Ok();
}

Status SnapshotStore::Restore(const std::string& id, const std::string& new_map) {
  MutexLock lock(mutex_);
  PLACEDB_RETURN_IF_ERROR(ValidateMapName(new_map).WithContext("new map"));
  PLACEDB_RETURN_IF_ERROR(GetLocked(id).status());
  return directory_->RestoreMap(new_map, (fs::path(path_) / id / kCheckpoint).string());
}

Status SnapshotStore::CheckRoomForImport(uint64_t archive_bytes) const {
  const uint64_t needed = archive_bytes > UINT64_MAX / 4 ? UINT64_MAX / 2 : 2 * archive_bytes;
  return CheckRoomFor(
      path_, needed, storage_.disk_reserve_bytes,
      "importing a snapshot archive of " + std::to_string(archive_bytes) + " bytes");
}

Result<uint64_t> SnapshotStore::ArchiveBytes(const std::string& id) const {
  MutexLock lock(mutex_);
  PLACEDB_RETURN_IF_ERROR(GetLocked(id).status());
  const fs::path dir = fs::path(path_) / id;
  auto paths = EntryPaths(dir.string());
  if (!paths.ok()) return paths.status();
  uint64_t total = kHeaderBytes;
  std::error_code ec;
  for (const std::string& p : *paths) total += 1 + 2 + p.size() + 8 + fs::file_size(dir / p, ec);
  return total + 1 + 8 + 8 + kDigestBytes;
}

Status SnapshotStore::WriteArchive(const std::string& id, size_t chunk_bytes,
                                   const std::function<Status(std::string_view)>& sink) const {
  chunk_bytes = std::max<size_t>(chunk_bytes, 4096);
  const fs::path dir = fs::path(path_) / id;
  // Every file is opened under the lock, then streamed without it: a slow client holds up no
  // other snapshot operation, and a Delete meanwhile does not cut the download short (the open
  // files stay readable).
  std::vector<std::string> paths;
  std::vector<std::unique_ptr<std::ifstream>> files;
  std::vector<uint64_t> sizes;
  {
    MutexLock lock(mutex_);
    PLACEDB_RETURN_IF_ERROR(GetLocked(id).status());
    auto listed = EntryPaths(dir.string());
    if (!listed.ok()) return listed.status();
    paths = std::move(listed).value();
    for (const std::string& p : paths) {
      std::error_code ec;
      sizes.push_back(fs::file_size(dir / p, ec));
      files.push_back(std::make_unique<std::ifstream>(dir / p, std::ios::binary));
      if (!*files.back() || ec) return Status::IoError("reading " + p + " of snapshot " + id);
    }
  }
  Sha256 sha;
  std::string pending;
  auto emit = [&](std::string_view bytes, bool hash = true) -> Status {
    if (hash) sha.Update(bytes);
    pending.append(bytes);
    while (pending.size() >= chunk_bytes) {
      PLACEDB_RETURN_IF_ERROR(sink(std::string_view(pending).substr(0, chunk_bytes)));
      pending.erase(0, chunk_bytes);
    }
    return Status::Ok();
  };
  std::string header(kMagic, sizeof kMagic);
  PutLe<uint32_t>(&header, kVersion);
  PutLe<uint32_t>(&header, 0);
  PLACEDB_RETURN_IF_ERROR(emit(header));
  uint64_t total = 0;
  std::string buffer(std::min<size_t>(chunk_bytes, size_t(1) << 20), '\0');
  for (size_t f = 0; f < paths.size(); ++f) {
    const std::string& p = paths[f];
    std::ifstream& in = *files[f];
    const uint64_t size = sizes[f];
    std::string entry;
    PutLe<uint8_t>(&entry, 1);
    PutLe<uint16_t>(&entry, uint16_t(p.size()));
    entry += p;
    PutLe<uint64_t>(&entry, size);
    PLACEDB_RETURN_IF_ERROR(emit(entry));
    uint64_t left = size;
    while (left > 0) {
      const size_t n = size_t(std::min<uint64_t>(left, buffer.size()));
      if (!in.read(buffer.data(), std::streamsize(n))) {
        return Status::IoError("reading " + p + " of snapshot " + id + ": shorter than its size");
      }
      PLACEDB_RETURN_IF_ERROR(emit(std::string_view(buffer.data(), n)));
      left -= n;
    }
    total += size;
  }
  std::string end;
  PutLe<uint8_t>(&end, 0);
  PutLe<uint64_t>(&end, uint64_t(paths.size()));
  PutLe<uint64_t>(&end, total);
  PLACEDB_RETURN_IF_ERROR(emit(end));
  PLACEDB_RETURN_IF_ERROR(emit(sha.Final(), /*hash=*/false));
  if (!pending.empty()) PLACEDB_RETURN_IF_ERROR(sink(pending));
  return Status::Ok();
}

Result<SnapshotInfo> SnapshotStore::Import(const std::string& archive_path,
                                           const DataDirectory::VocabularyFor& vocabulary) {
  std::error_code ec;
  const uint64_t archive_bytes = fs::file_size(archive_path, ec);
  if (ec) return Status::NotFound("cannot open archive " + archive_path + ": " + ec.message());
  auto open = [&] {
    return ArchiveReader(std::make_unique<std::ifstream>(archive_path, std::ios::binary),
                         archive_bytes);
  };
  // First the framing alone, skipping every entry's bytes: an archive over a limit, or with a
  // bad path or kind, costs a few reads and leaves no file behind (200,000 tiny entries cost 34 s
  // of file creation before the count was checked).
  {
    ArchiveReader framing = open();
    if (!framing.is_open()) return Status::NotFound("cannot open archive " + archive_path);
    uint64_t entries = 0, total = 0;
    Status walked = WalkArchive(
        framing, [&](const EntryFraming& entry) { return framing.Skip(entry.size); }, &entries,
        &total);
    if (!walked.ok()) {
      return walked.WithContext("importing " + fs::path(archive_path).filename().string());
    }
  }
  ArchiveReader reader = open();
  if (!reader.is_open()) return Status::NotFound("cannot open archive " + archive_path);
  std::string staging, scratch;
  {
    MutexLock lock(mutex_);
    staging = Scratch("importing");
    scratch = Scratch("verify");
  }
  // Unpacking and verification need no lock (own dot-folders), as in Create.
  fs::create_directories(fs::path(staging) / kCheckpoint, ec);
  if (ec) return Status::IoError("creating " + staging + ": " + ec.message());
  SnapshotInfo info;
  auto extract = [&]() -> Status {
    uint64_t entries = 0;
    uint64_t total = 0;
    std::string manifest_text;  // at most kMaxSnapshotManifestBytes (WalkArchive)
    std::string buffer;
    PLACEDB_RETURN_IF_ERROR(WalkArchive(
        reader,
        [&](const EntryFraming& entry) -> Status {
          const fs::path target = fs::path(staging) / entry.path;
          fs::create_directories(target.parent_path(), ec);
          if (ec || fs::exists(target)) {
            return Status::InvalidArgument("archive entry " +
                                           QuoteForMessage(entry.path, kMaxPath) +
                                           " appears twice or clashes with another entry's folder");
          }
          std::ofstream out(target, std::ios::binary);
          if (!out) return Status::IoError("writing " + target.string());
          uint64_t left = entry.size;
          while (left > 0) {
            const size_t n = size_t(std::min<uint64_t>(left, uint64_t(1) << 20));
            PLACEDB_RETURN_IF_ERROR(reader.Read(n, &buffer));
            if (entry.index == 1) manifest_text += buffer;
            out.write(buffer.data(), std::streamsize(n));
            left -= n;
          }
          out.flush();
          if (!out) return Status::IoError("writing " + target.string());
          return Status::Ok();
        },
        &entries, &total));
    std::string bytes;
    PLACEDB_RETURN_IF_ERROR(reader.Read(16, &bytes));
    const uint64_t stated_entries = GetLe<uint64_t>(bytes.data());
    const uint64_t stated_total = GetLe<uint64_t>(bytes.data() + 8);
    const std::string digest = reader.Digest();
    std::string stated_digest;
    PLACEDB_RETURN_IF_ERROR(reader.Read(kDigestBytes, &stated_digest, /*hash=*/false));
    if (!reader.AtEnd()) return Status::InvalidArgument("bytes after the archive's end");
    if (digest != stated_digest) {
      return Status::Corruption("the archive's SHA-256 does not match its contents");
    }
    if (stated_entries != entries || stated_total != total) {
      return Status::Corruption("the archive's entry count or size does not match its contents");
    }
    if (entries == 0) return Status::InvalidArgument("the archive holds no manifest");
    auto manifest = DecodeManifest(manifest_text);
    if (!manifest.ok()) return manifest.status();
    info = *manifest;
    const SnapshotInfo stated = info;
    PLACEDB_RETURN_IF_ERROR(
        Verify((fs::path(staging) / kCheckpoint).string(), scratch, vocabulary, &info));
    if (info.places != stated.places || info.vocabulary_checksum != stated.vocabulary_checksum ||
        info.feature_type != stated.feature_type) {
      return Status::InvalidArgument(
          "the archive's manifest does not agree with the map inside it (places " +
          std::to_string(stated.places) + " vs " + std::to_string(info.places) + ")");
    }
    return Status::Ok();
  };
  Status status = extract();
  if (status.ok()) {
    MutexLock lock(mutex_);
    if (fs::exists(fs::path(path_) / info.id)) info.id = UniqueId(info.map, info.created_unix_ms);
    status = StoreLocked(staging, info);
  }
  if (!status.ok()) {
    fs::remove_all(staging, ec);
    return status.WithContext("importing " + fs::path(archive_path).filename().string());
  }
  info.bytes = DirectoryBytes((fs::path(path_) / info.id / kCheckpoint).string());
  return info;
}

}  // namespace placedb
