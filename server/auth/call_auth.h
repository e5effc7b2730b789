// Who is calling and what they may do, for every placedb.v1.PlaceDb call and /metrics scrape
// (docs/security.md, "Principals, tokens and rights"). ParsingService asks it before each
// handler; the rights themselves live in server/auth/tokens.h.
//
// Three modes, from the configuration:
//   - no tokens file, no mutual TLS: no checks; every caller is "anonymous" with every right;
//   - mutual TLS, no tokens file: every holder of a verified client certificate has every right
//     (the client CA is the authority); the principal is the certificate's CN;
//   - a tokens file: `authorization: Bearer <token>`, or without that header a verified client
//     certificate whose CN or SAN a principal lists in certificate_names.
// Denials: UNAUTHENTICATED (no, malformed or unknown credentials), PERMISSION_DENIED (lacking
// the right). Messages name the method and the map, never the token.
#pragma once

#include <grpcpp/grpcpp.h>

#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <variant>
#include <vector>

#include "server/auth/token_store.h"
#include "server/auth/tokens.h"

namespace placedb::server::auth {

// What a method needs (docs/security.md lists the table per RPC).
enum class Right {
  kAny,    // any authenticated principal (ListMaps, GetServerInfo)
  kRead,   // read on the request's map
  kWrite,  // write on the request's map
  kAdmin,  // admin
};

// The label of placedb_auth_denied_total{reason}.
enum class DenyReason {
  kMissingCredentials,
  kMalformedCredentials,
  kUnknownToken,
  kUnknownCertificate,
  kPermissionDenied,
};
const char* DenyReasonLabel(DenyReason reason);

// An authenticated caller.
struct Caller {
  std::string name;         // the principal's name, the certificate's CN, or "anonymous"
  bool everything = false;  // auth off or mutual TLS without a tokens file: every right
  std::shared_ptr<const TokensFile> tokens;  // the snapshot `principal` points into
  const Principal* principal = nullptr;      // null when `everything`
  uint64_t generation = 0;                   // the store's generation `principal` is from
  // How it authenticated, to resolve it again after a reload (an open Ingest stream). The token
  // stays in memory for the call's life only; it is never logged.
  std::string token;
  std::vector<std::string> certificate_names;

  // A caller with every right (auth off: "anonymous"; mutual TLS alone: the certificate's CN).
  static Caller Everything(std::string name) {
    Caller caller;
    caller.name = std::move(name);
    caller.everything = true;
    return caller;
  }

  bool Has(Right right, const std::string& map) const;
  bool admin() const { return everything || (principal && principal->admin); }
};

// What a call presents to prove who it is, whatever the transport (gRPC metadata and TLS, or the
// console's HTTP headers and TLS).
struct Credentials {
  std::string peer;                        // "ipv4:a.b.c.d:port" / "ipv6:[...]:port", for the audit
  std::vector<std::string> authorization;  // every `authorization` header's value
  std::vector<std::string> certificate_names;  // the verified client certificate's names
};
// A gRPC call's credentials.
Credentials CredentialsOf(const grpc::ServerContext& context);

class CallAuthorizer {
 public:
  // Counts a denial: (reason, method) -> placedb_auth_denied_total.
  using DeniedCallback = std::function<void(DenyReason reason, const std::string& method)>;

  // `store` null = no tokens file. `store` must outlive this.
  CallAuthorizer(const TokenStore* store, bool mutual_tls, DeniedCallback on_denied);

  // False when every caller may do everything (no tokens file, no mutual TLS).
  bool enabled() const { return store_ != nullptr || mutual_tls_; }

  // Who is calling `method`. On failure: UNAUTHENTICATED naming the method, logged (audit) and
  // counted.
  std::variant<Caller, grpc::Status> Authenticate(const char* method,
                                                  const grpc::ServerContext& context) const;
  std::variant<Caller, grpc::Status> Authenticate(const char* method,
                                                  const Credentials& credentials) const;
  // OK when `caller` has `right` on `map` (Right::kAny: always); else PERMISSION_DENIED naming
  // the method, principal and map, logged and counted.
  grpc::Status Authorize(const char* method, const grpc::ServerContext& context,
                         const Caller& caller, Right right, const std::string& map) const;
  grpc::Status Authorize(const char* method, const std::string& peer, const Caller& caller,
                         Right right, const std::string& map) const;
  // For long calls (an Ingest stream): when the tokens file was reloaded since `caller` was
  // resolved, resolves it again from the credentials it came with (updating *caller). OK when it
  // is still a principal; UNAUTHENTICATED when its token or certificate name no longer is one.
  // `map` is for the audit line.
  grpc::Status Refresh(const char* method, const grpc::ServerContext& context,
                       const std::string& map, Caller* caller) const;

  // HTTP basic auth of a /metrics scrape from `peer` (the scraper's address, for the audit
  // line): `user` must be the name of the principal whose token is `password`, and that
  // principal must have `metrics` or `admin`. Denials are logged and counted with method
  // "metrics". Always true when there is no tokens file.
  bool AuthorizeScrape(const std::string& peer, const std::string& user,
                       const std::string& password) const;

 private:
  grpc::Status Deny(const char* method, const std::string& peer, const std::string& principal,
                    const std::string& map, DenyReason reason, const std::string& message) const;
  // Resolves credentials against the current snapshot; `method` words the errors. `previous`
  // (the principal the credentials named before a reload) and `map` are for the audit line.
  std::variant<Caller, grpc::Status> Resolve(const char* method, const std::string& peer,
                                             const std::string& previous, const std::string& map,
                                             std::string token,
                                             std::vector<std::string> certificate_names,
                                             bool by_token) const;

  const TokenStore* const store_;
  const bool mutual_tls_;
  const DeniedCallback on_denied_;
};

}  // namespace placedb::server::auth
