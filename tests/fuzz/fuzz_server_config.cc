// The server's configuration from YAML (ApplyConfigYaml, as --config reads it) and from
// PLACEDB_* variables (ApplyEnvironment). The first byte picks one. Invariants: no crash and no
// exception escaping; errors are INVALID_ARGUMENT; a configuration that is also valid
// (ValidateServerConfig), printed with ConfigToYaml (--print-config), loads back unchanged.
#include <cstddef>
#include <cstdint>
#include <map>
#include <string>
#include <string_view>

#include "server/config.h"
#include "tests/fuzz/fuzz_support.h"

namespace placedb {
namespace {

using fuzz::Fail;
using server::ServerConfig;

// What the server runs with (ParseCommandLine validates before --print-config prints it) must
// print as YAML that loads back into the same configuration.
void CheckPrintedConfigLoads(const ServerConfig& config) {
  if (!server::ValidateServerConfig(config).ok()) return;
  const std::string printed = server::ConfigToYaml(config);
  ServerConfig again;
  if (Status s = server::ApplyConfigYaml(printed, &again); !s.ok()) {
    Fail("--print-config output does not load:\n" + printed, s);
  }
  const std::string reprinted = server::ConfigToYaml(again);
  PLACEDB_FUZZ_CHECK(
      reprinted == printed,
      "--print-config output\n" + printed + "loads into a different configuration:\n" + reprinted);
}

void FuzzYaml(const std::string& text) {
  ServerConfig config;
  const Status status = server::ApplyConfigYaml(text, &config);
  if (!status.ok()) {
    PLACEDB_FUZZ_CHECK(status.code() == StatusCode::kInvalidArgument,
                       "ApplyConfigYaml: unexpected error " + status.ToString());
    return;
  }
  CheckPrintedConfigLoads(config);
}

// Lines NAME=VALUE are the environment; anything else is ignored.
void FuzzEnvironment(std::string_view text) {
  std::map<std::string, std::string> environment;
  size_t begin = 0;
  while (begin <= text.size()) {
    size_t end = text.find('\n', begin);
    if (end == std::string_view::npos) end = text.size();
    const std::string_view line = text.substr(begin, end - begin);
    if (const size_t eq = line.find('='); eq != std::string_view::npos) {
      environment[std::string(line.substr(0, eq))] = std::string(line.substr(eq + 1));
    }
    begin = end + 1;
  }
  ServerConfig config;
  const Status status = server::ApplyEnvironment(&config, [&](const char* name) -> const char* {
    auto it = environment.find(name);
    return it == environment.end() ? nullptr : it->second.c_str();
  });
  if (!status.ok()) {
    PLACEDB_FUZZ_CHECK(status.code() == StatusCode::kInvalidArgument,
                       "ApplyEnvironment: unexpected error " + status.ToString());
    return;
  }
  CheckPrintedConfigLoads(config);
}

}  // namespace
}  // namespace placedb

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  const std::string_view payload(reinterpret_cast<const char*>(data) + 1, size - 1);
  if (data[0] % 4 == 3) {
    placedb::FuzzEnvironment(payload);
  } else {
    placedb::FuzzYaml(std::string(payload));
  }
  return 0;
}
