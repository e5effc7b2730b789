// Incremental SHA-256 (libcrypto): a snapshot archive's digest (core/storage/snapshots.h), and a
// cluster snapshot's stored archive checked when read back (server/cluster/snapshot_archives.h).
#pragma once

#include <memory>
#include <string>
#include <string_view>

struct evp_md_ctx_st;

namespace placedb {

class Sha256 {
 public:
  Sha256();
  ~Sha256();
  Sha256(const Sha256&) = delete;
  Sha256& operator=(const Sha256&) = delete;
  void Update(std::string_view bytes);
  std::string Final();                              // the 32 raw digest bytes
  static std::string Hex(std::string_view digest);  // lower-case hex of raw bytes

 private:
  std::unique_ptr<evp_md_ctx_st, void (*)(evp_md_ctx_st*)> context_;
};

}  // namespace placedb
