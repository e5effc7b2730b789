// Issue 16's agreement test: CamVid sequences ingested through a real server with server-side
// detection (YOLOX-Nano), one map per sequence, and the maps' dynamic-object statistics compared
// with the label maps (Car, Pedestrian, Bicyclist pixels: testing::CamVidDynamicMask).
//
// What is asserted, and why it is not a constant fitted to the result:
//  1. The statistics are exact: each place's stored coverage equals the coverage of the region
//     the server filtered with (its boxes_used, refined by the map's default shape prior and
//     rasterized by the filter's own functions), each class's frames equal the frames whose
//     boxes have that class, and the map aggregate equals the sum of its places.
//  2. Their difference from the labels is the detector's error, nothing more: per frame,
//     |stored - label| <= |detected \ labelled| + |labelled \ detected| (over the image), so
//     over a sequence the mean absolute difference is at most
//     (1 - P) x mean stored + (1 - R) x mean label, with R and P the detector's pixel recall and
//     precision measured here on the same frames.
//  3. The stored coverage tracks the labels: the Pearson correlation over all frames is
//     significant at 1 % (t = r sqrt((n - 2) / (1 - r^2)) > 2.6).
// Per-class frame recall and precision (frames where a class was counted vs frames where its
// label is present) are printed, not asserted: small far objects are labelled but not
// detectable, which the pixel recall already accounts for.
//
// With PLACEDB_DYNAMICS_DOC_DIR set, the sample table (`placedb dynamics`) and chart
// (`--png`) of a map holding all four sequences ("camvid", one agent and weekday per sequence)
// are written there (docs/dynamics.md shows them).
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "client/cli.h"
#include "core/filter/box_masks.h"
#include "core/filter/dynamic_filter.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

namespace fs = std::filesystem;

constexpr int kFramesPerSequence = 40;
// CamVid has no wall clock: the frames of sequence k are placed on weekday k (Monday 2026-11-23
// onwards), spread evenly from 07:00 to 19:00 UTC, so the hour histogram has something to show.
constexpr int64_t kMonday20261116Ns = 1'794'787'200LL * 1'000'000'000LL;

std::string ModelPath() {
#ifdef PLACEDB_MODELS_DIR
  const std::string installed = std::string(PLACEDB_MODELS_DIR) + "/yolox_nano.onnx";
  if (fs::exists(installed)) return installed;
#endif
  return testing::SharedDir() + "/models/yolox_nano.onnx";
}

// The frames' groups of COCO classes and the CamVid labels they correspond to.
struct ClassGroup {
  const char* name;
  std::vector<int> coco;  // counted when any of these is among the frame's classes
  std::vector<int> camvid;
};
const ClassGroup kGroups[] = {
    {"people (person ~ Pedestrian, Bicyclist)", {0}, {9, 10}},
    {"vehicles (car, bus, truck ~ Car)", {2, 5, 7}, {8}},
    {"bicycle ~ Bicyclist", {1}, {10}},
};

struct FrameResult {
  double label = 0;     // share of labelled dynamic pixels
  double detected = 0;  // share of the server's filtered region (from its boxes_used)
  double stored = 0;    // the place's stored mean coverage
  double overlap = 0;   // share of pixels both labelled and detected
  bool label_present[3] = {false, false, false};
  bool class_seen[3] = {false, false, false};
};

double Mean(const std::vector<double>& values) {
  double sum = 0;
  for (double v : values) sum += v;
  return values.empty() ? 0 : sum / double(values.size());
}

std::string Ratio(uint64_t part, uint64_t whole) {
  if (whole == 0) return "-";
  char text[16];
  std::snprintf(text, sizeof text, "%.3f", double(part) / double(whole));
  return text;
}

double Pearson(const std::vector<double>& a, const std::vector<double>& b) {
  const double ma = Mean(a), mb = Mean(b);
  double sab = 0, saa = 0, sbb = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    sab += (a[i] - ma) * (b[i] - mb);
    saa += (a[i] - ma) * (a[i] - ma);
    sbb += (b[i] - mb) * (b[i] - mb);
  }
  return saa > 0 && sbb > 0 ? sab / std::sqrt(saa * sbb) : 0;
}

// The server's filtered region for a frame without depth on a default map: its boxes_used,
// narrowed by the shape prior (box_masks.h), rasterized as the filter does.
cv::Mat ServerRegion(const v1::IngestResponse& response, int width, int height) {
  DynamicObjects objects;
  for (const v1::UsedBox& box : response.boxes_used()) {
    objects.boxes.push_back(
        {box.class_id(), box.confidence(),
         cv::Rect2f(box.rect().x(), box.rect().y(), box.rect().width(), box.rect().height())});
  }
  if (objects.boxes.empty()) return cv::Mat::zeros(height, width, CV_8U);
  auto refined = RefineBoxesToMasks(objects, cv::Mat(), width, height, BoxRefinementConfig{});
  EXPECT_TRUE(refined.ok()) << refined.status().ToString();
  return RasterizeDynamicRegion(refined.ok() ? refined->objects : objects, width, height);
}

class DynamicsCamVidTest : public ServerTest {
 protected:
  int Cli(const std::vector<std::string>& args, std::string* out) {
    std::vector<std::string> full = {"placedb", "--address",
                                     "127.0.0.1:" + std::to_string(server_->port())};
    full.insert(full.end(), args.begin(), args.end());
    std::vector<const char*> argv;
    for (const std::string& a : full) argv.push_back(a.c_str());
    std::ostringstream o, e;
    std::istringstream in;
    client::CliIo io{o, e, in};
    const int code = client::RunCli(int(argv.size()), argv.data(), io);
    *out = o.str();
    EXPECT_EQ(code, 0) << e.str();
    return code;
  }
};

TEST_F(DynamicsCamVidTest, StatisticsAgreeWithTheLabelMapsWithinTheDetectorsError) {
  const std::string model = ModelPath();
  ASSERT_TRUE(fs::exists(model)) << model << " is required (tools/install_models.sh)";
  std::map<std::string, std::vector<testing::CamVidFrame>> sequences;
  for (const testing::CamVidFrame& f : testing::CamVidFrames()) sequences[f.sequence].push_back(f);
  ASSERT_EQ(sequences.size(), 4u) << "CamVid missing from " << testing::SharedDir();

  ServerConfig config = Config();
  config.detector.model = model;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);

  std::vector<double> all_label, all_stored;
  std::vector<v1::Observation> every_sequence;  // for the sample map "camvid"
  int weekday = 0;
  std::printf(
      "  sequence  frames  label mean  stored mean  MAD    bound  pixel R  pixel P  corr\n");
  for (const auto& [name, frames] : sequences) {
    std::string map = name;
    for (char& c : map) c = char(std::tolower(static_cast<unsigned char>(c)));
    map = "camvid-" + map;
    CreateMap(map, server_boxes);
    std::vector<testing::CamVidFrame> chosen;
    std::vector<v1::Observation> observations;
    for (int i = 0; i < kFramesPerSequence && i < int(frames.size()); ++i) {
      chosen.push_back(frames[size_t(i) * frames.size() / kFramesPerSequence]);
      v1::Observation o = JpegObservation(chosen.back().image_path, name, uint64_t(i + 1));
      o.set_timestamp_ns(kMonday20261116Ns + weekday * 86'400'000'000'000LL +
                         7 * 3'600'000'000'000LL +
                         i * (12 * 3'600'000'000'000LL) / kFramesPerSequence);
      observations.push_back(std::move(o));
    }
    ++weekday;
    every_sequence.insert(every_sequence.end(), observations.begin(), observations.end());
    const IngestOutcome ingest = IngestAll(stub_.get(), map, observations);
    ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
    ASSERT_EQ(ingest.responses.size(), chosen.size());

    std::vector<FrameResult> results;
    uint64_t class_frames[3] = {0, 0, 0};
    std::map<int, uint64_t> frames_by_class;  // from the responses' boxes
    size_t invalid = 0;
    for (size_t i = 0; i < chosen.size(); ++i) {
      const v1::IngestResponse& response = ingest.responses[i];
      ASSERT_FALSE(response.has_error()) << response.error().message();
      std::set<int> classes;
      for (const v1::UsedBox& box : response.boxes_used()) classes.insert(box.class_id());
      if (!response.stored()) {
        ++invalid;
        continue;
      }
      for (int c : classes) ++frames_by_class[c];
      const cv::Mat label = testing::CamVidDynamicMask(chosen[i]);
      const cv::Mat labels = cv::imread(chosen[i].label_path, cv::IMREAD_GRAYSCALE);
      const cv::Mat region = ServerRegion(response, label.cols, label.rows);
      const double pixels = double(label.total());
      FrameResult r;
      r.label = cv::countNonZero(label) / pixels;
      r.detected = cv::countNonZero(region) / pixels;
      r.overlap = cv::countNonZero(label & region) / pixels;
      grpc::ClientContext context;
      v1::GetPlaceRequest get;
      get.set_map(map);
      get.set_place_id(response.place_id());
      v1::Place place;
      ASSERT_TRUE(stub_->GetPlace(&context, get, &place).ok());
      ASSERT_EQ(place.dynamics().observations(), 1u);
      r.stored = place.dynamics().mean_coverage();
      // 1. Exact: parts per million of the very region the filter used.
      EXPECT_NEAR(r.stored, r.detected, 1e-6) << name << " frame " << chosen[i].frame;
      for (int g = 0; g < 3; ++g) {
        for (int id : kGroups[g].camvid) r.label_present[g] |= cv::countNonZero(labels == id) > 0;
        for (int id : kGroups[g].coco) r.class_seen[g] |= classes.count(id) > 0;
        class_frames[g] += r.class_seen[g];
      }
      results.push_back(r);
    }

    // 1. The map aggregate and the invalid frames' aggregate.
    v1::GetDynamicsRequest request;
    request.set_map(map);
    v1::GetDynamicsResponse dynamics;
    {
      grpc::ClientContext context;
      ASSERT_TRUE(stub_->GetDynamics(&context, request, &dynamics).ok());
    }
    ASSERT_EQ(dynamics.map().observations(), results.size());
    EXPECT_EQ(dynamics.invalid().observations(), invalid);
    std::vector<double> label, stored, detected;
    double overlap = 0, label_sum = 0, detected_sum = 0;
    for (const FrameResult& r : results) {
      label.push_back(r.label);
      stored.push_back(r.stored);
      detected.push_back(r.detected);
      overlap += r.overlap;
      label_sum += r.label;
      detected_sum += r.detected;
    }
    EXPECT_NEAR(dynamics.map().mean_coverage(), Mean(stored), 1e-6) << name;
    std::map<int, uint64_t> aggregate_classes;
    for (const v1::DynamicClassCount& c : dynamics.map().classes()) {
      aggregate_classes[c.class_id()] = c.frames();
    }
    EXPECT_EQ(aggregate_classes, frames_by_class) << name;

    // 2. The difference from the labels is bounded by the detector's measured pixel error.
    const double recall = label_sum > 0 ? overlap / label_sum : 1;
    const double precision = detected_sum > 0 ? overlap / detected_sum : 1;
    double mad = 0;
    for (const FrameResult& r : results) mad += std::abs(r.stored - r.label);
    mad /= double(results.size());
    const double bound = (1 - precision) * Mean(detected) + (1 - recall) * Mean(label);
    EXPECT_LE(mad, bound + 1e-6) << name;
    std::printf("  %-8s  %4zu    %6.2f%%     %6.2f%%     %5.2f%%  %5.2f%%  %.3f    %.3f    %.3f\n",
                name.c_str(), results.size(), 100 * Mean(label), 100 * Mean(stored), 100 * mad,
                100 * bound, recall, precision, Pearson(label, stored));
    for (int g = 0; g < 3; ++g) {
      int present = 0, seen_and_present = 0;
      for (const FrameResult& r : results) {
        present += r.label_present[g];
        seen_and_present += r.label_present[g] && r.class_seen[g];
      }
      std::printf("    %-42s frames seen %3llu, labelled %3d, frame recall %s, precision %s\n",
                  kGroups[g].name, static_cast<unsigned long long>(class_frames[g]), present,
                  Ratio(seen_and_present, uint64_t(present)).c_str(),
                  Ratio(seen_and_present, class_frames[g]).c_str());
    }
    all_label.insert(all_label.end(), label.begin(), label.end());
    all_stored.insert(all_stored.end(), stored.begin(), stored.end());
  }

  // 3. The stored coverage tracks the labels over all frames.
  const double r = Pearson(all_label, all_stored);
  const double n = double(all_label.size());
  const double t = r * std::sqrt((n - 2) / std::max(1e-12, 1 - r * r));
  double mad = 0;
  for (size_t i = 0; i < all_label.size(); ++i) mad += std::abs(all_label[i] - all_stored[i]);
  std::printf(
      "  all: %zu frames, mean absolute difference %.2f%% of the image, correlation %.3f "
      "(t = %.1f)\n",
      all_label.size(), 100 * mad / n, r, t);
  EXPECT_GT(t, 2.6) << "stored coverage does not track the labelled coverage";

  // The sample table and chart: every sequence in one map.
  const std::string sample_map = "camvid";
  CreateMap(sample_map, server_boxes);
  const IngestOutcome sample = IngestAll(stub_.get(), sample_map, every_sequence);
  ASSERT_TRUE(sample.status.ok()) << sample.status.error_message();
  std::string table;
  Cli({"dynamics", sample_map, "--limit", "8"}, &table);
  std::string people;
  Cli({"dynamics", sample_map, "--class", "person", "--limit", "5"}, &people);
  const char* doc_dir = std::getenv("PLACEDB_DYNAMICS_DOC_DIR");
  const std::string dir = doc_dir && *doc_dir ? doc_dir : root_;
  const std::string png = dir + "/camvid.png";
  std::string ignored;
  Cli({"dynamics", sample_map, "--limit", "8", "--png", png}, &ignored);
  EXPECT_FALSE(cv::imread(png).empty()) << png;
  std::printf(
      "\n$ placedb dynamics %s --limit 8\n%s\n$ placedb dynamics %s --class person "
      "--limit 5\n%s",
      sample_map.c_str(), table.c_str(), sample_map.c_str(), people.c_str());
  if (doc_dir && *doc_dir) {
    std::ofstream(dir + "/camvid-table.txt")
        << "$ placedb dynamics " << sample_map << " --limit 8\n"
        << table << "\n$ placedb dynamics " << sample_map << " --class person --limit 5\n"
        << people;
  }
}

}  // namespace
}  // namespace placedb::server_testing
