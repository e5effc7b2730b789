// placedb storage benchmark: prints `name value unit` lines.
//
//  1. The paper's Fig. 6 on real data: all 701 CamVid frames (ORB 1000) ingested into one map
//     without filtering (BoBW) and one with it (BoBW+DO: boxes = bounding boxes of the label
//     maps' Car/Pedestrian/Bicyclist components, the paper's keypoint-in-box rule), then bytes
//     on disk after a flush, the reduction, bytes per place, and ingest rates.
//  2. Persist rate (durable commit + index) by sync policy with 1, 2 and 8 concurrent writers,
//     each with and without the ACKED high-water mark (StorageOptions::acked_file), same run.
//  2b. The cost of dynamic-object statistics (issue 16, StorageOptions::dynamics): the 701
//     CamVid frames with their boxes ingested one by one (Add: process + durable commit + index)
//     with and without, same run; goal < 2 % of ingest time.
//  2c. The cost of thumbnails (issue 20, MapOptions::thumbnails): every 5th CamVid frame as JPEG
//     bytes with its label boxes, decoded as the service decodes it (colour when the map keeps
//     thumbnails, else gray) and Add()ed (ORB from pixels, box refinement, filter, thumbnail,
//     durable commit, index), with and without thumbnails, alternated 3 times in the same run;
//     the thumbnail's own time, its stored size and the map's bytes per place on disk.
//  2d. The statistics' cost on a real ingest (--only ingest): JPEG bytes decoded (core/decode), ORB
//     extracted by the map's pipeline, boxes from the label maps, durable commit + index; a
//     third of the CamVid frames per run, 6 pairs of runs with and without in alternating order;
//     the median and range of the pairs' costs; then 3 passes feeding each frame to a map with
//     and one without, alternating which goes first (load drift cancels frame by frame).
//  3. Reopen time at 10k and 100k places: places are CamVid feature sets multiplied by keeping a
//     random 90 % of the descriptors and flipping 4 random bits in each (real statistics, distinct
//     places), committed by 2 writers, then the map is closed and reopened.
//  3b. Reopen at scale (--only reopen, issue 17), e.g. --reopen 1000000: a map built fast (see
//     FastBuild) through PlaceMap::Commit, then reopened in fresh processes with the sequential
//     scan (the baseline) and the parallel load; seconds, places/s, bytes on disk, VmRSS/VmHWM.
//  3c. A map for the server at scale (--only server-map --reopen N --dir D --keep 1, issue 31):
//     CamVid's even frames stored whole plus filler places up to N (BuildServerMap), served and
//     queried by bench/server_1m.sh.
//  4. Snapshots (issue 15, --only snapshots): a map of --snapshot-places (10k) places built as in
//     3; SnapshotStore::Create (checkpoint + verification), WriteArchive to a sink that only
//     counts bytes and to a file, Import of that file into a second data directory, Restore
//     there; times, bytes on disk and archive bytes.
//
// Usage: placedb-bench-storage --vocabulary FILE [--dir DIR] [--reopen 10000,100000]
//                              [--only persist|dynamics|ingest|thumbnails|snapshots|reopen|
//                                      server-map]
//                              [--snapshot-places 10000] [--stored-features 32] [--keep 1]
// (--reopen-child DIR --load-threads N: internal, one reopen measured in a fresh process)
#include <malloc.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <random>
#include <span>
#include <sstream>
#include <thread>

#include "bench/bench_output.h"
#include "bench/source_views.h"
#include "core/base/files.h"
#include "core/decode/image_decoder.h"
#include "core/storage/map_store.h"
#include "core/storage/snapshots.h"
#include "core/vocabulary/weighting.h"

namespace fs = std::filesystem;
using namespace placedb;
using bench::NowMs;
using bench::Print;

namespace {

struct Frame {
  FeatureSet features;
  std::vector<DynamicBox> boxes;
};

std::vector<DynamicBox> BoxesFromLabels(const cv::Mat& labels) {
  std::vector<DynamicBox> boxes;
  const std::pair<int, int> classes[] = {{8, 2}, {9, 0}, {10, 1}};  // Car, Pedestrian, Bicyclist
  for (const auto& [label, coco] : classes) {
    cv::Mat mask = labels == label;
    cv::Mat components, stats, centroids;
    const int n = cv::connectedComponentsWithStats(mask, components, stats, centroids, 8);
    for (int c = 1; c < n; ++c) {
      if (stats.at<int>(c, cv::CC_STAT_AREA) < 50) continue;
      boxes.push_back({coco, 1.0f,
                       cv::Rect2f(float(stats.at<int>(c, cv::CC_STAT_LEFT)),
                                  float(stats.at<int>(c, cv::CC_STAT_TOP)),
                                  float(stats.at<int>(c, cv::CC_STAT_WIDTH)),
                                  float(stats.at<int>(c, cv::CC_STAT_HEIGHT)))});
    }
  }
  return boxes;
}

std::vector<Frame> LoadCamVid(const std::string& shared) {
  std::vector<std::string> images;
  for (const auto& entry : fs::directory_iterator(shared + "/data/camvid/images")) {
    images.push_back(entry.path().string());
  }
  std::sort(images.begin(), images.end());
  std::vector<Frame> frames(images.size());
  OrbConfig orb;
  orb.max_features = 1000;
  std::vector<std::thread> workers;
  for (unsigned t = 0; t < 2; ++t) {
    workers.emplace_back([&, t] {
      for (size_t i = t; i < images.size(); i += 2) {
        const std::string stem = fs::path(images[i]).stem().string();
        cv::Mat labels =
            cv::imread(shared + "/data/camvid/labels/" + stem + ".png", cv::IMREAD_GRAYSCALE);
        auto features = ExtractOrb(cv::imread(images[i], cv::IMREAD_GRAYSCALE), orb);
        if (!features.ok() || labels.empty()) continue;
        frames[i].features = std::move(features).value();
        frames[i].boxes = BoxesFromLabels(labels);
      }
    });
  }
  for (auto& worker : workers) worker.join();
  return frames;
}

struct IngestFigures {
  double places_per_s = 0;
  uint64_t bytes = 0;
  size_t places = 0;
  uint64_t kept = 0, dropped = 0;
};

IngestFigures Ingest(DataDirectory& dir, const std::string& name, const MapOptions& options,
                     const std::vector<Frame>& frames,
                     std::shared_ptr<const Vocabulary> vocabulary) {
  IngestFigures figures;
  {
    auto map = dir.CreateMap(name, options, vocabulary);
    if (!map.ok()) {
      std::fprintf(stderr, "%s\n", map.status().ToString().c_str());
      std::exit(1);
    }
    const double start = NowMs();
    for (const Frame& frame : frames) {
      Observation observation;
      observation.features = frame.features;
      observation.dynamic.boxes = frame.boxes;
      auto added = (*map)->Add(observation);
      if (!added.ok()) std::exit(1);
    }
    figures.places_per_s = double(frames.size()) / ((NowMs() - start) / 1000.0);
    const MapStats stats = (*map)->Stats();
    figures.places = stats.database.places;
    figures.kept = stats.database.descriptors_kept;
    figures.dropped = stats.database.descriptors_dropped;
    dir.CloseMap(name);
  }
  // Closed (memtables flushed): every byte is in the map's files.
  uint64_t bytes = 0;
  for (const auto& entry : fs::recursive_directory_iterator(dir.path() + "/maps/" + name)) {
    if (entry.is_regular_file()) bytes += entry.file_size();
  }
  figures.bytes = bytes;
  return figures;
}

struct Options {
  std::string vocabulary_path, work_dir, shared = PLACEDB_SHARED_DIR;
  std::vector<size_t> reopen_sizes = {10000, 100000};
  bool persist_only = false;
  bool dynamics_only = false;    // --only dynamics: section 2b alone
  bool ingest_only = false;      // --only ingest: section 2d alone
  bool thumbnails_only = false;  // --only thumbnails: section 2c alone
  bool snapshots_only = false;   // --only snapshots: section 4 alone
  size_t snapshot_places = 10000;
  bool keep = false;  // --keep 1: the work directory stays (bench/snapshots_wire.sh serves it)
  bool reopen_only = false;      // --only reopen: section 3b alone
  bool server_map_only = false;  // --only server-map: section 3c alone (--reopen N: its size)
  // Section 3b: features stored per place by the fast build (the BoW vectors keep every word).
  size_t stored_features = 32;
  // Internal: --reopen-child DIR opens that directory's map once and prints its figures.
  std::string reopen_child;
  unsigned load_threads = 2;  // --load-threads, for --reopen-child
};

// The command line; an exit code when the program must stop (usage error).
std::optional<int> ParseOptions(int argc, char** argv, Options* options) {
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (i + 1 >= argc) {
      std::fprintf(stderr,
                   "usage: placedb-bench-storage --vocabulary FILE [--dir DIR] "
                   "[--reopen 10000,100000] [--shared DIR] "
                   "[--only persist|dynamics|ingest|thumbnails|snapshots|reopen|server-map] "
                   "[--snapshot-places N] "
                   "[--stored-features 32] [--keep 1]\n");
      return 2;
    }
    const std::string value = argv[++i];
    if (arg == "--vocabulary") {
      options->vocabulary_path = value;
    } else if (arg == "--dir") {
      options->work_dir = value;
    } else if (arg == "--shared") {
      options->shared = value;
    } else if (arg == "--reopen") {
      options->reopen_sizes.clear();
      std::stringstream list(value);
      for (std::string item; std::getline(list, item, ',');)
        options->reopen_sizes.push_back(std::stoul(item));
    } else if (arg == "--only" && value == "persist") {
      options->persist_only = true;
    } else if (arg == "--only" && value == "dynamics") {
      options->dynamics_only = true;
    } else if (arg == "--only" && value == "ingest") {
      options->ingest_only = true;
    } else if (arg == "--only" && value == "thumbnails") {
      options->thumbnails_only = true;
    } else if (arg == "--only" && value == "snapshots") {
      options->snapshots_only = true;
    } else if (arg == "--only" && value == "reopen") {
      options->reopen_only = true;
    } else if (arg == "--only" && value == "server-map") {
      options->server_map_only = true;
    } else if (arg == "--stored-features") {
      options->stored_features = std::stoul(value);
    } else if (arg == "--reopen-child") {
      options->reopen_child = value;
    } else if (arg == "--load-threads") {
      options->load_threads = unsigned(std::stoul(value));
    } else if (arg == "--keep") {
      options->keep = value == "1";
    } else if (arg == "--snapshot-places") {
      options->snapshot_places = std::stoul(value);
    } else {
      std::fprintf(stderr, "unknown option %s\n", arg.c_str());
      return 2;
    }
  }
  return std::nullopt;
}

// 1. The paper's Fig. 6: the same frames with and without filtering, every write synced. False
// after an error.
bool BenchFiltering(const std::string& work_dir, const std::vector<Frame>& frames,
                    const std::shared_ptr<const Vocabulary>& vocabulary) {
  auto dir = DataDirectory::Open(work_dir + "/fig6");
  if (!dir.ok()) return false;
  MapOptions plain;
  plain.database.filter.method = FilterMethod::kNone;
  MapOptions filtered;
  filtered.database.filter.method = FilterMethod::kKeypointInBox;
  const IngestFigures bobw = Ingest(**dir, "bobw", plain, frames, vocabulary);
  const IngestFigures bobw_do = Ingest(**dir, "bobw-do", filtered, frames, vocabulary);
  Print("db_bytes_bobw", double(bobw.bytes), "bytes");
  Print("db_bytes_bobw_do", double(bobw_do.bytes), "bytes");
  Print("db_size_reduction", 100.0 * (1.0 - double(bobw_do.bytes) / double(bobw.bytes)), "percent");
  Print("descriptors_dropped_bobw_do",
        100.0 * double(bobw_do.dropped) / double(bobw_do.dropped + bobw_do.kept), "percent");
  Print("bytes_per_place_bobw", double(bobw.bytes) / double(bobw.places), "bytes");
  Print("bytes_per_place_bobw_do", double(bobw_do.bytes) / double(bobw_do.places), "bytes");
  Print("ingest_sync_every_write_bobw", bobw.places_per_s, "places/s");
  Print("ingest_sync_every_write_bobw_do", bobw_do.places_per_s, "places/s");
  return true;
}

// 2. Persist rate under one sync policy: the frames processed first, then committed by
// `writers` threads, so that only the durable commit (and index insert) is timed. Places/s, or
// a negative number after an error.
double BenchPersist(const std::string& work_dir, const std::vector<Frame>& frames,
                    const std::shared_ptr<const Vocabulary>& vocabulary, SyncMode mode, int writers,
                    bool acked_file) {
  StorageOptions storage;
  storage.sync = mode;
  storage.acked_file = acked_file;
  const std::string label =
      std::string(mode == SyncMode::kEveryWrite ? "sync_every_write" : "group_commit_5ms") + "_" +
      std::to_string(writers) + "_writers" + (acked_file ? "" : "_no_acked");
  static int run = 0;
  auto dir = DataDirectory::Open(work_dir + "/" + label + "-" + std::to_string(run++), storage);
  if (!dir.ok()) return -1;
  MapOptions options;
  auto map = (*dir)->CreateMap("m", options, vocabulary);
  if (!map.ok()) return -1;
  std::vector<ProcessedFrame> processed;
  for (const Frame& frame : frames) {
    Observation observation;
    observation.features = frame.features;
    auto p = (*map)->Process(observation);
    if (p.ok() && p->valid) processed.push_back(*p);
  }
  const double start = NowMs();
  std::vector<std::thread> threads;
  for (int t = 0; t < writers; ++t) {
    threads.emplace_back([&, t] {
      for (size_t i = size_t(t); i < processed.size(); i += size_t(writers)) {
        if (!(*map)->Commit(processed[i], {}).ok()) std::exit(1);
      }
    });
  }
  for (auto& thread : threads) thread.join();
  return double(processed.size()) / ((NowMs() - start) / 1000.0);
}

// 2b. Mean ingest time per frame (ms): every frame Add()ed (processing, durable commit, index)
// by one writer, with or without dynamic-object statistics. Negative after an error.
double BenchIngestDynamics(const std::string& work_dir, const std::vector<Frame>& frames,
                           const std::shared_ptr<const Vocabulary>& vocabulary, bool dynamics) {
  StorageOptions storage;
  storage.dynamics = dynamics;
  static int run = 0;
  auto dir = DataDirectory::Open(
      work_dir + "/dynamics-" + std::to_string(dynamics) + "-" + std::to_string(run++), storage);
  if (!dir.ok()) return -1;
  auto map = (*dir)->CreateMap("m", MapOptions(), vocabulary);
  if (!map.ok()) return -1;
  const double start = NowMs();
  int64_t timestamp = int64_t(1704067200) * 1'000'000'000;
  for (const Frame& frame : frames) {
    Observation observation;
    observation.features = frame.features;
    observation.dynamic.boxes = frame.boxes;
    observation.metadata.timestamp_ns = (timestamp += 33'000'000);
    if (!(*map)->Add(observation).ok()) return -1;
  }
  return (NowMs() - start) / double(frames.size());
}

// A CamVid frame as an agent sends it: the JPEG's bytes and the label maps' boxes.
struct JpegFrame {
  std::string jpeg;
  std::vector<DynamicBox> boxes;
};

// Every `every`-th CamVid frame, in order.
std::vector<JpegFrame> LoadCamVidJpegs(const std::string& shared, size_t every) {
  std::vector<std::string> images;
  for (const auto& entry : fs::directory_iterator(shared + "/data/camvid/images")) {
    images.push_back(entry.path().string());
  }
  std::sort(images.begin(), images.end());
  std::vector<JpegFrame> frames;
  for (size_t i = 0; i < images.size(); i += every) {
    const std::string stem = fs::path(images[i]).stem().string();
    cv::Mat labels =
        cv::imread(shared + "/data/camvid/labels/" + stem + ".png", cv::IMREAD_GRAYSCALE);
    auto bytes = ReadWholeFile(images[i]);
    if (labels.empty() || !bytes.ok()) continue;
    frames.push_back({std::move(bytes).value(), BoxesFromLabels(labels)});
  }
  return frames;
}

struct ThumbnailRun {
  double ms_per_frame = -1;  // decode + Add; negative after an error
  double median_ms = 0;      // the median frame's (less sensitive to the machine's load spikes)
  double bytes_per_place = 0;
  double thumbnail_bytes = 0;  // mean stored thumbnail value per place
  size_t places = 0;
};

// 2c. One map, one writer: every frame decoded (colour with thumbnails, as the service decodes
// for such maps) and Add()ed; then the map is closed and its files counted.
ThumbnailRun BenchIngestThumbnails(const std::string& work_dir,
                                   const std::vector<JpegFrame>& frames,
                                   const std::shared_ptr<const Vocabulary>& vocabulary,
                                   bool thumbnails) {
  ThumbnailRun run;
  static int runs = 0;
  const std::string path =
      work_dir + "/thumbnails-" + std::to_string(thumbnails) + "-" + std::to_string(runs++);
  auto dir = DataDirectory::Open(path);
  if (!dir.ok()) return run;
  MapOptions options;
  options.thumbnails.enabled = thumbnails;
  std::vector<PlaceId> ids;
  {
    auto map = (*dir)->CreateMap("m", options, vocabulary);
    if (!map.ok()) return run;
    DecodeOptions decode;
    decode.mode = thumbnails ? ColorMode::kColor : ColorMode::kGray;
    const double start = NowMs();
    uint64_t sequence = 0;
    std::vector<double> frame_ms;
    for (const JpegFrame& frame : frames) {
      const double frame_start = NowMs();
      auto image = DecodeImage(
          std::span(reinterpret_cast<const uint8_t*>(frame.jpeg.data()), frame.jpeg.size()),
          decode);
      if (!image.ok()) return run;
      Observation observation;
      observation.image = std::move(image).value();
      observation.dynamic.boxes = frame.boxes;
      observation.metadata.sequence = ++sequence;
      auto added = (*map)->Add(observation);
      if (!added.ok()) return run;
      if (added->stored) ids.push_back(added->id);
      frame_ms.push_back(NowMs() - frame_start);
    }
    run.ms_per_frame = (NowMs() - start) / double(frames.size());
    run.median_ms = bench::Median(frame_ms);
    for (PlaceId id : ids) {
      auto thumbnail = (*map)->GetThumbnail(id);
      if (thumbnail.ok() && thumbnail->has_value()) {
        run.thumbnail_bytes += double(EncodeThumbnail(**thumbnail).size());
      }
    }
    (*dir)->CloseMap("m");
  }
  uint64_t bytes = 0;
  for (const auto& entry : fs::recursive_directory_iterator(path + "/maps/m")) {
    if (entry.is_regular_file()) bytes += entry.file_size();
  }
  run.places = ids.size();
  if (!ids.empty()) {
    run.bytes_per_place = double(bytes) / double(ids.size());
    run.thumbnail_bytes /= double(ids.size());
  }
  return run;
}

// The thumbnail's own time per frame (reduce, blur the boxes, encode), on decoded colour frames.
double BenchMakeThumbnail(const std::vector<JpegFrame>& frames) {
  std::vector<cv::Mat> images;
  for (const JpegFrame& frame : frames) {
    auto image = DecodeImage(
        std::span(reinterpret_cast<const uint8_t*>(frame.jpeg.data()), frame.jpeg.size()), {});
    if (image.ok()) images.push_back(std::move(image).value());
  }
  ThumbnailSettings settings;
  settings.enabled = true;
  const double start = NowMs();
  for (size_t i = 0; i < images.size(); ++i) {
    if (!MakeThumbnail(images[i], frames[i].boxes, {}, settings).ok()) return -1;
  }
  return (NowMs() - start) / double(std::max<size_t>(images.size(), 1));
}

bool BenchThumbnails(const std::string& work_dir, const std::string& shared,
                     const std::shared_ptr<const Vocabulary>& vocabulary) {
  const std::vector<JpegFrame> frames = LoadCamVidJpegs(shared, 5);
  std::printf("# thumbnails: %zu CamVid JPEG frames (every 5th), label boxes, ORB 1000\n",
              frames.size());
  double ms[2] = {0, 0};      // [thumbnails]
  double median[2] = {0, 0};  // [thumbnails]
  ThumbnailRun last[2];
  const bool order[] = {true, false, false, true, true, false};  // 3 alternations
  for (bool thumbnails : order) {
    const ThumbnailRun run = BenchIngestThumbnails(work_dir, frames, vocabulary, thumbnails);
    if (run.ms_per_frame < 0) return false;
    ms[thumbnails] += run.ms_per_frame / 3;
    median[thumbnails] += run.median_ms / 3;
    last[thumbnails] = run;
  }
  Print("ingest_jpeg_thumbnails_on", ms[1], "ms/frame");
  Print("ingest_jpeg_thumbnails_off", ms[0], "ms/frame");
  Print("thumbnails_cost", 100.0 * (ms[1] / ms[0] - 1.0), "%");
  Print("ingest_jpeg_thumbnails_on_median", median[1], "ms/frame");
  Print("ingest_jpeg_thumbnails_off_median", median[0], "ms/frame");
  Print("thumbnails_cost_median", 100.0 * (median[1] / median[0] - 1.0), "%");
  // Where the difference goes besides the thumbnail: maps that keep thumbnails decode in colour.
  double decode_ms[2] = {0, 0};  // [colour]
  for (bool colour : {true, false, false, true}) {
    DecodeOptions decode;
    decode.mode = colour ? ColorMode::kColor : ColorMode::kGray;
    const double start = NowMs();
    for (const JpegFrame& frame : frames) {
      auto image = DecodeImage(
          std::span(reinterpret_cast<const uint8_t*>(frame.jpeg.data()), frame.jpeg.size()),
          decode);
      if (!image.ok()) return false;
    }
    decode_ms[colour] += (NowMs() - start) / double(frames.size()) / 2;
  }
  Print("decode_jpeg_colour", decode_ms[1], "ms/frame");
  Print("decode_jpeg_gray", decode_ms[0], "ms/frame");
  const double make = BenchMakeThumbnail(frames);
  if (make < 0) return false;
  Print("thumbnail_make", make, "ms/frame");
  Print("thumbnail_bytes_per_place", last[1].thumbnail_bytes, "bytes");
  Print("bytes_per_place_thumbnails_on", last[1].bytes_per_place, "bytes");
  Print("bytes_per_place_thumbnails_off", last[0].bytes_per_place, "bytes");
  Print("places_thumbnails_on", double(last[1].places), "places");
  Print("places_thumbnails_off", double(last[0].places), "places");
  return true;
}

// Mean real ingest time per frame (ms): decode + Add (ORB, filter, BoW, durable commit, index),
// one writer, with or without statistics. Negative after an error.
double BenchRealIngest(const std::string& work_dir, const std::vector<JpegFrame>& frames,
                       const std::shared_ptr<const Vocabulary>& vocabulary, bool dynamics) {
  StorageOptions storage;
  storage.dynamics = dynamics;
  static int run = 0;
  auto dir = DataDirectory::Open(
      work_dir + "/ingest-" + std::to_string(dynamics) + "-" + std::to_string(run++), storage);
  if (!dir.ok()) return -1;
  auto map = (*dir)->CreateMap("m", MapOptions(), vocabulary);
  if (!map.ok()) return -1;
  const double start = NowMs();
  int64_t timestamp = int64_t(1704067200) * 1'000'000'000;
  for (const JpegFrame& frame : frames) {
    auto image = DecodeImage(
        std::span(reinterpret_cast<const uint8_t*>(frame.jpeg.data()), frame.jpeg.size()),
        DecodeOptions{});
    if (!image.ok()) return -1;
    Observation observation;
    observation.image = std::move(image).value();
    observation.dynamic.boxes = frame.boxes;
    observation.metadata.timestamp_ns = (timestamp += 33'000'000);
    if (!(*map)->Add(observation).ok()) return -1;
  }
  return (NowMs() - start) / double(frames.size());
}

// 2d, interleaved: two maps, one with and one without statistics, fed the same frame one after
// the other (alternating which goes first), so the machine's load drifts on both alike at the
// scale of one frame. Appends each frame's times (ms: decode + Add) to *with / *without. False
// after an error.
bool BenchRealIngestInterleaved(const std::string& work_dir, const std::vector<JpegFrame>& frames,
                                const std::shared_ptr<const Vocabulary>& vocabulary,
                                std::vector<double>* with, std::vector<double>* without) {
  static int run = 0;
  std::unique_ptr<DataDirectory> dirs[2];
  std::shared_ptr<PlaceMap> maps[2];
  for (int dynamics = 0; dynamics < 2; ++dynamics) {
    StorageOptions storage;
    storage.dynamics = dynamics == 1;
    auto dir = DataDirectory::Open(
        work_dir + "/interleaved-" + std::to_string(dynamics) + "-" + std::to_string(run), storage);
    if (!dir.ok()) return false;
    dirs[dynamics] = std::move(dir).value();
    auto map = dirs[dynamics]->CreateMap("m", MapOptions(), vocabulary);
    if (!map.ok()) return false;
    maps[dynamics] = *map;
  }
  ++run;
  int64_t timestamp = int64_t(1704067200) * 1'000'000'000;
  for (size_t i = 0; i < frames.size(); ++i) {
    timestamp += 33'000'000;
    for (int k = 0; k < 2; ++k) {
      const int dynamics = (int(i) + k) % 2;
      const double start = NowMs();
      auto image = DecodeImage(
          std::span(reinterpret_cast<const uint8_t*>(frames[i].jpeg.data()), frames[i].jpeg.size()),
          DecodeOptions{});
      if (!image.ok()) return false;
      Observation observation;
      observation.image = std::move(image).value();
      observation.dynamic.boxes = frames[i].boxes;
      observation.metadata.timestamp_ns = timestamp;
      if (!maps[dynamics]->Add(observation).ok()) return false;
      (dynamics ? with : without)->push_back(NowMs() - start);
    }
  }
  return true;
}

double Median(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  const size_t n = values.size();
  return n == 0 ? 0 : n % 2 ? values[n / 2] : (values[n / 2 - 1] + values[n / 2]) / 2;
}

// 2d: 6 pairs, on/off then off/on alternately, so drift in the machine's load weighs on both.
bool BenchRealIngestCost(const std::string& work_dir, const std::string& shared,
                         const std::shared_ptr<const Vocabulary>& vocabulary) {
  const std::vector<JpegFrame> frames = LoadCamVidJpegs(shared, 3);
  if (frames.empty()) return false;
  std::printf("# real ingest: %zu CamVid JPEGs per run (decode + ORB 1000 + filter + commit)\n",
              frames.size());
  std::vector<double> with, without, cost;
  for (int pair = 0; pair < 6; ++pair) {
    double ms[2] = {0, 0};  // [dynamics]
    for (bool dynamics : {pair % 2 == 0, pair % 2 != 0}) {
      ms[dynamics] = BenchRealIngest(work_dir, frames, vocabulary, dynamics);
      if (ms[dynamics] < 0) return false;
    }
    with.push_back(ms[1]);
    without.push_back(ms[0]);
    cost.push_back(100.0 * (ms[1] / ms[0] - 1.0));
    Print("real_ingest_pair_" + std::to_string(pair + 1) + "_cost", cost.back(), "%");
  }
  Print("real_ingest_with_dynamics_median", Median(with), "ms/frame");
  Print("real_ingest_without_dynamics_median", Median(without), "ms/frame");
  Print("real_ingest_dynamics_cost_median", Median(cost), "%");
  Print("real_ingest_dynamics_cost_min", *std::min_element(cost.begin(), cost.end()), "%");
  Print("real_ingest_dynamics_cost_max", *std::max_element(cost.begin(), cost.end()), "%");
  // Interleaved frame by frame: 3 passes, the totals' ratio and the median per-frame difference.
  std::vector<double> frame_with, frame_without;
  for (int pass = 0; pass < 3; ++pass) {
    if (!BenchRealIngestInterleaved(work_dir, frames, vocabulary, &frame_with, &frame_without)) {
      return false;
    }
  }
  double sum_with = 0, sum_without = 0;
  std::vector<double> difference;
  for (size_t i = 0; i < frame_with.size(); ++i) {
    sum_with += frame_with[i];
    sum_without += frame_without[i];
    difference.push_back(frame_with[i] - frame_without[i]);
  }
  Print("interleaved_frames", double(frame_with.size()), "frames");
  Print("interleaved_with_dynamics_mean", sum_with / double(frame_with.size()), "ms/frame");
  Print("interleaved_without_dynamics_mean", sum_without / double(frame_without.size()),
        "ms/frame");
  Print("interleaved_dynamics_cost", 100.0 * (sum_with / sum_without - 1.0), "%");
  Print("interleaved_median_frame_difference", Median(difference), "ms");
  Print("interleaved_dynamics_cost_by_median", 100.0 * Median(difference) / Median(frame_without),
        "%");
  return true;
}

// A re-imaging stand-in that keeps real descriptor statistics: a random 90 % of `features`'
// descriptors, 4 random bits flipped in each.
FeatureSet NoisyCopy(const FeatureSet& features, std::mt19937_64& rng) {
  std::uniform_int_distribution<int> bit(0, 255);
  std::uniform_real_distribution<double> keep(0, 1);
  FeatureSet noisy;
  noisy.image_width = features.image_width;
  noisy.image_height = features.image_height;
  for (size_t i = 0; i < features.size(); ++i) {
    if (keep(rng) > 0.9) continue;
    Descriptor256 d = features.descriptors[i];
    for (int f = 0; f < 4; ++f) {
      const int b = bit(rng);
      d.words[size_t(b / 64)] ^= uint64_t(1) << (b % 64);
    }
    noisy.keypoints.push_back(features.keypoints[i]);
    noisy.descriptors.push_back(d);
  }
  return noisy;
}

// Places `first` .. `target` - 1 added by 2 writers: CamVid feature sets with a random 90 % of
// their descriptors kept and 4 bits flipped in each, so that places stay distinct.
void AddNoisyPlaces(PlaceMap& map, const std::vector<Frame>& frames, size_t first, size_t target) {
  std::vector<std::thread> writers;
  for (unsigned t = 0; t < 2; ++t) {
    writers.emplace_back([&, t] {
      std::mt19937_64 rng(first + t);
      for (size_t p = first + t; p < target; p += 2) {
        const Frame& frame = frames[p % frames.size()];
        Observation observation;
        observation.features = NoisyCopy(frame.features, rng);
        observation.dynamic.boxes = frame.boxes;
        if (!map.Add(observation).ok()) std::exit(1);
      }
    });
  }
  for (auto& writer : writers) writer.join();
}

// 3. Reopen time as one map grows through `reopen_sizes` (with the ingest rate, bytes on disk
// and in memory at each size). False after an error.
bool BenchReopen(const std::string& work_dir, const std::vector<Frame>& frames,
                 const std::shared_ptr<const Vocabulary>& vocabulary,
                 std::vector<size_t> reopen_sizes) {
  std::printf("# reopen workload: CamVid feature sets x (90 %% subsample, 4 bit flips)\n");
  std::sort(reopen_sizes.begin(), reopen_sizes.end());
  auto dir = DataDirectory::Open(work_dir + "/reopen");
  if (!dir.ok()) return false;
  MapOptions options;
  options.database.filter.method = FilterMethod::kKeypointInBox;
  auto map = (*dir)->CreateMap("sweep", options, vocabulary);
  if (!map.ok()) return false;
  size_t places = 0;
  for (size_t target : reopen_sizes) {
    const double start = NowMs();
    const size_t first = places;
    AddNoisyPlaces(**map, frames, first, target);
    places = target;
    const std::string n = std::to_string(target);
    Print("ingest_2_writers_to_" + n, double(target - first) / ((NowMs() - start) / 1000.0),
          "places/s");
    const MapStats stats = (*map)->Stats();
    map->reset();
    (*dir)->CloseMap("sweep");
    const double reopen_start = NowMs();
    map = (*dir)->OpenMap("sweep", vocabulary);
    if (!map.ok()) return false;
    Print("reopen_at_" + n + "_places", (NowMs() - reopen_start) / 1000.0, "s");
    Print("bytes_on_disk_at_" + n + "_places", double((*map)->Stats().bytes_on_disk), "bytes");
    Print("bytes_in_memory_at_" + n + "_places", double(stats.bytes_in_memory), "bytes");
  }
  map->reset();
  dir->reset();
  return true;
}

// 3b. Reopen at up to 1M places (--only reopen). Building such a map through Add() (transform
// + synced commit per place) would take hours on 2 cores, so the fast build processes each
// CamVid frame once (as in 3: 90 % of the descriptors, 4 bits flipped) and commits copies of
// the processed frames through PlaceMap::Commit, the real write path, with these differences,
// printed with the figures: each copy's BoW vector drops a random 10 % of its words (distinct
// places, about as many postings as in 3) and is normalised again; only the first
// `stored_features` features (and their direct-index entries) are stored, since reopen reads
// `places` and `bow` only and 1M full feature sets (~50 GB) do not fit the disk; 16 writers
// commit in group-commit mode (still acknowledged only once synced).
ProcessedFrame KeepFirstFeatures(ProcessedFrame frame, size_t count) {
  count = std::min(count, frame.static_features.size());
  std::vector<uint32_t> keep(count);
  for (uint32_t i = 0; i < count; ++i) keep[i] = i;
  frame.static_features = frame.static_features.Select(keep);
  DirectIndex direct;
  direct.levels_up = frame.direct.levels_up;
  for (size_t n = 0; n < frame.direct.node_count(); ++n) {
    const size_t before = direct.feature_ids.size();
    for (uint32_t id : frame.direct.features_of(n)) {
      if (id < count) direct.feature_ids.push_back(id);
    }
    if (direct.feature_ids.size() == before) continue;
    if (direct.offsets.empty()) direct.offsets.push_back(0);
    direct.node_ids.push_back(frame.direct.node_ids[n]);
    direct.offsets.push_back(uint32_t(direct.feature_ids.size()));
  }
  frame.direct = std::move(direct);
  return frame;
}

// The frames processed once by the map's pipeline (90 % of the descriptors, 4 bits flipped),
// each keeping its first `stored_features` features; invalid frames are left out.
std::vector<ProcessedFrame> ProcessBases(PlaceMap& map, const std::vector<Frame>& frames,
                                         size_t stored_features) {
  std::vector<ProcessedFrame> bases;
  std::mt19937_64 rng(7);
  for (const Frame& frame : frames) {
    Observation observation;
    observation.features = NoisyCopy(frame.features, rng);
    observation.dynamic.boxes = frame.boxes;
    auto processed = map.Process(observation, FrameRole::kStream);
    if (!processed.ok() || !processed->valid) continue;
    bases.push_back(KeepFirstFeatures(std::move(processed).value(), stored_features));
  }
  return bases;
}

// Commits copies of `bases` (place p: base p mod size, a random 10 % of its BoW words dropped)
// until the map holds `target` places; prints fast_build_to_<target>. False after an error.
bool CommitCopies(PlaceMap& map, const std::vector<ProcessedFrame>& bases, size_t target) {
  const size_t first = map.Stats().database.places;
  if (first >= target) return true;
  if (bases.empty()) return false;
  const ScoringType scoring = map.info().options.database.scoring;
  std::atomic<size_t> next{first};
  std::atomic<bool> failed{false};
  const double start = NowMs();
  std::vector<std::thread> writers;
  for (unsigned t = 0; t < 16; ++t) {
    writers.emplace_back([&, t] {
      std::mt19937_64 rng(first * 16 + t);
      std::uniform_real_distribution<double> drop(0, 1);
      for (size_t p = next++; p < target && !failed; p = next++) {
        ProcessedFrame frame = bases[p % bases.size()];
        std::erase_if(frame.bow, [&](const BowEntry&) { return drop(rng) < 0.1; });
        NormalizeForScoring(&frame.bow, scoring);
        PlaceMetadata metadata;
        metadata.agent_id = "agent-" + std::to_string(t);
        metadata.sequence = p;
        metadata.timestamp_ns = int64_t(p) * 100'000'000;
        auto added = map.Commit(frame, metadata);
        if (!added.ok()) {
          std::fprintf(stderr, "%s\n", added.status().ToString().c_str());
          failed = true;
        }
        if (p % 100000 == 0 && p > first) {
          std::fprintf(stderr, "# fast build: %zu places, %.0f s\n", p, (NowMs() - start) / 1000);
        }
      }
    });
  }
  for (auto& writer : writers) writer.join();
  if (failed) return false;
  Print("fast_build_to_" + std::to_string(target),
        double(target - first) / ((NowMs() - start) / 1000.0), "places/s");
  return true;
}

// Adds places until the map holds `target`: copies of the frames. False after an error.
bool FastBuild(PlaceMap& map, const std::vector<Frame>& frames, size_t target,
               size_t stored_features) {
  if (map.Stats().database.places >= target) return true;
  return CommitCopies(map, ProcessBases(map, frames, stored_features), target);
}

// VmRSS and VmHWM of this process in bytes (0 when /proc is not there).
std::pair<double, double> ProcessMemory() {
  std::ifstream status("/proc/self/status");
  double rss = 0, hwm = 0;
  for (std::string line; std::getline(status, line);) {
    if (line.rfind("VmRSS:", 0) == 0) rss = std::stod(line.substr(6)) * 1024;  // kB
    if (line.rfind("VmHWM:", 0) == 0) hwm = std::stod(line.substr(6)) * 1024;
  }
  return {rss, hwm};
}

// --reopen-child: opens the map of `dir` in this fresh process (so that its memory is the
// reopened map's alone) and prints `reopen_ms`, `places`, `postings`, `rss`, `hwm`, `bytes`.
int ReopenChild(const std::string& dir, const std::shared_ptr<const Vocabulary>& vocabulary,
                unsigned load_threads) {
  StorageOptions storage;
  storage.load_threads = load_threads;
  auto data = DataDirectory::Open(dir, storage);
  if (!data.ok()) {
    std::fprintf(stderr, "%s\n", data.status().ToString().c_str());
    return 1;
  }
  const double start = NowMs();
  auto map = (*data)->OpenMap("sweep", vocabulary);
  const double ms = NowMs() - start;
  if (!map.ok()) {
    std::fprintf(stderr, "%s\n", map.status().ToString().c_str());
    return 1;
  }
  // What placedb-server holds once its allocator tuning has run (server/allocator.h: it trims
  // every 5 s): memory the load freed, on whichever thread, goes back to the OS.
  malloc_trim(0);
  const auto [rss, hwm] = ProcessMemory();
  const MapStats stats = (*map)->Stats();
  const OpenTimings& timings = (*map)->open_timings();
  std::printf(
      "reopen_ms %.3f\nplaces %zu\nrss %.0f\nhwm %.0f\nbytes %llu\nindex_bytes %zu\n"
      "rebuild_ms %.3f\nread_decode_ms %.3f\nindex_ms %.3f\n",
      ms, stats.database.places, rss, hwm, (unsigned long long)stats.bytes_on_disk,
      stats.database.index_bytes, timings.total_ms, timings.read_decode_ms, timings.index_ms);
  return 0;
}

// Runs this binary with --reopen-child and reads its figures; empty after an error.
std::map<std::string, double> RunReopenChild(const std::string& self, const std::string& dir,
                                             const std::string& vocabulary_path, unsigned threads) {
  const std::string command = "'" + self + "' --vocabulary '" + vocabulary_path +
                              "' --reopen-child '" + dir + "' --load-threads " +
                              std::to_string(threads);
  std::map<std::string, double> figures;
  FILE* pipe = popen(command.c_str(), "r");
  if (!pipe) return figures;
  char name[64];
  double value = 0;
  while (std::fscanf(pipe, "%63s %lf", name, &value) == 2) figures[name] = value;
  if (pclose(pipe) != 0) figures.clear();
  return figures;
}

bool BenchReopenLarge(const std::string& work_dir, const std::vector<Frame>& frames,
                      const std::shared_ptr<const Vocabulary>& vocabulary,
                      const std::string& vocabulary_path, std::vector<size_t> sizes,
                      size_t stored_features) {
  std::printf(
      "# reopen at scale: fast build (CamVid frames processed once, 90 %% subsample, 4 bit "
      "flips; per place 10 %% of the BoW words dropped; first %zu features stored; 16 writers, "
      "group commit); each reopen in a fresh process, sequential scan (load_threads 1, the "
      "baseline) and parallel (load_threads 2: two threads read, decode and build whole index "
      "segments, the opening thread installs them) in the order seq, par, par, seq\n",
      stored_features);
  std::sort(sizes.begin(), sizes.end());
  const std::string dir_path = work_dir + "/reopen-large";
  const std::string self = fs::read_symlink("/proc/self/exe").string();
  for (size_t target : sizes) {
    {
      StorageOptions storage;
      storage.sync = SyncMode::kGroupCommit;
      auto dir = DataDirectory::Open(dir_path, storage);
      if (!dir.ok()) return false;
      auto map = (*dir)->ListMaps().empty() ? (*dir)->CreateMap("sweep", MapOptions(), vocabulary)
                                            : (*dir)->OpenMap("sweep", vocabulary);
      if (!map.ok()) {
        std::fprintf(stderr, "%s\n", map.status().ToString().c_str());
        return false;
      }
      if (!FastBuild(**map, frames, target, stored_features)) return false;
      if ((*map)->Stats().database.places != target) {
        std::fprintf(stderr, "the map holds %zu places, not %zu (remove %s)\n",
                     (*map)->Stats().database.places, target, dir_path.c_str());
        return false;
      }
    }
    malloc_trim(0);  // the children's memory is measured: give this process's back
    const std::string n = std::to_string(target);
    std::map<unsigned, std::vector<std::map<std::string, double>>> runs;
    for (unsigned threads : {1u, 2u, 2u, 1u}) {
      auto figures = RunReopenChild(self, dir_path, vocabulary_path, threads);
      if (figures.empty()) return false;
      std::printf("# reopen at %s places, load_threads %u: %.2f s, VmRSS %.0f MiB\n", n.c_str(),
                  threads, figures["reopen_ms"] / 1000, figures["rss"] / 1048576);
      runs[threads].push_back(figures);
    }
    auto mean = [&](unsigned threads, const std::string& name) {
      double sum = 0;
      for (const auto& run : runs[threads]) sum += run.at(name);
      return sum / double(runs[threads].size());
    };
    const double places = runs[2][0]["places"];
    Print("reopen_seconds_at_" + n + "_places", mean(2, "reopen_ms") / 1000, "s");
    Print("reopen_seconds_at_" + n + "_places_sequential", mean(1, "reopen_ms") / 1000, "s");
    Print("reopen_places_per_second_at_" + n + "_places", places / (mean(2, "reopen_ms") / 1000),
          "places/s");
    Print("reopen_places_per_second_at_" + n + "_places_sequential",
          places / (mean(1, "reopen_ms") / 1000), "places/s");
    Print("map_bytes_on_disk_at_" + n + "_places", runs[2][0]["bytes"], "bytes");
    Print("rss_after_reopen_at_" + n + "_places", mean(2, "rss"), "bytes");
    Print("hwm_after_reopen_at_" + n + "_places", mean(2, "hwm"), "bytes");
    Print("rss_after_reopen_at_" + n + "_places_sequential", mean(1, "rss"), "bytes");
    Print("hwm_after_reopen_at_" + n + "_places_sequential", mean(1, "hwm"), "bytes");
    Print("index_bytes_at_" + n + "_places", runs[2][0]["index_bytes"], "bytes");
    Print("index_bytes_at_" + n + "_places_sequential", runs[1][0]["index_bytes"], "bytes");
    // Where the time goes: the index (PlaceDatabase::Restore on one thread; parallel: building
    // segments summed over the workers plus installing them) and reading + decoding (summed over
    // the threads).
    for (unsigned threads : {2u, 1u}) {
      const std::string suffix = threads == 1 ? "_sequential" : "";
      Print("reopen_index_seconds_at_" + n + "_places" + suffix, mean(threads, "index_ms") / 1000,
            "s");
      Print("reopen_read_decode_seconds_at_" + n + "_places" + suffix,
            mean(threads, "read_decode_ms") / 1000, "s");
    }
  }
  return true;
}

// 3c. A 1M-place map for the server (--only server-map, issue 31): bench/server_1m.sh serves it
// and queries it through placedb-load. Verification reads the candidates' stored features, so
// the places a query can match must keep all of theirs: the even CamVid frames are stored whole
// (the queries are the odd ones, as JPEG). The rest of the map is filler that must not match
// them: copies (fast build, 32 features each: 1M full feature sets do not fit the disk) of 1500
// random views of Debian's sample images, not CamVid. The map verifies its 10 best candidates
// exhaustively and re-ranks them. With --keep 1 an existing map is reused.
bool BuildServerMap(const std::string& dir_path, const std::string& shared,
                    const std::vector<Frame>& camvid,
                    const std::shared_ptr<const Vocabulary>& vocabulary, size_t target) {
  StorageOptions storage;
  storage.sync = SyncMode::kGroupCommit;
  auto dir = DataDirectory::Open(dir_path, storage);
  if (!dir.ok()) {
    std::fprintf(stderr, "%s\n", dir.status().ToString().c_str());
    return false;
  }
  MapOptions options;
  options.database.verification.mode = VerificationMode::kExhaustive;
  options.database.verification.candidates = 10;
  auto map = (*dir)->ListMaps().empty() ? (*dir)->CreateMap("big", options, vocabulary)
                                        : (*dir)->OpenMap("big", vocabulary);
  if (!map.ok()) {
    std::fprintf(stderr, "%s\n", map.status().ToString().c_str());
    return false;
  }
  if ((*map)->Stats().database.places == 0) {
    size_t stored = 0;
    for (size_t i = 0; i < camvid.size(); i += 2) {
      Observation observation;
      observation.features = camvid[i].features;
      observation.dynamic.boxes = camvid[i].boxes;
      auto processed = (*map)->Process(observation, FrameRole::kStream);
      if (!processed.ok() || !processed->valid) continue;
      PlaceMetadata metadata;
      metadata.agent_id = "camvid";
      metadata.sequence = i;
      metadata.timestamp_ns = int64_t(i) * 1'000'000'000;
      if (auto added = (*map)->Commit(*processed, metadata); !added.ok()) {
        std::fprintf(stderr, "%s\n", added.status().ToString().c_str());
        return false;
      }
      ++stored;
    }
    const uint64_t bytes = (*map)->Stats().bytes_on_disk;
    std::printf("# server map: %zu CamVid places stored whole, %.0f KB on disk each\n", stored,
                double(bytes) / double(stored) / 1e3);
    Print("stored_bytes_per_whole_place", double(bytes) / double(stored), "bytes");
  }
  if ((*map)->Stats().database.places >= target) return true;  // built by an earlier run
  std::vector<Frame> views;
  for (FeatureSet& features : bench::ExtractViews(bench::SourceImages(shared, false), 1500)) {
    views.push_back({std::move(features), {}});
  }
  std::printf("# server map: filler from %zu views of Debian's sample images, 32 features each\n",
              views.size());
  return CommitCopies(**map, ProcessBases(**map, views, 32), target);
}

// Bytes of the regular files under `path`; with `unshared_only`, of those with one link only.
uint64_t TreeBytes(const std::string& path, bool unshared_only = false) {
  uint64_t bytes = 0;
  for (const auto& entry : fs::recursive_directory_iterator(path)) {
    if (!entry.is_regular_file()) continue;
    if (unshared_only && entry.hard_link_count() > 1) continue;
    bytes += entry.file_size();
  }
  return bytes;
}

// 4. A snapshot's life at `places` places: create (checkpoint + verification), archive, import
// into another data directory, restore. False after an error (printed).
bool BenchSnapshots(const std::string& work_dir, const std::vector<Frame>& frames,
                    const std::shared_ptr<const Vocabulary>& vocabulary, size_t places) {
  std::printf("# snapshot workload: %zu places as in the reopen workload\n", places);
  auto fail = [](const Status& status) {
    std::fprintf(stderr, "%s\n", status.ToString().c_str());
    return false;
  };
  const DataDirectory::VocabularyFor resolve = [&](const MapInfo&) -> Result<AnyVocabulary> {
    return AnyVocabulary(vocabulary);
  };
  const std::string n = std::to_string(places);
  auto source_dir = DataDirectory::Open(work_dir + "/snapshot-source");
  if (!source_dir.ok()) return fail(source_dir.status());
  auto map = (*source_dir)->CreateMap("m", MapOptions(), vocabulary);
  if (!map.ok()) return fail(map.status());
  AddNoisyPlaces(**map, frames, 0, places);
  Print("map_bytes_on_disk_at_" + n + "_places", double((*map)->Stats().bytes_on_disk), "bytes");
  auto source = SnapshotStore::Open(source_dir->get());
  if (!source.ok()) return fail(source.status());

  double start = NowMs();
  auto snapshot = (*source)->Create(**map, resolve);
  if (!snapshot.ok()) return fail(snapshot.status());
  Print("snapshot_create_at_" + n + "_places", (NowMs() - start) / 1000.0, "s");
  Print("snapshot_bytes_at_" + n + "_places", double(snapshot->bytes), "bytes");
  auto announced = (*source)->ArchiveBytes(snapshot->id);
  if (!announced.ok()) return fail(announced.status());

  // The archive as a download reads it (files + SHA-256), then as a client stores it.
  uint64_t counted = 0;
  start = NowMs();
  Status written = (*source)->WriteArchive(snapshot->id, size_t(256) << 10,
                                           [&](std::string_view bytes) -> Status {
                                             counted += bytes.size();
                                             return Status::Ok();
                                           });
  if (!written.ok()) return fail(written);
  Print("snapshot_archive_to_counter_at_" + n + "_places", (NowMs() - start) / 1000.0, "s");
  Print("snapshot_archive_bytes_at_" + n + "_places", double(counted), "bytes");
  if (counted != *announced)
    return fail(Status::Internal("ArchiveBytes disagrees with the archive"));
  const std::string archive = work_dir + "/snapshot.pdbsnap";
  {
    std::ofstream out(archive, std::ios::binary | std::ios::trunc);
    start = NowMs();
    written = (*source)->WriteArchive(snapshot->id, size_t(256) << 10,
                                      [&](std::string_view bytes) -> Status {
                                        out.write(bytes.data(), std::streamsize(bytes.size()));
                                        return out ? Status::Ok() : Status::IoError("writing");
                                      });
    out.close();
    if (!written.ok()) return fail(written);
    Print("snapshot_archive_to_file_at_" + n + "_places", (NowMs() - start) / 1000.0, "s");
  }

  auto target_dir = DataDirectory::Open(work_dir + "/snapshot-target");
  if (!target_dir.ok()) return fail(target_dir.status());
  auto target = SnapshotStore::Open(target_dir->get());
  if (!target.ok()) return fail(target.status());
  start = NowMs();
  auto imported = (*target)->Import(archive, resolve);
  if (!imported.ok()) return fail(imported.status());
  Print("snapshot_import_at_" + n + "_places", (NowMs() - start) / 1000.0, "s");
  // Restore with every file copied (the baseline: StorageOptions::restore_hard_links off, same
  // file system, same checkpoint), then as the server does it (tables hard-linked).
  {
    StorageOptions copying;
    copying.restore_hard_links = false;
    auto copy_dir = DataDirectory::Open(work_dir + "/snapshot-copy", copying);
    if (!copy_dir.ok()) return fail(copy_dir.status());
    start = NowMs();
    Status copied =
        (*copy_dir)->RestoreMap("restored", (*target)->path() + "/" + imported->id + "/checkpoint");
    if (!copied.ok()) return fail(copied);
    Print("snapshot_restore_copying_at_" + n + "_places", (NowMs() - start) / 1000.0, "s");
    Print("snapshot_restore_copying_new_bytes_at_" + n + "_places",
          double(TreeBytes(work_dir + "/snapshot-copy/maps/restored", /*unshared_only=*/true)),
          "bytes");
  }
  start = NowMs();
  Status restored = (*target)->Restore(imported->id, "restored");
  if (!restored.ok()) return fail(restored);
  Print("snapshot_restore_at_" + n + "_places", (NowMs() - start) / 1000.0, "s");
  Print("snapshot_restored_map_bytes_at_" + n + "_places",
        double(TreeBytes(work_dir + "/snapshot-target/maps/restored")), "bytes");
  // What the restore added to the disk: files shared with the snapshot (hard links) are not new.
  Print("snapshot_restore_new_bytes_at_" + n + "_places",
        double(TreeBytes(work_dir + "/snapshot-target/maps/restored", /*unshared_only=*/true)),
        "bytes");
  start = NowMs();
  auto reopened = (*target_dir)->OpenMap("restored", vocabulary);
  if (!reopened.ok()) return fail(reopened.status());
  Print("snapshot_restored_open_at_" + n + "_places", (NowMs() - start) / 1000.0, "s");
  if ((*reopened)->Stats().database.places != snapshot->places) {
    return fail(Status::Internal("the restored map does not hold the snapshot's places"));
  }
  return true;
}
}  // namespace

int main(int argc, char** argv) {
  Options options;
  if (auto exit_code = ParseOptions(argc, argv, &options)) return *exit_code;
  auto vocabulary = Vocabulary::Load(options.vocabulary_path);
  if (!vocabulary.ok()) {
    std::fprintf(stderr, "%s\n", vocabulary.status().ToString().c_str());
    return 1;
  }
  if (!options.reopen_child.empty()) {
    return ReopenChild(options.reopen_child, *vocabulary, options.load_threads);
  }
  std::string work_dir = options.work_dir;
  if (work_dir.empty()) work_dir = (fs::temp_directory_path() / "placedb-bench-storage").string();
  if (options.server_map_only) {
    if (!options.keep) fs::remove_all(work_dir);
    const bool ok = BuildServerMap(work_dir, options.shared, LoadCamVid(options.shared),
                                   *vocabulary, options.reopen_sizes.back());
    if (!options.keep) fs::remove_all(work_dir);
    return ok ? 0 : 1;
  }
  if (options.reopen_only) {
    // With --keep 1 a map built by an earlier run is reused (and grown to the sizes asked for).
    if (!options.keep) fs::remove_all(work_dir);
    const std::vector<Frame> frames = LoadCamVid(options.shared);
    const bool ok = BenchReopenLarge(work_dir, frames, *vocabulary, options.vocabulary_path,
                                     options.reopen_sizes, options.stored_features);
    if (!options.keep) fs::remove_all(work_dir);
    return ok ? 0 : 1;
  }
  fs::remove_all(work_dir);
  if (options.thumbnails_only) {
    if (!BenchThumbnails(work_dir, options.shared, *vocabulary)) return 1;
    fs::remove_all(work_dir);
    return 0;
  }
  if (options.ingest_only) {
    if (!BenchRealIngestCost(work_dir, options.shared, *vocabulary)) return 1;
    fs::remove_all(work_dir);
    return 0;
  }
  const std::vector<Frame> frames = LoadCamVid(options.shared);
  std::printf(
      "# workload: %zu CamVid frames, ORB 1000, boxes from label maps; vocabulary %u words\n",
      frames.size(), (*vocabulary)->word_count());

  const bool everything =
      !options.persist_only && !options.dynamics_only && !options.snapshots_only;
  if (options.snapshots_only) {
    if (!BenchSnapshots(work_dir, frames, *vocabulary, options.snapshot_places)) return 1;
    if (!options.keep) fs::remove_all(work_dir);
    return 0;
  }
  if (everything && !BenchFiltering(work_dir, frames, *vocabulary)) return 1;
  // 2. Sync policies under concurrent writers: the same 701 frames, N writer threads; with the
  // ACKED high-water mark (the default) and without it, in the order with, without, without,
  // with (drift in the machine's load then weighs on both alike); the mean of the two runs.
  for (SyncMode mode : {SyncMode::kEveryWrite, SyncMode::kGroupCommit}) {
    if (options.dynamics_only) break;
    for (int writers : {1, 2, 8}) {
      double rate[2] = {0, 0};  // [acked_file]
      for (bool acked_file : {true, false, false, true}) {
        const double r = BenchPersist(work_dir, frames, *vocabulary, mode, writers, acked_file);
        if (r < 0) return 1;
        rate[acked_file] += r / 2;
      }
      const std::string label =
          std::string(mode == SyncMode::kEveryWrite ? "sync_every_write" : "group_commit_5ms") +
          "_" + std::to_string(writers) + "_writers";
      Print("persist_" + label, rate[1], "places/s");
      Print("persist_" + label + "_no_acked", rate[0], "places/s");
      Print("acked_cost_" + label, 100.0 * (1.0 - rate[1] / rate[0]), "%");
    }
  }
  // 2b. Statistics on and off, in the order on, off, off, on; the mean of the two runs.
  if (!options.persist_only) {
    double ms[2] = {0, 0};  // [dynamics]
    for (bool dynamics : {true, false, false, true}) {
      const double m = BenchIngestDynamics(work_dir, frames, *vocabulary, dynamics);
      if (m < 0) return 1;
      ms[dynamics] += m / 2;
    }
    Print("ingest_with_dynamics", ms[1], "ms/frame");
    Print("ingest_without_dynamics", ms[0], "ms/frame");
    Print("dynamics_cost", 100.0 * (ms[1] / ms[0] - 1.0), "%");
  }
  if (everything && !BenchReopen(work_dir, frames, *vocabulary, options.reopen_sizes)) {
    return 1;
  }
  if (everything && !BenchSnapshots(work_dir, frames, *vocabulary, options.snapshot_places)) {
    return 1;
  }
  fs::remove_all(work_dir);
  return 0;
}
