// The loop-closure log of a map (core/storage/loop_log.h): constraints written with their places
// by concurrent callers of the commit queue, numbered in the order they became durable, each
// naming its place; none logged when the place's write fails; kept across a reopen, numbering
// on; filters; the stored value's codec and its damage; a follower woken by new constraints and
// by the map's deletion. Run under ThreadSanitizer by tools/test.sh (CONCURRENCY).
#include "core/storage/loop_log.h"

#include <gtest/gtest.h>

#include <chrono>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "core/storage/map_store.h"
#include "tests/join_on_exit.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

using testing::DefaultVocabulary;

using testing::RtabmapFrame;

// Agent "r<n>". (Built by appending: GCC 12 at -O3 warns about `"r" + std::to_string(n)`, a
// false -Wrestrict.)
std::string Robot(size_t n) {
  std::string name = "r";
  name += std::to_string(n);
  return name;
}

// A constraint of `frame` against `place` (as Ingest's verified matches make them).
LoopConstraint ConstraintOf(const PlaceMetadata& frame, PlaceId place, const std::string& agent,
                            uint64_t place_sequence) {
  LoopConstraint c;
  c.query = frame;
  c.place = place;
  c.place_metadata.agent_id = agent;
  c.place_metadata.sequence = place_sequence;
  c.score = 0.5;
  c.inliers = 40;
  c.pose_unavailable = "the frame came without a camera";
  c.found_unix_ns = 1;
  return c;
}

class LoopLogTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    vocabulary_ = DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
    root_ = testing::MakeTempDir("placedb-loop-log");
  }
  std::unique_ptr<DataDirectory> OpenDir(StorageOptions options = {}) {
    auto dir = DataDirectory::Open(root_ + "/data", options);
    EXPECT_TRUE(dir.ok()) << dir.status().ToString();
    return dir.ok() ? std::move(dir).value() : nullptr;
  }
  std::vector<LoopConstraint> ReadAll(const PlaceMap& map, uint64_t from = 1,
                                      const LoopFilter& filter = {}) {
    uint64_t scanned = 0;
    auto read = map.ReadLoops(from, 1000, filter, &scanned);
    EXPECT_TRUE(read.ok()) << read.status().ToString();
    return read.ok() ? *read : std::vector<LoopConstraint>{};
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
};

TEST_F(LoopLogTest, ConcurrentCommitsLogEachPlacesConstraintsInDurableOrder) {
  std::map<PlaceId, PlaceMetadata> placed;  // query place -> its frame
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("log", {}, vocabulary_);
    ASSERT_TRUE(map.ok());
    ASSERT_TRUE((*map)->Add(RtabmapFrame(1, "base")).ok());  // place 1: what every frame matched

    // 4 callers x 3 frames, 2 constraints each, through the commit queue (group commit).
    std::vector<ProcessedFrame> frames;
    for (int i = 2; i <= 13; ++i) {
      auto frame = (*map)->Process(RtabmapFrame(i, Robot(size_t(i) % 4)));
      ASSERT_TRUE(frame.ok());
      frames.push_back(*frame);
    }
    std::vector<std::shared_ptr<PendingCommit>> pending(frames.size());
    std::vector<PlaceMetadata> metadata(frames.size());
    std::vector<std::thread> callers;
    testing::JoinOnExit join;
    join.Add(callers);
    for (int t = 0; t < 4; ++t) {
      callers.emplace_back([&, t] {
        for (size_t i = size_t(t); i < frames.size(); i += 4) {
          metadata[i].agent_id = Robot((i + 2) % 4);
          metadata[i].sequence = i + 2;
          std::vector<LoopConstraint> found = {ConstraintOf(metadata[i], 1, "base", 1),
                                               ConstraintOf(metadata[i], 1, "base", 1)};
          pending[i] = (*map)->Enqueue(frames[i], metadata[i], std::move(found));
        }
      });
    }
    join.JoinAll();
    for (size_t i = 0; i < frames.size(); ++i) {
      const Result<AddResult>& added = pending[i]->Wait();
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      ASSERT_TRUE(added->stored);
      placed[added->id] = metadata[i];
    }
    const std::vector<LoopConstraint> log = ReadAll(**map);
    ASSERT_EQ(log.size(), 24u);
    EXPECT_EQ((*map)->last_loop_sequence(), 24u);
    for (size_t i = 0; i < log.size(); ++i) {
      EXPECT_EQ(log[i].sequence, i + 1);
      ASSERT_TRUE(placed.count(log[i].query_place)) << log[i].query_place;
      EXPECT_EQ(log[i].query, placed[log[i].query_place]);  // named its own place
      EXPECT_EQ(log[i].place, 1u);
    }
    // Durable order is id order: a group's places are written in id order.
    for (size_t i = 1; i < log.size(); ++i) {
      EXPECT_LE(log[i - 1].query_place, log[i].query_place);
    }
  }
  // Reopened: the same log, numbering on.
  auto dir = OpenDir();
  auto map = dir->OpenMap("log", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_EQ((*map)->last_loop_sequence(), 24u);
  EXPECT_EQ(ReadAll(**map).size(), 24u);
  auto frame = (*map)->Process(RtabmapFrame(20, "late"));
  ASSERT_TRUE(frame.ok());
  auto committed = (*map)->Enqueue(*frame, {"late", 20, 0, {}},
                                   {ConstraintOf({"late", 20, 0, {}}, 1, "base", 1)});
  ASSERT_TRUE(committed->Wait().ok());
  const std::vector<LoopConstraint> tail = ReadAll(**map, 25);
  ASSERT_EQ(tail.size(), 1u);
  EXPECT_EQ(tail[0].sequence, 25u);
  EXPECT_EQ(tail[0].query_place, committed->Wait()->id);
}

TEST_F(LoopLogTest, AFailedWriteLogsNothing) {
  std::vector<ProcessedFrame> frames;
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("full", {}, vocabulary_);
    ASSERT_TRUE(map.ok());
    for (int i = 1; i <= 3; ++i) {
      auto frame = (*map)->Process(RtabmapFrame(i, "a"));
      ASSERT_TRUE(frame.ok());
      frames.push_back(*frame);
    }
  }
  StorageOptions full;
  full.disk_reserve_bytes = uint64_t(1) << 62;  // more than any disk: nothing fits
  auto dir = OpenDir(full);
  auto map = dir->OpenMap("full", vocabulary_);
  ASSERT_TRUE(map.ok());
  const PlaceMetadata frame{"a", 2, 0, {}};
  auto refused = (*map)->Enqueue(frames[1], frame, {ConstraintOf(frame, 1, "a", 1)});
  EXPECT_EQ(refused->Wait().status().code(), StatusCode::kResourceExhausted);
  EXPECT_EQ((*map)->last_loop_sequence(), 0u);
  EXPECT_TRUE(ReadAll(**map).empty());
}

TEST(LoopLogCodec, RoundTripsAndDamageIsCorruption) {
  LoopConstraint c = ConstraintOf({"a", 7, 123, Pose{{1, 2, 3}, {0, 0, 0, 1}}}, 3, "b", 2);
  c.source = LoopSource::kLoopClosure;
  c.query_place = 9;
  c.merged = true;
  RelativePose pose;
  pose.transform[3] = 0.25;
  pose.metric = true;
  pose.solver = PoseSolver::kPnpQueryDepth;
  pose.correspondences = 80;
  pose.inliers = 61;
  pose.rms_error_px = 0.7;
  pose.information[0] = 1e4;
  c.pose = pose;
  c.pose_unavailable.clear();
  auto back = DecodeLoopConstraint(5, EncodeLoopConstraint(c));
  ASSERT_TRUE(back.ok()) << back.status().ToString();
  EXPECT_EQ(back->sequence, 5u);
  EXPECT_EQ(back->source, LoopSource::kLoopClosure);
  EXPECT_EQ(back->query, c.query);
  EXPECT_EQ(back->place_metadata, c.place_metadata);
  EXPECT_EQ(back->query_place, 9u);
  EXPECT_TRUE(back->merged);
  ASSERT_TRUE(back->pose);
  EXPECT_EQ(back->pose->transform, pose.transform);
  EXPECT_EQ(back->pose->information, pose.information);
  EXPECT_EQ(back->pose->solver, PoseSolver::kPnpQueryDepth);
  EXPECT_EQ(back->pose->inliers, 61);

  for (const std::string& damaged :
       {std::string("{"), std::string("{}"), EncodeLoopConstraint(c).substr(0, 40),
        std::string(R"({"source":9})")}) {
    auto decoded = DecodeLoopConstraint(11, damaged);
    ASSERT_FALSE(decoded.ok()) << damaged;
    EXPECT_EQ(decoded.status().code(), StatusCode::kCorruption);
    EXPECT_NE(decoded.status().message().find("loop constraint 11"), std::string::npos)
        << decoded.status().ToString();
  }
}

TEST(LoopLogFilter, AgentsInterAgentAndSequenceGap) {
  const LoopConstraint inter = ConstraintOf({"a", 50, 0, {}}, 1, "b", 1);
  const LoopConstraint near = ConstraintOf({"a", 50, 0, {}}, 1, "a", 48);
  const LoopConstraint far = ConstraintOf({"a", 50, 0, {}}, 1, "a", 3);
  EXPECT_TRUE(LoopFilter{}.Accepts(near));
  LoopFilter inter_only;
  inter_only.inter_agent_only = true;
  EXPECT_TRUE(inter_only.Accepts(inter));
  EXPECT_FALSE(inter_only.Accepts(far));
  LoopFilter gap;
  gap.min_sequence_gap = 10;
  EXPECT_FALSE(gap.Accepts(near));
  EXPECT_TRUE(gap.Accepts(far));
  EXPECT_TRUE(gap.Accepts(inter));  // the gap is for one agent's own frames
  LoopFilter of_b;
  of_b.agents = {"b"};
  EXPECT_TRUE(of_b.Accepts(inter));  // b on either side
  EXPECT_FALSE(of_b.Accepts(far));
}

TEST_F(LoopLogTest, AFollowerIsWokenByNewConstraintsAndByDeletion) {
  auto dir = OpenDir();
  auto map = dir->CreateMap("followed", {}, vocabulary_);
  ASSERT_TRUE(map.ok());
  ASSERT_TRUE((*map)->Add(RtabmapFrame(1, "a")).ok());
  auto frame = (*map)->Process(RtabmapFrame(2, "b"));
  ASSERT_TRUE(frame.ok());

  // Nothing new: the wait ends at its deadline.
  bool deleted = false;
  EXPECT_EQ((*map)->WaitForLoops(0, std::chrono::steady_clock::now(), &deleted), 0u);
  EXPECT_FALSE(deleted);

  uint64_t seen = 0;
  std::thread follower([&] {
    bool gone = false;
    seen =
        (*map)->WaitForLoops(0, std::chrono::steady_clock::now() + std::chrono::seconds(60), &gone);
  });
  testing::JoinOnExit join;
  join.Add(follower);
  const PlaceMetadata metadata{"b", 2, 0, {}};
  ASSERT_TRUE((*map)->Enqueue(*frame, metadata, {ConstraintOf(metadata, 1, "a", 1)})->Wait().ok());
  join.JoinAll();
  EXPECT_EQ(seen, 1u);

  std::thread deletion_follower([&] {
    (*map)->WaitForLoops(1, std::chrono::steady_clock::now() + std::chrono::seconds(60), &deleted);
  });
  testing::JoinOnExit join_deletion;
  join_deletion.Add(deletion_follower);
  ASSERT_TRUE(dir->DeleteMap("followed").ok());
  join_deletion.JoinAll();
  EXPECT_TRUE(deleted);
  uint64_t scanned = 0;
  EXPECT_EQ((*map)->ReadLoops(1, 10, {}, &scanned).status().code(), StatusCode::kNotFound);
}

}  // namespace
}  // namespace placedb
