// Binary descriptors and their Hamming distance.
//
// A 256-bit ORB descriptor is four 64-bit words; the distance is four XORs and four hardware
// popcounts (the build enables -mpopcnt on x86-64). 32-byte alignment keeps one descriptor inside
// one cache line, so contiguous arrays of them stream well.
#pragma once

#include <array>
#include <bit>
#include <cstdint>
#include <cstring>

namespace placedb {

struct alignas(32) Descriptor256 {
  std::array<uint64_t, 4> words{};

  static constexpr int kBytes = 32;
  static constexpr int kBits = 256;

  // From the 32 bytes OpenCV's ORB writes per row (byte i is bits 8i..8i+7).
  static Descriptor256 FromBytes(const uint8_t* bytes) {
    Descriptor256 d;
    std::memcpy(d.words.data(), bytes, kBytes);
    return d;
  }
  void ToBytes(uint8_t* bytes) const { std::memcpy(bytes, words.data(), kBytes); }
  const uint8_t* bytes() const { return reinterpret_cast<const uint8_t*>(words.data()); }

  bool operator==(const Descriptor256&) const = default;
};
static_assert(sizeof(Descriptor256) == 32);

inline int HammingDistance(const Descriptor256& a, const Descriptor256& b) {
  return std::popcount(a.words[0] ^ b.words[0]) + std::popcount(a.words[1] ^ b.words[1]) +
         std::popcount(a.words[2] ^ b.words[2]) + std::popcount(a.words[3] ^ b.words[3]);
}

}  // namespace placedb
