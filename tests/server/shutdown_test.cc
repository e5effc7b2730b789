// Shutting down: streams open and busy lose no acknowledged place, a frame in the middle of the
// pipeline is finished while health says NOT_SERVING, and the placedb-server binary exits 0 on
// SIGTERM.
#include <arpa/inet.h>
#include <fcntl.h>
#include <grpc/grpc.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <future>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "core/detect/detector.h"
#include "core/storage/map_store.h"
#include "tests/join_on_exit.h"
#include "tests/server/server_fixture.h"
#include "tests/test_support.h"

namespace placedb::server_testing {
namespace {

// Streams are open and busy when the server shuts down: every place it acknowledged is on disk.
TEST_F(ServerTest, ShutdownWithOpenStreamsLosesNoAcknowledgedPlace) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 20; ++frame) frames.push_back(RtabmapObservation(frame, "a"));

  std::mutex mutex;
  std::condition_variable acked_cv;
  std::vector<uint32_t> acked;
  std::atomic<bool> stop{false};
  std::vector<grpc::Status> finals(2);
  std::vector<std::thread> agents;
  // An assertion that returns early shuts the server down (ending the streams) and joins.
  bool shut_down = false;
  ::placedb::testing::JoinOnExit join_agents([&] {
    stop = true;
    if (!shut_down) server_->Shutdown();
  });
  join_agents.Add(agents);
  for (int agent = 0; agent < 2; ++agent) {
    agents.emplace_back([&, agent] {
      grpc::ClientContext context;
      auto stream = stub_->Ingest(&context);
      std::thread writer([&] {
        v1::IngestRequest header;
        header.mutable_header()->set_map("m");
        if (!stream->Write(header)) return;
        for (size_t i = size_t(agent); !stop; ++i) {
          v1::IngestRequest request;
          *request.mutable_observation() = frames[i % frames.size()];
          if (!stream->Write(request)) return;
        }
        stream->WritesDone();
      });
      v1::IngestResponse response;
      while (stream->Read(&response)) {
        if (response.stored()) {
          std::lock_guard lock(mutex);
          acked.push_back(response.place_id());
          acked_cv.notify_all();
        }
      }
      stop = true;
      writer.join();
      finals[size_t(agent)] = stream->Finish();
    });
  }
  // Also an idle stream (header only) and one that never sent its header: neither may hold up
  // the shutdown until its deadline.
  grpc::ClientContext idle_context, silent_context;
  auto idle = stub_->Ingest(&idle_context);
  v1::IngestRequest header;
  header.mutable_header()->set_map("m");
  ASSERT_TRUE(idle->Write(header));
  auto silent = stub_->Ingest(&silent_context);
  {
    std::unique_lock lock(mutex);
    ASSERT_TRUE(
        acked_cv.wait_for(lock, std::chrono::seconds(60), [&] { return acked.size() >= 12; }));
  }
  const auto shutdown_started = std::chrono::steady_clock::now();
  server_->Shutdown();  // streams still open and sending
  shut_down = true;
  const double shutdown_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - shutdown_started).count();
  EXPECT_LT(shutdown_s, 5.0) << "shutdown waited for idle streams (deadline is 10 s)";
  for (auto& agent : agents) agent.join();
  v1::IngestResponse ignored;
  EXPECT_FALSE(idle->Read(&ignored));
  EXPECT_FALSE(idle->Finish().ok());
  EXPECT_FALSE(silent->Read(&ignored));
  EXPECT_FALSE(silent->Finish().ok());
  for (const grpc::Status& status : finals) {
    EXPECT_TRUE(status.error_code() == grpc::StatusCode::UNAVAILABLE ||
                status.error_code() == grpc::StatusCode::CANCELLED)
        << int(status.error_code()) << " " << status.error_message();
  }
  StopServer();

  auto directory = DataDirectory::Open(root_ + "/data");
  ASSERT_TRUE(directory.ok()) << directory.status().ToString();
  auto map = (*directory)->OpenMap("m", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  std::lock_guard lock(mutex);
  EXPECT_GE((*map)->Stats().database.places, acked.size());
  for (uint32_t id : acked) EXPECT_TRUE((*map)->GetPlace(id).ok()) << "acknowledged place " << id;
  std::printf(
      "[server] shutdown with 2 busy streams in %.3f s: %zu acknowledged places, %zu on "
      "disk\n",
      shutdown_s, acked.size(), (*map)->Stats().database.places);
}

// A frame in the middle of the pipeline when shutdown starts is still stored and answered; while
// it finishes, health says NOT_SERVING and new calls are refused.
TEST_F(ServerTest, ShutdownFinishesInFlightFramesAndReportsNotServing) {
  auto gate = std::make_shared<GateDetector>();
  ServerDeps deps;
  deps.detector = gate;
  ASSERT_NO_FATAL_FAILURE(StartServer(Config(), deps));
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);
  CreateMap("m", server_boxes);

  IngestOutcome outcome;
  std::thread agent([&] { outcome = IngestAll(stub_.get(), "m", {RtabmapObservation(1, "a")}); });
  std::thread stopper;
  // An assertion that returns early lets the frame through (the shutdown then ends) and joins.
  ::placedb::testing::JoinOnExit join_threads([&] { gate->Open(); });
  join_threads.Add(agent);
  join_threads.Add(stopper);
  gate->WaitEntered();  // the frame is being detected
  stopper = std::thread([&] { server_->Shutdown(); });
  // Draining: health is NOT_SERVING (2) and new work is refused.
  std::string health;
  for (int i = 0; i < 500; ++i) {
    ASSERT_TRUE(HealthCheck(channel_, &health).ok());
    if (health == std::string("\x08\x02", 2)) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  EXPECT_EQ(health, std::string("\x08\x02", 2));
  v1::QueryResponse response;
  EXPECT_EQ(Query("m", RtabmapObservation(2, "a"), &response).error_code(),
            grpc::StatusCode::UNAVAILABLE);
  gate->Open();
  stopper.join();
  agent.join();
  ASSERT_EQ(outcome.responses.size(), 1u) << outcome.status.error_message();
  EXPECT_TRUE(outcome.responses[0].stored());
  EXPECT_EQ(outcome.responses[0].boxes_used_size(), 1);
  EXPECT_GT(outcome.responses[0].timings().detect_ms(), 0);
  StopServer();
  auto directory = DataDirectory::Open(root_ + "/data");
  ASSERT_TRUE(directory.ok());
  auto map = (*directory)->OpenMap("m", vocabulary_);
  ASSERT_TRUE(map.ok());
  EXPECT_TRUE((*map)->GetPlace(outcome.responses[0].place_id()).ok());
}

// build/tests/server_shutdown_test -> build/server/placedb-server
std::string ServerBinary() {
  char self[4096];
  const ssize_t n = readlink("/proc/self/exe", self, sizeof self - 1);
  if (n <= 0) return "";
  std::string path(self, size_t(n));
  path = path.substr(0, path.rfind('/'));  // build/tests
  return path.substr(0, path.rfind('/')) + "/server/placedb-server";
}

// How a placedb-server child process runs: where, with what environment, and where its stdout and
// stderr go (inherited when negative).
struct ProcessSetup {
  std::string working_directory;  // empty = this process's
  std::vector<std::string> unset_environment;
  std::vector<std::string> set_environment;  // NAME=VALUE
  int stdout_fd = -1;
  int stderr_fd = -1;
};

// placedb-server with `args` (after the binary's path).
pid_t StartServerBinary(const std::vector<std::string>& arguments, const ProcessSetup& setup) {
  const std::string binary = ServerBinary();
  std::vector<std::string> args = {binary};
  args.insert(args.end(), arguments.begin(), arguments.end());
  std::vector<char*> argv;
  for (std::string& arg : args) argv.push_back(arg.data());
  argv.push_back(nullptr);
  // The environment is made before fork: the child only calls async-signal-safe functions.
  std::vector<std::string> environment;
  for (char** entry = environ; *entry != nullptr; ++entry) {
    const std::string text = *entry;
    const std::string name = text.substr(0, text.find('='));
    bool unset = false;
    for (const std::string& removed : setup.unset_environment) unset = unset || removed == name;
    for (const std::string& added : setup.set_environment) {
      unset = unset || added.substr(0, added.find('=')) == name;
    }
    if (!unset) environment.push_back(text);
  }
  environment.insert(environment.end(), setup.set_environment.begin(), setup.set_environment.end());
  std::vector<char*> envp;
  for (std::string& entry : environment) envp.push_back(entry.data());
  envp.push_back(nullptr);
  const pid_t pid = fork();
  if (pid == 0) {
    if (!setup.working_directory.empty() && chdir(setup.working_directory.c_str()) != 0) {
      _exit(126);
    }
    if (setup.stdout_fd >= 0) dup2(setup.stdout_fd, STDOUT_FILENO);
    if (setup.stderr_fd >= 0) dup2(setup.stderr_fd, STDERR_FILENO);
    execve(binary.c_str(), argv.data(), envp.data());
    _exit(127);
  }
  return pid;
}

// A placedb-server process on `address` with `data`, metrics and console off. Its log and errors
// go to `output_fd` (none when negative).
pid_t StartServerProcess(const std::string& address, const std::string& data, int output_fd) {
  const std::string vocabulary = "default=" + testing::DefaultVocabularyPath();
  ProcessSetup setup;
  setup.stdout_fd = output_fd;  // the log's info lines
  setup.stderr_fd = output_fd;  // its warnings and errors, and usage errors
  return StartServerBinary(
      {"--listen", address, "--data-dir", data, "--metrics-listen", "off", "--console-listen",
       "off", "--vocabulary", vocabulary, "--log-level", "warn"},
      setup);
}

// Waits up to `seconds` for `pid` to exit (a pidfd becomes readable when it does): true with its
// status, false when it is still running.
bool WaitForExit(pid_t pid, int seconds, int* status) {
  // The syscall: Debian 12's <sys/pidfd.h> lacks extern "C" (its pidfd_open does not link).
  const int pidfd = int(syscall(SYS_pidfd_open, pid, 0));
  if (pidfd < 0) return waitpid(pid, status, 0) == pid;  // already reaped: cannot happen here
  pollfd exited = {pidfd, POLLIN, 0};
  const int ready = poll(&exited, 1, seconds * 1000);
  close(pidfd);
  return ready == 1 && waitpid(pid, status, 0) == pid;
}

// SIGTERM with streams open: the process drains, flushes and exits 0; the places are on disk.
TEST(ServerBinaryTest, SigtermShutsDownGracefullyWithExitZero) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  const std::string binary = ServerBinary();
  ASSERT_EQ(access(binary.c_str(), X_OK), 0) << binary << " is not built";
  const std::string root = testing::MakeTempDir("placedb-binary");
  const std::string address = "127.0.0.1:" + std::to_string(placedb::testing::UnusedLoopbackPort());
  const std::string data = root + "/data";
  const pid_t pid = StartServerProcess(address, data, -1);
  ASSERT_GE(pid, 0);
  grpc::ChannelArguments channel_args;  // retry quickly while the child starts
  channel_args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 50);
  channel_args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 50);
  channel_args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 200);
  auto channel =
      grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), channel_args);
  const bool connected =
      channel->WaitForConnected(std::chrono::system_clock::now() + std::chrono::seconds(20));
  if (!connected) kill(pid, SIGKILL);
  ASSERT_TRUE(connected) << "placedb-server did not start listening on " << address;
  auto stub = v1::PlaceDb::NewStub(channel);
  {
    grpc::ClientContext context;
    v1::CreateMapRequest request;
    request.set_name("m");
    v1::MapDescription description;
    ASSERT_TRUE(stub->CreateMap(&context, request, &description).ok());
  }
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 5; ++frame) frames.push_back(RtabmapObservation(frame, "a"));
  const IngestOutcome outcome = IngestAll(stub.get(), "m", frames);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  grpc::ClientContext idle_context;  // an open, idle stream must not hold up the exit
  auto idle = stub->Ingest(&idle_context);
  v1::IngestRequest header;
  header.mutable_header()->set_map("m");
  ASSERT_TRUE(idle->Write(header));

  const auto signalled = std::chrono::steady_clock::now();
  ASSERT_EQ(kill(pid, SIGTERM), 0);
  int status = 0;
  pid_t done = 0;
  while ((done = waitpid(pid, &status, WNOHANG)) == 0 &&
         std::chrono::steady_clock::now() - signalled < std::chrono::seconds(20)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (done == 0) kill(pid, SIGKILL);
  ASSERT_EQ(done, pid) << "placedb-server did not exit within 20 s of SIGTERM";
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  EXPECT_LT(std::chrono::steady_clock::now() - signalled, std::chrono::seconds(5));
  v1::IngestResponse ignored;
  EXPECT_FALSE(idle->Read(&ignored));
  (void)idle->Finish();

  auto directory = DataDirectory::Open(data);
  ASSERT_TRUE(directory.ok()) << directory.status().ToString();
  auto map = (*directory)->OpenMap("m", testing::DefaultVocabulary());
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  for (const auto& response : outcome.responses) {
    if (response.stored()) {
      EXPECT_TRUE((*map)->GetPlace(response.place_id()).ok());
    }
  }
  EXPECT_EQ((*map)->Stats().database.places, 5u);
}

// Starts a first server (waits until it serves), then a second one that must refuse to start:
// its exit status and everything it printed. The first is stopped at the end of the scope.
struct RefusedSecondServer {
  pid_t first = -1;
  std::string first_address;
  std::shared_ptr<grpc::Channel> channel;  // to the first
  int status = 0;                          // the second's, from waitpid
  std::string output;                      // the second's
  ~RefusedSecondServer() {
    if (first > 0) {
      kill(first, SIGTERM);
      waitpid(first, nullptr, 0);
    }
  }
};

void StartTwo(const std::string& first_address, const std::string& first_data,
              const std::string& second_address, const std::string& second_data,
              RefusedSecondServer* out) {
  const std::string binary = ServerBinary();
  ASSERT_EQ(access(binary.c_str(), X_OK), 0) << binary << " is not built";
  out->first_address = first_address;
  out->first = StartServerProcess(first_address, first_data, -1);
  ASSERT_GT(out->first, 0);
  out->channel = grpc::CreateChannel(first_address, grpc::InsecureChannelCredentials());
  ASSERT_TRUE(
      out->channel->WaitForConnected(std::chrono::system_clock::now() + std::chrono::seconds(20)))
      << "the first placedb-server did not start";
  int err[2];
  ASSERT_EQ(pipe(err), 0);
  const pid_t second = StartServerProcess(second_address, second_data, err[1]);
  close(err[1]);
  // A second server that did start would never exit: 30 s, then it is killed and fails the test.
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  pid_t done = 0;
  while ((done = waitpid(second, &out->status, WNOHANG)) == 0 &&
         std::chrono::steady_clock::now() < until) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  if (done == 0) {
    kill(second, SIGKILL);
    waitpid(second, &out->status, 0);
  }
  char buffer[4096];  // its output: complete once it is gone
  for (ssize_t n; (n = read(err[0], buffer, sizeof buffer)) > 0;) {
    out->output.append(buffer, size_t(n));
  }
  close(err[0]);
  ASSERT_NE(done, 0) << "the second placedb-server was still running after 30 s:\n" << out->output;
}

// The first server still serves (it alone answers on its port).
void ExpectFirstServes(const RefusedSecondServer& servers) {
  // Each call on a connection of its own (a private subchannel pool): the kernel splits
  // connections, not calls, between two servers sharing a port.
  for (int i = 0; i < 4; ++i) {
    grpc::ChannelArguments arguments;
    arguments.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
    auto stub = v1::PlaceDb::NewStub(grpc::CreateCustomChannel(
        servers.first_address, grpc::InsecureChannelCredentials(), arguments));
    grpc::ClientContext context;
    v1::ListMapsRequest request;
    v1::ListMapsResponse response;
    EXPECT_TRUE(stub->ListMaps(&context, request, &response).ok());
  }
}

// A second server on the same data directory refuses to start (exit 1, the reason on stderr)
// instead of serving every map as unavailable and creating new ones beside the first's.
TEST(ServerBinaryTest, SecondServerOnTheSameDataDirectoryRefusesToStart) {
  const std::string data = testing::MakeTempDir("placedb-binary-lock") + "/data";
  const auto address = [] {
    return "127.0.0.1:" + std::to_string(placedb::testing::UnusedLoopbackPort());
  };
  RefusedSecondServer servers;
  StartTwo(address(), data, address(), data, &servers);
  EXPECT_TRUE(WIFEXITED(servers.status) && WEXITSTATUS(servers.status) != 0) << servers.output;
  EXPECT_NE(
      servers.output.find("data directory " + data + ": in use by another placedb process (pid " +
                          std::to_string(servers.first) + ")"),
      std::string::npos)
      << servers.output;
  ExpectFirstServes(servers);
}

// A second server with its own data directory on the first's port refuses to start. (gRPC sets
// SO_REUSEPORT by default: both bound the port, both logged "listening", and the kernel split
// the connections between two databases: `maps list` alternated between two answers.)
TEST(ServerBinaryTest, SecondServerOnTheSamePortRefusesToStart) {
  const std::string address = "127.0.0.1:" + std::to_string(placedb::testing::UnusedLoopbackPort());
  const std::string root = testing::MakeTempDir("placedb-binary-port");
  RefusedSecondServer servers;
  StartTwo(address, root + "/first", address, root + "/second", &servers);
  EXPECT_TRUE(WIFEXITED(servers.status) && WEXITSTATUS(servers.status) != 0) << servers.output;
  EXPECT_NE(servers.output.find("cannot listen on " + address), std::string::npos)
      << servers.output;
  ExpectFirstServes(servers);
}

// Everything a child wrote to a file.
std::string FileText(const std::string& path) {
  std::ifstream in(path);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// The checkout this test was built from (its var/vocabulary holds the default vocabulary: the
// test fixture builds it there).
std::string Checkout() {
  return std::filesystem::path(PLACEDB_SOURCE_DIR).lexically_normal().string();
}

// Started from an empty directory with the embedded defaults (no --vocabulary): the server finds
// the default vocabulary in the checkout of its executable, not in the working directory, and
// serves. Its info lines go to stdout, none to stderr.
TEST(ServerBinaryTest, StartsFromAnyWorkingDirectory) {
  const std::string binary = ServerBinary();
  ASSERT_EQ(access(binary.c_str(), X_OK), 0) << binary << " is not built";
  const std::string expected_vocabulary = Checkout() + "/var/vocabulary/default.pdbv";
  ASSERT_EQ(access(expected_vocabulary.c_str(), R_OK), 0) << expected_vocabulary;
  const std::string root = testing::MakeTempDir("placedb-binary-cwd");
  const std::string elsewhere = root + "/elsewhere";
  ASSERT_TRUE(std::filesystem::create_directory(elsewhere));
  const std::string address = "127.0.0.1:" + std::to_string(placedb::testing::UnusedLoopbackPort());
  const int out = open((root + "/stdout").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
  const int err = open((root + "/stderr").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
  ASSERT_TRUE(out >= 0 && err >= 0);
  ProcessSetup setup;
  setup.working_directory = elsewhere;
  setup.unset_environment = {"PLACEDB_HOME", "PLACEDB_CONFIG"};
  setup.stdout_fd = out;
  setup.stderr_fd = err;
  const pid_t pid = StartServerBinary({"--listen", address, "--data-dir", root + "/data",
                                       "--metrics-listen", "off", "--console-listen", "off"},
                                      setup);
  close(out);
  close(err);
  ASSERT_GT(pid, 0);
  auto channel = grpc::CreateChannel(address, grpc::InsecureChannelCredentials());
  const bool connected =
      channel->WaitForConnected(std::chrono::system_clock::now() + std::chrono::seconds(20));
  int status = 0;
  if (!connected) {
    kill(pid, SIGKILL);
    waitpid(pid, &status, 0);
  }
  ASSERT_TRUE(connected) << "placedb-server did not start from " << elsewhere << ":\n"
                         << FileText(root + "/stdout") << FileText(root + "/stderr");
  {
    auto stub = v1::PlaceDb::NewStub(channel);
    grpc::ClientContext context;
    v1::ServerInfo info;
    ASSERT_TRUE(stub->GetServerInfo(&context, {}, &info).ok());
    ASSERT_GE(info.vocabularies_size(), 1);
    EXPECT_EQ(info.vocabularies(0).name(), "default");
  }
  ASSERT_EQ(kill(pid, SIGTERM), 0);
  ASSERT_TRUE(WaitForExit(pid, 20, &status)) << "placedb-server did not exit on SIGTERM";
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  const std::string stdout_text = FileText(root + "/stdout");
  EXPECT_NE(stdout_text.find("vocabulary 'default': " + expected_vocabulary), std::string::npos)
      << stdout_text;
  // Levels split: info on stdout only, warnings and errors on stderr only.
  const std::string stderr_text = FileText(root + "/stderr");
  EXPECT_EQ(stderr_text.find(" info "), std::string::npos) << stderr_text;
  EXPECT_EQ(stdout_text.find(" warning "), std::string::npos) << stdout_text;
  EXPECT_EQ(stdout_text.find(" error "), std::string::npos) << stdout_text;
  // Nothing was made in the working directory (no var/data beside it).
  EXPECT_TRUE(std::filesystem::is_empty(elsewhere));
}

// Errors go to stderr, not stdout: a bad configuration file (exit 2), and default files that
// are in none of the places looked at (exit 1, naming each path tried).
TEST(ServerBinaryTest, ErrorsGoToStderr) {
  const std::string binary = ServerBinary();
  ASSERT_EQ(access(binary.c_str(), X_OK), 0) << binary << " is not built";
  const std::string root = testing::MakeTempDir("placedb-binary-stderr");
  const auto run = [&](const std::vector<std::string>& args, const ProcessSetup& base,
                       std::string* stdout_text, std::string* stderr_text) {
    ProcessSetup setup = base;
    setup.stdout_fd = open((root + "/stdout").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
    setup.stderr_fd = open((root + "/stderr").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
    const pid_t pid = StartServerBinary(args, setup);
    close(setup.stdout_fd);
    close(setup.stderr_fd);
    int status = -1;
    if (!WaitForExit(pid, 20, &status)) {
      kill(pid, SIGKILL);
      waitpid(pid, &status, 0);
      ADD_FAILURE() << "placedb-server kept running";
    }
    *stdout_text = FileText(root + "/stdout");
    *stderr_text = FileText(root + "/stderr");
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  };
  const std::string address = "127.0.0.1:" + std::to_string(placedb::testing::UnusedLoopbackPort());
  const std::vector<std::string> quiet = {"--listen",         address, "--metrics-listen", "off",
                                          "--console-listen", "off"};

  std::ofstream(root + "/bad.yaml") << "threads: many\n";
  std::vector<std::string> args = quiet;
  args.insert(args.end(), {"--config", root + "/bad.yaml"});
  std::string out, err;
  EXPECT_EQ(run(args, {}, &out, &err), 2);
  EXPECT_NE(err.find("config file " + root + "/bad.yaml"), std::string::npos) << err;
  EXPECT_NE(err.find("threads"), std::string::npos) << err;
  EXPECT_EQ(out.find("bad.yaml"), std::string::npos) << out;

  const std::string home = root + "/home";
  ASSERT_TRUE(std::filesystem::create_directory(home));
  ProcessSetup in_home;
  in_home.working_directory = root;
  in_home.set_environment = {"PLACEDB_HOME=" + home};
  args = quiet;
  args.insert(args.end(), {"--data-dir", root + "/data"});
  EXPECT_EQ(run(args, in_home, &out, &err), 1);
  EXPECT_NE(err.find("vocabulary 'default' (var/vocabulary/default.pdbv) is in none of: " + home +
                     "/var/vocabulary/default.pdbv (PLACEDB_HOME)"),
            std::string::npos)
      << err;
  EXPECT_EQ(out.find("vocabulary 'default'"), std::string::npos) << out;
}

}  // namespace
}  // namespace placedb::server_testing
