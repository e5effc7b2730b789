// placedb-memory-flood: reproduces issue 19's memory finding against a real placedb-server and
// prints `name value unit` lines.
//
// It starts build/server/placedb-server (loopback port, temp data dir, the budget given), makes a
// large uncompressed PNG frame at run time from a real CamVid image scaled up (by default
// 1872x1404: 7.9 MB), then per round opens --streams concurrent Ingest streams (each on its own
// connection, as robots are) that send --frames frames each as fast as flow control allows,
// sampling the server's VmRSS every 100 ms during the flood and every second for --after-s seconds
// after it. Frames refused by the memory budget (RESOURCE_EXHAUSTED in the response) and streams
// refused at open are counted. Repeats --rounds times.
//
//   placedb-memory-flood [--server PATH] [--budget BYTES] [--streams 34] [--frames 4]
//                        [--rounds 3] [--after-s 60] [--server-env NAME=VALUE]...
//
// --server-env sets a variable for the server only (MALLOC_ARENA_MAX=2, LD_PRELOAD=..., ...).
#include <arpa/inet.h>
#include <grpcpp/grpcpp.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "proto/placedb.grpc.pb.h"

namespace {

namespace v1 = ::placedb::v1;
using placedb::bench::Print;
using Clock = std::chrono::steady_clock;

struct Options {
  std::string server = PLACEDB_SERVER_BINARY;
  std::string image = std::string(PLACEDB_SHARED_DIR) + "/data/camvid/images/0001TP_006690.jpg";
  uint64_t budget = 0;  // 0: the server's default
  int streams = 34;
  int frames = 4;
  int rounds = 3;
  int after_s = 60;
  int width = 1872, height = 1404;  // 7.9 MB as an uncompressed PNG
  std::vector<std::string> server_env;
};

double RssMib(pid_t pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;  // kB
  }
  return 0;
}

int FreePort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = 0;
  socklen_t length = sizeof address;
  if (bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0 ||
      getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) != 0) {
    close(fd);
    return 0;
  }
  const int port = ntohs(address.sin_port);
  close(fd);
  return port;
}

// One GET on loopback; the body, or "" on failure.
std::string HttpGet(int port, const std::string& path) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = htons(uint16_t(port));
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
    close(fd);
    return "";
  }
  const std::string request = "GET " + path + " HTTP/1.0\r\nHost: localhost\r\n\r\n";
  if (write(fd, request.data(), request.size()) != ssize_t(request.size())) {
    close(fd);
    return "";
  }
  std::string reply;
  char buffer[4096];
  for (ssize_t n; (n = read(fd, buffer, sizeof buffer)) > 0;) reply.append(buffer, size_t(n));
  close(fd);
  return reply;
}

// The value of a metric line starting with `series` (e.g. `placedb_memory_budget_bytes{kind=
// "in_use"}`), or -1.
double Metric(const std::string& text, const std::string& series) {
  size_t at = 0;
  while ((at = text.find(series, at)) != std::string::npos) {
    if (at == 0 || text[at - 1] == '\n') return std::atof(text.c_str() + at + series.size());
    at += series.size();
  }
  return -1;
}

struct RoundCounts {
  std::atomic<int> sent{0}, stored{0}, refused_budget{0}, other_errors{0}, streams_refused{0},
      streams_failed{0};
};

// A channel with its own connection (channels with equal arguments share one).
std::unique_ptr<v1::PlaceDb::Stub> Connect(const std::string& target, int id) {
  grpc::ChannelArguments args;
  args.SetMaxSendMessageSize(64 << 20);
  args.SetMaxReceiveMessageSize(64 << 20);
  args.SetInt("placedb.flood_connection", id);
  return v1::PlaceDb::NewStub(
      grpc::CreateCustomChannel(target, grpc::InsecureChannelCredentials(), args));
}

void RunStream(v1::PlaceDb::Stub* stub, const v1::Observation& frame, int frames,
               RoundCounts* counts) {
  grpc::ClientContext context;
  auto stream = stub->Ingest(&context);
  v1::IngestRequest header;
  header.mutable_header()->set_map("flood");
  std::thread writer([&] {
    if (!stream->Write(header)) return;
    v1::IngestRequest request;
    *request.mutable_observation() = frame;
    for (int i = 0; i < frames; ++i) {
      request.mutable_observation()->set_sequence(uint64_t(i));
      if (!stream->Write(request)) return;
      ++counts->sent;
    }
    stream->WritesDone();
  });
  v1::IngestResponse response;
  while (stream->Read(&response)) {
    if (response.has_error()) {
      if (response.error().code() == int(grpc::StatusCode::RESOURCE_EXHAUSTED)) {
        ++counts->refused_budget;
      } else {
        ++counts->other_errors;
      }
    } else if (response.stored()) {
      ++counts->stored;
    }
  }
  writer.join();
  const grpc::Status status = stream->Finish();
  if (status.error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED) {
    ++counts->streams_refused;
  } else if (!status.ok()) {
    ++counts->streams_failed;
    std::fprintf(stderr, "stream ended: %d %s\n", int(status.error_code()),
                 status.error_message().c_str());
  }
}

int Usage() {
  std::fprintf(stderr,
               "usage: placedb-memory-flood [--server PATH] [--image JPEG] [--budget BYTES] "
               "[--streams N] [--frames N] [--rounds N] [--after-s S] [--size WxH] "
               "[--server-env NAME=VALUE]...\n");
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (i + 1 >= argc) return Usage();
    const std::string value = argv[++i];
    if (arg == "--server") {
      o.server = value;
    } else if (arg == "--image") {
      o.image = value;
    } else if (arg == "--budget") {
      o.budget = std::stoull(value);
    } else if (arg == "--streams") {
      o.streams = std::stoi(value);
    } else if (arg == "--frames") {
      o.frames = std::stoi(value);
    } else if (arg == "--rounds") {
      o.rounds = std::stoi(value);
    } else if (arg == "--after-s") {
      o.after_s = std::stoi(value);
    } else if (arg == "--size") {
      if (std::sscanf(value.c_str(), "%dx%d", &o.width, &o.height) != 2) return Usage();
    } else if (arg == "--server-env") {
      o.server_env.push_back(value);
    } else {
      return Usage();
    }
  }

  // The frame: a real image scaled up, PNG without compression (the finding's ~7.9 MB frames).
  const cv::Mat source = cv::imread(o.image, cv::IMREAD_COLOR);
  if (source.empty()) {
    std::fprintf(stderr, "cannot read %s\n", o.image.c_str());
    return 2;
  }
  cv::Mat scaled;
  cv::resize(source, scaled, cv::Size(o.width, o.height), 0, 0, cv::INTER_LINEAR);
  std::vector<uint8_t> png;
  cv::imencode(".png", scaled, png, {cv::IMWRITE_PNG_COMPRESSION, 0});
  v1::Observation frame;
  frame.set_agent_id("flood");
  frame.mutable_encoded_image()->set_data(std::string(png.begin(), png.end()));
  Print("frame_png_bytes", double(png.size()), "bytes");
  Print("frame_pixels", double(o.width) * o.height, "pixels");

  // The server.
  const std::string data_dir =
      std::filesystem::temp_directory_path() / ("placedb-memory-flood-" + std::to_string(getpid()));
  std::filesystem::create_directories(data_dir);
  const int port = FreePort(), metrics_port = FreePort();
  const std::string listen = "127.0.0.1:" + std::to_string(port);
  std::vector<std::string> args = {o.server,
                                   "--listen",
                                   listen,
                                   "--metrics-listen",
                                   "127.0.0.1:" + std::to_string(metrics_port),
                                   "--console-listen",
                                   "off",
                                   "--data-dir",
                                   data_dir,
                                   "--vocabulary",
                                   "default=" + std::string(PLACEDB_DEFAULT_VOCABULARY),
                                   "--log-level",
                                   "error",
                                   "--max-message-bytes",
                                   std::to_string(16 << 20)};
  if (o.budget) {
    args.push_back("--memory-budget-bytes");
    args.push_back(std::to_string(o.budget));
  }
  const pid_t pid = fork();
  if (pid == 0) {
    for (const std::string& entry : o.server_env) putenv(const_cast<char*>(entry.c_str()));
    std::vector<char*> argv_child;
    for (std::string& arg : args) argv_child.push_back(arg.data());
    argv_child.push_back(nullptr);
    execv(o.server.c_str(), argv_child.data());
    std::perror("execv");
    std::_Exit(127);
  }
  auto stop_server = [&] {
    kill(pid, SIGTERM);
    int status = 0;
    waitpid(pid, &status, 0);
    std::error_code ignored;
    std::filesystem::remove_all(data_dir, ignored);
  };

  auto channel = grpc::CreateChannel(listen, grpc::InsecureChannelCredentials());
  if (!channel->WaitForConnected(std::chrono::system_clock::now() + std::chrono::seconds(60))) {
    std::fprintf(stderr, "the server did not come up on %s\n", listen.c_str());
    stop_server();
    return 1;
  }
  auto stub = v1::PlaceDb::NewStub(channel);
  {
    grpc::ClientContext context;
    v1::CreateMapRequest request;
    request.set_name("flood");
    v1::MapDescription response;
    const grpc::Status status = stub->CreateMap(&context, request, &response);
    if (!status.ok()) {
      std::fprintf(stderr, "CreateMap: %s\n", status.error_message().c_str());
      stop_server();
      return 1;
    }
  }
  std::this_thread::sleep_for(std::chrono::seconds(2));
  const double baseline = RssMib(pid);
  Print("baseline_rss", baseline, "MiB");
  const std::string metrics_path = "/metrics";
  const std::string first_scrape = HttpGet(metrics_port, metrics_path);
  Print("budget_limit",
        Metric(first_scrape, "placedb_memory_budget_bytes{kind=\"limit\"}") / 1048576, "MiB");
  Print("budget_fixed",
        Metric(first_scrape, "placedb_memory_budget_bytes{kind=\"fixed\"}") / 1048576, "MiB");

  for (int round = 1; round <= o.rounds; ++round) {
    const std::string name = "round" + std::to_string(round) + "_";
    RoundCounts counts;
    std::atomic<bool> flooding{true};
    double peak = 0, peak_budget = 0;
    std::thread sampler([&] {
      while (flooding) {
        peak = std::max(peak, RssMib(pid));
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
    });
    std::thread budget_sampler([&] {
      while (flooding) {
        peak_budget = std::max(peak_budget, Metric(HttpGet(metrics_port, metrics_path),
                                                   "placedb_memory_budget_bytes{kind=\"in_use\"}"));
        std::this_thread::sleep_for(std::chrono::milliseconds(500));
      }
    });
    const auto started = Clock::now();
    std::vector<std::thread> streams;
    for (int s = 0; s < o.streams; ++s) {
      streams.emplace_back(
          [&, s] { RunStream(Connect(listen, round * 1000 + s).get(), frame, o.frames, &counts); });
    }
    for (std::thread& t : streams) t.join();
    flooding = false;
    sampler.join();
    budget_sampler.join();
    Print(name + "flood_duration", std::chrono::duration<double>(Clock::now() - started).count(),
          "s");
    Print(name + "frames_sent", counts.sent, "frames");
    Print(name + "frames_stored", counts.stored, "frames");
    Print(name + "frames_refused_budget", counts.refused_budget, "frames");
    Print(name + "frames_other_errors", counts.other_errors, "frames");
    Print(name + "streams_refused", counts.streams_refused, "streams");
    Print(name + "streams_failed", counts.streams_failed, "streams");
    Print(name + "peak_rss", peak, "MiB");
    Print(name + "peak_budget_in_use", peak_budget / 1048576, "MiB");
    double last = 0;
    for (int second = 1; second <= o.after_s; ++second) {
      std::this_thread::sleep_for(std::chrono::seconds(1));
      last = RssMib(pid);
      if ((second == 5 || second == 15 || second == 30) && second < o.after_s) {
        Print(name + "rss_after_" + std::to_string(second) + "s", last, "MiB");
      }
    }
    Print(name + "rss_after_" + std::to_string(o.after_s) + "s", last, "MiB");
    {
      // What the stored places legitimately keep in memory (index, records): RSS after a round
      // may exceed the baseline by this much.
      grpc::ClientContext context;
      v1::GetMapRequest request;
      request.set_name("flood");
      v1::MapDescription map;
      if (stub->GetMap(&context, request, &map).ok()) {
        Print(name + "map_bytes_in_memory", double(map.stats().bytes_in_memory()) / 1048576, "MiB");
      }
    }
    Print(name + "budget_in_use_after",
          Metric(HttpGet(metrics_port, metrics_path),
                 "placedb_memory_budget_bytes{kind=\"in_use\"}") /
              1048576,
          "MiB");
  }
  stop_server();
  return 0;
}
