// The tokens file (docs/security.md, "Principals, tokens and rights"): who may call the server
// and what each caller may do. No gRPC here: the server's enforcement (server/auth/call_auth.h)
// and the `placedb-server tokens` command both build on it.
//
//   principals:
//     - name: robot-7                 # 1-64 of [A-Za-z0-9_.@-]
//       token_sha256: 2c26b4...       # 64 lowercase hex: SHA-256 of the token's UTF-8 bytes
//       admin: false                  # create/delete/recover/scrub maps; implies everything
//       metrics: false                # may scrape /metrics (HTTP basic auth)
//       maps: {"warehouse-*": [read, write], "campus": [read]}
//       certificate_names: [robot-7.fleet.internal]   # mTLS: the certificate's CN or a SAN
//
// Only hashes are stored: a token is `pdb_` + base64url(32 random bytes), a 256-bit secret that
// needs no slow hash.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/base/status.h"

namespace placedb::server::auth {

// Rights on the maps a pattern matches.
struct MapGrant {
  std::string pattern;  // map-name characters, '*' = any run of them (possibly empty)
  bool read = false;
  bool write = false;
};

struct Principal {
  std::string name;
  std::string token_sha256;  // 64 lowercase hex, or "" (certificate-only principal)
  std::vector<std::string> certificate_names;
  bool admin = false;
  bool metrics = false;
  std::vector<MapGrant> maps;

  // Admin may do everything; otherwise a grant whose pattern matches `map` must give the right.
  bool MayRead(const std::string& map) const;
  bool MayWrite(const std::string& map) const;
  bool MayScrapeMetrics() const { return admin || metrics; }
  // "admin", "metrics", "read warehouse-*", "write warehouse-*", ...; for `tokens list`, logs.
  std::string DescribeRights() const;
};

// True when `name` matches `pattern` ('*' = any run of characters, possibly empty).
bool PatternMatches(const std::string& pattern, const std::string& name);

// "" when valid, else why not: 1-64 of [A-Za-z0-9_.@-].
std::string PrincipalNameProblem(const std::string& name);
// "" when valid, else why not: 1-128 of the map-name characters [A-Za-z0-9_.-] and '*'.
std::string PatternProblem(const std::string& pattern);

// SHA-256 of the token's bytes as 64 lowercase hex digits (OpenSSL EVP).
std::string HashToken(const std::string& token);
// "pdb_" + base64url (no padding) of 32 bytes from the OS's CSPRNG (OpenSSL RAND_bytes).
// INTERNAL when the generator fails.
Result<std::string> GenerateToken();

// One loaded tokens file. Immutable once parsed; copy it to change it (the tokens command).
class TokensFile {
 public:
  // Parses and validates a whole file. INVALID_ARGUMENT naming `origin`, the entry
  // (principals[2] 'robot-7') and the key for: bad YAML, unknown keys, bad names, bad hex,
  // duplicate names / hashes / certificate names, unknown rights, bad patterns, a principal with
  // neither token_sha256 nor certificate_names.
  static Result<TokensFile> Parse(const std::string& text, const std::string& origin);
  // Reads and parses the file at `path` (NOT_FOUND / IO_ERROR when it cannot be read).
  static Result<TokensFile> Load(const std::string& path);

  // The file's YAML (round-trips through Parse).
  std::string Serialize() const;
  // Writes Serialize() to `path` atomically (temp file, fsync, rename, directory fsync), mode
  // 0600. On failure the file at `path` is unchanged.
  Status Save(const std::string& path) const;

  const std::vector<Principal>& principals() const { return principals_; }
  // Adds a principal after validating it against the others (same errors as Parse).
  Status Add(Principal principal);
  // Removes the principal named `name`; NOT_FOUND if there is none.
  Status Remove(const std::string& name);
  // The principal named `name`, or null.
  const Principal* Find(const std::string& name) const;

  // The principal whose token_sha256 is the token's SHA-256, or null. Constant time in the
  // matching entry's position: the digest is compared (CRYPTO_memcmp) with every entry's.
  const Principal* FindByToken(const std::string& token) const;
  // The first principal (in file order) listing one of `names` in certificate_names, or null.
  const Principal* FindByCertificateNames(const std::vector<std::string>& names) const;

 private:
  Status Validate(const Principal& principal, size_t index) const;

  std::vector<Principal> principals_;
  std::vector<std::array<uint8_t, 32>> digests_;  // token_sha256 as bytes, per principal
  std::vector<bool> has_digest_;
};

}  // namespace placedb::server::auth
