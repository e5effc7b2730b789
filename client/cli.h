// The `placedb` command line (docs/cli.md): maps, ingest, query, places, info, health and the load
// tester, all through the placedb.v1 API.
//
//   placedb [--address HOST:PORT] [--timeout S] [--json] [--token T]
//           [--tls [--ca-cert PEM] [--cert PEM --key PEM]]
//           COMMAND ...
//
// Exit codes: 0 ok, 1 an RPC failed (printed with its gRPC code name), 2 usage (bad arguments,
// unreadable local input, a load target that is not loopback). `health` exits 0 when SERVING,
// 1 otherwise, 2 when the server cannot be reached. placedb-load and placedb-server use the same
// 0 / 1 / 2 (docs/cli.md, "Exit codes").
#pragma once

#include <istream>
#include <ostream>
#include <string>

namespace placedb::client {

// Where a command reads and writes; tests hand in string streams.
struct CliIo {
  std::ostream& out;        // results (tables, or JSON with --json)
  std::ostream& err;        // errors, progress
  std::istream& in;         // confirmations (maps delete without --yes)
  bool err_is_tty = false;  // progress bar (true) or periodic progress lines (false)
  bool in_is_tty = false;   // whether a confirmation can be asked
  // The server the commands talk to (RunCli sets it): named in errors of calls that found none.
  std::string server_address{};
};

// Runs one command line (argv[0] is the program name). Never throws, never exits.
int RunCli(int argc, const char* const* argv, CliIo& io);

// For main(): the process's standard streams, TTY detection, then RunCli.
int CliMain(int argc, const char* const* argv);

}  // namespace placedb::client
