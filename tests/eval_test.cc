// The evaluation harness (eval/) on small subsets with known outcomes: the dataset format round
// trip, the adapters' ground truth, the revisit builder's reproducibility and coverage, the
// reports' shape, queries without ground truth, and the live-server backend agreeing with the
// in-process one.
#include <gtest/gtest.h>
#include <spdlog/spdlog.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>

#include "eval/adapters.h"
#include "eval/dataset.h"
#include "eval/remote.h"
#include "eval/report.h"
#include "eval/revisits.h"
#include "eval/runner.h"
#include "server/server.h"
#include "tests/test_support.h"
#include "tests/tls_certificates.h"

namespace fs = std::filesystem;

namespace placedb::eval {
namespace {

std::string CamVidDir() {
  return testing::SharedDir() + "/data/camvid";
}
std::string RtabmapDir() {
  return testing::SharedDir() + "/data/rtabmap-loop";
}

using testing::ReadFileBytes;

std::vector<std::string> Lines(const std::string& text) {
  std::vector<std::string> lines;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

RunOptions SmallRun(std::vector<int> features, std::vector<int> geoms) {
  RunOptions options;
  options.features = std::move(features);
  options.geoms = std::move(geoms);
  options.threads = 2;
  return options;
}

RunResults Evaluate(const Dataset& dataset, const RunOptions& options) {
  auto backend = MakeInProcessBackend(testing::DefaultVocabulary(), options.threads);
  auto results = RunEvaluation(dataset, options, *backend);
  EXPECT_TRUE(results.ok()) << results.status().ToString();
  return results.ok() ? std::move(results).value() : RunResults{};
}

const MethodRun* Find(const RunResults& results, int features, int geom,
                      const std::string& method) {
  for (const MethodRun& run : results.runs) {
    if (run.features == features && run.geom == geom && run.method == method) return &run;
  }
  return nullptr;
}

class EvalTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    ASSERT_TRUE(testing::DefaultVocabulary());
  }
};

// ---- Dataset format -------------------------------------------------------------------------

// Found by tests/fuzz/fuzz_eval_dataset: a CSV dataset with bytes that are not UTF-8 loaded, and
// then SaveDataset's JSON writer threw (terminating placedb-eval). Now both refuse it by name.
TEST_F(EvalTest, DatasetTextMustBeUtf8) {
  Dataset dataset;
  dataset.name = "utf8";
  dataset.directory = testing::MakeTempDir("placedb-eval-utf8");
  Entry entry;
  entry.id = "caf\xc3\xa9 \xe2\x82\xac \xf0\x9f\x9a\x97";  // well-formed: accepted
  entry.image = RtabmapDir() + "/1.jpg";
  dataset.database.push_back(entry);
  ASSERT_TRUE(SaveDataset(dataset).ok());
  ASSERT_TRUE(LoadDataset(dataset.directory).ok());
  std::filesystem::remove(dataset.directory + "/dataset.json");  // the CSV form from here on
  ASSERT_TRUE(SaveDatasetCsv(dataset).ok());
  auto loaded = LoadDataset(dataset.directory);
  ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
  EXPECT_EQ(loaded->database[0].id, entry.id);
  for (const std::string& broken :
       {std::string("\xff"), std::string("a\xc3"), std::string("\xc0\xaf"),
        std::string("\xed\xa0\x80"), std::string("\xf4\x90\x80\x80")}) {
    Dataset bad = dataset;
    bad.database[0].agent = broken;
    const Status status = SaveDataset(bad);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument) << status.ToString();
    EXPECT_NE(status.message().find("agent is not valid UTF-8"), std::string::npos)
        << status.message();
    ASSERT_TRUE(SaveDatasetCsv(dataset).ok());
    // The same bytes in a CSV file: refused when loading.
    std::ofstream(dataset.directory + "/database.csv", std::ios::app)
        << "x," << RtabmapDir() << "/2.jpg,,,robot" << broken << ",0,0,,\n";
    loaded = LoadDataset(dataset.directory);
    EXPECT_EQ(loaded.status().code(), StatusCode::kInvalidArgument) << loaded.status().ToString();
  }
}

// Found by tests/fuzz/fuzz_eval_dataset: a dataset.json whose format, name or description was
// not a string threw out of LoadDataset (terminating placedb-eval).
TEST_F(EvalTest, DatasetJsonWithMistypedHeaderIsRefused) {
  const std::string directory = testing::MakeTempDir("placedb-eval-mistyped");
  for (const std::string& header :
       {std::string(R"("format": 1)"),
        std::string(R"("format": "placedb-eval-dataset/1", "name": ["x"])"),
        std::string(R"("format": "placedb-eval-dataset/1", "description": {"a": 1})")}) {
    std::ofstream(directory + "/dataset.json", std::ios::trunc)
        << "{" << header << R"(, "database": [{"id": "a", "image": ")" << RtabmapDir()
        << R"(/1.jpg"}], "queries": []})";
    auto loaded = LoadDataset(directory);
    EXPECT_EQ(loaded.status().code(), StatusCode::kInvalidArgument) << header;
  }
  // Numbers an integer field cannot hold (converting them was undefined behaviour).
  for (const std::string& field : {std::string(R"("sequence": 3.3e25)"),
                                   std::string(R"("timestamp_ns": 18446744073709551615)"),
                                   std::string(R"("mask_values": [1e10])")}) {
    std::ofstream(directory + "/dataset.json", std::ios::trunc)
        << R"({"format": "placedb-eval-dataset/1", "database": [{"id": "a", "image": ")"
        << RtabmapDir() << R"(/1.jpg", )" << field << R"(}], "queries": []})";
    auto loaded = LoadDataset(directory);
    EXPECT_EQ(loaded.status().code(), StatusCode::kInvalidArgument) << field;
  }
}

TEST_F(EvalTest, DatasetRoundTripsThroughJsonAndCsv) {
  Dataset dataset;
  dataset.name = "tiny";
  dataset.description = "two database frames, two queries";
  dataset.directory = testing::MakeTempDir("placedb-eval-json");
  for (int frame : {1, 2}) {
    Entry entry;
    entry.id = "db," + std::to_string(frame);  // a comma: CSV quoting
    entry.image = RtabmapDir() + "/" + std::to_string(frame) + ".jpg";
    entry.agent = "robot";
    entry.sequence = frame;
    entry.timestamp_ns = frame * 1000;
    entry.boxes = std::vector<DynamicBox>{{0, 0.5f, cv::Rect2f(1, 2, 30, 40)}};
    dataset.database.push_back(entry);
  }
  Entry query;
  query.id = "q1";
  query.image = RtabmapDir() + "/41.jpg";
  query.coverage = 4.0 / 9.0;  // needs all 17 digits in the CSV to come back exactly
  query.ground_truth = {"db,1"};
  dataset.queries.push_back(query);
  query.id = "q2";  // no ground truth, no boxes known
  query.coverage.reset();
  query.ground_truth.clear();
  dataset.queries.push_back(query);

  ASSERT_TRUE(SaveDataset(dataset).ok());
  auto loaded = LoadDataset(dataset.directory);
  ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
  Dataset csv = dataset;
  csv.directory = testing::MakeTempDir("placedb-eval-csv");
  ASSERT_TRUE(SaveDatasetCsv(csv).ok());
  auto loaded_csv = LoadDataset(csv.directory);
  ASSERT_TRUE(loaded_csv.ok()) << loaded_csv.status().ToString();
  for (const Dataset* d : {&*loaded, &*loaded_csv}) {
    ASSERT_EQ(d->database.size(), 2u);
    ASSERT_EQ(d->queries.size(), 2u);
    EXPECT_EQ(d->database[1].id, "db,2");
    EXPECT_EQ(d->database[1].sequence, 2);
    EXPECT_EQ(d->database[1].timestamp_ns, 2000);
    ASSERT_TRUE(d->database[0].boxes.has_value());
    ASSERT_EQ(d->database[0].boxes->size(), 1u);
    EXPECT_EQ((*d->database[0].boxes)[0].rect, cv::Rect2f(1, 2, 30, 40));
    EXPECT_FLOAT_EQ((*d->database[0].boxes)[0].confidence, 0.5f);
    EXPECT_EQ(d->queries[0].ground_truth, std::vector<std::string>{"db,1"});
    EXPECT_TRUE(d->queries[1].ground_truth.empty());
    ASSERT_TRUE(d->queries[0].coverage.has_value());
    EXPECT_EQ(*d->queries[0].coverage, 4.0 / 9.0);
    EXPECT_FALSE(d->queries[1].coverage.has_value());
  }
  EXPECT_EQ(GroundTruthIndices(*loaded), (std::vector<std::vector<int>>{{0}, {}}));

  // Bad datasets are refused with the offending entry named.
  Dataset bad = dataset;
  bad.queries[0].ground_truth = {"nope"};
  Status status = ValidateDataset(bad, false);
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("nope"), std::string::npos) << status.message();
  bad = dataset;
  bad.database[0].image = "/no/such/image.jpg";
  EXPECT_EQ(ValidateDataset(bad, true).code(), StatusCode::kNotFound);
  // A name the file system refuses to look up (longer than a file name may be): not found, not
  // an exception (the fuzzer's find).
  bad.database[0].image = std::string(300, 'x') + ".jpg";
  EXPECT_EQ(ValidateDataset(bad, true).code(), StatusCode::kNotFound);
  bad = dataset;
  bad.database[1].id = bad.database[0].id;
  EXPECT_EQ(ValidateDataset(bad, false).code(), StatusCode::kInvalidArgument);
}

TEST_F(EvalTest, BoxesOutsideTheImageOrOfStaticClassesAreRefused) {
  Dataset dataset;
  dataset.name = "boxes";
  dataset.directory = testing::MakeTempDir("placedb-eval-boxes");
  for (int frame : {1, 2}) {
    Entry entry;
    entry.id = "db" + std::to_string(frame);
    entry.image = RtabmapDir() + "/" + std::to_string(frame) + ".jpg";  // 512x384
    // Every dynamic class, at the image's edges: accepted.
    entry.boxes = std::vector<DynamicBox>{
        {0, 1.0f, cv::Rect2f(-5, -5, 10, 10)}, {1, 1.0f, cv::Rect2f(500, 370, 50, 50)},
        {2, 1.0f, cv::Rect2f(0, 0, 512, 384)}, {3, 1.0f, cv::Rect2f(10, 10, 5, 5)},
        {5, 1.0f, cv::Rect2f(10, 10, 5, 5)},   {7, 1.0f, cv::Rect2f(10, 10, 5, 5)}};
    dataset.database.push_back(entry);
  }
  ASSERT_TRUE(SaveDataset(dataset).ok());
  ASSERT_TRUE(LoadDataset(dataset.directory).ok());

  auto refused = [&](const Dataset& bad, bool check_files) {
    const Status status = ValidateDataset(bad, check_files);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument) << status.ToString();
    EXPECT_NE(status.message().find("id db2"), std::string::npos) << status.message();
    return status.message();
  };
  // A static class (traffic light, 9) as an oracle box: refused, with or without files.
  Dataset bad = dataset;
  (*bad.database[1].boxes)[3].class_id = 9;
  EXPECT_NE(refused(bad, false).find("traffic light"), std::string::npos);
  ASSERT_FALSE(SaveDataset(bad).ok());
  // Entirely right of / below the image: refused once the image's size is known (the files).
  bad = dataset;
  (*bad.database[1].boxes)[1].rect = cv::Rect2f(512, 10, 20, 20);
  EXPECT_TRUE(ValidateDataset(bad, false).ok());
  EXPECT_NE(refused(bad, true).find("outside the 512x384 image"), std::string::npos);
  bad = dataset;
  (*bad.database[1].boxes)[1].rect = cv::Rect2f(10, 384, 20, 20);
  refused(bad, true);
  // Entirely left of / above it: refused even without the files.
  bad = dataset;
  (*bad.database[1].boxes)[0].rect = cv::Rect2f(-30, 10, 30, 20);
  refused(bad, false);
  bad = dataset;
  (*bad.database[1].boxes)[0].rect = cv::Rect2f(10, -20, 30, 20);
  refused(bad, false);
  // And when a saved dataset is loaded.
  bad = dataset;
  (*bad.database[1].boxes)[2].rect = cv::Rect2f(600, 0, 10, 10);
  ASSERT_TRUE(SaveDataset(bad).ok());  // no file check on save
  const auto loaded = LoadDataset(bad.directory);
  ASSERT_FALSE(loaded.ok());
  EXPECT_NE(loaded.status().message().find("database[1] (id db2): boxes[2]"), std::string::npos)
      << loaded.status().ToString();
}

TEST_F(EvalTest, FolderLayoutBecomesADataset) {
  const std::string root = testing::MakeTempDir("placedb-eval-folder");
  fs::create_directories(root + "/database");
  fs::create_directories(root + "/queries");
  for (int frame : {1, 2, 10}) {
    fs::copy_file(RtabmapDir() + "/" + std::to_string(frame) + ".jpg",
                  root + "/database/frame" + std::to_string(frame) + ".jpg");
  }
  fs::copy_file(RtabmapDir() + "/41.jpg", root + "/queries/q41.jpg");
  fs::copy_file(RtabmapDir() + "/60.jpg", root + "/queries/q60.jpg");
  std::ofstream(root + "/truth.csv") << "query,database\nq41.jpg,frame1.jpg\nq41,frame2\n";
  std::ofstream(root + "/boxes.csv") << "image,class,confidence,x,y,width,height\n"
                                     << "queries/q41.jpg,person,0.9,10,20,30,40\n";
  FolderOptions options;
  options.database_dir = root + "/database";
  options.queries_dir = root + "/queries";
  options.ground_truth_csv = root + "/truth.csv";
  options.boxes_csv = root + "/boxes.csv";
  auto dataset = PrepareFolder(options);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  ASSERT_EQ(dataset->database.size(), 3u);
  EXPECT_EQ(dataset->database[2].id, "frame10.jpg");  // natural order
  ASSERT_EQ(dataset->queries.size(), 2u);
  EXPECT_EQ(dataset->queries[0].ground_truth,
            (std::vector<std::string>{"frame1.jpg", "frame2.jpg"}));
  EXPECT_TRUE(dataset->queries[1].ground_truth.empty());
  ASSERT_EQ(dataset->queries[0].boxes->size(), 1u);
  EXPECT_EQ((*dataset->queries[0].boxes)[0].class_id, 0);
  EXPECT_TRUE(ValidateDataset(*dataset, true).ok());
}

// ---- Adapters + runs with known outcomes ----------------------------------------------------

TEST_F(EvalTest, RtabmapLoopMatchesTheRecognitionTest) {
  RtabmapOptions options;
  options.directory = RtabmapDir();
  auto dataset = PrepareRtabmap(options);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  ASSERT_EQ(dataset->database.size(), 40u);
  ASSERT_EQ(dataset->queries.size(), 44u);
  cv::Mat truth = testing::RtabmapGroundTruth();
  for (size_t q = 0; q < dataset->queries.size(); ++q) {
    int expected = 0;
    for (int d = 0; d < 40; ++d) expected += truth.at<uint8_t>(int(q) + 40, d) > 0;
    EXPECT_EQ(int(dataset->queries[q].ground_truth.size()), expected) << "query " << q + 41;
  }

  RunOptions run = SmallRun({500}, {kNoGeom, 6});
  run.boxes = BoxInput::kNone;  // nothing annotated: BoBW+DO sees no dynamic objects
  run.rerank = 0;               // verification of the best candidate only
  const RunResults results = Evaluate(*dataset, run);
  const MethodRun* plain = Find(results, 500, kNoGeom, kBoBW);
  const MethodRun* verified = Find(results, 500, 6, kBoBW);
  ASSERT_TRUE(plain && verified);
  const Summary a = Summarize(results, *plain, PaperBins()[0]);
  const Summary b = Summarize(results, *verified, PaperBins()[0]);
  std::printf("[eval] rtabmap ORB 500: NoGeom %.1f %% (%d/%d), Geo-6 %.1f %%, no-truth %d\n",
              a.accuracy, a.correct, a.queries, b.accuracy, a.no_truth);
  EXPECT_GE(a.accuracy, 80.0);
  EXPECT_GE(b.accuracy, 70.0);
  EXPECT_LE(b.accuracy, a.accuracy);  // verification can only refuse a top-1
  EXPECT_GE(a.recall_at_5, a.recall_at_1);
  // With nothing dynamic, BoBW+DO is BoBW.
  const MethodRun* with_do = Find(results, 500, kNoGeom, kBoBWDO);
  ASSERT_TRUE(with_do);
  for (size_t q = 0; q < plain->queries.size(); ++q) {
    EXPECT_EQ(plain->queries[q].top1, with_do->queries[q].top1);
  }
  EXPECT_EQ(plain->database.encoded_bytes, with_do->database.encoded_bytes);
}

// Issue 29: each database learns its vocabulary from its own stored descriptors (never the
// queries') and is rebuilt with it; the incremental alternative grows words instead.
TEST_F(EvalTest, MapLearnedVocabularyAndIncrementalWordsOnTheRtabmapLoop) {
  RtabmapOptions options;
  options.directory = RtabmapDir();
  auto dataset = PrepareRtabmap(options);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  RunOptions run = SmallRun({500}, {kNoGeom});
  run.boxes = BoxInput::kNone;
  run.short_term = false;

  auto fixed_backend = MakeInProcessBackend(testing::DefaultVocabulary(), run.threads);
  LearningOptions learning;
  learning.threads = 2;
  auto learned_backend = MakeInProcessBackend(testing::DefaultVocabulary(), run.threads, learning);
  auto incremental_backend = MakeInProcessBackend(testing::DefaultVocabulary(), run.threads,
                                                  std::nullopt, IncrementalWordsOptions{});
  auto fixed = RunEvaluation(*dataset, run, *fixed_backend);
  auto learned = RunEvaluation(*dataset, run, *learned_backend);
  auto incremental = RunEvaluation(*dataset, run, *incremental_backend);
  ASSERT_TRUE(fixed.ok() && learned.ok() && incremental.ok());
  const MethodRun* a = Find(*fixed, 500, kNoGeom, kBoBW);
  const MethodRun* b = Find(*learned, 500, kNoGeom, kBoBW);
  const MethodRun* c = Find(*incremental, 500, kNoGeom, kBoBW);
  ASSERT_TRUE(a && b && c);
  EXPECT_EQ(a->database.learned_words, 0u);
  // Learned from exactly what the database stored (all of it: under the sample bound).
  EXPECT_GT(b->database.learned_words, 1000u);
  EXPECT_EQ(b->database.learned_from_descriptors, b->database.descriptors_kept);
  EXPECT_GE(b->database.learned_depth, 4);
  EXPECT_LE(b->database.learned_depth, 6);
  EXPECT_EQ(b->database.places, a->database.places);
  EXPECT_GT(c->database.learned_words, 1000u);
  const double fixed_top1 = Summarize(*fixed, *a, PaperBins()[0]).accuracy;
  const double learned_top1 = Summarize(*learned, *b, PaperBins()[0]).accuracy;
  const double incremental_top1 = Summarize(*incremental, *c, PaperBins()[0]).accuracy;
  std::printf(
      "[eval] rtabmap ORB 500 NoGeom: fixed %.1f %%, learned %.1f %%, incremental %.1f %%\n",
      fixed_top1, learned_top1, incremental_top1);
  EXPECT_GE(fixed_top1, 80.0);
  EXPECT_GE(learned_top1, 80.0);
  EXPECT_GE(incremental_top1, 80.0);
  EXPECT_NE(learned->backend, fixed->backend);
}

Dataset CamVidSubset(int frames_per_sequence) {
  CamVidAdjacencyOptions options;
  options.camvid_dir = CamVidDir();
  options.max_frames_per_sequence = frames_per_sequence;
  auto dataset = PrepareCamVidAdjacency(options);
  EXPECT_TRUE(dataset.ok()) << dataset.status().ToString();
  return dataset.ok() ? std::move(dataset).value() : Dataset{};
}

TEST_F(EvalTest, CamVidAdjacencySubset) {
  const Dataset dataset = CamVidSubset(16);  // 4 sequences x 16 frames
  ASSERT_EQ(dataset.database.size(), 32u);
  ASSERT_EQ(dataset.queries.size(), 32u);
  int with_boxes = 0;
  for (const Entry& query : dataset.queries) {
    ASSERT_FALSE(query.ground_truth.empty()) << query.id;
    for (const std::string& id : query.ground_truth) {
      const auto it = std::find_if(dataset.database.begin(), dataset.database.end(),
                                   [&](const Entry& e) { return e.id == id; });
      ASSERT_NE(it, dataset.database.end());
      EXPECT_EQ(it->agent, query.agent);
      EXPECT_LE(std::llabs(it->sequence - query.sequence), 30);
    }
    // Coverage = the label map's dynamic pixels, as the recognition test computes it.
    auto mask = LoadEntryMask(dataset, query);
    ASSERT_TRUE(mask.ok());
    EXPECT_NEAR(*query.coverage, cv::countNonZero(*mask) / double(mask->total()), 1e-12);
    with_boxes += !query.boxes->empty();
  }
  EXPECT_GT(with_boxes, 10);
  // 0006R0's file names carry an "f": frame numbers still parse.
  EXPECT_TRUE(std::any_of(dataset.database.begin(), dataset.database.end(),
                          [](const Entry& e) { return e.agent == "0006R0" && e.sequence > 0; }));

  RunOptions run = SmallRun({500}, {kNoGeom, 6});
  run.boxes = BoxInput::kNone;
  run.masks = MaskInput::kOracle;
  run.filter = FilterMethod::kExactCoverage;
  run.rerank = 0;  // verification of the best candidate only (DBoW2's loop detector)
  const RunResults results = Evaluate(dataset, run);
  for (const char* method : {kBoBW, kBoBWDO}) {
    const MethodRun* r = Find(results, 500, kNoGeom, method);
    ASSERT_TRUE(r);
    const Summary s = Summarize(results, *r, PaperBins()[0]);
    std::printf("[eval] camvid subset ORB 500 NoGeom %s: %.1f %%\n", method, s.accuracy);
    EXPECT_GE(s.accuracy, 75.0) << method;
  }
  const MethodRun* bobw = Find(results, 500, kNoGeom, kBoBW);
  const MethodRun* with_do = Find(results, 500, kNoGeom, kBoBWDO);
  EXPECT_EQ(bobw->database.descriptors_dropped, 0u);
  EXPECT_GT(with_do->database.descriptors_dropped, 0u);
  EXPECT_LT(with_do->database.descriptors_kept, bobw->database.descriptors_kept);
  EXPECT_LT(with_do->database.encoded_bytes, bobw->database.encoded_bytes);
  // Verification (Geo-6 = exhaustive) only ever refuses a top-1 the ranking chose.
  const MethodRun* geo6 = Find(results, 500, 6, kBoBW);
  ASSERT_TRUE(geo6);
  for (size_t q = 0; q < bobw->queries.size(); ++q) {
    EXPECT_EQ(geo6->queries[q].top1, bobw->queries[q].top1);
    if (geo6->queries[q].correct) {
      EXPECT_TRUE(bobw->queries[q].correct);
    }
  }
}

TEST_F(EvalTest, CamVidStopsGroundTruthIsTheFirstVisit) {
  CamVidStopsOptions options;
  options.camvid_dir = CamVidDir();
  auto dataset = PrepareCamVidStops(options);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  // Seq05VD 02520-02850 (12 frames, 30 apart) and 0016E5 05430-05700 (10 frames).
  ASSERT_EQ(dataset->queries.size(), 22u);
  std::set<std::string> database_ids;
  for (const Entry& e : dataset->database) database_ids.insert(e.id);
  for (const Entry& query : dataset->queries) {
    const bool seq05 = query.agent == "Seq05VD";
    EXPECT_EQ(query.ground_truth.size(), seq05 ? 12u : 9u) << query.id;
    for (const std::string& id : query.ground_truth) {
      EXPECT_TRUE(database_ids.count(id));
      EXPECT_EQ(id.substr(0, 6), query.id.substr(0, 6));
    }
  }
  // Frames between and around the visits are neither database nor queries.
  EXPECT_FALSE(database_ids.count("Seq05VD_f02400"));
  EXPECT_FALSE(database_ids.count("Seq05VD_f02880"));
  EXPECT_FALSE(database_ids.count("0016E5_05250"));
  EXPECT_TRUE(database_ids.count("Seq05VD_f00000"));  // a distractor far from the stop
  EXPECT_TRUE(database_ids.count("0001TP_006690"));
}

// ---- Revisit builder ------------------------------------------------------------------------

TEST_F(EvalTest, RevisitBuilderIsReproducibleAndHitsTheRequestedCoverage) {
  RevisitOptions options;
  options.camvid_dir = CamVidDir();
  options.places = 5;
  options.visits = 2;
  options.min_coverage = 0.15;
  options.max_coverage = 0.35;
  options.seed = 7;
  options.out_dir = testing::MakeTempDir("placedb-eval-revisits-a");
  auto first = BuildRevisits(options);
  ASSERT_TRUE(first.ok()) << first.status().ToString();
  options.out_dir = testing::MakeTempDir("placedb-eval-revisits-b");
  auto second = BuildRevisits(options);
  ASSERT_TRUE(second.ok()) << second.status().ToString();

  ASSERT_EQ(first->dataset.database.size(), 5u);
  ASSERT_EQ(first->dataset.queries.size(), 5u);
  ASSERT_EQ(first->visits.size(), 10u);
  std::set<std::string> backgrounds;
  for (size_t i = 0; i < first->visits.size(); ++i) {
    const VisitInfo& visit = first->visits[i];
    backgrounds.insert(visit.background);
    EXPECT_NEAR(visit.measured_coverage, visit.requested_coverage, 0.02) << visit.id;
    EXPECT_GE(visit.requested_coverage, 0.15);
    EXPECT_LE(visit.requested_coverage, 0.35);
    EXPECT_GT(visit.objects, 0);
  }
  EXPECT_EQ(backgrounds.size(), 5u);
  const Dataset& a = first->dataset;
  const Dataset& b = second->dataset;
  for (int list = 0; list < 2; ++list) {
    const auto& entries_a = list ? a.queries : a.database;
    const auto& entries_b = list ? b.queries : b.database;
    for (size_t i = 0; i < entries_a.size(); ++i) {
      const Entry& ea = entries_a[i];
      // Same seed: byte-identical image and mask files.
      EXPECT_EQ(ReadFileBytes(a.Resolve(ea.image)), ReadFileBytes(b.Resolve(entries_b[i].image)))
          << ea.id;
      EXPECT_EQ(ReadFileBytes(a.Resolve(ea.mask)), ReadFileBytes(b.Resolve(entries_b[i].mask)))
          << ea.id;
      // The written mask is the stated coverage.
      cv::Mat mask = cv::imread(a.Resolve(ea.mask), cv::IMREAD_GRAYSCALE);
      ASSERT_FALSE(mask.empty());
      EXPECT_NEAR(cv::countNonZero(mask) / double(mask.total()), *ea.coverage, 1e-12);
      EXPECT_FALSE(ea.boxes->empty());
      if (list == 1) {
        EXPECT_EQ(ea.ground_truth, std::vector<std::string>{a.database[i].id});
      }
    }
  }
  // The two visits of a place differ (viewpoint, light, objects) but show the same place.
  const std::string v0 = ReadFileBytes(a.Resolve(a.database[0].image));
  const std::string v1 = ReadFileBytes(a.Resolve(a.queries[0].image));
  EXPECT_NE(v0, v1);
  ASSERT_TRUE(SaveDataset(a).ok());
  EXPECT_TRUE(LoadDataset(a.directory).ok());

  // The harness runs on it; with oracle masks BoBW+DO keeps fewer descriptors.
  RunOptions run = SmallRun({500}, {kNoGeom});
  run.boxes = BoxInput::kNone;
  run.masks = MaskInput::kOracle;
  run.filter = FilterMethod::kExactCoverage;
  const RunResults results = Evaluate(a, run);
  const MethodRun* bobw = Find(results, 500, kNoGeom, kBoBW);
  const MethodRun* with_do = Find(results, 500, kNoGeom, kBoBWDO);
  ASSERT_TRUE(bobw && with_do);
  EXPECT_LT(with_do->database.descriptors_kept, bobw->database.descriptors_kept);
}

TEST_F(EvalTest, VideoPeopleAreSegmentedByBackgroundSubtraction) {
  ASSERT_TRUE(fs::exists(kDebianVtestPath)) << "vtest.avi: install the Debian package opencv-doc";
  auto people = SegmentVideoPeople(kDebianVtestPath);
  ASSERT_TRUE(people.ok()) << people.status().ToString();
  EXPECT_GT(people->size(), 100u);  // 53 frames, several people each
  for (const VideoCutout& person : *people) {
    EXPECT_GT(person.rect.height, person.rect.width) << person.name;  // upright
    ASSERT_EQ(person.mask.size(), person.rect.size()) << person.name;
    ASSERT_EQ(person.patch.size(), person.rect.size()) << person.name;
    EXPECT_GE(cv::countNonZero(person.mask), 500) << person.name;
  }
  EXPECT_EQ(SegmentVideoPeople("/no/such/vtest.avi").status().code(), StatusCode::kNotFound);
}

TEST_F(EvalTest, HardRevisitsAreReproducibleAndMarkOnlyThePastedObjects) {
  RevisitOptions options = HardRevisitOptions();
  options.camvid_dir = CamVidDir();
  options.places = 4;
  options.visits = 2;
  options.min_coverage = 0.15;
  options.max_coverage = 0.35;
  options.seed = 11;
  ASSERT_TRUE(fs::exists(options.video_people)) << "vtest.avi: install opencv-doc";
  options.out_dir = testing::MakeTempDir("placedb-eval-hard-a");
  auto first = BuildRevisits(options);
  ASSERT_TRUE(first.ok()) << first.status().ToString();
  options.out_dir = testing::MakeTempDir("placedb-eval-hard-b");
  auto second = BuildRevisits(options);
  ASSERT_TRUE(second.ok()) << second.status().ToString();
  ASSERT_TRUE(SaveDataset(first->dataset).ok());
  ASSERT_TRUE(SaveDataset(second->dataset).ok());
  const Dataset& a = first->dataset;
  const Dataset& b = second->dataset;
  ASSERT_EQ(a.database.size(), 4u);
  ASSERT_EQ(a.queries.size(), 4u);
  ASSERT_EQ(first->visits.size(), 8u);
  // Same options: byte-identical dataset.json, images and masks.
  EXPECT_EQ(ReadFileBytes(a.directory + "/dataset.json"),
            ReadFileBytes(b.directory + "/dataset.json"));
  EXPECT_TRUE(LoadDataset(a.directory).ok());

  auto camvid = ListCamVid(CamVidDir());
  ASSERT_TRUE(camvid.ok());
  int video_objects = 0, objects = 0, unmarked_background_pixels = 0;
  for (size_t v = 0; v < first->visits.size(); ++v) {
    const VisitInfo& visit = first->visits[v];
    const Entry& ea =
        visit.visit == 0 ? a.database[size_t(visit.place)] : a.queries[size_t(visit.place)];
    const Entry& eb =
        visit.visit == 0 ? b.database[size_t(visit.place)] : b.queries[size_t(visit.place)];
    ASSERT_EQ(ea.id, visit.id);
    EXPECT_EQ(ReadFileBytes(a.Resolve(ea.image)), ReadFileBytes(b.Resolve(eb.image))) << ea.id;
    EXPECT_EQ(ReadFileBytes(a.Resolve(ea.mask)), ReadFileBytes(b.Resolve(eb.mask))) << ea.id;
    // Coverage is the pasted objects' (planned on what will be drawn: at most the feathered
    // edge of the last object above the target).
    cv::Mat mask = cv::imread(a.Resolve(ea.mask), cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(mask.empty());
    EXPECT_NEAR(cv::countNonZero(mask) / double(mask.total()), *ea.coverage, 1e-12);
    EXPECT_LE(visit.measured_coverage, visit.requested_coverage + 0.015) << ea.id;
    EXPECT_GT(visit.measured_coverage, 0.05) << ea.id;
    // Boxes: one per visible pasted object, dynamic classes only; the background's own objects
    // are listed in `source`, not as boxes.
    ASSERT_TRUE(ea.boxes.has_value());
    EXPECT_EQ(int(ea.boxes->size()), visit.objects) << ea.id;
    for (const DynamicBox& box : *ea.boxes) {
      EXPECT_TRUE(box.class_id == 0 || box.class_id == 1 || box.class_id == 2) << ea.id;
      // Every box is on marked pixels.
      const cv::Rect r = cv::Rect(box.rect) & cv::Rect(0, 0, mask.cols, mask.rows);
      EXPECT_GT(cv::countNonZero(mask(r)), 0) << ea.id;
    }
    EXPECT_NE(ea.source.find("background objects (static here"), std::string::npos);
    objects += visit.objects;
    video_objects += visit.video_objects;
    // The background's own objects, moved by the visit's viewpoint, are in the picture and NOT
    // in the mask (where nothing pasted stands in front of them).
    const auto frame = std::find_if(camvid->begin(), camvid->end(), [&](const CamVidFrame& f) {
      return f.stem == visit.background;
    });
    ASSERT_NE(frame, camvid->end());
    cv::Mat labels = cv::imread(frame->label_path, cv::IMREAD_GRAYSCALE), warped;
    cv::warpPerspective(labels, warped, visit.homography, labels.size(), cv::INTER_NEAREST,
                        cv::BORDER_REFLECT);
    cv::Mat own =
        (warped == kCamVidCar) | (warped == kCamVidPedestrian) | (warped == kCamVidBicyclist);
    if (visit.background_objects > 0) {
      EXPECT_GE(cv::countNonZero(own), 20) << ea.id;
    }
    unmarked_background_pixels += cv::countNonZero(own & ~mask);
    // Donors from other sequences only.
    const std::string sequence = visit.background.substr(0, visit.background.find('_'));
    const std::string pasted = ea.source.substr(ea.source.find("pasted: "));
    EXPECT_EQ(pasted.find(sequence + "_"), std::string::npos) << ea.source;
  }
  EXPECT_GT(unmarked_background_pixels, 1000);  // with the old oracle it would be 0
  EXPECT_GT(video_objects, 0);                  // both sources
  EXPECT_LT(video_objects, objects);
  // The two visits of a place differ.
  EXPECT_NE(ReadFileBytes(a.Resolve(a.database[0].image)),
            ReadFileBytes(a.Resolve(a.queries[0].image)));

  // Without the video, the hard preset says which package brings it.
  options.video_people = "/no/such/dir/vtest.avi";
  options.out_dir = testing::MakeTempDir("placedb-eval-hard-c");
  auto missing = BuildRevisits(options);
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(missing.status().message().find("opencv-doc"), std::string::npos);
  // --no-vtest: CamVid objects only.
  options.video_people.clear();
  options.places = 2;
  auto camvid_only = BuildRevisits(options);
  ASSERT_TRUE(camvid_only.ok()) << camvid_only.status().ToString();
  for (const VisitInfo& visit : camvid_only->visits) {
    EXPECT_EQ(visit.video_objects, 0);
    EXPECT_GT(visit.objects, 0);
  }
}

// ---- Scoring, empty ground truth, reports ---------------------------------------------------

TEST(EvalScoring, TopOneMustBeTrueAndVerifiedWhenVerificationIsOn) {
  const std::vector<int> truth = {3, 7};
  QueryOutcome o = ScoreQuery({{3, 0.5, false, 9}, {7, 0.4, true, 30}}, truth, false);
  EXPECT_TRUE(o.correct);
  EXPECT_EQ(o.truth_rank, 1);
  o = ScoreQuery({{3, 0.5, false, 9}, {7, 0.4, true, 30}}, truth, true);
  EXPECT_FALSE(o.correct);  // the best candidate failed verification
  o = ScoreQuery({{1, 0.5, true, 40}, {7, 0.4, false, 0}}, truth, true);
  EXPECT_FALSE(o.correct);
  EXPECT_EQ(o.truth_rank, 2);
  o = ScoreQuery({}, truth, false);
  EXPECT_FALSE(o.correct);
  EXPECT_EQ(o.top1, -1);
  o = ScoreQuery({{3, 0.5, true, 40}}, {}, true);  // no ground truth: never "correct"
  EXPECT_FALSE(o.correct);
  EXPECT_EQ(o.truth_rank, 0);
}

TEST(EvalScoring, PairedComparisonCountsDiscordantQueries) {
  RunResults results;
  results.query_coverage = {0.05, 0.15, 0.25, 0.35, 0.45, 0.0};
  results.query_has_truth = {true, true, true, true, true, false};
  MethodRun bobw, with_do;
  for (bool correct : {true, false, false, false, true, false}) {
    bobw.queries.push_back({});
    bobw.queries.back().correct = correct;
  }
  for (bool correct : {true, true, true, true, false, true}) {
    with_do.queries.push_back({});
    with_do.queries.back().correct = correct;
  }
  const PairedComparison all = ComparePaired(results, bobw, with_do, PaperBins()[0]);
  EXPECT_EQ(all.do_only, 3);  // the query without ground truth does not count
  EXPECT_EQ(all.bobw_only, 1);
  EXPECT_NEAR(all.p_value, 2 * (1 + 4) / 16.0, 1e-12);  // 2 P(X <= 1), X ~ B(4, 1/2)
  const PairedComparison above30 = ComparePaired(results, bobw, with_do, PaperBins()[3]);
  EXPECT_EQ(above30.do_only, 1);
  EXPECT_EQ(above30.bobw_only, 1);
  EXPECT_DOUBLE_EQ(above30.p_value, 1.0);
  EXPECT_DOUBLE_EQ(ComparePaired(results, bobw, bobw, PaperBins()[0]).p_value, 1.0);
  EXPECT_NEAR(RelativeChange(42.9, 47.78), 11.38, 0.01);  // the paper's first row
  EXPECT_TRUE(std::isnan(RelativeChange(0, 5)));
}

TEST_F(EvalTest, QueriesWithoutGroundTruthAndReportShapes) {
  // RTAB-Map loop, queries 41-50 + one query with its ground truth removed.
  RtabmapOptions options;
  options.directory = RtabmapDir();
  auto dataset = PrepareRtabmap(options);
  ASSERT_TRUE(dataset.ok());
  dataset->queries.resize(10);
  dataset->queries[0].ground_truth.clear();
  dataset->queries[1].coverage = 0.35;  // lands in every coverage bin
  RunOptions run = SmallRun({300, 500}, {kNoGeom, 2});
  run.boxes = BoxInput::kNone;
  const RunResults results = Evaluate(*dataset, run);
  ASSERT_EQ(results.runs.size(), 8u);  // 2 features x 2 geoms x {BoBW, BoBW+DO}
  const Summary all = Summarize(results, results.runs[0], PaperBins()[0]);
  int with_truth = 0;
  for (const Entry& q : dataset->queries) with_truth += !q.ground_truth.empty();
  EXPECT_EQ(all.queries, with_truth);
  EXPECT_EQ(all.no_truth, 10 - with_truth);
  EXPECT_GE(all.no_truth_accepted, 1);  // no verification: any top-1 is a false positive
  const Summary above30 = Summarize(results, results.runs[0], PaperBins()[3]);
  EXPECT_EQ(above30.queries, 1);

  const std::string dir = testing::MakeTempDir("placedb-eval-report");
  ASSERT_TRUE(WriteReport(results, *dataset, dir, "test").ok());
  const std::vector<std::string> csv = Lines(ReadFileBytes(dir + "/results.csv"));
  ASSERT_EQ(csv.size(), 1 + 8 * 4u);  // header + runs x bins
  const size_t columns = SplitCsvLine(csv[0]).size();
  for (const std::string& line : csv) EXPECT_EQ(SplitCsvLine(line).size(), columns) << line;
  EXPECT_NE(csv[1].find(",NoGeom,"), std::string::npos);
  EXPECT_NE(csv[1].find(",BoBW,All,"), std::string::npos);
  EXPECT_EQ(Lines(ReadFileBytes(dir + "/queries.csv")).size(), 1 + 8 * 10u);

  const std::vector<std::string> md = Lines(ReadFileBytes(dir + "/table3.md"));
  auto header = std::find_if(md.begin(), md.end(), [](const std::string& line) {
    return line.rfind("| keys | Geom | All BoBW | All BoBW+DO | +- |", 0) == 0;
  });
  ASSERT_NE(header, md.end());
  const auto cells = [](const std::string& line) {
    return std::count(line.begin(), line.end(), '|') - 1;
  };
  EXPECT_EQ(cells(*header), 2 + 4 * 3);
  EXPECT_EQ(cells(*(header + 1)), 2 + 4 * 3);
  for (int row = 0; row < 4; ++row) {  // 300/500 x NoGeom/Geo-2
    const std::string& line = *(header + 2 + row);
    EXPECT_EQ(cells(line), 2 + 4 * 3) << line;
    EXPECT_EQ(line.rfind(row < 2 ? "| 300 |" : "| 500 |", 0), 0u) << line;
  }
  for (const char* png :
       {"fig5_accuracy_vs_coverage.png", "fig6_database_size.png", "fig7_latency.png"}) {
    cv::Mat image = cv::imread(dir + "/" + png);
    ASSERT_FALSE(image.empty()) << png;
    EXPECT_GE(image.cols, 600);
    EXPECT_GE(image.rows, 300);
  }
}

// ---- Detector boxes -------------------------------------------------------------------------

TEST_F(EvalTest, DetectorBoxesAreCachedAndFilteredByConfidence) {
  std::string model = std::string(PLACEDB_MODELS_DIR) + "/yolox_nano.onnx";
  if (!fs::exists(model)) model = testing::SharedDir() + "/models/yolox_nano.onnx";
  ASSERT_TRUE(fs::exists(model)) << "no YOLOX-Nano model (tools/install_models.sh)";
  const Dataset dataset = CamVidSubset(4);  // 8 database frames, 8 queries
  RunOptions run = SmallRun({300}, {kNoGeom});
  run.boxes = BoxInput::kDetector;
  run.confidences = {0.2f, 0.4f};
  run.detector = YoloxNanoConfig(fs::path(model).parent_path().string());
  run.detections_cache = testing::MakeTempDir("placedb-eval-detections") + "/cache.json";
  auto inputs = PrepareInputs(dataset, run);
  ASSERT_TRUE(inputs.ok()) << inputs.status().ToString();
  ASSERT_TRUE(fs::exists(run.detections_cache));
  int boxes = 0;
  for (const DynamicObjects& d : inputs->database_dynamic) {
    for (const DynamicBox& box : d.boxes) {
      EXPECT_GE(box.confidence, 0.2f);  // detected at the lowest confidence asked
      ++boxes;
    }
  }
  EXPECT_GT(boxes, 5);  // CamVid streets: cars and people
  EXPECT_GT(inputs->detect_mean_ms, 0);

  // A second run reads the cache: no model needed.
  RunOptions cached = run;
  cached.detector.model_path = "/no/such/dir/yolox_nano.onnx";  // same model name
  auto again = PrepareInputs(dataset, cached);
  ASSERT_TRUE(again.ok()) << again.status().ToString();
  for (size_t i = 0; i < dataset.database.size(); ++i) {
    ASSERT_EQ(again->database_dynamic[i].boxes.size(), inputs->database_dynamic[i].boxes.size());
  }
  // A higher threshold than cached is served from the cache; a lower one needs the detector.
  cached.confidences = {0.3f};
  EXPECT_TRUE(PrepareInputs(dataset, cached).ok());
  cached.confidences = {0.1f};
  EXPECT_FALSE(PrepareInputs(dataset, cached).ok());

  // One BoBW+DO run per confidence; the stricter one keeps at least as many descriptors.
  const RunResults results = Evaluate(dataset, run);
  ASSERT_EQ(results.runs.size(), 3u);  // BoBW, DO @0.2, DO @0.4
  EXPECT_EQ(results.runs[1].confidence, 0.2f);
  EXPECT_EQ(results.runs[2].confidence, 0.4f);
  EXPECT_GT(results.runs[1].database.descriptors_dropped, 0u);
  EXPECT_LE(results.runs[2].database.descriptors_dropped,
            results.runs[1].database.descriptors_dropped);
  const std::string md = MarkdownReport(results, "detector");
  EXPECT_NE(md.find("BoBW+DO @0.20"), std::string::npos);
  EXPECT_NE(md.find("BoBW+DO @0.40"), std::string::npos);
}

TEST_F(EvalTest, DetectionCacheIsKeyedByImageContent) {
  std::string model = std::string(PLACEDB_MODELS_DIR) + "/yolox_nano.onnx";
  if (!fs::exists(model)) model = testing::SharedDir() + "/models/yolox_nano.onnx";
  ASSERT_TRUE(fs::exists(model)) << "no YOLOX-Nano model (tools/install_models.sh)";
  // Three entries, two of them the same bytes at two paths.
  auto make = [](const std::string& directory) {
    Dataset dataset;
    dataset.name = "cache";
    dataset.directory = directory;
    fs::create_directories(directory + "/a");
    fs::create_directories(directory + "/b");
    const std::string street = CamVidDir() + "/images/0016E5_05130.jpg";
    fs::copy_file(street, directory + "/a/street.jpg");
    fs::copy_file(street, directory + "/b/same_bytes.jpg");
    fs::copy_file(CamVidDir() + "/images/Seq05VD_f01920.jpg", directory + "/a/other.jpg");
    for (const char* image : {"a/street.jpg", "b/same_bytes.jpg", "a/other.jpg"}) {
      Entry entry;
      entry.id = image;
      entry.image = image;
      dataset.database.push_back(entry);
    }
    return dataset;
  };
  const Dataset first = make(testing::MakeTempDir("placedb-eval-cache-a"));
  RunOptions run = SmallRun({300}, {kNoGeom});
  run.boxes = BoxInput::kDetector;
  run.confidences = {0.2f};
  run.detector = YoloxNanoConfig(fs::path(model).parent_path().string());
  run.detections_cache = testing::MakeTempDir("placedb-eval-cache") + "/cache.json";
  std::vector<std::string> logged;
  run.log = [&](const std::string& line) { logged.push_back(line); };
  auto inputs = PrepareInputs(first, run);
  ASSERT_TRUE(inputs.ok()) << inputs.status().ToString();
  // Two distinct contents were detected (and said so), not three paths.
  EXPECT_NE(std::find_if(logged.begin(), logged.end(),
                         [](const std::string& line) {
                           return line.rfind("detection: 2/2 images, mean ", 0) == 0;
                         }),
            logged.end());
  std::ifstream in(run.detections_cache);
  const nlohmann::json cache = nlohmann::json::parse(in);
  ASSERT_EQ(cache["images"].size(), 2u);
  for (const auto& [key, value] : cache["images"].items()) {
    EXPECT_EQ(key.size(), 16u) << key;  // 64-bit hash in hex, no path
    EXPECT_EQ(key.find('/'), std::string::npos) << key;
  }
  EXPECT_EQ(inputs->database_dynamic[0].boxes.size(), inputs->database_dynamic[1].boxes.size());
  EXPECT_GT(inputs->database_dynamic[0].boxes.size(), 0u);

  // The same bytes elsewhere: served from the cache, no detector needed.
  const Dataset moved = make(testing::MakeTempDir("placedb-eval-cache-b"));
  RunOptions cached = run;
  cached.detector.model_path = "/no/such/dir/yolox_nano.onnx";  // same model name
  logged.clear();
  auto again = PrepareInputs(moved, cached);
  ASSERT_TRUE(again.ok()) << again.status().ToString();
  EXPECT_TRUE(logged.empty());
  for (size_t i = 0; i < moved.database.size(); ++i) {
    ASSERT_EQ(again->database_dynamic[i].boxes.size(), inputs->database_dynamic[i].boxes.size());
  }
  // Changed bytes at a cached path: a miss (the detector is needed, and here it cannot load).
  fs::copy_file(CamVidDir() + "/images/0001TP_006690.jpg", moved.Resolve("a/other.jpg"),
                fs::copy_options::overwrite_existing);
  EXPECT_FALSE(PrepareInputs(moved, cached).ok());
}

// ---- Live server ----------------------------------------------------------------------------

TEST_F(EvalTest, ServerBackendAgreesWithInProcess) {
  spdlog::set_level(spdlog::level::warn);
  server::ServerConfig config;
  config.listen = "127.0.0.1:0";
  config.metrics_listen = "";
  config.console_listen = "";
  config.data_dir = testing::MakeTempDir("placedb-eval-server") + "/data";
  config.threads = 2;
  config.log_level = "warn";
  config.vocabularies = {{"default", testing::DefaultVocabularyPath()}};
  server::ServerDeps deps;
  deps.vocabularies.emplace("default", testing::DefaultVocabulary());
  auto started = server::Server::Start(config, deps);
  ASSERT_TRUE(started.ok()) << started.status().ToString();
  const std::string address = "127.0.0.1:" + std::to_string((*started)->port());

  const Dataset dataset = CamVidSubset(10);  // 20 database frames, 20 queries
  RunOptions run = SmallRun({500}, {kNoGeom, 2});
  run.boxes = BoxInput::kOracle;
  run.masks = MaskInput::kOracle;
  run.filter = FilterMethod::kExactCoverage;
  // The shape prior needs no pixels, so both sides refine alike (GrabCut would make the server
  // decode colour, whose grayscale conversion is not libjpeg's grayscale decode that ORB sees
  // in-process); the short-term tier and re-ranking run on both sides as configured.
  run.refinement = BoxRefinement::kShape;
  const RunResults local = Evaluate(dataset, run);
  std::vector<std::string> logged;
  auto remote_backend = MakeServerBackend(address, testing::DefaultVocabulary(),
                                          [&](const std::string& line) { logged.push_back(line); });
  ASSERT_TRUE(remote_backend.ok()) << remote_backend.status().ToString();
  auto remote = RunEvaluation(dataset, run, **remote_backend);
  ASSERT_TRUE(remote.ok()) << remote.status().ToString();
  EXPECT_TRUE(logged.empty());  // same vocabulary
  ASSERT_EQ(remote->runs.size(), local.runs.size());
  for (size_t r = 0; r < local.runs.size(); ++r) {
    const MethodRun& l = local.runs[r];
    const MethodRun& s = remote->runs[r];
    EXPECT_EQ(l.database.places, s.database.places);
    EXPECT_EQ(l.database.descriptors_kept, s.database.descriptors_kept);
    EXPECT_EQ(l.database.descriptors_dropped, s.database.descriptors_dropped);
    EXPECT_GT(s.database.disk_bytes, 0u);
    ASSERT_EQ(l.queries.size(), s.queries.size());
    for (size_t q = 0; q < l.queries.size(); ++q) {
      EXPECT_EQ(l.queries[q].top1, s.queries[q].top1) << l.method << " query " << q;
      EXPECT_EQ(l.queries[q].correct, s.queries[q].correct) << l.method << " query " << q;
      EXPECT_EQ(l.queries[q].inliers, s.queries[q].inliers) << l.method << " query " << q;
    }
  }
  (*started)->Shutdown();
}

// --server against a mutual-TLS server: the harness presents its client certificate (the CLI's
// connection code, --tls --ca-cert --cert --key).
TEST_F(EvalTest, ServerBackendPresentsItsClientCertificate) {
  spdlog::set_level(spdlog::level::warn);
  const testing::TestCertificates& certs = testing::SharedTestCertificates();
  server::ServerConfig config;
  config.listen = "127.0.0.1:0";
  config.metrics_listen = "";
  config.console_listen = "";
  config.data_dir = testing::MakeTempDir("placedb-eval-server") + "/data";
  config.threads = 2;
  config.vocabularies = {{"default", testing::DefaultVocabularyPath()}};
  config.tls = {.cert_file = certs.server_cert,
                .key_file = certs.server_key,
                .client_ca_file = certs.ca_cert};
  server::ServerDeps deps;
  deps.vocabularies.emplace("default", testing::DefaultVocabulary());
  auto started = server::Server::Start(config, deps);
  ASSERT_TRUE(started.ok()) << started.status().ToString();
  client::ConnectionOptions connection;
  connection.address = "localhost:" + std::to_string((*started)->port());
  connection.tls = true;
  connection.ca_cert = certs.ca_cert;
  auto refused = MakeServerBackend(connection, testing::DefaultVocabulary(), nullptr);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kFailedPrecondition);
  connection.cert = certs.client_cert;
  connection.key = certs.client_key;
  auto backend = MakeServerBackend(connection, testing::DefaultVocabulary(), nullptr);
  EXPECT_TRUE(backend.ok()) << backend.status().ToString();
}

}  // namespace
}  // namespace placedb::eval
