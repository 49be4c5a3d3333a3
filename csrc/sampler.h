// The samplers: Mitsuba's `independent`, `stratified`, `multijitter`, `orthogonal` and
// `ldsampler`. All are counter-based: a sample's numbers depend only on (seed, pixel, sample),
// so an image is bitwise identical whatever the thread count or the order pixels are visited
// in. The stratified kinds build their pattern over the pixel's `sample_count` samples from
// per-pixel permutations (hashed from (seed, pixel, dimension)) and draw their jitter from the
// sample's own PCG32 stream; every single sample is uniform on [0, 1)^n, so estimates stay
// unbiased while the samples of a pixel are stratified.
#pragma once

#include <cmath>
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

/// Tiny Encryption Algorithm (Zafar et al. 2010), as Mitsuba's sample_tea_32.
inline void tea(uint32_t &v0, uint32_t &v1, int rounds = 4) {
    uint32_t sum = 0;
    for (int i = 0; i < rounds; ++i) {
        sum += 0x9e3779b9;
        v0 += ((v1 << 4) + 0xa341316c) ^ (v1 + sum) ^ ((v1 >> 5) + 0xc8013ea4);
        v1 += ((v0 << 4) + 0xad90777d) ^ (v0 + sum) ^ ((v0 >> 5) + 0x7e95761e);
    }
}

/// The smallest 2^k - 1 at least x.
RBPT_INLINE uint32_t pow2_mask(uint32_t x) {
    x |= x >> 1;
    x |= x >> 2;
    x |= x >> 4;
    x |= x >> 8;
    x |= x >> 16;
    return x;
}

/// One round of Kensler's permutation hash, a bijection of [0, w] (w + 1 a power of two).
RBPT_INLINE uint32_t kensler_round(uint32_t index, uint32_t w, uint32_t seed) {
    index ^= seed;
    index *= 0xe170893d;
    index ^= seed >> 16;
    index ^= (index & w) >> 4;
    index ^= seed >> 8;
    index *= 0x0929eb3f;
    index ^= seed >> 23;
    index ^= (index & w) >> 1;
    index *= 1 | seed >> 27;
    index *= 0x6935fa69;
    index ^= (index & w) >> 11;
    index *= 0x74dcb303;
    index ^= (index & w) >> 2;
    index *= 0x9e501cc3;
    index ^= (index & w) >> 2;
    index *= 0xc860a3df;
    index &= w;
    index ^= index >> 5;
    return index;
}

/// Element `index` of a pseudo-random permutation of {0, ..., n - 1} chosen by `seed`
/// (Kensler 2013, "Correlated Multi-Jittered Sampling": a hash bijective on the next power of
/// two, cycle-walked until it lands below n).
inline uint32_t permute_kensler(uint32_t index, uint32_t n, uint32_t seed) {
    if (n <= 1) return 0;
    const uint32_t w = pow2_mask(n - 1);
    do index = kensler_round(index, w, seed);
    while (index >= n);
    return (index + seed) % n;
}

/// x / d and x % d for a divisor d that many SIMD lanes share (x / d < 2^31), with no division
/// instruction (x86 has no vector one): the quotient estimated in double and corrected. The
/// results of / and %, exactly.
struct Divisor {
    uint32_t d;
    double inv;
    explicit Divisor(uint32_t d) : d(d), inv(1.0 / double(d)) {}
    RBPT_INLINE uint32_t quotient(uint32_t x) const {
        // x * inv lies within (x / d) 2^-52 < 2^-20 / d of x / d, closer than the next whole
        // number above it: q is floor(x / d), or one less where x / d is whole and the
        // product rounded below it. (double(x) and back through int32, whose conversions
        // AVX2 has in lanes.)
        const double xd = double(int32_t(x ^ 0x80000000u)) + 2147483648.0;
        const uint32_t q = uint32_t(int32_t(xd * inv));
        return x - q * d >= d ? q + 1 : q;
    }
    RBPT_INLINE uint32_t remainder(uint32_t x) const { return x - quotient(x) * d; }
};

/// Element `index` of a pseudo-random permutation of {0, ..., n - 1}, n a power of two: a
/// shuffle network of TEA-decided swaps, one level per bit (Mitsuba's `permute`).
inline uint32_t permute_pow2(uint32_t index, uint32_t n, uint32_t seed) {
    for (uint32_t bit = 1; bit < n; bit <<= 1) {
        uint32_t v0 = index | bit, v1 = seed;
        tea(v0, v1, 2);
        if (v0 & bit) index ^= bit;
    }
    return index;
}

/// Van der Corput radical inverse in base 2 of `index`, its digits xor-scrambled.
inline float radical_inverse_2(uint32_t index, uint32_t scramble) {
    index = (index << 16) | (index >> 16);
    index = ((index & 0x00ff00ffu) << 8) | ((index & 0xff00ff00u) >> 8);
    index = ((index & 0x0f0f0f0fu) << 4) | ((index & 0xf0f0f0f0u) >> 4);
    index = ((index & 0x33333333u) << 2) | ((index & 0xccccccccu) >> 2);
    index = ((index & 0x55555555u) << 1) | ((index & 0xaaaaaaaau) >> 1);
    return float((index ^ scramble) >> 8) * 0x1p-24f;
}

/// Second dimension of the Sobol sequence at `index`, xor-scrambled: with radical_inverse_2 it
/// forms a (0, 2)-sequence in base 2.
inline float sobol_2(uint32_t index, uint32_t scramble) {
    for (uint32_t v = 1u << 31; index != 0; index >>= 1, v ^= v >> 1)
        if (index & 1) scramble ^= v;
    return float(scramble >> 8) * 0x1p-24f;
}

/// One step of a PCG32 stream (O'Neill 2014): the next 32 random bits.
RBPT_INLINE uint32_t pcg32_next(uint64_t &state, uint64_t inc) {
    uint64_t old = state;
    state = old * 6364136223846793005ull + inc;
    uint32_t xorshifted = uint32_t(((old >> 18u) ^ old) >> 27u);
    uint32_t rot = uint32_t(old >> 59u);
    return (xorshifted >> rot) | (xorshifted << ((~rot + 1u) & 31));
}

/// The PCG32 stream of sample `sample` of the pixel whose stream key is `key` (PixelSeed).
RBPT_INLINE void pcg32_seed(uint64_t key, uint64_t sample, uint64_t *state, uint64_t *inc) {
    *inc = (mix64(key ^ (sample * 0xD1B54A32D192ED03ull)) << 1u) | 1u;
    *state = 0;
    pcg32_next(*state, *inc);
    *state += mix64(key + sample);
    pcg32_next(*state, *inc);
}

/// A float uniform in [0, 1) from 32 random bits (their top 24 as the mantissa).
RBPT_INLINE float uniform_float(uint32_t bits) { return float(bits >> 8) * 0x1p-24f; }

/// The first two uniforms of the independent sampler's streams (keys[k], samples[k]), k < n,
/// the position in the pixel that Camera::sample_position draws: the same numbers as
/// Sampler's, in a loop the compiler vectorises (render_bwd's film weights and gathers).
RBPT_INLINE void independent_first_2d(int n, const uint64_t *keys, const uint64_t *samples, float *u0,
                                      float *u1) {
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        uint64_t state, inc;
        pcg32_seed(keys[k], samples[k], &state, &inc);
        u0[k] = uniform_float(pcg32_next(state, inc));
        u1[k] = uniform_float(pcg32_next(state, inc));
    }
}

enum class SamplerType { Independent, Stratified, Multijitter, Orthogonal, LowDiscrepancy };

/// A sampler plugin's settings: its kind, `jitter`, and the sample count rounded as
/// Mitsuba 3 rounds it, with the stratification grid that count gives.
struct SamplerDesc {
    SamplerType type = SamplerType::Independent;
    bool jitter = true;
    uint32_t sample_count = 4;
    uint32_t res_x = 1, res_y = 1;  ///< grid of next_2d (stratified, multijitter, orthogonal)

    /// Set the number of samples per pixel as Mitsuba's set_sample_count does: stratified
    /// rounds up to a square, multijitter to rows x columns with rows = floor(sqrt(spp)),
    /// orthogonal to the square of a prime (at least 4), ldsampler to a power of 4 (at
    /// least 4); independent keeps it.
    void set_sample_count(uint32_t spp) {
        auto is_prime = [](uint32_t x) {
            for (uint32_t i = 2; i * i <= x; ++i)
                if (x % i == 0) return false;
            return true;
        };
        res_x = res_y = 1;
        switch (type) {
            case SamplerType::Independent: sample_count = spp; return;
            case SamplerType::Stratified:
                while (res_x * res_x < spp) ++res_x;
                res_y = res_x;
                break;
            case SamplerType::Multijitter:
                res_y = uint32_t(std::sqrt(double(spp)));
                while ((res_y + 1) * (res_y + 1) <= spp) ++res_y;  // exact floor(sqrt)
                while (res_y * res_y > spp) --res_y;
                res_x = (spp + res_y - 1) / res_y;
                break;
            case SamplerType::Orthogonal:
                res_x = 2;
                while (res_x * res_x < spp || !is_prime(res_x)) ++res_x;
                res_y = res_x;
                break;
            case SamplerType::LowDiscrepancy:
                res_x = 2;
                while (res_x * res_x < spp) res_x *= 2;
                res_y = res_x;
                break;
        }
        sample_count = res_x * res_y;
    }
};

/// What the samples of one pixel share, hashed from (seed, pixel) once per pixel: the key of
/// their random streams and the permutation seed of the stratified samplers' patterns.
struct PixelSeed {
    uint64_t stream = 0;
    uint32_t sequence = 0;
    PixelSeed() = default;
    PixelSeed(uint64_t seed, uint64_t pixel) {
        stream = mix64(mix64(seed) ^ pixel);
        // One permutation seed per pixel (Mitsuba's per-sequence seed); dimensions offset it.
        uint64_t key = mix64(mix64(seed ^ 0x6A09E667F3BCC909ull) ^ pixel);
        sequence = uint32_t(key ^ (key >> 32));
    }
};

/// The permutation seed of dimension `dim` of the pixel of permutation seed `sequence`
/// (PixelSeed's). Unlike Mitsuba's `seed + dim`, hashed: Kensler's and the TEA shuffle's
/// permutations of neighbouring seeds are correlated, which couples dimensions (e.g. the
/// pixel position with the light sample); see MITSUBA_FACTS.md, section m.
RBPT_INLINE uint32_t dimension_seed(uint32_t sequence, uint32_t dim) {
    uint64_t h = mix64((uint64_t(sequence) << 32) | dim);
    return uint32_t(h ^ (h >> 32));
}

/// (cell + offset) / n, kept below 1 (float rounding could reach it).
RBPT_INLINE float scaled_below_one(float x, float inv_n) { return std::min(x * inv_n, 0x1.fffffep-1f); }

/// The sample generator of one (seed, pixel, sample) triple. Its own PCG32 stream (O'Neill
/// 2014) is the `independent` sampler and the jitter of the stratified kinds; the stratified
/// kinds (dispatched by a switch, no virtual call) advance a dimension counter with every
/// next_1d / next_2d, as Mitsuba's samplers do.
class Sampler {
public:
    /// The independent sampler.
    Sampler(uint64_t seed, uint64_t pixel, uint64_t sample) : Sampler(PixelSeed(seed, pixel).stream, sample) {}

    /// Sample `sample` (< desc.sample_count) of pixel `pixel` with the sampler `desc`.
    Sampler(const SamplerDesc &desc, uint64_t seed, uint64_t pixel, uint64_t sample)
        : Sampler(desc, PixelSeed(seed, pixel), sample) {}

    /// Sample `sample` of the pixel `pixel` seeds, with the sampler `desc`.
    Sampler(const SamplerDesc &desc, const PixelSeed &pixel, uint64_t sample) : Sampler(pixel.stream, sample) {
        type_ = desc.type;
        desc_ = &desc;
        if (type_ == SamplerType::Independent) return;
        seq_ = pixel.sequence;
        index_ = uint32_t(sample);
        if (type_ == SamplerType::Orthogonal) {
            // The sample's row of the orthogonal array, the same in every dimension.
            uint32_t i = permute_kensler(index_, desc.sample_count, seq_);
            aux_[0] = i / desc.res_x;
            aux_[1] = i - aux_[0] * desc.res_x;
        } else if (type_ == SamplerType::LowDiscrepancy) {
            // The pixel's scrambles (shared by all dimensions, as Mitsuba's): 1D, and 2D x, y.
            uint32_t v1 = 0x48bc48ebu;
            aux_[0] = seq_;
            tea(aux_[0], v1);
            aux_[1] = seq_;
            aux_[2] = 0x98bc51abu;
            tea(aux_[1], aux_[2]);
        }
    }

    uint32_t next_u32() { return pcg32_next(state_, inc_); }

    /// Uniform float in [0, 1): 24 random mantissa bits.
    float uniform() { return uniform_float(next_u32()); }

    /// The independent sampler's PCG32 stream (state, increment), for paths traced in SIMD
    /// lanes (wavefront.h), which continue it with pcg32_next.
    uint64_t pcg_state() const { return state_; }
    uint64_t pcg_inc() const { return inc_; }
    /// The independent sampler continuing the stream (pcg_state(), pcg_inc()).
    static Sampler independent(uint64_t state, uint64_t inc) {
        Sampler s;
        s.state_ = state;
        s.inc_ = inc;
        return s;
    }

    /// What a sampler of any kind continues from besides its SamplerDesc: its stream, and
    /// the stratified kinds' pixel seed, sample index, dimension and row or scrambles (the
    /// wavefront keeps them per sample between its stages: wavefront.cpp's load_sampler).
    struct Parts {
        uint64_t state, inc;
        uint32_t seq, index, dim, aux[3];
    };
    Parts parts() const { return {state_, inc_, seq_, index_, dim_, {aux_[0], aux_[1], aux_[2]}}; }
    /// The sampler `desc` continuing from `parts`.
    Sampler(const SamplerDesc &desc, const Parts &parts)
        : state_(parts.state), inc_(parts.inc), type_(desc.type), desc_(&desc), seq_(parts.seq),
          index_(parts.index), dim_(parts.dim), aux_{parts.aux[0], parts.aux[1], parts.aux[2]} {}

    float next_1d() {
        if (type_ == SamplerType::Independent) return uniform();
        return stratified_1d();
    }
    Vec2 next_2d() {
        if (type_ == SamplerType::Independent) {
            float x = uniform();
            return {x, uniform()};
        }
        return stratified_2d();
    }

private:
    Sampler() = default;

    /// The PCG32 stream of sample `sample` of the pixel whose stream key is `key`.
    Sampler(uint64_t key, uint64_t sample) { pcg32_seed(key, sample, &state_, &inc_); }

    float jitter() { return desc_->jitter ? uniform() : 0.5f; }

    uint32_t dim_seed(uint32_t dim) const { return dimension_seed(seq_, dim); }

    // Out of line (noinline at their definitions): the independent sampler's hot path stays
    // a compare and a PCG step.
    float stratified_1d();
    Vec2 stratified_2d();
    float orthogonal_1d();

    uint64_t state_, inc_;
    SamplerType type_ = SamplerType::Independent;
    const SamplerDesc *desc_ = nullptr;
    uint32_t seq_ = 0, index_ = 0, dim_ = 0;
    uint32_t aux_[3] = {0, 0, 0};  ///< orthogonal: the array row (a0, a1); ldsampler: the scrambles
};

/// One dimension stratified into sample_count intervals, one sample each.
[[gnu::noinline]] inline float Sampler::stratified_1d() {
    const SamplerDesc &d = *desc_;
    if (d.type == SamplerType::Orthogonal) return orthogonal_1d();
    uint32_t seed = dim_seed(dim_++);
    uint32_t n = d.sample_count;
    switch (d.type) {
        case SamplerType::Stratified:
            return scaled_below_one(float(permute_kensler(index_, n, seed)) + jitter(), 1.f / float(n));
        case SamplerType::Multijitter:
            return scaled_below_one(float(permute_kensler(index_, n, seed * 0x45fbe943u)) + jitter(),
                          1.f / float(n));
        case SamplerType::LowDiscrepancy:
            return radical_inverse_2(permute_pow2(index_, n, seed), aux_[0]);
        default: return uniform();
    }
}

/// Two dimensions: stratified (a res x res grid, one sample per cell), correlated
/// multi-jittered (a res_x x res_y grid whose samples are also stratified in each axis),
/// orthogonal array (two 1D draws of an OA of strength 2), or a scrambled (0, 2)-sequence.
[[gnu::noinline]] inline Vec2 Sampler::stratified_2d() {
    const SamplerDesc &d = *desc_;
    if (d.type == SamplerType::Orthogonal) {
        float x = orthogonal_1d();
        return {x, orthogonal_1d()};
    }
    uint32_t seed = dim_seed(dim_++);
    uint32_t n = d.sample_count;
    switch (d.type) {
        case SamplerType::Stratified: {
            uint32_t p = permute_kensler(index_, n, seed);
            uint32_t y = p / d.res_x, x = p - y * d.res_x;
            float jx = jitter(), jy = jitter();
            float inv = 1.f / float(d.res_x);
            return {scaled_below_one(float(x) + jx, inv), scaled_below_one(float(y) + jy, inv)};
        }
        case SamplerType::Multijitter: {
            // Kensler's correlated multi-jittering: cell (x, y) of a res_x x res_y grid, and
            // within it the sub-cell given by permuted y (along x) and permuted x (along y).
            uint32_t s = permute_kensler(index_, n, seed * 0x51633e2du);
            uint32_t y = s / d.res_x, x = s - y * d.res_x;
            uint32_t sx = permute_kensler(x, d.res_x, seed * 0x68bc21ebu);
            uint32_t sy = permute_kensler(y, d.res_y, seed * 0x02e5be93u);
            float jx = jitter(), jy = jitter();
            return {scaled_below_one(float(x * d.res_y + sy) + jx, 1.f / float(n)),
                    scaled_below_one(float(y * d.res_x + sx) + jy, 1.f / float(n))};
        }
        case SamplerType::LowDiscrepancy: {
            uint32_t i = permute_pow2(index_, n, seed);
            return {radical_inverse_2(i, aux_[1]), sobol_2(i, aux_[2])};
        }
        default: {
            float x = uniform();
            return {x, uniform()};
        }
    }
}

/// Dimension dim_ of an orthogonal array of strength 2 (Bose's construction, as in Jarosz et
/// al. 2019 and Mitsuba's `orthogonal`): the pixel's samples, mapped to (a0, a1) in a p x p
/// grid (p prime), take column a0 + (j - 1) a1 mod p in dimension j, so every pair of
/// dimensions is stratified in p x p cells, and the paired column picks the sub-stratum
/// (multi-jittered, so each dimension is also stratified into p^2 intervals).
inline float Sampler::orthogonal_1d() {
    const SamplerDesc &d = *desc_;
    uint32_t j = dim_++, p = d.res_x;
    uint32_t a0 = aux_[0], a1 = aux_[1];
    uint32_t a_ij, a_ik;
    if (j == 0) {
        a_ij = a0;
        a_ik = a1;
    } else if (j == 1) {
        a_ij = a1;
        a_ik = a0;
    } else {
        uint32_t k = (j % 2) ? j - 1 : j + 1;
        a_ij = (a0 + (j - 1) * a1) % p;
        a_ik = (a0 + (k - 1) * a1) % p;
    }
    uint32_t seed = dim_seed(j);
    uint32_t stratum = permute_kensler(a_ij, p, seed * 0x51633e2du);
    uint32_t sub = permute_kensler(a_ik, p, seed * 0x68bc21ebu);
    return scaled_below_one(float(stratum * p + sub) + jitter(), 1.f / float(d.sample_count));
}

/// The samplers of up to Capacity samples of a stratified kind (not `independent`), one
/// column per field of Sampler::Parts, and their draws in SIMD lanes: next_1d and next_2d of
/// many samples at once, each its Sampler's numbers bit for bit (the permutations'
/// cycle-walks in rounds over 16 lanes, the divisions by Divisor). The wavefront draws its
/// vertices' numbers and its camera rays' positions with it.
struct SamplerColumns {
    static constexpr int Capacity = 256;
    alignas(64) uint64_t state[Capacity], inc[Capacity];
    alignas(64) uint32_t seq[Capacity], index[Capacity], dim[Capacity];
    alignas(64) uint32_t aux0[Capacity], aux1[Capacity], aux2[Capacity];

    void set(int k, const Sampler::Parts &p) {
        state[k] = p.state, inc[k] = p.inc, seq[k] = p.seq, index[k] = p.index, dim[k] = p.dim;
        aux0[k] = p.aux[0], aux1[k] = p.aux[1], aux2[k] = p.aux[2];
    }
    Sampler::Parts get(int k) const {
        return {state[k], inc[k], seq[k], index[k], dim[k], {aux0[k], aux1[k], aux2[k]}};
    }

    /// Start samples k < n, sample index[k] of the pixel whose stream key is keys[k] and
    /// whose permutation seed is seq[k] (PixelSeed's; the caller sets index and seq): as
    /// Sampler's constructor, their streams, dimension 0, and the orthogonal array's rows or
    /// the ldsampler's scrambles.
    void begin(const SamplerDesc &desc, int n, const uint64_t *keys);

    /// next_1d of samples k < n into u[k]. Those with draw[k] == 0 do not move on (their u[k]
    /// is written all the same); a null `draw` lets every sample draw.
    void next_1d(const SamplerDesc &desc, int n, const int *draw, float *u);
    /// next_2d of samples k < n into (ux[k], uy[k]), as next_1d.
    void next_2d(const SamplerDesc &desc, int n, const int *draw, float *ux, float *uy);
};

}  // namespace rbpt
