#include "server/parsing_service.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/wire_format_lite.h>
#include <grpcpp/impl/rpc_service_method.h>
#include <grpcpp/support/method_handler.h>
#include <grpcpp/support/proto_buffer_reader.h>

#include <algorithm>
#include <map>

#include "server/service.h"

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

// Ingest's reader-writer over raw bytes: reads parse, writes serialise.
class ParsingIngestStream final : public IngestStreamIo {
 public:
  explicit ParsingIngestStream(grpc::ServerReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>* raw)
      : raw_(raw) {}

  void SendInitialMetadata() override { raw_->SendInitialMetadata(); }
  bool NextMessageSize(uint32_t* size) override { return raw_->NextMessageSize(size); }
  bool Read(v1::IngestRequest* message) override {
    grpc::ByteBuffer bytes;
    if (!raw_->Read(&bytes)) return false;
    if (std::string problem = ParseMessage(bytes, message); !problem.empty()) {
      error_ = grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            StreamPosition(read_) + " is not a valid " +
                                v1::IngestRequest::descriptor()->full_name() + ": " + problem);
      return false;
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
  grpc::ServerReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>* const raw_;
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

ParsingService::ParsingService(PlaceDbService* service) : service_(service) {
  AddUnary("CreateMap", &PlaceDbService::CreateMap);
  AddUnary("GetMap", &PlaceDbService::GetMap);
  AddUnary("ListMaps", &PlaceDbService::ListMaps);
  AddUnary("DeleteMap", &PlaceDbService::DeleteMap);
  AddUnary("RecoverMap", &PlaceDbService::RecoverMap);
  AddUnary("ScrubMap", &PlaceDbService::ScrubMap);
  AddIngest("Ingest");
  AddUnary("Query", &PlaceDbService::Query);
  AddUnary("GetPlace", &PlaceDbService::GetPlace);
  AddUnary("DeletePlace", &PlaceDbService::DeletePlace);
  AddUnary("GetServerInfo", &PlaceDbService::GetServerInfo);
}

const char* ParsingService::Path(const char* method) {
  registered_.push_back(method);
  paths_.push_back(std::string("/") + kServiceName + "/" + method);
  return paths_.back().c_str();
}

template <typename Request, typename Response>
void ParsingService::AddUnary(const char* method,
                              grpc::Status (PlaceDbService::*handler)(grpc::ServerContext*,
                                                                      const Request*, Response*)) {
  auto parse_and_call = [method, handler](ParsingService* self, grpc::ServerContext* context,
                                          const grpc::ByteBuffer* in, grpc::ByteBuffer* out) {
    Request request;
    if (std::string problem = ParseMessage(*in, &request); !problem.empty()) {
      return self->service_->RefuseMalformed(
          method, context,
          grpc::Status(
              grpc::StatusCode::INVALID_ARGUMENT,
              "request is not a valid " + Request::descriptor()->full_name() + ": " + problem));
    }
    Response response;
    grpc::Status status = (self->service_->*handler)(context, &request, &response);
    if (!status.ok()) return status;
    bool own = false;
    return grpc::SerializationTraits<Response>::Serialize(response, out, &own);
  };
  AddMethod(new grpc::internal::RpcServiceMethod(
      Path(method), grpc::internal::RpcMethod::NORMAL_RPC,
      new grpc::internal::RpcMethodHandler<ParsingService, grpc::ByteBuffer, grpc::ByteBuffer>(
          parse_and_call, this)));
}

void ParsingService::AddIngest(const char* method) {
  auto stream = [](ParsingService* self, grpc::ServerContext* context,
                   grpc::ServerReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>* raw) {
    ParsingIngestStream io(raw);
    return self->service_->IngestStream(context, &io);
  };
  AddMethod(new grpc::internal::RpcServiceMethod(
      Path(method), grpc::internal::RpcMethod::BIDI_STREAMING,
      new grpc::internal::BidiStreamingHandler<ParsingService, grpc::ByteBuffer, grpc::ByteBuffer>(
          stream, this)));
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
