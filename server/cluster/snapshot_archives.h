// Cluster snapshots (issue 35, docs/cluster.md "Admin through workers"): snapshot archives
// (core/storage/snapshots.h format) kept in the cluster, not on one worker's disk, so that any
// worker lists, downloads, deletes and restores what another made.
//
// - The archive's bytes: chunks of kSnapshotChunkBytes (below NATS' default 1 MiB payload) on
//   subject placedb.<name>.snapshots.<hex of the id> of the JetStream stream
//   PLACEDB_<NAME>_SNAPSHOTS (file storage, the cluster's stream_replicas: stored as a map's
//   records are), one more subject token per stored archive (two Puts racing for one id never
//   share chunks), message ids unique to the Put (a retried publish is not stored twice).
// - The manifest: etcd snapshots/<id> (JSON), written create-if-absent after the last chunk is
//   acknowledged: the snapshot exists from that write on, whole. Delete removes the manifest
//   first, then purges the chunks' subject (a failure then leaves chunks no manifest names,
//   purged again by the next Delete of the id).
// - Reading checks the size and the SHA-256 of the bytes against the manifest.
//
// Thread safety: every method may be called concurrently.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/storage/snapshots.h"
#include "proto/cluster.grpc.pb.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"

namespace placedb::cluster {

inline constexpr size_t kSnapshotChunkBytes = size_t(512) << 10;

struct SnapshotManifest {
  SnapshotInfo info;  // id, source map, created, feature type, vocabulary, places, bytes
  // The stream sequence the archive's map holds everything up to: a map restored from it
  // continues its stream (and place ids) at base + 1.
  uint64_t base = 0;
  std::string config_json;  // the map's placedb.v1.MapConfig (proto JSON): a restored map's
  uint64_t archive_bytes = 0;
  std::string sha256;           // hex, of the archive's bytes
  std::string subject;          // the chunks' (one per stored archive: a failed Put purges its own)
  uint64_t first_sequence = 0;  // the first chunk's in the snapshots stream
  uint64_t chunks = 0;
};

std::string EncodeSnapshotManifest(const SnapshotManifest& manifest);
Result<SnapshotManifest> DecodeSnapshotManifest(const std::string& json);

// Issue 35 (compaction): a map's base, etcd bases/<map>: a verified replica checkpoint stored as
// a snapshot's archive is (its manifest's `base` = B, the sequence it holds every record up to;
// info.id "base:<map>", never listed with the snapshots), for the map of that create revision
// (a map re-created under its name has none). The map's stream may be purged below B + 1: a
// replica whose applied + 1 is below the stream's first sequence restores it, then the tail.
struct MapBase {
  int64_t create_revision = 0;  // of maps/<map>
  SnapshotManifest manifest;
  int64_t mod_revision = 0;  // of bases/<map> as read (compare-and-swap); not stored
};
std::string EncodeMapBase(const MapBase& base);
Result<MapBase> DecodeMapBase(const std::string& json);  // CORRUPTION when malformed

// What a replica's Shard.Checkpoint streamed into a file.
struct FetchedCheckpoint {
  uint64_t applied = 0;  // the applied sequence the archive holds
  uint64_t bytes = 0;
};
// Reads `stub`'s Checkpoint (`request`) into the file `spool` (truncated first). IO_ERROR naming
// `from` when the call fails, CORRUPTION when fewer bytes came than announced.
Result<FetchedCheckpoint> FetchCheckpoint(v1::Shard::Stub* stub, grpc::ClientContext* context,
                                          const v1::CheckpointRequest& request,
                                          const std::string& spool, const std::string& from);

class SnapshotArchives {
 public:
  SnapshotArchives(JetStream* jetstream, EtcdClient* etcd, std::string cluster_name,
                   int stream_replicas);

  // Stores the archive file at `path` under manifest->info.id (a free id: "-<n>" appended when
  // it is taken), filling in the id, archive_bytes, sha256, first_sequence and chunks. Nothing
  // is listed on failure (published chunks are purged again). IO_ERROR when the engines fail.
  Status Put(const std::string& path, SnapshotManifest* manifest,
             std::chrono::system_clock::time_point deadline);
  Result<std::vector<SnapshotManifest>> List();         // newest first
  Result<SnapshotManifest> Get(const std::string& id);  // NOT_FOUND naming the id
  // The archive's bytes to `sink` in their stored chunks; a sink error stops it and is returned.
  // CORRUPTION when the bytes read do not have the manifest's size and SHA-256 (known after the
  // last chunk: the sink must discard what it got), IO_ERROR when the stream does not deliver
  // them by `deadline`, or delivers nothing for 30 s (the snapshot deleted meanwhile).
  Status Read(const SnapshotManifest& manifest, std::chrono::system_clock::time_point deadline,
              const std::function<Status(std::string_view)>& sink);
  // Copies the archive into the file `path` (Read's errors).
  Status ReadToFile(const SnapshotManifest& manifest, const std::string& path,
                    std::chrono::system_clock::time_point deadline);
  Status Delete(const std::string& id);  // NOT_FOUND naming the id

  // Compaction (MapBase above). Stores the archive at `path` as `map`'s base (filling
  // base->manifest's id, size, SHA-256, subject, chunks), committed by one etcd transaction:
  // bases/<map> still at `expected_mod_revision` (0: absent) and every one of `guards` (the
  // coordinator key still ours, the map still of base->create_revision). FAILED_PRECONDITION when a
  // guard failed (another compaction or coordinator won: this one's chunks are purged), IO_ERROR
  // when the engines fail. The previous base's chunks stay: the caller deletes them (DeleteChunks)
  // once this one is durable.
  Status PutBase(const std::string& map, const std::string& path, MapBase* base,
                 int64_t expected_mod_revision, std::vector<Compare> guards,
                 std::chrono::system_clock::time_point deadline);
  // The map's base, nullopt when it has none.
  Result<std::optional<MapBase>> GetBase(const std::string& map);
  // Purges an archive's chunks (a replaced base's).
  Status DeleteChunks(const SnapshotManifest& manifest);
  // Deletes bases/<map> and its chunks (DeleteMap); OK when there is none.
  Status DeleteBase(const std::string& map);

 private:
  std::string Key(const std::string& id) const;
  // The archive's chunks on a subject unique to this call; fills manifest's id, archive_bytes,
  // sha256, subject, first_sequence, chunks. Purged again on failure.
  Status StoreChunks(const std::string& path, const std::string& id, SnapshotManifest* manifest,
                     std::chrono::system_clock::time_point deadline);
  Status EnsureStream();

  JetStream* const jetstream_;
  EtcdClient* const etcd_;
  const std::string cluster_name_;
  const int stream_replicas_;
  const std::string stream_;
};

}  // namespace placedb::cluster
