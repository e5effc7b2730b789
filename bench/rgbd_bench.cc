// placedb RGB-D benchmark: prints one `name value unit` line per figure (medians), with same-run
// baselines where they mean something.
//
// Workload (stated on stdout too):
//  1. The RGB-D path per frame on every real RGB-D frame available (rgbd-people 8, slambook2-rgbd
//     5, 640x480), run as one stream, several passes: depth decode to metres + Algorithm 1
//     (state update, feature depths, band split) + SIFT (1000) + float-vocabulary transform +
//     loop-closure update. Baseline: the same frame through ORB (1000) + the binary vocabulary.
//  2. Loop-closure update time as the map grows, bounded working memory vs unbounded. Frames are
//     synthesised from real SIFT descriptors (Debian sample images, opencv-doc + darknet): each
//     frame takes a random base image, keeps a random 300 of its descriptors and adds Gaussian
//     noise (sigma 4 on the 0..255 SIFT scale) to every value, then goes through the float
//     vocabulary. Medians over the 200 updates before each mark.
//
// Usage: placedb-bench-rgbd [--frames 1000,10000,50000] [--wm 1000] [--passes 5]
//        [--unbounded-max 10000]
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "core/depth_filter.h"
#include "core/features.h"
#include "core/float_vocabulary.h"
#include "core/loop_closure.h"
#include "core/sift_features.h"
#include "core/timing.h"
#include "core/vocabulary.h"
#include "rgbd/rgbd_support.h"

using namespace placedb;

namespace {

double Median(std::vector<double> values) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  return values[values.size() / 2];
}

void Print(const std::string& name, double value, const char* unit) {
  std::printf("%s %.4g %s\n", name.c_str(), value, unit);
  std::fflush(stdout);
}

std::vector<size_t> ParseList(const std::string& text) {
  std::vector<size_t> out;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) out.push_back(std::stoul(item));
  return out;
}

struct RgbdInput {
  std::string name;
  cv::Mat bgr;
  cv::Mat raw_depth;  // CV_16U millimetres
};

int RgbdPath(const FloatVocabulary& sift_vocabulary, const Vocabulary* orb_vocabulary, int passes) {
  std::vector<RgbdInput> frames;
  for (const auto& list : {rgbd::RgbdPeopleFrames(), rgbd::SlambookFrames()}) {
    for (const auto& f : list) {
      RgbdInput in{f.name, cv::imread(f.image_path, cv::IMREAD_COLOR),
                   cv::imread(f.depth_path, cv::IMREAD_ANYDEPTH)};
      if (!in.bgr.empty() && !in.raw_depth.empty()) frames.push_back(std::move(in));
    }
  }
  if (frames.empty()) {
    std::fprintf(stderr, "no RGB-D frames under %s/data\n", rgbd::SharedDir().c_str());
    return 1;
  }
  std::printf(
      "# RGB-D path: %zu real frames (rgbd-people, slambook2-rgbd) x %d passes, one "
      "stream\n",
      frames.size(), passes);
  auto filter = DepthStreamFilter::Create(DepthFilterConfig{});
  auto detector = LoopClosureDetector::Create(sift_vocabulary.word_count(), LoopClosureConfig{});
  if (!filter.ok() || !detector.ok()) return 1;
  std::vector<double> depth_ms, sift_ms, transform_ms, loop_ms, total_ms, orb_ms, orb_transform_ms;
  std::vector<double> features, kept;
  uint64_t tag = 0;
  for (int pass = 0; pass < passes; ++pass) {
    for (const auto& frame : frames) {
      Stopwatch total;
      Stopwatch lap;
      auto sift = ExtractSift(frame.bgr, SiftConfig{});
      if (!sift.ok()) return 1;
      const double t_sift = lap.Lap();
      auto split =
          filter->Process(frame.raw_depth, frame.bgr.cols, frame.bgr.rows, sift->keypoints);
      if (!split.ok()) {
        std::fprintf(stderr, "%s\n", split.status().ToString().c_str());
        return 1;
      }
      const FloatFeatureSet static_set = SelectFloatFeatures(*sift, split->kept);
      const double t_depth = lap.Lap();
      BowVector bow;
      sift_vocabulary.Transform(static_set.descriptors, &bow, nullptr, 0);
      const double t_transform = lap.Lap();
      auto update = (*detector)->Update(bow, tag++);
      if (!update.ok()) return 1;
      const double t_loop = lap.Lap();
      total_ms.push_back(total.ElapsedMs());
      sift_ms.push_back(t_sift);
      depth_ms.push_back(t_depth);
      transform_ms.push_back(t_transform);
      loop_ms.push_back(t_loop);
      features.push_back(double(sift->size()));
      kept.push_back(double(static_set.size()));
      if (orb_vocabulary != nullptr) {
        Stopwatch orb_watch;
        auto orb = ExtractOrb(frame.bgr, OrbConfig{});
        if (!orb.ok()) return 1;
        orb_ms.push_back(orb_watch.Lap());
        BowVector orb_bow;
        orb_vocabulary->Transform(orb->descriptors, &orb_bow, nullptr, 0);
        orb_transform_ms.push_back(orb_watch.Lap());
      }
    }
  }
  Print("rgbd_frame_total", Median(total_ms), "ms");
  Print("rgbd_frame_sift_extract", Median(sift_ms), "ms");
  Print("rgbd_frame_depth_filter", Median(depth_ms), "ms");
  Print("rgbd_frame_sift_transform", Median(transform_ms), "ms");
  Print("rgbd_frame_loop_closure_update", Median(loop_ms), "ms");
  Print("rgbd_frame_sift_features", Median(features), "features");
  Print("rgbd_frame_sift_features_kept", Median(kept), "features");
  if (!orb_ms.empty()) {
    Print("baseline_frame_orb_extract", Median(orb_ms), "ms");
    Print("baseline_frame_orb_transform", Median(orb_transform_ms), "ms");
  }
  return 0;
}

// Real SIFT descriptor sets of the Debian sample images.
std::vector<std::vector<float>> DebianSiftSets() {
  std::vector<std::vector<float>> sets;
  for (const auto& path : rgbd::DebianSampleImages()) {
    cv::Mat gray = cv::imread(path, cv::IMREAD_GRAYSCALE);
    if (gray.empty()) continue;
    auto f = ExtractSift(gray, SiftConfig{});
    if (f.ok() && f->size() >= 300) sets.push_back(std::move(f->descriptors));
  }
  return sets;
}

void GrowingMap(const FloatVocabulary& vocabulary, const std::vector<size_t>& unsorted_marks,
                size_t wm_bound, size_t unbounded_max) {
  const auto sets = DebianSiftSets();
  if (sets.empty()) {
    std::fprintf(stderr, "no Debian sample images (install opencv-doc and darknet)\n");
    return;
  }
  std::vector<size_t> marks = unsorted_marks;
  std::sort(marks.begin(), marks.end());
  if (marks.empty()) return;
  const size_t last = marks.back();
  std::printf(
      "# growing map: frames synthesised from %zu real SIFT sets (300 random descriptors "
      "+ N(0, 4) noise each), SIFT vocabulary %u words; WM bound %zu places (STM 30); "
      "unbounded baseline up to %zu frames\n",
      sets.size(), vocabulary.word_count(), wm_bound, unbounded_max);
  for (bool bounded : {true, false}) {
    LoopClosureConfig config;
    if (bounded) config.max_working_memory = wm_bound;
    auto detector = LoopClosureDetector::Create(vocabulary.word_count(), config);
    if (!detector.ok()) return;
    std::mt19937 rng(42);
    std::normal_distribution<float> noise(0.0f, 4.0f);
    std::vector<double> window_total, window_search;
    std::vector<float> frame(300 * kSiftDimensions);
    const size_t limit = bounded ? last : std::min(last, unbounded_max);
    size_t next = 0;  // index of the next mark
    for (size_t t = 1; t <= limit && next < marks.size(); ++t) {
      const auto& base = sets[rng() % sets.size()];
      const size_t count = base.size() / kSiftDimensions;
      for (size_t k = 0; k < 300; ++k) {
        const float* d = base.data() + (rng() % count) * kSiftDimensions;
        for (int j = 0; j < kSiftDimensions; ++j) {
          frame[k * kSiftDimensions + j] = std::max(0.0f, d[j] + noise(rng));
        }
      }
      BowVector bow;
      vocabulary.Transform(frame, &bow, nullptr, 0);
      auto update = (*detector)->Update(bow, t);
      if (!update.ok()) return;
      if (t + 200 > marks[next]) {
        window_total.push_back(update->total_ms);
        window_search.push_back(update->search_ms);
      }
      if (t == marks[next]) {
        const auto stats = (*detector)->Stats();
        const std::string tag = (bounded ? "wm" + std::to_string(wm_bound) : "unbounded") + "_at_" +
                                std::to_string(t / 1000) + "k";
        Print("loop_closure_update_" + tag, Median(window_total), "ms");
        Print("loop_closure_search_" + tag, Median(window_search), "ms");
        Print("loop_closure_wm_places_" + tag, double(stats.working), "places");
        Print("loop_closure_index_" + tag, double(stats.index_bytes) / 1e6, "MB");
        window_total.clear();
        window_search.clear();
        ++next;
      }
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<size_t> marks = {1000, 10000, 50000};
  size_t wm_bound = 1000;
  size_t unbounded_max = 10000;
  int passes = 5;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", arg.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (arg == "--frames") {
      marks = ParseList(value());
    } else if (arg == "--wm") {
      wm_bound = std::stoul(value());
    } else if (arg == "--passes") {
      passes = std::stoi(value());
    } else if (arg == "--unbounded-max") {
      unbounded_max = std::stoul(value());
    } else {
      std::fprintf(stderr,
                   "usage: placedb-bench-rgbd [--frames 1000,10000,50000] [--wm 1000] "
                   "[--passes 5] [--unbounded-max 10000]\n");
      return 2;
    }
  }
  auto sift_vocabulary = rgbd::LoadOrTrainSiftVocabulary(rgbd::SiftVocabularyPath());
  if (!sift_vocabulary.ok()) {
    std::fprintf(stderr, "SIFT vocabulary: %s\n", sift_vocabulary.status().ToString().c_str());
    return 1;
  }
  std::shared_ptr<const Vocabulary> orb_vocabulary;
  if (auto loaded = Vocabulary::Load(PLACEDB_DEFAULT_VOCABULARY_RGBD); loaded.ok()) {
    orb_vocabulary = *loaded;
  } else {
    std::printf("# no ORB vocabulary at %s: ORB baseline skipped\n",
                PLACEDB_DEFAULT_VOCABULARY_RGBD);
  }
  std::printf("# SIFT vocabulary %s: %u words\n", rgbd::SiftVocabularyPath().c_str(),
              (*sift_vocabulary)->word_count());
  if (int rc = RgbdPath(**sift_vocabulary, orb_vocabulary.get(), passes); rc != 0) return rc;
  GrowingMap(**sift_vocabulary, marks, wm_bound, unbounded_max);
  return 0;
}
