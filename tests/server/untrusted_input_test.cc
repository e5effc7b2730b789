// What a real server does with input it must not trust: damaged images (cut short, random scan
// data, a frame header that claims another size, damaged PNGs) through Ingest and Query;
// requests that are not valid protobuf (truncated, invalid UTF-8 in a string) sent as raw bytes
// to a unary method and to an Ingest stream; and error messages and GetServerInfo, which must not
// show the server's absolute paths.
#include <grpcpp/generic/generic_stub.h>
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <regex>
#include <string>
#include <vector>

#include "server/rpc/parsing_service.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

constexpr int kInvalidArgument = int(grpc::StatusCode::INVALID_ARGUMENT);

std::string CamVidPath(const std::string& frame) {
  return testing::SharedDir() + "/data/camvid/images/" + frame + ".jpg";
}

// ---- Damaged images, made here from real ones -----------------------------------------------

size_t AfterMarker(const std::string& jpeg, uint8_t code) {
  for (size_t i = 2; i + 1 < jpeg.size(); ++i) {
    if (uint8_t(jpeg[i]) == 0xFF && uint8_t(jpeg[i + 1]) == code) return i + 2;
  }
  ADD_FAILURE() << "no marker " << int(code);
  return 0;
}

std::string RandomScan(std::string jpeg) {
  const size_t sos = AfterMarker(jpeg, 0xDA);
  const size_t scan = sos + ((size_t(uint8_t(jpeg[sos])) << 8) | uint8_t(jpeg[sos + 1]));
  const size_t bytes = jpeg.size() - 2 - scan;
  std::mt19937 rng(7);
  for (size_t i = scan + bytes / 4; i < scan + 3 * bytes / 4; ++i) jpeg[i] = char(rng() & 0xFF);
  return jpeg;
}

std::string OtherHeight(std::string jpeg, uint32_t height) {
  const size_t sof = AfterMarker(jpeg, 0xC0);
  jpeg[sof + 3] = char(height >> 8);
  jpeg[sof + 4] = char(height & 0xFF);
  return jpeg;
}

struct Damaged {
  std::string what;
  std::string bytes;
  std::string message_start;  // of the error after "observation.encoded_image.data: "
};

std::vector<Damaged> DamagedImages() {
  const std::string jpeg = testing::ReadFileBytes(CamVidPath("0001TP_006690"));
  const std::string png =
      EncodePng(cv::imread(CamVidPath("0001TP_006720"), cv::IMREAD_GRAYSCALE));  // a real frame
  std::string flipped = png;
  flipped[png.size() / 2] = char(flipped[png.size() / 2] ^ 0x01);
  return {
      {"JPEG cut to half", jpeg.substr(0, jpeg.size() / 2),
       "JPEG data is truncated (libjpeg: Premature end of JPEG file)"},
      {"JPEG with random scan data", RandomScan(jpeg), "JPEG data is corrupt (libjpeg: "},
      {"JPEG header claiming 720 rows", OtherHeight(jpeg, 720), "JPEG data is"},
      {"JPEG header claiming 180 rows", OtherHeight(jpeg, 180), "JPEG data is"},
      {"PNG cut to half", png.substr(0, png.size() / 2), "PNG data is truncated"},
      {"PNG with a flipped bit", flipped, "PNG data is corrupt"},
  };
}

class UntrustedInputTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    if (HasFatalFailure()) return;
    StartServer(Config());
    CreateMap("m");
    // One good frame first: the damaged ones must leave it the only place.
    auto good = IngestAll(stub_.get(), "m", {JpegObservation(CamVidPath("0001TP_006690"), "a", 1)});
    ASSERT_TRUE(good.status.ok()) << good.status.error_message();
    ASSERT_EQ(good.responses.size(), 1u);
    ASSERT_TRUE(good.responses[0].stored()) << good.responses[0].DebugString();
    ASSERT_EQ(Stats("m").places(), 1u);
  }
};

TEST_F(UntrustedInputTest, DamagedImagesAreRefusedByIngestAndQuery) {
  const std::vector<Damaged> damaged = DamagedImages();
  std::vector<v1::Observation> observations;
  for (size_t i = 0; i < damaged.size(); ++i) {
    v1::Observation observation;
    observation.set_agent_id("a");
    observation.set_sequence(10 + i);
    observation.mutable_encoded_image()->set_data(damaged[i].bytes);
    observations.push_back(observation);
  }
  auto ingest = IngestAll(stub_.get(), "m", observations);
  ASSERT_TRUE(ingest.status.ok()) << ingest.status.error_message();
  ASSERT_EQ(ingest.responses.size(), damaged.size());
  for (size_t i = 0; i < damaged.size(); ++i) {
    const v1::IngestResponse& response = ingest.responses[i];
    EXPECT_FALSE(response.stored()) << damaged[i].what;
    EXPECT_EQ(response.error().code(), kInvalidArgument) << damaged[i].what;
    const std::string prefix = "observation.encoded_image.data: " + damaged[i].message_start;
    EXPECT_EQ(response.error().message().rfind(prefix, 0), 0u)
        << damaged[i].what << ": " << response.error().message();

    v1::QueryResponse query;
    const grpc::Status status = Query("m", observations[i], &query);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << damaged[i].what;
    EXPECT_EQ(status.error_message().rfind(prefix, 0), 0u)
        << damaged[i].what << ": " << status.error_message();
  }
  EXPECT_EQ(Stats("m").places(), 1u);

  // A damaged mask and a damaged 16-bit depth PNG are refused with their field.
  v1::Observation masked = JpegObservation(CamVidPath("0001TP_006750"), "a", 30);
  const std::string mask = EncodePng(cv::Mat(360, 480, CV_8U, cv::Scalar(0)));
  masked.set_dynamic_mask_png(mask.substr(0, mask.size() - 20));
  v1::Observation depth = JpegObservation(CamVidPath("0001TP_006750"), "a", 31);
  const std::string png16 = EncodePng(cv::Mat(360, 480, CV_16U, cv::Scalar(1500)));
  depth.mutable_depth()->set_png16(png16 + "trailing");
  auto more = IngestAll(stub_.get(), "m", {masked, depth});
  ASSERT_EQ(more.responses.size(), 2u);
  EXPECT_EQ(more.responses[0].error().message().rfind(
                "observation.dynamic_mask_png: PNG data is truncated", 0),
            0u)
      << more.responses[0].error().message();
  EXPECT_EQ(more.responses[1].error().message(),
            "observation.depth.png16: PNG data has 8 bytes after its IEND chunk (trailing data is "
            "refused)");
  EXPECT_EQ(Stats("m").places(), 1u);
}

// ---- Requests that are not valid protobuf ---------------------------------------------------

grpc::ByteBuffer Buffer(const std::string& bytes) {
  grpc::Slice slice(bytes);
  return grpc::ByteBuffer(&slice, 1);
}

std::string Bytes(const grpc::ByteBuffer& buffer) {
  std::vector<grpc::Slice> slices;
  (void)buffer.Dump(&slices);
  std::string out;
  for (const auto& s : slices) out.append(reinterpret_cast<const char*>(s.begin()), s.size());
  return out;
}

// Raw bytes to any method of the server, as a client with another protobuf library (or none)
// could send them.
class RawClient {
 public:
  explicit RawClient(std::shared_ptr<grpc::Channel> channel) : stub_(std::move(channel)) {}

  grpc::Status Unary(const std::string& method, const std::string& request,
                     std::string* response = nullptr) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
    grpc::CompletionQueue cq;
    auto call =
        stub_.PrepareUnaryCall(&context, "/placedb.v1.PlaceDb/" + method, Buffer(request), &cq);
    call->StartCall();
    grpc::ByteBuffer reply;
    grpc::Status status;
    call->Finish(&reply, &status, Tag(1));
    Next(&cq, 1);
    if (response) *response = Bytes(reply);
    return status;
  }

  // An Ingest stream of raw messages; the responses read before the stream ended.
  grpc::Status Ingest(const std::vector<std::string>& messages,
                      std::vector<v1::IngestResponse>* responses) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    grpc::CompletionQueue cq;
    auto call = stub_.PrepareCall(&context, "/placedb.v1.PlaceDb/Ingest", &cq);
    call->StartCall(Tag(1));
    EXPECT_TRUE(Next(&cq, 1));
    for (const std::string& message : messages) {
      call->Write(Buffer(message), Tag(2));
      if (!Next(&cq, 2)) break;  // the server ended the stream
    }
    call->WritesDone(Tag(3));
    Next(&cq, 3);
    while (true) {
      grpc::ByteBuffer reply;
      call->Read(&reply, Tag(4));
      if (!Next(&cq, 4)) break;
      v1::IngestResponse response;
      EXPECT_TRUE(response.ParseFromString(Bytes(reply)));
      responses->push_back(response);
    }
    grpc::Status status;
    call->Finish(&status, Tag(5));
    Next(&cq, 5);
    return status;
  }

 private:
  static void* Tag(intptr_t n) { return reinterpret_cast<void*>(n); }
  static bool Next(grpc::CompletionQueue* cq, intptr_t expected) {
    void* tag = nullptr;
    bool ok = false;
    EXPECT_TRUE(cq->Next(&tag, &ok));
    EXPECT_EQ(reinterpret_cast<intptr_t>(tag), expected);
    return ok;
  }

  grpc::GenericStub stub_;
};

// `message` serialised, with `from` replaced by `to` (same length) in its bytes.
std::string Patched(const google::protobuf::Message& message, const std::string& from,
                    const std::string& to) {
  std::string bytes = message.SerializeAsString();
  const size_t at = bytes.find(from);
  EXPECT_NE(at, std::string::npos);
  EXPECT_EQ(from.size(), to.size());
  if (at != std::string::npos) bytes.replace(at, from.size(), to);
  return bytes;
}

std::vector<std::string> MapNames(v1::PlaceDb::Stub* stub) {
  grpc::ClientContext context;
  v1::ListMapsResponse maps;
  EXPECT_TRUE(stub->ListMaps(&context, v1::ListMapsRequest(), &maps).ok());
  std::vector<std::string> names;
  for (const auto& map : maps.maps()) names.push_back(map.name());
  return names;
}

TEST_F(UntrustedInputTest, MalformedUnaryRequestsAreInvalidArgumentWithAReason) {
  RawClient raw(channel_);
  v1::CreateMapRequest create;
  create.set_name("mapx");
  create.mutable_config()->set_vocabulary("default");

  // A valid request through the raw path works (and is answered with a parseable message).
  std::string reply;
  ASSERT_TRUE(raw.Unary(
                     "GetMap",
                     [] {
                       v1::GetMapRequest get;
                       get.set_name("m");
                       return get.SerializeAsString();
                     }(),
                     &reply)
                  .ok());
  v1::MapDescription description;
  ASSERT_TRUE(description.ParseFromString(reply));
  EXPECT_EQ(description.name(), "m");
  EXPECT_EQ(description.stats().places(), 1u);

  // Truncated: the config's length says more bytes than remain.
  const std::string bytes = create.SerializeAsString();
  grpc::Status status = raw.Unary("CreateMap", bytes.substr(0, bytes.size() - 3));
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message(),
            "request is not a valid placedb.v1.CreateMapRequest: the data is truncated (field "
            "config (2) claims 9 bytes, 6 remain)");

  // Invalid UTF-8 in the name (a proto3 string), and in a nested string.
  status = raw.Unary("CreateMap", Patched(create, "mapx", "m\xFF\xFEx"));
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message(),
            "request is not a valid placedb.v1.CreateMapRequest: field name (1) is not valid "
            "UTF-8");
  status = raw.Unary("CreateMap", Patched(create, "default", "def\xC0\x80lt"));
  EXPECT_EQ(status.error_message(),
            "request is not a valid placedb.v1.CreateMapRequest: field config.vocabulary (1) is "
            "not valid UTF-8");

  // Bytes that are no protobuf at all, to another method.
  status = raw.Unary("GetPlace", std::string("\xFF\xFF\xFF\xFF\xFF\xFF\xFF\xFF\xFF\xFF\xFF", 11));
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message().rfind("request is not a valid placedb.v1.GetPlaceRequest: ", 0),
            0u)
      << status.error_message();

  // Nothing changed.
  EXPECT_EQ(MapNames(stub_.get()), std::vector<std::string>{"m"});
  EXPECT_EQ(Stats("m").places(), 1u);
}

TEST_F(UntrustedInputTest, MalformedIngestMessageEndsTheStreamNamingIt) {
  RawClient raw(channel_);
  v1::IngestRequest header;
  header.mutable_header()->set_map("m");
  v1::IngestRequest good;
  *good.mutable_observation() = JpegObservation(CamVidPath("0001TP_006720"), "agent1", 2);
  v1::IngestRequest bad = good;
  bad.mutable_observation()->set_agent_id("agent2");

  // The second observation's agent id is not UTF-8: the first is answered (and stored), then the
  // stream ends with INVALID_ARGUMENT naming the message; the bad one is not stored.
  std::vector<v1::IngestResponse> responses;
  grpc::Status status = raw.Ingest(
      {header.SerializeAsString(), good.SerializeAsString(), Patched(bad, "agent2", "agent\xE9")},
      &responses);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message(),
            "message 2 of the Ingest stream (observation 1) is not a valid "
            "placedb.v1.IngestRequest: field observation.agent_id (1) is not valid UTF-8");
  ASSERT_EQ(responses.size(), 1u);
  EXPECT_TRUE(responses[0].stored()) << responses[0].DebugString();
  EXPECT_EQ(Stats("m").places(), 2u);

  // A truncated header: nothing is read after it, nothing stored.
  responses.clear();
  const std::string header_bytes = header.SerializeAsString();
  status = raw.Ingest({header_bytes.substr(0, header_bytes.size() - 1), good.SerializeAsString()},
                      &responses);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message().rfind("message 0 of the Ingest stream (the header) is not a "
                                         "valid placedb.v1.IngestRequest: the data is truncated",
                                         0),
            0u)
      << status.error_message();
  EXPECT_TRUE(responses.empty());

  // A truncated observation (its image cut mid-field).
  responses.clear();
  const std::string good_bytes = good.SerializeAsString();
  status = raw.Ingest({header_bytes, good_bytes.substr(0, good_bytes.size() / 2)}, &responses);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message().rfind("message 1 of the Ingest stream (observation 0) is not a "
                                         "valid placedb.v1.IngestRequest: the data is truncated "
                                         "(field observation (2) claims ",
                                         0),
            0u)
      << status.error_message();
  EXPECT_TRUE(responses.empty());
  EXPECT_EQ(Stats("m").places(), 2u);
}

// The diagnosis of bytes protobuf refused, on its own (server/rpc/parsing_service.h).
TEST(DiagnoseMessageTest, NamesTheFirstProblemWithItsPath) {
  v1::QueryRequest query;
  query.set_map("m");
  query.mutable_observation()->add_boxes()->set_class_name("car");
  query.mutable_observation()->add_boxes()->set_class_name("bus");
  std::string bytes = query.SerializeAsString();
  // The second box's class name made invalid UTF-8: the repeated field's index is named.
  bytes.replace(bytes.find("bus"), 3, "b\xF5s");
  EXPECT_EQ(server::DiagnoseMessage(bytes, v1::QueryRequest()),
            "field observation.boxes[1].class_name (2) is not valid UTF-8");
  // A field number 0, an invalid wire type, a varint that never ends.
  EXPECT_EQ(server::DiagnoseMessage(std::string("\x00\x01", 2), v1::QueryRequest()),
            "the data is malformed (a bad field tag at byte 0)");
  EXPECT_EQ(server::DiagnoseMessage(std::string("\x0F\x01", 2), v1::QueryRequest()),
            "the data is malformed (wire type 7 in field map (1))");
  // Field 15 (no field of QueryRequest: named by its number), a varint that never ends.
  EXPECT_EQ(server::DiagnoseMessage(std::string("\x78\xFF\xFF", 3), v1::QueryRequest()),
            "the data is truncated or malformed (in field field number 15)");
  // A known field is named.
  EXPECT_EQ(server::DiagnoseMessage(std::string("\x20\xFF\xFF", 3), v1::QueryRequest()),
            "the data is truncated or malformed (in field min_sequence (4))");
}

// ---- No absolute path reaches a client ------------------------------------------------------

// A "/" starting a token followed by a path component: "/tmp/x", "(/data", "'/a".
bool HasAbsolutePath(const std::string& text) {
  static const std::regex kPath(R"((^|[\s(\['"=,`])/[A-Za-z0-9._~-])");
  return std::regex_search(text, kPath);
}

TEST(HasAbsolutePathTest, FindsPathsNotSlashes) {
  EXPECT_TRUE(HasAbsolutePath("/tmp/x"));
  EXPECT_TRUE(HasAbsolutePath("reading: /tmp/x/CURRENT: gone"));
  EXPECT_TRUE(HasAbsolutePath("model '/opt/m.onnx'"));
  EXPECT_FALSE(HasAbsolutePath("image_width/image_height: must be in [1, 100000]"));
  EXPECT_FALSE(HasAbsolutePath("maps/m/000012.log"));
  EXPECT_FALSE(HasAbsolutePath("1 / 2"));
}

TEST_F(UntrustedInputTest, NoAbsolutePathInClientVisibleErrors) {
  ASSERT_EQ(root_.front(), '/');
  std::vector<std::string> seen;  // every client-visible text, checked at the end
  auto status_of = [&](const grpc::Status& status) {
    EXPECT_FALSE(status.ok());
    seen.push_back(status.error_message());
  };
  {
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name("nope");
    v1::MapDescription response;
    status_of(stub_->GetMap(&context, request, &response));
  }
  status_of(CreateMapStatus("m"));
  {
    v1::MapConfig config;
    config.set_vocabulary("/etc/passwd");
    status_of(CreateMapStatus("m2", config));
  }
  {
    grpc::ClientContext context;
    v1::GetPlaceRequest request;
    request.set_map("m");
    request.set_place_id(999);
    v1::Place place;
    status_of(stub_->GetPlace(&context, request, &place));
  }

  // A map whose RocksDB lost its CURRENT file, and a detector model that does not exist (both
  // absolute paths in the server's own errors), seen after a restart.
  StopServer();
  std::error_code error;
  size_t removed = 0;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(root_ + "/data")) {
    if (entry.path().filename() == "CURRENT") {
      std::filesystem::remove(entry.path(), error);
      ++removed;
    }
  }
  ASSERT_GT(removed, 0u);
  ServerConfig config = Config();
  config.detector.model = root_ + "/models/missing-model.onnx";
  config.detector.required = false;
  StartServer(config);
  {
    grpc::ClientContext context;
    v1::ListMapsResponse maps;
    ASSERT_TRUE(stub_->ListMaps(&context, v1::ListMapsRequest(), &maps).ok());
    ASSERT_EQ(maps.maps_size(), 1);
    EXPECT_FALSE(maps.maps(0).available());
    EXPECT_FALSE(maps.maps(0).unavailable_reason().empty());
    seen.push_back(maps.maps(0).unavailable_reason());
  }
  {
    // A damaged map's description is an answer, not an error: its reason is client-visible.
    grpc::ClientContext context;
    v1::GetMapRequest request;
    request.set_name("m");
    v1::MapDescription response;
    ASSERT_TRUE(stub_->GetMap(&context, request, &response).ok());
    EXPECT_EQ(response.state(), v1::MAP_STATE_DAMAGED);
    seen.push_back(response.unavailable_reason());
    seen.push_back(response.damage().reason());
  }
  status_of(IngestAll(stub_.get(), "m", {}).status);
  {
    grpc::ClientContext context;
    v1::ServerInfo info;
    ASSERT_TRUE(stub_->GetServerInfo(&context, v1::GetServerInfoRequest(), &info).ok());
    ASSERT_EQ(info.vocabularies_size(), 1);
    EXPECT_EQ(info.vocabularies(0).path(), "default.pdbv");  // the file name only
    EXPECT_NE(info.detector().find("missing-model.onnx"), std::string::npos) << info.detector();
    seen.push_back(info.detector());
    seen.push_back(info.vocabularies(0).path());
  }

  // The server's own texts did hold the paths (the test is not vacuous): the data directory's
  // files are shown relative to it.
  bool relative = false;
  for (const std::string& text : seen) {
    SCOPED_TRACE(text);
    EXPECT_EQ(text.find(root_), std::string::npos);
    EXPECT_FALSE(HasAbsolutePath(text));
    if (text.find("maps/m/") != std::string::npos) relative = true;
  }
  EXPECT_TRUE(relative) << "no error named a file of the broken map";
}

}  // namespace
}  // namespace placedb::server_testing
