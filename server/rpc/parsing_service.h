// placedb.v1.PlaceDb as gRPC sees it: every method registered over raw bytes (grpc::ByteBuffer)
// and parsed here with protobuf, so that a request that is not a valid message is answered with
// INVALID_ARGUMENT and a message that names its type and the problem:
//
//   request is not a valid placedb.v1.CreateMapRequest: field name (1) is not valid UTF-8
//   message 3 of the Ingest stream (observation 2) is not a valid placedb.v1.IngestRequest:
//     the data is truncated (field observation (2) claims 20480 bytes, 1200 remain)
//
// gRPC's generated synchronous handlers answer such a request with INTERNAL and an empty message
// before any of our code runs, and an Ingest message that fails to parse looks to the handler
// like the client's half-close (the stream would end OK). Parsed requests go to PlaceDbService's
// handlers unchanged; responses are serialised as gRPC's own handlers do. Reflection and the
// health service are unaffected (the service name comes from the method paths).
//
// Every call is authenticated and authorized here first (server/auth/call_auth.h), before its
// request is parsed: UNAUTHENTICATED, then INVALID_ARGUMENT for a bad map name, then
// PERMISSION_DENIED; the rule per method is in the constructor. ListMaps answers only the maps
// the caller may read; GetServerInfo leaves out the server's details (vocabulary paths and
// memory, detector, worker threads) for callers that are not admin. An Ingest stream's header
// needs write on its map, and every later message is refused (ending the stream) once a reload
// of the tokens file revoked the caller (UNAUTHENTICATED) or its right (PERMISSION_DENIED).
#pragma once

#include <grpcpp/grpcpp.h>
#include <grpcpp/impl/service_type.h>

#include <deque>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "proto/placedb.grpc.pb.h"
#include "server/auth/call_auth.h"
#include "server/rpc/ingest_stream_io.h"

namespace google::protobuf {
class Message;
}

namespace placedb::server {

namespace v1 = ::placedb::v1;
class PlaceDbService;

// Parses `bytes` into `message`. Returns "" on success, else why they are not a valid message of
// its type ("field name (1) is not valid UTF-8", "the data is truncated (...)"), with the path of
// the offending field; `message` is then unspecified.
std::string ParseMessage(const grpc::ByteBuffer& bytes, google::protobuf::Message* message);
// The same diagnosis for flat bytes that protobuf refused to parse (exposed for tests/fuzzing).
std::string DiagnoseMessage(const std::string& bytes, const google::protobuf::Message& prototype);

class ParsingService final : public grpc::Service {
 public:
  // `service` answers every parsed request; `authorizer` (null: no checks) decides who may call
  // what. Both must outlive this.
  explicit ParsingService(PlaceDbService* service,
                          const auth::CallAuthorizer* authorizer = nullptr);

  // Methods of placedb.v1.PlaceDb (from the proto's descriptor) with no registration here: an RPC
  // added to placedb.proto needs one line in parsing_service.cc. Server::Start refuses to start
  // while this is not empty.
  std::vector<std::string> Unregistered() const;

  // One unary call from another transport (the console's JSON gateway, server/console): the same
  // path as a gRPC call of `method` (authenticate `credentials`, parse `request` as the method's
  // request message, check its map name, authorize, the handler, restrict the answer to what the
  // caller may see) with the same errors; on OK *response holds the serialised answer. There is
  // no deadline and no cancellation (the HTTP request's timeouts bound its reads and writes).
  // UNIMPLEMENTED for a method that is not a registered unary method. Thread-safe.
  grpc::Status CallUnary(const std::string& method, const auth::Credentials& credentials,
                         const std::string& request, std::string* response);
  // CallUnary's first step alone, for a transport that must refuse a caller before it reads the
  // request (the console answers from the HTTP headers, leaving a refused body unread): OK when
  // `credentials` name a caller `method` may authenticate; else the same UNAUTHENTICATED as
  // CallUnary, logged and counted the same way. Authorization needs the request (its map) and
  // stays CallUnary's. UNIMPLEMENTED for a method that is not a registered unary method.
  grpc::Status AuthenticateCall(const std::string& method, const auth::Credentials& credentials);

 private:
  // A registered unary method: `credentials` null = the gRPC call's own (from `context`).
  using UnaryCall =
      std::function<grpc::Status(grpc::ServerContext* context, const auth::Credentials* credentials,
                                 const grpc::ByteBuffer& in, grpc::ByteBuffer* out)>;
  // `map_of` names the request's map (for `right`; "" for methods on no map, whose field 1 is
  // then not checked as a map name; null: the request names no map at all, for admin methods on
  // snapshots).
  template <typename Request, typename Response>
  void AddUnary(const char* method,
                grpc::Status (PlaceDbService::*handler)(grpc::ServerContext*, const Request*,
                                                        Response*),
                auth::Right right, std::string (*map_of)(const Request&));
  void AddIngest(const char* method);
  // A server stream: `handler` writes each response through the callback it is given (false once
  // the client is gone). Checked as AddUnary.
  template <typename Request, typename Response>
  void AddServerStream(
      const char* method,
      grpc::Status (PlaceDbService::*handler)(grpc::ServerContext*, const Request*,
                                              const std::function<bool(const Response&)>&),
      auth::Right right, std::string (*map_of)(const Request&));
  // A client stream on no map: `right` must be kAdmin or kAny (it is checked before the first
  // message is read); `handler` reads each request through the callback it is given.
  template <typename Request, typename Response>
  void AddClientStream(const char* method,
                       grpc::Status (PlaceDbService::*handler)(
                           grpc::ServerContext*,
                           const std::function<grpc::Status(Request*, bool* done)>&, Response*),
                       auth::Right right);
  // Authenticates, parses and authorizes a request (the shared first half of AddUnary and
  // AddServerStream); `caller` receives who is calling.
  // `credentials` null = the gRPC call's own (from `context`).
  template <typename Request>
  grpc::Status Admit(const char* method, grpc::ServerContext* context,
                     const auth::Credentials* credentials, const grpc::ByteBuffer& in,
                     auth::Right right, std::string (*map_of)(const Request&), Request* request,
                     auth::Caller* caller, std::string* map);
  // Sets *caller (every right when there is no authorizer); else the denial (logged, counted).
  // `credentials` null = the gRPC call's own (from `context`).
  grpc::Status Authenticate(const char* method, const grpc::ServerContext& context,
                            auth::Caller* caller,
                            const auth::Credentials* credentials = nullptr) const;
  const char* Path(const char* method);  // "/placedb.v1.PlaceDb/<method>", stable storage

  PlaceDbService* const service_;
  const auth::CallAuthorizer* const authorizer_;
  std::deque<std::string> paths_;  // RpcServiceMethod keeps a pointer to its name
  std::vector<std::string> registered_;
  std::map<std::string, UnaryCall> unary_;  // filled by the constructor, read-only after
};

}  // namespace placedb::server
