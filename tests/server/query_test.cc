// Query (and the same frames through Ingest): every bad input gets its code and names the field
// while the map stays as it was; a SIFT map finds its own frames verified, from images and from
// precomputed SIFT alike; correspondences (inlier index pairs and the query's keypoints) only
// when asked, consistent with the inliers and the stored place's keypoints.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstddef>
#include <functional>
#include <map>
#include <opencv2/imgproc.hpp>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

// Every bad input gets its code, names what is wrong, and changes nothing stored.
TEST_F(ServerTest, BadInputGetsItsCodeAndLeavesTheMapIntact) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("m");
  {
    const IngestOutcome good =
        IngestAll(stub_.get(), "m", {RtabmapObservation(1, "a"), RtabmapObservation(2, "a")});
    ASSERT_TRUE(good.status.ok());
  }
  const v1::MapStats before = Stats("m");
  ASSERT_EQ(before.places(), 2u);

  const v1::Observation good = RtabmapObservation(7, "a");
  const v1::Features features = FeaturesOf(good);
  ASSERT_GT(features.keypoints_size(), 10);
  struct Case {
    std::string name;
    v1::Observation observation;
    grpc::StatusCode code;
    std::string message;  // must appear in the error message
  };
  std::vector<Case> cases;
  auto add = [&](std::string name, grpc::StatusCode code, std::string message,
                 const std::function<void(v1::Observation*)>& edit) {
    v1::Observation observation = good;
    edit(&observation);
    cases.push_back({std::move(name), std::move(observation), code, std::move(message)});
  };
  add("garbage image bytes", grpc::StatusCode::INVALID_ARGUMENT, "observation.encoded_image.data",
      [](v1::Observation* o) { o->mutable_encoded_image()->set_data("definitely not an image"); });
  add("damaged JPEG", grpc::StatusCode::INVALID_ARGUMENT, "JPEG", [](v1::Observation* o) {
    o->mutable_encoded_image()->set_data(std::string("\xFF\xD8\xFF\xE0\x00\x10", 6) +
                                         std::string(200, '\x11'));
  });
  add("no frame", grpc::StatusCode::INVALID_ARGUMENT, "encoded_image, raw_image, features or",
      [](v1::Observation* o) { o->clear_frame(); });
  add("keypoint outside the image", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.features.keypoints[3].x: 700 lies outside the 512x384 image",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_keypoints(3)->set_x(700);
      });
  add("descriptor bytes not a multiple of 32", grpc::StatusCode::INVALID_ARGUMENT, "multiple of 32",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_descriptors()->pop_back();
      });
  add("mismatched counts", grpc::StatusCode::INVALID_ARGUMENT, "descriptors for",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_keypoints()->RemoveLast();
      });
  add("non-finite keypoint", grpc::StatusCode::INVALID_ARGUMENT, "keypoints[0].size",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        o->mutable_features()->mutable_keypoints(0)->set_size(std::nanf(""));
      });
  add("too many descriptors", grpc::StatusCode::RESOURCE_EXHAUSTED, "max_descriptors_per_frame",
      [&](v1::Observation* o) {
        *o->mutable_features() = features;
        while (o->features().keypoints_size() <= 2000) {
          *o->mutable_features()->add_keypoints() = features.keypoints(0);
          o->mutable_features()->mutable_descriptors()->append(
              features.descriptors().substr(0, 32));
        }
      });
  add("too many boxes", grpc::StatusCode::RESOURCE_EXHAUSTED, "max_boxes_per_frame",
      [](v1::Observation* o) {
        for (int i = 0; i < 17; ++i) {
          v1::Box* box = o->add_boxes();
          box->set_class_id(0);
          box->set_confidence(0.5f);
          box->mutable_rect()->set_width(10);
          box->mutable_rect()->set_height(10);
        }
      });
  add("too many pixels", grpc::StatusCode::RESOURCE_EXHAUSTED, "max_image_pixels",
      [](v1::Observation* o) {
        o->mutable_encoded_image()->set_data(EncodePng(cv::Mat::zeros(1500, 1500, CV_8U)));
      });
  add("unknown box class", grpc::StatusCode::INVALID_ARGUMENT, "observation.boxes[0].class_name",
      [](v1::Observation* o) {
        v1::Box* box = o->add_boxes();
        box->set_class_name("unicorn");
        box->set_confidence(0.5f);
        box->mutable_rect()->set_width(10);
      });
  add("box confidence out of range", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.boxes[0].confidence", [](v1::Observation* o) {
        v1::Box* box = o->add_boxes();
        box->set_class_id(2);
        box->set_confidence(1.5f);
        box->mutable_rect()->set_width(10);
      });
  add("raw pixels of the wrong size", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.raw_image.data", [](v1::Observation* o) {
        v1::RawImage* raw = o->mutable_raw_image();
        raw->set_width(64);
        raw->set_height(48);
        raw->set_format(v1::PIXEL_FORMAT_BGR8);
        raw->set_data(std::string(64 * 48, '\0'));
      });
  add("mask of the wrong size", grpc::StatusCode::INVALID_ARGUMENT, "observation.dynamic_mask_png",
      [](v1::Observation* o) {
        o->set_dynamic_mask_png(EncodePng(cv::Mat::zeros(10, 10, CV_8U)));
      });
  add("depth of another aspect ratio", grpc::StatusCode::INVALID_ARGUMENT, "observation.depth",
      [](v1::Observation* o) {
        o->mutable_depth()->set_png16(EncodePng(cv::Mat::zeros(64, 64, CV_16U)));
      });
  add("depth intrinsics outside the image", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.depth.intrinsics.cx", [](v1::Observation* o) {
        o->mutable_depth()->set_png16(EncodePng(cv::Mat::zeros(48, 64, CV_16U)));
        v1::Intrinsics* k = o->mutable_depth()->mutable_intrinsics();
        k->set_fx(500);
        k->set_fy(500);
        k->set_cx(900);
        k->set_cy(200);
      });
  add("SIFT features on an ORB map", grpc::StatusCode::INVALID_ARGUMENT,
      "observation.sift_features", [](v1::Observation* o) {
        v1::SiftFeatures* sift = o->mutable_sift_features();
        sift->set_image_width(512);
        sift->set_image_height(384);
      });
  add("8-bit depth", grpc::StatusCode::INVALID_ARGUMENT, "16-bit", [](v1::Observation* o) {
    o->mutable_depth()->set_png16(EncodePng(cv::Mat::zeros(480, 640, CV_8U)));
  });
  add("non-finite pose", grpc::StatusCode::INVALID_ARGUMENT, "observation.pose",
      [](v1::Observation* o) { o->mutable_pose()->set_x(std::nan("")); });

  // Each case through Query and through an Ingest stream of bad frames only.
  std::vector<v1::Observation> bad;
  for (const Case& c : cases) {
    v1::QueryResponse response;
    const grpc::Status status = Query("m", c.observation, &response);
    EXPECT_EQ(status.error_code(), c.code) << c.name << ": " << status.error_message();
    EXPECT_NE(status.error_message().find(c.message), std::string::npos)
        << c.name << ": '" << status.error_message() << "' does not mention " << c.message;
    bad.push_back(c.observation);
  }
  const IngestOutcome ingested = IngestAll(stub_.get(), "m", bad);
  EXPECT_TRUE(ingested.status.ok())
      << "a bad frame must not end the stream: " << ingested.status.error_message();
  ASSERT_EQ(ingested.responses.size(), cases.size());
  for (size_t i = 0; i < cases.size(); ++i) {
    const v1::IngestResponse& response = ingested.responses[i];
    EXPECT_FALSE(response.stored()) << cases[i].name;
    EXPECT_EQ(response.error().code(), int(cases[i].code)) << cases[i].name;
    EXPECT_NE(response.error().message().find(cases[i].message), std::string::npos)
        << cases[i].name << ": " << response.error().message();
  }

  // Tiny images are answered (no corners: not a valid place), not refused; a side of 1 pixel is
  // refused (OpenCV's ORB cannot take it).
  v1::QueryResponse response;
  {
    v1::Observation dot;
    dot.mutable_encoded_image()->set_data(EncodePng(cv::Mat(1, 7, CV_8U, cv::Scalar(5))));
    const grpc::Status status = Query("m", dot, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(status.error_message().find("too small"), std::string::npos);
  }
  for (const auto& [w, h] : {std::pair{2, 2}, std::pair{8, 6}, std::pair{40, 3}}) {
    v1::Observation tiny;
    tiny.mutable_encoded_image()->set_data(
        EncodePng(cv::Mat(h, w, CV_8UC3, cv::Scalar(9, 99, 199))));
    ASSERT_TRUE(Query("m", tiny, &response).ok()) << w << "x" << h;
    EXPECT_FALSE(response.valid());
    EXPECT_NE(response.rejection().find("placeThreshold"), std::string::npos);
    v1::Observation raw;
    raw.mutable_raw_image()->set_width(uint32_t(w));
    raw.mutable_raw_image()->set_height(uint32_t(h));
    raw.mutable_raw_image()->set_format(v1::PIXEL_FORMAT_RGB8);
    raw.mutable_raw_image()->set_data(std::string(size_t(w * h * 3), '\x40'));
    ASSERT_TRUE(Query("m", raw, &response).ok()) << w << "x" << h;
  }

  // Maps, names and the stream protocol.
  EXPECT_EQ(Query("nowhere", good, &response).error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(IngestAll(stub_.get(), "nowhere", {good}).status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(CreateMapStatus("m").error_code(), grpc::StatusCode::ALREADY_EXISTS);
  const grpc::Status bad_name = CreateMapStatus("../evil");
  EXPECT_EQ(bad_name.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(bad_name.error_message().rfind("name:", 0), 0u) << bad_name.error_message();
  EXPECT_EQ(Query("../evil", good, &response).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  v1::MapConfig unknown_vocabulary;
  unknown_vocabulary.set_vocabulary("klingon");
  const grpc::Status vocabulary = CreateMapStatus("x", unknown_vocabulary);
  EXPECT_EQ(vocabulary.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(vocabulary.error_message().find("config.vocabulary"), std::string::npos);
  v1::MapConfig bad_orb;
  bad_orb.mutable_orb()->set_max_features(-3);
  const grpc::Status orb = CreateMapStatus("x", bad_orb);
  EXPECT_EQ(orb.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(orb.error_message().find("config.orb.max_features"), std::string::npos);
  v1::MapConfig too_many_features;
  too_many_features.mutable_orb()->set_max_features(5000);
  EXPECT_EQ(CreateMapStatus("x", too_many_features).error_code(),
            grpc::StatusCode::RESOURCE_EXHAUSTED);
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_SERVER);
  EXPECT_EQ(CreateMapStatus("x", server_boxes).error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  {
    grpc::ClientContext context;
    auto stream = stub_->Ingest(&context);
    v1::IngestRequest request;
    *request.mutable_observation() = good;  // no header first
    stream->Write(request);
    stream->WritesDone();
    v1::IngestResponse ignored;
    while (stream->Read(&ignored)) {
    }
    EXPECT_EQ(stream->Finish().error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  }
  {
    grpc::ClientContext context;  // a message over limits.max_message_bytes
    v1::QueryRequest request;
    request.set_map("m");
    request.mutable_observation()->mutable_encoded_image()->set_data(std::string(5 << 20, 'x'));
    EXPECT_EQ(stub_->Query(&context, request, &response).error_code(),
              grpc::StatusCode::RESOURCE_EXHAUSTED);
  }
  {
    grpc::ClientContext context;
    v1::GetPlaceRequest request;
    request.set_map("m");
    request.set_place_id(999);
    v1::Place place;
    EXPECT_EQ(stub_->GetPlace(&context, request, &place).error_code(), grpc::StatusCode::NOT_FOUND);
  }
  {
    grpc::ClientContext context;
    v1::DeleteMapRequest request;
    request.set_name("nowhere");
    v1::DeleteMapResponse deleted;
    EXPECT_EQ(stub_->DeleteMap(&context, request, &deleted).error_code(),
              grpc::StatusCode::NOT_FOUND);
  }

  const v1::MapStats after = Stats("m");
  EXPECT_EQ(after.places(), before.places());
  EXPECT_EQ(after.descriptors_kept(), before.descriptors_kept());
  EXPECT_EQ(after.descriptors_dropped(), before.descriptors_dropped());
  EXPECT_EQ(after.invalid_rejected(), before.invalid_rejected());
  grpc::ClientContext context;
  v1::ListMapsResponse maps;
  ASSERT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
  ASSERT_EQ(maps.maps_size(), 1) << "a refused CreateMap left a map behind";
}

// The operator's `search` settings reach every query's index search: skipping frequent words
// narrows the candidates (their scores stay exact), but only in maps of at least
// skip_words_min_places places.
TEST_F(ServerTest, SearchSettingsSkipFrequentWordsOnlyInLargeEnoughMaps) {
  std::vector<v1::Observation> observations;
  for (int frame = 1; frame <= 8; ++frame) observations.push_back(RtabmapObservation(frame, "a"));
  const auto matches = [&](const ServerConfig& config) {
    StartServer(config);
    v1::QueryResponse response;
    EXPECT_TRUE(Query("m", observations[3], &response, 3).ok());
    StopServer();
    return std::vector<v1::Match>(response.matches().begin(), response.matches().end());
  };
  ServerConfig config = Config();
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  CreateMap("m");
  const IngestOutcome outcome = IngestAll(stub_.get(), "m", observations);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_TRUE(outcome.responses[3].stored());
  const uint32_t place = outcome.responses[3].place_id();
  StopServer();

  config.search.threads = 2;
  const std::vector<v1::Match> exact = matches(config);  // the default: every word scored
  ASSERT_FALSE(exact.empty());
  EXPECT_EQ(exact[0].place_id(), place);
  EXPECT_NEAR(exact[0].score(), 1.0, 1.0 / 2048 + 1e-5);

  // Words held by more than a quarter of the 8 places are skipped while scanning: the frame's
  // own place still shares rarer words, so it is a candidate, rescored with every word.
  config.search.max_word_share = 0.25;
  config.search.skip_words_min_places = 8;
  const std::vector<v1::Match> skipping = matches(config);
  ASSERT_FALSE(skipping.empty());
  EXPECT_EQ(skipping[0].place_id(), place);
  EXPECT_NEAR(skipping[0].score(), exact[0].score(), 1e-4);

  // A share below one place in 8 skips every stored word: no place is a candidate.
  config.search.max_word_share = 0.1;
  EXPECT_TRUE(matches(config).empty());

  config.search.skip_words_min_places = 9;  // the map is smaller: exact again
  const std::vector<v1::Match> small_map = matches(config);
  ASSERT_EQ(small_map.size(), exact.size());
  EXPECT_EQ(small_map[0].place_id(), place);
  EXPECT_DOUBLE_EQ(small_map[0].score(), exact[0].score());
}

// A SIFT map: created on the float vocabulary, frames ingested as images, queried back (as images
// and as precomputed SIFT) with exhaustive verification, stored SIFT features read back.
TEST_F(ServerTest, SiftMapIngestsImagesAndFindsThemVerified) {
  ASSERT_TRUE(SiftVocabulary());
  ASSERT_NO_FATAL_FAILURE(StartServer(WithSift(Config()), SiftDeps()));
  {
    grpc::ClientContext context;
    v1::ServerInfo info;
    ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
    std::map<std::string, v1::FeatureType> kinds;
    for (const auto& vocabulary : info.vocabularies()) {
      kinds[vocabulary.name()] = vocabulary.feature_type();
    }
    EXPECT_EQ(kinds["default"], v1::FEATURE_TYPE_ORB);
    EXPECT_EQ(kinds["sift"], v1::FEATURE_TYPE_SIFT);
  }
  v1::MapConfig config;
  config.set_vocabulary("sift");  // feature_type unspecified: the vocabulary's kind
  config.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
  const v1::MapDescription created = CreateMap("sift-map", config);
  EXPECT_EQ(created.config().feature_type(), v1::FEATURE_TYPE_SIFT);
  EXPECT_EQ(created.config().sift().max_features(), 1000);  // effective values filled in
  EXPECT_NEAR(created.config().sift().contrast_threshold(), 0.04, 1e-9);
  EXPECT_NEAR(created.config().depth().threshold_m(), 0.15, 1e-6);
  EXPECT_EQ(created.config().depth().band_policy(), v1::BAND_POLICY_APPEARED_LAYER);
  EXPECT_NEAR(created.config().loop_closure().loop_threshold(), 0.12, 1e-9);
  EXPECT_EQ(created.vocabulary_checksum(), SiftVocabulary()->checksum_hex());

  std::vector<v1::Observation> observations;
  for (int frame = 1; frame <= 24; ++frame) observations.push_back(RtabmapObservation(frame, "a"));
  const IngestOutcome outcome = IngestAll(stub_.get(), "sift-map", observations);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), observations.size());
  std::vector<size_t> stored;
  for (size_t i = 0; i < outcome.responses.size(); ++i) {
    const v1::IngestResponse& response = outcome.responses[i];
    ASSERT_FALSE(response.has_error()) << i << ": " << response.error().message();
    EXPECT_EQ(
        response.counts().total(),
        response.counts().dynamic() + response.counts().depth_removed() + response.counts().kept());
    EXPECT_GT(response.timings().extract_ms(), 0);
    if (response.stored()) stored.push_back(i);
  }
  // The corridor is low-texture for SIFT: most frames, not necessarily all, are places.
  ASSERT_GE(stored.size(), 12u);
  EXPECT_EQ(Stats("sift-map").places(), stored.size());

  int verified = 0;
  for (size_t k = 0; k < stored.size(); k += 3) {
    const size_t i = stored[k];
    v1::QueryResponse response;
    ASSERT_TRUE(Query("sift-map", observations[i], &response, 3).ok());
    ASSERT_TRUE(response.valid()) << response.rejection();
    ASSERT_FALSE(response.matches().empty());
    EXPECT_EQ(response.matches(0).place_id(), outcome.responses[i].place_id()) << "frame " << i + 1;
    // The index stores weights within 1/2048 relative: an L1 self-match within that of 1.
    EXPECT_NEAR(response.matches(0).score(), 1.0, 1.0 / 2048 + 1e-5);
    verified += response.matches(0).verified();
    EXPECT_GT(response.matches(0).inliers(), 0);
    // Precomputed SIFT: the same ranking as the image.
    v1::Observation features_only;
    *features_only.mutable_sift_features() = SiftFeaturesOf(observations[i]);
    v1::QueryResponse from_features;
    ASSERT_TRUE(Query("sift-map", features_only, &from_features, 3).ok());
    ASSERT_EQ(from_features.matches_size(), response.matches_size());
    for (int m = 0; m < response.matches_size(); ++m) {
      EXPECT_EQ(from_features.matches(m).place_id(), response.matches(m).place_id());
      EXPECT_NEAR(from_features.matches(m).score(), response.matches(m).score(), 1e-9);
    }
  }
  EXPECT_EQ(verified, int((stored.size() + 2) / 3)) << "every self-match is verified";

  // Stored SIFT features on request: 512 bytes per kept keypoint.
  grpc::ClientContext context;
  v1::GetPlaceRequest request;
  request.set_map("sift-map");
  request.set_place_id(outcome.responses[stored[0]].place_id());
  request.set_include_features(true);
  v1::Place place;
  ASSERT_TRUE(stub_->GetPlace(&context, request, &place).ok());
  EXPECT_FALSE(place.has_features());
  EXPECT_EQ(uint32_t(place.sift_features().keypoints_size()), place.counts().kept());
  EXPECT_EQ(place.sift_features().descriptors().size(),
            size_t(place.sift_features().keypoints_size()) * 512);

  // ORB features cannot go into a SIFT map.
  v1::Observation orb_only;
  *orb_only.mutable_features() = FeaturesOf(observations[0]);
  v1::QueryResponse response;
  const grpc::Status wrong_type = Query("sift-map", orb_only, &response);
  EXPECT_EQ(wrong_type.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(wrong_type.error_message().find("observation.features"), std::string::npos)
      << wrong_type.error_message();
}

// Bad SIFT features and unregistrable depth are refused with the field named, storing nothing.
TEST_F(ServerTest, BadSiftFeaturesAndDepthAreRefused) {
  ASSERT_TRUE(SiftVocabulary());
  ASSERT_NO_FATAL_FAILURE(StartServer(WithSift(Config()), SiftDeps()));
  CreateMap("sift-map", SiftMapConfig());
  const v1::Observation good = RtabmapObservation(3, "a");
  const v1::SiftFeatures features = SiftFeaturesOf(good);
  ASSERT_GT(features.keypoints_size(), 30);
  struct Case {
    std::string name;
    v1::Observation observation;
    std::string message;
  };
  std::vector<Case> cases;
  auto add = [&](std::string name, std::string message,
                 const std::function<void(v1::Observation*)>& edit) {
    v1::Observation observation = good;
    edit(&observation);
    cases.push_back({std::move(name), std::move(observation), std::move(message)});
  };
  add("descriptor bytes not a multiple of 512", "observation.sift_features.descriptors",
      [&](v1::Observation* o) {
        *o->mutable_sift_features() = features;
        o->mutable_sift_features()->mutable_descriptors()->resize(features.descriptors().size() -
                                                                  4);
      });
  add("one descriptor too few", "observation.sift_features.descriptors", [&](v1::Observation* o) {
    *o->mutable_sift_features() = features;
    o->mutable_sift_features()->mutable_descriptors()->resize(features.descriptors().size() - 512);
  });
  add("keypoint outside the image", "observation.sift_features.keypoints[3].x",
      [&](v1::Observation* o) {
        *o->mutable_sift_features() = features;
        o->mutable_sift_features()->mutable_keypoints(3)->set_x(9999);
      });
  add("non-finite descriptor value", "observation.sift_features", [&](v1::Observation* o) {
    *o->mutable_sift_features() = features;
    const float nan = std::nanf("");
    o->mutable_sift_features()->mutable_descriptors()->replace(
        512 * 2 + 4 * 7, 4, reinterpret_cast<const char*>(&nan), 4);
  });
  add("depth with another aspect ratio", "observation.depth", [](v1::Observation* o) {
    o->mutable_depth()->set_png16(EncodePng(cv::Mat(300, 300, CV_16U, cv::Scalar(1500))));
  });
  add("sift features with depth of another aspect ratio", "observation.depth",
      [&](v1::Observation* o) {
        *o->mutable_sift_features() = features;
        o->mutable_depth()->set_png16(EncodePng(cv::Mat(100, 50, CV_16U, cv::Scalar(1500))));
      });
  std::vector<v1::Observation> bad;
  for (const Case& c : cases) {
    v1::QueryResponse response;
    const grpc::Status status = Query("sift-map", c.observation, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << c.name;
    EXPECT_NE(status.error_message().find(c.message), std::string::npos)
        << c.name << ": " << status.error_message();
    bad.push_back(c.observation);
  }
  const IngestOutcome outcome = IngestAll(stub_.get(), "sift-map", bad);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), cases.size());
  for (size_t i = 0; i < cases.size(); ++i) {
    const v1::IngestResponse& response = outcome.responses[i];
    EXPECT_FALSE(response.stored()) << cases[i].name;
    EXPECT_EQ(response.error().code(), int(grpc::StatusCode::INVALID_ARGUMENT)) << cases[i].name;
    EXPECT_NE(response.error().message().find(cases[i].message), std::string::npos)
        << cases[i].name << ": " << response.error().message();
  }
  const v1::MapStats stats = Stats("sift-map");
  EXPECT_EQ(stats.places(), 0u);
  EXPECT_EQ(stats.invalid_rejected(), 0u);
  EXPECT_EQ(stats.streams(), 0u) << "a refused frame must not touch the agent's stream state";
  // The good frame itself goes in.
  const IngestOutcome fine = IngestAll(stub_.get(), "sift-map", {good});
  ASSERT_EQ(fine.responses.size(), 1u);
  EXPECT_TRUE(fine.responses[0].stored())
      << fine.responses[0].rejection() << fine.responses[0].error().message();
}

// Query RTAB-Map frame 6 against a map holding frames 1..10: the top match is frame 6's place,
// its correspondences are its inliers, index both keypoint lists, and (a frame against itself)
// join keypoints at the same positions. Off by default.
TEST_F(ServerTest, CorrespondencesAreTheInliersOfTheTopMatch) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  v1::MapConfig config;
  config.mutable_verification()->set_mode(v1::VERIFICATION_MODE_EXHAUSTIVE);
  CreateMap("m", config);
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 10; ++frame) frames.push_back(RtabmapObservation(frame, "a"));
  const IngestOutcome outcome = IngestAll(stub_.get(), "m", frames);
  ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  ASSERT_EQ(outcome.responses.size(), frames.size());
  const uint32_t place = outcome.responses[5].place_id();
  ASSERT_TRUE(outcome.responses[5].stored());

  v1::QueryRequest request;
  request.set_map("m");
  *request.mutable_observation() = RtabmapObservation(6, "probe");
  request.mutable_options()->set_top_k(3);
  {
    grpc::ClientContext context;
    v1::QueryResponse plain;
    ASSERT_TRUE(stub_->Query(&context, request, &plain).ok());
    ASSERT_GT(plain.matches_size(), 0);
    EXPECT_TRUE(plain.matches(0).verified());
    EXPECT_EQ(plain.matches(0).correspondences_size(), 0) << "off by default";
    EXPECT_EQ(plain.query_keypoints_size(), 0);
    EXPECT_EQ(plain.query_dropped_keypoints_size(), 0);
    EXPECT_EQ(plain.image_width(), 0u);
  }
  request.mutable_options()->set_include_correspondences(true);
  grpc::ClientContext context;
  v1::QueryResponse response;
  ASSERT_TRUE(stub_->Query(&context, request, &response).ok());
  ASSERT_GT(response.matches_size(), 0);
  const v1::Match& top = response.matches(0);
  EXPECT_EQ(top.place_id(), place);
  ASSERT_TRUE(top.verified());
  EXPECT_EQ(top.correspondences_size(), top.inliers());
  EXPECT_EQ(response.query_keypoints_size(), int(response.counts().kept()));
  EXPECT_EQ(response.query_dropped_keypoints_size(), 0);  // no dynamic objects
  EXPECT_EQ(response.image_width(), 512u);
  EXPECT_EQ(response.image_height(), 384u);
  for (const v1::Match& match : response.matches()) {
    EXPECT_EQ(match.correspondences_size(), match.verified() ? match.inliers() : 0)
        << "place " << match.place_id();
  }

  grpc::ClientContext get_context;
  v1::GetPlaceRequest get;
  get.set_map("m");
  get.set_place_id(place);
  get.set_include_features(true);
  v1::Place stored;
  ASSERT_TRUE(stub_->GetPlace(&get_context, get, &stored).ok());
  const auto& place_keypoints = stored.features().keypoints();
  ASSERT_GT(place_keypoints.size(), 0);
  int coincide = 0;
  std::set<uint32_t> query_used, place_used;
  for (const v1::Correspondence& c : top.correspondences()) {
    ASSERT_LT(c.query_keypoint(), uint32_t(response.query_keypoints_size()));
    ASSERT_LT(c.place_keypoint(), uint32_t(place_keypoints.size()));
    EXPECT_TRUE(query_used.insert(c.query_keypoint()).second) << "query keypoint used twice";
    EXPECT_TRUE(place_used.insert(c.place_keypoint()).second) << "place keypoint used twice";
    const v1::Keypoint& q = response.query_keypoints(int(c.query_keypoint()));
    const v1::Keypoint& p = place_keypoints[int(c.place_keypoint())];
    if (std::abs(q.x() - p.x()) < 0.01f && std::abs(q.y() - p.y()) < 0.01f) ++coincide;
  }
  // The same image: identical descriptors at identical positions. Repeated texture may pair a
  // few keypoints with a twin elsewhere, never many.
  EXPECT_GE(coincide * 100, top.correspondences_size() * 95)
      << coincide << " of " << top.correspondences_size() << " coincide";

  // Through Ingest: the pairs' query side indexes the frame's own new place.
  v1::MatchOptions matches;
  matches.set_top_k(1);
  matches.set_include_correspondences(true);
  const IngestOutcome again = IngestAll(stub_.get(), "m", {RtabmapObservation(6, "b")}, &matches);
  ASSERT_TRUE(again.status.ok()) << again.status.error_message();
  ASSERT_EQ(again.responses.size(), 1u);
  const v1::IngestResponse& ingested = again.responses[0];
  ASSERT_TRUE(ingested.stored());
  ASSERT_EQ(ingested.matches_size(), 1);
  EXPECT_EQ(ingested.matches(0).place_id(), place);
  EXPECT_EQ(ingested.matches(0).correspondences_size(), ingested.matches(0).inliers());
  grpc::ClientContext new_context;
  get.set_place_id(ingested.place_id());
  v1::Place fresh;
  ASSERT_TRUE(stub_->GetPlace(&new_context, get, &fresh).ok());
  for (const v1::Correspondence& c : ingested.matches(0).correspondences()) {
    ASSERT_LT(c.query_keypoint(), uint32_t(fresh.features().keypoints_size()));
    ASSERT_LT(c.place_keypoint(), uint32_t(place_keypoints.size()));
  }
}

// A CamVid frame with boxes around its labelled cars, pedestrians and cyclists: the query's
// dropped keypoints are the filter's DC split and lie on the boxes.
TEST_F(ServerTest, DroppedKeypointsLieInsideTheBoxes) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("street");
  const auto camvid = testing::CamVidFrames();
  ASSERT_GT(camvid.size(), 10u);
  ASSERT_TRUE(IngestAll(stub_.get(), "street", {RtabmapObservation(1, "a")}).status.ok());
  const testing::CamVidFrame& frame = camvid[camvid.size() / 2];
  v1::QueryRequest request;
  request.set_map("street");
  *request.mutable_observation() = JpegObservation(frame.image_path, "c", 1);
  cv::Mat labels, stats, centroids;
  const int n =
      cv::connectedComponentsWithStats(testing::CamVidDynamicMask(frame), labels, stats, centroids);
  std::vector<cv::Rect2f> boxes;
  for (int k = 1; k < n; ++k) {
    if (stats.at<int>(k, cv::CC_STAT_AREA) < 400) continue;
    const cv::Rect2f rect(
        float(stats.at<int>(k, cv::CC_STAT_LEFT)), float(stats.at<int>(k, cv::CC_STAT_TOP)),
        float(stats.at<int>(k, cv::CC_STAT_WIDTH)), float(stats.at<int>(k, cv::CC_STAT_HEIGHT)));
    boxes.push_back(rect);
    v1::Box* box = request.mutable_observation()->add_boxes();
    box->set_class_name("car");
    box->set_confidence(0.9f);
    box->mutable_rect()->set_x(rect.x);
    box->mutable_rect()->set_y(rect.y);
    box->mutable_rect()->set_width(rect.width);
    box->mutable_rect()->set_height(rect.height);
  }
  ASSERT_FALSE(boxes.empty()) << frame.image_path << " has no labelled dynamic objects";
  request.mutable_options()->set_include_correspondences(true);
  grpc::ClientContext context;
  v1::QueryResponse response;
  ASSERT_TRUE(stub_->Query(&context, request, &response).ok());
  ASSERT_GT(response.counts().dynamic(), 0u);
  EXPECT_EQ(response.query_dropped_keypoints_size(), int(response.counts().dynamic()));
  EXPECT_EQ(response.query_keypoints_size(), int(response.counts().kept()));
  // A keypoint is dropped when enough of its patch is on an object: its centre is within the
  // box grown by half the patch.
  for (const v1::Keypoint& k : response.query_dropped_keypoints()) {
    bool inside = false;
    for (const cv::Rect2f& box : boxes) {
      const float grow = k.size() / 2;
      inside |= k.x() >= box.x - grow && k.x() <= box.x + box.width + grow &&
                k.y() >= box.y - grow && k.y() <= box.y + box.height + grow;
    }
    EXPECT_TRUE(inside) << "dropped keypoint at (" << k.x() << ", " << k.y() << ")";
  }
}

}  // namespace
}  // namespace placedb::server_testing
