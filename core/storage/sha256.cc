#include "core/storage/sha256.h"

#include <openssl/evp.h>

#include <array>

namespace placedb {

Sha256::Sha256() : context_(EVP_MD_CTX_new(), &EVP_MD_CTX_free) {
  EVP_DigestInit_ex(context_.get(), EVP_sha256(), nullptr);
}

Sha256::~Sha256() = default;

void Sha256::Update(std::string_view bytes) {
  EVP_DigestUpdate(context_.get(), bytes.data(), bytes.size());
}

std::string Sha256::Final() {
  std::array<unsigned char, EVP_MAX_MD_SIZE> digest{};
  unsigned int length = 0;
  EVP_DigestFinal_ex(context_.get(), digest.data(), &length);
  return std::string(reinterpret_cast<const char*>(digest.data()), length);
}

std::string Sha256::Hex(std::string_view digest) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string out;
  for (const char c : digest) {
    out += kDigits[(uint8_t(c) >> 4) & 0xf];
    out += kDigits[uint8_t(c) & 0xf];
  }
  return out;
}

}  // namespace placedb
