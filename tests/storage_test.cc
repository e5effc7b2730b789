// Durable maps on a real RocksDB in a temp directory, with real frames.
#include <gtest/gtest.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <map>
#include <thread>

#include "core/codec.h"
#include "core/map_store.h"
#include "tests/test_support.h"

namespace fs = std::filesystem;

namespace placedb {
namespace {

using testing::DefaultVocabulary;

Observation RtabmapFrame(int index) {
  Observation observation;
  observation.image = testing::ReadGray(testing::RtabmapFramePath(index));
  observation.metadata.agent_id = "robot-" + std::to_string(index % 3);
  observation.metadata.sequence = uint64_t(index);
  observation.metadata.timestamp_ns = int64_t(index) * 500'000'000;
  if (index % 4 == 0) {
    observation.metadata.pose = Pose{{double(index), 2.0, -1.5}, {0, 0, 0.38268343, 0.92387953}};
  }
  return observation;
}

// Every query's full ranked list, for exact before/after comparisons.
struct Ranked {
  std::vector<PlaceId> ids;
  std::vector<double> scores;
  std::vector<int> inliers;
  bool operator==(const Ranked&) const = default;
};

std::vector<Ranked> QueryAll(const PlaceMap& map, const std::vector<Observation>& queries) {
  std::vector<Ranked> out;
  for (const Observation& query : queries) {
    auto result = map.Query(query, {});
    EXPECT_TRUE(result.ok()) << result.status().ToString();
    Ranked ranked;
    if (result.ok()) {
      for (const Match& match : result->matches) {
        ranked.ids.push_back(match.place);
        ranked.scores.push_back(match.score);
        ranked.inliers.push_back(match.inliers);
      }
    }
    out.push_back(ranked);
  }
  return out;
}

class StorageTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    vocabulary_ = DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
    root_ = testing::MakeTempDir("placedb-storage");
  }

  std::unique_ptr<DataDirectory> OpenDir(StorageOptions options = {}) {
    auto dir = DataDirectory::Open(root_ + "/data", options);
    EXPECT_TRUE(dir.ok()) << dir.status().ToString();
    return dir.ok() ? std::move(dir).value() : nullptr;
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
};

TEST(Codec, RoundTripsEveryRecordType) {
  PlaceRecord record;
  record.id = 77;
  record.metadata = {"agent-ä", 12345678901ull, -42, Pose{{1, 2, 3}, {0.1, 0.2, 0.3, 0.9}}};
  record.counts = {900, 120, 780, 0.137};
  record.boxes_used = {{0, 0.5f, cv::Rect2f(1, 2, 30, 40)}, {2, 0.9f, cv::Rect2f(5, 6, 7, 8)}};
  auto decoded = DecodePlaceRecord(EncodePlaceRecord(record));
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->id, record.id);
  EXPECT_EQ(decoded->metadata, record.metadata);
  EXPECT_EQ(decoded->counts.static_, 780u);
  ASSERT_EQ(decoded->boxes_used.size(), 2u);
  EXPECT_EQ(decoded->boxes_used[1].rect, record.boxes_used[1].rect);

  BowVector bow = {{3, 0.25f}, {17, 0.5f}, {4000000, 0.25f}};
  auto bow_decoded = DecodeBow(EncodeBow(bow));
  ASSERT_TRUE(bow_decoded.ok());
  EXPECT_EQ(*bow_decoded, bow);

  FeatureSet features = testing::ExtractFile(testing::RtabmapFramePath(1), 300);
  DirectIndex direct;
  direct.levels_up = 2;
  direct.node_ids = {5, 9};
  direct.offsets = {0, 2, 3};
  direct.feature_ids = {0, 7, 3};
  FeatureSet features_out;
  DirectIndex direct_out;
  ASSERT_TRUE(DecodeFeatures(EncodeFeatures(features, direct), &features_out, &direct_out).ok());
  EXPECT_EQ(features_out.keypoints, features.keypoints);
  EXPECT_EQ(features_out.descriptors, features.descriptors);
  EXPECT_EQ(direct_out, direct);

  DatabaseConfig config;
  config.filter.method = FilterMethod::kExactCoverage;
  config.verification.mode = VerificationMode::kDirectIndex;
  config.dynamic_classes = {0, 2};
  auto config_out = DecodeDatabaseConfig(EncodeDatabaseConfig(config));
  ASSERT_TRUE(config_out.ok()) << config_out.status().ToString();
  EXPECT_EQ(config_out->filter.method, FilterMethod::kExactCoverage);
  EXPECT_EQ(config_out->verification.mode, VerificationMode::kDirectIndex);
  EXPECT_EQ(config_out->dynamic_classes, config.dynamic_classes);
}

TEST(Codec, DamagedBytesAreCorruptionNotACrash) {
  PlaceRecord record;
  record.id = 5;
  record.counts = {10, 0, 10, 0};
  const std::string good = EncodePlaceRecord(record);
  for (size_t cut = 0; cut < good.size(); ++cut) {
    auto decoded = DecodePlaceRecord(std::string_view(good).substr(0, cut));
    ASSERT_FALSE(decoded.ok());
    EXPECT_EQ(decoded.status().code(), StatusCode::kCorruption);
  }
  std::string wrong_version = good;
  wrong_version[0] = 9;
  EXPECT_NE(DecodePlaceRecord(wrong_version).status().message().find("version"), std::string::npos);
  // A huge claimed count must not allocate or read past the end.
  std::string bow = {1, char(0xFF), char(0xFF), char(0xFF), char(0xFF), 0x0F};
  EXPECT_EQ(DecodeBow(bow).status().code(), StatusCode::kCorruption);
  EXPECT_EQ(DecodeDatabaseConfig("{not json").status().code(), StatusCode::kCorruption);
  EXPECT_EQ(DecodePlaceKey("abc").status().code(), StatusCode::kCorruption);
}

TEST_F(StorageTest, ReopenGivesIdenticalResultsOnRtabmapAndCamVid) {
  std::vector<Observation> frames;
  for (int i = 1; i <= 84; ++i) frames.push_back(RtabmapFrame(i));
  auto camvid = testing::CamVidFrames();
  for (size_t i = 0; i < camvid.size(); i += 12) {
    Observation observation;
    observation.image = testing::ReadGray(camvid[i].image_path);
    observation.dynamic.mask = testing::CamVidDynamicMask(camvid[i]);
    observation.metadata.agent_id = camvid[i].sequence;
    observation.metadata.sequence = uint64_t(camvid[i].frame);
    frames.push_back(observation);
  }
  MapOptions options;
  options.database.filter.method = FilterMethod::kExactCoverage;
  options.database.verification.mode = VerificationMode::kExhaustive;
  std::vector<Ranked> before;
  MapStats stats_before;
  std::map<PlaceId, size_t> frame_of;  // stored place -> its frame
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("mixed", options, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    for (size_t i = 0; i < frames.size(); i += 2) {
      auto added = (*map)->Add(frames[i]);
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      if (added->stored) frame_of[added->id] = i;
    }
    ASSERT_GT(frame_of.size(), 50u);
    ASSERT_TRUE((*map)->RemovePlace(3).ok());
    before = QueryAll(**map, frames);
    stats_before = (*map)->Stats();
    EXPECT_GT(stats_before.bytes_on_disk, 0u);
    EXPECT_GT(stats_before.database.descriptors_dropped, 0u) << "CamVid masks dropped nothing";
  }
  auto dir = OpenDir();
  auto map = dir->OpenMap("mixed", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  ASSERT_TRUE((*map)->VerifyIntegrity().ok());
  const MapStats stats_after = (*map)->Stats();
  EXPECT_EQ(stats_after.database.places, stats_before.database.places);
  EXPECT_EQ(stats_after.database.descriptors_kept, stats_before.database.descriptors_kept);
  EXPECT_EQ(stats_after.database.descriptors_dropped, stats_before.database.descriptors_dropped);
  const std::vector<Ranked> after = QueryAll(**map, frames);
  ASSERT_EQ(after.size(), before.size());
  for (size_t q = 0; q < before.size(); ++q) {
    EXPECT_EQ(after[q], before[q]) << "query " << q << " differs after reopen";
  }
  // The metadata survived too, and ids are never reused.
  for (const auto& [id, frame] : frame_of) {
    if (id == 3) continue;
    auto place = (*map)->GetPlace(id);
    ASSERT_TRUE(place.ok()) << place.status().ToString();
    EXPECT_EQ(place->record.metadata, frames[frame].metadata);
    EXPECT_EQ(place->payload.features.size(), place->record.counts.static_);
  }
  EXPECT_EQ((*map)->GetPlace(3).status().code(), StatusCode::kNotFound);
  auto added = (*map)->Add(frames[1]);
  ASSERT_TRUE(added.ok() && added->stored);
  EXPECT_EQ(added->id, frame_of.rbegin()->first + 1);
}

TEST_F(StorageTest, ManyMapsCreateListDelete) {
  auto dir = OpenDir();
  EXPECT_TRUE(dir->ListMaps().empty());
  ASSERT_TRUE(dir->CreateMap("alpha", {}, vocabulary_).ok());
  ASSERT_TRUE(dir->CreateMap("beta-2", {}, vocabulary_).ok());
  EXPECT_EQ(dir->CreateMap("alpha", {}, vocabulary_).status().code(), StatusCode::kAlreadyExists);
  EXPECT_EQ(dir->CreateMap("../evil", {}, vocabulary_).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(dir->CreateMap("", {}, vocabulary_).status().code(), StatusCode::kInvalidArgument);
  MapOptions bad;
  bad.database.orb.max_features = -3;
  EXPECT_EQ(dir->CreateMap("gamma", bad, vocabulary_).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(dir->ListMaps(), (std::vector<std::string>{"alpha", "beta-2"}));

  auto alpha = dir->OpenMap("alpha", vocabulary_);
  ASSERT_TRUE(alpha.ok());
  ASSERT_TRUE((*alpha)->Add(RtabmapFrame(1)).ok());
  ASSERT_TRUE(dir->DeleteMap("alpha").ok());
  EXPECT_EQ(dir->ListMaps(), (std::vector<std::string>{"beta-2"}));
  // A holder of the deleted map gets a clear error, not a crash.
  EXPECT_EQ((*alpha)->Add(RtabmapFrame(2)).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(dir->OpenMap("alpha", vocabulary_).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(dir->DeleteMap("alpha").code(), StatusCode::kNotFound);
  // The name is free again.
  auto recreated = dir->CreateMap("alpha", {}, vocabulary_);
  ASSERT_TRUE(recreated.ok()) << recreated.status().ToString();
  alpha->reset();
  auto info = dir->ReadMapInfo("beta-2");
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->vocabulary_checksum, vocabulary_->checksum());
  // The layer above stores its own settings with the map, opaque to storage.
  MapOptions with_service;
  with_service.service_json = R"({"box_source":"server"})";
  ASSERT_TRUE(dir->CreateMap("gamma", with_service, vocabulary_).ok());
  dir->CloseMap("gamma");
  auto gamma = dir->ReadMapInfo("gamma");
  ASSERT_TRUE(gamma.ok()) << gamma.status().ToString();
  EXPECT_EQ(gamma->options.service_json, with_service.service_json);
}

TEST_F(StorageTest, AnotherVocabularyIsRefused) {
  {
    auto dir = OpenDir();
    ASSERT_TRUE(dir->CreateMap("m", {}, vocabulary_).ok());
  }
  // A different vocabulary: the same tree with one word weight changed.
  VocabularyTree tree = vocabulary_->ToTree();
  for (size_t i = 0; i < tree.word_id.size(); ++i) {
    if (tree.word_id[i] >= 0) {
      tree.weight[i] += 1.0f;
      break;
    }
  }
  auto other = Vocabulary::FromTree(tree);
  ASSERT_TRUE(other.ok()) << other.status().ToString();
  auto dir = OpenDir();
  auto refused = dir->OpenMap("m", *other);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find(vocabulary_->checksum_hex()), std::string::npos);
  auto map = dir->OpenMap("m", vocabulary_);
  ASSERT_TRUE(map.ok());
  EXPECT_EQ((*map)->CheckVocabulary(**other).code(), StatusCode::kFailedPrecondition);
  EXPECT_TRUE((*map)->CheckVocabulary(*vocabulary_).ok());
}

TEST_F(StorageTest, CheckpointAndRestore) {
  auto dir = OpenDir();
  auto map = dir->CreateMap("source", {}, vocabulary_);
  ASSERT_TRUE(map.ok());
  for (int i = 1; i <= 12; ++i) ASSERT_TRUE((*map)->Add(RtabmapFrame(i)).ok());
  const std::string backup = root_ + "/backup";
  ASSERT_TRUE((*map)->Checkpoint(backup).ok());
  EXPECT_EQ((*map)->Checkpoint(backup).code(), StatusCode::kAlreadyExists);
  // Writes after the checkpoint are not in it.
  ASSERT_TRUE((*map)->Add(RtabmapFrame(13)).ok());

  ASSERT_TRUE(dir->RestoreMap("restored", backup).ok());
  EXPECT_EQ(dir->RestoreMap("restored", backup).code(), StatusCode::kAlreadyExists);
  EXPECT_EQ(dir->RestoreMap("x", root_).code(), StatusCode::kInvalidArgument);
  auto restored = dir->OpenMap("restored", vocabulary_);
  ASSERT_TRUE(restored.ok()) << restored.status().ToString();
  EXPECT_EQ((*restored)->info().name, "restored");
  EXPECT_EQ((*restored)->Stats().database.places, 12u);
  ASSERT_TRUE((*restored)->VerifyIntegrity().ok());
  auto result = (*restored)->Query(RtabmapFrame(7), {});
  ASSERT_TRUE(result.ok());
  ASSERT_FALSE(result->matches.empty());
  EXPECT_EQ(result->matches[0].place, 7u);
}

TEST_F(StorageTest, InvalidObservationsAreCountedOrKeptAsMetadata) {
  auto dir = OpenDir();
  MapOptions keep;
  keep.store_invalid = true;
  auto map = dir->CreateMap("keeps-invalid", keep, vocabulary_);
  auto plain = dir->CreateMap("counts-invalid", {}, vocabulary_);
  ASSERT_TRUE(map.ok() && plain.ok());
  Observation covered = RtabmapFrame(9);
  covered.dynamic.boxes.push_back(
      {0, 0.9f, cv::Rect2f(0, 0, float(covered.image.cols), float(covered.image.rows))});
  for (const std::shared_ptr<PlaceMap>& m : {*map, *plain}) {
    auto added = m->Add(covered);
    ASSERT_TRUE(added.ok());
    EXPECT_FALSE(added->stored);
    ASSERT_TRUE(m->Add(RtabmapFrame(10)).ok());
  }
  EXPECT_EQ((*map)->Stats().invalid_stored, 1u);
  EXPECT_EQ((*plain)->Stats().invalid_stored, 0u);
  auto kept = (*map)->InvalidObservations(10);
  ASSERT_EQ(kept.size(), 1u);
  EXPECT_EQ(kept[0].metadata.sequence, 9u);
  EXPECT_EQ(kept[0].counts.static_, 0u);
  EXPECT_NE(kept[0].reason.find("placeThreshold"), std::string::npos);
  map->reset();
  plain->reset();
  dir.reset();

  auto reopened = OpenDir();
  auto again = reopened->OpenMap("keeps-invalid", vocabulary_);
  auto plain_again = reopened->OpenMap("counts-invalid", vocabulary_);
  ASSERT_TRUE(again.ok() && plain_again.ok());
  EXPECT_EQ((*again)->Stats().database.invalid_rejected, 1u);
  EXPECT_EQ((*plain_again)->Stats().database.invalid_rejected, 1u);
  EXPECT_EQ((*again)->Stats().invalid_stored, 1u);
  EXPECT_EQ((*again)->Stats().database.places, 1u);
}

TEST_F(StorageTest, GroupCommitAcknowledgesDurablyAndConcurrently) {
  StorageOptions options;
  options.sync = SyncMode::kGroupCommit;
  options.group_commit_delay_ms = 3;
  std::vector<ProcessedFrame> frames;
  {
    auto dir = OpenDir(options);
    auto map = dir->CreateMap("grouped", {}, vocabulary_);
    ASSERT_TRUE(map.ok());
    for (int i = 1; i <= 16; ++i) {
      auto frame = (*map)->Process(RtabmapFrame(i));
      ASSERT_TRUE(frame.ok());
      frames.push_back(*frame);
    }
    std::vector<std::thread> writers;
    std::atomic<int> failures{0};
    for (int t = 0; t < 4; ++t) {
      writers.emplace_back([&, t] {
        for (size_t i = size_t(t); i < frames.size(); i += 4) {
          if (!(*map)->Commit(frames[i], {}).ok()) failures.fetch_add(1);
        }
      });
    }
    for (auto& writer : writers) writer.join();
    EXPECT_EQ(failures.load(), 0);
  }
  auto dir = OpenDir(options);
  auto map = dir->OpenMap("grouped", vocabulary_);
  ASSERT_TRUE(map.ok());
  EXPECT_EQ((*map)->Stats().database.places, 16u);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

// Readers query while writers add and remove; run under ThreadSanitizer by tools/test.sh.
TEST_F(StorageTest, ConcurrentQueriesDuringIngestAndDeletion) {
  auto dir = OpenDir();
  MapOptions options;
  options.database.verification.mode = VerificationMode::kExhaustive;
  auto map = dir->CreateMap("busy", options, vocabulary_);
  ASSERT_TRUE(map.ok());
  std::vector<ProcessedFrame> frames;
  for (int i = 1; i <= 20; ++i) {
    auto frame = (*map)->Process(RtabmapFrame(i));
    ASSERT_TRUE(frame.ok());
    frames.push_back(*frame);
  }
  for (size_t i = 0; i < 5; ++i) ASSERT_TRUE((*map)->Commit(frames[i], {}).ok());
  std::atomic<bool> done{false};
  std::atomic<int> failures{0};
  std::atomic<int> queries{0};
  std::vector<std::thread> threads;
  for (int r = 0; r < 2; ++r) {
    threads.emplace_back([&, r] {
      for (size_t i = size_t(r); !done.load(); ++i) {
        QueryResult result = (*map)->Search(frames[i % frames.size()], {});
        if (!result.valid) failures.fetch_add(1);
        (void)(*map)->Stats();
        queries.fetch_add(1);
      }
    });
  }
  std::thread writer([&] {
    for (size_t i = 5; i < frames.size(); ++i) {
      auto added = (*map)->Commit(frames[i], {});
      if (!added.ok()) failures.fetch_add(1);
      if (i % 4 == 0 && !(*map)->RemovePlace(PlaceId(i - 3)).ok()) failures.fetch_add(1);
    }
    done.store(true);
  });
  writer.join();
  for (auto& t : threads) t.join();
  EXPECT_EQ(failures.load(), 0);
  EXPECT_GT(queries.load(), 0);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

TEST_F(StorageTest, ForeignOrCorruptedFilesGiveClearErrors) {
  // A non-empty directory that is not ours is never touched.
  const std::string foreign = root_ + "/foreign";
  fs::create_directories(foreign);
  std::ofstream(foreign + "/notes.txt") << "someone else's files";
  auto refused = DataDirectory::Open(foreign);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_TRUE(fs::exists(foreign + "/notes.txt"));

  // A damaged marker.
  const std::string damaged = root_ + "/damaged";
  ASSERT_TRUE(DataDirectory::Open(damaged).ok());
  std::ofstream(damaged + "/PLACEDB_DATA_DIR") << "garbage";
  EXPECT_EQ(DataDirectory::Open(damaged).status().code(), StatusCode::kCorruption);

  auto dir = OpenDir();
  // A directory under maps/ that is not a database.
  fs::create_directories(root_ + "/data/maps/junk");
  std::ofstream(root_ + "/data/maps/junk/file") << "x";
  auto junk = dir->OpenMap("junk", vocabulary_);
  ASSERT_FALSE(junk.ok());
  EXPECT_EQ(junk.status().code(), StatusCode::kCorruption);

  // A map whose every file is overwritten with garbage.
  {
    auto map = dir->CreateMap("broken", {}, vocabulary_);
    ASSERT_TRUE(map.ok());
    for (int i = 1; i <= 4; ++i) ASSERT_TRUE((*map)->Add(RtabmapFrame(i)).ok());
    dir->CloseMap("broken");
  }
  for (const auto& entry : fs::directory_iterator(root_ + "/data/maps/broken")) {
    if (!entry.is_regular_file()) continue;
    std::fstream file(entry.path(), std::ios::in | std::ios::out | std::ios::binary);
    const std::string noise(64, '\x5a');
    file.seekp(0);
    file.write(noise.data(), std::streamsize(noise.size()));
  }
  auto broken = dir->OpenMap("broken", vocabulary_);
  ASSERT_FALSE(broken.ok());
  EXPECT_TRUE(broken.status().code() == StatusCode::kCorruption ||
              broken.status().code() == StatusCode::kIoError)
      << broken.status().ToString();
  // Other maps are unaffected.
  ASSERT_TRUE(dir->CreateMap("healthy", {}, vocabulary_).ok());
}

}  // namespace
}  // namespace placedb
