// The stratified samplers' draws for many samples at once (SamplerColumns): Sampler's own
// numbers, bit for bit, computed in SIMD lanes. Each function below is the lanes' form of
// one of Sampler's (named in its comment); the loops marked `#pragma GCC ivdep` vectorise
// (test_wavefront's test08).
#include "sampler.h"

#include <algorithm>

namespace rbpt {

namespace {

constexpr int Capacity = SamplerColumns::Capacity;

/// A draw mask of every lane (SamplerColumns's `draw` when null).
const int *every_lane() {
    static const auto ones = [] {
        struct Ones {
            int v[Capacity];
        } o;
        std::fill(o.v, o.v + Capacity, 1);
        return o;
    }();
    return ones.v;
}

/// permute_kensler(index[k], n, seed[k]) for k < m, into out[k] (which may be index).
void permute_kensler_lanes(const uint32_t *index, uint32_t n, const uint32_t *seed, uint32_t *out, int m) {
    if (n <= 1) {
        std::fill(out, out + m, 0u);
        return;
    }
    const uint32_t w = pow2_mask(n - 1);
#pragma GCC ivdep
    for (int k = 0; k < m; ++k) out[k] = kensler_round(index[k], w, seed[k]);
    // Walk the cycles on where a lane landed at n or past it, 16 lanes at a time, until none
    // does (none ever does when n is a power of two).
    for (int first = 0; w + 1 != n && first < m; first += 16) {
        const int last = std::min(first + 16, m);
        for (;;) {
            int past = 0;
            for (int k = first; k < last; ++k) past |= out[k] >= n ? 1 : 0;
            if (!past) break;
#pragma GCC ivdep
            for (int k = first; k < last; ++k) out[k] = out[k] >= n ? kensler_round(out[k], w, seed[k]) : out[k];
        }
    }
    const Divisor mod(n);
#pragma GCC ivdep
    for (int k = 0; k < m; ++k) out[k] = mod.remainder(out[k] + seed[k]);
}

/// permute_pow2(index[k], n, seed[k]) for k < m, into out[k]: the shuffle network one level
/// (bit) at a time over all lanes.
void permute_pow2_lanes(const uint32_t *index, uint32_t n, const uint32_t *seed, uint32_t *out, int m) {
    std::copy(index, index + m, out);
    for (uint32_t bit = 1; bit < n; bit <<= 1) {
#pragma GCC ivdep
        for (int k = 0; k < m; ++k) {
            uint32_t v0 = out[k] | bit, v1 = seed[k];
            tea(v0, v1, 2);
            out[k] = (v0 & bit) ? out[k] ^ bit : out[k];
        }
    }
}

/// Sampler::jitter's number from a lane's stream (state, inc), or 0.5 without jitter.
template <bool Jitter>
RBPT_INLINE float jitter(uint64_t &state, uint64_t inc) {
    if constexpr (Jitter) return uniform_float(pcg32_next(state, inc));
    else return 0.5f;
}

/// The permutation seeds of the samples' next dimension (Sampler::dim_seed of dim_++), times
/// `factor`; the dimension moves on where draw[k].
void next_seeds(SamplerColumns &c, int n, const int *draw, uint32_t factor, uint32_t *seed) {
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        seed[k] = dimension_seed(c.seq[k], c.dim[k]) * factor;
        c.dim[k] += draw[k] != 0 ? 1u : 0u;
    }
}

/// u[k] = (stratum[k] + jitter) / count (the 1D draws' last step), each lane's jitter from
/// its stream, which moves on where draw[k].
template <bool Jitter>
void jittered_1d(SamplerColumns &c, int n, const int *draw, const uint32_t *stratum, uint32_t count, float *u) {
    const float inv = 1.f / float(count);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        uint64_t state = c.state[k];
        const float j = jitter<Jitter>(state, c.inc[k]);
        c.state[k] = draw[k] ? state : c.state[k];
        u[k] = scaled_below_one(float(stratum[k]) + j, inv);
    }
}

/// Sampler::stratified_1d of `stratified` and `multijitter` (a permuted stratum, jittered),
/// from the seeds next_seeds() gave.
template <bool Jitter>
void permuted_1d(SamplerColumns &c, const SamplerDesc &d, int n, const int *draw, const uint32_t *seed, float *u) {
    alignas(64) uint32_t stratum[Capacity];
    permute_kensler_lanes(c.index, d.sample_count, seed, stratum, n);
    jittered_1d<Jitter>(c, n, draw, stratum, d.sample_count, u);
}

/// Sampler::stratified_2d of `stratified`: a cell of the res x res grid, jittered.
template <bool Jitter>
void stratified_2d(SamplerColumns &c, const SamplerDesc &d, int n, const int *draw, const uint32_t *seed, float *ux,
                   float *uy) {
    alignas(64) uint32_t cell[Capacity];
    permute_kensler_lanes(c.index, d.sample_count, seed, cell, n);
    const Divisor row(d.res_x);
    const uint32_t res = d.res_x;
    const float inv = 1.f / float(d.res_x);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const uint32_t y = row.quotient(cell[k]), x = cell[k] - y * res;
        uint64_t state = c.state[k];
        const float jx = jitter<Jitter>(state, c.inc[k]);
        const float jy = jitter<Jitter>(state, c.inc[k]);
        c.state[k] = draw[k] ? state : c.state[k];
        ux[k] = scaled_below_one(float(x) + jx, inv);
        uy[k] = scaled_below_one(float(y) + jy, inv);
    }
}

/// Sampler::stratified_2d of `multijitter`: cell (x, y) of the res_x x res_y grid and the
/// sub-cells of permuted y and x within it, jittered.
template <bool Jitter>
void multijitter_2d(SamplerColumns &c, const SamplerDesc &d, int n, const int *draw, const uint32_t *seed, float *ux,
                    float *uy) {
    alignas(64) uint32_t cell[Capacity], x[Capacity], y[Capacity], sx[Capacity], sy[Capacity], s[Capacity];
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) s[k] = seed[k] * 0x51633e2du;
    permute_kensler_lanes(c.index, d.sample_count, s, cell, n);
    const Divisor row(d.res_x);
    const uint32_t res_x = d.res_x, res_y = d.res_y;
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        y[k] = row.quotient(cell[k]);
        x[k] = cell[k] - y[k] * res_x;
        s[k] = seed[k] * 0x68bc21ebu;
    }
    permute_kensler_lanes(x, res_x, s, sx, n);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) s[k] = seed[k] * 0x02e5be93u;
    permute_kensler_lanes(y, res_y, s, sy, n);
    const float inv = 1.f / float(d.sample_count);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        uint64_t state = c.state[k];
        const float jx = jitter<Jitter>(state, c.inc[k]);
        const float jy = jitter<Jitter>(state, c.inc[k]);
        c.state[k] = draw[k] ? state : c.state[k];
        ux[k] = scaled_below_one(float(x[k] * res_y + sy[k]) + jx, inv);
        uy[k] = scaled_below_one(float(y[k] * res_x + sx[k]) + jy, inv);
    }
}

/// Sampler::orthogonal_1d: dimension dim of Bose's orthogonal array, its column's stratum and
/// the paired column's sub-stratum, jittered.
template <bool Jitter>
void orthogonal_1d(SamplerColumns &c, const SamplerDesc &d, int n, const int *draw, float *u) {
    alignas(64) uint32_t a_ij[Capacity], a_ik[Capacity], s1[Capacity], s2[Capacity], stratum[Capacity], sub[Capacity];
    const uint32_t p = d.res_x;
    const Divisor mod(p);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const uint32_t j = c.dim[k], a0 = c.aux0[k], a1 = c.aux1[k];
        c.dim[k] += draw[k] != 0 ? 1u : 0u;
        const uint32_t pair = (j % 2) ? j - 1 : j + 1;
        const uint32_t ij = mod.remainder(a0 + (j - 1) * a1), ik = mod.remainder(a0 + (pair - 1) * a1);
        a_ij[k] = j == 0 ? a0 : (j == 1 ? a1 : ij);
        a_ik[k] = j == 0 ? a1 : (j == 1 ? a0 : ik);
        const uint32_t seed = dimension_seed(c.seq[k], j);
        s1[k] = seed * 0x51633e2du;
        s2[k] = seed * 0x68bc21ebu;
    }
    permute_kensler_lanes(a_ij, p, s1, stratum, n);
    permute_kensler_lanes(a_ik, p, s2, sub, n);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) stratum[k] = stratum[k] * p + sub[k];
    jittered_1d<Jitter>(c, n, draw, stratum, d.sample_count, u);
}

/// The independent sampler's next_1d (Sampler::uniform), or two for next_2d.
template <int Count>
void uniform_lanes(SamplerColumns &c, int n, const int *draw, float *u0, float *u1) {
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        uint64_t state = c.state[k];
        u0[k] = uniform_float(pcg32_next(state, c.inc[k]));
        if constexpr (Count == 2) u1[k] = uniform_float(pcg32_next(state, c.inc[k]));
        c.state[k] = draw[k] ? state : c.state[k];
    }
}

}  // namespace

void SamplerColumns::begin(const SamplerDesc &desc, int n, const uint64_t *keys) {
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        pcg32_seed(keys[k], uint64_t(index[k]), &state[k], &inc[k]);
        dim[k] = aux0[k] = aux1[k] = aux2[k] = 0;
    }
    if (desc.type == SamplerType::Orthogonal) {
        // The sample's row of the orthogonal array.
        alignas(64) uint32_t row[Capacity];
        permute_kensler_lanes(index, desc.sample_count, seq, row, n);
        const Divisor columns(desc.res_x);
        const uint32_t res = desc.res_x;
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            aux0[k] = columns.quotient(row[k]);
            aux1[k] = row[k] - aux0[k] * res;
        }
    } else if (desc.type == SamplerType::LowDiscrepancy) {
        // The pixel's scrambles: 1D, and 2D x, y.
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            uint32_t v1 = 0x48bc48ebu, x = seq[k], y = 0x98bc51abu;
            uint32_t s = seq[k];
            tea(s, v1);
            tea(x, y);
            aux0[k] = s, aux1[k] = x, aux2[k] = y;
        }
    }
}

void SamplerColumns::next_1d(const SamplerDesc &desc, int n, const int *draw, float *u) {
    if (!draw) draw = every_lane();
    alignas(64) uint32_t seed[Capacity];
    switch (desc.type) {
        case SamplerType::Independent: uniform_lanes<1>(*this, n, draw, u, nullptr); return;
        case SamplerType::Orthogonal:
            desc.jitter ? orthogonal_1d<true>(*this, desc, n, draw, u) : orthogonal_1d<false>(*this, desc, n, draw, u);
            return;
        case SamplerType::Stratified:
        case SamplerType::Multijitter:
            next_seeds(*this, n, draw, desc.type == SamplerType::Multijitter ? 0x45fbe943u : 1u, seed);
            desc.jitter ? permuted_1d<true>(*this, desc, n, draw, seed, u)
                        : permuted_1d<false>(*this, desc, n, draw, seed, u);
            return;
        case SamplerType::LowDiscrepancy: {
            next_seeds(*this, n, draw, 1u, seed);
            alignas(64) uint32_t i[Capacity];
            permute_pow2_lanes(index, desc.sample_count, seed, i, n);
#pragma GCC ivdep
            for (int k = 0; k < n; ++k) u[k] = radical_inverse_2(i[k], aux0[k]);
            return;
        }
    }
}

void SamplerColumns::next_2d(const SamplerDesc &desc, int n, const int *draw, float *ux, float *uy) {
    if (!draw) draw = every_lane();
    alignas(64) uint32_t seed[Capacity];
    switch (desc.type) {
        case SamplerType::Independent: uniform_lanes<2>(*this, n, draw, ux, uy); return;
        case SamplerType::Orthogonal:
            next_1d(desc, n, draw, ux);
            next_1d(desc, n, draw, uy);
            return;
        case SamplerType::Stratified:
            next_seeds(*this, n, draw, 1u, seed);
            desc.jitter ? stratified_2d<true>(*this, desc, n, draw, seed, ux, uy)
                        : stratified_2d<false>(*this, desc, n, draw, seed, ux, uy);
            return;
        case SamplerType::Multijitter:
            next_seeds(*this, n, draw, 1u, seed);
            desc.jitter ? multijitter_2d<true>(*this, desc, n, draw, seed, ux, uy)
                        : multijitter_2d<false>(*this, desc, n, draw, seed, ux, uy);
            return;
        case SamplerType::LowDiscrepancy: {
            // A scrambled (0, 2)-sequence: the radical inverse and sobol_2, whose loop over the
            // index's bits runs here over all lanes a bit at a time (the index is below n).
            next_seeds(*this, n, draw, 1u, seed);
            alignas(64) uint32_t i[Capacity], scramble[Capacity];
            permute_pow2_lanes(index, desc.sample_count, seed, i, n);
            std::copy(aux2, aux2 + n, scramble);
            uint32_t v = 1u << 31;
            for (uint32_t bit = 1; bit < desc.sample_count; bit <<= 1, v ^= v >> 1) {
#pragma GCC ivdep
                for (int k = 0; k < n; ++k) scramble[k] ^= (i[k] & bit) ? v : 0u;
            }
#pragma GCC ivdep
            for (int k = 0; k < n; ++k) {
                ux[k] = radical_inverse_2(i[k], aux1[k]);
                uy[k] = float(scramble[k] >> 8) * 0x1p-24f;
            }
            return;
        }
    }
}

}  // namespace rbpt
