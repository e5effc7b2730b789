// `placedb snapshots create|list|download|upload|restore|delete` (docs/cli.md, "snapshots"):
// the server's snapshot RPCs (admin). download writes the archive to a file (a partial file is
// removed on failure), upload sends one; both show progress on stderr.
#pragma once

#include <string>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
}  // namespace CLI

namespace placedb::client {

struct SnapshotsFlags {
  std::string map;   // create
  std::string id;    // download, restore, delete
  std::string file;  // download (output), upload (input)
  std::string new_map;
  bool progress = true;
};

struct SnapshotsCommands {
  CLI::App* create = nullptr;
  CLI::App* list = nullptr;
  CLI::App* download = nullptr;
  CLI::App* upload = nullptr;
  CLI::App* restore = nullptr;
  CLI::App* remove = nullptr;
};

SnapshotsCommands RegisterSnapshots(CLI::App& app, SnapshotsFlags* flags);

int SnapshotsCreate(const Connection& connection, const std::string& map, bool json, CliIo& io);
int SnapshotsList(const Connection& connection, bool json, CliIo& io);
// Refuses to overwrite an existing file.
int SnapshotsDownload(const Connection& connection, const SnapshotsFlags& flags, bool json,
                      CliIo& io);
int SnapshotsUpload(const Connection& connection, const SnapshotsFlags& flags, bool json,
                    CliIo& io);
int SnapshotsRestore(const Connection& connection, const std::string& id,
                     const std::string& new_map, bool json, CliIo& io);
int SnapshotsDelete(const Connection& connection, const std::string& id, bool json, CliIo& io);

}  // namespace placedb::client
