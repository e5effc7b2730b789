// The server's configuration: file, then environment, then flags; which vocabularies are
// optional; a vocabulary or detector that does not load at startup.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <fstream>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "core/base/status.h"
#include "core/storage/map_store.h"
#include "tests/server/server_fixture.h"
#include "tests/test_support.h"

namespace placedb::server_testing {
namespace {

// The checkout, from CMake: __FILE__ is relative to the build directory when ccache's base_dir
// rewrites the compiler's paths, and the test runs in another directory.
std::string SourceDir() {
  return PLACEDB_SOURCE_DIR;
}

// An embedded-default vocabulary whose file is missing is a warning (maps that need it are
// unavailable); one the operator named is a startup error.
TEST_F(ServerTest, MissingEmbeddedSiftVocabularyIsAWarningUnlessConfigured) {
  ServerConfig config = Config();
  config.vocabularies["sift"] = root_ + "/nowhere/sift-debian.pdbfv";
  config.optional_vocabularies = {"sift"};
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  const grpc::Status missing = CreateMapStatus("s", SiftMapConfig());
  EXPECT_EQ(missing.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(missing.error_message().find("not loaded"), std::string::npos)
      << missing.error_message();
  {
    grpc::ClientContext context;
    v1::ServerInfo info;
    ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
    ASSERT_EQ(info.vocabularies_size(), 1);
    EXPECT_EQ(info.vocabularies(0).name(), "default");
  }
  StopServer();
  config.optional_vocabularies.clear();
  auto refused = Server::Start(config, {});
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.status().message().find("vocabulary 'sift'"), std::string::npos)
      << refused.status().ToString();

  // Which entries are optional: the embedded ones as embedded (also when a file repeats them).
  const char* plain[] = {"placedb-server"};
  auto defaults = server::ParseCommandLine(1, plain, [](const char*) { return nullptr; });
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->config.vocabularies.at("sift"), "var/vocabulary/sift-debian.pdbfv");
  EXPECT_TRUE(defaults->config.optional_vocabularies.count("sift"));
  const char* flagged[] = {"placedb-server", "--vocabulary", "sift=/data/sift.pdbfv"};
  auto flag = server::ParseCommandLine(3, flagged, [](const char*) { return nullptr; });
  ASSERT_TRUE(flag.ok());
  EXPECT_FALSE(flag->config.optional_vocabularies.count("sift"));
  ServerConfig from_file;
  const ServerConfig embedded;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(embedded), &from_file).ok());
  EXPECT_TRUE(from_file.optional_vocabularies.count("sift"));
  ASSERT_TRUE(server::ApplyConfigYaml(
                  "vocabularies:\n  default: a.pdbv\n  sift: /data/sift.pdbfv\n", &from_file)
                  .ok());
  EXPECT_FALSE(from_file.optional_vocabularies.count("sift"));
}

// A detector model that does not load: detection is off (and says why) unless it is required.
TEST_F(ServerTest, DetectorThatFailsToLoadIsOffUnlessRequired) {
  ServerConfig config = Config();
  config.detector.model = root_ + "/no-such-model.onnx";
  config.detector.required = true;
  auto refused = Server::Start(config, {{{"default", vocabulary_}}, nullptr});
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kNotFound) << refused.status().ToString();

  config.detector.required = false;
  ASSERT_NO_FATAL_FAILURE(StartServer(config));
  grpc::ClientContext context;
  v1::ServerInfo info;
  ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
  EXPECT_EQ(info.detector().rfind("off: NOT_FOUND", 0), 0u) << info.detector();
  v1::MapConfig server_boxes;
  server_boxes.mutable_detection()->set_box_source(v1::BOX_SOURCE_BOTH);
  EXPECT_EQ(CreateMapStatus("m", server_boxes).error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  // Maps on agents' boxes work as ever.
  CreateMap("m");
  const IngestOutcome outcome = IngestAll(stub_.get(), "m", {RtabmapObservation(1, "a")});
  ASSERT_EQ(outcome.responses.size(), 1u);
  EXPECT_TRUE(outcome.responses[0].stored());
}

TEST(ServerConfigTest, FileThenEnvironmentThenFlags) {
  const std::string dir = testing::MakeTempDir("placedb-config");
  const std::string path = dir + "/placedb.yaml";
  std::ofstream(path) << "listen: 0.0.0.0:6000\n"
                         "data_dir: /srv/placedb\n"
                         "threads: 3\n"
                         "metrics_threads: 6\n"
                         "metrics_request_timeout_ms: 700\n"
                         "vocabularies:\n  default: a.pdbv\n  indoor: b.pdbv\n"
                         "limits:\n  max_boxes_per_frame: 9\n"
                         "  stream_header_timeout_ms: 1500\n  stream_idle_timeout_ms: 2500\n"
                         "storage:\n  sync: group_commit\n";
  std::map<std::string, std::string> env = {{"PLACEDB_DATA_DIR", "/env/data"},
                                            {"PLACEDB_METRICS_PORT", "9999"}};
  auto getenv = [&](const char* name) -> const char* {
    auto it = env.find(name);
    return it == env.end() ? nullptr : it->second.c_str();
  };
  const char* argv[] = {"placedb-server", "--config",       path.c_str(),  "--threads", "5",
                        "--vocabulary",   "outdoor=c.pdbv", "--max-boxes", "11"};
  auto parsed = server::ParseCommandLine(9, argv, getenv);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  ASSERT_FALSE(parsed->exit_code);
  const ServerConfig& c = parsed->config;
  EXPECT_EQ(c.listen, "0.0.0.0:6000");            // file
  EXPECT_EQ(c.data_dir, "/env/data");             // environment over file
  EXPECT_EQ(c.metrics_listen, "127.0.0.1:9999");  // environment (port only), loopback default
  EXPECT_EQ(c.metrics_threads, 6);
  EXPECT_EQ(c.metrics_request_timeout_ms, 700u);
  EXPECT_EQ(c.limits.stream_header_timeout_ms, 1500u);
  EXPECT_EQ(c.limits.stream_idle_timeout_ms, 2500u);
  EXPECT_EQ(c.threads, 5);  // flag over file
  EXPECT_EQ(c.limits.max_boxes_per_frame, 11u);
  EXPECT_EQ(c.storage.sync, SyncMode::kGroupCommit);
  EXPECT_EQ(c.vocabularies.size(), 3u);
  EXPECT_EQ(c.vocabularies.at("indoor"), "b.pdbv");
  EXPECT_EQ(c.vocabularies.at("outdoor"), "c.pdbv");

  // Round trip through --print-config's YAML.
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(c), &again).ok());
  EXPECT_EQ(server::ConfigToYaml(again), server::ConfigToYaml(c));
  EXPECT_EQ(again.metrics_threads, 6);
  EXPECT_EQ(again.metrics_request_timeout_ms, 700u);
  EXPECT_EQ(again.limits.stream_header_timeout_ms, 1500u);
  EXPECT_EQ(again.limits.stream_idle_timeout_ms, 2500u);

  ServerConfig bad;
  const Status typo = server::ApplyConfigYaml("limits:\n  max_boxes: 3\n", &bad);
  EXPECT_EQ(typo.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(typo.message().find("limits.max_boxes"), std::string::npos) << typo.message();
  EXPECT_FALSE(server::ApplyConfigYaml("threads: many\n", &bad).ok());
  // Out-of-range timeouts and thread counts name their key.
  for (const auto& [yaml, key] : std::vector<std::pair<std::string, std::string>>{
           {"limits:\n  stream_header_timeout_ms: 0\n", "limits.stream_header_timeout_ms"},
           {"limits:\n  stream_idle_timeout_ms: 10\n", "limits.stream_idle_timeout_ms"},
           {"metrics_threads: 1\n", "metrics_threads"},
           {"metrics_request_timeout_ms: 0\n", "metrics_request_timeout_ms"}}) {
    ServerConfig out_of_range;
    ASSERT_TRUE(server::ApplyConfigYaml(yaml, &out_of_range).ok()) << yaml;
    const Status invalid = server::ValidateServerConfig(out_of_range);
    EXPECT_EQ(invalid.code(), StatusCode::kInvalidArgument) << yaml;
    EXPECT_NE(invalid.message().find(key), std::string::npos) << invalid.message();
  }
  ServerConfig no_default;
  no_default.vocabularies = {{"indoor", "b.pdbv"}};
  EXPECT_NE(server::ValidateServerConfig(no_default).message().find("default"), std::string::npos);
  // The example config in the repository is valid.
  ServerConfig example;
  EXPECT_TRUE(server::ApplyConfigFile(SourceDir() + "/server/placedb.yaml", &example).ok());
  EXPECT_TRUE(server::ValidateServerConfig(example).ok());
  // ... and shows the defaults (of the stream and metrics-endpoint keys at least).
  const ServerConfig defaults;
  EXPECT_EQ(example.metrics_listen, defaults.metrics_listen);
  EXPECT_EQ(example.metrics_threads, defaults.metrics_threads);
  EXPECT_EQ(example.metrics_request_timeout_ms, defaults.metrics_request_timeout_ms);
  EXPECT_EQ(example.limits.stream_header_timeout_ms, defaults.limits.stream_header_timeout_ms);
  EXPECT_EQ(example.limits.stream_idle_timeout_ms, defaults.limits.stream_idle_timeout_ms);
}

// limits.max_snapshot_bytes: default 64 GiB, from the file, overridden by the environment,
// printed and read back, refused below 1 KiB or when the environment holds no byte count.
TEST(ServerConfigTest, MaxSnapshotBytesFromFileAndEnvironment) {
  EXPECT_EQ(ServerConfig().limits.max_snapshot_bytes, uint64_t(64) << 30);
  ServerConfig c;
  ASSERT_TRUE(server::ApplyConfigYaml("limits:\n  max_snapshot_bytes: 5000\n", &c).ok());
  EXPECT_EQ(c.limits.max_snapshot_bytes, 5000u);
  std::map<std::string, std::string> env = {{"PLACEDB_MAX_SNAPSHOT_BYTES", "1099511627776"}};
  auto getenv = [&](const char* name) -> const char* {
    auto it = env.find(name);
    return it == env.end() ? nullptr : it->second.c_str();
  };
  ASSERT_TRUE(server::ApplyEnvironment(&c, getenv).ok());
  EXPECT_EQ(c.limits.max_snapshot_bytes, uint64_t(1) << 40);
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(c), &again).ok());
  EXPECT_EQ(again.limits.max_snapshot_bytes, uint64_t(1) << 40);

  env["PLACEDB_MAX_SNAPSHOT_BYTES"] = "64G";
  Status status = server::ApplyEnvironment(&c, getenv);
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("PLACEDB_MAX_SNAPSHOT_BYTES"), std::string::npos)
      << status.message();
  c.limits.max_snapshot_bytes = 100;
  status = server::ValidateServerConfig(c);
  EXPECT_NE(status.message().find("limits.max_snapshot_bytes"), std::string::npos)
      << status.message();
}

TEST(ServerConfigTest, SearchSettings) {
  ServerConfig c;
  EXPECT_EQ(c.search.threads, 1);
  EXPECT_DOUBLE_EQ(c.search.max_word_share, 1.0);
  EXPECT_EQ(c.search.skip_words_min_places, 100000u);
  ASSERT_TRUE(
      server::ApplyConfigYaml(
          "search:\n  threads: 2\n  max_word_share: 0.1\n  skip_words_min_places: 500000\n", &c)
          .ok());
  EXPECT_EQ(c.search.threads, 2);
  EXPECT_DOUBLE_EQ(c.search.max_word_share, 0.1);
  EXPECT_EQ(c.search.skip_words_min_places, 500000u);
  ASSERT_TRUE(server::ValidateServerConfig(c).ok());
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(c), &again).ok());
  EXPECT_DOUBLE_EQ(again.search.max_word_share, 0.1);
  EXPECT_EQ(again.search.skip_words_min_places, 500000u);

  Status unknown = server::ApplyConfigYaml("search:\n  share: 0.1\n", &c);
  EXPECT_EQ(unknown.code(), StatusCode::kInvalidArgument);
  for (double share : {0.0, -0.5, 1.5}) {
    ServerConfig bad;
    bad.search.max_word_share = share;
    Status status = server::ValidateServerConfig(bad);
    EXPECT_NE(status.message().find("search.max_word_share"), std::string::npos) << share;
  }
  ServerConfig bad;
  bad.search.threads = 0;
  EXPECT_NE(server::ValidateServerConfig(bad).message().find("search.threads"), std::string::npos);
}

// Found by tests/fuzz/fuzz_server_config: a value with a CR (an environment or YAML file with CRLF
// line endings) was accepted, and --print-config printed it as a YAML line the CR ends, so the
// printed configuration was not the one in use. Control characters are now refused by key.
TEST(ServerConfigTest, ControlCharactersAreRefused) {
  const std::map<std::string, std::string> environment = {{"PLACEDB_DATA_DIR", "/srv/placedb\r"}};
  ServerConfig c;
  ASSERT_TRUE(server::ApplyEnvironment(&c, [&](const char* name) -> const char* {
                auto it = environment.find(name);
                return it == environment.end() ? nullptr : it->second.c_str();
              }).ok());
  Status status = server::ValidateServerConfig(c);
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("data_dir: contains a control character"), std::string::npos)
      << status.message();

  ServerConfig yaml;
  ASSERT_TRUE(server::ApplyConfigYaml("vocabularies:\n  indoor: \"in\\tdoor.pdbv\"\n", &yaml).ok());
  status = server::ValidateServerConfig(yaml);
  EXPECT_NE(status.message().find("vocabularies.indoor: contains a control character"),
            std::string::npos)
      << status.message();
  // Everything else still prints and loads back unchanged.
  ServerConfig plain;
  plain.data_dir = "/srv/place db/ü";
  ASSERT_TRUE(server::ValidateServerConfig(plain).ok());
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(plain), &again).ok());
  EXPECT_EQ(again.data_dir, plain.data_dir);
}

// Cluster mode's section and flags (issue 18): parsed, printed, validated with the key named.
TEST(ServerConfigTest, ClusterSection) {
  auto parse = [](std::vector<const char*> args) {
    args.insert(args.begin(), "placedb-server");
    return server::ParseCommandLine(int(args.size()), args.data(),
                                    [](const char*) { return nullptr; });
  };
  // Role single (the default) ignores the rest, however incomplete.
  auto single = parse({"--nats", "nonsense"});
  ASSERT_TRUE(single.ok()) << single.status().ToString();
  EXPECT_EQ(single->config.cluster.role, server::ClusterRole::kSingle);

  auto worker = parse({"--role", "worker", "--cluster-name", "fleet", "--nats",
                       "nats://10.0.0.1:4222,nats://10.0.0.2:4222", "--etcd",
                       "10.0.0.1:2379,10.0.0.2:2379,10.0.0.3:2379"});
  ASSERT_TRUE(worker.ok()) << worker.status().ToString();
  const server::ClusterSettings& k = worker->config.cluster;
  EXPECT_EQ(k.role, server::ClusterRole::kWorker);
  EXPECT_EQ(k.name, "fleet");
  EXPECT_EQ(k.nats, (std::vector<std::string>{"nats://10.0.0.1:4222", "nats://10.0.0.2:4222"}));
  EXPECT_EQ(k.etcd.size(), 3u);
  EXPECT_EQ(k.replicas, 2);
  EXPECT_EQ(k.stream_replicas, 3);
  EXPECT_EQ(k.replace_after_s, 30);
  EXPECT_EQ(k.compact_after_records, 100000);
  EXPECT_EQ(k.compact_after_bytes, int64_t(1) << 30);
  EXPECT_EQ(k.compact_keep_s, 150);

  // --print-config's YAML loads back to the same section.
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(worker->config), &again).ok());
  EXPECT_EQ(again.cluster.role, server::ClusterRole::kWorker);
  EXPECT_EQ(again.cluster.nats, k.nats);
  EXPECT_EQ(again.cluster.etcd, k.etcd);
  EXPECT_EQ(again.cluster.name, "fleet");

  auto refused = [&](std::vector<const char*> args, const std::string& message) {
    auto result = parse(std::move(args));
    ASSERT_FALSE(result.ok()) << message;
    EXPECT_EQ(result.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(result.status().message().find(message), std::string::npos)
        << result.status().message();
  };
  refused({"--role", "leader"}, "--role: must be single, worker or shard");
  refused({"--role", "worker", "--etcd", "a:2379"}, "cluster.nats: role worker needs");
  refused({"--role", "shard", "--nats", "nats://a:4222"}, "cluster.etcd: role shard needs");
  refused({"--role", "worker", "--nats", "nats://a", "--etcd", "a:2379"},
          "cluster.nats: 'nats://a' is not nats://host:port");
  refused({"--role", "worker", "--nats", "a:4222", "--etcd", "a:2379", "--cluster-name", "a.b"},
          "cluster.name: 'a.b' must be");
  refused({"--role", "shard", "--nats", "a:4222", "--etcd", "a:2379", "--advertise", "shard-0"},
          "cluster.advertise: 'shard-0' is not host:port");
  refused({"--role", "shard", "--nats", "a:4222", "--etcd", "a:2379", "--shard-id", "a/b"},
          "cluster.shard_id: 'a/b' must be");
  auto shard =
      parse({"--role", "shard", "--nats", "a:4222", "--etcd", "a:2379", "--shard-id", "shard-0",
             "--advertise", "10.0.0.5:50061", "--internal-listen", "0.0.0.0:50061"});
  ASSERT_TRUE(shard.ok()) << shard.status().ToString();
  EXPECT_EQ(shard->config.cluster.EffectiveShardId(), "shard-0");
  EXPECT_EQ(shard->config.cluster.internal_listen, "0.0.0.0:50061");

  ServerConfig yaml;
  const Status typo = server::ApplyConfigYaml("cluster:\n  role: worker\n  replica: 3\n", &yaml);
  EXPECT_NE(typo.message().find("cluster.replica: unknown key"), std::string::npos)
      << typo.message();
  ASSERT_TRUE(server::ApplyConfigYaml("cluster:\n  role: worker\n  nats: [\"nats://a:4222\"]\n"
                                      "  etcd: [\"a:2379\"]\n  stream_replicas: 7\n",
                                      &yaml)
                  .ok());
  EXPECT_NE(server::ValidateServerConfig(yaml).message().find(
                "cluster.stream_replicas: must be in [1, 5]"),
            std::string::npos);

  // Issue 35, compaction: YAML and flags, 0 = off, negative refused; --print-config keeps them.
  ServerConfig compact;
  ASSERT_TRUE(server::ApplyConfigYaml("cluster:\n  compact_after_records: 500\n"
                                      "  compact_after_bytes: 0\n  compact_keep_s: 200\n",
                                      &compact)
                  .ok());
  EXPECT_EQ(compact.cluster.compact_after_records, 500);
  EXPECT_EQ(compact.cluster.compact_after_bytes, 0);
  ServerConfig compact_again;
  ASSERT_TRUE(server::ApplyConfigYaml(server::ConfigToYaml(compact), &compact_again).ok());
  EXPECT_EQ(compact_again.cluster.compact_after_records, 500);
  EXPECT_EQ(compact_again.cluster.compact_after_bytes, 0);
  EXPECT_EQ(compact_again.cluster.compact_keep_s, 200);
  ServerConfig keep_bad;
  ASSERT_TRUE(server::ApplyConfigYaml("cluster:\n  role: worker\n  nats: [\"nats://a:4222\"]\n"
                                      "  etcd: [\"a:2379\"]\n  compact_keep_s: -1\n",
                                      &keep_bad)
                  .ok());
  EXPECT_NE(server::ValidateServerConfig(keep_bad).message().find(
                "cluster.compact_keep_s: must be in [0, 86400]"),
            std::string::npos);
  auto flagged = parse({"--role", "worker", "--nats", "a:4222", "--etcd", "a:2379",
                        "--compact-after-records", "20", "--compact-after-bytes", "65536"});
  ASSERT_TRUE(flagged.ok()) << flagged.status().ToString();
  EXPECT_EQ(flagged->config.cluster.compact_after_records, 20);
  EXPECT_EQ(flagged->config.cluster.compact_after_bytes, 65536);
  refused(
      {"--role", "worker", "--nats", "a:4222", "--etcd", "a:2379", "--compact-after-records", "-1"},
      "cluster.compact_after_records: must be >= 0");
  refused(
      {"--role", "worker", "--nats", "a:4222", "--etcd", "a:2379", "--compact-after-bytes", "-5"},
      "cluster.compact_after_bytes: must be >= 0");
}

// cluster.internal_tls (issue 35): off by default; YAML on/off, --internal-tls,
// PLACEDB_INTERNAL_TLS; on needs all three TLS files, the key missing named.
TEST(ServerConfigTest, ClusterInternalTls) {
  const std::map<std::string, std::string> no_env;
  auto parse = [](std::vector<const char*> args, const std::map<std::string, std::string>& env) {
    args.insert(args.begin(), "placedb-server");
    return server::ParseCommandLine(int(args.size()), args.data(), [&env](const char* name) {
      const auto it = env.find(name);
      return it == env.end() ? nullptr : it->second.c_str();
    });
  };
  const std::vector<const char*> worker = {"--role", "worker", "--nats",
                                           "a:4222", "--etcd", "a:2379"};
  auto with = [&](std::vector<const char*> more) {
    std::vector<const char*> args = worker;
    args.insert(args.end(), more.begin(), more.end());
    return args;
  };
  auto plain = parse(worker, no_env);
  ASSERT_TRUE(plain.ok()) << plain.status().ToString();
  EXPECT_FALSE(plain->config.cluster.internal_tls);

  const std::vector<const char*> files = {"--tls-cert", "n.pem",           "--tls-key",
                                          "n.key",      "--tls-client-ca", "ca.pem"};
  std::vector<const char*> on = with({"--internal-tls"});
  on.insert(on.end(), files.begin(), files.end());
  auto flagged = parse(on, no_env);
  ASSERT_TRUE(flagged.ok()) << flagged.status().ToString();
  EXPECT_TRUE(flagged->config.cluster.internal_tls);
  // --print-config says "on" and loads back.
  const std::string yaml = server::ConfigToYaml(flagged->config);
  EXPECT_NE(yaml.find("internal_tls: on"), std::string::npos) << yaml;
  ServerConfig again;
  ASSERT_TRUE(server::ApplyConfigYaml(yaml, &again).ok());
  EXPECT_TRUE(again.cluster.internal_tls);

  std::vector<const char*> env_args = worker;
  env_args.insert(env_args.end(), files.begin(), files.end());
  auto from_env = parse(env_args, {{"PLACEDB_INTERNAL_TLS", "on"}});
  ASSERT_TRUE(from_env.ok()) << from_env.status().ToString();
  EXPECT_TRUE(from_env->config.cluster.internal_tls);
  auto bad_env = parse(env_args, {{"PLACEDB_INTERNAL_TLS", "maybe"}});
  ASSERT_FALSE(bad_env.ok());
  EXPECT_NE(bad_env.status().message().find("PLACEDB_INTERNAL_TLS"), std::string::npos);

  ServerConfig from_yaml;
  ASSERT_TRUE(server::ApplyConfigYaml("cluster:\n  internal_tls: on\n", &from_yaml).ok());
  EXPECT_TRUE(from_yaml.cluster.internal_tls);
  ASSERT_TRUE(server::ApplyConfigYaml("cluster:\n  internal_tls: off\n", &from_yaml).ok());
  EXPECT_FALSE(from_yaml.cluster.internal_tls);

  // Without the files: a clear error naming the missing one.
  for (const auto& [args, missing] : std::vector<std::pair<std::vector<const char*>, std::string>>{
           {with({"--internal-tls"}), "tls.cert_file"},
           {with({"--internal-tls", "--tls-cert", "n.pem", "--tls-key", "n.key"}),
            "tls.client_ca_file"}}) {
    auto refused = parse(args, no_env);
    ASSERT_FALSE(refused.ok()) << missing;
    EXPECT_EQ(refused.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(refused.status().message().find("cluster.internal_tls: needs " + missing),
              std::string::npos)
        << refused.status().message();
  }
  // Role single ignores it (as the rest of the section).
  auto single = parse({"--internal-tls"}, no_env);
  ASSERT_TRUE(single.ok()) << single.status().ToString();

  // cluster.internal_ca_file stands in for tls.client_ca_file (the public API then stays
  // without client certificates).
  std::vector<const char*> own_ca = with({"--internal-tls", "--tls-cert", "n.pem", "--tls-key",
                                          "n.key", "--internal-ca", "internal-ca.pem"});
  auto separate = parse(own_ca, no_env);
  ASSERT_TRUE(separate.ok()) << separate.status().ToString();
  EXPECT_EQ(separate->config.cluster.InternalCaFile(separate->config.tls), "internal-ca.pem");
  EXPECT_FALSE(separate->config.tls.mutual());
  auto ca_env = parse(with({"--internal-tls", "--tls-cert", "n.pem", "--tls-key", "n.key"}),
                      {{"PLACEDB_INTERNAL_CA_FILE", "env-ca.pem"}});
  ASSERT_TRUE(ca_env.ok()) << ca_env.status().ToString();
  EXPECT_EQ(ca_env->config.cluster.internal_ca_file, "env-ca.pem");
  // The image's config turns it on, with the CA of the mounted secrets.
  ServerConfig image;
  ASSERT_TRUE(server::ApplyConfigFile(SourceDir() + "/deploy/placedb.yaml", &image).ok());
  EXPECT_TRUE(image.cluster.internal_tls);
  EXPECT_EQ(image.cluster.internal_ca_file, "/run/secrets/placedb/ca.crt");
}

}  // namespace
}  // namespace placedb::server_testing
