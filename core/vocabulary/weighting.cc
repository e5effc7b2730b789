#include "core/vocabulary/weighting.h"

#include <cmath>

namespace placedb {

namespace {

struct ScoringEntry {
  ScoringType type;
  const char* name;
};
constexpr ScoringEntry kScorings[] = {
    {ScoringType::kL1, "l1"},
    {ScoringType::kL2, "l2"},
    {ScoringType::kChiSquare, "chi2"},
    {ScoringType::kKL, "kl"},
    {ScoringType::kBhattacharyya, "bhattacharyya"},
    {ScoringType::kDotProduct, "dot"},
};

}  // namespace

const char* ScoringName(ScoringType type) {
  for (const auto& entry : kScorings) {
    if (entry.type == type) return entry.name;
  }
  return "unknown";
}

Result<ScoringType> ParseScoring(const std::string& name) {
  std::string names;
  for (const auto& entry : kScorings) {
    if (name == entry.name) return entry.type;
    names += names.empty() ? "" : ", ";
    names += entry.name;
  }
  return Status::InvalidArgument("scoring: unknown name '" + name + "'; expected one of " + names);
}

const char* WeightingName(WeightingType type) {
  switch (type) {
    case WeightingType::kTfIdf:
      return "tf-idf";
    case WeightingType::kTf:
      return "tf";
    case WeightingType::kIdf:
      return "idf";
    case WeightingType::kBinary:
      return "binary";
  }
  return "unknown";
}

void NormalizeForScoring(BowVector* bow, ScoringType type) {
  double norm = 0;
  switch (type) {
    case ScoringType::kL2:
      for (const BowEntry& entry : *bow) norm += double(entry.weight) * double(entry.weight);
      norm = std::sqrt(norm);
      break;
    case ScoringType::kDotProduct:
      return;
    case ScoringType::kL1:
    case ScoringType::kChiSquare:
    case ScoringType::kKL:
    case ScoringType::kBhattacharyya:
      for (const BowEntry& entry : *bow) norm += std::fabs(double(entry.weight));
      break;
  }
  if (norm <= 0) return;  // an empty or all-zero vector stays as it is
  for (BowEntry& entry : *bow) entry.weight = float(double(entry.weight) / norm);
}

}  // namespace placedb
