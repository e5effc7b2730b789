// `placedb place get|delete MAP ID` (docs/cli.md, "place"): one stored place's metadata, counts,
// boxes, (--features) static features and (--thumbnail FILE) thumbnail, or its durable removal.
// `placedb place list MAP` (alias `places list`): a page of the map's places, newest first
// (ListPlaces).
#pragma once

#include <cstdint>
#include <string>

#include "client/cli.h"
#include "client/connection.h"
#include "core/base/status.h"

namespace CLI {
class App;
}  // namespace CLI

namespace placedb::client {

struct PlaceFlags {
  std::string map;
  uint32_t id = 0;
  bool features = false;  // get: include the stored static features
  // list: the ListPlaces request's filter and paging; times as given (ParseTimeFlag).
  std::string agent;
  std::string from;
  std::string to;
  uint32_t limit = 0;
  uint32_t before = 0;
  std::string thumbnail;  // get: write the place's thumbnail JPEG to this file
};

// A --from/--to value: unix nanoseconds ("1732400000000000000") or UTC ISO 8601
// ("2026-11-24T07:30:00Z", optional fraction). INVALID_ARGUMENT naming `flag` otherwise.
Result<int64_t> ParseTimeFlag(const std::string& text, const std::string& flag);

// The `place` subcommands; the one parsed says which Place* function runs.
struct PlaceCommands {
  CLI::App* get = nullptr;
  CLI::App* remove = nullptr;
  CLI::App* list = nullptr;
};

// Adds `place` and its subcommands to `app`, their options bound to *flags.
PlaceCommands RegisterPlace(CLI::App& app, PlaceFlags* flags);

// With `thumbnail_file` set, the place's thumbnail is asked for and its JPEG written there
// (exit 1 when the place has none).
int PlaceGet(const Connection& connection, const std::string& map, uint32_t id, bool features,
             bool json, CliIo& io, const std::string& thumbnail_file = "");
int PlaceList(const Connection& connection, const PlaceFlags& flags, bool json, CliIo& io);
int PlaceDelete(const Connection& connection, const std::string& map, uint32_t id, bool json,
                CliIo& io);

}  // namespace placedb::client
