#include "server/config.h"

#include <netdb.h>
#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <CLI/CLI.hpp>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <set>
#include <thread>
#include <utility>
#include <vector>

#include "core/base/files.h"

namespace placedb::server {

std::map<std::string, std::string> EmbeddedVocabularies() {
  return {{"default", "var/vocabulary/default.pdbv"}, {"sift", "var/vocabulary/sift-debian.pdbfv"}};
}

const char* ClusterRoleName(ClusterRole role) {
  switch (role) {
    case ClusterRole::kSingle:
      return "single";
    case ClusterRole::kWorker:
      return "worker";
    case ClusterRole::kShard:
      return "shard";
  }
  return "single";
}

namespace {

std::string Hostname() {
  char name[256] = {};
  if (gethostname(name, sizeof(name) - 1) != 0) return "";
  return name;
}

Status ParseRole(const std::string& text, const std::string& key, ClusterRole* role) {
  if (text == "single") {
    *role = ClusterRole::kSingle;
  } else if (text == "worker") {
    *role = ClusterRole::kWorker;
  } else if (text == "shard") {
    *role = ClusterRole::kShard;
  } else {
    return Status::InvalidArgument(key + ": must be single, worker or shard, got '" + text + "'");
  }
  return Status::Ok();
}

// "a,b,,c" -> {a, b, c}
std::vector<std::string> SplitList(const std::string& text) {
  std::vector<std::string> out;
  size_t start = 0;
  while (start <= text.size()) {
    const size_t comma = std::min(text.find(',', start), text.size());
    if (comma > start) out.push_back(text.substr(start, comma - start));
    start = comma + 1;
  }
  return out;
}

}  // namespace

std::string ClusterSettings::EffectiveShardId() const {
  return shard_id.empty() ? Hostname() : shard_id;
}

int ServerConfig::worker_threads() const {
  if (threads > 0) return threads;
  return std::max(1, int(std::thread::hardware_concurrency()));
}

namespace {

Status Bad(const std::string& key, const std::string& what) {
  return Status::InvalidArgument(key + ": " + what);
}

bool ValidListenAddress(const std::string& address) {
  // host:port, [v6]:port, or unix:path. The port may be 0 (pick one).
  if (address.rfind("unix:", 0) == 0) return address.size() > 5;
  const auto colon = address.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 >= address.size()) return false;
  const std::string port = address.substr(colon + 1);
  if (port.find_first_not_of("0123456789") != std::string::npos || port.size() > 5) return false;
  return std::stoi(port) <= 65535;
}

// A control character in an address, path or name is a mistake (typically a CR from a file with
// CRLF line endings) that would also not survive --print-config (found by
// tests/fuzz/fuzz_server_config): refused, naming the key.
Status CheckNoControlCharacters(const ServerConfig& c) {
  std::vector<std::pair<std::string, const std::string*>> texts = {
      {"listen", &c.listen},
      {"metrics_listen", &c.metrics_listen},
      {"metrics_path", &c.metrics_path},
      {"console_listen", &c.console_listen},
      {"data_dir", &c.data_dir},
      {"tls.cert_file", &c.tls.cert_file},
      {"tls.key_file", &c.tls.key_file},
      {"tls.client_ca_file", &c.tls.client_ca_file},
      {"security.tokens_file", &c.security.tokens_file},
      {"log_level", &c.log_level},
      {"detector.backend", &c.detector.backend},
      {"detector.model", &c.detector.model},
      {"detector.config", &c.detector.config},
      {"detector.preprocessing", &c.detector.preprocessing},
      {"cluster.name", &c.cluster.name},
      {"cluster.shard_id", &c.cluster.shard_id},
      {"cluster.advertise", &c.cluster.advertise},
      {"cluster.internal_listen", &c.cluster.internal_listen},
      {"cluster.internal_ca_file", &c.cluster.internal_ca_file}};
  for (const std::string& url : c.cluster.nats) texts.push_back({"cluster.nats", &url});
  for (const std::string& address : c.cluster.etcd) texts.push_back({"cluster.etcd", &address});
  for (const auto& [name, path] : c.vocabularies) {
    texts.push_back({"vocabularies", &name});
    texts.push_back({"vocabularies." + name, &path});
  }
  for (const std::string& name : c.detector.classes) texts.push_back({"detector.classes", &name});
  for (const auto& [key, text] : texts) {
    for (const char ch : *text) {
      if (static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f) {
        return Bad(key, "contains a control character (a file with CRLF line endings?)");
      }
    }
  }
  return Status::Ok();
}

}  // namespace

namespace {

// host:port with a port (not unix:, not port 0 for an address others dial).
bool ValidDialAddress(const std::string& address) {
  return ValidListenAddress(address) && address.rfind("unix:", 0) != 0 &&
         address.substr(address.rfind(':') + 1) != "0";
}

// Role single ignores the section (today's server, whatever is written there).
Status ValidateCluster(const ClusterSettings& c, const TlsSettings& tls) {
  if (c.role == ClusterRole::kSingle) return Status::Ok();
  const std::string role = ClusterRoleName(c.role);
  if (c.name.empty() || c.name.size() > 64 ||
      c.name.find_first_not_of(
          "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-") !=
          std::string::npos) {
    return Bad("cluster.name", "'" + c.name +
                                   "' must be 1-64 characters of A-Z a-z 0-9 _ - (it is part of "
                                   "etcd keys, NATS subjects and stream names)");
  }
  if (c.nats.empty()) {
    return Bad("cluster.nats",
               "role " + role + " needs the NATS servers (nats://host:port, --nats a,b,c)");
  }
  for (const std::string& url : c.nats) {
    const std::string address = url.rfind("nats://", 0) == 0 ? url.substr(7) : url;
    if (!ValidDialAddress(address)) {
      return Bad("cluster.nats", "'" + url + "' is not nats://host:port");
    }
  }
  if (c.etcd.empty()) {
    return Bad("cluster.etcd",
               "role " + role + " needs the etcd members (host:port, --etcd a,b,c)");
  }
  for (const std::string& address : c.etcd) {
    if (!ValidDialAddress(address)) {
      return Bad("cluster.etcd", "'" + address + "' is not host:port");
    }
  }
  if (c.replicas < 1 || c.replicas > 5) return Bad("cluster.replicas", "must be in [1, 5]");
  if (c.stream_replicas < 1 || c.stream_replicas > 5) {
    return Bad("cluster.stream_replicas", "must be in [1, 5] (JetStream's limit)");
  }
  if (c.replace_after_s < 1 || c.replace_after_s > 86400) {
    return Bad("cluster.replace_after_s", "must be in [1, 86400]");
  }
  if (c.compact_after_records < 0) {
    return Bad("cluster.compact_after_records", "must be >= 0 (0: not by records)");
  }
  if (c.compact_after_bytes < 0) {
    return Bad("cluster.compact_after_bytes", "must be >= 0 (0: not by bytes)");
  }
  if (c.compact_keep_s < 0 || c.compact_keep_s > 86400) {
    return Bad("cluster.compact_keep_s", "must be in [0, 86400]");
  }
  if (c.internal_tls) {
    const std::string why =
        " (tls.cert_file and tls.key_file are this process's certificate on every internal hop, "
        "the CA bundle verifies the peers)";
    if (tls.cert_file.empty()) return Bad("cluster.internal_tls", "needs tls.cert_file" + why);
    if (tls.key_file.empty()) return Bad("cluster.internal_tls", "needs tls.key_file" + why);
    if (c.InternalCaFile(tls).empty()) {
      return Bad("cluster.internal_tls",
                 "needs tls.client_ca_file or cluster.internal_ca_file" + why);
    }
  }
  if (c.role == ClusterRole::kShard) {
    if (!ValidListenAddress(c.internal_listen) || c.internal_listen.rfind("unix:", 0) == 0) {
      return Bad("cluster.internal_listen", "'" + c.internal_listen + "' is not host:port");
    }
    const std::string id = c.EffectiveShardId();
    if (id.empty() || id.size() > 128 || id.find('/') != std::string::npos) {
      return Bad("cluster.shard_id", "'" + id +
                                         "' must be 1-128 characters without '/' (the hostname "
                                         "when not set)");
    }
    if (!c.advertise.empty()) {
      if (!ValidDialAddress(c.advertise)) {
        return Bad("cluster.advertise", "'" + c.advertise + "' is not host:port");
      }
    } else {
      // Workers dial <hostname>:<internal port>: the hostname must resolve here at least.
      const std::string host = Hostname();
      addrinfo* found = nullptr;
      const int error =
          host.empty() ? EAI_NONAME : getaddrinfo(host.c_str(), nullptr, nullptr, &found);
      if (found) freeaddrinfo(found);
      if (error != 0) {
        return Bad("cluster.advertise",
                   "not set and the hostname '" + host +
                       "' does not resolve: set the host:port workers reach this shard at");
      }
    }
  }
  return Status::Ok();
}

}  // namespace

Status ValidateServerConfig(const ServerConfig& c) {
  PLACEDB_RETURN_IF_ERROR(CheckNoControlCharacters(c));
  PLACEDB_RETURN_IF_ERROR(ValidateCluster(c.cluster, c.tls));
  if (!ValidListenAddress(c.listen)) return Bad("listen", "'" + c.listen + "' is not host:port");
  if (!c.metrics_listen.empty()) {
    if (!ValidListenAddress(c.metrics_listen) || c.metrics_listen.rfind("unix:", 0) == 0) {
      return Bad("metrics_listen", "'" + c.metrics_listen + "' is not host:port");
    }
    if (c.metrics_path.empty() || c.metrics_path[0] != '/') {
      return Bad("metrics_path", "must start with '/'");
    }
    if (c.metrics_threads < 2 || c.metrics_threads > 64) {
      return Bad("metrics_threads", "must be in [2, 64]");
    }
    if (c.metrics_request_timeout_ms < 100 || c.metrics_request_timeout_ms > 600000) {
      return Bad("metrics_request_timeout_ms", "must be in [100, 600000]");
    }
  }
  if (!c.console_listen.empty()) {
    if (!ValidListenAddress(c.console_listen) || c.console_listen.rfind("unix:", 0) == 0) {
      return Bad("console_listen", "'" + c.console_listen + "' is not host:port");
    }
    if (c.console_threads < 2 || c.console_threads > 64) {
      return Bad("console_threads", "must be in [2, 64]");
    }
    if (c.console_request_timeout_ms < 100 || c.console_request_timeout_ms > 600000) {
      return Bad("console_request_timeout_ms", "must be in [100, 600000]");
    }
    if (c.console_max_request_bytes < 1024 || c.console_max_request_bytes > (uint64_t(1) << 30)) {
      return Bad("console_max_request_bytes", "must be in [1024, 1073741824]");
    }
  }
  if (c.console_tls && !c.tls.enabled()) {
    return Bad("console_tls", "needs tls.cert_file and tls.key_file");
  }
  if (c.tls.cert_file.empty() != c.tls.key_file.empty()) {
    return Bad(c.tls.cert_file.empty() ? "tls.cert_file" : "tls.key_file",
               "TLS needs both tls.cert_file and tls.key_file");
  }
  if (c.tls.mutual() && !c.tls.enabled()) {
    return Bad("tls.client_ca_file", "mutual TLS needs tls.cert_file and tls.key_file too");
  }
  if (c.metrics_tls && !c.tls.enabled()) {
    return Bad("metrics_tls", "needs tls.cert_file and tls.key_file");
  }
  if (c.data_dir.empty()) return Bad("data_dir", "must not be empty");
  if (c.threads < 0 || c.threads > 1024) return Bad("threads", "must be in [0, 1024]");
  if (c.query_threads < 0 || c.query_threads > 1024) {
    return Bad("query_threads", "must be in [0, 1024]");
  }
  if (c.ingest_nice < 0 || c.ingest_nice > 19) return Bad("ingest_nice", "must be in [0, 19]");
  if (c.search.threads < 1 || c.search.threads > 64) {
    return Bad("search.threads", "must be in [1, 64]");
  }
  if (!(c.search.max_word_share > 0 && c.search.max_word_share <= 1)) {
    return Bad("search.max_word_share", "must be in (0, 1]");
  }
  if (c.opencv_threads < -1 || c.opencv_threads > 1024) {
    return Bad("opencv_threads", "must be in [-1, 1024]");
  }
  if (!c.vocabularies.count("default")) {
    return Bad("vocabularies", "a vocabulary named 'default' is required");
  }
  for (const auto& [name, path] : c.vocabularies) {
    if (name.empty()) return Bad("vocabularies", "a vocabulary name is empty");
    if (path.empty()) return Bad("vocabularies." + name, "path is empty");
  }
  if (c.storage.group_commit_delay_ms < 0 || c.storage.group_commit_delay_ms > 1000) {
    return Bad("storage.group_commit_delay_ms", "must be in [0, 1000]");
  }
  const Limits& l = c.limits;
  if (l.max_message_bytes < 1024 || l.max_message_bytes > (uint64_t(1) << 30)) {
    return Bad("limits.max_message_bytes", "must be in [1 KiB, 1 GiB]");
  }
  if (l.max_image_pixels < 1) return Bad("limits.max_image_pixels", "must be >= 1");
  if (l.max_descriptors_per_frame < 1 || l.max_descriptors_per_frame > 100000) {
    return Bad("limits.max_descriptors_per_frame", "must be in [1, 100000]");
  }
  if (l.max_concurrent_streams < 1) return Bad("limits.max_concurrent_streams", "must be >= 1");
  if (l.max_queued_frames < 1) return Bad("limits.max_queued_frames", "must be >= 1");
  if (l.max_inflight_per_stream < 1) return Bad("limits.max_inflight_per_stream", "must be >= 1");
  if (l.max_concurrent_unary < 1) return Bad("limits.max_concurrent_unary", "must be >= 1");
  if (l.memory_quota_bytes < (uint64_t(16) << 20)) {
    return Bad("limits.memory_quota_bytes", "must be >= 16 MiB");
  }
  if (l.stream_header_timeout_ms < 100 || l.stream_header_timeout_ms > 3600000) {
    return Bad("limits.stream_header_timeout_ms", "must be in [100, 3600000]");
  }
  if (l.stream_idle_timeout_ms < 100 || l.stream_idle_timeout_ms > 86400000) {
    return Bad("limits.stream_idle_timeout_ms", "must be in [100, 86400000]");
  }
  if (l.max_snapshot_bytes < 1024) return Bad("limits.max_snapshot_bytes", "must be >= 1 KiB");
  // Every read is granted a whole message first (docs/service.md, "Memory budget"): the budget
  // must hold a few, beside the block cache. The vocabularies are checked when loaded.
  if (l.memory_budget_bytes < c.storage.block_cache_bytes + 4 * l.max_message_bytes) {
    return Bad("limits.memory_budget_bytes",
               "must be at least storage.block_cache_bytes + 4 x limits.max_message_bytes = " +
                   std::to_string(c.storage.block_cache_bytes + 4 * l.max_message_bytes) +
                   ", got " + std::to_string(l.memory_budget_bytes));
  }
  if (l.memory_wait_ms > 600000) return Bad("limits.memory_wait_ms", "must be in [0, 600000]");
  if (!(c.shutdown_deadline_s >= 0 && c.shutdown_deadline_s <= 3600)) {
    return Bad("shutdown_deadline_s", "must be in [0, 3600]");
  }
  static const std::set<std::string> kLevels = {"trace", "debug",    "info", "warn",
                                                "error", "critical", "off"};
  if (!kLevels.count(c.log_level)) return Bad("log_level", "unknown level '" + c.log_level + "'");
  if (c.detector_enabled()) {
    const DetectorSettings& d = c.detector;
    if (d.backend != "yolox_onnx" && d.backend != "darknet") {
      return Bad("detector.backend", "must be yolox_onnx or darknet");
    }
    if (d.backend == "darknet" && d.config.empty()) {
      return Bad("detector.config", "the darknet backend needs its .cfg file");
    }
    if (!(d.merge_iou > 0 && d.merge_iou <= 1))
      return Bad("detector.merge_iou", "must be in (0, 1]");
    if (d.max_concurrent_calls < 0) return Bad("detector.max_concurrent_calls", "must be >= 0");
    for (const auto& [name, value] : d.class_confidence) {
      if (!(value > 0 && value <= 1))
        return Bad("detector.class_confidence." + name, "must be in (0, 1]");
    }
    const std::pair<const char*, float> shares[] = {
        {"detector.min_box_area", d.min_box_area},
        {"detector.large_box_area", d.large_box_area},
        {"detector.large_box_confidence", d.large_box_confidence}};
    for (const auto& [key, value] : shares) {
      if (!(value >= 0 && value <= 1)) return Bad(key, "must be in [0, 1]");
    }
  }
  return Status::Ok();
}

// ---- YAML ---------------------------------------------------------------------------------------

namespace {

// Reads a YAML node into typed fields, naming the key path in every error.
class YamlReader {
 public:
  Status Check(const YAML::Node& node, const std::string& path,
               const std::set<std::string>& known) {
    if (!node.IsMap()) return Bad(path.empty() ? "config" : path, "must be a mapping");
    for (const auto& item : node) {
      const std::string key = item.first.as<std::string>();
      if (!known.count(key)) {
        return Bad(Join(path, key), "unknown key (see server/placedb.yaml for the valid ones)");
      }
    }
    return Status::Ok();
  }

  template <typename T>
  Status Read(const YAML::Node& node, const std::string& path, const char* key, T* out) {
    const YAML::Node value = node[key];
    if (!value) return Status::Ok();
    try {
      *out = value.as<T>();
    } catch (const YAML::Exception&) {
      return Bad(Join(path, key), "cannot read '" + YAML::Dump(value) + "' as the expected type");
    }
    return Status::Ok();
  }

  static std::string Join(const std::string& path, const std::string& key) {
    return path.empty() ? key : path + "." + key;
  }
};

Status ApplyYamlNode(const YAML::Node& root, ServerConfig* c) {
  if (!root || root.IsNull()) return Status::Ok();  // an empty file changes nothing
  YamlReader r;
  PLACEDB_RETURN_IF_ERROR(r.Check(root, "",
                                  {"listen",
                                   "metrics_listen",
                                   "metrics_path",
                                   "metrics_threads",
                                   "metrics_request_timeout_ms",
                                   "metrics_tls",
                                   "console_listen",
                                   "console_tls",
                                   "console_threads",
                                   "console_request_timeout_ms",
                                   "console_max_request_bytes",
                                   "tls",
                                   "security",
                                   "data_dir",
                                   "threads",
                                   "query_threads",
                                   "ingest_nice",
                                   "search",
                                   "opencv_threads",
                                   "vocabularies",
                                   "storage",
                                   "limits",
                                   "shutdown_deadline_s",
                                   "detector",
                                   "log_level",
                                   "cluster"}));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "listen", &c->listen));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "metrics_listen", &c->metrics_listen));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "metrics_path", &c->metrics_path));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "metrics_threads", &c->metrics_threads));
  PLACEDB_RETURN_IF_ERROR(
      r.Read(root, "", "metrics_request_timeout_ms", &c->metrics_request_timeout_ms));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "metrics_tls", &c->metrics_tls));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "console_listen", &c->console_listen));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "console_tls", &c->console_tls));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "console_threads", &c->console_threads));
  PLACEDB_RETURN_IF_ERROR(
      r.Read(root, "", "console_request_timeout_ms", &c->console_request_timeout_ms));
  PLACEDB_RETURN_IF_ERROR(
      r.Read(root, "", "console_max_request_bytes", &c->console_max_request_bytes));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "data_dir", &c->data_dir));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "threads", &c->threads));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "query_threads", &c->query_threads));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "ingest_nice", &c->ingest_nice));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "opencv_threads", &c->opencv_threads));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "shutdown_deadline_s", &c->shutdown_deadline_s));
  PLACEDB_RETURN_IF_ERROR(r.Read(root, "", "log_level", &c->log_level));
  if (const YAML::Node v = root["vocabularies"]; v) {
    if (!v.IsMap()) return Bad("vocabularies", "must be a mapping of name: path");
    // The file's list replaces the embedded one, so a config can rename or drop entries.
    std::map<std::string, std::string> vocabularies;
    for (const auto& item : v) {
      const std::string name = item.first.as<std::string>();
      std::string path;
      PLACEDB_RETURN_IF_ERROR(r.Read(v, "vocabularies", name.c_str(), &path));
      vocabularies[name] = path;
    }
    c->vocabularies = std::move(vocabularies);
    // Entries that repeat an embedded default (as --print-config and server/placedb.yaml do)
    // stay optional like the default itself; any other entry is required.
    const std::map<std::string, std::string> embedded = EmbeddedVocabularies();
    std::set<std::string> optional;
    for (const auto& [name, path] : c->vocabularies) {
      auto it = embedded.find(name);
      if (name != "default" && it != embedded.end() && it->second == path &&
          c->optional_vocabularies.count(name)) {
        optional.insert(name);
      }
    }
    c->optional_vocabularies = std::move(optional);
  }
  if (const YAML::Node t = root["tls"]; t) {
    PLACEDB_RETURN_IF_ERROR(r.Check(t, "tls", {"cert_file", "key_file", "client_ca_file"}));
    PLACEDB_RETURN_IF_ERROR(r.Read(t, "tls", "cert_file", &c->tls.cert_file));
    PLACEDB_RETURN_IF_ERROR(r.Read(t, "tls", "key_file", &c->tls.key_file));
    PLACEDB_RETURN_IF_ERROR(r.Read(t, "tls", "client_ca_file", &c->tls.client_ca_file));
  }
  if (const YAML::Node s = root["security"]; s) {
    PLACEDB_RETURN_IF_ERROR(
        r.Check(s, "security", {"tokens_file", "reflection", "allow_unauthenticated_remote"}));
    PLACEDB_RETURN_IF_ERROR(r.Read(s, "security", "tokens_file", &c->security.tokens_file));
    PLACEDB_RETURN_IF_ERROR(r.Read(s, "security", "reflection", &c->security.reflection));
    PLACEDB_RETURN_IF_ERROR(r.Read(s, "security", "allow_unauthenticated_remote",
                                   &c->security.allow_unauthenticated_remote));
  }
  if (const YAML::Node s = root["search"]; s) {
    PLACEDB_RETURN_IF_ERROR(
        r.Check(s, "search", {"threads", "max_word_share", "skip_words_min_places"}));
    PLACEDB_RETURN_IF_ERROR(r.Read(s, "search", "threads", &c->search.threads));
    PLACEDB_RETURN_IF_ERROR(r.Read(s, "search", "max_word_share", &c->search.max_word_share));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(s, "search", "skip_words_min_places", &c->search.skip_words_min_places));
  }
  if (const YAML::Node s = root["storage"]; s) {
    PLACEDB_RETURN_IF_ERROR(r.Check(s, "storage",
                                    {"sync", "group_commit_delay_ms", "block_cache_bytes",
                                     "disk_reserve_bytes", "snapshots_keep_per_map"}));
    std::string sync;
    PLACEDB_RETURN_IF_ERROR(r.Read(s, "storage", "sync", &sync));
    if (sync == "every_write") {
      c->storage.sync = SyncMode::kEveryWrite;
    } else if (sync == "group_commit") {
      c->storage.sync = SyncMode::kGroupCommit;
    } else if (!sync.empty()) {
      return Bad("storage.sync", "must be every_write or group_commit, got '" + sync + "'");
    }
    PLACEDB_RETURN_IF_ERROR(
        r.Read(s, "storage", "group_commit_delay_ms", &c->storage.group_commit_delay_ms));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(s, "storage", "block_cache_bytes", &c->storage.block_cache_bytes));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(s, "storage", "disk_reserve_bytes", &c->storage.disk_reserve_bytes));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(s, "storage", "snapshots_keep_per_map", &c->snapshots.keep_per_map));
  }
  if (const YAML::Node l = root["limits"]; l) {
    PLACEDB_RETURN_IF_ERROR(
        r.Check(l, "limits",
                {"max_message_bytes", "max_image_pixels", "max_descriptors_per_frame",
                 "max_boxes_per_frame", "max_concurrent_streams", "max_queued_frames",
                 "max_inflight_per_stream", "max_concurrent_unary", "unary_queue_wait_ms",
                 "memory_quota_bytes", "stream_header_timeout_ms", "stream_idle_timeout_ms",
                 "memory_budget_bytes", "memory_wait_ms", "max_snapshot_bytes"}));
    Limits& x = c->limits;
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "max_message_bytes", &x.max_message_bytes));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "max_image_pixels", &x.max_image_pixels));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(l, "limits", "max_descriptors_per_frame", &x.max_descriptors_per_frame));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "max_boxes_per_frame", &x.max_boxes_per_frame));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(l, "limits", "max_concurrent_streams", &x.max_concurrent_streams));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "max_queued_frames", &x.max_queued_frames));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(l, "limits", "max_inflight_per_stream", &x.max_inflight_per_stream));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "max_concurrent_unary", &x.max_concurrent_unary));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "unary_queue_wait_ms", &x.unary_queue_wait_ms));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "memory_quota_bytes", &x.memory_quota_bytes));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(l, "limits", "stream_header_timeout_ms", &x.stream_header_timeout_ms));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(l, "limits", "stream_idle_timeout_ms", &x.stream_idle_timeout_ms));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "memory_budget_bytes", &x.memory_budget_bytes));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "memory_wait_ms", &x.memory_wait_ms));
    PLACEDB_RETURN_IF_ERROR(r.Read(l, "limits", "max_snapshot_bytes", &x.max_snapshot_bytes));
  }
  if (const YAML::Node d = root["detector"]; d) {
    PLACEDB_RETURN_IF_ERROR(
        r.Check(d, "detector",
                {"backend", "model", "config", "input_size", "preprocessing", "confidence",
                 "nms_iou", "classes", "max_concurrent_calls", "merge_iou", "required",
                 "rectangular_letterbox", "rewrite_graph", "class_confidence", "min_box_area",
                 "large_box_area", "large_box_confidence"}));
    DetectorSettings& x = c->detector;
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "backend", &x.backend));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "model", &x.model));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "config", &x.config));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "input_size", &x.input_size));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "preprocessing", &x.preprocessing));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "confidence", &x.confidence));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "nms_iou", &x.nms_iou));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "classes", &x.classes));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "max_concurrent_calls", &x.max_concurrent_calls));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "merge_iou", &x.merge_iou));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "required", &x.required));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(d, "detector", "rectangular_letterbox", &x.rectangular_letterbox));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "rewrite_graph", &x.rewrite_graph));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "class_confidence", &x.class_confidence));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "min_box_area", &x.min_box_area));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "large_box_area", &x.large_box_area));
    PLACEDB_RETURN_IF_ERROR(r.Read(d, "detector", "large_box_confidence", &x.large_box_confidence));
  }
  if (const YAML::Node k = root["cluster"]; k) {
    PLACEDB_RETURN_IF_ERROR(
        r.Check(k, "cluster",
                {"role", "name", "nats", "etcd", "shard_id", "advertise", "internal_listen",
                 "replicas", "stream_replicas", "replace_after_s", "compact_after_records",
                 "compact_after_bytes", "compact_keep_s", "internal_tls", "internal_ca_file"}));
    ClusterSettings& x = c->cluster;
    std::string role;
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "role", &role));
    if (!role.empty()) PLACEDB_RETURN_IF_ERROR(ParseRole(role, "cluster.role", &x.role));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "name", &x.name));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "nats", &x.nats));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "etcd", &x.etcd));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "shard_id", &x.shard_id));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "advertise", &x.advertise));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "internal_listen", &x.internal_listen));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "replicas", &x.replicas));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "stream_replicas", &x.stream_replicas));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "replace_after_s", &x.replace_after_s));
    PLACEDB_RETURN_IF_ERROR(
        r.Read(k, "cluster", "compact_after_records", &x.compact_after_records));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "compact_after_bytes", &x.compact_after_bytes));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "compact_keep_s", &x.compact_keep_s));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "internal_tls", &x.internal_tls));
    PLACEDB_RETURN_IF_ERROR(r.Read(k, "cluster", "internal_ca_file", &x.internal_ca_file));
  }
  return Status::Ok();
}

}  // namespace

Status ApplyConfigYaml(const std::string& yaml_text, ServerConfig* config) {
  try {
    return ApplyYamlNode(YAML::Load(yaml_text), config);
  } catch (const YAML::Exception& e) {
    return Status::InvalidArgument(std::string("config is not valid YAML: ") + e.what());
  }
}

Status ApplyConfigFile(const std::string& path, ServerConfig* config) {
  auto text = ReadWholeFile(path);
  if (!text.ok()) return text.status().WithContext("config file " + path);
  return ApplyConfigYaml(*text, config).WithContext("config file " + path);
}

// ---- Environment --------------------------------------------------------------------------------

Status ApplyEnvironment(ServerConfig* c, const std::function<const char*(const char*)>& getenv) {
  auto get = [&](const char* name) -> std::optional<std::string> {
    const char* v = getenv(name);
    if (!v || !*v) return std::nullopt;
    return std::string(v);
  };
  if (auto v = get("PLACEDB_LISTEN")) c->listen = *v;
  if (auto v = get("PLACEDB_DATA_DIR")) c->data_dir = *v;
  if (auto v = get("PLACEDB_METRICS_LISTEN")) c->metrics_listen = (*v == "off") ? "" : *v;
  if (auto v = get("PLACEDB_METRICS_PORT")) {
    // Keeps the configured host, replaces the port.
    if (v->find_first_not_of("0123456789") != std::string::npos || v->size() > 5) {
      return Bad("PLACEDB_METRICS_PORT", "'" + *v + "' is not a port number");
    }
    std::string host = "127.0.0.1";  // metrics were off: the default host (loopback)
    if (const auto colon = c->metrics_listen.rfind(':'); colon != std::string::npos) {
      host = c->metrics_listen.substr(0, colon);
    }
    c->metrics_listen = host + ":" + *v;
  }
  auto get_bool = [&](const char* name, bool* out) -> Status {
    const auto v = get(name);
    if (!v) return Status::Ok();
    if (*v == "1" || *v == "true" || *v == "yes" || *v == "on") {
      *out = true;
    } else if (*v == "0" || *v == "false" || *v == "no" || *v == "off") {
      *out = false;
    } else {
      return Bad(name, "'" + *v + "' is not true/false/1/0/yes/no/on/off");
    }
    return Status::Ok();
  };
  PLACEDB_RETURN_IF_ERROR(get_bool("PLACEDB_METRICS_TLS", &c->metrics_tls));
  if (auto v = get("PLACEDB_CONSOLE_LISTEN")) c->console_listen = (*v == "off") ? "" : *v;
  PLACEDB_RETURN_IF_ERROR(get_bool("PLACEDB_CONSOLE_TLS", &c->console_tls));
  if (auto v = get("PLACEDB_TLS_CERT_FILE")) c->tls.cert_file = *v;
  if (auto v = get("PLACEDB_TLS_KEY_FILE")) c->tls.key_file = *v;
  if (auto v = get("PLACEDB_TLS_CLIENT_CA_FILE")) c->tls.client_ca_file = *v;
  if (auto v = get("PLACEDB_TOKENS_FILE")) c->security.tokens_file = *v;
  PLACEDB_RETURN_IF_ERROR(
      get_bool("PLACEDB_ALLOW_UNAUTHENTICATED_REMOTE", &c->security.allow_unauthenticated_remote));
  if (auto v = get("PLACEDB_THREADS")) {
    if (v->find_first_not_of("0123456789") != std::string::npos || v->size() > 4) {
      return Bad("PLACEDB_THREADS", "'" + *v + "' is not a thread count");
    }
    c->threads = std::stoi(*v);
  }
  if (auto v = get("PLACEDB_LOG_LEVEL")) c->log_level = *v;
  if (auto v = get("PLACEDB_DETECTOR_MODEL")) c->detector.model = (*v == "off") ? "" : *v;
  if (auto v = get("PLACEDB_MEMORY_BUDGET_BYTES")) {
    if (v->find_first_not_of("0123456789") != std::string::npos || v->size() > 19) {
      return Bad("PLACEDB_MEMORY_BUDGET_BYTES", "'" + *v + "' is not a byte count");
    }
    c->limits.memory_budget_bytes = std::stoull(*v);
  }
  if (auto v = get("PLACEDB_MAX_SNAPSHOT_BYTES")) {
    if (v->find_first_not_of("0123456789") != std::string::npos || v->size() > 19) {
      return Bad("PLACEDB_MAX_SNAPSHOT_BYTES", "'" + *v + "' is not a byte count");
    }
    c->limits.max_snapshot_bytes = std::stoull(*v);
  }
  PLACEDB_RETURN_IF_ERROR(get_bool("PLACEDB_INTERNAL_TLS", &c->cluster.internal_tls));
  if (auto v = get("PLACEDB_INTERNAL_CA_FILE")) c->cluster.internal_ca_file = *v;
  return Status::Ok();
}

// ---- Command line -------------------------------------------------------------------------------

Result<CommandLine> ParseCommandLine(int argc, const char* const* argv,
                                     const std::function<const char*(const char*)>& getenv) {
  CLI::App app{"placedb-server: the placedb gRPC service (docs/service.md)", "placedb-server"};
  app.set_version_flag("--version", std::string("placedb-server ") + PLACEDB_VERSION);
  // `tokens` is parsed by main() before these flags (its own command group): listed here.
  app.footer(
      "Commands:\n"
      "  tokens                      manage the tokens file: add, list, revoke, rotate "
      "(placedb-server tokens --help)\n\n"
      "Exit codes (as placedb and placedb-load): 0 ok; 1 the server failed (could not start, or "
      "stopped on an error); 2 usage (a bad flag, configuration file or environment variable).");
  std::string config_path, listen, data_dir, metrics_listen, console_listen, log_level,
      detector_model;
  std::string tls_cert, tls_key, tls_client_ca, tokens_file;
  bool metrics_tls = false, console_tls = false, no_reflection = false,
       allow_unauthenticated_remote = false;
  int threads = 0;
  double shutdown_deadline = 0;
  std::vector<std::string> vocabularies;
  uint64_t max_message_bytes = 0, max_image_pixels = 0, memory_budget = 0;
  uint32_t max_descriptors = 0, max_boxes = 0, max_streams = 0, max_queued = 0;
  std::string role, cluster_name, nats, etcd, shard_id, advertise, internal_listen;
  bool print_config = false;
  auto* o_config = app.add_option("-c,--config", config_path,
                                  "YAML configuration file (default: $PLACEDB_CONFIG)");
  auto* o_listen = app.add_option("--listen", listen, "gRPC address host:port (127.0.0.1:50051)");
  auto* o_tls_cert = app.add_option("--tls-cert", tls_cert, "server certificate (PEM): TLS");
  auto* o_tls_key = app.add_option("--tls-key", tls_key, "the certificate's private key (PEM)");
  auto* o_tls_ca = app.add_option("--tls-client-ca", tls_client_ca,
                                  "client CA bundle (PEM): mutual TLS, clients need a certificate");
  auto* o_metrics_tls =
      app.add_flag("--metrics-tls", metrics_tls, "serve metrics over HTTPS with the TLS files");
  auto* o_tokens = app.add_option("--tokens-file", tokens_file,
                                  "principals, token hashes and rights (placedb-server tokens)");
  auto* o_no_reflection =
      app.add_flag("--no-reflection", no_reflection, "turn gRPC server reflection off");
  auto* o_unauth_remote = app.add_flag(
      "--allow-unauthenticated-remote", allow_unauthenticated_remote,
      "listen beyond loopback with neither tokens nor mutual TLS: anyone may do anything");
  auto* o_data = app.add_option("--data-dir", data_dir, "data directory (./var/data)");
  auto* o_metrics = app.add_option("--metrics-listen", metrics_listen,
                                   "Prometheus endpoint host:port (127.0.0.1:9464), 'off' = none");
  auto* o_console = app.add_option("--console-listen", console_listen,
                                   "web console host:port (127.0.0.1:9465), 'off' = none");
  auto* o_console_tls =
      app.add_flag("--console-tls", console_tls, "serve the console over HTTPS with the TLS files");
  auto* o_threads = app.add_option("--threads", threads, "worker threads (0 = every core)");
  auto* o_vocab = app.add_option("--vocabulary", vocabularies,
                                 "NAME=PATH, repeatable; adds or replaces a named vocabulary");
  auto* o_deadline =
      app.add_option("--shutdown-deadline", shutdown_deadline, "seconds in-flight calls get (30)");
  auto* o_log = app.add_option("--log-level", log_level, "trace|debug|info|warn|error|off");
  auto* o_detector = app.add_option("--detector-model", detector_model,
                                    "detector model file (.onnx or .weights); 'off' = none");
  auto* o_msg = app.add_option("--max-message-bytes", max_message_bytes, "limit");
  auto* o_pixels = app.add_option("--max-image-pixels", max_image_pixels, "limit");
  auto* o_desc = app.add_option("--max-descriptors", max_descriptors, "limit per frame");
  auto* o_boxes = app.add_option("--max-boxes", max_boxes, "limit per frame");
  auto* o_streams = app.add_option("--max-streams", max_streams, "concurrent Ingest streams");
  auto* o_queued = app.add_option("--max-queued-frames", max_queued, "frames waiting for a worker");
  auto* o_budget = app.add_option("--memory-budget-bytes", memory_budget,
                                  "memory budget: caches + frames in flight (1 GiB)");
  auto* o_role = app.add_option("--role", role, "cluster role: single (default) | worker | shard");
  auto* o_cluster_name =
      app.add_option("--cluster-name", cluster_name, "cluster name: etcd key and stream prefix");
  auto* o_nats = app.add_option("--nats", nats, "NATS servers, comma-separated nats://host:port");
  auto* o_etcd = app.add_option("--etcd", etcd, "etcd members, comma-separated host:port");
  auto* o_shard_id = app.add_option("--shard-id", shard_id, "shard: stable id (the hostname)");
  auto* o_advertise =
      app.add_option("--advertise", advertise, "shard: host:port workers reach its internal API");
  auto* o_internal = app.add_option("--internal-listen", internal_listen,
                                    "shard: internal API address (127.0.0.1:50061)");
  bool internal_tls = false;
  auto* o_internal_tls = app.add_flag(
      "--internal-tls", internal_tls,
      "cluster: mutual TLS to shards, NATS and etcd with the --tls-* files (plain text refused)");
  int64_t compact_after_records = 0, compact_after_bytes = 0;
  auto* o_compact_records =
      app.add_option("--compact-after-records", compact_after_records,
                     "cluster: a map's stream is compacted beyond this many records (0 = not)");
  auto* o_compact_bytes =
      app.add_option("--compact-after-bytes", compact_after_bytes,
                     "cluster: a map's stream is compacted beyond this many bytes (0 = not)");
  std::string internal_ca_file;
  auto* o_internal_ca =
      app.add_option("--internal-ca", internal_ca_file,
                     "cluster: CA bundle verifying internal peers (default: --tls-client-ca)");
  app.add_flag("--print-config", print_config, "print the effective configuration and exit");

  CommandLine out;
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version exit 0; every usage error 2, as placedb's (not CLI11's own codes).
    out.exit_code = app.exit(e) == 0 ? 0 : 2;
    return out;
  }
  ServerConfig& c = out.config;
  if (o_config->count() == 0) {
    if (const char* env = getenv("PLACEDB_CONFIG"); env && *env) config_path = env;
  }
  if (!config_path.empty()) PLACEDB_RETURN_IF_ERROR(ApplyConfigFile(config_path, &c));
  PLACEDB_RETURN_IF_ERROR(ApplyEnvironment(&c, getenv));
  if (o_listen->count()) c.listen = listen;
  if (o_tls_cert->count()) c.tls.cert_file = tls_cert;
  if (o_tls_key->count()) c.tls.key_file = tls_key;
  if (o_tls_ca->count()) c.tls.client_ca_file = tls_client_ca;
  if (o_metrics_tls->count()) c.metrics_tls = metrics_tls;
  if (o_tokens->count()) c.security.tokens_file = tokens_file;
  if (o_no_reflection->count()) c.security.reflection = !no_reflection;
  if (o_unauth_remote->count()) {
    c.security.allow_unauthenticated_remote = allow_unauthenticated_remote;
  }
  if (o_data->count()) c.data_dir = data_dir;
  if (o_metrics->count()) c.metrics_listen = metrics_listen == "off" ? "" : metrics_listen;
  if (o_console->count()) c.console_listen = console_listen == "off" ? "" : console_listen;
  if (o_console_tls->count()) c.console_tls = console_tls;
  if (o_threads->count()) c.threads = threads;
  if (o_deadline->count()) c.shutdown_deadline_s = shutdown_deadline;
  if (o_log->count()) c.log_level = log_level;
  if (o_detector->count()) c.detector.model = detector_model == "off" ? "" : detector_model;
  for (const std::string& entry : vocabularies) {
    const auto eq = entry.find('=');
    if (eq == std::string::npos || eq == 0 || eq + 1 == entry.size()) {
      return Bad("--vocabulary", "'" + entry + "' is not NAME=PATH");
    }
    c.vocabularies[entry.substr(0, eq)] = entry.substr(eq + 1);
    c.optional_vocabularies.erase(entry.substr(0, eq));  // named on the command line: required
  }
  (void)o_vocab;
  if (o_msg->count()) c.limits.max_message_bytes = max_message_bytes;
  if (o_pixels->count()) c.limits.max_image_pixels = max_image_pixels;
  if (o_desc->count()) c.limits.max_descriptors_per_frame = max_descriptors;
  if (o_boxes->count()) c.limits.max_boxes_per_frame = max_boxes;
  if (o_streams->count()) c.limits.max_concurrent_streams = max_streams;
  if (o_queued->count()) c.limits.max_queued_frames = max_queued;
  if (o_budget->count()) c.limits.memory_budget_bytes = memory_budget;
  if (o_role->count()) PLACEDB_RETURN_IF_ERROR(ParseRole(role, "--role", &c.cluster.role));
  if (o_cluster_name->count()) c.cluster.name = cluster_name;
  if (o_nats->count()) c.cluster.nats = SplitList(nats);
  if (o_etcd->count()) c.cluster.etcd = SplitList(etcd);
  if (o_shard_id->count()) c.cluster.shard_id = shard_id;
  if (o_advertise->count()) c.cluster.advertise = advertise;
  if (o_internal->count()) c.cluster.internal_listen = internal_listen;
  if (o_internal_tls->count()) c.cluster.internal_tls = internal_tls;
  if (o_compact_records->count()) c.cluster.compact_after_records = compact_after_records;
  if (o_compact_bytes->count()) c.cluster.compact_after_bytes = compact_after_bytes;
  if (o_internal_ca->count()) c.cluster.internal_ca_file = internal_ca_file;
  PLACEDB_RETURN_IF_ERROR(ValidateServerConfig(c));
  if (print_config) {
    std::cout << ConfigToYaml(c);
    out.exit_code = 0;
  }
  return out;
}

std::string ConfigToYaml(const ServerConfig& c) {
  YAML::Emitter e;
  e.SetFloatPrecision(6);
  e.SetDoublePrecision(6);
  e << YAML::BeginMap;
  e << YAML::Key << "listen" << YAML::Value << c.listen;
  e << YAML::Key << "metrics_listen" << YAML::Value << c.metrics_listen;
  e << YAML::Key << "metrics_path" << YAML::Value << c.metrics_path;
  e << YAML::Key << "metrics_threads" << YAML::Value << c.metrics_threads;
  e << YAML::Key << "metrics_request_timeout_ms" << YAML::Value << c.metrics_request_timeout_ms;
  e << YAML::Key << "metrics_tls" << YAML::Value << c.metrics_tls;
  e << YAML::Key << "console_listen" << YAML::Value << c.console_listen;
  e << YAML::Key << "console_tls" << YAML::Value << c.console_tls;
  e << YAML::Key << "console_threads" << YAML::Value << c.console_threads;
  e << YAML::Key << "console_request_timeout_ms" << YAML::Value << c.console_request_timeout_ms;
  e << YAML::Key << "console_max_request_bytes" << YAML::Value << c.console_max_request_bytes;
  e << YAML::Key << "tls" << YAML::Value << YAML::BeginMap;
  e << YAML::Key << "cert_file" << YAML::Value << c.tls.cert_file;
  e << YAML::Key << "key_file" << YAML::Value << c.tls.key_file;
  e << YAML::Key << "client_ca_file" << YAML::Value << c.tls.client_ca_file;
  e << YAML::EndMap;
  e << YAML::Key << "security" << YAML::Value << YAML::BeginMap;
  e << YAML::Key << "tokens_file" << YAML::Value << c.security.tokens_file;
  e << YAML::Key << "reflection" << YAML::Value << c.security.reflection;
  e << YAML::Key << "allow_unauthenticated_remote" << YAML::Value
    << c.security.allow_unauthenticated_remote;
  e << YAML::EndMap;
  e << YAML::Key << "data_dir" << YAML::Value << c.data_dir;
  e << YAML::Key << "threads" << YAML::Value << c.threads;
  e << YAML::Key << "query_threads" << YAML::Value << c.query_threads;
  e << YAML::Key << "ingest_nice" << YAML::Value << c.ingest_nice;
  e << YAML::Key << "search" << YAML::Value << YAML::BeginMap;
  e << YAML::Key << "threads" << YAML::Value << c.search.threads;
  e << YAML::Key << "max_word_share" << YAML::Value << c.search.max_word_share;
  e << YAML::Key << "skip_words_min_places" << YAML::Value << c.search.skip_words_min_places;
  e << YAML::EndMap;
  e << YAML::Key << "opencv_threads" << YAML::Value << c.opencv_threads;
  e << YAML::Key << "vocabularies" << YAML::Value << YAML::BeginMap;
  for (const auto& [name, path] : c.vocabularies) e << YAML::Key << name << YAML::Value << path;
  e << YAML::EndMap;
  e << YAML::Key << "storage" << YAML::Value << YAML::BeginMap;
  e << YAML::Key << "sync" << YAML::Value
    << (c.storage.sync == SyncMode::kGroupCommit ? "group_commit" : "every_write");
  e << YAML::Key << "group_commit_delay_ms" << YAML::Value << c.storage.group_commit_delay_ms;
  e << YAML::Key << "block_cache_bytes" << YAML::Value << c.storage.block_cache_bytes;
  e << YAML::Key << "disk_reserve_bytes" << YAML::Value << c.storage.disk_reserve_bytes;
  e << YAML::Key << "snapshots_keep_per_map" << YAML::Value << c.snapshots.keep_per_map;
  e << YAML::EndMap;
  const Limits& l = c.limits;
  e << YAML::Key << "limits" << YAML::Value << YAML::BeginMap;
  e << YAML::Key << "max_message_bytes" << YAML::Value << l.max_message_bytes;
  e << YAML::Key << "max_image_pixels" << YAML::Value << l.max_image_pixels;
  e << YAML::Key << "max_descriptors_per_frame" << YAML::Value << l.max_descriptors_per_frame;
  e << YAML::Key << "max_boxes_per_frame" << YAML::Value << l.max_boxes_per_frame;
  e << YAML::Key << "max_concurrent_streams" << YAML::Value << l.max_concurrent_streams;
  e << YAML::Key << "max_queued_frames" << YAML::Value << l.max_queued_frames;
  e << YAML::Key << "max_inflight_per_stream" << YAML::Value << l.max_inflight_per_stream;
  e << YAML::Key << "max_concurrent_unary" << YAML::Value << l.max_concurrent_unary;
  e << YAML::Key << "unary_queue_wait_ms" << YAML::Value << l.unary_queue_wait_ms;
  e << YAML::Key << "memory_quota_bytes" << YAML::Value << l.memory_quota_bytes;
  e << YAML::Key << "stream_header_timeout_ms" << YAML::Value << l.stream_header_timeout_ms;
  e << YAML::Key << "stream_idle_timeout_ms" << YAML::Value << l.stream_idle_timeout_ms;
  e << YAML::Key << "memory_budget_bytes" << YAML::Value << l.memory_budget_bytes;
  e << YAML::Key << "memory_wait_ms" << YAML::Value << l.memory_wait_ms;
  e << YAML::Key << "max_snapshot_bytes" << YAML::Value << l.max_snapshot_bytes;
  e << YAML::EndMap;
  e << YAML::Key << "shutdown_deadline_s" << YAML::Value << c.shutdown_deadline_s;
  const DetectorSettings& d = c.detector;
  e << YAML::Key << "detector" << YAML::Value << YAML::BeginMap;
  e << YAML::Key << "backend" << YAML::Value << d.backend;
  e << YAML::Key << "model" << YAML::Value << d.model;
  e << YAML::Key << "config" << YAML::Value << d.config;
  e << YAML::Key << "input_size" << YAML::Value << d.input_size;
  e << YAML::Key << "preprocessing" << YAML::Value << d.preprocessing;
  e << YAML::Key << "confidence" << YAML::Value << d.confidence;
  e << YAML::Key << "nms_iou" << YAML::Value << d.nms_iou;
  e << YAML::Key << "classes" << YAML::Value << YAML::Flow << d.classes;
  e << YAML::Key << "max_concurrent_calls" << YAML::Value << d.max_concurrent_calls;
  e << YAML::Key << "merge_iou" << YAML::Value << d.merge_iou;
  e << YAML::Key << "required" << YAML::Value << d.required;
  e << YAML::Key << "rectangular_letterbox" << YAML::Value << d.rectangular_letterbox;
  e << YAML::Key << "rewrite_graph" << YAML::Value << d.rewrite_graph;
  e << YAML::Key << "class_confidence" << YAML::Value << YAML::Flow << d.class_confidence;
  e << YAML::Key << "min_box_area" << YAML::Value << d.min_box_area;
  e << YAML::Key << "large_box_area" << YAML::Value << d.large_box_area;
  e << YAML::Key << "large_box_confidence" << YAML::Value << d.large_box_confidence;
  e << YAML::EndMap;
  e << YAML::Key << "log_level" << YAML::Value << c.log_level;
  const ClusterSettings& k = c.cluster;
  e << YAML::Key << "cluster" << YAML::Value << YAML::BeginMap;
  e << YAML::Key << "role" << YAML::Value << ClusterRoleName(k.role);
  e << YAML::Key << "name" << YAML::Value << k.name;
  e << YAML::Key << "nats" << YAML::Value << YAML::Flow << k.nats;
  e << YAML::Key << "etcd" << YAML::Value << YAML::Flow << k.etcd;
  e << YAML::Key << "shard_id" << YAML::Value << k.shard_id;
  e << YAML::Key << "advertise" << YAML::Value << k.advertise;
  e << YAML::Key << "internal_listen" << YAML::Value << k.internal_listen;
  e << YAML::Key << "replicas" << YAML::Value << k.replicas;
  e << YAML::Key << "stream_replicas" << YAML::Value << k.stream_replicas;
  e << YAML::Key << "replace_after_s" << YAML::Value << k.replace_after_s;
  e << YAML::Key << "compact_after_records" << YAML::Value << k.compact_after_records;
  e << YAML::Key << "compact_after_bytes" << YAML::Value << k.compact_after_bytes;
  e << YAML::Key << "compact_keep_s" << YAML::Value << k.compact_keep_s;
  e << YAML::Key << "internal_tls" << YAML::Value << (k.internal_tls ? "on" : "off");
  e << YAML::Key << "internal_ca_file" << YAML::Value << k.internal_ca_file;
  e << YAML::EndMap;
  e << YAML::EndMap;
  return std::string(e.c_str()) + "\n";
}

// ---- Embedded default paths --------------------------------------------------------------------

std::vector<PathRoot> DefaultPathRoots(const std::function<const char*(const char*)>& getenv,
                                       const std::string& executable) {
  namespace fs = std::filesystem;
  std::error_code error;
  if (const char* home = getenv("PLACEDB_HOME"); home && *home) {
    // The operator's choice is the only one: a second guess would hide a wrong value.
    return {{fs::absolute(home, error).lexically_normal().string(), "PLACEDB_HOME"}};
  }
  std::vector<PathRoot> roots;
  if (!executable.empty()) {
    // A few levels up: build/server/placedb-server, build/tools/..., or a binary in the checkout.
    fs::path dir = fs::path(executable).parent_path();
    for (int level = 0; level < 4 && !dir.empty(); ++level) {
      if (fs::is_regular_file(dir / "server" / "placedb.yaml", error)) {
        roots.push_back({dir.lexically_normal().string(), "the checkout of " + executable});
        break;
      }
      if (dir == dir.parent_path()) break;
      dir = dir.parent_path();
    }
  }
  const std::string cwd = fs::current_path(error).string();
  if (!error && (roots.empty() || roots.front().dir != cwd)) {
    roots.push_back({cwd, "the working directory"});
  }
  return roots;
}

Status ResolveDefaultPaths(const std::vector<PathRoot>& roots, ServerConfig* config) {
  namespace fs = std::filesystem;
  if (roots.empty()) return Status::NotFound("no directory to look for the default files in");
  const std::map<std::string, std::string> embedded = EmbeddedVocabularies();
  const std::string default_vocabulary = embedded.at("default");
  const auto vocabulary = config->vocabularies.find("default");
  const bool embedded_vocabulary =
      vocabulary != config->vocabularies.end() && vocabulary->second == default_vocabulary;
  const PathRoot* chosen = &roots.front();
  if (embedded_vocabulary) {
    chosen = nullptr;
    std::string tried;
    for (const PathRoot& root : roots) {
      const fs::path candidate = fs::path(root.dir) / default_vocabulary;
      std::error_code error;
      if (fs::is_regular_file(candidate, error)) {
        chosen = &root;
        break;
      }
      tried += (tried.empty() ? "" : ", ") + candidate.string() + " (" + root.why + ")";
    }
    if (chosen == nullptr) {
      return Status::NotFound("vocabulary 'default' (" + default_vocabulary +
                              ") is in none of: " + tried +
                              "; build it with tools/setup.sh, set PLACEDB_HOME to the directory "
                              "holding var/, or name one with --vocabulary default=PATH");
    }
  }
  for (auto& [name, path] : config->vocabularies) {
    const auto it = embedded.find(name);
    if (it != embedded.end() && it->second == path) {
      path = (fs::path(chosen->dir) / path).lexically_normal().string();
    }
  }
  if (config->data_dir == ServerConfig().data_dir) {
    config->data_dir = (fs::path(chosen->dir) / config->data_dir).lexically_normal().string();
  }
  return Status::Ok();
}

}  // namespace placedb::server
