// Multi-host test hosts (tests/cluster/hosts.h): network namespaces on a bridge (as root) or
// loopback addresses, with the engine clusters of tests/cluster/engines.h running inside them.
//
// Times (re-election after a host kill) are printed as `name value unit`, never asserted; the
// bounded waits only keep a broken engine from hanging the test.
#include "tests/cluster/hosts.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <csignal>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

#include "bench/bench_output.h"
#include "server/cluster/jetstream.h"
#include "tests/cluster/engines.h"

namespace placedb::cluster {
namespace {

namespace fs = std::filesystem;
using namespace std::chrono_literals;
using testing::Engines;
using testing::EnginesOptions;
using testing::Hosts;
using testing::HostsOptions;

// True when a TCP connection to host:port is established within `limit` (a dead or cut-off host
// either refuses, answers host-unreachable or stays silent: all false).
bool Reaches(const std::string& host, int port, std::chrono::milliseconds limit = 1000ms) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd < 0) return false;
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  bool connected = false;
  if (::inet_pton(AF_INET, host.c_str(), &address.sin_addr) == 1) {
    if (::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0) {
      connected = true;
    } else if (errno == EINPROGRESS) {
      pollfd waiting{fd, POLLOUT, 0};
      int error = 0;
      socklen_t length = sizeof(error);
      connected = ::poll(&waiting, 1, static_cast<int>(limit.count())) == 1 &&
                  ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &error, &length) == 0 && error == 0;
    }
  }
  ::close(fd);
  return connected;
}

// Reaches(), run inside `from`'s network namespace.
bool ReachesFrom(const Hosts& hosts, int from, const std::string& host, int port) {
  bool reached = false;
  EXPECT_TRUE(hosts.RunInside(from, [&] { reached = Reaches(host, port); }).ok());
  return reached;
}

// The state letter of /proc/<pid>/stat ('Z' zombie), or 0 when there is no such process.
char ProcessState(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
  std::string stat((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const size_t paren = stat.rfind(')');
  return paren == std::string::npos || paren + 2 >= stat.size() ? 0 : stat[paren + 2];
}

int PortOf(const std::string& url) {
  return std::stoi(url.substr(url.rfind(':') + 1));
}

std::unique_ptr<JetStream> Js(const Engines& engines, std::vector<int> nodes) {
  JetStreamOptions options;
  for (int node : nodes) options.servers.push_back(engines.NatsUrl(node));
  options.request_timeout = 2s;
  auto js = JetStream::Connect(options);
  EXPECT_TRUE(js.ok()) << js.status().ToString();
  return js.ok() ? std::move(*js) : nullptr;
}

// Publishes until a PubAck comes (same message id on every try, as the workers do), bounded.
Result<PubAck> PublishRetrying(JetStream& js, const std::string& subject, const std::string& id) {
  Result<PubAck> ack = Status::IoError("not tried");
  const auto until = std::chrono::steady_clock::now() + 60s;
  while (std::chrono::steady_clock::now() < until) {
    ack = js.Publish(subject, "payload " + id, id, 2s);
    if (ack.ok()) return ack;
    std::this_thread::sleep_for(200ms);
  }
  return ack;
}

TEST(HostsTest, EnginesRunInsideIsolatedHostsAndAKilledMetaLeaderHostIsReplaced) {
  auto hosts_or = Hosts::Create(HostsOptions{});
  ASSERT_TRUE(hosts_or.ok()) << hosts_or.status().ToString();
  Hosts& hosts = **hosts_or;
  std::printf("hosts: %s (%s, %s, %s)\n", hosts.kind_name(), hosts.address(0).c_str(),
              hosts.address(1).c_str(), hosts.address(2).c_str());
  const bool netns = hosts.kind() == Hosts::Kind::kNetns;
  if (::geteuid() == 0) {
    EXPECT_TRUE(netns) << "root: network namespaces expected";
  }

  EnginesOptions options;
  options.hosts = hosts.Addresses();
  options.netns = hosts.Namespaces();
  const double start_ms = bench::NowMs();
  auto engines_or = Engines::Start(options);
  ASSERT_TRUE(engines_or.ok()) << engines_or.status().ToString();
  Engines& engines = **engines_or;
  bench::Print("hosts_engines_start_ms", bench::NowMs() - start_ms, "ms");

  if (netns) {
    for (int i = 0; i < 3; ++i) {
      // nats-server and etcd of node i, and nothing else, live in host i.
      EXPECT_EQ(hosts.Processes(i).size(), 2u) << "host " << i;
    }
    // Each host has its own loopback: a listener on 127.0.0.1 inside host 1 (the socket stays in
    // the namespace it was made in) is reachable from host 1 only; host 1's nats-server is
    // reachable from host 0 on host 1's address, over the bridge.
    int listener = -1;
    int loopback_port = 0;
    ASSERT_TRUE(hosts
                    .RunInside(1,
                               [&] {
                                 listener = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
                                 sockaddr_in address{};
                                 address.sin_family = AF_INET;
                                 address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
                                 socklen_t length = sizeof(address);
                                 if (::bind(listener, reinterpret_cast<sockaddr*>(&address),
                                            sizeof(address)) == 0 &&
                                     ::listen(listener, 4) == 0 &&
                                     ::getsockname(listener, reinterpret_cast<sockaddr*>(&address),
                                                   &length) == 0) {
                                   loopback_port = ntohs(address.sin_port);
                                 }
                               })
                    .ok());
    ASSERT_GT(loopback_port, 0);
    EXPECT_TRUE(ReachesFrom(hosts, 1, "127.0.0.1", loopback_port));
    EXPECT_FALSE(ReachesFrom(hosts, 0, "127.0.0.1", loopback_port));
    ::close(listener);
    const int port1 = PortOf(engines.NatsUrl(1));
    EXPECT_TRUE(ReachesFrom(hosts, 0, hosts.address(1), port1));
  }

  auto js = Js(engines, {0, 1, 2});
  ASSERT_TRUE(js);
  StreamConfig stream;
  stream.name = "PLACEDB_HOSTS_TEST";
  stream.subjects = {"placedb.hosts.test"};
  const Status made = js->EnsureStream(stream);
  ASSERT_TRUE(made.ok()) << made.ToString();
  auto first = PublishRetrying(*js, stream.subjects[0], "a/1");
  ASSERT_TRUE(first.ok()) << first.status().ToString();

  auto leader_or = engines.MetaLeader(20s);
  ASSERT_TRUE(leader_or.ok()) << leader_or.status().ToString();
  const int killed = *leader_or;
  const int other = (killed + 1) % 3;
  const int nats_port = PortOf(engines.NatsUrl(killed));
  const int etcd_port = PortOf(engines.EtcdEndpoint(killed));
  std::printf("meta leader: n%d on %s\n", killed, hosts.address(killed).c_str());
  ASSERT_TRUE(ReachesFrom(hosts, other, hosts.address(killed), nats_port));

  // The whole host goes: every process in it, and (netns) its link.
  const double killed_ms = bench::NowMs();
  ASSERT_TRUE(hosts.Kill(killed).ok());
  engines.KillNode(killed);  // reaps (and, for loopback hosts, kills) the node's engines
  if (netns) {
    EXPECT_TRUE(hosts.Processes(killed).empty());
  }
  EXPECT_FALSE(ReachesFrom(hosts, other, hosts.address(killed), nats_port));
  EXPECT_FALSE(ReachesFrom(hosts, other, hosts.address(killed), etcd_port));
  EXPECT_FALSE(Reaches(hosts.address(killed), nats_port));

  // The two left elect a new meta leader, and the stream takes writes again.
  auto new_leader = engines.MetaLeader(30s);
  ASSERT_TRUE(new_leader.ok()) << new_leader.status().ToString();
  EXPECT_NE(*new_leader, killed);
  bench::Print("hosts_meta_leader_reelected_ms", bench::NowMs() - killed_ms, "ms");
  auto survivors = Js(engines, {(killed + 1) % 3, (killed + 2) % 3});
  ASSERT_TRUE(survivors);
  auto second = PublishRetrying(*survivors, stream.subjects[0], "a/2");
  ASSERT_TRUE(second.ok()) << second.status().ToString();
  EXPECT_EQ(second->sequence, first->sequence + 1);
  bench::Print("hosts_publish_after_host_kill_ms", bench::NowMs() - killed_ms, "ms");

  // The host comes back on the same address, ports and data: reachable, and in the cluster.
  ASSERT_TRUE(hosts.Start(killed).ok());
  auto restarted = engines.RestartNode(killed);
  ASSERT_TRUE(restarted.ok()) << restarted.ToString();
  EXPECT_TRUE(ReachesFrom(hosts, other, hosts.address(killed), nats_port));
  auto returned = Js(engines, {killed});
  ASSERT_TRUE(returned);
  auto third = PublishRetrying(*returned, stream.subjects[0], "a/3");
  ASSERT_TRUE(third.ok()) << third.status().ToString();
  EXPECT_EQ(third->sequence, first->sequence + 2);
  // A retried id is still a duplicate across the host's restart.
  auto again = PublishRetrying(*returned, stream.subjects[0], "a/2");
  ASSERT_TRUE(again.ok());
  EXPECT_TRUE(again->duplicate);
  EXPECT_EQ(again->sequence, second->sequence);
}

TEST(HostsTest, DestructorRemovesNamespacesBridgeAndRegistryAndKillsEveryProcess) {
  std::vector<std::string> namespaces;
  std::string registry_entries_before;
  pid_t sleeper = -1;
  {
    auto hosts = Hosts::Create(HostsOptions{2, true});
    ASSERT_TRUE(hosts.ok()) << hosts.status().ToString();
    if ((*hosts)->kind() != Hosts::Kind::kNetns)
      GTEST_SKIP() << "loopback hosts: nothing to remove";
    namespaces = (*hosts)->Namespaces();
    for (const auto& name : namespaces) EXPECT_TRUE(fs::exists("/run/netns/" + name)) << name;
    // A process inside host 1 that nobody tracks: the namespace sweep must find it.
    testing::EngineProcess process;
    ASSERT_TRUE(process.Start({"/bin/sleep", "600"}, "/dev/null", namespaces[1]).ok());
    sleeper = process.pid();
    // And one started through the host, killed with it.
    testing::EngineProcess tracked;
    ASSERT_TRUE((*hosts)->StartProcess(0, tracked, {"/bin/sleep", "600"}, "/dev/null").ok());
    ASSERT_TRUE((*hosts)->Kill(0).ok());
    for (int i = 0; i < 100 && ProcessState(tracked.pid()) != 'Z'; ++i) {
      std::this_thread::sleep_for(20ms);
    }
    EXPECT_EQ(ProcessState(tracked.pid()), 'Z') << "killed with its host";
    EXPECT_FALSE((*hosts)->up(0));
    ASSERT_TRUE([&] {
      for (int i = 0; i < 100; ++i) {
        if (!(*hosts)->Processes(1).empty()) return true;
        std::this_thread::sleep_for(20ms);
      }
      return false;
    }());
    hosts->reset();
    // Killed by the sweep: a zombie until the EngineProcess reaps it.
    EXPECT_EQ(ProcessState(sleeper), 'Z') << "pid " << sleeper << " outlived its host";
  }
  for (const auto& name : namespaces) EXPECT_FALSE(fs::exists("/run/netns/" + name)) << name;
  const std::string run = "pdb" + std::to_string(::getpid());
  for (const auto& entry : fs::directory_iterator("/sys/class/net")) {
    EXPECT_NE(entry.path().filename().string().rfind(run, 0), 0u)
        << "left behind: " << entry.path().filename();
  }
  for (const auto& entry : fs::directory_iterator(Hosts::RegistryDirectory())) {
    std::ifstream in(entry.path());
    pid_t owner = 0;
    in >> owner;
    EXPECT_NE(owner, ::getpid()) << "registry entry left: " << entry.path();
  }
}

// A test process that dies (SIGKILL) with hosts and engines up: the engines die with it
// (PR_SET_PDEATHSIG, also inside a namespace), and cleanup_engines.sh removes what it left (the
// namespaces, the bridge, the registry entry), as ctest's cleanup fixture does after a crash.
TEST(HostsTest, ACrashedRunsEnginesDieAndTheCleanupScriptRemovesItsHosts) {
  if (::geteuid() != 0) GTEST_SKIP() << "loopback hosts: nothing left to remove";
  // The child's own pid directory: the script must not touch engines of parallel tests.
  const std::string pid_dir =
      fs::temp_directory_path() / ("placedb-hosts-crash-" + std::to_string(::getpid()));
  fs::create_directories(pid_dir);
  int pipe_fds[2];
  ASSERT_EQ(::pipe(pipe_fds), 0);
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    ::close(pipe_fds[0]);
    ::setenv("PLACEDB_CLUSTER_PID_DIR", pid_dir.c_str(), 1);
    auto hosts = Hosts::Create(HostsOptions{2, true});
    if (!hosts.ok() || (*hosts)->kind() != Hosts::Kind::kNetns) _exit(3);
    EnginesOptions options;
    options.nodes = 2;
    options.hosts = (*hosts)->Addresses();
    options.netns = (*hosts)->Namespaces();
    options.etcd = false;
    auto engines = Engines::Start(options);
    if (!engines.ok()) _exit(4);
    // "<netns> <pid>...\n" per host, then wait to be killed.
    std::string report;
    for (int i = 0; i < 2; ++i) {
      report += (*hosts)->netns(i);
      for (pid_t pid : (*hosts)->Processes(i)) report += " " + std::to_string(pid);
      report += "\n";
    }
    report += "end\n";
    if (::write(pipe_fds[1], report.data(), report.size()) < 0) _exit(5);
    ::pause();
    _exit(0);
  }
  ::close(pipe_fds[1]);
  std::string report;
  char buffer[512];
  while (report.find("end\n") == std::string::npos) {
    const ssize_t n = ::read(pipe_fds[0], buffer, sizeof(buffer));
    if (n <= 0) break;
    report.append(buffer, static_cast<size_t>(n));
  }
  ::close(pipe_fds[0]);
  ::kill(child, SIGKILL);
  int status = 0;
  ::waitpid(child, &status, 0);
  ASSERT_NE(report.find("end\n"), std::string::npos) << "child exit " << WEXITSTATUS(status);

  std::vector<std::string> namespaces;
  std::vector<pid_t> engines;
  std::istringstream lines(report);
  for (std::string line; std::getline(lines, line) && line != "end";) {
    std::istringstream words(line);
    std::string name;
    words >> name;
    namespaces.push_back(name);
    for (pid_t pid; words >> pid;) engines.push_back(pid);
  }
  ASSERT_EQ(namespaces.size(), 2u);
  EXPECT_EQ(engines.size(), 2u);  // one nats-server per host
  for (pid_t pid : engines) {
    bool gone = false;
    for (int i = 0; i < 250 && !gone; ++i) {
      const char state = ProcessState(pid);
      gone = state == 0 || state == 'Z';
      if (!gone) std::this_thread::sleep_for(20ms);
    }
    EXPECT_TRUE(gone) << "engine " << pid << " outlived its crashed test";
  }
  for (const auto& name : namespaces) EXPECT_TRUE(fs::exists("/run/netns/" + name)) << name;

  const std::string command = std::string(PLACEDB_CLUSTER_CLEANUP_SCRIPT) + " " + pid_dir;
  EXPECT_EQ(std::system(command.c_str()), 0);
  for (const auto& name : namespaces) EXPECT_FALSE(fs::exists("/run/netns/" + name)) << name;
  const std::string run = "pdb" + std::to_string(child);
  for (const auto& entry : fs::directory_iterator("/sys/class/net")) {
    EXPECT_NE(entry.path().filename().string().rfind(run, 0), 0u)
        << "left behind: " << entry.path().filename();
  }
  for (const auto& entry : fs::directory_iterator(Hosts::RegistryDirectory())) {
    std::ifstream in(entry.path());
    pid_t owner = 0;
    in >> owner;
    EXPECT_NE(owner, child) << "registry entry left: " << entry.path();
  }
  std::error_code ignored;
  fs::remove_all(pid_dir, ignored);
}

TEST(HostsTest, LoopbackFallbackGivesOneAddressPerHostAndEnginesRunThere) {
  auto hosts = Hosts::Create(HostsOptions{3, false});
  ASSERT_TRUE(hosts.ok());
  EXPECT_EQ((*hosts)->kind(), Hosts::Kind::kLoopback);
  EXPECT_TRUE((*hosts)->Namespaces().empty());
  EnginesOptions options;
  options.hosts = (*hosts)->Addresses();
  options.etcd = false;
  auto engines = Engines::Start(options);
  ASSERT_TRUE(engines.ok()) << engines.status().ToString();
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ((*engines)->NatsUrl(i).rfind("nats://127.0.0." + std::to_string(i + 2) + ":", 0), 0u);
  }
  const int port = PortOf((*engines)->NatsUrl(1));
  ASSERT_TRUE(Reaches((*hosts)->address(1), port));
  // No namespace to sweep: a host's kill kills the process groups started through it.
  testing::EngineProcess tracked;
  ASSERT_TRUE((*hosts)->StartProcess(1, tracked, {"/bin/sleep", "600"}, "/dev/null").ok());
  ASSERT_TRUE((*hosts)->Kill(1).ok());
  for (int i = 0; i < 100 && ProcessState(tracked.pid()) != 'Z'; ++i) {
    std::this_thread::sleep_for(20ms);
  }
  EXPECT_EQ(ProcessState(tracked.pid()), 'Z') << "killed with its host";
  (*engines)->KillNode(1);
  EXPECT_FALSE(Reaches((*hosts)->address(1), port));
  auto leader = (*engines)->MetaLeader(30s);
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  EXPECT_NE(*leader, 1);
}

}  // namespace
}  // namespace placedb::cluster
