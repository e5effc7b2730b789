#include "server/cluster/etcd_client.h"

#include <grpcpp/client_context.h>
#include <grpcpp/create_channel.h>
#include <grpcpp/security/credentials.h>
#include <grpcpp/support/channel_arguments.h>

#include <algorithm>

#include "proto/etcd_rpc.grpc.pb.h"

namespace placedb::cluster {
namespace {

using Clock = std::chrono::system_clock;
namespace pb = etcdserverpb;

// The etcd error codes a caller can act on; everything else is a bug or an engine fault.
Status FromGrpc(const grpc::Status& status, const std::string& what) {
  const std::string message = what + ": " + status.error_message();
  switch (status.error_code()) {
    case grpc::StatusCode::OK:
      return Status::Ok();
    case grpc::StatusCode::NOT_FOUND:
      return Status::NotFound(message);
    case grpc::StatusCode::INVALID_ARGUMENT:
    case grpc::StatusCode::OUT_OF_RANGE:
      return Status::InvalidArgument(message);
    case grpc::StatusCode::FAILED_PRECONDITION:
      return Status::FailedPrecondition(message);
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return Status::ResourceExhausted(message);
    case grpc::StatusCode::CANCELLED:
      return Status::Cancelled(message);
    case grpc::StatusCode::UNAVAILABLE:
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return Status::IoError(message);
    default:
      return Status::Internal(message);
  }
}

// Codes after which the next member may answer: the member is gone, hung, or has no leader.
bool ShouldFailOver(grpc::StatusCode code) {
  return code == grpc::StatusCode::UNAVAILABLE || code == grpc::StatusCode::DEADLINE_EXCEEDED;
}

KeyValue FromProto(const pb::KeyValue& kv) {
  return {kv.key(), kv.value(), kv.create_revision(), kv.mod_revision(), kv.version(), kv.lease()};
}

GetResult FromProto(const pb::RangeResponse& response) {
  GetResult result;
  result.revision = response.header().revision();
  result.kvs.reserve(response.kvs_size());
  for (const auto& kv : response.kvs()) result.kvs.push_back(FromProto(kv));
  return result;
}

void SetRange(const std::string& key, bool prefix, std::string* key_out, std::string* end_out) {
  *key_out = key;
  if (prefix) *end_out = EtcdClient::PrefixEnd(key);
}

pb::Compare ToProto(const Compare& compare) {
  pb::Compare out;
  out.set_key(compare.key);
  switch (compare.op) {
    case Compare::Op::kEqual:
      out.set_result(pb::Compare::EQUAL);
      break;
    case Compare::Op::kNotEqual:
      out.set_result(pb::Compare::NOT_EQUAL);
      break;
    case Compare::Op::kGreater:
      out.set_result(pb::Compare::GREATER);
      break;
    case Compare::Op::kLess:
      out.set_result(pb::Compare::LESS);
      break;
  }
  switch (compare.target) {
    case Compare::Target::kCreateRevision:
      out.set_target(pb::Compare::CREATE);
      out.set_create_revision(compare.revision);
      break;
    case Compare::Target::kModRevision:
      out.set_target(pb::Compare::MOD);
      out.set_mod_revision(compare.revision);
      break;
    case Compare::Target::kValue:
      out.set_target(pb::Compare::VALUE);
      out.set_value(compare.value);
      break;
  }
  return out;
}

pb::RequestOp ToProto(const TxnOp& op) {
  pb::RequestOp out;
  switch (op.kind) {
    case TxnOp::Kind::kGet: {
      auto* range = out.mutable_request_range();
      SetRange(op.key, op.prefix, range->mutable_key(), range->mutable_range_end());
      break;
    }
    case TxnOp::Kind::kPut: {
      auto* put = out.mutable_request_put();
      put->set_key(op.key);
      put->set_value(op.value);
      put->set_lease(op.lease);
      break;
    }
    case TxnOp::Kind::kDelete: {
      auto* del = out.mutable_request_delete_range();
      SetRange(op.key, op.prefix, del->mutable_key(), del->mutable_range_end());
      break;
    }
  }
  return out;
}

}  // namespace

// ---- EtcdClient --------------------------------------------------------------------------------

Result<std::unique_ptr<EtcdClient>> EtcdClient::Create(EtcdOptions options) {
  if (options.endpoints.empty()) return Status::InvalidArgument("etcd: no endpoints given");
  if (options.call_timeout.count() <= 0 || options.attempt_timeout.count() <= 0) {
    return Status::InvalidArgument("etcd: call_timeout and attempt_timeout must be positive");
  }
  return std::unique_ptr<EtcdClient>(new EtcdClient(std::move(options)));
}

EtcdClient::EtcdClient(EtcdOptions options) : options_(std::move(options)) {
  channels_.resize(options_.endpoints.size());
}

EtcdClient::~EtcdClient() = default;

std::string EtcdClient::PrefixEnd(const std::string& prefix) {
  std::string end = prefix;
  while (!end.empty()) {
    auto& last = reinterpret_cast<unsigned char&>(end.back());
    if (last < 0xff) {
      ++last;
      return end;
    }
    end.pop_back();
  }
  return std::string(1, '\0');  // every key: etcd's "from key to the end"
}

std::shared_ptr<grpc::Channel> EtcdClient::ChannelTo(size_t endpoint) {
  MutexLock lock(mutex_);
  auto& channel = channels_[endpoint];
  if (!channel) {
    grpc::ChannelArguments args;
    // A restarted member is used again within a second, not after gRPC's default backoff
    // (up to 2 minutes). Not GRPC_ARG_MIN_RECONNECT_BACKOFF_MS: it is also the connect timeout,
    // and 100 ms aborts handshakes on a busy machine.
    args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 100);
    args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
    channel = grpc::CreateCustomChannel(options_.endpoints[endpoint],
                                        InternalChannelCredentials(options_.tls), args);
  }
  return channel;
}

size_t EtcdClient::preferred() {
  MutexLock lock(mutex_);
  return preferred_;
}

void EtcdClient::set_preferred(size_t endpoint) {
  MutexLock lock(mutex_);
  preferred_ = endpoint;
}

template <typename Attempt>
Status EtcdClient::WithFailover(const char* what, std::chrono::milliseconds timeout,
                                Attempt&& attempt) {
  if (timeout.count() <= 0) timeout = options_.call_timeout;
  const auto deadline = Clock::now() + timeout;
  const size_t count = options_.endpoints.size();
  const size_t first = preferred();
  std::string tried;
  for (int round = 0;; ++round) {
    for (size_t i = 0; i < count; ++i) {
      const size_t endpoint = (first + i) % count;
      const auto now = Clock::now();
      if (now >= deadline) {
        return Status::IoError(std::string("etcd ") + what + ": no member answered within " +
                               std::to_string(timeout.count()) + " ms; tried " + tried);
      }
      const auto attempt_deadline = std::min(deadline, now + options_.attempt_timeout);
      const grpc::Status status = attempt(ChannelTo(endpoint), attempt_deadline);
      if (status.ok() || !ShouldFailOver(status.error_code())) {
        if (endpoint != first) set_preferred(endpoint);
        return FromGrpc(status,
                        std::string("etcd ") + what + " on " + options_.endpoints[endpoint]);
      }
      if (round == 0) {
        if (!tried.empty()) tried += "; ";
        tried += options_.endpoints[endpoint] + " (" + status.error_message() + ")";
      }
    }
    // Every member refused (e.g. during a leader election): wait a little, then go round again.
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
}

Result<GetResult> EtcdClient::Get(const std::string& key, bool prefix) {
  pb::RangeRequest request;
  SetRange(key, prefix, request.mutable_key(), request.mutable_range_end());
  pb::RangeResponse response;
  PLACEDB_RETURN_IF_ERROR(
      WithFailover("Get", options_.call_timeout,
                   [&](const std::shared_ptr<grpc::Channel>& channel, Clock::time_point deadline) {
                     grpc::ClientContext context;
                     context.set_deadline(deadline);
                     return pb::KV::NewStub(channel)->Range(&context, request, &response);
                   }));
  return FromProto(response);
}

Result<int64_t> EtcdClient::Put(const std::string& key, const std::string& value, int64_t lease) {
  pb::PutRequest request;
  request.set_key(key);
  request.set_value(value);
  request.set_lease(lease);
  pb::PutResponse response;
  PLACEDB_RETURN_IF_ERROR(
      WithFailover("Put", options_.call_timeout,
                   [&](const std::shared_ptr<grpc::Channel>& channel, Clock::time_point deadline) {
                     grpc::ClientContext context;
                     context.set_deadline(deadline);
                     return pb::KV::NewStub(channel)->Put(&context, request, &response);
                   }));
  return response.header().revision();
}

Result<int64_t> EtcdClient::Delete(const std::string& key, bool prefix) {
  pb::DeleteRangeRequest request;
  SetRange(key, prefix, request.mutable_key(), request.mutable_range_end());
  pb::DeleteRangeResponse response;
  PLACEDB_RETURN_IF_ERROR(
      WithFailover("Delete", options_.call_timeout,
                   [&](const std::shared_ptr<grpc::Channel>& channel, Clock::time_point deadline) {
                     grpc::ClientContext context;
                     context.set_deadline(deadline);
                     return pb::KV::NewStub(channel)->DeleteRange(&context, request, &response);
                   }));
  return response.deleted();
}

Result<TxnResult> EtcdClient::Txn(const std::vector<Compare>& compares,
                                  const std::vector<TxnOp>& success,
                                  const std::vector<TxnOp>& failure) {
  pb::TxnRequest request;
  for (const auto& compare : compares) *request.add_compare() = ToProto(compare);
  for (const auto& op : success) *request.add_success() = ToProto(op);
  for (const auto& op : failure) *request.add_failure() = ToProto(op);
  pb::TxnResponse response;
  PLACEDB_RETURN_IF_ERROR(
      WithFailover("Txn", options_.call_timeout,
                   [&](const std::shared_ptr<grpc::Channel>& channel, Clock::time_point deadline) {
                     grpc::ClientContext context;
                     context.set_deadline(deadline);
                     return pb::KV::NewStub(channel)->Txn(&context, request, &response);
                   }));
  TxnResult result;
  result.succeeded = response.succeeded();
  result.revision = response.header().revision();
  for (const auto& op : response.responses()) {
    if (op.has_response_range()) result.gets.push_back(FromProto(op.response_range()));
  }
  return result;
}

Result<LeaseGrant> EtcdClient::GrantLease(int64_t ttl_seconds) {
  if (ttl_seconds <= 0) return Status::InvalidArgument("etcd GrantLease: ttl must be positive");
  pb::LeaseGrantRequest request;
  request.set_ttl(ttl_seconds);
  pb::LeaseGrantResponse response;
  PLACEDB_RETURN_IF_ERROR(
      WithFailover("GrantLease", options_.call_timeout,
                   [&](const std::shared_ptr<grpc::Channel>& channel, Clock::time_point deadline) {
                     grpc::ClientContext context;
                     context.set_deadline(deadline);
                     return pb::Lease::NewStub(channel)->LeaseGrant(&context, request, &response);
                   }));
  if (!response.error().empty()) {
    return Status::FailedPrecondition("etcd GrantLease: " + response.error());
  }
  return LeaseGrant{response.id(), response.ttl()};
}

Status EtcdClient::RevokeLease(int64_t lease_id) {
  pb::LeaseRevokeRequest request;
  request.set_id(lease_id);
  pb::LeaseRevokeResponse response;
  return WithFailover(
      "RevokeLease", options_.call_timeout,
      [&](const std::shared_ptr<grpc::Channel>& channel, Clock::time_point deadline) {
        grpc::ClientContext context;
        context.set_deadline(deadline);
        return pb::Lease::NewStub(channel)->LeaseRevoke(&context, request, &response);
      });
}

Result<int64_t> EtcdClient::KeepAliveOnce(int64_t lease_id, std::chrono::milliseconds timeout) {
  pb::LeaseKeepAliveRequest request;
  request.set_id(lease_id);
  pb::LeaseKeepAliveResponse response;
  PLACEDB_RETURN_IF_ERROR(WithFailover(
      "KeepAlive", timeout,
      [&](const std::shared_ptr<grpc::Channel>& channel, Clock::time_point deadline) {
        // One request and one reply per stream: each keepalive gets its own deadline and the
        // failover of the unary calls (a keepalive every ttl/3 costs nothing worth a long stream).
        grpc::ClientContext context;
        context.set_deadline(deadline);
        auto stub = pb::Lease::NewStub(channel);
        auto stream = stub->LeaseKeepAlive(&context);
        if (stream->Write(request) && stream->Read(&response)) {
          stream->WritesDone();
          context.TryCancel();  // the reply is in: no need to wait for the server's half-close
          stream->Finish().IgnoreError();
          return grpc::Status::OK;
        }
        stream->WritesDone();
        return stream->Finish();
      }));
  if (response.ttl() <= 0) {
    return Status::NotFound("etcd lease " + std::to_string(lease_id) +
                            " is gone (expired or revoked)");
  }
  return response.ttl();
}

std::unique_ptr<LeaseKeeper> EtcdClient::KeepAlive(LeaseGrant lease,
                                                   LeaseKeeper::LostCallback on_lost) {
  return std::make_unique<LeaseKeeper>(*this, lease, std::move(on_lost));
}

std::unique_ptr<Watcher> EtcdClient::Watch(const std::string& prefix, int64_t start_revision,
                                           Watcher::EventsCallback on_events,
                                           Watcher::EndCallback on_end) {
  return std::make_unique<Watcher>(*this, prefix, start_revision, std::move(on_events),
                                   std::move(on_end));
}

// ---- LeaseKeeper -------------------------------------------------------------------------------

LeaseKeeper::LeaseKeeper(EtcdClient& client, LeaseGrant lease, LostCallback on_lost)
    : client_(client), lease_(lease), on_lost_(std::move(on_lost)) {
  thread_ = std::thread([this] { Run(); });
}

LeaseKeeper::~LeaseKeeper() {
  Stop();
}

void LeaseKeeper::Stop() {
  {
    MutexLock lock(mutex_);
    stopping_ = true;
  }
  wake_.NotifyAll();
  if (thread_.joinable()) thread_.join();
}

void LeaseKeeper::Run() {
  using namespace std::chrono;
  const auto ttl = seconds(std::max<int64_t>(lease_.ttl_seconds, 1));
  const auto interval = std::max<milliseconds>(duration_cast<milliseconds>(ttl) / 3, 200ms);
  // Granted just before: counts as renewed now (conservative: the grant was earlier).
  auto renewed_at = steady_clock::now();
  auto wait = interval;
  for (;;) {
    {
      MutexLock lock(mutex_);
      const auto until = steady_clock::now() + wait;
      while (!stopping_ && steady_clock::now() < until) wake_.WaitUntil(mutex_, until);
      if (stopping_) return;
    }
    const auto sent_at = steady_clock::now();
    const auto left = duration_cast<milliseconds>(renewed_at + ttl - sent_at);
    Status why;
    if (left.count() > 0) {
      auto ttl_left = client_.KeepAliveOnce(lease_.id, left);
      if (ttl_left.ok()) {
        renewed_at = sent_at;  // etcd restarted the TTL at or after this instant
        wait = interval;
        continue;
      }
      why = ttl_left.status();
      if (why.code() != StatusCode::kNotFound && steady_clock::now() < renewed_at + ttl) {
        wait = std::min<milliseconds>(interval, 250ms);  // retry soon: the TTL is running out
        continue;
      }
    } else {
      why = Status::IoError("no keepalive reached etcd");
    }
    {
      MutexLock lock(mutex_);
      if (stopping_) return;
    }
    if (why.code() != StatusCode::kNotFound) {
      why = Status::IoError("etcd lease " + std::to_string(lease_.id) + " not renewed for its " +
                            std::to_string(ttl.count()) +
                            " s TTL (it may have expired): " + why.message());
    }
    lost_.store(true);
    if (on_lost_) on_lost_(why);
    return;
  }
}

// ---- Watcher -----------------------------------------------------------------------------------

Watcher::Watcher(EtcdClient& client, std::string prefix, int64_t start_revision,
                 EventsCallback on_events, EndCallback on_end)
    : client_(client),
      prefix_(std::move(prefix)),
      on_events_(std::move(on_events)),
      on_end_(std::move(on_end)),
      next_revision_(start_revision) {
  thread_ = std::thread([this] { Run(); });
}

Watcher::~Watcher() {
  Stop();
}

void Watcher::Stop() {
  {
    MutexLock lock(mutex_);
    stopping_ = true;
    if (context_) static_cast<grpc::ClientContext*>(context_)->TryCancel();
  }
  wake_.NotifyAll();
  if (thread_.joinable()) thread_.join();
}

void Watcher::Run() {
  size_t endpoint = client_.preferred();
  const size_t count = client_.options().endpoints.size();
  for (;;) {
    Status ended = RunStream(endpoint);
    {
      MutexLock lock(mutex_);
      if (stopping_) return;
    }
    if (!ended.ok()) {
      if (on_end_) on_end_(ended);
      return;
    }
    // The stream broke: the next member, after a short pause (members may all be restarting).
    endpoint = (endpoint + 1) % count;
    MutexLock lock(mutex_);
    const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(200);
    while (!stopping_ && std::chrono::steady_clock::now() < until) wake_.WaitUntil(mutex_, until);
    if (stopping_) return;
  }
}

Status Watcher::RunStream(size_t endpoint) {
  grpc::ClientContext context;
  {
    MutexLock lock(mutex_);
    if (stopping_) return Status::Ok();
    context_ = &context;
  }
  struct Unregister {
    Watcher* self;
    ~Unregister() {
      MutexLock lock(self->mutex_);
      self->context_ = nullptr;
    }
  } unregister{this};

  auto stub = pb::Watch::NewStub(client_.ChannelTo(endpoint));
  auto stream = stub->Watch(&context);
  pb::WatchRequest request;
  auto* create = request.mutable_create_request();
  create->set_key(prefix_);
  create->set_range_end(EtcdClient::PrefixEnd(prefix_));
  create->set_start_revision(next_revision_.load());
  if (!stream->Write(request)) {
    stream->Finish().IgnoreError();
    return Status::Ok();  // member unreachable: try the next
  }
  pb::WatchResponse response;
  std::vector<WatchEvent> events;
  while (stream->Read(&response)) {
    if (response.created() && next_revision_.load() <= 0) {
      next_revision_.store(response.header().revision() + 1);  // "from now" is now fixed
    }
    if (response.canceled()) {
      context.TryCancel();
      stream->Finish().IgnoreError();
      if (response.compact_revision() > 0) {
        return Status::FailedPrecondition("etcd watch on '" + prefix_ + "' from revision " +
                                          std::to_string(next_revision_.load()) +
                                          ": compacted (oldest kept " +
                                          std::to_string(response.compact_revision()) + ")");
      }
      return Status::Internal("etcd watch on '" + prefix_ +
                              "' cancelled by the server: " + response.cancel_reason());
    }
    if (response.events_size() == 0) continue;
    events.clear();
    for (const auto& event : response.events()) {
      events.push_back(
          {event.type() == pb::Event::DELETE ? WatchEvent::Type::kDelete : WatchEvent::Type::kPut,
           FromProto(event.kv())});
    }
    next_revision_.store(events.back().kv.mod_revision + 1);
    {
      MutexLock lock(mutex_);
      if (stopping_) break;
    }
    on_events_(events);
  }
  context.TryCancel();
  stream->Finish().IgnoreError();
  return Status::Ok();
}

}  // namespace placedb::cluster
