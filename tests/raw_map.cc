#include "tests/raw_map.h"

#include <gtest/gtest.h>

#include <algorithm>

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

}  // namespace placedb::testing
