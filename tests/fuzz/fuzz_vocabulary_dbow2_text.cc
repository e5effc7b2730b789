// The DBoW2/DBoW3 text vocabulary importer (ORB-SLAM's ORBvoc.txt format), through
// Vocabulary::Load as the server and tools call it (a file without the binary magic is text).
// Invariants: no crash; errors are CORRUPTION (or NOT_FOUND/IO for the file itself, which is
// always there); a vocabulary that imports quantises descriptors within bounds and exports to a
// text that imports and exports again unchanged.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "core/vocabulary/vocabulary.h"
#include "tests/fuzz/fuzz_support.h"
#include "tests/fuzz/vocabulary_checks.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  const std::string path = fuzz::WriteScratchFile("input.txt", text);
  auto loaded = Vocabulary::Load(path);
  if (!loaded.ok()) {
    const StatusCode code = loaded.status().code();
    PLACEDB_FUZZ_CHECK(code == StatusCode::kCorruption || code == StatusCode::kInvalidArgument ||
                           code == StatusCode::kResourceExhausted,
                       "Load: unexpected error " + loaded.status().ToString());
    return 0;
  }
  fuzz::CheckTransform(**loaded, text);
  fuzz::CheckTextRoundTrip(**loaded);
  return 0;
}
