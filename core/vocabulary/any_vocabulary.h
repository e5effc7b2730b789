// AnyVocabulary: the vocabulary a map quantises with, binary (ORB, vocabulary.h) or float (SIFT,
// float_vocabulary.h). A map is typed by its feature: the vocabulary's kind fixes which features
// it takes. Both kinds produce the same BowVector / DirectIndex, so the inverted index, scoring,
// storage of BoW vectors and loop closure do not care which one is behind it; Transform() takes
// the map's LocalFeatures and quantises them with the vocabulary of their family.
//
// A cheap value (a shared_ptr): copies share the vocabulary, never copy it. Implicitly built from
// either shared_ptr, so code written for ORB maps keeps passing a Vocabulary.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "core/base/status.h"
#include "core/features/local_features.h"
#include "core/vocabulary/float_vocabulary.h"
#include "core/vocabulary/vocabulary.h"

namespace placedb {

// The kind of vocabulary a feature type needs, for messages: "binary (ORB)", "float (SIFT)".
const char* VocabularyKindName(FeatureType type);

class AnyVocabulary {
 public:
  AnyVocabulary() = default;
  AnyVocabulary(std::shared_ptr<const Vocabulary> binary);         // NOLINT: implicit on purpose
  AnyVocabulary(std::shared_ptr<const FloatVocabulary> floating);  // NOLINT
  // A .pdbfv file is a float vocabulary; anything else goes to Vocabulary::Load (binary .pdbv or
  // DBoW2 text).
  static Result<AnyVocabulary> Load(const std::string& path);
  // The file's bytes (.pdbv or .pdbfv) in memory, and back: how a map stores a vocabulary it
  // learned. Parse checks what Load checks (CORRUPTION / INVALID_ARGUMENT without a path).
  std::string Serialize() const;  // empty without a vocabulary
  static Result<AnyVocabulary> Parse(std::string_view bytes);

  explicit operator bool() const { return binary_ || floating_; }
  FeatureType feature_type() const { return floating_ ? FeatureType::kSift : FeatureType::kOrb; }
  const std::shared_ptr<const Vocabulary>& binary() const { return binary_; }  // null if float
  const std::shared_ptr<const FloatVocabulary>& floating() const { return floating_; }  // or null

  uint32_t word_count() const;
  uint32_t node_count() const;
  int branching() const;
  int depth() const;
  uint64_t checksum() const;
  std::string checksum_hex() const;
  size_t memory_bytes() const;
  // "binary (ORB)" or "float (SIFT)": for messages.
  const char* kind() const;

  // Quantises `features` into a weighted BoW vector and, when `direct` is given, the direct
  // index at `levels_up` (Vocabulary::Transform). INVALID_ARGUMENT when the features are not of
  // this vocabulary's feature type, or without a vocabulary.
  Status Transform(const LocalFeatures& features, BowVector* bow, DirectIndex* direct,
                   int levels_up) const;

 private:
  std::shared_ptr<const Vocabulary> binary_;
  std::shared_ptr<const FloatVocabulary> floating_;
};

}  // namespace placedb
