// placedb-kill-soak: the service-level crash soak (docs/storage.md, "Kill soak and disk-full
// run"). Not a CI test: it runs for minutes. tools/kill_soak.sh builds and runs it.
//
// Kill mode (default): starts the real placedb-server on a loopback port with a fresh data
// directory, lets several agents ingest real frames (ORB features of the RTAB-Map corridor,
// computed here once) into one or two maps over the gRPC API, SIGKILLs the server at a random
// moment, restarts it and checks through the API that every place ever acknowledged is there
// with its content (agent, sequence, kept count; the features themselves for the places new
// since the last check). Some kills land while the server is still starting (opening the maps).
// Prints `kills`, `acknowledged_places`, `lost_places`, `places_checked` (and more) and exits 1
// on any loss.
//
// --disk-full: the data directory on a small tmpfs mounted here (root only). Agents ingest until
// the file system is full; the run checks that they see RESOURCE_EXHAUSTED per frame (their
// streams stay open), that reads answer while full, then remounts the tmpfs larger and checks
// that ingest resumes, then SIGKILLs the server and checks that nothing acknowledged was lost.
// Repeated for --rounds; observations are printed as `name value unit` lines.
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/mount.h>
#include <sys/socket.h>
#include <sys/statvfs.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <filesystem>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "client/connection.h"
#include "client/ingest_stream.h"
#include "core/base/thread_annotations.h"
#include "core/features/orb_features.h"
#include "proto/convert_features.h"
#include "proto/status.h"
#include "tools/shared_data.h"

namespace placedb::soak {
namespace {

namespace fs = std::filesystem;
namespace v1 = ::placedb::v1;
using client::Connection;
using Clock = std::chrono::steady_clock;

struct Options {
  std::string server;
  std::string vocabulary = PLACEDB_DEFAULT_VOCABULARY;
  std::string work_dir;
  int kills = 100;
  int agents = 3;
  int maps = 2;
  int min_run_ms = 200;
  int max_run_ms = 2500;
  int startup_kill_percent = 10;
  double fps = 25;  // per agent; 0 = as fast as the server answers
  uint32_t seed = 19;
  bool keep = false;
  bool disk_full = false;
  int tmpfs_mib = 128;
  int rounds = 2;
  int full_timeout_s = 300;
  int64_t disk_reserve_bytes = -1;  // storage.disk_reserve_bytes; -1 = the server's default
};

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

void Say(const std::string& line) {
  std::fprintf(stderr, "[soak] %s\n", line.c_str());
  std::fflush(stderr);
}

void Observe(const std::string& name, double value, const std::string& unit) {
  std::printf("%s %g %s\n", name.c_str(), value, unit.c_str());
  std::fflush(stdout);
}

// ---- frames ------------------------------------------------------------------------------------

// ORB features of the RTAB-Map corridor frames (the map's default ORB settings), as agents send
// them: the server then only transforms, searches and stores, so many places are in flight.
std::vector<v1::Features> LoadFrames(std::string* error) {
  std::vector<v1::Features> frames;
  OrbConfig config;  // the map defaults: 1000 features
  for (int i = 1; i <= 84; ++i) {
    cv::Mat image = cv::imread(data::RtabmapFramePath(i), cv::IMREAD_GRAYSCALE);
    if (image.empty()) {
      *error = "cannot read " + data::RtabmapFramePath(i) + " (../shared/data is required)";
      return {};
    }
    auto features = ExtractOrb(image, config);
    if (!features.ok()) {
      *error = features.status().ToString();
      return {};
    }
    wire::FeaturesToProto(*features, &frames.emplace_back());
  }
  return frames;
}

std::optional<Connection> Connect(const std::string& address, double timeout_s) {
  client::ConnectionOptions options;
  options.address = address;
  options.timeout_s = timeout_s;
  std::string error;  // only TLS options can fail
  return Connection::Open(options, &error);
}

// ---- the server process -------------------------------------------------------------------------

int UnusedLoopbackPort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof address;
  int port = 0;
  if (bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) == 0 &&
      getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) == 0) {
    port = ntohs(address.sin_port);
  }
  close(fd);
  return port;
}

class Server {
 public:
  // `metrics_port` 0: no metrics endpoint.
  Server(const Options& options, std::string data_dir, int port, int metrics_port = 0)
      : options_(options),
        data_dir_(std::move(data_dir)),
        port_(port),
        metrics_port_(metrics_port) {}
  ~Server() { Kill(); }

  std::string address() const { return "127.0.0.1:" + std::to_string(port_); }

  // Forks and execs the server (output appended to server.log in the work directory).
  bool Launch(std::string* error) {
    const std::string log = options_.work_dir + "/server.log";
    std::vector<std::string> args = {
        options_.server,
        "--listen",
        address(),
        "--data-dir",
        data_dir_,
        "--metrics-listen",
        metrics_port_ > 0 ? "127.0.0.1:" + std::to_string(metrics_port_) : "off",
        "--console-listen",
        "off",
        "--vocabulary",
        "default=" + options_.vocabulary,
        "--threads",
        "2",
        "--log-level",
        "warn",
        "--shutdown-deadline",
        "5"};
    if (options_.disk_reserve_bytes >= 0) {
      const std::string config = options_.work_dir + "/soak.yaml";
      std::FILE* file = std::fopen(config.c_str(), "w");
      if (!file) {
        *error = "cannot write " + config;
        return false;
      }
      std::fprintf(file, "storage:\n  disk_reserve_bytes: %lld\n",
                   static_cast<long long>(options_.disk_reserve_bytes));
      std::fclose(file);
      args.insert(args.end(), {"--config", config});
    }
    std::vector<char*> argv;
    for (auto& arg : args) argv.push_back(arg.data());
    argv.push_back(nullptr);
    const int log_fd = open(log.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
    if (log_fd < 0) {
      *error = "cannot open " + log;
      return false;
    }
    pid_ = fork();
    if (pid_ < 0) {
      close(log_fd);
      *error = std::string("fork: ") + std::strerror(errno);
      return false;
    }
    if (pid_ == 0) {
      // The working directory has no var/: only the vocabulary given here is loaded.
      if (chdir(options_.work_dir.c_str()) != 0) _exit(126);
      dup2(log_fd, STDOUT_FILENO);
      dup2(log_fd, STDERR_FILENO);
      execv(argv[0], argv.data());
      _exit(127);
    }
    close(log_fd);
    return true;
  }

  // Waits until the server answers health checks SERVING (it listens only once its maps are
  // open). False if it exits or takes longer than `timeout_s`.
  bool AwaitServing(double timeout_s, std::string* error) {
    const auto start = Clock::now();
    while (SecondsSince(start) < timeout_s) {
      int status = 0;
      if (pid_ > 0 && waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        *error = "the server exited during startup (status " + std::to_string(status) + "); see " +
                 options_.work_dir + "/server.log";
        return false;
      }
      auto connection = Connect(address(), 1);
      std::string serving;
      if (connection && client::CheckHealth(*connection, "", &serving).ok() &&
          serving == "SERVING") {
        return true;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    *error = "the server did not become SERVING within " + std::to_string(timeout_s) + " s";
    return false;
  }

  void Kill() { Signal(SIGKILL); }
  void Terminate() { Signal(SIGTERM); }
  bool running() const { return pid_ > 0; }

 private:
  void Signal(int signal) {
    if (pid_ <= 0) return;
    kill(pid_, signal);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
  }

  const Options& options_;
  const std::string data_dir_;
  const int port_;
  const int metrics_port_;
  pid_t pid_ = -1;
};

// The sum of the samples of `metric` whose labels contain `label` on the server's /metrics; -1
// when it cannot be read.
double ScrapeMetric(int port, const std::string& metric, const std::string& label) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = htons(uint16_t(port));
  std::string text;
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) == 0) {
    const std::string request = "GET /metrics HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n";
    if (write(fd, request.data(), request.size()) == ssize_t(request.size())) {
      char buffer[65536];
      ssize_t n;
      while ((n = read(fd, buffer, sizeof buffer)) > 0) text.append(buffer, size_t(n));
    }
  }
  close(fd);
  if (text.empty()) return -1;
  double sum = 0;
  size_t pos = 0;
  while ((pos = text.find("\n" + metric + "{", pos)) != std::string::npos) {
    const size_t end = text.find('\n', pos + 1);
    const std::string line = text.substr(pos + 1, end - pos - 1);
    pos = end;
    if (line.find(label) == std::string::npos) continue;
    sum += std::atof(line.substr(line.rfind(' ') + 1).c_str());
  }
  return sum;
}

// ---- what agents were told ------------------------------------------------------------------

struct Ack {
  std::string map;
  uint32_t id = 0;
  std::string agent;
  uint64_t sequence = 0;
  uint32_t kept = 0;
  bool features_checked = false;  // its features were compared once after a restart
};

class Ledger {
 public:
  void Acknowledge(Ack ack) {
    MutexLock lock(mutex_);
    ++stored_;
    acks_.push_back(std::move(ack));
  }
  void Refused(int code, const std::string& message) {
    MutexLock lock(mutex_);
    ++errors_[wire::GrpcCodeName(code)];
    if (first_error_.empty()) first_error_ = message;
  }
  void StreamEnded() {
    MutexLock lock(mutex_);
    ++streams_ended_;
  }
  // Only while no agent runs (the checker marks places whose features it compared).
  std::vector<Ack>& acks_while_stopped() NO_THREAD_SAFETY_ANALYSIS { return acks_; }
  std::vector<Ack> Snapshot() const {
    MutexLock lock(mutex_);
    return acks_;
  }
  size_t size() const {
    MutexLock lock(mutex_);
    return acks_.size();
  }
  uint64_t stored() const {
    MutexLock lock(mutex_);
    return stored_;
  }
  uint64_t errors(const std::string& code) const {
    MutexLock lock(mutex_);
    auto it = errors_.find(code);
    return it == errors_.end() ? 0 : it->second;
  }
  uint64_t all_errors() const {
    MutexLock lock(mutex_);
    uint64_t total = 0;
    for (const auto& [code, count] : errors_) total += count;
    return total;
  }
  std::map<std::string, uint64_t> error_counts() const {
    MutexLock lock(mutex_);
    return errors_;
  }
  std::string first_error() const {
    MutexLock lock(mutex_);
    return first_error_;
  }
  uint64_t streams_ended() const {
    MutexLock lock(mutex_);
    return streams_ended_;
  }
  void ResetErrors() {
    MutexLock lock(mutex_);
    errors_.clear();
    first_error_.clear();
    streams_ended_ = 0;
  }

 private:
  mutable Mutex mutex_;
  std::vector<Ack> acks_ GUARDED_BY(mutex_);
  uint64_t stored_ GUARDED_BY(mutex_) = 0;
  std::map<std::string, uint64_t> errors_ GUARDED_BY(mutex_);
  std::string first_error_ GUARDED_BY(mutex_);
  uint64_t streams_ended_ GUARDED_BY(mutex_) = 0;
};

// ---- agents ---------------------------------------------------------------------------------

struct Agent {
  std::string id;
  std::string map;
  uint64_t next_sequence = 0;  // carries on across restarts
  // Frames written and answered in the current run: the difference at a kill is what was in
  // flight.
  std::atomic<uint64_t> sent{0};
  std::atomic<uint64_t> answered{0};
  std::atomic<uint64_t> refused{0};  // frames answered with an error, in the current run
};

// Runs Ingest streams for `agent` until `stop`; a stream that ends (the server was killed, or
// anything else) is reopened after a short pause.
void RunAgent(const std::string& address, Agent* agent, const std::vector<v1::Features>& frames,
              double fps, Ledger* ledger, const std::atomic<bool>* stop) {
  auto connection = Connect(address, 10);
  v1::IngestHeader header;
  header.set_map(agent->map);
  const auto start = Clock::now();
  uint64_t paced = 0;
  while (!*stop) {
    const grpc::Status status = client::IngestStream::Run(
        *connection, header, /*window=*/4,
        [&](client::Outgoing* out) {
          if (fps > 0) {
            std::this_thread::sleep_until(
                start + std::chrono::microseconds(int64_t(double(paced++) * 1e6 / fps)));
          }
          if (*stop) return false;
          ++agent->sent;
          const uint64_t sequence = agent->next_sequence++;
          v1::Observation& observation = out->observation;
          observation.set_agent_id(agent->id);
          observation.set_sequence(sequence);
          observation.set_timestamp_ns(int64_t(sequence) * 100000000);
          *observation.mutable_features() = frames[sequence % frames.size()];
          out->tag = sequence;
          return true;
        },
        [&](const client::Answered& answered) {
          ++agent->answered;
          const v1::IngestResponse& response = answered.response;
          if (response.has_error()) {
            ++agent->refused;
            ledger->Refused(response.error().code(), response.error().message());
          } else if (response.stored()) {
            ledger->Acknowledge({.map = agent->map,
                                 .id = response.place_id(),
                                 .agent = agent->id,
                                 .sequence = response.sequence(),
                                 .kept = response.counts().kept()});
          }
        });
    if (*stop) break;
    if (!status.ok()) ledger->StreamEnded();
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
}

class Agents {
 public:
  Agents(std::deque<Agent>* agents, const std::vector<v1::Features>* frames, double fps,
         Ledger* ledger)
      : agents_(agents), frames_(frames), fps_(fps), ledger_(ledger) {}
  ~Agents() { Stop(); }
  void Start(const std::string& address) {
    stop_ = false;
    for (Agent& agent : *agents_) {
      // Here, before the threads start: the caller may read them at once.
      agent.sent = 0;
      agent.answered = 0;
      agent.refused = 0;
      threads_.emplace_back(RunAgent, address, &agent, std::cref(*frames_), fps_, ledger_, &stop_);
    }
  }
  void Stop() {
    stop_ = true;
    for (auto& thread : threads_) thread.join();
    threads_.clear();
  }

 private:
  std::deque<Agent>* agents_;
  const std::vector<v1::Features>* frames_;
  const double fps_;
  Ledger* ledger_;
  std::atomic<bool> stop_{false};
  std::vector<std::thread> threads_;
};

// ---- checks through the API ---------------------------------------------------------------------

struct CheckResult {
  uint64_t checked = 0;
  uint64_t lost = 0;        // NOT_FOUND
  uint64_t mismatched = 0;  // present with other content
  uint64_t failed = 0;      // the call failed otherwise
  std::string first_problem;
};

// Every acknowledged place: present, with the acknowledged agent, sequence and kept count; the
// features of those not yet compared (the places acknowledged since the last restart).
CheckResult CheckPlaces(const Connection& connection, std::vector<Ack>& acks) {
  CheckResult result;
  Mutex mutex;
  auto check_range = [&](size_t from, size_t step) {
    CheckResult local;
    for (size_t i = from; i < acks.size(); i += step) {
      Ack& ack = acks[i];
      v1::GetPlaceRequest request;
      request.set_map(ack.map);
      request.set_place_id(ack.id);
      request.set_include_features(!ack.features_checked);
      v1::Place place;
      grpc::Status status;
      for (int attempt = 0; attempt < 3; ++attempt) {
        auto context = connection.NewContext();
        status = connection.stub()->GetPlace(context.get(), request, &place);
        if (status.error_code() != grpc::StatusCode::UNAVAILABLE) break;
      }
      ++local.checked;
      std::string problem;
      if (status.error_code() == grpc::StatusCode::NOT_FOUND) {
        ++local.lost;
        problem = "lost";
      } else if (!status.ok()) {
        ++local.failed;
        problem = client::Describe(status);
      } else if (place.metadata().agent_id() != ack.agent ||
                 place.metadata().sequence() != ack.sequence || place.counts().kept() != ack.kept ||
                 (request.include_features() &&
                  (size_t(place.features().keypoints_size()) != ack.kept ||
                   place.features().descriptors().size() != size_t(ack.kept) * 32))) {
        ++local.mismatched;
        problem = "content differs: agent " + place.metadata().agent_id() + " sequence " +
                  std::to_string(place.metadata().sequence()) + " kept " +
                  std::to_string(place.counts().kept());
      } else {
        ack.features_checked = true;
      }
      if (!problem.empty() && local.first_problem.empty()) {
        local.first_problem = "map " + ack.map + " place " + std::to_string(ack.id) + " (" +
                              ack.agent + " #" + std::to_string(ack.sequence) + "): " + problem;
      }
    }
    MutexLock lock(mutex);
    result.checked += local.checked;
    result.lost += local.lost;
    result.mismatched += local.mismatched;
    result.failed += local.failed;
    if (result.first_problem.empty()) result.first_problem = local.first_problem;
  };
  std::thread second(check_range, 1, 2);
  check_range(0, 2);
  second.join();
  return result;
}

// Each map is listed, available and holds at least its acknowledged places.
std::string CheckMaps(const Connection& connection, const std::vector<std::string>& maps,
                      const std::vector<Ack>& acks) {
  std::map<std::string, uint64_t> acknowledged;
  for (const Ack& ack : acks) ++acknowledged[ack.map];
  for (const std::string& name : maps) {
    v1::GetMapRequest request;
    request.set_name(name);
    v1::MapDescription map;
    auto context = connection.NewContext();
    const grpc::Status status = connection.stub()->GetMap(context.get(), request, &map);
    if (!status.ok()) return "GetMap " + name + ": " + client::Describe(status);
    if (map.stats().places() < acknowledged[name]) {
      return "map " + name + " holds " + std::to_string(map.stats().places()) + " places, " +
             std::to_string(acknowledged[name]) + " were acknowledged";
    }
  }
  return "";
}

// Starts the server and creates the soak's maps in it. False (said) after an error.
bool StartWithMaps(Server& server, const std::vector<std::string>& maps) {
  std::string error;
  if (!server.Launch(&error) || !server.AwaitServing(120, &error)) {
    Say(error);
    return false;
  }
  auto connection = Connect(server.address(), 30);
  if (!connection) {
    Say("cannot connect to " + server.address());
    return false;
  }
  for (const std::string& name : maps) {
    v1::CreateMapRequest request;
    request.set_name(name);
    v1::MapDescription created;
    auto context = connection->NewContext();
    const grpc::Status status = connection->stub()->CreateMap(context.get(), request, &created);
    if (!status.ok()) {
      Say("CreateMap " + name + ": " + client::Describe(status));
      return false;
    }
  }
  return true;
}

std::deque<Agent> MakeAgents(const Options& options, const std::vector<std::string>& maps) {
  std::deque<Agent> agents;
  for (int i = 0; i < options.agents; ++i) {
    Agent& agent = agents.emplace_back();  // in place: the counters are atomics
    agent.id = "agent-" + std::to_string(i);
    agent.map = maps[size_t(i) % maps.size()];
  }
  return agents;
}

std::vector<std::string> MapNames(const Options& options) {
  std::vector<std::string> maps;
  for (int i = 0; i < std::max(options.maps, 1); ++i) maps.push_back("soak-" + std::to_string(i));
  return maps;
}

// ---- kill mode --------------------------------------------------------------------------------

int RunKills(const Options& options, const std::vector<v1::Features>& frames) {
  const auto started = Clock::now();
  const std::string data_dir = options.work_dir + "/data";
  const std::vector<std::string> maps = MapNames(options);
  Server server(options, data_dir, UnusedLoopbackPort());
  if (!StartWithMaps(server, maps)) return 2;
  std::string error;
  std::deque<Agent> agent_state = MakeAgents(options, maps);
  Ledger ledger;
  std::mt19937 rng(options.seed);
  int kills = 0, startup_kills = 0, kills_in_flight = 0;
  uint64_t in_flight_total = 0;
  CheckResult total;
  std::string first_problem;

  auto check = [&](const char* when) {
    auto connection = Connect(server.address(), 30);
    if (std::string maps_problem = CheckMaps(*connection, maps, ledger.acks_while_stopped());
        !maps_problem.empty()) {
      ++total.failed;
      if (first_problem.empty()) first_problem = std::string(when) + ": " + maps_problem;
    }
    const CheckResult result = CheckPlaces(*connection, ledger.acks_while_stopped());
    total.checked += result.checked;
    total.lost += result.lost;
    total.mismatched += result.mismatched;
    total.failed += result.failed;
    if (first_problem.empty() && !result.first_problem.empty()) {
      first_problem = std::string(when) + ": " + result.first_problem;
    }
  };

  while (kills < options.kills) {
    Agents agents(&agent_state, &frames, options.fps, &ledger);
    agents.Start(server.address());
    std::uniform_int_distribution<int> run_ms(options.min_run_ms, options.max_run_ms);
    std::this_thread::sleep_for(std::chrono::milliseconds(run_ms(rng)));
    server.Kill();
    ++kills;
    uint64_t in_flight = 0;
    for (const Agent& agent : agent_state) in_flight += agent.sent - agent.answered;
    in_flight_total += in_flight;
    if (in_flight > 0) ++kills_in_flight;
    agents.Stop();

    // Restart; now and then kill it again while it opens its maps (RocksDB recovery).
    if (!server.Launch(&error)) {
      Say(error);
      return 2;
    }
    if (kills < options.kills && int(rng() % 100) < options.startup_kill_percent) {
      std::this_thread::sleep_for(std::chrono::milliseconds(rng() % 400));
      server.Kill();
      ++kills;
      ++startup_kills;
      if (!server.Launch(&error)) {
        Say(error);
        return 2;
      }
    }
    if (!server.AwaitServing(120, &error)) {
      Say("after kill " + std::to_string(kills) + ": " + error);
      return 2;
    }
    check(("after kill " + std::to_string(kills)).c_str());
    if (kills % 10 == 0 || total.lost + total.mismatched + total.failed > 0) {
      Say("kills " + std::to_string(kills) + ", acknowledged " + std::to_string(ledger.size()) +
          ", lost " + std::to_string(total.lost) + ", checked " + std::to_string(total.checked) +
          ", " + std::to_string(int(SecondsSince(started))) + " s");
    }
  }
  server.Terminate();  // graceful: exit status is not checked, the data is
  if (!first_problem.empty()) Say("first problem: " + first_problem);

  std::printf("kills %d\n", kills);
  std::printf("kills_during_startup %d\n", startup_kills);
  std::printf("kills_with_frames_in_flight %d\n", kills_in_flight);
  std::printf("frames_in_flight_at_kills %llu\n", static_cast<unsigned long long>(in_flight_total));
  std::printf("acknowledged_places %zu\n", ledger.size());
  std::printf("lost_places %llu\n", static_cast<unsigned long long>(total.lost));
  std::printf("mismatched_places %llu\n", static_cast<unsigned long long>(total.mismatched));
  std::printf("failed_checks %llu\n", static_cast<unsigned long long>(total.failed));
  std::printf("places_checked %llu\n", static_cast<unsigned long long>(total.checked));
  std::printf("frame_errors %llu\n", static_cast<unsigned long long>(ledger.all_errors()));
  std::printf("duration_s %.0f\n", SecondsSince(started));
  for (const auto& [code, count] : ledger.error_counts()) {
    std::printf("frame_errors_%s %llu\n", code.c_str(), static_cast<unsigned long long>(count));
  }
  if (!ledger.first_error().empty()) Say("first frame error: " + ledger.first_error());
  const bool ok = total.lost == 0 && total.mismatched == 0 && total.failed == 0 &&
                  ledger.all_errors() == 0 && ledger.size() > 0;
  return ok ? 0 : 1;
}

// ---- disk-full mode ---------------------------------------------------------------------------

uint64_t UsedMiB(const std::string& path) {
  struct statvfs info {};
  if (statvfs(path.c_str(), &info) != 0) return 0;
  return (uint64_t(info.f_blocks - info.f_bfree) * info.f_frsize) >> 20;
}

bool MountTmpfs(const std::string& dir, uint64_t mib, bool remount, std::string* error) {
  const std::string size = "size=" + std::to_string(mib) + "m";
  if (mount("tmpfs", dir.c_str(), "tmpfs", remount ? MS_REMOUNT : 0, size.c_str()) != 0) {
    *error = std::string(remount ? "remounting" : "mounting") + " a tmpfs (" + size + ") on " +
             dir + ": " + std::strerror(errno);
    return false;
  }
  return true;
}

template <typename Predicate>
bool WaitFor(double timeout_s, Predicate done) {
  const auto start = Clock::now();
  while (!done()) {
    if (SecondsSince(start) > timeout_s) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return true;
}

// Reads while the disk is full: every acknowledged place, each map, the map list, a query.
void ReadWhileFull(const Connection& connection, const std::vector<std::string>& maps,
                   std::vector<Ack>& acks, const v1::Features& frame, const std::string& prefix) {
  const CheckResult places = CheckPlaces(connection, acks);
  Observe(prefix + "getplace_ok",
          double(places.checked - places.lost - places.mismatched - places.failed), "calls");
  Observe(prefix + "getplace_failed", double(places.lost + places.mismatched + places.failed),
          "calls");
  if (!places.first_problem.empty()) Say("reading while full: " + places.first_problem);
  int ok = 0, failed = 0;
  for (const std::string& name : maps) {
    v1::GetMapRequest request;
    request.set_name(name);
    v1::MapDescription map;
    auto context = connection.NewContext();
    (connection.stub()->GetMap(context.get(), request, &map).ok() ? ok : failed)++;
    v1::QueryRequest query;
    query.set_map(name);
    *query.mutable_observation()->mutable_features() = frame;
    v1::QueryResponse answer;
    auto query_context = connection.NewContext();
    const grpc::Status status = connection.stub()->Query(query_context.get(), query, &answer);
    (status.ok() && answer.valid() ? ok : failed)++;
  }
  v1::ListMapsResponse listed;
  auto context = connection.NewContext();
  (connection.stub()->ListMaps(context.get(), {}, &listed).ok() &&
           size_t(listed.maps_size()) == maps.size()
       ? ok
       : failed)++;
  Observe(prefix + "getmap_query_listmaps_ok", ok, "calls");
  Observe(prefix + "getmap_query_listmaps_failed", failed, "calls");
}

int RunDiskFull(const Options& options, const std::vector<v1::Features>& frames) {
  if (geteuid() != 0) {
    Say("--disk-full mounts a tmpfs: run it as root");
    return 2;
  }
  const auto started = Clock::now();
  const std::string mount_point = options.work_dir + "/tmpfs";
  fs::create_directories(mount_point);
  std::string error;
  if (!MountTmpfs(mount_point, uint64_t(options.tmpfs_mib), false, &error)) {
    Say(error);
    return 2;
  }
  struct Unmount {
    std::string dir;
    ~Unmount() { umount2(dir.c_str(), MNT_DETACH); }
  } unmount{mount_point};

  const std::vector<std::string> maps = MapNames(options);
  const int metrics_port = UnusedLoopbackPort();
  Server server(options, mount_point + "/data", UnusedLoopbackPort(), metrics_port);
  if (!StartWithMaps(server, maps)) return 2;
  std::deque<Agent> agent_state = MakeAgents(options, maps);
  Ledger ledger;
  uint64_t size_mib = uint64_t(options.tmpfs_mib);
  uint64_t lost_total = 0;
  bool ok = true;
  Observe("tmpfs_size", double(size_mib), "MiB");
  Observe("disk_reserve", double(options.disk_reserve_bytes), "bytes");
  for (int round = 1; round <= options.rounds; ++round) {
    const std::string p = "round" + std::to_string(round) + "_";
    if (round > 1) {
      // Shrink to what is used plus a little, so the disk fills again.
      size_mib = UsedMiB(mount_point) + 16;
      if (!MountTmpfs(mount_point, size_mib, true, &error)) {
        Say(error);
        return 2;
      }
      Observe(p + "tmpfs_size", double(size_mib), "MiB");
    }
    ledger.ResetErrors();
    const uint64_t stored_before = ledger.stored();
    const auto fill_start = Clock::now();
    Agents agents(&agent_state, &frames, options.fps, &ledger);
    agents.Start(server.address());
    // Full: every agent is refused frames (a map whose write-ahead log still has preallocated
    // room goes on storing a little longer than the others).
    if (!WaitFor(options.full_timeout_s, [&] {
          for (const Agent& agent : agent_state) {
            if (agent.refused < 3) return false;
          }
          return true;
        })) {
      Say("the disk did not fill within " + std::to_string(options.full_timeout_s) + " s");
      server.Kill();  // first: the agents' streams end with it
      return 1;
    }
    Observe(p + "time_to_full", SecondsSince(fill_start), "s");
    Observe(p + "acknowledged_until_full", double(ledger.stored() - stored_before), "places");
    Observe(p + "used_when_full", double(UsedMiB(mount_point)), "MiB");
    // Keep sending a while: every frame must be refused with RESOURCE_EXHAUSTED, on open streams.
    const uint64_t stored_when_full = ledger.stored();
    std::this_thread::sleep_for(std::chrono::seconds(2));
    const uint64_t exhausted = ledger.errors("RESOURCE_EXHAUSTED");
    const uint64_t other = ledger.all_errors() - exhausted;
    const std::string message = ledger.first_error();
    Observe(p + "frames_refused_resource_exhausted", double(exhausted), "frames");
    Observe(p + "frames_refused_other_codes", double(other), "frames");
    Observe(p + "stored_while_full", double(ledger.stored() - stored_when_full), "places");
    Observe(p + "streams_ended_while_full", double(ledger.streams_ended()), "streams");
    const bool names_map = message.find("disk full: map 'soak-") != std::string::npos;
    const bool has_path = message.find(options.work_dir) != std::string::npos ||
                          message.find("/tmp") != std::string::npos;
    Observe(p + "message_says_disk_full_and_names_map", names_map, "bool");
    Observe(p + "message_has_a_path", has_path, "bool");
    Say("round " + std::to_string(round) + " refusal: " + message);
    Observe(p + "metric_storage_errors_disk_full",
            ScrapeMetric(metrics_port, "placedb_storage_errors_total", "kind=\"disk_full\""),
            "errors");
    ok = ok && exhausted > 0 && other == 0 && names_map && !has_path && ledger.streams_ended() == 0;
    {
      auto connection = Connect(server.address(), 30);
      std::vector<Ack> acks = ledger.Snapshot();  // agents are still running
      ReadWhileFull(*connection, maps, acks, frames[1], p + "while_full_");
    }

    // Space returns.
    size_mib += 256;
    if (!MountTmpfs(mount_point, size_mib, true, &error)) {
      Say(error);
      server.Kill();
      return 2;
    }
    const auto freed = Clock::now();
    const uint64_t stored_at_free = ledger.stored();
    const uint64_t refused_at_free = ledger.all_errors();
    const bool resumed = WaitFor(60, [&] { return ledger.stored() > stored_at_free; });
    Observe(p + "resumed", resumed, "bool");
    Observe(p + "time_to_resume_after_space", SecondsSince(freed), "s");
    Observe(p + "frames_refused_after_space", double(ledger.all_errors() - refused_at_free),
            "frames");
    ok = ok && resumed;
    WaitFor(60, [&] { return ledger.stored() >= stored_at_free + 100; });
    Observe(p + "acknowledged_after_space", double(ledger.stored() - stored_at_free), "places");

    // Crash right after resuming; every acknowledged place must survive the restart.
    server.Kill();
    agents.Stop();
    if (!server.Launch(&error) || !server.AwaitServing(120, &error)) {
      Say(error);
      return 2;
    }
    auto connection = Connect(server.address(), 30);
    const CheckResult after = CheckPlaces(*connection, ledger.acks_while_stopped());
    const std::string maps_problem = CheckMaps(*connection, maps, ledger.acks_while_stopped());
    if (!after.first_problem.empty()) Say("after the kill: " + after.first_problem);
    if (!maps_problem.empty()) Say("after the kill: " + maps_problem);
    Observe(p + "acknowledged_total", double(ledger.size()), "places");
    Observe(p + "lost_after_kill", double(after.lost + after.mismatched + after.failed), "places");
    lost_total += after.lost + after.mismatched + after.failed;
    ok = ok && maps_problem.empty();
  }
  server.Terminate();
  Observe("acknowledged_places", double(ledger.size()), "places");
  Observe("lost_places", double(lost_total), "places");
  Observe("duration", SecondsSince(started), "s");
  return ok && lost_total == 0 ? 0 : 1;
}

}  // namespace
}  // namespace placedb::soak

int main(int argc, char** argv) {
  using placedb::soak::Options;
  Options options;
  CLI::App app{
      "placedb-kill-soak: SIGKILLs a real placedb-server under multi-agent ingest and "
      "checks every acknowledged place through the API (docs/storage.md)"};
  app.add_option("--server", options.server, "the placedb-server binary")->required();
  app.add_option("--vocabulary", options.vocabulary, "the default (ORB) vocabulary file");
  app.add_option("--work-dir", options.work_dir,
                 "where the data directory and server.log go (default: a new temp directory)");
  app.add_option("--kills", options.kills, "SIGKILLs of the server");
  app.add_option("--agents", options.agents, "concurrent ingest streams (one agent each)");
  app.add_option("--maps", options.maps, "maps the agents share");
  app.add_option("--min-run-ms", options.min_run_ms, "shortest ingest before a kill");
  app.add_option("--max-run-ms", options.max_run_ms, "longest ingest before a kill");
  app.add_option("--startup-kill-percent", options.startup_kill_percent,
                 "restarts killed again while the server opens its maps");
  app.add_option("--seed", options.seed, "random seed of the kill moments");
  app.add_option("--fps", options.fps, "frames per second per agent (0 = unpaced)");
  app.add_flag("--keep", options.keep, "keep the work directory");
  app.add_flag("--disk-full", options.disk_full,
               "the disk-full run on a tmpfs (root) instead of the kill soak");
  app.add_option("--tmpfs-mib", options.tmpfs_mib, "--disk-full: the tmpfs's first size");
  app.add_option("--rounds", options.rounds, "--disk-full: fill / free / kill rounds");
  app.add_option("--full-timeout-s", options.full_timeout_s,
                 "--disk-full: longest wait for a full disk");
  app.add_option("--disk-reserve-bytes", options.disk_reserve_bytes,
                 "the server's storage.disk_reserve_bytes (0: RocksDB itself runs out of space)");
  CLI11_PARSE(app, argc, argv);
  if (options.agents < 1 || options.kills < 1 || options.min_run_ms < 0 ||
      options.max_run_ms < options.min_run_ms) {
    std::fprintf(stderr, "placedb-kill-soak: bad --agents / --kills / --*-run-ms\n");
    return 2;
  }
  options.server = std::filesystem::absolute(options.server).string();
  options.vocabulary = std::filesystem::absolute(options.vocabulary).string();
  const bool made_work_dir = options.work_dir.empty();
  if (made_work_dir) {
    char pattern[] = "/tmp/placedb-soak-XXXXXX";
    if (!mkdtemp(pattern)) {
      std::perror("mkdtemp");
      return 2;
    }
    options.work_dir = pattern;
  }
  std::filesystem::create_directories(options.work_dir);
  options.work_dir = std::filesystem::absolute(options.work_dir).string();
  placedb::soak::Say("work directory " + options.work_dir);

  std::string error;
  const auto frames = placedb::soak::LoadFrames(&error);
  if (frames.empty()) {
    std::fprintf(stderr, "placedb-kill-soak: %s\n", error.c_str());
    return 2;
  }
  const int status = options.disk_full ? placedb::soak::RunDiskFull(options, frames)
                                       : placedb::soak::RunKills(options, frames);
  if (made_work_dir && !options.keep && status == 0) {
    std::error_code ec;
    std::filesystem::remove_all(options.work_dir, ec);
  }
  return status;
}
