// Placement (server/cluster/placement.h) on a real 3-member etcd cluster: one coordinator of
// several, maps placed on the least loaded live shards, a replica whose shard lease is gone
// replaced after the grace with epoch + 1, takeover when the coordinator stops, and the view that
// routing reads.
#include "server/cluster/placement.h"

#include <gtest/gtest.h>

#include <chrono>
#include <memory>
#include <set>
#include <string>
#include <thread>

#include "server/cluster/etcd_client.h"
#include "tests/cluster/engines.h"

namespace placedb::cluster {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;
using Clock = std::chrono::steady_clock;

class PlacementTest : public ::testing::Test {
 protected:
  void SetUp() override {
    testing::EnginesOptions options;
    options.nats = false;
    auto engines = testing::Engines::Start(options);
    ASSERT_TRUE(engines.ok()) << engines.status().ToString();
    engines_ = std::move(engines).value();
    EtcdOptions etcd_options;
    etcd_options.endpoints = engines_->EtcdEndpoints();
    auto etcd = EtcdClient::Create(etcd_options);
    ASSERT_TRUE(etcd.ok()) << etcd.status().ToString();
    etcd_ = std::move(etcd).value();
    auto view = ClusterView::Start(etcd_.get(), "t");
    ASSERT_TRUE(view.ok()) << view.status().ToString();
    view_ = std::move(view).value();
  }

  // A shard as the shard role registers itself: its key with its own lease (TTL 2 s).
  int64_t RegisterShard(const std::string& id) {
    auto lease = etcd_->GrantLease(2);
    EXPECT_TRUE(lease.ok());
    EXPECT_TRUE(
        etcd_->Put(view_->keys().Shard(id), R"({"address": "127.0.0.1:1"})", lease->id).ok());
    keepers_.push_back(etcd_->KeepAlive(*lease, [](const Status&) {}));
    return lease->id;
  }

  void CreateMapKey(const std::string& map) {
    MapRecordInfo info{.config_json = R"({"vocabulary": "default"})",
                       .stream = StreamName("t", map),
                       .created_unix_ms = 1,
                       .snapshot = {},
                       .snapshot_base = 0};
    ASSERT_TRUE(etcd_->Put(view_->keys().Map(map), EncodeMapInfo(info)).ok());
  }

  std::optional<Placement> WaitPlacement(const std::string& map,
                                         const std::function<bool(const Placement&)>& ready,
                                         seconds timeout = seconds(20)) {
    std::optional<Placement> out;
    view_->WaitFor(
        map,
        [&](const std::optional<MapView>& view) {
          if (!view || !view->placement || !ready(*view->placement)) return false;
          out = view->placement;
          return true;
        },
        Clock::now() + timeout);
    return out;
  }

  CoordinatorOptions Options(const std::string& self) {
    return {.self = self,
            .replicas = 2,
            .replace_after = seconds(1),
            .lease_ttl_s = 2,
            .period = milliseconds(100)};
  }

  std::unique_ptr<testing::Engines> engines_;
  std::unique_ptr<EtcdClient> etcd_;
  std::unique_ptr<ClusterView> view_;
  std::vector<std::unique_ptr<LeaseKeeper>> keepers_;
};

TEST(PlacementNamesTest, StreamNamesAndRecords) {
  EXPECT_EQ(StreamName("placedb", "lab/1"), "PLACEDB_PLACEDB_6C61622F31");
  EXPECT_EQ(StreamSubject("placedb", "lab/1"), "placedb.placedb.map.6C61622F31");
  auto placement = DecodePlacement(EncodePlacement({.epoch = 3, .replicas = {"a", "b"}}));
  ASSERT_TRUE(placement.ok());
  EXPECT_EQ(placement->epoch, 3);
  EXPECT_EQ(placement->replicas, (std::vector<std::string>{"a", "b"}));
  EXPECT_EQ(DecodePlacement("{\"epoch\": 1}").status().code(), StatusCode::kInvalidArgument);
  auto info = DecodeMapInfo(EncodeMapInfo({.config_json = R"({"vocabulary":"default"})",
                                           .stream = "S",
                                           .created_unix_ms = 5,
                                           .snapshot = {},
                                           .snapshot_base = 0}));
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->stream, "S");
  EXPECT_TRUE(info->snapshot.empty());
  // Issue 35: a map restored from a snapshot says which, and where its stream starts.
  auto restored = DecodeMapInfo(EncodeMapInfo({.config_json = "{}",
                                               .stream = "S",
                                               .created_unix_ms = 5,
                                               .snapshot = "lab-1",
                                               .snapshot_base = 24}));
  ASSERT_TRUE(restored.ok());
  EXPECT_EQ(restored->snapshot, "lab-1");
  EXPECT_EQ(restored->snapshot_base, 24u);
  EXPECT_EQ(info->config_json, R"({"vocabulary":"default"})");
}

TEST_F(PlacementTest, PlacesReplacesAndFailsOver) {
  const int64_t lease_a = RegisterShard("shard-a");
  RegisterShard("shard-b");
  auto first = std::make_unique<Coordinator>(etcd_.get(), view_.get(), Options("worker-1"));
  auto second = std::make_unique<Coordinator>(etcd_.get(), view_.get(), Options("worker-2"));

  CreateMapKey("m1");
  auto placed = WaitPlacement("m1", [](const Placement& p) { return p.replicas.size() == 2; });
  ASSERT_TRUE(placed);
  EXPECT_EQ(placed->epoch, 1);
  EXPECT_EQ(std::set<std::string>(placed->replicas.begin(), placed->replicas.end()),
            (std::set<std::string>{"shard-a", "shard-b"}));
  // One coordinator at a time.
  EXPECT_NE(first->leading(), second->leading());

  // Applied sequences (written by the shards) reach the view for routing; the map's create
  // revision too (a re-created map gets a fresh local copy on workers).
  ASSERT_TRUE(etcd_->Put(view_->keys().Applied("m1", "shard-b"), "42").ok());
  ASSERT_TRUE(view_->WaitFor(
      "m1",
      [](const std::optional<MapView>& v) {
        return v && v->applied.count("shard-b") && v->applied.at("shard-b") == 42;
      },
      Clock::now() + seconds(10)));
  EXPECT_GT(view_->Map("m1")->create_revision, 0);

  // A third shard: the next map still gets two replicas, the least loaded first (shard-c).
  RegisterShard("shard-c");
  for (const auto until = Clock::now() + seconds(10);
       view_->Shards().size() < 3 && Clock::now() < until;) {
    std::this_thread::sleep_for(milliseconds(20));
  }
  ASSERT_EQ(view_->Shards().size(), 3u);
  CreateMapKey("m2");
  auto second_map = WaitPlacement("m2", [](const Placement& p) { return p.replicas.size() == 2; });
  ASSERT_TRUE(second_map);
  EXPECT_EQ(second_map->replicas[0], "shard-c");

  // shard-a dies (its lease goes): after the grace its replicas move, epoch + 1, to a live shard.
  const auto killed = Clock::now();
  keepers_[0]->Stop();
  ASSERT_TRUE(etcd_->RevokeLease(lease_a).ok());
  auto replaced = WaitPlacement("m1", [](const Placement& p) { return p.epoch == 2; });
  ASSERT_TRUE(replaced);
  EXPECT_GE(Clock::now() - killed, seconds(1));  // not before replace_after
  EXPECT_EQ(replaced->replicas.size(), 2u);
  for (const std::string& shard : replaced->replicas) EXPECT_NE(shard, "shard-a");

  // The leader stops (revoking its lease): the other takes over and keeps placing.
  std::unique_ptr<Coordinator>& stopping = first->leading() ? first : second;
  stopping.reset();
  CreateMapKey("m3");
  auto third = WaitPlacement("m3", [](const Placement& p) { return p.replicas.size() == 2; });
  ASSERT_TRUE(third);
  EXPECT_TRUE((first && first->leading()) || (second && second->leading()));
}

}  // namespace
}  // namespace placedb::cluster
