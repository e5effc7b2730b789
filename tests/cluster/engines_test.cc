// Cluster mode's engine clients (server/cluster/etcd_client.h, server/cluster/jetstream.h)
// against real 3-node etcd and nats-server (JetStream) clusters (tests/cluster/engines.h).
//
// Times (lease expiry, re-election stall) are printed as `name value unit`, never asserted; the
// bounded waits below only keep a broken engine from hanging the test.
#include "tests/cluster/engines.h"

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <fstream>
#include <map>
#include <set>
#include <thread>

#include "bench/bench_output.h"
#include "core/base/thread_annotations.h"
#include "server/cluster/etcd_client.h"
#include "server/cluster/jetstream.h"
#include "tests/join_on_exit.h"

namespace placedb::cluster {
namespace {

using namespace std::chrono_literals;
using testing::Engines;
using testing::EnginesOptions;

// "<prefix><number>": appended, as a literal + std::to_string() trips GCC 12's false -Wrestrict.
std::string Id(std::string prefix, int64_t number) {
  prefix += std::to_string(number);
  return prefix;
}

std::unique_ptr<Engines> StartEngines(bool nats, bool etcd) {
  EnginesOptions options;
  options.nats = nats;
  options.etcd = etcd;
  const double start_ms = bench::NowMs();
  auto engines = Engines::Start(options);
  std::printf("engines started in %.0f ms\n", bench::NowMs() - start_ms);
  EXPECT_TRUE(engines.ok()) << engines.status().ToString();
  return engines.ok() ? std::move(*engines) : nullptr;
}

std::unique_ptr<EtcdClient> Etcd(std::vector<std::string> endpoints) {
  EtcdOptions options;
  options.endpoints = std::move(endpoints);
  auto client = EtcdClient::Create(options);
  EXPECT_TRUE(client.ok()) << client.status().ToString();
  return std::move(*client);
}

std::unique_ptr<JetStream> Js(std::vector<std::string> servers) {
  JetStreamOptions options;
  options.servers = std::move(servers);
  auto js = JetStream::Connect(options);
  EXPECT_TRUE(js.ok()) << js.status().ToString();
  return js.ok() ? std::move(*js) : nullptr;
}

// Polls `done` every 20 ms up to `limit` (a bound against hangs, not a timing assert).
template <typename Predicate>
bool WaitFor(Predicate done, std::chrono::milliseconds limit = 20s) {
  const auto until = std::chrono::steady_clock::now() + limit;
  while (std::chrono::steady_clock::now() < until) {
    if (done()) return true;
    std::this_thread::sleep_for(20ms);
  }
  return done();
}

// Collects watch events from the watcher's thread.
struct EventLog {
  Mutex mutex;
  std::vector<WatchEvent> events GUARDED_BY(mutex);
  void Add(const std::vector<WatchEvent>& batch) {
    MutexLock lock(mutex);
    events.insert(events.end(), batch.begin(), batch.end());
  }
  std::vector<WatchEvent> Snapshot() {
    MutexLock lock(mutex);
    return events;
  }
  size_t size() {
    MutexLock lock(mutex);
    return events.size();
  }
};

std::string Describe(const std::vector<WatchEvent>& events) {
  std::string out;
  for (const auto& event : events) {
    out += (event.type == WatchEvent::Type::kPut ? "put " : "delete ") + event.kv.key +
           (event.type == WatchEvent::Type::kPut ? "=" + event.kv.value : "") + "; ";
  }
  return out;
}

// ---- etcd --------------------------------------------------------------------------------------

// Issue 34: engines restarted after a kill must find their ports free. Ports from the kernel's
// ephemeral range are handed out as source ports of outgoing connections (many, under load): one
// held that way made the restarted engine fail to bind (EADDRINUSE, shown below). The harness
// picks its ports below that range, where connect() never takes one.
TEST(EnginesHarnessTest, PortsAreBelowTheEphemeralRangeAndFree) {
  int ephemeral_low = 32768;
  std::ifstream("/proc/sys/net/ipv4/ip_local_port_range") >> ephemeral_low;
  auto ports = testing::FreePorts("127.0.0.1", 20);
  ASSERT_TRUE(ports.ok()) << ports.status().ToString();
  std::set<int> distinct(ports->begin(), ports->end());
  EXPECT_EQ(distinct.size(), 20u);
  for (const int port : *ports) {
    EXPECT_LT(port, ephemeral_low);
    EXPECT_GE(port, 1024);
  }
  // Why it matters: a connection whose source port is P keeps a server from listening on P.
  const int listener = ::socket(AF_INET, SOCK_STREAM, 0);
  const int client = ::socket(AF_INET, SOCK_STREAM, 0);
  const int server = ::socket(AF_INET, SOCK_STREAM, 0);
  ASSERT_GE(listener, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof address;
  ASSERT_EQ(::bind(listener, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
  ASSERT_EQ(::listen(listener, 1), 0);
  ASSERT_EQ(::getsockname(listener, reinterpret_cast<sockaddr*>(&address), &length), 0);
  const sockaddr_in destination = address;
  address.sin_port = htons(uint16_t((*ports)[0]));
  ASSERT_EQ(::bind(client, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
  ASSERT_EQ(::connect(client, reinterpret_cast<const sockaddr*>(&destination), sizeof destination),
            0);
  const int yes = 1;
  ::setsockopt(server, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
  EXPECT_NE(::bind(server, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
  EXPECT_EQ(errno, EADDRINUSE);
  for (const int fd : {listener, client, server}) ::close(fd);
}

TEST(EtcdClientTest, PutGetPrefixAndDelete) {
  auto engines = StartEngines(/*nats=*/false, /*etcd=*/true);
  ASSERT_TRUE(engines);
  auto etcd = Etcd(engines->EtcdEndpoints());

  auto missing = etcd->Get("/t/none");
  ASSERT_TRUE(missing.ok()) << missing.status().ToString();
  EXPECT_TRUE(missing->kvs.empty());

  ASSERT_TRUE(etcd->Put("/t/maps/b", "2").ok());
  ASSERT_TRUE(etcd->Put("/t/maps/a", "1").ok());
  auto last = etcd->Put("/t/other", "3");
  ASSERT_TRUE(last.ok());

  auto one = etcd->Get("/t/maps/a");
  ASSERT_TRUE(one.ok());
  ASSERT_EQ(one->kvs.size(), 1u);
  EXPECT_EQ(one->kvs[0].value, "1");
  EXPECT_EQ(one->kvs[0].version, 1);

  auto maps = etcd->Get("/t/maps/", /*prefix=*/true);
  ASSERT_TRUE(maps.ok());
  ASSERT_EQ(maps->kvs.size(), 2u);
  EXPECT_EQ(maps->kvs[0].key, "/t/maps/a");  // sorted by key
  EXPECT_EQ(maps->kvs[1].key, "/t/maps/b");
  EXPECT_EQ(maps->revision, *last);

  auto deleted = etcd->Delete("/t/maps/", /*prefix=*/true);
  ASSERT_TRUE(deleted.ok());
  EXPECT_EQ(*deleted, 2);
  EXPECT_TRUE(etcd->Get("/t/maps/", true)->kvs.empty());
  EXPECT_EQ(etcd->Get("/t/other")->kvs.size(), 1u);  // outside the prefix: kept
}

TEST(EtcdClientTest, TxnCreateIfAbsentHasExactlyOneWinnerAndCompareAndSwapDetectsChange) {
  auto engines = StartEngines(false, true);
  ASSERT_TRUE(engines);
  auto endpoints = engines->EtcdEndpoints();
  auto first = Etcd(endpoints);
  std::reverse(endpoints.begin(), endpoints.end());
  auto second = Etcd(endpoints);  // starts on another member

  constexpr int kKeys = 30;
  std::atomic<int> ready{0};
  std::vector<std::vector<bool>> won(2, std::vector<bool>(kKeys));
  std::vector<std::vector<std::string>> seen(2, std::vector<std::string>(kKeys));
  auto race = [&](int who, EtcdClient& client) {
    ready.fetch_add(1);
    while (ready.load() < 2) {
    }
    for (int k = 0; k < kKeys; ++k) {
      const std::string key = Id("/t/race/", k);
      auto result = client.Txn({Compare::Absent(key)}, {TxnOp::Put(key, Id("client", who))},
                               {TxnOp::Get(key)});
      ASSERT_TRUE(result.ok()) << result.status().ToString();
      won[who][k] = result->succeeded;
      if (!result->succeeded) {
        ASSERT_EQ(result->gets.size(), 1u);
        ASSERT_EQ(result->gets[0].kvs.size(), 1u);
        seen[who][k] = result->gets[0].kvs[0].value;
      }
    }
  };
  std::thread a([&] { race(0, *first); });
  std::thread b([&] { race(1, *second); });
  a.join();
  b.join();
  int wins[2] = {0, 0};
  for (int k = 0; k < kKeys; ++k) {
    ASSERT_NE(won[0][k], won[1][k]) << "key " << k << ": exactly one create must win";
    const int winner = won[0][k] ? 0 : 1;
    ++wins[winner];
    EXPECT_EQ(seen[1 - winner][k], Id("client", winner));
    auto stored = first->Get(Id("/t/race/", k));
    ASSERT_TRUE(stored.ok());
    EXPECT_EQ(stored->kvs.at(0).value, Id("client", winner));
    EXPECT_EQ(stored->kvs.at(0).version, 1) << "the loser must not have written";
  }
  std::printf("etcd_txn_race wins %d/%d\n", wins[0], wins[1]);

  // Compare-and-swap: succeeds on the revision read, fails once someone else wrote.
  auto read = first->Get("/t/race/0");
  ASSERT_TRUE(read.ok());
  const int64_t revision = read->kvs.at(0).mod_revision;
  auto swapped = first->Txn({Compare::ModRevisionIs("/t/race/0", revision)},
                            {TxnOp::Put("/t/race/0", "swapped")});
  ASSERT_TRUE(swapped.ok());
  EXPECT_TRUE(swapped->succeeded);
  auto stale = second->Txn({Compare::ModRevisionIs("/t/race/0", revision)},
                           {TxnOp::Put("/t/race/0", "stale")});
  ASSERT_TRUE(stale.ok());
  EXPECT_FALSE(stale->succeeded);
  auto value_guard =
      second->Txn({Compare::ValueIs("/t/race/0", "swapped")}, {TxnOp::Delete("/t/race/0")});
  ASSERT_TRUE(value_guard.ok());
  EXPECT_TRUE(value_guard->succeeded);
  EXPECT_TRUE(first->Get("/t/race/0")->kvs.empty());
}

TEST(EtcdClientTest, LeaseKeepsKeysWhileKeptAliveAndExpiresAfterTtlOnceStopped) {
  auto engines = StartEngines(false, true);
  ASSERT_TRUE(engines);
  auto etcd = Etcd(engines->EtcdEndpoints());
  auto lease = etcd->GrantLease(2);
  ASSERT_TRUE(lease.ok()) << lease.status().ToString();
  EXPECT_GE(lease->ttl_seconds, 2);
  ASSERT_TRUE(etcd->Put("/t/shards/s1", "alive", lease->id).ok());

  std::atomic<int> lost{0};
  auto keeper = etcd->KeepAlive(*lease, [&](const Status&) { lost.fetch_add(1); });
  // Twice the TTL: without keepalives the key would be gone by now.
  std::this_thread::sleep_for(std::chrono::seconds(2 * lease->ttl_seconds));
  auto still = etcd->Get("/t/shards/s1");
  ASSERT_TRUE(still.ok());
  ASSERT_EQ(still->kvs.size(), 1u) << "the keepalive did not keep the lease";
  EXPECT_EQ(still->kvs[0].lease, lease->id);

  EventLog log;
  auto watcher = etcd->Watch("/t/shards/", still->revision + 1,
                             [&](const std::vector<WatchEvent>& events) { log.Add(events); });
  keeper->Stop();
  const double stopped_ms = bench::NowMs();
  double deleted_ms = 0;
  ASSERT_TRUE(WaitFor([&] {
    if (log.size() > 0 && deleted_ms == 0) deleted_ms = bench::NowMs();
    return log.size() > 0;
  })) << "the lease's key was never deleted";
  auto events = log.Snapshot();
  ASSERT_EQ(events.size(), 1u) << Describe(events);
  EXPECT_EQ(events[0].type, WatchEvent::Type::kDelete);
  EXPECT_TRUE(etcd->Get("/t/shards/s1")->kvs.empty());
  EXPECT_EQ(lost.load(), 0) << "Stop() must not report a loss";
  // From the keeper's stop (the last keepalive was at most ttl/3 before) to the delete event.
  bench::Print("etcd_lease_expiry_after_keepalive_stop_ms", deleted_ms - stopped_ms, "ms");
  bench::Print("etcd_lease_ttl_s", static_cast<double>(lease->ttl_seconds), "s");

  // A lease revoked under a running keeper: the keeper reports the loss.
  auto second = etcd->GrantLease(5);
  ASSERT_TRUE(second.ok());
  Mutex mutex;
  Status why;
  auto second_keeper = etcd->KeepAlive(*second, [&](const Status& status) {
    MutexLock lock(mutex);
    why = status;
    lost.fetch_add(1);
  });
  ASSERT_TRUE(etcd->RevokeLease(second->id).ok());
  ASSERT_TRUE(WaitFor([&] { return second_keeper->lost(); }));
  EXPECT_EQ(lost.load(), 1);
  MutexLock lock(mutex);
  EXPECT_EQ(why.code(), StatusCode::kNotFound) << why.ToString();
  EXPECT_EQ(etcd->RevokeLease(second->id).code(), StatusCode::kNotFound);
}

TEST(EtcdClientTest, WatchSeesPutsAndDeletesInOrderAndResumesFromARevision) {
  auto engines = StartEngines(false, true);
  ASSERT_TRUE(engines);
  auto etcd = Etcd(engines->EtcdEndpoints());
  auto start = etcd->Put("/t/unwatched", "x");
  ASSERT_TRUE(start.ok());

  EventLog live;
  auto watcher = etcd->Watch("/t/w/", *start + 1,
                             [&](const std::vector<WatchEvent>& events) { live.Add(events); });
  std::vector<int64_t> revisions;
  revisions.push_back(*etcd->Put("/t/w/a", "1"));
  revisions.push_back(*etcd->Put("/t/w/b", "2"));
  ASSERT_TRUE(etcd->Put("/t/elsewhere", "not watched").ok());
  ASSERT_EQ(*etcd->Delete("/t/w/a"), 1);
  revisions.push_back(etcd->Get("/t/w/", true)->revision);
  revisions.push_back(*etcd->Put("/t/w/a", "3"));
  ASSERT_TRUE(WaitFor([&] { return live.size() >= 4; }));
  const std::string expected = "put /t/w/a=1; put /t/w/b=2; delete /t/w/a; put /t/w/a=3; ";
  auto events = live.Snapshot();
  EXPECT_EQ(Describe(events), expected);
  for (size_t i = 0; i < events.size(); ++i) {
    EXPECT_EQ(events[i].kv.mod_revision, revisions[i]) << i;
  }
  watcher->Stop();
  EXPECT_EQ(watcher->next_revision(), revisions.back() + 1);

  // A new watch from the second event's revision replays history from there.
  EventLog resumed;
  auto from_history =
      etcd->Watch("/t/w/", revisions[1], [&](const std::vector<WatchEvent>& e) { resumed.Add(e); });
  ASSERT_TRUE(WaitFor([&] { return resumed.size() >= 3; }));
  std::this_thread::sleep_for(200ms);  // nothing more may come
  EXPECT_EQ(Describe(resumed.Snapshot()), "put /t/w/b=2; delete /t/w/a; put /t/w/a=3; ");
}

TEST(EtcdClientTest, KilledMemberFailsOverAndWatchContinues) {
  auto engines = StartEngines(false, true);
  ASSERT_TRUE(engines);
  auto etcd = Etcd(engines->EtcdEndpoints());  // member 0 first
  ASSERT_TRUE(etcd->Put("/t/f/before", "1").ok());
  EventLog log;
  auto watcher = etcd->Watch("/t/f/", etcd->Get("/t/f/", true)->revision + 1,
                             [&](const std::vector<WatchEvent>& e) { log.Add(e); });
  ASSERT_TRUE(etcd->Put("/t/f/k0", "0").ok());
  ASSERT_TRUE(WaitFor([&] { return log.size() >= 1; }));

  for (int killed = 0; killed < 3; ++killed) {
    engines->KillEtcd(killed);
    const double killed_ms = bench::NowMs();
    auto put = etcd->Put(Id("/t/f/k", killed + 1), std::to_string(killed + 1));
    ASSERT_TRUE(put.ok()) << "member " << killed << " killed: " << put.status().ToString();
    bench::Print("etcd_put_after_member_kill_ms", bench::NowMs() - killed_ms, "ms");
    auto got = etcd->Get("/t/f/", true);
    ASSERT_TRUE(got.ok()) << got.status().ToString();
    EXPECT_EQ(got->kvs.size(), static_cast<size_t>(killed + 3));
    ASSERT_TRUE(engines->RestartEtcd(killed).ok());
  }
  ASSERT_TRUE(WaitFor([&] { return log.size() >= 4; }));
  EXPECT_EQ(Describe(log.Snapshot()),
            "put /t/f/k0=0; put /t/f/k1=1; put /t/f/k2=2; put /t/f/k3=3; ");

  // A client of a dead member alone: UNAVAILABLE (IO_ERROR) naming the endpoint.
  engines->KillEtcd(2);
  EtcdOptions only_dead;
  only_dead.endpoints = {engines->EtcdEndpoint(2)};
  only_dead.call_timeout = 1s;
  auto dead = EtcdClient::Create(only_dead);
  ASSERT_TRUE(dead.ok());
  auto refused = (*dead)->Get("/t/f/k0");
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kIoError);
  EXPECT_NE(refused.status().message().find(engines->EtcdEndpoint(2)), std::string::npos)
      << refused.status().ToString();

  // The member returns: the same client uses it again (its channel leaves reconnect backoff).
  const double restart_ms = bench::NowMs();
  ASSERT_TRUE(engines->RestartEtcd(2).ok());
  const double ready_ms = bench::NowMs();
  ASSERT_TRUE(WaitFor([&] { return (*dead)->Get("/t/f/k0").ok(); }, 30s));
  bench::Print("etcd_member_restart_ms", ready_ms - restart_ms, "ms");
  bench::Print("etcd_restarted_member_reused_after_ready_ms", bench::NowMs() - ready_ms, "ms");
}

// ---- JetStream ---------------------------------------------------------------------------------

StreamConfig TestStream(const std::string& name) {
  StreamConfig config;
  config.name = name;
  config.subjects = {"placedb.test." + name};
  config.replicas = 3;
  config.duplicate_window = std::chrono::minutes(2);
  config.max_message_bytes = 1 << 20;
  return config;
}

TEST(JetStreamTest, DuplicatesReturnTheirOriginalSequenceAndConsumerStartsAtASequence) {
  auto engines = StartEngines(/*nats=*/true, /*etcd=*/false);
  ASSERT_TRUE(engines);
  auto js = Js(engines->NatsUrls());
  ASSERT_TRUE(js);
  const StreamConfig config = TestStream("DEDUP");
  const Status made = js->EnsureStream(config);
  ASSERT_TRUE(made.ok()) << made.ToString();
  ASSERT_TRUE(js->EnsureStream(config).ok()) << "same settings: nothing to do";
  StreamConfig other = config;
  other.replicas = 1;
  Status mismatch = js->EnsureStream(other);
  EXPECT_EQ(mismatch.code(), StatusCode::kFailedPrecondition) << mismatch.ToString();
  EXPECT_NE(mismatch.message().find("replicas 3, wanted 1"), std::string::npos)
      << mismatch.ToString();

  const std::string& subject = config.subjects[0];
  for (int i = 1; i <= 1000; ++i) {
    auto ack = js->Publish(subject, Id("payload ", i), Id("m", i), 5s);
    ASSERT_TRUE(ack.ok()) << ack.status().ToString();
    ASSERT_EQ(ack->sequence, static_cast<uint64_t>(i));
    ASSERT_FALSE(ack->duplicate);
  }
  for (int i = 1; i <= 1000; i += 10) {  // 100 re-publishes
    auto ack = js->Publish(subject, "payload again", Id("m", i), 5s);
    ASSERT_TRUE(ack.ok()) << ack.status().ToString();
    EXPECT_TRUE(ack->duplicate) << i;
    EXPECT_EQ(ack->sequence, static_cast<uint64_t>(i)) << "a duplicate's PubAck names the original";
  }
  auto info = js->GetStreamInfo(config.name);
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->messages, 1000u);
  EXPECT_EQ(info->last_sequence, 1000u);
  EXPECT_EQ(info->replicas, 3);
  EXPECT_EQ(info->cluster, "placedb");
  EXPECT_GE(engines->NodeOfServerName(info->leader), 0);
  EXPECT_EQ(info->others.size(), 2u);

  Mutex mutex;
  std::vector<std::pair<uint64_t, std::string>> got;
  auto consumer = js->Consume(config.name, subject, 500, [&](uint64_t seq, std::string_view data) {
    MutexLock lock(mutex);
    got.emplace_back(seq, std::string(data));
  });
  ASSERT_TRUE(consumer.ok()) << consumer.status().ToString();
  ASSERT_TRUE(WaitFor([&] {
    MutexLock lock(mutex);
    return got.size() >= 501;
  }));
  (*consumer)->Stop();
  MutexLock lock(mutex);
  ASSERT_EQ(got.size(), 501u);
  for (size_t i = 0; i < got.size(); ++i) {
    ASSERT_EQ(got[i].first, 500 + i);
    ASSERT_EQ(got[i].second, Id("payload ", 500 + i));
  }
  EXPECT_EQ((*consumer)->next_sequence(), 1001u);
  EXPECT_TRUE(js->DeleteStream(config.name).ok());
  EXPECT_EQ(js->GetStreamInfo(config.name).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(js->DeleteStream(config.name).code(), StatusCode::kNotFound);
}

// Every message of `stream` from sequence 1, by an ordered consumer.
std::vector<std::pair<uint64_t, std::string>> ReadAll(JetStream& js, const StreamConfig& config,
                                                      uint64_t last_sequence) {
  Mutex mutex;
  std::vector<std::pair<uint64_t, std::string>> got;
  // Creating a consumer needs the JetStream meta leader, which may still be re-elected after
  // nodes came back: retried (bounded).
  Result<std::unique_ptr<OrderedConsumer>> consumer = Status::Internal("not tried");
  WaitFor(
      [&] {
        consumer = js.Consume(config.name, config.subjects[0], 1,
                              [&](uint64_t seq, std::string_view data) {
                                MutexLock lock(mutex);
                                got.emplace_back(seq, std::string(data));
                              });
        if (!consumer.ok()) {
          // A failed attempt may have delivered messages before it failed (jetstream.h).
          MutexLock lock(mutex);
          got.clear();
        }
        return consumer.ok();
      },
      60s);
  EXPECT_TRUE(consumer.ok()) << consumer.status().ToString();
  if (!consumer.ok()) return {};
  WaitFor([&] {
    MutexLock lock(mutex);
    return !got.empty() && got.back().first >= last_sequence;
  });
  (*consumer)->Stop();
  MutexLock lock(mutex);
  return got;
}

// Issue 35: a map restored from a snapshot continues its place ids after the snapshot's records:
// on Debian's nats-server 2.9, a purge up to sequence N of an empty stream makes N its next
// sequence (and a subject-filtered purge removes that subject's messages only: a snapshot's
// archive in the snapshots stream).
TEST(JetStreamTest, PurgeToASequenceSetsAnEmptyStreamsNextSequence) {
  auto engines = StartEngines(/*nats=*/true, /*etcd=*/false);
  ASSERT_TRUE(engines);
  auto js = Js(engines->NatsUrls());
  ASSERT_TRUE(js);
  const StreamConfig config = TestStream("PURGED");
  ASSERT_TRUE(js->EnsureStream(config).ok());
  const std::string& subject = config.subjects[0];
  const Status purged = js->PurgeStream(config.name, "", 1001);
  ASSERT_TRUE(purged.ok()) << purged.ToString();
  // On a replicated stream 2.9 refuses the first publish after the purge (JetStream error
  // 10077, nothing stored): the wrapper says IO_ERROR, and the retry with the same id stores it.
  auto ack = js->Publish(subject, "first after the snapshot", "m-1001", 5s);
  if (!ack.ok()) {
    EXPECT_EQ(ack.status().code(), StatusCode::kIoError) << ack.status().ToString();
    ack = js->Publish(subject, "first after the snapshot", "m-1001", 5s);
  }
  ASSERT_TRUE(ack.ok()) << ack.status().ToString();
  EXPECT_EQ(ack->sequence, 1001u);
  auto info = js->GetStreamInfo(config.name);
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->first_sequence, 1001u);
  EXPECT_EQ(info->messages, 1u);
  EXPECT_EQ(info->last_sequence, 1001u);
  EXPECT_EQ(js->PurgeStream("NO_SUCH_STREAM", "", 0).code(), StatusCode::kNotFound);

  // Two subjects; one purged.
  StreamConfig two = TestStream("TWO");
  two.subjects = {"two.a", "two.b"};
  ASSERT_TRUE(js->EnsureStream(two).ok());
  for (int i = 0; i < 6; ++i) {
    ASSERT_TRUE(js->Publish(i % 2 ? "two.b" : "two.a", Id("m", i), "", 5s).ok());
  }
  ASSERT_TRUE(js->PurgeStream(two.name, "two.a", 0).ok());
  info = js->GetStreamInfo(two.name);
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->messages, 3u);
  for (const uint64_t sequence : {2u, 4u, 6u}) {
    auto message = js->GetMessage(two.name, sequence);
    ASSERT_TRUE(message.ok()) << sequence;
  }
  EXPECT_EQ(js->GetMessage(two.name, 1).status().code(), StatusCode::kNotFound);
}

TEST(JetStreamTest, LeaderKilledWhilePublishingLosesAndDuplicatesNothing) {
  auto engines = StartEngines(true, false);
  ASSERT_TRUE(engines);
  auto js = Js(engines->NatsUrls());
  ASSERT_TRUE(js);
  const StreamConfig config = TestStream("FAILOVER");
  const Status made = js->EnsureStream(config);
  ASSERT_TRUE(made.ok()) << made.ToString();
  auto leader = engines->StreamLeader(config.name);
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();

  // A consumer running through the kill (as a shard's applier does): on its own connection.
  auto consumer_js = Js(engines->NatsUrls());
  ASSERT_TRUE(consumer_js);
  Mutex live_mutex;
  std::vector<std::pair<uint64_t, std::string>> live;
  auto live_consumer = consumer_js->Consume(config.name, config.subjects[0], 1,
                                            [&](uint64_t seq, std::string_view data) {
                                              MutexLock lock(live_mutex);
                                              live.emplace_back(seq, std::string(data));
                                            });
  ASSERT_TRUE(live_consumer.ok()) << live_consumer.status().ToString();

  // Publishes 600 messages; each is retried with the same id until acknowledged.
  constexpr int kMessages = 600;
  std::map<std::string, uint64_t> acked;  // id -> sequence; publisher thread only until joined
  std::atomic<int> acked_count{0};
  std::atomic<double> last_ack_ms{0};
  double longest_gap_ms = 0;
  int failed_attempts = 0;
  std::atomic<bool> stop_publishing{false};
  std::thread publisher([&] {
    for (int i = 0; i < kMessages && !stop_publishing; ++i) {
      const std::string id = Id("f", i);
      while (!stop_publishing) {
        auto ack = js->Publish(config.subjects[0], "data " + id, id, 2s);
        if (ack.ok()) {
          const double now = bench::NowMs();
          if (last_ack_ms.load() > 0)
            longest_gap_ms = std::max(longest_gap_ms, now - last_ack_ms.load());
          last_ack_ms.store(now);
          acked[id] = ack->sequence;
          acked_count.fetch_add(1);
          break;
        }
        ++failed_attempts;
        ASSERT_EQ(ack.status().code(), StatusCode::kIoError) << ack.status().ToString();
        std::this_thread::sleep_for(50ms);
      }
    }
  });
  // An assertion that returns early (or a publisher stuck retrying) stops it and joins.
  ::placedb::testing::JoinOnExit join_publisher([&] { stop_publishing = true; });
  join_publisher.Add(publisher);
  ASSERT_TRUE(WaitFor([&] { return acked_count.load() >= 200; }, 60s));
  engines->KillNats(*leader);
  const double killed_ms = bench::NowMs();
  const int acked_at_kill = acked_count.load();
  ASSERT_TRUE(WaitFor([&] { return acked_count.load() > acked_at_kill + 5; }, 60s))
      << "publishing did not resume after the leader was killed";
  const double resumed_ms = bench::NowMs();
  publisher.join();
  bench::Print("jetstream_leader_kill_stall_ms", longest_gap_ms, "ms");
  bench::Print("jetstream_leader_kill_to_resumed_ms", resumed_ms - killed_ms, "ms");
  std::printf("failed publish attempts during the re-election: %d\n", failed_attempts);
  auto new_leader = engines->StreamLeader(config.name);
  ASSERT_TRUE(new_leader.ok());
  EXPECT_NE(*new_leader, *leader);

  auto info = js->GetStreamInfo(config.name);
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  auto all = ReadAll(*js, config, info->last_sequence);
  ASSERT_EQ(all.size(), info->messages);
  std::set<std::string> seen;
  for (const auto& [sequence, data] : all) {
    const std::string id = data.substr(5);
    EXPECT_TRUE(seen.insert(id).second) << id << " stored twice";
    auto it = acked.find(id);
    ASSERT_NE(it, acked.end()) << "stored but never published: " << id;
    EXPECT_EQ(it->second, sequence) << id;
  }
  EXPECT_EQ(seen.size(), static_cast<size_t>(kMessages)) << "every acknowledged message, once";

  // The live consumer got the same messages in the same order, none twice, across the kill.
  EXPECT_TRUE(WaitFor([&] {
    MutexLock lock(live_mutex);
    return !live.empty() && live.back().first >= info->last_sequence;
  }));
  (*live_consumer)->Stop();
  // libnats' own repetitions, which the consumer does not pass on (jetstream.h).
  std::printf("live consumer: %llu repeated deliveries dropped\n",
              static_cast<unsigned long long>((*live_consumer)->repeats_dropped()));
  {
    MutexLock lock(live_mutex);
    std::string twice;
    for (size_t i = 1; i < live.size(); ++i) {
      if (live[i].first <= live[i - 1].first) twice += " " + std::to_string(live[i].first);
    }
    EXPECT_TRUE(live == all) << "live consumer: " << live.size() << " messages, stream "
                             << all.size() << "; out of order or repeated:" << twice;
  }

  // The killed node comes back and catches up.
  ASSERT_TRUE(engines->RestartNats(*leader).ok());
  EXPECT_TRUE(WaitFor([&] {
    auto caught_up = js->GetStreamInfo(config.name);
    if (!caught_up.ok() || caught_up->others.size() != 2) return false;
    for (const auto& peer : caught_up->others) {
      if (!peer.current || peer.offline || peer.lag > 0) return false;
    }
    return true;
  }));
}

// Publishes `data` with `id` until acknowledged (bounded), as a worker retries a record.
Result<PubAck> PublishUntilAcked(JetStream& js, const std::string& subject, const std::string& data,
                                 const std::string& id) {
  Result<PubAck> ack = Status::Internal("not tried");
  WaitFor(
      [&] {
        ack = js.Publish(subject, data, id, 2s);
        return ack.ok();
      },
      60s);
  return ack;
}

// With 2 of 3 down nothing is acknowledged (IO_ERROR). Two cases: (a) the stream leader died too:
// no server takes the message, nothing is stored; (b) the leader survived: it has proposed the
// message to its Raft group and, once a peer returns, stores it although the publish failed. In
// both, a retry with the same message id (as a worker retries a record) ends with exactly one copy
// and the PubAck names its sequence.
TEST(JetStreamTest, TwoOfThreeDownRefusesWithUnavailableAndRetriesStoreExactlyOnce) {
  auto engines = StartEngines(true, false);
  ASSERT_TRUE(engines);
  auto js = Js(engines->NatsUrls());
  ASSERT_TRUE(js);
  const StreamConfig config = TestStream("QUORUM");
  const std::string& subject = config.subjects[0];
  const Status made = js->EnsureStream(config);
  ASSERT_TRUE(made.ok()) << made.ToString();
  for (int i = 1; i <= 10; ++i) ASSERT_TRUE(js->Publish(subject, "before", Id("q", i), 5s).ok());

  // (a) The leader and one follower down; the client is on the survivor.
  auto leader = engines->StreamLeader(config.name);
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  const int follower = (*leader + 1) % 3;
  const int survivor = (*leader + 2) % 3;
  auto on_survivor = Js({engines->NatsUrl(survivor)});
  ASSERT_TRUE(on_survivor);
  engines->KillNats(*leader);
  engines->KillNats(follower);
  auto refused = on_survivor->Publish(subject, "refused a", "q-a", 2s);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kIoError) << refused.status().ToString();
  std::printf("leader down too: %s\n", refused.status().ToString().c_str());
  const double back_ms = bench::NowMs();  // from the restart: the node's start is part of it
  ASSERT_TRUE(engines->RestartNats(follower).ok());
  auto after = PublishUntilAcked(*on_survivor, subject, "after a", "q-after-a");
  ASSERT_TRUE(after.ok()) << after.status().ToString();
  bench::Print("jetstream_node_restart_to_publish_ms", bench::NowMs() - back_ms, "ms");
  EXPECT_EQ(after->sequence, 11u) << "nothing stored without a leader";
  ASSERT_TRUE(engines->RestartNats(*leader).ok());

  // (b) Both followers of the current leader down; the client is on the leader.
  leader = engines->StreamLeader(config.name);
  ASSERT_TRUE(leader.ok()) << leader.status().ToString();
  auto on_leader = Js({engines->NatsUrl(*leader)});
  ASSERT_TRUE(on_leader);
  engines->KillNats((*leader + 1) % 3);
  engines->KillNats((*leader + 2) % 3);
  refused = on_leader->Publish(subject, "refused b", "q-b", 2s);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kIoError) << refused.status().ToString();
  std::printf("leader alone: %s\n", refused.status().ToString().c_str());
  auto info = on_leader->GetStreamInfo(config.name);
  if (info.ok()) {
    EXPECT_EQ(info->last_sequence, 11u) << "nothing stored while refused";
  }
  ASSERT_TRUE(engines->RestartNats((*leader + 1) % 3).ok());
  auto retried = PublishUntilAcked(*on_leader, subject, "refused b", "q-b");
  ASSERT_TRUE(retried.ok()) << retried.status().ToString();
  EXPECT_EQ(retried->sequence, 12u);
  std::printf("leader alone, retry after a peer returned: sequence %llu, %s\n",
              static_cast<unsigned long long>(retried->sequence),
              retried->duplicate ? "duplicate (the refused publish was stored late)"
                                 : "new (the refused publish was not stored)");

  info = on_leader->GetStreamInfo(config.name);
  ASSERT_TRUE(info.ok()) << info.status().ToString();
  EXPECT_EQ(info->messages, 12u);
  auto all = ReadAll(*on_leader, config, 12);
  ASSERT_EQ(all.size(), 12u);
  EXPECT_EQ(all[10].second, "after a");
  EXPECT_EQ(all[11].second, "refused b");
}

}  // namespace
}  // namespace placedb::cluster
