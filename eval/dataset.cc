#include "eval/dataset.h"

#include <algorithm>
#include <charconv>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>
#include <string_view>
#include <system_error>
#include <utility>

#include "core/detect/detector.h"

namespace fs = std::filesystem;

using json = nlohmann::json;

namespace placedb::eval {

std::string Dataset::Resolve(const std::string& path) const {
  if (path.empty()) return path;
  fs::path p(path);
  if (p.is_absolute() || directory.empty()) return path;
  return (fs::path(directory) / p).string();
}

namespace {

// Whether `path` names an existing file or folder. The paths come from dataset files: one the
// system refuses to look up (a name too long, a loop) does not exist, it does not throw.
bool PathExists(const std::string& path) {
  std::error_code ec;
  return fs::exists(path, ec) && !ec;
}
bool IsFolder(const std::string& path) {
  std::error_code ec;
  return fs::is_directory(path, ec) && !ec;
}

std::string Where(const char* list, size_t i, const Entry& entry) {
  return std::string(list) + "[" + std::to_string(i) + "] (id " + entry.id + ")";
}

// The COCO ids of the paper's dynamic classes (person 0, bicycle 1, car 2, motorcycle 3, bus 5,
// truck 7): the only classes an oracle box may have.
const std::set<int>& DynamicClassIds() {
  static const std::set<int> ids = [] {
    std::set<int> out;
    for (const std::string& name : DefaultDynamicClassNames()) {
      auto id = CocoClassId(name);
      if (id.ok()) out.insert(*id);
    }
    return out;
  }();
  return ids;
}

// An image's size from its header (PNG, JPEG), else by decoding it; empty when unreadable.
cv::Size ImageSize(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  unsigned char head[26] = {};
  if (!in.read(reinterpret_cast<char*>(head), sizeof(head))) return cv::Size();
  auto big16 = [](const unsigned char* p) { return (int(p[0]) << 8) | int(p[1]); };
  auto big32 = [](const unsigned char* p) {
    return int((uint32_t(p[0]) << 24) | (uint32_t(p[1]) << 16) | (uint32_t(p[2]) << 8) | p[3]);
  };
  static const unsigned char kPng[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1A, '\n'};
  if (std::equal(kPng, kPng + 8, head) && std::equal(head + 12, head + 16, "IHDR")) {
    return cv::Size(big32(head + 16), big32(head + 20));
  }
  if (head[0] == 0xFF && head[1] == 0xD8) {
    // Walk the JPEG markers to the first start-of-frame (SOF0-SOF15 but DHT, JPG, DAC).
    in.clear();
    in.seekg(2);
    unsigned char marker[4];
    while (in.read(reinterpret_cast<char*>(marker), 4)) {
      if (marker[0] != 0xFF) break;
      if (marker[1] == 0xFF) {  // fill byte
        in.seekg(-3, std::ios::cur);
        continue;
      }
      const int length = big16(marker + 2);
      const int type = marker[1];
      if (type >= 0xC0 && type <= 0xCF && type != 0xC4 && type != 0xC8 && type != 0xCC) {
        unsigned char frame[5];
        if (!in.read(reinterpret_cast<char*>(frame), 5)) break;
        return cv::Size(big16(frame + 3), big16(frame + 1));
      }
      if (length < 2) break;
      in.seekg(length - 2, std::ios::cur);
    }
  }
  cv::Mat image = cv::imread(path, cv::IMREAD_UNCHANGED);
  return image.size();
}

// Well-formed UTF-8 (no overlong forms, surrogates or code points past U+10FFFF): what JSON
// strings hold. The CSV form must hold the same, or a dataset would load from CSV and then make
// SaveDataset's JSON writer throw (found by tests/fuzz/fuzz_eval_dataset).
bool IsUtf8(std::string_view text) {
  size_t i = 0;
  while (i < text.size()) {
    const auto byte = [&](size_t at) { return uint8_t(text[at]); };
    const uint8_t lead = byte(i);
    size_t length = 0;
    uint8_t low = 0x80;
    uint8_t high = 0xBF;  // the allowed range of the second byte
    if (lead < 0x80) {
      ++i;
      continue;
    } else if (lead >= 0xC2 && lead <= 0xDF) {
      length = 2;
    } else if (lead >= 0xE0 && lead <= 0xEF) {
      length = 3;
      if (lead == 0xE0) low = 0xA0;   // overlong
      if (lead == 0xED) high = 0x9F;  // surrogates
    } else if (lead >= 0xF0 && lead <= 0xF4) {
      length = 4;
      if (lead == 0xF0) low = 0x90;   // overlong
      if (lead == 0xF4) high = 0x8F;  // past U+10FFFF
    } else {
      return false;
    }
    if (text.size() - i < length || byte(i + 1) < low || byte(i + 1) > high) return false;
    for (size_t k = 2; k < length; ++k) {
      if (byte(i + k) < 0x80 || byte(i + k) > 0xBF) return false;
    }
    i += length;
  }
  return true;
}

Status ValidateEntry(const Dataset& dataset, const char* list, size_t i, const Entry& entry,
                     bool check_files) {
  if (entry.id.empty()) {
    return Status::InvalidArgument(std::string(list) + "[" + std::to_string(i) + "]: empty id");
  }
  // Before Where(): the message must not quote a broken id.
  for (const auto& [field, text] : {std::pair<const char*, const std::string*>{"id", &entry.id},
                                    {"image", &entry.image},
                                    {"mask", &entry.mask},
                                    {"agent", &entry.agent},
                                    {"source", &entry.source}}) {
    if (!IsUtf8(*text)) {
      return Status::InvalidArgument(std::string(list) + "[" + std::to_string(i) + "]: " + field +
                                     " is not valid UTF-8");
    }
  }
  for (const std::string& id : entry.ground_truth) {
    if (!IsUtf8(id)) {
      return Status::InvalidArgument(Where(list, i, entry) +
                                     ": ground_truth has an id that is "
                                     "not valid UTF-8");
    }
  }
  if (entry.image.empty()) return Status::InvalidArgument(Where(list, i, entry) + ": no image");
  if (entry.coverage && !(*entry.coverage >= 0.0 && *entry.coverage <= 1.0)) {
    return Status::InvalidArgument(Where(list, i, entry) + ": coverage " +
                                   std::to_string(*entry.coverage) + " is not in [0, 1]");
  }
  if (entry.boxes) {
    for (size_t b = 0; b < entry.boxes->size(); ++b) {
      const DynamicBox& box = (*entry.boxes)[b];
      const std::string where = Where(list, i, entry) + ": boxes[" + std::to_string(b) + "]";
      if (!(box.rect.width > 0 && box.rect.height > 0) || !(box.confidence >= 0) ||
          !(box.confidence <= 1) || box.class_id < 0) {
        return Status::InvalidArgument(where +
                                       " needs a class id >= 0, a positive size and a "
                                       "confidence in [0, 1]");
      }
      if (!DynamicClassIds().count(box.class_id)) {
        return Status::InvalidArgument(
            where + " has class " + std::to_string(box.class_id) + " (" +
            CocoClassName(box.class_id) +
            "), not a dynamic class: oracle boxes mark person 0, bicycle 1, car 2, motorcycle "
            "3, bus 5 or truck 7");
      }
      if (!(box.rect.x + box.rect.width > 0 && box.rect.y + box.rect.height > 0)) {
        return Status::InvalidArgument(where +
                                       " lies entirely outside the image (left of or "
                                       "above it)");
      }
    }
  }
  if (check_files) {
    if (!PathExists(dataset.Resolve(entry.image))) {
      return Status::NotFound(Where(list, i, entry) + ": image " + dataset.Resolve(entry.image) +
                              " does not exist");
    }
    if (!entry.mask.empty() && !PathExists(dataset.Resolve(entry.mask))) {
      return Status::NotFound(Where(list, i, entry) + ": mask " + dataset.Resolve(entry.mask) +
                              " does not exist");
    }
    if (entry.boxes && !entry.boxes->empty()) {
      const cv::Size size = ImageSize(dataset.Resolve(entry.image));
      if (size.empty()) {
        return Status::InvalidArgument(Where(list, i, entry) + ": cannot read the size of " +
                                       dataset.Resolve(entry.image));
      }
      for (size_t b = 0; b < entry.boxes->size(); ++b) {
        const cv::Rect2f& r = (*entry.boxes)[b].rect;
        if (!(r.x < size.width && r.y < size.height)) {
          char text[160];
          std::snprintf(text, sizeof(text),
                        ": boxes[%zu] [%g %g %g %g] lies entirely outside the %dx%d image", b,
                        double(r.x), double(r.y), double(r.width), double(r.height), size.width,
                        size.height);
          return Status::InvalidArgument(Where(list, i, entry) + text);
        }
      }
    }
  }
  return Status::Ok();
}

// ---- JSON ----------------------------------------------------------------------------------

json BoxToJson(const DynamicBox& box) {
  return json{{"class", box.class_id},
              {"confidence", box.confidence},
              {"rect", {box.rect.x, box.rect.y, box.rect.width, box.rect.height}}};
}

json EntryToJson(const Entry& entry, bool query) {
  json j;
  j["id"] = entry.id;
  j["image"] = entry.image;
  if (!entry.mask.empty()) j["mask"] = entry.mask;
  if (!entry.mask_values.empty()) j["mask_values"] = entry.mask_values;
  if (entry.boxes) {
    json boxes = json::array();
    for (const DynamicBox& box : *entry.boxes) boxes.push_back(BoxToJson(box));
    j["boxes"] = boxes;
  }
  if (!entry.agent.empty()) j["agent"] = entry.agent;
  j["sequence"] = entry.sequence;
  j["timestamp_ns"] = entry.timestamp_ns;
  if (entry.coverage) j["coverage"] = *entry.coverage;
  if (!entry.source.empty()) j["source"] = entry.source;
  if (query) j["ground_truth"] = entry.ground_truth;
  return j;
}

Result<DynamicBox> BoxFromJson(const json& j, const std::string& where) {
  if (!j.is_object()) return Status::InvalidArgument(where + ": a box must be an object");
  DynamicBox box;
  const json& cls = j.contains("class") ? j["class"] : json();
  if (cls.is_number_integer()) {
    box.class_id = cls.get<int>();
  } else if (cls.is_string()) {
    auto id = CocoClassId(cls.get<std::string>());
    if (!id.ok()) return id.status().WithContext(where + ".class");
    box.class_id = *id;
  } else {
    return Status::InvalidArgument(where + ".class: a COCO class id or name is required");
  }
  box.confidence = j.value("confidence", 1.0f);
  if (!j.contains("rect") || !j["rect"].is_array() || j["rect"].size() != 4) {
    return Status::InvalidArgument(where + ".rect: [x, y, width, height] is required");
  }
  const json& r = j["rect"];
  for (const json& v : r) {
    if (!v.is_number()) return Status::InvalidArgument(where + ".rect: numbers expected");
  }
  box.rect = cv::Rect2f(r[0].get<float>(), r[1].get<float>(), r[2].get<float>(), r[3].get<float>());
  return box;
}

// Whether a JSON number converts to an integer in [lo, hi] without undefined behaviour
// (nlohmann casts a float such as 3e25 unchecked; found by tests/fuzz/fuzz_eval_dataset).
// Non-numbers pass: the conversion then throws a type error, which the caller reports.
bool FitsInteger(const json& v, int64_t lo, int64_t hi) {
  if (v.is_number_unsigned()) return v.get<uint64_t>() <= uint64_t(hi);
  if (v.is_number_integer()) return v.get<int64_t>() >= lo && v.get<int64_t>() <= hi;
  if (v.is_number_float()) {
    const double d = v.get<double>();
    return std::isfinite(d) && d >= double(lo) && d < double(hi) + 1.0;
  }
  return true;
}

Result<Entry> EntryFromJson(const json& j, const std::string& where, bool query) {
  if (!j.is_object()) return Status::InvalidArgument(where + ": an entry must be an object");
  for (const char* key : {"sequence", "timestamp_ns"}) {
    if (j.contains(key) && !FitsInteger(j[key], INT64_MIN, INT64_MAX)) {
      return Status::InvalidArgument(where + "." + key + ": not a 64-bit integer");
    }
  }
  if (j.contains("mask_values") && j["mask_values"].is_array()) {
    for (const json& v : j["mask_values"]) {
      if (!FitsInteger(v, INT_MIN, INT_MAX)) {
        return Status::InvalidArgument(where + ".mask_values: not a 32-bit integer");
      }
    }
  }
  Entry entry;
  try {
    entry.id = j.at("id").get<std::string>();
    entry.image = j.at("image").get<std::string>();
    entry.mask = j.value("mask", std::string());
    if (j.contains("mask_values")) entry.mask_values = j["mask_values"].get<std::vector<int>>();
    if (j.contains("boxes")) {
      std::vector<DynamicBox> boxes;
      for (size_t i = 0; i < j["boxes"].size(); ++i) {
        auto box = BoxFromJson(j["boxes"][i], where + ".boxes[" + std::to_string(i) + "]");
        if (!box.ok()) return box.status();
        boxes.push_back(*box);
      }
      entry.boxes = std::move(boxes);
    }
    entry.agent = j.value("agent", std::string());
    entry.sequence = j.value("sequence", int64_t(0));
    entry.timestamp_ns = j.value("timestamp_ns", int64_t(0));
    if (j.contains("coverage") && !j["coverage"].is_null()) {
      entry.coverage = j["coverage"].get<double>();
    }
    entry.source = j.value("source", std::string());
    if (query && j.contains("ground_truth")) {
      entry.ground_truth = j["ground_truth"].get<std::vector<std::string>>();
    }
  } catch (const json::exception& e) {
    return Status::InvalidArgument(where + ": " + e.what());
  }
  return entry;
}

Status WriteFileAtomically(const std::string& path, const std::string& contents) {
  const std::string temp = path + ".tmp";
  {
    std::ofstream out(temp, std::ios::binary | std::ios::trunc);
    if (!out) return Status::IoError("cannot write " + temp);
    out << contents;
    if (!out.flush()) return Status::IoError("cannot write " + temp);
  }
  std::error_code ec;
  fs::rename(temp, path, ec);
  if (ec) return Status::IoError("cannot rename " + temp + " to " + path + ": " + ec.message());
  return Status::Ok();
}

Status MakeDirectory(const std::string& directory) {
  std::error_code ec;
  fs::create_directories(directory, ec);
  if (ec) return Status::IoError("cannot create " + directory + ": " + ec.message());
  return Status::Ok();
}

Result<Dataset> LoadJson(const std::string& directory, const std::string& path) {
  std::ifstream in(path);
  if (!in) return Status::IoError("cannot read " + path);
  json j;
  try {
    j = json::parse(in);
  } catch (const json::exception& e) {
    return Status::InvalidArgument(path + ": not valid JSON: " + e.what());
  }
  if (!j.is_object()) return Status::InvalidArgument(path + ": the top level must be an object");
  Dataset dataset;
  dataset.directory = directory;
  // value() throws when the key holds another type ("name": [...]; found by
  // tests/fuzz/fuzz_eval_dataset).
  try {
    const std::string format = j.value("format", std::string());
    if (format != kDatasetFormat) {
      return Status::InvalidArgument(path + ": format is \"" + format + "\", expected \"" +
                                     kDatasetFormat + "\"");
    }
    dataset.name = j.value("name", fs::path(directory).filename().string());
    dataset.description = j.value("description", std::string());
  } catch (const json::exception& e) {
    return Status::InvalidArgument(path + ": format, name and description must be strings (" +
                                   e.what() + ")");
  }
  for (const char* list : {"database", "queries"}) {
    if (!j.contains(list) || !j[list].is_array()) {
      return Status::InvalidArgument(path + ": \"" + list + "\" must be an array");
    }
    const bool query = std::string(list) == "queries";
    std::vector<Entry>& out = query ? dataset.queries : dataset.database;
    for (size_t i = 0; i < j[list].size(); ++i) {
      auto entry =
          EntryFromJson(j[list][i], std::string(list) + "[" + std::to_string(i) + "]", query);
      if (!entry.ok()) return entry.status().WithContext(path);
      out.push_back(std::move(entry).value());
    }
  }
  return dataset;
}

// ---- CSV -----------------------------------------------------------------------------------

const std::vector<std::string> kEntryColumns = {"id",           "image",    "mask",
                                                "mask_values",  "agent",    "sequence",
                                                "timestamp_ns", "coverage", "source"};

Result<std::vector<std::map<std::string, std::string>>> ReadCsv(const std::string& path) {
  std::ifstream in(path);
  if (!in) return Status::NotFound("cannot read " + path);
  std::vector<std::map<std::string, std::string>> rows;
  std::string line;
  std::vector<std::string> header;
  int line_number = 0;
  while (std::getline(in, line)) {
    ++line_number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty() || line[0] == '#') continue;
    std::vector<std::string> fields = SplitCsvLine(line);
    if (header.empty()) {
      header = fields;
      continue;
    }
    if (fields.size() > header.size()) {
      return Status::InvalidArgument(path + ":" + std::to_string(line_number) + ": " +
                                     std::to_string(fields.size()) + " fields, the header has " +
                                     std::to_string(header.size()));
    }
    std::map<std::string, std::string> row;
    for (size_t i = 0; i < fields.size(); ++i) row[header[i]] = fields[i];
    rows.push_back(std::move(row));
  }
  return rows;
}

Result<Entry> EntryFromRow(const std::map<std::string, std::string>& row,
                           const std::string& where) {
  auto get = [&](const std::string& key) {
    auto it = row.find(key);
    return it == row.end() ? std::string() : it->second;
  };
  Entry entry;
  entry.id = get("id");
  entry.image = get("image");
  entry.mask = get("mask");
  entry.agent = get("agent");
  entry.source = get("source");
  try {
    std::stringstream values(get("mask_values"));
    for (std::string value; std::getline(values, value, ';');) {
      if (!value.empty()) entry.mask_values.push_back(std::stoi(value));
    }
    if (!get("sequence").empty()) entry.sequence = std::stoll(get("sequence"));
    if (!get("timestamp_ns").empty()) entry.timestamp_ns = std::stoll(get("timestamp_ns"));
    if (!get("coverage").empty()) entry.coverage = std::stod(get("coverage"));
  } catch (const std::exception&) {
    return Status::InvalidArgument(where +
                                   ": a number field (mask_values, sequence, "
                                   "timestamp_ns, coverage) does not parse");
  }
  return entry;
}

Result<Dataset> LoadCsv(const std::string& directory) {
  Dataset dataset;
  dataset.directory = directory;
  dataset.name = fs::path(directory).filename().string();
  for (const char* list : {"database", "queries"}) {
    const std::string path = directory + "/" + list + ".csv";
    auto rows = ReadCsv(path);
    if (!rows.ok()) return rows.status();
    std::vector<Entry>& out = std::string(list) == "queries" ? dataset.queries : dataset.database;
    for (size_t i = 0; i < rows->size(); ++i) {
      auto entry = EntryFromRow((*rows)[i], path + " row " + std::to_string(i + 1));
      if (!entry.ok()) return entry.status();
      out.push_back(std::move(entry).value());
    }
  }
  std::map<std::string, size_t> query_index;
  for (size_t i = 0; i < dataset.queries.size(); ++i) query_index[dataset.queries[i].id] = i;
  {
    const std::string path = directory + "/ground_truth.csv";
    auto rows = ReadCsv(path);
    if (!rows.ok()) return rows.status();
    for (size_t i = 0; i < rows->size(); ++i) {
      const auto& row = (*rows)[i];
      auto q = row.find("query_id"), d = row.find("database_id");
      if (q == row.end() || d == row.end()) {
        return Status::InvalidArgument(path + ": columns query_id and database_id are required");
      }
      auto it = query_index.find(q->second);
      if (it == query_index.end()) {
        return Status::InvalidArgument(path + " row " + std::to_string(i + 1) + ": unknown query " +
                                       q->second);
      }
      dataset.queries[it->second].ground_truth.push_back(d->second);
    }
  }
  const std::string boxes_path = directory + "/boxes.csv";
  if (PathExists(boxes_path)) {
    std::map<std::string, Entry*> by_id;
    for (Entry& entry : dataset.database) by_id["database/" + entry.id] = &entry;
    for (Entry& entry : dataset.queries) by_id["queries/" + entry.id] = &entry;
    // Every entry of a dataset with a boxes file has known boxes (possibly none).
    for (auto& [key, entry] : by_id) entry->boxes.emplace();
    auto rows = ReadCsv(boxes_path);
    if (!rows.ok()) return rows.status();
    for (size_t i = 0; i < rows->size(); ++i) {
      auto& row = (*rows)[i];
      const std::string where = boxes_path + " row " + std::to_string(i + 1);
      auto it = by_id.find(row["list"] + "/" + row["entry_id"]);
      if (it == by_id.end()) {
        return Status::InvalidArgument(where + ": unknown entry " + row["list"] + "/" +
                                       row["entry_id"]);
      }
      DynamicBox box;
      try {
        const std::string cls = row["class"];
        if (!cls.empty() && std::isdigit(static_cast<unsigned char>(cls[0]))) {
          box.class_id = std::stoi(cls);
        } else {
          auto id = CocoClassId(cls);
          if (!id.ok()) return id.status().WithContext(where);
          box.class_id = *id;
        }
        box.confidence = row["confidence"].empty() ? 1.0f : std::stof(row["confidence"]);
        box.rect = cv::Rect2f(std::stof(row["x"]), std::stof(row["y"]), std::stof(row["width"]),
                              std::stof(row["height"]));
      } catch (const std::exception&) {
        return Status::InvalidArgument(where + ": class, confidence, x, y, width, height");
      }
      it->second->boxes->push_back(box);
    }
  }
  return dataset;
}

// Box fields are floats: 9 significant digits bring each back exactly.
std::string CsvNumber(float value) {
  std::ostringstream out;
  out.precision(9);
  out << value;
  return out.str();
}

// Doubles (coverage) in their shortest form that parses back to the same value.
std::string CsvNumber(double value) {
  char text[32];
  const auto [end, error] = std::to_chars(text, text + sizeof(text), value);
  return error == std::errc() ? std::string(text, end) : std::to_string(value);
}

}  // namespace

Status ValidateDataset(const Dataset& dataset, bool check_files) {
  if (!IsUtf8(dataset.name) || !IsUtf8(dataset.description)) {
    return Status::InvalidArgument("the dataset's name or description is not valid UTF-8");
  }
  std::set<std::string> database_ids;
  for (size_t i = 0; i < dataset.database.size(); ++i) {
    const Entry& entry = dataset.database[i];
    PLACEDB_RETURN_IF_ERROR(ValidateEntry(dataset, "database", i, entry, check_files));
    if (!database_ids.insert(entry.id).second) {
      return Status::InvalidArgument(Where("database", i, entry) + ": duplicate id");
    }
  }
  std::set<std::string> query_ids;
  for (size_t i = 0; i < dataset.queries.size(); ++i) {
    const Entry& entry = dataset.queries[i];
    PLACEDB_RETURN_IF_ERROR(ValidateEntry(dataset, "queries", i, entry, check_files));
    if (!query_ids.insert(entry.id).second) {
      return Status::InvalidArgument(Where("queries", i, entry) + ": duplicate id");
    }
    for (const std::string& id : entry.ground_truth) {
      if (!database_ids.count(id)) {
        return Status::InvalidArgument(Where("queries", i, entry) +
                                       ": ground_truth names unknown database entry " + id);
      }
    }
  }
  if (dataset.database.empty()) return Status::InvalidArgument("the database list is empty");
  return Status::Ok();
}

Result<Dataset> LoadDataset(const std::string& directory) {
  if (!IsFolder(directory)) {
    return Status::NotFound(directory + ": no such dataset directory");
  }
  const std::string json_path = directory + "/dataset.json";
  auto dataset = PathExists(json_path) ? LoadJson(directory, json_path)
                 : PathExists(directory + "/database.csv")
                     ? LoadCsv(directory)
                     : Result<Dataset>(Status::NotFound(
                           directory + ": neither dataset.json nor database.csv is there"));
  if (!dataset.ok()) return dataset.status();
  PLACEDB_RETURN_IF_ERROR(ValidateDataset(*dataset, /*check_files=*/true).WithContext(directory));
  return dataset;
}

Status SaveDataset(const Dataset& dataset) {
  PLACEDB_RETURN_IF_ERROR(ValidateDataset(dataset, /*check_files=*/false));
  PLACEDB_RETURN_IF_ERROR(MakeDirectory(dataset.directory));
  // One entry per line: readable, and diffs stay small.
  std::string text = "{\n \"format\": " + json(kDatasetFormat).dump() +
                     ",\n \"name\": " + json(dataset.name).dump() +
                     ",\n \"description\": " + json(dataset.description).dump();
  for (int list = 0; list < 2; ++list) {
    const std::vector<Entry>& entries = list == 0 ? dataset.database : dataset.queries;
    text += list == 0 ? ",\n \"database\": [" : ",\n \"queries\": [";
    for (size_t i = 0; i < entries.size(); ++i) {
      text += i ? ",\n  " : "\n  ";
      text += EntryToJson(entries[i], list == 1).dump();
    }
    text += entries.empty() ? "]" : "\n ]";
  }
  text += "\n}\n";
  return WriteFileAtomically(dataset.directory + "/dataset.json", text);
}

Status SaveDatasetCsv(const Dataset& dataset) {
  PLACEDB_RETURN_IF_ERROR(ValidateDataset(dataset, /*check_files=*/false));
  PLACEDB_RETURN_IF_ERROR(MakeDirectory(dataset.directory));
  std::ostringstream boxes;
  boxes << "list,entry_id,class,confidence,x,y,width,height\n";
  bool any_boxes = false;
  for (const char* list : {"database", "queries"}) {
    const bool query = std::string(list) == "queries";
    const std::vector<Entry>& entries = query ? dataset.queries : dataset.database;
    std::ostringstream out;
    for (size_t c = 0; c < kEntryColumns.size(); ++c) out << (c ? "," : "") << kEntryColumns[c];
    out << "\n";
    for (const Entry& e : entries) {
      std::string values;
      for (size_t v = 0; v < e.mask_values.size(); ++v) {
        if (v) values += ';';
        values += std::to_string(e.mask_values[v]);
      }
      out << CsvField(e.id) << "," << CsvField(e.image) << "," << CsvField(e.mask) << "," << values
          << "," << CsvField(e.agent) << "," << e.sequence << "," << e.timestamp_ns << ","
          << (e.coverage ? CsvNumber(*e.coverage) : "") << "," << CsvField(e.source) << "\n";
      if (e.boxes) {
        any_boxes = true;
        for (const DynamicBox& b : *e.boxes) {
          boxes << list << "," << CsvField(e.id) << "," << b.class_id << ","
                << CsvNumber(b.confidence) << "," << CsvNumber(b.rect.x) << ","
                << CsvNumber(b.rect.y) << "," << CsvNumber(b.rect.width) << ","
                << CsvNumber(b.rect.height) << "\n";
        }
      }
    }
    PLACEDB_RETURN_IF_ERROR(
        WriteFileAtomically(dataset.directory + "/" + list + ".csv", out.str()));
  }
  std::ostringstream truth;
  truth << "query_id,database_id\n";
  for (const Entry& q : dataset.queries) {
    for (const std::string& id : q.ground_truth)
      truth << CsvField(q.id) << "," << CsvField(id) << "\n";
  }
  PLACEDB_RETURN_IF_ERROR(
      WriteFileAtomically(dataset.directory + "/ground_truth.csv", truth.str()));
  if (any_boxes) {
    PLACEDB_RETURN_IF_ERROR(WriteFileAtomically(dataset.directory + "/boxes.csv", boxes.str()));
  }
  return Status::Ok();
}

std::vector<std::vector<int>> GroundTruthIndices(const Dataset& dataset) {
  std::map<std::string, int> index;
  for (size_t i = 0; i < dataset.database.size(); ++i) index[dataset.database[i].id] = int(i);
  std::vector<std::vector<int>> truth(dataset.queries.size());
  for (size_t q = 0; q < dataset.queries.size(); ++q) {
    for (const std::string& id : dataset.queries[q].ground_truth) {
      auto it = index.find(id);
      if (it != index.end()) truth[q].push_back(it->second);
    }
    std::sort(truth[q].begin(), truth[q].end());
    truth[q].erase(std::unique(truth[q].begin(), truth[q].end()), truth[q].end());
  }
  return truth;
}

Result<cv::Mat> LoadEntryMask(const Dataset& dataset, const Entry& entry, cv::Size expected) {
  if (entry.mask.empty()) return cv::Mat();
  const std::string path = dataset.Resolve(entry.mask);
  cv::Mat raw = cv::imread(path, cv::IMREAD_GRAYSCALE);
  if (raw.empty()) return Status::IoError("cannot read mask " + path);
  if (expected.area() > 0 && raw.size() != expected) {
    return Status::InvalidArgument(
        "mask " + path + " is " + std::to_string(raw.cols) + "x" + std::to_string(raw.rows) +
        ", its image is " + std::to_string(expected.width) + "x" + std::to_string(expected.height));
  }
  cv::Mat mask;
  if (entry.mask_values.empty()) {
    mask = raw > 0;
  } else {
    mask = cv::Mat::zeros(raw.size(), CV_8U);
    for (int value : entry.mask_values) mask |= (raw == value);
  }
  return mask;
}

double EntryCoverage(const Dataset& dataset, const Entry& entry, cv::Size image_size) {
  if (entry.coverage) return *entry.coverage;
  if (!entry.mask.empty()) {
    auto mask = LoadEntryMask(dataset, entry);
    if (mask.ok() && !mask->empty()) return cv::countNonZero(*mask) / double(mask->total());
  }
  if (entry.boxes && !entry.boxes->empty() && image_size.area() > 0) {
    DynamicObjects objects;
    objects.boxes = *entry.boxes;
    cv::Mat region = RasterizeDynamicRegion(objects, image_size.width, image_size.height);
    return cv::countNonZero(region) / double(region.total());
  }
  return 0.0;
}

std::string CsvField(const std::string& value) {
  if (value.find_first_of(",\"\n\r") == std::string::npos) return value;
  std::string quoted = "\"";
  for (char c : value) {
    if (c == '"') quoted += '"';
    quoted += c;
  }
  return quoted + "\"";
}

std::vector<std::string> SplitCsvLine(const std::string& line) {
  std::vector<std::string> fields;
  std::string field;
  bool quoted = false;
  for (size_t i = 0; i < line.size(); ++i) {
    const char c = line[i];
    if (quoted) {
      if (c == '"' && i + 1 < line.size() && line[i + 1] == '"') {
        field += '"';
        ++i;
      } else if (c == '"') {
        quoted = false;
      } else {
        field += c;
      }
    } else if (c == '"') {
      quoted = true;
    } else if (c == ',') {
      fields.push_back(std::move(field));
      field.clear();
    } else {
      field += c;
    }
  }
  fields.push_back(std::move(field));
  return fields;
}

}  // namespace placedb::eval
