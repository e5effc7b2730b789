// Authentication and per-map authorization through a real server (docs/security.md): the matrix
// of every placedb.v1.PlaceDb RPC x every kind of caller, ListMaps filtering, wildcard patterns,
// the open health service, reflection on/off, messages that never hold a token, reloads (a token
// added, changed, revoked while Ingest streams are open: by Server::ReloadTokens() and by editing
// the file), the audit counters, the /metrics basic-auth check, and the principals that mutual-TLS
// client certificates name.
#include <arpa/inet.h>
#include <fcntl.h>
#include <google/protobuf/descriptor.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/security/credentials.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <future>
#include <map>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "client/connection.h"
#include "server/auth/call_auth.h"
#include "server/auth/token_store.h"
#include "server/auth/tokens.h"
#include "tests/server/server_fixture.h"
#include "tests/tls_certificates.h"

namespace placedb::server_testing {
namespace {

namespace fs = std::filesystem;
using server::auth::GenerateToken;
using server::auth::HashToken;
using server::auth::MapGrant;
using server::auth::Principal;
using server::auth::TokensFile;

std::string NewToken() {
  auto token = GenerateToken();
  EXPECT_TRUE(token.ok());
  return token.ok() ? *token : "";
}

std::string Bearer(const std::string& token) {
  return "Bearer " + token;
}

// One grpc::ClientContext with an authorization header ("" = none) and a deadline.
std::unique_ptr<grpc::ClientContext> Context(const std::string& authorization) {
  auto context = std::make_unique<grpc::ClientContext>();
  if (!authorization.empty()) context->AddMetadata("authorization", authorization);
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(60));
  return context;
}

// An open Ingest stream with its own credentials: frames are sent and answered one at a time.
class OpenStream {
 public:
  OpenStream(v1::PlaceDb::Stub* stub, const std::string& authorization, const std::string& map)
      : context_(Context(authorization)), stream_(stub->Ingest(context_.get())) {
    v1::IngestRequest header;
    header.mutable_header()->set_map(map);
    EXPECT_TRUE(stream_->Write(header));
  }
  // Sends one frame; true when it was answered (false: the stream ended).
  bool Send(const v1::Observation& observation, v1::IngestResponse* response) {
    v1::IngestRequest request;
    *request.mutable_observation() = observation;
    if (!stream_->Write(request)) return false;
    return stream_->Read(response);
  }
  grpc::Status Finish() {
    stream_->WritesDone();
    v1::IngestResponse ignored;
    while (stream_->Read(&ignored)) {
    }
    return stream_->Finish();
  }

 private:
  std::unique_ptr<grpc::ClientContext> context_;
  std::unique_ptr<grpc::ClientReaderWriter<v1::IngestRequest, v1::IngestResponse>> stream_;
};

class AuthTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    if (HasFatalFailure()) return;
    tokens_path_ = root_ + "/tokens.yaml";
    for (const char* name : {"admin", "reader", "writer", "other", "prometheus"}) {
      tokens_[name] = NewToken();
    }
    principals_ = {
        Make("admin", true, {}),
        Make("reader", false, {{"campus", true, false}}),
        Make("writer", false, {{"campus", false, true}}),
        Make("other", false, {{"warehouse-*", true, true}}),
    };
    Principal prometheus = Make("prometheus", false, {});
    prometheus.metrics = true;
    principals_.push_back(prometheus);
    SaveTokens();
  }

  Principal Make(const std::string& name, bool admin, std::vector<MapGrant> maps) {
    Principal p;
    p.name = name;
    p.token_sha256 = HashToken(tokens_.at(name));
    p.admin = admin;
    p.maps = std::move(maps);
    return p;
  }
  Principal* Find(const std::string& name) {
    for (Principal& p : principals_) {
      if (p.name == name) return &p;
    }
    return nullptr;
  }
  void SaveTokens() {
    TokensFile file;
    for (const Principal& p : principals_) ASSERT_TRUE(file.Add(p).ok()) << p.name;
    ASSERT_TRUE(file.Save(tokens_path_).ok());
  }

  void StartWithTokens(ServerConfig config) {
    config.security.tokens_file = tokens_path_;
    StartServer(config);
  }
  std::string As(const std::string& name) const { return Bearer(tokens_.at(name)); }

  grpc::Status CreateMapAs(const std::string& who, const std::string& name) {
    v1::CreateMapRequest request;
    request.set_name(name);
    v1::MapDescription response;
    return stub_->CreateMap(Context(who).get(), request, &response);
  }
  grpc::Status DeleteMapAs(const std::string& who, const std::string& name) {
    v1::DeleteMapRequest request;
    request.set_name(name);
    v1::DeleteMapResponse response;
    return stub_->DeleteMap(Context(who).get(), request, &response);
  }
  grpc::Status QueryAs(const std::string& who, const std::string& map) {
    v1::QueryRequest request;
    request.set_map(map);
    *request.mutable_observation() = RtabmapObservation(3, "probe");
    v1::QueryResponse response;
    return stub_->Query(Context(who).get(), request, &response);
  }
  std::vector<std::string> ListAs(const std::string& who, grpc::Status* status = nullptr) {
    v1::ListMapsResponse response;
    grpc::Status s = stub_->ListMaps(Context(who).get(), v1::ListMapsRequest(), &response);
    if (status) *status = s;
    std::vector<std::string> names;
    for (const auto& map : response.maps()) names.push_back(map.name());
    std::sort(names.begin(), names.end());
    return names;
  }
  IngestOutcome IngestAs(const std::string& who, const std::string& map,
                         const std::vector<v1::Observation>& observations) {
    v1::IngestHeader header;
    header.set_map(map);
    return IngestWithHeader(stub_.get(), header, observations, who);
  }

  // Everything a denied call must leave as it was: every map's statistics (through the admin)
  // and the data directory's files.
  std::string State() {
    std::string state;
    for (const std::string& name : ListAs(As("admin"))) {
      v1::GetMapRequest request;
      request.set_name(name);
      v1::MapDescription map;
      const grpc::Status status = stub_->GetMap(Context(As("admin")).get(), request, &map);
      const v1::MapStats& s = map.stats();
      state += name + ": " + std::to_string(status.error_code()) +
               " places=" + std::to_string(s.places()) +
               " kept=" + std::to_string(s.descriptors_kept()) +
               " dropped=" + std::to_string(s.descriptors_dropped()) +
               " rejected=" + std::to_string(s.invalid_rejected()) +
               " stored_invalid=" + std::to_string(s.invalid_stored()) +
               " streams=" + std::to_string(s.streams()) + "\n";
    }
    // Every file and folder, but those RocksDB rewrites on its own in a live map (a background
    // flush or compaction may run during any call, on a loaded machine too): its tables, logs
    // and MANIFEST, and with them the bytes on disk. What a call changes shows in the maps'
    // counts, the folders, ACKED and the snapshots.
    std::set<std::string> files;
    for (const auto& entry : fs::recursive_directory_iterator(root_ + "/data")) {
      const std::string relative = fs::relative(entry.path(), root_).string();
      const std::string name = entry.path().filename().string();
      const std::string extension = entry.path().extension().string();
      const bool live_map_file = relative.starts_with("data/maps/") && entry.is_regular_file();
      if (live_map_file && (extension == ".sst" || extension == ".log" || name.starts_with("LOG") ||
                            name.starts_with("OPTIONS-") || name.starts_with("MANIFEST-"))) {
        continue;
      }
      files.insert(relative);
    }
    for (const std::string& file : files) state += file + "\n";
    return state;
  }

  // Waits (bounded, generously) until `ready` holds; the watcher polls every second.
  static bool Eventually(const std::function<bool()>& ready) {
    for (int i = 0; i < 300; ++i) {
      if (ready()) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    return ready();
  }

  std::string tokens_path_;
  std::map<std::string, std::string> tokens_;
  std::vector<Principal> principals_;
};

using Code = grpc::StatusCode;

// ---- The matrix ---------------------------------------------------------------------------------

TEST_F(AuthTest, EveryRpcTimesEveryCallerGetsTheExactCode) {
  StartWithTokens(Config());
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());
  ASSERT_TRUE(CreateMapAs(As("admin"), "warehouse-1").ok());
  ASSERT_TRUE(CreateMapAs(As("admin"), "scratch").ok());
  const IngestOutcome seeded =
      IngestAs(As("admin"), "campus", {RtabmapObservation(1, "a"), RtabmapObservation(2, "a")});
  ASSERT_TRUE(seeded.status.ok()) << seeded.status.error_message();
  ASSERT_EQ(seeded.responses.size(), 2u);
  ASSERT_TRUE(seeded.responses[0].stored());
  const uint32_t place = seeded.responses[0].place_id();

  // The callers: the columns of the matrix.
  const std::vector<std::pair<std::string, std::string>> callers = {
      {"none", ""},
      {"malformed", "Basic " + tokens_.at("admin")},
      {"unknown", Bearer(NewToken())},
      {"read", As("reader")},
      {"write", As("writer")},
      {"admin", As("admin")},
      {"other_map", As("other")},
  };
  const Code U = Code::UNAUTHENTICATED, P = Code::PERMISSION_DENIED, K = Code::OK;
  struct Row {
    std::function<grpc::Status(const std::string& authorization)> call;
    std::map<std::string, Code> expected;  // read, write, admin, other_map (the rest: U)
  };
  auto unary = [this](auto method, auto request, auto response) {
    return [this, method, request, response](const std::string& authorization) mutable {
      return ((*stub_).*method)(Context(authorization).get(), request, &response);
    };
  };
  v1::CreateMapRequest create;
  create.set_name("created");
  v1::GetMapRequest get;
  get.set_name("campus");
  v1::DeleteMapRequest del;
  del.set_name("scratch");
  v1::RecoverMapRequest recover;
  recover.set_name("campus");
  recover.set_accept_data_loss(true);
  v1::ScrubMapRequest scrub;
  scrub.set_name("campus");
  v1::AdaptVocabularyRequest adapt;
  adapt.set_name("campus");
  adapt.set_depth(40);  // refused by the handler once allowed: nothing changes
  v1::RevertVocabularyRequest revert;
  revert.set_name("campus");
  v1::QueryRequest query;
  query.set_map("campus");
  *query.mutable_observation() = RtabmapObservation(3, "probe");
  v1::GetPlaceRequest get_place;
  get_place.set_map("campus");
  get_place.set_place_id(place);
  v1::ListPlacesRequest list_places;
  list_places.set_map("campus");
  v1::DeletePlaceRequest delete_place;
  delete_place.set_map("campus");
  delete_place.set_place_id(999999);  // none: the allowed caller's answer names it, nothing changes
  v1::GetDynamicsRequest dynamics;
  dynamics.set_map("campus");

  // Snapshots: admin only; a snapshot of campus to download and restore.
  v1::CreateSnapshotRequest create_snapshot;
  create_snapshot.set_map("campus");
  v1::Snapshot snapshot;
  ASSERT_TRUE(stub_->CreateSnapshot(Context(As("admin")).get(), create_snapshot, &snapshot).ok());
  v1::DeleteSnapshotRequest delete_snapshot;
  delete_snapshot.set_id("none-1");  // absent: the allowed caller gets NOT_FOUND, nothing changes
  v1::RestoreSnapshotRequest restore;
  restore.set_id(snapshot.id());
  restore.set_new_map("campus");  // taken: the allowed caller gets ALREADY_EXISTS
  auto download = [this, id = snapshot.id()](const std::string& authorization) {
    v1::DownloadSnapshotRequest request;
    request.set_id(id);
    auto context = Context(authorization);
    auto reader = stub_->DownloadSnapshot(context.get(), request);
    v1::SnapshotChunk chunk;
    while (reader->Read(&chunk)) {
    }
    return reader->Finish();
  };
  auto upload = [this](const std::string& authorization) {
    auto context = Context(authorization);
    v1::Snapshot response;
    auto writer = stub_->UploadSnapshot(context.get(), &response);
    v1::SnapshotChunk chunk;
    chunk.set_data("not an archive");
    writer->Write(chunk);
    writer->WritesDone();
    return writer->Finish();
  };

  std::map<std::string, Row> rows;
  rows["CreateSnapshot"] = {
      unary(&v1::PlaceDb::Stub::CreateSnapshot, create_snapshot, v1::Snapshot()),
      {{"read", P}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["ListSnapshots"] = {unary(&v1::PlaceDb::Stub::ListSnapshots, v1::ListSnapshotsRequest(),
                                 v1::ListSnapshotsResponse()),
                           {{"read", P}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["DeleteSnapshot"] = {
      unary(&v1::PlaceDb::Stub::DeleteSnapshot, delete_snapshot, v1::DeleteSnapshotResponse()),
      {{"read", P}, {"write", P}, {"admin", Code::NOT_FOUND}, {"other_map", P}}};
  rows["RestoreSnapshot"] = {
      unary(&v1::PlaceDb::Stub::RestoreSnapshot, restore, v1::MapDescription()),
      {{"read", P}, {"write", P}, {"admin", Code::ALREADY_EXISTS}, {"other_map", P}}};
  rows["DownloadSnapshot"] = {download,
                              {{"read", P}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["UploadSnapshot"] = {
      upload, {{"read", P}, {"write", P}, {"admin", Code::INVALID_ARGUMENT}, {"other_map", P}}};
  rows["CreateMap"] = {unary(&v1::PlaceDb::Stub::CreateMap, create, v1::MapDescription()),
                       {{"read", P}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["GetMap"] = {unary(&v1::PlaceDb::Stub::GetMap, get, v1::MapDescription()),
                    {{"read", K}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["ListMaps"] = {
      unary(&v1::PlaceDb::Stub::ListMaps, v1::ListMapsRequest(), v1::ListMapsResponse()),
      {{"read", K}, {"write", K}, {"admin", K}, {"other_map", K}}};
  rows["DeleteMap"] = {unary(&v1::PlaceDb::Stub::DeleteMap, del, v1::DeleteMapResponse()),
                       {{"read", P}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["RecoverMap"] = {
      unary(&v1::PlaceDb::Stub::RecoverMap, recover, v1::RecoverMapResponse()),
      // Allowed, and refused by the handler: campus is not damaged.
      {{"read", P}, {"write", P}, {"admin", Code::FAILED_PRECONDITION}, {"other_map", P}}};
  rows["ScrubMap"] = {unary(&v1::PlaceDb::Stub::ScrubMap, scrub, v1::ScrubReport()),
                      {{"read", P}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["AdaptVocabulary"] = {
      unary(&v1::PlaceDb::Stub::AdaptVocabulary, adapt, v1::MapVocabulary()),
      // Allowed, and refused by the handler: depth 40 is out of range.
      {{"read", P}, {"write", P}, {"admin", Code::INVALID_ARGUMENT}, {"other_map", P}}};
  rows["RevertVocabulary"] = {
      unary(&v1::PlaceDb::Stub::RevertVocabulary, revert, v1::MapVocabulary()),
      // Allowed, and refused by the handler: campus never switched vocabularies.
      {{"read", P}, {"write", P}, {"admin", Code::FAILED_PRECONDITION}, {"other_map", P}}};
  rows["Ingest"] = {[this](const std::string& authorization) {
                      return IngestAs(authorization, "campus", {RtabmapObservation(4, "b")}).status;
                    },
                    {{"read", P}, {"write", K}, {"admin", K}, {"other_map", P}}};
  rows["Query"] = {unary(&v1::PlaceDb::Stub::Query, query, v1::QueryResponse()),
                   {{"read", K}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["GetPlace"] = {unary(&v1::PlaceDb::Stub::GetPlace, get_place, v1::Place()),
                      {{"read", K}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["ListPlaces"] = {
      unary(&v1::PlaceDb::Stub::ListPlaces, list_places, v1::ListPlacesResponse()),
      {{"read", K}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["DeletePlace"] = {
      unary(&v1::PlaceDb::Stub::DeletePlace, delete_place, v1::DeletePlaceResponse()),
      {{"read", P}, {"write", Code::NOT_FOUND}, {"admin", Code::NOT_FOUND}, {"other_map", P}}};
  rows["GetDynamics"] = {
      unary(&v1::PlaceDb::Stub::GetDynamics, dynamics, v1::GetDynamicsResponse()),
      {{"read", K}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["WatchLoopClosures"] = {[this](const std::string& authorization) {
                                 v1::WatchLoopClosuresRequest request;
                                 request.set_map("campus");
                                 auto context = Context(authorization);
                                 auto reader = stub_->WatchLoopClosures(context.get(), request);
                                 v1::LoopConstraint constraint;
                                 while (reader->Read(&constraint)) {
                                 }
                                 return reader->Finish();
                               },
                               {{"read", K}, {"write", P}, {"admin", K}, {"other_map", P}}};
  rows["GetServerInfo"] = {
      unary(&v1::PlaceDb::Stub::GetServerInfo, v1::GetServerInfoRequest(), v1::ServerInfo()),
      {{"read", K}, {"write", K}, {"admin", K}, {"other_map", K}}};

  // Every RPC of the service has a row: a new RPC cannot be forgotten.
  const google::protobuf::ServiceDescriptor* service =
      v1::CreateMapRequest::descriptor()->file()->FindServiceByName("PlaceDb");
  ASSERT_NE(service, nullptr);
  size_t cells = 0;
  for (int m = 0; m < service->method_count(); ++m) {
    const std::string method(service->method(m)->name());
    auto row = rows.find(method);
    ASSERT_NE(row, rows.end()) << "placedb.v1.PlaceDb/" << method
                               << " has no row in the auth matrix (tests/server/auth_test.cc)";
    for (const auto& [label, authorization] : callers) {
      SCOPED_TRACE(method + " x " + label);
      if (method == "DeleteMap" && ListAs(As("admin")).size() < 3) {
        ASSERT_TRUE(CreateMapAs(As("admin"), "scratch").ok());  // the admin deleted it
      }
      const std::string before = State();
      const grpc::Status status = row->second.call(authorization);
      auto expected = row->second.expected.find(label);
      const Code want = expected == row->second.expected.end() ? U : expected->second;
      EXPECT_EQ(status.error_code(), want) << status.error_message();
      ++cells;
      if (status.error_code() == U || status.error_code() == P) {
        EXPECT_EQ(State(), before) << "a denied call changed something";
        EXPECT_NE(status.error_message().find(method + ": "), std::string::npos)
            << status.error_message();
        for (const auto& [name, token] : tokens_) {
          EXPECT_EQ(status.error_message().find(token), std::string::npos) << "token in message";
          EXPECT_EQ(status.error_message().find(token.substr(4, 12)), std::string::npos);
        }
      }
      if (method == "CreateMap" && status.ok()) {
        ASSERT_TRUE(DeleteMapAs(As("admin"), "created").ok());
      }
    }
    rows.erase(row);
  }
  EXPECT_TRUE(rows.empty()) << "a row for an RPC the service no longer has: "
                            << rows.begin()->first;
  EXPECT_EQ(cells, size_t(service->method_count()) * callers.size());
}

TEST_F(AuthTest, MessagesNameTheMethodAndMapNeverTheToken) {
  StartWithTokens(Config());
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());
  grpc::Status status = QueryAs("", "campus");
  EXPECT_EQ(status.error_code(), Code::UNAUTHENTICATED);
  EXPECT_EQ(status.error_message(), "Query: no credentials (send 'authorization: Bearer <token>')");
  status = DeleteMapAs("Basic dXNlcjpwYXNz", "campus");
  EXPECT_EQ(status.error_code(), Code::UNAUTHENTICATED);
  EXPECT_EQ(status.error_message(),
            "DeleteMap: malformed authorization header (expected 'Bearer <token>')");
  const std::string unknown = NewToken();
  status = QueryAs(Bearer(unknown), "campus");
  EXPECT_EQ(status.error_message(), "Query: unknown token");
  status = QueryAs(As("other"), "campus");
  EXPECT_EQ(status.error_code(), Code::PERMISSION_DENIED);
  EXPECT_EQ(status.error_message(), "Query: principal 'other' may not read map 'campus'");
  status = DeleteMapAs(As("reader"), "campus");
  EXPECT_EQ(status.error_code(), Code::PERMISSION_DENIED);
  EXPECT_EQ(status.error_message(), "DeleteMap: principal 'reader' is not an admin (map 'campus')");
  // Malformed Bearer headers.
  for (const std::string& header : {std::string("Bearer"), std::string("Bearer "),
                                    std::string("bearer  x y"), std::string("Token abc")}) {
    EXPECT_EQ(QueryAs(header, "campus").error_code(), Code::UNAUTHENTICATED) << header;
  }
  // The scheme is case-insensitive (RFC 6750).
  EXPECT_EQ(QueryAs("bearer " + tokens_.at("reader"), "campus").error_code(), Code::OK);
}

TEST_F(AuthTest, BadMapNamesAreInvalidAfterAuthenticationBeforeRights) {
  StartWithTokens(Config());
  for (const std::string& name : {std::string("../etc"), std::string("a/b"), std::string(""),
                                  std::string(65, 'x'), std::string("caf\xc3\xa9")}) {
    SCOPED_TRACE(name);
    EXPECT_EQ(QueryAs("", name).error_code(), Code::UNAUTHENTICATED);
    // The reader may not read such a map either way: the name is refused first.
    const grpc::Status status = QueryAs(As("reader"), name);
    EXPECT_EQ(status.error_code(), Code::INVALID_ARGUMENT) << status.error_message();
    EXPECT_EQ(status.error_message().rfind("Query: map: ", 0), 0u) << status.error_message();
    EXPECT_EQ(CreateMapAs(As("writer"), name).error_code(), Code::INVALID_ARGUMENT);
    EXPECT_EQ(IngestAs(As("writer"), name, {}).status.error_code(), Code::INVALID_ARGUMENT);
  }
}

TEST_F(AuthTest, ListMapsShowsOnlyReadableMapsAndWildcardsMatch) {
  StartWithTokens(Config());
  for (const char* name : {"campus", "warehouse-1", "warehouse-22", "warehouse", "yard"}) {
    ASSERT_TRUE(CreateMapAs(As("admin"), name).ok()) << name;
  }
  EXPECT_EQ(ListAs(As("admin")), (std::vector<std::string>{"campus", "warehouse", "warehouse-1",
                                                           "warehouse-22", "yard"}));
  EXPECT_EQ(ListAs(As("reader")), (std::vector<std::string>{"campus"}));
  EXPECT_EQ(ListAs(As("other")), (std::vector<std::string>{"warehouse-1", "warehouse-22"}));
  // Write only is not read.
  EXPECT_EQ(ListAs(As("writer")), (std::vector<std::string>{}));
  EXPECT_EQ(ListAs(As("prometheus")), (std::vector<std::string>{}));
  // The wildcard grants write on matching maps only.
  EXPECT_TRUE(IngestAs(As("other"), "warehouse-22", {RtabmapObservation(1, "w")}).status.ok());
  EXPECT_EQ(IngestAs(As("other"), "warehouse", {RtabmapObservation(1, "w")}).status.error_code(),
            Code::PERMISSION_DENIED);
  EXPECT_EQ(QueryAs(As("other"), "warehouse-1").error_code(), Code::OK);
  EXPECT_EQ(QueryAs(As("other"), "yard").error_code(), Code::PERMISSION_DENIED);
}

TEST_F(AuthTest, ServerInfoDetailsAreForAdmins) {
  StartWithTokens(Config());
  v1::ServerInfo admin, reader;
  ASSERT_TRUE(
      stub_->GetServerInfo(Context(As("admin")).get(), v1::GetServerInfoRequest(), &admin).ok());
  ASSERT_TRUE(
      stub_->GetServerInfo(Context(As("reader")).get(), v1::GetServerInfoRequest(), &reader).ok());
  EXPECT_EQ(reader.version(), admin.version());
  ASSERT_EQ(reader.vocabularies_size(), admin.vocabularies_size());
  ASSERT_GT(admin.vocabularies_size(), 0);
  EXPECT_EQ(reader.vocabularies(0).name(), admin.vocabularies(0).name());
  EXPECT_EQ(reader.vocabularies(0).checksum(), admin.vocabularies(0).checksum());
  EXPECT_EQ(reader.vocabularies(0).feature_type(), admin.vocabularies(0).feature_type());
  EXPECT_FALSE(admin.vocabularies(0).path().empty());
  EXPECT_GT(admin.vocabularies(0).memory_bytes(), 0u);
  EXPECT_TRUE(reader.vocabularies(0).path().empty());
  EXPECT_EQ(reader.vocabularies(0).memory_bytes(), 0u);
  EXPECT_FALSE(admin.detector().empty());
  EXPECT_TRUE(reader.detector().empty());
  EXPECT_EQ(admin.limits().worker_threads(), 2u);
  EXPECT_EQ(reader.limits().worker_threads(), 0u);
  EXPECT_EQ(reader.limits().max_message_bytes(), admin.limits().max_message_bytes());
}

TEST_F(AuthTest, HealthIsOpenWithoutAToken) {
  StartWithTokens(Config());
  std::string serving;
  const grpc::Status status = HealthCheck(channel_, &serving);
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(serving, std::string("\x08\x01", 2));  // SERVING
}

// grpc.reflection.v1alpha list_services through the generic stub: the bytes of the first
// answer, or the status when there is none.
grpc::Status ListServices(const std::shared_ptr<grpc::Channel>& channel, std::string* answer) {
  grpc::GenericStub generic(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  grpc::CompletionQueue queue;
  auto call = generic.PrepareCall(
      &context, "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo", &queue);
  void* tag = nullptr;
  bool ok = false;
  call->StartCall(reinterpret_cast<void*>(1));
  queue.Next(&tag, &ok);
  grpc::Slice request(std::string("\x3a\x01*", 3));  // list_services: "*"
  grpc::ByteBuffer bytes(&request, 1);
  call->Write(bytes, reinterpret_cast<void*>(2));
  queue.Next(&tag, &ok);
  call->WritesDone(reinterpret_cast<void*>(3));
  queue.Next(&tag, &ok);
  grpc::ByteBuffer response;
  call->Read(&response, reinterpret_cast<void*>(4));
  queue.Next(&tag, &ok);
  answer->clear();
  if (ok) {
    std::vector<grpc::Slice> slices;
    (void)response.Dump(&slices);
    for (const auto& s : slices) answer->append(reinterpret_cast<const char*>(s.begin()), s.size());
  }
  grpc::Status status;
  call->Finish(&status, reinterpret_cast<void*>(5));
  while (queue.Next(&tag, &ok) && tag != reinterpret_cast<void*>(5)) {
  }
  queue.Shutdown();
  while (queue.Next(&tag, &ok)) {
  }
  return status;
}

TEST_F(AuthTest, ReflectionFollowsTheConfigPerServer) {
  ServerConfig config = Config();
  config.security.reflection = false;
  StartWithTokens(config);
  std::string answer;
  EXPECT_EQ(ListServices(channel_, &answer).error_code(), Code::UNIMPLEMENTED);
  EXPECT_EQ(answer.find("placedb.v1.PlaceDb"), std::string::npos);
  StopServer();

  config.security.reflection = true;
  StartWithTokens(config);
  const grpc::Status status = ListServices(channel_, &answer);
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_NE(answer.find("placedb.v1.PlaceDb"), std::string::npos);
  StopServer();

  // And off again in the same process: nothing global was left on.
  config.security.reflection = false;
  StartWithTokens(config);
  EXPECT_EQ(ListServices(channel_, &answer).error_code(), Code::UNIMPLEMENTED);
}

TEST_F(AuthTest, WithoutTokensOrMutualTlsEveryCallerMayDoEverything) {
  StartServer(Config());
  EXPECT_TRUE(CreateMapAs("", "campus").ok());
  EXPECT_TRUE(CreateMapAs("Bearer whatever", "yard").ok());  // a token is ignored
  EXPECT_EQ(ListAs("").size(), 2u);
  EXPECT_TRUE(DeleteMapAs("", "yard").ok());
}

std::string Base64(const std::string& in) {
  static constexpr char kAlphabet[] =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  size_t i = 0;
  for (; i + 2 < in.size(); i += 3) {
    const uint32_t v =
        uint32_t(uint8_t(in[i])) << 16 | uint32_t(uint8_t(in[i + 1])) << 8 | uint8_t(in[i + 2]);
    for (int shift : {18, 12, 6, 0}) out += kAlphabet[(v >> shift) & 63];
  }
  if (i + 1 == in.size()) {
    const uint32_t v = uint32_t(uint8_t(in[i])) << 16;
    out += kAlphabet[(v >> 18) & 63];
    out += kAlphabet[(v >> 12) & 63];
    out += "==";
  } else if (i + 2 == in.size()) {
    const uint32_t v = uint32_t(uint8_t(in[i])) << 16 | uint32_t(uint8_t(in[i + 1])) << 8;
    for (int shift : {18, 12, 6}) out += kAlphabet[(v >> shift) & 63];
    out += "=";
  }
  return out;
}

// The HTTP status line's code of a scrape with basic auth (user:password; "" = no header).
int ScrapeStatus(int port, const std::string& credentials, std::string* reply = nullptr) {
  const std::string headers =
      credentials.empty() ? "" : "Authorization: Basic " + Base64(credentials) + "\r\n";
  const std::string got = HttpGet(port, "/metrics", headers);
  if (reply) *reply = got;
  if (got.size() < 12 || got.rfind("HTTP/1.", 0) != 0) return 0;
  return std::stoi(got.substr(9, 3));
}

TEST_F(AuthTest, MetricsNeedBasicAuthOfAPrincipalWithMetricsOrAdmin) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  StartWithTokens(config);
  const int port = server_->metrics_port();
  ASSERT_GT(port, 0);
  EXPECT_EQ(Base64("user:pass"), "dXNlcjpwYXNz");
  EXPECT_EQ(ScrapeStatus(port, ""), 401);
  EXPECT_EQ(ScrapeStatus(port, "prometheus:" + NewToken()), 401);
  EXPECT_EQ(ScrapeStatus(port, "reader:" + tokens_.at("reader")), 401);     // no metrics right
  EXPECT_EQ(ScrapeStatus(port, "admin:" + tokens_.at("prometheus")), 401);  // not its token
  EXPECT_EQ(ScrapeStatus(port, "admin:" + tokens_.at("admin")), 200);
  std::string reply;
  ASSERT_EQ(ScrapeStatus(port, "prometheus:" + tokens_.at("prometheus"), &reply), 200);
  const auto metrics = ParseMetrics(reply);
  EXPECT_EQ(MetricValue(metrics, "placedb_auth_denied_total",
                        {{"method", "metrics"}, {"reason", "unknown_token"}}),
            2);
  EXPECT_EQ(MetricValue(metrics, "placedb_auth_denied_total",
                        {{"method", "metrics"}, {"reason", "permission_denied"}}),
            1);
  // No Authorization header at all: the endpoint answers 401 before the check (not counted).
  EXPECT_TRUE(std::isnan(MetricValue(metrics, "placedb_auth_denied_total",
                                     {{"method", "metrics"}, {"reason", "missing_credentials"}})));
}

TEST_F(AuthTest, DeniedCallsAreCountedByReasonAndMethod) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  StartWithTokens(config);
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());
  (void)QueryAs("", "campus");
  (void)QueryAs("Basic x", "campus");
  (void)QueryAs(Bearer(NewToken()), "campus");
  (void)QueryAs(As("other"), "campus");
  (void)IngestAs(As("reader"), "campus", {});
  (void)IngestAs(As("reader"), "campus", {});
  std::string reply;
  ASSERT_EQ(ScrapeStatus(server_->metrics_port(), "prometheus:" + tokens_.at("prometheus"), &reply),
            200);
  const auto metrics = ParseMetrics(reply);
  auto denied = [&](const char* method, const char* reason) {
    return MetricValue(metrics, "placedb_auth_denied_total",
                       {{"method", method}, {"reason", reason}});
  };
  EXPECT_EQ(denied("Query", "missing_credentials"), 1);
  EXPECT_EQ(denied("Query", "malformed_credentials"), 1);
  EXPECT_EQ(denied("Query", "unknown_token"), 1);
  EXPECT_EQ(denied("Query", "permission_denied"), 1);
  EXPECT_EQ(denied("Ingest", "permission_denied"), 2);
  EXPECT_EQ(MetricValue(metrics, "placedb_rpc_requests_total",
                        {{"method", "Query"}, {"code", "UNAUTHENTICATED"}}),
            3);
}

// ---- Reload -------------------------------------------------------------------------------------

TEST_F(AuthTest, ReloadAddsChangesAndRevokesTokens) {
  ServerConfig config = Config();
  config.metrics_listen = "127.0.0.1:0";
  StartWithTokens(config);
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());

  // Added: works without a restart.
  tokens_["late"] = NewToken();
  principals_.push_back(Make("late", false, {{"camp*", true, false}}));
  SaveTokens();
  ASSERT_TRUE(server_->ReloadTokens().ok());
  EXPECT_EQ(QueryAs(As("late"), "campus").error_code(), Code::OK);

  // Changed: the old token fails, the new one works.
  const std::string old_token = tokens_.at("reader");
  tokens_["reader"] = NewToken();
  Find("reader")->token_sha256 = HashToken(tokens_.at("reader"));
  SaveTokens();
  ASSERT_TRUE(server_->ReloadTokens().ok());
  EXPECT_EQ(QueryAs(Bearer(old_token), "campus").error_code(), Code::UNAUTHENTICATED);
  EXPECT_EQ(QueryAs(As("reader"), "campus").error_code(), Code::OK);

  // A broken file keeps the principals, and says why.
  {
    std::ofstream broken(tokens_path_, std::ios::trunc);
    broken << "principals:\n  - name: x\n";
  }
  const Status failed = server_->ReloadTokens();
  EXPECT_EQ(failed.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(failed.message().find("principals[0] 'x'"), std::string::npos) << failed.message();
  EXPECT_EQ(QueryAs(As("reader"), "campus").error_code(), Code::OK);

  std::string reply;
  ASSERT_EQ(ScrapeStatus(server_->metrics_port(), "admin:" + tokens_.at("admin"), &reply), 200);
  const auto metrics = ParseMetrics(reply);
  EXPECT_EQ(MetricValue(metrics, "placedb_tokens_reloads_total", {{"result", "ok"}}), 2);
  EXPECT_EQ(MetricValue(metrics, "placedb_tokens_reloads_total", {{"result", "error"}}), 1);
}

// Revoked while two Ingest streams are open: the revoked caller's stream ends UNAUTHENTICATED at
// its next frame (its acknowledged frames stay); the other principal's stream goes on. `reload`
// applies the new file (ReloadTokens, or the watcher).
void RevokeDuringStreams(v1::PlaceDb::Stub* stub, const std::string& writer,
                         const std::string& admin, const std::function<void()>& revoke,
                         const std::function<uint64_t()>& places) {
  OpenStream revoked(stub, writer, "campus");
  OpenStream kept(stub, admin, "campus");
  v1::IngestResponse response;
  ASSERT_TRUE(revoked.Send(RtabmapObservation(1, "r"), &response));
  EXPECT_TRUE(response.stored());
  ASSERT_TRUE(kept.Send(RtabmapObservation(2, "k"), &response));
  EXPECT_TRUE(response.stored());
  EXPECT_EQ(places(), 2u);

  revoke();

  EXPECT_FALSE(revoked.Send(RtabmapObservation(3, "r"), &response));
  const grpc::Status ended = revoked.Finish();
  EXPECT_EQ(ended.error_code(), grpc::StatusCode::UNAUTHENTICATED) << ended.error_message();
  EXPECT_EQ(ended.error_message(), "Ingest: unknown token");
  ASSERT_TRUE(kept.Send(RtabmapObservation(4, "k"), &response));
  EXPECT_TRUE(response.stored());
  const grpc::Status finished = kept.Finish();
  EXPECT_TRUE(finished.ok()) << finished.error_message();
  EXPECT_EQ(places(), 3u);  // the revoked stream's acknowledged frame stays
}

uint64_t PlacesAs(v1::PlaceDb::Stub* stub, const std::string& admin, const std::string& map) {
  v1::GetMapRequest request;
  request.set_name(map);
  v1::MapDescription description;
  EXPECT_TRUE(stub->GetMap(Context(admin).get(), request, &description).ok());
  return description.stats().places();
}

TEST_F(AuthTest, RevokedTokenEndsItsOpenStreamOnReload) {
  StartWithTokens(Config());
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());
  const std::string writer = As("writer"), admin = As("admin");
  RevokeDuringStreams(
      stub_.get(), writer, admin,
      [&] {
        principals_.erase(principals_.begin() + 2);  // writer
        SaveTokens();
        ASSERT_TRUE(server_->ReloadTokens().ok());
      },
      [&] { return PlacesAs(stub_.get(), admin, "campus"); });
}

TEST_F(AuthTest, RevokedTokenEndsItsOpenStreamWhenTheFileChanges) {
  StartWithTokens(Config());
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());
  const std::string writer = As("writer"), admin = As("admin");
  RevokeDuringStreams(
      stub_.get(), writer, admin,
      [&] {
        principals_.erase(principals_.begin() + 2);  // writer
        SaveTokens();
        // The watcher (every second) applies it: wait until a new call sees it.
        ASSERT_TRUE(Eventually(
            [&] { return CreateMapAs(writer, "x").error_code() == Code::UNAUTHENTICATED; }));
      },
      [&] { return PlacesAs(stub_.get(), admin, "campus"); });
}

TEST_F(AuthTest, LostRightEndsTheStreamWithPermissionDenied) {
  StartWithTokens(Config());
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());
  OpenStream stream(stub_.get(), As("writer"), "campus");
  v1::IngestResponse response;
  ASSERT_TRUE(stream.Send(RtabmapObservation(1, "w"), &response));
  Find("writer")->maps = {{"campus", true, false}};  // read only now
  SaveTokens();
  ASSERT_TRUE(server_->ReloadTokens().ok());
  EXPECT_FALSE(stream.Send(RtabmapObservation(2, "w"), &response));
  const grpc::Status ended = stream.Finish();
  EXPECT_EQ(ended.error_code(), Code::PERMISSION_DENIED);
  EXPECT_EQ(ended.error_message(), "Ingest: principal 'writer' may not write map 'campus'");
  EXPECT_EQ(PlacesAs(stub_.get(), As("admin"), "campus"), 1u);
}

TEST_F(AuthTest, AStreamOutlivesAReloadThatKeepsItsRight) {
  StartWithTokens(Config());
  ASSERT_TRUE(CreateMapAs(As("admin"), "campus").ok());
  OpenStream stream(stub_.get(), As("writer"), "campus");
  v1::IngestResponse response;
  ASSERT_TRUE(stream.Send(RtabmapObservation(1, "w"), &response));
  tokens_["late"] = NewToken();
  principals_.push_back(Make("late", false, {}));
  SaveTokens();
  ASSERT_TRUE(server_->ReloadTokens().ok());
  ASSERT_TRUE(stream.Send(RtabmapObservation(2, "w"), &response));
  EXPECT_TRUE(response.stored());
  EXPECT_TRUE(stream.Finish().ok());
}

// ---- placedb-server tokens ---------------------------------------------------------------------

struct Finished {
  int status = -1;
  std::string out, err;
};

// Runs the placedb-server binary with `args` (shell words, quoted by the caller).
Finished RunServerBinary(const std::string& args, const std::string& dir) {
  Finished run;
  const std::string err_path = dir + "/stderr.txt";
  const std::string command = std::string(PLACEDB_SERVER_BINARY) + " " + args + " 2>" + err_path;
  FILE* pipe = popen(command.c_str(), "r");
  if (!pipe) return run;
  char buffer[4096];
  size_t n;
  while ((n = fread(buffer, 1, sizeof buffer, pipe)) > 0) run.out.append(buffer, n);
  const int status = pclose(pipe);
  run.status = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  std::ifstream err(err_path);
  run.err.assign(std::istreambuf_iterator<char>(err), std::istreambuf_iterator<char>());
  return run;
}

TEST_F(AuthTest, TokensCommandWritesHashesAndPrintsTheTokenOnce) {
  const std::string dir = root_ + "/cli";
  fs::create_directories(dir);
  const std::string file = dir + "/tokens.yaml";
  const std::string flag = " --tokens-file " + file;

  Finished ops = RunServerBinary("tokens add ops --role admin" + flag, dir);
  ASSERT_EQ(ops.status, 0) << ops.err;
  // stdout is the token and nothing else.
  ASSERT_EQ(ops.out.size(), 4u + 43u + 1u) << ops.out;
  const std::string ops_token = ops.out.substr(0, ops.out.size() - 1);
  EXPECT_EQ(ops_token.rfind("pdb_", 0), 0u);
  EXPECT_NE(ops.err.find("added principal 'ops' (admin)"), std::string::npos) << ops.err;
  EXPECT_EQ((fs::status(file).permissions() & fs::perms::all),
            fs::perms::owner_read | fs::perms::owner_write);

  Finished robot = RunServerBinary(
      "tokens add robot-7 --read 'warehouse-*' --write 'warehouse-*' --read campus" + flag, dir);
  ASSERT_EQ(robot.status, 0) << robot.err;
  const std::string robot_token = robot.out.substr(0, robot.out.size() - 1);
  Finished scraper = RunServerBinary("tokens add prometheus --role metrics" + flag, dir);
  ASSERT_EQ(scraper.status, 0) << scraper.err;

  // The file holds hashes, never a token.
  const std::string text = testing::ReadFileBytes(file);
  EXPECT_EQ(text.find(ops_token), std::string::npos);
  EXPECT_EQ(text.find(robot_token), std::string::npos);
  EXPECT_NE(text.find(HashToken(ops_token)), std::string::npos);

  Finished duplicate = RunServerBinary("tokens add ops" + flag, dir);
  EXPECT_EQ(duplicate.status, 1);
  EXPECT_TRUE(duplicate.out.empty());
  EXPECT_NE(duplicate.err.find("principal 'ops' exists"), std::string::npos) << duplicate.err;
  EXPECT_EQ(RunServerBinary("tokens add 'bad name'" + flag, dir).status, 1);
  EXPECT_EQ(RunServerBinary("tokens add x --role root" + flag, dir).status, 2);

  Finished list = RunServerBinary("tokens list" + flag, dir);
  ASSERT_EQ(list.status, 0) << list.err;
  EXPECT_NE(list.out.find("robot-7\tread warehouse-*, write warehouse-*, read campus"),
            std::string::npos)
      << list.out;
  EXPECT_EQ(list.out.find(HashToken(ops_token)), std::string::npos);  // never a whole hash

  // The server takes the tokens.
  tokens_path_ = file;
  StartWithTokens(Config());
  ASSERT_TRUE(CreateMapAs(Bearer(ops_token), "warehouse-3").ok());
  ASSERT_TRUE(CreateMapAs(Bearer(ops_token), "campus").ok());
  EXPECT_EQ(QueryAs(Bearer(robot_token), "warehouse-3").error_code(), Code::OK);
  EXPECT_EQ(DeleteMapAs(Bearer(robot_token), "campus").error_code(), Code::PERMISSION_DENIED);

  // Rotate: same rights, new token; the old one stops at the reload.
  Finished rotated = RunServerBinary("tokens rotate robot-7" + flag, dir);
  ASSERT_EQ(rotated.status, 0) << rotated.err;
  const std::string new_token = rotated.out.substr(0, rotated.out.size() - 1);
  EXPECT_NE(new_token, robot_token);
  ASSERT_TRUE(server_->ReloadTokens().ok());
  EXPECT_EQ(QueryAs(Bearer(robot_token), "warehouse-3").error_code(), Code::UNAUTHENTICATED);
  EXPECT_EQ(QueryAs(Bearer(new_token), "warehouse-3").error_code(), Code::OK);
  EXPECT_EQ(QueryAs(Bearer(new_token), "campus").error_code(), Code::OK);
  // The file's order is kept: robot-7 is still the second entry.
  list = RunServerBinary("tokens list" + flag, dir);
  EXPECT_EQ(list.out.find("robot-7"), list.out.find('\n') + 1) << list.out;

  // Revoke.
  Finished revoked = RunServerBinary("tokens revoke robot-7" + flag, dir);
  ASSERT_EQ(revoked.status, 0) << revoked.err;
  EXPECT_TRUE(revoked.out.empty());
  ASSERT_TRUE(server_->ReloadTokens().ok());
  EXPECT_EQ(QueryAs(Bearer(new_token), "warehouse-3").error_code(), Code::UNAUTHENTICATED);
  EXPECT_EQ(RunServerBinary("tokens revoke robot-7" + flag, dir).status, 1);
  EXPECT_EQ(RunServerBinary("tokens list --tokens-file " + dir + "/missing.yaml", dir).status, 1);
}

// The real binary: SIGHUP reloads the tokens file (and does not end the process); SIGTERM still
// shuts it down cleanly.
TEST_F(AuthTest, SighupReloadsTheTokensFileOfTheServerBinary) {
  const int port = testing::UnusedLoopbackPort();  // the server binds it next
  const std::string log = root_ + "/server.log";
  const std::string listen = "127.0.0.1:" + std::to_string(port);
  // Everything the child needs is made before fork: it only calls async-signal-safe functions.
  const std::string vocabulary = "default=" + testing::DefaultVocabularyPath();
  const std::string data = root_ + "/data";
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    const int out = open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    dup2(out, 1);
    dup2(out, 2);
    execl(PLACEDB_SERVER_BINARY, PLACEDB_SERVER_BINARY, "--listen", listen.c_str(), "--data-dir",
          data.c_str(), "--tokens-file", tokens_path_.c_str(), "--metrics-listen", "off",
          "--console-listen", "off", "--vocabulary", vocabulary.c_str(), "--threads", "1",
          static_cast<char*>(nullptr));
    _exit(127);
  }
  auto channel = grpc::CreateChannel(listen, grpc::InsecureChannelCredentials());
  auto stub = v1::PlaceDb::NewStub(channel);
  auto list_as = [&](const std::string& who) {
    v1::ListMapsResponse response;
    return stub->ListMaps(Context(who).get(), v1::ListMapsRequest(), &response).error_code();
  };
  ASSERT_TRUE(Eventually([&] { return list_as(As("reader")) == Code::OK; }))
      << testing::ReadFileBytes(log);

  tokens_["late"] = NewToken();
  principals_.push_back(Make("late", false, {}));
  SaveTokens();
  ASSERT_EQ(kill(pid, SIGHUP), 0);
  ASSERT_TRUE(Eventually([&] { return list_as(As("late")) == Code::OK; }));
  EXPECT_TRUE(Eventually([&] {
    return testing::ReadFileBytes(log).find("received SIGHUP: reloading the tokens file") !=
           std::string::npos;
  })) << testing::ReadFileBytes(log);
  EXPECT_EQ(list_as(As("reader")), Code::OK);  // the process is alive and serving

  ASSERT_EQ(kill(pid, SIGTERM), 0);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  EXPECT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0) << testing::ReadFileBytes(log);
}

// ---- Client certificates (mutual TLS) ----------------------------------------------------------
//
// The principal a verified client certificate names, through the real server over a real mutual
// TLS handshake on loopback (certificates from tests/tls_certificates.h), with the CLI's own
// connection code presenting the certificate (and a bearer token, when given).

class MutualTlsAuthTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    const testing::TestCertificates& c = testing::SharedTestCertificates();
    stranger_ =
        testing::IssueClientCertificate(c, "stranger", "stranger", {"stranger.fleet.internal"});
  }
  // A server requiring client certificates from the test CA; `tokens_file` "" = none.
  void StartMutualTls(const std::string& tokens_file) {
    const testing::TestCertificates& c = testing::SharedTestCertificates();
    ServerConfig config = Config();
    config.tls = {
        .cert_file = c.server_cert, .key_file = c.server_key, .client_ca_file = c.ca_cert};
    config.security.tokens_file = tokens_file;
    StartServer(config);
  }
  // A connection presenting `certificate` ({cert, key}) and sending `token` ("" = none).
  std::optional<client::Connection> Connect(const std::pair<std::string, std::string>& certificate,
                                            const std::string& token = "") {
    client::ConnectionOptions options;
    options.address = "localhost:" + std::to_string(server_->port());
    options.tls = true;
    options.ca_cert = testing::SharedTestCertificates().ca_cert;
    options.cert = certificate.first;
    options.key = certificate.second;
    options.token = token;
    options.timeout_s = 30;
    std::string error;
    std::optional<client::Connection> connection = client::Connection::Open(options, &error);
    EXPECT_TRUE(connection) << error;
    return connection;
  }
  static grpc::Status CreateMapOver(client::Connection& connection, const std::string& map) {
    v1::CreateMapRequest request;
    request.set_name(map);
    v1::MapDescription description;
    auto context = connection.NewContext();
    return connection.stub()->CreateMap(context.get(), request, &description);
  }
  static grpc::Status GetMapOver(client::Connection& connection, const std::string& map) {
    v1::GetMapRequest request;
    request.set_name(map);
    v1::MapDescription description;
    auto context = connection.NewContext();
    return connection.stub()->GetMap(context.get(), request, &description);
  }
  static std::pair<std::string, std::string> Robot8() {
    const testing::TestCertificates& c = testing::SharedTestCertificates();
    return {c.client_cert, c.client_key};  // CN robot-8.fleet.internal
  }
  static std::pair<std::string, std::string> Rogue() {
    const testing::TestCertificates& c = testing::SharedTestCertificates();
    return {c.other_client_cert, c.other_client_key};  // the same CN from another CA
  }

  std::pair<std::string, std::string> stranger_;  // CN stranger, DNS SAN stranger.fleet.internal
};

TEST_F(MutualTlsAuthTest, WithoutATokensFileEveryVerifiedCertificateMayDoEverything) {
  StartMutualTls("");
  auto robot8 = Connect(Robot8());
  ASSERT_TRUE(robot8);
  EXPECT_TRUE(CreateMapOver(*robot8, "campus").ok());
  auto stranger = Connect(stranger_);
  ASSERT_TRUE(stranger);
  EXPECT_TRUE(GetMapOver(*stranger, "campus").ok());
  // A certificate from another CA never gets past the handshake.
  auto rogue = Connect(Rogue());
  ASSERT_TRUE(rogue);
  EXPECT_EQ(GetMapOver(*rogue, "campus").error_code(), Code::UNAVAILABLE);
}

TEST_F(MutualTlsAuthTest, WithATokensFileCertificatesNamePrincipals) {
  const std::string ops_token = NewToken();
  TokensFile file;
  Principal by_cn;
  by_cn.name = "robot-8-cert";
  by_cn.certificate_names = {"robot-8.fleet.internal"};
  by_cn.maps = {{"camp*", true, false}};
  ASSERT_TRUE(file.Add(by_cn).ok());
  Principal by_san;
  by_san.name = "stranger-by-san";
  by_san.certificate_names = {"stranger.fleet.internal"};
  by_san.maps = {{"yard", true, false}};
  ASSERT_TRUE(file.Add(by_san).ok());
  Principal ops;
  ops.name = "ops";
  ops.token_sha256 = HashToken(ops_token);
  ops.admin = true;
  ASSERT_TRUE(file.Add(ops).ok());
  const std::string tokens_path = root_ + "/tokens.yaml";
  ASSERT_TRUE(file.Save(tokens_path).ok());
  StartMutualTls(tokens_path);

  // A bearer token wins over the certificate: the admin creates the maps over mutual TLS.
  auto as_ops = Connect(Robot8(), ops_token);
  ASSERT_TRUE(as_ops);
  ASSERT_TRUE(CreateMapOver(*as_ops, "campus").ok());
  ASSERT_TRUE(CreateMapOver(*as_ops, "yard").ok());
  auto unknown = Connect(Robot8(), NewToken());
  ASSERT_TRUE(unknown);
  EXPECT_EQ(GetMapOver(*unknown, "campus").error_code(), Code::UNAUTHENTICATED);

  // The certificate alone: its CN names robot-8-cert, which may read camp* only.
  auto robot8 = Connect(Robot8());
  ASSERT_TRUE(robot8);
  EXPECT_TRUE(GetMapOver(*robot8, "campus").ok());
  grpc::Status status = GetMapOver(*robot8, "yard");
  EXPECT_EQ(status.error_code(), Code::PERMISSION_DENIED);
  EXPECT_NE(status.error_message().find("'robot-8-cert'"), std::string::npos)
      << status.error_message();
  EXPECT_EQ(CreateMapOver(*robot8, "campus-2").error_code(), Code::PERMISSION_DENIED);
  // A DNS SAN names stranger-by-san.
  auto stranger = Connect(stranger_);
  ASSERT_TRUE(stranger);
  EXPECT_TRUE(GetMapOver(*stranger, "yard").ok());
  status = GetMapOver(*stranger, "campus");
  EXPECT_EQ(status.error_code(), Code::PERMISSION_DENIED);
  EXPECT_NE(status.error_message().find("'stranger-by-san'"), std::string::npos)
      << status.error_message();

  // Revoked: the certificate no longer names a principal.
  ASSERT_TRUE(file.Remove("stranger-by-san").ok());
  ASSERT_TRUE(file.Save(tokens_path).ok());
  ASSERT_TRUE(server_->ReloadTokens().ok());
  status = GetMapOver(*stranger, "yard");
  EXPECT_EQ(status.error_code(), Code::UNAUTHENTICATED);
  EXPECT_EQ(status.error_message(), "GetMap: client certificate 'stranger' names no principal");
}

}  // namespace
}  // namespace placedb::server_testing
