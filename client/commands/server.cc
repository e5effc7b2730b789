#include "client/commands/server.h"

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <utility>
#include <vector>

#include "client/commands/common.h"
#include "client/format.h"

namespace placedb::client {

ServerCommands RegisterServer(CLI::App& app, HealthFlags* flags) {
  ServerCommands commands;
  commands.info = app.add_subcommand("info", "server version, vocabularies, detector, limits");
  commands.health = app.add_subcommand(
      "health", "grpc.health.v1 Check: exit 0 SERVING, 1 otherwise, 2 unreachable");
  commands.console = app.add_subcommand("console", "print the URL of the server's web console");
  commands.health->add_option("--service", flags->service,
                              "service to check (default \"\": the whole server)");
  return commands;
}

int RunInfo(const Connection& connection, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::ServerInfo info;
  const grpc::Status status = connection.stub()->GetServerInfo(context.get(), {}, &info);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(info) << '\n';
    return kExitOk;
  }
  io.out << "placedb server " << info.version() << " at " << connection.options().address
         << "\n  detector  " << info.detector() << "\n\n";
  Table vocabularies(
      {"VOCABULARY", "FEATURES", ">WORDS", ">NODES", ">K", ">L", ">MEMORY", "CHECKSUM", "PATH"});
  for (const v1::VocabularyInfo& v : info.vocabularies()) {
    vocabularies.Add(
        {v.name(),
         v.feature_type() == v1::FEATURE_TYPE_UNSPECIFIED ? std::string("-")
                                                          : wire::EnumName(v.feature_type()),
         std::to_string(v.words()), std::to_string(v.nodes()), std::to_string(v.branching()),
         std::to_string(v.depth()), FormatBytes(v.memory_bytes()), v.checksum(), v.path()});
  }
  vocabularies.Print(io.out);
  const v1::Limits& l = info.limits();
  std::vector<std::pair<std::string, std::string>> limits;
  limits.push_back({"max_message_bytes", FormatBytes(l.max_message_bytes())});
  limits.push_back({"max_image_pixels", std::to_string(l.max_image_pixels())});
  limits.push_back({"max_descriptors_per_frame", std::to_string(l.max_descriptors_per_frame())});
  limits.push_back({"max_boxes_per_frame", std::to_string(l.max_boxes_per_frame())});
  limits.push_back({"max_concurrent_streams", std::to_string(l.max_concurrent_streams())});
  limits.push_back({"max_queued_frames", std::to_string(l.max_queued_frames())});
  limits.push_back({"max_inflight_per_stream", std::to_string(l.max_inflight_per_stream())});
  limits.push_back({"worker_threads", std::to_string(l.worker_threads())});
  io.out << '\n';
  PrintKeyValues(io.out, "limits", limits);
  return kExitOk;
}

int RunConsole(const Connection& connection, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::ServerInfo info;
  const grpc::Status status = connection.stub()->GetServerInfo(context.get(), {}, &info);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << nlohmann::json{{"console_url", info.console_url()}}.dump() << '\n';
  } else if (!info.console_url().empty()) {
    io.out << info.console_url() << '\n';
  } else {
    io.err << "placedb: the server at " << connection.options().address
           << " runs no console (console_listen is off; docs/console.md)\n";
  }
  return info.console_url().empty() ? 1 : kExitOk;
}

int RunHealth(const Connection& connection, const std::string& service, bool json, CliIo& io) {
  std::string serving;
  const grpc::Status status = CheckHealth(connection, service, &serving);
  int code = kExitOk;
  std::string state = serving;
  if (!status.ok()) {
    const bool unreachable = status.error_code() == grpc::StatusCode::UNAVAILABLE ||
                             status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED;
    state = unreachable                                          ? "UNREACHABLE"
            : status.error_code() == grpc::StatusCode::NOT_FOUND ? "SERVICE_UNKNOWN"
                                                                 : "ERROR";
    code = unreachable ? 2 : 1;
    io.err << "error: " << DescribeFailure(status, connection.options().address) << '\n';
  } else if (serving != "SERVING") {
    code = 1;
  }
  if (json) {
    nlohmann::json out = {
        {"address", connection.options().address}, {"service", service}, {"status", state}};
    if (!status.ok()) out["error"] = Describe(status);
    io.out << out.dump(2) << '\n';
  } else {
    io.out << state << '\n';
  }
  return code;
}

}  // namespace placedb::client
