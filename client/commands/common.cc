#include "client/commands/common.h"

#include <chrono>

#include "client/format.h"
#include "proto/status.h"

namespace placedb::client {

int RpcFailed(CliIo& io, const grpc::Status& status) {
  io.err << "error: " << DescribeFailure(status, io.server_address) << '\n';
  return kExitRpcError;
}

int UsageError(CliIo& io, const std::string& message) {
  io.err << "error: " << message << '\n';
  return kExitUsage;
}

std::string FormatBox(const v1::UsedBox& box) {
  return box.class_name() + " " + FormatDouble(box.confidence(), 2) + " [" +
         FormatDouble(box.rect().x(), 0) + " " + FormatDouble(box.rect().y(), 0) + " " +
         FormatDouble(box.rect().width(), 0) + "x" + FormatDouble(box.rect().height(), 0) + "]";
}

std::string FormatCounts(const v1::FrameCounts& counts) {
  return std::to_string(counts.total()) + " descriptors: " + std::to_string(counts.kept()) +
         " static kept, " + std::to_string(counts.dynamic()) + " dynamic dropped" +
         (counts.depth_removed() > 0
              ? ", " + std::to_string(counts.depth_removed()) + " removed by depth"
              : std::string()) +
         " (" + FormatDouble(counts.dynamic_coverage() * 100, 1) + "% of the image dynamic)";
}

int64_t UnixNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

nlohmann::json StreamErrorsJson(
    const std::vector<std::pair<std::string, grpc::Status>>& stream_errors) {
  nlohmann::json streams = nlohmann::json::array();
  for (const auto& [agent, status] : stream_errors) {
    streams.push_back({{"agent", agent},
                       {"code", wire::GrpcCodeName(int(status.error_code()))},
                       {"message", status.error_message()}});
  }
  return streams;
}

}  // namespace placedb::client
