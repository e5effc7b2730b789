// Engines: real 3-node nats-server (JetStream) and etcd clusters for cluster-mode tests and
// benchmarks (issue 18).
//
// Each node i runs one nats-server (server_name "n<i>", JetStream on a file store in the
// harness's temp dir, routes to the others) and one etcd member ("e<i>"), on the node's host
// address (127.0.0.1 by default; give one 127.0.0.x per node, or later a network namespace's
// address) with free ports picked at start. Start() returns once the JetStream meta leader is
// elected (every node answers account info) and every etcd member answers a linearizable read.
//
// Clean-up, so that no engine outlives a test run:
// - every engine runs in its own process group and gets SIGKILL when the test process dies
//   (PR_SET_PDEATHSIG, bound to the thread that started it: start engines from the test's main
//   thread);
// - the destructor SIGKILLs every group and removes the temp dir;
// - each running engine has a pid file in PidDirectory(); tests/cluster/cleanup_engines.sh (a ctest
//   FIXTURES_CLEANUP test) kills whatever a crashed run left behind and removes its temp dir.
//
// Threading: not thread-safe; use an Engines from one thread.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "server/cluster/internal_tls.h"

namespace placedb::cluster::testing {

struct EnginesOptions {
  int nodes = 3;
  // One host address per node; when empty, PLACEDB_ENGINES_HOSTS (comma-separated) or else
  // 127.0.0.1 for all.
  std::vector<std::string> hosts;
  // One network namespace per node (tests/cluster/hosts.h), or empty: the caller's. A node's
  // engines run inside its namespace and its ports are picked there.
  std::vector<std::string> netns;
  bool nats = true;
  bool etcd = true;
  // Mutual TLS on every engine port (PEM paths; empty: plain text): nats-server's clients
  // (`tls { verify: true }`: a client certificate signed by ca_file required) and routes, etcd's
  // clients (--client-cert-auth) and peers. cert_file must name the nodes' addresses (SANs) and
  // allow serverAuth and clientAuth: it is every engine's certificate, and the harness's own as
  // a client (client_tls()).
  struct Tls {
    std::string ca_file, cert_file, key_file;
  } tls{};
  std::chrono::seconds ready_timeout{60};
};

// `count` distinct free TCP ports on `host`, all below the kernel's ephemeral port range
// (/proc/sys/net/ipv4/ip_local_port_range). A port from that range, once the engine holding it is
// killed, can be taken by any outgoing connection as its source port (a client reconnecting to
// the dead port may even connect to itself), and the restarted engine then cannot bind it: under
// load, with many reconnecting clients, that made restarts fail. Another test process may still
// take a port before the engine binds it (rare: the start then fails and says so).
Result<std::vector<int>> FreePorts(const std::string& host, int count);

// One engine process (a process group of its own).
class EngineProcess {
 public:
  EngineProcess() = default;
  ~EngineProcess();
  EngineProcess(const EngineProcess&) = delete;
  EngineProcess& operator=(const EngineProcess&) = delete;

  // Starts `argv` (argv[0] a path) with stdout+stderr appended to `log_path`; inside the network
  // namespace /run/netns/`netns` when given (joined by the child before exec: same pid, so the
  // process group and PR_SET_PDEATHSIG hold as without one).
  Status Start(std::vector<std::string> argv, const std::string& log_path,
               const std::string& netns = "");
  // SIGKILL to the group, then reaps. No-op when not running.
  void Kill();
  // False once the process has exited (reaped here, so that a wait for it ends at once).
  bool running() const;
  pid_t pid() const { return pid_; }

 private:
  std::vector<std::string> argv_;
  mutable pid_t pid_ = -1;  // reaped by running() too
};

class Engines {
 public:
  static Result<std::unique_ptr<Engines>> Start(EnginesOptions options = {});
  ~Engines();
  Engines(const Engines&) = delete;
  Engines& operator=(const Engines&) = delete;

  int nodes() const { return static_cast<int>(nodes_.size()); }
  const std::string& host(int node) const;

  // "nats://host:port" of every node / of one.
  std::vector<std::string> NatsUrls() const;
  std::string NatsUrl(int node) const;
  std::string NatsServerName(int node) const;
  // The node of a nats server_name ("n2" -> 2), or -1.
  int NodeOfServerName(const std::string& server_name) const;
  // The harness's client TLS (EnginesOptions::tls's files; not enabled without them): give it to
  // JetStreamOptions::tls / EtcdOptions::tls to reach the engines.
  const InternalTls& client_tls() const { return client_tls_; }
  // "host:port" of every etcd member / of one.
  std::vector<std::string> EtcdEndpoints() const;
  std::string EtcdEndpoint(int node) const;

  // SIGKILL (no clean shutdown: a crash or a power cut of the process).
  void KillNats(int node);
  void KillEtcd(int node);
  // Starts the node's engine again on its data dir and ports; returns when it answers (nats:
  // accepts connections; etcd: answers a linearizable read, which needs a quorum).
  Status RestartNats(int node);
  Status RestartEtcd(int node);
  bool NatsRunning(int node) const;
  bool EtcdRunning(int node) const;
  // Both engines of a node: SIGKILL (reaps them, also when Hosts::Kill already killed them) and
  // restart (returns once both answer, as RestartNats/RestartEtcd).
  void KillNode(int node);
  Status RestartNode(int node);

  // The node whose nats-server is the JetStream meta leader (from the monitoring endpoint /jsz of
  // a running node), or an error when none is known within `timeout`.
  Result<int> MetaLeader(std::chrono::milliseconds timeout = std::chrono::seconds(10)) const;
  // "host:port" of a node's nats-server monitoring endpoint (HTTP).
  std::string NatsMonitor(int node) const;

  // The node whose nats-server leads `stream` (asked through any live node), or an error when no
  // leader is elected within `timeout`.
  Result<int> StreamLeader(const std::string& stream,
                           std::chrono::milliseconds timeout = std::chrono::seconds(10)) const;

  // Where engine pid files live (one file per running engine, named after its pid).
  static std::string PidDirectory();
  const std::string& directory() const { return directory_; }

 private:
  struct Node {
    std::string host;
    int nats_port = 0;
    int nats_cluster_port = 0;
    int nats_http_port = 0;
    std::string netns;
    int etcd_client_port = 0;
    int etcd_peer_port = 0;
    EngineProcess nats;
    EngineProcess etcd;
  };
  explicit Engines(EnginesOptions options) : options_(std::move(options)) {}
  Status Setup();
  Status StartNats(int node);
  Status StartEtcd(int node);
  Status WaitNatsReady(int node, std::chrono::steady_clock::time_point deadline) const;
  Status WaitEtcdReady(int node, std::chrono::steady_clock::time_point deadline) const;
  Status WaitStreamsPlaceable(std::chrono::steady_clock::time_point deadline) const;

  EnginesOptions options_;
  InternalTls client_tls_;
  std::string directory_;
  std::vector<std::unique_ptr<Node>> nodes_;
};

}  // namespace placedb::cluster::testing
