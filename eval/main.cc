// placedb-eval: the paper's section V (Munoz & Dexter, Table III and Figs. 5-7) as a harness.
//
//   placedb-eval prepare camvid|camvid-stops|rtabmap|folder|revisits|revisits-hard ... --out DIR
//   placedb-eval run --dataset DIR --out RESULTS_DIR [--features 300,500,...] [--geom none,0,1,2,6]
//       [--boxes oracle|detector|none] [--masks oracle|none] [--confidence 0.2]
//       [--filter keypoint_in_box|exact_coverage --sensitivity 0.25] [--server ADDRESS
//       [--tls [--ca-cert PEM] [--cert PEM --key PEM]] [--token T]]
//
// See docs/evaluation.md for the dataset format, the metrics and the figures.
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <opencv2/core.hpp>

#include "client/connection.h"
#include "core/base/stats.h"
#include "core/detect/detector.h"
#include "core/vocabulary/vocabulary.h"
#include "eval/adapters.h"
#include "eval/dataset.h"
#include "eval/remote.h"
#include "eval/report.h"
#include "eval/revisits.h"
#include "eval/runner.h"
#include "tools/shared_data.h"

namespace fs = std::filesystem;
using namespace placedb;
using namespace placedb::eval;

namespace {

using placedb::data::SharedDir;

std::string DefaultModel() {
  const std::string installed = std::string(PLACEDB_MODELS_DIR) + "/yolox_nano.onnx";
  if (fs::exists(installed)) return installed;
  return SharedDir() + "/models/yolox_nano.onnx";
}

void Log(const std::string& line) {
  std::fprintf(stderr, "[placedb-eval] %s\n", line.c_str());
}

int Fail(const Status& status) {
  std::fprintf(stderr, "placedb-eval: %s\n", status.ToString().c_str());
  return 1;
}

int Save(Dataset dataset, const std::string& out, bool csv) {
  dataset.directory = out;
  const Status saved = csv ? SaveDatasetCsv(dataset) : SaveDataset(dataset);
  if (!saved.ok()) return Fail(saved);
  size_t truth = 0;
  for (const Entry& q : dataset.queries) truth += !q.ground_truth.empty();
  std::printf("%s: %zu database entries, %zu queries (%zu with ground truth) -> %s/%s\n",
              dataset.name.c_str(), dataset.database.size(), dataset.queries.size(), truth,
              out.c_str(), csv ? "*.csv" : "dataset.json");
  return 0;
}

// "0.1:0.4" or "0.25".
bool ParseRange(const std::string& text, double* lo, double* hi) {
  try {
    const size_t colon = text.find(':');
    *lo = std::stod(text.substr(0, colon));
    *hi = colon == std::string::npos ? *lo : std::stod(text.substr(colon + 1));
    return true;
  } catch (const std::exception&) {
    return false;
  }
}

// ---- prepare --------------------------------------------------------------------------------

// `prepare`: one subcommand per dataset kind, all writing to --out.
struct PrepareFlags {
  CLI::App* command = nullptr;
  std::string out;
  bool csv = false;
  CamVidAdjacencyOptions adjacency;
  CLI::App* camvid = nullptr;
  CamVidStopsOptions stops;
  bool no_distractors = false;
  CLI::App* camvid_stops = nullptr;
  RtabmapOptions rtabmap;
  CLI::App* rtabmap_command = nullptr;
  FolderOptions folder;
  CLI::App* folder_command = nullptr;
  // `revisits` and its hard preset `revisits-hard` take the same flags (different defaults).
  RevisitOptions revisit, hard = HardRevisitOptions();
  std::string coverage = "0.1:0.4";
  bool no_vtest = false;
  CLI::App* revisits = nullptr;
  CLI::App* revisits_hard = nullptr;
};

void AddOut(CLI::App* command, PrepareFlags* f) {
  command->add_option("--out", f->out, "dataset directory to write")->required();
  command->add_flag("--csv", f->csv, "write database.csv/queries.csv/... instead of dataset.json");
}

// The subcommands of the recorded datasets: camvid, camvid-stops, rtabmap, folder.
void RegisterRecordedDatasets(PrepareFlags* f) {
  CLI::App* prepare = f->command;
  f->adjacency.camvid_dir = SharedDir() + "/data/camvid";
  CLI::App* camvid = f->camvid =
      prepare->add_subcommand("camvid", "CamVid adjacent frames (1 s windows)");
  camvid->add_option("--camvid", f->adjacency.camvid_dir, "CamVid directory")
      ->capture_default_str();
  camvid->add_option("--sequences", f->adjacency.sequences, "only these sequences")->delimiter(',');
  camvid->add_option("--max-frames-per-sequence", f->adjacency.max_frames_per_sequence,
                     "only the first N frames of each sequence (0 = all)");
  camvid
      ->add_option("--window", f->adjacency.window_frames, "correct within this many video frames")
      ->capture_default_str();
  AddOut(camvid, f);

  f->stops.camvid_dir = SharedDir() + "/data/camvid";
  CLI::App* camvid_stops = f->camvid_stops =
      prepare->add_subcommand("camvid-stops", "CamVid vehicle-stop revisits (README ranges)");
  camvid_stops->add_option("--camvid", f->stops.camvid_dir, "CamVid directory")
      ->capture_default_str();
  camvid_stops
      ->add_option("--guard", f->stops.guard_frames,
                   "frames near a stop in neither visit are left out")
      ->capture_default_str();
  camvid_stops->add_flag("--no-distractors", f->no_distractors,
                         "database = the first visits only (no other CamVid frames)");
  AddOut(camvid_stops, f);

  f->rtabmap.directory = SharedDir() + "/data/rtabmap-loop";
  CLI::App* rtab = f->rtabmap_command =
      prepare->add_subcommand("rtabmap", "RTAB-Map loop with ground_truth.bmp");
  rtab->add_option("--rtabmap", f->rtabmap.directory, "RTAB-Map loop directory")
      ->capture_default_str();
  rtab->add_option("--database-last", f->rtabmap.database_last, "database = frames 1..N")
      ->capture_default_str();
  AddOut(rtab, f);

  CLI::App* folders = f->folder_command =
      prepare->add_subcommand("folder", "database/ and queries/ folders + CSV");
  folders->add_option("--database", f->folder.database_dir, "database images")->required();
  folders->add_option("--queries", f->folder.queries_dir, "query images")->required();
  folders->add_option("--ground-truth", f->folder.ground_truth_csv, "CSV query,database")
      ->required();
  folders->add_option("--database-masks", f->folder.database_masks_dir, "<stem>.png masks");
  folders->add_option("--query-masks", f->folder.queries_masks_dir, "<stem>.png masks");
  folders->add_option("--boxes", f->folder.boxes_csv,
                      "CSV image,class,confidence,x,y,width,height");
  AddOut(folders, f);
}

void AddRevisitFlags(CLI::App* command, RevisitOptions& o, PrepareFlags* f) {
  command->add_option("--camvid", o.camvid_dir, "CamVid directory")->capture_default_str();
  command->add_option("--places", o.places, "places")->capture_default_str();
  command->add_option("--visits", o.visits, "visits per place (visit 0 = database)")
      ->capture_default_str();
  command->add_option("--coverage", f->coverage, "dynamic coverage per visit, MIN:MAX or VALUE")
      ->capture_default_str();
  command->add_option("--seed", o.seed, "random seed")->capture_default_str();
  command->add_option("--viewpoint", o.viewpoint, "homography strength (0 = none)")
      ->capture_default_str();
  command->add_option("--photometric", o.photometric, "photometric strength (0 = none)")
      ->capture_default_str();
  command
      ->add_option("--max-background-coverage", o.max_background_coverage,
                   "backgrounds' own dynamic coverage at most")
      ->capture_default_str();
  command
      ->add_option("--min-separation", o.min_separation_frames,
                   "backgrounds of a sequence at least this many video frames apart")
      ->capture_default_str();
  command->add_option("--out", f->out, "dataset directory to write")->required();
  command->add_flag("--csv", f->csv, "write the CSV form instead of dataset.json");
}

// The synthetic datasets: revisits and revisits-hard.
void RegisterRevisits(PrepareFlags* f) {
  f->revisit.camvid_dir = f->hard.camvid_dir = SharedDir() + "/data/camvid";
  f->revisits =
      f->command->add_subcommand("revisits", "synthetic revisits with different dynamic objects");
  AddRevisitFlags(f->revisits, f->revisit, f);
  f->revisits_hard = f->command->add_subcommand(
      "revisits-hard",
      "harder revisits: backgrounds keep their own (unmarked) objects, random placement, people "
      "from vtest.avi, stronger viewpoint and light changes");
  AddRevisitFlags(f->revisits_hard, f->hard, f);
  f->revisits_hard
      ->add_option("--vtest", f->hard.video_people, "people video (Debian package opencv-doc)")
      ->capture_default_str();
  f->revisits_hard->add_flag("--no-vtest", f->no_vtest,
                             "paste CamVid objects only (no people from vtest.avi)");
}

void RegisterPrepare(CLI::App& app, PrepareFlags* f) {
  f->command = app.add_subcommand("prepare", "write a dataset in the harness format");
  f->command->require_subcommand(1);
  RegisterRecordedDatasets(f);
  RegisterRevisits(f);
}

// Builds the revisits, prints how close the coverage came and what was pasted, and saves them.
int PrepareRevisits(PrepareFlags& f) {
  RevisitOptions& o = f.revisits->parsed() ? f.revisit : f.hard;
  if (!ParseRange(f.coverage, &o.min_coverage, &o.max_coverage)) {
    return Fail(Status::InvalidArgument("--coverage: MIN:MAX or VALUE, got " + f.coverage));
  }
  if (f.no_vtest) o.video_people.clear();
  o.out_dir = f.out;
  auto built = BuildRevisits(o);
  if (!built.ok()) return Fail(built.status());
  double worst = 0, sum = 0;
  std::vector<double> measured;
  int objects = 0, video_objects = 0, background_objects = 0;
  for (const VisitInfo& v : built->visits) {
    worst = std::max(worst, std::abs(v.measured_coverage - v.requested_coverage));
    measured.push_back(v.measured_coverage);
    sum += v.measured_coverage;
    objects += v.objects;
    video_objects += v.video_objects;
    background_objects += v.background_objects;
  }
  std::sort(measured.begin(), measured.end());
  std::printf("revisits: largest |measured - requested| coverage %.4f\n", worst);
  std::printf(
      "revisits: %zu visits, coverage min %.3f p10 %.3f median %.3f mean %.3f p90 %.3f max "
      "%.3f; pasted objects %d (%d from %s); background's own objects %d (%s)\n",
      measured.size(), measured.front(), PercentileOfSorted(measured, 0.1),
      PercentileOfSorted(measured, 0.5), sum / double(measured.size()),
      PercentileOfSorted(measured, 0.9), measured.back(), objects, video_objects,
      o.video_people.empty() ? "no video" : fs::path(o.video_people).filename().c_str(),
      background_objects, o.mask_background_objects ? "marked dynamic" : "not marked");
  return Save(built->dataset, f.out, f.csv);
}

int Prepare(PrepareFlags& f) {
  if (f.camvid->parsed()) {
    auto dataset = PrepareCamVidAdjacency(f.adjacency);
    return dataset.ok() ? Save(*dataset, f.out, f.csv) : Fail(dataset.status());
  }
  if (f.camvid_stops->parsed()) {
    f.stops.distractors = !f.no_distractors;
    auto dataset = PrepareCamVidStops(f.stops);
    return dataset.ok() ? Save(*dataset, f.out, f.csv) : Fail(dataset.status());
  }
  if (f.rtabmap_command->parsed()) {
    auto dataset = PrepareRtabmap(f.rtabmap);
    return dataset.ok() ? Save(*dataset, f.out, f.csv) : Fail(dataset.status());
  }
  if (f.folder_command->parsed()) {
    auto dataset = PrepareFolder(f.folder);
    return dataset.ok() ? Save(*dataset, f.out, f.csv) : Fail(dataset.status());
  }
  if (f.revisits->parsed() || f.revisits_hard->parsed()) return PrepareRevisits(f);
  return 2;
}

// ---- run ------------------------------------------------------------------------------------

// `run`: the flags as given; ResolveRunOptions turns them into `options`.
struct RunFlags {
  CLI::App* command = nullptr;
  std::string dataset_dir, results_dir, vocabulary_path = PLACEDB_DEFAULT_VOCABULARY;
  std::vector<std::string> geoms = {"none", "0", "1", "2", "6"};
  std::string boxes = "oracle", masks = "none", filter = "keypoint_in_box", server, title;
  std::string model = DefaultModel(), detector_config, detector_backend = "yolox_onnx";
  std::string preprocessing = "letterbox", detections_cache, cache_dir;
  std::vector<std::string> class_confidence;  // NAME=SCORE
  bool combine_boxes_and_masks = false;
  std::string refinement = "shape", short_term = "on", static_budget = "on";
  double short_term_horizon_s = 60;
  RunOptions options;
  client::ConnectionOptions connection;  // --server's TLS files and token (address = --server)
  bool learn_vocabulary = false;
  LearningOptions learning;
  bool incremental_words = false;
  IncrementalWordsOptions incremental;
};

// The flags of the configuration grid, the filter and the detector.
void RegisterRunFilterFlags(CLI::App* run, RunFlags* f) {
  RunOptions& options = f->options;
  run->add_option("--features", options.features, "ORB budgets")
      ->delimiter(',')
      ->capture_default_str();
  run->add_option("--geom", f->geoms, "none, a direct-index level (Geo-l), or exhaustive")
      ->delimiter(',')
      ->capture_default_str();
  run->add_option("--boxes", f->boxes, "oracle | detector | none")->capture_default_str();
  run->add_option("--masks", f->masks, "oracle | none")->capture_default_str();
  run->add_option("--confidence", options.confidences, "detector confidence threshold(s)")
      ->delimiter(',')
      ->capture_default_str();
  run->add_option("--filter", f->filter, "keypoint_in_box | corner_distance | exact_coverage")
      ->capture_default_str();
  run->add_option("--sensitivity", options.sensitivity, "exact_coverage threshold")
      ->capture_default_str();
  run->add_option("--place-threshold", options.place_threshold, "valid iff |SC| > this")
      ->capture_default_str();
  run->add_option("--min-inliers", options.min_inliers, "verified iff inliers >= this")
      ->capture_default_str();
  run->add_option("--top-k", options.top_k, "matches per query (recall@k)")->capture_default_str();
  run->add_option("--vocabulary", f->vocabulary_path, "vocabulary (never trained on eval images)")
      ->capture_default_str();
  run->add_option("--model", f->model, "detector model (.onnx, or darknet .weights)")
      ->capture_default_str();
  run->add_option("--detector-backend", f->detector_backend, "yolox_onnx | darknet")
      ->capture_default_str();
  run->add_option("--detector-config", f->detector_config, "darknet .cfg");
  run->add_option("--preprocessing", f->preprocessing, "letterbox | centre_crop | stretch")
      ->capture_default_str();
  run->add_flag("--combine-boxes-and-masks", f->combine_boxes_and_masks,
                "with --masks oracle and an explicit --boxes: filter with both (merged)");
  run->add_option("--class-confidence", f->class_confidence,
                  "detector boxes: a class's own threshold, NAME=SCORE[,...] (e.g. bus=0.5)")
      ->delimiter(',');
  run->add_option("--min-box-area", options.detector.min_box_area,
                  "detector boxes below this share of the frame are dropped (0 = off)")
      ->capture_default_str();
  run->add_option("--large-box-area", options.detector.large_box_area,
                  "detector boxes above this share of the frame need --large-box-confidence")
      ->capture_default_str();
  run->add_option("--large-box-confidence", options.detector.large_box_confidence,
                  "the score a box above --large-box-area needs (0 = off)")
      ->capture_default_str();
  run->add_option("--detections-cache", f->detections_cache,
                  "detections JSON reused across runs (default: in --cache-dir)");
  run->add_option("--cache-dir", f->cache_dir,
                  "directory of the detections cache, keyed by image content (default: --out)");
}

void RegisterRun(CLI::App& app, RunFlags* f) {
  CLI::App* run = f->command =
      app.add_subcommand("run", "BoBW vs BoBW+DO over a configuration grid");
  run->add_option("--dataset", f->dataset_dir, "dataset directory (prepare's --out)")->required();
  run->add_option("--out", f->results_dir, "results directory")->required();
  RegisterRunFilterFlags(run, f);
  RunOptions& options = f->options;
  run->add_option("--refine-boxes", f->refinement, "BoBW+DO: none | shape | grabcut")
      ->capture_default_str();
  run->add_option("--short-term", f->short_term,
                  "BoBW+DO: the short-term tier of DC words: on | off")
      ->check(CLI::IsMember({"on", "off"}))
      ->capture_default_str();
  run->add_option("--static-budget", f->static_budget,
                  "BoBW+DO: spend the ORB budget on static pixels: on | off")
      ->check(CLI::IsMember({"on", "off"}))
      ->capture_default_str();
  run->add_option("--short-term-horizon", f->short_term_horizon_s, "short-term horizon, seconds")
      ->capture_default_str();
  run->add_option("--short-term-weight", options.short_term_config.weight,
                  "weight of the DC-word similarity")
      ->capture_default_str();
  run->add_option("--rerank", options.rerank,
                  "verify the best N candidates and re-rank them by inliers (0 = best only)")
      ->capture_default_str();
  run->add_flag("--legacy-verifier", options.legacy_verifier,
                "verify with the verifier before issue 31 (scalar matching, OpenCV FM_RANSAC), "
                "to compare the default with it; in-process only");
  run->add_option("--threads", options.threads, "worker threads")->capture_default_str();
  run->add_flag("--learn-vocabulary", f->learn_vocabulary,
                "each database learns its vocabulary from its own stored SC descriptors (never "
                "the queries) and is rebuilt with it (issue 29); in-process only");
  run->add_option("--learned-depth", f->learning.depth,
                  "--learn-vocabulary: tree depth L (0 = from the amount of data)");
  run->add_option("--learned-branching", f->learning.branching,
                  "--learn-vocabulary: branching k (0 = from the amount of data)");
  run->add_option("--learn-sample", f->learning.max_sample_descriptors,
                  "--learn-vocabulary: at most this many descriptors sampled (0 = default)");
  run->add_flag("--incremental-words", f->incremental_words,
                "instead of a vocabulary, each database grows its own binary words as places are "
                "added (iBoW-LCD style, issue 29); with --geom none, in-process only");
  run->add_option("--incremental-ratio", f->incremental.ratio,
                  "--incremental-words: ratio test of the two nearest words");
  run->add_option("--incremental-max-distance", f->incremental.max_distance,
                  "--incremental-words: a match is at most this many bits away");
  run->add_option("--incremental-bucket-levels", f->incremental.bucket_levels,
                  "--incremental-words: depth of the fixed vocabulary's search buckets");
  run->add_flag("--incremental-merge-and", f->incremental.merge_and,
                "--incremental-words: a merged word becomes the AND of its descriptors");
  run->add_option("--server", f->server, "run against a live placedb-server at ADDRESS");
  // The CLI's connection flags (docs/cli.md), for --server.
  run->add_flag("--tls", f->connection.tls, "--server: connect with TLS (TLS 1.2+)");
  run->add_option("--ca-cert", f->connection.ca_cert, "--server: PEM root certificates for --tls")
      ->check(CLI::ExistingFile);
  run->add_option("--cert", f->connection.cert,
                  "--server: PEM client certificate for mutual TLS (with --key)")
      ->check(CLI::ExistingFile);
  run->add_option("--key", f->connection.key, "--server: the client certificate's PEM key")
      ->check(CLI::ExistingFile);
  run->add_option("--token", f->connection.token,
                  "--server: sent as 'authorization: Bearer TOKEN' (prefer PLACEDB_TOKEN)")
      ->envname("PLACEDB_TOKEN");
  run->add_option("--title", f->title, "report title");
}

// Which boxes and masks filter: oracle masks and boxes are merged by the filter, never by
// accident. `--masks oracle` alone means masks only; with an explicit `--boxes` too, the merge
// must be asked for.
Status ResolveDynamicInputs(RunFlags& f) {
  RunOptions& options = f.options;
  auto box_input = ParseBoxInput(f.boxes);
  if (!box_input.ok()) return box_input.status();
  options.boxes = *box_input;
  auto mask_input = ParseMaskInput(f.masks);
  if (!mask_input.ok()) return mask_input.status();
  options.masks = *mask_input;
  const bool boxes_given = f.command->count("--boxes") > 0;
  if (options.masks == MaskInput::kOracle) {
    if (!boxes_given) {
      options.boxes = BoxInput::kNone;
    } else if (options.boxes != BoxInput::kNone && !f.combine_boxes_and_masks) {
      return Status::InvalidArgument(
          "--masks oracle with --boxes " + f.boxes +
          ": the filter would merge the boxes with the masks; pass --combine-boxes-and-masks "
          "to mean that, or leave out --boxes (masks only)");
    }
  } else if (f.combine_boxes_and_masks) {
    Log("warning: --combine-boxes-and-masks ignored: no --masks oracle");
  }
  return Status::Ok();
}

// Options this run ignores: say so (they are not recorded in run.json either).
void WarnIgnoredFlags(const RunFlags& f) {
  const RunOptions& options = f.options;
  if (f.command->count("--sensitivity") > 0 && options.filter != FilterMethod::kExactCoverage) {
    Log("warning: --sensitivity ignored: it is the exact_coverage threshold, and the filter is " +
        std::string(FilterMethodName(options.filter)));
  }
  if (options.boxes != BoxInput::kDetector) {
    if (f.command->count("--confidence") > 0) {
      Log("warning: --confidence ignored: it thresholds detector boxes, and --boxes is " +
          std::string(options.boxes == BoxInput::kOracle ? "oracle" : "none"));
    }
    for (const char* flag : {"--model", "--detector-backend", "--detector-config",
                             "--preprocessing", "--detections-cache", "--cache-dir"}) {
      if (f.command->count(flag) > 0) {
        Log(std::string("warning: ") + flag + " ignored: no detector boxes (--boxes detector)");
      }
    }
  }
}

// The detector and its cache, for --boxes detector.
Status ResolveDetector(RunFlags& f) {
  RunOptions& options = f.options;
  auto backend = ParseDetectorBackend(f.detector_backend);
  if (!backend.ok()) return backend.status();
  auto pre = ParsePreprocessing(f.preprocessing);
  if (!pre.ok()) return pre.status();
  options.detector.backend = *backend;
  options.detector.model_path = f.model;
  options.detector.config_path = f.detector_config;
  options.detector.preprocessing = *pre;
  options.detector.opencv_threads = 0;  // set by Run for the whole process
  for (const std::string& entry : f.class_confidence) {
    const auto eq = entry.find('=');
    float score = 0;
    try {
      size_t used = 0;
      score = eq == std::string::npos ? 0 : std::stof(entry.substr(eq + 1), &used);
      if (eq != std::string::npos && eq + 1 + used != entry.size()) score = -1;
    } catch (const std::exception&) {
      score = -1;
    }
    if (eq == std::string::npos || eq == 0 || score < 0) {
      return Status::InvalidArgument("--class-confidence: '" + entry + "' is not NAME=SCORE");
    }
    options.detector.class_confidence[entry.substr(0, eq)] = score;
  }
  PLACEDB_RETURN_IF_ERROR(ValidateDetectorConfig(options.detector).WithContext("detector"));
  if (f.detections_cache.empty()) {
    // Entries are keyed by image content, so one cache directory can serve every dataset.
    const std::string name =
        "detections_" + fs::path(f.model).stem().string() + "_" + f.preprocessing + ".json";
    f.detections_cache = (f.cache_dir.empty() ? f.results_dir : f.cache_dir) + "/" + name;
  }
  options.detections_cache = f.detections_cache;
  std::error_code ec;
  fs::create_directories(fs::path(f.detections_cache).parent_path(), ec);
  return Status::Ok();
}

Status ResolveRunOptions(RunFlags& f) {
  RunOptions& options = f.options;
  options.geoms.clear();
  for (const std::string& g : f.geoms) {
    auto geom = ParseGeom(g);
    if (!geom.ok()) return geom.status();
    if (std::find(options.geoms.begin(), options.geoms.end(), *geom) == options.geoms.end()) {
      options.geoms.push_back(*geom);
    }
  }
  PLACEDB_RETURN_IF_ERROR(ResolveDynamicInputs(f));
  auto method = ParseFilterMethod(f.filter);
  if (!method.ok()) return method.status();
  options.filter = *method;
  WarnIgnoredFlags(f);
  auto refine = ParseBoxRefinement(f.refinement);
  if (!refine.ok()) return refine.status();
  options.refinement = *refine;
  options.short_term = f.short_term == "on";
  options.static_budget = f.static_budget == "on";
  options.short_term_config.horizon_ns = int64_t(f.short_term_horizon_s * 1e9);
  if (options.boxes == BoxInput::kDetector) PLACEDB_RETURN_IF_ERROR(ResolveDetector(f));
  options.log = Log;
  return Status::Ok();
}

int Run(RunFlags& f) {
  auto dataset = LoadDataset(f.dataset_dir);
  if (!dataset.ok()) return Fail(dataset.status());
  const Status resolved = ResolveRunOptions(f);
  if (!resolved.ok()) return Fail(resolved);
  const RunOptions& options = f.options;
  // Frames are processed in parallel by the harness: one OpenCV thread per worker.
  cv::setNumThreads(1);

  auto vocabulary = Vocabulary::Load(f.vocabulary_path);
  if (!vocabulary.ok()) return Fail(vocabulary.status().WithContext(f.vocabulary_path));
  std::unique_ptr<Backend> backend;
  if (f.incremental_words &&
      (f.learn_vocabulary || !f.server.empty() || options.geoms != std::vector<int>{kNoGeom})) {
    return Fail(Status::InvalidArgument(
        "--incremental-words: in-process, with --geom none and without --learn-vocabulary"));
  }
  if (f.learn_vocabulary && !f.server.empty()) {
    return Fail(Status::InvalidArgument("--learn-vocabulary: in-process only, not with --server"));
  }
  if (f.learn_vocabulary) {
    f.learning.threads = options.threads;
    const Status valid = ValidateLearningOptions(f.learning);
    if (!valid.ok()) return Fail(valid.WithContext("--learn-vocabulary"));
  }
  if (f.server.empty()) {
    backend = MakeInProcessBackend(
        *vocabulary, options.threads, f.learn_vocabulary ? std::optional(f.learning) : std::nullopt,
        f.incremental_words ? std::optional(f.incremental) : std::nullopt);
  } else {
    client::ConnectionOptions connection = f.connection;
    connection.address = f.server;
    auto remote = MakeServerBackend(std::move(connection), *vocabulary, Log);
    if (!remote.ok()) return Fail(remote.status());
    backend = std::move(remote).value();
  }
  Log("dataset " + dataset->name + ": " + std::to_string(dataset->database.size()) +
      " database entries, " + std::to_string(dataset->queries.size()) + " queries; backend " +
      backend->Name());
  auto results = RunEvaluation(*dataset, options, *backend);
  if (!results.ok()) return Fail(results.status());
  std::string title = f.title;
  if (title.empty()) {
    title = "placedb-eval: " + dataset->name + " (" + results->dynamic_source + ")";
  }
  const Status written = WriteReport(*results, *dataset, f.results_dir, title);
  if (!written.ok()) return Fail(written);
  std::cout << MarkdownReport(*results, title);
  Log("wrote " + f.results_dir +
      "/{results.csv,queries.csv,table3.md,run.json,fig5_accuracy_vs_coverage.png,"
      "fig6_database_size.png,fig7_latency.png}");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"placedb-eval: reproduce Munoz & Dexter section V (Table III, Figs. 5-7)"};
  app.require_subcommand(1);
  PrepareFlags prepare;
  RegisterPrepare(app, &prepare);
  RunFlags run;
  RegisterRun(app, &run);
  CLI11_PARSE(app, argc, argv);
  return prepare.command->parsed() ? Prepare(prepare) : Run(run);
}
