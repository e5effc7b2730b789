#include "core/vocabulary/any_vocabulary.h"

#include <cstring>
#include <fstream>

namespace placedb {

const char* VocabularyKindName(FeatureType type) {
  return type == FeatureType::kSift ? "float (SIFT)" : "binary (ORB)";
}

AnyVocabulary::AnyVocabulary(std::shared_ptr<const Vocabulary> binary)
    : binary_(std::move(binary)) {}

AnyVocabulary::AnyVocabulary(std::shared_ptr<const FloatVocabulary> floating)
    : floating_(std::move(floating)) {}

Result<AnyVocabulary> AnyVocabulary::Load(const std::string& path) {
  char magic[8] = {};
  {
    std::ifstream in(path, std::ios::binary);
    if (!in) return Status::NotFound("vocabulary file '" + path + "' cannot be opened");
    in.read(magic, sizeof(magic));
  }
  if (std::memcmp(magic, "PDBFVOC1", sizeof(magic)) == 0) {
    auto floating = FloatVocabulary::Load(path);
    if (!floating.ok()) return floating.status();
    return AnyVocabulary(std::move(floating).value());
  }
  auto binary = Vocabulary::Load(path);
  if (!binary.ok()) return binary.status();
  return AnyVocabulary(std::move(binary).value());
}

std::string AnyVocabulary::Serialize() const {
  if (floating_) return floating_->Serialize();
  if (binary_) return binary_->SerializeBinary();
  return {};
}

Result<AnyVocabulary> AnyVocabulary::Parse(std::string_view bytes) {
  if (bytes.size() >= 8 && std::memcmp(bytes.data(), "PDBFVOC1", 8) == 0) {
    auto floating = FloatVocabulary::Parse(bytes);
    if (!floating.ok()) return floating.status();
    return AnyVocabulary(std::move(floating).value());
  }
  auto binary = Vocabulary::ParseBinary(bytes);
  if (!binary.ok()) return binary.status();
  return AnyVocabulary(std::move(binary).value());
}

uint32_t AnyVocabulary::word_count() const {
  return floating_ ? floating_->word_count() : binary_ ? binary_->word_count() : 0;
}
uint32_t AnyVocabulary::node_count() const {
  return floating_ ? floating_->node_count() : binary_ ? binary_->node_count() : 0;
}
int AnyVocabulary::branching() const {
  return floating_ ? floating_->branching() : binary_ ? binary_->branching() : 0;
}
int AnyVocabulary::depth() const {
  return floating_ ? floating_->depth() : binary_ ? binary_->depth() : 0;
}
uint64_t AnyVocabulary::checksum() const {
  return floating_ ? floating_->checksum() : binary_ ? binary_->checksum() : 0;
}
std::string AnyVocabulary::checksum_hex() const {
  return floating_ ? floating_->checksum_hex() : binary_ ? binary_->checksum_hex() : "";
}
size_t AnyVocabulary::memory_bytes() const {
  return floating_ ? floating_->memory_bytes() : binary_ ? binary_->memory_bytes() : 0;
}
const char* AnyVocabulary::kind() const {
  return VocabularyKindName(feature_type());
}

Status AnyVocabulary::Transform(const LocalFeatures& features, BowVector* bow, DirectIndex* direct,
                                int levels_up) const {
  if (binary_ && features.orb()) {
    binary_->Transform(features.orb()->descriptors, bow, direct, levels_up);
  } else if (floating_ && features.sift()) {
    floating_->Transform(features.sift()->descriptors, bow, direct, levels_up);
  } else {
    return Status::InvalidArgument(std::string(FeatureTypeName(features.type())) +
                                   " features need a " + VocabularyKindName(features.type()) +
                                   " vocabulary; this one is " + (*this ? kind() : "missing"));
  }
  return Status::Ok();
}

}  // namespace placedb
