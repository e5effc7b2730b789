// Hosts: several "machines" on this one, for cluster-mode tests (issue 18).
//
// As root, each host is a network namespace of its own (`ip netns`): loopback up, and one veth
// pair whose outer end joins a bridge in the caller's (root) namespace. Host i has the address
// 10.<x>.0.<i+1>/24 and the bridge 10.<x>.0.254/24, so the test process reaches every host and
// the hosts reach each other only over the bridge; <x> is claimed per run (see Registry below),
// so parallel runs do not collide. Killing a host SIGKILLs every process inside its namespace and
// takes its link down: its ports are unreachable from the others, as after a power cut.
//
// Without the rights for namespaces (not root, no `ip`), each host is one loopback address
// 127.0.0.<i+2> in the caller's namespace (kind() says which was used): no isolation, and a
// host's kill only kills the process groups registered with Track().
//
// Clean-up: the destructor kills every process of every host and removes namespaces, veths and
// the bridge. A crashed run leaves a registry file (RegistryDirectory()/10.<x>, naming its owner
// pid, bridge and namespaces); tests/cluster/cleanup_engines.sh removes what a dead owner left,
// and Create() reclaims a subnet whose owner is dead.
//
// Threading: not thread-safe; use a Hosts from one thread (RunInside() runs its function on a
// thread of its own).
#pragma once

#include <sys/types.h>

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "tests/cluster/engines.h"

namespace placedb::cluster::testing {

struct HostsOptions {
  int hosts = 3;
  // False: the loopback fallback even as root (for runs that compare the two).
  bool allow_netns = true;
};

class Hosts {
 public:
  enum class Kind { kNetns, kLoopback };

  // Creates the hosts; in netns mode fails (and removes what it made) when a step fails, except
  // that a failure to create the first namespace falls back to loopback hosts.
  static Result<std::unique_ptr<Hosts>> Create(HostsOptions options = {});
  ~Hosts();
  Hosts(const Hosts&) = delete;
  Hosts& operator=(const Hosts&) = delete;

  Kind kind() const { return kind_; }
  // "netns" or "loopback", for test output.
  const char* kind_name() const { return kind_ == Kind::kNetns ? "netns" : "loopback"; }
  int size() const { return static_cast<int>(hosts_.size()); }
  // The host's IPv4 address (where its processes listen).
  const std::string& address(int host) const;
  // The host's namespace name (under /run/netns), or "" for loopback hosts.
  const std::string& netns(int host) const;
  // Per-host namespaces, for EnginesOptions::netns (empty for loopback hosts).
  std::vector<std::string> Namespaces() const;
  std::vector<std::string> Addresses() const;

  // Registers a process group started for `host` (loopback hosts have no namespace to sweep).
  void Track(int host, pid_t process_group);
  // Starts `argv` as `process` inside the host (its namespace; for loopback hosts, where the
  // caller is) and tracks it, so Kill(host) kills it with the rest: how tests run a
  // placedb-server (shard, worker) on a host. `process` must outlive the host's use of it.
  Status StartProcess(int host, EngineProcess& process, std::vector<std::string> argv,
                      const std::string& log_path);

  // SIGKILLs every process of the host (netns: every process in its namespace, plus tracked
  // groups) and, for netns hosts, takes its link down. The processes are not reaped: their
  // parents do that (EngineProcess::Kill). Idempotent.
  Status Kill(int host);
  // Brings a killed host's link up again (processes are the caller's to restart).
  Status Start(int host);
  bool up(int host) const;

  // Pids of live processes inside the host's namespace (empty for loopback hosts).
  std::vector<pid_t> Processes(int host) const;

  // Runs `fn` on a new thread that has joined the host's network namespace (the caller's for
  // loopback hosts) and waits for it. Fails when the namespace cannot be joined.
  Status RunInside(int host, const std::function<void()>& fn) const;

  static std::string RegistryDirectory();

 private:
  struct Host {
    std::string address;
    std::string netns;
    std::string veth;  // outer end, in the caller's namespace
    bool up = true;
    std::vector<pid_t> tracked;
  };
  Hosts() = default;
  Status SetupNetns(int count);
  void SetupLoopback(int count);
  void TearDown();

  Kind kind_ = Kind::kLoopback;
  int subnet_ = -1;  // <x> of 10.<x>.0.0/24
  std::string bridge_;
  std::string registry_file_;
  std::vector<Host> hosts_;
};

// Runs `ip` with `args` (no shell); its stderr goes into the error.
Status RunIp(const std::vector<std::string>& args);

// Runs `fn` on a new thread that has joined the network namespace /run/netns/`netns` (setns moves
// only the calling thread), and waits for it; `netns` empty: on the caller's namespace. Fails,
// without running `fn`, when the namespace cannot be joined.
Status RunInNetns(const std::string& netns, const std::function<void()>& fn);

}  // namespace placedb::cluster::testing
