// The frame pipeline and in-memory place database, on real images with the default vocabulary.
#include "core/pipeline/place_database.h"

#include <gtest/gtest.h>

#include <atomic>
#include <cstdio>
#include <map>
#include <opencv2/core.hpp>
#include <thread>

#include "core/vocabulary/vocabulary_learning.h"
#include "tests/test_support.h"

namespace placedb {
namespace {

using testing::DefaultVocabulary;
using testing::ReadGray;
using testing::RtabmapFramePath;

class PlaceDatabaseTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::HaveSharedData()) << "../shared/data is required";
    vocabulary_ = DefaultVocabulary();
    ASSERT_TRUE(vocabulary_);
  }

  std::unique_ptr<PlaceDatabase> MakeDatabase(DatabaseConfig config = {}) {
    auto db = PlaceDatabase::Create(vocabulary_, std::move(config));
    EXPECT_TRUE(db.ok()) << db.status().ToString();
    return db.ok() ? std::move(db).value() : nullptr;
  }

  static Observation Frame(int index, const std::string& agent = "robot-1") {
    Observation observation;
    observation.image = ReadGray(RtabmapFramePath(index));
    observation.metadata.agent_id = agent;
    observation.metadata.sequence = uint64_t(index);
    observation.metadata.timestamp_ns = int64_t(index) * 1'000'000'000;
    return observation;
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
};

TEST_F(PlaceDatabaseTest, CreateRejectsBadConfig) {
  DatabaseConfig bad_orb;
  bad_orb.orb.max_features = 0;
  auto result = PlaceDatabase::Create(vocabulary_, bad_orb);
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(result.status().message().find("max_features"), std::string::npos);

  DatabaseConfig bad_threshold;
  bad_threshold.filter.place_threshold = -1;
  EXPECT_FALSE(PlaceDatabase::Create(vocabulary_, bad_threshold).ok());

  EXPECT_EQ(PlaceDatabase::Create(AnyVocabulary(), {}).status().code(),
            StatusCode::kInvalidArgument);
}

// A map that switches vocabularies (issue 29) transforms a frame processed before the switch
// again: Retransform gives what processing the frame with the new vocabulary gives.
TEST_F(PlaceDatabaseTest, RetransformGivesWhatTheOtherVocabularyProcesses) {
  DatabaseConfig whole_boxes;
  whole_boxes.box_refinement.method = BoxRefinement::kNone;
  auto fixed = MakeDatabase(whole_boxes);
  LearningOptions options;
  options.min_descriptors = 1000;
  options.min_places = 5;
  options.depth = 4;
  VocabularyLearner learner(FeatureType::kOrb, options);
  for (int index = 1; index <= 12; ++index) {
    auto frame = fixed->Process(Frame(index));
    ASSERT_TRUE(frame.ok()) << frame.status().ToString();
    ASSERT_TRUE(learner.Offer(uint64_t(index), frame->static_features).ok());
  }
  auto learned = learner.Learn();
  ASSERT_TRUE(learned.ok()) << learned.status().ToString();
  auto created = PlaceDatabase::Create(learned->vocabulary, whole_boxes);
  ASSERT_TRUE(created.ok()) << created.status().ToString();
  PlaceDatabase& switched = **created;

  Observation observation = Frame(5);
  // A person box over the left half: DC words for the short-term tier too.
  observation.dynamic.boxes.push_back(
      {0, 0.9f, cv::Rect2f(0, 0, observation.image.cols / 2.0f, float(observation.image.rows))});
  auto before = fixed->Process(observation);
  auto expected = switched.Process(observation);
  ASSERT_TRUE(before.ok() && expected.ok());
  ASSERT_TRUE(before->valid);
  ASSERT_FALSE(before->dynamic_bow.empty());
  EXPECT_TRUE(fixed->OfThisVocabulary(*before));
  EXPECT_FALSE(switched.OfThisVocabulary(*before));
  EXPECT_NE(before->bow, expected->bow);

  ProcessedFrame frame = *before;
  ASSERT_TRUE(switched.Retransform(&frame).ok());
  EXPECT_TRUE(switched.OfThisVocabulary(frame));
  EXPECT_EQ(frame.vocabulary_checksum, learned->vocabulary.checksum());
  EXPECT_EQ(frame.bow, expected->bow);
  EXPECT_EQ(frame.direct, expected->direct);
  EXPECT_EQ(frame.dynamic_bow, expected->dynamic_bow);
  EXPECT_EQ(frame.dynamic_direct, expected->dynamic_direct);
  // Already of this vocabulary: nothing changes.
  ASSERT_TRUE(switched.Retransform(&frame).ok());
  EXPECT_EQ(frame.bow, expected->bow);

  // The retransformed frame is stored and found as the new vocabulary's own frames are.
  auto id = switched.Insert(frame, observation.metadata);
  ASSERT_TRUE(id.ok()) << id.status().ToString();
  auto found = switched.Query(observation, {});
  ASSERT_TRUE(found.ok());
  ASSERT_FALSE(found->matches.empty());
  EXPECT_EQ(found->matches.front().place, *id);
}

TEST_F(PlaceDatabaseTest, AddStoresStaticFeaturesAndReportsCounts) {
  auto db = MakeDatabase();
  auto added = db->Add(Frame(1));
  ASSERT_TRUE(added.ok()) << added.status().ToString();
  EXPECT_TRUE(added->stored);
  EXPECT_EQ(added->id, 1u);
  EXPECT_GT(added->counts.total, 100u);
  EXPECT_EQ(added->counts.dynamic, 0u);
  EXPECT_EQ(added->counts.static_, added->counts.total);
  EXPECT_GT(added->timings.extract_ms, 0);
  EXPECT_GT(added->timings.transform_ms, 0);

  auto record = db->Get(added->id);
  ASSERT_TRUE(record);
  EXPECT_EQ(record->metadata.agent_id, "robot-1");
  EXPECT_EQ(record->counts.static_, added->counts.static_);

  DatabaseStats stats = db->Stats();
  EXPECT_EQ(stats.places, 1u);
  EXPECT_EQ(stats.descriptors_kept, added->counts.static_);
  EXPECT_GT(stats.index_bytes, 0u);
}

TEST_F(PlaceDatabaseTest, DynamicDescriptorsAreDroppedNotStored) {
  // Whole boxes, as the paper filters (box refinement has its own tests).
  DatabaseConfig whole_boxes;
  whole_boxes.box_refinement.method = BoxRefinement::kNone;
  auto db = MakeDatabase(whole_boxes);
  Observation frame = Frame(5);
  // A person box over the left half of the image.
  frame.dynamic.boxes.push_back(
      {0, 0.9f, cv::Rect2f(0, 0, frame.image.cols / 2.0f, float(frame.image.rows))});
  auto added = db->Add(frame);
  ASSERT_TRUE(added.ok()) << added.status().ToString();
  ASSERT_TRUE(added->stored);
  EXPECT_GT(added->counts.dynamic, 0u);
  EXPECT_EQ(added->counts.dynamic + added->counts.static_, added->counts.total);
  EXPECT_NEAR(added->counts.dynamic_coverage, 0.5, 0.01);
  ASSERT_EQ(added->boxes_used.size(), 1u);
  // The database keeps exactly the SC features: check them through a payload store we hold.
  auto payloads = std::make_shared<InMemoryPayloadStore>();
  auto observed = PlaceDatabase::Create(vocabulary_, whole_boxes, payloads);
  ASSERT_TRUE(observed.ok());
  auto again = (*observed)->Add(frame);
  ASSERT_TRUE(again.ok() && again->stored);
  auto payload = payloads->Get(again->id);
  ASSERT_TRUE(payload.ok());
  EXPECT_EQ((*payload)->features.size(), added->counts.static_);
  EXPECT_GT(db->Stats().payload_bytes, 0u);
  for (const Keypoint& kp : (*payload)->features.keypoints()) {
    EXPECT_GE(kp.x, frame.image.cols / 2.0f) << "a keypoint inside the box was kept";
  }
  EXPECT_EQ(db->Stats().descriptors_dropped, added->counts.dynamic);
}

TEST_F(PlaceDatabaseTest, BoxesOfOtherClassesOrLowConfidenceAreIgnored) {
  DatabaseConfig config;
  config.dynamic_classes = {0};  // people only
  config.min_box_confidence = 0.5f;
  auto db = MakeDatabase(config);
  Observation frame = Frame(7);
  const cv::Rect2f everything(0, 0, float(frame.image.cols), float(frame.image.rows));
  frame.dynamic.boxes = {{2, 0.9f, everything},   // a car: not dynamic for this map
                         {0, 0.3f, everything}};  // a person below the confidence threshold
  auto added = db->Add(frame);
  ASSERT_TRUE(added.ok());
  EXPECT_TRUE(added->stored);
  EXPECT_EQ(added->counts.dynamic, 0u);
  EXPECT_TRUE(added->boxes_used.empty());
}

TEST_F(PlaceDatabaseTest, InvalidFrameIsNeitherStoredNorMatched) {
  auto db = MakeDatabase();
  ASSERT_TRUE(db->Add(Frame(1)).ok());
  Observation covered = Frame(1);
  covered.dynamic.boxes.push_back(
      {0, 1.0f, cv::Rect2f(0, 0, float(covered.image.cols), float(covered.image.rows))});
  auto added = db->Add(covered);
  ASSERT_TRUE(added.ok());
  EXPECT_FALSE(added->stored);
  EXPECT_EQ(added->counts.static_, 0u);
  EXPECT_NE(added->rejection.find("placeThreshold"), std::string::npos) << added->rejection;
  EXPECT_EQ(db->Stats().places, 1u);
  EXPECT_EQ(db->Stats().invalid_rejected, 1u);

  auto queried = db->Query(covered, {});
  ASSERT_TRUE(queried.ok());
  EXPECT_FALSE(queried->valid);
  EXPECT_TRUE(queried->matches.empty());
  EXPECT_EQ(queried->timings.search_ms, 0);
}

TEST_F(PlaceDatabaseTest, PlaceThresholdIsStrict) {
  auto db = MakeDatabase();
  auto processed = db->Process(Frame(3));
  ASSERT_TRUE(processed.ok());
  const int sc = int(processed->counts.static_);
  DatabaseConfig at_limit;
  at_limit.filter.place_threshold = sc;  // |SC| > threshold fails when equal
  auto strict = MakeDatabase(at_limit);
  EXPECT_FALSE(strict->Process(Frame(3))->valid);
  at_limit.filter.place_threshold = sc - 1;
  EXPECT_TRUE(MakeDatabase(at_limit)->Process(Frame(3))->valid);
}

TEST_F(PlaceDatabaseTest, QueryRanksTheSameViewFirst) {
  auto db = MakeDatabase();
  for (int i = 1; i <= 20; ++i) ASSERT_TRUE(db->Add(Frame(i)).ok());
  auto result = db->Query(Frame(12), {});
  ASSERT_TRUE(result.ok());
  ASSERT_TRUE(result->valid);
  ASSERT_EQ(result->matches.size(), 10u);
  EXPECT_EQ(result->matches[0].place, 12u);
  // Stored weights are quantised: an L1 self-match is within that bound of 1.
  EXPECT_NEAR(result->matches[0].score, 1.0, InvertedIndex::kWeightRelativeError + 1e-5);
  EXPECT_EQ(result->matches[0].metadata.sequence, 12u);
  for (size_t i = 1; i < result->matches.size(); ++i) {
    EXPECT_GE(result->matches[i - 1].score, result->matches[i].score);
  }
  EXPECT_GT(result->timings.search_ms, 0);
  EXPECT_GE(result->timings.total_ms, result->timings.search_ms);
}

TEST_F(PlaceDatabaseTest, PrecomputedFeaturesGiveTheSameResultAsTheImage) {
  auto db = MakeDatabase();
  for (int i = 1; i <= 10; ++i) ASSERT_TRUE(db->Add(Frame(i)).ok());
  Observation from_image = Frame(4);
  Observation precomputed;
  auto features = ExtractOrb(from_image.image, db->config().orb);
  ASSERT_TRUE(features.ok());
  precomputed.features = *features;
  auto a = db->Query(from_image, {});
  auto b = db->Query(precomputed, {});
  ASSERT_TRUE(a.ok() && b.ok());
  ASSERT_EQ(a->matches.size(), b->matches.size());
  for (size_t i = 0; i < a->matches.size(); ++i) {
    EXPECT_EQ(a->matches[i].place, b->matches[i].place);
    EXPECT_DOUBLE_EQ(a->matches[i].score, b->matches[i].score);
  }
  EXPECT_EQ(b->timings.extract_ms < a->timings.extract_ms, true);
}

TEST_F(PlaceDatabaseTest, BadPrecomputedInputIsRejectedAndChangesNothing) {
  auto db = MakeDatabase();
  ASSERT_TRUE(db->Add(Frame(1)).ok());
  const DatabaseStats before = db->Stats();

  Observation bad;
  FeatureSet outside = testing::ExtractFile(RtabmapFramePath(2));
  outside.keypoints[3].x = float(outside.image_width + 10);
  bad.features = std::move(outside);
  auto added = db->Add(bad);
  ASSERT_FALSE(added.ok());
  EXPECT_EQ(added.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(added.status().message().find("keypoints[3]"), std::string::npos);

  Observation mismatched;
  FeatureSet short_of_descriptors = testing::ExtractFile(RtabmapFramePath(2));
  short_of_descriptors.descriptors.pop_back();
  mismatched.features = std::move(short_of_descriptors);
  EXPECT_EQ(db->Add(mismatched).status().code(), StatusCode::kInvalidArgument);

  Observation wrong_mask = Frame(2);
  wrong_mask.dynamic.mask = cv::Mat::zeros(10, 10, CV_8U);
  EXPECT_EQ(db->Add(wrong_mask).status().code(), StatusCode::kInvalidArgument);

  Observation empty;
  EXPECT_EQ(db->Add(empty).status().code(), StatusCode::kInvalidArgument);

  const DatabaseStats after = db->Stats();
  EXPECT_EQ(after.places, before.places);
  EXPECT_EQ(after.descriptors_kept, before.descriptors_kept);
  EXPECT_EQ(after.index_bytes, before.index_bytes);
}

TEST_F(PlaceDatabaseTest, RemoveTakesThePlaceOutOfResults) {
  auto db = MakeDatabase();
  for (int i = 1; i <= 10; ++i) ASSERT_TRUE(db->Add(Frame(i)).ok());
  ASSERT_TRUE(db->Remove(6).ok());
  EXPECT_EQ(db->Remove(6).code(), StatusCode::kNotFound);
  EXPECT_EQ(db->Get(6), nullptr);
  auto result = db->Query(Frame(6), {});
  ASSERT_TRUE(result.ok());
  for (const Match& match : result->matches) EXPECT_NE(match.place, 6u);
  EXPECT_EQ(db->Stats().places, 9u);
  EXPECT_EQ(db->ListPlaces().size(), 9u);
  // Ids are never reused.
  auto again = db->Add(Frame(6));
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->id, 11u);
}

// The newest-first walk: filters, gaps, and the bound on ids examined per call.
TEST_F(PlaceDatabaseTest, ListPlacesBeforeWalksNewestFirstWithBoundedWork) {
  auto db = MakeDatabase();
  for (int i = 1; i <= 12; ++i) ASSERT_TRUE(db->Add(Frame(i, i <= 10 ? "a" : "b")).ok());
  ASSERT_TRUE(db->Remove(11).ok());
  const auto ids = [](const PlacePage& page) {
    std::vector<PlaceId> out;
    for (const auto& record : page.places) out.push_back(record->id);
    return out;
  };
  PlacePage page = db->ListPlacesBefore(0, 5, {}, 1000);
  EXPECT_EQ(ids(page), (std::vector<PlaceId>{12, 10, 9, 8, 7}));
  EXPECT_EQ(page.next_before, 7u);
  page = db->ListPlacesBefore(7, 100, {}, 1000);
  EXPECT_EQ(ids(page), (std::vector<PlaceId>{6, 5, 4, 3, 2, 1}));
  EXPECT_EQ(page.next_before, 0u);
  EXPECT_EQ(ids(db->ListPlacesBefore(99, 2, {}, 1000)), (std::vector<PlaceId>{12, 10}));

  // A filter that matches only the oldest place: each call examines at most 4 ids and says
  // where to go on, with an empty page, until the place turns up.
  const PlaceFilter oldest{
      .agent_id = "a", .from_timestamp_ns = 0, .to_timestamp_ns = 2'000'000'000};
  page = db->ListPlacesBefore(0, 10, oldest, 4);
  EXPECT_TRUE(page.places.empty());
  EXPECT_EQ(page.next_before, 9u);  // examined 12, 11, 10, 9
  page = db->ListPlacesBefore(page.next_before, 10, oldest, 4);
  EXPECT_TRUE(page.places.empty());
  EXPECT_EQ(page.next_before, 5u);
  page = db->ListPlacesBefore(page.next_before, 10, oldest, 4);
  EXPECT_EQ(ids(page), (std::vector<PlaceId>{1}));
  EXPECT_EQ(page.next_before, 0u);

  const PlaceFilter agent_b{.agent_id = "b", .from_timestamp_ns = 0, .to_timestamp_ns = 0};
  EXPECT_EQ(ids(db->ListPlacesBefore(0, 10, agent_b, 1000)), (std::vector<PlaceId>{12}));
  const PlaceFilter window{
      .agent_id = "", .from_timestamp_ns = 3'000'000'000, .to_timestamp_ns = 5'000'000'000};
  EXPECT_EQ(ids(db->ListPlacesBefore(0, 10, window, 1000)), (std::vector<PlaceId>{4, 3}));
}

TEST_F(PlaceDatabaseTest, InsertWithExplicitIdRestoresAndRefusesDuplicates) {
  auto db = MakeDatabase();
  auto frame = db->Process(Frame(2));
  ASSERT_TRUE(frame.ok());
  auto id = db->Insert(*frame, {}, PlaceId{42});
  ASSERT_TRUE(id.ok());
  EXPECT_EQ(*id, 42u);
  EXPECT_EQ(db->next_id(), 43u);
  EXPECT_EQ(db->Insert(*frame, {}, PlaceId{42}).status().code(), StatusCode::kAlreadyExists);
  EXPECT_EQ(db->Insert(*frame, {}, PlaceId{0}).status().code(), StatusCode::kInvalidArgument);
}

TEST_F(PlaceDatabaseTest, AcceptFilterExcludesCandidates) {
  auto db = MakeDatabase();
  for (int i = 1; i <= 10; ++i) ASSERT_TRUE(db->Add(Frame(i, i % 2 ? "odd" : "even")).ok());
  QueryOptions options;
  options.accept = [](const PlaceRecord& record) { return record.metadata.agent_id == "odd"; };
  auto result = db->Query(Frame(4), options);
  ASSERT_TRUE(result.ok());
  ASSERT_FALSE(result->matches.empty());
  for (const Match& match : result->matches) EXPECT_EQ(match.metadata.agent_id, "odd");
}

TEST_F(PlaceDatabaseTest, ExhaustiveVerificationConfirmsARealRevisit) {
  DatabaseConfig config;
  config.verification.mode = VerificationMode::kExhaustive;
  auto db = MakeDatabase(config);
  for (int i = 1; i <= 10; ++i) ASSERT_TRUE(db->Add(Frame(i)).ok());
  auto result = db->Query(Frame(3), {});
  ASSERT_TRUE(result.ok());
  ASSERT_FALSE(result->matches.empty());
  EXPECT_EQ(result->matches[0].place, 3u);
  EXPECT_TRUE(result->matches[0].verified);
  EXPECT_GE(result->matches[0].inliers, config.verification.min_inliers);
  EXPECT_GT(result->timings.verify_ms, 0);

  QueryOptions verified_only;
  verified_only.verified_only = true;
  auto strict = db->Query(Frame(3), verified_only);
  ASSERT_TRUE(strict.ok());
  for (const Match& match : strict->matches) EXPECT_TRUE(match.verified);
}

// Verification is off by default; asking for verified matches used to return none at all, with
// no reason (the SDK README's own `query(..., verify=True)`). Now they are verified on request.
TEST_F(PlaceDatabaseTest, VerifiedOnlyOnAMapThatDoesNotVerifyVerifiesOnRequest) {
  auto db = MakeDatabase();
  ASSERT_EQ(db->config().verification.mode, VerificationMode::kDisabled);
  for (int i = 1; i <= 10; ++i) ASSERT_TRUE(db->Add(Frame(i)).ok());
  auto plain = db->Query(Frame(3), {});
  ASSERT_TRUE(plain.ok());
  ASSERT_FALSE(plain->matches.empty());
  for (const Match& match : plain->matches) EXPECT_FALSE(match.verified);

  QueryOptions verified_only;
  verified_only.verified_only = true;
  auto strict = db->Query(Frame(3), verified_only);
  ASSERT_TRUE(strict.ok());
  ASSERT_FALSE(strict->matches.empty());
  EXPECT_EQ(strict->matches[0].place, 3u);
  for (const Match& match : strict->matches) {
    EXPECT_TRUE(match.verified);
    EXPECT_GE(match.inliers, db->config().verification.min_inliers);
  }
}

TEST_F(PlaceDatabaseTest, DirectIndexVerificationUsesTheConfiguredLevel) {
  DatabaseConfig config;
  config.verification.mode = VerificationMode::kDirectIndex;
  config.verification.levels_up = 3;
  auto db = MakeDatabase(config);
  for (int i = 1; i <= 5; ++i) ASSERT_TRUE(db->Add(Frame(i)).ok());
  EXPECT_EQ(db->Process(Frame(1))->direct.levels_up, 3);
  auto result = db->Query(Frame(2), {});
  ASSERT_TRUE(result.ok());
  ASSERT_FALSE(result->matches.empty());
  EXPECT_EQ(result->matches[0].place, 2u);
  EXPECT_TRUE(result->matches[0].verified) << result->matches[0].inliers << " inliers";
}

// Readers query while a writer adds and removes; run under ThreadSanitizer by tools/test.sh.
TEST_F(PlaceDatabaseTest, ConcurrentQueriesDuringAddAndRemove) {
  auto db = MakeDatabase();
  std::vector<ProcessedFrame> frames;
  for (int i = 1; frames.size() < 24; ++i) {
    auto frame = db->Process(Frame(i));
    ASSERT_TRUE(frame.ok());
    if (frame->valid) frames.push_back(*frame);  // a few corridor frames are too bare
  }
  for (int i = 0; i < 8; ++i) ASSERT_TRUE(db->Insert(frames[size_t(i)], {}).ok());

  std::atomic<bool> done{false};
  std::atomic<int> queries{0};
  std::atomic<int> failures{0};
  std::vector<std::thread> readers;
  for (int r = 0; r < 3; ++r) {
    readers.emplace_back([&, r] {
      size_t i = size_t(r);
      while (!done.load()) {
        QueryResult result = db->Search(frames[i % frames.size()], {});
        if (!result.valid) failures.fetch_add(1);
        for (const Match& match : result.matches) {
          if (match.place == 0) failures.fetch_add(1);
        }
        (void)db->Stats();
        queries.fetch_add(1);
        ++i;
      }
    });
  }
  std::thread writer([&] {
    // Writes start once a reader is searching, however the machine schedules the threads.
    while (queries.load() == 0) std::this_thread::yield();
    for (size_t i = 8; i < frames.size(); ++i) {
      auto id = db->Insert(frames[i], {});
      if (!id.ok()) failures.fetch_add(1);
      if (i % 3 == 0 && !db->Remove(PlaceId(i - 6)).ok()) failures.fetch_add(1);
    }
    done.store(true);
  });
  writer.join();
  for (auto& reader : readers) reader.join();
  EXPECT_EQ(failures.load(), 0);
  EXPECT_GT(queries.load(), 0);
  EXPECT_EQ(db->Stats().places, 24u - 5u);
}

// Three agents stream RGB-D frames with loop closure at once while a reader queries as one of
// them: per-agent state (Algorithm 1, the loop-closure detector and its long-term memory in the
// payload store) must stay per agent and race-free. Run under ThreadSanitizer by tools/test.sh.
TEST_F(PlaceDatabaseTest, ConcurrentAgentStreamsWithDepthAndLoopClosure) {
  DatabaseConfig config;
  config.loop_closure.short_term_memory = 2;
  config.loop_closure.max_working_memory = 3;  // forces transfers to and retrievals from LTM
  config.loop_closure.min_candidates = 2;
  auto db = MakeDatabase(config);
  constexpr int kFrames = 14;
  std::vector<Observation> frames;
  for (int i = 1; i <= kFrames; ++i) {
    Observation frame = Frame(i);
    // A flat wall at 2 m, then something at 0.7 m covering the left half (a deviation).
    cv::Mat depth(frame.image.rows, frame.image.cols, CV_16U, cv::Scalar(2000));
    if (i > 6) depth(cv::Rect(0, 0, depth.cols / 2, depth.rows)).setTo(700);
    frame.depth = DepthObservation{depth, {}, {}};
    frames.push_back(std::move(frame));
  }
  std::atomic<int> failures{0};
  std::atomic<bool> done{false};
  std::vector<std::thread> agents;
  std::vector<int> stored(3, 0), merged(3, 0), removing(3, 0);
  for (int a = 0; a < 3; ++a) {
    agents.emplace_back([&, a] {
      const std::string agent = "agent-" + std::to_string(a);
      for (int pass = 0; pass < 2; ++pass) {
        for (const Observation& source : frames) {
          Observation frame = source;
          frame.metadata.agent_id = agent;
          auto processed = db->Process(frame, FrameRole::kStream);
          if (!processed.ok() || !db->AdvanceStream(&*processed, agent).ok()) {
            failures.fetch_add(1);
            continue;
          }
          removing[size_t(a)] += processed->depth_state && processed->depth_state->removing;
          if (!processed->valid) continue;
          auto outcome = db->CloseLoop(*processed, frame.metadata);
          if (!outcome.ok()) {
            failures.fetch_add(1);
            continue;
          }
          (outcome->merged ? merged : stored)[size_t(a)] += 1;
        }
      }
    });
  }
  std::thread reader([&] {
    while (!done.load()) {
      auto result = db->Query(frames[3], QueryOptions{});
      if (!result.ok()) failures.fetch_add(1);
      (void)db->Stats();
      (void)db->LoopStats("agent-0");
    }
  });
  for (auto& agent : agents) agent.join();
  done.store(true);
  reader.join();
  EXPECT_EQ(failures.load(), 0);
  size_t total_stored = 0;
  for (int a = 0; a < 3; ++a) {
    total_stored += size_t(stored[size_t(a)]);
    // Each stream saw its own deviation: 8 frames at 0.7 m, removal from the 7th of them (the
    // second pass starts from a static level that already includes the first pass's frames).
    EXPECT_GT(removing[size_t(a)], 0) << "agent " << a;
    auto loop = db->LoopStats("agent-" + std::to_string(a));
    ASSERT_TRUE(loop.ok());
    EXPECT_EQ(loop->places, size_t(stored[size_t(a)]));
    EXPECT_GT(loop->transferred, 0u);
  }
  const DatabaseStats stats = db->Stats();
  EXPECT_EQ(stats.places, total_stored);
  EXPECT_EQ(stats.streams, 3u);
  EXPECT_GT(stats.loop_long_term, 0u);
  EXPECT_EQ(db->ResetStream("agent-1").code(), StatusCode::kOk);
  EXPECT_EQ(db->ResetStream("agent-1").code(), StatusCode::kNotFound);
}

}  // namespace
}  // namespace placedb

namespace placedb {
namespace {

class ShortTermTierTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto vocabulary = Vocabulary::Load(testing::DefaultVocabularyPath());
    ASSERT_TRUE(vocabulary.ok()) << vocabulary.status().ToString();
    vocabulary_ = *vocabulary;
  }

  // An RTAB-Map frame with a "car" over the middle of the view: neighbouring frames see the
  // same things there, as a revisit within seconds sees the same parked car.
  static Observation Frame(int index, int64_t timestamp_s, const std::string& agent = "robot") {
    Observation observation;
    observation.image = testing::ReadGray(testing::RtabmapFramePath(index));
    observation.metadata.agent_id = agent;
    observation.metadata.sequence = uint64_t(index);
    observation.metadata.timestamp_ns = timestamp_s * 1'000'000'000;
    const float w = float(observation.image.cols), h = float(observation.image.rows);
    observation.dynamic.boxes.push_back(
        {2, 0.9f, cv::Rect2f(w * 0.3f, h * 0.2f, w * 0.4f, h * 0.6f)});
    return observation;
  }

  std::unique_ptr<PlaceDatabase> Make(bool short_term, uint32_t max_places = 5000) {
    DatabaseConfig config;
    config.box_refinement.method = BoxRefinement::kNone;
    config.short_term.enabled = short_term;
    config.short_term.max_places = max_places;
    auto db = PlaceDatabase::Create(vocabulary_, config);
    EXPECT_TRUE(db.ok()) << db.status().ToString();
    return std::move(db).value();
  }

  static double ScoreOf(const QueryResult& result, PlaceId place) {
    for (const Match& match : result.matches) {
      if (match.place == place) return match.score;
    }
    return 0;
  }

  std::shared_ptr<const Vocabulary> vocabulary_;
};

TEST_F(ShortTermTierTest, RecentPlacesScoreTheirDynamicWordsOlderOnesDoNot) {
  auto with_tier = Make(true);
  auto without = Make(false);
  auto stored = with_tier->Add(Frame(10, 100));
  auto stored_plain = without->Add(Frame(10, 100));
  ASSERT_TRUE(stored.ok() && stored->stored && stored_plain.ok() && stored_plain->stored);
  ASSERT_GT(stored->counts.dynamic, 20u);
  EXPECT_EQ(with_tier->Stats().short_term_places, 1u);
  EXPECT_EQ(without->Stats().short_term_places, 0u);

  auto recent = with_tier->Query(Frame(11, 101), {});
  auto plain = without->Query(Frame(11, 101), {});
  ASSERT_TRUE(recent.ok() && plain.ok());
  const double sc_only = ScoreOf(*plain, stored_plain->id);
  ASSERT_GT(sc_only, 0);
  // Inside the horizon the objects both frames saw add to the score...
  EXPECT_GT(ScoreOf(*recent, stored->id), sc_only * 1.02);
  // ...beyond it (and with the clock far away either way) the place is scored on SC alone.
  auto later = with_tier->Query(Frame(11, 100 + 61), {});
  auto earlier = with_tier->Query(Frame(11, 100 - 61), {});
  ASSERT_TRUE(later.ok() && earlier.ok());
  EXPECT_DOUBLE_EQ(ScoreOf(*later, stored->id), sc_only);
  EXPECT_DOUBLE_EQ(ScoreOf(*earlier, stored->id), sc_only);
  // Nothing of the tier is stored: the durable counts are SC only.
  EXPECT_EQ(with_tier->Stats().descriptors_kept, without->Stats().descriptors_kept);
}

TEST_F(ShortTermTierTest, HorizonAndCapacityEvictAndRemovalForgets) {
  auto db = Make(true, /*max_places=*/2);
  auto a = db->Add(Frame(10, 100));
  auto b = db->Add(Frame(12, 130));
  ASSERT_TRUE(a.ok() && b.ok() && a->stored && b->stored);
  EXPECT_EQ(db->Stats().short_term_places, 2u);
  // Another agent's clock does not evict this agent's places; capacity does.
  auto c = db->Add(Frame(14, 5, "other"));
  ASSERT_TRUE(c.ok() && c->stored);
  EXPECT_EQ(db->Stats().short_term_places, 2u);
  // The agent's newest observation 70 s on: its places older than 60 s before it leave.
  auto d = db->Add(Frame(30, 200));
  ASSERT_TRUE(d.ok()) << d.status().ToString();
  ASSERT_TRUE(d->stored) << d->rejection << " static " << d->counts.static_ << " total "
                         << d->counts.total;
  const DatabaseStats stats = db->Stats();
  EXPECT_LE(stats.short_term_places, 2u);
  EXPECT_EQ(stats.places, 4u);
  ASSERT_TRUE(db->Remove(d->id).ok());
  EXPECT_LT(db->Stats().short_term_places, stats.short_term_places);
}

TEST(SpatialReRanking, VerifiedCandidatesComeFirstByInliers) {
  auto vocabulary = Vocabulary::Load(testing::DefaultVocabularyPath());
  ASSERT_TRUE(vocabulary.ok());
  for (bool rerank : {false, true}) {
    DatabaseConfig config;
    config.verification.mode = VerificationMode::kExhaustive;
    config.verification.rerank = rerank;
    auto db = PlaceDatabase::Create(*vocabulary, config);
    ASSERT_TRUE(db.ok());
    for (int i = 1; i <= 40; ++i) {
      Observation frame;
      frame.image = testing::ReadGray(testing::RtabmapFramePath(i));
      frame.metadata.sequence = uint64_t(i);
      ASSERT_TRUE((*db)->Add(frame).ok());
    }
    int reordered = 0;
    for (int q = 41; q <= 84; q += 3) {
      Observation query;
      query.image = testing::ReadGray(testing::RtabmapFramePath(q));
      QueryOptions options;
      options.top_k = 10;
      auto result = (*db)->Query(query, options);
      ASSERT_TRUE(result.ok());
      const auto& m = result->matches;
      for (size_t i = 1; i < m.size(); ++i) {
        if (rerank) {
          EXPECT_FALSE(!m[i - 1].verified && m[i].verified) << "query " << q;
          if (m[i - 1].verified && m[i].verified) {
            EXPECT_GE(m[i - 1].inliers, m[i].inliers);
          }
          if (!m[i - 1].verified && !m[i].verified) {
            EXPECT_GE(m[i - 1].score, m[i].score);
          }
          reordered += m[i - 1].score < m[i].score ? 1 : 0;
        } else {
          EXPECT_GE(m[i - 1].score, m[i].score) << "query " << q;
        }
      }
    }
    if (rerank) {
      EXPECT_GT(reordered, 0) << "re-ranking never changed the BoW order";
    }
  }
}

}  // namespace
}  // namespace placedb

namespace placedb {
namespace {

TEST(StaticFeatureBudget, FilteringKeepsTheWholeBudgetOfStaticFeatures) {
  auto vocabulary = Vocabulary::Load(testing::DefaultVocabularyPath());
  ASSERT_TRUE(vocabulary.ok());
  Observation frame;
  frame.image = testing::ReadGray(testing::RtabmapFramePath(20));
  const float w = float(frame.image.cols), h = float(frame.image.rows);
  frame.dynamic.boxes.push_back({0, 0.9f, cv::Rect2f(0, 0, w * 0.45f, h)});
  std::map<bool, ProcessedFrame> processed;
  for (bool budget : {false, true}) {
    DatabaseConfig config;
    config.orb.max_features = 500;
    config.box_refinement.method = BoxRefinement::kNone;
    config.static_feature_budget = budget;
    auto db = PlaceDatabase::Create(*vocabulary, config);
    ASSERT_TRUE(db.ok());
    auto result = (*db)->Process(frame);
    ASSERT_TRUE(result.ok()) << result.status().ToString();
    processed[budget] = std::move(result).value();
  }
  const FrameCounts& off = processed[false].counts;
  const FrameCounts& on = processed[true].counts;
  std::printf("[budget] static %u -> %u, dynamic %u -> %u (of 500)\n", off.static_, on.static_,
              off.dynamic, on.dynamic);
  EXPECT_GT(off.dynamic, 50u);
  EXPECT_LT(off.static_, 450u);
  // The budget spent on the static pixels gives back most of what the objects took (ORB finds
  // fewer corners than asked on this texture-poor half of a corridor).
  EXPECT_GT(on.static_, off.static_ + off.dynamic / 2);
  // The objects' features are the whole-frame extraction's (the short-term tier's words).
  EXPECT_EQ(on.dynamic, off.dynamic);
  EXPECT_FALSE(processed[true].dynamic_bow.empty());
  for (const Keypoint& kp : processed[true].static_features.keypoints()) {
    EXPECT_GE(kp.x + 0.5f, w * 0.45f) << "a static feature inside the box";
  }
}

}  // namespace
}  // namespace placedb
