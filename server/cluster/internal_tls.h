// Mutual TLS on cluster mode's internal hops (cluster.internal_tls, docs/cluster.md): the shard's
// internal API (placedb.cluster.v1.Shard) and its callers (workers, shards fetching checkpoints),
// and the NATS and etcd client connections. Every hop uses the public API's files: tls.cert_file
// + tls.key_file are this process's certificate, as a server and as a client (so it needs both
// serverAuth and clientAuth, or no extended key usage, and SANs for the address peers dial),
// and tls.client_ca_file (or cluster.internal_ca_file) is the bundle every peer's certificate
// must verify against.
#pragma once

#include <memory>
#include <string>

#include "core/base/status.h"
#include "server/config.h"

namespace grpc {
class ChannelCredentials;
class ServerCredentials;
}  // namespace grpc

namespace placedb::cluster {

// The PEM texts (read once at startup: a process keeps its certificate until restarted).
// !enabled(): every hop in plain text, as before cluster.internal_tls.
struct InternalTls {
  std::string cert_chain;   // this process's certificate (and chain)
  std::string private_key;  // its key
  std::string ca;           // the CAs peers must be signed by

  bool enabled() const { return !ca.empty(); }
};

// Reads and checks tls's files (server/net/transport_security.h's LoadTlsFiles), with `ca_file`
// as the CA bundle (cluster.internal_ca_file; empty: tls.client_ca_file): errors name the key
// and file. INVALID_ARGUMENT when a file is not set.
Result<InternalTls> LoadInternalTls(const server::TlsSettings& tls,
                                    const std::string& ca_file = "");

// A client's credentials for the shard's internal API and etcd: TLS verifying the server's
// certificate (chain to `ca`, name = the dialled host) and presenting ours. Insecure when
// !tls.enabled().
std::shared_ptr<grpc::ChannelCredentials> InternalChannelCredentials(const InternalTls& tls);

// The shard's internal API: TLS that requires a client certificate signed by `ca` (a client
// without one fails the handshake). Insecure when !tls.enabled().
std::shared_ptr<grpc::ServerCredentials> InternalServerCredentials(const InternalTls& tls);

}  // namespace placedb::cluster
