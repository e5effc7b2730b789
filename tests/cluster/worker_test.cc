// Cluster mode's worker role (server/cluster/worker.h) through the public placedb.v1 API, on real
// 3-node etcd and nats-server clusters (tests/cluster/engines.h) and placedb servers started
// in-process with the worker role on loopback ports.
#include "server/cluster/worker.h"

#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "core/base/files.h"
#include "core/base/thread_annotations.h"
#include "core/storage/codec.h"
#include "proto/cluster.grpc.pb.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/map_record.h"
#include "server/cluster/placement.h"
#include "server/cluster/shard.h"
#include "server/cluster/snapshot_archives.h"
#include "tests/cluster/cluster_frames.h"
#include "tests/cluster/engines.h"
#include "tests/join_on_exit.h"
#include "tests/raw_map.h"
#include "tests/server/server_fixture.h"
#include "tests/tls_certificates.h"

namespace placedb::server_testing {
namespace {

using namespace std::chrono_literals;
using cluster::testing::Engines;
using server::ClusterRole;
using server::ClusterWorker;
using server::MapBackend;
using server::MapRegistry;
using server::Metrics;

// One worker process's worth: a Server with the worker role, and a stub to it.
struct Worker {
  std::unique_ptr<Server> server;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<v1::PlaceDb::Stub> stub;
};

class ClusterWorkerTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    cluster::testing::EnginesOptions options;
    if (tls_) {
      const testing::TestCertificates& certs = testing::SharedTestCertificates();
      options.tls = {
          .ca_file = certs.ca_cert, .cert_file = certs.node_cert, .key_file = certs.node_key};
    }
    auto engines = Engines::Start(options);
    ASSERT_TRUE(engines.ok()) << engines.status().ToString();
    engines_ = std::move(engines).value();
  }
  void TearDown() override {
    workers_.clear();
    engines_.reset();
    ServerTest::TearDown();
  }

  ServerConfig WorkerConfig(int index) const {
    ServerConfig config = Config();
    config.data_dir = root_ + "/worker-" + std::to_string(index);
    config.cluster.role = ClusterRole::kWorker;
    config.cluster.name = "test";
    config.cluster.nats = engines_->NatsUrls();
    config.cluster.etcd = engines_->EtcdEndpoints();
    config.cluster.replace_after_s = 2;
    if (compact_after_records_ >= 0) {
      config.cluster.compact_after_records = compact_after_records_;
      config.cluster.compact_after_bytes = 0;
      config.cluster.compact_keep_s = 3;  // records younger than 3 s stay (production: 150)
    }
    if (tls_) {
      // The node certificate on every hop, and mutual TLS on the public API too (same files).
      const testing::TestCertificates& certs = testing::SharedTestCertificates();
      config.cluster.internal_tls = true;
      config.tls = {.cert_file = certs.node_cert,
                    .key_file = certs.node_key,
                    .client_ca_file = certs.ca_cert};
    }
    return config;
  }

  Worker& StartWorker(int index, bool metrics = false) {
    ServerDeps deps;
    deps.vocabularies.emplace("default", vocabulary_);
    configs_.push_back(std::make_unique<ServerConfig>(WorkerConfig(index)));
    if (metrics) configs_.back()->metrics_listen = "127.0.0.1:0";
    const ServerConfig& config = *configs_.back();
    deps.cluster_backend = [&config](MapRegistry* maps,
                                     Metrics* metrics) -> Result<std::unique_ptr<MapBackend>> {
      auto worker = ClusterWorker::Start(config, maps, metrics);
      if (!worker.ok()) return worker.status();
      return std::unique_ptr<MapBackend>(std::move(worker).value());
    };
    auto started = Server::Start(config, std::move(deps));
    EXPECT_TRUE(started.ok()) << started.status().ToString();
    auto worker = std::make_unique<Worker>();
    if (!started.ok()) return *workers_.emplace_back(std::move(worker));
    worker->server = std::move(started).value();
    worker->channel = grpc::CreateChannel("127.0.0.1:" + std::to_string(worker->server->port()),
                                          cluster::InternalChannelCredentials(ClientTls()));
    worker->stub = v1::PlaceDb::NewStub(worker->channel);
    return *workers_.emplace_back(std::move(worker));
  }

  static grpc::Status CreateClusterMap(Worker& worker, const std::string& name,
                                       const v1::MapConfig& config = {}) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::CreateMapRequest request;
    request.set_name(name);
    *request.mutable_config() = config;
    v1::MapDescription response;
    return worker.stub->CreateMap(&context, request, &response);
  }

  // An in-process shard "shard-<i>" on the engines (lease 2 s), data under root_.
  std::unique_ptr<cluster::Shard> StartShard(int i) const {
    cluster::ShardOptions options;
    options.cluster_name = "test";
    options.nats = engines_->NatsUrls();
    options.etcd = engines_->EtcdEndpoints();
    options.shard_id = "shard-" + std::to_string(i);
    options.internal_listen = "127.0.0.1:0";
    options.data_dir = root_ + "/shard-" + std::to_string(i);
    options.vocabularies.emplace("default", vocabulary_);
    options.lease_ttl_s = 2;
    options.tls = ClientTls();
    auto shard = cluster::Shard::Start(std::move(options));
    EXPECT_TRUE(shard.ok()) << shard.status().ToString();
    return shard.ok() ? std::move(shard).value() : nullptr;
  }
  // Shards "shard-0".."shard-<count - 1>" (StartShard); a null entry for one that did not start.
  std::vector<std::unique_ptr<cluster::Shard>> StartShards(int count) const {
    std::vector<std::unique_ptr<cluster::Shard>> shards;
    for (int i = 0; i < count; ++i) shards.push_back(StartShard(i));
    return shards;
  }

  std::unique_ptr<cluster::JetStream> Js() const {
    cluster::JetStreamOptions options;
    options.servers = engines_->NatsUrls();
    options.tls = ClientTls();
    auto js = cluster::JetStream::Connect(options);
    EXPECT_TRUE(js.ok()) << js.status().ToString();
    return js.ok() ? std::move(js).value() : nullptr;
  }

  // The node certificate's TLS (the engines' client TLS) with tls_, else plain text.
  const cluster::InternalTls& ClientTls() const { return engines_->client_tls(); }

  bool tls_ = false;  // cluster.internal_tls on every hop (ClusterInternalTlsTest)
  // >= 0: the next workers' cluster.compact_after_records (compact_after_bytes 0); 0: off.
  int64_t compact_after_records_ = -1;
  std::unique_ptr<Engines> engines_;
  std::vector<std::unique_ptr<ServerConfig>> configs_;  // each outlives its worker
  std::vector<std::unique_ptr<Worker>> workers_;
};

// The first of `shards` holding a replica of `map` (-1: none).
int ShardHolding(const std::vector<std::unique_ptr<cluster::Shard>>& shards,
                 const std::string& map) {
  for (size_t i = 0; i < shards.size(); ++i) {
    if (!shards[i]) continue;
    for (const cluster::ReplicaStatus& replica : shards[i]->Replicas()) {
      if (replica.map == map) return int(i);
    }
  }
  return -1;
}

std::vector<v1::Observation> Frames(const std::string& agent, int first, int last) {
  std::vector<v1::Observation> out;
  for (int frame = first; frame <= last; ++frame) out.push_back(RtabmapObservation(frame, agent));
  return out;
}

// The places `ingested` stored, by frame (its first response is `first_frame`'s), into
// *place_of; the stream and every response must be free of errors.
void CollectPlaces(const IngestOutcome& ingested, int first_frame,
                   std::map<int, uint32_t>* place_of) {
  ASSERT_TRUE(ingested.status.ok()) << ingested.status.error_message();
  for (size_t i = 0; i < ingested.responses.size(); ++i) {
    ASSERT_FALSE(ingested.responses[i].has_error()) << ingested.responses[i].error().message();
    if (ingested.responses[i].stored()) {
      (*place_of)[first_frame + int(i)] = ingested.responses[i].place_id();
    }
  }
}

// The best match's place id for RTAB-Map frame `frame` queried in `map` through `stub`; 0 when
// nothing matched or the query failed (which fails the test).
uint32_t TopPlace(v1::PlaceDb::Stub* stub, const std::string& map, int frame) {
  v1::QueryRequest request;
  request.set_map(map);
  *request.mutable_observation() = RtabmapObservation(frame, "q");
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + 30s);
  v1::QueryResponse response;
  const grpc::Status status = stub->Query(&context, request, &response);
  EXPECT_TRUE(status.ok()) << status.error_message();
  return response.matches_size() > 0 ? response.matches(0).place_id() : 0;
}

// cluster.internal_tls (issue 35): the same cluster with mutual TLS on every internal hop.
class ClusterInternalTlsTest : public ClusterWorkerTest {
 protected:
  ClusterInternalTlsTest() { tls_ = true; }
};

// A TLS channel to `address` trusting the test CA, with `cert`/`key` as the client certificate
// (none when empty).
std::shared_ptr<grpc::Channel> TlsChannel(const std::string& address, const std::string& cert,
                                          const std::string& key) {
  const testing::TestCertificates& certs = testing::SharedTestCertificates();
  cluster::InternalTls tls;
  tls.ca = ReadWholeFile(certs.ca_cert).value();
  if (!cert.empty()) {
    tls.cert_chain = ReadWholeFile(cert).value();
    tls.private_key = ReadWholeFile(key).value();
  }
  return grpc::CreateChannel(address, cluster::InternalChannelCredentials(tls));
}

// Shard Status on `channel` within 5 s.
grpc::Status ShardStatus(const std::shared_ptr<grpc::Channel>& channel) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + 5s);
  cluster::v1::StatusResponse status;
  return cluster::v1::Shard::NewStub(channel)->Status(&context, {}, &status);
}

// Engines, shards and a worker with TLS and client certificates everywhere: ingest, queries
// (worker -> shard), a replica restored from a peer's checkpoint (shard -> shard), and every
// hop refuses plain text and a client without a certificate.
TEST_F(ClusterInternalTlsTest, IngestAndQueryWithTlsEverywherePlaintextRefused) {
  constexpr int kFrames = 30;
  FeatureFrames(84);
  ASSERT_TRUE(ClientTls().enabled());
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(2);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& worker = StartWorker(1);
  ASSERT_TRUE(worker.stub);
  ASSERT_TRUE(CreateClusterMap(worker, "m").ok());
  std::vector<v1::Observation> frames;
  for (int f = 1; f <= kFrames; ++f) frames.push_back(FeatureObservation(f, "agent"));
  v1::MatchOptions matches;
  matches.set_top_k(3);
  const IngestOutcome ingested = IngestAll(worker.stub.get(), "m", frames, &matches);
  ASSERT_TRUE(ingested.status.ok()) << ingested.status.error_message();
  ASSERT_EQ(ingested.responses.size(), size_t(kFrames));
  uint32_t last_place = 0;
  for (const v1::IngestResponse& response : ingested.responses) {
    ASSERT_FALSE(response.has_error()) << response.error().message();
    if (response.stored()) last_place = response.place_id();
  }
  ASSERT_GT(last_place, 0u);
  // A query that must wait for a replica with every frame: answered through a shard over TLS.
  {
    v1::QueryRequest request;
    request.set_map("m");
    request.set_min_sequence(kFrames);
    *request.mutable_observation() = FeatureObservation(5, "q");
    request.mutable_options()->set_top_k(3);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::QueryResponse response;
    const grpc::Status status = worker.stub->Query(&context, request, &response);
    ASSERT_TRUE(status.ok()) << status.error_message();
    EXPECT_GE(response.sequence(), uint64_t(kFrames));
    EXPECT_GT(response.matches_size(), 0);
  }
  {
    v1::GetPlaceRequest request;
    request.set_map("m");
    request.set_place_id(last_place);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::Place place;
    const grpc::Status status = worker.stub->GetPlace(&context, request, &place);
    ASSERT_TRUE(status.ok()) << status.error_message();
    EXPECT_EQ(place.place_id(), last_place);
  }

  // The internal API: plain text and a TLS client without a certificate fail; the node's
  // certificate passes (and so does a client certificate of the same CA: it is the CA that
  // counts, not the name).
  const testing::TestCertificates& certs = testing::SharedTestCertificates();
  const std::string internal = "127.0.0.1:" + std::to_string(shards[0]->internal_port());
  EXPECT_FALSE(ShardStatus(grpc::CreateChannel(internal, grpc::InsecureChannelCredentials())).ok());
  EXPECT_FALSE(ShardStatus(TlsChannel(internal, "", "")).ok());
  EXPECT_FALSE(
      ShardStatus(TlsChannel(internal, certs.other_client_cert, certs.other_client_key)).ok())
      << "a certificate of another CA";
  const grpc::Status node = ShardStatus(TlsChannel(internal, certs.node_cert, certs.node_key));
  EXPECT_TRUE(node.ok()) << node.error_message();

  // NATS: plain text, and TLS without a client certificate, are refused.
  {
    cluster::JetStreamOptions options;
    options.servers = engines_->NatsUrls();
    options.connect_timeout = 2s;
    EXPECT_FALSE(cluster::JetStream::Connect(options).ok()) << "plain text";
    options.tls.ca = ClientTls().ca;
    EXPECT_FALSE(cluster::JetStream::Connect(options).ok()) << "no client certificate";
    options.tls = ClientTls();
    EXPECT_TRUE(cluster::JetStream::Connect(options).ok());
  }
  // etcd: the same.
  {
    cluster::EtcdOptions options;
    options.endpoints = engines_->EtcdEndpoints();
    options.call_timeout = 3s;
    options.attempt_timeout = 1s;
    auto plain = cluster::EtcdClient::Create(options);
    ASSERT_TRUE(plain.ok());
    EXPECT_FALSE((*plain)->Get("/placedb/test/maps/", true).ok()) << "plain text";
    options.tls.ca = ClientTls().ca;
    auto anonymous = cluster::EtcdClient::Create(options);
    ASSERT_TRUE(anonymous.ok());
    EXPECT_FALSE((*anonymous)->Get("/placedb/test/maps/", true).ok()) << "no client certificate";
    options.tls = ClientTls();
    options.call_timeout = 10s;
    auto good = cluster::EtcdClient::Create(options);
    ASSERT_TRUE(good.ok());
    const auto read = (*good)->Get("/placedb/test/maps/", true);
    ASSERT_TRUE(read.ok()) << read.status().ToString();
    EXPECT_EQ(read->kvs.size(), 1u);
  }
  // Shard -> shard: a new shard replaces a stopped one, restored from the other's checkpoint
  // over TLS.
  const int stopped = ShardHolding(shards, "m");
  ASSERT_GE(stopped, 0);
  const std::string peer = "shard-" + std::to_string(1 - stopped);
  shards[size_t(stopped)].reset();
  std::unique_ptr<cluster::Shard> replacement = StartShard(2);
  ASSERT_TRUE(replacement);
  cluster::ReplicaStatus restored;
  for (const auto until = std::chrono::steady_clock::now() + 90s;
       std::chrono::steady_clock::now() < until;) {
    for (const cluster::ReplicaStatus& replica : replacement->Replicas()) {
      if (replica.map == "m") restored = replica;
    }
    if (restored.applied_sequence >= uint64_t(kFrames)) break;
    std::this_thread::sleep_for(100ms);
  }
  EXPECT_GE(restored.applied_sequence, uint64_t(kFrames)) << restored.state;
  EXPECT_EQ(restored.restored_from, peer) << restored.state;
}

// Bad internal TLS files stop a worker and a shard at startup, naming the key and the file; a
// missing one is a configuration error (exit 2) before anything starts.
TEST_F(ClusterInternalTlsTest, StartupNamesTheBadFile) {
  const testing::TestCertificates& certs = testing::SharedTestCertificates();
  {
    ServerConfig config = WorkerConfig(1);
    config.tls.key_file = certs.client_key;  // not the node certificate's key
    ServerDeps deps;
    deps.vocabularies.emplace("default", vocabulary_);
    deps.cluster_backend = [&config](MapRegistry* maps,
                                     Metrics* metrics) -> Result<std::unique_ptr<MapBackend>> {
      auto worker = ClusterWorker::Start(config, maps, metrics);
      if (!worker.ok()) return worker.status();
      return std::unique_ptr<MapBackend>(std::move(worker).value());
    };
    auto started = Server::Start(config, std::move(deps));
    ASSERT_FALSE(started.ok());
    // The public API checks the same files first; either way the key and file are named.
    EXPECT_NE(started.status().message().find("tls.key_file (" + certs.client_key + ")"),
              std::string::npos)
        << started.status().ToString();
  }
  const std::string common = std::string(PLACEDB_SERVER_BINARY) + " --role shard --nats " +
                             engines_->NatsUrl(0) + " --etcd " + engines_->EtcdEndpoint(0) +
                             " --shard-id s --advertise 127.0.0.1:1 --internal-listen " +
                             "127.0.0.1:0 --metrics-listen off --console-listen off --data-dir " +
                             root_ + "/bad-shard --internal-tls --tls-cert " + certs.node_cert +
                             " --tls-key " + certs.node_key;
  std::string output;
  EXPECT_EQ(testing::RunShell(common + " --tls-client-ca " + certs.not_pem, &output), 1) << output;
  EXPECT_NE(output.find("cluster.internal_tls"), std::string::npos) << output;
  EXPECT_NE(output.find("tls.client_ca_file (" + certs.not_pem + "): no PEM certificate"),
            std::string::npos)
      << output;
  EXPECT_EQ(testing::RunShell(common, &output), 2) << output;
  EXPECT_NE(output.find("cluster.internal_tls: needs tls.client_ca_file or "
                        "cluster.internal_ca_file"),
            std::string::npos)
      << output;
}

// Maps are the cluster's (any worker sees them), places are stream sequences acknowledged after
// JetStream's PubAck, and a replayed frame (same agent and sequence) gets its place id again.
TEST_F(ClusterWorkerTest, MapsAndIngestThroughAnyWorker) {
  Worker& first = StartWorker(1);
  Worker& second = StartWorker(2);
  ASSERT_TRUE(first.stub && second.stub);
  {
    grpc::ClientContext context;
    v1::ServerInfo info;
    ASSERT_TRUE(first.stub->GetServerInfo(&context, {}, &info).ok());
    EXPECT_EQ(info.role(), "worker");
  }
  ASSERT_TRUE(CreateClusterMap(first, "lab-1").ok());
  EXPECT_EQ(CreateClusterMap(second, "lab-1").error_code(), grpc::StatusCode::ALREADY_EXISTS);
  ASSERT_TRUE(CreateClusterMap(second, "yard").ok());
  {
    grpc::ClientContext context;
    v1::ListMapsResponse maps;
    ASSERT_TRUE(first.stub->ListMaps(&context, {}, &maps).ok());
    ASSERT_EQ(maps.maps_size(), 2);
    EXPECT_EQ(maps.maps(0).name(), "lab-1");
    EXPECT_EQ(maps.maps(1).name(), "yard");
    grpc::ClientContext get_context;
    v1::GetMapRequest get;
    get.set_name("lab-1");
    v1::MapDescription description;
    ASSERT_TRUE(second.stub->GetMap(&get_context, get, &description).ok());
    EXPECT_EQ(description.config().vocabulary(), "default");
    EXPECT_EQ(description.state(), v1::MAP_STATE_AVAILABLE);
  }

  // Ingest through the first worker: every frame a place, ids = the stream's sequences.
  const IngestOutcome ingested = IngestAll(first.stub.get(), "lab-1", Frames("agent-a", 1, 8));
  ASSERT_TRUE(ingested.status.ok()) << ingested.status.error_message();
  ASSERT_EQ(ingested.responses.size(), 8u);
  std::vector<uint32_t> ids;
  for (const v1::IngestResponse& response : ingested.responses) {
    ASSERT_FALSE(response.has_error()) << response.error().message();
    if (response.stored()) ids.push_back(response.place_id());
  }
  ASSERT_FALSE(ids.empty());
  EXPECT_TRUE(std::is_sorted(ids.begin(), ids.end()));
  EXPECT_EQ(std::set<uint32_t>(ids.begin(), ids.end()).size(), ids.size());
  auto js = Js();
  ASSERT_TRUE(js);
  auto info = js->GetStreamInfo(cluster::StreamName("test", "lab-1"));
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->last_sequence, 8u);  // one record per frame, stored or not
  EXPECT_EQ(info->replicas, 3);

  // The same frames again, through the other worker: the same place ids, nothing new stored.
  const IngestOutcome replayed = IngestAll(second.stub.get(), "lab-1", Frames("agent-a", 1, 8));
  ASSERT_TRUE(replayed.status.ok()) << replayed.status.error_message();
  ASSERT_EQ(replayed.responses.size(), 8u);
  for (size_t i = 0; i < 8; ++i) {
    EXPECT_EQ(replayed.responses[i].place_id(), ingested.responses[i].place_id()) << i;
  }
  info = js->GetStreamInfo(cluster::StreamName("test", "lab-1"));
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->last_sequence, 8u);

  // DeleteMap: gone for every worker, its stream too.
  {
    grpc::ClientContext context;
    v1::DeleteMapRequest request;
    request.set_name("lab-1");
    v1::DeleteMapResponse response;
    ASSERT_TRUE(second.stub->DeleteMap(&context, request, &response).ok());
    grpc::ClientContext get_context;
    v1::GetMapRequest get;
    get.set_name("lab-1");
    v1::MapDescription description;
    EXPECT_EQ(first.stub->GetMap(&get_context, get, &description).error_code(),
              grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(js->GetStreamInfo(cluster::StreamName("test", "lab-1")).status().code(),
              StatusCode::kNotFound);
  }

  // Re-created under its name with another configuration: the worker that held a copy of the
  // old map processes frames with the new one, and the new stream starts at 1.
  {
    grpc::ClientContext context;
    v1::CreateMapRequest request;
    request.set_name("lab-1");
    request.mutable_config()->mutable_orb()->set_max_features(300);
    v1::MapDescription response;
    ASSERT_TRUE(second.stub->CreateMap(&context, request, &response).ok());
    EXPECT_EQ(response.config().orb().max_features(), 300);
  }
  const IngestOutcome again = IngestAll(first.stub.get(), "lab-1", Frames("agent-a", 1, 2));
  ASSERT_TRUE(again.status.ok()) << again.status.error_message();
  ASSERT_EQ(again.responses.size(), 2u);
  ASSERT_GT(ingested.responses[0].counts().total(), 300u);  // the old map's budget: 1000
  EXPECT_LE(again.responses[0].counts().total(), 300u);
  EXPECT_GT(again.responses[0].counts().total(), 0u);
  info = js->GetStreamInfo(cluster::StreamName("test", "lab-1"));
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->last_sequence, 2u);
}

// With 2 of 3 NATS servers down nothing is acknowledged (the frame's answer is UNAVAILABLE); with
// one back, ingest resumes, and the refused frame sent again is stored once.
TEST_F(ClusterWorkerTest, NoQuorumNothingAcknowledgedThenResumes) {
  Worker& worker = StartWorker(1, /*metrics=*/true);
  ASSERT_TRUE(worker.stub);
  ASSERT_TRUE(CreateClusterMap(worker, "m").ok());
  const IngestOutcome before = IngestAll(worker.stub.get(), "m", Frames("agent-a", 1, 2));
  ASSERT_TRUE(before.status.ok());
  auto js = Js();
  ASSERT_TRUE(js);
  const std::string stream = cluster::StreamName("test", "m");
  // Down: two nodes that are not the one the worker is connected to, when we can tell (either
  // way no quorum is left).
  engines_->KillNats(1);
  engines_->KillNats(2);
  const IngestOutcome refused = IngestAll(worker.stub.get(), "m", Frames("agent-a", 3, 3));
  ASSERT_EQ(refused.responses.size(), 1u);
  EXPECT_TRUE(refused.responses[0].has_error());
  EXPECT_EQ(refused.responses[0].error().code(), int(grpc::StatusCode::UNAVAILABLE))
      << refused.responses[0].error().message();
  EXPECT_FALSE(refused.responses[0].stored());
  EXPECT_EQ(refused.responses[0].place_id(), 0u);

  ASSERT_TRUE(engines_->RestartNats(1).ok());
  // Quorum is back once the stream has a leader again: waited for (up to 60 s), not left to the
  // frame's deadline (the election outlasted it on a loaded machine).
  const auto leader = engines_->StreamLeader(stream, std::chrono::seconds(60));
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  // Frame 3 again (same id: stored at most once), then a new one.
  const IngestOutcome after = IngestAll(worker.stub.get(), "m", Frames("agent-a", 3, 4));
  ASSERT_TRUE(after.status.ok()) << after.status.error_message();
  ASSERT_EQ(after.responses.size(), 2u);
  for (const auto& response : after.responses) {
    EXPECT_FALSE(response.has_error()) << response.error().message();
  }
  auto info = js->GetStreamInfo(stream);
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->last_sequence, 4u);  // frames 1-4, each once
  // The publishes that got no acknowledgement were retried with the same id, and counted.
  const auto metrics = ParseMetrics(HttpGet(worker.server->metrics_port(), "/metrics"));
  EXPECT_GT(MetricValue(metrics, "placedb_cluster_retries_total", {{"call", "Publish"}}), 0);
  EXPECT_GE(MetricValue(metrics, "placedb_cluster_publish_seconds_count"), 4);
}

// An agent of the kill tests: its map, the worker it starts on and what its first stream got.
struct Agent {
  std::string id, map;
  Worker* worker;
  IngestOutcome first;
};
// 4 agents, 2 per map, one of each map on each worker.
std::vector<Agent> FourAgents(Worker& survivor, Worker& doomed) {
  return {{"a1", "m1", &survivor, {}},
          {"a2", "m1", &doomed, {}},
          {"a3", "m2", &survivor, {}},
          {"a4", "m2", &doomed, {}}};
}

// 2 maps, 4 agents over 2 workers; during ingest the JetStream leader of a map's stream is killed
// and one worker stops with its streams cut. Every agent then sends what was not acknowledged
// again through the surviving worker: every frame ends with a place id, the ids answered twice
// agree, and each map's stream holds each frame once (no duplicates, nothing lost).
TEST_F(ClusterWorkerTest, LeaderAndWorkerKilledDuringIngest) {
  constexpr int kFrames = 400;
  FeatureFrames(84);
  Worker& survivor = StartWorker(1);
  Worker& doomed = StartWorker(2);
  ASSERT_TRUE(survivor.stub && doomed.stub);
  ASSERT_TRUE(CreateClusterMap(survivor, "m1").ok());
  ASSERT_TRUE(CreateClusterMap(survivor, "m2").ok());
  std::vector<Agent> agents = FourAgents(survivor, doomed);
  std::vector<std::thread> threads;
  for (Agent& agent : agents) {
    threads.emplace_back([&agent] {
      std::vector<v1::Observation> frames;
      for (int f = 1; f <= kFrames; ++f) frames.push_back(FeatureObservation(f, agent.id));
      agent.first = IngestAll(agent.worker->stub.get(), agent.map, frames);
    });
  }
  // Mid-ingest: the stream leader of m1 dies, then the second worker.
  std::this_thread::sleep_for(150ms);
  auto leader = engines_->StreamLeader(cluster::StreamName("test", "m1"));
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  engines_->KillNats(*leader);
  std::this_thread::sleep_for(150ms);
  doomed.server->Shutdown();
  for (std::thread& thread : threads) thread.join();
  ASSERT_TRUE(engines_->RestartNats(*leader).ok());

  // Resend what was not acknowledged (no answer, or an error) through the survivor.
  std::map<std::string, std::map<int, uint32_t>> ids;  // agent -> frame -> place id
  int acknowledged_first = 0;
  for (Agent& agent : agents) {
    std::vector<v1::Observation> again;
    for (int f = 1; f <= kFrames; ++f) {
      const auto& responses = agent.first.responses;
      if (size_t(f) <= responses.size() && !responses[size_t(f - 1)].has_error()) {
        // 0: an invalid frame (too few static features): a record, no place.
        ids[agent.id][f] = responses[size_t(f - 1)].place_id();
        ++acknowledged_first;
      }
      // Acknowledged frames too, for some: their ids must come back unchanged.
      if (!ids[agent.id].count(f) || f % 7 == 0) again.push_back(FeatureObservation(f, agent.id));
    }
    const IngestOutcome second = IngestAll(survivor.stub.get(), agent.map, again);
    ASSERT_TRUE(second.status.ok()) << second.status.error_message();
    ASSERT_EQ(second.responses.size(), again.size());
    for (size_t i = 0; i < again.size(); ++i) {
      const int f = int(again[i].sequence());
      ASSERT_FALSE(second.responses[i].has_error()) << second.responses[i].error().message();
      if (ids[agent.id].count(f)) {
        EXPECT_EQ(second.responses[i].place_id(), ids[agent.id][f]) << agent.id << " " << f;
      }
      ids[agent.id][f] = second.responses[i].place_id();
    }
  }
  std::printf("cluster_worker_failover_acknowledged_before_resend %d frames\n", acknowledged_first);
  // Each map's stream: exactly one record per frame of its two agents, place ids all distinct.
  auto js = Js();
  ASSERT_TRUE(js);
  for (const std::string map : {"m1", "m2"}) {
    std::set<uint32_t> distinct;
    size_t places = 0;
    for (const Agent& agent : agents) {
      if (agent.map != map) continue;
      ASSERT_EQ(ids[agent.id].size(), size_t(kFrames));
      for (const auto& [frame, id] : ids[agent.id]) {
        if (id == 0) continue;
        distinct.insert(id);
        ++places;
      }
    }
    ASSERT_GT(places, size_t(kFrames));  // most frames are places
    EXPECT_EQ(distinct.size(), places) << map;
    auto info = js->GetStreamInfo(cluster::StreamName("test", map));
    ASSERT_TRUE(info.ok()) << info.status().ToString();
    EXPECT_EQ(info->messages, uint64_t(2 * kFrames)) << map;
    EXPECT_LE(*distinct.rbegin(), info->last_sequence) << map;

    // The records themselves: one per (agent, frame), and each acknowledged place id is the
    // sequence of the record of that very frame.
    Mutex mutex;
    CondVar done;
    std::map<uint64_t, std::pair<std::string, uint64_t>> records;  // sequence -> agent, frame
    std::vector<std::string> errors;
    auto consumer =
        js->Consume(cluster::StreamName("test", map), cluster::StreamSubject("test", map), 1,
                    [&](uint64_t sequence, std::string_view data) {
                      auto record = cluster::DecodeMapRecord(data, FeatureType::kOrb);
                      MutexLock lock(mutex);
                      if (!record.ok()) {
                        errors.push_back(record.status().ToString());
                      } else {
                        records[sequence] = {record->metadata.agent_id, record->metadata.sequence};
                      }
                      done.NotifyAll();
                    });
    ASSERT_TRUE(consumer.ok()) << consumer.status().ToString();
    {
      MutexLock lock(mutex);
      const auto until = std::chrono::steady_clock::now() + 30s;
      while (records.size() + errors.size() < info->messages && done.WaitUntil(mutex, until)) {
      }
      EXPECT_TRUE(errors.empty()) << errors.front();
      ASSERT_EQ(records.size(), info->messages);
      std::set<std::pair<std::string, uint64_t>> frames;
      for (const auto& [sequence, frame] : records) frames.insert(frame);
      EXPECT_EQ(frames.size(), records.size()) << map << ": a frame stored twice";
      for (const Agent& agent : agents) {
        if (agent.map != map) continue;
        for (const auto& [frame, id] : ids[agent.id]) {
          if (id == 0) continue;
          ASSERT_TRUE(records.count(id)) << id;
          EXPECT_EQ(records[id], std::make_pair(agent.id, uint64_t(frame)));
        }
      }
    }
    (*consumer)->Stop();
  }
}

// The roles as the binary takes them: placedb-server --role shard and --role worker with the
// cluster flags: the worker serves the public API on the cluster (ingest with matches searched
// on the shard process, a place read from it); without the engines' addresses a worker refuses
// to start (status 2).
TEST_F(ClusterWorkerTest, PlacedbServerProcessesWithTheClusterRoles) {
  const std::string binary = PLACEDB_SERVER_BINARY;
  const std::string quiet = " --console-listen off --metrics-listen off > /dev/null 2>&1";
  const int refused = std::system((binary + " --role worker --etcd 127.0.0.1:1" + quiet).c_str());
  ASSERT_TRUE(WIFEXITED(refused));
  EXPECT_EQ(WEXITSTATUS(refused), 2);

  auto join = [](const std::vector<std::string>& items) {
    std::string out;
    for (const std::string& item : items) out += (out.empty() ? "" : ",") + item;
    return out;
  };
  // A shard process first: the worker's ingest below searches it, GetPlace reads it.
  const int internal = FreePort();
  ASSERT_GT(internal, 0);
  cluster::testing::EngineProcess shard;
  const std::string internal_address = "127.0.0.1:" + std::to_string(internal);
  ASSERT_TRUE(shard
                  .Start({binary,
                          "--role",
                          "shard",
                          "--cluster-name",
                          "proc",
                          "--nats",
                          join(engines_->NatsUrls()),
                          "--etcd",
                          join(engines_->EtcdEndpoints()),
                          "--shard-id",
                          "p-shard",
                          "--advertise",
                          internal_address,
                          "--internal-listen",
                          internal_address,
                          "--data-dir",
                          root_ + "/process-shard",
                          "--vocabulary",
                          "default=" + testing::DefaultVocabularyPath(),
                          "--console-listen",
                          "off",
                          "--metrics-listen",
                          "off"},
                         root_ + "/process-shard.log")
                  .ok());
  const int port = FreePort();
  ASSERT_GT(port, 0);
  cluster::testing::EngineProcess process;
  ASSERT_TRUE(
      process
          .Start({binary, "--role", "worker", "--cluster-name", "proc", "--nats",
                  join(engines_->NatsUrls()), "--etcd", join(engines_->EtcdEndpoints()), "--listen",
                  "127.0.0.1:" + std::to_string(port), "--data-dir", root_ + "/process-worker",
                  "--vocabulary", "default=" + testing::DefaultVocabularyPath(), "--console-listen",
                  "off", "--metrics-listen", "off"},
                 root_ + "/process-worker.log")
          .ok());
  Worker worker;
  worker.channel =
      grpc::CreateChannel("127.0.0.1:" + std::to_string(port), grpc::InsecureChannelCredentials());
  ASSERT_TRUE(worker.channel->WaitForConnected(std::chrono::system_clock::now() + 30s));
  worker.stub = v1::PlaceDb::NewStub(worker.channel);
  {
    grpc::ClientContext context;
    context.set_wait_for_ready(true);
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::ServerInfo info;
    ASSERT_TRUE(worker.stub->GetServerInfo(&context, {}, &info).ok());
    EXPECT_EQ(info.role(), "worker");
  }
  // The shard registers within a moment of starting; CreateMap then waits for its placement.
  const auto until = std::chrono::steady_clock::now() + 30s;
  grpc::Status created;
  auto etcd = cluster::EtcdClient::Create({.endpoints = engines_->EtcdEndpoints()});
  ASSERT_TRUE(etcd.ok());
  while (std::chrono::steady_clock::now() < until) {
    auto registered = (*etcd)->Get(cluster::ClusterKeys("proc").Shard("p-shard"));
    if (registered.ok() && !registered->kvs.empty()) break;
    std::this_thread::sleep_for(100ms);
  }
  ASSERT_TRUE(CreateClusterMap(worker, "p").ok());
  v1::MatchOptions matches;
  matches.set_top_k(3);
  const IngestOutcome ingested =
      IngestAll(worker.stub.get(), "p", Frames("agent-p", 1, 3), &matches);
  ASSERT_TRUE(ingested.status.ok()) << ingested.status.error_message();
  ASSERT_EQ(ingested.responses.size(), 3u);
  for (const auto& response : ingested.responses) {
    ASSERT_FALSE(response.has_error()) << response.error().message();
  }
  ASSERT_TRUE(ingested.responses[2].stored());
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::GetPlaceRequest request;
    request.set_map("p");
    request.set_place_id(ingested.responses[2].place_id());
    v1::Place place;
    const grpc::Status read = worker.stub->GetPlace(&context, request, &place);
    ASSERT_TRUE(read.ok()) << read.error_message();
    EXPECT_EQ(place.metadata().agent_id(), "agent-p");
    EXPECT_EQ(place.metadata().sequence(), 3u);
  }
  auto js = Js();
  ASSERT_TRUE(js);
  auto info = js->GetStreamInfo(cluster::StreamName("proc", "p"));
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->last_sequence, 3u);
  process.Kill();
  shard.Kill();
}

// The whole path with shards: 3 shards, 2 workers, 2 maps, 4 agents ingesting with matches
// (searched on a replica that applied the stream's last place) while the JetStream leader of a
// stream, a shard holding a replica and a worker are killed, and queries go on through the other
// worker. Afterwards every acknowledged place is on both live replicas of its map with the same
// record, BoW and features, each frame is one place, the replicas' integrity checks pass, and
// queries were answered before, during and after the kills.
// Issue 29 in cluster mode: one replica learns the map's vocabulary, the worker publishes it to
// the map's stream in parts, and every replica switches at the same record to the same bytes;
// a replica made later from a checkpoint carries it; queries and ingest through a worker that
// had the old vocabulary go on; revert is one more record.
TEST_F(ClusterWorkerTest, ReplicasSwitchToOneLearnedVocabularyAtOneRecord) {
  FeatureFrames(60);
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(3);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& first = StartWorker(1);
  Worker& second = StartWorker(2);
  ASSERT_TRUE(first.stub && second.stub);
  ASSERT_TRUE(CreateClusterMap(first, "learn").ok());
  std::vector<v1::Observation> frames;
  for (int f = 1; f <= 40; ++f) frames.push_back(FeatureObservation(f, "agent-a"));
  const IngestOutcome ingested = IngestAll(first.stub.get(), "learn", frames);
  std::map<int, uint32_t> place_of;  // frame -> place
  ASSERT_NO_FATAL_FAILURE(CollectPlaces(ingested, 1, &place_of));
  ASSERT_GE(place_of.size(), 30u);
  auto js = Js();
  ASSERT_TRUE(js);
  // The live replicas of a map once they applied its stream's end.
  const auto caught_up = [&](size_t want, const std::string& map = "learn") {
    std::vector<std::pair<int, std::shared_ptr<PlaceMap>>> replicas;
    auto info = js->GetStreamInfo(cluster::StreamName("test", map));
    if (!info.ok()) return replicas;
    const auto until = std::chrono::steady_clock::now() + 90s;
    while (std::chrono::steady_clock::now() < until) {
      replicas.clear();
      for (size_t i = 0; i < shards.size(); ++i) {
        if (!shards[i]) continue;
        for (const cluster::ReplicaStatus& replica : shards[i]->Replicas()) {
          if (replica.map != map || replica.applied_sequence < info->last_sequence) continue;
          if (auto opened = shards[i]->Map(map); opened.ok()) {
            replicas.emplace_back(int(i), *opened);
          }
        }
      }
      if (replicas.size() == want) break;
      std::this_thread::sleep_for(50ms);
    }
    return replicas;
  };
  const AnyVocabulary file(vocabulary_);

  // Learned through the other worker (it never held the map's frames).
  v1::MapVocabulary adapted;
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 120s);
    v1::AdaptVocabularyRequest request;
    request.set_name("learn");
    request.set_branching(8);
    request.set_depth(4);
    request.set_max_sample_descriptors(20000);
    const grpc::Status status = second.stub->AdaptVocabulary(&context, request, &adapted);
    ASSERT_TRUE(status.ok()) << status.error_message();
  }
  EXPECT_EQ(adapted.map(), "learn");
  EXPECT_EQ(adapted.generation(), 1u);
  EXPECT_EQ(adapted.current().origin(), "learned");
  EXPECT_EQ(adapted.current().places_offered(), place_of.size());
  EXPECT_EQ(adapted.current().branching(), 8u);
  EXPECT_EQ(adapted.previous().checksum(), file.checksum_hex());
  auto replicas = caught_up(2);
  ASSERT_EQ(replicas.size(), 2u);
  const std::string learned_bytes = replicas[0].second->vocabulary().Serialize();
  for (const auto& [shard, map] : replicas) {
    EXPECT_EQ(map->vocabulary().checksum_hex(), adapted.current().checksum()) << shard;
    EXPECT_EQ(map->vocabulary().Serialize(), learned_bytes) << shard;
    EXPECT_EQ(map->info().vocabulary.generation, 1u) << shard;
    EXPECT_EQ(map->info().vocabulary.places_reindexed, place_of.size()) << shard;
  }
  EXPECT_EQ(replicas[0].second->applied_sequence(), replicas[1].second->applied_sequence());

  // GetMap through the first worker shows it; a query through it (whose copy of the map still
  // had the file's vocabulary) finds each frame's place, and so do frames ingested after.
  const auto get_map = [&](Worker& worker) {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name("learn");
    v1::MapDescription description;
    EXPECT_TRUE(worker.stub->GetMap(&context, request, &description).ok());
    return description;
  };
  EXPECT_EQ(get_map(first).vocabulary().current().checksum(), adapted.current().checksum());
  EXPECT_EQ(get_map(first).vocabulary_checksum(), adapted.current().checksum());
  const auto expect_found = [&](Worker& worker, int frame, uint32_t place) {
    v1::QueryRequest request;
    request.set_map("learn");
    *request.mutable_observation() = FeatureObservation(frame, "q");
    request.mutable_options()->set_top_k(3);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::QueryResponse response;
    const grpc::Status status = worker.stub->Query(&context, request, &response);
    ASSERT_TRUE(status.ok()) << status.error_message();
    ASSERT_GT(response.matches_size(), 0) << "frame " << frame;
    EXPECT_EQ(response.matches(0).place_id(), place) << "frame " << frame;
  };
  for (const int frame : {1, 13, 27, 40}) {
    if (place_of.count(frame)) expect_found(first, frame, place_of[frame]);
  }
  frames.clear();
  for (int f = 41; f <= 50; ++f) frames.push_back(FeatureObservation(f, "agent-a"));
  const IngestOutcome after = IngestAll(first.stub.get(), "learn", frames);
  ASSERT_TRUE(after.status.ok()) << after.status.error_message();
  for (size_t i = 0; i < after.responses.size(); ++i) {
    ASSERT_FALSE(after.responses[i].has_error()) << after.responses[i].error().message();
    if (after.responses[i].stored()) place_of[41 + int(i)] = after.responses[i].place_id();
  }
  for (const int frame : {41, 45, 50}) {
    if (place_of.count(frame)) expect_found(second, frame, place_of[frame]);
  }

  // A replica made now restores a peer's checkpoint: the learned vocabulary comes with it.
  replicas = caught_up(2);
  ASSERT_EQ(replicas.size(), 2u);
  const int doomed = replicas[0].first;
  replicas.clear();
  shards[size_t(doomed)].reset();
  replicas = caught_up(2);  // the coordinator replaces it on the third shard (after 2 s)
  ASSERT_EQ(replicas.size(), 2u);
  bool restored = false;
  for (const auto& [shard, map] : replicas) {
    EXPECT_EQ(map->vocabulary().Serialize(), learned_bytes) << shard;
    EXPECT_EQ(map->info().vocabulary.generation, 1u) << shard;
    for (const cluster::ReplicaStatus& status : shards[size_t(shard)]->Replicas()) {
      if (status.map == "learn" && !status.restored_from.empty()) restored = true;
    }
  }
  EXPECT_TRUE(restored) << "the new replica started from a checkpoint";
  expect_found(first, 45, place_of[45]);

  // Back to the file's vocabulary: one record, every replica (the new one too).
  v1::MapVocabulary reverted;
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 120s);
    v1::RevertVocabularyRequest request;
    request.set_name("learn");
    const grpc::Status status = first.stub->RevertVocabulary(&context, request, &reverted);
    ASSERT_TRUE(status.ok()) << status.error_message();
  }
  EXPECT_EQ(reverted.generation(), 2u);
  EXPECT_EQ(reverted.current().checksum(), file.checksum_hex());
  replicas = caught_up(2);
  ASSERT_EQ(replicas.size(), 2u);
  for (const auto& [shard, map] : replicas) {
    EXPECT_EQ(map->vocabulary().checksum(), file.checksum()) << shard;
    EXPECT_EQ(map->info().vocabulary.generation, 2u) << shard;
  }
  expect_found(second, 13, place_of[13]);

  // Refusals: an unknown map; a map too small to learn from, unchanged.
  ASSERT_TRUE(CreateClusterMap(first, "tiny").ok());
  ASSERT_TRUE(IngestAll(first.stub.get(), "tiny", {FeatureObservation(1, "agent-a")}).status.ok());
  ASSERT_EQ(caught_up(2, "tiny").size(), 2u);
  for (const std::string name : {"nowhere", "tiny"}) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 60s);
    v1::AdaptVocabularyRequest request;
    request.set_name(name);
    v1::MapVocabulary response;
    const grpc::Status status = first.stub->AdaptVocabulary(&context, request, &response);
    EXPECT_EQ(status.error_code(),
              name == "tiny" ? grpc::StatusCode::FAILED_PRECONDITION : grpc::StatusCode::NOT_FOUND)
        << name << ": " << status.error_message();
  }
  EXPECT_EQ(get_map(first).vocabulary().generation(), 2u);
  // The policy is a single server's: refused here rather than stored and never run.
  v1::MapConfig policy;
  policy.mutable_vocabulary_policy()->set_adapt_after_descriptors(5000);
  const grpc::Status refused = CreateClusterMap(first, "grows", policy);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << refused.error_message();
  EXPECT_NE(refused.error_message().find("vocabulary_policy"), std::string::npos);
}

TEST_F(ClusterWorkerTest, EndToEndWithShardsAndKills) {
  constexpr int kFrames = 120;
  FeatureFrames(84);
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(3);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& survivor = StartWorker(1);
  Worker& doomed = StartWorker(2);
  ASSERT_TRUE(survivor.stub && doomed.stub);
  ASSERT_TRUE(CreateClusterMap(survivor, "m1").ok());
  {
    // m2 counts query hits (issue 16): the queries below publish CountObservation records.
    grpc::ClientContext context;
    v1::CreateMapRequest request;
    request.set_name("m2");
    request.mutable_config()->mutable_dynamics()->set_count_query_hits_above(0.001);
    v1::MapDescription response;
    ASSERT_TRUE(survivor.stub->CreateMap(&context, request, &response).ok());
  }

  // Queries through the survivor all along (read-your-writes off: any replica).
  std::atomic<bool> querying{true};
  std::atomic<int> answered{0}, failed{0};
  std::thread queries([&] {
    int frame = 1;
    while (querying) {
      v1::QueryRequest request;
      request.set_map("m2");
      *request.mutable_observation() = FeatureObservation(frame++ % 84 + 1, "q");
      request.mutable_options()->set_top_k(3);
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + 2s);
      v1::QueryResponse response;
      if (survivor.stub->Query(&context, request, &response).ok()) {
        ++answered;
      } else {
        ++failed;
      }
      std::this_thread::sleep_for(50ms);
    }
  });

  // An assertion that returns early stops the queries and joins every thread (the agents end
  // on their own: their frames are bounded).
  std::vector<std::thread> threads;
  ::placedb::testing::JoinOnExit join_on_exit([&querying] { querying = false; });
  join_on_exit.Add(queries);
  join_on_exit.Add(threads);

  std::vector<Agent> agents = FourAgents(survivor, doomed);
  v1::MatchOptions matches;
  matches.set_top_k(3);
  threads.reserve(agents.size());
  for (Agent& agent : agents) {
    threads.emplace_back([&agent, &matches] {
      std::vector<v1::Observation> frames;
      for (int f = 1; f <= kFrames; ++f) frames.push_back(FeatureObservation(f, agent.id));
      agent.first = IngestAll(agent.worker->stub.get(), agent.map, frames, &matches);
    });
  }
  // The kills once m1's stream holds a quarter of its frames: mid-ingest, whatever the load.
  {
    auto watcher = Js();
    ASSERT_TRUE(watcher);
    const auto until = std::chrono::steady_clock::now() + 60s;
    while (std::chrono::steady_clock::now() < until) {
      auto info = watcher->GetStreamInfo(cluster::StreamName("test", "m1"));
      if (info.ok() && info->last_sequence >= uint64_t(kFrames / 2)) break;
      std::this_thread::sleep_for(10ms);
    }
  }
  auto leader = engines_->StreamLeader(cluster::StreamName("test", "m1"));
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  engines_->KillNats(*leader);
  // A shard holding a replica of m1 dies (destroyed: its lease expires, its replicas move).
  const int killed = ShardHolding(shards, "m1");
  ASSERT_GE(killed, 0);
  shards[size_t(killed)].reset();
  std::this_thread::sleep_for(300ms);
  doomed.server->Shutdown();
  for (std::thread& thread : threads) thread.join();
  const int answered_during = answered;
  ASSERT_TRUE(engines_->RestartNats(*leader).ok());

  // What was not acknowledged goes again through the survivor (with matches: searched too).
  std::map<std::string, std::map<int, uint32_t>> ids;
  int acknowledged_first = 0;
  for (Agent& agent : agents) {
    std::vector<v1::Observation> again;
    for (int f = 1; f <= kFrames; ++f) {
      const auto& responses = agent.first.responses;
      if (size_t(f) <= responses.size() && !responses[size_t(f - 1)].has_error()) {
        ids[agent.id][f] = responses[size_t(f - 1)].place_id();
        ++acknowledged_first;
      } else {
        again.push_back(FeatureObservation(f, agent.id));
      }
    }
    if (again.empty()) continue;
    const IngestOutcome second = IngestAll(survivor.stub.get(), agent.map, again, &matches);
    ASSERT_TRUE(second.status.ok()) << second.status.error_message();
    ASSERT_EQ(second.responses.size(), again.size());
    for (size_t i = 0; i < again.size(); ++i) {
      ASSERT_FALSE(second.responses[i].has_error()) << second.responses[i].error().message();
      ids[agent.id][int(again[i].sequence())] = second.responses[i].place_id();
    }
  }
  std::printf("cluster_e2e_acknowledged_before_resend %d frames\n", acknowledged_first);

  // Both live replicas of each map catch up (the killed shard's replica replaced, epoch + 1).
  auto js = Js();
  ASSERT_TRUE(js);
  for (const std::string map : {"m1", "m2"}) {
    auto info = js->GetStreamInfo(cluster::StreamName("test", map));
    ASSERT_TRUE(info.ok());
    std::vector<std::shared_ptr<PlaceMap>> replicas;
    const auto until = std::chrono::steady_clock::now() + 60s;
    while (std::chrono::steady_clock::now() < until) {
      replicas.clear();
      for (const auto& shard : shards) {
        if (!shard) continue;
        for (const cluster::ReplicaStatus& replica : shard->Replicas()) {
          if (replica.map != map || replica.applied_sequence < info->last_sequence) continue;
          auto opened = shard->Map(map);
          if (opened.ok()) replicas.push_back(*opened);
        }
      }
      if (replicas.size() == 2) break;
      std::this_thread::sleep_for(100ms);
    }
    ASSERT_EQ(replicas.size(), 2u) << map << ": two replicas caught up";
    std::set<uint32_t> distinct;
    size_t places = 0;
    for (const Agent& agent : agents) {
      if (agent.map != map) continue;
      ASSERT_EQ(ids[agent.id].size(), size_t(kFrames));
      for (const auto& [frame, id] : ids[agent.id]) {
        if (id == 0) continue;
        ++places;
        distinct.insert(id);
        auto a = replicas[0]->GetPlace(id);
        auto b = replicas[1]->GetPlace(id);
        ASSERT_TRUE(a.ok() && b.ok()) << map << " place " << id;
        EXPECT_EQ(a->record.metadata.agent_id, agent.id);
        EXPECT_EQ(a->record.metadata.sequence, uint64_t(frame));
        EXPECT_EQ(EncodePlaceRecord(a->record), EncodePlaceRecord(b->record)) << id;
        EXPECT_EQ(EncodeBow(a->payload.bow), EncodeBow(b->payload.bow)) << id;
        EXPECT_EQ(EncodeLocalFeatures(a->payload.features, a->payload.direct),
                  EncodeLocalFeatures(b->payload.features, b->payload.direct))
            << id;
      }
    }
    EXPECT_EQ(distinct.size(), places) << map << ": a place id answered twice";
    if (map == "m2") {
      // Query hits counted: records beyond the frames', applied by both replicas.
      EXPECT_GT(info->messages, uint64_t(2 * kFrames));
    }
    for (const auto& replica : replicas) {
      EXPECT_EQ(replica->Stats().database.places, places) << map << ": duplicates or losses";
      EXPECT_TRUE(replica->VerifyIntegrity().ok()) << map;
    }
  }
  // GetMap's places: a replica's count.
  {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name("m1");
    v1::MapDescription description;
    ASSERT_TRUE(survivor.stub->GetMap(&context, request, &description).ok());
    size_t places = 0;
    for (const char* agent : {"a1", "a2"}) {
      for (const auto& [frame, id] : ids[agent]) places += id != 0;
    }
    EXPECT_EQ(description.stats().places(), places);
  }
  // DeletePlace: published, then gone from the replicas; NOT_FOUND for an id that is no place.
  {
    const uint32_t id = ids["a1"][1] ? ids["a1"][1] : ids["a1"][2];
    ASSERT_GT(id, 0u);
    grpc::ClientContext context;
    v1::DeletePlaceRequest request;
    request.set_map("m1");
    request.set_place_id(id);
    v1::DeletePlaceResponse response;
    const grpc::Status deleted = survivor.stub->DeletePlace(&context, request, &response);
    ASSERT_TRUE(deleted.ok()) << deleted.error_message();
    grpc::StatusCode code = grpc::StatusCode::OK;
    for (const auto until = std::chrono::steady_clock::now() + 20s;
         code != grpc::StatusCode::NOT_FOUND && std::chrono::steady_clock::now() < until;) {
      grpc::ClientContext get_context;
      v1::GetPlaceRequest get;
      get.set_map("m1");
      get.set_place_id(id);
      v1::Place place;
      code = survivor.stub->GetPlace(&get_context, get, &place).error_code();
      if (code != grpc::StatusCode::NOT_FOUND) std::this_thread::sleep_for(50ms);
    }
    EXPECT_EQ(code, grpc::StatusCode::NOT_FOUND);
    grpc::ClientContext again_context;
    EXPECT_EQ(survivor.stub->DeletePlace(&again_context, request, &response).error_code(),
              grpc::StatusCode::NOT_FOUND);
  }
  // Read-your-writes: a query asking for a replica that applied a1's last place gets one.
  {
    const uint32_t last = ids["a1"][kFrames];
    ASSERT_GT(last, 0u);
    v1::QueryRequest request;
    request.set_map("m1");
    request.set_min_sequence(last);
    *request.mutable_observation() = FeatureObservation(kFrames, "q");
    request.mutable_options()->set_top_k(5);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 10s);
    v1::QueryResponse response;
    const grpc::Status status = survivor.stub->Query(&context, request, &response);
    ASSERT_TRUE(status.ok()) << status.error_message();
    EXPECT_GE(response.sequence(), last);
    ASSERT_GT(response.matches_size(), 0);
  }
  querying = false;
  queries.join();
  std::printf("cluster_e2e_queries_answered %d queries\ncluster_e2e_queries_failed %d queries\n",
              answered.load(), failed.load());
  EXPECT_GT(answered_during, 0);
  EXPECT_GT(answered.load(), answered_during);  // and after the kills
  workers_.clear();                             // before the shards they call
  shards.clear();
}

// A map whose loop-closure working memory is bounded (20 places): the detector's long-term
// memory, its retrieval and the loop verification all read places (on a worker: from replicas).
v1::MapConfig LoopMapConfig() {
  v1::MapConfig config;
  config.mutable_loop_closure()->set_max_working_memory(20);
  return config;
}

// Frames first..last of `agent` (precomputed features; frames past 84 revisit the start) in one
// loop-closure Ingest stream. At frames 31-32 and 71-72 the agent stands still: they repeat the
// features of frames 30 and 70 (rehearsal merges them).
IngestOutcome LoopIngest(v1::PlaceDb::Stub* stub, const std::string& map, const std::string& agent,
                         int first, int last) {
  v1::IngestHeader header;
  header.set_map(map);
  header.set_loop_closure(true);
  std::vector<v1::Observation> frames;
  for (int f = first; f <= last; ++f) {
    frames.push_back(FeatureObservation(f, agent));
    for (const int still : {30, 70}) {
      if (f == still + 1 || f == still + 2) {
        *frames.back().mutable_features() = FeatureObservation(still, agent).features();
      }
    }
  }
  return IngestWithHeader(stub, header, frames);
}

// One frame's loop-closure answer with places named by the frame that stored them (ids differ
// between a single server and a cluster, whose ids are stream sequences). -1: an unknown place.
struct LoopDecision {
  std::string error;
  bool stored = false, merged = false, loop = false, rejected = false;
  int place = 0, loop_target = 0, rejected_target = 0, best = 0;
  uint32_t candidates = 0, retrieved = 0, transferred = 0, replayed = 0;
  int inliers = 0;
  double loop_posterior = 0, best_posterior = 0;
};

std::string Show(const LoopDecision& d) {
  char text[400];
  std::snprintf(text, sizeof(text),
                "error='%s' stored=%d merged=%d place=%d loop=%d->%d (%.6f, %d inliers) "
                "rejected=%d->%d best=%d (%.6f) candidates=%u retrieved=%u transferred=%u "
                "replayed=%u",
                d.error.c_str(), d.stored, d.merged, d.place, d.loop, d.loop_target,
                d.loop_posterior, d.inliers, d.rejected, d.rejected_target, d.best,
                d.best_posterior, d.candidates, d.retrieved, d.transferred, d.replayed);
  return text;
}

// `frame_of` (place id -> frame that stored it) carries over the calls of one agent's run.
std::vector<LoopDecision> Decisions(const IngestOutcome& outcome, int first_frame,
                                    std::map<uint32_t, int>* frame_of) {
  auto frame = [&](uint32_t id) {
    if (id == 0) return 0;
    auto it = frame_of->find(id);
    return it == frame_of->end() ? -1 : it->second;
  };
  std::vector<LoopDecision> out;
  for (size_t i = 0; i < outcome.responses.size(); ++i) {
    const v1::IngestResponse& r = outcome.responses[i];
    LoopDecision d;
    d.error = r.has_error() ? r.error().message() : "";
    d.stored = r.stored();
    if (d.stored) (*frame_of)[r.place_id()] = first_frame + int(i);
    const v1::LoopClosure& lc = r.loop_closure();
    d.merged = lc.merged();
    d.place = frame(lc.place_id());
    d.loop = lc.loop_found();
    d.loop_target = frame(lc.loop_place_id());
    d.loop_posterior = lc.loop_posterior();
    d.inliers = lc.loop_inliers();
    d.rejected = lc.loop_rejected();
    d.rejected_target = frame(lc.rejected_place_id());
    d.best = frame(lc.best_place_id());
    d.best_posterior = lc.best_posterior();
    d.candidates = lc.candidates();
    d.retrieved = lc.retrieved();
    d.transferred = lc.transferred();
    d.replayed = lc.replayed();
    out.push_back(d);
  }
  return out;
}

// Frame by frame, the cluster decided as the single server did.
void ExpectSameDecisions(const std::vector<LoopDecision>& single,
                         const std::vector<LoopDecision>& clustered, int first_frame) {
  ASSERT_EQ(single.size(), clustered.size());
  for (size_t i = 0; i < single.size(); ++i) {
    const LoopDecision& a = single[i];
    const LoopDecision& b = clustered[i];
    const bool same = a.error == b.error && a.stored == b.stored && a.merged == b.merged &&
                      a.place == b.place && a.loop == b.loop && a.loop_target == b.loop_target &&
                      a.rejected == b.rejected && a.rejected_target == b.rejected_target &&
                      a.best == b.best && a.candidates == b.candidates &&
                      a.retrieved == b.retrieved && a.transferred == b.transferred &&
                      a.replayed == b.replayed && a.inliers == b.inliers &&
                      std::abs(a.loop_posterior - b.loop_posterior) < 1e-9 &&
                      std::abs(a.best_posterior - b.best_posterior) < 1e-9;
    EXPECT_TRUE(same) << "frame " << first_frame + int(i) << "\n  single:  " << Show(a)
                      << "\n  cluster: " << Show(b);
  }
}

struct LoopTotals {
  int stored = 0, merged = 0, loops = 0, retrieved = 0, verified = 0;
};
LoopTotals Totals(const std::vector<LoopDecision>& decisions) {
  LoopTotals t;
  for (const LoopDecision& d : decisions) {
    t.stored += d.stored;
    t.merged += d.merged;
    t.loops += d.loop;
    t.retrieved += int(d.retrieved);
    t.verified += d.loop && d.inliers > 0;
  }
  return t;
}

// Loop closure through a worker (the detector on the worker, the places on 2 shard replicas)
// decides every frame as a single server fed the same frames does: stored or merged, the loop
// and its target, the best hypothesis, working/long-term memory traffic, the verification's
// inliers. The sequence (84 RTAB-Map frames, then its first 26 again) closes loops, merges frames
// and retrieves places from long-term memory (working memory bounded at 20).
TEST_F(ClusterWorkerTest, LoopClosureOnAWorkerDecidesAsASingleServer) {
  constexpr int kFrames = 110;
  FeatureFrames(84);
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("loop", LoopMapConfig());
  const IngestOutcome single = LoopIngest(stub_.get(), "loop", "rover", 1, kFrames);
  ASSERT_TRUE(single.status.ok()) << single.status.error_message();
  ASSERT_EQ(single.responses.size(), size_t(kFrames));
  StopServer();

  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(2);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& worker = StartWorker(1);
  ASSERT_TRUE(worker.stub);
  ASSERT_TRUE(CreateClusterMap(worker, "loop", LoopMapConfig()).ok());
  const IngestOutcome clustered = LoopIngest(worker.stub.get(), "loop", "rover", 1, kFrames);
  ASSERT_TRUE(clustered.status.ok()) << clustered.status.error_message();
  ASSERT_EQ(clustered.responses.size(), size_t(kFrames));

  std::map<uint32_t, int> single_frames, cluster_frames;
  const auto a = Decisions(single, 1, &single_frames);
  const auto b = Decisions(clustered, 1, &cluster_frames);
  ExpectSameDecisions(a, b, 1);
  // The run exercises what the worker reads from replicas: retrieval, verified loops; and
  // rehearsal (merged frames publish CountObservation records, not places).
  const LoopTotals t = Totals(a);
  std::printf("cluster_loop_frames %d stored %d merged %d loops %d retrieved %d\n", kFrames,
              t.stored, t.merged, t.loops, t.retrieved);
  EXPECT_GT(t.loops, 0);
  EXPECT_EQ(t.verified, t.loops);
  EXPECT_GT(t.retrieved, 0);
  EXPECT_GT(t.merged, 0);
  // One record per frame (a place, a merged frame's observation, or an invalid frame), and one
  // more per accepted loop: its constraint for the replicas' loop-closure logs (issue 32).
  auto js = Js();
  ASSERT_TRUE(js);
  auto info = js->GetStreamInfo(cluster::StreamName("test", "loop"));
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->last_sequence, uint64_t(kFrames + t.loops));
  workers_.clear();  // before the shards it calls
  shards.clear();
}

// The agent's stream moves to another worker (the first one stops), then to a third, then back
// to the second (which still had a detector for the agent from its earlier stream): each time
// the first frame's new detector replays every place of the agent from a replica (as a single
// server replays its own after a restart), and the frames decide as a single server restarted
// at the same frames, among them loops closed on places stored before the first move. Then a
// replay of many places, for the figure in docs/cluster.md.
TEST_F(ClusterWorkerTest, LoopClosureFailoverReplaysTheAgentsPlacesFromAReplica) {
  constexpr int kBulk = 2000;
  const std::vector<std::pair<int, int>> segments = {{1, 60}, {61, 90}, {91, 110}, {111, 130}};
  FeatureFrames(84);
  std::vector<IngestOutcome> single;
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("loop", LoopMapConfig());
  for (const auto& [first, last] : segments) {
    if (!single.empty()) {
      StopServer();
      ASSERT_NO_FATAL_FAILURE(StartServer(Config()));  // the same data directory: a restart
    }
    single.push_back(LoopIngest(stub_.get(), "loop", "rover", first, last));
    ASSERT_TRUE(single.back().status.ok()) << single.back().status.error_message();
  }
  StopServer();

  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(2);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& a = StartWorker(1);
  Worker& b = StartWorker(2);
  Worker& c = StartWorker(3);
  ASSERT_TRUE(a.stub && b.stub && c.stub);
  ASSERT_TRUE(CreateClusterMap(a, "loop", LoopMapConfig()).ok());
  std::vector<IngestOutcome> clustered;
  const std::vector<Worker*> route = {&a, &b, &c, &b};
  for (size_t k = 0; k < segments.size(); ++k) {
    clustered.push_back(
        LoopIngest(route[k]->stub.get(), "loop", "rover", segments[k].first, segments[k].second));
    ASSERT_TRUE(clustered.back().status.ok()) << clustered.back().status.error_message();
    ASSERT_EQ(clustered.back().responses.size(),
              size_t(segments[k].second - segments[k].first + 1));
    if (k == 0) a.server->Shutdown();  // the agent's detector is gone with it
  }

  std::map<uint32_t, int> single_frames, cluster_frames;
  std::set<uint32_t> stored;         // the agent's places so far (cluster ids)
  std::set<uint32_t> stored_before;  // ... before the first move
  int loops_on_earlier = 0;
  for (size_t k = 0; k < segments.size(); ++k) {
    ExpectSameDecisions(Decisions(single[k], segments[k].first, &single_frames),
                        Decisions(clustered[k], segments[k].first, &cluster_frames),
                        segments[k].first);
    const auto& responses = clustered[k].responses;
    // The segment's first frame replayed every place stored before it (none for the first).
    EXPECT_EQ(responses[0].loop_closure().replayed(), stored.size()) << "segment " << k;
    for (const v1::IngestResponse& r : responses) {
      if (r.stored()) stored.insert(r.place_id());
      const v1::LoopClosure& lc = r.loop_closure();
      if (k > 0) loops_on_earlier += lc.loop_found() && stored_before.count(lc.loop_place_id());
    }
    if (k == 0) stored_before = stored;
  }
  ASSERT_FALSE(stored_before.empty());
  EXPECT_GT(loops_on_earlier, 0);

  // Replay time for N places: `bulk` stores kBulk places without loop closure, then its first
  // loop-closure frame on the second worker replays them all (from a replica, paged).
  std::vector<v1::Observation> frames;
  for (int f = 1; f <= kBulk; ++f) frames.push_back(FeatureObservation(f, "bulk"));
  const IngestOutcome bulk = IngestAll(b.stub.get(), "loop", frames);
  ASSERT_TRUE(bulk.status.ok()) << bulk.status.error_message();
  size_t bulk_places = 0;
  for (const v1::IngestResponse& r : bulk.responses) bulk_places += r.stored();
  // The replay reads from a replica that applied the stream's end: wait for both, so that the
  // figure is the replay's, not the appliers' catching up.
  {
    auto js = Js();
    ASSERT_TRUE(js);
    auto info = js->GetStreamInfo(cluster::StreamName("test", "loop"));
    ASSERT_TRUE(info.ok()) << info.status().ToString();
    const auto until = std::chrono::steady_clock::now() + 60s;
    size_t caught_up = 0;
    while (caught_up < 2 && std::chrono::steady_clock::now() < until) {
      caught_up = 0;
      for (const auto& shard : shards) {
        for (const cluster::ReplicaStatus& replica : shard->Replicas()) {
          caught_up += replica.map == "loop" && replica.applied_sequence >= info->last_sequence;
        }
      }
      if (caught_up < 2) std::this_thread::sleep_for(50ms);
    }
    ASSERT_EQ(caught_up, 2u);
  }
  // The replaying frame is its stream's first (its total_ms is its own, not queued behind
  // another's); the next frame of the stream keeps the detector. For comparison: the first frame
  // of an agent without places (the listing finds none).
  const IngestOutcome replay = LoopIngest(b.stub.get(), "loop", "bulk", kBulk + 1, kBulk + 2);
  const IngestOutcome none = LoopIngest(b.stub.get(), "loop", "newcomer", 1, 1);
  ASSERT_TRUE(replay.status.ok() && none.status.ok()) << replay.status.error_message();
  ASSERT_EQ(replay.responses.size(), 2u);
  ASSERT_EQ(none.responses.size(), 1u);
  EXPECT_EQ(replay.responses[0].loop_closure().replayed(), bulk_places);
  EXPECT_EQ(replay.responses[1].loop_closure().replayed(), 0u);
  EXPECT_EQ(none.responses[0].loop_closure().replayed(), 0u);
  std::printf(
      "cluster_loop_failover replayed %u places: first frame after the move %.1f ms\n"
      "cluster_loop_replay %zu places: the replaying frame %.1f ms; an agent without places: "
      "%.1f ms\n",
      clustered[1].responses[0].loop_closure().replayed(),
      clustered[1].responses[0].timings().total_ms(), bulk_places,
      replay.responses[0].timings().total_ms(), none.responses[0].timings().total_ms());
  workers_.clear();
  shards.clear();
}

// A frame resent after a failover whose first answer was lost (docs/cluster.md): its message id
// de-duplicates to the record its first publish left, and the answer is that record's even when
// this worker processes the frame otherwise. The first worker's records are published here with
// the frame's message id (<agent>/<sequence>), then the frame goes through a worker:
// - first merged by loop closure (a CountObservation), now stored by the new detector: merged
//   into the same place, and the next frame's detector holds no place for it;
// - first invalid (Algorithm 1 warming up), now valid: not stored, the first rejection;
// - first stored, now invalid: stored, the same place.
TEST_F(ClusterWorkerTest, ResentFrameIsAnsweredByTheStreamsRecord) {
  FeatureFrames(40);
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(2);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& worker = StartWorker(1);
  ASSERT_TRUE(worker.stub);
  ASSERT_TRUE(CreateClusterMap(worker, "resent", LoopMapConfig()).ok());
  auto js = Js();
  ASSERT_TRUE(js);
  const std::string subject = cluster::StreamSubject("test", "resent");
  auto last_sequence = [&]() -> uint64_t {
    auto info = js->GetStreamInfo(cluster::StreamName("test", "resent"));
    EXPECT_TRUE(info.ok()) << info.status().ToString();
    return info.ok() ? info->last_sequence : 0;
  };
  // Until both replicas are open and have applied the whole stream: a new detector's replay
  // reads the rover's places from one, and a replica still opening refuses.
  auto await_replicas = [&]() -> bool {
    const uint64_t last = last_sequence();
    const auto until = std::chrono::steady_clock::now() + 60s;
    while (std::chrono::steady_clock::now() < until) {
      size_t caught_up = 0;
      for (const auto& shard : shards) {
        for (const cluster::ReplicaStatus& replica : shard->Replicas()) {
          caught_up += replica.map == "resent" && replica.applied_sequence >= last;
        }
      }
      if (caught_up == 2) return true;
      std::this_thread::sleep_for(50ms);
    }
    return false;
  };
  // What the first worker published for frame `sequence` of the rover; its stream sequence.
  auto first_publish = [&](const std::string& record, int sequence) -> uint64_t {
    auto ack = js->Publish(subject, record, "rover/" + std::to_string(sequence), 10s);
    EXPECT_TRUE(ack.ok()) << ack.status().ToString();
    EXPECT_TRUE(!ack.ok() || !ack->duplicate);
    return ack.ok() ? ack->sequence : 0;
  };
  auto metadata = [](int sequence) {
    PlaceMetadata out;
    out.agent_id = "rover";
    out.sequence = uint64_t(sequence);
    out.timestamp_ns = int64_t(sequence) * 100'000'000;
    return out;
  };

  // The rover's places so far: frames 1-3.
  const IngestOutcome earlier =
      IngestAll(worker.stub.get(), "resent",
                {FeatureObservation(1, "rover"), FeatureObservation(2, "rover"),
                 FeatureObservation(3, "rover")});
  ASSERT_TRUE(earlier.status.ok()) << earlier.status.error_message();
  ASSERT_EQ(earlier.responses.size(), 3u);
  std::set<uint32_t> places;
  for (const v1::IngestResponse& r : earlier.responses) {
    ASSERT_TRUE(r.stored()) << r.ShortDebugString();
    places.insert(r.place_id());
  }
  const uint32_t last_place = earlier.responses.back().place_id();

  // 1. Frame 10 was merged into the rover's last place by the first worker's detector. The new
  // detector (a replay of frames 1-3) stores it: a frame unlike frame 3. Frame 11 repeats its
  // features (the rover stands still): rehearsal would merge it into whatever place the detector
  // holds for frame 10.
  const uint64_t merged_record = first_publish(
      cluster::EncodeCountObservation(last_place, ProcessedFrame(), metadata(10)), 10);
  ASSERT_GT(merged_record, 0u);
  ASSERT_TRUE(await_replicas());
  {
    v1::IngestHeader header;
    header.set_map("resent");
    header.set_loop_closure(true);
    std::vector<v1::Observation> frames = {FeatureObservation(10, "rover"),
                                           FeatureObservation(10, "rover")};
    frames[1].set_sequence(11);
    frames[1].set_timestamp_ns(11 * 100'000'000);
    const IngestOutcome resent = IngestWithHeader(worker.stub.get(), header, frames);
    ASSERT_TRUE(resent.status.ok()) << resent.status.error_message();
    ASSERT_EQ(resent.responses.size(), 2u);
    const v1::IngestResponse& r = resent.responses[0];
    EXPECT_FALSE(r.has_error()) << r.error().message();
    EXPECT_EQ(r.loop_closure().replayed(), 3u);
    EXPECT_FALSE(r.stored()) << "the stream holds frame 10 as merged, not as a place";
    EXPECT_TRUE(r.loop_closure().merged());
    EXPECT_EQ(r.place_id(), last_place);
    EXPECT_EQ(r.loop_closure().place_id(), last_place);
    EXPECT_NE(r.place_id(), uint32_t(merged_record));
    // Frame 11: the detector was rebuilt from the rover's places (no place for frame 10), so it
    // is stored as a new place or merged into one of them, never into the CountObservation.
    const v1::IngestResponse& next = resent.responses[1];
    EXPECT_FALSE(next.has_error()) << next.error().message();
    std::printf("frame 11 after the rebuilt detector: %s place %u\n",
                next.stored() ? "stored as" : "merged into", next.place_id());
    EXPECT_EQ(next.loop_closure().replayed(), 3u);
    if (next.stored()) {
      EXPECT_GT(next.place_id(), merged_record);
    } else {
      EXPECT_TRUE(next.loop_closure().merged());
      EXPECT_TRUE(places.count(next.place_id())) << next.ShortDebugString();
    }
  }

  // 2. Frame 20 was invalid at first (e.g. depth filtered away while Algorithm 1 warmed up);
  // resent, it is valid.
  ProcessedFrame invalid;
  invalid.rejection = "invalid place representation: 3 static descriptors (first publish)";
  const uint64_t invalid_record =
      first_publish(cluster::EncodeInvalidFrame(invalid, metadata(20)), 20);
  ASSERT_GT(invalid_record, 0u);
  {
    const uint64_t before = last_sequence();
    const IngestOutcome resent =
        IngestAll(worker.stub.get(), "resent", {FeatureObservation(20, "rover")});
    ASSERT_TRUE(resent.status.ok()) << resent.status.error_message();
    ASSERT_EQ(resent.responses.size(), 1u);
    const v1::IngestResponse& r = resent.responses[0];
    EXPECT_FALSE(r.has_error()) << r.error().message();
    EXPECT_FALSE(r.stored()) << "place " << r.place_id() << " would be record " << invalid_record
                             << ", an invalid frame";
    EXPECT_EQ(r.place_id(), 0u);
    EXPECT_EQ(r.rejection(), invalid.rejection);
    EXPECT_EQ(last_sequence(), before) << "the resent frame added a record";
  }
  // The same in a loop-closure stream (its new detector decides on frame 21 first).
  const uint64_t invalid_loop_record =
      first_publish(cluster::EncodeInvalidFrame(invalid, metadata(21)), 21);
  ASSERT_GT(invalid_loop_record, 0u);
  ASSERT_TRUE(await_replicas());
  {
    const uint64_t before = last_sequence();
    v1::IngestHeader header;
    header.set_map("resent");
    header.set_loop_closure(true);
    const IngestOutcome resent =
        IngestWithHeader(worker.stub.get(), header, {FeatureObservation(21, "rover")});
    ASSERT_TRUE(resent.status.ok()) << resent.status.error_message();
    ASSERT_EQ(resent.responses.size(), 1u);
    const v1::IngestResponse& r = resent.responses[0];
    EXPECT_FALSE(r.has_error()) << r.error().message();
    EXPECT_FALSE(r.stored()) << "place " << r.place_id() << " would be record "
                             << invalid_loop_record << ", an invalid frame";
    EXPECT_FALSE(r.loop_closure().merged());
    EXPECT_EQ(r.place_id(), 0u);
    EXPECT_EQ(r.rejection(), invalid.rejection);
    EXPECT_EQ(last_sequence(), before) << "the resent frame added a record";
  }

  // 3. Frame 30 was stored at first; resent, it is invalid (3 keypoints).
  const IngestOutcome stored =
      IngestAll(worker.stub.get(), "resent", {FeatureObservation(30, "rover")});
  ASSERT_TRUE(stored.status.ok()) << stored.status.error_message();
  ASSERT_EQ(stored.responses.size(), 1u);
  ASSERT_TRUE(stored.responses[0].stored());
  {
    v1::Observation few = FeatureObservation(30, "rover");
    v1::Features* features = few.mutable_features();
    features->mutable_keypoints()->DeleteSubrange(3, features->keypoints_size() - 3);
    features->mutable_descriptors()->resize(3 * 32);
    const uint64_t before = last_sequence();
    const IngestOutcome resent = IngestAll(worker.stub.get(), "resent", {few});
    ASSERT_TRUE(resent.status.ok()) << resent.status.error_message();
    ASSERT_EQ(resent.responses.size(), 1u);
    const v1::IngestResponse& r = resent.responses[0];
    EXPECT_FALSE(r.has_error()) << r.error().message();
    EXPECT_TRUE(r.stored()) << "the stream holds frame 30 as place "
                            << stored.responses[0].place_id() << "; answered "
                            << r.ShortDebugString();
    EXPECT_EQ(r.place_id(), stored.responses[0].place_id());
    EXPECT_EQ(last_sequence(), before) << "the resent frame added a record";
  }
  workers_.clear();  // before the shards it calls
  shards.clear();
}

// Issue 32: the loop-closure log in cluster mode. Two agents ingest with matches through one
// worker while a consumer follows WatchLoopClosures through another; that worker is shut down
// mid-stream (the consumer resumes through the survivor from its last sequence + 1) and a shard
// holding a replica is killed (the survivor's relay moves to another replica). Every constraint
// the Ingest answers announced is delivered exactly once, in order.
TEST_F(ClusterWorkerTest, LoopClosureLogSurvivesAWorkerAndAReplicaKilled) {
  FeatureFrames(84);
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(3);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& survivor = StartWorker(1);
  Worker& doomed = StartWorker(2);
  ASSERT_TRUE(survivor.stub && doomed.stub);
  v1::MapConfig config;
  config.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
  ASSERT_TRUE(CreateClusterMap(survivor, "loops", config).ok());

  // The consumer: follows through a worker from its last sequence + 1 until the stream ends (the
  // worker goes, or the test cancels `context`). `received` counts constraints for the test's
  // waits; `consumed` is read once the consumer's thread is joined.
  std::vector<v1::LoopConstraint> consumed;
  std::atomic<size_t> received{0};
  std::atomic<bool> live{false};  // the current stream said it caught up
  auto follow = [&](Worker& worker, grpc::ClientContext* context) {
    v1::WatchLoopClosuresRequest request;
    request.set_map("loops");
    request.set_follow(true);
    request.set_from_sequence(consumed.empty() ? 1 : consumed.back().sequence() + 1);
    context->set_deadline(std::chrono::system_clock::now() + 180s);
    auto reader = worker.stub->WatchLoopClosures(context, request);
    v1::LoopConstraint message;
    while (reader->Read(&message)) {
      if (message.sequence() == 0) {
        live = true;
        continue;
      }
      consumed.push_back(message);
      ++received;
    }
    return reader->Finish();
  };
  // Waits (at most 60 s: a hang, not a timing) until `done`.
  auto await = [](const std::function<bool()>& done) {
    const auto until = std::chrono::steady_clock::now() + 60s;
    while (!done() && std::chrono::steady_clock::now() < until) {
      std::this_thread::sleep_for(10ms);
    }
    return done();
  };

  std::map<std::string, std::vector<v1::Observation>> sent;
  for (int f = 1; f <= 84; ++f) {
    const std::string agent = f <= 42 ? "a" : "b";  // b comes back to a's start
    sent[agent].push_back(FeatureObservation(f, agent));
  }
  std::map<std::string, IngestOutcome> outcomes = {{"a", {}}, {"b", {}}};
  v1::MatchOptions matches;
  matches.set_top_k(3);
  grpc::ClientContext first_context, second_context;
  grpc::Status first_stream, second_stream;
  std::thread consumer, agent_a, agent_b;
  ::placedb::testing::JoinOnExit join([&] {
    first_context.TryCancel();
    second_context.TryCancel();
  });
  join.Add(consumer);
  join.Add(agent_a);
  join.Add(agent_b);
  consumer = std::thread([&] { first_stream = follow(doomed, &first_context); });
  ASSERT_TRUE(await([&] { return live.load(); })) << "the follower never caught up";
  agent_a = std::thread(
      [&] { outcomes["a"] = IngestAll(survivor.stub.get(), "loops", sent["a"], &matches); });
  agent_b = std::thread(
      [&] { outcomes["b"] = IngestAll(survivor.stub.get(), "loops", sent["b"], &matches); });

  // The consumer's worker goes once it has relayed a few constraints.
  ASSERT_TRUE(await([&] { return received >= 5; }));
  doomed.server->Shutdown();
  consumer.join();
  EXPECT_NE(first_stream.error_code(), grpc::StatusCode::OK);
  const size_t before_worker_went = received;

  // Resumed through the survivor; then a shard holding a replica of the map dies.
  live = false;
  consumer = std::thread([&] { second_stream = follow(survivor, &second_context); });
  ASSERT_TRUE(await([&] { return live.load() || received > before_worker_went; }));
  const int killed = ShardHolding(shards, "loops");
  ASSERT_GE(killed, 0);
  shards[size_t(killed)].reset();
  agent_a.join();
  agent_b.join();

  // What the answers announced: each verified match, keyed (agent, sequence, place, matched). A
  // frame the shard's death failed (a search cut off) goes again, as its robot would send it.
  using Key = std::tuple<std::string, uint64_t, uint32_t, uint32_t>;
  std::multiset<Key> announced;
  for (const std::string agent : {"a", "b"}) {
    ASSERT_TRUE(outcomes[agent].status.ok())
        << agent << ": " << outcomes[agent].status.error_message();
    auto& responses = outcomes[agent].responses;
    ASSERT_EQ(responses.size(), sent[agent].size());
    for (size_t i = 0; i < responses.size(); ++i) {
      if (!responses[i].has_error()) continue;
      const IngestOutcome again =
          IngestAll(survivor.stub.get(), "loops", {sent[agent][i]}, &matches);
      ASSERT_TRUE(again.status.ok() && again.responses.size() == 1u);
      responses[i] = again.responses[0];
    }
    for (size_t i = 0; i < responses.size(); ++i) {
      ASSERT_FALSE(responses[i].has_error()) << responses[i].error().message();
      for (const v1::Match& match : responses[i].matches()) {
        if (!match.verified()) continue;
        announced.insert(
            {agent, sent[agent][i].sequence(), responses[i].place_id(), match.place_id()});
      }
    }
  }
  ASSERT_FALSE(announced.empty());
  // Every one arrives (through whichever replica is relayed now), then the consumer stops.
  EXPECT_TRUE(await([&] { return received >= announced.size(); }))
      << received << " of " << announced.size() << " constraints";
  second_context.TryCancel();
  consumer.join();
  EXPECT_EQ(second_stream.error_code(), grpc::StatusCode::CANCELLED)
      << second_stream.error_message();

  std::multiset<Key> logged;
  size_t inter = 0;
  for (size_t i = 0; i < consumed.size(); ++i) {
    const v1::LoopConstraint& c = consumed[i];
    EXPECT_EQ(c.sequence(), i + 1) << "in order, none missing, none twice";
    logged.insert({c.query().agent_id(), c.query().sequence(), c.query_place_id(), c.place_id()});
    inter += c.query().agent_id() != c.place().agent_id();
  }
  EXPECT_EQ(logged, announced);
  EXPECT_GT(inter, 0u);
  std::printf("cluster_loop_log %zu constraints (%zu inter-agent, %zu before the worker went)\n",
              consumed.size(), inter, before_worker_went);
  workers_.clear();
  shards.clear();
}

// Issue 35: ScrubMap and RecoverMap through a worker cover every live replica. A corrupt SST
// block on one replica is reported (the other replica's clean report does not hide it) and
// RecoverMap rebuilds that replica from the other's checkpoint; then a replica that does not
// open (its MANIFEST gone) likewise. Nothing acknowledged is lost: the places are found again.
TEST_F(ClusterWorkerTest, ScrubAndRecoverEveryReplicaThroughAWorker) {
  namespace fs = std::filesystem;
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(2);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& worker = StartWorker(1);
  ASSERT_TRUE(worker.stub);
  ASSERT_TRUE(CreateClusterMap(worker, "lab").ok());
  const IngestOutcome ingested = IngestAll(worker.stub.get(), "lab", Frames("agent-a", 1, 24));
  std::map<int, uint32_t> place_of;  // frame -> place
  ASSERT_NO_FATAL_FAILURE(CollectPlaces(ingested, 1, &place_of));
  const uint64_t stored = place_of.size();
  ASSERT_GT(stored, 10u);
  auto js = Js();
  ASSERT_TRUE(js);
  // Both replicas open and caught up with the stream's end.
  const auto caught_up = [&] {
    auto info = js->GetStreamInfo(cluster::StreamName("test", "lab"));
    if (!info.ok()) return false;
    const auto until = std::chrono::steady_clock::now() + 90s;
    while (std::chrono::steady_clock::now() < until) {
      int ready = 0;
      for (const auto& shard : shards) {
        for (const cluster::ReplicaStatus& replica : shard->Replicas()) {
          ready += replica.map == "lab" && replica.state == "applying" &&
                   replica.applied_sequence >= info->last_sequence;
        }
      }
      if (ready == 2) return true;
      std::this_thread::sleep_for(50ms);
    }
    return false;
  };
  ASSERT_TRUE(caught_up());
  // A rebuilt replica copies the peer whose applied sequence etcd has (reported every second).
  cluster::EtcdOptions etcd_options;
  etcd_options.endpoints = engines_->EtcdEndpoints();
  auto etcd = cluster::EtcdClient::Create(etcd_options);
  ASSERT_TRUE(etcd.ok()) << etcd.status().ToString();
  const auto applied_reported = [&](const std::string& shard) {
    const auto until = std::chrono::steady_clock::now() + 30s;
    while (std::chrono::steady_clock::now() < until) {
      auto read = (*etcd)->Get("/placedb/test/applied/lab/" + shard);
      if (read.ok() && !read->kvs.empty() && read->kvs[0].value != "0") return true;
      std::this_thread::sleep_for(50ms);
    }
    return false;
  };
  // The worker's scrub, once it reaches both replicas (a restarted shard registers again).
  const auto scrub = [&](v1::ScrubReport* report) {
    const auto until = std::chrono::steady_clock::now() + 60s;
    grpc::Status status;
    do {
      report->Clear();
      grpc::ClientContext context;
      v1::ScrubMapRequest request;
      request.set_name("lab");
      status = worker.stub->ScrubMap(&context, request, report);
      bool both = status.ok() && report->replicas_size() == 2;
      for (const auto& replica : report->replicas()) {
        both = both && replica.error().find("UNAVAILABLE") == std::string::npos &&
               replica.error().find("IO_ERROR") == std::string::npos;
      }
      if (both) return status;
      std::this_thread::sleep_for(100ms);
    } while (std::chrono::steady_clock::now() < until);
    return status;
  };
  const auto recover = [&](bool accept, v1::RecoverMapResponse* response,
                           const std::string& name = "lab") {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 120s);
    v1::RecoverMapRequest request;
    request.set_name(name);
    request.set_accept_data_loss(accept);
    return worker.stub->RecoverMap(&context, request, response);
  };
  const auto expect_found = [&](int frame) {
    EXPECT_EQ(TopPlace(worker.stub.get(), "lab", frame), place_of[frame]) << "frame " << frame;
  };

  v1::ScrubReport report;
  ASSERT_TRUE(scrub(&report).ok());
  EXPECT_TRUE(report.clean());
  ASSERT_EQ(report.replicas_size(), 2);
  EXPECT_EQ(report.places_checked(), 2 * stored);
  for (const auto& replica : report.replicas()) {
    EXPECT_TRUE(replica.report().clean()) << replica.shard();
    EXPECT_EQ(replica.report().places_checked(), stored) << replica.shard();
  }
  v1::RecoverMapResponse recovered;
  EXPECT_EQ(recover(false, &recovered).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(recover(true, &recovered).error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_EQ(recover(true, &recovered, "nowhere").error_code(), grpc::StatusCode::NOT_FOUND);

  // A corrupt block in the largest SST file (the features) of shard-0's copy, written while the
  // shard is down (its close flushed every place to SST files); it opens again (features are
  // not read at open).
  const std::string map_dir = root_ + "/shard-0/maps/lab";
  shards[0].reset();
  const std::string garbled = testing::GarbleLargestSst(map_dir);  // the features' file
  ASSERT_FALSE(garbled.empty());
  const std::string sst = "maps/lab/" + garbled;
  shards[0] = StartShard(0);
  ASSERT_TRUE(shards[0]);
  ASSERT_TRUE(caught_up());
  ASSERT_TRUE(applied_reported("shard-1"));
  ASSERT_TRUE(scrub(&report).ok());
  EXPECT_FALSE(report.clean());
  ASSERT_EQ(report.replicas_size(), 2);
  bool reported = false;
  for (const auto& replica : report.replicas()) {
    EXPECT_EQ(replica.report().clean(), replica.shard() == "shard-1") << replica.shard();
    if (replica.shard() != "shard-0") continue;
    ASSERT_EQ(replica.report().damaged_files_size(), 1);
    EXPECT_EQ(replica.report().damaged_files(0).file(), sst);
  }
  for (const auto& file : report.damaged_files()) {
    reported = reported || (file.file() == sst && file.reason().starts_with("shard shard-0: "));
  }
  EXPECT_TRUE(reported) << report.DebugString();

  ASSERT_TRUE(recover(true, &recovered).ok());
  ASSERT_EQ(recovered.replicas_size(), 2);
  for (const auto& replica : recovered.replicas()) {
    EXPECT_TRUE(replica.error().empty()) << replica.shard() << ": " << replica.error();
    EXPECT_EQ(replica.damaged(), replica.shard() == "shard-0") << replica.shard();
    if (replica.shard() != "shard-0") continue;
    EXPECT_TRUE(replica.rebuilt());
    EXPECT_EQ(replica.restored_from(), "shard-1");
    EXPECT_NE(replica.found().find(sst), std::string::npos) << replica.found();
  }
  EXPECT_EQ(recovered.accepted().places_lost(), 0u);
  EXPECT_NE(recovered.accepted().reason().find("shard shard-0"), std::string::npos)
      << recovered.accepted().reason();
  EXPECT_EQ(recovered.map().name(), "lab");
  ASSERT_TRUE(caught_up());
  ASSERT_TRUE(scrub(&report).ok());
  EXPECT_TRUE(report.clean()) << report.DebugString();
  EXPECT_EQ(report.places_checked(), 2 * stored);
  for (const int frame : {1, 12, 24}) {
    if (place_of.count(frame)) expect_found(frame);
  }

  // shard-1's copy loses its MANIFEST: it no longer opens (damaged). The scrub says so (DATA_LOSS
  // for that replica), RecoverMap rebuilds it from shard-0's.
  shards[1].reset();
  for (const auto& entry : fs::directory_iterator(root_ + "/shard-1/maps/lab")) {
    if (entry.path().filename().string().starts_with("MANIFEST-")) fs::remove(entry.path());
  }
  shards[1] = StartShard(1);
  ASSERT_TRUE(shards[1]);
  const auto until = std::chrono::steady_clock::now() + 60s;
  bool damaged = false;
  while (!damaged && std::chrono::steady_clock::now() < until) {
    for (const cluster::ReplicaStatus& replica : shards[1]->Replicas()) {
      damaged = damaged || (replica.map == "lab" && replica.state.starts_with("damaged: "));
    }
    if (!damaged) std::this_thread::sleep_for(50ms);
  }
  ASSERT_TRUE(damaged);
  ASSERT_TRUE(applied_reported("shard-0"));
  ASSERT_TRUE(scrub(&report).ok());
  EXPECT_FALSE(report.clean());
  for (const auto& replica : report.replicas()) {
    if (replica.shard() == "shard-1") {
      EXPECT_NE(replica.error().find("maps/lab/CURRENT"), std::string::npos) << replica.error();
    } else {
      EXPECT_TRUE(replica.report().clean());
    }
  }
  ASSERT_TRUE(recover(true, &recovered).ok());
  for (const auto& replica : recovered.replicas()) {
    EXPECT_EQ(replica.rebuilt(), replica.shard() == "shard-1") << replica.shard();
    if (replica.shard() == "shard-1") {
      EXPECT_EQ(replica.restored_from(), "shard-0");
    }
  }
  ASSERT_TRUE(caught_up());
  ASSERT_TRUE(scrub(&report).ok());
  EXPECT_TRUE(report.clean()) << report.DebugString();
  // Ingest goes on with ids after the old places, on both replicas.
  const IngestOutcome more = IngestAll(worker.stub.get(), "lab", Frames("agent-a", 25, 30));
  ASSERT_TRUE(more.status.ok()) << more.status.error_message();
  ASSERT_TRUE(caught_up());
  for (const auto& shard : shards) {
    auto map = shard->Map("lab");
    ASSERT_TRUE(map.ok());
    EXPECT_GE((*map)->database()->Stats().places, stored) << shard->shard_id();
  }
  expect_found(12);
}

// Issue 35: snapshots through workers live in the cluster: made through one worker (the most
// applied replica's checkpoint, verified), listed and downloaded through another (the same
// bytes, SHA-256 checked when read back), deleted, uploaded again, and restored as a new map
// whose replicas start from the archive and whose stream continues after the snapshot's records:
// the same places under the same ids, new ones above them, and a replacement replica comes up.
// Bad input is refused as a single server refuses it, nothing stored. Prints what it costs.
TEST_F(ClusterWorkerTest, SnapshotsThroughAnyWorkerAndRestoreAsANewMap) {
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(3);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  Worker& a = StartWorker(1);
  Worker& b = StartWorker(2);
  ASSERT_TRUE(a.stub && b.stub);
  ASSERT_TRUE(CreateClusterMap(a, "orig").ok());
  const IngestOutcome ingested = IngestAll(a.stub.get(), "orig", Frames("agent-a", 1, 24));
  std::map<int, uint32_t> place_of;  // frame -> place
  ASSERT_NO_FATAL_FAILURE(CollectPlaces(ingested, 1, &place_of));
  ASSERT_GT(place_of.size(), 10u);
  auto js = Js();
  ASSERT_TRUE(js);
  // The live replicas of `map` that applied its stream's end (`want` of them).
  const auto caught_up = [&](const std::string& map, size_t want) {
    const auto until = std::chrono::steady_clock::now() + 90s;
    while (std::chrono::steady_clock::now() < until) {
      auto info = js->GetStreamInfo(cluster::StreamName("test", map));
      size_t ready = 0;
      for (const auto& shard : shards) {
        if (!shard) continue;
        for (const cluster::ReplicaStatus& replica : shard->Replicas()) {
          ready += info.ok() && replica.map == map && replica.state == "applying" &&
                   replica.applied_sequence >= info->last_sequence;
        }
      }
      if (ready == want) return true;
      std::this_thread::sleep_for(50ms);
    }
    return false;
  };
  ASSERT_TRUE(caught_up("orig", 2));
  const auto seconds_since = [](std::chrono::steady_clock::time_point start) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  };
  const auto list = [](Worker& worker) {
    grpc::ClientContext context;
    v1::ListSnapshotsResponse response;
    EXPECT_TRUE(worker.stub->ListSnapshots(&context, {}, &response).ok());
    std::vector<std::string> ids;
    for (const auto& snapshot : response.snapshots()) ids.push_back(snapshot.id());
    return ids;
  };
  const auto download = [](Worker& worker, const std::string& id, std::string* archive) {
    v1::DownloadSnapshotRequest request;
    request.set_id(id);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 60s);
    auto reader = worker.stub->DownloadSnapshot(&context, request);
    v1::SnapshotChunk chunk;
    uint64_t announced = 0;
    archive->clear();
    for (bool first = true; reader->Read(&chunk); first = false) {
      if (first) announced = chunk.archive_bytes();
      archive->append(chunk.data());
    }
    grpc::Status status = reader->Finish();
    if (status.ok()) {
      EXPECT_EQ(announced, archive->size());
    }
    return status;
  };
  const auto upload = [](Worker& worker, const std::string& archive, v1::Snapshot* response) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 60s);
    auto writer = worker.stub->UploadSnapshot(&context, response);
    for (size_t offset = 0; offset < archive.size(); offset += 64 << 10) {
      v1::SnapshotChunk chunk;
      if (offset == 0) chunk.set_archive_bytes(archive.size());
      chunk.set_data(archive.substr(offset, 64 << 10));
      if (!writer->Write(chunk)) break;
    }
    writer->WritesDone();
    return writer->Finish();
  };
  const auto restore = [](Worker& worker, const std::string& id, const std::string& name,
                          v1::MapDescription* map) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 120s);
    v1::RestoreSnapshotRequest request;
    request.set_id(id);
    request.set_new_map(name);
    return worker.stub->RestoreSnapshot(&context, request, map);
  };
  const auto top_place = [](Worker& worker, const std::string& map, int frame) {
    return TopPlace(worker.stub.get(), map, frame);
  };

  // Made through worker a.
  auto clock = std::chrono::steady_clock::now();
  v1::Snapshot made;
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 120s);
    v1::CreateSnapshotRequest request;
    request.set_map("orig");
    const grpc::Status status = a.stub->CreateSnapshot(&context, request, &made);
    ASSERT_TRUE(status.ok()) << status.error_message();
  }
  const double create_s = seconds_since(clock);
  EXPECT_EQ(made.map(), "orig");
  EXPECT_EQ(made.places(), place_of.size());
  // Listed and downloaded through worker b: the same bytes as through a.
  EXPECT_EQ(list(b), std::vector<std::string>{made.id()});
  std::string archive, again;
  clock = std::chrono::steady_clock::now();
  grpc::Status status = download(b, made.id(), &archive);
  const double download_s = seconds_since(clock);
  ASSERT_TRUE(status.ok()) << status.error_message();
  ASSERT_TRUE(download(a, made.id(), &again).ok());
  EXPECT_EQ(archive, again);
  ASSERT_GT(archive.size(), 512u << 10) << "the archive must span several stored chunks";
  {
    // What is read back is checked against the manifest: a manifest whose SHA-256 the stored
    // bytes do not have makes the download DATA_LOSS (after its bytes: the client discards them).
    cluster::EtcdOptions etcd_options;
    etcd_options.endpoints = engines_->EtcdEndpoints();
    auto etcd = cluster::EtcdClient::Create(etcd_options);
    ASSERT_TRUE(etcd.ok()) << etcd.status().ToString();
    const std::string key = "/placedb/test/snapshots/" + made.id();
    auto stored = (*etcd)->Get(key);
    ASSERT_TRUE(stored.ok() && stored->kvs.size() == 1);
    auto manifest = cluster::DecodeSnapshotManifest(stored->kvs[0].value);
    ASSERT_TRUE(manifest.ok()) << manifest.status().ToString();
    cluster::SnapshotManifest wrong = *manifest;
    wrong.sha256 = std::string(64, '0');
    ASSERT_TRUE((*etcd)->Put(key, cluster::EncodeSnapshotManifest(wrong)).ok());
    EXPECT_EQ(download(b, made.id(), &again).error_code(), grpc::StatusCode::DATA_LOSS);
    ASSERT_TRUE((*etcd)->Put(key, stored->kvs[0].value).ok());
    ASSERT_TRUE(download(b, made.id(), &again).ok());
    EXPECT_EQ(archive, again);
  }

  // Bad input: a single server's codes, nothing stored.
  v1::MapDescription description;
  EXPECT_EQ(restore(a, "absent-1", "x", &description).error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(restore(a, made.id(), "orig", &description).error_code(),
            grpc::StatusCode::ALREADY_EXISTS);
  EXPECT_EQ(restore(a, made.id(), "../bad", &description).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(download(a, "absent-1", &again).error_code(), grpc::StatusCode::NOT_FOUND);
  {
    grpc::ClientContext context;
    v1::DeleteSnapshotRequest request;
    request.set_id("absent-1");
    v1::DeleteSnapshotResponse response;
    EXPECT_EQ(b.stub->DeleteSnapshot(&context, request, &response).error_code(),
              grpc::StatusCode::NOT_FOUND);
  }
  std::string corrupt = archive;
  corrupt[corrupt.size() / 2] ^= 0x5a;
  v1::Snapshot refused;
  status = upload(a, corrupt, &refused);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::DATA_LOSS) << status.error_message();
  EXPECT_EQ(list(a), std::vector<std::string>{made.id()});
  {
    grpc::ClientContext context;
    v1::ListMapsResponse maps;
    ASSERT_TRUE(a.stub->ListMaps(&context, {}, &maps).ok());
    EXPECT_EQ(maps.maps_size(), 1);
  }

  // Restored through b as made (its base from the replica's checkpoint, its configuration the
  // map's): the same places under the same ids; the map stays when the snapshot goes.
  status = restore(b, made.id(), "copy0", &description);
  ASSERT_TRUE(status.ok()) << status.error_message();
  ASSERT_TRUE(caught_up("copy0", 2));
  for (const auto& [frame, place] : place_of) {
    if (frame % 7 == 2) {
      EXPECT_EQ(top_place(a, "copy0", frame), place) << "frame " << frame;
    }
  }

  // Deleted through b; uploaded through b again; restored through a.
  {
    grpc::ClientContext context;
    v1::DeleteSnapshotRequest request;
    request.set_id(made.id());
    v1::DeleteSnapshotResponse response;
    ASSERT_TRUE(b.stub->DeleteSnapshot(&context, request, &response).ok());
  }
  EXPECT_TRUE(list(a).empty());
  EXPECT_EQ(download(a, made.id(), &again).error_code(), grpc::StatusCode::NOT_FOUND);
  v1::Snapshot uploaded;
  clock = std::chrono::steady_clock::now();
  status = upload(b, archive, &uploaded);
  const double upload_s = seconds_since(clock);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(uploaded.places(), made.places());
  EXPECT_EQ(list(a), std::vector<std::string>{uploaded.id()});
  clock = std::chrono::steady_clock::now();
  status = restore(a, uploaded.id(), "copy", &description);
  const double restore_s = seconds_since(clock);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(description.name(), "copy");
  ASSERT_TRUE(caught_up("copy", 2));
  auto copy_stream = js->GetStreamInfo(cluster::StreamName("test", "copy"));
  auto orig_stream = js->GetStreamInfo(cluster::StreamName("test", "orig"));
  ASSERT_TRUE(copy_stream.ok() && orig_stream.ok());
  EXPECT_EQ(copy_stream->first_sequence, orig_stream->last_sequence + 1);

  // The same places under the same ids, through either worker.
  for (const auto& [frame, place] : place_of) {
    if (frame % 5 != 1) continue;
    EXPECT_EQ(top_place(b, "copy", frame), place) << "frame " << frame;
    v1::GetPlaceRequest request;
    request.set_map("copy");
    request.set_place_id(place);
    grpc::ClientContext context;
    v1::Place got;
    EXPECT_TRUE(a.stub->GetPlace(&context, request, &got).ok()) << place;
  }
  // New places continue above the snapshot's.
  const IngestOutcome more = IngestAll(b.stub.get(), "copy", Frames("agent-b", 30, 34));
  ASSERT_TRUE(more.status.ok()) << more.status.error_message();
  uint32_t first_new = 0;
  for (const auto& response : more.responses) {
    ASSERT_FALSE(response.has_error()) << response.error().message();
    if (response.stored() && first_new == 0) first_new = response.place_id();
  }
  ASSERT_NE(first_new, 0u);
  EXPECT_GT(first_new, orig_stream->last_sequence);
  ASSERT_TRUE(caught_up("copy", 2));

  // A replica replaced (its shard gone): the new one comes up from the live one's checkpoint.
  const int doomed = ShardHolding(shards, "copy");
  ASSERT_GE(doomed, 0);
  shards[size_t(doomed)].reset();
  ASSERT_TRUE(caught_up("copy", 2));
  bool from_peer = false;  // the replacement restored a live replica's checkpoint
  for (const auto& shard : shards) {
    if (!shard) continue;
    for (const cluster::ReplicaStatus& replica : shard->Replicas()) {
      from_peer =
          from_peer || (replica.map == "copy" && replica.restored_from.starts_with("shard-"));
    }
  }
  EXPECT_TRUE(from_peer);
  EXPECT_EQ(top_place(a, "copy", place_of.begin()->first), place_of.begin()->second);
  std::printf(
      "cluster snapshot of %zu places: create %.2f s, archive %zu bytes, download %.2f s, "
      "upload %.2f s, restore %.2f s\n",
      place_of.size(), create_s, archive.size(), download_s, upload_s, restore_s);
}

}  // namespace
}  // namespace placedb::server_testing

namespace placedb::server_testing {
namespace {

// bases/<map> round-trips (the manifest and the map's create revision); malformed is CORRUPTION;
// the key is not under snapshots/ (ListSnapshots never sees a base).
TEST(CompactionBaseTest, BaseRecordRoundTripsAndIsNoSnapshot) {
  cluster::MapBase base;
  base.create_revision = 42;
  base.manifest.info.id = "base:lab";
  base.manifest.info.map = "lab";
  base.manifest.info.created_unix_ms = 7;
  base.manifest.base = 640;
  base.manifest.config_json = R"({"vocabulary":"default"})";
  base.manifest.archive_bytes = 1234;
  base.manifest.sha256 = std::string(64, 'a');
  base.manifest.subject = "placedb.test.snapshots.62.1";
  base.manifest.first_sequence = 9;
  base.manifest.chunks = 1;
  auto decoded = cluster::DecodeMapBase(cluster::EncodeMapBase(base));
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->create_revision, 42);
  EXPECT_EQ(decoded->manifest.base, 640u);
  EXPECT_EQ(decoded->manifest.subject, base.manifest.subject);
  EXPECT_EQ(decoded->manifest.sha256, base.manifest.sha256);
  EXPECT_EQ(cluster::DecodeMapBase("{\"manifest\": {}}").status().code(), StatusCode::kCorruption);
  EXPECT_EQ(cluster::DecodeMapBase("{\"create_revision\": 1, \"manifest\": {}}").status().code(),
            StatusCode::kCorruption);
  const cluster::ClusterKeys keys("test");
  EXPECT_EQ(keys.Base("lab"), "/placedb/test/bases/lab");
  EXPECT_NE(keys.Base("lab").rfind(keys.Snapshot(""), 0), 0u);
}

// Issue 35, compaction: the coordinating worker makes a replica's checkpoint the stream's base
// and purges the stream below it; a replica that was down across two compactions resumes from
// the base (its applier finds the gap, nothing skipped), a replacement replica starts from the
// base or a newer checkpoint and applies only the tail; every acknowledged place stays, under
// its id, on every replica; snapshots do not list the base.
TEST_F(ClusterWorkerTest, CompactionMakesABaseAndReplicasCatchUpFromItAndTheTail) {
  std::vector<std::unique_ptr<cluster::Shard>> shards = StartShards(2);
  for (const auto& shard : shards) ASSERT_TRUE(shard);
  compact_after_records_ = 0;  // worker 1: no compaction
  Worker& first = StartWorker(1);
  ASSERT_TRUE(first.stub);
  ASSERT_TRUE(CreateClusterMap(first, "lab").ok());
  std::map<int, uint32_t> place_of;  // frame -> place
  const auto ingest = [&](Worker& worker, int from, int to) {
    const IngestOutcome ingested = IngestAll(worker.stub.get(), "lab", Frames("agent-a", from, to));
    ASSERT_NO_FATAL_FAILURE(CollectPlaces(ingested, from, &place_of));
  };
  ingest(first, 1, 24);
  ASSERT_GT(place_of.size(), 10u);
  auto js = Js();
  ASSERT_TRUE(js);
  const std::string stream = cluster::StreamName("test", "lab");
  // Polls `done` until it holds or `limit` passes.
  const auto await = [](const std::function<bool()>& done, std::chrono::seconds limit) {
    const auto until = std::chrono::steady_clock::now() + limit;
    while (std::chrono::steady_clock::now() < until) {
      if (done()) return true;
      std::this_thread::sleep_for(50ms);
    }
    return done();
  };
  const auto replica_of = [](cluster::Shard& shard) -> std::optional<cluster::ReplicaStatus> {
    for (const cluster::ReplicaStatus& replica : shard.Replicas()) {
      if (replica.map == "lab") return replica;
    }
    return std::nullopt;
  };
  const auto caught_up = [&](cluster::Shard& shard) {
    auto info = js->GetStreamInfo(stream);
    auto replica = replica_of(shard);
    return info.ok() && replica && replica->state == "applying" &&
           replica->applied_sequence >= info->last_sequence;
  };
  ASSERT_TRUE(await([&] { return caught_up(*shards[0]) && caught_up(*shards[1]); }, 90s));
  auto before = js->GetStreamInfo(stream);
  ASSERT_TRUE(before.ok()) << before.status().ToString();
  EXPECT_EQ(before->first_sequence, 1u);
  const uint64_t down_at = replica_of(*shards[1])->applied_sequence;

  // shard-1 goes down (2 shards: nobody replaces it); a worker that compacts beyond 6 records
  // takes over as coordinator.
  shards[1].reset();
  compact_after_records_ = 6;
  Worker& second = StartWorker(2, /*metrics=*/true);
  ASSERT_TRUE(second.stub);
  workers_.front()->server.reset();  // its coordinator's lease revoked: the second takes over
  cluster::EtcdOptions etcd_options;
  etcd_options.endpoints = engines_->EtcdEndpoints();
  etcd_options.tls = ClientTls();
  auto etcd = cluster::EtcdClient::Create(etcd_options);
  ASSERT_TRUE(etcd.ok()) << etcd.status().ToString();
  cluster::SnapshotArchives archives(js.get(), etcd->get(), "test", 0);
  const auto base_at_least = [&](uint64_t sequence) {
    auto base = archives.GetBase("lab");
    return base.ok() && base->has_value() && (**base).manifest.base >= sequence;
  };
  const auto stream_from = [&](uint64_t sequence) {
    auto info = js->GetStreamInfo(stream);
    return info.ok() && info->first_sequence >= sequence;
  };
  const auto started = std::chrono::steady_clock::now();
  ASSERT_TRUE(await([&] { return base_at_least(before->last_sequence); }, 60s));
  ASSERT_TRUE(await([&] { return stream_from(before->last_sequence + 1); }, 30s));
  std::printf("compaction: first base at record %llu and purge after %.2f s\n",
              static_cast<unsigned long long>(before->last_sequence),
              std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count());
  auto compacted = js->GetStreamInfo(stream);
  ASSERT_TRUE(compacted.ok());
  EXPECT_LT(compacted->bytes, before->bytes);
  EXPECT_EQ(compacted->messages, 0u);
  std::printf("compaction: stream %llu bytes, %llu records -> %llu bytes, %llu records\n",
              static_cast<unsigned long long>(before->bytes),
              static_cast<unsigned long long>(before->messages),
              static_cast<unsigned long long>(compacted->bytes),
              static_cast<unsigned long long>(compacted->messages));
  // Not a snapshot.
  {
    grpc::ClientContext context;
    v1::ListSnapshotsResponse listed;
    ASSERT_TRUE(second.stub->ListSnapshots(&context, {}, &listed).ok());
    EXPECT_EQ(listed.snapshots_size(), 0);
  }

  // More places (ids continue), a later compaction purges past what shard-1 applied.
  ingest(second, 25, 40);
  auto tail = js->GetStreamInfo(stream);
  ASSERT_TRUE(tail.ok());
  ASSERT_GT(tail->last_sequence, down_at + 1);
  ASSERT_TRUE(await([&] { return base_at_least(down_at + 1); }, 60s));
  ASSERT_TRUE(await([&] { return stream_from(down_at + 2); }, 30s));

  // shard-0 goes down too, and shard-1 returns: its applied + 1 is below the stream's first
  // sequence; with no live peer it rebuilds from the base and applies the tail after it.
  shards[0].reset();
  const auto returned = std::chrono::steady_clock::now();
  shards[1] = StartShard(1);
  ASSERT_TRUE(shards[1]);
  ASSERT_TRUE(await([&] { return caught_up(*shards[1]); }, 90s));
  const double resume_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - returned).count();
  auto resumed = replica_of(*shards[1]);
  ASSERT_TRUE(resumed);
  EXPECT_EQ(resumed->restored_from.rfind("base ", 0), 0u) << resumed->restored_from;
  std::printf(
      "compaction: a replica down across the compactions resumed via the %s + tail to %llu "
      "in %.2f s\n",
      resumed->restored_from.c_str(), static_cast<unsigned long long>(resumed->applied_sequence),
      resume_s);
  ingest(second, 41, 44);  // served by shard-1 alone
  ASSERT_TRUE(await([&] { return caught_up(*shards[1]); }, 90s));

  // A replacement: shard-2 up, shard-0 (gone) replaced by it; it starts from the base or
  // shard-1's newer checkpoint, never from record 1.
  const auto replaced = std::chrono::steady_clock::now();
  shards.push_back(StartShard(2));
  ASSERT_TRUE(shards[2]);
  ASSERT_TRUE(await([&] { return caught_up(*shards[2]) && caught_up(*shards[1]); }, 120s));
  auto fresh = replica_of(*shards[2]);
  ASSERT_TRUE(fresh);
  EXPECT_FALSE(fresh->restored_from.empty()) << "replayed the stream from 1";
  std::printf("compaction: a replacement replica caught up from %s + tail in %.2f s\n",
              fresh->restored_from.c_str(),
              std::chrono::duration<double>(std::chrono::steady_clock::now() - replaced).count());

  // Both replicas hold the same places, every acknowledged one, under its id.
  auto a = shards[1]->Map("lab");
  auto b = shards[2]->Map("lab");
  ASSERT_TRUE(a.ok() && b.ok());
  const std::vector<PlaceId> ids = (*a)->database()->ListPlaces();
  EXPECT_EQ(ids, (*b)->database()->ListPlaces());
  EXPECT_EQ((*a)->applied_sequence(), (*b)->applied_sequence());
  for (const auto& [frame, place] : place_of) {
    EXPECT_TRUE(std::binary_search(ids.begin(), ids.end(), PlaceId(place)))
        << "frame " << frame << " place " << place;
  }
  for (const int frame : {1, 12, 24, 30, 40, 44}) {
    if (!place_of.count(frame)) continue;
    EXPECT_EQ(TopPlace(second.stub.get(), "lab", frame), place_of[frame]) << "frame " << frame;
  }
  const auto metrics = ParseMetrics(HttpGet(second.server->metrics_port(), "/metrics"));
  EXPECT_GE(MetricValue(metrics, "placedb_cluster_compactions_total", {}), 2);
  EXPECT_GE(MetricValue(metrics, "placedb_cluster_base_sequence", {{"map", "lab"}}),
            double(down_at + 1));
  // A compaction tried while a shard just died may fail (counted, tried again 10 s later).
  const double failures = MetricValue(metrics, "placedb_cluster_compaction_failures_total", {});
  EXPECT_GE(failures, 0);
  std::printf("compaction: %g compactions, %g failed\n",
              MetricValue(metrics, "placedb_cluster_compactions_total", {}), failures);
}

}  // namespace
}  // namespace placedb::server_testing
