// placedb-fuzz-seeds OUT_DIR [CONFIG_YAML]: writes the fuzz targets' seed corpora from real data
// (../shared, as tools/shared_data.h finds it) into OUT_DIR/<target>/, and the generated
// dictionaries (the keys of the configuration YAML and of the JSON records) as
// OUT_DIR/<target>.dict. Run by tools/fuzz.sh; the corpora are build products, never committed
// (docs/fuzzing.md).
//
// Every seed is a valid input of its target's format (the first byte selects the target's mode,
// as each target documents), small so that the fuzzers mutate it quickly: real camera frames
// downscaled to 48-96 pixels wide, a dozen real ORB/SIFT features, tiny vocabularies trained on
// real descriptors.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include "core/base/files.h"
#include "core/features/orb_features.h"
#include "core/features/sift_features.h"
#include "core/storage/codec.h"
#include "core/vocabulary/float_vocabulary.h"
#include "core/vocabulary/vocabulary.h"
#include "core/vocabulary/vocabulary_trainer.h"
#include "eval/dataset.h"
#include "proto/convert_config.h"
#include "proto/convert_frame.h"
#include "proto/placedb.pb.h"
#include "server/backend/map_registry.h"
#include "server/config.h"
#include "tests/fuzz/fuzz_support.h"
#include "tools/shared_data.h"

namespace placedb {
namespace {

namespace fs = std::filesystem;
namespace v1 = ::placedb::v1;

std::string g_out;
int g_written = 0;

[[noreturn]] void Die(const std::string& what, const Status& status = Status::Ok()) {
  std::fprintf(stderr, "placedb-fuzz-seeds: %s%s%s\n", what.c_str(), status.ok() ? "" : ": ",
               status.ok() ? "" : status.ToString().c_str());
  std::exit(1);
}

template <typename T>
T Check(Result<T> result, const std::string& what) {
  if (!result.ok()) Die(what, result.status());
  return std::move(result).value();
}

// Writes one seed: the mode byte (when >= 0) followed by `bytes`.
void Seed(const std::string& target, const std::string& name, int mode, const std::string& bytes) {
  const fs::path dir = fs::path(g_out) / target;
  fs::create_directories(dir);
  std::ofstream out(dir / name, std::ios::binary | std::ios::trunc);
  if (mode >= 0) out.put(char(mode));
  out.write(bytes.data(), std::streamsize(bytes.size()));
  if (!out) Die("cannot write " + (dir / name).string());
  ++g_written;
}

void Dictionary(const std::string& target, const std::set<std::string>& tokens) {
  std::ofstream out(fs::path(g_out) / (target + ".dict"), std::ios::trunc);
  for (const std::string& token : tokens) {
    out << '"';
    for (char c : token) {
      if (c == '"' || c == '\\') out << '\\';
      out << c;
    }
    out << "\"\n";
  }
  if (!out) Die("cannot write the dictionary of " + target);
}

void JsonKeys(const nlohmann::json& j, std::set<std::string>* keys) {
  if (j.is_object()) {
    for (auto it = j.begin(); it != j.end(); ++it) {
      keys->insert("\"" + it.key() + "\"");
      JsonKeys(it.value(), keys);
    }
  } else if (j.is_array()) {
    for (const auto& value : j) JsonKeys(value, keys);
  }
}

std::string Encode(const cv::Mat& image, const std::string& extension,
                   const std::vector<int>& params = {}) {
  std::vector<uchar> bytes;
  if (!cv::imencode(extension, image, bytes, params)) Die("cannot encode " + extension);
  return std::string(bytes.begin(), bytes.end());
}

cv::Mat Shrink(const cv::Mat& image, int width, int interpolation = cv::INTER_AREA) {
  cv::Mat out;
  cv::resize(image, out, cv::Size(width, std::max(1, image.rows * width / image.cols)), 0, 0,
             interpolation);
  return out;
}

cv::Mat Read(const std::string& path, int flags = cv::IMREAD_COLOR) {
  cv::Mat image = cv::imread(path, flags);
  if (image.empty()) Die("cannot read " + path);
  return image;
}

// The real data every seed is made of.
struct RealData {
  std::vector<cv::Mat> frames;  // CamVid frames, colour
  cv::Mat labels;               // CamVid label map of frames[0] (8 Car, 9 Pedestrian, ...)
  cv::Mat depth;                // RGB-D people: 16-bit depth, millimetres
  cv::Mat depth_image;          // its colour frame
};

RealData LoadRealData() {
  const std::string shared = data::SharedDir() + "/data";
  if (!fs::is_directory(shared)) Die("no shared data at " + shared + " (PLACEDB_SHARED_DIR)");
  RealData data;
  const auto camvid = Check(ListImageFiles(shared + "/camvid/images"), "listing CamVid");
  if (camvid.size() < 3) Die("CamVid has fewer than 3 images");
  for (size_t i = 0; i < 3; ++i) data.frames.push_back(Read(camvid[i * camvid.size() / 3]));
  const std::string label =
      shared + "/camvid/labels/" + fs::path(camvid[0]).stem().string() + ".png";
  data.labels = Read(label, cv::IMREAD_GRAYSCALE);
  const std::string rgbd = shared + "/rgbd-people";
  const auto depths = Check(ListImageFiles(rgbd + "/depth/test1"), "listing RGB-D depth");
  if (depths.empty()) Die("no RGB-D depth images");
  data.depth = Read(depths[0], cv::IMREAD_UNCHANGED);
  if (data.depth.type() != CV_16UC1) Die(depths[0] + " is not 16-bit depth");
  data.depth_image = Read(rgbd + "/image/test1/" + fs::path(depths[0]).filename().string());
  return data;
}

cv::Mat Gray(const cv::Mat& image) {
  cv::Mat gray;
  cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  return gray;
}

FeatureSet Orb(const cv::Mat& image, int count) {
  OrbConfig config;
  config.max_features = count;
  return Check(ExtractOrb(Gray(image), config), "ORB");
}

FloatFeatureSet Sift(const cv::Mat& image, int count) {
  SiftConfig config;
  config.max_features = count;
  return Check(ExtractSift(Gray(image), config), "SIFT");
}

// With only 3 training images most words occur in all of them, and TF-IDF gives those weight 0
// (and empty BoW vectors): seeds that need words use TF weighting.
std::shared_ptr<const Vocabulary> TinyVocabulary(const RealData& data, int k, int levels,
                                                 WeightingType weighting) {
  std::vector<std::vector<Descriptor256>> images;
  for (const cv::Mat& frame : data.frames) images.push_back(Orb(frame, 300).descriptors);
  TrainerConfig config;
  config.branching = k;
  config.depth = levels;
  config.threads = 1;
  config.weighting = weighting;
  return Check(TrainVocabulary(images, config), "training a tiny vocabulary");
}

std::shared_ptr<const FloatVocabulary> TinyFloatVocabulary(const RealData& data) {
  std::vector<std::vector<float>> images;
  for (const cv::Mat& frame : data.frames) images.push_back(Sift(frame, 60).descriptors);
  FloatTrainerConfig config;
  config.branching = 3;
  config.depth = 2;
  config.weighting = WeightingType::kTf;
  return Check(FloatVocabulary::Train(images, kSiftDimensions, config),
               "training a tiny SIFT vocabulary");
}

DynamicBox Box(int class_id, float confidence, float x, float y, float w, float h) {
  DynamicBox box;
  box.class_id = class_id;
  box.confidence = confidence;
  box.rect = cv::Rect2f(x, y, w, h);
  return box;
}

// ---- per target ------------------------------------------------------------------------------

void CodecSeeds(const RealData& data, const Vocabulary& vocabulary,
                const FloatVocabulary& float_vocabulary) {
  const std::string t = "fuzz_codec";
  Seed(t, "place-key", 0, PlaceKey(42));
  Seed(t, "u64-key", 0, U64Key(123456789));

  PlaceRecord record;
  record.id = 17;
  record.metadata.agent_id = "robot-1";
  record.metadata.sequence = 6690;
  record.metadata.timestamp_ns = 1534837737203029000;
  record.metadata.pose = Pose{{1.5, -2.0, 0.25}, {0, 0, 0.7071, 0.7071}};
  record.counts = {
      .total = 300, .dynamic = 40, .static_ = 250, .dynamic_coverage = 0.12, .depth_removed = 10};
  record.boxes_used = {Box(0, 0.9f, 10, 20, 30, 60), Box(2, 0.6f, 200, 150, 120, 80)};
  Seed(t, "place-record", 1, EncodePlaceRecord(record));

  const FeatureSet orb = Orb(data.frames[0], 24);
  BowVector bow;
  DirectIndex direct;
  vocabulary.Transform(orb.descriptors, &bow, &direct, 1);
  Seed(t, "bow", 2, EncodeBow(bow));
  Seed(t, "features", 3, EncodeFeatures(orb, direct));
  Seed(t, "local-features-orb", 5, EncodeLocalFeatures(orb, direct));
  // Version 2: a place stored with its camera and keypoint depths (issue 32).
  FrameGeometry geometry;
  geometry.camera = PinholeCamera(orb.image_width, orb.image_height, 500, 500,
                                  orb.image_width / 2.0, orb.image_height / 2.0);
  geometry.camera->distortion_model = "plumb_bob";
  geometry.camera->distortion = {0.1, -0.05, 0.001, 0.002, 0.0};
  for (size_t i = 0; i < orb.size(); ++i) geometry.depth_m.push_back(i % 3 == 0 ? 0.0f : 1.5f + i);
  Seed(t, "features-geometry", 3, EncodeFeatures(orb, direct, geometry));
  Seed(t, "local-features-orb-geometry", 5, EncodeLocalFeatures(orb, direct, geometry));

  FloatFeatureSet sift = Sift(data.frames[1], 4);
  BowVector float_bow;
  DirectIndex float_direct;
  float_vocabulary.Transform(sift.descriptors, &float_bow, &float_direct, 0);
  Seed(t, "float-features", 4, EncodeFloatFeatures(sift, float_direct));
  Seed(t, "local-features-sift", 6, EncodeLocalFeatures(sift, float_direct));

  DatabaseConfig config;
  Seed(t, "database-config-orb", 7, EncodeDatabaseConfig(config));
  config.feature_type = FeatureType::kSift;
  Seed(t, "database-config-sift", 7, EncodeDatabaseConfig(config));

  InvalidObservation invalid;
  invalid.serial = 3;
  invalid.metadata = record.metadata;
  invalid.counts = {.total = 12, .dynamic = 9, .static_ = 3};
  invalid.boxes_used = record.boxes_used;
  invalid.reason = "3 static descriptors <= placeThreshold 10";
  Seed(t, "invalid-observation", 8, EncodeInvalidObservation(invalid));

  ThumbnailSettings thumbnails;
  thumbnails.enabled = true;
  thumbnails.max_side = 64;
  const std::vector<Keypoint> dropped = {orb.keypoints.begin(), orb.keypoints.begin() + 3};
  auto thumbnail = MakeThumbnail(data.frames[0], record.boxes_used, dropped, thumbnails);
  if (!thumbnail.ok()) Die("thumbnail: " + thumbnail.status().ToString());
  Seed(t, "thumbnail", 9, EncodeThumbnail(*thumbnail));

  std::set<std::string> keys;
  JsonKeys(nlohmann::json::parse(EncodeDatabaseConfig(config)), &keys);
  Dictionary(t, keys);
}

void MapSettingsSeeds() {
  const std::string t = "fuzz_map_settings";
  using server::MapRegistry;
  wire::ServiceMapSettings settings;
  Seed(t, "service-default", 0, MapRegistry::EncodeSettings(settings));
  settings.box_source = BoxSource::kBoth;
  settings.detection_enabled = false;
  Seed(t, "service-both", 0, MapRegistry::EncodeSettings(settings));

  std::set<std::string> keys;
  for (const FeatureType type : {FeatureType::kOrb, FeatureType::kSift}) {
    MapOptions options;
    options.database.feature_type = type;
    const std::string name = FeatureTypeName(type);
    // The map info as DataDirectory stores it (core/storage/data_directory.cc EncodeInfo).
    nlohmann::json info;
    info["name"] = "fuzz-" + name;
    info["database"] = nlohmann::json::parse(EncodeDatabaseConfig(options.database));
    info["store_invalid"] = true;
    info["service"] = MapRegistry::EncodeSettings(settings);
    info["vocabulary_checksum"] = 0x1234abcd5678ef01ull;
    info["created_unix_ms"] = 1700000000000;
    Seed(t, "map-info-" + name, 1, info.dump());
    JsonKeys(info, &keys);
    JsonKeys(nlohmann::json::parse(MapRegistry::EncodeSettings(settings)), &keys);

    v1::CreateMapRequest request;
    request.set_name("fuzz-" + name);
    wire::MapConfigToProto(options, settings, "default", request.mutable_config());
    Seed(t, "create-map-" + name, type == FeatureType::kOrb ? 2 : 3, request.SerializeAsString());
    v1::CreateMapRequest empty;
    empty.set_name("fuzz");
    Seed(t, "create-map-defaults-" + name, type == FeatureType::kOrb ? 2 : 3,
         empty.SerializeAsString());
  }
  Dictionary(t, keys);
}

void ServerConfigSeeds(const std::string& config_yaml) {
  const std::string t = "fuzz_server_config";
  const std::string example = Check(ReadWholeFile(config_yaml), "reading " + config_yaml);
  Seed(t, "placedb.yaml", 0, example);
  const std::string printed = server::ConfigToYaml(server::ServerConfig{});
  Seed(t, "print-config", 0, printed);
  Seed(t, "environment", 3,
       "PLACEDB_LISTEN=127.0.0.1:50051\nPLACEDB_DATA_DIR=/var/lib/placedb\n"
       "PLACEDB_METRICS_LISTEN=off\nPLACEDB_METRICS_PORT=9464\nPLACEDB_THREADS=4\n"
       "PLACEDB_LOG_LEVEL=debug\nPLACEDB_DETECTOR_MODEL=off\n");
  // Keys of both YAML texts ("key:"), for the dictionary.
  std::set<std::string> keys;
  const std::regex key(R"(^\s*([A-Za-z_][A-Za-z0-9_]*):)");
  for (const std::string* text : {&example, &printed}) {
    std::istringstream lines(*text);
    for (std::string line; std::getline(lines, line);) {
      std::smatch m;
      if (std::regex_search(line, m, key)) keys.insert(m[1].str() + ":");
    }
  }
  for (const char* name :
       {"PLACEDB_LISTEN=", "PLACEDB_DATA_DIR=", "PLACEDB_METRICS_LISTEN=", "PLACEDB_METRICS_PORT=",
        "PLACEDB_THREADS=", "PLACEDB_LOG_LEVEL=", "PLACEDB_DETECTOR_MODEL="}) {
    keys.insert(name);
  }
  Dictionary(t, keys);
}

void VocabularySeeds(const RealData& data) {
  const std::string scratch = fuzz::ScratchDir();
  int n = 0;
  for (const auto& [k, levels, weighting] :
       std::vector<std::tuple<int, int, WeightingType>>{{4, 2, WeightingType::kTfIdf},
                                                        {3, 3, WeightingType::kTf},
                                                        {2, 1, WeightingType::kIdf}}) {
    const auto vocabulary = TinyVocabulary(data, k, levels, weighting);
    const std::string name = "k" + std::to_string(k) + "-L" + std::to_string(levels);
    const std::string binary = scratch + "/seed" + std::to_string(n) + ".pdbv";
    const std::string text = scratch + "/seed" + std::to_string(n++) + ".txt";
    if (Status s = vocabulary->SaveBinary(binary); !s.ok()) Die("saving a vocabulary", s);
    if (Status s = vocabulary->ExportDbow2Text(text); !s.ok()) Die("exporting a vocabulary", s);
    const std::string binary_bytes = fuzz::ReadWholeFileOrDie(binary);
    Seed("fuzz_vocabulary_binary", name + "-fixed", 1, binary_bytes);
    Seed("fuzz_vocabulary_binary", name, 0, binary_bytes);
    Seed("fuzz_vocabulary_dbow2_text", name, -1, fuzz::ReadWholeFileOrDie(text));
  }
  const auto float_vocabulary = TinyFloatVocabulary(data);
  const std::string path = scratch + "/seed.pdbfv";
  if (Status s = float_vocabulary->Save(path); !s.ok()) Die("saving a SIFT vocabulary", s);
  const std::string bytes = fuzz::ReadWholeFileOrDie(path);
  Seed("fuzz_float_vocabulary", "k3-L2-repaired", 3, bytes);
  Seed("fuzz_float_vocabulary", "k3-L2", 0, bytes);
}

void AddBoxes(v1::Observation* observation, int width, int height) {
  for (const DynamicBox& box :
       {Box(0, 0.9f, width * 0.1f, height * 0.2f, width * 0.2f, height * 0.6f),
        Box(2, 0.7f, width * 0.5f, height * 0.5f, width * 0.4f, height * 0.3f)}) {
    wire::AgentBoxToProto(box, observation->add_boxes());
  }
  v1::Box* named = observation->add_boxes();
  named->set_class_name("bicycle");
  named->set_confidence(0.5f);
  named->mutable_rect()->set_x(1);
  named->mutable_rect()->set_y(1);
  named->mutable_rect()->set_width(float(width) / 4);
  named->mutable_rect()->set_height(float(height) / 4);
}

void SetFeatures(const FeatureSet& orb, v1::Features* out) {
  out->set_image_width(uint32_t(orb.image_width));
  out->set_image_height(uint32_t(orb.image_height));
  std::string descriptors;
  for (size_t i = 0; i < orb.size(); ++i) {
    const Keypoint& k = orb.keypoints[i];
    v1::Keypoint* p = out->add_keypoints();
    p->set_x(k.x);
    p->set_y(k.y);
    p->set_size(k.size);
    p->set_angle(k.angle);
    p->set_response(k.response);
    p->set_octave(k.octave);
    descriptors.append(reinterpret_cast<const char*>(orb.descriptors[i].bytes()),
                       Descriptor256::kBytes);
  }
  out->set_descriptors(descriptors);
}

void SetSiftFeatures(const FloatFeatureSet& sift, v1::SiftFeatures* out) {
  out->set_image_width(uint32_t(sift.image_width));
  out->set_image_height(uint32_t(sift.image_height));
  for (const Keypoint& k : sift.keypoints) {
    v1::Keypoint* p = out->add_keypoints();
    p->set_x(k.x);
    p->set_y(k.y);
    p->set_size(k.size);
    p->set_angle(k.angle);
    p->set_response(k.response);
    p->set_octave(k.octave);
  }
  out->set_descriptors(std::string(reinterpret_cast<const char*>(sift.descriptors.data()),
                                   sift.descriptors.size() * sizeof(float)));
}

cv::Mat MaskFromLabels(const cv::Mat& labels, int width) {
  cv::Mat small = Shrink(labels, width, cv::INTER_NEAREST);
  cv::Mat mask = (small == 8) | (small == 9) | (small == 10);  // car, pedestrian, bicyclist
  return mask;
}

void ObservationSeeds(const RealData& data) {
  const std::string t = "fuzz_observation";
  const cv::Mat frame = Shrink(data.frames[0], 64);
  const int w = frame.cols;
  const int h = frame.rows;

  v1::IngestRequest header;
  header.mutable_header()->set_map("fuzz");
  header.mutable_header()->mutable_matches()->set_top_k(5);
  header.mutable_header()->set_loop_closure(true);
  Seed(t, "ingest-header", 0, header.SerializeAsString());

  // An encoded JPEG with boxes and a mask, as agents with their own detector send it.
  v1::Observation image;
  image.set_agent_id("robot-1");
  image.set_sequence(6690);
  image.set_timestamp_ns(1534837737203029000);
  image.mutable_encoded_image()->set_data(Encode(frame, ".jpg", {cv::IMWRITE_JPEG_QUALITY, 70}));
  AddBoxes(&image, w, h);
  image.set_dynamic_mask_png(Encode(MaskFromLabels(data.labels, w), ".png"));
  image.mutable_matches()->set_top_k(3);
  v1::IngestRequest ingest;
  *ingest.mutable_observation() = image;
  Seed(t, "ingest-jpeg-boxes-mask", 0, ingest.SerializeAsString());
  Seed(t, "ingest-jpeg-boxes-mask-color", 2, ingest.SerializeAsString());

  // Precomputed ORB features of a real frame (at its own, larger size).
  const cv::Mat medium = Shrink(data.frames[1], 160);
  v1::Observation features;
  features.set_agent_id("robot-2");
  SetFeatures(Orb(medium, 16), features.mutable_features());
  AddBoxes(&features, medium.cols, medium.rows);
  v1::QueryRequest query;
  query.set_map("fuzz");
  *query.mutable_observation() = features;
  query.mutable_options()->set_top_k(4);
  query.mutable_options()->set_verified_only(true);
  Seed(t, "query-orb-features", 1, query.SerializeAsString());
  *ingest.mutable_observation() = features;
  Seed(t, "ingest-orb-features", 0, ingest.SerializeAsString());

  // SIFT features.
  v1::Observation sift;
  SetSiftFeatures(Sift(medium, 3), sift.mutable_sift_features());
  *query.mutable_observation() = sift;
  Seed(t, "query-sift-features", 1, query.SerializeAsString());

  // A raw grayscale frame with 16-bit PNG depth and intrinsics (RGB-D people).
  const cv::Mat rgbd = Shrink(data.depth_image, 48);
  v1::Observation raw;
  raw.set_agent_id("kinect");
  v1::RawImage* pixels = raw.mutable_raw_image();
  const cv::Mat gray = Gray(rgbd);
  pixels->set_width(uint32_t(gray.cols));
  pixels->set_height(uint32_t(gray.rows));
  pixels->set_format(v1::PIXEL_FORMAT_GRAY8);
  pixels->set_data(std::string(reinterpret_cast<const char*>(gray.data), gray.total()));
  const cv::Mat depth = Shrink(data.depth, 48, cv::INTER_NEAREST);
  raw.mutable_depth()->set_png16(Encode(depth, ".png"));
  v1::Intrinsics* intrinsics = raw.mutable_depth()->mutable_intrinsics();
  intrinsics->set_fx(40);
  intrinsics->set_fy(40);
  intrinsics->set_cx(24);
  intrinsics->set_cy(gray.rows / 2.0);
  AddBoxes(&raw, gray.cols, gray.rows);
  *ingest.mutable_observation() = raw;
  Seed(t, "ingest-raw-depth-png16", 0, ingest.SerializeAsString());
  // The same for server-side detection (colour): a GRAY8 frame must come out as BGR.
  Seed(t, "ingest-raw-depth-png16-color", 2, ingest.SerializeAsString());

  // The same depth as raw float32 metres, quarter size.
  const cv::Mat quarter = Shrink(data.depth, 12, cv::INTER_NEAREST);
  cv::Mat metres;
  quarter.convertTo(metres, CV_32F, 0.001);
  v1::RawDepth* raw_depth = raw.mutable_depth()->mutable_raw_float32();
  raw_depth->set_width(uint32_t(metres.cols));
  raw_depth->set_height(uint32_t(metres.rows));
  raw_depth->set_data(
      std::string(reinterpret_cast<const char*>(metres.data), metres.total() * sizeof(float)));
  *query.mutable_observation() = raw;
  Seed(t, "query-raw-depth-float", 1, query.SerializeAsString());
}

void ImageSeeds(const RealData& data) {
  const std::string t = "fuzz_image";
  const cv::Mat small = Shrink(data.frames[2], 48);
  Seed(t, "jpeg-gray", 0, Encode(Gray(small), ".jpg", {cv::IMWRITE_JPEG_QUALITY, 60}));
  Seed(t, "jpeg-color", 1, Encode(small, ".jpg", {cv::IMWRITE_JPEG_QUALITY, 60}));
  Seed(t, "jpeg-progressive", 1,
       Encode(small, ".jpg", {cv::IMWRITE_JPEG_QUALITY, 60, cv::IMWRITE_JPEG_PROGRESSIVE, 1}));
  Seed(t, "png-color", 0, Encode(Shrink(data.frames[0], 24), ".png"));
  Seed(t, "png-gray", 1, Encode(Gray(Shrink(data.frames[1], 24)), ".png"));
  Seed(t, "mask-png", 2, Encode(MaskFromLabels(data.labels, 32), ".png"));
  Seed(t, "depth-png16", 3, Encode(Shrink(data.depth, 32, cv::INTER_NEAREST), ".png"));
}

void EvalDatasetSeeds() {
  const std::string t = "fuzz_eval_dataset";
  eval::Dataset dataset;
  dataset.name = "camvid-mini";
  dataset.description = "two places, seen twice";
  dataset.directory = fuzz::ScratchDir() + "/eval-seed";
  eval::Entry a;
  a.id = "0001TP_006690";
  a.image = "img0.png";
  a.mask = "mask0.png";
  a.agent = "0001TP";
  a.sequence = 6690;
  a.timestamp_ns = 223000000;
  eval::Entry b = a;
  b.id = "0001TP_006720";
  b.image = "img1.png";
  b.mask = "mask1.png";
  b.mask_values = {8, 9, 10};
  b.sequence = 6720;
  b.boxes = std::vector<DynamicBox>{Box(0, 1.0f, 2, 2, 6, 5), Box(2, 0.8f, 8, 6, 4, 4)};
  eval::Entry q1;
  q1.id = "q1";
  q1.image = "img2.png";
  q1.coverage = 0.25;
  q1.source = "synthetic: \"occluded\", shifted";
  q1.ground_truth = {a.id};
  eval::Entry q2;
  q2.id = "q2";
  q2.image = "img3.png";
  q2.boxes = std::vector<DynamicBox>{};
  q2.ground_truth = {a.id, b.id};
  dataset.database = {a, b};
  dataset.queries = {q1, q2};
  if (Status s = eval::ValidateDataset(dataset, false); !s.ok()) Die("the eval seed", s);
  if (Status s = eval::SaveDataset(dataset); !s.ok()) Die("saving the eval seed", s);
  const std::string json = fuzz::ReadWholeFileOrDie(dataset.directory + "/dataset.json");
  Seed(t, "dataset-json", 0, json);
  std::set<std::string> keys;
  JsonKeys(nlohmann::json::parse(json), &keys);
  Dictionary(t, keys);
  fs::remove(dataset.directory + "/dataset.json");
  if (Status s = eval::SaveDatasetCsv(dataset); !s.ok()) Die("saving the eval CSV seed", s);
  std::string csv;
  for (const char* name : {"database.csv", "queries.csv", "ground_truth.csv", "boxes.csv"}) {
    const std::string path = dataset.directory + "/" + name;
    if (!csv.empty()) csv += fuzz::kPartSeparator;
    if (fs::exists(path)) csv += fuzz::ReadWholeFileOrDie(path);
  }
  Seed(t, "dataset-csv", 1, csv);
}

}  // namespace
}  // namespace placedb

int main(int argc, char** argv) {
  using namespace placedb;
  if (argc < 2 || argc > 3) {
    std::fprintf(stderr, "usage: placedb-fuzz-seeds OUT_DIR [CONFIG_YAML]\n");
    return 2;
  }
  g_out = argv[1];
  const std::string config_yaml = argc == 3 ? argv[2] : "server/placedb.yaml";
  const RealData data = LoadRealData();
  const auto vocabulary = TinyVocabulary(data, 4, 2, WeightingType::kTf);
  const auto float_vocabulary = TinyFloatVocabulary(data);
  CodecSeeds(data, *vocabulary, *float_vocabulary);
  MapSettingsSeeds();
  ServerConfigSeeds(config_yaml);
  VocabularySeeds(data);
  ObservationSeeds(data);
  ImageSeeds(data);
  EvalDatasetSeeds();
  std::printf("placedb-fuzz-seeds: %d seeds from %s in %s\n", g_written, data::SharedDir().c_str(),
              g_out.c_str());
  return 0;
}
