#include "server/net/transport_security.h"

#include <arpa/inet.h>
#include <grpc/grpc_security_constants.h>
#include <grpcpp/security/auth_context.h>
#include <grpcpp/security/server_credentials.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cctype>
#include <utility>

#include "core/base/files.h"

namespace placedb::server {

namespace {

struct X509Free {
  void operator()(X509* x) const { X509_free(x); }
};
struct PkeyFree {
  void operator()(EVP_PKEY* k) const { EVP_PKEY_free(k); }
};
struct BioFree {
  void operator()(BIO* b) const { BIO_free(b); }
};
using X509Ptr = std::unique_ptr<X509, X509Free>;
using PkeyPtr = std::unique_ptr<EVP_PKEY, PkeyFree>;
using BioPtr = std::unique_ptr<BIO, BioFree>;

// OpenSSL would otherwise ask for an encrypted key's passphrase on the terminal.
int NoPassphrase(char*, int, int, void*) {
  return -1;
}

BioPtr MemoryBio(const std::string& text) {
  return BioPtr(BIO_new_mem_buf(text.data(), int(text.size())));
}

// Every PEM certificate of `pem`, in order (none when it holds none).
std::vector<X509Ptr> Certificates(const std::string& pem) {
  std::vector<X509Ptr> out;
  BioPtr bio = MemoryBio(pem);
  while (X509* cert = PEM_read_bio_X509(bio.get(), nullptr, NoPassphrase, nullptr)) {
    out.emplace_back(cert);
  }
  ERR_clear_error();  // the end of the input is reported as an error
  return out;
}

PkeyPtr PrivateKey(const std::string& pem) {
  BioPtr bio = MemoryBio(pem);
  PkeyPtr key(PEM_read_bio_PrivateKey(bio.get(), nullptr, NoPassphrase, nullptr));
  ERR_clear_error();
  return key;
}

std::string Where(const char* key, const std::string& path) {
  return std::string(key) + " (" + path + ")";
}

Result<std::string> ReadPem(const char* key, const std::string& path) {
  auto text = ReadWholeFile(path);
  if (!text.ok()) return text.status().WithContext(key);
  return text;
}

std::string Lower(std::string text) {
  for (char& c : text) c = char(std::tolower(static_cast<unsigned char>(c)));
  return text;
}

bool IsLoopbackHost(const std::string& host) {
  if (Lower(host) == "localhost") return true;
  in_addr v4{};
  if (inet_pton(AF_INET, host.c_str(), &v4) == 1) return (ntohl(v4.s_addr) >> 24) == 127;
  in6_addr v6{};
  if (inet_pton(AF_INET6, host.c_str(), &v6) == 1) {
    return IN6_IS_ADDR_LOOPBACK(&v6) || (IN6_IS_ADDR_V4MAPPED(&v6) && v6.s6_addr[12] == 127);
  }
  return false;
}

bool IsLoopbackEntry(const std::string& address) {
  if (address.rfind("unix:", 0) == 0 || address.rfind("unix-abstract:", 0) == 0) return true;
  if (!address.empty() && address[0] == '[') {
    const auto close = address.find(']');
    return close != std::string::npos && IsLoopbackHost(address.substr(1, close - 1));
  }
  const auto colon = address.rfind(':');
  // A bare port ("9464", "+9464") binds every interface.
  if (colon == std::string::npos) return false;
  return IsLoopbackHost(address.substr(0, colon));
}

}  // namespace

Result<TlsFiles> LoadTlsFiles(const TlsSettings& tls) {
  TlsFiles files;
  auto chain = ReadPem("tls.cert_file", tls.cert_file);
  if (!chain.ok()) return chain.status();
  files.cert_chain = std::move(*chain);
  const std::vector<X509Ptr> certificates = Certificates(files.cert_chain);
  if (certificates.empty()) {
    return Status::InvalidArgument(Where("tls.cert_file", tls.cert_file) +
                                   ": no PEM certificate in it");
  }
  auto key_text = ReadPem("tls.key_file", tls.key_file);
  if (!key_text.ok()) return key_text.status();
  files.private_key = std::move(*key_text);
  const PkeyPtr key = PrivateKey(files.private_key);
  if (!key) {
    // Never the file's bytes: only what is wrong with it.
    const bool encrypted = files.private_key.find("ENCRYPTED") != std::string::npos;
    return Status::InvalidArgument(
        Where("tls.key_file", tls.key_file) +
        (encrypted ? ": the key is encrypted (a passphrase-protected key cannot be used)"
                   : ": not a PEM private key"));
  }
  if (X509_check_private_key(certificates.front().get(), key.get()) != 1) {
    ERR_clear_error();
    return Status::InvalidArgument(Where("tls.key_file", tls.key_file) +
                                   ": the key does not belong to the certificate in " +
                                   Where("tls.cert_file", tls.cert_file));
  }
  if (tls.mutual()) {
    auto ca = ReadPem("tls.client_ca_file", tls.client_ca_file);
    if (!ca.ok()) return ca.status();
    files.client_ca = std::move(*ca);
    if (Certificates(files.client_ca).empty()) {
      return Status::InvalidArgument(Where("tls.client_ca_file", tls.client_ca_file) +
                                     ": no PEM certificate in it");
    }
  }
  return files;
}

Result<std::shared_ptr<grpc::ServerCredentials>> MakeServerCredentials(const TlsSettings& tls) {
  if (!tls.enabled()) return grpc::InsecureServerCredentials();
  auto files = LoadTlsFiles(tls);
  if (!files.ok()) return files.status();
  grpc::SslServerCredentialsOptions options(
      tls.mutual() ? GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY
                   : GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
  options.pem_root_certs = files->client_ca;
  options.pem_key_cert_pairs.push_back({files->private_key, files->cert_chain});
  return grpc::SslServerCredentials(options);
}

Status ConfigureSslContext(void* ssl_ctx, const TlsSettings& tls) {
  SSL_CTX* ctx = static_cast<SSL_CTX*>(ssl_ctx);
  auto files = LoadTlsFiles(tls);
  if (!files.ok()) return files.status();
  auto failed = [](const std::string& what) {
    ERR_clear_error();
    return Status::Internal("metrics TLS: " + what);
  };
  if (SSL_CTX_set_min_proto_version(ctx, TLS1_2_VERSION) != 1) {
    return failed("cannot require TLS 1.2");
  }
  std::vector<X509Ptr> chain = Certificates(files->cert_chain);
  if (SSL_CTX_use_certificate(ctx, chain.front().get()) != 1) {
    return failed("cannot use " + Where("tls.cert_file", tls.cert_file));
  }
  for (size_t i = 1; i < chain.size(); ++i) {
    if (SSL_CTX_add1_chain_cert(ctx, chain[i].get()) != 1) {
      return failed("cannot use the chain of " + Where("tls.cert_file", tls.cert_file));
    }
  }
  const PkeyPtr key = PrivateKey(files->private_key);
  if (SSL_CTX_use_PrivateKey(ctx, key.get()) != 1 || SSL_CTX_check_private_key(ctx) != 1) {
    return failed("cannot use " + Where("tls.key_file", tls.key_file));
  }
  if (tls.mutual()) {
    X509_STORE* store = SSL_CTX_get_cert_store(ctx);
    for (const X509Ptr& ca : Certificates(files->client_ca)) {
      if (X509_STORE_add_cert(store, ca.get()) != 1 || SSL_CTX_add_client_CA(ctx, ca.get()) != 1) {
        return failed("cannot use " + Where("tls.client_ca_file", tls.client_ca_file));
      }
    }
    // No certificate, or one that does not verify: the handshake fails.
    SSL_CTX_set_verify(ctx, SSL_VERIFY_PEER | SSL_VERIFY_FAIL_IF_NO_PEER_CERT, nullptr);
    // A client resuming a session (curl does) is refused with an internal-error alert unless
    // the sessions carry a context when client certificates are verified.
    static constexpr unsigned char kSessionContext[] = "placedb-metrics";
    if (SSL_CTX_set_session_id_context(ctx, kSessionContext, sizeof kSessionContext - 1) != 1) {
      return failed("cannot set the session context");
    }
  }
  return Status::Ok();
}

std::string DescribeTransport(const TlsSettings& tls) {
  if (!tls.enabled()) return "plaintext";
  std::string text = "TLS 1.2+ (certificate " + tls.cert_file + ")";
  if (tls.mutual()) {
    text = "mutual " + text + ", client certificates required, CAs " + tls.client_ca_file;
  }
  return text;
}

std::vector<std::string> PeerCertificateNames(const grpc::AuthContext& context) {
  std::vector<std::string> names;
  for (const char* property :
       {GRPC_X509_CN_PROPERTY_NAME, GRPC_PEER_DNS_PROPERTY_NAME, GRPC_PEER_URI_PROPERTY_NAME}) {
    for (const grpc::string_ref& value : context.FindPropertyValues(property)) {
      std::string name(value.data(), value.size());
      if (!name.empty() && std::find(names.begin(), names.end(), name) == names.end()) {
        names.push_back(std::move(name));
      }
    }
  }
  return names;
}

std::vector<std::string> PeerCertificateNames(const void* ssl_connection) {
  const SSL* ssl = static_cast<const SSL*>(ssl_connection);
  std::vector<std::string> names;
  if (!ssl || SSL_get_verify_result(ssl) != X509_V_OK) return names;
  const X509Ptr certificate(SSL_get1_peer_certificate(ssl));
  if (!certificate) return names;
  auto add = [&names](const unsigned char* data, int length) {
    if (!data || length <= 0) return;
    std::string name(reinterpret_cast<const char*>(data), size_t(length));
    if (std::find(names.begin(), names.end(), name) == names.end())
      names.push_back(std::move(name));
  };
  // The subject's CN, then DNS and URI SANs: the order gRPC's auth context reports them in.
  const X509_NAME* subject = X509_get_subject_name(certificate.get());
  for (int i = -1; (i = X509_NAME_get_index_by_NID(subject, NID_commonName, i)) >= 0;) {
    const ASN1_STRING* cn = X509_NAME_ENTRY_get_data(X509_NAME_get_entry(subject, i));
    add(ASN1_STRING_get0_data(cn), ASN1_STRING_length(cn));
  }
  auto* sans = static_cast<GENERAL_NAMES*>(
      X509_get_ext_d2i(certificate.get(), NID_subject_alt_name, nullptr, nullptr));
  for (int type : {GEN_DNS, GEN_URI}) {
    for (int i = 0; sans && i < sk_GENERAL_NAME_num(sans); ++i) {
      const GENERAL_NAME* san = sk_GENERAL_NAME_value(sans, i);
      if (san->type != type) continue;
      const ASN1_IA5STRING* text =
          type == GEN_DNS ? san->d.dNSName : san->d.uniformResourceIdentifier;
      add(ASN1_STRING_get0_data(text), ASN1_STRING_length(text));
    }
  }
  GENERAL_NAMES_free(sans);
  return names;
}

bool IsLoopbackAddress(const std::string& address) {
  if (address.empty()) return false;
  size_t start = 0;
  for (;;) {
    const auto comma = address.find(',', start);
    if (!IsLoopbackEntry(address.substr(start, comma - start))) return false;
    if (comma == std::string::npos) return true;
    start = comma + 1;
  }
}

std::vector<std::string> CleartextTokenWarnings(const ServerConfig& config) {
  std::vector<std::string> warnings;
  if (config.security.tokens_file.empty()) return warnings;
  auto check = [&](const std::string& listen, bool tls, const char* what, const char* how) {
    if (listen.empty() || tls || IsLoopbackAddress(listen)) return;
    warnings.push_back(std::string(what) + " on " + listen + " takes " + how +
                       " over plaintext from other hosts: anyone on the network path can read "
                       "them and act as their principals");
  };
  check(config.listen, config.tls.enabled(), "gRPC", "bearer tokens");
  check(config.metrics_listen, config.metrics_tls, "metrics", "tokens (basic auth passwords)");
  check(config.console_listen, config.console_tls, "console", "bearer tokens");
  return warnings;
}

Status CheckExposure(const ServerConfig& config) {
  for (const std::string& warning : CleartextTokenWarnings(config)) {
    spdlog::warn(
        "SECURITY WARNING: {}. Configure tls.cert_file and tls.key_file (and "
        "metrics_tls / console_tls), or listen on loopback (docs/security.md)",
        warning);
  }
  // Metrics are authenticated by the tokens file (HTTP basic auth) or by client certificates
  // when they are served over mutual TLS; mutual TLS on the gRPC port alone leaves them open.
  const bool grpc_authenticated = config.authenticates_callers();
  const bool metrics_authenticated =
      !config.security.tokens_file.empty() || (config.metrics_tls && config.tls.mutual());
  std::vector<std::string> exposed;
  std::string risk;  // what anyone who reaches them could do
  if (!grpc_authenticated && !IsLoopbackAddress(config.listen)) {
    exposed.push_back("listen = " + config.listen);
    risk = "read, change and delete every map";
  }
  if (!config.metrics_listen.empty() && !metrics_authenticated &&
      !IsLoopbackAddress(config.metrics_listen)) {
    exposed.push_back("metrics_listen = " + config.metrics_listen);
    if (risk.empty()) risk = "read the metrics (map names, sizes, traffic)";
  }
  // The console is the gRPC API's read side over HTTP: the same callers may use it, so the same
  // rule (tokens, or client certificates required by console_tls with a client CA).
  const bool console_authenticated =
      !config.security.tokens_file.empty() || (config.console_tls && config.tls.mutual());
  if (!config.console_listen.empty() && !console_authenticated &&
      !IsLoopbackAddress(config.console_listen)) {
    exposed.push_back("console_listen = " + config.console_listen);
    if (risk.empty()) risk = "read and query every map";
  }
  std::string where;
  for (const std::string& e : exposed) where += (where.empty() ? "" : ", ") + e;
  if (exposed.empty()) {
    if (config.security.allow_unauthenticated_remote && !grpc_authenticated) {
      spdlog::warn(
          "SECURITY WARNING: security.allow_unauthenticated_remote is set: this server would "
          "accept unauthenticated callers from other hosts (it listens on loopback only now)");
    }
    if (!grpc_authenticated) {
      spdlog::info(
          "callers are not authenticated (no security.tokens_file, no tls.client_ca_file): "
          "serving on loopback only; configure tokens or mutual TLS to listen beyond it "
          "(docs/security.md)");
    }
    return Status::Ok();
  }
  if (!config.security.allow_unauthenticated_remote) {
    return Status::InvalidArgument(
        where +
        " accepts connections from other hosts, but callers are not authenticated (no "
        "security.tokens_file, no tls.client_ca_file; for metrics_listen, no tokens file and no "
        "metrics_tls with a client CA): anyone who reaches it could " +
        risk +
        ". Configure tokens or mutual TLS (docs/security.md), listen on loopback, or accept the "
        "risk with security.allow_unauthenticated_remote (--allow-unauthenticated-remote, "
        "PLACEDB_ALLOW_UNAUTHENTICATED_REMOTE=1)");
  }
  spdlog::warn(
      "SECURITY WARNING: {} accepts connections from other hosts WITHOUT AUTHENTICATION "
      "(security.allow_unauthenticated_remote is set): anyone who reaches it can {}",
      where, risk);
  return Status::Ok();
}

}  // namespace placedb::server
