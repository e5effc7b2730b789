#include "server/cluster/internal_tls.h"

#include <grpc/grpc_security_constants.h>
#include <grpcpp/security/credentials.h>
#include <grpcpp/security/server_credentials.h>

#include "server/net/transport_security.h"

namespace placedb::cluster {

Result<InternalTls> LoadInternalTls(const server::TlsSettings& public_tls,
                                    const std::string& ca_file) {
  server::TlsSettings tls = public_tls;
  if (!ca_file.empty()) tls.client_ca_file = ca_file;
  for (const auto& [key, value] :
       {std::pair<const char*, const std::string*>{"tls.cert_file", &tls.cert_file},
        {"tls.key_file", &tls.key_file},
        {"tls.client_ca_file", &tls.client_ca_file}}) {
    if (value->empty()) {
      return Status::InvalidArgument(std::string("cluster.internal_tls needs ") + key +
                                     " (tls.cert_file, tls.key_file, and a CA bundle that "
                                     "verifies every peer)");
    }
  }
  // Errors name tls.client_ca_file also for cluster.internal_ca_file: the path says which.
  auto files = server::LoadTlsFiles(tls);
  if (!files.ok()) return files.status().WithContext("cluster.internal_tls");
  InternalTls out;
  out.cert_chain = std::move(files->cert_chain);
  out.private_key = std::move(files->private_key);
  out.ca = std::move(files->client_ca);
  return out;
}

std::shared_ptr<grpc::ChannelCredentials> InternalChannelCredentials(const InternalTls& tls) {
  if (!tls.enabled()) return grpc::InsecureChannelCredentials();
  grpc::SslCredentialsOptions options;
  options.pem_root_certs = tls.ca;
  options.pem_private_key = tls.private_key;
  options.pem_cert_chain = tls.cert_chain;
  return grpc::SslCredentials(options);
}

std::shared_ptr<grpc::ServerCredentials> InternalServerCredentials(const InternalTls& tls) {
  if (!tls.enabled()) return grpc::InsecureServerCredentials();
  grpc::SslServerCredentialsOptions options(
      GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
  options.pem_root_certs = tls.ca;
  options.pem_key_cert_pairs.push_back({tls.private_key, tls.cert_chain});
  return grpc::SslServerCredentials(options);
}

}  // namespace placedb::cluster
