// `placedb info`, `placedb health` and `placedb console` (docs/cli.md): what the server runs
// (version, vocabularies, detector, limits), whether it serves (grpc.health.v1; the exit code
// says it to scripts), and where its web console is.
#pragma once

#include <string>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
}  // namespace CLI

namespace placedb::client {

struct HealthFlags {
  std::string service;  // "" = the whole server
};

struct ServerCommands {
  CLI::App* info = nullptr;
  CLI::App* health = nullptr;
  CLI::App* console = nullptr;
};

// Adds `info`, `health` and `console` to `app`, health's options bound to *flags.
ServerCommands RegisterServer(CLI::App& app, HealthFlags* flags);

int RunInfo(const Connection& connection, bool json, CliIo& io);
// Prints the console's URL (ServerInfo.console_url); exit 1 when the server runs none.
int RunConsole(const Connection& connection, bool json, CliIo& io);
// 0 SERVING, 1 anything else the server says, 2 unreachable.
int RunHealth(const Connection& connection, const std::string& service, bool json, CliIo& io);

}  // namespace placedb::client
