#include "tests/raw_map.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <fstream>

namespace placedb::testing {

namespace {

// placedb's families in its order, then any other the map has (a later vocabulary's "bow.<g>").
std::vector<rocksdb::ColumnFamilyDescriptor> Families(const std::string& map_dir) {
  std::vector<std::string> names = {"default", "places",   "bow",        "features",
                                    "invalid", "dynamics", "thumbnails", "loops"};
  std::vector<std::string> present;
  if (rocksdb::DB::ListColumnFamilies(rocksdb::DBOptions(), map_dir, &present).ok()) {
    for (const std::string& name : present) {
      if (std::find(names.begin(), names.end(), name) == names.end()) names.push_back(name);
    }
  }
  std::vector<rocksdb::ColumnFamilyDescriptor> families;
  for (const std::string& name : names) {
    families.emplace_back(name, rocksdb::ColumnFamilyOptions());
  }
  return families;
}

void Close(rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
  for (auto* handle : handles) (void)raw->DestroyColumnFamilyHandle(handle);
  delete raw;
}

}  // namespace

void EditRawMap(const std::string& map_dir, const RawEdit& edit) {
  std::vector<rocksdb::ColumnFamilyHandle*> handles;
  rocksdb::DB* raw = nullptr;
  const rocksdb::Status opened =
      rocksdb::DB::Open(rocksdb::DBOptions(), map_dir, Families(map_dir), &handles, &raw);
  ASSERT_TRUE(opened.ok()) << map_dir << ": " << opened.ToString();
  edit(raw, handles);
  Close(raw, handles);
}

std::vector<std::string> SstFilesOf(const std::string& map_dir, const std::string& family) {
  std::vector<rocksdb::ColumnFamilyHandle*> handles;
  rocksdb::DB* raw = nullptr;
  std::vector<std::string> files;
  const rocksdb::Status opened = rocksdb::DB::OpenForReadOnly(rocksdb::DBOptions(), map_dir,
                                                              Families(map_dir), &handles, &raw);
  EXPECT_TRUE(opened.ok()) << map_dir << ": " << opened.ToString();
  if (!opened.ok()) return files;
  std::vector<rocksdb::LiveFileMetaData> live;
  raw->GetLiveFilesMetaData(&live);
  for (const auto& file : live) {
    if (file.column_family_name == family) files.push_back(file.db_path + file.name);
  }
  Close(raw, handles);
  return files;
}

std::string GarbleLargestSst(const std::string& map_dir) {
  namespace fs = std::filesystem;
  fs::path largest;
  for (const auto& entry : fs::directory_iterator(map_dir)) {
    if (entry.path().extension() != ".sst") continue;
    if (largest.empty() || entry.file_size() > fs::file_size(largest)) largest = entry.path();
  }
  EXPECT_FALSE(largest.empty()) << "no SST file in " << map_dir;
  if (largest.empty()) return "";
  std::fstream file(largest, std::ios::in | std::ios::out | std::ios::binary);
  file.seekp(std::streamoff(fs::file_size(largest) / 2));
  const std::string noise(64, '\x5a');
  file.write(noise.data(), std::streamsize(noise.size()));
  return largest.filename().string();
}

}  // namespace placedb::testing
