// What mutual TLS on every internal hop costs cluster mode (issue 35, cluster.internal_tls): two
// clusters side by side on loopback, each real 3-node nats-server and etcd clusters
// (tests/cluster/engines.h), 2 in-process shards and 1 in-process worker; "plaintext" (the
// same-run baseline) and "tls" (engines with TLS on clients, routes and peers; shards and worker
// with internal_tls); the worker's public API is mutual TLS in both (the same files), so the
// modes differ in the internal hops only (worker -> shard, NATS, etcd). Rounds alternate the
// modes (A B, then B A) on a fresh map each: --agents agents ingest --frames precomputed-feature
// frames (matches top 3: a search on a replica before each publish), then --queries queries one
// at a time through the worker (read-your-writes: a replica that applied the whole stream).
//
// Prints `name value unit` lines: ingest frames/s and query p50/p99 per mode (median over the
// rounds), the relative change of tls against plaintext, and the median of the rounds' own
// changes ("_paired"). A gtest program (it stands on the
// service tests' fixture); not run by ctest:
//   cluster_tls_bench [--rounds N] [--frames F] [--agents A] [--queries Q]
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "server/cluster/internal_tls.h"
#include "server/cluster/shard.h"
#include "server/cluster/worker.h"
#include "tests/cluster/cluster_frames.h"
#include "tests/cluster/engines.h"
#include "tests/server/server_fixture.h"
#include "tests/tls_certificates.h"

namespace placedb::server_testing {
namespace {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

int rounds = 5, frames = 200, agents = 2, queries = 200;

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  return values[std::min(values.size() - 1, size_t(p * double(values.size())))];
}

// /proc/loadavg's first three fields.
std::string LoadAverage() {
  char text[64] = {};
  if (std::FILE* file = std::fopen("/proc/loadavg", "r")) {
    if (!std::fgets(text, sizeof text, file)) text[0] = 0;
    std::fclose(file);
  }
  std::string load = text;
  size_t end = 0;
  for (int field = 0; field < 3 && end != std::string::npos; ++field) end = load.find(' ', end + 1);
  return load.substr(0, end);
}

// One cluster: engines, 2 shards, 1 worker (a Server with the worker role).
struct Cluster {
  std::string mode;
  std::unique_ptr<cluster::testing::Engines> engines;
  std::vector<std::unique_ptr<cluster::Shard>> shards;
  std::unique_ptr<ServerConfig> config;
  std::unique_ptr<Server> worker;
  std::unique_ptr<v1::PlaceDb::Stub> stub;
  std::map<std::string, std::vector<double>> figures;  // per round
};

class ClusterTlsBench : public ServerTest {
 protected:
  void Start(Cluster& c, bool tls) {
    c.mode = tls ? "tls" : "plaintext";
    const testing::TestCertificates& certs = testing::SharedTestCertificates();
    cluster::testing::EnginesOptions options;
    if (tls) {
      options.tls = {
          .ca_file = certs.ca_cert, .cert_file = certs.node_cert, .key_file = certs.node_key};
    }
    auto engines = cluster::testing::Engines::Start(options);
    ASSERT_TRUE(engines.ok()) << engines.status().ToString();
    c.engines = std::move(engines).value();
    const std::string dir = root_ + "/" + c.mode;
    for (int i = 0; i < 2; ++i) {
      cluster::ShardOptions shard;
      shard.cluster_name = "bench";
      shard.nats = c.engines->NatsUrls();
      shard.etcd = c.engines->EtcdEndpoints();
      shard.shard_id = "shard-" + std::to_string(i);
      shard.internal_listen = "127.0.0.1:0";
      shard.data_dir = dir + "/shard-" + std::to_string(i);
      shard.vocabularies.emplace("default", vocabulary_);
      shard.tls = c.engines->client_tls();
      auto started = cluster::Shard::Start(std::move(shard));
      ASSERT_TRUE(started.ok()) << started.status().ToString();
      c.shards.push_back(std::move(started).value());
    }
    c.config = std::make_unique<ServerConfig>(Config());
    ServerConfig& config = *c.config;
    config.data_dir = dir + "/worker";
    config.cluster.role = server::ClusterRole::kWorker;
    config.cluster.name = "bench";
    config.cluster.nats = c.engines->NatsUrls();
    config.cluster.etcd = c.engines->EtcdEndpoints();
    // The public API is mutual TLS in both modes: the modes differ in the internal hops only.
    config.tls = {
        .cert_file = certs.node_cert, .key_file = certs.node_key, .client_ca_file = certs.ca_cert};
    config.cluster.internal_tls = tls;
    ServerDeps deps;
    deps.vocabularies.emplace("default", vocabulary_);
    deps.cluster_backend =
        [&config](server::MapRegistry* maps,
                  server::Metrics* metrics) -> Result<std::unique_ptr<server::MapBackend>> {
      auto worker = server::ClusterWorker::Start(config, maps, metrics);
      if (!worker.ok()) return worker.status();
      return std::unique_ptr<server::MapBackend>(std::move(worker).value());
    };
    auto started = Server::Start(config, std::move(deps));
    ASSERT_TRUE(started.ok()) << started.status().ToString();
    c.worker = std::move(started).value();
    auto client = cluster::LoadInternalTls(config.tls);
    ASSERT_TRUE(client.ok()) << client.status().ToString();
    c.stub =
        v1::PlaceDb::NewStub(grpc::CreateChannel("127.0.0.1:" + std::to_string(c.worker->port()),
                                                 cluster::InternalChannelCredentials(*client)));
  }

  // One round on a fresh map: ingest by `agents` agents at once, then queries one at a time.
  void Round(Cluster& c, int round) {
    const std::string map = "r" + std::to_string(round);
    {
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + 60s);
      v1::CreateMapRequest request;
      request.set_name(map);
      v1::MapDescription response;
      const grpc::Status created = c.stub->CreateMap(&context, request, &response);
      ASSERT_TRUE(created.ok()) << c.mode << ": " << created.error_message();
    }
    // Both replicas open before the first frame (a search finds a replica to ask).
    int open = 0;
    for (const auto until = Clock::now() + 60s; open < 2 && Clock::now() < until;) {
      open = 0;
      for (const auto& shard : c.shards) {
        for (const cluster::ReplicaStatus& replica : shard->Replicas()) {
          open += replica.map == map && replica.state == "applying";
        }
      }
      if (open < 2) std::this_thread::sleep_for(20ms);
    }
    ASSERT_EQ(open, 2) << c.mode << ": the map's replicas did not open";
    v1::MatchOptions matches;
    matches.set_top_k(3);
    std::vector<IngestOutcome> outcomes(static_cast<size_t>(agents));
    std::vector<std::thread> threads;
    const auto start = Clock::now();
    for (int a = 0; a < agents; ++a) {
      threads.emplace_back([&, a] {
        std::vector<v1::Observation> observations;
        const std::string agent = "agent-" + std::to_string(a);
        for (int f = 1; f <= frames; ++f) observations.push_back(FeatureObservation(f, agent));
        outcomes[size_t(a)] = IngestAll(c.stub.get(), map, observations, &matches);
      });
    }
    for (std::thread& thread : threads) thread.join();
    const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
    for (const IngestOutcome& outcome : outcomes) {
      ASSERT_TRUE(outcome.status.ok()) << c.mode << ": " << outcome.status.error_message();
      for (const v1::IngestResponse& response : outcome.responses) {
        ASSERT_FALSE(response.has_error()) << c.mode << ": " << response.error().message();
      }
    }
    c.figures["ingest_frames_per_s"].push_back(double(agents * frames) / seconds);

    std::vector<double> latencies;
    for (int q = 0; q < queries; ++q) {
      v1::QueryRequest request;
      request.set_map(map);
      request.set_min_sequence(uint64_t(agents * frames));
      *request.mutable_observation() = FeatureObservation(q % 84 + 1, "q");
      request.mutable_options()->set_top_k(3);
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + 30s);
      v1::QueryResponse response;
      const auto sent = Clock::now();
      const grpc::Status status = c.stub->Query(&context, request, &response);
      ASSERT_TRUE(status.ok()) << c.mode << ": " << status.error_message();
      latencies.push_back(std::chrono::duration<double, std::milli>(Clock::now() - sent).count());
    }
    c.figures["query_p50_ms"].push_back(Percentile(latencies, 0.5));
    c.figures["query_p99_ms"].push_back(Percentile(latencies, 0.99));
    std::printf("# round %d %s: %.1f frames/s, query p50 %.2f ms, p99 %.2f ms\n", round,
                c.mode.c_str(), c.figures["ingest_frames_per_s"].back(),
                c.figures["query_p50_ms"].back(), c.figures["query_p99_ms"].back());
    std::fflush(stdout);
  }
};

TEST_F(ClusterTlsBench, PlaintextAgainstInternalTls) {
  FeatureFrames(84);
  const std::string load = LoadAverage();
  std::printf("# load %s; %u cores; %d rounds, %d agents x %d frames, %d queries\n", load.c_str(),
              std::thread::hardware_concurrency(), rounds, agents, frames, queries);
  Cluster plain, tls;
  ASSERT_NO_FATAL_FAILURE(Start(plain, false));
  ASSERT_NO_FATAL_FAILURE(Start(tls, true));
  for (int round = 1; round <= rounds; ++round) {
    // A B, then B A: a drift in the machine's load favours neither.
    Cluster* order[2] = {&plain, &tls};
    if (round % 2 == 0) std::swap(order[0], order[1]);
    for (Cluster* c : order) ASSERT_NO_FATAL_FAILURE(Round(*c, round));
  }
  for (const std::string name : {"ingest_frames_per_s", "query_p50_ms", "query_p99_ms"}) {
    const char* unit = name == "ingest_frames_per_s" ? "frames/s" : "ms";
    const double a = bench::Median(plain.figures[name]), b = bench::Median(tls.figures[name]);
    bench::Print("cluster_plaintext_" + name, a, unit);
    bench::Print("cluster_tls_" + name, b, unit);
    bench::Print("cluster_tls_change_" + name, (b - a) / a * 100, "%");
    // Paired: each round's two runs are adjacent in time, so the median of the rounds' own
    // changes moves less with a load that changes between rounds.
    std::vector<double> changes;
    for (size_t r = 0; r < plain.figures[name].size(); ++r) {
      changes.push_back((tls.figures[name][r] - plain.figures[name][r]) / plain.figures[name][r] *
                        100);
    }
    bench::Print("cluster_tls_change_" + name + "_paired", bench::Median(changes), "%");
  }
  std::printf("# load %s\n", LoadAverage().c_str());
  // The worker first (it calls the shards), then shards, then engines.
  for (Cluster* c : {&plain, &tls}) {
    c->stub.reset();
    c->worker->Shutdown();
    c->worker.reset();
    c->shards.clear();
    c->engines.reset();
  }
}

}  // namespace
}  // namespace placedb::server_testing

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  using placedb::server_testing::agents;
  using placedb::server_testing::frames;
  using placedb::server_testing::queries;
  using placedb::server_testing::rounds;
  for (int i = 1; i + 1 < argc; i += 2) {
    const int value = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--rounds")) {
      rounds = value;
    } else if (!std::strcmp(argv[i], "--frames")) {
      frames = value;
    } else if (!std::strcmp(argv[i], "--agents")) {
      agents = value;
    } else if (!std::strcmp(argv[i], "--queries")) {
      queries = value;
    } else {
      std::fprintf(stderr, "cluster_tls_bench: unknown option %s\n", argv[i]);
      return 2;
    }
  }
  return RUN_ALL_TESTS();
}
