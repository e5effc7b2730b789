#include "tests/tls_certificates.h"

#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cstdio>
#include <fstream>

#include "tests/test_support.h"

namespace placedb::testing {

namespace {

// The extensions of each kind of certificate (openssl's -extfile / -extensions).
constexpr char kExtensions[] = R"([req]
distinguished_name = dn
prompt = no
[dn]
CN = unused
[ca]
basicConstraints = critical,CA:TRUE
keyUsage = critical,keyCertSign,cRLSign
subjectKeyIdentifier = hash
[server]
basicConstraints = CA:FALSE
keyUsage = critical,digitalSignature
extendedKeyUsage = serverAuth
subjectAltName = DNS:localhost,IP:127.0.0.1
[client]
basicConstraints = CA:FALSE
keyUsage = critical,digitalSignature
extendedKeyUsage = clientAuth
subjectAltName = DNS:robot-8.fleet.internal,URI:spiffe://fleet/robot-8
[node]
basicConstraints = CA:FALSE
keyUsage = critical,digitalSignature,keyEncipherment
extendedKeyUsage = serverAuth,clientAuth
subjectAltName = @node_names
[node_names]
DNS.1 = localhost
)";

// node_cert's SANs besides DNS:localhost: the loopback addresses tests put engines on.
std::string NodeNames(const std::vector<std::string>& more) {
  std::string out;
  int ip = 0, dns = 1;
  for (int last = 1; last <= 9; ++last) {
    out += "IP." + std::to_string(++ip) + " = 127.0.0." + std::to_string(last) + "\n";
  }
  for (const std::string& name : more) {
    const bool is_ip = !name.empty() && name.find_first_not_of("0123456789.") == std::string::npos;
    out += is_ip ? "IP." + std::to_string(++ip) : "DNS." + std::to_string(++dns);
    out += " = " + name + "\n";
  }
  return out;
}

constexpr char kNewKey[] = "-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes";

std::string Quote(const std::string& text) {
  return "'" + text + "'";  // temp paths and test names: no quotes in them
}

bool Openssl(const std::string& arguments) {
  std::string output;
  const int status = RunShell("openssl " + arguments, &output);
  if (status != 0)
    ADD_FAILURE() << "openssl " << arguments << " failed (" << status << "):\n" << output;
  return status == 0;
}

// A key and a certificate for `subject`, signed by ca (ca_cert + ca_key) with the extensions of
// `section` in `config`.
bool Issue(const std::string& config, const std::string& section, const std::string& subject,
           const std::string& ca_cert, const std::string& ca_key, const std::string& cert,
           const std::string& key) {
  const std::string csr = cert + ".csr";
  return Openssl("req -new -config " + Quote(config) + " " + kNewKey + " -keyout " + Quote(key) +
                 " -out " + Quote(csr) + " -subj " + Quote(subject)) &&
         Openssl("x509 -req -in " + Quote(csr) + " -CA " + Quote(ca_cert) + " -CAkey " +
                 Quote(ca_key) + " -CAcreateserial -days 2 -extfile " + Quote(config) +
                 " -extensions " + section + " -out " + Quote(cert));
}

bool MakeCa(const std::string& config, const std::string& subject, const std::string& cert,
            const std::string& key) {
  return Openssl("req -x509 -config " + Quote(config) + " -extensions ca " + kNewKey + " -keyout " +
                 Quote(key) + " -out " + Quote(cert) + " -days 2 -subj " + Quote(subject));
}

}  // namespace

int RunShell(const std::string& command, std::string* output) {
  output->clear();
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (!pipe) return -1;
  char buffer[4096];
  size_t got;
  while ((got = fread(buffer, 1, sizeof buffer, pipe)) > 0) output->append(buffer, got);
  const int status = pclose(pipe);
  if (status == -1 || !WIFEXITED(status)) return -1;
  return WEXITSTATUS(status);
}

TestCertificates MakeTestCertificates() {
  TestCertificates c;
  c.dir = MakeTempDir("placedb-certs");
  const std::string config = c.dir + "/openssl.cnf";
  std::ofstream(config) << kExtensions << NodeNames({});
  auto path = [&](const char* name) { return c.dir + "/" + name; };
  c.ca_cert = path("ca.pem");
  c.ca_key = path("ca.key");
  c.server_cert = path("server.pem");
  c.server_key = path("server.key");
  c.client_cert = path("client.pem");
  c.client_key = path("client.key");
  c.node_cert = path("node.pem");
  c.node_key = path("node.key");
  c.other_ca_cert = path("other-ca.pem");
  c.other_ca_key = path("other-ca.key");
  c.other_client_cert = path("other-client.pem");
  c.other_client_key = path("other-client.key");
  c.not_pem = path("not-pem.txt");
  std::ofstream(c.not_pem) << "this is not a PEM file\n";
  MakeCa(config, "/CN=placedb test CA", c.ca_cert, c.ca_key) &&
      Issue(config, "server", "/CN=localhost", c.ca_cert, c.ca_key, c.server_cert, c.server_key) &&
      Issue(config, "client", "/CN=robot-8.fleet.internal", c.ca_cert, c.ca_key, c.client_cert,
            c.client_key) &&
      Issue(config, "node", "/CN=placedb-node", c.ca_cert, c.ca_key, c.node_cert, c.node_key) &&
      MakeCa(config, "/CN=other test CA", c.other_ca_cert, c.other_ca_key) &&
      Issue(config, "client", "/CN=robot-8.fleet.internal", c.other_ca_cert, c.other_ca_key,
            c.other_client_cert, c.other_client_key);
  return c;
}

const TestCertificates& SharedTestCertificates() {
  static const TestCertificates certificates = MakeTestCertificates();
  return certificates;
}

std::pair<std::string, std::string> IssueClientCertificate(
    const TestCertificates& certs, const std::string& name, const std::string& common_name,
    const std::vector<std::string>& dns_names) {
  const std::string config = certs.dir + "/" + name + ".cnf";
  std::string alt;
  for (const std::string& dns : dns_names) alt += (alt.empty() ? "DNS:" : ",DNS:") + dns;
  std::ofstream(config) << "[req]\ndistinguished_name = dn\nprompt = no\n[dn]\nCN = unused\n"
                        << "[client]\nbasicConstraints = CA:FALSE\n"
                        << "keyUsage = critical,digitalSignature\nextendedKeyUsage = clientAuth\n"
                        << (alt.empty() ? "" : "subjectAltName = " + alt + "\n");
  const std::string cert = certs.dir + "/" + name + ".pem";
  const std::string key = certs.dir + "/" + name + ".key";
  Issue(config, "client", "/CN=" + common_name, certs.ca_cert, certs.ca_key, cert, key);
  return {cert, key};
}

std::pair<std::string, std::string> IssueNodeCertificate(
    const TestCertificates& certs, const std::string& name,
    const std::vector<std::string>& addresses) {
  const std::string config = certs.dir + "/" + name + ".cnf";
  std::ofstream(config) << kExtensions << NodeNames(addresses);
  const std::string cert = certs.dir + "/" + name + ".pem";
  const std::string key = certs.dir + "/" + name + ".key";
  Issue(config, "node", "/CN=placedb-node", certs.ca_cert, certs.ca_key, cert, key);
  return {cert, key};
}

}  // namespace placedb::testing
