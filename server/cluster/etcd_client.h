// EtcdClient: placedb's client for etcd's v3 gRPC API (metadata, leases, placement of cluster
// mode; design in /work/notes/cluster-design.md, later docs/cluster.md).
//
// Talks to etcd through our own wire-compatible subset of etcd's API
// (proto/etcd_rpc.proto): KV Range/Put/DeleteRange/Txn, Lease Grant/Revoke/
// KeepAlive, Watch.
//
// What we rely on from etcd (3.4):
// - Every KV request through the gRPC API is linearizable (Range without `serializable`), and a
//   successful reply means the change is committed on a quorum (Raft) and fsynced on it.
// - A Txn is atomic: its compares and the chosen branch apply at one revision.
// - A lease's keys are deleted when the lease expires (no keepalive within its TTL) or is
//   revoked; etcd raises a TTL below its minimum (1.5 x the election timeout) to that minimum.
// - Watch delivers every event of a key range in revision order, from any revision not yet
//   compacted; a reconnecting watcher resumes from its last revision + 1 and misses nothing.
//
// Failover: the client holds one channel per endpoint and sends each call to the member that
// answered last. When a member is UNAVAILABLE (refused, gone, no leader, leader changing) the call
// moves to the next member, round after round, until the call's deadline; then it fails with
// IO_ERROR (mapped to gRPC UNAVAILABLE, proto/status.h) naming every endpoint tried and what
// each said. A write whose reply was lost (member died after committing) may have been applied
// even though the call reports an error: callers of Txn re-read before concluding.
//
// Threading: EtcdClient is thread-safe (calls from any number of threads). LeaseKeeper and
// Watcher each run one thread of their own; their callbacks run on that thread, one at a time,
// and must not destroy or Stop() their own LeaseKeeper/Watcher. Both stop cleanly in Stop() and
// in their destructors; the client must outlive them.
#pragma once

#include <grpcpp/channel.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "server/cluster/internal_tls.h"

namespace placedb::cluster {

struct EtcdOptions {
  std::vector<std::string> endpoints;  // "host:port" of the client URLs
  // Enabled: TLS to every member (its certificate verified against tls.ca, ours presented);
  // otherwise plain text.
  InternalTls tls{};
  // Whole call, over every member it tries.
  std::chrono::milliseconds call_timeout{5000};
  // One member's attempt (a hung member costs at most this before the next is tried).
  std::chrono::milliseconds attempt_timeout{1500};
};

struct KeyValue {
  std::string key;
  std::string value;
  int64_t create_revision = 0;
  int64_t mod_revision = 0;
  int64_t version = 0;
  int64_t lease = 0;  // 0: no lease
};

struct GetResult {
  std::vector<KeyValue> kvs;  // sorted by key
  int64_t revision = 0;       // the store's revision when read
};

// One compare of a Txn. Absent(key) is create-if-absent's guard; ModRevisionIs is
// compare-and-swap's (the mod_revision of the value read).
struct Compare {
  enum class Target { kCreateRevision, kModRevision, kValue };
  enum class Op { kEqual, kNotEqual, kGreater, kLess };
  std::string key;
  Target target = Target::kCreateRevision;
  Op op = Op::kEqual;
  int64_t revision = 0;  // kCreateRevision, kModRevision
  std::string value;     // kValue

  static Compare Absent(std::string key) {
    return {std::move(key), Target::kCreateRevision, Op::kEqual, 0, {}};
  }
  static Compare ModRevisionIs(std::string key, int64_t mod_revision) {
    return {std::move(key), Target::kModRevision, Op::kEqual, mod_revision, {}};
  }
  static Compare ValueIs(std::string key, std::string value) {
    return {std::move(key), Target::kValue, Op::kEqual, 0, std::move(value)};
  }
};

// One operation of a Txn branch.
struct TxnOp {
  enum class Kind { kGet, kPut, kDelete };
  Kind kind = Kind::kGet;
  std::string key;
  std::string value;    // kPut
  int64_t lease = 0;    // kPut
  bool prefix = false;  // kGet, kDelete: every key starting with `key`

  static TxnOp Get(std::string key, bool prefix = false) {
    return {Kind::kGet, std::move(key), {}, 0, prefix};
  }
  static TxnOp Put(std::string key, std::string value, int64_t lease = 0) {
    return {Kind::kPut, std::move(key), std::move(value), lease, false};
  }
  static TxnOp Delete(std::string key, bool prefix = false) {
    return {Kind::kDelete, std::move(key), {}, 0, prefix};
  }
};

struct TxnResult {
  bool succeeded = false;       // every compare held: the success branch ran
  int64_t revision = 0;         // the store's revision after the transaction
  std::vector<GetResult> gets;  // one per kGet of the branch that ran, in order
};

struct LeaseGrant {
  int64_t id = 0;
  int64_t ttl_seconds = 0;  // as granted (etcd may raise it to its minimum)
};

struct WatchEvent {
  enum class Type { kPut, kDelete };
  Type type = Type::kPut;
  KeyValue kv;  // for kDelete: key and mod_revision (the deletion's revision) only
};

class EtcdClient;

// Keeps a lease alive from its own thread: one keepalive every ttl/3. When etcd says the lease is
// gone, or no member renewed it for a whole TTL (the lease may have expired: the holder must act
// as if it had), `on_lost` runs once with the reason and the thread ends. Stop() ends the thread
// without revoking the lease (it then expires after its TTL); it never calls `on_lost`.
class LeaseKeeper {
 public:
  using LostCallback = std::function<void(const Status& why)>;
  LeaseKeeper(EtcdClient& client, LeaseGrant lease, LostCallback on_lost);
  ~LeaseKeeper();
  LeaseKeeper(const LeaseKeeper&) = delete;
  LeaseKeeper& operator=(const LeaseKeeper&) = delete;

  // Idempotent; waits for the thread (at most one keepalive call in flight).
  void Stop() EXCLUDES(mutex_);
  bool lost() const { return lost_.load(); }
  int64_t lease_id() const { return lease_.id; }

 private:
  void Run() EXCLUDES(mutex_);

  EtcdClient& client_;
  const LeaseGrant lease_;
  const LostCallback on_lost_;
  std::atomic<bool> lost_{false};
  Mutex mutex_;
  CondVar wake_;
  bool stopping_ GUARDED_BY(mutex_) = false;
  std::thread thread_;
};

// Watches every key under a prefix from a revision, on its own thread. `on_events` gets each
// batch of events in revision order (a batch shares one revision per transaction). A broken stream
// (member killed) is reopened on the next member from the last delivered revision + 1: nothing is
// missed or repeated. When the watch cannot go on (its start revision was compacted) `on_end`
// runs once with the reason and the thread ends. Stop() cancels the stream; no callback runs
// after it returns.
class Watcher {
 public:
  using EventsCallback = std::function<void(const std::vector<WatchEvent>& events)>;
  using EndCallback = std::function<void(const Status& why)>;
  Watcher(EtcdClient& client, std::string prefix, int64_t start_revision, EventsCallback on_events,
          EndCallback on_end);
  ~Watcher();
  Watcher(const Watcher&) = delete;
  Watcher& operator=(const Watcher&) = delete;

  void Stop() EXCLUDES(mutex_);
  // The revision the next event will be at least (last delivered + 1, or the start).
  int64_t next_revision() const { return next_revision_.load(); }

 private:
  void Run() EXCLUDES(mutex_);
  // One stream on one member: returns when it breaks (OK: retry elsewhere) or must end (error).
  Status RunStream(size_t endpoint) EXCLUDES(mutex_);

  EtcdClient& client_;
  const std::string prefix_;
  const EventsCallback on_events_;
  const EndCallback on_end_;
  std::atomic<int64_t> next_revision_;
  Mutex mutex_;
  CondVar wake_;
  bool stopping_ GUARDED_BY(mutex_) = false;
  void* context_ GUARDED_BY(mutex_) = nullptr;  // the open stream's grpc::ClientContext
  std::thread thread_;
};

class EtcdClient {
 public:
  // Makes no connection yet; fails on an empty endpoint list.
  static Result<std::unique_ptr<EtcdClient>> Create(EtcdOptions options);
  ~EtcdClient();

  // The key's value, or every key under the prefix (NotFound never: an empty `kvs`).
  Result<GetResult> Get(const std::string& key, bool prefix = false);
  // Returns the revision of the write. lease 0: none.
  Result<int64_t> Put(const std::string& key, const std::string& value, int64_t lease = 0);
  // Returns how many keys were deleted (0 when none matched).
  Result<int64_t> Delete(const std::string& key, bool prefix = false);
  // Runs `success` if every compare holds, else `failure`, atomically.
  Result<TxnResult> Txn(const std::vector<Compare>& compares, const std::vector<TxnOp>& success,
                        const std::vector<TxnOp>& failure = {});

  Result<LeaseGrant> GrantLease(int64_t ttl_seconds);
  // NotFound when the lease is already gone.
  Status RevokeLease(int64_t lease_id);
  // One keepalive round trip: the renewed TTL in seconds; NotFound when the lease is gone.
  // `timeout` (0: the call timeout) bounds the call over every member.
  Result<int64_t> KeepAliveOnce(int64_t lease_id,
                                std::chrono::milliseconds timeout = std::chrono::milliseconds(0));

  // Starts a LeaseKeeper / Watcher (see their comments).
  std::unique_ptr<LeaseKeeper> KeepAlive(LeaseGrant lease, LeaseKeeper::LostCallback on_lost);
  std::unique_ptr<Watcher> Watch(const std::string& prefix, int64_t start_revision,
                                 Watcher::EventsCallback on_events,
                                 Watcher::EndCallback on_end = nullptr);

  const EtcdOptions& options() const { return options_; }
  // The smallest key greater than every key starting with `prefix` (etcd's range_end).
  static std::string PrefixEnd(const std::string& prefix);

 private:
  friend class Watcher;
  explicit EtcdClient(EtcdOptions options);

  std::shared_ptr<grpc::Channel> ChannelTo(size_t endpoint) EXCLUDES(mutex_);
  size_t preferred() EXCLUDES(mutex_);
  void set_preferred(size_t endpoint) EXCLUDES(mutex_);
  // Runs `attempt(channel, deadline)` on the members in turn from the preferred one (see the
  // file comment). `attempt` returns the gRPC status code of its call and its message.
  template <typename Attempt>
  Status WithFailover(const char* what, std::chrono::milliseconds timeout, Attempt&& attempt);

  const EtcdOptions options_;
  Mutex mutex_;
  std::vector<std::shared_ptr<grpc::Channel>> channels_ GUARDED_BY(mutex_);
  size_t preferred_ GUARDED_BY(mutex_) = 0;
};

}  // namespace placedb::cluster
