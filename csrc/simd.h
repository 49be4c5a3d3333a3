// Float lanes for the BVH: the vector operations of the slab test and of the packed
// ray-triangle test, eight lanes wide where the build targets AVX (AVX2 and AVX-512 machines
// alike) and four with SSE (the x86-64 baseline) otherwise; and the wavefront's moves of
// lanes in SIMD registers: compaction of columns, lists of lanes.
#pragma once

#include <immintrin.h>

#include <cstdint>

namespace rbpt::simd {

#if defined(__AVX__)
constexpr int Width = 8;
using V = __m256;
inline V set1(float x) { return _mm256_set1_ps(x); }
inline V zero() { return _mm256_setzero_ps(); }
inline V load(const float *p) { return _mm256_load_ps(p); }
inline void store(float *p, V a) { _mm256_storeu_ps(p, a); }
inline V add(V a, V b) { return _mm256_add_ps(a, b); }
inline V sub(V a, V b) { return _mm256_sub_ps(a, b); }
inline V mul(V a, V b) { return _mm256_mul_ps(a, b); }
inline V div(V a, V b) { return _mm256_div_ps(a, b); }
inline V min(V a, V b) { return _mm256_min_ps(a, b); }
inline V max(V a, V b) { return _mm256_max_ps(a, b); }
inline V bit_or(V a, V b) { return _mm256_or_ps(a, b); }
inline V bit_and(V a, V b) { return _mm256_and_ps(a, b); }
inline V and_not(V a, V b) { return _mm256_andnot_ps(a, b); }  ///< ~a & b
inline V eq(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_EQ_OQ); }
inline V neq(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_NEQ_UQ); }
inline V lt(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_LT_OQ); }
inline V le(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_LE_OQ); }
inline V gt(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_GT_OQ); }
inline int mask(V a) { return _mm256_movemask_ps(a); }
#else
constexpr int Width = 4;
using V = __m128;
inline V set1(float x) { return _mm_set1_ps(x); }
inline V zero() { return _mm_setzero_ps(); }
inline V load(const float *p) { return _mm_load_ps(p); }
inline void store(float *p, V a) { _mm_storeu_ps(p, a); }
inline V add(V a, V b) { return _mm_add_ps(a, b); }
inline V sub(V a, V b) { return _mm_sub_ps(a, b); }
inline V mul(V a, V b) { return _mm_mul_ps(a, b); }
inline V div(V a, V b) { return _mm_div_ps(a, b); }
inline V min(V a, V b) { return _mm_min_ps(a, b); }
inline V max(V a, V b) { return _mm_max_ps(a, b); }
inline V bit_or(V a, V b) { return _mm_or_ps(a, b); }
inline V bit_and(V a, V b) { return _mm_and_ps(a, b); }
inline V and_not(V a, V b) { return _mm_andnot_ps(a, b); }  ///< ~a & b
inline V eq(V a, V b) { return _mm_cmpeq_ps(a, b); }
inline V neq(V a, V b) { return _mm_cmpneq_ps(a, b); }
inline V lt(V a, V b) { return _mm_cmplt_ps(a, b); }
inline V le(V a, V b) { return _mm_cmple_ps(a, b); }
inline V gt(V a, V b) { return _mm_cmpgt_ps(a, b); }
inline int mask(V a) { return _mm_movemask_ps(a); }
#endif

/// |a| in every lane.
inline V abs(V a) { return and_not(set1(-0.f), a); }

#if defined(__AVX2__) && !defined(__AVX512F__)
/// The permutation that moves the lanes set in an 8-bit mask to the front, in order (AVX2
/// has no compression): lane i of compress_indices(mask) is the index of the mask's i-th set
/// bit (the lanes beyond its count take 0).
struct CompressTable {
    uint64_t indices[256] = {};  ///< eight byte-sized lane indices per mask
    constexpr CompressTable() {
        for (int mask = 0; mask < 256; ++mask) {
            int j = 0;
            for (int i = 0; i < 8; ++i)
                if (mask >> i & 1) indices[mask] |= uint64_t(i) << (8 * j++);
        }
    }
};
inline constexpr CompressTable compress_table{};
inline __m256i compress_indices(int mask) {
    return _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(int64_t(compress_table.indices[mask])));
}
#endif

/// Move the lanes k of [0, n) where alive[k] != 0 to the front of each column, in order, and
/// return their number: 32-bit columns `words` and 64-bit columns `doubles`, each holding
/// (and aligned to) whole vectors of 16 lanes beyond n. With AVX-512, sixteen lanes of a
/// column at a time, compressed in a register (in place: the lanes stored go no further than
/// the sixteen just loaded; a masked store, as a compressing store to memory is slow on AMD's
/// Zen 4). With AVX2, eight at a time, moved by one permute and stored whole: a store reaches
/// no further than the eight lanes just loaded, and leaves copies of them beyond the live
/// lanes, which are not live. Otherwise one lane at a time.
template <size_t NW, size_t ND>
inline int compact_columns(uint32_t *const (&words)[NW], uint64_t *const (&doubles)[ND], const int *alive, int n) {
    int live = 0;
#if defined(__AVX512F__)
    for (int k = 0; k < n; k += 16) {
        const __mmask16 in = __mmask16(n - k >= 16 ? 0xffffu : (1u << (n - k)) - 1u);
        const __mmask16 on = _mm512_mask_cmpneq_epi32_mask(in, _mm512_load_si512(alive + k), _mm512_setzero_si512());
        if (on == 0xffffu && live == k) {
            live += 16;  // (a full run in place)
            continue;
        }
        const int count = __builtin_popcount(on);
        const __mmask16 out = __mmask16((1u << count) - 1u);
        for (uint32_t *w : words) {
            _mm512_mask_storeu_epi32(w + live, out, _mm512_maskz_compress_epi32(on, _mm512_load_si512(w + k)));
        }
        const __mmask8 lo = __mmask8(on & 0xffu), hi = __mmask8(on >> 8);
        const int count_lo = __builtin_popcount(lo);
        for (uint64_t *d : doubles) {
            // (Both halves loaded before either is stored: the first's store may reach the second.)
            const __m512i a = _mm512_maskz_compress_epi64(lo, _mm512_load_si512(d + k));
            const __m512i c = _mm512_maskz_compress_epi64(hi, _mm512_load_si512(d + k + 8));
            _mm512_mask_storeu_epi64(d + live, __mmask8((1u << count_lo) - 1u), a);
            _mm512_mask_storeu_epi64(d + live + count_lo, __mmask8((1u << (count - count_lo)) - 1u), c);
        }
        live += count;
    }
#elif defined(__AVX2__)
    for (int k = 0; k < n; k += 8) {
        const int in = n - k >= 8 ? 0xff : (1 << (n - k)) - 1;
        const __m256i dead = _mm256_cmpeq_epi32(_mm256_load_si256(reinterpret_cast<const __m256i *>(alive + k)),
                                                _mm256_setzero_si256());
        const int on = ~_mm256_movemask_ps(_mm256_castsi256_ps(dead)) & in;
        if (on == 0xff && live == k) {
            live += 8;  // (a full run in place)
            continue;
        }
        const __m256i move = compress_indices(on);
        for (uint32_t *w : words) {
            const __m256i v = _mm256_load_si256(reinterpret_cast<const __m256i *>(w + k));
            _mm256_storeu_si256(reinterpret_cast<__m256i *>(w + live), _mm256_permutevar8x32_epi32(v, move));
        }
        // A 64-bit column four lanes at a time, as pairs of 32-bit lanes: each bit of the
        // half's mask doubled.
        const int lo = on & 15, hi = on >> 4, count_lo = __builtin_popcount(lo);
        auto doubled = [](int m) {
            const int spread = (m & 1) | (m & 2) << 1 | (m & 4) << 2 | (m & 8) << 3;
            return spread | spread << 1;
        };
        const __m256i move_lo = compress_indices(doubled(lo)), move_hi = compress_indices(doubled(hi));
        for (uint64_t *d : doubles) {
            const __m256i a = _mm256_permutevar8x32_epi32(_mm256_load_si256(reinterpret_cast<const __m256i *>(d + k)), move_lo);
            const __m256i c = _mm256_permutevar8x32_epi32(_mm256_load_si256(reinterpret_cast<const __m256i *>(d + k + 4)), move_hi);
            _mm256_storeu_si256(reinterpret_cast<__m256i *>(d + live), a);
            _mm256_storeu_si256(reinterpret_cast<__m256i *>(d + live + count_lo), c);
        }
        live += __builtin_popcount(on);
    }
#else
    for (int k = 0; k < n; ++k) {
        if (!alive[k]) continue;
        if (live != k) {
            for (uint32_t *w : words) w[live] = w[k];
            for (uint64_t *d : doubles) d[live] = d[k];
        }
        ++live;
    }
#endif
    return live;
}

/// The indices k in [0, n) where values[k] == value, in increasing order, written to list
/// (which must hold n entries: what lies beyond their count is overwritten); returns their
/// count. With AVX-512, sixteen at a time by compressing a vector of indices; with AVX2,
/// eight at a time, moved by a permute and stored whole (no further than the eight indices
/// just tested). (GCC does not vectorise the scalar loop's stores at a running position.)
inline int select_indices(const int *values, int n, int value, int *list) {
    int m = 0, k = 0;
#if defined(__AVX512F__)
    __m512i index = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const __m512i sixteen = _mm512_set1_epi32(16), want = _mm512_set1_epi32(value);
    for (; k + 16 <= n; k += 16) {
        const __mmask16 equal = _mm512_cmpeq_epi32_mask(_mm512_loadu_si512(values + k), want);
        const int count = __builtin_popcount(equal);
        // (Compressed in a register, then a masked store: a compressing store to memory is
        // slow on AMD's Zen 4.)
        _mm512_mask_storeu_epi32(list + m, __mmask16((1u << count) - 1u), _mm512_maskz_compress_epi32(equal, index));
        m += count;
        index = _mm512_add_epi32(index, sixteen);
    }
#elif defined(__AVX2__)
    __m256i index = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256i eight = _mm256_set1_epi32(8), want = _mm256_set1_epi32(value);
    for (; k + 8 <= n; k += 8) {
        const __m256i v = _mm256_loadu_si256(reinterpret_cast<const __m256i *>(values + k));
        const int equal = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(v, want)));
        _mm256_storeu_si256(reinterpret_cast<__m256i *>(list + m), _mm256_permutevar8x32_epi32(index, compress_indices(equal)));
        m += __builtin_popcount(equal);
        index = _mm256_add_epi32(index, eight);
    }
#endif
    for (; k < n; ++k) {
        list[m] = k;
        m += values[k] == value;
    }
    return m;
}

/// The length of a list of `count` indices rounded up to whole vectors of 16 lanes, its
/// entries from `count` on repeating its last one (the list must hold that many): loops over
/// a list run to that length and ignore the results beyond `count`, so that they end
/// without the remainder GCC runs one lane at a time after a vectorised loop (which for a
/// long loop body costs about as much as the vectors).
inline int pad_indices(int *list, int count) {
    const int padded = (count + 15) & ~15;
    for (int j = count; j < padded; ++j) list[j] = list[count - 1];
    return padded;
}

}  // namespace rbpt::simd
