#include "eval/runner.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "core/base/parallel.h"
#include "core/base/stats.h"
#include "core/base/text.h"
#include "core/base/thread_annotations.h"
#include "core/base/timing.h"
#include "core/features/orb_features.h"
#include "core/storage/codec.h"

namespace fs = std::filesystem;
using json = nlohmann::json;

namespace placedb::eval {

namespace {

void Log(const RunOptions& options, const std::string& line) {
  if (options.log) options.log(line);
}

// Oracle boxes of an entry that has a mask but no boxes: the mask's connected components
// (class "person": any dynamic class would do, the filter only asks whether it is dynamic).
std::vector<DynamicBox> BoxesFromMask(const cv::Mat& mask) {
  std::vector<DynamicBox> boxes;
  cv::Mat components, stats, centroids;
  const int count = cv::connectedComponentsWithStats(mask, components, stats, centroids, 8);
  for (int c = 1; c < count; ++c) {
    if (stats.at<int>(c, cv::CC_STAT_AREA) < 20) continue;
    DynamicBox box;
    box.class_id = 0;
    box.rect = cv::Rect2f(
        float(stats.at<int>(c, cv::CC_STAT_LEFT)), float(stats.at<int>(c, cv::CC_STAT_TOP)),
        float(stats.at<int>(c, cv::CC_STAT_WIDTH)), float(stats.at<int>(c, cv::CC_STAT_HEIGHT)));
    boxes.push_back(box);
  }
  return boxes;
}

// ---- Detection cache ----------------------------------------------------------------------

struct Detection {
  std::vector<DynamicBox> boxes;
  double ms = 0;
};

std::string DetectorKey(const DetectorConfig& config) {
  return std::string(DetectorBackendName(config.backend)) + "|" +
         fs::path(config.model_path).filename().string() + "|" + std::to_string(config.input_size) +
         "|" + PreprocessingName(config.preprocessing) + "|" +
         std::to_string(config.nms_iou_threshold);
}

// Cache entries are keyed by the image file's content, not its path: the same bytes anywhere
// (another dataset directory, a copy) hit the same entry, and a changed file misses.
constexpr const char* kCacheKeys = "fnv1a64-of-file-bytes";

// 64-bit FNV-1a of the file's bytes as 16 hex digits.
Result<std::string> ContentKey(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return Status::IoError("cannot read " + path);
  uint64_t hash = 0xcbf29ce484222325ull;
  char buffer[1 << 16];
  while (in.read(buffer, sizeof(buffer)) || in.gcount() > 0) {
    const std::streamsize n = in.gcount();
    for (std::streamsize i = 0; i < n; ++i) {
      hash ^= uint64_t(static_cast<unsigned char>(buffer[i]));
      hash *= 0x100000001b3ull;
    }
  }
  if (in.bad()) return Status::IoError("cannot read " + path);
  char hex[17];
  std::snprintf(hex, sizeof(hex), "%016llx", static_cast<unsigned long long>(hash));
  return std::string(hex);
}

// The cached detections, when they were made by the same detector at a threshold at or below
// `config.confidence_threshold`; that threshold is then lowered to the cache's so new detections
// join it consistently. A cache keyed otherwise (older files keyed by path) is ignored.
std::map<std::string, Detection> ReadDetectionCache(const std::string& path,
                                                    DetectorConfig* config) {
  std::map<std::string, Detection> cache;
  std::ifstream in(path);
  if (!in) return cache;
  try {
    json j = json::parse(in);
    if (j.value("detector", std::string()) != DetectorKey(*config)) return cache;
    if (j.value("keys", std::string()) != kCacheKeys) return cache;
    const float cached = j.value("min_confidence", 1.0f);
    if (cached > config->confidence_threshold + 1e-6f) return cache;
    config->confidence_threshold = cached;
    for (const auto& [image, value] : j["images"].items()) {
      Detection detection;
      detection.ms = value.value("ms", 0.0);
      for (const json& b : value["boxes"]) {
        DynamicBox box;
        box.class_id = b[0].get<int>();
        box.confidence = b[1].get<float>();
        box.rect =
            cv::Rect2f(b[2].get<float>(), b[3].get<float>(), b[4].get<float>(), b[5].get<float>());
        detection.boxes.push_back(box);
      }
      cache[image] = std::move(detection);
    }
  } catch (const json::exception&) {
    cache.clear();  // a damaged cache is rebuilt
  }
  return cache;
}

Status WriteDetectionCache(const std::string& path, const DetectorConfig& config,
                           const std::map<std::string, Detection>& cache) {
  json j;
  j["detector"] = DetectorKey(config);
  j["keys"] = kCacheKeys;
  j["min_confidence"] = config.confidence_threshold;
  j["images"] = json::object();
  for (const auto& [image, detection] : cache) {
    json boxes = json::array();
    for (const DynamicBox& b : detection.boxes) {
      boxes.push_back({b.class_id, b.confidence, b.rect.x, b.rect.y, b.rect.width, b.rect.height});
    }
    j["images"][image] = {{"ms", detection.ms}, {"boxes", boxes}};
  }
  const std::string temp = path + ".tmp";
  {
    std::ofstream out(temp, std::ios::trunc);
    if (!out) return Status::IoError("cannot write " + temp);
    out << j.dump() << "\n";
    if (!out.flush()) return Status::IoError("cannot write " + temp);
  }
  std::error_code ec;
  fs::rename(temp, path, ec);
  if (ec) return Status::IoError("cannot rename " + temp + ": " + ec.message());
  return Status::Ok();
}

// Detections of every entry (database then queries), at the lowest requested confidence.
Status Detect(const Dataset& dataset, const RunOptions& options, EvalInputs* inputs) {
  DetectorConfig config = options.detector;
  config.confidence_threshold =
      *std::min_element(options.confidences.begin(), options.confidences.end());
  // The cache holds the boxes before the box rules (one cache serves every rule); the rules are
  // applied below, with the runs' lowest threshold for the classes without their own.
  DetectorConfig rules = config;
  for (const auto& [name, value] : config.class_confidence) {
    config.confidence_threshold = std::min(config.confidence_threshold, value);
  }
  config.class_confidence.clear();
  config.min_box_area = 0;
  config.large_box_confidence = 0;
  const bool area_rules = rules.min_box_area > 0 || rules.large_box_confidence > 0;
  if (config.max_concurrent_calls == 0) config.max_concurrent_calls = std::max(1, options.threads);
  std::map<std::string, Detection> cache;
  if (!options.detections_cache.empty()) {
    cache = ReadDetectionCache(options.detections_cache, &config);
  }

  std::vector<const Entry*> entries;
  for (const Entry& e : dataset.database) entries.push_back(&e);
  for (const Entry& e : dataset.queries) entries.push_back(&e);
  // Every entry's content key; one path per key still to detect.
  std::vector<std::string> keys(entries.size());
  std::vector<Status> key_errors(entries.size());
  ParallelFor(entries.size(), options.threads, [&](size_t i, int) {
    auto key = ContentKey(dataset.Resolve(entries[i]->image));
    if (key.ok()) {
      keys[i] = std::move(key).value();
    } else {
      key_errors[i] = key.status();
    }
  });
  for (const Status& error : key_errors) PLACEDB_RETURN_IF_ERROR(error);
  std::map<std::string, std::string> missing_paths;  // key -> a file with that content
  for (size_t i = 0; i < entries.size(); ++i) {
    if (!cache.count(keys[i])) missing_paths.emplace(keys[i], dataset.Resolve(entries[i]->image));
  }
  const std::vector<std::pair<std::string, std::string>> missing(missing_paths.begin(),
                                                                 missing_paths.end());
  if (!missing.empty()) {
    auto detector = CreateDetector(config);
    if (!detector.ok()) return detector.status().WithContext("creating the detector");
    Log(options, "detecting dynamic objects in " + std::to_string(missing.size()) +
                     " images with " + (*detector)->Describe());
    std::vector<Detection> found(missing.size());
    std::vector<Status> errors(missing.size());
    // Progress every 25 images and at the end: images done / total, mean ms per image.
    struct {
      Mutex mutex;
      size_t done GUARDED_BY(mutex) = 0;
      double done_ms GUARDED_BY(mutex) = 0;
    } progress;
    ParallelFor(missing.size(), options.threads, [&](size_t i, int) {
      const std::string& path = missing[i].second;
      cv::Mat bgr = cv::imread(path, cv::IMREAD_COLOR);
      if (bgr.empty()) {
        errors[i] = Status::IoError("cannot read " + path);
      } else {
        Stopwatch watch;
        auto boxes = (*detector)->Detect(bgr);
        found[i].ms = watch.ElapsedMs();
        if (boxes.ok()) {
          found[i].boxes = std::move(boxes).value();
        } else {
          errors[i] = boxes.status().WithContext(path);
        }
      }
      MutexLock lock(progress.mutex);
      const size_t done = ++progress.done;
      progress.done_ms += found[i].ms;
      if (done % 25 == 0 || done == missing.size()) {
        char line[128];
        std::snprintf(line, sizeof(line), "detection: %zu/%zu images, mean %.1f ms per image", done,
                      missing.size(), progress.done_ms / double(done));
        Log(options, line);
      }
    });
    for (size_t i = 0; i < missing.size(); ++i) {
      PLACEDB_RETURN_IF_ERROR(errors[i]);
      cache[missing[i].first] = std::move(found[i]);
    }
    if (!options.detections_cache.empty()) {
      PLACEDB_RETURN_IF_ERROR(WriteDetectionCache(options.detections_cache, config, cache));
    }
  }
  double total_ms = 0;
  for (size_t i = 0; i < entries.size(); ++i) {
    const Detection& detection = cache.at(keys[i]);
    total_ms += detection.ms;
    DynamicObjects& out = i < dataset.database.size()
                              ? inputs->database_dynamic[i]
                              : inputs->query_dynamic[i - dataset.database.size()];
    cv::Size size;
    if (area_rules) {
      const std::string path = dataset.Resolve(entries[i]->image);
      const cv::Mat image = cv::imread(path, cv::IMREAD_UNCHANGED);
      if (image.empty()) return Status::IoError("cannot read " + path);
      size = image.size();
    }
    out.boxes = ApplyBoxRules(detection.boxes, rules, size);
  }
  inputs->detect_mean_ms = entries.empty() ? 0 : total_ms / double(entries.size());
  return Status::Ok();
}

// ---- In-process backend -------------------------------------------------------------------

class InProcessBackend final : public Backend {
 public:
  InProcessBackend(std::shared_ptr<const Vocabulary> vocabulary, int threads,
                   std::optional<LearningOptions> learning,
                   std::optional<IncrementalWordsOptions> incremental)
      : vocabulary_(std::move(vocabulary)),
        threads_(std::max(1, threads)),
        learning_(std::move(learning)),
        incremental_(std::move(incremental)) {}

  std::string Name() const override {
    return learning_      ? "in-process, map-learned vocabulary"
           : incremental_ ? "in-process, incremental words (iBoW-style)"
                          : "in-process";
  }
  double ExtractMeanMs() const override { return extract_mean_ms_; }

  Status Prepare(const EvalInputs& inputs, int features) override {
    const Dataset& dataset = *inputs.dataset;
    learned_.clear();
    OrbConfig orb;
    orb.max_features = features;
    const size_t n = dataset.database.size() + dataset.queries.size();
    std::vector<FeatureSet> extracted(n);
    std::vector<cv::Mat> images(n);
    std::vector<cv::Mat> grays(n);
    std::vector<Status> errors(n);
    std::vector<double> ms(n, 0.0);
    ParallelFor(n, threads_, [&](size_t i, int) {
      const Entry& entry = i < dataset.database.size()
                               ? dataset.database[i]
                               : dataset.queries[i - dataset.database.size()];
      const std::string path = dataset.Resolve(entry.image);
      // ORB on the grayscale decode, as the server extracts; the colour decode is what the
      // server's box refinement sees.
      cv::Mat gray = cv::imread(path, cv::IMREAD_GRAYSCALE);
      images[i] = cv::imread(path, cv::IMREAD_COLOR);
      grays[i] = gray;
      if (gray.empty() || images[i].empty()) {
        errors[i] = Status::IoError("cannot read " + path);
        return;
      }
      Stopwatch watch;
      auto result = ExtractOrb(gray, orb);
      ms[i] = watch.ElapsedMs();
      if (!result.ok()) {
        errors[i] = result.status().WithContext(path);
        return;
      }
      extracted[i] = std::move(result).value();
    });
    for (const Status& error : errors) PLACEDB_RETURN_IF_ERROR(error);
    database_features_.assign(
        std::make_move_iterator(extracted.begin()),
        std::make_move_iterator(extracted.begin() + std::ptrdiff_t(dataset.database.size())));
    query_features_.assign(
        std::make_move_iterator(extracted.begin() + std::ptrdiff_t(dataset.database.size())),
        std::make_move_iterator(extracted.end()));
    database_images_.assign(images.begin(),
                            images.begin() + std::ptrdiff_t(dataset.database.size()));
    query_images_.assign(images.begin() + std::ptrdiff_t(dataset.database.size()), images.end());
    database_gray_.assign(grays.begin(), grays.begin() + std::ptrdiff_t(dataset.database.size()));
    query_gray_.assign(grays.begin() + std::ptrdiff_t(dataset.database.size()), grays.end());
    double total = 0;
    for (double value : ms) total += value;
    extract_mean_ms_ = n ? total / double(n) : 0;
    return Status::Ok();
  }

  Result<MethodRun> Run(const EvalInputs& inputs, const DatabaseConfig& config, bool filtering,
                        size_t top_k) override {
    const Dataset& dataset = *inputs.dataset;
    auto created = PlaceDatabase::Create(vocabulary_, config);
    if (!created.ok()) return created.status();
    auto database = std::move(created).value();
    // The static feature budget needs the pixels: ORB then runs in the pipeline, as in the
    // server, instead of the features extracted once per budget.
    const bool pixels_only = filtering && config.static_feature_budget;
    colour_for_boxes_ = config.box_refinement.method == BoxRefinement::kGrabCut;
    MethodRun run;
    Stopwatch build;
    if (incremental_) return RunIncremental(inputs, filtering, pixels_only, *database, top_k);
    if (!learning_) {
      PLACEDB_RETURN_IF_ERROR(
          Build(inputs, filtering, pixels_only, *database, &run.database, nullptr));
    } else {
      // The map learns from what it stored (the database side's SC descriptors, never a query),
      // then every place is transformed again with the learned vocabulary, as the service does.
      // What is stored depends on the budget (Prepare) and the dynamic input, not on the
      // verification setting: one vocabulary per (method, confidence) and budget.
      const std::pair<bool, float> key{filtering, filtering ? config.min_box_confidence : 0.0f};
      auto cached = learned_.find(key);
      std::vector<std::pair<size_t, ProcessedFrame>> stored;
      uint64_t invalid = 0;
      if (cached == learned_.end()) {
        VocabularyLearner learner(config.feature_type, *learning_);
        PLACEDB_RETURN_IF_ERROR(
            Build(inputs, filtering, pixels_only, *database, &run.database, &learner, &stored));
        auto learned = learner.Learn();
        if (!learned.ok()) return learned.status().WithContext("database of " + dataset.name);
        cached = learned_.emplace(key, std::move(learned).value()).first;
        invalid = database->Stats().invalid_rejected;
      }
      auto relearned = PlaceDatabase::Create(cached->second.vocabulary, config);
      if (!relearned.ok()) return relearned.status();
      database = std::move(relearned).value();
      if (stored.empty()) {
        PLACEDB_RETURN_IF_ERROR(
            Build(inputs, filtering, pixels_only, *database, &run.database, nullptr));
      } else {
        // The stored frames transformed again with the learned vocabulary, as a map switching
        // vocabularies does (no second extraction).
        if (invalid > 0) database->CountInvalid(invalid);
        run.database.encoded_bytes = 0;
        for (auto& [index, frame] : stored) {
          PLACEDB_RETURN_IF_ERROR(database->Retransform(&frame));
          const PlaceMetadata metadata = Metadata(dataset.database[index], index);
          auto id = database->Insert(frame, metadata);
          if (!id.ok()) return id.status();
          run.database.encoded_bytes += EncodedBytes(frame, metadata, *id);
        }
      }
      const LearnedVocabulary& learned = cached->second;
      run.database.learned_words = learned.vocabulary.word_count();
      run.database.learned_depth = learned.shape.depth;
      run.database.learned_from_descriptors = learned.descriptors_sampled;
      run.database.learn_seconds = learned.train_ms / 1000.0;
    }
    run.database.build_seconds = build.ElapsedMs() / 1000.0;
    PlaceDatabase& db = *database;
    CountDatabase(db, &run.database);

    QueryOptions query_options;
    query_options.top_k = top_k;
    const bool verification = config.verification.mode != VerificationMode::kDisabled;
    for (size_t q = 0; q < dataset.queries.size(); ++q) {
      auto result = db.Query(Observe(inputs, q, true, filtering, pixels_only), query_options);
      if (!result.ok()) return result.status().WithContext("query " + dataset.queries[q].id);
      std::vector<RankedMatch> ranked;
      for (const Match& match : result->matches) {
        ranked.push_back(
            {int(match.metadata.sequence), match.score, match.verified, match.inliers});
      }
      QueryOutcome outcome = ScoreQuery(ranked, inputs.truth[q], verification);
      outcome.valid = result->valid;
      // Extraction is reported apart (BoBW's features are precomputed); box refinement, when
      // it runs, is the filter's own cost and stays in.
      outcome.latency_ms = result->timings.total_ms - result->timings.extract_ms;
      outcome.match_ms = result->timings.search_ms + result->timings.verify_ms;
      outcome.kept = result->counts.static_;
      outcome.dropped = result->counts.dynamic;
      run.queries.push_back(outcome);
    }
    return run;
  }

 private:
  // The incremental alternative (eval/incremental_words.h): the stored frames' SC descriptors
  // grow the words in database order; queries rank by them (no verification).
  Result<MethodRun> RunIncremental(const EvalInputs& inputs, bool filtering, bool pixels_only,
                                   PlaceDatabase& db, size_t top_k) {
    const Dataset& dataset = *inputs.dataset;
    MethodRun run;
    Stopwatch build;
    std::vector<std::pair<size_t, ProcessedFrame>> stored;
    PLACEDB_RETURN_IF_ERROR(
        Build(inputs, filtering, pixels_only, db, &run.database, nullptr, &stored));
    IncrementalWords words(*vocabulary_, *incremental_);
    for (const auto& [index, frame] : stored) {
      words.AddPlace(uint32_t(index), frame.static_features.orb()->descriptors);
    }
    run.database.build_seconds = build.ElapsedMs() / 1000.0;
    CountDatabase(db, &run.database);
    run.database.memory_bytes = 0;  // the words live outside the database
    run.database.learned_words = uint32_t(words.word_count());
    for (size_t q = 0; q < dataset.queries.size(); ++q) {
      Stopwatch watch;
      auto frame = db.Process(Observe(inputs, q, true, filtering, pixels_only));
      if (!frame.ok()) return frame.status().WithContext("query " + dataset.queries[q].id);
      std::vector<RankedMatch> ranked;
      Stopwatch match;
      if (frame->valid) {
        for (const auto& [index, score] :
             words.Query(frame->static_features.orb()->descriptors, top_k)) {
          ranked.push_back({int(index), score, false, 0});
        }
      }
      QueryOutcome outcome = ScoreQuery(ranked, inputs.truth[q], false);
      outcome.valid = frame->valid;
      outcome.match_ms = match.ElapsedMs();
      outcome.latency_ms = watch.ElapsedMs() - frame->timings.extract_ms;
      outcome.kept = frame->counts.static_;
      outcome.dropped = frame->counts.dynamic;
      run.queries.push_back(outcome);
    }
    return run;
  }

  // The database's figures after its build.
  static void CountDatabase(const PlaceDatabase& db, DatabaseFigures* figures) {
    const DatabaseStats stats = db.Stats();
    figures->places = stats.places;
    figures->invalid = stats.invalid_rejected;
    figures->descriptors_kept = stats.descriptors_kept;
    figures->descriptors_dropped = stats.descriptors_dropped;
    figures->memory_bytes = stats.index_bytes + stats.record_bytes + stats.payload_bytes;
  }

  // Processes and inserts every database entry; `learner`, when given, is offered each stored
  // place's SC features, and `stored` receives the stored frames with their entry's index.
  Status Build(const EvalInputs& inputs, bool filtering, bool pixels_only, PlaceDatabase& db,
               DatabaseFigures* figures, VocabularyLearner* learner,
               std::vector<std::pair<size_t, ProcessedFrame>>* stored = nullptr) {
    const Dataset& dataset = *inputs.dataset;
    const size_t n = dataset.database.size();
    std::vector<std::optional<ProcessedFrame>> processed(n);
    std::vector<Status> errors(n);
    ParallelFor(n, threads_, [&](size_t i, int) {
      auto frame = db.Process(Observe(inputs, i, false, filtering, pixels_only));
      if (!frame.ok()) {
        errors[i] = frame.status().WithContext("database entry " + dataset.database[i].id);
        return;
      }
      processed[i] = std::move(frame).value();
    });
    for (size_t i = 0; i < n; ++i) {
      PLACEDB_RETURN_IF_ERROR(errors[i]);
      const ProcessedFrame& frame = *processed[i];
      if (!frame.valid) {
        db.CountInvalid();
        continue;
      }
      PlaceMetadata metadata = Metadata(dataset.database[i], i);
      auto id = db.Insert(frame, metadata);
      if (!id.ok()) return id.status();
      if (learner) PLACEDB_RETURN_IF_ERROR(learner->Offer(*id, frame.static_features));
      figures->encoded_bytes += EncodedBytes(frame, metadata, *id);
      if (stored) stored->emplace_back(i, std::move(*processed[i]));
      processed[i].reset();
    }
    return Status::Ok();
  }

  // What a durable map writes for a place (map_store: three values under 4-byte keys).
  static uint64_t EncodedBytes(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                               PlaceId id) {
    PlaceRecord record;
    record.id = id;
    record.metadata = metadata;
    record.counts = frame.counts;
    record.boxes_used = frame.boxes_used;
    return EncodePlaceRecord(record).size() + EncodeBow(frame.bow).size() +
           EncodeLocalFeatures(frame.static_features, frame.direct).size() +
           3 * PlaceKey(id).size();
  }

  static PlaceMetadata Metadata(const Entry& entry, size_t index) {
    PlaceMetadata metadata;
    metadata.agent_id = entry.agent;
    metadata.sequence = uint64_t(index);  // the database index: how matches map back
    metadata.timestamp_ns = entry.timestamp_ns;
    return metadata;
  }

  Observation Observe(const EvalInputs& inputs, size_t i, bool query, bool filtering,
                      bool pixels_only) const {
    Observation observation;
    const DynamicObjects& dynamic = query ? inputs.query_dynamic[i] : inputs.database_dynamic[i];
    const bool objects = filtering && (!dynamic.boxes.empty() || !dynamic.mask.empty());
    // Without objects the pipeline extracts what was extracted once per budget: reuse it.
    if (!pixels_only || !objects) {
      observation.features = query ? query_features_[i] : database_features_[i];
    }
    if (filtering) {
      observation.dynamic = dynamic;
      // The pixels, as the server decodes them: colour when GrabCut refines the boxes, else the
      // grayscale decode that ORB sees.
      observation.image = colour_for_boxes_ && !dynamic.boxes.empty()
                              ? (query ? query_images_[i] : database_images_[i])
                              : (query ? query_gray_[i] : database_gray_[i]);
    }
    const Entry& entry = query ? inputs.dataset->queries[i] : inputs.dataset->database[i];
    observation.metadata = Metadata(entry, i);
    return observation;
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
  int threads_;
  // Set: each database learns its vocabulary from its own stored places (fixed: vocabulary_).
  std::optional<LearningOptions> learning_;
  // Set: the incremental alternative instead of a vocabulary (RunIncremental).
  std::optional<IncrementalWordsOptions> incremental_;
  // The vocabularies learned for the current budget, by (BoBW+DO, box confidence).
  std::map<std::pair<bool, float>, LearnedVocabulary> learned_;
  std::vector<FeatureSet> database_features_;
  std::vector<FeatureSet> query_features_;
  std::vector<cv::Mat> database_images_;  // BGR
  std::vector<cv::Mat> query_images_;
  std::vector<cv::Mat> database_gray_;  // the grayscale decode
  std::vector<cv::Mat> query_gray_;
  bool colour_for_boxes_ = false;  // set by Run() for its configuration
  double extract_mean_ms_ = 0;
};

std::string DynamicSourceName(const RunOptions& options) {
  std::string boxes;
  switch (options.boxes) {
    case BoxInput::kNone:
      break;
    case BoxInput::kOracle:
      boxes = "oracle boxes";
      break;
    case BoxInput::kDetector:
      boxes = "detector boxes (" + fs::path(options.detector.model_path).filename().string() +
              ", " + PreprocessingName(options.detector.preprocessing);
      // The box rules, when any applies (core/detect/detector.h, ApplyBoxRules).
      for (const auto& [name, value] : options.detector.class_confidence) {
        char rule[64];
        std::snprintf(rule, sizeof(rule), ", %s >= %g", name.c_str(), value);
        boxes += rule;
      }
      if (options.detector.min_box_area > 0) {
        char rule[64];
        std::snprintf(rule, sizeof(rule), ", area >= %g", options.detector.min_box_area);
        boxes += rule;
      }
      if (options.detector.large_box_confidence > 0 && options.detector.large_box_area < 1) {
        char rule[96];
        std::snprintf(rule, sizeof(rule), ", area > %g needs %g", options.detector.large_box_area,
                      options.detector.large_box_confidence);
        boxes += rule;
      }
      boxes += ")";
      break;
  }
  std::string source = boxes;
  if (options.masks == MaskInput::kOracle)
    source += std::string(source.empty() ? "" : " + ") + "oracle masks";
  if (source.empty()) source = "no dynamic input";
  source += std::string(", filter ") + FilterMethodName(options.filter);
  if (options.filter == FilterMethod::kExactCoverage) {
    char threshold[32];
    std::snprintf(threshold, sizeof(threshold), " %g%%", options.sensitivity * 100.0);
    source += threshold;
  }
  if (options.refinement != BoxRefinement::kNone) {
    source += std::string(", boxes refined: ") + BoxRefinementName(options.refinement);
  }
  if (options.short_term) {
    char tier[96];
    std::snprintf(tier, sizeof(tier), ", short-term tier %gs x %g",
                  double(options.short_term_config.horizon_ns) / 1e9,
                  double(options.short_term_config.weight));
    source += tier;
  }
  if (options.static_budget) source += ", static feature budget";
  if (options.rerank > 0) source += ", re-rank top " + std::to_string(options.rerank);
  return source;
}

}  // namespace

std::string GeomName(int geom) {
  return geom < 0 ? "NoGeom" : "Geo-" + std::to_string(geom);
}

Result<int> ParseGeom(const std::string& text) {
  std::string t = AsciiLower(text);
  if (t == "none" || t == "nogeom" || t == "disabled" || t == "off") return kNoGeom;
  if (t == "exhaustive") return 6;
  if (t.rfind("geo-", 0) == 0) t = t.substr(4);
  if (!t.empty() && t.size() <= 2 && std::all_of(t.begin(), t.end(), ::isdigit)) {
    return std::stoi(t);
  }
  return Status::InvalidArgument("geometric setting \"" + text +
                                 "\": use none, a level 0-99 (Geo-l) or exhaustive");
}

Result<BoxInput> ParseBoxInput(const std::string& text) {
  const std::string t = AsciiLower(text);
  if (t == "none") return BoxInput::kNone;
  if (t == "oracle") return BoxInput::kOracle;
  if (t == "detector") return BoxInput::kDetector;
  return Status::InvalidArgument("boxes \"" + text + "\": use oracle, detector or none");
}

Result<MaskInput> ParseMaskInput(const std::string& text) {
  const std::string t = AsciiLower(text);
  if (t == "none") return MaskInput::kNone;
  if (t == "oracle") return MaskInput::kOracle;
  return Status::InvalidArgument("masks \"" + text + "\": use oracle or none");
}

Status ValidateRunOptions(const RunOptions& options) {
  if (options.features.empty()) return Status::InvalidArgument("features: at least one budget");
  for (int f : options.features) {
    if (f < 1 || f > 100000) {
      return Status::InvalidArgument("features: " + std::to_string(f) + " is not in [1, 100000]");
    }
  }
  if (options.geoms.empty()) return Status::InvalidArgument("geom: at least one setting");
  for (int g : options.geoms) {
    if (g < kNoGeom || g > 99) {
      return Status::InvalidArgument("geom: " + std::to_string(g) + " is not a setting");
    }
  }
  if (options.confidences.empty()) return Status::InvalidArgument("confidence: at least one");
  for (float c : options.confidences) {
    if (!(c > 0 && c <= 1)) {
      return Status::InvalidArgument("confidence: " + std::to_string(c) + " is not in (0, 1]");
    }
  }
  if (!(options.sensitivity >= 0 && options.sensitivity < 1)) {
    return Status::InvalidArgument("sensitivity must be in [0, 1)");
  }
  if (options.top_k < 1) return Status::InvalidArgument("top_k must be at least 1");
  if (options.boxes == BoxInput::kDetector && options.detector.model_path.empty()) {
    return Status::InvalidArgument("detector boxes need a model (--model)");
  }
  return Status::Ok();
}

Result<EvalInputs> PrepareInputs(const Dataset& dataset, const RunOptions& options) {
  EvalInputs inputs;
  inputs.dataset = &dataset;
  inputs.truth = GroundTruthIndices(dataset);
  inputs.database_dynamic.resize(dataset.database.size());
  inputs.query_dynamic.resize(dataset.queries.size());
  const bool need_masks = options.masks == MaskInput::kOracle;
  for (int list = 0; list < 2; ++list) {
    const std::vector<Entry>& entries = list == 0 ? dataset.database : dataset.queries;
    std::vector<DynamicObjects>& out = list == 0 ? inputs.database_dynamic : inputs.query_dynamic;
    for (size_t i = 0; i < entries.size(); ++i) {
      const Entry& entry = entries[i];
      cv::Mat mask;
      if (need_masks || (options.boxes == BoxInput::kOracle && !entry.boxes)) {
        auto loaded = LoadEntryMask(dataset, entry);
        if (!loaded.ok()) return loaded.status();
        mask = std::move(loaded).value();
      }
      if (need_masks) out[i].mask = mask;
      if (options.boxes == BoxInput::kOracle) {
        if (entry.boxes) {
          out[i].boxes = *entry.boxes;
        } else if (!mask.empty()) {
          out[i].boxes = BoxesFromMask(mask);
        }
      }
      if (list == 1) {
        cv::Size size;
        if (!entry.coverage && entry.mask.empty() && entry.boxes && !entry.boxes->empty()) {
          cv::Mat image = cv::imread(dataset.Resolve(entry.image), cv::IMREAD_GRAYSCALE);
          size = image.size();
        }
        inputs.query_coverage.push_back(EntryCoverage(dataset, entry, size));
      }
    }
  }
  if (options.boxes == BoxInput::kDetector) {
    PLACEDB_RETURN_IF_ERROR(Detect(dataset, options, &inputs));
  }
  return inputs;
}

DatabaseConfig MakeDatabaseConfig(const RunOptions& options, int features, int geom,
                                  float confidence, bool filtering) {
  DatabaseConfig config;
  config.orb.max_features = features;
  config.filter.method = filtering ? options.filter : FilterMethod::kNone;
  config.filter.sensitivity_threshold = options.sensitivity;
  config.filter.place_threshold = options.place_threshold;
  config.min_box_confidence = filtering && options.boxes == BoxInput::kDetector ? confidence : 0.0f;
  if (geom == kNoGeom) {
    config.verification.mode = VerificationMode::kDisabled;
  } else {
    config.verification.mode = VerificationMode::kDirectIndex;
    config.verification.levels_up = geom;
  }
  config.verification.min_inliers = options.min_inliers;
  // DBoW2's loop detector verifies its best candidate; re-ranking verifies the best N.
  config.verification.candidates = options.rerank > 0 ? options.rerank : 1;
  config.verification.rerank = options.rerank > 0;
  config.verification.legacy = options.legacy_verifier;
  if (filtering) {
    config.box_refinement.method = options.refinement;
    config.short_term = options.short_term_config;
    config.short_term.enabled = options.short_term;
    config.static_feature_budget = options.static_budget;
  }
  return config;
}

QueryOutcome ScoreQuery(const std::vector<RankedMatch>& matches, const std::vector<int>& truth,
                        bool verification) {
  QueryOutcome outcome;
  outcome.valid = true;
  if (matches.empty()) return outcome;
  outcome.top1 = matches[0].database_index;
  outcome.score = matches[0].score;
  outcome.verified = matches[0].verified;
  outcome.inliers = matches[0].inliers;
  for (size_t r = 0; r < matches.size(); ++r) {
    if (std::binary_search(truth.begin(), truth.end(), matches[r].database_index)) {
      outcome.truth_rank = int(r) + 1;
      break;
    }
  }
  outcome.correct = outcome.truth_rank == 1 && (!verification || outcome.verified);
  return outcome;
}

std::unique_ptr<Backend> MakeInProcessBackend(std::shared_ptr<const Vocabulary> vocabulary,
                                              int threads, std::optional<LearningOptions> learning,
                                              std::optional<IncrementalWordsOptions> incremental) {
  return std::make_unique<InProcessBackend>(std::move(vocabulary), threads, std::move(learning),
                                            std::move(incremental));
}

Result<RunResults> RunEvaluation(const Dataset& dataset, const RunOptions& options,
                                 Backend& backend) {
  PLACEDB_RETURN_IF_ERROR(ValidateRunOptions(options));
  auto inputs = PrepareInputs(dataset, options);
  if (!inputs.ok()) return inputs.status();
  RunResults results;
  results.dataset_name = dataset.name;
  results.backend = backend.Name();
  results.dynamic_source = DynamicSourceName(options);
  results.options = options;
  results.options.log = nullptr;
  results.database_size = dataset.database.size();
  results.query_coverage = inputs->query_coverage;
  for (const auto& truth : inputs->truth) results.query_has_truth.push_back(!truth.empty());
  results.detect_mean_ms = inputs->detect_mean_ms;

  // Detector confidences only matter for detector boxes.
  std::vector<float> confidences = options.confidences;
  if (options.boxes != BoxInput::kDetector) confidences = {0.0f};
  for (int features : options.features) {
    Stopwatch prepare;
    PLACEDB_RETURN_IF_ERROR(backend.Prepare(*inputs, features));
    results.extract_mean_ms[features] = backend.ExtractMeanMs();
    Log(options, "ORB " + std::to_string(features) + ": inputs ready in " +
                     std::to_string(int(prepare.ElapsedMs())) + " ms");
    for (int geom : options.geoms) {
      for (int pass = 0; pass <= int(confidences.size()); ++pass) {
        const bool filtering = pass > 0;
        const float confidence = filtering ? confidences[size_t(pass - 1)] : 0.0f;
        const DatabaseConfig config =
            MakeDatabaseConfig(options, features, geom, confidence, filtering);
        auto run = backend.Run(*inputs, config, filtering, options.top_k);
        if (!run.ok()) {
          return run.status().WithContext("ORB " + std::to_string(features) + " " + GeomName(geom) +
                                          (filtering ? " BoBW+DO" : " BoBW"));
        }
        run->features = features;
        run->geom = geom;
        run->confidence = confidence;
        run->method = filtering ? kBoBWDO : kBoBW;
        results.runs.push_back(std::move(run).value());
        const Summary all = Summarize(results, results.runs.back(), {"All", -1});
        char line[256];
        std::snprintf(line, sizeof(line),
                      "ORB %d %-6s %-7s%s: top-1 %5.1f %% (%d/%d), places %zu, %.2f MB, "
                      "latency p50 %.2f ms",
                      features, GeomName(geom).c_str(), filtering ? kBoBWDO : kBoBW,
                      filtering && options.boxes == BoxInput::kDetector
                          ? (" @" + std::to_string(confidence).substr(0, 4)).c_str()
                          : "",
                      all.accuracy, all.correct, all.queries, results.runs.back().database.places,
                      double(std::max(results.runs.back().database.encoded_bytes,
                                      results.runs.back().database.disk_bytes)) /
                          1e6,
                      all.latency_p50_ms);
        Log(options, line);
      }
    }
  }
  return results;
}

std::vector<CoverageBin> PaperBins() {
  return {{"All", -1}, {">10%", 0.10}, {">20%", 0.20}, {">30%", 0.30}};
}

Summary Summarize(const RunResults& results, const MethodRun& run, const CoverageBin& bin) {
  Summary summary;
  std::vector<double> latencies;
  double match_total = 0;
  int recall1 = 0, recall5 = 0, recall10 = 0;
  for (size_t q = 0; q < run.queries.size(); ++q) {
    const double coverage = q < results.query_coverage.size() ? results.query_coverage[q] : 0;
    if (bin.above >= 0 && !(coverage > bin.above)) continue;
    const QueryOutcome& outcome = run.queries[q];
    latencies.push_back(outcome.latency_ms);
    match_total += outcome.match_ms;
    if (!outcome.valid) ++summary.invalid;
    const bool has_truth = q < results.query_has_truth.size() && results.query_has_truth[q];
    if (!has_truth) {
      ++summary.no_truth;
      const bool verification = run.geom != kNoGeom;
      if (outcome.top1 >= 0 && (!verification || outcome.verified)) ++summary.no_truth_accepted;
      continue;
    }
    ++summary.queries;
    summary.correct += outcome.correct;
    recall1 += outcome.truth_rank == 1;
    recall5 += outcome.truth_rank >= 1 && outcome.truth_rank <= 5;
    recall10 += outcome.truth_rank >= 1 && outcome.truth_rank <= 10;
  }
  if (summary.queries > 0) {
    const double n = summary.queries;
    summary.accuracy = 100.0 * summary.correct / n;
    summary.recall_at_1 = 100.0 * recall1 / n;
    summary.recall_at_5 = 100.0 * recall5 / n;
    summary.recall_at_10 = 100.0 * recall10 / n;
  }
  if (!latencies.empty()) {
    double total = 0;
    for (double l : latencies) total += l;
    summary.latency_mean_ms = total / double(latencies.size());
    summary.match_mean_ms = match_total / double(latencies.size());
    summary.latency_p50_ms = Percentile(latencies, 0.50);
    summary.latency_p90_ms = Percentile(latencies, 0.90);
  }
  return summary;
}

}  // namespace placedb::eval
