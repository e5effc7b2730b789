// Certificates for TLS tests, made at test time with the `openssl` CLI (EC P-256 keys, valid two
// days) in a fresh temp directory: nothing is checked in.
//
//   const testing::TestCertificates& certs = testing::SharedTestCertificates();
//   config.tls = {.cert_file = certs.server_cert, .key_file = certs.server_key,
//                 .client_ca_file = certs.ca_cert};                      // mutual TLS
//   client::ConnectionOptions o{.tls = true, .ca_cert = certs.ca_cert,
//                               .cert = certs.client_cert, .key = certs.client_key};
//   auto robot9 = testing::IssueClientCertificate(certs, "robot-9", "robot-9.fleet.internal");
//
// Connect to "localhost:PORT" or "127.0.0.1:PORT": the server certificate names both.
#pragma once

#include <string>
#include <vector>

namespace placedb::testing {

// Paths of PEM files (keys unencrypted).
struct TestCertificates {
  std::string dir;
  std::string ca_cert, ca_key;  // "placedb test CA" (self-signed)
  // CN localhost, SANs DNS:localhost and IP:127.0.0.1, signed by the CA; serverAuth.
  std::string server_cert, server_key;
  // CN robot-8.fleet.internal, SANs DNS:robot-8.fleet.internal and URI:spiffe://fleet/robot-8,
  // signed by the CA; clientAuth.
  std::string client_cert, client_key;
  // A cluster node's certificate (cluster.internal_tls: one certificate for both ends of every
  // internal hop): CN placedb-node, SANs DNS:localhost and IP:127.0.0.1..127.0.0.9, signed by
  // the CA; serverAuth and clientAuth.
  std::string node_cert, node_key;
  // An unrelated CA ("other test CA"), and a client certificate it signed with the same CN as
  // client_cert: a good name from the wrong CA.
  std::string other_ca_cert, other_ca_key;
  std::string other_client_cert, other_client_key;
  // A file that is not PEM, and the server certificate concatenated with a foreign key (the CA's):
  // for startup-error cases.
  std::string not_pem;
};

// Makes every file above in a new temp directory (removed at process exit). Fails the running
// test (ADD_FAILURE, with openssl's output) and returns what it made so far when openssl fails.
TestCertificates MakeTestCertificates();
// MakeTestCertificates() once per process.
const TestCertificates& SharedTestCertificates();

// A further client certificate signed by `certs`'s CA (clientAuth): files <name>.pem and
// <name>.key in certs.dir; subject CN `common_name`, plus `dns_names` as DNS SANs. Returns
// {certificate, key} paths; fails the test when openssl fails.
std::pair<std::string, std::string> IssueClientCertificate(
    const TestCertificates& certs, const std::string& name, const std::string& common_name,
    const std::vector<std::string>& dns_names = {});

// A further node certificate (as node_cert: serverAuth + clientAuth, signed by `certs`'s CA):
// files <name>.pem and <name>.key in certs.dir; SANs node_cert's plus `addresses` (IPv4
// addresses become IP SANs, anything else DNS SANs). Returns {certificate, key} paths.
std::pair<std::string, std::string> IssueNodeCertificate(const TestCertificates& certs,
                                                         const std::string& name,
                                                         const std::vector<std::string>& addresses);

// Runs `command` through /bin/sh with stdout+stderr captured; returns its exit status
// (-1 when it could not run) and sets *output.
int RunShell(const std::string& command, std::string* output);

}  // namespace placedb::testing
