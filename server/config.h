// The server's configuration: embedded defaults, overridden by a YAML file, then by PLACEDB_*
// environment variables, then by command-line flags (docs/service.md lists them all;
// server/placedb.yaml is a commented example).
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/storage/map_store.h"
#include "core/storage/snapshots.h"
#include "proto/convert_frame.h"

namespace placedb::server {

// Exceeding any of these is RESOURCE_EXHAUSTED, with a message naming the limit.
struct Limits {
  uint64_t max_message_bytes = uint64_t(16) << 20;  // one gRPC message (an observation)
  uint64_t max_image_pixels = 4096 * 4096;          // width * height of any image, mask, depth
  uint32_t max_descriptors_per_frame = 10000;       // keypoints sent, or a map's ORB/SIFT budget
  uint32_t max_boxes_per_frame = 256;               // agent boxes of one observation
  uint32_t max_concurrent_streams = 32;             // Ingest streams, snapshot transfers
  uint32_t max_queued_frames = 32;                  // frames waiting for a worker (all calls)
  uint32_t max_inflight_per_stream = 8;             // frames read but not yet answered, per stream
  uint32_t max_concurrent_unary = 64;               // unary calls being served at once
  uint32_t unary_queue_wait_ms = 2000;              // a unary call waits this long for room
  uint64_t memory_quota_bytes = uint64_t(1) << 30;  // gRPC's ResourceQuota (transport buffers)
  // An Ingest stream holds a handler thread and a max_concurrent_streams slot from its start:
  // the server closes (cancels) one whose IngestHeader has not arrived within
  // stream_header_timeout_ms, and one with no frame in flight that receives nothing for
  // stream_idle_timeout_ms, or whose answer the client has not taken for that long.
  uint32_t stream_header_timeout_ms = 10000;
  uint32_t stream_idle_timeout_ms = 60000;
  // The server's memory budget (server/ingest/memory_budget.h): the process at startup, the block
  // cache, every pending read, every frame and Query from its read to its answer. Reads wait for
  // it; a frame that still does not fit waits memory_wait_ms, then is refused
  // (RESOURCE_EXHAUSTED naming this key).
  uint64_t memory_budget_bytes = uint64_t(1) << 30;
  uint32_t memory_wait_ms = 2000;
  // The largest snapshot archive an UploadSnapshot may bring (announced or received). An
  // announced size must also fit the data directory's free space minus
  // storage.disk_reserve_bytes.
  uint64_t max_snapshot_bytes = uint64_t(64) << 30;

  // The ones an observation is checked against when it is decoded.
  wire::FrameLimits frame() const {
    return {.max_image_pixels = max_image_pixels,
            .max_descriptors_per_frame = max_descriptors_per_frame,
            .max_boxes_per_frame = max_boxes_per_frame};
  }
};

// Server-side detection (core/detect/detector.h). Absent model = detection off.
struct DetectorSettings {
  std::string backend = "yolox_onnx";  // or "darknet"
  std::string model;                   // .onnx (YOLOX) or .weights (darknet)
  std::string config;                  // darknet .cfg
  int input_size = 416;
  std::string preprocessing = "letterbox";  // letterbox | centre_crop | stretch
  bool rectangular_letterbox = true;  // YOLOX letterbox: input of the frame's aspect (detector.h)
  bool rewrite_graph = true;          // YOLOX: graph rewritten for OpenCV (detector.h)
  float confidence = 0.2f;
  // Box rules (core/detect/detector.h, ApplyBoxRules): a class's own score threshold (COCO name
  // -> (0, 1]), and plausibility as shares of the frame: boxes below min_box_area are dropped,
  // boxes above large_box_area need large_box_confidence (on by default: a low score on a third
  // of the frame is a false positive; docs/detector.md, "Box plausibility").
  std::map<std::string, float> class_confidence;
  float min_box_area = 0.0f;
  float large_box_area = 0.3f;
  float large_box_confidence = 0.5f;
  float nms_iou = 0.45f;
  std::vector<std::string> classes;  // COCO names reported; empty = the paper's six
  int max_concurrent_calls = 0;      // 0 = worker threads
  float merge_iou = 0.5f;            // box_source BOTH: server box duplicates an agent box above
  // A model that fails to load: false = log it and run with detection off (maps that need it
  // refuse frames with FAILED_PRECONDITION), true = refuse to start.
  bool required = false;
};

// The embedded vocabularies: default (ORB, var/vocabulary/default.pdbv) and sift (SIFT,
// var/vocabulary/sift-debian.pdbfv); tools/setup.sh builds both.
std::map<std::string, std::string> EmbeddedVocabularies();

// Transport security (docs/security.md). cert_file + key_file (PEM) = TLS 1.2 or later on the
// gRPC port; client_ca_file (a PEM bundle) as well = mutual TLS: a client without a certificate
// signed by one of these CAs is refused at the handshake, and the certificate's CN or a SAN can
// name the caller's principal (tokens file, `certificate_names`).
struct TlsSettings {
  std::string cert_file;
  std::string key_file;
  std::string client_ca_file;

  bool enabled() const { return !cert_file.empty(); }
  bool mutual() const { return !client_ca_file.empty(); }
};

// Who may call what (docs/security.md).
struct SecuritySettings {
  // Principals, their token hashes and rights (server/auth); reloaded on SIGHUP and when the file
  // changes. Empty = no tokens: every caller may do everything.
  std::string tokens_file;
  bool reflection = true;  // gRPC server reflection (the schema only; open to every caller)
  // Without tokens or mutual TLS anyone who reaches the port may do anything, so the server
  // refuses to listen (gRPC or metrics) beyond loopback unless this is set; when it is, every
  // start logs a warning saying so.
  bool allow_unauthenticated_remote = false;
};

// How Query and Ingest's matches search the inverted index (docs/index.md). Loop closure's own
// searches are not affected.
struct SearchSettings {
  // Threads one query may use (PlaceDatabase QueryOptions::search_threads; 1..64). The answer is
  // the same for every value; 2 roughly halves a large map's search on an idle 2-core machine,
  // and only waits for a core on a busy one.
  int threads = 1;
  // < 1: in maps of at least skip_words_min_places places, a query's words held by more than
  // this share of the places are skipped while scanning, and the best candidates by the other
  // words are rescored with them (QueryOptions::max_word_share): exact scores, approximate
  // candidates. (0, 1]; 1 (the default) = the exact ranking. 0.03 takes a 1M-place search from
  // ~21 to ~16 ms, and changes the top 1 of 3 % of new views of stored places (docs/index.md).
  double max_word_share = 1.0;
  uint64_t skip_words_min_places = 100000;
};

// Cluster mode (issue 18, docs/cluster.md): the process's role and the engines it uses. Role
// single (the default) is today's embedded server and ignores every other key here.
enum class ClusterRole { kSingle, kWorker, kShard };
const char* ClusterRoleName(ClusterRole role);  // "single" | "worker" | "shard"

struct ClusterSettings {
  ClusterRole role = ClusterRole::kSingle;
  // Prefix of the etcd keys (/placedb/<name>/...) and of the stream names: clusters sharing
  // engines keep apart by name. [A-Za-z0-9_-]+ (it is part of NATS subjects and stream names).
  std::string name = "placedb";
  std::vector<std::string> nats;  // nats://host:port of the NATS servers (worker, shard)
  std::vector<std::string> etcd;  // host:port of the etcd members (worker, shard)
  // Shard: its stable id (a StatefulSet pod name); empty = the hostname.
  std::string shard_id;
  // Shard: host:port workers use for its internal API; empty = <hostname>:<internal_listen port>.
  std::string advertise;
  std::string internal_listen = "127.0.0.1:50061";  // shard: placedb.cluster.v1.Shard
  int replicas = 2;                                 // map replicas (shards per map)
  int stream_replicas = 3;                          // JetStream replicas of each map's stream
  int replace_after_s = 30;  // a replica whose shard lease expired is replaced after this
  // Issue 35, compaction (docs/cluster.md): a map's stream gets a new base (a verified replica
  // checkpoint) and is purged below it once it holds more than this many records or bytes
  // beyond its base; 0 turns that measure off (both 0: streams keep every record).
  int64_t compact_after_records = 100000;
  int64_t compact_after_bytes = int64_t(1) << 30;
  // A purge never removes records stored less than this long ago: a frame resent within the
  // stream's duplicate window (2 min) gets a duplicate PubAck naming its first record, which the
  // worker reads back (docs/cluster.md "Duplicates"). Below 120 such a read may find nothing.
  int compact_keep_s = 150;
  // Mutual TLS on every internal hop (docs/cluster.md): the shard's internal API, its callers,
  // NATS and etcd, with tls.cert_file/key_file as this process's certificate (server and client)
  // and the CA bundle InternalCaFile() verifying every peer; plain text is then refused. YAML
  // on/off.
  bool internal_tls = false;
  // The CA bundle for internal peers; empty = tls.client_ca_file. Set it on a worker whose public
  // API should not require client certificates (tls.client_ca_file makes it mutual TLS).
  std::string internal_ca_file;

  // The shard id in effect: shard_id, or the hostname.
  std::string EffectiveShardId() const;
  // internal_ca_file, or else `tls`'s client_ca_file.
  const std::string& InternalCaFile(const TlsSettings& tls) const {
    return internal_ca_file.empty() ? tls.client_ca_file : internal_ca_file;
  }
};

struct ServerConfig {
  // Loopback by default: a server reachable from other hosts needs tokens or mutual TLS, or
  // security.allow_unauthenticated_remote.
  std::string listen = "127.0.0.1:50051";
  TlsSettings tls;
  SecuritySettings security;
  // Loopback by default: deployments that are scraped from elsewhere set 0.0.0.0:9464.
  std::string metrics_listen = "127.0.0.1:9464";  // empty = no metrics endpoint
  std::string metrics_path = "/metrics";
  // Serve the metrics over HTTPS with tls.cert_file/key_file (and, with tls.client_ca_file,
  // require a client certificate from a scraper).
  bool metrics_tls = false;
  // Requests handled at once (past their headers; 64 connections may be open, http_endpoint.h),
  // and how long a request may take to arrive, and its answer to be written, before a close.
  int metrics_threads = 4;
  uint32_t metrics_request_timeout_ms = 5000;
  // The web console (docs/console.md): its pages and JSON API on their own HTTP listener.
  // Loopback by default; beyond it the same rule as the gRPC port (tokens or mutual TLS).
  std::string console_listen = "127.0.0.1:9465";  // empty = no console
  // Serve the console over HTTPS with tls.cert_file/key_file (and, with tls.client_ca_file,
  // require a client certificate from the browser).
  bool console_tls = false;
  int console_threads = 4;                      // requests past their headers at once
  uint32_t console_request_timeout_ms = 30000;  // per read and write; per request and answer
  uint64_t console_max_request_bytes = uint64_t(16) << 20;  // larger bodies: 413
  std::string data_dir = "./var/data";
  int threads = 0;         // worker threads; 0 = hardware concurrency
  int opencv_threads = 1;  // cv::setNumThreads; frames are parallel already. -1 = leave alone
  // Query's own workers, so that ingest cannot fill them (issue 17); 0 = as many as `threads`.
  int query_threads = 0;
  // The ingest workers' nice value (0..19; queries keep the normal priority): on a busy machine
  // queries then get the CPU first. 0 = off.
  int ingest_nice = 10;
  SearchSettings search;
  // name -> vocabulary file: binary .pdbv / DBoW2 text (ORB maps) or float .pdbfv (SIFT maps).
  // "default" is required (CreateMap with no vocabulary uses it).
  std::map<std::string, std::string> vocabularies = EmbeddedVocabularies();
  // Of those, the ones the server runs without when their file is missing (a warning; maps that
  // need one are unavailable, with the reason): the embedded defaults other than "default", as
  // long as they keep their embedded path. A vocabulary named by a flag is always required.
  std::set<std::string> optional_vocabularies = {"sift"};
  StorageOptions storage;
  SnapshotOptions snapshots;  // YAML storage.snapshots_keep_per_map
  Limits limits;
  double shutdown_deadline_s = 30;  // in-flight calls get this long on SIGTERM/SIGINT
  // How often maps' vocabulary policies are checked (MapConfig.vocabulary_policy, issue 29).
  // Not in the YAML: tests shorten it.
  uint32_t vocabulary_policy_interval_ms = 30000;
  DetectorSettings detector;       // used when detector.model is set
  std::string log_level = "info";  // trace | debug | info | warn | error | off
  ClusterSettings cluster;         // cluster: role single unless set

  bool detector_enabled() const { return !detector.model.empty(); }
  // Callers must prove who they are: a tokens file, or mutual TLS.
  bool authenticates_callers() const { return !security.tokens_file.empty() || tls.mutual(); }
  int worker_threads() const;  // threads, or the hardware concurrency
  int query_worker_threads() const { return query_threads > 0 ? query_threads : worker_threads(); }
};

// Checks values (not files): INVALID_ARGUMENT naming the first bad key. Text values must not
// contain control characters.
Status ValidateServerConfig(const ServerConfig& config);

// Applies a YAML file's keys over `config`. Unknown keys are errors (typos do not pass silently).
Status ApplyConfigFile(const std::string& path, ServerConfig* config);
Status ApplyConfigYaml(const std::string& yaml_text, ServerConfig* config);  // for tests

// Applies PLACEDB_LISTEN, PLACEDB_DATA_DIR, PLACEDB_METRICS_LISTEN, PLACEDB_METRICS_PORT,
// PLACEDB_METRICS_TLS, PLACEDB_CONSOLE_LISTEN, PLACEDB_CONSOLE_TLS, PLACEDB_THREADS,
// PLACEDB_LOG_LEVEL, PLACEDB_DETECTOR_MODEL, PLACEDB_MEMORY_BUDGET_BYTES, PLACEDB_TLS_CERT_FILE,
// PLACEDB_TLS_KEY_FILE, PLACEDB_TLS_CLIENT_CA_FILE, PLACEDB_TOKENS_FILE,
// PLACEDB_ALLOW_UNAUTHENTICATED_REMOTE. `getenv` is injectable for tests. Also
// PLACEDB_MAX_SNAPSHOT_BYTES (limits.max_snapshot_bytes), PLACEDB_INTERNAL_TLS
// (cluster.internal_tls), PLACEDB_INTERNAL_CA_FILE (cluster.internal_ca_file).
Status ApplyEnvironment(ServerConfig* config,
                        const std::function<const char*(const char*)>& getenv);

// The whole chain for main(): defaults < --config file (or PLACEDB_CONFIG) < environment <
// flags. `exit_code` is set when the process should exit right away (--help, --version,
// --print-config, or a usage error already reported on stderr).
struct CommandLine {
  ServerConfig config;
  std::optional<int> exit_code;
};
Result<CommandLine> ParseCommandLine(int argc, const char* const* argv,
                                     const std::function<const char*(const char*)>& getenv);

// The effective configuration as YAML (--print-config; loadable with --config).
std::string ConfigToYaml(const ServerConfig& config);

// The embedded defaults' relative paths (the vocabularies at var/vocabulary/..., data_dir
// ./var/data) do not depend on the working directory: they are looked up under these roots, in
// order. $PLACEDB_HOME alone when it is set; else the checkout holding `executable` (the nearest
// of its parent directories with server/placedb.yaml, e.g. build/server/placedb-server ->
// the checkout), then the working directory (as before). Paths the operator gave (file,
// environment, flags) keep their meaning: relative to the working directory.
struct PathRoot {
  std::string dir;  // absolute
  std::string why;  // "PLACEDB_HOME", "the checkout of <exe>", "the working directory"
};
std::vector<PathRoot> DefaultPathRoots(const std::function<const char*(const char*)>& getenv,
                                       const std::string& executable);

// Rewrites the embedded defaults still in `config` to absolute paths under the first root that
// holds the default vocabulary (var/vocabulary/default.pdbv), or the first root when the default
// vocabulary is the operator's own. NOT_FOUND naming every path tried when no root holds it.
Status ResolveDefaultPaths(const std::vector<PathRoot>& roots, ServerConfig* config);

}  // namespace placedb::server
