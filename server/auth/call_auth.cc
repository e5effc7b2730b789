#include "server/auth/call_auth.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cctype>

#include "core/base/text.h"
#include "server/net/transport_security.h"

namespace placedb::server::auth {

namespace {

constexpr char kAnonymous[] = "anonymous";

bool IsSpace(char c) {
  return c == ' ' || c == '\t';
}

// The token of "Bearer <token>" (scheme case-insensitive, RFC 6750), or nullopt.
std::optional<std::string> BearerToken(std::string_view value) {
  constexpr std::string_view kScheme = "bearer";
  if (value.size() <= kScheme.size() || !IsSpace(value[kScheme.size()])) return std::nullopt;
  for (size_t i = 0; i < kScheme.size(); ++i) {
    if (std::tolower(static_cast<unsigned char>(value[i])) != kScheme[i]) return std::nullopt;
  }
  value.remove_prefix(kScheme.size());
  while (!value.empty() && IsSpace(value.front())) value.remove_prefix(1);
  while (!value.empty() && IsSpace(value.back())) value.remove_suffix(1);
  if (value.empty()) return std::nullopt;
  for (char c : value) {
    if (c <= ' ' || c == 0x7f) return std::nullopt;
  }
  return std::string(value);
}

// The verified client certificate's names (empty without one).
std::vector<std::string> CertificateNames(const grpc::ServerContext& context) {
  const std::shared_ptr<const grpc::AuthContext> auth = context.auth_context();
  if (!auth || !auth->IsPeerAuthenticated()) return {};
  return PeerCertificateNames(*auth);
}

const char* Verb(Right right) {
  switch (right) {
    case Right::kRead:
      return "read";
    case Right::kWrite:
      return "write";
    default:
      return "administer";
  }
}

}  // namespace

Credentials CredentialsOf(const grpc::ServerContext& context) {
  Credentials credentials;
  credentials.peer = context.peer();
  const auto headers = context.client_metadata().equal_range("authorization");
  for (auto header = headers.first; header != headers.second; ++header) {
    credentials.authorization.emplace_back(header->second.data(), header->second.size());
  }
  credentials.certificate_names = CertificateNames(context);
  return credentials;
}

const char* DenyReasonLabel(DenyReason reason) {
  switch (reason) {
    case DenyReason::kMissingCredentials:
      return "missing_credentials";
    case DenyReason::kMalformedCredentials:
      return "malformed_credentials";
    case DenyReason::kUnknownToken:
      return "unknown_token";
    case DenyReason::kUnknownCertificate:
      return "unknown_certificate";
    case DenyReason::kPermissionDenied:
      return "permission_denied";
  }
  return "unknown";
}

bool Caller::Has(Right right, const std::string& map) const {
  if (everything) return true;
  if (!principal) return false;
  switch (right) {
    case Right::kAny:
      return true;
    case Right::kRead:
      return principal->MayRead(map);
    case Right::kWrite:
      return principal->MayWrite(map);
    case Right::kAdmin:
      return principal->admin;
  }
  return false;
}

CallAuthorizer::CallAuthorizer(const TokenStore* store, bool mutual_tls, DeniedCallback on_denied)
    : store_(store), mutual_tls_(mutual_tls), on_denied_(std::move(on_denied)) {}

grpc::Status CallAuthorizer::Deny(const char* method, const std::string& peer,
                                  const std::string& principal, const std::string& map,
                                  DenyReason reason, const std::string& message) const {
  // The principal can be a client certificate's name; the map comes from the request, unchecked.
  spdlog::warn("auth denied method={} principal={} peer={} map={} reason={}", method,
               principal.empty() ? kAnonymous : ForLog(principal), ForLog(peer),
               map.empty() ? "-" : ForLog(map), DenyReasonLabel(reason));
  if (on_denied_) on_denied_(reason, method);
  return grpc::Status(reason == DenyReason::kPermissionDenied ? grpc::StatusCode::PERMISSION_DENIED
                                                              : grpc::StatusCode::UNAUTHENTICATED,
                      std::string(method) + ": " + message);
}

std::variant<Caller, grpc::Status> CallAuthorizer::Resolve(
    const char* method, const std::string& peer, const std::string& previous,
    const std::string& map, std::string token, std::vector<std::string> certificate_names,
    bool by_token) const {
  Caller caller;
  // The generation before the snapshot: if a reload comes between them, the caller looks older
  // than its snapshot and is merely resolved again.
  caller.generation = store_->generation();
  caller.tokens = store_->snapshot();
  if (by_token) {
    caller.principal = caller.tokens->FindByToken(token);
    if (!caller.principal) {
      return Deny(method, peer, previous, map, DenyReason::kUnknownToken, "unknown token");
    }
  } else {
    caller.principal = caller.tokens->FindByCertificateNames(certificate_names);
    if (!caller.principal) {
      return Deny(method, peer, previous, map, DenyReason::kUnknownCertificate,
                  "client certificate '" + certificate_names.front() + "' names no principal");
    }
  }
  caller.name = caller.principal->name;
  caller.token = std::move(token);
  caller.certificate_names = std::move(certificate_names);
  return caller;
}

std::variant<Caller, grpc::Status> CallAuthorizer::Authenticate(
    const char* method, const grpc::ServerContext& context) const {
  if (!enabled()) return Caller::Everything(kAnonymous);
  return Authenticate(method, CredentialsOf(context));
}

std::variant<Caller, grpc::Status> CallAuthorizer::Authenticate(
    const char* method, const Credentials& credentials) const {
  if (!enabled()) return Caller::Everything(kAnonymous);
  const std::string& peer = credentials.peer;
  const size_t header_count = credentials.authorization.size();

  if (store_ && header_count > 0) {
    if (header_count > 1) {
      return Deny(method, peer, "", "", DenyReason::kMalformedCredentials,
                  "more than one authorization header");
    }
    std::optional<std::string> token = BearerToken(credentials.authorization.front());
    if (!token) {
      return Deny(method, peer, "", "", DenyReason::kMalformedCredentials,
                  "malformed authorization header (expected 'Bearer <token>')");
    }
    return Resolve(method, peer, "", "", std::move(*token), {}, true);
  }
  // Only without a bearer header: a token always wins over the certificate.
  std::vector<std::string> names = credentials.certificate_names;
  if (!names.empty()) {
    if (store_) return Resolve(method, peer, "", "", "", std::move(names), false);
    // Mutual TLS without a tokens file: the client CA vouches for every certificate holder.
    Caller caller = Caller::Everything(names.front());
    caller.certificate_names = std::move(names);
    return caller;
  }
  return Deny(method, peer, "", "", DenyReason::kMissingCredentials,
              store_ ? "no credentials (send 'authorization: Bearer <token>')"
                     : "no credentials (present a client certificate)");
}

grpc::Status CallAuthorizer::Authorize(const char* method, const grpc::ServerContext& context,
                                       const Caller& caller, Right right,
                                       const std::string& map) const {
  if (caller.Has(right, map)) return grpc::Status::OK;  // no peer() for the common case
  return Authorize(method, context.peer(), caller, right, map);
}

grpc::Status CallAuthorizer::Authorize(const char* method, const std::string& peer,
                                       const Caller& caller, Right right,
                                       const std::string& map) const {
  if (caller.Has(right, map)) return grpc::Status::OK;
  const std::string message =
      right == Right::kAdmin
          ? "principal '" + caller.name + "' is not an admin" +
                (map.empty() ? std::string() : " (map '" + map + "')")
          : "principal '" + caller.name + "' may not " + Verb(right) + " map '" + map + "'";
  return Deny(method, peer, caller.name, map, DenyReason::kPermissionDenied, message);
}

grpc::Status CallAuthorizer::Refresh(const char* method, const grpc::ServerContext& context,
                                     const std::string& map, Caller* caller) const {
  if (!store_ || caller->everything || store_->generation() == caller->generation) {
    return grpc::Status::OK;
  }
  const bool by_token = !caller->token.empty();
  auto resolved = Resolve(method, context.peer(), caller->name, map, caller->token,
                          caller->certificate_names, by_token);
  if (auto* status = std::get_if<grpc::Status>(&resolved)) return *status;
  *caller = std::move(std::get<Caller>(resolved));
  return grpc::Status::OK;
}

bool CallAuthorizer::AuthorizeScrape(const std::string& peer, const std::string& user,
                                     const std::string& password) const {
  if (!store_) return true;
  const std::shared_ptr<const TokensFile> tokens = store_->snapshot();
  const Principal* principal = password.empty() ? nullptr : tokens->FindByToken(password);
  DenyReason reason = DenyReason::kPermissionDenied;
  if (password.empty()) {
    reason = DenyReason::kMissingCredentials;
  } else if (!principal || principal->name != user) {
    reason = DenyReason::kUnknownToken;
  } else if (principal->MayScrapeMetrics()) {
    return true;
  }
  // The user name is the client's claim: logged only when it matched the token.
  (void)Deny("metrics", peer, principal && principal->name == user ? user : "", "", reason,
             "not allowed");
  return false;
}

}  // namespace placedb::server::auth
