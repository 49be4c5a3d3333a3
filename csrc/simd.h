// Float lanes for the BVH: the vector operations of the slab test and of the packed
// ray-triangle test, eight lanes wide where the build targets AVX (AVX2 and AVX-512 machines
// alike) and four with SSE (the x86-64 baseline) otherwise.
#pragma once

#include <immintrin.h>

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

/// The indices k in [0, n) where values[k] == value, in increasing order, written to list
/// (which must hold n entries, or one more than their count); returns their count. With
/// AVX-512, sixteen at a time by compressing a vector of indices (GCC does not vectorise the
/// scalar loop's stores at a running position).
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
