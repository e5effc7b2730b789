// Cluster mode's metadata in etcd (issue 18, docs/cluster.md): the key layout, a watcher-fed
// cache of it for routing (ClusterView), and the coordinator that places maps on shards.
//
// Keys under /placedb/<cluster name>/ (ClusterKeys):
//   shards/<shard_id>        {"address": "host:port"}, with the shard's lease (it is live while
//                            the key exists)
//   maps/<map>               {"config": <placedb.v1.MapConfig as proto JSON>, "stream": name,
//                            "created_unix_ms": N}
//   placement/<map>          {"epoch": N, "replicas": ["shard-a", "shard-b"]}; written only by
//                            the coordinator (and deleted with the map by DeleteMap)
//   applied/<map>/<shard_id> decimal applied sequence of that replica (the shard refreshes it)
//   coordinator              the elected coordinator's id, with its lease
//   bases/<map>              issue 35: the map's compaction base (snapshot_archives.h, MapBase);
//                            written by the coordinator's compaction (compare-and-swap)
//
// The coordinator runs inside the WORKER processes (every worker campaigns; one holds the key).
// Why there and not in shards: a shard's death is exactly the event the coordinator must react
// to (replace its replicas); a coordinator inside shards would go down with the shard it has to
// replace half the time, adding a re-election to every replacement. Workers are the processes
// that write maps/<map> (CreateMap) and wait for its placement, need only etcd for it, and are
// stateless, so a coordinator failover costs one lease TTL and nothing else: its whole state is
// etcd's (the grace timers of missing shards restart with a new coordinator: a replacement may
// come up to replace_after_s later, never earlier).
//
// Consistency: every coordinator write is one etcd transaction comparing the coordinator key's
// value (still us) and the placement key's mod revision as read (absent for a new map): two
// coordinators (a paused one whose lease expired) or a DeleteMap racing cannot lose an update;
// the loser re-reads on the next round. A replacement bumps the epoch.
//
// Threading: ClusterView and Coordinator are thread-safe; each runs one thread of its own (the
// view's is its etcd Watcher's). The EtcdClient must outlive them.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "server/cluster/etcd_client.h"

namespace placedb::cluster {

// The key layout of one cluster (see the file comment).
struct ClusterKeys {
  explicit ClusterKeys(std::string cluster_name);
  std::string root;  // "/placedb/<name>/"
  std::string Shard(const std::string& id) const { return root + "shards/" + id; }
  std::string Map(const std::string& map) const { return root + "maps/" + map; }
  std::string Placement(const std::string& map) const { return root + "placement/" + map; }
  std::string Applied(const std::string& map, const std::string& shard) const {
    return root + "applied/" + map + "/" + shard;
  }
  std::string AppliedPrefix(const std::string& map) const { return root + "applied/" + map + "/"; }
  std::string Coordinator() const { return root + "coordinator"; }
  std::string Snapshot(const std::string& id) const { return root + "snapshots/" + id; }
  // Issue 35, compaction: the map's base (server/cluster/snapshot_archives.h, MapBase).
  std::string Base(const std::string& map) const { return root + "bases/" + map; }
};

// Stream of a map: PLACEDB_<NAME>_<hex of the map name's bytes>, upper-case; subject
// placedb.<name>.map.<hex> (map names may hold characters NATS subjects cannot).
std::string HexOf(const std::string& bytes);
std::string StreamName(const std::string& cluster_name, const std::string& map);
std::string StreamSubject(const std::string& cluster_name, const std::string& map);
// Issue 35: the cluster's snapshot archives (server/cluster/snapshot_archives.h): stream
// PLACEDB_<NAME>_SNAPSHOTS (not a hex name: no map's), subjects placedb.<name>.snapshots.<hex id>
// (and one more token per stored archive).
std::string SnapshotStreamName(const std::string& cluster_name);
std::string SnapshotSubject(const std::string& cluster_name, const std::string& id);

struct Placement {
  int64_t epoch = 0;
  std::vector<std::string> replicas;  // shard ids
  int64_t mod_revision = 0;           // of the placement key when read (compare-and-swap)
};
std::string EncodePlacement(const Placement& placement);
Result<Placement> DecodePlacement(const std::string& json);  // INVALID_ARGUMENT when malformed

// maps/<map>'s value.
struct MapRecordInfo {
  std::string config_json;  // placedb.v1.MapConfig as proto JSON (effective: vocabulary named)
  std::string stream;
  int64_t created_unix_ms = 0;
  // Issue 35: a map restored from a cluster snapshot (snapshots/<id>): its replicas start from
  // that archive, and its stream from snapshot_base + 1 (the archive holds the records up to it).
  std::string snapshot;
  uint64_t snapshot_base = 0;
};
std::string EncodeMapInfo(const MapRecordInfo& info);
Result<MapRecordInfo> DecodeMapInfo(const std::string& json);

// What the view holds of one map.
struct MapView {
  MapRecordInfo info;
  int64_t create_revision = 0;  // of maps/<map>: a map re-created under its name has another
  std::optional<Placement> placement;
  std::map<std::string, uint64_t> applied;  // shard id -> applied sequence (as last published)
};

// A cache of the cluster's keys, fed by one etcd watch (read once, then every change in order).
// Readers get copies. A watch that ends (its revision compacted) is restarted from a fresh read.
class ClusterView {
 public:
  static Result<std::unique_ptr<ClusterView>> Start(EtcdClient* etcd, std::string cluster_name);
  ~ClusterView();  // Stop()
  ClusterView(const ClusterView&) = delete;
  ClusterView& operator=(const ClusterView&) = delete;
  void Stop() EXCLUDES(mutex_);

  const ClusterKeys& keys() const { return keys_; }
  std::optional<MapView> Map(const std::string& map) const EXCLUDES(mutex_);
  std::map<std::string, MapView> Maps() const EXCLUDES(mutex_);
  // Live shards (their key exists): id -> address.
  std::map<std::string, std::string> Shards() const EXCLUDES(mutex_);
  // Waits until `ready(view of the map or nullopt)` holds or `deadline`; true if it held.
  // `ready` runs under the view's lock: it must not call the view.
  bool WaitFor(const std::string& map,
               const std::function<bool(const std::optional<MapView>&)>& ready,
               std::chrono::steady_clock::time_point deadline) EXCLUDES(mutex_);

 private:
  ClusterView(EtcdClient* etcd, std::string cluster_name);
  Status Load() EXCLUDES(mutex_);  // a fresh read, then the watch from its revision + 1
  void Apply(const KeyValue& kv, bool deleted) REQUIRES(mutex_);
  void OnEnd(const Status& why) EXCLUDES(mutex_);

  EtcdClient* const etcd_;
  const ClusterKeys keys_;
  mutable Mutex mutex_;
  CondVar changed_;
  std::map<std::string, MapView> maps_ GUARDED_BY(mutex_);
  std::map<std::string, std::string> shards_ GUARDED_BY(mutex_);
  // Applied sequences and placements may arrive before maps/<map> (watch order is revision
  // order, but a map's keys are written by different processes): kept apart until then.
  std::map<std::string, Placement> placements_ GUARDED_BY(mutex_);
  std::map<std::string, std::map<std::string, uint64_t>> applied_ GUARDED_BY(mutex_);
  std::unique_ptr<Watcher> watcher_;  // replaced only by the restart thread
  std::thread restart_;               // restarts a watch that ended
  bool stopping_ GUARDED_BY(mutex_) = false;
  bool restart_wanted_ GUARDED_BY(mutex_) = false;
  void RestartLoop() EXCLUDES(mutex_);
};

struct CoordinatorOptions {
  std::string self;  // this process's id (stored in the coordinator key)
  int replicas = 2;
  std::chrono::seconds replace_after{30};
  int64_t lease_ttl_s = 5;
  std::chrono::milliseconds period{500};  // one round of campaign / placement
};

// Campaigns for the coordinator key and, while holding it, places maps on shards (see the file
// comment): a map without placement gets min(replicas, live shards) of the least loaded live
// shards; a placed map gets a missing replica slot filled when a live shard is free; a replica
// whose shard key has been gone for replace_after is replaced by the least loaded live shard not
// already a replica (epoch + 1). Load = placements a shard is in.
class Coordinator {
 public:
  Coordinator(EtcdClient* etcd, ClusterView* view, CoordinatorOptions options);
  ~Coordinator();  // Stop(); the lease is revoked so that another process takes over at once
  Coordinator(const Coordinator&) = delete;
  Coordinator& operator=(const Coordinator&) = delete;
  void Stop() EXCLUDES(mutex_);
  bool leading() const { return leading_.load(); }
  uint64_t placements_written() const { return written_.load(); }

 private:
  void Run() EXCLUDES(mutex_);
  void Campaign();
  void Place();
  // One compare-and-swap of placement/<map>; false when another writer won (re-read next round).
  bool Write(const std::string& map, const std::optional<Placement>& previous,
             const Placement& next);

  EtcdClient* const etcd_;
  ClusterView* const view_;
  const CoordinatorOptions options_;
  std::atomic<bool> leading_{false};
  std::atomic<uint64_t> written_{0};
  std::unique_ptr<LeaseKeeper> keeper_;  // Run()'s thread only
  int64_t lease_ = 0;                    // Run()'s thread only
  // Shard id -> when the coordinator first saw it missing (Run()'s thread only).
  std::map<std::string, std::chrono::steady_clock::time_point> missing_since_;
  Mutex mutex_;
  CondVar wake_;
  bool stopping_ GUARDED_BY(mutex_) = false;
  std::thread thread_;
};

}  // namespace placedb::cluster
