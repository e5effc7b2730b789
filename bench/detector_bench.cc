// placedb detector benchmark: prints one `name value unit` line per figure.
//
// Workload (stated on stdout too): CamVid frames (480x360), --frames of them spread evenly over
// the whole set (darknet's sample images when CamVid is missing), the default dynamic classes,
// confidence 0.2, letterbox. Every figure is a whole Detect() call: preprocessing, inference,
// decoding, NMS.
//  - latency: one stream, one call at a time, OpenCV threads = 1 and = 2; each frame's fastest of
//    --rounds passes, then the median (and p90) over the frames.
//  - throughput: 2 worker threads sharing one detector (two Nets in its pool), each call with
//    OpenCV threads = 1; frames/s over all frames, median (and best) of --rounds rounds.
// For YOLOX-Nano at 416 (the default: rectangular letterbox and fused SiLU; `416_square`: fused
// SiLU on the square input; `416_baseline`: the square input and the graph as exported, i.e. the
// detector before issue 17, as a same-run baseline) and Yolo-Fastest 1.1 XL at 416 and 320.
//
// Then YOLOX-Nano's network alone (cv::dnn::Net on one frame, OpenCV threads = 1, fastest pass
// after a warm-up), for the issue 17 profile:
//  - detector.yolox_nano.<variant>.forward: ms per forward, and .layer.<OpenCV layer type>: ms
//    per layer type from Net::getPerfProfile (of the fastest pass), for 416x416 with the graph
//    as exported (the baseline), 416x416 and 416x320 with SiLU fused (onnx_graph.h), and
//    416x320_rewritten: SiLU fused and the Focus stem cut (the detector's default; its blob
//    made by SpaceToDepthBlob, outside the timing like blobFromImage's);
//  - detector.yolox_nano.416x320_fused.batch<N>.per_frame: forward() of N frames in one blob, ms
//    per frame, N = 2, 4 (N = 1 is 416x320_fused.forward): what batched inference buys here.
// The variants run in turn within each of 3 x --rounds + 2 passes, fastest pass kept.
//
// Usage: placedb-bench-detector [--models DIR] [--frames N] [--rounds N] [--no-network]
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/core/utility.hpp>
#include <opencv2/dnn.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <thread>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/files.h"
#include "core/base/stats.h"
#include "core/detect/detector.h"
#include "core/detect/onnx_graph.h"

namespace fs = std::filesystem;
using namespace placedb;
using bench::NowMs;
using bench::Print;

namespace {

// The image files of `dir` in natural order; none when it is missing.
std::vector<std::string> ListImages(const std::string& dir) {
  auto images = ListImageFiles(dir);
  return images.ok() ? std::move(*images) : std::vector<std::string>();
}

std::vector<cv::Mat> LoadFrames(const std::string& shared, size_t count, std::string* source) {
  std::vector<std::string> paths = ListImages(shared + "/data/camvid/images");
  *source = "CamVid " + shared + "/data/camvid/images";
  if (paths.empty()) {
    paths = ListImages("/usr/share/darknet/data");
    *source = "darknet samples /usr/share/darknet/data";
  }
  std::vector<cv::Mat> frames;
  for (size_t i = 0; i < count && !paths.empty(); ++i) {
    cv::Mat image = cv::imread(paths[i * paths.size() / count % paths.size()], cv::IMREAD_COLOR);
    if (!image.empty()) frames.push_back(image);
  }
  return frames;
}

std::unique_ptr<Detector> Create(DetectorConfig config, int opencv_threads, int concurrent) {
  config.opencv_threads = opencv_threads;
  config.max_concurrent_calls = concurrent;
  auto created = CreateDetector(config);
  if (!created.ok()) {
    std::fprintf(stderr, "cannot create the detector: %s\n", created.status().ToString().c_str());
    std::exit(1);
  }
  return std::move(*created);
}

void Detect(const Detector& detector, const cv::Mat& frame) {
  auto boxes = detector.Detect(frame);
  if (!boxes.ok()) {
    std::fprintf(stderr, "Detect failed: %s\n", boxes.status().ToString().c_str());
    std::exit(1);
  }
}

// Single stream: each frame timed in `rounds` passes and its fastest pass kept (the machine may
// be shared: the fastest pass is the least disturbed one), then the median and p90 over frames.
void BenchLatency(const std::string& prefix, const DetectorConfig& config,
                  const std::vector<cv::Mat>& frames, int opencv_threads, int rounds) {
  auto detector = Create(config, opencv_threads, 1);
  for (size_t i = 0; i < std::min<size_t>(3, frames.size()); ++i) Detect(*detector, frames[i]);
  std::vector<double> best(frames.size(), 1e30);
  for (int round = 0; round < rounds; ++round) {
    for (size_t i = 0; i < frames.size(); ++i) {
      const double start = NowMs();
      Detect(*detector, frames[i]);
      best[i] = std::min(best[i], NowMs() - start);
    }
  }
  const std::string name = prefix + ".threads" + std::to_string(opencv_threads);
  Print(name + ".latency_median", Percentile(best, 0.5), "ms");
  Print(name + ".latency_p90", Percentile(best, 0.9), "ms");
}

// `workers` threads pulling frames from a shared counter; frames/s, median over rounds.
void BenchThroughput(const std::string& prefix, const DetectorConfig& config,
                     const std::vector<cv::Mat>& frames, int workers, int rounds) {
  auto detector = Create(config, 1, workers);
  std::vector<double> fps;
  for (int round = -1; round < rounds; ++round) {  // round -1 warms up every Net in the pool
    std::atomic<size_t> next{0};
    const double start = NowMs();
    std::vector<std::thread> threads;
    for (int w = 0; w < workers; ++w) {
      threads.emplace_back([&] {
        for (size_t i = next++; i < frames.size(); i = next++) Detect(*detector, frames[i]);
      });
    }
    for (auto& thread : threads) thread.join();
    if (round >= 0) fps.push_back(double(frames.size()) * 1000.0 / (NowMs() - start));
  }
  const std::string name = prefix + ".workers" + std::to_string(workers) + "_threads1";
  Print(name + ".throughput_median", Percentile(fps, 0.5), "frames/s");
  Print(name + ".throughput_best", *std::max_element(fps.begin(), fps.end()), "frames/s");
}

// One variant of YOLOX's network alone: a Net, its input blob (`batch` copies of the frame
// letterboxed into width x height), the fastest forward() seen and that pass's per-layer-type
// times (Net::getPerfProfile).
struct NetworkCase {
  std::string name;
  int batch;
  cv::dnn::Net net;
  cv::Mat blob;
  double best_ms = 1e30;
  std::map<std::string, double> layers_ms;
};

NetworkCase MakeNetworkCase(const std::string& name, const std::vector<unsigned char>& model,
                            const cv::Mat& frame, int width, int height, int batch,
                            const FocusStem* stem = nullptr) {
  NetworkCase c;
  c.name = name;
  c.batch = batch;
  c.net = cv::dnn::readNetFromONNX(model);
  c.net.setPreferableBackend(cv::dnn::DNN_BACKEND_OPENCV);
  c.net.setPreferableTarget(cv::dnn::DNN_TARGET_CPU);
  const double scale = std::min(double(width) / frame.cols, double(height) / frame.rows);
  cv::Mat input(height, width, CV_8UC3, cv::Scalar::all(114));
  const cv::Rect picture(0, 0, int(std::lround(frame.cols * scale)),
                         int(std::lround(frame.rows * scale)));
  cv::Mat roi = input(picture);
  cv::resize(frame, roi, picture.size());
  c.blob = stem ? SpaceToDepthBlob(input, *stem)
                : cv::dnn::blobFromImages(std::vector<cv::Mat>(size_t(batch), input), 1.0,
                                          cv::Size(), cv::Scalar(), false, false);
  return c;
}

// Every case once per pass, `passes` passes after a warm-up: under a varying load each case
// gets its share of the quiet moments.
void BenchNetworks(std::vector<NetworkCase>& cases, int passes) {
  for (int pass = -1; pass < passes; ++pass) {
    for (NetworkCase& c : cases) {
      std::vector<cv::Mat> outputs;
      const double start = NowMs();
      c.net.setInput(c.blob);
      c.net.forward(outputs, c.net.getUnconnectedOutLayersNames());
      const double ms = NowMs() - start;
      if (pass < 0 || ms >= c.best_ms) continue;
      c.best_ms = ms;
      std::vector<double> layer_ticks;
      c.net.getPerfProfile(layer_ticks);
      c.layers_ms.clear();
      for (size_t i = 0; i < layer_ticks.size(); ++i) {
        c.layers_ms[c.net.getLayer(int(i) + 1)->type] +=
            layer_ticks[i] * 1000.0 / cv::getTickFrequency();
      }
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  std::string shared = PLACEDB_SHARED_DIR;
  if (const char* env = std::getenv("PLACEDB_SHARED_DIR")) shared = env;
  std::string models = PLACEDB_MODELS_DIR;
  if (!fs::exists(models + "/yolox_nano.onnx")) models = shared + "/models";
  size_t frame_count = 40;
  int rounds = 3;
  bool network = true;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--no-network") {
      network = false;
    } else if ((arg == "--models" || arg == "--frames" || arg == "--rounds") && i + 1 < argc) {
      const std::string value = argv[++i];
      if (arg == "--models") models = value;
      if (arg == "--frames") frame_count = size_t(std::max(1, std::atoi(value.c_str())));
      if (arg == "--rounds") rounds = std::max(1, std::atoi(value.c_str()));
    } else {
      std::fprintf(stderr, "usage: %s [--models DIR] [--frames N] [--rounds N] [--no-network]\n",
                   argv[0]);
      return 2;
    }
  }

  std::string source;
  const std::vector<cv::Mat> frames = LoadFrames(shared, frame_count, &source);
  if (frames.empty()) {
    std::fprintf(stderr, "no frames: need %s/data/camvid or Debian's darknet package\n",
                 shared.c_str());
    return 1;
  }
  std::printf("# frames: %zu from %s (%dx%d)\n", frames.size(), source.c_str(), frames[0].cols,
              frames[0].rows);
  std::printf("# models: %s; hardware threads: %u; confidence 0.2, letterbox\n", models.c_str(),
              std::thread::hardware_concurrency());

  struct Case {
    const char* name;
    DetectorConfig config;
  };
  std::vector<Case> cases;
  cases.push_back({"detector.yolox_nano.416", YoloxNanoConfig(models)});
  cases.push_back({"detector.yolox_nano.416_square", YoloxNanoConfig(models)});
  cases.back().config.rectangular_letterbox = false;
  cases.push_back({"detector.yolox_nano.416_baseline", YoloxNanoConfig(models)});
  cases.back().config.rectangular_letterbox = false;
  cases.back().config.rewrite_graph = false;
  cases.push_back({"detector.yolo_fastest_xl.416", YoloFastestConfig(models)});
  cases.push_back({"detector.yolo_fastest_xl.320", YoloFastestConfig(models)});
  cases.back().config.input_size = 320;

  for (const Case& c : cases) {
    std::printf("# %s\n", Create(c.config, 0, 1)->Describe().c_str());
    BenchLatency(c.name, c.config, frames, 1, rounds);
    BenchLatency(c.name, c.config, frames, 2, rounds);
    BenchThroughput(c.name, c.config, frames, 2, rounds);
  }

  if (network) {
    cv::setNumThreads(1);
    std::ifstream file(models + "/yolox_nano.onnx", std::ios::binary);
    const std::vector<unsigned char> exported((std::istreambuf_iterator<char>(file)), {});
    int fused_pairs = 0;
    RegisterSiluLayer();
    const std::vector<unsigned char> fused = FuseSiluNodes(exported, &fused_pairs);
    FocusStem stem;
    bool cut = false;
    const std::vector<unsigned char> rewritten = CutFocusStem(fused, &stem, &cut);
    std::printf(
        "# YOLOX-Nano network alone, frame 0, OpenCV threads 1; %d SiLU pairs fused, "
        "Focus stem %s\n",
        fused_pairs, cut ? "cut" : "not found");
    const std::string p = "detector.yolox_nano.";
    std::vector<NetworkCase> cases;
    cases.push_back(MakeNetworkCase(p + "416x416_graph", exported, frames[0], 416, 416, 1));
    cases.push_back(MakeNetworkCase(p + "416x416_fused", fused, frames[0], 416, 416, 1));
    cases.push_back(MakeNetworkCase(p + "416x320_fused", fused, frames[0], 416, 320, 1));
    if (cut) {
      cases.push_back(
          MakeNetworkCase(p + "416x320_rewritten", rewritten, frames[0], 416, 320, 1, &stem));
    }
    for (int batch : {2, 4}) {
      cases.push_back(MakeNetworkCase(p + "416x320_fused.batch" + std::to_string(batch), fused,
                                      frames[0], 416, 320, batch));
    }
    BenchNetworks(cases, 3 * rounds + 2);
    for (const NetworkCase& c : cases) {
      if (c.batch > 1) {
        Print(c.name + ".per_frame", c.best_ms / c.batch, "ms");
        continue;
      }
      Print(c.name + ".forward", c.best_ms, "ms");
      for (const auto& [type, ms] : c.layers_ms) {
        if (ms >= 0.01) Print(c.name + ".layer." + type, ms, "ms");
      }
    }
  }
  return 0;
}
