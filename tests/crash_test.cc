// Crash safety: a child process ingests places and is killed with SIGKILL at random moments. After
// each kill the parent reopens the map and checks that every acknowledged place is present and
// found by its own frame with the same score as before, and that no half-written place exists.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <deque>
#include <map>
#include <random>
#include <set>
#include <thread>

#include "core/storage/map_store.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

constexpr int kFrames = 20;
constexpr char kChildEnv[] = "PLACEDB_CRASH_CHILD";
// "group": the child commits through the map's commit queue (PlaceMap::Enqueue) from several
// threads, as the service's Ingest streams do; otherwise one thread calls Commit().
constexpr char kModeEnv[] = "PLACEDB_CRASH_MODE";
constexpr int kGroupThreads = 4;
constexpr size_t kGroupWindow = 8;  // places each thread keeps queued, like a stream's window

void Say(const char* format, unsigned id, int frame) {
  char line[64];
  const int len = std::snprintf(line, sizeof line, format, id, frame);
  if (write(STDOUT_FILENO, line, size_t(len)) != len) std::_Exit(6);
}

// The child (this binary re-executed with PLACEDB_CRASH_CHILD=<data dir>): commits frames forever
// and reports on stdout: "ack ID FRAME" once a place is durable, "rm ID" before removing one and
// "del ID" once the removal is durable.
[[noreturn]] void RunChild(const std::string& data_dir) {
  auto dir = DataDirectory::Open(data_dir);
  if (!dir.ok()) std::_Exit(3);
  auto map = (*dir)->OpenMap("crash", testing::DefaultVocabulary());
  if (!map.ok()) std::_Exit(4);
  const std::vector<ProcessedFrame> frames =
      testing::ProcessRtabmapFrames(*(*map)->database(), kFrames);
  const char* mode = std::getenv(kModeEnv);
  if (mode && std::string(mode) == "group") {
    // Acknowledged (reported) only once its PendingCommit is done: durable and indexed.
    auto stream = [&](int thread) {
      std::mt19937 rng{uint32_t(getpid()) * 31u + uint32_t(thread)};
      std::deque<std::pair<std::shared_ptr<PendingCommit>, int>> window;
      for (uint64_t n = 0;; ++n) {
        const int frame = int(rng() % kFrames);
        PlaceMetadata metadata;
        metadata.sequence = uint64_t(frame);
        metadata.agent_id = "crash-child-" + std::to_string(thread);
        window.emplace_back((*map)->Enqueue(frames[size_t(frame)], metadata), frame);
        if (window.size() < kGroupWindow) continue;
        const auto& added = window.front().first->Wait();
        if (!added.ok() || !added->stored) std::_Exit(5);
        Say("ack %u %d\n", added->id, window.front().second);
        window.pop_front();
      }
    };
    std::vector<std::thread> threads;
    for (int t = 0; t < kGroupThreads; ++t) threads.emplace_back(stream, t);
    for (auto& thread : threads) thread.join();  // never: the parent kills the child
    std::_Exit(8);
  }
  std::mt19937 rng{uint32_t(getpid())};
  for (uint64_t n = 0;; ++n) {
    const int frame = int(rng() % kFrames);
    PlaceMetadata metadata;
    metadata.sequence = uint64_t(frame);
    metadata.agent_id = "crash-child";
    auto added = (*map)->Commit(frames[size_t(frame)], metadata);
    if (!added.ok() || !added->stored) std::_Exit(5);
    Say("ack %u %d\n", added->id, frame);
    if (n % 7 == 3) {
      Say("rm %u %d\n", added->id, 0);
      if (Status removed = (*map)->RemovePlace(added->id); !removed.ok()) {
        std::fprintf(stderr, "crash child: %s\n", removed.ToString().c_str());
        std::_Exit(7);
      }
      Say("del %u %d\n", added->id, 0);
    }
  }
}

struct ChildReport {
  std::map<PlaceId, int> acknowledged;  // place -> frame
  std::set<PlaceId> removing;           // removal started, outcome unknown
  std::set<PlaceId> removed;            // removal acknowledged
};

void ParseReport(const std::string& output, ChildReport* report) {
  size_t pos = 0;
  while (true) {
    const size_t end = output.find('\n', pos);
    if (end == std::string::npos) break;  // a line cut by the kill was never acknowledged
    const std::string line = output.substr(pos, end - pos);
    pos = end + 1;
    unsigned id = 0;
    int frame = 0;
    if (std::sscanf(line.c_str(), "ack %u %d", &id, &frame) == 2) {
      report->acknowledged[id] = frame;
    } else if (std::sscanf(line.c_str(), "rm %u", &id) == 1) {
      report->removing.insert(id);
    } else if (std::sscanf(line.c_str(), "del %u", &id) == 1) {
      report->removing.erase(id);
      report->removed.insert(id);
    }
  }
}

// Kills the child `kills` times (mode: kModeEnv's value, "" for Commit()) and checks the map after
// each kill.
void KillAndCheck(const std::string& mode, int kills) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  auto vocabulary = testing::DefaultVocabulary();
  ASSERT_TRUE(vocabulary);
  const std::string root = testing::MakeTempDir("placedb-crash");
  const std::string data_dir = root + "/data";
  std::vector<ProcessedFrame> frames;
  {
    auto dir = DataDirectory::Open(data_dir);
    ASSERT_TRUE(dir.ok());
    auto map = (*dir)->CreateMap("crash", {}, vocabulary);
    ASSERT_TRUE(map.ok());
    frames = testing::ProcessRtabmapFrames(*(*map)->database(), kFrames);
  }
  std::mt19937 rng(2026);
  ChildReport report;
  const int kKills = kills;
  // The child's environment, built before fork: only async-signal-safe calls after it.
  std::vector<std::string> env_strings = {std::string(kChildEnv) + "=" + data_dir,
                                          std::string(kModeEnv) + "=" + mode};
  for (char** e = environ; *e; ++e) env_strings.emplace_back(*e);
  std::vector<char*> envp;
  for (auto& e : env_strings) envp.push_back(e.data());
  envp.push_back(nullptr);
  for (int run = 0; run < kKills; ++run) {
    int pipe_fds[2];
    ASSERT_EQ(pipe(pipe_fds), 0);
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      dup2(pipe_fds[1], STDOUT_FILENO);
      close(pipe_fds[0]);
      close(pipe_fds[1]);
      execle("/proc/self/exe", "crash_test_child", static_cast<char*>(nullptr), envp.data());
      std::_Exit(127);
    }
    close(pipe_fds[1]);
    // Kill at a random moment: sometimes while the child reopens, mostly mid-ingest.
    std::this_thread::sleep_for(std::chrono::milliseconds(100 + rng() % 1400));
    kill(child, SIGKILL);
    int status = 0;
    waitpid(child, &status, 0);
    ASSERT_TRUE(WIFSIGNALED(status)) << "child exited on its own with " << WEXITSTATUS(status);
    std::string output;
    char buffer[4096];
    for (ssize_t n; (n = read(pipe_fds[0], buffer, sizeof buffer)) > 0;) {
      output.append(buffer, size_t(n));
    }
    close(pipe_fds[0]);
    const size_t before = report.acknowledged.size();
    ParseReport(output, &report);

    auto dir = DataDirectory::Open(data_dir);
    ASSERT_TRUE(dir.ok()) << dir.status().ToString();
    auto map = (*dir)->OpenMap("crash", vocabulary);
    ASSERT_TRUE(map.ok()) << "run " << run << ": " << map.status().ToString();
    const Status integrity = (*map)->VerifyIntegrity();
    ASSERT_TRUE(integrity.ok()) << "run " << run << ": " << integrity.ToString();
    int present = 0;
    for (const auto& [id, frame] : report.acknowledged) {
      auto record = (*map)->database()->Get(id);
      if (report.removed.count(id)) {
        EXPECT_EQ(record, nullptr) << "acknowledged removal of place " << id << " was lost";
      } else if (!report.removing.count(id)) {
        ASSERT_NE(record, nullptr) << "run " << run << ": acknowledged place " << id << " lost";
        EXPECT_EQ(record->metadata.sequence, uint64_t(frame));
        ++present;
      }
    }
    // The newest acknowledged places are found by their own frame, with the full score.
    int checked = 0;
    for (auto it = report.acknowledged.rbegin(); it != report.acknowledged.rend() && checked < 4;
         ++it) {
      if (report.removed.count(it->first) || report.removing.count(it->first)) continue;
      ++checked;
      QueryOptions options;
      options.top_k = 100000;
      QueryResult result = (*map)->Search(frames[size_t(it->second)], options);
      bool found = false;
      for (const Match& match : result.matches) {
        if (match.place == it->first) {
          found = true;
          // Stored weights are quantised: an L1 self-match is within that bound of 1.
          EXPECT_NEAR(match.score, 1.0, InvertedIndex::kWeightRelativeError + 1e-5);
        }
      }
      EXPECT_TRUE(found) << "acknowledged place " << it->first << " not found by its own frame";
    }
    std::printf(
        "[crash] kill %d: %zu new acknowledgements, %d acknowledged places present, "
        "%zu removals acknowledged, map holds %zu places\n",
        run + 1, report.acknowledged.size() - before, present, report.removed.size(),
        (*map)->Stats().database.places);
  }
  EXPECT_GT(report.acknowledged.size(), 100u) << "the child barely ingested anything";
}

TEST(CrashSafety, AcknowledgedPlacesSurviveSigkill) {
  KillAndCheck("", 24);
}

// Group commit: 4 threads keep 8 places each in the map's commit queue; every place reported
// durable by its PendingCommit survives, none is half-written, each is found by its own frame.
TEST(CrashSafety, GroupCommittedPlacesSurviveSigkill) {
  KillAndCheck("group", 16);
}

}  // namespace
}  // namespace placedb

int main(int argc, char** argv) {
  if (const char* data_dir = std::getenv(placedb::kChildEnv)) placedb::RunChild(data_dir);
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
