#include "tests/cluster/hosts.h"

#include <fcntl.h>
#include <ifaddrs.h>
#include <netinet/in.h>
#include <sched.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <set>
#include <thread>

namespace placedb::cluster::testing {
namespace fs = std::filesystem;

namespace {

constexpr int kFirstSubnet = 200;  // 10.200.0.0/24 .. 10.249.0.0/24: rarely used by real networks
constexpr int kLastSubnet = 249;

std::string IpBinary() {
  for (const char* candidate : {"/usr/sbin/ip", "/sbin/ip", "/usr/bin/ip", "/bin/ip"}) {
    if (::access(candidate, X_OK) == 0) return candidate;
  }
  return "/usr/sbin/ip";
}

bool ProcessAlive(pid_t pid) {
  return pid > 0 && (::kill(pid, 0) == 0 || errno == EPERM);
}

// The second octet of every 10.x.y.z address on this namespace's interfaces.
std::set<int> UsedTenSubnets() {
  std::set<int> used;
  ifaddrs* list = nullptr;
  if (::getifaddrs(&list) != 0) return used;
  for (ifaddrs* entry = list; entry; entry = entry->ifa_next) {
    if (!entry->ifa_addr || entry->ifa_addr->sa_family != AF_INET) continue;
    const uint32_t address =
        ntohl(reinterpret_cast<sockaddr_in*>(entry->ifa_addr)->sin_addr.s_addr);
    if ((address >> 24) == 10) used.insert(static_cast<int>((address >> 16) & 0xff));
  }
  ::freeifaddrs(list);
  return used;
}

// The inode of a network namespace file (/run/netns/<name> or /proc/<pid>/ns/net), or 0.
ino_t NamespaceInode(const std::string& path) {
  struct stat info {};
  return ::stat(path.c_str(), &info) == 0 ? info.st_ino : 0;
}

std::vector<pid_t> ProcessesInNamespace(const std::string& netns) {
  std::vector<pid_t> pids;
  const ino_t inode = NamespaceInode("/run/netns/" + netns);
  if (inode == 0) return pids;
  std::error_code error;
  for (const auto& entry : fs::directory_iterator("/proc", error)) {
    const std::string name = entry.path().filename().string();
    if (name.empty() || name.find_first_not_of("0123456789") != std::string::npos) continue;
    if (NamespaceInode(entry.path().string() + "/ns/net") == inode) {
      pids.push_back(static_cast<pid_t>(std::atoi(name.c_str())));
    }
  }
  return pids;
}

void KillNamespaceProcesses(const std::string& netns) {
  // A process may fork while being swept: repeat until the namespace is empty (bounded).
  for (int round = 0; round < 20; ++round) {
    const auto pids = ProcessesInNamespace(netns);
    if (pids.empty()) return;
    for (pid_t pid : pids) ::kill(pid, SIGKILL);
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

}  // namespace

Status RunIp(const std::vector<std::string>& args) {
  std::vector<std::string> argv = {IpBinary()};
  argv.insert(argv.end(), args.begin(), args.end());
  std::vector<char*> raw;
  for (auto& arg : argv) raw.push_back(arg.data());
  raw.push_back(nullptr);
  int pipe_fds[2];
  if (::pipe(pipe_fds) != 0) return Status::IoError(std::string("pipe: ") + std::strerror(errno));
  const pid_t pid = ::fork();
  if (pid < 0) return Status::IoError(std::string("fork: ") + std::strerror(errno));
  if (pid == 0) {
    ::close(pipe_fds[0]);
    ::dup2(pipe_fds[1], 2);
    const int null = ::open("/dev/null", O_RDWR);
    if (null >= 0) {
      ::dup2(null, 0);
      ::dup2(null, 1);
    }
    ::execv(raw[0], raw.data());
    _exit(127);
  }
  ::close(pipe_fds[1]);
  std::string errors;
  char buffer[512];
  for (ssize_t n; (n = ::read(pipe_fds[0], buffer, sizeof(buffer))) != 0;) {
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) break;
    errors.append(buffer, static_cast<size_t>(n));
  }
  ::close(pipe_fds[0]);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (WIFEXITED(status) && WEXITSTATUS(status) == 0) return Status::Ok();
  std::string command;
  for (const auto& arg : argv) command += (command.empty() ? "" : " ") + arg;
  return Status::IoError(command + " failed: " + errors);
}

std::string Hosts::RegistryDirectory() {
  if (const char* dir = std::getenv("PLACEDB_HOSTS_REGISTRY"); dir && *dir) return dir;
  return "/run/placedb-hosts";
}

Result<std::unique_ptr<Hosts>> Hosts::Create(HostsOptions options) {
  if (options.hosts < 1 || options.hosts > 250) {
    return Status::InvalidArgument("Hosts: between 1 and 250 hosts");
  }
  std::unique_ptr<Hosts> hosts(new Hosts());
  if (options.allow_netns && ::geteuid() == 0) {
    const Status status = hosts->SetupNetns(options.hosts);
    if (status.ok()) return hosts;
    // Only a namespace that could not be made at all means "no rights here": fall back. A
    // failure later is a real error.
    if (!hosts->hosts_.empty()) {
      hosts->TearDown();
      return status;
    }
    hosts->TearDown();
    std::fprintf(stderr, "hosts: network namespaces unavailable (%s); using loopback addresses\n",
                 status.ToString().c_str());
  }
  hosts->SetupLoopback(options.hosts);
  return hosts;
}

void Hosts::SetupLoopback(int count) {
  kind_ = Kind::kLoopback;
  hosts_.clear();
  for (int i = 0; i < count; ++i) {
    Host host;
    host.address = "127.0.0." + std::to_string(i + 2);
    hosts_.push_back(std::move(host));
  }
}

Status Hosts::SetupNetns(int count) {
  kind_ = Kind::kNetns;
  std::error_code error;
  fs::create_directories(RegistryDirectory(), error);
  // Claim a subnet: the registry file is created exclusively; one whose owner died is reclaimed
  // (its leftovers removed first); one that an interface already uses is skipped.
  const std::set<int> used = UsedTenSubnets();
  const std::string run = std::to_string(::getpid());
  for (int x = kFirstSubnet; x <= kLastSubnet && subnet_ < 0; ++x) {
    if (used.count(x)) continue;
    const std::string file = RegistryDirectory() + "/10." + std::to_string(x);
    int fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_EXCL, 0644);
    if (fd < 0 && errno == EEXIST) {
      std::ifstream in(file);
      pid_t owner = 0;
      in >> owner;
      if (owner <= 0 || ProcessAlive(owner)) continue;
      // A dead owner's leftovers: the same removal as cleanup_engines.sh.
      std::string bridge, netns;
      in >> bridge;
      while (in >> netns) {
        KillNamespaceProcesses(netns);
        (void)RunIp({"netns", "del", netns});
      }
      if (!bridge.empty()) {
        // Its veths' outer ends ("<bridge without the final b>v<i>"), then the bridge.
        const std::string veths = bridge.substr(0, bridge.size() - 1) + "v";
        for (const auto& link : fs::directory_iterator("/sys/class/net", error)) {
          const std::string name = link.path().filename().string();
          if (name.rfind(veths, 0) == 0) (void)RunIp({"link", "del", name});
        }
        (void)RunIp({"link", "del", bridge});
      }
      fs::remove(file, error);
      fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_EXCL, 0644);
    }
    if (fd < 0) continue;
    ::close(fd);
    subnet_ = x;
    registry_file_ = file;
  }
  if (subnet_ < 0) return Status::ResourceExhausted("Hosts: no free 10.x.0.0/24 subnet");

  // Interface names are at most 15 characters: "pdb<pid>b" / "pdb<pid>v<i>".
  bridge_ = "pdb" + run + "b";
  {
    std::ofstream registry(registry_file_);
    registry << ::getpid() << "\n" << bridge_ << "\n";
    for (int i = 0; i < count; ++i) registry << "pdb" << run << "h" << i << "\n";
    if (!registry) return Status::IoError("cannot write " + registry_file_);
  }
  const std::string prefix = "10." + std::to_string(subnet_) + ".0.";
  for (int i = 0; i < count; ++i) {
    Host host;
    host.netns = "pdb" + run + "h" + std::to_string(i);
    host.veth = "pdb" + run + "v" + std::to_string(i);
    host.address = prefix + std::to_string(i + 1);
    PLACEDB_RETURN_IF_ERROR(RunIp({"netns", "add", host.netns}));
    hosts_.push_back(host);
    if (i == 0) {
      PLACEDB_RETURN_IF_ERROR(RunIp({"link", "add", bridge_, "type", "bridge"}));
      PLACEDB_RETURN_IF_ERROR(RunIp({"addr", "add", prefix + "254/24", "dev", bridge_}));
      PLACEDB_RETURN_IF_ERROR(RunIp({"link", "set", bridge_, "up"}));
    }
    const std::string inner = host.veth + "i";
    PLACEDB_RETURN_IF_ERROR(
        RunIp({"link", "add", host.veth, "type", "veth", "peer", "name", inner}));
    PLACEDB_RETURN_IF_ERROR(RunIp({"link", "set", inner, "netns", host.netns}));
    PLACEDB_RETURN_IF_ERROR(RunIp({"-n", host.netns, "link", "set", inner, "name", "eth0"}));
    PLACEDB_RETURN_IF_ERROR(
        RunIp({"-n", host.netns, "addr", "add", host.address + "/24", "dev", "eth0"}));
    PLACEDB_RETURN_IF_ERROR(RunIp({"-n", host.netns, "link", "set", "eth0", "up"}));
    PLACEDB_RETURN_IF_ERROR(RunIp({"-n", host.netns, "link", "set", "lo", "up"}));
    PLACEDB_RETURN_IF_ERROR(RunIp({"link", "set", host.veth, "master", bridge_}));
    PLACEDB_RETURN_IF_ERROR(RunIp({"link", "set", host.veth, "up"}));
  }
  return Status::Ok();
}

void Hosts::TearDown() {
  for (size_t i = 0; i < hosts_.size(); ++i) (void)Kill(static_cast<int>(i));
  for (auto& host : hosts_) {
    // Deleting the namespace destroys its end of the veth pair, and with it the outer end.
    if (!host.netns.empty()) (void)RunIp({"netns", "del", host.netns});
    if (!host.veth.empty()) (void)RunIp({"link", "del", host.veth});
  }
  if (!bridge_.empty()) (void)RunIp({"link", "del", bridge_});
  if (!registry_file_.empty()) {
    std::error_code ignored;
    fs::remove(registry_file_, ignored);
  }
  hosts_.clear();
  bridge_.clear();
  registry_file_.clear();
  subnet_ = -1;
}

Hosts::~Hosts() {
  TearDown();
}

const std::string& Hosts::address(int host) const {
  return hosts_.at(host).address;
}
const std::string& Hosts::netns(int host) const {
  return hosts_.at(host).netns;
}

std::vector<std::string> Hosts::Namespaces() const {
  std::vector<std::string> names;
  if (kind_ != Kind::kNetns) return names;
  for (const auto& host : hosts_) names.push_back(host.netns);
  return names;
}

std::vector<std::string> Hosts::Addresses() const {
  std::vector<std::string> addresses;
  for (const auto& host : hosts_) addresses.push_back(host.address);
  return addresses;
}

void Hosts::Track(int host, pid_t process_group) {
  hosts_.at(host).tracked.push_back(process_group);
}

Status Hosts::StartProcess(int host, EngineProcess& process, std::vector<std::string> argv,
                           const std::string& log_path) {
  PLACEDB_RETURN_IF_ERROR(process.Start(std::move(argv), log_path, netns(host)));
  Track(host, process.pid());
  return Status::Ok();
}

Status Hosts::Kill(int index) {
  Host& host = hosts_.at(index);
  for (pid_t group : host.tracked) {
    ::kill(-group, SIGKILL);
    ::kill(group, SIGKILL);
  }
  host.tracked.clear();
  Status status;
  if (kind_ == Kind::kNetns) {
    // Link down first: nothing of the dying host reaches the others while it is being swept.
    if (host.up) status = RunIp({"link", "set", host.veth, "down"});
    KillNamespaceProcesses(host.netns);
  }
  host.up = false;
  return status;
}

Status Hosts::Start(int index) {
  Host& host = hosts_.at(index);
  if (kind_ == Kind::kNetns && !host.up) {
    PLACEDB_RETURN_IF_ERROR(RunIp({"link", "set", host.veth, "up"}));
  }
  host.up = true;
  return Status::Ok();
}

bool Hosts::up(int host) const {
  return hosts_.at(host).up;
}

std::vector<pid_t> Hosts::Processes(int host) const {
  if (kind_ != Kind::kNetns) return {};
  return ProcessesInNamespace(hosts_.at(host).netns);
}

Status Hosts::RunInside(int index, const std::function<void()>& fn) const {
  return RunInNetns(kind_ == Kind::kNetns ? hosts_.at(index).netns : "", fn);
}

Status RunInNetns(const std::string& netns, const std::function<void()>& fn) {
  Status status;
  std::thread thread([&] {
    if (!netns.empty()) {
      const int fd = ::open(("/run/netns/" + netns).c_str(), O_RDONLY | O_CLOEXEC);
      if (fd < 0 || ::setns(fd, CLONE_NEWNET) != 0) {
        status = Status::IoError("cannot join namespace " + netns + ": " + std::strerror(errno));
        if (fd >= 0) ::close(fd);
        return;
      }
      ::close(fd);
    }
    fn();
  });
  thread.join();
  return status;
}

}  // namespace placedb::cluster::testing
