#include "client/connection.h"

#include <google/protobuf/io/coded_stream.h>
#include <grpcpp/generic/generic_stub.h>

#include <algorithm>
#include <future>
#include <tuple>
#include <vector>

#include "core/base/files.h"
#include "proto/status.h"

namespace placedb::client {

std::shared_ptr<grpc::ChannelCredentials> MakeChannelCredentials(const ConnectionOptions& options,
                                                                 std::string* error) {
  if (options.cert.empty() != options.key.empty()) {
    *error = options.cert.empty() ? "--key needs --cert" : "--cert needs --key";
    return nullptr;
  }
  if (!options.tls) {
    if (!options.cert.empty() || !options.ca_cert.empty()) {
      *error = std::string(options.cert.empty() ? "--ca-cert" : "--cert") + " needs --tls";
      return nullptr;
    }
    return grpc::InsecureChannelCredentials();
  }
  grpc::SslCredentialsOptions ssl;
  for (const auto& [flag, path, out] : {std::tuple<const char*, const std::string*, std::string*>{
                                            "--ca-cert", &options.ca_cert, &ssl.pem_root_certs},
                                        {"--cert", &options.cert, &ssl.pem_cert_chain},
                                        {"--key", &options.key, &ssl.pem_private_key}}) {
    if (path->empty()) continue;
    auto pem = ReadWholeFile(*path);
    if (!pem.ok()) {
      *error = std::string(flag) + ": " + pem.status().message();
      return nullptr;
    }
    *out = std::move(*pem);
  }
  return grpc::SslCredentials(ssl);
}

std::optional<Connection> Connection::Open(const ConnectionOptions& options, std::string* error) {
  Connection connection;
  connection.options_ = options;
  std::shared_ptr<grpc::ChannelCredentials> credentials = MakeChannelCredentials(options, error);
  if (!credentials) return std::nullopt;
  grpc::ChannelArguments arguments;
  // Frames are up to a few MiB; the server's limit (limits.max_message_bytes) is what counts.
  arguments.SetMaxSendMessageSize(-1);
  arguments.SetMaxReceiveMessageSize(-1);
  connection.channel_ = grpc::CreateCustomChannel(options.address, credentials, arguments);
  connection.stub_ = v1::PlaceDb::NewStub(connection.channel_);
  return connection;
}

std::unique_ptr<grpc::ClientContext> Connection::NewContext(bool unary) const {
  auto context = std::make_unique<grpc::ClientContext>();
  if (!options_.token.empty()) context->AddMetadata("authorization", "Bearer " + options_.token);
  if (unary && options_.timeout_s > 0) {
    context->set_deadline(std::chrono::system_clock::now() +
                          std::chrono::microseconds(int64_t(options_.timeout_s * 1e6)));
  }
  return context;
}

grpc::Status MapServingStatus(const v1::MapDescription& map) {
  switch (map.state()) {
    case v1::MAP_STATE_DAMAGED:
      return grpc::Status(grpc::StatusCode::DATA_LOSS,
                          "map '" + map.name() + "' is damaged: " + map.unavailable_reason());
    case v1::MAP_STATE_UNAVAILABLE:
      return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                          "map '" + map.name() + "' is unavailable: " + map.unavailable_reason());
    default:
      return grpc::Status::OK;
  }
}

std::string ServerTarget(const std::string& address) {
  const bool bare_port =
      !address.empty() && address.size() <= 5 &&
      std::all_of(address.begin(), address.end(), [](char c) { return c >= '0' && c <= '9'; });
  return bare_port ? "localhost:" + address : address;
}

std::string Describe(const grpc::Status& status) {
  std::string text = wire::GrpcCodeName(int(status.error_code()));
  if (!status.error_message().empty()) text += ": " + status.error_message();
  return text;
}

std::string DescribeFailure(const grpc::Status& status, const std::string& address) {
  std::string text = Describe(status);
  // gRPC's own texts for a call that found no server; a server's UNAVAILABLE (draining, no
  // quorum) says something else.
  const std::string& message = status.error_message();
  // (DEADLINE_EXCEEDED is left out: a server that answers slowly gets it too.)
  const bool never_reached = status.error_code() == grpc::StatusCode::UNAVAILABLE &&
                             (message.find("failed to connect") != std::string::npos ||
                              message.find("Failed to connect") != std::string::npos ||
                              message.find("DNS resolution failed") != std::string::npos ||
                              message.find("Connection refused") != std::string::npos);
  if (never_reached && !address.empty()) {
    text += "\n  is placedb-server running at " + address +
            "? (set the address with --address HOST:PORT or PLACEDB_ADDRESS)";
  }
  return text;
}

// The health messages are two fields; they are encoded here rather than generating
// grpc/health/v1/health.proto, which Debian's gRPC packages do not ship:
//   HealthCheckRequest  { string service = 1; }
//   HealthCheckResponse { ServingStatus status = 1; }  UNKNOWN 0, SERVING 1, NOT_SERVING 2,
//                                                      SERVICE_UNKNOWN 3
grpc::Status CheckHealth(const Connection& connection, const std::string& service,
                         std::string* serving_status) {
  std::string request;
  if (!service.empty()) {
    google::protobuf::io::StringOutputStream raw(&request);
    google::protobuf::io::CodedOutputStream out(&raw);
    out.WriteTag((1 << 3) | 2);  // field 1, length-delimited
    out.WriteVarint32(uint32_t(service.size()));
    out.WriteString(service);
  }
  grpc::Slice slice(request);
  grpc::ByteBuffer request_buffer(&slice, 1);
  grpc::ByteBuffer response_buffer;
  grpc::GenericStub stub(connection.channel());
  auto context = connection.NewContext();
  std::promise<grpc::Status> done;
  stub.UnaryCall(context.get(), "/grpc.health.v1.Health/Check", grpc::StubOptions(),
                 &request_buffer, &response_buffer,
                 [&done](grpc::Status status) { done.set_value(std::move(status)); });
  grpc::Status status = done.get_future().get();
  if (!status.ok()) return status;

  std::vector<grpc::Slice> slices;
  if (!response_buffer.Dump(&slices).ok()) {
    return grpc::Status(grpc::StatusCode::INTERNAL, "unreadable health response");
  }
  std::string bytes;
  for (const grpc::Slice& s : slices) {
    bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
  }
  uint64_t value = 0;  // absent field = UNKNOWN
  google::protobuf::io::CodedInputStream in(reinterpret_cast<const uint8_t*>(bytes.data()),
                                            int(bytes.size()));
  bool well_formed = true;
  while (uint32_t tag = in.ReadTag()) {
    uint64_t varint = 0;
    uint32_t length = 0;
    switch (tag & 7) {  // wire type
      case 0:
        well_formed = in.ReadVarint64(&varint);
        if (tag >> 3 == 1) value = varint;
        break;
      case 1:
        well_formed = in.Skip(8);
        break;
      case 2:
        well_formed = in.ReadVarint32(&length) && in.Skip(int(length));
        break;
      case 5:
        well_formed = in.Skip(4);
        break;
      default:
        well_formed = false;
    }
    if (!well_formed) break;
  }
  if (!well_formed) return grpc::Status(grpc::StatusCode::INTERNAL, "malformed health response");
  static const char* const kStatuses[] = {"UNKNOWN", "SERVING", "NOT_SERVING", "SERVICE_UNKNOWN"};
  *serving_status = value < std::size(kStatuses) ? kStatuses[value] : "UNKNOWN";
  return grpc::Status::OK;
}

}  // namespace placedb::client
