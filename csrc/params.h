// The parameter table: the values the renderer reads for every differentiable scene
// parameter (material inputs, texels, emission), in the number type the path tracer runs on.
// Constant-parameter lookups and bilinear texel gathers are the only places values enter the
// path tracer, which is what lets autodiff types decide what to record.
#pragma once

#include <cstdint>
#include <vector>

#include "math.h"

namespace rbpt {

template <typename S>
struct Params;

/// Plain float/double parameters, read straight from caller-owned contiguous buffers.
template <typename T>
struct Params<RGB<T>> {
    std::vector<const T *> data;
    std::vector<int64_t> numel;

    /// RGB value of a parameter of 3 entries, or a scalar broadcast to RGB.
    RGB<T> spectrum(int p) const {
        const T *d = data[p];
        return numel[p] == 1 ? RGB<T>(d[0]) : RGB<T>(d[0], d[1], d[2]);
    }
    T real(int p) const { return data[p][0]; }
    /// Weighted sum of `n` texels (pixel indices) of an (H, W, C) bitmap parameter.
    RGB<T> bilinear(int p, int channels, const int64_t *index, const float *weight, int n) const {
        const T *d = data[p];
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
    float mean(int p) const {
        double sum = 0.0;
        for (int64_t i = 0; i < numel[p]; ++i) sum += double(data[p][i]);
        return numel[p] > 0 ? float(sum / double(numel[p])) : 0.f;
    }
};

}  // namespace rbpt
