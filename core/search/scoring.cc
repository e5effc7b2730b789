#include "core/search/scoring.h"

#include <cmath>

namespace placedb {

namespace {

// KL divergence needs a weight for words the candidate lacks; DBoW2 uses the same epsilon.
constexpr double kKlEpsilon = 1e-12;
const double kLogKlEpsilon = std::log(kKlEpsilon);

// Calls term(q, c) for every word in the union of two sorted vectors, with 0 for a missing side.
template <typename Term>
void ForEachWordOfUnion(const BowVector& a, const BowVector& b, Term&& term) {
  auto ia = a.begin();
  auto ib = b.begin();
  while (ia != a.end() || ib != b.end()) {
    if (ib == b.end() || (ia != a.end() && ia->word < ib->word)) {
      term(double(ia->weight), 0.0);
      ++ia;
    } else if (ia == a.end() || ib->word < ia->word) {
      term(0.0, double(ib->weight));
      ++ib;
    } else {
      term(double(ia->weight), double(ib->weight));
      ++ia;
      ++ib;
    }
  }
}

}  // namespace

double Score(const BowVector& query, const BowVector& candidate, ScoringType type) {
  // The literal definitions over the union of words; the inverted-index decomposition below
  // must agree with these on normalised vectors (and the tests check that it does).
  double acc = 0;
  switch (type) {
    case ScoringType::kL1:
      ForEachWordOfUnion(query, candidate, [&](double q, double c) { acc += std::fabs(q - c); });
      return 1.0 - 0.5 * acc;
    case ScoringType::kL2: {
      ForEachWordOfUnion(query, candidate, [&](double q, double c) { acc += q * c; });
      return FinalizeScore(type, acc, 0);
    }
    case ScoringType::kChiSquare:
      ForEachWordOfUnion(query, candidate, [&](double q, double c) {
        if (q + c > 0) acc += (q - c) * (q - c) / (q + c);
      });
      return 1.0 - 0.5 * acc;
    case ScoringType::kKL:
      ForEachWordOfUnion(query, candidate, [&](double q, double c) {
        if (q <= 0) return;  // 0 * log(0 / c) = 0
        acc += q * (std::log(q) - (c > 0 ? std::log(c) : kLogKlEpsilon));
      });
      return -acc;
    case ScoringType::kBhattacharyya:
      ForEachWordOfUnion(query, candidate, [&](double q, double c) {
        if (q > 0 && c > 0) acc += std::sqrt(q * c);
      });
      return acc;
    case ScoringType::kDotProduct:
      ForEachWordOfUnion(query, candidate, [&](double q, double c) { acc += q * c; });
      return acc;
  }
  return 0;
}

double ScoreTerm(ScoringType type, float query_weight, float candidate_weight) {
  const double q = query_weight;
  const double c = candidate_weight;
  switch (type) {
    case ScoringType::kL1:
      // |q - c| replaces the |q| + |c| the union sum would count for this word if unshared.
      return std::fabs(q - c) - std::fabs(q) - std::fabs(c);
    case ScoringType::kL2:
    case ScoringType::kDotProduct:
      return q * c;
    case ScoringType::kChiSquare:
      return q + c > 0 ? q * c / (q + c) : 0.0;
    case ScoringType::kKL:
      // Corrects QueryConstant's q * (ln q - ln eps) to the shared word's q * (ln q - ln c).
      if (q <= 0 || c <= 0) return 0.0;
      return q * (kLogKlEpsilon - std::log(c));
    case ScoringType::kBhattacharyya:
      return q > 0 && c > 0 ? std::sqrt(q * c) : 0.0;
  }
  return 0;
}

double QueryConstant(ScoringType type, const BowVector& query) {
  if (type != ScoringType::kKL) return 0;
  // KL as if the candidate had none of the query's words; shared words are corrected per term.
  double constant = 0;
  for (const BowEntry& entry : query) {
    const double q = entry.weight;
    if (q > 0) constant += q * (std::log(q) - kLogKlEpsilon);
  }
  return constant;
}

double FinalizeScore(ScoringType type, double accumulated, double query_constant) {
  switch (type) {
    case ScoringType::kL1:
      return -0.5 * accumulated;
    case ScoringType::kL2:
      // Rounding can push the dot product of unit vectors just above 1.
      if (accumulated >= 1) return 1.0;
      return 1.0 - std::sqrt(1.0 - accumulated);
    case ScoringType::kChiSquare:
      return 2.0 * accumulated;
    case ScoringType::kKL:
      return -(query_constant + accumulated);
    case ScoringType::kBhattacharyya:
    case ScoringType::kDotProduct:
      return accumulated;
  }
  return 0;
}

}  // namespace placedb
