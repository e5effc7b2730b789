#include "client/commands/snapshots.h"

#include <CLI/CLI.hpp>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <optional>
#include <utility>
#include <vector>

#include "client/commands/common.h"
#include "client/format.h"
#include "client/progress.h"

namespace placedb::client {

namespace {

constexpr size_t kUploadChunkBytes = size_t(1) << 20;

void PrintSnapshot(std::ostream& out, const std::string& title, const v1::Snapshot& s) {
  PrintKeyValues(out, title,
                 {{"id", s.id()},
                  {"map", s.map()},
                  {"created", FormatUnixMs(s.created_unix_ms())},
                  {"places", std::to_string(s.places())},
                  {"features", s.feature_type()},
                  {"size on server", FormatBytes(s.bytes())}});
}

}  // namespace

SnapshotsCommands RegisterSnapshots(CLI::App& app, SnapshotsFlags* flags) {
  SnapshotsCommands commands;
  CLI::App* group =
      app.add_subcommand("snapshots", "verified copies of maps: create, move, restore (admin)");
  group->require_subcommand(1);
  commands.create = group->add_subcommand("create", "snapshot a map (online: ingest goes on)");
  commands.create->add_option("MAP", flags->map, "map name")->required();
  commands.list = group->add_subcommand("list", "the server's snapshots, newest first");
  commands.download = group->add_subcommand("download", "write a snapshot's archive to a file");
  commands.download->add_option("ID", flags->id, "snapshot id")->required();
  commands.download->add_option("FILE", flags->file, "the archive to write (must not exist)")
      ->required();
  commands.upload =
      group->add_subcommand("upload", "send an archive; the server keeps it as a snapshot");
  commands.upload->add_option("FILE", flags->file, "the archive")
      ->required()
      ->check(CLI::ExistingFile);
  commands.restore = group->add_subcommand("restore", "a snapshot as a new map");
  commands.restore->add_option("ID", flags->id, "snapshot id")->required();
  commands.restore->add_option("NEW_MAP", flags->new_map, "the new map's name")->required();
  commands.remove = group->add_subcommand("delete", "delete a snapshot (its map stays)");
  commands.remove->add_option("ID", flags->id, "snapshot id")->required();
  for (CLI::App* transfer : {commands.download, commands.upload}) {
    transfer->add_flag("!--no-progress", flags->progress, "no progress on stderr");
  }
  return commands;
}

int SnapshotsCreate(const Connection& connection, const std::string& map, bool json, CliIo& io) {
  auto context = connection.NewContext(/*unary=*/false);  // flush + verification: no deadline
  v1::CreateSnapshotRequest request;
  request.set_map(map);
  v1::Snapshot snapshot;
  const grpc::Status status = connection.stub()->CreateSnapshot(context.get(), request, &snapshot);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(snapshot) << '\n';
  } else {
    PrintSnapshot(io.out, "snapshot created", snapshot);
  }
  return kExitOk;
}

int SnapshotsList(const Connection& connection, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::ListSnapshotsResponse response;
  const grpc::Status status =
      connection.stub()->ListSnapshots(context.get(), v1::ListSnapshotsRequest(), &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(response) << '\n';
    return kExitOk;
  }
  if (response.snapshots().empty()) {
    io.out << "no snapshots\n";
    return kExitOk;
  }
  Table table({"ID", "MAP", "CREATED", ">PLACES", ">SIZE"});
  for (const v1::Snapshot& s : response.snapshots()) {
    table.Add({s.id(), s.map(), FormatUnixMs(s.created_unix_ms()), std::to_string(s.places()),
               FormatBytes(s.bytes())});
  }
  table.Print(io.out);
  return kExitOk;
}

int SnapshotsDownload(const Connection& connection, const SnapshotsFlags& flags, bool json,
                      CliIo& io) {
  namespace fs = std::filesystem;
  if (fs::exists(flags.file)) return UsageError(io, flags.file + " exists; not overwritten");
  std::ofstream out(flags.file, std::ios::binary);
  if (!out) return UsageError(io, "cannot write " + flags.file);
  auto remove_partial = [&] {
    out.close();
    std::error_code ec;
    fs::remove(flags.file, ec);
  };
  auto context = connection.NewContext(/*unary=*/false);
  v1::DownloadSnapshotRequest request;
  request.set_id(flags.id);
  auto reader = connection.stub()->DownloadSnapshot(context.get(), request);
  v1::SnapshotChunk chunk;
  v1::Snapshot snapshot;
  uint64_t total = 0, received = 0;
  std::optional<Progress> progress;
  while (reader->Read(&chunk)) {
    if (chunk.has_snapshot()) {
      snapshot = chunk.snapshot();
      total = chunk.archive_bytes();
      if (flags.progress && !json) {
        progress.emplace(io.err, io.err_is_tty, size_t(total), 2.0, Progress::Unit::kBytes);
      }
    }
    out.write(chunk.data().data(), std::streamsize(chunk.data().size()));
    received += chunk.data().size();
    if (progress) progress->Add(chunk.data().size());
  }
  if (progress) progress->Stop();
  const grpc::Status status = reader->Finish();
  out.flush();
  if (!status.ok() || !out || received != total) {
    remove_partial();
    if (!status.ok()) return RpcFailed(io, status);
    return RpcFailed(
        io, grpc::Status(grpc::StatusCode::DATA_LOSS, "received " + std::to_string(received) +
                                                          " of " + std::to_string(total) +
                                                          " bytes, or cannot write " + flags.file));
  }
  if (json) {
    io.out << nlohmann::json({{"downloaded",
                               {{"id", snapshot.id()}, {"file", flags.file}, {"bytes", received}}}})
                  .dump(2)
           << '\n';
  } else {
    io.out << "downloaded snapshot '" << snapshot.id() << "' (map '" << snapshot.map() << "', "
           << snapshot.places() << " places) to " << flags.file << " (" << FormatBytes(received)
           << ")\n";
  }
  return kExitOk;
}

int SnapshotsUpload(const Connection& connection, const SnapshotsFlags& flags, bool json,
                    CliIo& io) {
  std::ifstream in(flags.file, std::ios::binary);
  std::error_code ec;
  const uint64_t total = std::filesystem::file_size(flags.file, ec);
  if (!in || ec) return UsageError(io, "cannot read " + flags.file);
  auto context = connection.NewContext(/*unary=*/false);
  v1::Snapshot snapshot;
  auto writer = connection.stub()->UploadSnapshot(context.get(), &snapshot);
  std::optional<Progress> progress;
  if (flags.progress && !json) {
    progress.emplace(io.err, io.err_is_tty, size_t(total), 2.0, Progress::Unit::kBytes);
  }
  std::string buffer(kUploadChunkBytes, '\0');
  bool first = true;
  for (;;) {
    in.read(buffer.data(), std::streamsize(buffer.size()));
    const size_t n = size_t(in.gcount());
    if (n == 0 && !first) break;
    v1::SnapshotChunk chunk;
    if (first) chunk.set_archive_bytes(total);
    first = false;
    chunk.set_data(buffer.substr(0, n));
    if (!writer->Write(chunk)) break;  // the server ended the call: Finish() says why
    if (progress) progress->Add(n);
    if (n < buffer.size()) break;
  }
  writer->WritesDone();
  const grpc::Status status = writer->Finish();
  if (progress) progress->Stop();
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(snapshot) << '\n';
  } else {
    PrintSnapshot(io.out, "snapshot uploaded", snapshot);
  }
  return kExitOk;
}

int SnapshotsRestore(const Connection& connection, const std::string& id,
                     const std::string& new_map, bool json, CliIo& io) {
  auto context = connection.NewContext(/*unary=*/false);  // restoring copies: no short deadline
  v1::RestoreSnapshotRequest request;
  request.set_id(id);
  request.set_new_map(new_map);
  v1::MapDescription map;
  const grpc::Status status = connection.stub()->RestoreSnapshot(context.get(), request, &map);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(map) << '\n';
  } else {
    io.out << "restored snapshot '" << id << "' as map '" << map.name() << "' ("
           << map.stats().places() << " places)\n";
  }
  return kExitOk;
}

int SnapshotsDelete(const Connection& connection, const std::string& id, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::DeleteSnapshotRequest request;
  request.set_id(id);
  v1::DeleteSnapshotResponse response;
  const grpc::Status status = connection.stub()->DeleteSnapshot(context.get(), request, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << nlohmann::json({{"deleted", {{"snapshot", id}}}}).dump(2) << '\n';
  } else {
    io.out << "deleted snapshot '" << id << "'\n";
  }
  return kExitOk;
}

}  // namespace placedb::client
