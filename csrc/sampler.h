// Counter-based random numbers: every (seed, pixel, sample) triple has its own PCG32 stream, so
// an image is bitwise identical whatever the thread count or the order pixels are visited in.
#pragma once

#include <cstdint>

#include "math.h"

namespace rbpt {

/// SplitMix64 finaliser: a bijective 64-bit mix used to derive stream states from counters.
inline uint64_t mix64(uint64_t x) {
    x += 0x9E3779B97F4A7C15ull;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

/// PCG32 (O'Neill 2014) seeded from (seed, pixel, sample); the `independent` sampler.
class Sampler {
public:
    Sampler(uint64_t seed, uint64_t pixel, uint64_t sample) {
        uint64_t key = mix64(mix64(seed) ^ pixel);
        inc_ = (mix64(key ^ (sample * 0xD1B54A32D192ED03ull)) << 1u) | 1u;
        state_ = 0;
        next_u32();
        state_ += mix64(key + sample);
        next_u32();
    }

    uint32_t next_u32() {
        uint64_t old = state_;
        state_ = old * 6364136223846793005ull + inc_;
        uint32_t xorshifted = uint32_t(((old >> 18u) ^ old) >> 27u);
        uint32_t rot = uint32_t(old >> 59u);
        return (xorshifted >> rot) | (xorshifted << ((~rot + 1u) & 31));
    }

    /// Uniform float in [0, 1): 24 random mantissa bits.
    float next_1d() { return float(next_u32() >> 8) * 0x1p-24f; }
    Vec2 next_2d() {
        float x = next_1d();
        return {x, next_1d()};
    }

private:
    uint64_t state_, inc_;
};

}  // namespace rbpt
