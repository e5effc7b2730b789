// What several `placedb` commands share: error exits, the text of boxes and descriptor counts,
// the wall clock stamped on observations, and the JSON of ended streams.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "client/cli.h"
#include "client/connection.h"

namespace placedb::client {

// "error: <the status>" on io.err; kExitRpcError.
int RpcFailed(CliIo& io, const grpc::Status& status);
// "error: <message>" on io.err; kExitUsage.
int UsageError(CliIo& io, const std::string& message);

// "person 0.90 [10 20 30x40]".
std::string FormatBox(const v1::UsedBox& box);
// "500 descriptors: 450 static kept, 50 dynamic dropped (12.5% of the image dynamic)".
std::string FormatCounts(const v1::FrameCounts& counts);

// Observation.timestamp_ns of a frame sent now.
int64_t UnixNowNs();

// The streams that ended with an error, by agent: [{"agent", "code", "message"}, ...].
nlohmann::json StreamErrorsJson(
    const std::vector<std::pair<std::string, grpc::Status>>& stream_errors);

}  // namespace placedb::client
