// The sensors (`perspective`, `orthographic`, `thinlens`) and their film geometry: pixel -> ray,
// and the reconstruction filter whose weights splat each sample into the pixels around it (as
// Mitsuba's film does). Every sensor's ray weight is 1, as in Mitsuba's RGB variants.
#pragma once

#include <array>
#include <vector>

#include "math.h"
#include "sampler.h"
#include "warp.h"

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

    /// Derive the constants eval() uses from the parameters above; call after setting them.
    void prepare();
    /// Mitsuba's 1D filter profile (box: 1; tent: 1 - |x|/r; gaussian: exp(-x^2/2s^2) - bias;
    /// mitchell: the cubic of Mitchell and Netravali 1988 in |x| < 2; lanczos: windowed sinc).
    float eval(float x) const;
    /// eval() at the n offsets x0, x0 + 1, ..., x0 + n - 1 (a row of splat weights). The box
    /// and the tent inline (each sample's splat and gather take two rows), the others not.
    void eval_row(float x0, int n, float *w) const {
        if (type == FilterType::Tent) {
            for (int k = 0; k < n; ++k) w[k] = std::max(0.f, 1.f - std::abs((x0 + float(k)) * inv_radius_));
        } else if (type == FilterType::Box) {
            for (int k = 0; k < n; ++k) w[k] = std::abs(x0 + float(k)) <= radius ? 1.f : 0.f;
        } else {
            eval_row_other(x0, n, w);
        }
    }
    /// eval_row() for `count` samples at once, sample k's row starting at x0[k]: weight o of
    /// sample k goes to w[o * stride + k] (o < n). For the tent and the gaussian a loop over
    /// the samples that the compiler vectorises (the same operations as eval_row's, so the
    /// same weights); the others call eval_row per sample.
    void eval_rows(const float *x0, int count, int n, float *w, int stride) const;
    /// The largest border() the film handles (radius 16.5 pixels).
    static constexpr int MaxBorder = 16;
    /// How many pixels a sample's splat reaches on each side of the pixel it lies in.
    int border() const {
        return type == FilterType::Box ? 0 : std::max(0, int(std::ceil(radius - 0.5f)));
    }

private:
    void eval_row_other(float x0, int n, float *w) const;
    /// 1 / radius (the tent's weight is 1 - |x| / radius, as Mitsuba's, with a product).
    float inv_radius_ = std::numeric_limits<float>::quiet_NaN();
    /// The gaussian's exponent factor -1 / (2 stddev^2) and its value at the radius
    /// (subtracted so that the profile reaches zero there). NaN until prepare().
    struct {
        float alpha = std::numeric_limits<float>::quiet_NaN();
        float bias = std::numeric_limits<float>::quiet_NaN();
    } gaussian_;
};

enum class CameraType { Perspective, Orthographic, ThinLens };

struct Camera {
    CameraType type = CameraType::Perspective;
    /// Columns of the camera-to-world matrix, normalised: local x (left), y (up), z (forward),
    /// and the origin.
    Vec3 axis_x, axis_y, axis_z, origin;
    /// The same columns unnormalised (orthographic: their lengths scale the viewed region).
    Vec3 frame_x, frame_y, frame_z;
    float tan_half_x = 1.f, tan_half_y = 1.f;  ///< half extent of the image plane at z = 1
    float near_clip = 1e-2f, far_clip = 1e4f;
    float aperture_radius = 0.f, focus_distance = 1e4f;  ///< thinlens
    int film_width = 1, film_height = 1;
    int crop_x = 0, crop_y = 0, crop_width = 1, crop_height = 1;
    Filter filter;
    SamplerDesc sampler;  ///< the sensor's sampler, as in Mitsuba

    /// The ray through film position `pos` in pixels (0, 0 = top left corner of the full
    /// film), drawing the aperture sample (thinlens only) from `sampler`.
    Ray sample_ray(Vec2 pos, Sampler &sampler) const {
        return ray_for(pos, type == CameraType::ThinLens ? sampler.next_2d() : Vec2{0.5f, 0.5f});
    }

    /// The ray through film position `pos` and aperture sample `u` (a point of the unit
    /// square, mapped to the lens disk). Rays start on the near clip plane (tmin) and end on
    /// the far one (tmax), as Mitsuba's.
    Ray ray_for(Vec2 pos, Vec2 u) const {
        if (type == CameraType::Orthographic) return orthographic_ray(pos);
        if (type == CameraType::ThinLens) return thin_lens_ray(pos, u);
        return perspective_ray(pos);
    }

    /// The perspective sensor's ray through film position `pos`: through the pinhole at the
    /// origin.
    RBPT_INLINE Ray perspective_ray(Vec2 pos) const {
        float sx = 1.f - 2.f * (pos.x / float(film_width));
        float sy = 1.f - 2.f * (pos.y / float(film_height));
        // The local direction (x, y, 1), normalised once it is in world space (the axes need
        // not be orthogonal); the clip planes are at local z = near_clip and far_clip.
        float x = sx * tan_half_x, y = sy * tan_half_y, len = std::sqrt(x * x + y * y + 1.f);
        Ray ray;
        ray.o = origin;
        ray.d = normalize(axis_x * x + axis_y * y + axis_z);
        ray.tmin = near_clip * len;
        ray.tmax = far_clip * len;
        return ray;
    }

    /// The region [-1, 1] x [-1/aspect, 1/aspect] of the local z = near_clip plane, mapped by
    /// to_world (whose scale gives the extent), looking along local +z.
    Ray orthographic_ray(Vec2 pos) const;
    /// Through the point `u` picks on the aperture disk towards the point of the focal plane
    /// (local z = focus_distance) that the pinhole ray reaches.
    Ray thin_lens_ray(Vec2 pos, Vec2 u) const;

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
        filter.eval_row(splat_row_start(px, b, pos.x), 2 * b + 1, wx);
        filter.eval_row(splat_row_start(py, b, pos.y), 2 * b + 1, wy);
    }
    /// The first offset of a splat's row: pixel p + k has its centre at p + k + 0.5, and the
    /// offsets from the sample at `pos` grow by 1 along the row, from k = -b.
    static float splat_row_start(int p, int b, float pos) { return float(p - b) + 0.5f - pos; }
};

}  // namespace rbpt
