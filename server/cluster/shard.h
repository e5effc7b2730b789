// The map-shard role of cluster mode (issue 18, `placedb-server --role shard`): holds replicas of
// maps and applies their streams.
//
// What a Shard does, from Start() to its destructor:
// - Registers /placedb/<name>/shards/<shard_id> = {"address": advertise} with a lease of
//   lease_ttl_s (LeaseKeeper); when the lease is lost (etcd unreachable for a TTL, or revoked) it
//   registers again with a new lease as soon as etcd answers.
// - Follows maps/ and placement/ (an etcd watch wakes a reconcile; a reconcile also runs every
//   `reconcile_interval`): every map whose placement lists shard_id is opened from data_dir (or
//   created from maps/<map>'s config, server/cluster/placement.h's format), and an ordered
//   consumer of its stream applies the records in order from applied + 1: the consumer queues
//   them, the replica's applier thread applies what has queued up meanwhile as one synced batch
//   (ReplicaApply::ApplyBatch: place id = stream sequence, applied sequence in the same batch, so a
//   restarted shard resumes without gaps or duplicates). A placed map without a local copy is
//   first restored from the checkpoint of the live replica that applied the most (its Checkpoint
//   RPC: an unverified SnapshotStore::CreateForTransfer taken with the peer's applier paused;
//   SnapshotStore::Import verifies it here), then applied from the checkpoint's applied + 1; with
//   no such peer, or when that fails, it replays the stream from 1 (streams keep every record),
//   except a map restored from a cluster snapshot (issue 35), whose stream starts after it: that
//   replica restores the snapshot's archive from the cluster, or stays unavailable.
// - ScrubMap / RecoverMap (shard_admin.cc): this replica's scrub; a damaged one is dropped and
//   made again as a new replica (under the lifecycle lock: no reconcile races it).
//   Restores run on the reconcile thread: other maps' reconciles wait meanwhile. A map that
//   leaves the placement (or is deleted) is stopped, closed and deleted locally.
// - A record that does not decode or apply stops that replica's applier (state "failed: ..."):
//   nothing is skipped; the next reconcile starts it again from applied + 1 (so a transient
//   storage error heals; a corrupt record keeps the replica failed, and visible in Status).
// - Writes applied/<map>/<shard_id> (decimal) about every `report_interval`, and the gauges
//   placedb_shard_applied_sequence{map,shard} and placedb_shard_lag_records{map,shard} (stream
//   last sequence - applied) on `metrics`' registry when given.
// - Serves placedb.cluster.v1.Shard (proto/cluster.proto) on internal_listen (port 0 picks one,
//   see internal_port()): plain text, or with options.tls (cluster.internal_tls) mutual TLS only:
//   a caller without a certificate signed by tls.ca fails the handshake.
//
// Threading: Start/destructor from one thread; every other method is thread-safe. Consumers
// queue on libnats' delivery threads and appliers apply on their own threads (one of each per
// map), reconciles run on the shard's own thread, RPCs on gRPC's threads.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/storage/map_store.h"
#include "core/vocabulary/any_vocabulary.h"
#include "server/cluster/internal_tls.h"
#include "server/config.h"

namespace placedb::server {
class Metrics;
}  // namespace placedb::server

namespace placedb::cluster {

struct ShardOptions {
  std::string cluster_name = "placedb";  // cluster.name
  std::vector<std::string> nats;         // cluster.nats: nats://host:port
  std::vector<std::string> etcd;         // cluster.etcd: host:port
  std::string shard_id;                  // cluster.shard_id (required: main.cc defaults it)
  // cluster.advertise; empty: internal_listen's host and bound port (set it when listening on
  // 0.0.0.0 or behind a name).
  std::string advertise;
  std::string internal_listen = "127.0.0.1:50061";  // cluster.internal_listen; port 0 picks one
  std::string data_dir;                             // the usual data_dir: maps/<name>/ as today
  StorageOptions storage;                           // the usual storage options
  server::SearchSettings search;                    // the usual search settings
  uint32_t max_descriptors_per_frame = 4000;        // limits.max_descriptors_per_frame
  // cluster.internal_tls: mutual TLS on the internal API, the checkpoint fetches from peers,
  // NATS and etcd (server/cluster/internal_tls.h); not enabled = plain text everywhere.
  InternalTls tls{};
  // Vocabulary name -> vocabulary (the server's `vocabularies`, loaded by the caller); a map's
  // MapConfig.vocabulary picks one ("" = "default"). A map whose vocabulary is missing stays
  // unopened with the reason in Status.
  std::map<std::string, AnyVocabulary> vocabularies;
  server::Metrics* metrics = nullptr;  // optional; must outlive the Shard
  int64_t lease_ttl_s = 5;
  std::chrono::milliseconds report_interval{1000};     // applied/<map>/<id>, gauges
  std::chrono::milliseconds reconcile_interval{1000};  // besides every watch event
};

// What Status reports per replica.
struct ReplicaStatus {
  std::string map;
  uint64_t applied_sequence = 0;
  uint64_t stream_last_sequence = 0;  // as last read (0: unknown)
  uint64_t places = 0;
  // "applying", "failed: <reason>", "unavailable: <reason>", "damaged: <reason>" (its storage:
  // RecoverMap rebuilds it)
  std::string state;
  // Issue 29: the vocabulary whose switch this replica has prepared (0: none).
  uint64_t prepared_vocabulary = 0;
  // The peer whose checkpoint this replica started from (when this process created it), or
  // "snapshot <id>" (a map restored from a cluster snapshot); empty when it replayed the stream
  // from its start or was already on disk.
  std::string restored_from;
};

class Shard {
 public:
  // Opens data_dir, connects to NATS and etcd, serves internal_listen, registers, then returns;
  // maps are opened by the first reconcile (right after). INVALID_ARGUMENT for missing options
  // (shard_id, nats, etcd, data_dir, a "default" vocabulary), the errors of DataDirectory::Open,
  // IO_ERROR when NATS or etcd does not answer or the port cannot be bound. Nothing is left
  // running on failure.
  static Result<std::unique_ptr<Shard>> Start(ShardOptions options);
  // Stops serving, the appliers and the lease keeper (the registration then expires after its
  // TTL: a restart within it keeps the placement), closes the maps.
  ~Shard();
  Shard(const Shard&) = delete;
  Shard& operator=(const Shard&) = delete;

  int internal_port() const;
  const std::string& shard_id() const;
  // Every replica placed here, by map name (also ones not open, with the reason).
  std::vector<ReplicaStatus> Replicas() const;
  // The replica's open map (for tests and the process's own use); NOT_FOUND when not held,
  // UNAVAILABLE while it is not open.
  Result<std::shared_ptr<PlaceMap>> Map(const std::string& map) const;

  class Impl;

 private:
  explicit Shard(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace placedb::cluster
