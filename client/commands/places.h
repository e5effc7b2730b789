// `placedb place get|delete MAP ID` (docs/cli.md, "place"): one stored place's metadata, counts,
// boxes, (--features) static features and (--thumbnail FILE) thumbnail, or its durable removal.
#pragma once

#include <cstdint>
#include <string>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
}  // namespace CLI

namespace placedb::client {

struct PlaceFlags {
  std::string map;
  uint32_t id = 0;
  bool features = false;  // get: include the stored static features
  std::string thumbnail;  // get: write the place's thumbnail JPEG to this file
};

// The `place` subcommands; the one parsed says which Place* function runs.
struct PlaceCommands {
  CLI::App* get = nullptr;
  CLI::App* remove = nullptr;
};

// Adds `place` and its subcommands to `app`, their options bound to *flags.
PlaceCommands RegisterPlace(CLI::App& app, PlaceFlags* flags);

// With `thumbnail_file` set, the place's thumbnail is asked for and its JPEG written there
// (exit 1 when the place has none).
int PlaceGet(const Connection& connection, const std::string& map, uint32_t id, bool features,
             bool json, CliIo& io, const std::string& thumbnail_file = "");
int PlaceDelete(const Connection& connection, const std::string& map, uint32_t id, bool json,
                CliIo& io);

}  // namespace placedb::client
