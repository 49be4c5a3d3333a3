// Warping functions from the unit square to directions and points, with their densities
// (Mitsuba's mitsuba/core/warp.h conventions).
#pragma once

#include "math.h"

namespace rbpt::warp {

/// sin and cos of an angle in [-pi/4, pi/4] by the minimax polynomials of Cephes' sinf and
/// cosf (within an ulp or two; no range reduction, no libm call).
RBPT_INLINE Vec2 sincos_octant(float x) {
    float x2 = x * x;
    float s = x + x * x2 * (-1.6666654611e-1f + x2 * (8.3321608736e-3f + x2 * -1.9515295891e-4f));
    float c = 1.f - 0.5f * x2 +
              x2 * x2 * (4.166664568298827e-2f + x2 * (-1.388731625493765e-3f + x2 * 2.443315711809948e-5f));
    return {s, c};
}

/// (cos, sin) of 2 pi u for u in [0, 1]: the angle reduced to [-pi/4, pi/4] around the nearest
/// multiple of pi/2 (exactly: 4 u - j is exact for j = round(4 u)), then sincos_octant and
/// the quadrant's signs and swap. Within a few ulps of libm's; vectorises.
RBPT_INLINE Vec2 cossin_2pi(float u) {
    float x = 4.f * u;
    float j = std::nearbyint(x);
    Vec2 sc = sincos_octant((Pi / 2.f) * (x - j));
    // Quadrant q: cos and sin swap where q is odd; cos is negative in quadrants 1 and 2, sin
    // in 2 and 3. (Two-way selects: GCC does not vectorise the four-way one.)
    int q = int(j) & 3;
    float c = (q & 1) != 0 ? sc.x : sc.y, s = (q & 1) != 0 ? sc.y : sc.x;
    c = c * (q == 1 || q == 2 ? -1.f : 1.f);
    s = s * (q >= 2 ? -1.f : 1.f);
    return {c, s};
}

/// Shirley-Chiu concentric map from [0,1)^2 to the unit disk. The angle is pi/4 t with
/// |t| <= 1, or pi/2 minus such an angle: sin and cos of the octant angle, swapped in the
/// second case. (t's quotient is picked before the one division: in SIMD lanes, where both
/// cases are computed, that is one division instead of two, with the same values.)
RBPT_INLINE Vec2 square_to_uniform_disk_concentric(Vec2 u) {
    float x = 2.f * u.x - 1.f, y = 2.f * u.y - 1.f;
    if (x == 0.f && y == 0.f) return {0.f, 0.f};
    const bool x_major = std::abs(x) > std::abs(y);
    const float r = x_major ? x : y, t = (x_major ? y : x) / r;
    Vec2 sc = sincos_octant((Pi / 4.f) * t);
    return x_major ? Vec2{r * sc.y, r * sc.x} : Vec2{r * sc.x, r * sc.y};
}

/// Cosine-weighted hemisphere around +z; pdf = cos(theta) / pi.
RBPT_INLINE Vec3 square_to_cosine_hemisphere(Vec2 u) {
    Vec2 p = square_to_uniform_disk_concentric(u);
    float z = safe_sqrt(1.f - p.x * p.x - p.y * p.y);
    return {p.x, p.y, z};
}
inline float square_to_cosine_hemisphere_pdf(const Vec3 &v) { return InvPi * std::max(v.z, 0.f); }

/// Uniform direction on the unit sphere; pdf = 1 / (4 pi).
RBPT_INLINE Vec3 square_to_uniform_sphere(Vec2 u) {
    float z = 1.f - 2.f * u.y;
    float r = safe_sqrt(1.f - z * z);
    Vec2 cs = cossin_2pi(u.x);  // (vectorises: the wavefront's environment samples)
    return {r * cs.x, r * cs.y, z};
}

/// Uniform direction in the cone around +z with cos(half-angle) = cos_max.
inline float square_to_uniform_cone_pdf(float cos_max) {
    return 1.f / (2.f * Pi * (1.f - cos_max));
}

/// A point of a sphere of radius `radius` seen from outside it, its centre at dc (|dc|^2 =
/// dc2) from the viewer: uniform in the cone of directions it subtends, as Mitsuba's sphere
/// samples it (with a Taylor expansion for small cones, where 1 - cos_max cancels badly).
/// Returns the unit vector from the centre to the point, and the cone's solid-angle density.
/// (Geometry::sample_direction, and the wavefront's vector stage: inline, so that a loop the
/// compiler vectorises can call it.)
struct SphereConeSample {
    Vec3 n;
    float pdf;
};
RBPT_INLINE SphereConeSample sample_sphere_cone(const Vec3 &dc, float dc2, float radius, Vec2 u) {
    float inv_dc = 1.f / std::sqrt(dc2);
    float sin_max = radius * inv_dc, sin_max2 = sin_max * sin_max;
    float inv_sin_max = 1.f / sin_max, cos_max = safe_sqrt(1.f - sin_max2);
    // (A square as a product, as Mitsuba's dr::sqr: std::pow(x, 2) is not always x * x's
    // rounding.)
    float wide = sin_max2 > 0.00068523f ? 1.f : 0.f;  // (a float flag: see wavefront.cpp)
    float t = (cos_max - 1.f) * u.x + 1.f;
    float sin2 = wide != 0.f ? 1.f - t * t : sin_max2 * u.x;
    float cos = safe_sqrt(1.f - sin2);
    float cos_alpha = sin2 * inv_sin_max + cos * safe_sqrt(1.f - sin2 * inv_sin_max * inv_sin_max);
    float sin_alpha = safe_sqrt(1.f - cos_alpha * cos_alpha);
    Vec2 cs = cossin_2pi(u.y);  // (cos, sin) of phi = 2 pi u.y, without libm
    Vec3 local{cs.x * sin_alpha, cs.y * sin_alpha, cos_alpha};
    return {Frame(dc * -inv_dc).to_world(local),
            wide != 0.f ? square_to_uniform_cone_pdf(cos_max) : 1.f / (Pi * sin_max2)};
}

/// Uniform barycentrics (b1, b2) on a triangle.
inline Vec2 square_to_uniform_triangle(Vec2 u) {
    float t = safe_sqrt(1.f - u.x);
    return {1.f - t, t * u.y};
}

}  // namespace rbpt::warp
