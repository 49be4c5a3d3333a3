// Warping functions from the unit square to directions and points, with their densities
// (Mitsuba's mitsuba/core/warp.h conventions).
#pragma once

#include "math.h"

namespace rbpt::warp {

/// Shirley-Chiu concentric map from [0,1)^2 to the unit disk.
RBPT_INLINE Vec2 square_to_uniform_disk_concentric(Vec2 u) {
    float x = 2.f * u.x - 1.f, y = 2.f * u.y - 1.f;
    if (x == 0.f && y == 0.f) return {0.f, 0.f};
    float r, phi;
    if (std::abs(x) > std::abs(y)) {
        r = x;
        phi = (Pi / 4.f) * (y / x);
    } else {
        r = y;
        phi = Pi / 2.f - (Pi / 4.f) * (x / y);
    }
    return {r * std::cos(phi), r * std::sin(phi)};
}

/// Cosine-weighted hemisphere around +z; pdf = cos(theta) / pi.
RBPT_INLINE Vec3 square_to_cosine_hemisphere(Vec2 u) {
    Vec2 p = square_to_uniform_disk_concentric(u);
    float z = safe_sqrt(1.f - p.x * p.x - p.y * p.y);
    return {p.x, p.y, z};
}
inline float square_to_cosine_hemisphere_pdf(const Vec3 &v) { return InvPi * std::max(v.z, 0.f); }

/// Uniform direction on the unit sphere; pdf = 1 / (4 pi).
inline Vec3 square_to_uniform_sphere(Vec2 u) {
    float z = 1.f - 2.f * u.y;
    float r = safe_sqrt(1.f - z * z);
    float phi = 2.f * Pi * u.x;
    return {r * std::cos(phi), r * std::sin(phi), z};
}

/// Uniform direction in the cone around +z with cos(half-angle) = cos_max.
inline float square_to_uniform_cone_pdf(float cos_max) {
    return 1.f / (2.f * Pi * (1.f - cos_max));
}

/// Uniform barycentrics (b1, b2) on a triangle.
inline Vec2 square_to_uniform_triangle(Vec2 u) {
    float t = safe_sqrt(1.f - u.x);
    return {1.f - t, t * u.y};
}

}  // namespace rbpt::warp
