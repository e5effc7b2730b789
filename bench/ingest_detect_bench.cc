// placedb end-to-end ingest with server-side detection (issue 17): prints `name value unit` lines.
//
// Workload: 640x480 JPEG frames (quality 90) made at start from CamVid (every third frame, at
// most --source-frames, upscaled from 480x360) into a temporary folder; a real placedb-server
// (this build's, default worker threads = cores, OpenCV threads 1, YOLOX-Nano at 416) with one
// map created with detection on (box source server); placedb-load with --agents encoded-image
// Ingest streams, unpaced (as fast as the server takes them), for --seconds. Two server setups,
// alternating round by round (which goes first alternates too):
//  - baseline: detector.rectangular_letterbox false, detector.rewrite_graph false (the detector
//    as it was before issue 17: square 416x416 input, the ONNX graph as exported);
//  - change: the defaults (416x320 input for 4:3 frames, SiLU fused, Focus stem cut).
// Figures per setup, the median over --rounds:
//  - ingest_detect.<setup>.throughput: frames/s acknowledged;
//  - ingest_detect.<setup>.server_cpu_per_frame: the server process's user + system CPU time
//    (/proc/PID/stat) during the load, divided by the frames: what a frame costs on 2 cores;
//  - ingest_detect.<setup>.stage.<stage>: mean of each stage's time (ms) from the responses'
//    timings: wall time on a worker thread, equal to CPU time when the cores are not shared.
// The 1-minute load average before each run goes to a `#` line: the machine may be shared.
//
// Usage: placedb-bench-ingest-detect [--seconds S] [--rounds R] [--agents N] [--source-frames N]
//                                    [--models DIR] [--vocabulary FILE] [--dir DIR]
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/files.h"

namespace fs = std::filesystem;
using placedb::bench::Median;
using placedb::bench::Print;

namespace {

struct Options {
  double seconds = 20;
  int rounds = 2;
  int agents = 4;
  size_t source_frames = 120;
  std::string models = PLACEDB_MODELS_DIR;
  std::string vocabulary = PLACEDB_DEFAULT_VOCABULARY;
  std::string dir =
      fs::temp_directory_path() / ("placedb-bench-ingest-detect-" + std::to_string(getpid()));
};

std::string LoadAverage() {
  std::ifstream file("/proc/loadavg");
  std::string one, five, fifteen;
  file >> one >> five >> fifteen;
  return one + " " + five + " " + fifteen;
}

// User + system CPU seconds of process `pid` (fields 14 and 15 of /proc/PID/stat).
double CpuSeconds(pid_t pid) {
  std::ifstream file("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(file)), {});
  const size_t close = text.rfind(')');  // the command name may hold spaces
  if (close == std::string::npos) return 0;
  std::istringstream fields(text.substr(close + 2));
  std::string field;
  double user = 0, system = 0;
  for (int i = 3; i <= 15 && fields >> field; ++i) {
    if (i == 14) user = std::atof(field.c_str());
    if (i == 15) system = std::atof(field.c_str());
  }
  return (user + system) / double(sysconf(_SC_CLK_TCK));
}

pid_t Spawn(std::vector<std::string> args, const std::string& log) {
  std::fflush(stdout);  // or the child inherits, and prints again, what is still buffered
  const pid_t pid = fork();
  if (pid == 0) {
    if (!log.empty()) {
      if (std::FILE* out = std::freopen(log.c_str(), "w", stdout)) (void)out;
      if (std::FILE* err = std::freopen(log.c_str(), "a", stderr)) (void)err;
    }
    std::vector<char*> argv;
    for (std::string& arg : args) argv.push_back(arg.data());
    argv.push_back(nullptr);
    execv(argv[0], argv.data());
    std::perror("execv");
    std::_Exit(127);
  }
  return pid;
}

int Wait(pid_t pid) {
  int status = 0;
  waitpid(pid, &status, 0);
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128;
}

int Run(std::vector<std::string> args, const std::string& log) {
  return Wait(Spawn(args, log));
}

// 640x480 JPEGs from CamVid into `dir`; how many.
size_t MakeFrames(const std::string& shared, size_t count, const std::string& dir) {
  auto paths = placedb::ListImageFiles(shared + "/data/camvid/images");
  if (!paths.ok()) return 0;
  fs::create_directories(dir);
  size_t made = 0;
  for (size_t i = 0; i < paths->size() && made < count; i += 3) {
    const cv::Mat image = cv::imread((*paths)[i], cv::IMREAD_COLOR);
    if (image.empty()) continue;
    cv::Mat frame;
    cv::resize(image, frame, cv::Size(640, 480), 0, 0, cv::INTER_LINEAR);
    char name[32];
    std::snprintf(name, sizeof name, "/%04zu.jpg", made);
    if (cv::imwrite(dir + name, frame, {cv::IMWRITE_JPEG_QUALITY, 90})) ++made;
  }
  return made;
}

struct Setup {
  std::string name;
  bool rectangular_letterbox;
  bool rewrite_graph;
};

struct RunResult {
  bool ok = false;
  double throughput = 0, cpu_per_frame = 0;
  std::map<std::string, double> stage_ms;
};

RunResult RunSetup(const Options& o, const Setup& setup, const std::string& frames, int round) {
  RunResult result;
  const std::string base = o.dir + "/" + setup.name + "-" + std::to_string(round);
  const std::string config = base + ".yaml";
  {
    std::ofstream yaml(config);
    yaml << "detector:\n  model: " << o.models << "/yolox_nano.onnx\n  rectangular_letterbox: "
         << (setup.rectangular_letterbox ? "true" : "false")
         << "\n  rewrite_graph: " << (setup.rewrite_graph ? "true" : "false")
         << "\n  required: true\n";
  }
  // A port from the pid and round: two benchmark processes do not collide in practice.
  const std::string address =
      "127.0.0.1:" +
      std::to_string(20000 + (getpid() * 7 + round * 2 + setup.rewrite_graph) % 30000);
  const pid_t server =
      Spawn({PLACEDB_SERVER_BINARY, "--config", config, "--listen", address, "--metrics-listen",
             "off", "--console-listen", "off", "--data-dir", base + "-data", "--vocabulary",
             "default=" + o.vocabulary, "--log-level", "warn"},
            base + "-server.log");
  bool up = false;
  for (int attempt = 0; attempt < 100 && !up; ++attempt) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    up = Run({PLACEDB_CLI_BINARY, "--address", address, "health"}, base + "-health.log") == 0;
  }
  if (up &&
      Run({PLACEDB_CLI_BINARY, "--address", address, "maps", "create", "e2e", "--detection", "on"},
          base + "-create.log") == 0) {
    std::printf("# %s round %d: load average %s\n", setup.name.c_str(), round,
                LoadAverage().c_str());
    const double cpu_before = CpuSeconds(server);
    char seconds[32];
    std::snprintf(seconds, sizeof seconds, "%g", o.seconds);
    const int load =
        Run({PLACEDB_LOAD_BINARY, frames, "--address", address, "--map", "e2e", "--agents",
             std::to_string(o.agents), "--duration", seconds, "--json-out", base + ".json"},
            base + "-load.log");
    const double cpu = CpuSeconds(server) - cpu_before;
    std::ifstream file(base + ".json");
    const nlohmann::json report = nlohmann::json::parse(file, nullptr, /*allow_exceptions=*/false);
    if (load == 0 && report.is_object()) {
      const double frames_done = report.value("frames", 0.0);
      result.throughput = report.value("throughput_fps", 0.0);
      result.cpu_per_frame = frames_done > 0 ? cpu * 1000.0 / frames_done : 0;
      const auto& stages = report["rpc"]["ingest"]["stages_ms"];
      for (const auto& [stage, figures] : stages.items()) {
        result.stage_ms[stage] = figures.value("mean", 0.0);
      }
      result.ok = frames_done > 0;
    } else {
      std::fprintf(stderr, "placedb-load failed (exit %d): see %s-load.log\n", load, base.c_str());
    }
  } else {
    std::fprintf(stderr, "the server did not come up or refused the map: see %s-server.log\n",
                 base.c_str());
  }
  kill(server, SIGTERM);
  Wait(server);
  return result;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  std::string shared = PLACEDB_SHARED_DIR;
  if (const char* env = std::getenv("PLACEDB_SHARED_DIR")) shared = env;
  if (!fs::exists(o.models + "/yolox_nano.onnx")) o.models = shared + "/models";
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string arg = argv[i], value = argv[i + 1];
    if (arg == "--seconds") {
      o.seconds = std::max(1.0, std::atof(value.c_str()));
    } else if (arg == "--rounds") {
      o.rounds = std::max(1, std::atoi(value.c_str()));
    } else if (arg == "--agents") {
      o.agents = std::max(1, std::atoi(value.c_str()));
    } else if (arg == "--source-frames") {
      o.source_frames = size_t(std::max(1, std::atoi(value.c_str())));
    } else if (arg == "--models") {
      o.models = value;
    } else if (arg == "--vocabulary") {
      o.vocabulary = value;
    } else if (arg == "--dir") {
      o.dir = value + "/ingest-detect-" + std::to_string(getpid());
    } else {
      argc = -1;
      break;
    }
  }
  if (argc < 0 || argc % 2 == 0) {
    std::fprintf(stderr,
                 "usage: %s [--seconds S] [--rounds R] [--agents N] [--source-frames N] "
                 "[--models DIR] [--vocabulary FILE] [--dir DIR]\n",
                 argv[0]);
    return 2;
  }
  const std::string frames = o.dir + "/frames";
  const size_t made = MakeFrames(shared, o.source_frames, frames);
  if (made == 0) {
    std::fprintf(stderr, "no frames: need %s/data/camvid\n", shared.c_str());
    return 1;
  }
  std::printf(
      "# %zu JPEG frames 640x480 (q90) from CamVid; %d agents unpaced, %g s per run, %d "
      "round(s); server: %s, %u hardware threads\n",
      made, o.agents, o.seconds, o.rounds, PLACEDB_SERVER_BINARY,
      std::thread::hardware_concurrency());
  const Setup setups[2] = {{"baseline", false, false}, {"change", true, true}};
  std::map<std::string, std::vector<RunResult>> results;
  int status = 0;
  for (int round = 0; round < o.rounds; ++round) {
    for (int k = 0; k < 2; ++k) {
      const Setup& setup = setups[(k + round) % 2];
      RunResult r = RunSetup(o, setup, frames, round);
      if (!r.ok) status = 1;
      if (r.ok) results[setup.name].push_back(std::move(r));
    }
  }
  for (const Setup& setup : setups) {
    const auto& runs = results[setup.name];
    if (runs.empty()) continue;
    const std::string prefix = "ingest_detect." + setup.name;
    std::vector<double> fps, cpu;
    std::map<std::string, std::vector<double>> stages;
    for (const RunResult& r : runs) {
      fps.push_back(r.throughput);
      cpu.push_back(r.cpu_per_frame);
      for (const auto& [stage, ms] : r.stage_ms) stages[stage].push_back(ms);
    }
    Print(prefix + ".throughput", Median(fps), "frames/s");
    Print(prefix + ".server_cpu_per_frame", Median(cpu), "ms");
    for (const char* stage : {"queue", "decode", "detect", "extract", "refine", "filter",
                              "transform", "store", "total"}) {
      if (stages.count(stage)) Print(prefix + ".stage." + stage, Median(stages[stage]), "ms");
    }
  }
  std::error_code ignored;
  fs::remove_all(o.dir, ignored);
  return status;
}
