// The evaluation harness's dataset format (docs/evaluation.md): a directory holding
// `dataset.json` (or, alternatively, `database.csv` + `queries.csv` + `ground_truth.csv` and an
// optional `boxes.csv`), plus whatever image and mask files its entries name.
//
// A dataset is a list of database entries (what the place database is built from) and a list of
// query entries, each query naming the database entries that show the same place (its ground
// truth, possibly empty). Every entry has an image and optionally what is known about its dynamic
// objects: a mask (a PNG whose non-zero pixels, or whose pixels with one of `mask_values`, are
// dynamic), boxes (COCO class, confidence, rectangle), and the fraction of its pixels covered by
// dynamic objects. Relative paths are relative to the dataset directory.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/filter/dynamic_filter.h"

namespace placedb::eval {

inline constexpr const char* kDatasetFormat = "placedb-eval-dataset/1";

struct Entry {
  std::string id;     // unique within its list (database or queries)
  std::string image;  // relative to the dataset directory, or absolute
  std::string mask;   // optional, same convention
  // Pixel values of `mask` that are dynamic; empty = every non-zero pixel. Lets a dataset point
  // straight at a label map (CamVid: 8 Car, 9 Pedestrian, 10 Bicyclist).
  std::vector<int> mask_values;
  // Ground-truth ("oracle") boxes; nullopt = unknown (an empty list means "none").
  std::optional<std::vector<DynamicBox>> boxes;
  std::string agent;               // e.g. the sequence or robot name
  int64_t sequence = 0;            // frame number within the agent's stream
  int64_t timestamp_ns = 0;        // capture time
  std::optional<double> coverage;  // fraction of the image's pixels on dynamic objects, [0, 1]
  std::string source;              // free-text provenance (e.g. how a synthetic frame was made)
  std::vector<std::string> ground_truth;  // queries only: ids of database entries, same place
};

struct Dataset {
  std::string name;
  std::string description;
  std::string directory;  // where the dataset was loaded from / will be saved to
  std::vector<Entry> database;
  std::vector<Entry> queries;

  // `path` made absolute against `directory` when it is relative.
  std::string Resolve(const std::string& path) const;
};

// Checks ids (non-empty, unique per list), ground-truth references (every id names a database
// entry), coverages in [0, 1], boxes with positive size, confidence in [0, 1] and a dynamic
// class (COCO person 0, bicycle 1, car 2, motorcycle 3, bus 5, truck 7), not entirely left of
// or above the image, and text (ids, paths, agent, source, name, description) in valid UTF-8, as
// dataset.json requires; with `check_files`, that every image and mask exists and that no box lies
// entirely right of or below its image. INVALID_ARGUMENT / NOT_FOUND naming the first problem
// ("queries[3] (id q7): ground_truth names unknown database entry x").
Status ValidateDataset(const Dataset& dataset, bool check_files);

// Loads `directory`/dataset.json, or the CSV files when there is no JSON. Validates (with files).
Result<Dataset> LoadDataset(const std::string& directory);

// Writes `dataset.directory`/dataset.json (creating the directory), atomically (temp + rename).
Status SaveDataset(const Dataset& dataset);
// Writes the CSV form (database.csv, queries.csv, ground_truth.csv, boxes.csv) instead.
Status SaveDatasetCsv(const Dataset& dataset);

// Ground truth as indices into `dataset.database`, one list per query (sorted, unique).
std::vector<std::vector<int>> GroundTruthIndices(const Dataset& dataset);

// The entry's dynamic mask as CV_8U 255 = dynamic (empty Mat when the entry has none). The mask
// must be the size of the entry's image: `expected` (when non-empty) is checked.
Result<cv::Mat> LoadEntryMask(const Dataset& dataset, const Entry& entry,
                              cv::Size expected = cv::Size());

// Dynamic coverage of an entry: its stated coverage, else its mask's, else the union of its
// boxes (given the image size), else 0.
double EntryCoverage(const Dataset& dataset, const Entry& entry, cv::Size image_size);

// RFC 4180-ish CSV: fields with a comma, quote or newline are quoted, quotes doubled.
std::string CsvField(const std::string& value);
// Splits one CSV line (no embedded newlines) into fields, honouring quotes.
std::vector<std::string> SplitCsvLine(const std::string& line);

}  // namespace placedb::eval
