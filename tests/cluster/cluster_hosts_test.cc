// The issue's CI scenario (issue 18) with real processes on separate hosts: 3 hosts (network
// namespaces as root, loopback addresses otherwise; tests/cluster/hosts.h), each running
// nats-server, etcd, a `placedb-server --role shard` and a `placedb-server --role worker`. 2 maps,
// 4 agents ingesting precomputed feature frames through the workers, queries through a worker all
// along. Mid-ingest the nats-server leading m1's stream, a shard process holding a replica of m1
// and a worker process that agents are connected to are SIGKILLed; agents whose stream broke
// reconnect to another worker and resend every unacknowledged frame (same sequence: the message
// id de-duplicates). Afterwards, once the map's two live replicas (the killed one replaced) have
// applied the stream, the shards stop and their data directories are opened here: every
// acknowledged place is on both replicas, the replicas are identical, no frame is stored twice,
// and both scrub clean.
//
// Run twice (ClusterHostsTest/<name>/Plaintext and /InternalTls): the second with TLS and client
// certificates on every hop (issue 35: cluster.internal_tls; nats-server and etcd with TLS on
// clients, routes and peers, and the workers' public API with mutual TLS from the same files).
//
// Figures are printed as `name value unit`, never asserted; the bounded waits and the watchdog
// only turn a hang into a failure.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/files.h"
#include "core/storage/codec.h"
#include "core/storage/map_store.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/placement.h"
#include "tests/cluster/cluster_frames.h"
#include "tests/cluster/engines.h"
#include "tests/cluster/hosts.h"
#include "tests/join_on_exit.h"
#include "tests/server/server_fixture.h"
#include "tests/tls_certificates.h"

namespace placedb::server_testing {
namespace {

using namespace std::chrono_literals;
using cluster::testing::EngineProcess;
using cluster::testing::Engines;
using cluster::testing::EnginesOptions;
using cluster::testing::Hosts;
using cluster::testing::HostsOptions;
using Clock = std::chrono::steady_clock;

constexpr int kHosts = 3;
constexpr int kFrames = 150;  // per agent
constexpr char kCluster[] = "hosts";

// Fails the test (abort: gtest reports the crash) when it has not finished within `limit`: a
// hang must not block CI. The engines and servers die with this process (PR_SET_PDEATHSIG); the
// cleanup fixture removes the namespaces.
class Watchdog {
 public:
  explicit Watchdog(std::chrono::seconds limit)
      : thread_([this, limit] {
          std::unique_lock<std::mutex> lock(mutex_);
          if (!done_cv_.wait_for(lock, limit, [this] { return done_; })) {
            std::fprintf(stderr, "watchdog: cluster_hosts_test still running after %d s\n",
                         int(limit.count()));
            std::abort();
          }
        }) {}
  ~Watchdog() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      done_ = true;
    }
    done_cv_.notify_all();
    thread_.join();
  }

 private:
  std::mutex mutex_;
  std::condition_variable done_cv_;
  bool done_ = false;
  std::thread thread_;
};

std::string Join(const std::vector<std::string>& items) {
  std::string out;
  for (const std::string& item : items) out += (out.empty() ? "" : ",") + item;
  return out;
}

// The last `lines` lines of a log file.
std::string Tail(const std::string& path, size_t lines = 20) {
  std::ifstream in(path);
  std::vector<std::string> all;
  for (std::string line; std::getline(in, line);) all.push_back(line);
  std::string out;
  for (size_t i = all.size() > lines ? all.size() - lines : 0; i < all.size(); ++i) {
    out += "  " + all[i] + "\n";
  }
  return out;
}

// SIGTERM, then waits (bounded) for the process to exit and reaps it; true when it exited by
// itself with status 0 (a clean shutdown).
bool Terminate(EngineProcess& process, std::chrono::seconds limit = 30s) {
  if (!process.running()) return false;
  const pid_t pid = process.pid();
  ::kill(pid, SIGTERM);
  bool clean = false;
  for (const auto until = Clock::now() + limit; Clock::now() < until;) {
    siginfo_t info{};
    // WNOWAIT: looked at, not reaped (EngineProcess::Kill reaps it below).
    if (::waitid(P_PID, id_t(pid), &info, WEXITED | WNOHANG | WNOWAIT) == 0 && info.si_pid == pid) {
      clean = info.si_code == CLD_EXITED && info.si_status == 0;
      break;
    }
    std::this_thread::sleep_for(50ms);
  }
  process.Kill();  // reaps (SIGKILL first when it did not stop in time)
  return clean;
}

// One host's placedb-server processes.
struct HostProcesses {
  std::string address;
  std::string dir;
  int worker_port = 0;
  int internal_port = 0;
  EngineProcess shard;
  EngineProcess worker;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<v1::PlaceDb::Stub> stub;
  std::string shard_log() const { return dir + "/shard.log"; }
  std::string worker_log() const { return dir + "/worker.log"; }
  std::string shard_data() const { return dir + "/shard"; }
};

// An agent: its map, the worker it starts on, and what was acknowledged (frame -> response).
struct AgentRun {
  AgentRun(std::string agent, std::string on_map, int first_worker)
      : id(std::move(agent)), map(std::move(on_map)), worker(first_worker) {}
  std::string id, map;
  int worker = 0;
  std::map<int, v1::IngestResponse> acknowledged;
  int streams = 0;  // Ingest streams opened (1 + reconnects and retries)
  int broken = 0;   // streams that ended with an error (worker gone, connection refused)
  int resent = 0;   // frames sent again (no answer, or refused)
  int resent_acknowledged = 0;  // acknowledged frames sent again after a broken stream, answered
  int changed = 0;              // frames acknowledged twice, differently (place id or stored)
  double slowest_ms = 0;        // the longest a frame took in a worker (its timings.total_ms)
  bool finished = false;        // every frame acknowledged
};

// Sends every frame not acknowledged yet, until all are: a stream that breaks moves the agent
// to the next worker (a dead one refuses the connection and is skipped the same way), frames
// refused with an error go again on the same worker. Same agent id and sequences every time.
// After a broken stream, every 7th frame acknowledged before goes again too (until answered once
// more): the other worker must answer it alike, same place id (the message id de-duplicates).
void RunAgent(AgentRun& agent, const std::vector<v1::PlaceDb::Stub*>& workers,
              const v1::MatchOptions& matches, Clock::time_point until,
              const std::atomic<bool>& stop) {
  int worker = agent.worker;
  std::set<int> sent, checked;
  bool after_break = false;
  while (!stop && Clock::now() < until) {
    std::vector<v1::Observation> pending;
    bool unacknowledged = false;
    for (int f = 1; f <= kFrames; ++f) {
      if (agent.acknowledged.count(f)) {
        if (!after_break || f % 7 != 0 || checked.count(f)) continue;
      } else {
        unacknowledged = true;
        if (!sent.insert(f).second) ++agent.resent;
      }
      pending.push_back(FeatureObservation(f, agent.id));
    }
    if (!unacknowledged) {
      agent.finished = true;
      return;
    }
    ++agent.streams;
    const IngestOutcome outcome = IngestAll(workers[size_t(worker)], agent.map, pending, &matches);
    for (const v1::IngestResponse& response : outcome.responses) {
      agent.slowest_ms = std::max(agent.slowest_ms, response.timings().total_ms());
      if (response.has_error()) continue;
      const int frame = int(response.sequence());
      auto [it, inserted] = agent.acknowledged.emplace(frame, response);
      if (inserted) continue;
      checked.insert(frame);
      ++agent.resent_acknowledged;
      if (it->second.place_id() != response.place_id() ||
          it->second.stored() != response.stored()) {
        ++agent.changed;
      }
    }
    after_break = !outcome.status.ok();
    if (after_break) {
      ++agent.broken;
      worker = (worker + 1) % int(workers.size());
    }
    std::this_thread::sleep_for(100ms);
  }
}

// The parameter: cluster.internal_tls on every hop.
class ClusterHostsTest : public ServerTest, public ::testing::WithParamInterface<bool> {};

TEST_P(ClusterHostsTest, StreamLeaderShardAndWorkerKilledDuringIngestAcrossHosts) {
  const bool tls = GetParam();
  Watchdog watchdog(tls ? 300s : 240s);
  const double start_ms = bench::NowMs();
  const std::string binary = PLACEDB_SERVER_BINARY;
  FeatureFrames(84);

  auto hosts_or = Hosts::Create(HostsOptions{});
  ASSERT_TRUE(hosts_or.ok()) << hosts_or.status().ToString();
  Hosts& hosts = **hosts_or;
  std::printf("hosts: %s (%s, %s, %s)\n", hosts.kind_name(), hosts.address(0).c_str(),
              hosts.address(1).c_str(), hosts.address(2).c_str());
  // One node certificate for every process, naming every host's address.
  const testing::TestCertificates& certs = testing::SharedTestCertificates();
  const auto [node_cert, node_key] =
      tls ? testing::IssueNodeCertificate(certs, "hosts-node", hosts.Addresses())
          : std::pair<std::string, std::string>();
  EnginesOptions engine_options;
  engine_options.hosts = hosts.Addresses();
  engine_options.netns = hosts.Namespaces();
  if (tls)
    engine_options.tls = {.ca_file = certs.ca_cert, .cert_file = node_cert, .key_file = node_key};
  auto engines_or = Engines::Start(engine_options);
  ASSERT_TRUE(engines_or.ok()) << engines_or.status().ToString();
  Engines& engines = **engines_or;
  const std::string prefix = tls ? "cluster_hosts_tls_" : "cluster_hosts_";
  bench::Print(prefix + "engines_ready_ms", bench::NowMs() - start_ms, "ms");

  // The coordinator (in the workers) replaces a replica 2 s after its shard's lease (5 s) expired.
  const std::string config = root_ + "/cluster.yaml";
  std::ofstream(config) << "cluster:\n  replace_after_s: 2\n";
  std::vector<std::unique_ptr<HostProcesses>> procs;
  for (int i = 0; i < kHosts; ++i) {
    auto p = std::make_unique<HostProcesses>();
    p->address = hosts.address(i);
    p->dir = root_ + "/h" + std::to_string(i);
    std::filesystem::create_directories(p->dir);
    // Ports free inside the host (its own namespace as root).
    ASSERT_TRUE(hosts
                    .RunInside(i,
                               [&] {
                                 p->worker_port = FreePort(p->address);
                                 p->internal_port = FreePort(p->address);
                               })
                    .ok());
    ASSERT_GT(p->worker_port, 0);
    ASSERT_GT(p->internal_port, 0);
    ASSERT_NE(p->worker_port, p->internal_port);
    const std::vector<std::string> common = {binary,
                                             "--config",
                                             config,
                                             "--cluster-name",
                                             kCluster,
                                             "--nats",
                                             Join(engines.NatsUrls()),
                                             "--etcd",
                                             Join(engines.EtcdEndpoints()),
                                             "--vocabulary",
                                             "default=" + testing::DefaultVocabularyPath(),
                                             "--detector-model",
                                             "off",
                                             "--console-listen",
                                             "off",
                                             "--metrics-listen",
                                             "off",
                                             "--allow-unauthenticated-remote"};
    std::vector<std::string> tls_args;
    if (tls) {
      tls_args = {"--internal-tls", "--tls-cert",      node_cert,    "--tls-key",
                  node_key,         "--tls-client-ca", certs.ca_cert};
    }
    const std::string internal = p->address + ":" + std::to_string(p->internal_port);
    std::vector<std::string> shard = common;
    shard.insert(shard.end(), tls_args.begin(), tls_args.end());
    shard.insert(shard.end(),
                 {"--role", "shard", "--shard-id", "shard-" + std::to_string(i), "--advertise",
                  internal, "--internal-listen", internal, "--data-dir", p->shard_data()});
    ASSERT_TRUE(hosts.StartProcess(i, p->shard, shard, p->shard_log()).ok());
    std::vector<std::string> worker = common;
    worker.insert(worker.end(), tls_args.begin(), tls_args.end());
    worker.insert(worker.end(), {"--role", "worker", "--listen",
                                 p->address + ":" + std::to_string(p->worker_port), "--data-dir",
                                 p->dir + "/worker"});
    ASSERT_TRUE(hosts.StartProcess(i, p->worker, worker, p->worker_log()).ok());
    // The public API takes mutual TLS from the same files: the node certificate as a client's.
    p->channel = grpc::CreateChannel(p->address + ":" + std::to_string(p->worker_port),
                                     cluster::InternalChannelCredentials(engines.client_tls()));
    p->stub = v1::PlaceDb::NewStub(p->channel);
    procs.push_back(std::move(p));
  }
  // On failure: where the servers said why.
  struct DumpLogs {
    const std::vector<std::unique_ptr<HostProcesses>>& procs;
    ~DumpLogs() {
      if (!::testing::Test::HasFailure()) return;
      for (const auto& p : procs) {
        std::printf("--- %s\n%s--- %s\n%s", p->shard_log().c_str(), Tail(p->shard_log()).c_str(),
                    p->worker_log().c_str(), Tail(p->worker_log()).c_str());
      }
    }
  } dump_logs{procs};

  for (const auto& p : procs) {
    grpc::ClientContext context;
    context.set_wait_for_ready(true);
    context.set_deadline(std::chrono::system_clock::now() + 60s);
    v1::ServerInfo info;
    const grpc::Status status = p->stub->GetServerInfo(&context, {}, &info);
    ASSERT_TRUE(status.ok()) << p->address << ": " << status.error_message();
    EXPECT_EQ(info.role(), "worker");
  }
  auto etcd = cluster::EtcdClient::Create(
      {.endpoints = engines.EtcdEndpoints(), .tls = engines.client_tls()});
  ASSERT_TRUE(etcd.ok()) << etcd.status().ToString();
  auto view_or = cluster::ClusterView::Start(etcd->get(), kCluster);
  ASSERT_TRUE(view_or.ok()) << view_or.status().ToString();
  cluster::ClusterView& view = **view_or;
  for (const auto until = Clock::now() + 60s;
       view.Shards().size() < size_t(kHosts) && Clock::now() < until;) {
    std::this_thread::sleep_for(100ms);
  }
  ASSERT_EQ(view.Shards().size(), size_t(kHosts)) << "shards registered";
  for (const std::string map : {"m1", "m2"}) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::CreateMapRequest request;
    request.set_name(map);
    v1::MapDescription response;
    const grpc::Status created = procs[0]->stub->CreateMap(&context, request, &response);
    ASSERT_TRUE(created.ok()) << map << ": " << created.error_message();
  }
  bench::Print(prefix + "ready_ms", bench::NowMs() - start_ms, "ms");

  cluster::JetStreamOptions js_options;
  js_options.servers = engines.NatsUrls();
  js_options.request_timeout = 2s;
  js_options.tls = engines.client_tls();
  auto js_or = cluster::JetStream::Connect(js_options);
  ASSERT_TRUE(js_or.ok()) << js_or.status().ToString();
  cluster::JetStream& js = **js_or;

  // Queries on m1 through host 0's worker (never killed) all along. Phase 0: before the kills,
  // 1: after them.
  std::atomic<int> phase{0};
  std::atomic<bool> querying{true};
  std::atomic<int> answered[2] = {0, 0}, failed[2] = {0, 0};
  std::thread queries([&] {
    for (int frame = 1; querying; ++frame) {
      v1::QueryRequest request;
      request.set_map("m1");
      *request.mutable_observation() = FeatureObservation(frame % 84 + 1, "q");
      request.mutable_options()->set_top_k(3);
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + 2s);
      v1::QueryResponse response;
      const int p = phase;
      if (procs[0]->stub->Query(&context, request, &response).ok()) {
        ++answered[p];
      } else {
        ++failed[p];
      }
      std::this_thread::sleep_for(100ms);
    }
  });

  // 4 agents, 2 per map; host 2's worker (killed below) holds one agent of each map.
  std::vector<AgentRun> agents = {
      {"a1", "m1", 0},
      {"a2", "m1", 2},
      {"a3", "m2", 1},
      {"a4", "m2", 2},
  };
  std::vector<v1::PlaceDb::Stub*> stubs;
  for (const auto& p : procs) stubs.push_back(p->stub.get());
  v1::MatchOptions matches;
  matches.set_top_k(3);
  const auto agents_until = Clock::now() + 150s;
  std::atomic<bool> stop_agents{false};
  std::vector<std::thread> threads;
  for (AgentRun& agent : agents) {
    threads.emplace_back([&agent, &stubs, &matches, agents_until, &stop_agents] {
      RunAgent(agent, stubs, matches, agents_until, stop_agents);
    });
  }
  // An assertion that returns early stops and joins them.
  ::placedb::testing::JoinOnExit join_on_exit([&] {
    stop_agents = true;
    querying = false;
  });
  join_on_exit.Add(threads);
  join_on_exit.Add(queries);

  // The kills once the two streams hold a quarter of all frames: mid-ingest for both maps (the
  // faster one is not done yet), whatever the load.
  const std::string m1_stream = cluster::StreamName(kCluster, "m1");
  const std::string m2_stream = cluster::StreamName(kCluster, "m2");
  bool started = false;
  for (const auto until = Clock::now() + 60s; !started && Clock::now() < until;) {
    auto m1 = js.GetStreamInfo(m1_stream);
    auto m2 = js.GetStreamInfo(m2_stream);
    started = m1.ok() && m2.ok() && m1->last_sequence + m2->last_sequence >= uint64_t(kFrames);
    if (!started) std::this_thread::sleep_for(20ms);
  }
  ASSERT_TRUE(started) << "ingest did not get a quarter of the way";
  const auto placed = view.Map("m1");
  ASSERT_TRUE(placed && placed->placement && placed->placement->replicas.size() == 2);
  const int64_t epoch = placed->placement->epoch;
  // (a) The nats-server leading m1's stream.
  auto leader = engines.StreamLeader(m1_stream);
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  // (b) The shard process holding (the first) replica of m1.
  const std::string killed_shard = placed->placement->replicas[0];
  const int shard_host = std::stoi(killed_shard.substr(killed_shard.find('-') + 1));
  // (c) Host 2's worker, which a2 and a4 are streaming to.
  constexpr int kWorkerHost = 2;
  const double kill_ms = bench::NowMs();
  phase = 1;
  engines.KillNats(*leader);
  procs[size_t(shard_host)]->shard.Kill();
  std::this_thread::sleep_for(300ms);
  procs[kWorkerHost]->worker.Kill();
  std::printf(
      "killed: nats n%d (m1's stream leader), %s (m1 replica, host %d), worker of host %d\n",
      *leader, killed_shard.c_str(), shard_host, kWorkerHost);
  // The nats-server comes back on its data directory while the agents go on.
  std::this_thread::sleep_for(2s);
  ASSERT_TRUE(engines.RestartNats(*leader).ok());

  for (std::thread& thread : threads) thread.join();
  bench::Print(prefix + "ingest_after_kill_ms", bench::NowMs() - kill_ms, "ms");
  int acknowledged = 0, streams = 0, broken = 0, resent = 0, resent_acknowledged = 0;
  double slowest_ms = 0;
  for (const AgentRun& agent : agents) {
    ASSERT_TRUE(agent.finished) << agent.id << ": " << agent.acknowledged.size() << " of "
                                << kFrames << " frames acknowledged";
    EXPECT_EQ(agent.changed, 0) << agent.id << ": a frame acknowledged twice, differently";
    acknowledged += int(agent.acknowledged.size());
    streams += agent.streams;
    broken += agent.broken;
    resent += agent.resent;
    resent_acknowledged += agent.resent_acknowledged;
    slowest_ms = std::max(slowest_ms, agent.slowest_ms);
  }
  bench::Print(prefix + "acknowledged", acknowledged, "frames");
  bench::Print(prefix + "streams", streams, "streams");
  bench::Print(prefix + "streams_broken", broken, "streams");
  bench::Print(prefix + "resent", resent, "frames");
  bench::Print(prefix + "resent_acknowledged", resent_acknowledged, "frames");
  bench::Print(prefix + "slowest_frame_ms", slowest_ms, "ms");
  EXPECT_GT(broken, 0) << "the killed worker's agents had their streams cut";
  EXPECT_GT(resent_acknowledged, 0) << "acknowledged frames sent again after a broken stream";

  // Both live replicas of each map apply the stream's last record (the killed shard's replicas
  // replaced: epoch + 1).
  std::map<std::string, uint64_t> last;
  std::map<std::string, std::vector<std::string>> live;
  for (const std::string map : {"m1", "m2"}) {
    auto info = js.GetStreamInfo(cluster::StreamName(kCluster, map));
    ASSERT_TRUE(info.ok()) << info.status().ToString();
    last[map] = info->last_sequence;
    // One record per frame: every frame sent again was de-duplicated by its message id.
    EXPECT_EQ(info->messages, uint64_t(2 * kFrames)) << map;
    EXPECT_EQ(info->last_sequence, uint64_t(2 * kFrames)) << map;
    const bool caught_up = view.WaitFor(
        map,
        [&](const std::optional<cluster::MapView>& m) {
          if (!m || !m->placement || m->placement->replicas.size() != 2) return false;
          if (map == "m1" && m->placement->epoch <= epoch) return false;
          for (const std::string& shard : m->placement->replicas) {
            if (shard == killed_shard) return false;
            const auto applied = m->applied.find(shard);
            if (applied == m->applied.end() || applied->second < last[map]) return false;
          }
          live[map] = m->placement->replicas;
          return true;
        },
        Clock::now() + 60s);
    ASSERT_TRUE(caught_up) << map << ": two live replicas did not apply sequence " << last[map];
  }
  bench::Print(prefix + "recovered_after_kill_ms", bench::NowMs() - kill_ms, "ms");
  querying = false;
  queries.join();
  bench::Print(prefix + "queries_answered_before_kills", answered[0], "queries");
  bench::Print(prefix + "queries_failed_before_kills", failed[0], "queries");
  bench::Print(prefix + "queries_answered_after_kills", answered[1], "queries");
  bench::Print(prefix + "queries_failed_after_kills", failed[1], "queries");
  EXPECT_GT(answered[1].load(), 0);

  // After recovery every query answers, through either live worker, from a replica that applied
  // the map's whole stream (read-your-writes).
  int valid_queries = 0;
  for (int i = 0; i < 20; ++i) {
    const std::string map = i % 2 ? "m2" : "m1";
    v1::QueryRequest request;
    request.set_map(map);
    request.set_min_sequence(last[map]);
    *request.mutable_observation() = FeatureObservation(i + 1, "q");
    request.mutable_options()->set_top_k(3);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 10s);
    v1::QueryResponse response;
    const grpc::Status status = procs[size_t(i / 2 % 2)]->stub->Query(&context, request, &response);
    ASSERT_TRUE(status.ok()) << map << ": " << status.error_message();
    if (!response.valid()) {
      // A frame with too few features is answered by the worker, no replica asked.
      std::printf("query frame %d invalid: %s\n", i + 1, response.rejection().c_str());
      continue;
    }
    ++valid_queries;
    EXPECT_GE(response.sequence(), last[map]);
    EXPECT_GT(response.matches_size(), 0);
  }
  EXPECT_GT(valid_queries, 10);

  // The workers, then the shards, stop cleanly; the shards' data directories are then ours.
  for (int i = 0; i < kHosts; ++i) {
    if (procs[size_t(i)]->worker.running()) {
      EXPECT_TRUE(Terminate(procs[size_t(i)]->worker)) << "worker of host " << i;
    }
  }
  for (int i = 0; i < kHosts; ++i) {
    if (procs[size_t(i)]->shard.running()) {
      EXPECT_TRUE(Terminate(procs[size_t(i)]->shard)) << "shard of host " << i;
    }
  }
  std::map<std::string, std::unique_ptr<DataDirectory>> dirs;  // shard id -> its directory
  for (const auto& [map, shards] : live) {
    for (const std::string& shard : shards) {
      if (dirs.count(shard)) continue;
      const int host = std::stoi(shard.substr(shard.find('-') + 1));
      auto dir = DataDirectory::Open(procs[size_t(host)]->shard_data());
      ASSERT_TRUE(dir.ok()) << shard << ": " << dir.status().ToString();
      dirs[shard] = std::move(dir).value();
    }
  }
  for (const std::string map : {"m1", "m2"}) {
    std::shared_ptr<PlaceMap> replicas[2];
    for (int r = 0; r < 2; ++r) {
      auto opened = dirs[live[map][size_t(r)]]->OpenMap(map, AnyVocabulary(vocabulary_));
      ASSERT_TRUE(opened.ok()) << map << " on " << live[map][size_t(r)] << ": "
                               << opened.status().ToString();
      replicas[r] = std::move(opened).value();
      EXPECT_GE(replicas[r]->applied_sequence(), last[map]);
    }
    // Every sequence of the stream: a place on both replicas, identical, or on neither.
    std::map<std::pair<std::string, uint64_t>, std::vector<uint32_t>> stored;  // frame -> ids
    for (uint64_t id = 1; id <= last[map]; ++id) {
      auto a = replicas[0]->GetPlace(PlaceId(id));
      auto b = replicas[1]->GetPlace(PlaceId(id));
      ASSERT_EQ(a.ok(), b.ok()) << map << " place " << id << ": on one replica only";
      if (!a.ok()) {
        EXPECT_EQ(a.status().code(), StatusCode::kNotFound) << a.status().ToString();
        EXPECT_EQ(b.status().code(), StatusCode::kNotFound) << b.status().ToString();
        continue;
      }
      EXPECT_EQ(EncodePlaceRecord(a->record), EncodePlaceRecord(b->record)) << map << " " << id;
      EXPECT_EQ(EncodeBow(a->payload.bow), EncodeBow(b->payload.bow)) << map << " " << id;
      EXPECT_EQ(EncodeLocalFeatures(a->payload.features, a->payload.direct),
                EncodeLocalFeatures(b->payload.features, b->payload.direct))
          << map << " " << id;
      stored[{a->record.metadata.agent_id, a->record.metadata.sequence}].push_back(uint32_t(id));
    }
    size_t places = 0;
    for (const auto& [frame, ids] : stored) {
      places += ids.size();
      EXPECT_EQ(ids.size(), 1u) << map << ": " << frame.first << "/" << frame.second
                                << " stored under " << ids.size() << " ids";
    }
    // Every acknowledged place is there under its id; a frame acknowledged as no place is not.
    size_t acknowledged_places = 0;
    for (const AgentRun& agent : agents) {
      if (agent.map != map) continue;
      for (const auto& [frame, response] : agent.acknowledged) {
        const auto it = stored.find({agent.id, uint64_t(frame)});
        if (!response.stored()) {
          EXPECT_TRUE(it == stored.end()) << agent.id << "/" << frame << ": not acknowledged as "
                                          << "a place, stored as " << it->second.front();
          continue;
        }
        ++acknowledged_places;
        ASSERT_TRUE(it != stored.end()) << map << ": acknowledged place " << response.place_id()
                                        << " (" << agent.id << "/" << frame << ") lost";
        EXPECT_EQ(it->second.front(), response.place_id()) << agent.id << "/" << frame;
      }
    }
    EXPECT_EQ(places, acknowledged_places) << map << ": places no agent got an id for";
    bench::Print(prefix + "places_" + map, double(places), "places");
    for (int r = 0; r < 2; ++r) {
      EXPECT_EQ(replicas[r]->Stats().database.places, places) << map;
      EXPECT_TRUE(replicas[r]->VerifyIntegrity().ok()) << map << " replica " << r;
      auto scrub = replicas[r]->Scrub();
      ASSERT_TRUE(scrub.ok()) << scrub.status().ToString();
      EXPECT_TRUE(scrub->clean()) << map << " replica " << r << ": " << scrub->damaged_places.size()
                                  << " places, " << scrub->damaged_files.size() << " files damaged";
      EXPECT_EQ(scrub->places_checked, places);
    }
  }
  bench::Print(prefix + "test_ms", bench::NowMs() - start_ms, "ms");
}

INSTANTIATE_TEST_SUITE_P(, ClusterHostsTest, ::testing::Bool(),
                         [](const ::testing::TestParamInfo<bool>& info) {
                           return info.param ? "InternalTls" : "Plaintext";
                         });

}  // namespace
}  // namespace placedb::server_testing
