// GetDynamics and Place.dynamics (issue 16) through a real server: the statistics of ingested
// frames, ranked and paged, and bad requests.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <set>
#include <string>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

// RTAB-Map frame `frame` with a person box whose width grows with the frame (so coverage
// differs from place to place) and a car on every fourth frame.
v1::Observation WithObjects(int frame) {
  v1::Observation observation = RtabmapObservation(frame, "rover");
  v1::Box* person = observation.add_boxes();
  person->set_class_id(0);
  person->set_confidence(0.9f);
  person->mutable_rect()->set_width(float(8 * (frame % 20 + 1)));
  person->mutable_rect()->set_height(200);
  if (frame % 4 == 0) {
    v1::Box* car = observation.add_boxes();
    car->set_class_id(2);
    car->set_confidence(0.8f);
    car->mutable_rect()->set_x(400);
    car->mutable_rect()->set_y(300);
    car->mutable_rect()->set_width(200);
    car->mutable_rect()->set_height(150);
  }
  return observation;
}

class DynamicsTest : public ServerTest {
 protected:
  grpc::Status Get(const v1::GetDynamicsRequest& request, v1::GetDynamicsResponse* response) {
    grpc::ClientContext context;
    return stub_->GetDynamics(&context, request, response);
  }
};

TEST_F(DynamicsTest, IngestedFramesAreCountedRankedAndPaged) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  CreateMap("street");
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 24; ++frame) frames.push_back(WithObjects(frame));
  const IngestOutcome ingest = IngestAll(stub_.get(), "street", frames);
  ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
  std::set<uint32_t> stored;
  size_t with_car = 0;
  for (size_t i = 0; i < ingest.responses.size(); ++i) {
    if (!ingest.responses[i].stored()) continue;
    stored.insert(ingest.responses[i].place_id());
    with_car += frames[i].boxes_size() > 1;
  }
  ASSERT_GT(stored.size(), 12u);

  v1::GetDynamicsRequest request;
  request.set_map("street");
  request.set_limit(5);
  v1::GetDynamicsResponse page;
  ASSERT_TRUE(Get(request, &page).ok());
  EXPECT_EQ(page.map().observations(), stored.size());
  EXPECT_GT(page.map().mean_coverage(), 0.0);
  EXPECT_EQ(page.ranked(), stored.size());
  // The map's mean coverage is also a gauge.
  EXPECT_NEAR(MetricValue(Scrape(), "placedb_map_dynamic_coverage", {{"map", "street"}}),
              page.map().mean_coverage(), 1e-6);
  // Frames refused as invalid have their own aggregate.
  EXPECT_EQ(page.invalid().observations(), frames.size() - stored.size());
  ASSERT_EQ(page.places_size(), 5);
  EXPECT_EQ(page.next_offset(), 5u);
  for (int i = 1; i < page.places_size(); ++i) {
    EXPECT_GE(page.places(i - 1).score(), page.places(i).score()) << "not best first";
  }
  // Walking every page visits every stored place once.
  std::set<uint32_t> visited;
  for (uint32_t offset = 0;;) {
    request.set_offset(offset);
    v1::GetDynamicsResponse next;
    ASSERT_TRUE(Get(request, &next).ok());
    for (const v1::RankedPlace& place : next.places()) {
      EXPECT_TRUE(visited.insert(place.place_id()).second) << "place on two pages";
      EXPECT_EQ(place.support(), 1u);
    }
    if (next.next_offset() == 0) break;
    offset = next.next_offset();
  }
  EXPECT_EQ(visited, stored);
  request.set_offset(uint32_t(stored.size()) + 10);  // past the end: empty, not an error
  v1::GetDynamicsResponse past;
  ASSERT_TRUE(Get(request, &past).ok());
  EXPECT_EQ(past.places_size(), 0);
  EXPECT_EQ(past.next_offset(), 0u);
  EXPECT_EQ(past.ranked(), stored.size());

  // By class: the places whose frame had a car first, with share 1.
  request.set_offset(0);
  request.set_limit(100);
  request.set_measure(v1::DYNAMICS_MEASURE_CLASS_SHARE);
  request.set_class_id(2);
  request.set_include_statistics(true);
  v1::GetDynamicsResponse cars;
  ASSERT_TRUE(Get(request, &cars).ok());
  ASSERT_EQ(size_t(cars.places_size()), stored.size());
  for (int i = 0; i < cars.places_size(); ++i) {
    const bool car = size_t(i) < with_car;
    EXPECT_EQ(cars.places(i).score(), car ? 1.0 : 0.0) << i;
    const v1::DynamicStatistics& statistics = cars.places(i).statistics();
    EXPECT_EQ(statistics.observations(), 1u);
    ASSERT_GE(statistics.classes_size(), 1);
    EXPECT_EQ(statistics.classes(0).class_id(), 0);  // the person, in every frame
  }

  // The class by its COCO name: the same ranking.
  request.set_class_id(0);
  request.set_class_name("car");
  v1::GetDynamicsResponse named;
  ASSERT_TRUE(Get(request, &named).ok());
  ASSERT_EQ(named.places_size(), cars.places_size());
  for (int i = 0; i < named.places_size(); ++i) {
    EXPECT_EQ(named.places(i).place_id(), cars.places(i).place_id());
  }
  request.clear_class_name();

  // Place.dynamics: the place's own statistics. The fixture's timestamps (sequence x 100 ms
  // after the epoch) fall on Thursday 1970-01-01 00:00 UTC.
  grpc::ClientContext context;
  v1::GetPlaceRequest get;
  get.set_map("street");
  get.set_place_id(*stored.begin());
  v1::Place place;
  ASSERT_TRUE(stub_->GetPlace(&context, get, &place).ok());
  EXPECT_EQ(place.dynamics().observations(), 1u);
  // Kept in parts per million.
  EXPECT_NEAR(place.dynamics().mean_coverage(), place.counts().dynamic_coverage(), 1e-6);
  ASSERT_EQ(place.dynamics().hours_size(), 1);
  EXPECT_EQ(place.dynamics().hours(0).weekday(), 3u);
  EXPECT_EQ(place.dynamics().hours(0).hour(), 0u);

  // An hour window without any observation ranks nothing.
  request.set_measure(v1::DYNAMICS_MEASURE_HOUR_WINDOW);
  request.set_first_hour(8);
  request.set_last_hour(10);
  v1::GetDynamicsResponse morning;
  ASSERT_TRUE(Get(request, &morning).ok());
  EXPECT_EQ(morning.ranked(), 0u);
  EXPECT_EQ(morning.places_size(), 0);
}

TEST_F(DynamicsTest, BadRequestsNameTheirField) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("street");
  auto status = [&](v1::GetDynamicsRequest request) {
    v1::GetDynamicsResponse response;
    return Get(request, &response);
  };
  v1::GetDynamicsRequest request;
  request.set_map("nowhere");
  EXPECT_EQ(status(request).error_code(), grpc::StatusCode::NOT_FOUND);
  request.set_map("street");
  EXPECT_TRUE(status(request).ok()) << "an empty map has empty statistics";
  struct Case {
    std::string field;
    v1::GetDynamicsRequest request;
  };
  std::vector<Case> cases;
  cases.push_back({"limit", request});
  cases.back().request.set_limit(5000);
  cases.push_back({"class_id", request});
  cases.back().request.set_measure(v1::DYNAMICS_MEASURE_CLASS_SHARE);
  cases.back().request.set_class_id(-3);
  cases.push_back({"last_hour: 30", request});
  cases.back().request.set_measure(v1::DYNAMICS_MEASURE_HOUR_WINDOW);
  cases.back().request.set_last_hour(30);
  cases.push_back({"weekdays", request});
  cases.back().request.set_measure(v1::DYNAMICS_MEASURE_HOUR_WINDOW);
  cases.back().request.set_weekdays(0x100);
  cases.push_back({"class_name", request});
  cases.back().request.set_measure(v1::DYNAMICS_MEASURE_CLASS_SHARE);
  cases.back().request.set_class_name("unicorn");
  cases.push_back({"disagree", request});
  cases.back().request.set_measure(v1::DYNAMICS_MEASURE_CLASS_SHARE);
  cases.back().request.set_class_id(2);
  cases.back().request.set_class_name("person");
  cases.push_back({"measure", request});
  cases.back().request.set_measure(v1::DynamicsMeasure(42));
  for (const Case& c : cases) {
    const grpc::Status s = status(c.request);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << c.field;
    EXPECT_NE(s.error_message().find(c.field), std::string::npos) << s.error_message();
  }
}

// MapConfig.dynamics.count_query_hits_above: a query whose best match scores above it is one
// more observation of that place, durably (it survives a restart); below it, or on a map that
// does not count hits, a query changes nothing.
TEST_F(DynamicsTest, QueryHitsAboveTheMapsScoreAreCounted) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  v1::MapConfig counting;
  counting.mutable_dynamics()->set_count_query_hits_above(0.3);
  EXPECT_EQ(CreateMap("counted", counting).config().dynamics().count_query_hits_above(), 0.3);
  CreateMap("plain");
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 20; ++frame) frames.push_back(WithObjects(frame));
  for (const char* map : {"counted", "plain"}) {
    const IngestOutcome ingest = IngestAll(stub_.get(), map, frames);
    ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
  }
  auto place_dynamics = [&](const std::string& map, uint32_t id) {
    grpc::ClientContext context;
    v1::GetPlaceRequest get;
    get.set_map(map);
    get.set_place_id(id);
    v1::Place place;
    EXPECT_TRUE(stub_->GetPlace(&context, get, &place).ok());
    return place.dynamics();
  };
  auto map_observations = [&](const std::string& map) {
    v1::GetDynamicsRequest request;
    request.set_map(map);
    v1::GetDynamicsResponse response;
    EXPECT_TRUE(Get(request, &response).ok());
    return response.map().observations();
  };
  const uint64_t counted_before = map_observations("counted");
  const uint64_t plain_before = map_observations("plain");

  // The same view again, a day later (Friday 1970-01-02 09:00 UTC), with a bigger person.
  v1::Observation again = WithObjects(12);
  again.set_timestamp_ns(int64_t(33) * 3600 * 1'000'000'000LL);
  again.mutable_boxes(0)->mutable_rect()->set_width(300);
  v1::QueryResponse hit;
  ASSERT_TRUE(Query("counted", again, &hit).ok());
  ASSERT_TRUE(hit.valid());
  ASSERT_GT(hit.matches_size(), 0);
  ASSERT_GT(hit.matches(0).score(), 0.3) << "the same image should match its place well";
  const uint32_t place = hit.matches(0).place_id();
  const v1::DynamicStatistics counted = place_dynamics("counted", place);
  EXPECT_EQ(counted.observations(), 2u);
  EXPECT_NEAR(counted.max_coverage(), hit.counts().dynamic_coverage(), 1e-6);
  EXPECT_EQ(counted.last_timestamp_ns(), again.timestamp_ns());
  ASSERT_EQ(counted.hours_size(), 2);
  EXPECT_EQ(counted.hours(1).weekday(), 4u);
  EXPECT_EQ(counted.hours(1).hour(), 9u);
  EXPECT_EQ(map_observations("counted"), counted_before + 1);

  // A map that does not count hits: the same query changes nothing.
  v1::QueryResponse plain_hit;
  ASSERT_TRUE(Query("plain", again, &plain_hit).ok());
  ASSERT_GT(plain_hit.matches_size(), 0);
  EXPECT_EQ(place_dynamics("plain", plain_hit.matches(0).place_id()).observations(), 1u);
  EXPECT_EQ(map_observations("plain"), plain_before);

  // A view the map has not seen (a CamVid street): its best match scores below 0.3.
  const v1::Observation street =
      JpegObservation(testing::CamVidFrames().front().image_path, "rover", 99);
  v1::QueryResponse miss;
  ASSERT_TRUE(Query("counted", street, &miss).ok());
  if (miss.matches_size() > 0) {
    EXPECT_LE(miss.matches(0).score(), 0.3);
  }
  EXPECT_EQ(map_observations("counted"), counted_before + 1);

  // Acknowledged means counted: after a restart the hit is still there.
  const ServerConfig config = Config();
  StopServer();
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  EXPECT_EQ(place_dynamics("counted", place).observations(), 2u);
  v1::GetMapRequest get_map;
  get_map.set_name("counted");
  grpc::ClientContext context;
  v1::MapDescription description;
  ASSERT_TRUE(stub_->GetMap(&context, get_map, &description).ok());
  EXPECT_EQ(description.config().dynamics().count_query_hits_above(), 0.3);

  // The setting must be a finite score >= 0.
  for (double bad : {-0.5, std::nan("")}) {
    v1::MapConfig config_bad;
    config_bad.mutable_dynamics()->set_count_query_hits_above(bad);
    const grpc::Status refused = CreateMapStatus("bad", config_bad);
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << bad;
    EXPECT_NE(refused.error_message().find("config.dynamics.count_query_hits_above"),
              std::string::npos)
        << refused.error_message();
  }
}

// GetDynamics near a pose: RTAB-Map frames on a synthetic straight path (x = frame number), some
// without a pose; only the places within the radius are ranked, and the filter's bad requests
// name their field.
TEST_F(DynamicsTest, PlacesNearAPoseAreRankedAlone) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("path");
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 24; ++frame) {
    v1::Observation observation = WithObjects(frame);
    observation.clear_pose();
    if (frame % 6 != 0) {  // every sixth frame has no pose
      observation.mutable_pose()->set_x(frame);
      observation.mutable_pose()->set_y(0.5);
      observation.mutable_pose()->set_z(0);
      observation.mutable_pose()->set_qw(1);
    }
    frames.push_back(observation);
  }
  const IngestOutcome ingest = IngestAll(stub_.get(), "path", frames);
  ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
  // Near (10, 0.5, 0) within 3.5: frames 7..13 that were stored and have a pose (not 12).
  std::set<uint32_t> expected;
  for (size_t i = 0; i < ingest.responses.size(); ++i) {
    const int frame = int(i) + 1;
    if (ingest.responses[i].stored() && frame >= 7 && frame <= 13 && frame % 6 != 0) {
      expected.insert(ingest.responses[i].place_id());
    }
  }
  ASSERT_GE(expected.size(), 3u);

  v1::GetDynamicsRequest request;
  request.set_map("path");
  request.mutable_near()->set_x(10);
  request.mutable_near()->set_y(0.5);
  request.set_near_radius(3.5);
  v1::GetDynamicsResponse near;
  ASSERT_TRUE(Get(request, &near).ok());
  std::set<uint32_t> ranked;
  for (const v1::RankedPlace& place : near.places()) ranked.insert(place.place_id());
  EXPECT_EQ(ranked, expected);
  EXPECT_EQ(near.ranked(), expected.size());
  // The map aggregate is the whole map's, whatever the filter.
  EXPECT_EQ(near.map().observations(),
            uint64_t(std::count_if(ingest.responses.begin(), ingest.responses.end(),
                                   [](const auto& r) { return r.stored(); })));
  // Far from the path: nothing.
  request.mutable_near()->set_y(100);
  v1::GetDynamicsResponse far;
  ASSERT_TRUE(Get(request, &far).ok());
  EXPECT_EQ(far.places_size(), 0);
  EXPECT_EQ(far.ranked(), 0u);

  struct Case {
    std::string field;
    v1::GetDynamicsRequest request;
  };
  v1::GetDynamicsRequest base;
  base.set_map("path");
  std::vector<Case> cases;
  cases.push_back({"near_radius: must be > 0 with near", base});
  cases.back().request.mutable_near()->set_x(1);
  cases.push_back({"near: is required with near_radius", base});
  cases.back().request.set_near_radius(2);
  cases.push_back({"near_radius", base});
  cases.back().request.mutable_near()->set_x(1);
  cases.back().request.set_near_radius(-2);
  cases.push_back({"near_radius", base});
  cases.back().request.mutable_near()->set_x(1);
  cases.back().request.set_near_radius(std::nan(""));
  cases.push_back({"near: the position must be finite", base});
  cases.back().request.mutable_near()->set_x(std::nan(""));
  cases.back().request.set_near_radius(2);
  for (const Case& c : cases) {
    v1::GetDynamicsResponse response;
    const grpc::Status s = Get(c.request, &response);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << c.field;
    EXPECT_NE(s.error_message().find(c.field), std::string::npos) << s.error_message();
  }
}

}  // namespace
}  // namespace placedb::server_testing
