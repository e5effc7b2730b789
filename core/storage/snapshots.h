// Snapshots: named, verified, online copies of one map, kept in the data directory, with an
// archive format to move them between servers (docs/storage.md, "Snapshots": design, figures).
//
// Layout: DATA_DIR/snapshots/<id>/ holds SNAPSHOT.json (the manifest: format version, source
// map, creation time, vocabulary kind and checksum, places) and checkpoint/ (a RocksDB checkpoint
// made by PlaceMap::Checkpoint: the map's info record, places and damage history travel inside
// it; ACKED is rebuilt from its contents on restore). A snapshot under construction lives in a
// dot-folder and is renamed into place only once verified, so List never shows a half snapshot.
//
// Verification (Create and Import): the checkpoint is restored into a scratch data directory
// under snapshots/.verify-*, opened as a placedb map with the vocabulary the caller resolves from
// its info record, and scrubbed (every place decoded, every SST block checked). Only a clean
// scrub whose info agrees with the manifest makes a snapshot.
//
// Archive (version 1; all integers little-endian):
//   header  "PDBSNAP\n" (8 bytes), u32 version = 1, u32 flags = 0
//   entry*  u8 kind = 1, u16 path length, path (relative, '/'-separated, no "." or ".." parts,
//           "SNAPSHOT.json" first, then "checkpoint/<file>"), u64 size, size bytes
//   end     u8 kind = 0, u64 entry count, u64 sum of entry sizes,
//           32 bytes SHA-256 of every archive byte before them
// Limits (an archive comes from the network): a path of at most 1024 bytes, a SNAPSHOT.json of
// at most kMaxSnapshotManifestBytes (a real one is a few hundred bytes; it is the one entry held
// in memory), at most kMaxSnapshotArchiveEntries entries (a checkpoint of a map at the 64 GiB
// upload limit has a few thousand files at most). Import checks every limit from the field that
// states it, before reading what that field sizes, and checks the whole framing (limits, kinds,
// paths, sizes against the file's length) before it writes any file; other entries are copied
// through a 1 MiB buffer, so an import holds little memory whatever the archive claims.
// A truncated archive, a wrong digest or count: CORRUPTION (gRPC DATA_LOSS). Not an archive, an
// unknown version, a bad path, an archive over a limit, a manifest that does not parse or does
// not agree with the map inside: INVALID_ARGUMENT. A vocabulary this server does not have:
// FAILED_PRECONDITION. In every failure nothing is left behind.
//
// Thread safety: a SnapshotStore serialises its own operations, except that WriteArchive holds
// the lock only to open the snapshot's files (a slow reader blocks nothing; a Delete meanwhile
// does not cut it short), and Create and Import hold it only to name their dot-folders and to
// store the verified result: the checkpoint, unpacking and verification run without it, so List,
// Get, Delete and downloads do not wait for them. Create takes an online checkpoint, so writers
// of the map are not held up beyond RocksDB's memtable flush. Only Restore uses the
// DataDirectory; the rest may run while it closes.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "core/storage/map_store.h"

namespace placedb {

struct SnapshotInfo {
  std::string id;   // "<map>-<unix ms>[-<n>]"; ValidateSnapshotId accepts it
  std::string map;  // the source map's name
  int64_t created_unix_ms = 0;
  std::string feature_type;  // the vocabulary's kind ("orb", "sift")
  uint64_t vocabulary_checksum = 0;
  uint64_t places = 0;  // places in the snapshot
  uint64_t bytes = 0;   // checkpoint files on disk
};

struct SnapshotOptions {
  // Snapshots kept per source map; creating one more deletes the oldest. 0 = keep all.
  size_t keep_per_map = 5;
};

// INVALID_ARGUMENT unless 1..200 characters of [A-Za-z0-9._-] not starting with '.'.
Status ValidateSnapshotId(std::string_view id);

// Archive limits (see the header comment); the refusal's message names the limit.
inline constexpr uint64_t kMaxSnapshotManifestBytes = uint64_t(64) << 10;
inline constexpr uint64_t kMaxSnapshotArchiveEntries = 10'000;

// What an archive's first bytes (`head`, e.g. the start of an upload) already tell: the
// INVALID_ARGUMENT Import would answer for any archive starting so (not an archive, an unknown
// version, a bad entry kind or path, a manifest or entry count over the limits), else OK. Lets a
// receiver refuse before spooling the rest; Import still checks everything.
Status CheckSnapshotArchiveHead(std::string_view head);

class SnapshotStore {
 public:
  // `directory` must outlive Restore calls. Creates DATA_DIR/snapshots/ and removes leftovers of
  // interrupted operations (dot-folders) found there.
  static Result<std::unique_ptr<SnapshotStore>> Open(DataDirectory* directory,
                                                     SnapshotOptions options = {});

  // An online, consistent, verified snapshot of `map` (ingest may continue meanwhile).
  Result<SnapshotInfo> Create(const PlaceMap& map, const DataDirectory::VocabularyFor& vocabulary);
  // A snapshot of `map` for handing to another store, which verifies it on Import (a cluster
  // replica's catch-up, server/cluster/shard.h): Create without the verification (about half of
  // Create's time on a large map: the receiver's Import opens and scrubs it anyway; the archive's
  // SHA-256 covers the transfer). The manifest's place count is the map's right after the
  // checkpoint, so the caller keeps the map's writers out during the call. It is meant for
  // WriteArchive and then Delete; retention and List treat it as any snapshot.
  Result<SnapshotInfo> CreateForTransfer(const PlaceMap& map);
  // Newest first.
  std::vector<SnapshotInfo> List() const;
  Result<SnapshotInfo> Get(const std::string& id) const;  // NOT_FOUND if absent
  Status Delete(const std::string& id);
  // The snapshot as a new map `new_map` (ALREADY_EXISTS when it exists).
  Status Restore(const std::string& id, const std::string& new_map);

  // Streams the snapshot's archive to `sink` in pieces of at most `chunk_bytes`; a sink error
  // stops the stream and is returned. The archive's size is ArchiveBytes(id).
  Status WriteArchive(const std::string& id, size_t chunk_bytes,
                      const std::function<Status(std::string_view)>& sink) const;
  Result<uint64_t> ArchiveBytes(const std::string& id) const;
  // Reads, checks and verifies the archive file at `archive_path` and keeps it as a new
  // snapshot (a new id when its own id is taken). See the header comment for the errors.
  Result<SnapshotInfo> Import(const std::string& archive_path,
                              const DataDirectory::VocabularyFor& vocabulary);

  // RESOURCE_EXHAUSTED ("disk full") unless the data directory has room for importing an archive
  // of `archive_bytes`: the archive spooled before Import and the copy Import unpacks from it,
  // beyond StorageOptions::disk_reserve_bytes (DataDirectory::CheckRoomFor).
  Status CheckRoomForImport(uint64_t archive_bytes) const;

  const std::string& path() const { return path_; }

 private:
  SnapshotStore(DataDirectory* directory, SnapshotOptions options, std::string path);
  // Restores `checkpoint` into the scratch data directory `scratch` (removed after), opens and
  // scrubs it; fills places, feature type and vocabulary checksum.
  Status Verify(const std::string& checkpoint, const std::string& scratch,
                const DataDirectory::VocabularyFor& vocabulary, SnapshotInfo* info) const;
  // Create's and CreateForTransfer's common part: the checkpoint in a dot-folder, `describe`
  // filling in what it holds (places, feature type, vocabulary), then stored under a new id;
  // errors carry `what` + the map's name.
  Result<SnapshotInfo> MakeSnapshot(
      const PlaceMap& map, const std::string& what,
      const std::function<Status(const std::string& checkpoint, SnapshotInfo* info)>& describe);
  // Writes info's manifest into `staging` and renames it to info.id.
  Status StoreLocked(const std::string& staging, const SnapshotInfo& info) REQUIRES(mutex_);
  std::string UniqueId(const std::string& map, int64_t unix_ms) const REQUIRES(mutex_);
  Result<SnapshotInfo> GetLocked(const std::string& id) const REQUIRES(mutex_);
  void ApplyRetention(const std::string& map) REQUIRES(mutex_);
  std::string Scratch(const std::string& what) REQUIRES(mutex_);

  DataDirectory* const directory_;  // Restore only
  const StorageOptions storage_;    // the directory's, for verification and CheckRoomForImport
  const SnapshotOptions options_;
  const std::string path_;
  mutable Mutex mutex_;
  uint64_t scratch_counter_ GUARDED_BY(mutex_) = 0;
};

}  // namespace placedb
