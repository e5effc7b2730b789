#include "server/server.h"

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/impl/server_builder_option.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>

#include "server/auth/call_auth.h"
#include "server/auth/token_store.h"
#include "server/backend/local_backend.h"
#include "server/backend/map_registry.h"
#include "server/backend/vocabulary_policy.h"
#include "server/console/console.h"
#include "server/ingest/memory_budget.h"
#include "server/ingest/worker_pool.h"
#include "server/metrics.h"
#include "server/net/http_endpoint.h"
#include "server/net/transport_security.h"
#include "server/rpc/parsing_service.h"
#include "server/rpc/service.h"

namespace placedb::server {

namespace {

constexpr char kServiceName[] = "placedb.v1.PlaceDb";

struct LoadedVocabularies {
  std::vector<VocabularyEntry> loaded;
  std::vector<MissingVocabulary> missing;  // optional ones whose file is missing
};

Result<LoadedVocabularies> LoadVocabularies(const ServerConfig& config,
                                            const std::map<std::string, AnyVocabulary>& preloaded) {
  LoadedVocabularies out;
  for (const auto& [name, path] : config.vocabularies) {
    VocabularyEntry entry;
    entry.name = name;
    entry.path = path;
    if (auto it = preloaded.find(name); it != preloaded.end() && it->second) {
      entry.vocabulary = it->second;
    } else {
      std::error_code error;
      if (config.optional_vocabularies.count(name) && !std::filesystem::exists(path, error)) {
        // An embedded default the machine has not built (tools/setup.sh does): run without it.
        spdlog::warn(
            "vocabulary '{}': {} is missing; running without it (maps that need it are "
            "unavailable; tools/setup.sh builds it)",
            name, path);
        out.missing.push_back({name, path, "file missing"});
        continue;
      }
      auto loaded = AnyVocabulary::Load(path);
      if (!loaded.ok()) {
        return loaded.status().WithContext("vocabulary '" + name + "' (" + path + ")");
      }
      entry.vocabulary = std::move(loaded).value();
    }
    for (const VocabularyEntry& other : out.loaded) {
      if (other.vocabulary.checksum() == entry.vocabulary.checksum()) {
        // Maps pick their vocabulary by checksum: two names for one vocabulary are ambiguous.
        return Status::InvalidArgument("vocabularies: '" + name + "' and '" + other.name +
                                       "' are the same vocabulary (checksum " +
                                       entry.vocabulary.checksum_hex() + ")");
      }
    }
    spdlog::info("vocabulary '{}': {} ({}, {} words, k={}, L={}, checksum {})", name, path,
                 entry.vocabulary.kind(), entry.vocabulary.word_count(),
                 entry.vocabulary.branching(), entry.vocabulary.depth(),
                 entry.vocabulary.checksum_hex());
    out.loaded.push_back(std::move(entry));
  }
  return out;
}

// Server reflection for this server only, on or off: InitProtoReflectionServerBuilderPlugin()
// would turn it on for every server the process builds after it.
class ReflectionOption final : public grpc::ServerBuilderOption {
 public:
  explicit ReflectionOption(bool enabled) : enabled_(enabled) {}
  void UpdateArguments(grpc::ChannelArguments*) override {}
  void UpdatePlugins(std::vector<std::unique_ptr<grpc::ServerBuilderPlugin>>* plugins) override {
    constexpr char kName[] = "proto_server_reflection";
    // One registered globally (by other code in the process) is removed or kept, as configured.
    plugins->erase(std::remove_if(plugins->begin(), plugins->end(),
                                  [&](const auto& plugin) { return plugin->name() == kName; }),
                   plugins->end());
    if (enabled_) {
      plugins->push_back(std::make_unique<grpc::reflection::ProtoServerReflectionPlugin>());
    }
  }

 private:
  const bool enabled_;
};

// VmRSS of this process, 0 when /proc is not there.
uint64_t ResidentBytes() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stoull(line.substr(6)) * 1024;  // kB
  }
  return 0;
}

}  // namespace

Result<std::shared_ptr<const Detector>> CreateConfiguredDetector(const ServerConfig& config) {
  if (!config.detector_enabled()) return std::shared_ptr<const Detector>();
  const DetectorSettings& s = config.detector;
  DetectorConfig d;
  auto backend = ParseDetectorBackend(s.backend);
  if (!backend.ok()) return backend.status().WithContext("detector.backend");
  d.backend = *backend;
  d.model_path = s.model;
  d.config_path = s.config;
  d.input_size = s.input_size;
  auto preprocessing = ParsePreprocessing(s.preprocessing);
  if (!preprocessing.ok()) return preprocessing.status().WithContext("detector.preprocessing");
  d.preprocessing = *preprocessing;
  d.rectangular_letterbox = s.rectangular_letterbox;
  d.rewrite_graph = s.rewrite_graph;
  d.confidence_threshold = s.confidence;
  d.nms_iou_threshold = s.nms_iou;
  d.class_confidence = s.class_confidence;
  d.min_box_area = s.min_box_area;
  d.large_box_area = s.large_box_area;
  d.large_box_confidence = s.large_box_confidence;
  if (!s.classes.empty()) d.dynamic_classes = s.classes;
  d.opencv_threads = 0;  // the server sets OpenCV's threads itself (opencv_threads)
  d.max_concurrent_calls =
      s.max_concurrent_calls > 0 ? s.max_concurrent_calls : config.worker_threads();
  auto detector = CreateDetector(d);
  if (!detector.ok()) return detector.status().WithContext("detector");
  return std::shared_ptr<const Detector>(std::move(detector).value());
}

Server::Server(ServerConfig config) : config_(std::move(config)) {}

Result<std::unique_ptr<Server>> Server::Start(const ServerConfig& config, ServerDeps deps) {
  PLACEDB_RETURN_IF_ERROR(ValidateServerConfig(config));
  // Before anything slow: the safe default, and the TLS files (a bad one fails at once).
  PLACEDB_RETURN_IF_ERROR(CheckExposure(config));
  auto credentials = MakeServerCredentials(config.tls);
  if (!credentials.ok()) return credentials.status();
  std::unique_ptr<Server> server(new Server(config));
  const ServerConfig& c = server->config_;
  if (c.opencv_threads >= 0) cv::setNumThreads(c.opencv_threads);

  auto vocabularies = LoadVocabularies(c, deps.vocabularies);
  if (!vocabularies.ok()) return vocabularies.status();
  auto maps = MapRegistry::Open(c.data_dir, c.storage, std::move(vocabularies->loaded),
                                std::move(vocabularies->missing), c.snapshots);
  if (!maps.ok()) return maps.status();
  server->maps_ = std::move(maps).value();

  std::string detector_status = "off";
  if (deps.detector) {
    server->detector_ = deps.detector;
  } else {
    auto detector = CreateConfiguredDetector(c);
    if (detector.ok()) {
      server->detector_ = std::move(detector).value();
    } else if (c.detector.required) {
      return detector.status();
    } else {
      // Degraded, not fatal (docs/detector.md): agents' boxes still work.
      detector_status = "off: " + detector.status().ToString();
      spdlog::error("server-side detection is OFF: {} (set detector.required to refuse to start)",
                    detector.status().ToString());
    }
  }
  spdlog::info("detector: {}", server->detector_ ? server->detector_->Describe() : detector_status);

  // The memory budget's fixed part: the process as it starts serving (code, libraries,
  // vocabularies, the maps' indexes as opened, the detector: its resident size now) and the block
  // cache, which fills later. What is left is for requests, and must hold at least a few whole
  // messages (each read is granted one first).
  server->budget_ = std::make_unique<MemoryBudget>(c.limits.memory_budget_bytes);
  for (const auto& [what, bytes] :
       {std::pair<std::string, uint64_t>{"the process at startup (code, libraries, vocabularies, "
                                         "maps, detector)",
                                         deps.resident_bytes.value_or(ResidentBytes())},
        std::pair<std::string, uint64_t>{"storage.block_cache_bytes",
                                         c.storage.block_cache_bytes}}) {
    // A configuration error, not a load: INVALID_ARGUMENT.
    if (Status reserved = server->budget_->ReserveFixed(what, bytes); !reserved.ok()) {
      return Status::InvalidArgument(reserved.message());
    }
  }
  if (const uint64_t left = c.limits.memory_budget_bytes - server->budget_->fixed();
      left < 4 * c.limits.max_message_bytes) {
    return Status::InvalidArgument(
        "limits.memory_budget_bytes = " + std::to_string(c.limits.memory_budget_bytes) +
        " leaves " + std::to_string(left) +
        " bytes beyond its fixed part (the process at startup, the block cache): less than 4 x "
        "limits.max_message_bytes");
  }

  server->metrics_ = std::make_unique<Metrics>();
  Metrics* metrics = server->metrics_.get();
  if (!c.security.tokens_file.empty()) {
    auto tokens = auth::TokenStore::Open(c.security.tokens_file,
                                         [metrics](bool ok) { metrics->TokensReloaded(ok); });
    if (!tokens.ok()) return tokens.status();
    server->tokens_ = std::move(tokens).value();
    server->tokens_->StartWatching(std::chrono::seconds(1));
    spdlog::info("tokens file {}: {} principals; every call needs a token{}",
                 c.security.tokens_file, server->tokens_->snapshot()->principals().size(),
                 c.tls.mutual() ? " or a client certificate a principal lists" : "");
  } else if (c.tls.mutual()) {
    spdlog::info(
        "no tokens file: every holder of a client certificate the client CA verifies may "
        "do everything");
  }
  server->authorizer_ = std::make_unique<auth::CallAuthorizer>(
      server->tokens_.get(), c.tls.mutual(),
      [metrics](auth::DenyReason reason, const std::string& method) {
        metrics->AuthDenied(auth::DenyReasonLabel(reason), method);
      });
  server->pool_ = std::make_unique<WorkerPool>(
      c.worker_threads(), c.limits.max_queued_frames,
      [metrics](size_t depth) { metrics->SetQueueDepth(depth); }, c.ingest_nice);
  // Queries on workers of their own at the normal priority: ingest cannot fill them (issue 17).
  server->query_pool_ =
      std::make_unique<WorkerPool>(c.query_worker_threads(), c.limits.max_queued_frames);
  if (deps.cluster_backend) {
    auto backend = deps.cluster_backend(server->maps_.get(), metrics);
    if (!backend.ok()) return backend.status();
    server->backend_ = std::move(backend).value();
    server->clustered_ = true;
  } else {
    server->backend_ =
        std::make_unique<LocalBackend>(server->config_, server->maps_.get(), metrics);
  }
  server->service_ = std::make_unique<PlaceDbService>(
      server->config_, server->maps_.get(), server->backend_.get(), server->pool_.get(), metrics,
      server->detector_.get(), detector_status, server->budget_.get(), server->query_pool_.get());

  if (!server->clustered_) {
    server->vocabulary_policy_ = std::make_unique<VocabularyPolicyRunner>(
        server->maps_.get(), std::chrono::milliseconds(c.vocabulary_policy_interval_ms));
    server->vocabulary_policy_->Start();
  }

  // Requests are parsed by ParsingService, so malformed ones get INVALID_ARGUMENT with a reason.
  server->parsing_ =
      std::make_unique<ParsingService>(server->service_.get(), server->authorizer_.get());
  if (const auto missing = server->parsing_->Unregistered(); !missing.empty()) {
    return Status::Internal("server/rpc/parsing_service.cc does not register " + missing.front());
  }
  // The console before gRPC starts: GetServerInfo reports its bound address from the first call.
  if (!c.console_listen.empty()) {
    const bool certificates = c.console_tls && c.tls.mutual();
    server->console_ = std::make_unique<Console>(server->parsing_.get(),
                                                 !c.security.tokens_file.empty() || certificates);
    HttpEndpointSettings console;
    console.name = "console";
    console.listen = c.console_listen;
    console.threads = c.console_threads;
    console.request_timeout_ms = c.console_request_timeout_ms;
    console.max_request_bytes = c.console_max_request_bytes;
    if (c.console_tls) console.tls = c.tls;
    PLACEDB_RETURN_IF_ERROR(server->console_->Serve(console));
    server->console_port_ = server->console_->port();
    server->service_->SetConsoleUrl(server->console_->url());
  }

  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  builder.SetOption(std::make_unique<ReflectionOption>(c.security.reflection));
  builder.AddListeningPort(c.listen, *credentials, &server->port_);
  // gRPC sets SO_REUSEPORT by default: a second server on this port would bind it too and the
  // kernel would split the connections between two databases. A port in use is an error.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  builder.RegisterService(server->parsing_.get());
  builder.SetMaxReceiveMessageSize(int(c.limits.max_message_bytes));
  // Transport memory and handler threads are bounded: a flood of calls gets RESOURCE_EXHAUSTED
  // instead of exhausting the machine. Each open stream holds a handler thread.
  // The transport's buffers are part of the memory budget (a pending read holds a reservation of
  // a whole message): the quota never exceeds it.
  grpc::ResourceQuota quota("placedb");
  quota.Resize(size_t(std::min(c.limits.memory_quota_bytes, c.limits.memory_budget_bytes)));
  quota.SetMaxThreads(int(c.limits.max_concurrent_streams + c.limits.max_concurrent_unary + 8));
  builder.SetResourceQuota(quota);
  builder.AddChannelArgument(GRPC_ARG_MAX_CONCURRENT_STREAMS,
                             int(c.limits.max_concurrent_streams + c.limits.max_concurrent_unary));
  // Robots drop off networks: find dead connections (and their streams) within ~80 s. Clients
  // may ping every 4 s or more (the Python SDK: 5 s), so that they find a vanished server fast.
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIME_MS, 60000);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, 20000);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS, 4000);
  server->server_ = builder.BuildAndStart();
  if (!server->server_ || server->port_ == 0) {
    server->server_.reset();
    return Status::IoError("cannot listen on " + c.listen +
                           " (address in use, or not a local address?)");
  }
  if (auto* health = server->server_->GetHealthCheckService()) {
    health->SetServingStatus(true);
    health->SetServingStatus(kServiceName, true);
  }

  if (!c.metrics_listen.empty()) {
    PlaceDbService* service = server->service_.get();
    const MemoryBudget* budget = server->budget_.get();
    Metrics::Endpoint endpoint;
    endpoint.listen = c.metrics_listen;
    endpoint.path = c.metrics_path;
    endpoint.threads = c.metrics_threads;
    endpoint.request_timeout_ms = c.metrics_request_timeout_ms;
    if (c.metrics_tls) endpoint.tls = c.tls;
    if (server->tokens_) {
      // Scrapes need basic auth of a principal with `metrics` or `admin` (docs/security.md).
      const auth::CallAuthorizer* authorizer = server->authorizer_.get();
      endpoint.authorize = [authorizer](const std::string& peer, const std::string& user,
                                        const std::string& password) {
        return authorizer->AuthorizeScrape(peer, user, password);
      };
    }
    Status serving = metrics->Serve(endpoint, [service, metrics, budget] {
      service->RefreshMapGauges();
      metrics->SetMemoryBudget(budget->limit(), budget->fixed(), budget->in_use());
    });
    if (!serving.ok()) {
      server->Shutdown();
      return serving;
    }
    server->metrics_port_ = metrics->port();
  }
  spdlog::info("gRPC transport: {}; metrics: {}", DescribeTransport(c.tls),
               c.metrics_listen.empty() ? "off"
               : c.metrics_tls          ? "HTTPS with the same files"
                                        : "plaintext HTTP");
  spdlog::info("placedb-server {} listening on {} (port {}), metrics {}, data {}, {} workers",
               PLACEDB_VERSION, c.listen, server->port_,
               c.metrics_listen.empty() ? std::string("off")
                                        : c.metrics_listen + c.metrics_path + " (port " +
                                              std::to_string(server->metrics_port_) + ")",
               c.data_dir, server->pool_->threads());
  spdlog::info("console: {}", server->console_ ? server->console_->url() : std::string("off"));
  // Again after the summary an operator reads (CheckExposure said it first, before the slow part).
  for (const std::string& warning : CleartextTokenWarnings(c)) {
    spdlog::warn("SECURITY WARNING: {}", warning);
  }
  return server;
}

Server::~Server() {
  Shutdown();
}

Status Server::ReloadTokens() {
  if (!tokens_) return Status::FailedPrecondition("no tokens file is configured");
  return tokens_->Reload();
}

void Server::Shutdown() {
  {
    MutexLock lock(shutdown_mutex_);
    if (shutdown_started_) {
      while (!shutdown_finished_) shutdown_done_.Wait(shutdown_mutex_);
      return;
    }
    shutdown_started_ = true;
  }
  const auto started = std::chrono::steady_clock::now();
  if (vocabulary_policy_) vocabulary_policy_->Stop();  // cancels a switch in progress
  if (server_) {
    spdlog::info("shutting down: refusing new calls, finishing in-flight work (at most {} s)",
                 config_.shutdown_deadline_s);
    if (auto* health = server_->GetHealthCheckService()) {
      health->SetServingStatus(false);
    }
    service_->BeginDrain();
    // Our calls finish first (bounded by the deadline); then gRPC shuts down at once: it cancels
    // whatever is left and closes connections instead of waiting for idle clients to notice
    // its GOAWAY (an idle synchronous client may take seconds to).
    const auto deadline =
        started + std::chrono::milliseconds(int64_t(config_.shutdown_deadline_s * 1000.0));
    if (!service_->WaitIdle(deadline)) {
      spdlog::warn("shutdown deadline ({} s) passed with calls in flight: cancelling them",
                   config_.shutdown_deadline_s);
    }
    server_->Shutdown(std::chrono::system_clock::now());  // returns once every handler returned
    server_->Wait();
  }
  if (console_) console_->Stop();  // its calls go through service_: stopped with gRPC's
  if (pool_) pool_->Stop();
  if (query_pool_) query_pool_->Stop();
  if (metrics_) metrics_->StopServing();
  if (tokens_) tokens_->StopWatching();
  if (clustered_) backend_.reset();  // the engines' connections; no call uses them any more
  if (maps_) maps_->CloseAll();      // flushes and closes RocksDB
  spdlog::info("shutdown complete in {:.3f} s",
               std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count());
  MutexLock lock(shutdown_mutex_);
  shutdown_finished_ = true;
  shutdown_done_.NotifyAll();
}

void Server::Wait() {
  MutexLock lock(shutdown_mutex_);
  while (!shutdown_finished_) shutdown_done_.Wait(shutdown_mutex_);
}

}  // namespace placedb::server
