// Map names over the wire: every RPC that takes a map name refuses a name that breaks the rule
// (core/base/map_name.h) with INVALID_ARGUMENT naming the request field, before any storage is
// touched: the data directory's file tree is the same afterwards and the map a refused name
// resembles ("loop\0x", "loop/../loop") is untouched.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <functional>
#include <set>
#include <string>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

using namespace std::string_literals;
namespace fs = std::filesystem;

// Every path under `root`, relative, with a trailing '/' for directories.
std::set<std::string> Tree(const std::string& root) {
  std::set<std::string> paths;
  for (const auto& entry : fs::recursive_directory_iterator(root)) {
    std::string path = fs::relative(entry.path(), root).string();
    if (entry.is_directory()) path += '/';
    paths.insert(path);
  }
  return paths;
}

// Names that break the rule, as a client can send them (proto3 strings are valid UTF-8; other
// bytes are refused by the request parser before any handler runs: untrusted_input_test).
std::vector<std::string> BadNames() {
  return {""s,
          "."s,
          ".."s,
          "../evil"s,
          "../../escape"s,
          "loop/../loop"s,
          "a/b"s,
          "/etc/passwd"s,
          "/tmp"s,
          "loop\0"s,
          "loop\0/../x"s,
          "a\0b"s,
          "\x7f"s,
          "a\nb"s,
          "caf\xc3\xa9"s,
          "\xe5\x9c\xb0\xe5\x9b\xbe"s,
          "-loop"s,
          ".loop"s,
          " loop"s,
          "loop "s,
          "two words"s,
          "a\\b"s,
          std::string(65, 'a'),
          std::string(5000, 'b')};
}

struct Call {
  const char* method;
  const char* field;  // the request field the message must name
  std::function<grpc::Status(const std::string& name)> run;
};

TEST_F(ServerTest, EveryRpcRefusesBadMapNamesBeforeStorage) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  CreateMap("loop");
  ASSERT_TRUE(IngestAll(stub_.get(), "loop", {RtabmapObservation(1, "a")}).status.ok());
  v1::PlaceDb::Stub* stub = stub_.get();
  const v1::Observation observation = RtabmapObservation(2, "a");

  const std::vector<Call> calls = {
      {"CreateMap", "name", [&](const std::string& name) { return CreateMapStatus(name); }},
      {"GetMap", "name",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::GetMapRequest request;
         request.set_name(name);
         v1::MapDescription response;
         return stub->GetMap(&context, request, &response);
       }},
      {"DeleteMap", "name",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::DeleteMapRequest request;
         request.set_name(name);
         v1::DeleteMapResponse response;
         return stub->DeleteMap(&context, request, &response);
       }},
      {"RecoverMap", "name",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::RecoverMapRequest request;
         request.set_name(name);
         request.set_accept_data_loss(true);
         v1::RecoverMapResponse response;
         return stub->RecoverMap(&context, request, &response);
       }},
      {"ScrubMap", "name",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::ScrubMapRequest request;
         request.set_name(name);
         v1::ScrubReport response;
         return stub->ScrubMap(&context, request, &response);
       }},
      {"Query", "map",
       [&](const std::string& name) {
         v1::QueryResponse response;
         return Query(name, observation, &response);
       }},
      {"GetPlace", "map",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::GetPlaceRequest request;
         request.set_map(name);
         request.set_place_id(1);
         v1::Place response;
         return stub->GetPlace(&context, request, &response);
       }},
      {"ListPlaces", "map",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::ListPlacesRequest request;
         request.set_map(name);
         v1::ListPlacesResponse response;
         return stub->ListPlaces(&context, request, &response);
       }},
      {"DeletePlace", "map",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::DeletePlaceRequest request;
         request.set_map(name);
         request.set_place_id(1);
         v1::DeletePlaceResponse response;
         return stub->DeletePlace(&context, request, &response);
       }},
      {"GetDynamics", "map",
       [&](const std::string& name) {
         grpc::ClientContext context;
         v1::GetDynamicsRequest request;
         request.set_map(name);
         v1::GetDynamicsResponse response;
         return stub->GetDynamics(&context, request, &response);
       }},
      {"Ingest", "header.map",
       [&](const std::string& name) { return IngestAll(stub, name, {observation}).status; }},
  };

  const std::set<std::string> before = Tree(root_);
  ASSERT_TRUE(before.count("data/maps/loop/")) << "the data directory is not where expected";
  for (const Call& call : calls) {
    for (const std::string& name : BadNames()) {
      SCOPED_TRACE(std::string(call.method) + " " + name.substr(0, 70));
      const grpc::Status status = call.run(name);
      EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
      EXPECT_EQ(status.error_message().rfind(std::string(call.field) + ": map name \"", 0), 0u)
          << status.error_message();
    }
  }
  EXPECT_EQ(Tree(root_), before);

  // The map the bad names resemble is as it was.
  EXPECT_EQ(Stats("loop").places(), 1u);
  grpc::ClientContext context;
  v1::ListMapsResponse maps;
  ASSERT_TRUE(stub_->ListMaps(&context, {}, &maps).ok());
  ASSERT_EQ(maps.maps_size(), 1);
  EXPECT_EQ(maps.maps(0).name(), "loop");
}

// The longest valid name and the full alphabet work end to end (the rule is not stricter than
// it says).
TEST_F(ServerTest, ValidNamesAtTheEdgesOfTheRuleWork) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  for (const std::string& name : {std::string(64, 'm'), "Az09_.-"s, "7"s}) {
    SCOPED_TRACE(name);
    EXPECT_TRUE(CreateMapStatus(name).ok());
    EXPECT_TRUE(IngestAll(stub_.get(), name, {RtabmapObservation(1, "a")}).status.ok());
    EXPECT_EQ(Stats(name).places(), 1u);
    grpc::ClientContext context;
    v1::DeleteMapRequest request;
    request.set_name(name);
    v1::DeleteMapResponse response;
    EXPECT_TRUE(stub_->DeleteMap(&context, request, &response).ok());
  }
}

}  // namespace
}  // namespace placedb::server_testing
