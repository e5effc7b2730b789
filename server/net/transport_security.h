// Transport security of the server (docs/security.md): TLS / mutual TLS on the gRPC port and on
// /metrics from the PEM files of TlsSettings, the certificate names of a caller, and the
// loopback-only safe default for servers that do not authenticate their callers.
//
// Nothing here keeps state: each function reads the files it is given when it is called.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "server/config.h"

namespace grpc {
class AuthContext;
class ServerCredentials;
}  // namespace grpc

namespace placedb::server {

// The PEM texts of TlsSettings, checked: at least one certificate in cert_file, an unencrypted
// private key in key_file that belongs to cert_file's first certificate, and (mutual TLS) at
// least one certificate in client_ca_file.
struct TlsFiles {
  std::string cert_chain;  // cert_file as read
  std::string private_key;
  std::string client_ca;  // empty without mutual TLS
};
// Errors name the config key and the file, never the key's bytes: NOT_FOUND (missing file),
// IO_ERROR (unreadable), INVALID_ARGUMENT (not PEM, no certificate, encrypted key, key not
// matching the certificate).
Result<TlsFiles> LoadTlsFiles(const TlsSettings& tls);

// The gRPC port's credentials: insecure when !tls.enabled(); otherwise TLS 1.2 or later (gRPC's
// own minimum for SslServerCredentials, which Debian's gRPC 1.51 cannot raise or lower through
// the C++ API), and with tls.mutual() a client certificate signed by one of client_ca_file's
// CAs is required and verified at the handshake. Errors as LoadTlsFiles.
Result<std::shared_ptr<grpc::ServerCredentials>> MakeServerCredentials(const TlsSettings& tls);

// Sets up an OpenSSL SSL_CTX (passed as void* so that this header needs no OpenSSL) for HTTPS
// with tls's files: TLS 1.2 or later, the certificate chain and key, and with tls.mutual() a
// client certificate that must be presented and verify against client_ca_file. Errors as
// LoadTlsFiles; on failure the context is left partly configured (the caller discards it).
Status ConfigureSslContext(void* ssl_ctx, const TlsSettings& tls);

// "plaintext", "TLS" or "mutual TLS", with the files: for the start-up log line.
std::string DescribeTransport(const TlsSettings& tls);

// The names a mutual-TLS caller's certificate gives it: its subject CN, then its DNS and URI
// SANs, as gRPC's auth context reports them (no duplicates; empty for a plaintext or
// certificate-less caller). The tokens file's `certificate_names` match against these.
std::vector<std::string> PeerCertificateNames(const grpc::AuthContext& context);
// The same names of an HTTPS connection's verified client certificate (`ssl`: its OpenSSL SSL*,
// as void* so that this header needs no OpenSSL; null or no verified certificate: empty).
std::vector<std::string> PeerCertificateNames(const void* ssl);

// True when a listen address only accepts connections from this machine: an IPv4 address in
// 127.0.0.0/8, ::1 (or ::ffff:127.x.y.z), "localhost", or a unix: socket. Anything else (0.0.0.0,
// [::], a bare port, another host name) is not. `address` is host:port, [v6]:port or unix:path;
// a comma-separated list is loopback when every entry is.
bool IsLoopbackAddress(const std::string& address);

// The safe default (docs/security.md, "Safe defaults"): a server that does not authenticate its
// callers (no tokens file, no mutual TLS) listens on loopback only; so do plaintext metrics
// without a tokens file (mutual TLS on the gRPC port does not cover them, metrics_tls with a
// client CA does). Otherwise INVALID_ARGUMENT naming the address and
// security.allow_unauthenticated_remote / --allow-unauthenticated-remote, unless that option is
// set: then a warning is logged (every start with the option set and no authentication). Logs
// one info line when the server stays on loopback for this reason.
Status CheckExposure(const ServerConfig& config);

// With a tokens file, the listeners that carry tokens in clear text to other hosts: gRPC without
// TLS, metrics without metrics_tls (basic auth's password is a token), the console without
// console_tls, each on a non-loopback address. One sentence per listener ("gRPC on
// 0.0.0.0:50051 takes bearer tokens over plaintext ..."); empty when there is none.
// CheckExposure logs each as a SECURITY WARNING, and Server::Start repeats them in its startup
// summary (finding 8 of issue 34: such a server used to start without a word).
std::vector<std::string> CleartextTokenWarnings(const ServerConfig& config);

}  // namespace placedb::server
