// The start of a snapshot archive (core/storage/snapshots.h, "Archive"), for tests that build
// hostile ones: its header and the framing of a first entry `path` that states `size` bytes, none
// of which follow.
#pragma once

#include <cstdint>
#include <string>

namespace placedb::testing {

inline std::string ArchiveStart(const std::string& path, uint64_t size) {
  std::string out = "PDBSNAP\n";
  auto put = [&](uint64_t value, int bytes) {
    for (int i = 0; i < bytes; ++i) out.push_back(char((value >> (8 * i)) & 0xff));
  };
  put(1, 4);  // version
  put(0, 4);  // flags
  put(1, 1);  // an entry
  put(path.size(), 2);
  out += path;
  put(size, 8);
  return out;
}

}  // namespace placedb::testing
