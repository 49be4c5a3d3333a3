// The perspective sensor and its film: pixel -> ray, with the reconstruction filter applied by
// importance sampling it (filter importance sampling).
//
// Unlike Mitsuba, which splats every sample into all pixels under the filter and divides by the
// summed weights, each pixel here draws its own sample positions with density proportional to
// the filter (truncated to the film, as Mitsuba's weights are) and averages them. Both converge
// to the same filtered image; ours keeps pixels independent, which makes rendering and its
// adjoint embarrassingly parallel and deterministic.
#pragma once

#include <array>
#include <vector>

#include "math.h"
#include "sampler.h"

namespace rbpt {

enum class FilterType { Box, Tent, Gaussian };

/// A separable reconstruction filter f(x) f(y) of radius `radius` (in pixels).
struct Filter {
    FilterType type = FilterType::Box;
    float radius = 0.5f;
    float stddev = 0.5f;
    /// Gaussian only: CDF of the truncated filter tabulated on `Resolution` equal bins.
    static constexpr int Resolution = 512;
    std::vector<float> cdf;

    /// Mitsuba's 1D filter profile (box: 1; tent: 1 - |x|/r; gaussian: exp(-x^2/2s^2) - bias).
    float eval(float x) const;
    /// Build the sampling table; call after setting type, radius and stddev.
    void prepare();
    /// An offset in [-radius, radius] distributed proportionally to eval().
    float sample(float u) const;
};

struct Camera {
    /// Columns of the camera-to-world matrix: local x (left), y (up), z (forward), origin.
    Vec3 axis_x, axis_y, axis_z, origin;
    float tan_half_x = 1.f, tan_half_y = 1.f;  ///< half extent of the image plane at z = 1
    float near_clip = 1e-2f, far_clip = 1e4f;
    int film_width = 1, film_height = 1;
    int crop_x = 0, crop_y = 0, crop_width = 1, crop_height = 1;
    Filter filter;

    /// Generate the ray through film position (fx, fy) in pixels (0, 0 = top left corner).
    Ray ray_at(float fx, float fy, float *tmin) const {
        float sx = fx / float(film_width), sy = fy / float(film_height);
        Vec3 d_local = normalize(
            Vec3{(1.f - 2.f * sx) * tan_half_x, (1.f - 2.f * sy) * tan_half_y, 1.f});
        Vec3 d = normalize(axis_x * d_local.x + axis_y * d_local.y + axis_z * d_local.z);
        float inv_z = 1.f / d_local.z;
        Ray ray;
        ray.o = origin;
        ray.d = d;
        *tmin = near_clip * inv_z;
        ray.tmax = far_clip * inv_z;
        return ray;
    }

    /// A filter-distributed sample position for pixel (px, py) of the full film; positions are
    /// kept inside the crop window like Mitsuba's sample positions (by rejection).
    Vec2 sample_position(int px, int py, Sampler &sampler) const {
        Vec2 u = sampler.next_2d();
        if (filter.type == FilterType::Box) return {px + u.x, py + u.y};
        return {sample_axis(px, crop_x, crop_x + crop_width, u.x, sampler),
                sample_axis(py, crop_y, crop_y + crop_height, u.y, sampler)};
    }

private:
    float sample_axis(int p, int lo, int hi, float u, Sampler &sampler) const {
        float center = float(p) + 0.5f;
        for (int attempt = 0; attempt < 16; ++attempt) {
            float x = center + filter.sample(u);
            if (x >= float(lo) && x < float(hi)) return x;
            u = sampler.next_1d();
        }
        return center;
    }
};

}  // namespace rbpt
