// Snapshots (core/storage/snapshots.h) on real RocksDB maps in temp directories, with real frames:
// online consistency under a 2-agent ingest, archive round trips between data directories, and
// refused archives that leave nothing behind.
#include "core/storage/snapshots.h"

#include <gtest/gtest.h>
#include <openssl/evp.h>
#include <sys/resource.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <thread>
#include <tuple>

#include "core/base/files.h"
#include "core/base/timing.h"
#include "tests/rtabmap_frames.h"
#include "tests/snapshot_archive.h"
#include "tests/test_support.h"

namespace fs = std::filesystem;

namespace placedb {
namespace {

using testing::RtabmapFrame;

// A query's ranked answer, by the matched places' (agent, sequence): place ids differ between a
// map and its rebuilt reference, the frames they hold do not.
struct Answer {
  std::vector<std::tuple<std::string, uint64_t, double, int>> matches;
  bool operator==(const Answer&) const = default;
};

std::vector<Answer> AskAll(const PlaceMap& map, const std::vector<Observation>& queries) {
  std::vector<Answer> out;
  for (const Observation& query : queries) {
    auto result = map.Query(query, {});
    EXPECT_TRUE(result.ok()) << result.status().ToString();
    Answer answer;
    if (result.ok()) {
      for (const Match& m : result->matches) {
        answer.matches.emplace_back(m.metadata.agent_id, m.metadata.sequence, m.score, m.inliers);
      }
    }
    out.push_back(answer);
  }
  return out;
}

// Every file and folder under `path`, relative, to show that a refused operation left nothing.
std::set<std::string> Tree(const std::string& path) {
  std::set<std::string> out;
  for (const auto& entry : fs::recursive_directory_iterator(path)) {
    out.insert(fs::relative(entry.path(), path).generic_string());
  }
  return out;
}

// An archive in format version 1 (core/storage/snapshots.h) of `entries` (path, bytes), in that
// order, with a correct count, size and SHA-256: what a careless or hostile writer could send.
std::string HandBuiltArchive(const std::vector<std::pair<std::string, std::string>>& entries) {
  auto put = [](std::string* out, uint64_t value, int bytes) {
    for (int i = 0; i < bytes; ++i) out->push_back(char((value >> (8 * i)) & 0xff));
  };
  std::string out = "PDBSNAP\n";
  put(&out, 1, 4);
  put(&out, 0, 4);
  uint64_t total = 0;
  for (const auto& [path, bytes] : entries) {
    put(&out, 1, 1);
    put(&out, path.size(), 2);
    out += path;
    put(&out, bytes.size(), 8);
    out += bytes;
    total += bytes.size();
  }
  put(&out, 0, 1);
  put(&out, entries.size(), 8);
  put(&out, total, 8);
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_Digest(out.data(), out.size(), digest, &length, EVP_sha256(), nullptr);
  return out + std::string(reinterpret_cast<const char*>(digest), length);
}

// The entries of a well-formed archive (no checks: the archive comes from WriteArchive).
std::vector<std::pair<std::string, std::string>> Entries(const std::string& archive) {
  auto get = [&](size_t at, int bytes) {
    uint64_t value = 0;
    for (int i = 0; i < bytes; ++i) value |= uint64_t(uint8_t(archive[at + size_t(i)])) << (8 * i);
    return value;
  };
  std::vector<std::pair<std::string, std::string>> out;
  size_t at = 16;
  while (archive[at] == 1) {
    const size_t length = get(at + 1, 2);
    std::string path = archive.substr(at + 3, length);
    const size_t size = get(at + 3 + length, 8);
    out.emplace_back(std::move(path), archive.substr(at + 11 + length, size));
    at += 11 + length + size;
  }
  return out;
}

using ::placedb::testing::ArchiveStart;

// The process's peak resident set so far.
uint64_t PeakRssBytes() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return uint64_t(usage.ru_maxrss) * 1024;
}

class SnapshotsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    vocabulary_ = testing::DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
    root_ = testing::MakeTempDir("placedb-snapshots");
    for (int i = 40; i <= 70; i += 3) queries_.push_back(RtabmapFrame(i, "query"));
  }

  std::unique_ptr<DataDirectory> OpenDir(const std::string& name) {
    auto dir = DataDirectory::Open(root_ + "/" + name);
    EXPECT_TRUE(dir.ok()) << dir.status().ToString();
    return dir.ok() ? std::move(dir).value() : nullptr;
  }

  // What the server does: the vocabulary whose identity the map's info names, or
  // FAILED_PRECONDITION when this "server" does not have it.
  DataDirectory::VocabularyFor Resolver(AnyVocabulary known) {
    return [known](const MapInfo& info) -> Result<AnyVocabulary> {
      if (info.vocabulary_checksum != known.checksum()) {
        return Status::FailedPrecondition("no vocabulary with checksum " +
                                          std::to_string(info.vocabulary_checksum));
      }
      return known;
    };
  }

  // A map of `count` frames from one agent, and a snapshot of it.
  SnapshotInfo MakeSnapshot(DataDirectory* dir, SnapshotStore* store, const std::string& name,
                            int count) {
    auto map = dir->CreateMap(name, {}, vocabulary_);
    EXPECT_TRUE(map.ok()) << map.status().ToString();
    if (!map.ok()) return {};
    for (int i = 1; i <= count; ++i) EXPECT_TRUE((*map)->Add(RtabmapFrame(i, "robot")).ok());
    auto info = store->Create(**map, Resolver(vocabulary_));
    EXPECT_TRUE(info.ok()) << info.status().ToString();
    return info.ok() ? *info : SnapshotInfo{};
  }

  std::string Archive(const SnapshotStore& store, const std::string& id) {
    std::string bytes;
    Status s = store.WriteArchive(id, 4096, [&](std::string_view chunk) {
      EXPECT_LE(chunk.size(), 4096u);
      bytes.append(chunk);
      return Status::Ok();
    });
    EXPECT_TRUE(s.ok()) << s.ToString();
    auto size = store.ArchiveBytes(id);
    EXPECT_TRUE(size.ok());
    if (size.ok()) {
      EXPECT_EQ(*size, bytes.size());
    }
    return bytes;
  }

  std::string WriteFile(const std::string& name, const std::string& bytes) {
    const std::string path = root_ + "/" + name;
    std::ofstream(path, std::ios::binary) << bytes;
    return path;
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
  std::vector<Observation> queries_;
};

TEST_F(SnapshotsTest, SnapshotDuringTwoAgentIngestRestoresThatState) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  auto source = dir->CreateMap("source", {}, vocabulary_);
  ASSERT_TRUE(source.ok());

  // Two agents ingest their own frames in order; a snapshot is taken once both have started.
  constexpr int kPerAgent = 14;
  std::atomic<int> added{0};
  auto ingest = [&](const std::string& agent, int first) {
    for (int i = first; i < first + kPerAgent; ++i) {
      auto result = (*source)->Add(RtabmapFrame(i, agent));
      EXPECT_TRUE(result.ok()) << result.status().ToString();
      ++added;
    }
  };
  std::thread a(ingest, "agent-a", 1);
  std::thread b(ingest, "agent-b", 1 + kPerAgent);
  while (added < 6) std::this_thread::yield();
  auto snapshot = (*store)->Create(**source, Resolver(vocabulary_));
  a.join();
  b.join();
  ASSERT_TRUE(snapshot.ok()) << snapshot.status().ToString();
  EXPECT_EQ(snapshot->map, "source");
  EXPECT_EQ(snapshot->vocabulary_checksum, AnyVocabulary(vocabulary_).checksum());
  EXPECT_GE(snapshot->places, 1u);

  ASSERT_TRUE((*store)->Restore(snapshot->id, "restored").ok());
  auto restored = dir->OpenMap("restored", vocabulary_);
  ASSERT_TRUE(restored.ok()) << restored.status().ToString();
  EXPECT_EQ((*restored)->Stats().database.places, snapshot->places);

  // The snapshot holds what each agent's stream stored up to some frame (each agent writes in
  // order; a frame may be merged or invalid and store nothing). Rebuild the source's state at
  // the snapshot: each agent's frames up to the last one held, ingested into a new map.
  std::map<std::string, std::vector<uint64_t>> held;
  for (PlaceId id : (*restored)->database()->ListPlaces()) {
    auto place = (*restored)->GetPlace(id);
    ASSERT_TRUE(place.ok());
    held[place->record.metadata.agent_id].push_back(place->record.metadata.sequence);
  }
  auto reference = dir->CreateMap("reference", {}, vocabulary_);
  ASSERT_TRUE(reference.ok());
  for (const auto& [agent, first] :
       std::vector<std::pair<std::string, int>>{{"agent-a", 1}, {"agent-b", 1 + kPerAgent}}) {
    std::vector<uint64_t>& sequences = held[agent];
    std::sort(sequences.begin(), sequences.end());
    const int last = sequences.empty() ? first - 1 : int(sequences.back());
    std::vector<uint64_t> stored;
    for (int i = first; i <= last; ++i) {
      auto added = (*reference)->Add(RtabmapFrame(i, agent));
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      if (added->stored) stored.push_back(uint64_t(i));
    }
    EXPECT_EQ(sequences, stored) << agent << ": the snapshot is not a prefix of its stream";
  }
  const auto expected = AskAll(**reference, queries_);
  EXPECT_EQ(AskAll(**restored, queries_), expected);
  size_t answered = 0;
  for (const Answer& answer : expected) answered += answer.matches.empty() ? 0 : 1;
  EXPECT_GT(answered, 0u) << "the queries must match something for the comparison to count";
}

TEST_F(SnapshotsTest, ArchiveMovesASnapshotToAnotherDataDirectory) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const SnapshotInfo info = MakeSnapshot(dir.get(), store->get(), "lab", 20);
  ASSERT_FALSE(info.id.empty());
  auto source = dir->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(source.ok());
  const auto expected = AskAll(**source, queries_);
  const std::string path = WriteFile("lab.pdbsnap", Archive(**store, info.id));

  auto other = OpenDir("other");
  auto other_store = SnapshotStore::Open(other.get());
  ASSERT_TRUE(other_store.ok());
  auto imported = (*other_store)->Import(path, Resolver(vocabulary_));
  ASSERT_TRUE(imported.ok()) << imported.status().ToString();
  EXPECT_EQ(imported->id, info.id);
  EXPECT_EQ(imported->map, "lab");
  EXPECT_EQ(imported->places, info.places);
  EXPECT_EQ(imported->places, (*source)->Stats().database.places);
  EXPECT_EQ(imported->created_unix_ms, info.created_unix_ms);
  ASSERT_EQ((*other_store)->List().size(), 1u);

  ASSERT_TRUE((*other_store)->Restore(imported->id, "copy").ok());
  EXPECT_EQ((*other_store)->Restore(imported->id, "copy").code(), StatusCode::kAlreadyExists);
  auto copy = other->OpenMap("copy", vocabulary_);
  ASSERT_TRUE(copy.ok()) << copy.status().ToString();
  EXPECT_EQ((*copy)->info().name, "copy");
  EXPECT_EQ(AskAll(**copy, queries_), expected);

  // Importing the same archive again keeps both, under a new id.
  auto again = (*other_store)->Import(path, Resolver(vocabulary_));
  ASSERT_TRUE(again.ok()) << again.status().ToString();
  EXPECT_NE(again->id, info.id);
  EXPECT_EQ((*other_store)->List().size(), 2u);
}

TEST_F(SnapshotsTest, TransferCheckpointsAreVerifiedByTheirReceiver) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  auto source = dir->CreateMap("lab", {}, vocabulary_);
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  for (int i = 1; i <= 12; ++i) ASSERT_TRUE((*source)->Add(RtabmapFrame(i, "robot")).ok());
  auto sent = (*store)->CreateForTransfer(**source);
  ASSERT_TRUE(sent.ok()) << sent.status().ToString();
  EXPECT_EQ(sent->places, (*source)->Stats().database.places);
  EXPECT_EQ(sent->vocabulary_checksum, AnyVocabulary(vocabulary_).checksum());
  const std::string good = Archive(**store, sent->id);

  auto other = OpenDir("other");
  auto other_store = SnapshotStore::Open(other.get());
  ASSERT_TRUE(other_store.ok());
  auto imported = (*other_store)->Import(WriteFile("good.pdbsnap", good), Resolver(vocabulary_));
  ASSERT_TRUE(imported.ok()) << imported.status().ToString();
  EXPECT_EQ(imported->places, sent->places);
  ASSERT_TRUE((*other_store)->Restore(imported->id, "copy").ok());
  auto copy = other->OpenMap("copy", vocabulary_);
  ASSERT_TRUE(copy.ok()) << copy.status().ToString();
  EXPECT_EQ(AskAll(**copy, queries_), AskAll(**source, queries_));

  // Damage the sender never checked (a table's bytes flipped before the archive was written,
  // its digest then sound): the receiver's verification refuses it and keeps nothing.
  auto entries = Entries(good);
  bool damaged = false;
  for (auto& [path, bytes] : entries) {
    if (!damaged && path.ends_with(".sst") && bytes.size() > 200) {
      bytes[bytes.size() / 3] ^= 0x5a;
      damaged = true;
    }
  }
  ASSERT_TRUE(damaged);
  const auto before = Tree(root_ + "/other");
  auto refused =
      (*other_store)
          ->Import(WriteFile("damaged.pdbsnap", HandBuiltArchive(entries)), Resolver(vocabulary_));
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kCorruption) << refused.status().ToString();
  EXPECT_EQ(Tree(root_ + "/other"), before);

  // A manifest whose place count is not the map's (writers were not kept out) is refused too.
  auto miscounted = Entries(good);
  ASSERT_EQ(miscounted.front().first, "SNAPSHOT.json");
  std::string& manifest = miscounted.front().second;
  const std::string count = "\"places\": " + std::to_string(sent->places);
  const size_t at = manifest.find(count);
  ASSERT_NE(at, std::string::npos) << manifest;
  manifest.replace(at, count.size(), "\"places\": " + std::to_string(sent->places + 1));
  refused = (*other_store)
                ->Import(WriteFile("miscounted.pdbsnap", HandBuiltArchive(miscounted)),
                         Resolver(vocabulary_));
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kInvalidArgument) << refused.status().ToString();
  EXPECT_EQ(Tree(root_ + "/other"), before);
}

TEST_F(SnapshotsTest, BadArchivesAreRefusedAndLeaveNothingBehind) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const SnapshotInfo info = MakeSnapshot(dir.get(), store->get(), "lab", 8);
  ASSERT_FALSE(info.id.empty());
  const std::string good = Archive(**store, info.id);

  auto other = OpenDir("other");
  auto other_store = SnapshotStore::Open(other.get());
  ASSERT_TRUE(other_store.ok());
  const auto before = Tree(root_ + "/other");

  auto refused = [&](const std::string& what, const std::string& bytes,
                     std::vector<StatusCode> codes, AnyVocabulary known) {
    SCOPED_TRACE(what);
    auto result = (*other_store)->Import(WriteFile("bad.pdbsnap", bytes), Resolver(known));
    ASSERT_FALSE(result.ok());
    EXPECT_TRUE(std::find(codes.begin(), codes.end(), result.status().code()) != codes.end())
        << result.status().ToString();
    EXPECT_EQ(Tree(root_ + "/other"), before);
    EXPECT_TRUE((*other_store)->List().empty());
    EXPECT_TRUE(other->ListMaps().empty());
  };
  const AnyVocabulary ours(vocabulary_);
  const std::vector<StatusCode> bad = {StatusCode::kInvalidArgument, StatusCode::kCorruption};

  // Truncated anywhere: in the header, an entry's header, a file's bytes, the trailer.
  for (size_t keep : {size_t(0), size_t(5), size_t(20), good.size() / 2, good.size() - 1}) {
    refused("truncated to " + std::to_string(keep), good.substr(0, keep), bad, ours);
  }
  refused("truncated mid-file", good.substr(0, good.size() - 100), {StatusCode::kCorruption}, ours);
  // One byte flipped in the middle (file data): the digest catches it.
  std::string flipped = good;
  flipped[flipped.size() / 2] ^= 0x40;
  refused("one byte flipped", flipped, {StatusCode::kCorruption}, ours);
  // The digest itself damaged.
  std::string digest = good;
  digest.back() ^= 0x01;
  refused("digest flipped", digest, {StatusCode::kCorruption}, ours);
  // Foreign files: text, another format's header, an archive with bytes appended.
  refused("text", "hello, this is not a snapshot\n", {StatusCode::kInvalidArgument}, ours);
  refused("tar-like", std::string(512, '\0') + "ustar", {StatusCode::kInvalidArgument}, ours);
  refused("trailing bytes", good + "x", {StatusCode::kInvalidArgument}, ours);
  std::string version = good;
  version[8] = 9;
  refused("unknown version", version, {StatusCode::kInvalidArgument}, ours);
  // A sound archive of a map built with a vocabulary this server does not have.
  refused("foreign vocabulary", good, {StatusCode::kFailedPrecondition},
          AnyVocabulary(testing::OtherVocabulary()));

  // And the sound one still imports.
  EXPECT_TRUE((*other_store)->Import(WriteFile("good.pdbsnap", good), Resolver(ours)).ok());
}

TEST_F(SnapshotsTest, ADeleteDuringADownloadDoesNotCutItShort) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const SnapshotInfo info = MakeSnapshot(dir.get(), store->get(), "lab", 10);
  ASSERT_FALSE(info.id.empty());
  std::string bytes;
  bool deleted = false;
  // The sink deletes the snapshot at the first chunk: the store's lock is not held while
  // streaming (this would deadlock otherwise), and the files already open stay readable.
  Status written = (*store)->WriteArchive(info.id, 4096, [&](std::string_view chunk) {
    if (!deleted) {
      deleted = true;
      EXPECT_TRUE((*store)->Delete(info.id).ok());
    }
    bytes.append(chunk);
    return Status::Ok();
  });
  ASSERT_TRUE(written.ok()) << written.ToString();
  EXPECT_TRUE((*store)->List().empty());
  auto imported = (*store)->Import(WriteFile("lab.pdbsnap", bytes), Resolver(vocabulary_));
  ASSERT_TRUE(imported.ok()) << imported.status().ToString();
  EXPECT_EQ(imported->places, info.places);
  // A sink error stops the stream and is returned.
  EXPECT_EQ((*store)
                ->WriteArchive(imported->id, 4096,
                               [](std::string_view) { return Status::Cancelled("client gone"); })
                .code(),
            StatusCode::kCancelled);
}

TEST_F(SnapshotsTest, ListDeleteAndRetention) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get(), SnapshotOptions{.keep_per_map = 2});
  ASSERT_TRUE(store.ok());
  auto map = dir->CreateMap("lab", {}, vocabulary_);
  ASSERT_TRUE(map.ok());
  std::vector<std::string> ids;
  for (int i = 1; i <= 3; ++i) {
    ASSERT_TRUE((*map)->Add(RtabmapFrame(i, "robot")).ok());
    auto info = (*store)->Create(**map, Resolver(vocabulary_));
    ASSERT_TRUE(info.ok()) << info.status().ToString();
    EXPECT_EQ(info->places, uint64_t(i));
    ids.push_back(info->id);
  }
  // The oldest went; newest first.
  auto list = (*store)->List();
  ASSERT_EQ(list.size(), 2u);
  EXPECT_EQ(list[0].id, ids[2]);
  EXPECT_EQ(list[1].id, ids[1]);
  EXPECT_EQ(list[0].places, 3u);
  EXPECT_GT(list[0].bytes, 0u);
  EXPECT_EQ((*store)->Get(ids[0]).status().code(), StatusCode::kNotFound);

  EXPECT_EQ((*store)->Delete("../maps").code(), StatusCode::kInvalidArgument);
  EXPECT_EQ((*store)->Delete("nope").code(), StatusCode::kNotFound);
  EXPECT_EQ((*store)->Restore(ids[2], "bad/name").code(), StatusCode::kInvalidArgument);
  EXPECT_EQ((*store)->Restore("nope", "fine").code(), StatusCode::kNotFound);
  ASSERT_TRUE((*store)->Delete(ids[1]).ok());
  ASSERT_EQ((*store)->List().size(), 1u);
  // Deleting a snapshot leaves the map alone.
  EXPECT_EQ((*map)->Stats().database.places, 3u);

  // Leftovers of an interrupted operation are cleared when the store opens.
  fs::create_directories((*store)->path() + "/.importing-1-1/checkpoint");
  store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  EXPECT_FALSE(fs::exists((*store)->path() + "/.importing-1-1"));
  EXPECT_EQ((*store)->List().size(), 1u);
}

}  // namespace
}  // namespace placedb

namespace placedb {
namespace {

TEST_F(SnapshotsTest, EntriesThatClashAreRefusedEvenWithAValidDigest) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const SnapshotInfo info = MakeSnapshot(dir.get(), store->get(), "lab", 6);
  ASSERT_FALSE(info.id.empty());
  const auto entries = Entries(Archive(**store, info.id));
  ASSERT_GE(entries.size(), 3u);
  ASSERT_EQ(entries.front().first, "SNAPSHOT.json");
  // The hand-built writer is right: the same entries rebuilt import.
  auto other = OpenDir("other");
  auto other_store = SnapshotStore::Open(other.get());
  ASSERT_TRUE(other_store.ok());
  {
    auto rebuilt = (*other_store)
                       ->Import(WriteFile("rebuilt.pdbsnap", HandBuiltArchive(entries)),
                                Resolver(vocabulary_));
    ASSERT_TRUE(rebuilt.ok()) << rebuilt.status().ToString();
    ASSERT_TRUE((*other_store)->Delete(rebuilt->id).ok());
  }
  const auto before = Tree(root_ + "/other");
  // A file then a folder of the same name, the reverse, and the same file twice.
  const std::vector<std::vector<std::pair<std::string, std::string>>> clashes = {
      {{"checkpoint/a", "x"}, {"checkpoint/a/b", "y"}},
      {{"checkpoint/a/b", "y"}, {"checkpoint/a", "x"}},
      {{"checkpoint/CURRENT", "x"}, {"checkpoint/CURRENT", "y"}},
  };
  for (const auto& clash : clashes) {
    auto bad = entries;
    bad.insert(bad.begin() + 1, clash.begin(), clash.end());
    auto imported =
        (*other_store)
            ->Import(WriteFile("clash.pdbsnap", HandBuiltArchive(bad)), Resolver(vocabulary_));
    ASSERT_FALSE(imported.ok()) << clash.front().first;
    EXPECT_EQ(imported.status().code(), StatusCode::kInvalidArgument)
        << imported.status().ToString();
    EXPECT_NE(imported.status().message().find("clashes"), std::string::npos)
        << imported.status().ToString();
    EXPECT_EQ(Tree(root_ + "/other"), before) << clash.front().first;
  }
  EXPECT_TRUE((*other_store)->List().empty());
}

// Hostile archives over the stated limits (snapshots.h): refused from the field that states
// the size or count, before what it sizes is read or any file is written. Before the limits, a
// 1 GiB SNAPSHOT.json was held in memory whole (3.2 GB RSS in the server) and 200,000 one-byte
// entries were unpacked into files for 34 s before a refusal.
TEST_F(SnapshotsTest, ArchivesOverTheLimitsAreRefusedFromTheirFraming) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const auto before = Tree(root_ + "/data");
  auto refused = [&](const std::string& what, const std::string& path, const std::string& limit) {
    SCOPED_TRACE(what);
    const uint64_t peak_before = PeakRssBytes();
    Stopwatch watch;
    auto result = (*store)->Import(path, Resolver(vocabulary_));
    const double ms = watch.ElapsedMs();
    ASSERT_FALSE(result.ok());
    EXPECT_EQ(result.status().code(), StatusCode::kInvalidArgument) << result.status().ToString();
    EXPECT_NE(result.status().message().find(limit), std::string::npos)
        << result.status().ToString();
    EXPECT_EQ(Tree(root_ + "/data"), before);
    // The hostile sizes are 1 GiB: a refusal that read them would show here.
    EXPECT_LT(PeakRssBytes(), peak_before + (uint64_t(256) << 20));
    std::printf("%s: refused in %.1f ms: %s\n", what.c_str(), ms,
                result.status().ToString().c_str());
  };
  const std::string limit = std::to_string(kMaxSnapshotManifestBytes) + "-byte limit";

  // A manifest claiming 1 GiB, the file ending right after that claim: the limit, not the
  // truncation, is the answer (the claim is refused before any of its bytes is read).
  refused("huge manifest, truncated after its size",
          WriteFile("huge-manifest.pdbsnap", ArchiveStart("SNAPSHOT.json", uint64_t(1) << 30)),
          limit);
  // The same claim with the bytes there (a sparse file of zeros) and a full trailer.
  {
    const std::string path =
        WriteFile("sparse-manifest.pdbsnap", ArchiveStart("SNAPSHOT.json", uint64_t(1) << 30));
    const uint64_t body_end = fs::file_size(path) + (uint64_t(1) << 30);
    fs::resize_file(path, body_end + 1 + 16 + 32);  // end record and digest: zeros
    refused("huge manifest, present (sparse)", path, limit);
  }
  // One byte over the limit is refused; at the limit the framing is accepted (the manifest is
  // then found not to be JSON).
  refused("manifest one byte over",
          WriteFile("over.pdbsnap",
                    HandBuiltArchive(
                        {{"SNAPSHOT.json", std::string(kMaxSnapshotManifestBytes + 1, ' ')}})),
          limit);
  {
    auto at_limit = (*store)->Import(
        WriteFile("at.pdbsnap", HandBuiltArchive({{"SNAPSHOT.json",
                                                   std::string(kMaxSnapshotManifestBytes, ' ')}})),
        Resolver(vocabulary_));
    ASSERT_FALSE(at_limit.ok());
    EXPECT_NE(at_limit.status().message().find("not a JSON object"), std::string::npos)
        << at_limit.status().ToString();
    EXPECT_EQ(Tree(root_ + "/data"), before);
  }
  // A path length over 1024 bytes, refused before the path is read.
  refused("long path", WriteFile("long-path.pdbsnap", ArchiveStart(std::string(60000, 'a'), 0)),
          "at most 1024");

  // 200,000 one-byte entries with a sound framing and digest: refused at entry
  // kMaxSnapshotArchiveEntries + 1 of the framing pass, before a single file is written.
  std::vector<std::pair<std::string, std::string>> many = {{"SNAPSHOT.json", "{}"}};
  char name[32];
  for (int i = 0; i < 200'000; ++i) {
    std::snprintf(name, sizeof name, "checkpoint/%06d.sst", i);
    many.emplace_back(name, "x");
  }
  refused("200,000 entries", WriteFile("many.pdbsnap", HandBuiltArchive(many)),
          "more than " + std::to_string(kMaxSnapshotArchiveEntries) + " entries");
  EXPECT_TRUE((*store)->List().empty());
}

TEST_F(SnapshotsTest, AnArchivesHeadShowsWhatIsOverTheLimits) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const SnapshotInfo info = MakeSnapshot(dir.get(), store->get(), "lab", 4);
  ASSERT_FALSE(info.id.empty());
  const std::string good = Archive(**store, info.id);
  // Any start of a sound archive is sound so far, however short.
  for (size_t keep : {size_t(0), size_t(10), size_t(16), size_t(40), size_t(4096), good.size()}) {
    EXPECT_TRUE(CheckSnapshotArchiveHead(std::string_view(good).substr(0, keep)).ok()) << keep;
  }
  auto invalid = [](const std::string& head, const std::string& says) {
    const Status status = CheckSnapshotArchiveHead(head);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument) << status.ToString();
    EXPECT_NE(status.message().find(says), std::string::npos) << status.ToString();
  };
  invalid(ArchiveStart("SNAPSHOT.json", uint64_t(1) << 30), "limit of a snapshot manifest");
  invalid(ArchiveStart("checkpoint/CURRENT", 10), "unacceptable path");
  invalid(std::string(4096, 'x'), "bad magic");
}

TEST_F(SnapshotsTest, RestoreHardLinksTheSnapshotsTablesAndLeavesTheSnapshotWhole) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const SnapshotInfo info = MakeSnapshot(dir.get(), store->get(), "lab", 20);
  ASSERT_FALSE(info.id.empty());
  const std::string checkpoint = (*store)->path() + "/" + info.id + "/checkpoint";
  // The checkpoint's tables that are the same file (inode) in `restored`, and how many it has.
  auto shared_tables = [&](const std::string& restored) {
    size_t shared = 0, total = 0;
    for (const auto& entry : fs::directory_iterator(checkpoint)) {
      if (entry.path().extension() != ".sst") continue;
      ++total;
      std::error_code ec;
      if (fs::equivalent(entry.path(), fs::path(restored) / entry.path().filename(), ec)) ++shared;
    }
    return std::pair(shared, total);
  };
  ASSERT_TRUE((*store)->Restore(info.id, "first").ok());
  {
    auto first = dir->OpenMap("first", vocabulary_);
    ASSERT_TRUE(first.ok()) << first.status().ToString();
    const auto [shared, total] = shared_tables(dir->path() + "/maps/first");
    EXPECT_GT(total, 0u);
    EXPECT_EQ(shared, total);  // every table of the snapshot is linked, not copied
    // The restored map lives its own life: new places (written, flushed at close), then it is
    // deleted (its names unlinked).
    for (int i = 30; i <= 40; ++i) ASSERT_TRUE((*first)->Add(RtabmapFrame(i, "later")).ok());
  }
  dir->CloseMap("first");
  ASSERT_TRUE(dir->DeleteMap("first").ok());
  // The snapshot is untouched: it still restores to the map it was.
  ASSERT_TRUE((*store)->Restore(info.id, "second").ok());
  auto second = dir->OpenMap("second", vocabulary_);
  ASSERT_TRUE(second.ok()) << second.status().ToString();
  auto lab = dir->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(lab.ok());
  EXPECT_EQ((*second)->Stats().database.places, info.places);
  EXPECT_EQ(AskAll(**second, queries_), AskAll(**lab, queries_));
  auto scrub = (*second)->Scrub();
  ASSERT_TRUE(scrub.ok());
  EXPECT_TRUE(scrub->clean());

  // With links off (the benchmark's baseline) every file is copied.
  StorageOptions copying;
  copying.restore_hard_links = false;
  auto plain = DataDirectory::Open(root_ + "/plain", copying);
  ASSERT_TRUE(plain.ok());
  ASSERT_TRUE((*plain)->RestoreMap("copied", checkpoint).ok());
  const auto [shared, total] = shared_tables(root_ + "/plain/maps/copied");
  EXPECT_GT(total, 0u);
  EXPECT_EQ(shared, 0u);
}

}  // namespace
}  // namespace placedb

namespace placedb {
namespace {

// Verification runs without the store's lock: the vocabulary resolver, called in the middle of
// it, lists, reads and deletes other snapshots (this would deadlock if the lock were held), for
// Create and Import alike; the snapshot made then is whole.
TEST_F(SnapshotsTest, OtherOperationsGoOnDuringAVerification) {
  auto dir = OpenDir("data");
  auto store = SnapshotStore::Open(dir.get());
  ASSERT_TRUE(store.ok());
  const SnapshotInfo first = MakeSnapshot(dir.get(), store->get(), "lab", 8);
  ASSERT_FALSE(first.id.empty());
  const std::string archive = WriteFile("lab.pdbsnap", Archive(**store, first.id));
  auto map = dir->OpenMap("lab", vocabulary_);
  ASSERT_TRUE(map.ok());
  std::vector<std::string> seen;
  auto meanwhile = [&](const std::string& victim) {
    return [&, victim, resolve = Resolver(vocabulary_)](const MapInfo& info) {
      for (const SnapshotInfo& s : (*store)->List()) seen.push_back(s.id);
      EXPECT_TRUE((*store)->Get(victim).ok());
      EXPECT_TRUE((*store)->Delete(victim).ok());
      return resolve(info);
    };
  };
  auto second = (*store)->Create(**map, meanwhile(first.id));
  ASSERT_TRUE(second.ok()) << second.status().ToString();
  EXPECT_EQ(seen, std::vector<std::string>{first.id});  // the one being made is not listed
  seen.clear();
  auto imported = (*store)->Import(archive, meanwhile(second->id));
  ASSERT_TRUE(imported.ok()) << imported.status().ToString();
  EXPECT_EQ(seen, std::vector<std::string>{second->id});
  ASSERT_EQ((*store)->List().size(), 1u);
  EXPECT_EQ((*store)->List().front().id, imported->id);
  EXPECT_EQ(imported->places, first.places);
  ASSERT_TRUE((*store)->Restore(imported->id, "copy").ok());
  auto copy = dir->OpenMap("copy", vocabulary_);
  ASSERT_TRUE(copy.ok()) << copy.status().ToString();
  EXPECT_EQ(AskAll(**copy, queries_), AskAll(**map, queries_));
}

}  // namespace
}  // namespace placedb
