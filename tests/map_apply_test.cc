// PlaceMap::ApplyAt and ApplyBatch (cluster mode, issue 18): records applied at stream sequences,
// on a real RocksDB in a temp directory, with real frames (the RTAB-Map loop).
#include <gtest/gtest.h>

#include <atomic>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include "core/storage/codec.h"
#include "core/storage/map_store.h"
#include "tests/join_on_exit.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

class MapApplyTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    vocabulary_ = testing::DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
    root_ = testing::MakeTempDir("placedb-apply");
  }

  std::unique_ptr<DataDirectory> OpenDir() {
    auto dir = DataDirectory::Open(root_ + "/data");
    EXPECT_TRUE(dir.ok()) << dir.status().ToString();
    return dir.ok() ? std::move(dir).value() : nullptr;
  }

  static MapLogRecord Add(const ProcessedFrame& frame, uint64_t agent_sequence) {
    MapLogRecord record;
    record.kind = MapLogRecord::Kind::kAddPlace;
    record.frame = frame;
    record.metadata.agent_id = "robot";
    record.metadata.sequence = agent_sequence;
    record.metadata.timestamp_ns = int64_t(agent_sequence) * 1000;
    record.dynamics = MakeObservation(0.25, {}, record.metadata.timestamp_ns, 42);
    return record;
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
};

TEST_F(MapApplyTest, AppliesInOrderWithGapsIdempotentlyAndResumesAfterReopen) {
  std::vector<ProcessedFrame> frames;
  {
    auto dir = OpenDir();
    ASSERT_TRUE(dir);
    auto map = dir->CreateMap("replica", {}, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    frames = testing::ProcessRtabmapFrames(*(*map)->database(), 4);
    ASSERT_EQ(frames.size(), 4u);
    PlaceMap& m = **map;
    EXPECT_EQ(m.applied_sequence(), 0u);

    // 3: a place; 4: one more observation of it; 5: a place; 6: an invalid frame; 7: 3 removed.
    auto applied = m.ApplyAt(3, Add(frames[0], 1));
    ASSERT_TRUE(applied.ok()) << applied.status().ToString();
    EXPECT_TRUE(*applied);
    MapLogRecord count;
    count.kind = MapLogRecord::Kind::kCountObservation;
    count.place = 3;
    count.dynamics = MakeObservation(0.5, {}, 7, 43);
    ASSERT_TRUE(m.ApplyAt(4, count).ok());
    ASSERT_TRUE(m.ApplyAt(5, Add(frames[1], 2)).ok());
    MapLogRecord invalid;
    invalid.kind = MapLogRecord::Kind::kInvalidFrame;
    invalid.frame.rejection = "too few features";
    ASSERT_TRUE(m.ApplyAt(6, invalid).ok());
    MapLogRecord remove;
    remove.kind = MapLogRecord::Kind::kDeletePlace;
    remove.place = 3;
    ASSERT_TRUE(m.ApplyAt(7, remove).ok());
    EXPECT_EQ(m.applied_sequence(), 7u);
    EXPECT_EQ(m.GetPlace(3).status().code(), StatusCode::kNotFound);
    auto place = m.GetPlace(5);
    ASSERT_TRUE(place.ok()) << place.status().ToString();
    EXPECT_EQ(place->record.metadata.sequence, 2u);
    EXPECT_EQ(place->payload.bow, frames[1].bow);
    EXPECT_EQ(m.Stats().database.places, 1u);
    EXPECT_EQ(m.Stats().database.invalid_rejected, 1u);

    // Re-applied (a redelivery): nothing changes.
    auto again = m.ApplyAt(5, Add(frames[2], 3));
    ASSERT_TRUE(again.ok());
    EXPECT_FALSE(*again);
    again = m.ApplyAt(7, Add(frames[2], 3));
    ASSERT_TRUE(again.ok());
    EXPECT_FALSE(*again);
    EXPECT_EQ(m.Stats().database.places, 1u);
    EXPECT_EQ(m.GetPlace(5)->record.metadata.sequence, 2u);
    auto dynamics = m.GetDynamics(5);
    ASSERT_TRUE(dynamics.ok());
    EXPECT_EQ(dynamics->observations, 1u);
    EXPECT_TRUE(m.VerifyIntegrity().ok());
  }
  // Reopened: the applied sequence and the places are back; the next place continues the ids.
  auto dir = OpenDir();
  ASSERT_TRUE(dir);
  auto map = dir->OpenMap("replica", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  PlaceMap& m = **map;
  EXPECT_EQ(m.applied_sequence(), 7u);
  EXPECT_FALSE(*m.ApplyAt(6, Add(frames[2], 3)));
  ASSERT_TRUE(*m.ApplyAt(9, Add(frames[2], 3)));
  EXPECT_EQ(m.GetPlace(9)->record.metadata.sequence, 3u);
  QueryResult result = m.Search(frames[2], {});
  ASSERT_TRUE(result.valid);
  ASSERT_FALSE(result.matches.empty());
  EXPECT_EQ(result.matches.front().place, 9u);
  // The database's own next id follows the stream (a single-node commit would not reuse one).
  auto committed = m.Commit(frames[3], {});
  ASSERT_TRUE(committed.ok()) << committed.status().ToString();
  EXPECT_EQ(committed->id, 10u);
}

TEST_F(MapApplyTest, ARecordTheMapCannotTakeChangesNothing) {
  auto dir = OpenDir();
  ASSERT_TRUE(dir);
  auto map = dir->CreateMap("replica", {}, vocabulary_);
  ASSERT_TRUE(map.ok());
  PlaceMap& m = **map;
  auto frames = testing::ProcessRtabmapFrames(*m.database(), 1);
  ASSERT_EQ(frames.size(), 1u);
  ASSERT_TRUE(*m.ApplyAt(1, Add(frames[0], 1)));

  MapLogRecord bad = Add(frames[0], 2);
  bad.frame.direct.levels_up += 1;
  EXPECT_EQ(m.ApplyAt(2, bad).status().code(), StatusCode::kInvalidArgument);
  MapLogRecord invalid_frame = Add(frames[0], 2);
  invalid_frame.frame.valid = false;
  EXPECT_EQ(m.ApplyAt(2, invalid_frame).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(m.ApplyAt(uint64_t(1) << 32, Add(frames[0], 2)).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(m.applied_sequence(), 1u);
  EXPECT_EQ(m.Stats().database.places, 1u);
  // The same sequence then applies a good record.
  EXPECT_TRUE(*m.ApplyAt(2, Add(frames[0], 2)));
  EXPECT_EQ(m.applied_sequence(), 2u);
}

// Everything a replica holds that a client or another replica could tell apart.
std::map<PlaceId, std::string> Contents(const PlaceMap& map) {
  std::map<PlaceId, std::string> out;
  for (PlaceId id : map.database()->ListPlaces()) {
    auto place = map.GetPlace(id);
    EXPECT_TRUE(place.ok()) << place.status().ToString();
    if (!place.ok()) continue;
    auto dynamics = map.GetDynamics(id);
    out[id] = EncodePlaceRecord(place->record) + EncodeBow(place->payload.bow) +
              EncodeLocalFeatures(place->payload.features, place->payload.direct) +
              (dynamics.ok() ? EncodeDynamics(*dynamics) : dynamics.status().ToString());
  }
  return out;
}

TEST_F(MapApplyTest, BatchesStoreWhatOneRecordAtATimeStores) {
  auto dir = OpenDir();
  ASSERT_TRUE(dir);
  auto single = dir->CreateMap("single", {}, vocabulary_);
  auto batched = dir->CreateMap("batched", {}, vocabulary_);
  ASSERT_TRUE(single.ok() && batched.ok());
  auto frames = testing::ProcessRtabmapFrames(*(*single)->database(), 6);
  ASSERT_EQ(frames.size(), 6u);

  // Sequences 1..12: places, a count of a place added in the same run (2 -> 1) and of one from
  // an earlier batch (8 -> 5), an invalid frame, a removal mid-stream (9 -> 3), a removal of a
  // place never stored (11), a gap (10 absent), a repeat (6 again).
  std::vector<std::pair<uint64_t, MapLogRecord>> log;
  log.emplace_back(1, Add(frames[0], 1));
  MapLogRecord count;
  count.kind = MapLogRecord::Kind::kCountObservation;
  count.place = 1;
  count.dynamics = MakeObservation(0.5, {}, 7, 43);
  log.emplace_back(2, count);
  log.emplace_back(3, Add(frames[1], 2));
  MapLogRecord invalid;
  invalid.kind = MapLogRecord::Kind::kInvalidFrame;
  invalid.frame.rejection = "too few features";
  invalid.dynamics = MakeObservation(0.1, {}, 9, 44);
  log.emplace_back(4, invalid);
  log.emplace_back(5, Add(frames[2], 3));
  log.emplace_back(6, Add(frames[3], 4));
  log.emplace_back(6, Add(frames[4], 5));
  log.emplace_back(7, Add(frames[4], 5));
  count.place = 5;
  log.emplace_back(8, count);
  MapLogRecord remove;
  remove.kind = MapLogRecord::Kind::kDeletePlace;
  remove.place = 3;
  log.emplace_back(9, remove);
  remove.place = 10;
  log.emplace_back(11, remove);
  log.emplace_back(12, Add(frames[5], 6));

  for (const auto& [sequence, record] : log) ASSERT_TRUE((*single)->ApplyAt(sequence, record).ok());
  // The batched replica: in pieces of 5, 4 and the rest, the first piece twice (a redelivery).
  std::vector<PlaceMap::SequencedRecord> all;
  for (const auto& [sequence, record] : log) all.push_back({sequence, &record});
  const std::span<const PlaceMap::SequencedRecord> records(all);
  auto applied = (*batched)->ApplyBatch(records.subspan(0, 5));
  ASSERT_TRUE(applied.ok()) << applied.status().ToString();
  EXPECT_EQ(*applied, 5u);
  EXPECT_EQ(*(*batched)->ApplyBatch(records.subspan(0, 5)), 0u);
  EXPECT_EQ(*(*batched)->ApplyBatch(records.subspan(5, 4)), 3u);  // 6, 6 again (skipped), 7, 8
  EXPECT_EQ(*(*batched)->ApplyBatch(records.subspan(9)), 3u);

  auto same = [&](const PlaceMap& a, const PlaceMap& b) {
    EXPECT_EQ(a.applied_sequence(), 12u);
    EXPECT_EQ(b.applied_sequence(), 12u);
    EXPECT_EQ(Contents(a), Contents(b));
    EXPECT_EQ(Contents(a).size(), 5u);
    EXPECT_EQ(a.MapDynamics().value(), b.MapDynamics().value());
    EXPECT_EQ(a.InvalidDynamics().value(), b.InvalidDynamics().value());
    EXPECT_EQ(a.Stats().database.invalid_rejected, b.Stats().database.invalid_rejected);
    EXPECT_EQ(a.InvalidObservations(10).size(), b.InvalidObservations(10).size());
    EXPECT_TRUE(b.VerifyIntegrity().ok());
  };
  same(**single, **batched);
  // Each: its own observation and the count (of the same run for 1, of a later one for 5).
  EXPECT_EQ((*batched)->GetDynamics(1)->observations, 2u);
  EXPECT_EQ((*batched)->GetDynamics(5)->observations, 2u);
  // Both reopened: the same again.
  single->reset();
  batched->reset();
  dir.reset();
  dir = OpenDir();
  ASSERT_TRUE(dir);
  auto single_again = dir->OpenMap("single", vocabulary_);
  auto batched_again = dir->OpenMap("batched", vocabulary_);
  ASSERT_TRUE(single_again.ok() && batched_again.ok());
  same(**single_again, **batched_again);
}

TEST_F(MapApplyTest, ABatchStopsAtARecordTheMapCannotTake) {
  auto dir = OpenDir();
  ASSERT_TRUE(dir);
  auto map = dir->CreateMap("replica", {}, vocabulary_);
  ASSERT_TRUE(map.ok());
  PlaceMap& m = **map;
  auto frames = testing::ProcessRtabmapFrames(*m.database(), 3);
  ASSERT_EQ(frames.size(), 3u);
  MapLogRecord bad = Add(frames[1], 2);
  bad.frame.direct.levels_up += 1;
  const MapLogRecord first = Add(frames[0], 1), third = Add(frames[2], 3);
  const std::vector<PlaceMap::SequencedRecord> records = {{1, &first}, {2, &bad}, {3, &third}};
  auto applied = m.ApplyBatch(records);
  EXPECT_EQ(applied.status().code(), StatusCode::kInvalidArgument) << applied.status().ToString();
  EXPECT_NE(applied.status().message().find("record 2"), std::string::npos);
  // The record before it is applied and searchable; it and the one after are not.
  EXPECT_EQ(m.applied_sequence(), 1u);
  EXPECT_EQ(m.Stats().database.places, 1u);
  EXPECT_TRUE(m.GetPlace(1).ok());
  EXPECT_EQ(m.GetPlace(3).status().code(), StatusCode::kNotFound);
  EXPECT_TRUE(m.VerifyIntegrity().ok());
}

// A shard answers a read with a minimum sequence once its replica's applied sequence reaches it:
// every place up to that sequence must then be found. (The applied sequence used to move when the
// batch was durable, before its places were in the index: under load a replica said "applied 12"
// with 7 of 12 places.) A reader polls while batches of places are applied.
TEST_F(MapApplyTest, AnAppliedSequenceMeansEveryPlaceUpToItIsFound) {
  auto dir = OpenDir();
  ASSERT_TRUE(dir);
  auto map = dir->CreateMap("replica", {}, vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  PlaceMap& m = **map;
  const auto frames = testing::ProcessRtabmapFrames(*m.database(), 8);
  ASSERT_EQ(frames.size(), 8u);
  constexpr uint64_t kBatches = 20, kBatchSize = 32;

  std::atomic<bool> done{false};
  std::atomic<uint64_t> checks{0};
  std::atomic<uint64_t> missing_at{0};  // an applied sequence whose place was not found
  std::thread reader;
  testing::JoinOnExit join([&] { done = true; });
  join.Add(reader);
  reader = std::thread([&] {
    while (!done && missing_at == 0) {
      const uint64_t applied = m.applied_sequence();
      if (applied == 0) continue;
      ++checks;
      if (!m.GetPlace(PlaceId(applied)).ok()) missing_at = applied;
    }
  });
  std::vector<MapLogRecord> records;
  for (uint64_t i = 0; i < kBatches * kBatchSize; ++i) {
    records.push_back(Add(frames[i % frames.size()], i + 1));
  }
  for (uint64_t b = 0; b < kBatches && missing_at == 0; ++b) {
    std::vector<PlaceMap::SequencedRecord> batch;
    for (uint64_t i = b * kBatchSize; i < (b + 1) * kBatchSize; ++i) {
      batch.push_back({i + 1, &records[i]});
    }
    auto applied = m.ApplyBatch(batch);
    ASSERT_TRUE(applied.ok()) << applied.status().ToString();
  }
  join.JoinAll();
  EXPECT_EQ(missing_at.load(), 0u) << "applied sequence " << missing_at << " was not found";
  EXPECT_GT(checks.load(), 0u);
  EXPECT_EQ(m.Stats().database.places, kBatches * kBatchSize);
}

}  // namespace
}  // namespace placedb
