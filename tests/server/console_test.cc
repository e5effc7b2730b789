// The web console's JSON API (server/console/console.h) against a real server on loopback, with
// a cpp-httplib client: every endpoint, bad input with its HTTP status and no change to the map,
// tokens, the Host rule, and the console's place in the safe default.
#include "server/console/console.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <httplib.h>

#include <atomic>
#include <chrono>
#include <fstream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "proto/names.h"
#include "server/auth/tokens.h"
#include "server/net/transport_security.h"
#include "tests/server/server_fixture.h"
#include "tests/tls_certificates.h"

namespace placedb::server_testing {
namespace {

using nlohmann::json;

struct Reply {
  int status = 0;
  std::string content_type;
  std::string body;
  json Json() const { return json::parse(body, nullptr, /*allow_exceptions=*/false); }
};

std::string ToJson(const google::protobuf::Message& message) {
  std::string text;
  EXPECT_TRUE(google::protobuf::util::MessageToJsonString(message, &text).ok());
  return text;
}

class ConsoleTest : public ServerTest {
 protected:
  ServerConfig ConsoleConfig() {
    ServerConfig config = Config();
    config.console_listen = "127.0.0.1:0";
    return config;
  }

  // A map of RTAB-Map frames 1..places from agent "a", and a second agent's frame.
  void Populate(const std::string& map, int places) {
    CreateMap(map);
    std::vector<v1::Observation> frames;
    for (int frame = 1; frame <= places; ++frame) frames.push_back(RtabmapObservation(frame, "a"));
    const IngestOutcome outcome = IngestAll(stub_.get(), map, frames);
    ASSERT_TRUE(outcome.status.ok()) << outcome.status.error_message();
  }

  Reply Send(const std::string& method, const std::string& path, const std::string& body,
             httplib::Headers headers = {}, const std::string& content_type = "application/json") {
    httplib::Client client("127.0.0.1", server_->console_port());
    client.set_read_timeout(std::chrono::seconds(60));
    httplib::Result result = method == "GET" ? client.Get(path, headers)
                                             : client.Post(path, headers, body, content_type);
    Reply reply;
    if (!result) {
      ADD_FAILURE() << method << " " << path << ": " << httplib::to_string(result.error());
      return reply;
    }
    reply.status = result->status;
    reply.content_type = result->get_header_value("Content-Type");
    reply.body = result->body;
    return reply;
  }
  Reply Call(const std::string& method, const std::string& request_json,
             httplib::Headers headers = {}) {
    return Send("POST", "/api/v1/" + method, request_json, std::move(headers));
  }

  // What must not change after a bad request: the places and a query's answer.
  std::pair<uint64_t, std::string> MapState(const std::string& map) {
    v1::QueryResponse response;
    EXPECT_TRUE(Query(map, RtabmapObservation(4, "probe"), &response, 3).ok());
    std::string ranking;
    for (const v1::Match& match : response.matches()) {
      ranking += std::to_string(match.place_id()) + ":" + std::to_string(match.score()) + " ";
    }
    return {Stats(map).places(), ranking};
  }

  v1::QueryRequest QueryOf(const std::string& map, int frame) {
    v1::QueryRequest request;
    request.set_map(map);
    *request.mutable_observation() = RtabmapObservation(frame, "probe");
    request.mutable_options()->set_top_k(3);
    request.mutable_options()->set_include_correspondences(true);
    return request;
  }
};

TEST(ConsoleStatusTest, GrpcCodesMapToHttpStatuses) {
  using Code = grpc::StatusCode;
  const std::vector<std::pair<Code, int>> expected = {
      {Code::INVALID_ARGUMENT, 400},   {Code::UNAUTHENTICATED, 401},
      {Code::PERMISSION_DENIED, 403},  {Code::NOT_FOUND, 404},
      {Code::ALREADY_EXISTS, 409},     {Code::FAILED_PRECONDITION, 409},
      {Code::RESOURCE_EXHAUSTED, 429}, {Code::DATA_LOSS, 500},
      {Code::INTERNAL, 500},           {Code::UNAVAILABLE, 503},
      {Code::UNIMPLEMENTED, 501}};
  for (const auto& [code, status] : expected) {
    EXPECT_EQ(server::HttpStatusOf(code), status) << int(code);
  }
}

TEST(ConsoleConfigTest, FileEnvironmentFlagsAndTheExample) {
  const std::string dir = testing::MakeTempDir("placedb-console-config");
  const std::string path = dir + "/placedb.yaml";
  std::ofstream(path) << "console_listen: 127.0.0.1:7000\n"
                         "console_threads: 3\n"
                         "console_request_timeout_ms: 900\n"
                         "console_max_request_bytes: 2048\n";
  std::map<std::string, std::string> env = {{"PLACEDB_CONSOLE_LISTEN", "127.0.0.1:7100"}};
  auto getenv = [&](const char* name) -> const char* {
    auto it = env.find(name);
    return it == env.end() ? nullptr : it->second.c_str();
  };
  const char* argv[] = {"placedb-server", "--config", path.c_str()};
  auto parsed = server::ParseCommandLine(3, argv, getenv);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->config.console_listen, "127.0.0.1:7100");  // environment over file
  EXPECT_EQ(parsed->config.console_threads, 3);
  EXPECT_EQ(parsed->config.console_request_timeout_ms, 900u);
  EXPECT_EQ(parsed->config.console_max_request_bytes, 2048u);
  ServerConfig again;  // --print-config round trip
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(parsed->config), &again).ok());
  EXPECT_EQ(server::ConfigToYaml(again), server::ConfigToYaml(parsed->config));

  const char* off[] = {"placedb-server", "--console-listen", "off"};
  parsed = server::ParseCommandLine(3, off, getenv);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->config.console_listen, "");  // flag over environment
  env = {{"PLACEDB_CONSOLE_LISTEN", "off"}};
  const char* plain[] = {"placedb-server"};
  parsed = server::ParseCommandLine(1, plain, getenv);
  ASSERT_TRUE(parsed.ok());
  EXPECT_EQ(parsed->config.console_listen, "");

  for (const auto& [yaml, key] : std::vector<std::pair<std::string, std::string>>{
           {"console_listen: nowhere\n", "console_listen"},
           {"console_threads: 1\n", "console_threads"},
           {"console_request_timeout_ms: 5\n", "console_request_timeout_ms"},
           {"console_max_request_bytes: 10\n", "console_max_request_bytes"},
           {"console_tls: true\n", "console_tls"}}) {
    ServerConfig bad;
    ASSERT_TRUE(server::ApplyConfigYaml(yaml, &bad).ok()) << yaml;
    const Status invalid = server::ValidateServerConfig(bad);
    EXPECT_EQ(invalid.code(), StatusCode::kInvalidArgument) << yaml;
    EXPECT_NE(invalid.message().find(key), std::string::npos) << invalid.message();
  }
  // The example config shows the defaults.
  ServerConfig example;
  ASSERT_TRUE(
      server::ApplyConfigFile(std::string(PLACEDB_SOURCE_DIR) + "/server/placedb.yaml", &example)
          .ok());
  const ServerConfig defaults;
  EXPECT_EQ(example.console_listen, defaults.console_listen);
  EXPECT_EQ(example.console_tls, defaults.console_tls);
  EXPECT_EQ(example.console_threads, defaults.console_threads);
  EXPECT_EQ(example.console_request_timeout_ms, defaults.console_request_timeout_ms);
  EXPECT_EQ(example.console_max_request_bytes, defaults.console_max_request_bytes);
}

TEST_F(ConsoleTest, EveryEndpointAnswersAsGrpcDoes) {
  ASSERT_NO_FATAL_FAILURE(StartServer(ConsoleConfig()));
  ASSERT_GT(server_->console_port(), 0);
  ASSERT_NO_FATAL_FAILURE(Populate("office", 8));

  // GetServerInfo carries the console's URL as bound.
  Reply info = Call("GetServerInfo", "{}");
  ASSERT_EQ(info.status, 200) << info.body;
  EXPECT_EQ(info.content_type, "application/json");
  EXPECT_EQ(info.Json()["console_url"],
            "http://127.0.0.1:" + std::to_string(server_->console_port()) + "/");

  Reply maps = Call("ListMaps", "{}");
  ASSERT_EQ(maps.status, 200) << maps.body;
  ASSERT_EQ(maps.Json()["maps"].size(), 1u);
  EXPECT_EQ(maps.Json()["maps"][0]["name"], "office");

  // The proto's own field names, zeros printed, 64-bit integers as strings (protobuf JSON).
  Reply map = Call("GetMap", R"({"name": "office"})");
  ASSERT_EQ(map.status, 200) << map.body;
  EXPECT_EQ(map.Json()["stats"]["places"], "8");
  EXPECT_TRUE(map.Json()["stats"].contains("descriptors_dropped"));

  Reply place = Call("GetPlace", R"({"map": "office", "place_id": 3, "include_features": true})");
  ASSERT_EQ(place.status, 200) << place.body;
  EXPECT_EQ(place.Json()["metadata"]["sequence"], "3");
  EXPECT_GT(place.Json()["features"]["keypoints"].size(), 20u);

  Reply dynamics = Call("GetDynamics", R"({"map": "office"})");
  EXPECT_EQ(dynamics.status, 200) << dynamics.body;

  // A query as a browser sends it: the JPEG base64 in encoded_image.data.
  Reply query = Call("Query", ToJson(QueryOf("office", 5)));
  ASSERT_EQ(query.status, 200) << query.body;
  const json answer = query.Json();
  ASSERT_FALSE(answer["matches"].empty());
  EXPECT_EQ(answer["matches"][0]["metadata"]["sequence"], "5");
  EXPECT_TRUE(answer["timings"].contains("total_ms"));
  EXPECT_TRUE(answer["counts"].contains("kept"));

  // ListPlaces: newest first once the server implements it (i20-places); until then the
  // generated handler's UNIMPLEMENTED, as 501.
  Reply places = Call("ListPlaces", R"({"map": "office", "limit": 3})");
  ASSERT_TRUE(places.status == 200 || places.status == 501) << places.body;
  if (places.status == 200) {
    ASSERT_EQ(places.Json()["places"].size(), 3u);
    EXPECT_EQ(places.Json()["places"][0]["place_id"], 8);
  } else {
    EXPECT_EQ(places.Json()["code"], "UNIMPLEMENTED");
  }

  // The thumbnail route: a map that keeps none answers 404 with the reason; one that keeps them
  // answers the JPEG GetPlace returns.
  Reply none = Send("GET", "/api/v1/maps/office/places/3/thumbnail.jpg", "");
  EXPECT_EQ(none.status, 404) << none.body;
  EXPECT_EQ(none.Json()["code"], "NOT_FOUND");
  v1::MapConfig with_thumbnails;
  with_thumbnails.mutable_thumbnails()->set_enabled(true);
  CreateMap("lobby", with_thumbnails);
  ASSERT_TRUE(IngestAll(stub_.get(), "lobby", {RtabmapObservation(9, "b")}).status.ok());
  Reply jpeg = Send("GET", "/api/v1/maps/lobby/places/1/thumbnail.jpg", "");
  ASSERT_EQ(jpeg.status, 200) << jpeg.body;
  EXPECT_EQ(jpeg.content_type, "image/jpeg");
  grpc::ClientContext context;
  v1::GetPlaceRequest get;
  get.set_map("lobby");
  get.set_place_id(1);
  get.set_include_thumbnail(true);
  v1::Place stored;
  ASSERT_TRUE(stub_->GetPlace(&context, get, &stored).ok());
  EXPECT_EQ(jpeg.body, stored.thumbnail().jpeg());
  EXPECT_EQ(jpeg.body.substr(0, 2), "\xFF\xD8");

  // The pages, embedded, with a policy that loads nothing from elsewhere.
  Reply index = Send("GET", "/", "");
  ASSERT_EQ(index.status, 200);
  EXPECT_NE(index.body.find("/console.js"), std::string::npos);
  EXPECT_EQ(index.content_type, "text/html; charset=utf-8");
  Reply script = Send("GET", "/console.js", "");
  ASSERT_EQ(script.status, 200);
  EXPECT_NE(script.body.find("/api/v1/"), std::string::npos);
  EXPECT_EQ(Send("GET", "/nothing.html", "").status, 404);
}

// The pages name enum values from the server's table (GET /enum-names.json), which must give every
// value name the JSON API can print the proto's name for it (proto/names.h), (name) option
// included, never a second spelling.
TEST_F(ConsoleTest, EnumNamesAreTheProtosNames) {
  ASSERT_NO_FATAL_FAILURE(StartServer(ConsoleConfig()));
  ASSERT_NO_FATAL_FAILURE(Populate("office", 2));
  Reply reply = Send("GET", "/enum-names.json", "");
  ASSERT_EQ(reply.status, 200) << reply.body;
  EXPECT_EQ(reply.content_type, "application/json");
  const json names = reply.Json();
  ASSERT_TRUE(names.is_object()) << reply.body;
  // "(missing)" rather than a const lookup of an absent key (undefined in nlohmann::json).
  auto name_of = [&names](const std::string& type, const std::string& value) {
    if (!names.contains(type) || !names[type].is_object()) return std::string("(missing)");
    return names[type].value(value, std::string("(missing)"));
  };

  const google::protobuf::FileDescriptor* file = v1::MapConfig::descriptor()->file();
  EXPECT_EQ(names.size(), size_t(file->enum_type_count()));
  for (int e = 0; e < file->enum_type_count(); ++e) {
    const google::protobuf::EnumDescriptor* type = file->enum_type(e);
    ASSERT_TRUE(names.contains(type->name())) << type->name();
    EXPECT_EQ(names[type->name()].size(), size_t(type->value_count())) << type->name();
    for (int v = 0; v < type->value_count(); ++v) {
      const google::protobuf::EnumValueDescriptor* value = type->value(v);
      EXPECT_EQ(name_of(type->name(), value->name()), wire::EnumValueName(type, value->number()))
          << value->full_name();
    }
  }
  // Where the (name) option or the class table differs from the value name's suffix.
  EXPECT_EQ(name_of("BoxSource", "BOX_SOURCE_UNSPECIFIED"), "agent");
  EXPECT_EQ(name_of("Scoring", "SCORING_CHI_SQUARE"), "chi2");
  EXPECT_EQ(name_of("CocoClass", "COCO_CLASS_TRAFFIC_LIGHT"), wire::DynamicClassName(9));
  EXPECT_EQ(name_of("CocoClass", "COCO_CLASS_PERSON"), "person");

  // The values the maps view names, as the JSON API prints them for a real map.
  Reply maps = Call("ListMaps", "{}");
  ASSERT_EQ(maps.status, 200) << maps.body;
  const json summary = maps.Json()["maps"][0];
  ASSERT_TRUE(summary.is_object()) << maps.body;
  EXPECT_EQ(name_of("MapState", summary.value("state", "")), "available");
  EXPECT_EQ(name_of("FeatureType", summary.value("feature_type", "")), "orb");
  Reply map = Call("GetMap", R"({"name": "office"})");
  ASSERT_EQ(map.status, 200) << map.body;
  const json detection = map.Json()["config"]["detection"];
  ASSERT_TRUE(detection.contains("box_source")) << map.body;
  const std::string box_source = detection["box_source"];
  v1::BoxSource parsed;
  ASSERT_TRUE(v1::BoxSource_Parse(box_source, &parsed)) << box_source;
  EXPECT_EQ(name_of("BoxSource", box_source), wire::EnumName(parsed));
}

TEST_F(ConsoleTest, BadRequestsGetTheirStatusAndChangeNothing) {
  ServerConfig config = ConsoleConfig();
  config.console_max_request_bytes = 64 * 1024;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  ASSERT_NO_FATAL_FAILURE(Populate("office", 6));
  const auto before = MapState("office");
  ASSERT_EQ(before.first, 6u);

  v1::QueryRequest garbage = QueryOf("office", 2);
  garbage.mutable_observation()->mutable_encoded_image()->set_data("not an image at all");
  struct Case {
    std::string name;
    std::string method;  // "" = a raw path
    std::string path;
    std::string body;
    int status;
    std::string code;
    std::string message;  // must appear in the message
  };
  const std::string huge = R"({"name": ")" + std::string(100 * 1024, 'x') + R"("})";
  const std::vector<Case> cases = {
      {"unknown map", "GetMap", "", R"({"name": "nowhere"})", 404, "NOT_FOUND", "nowhere"},
      {"unknown map query", "Query", "", ToJson(QueryOf("nowhere", 2)), 404, "NOT_FOUND",
       "nowhere"},
      {"undecodable image", "Query", "", ToJson(garbage), 400, "INVALID_ARGUMENT",
       "observation.encoded_image.data"},
      {"body over the limit", "GetMap", "", huge, 413, "RESOURCE_EXHAUSTED",
       "console_max_request_bytes"},
      {"bad paging", "GetDynamics", "", R"({"map": "office", "limit": 5000})", 400,
       "INVALID_ARGUMENT", "limit"},
      {"malformed JSON", "GetMap", "", R"({"name": )", 400, "INVALID_ARGUMENT",
       "placedb.v1.GetMapRequest"},
      {"misspelt field", "GetMap", "", R"({"nmae": "office"})", 400, "INVALID_ARGUMENT", "nmae"},
      {"wrong type", "GetPlace", "", R"({"map": "office", "place_id": "three"})", 400,
       "INVALID_ARGUMENT", "place_id"},
      {"bad map name", "GetMap", "", R"({"name": "../etc"})", 400, "INVALID_ARGUMENT", "name"},
      {"not on the allow-list", "DeleteMap", "", R"({"name": "office"})", 404, "NOT_FOUND",
       "not served over HTTP"},
      {"admin method", "CreateMap", "", R"({"name": "other"})", 404, "NOT_FOUND",
       "not served over HTTP"},
      {"unknown place thumbnail", "", "/api/v1/maps/office/places/99/thumbnail.jpg", "", 404,
       "NOT_FOUND", "99"},
      {"thumbnail of an unknown map", "", "/api/v1/maps/nowhere/places/1/thumbnail.jpg", "", 404,
       "NOT_FOUND", "nowhere"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    const Reply reply = c.method.empty() ? Send("GET", c.path, "") : Call(c.method, c.body);
    EXPECT_EQ(reply.status, c.status) << reply.body;
    EXPECT_EQ(reply.Json()["code"], c.code) << reply.body;
    EXPECT_NE(reply.Json().value("message", "").find(c.message), std::string::npos) << reply.body;
    EXPECT_EQ(MapState("office"), before);
  }
  // ListPlaces' paging once implemented (i20-places), else UNIMPLEMENTED.
  const Reply paging = Call("ListPlaces", R"({"map": "office", "limit": 5000})");
  EXPECT_TRUE(paging.status == 400 || paging.status == 501) << paging.body;
  // Not a JSON request, and not a POST.
  EXPECT_EQ(Send("POST", "/api/v1/GetMap", "name=office", {}, "text/plain").status, 415);
  EXPECT_EQ(Send("GET", "/api/v1/GetMap", "").status, 405);
  EXPECT_EQ(MapState("office"), before);
}

TEST_F(ConsoleTest, TokensApplyAsOnGrpc) {
  using server::auth::GenerateToken;
  using server::auth::HashToken;
  using server::auth::Principal;
  const std::string reader_token = *GenerateToken(), other_token = *GenerateToken();
  const std::string admin_token = *GenerateToken();
  server::auth::TokensFile file;
  Principal admin;
  admin.name = "admin";
  admin.token_sha256 = HashToken(admin_token);
  admin.admin = true;
  Principal reader;
  reader.name = "reader";
  reader.token_sha256 = HashToken(reader_token);
  reader.maps = {{"office", true, false}};
  Principal other;
  other.name = "other";
  other.token_sha256 = HashToken(other_token);
  other.maps = {{"warehouse-*", true, true}};
  for (const Principal& p : {admin, reader, other}) ASSERT_TRUE(file.Add(p).ok());
  const std::string tokens_path = root_ + "/tokens.yaml";
  ASSERT_TRUE(file.Save(tokens_path).ok());

  ServerConfig config = ConsoleConfig();
  config.security.tokens_file = tokens_path;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  {
    grpc::ClientContext context;
    context.AddMetadata("authorization", "Bearer " + admin_token);
    v1::CreateMapRequest request;
    request.set_name("office");
    v1::MapDescription description;
    ASSERT_TRUE(stub_->CreateMap(&context, request, &description).ok());
  }
  auto as = [](const std::string& token) {
    return httplib::Headers{{"Authorization", "Bearer " + token}};
  };
  const std::string get = R"({"name": "office"})";

  Reply missing = Call("GetMap", get);
  EXPECT_EQ(missing.status, 401);
  EXPECT_EQ(missing.Json()["code"], "UNAUTHENTICATED");
  EXPECT_NE(missing.body.find("no credentials"), std::string::npos) << missing.body;
  Reply wrong = Call("GetMap", get, as(*GenerateToken()));
  EXPECT_EQ(wrong.status, 401);
  EXPECT_NE(wrong.body.find("unknown token"), std::string::npos) << wrong.body;
  EXPECT_EQ(Call("GetMap", get, {{"Authorization", "Basic abc"}}).status, 401);
  Reply denied = Call("GetMap", get, as(other_token));
  EXPECT_EQ(denied.status, 403);
  EXPECT_EQ(denied.Json()["code"], "PERMISSION_DENIED");
  EXPECT_NE(denied.body.find("may not read map 'office'"), std::string::npos) << denied.body;
  EXPECT_EQ(Call("GetMap", get, as(reader_token)).status, 200);
  // The dynamics page's call needs the same right.
  const std::string dynamics = R"({"map": "office"})";
  EXPECT_EQ(Call("GetDynamics", dynamics).status, 401);
  EXPECT_EQ(Call("GetDynamics", dynamics, as(other_token)).status, 403);
  EXPECT_EQ(Call("GetDynamics", dynamics, as(reader_token)).status, 200);

  // ListMaps shows a caller only its maps; GetServerInfo hides the server's files from non-admins.
  EXPECT_EQ(Call("ListMaps", "{}", as(reader_token)).Json()["maps"].size(), 1u);
  EXPECT_EQ(Call("ListMaps", "{}", as(other_token)).Json()["maps"].size(), 0u);
  const json info = Call("GetServerInfo", "{}", as(reader_token)).Json();
  EXPECT_EQ(info["vocabularies"][0]["path"], "");
  // The pages themselves are public (they hold no data); a host name is fine with tokens.
  EXPECT_EQ(Send("GET", "/", "", {{"Host", "console.example"}}).status, 200);
}

// The dynamics page's calls: GetDynamics over HTTP for a map of frames with person and car boxes
// (the totals, the hours, a class's ranking, as gRPC answers them), /enum-numbers.json naming the
// class ids, and a missing map refused with 404.
TEST_F(ConsoleTest, DynamicsOfARealMapAsGrpcAnswers) {
  ASSERT_NO_FATAL_FAILURE(StartServer(ConsoleConfig()));
  CreateMap("street");
  // Frames at three hours of a past day: a person on every frame, a car on every third.
  const int64_t day_ns = 86'400'000'000'000;
  const int64_t midnight_ns = (std::chrono::duration_cast<std::chrono::nanoseconds>(
                                   std::chrono::system_clock::now().time_since_epoch())
                                       .count() /
                                   day_ns -
                               2) *
                              day_ns;
  const uint32_t hours[] = {7, 12, 18};
  std::vector<v1::Observation> frames;
  for (int frame = 1; frame <= 9; ++frame) {
    v1::Observation observation = RtabmapObservation(frame, "rover");
    observation.set_timestamp_ns(midnight_ns + int64_t(hours[frame % 3]) * 3'600'000'000'000 +
                                 frame * 1'000'000'000LL);
    v1::Box* person = observation.add_boxes();
    person->set_class_name("person");
    person->set_confidence(0.9f);
    person->mutable_rect()->set_width(float(20 * frame));
    person->mutable_rect()->set_height(200);
    if (frame % 3 == 0) {
      v1::Box* car = observation.add_boxes();
      car->set_class_name("car");
      car->set_confidence(0.8f);
      car->mutable_rect()->set_x(400);
      car->mutable_rect()->set_y(300);
      car->mutable_rect()->set_width(200);
      car->mutable_rect()->set_height(150);
    }
    frames.push_back(std::move(observation));
  }
  const IngestOutcome ingest = IngestAll(stub_.get(), "street", frames);
  ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
  std::vector<uint32_t> car_places;
  for (size_t i = 0; i < ingest.responses.size(); ++i) {
    if (ingest.responses[i].stored() && frames[i].boxes_size() > 1) {
      car_places.push_back(ingest.responses[i].place_id());
    }
  }
  ASSERT_FALSE(car_places.empty());

  // The totals and the hours, as the page asks for them first.
  Reply totals = Call("GetDynamics", R"({"map": "street", "limit": 1})");
  ASSERT_EQ(totals.status, 200) << totals.body;
  const json map = totals.Json()["map"];
  grpc::ClientContext context;
  v1::GetDynamicsRequest request;
  request.set_map("street");
  request.set_limit(1);
  v1::GetDynamicsResponse expected;
  ASSERT_TRUE(stub_->GetDynamics(&context, request, &expected).ok());
  EXPECT_EQ(map["observations"], std::to_string(expected.map().observations()));
  EXPECT_GT(expected.map().observations(), 0u);
  EXPECT_DOUBLE_EQ(map["mean_coverage"].get<double>(), expected.map().mean_coverage());
  std::map<int, std::string> class_frames;
  for (const json& c : map["classes"]) class_frames[c["class_id"].get<int>()] = c["frames"];
  EXPECT_EQ(class_frames[0], std::to_string(expected.map().observations()));  // every place
  EXPECT_EQ(class_frames[2], std::to_string(car_places.size()));
  std::set<uint32_t> hours_seen;
  for (const json& bin : map["hours"]) hours_seen.insert(bin["hour"].get<uint32_t>());
  EXPECT_EQ(hours_seen, (std::set<uint32_t>{7, 12, 18}));

  // The class ranking by name: the car places first, each in every one of its frames.
  Reply ranking =
      Call("GetDynamics",
           R"({"map": "street", "measure": "DYNAMICS_MEASURE_CLASS_SHARE", "class_name": "car",)"
           R"( "limit": 24, "include_statistics": true})");
  ASSERT_EQ(ranking.status, 200) << ranking.body;
  const json places = ranking.Json()["places"];
  ASSERT_GT(places.size(), car_places.size());
  std::set<uint32_t> top;
  for (size_t i = 0; i < car_places.size(); ++i) {
    top.insert(places[i]["place_id"].get<uint32_t>());
    EXPECT_DOUBLE_EQ(places[i]["score"].get<double>(), 1.0) << places[i].dump();
    EXPECT_TRUE(places[i]["statistics"].contains("classes")) << places[i].dump();
  }
  EXPECT_EQ(top, std::set<uint32_t>(car_places.begin(), car_places.end()));
  EXPECT_DOUBLE_EQ(places[car_places.size()]["score"].get<double>(), 0.0);

  // The names the page gives class ids: the proto's, by number.
  Reply numbers = Send("GET", "/enum-numbers.json", "");
  ASSERT_EQ(numbers.status, 200) << numbers.body;
  EXPECT_EQ(numbers.content_type, "application/json");
  const json coco = numbers.Json()["CocoClass"];
  ASSERT_TRUE(coco.is_object()) << numbers.body;
  EXPECT_EQ(coco.value("0", ""), "person");
  EXPECT_EQ(coco.value("2", ""), "car");
  EXPECT_EQ(coco.value("9", ""), wire::DynamicClassName(9));
  EXPECT_EQ(numbers.Json()["BoxSource"].value("0", ""), "agent");

  // A missing map, and a class that is none.
  Reply missing = Call("GetDynamics", R"({"map": "nowhere"})");
  EXPECT_EQ(missing.status, 404) << missing.body;
  EXPECT_EQ(missing.Json()["code"], "NOT_FOUND");
  EXPECT_NE(missing.Json().value("message", "").find("nowhere"), std::string::npos) << missing.body;
  Reply unknown_class = Call(
      "GetDynamics",
      R"({"map": "street", "measure": "DYNAMICS_MEASURE_CLASS_SHARE", "class_name": "dragon"})");
  EXPECT_EQ(unknown_class.status, 400) << unknown_class.body;
  EXPECT_NE(unknown_class.Json().value("message", "").find("dragon"), std::string::npos)
      << unknown_class.body;
}

// HTTP workers and gRPC handlers call the same service at once: every answer is the serial one.
TEST_F(ConsoleTest, ConcurrentHttpAndGrpcQueriesAgree) {
  ASSERT_NO_FATAL_FAILURE(StartServer(ConsoleConfig()));
  ASSERT_NO_FATAL_FAILURE(Populate("office", 6));
  const std::string request = ToJson(QueryOf("office", 4));
  auto top_of = [](const std::string& body) {
    const json answer = json::parse(body, nullptr, false);
    if (answer.is_discarded() || answer["matches"].empty()) return std::string("none");
    return answer["matches"][0]["place_id"].dump();
  };
  const Reply serial = Call("Query", request);
  ASSERT_EQ(serial.status, 200) << serial.body;
  const std::string expected = top_of(serial.body);
  std::atomic<int> http_agree{0}, grpc_agree{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&] {
      for (int i = 0; i < 3; ++i) {
        const Reply reply = Call("Query", request);
        if (reply.status == 200 && top_of(reply.body) == expected) ++http_agree;
        v1::QueryResponse response;
        if (Query("office", RtabmapObservation(4, "probe"), &response, 3).ok() &&
            response.matches_size() > 0 &&
            std::to_string(response.matches(0).place_id()) == expected) {
          ++grpc_agree;
        }
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  EXPECT_EQ(http_agree.load(), 12);
  EXPECT_EQ(grpc_agree.load(), 12);
}

// console_tls with a client CA and a tokens file: the browser's certificate names its principal
// (here by its URI SAN), as on the gRPC port; without a certificate there is no connection.
TEST_F(ConsoleTest, HttpsClientCertificateNamesThePrincipal) {
  const testing::TestCertificates& certs = testing::SharedTestCertificates();
  using server::auth::Principal;
  const std::string admin_token = *server::auth::GenerateToken();
  Principal admin;
  admin.name = "admin";
  admin.token_sha256 = server::auth::HashToken(admin_token);
  admin.admin = true;
  Principal robot;
  robot.name = "robot";
  robot.certificate_names = {"spiffe://fleet/robot-8"};
  robot.maps = {{"office", true, false}};
  server::auth::TokensFile file;
  ASSERT_TRUE(file.Add(admin).ok());
  ASSERT_TRUE(file.Add(robot).ok());
  ASSERT_TRUE(file.Save(root_ + "/tokens.yaml").ok());

  ServerConfig config = ConsoleConfig();
  config.tls = {certs.server_cert, certs.server_key, certs.ca_cert};
  config.console_tls = true;
  config.security.tokens_file = root_ + "/tokens.yaml";
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  ASSERT_GT(server_->console_port(), 0);

  auto get_map = [&](const std::string& name, bool with_certificate) {
    auto client = with_certificate
                      ? std::make_unique<httplib::SSLClient>("127.0.0.1", server_->console_port(),
                                                             certs.client_cert, certs.client_key)
                      : std::make_unique<httplib::SSLClient>("127.0.0.1", server_->console_port());
    client->set_ca_cert_path(certs.ca_cert);
    client->enable_server_certificate_verification(true);
    client->set_read_timeout(std::chrono::seconds(30));
    auto result =
        client->Post("/api/v1/GetMap", R"({"name": ")" + name + R"("})", "application/json");
    Reply reply;
    if (result) {
      reply.status = result->status;
      reply.body = result->body;
    }
    return reply;
  };
  // No map exists: an admitted call reaches the handler (404), a refused one stops at
  // authorization (403).
  Reply allowed = get_map("office", true);
  EXPECT_EQ(allowed.status, 404) << allowed.body;  // admitted: the handler says it is not there
  EXPECT_EQ(allowed.Json()["code"], "NOT_FOUND");
  Reply denied = get_map("yard", true);
  EXPECT_EQ(denied.status, 403) << denied.body;
  EXPECT_NE(denied.body.find("principal 'robot' may not read map 'yard'"), std::string::npos)
      << denied.body;
  EXPECT_EQ(get_map("office", false).status, 0);  // the handshake needs a client certificate
  EXPECT_EQ(server::PeerCertificateNames(static_cast<const void*>(nullptr)).size(), 0u);
}

TEST_F(ConsoleTest, UnauthenticatedConsoleAnswersOnlyByAddress) {
  ASSERT_NO_FATAL_FAILURE(StartServer(ConsoleConfig()));
  CreateMap("office");
  const std::string port = std::to_string(server_->console_port());
  // A page of another site whose name resolves to 127.0.0.1 (DNS rebinding) reads nothing.
  Reply rebound = Send("POST", "/api/v1/ListMaps", "{}", {{"Host", "attacker.example:" + port}});
  EXPECT_EQ(rebound.status, 403);
  EXPECT_NE(rebound.body.find("host name"), std::string::npos) << rebound.body;
  EXPECT_EQ(Send("POST", "/api/v1/ListMaps", "{}", {{"Host", "localhost:" + port}}).status, 200);
  EXPECT_EQ(Send("POST", "/api/v1/ListMaps", "{}", {{"Host", "[::1]:" + port}}).status, 200);
}

TEST_F(ConsoleTest, NonLoopbackConsoleNeedsAuthentication) {
  ServerConfig config = Config();
  config.console_listen = "0.0.0.0:0";
  auto refused = Server::Start(config);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("console_listen = 0.0.0.0:0"), std::string::npos)
      << refused.status().ToString();
}

TEST_F(ConsoleTest, ConsoleOffMeansNoListenerAndNoUrl) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));  // the fixture turns the console off
  EXPECT_EQ(server_->console_port(), 0);
  grpc::ClientContext context;
  v1::ServerInfo info;
  ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
  EXPECT_EQ(info.console_url(), "");
}

}  // namespace
}  // namespace placedb::server_testing
