// The SIFT vocabulary loader (FloatVocabulary::Load, .pdbfv) on arbitrary files. The first byte
// asks the target to repair the file first: bit 0 sizes the payload to what the header's counts
// announce (padding with zeros or truncating, up to 4 MiB) and bit 1 writes the correct checksum,
// so that mutations of the counts and arrays reach Validate() instead of stopping at the size or
// checksum checks. Invariants: no crash; a loaded vocabulary quantises descriptors within bounds
// and saves and loads back with the same checksum.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include "core/vocabulary/float_vocabulary.h"
#include "core/vocabulary/vocabulary.h"
#include "tests/fuzz/fuzz_support.h"

namespace {

// The packed 64-byte header (core/vocabulary/float_vocabulary.cc, FileHeader).
constexpr size_t kHeaderBytes = 64;
constexpr size_t kDimensionsAt = 16;  // then branching, depth, scoring, weighting
constexpr size_t kNodeCountAt = 36;
constexpr size_t kWordCountAt = 40;
constexpr size_t kPayloadBytesAt = 48;
constexpr size_t kChecksumAt = 56;
constexpr uint64_t kMaxRepairedPayload = uint64_t(4) << 20;

uint32_t U32At(const std::string& file, size_t at) {
  uint32_t v;
  std::memcpy(&v, file.data() + at, sizeof(v));
  return v;
}

uint64_t Payload(const std::string& file) {
  const uint64_t nodes = U32At(file, kNodeCountAt);
  const uint64_t words = U32At(file, kWordCountAt);
  const uint64_t dims = U32At(file, kDimensionsAt);
  return nodes * 12 + words * 8 + nodes * dims * 4;
}

void FixSize(std::string* file) {
  const uint64_t payload = Payload(*file);
  if (payload > kMaxRepairedPayload) return;
  std::memcpy(file->data() + kPayloadBytesAt, &payload, sizeof(payload));
  file->resize(kHeaderBytes + payload, '\0');
}

// FloatVocabulary::ComputeChecksum over the arrays as the file lays them out.
void FixChecksum(std::string* file) {
  const uint64_t nodes = U32At(*file, kNodeCountAt);
  const uint64_t words = U32At(*file, kWordCountAt);
  const uint64_t dims = U32At(*file, kDimensionsAt);
  if (file->size() != kHeaderBytes + Payload(*file)) return;
  uint32_t params[5];
  std::memcpy(params, file->data() + kDimensionsAt, sizeof(params));
  uint64_t h = placedb::Checksum64(params, sizeof(params), 0x70646266766f6331ull);
  const char* at = file->data() + kHeaderBytes;
  const char* const end = file->data() + file->size();
  for (const uint64_t count : {nodes, nodes, nodes, words, words, nodes * dims}) {
    // Payload() wraps for huge counts, so a size that "matches" can still be short of them.
    if (count > uint64_t(end - at) / 4) return;
    h = placedb::Checksum64(at, count * 4, h ^ (count << 1));
    at += count * 4;
  }
  std::memcpy(file->data() + kChecksumAt, &h, sizeof(h));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace placedb;
  if (size == 0) return 0;
  std::string file(reinterpret_cast<const char*>(data) + 1, size - 1);
  const bool repair = file.size() >= kHeaderBytes;
  if (repair && (data[0] & 1)) FixSize(&file);
  if (repair && (data[0] & 2)) FixChecksum(&file);
  const std::string path = fuzz::WriteScratchFile("input.pdbfv", file);
  auto loaded = FloatVocabulary::Load(path);
  if (!loaded.ok()) {
    const StatusCode code = loaded.status().code();
    PLACEDB_FUZZ_CHECK(code == StatusCode::kCorruption || code == StatusCode::kInvalidArgument ||
                           code == StatusCode::kResourceExhausted,
                       "Load: unexpected error " + loaded.status().ToString());
    // A stale FixChecksum (the format changed) would silently stop the fuzzing at the checksum.
    PLACEDB_FUZZ_CHECK(!repair || !(data[0] & 2) || file.size() != kHeaderBytes + Payload(file) ||
                           loaded.status().message().find("checksum mismatch") == std::string::npos,
                       "FixChecksum no longer matches the format: update it");
    return 0;
  }
  const FloatVocabulary& vocabulary = **loaded;

  // A few finite descriptors from the input's bytes, quantised at every level.
  const size_t dims = size_t(vocabulary.dimensions());
  std::vector<float> descriptors(dims * 3, 0.0f);
  for (size_t i = 0; i < descriptors.size() && i < size; ++i) {
    descriptors[i] = float(int8_t(data[i])) / 16.0f;
  }
  for (int levels_up = 0; levels_up <= vocabulary.depth(); ++levels_up) {
    BowVector bow;
    DirectIndex direct;
    vocabulary.Transform(descriptors, &bow, &direct, levels_up);
    for (size_t i = 0; i < bow.size(); ++i) {
      PLACEDB_FUZZ_CHECK(bow[i].word < vocabulary.word_count(), "Transform: word out of range");
      PLACEDB_FUZZ_CHECK(std::isfinite(bow[i].weight), "Transform: non-finite weight");
    }
    for (NodeId node : direct.node_ids) {
      PLACEDB_FUZZ_CHECK(node < vocabulary.node_count(), "Transform: direct node out of range");
    }
  }

  const std::string saved = fuzz::ScratchDir() + "/saved.pdbfv";
  if (Status s = vocabulary.Save(saved); !s.ok()) fuzz::Fail("Save", s);
  auto reloaded = FloatVocabulary::Load(saved);
  if (!reloaded.ok()) fuzz::Fail("a saved vocabulary does not load", reloaded.status());
  PLACEDB_FUZZ_CHECK((*reloaded)->checksum() == vocabulary.checksum(),
                     "save/load changed the checksum");
  return 0;
}
