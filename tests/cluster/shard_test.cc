// The map-shard role (server/cluster/shard.h) against real 3-node nats-server (JetStream) and etcd
// clusters (tests/cluster/engines.h), with real frames (the RTAB-Map loop). The test plays the
// worker and the coordinator: it creates each map's stream, writes maps/<map> and
// placement/<map>, and publishes records made by the record codec (server/cluster/map_record.h).
// Shards run in-process on loopback ports; their internal API is called over gRPC.
//
// Waits are bounded only against hangs; nothing asserts a duration.
#include "server/cluster/shard.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <atomic>
#include <map>
#include <set>
#include <thread>

#include "core/storage/codec.h"
#include "proto/cluster.grpc.pb.h"
#include "proto/convert_config.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "server/cluster/map_record.h"
#include "server/cluster/placement.h"
#include "server/metrics.h"
#include "tests/cluster/engines.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace placedb::cluster {
namespace {

using namespace std::chrono_literals;
namespace cv1 = ::placedb::cluster::v1;
namespace pv1 = ::placedb::v1;

constexpr char kCluster[] = "test";

template <typename Predicate>
bool WaitFor(Predicate done, std::chrono::milliseconds limit = 30s) {
  const auto until = std::chrono::steady_clock::now() + limit;
  while (std::chrono::steady_clock::now() < until) {
    if (done()) return true;
    std::this_thread::sleep_for(20ms);
  }
  return done();
}

std::string StreamOf(const std::string& map) {
  return cluster::StreamName(kCluster, map);
}
std::string SubjectOf(const std::string& map) {
  return cluster::StreamSubject(kCluster, map);
}
std::string Key(const std::string& suffix) {
  return std::string("/placedb/") + kCluster + "/" + suffix;
}

class ShardTest : public ::testing::Test {
 protected:
  // No assertion here: a fatal failure in SetUpTestSuite makes gtest print "[  SKIPPED ]",
  // which ctest takes for a skip. What went wrong is kept, and every test fails on it in SetUp.
  static void SetUpTestSuite() { setup_error_ = new std::string(Prepare()); }
  static std::string Prepare() {
    if (!placedb::testing::HaveSharedData()) return "../shared/data is required";
    auto engines = testing::Engines::Start();
    if (!engines.ok()) return "engines: " + engines.status().ToString();
    engines_ = std::move(engines).value().release();
    vocabulary_ = new AnyVocabulary(placedb::testing::DefaultVocabulary());
    // The frames, processed as a worker would for a map of the default configuration.
    wire::ServiceMapSettings settings;
    auto options = wire::MapOptionsFromProto(
        pv1::MapConfig(), 4000, wire::MapVocabulary{"default", FeatureType::kOrb}, &settings);
    if (!options.ok()) return options.status().ToString();
    auto db = PlaceDatabase::Create(*vocabulary_, options->database);
    if (!db.ok()) return db.status().ToString();
    frames_ = new std::vector<ProcessedFrame>(placedb::testing::ProcessRtabmapFrames(**db, 12));
    if (frames_->size() != 12u) return "12 RTAB-Map frames expected";
    return "";
  }
  static void TearDownTestSuite() {
    delete frames_;
    delete vocabulary_;
    delete engines_;  // kills every engine
    delete setup_error_;
  }

  void SetUp() override {
    ASSERT_TRUE(setup_error_->empty()) << *setup_error_;
    ASSERT_TRUE(engines_);
    root_ = placedb::testing::MakeTempDir("placedb-shard");
    JetStreamOptions js;
    js.servers = engines_->NatsUrls();
    auto connected = JetStream::Connect(js);
    ASSERT_TRUE(connected.ok()) << connected.status().ToString();
    js_ = std::move(connected).value();
    EtcdOptions etcd;
    etcd.endpoints = engines_->EtcdEndpoints();
    auto client = EtcdClient::Create(etcd);
    ASSERT_TRUE(client.ok());
    etcd_ = std::move(client).value();
  }

  // The worker's and coordinator's part: the stream, maps/<map>, placement/<map>.
  void CreateMap(const std::string& map, const std::vector<std::string>& replicas) {
    StreamConfig stream;
    stream.name = StreamOf(map);
    stream.subjects = {SubjectOf(map)};
    const Status made = js_->EnsureStream(stream);
    ASSERT_TRUE(made.ok()) << made.ToString();
    std::string config;
    ASSERT_TRUE(google::protobuf::util::MessageToJsonString(pv1::MapConfig(), &config).ok());
    ASSERT_TRUE(etcd_
                    ->Put(Key("maps/" + map),
                          R"({"config": )" + config + R"(, "stream": ")" + stream.name + R"("})")
                    .ok());
    Place(map, replicas);
  }
  void Place(const std::string& map, const std::vector<std::string>& replicas) {
    std::string list;
    for (const std::string& r : replicas) list += (list.empty() ? "\"" : ",\"") + r + "\"";
    ASSERT_TRUE(
        etcd_->Put(Key("placement/" + map), R"({"epoch": 1, "replicas": [)" + list + "]}").ok());
  }

  std::unique_ptr<Shard> StartShard(const std::string& id, server::Metrics* metrics = nullptr) {
    ShardOptions options;
    options.cluster_name = kCluster;
    options.nats = engines_->NatsUrls();
    options.etcd = engines_->EtcdEndpoints();
    options.shard_id = id;
    options.internal_listen = "127.0.0.1:0";
    options.data_dir = root_ + "/" + id;
    options.vocabularies = {{"default", *vocabulary_}};
    options.report_interval = 200ms;
    options.reconcile_interval = 200ms;
    options.metrics = metrics;
    auto shard = Shard::Start(options);
    EXPECT_TRUE(shard.ok()) << shard.status().ToString();
    return shard.ok() ? std::move(shard).value() : nullptr;
  }

  // Publishes with a message id, retrying (same id) on errors as a worker must, for up to 60 s:
  // a deadline, not a count of attempts (they fail at once while the client reconnects, and a
  // stream leader's election on a loaded machine took more than 100 of them).
  PubAck Publish(const std::string& map, const std::string& data, const std::string& id) {
    const auto until = std::chrono::steady_clock::now() + 60s;
    Status last;
    while (std::chrono::steady_clock::now() < until) {
      auto ack = js_->Publish(SubjectOf(map), data, id, 2s);
      if (ack.ok()) return *ack;
      last = ack.status();
      std::this_thread::sleep_for(100ms);
    }
    ADD_FAILURE() << "publish " << id << " never acknowledged within 60 s: " << last.ToString();
    return {};
  }
  PubAck AddPlace(const std::string& map, int frame, const std::string& agent = "robot") {
    PlaceMetadata metadata;
    metadata.agent_id = agent;
    metadata.sequence = uint64_t(frame);
    metadata.timestamp_ns = int64_t(frame) * 1'000'000;
    return Publish(map, EncodeAddPlace((*frames_)[size_t(frame)], metadata),
                   agent + "/" + std::to_string(frame));
  }

  static uint64_t Applied(const Shard& shard, const std::string& map) {
    auto m = shard.Map(map);
    return m.ok() ? (*m)->applied_sequence() : 0;
  }

  // The value of a gauge family's series for `map` (-1 when absent).
  static double Gauge(server::Metrics& metrics, const std::string& family, const std::string& map) {
    for (const auto& f : metrics.registry()->Collect()) {
      if (f.name != family) continue;
      for (const auto& metric : f.metric) {
        for (const auto& label : metric.label) {
          if (label.name == "map" && label.value == map) return metric.gauge.value;
        }
      }
    }
    return -1;
  }

  static std::unique_ptr<cv1::Shard::Stub> Stub(const Shard& shard) {
    return cv1::Shard::NewStub(grpc::CreateChannel(
        "127.0.0.1:" + std::to_string(shard.internal_port()), grpc::InsecureChannelCredentials()));
  }

  // Every place of the replica: id -> (record, bow, features bytes).
  static std::map<PlaceId, std::string> Contents(const Shard& shard, const std::string& map) {
    std::map<PlaceId, std::string> out;
    auto m = shard.Map(map);
    EXPECT_TRUE(m.ok()) << m.status().ToString();
    if (!m.ok()) return out;
    PlaceId before = 0;
    for (;;) {
      const PlacePage page = (*m)->database()->ListPlacesBefore(before, 1000, {}, 1u << 30);
      for (const auto& record : page.places) {
        auto place = (*m)->GetPlace(record->id);
        EXPECT_TRUE(place.ok());
        if (!place.ok()) continue;
        out[record->id] = EncodePlaceRecord(place->record) + EncodeBow(place->payload.bow) +
                          EncodeLocalFeatures(place->payload.features, place->payload.direct);
      }
      if (page.next_before == 0) break;
      before = page.next_before;
    }
    return out;
  }

  static testing::Engines* engines_;
  static std::string* setup_error_;
  static AnyVocabulary* vocabulary_;
  static std::vector<ProcessedFrame>* frames_;
  std::string root_;
  std::unique_ptr<JetStream> js_;
  std::unique_ptr<EtcdClient> etcd_;
};

testing::Engines* ShardTest::engines_ = nullptr;
std::string* ShardTest::setup_error_ = nullptr;
AnyVocabulary* ShardTest::vocabulary_ = nullptr;
std::vector<ProcessedFrame>* ShardTest::frames_ = nullptr;

TEST_F(ShardTest, TwoReplicasApplyInOrderOnceAndHoldIdenticalPlaces) {
  const std::string map = "lab";
  CreateMap(map, {"shard-a", "shard-b"});
  auto a = StartShard("shard-a");
  auto b = StartShard("shard-b");
  ASSERT_TRUE(a && b);

  std::set<uint64_t> places;
  for (int i = 0; i < 4; ++i) places.insert(AddPlace(map, i).sequence);
  // A retried publish (same message id) is not stored again.
  const PubAck again = AddPlace(map, 1);
  EXPECT_TRUE(again.duplicate);
  PlaceMetadata metadata;
  metadata.agent_id = "robot";
  ProcessedFrame invalid;
  invalid.rejection = "too few features";
  const uint64_t invalid_seq =
      Publish(map, EncodeInvalidFrame(invalid, metadata), "robot/i").sequence;
  const uint64_t first = *places.begin();
  const uint64_t deleted = Publish(map, EncodeDeletePlace(PlaceId(first)), "delete/1").sequence;
  places.erase(first);
  const uint64_t last = deleted;
  EXPECT_EQ(last, 6u);  // 4 places, an invalid frame, a removal; the duplicate took none

  ASSERT_TRUE(WaitFor([&] { return Applied(*a, map) == last && Applied(*b, map) == last; }))
      << Applied(*a, map) << " " << Applied(*b, map);
  const auto on_a = Contents(*a, map);
  const auto on_b = Contents(*b, map);
  std::set<uint64_t> ids;
  for (const auto& [id, bytes] : on_a) ids.insert(id);
  EXPECT_EQ(ids, places);  // ids = stream sequences; the invalid frame's and removal's: no place
  EXPECT_FALSE(ids.count(invalid_seq));
  EXPECT_EQ(on_a, on_b);  // the same ids, records, BoW vectors and features on both replicas
  EXPECT_EQ((*a->Map(map))->database()->Stats().invalid_rejected, 1u);

  // The internal API: Status, GetPlace.
  auto stub = Stub(*a);
  {
    grpc::ClientContext context;
    cv1::StatusResponse status;
    ASSERT_TRUE(stub->Status(&context, cv1::StatusRequest(), &status).ok());
    EXPECT_EQ(status.shard_id(), "shard-a");
    ASSERT_EQ(status.maps_size(), 1);
    EXPECT_EQ(status.maps(0).applied_sequence(), last);
    EXPECT_EQ(status.maps(0).places(), places.size());
    EXPECT_EQ(status.maps(0).state(), "applying");
  }
  {
    grpc::ClientContext context;
    pv1::GetPlaceRequest request;
    request.set_map(map);
    request.set_place_id(uint32_t(*places.begin()));
    pv1::Place place;
    ASSERT_TRUE(stub->GetPlace(&context, request, &place).ok());
    EXPECT_EQ(place.place_id(), *places.begin());
    EXPECT_EQ(place.metadata().agent_id(), "robot");
    grpc::ClientContext gone;
    request.set_place_id(uint32_t(first));
    EXPECT_EQ(stub->GetPlace(&gone, request, &place).error_code(), grpc::StatusCode::NOT_FOUND);
  }
  {
    grpc::ClientContext context;
    pv1::ListPlacesRequest request;
    request.set_map(map);
    pv1::ListPlacesResponse listed;
    ASSERT_TRUE(stub->ListPlaces(&context, request, &listed).ok());
    ASSERT_EQ(size_t(listed.places_size()), places.size());
    EXPECT_EQ(listed.places(0).place_id(), *places.rbegin());  // newest first
  }
  {
    // Every stored frame counted in the map's aggregate (also the removed place's); the invalid
    // frame in its own.
    grpc::ClientContext context;
    pv1::GetDynamicsRequest request;
    request.set_map(map);
    pv1::GetDynamicsResponse dynamics;
    ASSERT_TRUE(stub->GetDynamics(&context, request, &dynamics).ok());
    EXPECT_EQ(dynamics.map().observations(), 4u);
    EXPECT_EQ(dynamics.invalid().observations(), 1u);
  }
  // applied/<map>/<shard> is published.
  EXPECT_TRUE(WaitFor([&] {
    auto value = etcd_->Get(Key("applied/" + map + "/shard-b"));
    return value.ok() && !value->kvs.empty() && value->kvs[0].value == std::to_string(last);
  }));

  // Search with min_sequence waits until the replica has applied it: the place published after
  // the call started is found.
  cv1::SearchRequest search;
  search.set_map(map);
  search.set_min_sequence(last + 1);
  FrameToSearchRequest((*frames_)[7], &search);
  std::atomic<bool> answered{false};
  cv1::SearchResponse found;
  grpc::Status searched;
  std::thread caller([&] {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 30s);
    searched = stub->Search(&context, search, &found);
    answered = true;
  });
  std::this_thread::sleep_for(300ms);
  const bool early = answered.load();
  const uint64_t added = AddPlace(map, 7).sequence;
  caller.join();
  EXPECT_FALSE(early);
  ASSERT_TRUE(searched.ok()) << searched.error_message();
  EXPECT_GE(found.applied_sequence(), added);
  ASSERT_GT(found.matches_size(), 0);
  EXPECT_EQ(found.matches(0).place_id(), added);
  // Not reached within the deadline: DEADLINE_EXCEEDED, naming what was applied.
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 500ms);
    search.set_min_sequence(added + 100);
    const grpc::Status late = stub->Search(&context, search, &found);
    EXPECT_EQ(late.error_code(), grpc::StatusCode::DEADLINE_EXCEEDED) << late.error_message();
  }

  // Removed from the placement: shard-b stops and deletes its replica.
  Place(map, {"shard-a"});
  EXPECT_TRUE(WaitFor([&] { return b->Replicas().empty(); }));
  EXPECT_EQ(b->Map(map).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(a->Map(map).status().code(), StatusCode::kOk);

  // A new replica catches up from shard-a's checkpoint, then applies what follows it.
  Place(map, {"shard-a", "shard-c"});
  const auto catchup_start = std::chrono::steady_clock::now();
  auto c = StartShard("shard-c");
  ASSERT_TRUE(c);
  ASSERT_TRUE(WaitFor([&] { return Applied(*c, map) == added; })) << Applied(*c, map);
  std::printf(
      "shard_checkpoint_catchup_ms %.0f ms (%zu places)\n",
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - catchup_start)
          .count(),
      Contents(*a, map).size());
  const auto replicas = c->Replicas();
  ASSERT_EQ(replicas.size(), 1u);
  EXPECT_EQ(replicas[0].restored_from, "shard-a");
  const uint64_t after = AddPlace(map, 8).sequence;
  ASSERT_TRUE(WaitFor([&] { return Applied(*a, map) == after && Applied(*c, map) == after; }));
  EXPECT_EQ(Contents(*a, map), Contents(*c, map));
  EXPECT_TRUE((*c->Map(map))->VerifyIntegrity().ok());

  // Figures (printed, not asserted): records published back to back until both replicas applied
  // them.
  const auto start = std::chrono::steady_clock::now();
  uint64_t bulk_last = 0;
  constexpr int kBulk = 60;
  for (int i = 0; i < kBulk; ++i) {
    PlaceMetadata bulk;
    bulk.agent_id = "bulk";
    bulk.sequence = uint64_t(i);
    bulk_last = Publish(map, EncodeAddPlace((*frames_)[size_t(i) % frames_->size()], bulk),
                        "bulk/" + std::to_string(i))
                    .sequence;
  }
  const double published_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  ASSERT_TRUE(
      WaitFor([&] { return Applied(*a, map) == bulk_last && Applied(*c, map) == bulk_last; }));
  const double applied_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("shard_publish_records_per_s %.0f records/s\n", kBulk / published_s);
  std::printf("shard_publish_to_applied_two_replicas_records_per_s %.0f records/s\n",
              kBulk / applied_s);
}

// Loop closure's reads on a worker (FetchPlaces, ListAgentPlaces): the replica's own bytes for
// the places asked, absent ones left out; an agent's places page by page, newest first, with
// their observation sequences; both wait for min_sequence like Search.
TEST_F(ShardTest, FetchPlacesAndListAgentPlacesForLoopClosure) {
  const std::string map = "loop-reads";
  CreateMap(map, {"shard-l"});
  auto shard = StartShard("shard-l");
  ASSERT_TRUE(shard);
  std::vector<uint64_t> robot;  // the robot's places, oldest first
  for (int frame = 0; frame < 5; ++frame) robot.push_back(AddPlace(map, frame).sequence);
  const uint64_t other = AddPlace(map, 5, "other").sequence;
  const uint64_t last =
      Publish(map, EncodeDeletePlace(PlaceId(robot[1])), "delete/" + map).sequence;
  const uint64_t removed = robot[1];
  robot.erase(robot.begin() + 1);
  ASSERT_TRUE(WaitFor([&] { return Applied(*shard, map) == last; }));
  auto m = shard->Map(map);
  ASSERT_TRUE(m.ok());
  auto stub = Stub(*shard);

  for (const bool features : {false, true}) {
    grpc::ClientContext context;
    cv1::FetchPlacesRequest request;
    request.set_map(map);
    request.set_min_sequence(last);
    for (const uint64_t id : {robot[2], removed, other}) request.add_place_ids(uint32_t(id));
    request.set_features(features);
    cv1::FetchPlacesResponse response;
    ASSERT_TRUE(stub->FetchPlaces(&context, request, &response).ok());
    EXPECT_EQ(response.applied_sequence(), last);
    ASSERT_EQ(response.places_size(), 2);  // the removed place left out, the order kept
    EXPECT_EQ(response.places(0).place_id(), robot[2]);
    EXPECT_EQ(response.places(1).place_id(), other);
    for (const cv1::FetchedPlace& fetched : response.places()) {
      auto place = (*m)->GetPlace(fetched.place_id());
      ASSERT_TRUE(place.ok());
      EXPECT_EQ(fetched.bow(), EncodeBow(place->payload.bow));
      EXPECT_EQ(fetched.features(),
                features ? EncodeLocalFeatures(place->payload.features, place->payload.direct)
                         : std::string());
    }
  }

  // The robot's places in pages of 2: every one once, newest first, with its sequence and BoW.
  std::vector<uint64_t> listed;
  cv1::ListAgentPlacesRequest list;
  list.set_map(map);
  list.set_agent_id("robot");
  list.set_limit(2);
  list.set_min_sequence(last);
  for (int page = 0; page < 10; ++page) {
    grpc::ClientContext context;
    cv1::ListAgentPlacesResponse response;
    ASSERT_TRUE(stub->ListAgentPlaces(&context, list, &response).ok());
    EXPECT_LE(response.places_size(), 2);
    for (const cv1::AgentPlace& place : response.places()) {
      listed.push_back(place.place_id());
      auto stored = (*m)->GetPlace(place.place_id());
      ASSERT_TRUE(stored.ok());
      EXPECT_EQ(place.sequence(), stored->record.metadata.sequence);
      EXPECT_EQ(place.bow(), EncodeBow(stored->payload.bow));
    }
    if (response.next_before_place_id() == 0) break;
    list.set_before_place_id(response.next_before_place_id());
  }
  EXPECT_EQ(listed, std::vector<uint64_t>(robot.rbegin(), robot.rend()));

  // Errors: no agent, a map not held here, min_sequence not reached in time.
  {
    grpc::ClientContext context;
    cv1::ListAgentPlacesRequest request;
    request.set_map(map);
    cv1::ListAgentPlacesResponse response;
    EXPECT_EQ(stub->ListAgentPlaces(&context, request, &response).error_code(),
              grpc::StatusCode::INVALID_ARGUMENT);
  }
  {
    grpc::ClientContext context;
    cv1::FetchPlacesRequest request;
    request.set_map("elsewhere");
    cv1::FetchPlacesResponse response;
    EXPECT_EQ(stub->FetchPlaces(&context, request, &response).error_code(),
              grpc::StatusCode::NOT_FOUND);
  }
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 500ms);
    cv1::FetchPlacesRequest request;
    request.set_map(map);
    request.set_min_sequence(last + 100);
    request.add_place_ids(uint32_t(robot[0]));
    cv1::FetchPlacesResponse response;
    EXPECT_EQ(stub->FetchPlaces(&context, request, &response).error_code(),
              grpc::StatusCode::DEADLINE_EXCEEDED);
  }
}

TEST_F(ShardTest, ARestartedShardResumesWithoutGapsOrDuplicates) {
  const std::string map = "restart";
  CreateMap(map, {"shard-r"});
  std::set<uint64_t> places;
  auto shard = StartShard("shard-r");
  ASSERT_TRUE(shard);
  for (int i = 0; i < 3; ++i) places.insert(AddPlace(map, i).sequence);
  ASSERT_TRUE(WaitFor([&] { return Applied(*shard, map) == 3; }));
  shard.reset();  // destroyed: a stop at any point
  for (int i = 3; i < 6; ++i) places.insert(AddPlace(map, i).sequence);
  server::Metrics metrics;
  shard = StartShard("shard-r", &metrics);
  ASSERT_TRUE(shard);
  ASSERT_TRUE(WaitFor([&] { return Applied(*shard, map) == 6; }));
  // The gauges, on the process's metrics registry.
  EXPECT_TRUE(WaitFor([&] {
    return Gauge(metrics, "placedb_shard_applied_sequence", map) == 6.0 &&
           Gauge(metrics, "placedb_shard_lag_records", map) == 0.0;
  }));
  std::set<uint64_t> ids;
  for (const auto& [id, bytes] : Contents(*shard, map)) ids.insert(id);
  EXPECT_EQ(ids, places);
  EXPECT_TRUE((*shard->Map(map))->VerifyIntegrity().ok());

  // Its lease lost (revoked): it registers again.
  auto registered = etcd_->Get(Key("shards/shard-r"));
  ASSERT_TRUE(registered.ok() && registered->kvs.size() == 1u);
  const int64_t lease = registered->kvs[0].lease;
  ASSERT_TRUE(etcd_->RevokeLease(lease).ok());
  EXPECT_TRUE(WaitFor([&] {
    auto now = etcd_->Get(Key("shards/shard-r"));
    return now.ok() && now->kvs.size() == 1u && now->kvs[0].lease != lease;
  }));

  // The map deleted and re-created under its name while the shard is down: the old local copy
  // is not resumed on the new stream.
  shard.reset();
  ASSERT_TRUE(etcd_->Delete(Key("placement/" + map)).ok());
  ASSERT_TRUE(etcd_->Delete(Key("maps/" + map)).ok());
  ASSERT_TRUE(js_->DeleteStream(StreamOf(map)).ok());
  CreateMap(map, {"shard-r"});
  const uint64_t fresh = AddPlace(map, 9).sequence;
  EXPECT_EQ(fresh, 1u);
  shard = StartShard("shard-r");
  ASSERT_TRUE(shard);
  ASSERT_TRUE(WaitFor([&] { return Applied(*shard, map) == 1; }));
  const auto contents = Contents(*shard, map);
  ASSERT_EQ(contents.size(), 1u);
  EXPECT_EQ(contents.begin()->first, 1u);
  EXPECT_EQ((*shard->Map(map))->GetPlace(1)->record.metadata.sequence, 9u);
}

TEST_F(ShardTest, NothingIsLostWhenTheStreamLeaderIsKilledDuringPublishing) {
  const std::string map = "leader";
  CreateMap(map, {"shard-x", "shard-y"});
  auto x = StartShard("shard-x");
  auto y = StartShard("shard-y");
  ASSERT_TRUE(x && y);
  auto leader = engines_->StreamLeader(StreamOf(map));
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  std::set<uint64_t> acknowledged;
  for (int i = 0; i < 12; ++i) {
    if (i == 4) engines_->KillNats(*leader);
    const PubAck ack = AddPlace(map, i, "agent-" + std::to_string(i % 2));
    ASSERT_GT(ack.sequence, 0u);
    acknowledged.insert(ack.sequence);
  }
  ASSERT_TRUE(engines_->RestartNats(*leader).ok());
  const uint64_t last = *acknowledged.rbegin();
  ASSERT_TRUE(WaitFor([&] { return Applied(*x, map) >= last && Applied(*y, map) >= last; }, 60s))
      << Applied(*x, map) << " " << Applied(*y, map);
  const auto on_x = Contents(*x, map);
  std::set<uint64_t> ids;
  for (const auto& [id, bytes] : on_x) ids.insert(id);
  // What each replica says of itself, for a failure's message.
  std::string replicas;
  for (const Shard* shard : {x.get(), y.get()}) {
    for (const ReplicaStatus& replica : shard->Replicas()) {
      replicas += replica.map + ": applied " + std::to_string(replica.applied_sequence) +
                  ", places " + std::to_string(replica.places) + ", " + replica.state +
                  (replica.restored_from.empty() ? "" : ", from " + replica.restored_from) + "; ";
    }
  }
  SCOPED_TRACE("acknowledged up to " + std::to_string(last) + "; " + replicas);
  EXPECT_EQ(acknowledged.size(), 12u);
  // Every acknowledged place on both replicas, identical; extra places only from a publish that
  // was stored but whose ack was lost (then retried with the same id: a duplicate, no extra).
  for (uint64_t id : acknowledged) EXPECT_TRUE(ids.count(id)) << "place " << id << " lost";
  EXPECT_EQ(on_x, Contents(*y, map));
}

}  // namespace
}  // namespace placedb::cluster
