// Durable maps on a real RocksDB in a temp directory, with real frames.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <mutex>
#include <thread>

#include "core/search/place_index.h"
#include "core/storage/codec.h"
#include "core/storage/map_store.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace fs = std::filesystem;

namespace placedb {
namespace {

using testing::DefaultVocabulary;
using testing::SiftVocabulary;

Observation RtabmapFrame(int index) {
  Observation observation;
  observation.image = testing::ReadGray(testing::RtabmapFramePath(index));
  observation.metadata.agent_id = "robot-" + std::to_string(index % 3);
  observation.metadata.sequence = uint64_t(index);
  observation.metadata.timestamp_ns = int64_t(index) * 500'000'000;
  if (index % 4 == 0) {
    observation.metadata.pose = Pose{{double(index), 2.0, -1.5}, {0, 0, 0.38268343, 0.92387953}};
  }
  return observation;
}

// Every query's full ranked list, for exact before/after comparisons.
struct Ranked {
  std::vector<PlaceId> ids;
  std::vector<double> scores;
  std::vector<int> inliers;
  bool operator==(const Ranked&) const = default;
};

std::vector<Ranked> QueryAll(const PlaceMap& map, const std::vector<Observation>& queries) {
  std::vector<Ranked> out;
  for (const Observation& query : queries) {
    auto result = map.Query(query, {});
    EXPECT_TRUE(result.ok()) << result.status().ToString();
    Ranked ranked;
    if (result.ok()) {
      for (const Match& match : result->matches) {
        ranked.ids.push_back(match.place);
        ranked.scores.push_back(match.score);
        ranked.inliers.push_back(match.inliers);
      }
    }
    out.push_back(ranked);
  }
  return out;
}

// Little-endian bytes, to hand-build values in the formats older versions wrote.
struct Bytes {
  std::string s;
  template <typename T>
  Bytes& Put(T v) {
    s.append(reinterpret_cast<const char*>(&v), sizeof v);
    return *this;
  }
  Bytes& Varint(uint64_t v) {
    for (; v >= 0x80; v >>= 7) s.push_back(char(uint8_t(v) | 0x80));
    s.push_back(char(v));
    return *this;
  }
  Bytes& Str(const std::string& text) {
    Varint(text.size());
    s += text;
    return *this;
  }
};

// A map config exactly as the encoder wrote it before RGB-D (format 1: no feature_type, sift,
// depth or loop_closure).
constexpr char kFormat1Config[] =
    R"({"dynamic_classes":[0,2],"filter":{"method":"exact_coverage","place_threshold":25,)"
    R"("sensitivity_threshold":0.25},"format":1,"min_box_confidence":0.30000001192092896,)"
    R"("orb":{"edge_threshold":31,"fast_threshold":20,"levels":8,"max_features":700,)"
    R"("patch_size":31,"scale_factor":1.2000000476837158},"scoring":"l1",)"
    R"("verification":{"candidates":0,"levels_up":2,"max_hamming":64,"min_inliers":15,)"
    R"("mode":"exhaustive","ransac_confidence":0.99,"ransac_max_iterations":500,)"
    R"("ransac_threshold_px":2.0,"ratio":0.800000011920929}})";

// kFormat1Config as format 2 with `extra` members added.
std::string Format2ConfigWith(const std::string& extra) {
  std::string json = kFormat1Config;
  json.replace(json.find(R"("format":1)"), 10, R"("format":2)");
  json.pop_back();  // the closing brace
  return json + "," + extra + "}";
}

class StorageTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    vocabulary_ = DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
    root_ = testing::MakeTempDir("placedb-storage");
  }

  std::unique_ptr<DataDirectory> OpenDir(StorageOptions options = {}) {
    auto dir = DataDirectory::Open(root_ + "/data", options);
    EXPECT_TRUE(dir.ok()) << dir.status().ToString();
    return dir.ok() ? std::move(dir).value() : nullptr;
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
  std::string root_;
};

TEST(Codec, RoundTripsEveryRecordType) {
  PlaceRecord record;
  record.id = 77;
  record.metadata = {"agent-ä", 12345678901ull, -42, Pose{{1, 2, 3}, {0.1, 0.2, 0.3, 0.9}}};
  record.counts = {900, 120, 780, 0.137};
  record.boxes_used = {{0, 0.5f, cv::Rect2f(1, 2, 30, 40)}, {2, 0.9f, cv::Rect2f(5, 6, 7, 8)}};
  auto decoded = DecodePlaceRecord(EncodePlaceRecord(record));
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->id, record.id);
  EXPECT_EQ(decoded->metadata, record.metadata);
  EXPECT_EQ(decoded->counts.static_, 780u);
  ASSERT_EQ(decoded->boxes_used.size(), 2u);
  EXPECT_EQ(decoded->boxes_used[1].rect, record.boxes_used[1].rect);

  BowVector bow = {{3, 0.25f}, {17, 0.5f}, {4000000, 0.25f}};
  auto bow_decoded = DecodeBow(EncodeBow(bow));
  ASSERT_TRUE(bow_decoded.ok());
  EXPECT_EQ(*bow_decoded, bow);

  FeatureSet features = testing::ExtractFile(testing::RtabmapFramePath(1), 300);
  DirectIndex direct;
  direct.levels_up = 2;
  direct.node_ids = {5, 9};
  direct.offsets = {0, 2, 3};
  direct.feature_ids = {0, 7, 3};
  FeatureSet features_out;
  DirectIndex direct_out;
  ASSERT_TRUE(DecodeFeatures(EncodeFeatures(features, direct), &features_out, &direct_out).ok());
  EXPECT_EQ(features_out.keypoints, features.keypoints);
  EXPECT_EQ(features_out.descriptors, features.descriptors);
  EXPECT_EQ(direct_out, direct);

  DatabaseConfig config;
  config.filter.method = FilterMethod::kExactCoverage;
  config.verification.mode = VerificationMode::kDirectIndex;
  config.dynamic_classes = {0, 2};
  auto config_out = DecodeDatabaseConfig(EncodeDatabaseConfig(config));
  ASSERT_TRUE(config_out.ok()) << config_out.status().ToString();
  EXPECT_EQ(config_out->filter.method, FilterMethod::kExactCoverage);
  EXPECT_EQ(config_out->verification.mode, VerificationMode::kDirectIndex);
  EXPECT_EQ(config_out->dynamic_classes, config.dynamic_classes);
}

TEST(Codec, DamagedBytesAreCorruptionNotACrash) {
  PlaceRecord record;
  record.id = 5;
  record.counts = {10, 0, 10, 0};
  const std::string good = EncodePlaceRecord(record);
  for (size_t cut = 0; cut < good.size(); ++cut) {
    auto decoded = DecodePlaceRecord(std::string_view(good).substr(0, cut));
    ASSERT_FALSE(decoded.ok());
    EXPECT_EQ(decoded.status().code(), StatusCode::kCorruption);
  }
  std::string wrong_version = good;
  wrong_version[0] = 9;
  EXPECT_NE(DecodePlaceRecord(wrong_version).status().message().find("version"), std::string::npos);
  // A huge claimed count must not allocate or read past the end.
  std::string bow = {1, char(0xFF), char(0xFF), char(0xFF), char(0xFF), 0x0F};
  EXPECT_EQ(DecodeBow(bow).status().code(), StatusCode::kCorruption);
  EXPECT_EQ(DecodeDatabaseConfig("{not json").status().code(), StatusCode::kCorruption);
  EXPECT_EQ(DecodePlaceKey("abc").status().code(), StatusCode::kCorruption);
}

TEST(Codec, RecordsCarryDepthRemovedAndVersionOneStillDecodes) {
  PlaceRecord record;
  record.id = 9;
  record.metadata.agent_id = "kinect";
  record.counts = {100, 20, 60, 0.2, 20};
  const std::string encoded = EncodePlaceRecord(record);
  EXPECT_EQ(encoded[0], 2) << "place records are format version 2";
  auto decoded = DecodePlaceRecord(encoded);
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->counts.depth_removed, 20u);
  EXPECT_EQ(decoded->counts.static_, 60u);
  // Counts that do not add up (total = dynamic + depth_removed + static) are corruption.
  record.counts.depth_removed = 21;
  EXPECT_EQ(DecodePlaceRecord(EncodePlaceRecord(record)).status().code(), StatusCode::kCorruption);

  // Version 1, as maps made before RGB-D hold it: no depth_removed.
  Bytes v1;
  v1.Put<uint8_t>(1).Put<uint32_t>(42).Str("rover").Put<uint64_t>(7).Put<int64_t>(123);
  v1.Put<uint8_t>(0);                                                           // no pose
  v1.Put<uint32_t>(100).Put<uint32_t>(30).Put<uint32_t>(70).Put<double>(0.25);  // counts
  v1.Varint(1).Put<int32_t>(0).Put<float>(0.9f).Put<float>(1).Put<float>(2).Put<float>(3);
  v1.Put<float>(4);
  auto old = DecodePlaceRecord(v1.s);
  ASSERT_TRUE(old.ok()) << old.status().ToString();
  EXPECT_EQ(old->id, 42u);
  EXPECT_EQ(old->metadata.agent_id, "rover");
  EXPECT_EQ(old->metadata.sequence, 7u);
  EXPECT_EQ(old->counts.total, 100u);
  EXPECT_EQ(old->counts.static_, 70u);
  EXPECT_EQ(old->counts.depth_removed, 0u);
  ASSERT_EQ(old->boxes_used.size(), 1u);
  EXPECT_EQ(old->boxes_used[0].rect, cv::Rect2f(1, 2, 3, 4));
  for (size_t cut = 0; cut < v1.s.size(); ++cut) {
    EXPECT_EQ(DecodePlaceRecord(std::string_view(v1.s).substr(0, cut)).status().code(),
              StatusCode::kCorruption);
  }

  // Invalid observations: the same.
  InvalidObservation invalid;
  invalid.serial = 3;
  invalid.counts = {50, 10, 5, 0.5, 35};
  invalid.reason = "too few";
  const std::string invalid_encoded = EncodeInvalidObservation(invalid);
  EXPECT_EQ(invalid_encoded[0], 2);
  auto invalid_decoded = DecodeInvalidObservation(invalid_encoded);
  ASSERT_TRUE(invalid_decoded.ok()) << invalid_decoded.status().ToString();
  EXPECT_EQ(invalid_decoded->counts.depth_removed, 35u);
  Bytes invalid_v1;
  invalid_v1.Put<uint8_t>(1).Put<uint64_t>(3).Str("a").Put<uint64_t>(1).Put<int64_t>(2);
  invalid_v1.Put<uint8_t>(0).Put<uint32_t>(15).Put<uint32_t>(10).Put<uint32_t>(5);
  invalid_v1.Put<double>(0.5).Varint(0).Str("too few");
  auto invalid_old = DecodeInvalidObservation(invalid_v1.s);
  ASSERT_TRUE(invalid_old.ok()) << invalid_old.status().ToString();
  EXPECT_EQ(invalid_old->counts.total, 15u);
  EXPECT_EQ(invalid_old->counts.depth_removed, 0u);
  EXPECT_EQ(invalid_old->reason, "too few");
}

// Found by tests/fuzz/fuzz_codec: a word-id delta near 2^64 wrapped the running id below the
// previous one, so a damaged BoW (or direct index) decoded unsorted (and its re-encoding did not
// decode).
TEST(Codec, BowWordIdDeltaThatWrapsIsCorruption) {
  Bytes wrapped;
  wrapped.Put<uint8_t>(1).Varint(2);
  wrapped.Varint(5).Put<float>(1.0f);
  wrapped.Varint(~uint64_t{0} - 2).Put<float>(1.0f);  // 5 + (2^64 - 3) wraps to 2
  const auto decoded = DecodeBow(wrapped.s);
  EXPECT_EQ(decoded.status().code(), StatusCode::kCorruption) << decoded.status().ToString();
  Bytes largest;  // the largest word id still decodes
  largest.Put<uint8_t>(1).Varint(2).Varint(5).Put<float>(1.0f).Varint(0xFFFFFFFEull - 5);
  largest.Put<float>(2.0f);
  auto ok = DecodeBow(largest.s);
  ASSERT_TRUE(ok.ok()) << ok.status().ToString();
  EXPECT_EQ(ok->back().word, 0xFFFFFFFEu);
  EXPECT_EQ(DecodeBow(EncodeBow(*ok)).value(), *ok);

  // The direct index's node ids are delta-coded the same way.
  Bytes direct;
  direct.Put<uint8_t>(1).Put<uint32_t>(640).Put<uint32_t>(480).Varint(0);  // no features
  direct.Put<uint8_t>(0).Varint(2).Varint(5).Varint(0).Varint(~uint64_t{0} - 2).Varint(0);
  FeatureSet features;
  DirectIndex index;
  EXPECT_EQ(DecodeFeatures(direct.s, &features, &index).code(), StatusCode::kCorruption);
}

// Found by tests/fuzz/fuzz_codec: an empty set decoded through memcpy into an empty vector's
// null data() (undefined behaviour, reported by the ASan+UBSan stage).
TEST(Codec, EmptyFeatureSetsRoundTrip) {
  FloatFeatureSet sift;
  sift.image_width = 640;
  sift.image_height = 480;
  FloatFeatureSet sift_out;
  DirectIndex direct_out;
  ASSERT_TRUE(
      DecodeFloatFeatures(EncodeFloatFeatures(sift, DirectIndex{}), &sift_out, &direct_out).ok());
  EXPECT_TRUE(sift_out.empty());
  EXPECT_EQ(sift_out.image_width, 640);
  FeatureSet orb;
  orb.image_width = 640;
  orb.image_height = 480;
  FeatureSet orb_out;
  ASSERT_TRUE(DecodeFeatures(EncodeFeatures(orb, DirectIndex{}), &orb_out, &direct_out).ok());
  EXPECT_TRUE(orb_out.empty());
  EXPECT_EQ(orb_out.image_height, 480);
}

TEST(Codec, FloatFeaturesRoundTripAndDamageIsCorruption) {
  ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
  SiftConfig sift;
  sift.max_features = 200;
  auto features = ExtractSift(testing::ReadGray(testing::RtabmapFramePath(1)), sift);
  ASSERT_TRUE(features.ok()) << features.status().ToString();
  ASSERT_GT(features->size(), 50u);
  DirectIndex direct;
  direct.levels_up = 2;
  direct.node_ids = {3, 11, 4000};
  direct.offsets = {0, 2, 3, 5};
  direct.feature_ids = {0, 5, 1, 2, 7};
  const std::string bytes = EncodeFloatFeatures(*features, direct);
  EXPECT_EQ(uint8_t(bytes[0]), 0x81);
  FloatFeatureSet out;
  DirectIndex direct_out;
  ASSERT_TRUE(DecodeFloatFeatures(bytes, &out, &direct_out).ok());
  EXPECT_EQ(out.image_width, features->image_width);
  EXPECT_EQ(out.image_height, features->image_height);
  EXPECT_EQ(out.keypoints, features->keypoints);
  EXPECT_EQ(out.descriptors, features->descriptors);
  EXPECT_EQ(direct_out, direct);

  // Neither decoder takes the other's payload.
  FeatureSet orb;
  DirectIndex orb_direct;
  EXPECT_EQ(DecodeFeatures(bytes, &orb, &orb_direct).code(), StatusCode::kCorruption);
  const std::string orb_bytes =
      EncodeFeatures(testing::ExtractFile(testing::RtabmapFramePath(1), 50), DirectIndex{});
  EXPECT_EQ(DecodeFloatFeatures(orb_bytes, &out, &direct_out).code(), StatusCode::kCorruption);

  // Every truncation of a small payload, trailing bytes, a wrong version.
  const FloatFeatureSet small = SelectFloatFeatures(*features, {0, 1, 2, 3, 4, 5, 6, 7});
  DirectIndex small_direct;
  small_direct.levels_up = 1;
  small_direct.node_ids = {3};
  small_direct.offsets = {0, 2};
  small_direct.feature_ids = {0, 7};
  const std::string good = EncodeFloatFeatures(small, small_direct);
  ASSERT_TRUE(DecodeFloatFeatures(good, &out, &direct_out).ok());
  EXPECT_EQ(out.descriptors, small.descriptors);
  for (size_t cut = 0; cut < good.size(); ++cut) {
    ASSERT_EQ(DecodeFloatFeatures(std::string_view(good).substr(0, cut), &out, &direct_out).code(),
              StatusCode::kCorruption)
        << "cut at " << cut;
  }
  EXPECT_EQ(DecodeFloatFeatures(good + '\0', &out, &direct_out).code(), StatusCode::kCorruption);
  std::string damaged = good;
  damaged[0] = char(0x83);  // 0x81 and 0x82 (with geometry) are known
  const Status version = DecodeFloatFeatures(damaged, &out, &direct_out);
  EXPECT_EQ(version.code(), StatusCode::kCorruption);
  EXPECT_NE(version.message().find("version"), std::string::npos) << version.ToString();
  // A NaN descriptor value (the first float after 1 + 4 + 4 + 1 + 8 * 21 bytes).
  damaged = good;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::memcpy(damaged.data() + 178, &nan, sizeof nan);
  EXPECT_EQ(DecodeFloatFeatures(damaged, &out, &direct_out).code(), StatusCode::kCorruption);
  // A huge claimed keypoint count must not allocate or read past the end.
  Bytes huge;
  huge.Put<uint8_t>(0x81).Put<uint32_t>(640).Put<uint32_t>(480).Varint(uint64_t(1) << 40);
  huge.s += std::string(600, '\0');
  EXPECT_EQ(DecodeFloatFeatures(huge.s, &out, &direct_out).code(), StatusCode::kCorruption);
  // A direct index naming a feature the payload does not have.
  small_direct.feature_ids = {0, 8};
  EXPECT_EQ(DecodeFloatFeatures(EncodeFloatFeatures(small, small_direct), &out, &direct_out).code(),
            StatusCode::kCorruption);
}

TEST(Codec, RgbdConfigRoundTripsAndFormat1ConfigsLoadAsOrb) {
  DatabaseConfig c;
  c.feature_type = FeatureType::kSift;
  c.sift = {1500, 4, 0.03, 12, 1.5};
  c.depth.refine_boxes = false;
  c.depth.refine.bin_m = 0.04f;
  c.depth.refine.min_mode_fraction = 0.2f;
  c.depth.refine.dilate_px = 6;
  c.depth.refine.min_valid_fraction = 0.3f;
  c.depth.stream_filter = false;
  DepthFilterConfig& f = c.depth.filter;
  f.format.metres_per_unit = 0.0002;
  f.format.min_depth_m = 0.2f;
  f.format.max_depth_m = 8.0f;
  f.mean_mode = MeanDepthMode::kAllPixels;
  f.threshold_m = 0.3f;
  f.persistence = 3;
  f.static_window = 7;
  f.warmup_frames = 2;
  f.band_policy = BandPolicy::kNearestLayer;
  f.rise_band = {1.5f, 4.0f};
  f.fall_band = {0.1f, 0.9f};
  f.nearest_layer.min_gap_m = 0.2f;
  f.nearest_layer.max_layer_fraction = 0.6f;
  f.appeared_layer.margin_m = 0.05f;
  f.appeared_layer.merge_gap_m = 0.15f;
  f.feature_window_radius = 3;
  f.remove_features_without_depth = true;
  f.use_range = true;
  f.rebaseline_after = 40;
  LoopClosureConfig& l = c.loop_closure;
  l.likelihood_similarity = SimilarityMeasure::kScore;
  l.rehearsal_similarity = SimilarityMeasure::kScore;
  l.likelihood_baseline = LikelihoodBaseline::kNone;
  l.scoring = ScoringType::kL2;
  l.loop_threshold = 0.2;
  l.rehearsal_threshold = 0.3;
  l.short_term_memory = 5;
  l.no_loop_stay = 0.85;
  l.loop_to_no_loop = 0.15;
  l.transition_sigma = 2;
  l.transition_radius = 10;
  l.hypothesis_radius = 1;
  l.min_candidates = 4;
  l.min_similarity_excess = 0.05;
  l.max_working_memory = 50;
  l.time_budget_ms = 3.5;
  l.retrieval_radius = 2;
  l.max_retrieved = 3;
  c.verify_loops = false;
  const std::string encoded = EncodeDatabaseConfig(c);
  auto decoded = DecodeDatabaseConfig(encoded);
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(EncodeDatabaseConfig(*decoded), encoded);  // every field the encoder writes
  EXPECT_EQ(decoded->feature_type, FeatureType::kSift);
  EXPECT_EQ(decoded->sift.octave_layers, 4);
  EXPECT_FALSE(decoded->verify_loops);
  EXPECT_EQ(decoded->sift.contrast_threshold, 0.03);
  EXPECT_FALSE(decoded->depth.refine_boxes);
  EXPECT_EQ(decoded->depth.refine.dilate_px, 6);
  EXPECT_EQ(decoded->depth.filter.format.metres_per_unit, 0.0002);
  EXPECT_EQ(decoded->depth.filter.mean_mode, MeanDepthMode::kAllPixels);
  EXPECT_EQ(decoded->depth.filter.threshold_m, 0.3f);
  EXPECT_EQ(decoded->depth.filter.band_policy, BandPolicy::kNearestLayer);
  EXPECT_EQ(decoded->depth.filter.fall_band, (DepthBand{0.1f, 0.9f}));
  EXPECT_EQ(decoded->depth.filter.appeared_layer.margin_m, 0.05f);
  EXPECT_TRUE(decoded->depth.filter.use_range);
  EXPECT_EQ(decoded->depth.filter.rebaseline_after, 40);
  EXPECT_EQ(decoded->loop_closure.likelihood_baseline, LikelihoodBaseline::kNone);
  EXPECT_EQ(decoded->loop_closure.scoring, ScoringType::kL2);
  EXPECT_EQ(decoded->loop_closure.max_working_memory, 50u);
  EXPECT_EQ(decoded->loop_closure.time_budget_ms, 3.5);
  EXPECT_EQ(decoded->loop_closure.max_retrieved, 3);

  // A map made before RGB-D: an ORB map with every new setting at its default.
  auto old = DecodeDatabaseConfig(kFormat1Config);
  ASSERT_TRUE(old.ok()) << old.status().ToString();
  DatabaseConfig expected;
  expected.orb.max_features = 700;
  expected.filter.method = FilterMethod::kExactCoverage;
  expected.filter.place_threshold = 25;
  expected.dynamic_classes = {0, 2};
  expected.min_box_confidence = 0.3f;
  expected.verification.mode = VerificationMode::kExhaustive;
  // Before format 3: whole boxes, no short-term tier, no re-ranking (what those maps did).
  expected.box_refinement.method = BoxRefinement::kNone;
  expected.short_term.enabled = false;
  expected.verification.rerank = false;
  expected.static_feature_budget = false;
  EXPECT_EQ(old->feature_type, FeatureType::kOrb);
  EXPECT_EQ(EncodeDatabaseConfig(*old), EncodeDatabaseConfig(expected));
  // Partial sections keep the defaults of what they leave out.
  auto partial = DecodeDatabaseConfig(
      Format2ConfigWith(R"("depth":{"filter":{"persistence":2}},"loop_closure":{})"));
  ASSERT_TRUE(partial.ok()) << partial.status().ToString();
  EXPECT_EQ(partial->depth.filter.persistence, 2);
  EXPECT_EQ(partial->depth.filter.static_window, DepthFilterConfig{}.static_window);
  EXPECT_EQ(partial->loop_closure.short_term_memory, LoopClosureConfig{}.short_term_memory);

  // Bad values are refused naming their key.
  struct Bad {
    std::string extra;
    StatusCode code;
    std::string key;
  };
  const Bad bad[] = {
      {R"("feature_type":"surf")", StatusCode::kInvalidArgument, "feature_type"},
      {R"("feature_type":3)", StatusCode::kCorruption, "feature_type"},
      {R"("sift":{"sigma":"wide"})", StatusCode::kCorruption, "sift.sigma"},
      {R"("depth":[])", StatusCode::kCorruption, "depth"},
      {R"("depth":{"filter":{"threshold_m":"far"}})", StatusCode::kCorruption,
       "depth.filter.threshold_m"},
      {R"("depth":{"filter":{"persistence":-2}})", StatusCode::kInvalidArgument, "persistence"},
      {R"("depth":{"filter":{"band_policy":"widest"}})", StatusCode::kInvalidArgument,
       "depth.filter.band_policy"},
      {R"("depth":{"filter":{"fall_band":{"near_m":0.5}}})", StatusCode::kCorruption,
       "depth.filter.fall_band.far_m"},
      {R"("depth":{"filter":{"rise_band":{"near_m":3,"far_m":1}}})", StatusCode::kInvalidArgument,
       "rise_band"},
      {R"("depth":{"refine":{"dilate_px":1e12}})", StatusCode::kCorruption,
       "depth.refine.dilate_px"},
      {R"("depth":{"filter":{"format":{"min_depth_m":1e300}}})", StatusCode::kInvalidArgument,
       "depth.filter.format.min_depth_m"},
      {R"("loop_closure":{"max_working_memory":-1})", StatusCode::kInvalidArgument,
       "loop_closure.max_working_memory"},
      {R"("loop_closure":{"short_term_memory":2.5})", StatusCode::kCorruption,
       "loop_closure.short_term_memory"},
      {R"("loop_closure":{"likelihood_baseline":"mean"})", StatusCode::kInvalidArgument,
       "loop_closure.likelihood_baseline"},
      {R"("loop_closure":{"loop_threshold":7})", StatusCode::kInvalidArgument, "loop_closure"},
  };
  for (const Bad& b : bad) {
    const Status status = DecodeDatabaseConfig(Format2ConfigWith(b.extra)).status();
    EXPECT_EQ(status.code(), b.code) << b.extra << ": " << status.ToString();
    EXPECT_NE(status.message().find(b.key), std::string::npos)
        << b.extra << ": " << status.ToString();
  }
  std::string future = kFormat1Config;
  future.replace(future.find(R"("format":1)"), 10, R"("format":3)");
  EXPECT_EQ(DecodeDatabaseConfig(future).status().code(), StatusCode::kCorruption);
  std::string no_orb = kFormat1Config;
  no_orb.replace(no_orb.find(R"("orb")"), 5, R"("bro")");
  const Status missing = DecodeDatabaseConfig(no_orb).status();
  EXPECT_EQ(missing.code(), StatusCode::kCorruption);
  EXPECT_NE(missing.message().find("orb"), std::string::npos) << missing.ToString();
}

TEST_F(StorageTest, ReopenGivesIdenticalResultsOnRtabmapAndCamVid) {
  std::vector<Observation> frames;
  for (int i = 1; i <= 84; ++i) frames.push_back(RtabmapFrame(i));
  auto camvid = testing::CamVidFrames();
  for (size_t i = 0; i < camvid.size(); i += 12) {
    Observation observation;
    observation.image = testing::ReadGray(camvid[i].image_path);
    observation.dynamic.mask = testing::CamVidDynamicMask(camvid[i]);
    observation.metadata.agent_id = camvid[i].sequence;
    observation.metadata.sequence = uint64_t(camvid[i].frame);
    frames.push_back(observation);
  }
  MapOptions options;
  options.database.filter.method = FilterMethod::kExactCoverage;
  options.database.verification.mode = VerificationMode::kExhaustive;
  std::vector<Ranked> before;
  MapStats stats_before;
  std::map<PlaceId, size_t> frame_of;  // stored place -> its frame
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("mixed", options, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    for (size_t i = 0; i < frames.size(); i += 2) {
      auto added = (*map)->Add(frames[i]);
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      if (added->stored) frame_of[added->id] = i;
    }
    ASSERT_GT(frame_of.size(), 50u);
    ASSERT_TRUE((*map)->RemovePlace(3).ok());
    before = QueryAll(**map, frames);
    stats_before = (*map)->Stats();
    EXPECT_GT(stats_before.bytes_on_disk, 0u);
    EXPECT_GT(stats_before.database.descriptors_dropped, 0u) << "CamVid masks dropped nothing";
  }
  auto dir = OpenDir();
  auto map = dir->OpenMap("mixed", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  ASSERT_TRUE((*map)->VerifyIntegrity().ok());
  const MapStats stats_after = (*map)->Stats();
  EXPECT_EQ(stats_after.database.places, stats_before.database.places);
  EXPECT_EQ(stats_after.database.descriptors_kept, stats_before.database.descriptors_kept);
  EXPECT_EQ(stats_after.database.descriptors_dropped, stats_before.database.descriptors_dropped);
  const std::vector<Ranked> after = QueryAll(**map, frames);
  ASSERT_EQ(after.size(), before.size());
  for (size_t q = 0; q < before.size(); ++q) {
    EXPECT_EQ(after[q], before[q]) << "query " << q << " differs after reopen";
  }
  // The metadata survived too, and ids are never reused.
  for (const auto& [id, frame] : frame_of) {
    if (id == 3) continue;
    auto place = (*map)->GetPlace(id);
    ASSERT_TRUE(place.ok()) << place.status().ToString();
    EXPECT_EQ(place->record.metadata, frames[frame].metadata);
    EXPECT_EQ(place->payload.features.size(), place->record.counts.static_);
  }
  EXPECT_EQ((*map)->GetPlace(3).status().code(), StatusCode::kNotFound);
  auto added = (*map)->Add(frames[1]);
  ASSERT_TRUE(added.ok() && added->stored);
  EXPECT_EQ(added->id, frame_of.rbegin()->first + 1);
}

// Opening a map reads `places` and `bow` with StorageOptions::load_threads threads over ranges
// of load_range_ids ids (issue 17), each range's index built off the database and installed in
// order. Small ranges put many range boundaries (appended to their index segment), whole empty
// ranges (deleted places) and a first and last range with gaps into a small map; the default
// builds the one whole segment: every loader must rebuild exactly the map the sequential scan
// rebuilds.
TEST_F(StorageTest, ParallelLoadRebuildsExactlyWhatTheSequentialScanDoes) {
  constexpr int kPlaces = 240;
  std::vector<Observation> queries;
  for (int i = 1; i <= 84; i += 6) queries.push_back(RtabmapFrame(i));
  std::vector<Ranked> before;
  MapStats stats_before;
  std::vector<PlaceId> ids_before;
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("ranges", {}, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    const auto frames = testing::ProcessRtabmapFrames(*(*map)->database());
    ASSERT_GT(frames.size(), 60u);
    for (int n = 0; n < kPlaces; ++n) {
      // Frames in a shuffled order, so neighbouring ids hold different places.
      const ProcessedFrame& frame = frames[size_t(n * 37) % frames.size()];
      auto added = (*map)->Commit(
          frame, {"robot-" + std::to_string(n % 3), uint64_t(n), int64_t(n) * 1000, std::nullopt});
      ASSERT_TRUE(added.ok() && added->stored) << added.status().ToString();
      ASSERT_EQ(added->id, PlaceId(n + 1));
    }
    // The first place, a run covering whole ranges (48..63 at 16 ids), scattered ones, the last.
    std::vector<PlaceId> removed = {1, 128, 200, kPlaces};
    for (PlaceId id = 40; id <= 75; ++id) removed.push_back(id);
    for (PlaceId id : removed) ASSERT_TRUE((*map)->RemovePlace(id).ok()) << id;
    before = QueryAll(**map, queries);
    stats_before = (*map)->Stats();
    ids_before = (*map)->database()->ListPlaces();
    ASSERT_EQ(ids_before.size(), size_t(kPlaces) - removed.size());
  }
  struct Loader {
    unsigned threads;
    uint32_t range_ids;
  };
  size_t sequential_index_bytes = 0;
  // The sequential scan; 2 and 3 threads over small ranges; 2 threads over ranges so large that
  // the map is one scan; the default.
  for (const Loader loader :
       {Loader{1, 16}, Loader{2, 16}, Loader{3, 8}, Loader{2, 1u << 20}, Loader{2, 0}}) {
    SCOPED_TRACE("load_threads " + std::to_string(loader.threads) + ", load_range_ids " +
                 std::to_string(loader.range_ids));
    StorageOptions options;
    options.load_threads = loader.threads;
    options.load_range_ids = loader.range_ids;
    auto dir = OpenDir(options);
    auto map = dir->OpenMap("ranges", vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    EXPECT_EQ((*map)->open_timings().threads, loader.threads);
    EXPECT_EQ((*map)->database()->ListPlaces(), ids_before);
    const MapStats stats = (*map)->Stats();
    EXPECT_EQ(stats.database.places, stats_before.database.places);
    EXPECT_EQ(stats.database.descriptors_kept, stats_before.database.descriptors_kept);
    // Removals leave slack in the index before the close: the rebuilds are compared together.
    // The sequential scan adds place by place (InvertedIndex::Add); the others build each range
    // off the index: a whole segment gets each run at its final size and no garbage slots (never
    // more memory than Add), small ranges appended to their segment grow runs like Add in
    // bigger steps (within a few percent of it).
    if (!sequential_index_bytes) sequential_index_bytes = stats.database.index_bytes;
    if (loader.threads == 1) {
      EXPECT_EQ(stats.database.index_bytes, sequential_index_bytes);
    } else if (loader.range_ids == 0 || loader.range_ids >= 65536) {
      EXPECT_LE(stats.database.index_bytes, sequential_index_bytes);
    } else {
      EXPECT_LE(stats.database.index_bytes, sequential_index_bytes + sequential_index_bytes / 32);
    }
    EXPECT_EQ(stats.database.record_bytes, stats_before.database.record_bytes);
    // The same places, scores and order as the map the commits built with InvertedIndex::Add.
    EXPECT_EQ(QueryAll(**map, queries), before);
    for (PlaceId id : {PlaceId(2), PlaceId(39), PlaceId(76), PlaceId(kPlaces - 1)}) {
      auto place = (*map)->GetPlace(id);
      ASSERT_TRUE(place.ok()) << place.status().ToString();
      EXPECT_EQ(place->record.metadata.sequence, uint64_t(id - 1));
    }
    EXPECT_EQ((*map)->GetPlace(60).status().code(), StatusCode::kNotFound);
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  }
  // Ids are never reused, whichever loader opened the map: the last place was removed.
  auto dir = OpenDir();
  auto map = dir->OpenMap("ranges", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  auto added = (*map)->Add(RtabmapFrame(7));
  ASSERT_TRUE(added.ok() && added->stored) << added.status().ToString();
  EXPECT_EQ(added->id, PlaceId(kPlaces + 1));
}

TEST_F(StorageTest, ManyMapsCreateListDelete) {
  auto dir = OpenDir();
  EXPECT_TRUE(dir->ListMaps().empty());
  ASSERT_TRUE(dir->CreateMap("alpha", {}, vocabulary_).ok());
  ASSERT_TRUE(dir->CreateMap("beta-2", {}, vocabulary_).ok());
  EXPECT_EQ(dir->CreateMap("alpha", {}, vocabulary_).status().code(), StatusCode::kAlreadyExists);
  EXPECT_EQ(dir->CreateMap("../evil", {}, vocabulary_).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(dir->CreateMap("", {}, vocabulary_).status().code(), StatusCode::kInvalidArgument);
  MapOptions bad;
  bad.database.orb.max_features = -3;
  EXPECT_EQ(dir->CreateMap("gamma", bad, vocabulary_).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(dir->ListMaps(), (std::vector<std::string>{"alpha", "beta-2"}));

  auto alpha = dir->OpenMap("alpha", vocabulary_);
  ASSERT_TRUE(alpha.ok());
  ASSERT_TRUE((*alpha)->Add(RtabmapFrame(1)).ok());
  ASSERT_TRUE(dir->DeleteMap("alpha").ok());
  EXPECT_EQ(dir->ListMaps(), (std::vector<std::string>{"beta-2"}));
  // A holder of the deleted map gets a clear error, not a crash.
  EXPECT_EQ((*alpha)->Add(RtabmapFrame(2)).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(dir->OpenMap("alpha", vocabulary_).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(dir->DeleteMap("alpha").code(), StatusCode::kNotFound);
  // The name is free again.
  auto recreated = dir->CreateMap("alpha", {}, vocabulary_);
  ASSERT_TRUE(recreated.ok()) << recreated.status().ToString();
  alpha->reset();
  auto info = dir->ReadMapInfo("beta-2");
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->vocabulary_checksum, vocabulary_->checksum());
  // The layer above stores its own settings with the map, opaque to storage.
  MapOptions with_service;
  with_service.service_json = R"({"box_source":"server"})";
  ASSERT_TRUE(dir->CreateMap("gamma", with_service, vocabulary_).ok());
  dir->CloseMap("gamma");
  auto gamma = dir->ReadMapInfo("gamma");
  ASSERT_TRUE(gamma.ok()) << gamma.status().ToString();
  EXPECT_EQ(gamma->options.service_json, with_service.service_json);
}

TEST_F(StorageTest, AnotherVocabularyIsRefused) {
  {
    auto dir = OpenDir();
    ASSERT_TRUE(dir->CreateMap("m", {}, vocabulary_).ok());
  }
  // A different vocabulary: the same tree with one word weight changed.
  const std::shared_ptr<const Vocabulary> other = testing::OtherVocabulary();
  ASSERT_TRUE(other);
  auto dir = OpenDir();
  auto refused = dir->OpenMap("m", other);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find(vocabulary_->checksum_hex()), std::string::npos);
  auto map = dir->OpenMap("m", vocabulary_);
  ASSERT_TRUE(map.ok());
  EXPECT_EQ((*map)->CheckVocabulary(other).code(), StatusCode::kFailedPrecondition);
  EXPECT_TRUE((*map)->CheckVocabulary(vocabulary_).ok());
}

TEST_F(StorageTest, CheckpointAndRestore) {
  auto dir = OpenDir();
  auto map = dir->CreateMap("source", {}, vocabulary_);
  ASSERT_TRUE(map.ok());
  for (int i = 1; i <= 12; ++i) ASSERT_TRUE((*map)->Add(RtabmapFrame(i)).ok());
  const std::string backup = root_ + "/backup";
  ASSERT_TRUE((*map)->Checkpoint(backup).ok());
  EXPECT_EQ((*map)->Checkpoint(backup).code(), StatusCode::kAlreadyExists);
  // Writes after the checkpoint are not in it.
  ASSERT_TRUE((*map)->Add(RtabmapFrame(13)).ok());

  ASSERT_TRUE(dir->RestoreMap("restored", backup).ok());
  EXPECT_EQ(dir->RestoreMap("restored", backup).code(), StatusCode::kAlreadyExists);
  EXPECT_EQ(dir->RestoreMap("x", root_).code(), StatusCode::kInvalidArgument);
  auto restored = dir->OpenMap("restored", vocabulary_);
  ASSERT_TRUE(restored.ok()) << restored.status().ToString();
  EXPECT_EQ((*restored)->info().name, "restored");
  EXPECT_EQ((*restored)->Stats().database.places, 12u);
  ASSERT_TRUE((*restored)->VerifyIntegrity().ok());
  auto result = (*restored)->Query(RtabmapFrame(7), {});
  ASSERT_TRUE(result.ok());
  ASSERT_FALSE(result->matches.empty());
  EXPECT_EQ(result->matches[0].place, 7u);
}

TEST_F(StorageTest, InvalidObservationsAreCountedOrKeptAsMetadata) {
  auto dir = OpenDir();
  MapOptions keep;
  keep.store_invalid = true;
  auto map = dir->CreateMap("keeps-invalid", keep, vocabulary_);
  auto plain = dir->CreateMap("counts-invalid", {}, vocabulary_);
  ASSERT_TRUE(map.ok() && plain.ok());
  Observation covered = RtabmapFrame(9);
  covered.dynamic.boxes.push_back(
      {0, 0.9f, cv::Rect2f(0, 0, float(covered.image.cols), float(covered.image.rows))});
  for (const std::shared_ptr<PlaceMap>& m : {*map, *plain}) {
    auto added = m->Add(covered);
    ASSERT_TRUE(added.ok());
    EXPECT_FALSE(added->stored);
    ASSERT_TRUE(m->Add(RtabmapFrame(10)).ok());
  }
  EXPECT_EQ((*map)->Stats().invalid_stored, 1u);
  EXPECT_EQ((*plain)->Stats().invalid_stored, 0u);
  auto kept = (*map)->InvalidObservations(10);
  ASSERT_EQ(kept.size(), 1u);
  EXPECT_EQ(kept[0].metadata.sequence, 9u);
  EXPECT_EQ(kept[0].counts.static_, 0u);
  EXPECT_NE(kept[0].reason.find("placeThreshold"), std::string::npos);
  map->reset();
  plain->reset();
  dir.reset();

  auto reopened = OpenDir();
  auto again = reopened->OpenMap("keeps-invalid", vocabulary_);
  auto plain_again = reopened->OpenMap("counts-invalid", vocabulary_);
  ASSERT_TRUE(again.ok() && plain_again.ok());
  EXPECT_EQ((*again)->Stats().database.invalid_rejected, 1u);
  EXPECT_EQ((*plain_again)->Stats().database.invalid_rejected, 1u);
  EXPECT_EQ((*again)->Stats().invalid_stored, 1u);
  EXPECT_EQ((*again)->Stats().database.places, 1u);
}

TEST_F(StorageTest, GroupCommitAcknowledgesDurablyAndConcurrently) {
  StorageOptions options;
  options.sync = SyncMode::kGroupCommit;
  options.group_commit_delay_ms = 3;
  std::vector<ProcessedFrame> frames;
  {
    auto dir = OpenDir(options);
    auto map = dir->CreateMap("grouped", {}, vocabulary_);
    ASSERT_TRUE(map.ok());
    for (int i = 1; i <= 16; ++i) {
      auto frame = (*map)->Process(RtabmapFrame(i));
      ASSERT_TRUE(frame.ok());
      frames.push_back(*frame);
    }
    std::vector<std::thread> writers;
    std::atomic<int> failures{0};
    for (int t = 0; t < 4; ++t) {
      writers.emplace_back([&, t] {
        for (size_t i = size_t(t); i < frames.size(); i += 4) {
          if (!(*map)->Commit(frames[i], {}).ok()) failures.fetch_add(1);
        }
      });
    }
    for (auto& writer : writers) writer.join();
    EXPECT_EQ(failures.load(), 0);
  }
  auto dir = OpenDir(options);
  auto map = dir->OpenMap("grouped", vocabulary_);
  ASSERT_TRUE(map.ok());
  EXPECT_EQ((*map)->Stats().database.places, 16u);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

// The commit queue (PlaceMap::Enqueue, group commit): four callers keep places queued at once;
// each place is indexed when its commit is done, ids follow each caller's order, and everything
// acknowledged is there after a reopen (ACKED and the database agree: the map opens). Both sync
// modes. Run under ThreadSanitizer by tools/test.sh.
TEST_F(StorageTest, ConcurrentCommitQueueAcknowledgesEachPlaceDurablyInCallersOrder) {
  for (SyncMode mode : {SyncMode::kEveryWrite, SyncMode::kGroupCommit}) {
    SCOPED_TRACE(mode == SyncMode::kEveryWrite ? "every_write" : "group_commit");
    StorageOptions options;
    options.sync = mode;
    const std::string name = mode == SyncMode::kEveryWrite ? "queued" : "queued-grouped";
    std::vector<ProcessedFrame> frames;
    std::map<PlaceId, size_t> acknowledged;  // place -> frame
    {
      auto dir = OpenDir(options);
      auto map = dir->CreateMap(name, {}, vocabulary_);
      ASSERT_TRUE(map.ok());
      for (int i = 1; i <= 24; ++i) {
        auto frame = (*map)->Process(RtabmapFrame(i), FrameRole::kStream);
        ASSERT_TRUE(frame.ok());
        if (frame->valid) frames.push_back(*frame);
      }
      ASSERT_GE(frames.size(), 20u);
      constexpr size_t kCallers = 4;
      std::vector<std::vector<std::pair<PlaceId, size_t>>> results(kCallers);
      std::atomic<int> failures{0};
      std::vector<std::thread> callers;
      for (size_t t = 0; t < kCallers; ++t) {
        callers.emplace_back([&, t] {
          std::vector<std::pair<std::shared_ptr<PendingCommit>, size_t>> queued;
          for (size_t i = t; i < frames.size(); i += kCallers) {
            PlaceMetadata metadata;
            metadata.agent_id = "caller-" + std::to_string(t);
            metadata.sequence = i;
            queued.emplace_back((*map)->Enqueue(frames[i], metadata), i);
          }
          for (auto& [pending, i] : queued) {
            const Result<AddResult>& added = pending->Wait();
            EXPECT_TRUE(pending->done());
            if (!added.ok() || !added->stored) {
              failures.fetch_add(1);
              continue;
            }
            // Done = durable and indexed: readable and found by its own frame at once.
            if (!(*map)->database()->Get(added->id)) failures.fetch_add(1);
            results[t].emplace_back(added->id, i);
          }
        });
      }
      for (auto& caller : callers) caller.join();
      EXPECT_EQ(failures.load(), 0);
      for (size_t t = 0; t < kCallers; ++t) {
        for (size_t k = 1; k < results[t].size(); ++k) {
          EXPECT_GT(results[t][k].first, results[t][k - 1].first) << "caller " << t;
        }
        for (const auto& [id, i] : results[t]) {
          EXPECT_TRUE(acknowledged.emplace(id, i).second) << "id " << id << " given twice";
        }
      }
      EXPECT_EQ(acknowledged.size(), frames.size());
      for (const auto& [id, i] : acknowledged) {
        QueryResult result = (*map)->Search(frames[i], {});
        ASSERT_FALSE(result.matches.empty());
        EXPECT_EQ(result.matches[0].place, id);
        // The index stores weights within 1/2048 relative: an L1 self-match within that of 1.
        EXPECT_NEAR(result.matches[0].score, 1.0, InvertedIndex::kWeightRelativeError + 1e-5);
      }
    }
    auto dir = OpenDir(options);
    auto map = dir->OpenMap(name, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
    EXPECT_EQ((*map)->Stats().database.places, acknowledged.size());
    for (const auto& [id, i] : acknowledged) {
      auto stored = (*map)->GetPlace(id);
      ASSERT_TRUE(stored.ok()) << id;
      EXPECT_EQ(stored->record.metadata.sequence, i);
    }
  }
}

// A write that fails fails every place of its group and stores none of them: here the disk-full
// reserve refuses every new place (RESOURCE_EXHAUSTED, as when the disk is full). Frames the
// checks refuse, and invalid ones, are answered at once, as Commit() answers them. Places still
// queued when their map is deleted are answered too (NOT_FOUND or stored), never left waiting.
TEST_F(StorageTest, ConcurrentCommitQueueFailureFailsEveryQueuedPlaceAndStoresNone) {
  std::vector<ProcessedFrame> frames;
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("refused", {}, vocabulary_);
    ASSERT_TRUE(map.ok());
    for (int i = 1; i <= 8; ++i) {
      auto frame = (*map)->Process(RtabmapFrame(i), FrameRole::kStream);
      ASSERT_TRUE(frame.ok());
      frames.push_back(*frame);
    }
  }
  {
    StorageOptions full;
    full.disk_reserve_bytes = uint64_t(1) << 62;  // more than any disk: nothing fits
    auto dir = OpenDir(full);
    auto map = dir->OpenMap("refused", vocabulary_);
    ASSERT_TRUE(map.ok());
    std::vector<std::shared_ptr<PendingCommit>> queued;
    for (const ProcessedFrame& frame : frames) queued.push_back((*map)->Enqueue(frame, {}));
    for (const auto& pending : queued) {
      const Result<AddResult>& added = pending->Wait();
      ASSERT_FALSE(added.ok());
      EXPECT_EQ(added.status().code(), StatusCode::kResourceExhausted) << added.status().ToString();
      EXPECT_NE(added.status().message().find("disk full: map 'refused'"), std::string::npos)
          << added.status().ToString();
    }
    EXPECT_EQ((*map)->Stats().database.places, 0u);
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());

    // Refused by the checks: done before Enqueue() returns, with Commit()'s answer.
    ProcessedFrame pending_stage = frames[0];
    pending_stage.stream_pending = true;
    auto refused = (*map)->Enqueue(pending_stage, {});
    EXPECT_TRUE(refused->done());
    EXPECT_EQ(refused->Wait().status().code(), StatusCode::kFailedPrecondition);
    ProcessedFrame invalid = frames[0];
    invalid.valid = false;
    invalid.rejection = "too few";
    auto counted = (*map)->Enqueue(invalid, {});
    EXPECT_TRUE(counted->done());
    ASSERT_TRUE(counted->Wait().ok()) << counted->Wait().status().ToString();
    EXPECT_FALSE(counted->Wait()->stored);
  }
  auto dir = OpenDir();
  auto map = dir->OpenMap("refused", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_EQ((*map)->Stats().database.places, 0u);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  // With room again the same frames are stored.
  ASSERT_TRUE((*map)->Enqueue(frames[0], {})->Wait().ok());
  EXPECT_EQ((*map)->Stats().database.places, 1u);

  // Deleted with places queued: each is answered.
  std::vector<std::shared_ptr<PendingCommit>> queued;
  for (const ProcessedFrame& frame : frames) queued.push_back((*map)->Enqueue(frame, {}));
  ASSERT_TRUE(dir->DeleteMap("refused").ok());
  for (const auto& pending : queued) {
    const Result<AddResult>& added = pending->Wait();
    if (!added.ok()) {
      EXPECT_EQ(added.status().code(), StatusCode::kNotFound);
    }
  }
  EXPECT_EQ((*map)->Enqueue(frames[1], {})->Wait().status().code(), StatusCode::kNotFound);
}

// Readers query while writers add and remove; run under ThreadSanitizer by tools/test.sh.
TEST_F(StorageTest, ConcurrentQueriesDuringIngestAndDeletion) {
  auto dir = OpenDir();
  MapOptions options;
  options.database.verification.mode = VerificationMode::kExhaustive;
  auto map = dir->CreateMap("busy", options, vocabulary_);
  ASSERT_TRUE(map.ok());
  std::vector<ProcessedFrame> frames;
  for (int i = 1; i <= 20; ++i) {
    auto frame = (*map)->Process(RtabmapFrame(i));
    ASSERT_TRUE(frame.ok());
    frames.push_back(*frame);
  }
  for (size_t i = 0; i < 5; ++i) ASSERT_TRUE((*map)->Commit(frames[i], {}).ok());
  // Readers query the valid frames only: an invalid one (frame 19 is) is answered invalid by
  // design, and how far the readers get before the writer ends depends on the machine.
  std::vector<size_t> queried;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (frames[i].valid) queried.push_back(i);
  }
  ASSERT_GE(queried.size(), 15u);
  std::atomic<bool> done{false};
  std::mutex failures_mutex;
  std::vector<std::string> failures;
  auto fail = [&](std::string what) {
    std::lock_guard lock(failures_mutex);
    failures.push_back(std::move(what));
  };
  std::atomic<int> queries{0};
  std::vector<std::thread> threads;
  for (int r = 0; r < 2; ++r) {
    threads.emplace_back([&, r] {
      for (size_t i = size_t(r); !done.load(); ++i) {
        const size_t frame = queried[i % queried.size()];
        QueryResult result = (*map)->Search(frames[frame], {});
        if (!result.valid)
          fail("query of frame " + std::to_string(frame) + ": " + result.rejection);
        (void)(*map)->Stats();
        queries.fetch_add(1);
      }
    });
  }
  std::thread writer([&] {
    for (size_t i = 5; i < frames.size(); ++i) {
      auto added = (*map)->Commit(frames[i], {});
      if (!added.ok())
        fail("commit of frame " + std::to_string(i) + ": " + added.status().ToString());
      if (i % 4 == 0) {
        if (Status removed = (*map)->RemovePlace(PlaceId(i - 3)); !removed.ok()) {
          fail("removal of place " + std::to_string(i - 3) + ": " + removed.ToString());
        }
      }
    }
    done.store(true);
  });
  writer.join();
  for (auto& t : threads) t.join();
  EXPECT_TRUE(failures.empty()) << failures.size() << " failures, first: " << failures.front();
  EXPECT_GT(queries.load(), 0);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

TEST_F(StorageTest, ForeignOrCorruptedFilesGiveClearErrors) {
  // A non-empty directory that is not ours is never touched.
  const std::string foreign = root_ + "/foreign";
  fs::create_directories(foreign);
  std::ofstream(foreign + "/notes.txt") << "someone else's files";
  auto refused = DataDirectory::Open(foreign);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_TRUE(fs::exists(foreign + "/notes.txt"));

  // A damaged marker.
  const std::string damaged = root_ + "/damaged";
  ASSERT_TRUE(DataDirectory::Open(damaged).ok());
  std::ofstream(damaged + "/PLACEDB_DATA_DIR") << "garbage";
  EXPECT_EQ(DataDirectory::Open(damaged).status().code(), StatusCode::kCorruption);

  auto dir = OpenDir();
  // A directory under maps/ that is not a database.
  fs::create_directories(root_ + "/data/maps/junk");
  std::ofstream(root_ + "/data/maps/junk/file") << "x";
  auto junk = dir->OpenMap("junk", vocabulary_);
  ASSERT_FALSE(junk.ok());
  EXPECT_EQ(junk.status().code(), StatusCode::kCorruption);

  // A map whose every file is overwritten with garbage.
  {
    auto map = dir->CreateMap("broken", {}, vocabulary_);
    ASSERT_TRUE(map.ok());
    for (int i = 1; i <= 4; ++i) ASSERT_TRUE((*map)->Add(RtabmapFrame(i)).ok());
    dir->CloseMap("broken");
  }
  for (const auto& entry : fs::directory_iterator(root_ + "/data/maps/broken")) {
    if (!entry.is_regular_file()) continue;
    std::fstream file(entry.path(), std::ios::in | std::ios::out | std::ios::binary);
    const std::string noise(64, '\x5a');
    file.seekp(0);
    file.write(noise.data(), std::streamsize(noise.size()));
  }
  auto broken = dir->OpenMap("broken", vocabulary_);
  ASSERT_FALSE(broken.ok());
  EXPECT_TRUE(broken.status().code() == StatusCode::kCorruption ||
              broken.status().code() == StatusCode::kIoError)
      << broken.status().ToString();
  // Other maps are unaffected.
  ASSERT_TRUE(dir->CreateMap("healthy", {}, vocabulary_).ok());
}

// One process per data directory: a second Open() is refused while the first lives (even in
// the same process), the message names the holder, and nothing of the directory changes; the
// lock goes with its holder, including a holder killed with SIGKILL.
TEST_F(StorageTest, DataDirectoryIsLockedByItsFirstOpener) {
  const std::string path = root_ + "/locked";
  std::vector<std::string> files_before;
  {
    auto first = DataDirectory::Open(path);
    ASSERT_TRUE(first.ok()) << first.status().ToString();
    for (const auto& entry : fs::recursive_directory_iterator(path)) {
      files_before.push_back(entry.path().string());
    }
    auto second = DataDirectory::Open(path);
    ASSERT_FALSE(second.ok());
    EXPECT_EQ(second.status().code(), StatusCode::kFailedPrecondition);
    EXPECT_NE(second.status().message().find("in use by another placedb process (pid " +
                                             std::to_string(getpid()) + ")"),
              std::string::npos)
        << second.status().ToString();
    std::vector<std::string> files_after;
    for (const auto& entry : fs::recursive_directory_iterator(path)) {
      files_after.push_back(entry.path().string());
    }
    EXPECT_EQ(files_after, files_before);
    ASSERT_TRUE((*first)->CreateMap("still-writable", {}, vocabulary_).ok());
  }
  ASSERT_TRUE(DataDirectory::Open(path).ok()) << "the lock outlived its DataDirectory";

  int ready[2];
  ASSERT_EQ(pipe(ready), 0);
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    auto held = DataDirectory::Open(path);
    const char byte = held.ok() ? '1' : '0';
    (void)!write(ready[1], &byte, 1);
    pause();  // holds the lock until killed
    _exit(0);
  }
  char byte = 0;
  ASSERT_EQ(read(ready[0], &byte, 1), 1);
  ASSERT_EQ(byte, '1');
  auto while_held = DataDirectory::Open(path);
  EXPECT_EQ(while_held.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(while_held.status().message().find("(pid " + std::to_string(child) + ")"),
            std::string::npos)
      << while_held.status().ToString();
  kill(child, SIGKILL);
  waitpid(child, nullptr, 0);
  close(ready[0]);
  close(ready[1]);
  auto after_kill = DataDirectory::Open(path);
  ASSERT_TRUE(after_kill.ok()) << after_kill.status().ToString();
  EXPECT_EQ((*after_kill)->ListMaps(), std::vector<std::string>{"still-writable"});
}

TEST_F(StorageTest, SiftMapSurvivesReopenAndRefusesTheWrongVocabularyKind) {
  const auto sift = SiftVocabulary();
  ASSERT_TRUE(sift);
  MapOptions options;
  options.database.feature_type = FeatureType::kSift;
  options.database.verification.mode = VerificationMode::kExhaustive;
  std::vector<Observation> frames;
  for (int i = 1; i <= 24; i += 2) frames.push_back(RtabmapFrame(i));
  std::map<size_t, PlaceId> id_of;  // frame -> place
  std::map<PlaceId, StoredPlace> stored;
  {
    auto dir = OpenDir();
    // The vocabulary's kind must be the map's feature type.
    auto orb_with_sift = dir->CreateMap("orb-map", {}, sift);
    ASSERT_FALSE(orb_with_sift.ok());
    EXPECT_EQ(orb_with_sift.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(orb_with_sift.status().message().find("float (SIFT)"), std::string::npos)
        << orb_with_sift.status().ToString();
    auto sift_with_orb = dir->CreateMap("sift-map", options, vocabulary_);
    ASSERT_FALSE(sift_with_orb.ok());
    EXPECT_EQ(sift_with_orb.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(sift_with_orb.status().message().find("binary (ORB)"), std::string::npos)
        << sift_with_orb.status().ToString();
    EXPECT_TRUE(dir->ListMaps().empty());

    auto map = dir->CreateMap("sift", options, sift);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    for (size_t i = 0; i < frames.size(); ++i) {
      auto added = (*map)->Add(frames[i]);
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      if (added->stored) id_of[i] = added->id;
    }
    ASSERT_GE(id_of.size(), 8u);
    for (const auto& [i, id] : id_of) {
      auto place = (*map)->GetPlace(id);
      ASSERT_TRUE(place.ok()) << place.status().ToString();
      EXPECT_EQ(place->payload.features.orb(), nullptr);  // a SIFT map keeps no ORB features
      EXPECT_EQ(place->payload.features.sift()->size(), place->record.counts.static_);
      // What was stored is the frame's SC features, exactly.
      auto processed = (*map)->Process(frames[i]);
      ASSERT_TRUE(processed.ok());
      EXPECT_EQ(place->payload.features.sift()->keypoints,
                processed->static_features.sift()->keypoints);
      EXPECT_EQ(place->payload.features.sift()->descriptors,
                processed->static_features.sift()->descriptors);
      EXPECT_EQ(place->payload.direct, processed->direct);
      stored[id] = std::move(place).value();
    }
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  }
  auto dir = OpenDir();
  auto refused = dir->OpenMap("sift", vocabulary_);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find(sift->checksum_hex()), std::string::npos)
      << refused.status().ToString();
  EXPECT_NE(refused.status().message().find("float (SIFT)"), std::string::npos);
  auto map = dir->OpenMap("sift", sift);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_EQ((*map)->info().options.database.feature_type, FeatureType::kSift);
  EXPECT_EQ((*map)->info().vocabulary_checksum, sift->checksum());
  EXPECT_EQ((*map)->CheckVocabulary(vocabulary_).code(), StatusCode::kFailedPrecondition);
  EXPECT_TRUE((*map)->CheckVocabulary(sift).ok());
  EXPECT_EQ(dir->OpenMap("sift", vocabulary_).status().code(), StatusCode::kFailedPrecondition);
  const Status integrity = (*map)->VerifyIntegrity();
  EXPECT_TRUE(integrity.ok()) << integrity.ToString();
  EXPECT_EQ((*map)->Stats().database.places, id_of.size());
  for (const auto& [id, before] : stored) {
    auto after = (*map)->GetPlace(id);
    ASSERT_TRUE(after.ok()) << after.status().ToString();
    EXPECT_EQ(after->record.metadata, before.record.metadata);
    EXPECT_EQ(after->payload.features.sift()->image_width,
              before.payload.features.sift()->image_width);
    EXPECT_EQ(after->payload.features.sift()->keypoints, before.payload.features.sift()->keypoints);
    EXPECT_EQ(after->payload.features.sift()->descriptors,
              before.payload.features.sift()->descriptors);
    EXPECT_EQ(after->payload.direct, before.payload.direct);
    EXPECT_EQ(after->payload.bow, before.payload.bow);
  }
  // Each frame finds its own place, geometrically verified.
  for (const auto& [i, id] : id_of) {
    QueryOptions query;
    query.top_k = 3;
    auto result = (*map)->Query(frames[i], query);
    ASSERT_TRUE(result.ok()) << result.status().ToString();
    ASSERT_FALSE(result->matches.empty());
    EXPECT_EQ(result->matches[0].place, id) << "frame " << i;
    EXPECT_TRUE(result->matches[0].verified)
        << "frame " << i << ": " << result->matches[0].inliers << " inliers";
  }
  // An ORB map refuses the float vocabulary as well.
  ASSERT_TRUE(dir->CreateMap("orb", {}, vocabulary_).ok());
  dir->CloseMap("orb");
  EXPECT_EQ(dir->OpenMap("orb", sift).status().code(), StatusCode::kFailedPrecondition);
  EXPECT_TRUE(dir->OpenMap("orb", vocabulary_).ok());
}

// The frames of a revisit: 1..20 with frame 6 seen twice in a row (rehearsal merges it), then
// 1..20 again.
std::vector<int> RevisitSequence() {
  std::vector<int> sequence;
  for (int i = 1; i <= 20; ++i) {
    sequence.push_back(i);
    if (i == 6) sequence.push_back(i);
  }
  for (int i = 1; i <= 20; ++i) sequence.push_back(i);
  return sequence;
}

TEST_F(StorageTest, LoopClosureReadsLongTermMemoryFromRocksDb) {
  MapOptions options;
  LoopClosureConfig& loop = options.database.loop_closure;
  loop.max_working_memory = 5;
  loop.short_term_memory = 2;
  loop.min_candidates = 2;
  auto dir = OpenDir();
  auto map = dir->CreateMap("looping", options, vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  const std::vector<int> sequence = RevisitSequence();
  size_t valid = 0, merged = 0, retrieved = 0, transferred = 0, max_long_term = 0, loops = 0;
  for (size_t n = 0; n < sequence.size(); ++n) {
    Observation observation = RtabmapFrame(sequence[n]);
    observation.metadata.agent_id = "rover";
    observation.metadata.sequence = n + 1;
    auto frame = (*map)->Process(observation, FrameRole::kStream);
    ASSERT_TRUE(frame.ok()) << frame.status().ToString();
    ASSERT_TRUE((*map)->AdvanceStream(&*frame, "rover").ok());
    if (!frame->valid) {
      ASSERT_TRUE((*map)->Commit(*frame, observation.metadata).ok());
      continue;
    }
    ++valid;
    AddResult added;
    auto outcome = (*map)->CloseLoop(*frame, observation.metadata, &added);
    ASSERT_TRUE(outcome.ok()) << "frame " << n << ": " << outcome.status().ToString();
    if (outcome->merged) {
      ++merged;
      EXPECT_FALSE(added.stored);
      EXPECT_EQ(added.counts.static_, frame->counts.static_);
      EXPECT_NE(outcome->place, 0u);
    } else {
      EXPECT_TRUE(added.stored);
      EXPECT_EQ(outcome->place, added.id);
      EXPECT_GE(added.timings.store_ms, 0.0);
    }
    if (outcome->loop) {
      ++loops;
      EXPECT_TRUE((*map)->database()->Get(*outcome->loop)) << "a loop to an unknown place";
    }
    retrieved += outcome->retrieved;
    transferred += outcome->transferred;
    max_long_term = std::max(max_long_term, (*map)->Stats().database.loop_long_term);
  }
  std::printf("%zu valid frames, %zu merged, %zu transferred, %zu retrieved, %zu loops\n", valid,
              merged, transferred, retrieved, loops);
  EXPECT_GT(merged, 0u);
  EXPECT_GT(transferred, 0u);
  EXPECT_GT(max_long_term, 0u) << "no place ever left working memory";
  EXPECT_GT(retrieved, 0u) << "no place came back from long-term memory (RocksDB)";
  const MapStats stats = (*map)->Stats();
  EXPECT_EQ(stats.database.places, valid - merged) << "merged frames must not be stored";
  EXPECT_EQ(stats.database.streams, 1u);
  EXPECT_LE(stats.database.loop_working_memory, 2u + 5u);
  auto loop_stats = (*map)->database()->LoopStats("rover");
  ASSERT_TRUE(loop_stats.ok());
  EXPECT_EQ(loop_stats->retrieved, retrieved);
  EXPECT_EQ(loop_stats->merged, merged);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());

  // Stream state is in memory only: a reopened map starts every agent afresh.
  map->reset();
  dir->CloseMap("looping");
  dir.reset();
  dir = OpenDir();
  auto reopened = dir->OpenMap("looping", vocabulary_);
  ASSERT_TRUE(reopened.ok()) << reopened.status().ToString();
  EXPECT_EQ((*reopened)->Stats().database.places, valid - merged);
  EXPECT_EQ((*reopened)->Stats().database.streams, 0u);
  EXPECT_EQ((*reopened)->database()->LoopStats("rover").status().code(), StatusCode::kNotFound);
}

// CloseLoop commits under the lifecycle lock it already holds: deleting the map meanwhile must
// neither deadlock nor crash, and later calls see NOT_FOUND.
TEST_F(StorageTest, ConcurrentLoopClosureAndMapDeletion) {
  auto dir = OpenDir();
  MapOptions options;
  options.database.loop_closure.max_working_memory = 3;
  options.database.loop_closure.short_term_memory = 1;
  auto map = dir->CreateMap("doomed", options, vocabulary_);
  ASSERT_TRUE(map.ok());
  std::vector<ProcessedFrame> frames;
  for (int i = 1; i <= 12; ++i) {
    auto frame = (*map)->Process(RtabmapFrame(i), FrameRole::kStream);
    ASSERT_TRUE(frame.ok());
    ASSERT_TRUE((*map)->AdvanceStream(&*frame, "rover").ok());
    if (frame->valid) frames.push_back(*frame);
  }
  std::atomic<int> closed{0};
  std::atomic<int> failures{0};
  std::thread looper([&] {
    for (uint64_t n = 0;; ++n) {
      PlaceMetadata metadata;
      metadata.agent_id = "rover";
      metadata.sequence = n;
      AddResult added;
      auto outcome = (*map)->CloseLoop(frames[n % frames.size()], metadata, &added);
      if (!outcome.ok()) {
        if (outcome.status().code() != StatusCode::kNotFound) failures.fetch_add(1);
        return;
      }
      closed.fetch_add(1);
    }
  });
  while (closed.load() < 5) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  ASSERT_TRUE(dir->DeleteMap("doomed").ok());
  looper.join();
  EXPECT_EQ(failures.load(), 0);
  AddResult added;
  EXPECT_EQ((*map)->CloseLoop(frames[0], {}, &added).status().code(), StatusCode::kNotFound);
  ProcessedFrame frame = frames[0];
  EXPECT_EQ((*map)->AdvanceStream(&frame, "rover").code(), StatusCode::kNotFound);
}

TEST_F(StorageTest, DepthRemovedCountsSurviveReopen) {
  MapOptions options;
  options.store_invalid = true;
  DepthFilterConfig& filter = options.database.depth.filter;
  filter.band_policy = BandPolicy::kFixed;
  filter.fall_band = {0.0f, 1.5f};
  filter.persistence = 0;
  filter.warmup_frames = 1;
  filter.static_window = 2;
  const cv::Mat image = testing::ReadGray(testing::RtabmapFramePath(1));
  // A static scene 3 m away; then its left half comes to 1 m and stays; then all of it.
  const cv::Mat far(image.size(), CV_16U, cv::Scalar(3000));
  cv::Mat half = far.clone();
  half(cv::Rect(0, 0, image.cols / 2, image.rows)).setTo(1000);
  const cv::Mat near(image.size(), CV_16U, cv::Scalar(1000));
  uint64_t sequence = 0;
  auto observe = [&](const cv::Mat& depth) {
    Observation observation;
    observation.image = image;
    observation.depth = DepthObservation{depth, std::nullopt, std::nullopt};
    observation.metadata.agent_id = "kinect";
    observation.metadata.sequence = ++sequence;
    return observation;
  };
  std::map<PlaceId, FrameCounts> removing;  // stored places with features removed by depth
  FrameCounts invalid_counts;
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("depth", options, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    for (int i = 0; i < 3; ++i) {
      auto added = (*map)->Add(observe(far));
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      ASSERT_TRUE(added->stored) << added->rejection;
      EXPECT_EQ(added->counts.depth_removed, 0u);
    }
    for (int i = 0; i < 6; ++i) {
      auto added = (*map)->Add(observe(half));
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      ASSERT_TRUE(added->stored) << added->rejection;
      ASSERT_TRUE(added->depth_state.has_value());
      if (added->counts.depth_removed > 0) {
        EXPECT_TRUE(added->depth_state->removing);
        EXPECT_EQ(added->counts.total,
                  added->counts.dynamic + added->counts.depth_removed + added->counts.static_);
        removing[added->id] = added->counts;
      }
    }
    ASSERT_FALSE(removing.empty()) << "Algorithm 1 never removed the near half's features";
    // The whole view in the band: nothing static left, an invalid frame kept as metadata.
    auto added = (*map)->Add(observe(near));
    ASSERT_TRUE(added.ok()) << added.status().ToString();
    EXPECT_FALSE(added->stored);
    invalid_counts = added->counts;
    EXPECT_GT(invalid_counts.depth_removed, 0u);
    EXPECT_EQ(invalid_counts.static_, 0u);
  }
  auto dir = OpenDir();
  auto map = dir->OpenMap("depth", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
  for (const auto& [id, counts] : removing) {
    auto place = (*map)->GetPlace(id);
    ASSERT_TRUE(place.ok()) << place.status().ToString();
    EXPECT_EQ(place->record.counts.depth_removed, counts.depth_removed);
    EXPECT_EQ(place->record.counts.static_, counts.static_);
    EXPECT_EQ(place->record.counts.total, counts.total);
    EXPECT_EQ(place->payload.features.size(), counts.static_);
  }
  auto invalid = (*map)->InvalidObservations(10);
  ASSERT_EQ(invalid.size(), 1u);
  EXPECT_EQ(invalid[0].counts.depth_removed, invalid_counts.depth_removed);
  EXPECT_EQ(invalid[0].metadata.sequence, sequence);
  EXPECT_NE(invalid[0].reason.find("depth filter"), std::string::npos) << invalid[0].reason;
}

}  // namespace
}  // namespace placedb

namespace placedb {
namespace {

TEST(CodecFormat3, BoxRefinementShortTermAndReRankingRoundTrip) {
  DatabaseConfig config;
  config.box_refinement.method = BoxRefinement::kShape;
  config.box_refinement.max_side = 96;
  config.box_refinement.dilate_px = 3;
  config.short_term.enabled = false;
  config.short_term.horizon_ns = 5'000'000'000;
  config.short_term.max_places = 77;
  config.short_term.weight = 0.5f;
  config.verification.rerank = false;
  config.static_feature_budget = false;
  auto decoded = DecodeDatabaseConfig(EncodeDatabaseConfig(config));
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->box_refinement.method, BoxRefinement::kShape);
  EXPECT_EQ(decoded->box_refinement.max_side, 96);
  EXPECT_EQ(decoded->box_refinement.dilate_px, 3);
  EXPECT_FALSE(decoded->short_term.enabled);
  EXPECT_EQ(decoded->short_term.horizon_ns, 5'000'000'000);
  EXPECT_EQ(decoded->short_term.max_places, 77u);
  EXPECT_EQ(decoded->short_term.weight, 0.5f);
  EXPECT_FALSE(decoded->verification.rerank);
  EXPECT_FALSE(decoded->static_feature_budget);
  EXPECT_EQ(EncodeDatabaseConfig(*decoded), EncodeDatabaseConfig(config));
  // The defaults of a new map: the shape prior, the static budget, the tier and re-ranking on.
  auto defaults = DecodeDatabaseConfig(EncodeDatabaseConfig(DatabaseConfig{}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->box_refinement.method, BoxRefinement::kShape);
  EXPECT_TRUE(defaults->short_term.enabled);
  EXPECT_TRUE(defaults->verification.rerank);
  EXPECT_TRUE(defaults->static_feature_budget);
}

// ---- Dynamic-object statistics (issue 16) ---------------------------------------------------

constexpr int64_t kHourNs = int64_t(3600) * 1'000'000'000;
// 2024-01-01 00:00:00 UTC, a Monday.
constexpr int64_t kMonday2024Ns = int64_t(1704067200) * 1'000'000'000;

// An RTAB-Map frame with a person box (and a car box on every third frame) and a timestamp one
// hour after the previous frame's, starting on a Monday at midnight UTC.
Observation FrameWithObjects(int index) {
  Observation observation = RtabmapFrame(index);
  observation.metadata.timestamp_ns = kMonday2024Ns + int64_t(index) * kHourNs;
  const int width = observation.image.cols, height = observation.image.rows;
  DynamicBox person;
  person.class_id = 0;
  person.confidence = 0.9f;
  person.rect = cv::Rect2f(0, 0, float(width) * 0.1f * float(1 + index % 3), float(height) * 0.5f);
  observation.dynamic.boxes.push_back(person);
  if (index % 3 == 0) {
    DynamicBox car = person;
    car.class_id = 2;
    car.rect = cv::Rect2f(float(width) * 0.7f, float(height) * 0.6f, float(width) * 0.3f,
                          float(height) * 0.4f);
    observation.dynamic.boxes.push_back(car);
  }
  return observation;
}

// The valid frames among FrameWithObjects(1..count), processed by `map` and not committed, with
// their metadata.
void ProcessValidFramesWithObjects(const PlaceMap& map, int count,
                                   std::vector<ProcessedFrame>* frames,
                                   std::vector<PlaceMetadata>* metadata) {
  for (int i = 1; i <= count; ++i) {
    const Observation observation = FrameWithObjects(i);
    auto frame = map.Process(observation);
    ASSERT_TRUE(frame.ok()) << frame.status().ToString();
    if (!frame->valid) continue;
    frames->push_back(*frame);
    metadata->push_back(observation.metadata);
  }
}

// Each stored frame's statistics are its place's; the map's aggregate sums them; both survive
// reopening and a checkpoint, and a removed place's go while the map's history keeps them.
TEST_F(StorageTest, DynamicsAreCountedPerPlaceAndSurviveReopenAndCheckpoint) {
  std::map<PlaceId, PlaceDynamics> expected;
  PlaceDynamics all;
  const std::string backup = root_ + "/dynamics-backup";
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("moving", {}, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    for (int i = 1; i <= 30; ++i) {
      const Observation observation = FrameWithObjects(i);
      auto added = (*map)->Add(observation);
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      if (!added->stored) continue;
      // What the pipeline measured for this frame, at its timestamp.
      expected[added->id] =
          MakeObservation(added->counts.dynamic_coverage, added->boxes_used,
                          observation.metadata.timestamp_ns, std::numeric_limits<int64_t>::max());
      Merge(&all, expected[added->id]);
      auto stored = (*map)->GetDynamics(added->id);
      ASSERT_TRUE(stored.ok()) << stored.status().ToString();
      EXPECT_EQ(stored->observations, 1u);
      EXPECT_GT(stored->coverage_ppm_max, 0u) << "frame " << i << ": no coverage counted";
      EXPECT_EQ(stored->classes.at(0).boxes, 1u);
      EXPECT_EQ(stored->last_timestamp_ns, observation.metadata.timestamp_ns);
      EXPECT_EQ(stored->hours[size_t(HourBinOf(observation.metadata.timestamp_ns))].observations,
                1u);
    }
    ASSERT_GT(expected.size(), 20u);
    auto aggregate = (*map)->MapDynamics();
    ASSERT_TRUE(aggregate.ok()) << aggregate.status().ToString();
    EXPECT_EQ(*aggregate, all);
    EXPECT_EQ(aggregate->observations, expected.size());
    EXPECT_GT(aggregate->classes.at(2).frames, 0u);
    ASSERT_TRUE((*map)->Checkpoint(backup).ok());
    ASSERT_TRUE((*map)->RemovePlace(expected.begin()->first).ok());
    ASSERT_TRUE((*map)->VerifyIntegrity().ok());
  }
  const PlaceId removed = expected.begin()->first;
  auto dir = OpenDir();
  auto map = dir->OpenMap("moving", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  ASSERT_TRUE((*map)->VerifyIntegrity().ok());
  EXPECT_EQ((*map)->GetDynamics(removed).status().code(), StatusCode::kNotFound);
  auto aggregate = (*map)->MapDynamics();
  ASSERT_TRUE(aggregate.ok());
  EXPECT_EQ(*aggregate, all) << "the map's history lost the removed place's frames";
  std::map<PlaceId, PlaceDynamics> visited;
  ASSERT_TRUE((*map)
                  ->ForEachPlaceDynamics([&](PlaceId id, const PlaceDynamics& d) {
                    visited[id] = d;
                    return true;
                  })
                  .ok());
  std::map<PlaceId, PlaceDynamics> remaining = expected;
  remaining.erase(removed);
  EXPECT_EQ(visited, remaining);
  size_t seen = 0;
  ASSERT_TRUE(
      (*map)->ForEachPlaceDynamics([&](PlaceId, const PlaceDynamics&) { return ++seen < 3; }).ok());
  EXPECT_EQ(seen, 3u) << "the visitor's false must stop the scan";

  ASSERT_TRUE(dir->RestoreMap("moving-restored", backup).ok());
  auto restored = dir->OpenMap("moving-restored", vocabulary_);
  ASSERT_TRUE(restored.ok()) << restored.status().ToString();
  for (const auto& [id, d] : expected) {
    auto stored = (*restored)->GetDynamics(id);
    ASSERT_TRUE(stored.ok()) << stored.status().ToString();
    EXPECT_EQ(*stored, d) << "place " << id;
  }
  EXPECT_EQ(*(*restored)->MapDynamics(), all);
  auto scrub = (*restored)->Scrub();
  ASSERT_TRUE(scrub.ok());
  EXPECT_TRUE(scrub->clean());
}

// A map with thumbnails keeps one per place with pixels, in the place's own batch: it survives
// reopening and a checkpoint, goes with the place, is absent for precomputed features and in a map
// without thumbnails, and Scrub and VerifyIntegrity decode it.
TEST_F(StorageTest, ThumbnailsAreStoredWithThePlaceAndGoWithIt) {
  MapOptions options;
  options.thumbnails.enabled = true;
  options.thumbnails.max_side = 200;
  options.thumbnails.jpeg_quality = 60;
  std::map<PlaceId, Thumbnail> expected;
  PlaceId without_pixels = 0;
  const std::string backup = root_ + "/thumbnails-backup";
  {
    auto dir = OpenDir();
    auto map = dir->CreateMap("pictures", options, vocabulary_);
    ASSERT_TRUE(map.ok()) << map.status().ToString();
    EXPECT_EQ((*map)->info().options.thumbnails, options.thumbnails);
    for (int i = 1; i <= 20; ++i) {
      auto added = (*map)->Add(FrameWithObjects(i));
      ASSERT_TRUE(added.ok()) << added.status().ToString();
      if (!added->stored) continue;
      auto thumbnail = (*map)->GetThumbnail(added->id);
      ASSERT_TRUE(thumbnail.ok()) << thumbnail.status().ToString();
      ASSERT_TRUE(thumbnail->has_value()) << "place " << added->id;
      EXPECT_EQ((*thumbnail)->width, 200u);
      EXPECT_EQ((*thumbnail)->height, 150u);
      EXPECT_GT((*thumbnail)->jpeg.size(), 1000u);
      EXPECT_EQ((*thumbnail)->source_width, 512u);  // RTAB-Map frames are 512x384
      EXPECT_EQ((*thumbnail)->source_height, 384u);
      EXPECT_EQ((*thumbnail)->dropped_keypoints.size(), added->counts.dynamic);
      expected[added->id] = **thumbnail;
    }
    ASSERT_GT(expected.size(), 10u);
    // Precomputed features carry no pixels: the place has no thumbnail, and that is no error.
    Observation features;
    features.features = LocalFeatures(testing::ExtractFile(testing::RtabmapFramePath(40)));
    auto added = (*map)->Add(features);
    ASSERT_TRUE(added.ok() && added->stored) << added.status().ToString();
    without_pixels = added->id;
    EXPECT_FALSE((*(*map)->GetThumbnail(without_pixels)).has_value());
    ASSERT_TRUE((*map)->Checkpoint(backup).ok());
    ASSERT_TRUE((*map)->RemovePlace(expected.begin()->first).ok());
    EXPECT_EQ((*map)->GetThumbnail(expected.begin()->first).status().code(), StatusCode::kNotFound);
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
    EXPECT_EQ((*map)->GetThumbnail(9999).status().code(), StatusCode::kNotFound);

    // A map without thumbnails keeps none (and its default settings are off).
    auto plain = dir->CreateMap("plain", {}, vocabulary_);
    ASSERT_TRUE(plain.ok());
    EXPECT_FALSE((*plain)->info().options.thumbnails.enabled);
    auto stored = (*plain)->Add(FrameWithObjects(3));
    ASSERT_TRUE(stored.ok() && stored->stored);
    EXPECT_FALSE((*(*plain)->GetThumbnail(stored->id)).has_value());
    // Bad settings are refused before anything is created.
    MapOptions bad = options;
    bad.thumbnails.max_side = 2000;
    auto refused = dir->CreateMap("bad", bad, vocabulary_);
    ASSERT_FALSE(refused.ok());
    EXPECT_EQ(refused.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(refused.status().message().find("thumbnails.max_side"), std::string::npos);
  }
  const PlaceId removed = expected.begin()->first;
  auto dir = OpenDir();
  auto map = dir->OpenMap("pictures", vocabulary_);
  ASSERT_TRUE(map.ok()) << map.status().ToString();
  EXPECT_EQ((*map)->info().options.thumbnails, options.thumbnails);
  EXPECT_EQ((*map)->GetThumbnail(removed).status().code(), StatusCode::kNotFound);
  for (const auto& [id, thumbnail] : expected) {
    if (id == removed) continue;
    auto reread = (*map)->GetThumbnail(id);
    ASSERT_TRUE(reread.ok() && reread->has_value()) << "place " << id;
    EXPECT_EQ(**reread, thumbnail) << "place " << id;
  }
  ASSERT_TRUE((*map)->VerifyIntegrity().ok());
  ASSERT_TRUE(dir->RestoreMap("pictures-restored", backup).ok());
  auto restored = dir->OpenMap("pictures-restored", vocabulary_);
  ASSERT_TRUE(restored.ok()) << restored.status().ToString();
  for (const auto& [id, thumbnail] : expected) {
    auto reread = (*restored)->GetThumbnail(id);
    ASSERT_TRUE(reread.ok() && reread->has_value()) << "place " << id;
    EXPECT_EQ(**reread, thumbnail) << "place " << id;
  }
  EXPECT_FALSE((*(*restored)->GetThumbnail(without_pixels)).has_value());
  auto scrub = (*restored)->Scrub();
  ASSERT_TRUE(scrub.ok());
  EXPECT_TRUE(scrub->clean());
  EXPECT_TRUE((*restored)->VerifyIntegrity().ok());
}

// A frame refused as invalid (here: a person box over the whole view, so every descriptor is
// DC) has no place; its statistics go to the invalid frames' aggregate, not the map's. Both
// with the frame kept as metadata (a synced write) and only counted (rides on the next write).
TEST_F(StorageTest, InvalidFramesHaveTheirOwnDynamics) {
  for (bool store_invalid : {true, false}) {
    SCOPED_TRACE(store_invalid ? "store_invalid" : "counted only");
    MapOptions options;
    options.store_invalid = store_invalid;
    auto dir = OpenDir();
    const std::string name = store_invalid ? "kept" : "counted";
    auto map = dir->CreateMap(name, options, vocabulary_);
    ASSERT_TRUE(map.ok());
    Observation covered = FrameWithObjects(5);
    covered.dynamic.boxes.resize(1);
    covered.dynamic.boxes[0].rect =
        cv::Rect2f(0, 0, float(covered.image.cols), float(covered.image.rows));
    auto refused = (*map)->Add(covered);
    ASSERT_TRUE(refused.ok()) << refused.status().ToString();
    ASSERT_FALSE(refused->stored);
    auto added = (*map)->Add(FrameWithObjects(6));  // a valid frame: synced, counted as a place
    ASSERT_TRUE(added.ok() && added->stored);
    auto invalid = (*map)->InvalidDynamics();
    ASSERT_TRUE(invalid.ok()) << invalid.status().ToString();
    EXPECT_EQ(invalid->observations, 1u);
    // What the pipeline measured (box refinement narrows the box to the object's pixels).
    EXPECT_NEAR(invalid->max_coverage(), refused->counts.dynamic_coverage, 1e-6);
    EXPECT_GT(invalid->max_coverage(), 0.5);
    EXPECT_EQ(invalid->classes.at(0).frames, 1u);
    EXPECT_EQ((*map)->MapDynamics()->observations, 1u) << "the invalid frame is not a place's";
    EXPECT_TRUE((*map)->VerifyIntegrity().ok());
    map->reset();
    dir->CloseMap(name);
    auto reopened = dir->OpenMap(name, vocabulary_);
    ASSERT_TRUE(reopened.ok());
    EXPECT_EQ((*reopened)->InvalidDynamics()->observations, 1u);
  }
}

// Concurrent writers all add to the map's aggregate (one key): a merge operator loses none,
// where a read-modify-write would.
TEST_F(StorageTest, ConcurrentCommitsLoseNoDynamics) {
  auto dir = OpenDir();
  auto map = dir->CreateMap("crowd", {}, vocabulary_);
  ASSERT_TRUE(map.ok());
  std::vector<ProcessedFrame> frames;
  std::vector<PlaceMetadata> metadata;
  ProcessValidFramesWithObjects(**map, 24, &frames, &metadata);
  ASSERT_GT(frames.size(), 12u);
  std::atomic<int> failures{0};
  std::vector<std::thread> threads;
  for (size_t t = 0; t < 4; ++t) {
    threads.emplace_back([&, t] {
      for (size_t i = t; i < frames.size(); i += 4) {
        auto added = (*map)->Commit(frames[i], metadata[i]);
        if (!added.ok() || !added->stored) failures.fetch_add(1);
      }
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(failures.load(), 0);
  auto aggregate = (*map)->MapDynamics();
  ASSERT_TRUE(aggregate.ok());
  EXPECT_EQ(aggregate->observations, frames.size());
  uint64_t people = 0;
  for (const ProcessedFrame& frame : frames) {
    for (const DynamicBox& box : frame.boxes_used) people += box.class_id == 0;
  }
  EXPECT_EQ(aggregate->classes.at(0).boxes, people);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

// MapOptions::count_query_hits_above (issue 16): queries that hit a place above the score,
// counted from 3 threads while a writer stores the rest of the frames, are each counted once at
// their place and in the aggregate; off, or below the score, nothing is written. Survives reopen.
TEST_F(StorageTest, ConcurrentQueryHitsAreCountedOnce) {
  MapOptions options;
  options.count_query_hits_above = 0.3;
  auto dir = OpenDir();
  auto map = dir->CreateMap("hits", options, vocabulary_);
  ASSERT_TRUE(map.ok());
  std::vector<ProcessedFrame> frames;
  std::vector<PlaceMetadata> metadata;
  ProcessValidFramesWithObjects(**map, 24, &frames, &metadata);
  ASSERT_GT(frames.size(), 12u);
  const size_t first_half = frames.size() / 2;
  for (size_t i = 0; i < first_half; ++i) ASSERT_TRUE((*map)->Commit(frames[i], metadata[i]).ok());

  std::atomic<int> failures{0};
  std::mutex mutex;
  std::map<PlaceId, uint64_t> hits;  // place -> hits counted
  std::vector<std::thread> threads;
  threads.emplace_back([&] {  // the writer: the second half
    for (size_t i = first_half; i < frames.size(); ++i) {
      if (!(*map)->Commit(frames[i], metadata[i]).ok()) failures.fetch_add(1);
    }
  });
  for (size_t t = 0; t < 3; ++t) {
    threads.emplace_back([&, t] {
      for (size_t i = t; i < first_half; i += 3) {
        const QueryResult result = (*map)->Search(frames[i], QueryOptions{});
        auto counted = (*map)->CountQueryHit(frames[i], metadata[i], result);
        if (!counted.ok()) failures.fetch_add(1);
        if (counted.ok() && *counted) {
          std::lock_guard lock(mutex);
          ++hits[result.matches.front().place];
        }
      }
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(failures.load(), 0);
  ASSERT_GE(hits.size(), first_half / 2) << "the stored frames should match themselves";
  uint64_t counted = 0;
  for (const auto& [place, n] : hits) {
    counted += n;
    auto d = (*map)->GetDynamics(place);
    ASSERT_TRUE(d.ok());
    EXPECT_EQ(d->observations, 1 + n) << place;
  }
  auto aggregate = (*map)->MapDynamics();
  ASSERT_TRUE(aggregate.ok());
  EXPECT_EQ(aggregate->observations, frames.size() + counted);

  // Below the score, or invalid: false, nothing written.
  QueryResult weak = (*map)->Search(frames[0], QueryOptions{});
  ASSERT_FALSE(weak.matches.empty());
  weak.matches.front().score = 0.3;  // not above
  auto below = (*map)->CountQueryHit(frames[0], metadata[0], weak);
  ASSERT_TRUE(below.ok());
  EXPECT_FALSE(*below);
  weak.valid = false;
  weak.matches.front().score = 0.9;
  EXPECT_FALSE(*(*map)->CountQueryHit(frames[0], metadata[0], weak));
  EXPECT_EQ((*map)->MapDynamics()->observations, frames.size() + counted);
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());

  // The setting is the map's: it survives a reopen, and a map without it counts nothing.
  map->reset();
  dir.reset();
  dir = OpenDir();
  auto reopened = dir->OpenMap("hits", vocabulary_);
  ASSERT_TRUE(reopened.ok()) << reopened.status().ToString();
  EXPECT_EQ((*reopened)->info().options.count_query_hits_above, 0.3);
  EXPECT_EQ((*reopened)->MapDynamics()->observations, frames.size() + counted);
  auto plain = dir->CreateMap("plain", {}, vocabulary_);
  ASSERT_TRUE(plain.ok());
  ASSERT_TRUE((*plain)->Commit(frames[0], metadata[0]).ok());
  const QueryResult strong = (*plain)->Search(frames[0], QueryOptions{});
  EXPECT_FALSE(*(*plain)->CountQueryHit(frames[0], metadata[0], strong));
  EXPECT_EQ((*plain)->MapDynamics()->observations, 1u);
}

// A frame loop-closure rehearsal merges into a place is counted at that place: every valid
// frame is counted once, stored or merged.
TEST_F(StorageTest, DynamicsCountFramesMergedByRehearsal) {
  MapOptions options;
  options.database.loop_closure.max_working_memory = 5;
  options.database.loop_closure.short_term_memory = 2;
  options.database.loop_closure.min_candidates = 2;
  auto dir = OpenDir();
  auto map = dir->CreateMap("rehearsed", options, vocabulary_);
  ASSERT_TRUE(map.ok());
  const std::vector<int> sequence = RevisitSequence();
  size_t valid = 0, merged = 0;
  std::map<PlaceId, uint64_t> frames_at;
  for (size_t n = 0; n < sequence.size(); ++n) {
    Observation observation = FrameWithObjects(sequence[n]);
    observation.metadata.agent_id = "rover";
    observation.metadata.sequence = n + 1;
    auto frame = (*map)->Process(observation, FrameRole::kStream);
    ASSERT_TRUE(frame.ok());
    ASSERT_TRUE((*map)->AdvanceStream(&*frame, "rover").ok());
    if (!frame->valid) {
      ASSERT_TRUE((*map)->Commit(*frame, observation.metadata).ok());
      continue;
    }
    ++valid;
    AddResult added;
    auto outcome = (*map)->CloseLoop(*frame, observation.metadata, &added);
    ASSERT_TRUE(outcome.ok()) << outcome.status().ToString();
    merged += outcome->merged;
    ++frames_at[outcome->place];
  }
  ASSERT_GT(merged, 0u) << "the sequence no longer exercises rehearsal";
  auto aggregate = (*map)->MapDynamics();
  ASSERT_TRUE(aggregate.ok());
  EXPECT_EQ(aggregate->observations, valid) << "invalid frames are not counted; valid ones are";
  for (const auto& [id, count] : frames_at) {
    auto stored = (*map)->GetDynamics(id);
    ASSERT_TRUE(stored.ok()) << stored.status().ToString();
    EXPECT_EQ(stored->observations, count) << "place " << id;
  }
  EXPECT_TRUE((*map)->VerifyIntegrity().ok());
}

// Statistics never reach the serving index: a persistent map (which keeps them) and an
// in-memory PlaceDatabase (which has none) keep the same descriptors and rank identically.
TEST_F(StorageTest, DynamicsNeverChangeDescriptorsOrRanking) {
  MapOptions options;
  options.database.verification.mode = VerificationMode::kExhaustive;
  auto dir = OpenDir();
  auto map = dir->CreateMap("ranked", options, vocabulary_);
  ASSERT_TRUE(map.ok());
  auto memory = PlaceDatabase::Create(vocabulary_, options.database);
  ASSERT_TRUE(memory.ok());
  std::vector<Observation> frames;
  for (int i = 1; i <= 40; ++i) frames.push_back(FrameWithObjects(i));
  for (size_t i = 0; i < frames.size(); i += 2) {
    auto stored = (*map)->Add(frames[i]);
    auto kept = (*memory)->Add(frames[i]);
    ASSERT_TRUE(stored.ok() && kept.ok());
    ASSERT_EQ(stored->stored, kept->stored);
    ASSERT_EQ(stored->id, kept->id);
    EXPECT_EQ(stored->counts.static_, kept->counts.static_);
    EXPECT_EQ(stored->counts.dynamic, kept->counts.dynamic);
  }
  auto aggregate = (*map)->MapDynamics();
  ASSERT_TRUE(aggregate.ok());
  ASSERT_GT(aggregate->observations, 0u);
  for (const Observation& query : frames) {
    auto a = (*map)->Query(query, {});
    auto b = (*memory)->Query(query, {});
    ASSERT_TRUE(a.ok() && b.ok());
    ASSERT_EQ(a->matches.size(), b->matches.size());
    for (size_t m = 0; m < a->matches.size(); ++m) {
      EXPECT_EQ(a->matches[m].place, b->matches[m].place);
      EXPECT_EQ(a->matches[m].score, b->matches[m].score);
      EXPECT_EQ(a->matches[m].inliers, b->matches[m].inliers);
    }
  }
  for (PlaceId id : (*map)->database()->ListPlaces()) {
    auto place = (*map)->GetPlace(id);
    ASSERT_TRUE(place.ok());
    EXPECT_EQ(place->payload.features.size(), (*memory)->Get(id)->counts.static_);
  }
}

}  // namespace
}  // namespace placedb
