// Runs the paper's section V over a dataset (eval/dataset.h): BoBW (no filtering) and BoBW+DO
// (dynamic-object filtering) over a grid of ORB budgets x geometric-verification settings x
// detector confidences, each as a fresh database built from the dataset's database entries and
// queried with its query entries.
//
// Correct (top-1 accuracy): the best-ranked place is in the query's ground truth AND, when
// verification is on, passed it (only the best candidate is verified, as DBoW2's loop detector
// does). recall@k: a ground-truth place is among the k best-ranked (BoW ranking only, no
// verification). Queries with an empty ground truth are left out of both and counted apart: with
// verification on they are correctly rejected when the top-1 fails it (or the query is invalid);
// without verification any returned match is a false positive. An invalid query (too few static
// descriptors, the paper's eq. 6) returns nothing and counts as a miss.
//
// Two backends: in-process against the core library (features extracted once per ORB budget and
// reused by every setting; query latency = the engine's filter + transform + search + verify,
// extraction reported apart), or a live placedb-server through the proto (eval/remote.h: images
// travel encoded; latency is the client's round trip and includes decode + extraction).
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/detect/detector.h"
#include "core/filter/dynamic_filter.h"
#include "core/pipeline/place_database.h"
#include "core/vocabulary/vocabulary.h"
#include "core/vocabulary/vocabulary_learning.h"
#include "eval/dataset.h"
#include "eval/incremental_words.h"

namespace placedb::eval {

// Geometric settings: -1 = no verification ("NoGeom"), l >= 0 = direct index l levels above the
// words ("Geo-l"); l >= the vocabulary depth puts every feature under the root (exhaustive).
inline constexpr int kNoGeom = -1;
std::string GeomName(int geom);  // "NoGeom", "Geo-0", ...
// "none"/"nogeom"/"disabled" -> -1; "0", "geo-1", "Geo-2" -> the level; "exhaustive" -> 6.
Result<int> ParseGeom(const std::string& text);

enum class BoxInput { kNone, kOracle, kDetector };
enum class MaskInput { kNone, kOracle };
Result<BoxInput> ParseBoxInput(const std::string& text);    // none | oracle | detector
Result<MaskInput> ParseMaskInput(const std::string& text);  // none | oracle

inline constexpr const char* kBoBW = "BoBW";
inline constexpr const char* kBoBWDO = "BoBW+DO";

struct RunOptions {
  std::vector<int> features = {300, 500, 1000, 1500, 2000};
  std::vector<int> geoms = {kNoGeom, 0, 1, 2, 6};
  BoxInput boxes = BoxInput::kOracle;
  MaskInput masks = MaskInput::kNone;
  // Detector boxes at or above each confidence are used (one BoBW+DO run per value); oracle
  // boxes have confidence 1, so the list only matters for detector boxes.
  std::vector<float> confidences = {0.2f};
  FilterMethod filter = FilterMethod::kKeypointInBox;
  float sensitivity = 0.25f;  // exact_coverage only
  int place_threshold = 20;
  // The defaults below are the service's (a map created with default settings); the paper's
  // BoBW+DO is --refine-boxes none --short-term off --static-budget off --rerank 0.
  // BoBW+DO: boxes narrowed to their objects' pixels (core/filter/box_masks.h) before filtering.
  BoxRefinement refinement = BoxRefinement::kShape;
  // BoBW+DO: the short-term tier of DC words (core/pipeline/place_database.h, ShortTermConfig).
  bool short_term = true;
  // BoBW+DO: ORB's budget spent on the static pixels (DatabaseConfig::static_feature_budget).
  bool static_budget = true;
  ShortTermConfig short_term_config;
  // Both methods: verify the best `rerank` candidates and re-rank them by inliers (spatial
  // re-ranking); 0 = verify the best candidate only, as DBoW2's loop detector does.
  int rerank = 10;
  // The verifier before issue 31 (VerificationConfig::legacy), to compare the default with it.
  bool legacy_verifier = false;
  int min_inliers = 15;
  size_t top_k = 10;
  DetectorConfig detector;                      // model path etc. for BoxInput::kDetector
  std::string detections_cache;                 // JSON file reused across runs; empty = none
  int threads = 2;                              // extraction / processing / detection workers
  std::function<void(const std::string&)> log;  // progress lines; may be empty
};

// Validates the grid (features in [1, 100000], geoms >= -1, confidences in (0, 1], ...).
Status ValidateRunOptions(const RunOptions& options);

// The dynamic-object input of every entry (what BoBW+DO sees), fixed for a run.
struct EvalInputs {
  const Dataset* dataset = nullptr;
  std::vector<std::vector<int>> truth;  // per query: database indices
  std::vector<DynamicObjects> database_dynamic;
  std::vector<DynamicObjects> query_dynamic;
  std::vector<double> query_coverage;  // ground-truth coverage (for the bins)
  double detect_mean_ms = 0;           // detector time per frame, when it ran
};

// Prepares EvalInputs: loads oracle boxes/masks or runs (or reads cached) detections.
Result<EvalInputs> PrepareInputs(const Dataset& dataset, const RunOptions& options);

struct DatabaseFigures {
  size_t places = 0;
  uint64_t invalid = 0;              // entries refused as invalid place representations
  uint64_t descriptors_kept = 0;     // SC
  uint64_t descriptors_dropped = 0;  // DC
  // Bytes a durable map writes per place (core/storage/codec.h: record + BoW + SC features + direct
  // index + keys), summed: the database's size before RocksDB's own overhead.
  uint64_t encoded_bytes = 0;
  uint64_t memory_bytes = 0;  // in-memory index + records + payloads (DatabaseStats)
  uint64_t disk_bytes = 0;    // server backend: the map's files (MapStats.bytes_on_disk)
  double build_seconds = 0;
  // Map-learned vocabulary runs: the vocabulary this database learned from its stored places.
  uint32_t learned_words = 0;
  int learned_depth = 0;
  uint64_t learned_from_descriptors = 0;
  double learn_seconds = 0;  // training alone (build_seconds includes it and both builds)
};

struct QueryOutcome {
  bool valid = false;
  int top1 = -1;  // database index of the best-ranked place, -1 when none
  double score = 0;
  bool verified = false;
  int inliers = 0;
  int truth_rank = 0;  // 1-based rank of the first ground-truth place in the top-k; 0 = none
  bool correct = false;
  double latency_ms = 0;  // the whole query (see the backend)
  double match_ms = 0;    // the engine's search + verification: the paper's matching time
  uint32_t kept = 0, dropped = 0;
};

struct MethodRun {
  int features = 0;
  int geom = kNoGeom;
  float confidence = 0;  // the DO run's box threshold (0 for BoBW)
  std::string method;    // kBoBW or kBoBWDO
  DatabaseFigures database;
  std::vector<QueryOutcome> queries;
};

// Where the databases live: the core library in this process, or a live server.
class Backend {
 public:
  virtual ~Backend() = default;
  virtual std::string Name() const = 0;
  // Called once per ORB budget before its runs (the in-process backend extracts here).
  virtual Status Prepare(const EvalInputs& inputs, int features) = 0;
  // One database built and queried. `filtering` = BoBW+DO (the dynamic inputs are passed).
  virtual Result<MethodRun> Run(const EvalInputs& inputs, const DatabaseConfig& config,
                                bool filtering, size_t top_k) = 0;
  // Mean ORB extraction time per frame for the last Prepare (0 if not measured).
  virtual double ExtractMeanMs() const { return 0; }
};

// With `learning`, each database is built with `vocabulary`, learns its own vocabulary from
// its stored places' SC descriptors (core/vocabulary/vocabulary_learning.h; never from a query)
// and is built again with it: the map-learned vocabulary of issue 29.
// With `incremental` instead, each database grows its own binary words as places are added
// (eval/incremental_words.h), the alternative of issue 29's item 5; NoGeom only.
std::unique_ptr<Backend> MakeInProcessBackend(
    std::shared_ptr<const Vocabulary> vocabulary, int threads,
    std::optional<LearningOptions> learning = std::nullopt,
    std::optional<IncrementalWordsOptions> incremental = std::nullopt);

struct RunResults {
  std::string dataset_name;
  std::string backend;
  std::string dynamic_source;  // "oracle masks", "oracle boxes", "detector yolox_nano.onnx", ...
  RunOptions options;
  size_t database_size = 0;
  std::vector<double> query_coverage;
  std::vector<bool> query_has_truth;
  std::map<int, double> extract_mean_ms;  // per ORB budget
  double detect_mean_ms = 0;
  std::vector<MethodRun> runs;
};

// The database configuration of one grid point (verification of the best candidate only).
DatabaseConfig MakeDatabaseConfig(const RunOptions& options, int features, int geom,
                                  float confidence, bool filtering);

// The whole grid. BoBW does not depend on the confidence: it runs once per (features, geom).
Result<RunResults> RunEvaluation(const Dataset& dataset, const RunOptions& options,
                                 Backend& backend);

// Scores one query's ranked matches (database indices, best first).
struct RankedMatch {
  int database_index = -1;
  double score = 0;
  bool verified = false;
  int inliers = 0;
};
QueryOutcome ScoreQuery(const std::vector<RankedMatch>& matches, const std::vector<int>& truth,
                        bool verification);

// ---- Summaries --------------------------------------------------------------------------------

struct CoverageBin {
  std::string name;   // "All", ">10%", ...
  double above = -1;  // queries with coverage strictly above this (-1 = all)
};
std::vector<CoverageBin> PaperBins();  // All, >10%, >20%, >30%

struct Summary {
  int queries = 0;  // with a non-empty ground truth
  int correct = 0;
  double accuracy = 0;                                        // percent
  double recall_at_1 = 0, recall_at_5 = 0, recall_at_10 = 0;  // percent
  int invalid = 0;
  int no_truth = 0;           // queries without ground truth in the bin
  int no_truth_accepted = 0;  // of those, answered with an accepted (verified / any) match
  double latency_mean_ms = 0, latency_p50_ms = 0, latency_p90_ms = 0;
  double match_mean_ms = 0;  // search + verification only
};
Summary Summarize(const RunResults& results, const MethodRun& run, const CoverageBin& bin);

}  // namespace placedb::eval
