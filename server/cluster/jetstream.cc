#include "server/cluster/jetstream.h"

#include <nats/nats.h>

#include <algorithm>

namespace placedb::cluster {
namespace {

bool IsUnavailable(natsStatus status, jsErrCode code) {
  switch (code) {
    case JSClusterNotAvailErr:
    case JSClusterNotLeaderErr:
    case JSClusterNoPeersErr:
    case JSInsufficientResourcesErr:
    case JSStreamOfflineErr:
      return true;
    default:
      break;
  }
  switch (status) {
    case NATS_TIMEOUT:
    case NATS_NO_RESPONDERS:
    case NATS_NO_SERVER:
    case NATS_CONNECTION_CLOSED:
    case NATS_CONNECTION_DISCONNECTED:
    case NATS_STALE_CONNECTION:
    case NATS_NOT_YET_CONNECTED:
    case NATS_IO_ERROR:
      return true;
    default:
      return false;
  }
}

// The library's own text for the failure (its last error on this thread), else the status name.
std::string Describe(natsStatus status, jsErrCode code) {
  natsStatus last = NATS_OK;
  const char* text = nats_GetLastError(&last);
  std::string out = (text && *text) ? text : natsStatus_GetText(status);
  // libnats reports "no responders" as JSNotEnabledErr: the code would mislead.
  if (code != 0 && status != NATS_NO_RESPONDERS) {
    out += " (JetStream error " + std::to_string(static_cast<int>(code)) + ")";
  }
  return out;
}

Status ToStatus(natsStatus status, jsErrCode code, const std::string& what) {
  if (status == NATS_OK) return Status::Ok();
  const std::string message = what + ": " + Describe(status, code);
  if (code == JSStreamNotFoundErr || status == NATS_NOT_FOUND) return Status::NotFound(message);
  if (IsUnavailable(status, code)) {
    if (status == NATS_TIMEOUT || status == NATS_NO_RESPONDERS) {
      return Status::IoError(what + ": no JetStream quorum answered (" + Describe(status, code) +
                             ")");
    }
    return Status::IoError(message);
  }
  if (status == NATS_INVALID_ARG) return Status::InvalidArgument(message);
  return Status::Internal(message);
}

jsOptions RequestOptions(std::chrono::milliseconds timeout) {
  jsOptions options;
  jsOptions_Init(&options);
  options.Wait = timeout.count();
  return options;
}

}  // namespace

// ---- JetStream ---------------------------------------------------------------------------------

Result<std::unique_ptr<JetStream>> JetStream::Connect(JetStreamOptions options) {
  if (options.servers.empty()) return Status::InvalidArgument("JetStream: no servers given");
  natsOptions* nats_options = nullptr;
  if (natsOptions_Create(&nats_options) != NATS_OK) {
    return Status::Internal("JetStream: natsOptions_Create failed");
  }
  std::vector<const char*> servers;
  for (const auto& server : options.servers) servers.push_back(server.c_str());
  natsStatus status =
      natsOptions_SetServers(nats_options, servers.data(), static_cast<int>(servers.size()));
  if (status == NATS_OK) status = natsOptions_SetName(nats_options, options.client_name.c_str());
  if (status == NATS_OK)
    status = natsOptions_SetTimeout(nats_options, options.connect_timeout.count());
  // Reconnect forever, quickly: a killed node's clients move to another within ~100 ms.
  if (status == NATS_OK) status = natsOptions_SetAllowReconnect(nats_options, true);
  if (status == NATS_OK) status = natsOptions_SetMaxReconnect(nats_options, -1);
  if (status == NATS_OK) status = natsOptions_SetReconnectWait(nats_options, 100);
  // A server whose host vanished sends no reset: 2 unanswered pings 1 s apart mark it dead, and
  // the connection moves on (libnats' default, 2 minutes, would stall every publish meanwhile).
  if (status == NATS_OK) status = natsOptions_SetPingInterval(nats_options, 1000);
  if (status == NATS_OK) status = natsOptions_SetMaxPingsOut(nats_options, 2);
  // Publishes made while reconnecting fail at once (IO_ERROR) instead of being buffered and
  // acknowledged never: the caller retries with the same message id.
  if (status == NATS_OK) status = natsOptions_SetReconnectBufSize(nats_options, 0);
  if (status == NATS_OK && options.tls.enabled()) {
    // Secure: a server that does not offer TLS is refused, never used in plain text.
    status = natsOptions_SetSecure(nats_options, true);
    if (status == NATS_OK)
      status = natsOptions_SetCATrustedCertificates(nats_options, options.tls.ca.c_str());
    if (status == NATS_OK && !options.tls.cert_chain.empty()) {
      status = natsOptions_SetCertificatesChain(nats_options, options.tls.cert_chain.c_str(),
                                                options.tls.private_key.c_str());
    }
    if (status != NATS_OK) {
      natsOptions_Destroy(nats_options);
      return Status::InvalidArgument("JetStream: cannot use the TLS certificates: " +
                                     Describe(status, static_cast<jsErrCode>(0)));
    }
  }
  natsConnection* connection = nullptr;
  if (status == NATS_OK) status = natsConnection_Connect(&connection, nats_options);
  natsOptions_Destroy(nats_options);
  if (status != NATS_OK) {
    std::string list;
    for (const auto& server : options.servers) list += (list.empty() ? "" : ", ") + server;
    return Status::IoError("JetStream: cannot connect to any of " + list + ": " +
                           Describe(status, static_cast<jsErrCode>(0)));
  }
  jsOptions js_options = RequestOptions(options.request_timeout);
  jsCtx* context = nullptr;
  status = natsConnection_JetStream(&context, connection, &js_options);
  if (status != NATS_OK) {
    natsConnection_Destroy(connection);
    return ToStatus(status, static_cast<jsErrCode>(0), "JetStream: creating the context");
  }
  return std::unique_ptr<JetStream>(new JetStream(connection, context, std::move(options)));
}

JetStream::JetStream(natsConnection* connection, jsCtx* context, JetStreamOptions options)
    : options_(std::move(options)), connection_(connection), context_(context) {}

JetStream::~JetStream() {
  jsCtx_Destroy(context_);
  natsConnection_Close(connection_);
  natsConnection_Destroy(connection_);
}

std::string JetStream::ConnectedUrl() const {
  char buffer[256] = {0};
  if (natsConnection_GetConnectedUrl(connection_, buffer, sizeof(buffer)) != NATS_OK) return {};
  return buffer;
}

Status JetStream::EnsureStream(const StreamConfig& wanted) {
  if (wanted.name.empty() || wanted.subjects.empty()) {
    return Status::InvalidArgument("JetStream stream: name and subjects are required");
  }
  auto info_or = GetStreamInfo(wanted.name);
  if (!info_or.ok() && info_or.status().code() != StatusCode::kNotFound) return info_or.status();

  jsStreamConfig config;
  jsStreamConfig_Init(&config);
  std::vector<const char*> subjects;
  for (const auto& subject : wanted.subjects) subjects.push_back(subject.c_str());
  config.Name = wanted.name.c_str();
  config.Subjects = subjects.data();
  config.SubjectsLen = static_cast<int>(subjects.size());
  config.Storage = js_FileStorage;
  config.Retention = js_LimitsPolicy;
  config.Replicas = wanted.replicas;
  config.Duplicates =
      std::chrono::duration_cast<std::chrono::nanoseconds>(wanted.duplicate_window).count();
  config.MaxMsgSize = wanted.max_message_bytes;

  jsOptions options = RequestOptions(options_.request_timeout);
  jsStreamInfo* info = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  natsStatus status = NATS_OK;
  if (!info_or.ok()) {
    status = js_AddStream(&info, context_, &config, &options, &code);
    if (status == NATS_OK) {
      jsStreamInfo_Destroy(info);
      return Status::Ok();
    }
    if (code != JSStreamNameExistErr) {
      return ToStatus(status, code, "JetStream: creating stream " + wanted.name);
    }
    // Created by someone else meanwhile: compare with theirs below.
  }
  status = js_GetStreamInfo(&info, context_, wanted.name.c_str(), &options, &code);
  if (status != NATS_OK) return ToStatus(status, code, "JetStream: stream info " + wanted.name);
  const jsStreamConfig& have = *info->Config;
  std::string difference;
  std::vector<std::string> have_subjects(have.Subjects, have.Subjects + have.SubjectsLen);
  std::vector<std::string> want_subjects = wanted.subjects;
  std::sort(have_subjects.begin(), have_subjects.end());
  std::sort(want_subjects.begin(), want_subjects.end());
  auto join = [](const std::vector<std::string>& list) {
    std::string out;
    for (const auto& s : list) out += (out.empty() ? "" : ",") + s;
    return out;
  };
  if (have_subjects != want_subjects) {
    difference = "subjects " + join(have_subjects) + ", wanted " + join(want_subjects);
  } else if (have.Replicas != wanted.replicas) {
    difference =
        "replicas " + std::to_string(have.Replicas) + ", wanted " + std::to_string(wanted.replicas);
  } else if (have.Storage != js_FileStorage) {
    difference = "memory storage, wanted file storage";
  } else if (have.Duplicates != config.Duplicates) {
    difference = "duplicate window " + std::to_string(have.Duplicates / 1000000) + " ms, wanted " +
                 std::to_string(wanted.duplicate_window.count()) + " ms";
  } else if (have.MaxMsgSize != wanted.max_message_bytes) {
    difference = "max message size " + std::to_string(have.MaxMsgSize) + " bytes, wanted " +
                 std::to_string(wanted.max_message_bytes);
  }
  jsStreamInfo_Destroy(info);
  if (!difference.empty()) {
    return Status::FailedPrecondition("JetStream stream " + wanted.name + " exists with " +
                                      difference);
  }
  return Status::Ok();
}

Result<StreamInfo> JetStream::GetStreamInfo(const std::string& stream) {
  jsOptions options = RequestOptions(options_.request_timeout);
  jsStreamInfo* info = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus status = js_GetStreamInfo(&info, context_, stream.c_str(), &options, &code);
  if (status != NATS_OK) return ToStatus(status, code, "JetStream: stream info " + stream);
  StreamInfo out;
  out.messages = info->State.Msgs;
  out.first_sequence = info->State.FirstSeq;
  out.last_sequence = info->State.LastSeq;
  out.replicas = info->Config ? static_cast<int>(info->Config->Replicas) : 0;
  if (info->Cluster) {
    if (info->Cluster->Name) out.cluster = info->Cluster->Name;
    if (info->Cluster->Leader) out.leader = info->Cluster->Leader;
    for (int i = 0; i < info->Cluster->ReplicasLen; ++i) {
      const jsPeerInfo* peer = info->Cluster->Replicas[i];
      out.others.push_back({peer->Name ? peer->Name : "", peer->Current, peer->Offline, peer->Lag});
    }
  }
  jsStreamInfo_Destroy(info);
  return out;
}

Status JetStream::DeleteStream(const std::string& stream) {
  jsOptions options = RequestOptions(options_.request_timeout);
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus status = js_DeleteStream(context_, stream.c_str(), &options, &code);
  return ToStatus(status, code, "JetStream: deleting stream " + stream);
}

Status JetStream::PurgeStream(const std::string& stream, const std::string& subject,
                              uint64_t sequence) {
  jsOptions options = RequestOptions(options_.request_timeout);
  if (!subject.empty()) options.Stream.Purge.Subject = subject.c_str();
  options.Stream.Purge.Sequence = sequence;
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus status = js_PurgeStream(context_, stream.c_str(), &options, &code);
  return ToStatus(status, code, "JetStream: purging stream " + stream);
}

Result<PubAck> JetStream::Publish(const std::string& subject, std::string_view data,
                                  const std::string& message_id,
                                  std::chrono::milliseconds timeout) {
  jsPubOptions options;
  jsPubOptions_Init(&options);
  options.MaxWait = timeout.count();
  if (!message_id.empty()) options.MsgId = message_id.c_str();
  jsPubAck* ack = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus status = js_Publish(&ack, context_, subject.c_str(), data.data(),
                                       static_cast<int>(data.size()), &options, &code);
  if (status == NATS_INSUFFICIENT_BUFFER &&
      natsConnection_Status(connection_) != NATS_CONN_STATUS_CONNECTED) {
    // The reconnect buffer is off (Connect): a publish while reconnecting is refused at once.
    return Status::IoError("JetStream: publishing to " + subject +
                           ": no connection to NATS (reconnecting)");
  }
  if (status == NATS_ERR && code == JSStreamStoreFailedErr) {
    // Not stored. nats-server 2.9 answers so to the first publish after a purge up to a sequence
    // of a replicated stream (its leader's expected sequence is reset by it): a retry with the
    // same message id stores it (engines_test, PurgeToASequenceSetsAnEmptyStreamsNextSequence).
    return Status::IoError("JetStream: publishing to " + subject + ": not stored (" +
                           Describe(status, code) + ")");
  }
  if (status != NATS_OK) {
    return ToStatus(status, code,
                    "JetStream: publishing to " + subject + " (timeout " +
                        std::to_string(timeout.count()) + " ms)");
  }
  PubAck out{ack->Sequence, ack->Duplicate};
  jsPubAck_Destroy(ack);
  return out;
}

Result<StoredMessage> JetStream::GetMessage(const std::string& stream, uint64_t sequence) {
  jsOptions options = RequestOptions(options_.request_timeout);
  natsMsg* message = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus status =
      js_GetMsg(&message, context_, stream.c_str(), sequence, &options, &code);
  const std::string what =
      "JetStream: reading message " + std::to_string(sequence) + " of " + stream;
  // A sequence the stream does not hold is JSNoMessageFoundErr, not NATS_NOT_FOUND.
  if (status != NATS_OK && code == JSNoMessageFoundErr) {
    return Status::NotFound(what + ": no message at that sequence");
  }
  if (status != NATS_OK) return ToStatus(status, code, what);
  StoredMessage out;
  out.data.assign(natsMsg_GetData(message), static_cast<size_t>(natsMsg_GetDataLength(message)));
  const char* id = nullptr;
  if (natsMsgHeader_Get(message, "Nats-Msg-Id", &id) == NATS_OK && id) out.message_id = id;
  natsMsg_Destroy(message);
  return out;
}

Result<std::unique_ptr<OrderedConsumer>> JetStream::Consume(const std::string& stream,
                                                            const std::string& subject,
                                                            uint64_t start_sequence,
                                                            OrderedConsumer::Callback callback) {
  if (start_sequence == 0)
    return Status::InvalidArgument("JetStream consumer: sequences start at 1");
  std::unique_ptr<OrderedConsumer> consumer(
      new OrderedConsumer(std::move(callback), start_sequence));
  jsOptions options = RequestOptions(options_.request_timeout);
  jsSubOptions sub_options;
  jsSubOptions_Init(&sub_options);
  sub_options.Stream = stream.c_str();
  sub_options.Ordered = true;
  sub_options.Config.DeliverPolicy = js_DeliverByStartSequence;
  sub_options.Config.OptStartSeq = start_sequence;
  // Idle heartbeats every second. libnats' default for ordered consumers is 5 s and it checks for
  // missed ones every 2 intervals, so a consumer lost with its server (killed, host gone) was
  // recreated only 10-20 s later: that long the replica applied nothing, and ingest with matches
  // (which searches a replica that applied the stream's last place) stalled with it
  // (tests/cluster/cluster_hosts_test.cc). With 1 s: noticed and recreated within 2-4 s.
  sub_options.Config.Heartbeat = 1'000'000'000;  // nanoseconds
  natsSubscription* subscription = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  natsStatus status =
      js_Subscribe(&subscription, context_, subject.c_str(), &OrderedConsumer::OnMessage,
                   consumer.get(), &options, &sub_options, &code);
  if (status != NATS_OK) {
    return ToStatus(status, code, "JetStream: ordered consumer of " + stream);
  }
  status =
      natsSubscription_SetOnCompleteCB(subscription, &OrderedConsumer::OnComplete, consumer.get());
  {
    MutexLock lock(consumer->mutex_);
    consumer->subscription_ = subscription;
  }
  if (status != NATS_OK) {
    consumer->Stop();
    return ToStatus(status, code, "JetStream: ordered consumer of " + stream);
  }
  return consumer;
}

// ---- OrderedConsumer ---------------------------------------------------------------------------

OrderedConsumer::OrderedConsumer(Callback callback, uint64_t start)
    : callback_(std::move(callback)), next_sequence_(start) {}

OrderedConsumer::~OrderedConsumer() {
  Stop();
}

uint64_t OrderedConsumer::next_sequence() const {
  MutexLock lock(mutex_);
  return next_sequence_;
}

uint64_t OrderedConsumer::repeats_dropped() const {
  MutexLock lock(mutex_);
  return repeats_dropped_;
}

void OrderedConsumer::OnMessage(natsConnection*, natsSubscription*, natsMsg* message,
                                void* closure) {
  auto* self = static_cast<OrderedConsumer*>(closure);
  jsMsgMetaData* meta = nullptr;
  if (natsMsg_GetMetaData(&meta, message) == NATS_OK) {
    const uint64_t sequence = meta->Sequence.Stream;
    jsMsgMetaData_Destroy(meta);
    bool repeated = false;
    {
      MutexLock lock(self->mutex_);
      // Delivered already: libnats recreated the consumer from a sequence it had passed (see the
      // file comment). Messages come in sequence order, so this is the only repetition.
      repeated = sequence < self->next_sequence_;
      if (repeated) {
        ++self->repeats_dropped_;
      } else {
        self->next_sequence_ = sequence + 1;
      }
    }
    if (!repeated) {
      self->callback_(sequence,
                      std::string_view(natsMsg_GetData(message),
                                       static_cast<size_t>(natsMsg_GetDataLength(message))));
    }
  }
  natsMsg_Destroy(message);
}

void OrderedConsumer::OnComplete(void* closure) {
  auto* self = static_cast<OrderedConsumer*>(closure);
  MutexLock lock(self->mutex_);
  self->completed_ = true;
  self->completed_cv_.NotifyAll();
}

void OrderedConsumer::Stop() {
  natsSubscription* subscription = nullptr;
  {
    MutexLock lock(mutex_);
    subscription = subscription_;
    subscription_ = nullptr;
  }
  if (!subscription) return;
  // After Unsubscribe the delivery thread finishes the callback in progress, then calls
  // OnComplete: waiting for it means no callback runs once Stop() returns.
  const bool unsubscribed = natsSubscription_Unsubscribe(subscription) == NATS_OK;
  if (unsubscribed) {
    MutexLock lock(mutex_);
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    while (!completed_ && std::chrono::steady_clock::now() < until) {
      completed_cv_.WaitUntil(mutex_, until);
    }
  }
  natsSubscription_Destroy(subscription);
}

}  // namespace placedb::cluster
