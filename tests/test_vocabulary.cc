#include <gtest/gtest.h>

#include <cstdlib>
#include <mutex>

#include "tests/test_support.h"

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

}  // namespace placedb::testing
