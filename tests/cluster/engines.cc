#include "tests/cluster/engines.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sched.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <thread>

#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "tests/cluster/hosts.h"

namespace placedb::cluster::testing {
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

namespace {

// An executable: `env_name` when set, else the first of `candidates` that exists.
std::string FindBinary(const char* env_name, std::vector<std::string> candidates) {
  if (const char* from_env = std::getenv(env_name); from_env && *from_env) return from_env;
  for (const auto& candidate : candidates) {
    if (::access(candidate.c_str(), X_OK) == 0) return candidate;
  }
  return candidates.front();
}

std::string NatsServerBinary() {
  return FindBinary("PLACEDB_NATS_SERVER", {"/usr/sbin/nats-server", "/usr/bin/nats-server"});
}
std::string EtcdBinary() {
  return FindBinary("PLACEDB_ETCD", {"/usr/bin/etcd", "/usr/sbin/etcd"});
}

}  // namespace

Result<std::vector<int>> FreePorts(const std::string& host, int count) {
  // The kernel's ephemeral range: ports below its start are never handed out as source ports.
  int ephemeral_low = 32768;
  std::ifstream("/proc/sys/net/ipv4/ip_local_port_range") >> ephemeral_low;
  const int low = 10000;
  const int high = std::max(low + 1000, std::min(ephemeral_low, 65536));
  // A random start, so that tests running side by side rarely try the same ports.
  std::random_device seed;
  int candidate = low + int(seed() % unsigned(high - low));
  std::vector<int> sockets;
  std::vector<int> ports;
  Status status;
  for (int tried = 0; int(ports.size()) < count && status.ok(); ++tried, ++candidate) {
    if (tried == high - low) {
      status = Status::IoError("no free port on " + host + " in " + std::to_string(low) + ".." +
                               std::to_string(high - 1));
      break;
    }
    if (candidate >= high) candidate = low;
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(uint16_t(candidate));
    if (fd < 0 || ::inet_pton(AF_INET, host.c_str(), &address.sin_addr) != 1) {
      status = Status::IoError("no socket for " + host + ": " + std::strerror(errno));
      if (fd >= 0) ::close(fd);
      break;
    }
    // No SO_REUSEADDR: a port still in TIME_WAIT is passed over too.
    if (::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0) {
      ::close(fd);
      continue;
    }
    sockets.push_back(fd);
    ports.push_back(candidate);
  }
  for (int fd : sockets) ::close(fd);
  if (!status.ok()) return status;
  return ports;
}

namespace {

// True once `host:port` accepts a TCP connection.
bool Accepts(const std::string& host, int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return false;
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  const bool ok = ::inet_pton(AF_INET, host.c_str(), &address.sin_addr) == 1 &&
                  ::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0;
  ::close(fd);
  return ok;
}

// The body of an HTTP/1.0 GET of `path` on host:port (the nats-server monitoring endpoint).
Result<std::string> HttpGet(const std::string& host, int port, const std::string& path) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return Status::IoError(std::string("socket: ") + std::strerror(errno));
  timeval timeout{2, 0};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof(timeout));
  ::setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof(timeout));
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  if (::inet_pton(AF_INET, host.c_str(), &address.sin_addr) != 1 ||
      ::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0) {
    ::close(fd);
    return Status::IoError("connect " + host + ":" + std::to_string(port) + ": " +
                           std::strerror(errno));
  }
  const std::string request = "GET " + path + " HTTP/1.0\r\nHost: " + host + "\r\n\r\n";
  if (::send(fd, request.data(), request.size(), MSG_NOSIGNAL) !=
      static_cast<ssize_t>(request.size())) {
    ::close(fd);
    return Status::IoError("send to " + host + ": " + std::strerror(errno));
  }
  std::string response;
  char buffer[4096];
  for (ssize_t n; (n = ::recv(fd, buffer, sizeof(buffer), 0)) > 0;) response.append(buffer, n);
  ::close(fd);
  const size_t body = response.find("\r\n\r\n");
  if (response.rfind("HTTP/1.", 0) != 0 || body == std::string::npos ||
      response.find(" 200 ") > body) {
    return Status::IoError("GET " + path + " on " + host + ": bad response");
  }
  return response.substr(body + 4);
}

std::string Tail(const std::string& path, size_t bytes = 1500) {
  std::ifstream in(path, std::ios::binary);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return text.size() > bytes ? text.substr(text.size() - bytes) : text;
}

// "<letter><number>" (engine names); appends rather than `Named('e', i)`, which GCC 12
// flags with a false -Wrestrict at -O3.
std::string Named(char letter, int number) {
  std::string name(1, letter);
  name += std::to_string(number);
  return name;
}

// nats-server's `tls { }` block with the files (an empty string without them), indented by
// `indent`: client connections (verify: a client certificate is required) or, inside
// `cluster { }`, routes. A handshake may take a while on a loaded machine (default 0.5 s).
std::string TlsBlock(const EnginesOptions::Tls& tls, const std::string& indent) {
  if (tls.ca_file.empty()) return "";
  return indent + "tls {\n" + indent + "  cert_file: \"" + tls.cert_file + "\"\n" + indent +
         "  key_file: \"" + tls.key_file + "\"\n" + indent + "  ca_file: \"" + tls.ca_file +
         "\"\n" + indent + "  verify: true\n" + indent + "  timeout: 5\n" + indent + "}\n";
}

void SleepMs(int ms) {
  std::this_thread::sleep_for(std::chrono::milliseconds(ms));
}

}  // namespace

// ---- EngineProcess -----------------------------------------------------------------------------

EngineProcess::~EngineProcess() {
  Kill();
}

Status EngineProcess::Start(std::vector<std::string> argv, const std::string& log_path,
                            const std::string& netns) {
  if (running()) return Status::FailedPrecondition("engine already running: " + argv_[0]);
  const std::string netns_path = netns.empty() ? "" : "/run/netns/" + netns;
  argv_ = std::move(argv);
  std::vector<char*> args;
  for (auto& arg : argv_) args.push_back(arg.data());
  args.push_back(nullptr);
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid < 0) return Status::IoError(std::string("fork: ") + std::strerror(errno));
  if (pid == 0) {
    ::setpgid(0, 0);
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) _exit(1);  // the test died before prctl
    if (!netns_path.empty()) {
      const int ns = ::open(netns_path.c_str(), O_RDONLY);
      if (ns < 0 || ::setns(ns, CLONE_NEWNET) != 0) _exit(126);
      ::close(ns);
    }
    const int log = ::open(log_path.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
    const int null = ::open("/dev/null", O_RDONLY);
    if (log >= 0) {
      ::dup2(log, 1);
      ::dup2(log, 2);
    }
    if (null >= 0) ::dup2(null, 0);
    ::execv(args[0], args.data());
    _exit(127);
  }
  ::setpgid(pid, pid);  // also here: no window where a kill of the group misses the child
  pid_ = pid;
  fs::create_directories(Engines::PidDirectory());
  // Line 1: the binary (the cleanup kills the pid only while it still runs it); line 2: the
  // engines' directory (removed by the cleanup when a crash left it).
  std::ofstream(Engines::PidDirectory() + "/" + std::to_string(pid))
      << argv_[0] << "\n"
      << fs::path(log_path).parent_path().string() << "\n";
  return Status::Ok();
}

bool EngineProcess::running() const {
  if (pid_ <= 0) return false;
  int status = 0;
  if (::waitpid(pid_, &status, WNOHANG) != pid_) return true;
  std::error_code ignored;
  fs::remove(Engines::PidDirectory() + "/" + std::to_string(pid_), ignored);
  pid_ = -1;
  return false;
}

void EngineProcess::Kill() {
  if (pid_ <= 0) return;
  ::kill(-pid_, SIGKILL);
  ::kill(pid_, SIGKILL);
  int status = 0;
  while (::waitpid(pid_, &status, 0) < 0 && errno == EINTR) {
  }
  std::error_code ignored;
  fs::remove(Engines::PidDirectory() + "/" + std::to_string(pid_), ignored);
  pid_ = -1;
}

// ---- Engines -----------------------------------------------------------------------------------

std::string Engines::PidDirectory() {
  if (const char* dir = std::getenv("PLACEDB_CLUSTER_PID_DIR"); dir && *dir) return dir;
#ifdef PLACEDB_CLUSTER_PID_DIR
  return PLACEDB_CLUSTER_PID_DIR;  // the build tree's, where ctest's cleanup looks
#endif
  return (fs::temp_directory_path() / ("placedb-cluster-pids-" + std::to_string(::getuid())))
      .string();
}

Result<std::unique_ptr<Engines>> Engines::Start(EnginesOptions options) {
  if (options.nodes < 1) return Status::InvalidArgument("Engines: at least one node");
  if (options.hosts.empty()) {
    // PLACEDB_ENGINES_HOSTS="127.0.0.2,127.0.0.3,127.0.0.4": one address per node, for runs
    // that check nothing depends on the nodes sharing one.
    if (const char* hosts = std::getenv("PLACEDB_ENGINES_HOSTS"); hosts && *hosts) {
      std::string list = hosts;
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = std::min(list.find(',', start), list.size());
        options.hosts.push_back(list.substr(start, comma - start));
        start = comma + 1;
      }
    } else {
      options.hosts.assign(options.nodes, "127.0.0.1");
    }
  }
  if (static_cast<int>(options.hosts.size()) != options.nodes) {
    return Status::InvalidArgument("Engines: one host per node");
  }
  if (!options.netns.empty() && static_cast<int>(options.netns.size()) != options.nodes) {
    return Status::InvalidArgument("Engines: one network namespace per node, or none");
  }
  // Free ports are picked before the engines bind them, so a process started meanwhile (a test
  // running beside this one) can take one: the engine then fails to listen. Start over on fresh
  // ports, a few times, before reporting it.
  Status failed = Status::Ok();
  for (int attempt = 1; attempt <= 3; ++attempt) {
    std::unique_ptr<Engines> engines(new Engines(options));
    failed = engines->Setup();
    if (failed.ok()) return engines;
    std::fprintf(stderr, "Engines: start attempt %d failed: %s\n", attempt,
                 failed.ToString().c_str());
  }  // each failed attempt's destructor killed its engines and removed its directory
  return failed;
}

Status Engines::Setup() {
  std::string pattern = (fs::temp_directory_path() / "placedb-engines-XXXXXX").string();
  if (!::mkdtemp(pattern.data())) {
    return Status::IoError("mkdtemp " + pattern + ": " + std::strerror(errno));
  }
  directory_ = pattern;
  if (!options_.tls.ca_file.empty()) {
    auto tls = LoadInternalTls({.cert_file = options_.tls.cert_file,
                                .key_file = options_.tls.key_file,
                                .client_ca_file = options_.tls.ca_file});
    if (!tls.ok()) return tls.status().WithContext("Engines");
    client_tls_ = std::move(tls).value();
  }
  for (int i = 0; i < options_.nodes; ++i) {
    auto node = std::make_unique<Node>();
    node->host = options_.hosts[i];
    if (!options_.netns.empty()) node->netns = options_.netns.at(i);
    // Ports are picked where the engines bind them: inside the node's namespace.
    Result<std::vector<int>> ports = Status::Internal("no ports picked");
    PLACEDB_RETURN_IF_ERROR(RunInNetns(node->netns, [&] { ports = FreePorts(node->host, 5); }));
    if (!ports.ok()) return ports.status();
    node->nats_port = (*ports)[0];
    node->nats_cluster_port = (*ports)[1];
    node->etcd_client_port = (*ports)[2];
    node->etcd_peer_port = (*ports)[3];
    node->nats_http_port = (*ports)[4];
    nodes_.push_back(std::move(node));
  }
  // Every engine first, then wait: the members need each other to become ready.
  for (int i = 0; i < nodes(); ++i) {
    if (options_.nats) PLACEDB_RETURN_IF_ERROR(StartNats(i));
    if (options_.etcd) PLACEDB_RETURN_IF_ERROR(StartEtcd(i));
  }
  const auto deadline = Clock::now() + options_.ready_timeout;
  for (int i = 0; i < nodes(); ++i) {
    if (options_.nats) PLACEDB_RETURN_IF_ERROR(WaitNatsReady(i, deadline));
    if (options_.etcd) PLACEDB_RETURN_IF_ERROR(WaitEtcdReady(i, deadline));
  }
  if (options_.nats) PLACEDB_RETURN_IF_ERROR(WaitStreamsPlaceable(deadline));
  return Status::Ok();
}

// Each node answering is not enough: until the meta leader has heard from every peer, a stream
// with a replica on each is refused ("insufficient resources"; seen under load right after the
// start). A probe stream made and deleted again proves placement works.
Status Engines::WaitStreamsPlaceable(Clock::time_point deadline) const {
  JetStreamOptions options;
  options.servers = NatsUrls();
  options.request_timeout = std::chrono::milliseconds(2000);
  options.tls = client_tls_;
  auto js = JetStream::Connect(options);
  if (!js.ok()) return js.status();
  StreamConfig probe;
  probe.name = "PLACEDB_HARNESS_PLACEMENT_PROBE";
  probe.subjects = {"placedb.harness.placement-probe"};
  probe.replicas = nodes();
  Status last;
  while (Clock::now() < deadline) {
    last = (*js)->EnsureStream(probe);
    if (last.ok()) return (*js)->DeleteStream(probe.name);
    SleepMs(200);
  }
  return Status::IoError("JetStream cannot place a stream with " + std::to_string(nodes()) +
                         " replicas: " + last.ToString());
}

Engines::~Engines() {
  for (auto& node : nodes_) {
    node->nats.Kill();
    node->etcd.Kill();
  }
  if (!directory_.empty() && !std::getenv("PLACEDB_KEEP_ENGINES_DIR")) {
    std::error_code ignored;
    fs::remove_all(directory_, ignored);
  }
}

const std::string& Engines::host(int node) const {
  return nodes_.at(node)->host;
}

std::string Engines::NatsUrl(int node) const {
  return "nats://" + host(node) + ":" + std::to_string(nodes_.at(node)->nats_port);
}

std::vector<std::string> Engines::NatsUrls() const {
  std::vector<std::string> urls;
  for (int i = 0; i < nodes(); ++i) urls.push_back(NatsUrl(i));
  return urls;
}

std::string Engines::NatsServerName(int node) const {
  return Named('n', node);
}

int Engines::NodeOfServerName(const std::string& server_name) const {
  for (int i = 0; i < nodes(); ++i) {
    if (NatsServerName(i) == server_name) return i;
  }
  return -1;
}

std::string Engines::EtcdEndpoint(int node) const {
  return host(node) + ":" + std::to_string(nodes_.at(node)->etcd_client_port);
}

std::vector<std::string> Engines::EtcdEndpoints() const {
  std::vector<std::string> endpoints;
  for (int i = 0; i < nodes(); ++i) endpoints.push_back(EtcdEndpoint(i));
  return endpoints;
}

Status Engines::StartNats(int index) {
  Node& node = *nodes_.at(index);
  const std::string name = NatsServerName(index);
  const std::string config_path = directory_ + "/" + name + ".conf";
  {
    std::ofstream config(config_path);
    config << "server_name: " << name << "\n"
           << "listen: \"" << node.host << ":" << node.nats_port << "\"\n"
           << "http: \"" << node.host << ":" << node.nats_http_port << "\"\n"
           << TlsBlock(options_.tls, "") << "jetstream {\n"
           << "  store_dir: \"" << directory_ << "/" << name << "\"\n"
           << "  max_memory_store: 64MB\n"
           << "  max_file_store: 4GB\n"
           << "}\n"
           << "cluster {\n"
           << "  name: placedb\n"
           << "  listen: \"" << node.host << ":" << node.nats_cluster_port << "\"\n"
           << TlsBlock(options_.tls, "  ") << "  routes: [\n";
    for (const auto& other : nodes_) {
      config << "    \"nats-route://" << other->host << ":" << other->nats_cluster_port << "\"\n";
    }
    config << "  ]\n}\n";
    if (!config) return Status::IoError("cannot write " + config_path);
  }
  return node.nats.Start({NatsServerBinary(), "-c", config_path}, directory_ + "/" + name + ".log",
                         node.netns);
}

// A restart finds its data dir and ignores the --initial-* flags: the same command line serves.
Status Engines::StartEtcd(int index) {
  Node& node = *nodes_.at(index);
  const std::string name = Named('e', index);
  const bool tls = !options_.tls.ca_file.empty();
  const std::string scheme = tls ? "https://" : "http://";
  const std::string client_url = scheme + EtcdEndpoint(index);
  const std::string peer_url = scheme + node.host + ":" + std::to_string(node.etcd_peer_port);
  std::string initial_cluster;
  for (int i = 0; i < nodes(); ++i) {
    if (!initial_cluster.empty()) initial_cluster += ",";
    initial_cluster +=
        Named('e', i) + "=" + scheme + host(i) + ":" + std::to_string(nodes_[i]->etcd_peer_port);
  }
  std::vector<std::string> argv = {
      EtcdBinary(), "--name", name, "--data-dir", directory_ + "/" + name, "--listen-client-urls",
      client_url, "--advertise-client-urls", client_url, "--listen-peer-urls", peer_url,
      "--initial-advertise-peer-urls", peer_url, "--initial-cluster", initial_cluster,
      "--initial-cluster-state", "new", "--initial-cluster-token", "placedb-engines",
      // etcd's defaults, spelled out: lease TTLs below 1.5 x the election timeout are raised.
      "--heartbeat-interval", "100", "--election-timeout", "1000", "--logger", "zap", "--log-level",
      "warn"};
  if (tls) {
    const EnginesOptions::Tls& t = options_.tls;
    argv.insert(argv.end(), {"--cert-file", t.cert_file, "--key-file", t.key_file,
                             "--trusted-ca-file", t.ca_file, "--client-cert-auth",
                             "--peer-cert-file", t.cert_file, "--peer-key-file", t.key_file,
                             "--peer-trusted-ca-file", t.ca_file, "--peer-client-cert-auth"});
  }
  return node.etcd.Start(std::move(argv), directory_ + "/" + name + ".log", node.netns);
}

Status Engines::WaitNatsReady(int index, Clock::time_point deadline) const {
  const std::string log = directory_ + "/" + NatsServerName(index) + ".log";
  Status last;
  while (Clock::now() < deadline) {
    if (!nodes_.at(index)->nats.running()) break;
    JetStreamOptions options;
    options.servers = {NatsUrl(index)};
    options.tls = client_tls_;
    // A TLS handshake on a loaded machine takes longer than a plain connect.
    options.connect_timeout = std::chrono::milliseconds(client_tls_.enabled() ? 2000 : 500);
    options.request_timeout = std::chrono::milliseconds(1000);
    auto js = JetStream::Connect(options);
    if (js.ok()) {
      // Stream info of a stream that does not exist: NOT_FOUND comes from the JetStream meta
      // leader, so it proves one is elected and this node reaches it.
      auto info = (*js)->GetStreamInfo("PLACEDB_HARNESS_READY_PROBE");
      if (info.status().code() == StatusCode::kNotFound) return Status::Ok();
      last = info.status();
    } else {
      last = js.status();
    }
    SleepMs(200);
  }
  return Status::IoError("nats-server " + NatsServerName(index) + " not ready: " + last.ToString() +
                         "\n--- " + log + " (tail) ---\n" + Tail(log));
}

Status Engines::WaitEtcdReady(int index, Clock::time_point deadline) const {
  const std::string log = directory_ + "/" + Named('e', index) + ".log";
  // etcd listens for clients only once it has joined the cluster; a gRPC channel created before
  // would sit in reconnect backoff: wait for the port first.
  while (Clock::now() < deadline && nodes_.at(index)->etcd.running() &&
         !Accepts(host(index), nodes_.at(index)->etcd_client_port)) {
    SleepMs(50);
  }
  EtcdOptions options;
  options.endpoints = {EtcdEndpoint(index)};
  options.tls = client_tls_;
  options.call_timeout = std::chrono::milliseconds(1000);
  options.attempt_timeout = std::chrono::milliseconds(1000);
  auto client = EtcdClient::Create(options);
  if (!client.ok()) return client.status();
  Status last;
  while (Clock::now() < deadline) {
    if (!nodes_.at(index)->etcd.running()) break;
    auto got = (*client)->Get("/placedb-harness/ready");
    if (got.ok()) return Status::Ok();
    last = got.status();
    SleepMs(200);
  }
  return Status::IoError("etcd member " + Named('e', index) + " not ready: " + last.ToString() +
                         "\n--- " + log + " (tail) ---\n" + Tail(log));
}

void Engines::KillNats(int node) {
  nodes_.at(node)->nats.Kill();
}
void Engines::KillEtcd(int node) {
  nodes_.at(node)->etcd.Kill();
}
bool Engines::NatsRunning(int node) const {
  return nodes_.at(node)->nats.running();
}
bool Engines::EtcdRunning(int node) const {
  return nodes_.at(node)->etcd.running();
}

void Engines::KillNode(int node) {
  KillNats(node);
  KillEtcd(node);
}

Status Engines::RestartNode(int node) {
  // Both first: a restarted etcd member may need the others' answers, nats-server needs none.
  if (options_.nats) PLACEDB_RETURN_IF_ERROR(StartNats(node));
  if (options_.etcd) PLACEDB_RETURN_IF_ERROR(StartEtcd(node));
  const auto deadline = Clock::now() + options_.ready_timeout;
  if (options_.nats) PLACEDB_RETURN_IF_ERROR(WaitNatsReady(node, deadline));
  if (options_.etcd) PLACEDB_RETURN_IF_ERROR(WaitEtcdReady(node, deadline));
  return Status::Ok();
}

std::string Engines::NatsMonitor(int node) const {
  return host(node) + ":" + std::to_string(nodes_.at(node)->nats_http_port);
}

Result<int> Engines::MetaLeader(std::chrono::milliseconds timeout) const {
  const auto deadline = Clock::now() + timeout;
  std::string last = "no nats-server is running";
  while (Clock::now() < deadline) {
    for (int i = 0; i < nodes(); ++i) {
      if (!NatsRunning(i)) continue;
      auto body = HttpGet(host(i), nodes_[i]->nats_http_port, "/jsz");
      if (!body.ok()) {
        last = body.status().ToString();
        continue;
      }
      // {"meta_cluster": {"name": ..., "leader": "n1", ...}}: read the leader's name without a
      // JSON library (the harness links none); empty while an election runs.
      const size_t meta = body->find("\"meta_cluster\"");
      const size_t key = meta == std::string::npos ? meta : body->find("\"leader\"", meta);
      const size_t open = key == std::string::npos ? key : body->find('"', body->find(':', key));
      const size_t close = open == std::string::npos ? open : body->find('"', open + 1);
      if (close == std::string::npos) {
        last = "no meta leader in /jsz of " + NatsServerName(i);
        continue;
      }
      const int leader = NodeOfServerName(body->substr(open + 1, close - open - 1));
      if (leader >= 0 && NatsRunning(leader)) return leader;
      last = "meta leader '" + body->substr(open + 1, close - open - 1) + "' is not a live node";
    }
    SleepMs(200);
  }
  return Status::IoError("no JetStream meta leader within " + std::to_string(timeout.count()) +
                         " ms: " + last);
}

Status Engines::RestartNats(int node) {
  PLACEDB_RETURN_IF_ERROR(StartNats(node));
  return WaitNatsReady(node, Clock::now() + options_.ready_timeout);
}

Status Engines::RestartEtcd(int node) {
  PLACEDB_RETURN_IF_ERROR(StartEtcd(node));
  return WaitEtcdReady(node, Clock::now() + options_.ready_timeout);
}

Result<int> Engines::StreamLeader(const std::string& stream,
                                  std::chrono::milliseconds timeout) const {
  JetStreamOptions options;
  for (int i = 0; i < nodes(); ++i) {
    if (NatsRunning(i)) options.servers.push_back(NatsUrl(i));
  }
  if (options.servers.empty()) return Status::FailedPrecondition("no nats-server is running");
  options.tls = client_tls_;
  options.request_timeout = std::chrono::milliseconds(1000);
  auto js = JetStream::Connect(options);
  if (!js.ok()) return js.status();
  const auto deadline = Clock::now() + timeout;
  Status last;
  while (Clock::now() < deadline) {
    auto info = (*js)->GetStreamInfo(stream);
    if (info.ok() && !info->leader.empty()) {
      const int node = NodeOfServerName(info->leader);
      if (node >= 0) return node;
      return Status::Internal("stream leader '" + info->leader + "' is no node of the harness");
    }
    last = info.ok() ? Status::IoError("no leader elected") : info.status();
    SleepMs(100);
  }
  return Status::IoError("stream " + stream + ": no leader within " +
                         std::to_string(timeout.count()) + " ms: " + last.ToString());
}

}  // namespace placedb::cluster::testing
