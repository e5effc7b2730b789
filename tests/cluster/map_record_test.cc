// The record codec of cluster mode (server/cluster/map_record.h): every record kind round-trips
// with real frames, and damaged bytes are CORRUPTION, never a crash or a half record.
#include "server/cluster/map_record.h"

#include <gtest/gtest.h>

#include "core/storage/codec.h"
#include "proto/cluster.pb.h"
#include "tests/rtabmap_frames.h"
#include "tests/test_support.h"

namespace placedb::cluster {
namespace {

class MapRecordTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(placedb::testing::HaveSharedData()) << "../shared/data is required";
    auto db = PlaceDatabase::Create(placedb::testing::DefaultVocabulary(), DatabaseConfig());
    ASSERT_TRUE(db.ok());
    db_ = std::move(db).value();
    frames_ = placedb::testing::ProcessRtabmapFrames(*db_, 2);
    ASSERT_EQ(frames_.size(), 2u);
    metadata_.agent_id = "robot-1";
    metadata_.sequence = 17;
    metadata_.timestamp_ns = 123456789;
    metadata_.pose = Pose{{1.0, 2.0, 3.0}, {0, 0, 0, 1}};
  }
  std::unique_ptr<PlaceDatabase> db_;
  std::vector<ProcessedFrame> frames_;
  PlaceMetadata metadata_;
};

TEST_F(MapRecordTest, EveryKindRoundTrips) {
  ProcessedFrame frame = frames_[0];
  frame.counts.dynamic_coverage = 0.25;
  frame.boxes_used.push_back(DynamicBox{});
  const std::string add = EncodeAddPlace(frame, metadata_, 42);
  auto decoded = DecodeMapRecord(add, FeatureType::kOrb);
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->kind, MapLogRecord::Kind::kAddPlace);
  EXPECT_TRUE(decoded->frame.valid);
  EXPECT_EQ(decoded->metadata, metadata_);
  EXPECT_EQ(decoded->frame.bow, frame.bow);
  EXPECT_EQ(EncodeLocalFeatures(decoded->frame.static_features, decoded->frame.direct),
            EncodeLocalFeatures(frame.static_features, frame.direct));
  EXPECT_EQ(decoded->frame.counts.static_, frame.counts.static_);
  EXPECT_EQ(decoded->frame.boxes_used.size(), 1u);
  ASSERT_TRUE(decoded->dynamics.has_value());
  EXPECT_EQ(*decoded->dynamics,
            MakeObservation(0.25, frame.boxes_used, metadata_.timestamp_ns, 42));
  // The same inputs make the same bytes (every replica stores the publisher's operand).
  EXPECT_EQ(EncodeAddPlace(frame, metadata_, 42), add);

  auto removal = DecodeMapRecord(EncodeDeletePlace(9), FeatureType::kOrb);
  ASSERT_TRUE(removal.ok());
  EXPECT_EQ(removal->kind, MapLogRecord::Kind::kDeletePlace);
  EXPECT_EQ(removal->place, 9u);

  auto count = DecodeMapRecord(EncodeCountObservation(5, frame, metadata_, 43), FeatureType::kOrb);
  ASSERT_TRUE(count.ok());
  EXPECT_EQ(count->kind, MapLogRecord::Kind::kCountObservation);
  EXPECT_EQ(count->place, 5u);
  EXPECT_EQ(*count->dynamics, MakeObservation(0.25, frame.boxes_used, metadata_.timestamp_ns, 43));

  ProcessedFrame invalid;
  invalid.rejection = "too few features";
  invalid.counts.static_ = 3;
  invalid.counts.total = 3;  // the codec checks the counts add up
  auto refused = DecodeMapRecord(EncodeInvalidFrame(invalid, metadata_, 44), FeatureType::kOrb);
  ASSERT_TRUE(refused.ok()) << refused.status().ToString();
  EXPECT_EQ(refused->kind, MapLogRecord::Kind::kInvalidFrame);
  EXPECT_FALSE(refused->frame.valid);
  EXPECT_EQ(refused->frame.rejection, "too few features");
  EXPECT_EQ(refused->frame.counts.static_, 3u);
  EXPECT_EQ(refused->metadata, metadata_);

  // The search request's frame.
  v1::SearchRequest request;
  FrameToSearchRequest(frames_[1], &request);
  ProcessedFrame back;
  ASSERT_TRUE(FrameFromSearchRequest(request, FeatureType::kOrb, &back).ok());
  EXPECT_EQ(back.bow, frames_[1].bow);
  EXPECT_EQ(back.direct.levels_up, frames_[1].direct.levels_up);
  // Both carry the vocabulary that made the vectors (issue 29).
  EXPECT_NE(frames_[1].vocabulary_checksum, 0u);
  EXPECT_EQ(back.vocabulary_checksum, frames_[1].vocabulary_checksum);
  EXPECT_EQ(decoded->frame.vocabulary_checksum, frame.vocabulary_checksum);
}

TEST_F(MapRecordTest, AVocabularyTravelsInPartsThenOneSwitch) {
  const AnyVocabulary vocabulary(placedb::testing::DefaultVocabulary());
  const std::string bytes = vocabulary.Serialize();
  const size_t part_bytes = bytes.size() / 4 + 1;  // 4 parts
  const std::vector<std::string> parts = EncodeVocabularyParts(vocabulary, part_bytes);
  ASSERT_EQ(parts.size(), 4u);
  std::string joined;
  for (size_t i = 0; i < parts.size(); ++i) {
    EXPECT_LT(parts[i].size(), part_bytes + 64) << i;
    auto decoded = DecodeMapRecord(parts[i], FeatureType::kOrb);
    ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
    EXPECT_EQ(decoded->kind, MapLogRecord::Kind::kVocabularyPart);
    EXPECT_EQ(decoded->vocabulary_part.checksum, vocabulary.checksum());
    EXPECT_EQ(decoded->vocabulary_part.index, i);
    EXPECT_EQ(decoded->vocabulary_part.count, 4u);
    joined += decoded->vocabulary_part.bytes;
  }
  EXPECT_EQ(joined, bytes);

  VocabularySource source;
  source.origin = "learned";
  source.checksum = vocabulary.checksum();
  source.branching = 10;
  source.depth = 6;
  source.words = 1000;
  source.learned_unix_ms = 1764320000000;
  source.places_offered = 30;
  source.descriptors_sampled = 25000;
  source.learn_ms = 812.5;
  auto change = DecodeMapRecord(EncodeSwitchVocabulary(source, 4), FeatureType::kOrb);
  ASSERT_TRUE(change.ok()) << change.status().ToString();
  EXPECT_EQ(change->kind, MapLogRecord::Kind::kSwitchVocabulary);
  EXPECT_EQ(change->vocabulary_source, source);
  EXPECT_EQ(change->vocabulary_parts, 4u);

  // Damaged: a part beyond its count, a checksum that is not 16 hex digits.
  v1::MapRecord record;
  ASSERT_TRUE(record.ParseFromString(parts[1]));
  record.mutable_vocabulary_part()->set_index(4);
  EXPECT_EQ(DecodeMapRecord(record.SerializeAsString(), FeatureType::kOrb).status().code(),
            StatusCode::kCorruption);
  ASSERT_TRUE(record.ParseFromString(EncodeSwitchVocabulary(source, 4)));
  record.mutable_switch_vocabulary()->mutable_source()->set_checksum("xyz");
  auto bad = DecodeMapRecord(record.SerializeAsString(), FeatureType::kOrb);
  EXPECT_EQ(bad.status().code(), StatusCode::kCorruption);
  EXPECT_NE(bad.status().message().find("switch_vocabulary.source.checksum"), std::string::npos)
      << bad.status().ToString();
}

TEST_F(MapRecordTest, DamagedBytesAreCorruption) {
  const std::string add = EncodeAddPlace(frames_[0], metadata_, 42);
  // Every truncation: CORRUPTION (a shorter valid protobuf has a damaged payload or no kind).
  for (size_t size = 0; size < add.size(); size += std::max<size_t>(1, add.size() / 300)) {
    auto decoded = DecodeMapRecord(std::string_view(add).substr(0, size), FeatureType::kOrb);
    EXPECT_FALSE(decoded.ok()) << "truncated to " << size;
    if (!decoded.ok()) {
      EXPECT_EQ(decoded.status().code(), StatusCode::kCorruption) << size;
    }
  }
  // A payload of another family, or a damaged payload inside a well-formed message.
  EXPECT_EQ(DecodeMapRecord(add, FeatureType::kSift).status().code(), StatusCode::kCorruption);
  v1::MapRecord record;
  ASSERT_TRUE(record.ParseFromString(add));
  record.mutable_add_place()->set_bow("\x01\xff");
  auto bad_bow = DecodeMapRecord(record.SerializeAsString(), FeatureType::kOrb);
  EXPECT_EQ(bad_bow.status().code(), StatusCode::kCorruption);
  EXPECT_NE(bad_bow.status().message().find("add_place.bow"), std::string::npos);
  record.Clear();
  EXPECT_EQ(DecodeMapRecord(record.SerializeAsString(), FeatureType::kOrb).status().code(),
            StatusCode::kCorruption);  // no kind
  record.mutable_delete_place()->set_place_id(0);
  EXPECT_EQ(DecodeMapRecord(record.SerializeAsString(), FeatureType::kOrb).status().code(),
            StatusCode::kCorruption);
  EXPECT_EQ(DecodeMapRecord("not a record at all \xff\xff\xff", FeatureType::kOrb).status().code(),
            StatusCode::kCorruption);
  // Flipped bytes: never a crash; either CORRUPTION or a record that decodes.
  for (size_t i = 0; i < add.size(); i += 7) {
    std::string flipped = add;
    flipped[i] = char(flipped[i] ^ 0x5a);
    auto decoded = DecodeMapRecord(flipped, FeatureType::kOrb);
    if (!decoded.ok()) {
      EXPECT_EQ(decoded.status().code(), StatusCode::kCorruption);
    }
  }
}

}  // namespace
}  // namespace placedb::cluster
