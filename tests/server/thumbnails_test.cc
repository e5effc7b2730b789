// Per-place thumbnails (issue 20) through a real server: CamVid frames with the boxes of their
// labelled cars, pedestrians and cyclists and RTAB-Map frames are ingested into a map that keeps
// thumbnails; GetPlace(include_thumbnail) returns each place's reduced JPEG with its boxes
// blurred and its dropped keypoints. Precomputed features and maps without thumbnails have none;
// bad settings are INVALID_ARGUMENT; a corrupt stored thumbnail is DATA_LOSS and scrub finds it.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <rocksdb/db.h>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <span>
#include <string>
#include <vector>

#include "core/decode/image_decoder.h"
#include "core/storage/codec.h"
#include "core/thumbnail/thumbnail.h"
#include "tests/raw_map.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

cv::Mat Decode(const std::string& bytes) {
  auto decoded =
      DecodeImage(std::span(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()), {});
  EXPECT_TRUE(decoded.ok()) << decoded.status().ToString();
  return decoded.ok() ? *decoded : cv::Mat();
}

double LaplacianVariance(const cv::Mat& image) {
  cv::Mat gray;
  cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  cv::Mat laplacian;
  cv::Laplacian(gray, laplacian, CV_64F);
  cv::Scalar mean, stddev;
  cv::meanStdDev(laplacian, mean, stddev);
  return stddev[0] * stddev[0];
}

// A CamVid frame as an agent sends it: the JPEG, with the bounding boxes of its labelled dynamic
// objects (>= 400 px; Car -> car, Pedestrian and Bicyclist -> person), at most `max_boxes`.
v1::Observation CamVidObservation(const testing::CamVidFrame& frame, uint64_t sequence,
                                  int max_boxes) {
  v1::Observation observation = JpegObservation(frame.image_path, frame.sequence, sequence);
  const cv::Mat labels = cv::imread(frame.label_path, cv::IMREAD_GRAYSCALE);
  EXPECT_FALSE(labels.empty()) << frame.label_path;
  for (const auto& [label, coco] : std::vector<std::pair<int, int>>{{8, 2}, {9, 0}, {10, 0}}) {
    cv::Mat components, stats, centroids;
    const int count =
        cv::connectedComponentsWithStats(labels == label, components, stats, centroids, 8);
    for (int c = 1; c < count && observation.boxes_size() < max_boxes; ++c) {
      const int* s = stats.ptr<int>(c);
      if (s[cv::CC_STAT_AREA] < 400) continue;
      v1::Box* box = observation.add_boxes();
      box->set_class_id(coco);
      box->set_confidence(1.0f);
      box->mutable_rect()->set_x(float(s[cv::CC_STAT_LEFT]));
      box->mutable_rect()->set_y(float(s[cv::CC_STAT_TOP]));
      box->mutable_rect()->set_width(float(s[cv::CC_STAT_WIDTH]));
      box->mutable_rect()->set_height(float(s[cv::CC_STAT_HEIGHT]));
    }
  }
  return observation;
}

class ThumbnailsTest : public ServerTest {
 protected:
  static v1::MapConfig WithThumbnails(uint32_t max_side = 0) {
    v1::MapConfig config;
    config.mutable_thumbnails()->set_enabled(true);
    config.mutable_thumbnails()->set_max_side(max_side);
    return config;
  }
  grpc::Status GetPlace(const std::string& map, uint32_t id, bool thumbnail, v1::Place* place) {
    grpc::ClientContext context;
    v1::GetPlaceRequest request;
    request.set_map(map);
    request.set_place_id(id);
    request.set_include_thumbnail(thumbnail);
    return stub_->GetPlace(&context, request, place);
  }
  v1::MapConfig GetMapConfig(const std::string& map) {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name(map);
    v1::MapDescription description;
    EXPECT_TRUE(stub_->GetMap(&context, request, &description).ok());
    return description.config();
  }
};

TEST_F(ThumbnailsTest, IngestedFramesKeepReducedJpegsWithTheirBoxesBlurred) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  const v1::MapDescription created = CreateMap("street", WithThumbnails());
  // The effective settings: 0 took the defaults.
  EXPECT_TRUE(created.config().thumbnails().enabled());
  EXPECT_EQ(created.config().thumbnails().max_side(), 320u);
  EXPECT_EQ(created.config().thumbnails().jpeg_quality(), 75u);
  EXPECT_EQ(GetMapConfig("street").thumbnails().SerializeAsString(),
            created.config().thumbnails().SerializeAsString());

  std::vector<v1::Observation> frames;
  const auto camvid = testing::CamVidFrames();
  for (size_t f = 0; f < camvid.size() && frames.size() < 10; f += 60) {
    v1::Observation observation = CamVidObservation(camvid[f], f + 1, 16);
    if (observation.boxes_size() > 0) frames.push_back(std::move(observation));
  }
  ASSERT_EQ(frames.size(), 10u);
  const size_t camvid_frames = frames.size();
  for (int frame = 1; frame <= 12; ++frame) frames.push_back(RtabmapObservation(frame, "rover"));
  const IngestOutcome ingest = IngestAll(stub_.get(), "street", frames);
  ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
  ASSERT_EQ(ingest.responses.size(), frames.size());

  size_t checked = 0, camvid_checked = 0, regions = 0, with_dropped = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    const v1::IngestResponse& response = ingest.responses[i];
    ASSERT_FALSE(response.has_error()) << response.error().message();
    if (!response.stored()) continue;
    v1::Place place;
    ASSERT_TRUE(GetPlace("street", response.place_id(), true, &place).ok());
    ASSERT_TRUE(place.has_thumbnail()) << "place " << response.place_id();
    const v1::Thumbnail& thumbnail = place.thumbnail();
    const cv::Mat source = Decode(frames[i].encoded_image().data());
    const cv::Size size = ThumbnailSize(source.cols, source.rows, 320);
    EXPECT_EQ(thumbnail.width(), uint32_t(size.width));
    EXPECT_EQ(thumbnail.height(), uint32_t(size.height));
    EXPECT_EQ(thumbnail.source_width(), uint32_t(source.cols));
    EXPECT_EQ(thumbnail.source_height(), uint32_t(source.rows));
    const cv::Mat decoded = Decode(thumbnail.jpeg());
    ASSERT_EQ(decoded.size(), size);
    EXPECT_EQ(uint32_t(thumbnail.dropped_keypoints_size()), place.counts().dynamic());
    with_dropped += thumbnail.dropped_keypoints_size() > 0;
    for (const v1::Keypoint& k : thumbnail.dropped_keypoints()) {
      EXPECT_TRUE(k.x() >= 0 && k.x() < source.cols && k.y() >= 0 && k.y() < source.rows);
    }
    ++checked;
    if (i >= camvid_frames) continue;
    // The boxes used are blurred: smooth inside; outside, the reduced frame within JPEG error.
    ASSERT_GT(place.boxes_used_size(), 0);
    const cv::Mat reduced = ReduceFrame(source, 320);
    cv::Mat blurred = cv::Mat::zeros(size, CV_8U);
    for (const v1::UsedBox& box : place.boxes_used()) {
      const cv::Rect2f rect(box.rect().x(), box.rect().y(), box.rect().width(),
                            box.rect().height());
      const cv::Rect r = ThumbnailBoxRect(rect, source.size(), size);
      ASSERT_FALSE(r.empty());
      blurred(r).setTo(255);
      const cv::Rect inner(r.x + 2, r.y + 2, r.width - 4, r.height - 4);
      if (inner.width < 6 || inner.height < 6) continue;
      const double before = LaplacianVariance(reduced(inner));
      if (before < 30) continue;
      EXPECT_LT(LaplacianVariance(decoded(inner)), 0.2 * before)
          << "place " << response.place_id() << " box " << r;
      ++regions;
    }
    cv::Mat outside;
    cv::dilate(blurred, outside, cv::Mat::ones(17, 17, CV_8U));
    outside = outside == 0;
    cv::Mat difference;
    cv::absdiff(decoded, reduced, difference);
    EXPECT_LT(cv::mean(difference, outside)[0], 8.0) << "place " << response.place_id();
    ++camvid_checked;
  }
  EXPECT_GE(camvid_checked, 8u);
  EXPECT_GE(checked, camvid_checked + 8);
  EXPECT_GE(regions, 10u);
  EXPECT_GE(with_dropped, 8u);

  // Not asked for: not sent.
  v1::Place place;
  ASSERT_TRUE(GetPlace("street", ingest.responses[0].place_id(), false, &place).ok());
  EXPECT_FALSE(place.has_thumbnail());
}

TEST_F(ThumbnailsTest, PrecomputedFeaturesAndMapsWithoutThumbnailsHaveNone) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("features", WithThumbnails(128));
  EXPECT_EQ(GetMapConfig("features").thumbnails().max_side(), 128u);
  v1::Observation observation = RtabmapObservation(10, "rover");
  v1::Observation features = observation;
  *features.mutable_features() = FeaturesOf(observation);
  IngestOutcome ingest = IngestAll(stub_.get(), "features", {features, observation});
  ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
  ASSERT_EQ(ingest.responses.size(), 2u);
  ASSERT_TRUE(ingest.responses[0].stored() && ingest.responses[1].stored());
  v1::Place place;
  ASSERT_TRUE(GetPlace("features", ingest.responses[0].place_id(), true, &place).ok());
  EXPECT_FALSE(place.has_thumbnail()) << "precomputed features carry no pixels";
  ASSERT_TRUE(GetPlace("features", ingest.responses[1].place_id(), true, &place).ok());
  ASSERT_TRUE(place.has_thumbnail());
  EXPECT_EQ(std::max(place.thumbnail().width(), place.thumbnail().height()), 128u);

  CreateMap("plain");
  const v1::MapConfig plain = GetMapConfig("plain");
  EXPECT_FALSE(plain.thumbnails().enabled());
  EXPECT_EQ(plain.thumbnails().max_side(), 320u);  // effective, should they be turned on
  ingest = IngestAll(stub_.get(), "plain", {observation});
  ASSERT_TRUE(ingest.status.ok() && ingest.responses.size() == 1u);
  ASSERT_TRUE(ingest.responses[0].stored());
  ASSERT_TRUE(GetPlace("plain", ingest.responses[0].place_id(), true, &place).ok());
  EXPECT_FALSE(place.has_thumbnail());
}

TEST_F(ThumbnailsTest, BadSettingsAreInvalidArgumentNamingTheField) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  struct Bad {
    uint32_t max_side, quality;
    const char* field;
  };
  for (const Bad& bad :
       {Bad{8, 0, "config.thumbnails.max_side"}, Bad{2000, 0, "config.thumbnails.max_side"},
        Bad{0, 101, "config.thumbnails.jpeg_quality"}}) {
    v1::MapConfig config = WithThumbnails(bad.max_side);
    config.mutable_thumbnails()->set_jpeg_quality(bad.quality);
    config.mutable_thumbnails()->set_enabled(bad.max_side != 2000);  // checked on or off
    const grpc::Status status = CreateMapStatus("bad", config);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << bad.field;
    EXPECT_NE(status.error_message().find(bad.field), std::string::npos) << status.error_message();
  }
  grpc::ClientContext context;
  v1::GetMapRequest request;
  request.set_name("bad");
  v1::MapDescription description;
  EXPECT_EQ(stub_->GetMap(&context, request, &description).error_code(),
            grpc::StatusCode::NOT_FOUND);
}

// A thumbnail value that does not decode: GetPlace with the thumbnail is DATA_LOSS naming the
// place (without it the place still answers), and scrub reports the place.
TEST_F(ThumbnailsTest, CorruptThumbnailIsDataLossAndScrubFindsIt) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("lab", WithThumbnails());
  std::vector<v1::Observation> frames;
  for (int frame = 20; frame < 26; ++frame) frames.push_back(RtabmapObservation(frame, "rover"));
  const IngestOutcome ingest = IngestAll(stub_.get(), "lab", frames);
  ASSERT_TRUE(ingest.status.ok());
  uint32_t victim = 0;
  for (const v1::IngestResponse& response : ingest.responses) {
    if (response.stored()) victim = response.place_id();
  }
  ASSERT_NE(victim, 0u);
  StopServer();  // closes (and flushes) the map: RocksDB below replays nothing of placedb's
  ASSERT_NO_FATAL_FAILURE(testing::EditRawMap(
      root_ + "/data/maps/lab",
      [victim](rocksdb::DB* raw, std::vector<rocksdb::ColumnFamilyHandle*>& handles) {
        std::string value;
        ASSERT_TRUE(raw->Get({}, handles[6], PlaceKey(victim), &value).ok());
        value.resize(value.size() / 2);  // cut in the middle of the JPEG
        rocksdb::WriteOptions sync;
        sync.sync = true;
        EXPECT_TRUE(raw->Put(sync, handles[6], PlaceKey(victim), value).ok());
      }));
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  v1::Place place;
  const grpc::Status status = GetPlace("lab", victim, true, &place);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::DATA_LOSS) << status.error_message();
  EXPECT_NE(status.error_message().find("place " + std::to_string(victim)), std::string::npos)
      << status.error_message();
  EXPECT_TRUE(GetPlace("lab", victim, false, &place).ok());
  EXPECT_TRUE(GetPlace("lab", ingest.responses[0].place_id(), true, &place).ok());

  grpc::ClientContext context;
  v1::ScrubMapRequest request;
  request.set_name("lab");
  v1::ScrubReport report;
  ASSERT_TRUE(stub_->ScrubMap(&context, request, &report).ok());
  EXPECT_FALSE(report.clean());
  ASSERT_EQ(report.damaged_places_size(), 1);
  EXPECT_EQ(report.damaged_places(0).place_id(), victim);
  EXPECT_NE(report.damaged_places(0).reason().find("thumbnail"), std::string::npos)
      << report.damaged_places(0).reason();
}

}  // namespace
}  // namespace placedb::server_testing
