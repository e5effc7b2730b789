// A closed map's RocksDB opened raw (every column family, RocksDB's default options, none of
// placedb's), for tests that damage or inspect what placedb wrote. The map must not be open.
#pragma once

#include <rocksdb/db.h>

#include <functional>
#include <string>
#include <vector>

namespace placedb::testing {

// The handles in placedb's column family order: default, places, bow, features, invalid,
// dynamics, thumbnails; then the map's other families (an adapted vocabulary's "bow.<g>").
using RawEdit =
    std::function<void(rocksdb::DB*, std::vector<rocksdb::ColumnFamilyHandle*>& handles)>;

// Opens the map at `map_dir` read-write, runs `edit`, closes it (a clean close: RocksDB flushes).
// Fails the test when it does not open.
void EditRawMap(const std::string& map_dir, const RawEdit& edit);

// The live SST files (paths) of one column family, read from the map's MANIFEST (read-only).
std::vector<std::string> SstFilesOf(const std::string& map_dir, const std::string& family);

// Overwrites 64 bytes in the middle of the largest SST file in `map_dir` (a closed map's; the
// features family's, which is the largest) and returns that file's name (no folder). Fails the
// test, and returns "", when there is none.
std::string GarbleLargestSst(const std::string& map_dir);

}  // namespace placedb::testing
