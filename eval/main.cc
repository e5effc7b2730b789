// placedb-eval: the paper's section V (Munoz & Dexter, Table III and Figs. 5-7) as a harness.
//
//   placedb-eval prepare camvid|camvid-stops|rtabmap|folder|revisits|revisits-hard ... --out DIR
//   placedb-eval run --dataset DIR --out RESULTS_DIR [--features 300,500,...] [--geom none,0,1,2,6]
//       [--boxes oracle|detector|none] [--masks oracle|none] [--confidence 0.2]
//       [--filter keypoint_in_box|exact_coverage --sensitivity 0.25] [--server ADDRESS]
//
// See docs/evaluation.md for the dataset format, the metrics and the figures.
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <opencv2/core.hpp>

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

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"placedb-eval: reproduce Munoz & Dexter section V (Table III, Figs. 5-7)"};
  app.require_subcommand(1);

  // ---- prepare ------------------------------------------------------------------------------
  CLI::App* prepare = app.add_subcommand("prepare", "write a dataset in the harness format");
  prepare->require_subcommand(1);
  std::string out;
  bool csv = false;
  auto add_out = [&](CLI::App* command) {
    command->add_option("--out", out, "dataset directory to write")->required();
    command->add_flag("--csv", csv, "write database.csv/queries.csv/... instead of dataset.json");
  };

  CamVidAdjacencyOptions adjacency;
  adjacency.camvid_dir = SharedDir() + "/data/camvid";
  CLI::App* camvid = prepare->add_subcommand("camvid", "CamVid adjacent frames (1 s windows)");
  camvid->add_option("--camvid", adjacency.camvid_dir, "CamVid directory")->capture_default_str();
  camvid->add_option("--sequences", adjacency.sequences, "only these sequences")->delimiter(',');
  camvid->add_option("--max-frames-per-sequence", adjacency.max_frames_per_sequence,
                     "only the first N frames of each sequence (0 = all)");
  camvid->add_option("--window", adjacency.window_frames, "correct within this many video frames")
      ->capture_default_str();
  add_out(camvid);

  CamVidStopsOptions stops;
  stops.camvid_dir = SharedDir() + "/data/camvid";
  bool no_distractors = false;
  CLI::App* camvid_stops =
      prepare->add_subcommand("camvid-stops", "CamVid vehicle-stop revisits (README ranges)");
  camvid_stops->add_option("--camvid", stops.camvid_dir, "CamVid directory")->capture_default_str();
  camvid_stops
      ->add_option("--guard", stops.guard_frames,
                   "frames near a stop in neither visit are left out")
      ->capture_default_str();
  camvid_stops->add_flag("--no-distractors", no_distractors,
                         "database = the first visits only (no other CamVid frames)");
  add_out(camvid_stops);

  RtabmapOptions rtabmap;
  rtabmap.directory = SharedDir() + "/data/rtabmap-loop";
  CLI::App* rtab = prepare->add_subcommand("rtabmap", "RTAB-Map loop with ground_truth.bmp");
  rtab->add_option("--rtabmap", rtabmap.directory, "RTAB-Map loop directory")
      ->capture_default_str();
  rtab->add_option("--database-last", rtabmap.database_last, "database = frames 1..N")
      ->capture_default_str();
  add_out(rtab);

  FolderOptions folder;
  CLI::App* folders = prepare->add_subcommand("folder", "database/ and queries/ folders + CSV");
  folders->add_option("--database", folder.database_dir, "database images")->required();
  folders->add_option("--queries", folder.queries_dir, "query images")->required();
  folders->add_option("--ground-truth", folder.ground_truth_csv, "CSV query,database")->required();
  folders->add_option("--database-masks", folder.database_masks_dir, "<stem>.png masks");
  folders->add_option("--query-masks", folder.queries_masks_dir, "<stem>.png masks");
  folders->add_option("--boxes", folder.boxes_csv, "CSV image,class,confidence,x,y,width,height");
  add_out(folders);

  // `revisits` and its hard preset `revisits-hard` take the same flags (different defaults).
  RevisitOptions revisit, hard = HardRevisitOptions();
  revisit.camvid_dir = hard.camvid_dir = SharedDir() + "/data/camvid";
  std::string coverage = "0.1:0.4";
  auto add_revisit_flags = [&](CLI::App* command, RevisitOptions& o) {
    command->add_option("--camvid", o.camvid_dir, "CamVid directory")->capture_default_str();
    command->add_option("--places", o.places, "places")->capture_default_str();
    command->add_option("--visits", o.visits, "visits per place (visit 0 = database)")
        ->capture_default_str();
    command->add_option("--coverage", coverage, "dynamic coverage per visit, MIN:MAX or VALUE")
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
    command->add_option("--out", out, "dataset directory to write")->required();
    command->add_flag("--csv", csv, "write the CSV form instead of dataset.json");
  };
  CLI::App* revisits =
      prepare->add_subcommand("revisits", "synthetic revisits with different dynamic objects");
  add_revisit_flags(revisits, revisit);
  bool no_vtest = false;
  CLI::App* revisits_hard = prepare->add_subcommand(
      "revisits-hard",
      "harder revisits: backgrounds keep their own (unmarked) objects, random placement, people "
      "from vtest.avi, stronger viewpoint and light changes");
  add_revisit_flags(revisits_hard, hard);
  revisits_hard
      ->add_option("--vtest", hard.video_people, "people video (Debian package opencv-doc)")
      ->capture_default_str();
  revisits_hard->add_flag("--no-vtest", no_vtest,
                          "paste CamVid objects only (no people from vtest.avi)");

  // ---- run ----------------------------------------------------------------------------------
  CLI::App* run = app.add_subcommand("run", "BoBW vs BoBW+DO over a configuration grid");
  std::string dataset_dir, results_dir, vocabulary_path = PLACEDB_DEFAULT_VOCABULARY;
  std::vector<std::string> geoms = {"none", "0", "1", "2", "6"};
  std::string boxes = "oracle", masks = "none", filter = "keypoint_in_box", server, title;
  std::string model = DefaultModel(), detector_config, detector_backend = "yolox_onnx";
  std::string preprocessing = "letterbox", detections_cache;
  RunOptions options;
  run->add_option("--dataset", dataset_dir, "dataset directory (prepare's --out)")->required();
  run->add_option("--out", results_dir, "results directory")->required();
  run->add_option("--features", options.features, "ORB budgets")
      ->delimiter(',')
      ->capture_default_str();
  run->add_option("--geom", geoms, "none, a direct-index level (Geo-l), or exhaustive")
      ->delimiter(',')
      ->capture_default_str();
  run->add_option("--boxes", boxes, "oracle | detector | none")->capture_default_str();
  run->add_option("--masks", masks, "oracle | none")->capture_default_str();
  run->add_option("--confidence", options.confidences, "detector confidence threshold(s)")
      ->delimiter(',')
      ->capture_default_str();
  run->add_option("--filter", filter, "keypoint_in_box | corner_distance | exact_coverage")
      ->capture_default_str();
  run->add_option("--sensitivity", options.sensitivity, "exact_coverage threshold")
      ->capture_default_str();
  run->add_option("--place-threshold", options.place_threshold, "valid iff |SC| > this")
      ->capture_default_str();
  run->add_option("--min-inliers", options.min_inliers, "verified iff inliers >= this")
      ->capture_default_str();
  run->add_option("--top-k", options.top_k, "matches per query (recall@k)")->capture_default_str();
  run->add_option("--vocabulary", vocabulary_path, "vocabulary (never trained on eval images)")
      ->capture_default_str();
  run->add_option("--model", model, "detector model (.onnx, or darknet .weights)")
      ->capture_default_str();
  run->add_option("--detector-backend", detector_backend, "yolox_onnx | darknet")
      ->capture_default_str();
  run->add_option("--detector-config", detector_config, "darknet .cfg");
  run->add_option("--preprocessing", preprocessing, "letterbox | centre_crop | stretch")
      ->capture_default_str();
  std::string cache_dir;
  bool combine_boxes_and_masks = false;
  run->add_flag("--combine-boxes-and-masks", combine_boxes_and_masks,
                "with --masks oracle and an explicit --boxes: filter with both (merged)");
  run->add_option("--detections-cache", detections_cache,
                  "detections JSON reused across runs (default: in --cache-dir)");
  run->add_option("--cache-dir", cache_dir,
                  "directory of the detections cache, keyed by image content (default: --out)");
  std::string refinement = "shape", short_term = "on", static_budget = "on";
  double short_term_horizon_s = 60;
  run->add_option("--refine-boxes", refinement, "BoBW+DO: none | shape | grabcut")
      ->capture_default_str();
  run->add_option("--short-term", short_term, "BoBW+DO: the short-term tier of DC words: on | off")
      ->check(CLI::IsMember({"on", "off"}))
      ->capture_default_str();
  run->add_option("--static-budget", static_budget,
                  "BoBW+DO: spend the ORB budget on static pixels: on | off")
      ->check(CLI::IsMember({"on", "off"}))
      ->capture_default_str();
  run->add_option("--short-term-horizon", short_term_horizon_s, "short-term horizon, seconds")
      ->capture_default_str();
  run->add_option("--short-term-weight", options.short_term_config.weight,
                  "weight of the DC-word similarity")
      ->capture_default_str();
  run->add_option("--rerank", options.rerank,
                  "verify the best N candidates and re-rank them by inliers (0 = best only)")
      ->capture_default_str();
  run->add_option("--threads", options.threads, "worker threads")->capture_default_str();
  run->add_option("--server", server, "run against a live placedb-server at ADDRESS");
  run->add_option("--title", title, "report title");

  CLI11_PARSE(app, argc, argv);

  if (prepare->parsed()) {
    if (camvid->parsed()) {
      auto dataset = PrepareCamVidAdjacency(adjacency);
      return dataset.ok() ? Save(*dataset, out, csv) : Fail(dataset.status());
    }
    if (camvid_stops->parsed()) {
      stops.distractors = !no_distractors;
      auto dataset = PrepareCamVidStops(stops);
      return dataset.ok() ? Save(*dataset, out, csv) : Fail(dataset.status());
    }
    if (rtab->parsed()) {
      auto dataset = PrepareRtabmap(rtabmap);
      return dataset.ok() ? Save(*dataset, out, csv) : Fail(dataset.status());
    }
    if (folders->parsed()) {
      auto dataset = PrepareFolder(folder);
      return dataset.ok() ? Save(*dataset, out, csv) : Fail(dataset.status());
    }
    if (revisits->parsed() || revisits_hard->parsed()) {
      RevisitOptions& o = revisits->parsed() ? revisit : hard;
      if (!ParseRange(coverage, &o.min_coverage, &o.max_coverage)) {
        return Fail(Status::InvalidArgument("--coverage: MIN:MAX or VALUE, got " + coverage));
      }
      if (no_vtest) o.video_people.clear();
      o.out_dir = out;
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
      auto at = [&](double q) { return measured[size_t(q * double(measured.size() - 1) + 0.5)]; };
      std::printf("revisits: largest |measured - requested| coverage %.4f\n", worst);
      std::printf(
          "revisits: %zu visits, coverage min %.3f p10 %.3f median %.3f mean %.3f p90 %.3f max "
          "%.3f; pasted objects %d (%d from %s); background's own objects %d (%s)\n",
          measured.size(), measured.front(), at(0.1), at(0.5), sum / double(measured.size()),
          at(0.9), measured.back(), objects, video_objects,
          o.video_people.empty() ? "no video" : fs::path(o.video_people).filename().c_str(),
          background_objects, o.mask_background_objects ? "marked dynamic" : "not marked");
      return Save(built->dataset, out, csv);
    }
    return 2;
  }

  // run
  auto dataset = LoadDataset(dataset_dir);
  if (!dataset.ok()) return Fail(dataset.status());
  options.geoms.clear();
  for (const std::string& g : geoms) {
    auto geom = ParseGeom(g);
    if (!geom.ok()) return Fail(geom.status());
    if (std::find(options.geoms.begin(), options.geoms.end(), *geom) == options.geoms.end()) {
      options.geoms.push_back(*geom);
    }
  }
  auto box_input = ParseBoxInput(boxes);
  if (!box_input.ok()) return Fail(box_input.status());
  options.boxes = *box_input;
  auto mask_input = ParseMaskInput(masks);
  if (!mask_input.ok()) return Fail(mask_input.status());
  options.masks = *mask_input;
  // Oracle masks and boxes are merged by the filter: never by accident. `--masks oracle` alone
  // means masks only; with an explicit `--boxes` too, the merge must be asked for.
  const bool boxes_given = run->count("--boxes") > 0;
  if (options.masks == MaskInput::kOracle) {
    if (!boxes_given) {
      options.boxes = BoxInput::kNone;
    } else if (options.boxes != BoxInput::kNone && !combine_boxes_and_masks) {
      return Fail(Status::InvalidArgument(
          "--masks oracle with --boxes " + boxes +
          ": the filter would merge the boxes with the masks; pass --combine-boxes-and-masks "
          "to mean that, or leave out --boxes (masks only)"));
    }
  } else if (combine_boxes_and_masks) {
    Log("warning: --combine-boxes-and-masks ignored: no --masks oracle");
  }
  auto method = ParseFilterMethod(filter);
  if (!method.ok()) return Fail(method.status());
  options.filter = *method;
  // Options this run ignores: say so, and do not record them (run.json).
  if (run->count("--sensitivity") > 0 && options.filter != FilterMethod::kExactCoverage) {
    Log("warning: --sensitivity ignored: it is the exact_coverage threshold, and the filter is " +
        std::string(FilterMethodName(options.filter)));
  }
  if (options.boxes != BoxInput::kDetector) {
    if (run->count("--confidence") > 0) {
      Log("warning: --confidence ignored: it thresholds detector boxes, and --boxes is " +
          std::string(options.boxes == BoxInput::kOracle ? "oracle" : "none"));
    }
    for (const char* flag : {"--model", "--detector-backend", "--detector-config",
                             "--preprocessing", "--detections-cache", "--cache-dir"}) {
      if (run->count(flag) > 0) {
        Log(std::string("warning: ") + flag + " ignored: no detector boxes (--boxes detector)");
      }
    }
  }
  auto refine = ParseBoxRefinement(refinement);
  if (!refine.ok()) return Fail(refine.status());
  options.refinement = *refine;
  options.short_term = short_term == "on";
  options.static_budget = static_budget == "on";
  options.short_term_config.horizon_ns = int64_t(short_term_horizon_s * 1e9);
  if (options.boxes == BoxInput::kDetector) {
    auto backend = ParseDetectorBackend(detector_backend);
    if (!backend.ok()) return Fail(backend.status());
    auto pre = ParsePreprocessing(preprocessing);
    if (!pre.ok()) return Fail(pre.status());
    options.detector.backend = *backend;
    options.detector.model_path = model;
    options.detector.config_path = detector_config;
    options.detector.preprocessing = *pre;
    options.detector.opencv_threads = 0;  // set below for the whole process
    if (detections_cache.empty()) {
      // Entries are keyed by image content, so one cache directory can serve every dataset.
      const std::string name =
          "detections_" + fs::path(model).stem().string() + "_" + preprocessing + ".json";
      detections_cache = (cache_dir.empty() ? results_dir : cache_dir) + "/" + name;
    }
    options.detections_cache = detections_cache;
    std::error_code ec;
    fs::create_directories(fs::path(detections_cache).parent_path(), ec);
  }
  options.log = Log;
  // Frames are processed in parallel by the harness: one OpenCV thread per worker.
  cv::setNumThreads(1);

  auto vocabulary = Vocabulary::Load(vocabulary_path);
  if (!vocabulary.ok()) return Fail(vocabulary.status().WithContext(vocabulary_path));
  std::unique_ptr<Backend> backend;
  if (server.empty()) {
    backend = MakeInProcessBackend(*vocabulary, options.threads);
  } else {
    auto remote = MakeServerBackend(server, *vocabulary, Log);
    if (!remote.ok()) return Fail(remote.status());
    backend = std::move(remote).value();
  }
  Log("dataset " + dataset->name + ": " + std::to_string(dataset->database.size()) +
      " database entries, " + std::to_string(dataset->queries.size()) + " queries; backend " +
      backend->Name());
  auto results = RunEvaluation(*dataset, options, *backend);
  if (!results.ok()) return Fail(results.status());
  if (title.empty())
    title = "placedb-eval: " + dataset->name + " (" + results->dynamic_source + ")";
  const Status written = WriteReport(*results, *dataset, results_dir, title);
  if (!written.ok()) return Fail(written);
  std::cout << MarkdownReport(*results, title);
  Log("wrote " + results_dir +
      "/{results.csv,queries.csv,table3.md,run.json,fig5_accuracy_vs_coverage.png,"
      "fig6_database_size.png,fig7_latency.png}");
  return 0;
}
