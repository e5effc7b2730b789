// The web console of placedb-server (docs/console.md): its pages and a JSON API on their own
// HTTP listener (server/net/http_endpoint.h), over the same calls as gRPC.
//
//   POST /api/v1/<Method>   the request as protobuf JSON (the proto's field names) -> the answer
//                           as protobuf JSON; only the read and query methods of kConsoleMethods.
//                           Each call goes through ParsingService::CallUnary: the same
//                           authentication (`Authorization: Bearer <token>`, or the HTTPS client
//                           certificate's names), map-name check, authorization, handler and
//                           restrictions as the gRPC call. Errors: the gRPC code as an HTTP
//                           status (HttpStatusOf) with {"code":"NOT_FOUND","message":"..."}.
//   GET /api/v1/maps/<map>/places/<id>/thumbnail.jpg   the place's thumbnail (GetPlace
//                           include_thumbnail); 404 when the map keeps none for it.
//   GET /enum-names.json    {"<Enum>": {"<VALUE_NAME>": "<name>"}} for every placedb.v1 enum: the
//                           names proto/names.h gives the value names the JSON API prints
//                           (BOX_SOURCE_UNSPECIFIED -> "agent"), so the pages name values as the
//                           CLI and reports do, from the proto's (name) option, not a table here.
//   GET /enum-numbers.json  {"<Enum>": {"<number>": "<name>"}}, the same names by number: the
//                           fields the proto keeps int32 (UsedBox.class_id, DynamicClassCount
//                           .class_id: COCO ids, named by CocoClass) print as numbers.
//   GET /, /<file>          the pages (server/console/web, embedded into the binary at build).
//
// Refusals come from the headers, before httplib reads a body (its pre-routing handler), so a
// refused body is never read nor parsed and the answer closes the connection: the Host rule
// below (403), a method not on the list (404), a caller whose credentials are refused (401: the
// same ParsingService::AuthenticateCall as CallUnary's first step, so no second token check),
// and a Content-Length over max_request_bytes (413, server/net/http_endpoint.h). Authorization on
// the request's map needs the body: an authenticated caller without the right gets 403 after it.
// POSTs must say `Content-Type: application/json` (a browser then asks before a cross-site page
// may send one, and the console never says yes). A console that does not authenticate (no tokens
// file, no client certificates) answers only requests whose Host is an IP address or localhost:
// another site's name resolved to 127.0.0.1 (DNS rebinding) cannot read the maps.
#pragma once

#include <grpcpp/grpcpp.h>

#include <memory>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "server/net/http_endpoint.h"

namespace placedb::server {

class ParsingService;

// The methods the JSON API serves: reads and queries, no administration or writes.
extern const std::vector<std::string> kConsoleMethods;

// The HTTP status a gRPC code is answered with (INVALID_ARGUMENT 400, UNAUTHENTICATED 401,
// PERMISSION_DENIED 403, NOT_FOUND 404, ALREADY_EXISTS / FAILED_PRECONDITION / ABORTED 409,
// RESOURCE_EXHAUSTED 429, UNIMPLEMENTED 501, UNAVAILABLE 503, DEADLINE_EXCEEDED 504,
// CANCELLED 499, OUT_OF_RANGE 400, anything else 500).
int HttpStatusOf(grpc::StatusCode code);

// One embedded page file (generated from server/console/web by CMake).
struct ConsoleFile {
  const char* path;  // "/index.html"
  const unsigned char* data;
  size_t size;
};
// The file served at `path` ("/" is "/index.html"); null when there is none.
const ConsoleFile* FindConsoleFile(const std::string& path);
// The body of GET /enum-names.json.
std::string ConsoleEnumNames();
// The body of GET /enum-numbers.json.
std::string ConsoleEnumNumbers();

class Console {
 public:
  // `calls` must outlive this. `authenticated`: whether callers must prove who they are (tokens
  // or client certificates); without it the Host rule above applies.
  Console(ParsingService* calls, bool authenticated);
  ~Console();  // Stop()

  // Serves on settings.listen; errors as HttpEndpoint::Serve.
  Status Serve(const HttpEndpointSettings& settings);
  int port() const { return http_.port(); }
  // "http://host:port/" (https with TLS) as bound; "" when not serving.
  std::string url() const { return url_; }
  void Stop();

 private:
  ParsingService* const calls_;
  const bool authenticated_;
  HttpEndpoint http_;
  std::string url_;
};

}  // namespace placedb::server
