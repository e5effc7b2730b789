// Damage to a map's files is never silent: a real map of RTAB-Map frames is built by a child
// process that is killed (its last places only in the write-ahead log), then each test damages a
// copy of its files the way a disk or an operator can and checks that the map is not opened with
// fewer places: OpenMap says CORRUPTION naming the file, RecoverMap accepts the loss and counts it
// exactly, Scrub finds a corrupt SST block.
#include <gtest/gtest.h>
#include <rocksdb/db.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>

#include "core/storage/map_store.h"
#include "tests/raw_map.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace fs = std::filesystem;

namespace placedb {
namespace {

constexpr char kChildEnv[] = "PLACEDB_DAMAGE_CHILD";
constexpr int kFlushed = 40;  // places the child flushes to SST files (a clean close)
constexpr int kPlaces = 82;   // acknowledged places in all; the last 42 only in the WAL

// The child: creates map "lab", stores kFlushed places, closes it cleanly (RocksDB flushes them
// to SST files), reopens it, stores the rest and exits without closing anything, as a SIGKILL
// would: those places are acknowledged, in the WAL and in no SST. Prints "ack ID" per place.
[[noreturn]] void RunChild(const std::string& data_dir) {
  auto vocabulary = testing::DefaultVocabulary();
  auto dir = DataDirectory::Open(data_dir);
  if (!vocabulary || !dir.ok()) std::_Exit(3);
  std::vector<ProcessedFrame> frames;
  {
    auto map = (*dir)->CreateMap("lab", {}, vocabulary);
    if (!map.ok()) std::_Exit(4);
    frames = testing::ProcessRtabmapFrames(*(*map)->database());
    if (frames.empty()) std::_Exit(5);
    for (int n = 0; n < kFlushed; ++n) {
      PlaceMetadata metadata{"robot", uint64_t(n), 0, std::nullopt};
      auto added = (*map)->Commit(frames[size_t(n) % frames.size()], metadata);
      if (!added.ok() || !added->stored) std::_Exit(6);
      std::printf("ack %u\n", added->id);
    }
    (*dir)->CloseMap("lab");
  }
  // The files as they are now: a map whose WAL will "end early" (DamageTest uses it).
  std::error_code ec;
  fs::copy(data_dir + "/maps/lab", data_dir + "/../early", fs::copy_options::recursive, ec);
  if (ec) std::_Exit(9);
  auto map = (*dir)->OpenMap("lab", vocabulary);
  if (!map.ok()) std::_Exit(7);
  for (int n = kFlushed; n < kPlaces; ++n) {
    PlaceMetadata metadata{"robot", uint64_t(n), 0, std::nullopt};
    auto added = (*map)->Commit(frames[size_t(n) % frames.size()], metadata);
    if (!added.ok() || !added->stored) std::_Exit(8);
    std::printf("ack %u\n", added->id);
  }
  std::fflush(stdout);
  std::_Exit(0);  // no destructor runs: nothing is flushed, as after SIGKILL
}

using testing::EditRawMap;
using testing::RawEdit;

class DamageTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!testing::HaveSharedData()) return;
    template_root_ = new std::string(testing::MakeTempDir("placedb-damage-template"));
    const std::string data_dir = *template_root_ + "/data";
    int pipe_fds[2];
    ASSERT_EQ(pipe(pipe_fds), 0);
    const std::string env = std::string(kChildEnv) + "=" + data_dir;
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      dup2(pipe_fds[1], STDOUT_FILENO);
      close(pipe_fds[0]);
      close(pipe_fds[1]);
      putenv(const_cast<char*>(env.c_str()));
      execl("/proc/self/exe", "damage_test_child", static_cast<char*>(nullptr));
      std::_Exit(127);
    }
    close(pipe_fds[1]);
    std::string output;
    char buffer[4096];
    for (ssize_t n; (n = read(pipe_fds[0], buffer, sizeof buffer)) > 0;) {
      output.append(buffer, size_t(n));
    }
    close(pipe_fds[0]);
    int status = 0;
    waitpid(child, &status, 0);
    ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << "child failed: " << status;
    int acks = 0;
    for (size_t at = output.find("ack "); at != std::string::npos;
         at = output.find("ack ", at + 1)) {
      ++acks;
    }
    ASSERT_EQ(acks, kPlaces);
  }
  static void TearDownTestSuite() {
    delete template_root_;
    template_root_ = nullptr;
  }

  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    ASSERT_TRUE(template_root_);
    vocabulary_ = testing::DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
    root_ = testing::MakeTempDir("placedb-damage");
    fs::copy(*template_root_ + "/data", root_ + "/data", fs::copy_options::recursive);
    map_dir_ = root_ + "/data/maps/lab";
  }

  DataDirectory::VocabularyFor Vocab() const {
    return [this](const MapInfo&) -> Result<AnyVocabulary> { return AnyVocabulary(vocabulary_); };
  }

  std::unique_ptr<DataDirectory> OpenDir() {
    auto dir = DataDirectory::Open(root_ + "/data");
    EXPECT_TRUE(dir.ok()) << dir.status().ToString();
    return dir.ok() ? std::move(dir).value() : nullptr;
  }

  // Closes the map cleanly first (everything in SST files: RocksDB opened here without placedb's
  // merge operators replays no placedb write), then runs `edit` on the map's raw RocksDB.
  void EditClosedMap(const RawEdit& edit) {
    {
      auto dir = OpenDir();
      ASSERT_TRUE(dir->OpenMap("lab", vocabulary_).ok());
      dir->CloseMap("lab");
    }
    EditRawMap(map_dir_, edit);
  }

  // The map's files whose name ends with `suffix` (".log", ".sst"), by name.
  std::vector<fs::path> Files(const std::string& suffix) const {
    std::vector<fs::path> files;
    for (const auto& entry : fs::directory_iterator(map_dir_)) {
      const std::string name = entry.path().filename().string();
      if (name.size() >= suffix.size() && name.ends_with(suffix)) files.push_back(entry.path());
    }
    std::sort(files.begin(), files.end());
    return files;
  }

  // The live WAL, holding the child's last places: the largest log.
  fs::path Wal() const {
    fs::path wal;
    for (const fs::path& log : Files(".log")) {
      if (wal.empty() || fs::file_size(log) > fs::file_size(wal)) wal = log;
    }
    EXPECT_FALSE(wal.empty());
    EXPECT_GT(fs::file_size(wal), 1000000u)
        << "the WAL should hold " << kPlaces - kFlushed << " places";
    return wal;
  }

  // The SST files of one column family, read from the map's MANIFEST (RocksDB read-only).
  std::vector<std::string> SstFilesOf(const std::string& family) const {
    return testing::SstFilesOf(map_dir_, family);
  }

  // Opens and closes the map: every place flushed to SST files, the WAL empty.
  void CloseCleanly() {
    auto dir = OpenDir();
    ASSERT_TRUE(dir->OpenMap("lab", vocabulary_).ok());
    dir->CloseMap("lab");
  }

  fs::path Manifest() const {
    std::vector<fs::path> manifests;
    for (const auto& entry : fs::directory_iterator(map_dir_)) {
      if (entry.path().filename().string().starts_with("MANIFEST-"))
        manifests.push_back(entry.path());
    }
    EXPECT_EQ(manifests.size(), 1u);
    return manifests.empty() ? fs::path() : manifests[0];
  }

  // Every file of the map, by name, with its bytes.
  std::map<std::string, std::string> FileBytes() const {
    std::map<std::string, std::string> files;
    for (const auto& entry : fs::directory_iterator(map_dir_)) {
      if (entry.is_regular_file()) {
        files[entry.path().filename().string()] = ReadFile(entry.path().string());
      }
    }
    return files;
  }

  // Recovery moved nothing out of existence: every file of `before` is in the quarantine that
  // `accepted` names, byte for byte.
  void ExpectQuarantined(const MapDamage& accepted,
                         const std::map<std::string, std::string>& before) {
    ASSERT_FALSE(accepted.quarantine.empty());
    EXPECT_NE(accepted.reason.find(accepted.quarantine), std::string::npos) << accepted.reason;
    const fs::path quarantine = fs::path(root_) / "data" / accepted.quarantine;
    for (const auto& [name, bytes] : before) {
      if (name == "LOCK" || name.starts_with("LOG")) continue;  // RocksDB's own log grows
      EXPECT_TRUE(fs::exists(quarantine / name)) << name;
      EXPECT_TRUE(ReadFile((quarantine / name).string()) == bytes) << name << " changed";
    }
  }

  // Map `name` (damaged in its MANIFEST) is refused, then recovered by RocksDB's repair with
  // every place, and the files of `before` kept in the quarantine.
  void ExpectRecoveredWhole(const std::string& name,
                            const std::map<std::string, std::string>& before) {
    auto dir = OpenDir();
    ASSERT_FALSE(dir->OpenMap(name, vocabulary_).ok());
    MapDamage accepted;
    auto map = dir->RecoverMap(name, Vocab(), &accepted);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    std::printf("[recovered] %s\n", accepted.reason.c_str());
    EXPECT_EQ((*map)->Stats().database.places, uint64_t(kPlaces));
    EXPECT_EQ(accepted.places_lost, 0u);
    EXPECT_EQ(accepted.writes_lost, 0u);
    EXPECT_NE(accepted.reason.find("repair"), std::string::npos) << accepted.reason;
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
    ExpectQuarantined(accepted, before);
  }

  // The MANIFEST that CURRENT names (`manifest`) is missing: damage, not "unavailable" (the
  // registry then offers recovery), named in ReadMapInfo's and OpenMap's reasons; repair keeps
  // every place. Returns what the recovery accepted.
  MapDamage ExpectManifestMissingAndRecovered(DataDirectory& dir, const std::string& manifest) {
    auto info = dir.ReadMapInfo("lab");
    EXPECT_FALSE(info.ok());
    EXPECT_EQ(info.status().code(), StatusCode::kCorruption) << info.status().ToString();
    EXPECT_NE(info.status().message().find(manifest), std::string::npos) << info.status().message();
    ExpectDamaged(dir, "maps/lab/CURRENT");
    MapDamage accepted;
    auto map = dir.RecoverMap("lab", Vocab(), &accepted);
    EXPECT_TRUE(map.ok()) << map.status().ToString();
    if (map.ok()) {
      EXPECT_EQ((*map)->Stats().database.places, uint64_t(kPlaces));
    }
    EXPECT_EQ(accepted.places_lost, 0u);
    return accepted;
  }

  static std::string ReadFile(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(in), {});
  }

  static void Overwrite(const fs::path& file, uintmax_t offset, size_t bytes) {
    std::fstream stream(file, std::ios::in | std::ios::out | std::ios::binary);
    stream.seekp(std::streamoff(offset));
    const std::string noise(bytes, '\xa5');
    stream.write(noise.data(), std::streamsize(noise.size()));
    ASSERT_TRUE(stream.good()) << file;
  }

  // OpenMap must fail with CORRUPTION, the reason naming `file_part`, never an absolute path.
  MapDamage ExpectDamaged(DataDirectory& dir, const std::string& file_part) {
    MapDamage damage;
    auto map = dir.OpenMap("lab", vocabulary_, &damage);
    EXPECT_FALSE(map.ok()) << "a damaged map opened with "
                           << (map.ok() ? (*map)->Stats().database.places : 0) << " places";
    if (map.ok()) return damage;
    EXPECT_EQ(map.status().code(), StatusCode::kCorruption) << map.status().ToString();
    std::printf("[damage] %s\n", damage.reason.c_str());
    EXPECT_NE(damage.reason.find(file_part), std::string::npos) << damage.reason;
    EXPECT_EQ(damage.reason.find(root_), std::string::npos) << damage.reason;
    EXPECT_EQ(map.status().message().find(root_), std::string::npos) << map.status().message();
    return damage;
  }

  // RecoverMap accepts the loss; the count is exact: `expected_lost` places are lost (at most
  // that many when `at_most`: a repaired log may keep places after a damaged record), the ids
  // first_lost..last_lost hold every lost one, every other id is there. Closes `dir` (one
  // DataDirectory per directory at a time) to check the restart.
  void ExpectRecovered(std::unique_ptr<DataDirectory>& dir, uint64_t expected_lost,
                       bool at_most = false) {
    MapDamage accepted;
    auto map = dir->RecoverMap("lab", Vocab(), &accepted);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    std::printf("[recovered] %s\n", accepted.reason.c_str());
    const uint64_t kept = (*map)->Stats().database.places;
    const uint64_t lost = accepted.places_lost;
    if (at_most) {
      EXPECT_LE(lost, expected_lost);
    } else {
      EXPECT_EQ(lost, expected_lost);
    }
    EXPECT_EQ(kept + lost, uint64_t(kPlaces));
    EXPECT_EQ(accepted.writes_lost, lost);
    if (lost > 0) {
      EXPECT_GE(accepted.first_lost, PlaceId(1));
      EXPECT_LE(accepted.last_lost, PlaceId(kPlaces));
      EXPECT_GE(uint64_t(accepted.last_lost - accepted.first_lost + 1), lost);
    }
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
    ASSERT_EQ((*map)->damage_history().size(), 1u);
    EXPECT_EQ((*map)->damage_history()[0].places_lost, lost);
    // The map works again, and its history survives a restart.
    for (PlaceId id = 1; id <= PlaceId(kPlaces); ++id) {
      if (id < accepted.first_lost || id > accepted.last_lost) {
        EXPECT_NE((*map)->database()->Get(id), nullptr) << id;
      }
    }
    map = Result<std::shared_ptr<PlaceMap>>(Status::Internal("released"));
    dir.reset();
    auto again = OpenDir();
    auto reopened = again->OpenMap("lab", vocabulary_);
    ASSERT_TRUE(reopened.ok()) << reopened.status().ToString();
    EXPECT_EQ((*reopened)->Stats().database.places, kept);
    ASSERT_EQ((*reopened)->damage_history().size(), 1u);
    EXPECT_EQ((*reopened)->damage_history()[0].places_lost, lost);
  }

  static std::string* template_root_;
  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
  std::string map_dir_;
};

std::string* DamageTest::template_root_ = nullptr;

TEST_F(DamageTest, KilledAndCleanReopensKeepEveryAcknowledgedPlace) {
  {
    auto dir = OpenDir();
    auto map = dir->OpenMap("lab", vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    EXPECT_EQ((*map)->Stats().database.places, uint64_t(kPlaces));
    // Acknowledged means counted: the statistics of the places only in the WAL survived too
    // (the child's frames carry no timestamp: untimed).
    auto dynamics = (*map)->MapDynamics();
    ASSERT_TRUE(dynamics.ok()) << dynamics.status().ToString();
    EXPECT_EQ(dynamics->observations, uint64_t(kPlaces));
    EXPECT_EQ(dynamics->untimed, uint64_t(kPlaces));
    for (PlaceId id = 1; id <= PlaceId(kPlaces); ++id) {
      auto place = (*map)->GetDynamics(id);
      ASSERT_TRUE(place.ok()) << place.status().ToString();
      EXPECT_EQ(place->observations, 1u) << "place " << id;
    }
    EXPECT_TRUE((*map)->open_note().empty()) << (*map)->open_note();
    EXPECT_TRUE((*map)->damage_history().empty());
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
    auto scrub = (*map)->Scrub();
    ASSERT_TRUE(scrub.ok());
    EXPECT_TRUE(scrub->clean());
    EXPECT_EQ(scrub->places_checked, uint64_t(kPlaces));
    EXPECT_GT(scrub->files_checked, 0u);
  }
  auto dir = OpenDir();  // after a clean close
  auto map = dir->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_EQ((*map)->Stats().database.places, uint64_t(kPlaces));
  // Not damaged: nothing to accept.
  dir->CloseMap("lab");
  map = Result<std::shared_ptr<PlaceMap>>(Status::Internal("released"));
  MapDamage accepted;
  auto recovered = dir->RecoverMap("lab", Vocab(), &accepted);
  ASSERT_TRUE(recovered.ok()) << recovered.status().ToString();
  EXPECT_EQ(accepted.writes_lost, 0u);
  EXPECT_TRUE((*recovered)->damage_history().empty());
}

TEST_F(DamageTest, TruncatedWalIsDamageNamingTheLog) {
  const fs::path wal = Wal();
  fs::resize_file(wal, fs::file_size(wal) / 2);
  auto dir = OpenDir();
  const MapDamage damage = ExpectDamaged(*dir, "maps/lab/" + wal.filename().string());
  EXPECT_GT(damage.places_lost, 0u);
  EXPECT_NE(damage.reason.find("acknowledged"), std::string::npos) << damage.reason;
  // Reading its info does not hide it either, and changes nothing.
  const auto size = fs::file_size(wal);
  ExpectRecovered(dir, damage.places_lost);
  EXPECT_GT(size, 0u);
}

TEST_F(DamageTest, GarbledWalIsDamage) {
  const fs::path wal = Wal();
  Overwrite(wal, fs::file_size(wal) / 3, 200);
  auto dir = OpenDir();
  const MapDamage damage = ExpectDamaged(*dir, "maps/lab/" + wal.filename().string());
  EXPECT_GT(damage.places_lost, 0u);
  // Repair reads the log on past the garbled record: it keeps the places after it, which
  // point-in-time recovery (what opening counted) would drop.
  ExpectRecovered(dir, damage.places_lost - 1, /*at_most=*/true);
}

TEST_F(DamageTest, DeletedWalIsDamage) {
  fs::remove(Wal());
  auto dir = OpenDir();
  // RocksDB opens it without complaint (the log was never closed): ACKED's count tells.
  const MapDamage damage = ExpectDamaged(*dir, "the write-ahead log ends early");
  EXPECT_EQ(damage.places_lost, uint64_t(kPlaces - kFlushed));
  ExpectRecovered(dir, kPlaces - kFlushed);
}

TEST_F(DamageTest, WalEndingEarlyAtARecordBoundaryIsCaughtByAcked) {
  // RocksDB cannot see a log cut exactly between records: the map's files as they were after
  // the first kFlushed places, with the final ACKED, are that case. Only ACKED's count tells.
  const std::string acked = ReadFile(map_dir_ + "/ACKED");
  fs::remove_all(map_dir_);
  fs::copy(*template_root_ + "/early", map_dir_, fs::copy_options::recursive);
  std::ofstream(map_dir_ + "/ACKED", std::ios::binary | std::ios::trunc) << acked;
  auto dir = OpenDir();
  const MapDamage damage = ExpectDamaged(*dir, "write-ahead log ends early");
  EXPECT_EQ(damage.places_lost, uint64_t(kPlaces - kFlushed));
  EXPECT_EQ(damage.first_lost, PlaceId(kFlushed + 1));
  ExpectRecovered(dir, kPlaces - kFlushed);
}

TEST_F(DamageTest, DeletedAckedIsDamage) {
  fs::remove(map_dir_ + "/ACKED");
  auto dir = OpenDir();
  const MapDamage damage = ExpectDamaged(*dir, "maps/lab/ACKED is missing");
  ExpectRecovered(dir, 0);
}

TEST_F(DamageTest, HalfTruncatedManifestIsDamageAndRepairable) {
  std::vector<fs::path> manifests;
  for (const auto& entry : fs::directory_iterator(map_dir_)) {
    if (entry.path().filename().string().starts_with("MANIFEST-"))
      manifests.push_back(entry.path());
  }
  ASSERT_EQ(manifests.size(), 1u);
  fs::resize_file(manifests[0], fs::file_size(manifests[0]) / 2);
  auto dir = OpenDir();
  const std::string name = "maps/lab/" + manifests[0].filename().string();
  auto info = dir->ReadMapInfo("lab");
  ASSERT_FALSE(info.ok());
  EXPECT_EQ(info.status().code(), StatusCode::kCorruption) << info.status().ToString();
  ExpectDamaged(*dir, name);
  // RocksDB's repair rebuilds the MANIFEST from the SST and WAL files: nothing is lost.
  ExpectRecovered(dir, 0);
}

// Issue 34: a map closed cleanly (every place in SST files, as after a server restart) whose
// MANIFEST is cut in half. Point-in-time recovery would open it from the MANIFEST's first half
// and delete the SST files it no longer names; recovery must keep every place (what RocksDB's
// repair keeps), and every file as it was must still exist, byte for byte, in the quarantine.
TEST_F(DamageTest, HalfTruncatedManifestOfACleanMapLosesNothingAndDeletesNothing) {
  CloseCleanly();
  const fs::path manifest = Manifest();
  fs::resize_file(manifest, fs::file_size(manifest) / 2);
  const auto before = FileBytes();
  ExpectRecoveredWhole("lab", before);
}

// The same on a map made, filled and closed in one session (a server's map after its first
// stop): its MANIFEST's first half describes the map before the flush at close. Opened from it,
// RocksDB deletes the SST files flushed later as not belonging to the map.
TEST_F(DamageTest, HalfTruncatedManifestOfAMapFilledInOneSessionLosesNothing) {
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("fresh", {}, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    const auto frames = testing::ProcessRtabmapFrames(*(*map)->database());
    ASSERT_FALSE(frames.empty());
    for (int n = 0; n < kPlaces; ++n) {
      auto added = (*map)->Commit(frames[size_t(n) % frames.size()],
                                  PlaceMetadata{"robot", uint64_t(n), 0, std::nullopt});
      ASSERT_TRUE(added.ok() && added->stored) << added.status().ToString();
    }
    dir->CloseMap("fresh");
  }
  map_dir_ = root_ + "/data/maps/fresh";
  const fs::path manifest = Manifest();
  fs::resize_file(manifest, fs::file_size(manifest) / 2);
  const auto before = FileBytes();
  ExpectRecoveredWhole("fresh", before);
}

TEST_F(DamageTest, DeletedManifestIsDamageAndRecoverable) {
  CloseCleanly();
  const fs::path manifest = Manifest();
  fs::remove(manifest);
  const auto before = FileBytes();
  auto dir = OpenDir();
  const MapDamage accepted = ExpectManifestMissingAndRecovered(*dir, manifest.filename().string());
  ExpectQuarantined(accepted, before);
}

TEST_F(DamageTest, CurrentNamingAMissingManifestIsDamageAndRecoverable) {
  CloseCleanly();
  std::ofstream(map_dir_ + "/CURRENT", std::ios::trunc) << "MANIFEST-999999\n";
  auto dir = OpenDir();
  ExpectManifestMissingAndRecovered(*dir, "MANIFEST-999999");
}

// The features SST files deleted: the places are still found (their records and BoW vectors are
// intact) but can no longer be verified or read. Recovery counts them; reading one is DATA_LOSS,
// never NOT_FOUND; scrub reports them.
TEST_F(DamageTest, DeletedFeaturesFilesAreCountedAndTheirPlacesReadAsDataLoss) {
  CloseCleanly();
  const auto features = SstFilesOf("features");
  ASSERT_FALSE(features.empty());
  for (const std::string& file : features) fs::remove(file);
  auto dir = OpenDir();
  ExpectDamaged(*dir, "maps/lab/");
  MapDamage accepted;
  auto map = dir->RecoverMap("lab", Vocab(), &accepted);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  std::printf("[recovered] %s\n", accepted.reason.c_str());
  EXPECT_EQ((*map)->Stats().database.places, uint64_t(kPlaces));
  EXPECT_EQ(accepted.features_lost, uint64_t(kPlaces));
  EXPECT_EQ(accepted.records_lost + accepted.bow_lost, 0u);
  EXPECT_NE(accepted.reason.find(std::to_string(kPlaces) + " places lost their features"),
            std::string::npos)
      << accepted.reason;
  for (PlaceId id : {PlaceId(1), PlaceId(kPlaces)}) {
    auto read = (*map)->GetPlace(id);
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.status().code(), StatusCode::kCorruption) << read.status().ToString();
    EXPECT_NE(read.status().message().find("features"), std::string::npos)
        << read.status().message();
  }
  auto scrub = (*map)->Scrub();
  ASSERT_TRUE(scrub.ok());
  EXPECT_EQ(scrub->damaged_places.size(), size_t(kPlaces));
  ASSERT_EQ((*map)->damage_history().size(), 1u);
  EXPECT_EQ((*map)->damage_history()[0].features_lost, uint64_t(kPlaces));
  // The count survives a restart (the history is persisted).
  map = Result<std::shared_ptr<PlaceMap>>(Status::Internal("released"));
  dir.reset();
  auto again = OpenDir();
  auto reopened = again->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(reopened.ok()) << reopened.status().ToString();
  ASSERT_EQ((*reopened)->damage_history().size(), 1u);
  EXPECT_EQ((*reopened)->damage_history()[0].features_lost, uint64_t(kPlaces));
}

// A BoW SST file deleted: the places it held cannot be found any more; recovery drops what is
// left of them (kept in the quarantine) and counts them, instead of refusing the whole map.
TEST_F(DamageTest, DeletedBowFileDropsOnlyItsPlacesAndCountsThem) {
  CloseCleanly();
  const auto bow = SstFilesOf("bow");
  ASSERT_EQ(bow.size(), 2u) << "the child's first " << kFlushed << " places, then the rest";
  fs::remove(bow[0]);
  const auto before = FileBytes();
  auto dir = OpenDir();
  ExpectDamaged(*dir, "maps/lab/");
  MapDamage accepted;
  auto map = dir->RecoverMap("lab", Vocab(), &accepted);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  std::printf("[recovered] %s\n", accepted.reason.c_str());
  const uint64_t kept = (*map)->Stats().database.places;
  EXPECT_GT(kept, 0u);
  EXPECT_LT(kept, uint64_t(kPlaces));
  EXPECT_EQ(accepted.bow_lost, uint64_t(kPlaces) - kept);
  EXPECT_EQ(accepted.places_lost, accepted.bow_lost);  // dropped: no longer served
  EXPECT_EQ(accepted.features_lost + accepted.records_lost, 0u);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  for (PlaceId id = 1; id <= PlaceId(kPlaces); ++id) {
    if ((*map)->database()->Get(id)) {
      EXPECT_TRUE((*map)->GetPlace(id).ok()) << id;
    }
  }
  ExpectQuarantined(accepted, before);
}

TEST_F(DamageTest, DeletedCurrentIsDamage) {
  fs::remove(map_dir_ + "/CURRENT");
  auto dir = OpenDir();
  EXPECT_EQ(dir->ReadMapInfo("lab").status().code(), StatusCode::kCorruption);
  const MapDamage damage = ExpectDamaged(*dir, "maps/lab/CURRENT");
  EXPECT_NE(damage.reason.find("missing"), std::string::npos);
  ExpectRecovered(dir, 0);
}

TEST_F(DamageTest, MapDirectoryReplacedByAFileIsListedAsDamage) {
  fs::remove_all(map_dir_);
  std::ofstream(map_dir_) << "not a map";
  auto dir = OpenDir();
  EXPECT_EQ(dir->ListMaps(), std::vector<std::string>{"lab"});
  auto info = dir->ReadMapInfo("lab");
  ASSERT_FALSE(info.ok());
  EXPECT_EQ(info.status().code(), StatusCode::kCorruption);
  ExpectDamaged(*dir, "maps/lab is a file");
  auto recovered = dir->RecoverMap("lab", Vocab());
  ASSERT_FALSE(recovered.ok());
  EXPECT_EQ(recovered.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_TRUE(dir->DeleteMap("lab").ok());
  EXPECT_TRUE(dir->ListMaps().empty());
}

TEST_F(DamageTest, MissingMapInfoRecordIsDamage) {
  EditClosedMap([](rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
    rocksdb::WriteOptions sync;
    sync.sync = true;
    EXPECT_TRUE(raw->Delete(sync, handles[0], "info").ok());
  });
  auto dir = OpenDir();
  auto info = dir->ReadMapInfo("lab");
  ASSERT_FALSE(info.ok());
  EXPECT_EQ(info.status().code(), StatusCode::kCorruption);
  ExpectDamaged(*dir, "maps/lab: the map info record is missing");
  // Without it the map's configuration is unknown: only a checkpoint helps.
  auto recovered = dir->RecoverMap("lab", Vocab());
  ASSERT_FALSE(recovered.ok());
  EXPECT_EQ(recovered.status().code(), StatusCode::kFailedPrecondition);
}

// Drops column families of the (closed) map at `map_dir`, as maps made before they existed lack
// them.
void DropFamilies(const std::string& map_dir, const std::vector<std::string>& drop) {
  EditRawMap(map_dir, [&](rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
    for (auto* handle : handles) {
      if (std::find(drop.begin(), drop.end(), handle->GetName()) != drop.end()) {
        EXPECT_TRUE(raw->DropColumnFamily(handle).ok());
      }
    }
  });
}

// A map made before issue 16 has no "dynamics" (nor "thumbnails", nor issue 32's "loops") column
// family: it is read without them (ReadMapInfo opens read-only), gets empty ones when opened for
// writing, and counts (and logs loop constraints) from then.
TEST_F(DamageTest, MapWithoutTheDynamicsFamilyOpensAndStartsCounting) {
  {
    auto dir = OpenDir();
    ASSERT_TRUE(dir->OpenMap("lab", vocabulary_).ok());
    dir->CloseMap("lab");
  }
  ASSERT_NO_FATAL_FAILURE(DropFamilies(map_dir_, {"dynamics", "thumbnails", "loops"}));
  auto dir = OpenDir();
  auto info = dir->ReadMapInfo("lab");
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  auto map = dir->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_EQ((*map)->Stats().database.places, uint64_t(kPlaces));
  auto before = (*map)->GetDynamics(1);
  ASSERT_TRUE(before.ok()) << before.status().ToString();
  EXPECT_TRUE(before->empty());
  EXPECT_TRUE((*map)->MapDynamics()->empty());
  auto frames = testing::ProcessRtabmapFrames(*(*map)->database(), 1);
  ASSERT_FALSE(frames.empty());
  auto added = (*map)->Commit(frames[0], PlaceMetadata{"robot", 1, 0, std::nullopt});
  ASSERT_TRUE(added.ok() && added->stored) << added.status().ToString();
  EXPECT_EQ((*map)->GetDynamics(added->id)->observations, 1u);
  EXPECT_EQ((*map)->MapDynamics()->observations, 1u);
  EXPECT_EQ((*map)->last_loop_sequence(), 0u);
  LoopConstraint found;
  found.query = {"robot", 2, 0, std::nullopt};
  found.place = added->id;
  found.pose_unavailable = "no camera";
  ASSERT_TRUE((*map)->Enqueue(frames[0], found.query, {found})->Wait().ok());
  uint64_t scanned = 0;
  auto logged = (*map)->ReadLoops(1, 10, {}, &scanned);
  ASSERT_TRUE(logged.ok()) << logged.status().ToString();
  ASSERT_EQ(logged->size(), 1u);
  EXPECT_EQ(logged->front().query_place, added->id + 1);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

// A map made before issue 20 has no "thumbnails" family: it opens (read-only without it), gets an
// empty one when opened for writing, and keeps thumbnails from then when its settings say so.
// (Settings cannot change after creation: here a map made with thumbnails loses its family.)
TEST_F(DamageTest, MapWithoutTheThumbnailsFamilyOpensAndStartsKeepingThem) {
  MapOptions options;
  options.thumbnails.enabled = true;
  Observation frame;
  frame.image = testing::ReadGray(testing::RtabmapFramePath(20));
  frame.dynamic.boxes.push_back({0, 0.9f, cv::Rect2f(0, 0, 150, 300)});
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("kept", options, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    auto added = (*map)->Add(frame);
    ASSERT_TRUE(added.ok() && added->stored) << added.status().ToString();
    ASSERT_TRUE((*(*map)->GetThumbnail(added->id)).has_value());
    dir->CloseMap("kept");
  }
  ASSERT_NO_FATAL_FAILURE(DropFamilies(root_ + "/data/maps/kept", {"thumbnails"}));
  auto dir = OpenDir();
  auto info = dir->ReadMapInfo("kept");
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_TRUE(info->options.thumbnails.enabled);
  auto map = dir->OpenMap("kept", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  auto lost = (*map)->GetThumbnail(1);
  ASSERT_TRUE(lost.ok()) << lost.status().ToString();
  EXPECT_FALSE(lost->has_value());
  auto added = (*map)->Add(frame);
  ASSERT_TRUE(added.ok() && added->stored) << added.status().ToString();
  auto kept = (*map)->GetThumbnail(added->id);
  ASSERT_TRUE(kept.ok()) << kept.status().ToString();
  ASSERT_TRUE(kept->has_value());
  EXPECT_EQ((*kept)->width, 320u);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  // Any other family missing is still damage.
  *map = nullptr;
  dir->CloseMap("kept");
  ASSERT_NO_FATAL_FAILURE(DropFamilies(root_ + "/data/maps/kept", {"bow"}));
  EXPECT_FALSE(dir->OpenMap("kept", vocabulary_).ok());
}

TEST_F(DamageTest, CorruptBowBlockIsDamageAtOpen) {
  // The index is rebuilt from the BoW vectors at open: a corrupt block there is found at once.
  const auto files = SstFilesOf("bow");
  ASSERT_EQ(files.size(), 1u);
  Overwrite(files[0], fs::file_size(files[0]) / 3, 64);
  auto dir = OpenDir();
  const MapDamage damage =
      ExpectDamaged(*dir, "maps/lab/" + fs::path(files[0]).filename().string());
  EXPECT_NE(damage.reason.find("checksum"), std::string::npos) << damage.reason;
  // Point-in-time recovery cannot mend an SST block: the map stays damaged.
  auto recovered = dir->RecoverMap("lab", Vocab());
  ASSERT_FALSE(recovered.ok());
  EXPECT_EQ(recovered.status().code(), StatusCode::kFailedPrecondition);
  ExpectDamaged(*dir, "maps/lab/" + fs::path(files[0]).filename().string());
}

// Issue 17: several load threads over ranges of place ids report damage in the middle of the id
// range exactly as the sequential scan does (the first problem in id order, the file named): an
// SST block of `bow` that does not read, a record that does not decode, a place whose BoW vector
// is missing, a BoW vector whose place record is missing.
TEST_F(DamageTest, ParallelLoadReportsDamageInTheMiddleLikeTheSequentialScan) {
  StorageOptions sequential;
  sequential.load_threads = 1;
  StorageOptions parallel;  // 82 places in 11 ranges of 8 ids
  parallel.load_threads = 2;
  parallel.load_range_ids = 8;
  // Opens the map with each loader (in a fresh DataDirectory) and checks both refuse it alike.
  const auto expect_alike = [&](const std::string& part) {
    std::string reasons[2];
    for (int p = 0; p < 2; ++p) {
      auto dir = DataDirectory::Open(root_ + "/data", p == 0 ? sequential : parallel);
      ASSERT_TRUE(dir.ok()) << dir.status().ToString();
      reasons[p] = ExpectDamaged(**dir, part).reason;
    }
    EXPECT_EQ(reasons[0], reasons[1]);
  };
  // Back to the fixture's files, closed cleanly (everything in SST files: RocksDB opened below
  // without placedb's merge operators replays no placedb write), then `edit` on the raw RocksDB.
  const auto edited = [&](const RawEdit& edit) {
    fs::remove_all(root_ + "/data");
    fs::copy(*template_root_ + "/data", root_ + "/data", fs::copy_options::recursive);
    EditClosedMap(edit);
  };
  rocksdb::WriteOptions sync;
  sync.sync = true;

  {
    SCOPED_TRACE("a corrupt block of bow, a third into the flushed places");
    const auto files = SstFilesOf("bow");
    ASSERT_EQ(files.size(), 1u);
    Overwrite(files[0], fs::file_size(files[0]) / 3, 64);
    expect_alike("maps/lab/" + fs::path(files[0]).filename().string());
  }
  {
    SCOPED_TRACE("place 45's record does not decode");
    edited([&](rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
      EXPECT_TRUE(raw->Put(sync, handles[1], PlaceKey(45), std::string("\x02garbage")).ok());
    });
    expect_alike("place 0000002D: place record");
  }
  {
    SCOPED_TRACE("place 70's BoW vector does not decode");
    edited([&](rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
      EXPECT_TRUE(raw->Put(sync, handles[2], PlaceKey(70), std::string("\x01\x05\x01")).ok());
    });
    expect_alike("place 00000046: bow vector");
  }
  {
    SCOPED_TRACE("place 50's BoW vector is missing");
    edited([&](rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
      EXPECT_TRUE(raw->Delete(sync, handles[2], PlaceKey(50)).ok());
    });
    expect_alike("place 00000032 has no BoW vector");
  }
  {
    SCOPED_TRACE("place 60's record is missing, its BoW vector is there");
    edited([&](rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
      EXPECT_TRUE(raw->Delete(sync, handles[1], PlaceKey(60)).ok());
    });
    expect_alike("has no BoW vector");
  }
  {
    SCOPED_TRACE("undamaged: both loaders open it");
    edited([](rocksdb::DB*, std::vector<rocksdb::ColumnFamilyHandle*>&) {});
    for (const StorageOptions& options : {sequential, parallel}) {
      auto dir = DataDirectory::Open(root_ + "/data", options);
      ASSERT_TRUE(dir.ok());
      auto map = (*dir)->OpenMap("lab", vocabulary_);
      ASSERT_TRUE(map.ok()) << map.status().ToString();
      EXPECT_EQ((*map)->Stats().database.places, size_t(kPlaces));
    }
  }
}

TEST_F(DamageTest, ScrubFindsACorruptFeaturesBlock) {
  const auto files = SstFilesOf("features");
  ASSERT_EQ(files.size(), 1u);
  const std::string sst = "maps/lab/" + fs::path(files[0]).filename().string();
  Overwrite(files[0], fs::file_size(files[0]) / 2, 64);
  auto dir = OpenDir();
  // Features are read only for verification: the map opens, the damage is found by reading.
  auto map = dir->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  auto report = (*map)->Scrub();
  ASSERT_TRUE(report.ok());
  EXPECT_FALSE(report->clean());
  // Files and runs of places checked on several threads: the same report, in the same order.
  auto parallel = (*map)->Scrub(4);
  ASSERT_TRUE(parallel.ok());
  EXPECT_EQ(parallel->files_checked, report->files_checked);
  EXPECT_EQ(parallel->places_checked, report->places_checked);
  ASSERT_EQ(parallel->damaged_files.size(), report->damaged_files.size());
  ASSERT_EQ(parallel->damaged_places.size(), report->damaged_places.size());
  for (size_t i = 0; i < report->damaged_places.size(); ++i) {
    EXPECT_EQ(parallel->damaged_places[i].id, report->damaged_places[i].id);
    EXPECT_EQ(parallel->damaged_places[i].reason, report->damaged_places[i].reason);
  }
  EXPECT_EQ(report->places_checked, uint64_t(kPlaces));
  ASSERT_EQ(report->damaged_files.size(), 1u);
  EXPECT_EQ(report->damaged_files[0].file, sst);
  ASSERT_GE(report->damaged_places.size(), 1u);
  EXPECT_LE(report->damaged_places.size(), 3u);  // the one or two places of one 16 KB block
  for (const auto& place : report->damaged_places) {
    EXPECT_LE(place.id, PlaceId(kFlushed)) << "only flushed places are in the SST";
    EXPECT_NE(place.reason.find(sst), std::string::npos) << place.reason;
    auto read = (*map)->GetPlace(place.id);
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.status().code(), StatusCode::kCorruption) << read.status().ToString();
    EXPECT_EQ(read.status().message().find(root_), std::string::npos) << read.status().message();
  }
  // Every other place reads back.
  for (PlaceId id = 1; id <= PlaceId(kPlaces); ++id) {
    bool damaged = false;
    for (const auto& place : report->damaged_places) damaged |= place.id == id;
    if (!damaged) {
      EXPECT_TRUE((*map)->GetPlace(id).ok()) << id;
    }
  }
}

TEST_F(DamageTest, TornUnacknowledgedTailIsToleratedAndNoted) {
  // A torn last record (power lost mid-write) holds no acknowledged write: the map opens with
  // every acknowledged place, and says what it tolerated.
  const fs::path wal = Wal();
  // A full-record header (checksum, length 1000, type 1) with only 100 bytes of its body.
  std::string torn;
  const uintmax_t left_in_block = 32768 - fs::file_size(wal) % 32768;
  if (left_in_block < 7 + 100) torn.assign(left_in_block, '\0');  // the block's trailer
  torn += std::string("\x12\x34\x56\x78\xe8\x03\x01", 7) + std::string(100, '\x07');
  std::ofstream(wal, std::ios::app | std::ios::binary) << torn;
  auto dir = OpenDir();
  auto map = dir->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_EQ((*map)->Stats().database.places, uint64_t(kPlaces));
  EXPECT_NE((*map)->open_note().find(wal.filename().string()), std::string::npos)
      << (*map)->open_note();
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

}  // namespace
}  // namespace placedb

int main(int argc, char** argv) {
  if (const char* data_dir = std::getenv(placedb::kChildEnv)) placedb::RunChild(data_dir);
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
