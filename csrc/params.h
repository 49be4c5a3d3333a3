// The parameter table: the values the renderer reads for every differentiable scene
// parameter (material inputs, texels, emission), in the number type the path tracer runs on.
// Constant-parameter lookups and bilinear texel gathers are the only places values enter the
// path tracer, which is what lets autodiff types decide what to record.
#pragma once

#include <cstdint>
#include <vector>

#include "autodiff.h"
#include "dual.h"
#include "math.h"

namespace rbpt {

template <typename S>
struct Params;

/// One read of a parameter: `n` entries (`channels` values each, starting at `offset`)
/// summed with `weight`; a constant is one entry of weight 1.
struct ParamRead {
    int param = -1, channels = 1, n = 0;
    int64_t offset[4] = {0, 0, 0, 0};
    float weight[4] = {0.f, 0.f, 0.f, 0.f};
};

/// The reads of watched parameters that a plain render makes (the backward pass in lanes,
/// wavefront.h, watches the differentiated ones): how many, and the last.
struct ParamReadLog {
    const char *watched = nullptr;  ///< per parameter: nonzero where reads are logged
    int count = 0;
    ParamRead last;

    void note(int p, int channels, int n, const int64_t *index, const float *weight) {
        ++count;
        last.param = p, last.channels = channels, last.n = n;
        for (int k = 0; k < n; ++k) {
            last.offset[k] = index ? index[k] * channels : 0;
            last.weight[k] = weight ? weight[k] : 1.f;
        }
    }
};

namespace detail {
template <typename T>
float mean_of(const T *d, int64_t n) {
    double sum = 0.0;
    for (int64_t i = 0; i < n; ++i) sum += double(d[i]);
    return n > 0 ? float(sum / double(n)) : 0.f;
}
}  // namespace detail

/// Plain float/double parameters, read straight from caller-owned contiguous buffers.
template <typename T>
struct Params<RGB<T>> {
    std::vector<const T *> data;
    std::vector<int64_t> numel;
    ParamReadLog *log = nullptr;  ///< if set, notes the reads of the parameters it watches

    /// RGB value of a parameter of 3 entries, or a scalar broadcast to RGB. (Inlined: called,
    /// its value came back through the stack in two stores that the caller's loads spanned, a
    /// store-forwarding stall at each of the backward pass's lookups in the shade stage.)
    RBPT_INLINE RGB<T> spectrum(int p) const {
        if (log && log->watched[p]) log->note(p, numel[p] == 1 ? 1 : 3, 1, nullptr, nullptr);
        return value_of(data[p], numel[p]);
    }
    T real(int p) const {
        if (log && log->watched[p]) log->note(p, 1, 1, nullptr, nullptr);
        return data[p][0];
    }
    /// Weighted sum of `n` texels (pixel indices) of an (H, W, C) bitmap parameter.
    RGB<T> bilinear(int p, int channels, const int64_t *index, const float *weight, int n) const {
        if (log && log->watched[p]) log->note(p, channels, n, index, weight);
        return gather(data[p], channels, index, weight, n);
    }

    static RGB<T> value_of(const T *d, int64_t numel) {
        return numel == 1 ? RGB<T>(d[0]) : RGB<T>(d[0], d[1], d[2]);
    }
    static RGB<T> gather(const T *d, int channels, const int64_t *index, const float *weight, int n) {
        RGB<T> r(T(0));
        for (int k = 0; k < n; ++k) {
            const T *texel = d + index[k] * channels;
            T w = T(weight[k]);
            if (channels == 1) {
                r += RGB<T>(w * texel[0]);
            } else {
                r += RGB<T>(w * texel[0], w * texel[1], w * texel[2]);
            }
        }
        return r;
    }
    /// Detached mean over a parameter's entries (for sampling weights).
    float mean(int p) const { return detail::mean_of(data[p], numel[p]); }
    bool differentiable(int) const { return false; }
};

/// Reverse mode: parameters that require gradients are read as sink nodes whose backward step
/// adds the incoming adjoint into this worker's gradient buffer (`grad`, one per parameter;
/// nullptr for constants, which record nothing). Buffers are double whatever T is: a float
/// sum stops growing once it is 2^24 times the terms added to it.
template <typename T>
struct Params<Var<T>> {
    std::vector<const T *> data;
    std::vector<int64_t> numel;
    std::vector<double *> grad;

    Var<T> spectrum(int p) const {
        RGB<T> v = Params<RGB<T>>::value_of(data[p], numel[p]);
        double *g = grad[p];
        if (!g) return Var<T>(v);
        return Var<T>(v, g, numel[p] == 1 ? 1 : 3);
    }
    Var<T> real(int p) const { return spectrum(p); }
    Var<T> bilinear(int p, int channels, const int64_t *index, const float *weight, int n) const {
        RGB<T> v = Params<RGB<T>>::gather(data[p], channels, index, weight, n);
        double *g = grad[p];
        if (!g) return Var<T>(v);
        // Scatter the adjoint to the (up to) four texels, weighted as in the lookup.
        int64_t offset[4];
        for (int k = 0; k < n; ++k) offset[k] = index[k] * channels;
        return Var<T>(v, g, channels, n, offset, weight);
    }
    float mean(int p) const { return detail::mean_of(data[p], numel[p]); }
    bool differentiable(int p) const { return grad[p] != nullptr; }
};

/// Forward mode: each parameter carries a tangent (nullptr: zero tangent).
template <typename T>
struct Params<Dual<T>> {
    std::vector<const T *> data;
    std::vector<int64_t> numel;
    std::vector<const T *> tangent;

    Dual<T> spectrum(int p) const {
        RGB<T> v = Params<RGB<T>>::value_of(data[p], numel[p]);
        if (!tangent[p]) return Dual<T>(v);
        return Dual<T>(v, Params<RGB<T>>::value_of(tangent[p], numel[p]));
    }
    Dual<T> real(int p) const { return spectrum(p); }
    Dual<T> bilinear(int p, int channels, const int64_t *index, const float *weight, int n) const {
        RGB<T> v = Params<RGB<T>>::gather(data[p], channels, index, weight, n);
        if (!tangent[p]) return Dual<T>(v);
        return Dual<T>(v, Params<RGB<T>>::gather(tangent[p], channels, index, weight, n));
    }
    float mean(int p) const { return detail::mean_of(data[p], numel[p]); }
    bool differentiable(int p) const { return tangent[p] != nullptr; }
};

}  // namespace rbpt
