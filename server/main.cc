// placedb-server: the gRPC service (docs/service.md).
//
//   placedb-server [--config placedb.yaml] [--listen 127.0.0.1:50051] [--data-dir ./var/data] ...
//
//   placedb-server tokens add|list|revoke|rotate ...   (server/auth/tokens_command.h)
//
// cluster.role (--role) picks what the process is (docs/cluster.md): single (the embedded
// server), worker (the public API on the cluster: server/cluster/worker.h) or shard (map replicas
// and the internal API: server/cluster/shard.h). A build without libnats has single only.
//
// SIGHUP reloads the tokens file (security.tokens_file; a bad file keeps the previous principals).
// SIGTERM / SIGINT start a graceful shutdown (a sigwait thread does the work, never a signal
// handler); a second signal during it exits at once with status 1 (acknowledged places are
// durable either way). Exit status 0 after a clean shutdown, 2 for a bad configuration, 1 when
// the server cannot start.
//
// The log: info and below on stdout, warnings and errors on stderr (docs/service.md, "Logs").
// The embedded defaults' files are found from the executable, not the working directory
// (ResolveDefaultPaths in server/config.h), so the server starts from any directory.
#include <signal.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <memory>
#include <string>
#include <thread>

#include "server/allocator.h"
#include "server/auth/tokens_command.h"
#include "server/config.h"
#include "server/server.h"
#ifdef PLACEDB_CLUSTER_ROLES
#include "server/cluster/shard.h"
#include "server/cluster/worker.h"
#include "server/metrics.h"
#endif

namespace {

// Warnings and errors on stderr, where a shell, a supervisor or a test looks for them; the rest
// on stdout. Each stream keeps its colours when it is a terminal.
class SplitLevelSink final : public spdlog::sinks::sink {
 public:
  void log(const spdlog::details::log_msg& message) override {
    (message.level >= spdlog::level::warn ? errors_ : rest_)->log(message);
  }
  void flush() override {
    rest_->flush();
    errors_->flush();
  }
  void set_pattern(const std::string& pattern) override {
    rest_->set_pattern(pattern);
    errors_->set_pattern(pattern);
  }
  void set_formatter(std::unique_ptr<spdlog::formatter> formatter) override {
    errors_->set_formatter(formatter->clone());
    rest_->set_formatter(std::move(formatter));
  }

 private:
  std::shared_ptr<spdlog::sinks::sink> rest_ =
      std::make_shared<spdlog::sinks::stdout_color_sink_mt>();
  std::shared_ptr<spdlog::sinks::sink> errors_ =
      std::make_shared<spdlog::sinks::stderr_color_sink_mt>();
};

std::string ExecutablePath() {
  std::error_code error;
  const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", error);
  return error ? std::string() : self.string();
}

}  // namespace

#ifdef PLACEDB_CLUSTER_ROLES
namespace {

// The shard role: map replicas and the internal API (server/cluster/shard.h), plus the metrics
// endpoint; no public API. Runs until SIGTERM/SIGINT. Exit 1 when it cannot start.
int RunShard(const placedb::server::ServerConfig& config, const sigset_t& signals) {
  namespace server = placedb::server;
  placedb::cluster::ShardOptions options;
  const server::ClusterSettings& c = config.cluster;
  options.cluster_name = c.name;
  options.nats = c.nats;
  options.etcd = c.etcd;
  options.shard_id = c.EffectiveShardId();
  options.advertise = c.advertise;
  if (options.advertise.empty()) {
    // Validated: the hostname resolves; workers dial it on the internal port.
    char host[256] = {};
    gethostname(host, sizeof(host) - 1);
    options.advertise = host;
    options.advertise += c.internal_listen.substr(c.internal_listen.rfind(':'));
  }
  options.internal_listen = c.internal_listen;
  if (c.internal_tls) {
    auto tls = placedb::cluster::LoadInternalTls(config.tls, c.internal_ca_file);
    if (!tls.ok()) {
      spdlog::error("cannot start: {}", tls.status().ToString());
      return 1;
    }
    options.tls = std::move(tls).value();
  }
  options.data_dir = config.data_dir;
  options.storage = config.storage;
  options.search = config.search;
  options.max_descriptors_per_frame = config.limits.max_descriptors_per_frame;
  for (const auto& [name, path] : config.vocabularies) {
    auto vocabulary = placedb::AnyVocabulary::Load(path);
    if (!vocabulary.ok()) {
      if (config.optional_vocabularies.count(name)) {
        spdlog::warn("vocabulary '{}' ({}) not loaded: {}", name, path,
                     vocabulary.status().ToString());
        continue;
      }
      spdlog::error("cannot start: vocabulary '{}' ({}): {}", name, path,
                    vocabulary.status().ToString());
      return 1;
    }
    options.vocabularies.emplace(name, std::move(vocabulary).value());
  }
  server::Metrics metrics;
  if (!config.metrics_listen.empty()) {
    server::Metrics::Endpoint endpoint;
    endpoint.listen = config.metrics_listen;
    endpoint.path = config.metrics_path;
    endpoint.threads = config.metrics_threads;
    endpoint.request_timeout_ms = config.metrics_request_timeout_ms;
    if (placedb::Status served = metrics.Serve(endpoint, nullptr); !served.ok()) {
      spdlog::error("cannot start: metrics: {}", served.ToString());
      return 1;
    }
  }
  options.metrics = &metrics;
  auto shard = placedb::cluster::Shard::Start(std::move(options));
  if (!shard.ok()) {
    spdlog::error("cannot start: {}", shard.status().ToString());
    return 1;
  }
  spdlog::info("shard '{}' serving the internal API on port {} ({})", (*shard)->shard_id(),
               (*shard)->internal_port(),
               c.internal_tls ? "mutual TLS; NATS and etcd over TLS" : "plaintext");
  int received = 0;
  sigwait(&signals, &received);
  spdlog::info("received {}, stopping the shard", strsignal(received));
  shard->reset();
  metrics.StopServing();
  return 0;
}

}  // namespace
#endif

int main(int argc, char** argv) {
  spdlog::set_default_logger(
      std::make_shared<spdlog::logger>("placedb", std::make_shared<SplitLevelSink>()));
  spdlog::set_pattern("%Y-%m-%dT%H:%M:%S.%e%z %^%l%$ %v");
  // Its own command group, before the server's flags are parsed (those stay as they are).
  if (argc >= 2 && std::string(argv[1]) == "tokens") {
    return placedb::server::auth::RunTokensCommand(
        argc - 1, argv + 1, std::cout, std::cerr,
        [](const char* name) { return std::getenv(name); });
  }
  // Block the shutdown signals in every thread (threads inherit the mask); one thread waits for
  // them with sigwait.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  // SIGHUP too, taken by the same thread: a reload, not a shutdown (and never the default
  // action, which would end the process).
  sigset_t with_reload = signals;
  sigaddset(&with_reload, SIGHUP);
  pthread_sigmask(SIG_BLOCK, &with_reload, nullptr);
  // After the mask: the allocator may start a thread (glibc's trimmer), which must not take the
  // shutdown signals.
  placedb::server::TuneAllocator();
  signal(SIGPIPE, SIG_IGN);

  auto command_line = placedb::server::ParseCommandLine(
      argc, argv, [](const char* name) { return std::getenv(name); });
  if (!command_line.ok()) {
    spdlog::error("{}", command_line.status().ToString());
    return 2;
  }
  if (command_line->exit_code) return *command_line->exit_code;
  placedb::server::ServerConfig& config = command_line->config;
  spdlog::set_level(spdlog::level::from_str(config.log_level));
  if (placedb::Status found = placedb::server::ResolveDefaultPaths(
          placedb::server::DefaultPathRoots([](const char* name) { return std::getenv(name); },
                                            ExecutablePath()),
          &config);
      !found.ok()) {
    spdlog::error("cannot start: {}", found.ToString());
    return 1;
  }
  spdlog::info("allocator: {}", placedb::server::AllocatorDescription());

  placedb::server::ServerDeps deps;
  switch (config.cluster.role) {
    case placedb::server::ClusterRole::kSingle:
      break;
#ifdef PLACEDB_CLUSTER_ROLES
    case placedb::server::ClusterRole::kWorker:
      deps.cluster_backend = [&config](placedb::server::MapRegistry* maps,
                                       placedb::server::Metrics* metrics)
          -> placedb::Result<std::unique_ptr<placedb::server::MapBackend>> {
        auto worker = placedb::server::ClusterWorker::Start(config, maps, metrics);
        if (!worker.ok()) return worker.status();
        return std::unique_ptr<placedb::server::MapBackend>(std::move(worker).value());
      };
      break;
    case placedb::server::ClusterRole::kShard:
      return RunShard(config, signals);
#else
    default:
      spdlog::error("cluster.role {}: this build has no cluster mode (it needs libnats-dev)",
                    placedb::server::ClusterRoleName(config.cluster.role));
      return 2;
#endif
  }
  spdlog::info("role: {}", placedb::server::ClusterRoleName(config.cluster.role));
  auto server = placedb::server::Server::Start(config, std::move(deps));
  if (!server.ok()) {
    spdlog::error("cannot start: {}", server.status().ToString());
    return 1;
  }

  std::thread signal_thread([&server, &config, signals, with_reload] {
    int received = 0;
    while (sigwait(&with_reload, &received) == 0 && received == SIGHUP) {
      if (config.security.tokens_file.empty()) {
        spdlog::info("received SIGHUP: no tokens file to reload");
        continue;
      }
      spdlog::info("received SIGHUP: reloading the tokens file {}", config.security.tokens_file);
      (void)(*server)->ReloadTokens();  // logs its own outcome
    }
    spdlog::info("received {}, shutting down gracefully", strsignal(received));
    std::thread second([signals] {
      int again = 0;
      sigwait(&signals, &again);
      spdlog::warn("received {} during shutdown: exiting now", strsignal(again));
      std::_Exit(1);
    });
    second.detach();
    (*server)->Shutdown();
  });
  (*server)->Wait();
  signal_thread.join();
  server->reset();
  return 0;
}
