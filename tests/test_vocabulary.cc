#include <gtest/gtest.h>

#include <cstdlib>
#include <mutex>

#include "tests/test_support.h"
#include "tools/rgbd_data.h"

namespace placedb::testing {

std::string DefaultVocabularyPath() {
  if (const char* env = std::getenv("PLACEDB_VOCABULARY")) return env;
  return PLACEDB_DEFAULT_VOCABULARY;
}

std::shared_ptr<const Vocabulary> DefaultVocabulary() {
  static std::once_flag once;
  static std::shared_ptr<const Vocabulary> vocabulary;
  static std::string error;
  std::call_once(once, [] {
    auto loaded = Vocabulary::Load(DefaultVocabularyPath());
    if (loaded.ok()) {
      vocabulary = *loaded;
    } else {
      error = loaded.status().ToString();
    }
  });
  EXPECT_TRUE(vocabulary) << "default vocabulary " << DefaultVocabularyPath() << ": " << error
                          << " (build it with tools/build_default_vocabulary.sh)";
  return vocabulary;
}

std::shared_ptr<const Vocabulary> OtherVocabulary() {
  auto vocabulary = DefaultVocabulary();
  if (!vocabulary) return nullptr;
  VocabularyTree tree = vocabulary->ToTree();
  for (size_t i = 0; i < tree.word_id.size(); ++i) {
    if (tree.word_id[i] >= 0) {
      tree.weight[i] += 1.0f;
      break;
    }
  }
  auto other = Vocabulary::FromTree(tree);
  EXPECT_TRUE(other.ok()) << other.status().ToString();
  return other.ok() ? *other : nullptr;
}

std::shared_ptr<const FloatVocabulary> SiftVocabulary() {
  static const std::shared_ptr<const FloatVocabulary> vocabulary =
      []() -> std::shared_ptr<const FloatVocabulary> {
    auto loaded = rgbd::LoadOrTrainSiftVocabulary(rgbd::SiftVocabularyPath());
    EXPECT_TRUE(loaded.ok()) << loaded.status().ToString();
    return loaded.ok() ? *loaded : nullptr;
  }();
  return vocabulary;
}

}  // namespace placedb::testing
