// What a switch of vocabulary costs a cluster map's replicas (issue 29, docs/cluster.md "A map's
// own vocabulary"): two in-process shards replicating one map on real 3-node nats-server and etcd
// clusters on loopback (tests/cluster/engines.h), places published as a worker publishes them
// (the record codec, RTAB-Map frames), then the vocabulary learned on one replica, published in
// parts and switched to, while a publisher keeps adding places at --rate per second.
//
// The figure is the apply lag of those places: from their PubAck until both replicas have applied
// them (a frame's next Search waits for that). Two runs on fresh maps of the same size:
// "prepared" (PrepareVocabularySwitch built ahead, the switch record only catches up: what the
// worker does) and, as the same-run baseline, "unprepared" (the switch record right after the
// parts: each replica builds the switch then, holding its later records back).
//   cluster_vocabulary_bench [--places N] [--rate R] [--sample D]
#include <google/protobuf/util/json_util.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/text.h"
#include "proto/convert_config.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/map_record.h"
#include "server/cluster/placement.h"
#include "server/cluster/shard.h"
#include "tests/cluster/engines.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace placedb::cluster {
namespace {

using namespace std::chrono_literals;
constexpr char kCluster[] = "bench";

std::string Key(const std::string& suffix) {
  return std::string("/placedb/") + kCluster + "/" + suffix;
}

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  return values[std::min(values.size() - 1, size_t(p * double(values.size())))];
}

struct Bench {
  std::unique_ptr<testing::Engines> engines;
  std::unique_ptr<JetStream> js;
  std::unique_ptr<EtcdClient> etcd;
  std::vector<std::unique_ptr<Shard>> shards;
  std::vector<ProcessedFrame> frames;
  int published = 0;  // message ids

  uint64_t Publish(const std::string& map, const std::string& data) {
    // Appended: GCC 12 warns falsely (-Wrestrict) on "p" + std::to_string().
    std::string id = "p";
    id += std::to_string(++published);
    for (int attempt = 0; attempt < 100; ++attempt) {
      auto ack = js->Publish(StreamSubject(kCluster, map), data, id, 2s);
      if (ack.ok()) return ack->sequence;
      std::this_thread::sleep_for(100ms);
    }
    std::fprintf(stderr, "publish %s failed\n", id.c_str());
    std::exit(1);
  }
  std::string AddPlace(size_t i) const {
    PlaceMetadata metadata;
    metadata.agent_id = "robot";
    metadata.sequence = i + 1;
    metadata.timestamp_ns = int64_t(i + 1) * 1'000'000;
    return EncodeAddPlace(frames[i % frames.size()], metadata);
  }
  // Both replicas' applied sequence (the lower).
  uint64_t Applied(const std::string& map) const {
    uint64_t low = UINT64_MAX;
    for (const auto& shard : shards) {
      auto m = shard->Map(map);
      low = std::min<uint64_t>(low, m.ok() ? (*m)->applied_sequence() : 0);
    }
    return low;
  }
  bool WaitApplied(const std::string& map, uint64_t sequence, std::chrono::seconds limit) const {
    const auto until = std::chrono::steady_clock::now() + limit;
    while (Applied(map) < sequence) {
      if (std::chrono::steady_clock::now() > until) return false;
      std::this_thread::sleep_for(2ms);
    }
    return true;
  }
  bool Prepared(const std::string& map, uint64_t checksum) const {
    for (const auto& shard : shards) {
      auto m = shard->Map(map);
      if (!m.ok() || (*m)->prepared_vocabulary() != checksum) return false;
    }
    return true;
  }
  void CreateMap(const std::string& map) {
    StreamConfig stream;
    stream.name = StreamName(kCluster, map);
    stream.subjects = {StreamSubject(kCluster, map)};
    if (Status made = js->EnsureStream(stream); !made.ok()) {
      std::fprintf(stderr, "stream: %s\n", made.ToString().c_str());
      std::exit(1);
    }
    std::string config;
    (void)google::protobuf::util::MessageToJsonString(placedb::v1::MapConfig(), &config);
    (void)etcd->Put(Key("maps/" + map),
                    R"({"config": )" + config + R"(, "stream": ")" + stream.name + R"("})");
    (void)etcd->Put(Key("placement/" + map), R"({"epoch": 1, "replicas": ["a", "b"]})");
  }
};

// One run: a map of `places`, learned on replica a, switched with or without preparation while
// places keep coming at `rate` per second. Prints the run's figures with `mode` in their names.
void Run(Bench& bench, const std::string& mode, int places, double rate, uint64_t sample) {
  const std::string map = "m-" + mode;
  bench.CreateMap(map);
  uint64_t last = 0;
  for (int i = 0; i < places; ++i) last = bench.Publish(map, bench.AddPlace(size_t(i)));
  if (!bench.WaitApplied(map, last, 600s)) {
    std::fprintf(stderr, "%s: the replicas did not apply %d places\n", mode.c_str(), places);
    std::exit(1);
  }
  auto replica = bench.shards[0]->Map(map);
  AdaptOptions options;
  options.learning.max_sample_descriptors = sample;
  const double learn_start = bench::NowMs();
  auto learned = (*replica)->LearnVocabulary(options);
  if (!learned.ok()) {
    std::fprintf(stderr, "learn: %s\n", learned.status().ToString().c_str());
    std::exit(1);
  }
  bench::Print("cluster_vocabulary_learn_" + mode, (bench::NowMs() - learn_start) / 1000, "s");

  // Places at `rate` from now until the switch is applied and 2 s more; each one's lag.
  std::atomic<bool> switched{false};
  std::vector<double> lags;
  std::thread publisher([&] {
    const auto period = std::chrono::duration<double>(1.0 / rate);
    size_t i = size_t(places);
    double switched_at = 0;
    for (auto next = std::chrono::steady_clock::now();;
         next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(period)) {
      std::this_thread::sleep_until(next);
      const uint64_t sequence = bench.Publish(map, bench.AddPlace(i++));
      const double acked = bench::NowMs();
      if (!bench.WaitApplied(map, sequence, 600s)) break;
      lags.push_back(bench::NowMs() - acked);
      if (switched && switched_at == 0) switched_at = bench::NowMs();
      if (switched_at > 0 && bench::NowMs() - switched_at > 2000) break;
    }
  });
  const uint64_t checksum = learned->vocabulary.checksum();
  const auto parts = EncodeVocabularyParts(learned->vocabulary, 512 << 10);
  for (const std::string& part : parts) (void)bench.Publish(map, part);
  const double prepare_start = bench::NowMs();
  if (mode == "prepared") {
    (void)bench.Publish(map, EncodePrepareVocabulary(checksum, uint32_t(parts.size())));
    while (!bench.Prepared(map, checksum)) std::this_thread::sleep_for(5ms);
    bench::Print("cluster_vocabulary_prepare_" + mode, (bench::NowMs() - prepare_start) / 1000,
                 "s");
  }
  const double switch_start = bench::NowMs();
  const uint64_t at =
      bench.Publish(map, EncodeSwitchVocabulary(learned->source, uint32_t(parts.size())));
  if (!bench.WaitApplied(map, at, 600s)) {
    std::fprintf(stderr, "%s: the switch was not applied\n", mode.c_str());
    std::exit(1);
  }
  switched = true;
  bench::Print("cluster_vocabulary_switch_record_" + mode, (bench::NowMs() - switch_start) / 1000,
               "s");
  publisher.join();
  for (const auto& shard : bench.shards) {
    auto m = shard->Map(map);
    if ((*m)->vocabulary().checksum() != checksum) {
      std::fprintf(stderr, "%s: a replica did not switch\n", mode.c_str());
      std::exit(1);
    }
  }
  bench::Print("cluster_vocabulary_places_added_during_" + mode, double(lags.size()), "places");
  bench::Print("cluster_vocabulary_apply_lag_p50_" + mode, Percentile(lags, 0.5), "ms");
  bench::Print("cluster_vocabulary_apply_lag_max_" + mode, Percentile(lags, 1.0), "ms");
}

int Main(int argc, char** argv) {
  int places = 2000;
  double rate = 10;
  uint64_t sample = 200000;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--places")) places = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--rate")) rate = std::atof(argv[i + 1]);
    if (!std::strcmp(argv[i], "--sample")) sample = uint64_t(std::atoll(argv[i + 1]));
  }
  if (!placedb::testing::HaveSharedData()) {
    std::fprintf(stderr, "../shared/data is required\n");
    return 1;
  }
  Bench bench;
  auto engines = testing::Engines::Start();
  if (!engines.ok()) {
    std::fprintf(stderr, "engines: %s\n", engines.status().ToString().c_str());
    return 1;
  }
  bench.engines = std::move(engines).value();
  JetStreamOptions js;
  js.servers = bench.engines->NatsUrls();
  auto connected = JetStream::Connect(js);
  EtcdOptions etcd;
  etcd.endpoints = bench.engines->EtcdEndpoints();
  auto client = EtcdClient::Create(etcd);
  if (!connected.ok() || !client.ok()) return 1;
  bench.js = std::move(connected).value();
  bench.etcd = std::move(client).value();
  const AnyVocabulary vocabulary(placedb::testing::DefaultVocabulary());
  auto db = PlaceDatabase::Create(vocabulary, DatabaseConfig());
  if (!db.ok()) return 1;
  bench.frames = placedb::testing::ProcessRtabmapFrames(**db, 100);
  const std::string root = placedb::testing::MakeTempDir("placedb-cluster-vocabulary-bench");
  for (const char* id : {"a", "b"}) {
    ShardOptions options;
    options.cluster_name = kCluster;
    options.nats = bench.engines->NatsUrls();
    options.etcd = bench.engines->EtcdEndpoints();
    options.shard_id = id;
    options.internal_listen = "127.0.0.1:0";
    options.data_dir = root + "/" + id;
    options.vocabularies = {{"default", vocabulary}};
    options.report_interval = 200ms;
    options.reconcile_interval = 200ms;
    auto shard = Shard::Start(options);
    if (!shard.ok()) {
      std::fprintf(stderr, "shard: %s\n", shard.status().ToString().c_str());
      return 1;
    }
    bench.shards.push_back(std::move(shard).value());
  }
  bench::Print("cluster_vocabulary_places", places, "places");
  bench::Print("cluster_vocabulary_rate", rate, "places/s");
  Run(bench, "prepared", places, rate, sample);
  Run(bench, "unprepared", places, rate, sample);
  bench.shards.clear();
  std::filesystem::remove_all(root);
  return 0;
}

}  // namespace
}  // namespace placedb::cluster

int main(int argc, char** argv) {
  return placedb::cluster::Main(argc, argv);
}
