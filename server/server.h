// The placedb server: vocabularies, maps, worker pool, metrics endpoint, detector and the gRPC
// server (placedb.v1.PlaceDb + standard health service + reflection), with graceful shutdown.
//
//   auto server = Server::Start(config);   // listening once this returns
//   ...
//   server->Shutdown();  // NOT_SERVING, stop accepting, finish in-flight work (bounded by
//                        // shutdown_deadline_s), close maps (flush)
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "core/detect/detector.h"
#include "core/vocabulary/any_vocabulary.h"
#include "server/config.h"

namespace grpc {
class Server;
}

namespace placedb::server {

namespace auth {
class CallAuthorizer;
class TokenStore;
}  // namespace auth
class MapBackend;
class Console;
class MapRegistry;
class MemoryBudget;
class Metrics;
class ParsingService;
class PlaceDbService;
class VocabularyPolicyRunner;
class WorkerPool;

// Things a caller (a test) may hand in ready-made instead of having them loaded from the config.
struct ServerDeps {
  // Preloaded vocabularies (binary or float) by name; they replace the config's path for that
  // name.
  std::map<std::string, AnyVocabulary> vocabularies;
  // A ready detector; when null one is created from config.detector (if a model is set).
  std::shared_ptr<const Detector> detector;
  // The resident size the memory budget charges as the process at startup; unset: this process's
  // VmRSS (a test process's other work would make that vary from one start to the next).
  std::optional<uint64_t> resident_bytes = std::nullopt;
  // Cluster mode's worker role (server/cluster/worker.h): the MapBackend the service reaches
  // its maps through, made from the server's own maps (the worker's local copies) and metrics
  // once they exist. Unset: the embedded server (role single, server/backend/local_backend.h).
  std::function<Result<std::unique_ptr<MapBackend>>(MapRegistry*, Metrics*)> cluster_backend =
      nullptr;
};

class Server {
 public:
  // Loads, opens and starts listening. Errors: INVALID_ARGUMENT (config), NOT_FOUND / IO_ERROR /
  // CORRUPTION (vocabulary, data directory, detector model), IO_ERROR (cannot listen). An
  // optional vocabulary (config.optional_vocabularies) whose file is missing is a warning.
  static Result<std::unique_ptr<Server>> Start(const ServerConfig& config, ServerDeps deps = {});
  ~Server();  // Shutdown()

  int port() const { return port_; }                        // the bound gRPC port
  int metrics_port() const { return metrics_port_; }        // 0 when metrics are off
  int console_port() const { return console_port_; }        // 0 when the console is off
  MemoryBudget& memory_budget() const { return *budget_; }  // tests hold part of it as load
  const ServerConfig& config() const { return config_; }

  // Loads security.tokens_file again (SIGHUP): OK and the new principals apply to the next
  // call (and to open Ingest streams at their next message); on error the previous principals
  // stay. FAILED_PRECONDITION when no tokens file is configured.
  Status ReloadTokens();

  // Graceful shutdown; idempotent and thread-safe (other callers wait for the first).
  void Shutdown();
  // Blocks until Shutdown() has completed.
  void Wait();

 private:
  explicit Server(ServerConfig config);

  const ServerConfig config_;
  std::unique_ptr<Metrics> metrics_;
  std::unique_ptr<MemoryBudget> budget_;  // before the maps and the service that charge it
  std::unique_ptr<MapRegistry> maps_;
  std::shared_ptr<const Detector> detector_;
  std::unique_ptr<WorkerPool> pool_;
  std::unique_ptr<WorkerPool> query_pool_;  // Query's own (config query_threads)
  std::unique_ptr<MapBackend> backend_;     // the maps (local or the cluster's); before the service
  bool clustered_ = false;                  // backend_ is a cluster worker
  std::unique_ptr<PlaceDbService> service_;
  std::unique_ptr<auth::TokenStore> tokens_;  // null without security.tokens_file
  std::unique_ptr<auth::CallAuthorizer> authorizer_;
  std::unique_ptr<ParsingService> parsing_;  // what gRPC calls: parses, then calls service_
  std::unique_ptr<Console> console_;         // the web console over parsing_ (server/console)
  // Maps' vocabulary policies (single-node only); stopped first at shutdown.
  std::unique_ptr<VocabularyPolicyRunner> vocabulary_policy_;
  std::unique_ptr<grpc::Server> server_;
  int port_ = 0;
  int metrics_port_ = 0;
  int console_port_ = 0;

  Mutex shutdown_mutex_;
  CondVar shutdown_done_;
  bool shutdown_started_ GUARDED_BY(shutdown_mutex_) = false;
  bool shutdown_finished_ GUARDED_BY(shutdown_mutex_) = false;
};

// Loads a detector as config.detector describes (null when no model is configured).
Result<std::shared_ptr<const Detector>> CreateConfiguredDetector(const ServerConfig& config);

}  // namespace placedb::server
