// placedb RGB-D benchmark: prints one `name value unit` line per figure (medians), with same-run
// baselines where they mean something. Everything goes through PlaceDatabase (core/
// place_database.h), the pipeline the server runs: Process(observation, FrameRole::kStream) ->
// AdvanceStream(&frame, agent) -> CloseLoop(frame, metadata) (store = null: Insert()).
//
// Workload (stated on stdout too):
//  1. The RGB-D path per frame on every real RGB-D frame available (rgbd-people 8, slambook2-rgbd
//     5, 640x480, with their 16-bit depth in millimetres), run as one stream of agent "bench",
//     several passes, through a SIFT map (feature_type kSift, the Debian SIFT vocabulary):
//     SIFT (1000) extraction, depth (decode to metres + Algorithm 1), DC/SC filter, float-
//     vocabulary transform, then CloseLoop: the Bayesian loop-closure update and the insert.
//     Stages are the frame's StageTimings; "update" is LoopClosureOutcome.update_ms, "store" is
//     the CloseLoop time minus the update (median over the frames stored, not merged by
//     rehearsal), "total" the wall time of the three calls. Invalid frames are counted only.
//     Baseline: the same frames, interleaved, through an ORB map (ORB 1000, the default
//     vocabulary).
//  2. The loop-closure step as the map grows, through a SIFT map with the loop-closure working
//     memory bounded (--wm places) and unbounded (up to --unbounded-max frames). Frames are
//     synthesised from real SIFT descriptors (Debian sample images, opencv-doc + darknet): each
//     frame takes a random base image, keeps a random 300 of its descriptors and adds Gaussian
//     noise (sigma 4 on the 0..255 SIFT scale) to every value, and is given to the map as
//     precomputed features (640x480, keypoints at random positions). The map's payloads go to a
//     bench PayloadStore that keeps BoW vectors and direct indexes but drops the descriptors
//     (see BowOnlyPayloadStore). Medians over the 200 frames before each mark: CloseLoop (the
//     whole loop-closure step incl. the insert), the detector's update alone, and Process
//     (validation + transform).
//
// Timings are wall-clock medians on whatever else the machine is running; compare figures of
// one run with each other rather than across runs.
//
// Usage: placedb-bench-rgbd [--frames 1000,10000,50000] [--wm 1000] [--passes 5]
//        [--unbounded-max 10000]
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "bench/bench_output.h"
#include "core/base/timing.h"
#include "core/features/sift_features.h"
#include "core/pipeline/place_database.h"
#include "core/vocabulary/any_vocabulary.h"
#include "core/vocabulary/float_vocabulary.h"
#include "core/vocabulary/vocabulary.h"
#include "tools/rgbd_data.h"

using namespace placedb;
using bench::Median;
using bench::Print;

namespace {

const char kAgent[] = "bench";

void PrintLoad(const char* when) {
  double load[3] = {0, 0, 0};
  if (getloadavg(load, 3) == 3) {
    std::printf("# load average %s: %.2f %.2f %.2f\n", when, load[0], load[1], load[2]);
    std::fflush(stdout);
  }
}

std::vector<size_t> ParseList(const std::string& text) {
  std::vector<size_t> out;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) out.push_back(std::stoul(item));
  return out;
}

// Stands in for a persistent map whose features stay on disk (as MapStore keeps them in
// RocksDB): in memory it keeps what loop closure reads back, each place's BoW vector (the
// long-term memory retrieves it from here) and its direct index, and drops the keypoints and
// descriptors. 50k frames x 300 x 512 B of SIFT descriptors would not fit in RAM. Verification
// is disabled in the growing-map database, so nothing ever reads the dropped features.
class BowOnlyPayloadStore final : public PayloadStore {
 public:
  Status Put(PlaceId id, std::shared_ptr<const PlacePayload> payload) override {
    auto slim = std::make_shared<PlacePayload>();
    slim->bow = payload->bow;
    slim->direct = payload->direct;
    return kept_.Put(id, std::move(slim));
  }
  Result<std::shared_ptr<const PlacePayload>> Get(PlaceId id) const override {
    return kept_.Get(id);
  }
  Status Erase(PlaceId id) override { return kept_.Erase(id); }
  size_t MemoryBytes() const override { return kept_.MemoryBytes(); }

 private:
  InMemoryPayloadStore kept_;
};

struct RgbdInput {
  std::string name;
  cv::Mat bgr;
  cv::Mat raw_depth;  // CV_16U millimetres
};

// Per-frame figures of one map over the RGB-D stream.
struct StreamSamples {
  std::vector<double> extract, depth, filter, transform, update, store, total;
  std::vector<double> features, kept;
  size_t invalid = 0;
  size_t merged = 0;
  size_t loops = 0;
};

Status RunStreamFrame(PlaceDatabase* db, const RgbdInput& input, uint64_t sequence,
                      StreamSamples* samples) {
  Observation observation;
  observation.image = input.bgr;
  observation.depth = DepthObservation{input.raw_depth, {}, {}};
  observation.metadata.agent_id = kAgent;
  observation.metadata.sequence = sequence;
  Stopwatch total;
  auto frame = db->Process(observation, FrameRole::kStream);
  if (!frame.ok()) return frame.status().WithContext(input.name);
  PLACEDB_RETURN_IF_ERROR(db->AdvanceStream(&*frame, kAgent).WithContext(input.name));
  if (!frame->valid) {
    // Not stored and not matched: counted, left out of the stage medians.
    ++samples->invalid;
    return Status::Ok();
  }
  Stopwatch close;
  auto outcome = db->CloseLoop(*frame, observation.metadata);
  if (!outcome.ok()) return outcome.status().WithContext(input.name);
  const double close_ms = close.ElapsedMs();
  samples->total.push_back(total.ElapsedMs());
  samples->extract.push_back(frame->timings.extract_ms);
  samples->depth.push_back(frame->timings.depth_ms);
  samples->filter.push_back(frame->timings.filter_ms);
  samples->transform.push_back(frame->timings.transform_ms);
  samples->update.push_back(outcome->update_ms);
  // Rehearsal merges a frame into the previous place without storing it: store figures are
  // of the stored frames only.
  if (!outcome->merged) samples->store.push_back(close_ms - outcome->update_ms);
  samples->features.push_back(double(frame->counts.total));
  samples->kept.push_back(double(frame->counts.static_));
  samples->merged += outcome->merged ? 1 : 0;
  samples->loops += outcome->loop ? 1 : 0;
  return Status::Ok();
}

void PrintStream(const std::string& prefix, const StreamSamples& s, const PlaceDatabase& db) {
  Print(prefix + "_total", Median(s.total), "ms");
  Print(prefix + "_extract", Median(s.extract), "ms");
  Print(prefix + "_depth", Median(s.depth), "ms");
  Print(prefix + "_filter", Median(s.filter), "ms");
  Print(prefix + "_transform", Median(s.transform), "ms");
  Print(prefix + "_loop_closure_update", Median(s.update), "ms");
  Print(prefix + "_store", Median(s.store), "ms");
  Print(prefix + "_features", Median(s.features), "features");
  Print(prefix + "_features_kept", Median(s.kept), "features");
  Print(prefix + "_invalid", double(s.invalid), "frames");
  Print(prefix + "_merged", double(s.merged), "frames");
  Print(prefix + "_loops_accepted", double(s.loops), "frames");
  Print(prefix + "_places", double(db.Stats().places), "places");
}

int RgbdPath(const std::shared_ptr<const FloatVocabulary>& sift_vocabulary,
             const std::shared_ptr<const Vocabulary>& orb_vocabulary, int passes) {
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
      "# RGB-D path: %zu real frames (rgbd-people, slambook2-rgbd) x %d passes, one stream "
      "(agent \"%s\"), PlaceDatabase Process(kStream) + AdvanceStream + CloseLoop (Insert); "
      "SIFT map, baseline ORB map on the same frames, interleaved\n",
      frames.size(), passes, kAgent);
  PrintLoad("before the RGB-D path");

  DatabaseConfig sift_config;
  sift_config.feature_type = FeatureType::kSift;
  auto sift_db = PlaceDatabase::Create(AnyVocabulary(sift_vocabulary), sift_config);
  if (!sift_db.ok()) {
    std::fprintf(stderr, "SIFT map: %s\n", sift_db.status().ToString().c_str());
    return 1;
  }
  std::unique_ptr<PlaceDatabase> orb_db;
  if (orb_vocabulary) {
    auto created = PlaceDatabase::Create(AnyVocabulary(orb_vocabulary), DatabaseConfig{});
    if (!created.ok()) {
      std::fprintf(stderr, "ORB map: %s\n", created.status().ToString().c_str());
      return 1;
    }
    orb_db = std::move(created).value();
  }

  StreamSamples sift, orb;
  uint64_t sequence = 0;
  for (int pass = 0; pass < passes; ++pass) {
    for (const auto& frame : frames) {
      ++sequence;
      if (Status s = RunStreamFrame(sift_db->get(), frame, sequence, &sift); !s.ok()) {
        std::fprintf(stderr, "SIFT map: %s\n", s.ToString().c_str());
        return 1;
      }
      if (orb_db) {
        if (Status s = RunStreamFrame(orb_db.get(), frame, sequence, &orb); !s.ok()) {
          std::fprintf(stderr, "ORB map: %s\n", s.ToString().c_str());
          return 1;
        }
      }
    }
  }
  PrintStream("rgbd_sift_frame", sift, **sift_db);
  if (orb_db) PrintStream("baseline_orb_frame", orb, *orb_db);
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

void GrowingMap(const std::shared_ptr<const FloatVocabulary>& vocabulary,
                const std::vector<size_t>& unsorted_marks, size_t wm_bound, size_t unbounded_max) {
  constexpr size_t kPerFrame = 300;
  constexpr int kWidth = 640, kHeight = 480;
  constexpr size_t kWindow = 200;
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
      "# growing map: SIFT PlaceDatabase, one stream; frames synthesised from %zu real SIFT sets "
      "(%zu random descriptors + N(0, 4) noise each, precomputed features %dx%d), SIFT vocabulary "
      "%u words, verification (and loop verification) disabled, payloads without descriptors; WM "
      "bound %zu places "
      "(STM 30); unbounded baseline up to %zu frames; medians over the %zu frames before each "
      "mark\n",
      sets.size(), kPerFrame, kWidth, kHeight, vocabulary->word_count(), wm_bound, unbounded_max,
      kWindow);
  for (bool bounded : {true, false}) {
    DatabaseConfig config;
    config.feature_type = FeatureType::kSift;
    config.verification.mode = VerificationMode::kDisabled;
    config.verify_loops = false;  // the payloads hold no descriptors to verify with
    config.loop_closure.max_working_memory = bounded ? wm_bound : 0;
    auto db = PlaceDatabase::Create(AnyVocabulary(vocabulary), config,
                                    std::make_shared<BowOnlyPayloadStore>());
    if (!db.ok()) {
      std::fprintf(stderr, "growing map: %s\n", db.status().ToString().c_str());
      return;
    }
    const std::string run = bounded ? "wm" + std::to_string(wm_bound) : "unbounded";
    PrintLoad(("before the " + run + " run").c_str());
    std::mt19937 rng(42);
    std::normal_distribution<float> noise(0.0f, 4.0f);
    Observation observation;
    observation.metadata.agent_id = kAgent;
    FloatFeatureSet features;
    features.image_width = kWidth;
    features.image_height = kHeight;
    features.keypoints.resize(kPerFrame);
    features.descriptors.resize(kPerFrame * kSiftDimensions);
    std::vector<double> window_close, window_update, window_process;
    const size_t limit = bounded ? last : std::min(last, unbounded_max);
    size_t next = 0;  // index of the next mark
    Stopwatch run_watch;
    for (size_t t = 1; t <= limit && next < marks.size(); ++t) {
      const auto& base = sets[rng() % sets.size()];
      const size_t count = base.size() / kSiftDimensions;
      for (size_t k = 0; k < kPerFrame; ++k) {
        Keypoint& kp = features.keypoints[k];
        kp.x = float(rng() % kWidth) + 0.5f;
        kp.y = float(rng() % kHeight) + 0.5f;
        kp.size = 10;
        kp.angle = 0;
        kp.octave = 1;
        const float* d = base.data() + (rng() % count) * kSiftDimensions;
        for (int j = 0; j < kSiftDimensions; ++j) {
          features.descriptors[k * kSiftDimensions + j] = std::max(0.0f, d[j] + noise(rng));
        }
      }
      observation.metadata.sequence = t;
      observation.features = features;

      Stopwatch process_watch;
      auto frame = (*db)->Process(observation, FrameRole::kStream);
      Status advanced = frame.ok() ? (*db)->AdvanceStream(&*frame, kAgent) : frame.status();
      const double process_ms = process_watch.ElapsedMs();
      if (!advanced.ok() || !frame->valid) {
        std::fprintf(stderr, "growing map frame %zu: %s\n", t,
                     advanced.ok() ? frame->rejection.c_str() : advanced.ToString().c_str());
        return;
      }
      Stopwatch close_watch;
      auto outcome = (*db)->CloseLoop(*frame, observation.metadata);
      const double close_ms = close_watch.ElapsedMs();
      if (!outcome.ok()) {
        std::fprintf(stderr, "growing map frame %zu: %s\n", t, outcome.status().ToString().c_str());
        return;
      }
      if (t + kWindow > marks[next]) {
        window_close.push_back(close_ms);
        window_update.push_back(outcome->update_ms);
        window_process.push_back(process_ms);
      }
      if (t == marks[next]) {
        const DatabaseStats stats = (*db)->Stats();
        const std::string tag = run + "_at_" + std::to_string(t / 1000) + "k";
        Print("loop_closure_step_" + tag, Median(window_close), "ms");
        Print("loop_closure_update_" + tag, Median(window_update), "ms");
        Print("process_" + tag, Median(window_process), "ms");
        Print("loop_closure_wm_places_" + tag, double(stats.loop_working_memory), "places");
        Print("loop_closure_ltm_places_" + tag, double(stats.loop_long_term), "places");
        Print("map_places_" + tag, double(stats.places), "places");
        Print("map_index_" + tag, double(stats.index_bytes) / 1e6, "MB");
        if (auto loop = (*db)->LoopStats(kAgent); loop.ok()) {
          Print("loop_closure_index_" + tag, double(loop->index_bytes) / 1e6, "MB");
        }
        Print("payload_store_" + tag, double(stats.payload_bytes) / 1e6, "MB");
        std::printf("# %s: %zu frames after %.1f s\n", run.c_str(), t,
                    run_watch.ElapsedMs() / 1000.0);
        std::fflush(stdout);
        window_close.clear();
        window_update.clear();
        window_process.clear();
        ++next;
      }
    }
  }
  PrintLoad("after the growing map");
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
  if (auto loaded = Vocabulary::Load(PLACEDB_DEFAULT_VOCABULARY); loaded.ok()) {
    orb_vocabulary = *loaded;
  } else {
    std::printf("# no ORB vocabulary at %s: ORB baseline skipped\n", PLACEDB_DEFAULT_VOCABULARY);
  }
  std::printf("# SIFT vocabulary %s: %u words\n", rgbd::SiftVocabularyPath().c_str(),
              (*sift_vocabulary)->word_count());
  if (orb_vocabulary) {
    std::printf("# ORB vocabulary %s: %u words\n", PLACEDB_DEFAULT_VOCABULARY,
                orb_vocabulary->word_count());
  }
  if (int rc = RgbdPath(*sift_vocabulary, orb_vocabulary, passes); rc != 0) return rc;
  GrowingMap(*sift_vocabulary, marks, wm_bound, unbounded_max);
  return 0;
}
