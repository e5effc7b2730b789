// A full disk: a map's data directory on a small tmpfs that the test mounts (root only; skipped
// otherwise). Writing places until the file system is full must give RESOURCE_EXHAUSTED ("disk
// full", naming the map, never the directory's path), keep every read working, lose nothing that
// was acknowledged, and let writes resume once space is freed: in this process and after a
// reopen.
#include <gtest/gtest.h>
#include <sys/mount.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <ostream>
#include <string>

#include "core/storage/map_store.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

namespace fs = std::filesystem;

constexpr int kFrames = 12;
constexpr size_t kTmpfsMiB = 96;
// The filler takes all but this much of the tmpfs once the map exists: the map fills the rest
// quickly, and deleting the filler leaves room for RocksDB to flush its memtables (all that was
// written since the last flush) when it resumes.
constexpr size_t kLeftMiB = 12;

size_t FreeMiB(const std::string& path) {
  struct statvfs info {};
  if (statvfs(path.c_str(), &info) != 0) return 0;
  return size_t(info.f_bavail) * info.f_frsize >> 20;
}

bool WriteFiller(const std::string& path, size_t mib) {
  std::ofstream out(path, std::ios::binary);
  const std::string block(size_t(1) << 20, 'x');
  for (size_t i = 0; i < mib && out; ++i) out.write(block.data(), std::streamsize(block.size()));
  out.close();
  return bool(out);
}

struct DiskFullCase {
  SyncMode sync;
  uint64_t reserve;  // StorageOptions::disk_reserve_bytes: 0 = RocksDB runs out of space itself
};

// Printed in test names instead of the struct's bytes (padding included).
void PrintTo(const DiskFullCase& c, std::ostream* out) {
  *out << (c.sync == SyncMode::kEveryWrite ? "every write" : "group commit") << ", reserve "
       << c.reserve;
}

class DiskFullTest : public ::testing::TestWithParam<DiskFullCase> {
 protected:
  void SetUp() override {
    if (geteuid() != 0) GTEST_SKIP() << "mounting a tmpfs needs root";
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    mount_point_ = testing::MakeTempDir("placedb-disk-full");
    const std::string options = "size=" + std::to_string(kTmpfsMiB) + "m";
    if (mount("tmpfs", mount_point_.c_str(), "tmpfs", 0, options.c_str()) != 0) {
      GTEST_SKIP() << "cannot mount a tmpfs on " << mount_point_ << ": " << std::strerror(errno);
    }
    mounted_ = true;
  }
  void TearDown() override {
    if (mounted_ && umount2(mount_point_.c_str(), MNT_DETACH) != 0) {
      ADD_FAILURE() << "umount " << mount_point_ << ": " << std::strerror(errno);
    }
  }

  std::string mount_point_;
  bool mounted_ = false;
};

TEST_P(DiskFullTest, FullDiskRefusesWritesKeepsReadsAndResumes) {
  auto vocabulary = testing::DefaultVocabulary();
  ASSERT_TRUE(vocabulary);
  const std::string data_dir = mount_point_ + "/data";
  const std::string filler = mount_point_ + "/filler";
  StorageOptions storage;
  storage.sync = GetParam().sync;
  storage.disk_reserve_bytes = GetParam().reserve;
  storage.group_commit_delay_ms = 1;       // one writer: a shorter wait per place
  std::map<PlaceId, size_t> acknowledged;  // place -> frame
  std::vector<ProcessedFrame> frames;
  {
    auto dir = DataDirectory::Open(data_dir, storage);
    ASSERT_TRUE(dir.ok()) << dir.status().ToString();
    MapOptions options;
    options.database.verification.mode = VerificationMode::kDirectIndex;  // reads features
    auto map = (*dir)->CreateMap("full", options, vocabulary);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    frames = testing::ProcessRtabmapFrames(*(*map)->database(), kFrames);
    ASSERT_EQ(frames.size(), size_t(kFrames));
    // A first place before the filler: RocksDB preallocates the write-ahead log at its first
    // write (about 35 MB, which a tmpfs counts as used), and CreateMap's flush started a new one.
    {
      auto first = (*map)->Commit(frames[0], {});
      ASSERT_TRUE(first.ok()) << first.status().ToString();
      acknowledged[first->id] = 0;
    }
    const size_t free_mib = FreeMiB(mount_point_);
    ASSERT_GT(free_mib, kLeftMiB + 8);
    ASSERT_TRUE(WriteFiller(filler, free_mib - kLeftMiB));

    // Fill the rest. A place is ~60 KB; the bound only stops a runaway loop.
    Status refused;
    for (size_t n = 0; n < 5000 && refused.ok(); ++n) {
      PlaceMetadata metadata;
      metadata.sequence = n;
      metadata.agent_id = "filler";
      auto added = (*map)->Commit(frames[n % frames.size()], metadata);
      if (!added.ok()) {
        refused = added.status();
      } else {
        ASSERT_TRUE(added->stored);
        acknowledged[added->id] = n % frames.size();
      }
    }
    ASSERT_FALSE(refused.ok()) << "the tmpfs never filled up";
    ASSERT_FALSE(acknowledged.empty());
    EXPECT_EQ(refused.code(), StatusCode::kResourceExhausted) << refused.ToString();
    EXPECT_EQ(refused.message().rfind("disk full: map 'full': storing place ", 0), 0u)
        << refused.message();
    EXPECT_NE(refused.message().find("free space, then retry"), std::string::npos);
    EXPECT_EQ(refused.message().find(mount_point_), std::string::npos) << refused.message();

    // Still full: the next write is refused the same way. A removal is refused once RocksDB
    // itself ran out of space (the place stays); within the reserve it goes through.
    auto again = (*map)->Commit(frames[0], {});
    ASSERT_FALSE(again.ok());
    EXPECT_EQ(again.status().code(), StatusCode::kResourceExhausted);
    const PlaceId kept = acknowledged.begin()->first;
    const PlaceId removed_id = std::prev(acknowledged.end())->first;
    Status removed = (*map)->RemovePlace(removed_id);
    if (GetParam().reserve > 0) {
      EXPECT_TRUE(removed.ok()) << removed.ToString();
      acknowledged.erase(removed_id);
    } else {
      EXPECT_EQ(removed.code(), StatusCode::kResourceExhausted) << removed.ToString();
      EXPECT_EQ(removed.message().rfind("disk full: map 'full': removing place ", 0), 0u)
          << removed.message();
    }

    // Reads keep working: every acknowledged place, queries (which verify against features
    // on disk), stats and the map list.
    for (const auto& [id, frame] : acknowledged) {
      auto place = (*map)->GetPlace(id);
      ASSERT_TRUE(place.ok()) << "place " << id << ": " << place.status().ToString();
      EXPECT_EQ(place->payload.features.size(), frames[frame].static_features.size());
    }
    QueryResult found = (*map)->Search(frames[1], {});
    ASSERT_TRUE(found.valid) << found.rejection;
    ASSERT_FALSE(found.matches.empty());
    EXPECT_TRUE(found.matches[0].verified);
    EXPECT_EQ(acknowledged.at(found.matches[0].place), 1u);
    EXPECT_EQ((*map)->Stats().database.places, acknowledged.size());
    EXPECT_EQ((*dir)->ListMaps(), std::vector<std::string>{"full"});

    // Space returns: the next write resumes the map.
    ASSERT_TRUE(fs::remove(filler));
    for (size_t n = 0; n < 20; ++n) {
      auto added = (*map)->Commit(frames[n % frames.size()], {});
      ASSERT_TRUE(added.ok()) << "write " << n
                              << " after freeing space: " << added.status().ToString();
      acknowledged[added->id] = n % frames.size();
    }
    EXPECT_TRUE((*map)->RemovePlace(kept).ok());
    acknowledged.erase(kept);
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  }

  // Reopened: exactly the acknowledged places, complete.
  auto dir = DataDirectory::Open(data_dir, storage);
  ASSERT_TRUE(dir.ok()) << dir.status().ToString();
  auto map = (*dir)->OpenMap("full", vocabulary);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  EXPECT_EQ((*map)->Stats().database.places, acknowledged.size());
  for (const auto& [id, frame] : acknowledged) {
    auto place = (*map)->GetPlace(id);
    ASSERT_TRUE(place.ok()) << "place " << id << " lost: " << place.status().ToString();
    EXPECT_EQ(place->payload.features.size(), frames[frame].static_features.size());
  }
}

// Closed while the disk is full (a shutdown then): reopened once there is space, the map holds
// every acknowledged place (the write-ahead log ends in the refused write's partial record).
TEST_P(DiskFullTest, ClosedWhileFullReopensWithEveryAcknowledgedPlace) {
  auto vocabulary = testing::DefaultVocabulary();
  ASSERT_TRUE(vocabulary);
  const std::string data_dir = mount_point_ + "/data";
  const std::string filler = mount_point_ + "/filler";
  StorageOptions storage;
  storage.sync = GetParam().sync;
  storage.disk_reserve_bytes = GetParam().reserve;
  storage.group_commit_delay_ms = 1;
  std::map<PlaceId, size_t> acknowledged;
  std::vector<ProcessedFrame> frames;
  {
    auto dir = DataDirectory::Open(data_dir, storage);
    ASSERT_TRUE(dir.ok()) << dir.status().ToString();
    auto map = (*dir)->CreateMap("full", {}, vocabulary);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    frames = testing::ProcessRtabmapFrames(*(*map)->database(), kFrames);
    ASSERT_EQ(frames.size(), size_t(kFrames));
    const size_t free_mib = FreeMiB(mount_point_);
    ASSERT_GT(free_mib, kLeftMiB + 8);
    ASSERT_TRUE(WriteFiller(filler, free_mib - kLeftMiB));
    Status refused;
    for (size_t n = 0; n < 5000 && refused.ok(); ++n) {
      auto added = (*map)->Commit(frames[n % frames.size()], {});
      if (added.ok()) {
        acknowledged[added->id] = n % frames.size();
      } else {
        refused = added.status();
      }
    }
    ASSERT_EQ(refused.code(), StatusCode::kResourceExhausted) << refused.ToString();
  }  // closed while full: the flush on close fails too
  ASSERT_TRUE(fs::remove(filler));
  auto dir = DataDirectory::Open(data_dir, storage);
  ASSERT_TRUE(dir.ok()) << dir.status().ToString();
  auto map = (*dir)->OpenMap("full", vocabulary);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  for (const auto& [id, frame] : acknowledged) {
    auto place = (*map)->GetPlace(id);
    ASSERT_TRUE(place.ok()) << "place " << id << " lost: " << place.status().ToString();
    EXPECT_EQ(place->payload.features.size(), frames[frame].static_features.size());
  }
  auto added = (*map)->Commit(frames[0], {});
  EXPECT_TRUE(added.ok()) << added.status().ToString();
}

INSTANTIATE_TEST_SUITE_P(
    SyncModes, DiskFullTest,
    ::testing::Values(DiskFullCase{SyncMode::kEveryWrite, StorageOptions().disk_reserve_bytes},
                      DiskFullCase{SyncMode::kGroupCommit, StorageOptions().disk_reserve_bytes},
                      DiskFullCase{SyncMode::kEveryWrite, 0},
                      DiskFullCase{SyncMode::kGroupCommit, 0}),
    [](const ::testing::TestParamInfo<DiskFullCase>& info) {
      return std::string(info.param.sync == SyncMode::kEveryWrite ? "EveryWrite" : "GroupCommit") +
             (info.param.reserve > 0 ? "Reserve" : "NoReserve");
    });

}  // namespace
}  // namespace placedb
