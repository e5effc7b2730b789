#include "eval/adapters.h"

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>

#include "core/base/files.h"
#include "core/detect/detector.h"

namespace fs = std::filesystem;

namespace placedb::eval {

std::vector<int> CamVidDynamicLabels() {
  return {kCamVidCar, kCamVidPedestrian, kCamVidBicyclist};
}

int CamVidLabelToCoco(int label) {
  switch (label) {
    case kCamVidCar:
      return 2;  // car
    case kCamVidPedestrian:
      return 0;  // person
    case kCamVidBicyclist:
      return 1;  // bicycle
    default:
      return -1;
  }
}

Result<std::vector<CamVidFrame>> ListCamVid(const std::string& camvid_dir) {
  const fs::path images = fs::path(camvid_dir) / "images";
  if (!fs::is_directory(images)) {
    return Status::NotFound(camvid_dir +
                            ": no images/ directory (expected CamVid as in "
                            "../shared/data/camvid)");
  }
  std::vector<CamVidFrame> frames;
  for (const auto& file : fs::directory_iterator(images)) {
    if (!IsImageFile(file.path())) continue;
    const std::string stem = file.path().stem().string();
    const size_t underscore = stem.rfind('_');
    if (underscore == std::string::npos) continue;
    const std::string number = stem.substr(underscore + 1);
    const size_t digits = number.find_first_of("0123456789");
    if (digits == std::string::npos) continue;
    CamVidFrame frame;
    frame.sequence = stem.substr(0, underscore);
    frame.frame = std::stoi(number.substr(digits));  // "f00930" -> 930
    frame.stem = stem;
    frame.image_path = fs::absolute(file.path()).lexically_normal().string();
    frame.label_path =
        (fs::absolute(fs::path(camvid_dir)) / "labels" / (stem + ".png")).lexically_normal();
    frames.push_back(std::move(frame));
  }
  if (frames.empty()) return Status::NotFound(images.string() + ": no CamVid frames");
  std::sort(frames.begin(), frames.end(), [](const CamVidFrame& a, const CamVidFrame& b) {
    return std::tie(a.sequence, a.frame) < std::tie(b.sequence, b.frame);
  });
  return frames;
}

std::vector<DynamicBox> BoxesFromLabels(const cv::Mat& labels, int min_area) {
  std::vector<DynamicBox> boxes;
  for (int label : CamVidDynamicLabels()) {
    cv::Mat mask = labels == label;
    if (cv::countNonZero(mask) == 0) continue;
    cv::Mat components, stats, centroids;
    const int count = cv::connectedComponentsWithStats(mask, components, stats, centroids, 8);
    for (int c = 1; c < count; ++c) {
      if (stats.at<int>(c, cv::CC_STAT_AREA) < min_area) continue;
      DynamicBox box;
      box.class_id = CamVidLabelToCoco(label);
      box.confidence = 1.0f;
      box.rect = cv::Rect2f(
          float(stats.at<int>(c, cv::CC_STAT_LEFT)), float(stats.at<int>(c, cv::CC_STAT_TOP)),
          float(stats.at<int>(c, cv::CC_STAT_WIDTH)), float(stats.at<int>(c, cv::CC_STAT_HEIGHT)));
      boxes.push_back(box);
    }
  }
  return boxes;
}

Result<Entry> CamVidEntry(const CamVidFrame& frame, int min_box_area) {
  cv::Mat labels = cv::imread(frame.label_path, cv::IMREAD_GRAYSCALE);
  if (labels.empty()) return Status::NotFound("cannot read CamVid labels " + frame.label_path);
  cv::Mat dynamic = cv::Mat::zeros(labels.size(), CV_8U);
  for (int label : CamVidDynamicLabels()) dynamic |= labels == label;
  Entry entry;
  entry.id = frame.stem;
  entry.image = frame.image_path;
  entry.mask = frame.label_path;
  entry.mask_values = CamVidDynamicLabels();
  entry.boxes = BoxesFromLabels(labels, min_box_area);
  entry.agent = frame.sequence;
  entry.sequence = frame.frame;
  entry.timestamp_ns = int64_t(frame.frame) * 1000000000LL / 30;
  entry.coverage = cv::countNonZero(dynamic) / double(dynamic.total());
  return entry;
}

Result<Dataset> PrepareCamVidAdjacency(const CamVidAdjacencyOptions& options) {
  auto frames = ListCamVid(options.camvid_dir);
  if (!frames.ok()) return frames.status();
  Dataset dataset;
  dataset.name = "camvid-adjacency";
  dataset.description =
      "CamVid adjacent frames: database = every other frame of each sequence, queries = the "
      "frames in between; correct = a database frame of the same sequence within " +
      std::to_string(options.window_frames) +
      " video frames (30 fps). Masks and boxes from the label maps (Car, Pedestrian, "
      "Bicyclist).";
  std::map<std::string, int> position;  // per sequence
  std::map<std::string, int> taken;
  std::vector<const CamVidFrame*> query_frames;
  for (const CamVidFrame& frame : *frames) {
    if (!options.sequences.empty() && std::find(options.sequences.begin(), options.sequences.end(),
                                                frame.sequence) == options.sequences.end()) {
      continue;
    }
    if (options.max_frames_per_sequence > 0 &&
        taken[frame.sequence] >= options.max_frames_per_sequence) {
      continue;
    }
    ++taken[frame.sequence];
    auto entry = CamVidEntry(frame, options.min_box_area);
    if (!entry.ok()) return entry.status();
    if (position[frame.sequence]++ % 2 == 0) {
      dataset.database.push_back(std::move(entry).value());
    } else {
      dataset.queries.push_back(std::move(entry).value());
    }
  }
  for (Entry& query : dataset.queries) {
    for (const Entry& candidate : dataset.database) {
      if (candidate.agent == query.agent &&
          std::llabs(candidate.sequence - query.sequence) <= options.window_frames) {
        query.ground_truth.push_back(candidate.id);
      }
    }
  }
  if (dataset.database.empty()) {
    return Status::InvalidArgument("no CamVid frames selected (sequences: check the names)");
  }
  return dataset;
}

std::vector<CamVidStop> DefaultCamVidStops() {
  return {{"Seq05VD", 1920, 2250, 2520, 2850}, {"0016E5", 4830, 5070, 5430, 5700}};
}

Result<Dataset> PrepareCamVidStops(const CamVidStopsOptions& options) {
  auto frames = ListCamVid(options.camvid_dir);
  if (!frames.ok()) return frames.status();
  Dataset dataset;
  dataset.name = "camvid-stops";
  dataset.description =
      "CamVid vehicle-stop revisits: the same place seen twice with different dynamic objects. "
      "Database = the first visit of each stop" +
      std::string(options.distractors ? " plus every other CamVid frame as a distractor" : "") +
      "; queries = the second visit; ground truth = every frame of the first visit of the same "
      "stop. Frames within " +
      std::to_string(options.guard_frames) +
      " video frames of a stop that belong to neither visit are left out.";
  std::vector<std::vector<std::string>> first_visit(options.stops.size());
  std::vector<Entry> queries;
  std::vector<size_t> query_stop;
  for (const CamVidFrame& frame : *frames) {
    int role = 0;  // 0 distractor, 1 first visit, 2 second visit, 3 left out
    size_t stop_index = 0;
    for (size_t s = 0; s < options.stops.size(); ++s) {
      const CamVidStop& stop = options.stops[s];
      if (frame.sequence != stop.sequence) continue;
      if (frame.frame >= stop.first_begin && frame.frame <= stop.first_end) {
        role = 1;
      } else if (frame.frame >= stop.second_begin && frame.frame <= stop.second_end) {
        role = 2;
      } else if (frame.frame >= stop.first_begin - options.guard_frames &&
                 frame.frame <= stop.second_end + options.guard_frames) {
        role = 3;
      }
      if (role) {
        stop_index = s;
        break;
      }
    }
    if (role == 3 || (role == 0 && !options.distractors)) continue;
    auto entry = CamVidEntry(frame, options.min_box_area);
    if (!entry.ok()) return entry.status();
    if (role == 2) {
      queries.push_back(std::move(entry).value());
      query_stop.push_back(stop_index);
    } else {
      if (role == 1) first_visit[stop_index].push_back(entry->id);
      dataset.database.push_back(std::move(entry).value());
    }
  }
  for (size_t q = 0; q < queries.size(); ++q) queries[q].ground_truth = first_visit[query_stop[q]];
  dataset.queries = std::move(queries);
  for (size_t s = 0; s < options.stops.size(); ++s) {
    if (first_visit[s].empty()) {
      return Status::NotFound("stop " + options.stops[s].sequence + " " +
                              std::to_string(options.stops[s].first_begin) + "-" +
                              std::to_string(options.stops[s].first_end) +
                              ": no frames of its first visit in " + options.camvid_dir);
    }
  }
  return dataset;
}

Result<Dataset> PrepareRtabmap(const RtabmapOptions& options) {
  const std::string truth_path = options.directory + "/ground_truth.bmp";
  cv::Mat truth = cv::imread(truth_path, cv::IMREAD_GRAYSCALE);
  if (truth.empty()) return Status::NotFound("cannot read " + truth_path);
  if (truth.rows != truth.cols) {
    return Status::InvalidArgument(truth_path + " must be square (frames x frames)");
  }
  const int frames = truth.rows;
  if (options.database_last < 1 || options.database_last >= frames) {
    return Status::InvalidArgument("database_last must be in [1, " + std::to_string(frames - 1) +
                                   "]");
  }
  Dataset dataset;
  dataset.name = "rtabmap-loop";
  dataset.description = "RTAB-Map loop: database = frames 1-" +
                        std::to_string(options.database_last) + ", queries = frames " +
                        std::to_string(options.database_last + 1) + "-" + std::to_string(frames) +
                        ", ground truth from ground_truth.bmp.";
  const fs::path root = fs::absolute(options.directory).lexically_normal();
  for (int frame = 1; frame <= frames; ++frame) {
    Entry entry;
    entry.id = std::to_string(frame);
    entry.image = (root / (std::to_string(frame) + ".jpg")).string();
    entry.agent = "rtabmap";
    entry.sequence = frame;
    if (frame <= options.database_last) {
      dataset.database.push_back(std::move(entry));
    } else {
      for (int d = 1; d <= options.database_last; ++d) {
        if (truth.at<uint8_t>(frame - 1, d - 1) > 0)
          entry.ground_truth.push_back(std::to_string(d));
      }
      dataset.queries.push_back(std::move(entry));
    }
  }
  return dataset;
}

Result<Dataset> PrepareFolder(const FolderOptions& options) {
  Dataset dataset;
  dataset.name = fs::path(options.database_dir).parent_path().filename().string();
  if (dataset.name.empty()) dataset.name = "folder";
  dataset.description = "Generic folders: database " + options.database_dir + ", queries " +
                        options.queries_dir + ", ground truth " + options.ground_truth_csv + ".";
  // id = file name; lookups by file name or stem.
  std::map<std::string, std::string> database_ids, query_ids;
  std::map<std::string, Entry*> by_key;
  for (int list = 0; list < 2; ++list) {
    const std::string& dir = list == 0 ? options.database_dir : options.queries_dir;
    const std::string& masks = list == 0 ? options.database_masks_dir : options.queries_masks_dir;
    auto images = ListImageFiles(dir);
    if (!images.ok()) return images.status();
    if (images->empty()) return Status::InvalidArgument(dir + ": no image files");
    std::vector<Entry>& out = list == 0 ? dataset.database : dataset.queries;
    auto& ids = list == 0 ? database_ids : query_ids;
    int64_t sequence = 0;
    for (const fs::path path : *images) {
      Entry entry;
      entry.id = path.filename().string();
      entry.image = fs::absolute(path).lexically_normal().string();
      entry.agent = list == 0 ? "database" : "queries";
      entry.sequence = sequence++;
      if (!masks.empty()) {
        const fs::path mask = fs::path(masks) / (path.stem().string() + ".png");
        if (fs::exists(mask)) entry.mask = fs::absolute(mask).lexically_normal().string();
      }
      ids[entry.id] = entry.id;
      ids[path.stem().string()] = entry.id;
      out.push_back(std::move(entry));
    }
  }
  for (Entry& e : dataset.database) by_key["database/" + e.id] = &e;
  for (Entry& e : dataset.queries) by_key["queries/" + e.id] = &e;

  std::ifstream in(options.ground_truth_csv);
  if (!in) return Status::NotFound("cannot read ground truth " + options.ground_truth_csv);
  std::string line;
  bool header = true;
  int line_number = 0;
  while (std::getline(in, line)) {
    ++line_number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty() || line[0] == '#') continue;
    auto fields = SplitCsvLine(line);
    if (header) {
      header = false;
      if (fields.size() < 2 || fields[0] != "query" || fields[1] != "database") {
        return Status::InvalidArgument(options.ground_truth_csv +
                                       ": the header must be `query,database`");
      }
      continue;
    }
    const std::string where = options.ground_truth_csv + ":" + std::to_string(line_number);
    if (fields.size() < 2) return Status::InvalidArgument(where + ": two fields expected");
    auto q = query_ids.find(fields[0]);
    auto d = database_ids.find(fields[1]);
    if (q == query_ids.end())
      return Status::InvalidArgument(where + ": unknown query " + fields[0]);
    if (d == database_ids.end()) {
      return Status::InvalidArgument(where + ": unknown database image " + fields[1]);
    }
    by_key["queries/" + q->second]->ground_truth.push_back(d->second);
  }
  if (!options.boxes_csv.empty()) {
    for (auto& [key, entry] : by_key) entry->boxes.emplace();
    std::ifstream boxes(options.boxes_csv);
    if (!boxes) return Status::NotFound("cannot read boxes " + options.boxes_csv);
    header = true;
    line_number = 0;
    while (std::getline(boxes, line)) {
      ++line_number;
      if (!line.empty() && line.back() == '\r') line.pop_back();
      if (line.empty() || line[0] == '#') continue;
      if (header) {
        header = false;
        continue;
      }
      const std::string where = options.boxes_csv + ":" + std::to_string(line_number);
      auto fields = SplitCsvLine(line);
      if (fields.size() < 7) {
        return Status::InvalidArgument(where + ": image,class,confidence,x,y,width,height");
      }
      // image = database/NAME or queries/NAME (file name or stem).
      const size_t slash = fields[0].find('/');
      const std::string list = slash == std::string::npos ? "" : fields[0].substr(0, slash);
      const std::string name = slash == std::string::npos ? "" : fields[0].substr(slash + 1);
      const auto& ids = list == "database" ? database_ids : query_ids;
      auto id = ids.find(name);
      if ((list != "database" && list != "queries") || id == ids.end()) {
        return Status::InvalidArgument(where +
                                       ": image must be database/NAME or queries/NAME of "
                                       "an existing image, got " +
                                       fields[0]);
      }
      DynamicBox box;
      try {
        if (!fields[1].empty() && std::isdigit(static_cast<unsigned char>(fields[1][0]))) {
          box.class_id = std::stoi(fields[1]);
        } else {
          auto cls = CocoClassId(fields[1]);
          if (!cls.ok()) return cls.status().WithContext(where);
          box.class_id = *cls;
        }
        box.confidence = fields[2].empty() ? 1.0f : std::stof(fields[2]);
        box.rect = cv::Rect2f(std::stof(fields[3]), std::stof(fields[4]), std::stof(fields[5]),
                              std::stof(fields[6]));
      } catch (const std::exception&) {
        return Status::InvalidArgument(where + ": numbers expected");
      }
      by_key[list + "/" + id->second]->boxes->push_back(box);
    }
  }
  return dataset;
}

}  // namespace placedb::eval
