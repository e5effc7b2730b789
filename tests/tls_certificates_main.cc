// placedb-test-certs OUT_DIR: writes tests/tls_certificates.h's certificates (ca.pem, ca.key,
// server.pem, server.key, client.pem, client.key, node.pem, node.key, other-ca.pem, other-ca.key,
// other-client.pem, other-client.key) into OUT_DIR, for tests in other languages (the Python
// SDK's TLS test) and scripts (bench/cluster_tls_overhead.sh).
// Exit status 0 when every file was made, 1 otherwise (openssl's output on stderr).
#include <filesystem>
#include <iostream>
#include <string>

#include "tests/tls_certificates.h"

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: placedb-test-certs OUT_DIR\n";
    return 2;
  }
  namespace fs = std::filesystem;
  const placedb::testing::TestCertificates certs = placedb::testing::MakeTestCertificates();
  const fs::path out = argv[1];
  std::error_code error;
  fs::create_directories(out, error);
  for (const std::string& file :
       {certs.ca_cert, certs.ca_key, certs.server_cert, certs.server_key, certs.client_cert,
        certs.client_key, certs.node_cert, certs.node_key, certs.other_ca_cert, certs.other_ca_key,
        certs.other_client_cert, certs.other_client_key}) {
    if (error || !fs::exists(file)) {
      std::cerr << "placedb-test-certs: " << file << " was not made\n";
      return 1;
    }
    fs::copy_file(file, out / fs::path(file).filename(), fs::copy_options::overwrite_existing,
                  error);
    if (error) {
      std::cerr << "placedb-test-certs: copying " << file << ": " << error.message() << "\n";
      return 1;
    }
  }
  return 0;
}
