// CreateMap, GetMap, ListMaps: a map's configuration is checked against its vocabulary and the
// limits, filled in with the effective values, and reopened after a restart with the vocabulary
// whose checksum it recorded.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <cstddef>
#include <string>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

// Maps reopen with the vocabulary whose checksum they recorded; one whose vocabulary is not
// configured is listed as unavailable (not fatal) until it is.
TEST_F(ServerTest, RestartReopensMapsWithTheirOwnVocabulary) {
  // Another vocabulary: the default's tree with one word weight changed.
  const std::shared_ptr<const Vocabulary> other = placedb::testing::OtherVocabulary();
  ASSERT_TRUE(other);
  ServerConfig config = Config();
  config.vocabularies["other"] = "(preloaded)";
  ServerDeps deps;
  deps.vocabularies["other"] = other;
  ASSERT_NO_FATAL_FAILURE(StartServer(config, deps));
  v1::MapConfig with_other;
  with_other.set_vocabulary("other");
  with_other.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
  with_other.mutable_filter()->set_method(v1::FILTER_METHOD_EXACT_COVERAGE);
  const v1::MapDescription created = CreateMap("other-map", with_other);
  EXPECT_EQ(created.config().vocabulary(), "other");
  EXPECT_EQ(created.config().verification().mode(), v1::VERIFICATION_MODE_EXHAUSTIVE);
  EXPECT_EQ(created.config().orb().max_features(), 1000);  // defaults filled in
  EXPECT_EQ(created.config().detection().box_source(), v1::BOX_SOURCE_AGENT);
  EXPECT_EQ(created.config().detection().classes_size(), 6);
  CreateMap("default-map");
  ASSERT_TRUE(IngestAll(stub_.get(), "other-map", {RtabmapObservation(1, "a")}).status.ok());
  ASSERT_TRUE(IngestAll(stub_.get(), "default-map", {RtabmapObservation(2, "a")}).status.ok());
  StopServer();

  // Without "other": its map is unavailable, the rest serves.
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  {
    grpc::ClientContext context;
    v1::ListMapsResponse maps;
    ASSERT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
    ASSERT_EQ(maps.maps_size(), 2);
    EXPECT_EQ(maps.maps(0).name(), "default-map");
    EXPECT_TRUE(maps.maps(0).available());
    EXPECT_EQ(maps.maps(0).places(), 1u);
    EXPECT_EQ(maps.maps(1).name(), "other-map");
    EXPECT_FALSE(maps.maps(1).available());
    EXPECT_NE(maps.maps(1).unavailable_reason().find(other->checksum_hex()), std::string::npos)
        << maps.maps(1).unavailable_reason();
  }
  v1::QueryResponse response;
  const grpc::Status unavailable = Query("other-map", RtabmapObservation(1, "a"), &response);
  EXPECT_EQ(unavailable.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(unavailable.error_message().find("not configured"), std::string::npos);
  EXPECT_TRUE(Query("default-map", RtabmapObservation(2, "a"), &response).ok());
  ASSERT_FALSE(response.matches().empty());
  // The index stores weights within 1/2048 relative: an L1 self-match within that of 1.
  EXPECT_NEAR(response.matches(0).score(), 1.0, 1.0 / 2048 + 1e-5);
  StopServer();

  // With it again: available, with its configuration and places.
  ASSERT_NO_FATAL_FAILURE(StartServer(config, deps));
  grpc::ClientContext context;
  v1::GetMapRequest request;
  request.set_name("other-map");
  v1::MapDescription description;
  ASSERT_TRUE(stub_->GetMap(&context, request, &description).ok());
  EXPECT_EQ(description.config().vocabulary(), "other");
  EXPECT_EQ(description.config().filter().method(), v1::FILTER_METHOD_EXACT_COVERAGE);
  EXPECT_EQ(description.stats().places(), 1u);
  EXPECT_EQ(description.vocabulary_checksum(), other->checksum_hex());
  ASSERT_TRUE(Query("other-map", RtabmapObservation(1, "a"), &response).ok());
  ASSERT_FALSE(response.matches().empty());
  EXPECT_GT(response.matches(0).inliers(), 12);
}

// A map's feature type must be its vocabulary's kind.
TEST_F(ServerTest, FeatureTypeMustMatchTheVocabulary) {
  ASSERT_TRUE(SiftVocabulary());
  ASSERT_NO_FATAL_FAILURE(StartServer(WithSift(Config()), SiftDeps()));
  v1::MapConfig sift_on_orb;
  sift_on_orb.set_feature_type(v1::FEATURE_TYPE_SIFT);  // on "default", a binary vocabulary
  const grpc::Status refused = CreateMapStatus("x", sift_on_orb);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(refused.error_message().rfind("config.feature_type", 0), 0u) << refused.error_message();
  v1::MapConfig orb_on_sift;
  orb_on_sift.set_vocabulary("sift");
  orb_on_sift.set_feature_type(v1::FEATURE_TYPE_ORB);
  EXPECT_EQ(CreateMapStatus("x", orb_on_sift).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  v1::MapConfig too_many = SiftMapConfig();
  too_many.mutable_sift()->set_max_features(5000);  // over limits.max_descriptors_per_frame 2000
  const grpc::Status budget = CreateMapStatus("x", too_many);
  EXPECT_EQ(budget.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(budget.error_message().find("config.sift.max_features"), std::string::npos);
  v1::MapConfig bad_sift = SiftMapConfig();
  bad_sift.mutable_sift()->set_octave_layers(0);
  const grpc::Status layers = CreateMapStatus("x", bad_sift);
  EXPECT_EQ(layers.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(layers.error_message().find("config.sift.octave_layers"), std::string::npos);
  v1::MapConfig bad_depth;
  bad_depth.mutable_depth()->set_threshold_m(-1);
  const grpc::Status depth = CreateMapStatus("x", bad_depth);
  EXPECT_EQ(depth.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(depth.error_message().rfind("config.depth.threshold_m", 0), 0u)
      << depth.error_message();
  v1::MapConfig bad_band;
  bad_band.mutable_depth()->mutable_rise_band()->set_near_m(3);
  bad_band.mutable_depth()->mutable_rise_band()->set_far_m(2);
  EXPECT_NE(CreateMapStatus("x", bad_band).error_message().find("config.depth.rise_band"),
            std::string::npos);
  v1::MapConfig bad_loop;
  bad_loop.mutable_loop_closure()->set_loop_threshold(1.5);
  const grpc::Status loop = CreateMapStatus("x", bad_loop);
  EXPECT_EQ(loop.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(loop.error_message().rfind("config.loop_closure.loop_threshold", 0), 0u)
      << loop.error_message();
  // All = the limit: a SIFT map never extracts more than a frame may carry.
  v1::MapConfig all = SiftMapConfig();
  all.mutable_sift()->set_max_features(0);
  EXPECT_EQ(CreateMap("all", all).config().sift().max_features(), 2000);
  // Settings round-trip.
  v1::MapConfig tuned;
  tuned.mutable_depth()->set_threshold_m(0.3f);
  tuned.mutable_depth()->set_band_policy(v1::BAND_POLICY_FIXED);
  tuned.mutable_depth()->set_stream_filter(false);
  tuned.mutable_loop_closure()->set_short_term_memory(12);
  const v1::MapDescription described = CreateMap("tuned", tuned);
  EXPECT_EQ(described.config().feature_type(), v1::FEATURE_TYPE_ORB);
  EXPECT_NEAR(described.config().depth().threshold_m(), 0.3, 1e-6);
  EXPECT_EQ(described.config().depth().band_policy(), v1::BAND_POLICY_FIXED);
  EXPECT_FALSE(described.config().depth().stream_filter());
  EXPECT_EQ(described.config().loop_closure().short_term_memory(), 12);
  grpc::ClientContext context;
  v1::ListMapsResponse maps;
  ASSERT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
  EXPECT_EQ(maps.maps_size(), 2) << "a refused CreateMap left a map behind";
  for (const v1::MapSummary& summary : maps.maps()) {
    grpc::ClientContext get_context;
    v1::GetMapRequest get;
    get.set_name(summary.name());
    v1::MapDescription description;
    ASSERT_TRUE(stub_->GetMap(&get_context, get, &description).ok());
    EXPECT_NE(summary.feature_type(), v1::FEATURE_TYPE_UNSPECIFIED) << summary.name();
    EXPECT_EQ(summary.feature_type(), description.config().feature_type()) << summary.name();
  }
}

}  // namespace
}  // namespace placedb::server_testing
