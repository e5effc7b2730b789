// JetStream: placedb's client for NATS JetStream, the data log of cluster mode (one stream per
// map; place id = stream sequence; design in /work/notes/cluster-design.md).
//
// Over libnats (Debian's libnats-dev 3.4, the NATS C client). What we rely on from nats-server
// 2.9 (Debian 12: 2.9.10):
// - A PubAck means the message is stored, at that sequence, on a quorum of the stream's replicas
//   (2 of 3 for replicas 3): Raft in the stream's group. It does NOT mean fsynced: 2.9 fsyncs the
//   file store periodically (every 2 minutes by the design note; not checked against the 2.9.10
//   source; `sync_interval: always` needs 2.10). An acknowledged message survives the loss of any
//   one node (SIGKILL: the page cache survives), but a simultaneous power loss of two may lose
//   what was acknowledged since their last fsync.
// - Duplicates: a publish carrying a message id (Nats-Msg-Id) already seen within the stream's
//   duplicate window is not stored again; its PubAck says duplicate and carries the sequence of
//   the original (tested in tests/cluster/engines_test.cc). Only within the window.
// - Sequences are dense and never reused; one stream's messages are totally ordered.
// - Without a quorum (2 of 3 replicas down) no publish is acknowledged: IO_ERROR, and publishing
//   resumes by itself when a quorum is back. Nothing acknowledged does not mean nothing stored:
//   when the stream's leader is the node left, it has already proposed the message to its Raft
//   group and stores it once a peer returns (measured: tests/cluster/engines_test.cc,
//   TwoOfThreeDown...). So a failed publish must be retried with the same message id (within the
//   duplicate window): the retry's PubAck is then a duplicate naming the late-stored sequence,
//   and the message exists exactly once. When the leader died too, nothing is stored.
// - An ordered consumer (ephemeral, in-order, no acks, flow control and heartbeats) delivers every
//   message from its start sequence in sequence order; when it falls behind or its server dies
//   the library recreates it from the last delivered sequence + 1, so nothing is skipped (tested
//   through a stream-leader kill). Nothing is repeated either, by our own check: a live consumer
//   once got 602 messages of a 600-message stream across a leader kill (engines_test, CI). The
//   likely cause, read in libnats 3.4.1's js.c (not reproduced on purpose): the recreation on
//   missed heartbeats runs on a timer thread and takes the restart sequence before applyNewSID
//   briefly releases the subscription's lock; a message of the old consumer that the read loop
//   accepts in that window is delivered again by the new consumer. OrderedConsumer drops a
//   message whose sequence it delivered already (repeats_dropped() counts them). Heartbeats
//   every second: a lost consumer is noticed within 2-4 s. Messages may reach the callback before
//   Consume returns; when Consume then fails (IO_ERROR: its request timed out, e.g. during a
//   leader election, while the server made the consumer anyway) those deliveries have happened,
//   in order from the start sequence, and none follow. A caller that retries from the same start
//   sees them again (seen in engines_test: every message once per failed attempt); the shard's
//   applier is idempotent.
//
// Errors: no quorum, no server, timeouts -> IO_ERROR (gRPC UNAVAILABLE, proto/status.h) with what
// was attempted; an existing stream with other settings -> FAILED_PRECONDITION naming the setting;
// a missing stream -> NOT_FOUND.
//
// Threading: JetStream is thread-safe (libnats connections and JetStream contexts are). An
// OrderedConsumer's callback runs on that consumer's own thread (libnats' per-subscription
// delivery thread), one message at a time; it must not Stop() or destroy its own consumer. Every
// OrderedConsumer must be stopped or destroyed before its JetStream.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "server/cluster/internal_tls.h"

// libnats' opaque types, so that users of this header need not include nats.h.
typedef struct __natsConnection natsConnection;
typedef struct __jsCtx jsCtx;
typedef struct __natsSubscription natsSubscription;
typedef struct __natsMsg natsMsg;

namespace placedb::cluster {

struct JetStreamOptions {
  std::vector<std::string> servers;  // "nats://host:port"; any member of the cluster will do
  std::string client_name = "placedb";
  std::chrono::milliseconds connect_timeout{2000};
  // JetStream API requests (stream info, add, delete).
  std::chrono::milliseconds request_timeout{5000};
  // Enabled: TLS only (the server's certificate verified against tls.ca); our certificate is
  // presented when tls.cert_chain is set. Otherwise plain text.
  InternalTls tls{};
};

// What EnsureStream creates (always file storage, limits retention).
struct StreamConfig {
  std::string name;
  std::vector<std::string> subjects;
  int replicas = 3;
  std::chrono::milliseconds duplicate_window{std::chrono::minutes(2)};
  int32_t max_message_bytes = 1 << 20;
};

struct PubAck {
  uint64_t sequence = 0;   // for a duplicate: the original message's sequence
  bool duplicate = false;  // the message id was seen within the duplicate window: not stored
};

// A message read back from a stream by its sequence (GetMessage).
struct StoredMessage {
  std::string data;
  std::string message_id;  // its Nats-Msg-Id header; empty when it was published without one
};

struct StreamPeer {
  std::string name;  // nats-server's server_name
  bool current = false;
  bool offline = false;
  uint64_t lag = 0;
};

struct StreamInfo {
  uint64_t messages = 0;
  uint64_t first_sequence = 0;
  uint64_t last_sequence = 0;
  int replicas = 0;                // configured
  std::string cluster;             // empty when not clustered
  std::string leader;              // server_name of the stream's leader; empty: none elected
  std::vector<StreamPeer> others;  // the replicas other than the leader
};

class JetStream;

// An ordered consumer (see the file comment); Stop() or the destructor unsubscribes and waits
// until the delivery thread has finished its last callback.
class OrderedConsumer {
 public:
  using Callback = std::function<void(uint64_t sequence, std::string_view data)>;
  ~OrderedConsumer();
  OrderedConsumer(const OrderedConsumer&) = delete;
  OrderedConsumer& operator=(const OrderedConsumer&) = delete;

  void Stop() EXCLUDES(mutex_);
  // The sequence the next delivered message will have (start, or last delivered + 1).
  uint64_t next_sequence() const EXCLUDES(mutex_);
  // Messages libnats handed over again after they had been delivered, not passed on (see the
  // file comment).
  uint64_t repeats_dropped() const EXCLUDES(mutex_);

 private:
  friend class JetStream;
  explicit OrderedConsumer(Callback callback, uint64_t start);
  static void OnMessage(natsConnection*, natsSubscription*, natsMsg* message, void* closure);
  static void OnComplete(void* closure);

  const Callback callback_;
  mutable Mutex mutex_;
  CondVar completed_cv_;
  natsSubscription* subscription_ GUARDED_BY(mutex_) = nullptr;
  bool completed_ GUARDED_BY(mutex_) = false;
  uint64_t next_sequence_ GUARDED_BY(mutex_);
  uint64_t repeats_dropped_ GUARDED_BY(mutex_) = 0;
};

class JetStream {
 public:
  // Connects to one of `servers` (IO_ERROR when none answers within the connect timeout). The
  // connection reconnects by itself forever (to any server of the cluster, including ones it
  // learns from the cluster); calls made while it is disconnected fail with IO_ERROR.
  static Result<std::unique_ptr<JetStream>> Connect(JetStreamOptions options);
  ~JetStream();
  JetStream(const JetStream&) = delete;
  JetStream& operator=(const JetStream&) = delete;

  // Creates the stream, or checks that the existing one has these settings: FAILED_PRECONDITION
  // naming the first difference otherwise (the stream is left as it is).
  Status EnsureStream(const StreamConfig& config);
  Result<StreamInfo> GetStreamInfo(const std::string& stream);
  // NOT_FOUND when there is no such stream.
  Status DeleteStream(const std::string& stream);
  // Removes the messages of `stream` on `subject` (empty: every subject) below `sequence` (0:
  // all of them). On an empty stream a purge up to `sequence` makes it the next message's
  // sequence (a restored map's stream continues after its snapshot's records). NOT_FOUND as
  // DeleteStream.
  Status PurgeStream(const std::string& stream, const std::string& subject, uint64_t sequence);

  // Publishes `data` with message id `message_id` (empty: none, no de-duplication) and waits up
  // to `timeout` for the PubAck. IO_ERROR when no PubAck came (no quorum, no leader, no
  // connection, reconnecting): the message may still be stored later (see the file comment), so
  // a retry must reuse the same id.
  Result<PubAck> Publish(const std::string& subject, std::string_view data,
                         const std::string& message_id, std::chrono::milliseconds timeout);

  // The message stored at `sequence` in `stream` (a request to the stream's leader, waiting up to
  // the request timeout): what a duplicate's PubAck names. NOT_FOUND when the stream has no
  // message there (or no such stream); IO_ERROR as Publish.
  Result<StoredMessage> GetMessage(const std::string& stream, uint64_t sequence);

  // Starts an ordered consumer of the messages of `stream` on `subject` (a subject of the stream,
  // wildcards allowed) from `start_sequence` (>= 1).
  Result<std::unique_ptr<OrderedConsumer>> Consume(const std::string& stream,
                                                   const std::string& subject,
                                                   uint64_t start_sequence,
                                                   OrderedConsumer::Callback callback);

  // The URL of the server this connection is on (empty while disconnected).
  std::string ConnectedUrl() const;

 private:
  JetStream(natsConnection* connection, jsCtx* context, JetStreamOptions options);

  const JetStreamOptions options_;
  natsConnection* const connection_;
  jsCtx* const context_;
};

}  // namespace placedb::cluster
