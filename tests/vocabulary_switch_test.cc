// A map's own vocabulary (issue 29): PlaceMap::AdaptVocabulary / RevertVocabulary on a real
// RocksDB in a temp directory with the RTAB-Map loop's frames: the switch, what the map stores
// and opens with, writes and queries during a switch, refusals, and SIGKILL at every phase.
#include <gtest/gtest.h>
#include <rocksdb/db.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <thread>

#include "core/base/text.h"
#include "core/storage/map_store.h"
#include "tests/raw_map.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace fs = std::filesystem;

namespace placedb {
namespace {

constexpr char kChildEnv[] = "PLACEDB_SWITCH_CHILD";  // the data directory
constexpr char kPhaseEnv[] = "PLACEDB_SWITCH_PHASE";  // the VocabularyPhase to die at
constexpr char kRevertEnv[] = "PLACEDB_SWITCH_REVERT";

// Small and quick to learn (the shape is not what these tests are about).
AdaptOptions Quick() {
  AdaptOptions options;
  options.learning.branching = 8;
  options.learning.depth = 4;
  options.learning.max_sample_descriptors = 20000;
  return options;
}

AnyVocabulary Default() {
  return AnyVocabulary(testing::DefaultVocabulary());
}

PlaceMetadata Metadata(size_t frame) {
  PlaceMetadata metadata;
  metadata.sequence = frame;
  metadata.agent_id = "robot";
  return metadata;
}

// Every frame's own place is the best match, with the full self-match score.
void ExpectEachFrameFindsItsPlace(const PlaceMap& map, const std::vector<ProcessedFrame>& frames,
                                  const std::vector<PlaceId>& places) {
  ASSERT_EQ(frames.size(), places.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    const QueryResult result = map.Search(frames[i], {});
    ASSERT_TRUE(result.valid) << "frame " << i << ": " << result.rejection;
    ASSERT_FALSE(result.matches.empty()) << "frame " << i;
    EXPECT_EQ(result.matches.front().place, places[i]) << "frame " << i;
    EXPECT_NEAR(result.matches.front().score, 1.0, 1e-2) << "frame " << i;
  }
}

std::vector<std::string> FamiliesOf(const std::string& map_dir) {
  std::vector<std::string> families;
  EXPECT_TRUE(rocksdb::DB::ListColumnFamilies(rocksdb::DBOptions(), map_dir, &families).ok());
  std::sort(families.begin(), families.end());
  return families;
}

bool HasFamily(const std::string& map_dir, const std::string& name) {
  const auto families = FamiliesOf(map_dir);
  return std::find(families.begin(), families.end(), name) != families.end();
}

class VocabularySwitchTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    root_ = testing::MakeTempDir("placedb-vocabulary-switch");
    auto dir = DataDirectory::Open(root_ + "/data");
    ASSERT_TRUE(dir.ok()) << dir.status().ToString();
    dir_ = std::move(dir).value();
    auto map = dir_->CreateMap("lab", {}, Default());
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    map_ = *map;
    frames_ = testing::ProcessRtabmapFrames(*map_->database(), 40);
    ASSERT_GE(frames_.size(), 30u);
  }
  void TearDown() override {
    map_.reset();
    dir_.reset();
    if (!root_.empty()) fs::remove_all(root_);
  }

  // Stores frames [begin, end) and returns their places.
  std::vector<PlaceId> Store(size_t begin, size_t end) {
    std::vector<PlaceId> places;
    for (size_t i = begin; i < end; ++i) {
      auto added = map_->Commit(frames_[i], Metadata(i));
      EXPECT_TRUE(added.ok() && added->stored) << added.status().ToString();
      places.push_back(added.ok() ? added->id : 0);
    }
    return places;
  }

  std::shared_ptr<PlaceMap> Reopen(AnyVocabulary vocabulary) {
    map_.reset();
    dir_->CloseMap("lab");
    auto map = dir_->OpenMap("lab", std::move(vocabulary));
    EXPECT_TRUE(map.ok()) << map.status().ToString();
    map_ = map.ok() ? *map : nullptr;
    return map_;
  }

  std::string MapDir() const { return root_ + "/data/maps/lab"; }

  std::string root_;
  std::unique_ptr<DataDirectory> dir_;
  std::shared_ptr<PlaceMap> map_;
  std::vector<ProcessedFrame> frames_;
};

TEST_F(VocabularySwitchTest, AdaptsStoresTheVocabularyAndReverts) {
  const std::vector<PlaceId> places = Store(0, 30);
  const uint64_t file_checksum = Default().checksum();
  EXPECT_FALSE(map_->info().vocabulary.stored());

  auto adapted = map_->AdaptVocabulary(Quick());
  ASSERT_TRUE(adapted.ok()) << adapted.status().ToString();
  EXPECT_EQ(adapted->generation, 1u);
  EXPECT_EQ(adapted->current.origin, "learned");
  EXPECT_NE(adapted->current.checksum, file_checksum);
  EXPECT_EQ(adapted->current.branching, 8u);
  EXPECT_EQ(adapted->current.depth, 4u);
  EXPECT_EQ(adapted->current.places_offered, 30u);
  EXPECT_GT(adapted->current.descriptors_sampled, 5000u);
  EXPECT_LE(adapted->current.descriptors_sampled, 20000u + 2000u);  // the bound plus one place
  EXPECT_GT(adapted->current.learned_unix_ms, 0);
  ASSERT_TRUE(adapted->previous.has_value());
  EXPECT_EQ(adapted->previous->origin, "file");
  EXPECT_EQ(adapted->previous->checksum, file_checksum);
  EXPECT_EQ(adapted->places_reindexed, 30u);
  const MapInfo info = map_->info();
  EXPECT_EQ(info.vocabulary_checksum, adapted->current.checksum);
  EXPECT_EQ(info.vocabulary, *adapted);
  EXPECT_EQ(map_->vocabulary().checksum(), adapted->current.checksum);
  EXPECT_EQ(map_->database()->vocabulary().checksum(), adapted->current.checksum);
  ASSERT_TRUE(map_->VerifyIntegrity().ok()) << map_->VerifyIntegrity().ToString();
  // Frames processed with the file's vocabulary are transformed again when searched or stored.
  ExpectEachFrameFindsItsPlace(
      *map_, std::vector<ProcessedFrame>(frames_.begin(), frames_.begin() + 30), places);
  std::vector<PlaceId> more = Store(30, 34);
  std::vector<PlaceId> all = places;
  all.insert(all.end(), more.begin(), more.end());
  const std::vector<ProcessedFrame> stored(frames_.begin(), frames_.begin() + 34);
  ExpectEachFrameFindsItsPlace(*map_, stored, all);
  EXPECT_TRUE(HasFamily(MapDir(), "bow.1"));

  // The map opens without any vocabulary file, with the one it learned.
  ASSERT_TRUE(Reopen(AnyVocabulary()));
  EXPECT_EQ(map_->info().vocabulary, *adapted);
  EXPECT_EQ(map_->vocabulary().checksum(), adapted->current.checksum);
  ASSERT_TRUE(map_->VerifyIntegrity().ok()) << map_->VerifyIntegrity().ToString();
  ExpectEachFrameFindsItsPlace(*map_, stored, all);
  // A file's vocabulary given at open does not replace it.
  ASSERT_TRUE(Reopen(Default()));
  EXPECT_EQ(map_->vocabulary().checksum(), adapted->current.checksum);

  // One command back to the file's vocabulary, which the map now stores too.
  auto reverted = map_->RevertVocabulary();
  ASSERT_TRUE(reverted.ok()) << reverted.status().ToString();
  EXPECT_EQ(reverted->generation, 2u);
  EXPECT_EQ(reverted->current.origin, "file");
  EXPECT_EQ(reverted->current.checksum, file_checksum);
  ASSERT_TRUE(reverted->previous.has_value());
  EXPECT_EQ(reverted->previous->checksum, adapted->current.checksum);
  EXPECT_EQ(reverted->places_reindexed, 34u);
  EXPECT_FALSE(HasFamily(MapDir(), "bow.1"));
  EXPECT_TRUE(HasFamily(MapDir(), "bow.2"));
  ExpectEachFrameFindsItsPlace(*map_, stored, all);
  ASSERT_TRUE(Reopen(AnyVocabulary()));
  EXPECT_EQ(map_->vocabulary().checksum(), file_checksum);
  ASSERT_TRUE(map_->VerifyIntegrity().ok()) << map_->VerifyIntegrity().ToString();
  ExpectEachFrameFindsItsPlace(*map_, stored, all);
  // The place's direct index is the current vocabulary's: verification finds inliers.
  QueryOptions verify;
  verify.verified_only = true;
  const QueryResult verified = map_->Search(frames_[3], verify);
  ASSERT_FALSE(verified.matches.empty());
  EXPECT_EQ(verified.matches.front().place, all[3]);
  EXPECT_GT(verified.matches.front().inliers, 100);
}

TEST_F(VocabularySwitchTest, ConcurrentWritesAndQueriesGoOnDuringTheSwitch) {
  const std::vector<PlaceId> first = Store(0, 20);
  std::atomic<bool> done{false};
  std::atomic<size_t> writes{0};
  std::vector<std::pair<size_t, PlaceId>> added;  // the writer's
  Status writer_status, reader_status;
  std::thread writer([&] {
    // Commit, the commit queue and removals, round and round while the switch runs.
    for (size_t round = 0; !done.load() || round < 4; ++round) {
      const size_t i = 20 + round % 20;
      if (round % 2 == 0) {
        auto stored = map_->Commit(frames_[i], Metadata(i));
        if (!stored.ok()) {
          writer_status = stored.status();
          return;
        }
        added.emplace_back(i, stored->id);
      } else {
        auto stored = map_->Enqueue(frames_[i], Metadata(i))->Wait();
        if (!stored.ok()) {
          writer_status = stored.status();
          return;
        }
        added.emplace_back(i, stored->id);
      }
      if (round % 5 == 4) {
        if (Status removed = map_->RemovePlace(added.back().second); !removed.ok()) {
          writer_status = removed;
          return;
        }
        added.pop_back();
      }
      ++writes;
    }
  });
  std::thread reader([&] {
    for (size_t round = 0; !done.load() || round < 4; ++round) {
      const QueryResult result = map_->Search(frames_[round % 20], {});
      if (!result.valid || result.matches.empty() ||
          result.matches.front().place != first[round % 20]) {
        reader_status = Status::Internal("frame " + std::to_string(round % 20) +
                                         " did not find its place: " + result.rejection);
        return;
      }
    }
  });
  // Each phase waits for more writes, so places are stored and removed while the new index is
  // built and caught up (not only before or after the switch).
  AdaptOptions options = Quick();
  options.on_phase = [&](VocabularyPhase phase) {
    if (phase != VocabularyPhase::kLearned && phase != VocabularyPhase::kReindexed) return;
    const size_t target = writes.load() + 6;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (writes.load() < target && writer_status.ok() &&
           std::chrono::steady_clock::now() < deadline) {
      std::this_thread::yield();
    }
  };
  auto adapted = map_->AdaptVocabulary(options);
  done = true;
  writer.join();
  reader.join();
  ASSERT_TRUE(adapted.ok()) << adapted.status().ToString();
  ASSERT_TRUE(writer_status.ok()) << writer_status.ToString();
  ASSERT_TRUE(reader_status.ok()) << reader_status.ToString();
  ASSERT_TRUE(map_->VerifyIntegrity().ok()) << map_->VerifyIntegrity().ToString();
  EXPECT_EQ(map_->Stats().database.places, first.size() + added.size());
  std::vector<ProcessedFrame> frames(frames_.begin(), frames_.begin() + 20);
  std::vector<PlaceId> places = first;
  ExpectEachFrameFindsItsPlace(*map_, frames, places);
  // Every place the writer kept is in the new index under its id, found by its own frame.
  for (const auto& [frame, id] : added) {
    ASSERT_NE(map_->database()->Get(id), nullptr) << "place " << id << " lost by the switch";
    QueryOptions options;
    options.top_k = 1000;
    bool found = false;
    for (const Match& match : map_->Search(frames_[frame], options).matches) {
      if (match.place == id) {
        found = true;
        EXPECT_NEAR(match.score, 1.0, 1e-2);
      }
    }
    EXPECT_TRUE(found) << "place " << id;
  }
  ASSERT_TRUE(Reopen(AnyVocabulary()));
  EXPECT_EQ(map_->Stats().database.places, first.size() + added.size());
}

TEST_F(VocabularySwitchTest, RefusesWhatItCannotDoAndLeavesTheMapAsItWas) {
  Store(0, 3);
  auto small = map_->AdaptVocabulary(Quick());
  ASSERT_EQ(small.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(small.status().message().find("too small to learn a vocabulary from"),
            std::string::npos)
      << small.status().ToString();
  EXPECT_NE(small.status().message().find("3 places"), std::string::npos);
  EXPECT_FALSE(map_->info().vocabulary.stored());
  EXPECT_EQ(FamiliesOf(MapDir()).size(), 8u);  // no family left behind

  auto none = map_->RevertVocabulary();
  ASSERT_EQ(none.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(none.status().message().find("no previous vocabulary"), std::string::npos);

  AdaptOptions bad = Quick();
  bad.learning.depth = 40;
  EXPECT_EQ(map_->AdaptVocabulary(bad).status().code(), StatusCode::kInvalidArgument);

  // A second switch while one runs is refused; the first completes.
  Store(3, 30);
  Status second = Status::Internal("not tried");
  AdaptOptions watched = Quick();
  watched.on_phase = [&](VocabularyPhase phase) {
    if (phase == VocabularyPhase::kLearned) second = map_->AdaptVocabulary(Quick()).status();
  };
  auto first = map_->AdaptVocabulary(watched);
  ASSERT_TRUE(first.ok()) << first.status().ToString();
  EXPECT_EQ(second.code(), StatusCode::kFailedPrecondition) << second.ToString();
  EXPECT_NE(second.message().find("already switching"), std::string::npos);
  EXPECT_FALSE(map_->switching_vocabulary());

  // A damaged previous vocabulary: RevertVocabulary says so and changes nothing.
  map_.reset();
  dir_->CloseMap("lab");
  const std::string previous_key = "vocabulary." + Hex64(first->previous->checksum);
  const std::string current_key = "vocabulary." + Hex64(first->current.checksum);
  testing::EditRawMap(MapDir(), [&](rocksdb::DB* db, auto& handles) {
    std::string value;
    ASSERT_TRUE(db->Get({}, handles[0], previous_key, &value).ok());
    value[value.size() / 2] = char(value[value.size() / 2] ^ 0x5a);
    ASSERT_TRUE(db->Put({}, handles[0], previous_key, value).ok());
  });
  ASSERT_TRUE(Reopen(AnyVocabulary()));
  auto revert = map_->RevertVocabulary();
  ASSERT_EQ(revert.status().code(), StatusCode::kCorruption) << revert.status().ToString();
  EXPECT_NE(revert.status().message().find("previous vocabulary is damaged"), std::string::npos);
  EXPECT_EQ(map_->info().vocabulary, *first);
  ASSERT_TRUE(map_->VerifyIntegrity().ok());

  // A damaged stored vocabulary: the map does not open, and says why.
  map_.reset();
  dir_->CloseMap("lab");
  testing::EditRawMap(MapDir(), [&](rocksdb::DB* db, auto& handles) {
    std::string value;
    ASSERT_TRUE(db->Get({}, handles[0], current_key, &value).ok());
    ASSERT_TRUE(db->Put({}, handles[0], current_key, value.substr(0, value.size() / 3)).ok());
  });
  auto damaged = dir_->OpenMap("lab", Default());
  ASSERT_EQ(damaged.status().code(), StatusCode::kCorruption);
  EXPECT_NE(damaged.status().message().find("stored vocabulary is damaged"), std::string::npos)
      << damaged.status().ToString();
}

TEST_F(VocabularySwitchTest, ACancelledSwitchLeavesTheMapAsItWas) {
  const std::vector<PlaceId> places = Store(0, 30);
  for (const VocabularyPhase at : {VocabularyPhase::kLearned, VocabularyPhase::kReindexed}) {
    std::atomic<bool> cancel{false};
    AdaptOptions options = Quick();
    options.cancel = &cancel;
    options.on_phase = [&](VocabularyPhase phase) {
      if (phase == at) cancel = true;
    };
    auto cancelled = map_->AdaptVocabulary(options);
    ASSERT_EQ(cancelled.status().code(), StatusCode::kCancelled) << cancelled.status().ToString();
    EXPECT_FALSE(map_->info().vocabulary.stored());
    EXPECT_EQ(map_->vocabulary().checksum(), Default().checksum());
    EXPECT_EQ(FamiliesOf(MapDir()).size(), 8u);  // the half-built family is dropped
    ExpectEachFrameFindsItsPlace(
        *map_, std::vector<ProcessedFrame>(frames_.begin(), frames_.begin() + 30), places);
  }
}

TEST_F(VocabularySwitchTest, CheckpointsCarryTheVocabulary) {
  const std::vector<PlaceId> places = Store(0, 30);
  auto adapted = map_->AdaptVocabulary(Quick());
  ASSERT_TRUE(adapted.ok()) << adapted.status().ToString();
  const std::string checkpoint = root_ + "/checkpoint";
  ASSERT_TRUE(map_->Checkpoint(checkpoint).ok());
  ASSERT_TRUE(dir_->RestoreMap("copy", checkpoint).ok());
  auto copy = dir_->OpenMap("copy", AnyVocabulary());
  ASSERT_TRUE(copy.ok()) << copy.status().ToString();
  EXPECT_EQ((*copy)->info().vocabulary, *adapted);
  ExpectEachFrameFindsItsPlace(
      **copy, std::vector<ProcessedFrame>(frames_.begin(), frames_.begin() + 30), places);
}

TEST_F(VocabularySwitchTest, SiftMapsLearnAFloatVocabulary) {
  const auto sift = testing::SiftVocabulary();
  ASSERT_TRUE(sift);
  MapOptions options;
  options.database.feature_type = FeatureType::kSift;
  auto map = dir_->CreateMap("sift", options, AnyVocabulary(sift));
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  const std::vector<ProcessedFrame> frames = testing::ProcessRtabmapFrames(*(*map)->database(), 24);
  std::vector<PlaceId> places;
  for (size_t i = 0; i < frames.size(); ++i) {
    auto added = (*map)->Commit(frames[i], Metadata(i));
    ASSERT_TRUE(added.ok()) << added.status().ToString();
    places.push_back(added->id);
  }
  AdaptOptions small = Quick();  // SIFT keeps ~110 descriptors per frame here
  small.learning.min_descriptors = 2000;
  auto adapted = (*map)->AdaptVocabulary(small);
  ASSERT_TRUE(adapted.ok()) << adapted.status().ToString();
  EXPECT_EQ((*map)->vocabulary().feature_type(), FeatureType::kSift);
  EXPECT_STREQ((*map)->vocabulary().kind(), AnyVocabulary(sift).kind());
  EXPECT_NE(adapted->current.checksum, AnyVocabulary(sift).checksum());
  ASSERT_TRUE((*map)->VerifyIntegrity().ok());
  ExpectEachFrameFindsItsPlace(**map, frames, places);
  map->reset();
  dir_->CloseMap("sift");
  auto reopened = dir_->OpenMap("sift", AnyVocabulary());
  ASSERT_TRUE(reopened.ok()) << reopened.status().ToString();
  EXPECT_EQ((*reopened)->vocabulary().checksum(), adapted->current.checksum);
  ExpectEachFrameFindsItsPlace(**reopened, frames, places);
}

// The child: opens the map and switches (adapts, or reverts with PLACEDB_SWITCH_REVERT), dying
// by SIGKILL at the phase named in the environment.
[[noreturn]] void RunChild(const std::string& data_dir) {
  const int phase = std::atoi(std::getenv(kPhaseEnv));
  const bool revert = std::getenv(kRevertEnv) && std::string(std::getenv(kRevertEnv)) == "1";
  auto dir = DataDirectory::Open(data_dir);
  if (!dir.ok()) std::_Exit(3);
  auto map = (*dir)->OpenMap("lab", Default());
  if (!map.ok()) std::_Exit(4);
  AdaptOptions options = Quick();
  options.on_phase = [&](VocabularyPhase reached) {
    if (int(reached) == phase) kill(getpid(), SIGKILL);
  };
  auto switched = revert ? (*map)->RevertVocabulary(options) : (*map)->AdaptVocabulary(options);
  std::_Exit(switched.ok() ? 0 : 5);
}

// Runs the child to `phase` and returns how it ended.
int SwitchInChild(const std::string& data_dir, VocabularyPhase phase, bool revert) {
  std::vector<std::string> env_strings = {std::string(kChildEnv) + "=" + data_dir,
                                          std::string(kPhaseEnv) + "=" + std::to_string(int(phase)),
                                          std::string(kRevertEnv) + "=" + (revert ? "1" : "0")};
  for (char** e = environ; *e; ++e) env_strings.emplace_back(*e);
  std::vector<char*> envp;
  for (auto& e : env_strings) envp.push_back(e.data());
  envp.push_back(nullptr);
  const pid_t child = fork();
  if (child == 0) {
    execle("/proc/self/exe", "vocabulary_switch_child", static_cast<char*>(nullptr), envp.data());
    std::_Exit(127);
  }
  int status = 0;
  waitpid(child, &status, 0);
  return status;
}

// Cluster mode: replicas apply the same log. A vocabulary learned on one replica reaches the
// others in parts, and each switches at the switch record's sequence to the same bytes.
TEST_F(VocabularySwitchTest, ReplicasSwitchAtTheSameRecordToByteIdenticalVocabularies) {
  auto made = dir_->CreateMap("other", {}, Default());
  ASSERT_TRUE(made.ok()) << made.status().ToString();
  std::vector<std::shared_ptr<PlaceMap>> replicas = {map_, *made};
  const auto add = [&](size_t frame) {
    MapLogRecord record;
    record.frame = frames_[frame];  // processed with the default vocabulary
    record.metadata = Metadata(frame);
    return record;
  };
  std::vector<MapLogRecord> log;  // sequence = index + 1
  for (size_t i = 0; i < 30; ++i) log.push_back(add(i));
  // One replica learns; its bytes travel in 3 parts.
  for (const auto& replica : replicas) {
    std::vector<PlaceMap::SequencedRecord> batch;
    for (size_t i = 0; i < log.size(); ++i) batch.push_back({i + 1, &log[i]});
    ASSERT_TRUE(replica->ApplyBatch(batch).ok());
  }
  auto learned = replicas[0]->LearnVocabulary(Quick());
  ASSERT_TRUE(learned.ok()) << learned.status().ToString();
  EXPECT_EQ(learned->source.places_offered, 30u);
  EXPECT_EQ(replicas[0]->vocabulary().checksum(), Default().checksum());  // nothing switched
  const std::string bytes = learned->vocabulary.Serialize();
  const size_t part = bytes.size() / 3 + 1;
  for (uint32_t i = 0; i < 3; ++i) {
    MapLogRecord record;
    record.kind = MapLogRecord::Kind::kVocabularyPart;
    record.vocabulary_part = {learned->vocabulary.checksum(), i, 3, bytes.substr(i * part, part)};
    log.push_back(record);  // 31..33
  }
  MapLogRecord prepare;
  prepare.kind = MapLogRecord::Kind::kPrepareVocabulary;
  prepare.vocabulary_source.checksum = learned->vocabulary.checksum();
  prepare.vocabulary_parts = 3;
  log.push_back(prepare);  // 34
  log.push_back(add(30));  // 35: processed before the switch: transformed again at the switch
  MapLogRecord change;
  change.kind = MapLogRecord::Kind::kSwitchVocabulary;
  change.vocabulary_source = learned->source;
  change.vocabulary_parts = 3;
  log.push_back(change);   // 36
  log.push_back(add(31));  // 37: processed before the switch: transformed again when applied
  std::vector<PlaceId> places;
  for (PlaceId id = 1; id <= 30; ++id) places.push_back(id);
  places.push_back(35);
  places.push_back(37);
  const std::vector<ProcessedFrame> stored(frames_.begin(), frames_.begin() + 32);
  for (const auto& replica : replicas) {
    // Applied a record at a time for one replica, built ahead of the switch (as a shard does on
    // the prepare record) and then in one batch for the other.
    if (replica == replicas[0]) {
      for (size_t i = 30; i < log.size(); ++i) {
        auto applied = replica->ApplyAt(i + 1, log[i]);
        ASSERT_TRUE(applied.ok()) << applied.status().ToString();
        EXPECT_TRUE(*applied);
      }
    } else {
      std::vector<PlaceMap::SequencedRecord> batch;
      for (size_t i = 30; i < 35; ++i) batch.push_back({i + 1, &log[i]});
      auto applied = replica->ApplyBatch(batch);
      ASSERT_TRUE(applied.ok()) << applied.status().ToString();
      EXPECT_EQ(*applied, 5u);
      EXPECT_EQ(replica->prepared_vocabulary(), 0u);
      const Status prepared = replica->PrepareVocabularySwitch(learned->vocabulary.checksum(), 3);
      ASSERT_TRUE(prepared.ok()) << prepared.ToString();
      EXPECT_EQ(replica->prepared_vocabulary(), learned->vocabulary.checksum());
      EXPECT_EQ(replica->vocabulary().checksum(), Default().checksum());  // not switched yet
      batch.clear();
      for (size_t i = 35; i < log.size(); ++i) batch.push_back({i + 1, &log[i]});
      applied = replica->ApplyBatch(batch);
      ASSERT_TRUE(applied.ok()) << applied.status().ToString();
      EXPECT_EQ(*applied, 2u);
      EXPECT_EQ(replica->prepared_vocabulary(), 0u);
    }
    EXPECT_EQ(replica->applied_sequence(), 37u);
    EXPECT_EQ(replica->vocabulary().checksum(), learned->vocabulary.checksum());
    EXPECT_EQ(replica->vocabulary().Serialize(), bytes);
    const VocabularyRecord record = replica->info().vocabulary;
    EXPECT_EQ(record.generation, 1u);
    EXPECT_EQ(record.current, learned->source);
    ASSERT_TRUE(record.previous);
    EXPECT_EQ(record.previous->checksum, Default().checksum());
    EXPECT_EQ(record.places_reindexed, 31u);
    ExpectEachFrameFindsItsPlace(*replica, stored, places);
    ASSERT_TRUE(replica->VerifyIntegrity().ok()) << replica->VerifyIntegrity().ToString();
  }
  // The same places under the same ids with the same vectors on both.
  for (const PlaceId id : places) {
    auto a = replicas[0]->GetPlace(id), b = replicas[1]->GetPlace(id);
    ASSERT_TRUE(a.ok() && b.ok()) << id;
    EXPECT_EQ(a->payload.bow, b->payload.bow) << id;
  }
  // Reopened without any vocabulary file: the switch and its sequence are durable, the parts
  // gone (the vocabulary is stored whole).
  replicas[0].reset();
  map_ = Reopen(AnyVocabulary());
  ASSERT_TRUE(map_);
  replicas[0] = map_;
  EXPECT_EQ(map_->applied_sequence(), 37u);
  EXPECT_EQ(map_->vocabulary().checksum(), learned->vocabulary.checksum());
  ExpectEachFrameFindsItsPlace(*map_, stored, places);

  // A switch whose parts never arrived: CORRUPTION naming the part, nothing changed.
  MapLogRecord missing = change;
  missing.vocabulary_source.checksum ^= 1;
  auto refused = map_->ApplyAt(38, missing);
  EXPECT_EQ(refused.status().code(), StatusCode::kCorruption) << refused.status().ToString();
  EXPECT_NE(refused.status().message().find("part 0 of 3 is missing"), std::string::npos)
      << refused.status().ToString();
  EXPECT_EQ(map_->applied_sequence(), 37u);
  EXPECT_EQ(map_->vocabulary().checksum(), learned->vocabulary.checksum());
  EXPECT_EQ(map_->PrepareVocabularySwitch(missing.vocabulary_source.checksum, 3).code(),
            StatusCode::kCorruption);

  // Back to the previous vocabulary: a switch without parts (the replicas store it).
  MapLogRecord back;
  back.kind = MapLogRecord::Kind::kSwitchVocabulary;
  back.vocabulary_source = *map_->info().vocabulary.previous;
  for (const auto& replica : replicas) {
    auto applied = replica->ApplyAt(39, back);
    ASSERT_TRUE(applied.ok()) << applied.status().ToString();
    EXPECT_EQ(replica->vocabulary().checksum(), Default().checksum());
    EXPECT_EQ(replica->info().vocabulary.generation, 2u);
    EXPECT_EQ(replica->applied_sequence(), 39u);
    ExpectEachFrameFindsItsPlace(*replica, stored, places);
  }
  // A replica's vocabulary changes only through its log.
  EXPECT_EQ(map_->AdaptVocabulary(Quick()).status().code(), StatusCode::kFailedPrecondition);
  EXPECT_EQ(map_->InstallVocabulary(learned->vocabulary, learned->source).status().code(),
            StatusCode::kFailedPrecondition);
}

TEST_F(VocabularySwitchTest, SigkillAtEveryPhaseLeavesTheOldVocabularyOrTheNew) {
  const std::vector<PlaceId> places = Store(0, 30);
  const std::vector<ProcessedFrame> stored(frames_.begin(), frames_.begin() + 30);
  const std::string data_dir = root_ + "/data";
  uint64_t generation = 0;
  uint64_t checksum = Default().checksum();
  for (const bool revert : {false, true}) {
    for (const VocabularyPhase phase :
         {VocabularyPhase::kLearned, VocabularyPhase::kReindexed, VocabularyPhase::kCaughtUp,
          VocabularyPhase::kSwitched, VocabularyPhase::kCleaned}) {
      SCOPED_TRACE((revert ? "revert, phase " : "adapt, phase ") + std::to_string(int(phase)));
      map_.reset();
      dir_.reset();  // the child needs the directory's lock
      const int status = SwitchInChild(data_dir, phase, revert);
      ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL)
          << "child ended with " << (WIFEXITED(status) ? WEXITSTATUS(status) : -1);
      auto dir = DataDirectory::Open(data_dir);
      ASSERT_TRUE(dir.ok()) << dir.status().ToString();
      dir_ = std::move(dir).value();
      auto map = dir_->OpenMap("lab", Default());
      ASSERT_TRUE(map.ok()) << map.status().ToString();
      map_ = *map;
      const VocabularyRecord record = map_->info().vocabulary;
      if (phase < VocabularyPhase::kSwitched) {
        EXPECT_EQ(record.generation, generation);
        EXPECT_EQ(map_->vocabulary().checksum(), checksum);
      } else {
        EXPECT_EQ(record.generation, generation + 1);
        EXPECT_EQ(record.current.checksum, map_->vocabulary().checksum());
        ASSERT_TRUE(record.previous.has_value());
        EXPECT_EQ(record.previous->checksum, checksum);
        // Learning from the same places gives the same vocabulary: a second adaptation's is the
        // first's; a revert goes back to the one before.
        if (revert || generation > 0) {
          EXPECT_NE(record.current.checksum, Default().checksum());
        }
        if (!revert && generation == 0) {
          EXPECT_NE(record.current.checksum, checksum);
        }
        generation = record.generation;
        checksum = map_->vocabulary().checksum();
      }
      // Only the generation in use has a family; the others were dropped at open.
      for (uint64_t g = 1; g <= generation + 1; ++g) {
        EXPECT_EQ(HasFamily(MapDir(), "bow." + std::to_string(g)), g == generation)
            << "generation " << g;
      }
      ASSERT_TRUE(map_->VerifyIntegrity().ok()) << map_->VerifyIntegrity().ToString();
      EXPECT_EQ(map_->Stats().database.places, places.size());
      ExpectEachFrameFindsItsPlace(*map_, stored, places);
    }
  }
}

}  // namespace
}  // namespace placedb

int main(int argc, char** argv) {
  if (const char* data_dir = std::getenv(placedb::kChildEnv)) placedb::RunChild(data_dir);
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
