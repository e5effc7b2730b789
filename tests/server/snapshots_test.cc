// The snapshot RPCs on a real server over loopback: create, list, download, upload to a second
// server (another data directory), restore, delete; bad uploads refused with nothing left behind.
#include <gtest/gtest.h>

#include <filesystem>
#include <set>
#include <thread>

#include "tests/server/server_fixture.h"

namespace fs = std::filesystem;

namespace placedb::server_testing {
namespace {

class SnapshotsServerTest : public ServerTest {
 protected:
  // Every query's matches (ids, scores, inliers, metadata), serialised: equal means identical.
  std::vector<std::string> Answers(const std::string& map) {
    std::vector<std::string> out;
    for (int frame = 40; frame <= 70; frame += 3) {
      v1::QueryResponse response;
      grpc::Status status = Query(map, RtabmapObservation(frame, "query"), &response);
      EXPECT_TRUE(status.ok()) << status.error_message();
      std::string matches;
      for (const v1::Match& match : response.matches()) matches += match.SerializeAsString();
      out.push_back(matches);
    }
    return out;
  }

  grpc::Status Download(const std::string& id, std::string* archive, v1::Snapshot* snapshot) {
    v1::DownloadSnapshotRequest request;
    request.set_id(id);
    grpc::ClientContext context;
    auto reader = stub_->DownloadSnapshot(&context, request);
    v1::SnapshotChunk chunk;
    uint64_t announced = 0;
    for (bool first = true; reader->Read(&chunk); first = false) {
      if (first) {
        *snapshot = chunk.snapshot();
        announced = chunk.archive_bytes();
      } else {
        EXPECT_FALSE(chunk.has_snapshot());
      }
      archive->append(chunk.data());
    }
    grpc::Status status = reader->Finish();
    if (status.ok()) {
      EXPECT_EQ(announced, archive->size());
    }
    return status;
  }

  // Uploads `archive` in 64 KiB chunks; `announce` sets archive_bytes in the first one.
  grpc::Status Upload(const std::string& archive, uint64_t announce, v1::Snapshot* response) {
    grpc::ClientContext context;
    auto writer = stub_->UploadSnapshot(&context, response);
    size_t offset = 0;
    do {
      v1::SnapshotChunk chunk;
      if (offset == 0) chunk.set_archive_bytes(announce);
      chunk.set_data(archive.substr(offset, 64 << 10));
      offset += chunk.data().size();
      if (!writer->Write(chunk)) break;
    } while (offset < archive.size());
    writer->WritesDone();
    return writer->Finish();
  }

  std::vector<std::string> SnapshotIds() {
    v1::ListSnapshotsResponse list;
    EXPECT_TRUE(stub_->ListSnapshots(Context().get(), {}, &list).ok());
    std::vector<std::string> ids;
    for (const auto& s : list.snapshots()) ids.push_back(s.id());
    return ids;
  }

  static std::unique_ptr<grpc::ClientContext> Context() {
    return std::make_unique<grpc::ClientContext>();
  }

  std::set<std::string> Tree(const std::string& dir) {
    std::set<std::string> out;
    for (const auto& entry : fs::recursive_directory_iterator(dir)) {
      out.insert(fs::relative(entry.path(), dir).generic_string());
    }
    return out;
  }
};

TEST_F(SnapshotsServerTest, DownloadUploadToASecondServerRestoresIdenticalAnswers) {
  StartServer(Config());
  CreateMap("lab");
  std::vector<v1::Observation> frames;
  for (int i = 1; i <= 24; ++i) frames.push_back(RtabmapObservation(i, "robot"));
  ASSERT_TRUE(IngestAll(stub_.get(), "lab", frames).status.ok());
  const std::vector<std::string> expected = Answers("lab");

  v1::CreateSnapshotRequest create;
  create.set_map("lab");
  v1::Snapshot created;
  grpc::Status status = stub_->CreateSnapshot(Context().get(), create, &created);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(created.map(), "lab");
  EXPECT_EQ(created.places(), Stats("lab").places());
  EXPECT_EQ(SnapshotIds(), std::vector<std::string>{created.id()});

  // Ingest goes on after the snapshot; the snapshot does not change.
  ASSERT_TRUE(IngestAll(stub_.get(), "lab", {RtabmapObservation(30, "robot")}).status.ok());

  std::string archive;
  v1::Snapshot described;
  status = Download(created.id(), &archive, &described);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(described.SerializeAsString(), created.SerializeAsString());

  // Restoring on the same server.
  v1::RestoreSnapshotRequest restore;
  restore.set_id(created.id());
  restore.set_new_map("lab-copy");
  v1::MapDescription restored;
  status = stub_->RestoreSnapshot(Context().get(), restore, &restored);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(restored.name(), "lab-copy");
  EXPECT_EQ(Answers("lab-copy"), expected);

  // A second server with its own data directory.
  StopServer();
  ServerConfig second = Config();
  second.data_dir = root_ + "/second";
  StartServer(second);
  v1::Snapshot uploaded;
  status = Upload(archive, archive.size(), &uploaded);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(uploaded.id(), created.id());
  EXPECT_EQ(uploaded.places(), created.places());
  restore.set_new_map("lab");
  status = stub_->RestoreSnapshot(Context().get(), restore, &restored);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(Answers("lab"), expected);
  EXPECT_EQ(stub_->RestoreSnapshot(Context().get(), restore, &restored).error_code(),
            grpc::StatusCode::ALREADY_EXISTS);

  v1::DeleteSnapshotRequest del;
  del.set_id(created.id());
  v1::DeleteSnapshotResponse deleted;
  ASSERT_TRUE(stub_->DeleteSnapshot(Context().get(), del, &deleted).ok());
  EXPECT_TRUE(SnapshotIds().empty());
  EXPECT_EQ(stub_->DeleteSnapshot(Context().get(), del, &deleted).error_code(),
            grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(Stats("lab").places(), created.places());  // the restored map stays
}

TEST_F(SnapshotsServerTest, BadUploadsAreRefusedAndLeaveNothingBehind) {
  StartServer(Config());
  CreateMap("lab");
  std::vector<v1::Observation> frames;
  for (int i = 1; i <= 8; ++i) frames.push_back(RtabmapObservation(i, "robot"));
  ASSERT_TRUE(IngestAll(stub_.get(), "lab", frames).status.ok());
  v1::CreateSnapshotRequest create;
  create.set_map("lab");
  v1::Snapshot created;
  ASSERT_TRUE(stub_->CreateSnapshot(Context().get(), create, &created).ok());
  std::string archive;
  v1::Snapshot described;
  ASSERT_TRUE(Download(created.id(), &archive, &described).ok());
  v1::DeleteSnapshotRequest del;
  del.set_id(created.id());
  v1::DeleteSnapshotResponse deleted;
  ASSERT_TRUE(stub_->DeleteSnapshot(Context().get(), del, &deleted).ok());
  const auto before = Tree(root_ + "/data");

  using Code = grpc::StatusCode;
  struct Case {
    std::string what;
    std::string bytes;
    uint64_t announce;
    Code code;
  };
  std::string flipped = archive;
  flipped[flipped.size() / 2] ^= 0x20;
  const std::vector<Case> cases = {
      {"truncated, announced whole", archive.substr(0, archive.size() / 2), archive.size(),
       Code::DATA_LOSS},
      {"truncated, not announced", archive.substr(0, archive.size() - 10), 0, Code::DATA_LOSS},
      {"longer than announced", archive, archive.size() - 1, Code::INVALID_ARGUMENT},
      {"one byte flipped", flipped, 0, Code::DATA_LOSS},
      {"foreign", "PK\x03\x04 a zip file, not a snapshot", 0, Code::INVALID_ARGUMENT},
      {"empty", "", 0, Code::INVALID_ARGUMENT},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    v1::Snapshot response;
    grpc::Status status = Upload(c.bytes, c.announce, &response);
    EXPECT_EQ(status.error_code(), c.code) << status.error_message();
    EXPECT_EQ(status.error_message().find(root_), std::string::npos) << status.error_message();
    EXPECT_TRUE(SnapshotIds().empty());
    EXPECT_EQ(Tree(root_ + "/data"), before);
  }
  // Restoring a snapshot that is not there, or under a bad name.
  v1::RestoreSnapshotRequest restore;
  restore.set_id("nope");
  restore.set_new_map("x");
  v1::MapDescription restored;
  EXPECT_EQ(stub_->RestoreSnapshot(Context().get(), restore, &restored).error_code(),
            Code::NOT_FOUND);
  restore.set_id("../maps");
  EXPECT_EQ(stub_->RestoreSnapshot(Context().get(), restore, &restored).error_code(),
            Code::INVALID_ARGUMENT);
}

TEST_F(SnapshotsServerTest, AServerRestartDuringADownloadEndsItAndTheSnapshotStaysWhole) {
  StartServer(Config());
  CreateMap("lab");
  std::vector<v1::Observation> frames;
  for (int i = 1; i <= 84; ++i) frames.push_back(RtabmapObservation(i, "robot"));
  ASSERT_TRUE(IngestAll(stub_.get(), "lab", frames).status.ok());
  const std::vector<std::string> expected = Answers("lab");
  v1::CreateSnapshotRequest create;
  create.set_map("lab");
  v1::Snapshot created;
  ASSERT_TRUE(stub_->CreateSnapshot(Context().get(), create, &created).ok());

  // Read the first chunk, then stop the server while the download is open. The download's
  // channel has a small, fixed HTTP/2 window (no BDP growth), so the server cannot have pushed
  // the whole archive into buffers before it drains.
  const std::string address = "127.0.0.1:" + std::to_string(server_->port());
  grpc::ChannelArguments small_window;
  small_window.SetInt(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES, 64 << 10);
  small_window.SetInt(GRPC_ARG_HTTP2_BDP_PROBE, 0);
  auto downloader = v1::PlaceDb::NewStub(
      grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), small_window));
  v1::DownloadSnapshotRequest request;
  request.set_id(created.id());
  grpc::ClientContext context;
  auto reader = downloader->DownloadSnapshot(&context, request);
  v1::SnapshotChunk chunk;
  ASSERT_TRUE(reader->Read(&chunk));
  const uint64_t total = chunk.archive_bytes();
  uint64_t received = chunk.data().size();
  ASSERT_GT(total, 4 * received) << "the archive must span several chunks";
  std::thread stop([this] { StopServer(); });
  // Until the server is draining (new calls refused), then read on: the stream ends early.
  auto probe =
      v1::PlaceDb::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
  v1::DeleteSnapshotRequest absent;
  absent.set_id("absent-1");
  for (;;) {  // NOT_FOUND while serving; UNAVAILABLE (or no connection) once draining
    v1::DeleteSnapshotResponse response;
    if (probe->DeleteSnapshot(Context().get(), absent, &response).error_code() !=
        grpc::StatusCode::NOT_FOUND) {
      break;
    }
    std::this_thread::yield();
  }
  while (reader->Read(&chunk)) received += chunk.data().size();
  const grpc::Status ended = reader->Finish();
  stop.join();
  EXPECT_FALSE(ended.ok());
  EXPECT_LT(received, total);

  // After the restart the snapshot downloads whole and restores to the same answers.
  StartServer(Config());
  std::string archive;
  v1::Snapshot described;
  ASSERT_TRUE(Download(created.id(), &archive, &described).ok());
  EXPECT_EQ(archive.size(), total);
  v1::DeleteSnapshotRequest del;
  del.set_id(created.id());
  v1::DeleteSnapshotResponse deleted;
  ASSERT_TRUE(stub_->DeleteSnapshot(Context().get(), del, &deleted).ok());
  v1::Snapshot uploaded;
  ASSERT_TRUE(Upload(archive, archive.size(), &uploaded).ok());
  v1::RestoreSnapshotRequest restore;
  restore.set_id(uploaded.id());
  restore.set_new_map("lab-copy");
  v1::MapDescription restored;
  ASSERT_TRUE(stub_->RestoreSnapshot(Context().get(), restore, &restored).ok());
  EXPECT_EQ(Answers("lab-copy"), expected);
  for (const auto& entry : fs::directory_iterator(root_ + "/data/snapshots")) {
    EXPECT_NE(entry.path().filename().string().front(), '.') << entry.path();
  }
}

}  // namespace
}  // namespace placedb::server_testing
