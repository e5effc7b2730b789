#include "server/auth/tokens.h"

#include <fcntl.h>
#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/rand.h>
#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <set>

#include "core/base/files.h"

namespace placedb::server::auth {

namespace {

bool NameChar(char c) {
  return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '.' || c == '-';
}

bool HexDigit(char c) {
  return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f');
}

bool ParseDigest(const std::string& hex, std::array<uint8_t, 32>* out) {
  if (hex.size() != 64) return false;
  for (size_t i = 0; i < 32; ++i) {
    auto nibble = [](char c) { return c <= '9' ? c - '0' : c - 'a' + 10; };
    if (!HexDigit(hex[2 * i]) || !HexDigit(hex[2 * i + 1])) return false;
    (*out)[i] = uint8_t(nibble(hex[2 * i]) << 4 | nibble(hex[2 * i + 1]));
  }
  return true;
}

std::array<uint8_t, 32> Sha256(const std::string& bytes) {
  std::array<uint8_t, 32> digest{};
  unsigned int length = 0;
  EVP_Digest(bytes.data(), bytes.size(), digest.data(), &length, EVP_sha256(), nullptr);
  return digest;
}

std::string Entry(size_t index, const std::string& name) {
  std::string entry = "principals[" + std::to_string(index) + "]";
  if (!name.empty()) entry += " '" + name + "'";
  return entry;
}

std::string Errno(const std::string& what, const std::string& path) {
  return what + " " + path + ": " + std::strerror(errno);
}

Status WriteAll(int fd, const std::string& bytes, const std::string& path) {
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t put = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (put < 0 && errno == EINTR) continue;
    if (put < 0) return Status::IoError(Errno("cannot write", path));
    done += size_t(put);
  }
  return Status::Ok();
}

}  // namespace

bool Principal::MayRead(const std::string& map) const {
  if (admin) return true;
  for (const MapGrant& grant : maps) {
    if (grant.read && PatternMatches(grant.pattern, map)) return true;
  }
  return false;
}

bool Principal::MayWrite(const std::string& map) const {
  if (admin) return true;
  for (const MapGrant& grant : maps) {
    if (grant.write && PatternMatches(grant.pattern, map)) return true;
  }
  return false;
}

std::string Principal::DescribeRights() const {
  std::string out;
  auto add = [&out](const std::string& what) {
    if (!out.empty()) out += ", ";
    out += what;
  };
  if (admin) add("admin");
  if (metrics) add("metrics");
  for (const MapGrant& grant : maps) {
    if (grant.read) add("read " + grant.pattern);
    if (grant.write) add("write " + grant.pattern);
  }
  return out.empty() ? "none" : out;
}

bool PatternMatches(const std::string& pattern, const std::string& name) {
  // Glob with '*' only: greedy with backtracking to the last star (linear in practice).
  size_t p = 0, n = 0, star = std::string::npos, resume = 0;
  while (n < name.size()) {
    if (p < pattern.size() && pattern[p] == '*') {
      star = p++;
      resume = n;
    } else if (p < pattern.size() && pattern[p] == name[n]) {
      ++p, ++n;
    } else if (star != std::string::npos) {
      p = star + 1;
      n = ++resume;
    } else {
      return false;
    }
  }
  while (p < pattern.size() && pattern[p] == '*') ++p;
  return p == pattern.size();
}

std::string PrincipalNameProblem(const std::string& name) {
  if (name.empty() || name.size() > 64) {
    return "must be 1-64 characters, got " + std::to_string(name.size());
  }
  for (char c : name) {
    if (!NameChar(c) && c != '@') return "may only hold letters, digits, '_', '.', '@' and '-'";
  }
  return "";
}

std::string PatternProblem(const std::string& pattern) {
  if (pattern.empty() || pattern.size() > 128) {
    return "must be 1-128 characters, got " + std::to_string(pattern.size());
  }
  for (char c : pattern) {
    if (!NameChar(c) && c != '*') {
      return "may only hold map-name characters (letters, digits, '_', '.', '-') and '*'";
    }
  }
  return "";
}

std::string HashToken(const std::string& token) {
  static constexpr char kHex[] = "0123456789abcdef";
  const std::array<uint8_t, 32> digest = Sha256(token);
  std::string hex(64, '0');
  for (size_t i = 0; i < 32; ++i) {
    hex[2 * i] = kHex[digest[i] >> 4];
    hex[2 * i + 1] = kHex[digest[i] & 15];
  }
  return hex;
}

Result<std::string> GenerateToken() {
  static constexpr char kAlphabet[] =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_";
  std::array<uint8_t, 32> bytes{};
  if (RAND_bytes(bytes.data(), int(bytes.size())) != 1) {
    return Status::Internal("the random generator failed (OpenSSL RAND_bytes)");
  }
  std::string token = "pdb_";
  uint32_t buffer = 0;
  int bits = 0;
  for (uint8_t byte : bytes) {
    buffer = (buffer << 8) | byte;
    bits += 8;
    while (bits >= 6) {
      bits -= 6;
      token += kAlphabet[(buffer >> bits) & 63];
    }
  }
  if (bits > 0) token += kAlphabet[(buffer << (6 - bits)) & 63];
  OPENSSL_cleanse(bytes.data(), bytes.size());
  return token;
}

// ---- TokensFile ---------------------------------------------------------------------------------

Status TokensFile::Validate(const Principal& p, size_t index) const {
  const std::string entry = Entry(index, p.name);
  if (std::string problem = PrincipalNameProblem(p.name); !problem.empty()) {
    return Status::InvalidArgument(entry + ": name " + problem);
  }
  if (p.token_sha256.empty() && p.certificate_names.empty()) {
    return Status::InvalidArgument(entry + ": needs token_sha256 or certificate_names");
  }
  std::array<uint8_t, 32> digest{};
  if (!p.token_sha256.empty() && !ParseDigest(p.token_sha256, &digest)) {
    return Status::InvalidArgument(entry +
                                   ": token_sha256 must be 64 lowercase hex digits (the SHA-256 "
                                   "of the token, never the token itself)");
  }
  for (const std::string& cert : p.certificate_names) {
    if (cert.empty() || cert.size() > 253) {
      return Status::InvalidArgument(entry +
                                     ": certificate_names: a name must be 1-253 characters");
    }
  }
  for (const MapGrant& grant : p.maps) {
    if (std::string problem = PatternProblem(grant.pattern); !problem.empty()) {
      return Status::InvalidArgument(entry + ": maps: pattern '" + grant.pattern + "' " + problem);
    }
  }
  for (const Principal& other : principals_) {
    if (&other == &p) continue;
    if (other.name == p.name) {
      return Status::InvalidArgument(entry + ": name: '" + p.name + "' is already a principal");
    }
    if (!p.token_sha256.empty() && other.token_sha256 == p.token_sha256) {
      return Status::InvalidArgument(entry + ": token_sha256: the same token as principal '" +
                                     other.name + "'");
    }
    for (const std::string& cert : p.certificate_names) {
      for (const std::string& theirs : other.certificate_names) {
        if (cert == theirs) {
          return Status::InvalidArgument(entry + ": certificate_names: '" + cert +
                                         "' already names principal '" + other.name + "'");
        }
      }
    }
  }
  return Status::Ok();
}

Status TokensFile::Add(Principal principal) {
  principals_.push_back(std::move(principal));
  if (Status valid = Validate(principals_.back(), principals_.size() - 1); !valid.ok()) {
    principals_.pop_back();
    return valid;
  }
  std::array<uint8_t, 32> digest{};
  has_digest_.push_back(ParseDigest(principals_.back().token_sha256, &digest));
  digests_.push_back(digest);
  return Status::Ok();
}

Status TokensFile::Remove(const std::string& name) {
  for (size_t i = 0; i < principals_.size(); ++i) {
    if (principals_[i].name != name) continue;
    principals_.erase(principals_.begin() + long(i));
    digests_.erase(digests_.begin() + long(i));
    has_digest_.erase(has_digest_.begin() + long(i));
    return Status::Ok();
  }
  return Status::NotFound("no principal named '" + name + "'");
}

const Principal* TokensFile::Find(const std::string& name) const {
  for (const Principal& p : principals_) {
    if (p.name == name) return &p;
  }
  return nullptr;
}

const Principal* TokensFile::FindByToken(const std::string& token) const {
  const std::array<uint8_t, 32> digest = Sha256(token);
  // Every entry is compared, whatever matched before: the time does not depend on where (or
  // whether) the token's entry is.
  size_t found = principals_.size();
  for (size_t i = 0; i < principals_.size(); ++i) {
    const bool equal = CRYPTO_memcmp(digest.data(), digests_[i].data(), digest.size()) == 0;
    const bool match = equal & has_digest_[i];
    found = match ? i : found;
  }
  return found < principals_.size() ? &principals_[found] : nullptr;
}

const Principal* TokensFile::FindByCertificateNames(const std::vector<std::string>& names) const {
  for (const Principal& p : principals_) {
    for (const std::string& mine : p.certificate_names) {
      for (const std::string& name : names) {
        if (mine == name) return &p;
      }
    }
  }
  return nullptr;
}

Result<TokensFile> TokensFile::Parse(const std::string& text, const std::string& origin) {
  auto fail = [&origin](const std::string& message) {
    return Status::InvalidArgument(origin + ": " + message);
  };
  YAML::Node root;
  try {
    root = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    return fail("not valid YAML: " + e.msg + " (line " + std::to_string(e.mark.line + 1) + ")");
  }
  TokensFile file;
  if (!root || root.IsNull()) return file;  // an empty file: no principals
  if (!root.IsMap()) return fail("must be a mapping with a 'principals' list");
  for (const auto& key : root) {
    const std::string name = key.first.IsScalar() ? key.first.Scalar() : "(not a string)";
    if (name != "principals") return fail("unknown key '" + name + "' (expected 'principals')");
  }
  const YAML::Node list = root["principals"];
  if (!list || list.IsNull()) return file;
  if (!list.IsSequence()) return fail("principals must be a list");
  for (size_t i = 0; i < list.size(); ++i) {
    const YAML::Node node = list[i];
    Principal p;
    if (node.IsMap() && node["name"] && node["name"].IsScalar()) {
      p.name = node["name"].Scalar();
    }
    const std::string entry = Entry(i, p.name);
    if (!node.IsMap()) return fail(entry + ": must be a mapping");
    try {
      for (const auto& kv : node) {
        const std::string key = kv.first.as<std::string>();
        const YAML::Node& value = kv.second;
        if (key == "name") {
          if (!value.IsScalar()) return fail(entry + ": name must be a string");
        } else if (key == "token_sha256") {
          if (!value.IsScalar()) return fail(entry + ": token_sha256 must be a string");
          p.token_sha256 = value.Scalar();
        } else if (key == "admin") {
          p.admin = value.as<bool>();
        } else if (key == "metrics") {
          p.metrics = value.as<bool>();
        } else if (key == "certificate_names") {
          if (!value.IsSequence()) return fail(entry + ": certificate_names must be a list");
          for (const auto& name : value) {
            if (!name.IsScalar()) return fail(entry + ": certificate_names must hold strings");
            p.certificate_names.push_back(name.Scalar());
          }
        } else if (key == "maps") {
          if (!value.IsMap()) {
            return fail(entry + ": maps must be a mapping of pattern -> [read, write]");
          }
          for (const auto& grant_node : value) {
            MapGrant grant;
            grant.pattern = grant_node.first.as<std::string>();
            const YAML::Node& rights = grant_node.second;
            if (!rights.IsSequence()) {
              return fail(entry + ": maps: '" + grant.pattern +
                          "' must list rights ([read, write])");
            }
            for (const auto& right : rights) {
              const std::string r = right.IsScalar() ? right.Scalar() : "";
              if (r == "read") {
                grant.read = true;
              } else if (r == "write") {
                grant.write = true;
              } else {
                return fail(entry + ": maps: '" + grant.pattern + "': unknown right '" + r +
                            "' (expected read or write)");
              }
            }
            for (const MapGrant& other : p.maps) {
              if (other.pattern == grant.pattern) {
                return fail(entry + ": maps: pattern '" + grant.pattern + "' is listed twice");
              }
            }
            p.maps.push_back(std::move(grant));
          }
        } else {
          return fail(entry + ": unknown key '" + key +
                      "' (expected name, token_sha256, admin, metrics, maps, certificate_names)");
        }
      }
    } catch (const YAML::Exception& e) {
      return fail(entry + ": " + e.msg + " (line " + std::to_string(e.mark.line + 1) + ")");
    }
    if (!node["name"]) return fail(entry + ": name is missing");
    if (Status added = file.Add(std::move(p)); !added.ok()) return fail(added.message());
  }
  return file;
}

Result<TokensFile> TokensFile::Load(const std::string& path) {
  auto text = ReadWholeFile(path);
  if (!text.ok()) return text.status();
  return Parse(*text, path);
}

std::string TokensFile::Serialize() const {
  YAML::Emitter out;
  out << YAML::Comment(
      "placedb tokens file: written by `placedb-server tokens add`; holds only SHA-256 hashes.");
  out << YAML::BeginMap << YAML::Key << "principals" << YAML::Value << YAML::BeginSeq;
  for (const Principal& p : principals_) {
    out << YAML::BeginMap << YAML::Key << "name" << YAML::Value << YAML::DoubleQuoted << p.name;
    if (!p.token_sha256.empty())
      out << YAML::Key << "token_sha256" << YAML::Value << p.token_sha256;
    if (p.admin) out << YAML::Key << "admin" << YAML::Value << true;
    if (p.metrics) out << YAML::Key << "metrics" << YAML::Value << true;
    if (!p.maps.empty()) {
      out << YAML::Key << "maps" << YAML::Value << YAML::BeginMap;
      for (const MapGrant& grant : p.maps) {
        out << YAML::Key << YAML::DoubleQuoted << grant.pattern << YAML::Value << YAML::Flow
            << YAML::BeginSeq;
        if (grant.read) out << "read";
        if (grant.write) out << "write";
        out << YAML::EndSeq;
      }
      out << YAML::EndMap;
    }
    if (!p.certificate_names.empty()) {
      out << YAML::Key << "certificate_names" << YAML::Value << YAML::Flow << YAML::BeginSeq;
      for (const std::string& name : p.certificate_names) out << YAML::DoubleQuoted << name;
      out << YAML::EndSeq;
    }
    out << YAML::EndMap;
  }
  out << YAML::EndSeq << YAML::EndMap;
  return std::string(out.c_str()) + "\n";
}

Status TokensFile::Save(const std::string& path) const {
  static std::atomic<uint64_t> counter{0};
  const std::string temp =
      path + ".tmp." + std::to_string(::getpid()) + "." + std::to_string(counter.fetch_add(1));
  const int fd = ::open(temp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
  if (fd < 0) return Status::IoError(Errno("cannot create", temp));
  Status status = WriteAll(fd, Serialize(), temp);
  if (status.ok() && ::fsync(fd) != 0) status = Status::IoError(Errno("cannot sync", temp));
  if (::close(fd) != 0 && status.ok()) status = Status::IoError(Errno("cannot close", temp));
  if (status.ok() && ::rename(temp.c_str(), path.c_str()) != 0) {
    status = Status::IoError(Errno("cannot rename " + temp + " to", path));
  }
  if (!status.ok()) {
    ::unlink(temp.c_str());
    return status;
  }
  // The rename itself is durable once the directory is synced.
  std::string directory = std::filesystem::path(path).parent_path().string();
  if (directory.empty()) directory = ".";
  const int dir = ::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir >= 0) {
    ::fsync(dir);
    ::close(dir);
  }
  return Status::Ok();
}

}  // namespace placedb::server::auth
