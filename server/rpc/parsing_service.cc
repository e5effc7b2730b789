#include "server/rpc/parsing_service.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/wire_format_lite.h>
#include <grpcpp/impl/rpc_service_method.h>
#include <grpcpp/support/method_handler.h>
#include <grpcpp/support/proto_buffer_reader.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <map>

#include "core/base/map_name.h"
#include "core/base/text.h"
#include "proto/status.h"
#include "server/rpc/service.h"

namespace placedb::server {

namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::internal::WireFormatLite;
using google::protobuf::io::CodedInputStream;

constexpr char kServiceName[] = "placedb.v1.PlaceDb";

// Well-formed UTF-8 as protobuf checks proto3 strings: no overlong forms, no surrogates, nothing
// above U+10FFFF.
bool ValidUtf8(const std::string& s) {
  const auto* p = reinterpret_cast<const unsigned char*>(s.data());
  const size_t n = s.size();
  size_t i = 0;
  while (i < n) {
    const unsigned char c = p[i];
    if (c < 0x80) {
      ++i;
      continue;
    }
    size_t length = 0;
    uint32_t min = 0, code = 0;
    if ((c & 0xE0) == 0xC0) {
      length = 2, min = 0x80, code = c & 0x1F;
    } else if ((c & 0xF0) == 0xE0) {
      length = 3, min = 0x800, code = c & 0x0F;
    } else if ((c & 0xF8) == 0xF0) {
      length = 4, min = 0x10000, code = c & 0x07;
    } else {
      return false;
    }
    if (n - i < length) return false;
    for (size_t k = 1; k < length; ++k) {
      if ((p[i + k] & 0xC0) != 0x80) return false;
      code = (code << 6) | (p[i + k] & 0x3F);
    }
    if (code < min || code > 0x10FFFF || (code >= 0xD800 && code <= 0xDFFF)) return false;
    i += length;
  }
  return true;
}

std::string FieldName(const std::string& path, const FieldDescriptor* field, int number,
                      int index) {
  std::string name = path;
  if (!name.empty()) name += '.';
  if (!field) return name.append("field number ").append(std::to_string(number));
  name += field->name();
  if (field->is_repeated()) name.append("[").append(std::to_string(index)).append("]");
  return name;
}

// Walks the wire format of `bytes` against `type`: the first problem protobuf's parser would have
// refused, with the path of the field it is in; "" if none is found.
std::string Diagnose(const std::string& bytes, const Descriptor* type, const std::string& path,
                     int depth) {
  if (depth > 100) return "messages nested more than 100 deep";
  CodedInputStream input(reinterpret_cast<const uint8_t*>(bytes.data()), int(bytes.size()));
  std::map<int, int> seen;  // field number -> occurrences so far (repeated fields' indexes)
  while (true) {
    const int offset = input.CurrentPosition();
    const uint32_t tag = input.ReadTag();
    if (tag == 0) {
      if (input.CurrentPosition() == int(bytes.size())) return "";
      return "the data is malformed (a bad field tag at byte " + std::to_string(offset) +
             (path.empty() ? "" : " of " + path) + ")";
    }
    const int number = int(WireFormatLite::GetTagFieldNumber(tag));
    const FieldDescriptor* field = type ? type->FindFieldByNumber(number) : nullptr;
    const std::string name = FieldName(path, field, number, seen[number]++);
    const std::string numbered = field ? name + " (" + std::to_string(number) + ")" : name;
    if (int(WireFormatLite::GetTagWireType(tag)) > 5) {
      return "the data is malformed (wire type " +
             std::to_string(int(WireFormatLite::GetTagWireType(tag))) + " in field " + numbered +
             ")";
    }
    if (WireFormatLite::GetTagWireType(tag) != WireFormatLite::WIRETYPE_LENGTH_DELIMITED) {
      if (!WireFormatLite::SkipField(&input, tag)) {
        return "the data is truncated or malformed (in field " + numbered + ")";
      }
      continue;
    }
    uint32_t length = 0;
    if (!input.ReadVarint32(&length)) {
      return "the data is truncated (in the length of field " + numbered + ")";
    }
    const int remaining = int(bytes.size()) - input.CurrentPosition();
    if (length > uint32_t(remaining)) {
      return "the data is truncated (field " + numbered + " claims " + std::to_string(length) +
             " bytes, " + std::to_string(remaining) + " remain)";
    }
    std::string value;
    input.ReadString(&value, int(length));
    if (!field) continue;
    if (field->type() == FieldDescriptor::TYPE_STRING && !ValidUtf8(value)) {
      return "field " + numbered + " is not valid UTF-8";
    }
    if (field->type() == FieldDescriptor::TYPE_MESSAGE) {
      std::string inner = Diagnose(value, field->message_type(), name, depth + 1);
      if (!inner.empty()) return inner;
    }
  }
}

// The stream messages' own errors, counted from 0 (the header).
std::string StreamPosition(uint64_t message) {
  return "message " + std::to_string(message) + " of the Ingest stream (" +
         (message == 0 ? std::string("the header") : "observation " + std::to_string(message - 1)) +
         ")";
}

// The shared map-name rule (core/base/map_name.h), checked after authentication and before
// rights, so that a bad name is INVALID_ARGUMENT for every caller.
grpc::Status CheckRequestMapName(const char* method, const std::string& field,
                                 const std::string& map) {
  if (Status valid = ValidateMapName(map); !valid.ok()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        std::string(method) + ": " + field + ": " + valid.message());
  }
  return grpc::Status::OK;
}

// What a caller that is not admin is not shown of the server: its files, memory and machine.
template <typename Response>
void RestrictResponse(const auth::Caller&, Response*) {}
void RestrictResponse(const auth::Caller& caller, v1::ListMapsResponse* response) {
  if (caller.everything) return;
  auto* maps = response->mutable_maps();
  maps->erase(std::remove_if(maps->begin(), maps->end(),
                             [&caller](const v1::MapSummary& map) {
                               return !caller.Has(auth::Right::kRead, map.name());
                             }),
              maps->end());
}
void RestrictResponse(const auth::Caller& caller, v1::ServerInfo* response) {
  if (caller.admin()) return;
  for (v1::VocabularyInfo& vocabulary : *response->mutable_vocabularies()) {
    vocabulary.clear_path();
    vocabulary.clear_memory_bytes();
  }
  response->clear_detector();
  response->mutable_limits()->clear_worker_threads();
}

// Ingest's reader-writer over raw bytes: reads parse, writes serialise. With an authorizer, the
// header needs write on its map, and each later message checks the caller again after a reload
// of the tokens file.
class ParsingIngestStream final : public IngestStreamIo {
 public:
  ParsingIngestStream(grpc::ServerReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>* raw,
                      const auth::CallAuthorizer* authorizer, const grpc::ServerContext* context,
                      auth::Caller caller)
      : raw_(raw), authorizer_(authorizer), context_(context), caller_(std::move(caller)) {}

  void SendInitialMetadata() override { raw_->SendInitialMetadata(); }
  bool NextMessageSize(uint32_t* size) override { return raw_->NextMessageSize(size); }
  bool Read(v1::IngestRequest* message) override {
    grpc::ByteBuffer bytes;
    if (!raw_->Read(&bytes)) return false;
    if (authorizer_ && read_ > 0) {
      // Frames already acknowledged stay; this one and the rest are refused.
      error_ = Recheck();
      if (!error_.ok()) return false;
    }
    if (std::string problem = ParseMessage(bytes, message); !problem.empty()) {
      error_ = grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            StreamPosition(read_) + " is not a valid " +
                                v1::IngestRequest::descriptor()->full_name() + ": " + problem);
      return false;
    }
    if (authorizer_ && read_ == 0 && message->has_header()) {
      map_ = message->header().map();
      error_ = CheckRequestMapName("Ingest", "header.map", map_);
      if (error_.ok()) {
        error_ = authorizer_->Authorize("Ingest", *context_, caller_, auth::Right::kWrite, map_);
      }
      if (!error_.ok()) return false;
    }
    ++read_;
    return true;
  }
  // The pipeline's delivery thread writes while the handler thread reads: gRPC allows one of
  // each at a time, and nothing here is shared between them.
  bool Write(const v1::IngestResponse& message, grpc::WriteOptions options) override {
    grpc::ByteBuffer bytes;
    bool own = false;
    if (!grpc::SerializationTraits<v1::IngestResponse>::Serialize(message, &bytes, &own).ok()) {
      return false;
    }
    return raw_->Write(bytes, options);
  }
  grpc::Status ReadError() const override { return error_; }

 private:
  // After a reload: is the caller still a principal, with write on the stream's map?
  grpc::Status Recheck() {
    const uint64_t generation = caller_.generation;
    grpc::Status still = authorizer_->Refresh("Ingest", *context_, map_, &caller_);
    if (still.ok() && caller_.generation != generation) {
      still = authorizer_->Authorize("Ingest", *context_, caller_, auth::Right::kWrite, map_);
    }
    return still;
  }

  grpc::ServerReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>* const raw_;
  const auth::CallAuthorizer* const authorizer_;  // null: no checks
  const grpc::ServerContext* const context_;
  auth::Caller caller_;
  std::string map_;    // the header's
  uint64_t read_ = 0;  // messages parsed so far
  grpc::Status error_;
};

}  // namespace

std::string DiagnoseMessage(const std::string& bytes, const google::protobuf::Message& prototype) {
  std::string problem = Diagnose(bytes, prototype.GetDescriptor(), "", 0);
  return problem.empty() ? "protobuf could not parse it" : problem;
}

std::string ParseMessage(const grpc::ByteBuffer& bytes, google::protobuf::Message* message) {
  grpc::ByteBuffer shared(bytes);  // the reader consumes a buffer; slices are shared, not copied
  grpc::ProtoBufferReader reader(&shared);
  if (reader.status().ok() && message->ParseFromZeroCopyStream(&reader)) return "";
  // The slow path, for refused requests only: flatten and find the first problem.
  std::vector<grpc::Slice> slices;
  if (!bytes.Dump(&slices).ok()) return "its bytes cannot be read";
  std::string flat;
  flat.reserve(bytes.Length());
  for (const grpc::Slice& slice : slices) {
    flat.append(reinterpret_cast<const char*>(slice.begin()), slice.size());
  }
  return DiagnoseMessage(flat, *message);
}

ParsingService::ParsingService(PlaceDbService* service, const auth::CallAuthorizer* authorizer)
    : service_(service), authorizer_(authorizer && authorizer->enabled() ? authorizer : nullptr) {
  using auth::Right;
  // The rights per method (docs/security.md): the map each request names, and what it needs.
  AddUnary(
      "CreateMap", &PlaceDbService::CreateMap, Right::kAdmin,
      +[](const v1::CreateMapRequest& r) { return r.name(); });
  AddUnary(
      "GetMap", &PlaceDbService::GetMap, Right::kRead,
      +[](const v1::GetMapRequest& r) { return r.name(); });
  AddUnary(
      "ListMaps", &PlaceDbService::ListMaps, Right::kAny,
      +[](const v1::ListMapsRequest&) { return std::string(); });
  AddUnary(
      "DeleteMap", &PlaceDbService::DeleteMap, Right::kAdmin,
      +[](const v1::DeleteMapRequest& r) { return r.name(); });
  AddUnary(
      "RecoverMap", &PlaceDbService::RecoverMap, Right::kAdmin,
      +[](const v1::RecoverMapRequest& r) { return r.name(); });
  AddUnary(
      "ScrubMap", &PlaceDbService::ScrubMap, Right::kAdmin,
      +[](const v1::ScrubMapRequest& r) { return r.name(); });
  AddUnary(
      "AdaptVocabulary", &PlaceDbService::AdaptVocabulary, Right::kAdmin,
      +[](const v1::AdaptVocabularyRequest& r) { return r.name(); });
  AddUnary(
      "RevertVocabulary", &PlaceDbService::RevertVocabulary, Right::kAdmin,
      +[](const v1::RevertVocabularyRequest& r) { return r.name(); });
  AddIngest("Ingest");  // write on header.map (ParsingIngestStream)
  AddUnary(
      "Query", &PlaceDbService::Query, Right::kRead,
      +[](const v1::QueryRequest& r) { return r.map(); });
  AddUnary(
      "GetPlace", &PlaceDbService::GetPlace, Right::kRead,
      +[](const v1::GetPlaceRequest& r) { return r.map(); });
  AddUnary(
      "ListPlaces", &PlaceDbService::ListPlaces, Right::kRead,
      +[](const v1::ListPlacesRequest& r) { return r.map(); });
  AddUnary(
      "DeletePlace", &PlaceDbService::DeletePlace, Right::kWrite,
      +[](const v1::DeletePlaceRequest& r) { return r.map(); });
  AddUnary(
      "GetDynamics", &PlaceDbService::GetDynamics, Right::kRead,
      +[](const v1::GetDynamicsRequest& r) { return r.map(); });
  AddServerStream<v1::WatchLoopClosuresRequest, v1::LoopConstraint>(
      "WatchLoopClosures", &PlaceDbService::WatchLoopClosuresStream, Right::kRead,
      +[](const v1::WatchLoopClosuresRequest& r) { return r.map(); });
  AddUnary(
      "GetServerInfo", &PlaceDbService::GetServerInfo, Right::kAny,
      +[](const v1::GetServerInfoRequest&) { return std::string(); });
  // Snapshots: admin. Only CreateSnapshot names a map in field 1; RestoreSnapshot's new_map is
  // checked by the registry (field new_map).
  AddUnary(
      "CreateSnapshot", &PlaceDbService::CreateSnapshot, Right::kAdmin,
      +[](const v1::CreateSnapshotRequest& r) { return r.map(); });
  AddUnary<v1::ListSnapshotsRequest, v1::ListSnapshotsResponse>(
      "ListSnapshots", &PlaceDbService::ListSnapshots, Right::kAdmin, nullptr);
  AddUnary<v1::DeleteSnapshotRequest, v1::DeleteSnapshotResponse>(
      "DeleteSnapshot", &PlaceDbService::DeleteSnapshot, Right::kAdmin, nullptr);
  AddUnary<v1::RestoreSnapshotRequest, v1::MapDescription>(
      "RestoreSnapshot", &PlaceDbService::RestoreSnapshot, Right::kAdmin, nullptr);
  AddServerStream<v1::DownloadSnapshotRequest, v1::SnapshotChunk>(
      "DownloadSnapshot", &PlaceDbService::DownloadSnapshotStream, Right::kAdmin, nullptr);
  AddClientStream<v1::SnapshotChunk, v1::Snapshot>(
      "UploadSnapshot", &PlaceDbService::UploadSnapshotStream, Right::kAdmin);
}

grpc::Status ParsingService::Authenticate(const char* method, const grpc::ServerContext& context,
                                          auth::Caller* caller,
                                          const auth::Credentials* credentials) const {
  if (!authorizer_) {
    *caller = auth::Caller::Everything("anonymous");
    return grpc::Status::OK;
  }
  auto authenticated = credentials ? authorizer_->Authenticate(method, *credentials)
                                   : authorizer_->Authenticate(method, context);
  if (auto* denied = std::get_if<grpc::Status>(&authenticated)) return *denied;
  *caller = std::move(std::get<auth::Caller>(authenticated));
  return grpc::Status::OK;
}

const char* ParsingService::Path(const char* method) {
  registered_.push_back(method);
  paths_.push_back(std::string("/") + kServiceName + "/" + method);
  return paths_.back().c_str();
}

template <typename Request>
grpc::Status ParsingService::Admit(const char* method, grpc::ServerContext* context,
                                   const auth::Credentials* credentials, const grpc::ByteBuffer& in,
                                   auth::Right right, std::string (*map_of)(const Request&),
                                   Request* request, auth::Caller* caller, std::string* map) {
  // Who is calling, before anything of the request is looked at.
  if (grpc::Status denied = Authenticate(method, *context, caller, credentials); !denied.ok()) {
    return service_->RefuseMalformed(method, context, denied);
  }
  if (std::string problem = ParseMessage(in, request); !problem.empty()) {
    return service_->RefuseMalformed(
        method, context,
        grpc::Status(
            grpc::StatusCode::INVALID_ARGUMENT,
            "request is not a valid " + Request::descriptor()->full_name() + ": " + problem));
  }
  *map = map_of ? map_of(*request) : std::string();
  if (authorizer_) {
    // Every request on a map names it in field 1 ("name" or "map").
    grpc::Status allowed =
        right == auth::Right::kAny || !map_of
            ? grpc::Status::OK
            : CheckRequestMapName(
                  method, std::string(Request::descriptor()->FindFieldByNumber(1)->name()), *map);
    if (allowed.ok()) {
      allowed = credentials
                    ? authorizer_->Authorize(method, credentials->peer, *caller, right, *map)
                    : authorizer_->Authorize(method, *context, *caller, right, *map);
    }
    if (!allowed.ok()) return service_->RefuseMalformed(method, context, allowed);
  }
  return grpc::Status::OK;
}

template <typename Request, typename Response>
void ParsingService::AddUnary(const char* method,
                              grpc::Status (PlaceDbService::*handler)(grpc::ServerContext*,
                                                                      const Request*, Response*),
                              auth::Right right, std::string (*map_of)(const Request&)) {
  UnaryCall call = [this, method, handler, right, map_of](
                       grpc::ServerContext* context, const auth::Credentials* credentials,
                       const grpc::ByteBuffer& in, grpc::ByteBuffer* out) {
    auth::Caller caller;
    Request request;
    std::string map;
    if (grpc::Status admitted =
            Admit(method, context, credentials, in, right, map_of, &request, &caller, &map);
        !admitted.ok()) {
      return admitted;
    }
    Response response;
    grpc::Status status = (service_->*handler)(context, &request, &response);
    if (right == auth::Right::kAdmin) {
      spdlog::info("auth admin method={} principal={} peer={} map={} result={}", method,
                   ForLog(caller.name), ForLog(credentials ? credentials->peer : context->peer()),
                   ForLog(map), wire::GrpcCodeName(status.error_code()));
    }
    if (!status.ok()) return status;
    RestrictResponse(caller, &response);
    bool own = false;
    return grpc::SerializationTraits<Response>::Serialize(response, out, &own);
  };
  unary_[method] = call;
  auto parse_and_call = [call](ParsingService*, grpc::ServerContext* context,
                               const grpc::ByteBuffer* in,
                               grpc::ByteBuffer* out) { return call(context, nullptr, *in, out); };
  AddMethod(new grpc::internal::RpcServiceMethod(
      Path(method), grpc::internal::RpcMethod::NORMAL_RPC,
      new grpc::internal::RpcMethodHandler<ParsingService, grpc::ByteBuffer, grpc::ByteBuffer>(
          parse_and_call, this)));
}

void ParsingService::AddIngest(const char* method) {
  auto stream = [method](ParsingService* self, grpc::ServerContext* context,
                         grpc::ServerReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>* raw) {
    // Authenticated before the stream is admitted: an unknown caller never holds a stream slot.
    auth::Caller caller;
    if (grpc::Status denied = self->Authenticate(method, *context, &caller); !denied.ok()) {
      return self->service_->RefuseMalformed(method, context, denied);
    }
    ParsingIngestStream io(raw, self->authorizer_, context, std::move(caller));
    return self->service_->IngestStream(context, &io);
  };
  AddMethod(new grpc::internal::RpcServiceMethod(
      Path(method), grpc::internal::RpcMethod::BIDI_STREAMING,
      new grpc::internal::BidiStreamingHandler<ParsingService, grpc::ByteBuffer, grpc::ByteBuffer>(
          stream, this)));
}

template <typename Request, typename Response>
void ParsingService::AddServerStream(
    const char* method,
    grpc::Status (PlaceDbService::*handler)(grpc::ServerContext*, const Request*,
                                            const std::function<bool(const Response&)>&),
    auth::Right right, std::string (*map_of)(const Request&)) {
  auto stream = [method, handler, right, map_of](ParsingService* self, grpc::ServerContext* context,
                                                 const grpc::ByteBuffer* in,
                                                 grpc::ServerWriter<grpc::ByteBuffer>* writer) {
    auth::Caller caller;
    Request request;
    std::string map;
    if (grpc::Status admitted =
            self->Admit(method, context, nullptr, *in, right, map_of, &request, &caller, &map);
        !admitted.ok()) {
      return admitted;
    }
    auto write = [writer](const Response& response) {
      grpc::ByteBuffer bytes;
      bool own = false;
      if (!grpc::SerializationTraits<Response>::Serialize(response, &bytes, &own).ok()) {
        return false;
      }
      return writer->Write(bytes);
    };
    grpc::Status status = (self->service_->*handler)(context, &request, write);
    if (right == auth::Right::kAdmin) {
      spdlog::info("auth admin method={} principal={} peer={} map={} result={}", method,
                   ForLog(caller.name), ForLog(context->peer()), ForLog(map),
                   wire::GrpcCodeName(status.error_code()));
    }
    return status;
  };
  AddMethod(new grpc::internal::RpcServiceMethod(
      Path(method), grpc::internal::RpcMethod::SERVER_STREAMING,
      new grpc::internal::ServerStreamingHandler<ParsingService, grpc::ByteBuffer,
                                                 grpc::ByteBuffer>(stream, this)));
}

template <typename Request, typename Response>
void ParsingService::AddClientStream(const char* method,
                                     grpc::Status (PlaceDbService::*handler)(
                                         grpc::ServerContext*,
                                         const std::function<grpc::Status(Request*, bool* done)>&,
                                         Response*),
                                     auth::Right right) {
  auto stream = [method, handler, right](ParsingService* self, grpc::ServerContext* context,
                                         grpc::ServerReader<grpc::ByteBuffer>* reader,
                                         grpc::ByteBuffer* out) {
    auth::Caller caller;
    if (grpc::Status denied = self->Authenticate(method, *context, &caller); !denied.ok()) {
      return self->service_->RefuseMalformed(method, context, denied);
    }
    if (self->authorizer_) {
      if (grpc::Status allowed = self->authorizer_->Authorize(method, *context, caller, right, "");
          !allowed.ok()) {
        return self->service_->RefuseMalformed(method, context, allowed);
      }
    }
    size_t messages = 0;
    auto read = [&](Request* request, bool* done) {
      grpc::ByteBuffer bytes;
      *done = !reader->Read(&bytes);
      if (*done) return grpc::Status::OK;
      ++messages;
      if (std::string problem = ParseMessage(bytes, request); !problem.empty()) {
        return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            "message " + std::to_string(messages) + " of the " + method +
                                " stream is not a valid " + Request::descriptor()->full_name() +
                                ": " + problem);
      }
      return grpc::Status::OK;
    };
    Response response;
    grpc::Status status = (self->service_->*handler)(context, read, &response);
    if (right == auth::Right::kAdmin) {
      spdlog::info("auth admin method={} principal={} peer={} map= result={}", method,
                   ForLog(caller.name), ForLog(context->peer()),
                   wire::GrpcCodeName(status.error_code()));
    }
    if (!status.ok()) return status;
    bool own = false;
    return grpc::SerializationTraits<Response>::Serialize(response, out, &own);
  };
  AddMethod(new grpc::internal::RpcServiceMethod(
      Path(method), grpc::internal::RpcMethod::CLIENT_STREAMING,
      new grpc::internal::ClientStreamingHandler<ParsingService, grpc::ByteBuffer,
                                                 grpc::ByteBuffer>(stream, this)));
}

grpc::Status ParsingService::CallUnary(const std::string& method,
                                       const auth::Credentials& credentials,
                                       const std::string& request, std::string* response) {
  const auto found = unary_.find(method);
  if (found == unary_.end()) {
    return grpc::Status(grpc::StatusCode::UNIMPLEMENTED,
                        "'" + method + "' is not a unary method of " + kServiceName);
  }
  grpc::Slice slice(request);
  const grpc::ByteBuffer in(&slice, 1);
  grpc::ByteBuffer out;
  // A context of no gRPC call: no deadline, never cancelled, no peer (credentials name it).
  grpc::ServerContext context;
  grpc::Status status = found->second(&context, &credentials, in, &out);
  if (!status.ok()) return status;
  std::vector<grpc::Slice> slices;
  if (!out.Dump(&slices).ok()) {
    return grpc::Status(grpc::StatusCode::INTERNAL, "cannot read the answer");
  }
  response->clear();
  response->reserve(out.Length());
  for (const grpc::Slice& piece : slices) {
    response->append(reinterpret_cast<const char*>(piece.begin()), piece.size());
  }
  return grpc::Status::OK;
}

grpc::Status ParsingService::AuthenticateCall(const std::string& method,
                                              const auth::Credentials& credentials) {
  const auto found = unary_.find(method);
  if (found == unary_.end()) {
    return grpc::Status(grpc::StatusCode::UNIMPLEMENTED,
                        "'" + method + "' is not a unary method of " + kServiceName);
  }
  // As Admit's first step, with the context CallUnary gives a call of no gRPC transport.
  grpc::ServerContext context;
  auth::Caller caller;
  if (grpc::Status denied = Authenticate(found->first.c_str(), context, &caller, &credentials);
      !denied.ok()) {
    return service_->RefuseMalformed(found->first.c_str(), &context, denied);
  }
  return grpc::Status::OK;
}

std::vector<std::string> ParsingService::Unregistered() const {
  std::vector<std::string> missing;
  const google::protobuf::ServiceDescriptor* service =
      v1::CreateMapRequest::descriptor()->file()->FindServiceByName("PlaceDb");
  for (int i = 0; service && i < service->method_count(); ++i) {
    const std::string& name = service->method(i)->name();
    if (std::find(registered_.begin(), registered_.end(), name) == registered_.end()) {
      missing.push_back(service->full_name() + "/" + name);
    }
  }
  return missing;
}

}  // namespace placedb::server
