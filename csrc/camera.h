// The perspective sensor and its film geometry: pixel -> ray, and the reconstruction filter
// whose weights splat each sample into the pixels around it (as Mitsuba's film does).
#pragma once

#include <array>
#include <vector>

#include "math.h"
#include "sampler.h"

namespace rbpt {

enum class FilterType { Box, Tent, Gaussian, Mitchell, Lanczos };

/// A separable reconstruction filter f(x) f(y) of radius `radius` (in pixels). Mitchell-
/// Netravali (also Catmull-Rom: B = 0, C = 1/2) and Lanczos have negative lobes: weights may
/// be negative, and a pixel is still sum w L / sum w, as in Mitsuba.
struct Filter {
    FilterType type = FilterType::Box;
    float radius = 0.5f;
    float stddev = 0.5f;
    float b = 1.f / 3.f, c = 1.f / 3.f;  ///< Mitchell-Netravali's B and C (radius 2)
    int lobes = 3;                        ///< Lanczos: sinc(x) sinc(x / lobes), radius = lobes

    /// Mitsuba's 1D filter profile (box: 1; tent: 1 - |x|/r; gaussian: exp(-x^2/2s^2) - bias;
    /// mitchell: the cubic of Mitchell and Netravali 1988 in |x| < 2; lanczos: windowed sinc).
    float eval(float x) const;
    /// eval() at the n offsets x0, x0 + 1, ..., x0 + n - 1 (a row of splat weights).
    void eval_row(float x0, int n, float *w) const;
    /// The largest border() the film handles (radius 16.5 pixels).
    static constexpr int MaxBorder = 16;
    /// How many pixels a sample's splat reaches on each side of the pixel it lies in.
    int border() const {
        return type == FilterType::Box ? 0 : std::max(0, int(std::ceil(radius - 0.5f)));
    }
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

    /// A sample position uniformly distributed in pixel (px, py) of the full film.
    Vec2 sample_position(int px, int py, Sampler &sampler) const {
        Vec2 u = sampler.next_2d();
        return {float(px) + u.x, float(py) + u.y};
    }

    /// Filter weights of a sample at film position `pos` taken in pixel (px, py), for the
    /// 2b + 1 pixels px - b .. px + b (and likewise in y), b = filter.border().
    void splat_weights(Vec2 pos, int px, int py, float *wx, float *wy) const {
        int b = filter.border();
        if (b == 0) {  // box: the sample's own pixel only
            wx[0] = wy[0] = 1.f;
            return;
        }
        // Pixel px + k has its centre at px + k + 0.5; the offsets grow by 1 along the row.
        filter.eval_row(float(px - b) + 0.5f - pos.x, 2 * b + 1, wx);
        filter.eval_row(float(py - b) + 0.5f - pos.y, 2 * b + 1, wy);
    }
};

}  // namespace rbpt
