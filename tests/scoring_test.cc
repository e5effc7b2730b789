#include "core/search/scoring.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <set>

namespace placedb {
namespace {

constexpr ScoringType kAllScorings[] = {
    ScoringType::kL1,
    ScoringType::kL2,
    ScoringType::kChiSquare,
    ScoringType::kKL,
    ScoringType::kBhattacharyya,
    ScoringType::kDotProduct,
};

BowVector Normalized(BowVector bow, ScoringType type) {
  NormalizeForScoring(&bow, type);
  return bow;
}

// What an inverted index computes: only the words both vectors share are visited.
double DecomposedScore(const BowVector& query, const BowVector& candidate, ScoringType type) {
  double accumulated = 0;
  auto c = candidate.begin();
  for (const BowEntry& q : query) {
    while (c != candidate.end() && c->word < q.word) ++c;
    if (c != candidate.end() && c->word == q.word) {
      accumulated += ScoreTerm(type, q.weight, c->weight);
    }
  }
  return FinalizeScore(type, accumulated, QueryConstant(type, query));
}

BowVector RandomBow(std::mt19937& rng, uint32_t vocabulary, size_t max_words) {
  std::uniform_int_distribution<uint32_t> word(0, vocabulary - 1);
  std::uniform_int_distribution<size_t> count(1, max_words);
  std::uniform_real_distribution<float> weight(0.01f, 1.0f);
  std::set<uint32_t> words;
  const size_t n = count(rng);
  while (words.size() < n) words.insert(word(rng));
  BowVector bow;
  for (uint32_t w : words) bow.push_back({w, weight(rng)});
  return bow;
}

TEST(ScoringTest, L1OnHandComputedVectors) {
  // |v - w|_1 = 0.4 + 0.4 = 0.8, so 1 - 0.4.
  const BowVector v = {{1, 0.2f}, {2, 0.8f}};
  const BowVector w = {{1, 0.6f}, {2, 0.4f}};
  EXPECT_NEAR(Score(v, w, ScoringType::kL1), 0.6, 1e-7);
  // Half the mass shared: |v - w|_1 = 0.5 + 0 + 0.5.
  const BowVector a = {{1, 0.5f}, {2, 0.5f}};
  const BowVector b = {{2, 0.5f}, {3, 0.5f}};
  EXPECT_NEAR(Score(a, b, ScoringType::kL1), 0.5, 1e-7);
}

TEST(ScoringTest, L2OnHandComputedVectors) {
  const BowVector a = Normalized({{1, 1.0f}, {2, 1.0f}}, ScoringType::kL2);
  const BowVector b = Normalized({{2, 1.0f}, {3, 1.0f}}, ScoringType::kL2);
  // <a, b> = 1/2, so 1 - sqrt(1/2).
  EXPECT_NEAR(Score(a, b, ScoringType::kL2), 1.0 - std::sqrt(0.5), 1e-6);
}

TEST(ScoringTest, ChiSquareOnHandComputedVectors) {
  // chi2 = 0.25/0.5 + 0 + 0.25/0.5 = 1, so 1 - 0.5.
  const BowVector a = {{1, 0.5f}, {2, 0.5f}};
  const BowVector b = {{2, 0.5f}, {3, 0.5f}};
  EXPECT_NEAR(Score(a, b, ScoringType::kChiSquare), 0.5, 1e-7);
  // chi2 = (0.2-0.6)^2/0.8 + (0.8-0.4)^2/1.2 = 0.2 + 0.1333..
  const BowVector v = {{1, 0.2f}, {2, 0.8f}};
  const BowVector w = {{1, 0.6f}, {2, 0.4f}};
  EXPECT_NEAR(Score(v, w, ScoringType::kChiSquare), 1.0 - 0.5 * (0.2 + 0.16 / 1.2), 1e-6);
}

TEST(ScoringTest, KlOnHandComputedVectors) {
  // Word 1 is missing from b (epsilon 1e-12); word 2 contributes 0.5 * ln(1) = 0.
  const BowVector a = {{1, 0.5f}, {2, 0.5f}};
  const BowVector b = {{2, 0.5f}, {3, 0.5f}};
  EXPECT_NEAR(Score(a, b, ScoringType::kKL), -0.5 * (std::log(0.5) - std::log(1e-12)), 1e-9);
  const BowVector v = {{1, 0.2f}, {2, 0.8f}};
  const BowVector w = {{1, 0.6f}, {2, 0.4f}};
  const double kl = 0.2 * std::log(0.2 / 0.6) + 0.8 * std::log(0.8 / 0.4);
  EXPECT_NEAR(Score(v, w, ScoringType::kKL), -kl, 1e-6);
  // Not symmetric.
  EXPECT_GT(std::fabs(Score(v, w, ScoringType::kKL) - Score(w, v, ScoringType::kKL)), 1e-3);
}

TEST(ScoringTest, BhattacharyyaOnHandComputedVectors) {
  const BowVector v = {{1, 0.2f}, {2, 0.8f}};
  const BowVector w = {{1, 0.8f}, {3, 0.2f}};
  EXPECT_NEAR(Score(v, w, ScoringType::kBhattacharyya), std::sqrt(0.16), 1e-7);
}

TEST(ScoringTest, DotProductIsUnnormalised) {
  const BowVector v = {{1, 2.0f}, {2, 3.0f}};
  const BowVector w = {{2, 4.0f}, {5, 1.0f}};
  EXPECT_DOUBLE_EQ(Score(v, w, ScoringType::kDotProduct), 12.0);
  EXPECT_EQ(Normalized(v, ScoringType::kDotProduct), v);
}

TEST(ScoringTest, NormalizeUsesTheNormEachScoringNeeds) {
  const BowVector bow = {{1, 1.0f}, {4, 3.0f}};
  for (ScoringType type :
       {ScoringType::kL1, ScoringType::kChiSquare, ScoringType::kKL, ScoringType::kBhattacharyya}) {
    const BowVector normalized = Normalized(bow, type);
    ASSERT_EQ(normalized.size(), 2u);
    EXPECT_FLOAT_EQ(normalized[0].weight, 0.25f) << ScoringName(type);
    EXPECT_FLOAT_EQ(normalized[1].weight, 0.75f) << ScoringName(type);
    EXPECT_EQ(normalized[1].word, 4u);
  }
  const BowVector l2 = Normalized({{1, 3.0f}, {2, 4.0f}}, ScoringType::kL2);
  EXPECT_FLOAT_EQ(l2[0].weight, 0.6f);
  EXPECT_FLOAT_EQ(l2[1].weight, 0.8f);
}

TEST(ScoringTest, NormalizeLeavesZeroVectorsAlone) {
  for (ScoringType type : kAllScorings) {
    EXPECT_TRUE(Normalized({}, type).empty());
    const BowVector zero = {{3, 0.0f}};
    EXPECT_EQ(Normalized(zero, type), zero) << ScoringName(type);
  }
}

TEST(ScoringTest, IdenticalVectorsScoreTheMaximum) {
  std::mt19937 rng(7);
  for (int trial = 0; trial < 20; ++trial) {
    const BowVector raw = RandomBow(rng, 500, 60);
    EXPECT_NEAR(Score(Normalized(raw, ScoringType::kL1), Normalized(raw, ScoringType::kL1),
                      ScoringType::kL1),
                1.0, 1e-6);
    EXPECT_NEAR(Score(Normalized(raw, ScoringType::kChiSquare),
                      Normalized(raw, ScoringType::kChiSquare), ScoringType::kChiSquare),
                1.0, 1e-6);
    EXPECT_NEAR(Score(Normalized(raw, ScoringType::kBhattacharyya),
                      Normalized(raw, ScoringType::kBhattacharyya), ScoringType::kBhattacharyya),
                1.0, 1e-6);
    EXPECT_NEAR(Score(Normalized(raw, ScoringType::kKL), Normalized(raw, ScoringType::kKL),
                      ScoringType::kKL),
                0.0, 1e-9);
    // 1 - sqrt(1 - <v, v>) turns the float rounding of the unit norm (~1e-7) into ~3e-4.
    EXPECT_NEAR(Score(Normalized(raw, ScoringType::kL2), Normalized(raw, ScoringType::kL2),
                      ScoringType::kL2),
                1.0, 1e-3);
  }
  // Exactly representable unit vector: exactly 1.
  const BowVector unit = {{1, 0.5f}, {2, 0.5f}, {3, 0.5f}, {4, 0.5f}};
  EXPECT_DOUBLE_EQ(Score(unit, unit, ScoringType::kL2), 1.0);
}

TEST(ScoringTest, DisjointVectorsScoreZero) {
  const BowVector a = {{1, 0.25f}, {3, 0.75f}};
  const BowVector b = {{2, 0.5f}, {4, 0.5f}};
  for (ScoringType type : {ScoringType::kL1, ScoringType::kL2, ScoringType::kChiSquare,
                           ScoringType::kBhattacharyya, ScoringType::kDotProduct}) {
    EXPECT_NEAR(Score(Normalized(a, type), Normalized(b, type), type), 0.0, 1e-7)
        << ScoringName(type);
  }
  // KL of disjoint vectors is the worst it can be: every word at epsilon.
  EXPECT_NEAR(Score(a, b, ScoringType::kKL), -QueryConstant(ScoringType::kKL, a), 1e-9);
}

TEST(ScoringTest, ScoresStayInTheirRange) {
  std::mt19937 rng(11);
  for (int trial = 0; trial < 200; ++trial) {
    const BowVector a = RandomBow(rng, 100, 30);
    const BowVector b = RandomBow(rng, 100, 30);
    for (ScoringType type : {ScoringType::kL1, ScoringType::kL2, ScoringType::kChiSquare,
                             ScoringType::kBhattacharyya}) {
      const double s = Score(Normalized(a, type), Normalized(b, type), type);
      EXPECT_GE(s, -1e-6) << ScoringName(type);
      EXPECT_LE(s, 1 + 1e-6) << ScoringName(type);
    }
    EXPECT_LE(
        Score(Normalized(a, ScoringType::kKL), Normalized(b, ScoringType::kKL), ScoringType::kKL),
        1e-9);
  }
}

TEST(ScoringTest, InvertedIndexDecompositionAgreesWithScore) {
  std::mt19937 rng(3);
  for (ScoringType type : kAllScorings) {
    for (int trial = 0; trial < 300; ++trial) {
      // A small vocabulary so that most pairs share some words.
      const BowVector q = Normalized(RandomBow(rng, 200, 80), type);
      const BowVector c = Normalized(RandomBow(rng, 200, 80), type);
      const double full = Score(q, c, type);
      // Float weights normalised to ~1e-7: the decomposition assumes unit norm exactly.
      EXPECT_NEAR(DecomposedScore(q, c, type), full, 1e-6 * std::max(1.0, std::fabs(full)))
          << ScoringName(type) << " trial " << trial;
    }
  }
}

TEST(ScoringTest, ScoreTermsMatchTheirDefinitions) {
  EXPECT_DOUBLE_EQ(ScoreTerm(ScoringType::kL1, 0.25f, 0.5f), 0.25 - 0.25 - 0.5);
  EXPECT_DOUBLE_EQ(ScoreTerm(ScoringType::kL2, 0.25f, 0.5f), 0.125);
  EXPECT_DOUBLE_EQ(ScoreTerm(ScoringType::kChiSquare, 0.25f, 0.5f), 0.125 / 0.75);
  EXPECT_DOUBLE_EQ(ScoreTerm(ScoringType::kKL, 0.25f, 0.5f),
                   0.25 * (std::log(1e-12) - std::log(0.5)));
  EXPECT_DOUBLE_EQ(ScoreTerm(ScoringType::kBhattacharyya, 0.25f, 0.25f), 0.25);
  EXPECT_DOUBLE_EQ(ScoreTerm(ScoringType::kDotProduct, 2.0f, 3.0f), 6.0);
  const BowVector q = {{1, 0.5f}, {2, 0.5f}};
  EXPECT_DOUBLE_EQ(QueryConstant(ScoringType::kKL, q), std::log(0.5) - std::log(1e-12));
  for (ScoringType type : kAllScorings) {
    if (type != ScoringType::kKL) {
      EXPECT_EQ(QueryConstant(type, q), 0.0) << ScoringName(type);
    }
  }
  // L2 clamps rounding above 1.
  EXPECT_EQ(FinalizeScore(ScoringType::kL2, 1.0000001, 0), 1.0);
}

TEST(ScoringTest, NamesRoundTrip) {
  std::set<std::string> names;
  for (ScoringType type : kAllScorings) {
    const std::string name = ScoringName(type);
    names.insert(name);
    auto parsed = ParseScoring(name);
    ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
    EXPECT_EQ(*parsed, type);
  }
  EXPECT_EQ(names, (std::set<std::string>{"l1", "l2", "chi2", "kl", "bhattacharyya", "dot"}));
  auto bad = ParseScoring("L3");
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(bad.status().message().find("'L3'"), std::string::npos);
  EXPECT_NE(bad.status().message().find("bhattacharyya"), std::string::npos);
  EXPECT_FALSE(ParseScoring("").ok());
}

TEST(ScoringTest, WeightingNames) {
  EXPECT_STREQ(WeightingName(WeightingType::kTfIdf), "tf-idf");
  EXPECT_STREQ(WeightingName(WeightingType::kTf), "tf");
  EXPECT_STREQ(WeightingName(WeightingType::kIdf), "idf");
  EXPECT_STREQ(WeightingName(WeightingType::kBinary), "binary");
}

TEST(ScoringTest, EnumValuesMatchDbow2) {
  // A DBoW2 text vocabulary stores these integers in its header.
  EXPECT_EQ(int(ScoringType::kL1), 0);
  EXPECT_EQ(int(ScoringType::kL2), 1);
  EXPECT_EQ(int(ScoringType::kChiSquare), 2);
  EXPECT_EQ(int(ScoringType::kKL), 3);
  EXPECT_EQ(int(ScoringType::kBhattacharyya), 4);
  EXPECT_EQ(int(ScoringType::kDotProduct), 5);
  EXPECT_EQ(int(WeightingType::kTfIdf), 0);
  EXPECT_EQ(int(WeightingType::kBinary), 3);
}

}  // namespace
}  // namespace placedb
