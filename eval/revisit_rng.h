// The revisit builder's random numbers (eval/revisits.h): SplitMix64, tiny and fully specified, so
// the same seed gives the same numbers on any platform (std::uniform_real_distribution is not
// specified bit-for-bit). Everything the builder draws comes from one of these.
#pragma once

#include <cstddef>
#include <cstdint>

namespace placedb::eval {

class Rng {
 public:
  explicit Rng(uint64_t seed) : state_(seed) {}
  uint64_t Next() {
    uint64_t z = (state_ += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  double Uniform(double lo, double hi) { return lo + (hi - lo) * double(Next() >> 11) * 0x1p-53; }
  size_t Below(size_t n) { return n ? size_t(Next() % n) : 0; }

 private:
  uint64_t state_;
};

// The seed of stream (a, b) of `seed`: each place's visits, and the choice of backgrounds, draw
// from their own stream, so one draw more or less in one does not shift the others.
inline uint64_t StreamSeed(uint64_t seed, uint64_t a, uint64_t b) {
  Rng mix(seed ^ (a * 0xD1B54A32D192ED03ull) ^ (b * 0xABC98388FB8FAC03ull));
  return mix.Next();
}

}  // namespace placedb::eval
