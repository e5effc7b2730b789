// Checks shared by the vocabulary targets: what a vocabulary that loaded must do safely.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "core/vocabulary/vocabulary.h"
#include "tests/fuzz/fuzz_support.h"

namespace placedb::fuzz {

// Quantises up to 8 descriptors taken from `bytes` at every direct-index level: a loaded tree is
// trusted by the descent (no bounds checks there), so the loader's validation must make every
// path safe. Words and nodes must be in range, the BoW sorted without duplicates.
inline void CheckTransform(const Vocabulary& vocabulary, std::string_view bytes) {
  std::vector<Descriptor256> descriptors;
  for (size_t at = 0; at + Descriptor256::kBytes <= bytes.size() && descriptors.size() < 8;
       at += Descriptor256::kBytes) {
    descriptors.push_back(
        Descriptor256::FromBytes(reinterpret_cast<const uint8_t*>(bytes.data() + at)));
  }
  descriptors.push_back(Descriptor256{});  // at least one
  for (int levels_up = 0; levels_up <= vocabulary.depth(); ++levels_up) {
    BowVector bow;
    DirectIndex direct;
    vocabulary.Transform(descriptors, &bow, &direct, levels_up);
    for (size_t i = 0; i < bow.size(); ++i) {
      PLACEDB_FUZZ_CHECK(bow[i].word < vocabulary.word_count(), "Transform: word out of range");
      PLACEDB_FUZZ_CHECK(i == 0 || bow[i - 1].word < bow[i].word, "Transform: BoW not sorted");
    }
    for (NodeId node : direct.node_ids) {
      PLACEDB_FUZZ_CHECK(node < vocabulary.node_count(), "Transform: direct node out of range");
    }
    for (uint32_t feature : direct.feature_ids) {
      PLACEDB_FUZZ_CHECK(feature < descriptors.size(), "Transform: direct feature out of range");
    }
  }
}

// Export to DBoW2 text, import, export again: the same text (the text format is canonical for
// what it can express; a numbering it cannot keep is refused with FAILED_PRECONDITION).
inline void CheckTextRoundTrip(const Vocabulary& vocabulary) {
  const std::string path = ScratchDir() + "/export.txt";
  const Status exported = vocabulary.ExportDbow2Text(path);
  if (!exported.ok()) {
    PLACEDB_FUZZ_CHECK(exported.code() == StatusCode::kFailedPrecondition,
                       "ExportDbow2Text: unexpected error " + exported.ToString());
    return;
  }
  auto first = ReadWholeFileOrDie(path);
  auto imported = Vocabulary::ImportDbow2Text(path);
  if (!imported.ok()) Fail("an exported DBoW2 text does not import", imported.status());
  const Status again = (*imported)->ExportDbow2Text(path);
  if (!again.ok()) Fail("a re-imported vocabulary does not export", again);
  PLACEDB_FUZZ_CHECK(ReadWholeFileOrDie(path) == first, "DBoW2 text export/import not stable");
}

}  // namespace placedb::fuzz
