#include "server/console/console.h"

#include <arpa/inet.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/dynamic_message.h>
#include <google/protobuf/util/json_util.h>
#include <httplib.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <functional>
#include <nlohmann/json.hpp>
#include <regex>

#include "proto/names.h"
#include "proto/placedb.grpc.pb.h"
#include "proto/status.h"
#include "server/auth/call_auth.h"
#include "server/net/transport_security.h"
#include "server/rpc/parsing_service.h"

namespace placedb::server {

namespace {

namespace v1 = ::placedb::v1;
using google::protobuf::Message;

const google::protobuf::ServiceDescriptor* PlaceDbDescriptor() {
  return v1::GetServerInfoRequest::descriptor()->file()->FindServiceByName("PlaceDb");
}

// {"code":"NOT_FOUND","message":"..."} with the code's HTTP status.
void Answer(httplib::Response& response, int http_status, const std::string& code,
            const std::string& message) {
  response.status = http_status;
  response.set_content(nlohmann::json{{"code", code}, {"message", message}}.dump(),
                       "application/json");
}
void AnswerStatus(httplib::Response& response, const grpc::Status& status) {
  Answer(response, HttpStatusOf(status.error_code()), wire::GrpcCodeName(status.error_code()),
         status.error_message());
}

// Host is an IP literal or localhost (with or without a port).
bool HostIsAddress(const std::string& host_header) {
  std::string host = host_header;
  if (!host.empty() && host.front() == '[') return host.find(']') != std::string::npos;
  if (const auto colon = host.find(':'); colon != std::string::npos) host.resize(colon);
  in_addr address{};
  return host == "localhost" || inet_pton(AF_INET, host.c_str(), &address) == 1;
}

std::string ContentType(const std::string& path) {
  const auto dot = path.rfind('.');
  const std::string extension = dot == std::string::npos ? "" : path.substr(dot + 1);
  if (extension == "html") return "text/html; charset=utf-8";
  if (extension == "css") return "text/css; charset=utf-8";
  if (extension == "js") return "text/javascript; charset=utf-8";
  if (extension == "svg") return "image/svg+xml";
  if (extension == "png") return "image/png";
  return "application/octet-stream";
}

// POST /api/v1/<Method>.
constexpr char kApiPattern[] = R"(/api/v1/([A-Za-z]+))";

}  // namespace

const std::vector<std::string> kConsoleMethods = {
    "ListMaps", "GetMap", "ListPlaces", "GetPlace", "Query", "GetDynamics", "GetServerInfo"};

namespace {

// Every placedb.v1 enum: {type name: {key_of(value): the value's API name}}. Aliases (CocoClass)
// share a number and its name (EnumValueName goes by number).
std::string EnumTable(
    const std::function<std::string(const google::protobuf::EnumValueDescriptor*)>& key_of) {
  const google::protobuf::FileDescriptor* file = v1::GetServerInfoRequest::descriptor()->file();
  nlohmann::json table = nlohmann::json::object();
  for (int e = 0; e < file->enum_type_count(); ++e) {
    const google::protobuf::EnumDescriptor* type = file->enum_type(e);
    nlohmann::json values = nlohmann::json::object();
    for (int v = 0; v < type->value_count(); ++v) {
      values[key_of(type->value(v))] = wire::EnumValueName(type, type->value(v)->number());
    }
    table[type->name()] = std::move(values);
  }
  return table.dump();
}

}  // namespace

std::string ConsoleEnumNames() {
  // Aliases too: protobuf's JSON prints a number's first value name, named the same.
  return EnumTable(
      [](const google::protobuf::EnumValueDescriptor* value) { return value->name(); });
}

std::string ConsoleEnumNumbers() {
  return EnumTable([](const google::protobuf::EnumValueDescriptor* value) {
    return std::to_string(value->number());
  });
}

int HttpStatusOf(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return 200;
    case grpc::StatusCode::INVALID_ARGUMENT:
    case grpc::StatusCode::OUT_OF_RANGE:
      return 400;
    case grpc::StatusCode::UNAUTHENTICATED:
      return 401;
    case grpc::StatusCode::PERMISSION_DENIED:
      return 403;
    case grpc::StatusCode::NOT_FOUND:
      return 404;
    case grpc::StatusCode::ALREADY_EXISTS:
    case grpc::StatusCode::FAILED_PRECONDITION:
    case grpc::StatusCode::ABORTED:
      return 409;
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return 429;
    case grpc::StatusCode::CANCELLED:
      return 499;
    case grpc::StatusCode::UNIMPLEMENTED:
      return 501;
    case grpc::StatusCode::UNAVAILABLE:
      return 503;
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return 504;
    default:
      return 500;
  }
}

Console::Console(ParsingService* calls, bool authenticated)
    : calls_(calls), authenticated_(authenticated) {}

Console::~Console() {
  Stop();
}

void Console::Stop() {
  http_.Stop();
  url_.clear();
}

Status Console::Serve(const HttpEndpointSettings& settings) {
  Stop();
  ParsingService* calls = calls_;
  const bool authenticated = authenticated_;

  // The caller's credentials, as a gRPC call's would be.
  auto credentials_of = [](const httplib::Request& request) {
    auth::Credentials credentials;
    credentials.peer = HttpPeerName(request);
    const auto headers = request.headers.equal_range("Authorization");
    for (auto header = headers.first; header != headers.second; ++header) {
      credentials.authorization.push_back(header->second);
    }
    credentials.certificate_names = PeerCertificateNames(static_cast<const void*>(request.ssl));
    return credentials;
  };

  // One unary call with a protobuf request; false with the error answered.
  auto call = [calls, credentials_of](const httplib::Request& request, httplib::Response& response,
                                      const std::string& method, const Message& in, Message* out) {
    std::string answer;
    const grpc::Status status =
        calls->CallUnary(method, credentials_of(request), in.SerializeAsString(), &answer);
    if (!status.ok()) {
      AnswerStatus(response, status);
      return false;
    }
    if (!out->ParseFromString(answer)) {
      Answer(response, 500, "INTERNAL", method + ": the answer does not parse");
      return false;
    }
    return true;
  };

  // The method of a POST to the JSON API (the pre-routing handler admitted it), answered here.
  auto api = [call](const httplib::Request& request, httplib::Response& response) {
    const std::string method = request.matches[1];
    const std::string content_type = request.get_header_value("Content-Type");
    if (content_type.rfind("application/json", 0) != 0) {
      Answer(response, 415, "INVALID_ARGUMENT",
             "send the request as Content-Type: application/json");
      return;
    }
    const google::protobuf::MethodDescriptor* descriptor =
        PlaceDbDescriptor()->FindMethodByName(method);
    const Message* request_type =
        google::protobuf::MessageFactory::generated_factory()->GetPrototype(
            descriptor->input_type());
    const Message* response_type =
        google::protobuf::MessageFactory::generated_factory()->GetPrototype(
            descriptor->output_type());
    std::unique_ptr<Message> in(request_type->New());
    std::unique_ptr<Message> out(response_type->New());
    const std::string body = request.body.empty() ? "{}" : request.body;
    google::protobuf::util::JsonParseOptions parse;
    parse.ignore_unknown_fields = false;  // a misspelt field is an error, not ignored
    if (auto parsed = google::protobuf::util::JsonStringToMessage(body, in.get(), parse);
        !parsed.ok()) {
      Answer(response, 400, "INVALID_ARGUMENT",
             "request is not a valid " + descriptor->input_type()->full_name() +
                 " in JSON: " + std::string(parsed.message()));
      return;
    }
    if (!call(request, response, method, *in, out.get())) return;
    google::protobuf::util::JsonPrintOptions print;
    print.preserve_proto_field_names = true;
    print.always_print_primitive_fields = true;  // zeros too: the pages need no defaults
    std::string json;
    if (auto printed = google::protobuf::util::MessageToJsonString(*out, &json, print);
        !printed.ok()) {
      Answer(response, 500, "INTERNAL", method + ": cannot write the answer as JSON");
      return;
    }
    response.status = 200;
    response.set_content(json, "application/json");
  };

  auto thumbnail = [call](const httplib::Request& request, httplib::Response& response) {
    v1::GetPlaceRequest get;
    get.set_map(request.matches[1]);
    const std::string id = request.matches[2];
    if (id.size() > 10 || std::stoull(id) > 0xffffffffull) {
      Answer(response, 400, "INVALID_ARGUMENT", "place id '" + id + "' is out of range");
      return;
    }
    get.set_place_id(uint32_t(std::stoull(id)));
    get.set_include_thumbnail(true);
    v1::Place place;
    if (!call(request, response, "GetPlace", get, &place)) return;
    if (!place.has_thumbnail() || place.thumbnail().jpeg().empty()) {
      Answer(response, 404, "NOT_FOUND",
             "map '" + get.map() + "' keeps no thumbnail of place " + id);
      return;
    }
    response.status = 200;
    response.set_header("Cache-Control", "private, max-age=3600");  // a place never changes
    response.set_content(place.thumbnail().jpeg(), "image/jpeg");
  };

  // Made once: the descriptors do not change while the server runs.
  auto enum_names = [names = ConsoleEnumNames()](const httplib::Request&,
                                                 httplib::Response& response) {
    response.status = 200;
    response.set_content(names, "application/json");
  };

  auto enum_numbers = [numbers = ConsoleEnumNumbers()](const httplib::Request&,
                                                       httplib::Response& response) {
    response.status = 200;
    response.set_content(numbers, "application/json");
  };

  auto page = [](const httplib::Request& request, httplib::Response& response) {
    const ConsoleFile* file = FindConsoleFile(request.path);
    if (!file) {
      Answer(response, 404, "NOT_FOUND", "no page '" + request.path + "'");
      return;
    }
    response.status = 200;
    response.set_content(std::string(reinterpret_cast<const char*>(file->data), file->size),
                         ContentType(file->path));
  };

  auto routes = [=](httplib::Server& http) {
    // httplib runs this before it reads a body: every refusal here costs the headers only, and
    // the body stays unread (the answer closes the connection).
    http.set_pre_routing_handler([authenticated, calls, credentials_of](
                                     const httplib::Request& request, httplib::Response& response) {
      if (!authenticated && !HostIsAddress(request.get_header_value("Host"))) {
        Answer(response, 403, "PERMISSION_DENIED",
               "this console does not authenticate its callers: open it by address "
               "(http://127.0.0.1:<port>/), not by a host name");
        return httplib::Server::HandlerResponse::Handled;
      }
      static const std::regex kApiCall(kApiPattern);
      std::smatch match;
      if (request.method != "POST" || !std::regex_match(request.path, match, kApiCall)) {
        return httplib::Server::HandlerResponse::Unhandled;
      }
      const std::string method = match[1];
      if (std::find(kConsoleMethods.begin(), kConsoleMethods.end(), method) ==
          kConsoleMethods.end()) {
        Answer(response, 404, "NOT_FOUND",
               "'" + method +
                   "' is not served over HTTP (the console's methods: ListMaps, GetMap, "
                   "ListPlaces, GetPlace, Query, GetDynamics, GetServerInfo)");
        return httplib::Server::HandlerResponse::Handled;
      }
      // Who is calling, from the headers (finding 4 of issue 34: parsing refused callers'
      // bodies first cost 0.36 s of CPU each). CallUnary authorizes the admitted ones on the
      // request's map once the body is read.
      if (authenticated) {
        if (const grpc::Status status = calls->AuthenticateCall(method, credentials_of(request));
            !status.ok()) {
          AnswerStatus(response, status);
          return httplib::Server::HandlerResponse::Handled;
        }
      }
      return httplib::Server::HandlerResponse::Unhandled;
    });
    http.set_post_routing_handler([](const httplib::Request&, httplib::Response& response) {
      // Everything is served from here: no other origin's scripts, styles, fonts or frames.
      response.set_header("Content-Security-Policy",
                          "default-src 'self'; img-src 'self' blob: data:; frame-ancestors 'none'");
      response.set_header("X-Content-Type-Options", "nosniff");
      response.set_header("Referrer-Policy", "no-referrer");
    });
    // httplib's own refusals (413 for a body over the limit, 404/405 for unknown routes) as JSON.
    http.set_error_handler(httplib::Server::HandlerWithResponse(
        [](const httplib::Request& request, httplib::Response& response) {
          if (!response.body.empty()) return httplib::Server::HandlerResponse::Unhandled;
          if (response.status == 413) {
            Answer(response, 413, "RESOURCE_EXHAUSTED",
                   "the request body is larger than console_max_request_bytes");
          } else if (response.status == 404) {
            Answer(response, 404, "NOT_FOUND", "no page or method '" + request.path + "'");
          } else {
            Answer(response, response.status, "INVALID_ARGUMENT",
                   "HTTP " + std::to_string(response.status) + " for " + request.method + " " +
                       request.path);
          }
          return httplib::Server::HandlerResponse::Handled;
        }));
    http.Post(kApiPattern, api);
    http.Get(R"(/api/v1/maps/([^/]+)/places/([0-9]+)/thumbnail\.jpg)", thumbnail);
    http.Get(R"(/api/.*)", [](const httplib::Request& request, httplib::Response& response) {
      Answer(response, 405, "INVALID_ARGUMENT",
             "'" + request.path + "': the JSON API takes POST with a JSON body");
      response.set_header("Allow", "POST");
    });
    http.Get("/enum-names.json", enum_names);
    http.Get("/enum-numbers.json", enum_numbers);
    http.Get(R"(/[A-Za-z0-9._-]*)", page);
  };
  HttpEndpointSettings named = settings;
  if (named.name.empty()) named.name = "console";
  PLACEDB_RETURN_IF_ERROR(http_.Serve(named, routes));
  std::string host = settings.listen.substr(0, settings.listen.rfind(':'));
  url_ = std::string(settings.tls ? "https" : "http") + "://" + host + ":" +
         std::to_string(http_.port()) + "/";
  return Status::Ok();
}

}  // namespace placedb::server
