// The binary vocabulary loader (Vocabulary::LoadBinary, .pdbv) on arbitrary files. The first
// byte's low bit asks the target to write correct header and block checksums into the file
// before loading it: random bytes almost never pass a 64-bit checksum, and the interesting code
// (ValidateBlock, which must make every descent through the tree safe) runs only after it.
// Invariants: no crash; a loaded vocabulary quantises descriptors within bounds, saves and loads
// back with the same checksum, and its DBoW2 text export is stable under re-import.
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>
#include <string_view>

#include "core/vocabulary/vocabulary.h"
#include "tests/fuzz/fuzz_support.h"
#include "tests/fuzz/vocabulary_checks.h"

namespace {

// Offsets in the 64-byte header (core/vocabulary/vocabulary_io.cc, FileHeader).
constexpr size_t kHeaderBytes = 64;
constexpr size_t kBlockChecksumAt = 48;
constexpr size_t kHeaderChecksumAt = 56;

void FixChecksums(std::string* file) {
  if (file->size() < kHeaderBytes) return;
  const uint64_t block =
      placedb::Checksum64(file->data() + kHeaderBytes, file->size() - kHeaderBytes);
  std::memcpy(file->data() + kBlockChecksumAt, &block, sizeof(block));
  const uint64_t header = placedb::Checksum64(file->data(), kHeaderChecksumAt);
  std::memcpy(file->data() + kHeaderChecksumAt, &header, sizeof(header));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  if (size == 0) return 0;
  std::string file(reinterpret_cast<const char*>(data) + 1, size - 1);
  const bool fixed = data[0] & 1;
  if (fixed) FixChecksums(&file);
  const std::string path = fuzz::WriteScratchFile("input.pdbv", file);
  auto loaded = Vocabulary::LoadBinary(path);
  if (!loaded.ok()) {
    const StatusCode code = loaded.status().code();
    PLACEDB_FUZZ_CHECK(code == StatusCode::kCorruption || code == StatusCode::kInvalidArgument ||
                           code == StatusCode::kResourceExhausted,
                       "LoadBinary: unexpected error " + loaded.status().ToString());
    // A stale FixChecksums (the format changed) would silently stop the fuzzing at the checksum.
    PLACEDB_FUZZ_CHECK(!fixed || file.size() < kHeaderBytes ||
                           loaded.status().message().find("checksum mismatch") == std::string::npos,
                       "FixChecksums no longer matches the format: update the offsets");
    return 0;
  }
  const Vocabulary& vocabulary = **loaded;
  fuzz::CheckTransform(vocabulary, std::string_view(file).substr(kHeaderBytes));

  const std::string saved = fuzz::ScratchDir() + "/saved.pdbv";
  if (Status s = vocabulary.SaveBinary(saved); !s.ok()) fuzz::Fail("SaveBinary", s);
  auto reloaded = Vocabulary::LoadBinary(saved);
  if (!reloaded.ok()) fuzz::Fail("a saved vocabulary does not load", reloaded.status());
  PLACEDB_FUZZ_CHECK((*reloaded)->checksum() == vocabulary.checksum(),
                     "save/load changed the checksum");

  fuzz::CheckTextRoundTrip(vocabulary);
  return 0;
}
