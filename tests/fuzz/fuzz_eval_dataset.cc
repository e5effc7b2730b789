// The evaluation dataset loader (eval::LoadDataset) on a generated directory: the input's parts
// (fuzz_support.h SplitParts) are dataset.json (first byte even) or database.csv, queries.csv,
// ground_truth.csv and boxes.csv (odd), next to small real image and mask files named img0.png ..
// img3.png, mask0.png .. mask1.png (16x12). Invariants: no crash and no exception escaping;
// a dataset that loads has ground truth in range, masks and coverages that load or fail cleanly,
// and saves (JSON, then CSV) to files that load back into the same dataset.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "eval/dataset.h"
#include "tests/fuzz/fuzz_support.h"

namespace placedb {
namespace {

namespace fs = std::filesystem;
using fuzz::Fail;

const cv::Size kImageSize(16, 12);
const char* const kDatasetFiles[] = {"dataset.json", "database.csv", "queries.csv",
                                     "ground_truth.csv", "boxes.csv"};

std::string DatasetDir() {
  static const std::string dir = [] {
    const std::string path = fuzz::ScratchDir() + "/dataset";
    fs::create_directories(path);
    cv::Mat image(kImageSize, CV_8UC1);
    cv::randu(image, 0, 255);
    for (int i = 0; i < 4; ++i) cv::imwrite(path + "/img" + std::to_string(i) + ".png", image);
    cv::Mat mask = cv::Mat::zeros(kImageSize, CV_8UC1);
    mask(cv::Rect(2, 2, 6, 5)) = 255;
    cv::imwrite(path + "/mask0.png", mask);
    mask(cv::Rect(8, 6, 4, 4)) = 9;  // a label map value (mask_values)
    cv::imwrite(path + "/mask1.png", mask);
    return path;
  }();
  return dir;
}

void ClearDatasetFiles(const std::string& dir) {
  std::error_code ec;
  for (const char* name : kDatasetFiles) fs::remove(dir + "/" + name, ec);
}

// The dataset as its JSON file: what a load must reproduce. Name and description are fixed
// first, since the CSV form has neither.
std::string SavedJson(eval::Dataset dataset, const std::string& dir) {
  dataset.name = "fuzz";
  dataset.description.clear();
  dataset.directory = dir;
  if (Status s = eval::SaveDataset(dataset); !s.ok()) Fail("SaveDataset", s);
  return fuzz::ReadWholeFileOrDie(dir + "/dataset.json");
}

void CheckLoaded(const eval::Dataset& dataset, const std::string& dir) {
  const auto truth = eval::GroundTruthIndices(dataset);
  PLACEDB_FUZZ_CHECK(truth.size() == dataset.queries.size(), "one ground-truth list per query");
  for (const auto& list : truth) {
    for (int index : list) {
      PLACEDB_FUZZ_CHECK(index >= 0 && size_t(index) < dataset.database.size(),
                         "ground truth index out of range");
    }
  }
  for (const auto* list : {&dataset.database, &dataset.queries}) {
    for (const eval::Entry& entry : *list) {
      // Only files of the generated directory: an absolute path could name a FIFO or a device.
      if (!entry.mask.empty() && entry.mask[0] != '/' &&
          entry.mask.find("..") == std::string::npos) {
        (void)eval::LoadEntryMask(dataset, entry, kImageSize);
        const double coverage = eval::EntryCoverage(dataset, entry, kImageSize);
        PLACEDB_FUZZ_CHECK(std::isfinite(coverage) && coverage >= 0 && coverage <= 1,
                           "coverage outside [0, 1]: " + std::to_string(coverage));
      } else if (entry.mask.empty()) {
        const double coverage = eval::EntryCoverage(dataset, entry, kImageSize);
        PLACEDB_FUZZ_CHECK(std::isfinite(coverage) && coverage >= 0 && coverage <= 1,
                           "coverage outside [0, 1]: " + std::to_string(coverage));
      }
    }
  }

  // JSON round trip, then CSV: both must load back into the same dataset.
  ClearDatasetFiles(dir);
  const std::string json = SavedJson(dataset, dir);
  auto from_json = eval::LoadDataset(dir);
  if (!from_json.ok()) Fail("a saved dataset.json does not load:\n" + json, from_json.status());
  ClearDatasetFiles(dir);
  PLACEDB_FUZZ_CHECK(SavedJson(*from_json, dir) == json, "dataset.json round trip changed it");

  // The CSV form knows boxes for every entry or for none: with a boxes.csv, an entry without
  // rows has an empty list (documented in eval/dataset.cc), so "unknown" becomes "none".
  eval::Dataset expected = *from_json;
  bool any_boxes = false;
  for (const auto* list : {&expected.database, &expected.queries}) {
    for (const eval::Entry& entry : *list) any_boxes = any_boxes || entry.boxes.has_value();
  }
  for (auto* list : {&expected.database, &expected.queries}) {
    for (eval::Entry& entry : *list) {
      if (any_boxes && !entry.boxes) entry.boxes.emplace();
    }
  }
  ClearDatasetFiles(dir);
  const std::string expected_json = SavedJson(expected, dir);

  ClearDatasetFiles(dir);
  eval::Dataset csv = *from_json;
  csv.directory = dir;
  if (Status s = eval::SaveDatasetCsv(csv); !s.ok()) Fail("SaveDatasetCsv", s);
  auto from_csv = eval::LoadDataset(dir);
  if (!from_csv.ok())
    Fail("a saved CSV dataset does not load (JSON form:\n" + json + ")", from_csv.status());
  ClearDatasetFiles(dir);
  const std::string json_from_csv = SavedJson(*from_csv, dir);
  PLACEDB_FUZZ_CHECK(json_from_csv == expected_json, "CSV round trip changed the dataset from\n" +
                                                         expected_json + "\nto\n" + json_from_csv);
}

}  // namespace
}  // namespace placedb

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  if (size == 0) return 0;
  const std::string dir = DatasetDir();
  ClearDatasetFiles(dir);
  const auto parts =
      fuzz::SplitParts(std::string_view(reinterpret_cast<const char*>(data) + 1, size - 1));
  if (data[0] % 2 == 0) {
    fuzz::WriteScratchFile("dataset/dataset.json", parts[0]);
  } else {
    // database.csv, queries.csv, ground_truth.csv, boxes.csv: as many as there are parts.
    for (size_t i = 0; i < parts.size() && i + 1 < std::size(kDatasetFiles); ++i) {
      fuzz::WriteScratchFile(std::string("dataset/") + kDatasetFiles[i + 1], parts[i]);
    }
  }
  auto dataset = eval::LoadDataset(dir);
  if (!dataset.ok()) {
    const StatusCode code = dataset.status().code();
    PLACEDB_FUZZ_CHECK(code == StatusCode::kInvalidArgument || code == StatusCode::kNotFound ||
                           code == StatusCode::kCorruption,
                       "LoadDataset: unexpected error " + dataset.status().ToString());
    return 0;
  }
  CheckLoaded(*dataset, dir);
  return 0;
}
