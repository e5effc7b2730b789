// Vocabulary module: trainer, greedy descent, Transform, binary and DBoW2 text formats.
//
// Trains small vocabularies on ORB descriptors of Debian's sample images (real data, no mocks)
// and checks every result against a brute-force reference written here.
#include "core/vocabulary/vocabulary.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <numeric>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "core/vocabulary/vocabulary_trainer.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

using Images = std::vector<std::vector<Descriptor256>>;
using testing::ReadFileBytes;

// ORB descriptors of every Debian sample image (~100 images, ~80k descriptors), extracted once.
const Images& SampleImages() {
  static const Images images = [] {
    Images out;
    for (const std::string& path : testing::DebianSampleImages()) {
      FeatureSet features = testing::ExtractFile(path, 1000);
      if (!features.descriptors.empty()) out.push_back(std::move(features.descriptors));
    }
    return out;
  }();
  return images;
}

size_t DescriptorCount(const Images& images) {
  size_t total = 0;
  for (const auto& image : images) total += image.size();
  return total;
}

std::shared_ptr<const Vocabulary> Train(const Images& images, int k, int levels, uint64_t seed,
                                        int threads = 2,
                                        WeightingType weighting = WeightingType::kTfIdf) {
  TrainerConfig config;
  config.branching = k;
  config.depth = levels;
  config.seed = seed;
  config.threads = threads;
  config.weighting = weighting;
  auto trained = TrainVocabulary(images, config);
  EXPECT_TRUE(trained.ok()) << trained.status().ToString();
  return trained.ok() ? *trained : nullptr;
}

// The vocabulary most tests share: k=10, L=4 over all sample images.
std::shared_ptr<const Vocabulary> StandardVocabulary() {
  static const std::shared_ptr<const Vocabulary> vocabulary = Train(SampleImages(), 10, 4, 1);
  return vocabulary;
}

// Reference greedy descent: the path root .. leaf, ties to the lower node id.
std::vector<NodeId> BruteForcePath(const Vocabulary& v, const Descriptor256& d) {
  std::vector<NodeId> path = {0};
  NodeId node = 0;
  while (v.ChildCount(node) > 0) {
    NodeId best = v.FirstChild(node);
    int best_distance = 1 << 30;
    for (NodeId c = v.FirstChild(node); c < v.FirstChild(node) + v.ChildCount(node); ++c) {
      const int distance = HammingDistance(d, v.NodeDescriptor(c));
      if (distance < best_distance) {
        best_distance = distance;
        best = c;
      }
    }
    node = best;
    path.push_back(node);
  }
  return path;
}

// Reference Transform: DBoW2 weighting, not normalised, zero weights left out.
BowVector ExpectedBow(const Vocabulary& v, const std::vector<Descriptor256>& descriptors) {
  std::map<WordId, int> occurrences;
  for (const auto& d : descriptors) ++occurrences[v.NodeWord(BruteForcePath(v, d).back())];
  const double n = double(descriptors.size());
  BowVector bow;
  for (const auto& [word, count] : occurrences) {
    double weight = 0;
    switch (v.weighting()) {
      case WeightingType::kTfIdf:
        weight = count * double(v.WordWeight(word)) / n;
        break;
      case WeightingType::kTf:
        weight = count / n;
        break;
      case WeightingType::kIdf:
        weight = v.WordWeight(word);
        break;
      case WeightingType::kBinary:
        weight = 1;
        break;
    }
    if (weight > 0) bow.push_back({word, float(weight)});
  }
  return bow;
}

void ExpectBowNear(const BowVector& actual, const BowVector& expected) {
  ASSERT_EQ(actual.size(), expected.size());
  for (size_t i = 0; i < actual.size(); ++i) {
    ASSERT_EQ(actual[i].word, expected[i].word) << "entry " << i;
    EXPECT_NEAR(actual[i].weight, expected[i].weight, 1e-6 * std::abs(expected[i].weight))
        << "word " << actual[i].word;
  }
}

// A temporary directory removed when the test ends. (Not testing::MakeTempDir: its exit-time
// cleanup currently runs after its list of directories has been destroyed.)
class ScratchDir {
 public:
  ScratchDir() {
    std::string pattern = (std::filesystem::temp_directory_path() / "vocabulary-test-XXXXXX");
    if (::mkdtemp(pattern.data()) == nullptr) ADD_FAILURE() << "mkdtemp " << pattern;
    path_ = pattern;
  }
  ~ScratchDir() {
    std::error_code ignored;
    std::filesystem::remove_all(path_, ignored);
  }
  ScratchDir(const ScratchDir&) = delete;
  ScratchDir& operator=(const ScratchDir&) = delete;
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

void WriteBytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), std::streamsize(bytes.size()));
  ASSERT_TRUE(out.good()) << path;
}

void ExpectSameTree(const VocabularyTree& a, const VocabularyTree& b) {
  EXPECT_EQ(a.branching, b.branching);
  EXPECT_EQ(a.depth, b.depth);
  EXPECT_EQ(a.scoring, b.scoring);
  EXPECT_EQ(a.weighting, b.weighting);
  EXPECT_EQ(a.parent, b.parent);
  EXPECT_EQ(a.descriptor, b.descriptor);
  EXPECT_EQ(a.weight, b.weight);
  EXPECT_EQ(a.word_id, b.word_id);
}

Descriptor256 RandomDescriptor(std::mt19937_64& random) {
  Descriptor256 d;
  for (auto& word : d.words) word = random();
  return d;
}

// ---- training ------------------------------------------------------------------------------

TEST(VocabularyTrainerTest, SampleImagesAreAvailable) {
  ASSERT_GE(SampleImages().size(), 50u) << "install opencv-doc and darknet";
  EXPECT_GE(DescriptorCount(SampleImages()), 40000u);
}

TEST(VocabularyTrainerTest, SameSeedSameVocabularyWhateverTheThreadCount) {
  // The root (~80k descriptors) is split with chunked parallel passes, the level below with
  // one node per thread: both paths must be independent of the thread count.
  auto one = Train(SampleImages(), 10, 3, 7, 1);
  auto two = Train(SampleImages(), 10, 3, 7, 2);
  auto three = Train(SampleImages(), 10, 3, 7, 3);
  ASSERT_TRUE(one && two && three);
  EXPECT_EQ(one->checksum(), two->checksum());
  EXPECT_EQ(one->checksum(), three->checksum());
  ExpectSameTree(one->ToTree(), two->ToTree());

  auto other_seed = Train(SampleImages(), 10, 3, 8, 2);
  ASSERT_TRUE(other_seed);
  EXPECT_NE(one->checksum(), other_seed->checksum());
}

TEST(VocabularyTrainerTest, ShapeFollowsTheConfig) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  EXPECT_EQ(v->branching(), 10);
  EXPECT_EQ(v->depth(), 4);
  EXPECT_EQ(v->weighting(), WeightingType::kTfIdf);
  EXPECT_GT(v->word_count(), 5000u);
  EXPECT_LE(v->word_count(), 10000u);
  EXPECT_EQ(v->checksum_hex().size(), 16u);
  // Breadth-first with contiguous children; words numbered in breadth-first leaf order.
  uint32_t next_child = 1;
  WordId next_word = 0;
  for (NodeId node = 0; node < v->node_count(); ++node) {
    EXPECT_LE(v->ChildCount(node), 10u);
    if (v->ChildCount(node) == 0) {
      EXPECT_EQ(v->NodeWord(node), next_word++);
      EXPECT_EQ(v->NodeOfWord(v->NodeWord(node)), node);
    } else {
      EXPECT_EQ(v->FirstChild(node), next_child);
      EXPECT_EQ(v->NodeWord(node), Vocabulary::kNoWord);
      next_child += v->ChildCount(node);
    }
  }
  EXPECT_EQ(next_child, v->node_count());
  EXPECT_EQ(next_word, v->word_count());
}

TEST(VocabularyTrainerTest, WordWeightsAreIdfOverTrainingImages) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  const Images& images = SampleImages();
  std::vector<uint32_t> images_with_word(v->word_count(), 0);
  for (const auto& image : images) {
    std::vector<WordId> words;
    for (const auto& d : image) words.push_back(v->WordOf(d));
    std::sort(words.begin(), words.end());
    words.erase(std::unique(words.begin(), words.end()), words.end());
    for (WordId w : words) ++images_with_word[w];
  }
  const double n = double(images.size());
  for (WordId w = 0; w < v->word_count(); ++w) {
    const double expected = std::log(n / std::max(1u, images_with_word[w]));
    ASSERT_NEAR(v->WordWeight(w), expected, 1e-5) << "word " << w;
  }
}

TEST(VocabularyTrainerTest, FewDistinctDescriptorsGetOneChildEach) {
  std::mt19937_64 random(3);
  const Descriptor256 distinct[3] = {RandomDescriptor(random), RandomDescriptor(random),
                                     RandomDescriptor(random)};
  Images images(4);
  for (int copy = 0; copy < 100; ++copy) {
    for (int i = 0; i < 3; ++i) images[size_t(copy % 4)].push_back(distinct[i]);
  }
  auto v = Train(images, 5, 3, 1);
  ASSERT_TRUE(v);
  EXPECT_EQ(v->word_count(), 3u);
  EXPECT_EQ(v->node_count(), 4u);
  for (const auto& d : distinct) EXPECT_EQ(v->NodeDescriptor(v->NodeOfWord(v->WordOf(d))), d);
  // Every training image holds every word: idf 0, so TF-IDF vectors are empty (as in DBoW2).
  BowVector bow;
  v->Transform(images[0], &bow, nullptr, 0);
  EXPECT_TRUE(bow.empty());
}

TEST(VocabularyTrainerTest, IdenticalDescriptorsGiveOneWord) {
  std::mt19937_64 random(4);
  const Descriptor256 d = RandomDescriptor(random);
  Images images = {std::vector<Descriptor256>(50, d), std::vector<Descriptor256>(20, d)};
  auto v = Train(images, 2, 4, 1);
  ASSERT_TRUE(v);
  EXPECT_EQ(v->word_count(), 1u);
  EXPECT_EQ(v->node_count(), 2u);
  EXPECT_EQ(v->WordOf(d), 0u);
}

TEST(VocabularyTrainerTest, NearDuplicateClustersNeverBreakTheTree) {
  // Few base descriptors with a few flipped bits, heavily duplicated: k-means here meets
  // coinciding centres and emptied clusters. Whatever happens, the tree must stay valid.
  for (uint64_t seed = 1; seed <= 40; ++seed) {
    std::mt19937_64 random(seed);
    std::vector<Descriptor256> bases;
    for (int b = 0; b < 2 + int(seed % 5); ++b) bases.push_back(RandomDescriptor(random));
    Images images(3);
    for (int i = 0; i < 60; ++i) {
      Descriptor256 d = bases[random() % bases.size()];
      for (uint64_t flips = random() % 4; flips > 0; --flips) {
        d.words[random() % 4] ^= uint64_t{1} << (random() % 64);
      }
      images[size_t(i % 3)].push_back(d);
      if (i % 2 == 0) images[size_t((i + 1) % 3)].push_back(d);
    }
    const int k = 3 + int(seed % 6);
    auto v = Train(images, k, 3, seed, 2);
    ASSERT_TRUE(v) << "seed " << seed;
    for (NodeId node = 0; node < v->node_count(); ++node) {
      ASSERT_LE(v->ChildCount(node), uint32_t(k));
    }
    for (const auto& image : images) {
      for (const auto& d : image) ASSERT_LT(v->WordOf(d), v->word_count());
    }
  }
}

TEST(VocabularyTrainerTest, RejectsBadConfigs) {
  const Images images = {
      std::vector<Descriptor256>(SampleImages()[0].begin(), SampleImages()[0].begin() + 100)};
  auto expect_invalid = [&](TrainerConfig config, const char* field) {
    auto result = TrainVocabulary(images, config);
    ASSERT_FALSE(result.ok()) << field;
    EXPECT_EQ(result.status().code(), StatusCode::kInvalidArgument) << field;
    EXPECT_NE(result.status().message().find(field), std::string::npos)
        << result.status().message();
  };
  TrainerConfig config;
  config.branching = 1;
  expect_invalid(config, "branching");
  config.branching = 65;
  expect_invalid(config, "branching");
  config = {};
  config.depth = 0;
  expect_invalid(config, "depth");
  config.depth = 11;
  expect_invalid(config, "depth");
  config = {};
  config.threads = -1;
  expect_invalid(config, "threads");
  config = {};
  config.max_iterations = 0;
  expect_invalid(config, "max_iterations");
  config = {};
  config.weighting = static_cast<WeightingType>(9);
  expect_invalid(config, "weighting");
  config = {};
  config.scoring = static_cast<ScoringType>(-1);
  expect_invalid(config, "scoring");

  // Fewer descriptors than k, or none at all.
  const Images tiny = {std::vector<Descriptor256>(images[0].begin(), images[0].begin() + 3)};
  auto result = TrainVocabulary(tiny, TrainerConfig{});
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), StatusCode::kInvalidArgument);
  EXPECT_FALSE(TrainVocabulary(Images{}, TrainerConfig{}).ok());
}

TEST(VocabularyTrainerTest, ReportsProgressUpToOne) {
  std::vector<double> fractions;
  TrainerConfig config;
  config.branching = 6;
  config.depth = 2;
  auto result = TrainVocabulary(SampleImages(), config, [&](double fraction, const char* phase) {
    EXPECT_NE(phase, nullptr);
    fractions.push_back(fraction);
  });
  ASSERT_TRUE(result.ok()) << result.status().ToString();
  ASSERT_GE(fractions.size(), 2u);
  EXPECT_TRUE(std::is_sorted(fractions.begin(), fractions.end()));
  EXPECT_EQ(fractions.back(), 1.0);
}

// ---- descent and Transform -----------------------------------------------------------------

TEST(VocabularyTest, WordOfIsGreedyDescent) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  for (size_t i = 0; i < SampleImages().size(); i += 3) {
    for (const auto& d : SampleImages()[i]) {
      ASSERT_EQ(v->WordOf(d), v->NodeWord(BruteForcePath(*v, d).back()));
    }
  }
  std::mt19937_64 random(11);
  for (int i = 0; i < 2000; ++i) {
    const Descriptor256 d = RandomDescriptor(random);
    ASSERT_EQ(v->WordOf(d), v->NodeWord(BruteForcePath(*v, d).back()));
  }
}

TEST(VocabularyTest, TiesGoToTheLowerNodeId) {
  // Root with two identical children: every descriptor must land on the first one.
  std::mt19937_64 random(5);
  VocabularyTree tree;
  tree.branching = 2;
  tree.depth = 1;
  const Descriptor256 d = RandomDescriptor(random);
  tree.parent = {0, 0, 0};
  tree.descriptor = {Descriptor256{}, d, d};
  tree.weight = {0, 1, 1};
  tree.word_id = {-1, 1, 0};  // word ids need not follow node order
  auto v = Vocabulary::FromTree(tree);
  ASSERT_TRUE(v.ok()) << v.status().ToString();
  for (int i = 0; i < 100; ++i) EXPECT_EQ((*v)->WordOf(RandomDescriptor(random)), 1u);
  BowVector bow;
  std::vector<Descriptor256> descriptors = {RandomDescriptor(random)};
  (*v)->Transform(descriptors, &bow, nullptr, 0);
  ASSERT_EQ(bow.size(), 1u);
  EXPECT_EQ(bow[0].word, 1u);
}

TEST(VocabularyTest, TransformWeightsFollowDbow2ForEveryWeighting) {
  auto base = StandardVocabulary();
  ASSERT_TRUE(base);
  for (WeightingType weighting :
       {WeightingType::kTfIdf, WeightingType::kTf, WeightingType::kIdf, WeightingType::kBinary}) {
    SCOPED_TRACE(static_cast<int>(weighting));
    VocabularyTree tree = base->ToTree();
    tree.weighting = weighting;
    auto v = Vocabulary::FromTree(tree);
    ASSERT_TRUE(v.ok()) << v.status().ToString();
    // The weighting is part of the vocabulary's identity.
    if (weighting == WeightingType::kTfIdf) {
      EXPECT_EQ((*v)->checksum(), base->checksum());
    } else {
      EXPECT_NE((*v)->checksum(), base->checksum());
    }
    for (size_t i = 0; i < SampleImages().size(); i += 7) {
      const auto& descriptors = SampleImages()[i];
      BowVector bow;
      (*v)->Transform(descriptors, &bow, nullptr, 0);
      ExpectBowNear(bow, ExpectedBow(**v, descriptors));
      // Sorted, unique, positive: the BowVector contract.
      for (size_t e = 0; e < bow.size(); ++e) {
        EXPECT_GT(bow[e].weight, 0.0f);
        if (e > 0) {
          EXPECT_LT(bow[e - 1].word, bow[e].word);
        }
      }
      if (weighting == WeightingType::kTf) {
        // Term frequencies of all features: they sum to 1 without any normalisation.
        double sum = 0;
        for (const auto& entry : bow) sum += entry.weight;
        EXPECT_NEAR(sum, 1.0, 1e-5);
      }
    }
  }
}

TEST(VocabularyTest, DirectIndexGroupsFeaturesByAncestor) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  const auto& descriptors = SampleImages()[1];
  std::vector<std::vector<NodeId>> paths;
  for (const auto& d : descriptors) paths.push_back(BruteForcePath(*v, d));
  for (int levels_up : {0, 1, 2, 3, 4, 9, -1}) {
    SCOPED_TRACE(levels_up);
    DirectIndex direct;
    BowVector bow;
    v->Transform(descriptors, &bow, &direct, levels_up);
    EXPECT_EQ(direct.levels_up, std::max(levels_up, 0));
    // Reference: the ancestor at depth L - levels_up, or the leaf when it is shallower.
    const int target = std::max(0, v->depth() - std::max(levels_up, 0));
    std::map<NodeId, std::vector<uint32_t>> expected;
    for (size_t f = 0; f < paths.size(); ++f) {
      const auto& path = paths[f];
      expected[path[std::min(size_t(target), path.size() - 1)]].push_back(uint32_t(f));
    }
    ASSERT_EQ(direct.node_count(), expected.size());
    ASSERT_EQ(direct.offsets.size(), expected.size() + 1);
    EXPECT_EQ(direct.offsets.back(), descriptors.size());
    size_t i = 0;
    for (const auto& [node, features] : expected) {
      EXPECT_EQ(direct.node_ids[i], node);
      const auto actual = direct.features_of(i);
      EXPECT_EQ(std::vector<uint32_t>(actual.begin(), actual.end()), features);
      ++i;
    }
    if (levels_up >= v->depth()) {
      ASSERT_EQ(direct.node_ids, std::vector<NodeId>{0});  // exhaustive: everything at the root
    }
    if (levels_up <= 0) {
      // The words' own nodes.
      for (NodeId node : direct.node_ids) EXPECT_EQ(v->ChildCount(node), 0u);
    }
  }
}

TEST(VocabularyTest, EmptyInputGivesEmptyOutputs) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  BowVector bow = {{1, 1.0f}};
  DirectIndex direct;
  direct.node_ids = {3};
  v->Transform({}, &bow, &direct, 2);
  EXPECT_TRUE(bow.empty());
  EXPECT_TRUE(direct.node_ids.empty());
  EXPECT_TRUE(direct.feature_ids.empty());
  EXPECT_EQ(direct.levels_up, 2);
  v->Transform(SampleImages()[0], nullptr, nullptr, 0);  // nothing requested: no crash
}

TEST(VocabularyTest, ConcurrentTransformsAgree) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  std::vector<BowVector> expected(SampleImages().size());
  for (size_t i = 0; i < expected.size(); ++i)
    v->Transform(SampleImages()[i], &expected[i], nullptr, 0);
  std::vector<int> mismatches(2, 0);
  std::vector<std::thread> threads;
  for (int t = 0; t < 2; ++t) {
    threads.emplace_back([&, t] {
      BowVector bow;
      DirectIndex direct;
      for (size_t i = size_t(t); i < expected.size(); ++i) {
        v->Transform(SampleImages()[i], &bow, &direct, 1);
        if (bow != expected[i]) ++mismatches[size_t(t)];
      }
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(mismatches, std::vector<int>(2, 0));
}

// ---- FromTree ------------------------------------------------------------------------------

VocabularyTree SmallTree() {
  // root -> A (inner), B (leaf); A -> C, D (leaves).
  std::mt19937_64 random(9);
  VocabularyTree tree;
  tree.branching = 2;
  tree.depth = 2;
  tree.parent = {0, 0, 0, 1, 1};
  tree.descriptor.push_back(Descriptor256{});  // the root's is ignored (and not kept)
  for (int i = 1; i < 5; ++i) tree.descriptor.push_back(RandomDescriptor(random));
  tree.weight = {0, 0, 0.5f, 0.25f, 0.75f};
  tree.word_id = {-1, -1, 0, 1, 2};
  return tree;
}

TEST(VocabularyTest, FromTreeRejectsMalformedTrees) {
  ASSERT_TRUE(Vocabulary::FromTree(SmallTree()).ok());
  auto expect_invalid = [](const VocabularyTree& tree, const char* what) {
    auto result = Vocabulary::FromTree(tree);
    ASSERT_FALSE(result.ok()) << what;
    EXPECT_EQ(result.status().code(), StatusCode::kInvalidArgument) << what;
    EXPECT_FALSE(result.status().message().empty());
  };
  VocabularyTree tree = SmallTree();
  tree.parent[3] = 4;
  expect_invalid(tree, "parent after child");
  tree = SmallTree();
  tree.word_id[2] = -1;
  expect_invalid(tree, "leaf without word");
  tree = SmallTree();
  tree.word_id[1] = 3;
  expect_invalid(tree, "inner node with word");
  tree = SmallTree();
  tree.word_id[3] = 0;
  expect_invalid(tree, "duplicate word id");
  tree = SmallTree();
  tree.word_id[3] = 7;
  expect_invalid(tree, "word id out of range");
  tree = SmallTree();
  tree.branching = 1;
  expect_invalid(tree, "k = 1");
  tree = SmallTree();
  tree.depth = 1;
  expect_invalid(tree, "too deep");
  tree = SmallTree();
  tree.parent.push_back(0);  // a third child of the root
  tree.descriptor.push_back({});
  tree.weight.push_back(1);
  tree.word_id.push_back(3);
  expect_invalid(tree, "more than k children");
  tree = SmallTree();
  tree.weight.pop_back();
  expect_invalid(tree, "size mismatch");
  tree = SmallTree();
  tree.weight[4] = std::nanf("");
  expect_invalid(tree, "NaN weight");
  tree = SmallTree();
  tree.weighting = static_cast<WeightingType>(4);
  expect_invalid(tree, "weighting");
  expect_invalid(VocabularyTree{}, "empty");
}

TEST(VocabularyTest, FromTreeKeepsWordIdsAndToTreeRoundTrips) {
  // Nodes given depth-first: the layout becomes breadth-first but word ids stay.
  VocabularyTree tree = SmallTree();
  // Reorder to root, A, C, D, B (parents still first).
  VocabularyTree dfs = tree;
  const int order[5] = {0, 1, 3, 4, 2};
  const uint32_t new_id[5] = {0, 1, 4, 2, 3};
  for (int i = 0; i < 5; ++i) {
    dfs.parent[size_t(i)] = new_id[tree.parent[size_t(order[i])]];
    dfs.descriptor[size_t(i)] = tree.descriptor[size_t(order[i])];
    dfs.weight[size_t(i)] = tree.weight[size_t(order[i])];
    dfs.word_id[size_t(i)] = tree.word_id[size_t(order[i])];
  }
  auto a = Vocabulary::FromTree(tree);
  auto b = Vocabulary::FromTree(dfs);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ((*a)->checksum(), (*b)->checksum());
  ExpectSameTree((*a)->ToTree(), tree);
  auto again = Vocabulary::FromTree((*a)->ToTree());
  ASSERT_TRUE(again.ok());
  EXPECT_EQ((*again)->checksum(), (*a)->checksum());
}

// ---- binary format -------------------------------------------------------------------------

TEST(VocabularyIoTest, BinaryRoundTripIsExact) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  const ScratchDir scratch;
  const std::string& dir = scratch.path();
  const std::string path = dir + "/v.pdbv";
  ASSERT_TRUE(v->SaveBinary(path).ok());
  for (auto loaded : {Vocabulary::LoadBinary(path), Vocabulary::Load(path)}) {
    ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
    const Vocabulary& w = **loaded;
    EXPECT_EQ(w.checksum(), v->checksum());
    EXPECT_EQ(w.memory_bytes(), v->memory_bytes());
    ExpectSameTree(w.ToTree(), v->ToTree());
    for (size_t i = 0; i < SampleImages().size(); i += 5) {
      BowVector a, b;
      DirectIndex da, db;
      v->Transform(SampleImages()[i], &a, &da, 2);
      w.Transform(SampleImages()[i], &b, &db, 2);
      ASSERT_EQ(a, b);
      ASSERT_EQ(da, db);
    }
  }
  // Saving again over the same path replaces it atomically and leaves no temp files behind.
  ASSERT_TRUE(v->SaveBinary(path).ok());
  size_t files = 0;
  for ([[maybe_unused]] const auto& entry : std::filesystem::directory_iterator(dir)) ++files;
  EXPECT_EQ(files, 1u);
}

TEST(VocabularyIoTest, MissingFilesAreNotFound) {
  const ScratchDir scratch;
  const std::string path = scratch.path() + "/nothing.pdbv";
  EXPECT_EQ(Vocabulary::Load(path).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(Vocabulary::LoadBinary(path).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(Vocabulary::ImportDbow2Text(path).status().code(), StatusCode::kNotFound);
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  EXPECT_FALSE(v->SaveBinary("/nonexistent-dir/x.pdbv").ok());
}

// File layout, as written by vocabulary_io.cc (white box: lets the tests forge files with valid
// checksums whose contents are wrong).
constexpr size_t kHeaderBytes = 64;
constexpr size_t kChecksumOffset = 48;
constexpr size_t kHeaderChecksumOffset = 56;

void FixChecksums(std::string* file) {
  const uint64_t block = Checksum64(file->data() + kHeaderBytes, file->size() - kHeaderBytes);
  std::memcpy(file->data() + kChecksumOffset, &block, 8);
  const uint64_t header = Checksum64(file->data(), kHeaderChecksumOffset);
  std::memcpy(file->data() + kHeaderChecksumOffset, &header, 8);
}

TEST(VocabularyIoTest, DamagedBinaryFilesFailCleanly) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  const ScratchDir scratch;
  const std::string& dir = scratch.path();
  const std::string good_path = dir + "/good.pdbv";
  ASSERT_TRUE(v->SaveBinary(good_path).ok());
  const std::string good = ReadFileBytes(good_path);
  ASSERT_EQ(good.size(), kHeaderBytes + v->memory_bytes());
  const std::string path = dir + "/bad.pdbv";
  auto load = [&](const std::string& bytes) {
    WriteBytes(path, bytes);
    return Vocabulary::LoadBinary(path);
  };
  auto expect_fails = [&](const std::string& bytes, StatusCode code, const std::string& phrase) {
    auto result = load(bytes);
    ASSERT_FALSE(result.ok()) << phrase;
    EXPECT_EQ(result.status().code(), code) << result.status().ToString();
    EXPECT_NE(result.status().message().find(phrase), std::string::npos)
        << result.status().ToString();
    EXPECT_NE(result.status().message().find(path), std::string::npos);
  };

  // Truncations anywhere.
  for (size_t size : {size_t{0}, size_t{5}, size_t{8}, size_t{40}, size_t{63}, size_t{64},
                      size_t{65}, good.size() / 2, good.size() - 1}) {
    auto result = load(good.substr(0, size));
    ASSERT_FALSE(result.ok()) << size;
    EXPECT_TRUE(result.status().code() == StatusCode::kCorruption ||
                result.status().code() == StatusCode::kInvalidArgument)
        << result.status().ToString();
  }
  expect_fails(good.substr(0, good.size() - 1), StatusCode::kCorruption, "truncated");
  expect_fails(good + "x", StatusCode::kCorruption, "trailing");
  // Foreign files.
  expect_fails("\x89PNG\r\n\x1a\n and so on, not a vocabulary at all", StatusCode::kInvalidArgument,
               "magic");
  expect_fails(ReadFileBytes(testing::DebianSampleImages()[0]), StatusCode::kInvalidArgument,
               "magic");
  // Flipped bits in the block: checksum.
  {
    std::string bytes = good;
    bytes[kHeaderBytes + 1000] ^= 0x10;
    expect_fails(bytes, StatusCode::kCorruption, "checksum");
  }
  // Header damage.
  for (size_t offset = 8; offset < kHeaderBytes; ++offset) {
    std::string bytes = good;
    bytes[offset] ^= 0x40;
    auto result = load(bytes);
    ASSERT_FALSE(result.ok()) << "header byte " << offset;
  }
  // A newer format version, with a valid header checksum.
  {
    std::string bytes = good;
    bytes[8] = 2;
    FixChecksums(&bytes);
    expect_fails(bytes, StatusCode::kInvalidArgument, "version");
  }
  // Counts that disagree with the size, with valid checksums.
  {
    std::string bytes = good;
    uint32_t nodes;
    std::memcpy(&nodes, bytes.data() + 32, 4);
    nodes += 100;
    std::memcpy(bytes.data() + 32, &nodes, 4);
    FixChecksums(&bytes);
    expect_fails(bytes, StatusCode::kCorruption, "block size");
  }
  // Scoring changed in the header only: the block's own parameter record disagrees.
  {
    std::string bytes = good;
    bytes[24] = 3;
    FixChecksums(&bytes);
    expect_fails(bytes, StatusCode::kCorruption, "parameter");
  }
  // Structure broken behind valid checksums.
  const size_t n = v->node_count();
  auto align = [](size_t x) { return (x + 63) / 64 * 64; };
  const size_t first_child = kHeaderBytes + align(64 + n * 32);
  const size_t child_count = first_child + align(n * 4);
  const size_t node_word = child_count + align(n * 4);
  {
    std::string bytes = good;
    const uint32_t too_many = 11;
    std::memcpy(bytes.data() + child_count, &too_many, 4);  // root
    FixChecksums(&bytes);
    expect_fails(bytes, StatusCode::kCorruption, "node 0");
  }
  {
    std::string bytes = good;
    NodeId inner = 1;
    while (v->ChildCount(inner) == 0) ++inner;
    const uint32_t out_of_range = 0x7FFFFFFF;
    std::memcpy(bytes.data() + first_child + 4 * inner, &out_of_range, 4);
    FixChecksums(&bytes);
    expect_fails(bytes, StatusCode::kCorruption, "node " + std::to_string(inner) + " ");
  }
  {
    std::string bytes = good;
    const NodeId leaf = v->NodeOfWord(0);
    const uint32_t bad_word = v->word_count();
    std::memcpy(bytes.data() + node_word + 4 * leaf, &bad_word, 4);
    FixChecksums(&bytes);
    expect_fails(bytes, StatusCode::kCorruption, "word");
  }
  // Random damage behind valid checksums in the index arrays: never a crash, and whatever
  // loads must still transform safely (ASan watches).
  std::mt19937_64 random(21);
  for (int trial = 0; trial < 150; ++trial) {
    std::string bytes = good;
    const size_t at = first_child + random() % (bytes.size() - first_child);
    bytes[at] = char(random());
    if (trial % 3 == 0) bytes[at + 1 < bytes.size() ? at + 1 : at] = char(0xFF);
    FixChecksums(&bytes);
    auto result = load(bytes);
    if (result.ok()) {
      BowVector bow;
      DirectIndex direct;
      (*result)->Transform(SampleImages()[0], &bow, &direct, 1);
    } else {
      EXPECT_EQ(result.status().code(), StatusCode::kCorruption) << result.status().ToString();
    }
  }
}

// ---- DBoW2 text ----------------------------------------------------------------------------

TEST(VocabularyIoTest, Dbow2TextRoundTripIsExact) {
  auto v = StandardVocabulary();
  ASSERT_TRUE(v);
  const ScratchDir scratch;
  const std::string& dir = scratch.path();
  ASSERT_TRUE(v->ExportDbow2Text(dir + "/a.txt").ok());
  auto imported = Vocabulary::ImportDbow2Text(dir + "/a.txt");
  ASSERT_TRUE(imported.ok()) << imported.status().ToString();
  EXPECT_EQ((*imported)->checksum(), v->checksum());
  ExpectSameTree((*imported)->ToTree(), v->ToTree());
  for (size_t i = 0; i < SampleImages().size(); i += 5) {
    BowVector a, b;
    DirectIndex da, db;
    v->Transform(SampleImages()[i], &a, &da, 1);
    (*imported)->Transform(SampleImages()[i], &b, &db, 1);
    ASSERT_EQ(a, b);
    ASSERT_EQ(da, db);
  }
  // Export of the import is byte-identical; Load() sniffs the text format.
  ASSERT_TRUE((*imported)->ExportDbow2Text(dir + "/b.txt").ok());
  EXPECT_EQ(ReadFileBytes(dir + "/a.txt"), ReadFileBytes(dir + "/b.txt"));
  auto sniffed = Vocabulary::Load(dir + "/b.txt");
  ASSERT_TRUE(sniffed.ok()) << sniffed.status().ToString();
  EXPECT_EQ((*sniffed)->checksum(), v->checksum());

  // The format itself: "k L scoring weighting", then parent, leaf flag, 32 bytes, weight.
  std::istringstream text(ReadFileBytes(dir + "/a.txt"));
  std::string line;
  std::getline(text, line);
  EXPECT_EQ(line, "10 4 0 0");
  std::getline(text, line);
  std::istringstream fields(line);
  std::vector<std::string> tokens;
  for (std::string token; fields >> token;) tokens.push_back(token);
  ASSERT_EQ(tokens.size(), 35u);
  EXPECT_EQ(tokens[0], "0");
  EXPECT_EQ(tokens[1], "0");
}

std::string DescriptorText(int seed) {
  std::string text;
  for (int b = 0; b < 32; ++b) text += std::to_string((seed * 37 + b * 11) % 256) + " ";
  return text;
}

// SmallTree() in DBoW2 text: root -> 1 (inner), 2 (leaf); 1 -> 3, 4 (leaves).
std::string SmallText(const std::string& eol = "\n") {
  return "2 2 0 0" + eol + "0 0 " + DescriptorText(1) + "0" + eol + "0 1 " + DescriptorText(2) +
         "0.5" + eol + "1 1 " + DescriptorText(3) + "0.25" + eol + "1 1 " + DescriptorText(4) +
         "1e-05" + eol;
}

TEST(VocabularyIoTest, Dbow2TextToleratesCrlfAndTrailingBlankLines) {
  const ScratchDir scratch;
  const std::string& dir = scratch.path();
  WriteBytes(dir + "/unix.txt", SmallText());
  WriteBytes(dir + "/dos.txt", SmallText("\r\n") + "\r\n\n  \n");
  auto unix_text = Vocabulary::ImportDbow2Text(dir + "/unix.txt");
  auto dos_text = Vocabulary::Load(dir + "/dos.txt");
  ASSERT_TRUE(unix_text.ok()) << unix_text.status().ToString();
  ASSERT_TRUE(dos_text.ok()) << dos_text.status().ToString();
  EXPECT_EQ((*unix_text)->checksum(), (*dos_text)->checksum());
  const Vocabulary& v = **unix_text;
  EXPECT_EQ(v.branching(), 2);
  EXPECT_EQ(v.depth(), 2);
  EXPECT_EQ(v.node_count(), 5u);
  EXPECT_EQ(v.word_count(), 3u);
  EXPECT_FLOAT_EQ(v.WordWeight(0), 0.5f);
  EXPECT_FLOAT_EQ(v.WordWeight(1), 0.25f);
  EXPECT_FLOAT_EQ(v.WordWeight(2), 1e-5f);
  EXPECT_EQ(v.NodeOfWord(0), 2u);
}

TEST(VocabularyIoTest, Dbow2TextKeepsFileWordNumbering) {
  // Depth-first file: words are numbered in line order (as DBoW2 does), not breadth-first.
  const std::string text = "2 2 0 0\n0 0 " + DescriptorText(1) + "0\n1 1 " + DescriptorText(3) +
                           "0.25\n1 1 " + DescriptorText(4) + "0.75\n0 1 " + DescriptorText(2) +
                           "0.5\n";
  const ScratchDir scratch;
  const std::string& dir = scratch.path();
  WriteBytes(dir + "/dfs.txt", text);
  auto v = Vocabulary::ImportDbow2Text(dir + "/dfs.txt");
  ASSERT_TRUE(v.ok()) << v.status().ToString();
  // Line 5 (node 4) is the root's leaf child: word 2, breadth-first node 2.
  EXPECT_EQ((*v)->NodeWord(2), 2u);
  EXPECT_FLOAT_EQ((*v)->WordWeight(2), 0.5f);
  EXPECT_EQ((*v)->NodeWord(3), 0u);
  // Exported back in DBoW2's own line order: the same file, byte for byte, and the same
  // vocabulary when imported again.
  const Status exported = (*v)->ExportDbow2Text(dir + "/out.txt");
  ASSERT_TRUE(exported.ok()) << exported.ToString();
  EXPECT_EQ(ReadFileBytes(dir + "/out.txt"), text);
  auto again = Vocabulary::ImportDbow2Text(dir + "/out.txt");
  ASSERT_TRUE(again.ok()) << again.status().ToString();
  EXPECT_EQ((*again)->checksum(), (*v)->checksum());
  // The binary format keeps it.
  ASSERT_TRUE((*v)->SaveBinary(dir + "/dfs.pdbv").ok());
  auto loaded = Vocabulary::LoadBinary(dir + "/dfs.pdbv");
  ASSERT_TRUE(loaded.ok());
  EXPECT_EQ((*loaded)->NodeWord(2), 2u);
}

// Word ids that no leaf-line order can express (two sibling leaves numbered against their
// order) are kept by the binary format and refused by the text export, which would renumber them.
TEST(VocabularyIoTest, Dbow2TextExportRefusesANumberingItCannotExpress) {
  VocabularyTree tree = SmallTree();
  tree.word_id = {-1, -1, 0, 2, 1};  // C and D, siblings in that order, numbered 2 and 1
  auto v = Vocabulary::FromTree(tree);
  ASSERT_TRUE(v.ok()) << v.status().ToString();
  const ScratchDir scratch;
  const Status exported = (*v)->ExportDbow2Text(scratch.path() + "/out.txt");
  EXPECT_EQ(exported.code(), StatusCode::kFailedPrecondition) << exported.ToString();
  EXPECT_NE(exported.message().find("save it as binary"), std::string::npos);
  EXPECT_FALSE(std::filesystem::exists(scratch.path() + "/out.txt"));
  // The breadth-first numbering of the same tree exports and round trips.
  auto standard = Vocabulary::FromTree(SmallTree());
  ASSERT_TRUE(standard.ok());
  ASSERT_TRUE((*standard)->ExportDbow2Text(scratch.path() + "/bfs.txt").ok());
  auto imported = Vocabulary::ImportDbow2Text(scratch.path() + "/bfs.txt");
  ASSERT_TRUE(imported.ok()) << imported.status().ToString();
  EXPECT_EQ((*imported)->checksum(), (*standard)->checksum());
}

TEST(VocabularyIoTest, MalformedDbow2TextNamesTheLine) {
  const ScratchDir scratch;
  const std::string& dir = scratch.path();
  const std::string good = SmallText();
  std::vector<std::string> lines;
  {
    std::istringstream in(good);
    for (std::string line; std::getline(in, line);) lines.push_back(line);
  }
  auto join = [](const std::vector<std::string>& parts) {
    std::string text;
    for (const auto& part : parts) text += part + "\n";
    return text;
  };
  auto expect_error = [&](const std::string& text, const std::string& where,
                          const std::string& what) {
    WriteBytes(dir + "/bad.txt", text);
    auto result = Vocabulary::ImportDbow2Text(dir + "/bad.txt");
    ASSERT_FALSE(result.ok()) << where << " " << what;
    EXPECT_EQ(result.status().code(), StatusCode::kCorruption) << result.status().ToString();
    EXPECT_NE(result.status().message().find(where), std::string::npos)
        << result.status().ToString();
    EXPECT_NE(result.status().message().find(what), std::string::npos)
        << result.status().ToString();
  };
  auto with_line = [&](size_t index, const std::string& replacement) {
    auto copy = lines;
    copy[index] = replacement;
    return join(copy);
  };
  expect_error("", "empty", "empty");
  expect_error(with_line(0, "2 2 0"), "line 1", "weighting");
  expect_error(with_line(0, "2 2 0 9"), "line 1", "weighting");
  expect_error(with_line(0, "1 2 0 0"), "line 1", "k must");
  expect_error(with_line(0, "x 2 0 0"), "line 1", "bad k");
  expect_error(with_line(2, "0 1 " + DescriptorText(2)), "line 3", "missing weight");
  expect_error(with_line(2, "0 1 1 2 3 0.5"), "line 3", "descriptor byte");
  expect_error(with_line(3, "1 1 256 " + DescriptorText(3).substr(2) + "0.25"), "line 4",
               "descriptor byte");
  expect_error(with_line(3, "1 1 " + DescriptorText(3) + "0.25 7"), "line 4", "extra");
  expect_error(with_line(3, "1 1 " + DescriptorText(3) + "abc"), "line 4", "weight");
  expect_error(with_line(3, "1 1 " + DescriptorText(3) + "nan"), "line 4", "weight");
  expect_error(with_line(3, "1 2 " + DescriptorText(3) + "0.25"), "line 4", "leaf flag");
  expect_error(with_line(3, "-1 1 " + DescriptorText(3) + "0.25"), "line 4", "parent");
  expect_error(with_line(3, "5 1 " + DescriptorText(3) + "0.25"), "line 4", "parent 5");
  expect_error(with_line(3, "2 1 " + DescriptorText(3) + "0.25"), "line 4", "is a leaf");
  expect_error(with_line(3, "0 1 " + DescriptorText(3) + "0.25"), "line 4", "more than k");
  expect_error(with_line(2, ""), "line 3", "empty line");
  // Node 1 declared inner but given no children.
  expect_error(join({lines[0], lines[1], lines[2]}), "line 2", "no children");
  // Too deep: L = 1 but node 3 hangs below node 1.
  expect_error(with_line(0, "2 1 0 0"), "line 4", "deeper");
  // Binary junk.
  expect_error(std::string("10 6 0 0\n\0\0\0", 12), "NUL", "NUL");
}

// ---- checksum ------------------------------------------------------------------------------

TEST(Checksum64Test, SensitiveToEveryBitLengthAndSeed) {
  std::mt19937_64 random(1);
  std::vector<uint8_t> data(1000);
  for (auto& byte : data) byte = uint8_t(random());
  const uint64_t base = Checksum64(data.data(), data.size());
  EXPECT_EQ(base, Checksum64(data.data(), data.size()));
  EXPECT_NE(base, Checksum64(data.data(), data.size(), 1));
  EXPECT_NE(base, Checksum64(data.data(), data.size() - 1));
  std::vector<uint8_t> padded = data;
  padded.push_back(0);
  EXPECT_NE(base, Checksum64(padded.data(), padded.size()));
  for (size_t bit = 0; bit < data.size() * 8; bit += 7) {
    data[bit / 8] ^= uint8_t(1u << (bit % 8));
    ASSERT_NE(base, Checksum64(data.data(), data.size())) << bit;
    data[bit / 8] ^= uint8_t(1u << (bit % 8));
  }
  EXPECT_NE(Checksum64(nullptr, 0), Checksum64(nullptr, 0, 1));
}

// ---- the default vocabulary ----------------------------------------------------------------

TEST(DefaultVocabularyTest, LoadsWithTheExpectedShape) {
  auto v = testing::DefaultVocabulary();
  ASSERT_TRUE(v);
  EXPECT_EQ(v->branching(), 10);
  EXPECT_EQ(v->depth(), 6);
  EXPECT_EQ(v->weighting(), WeightingType::kTfIdf);
  EXPECT_GT(v->word_count(), 100000u);
  BowVector bow;
  v->Transform(SampleImages()[0], &bow, nullptr, 0);
  EXPECT_GT(bow.size(), SampleImages()[0].size() / 2);
}

}  // namespace
}  // namespace placedb
