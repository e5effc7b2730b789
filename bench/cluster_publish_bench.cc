// JetStream publish latency and throughput for cluster mode's records (issue 18): 50 KB messages
// (about an AddPlace record: features ~60 KB less the descriptors' share, plus a thumbnail) on a
// real 3-node nats-server cluster on loopback (tests/cluster/engines.h), each publish waiting for
// its PubAck (the worker's ack-after-PubAck path).
//
// Prints `name value unit` lines: replicas 3 (what cluster mode uses) and, as the same-run
// baseline, replicas 1 on the same servers; one publisher, then --publishers concurrent ones.
//   cluster_publish_bench [--messages N] [--bytes B] [--publishers P]
#include <algorithm>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "server/cluster/jetstream.h"
#include "tests/cluster/engines.h"

namespace placedb::cluster {
namespace {

// "<prefix><number>": appended, as `"c" + std::to_string(i)` trips GCC 12's false -Wrestrict.
std::string Id(std::string prefix, int number) {
  prefix += std::to_string(number);
  return prefix;
}

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const size_t index = std::min(values.size() - 1, static_cast<size_t>(p * values.size()));
  return values[index];
}

int Run(int messages, int bytes, int publishers) {
  testing::EnginesOptions engine_options;
  engine_options.etcd = false;
  auto engines = testing::Engines::Start(engine_options);
  if (!engines.ok()) {
    std::fprintf(stderr, "engines: %s\n", engines.status().ToString().c_str());
    return 1;
  }
  JetStreamOptions options;
  options.servers = (*engines)->NatsUrls();
  const std::string payload(static_cast<size_t>(bytes), 'x');

  for (int replicas : {1, 3}) {
    StreamConfig config;
    config.name = "BENCH_R" + std::to_string(replicas);
    config.subjects = {"placedb.bench.r" + std::to_string(replicas)};
    config.replicas = replicas;
    config.max_message_bytes = 1 << 20;
    std::vector<std::unique_ptr<JetStream>> clients;
    for (int p = 0; p < publishers; ++p) {
      auto js = JetStream::Connect(options);
      if (!js.ok()) {
        std::fprintf(stderr, "connect: %s\n", js.status().ToString().c_str());
        return 1;
      }
      clients.push_back(std::move(*js));
    }
    if (Status s = clients[0]->EnsureStream(config); !s.ok()) {
      std::fprintf(stderr, "stream: %s\n", s.ToString().c_str());
      return 1;
    }
    const std::string tag = "cluster_publish_50k_r" + std::to_string(replicas);
    // One publisher: latency per PubAck.
    std::vector<double> latencies;
    const double start = bench::NowMs();
    for (int i = 0; i < messages; ++i) {
      const double t0 = bench::NowMs();
      auto ack =
          clients[0]->Publish(config.subjects[0], payload, Id("s", i), std::chrono::seconds(5));
      if (!ack.ok()) {
        std::fprintf(stderr, "publish: %s\n", ack.status().ToString().c_str());
        return 1;
      }
      latencies.push_back(bench::NowMs() - t0);
    }
    const double elapsed = bench::NowMs() - start;
    bench::Print(tag + "_p50", Percentile(latencies, 0.50), "ms");
    bench::Print(tag + "_p99", Percentile(latencies, 0.99), "ms");
    bench::Print(tag + "_msgs_per_s", messages * 1000.0 / elapsed, "msg/s");

    // Concurrent publishers (workers of a cluster publish to a map's stream at once).
    std::atomic<int> failures{0};
    std::vector<std::thread> threads;
    const double concurrent_start = bench::NowMs();
    for (int p = 0; p < publishers; ++p) {
      threads.emplace_back([&, p] {
        for (int i = 0; i < messages; ++i) {
          auto ack = clients[p]->Publish(config.subjects[0], payload, Id(Id("c", p) + "-", i),
                                         std::chrono::seconds(5));
          if (!ack.ok()) failures.fetch_add(1);
        }
      });
    }
    for (auto& thread : threads) thread.join();
    const double concurrent_elapsed = bench::NowMs() - concurrent_start;
    bench::Print(tag + "_" + std::to_string(publishers) + "pub_msgs_per_s",
                 publishers * messages * 1000.0 / concurrent_elapsed, "msg/s");
    if (failures.load() > 0) {
      std::fprintf(stderr, "%d concurrent publishes failed\n", failures.load());
      return 1;
    }
    (void)clients[0]->DeleteStream(config.name);
  }
  return 0;
}

}  // namespace
}  // namespace placedb::cluster

int main(int argc, char** argv) {
  int messages = 500;
  int bytes = 50 * 1024;
  int publishers = 4;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--messages")) messages = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--bytes")) bytes = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--publishers")) publishers = std::atoi(argv[i + 1]);
  }
  return placedb::cluster::Run(messages, bytes, publishers);
}
