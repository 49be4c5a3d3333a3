// Isotropic microfacet distributions (Beckmann and GGX) with Smith shadowing and sampling of
// visible normals, after Mitsuba's MicrofacetDistribution. D and G1 are templated on the
// roughness type R (so that roughness can be differentiated); sampling is detached (float).
//
// Unlike Mitsuba, the Beckmann G1 is the exact Smith term (with erf) instead of Mitsuba's
// rational approximation (relative difference below 0.35%), so that the density of the
// visible-normal sampler integrates to one exactly.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#include "math.h"

namespace rbpt {

enum class MicrofacetType { Beckmann, GGX };

/// Normal distribution D(m) of microfacet normal m (local frame, z up).
template <typename R>
R microfacet_D(MicrofacetType type, const R &alpha, const Vec3 &m) {
    using std::exp;
    float cos2 = m.z * m.z, xy2 = m.x * m.x + m.y * m.y;
    if (m.z <= 0.f) return R(0.f);
    R a2 = alpha * alpha;
    R result;
    if (type == MicrofacetType::Beckmann) {
        if constexpr (std::is_same_v<R, float>) {
            // Float renders: exp_poly, as the wavefront's lanes (beckmann_D); below e^-87,
            // where it stops, D is below the cut-off but at normals within 1e-4 of grazing.
            float e = -(xy2 / cos2) / a2;
            if (e < -87.f) return 0.f;
            result = exp_poly(e) / (Pi * a2 * (cos2 * cos2));
        } else {
            // Beyond e^-150, D is below the cut-off below for any alpha above 1e-10 (and exp
            // would take libm's slow underflow path).
            if (-(xy2 / cos2) / detach_real(a2) < -150.f) return R(0.f);
            result = exp(-(xy2 / cos2) / a2) / (Pi * a2 * (cos2 * cos2));
        }
    } else {
        R t = xy2 / a2 + cos2;
        result = 1.f / (Pi * a2 * t * t);
    }
    // As Mitsuba: drop values too small to matter, avoiding underflow downstream.
    return detach_real(result) * m.z > 1e-20f ? result : R(0.f);
}

/// erfc(z) for float z >= 0 (Numerical Recipes' erfcc: fractional error below 1.2e-7, plus the
/// rounding of z^2 in float), on exp_poly, so that vectorised loops can call it.
RBPT_INLINE float erfc_poly(float z) {
    float t = 1.f / (1.f + 0.5f * z);
    float p = 0.17087277f;
    p = p * t - 0.82215223f;
    p = p * t + 1.48851587f;
    p = p * t - 1.13520398f;
    p = p * t + 0.27886807f;
    p = p * t - 0.18628806f;
    p = p * t + 0.09678418f;
    p = p * t + 0.37409196f;
    p = p * t + 1.00002368f;
    p = p * t - 1.26551223f;
    return t * exp_poly(-z * z + p);
}

/// Smith's masking function G1(v, m) for direction v and microfacet normal m, of the
/// distribution `Type` (a template argument for loops over one distribution, which inline it).
/// With VectorMath, Beckmann's takes erf and exp from erfc_poly and exp_poly (float only):
/// within 2e-7 of libm's, and vectorisable. (Forced inline, with the polynomials: GCC's size
/// limits left Beckmann's out of line, and the tables' vectorised loop with it.)
template <MicrofacetType Type, bool VectorMath = false, typename R>
RBPT_INLINE R smith_G1(const R &alpha, const Vec3 &v, const Vec3 &m) {
    using std::erf;
    using std::exp;
    using std::sqrt;
    if (dot(v, m) * v.z <= 0.f) return R(0.f);  // the back of a microfacet is never seen
    float xy2 = v.x * v.x + v.y * v.y;
    if (xy2 == 0.f) return R(1.f);
    float tan2 = xy2 / (v.z * v.z);
    if constexpr (Type == MicrofacetType::Beckmann) {
        R a = 1.f / (alpha * std::sqrt(tan2));
        // Beyond a = 9, lambda < 1e-37: G1 is 1 in float and double (and exp would underflow).
        if (detach_real(a) > 9.f) return R(1.f);
        R lambda;
        if constexpr (VectorMath) {
            static_assert(std::is_same_v<R, float>, "VectorMath is for float");
            lambda = erfc_poly(a) * -0.5f + exp_poly(-a * a) / (a * (2.f * 1.7724538509055159f));
        } else {
            lambda = (erf(a) - 1.f) * 0.5f + exp(-a * a) / (a * (2.f * 1.7724538509055159f));
        }
        return 1.f / (1.f + lambda);
    } else {
        return 2.f / (1.f + sqrt(1.f + alpha * alpha * tan2));
    }
}

/// Smith's masking function G1(v, m) for direction v and microfacet normal m.
/// (Float renders take Beckmann's from the polynomials, as the wavefront's lanes do.)
template <typename R>
R smith_G1(MicrofacetType type, const R &alpha, const Vec3 &v, const Vec3 &m) {
    return type == MicrofacetType::Beckmann
               ? smith_G1<MicrofacetType::Beckmann, std::is_same_v<R, float>>(alpha, v, m)
               : smith_G1<MicrofacetType::GGX>(alpha, v, m);
}

/// Density of sample_visible_normal(): G1(wi, m) |wi.m| D(m) / cos(wi).
template <typename R>
R visible_normal_pdf(MicrofacetType type, const R &alpha, const Vec3 &wi, const Vec3 &m) {
    if (wi.z <= 0.f) return R(0.f);
    return smith_G1(type, alpha, wi, m) * std::abs(dot(wi, m)) * microfacet_D(type, alpha, m) /
           wi.z;
}

/// Sampling of the microfacet normals visible from one direction wi (wi.z > 0), distributed
/// as visible_normal_pdf. What depends only on (distribution, alpha, wi) is computed once, at
/// construction. A sample is separable in u: part_x(u.x) depends on u.x alone (Beckmann's
/// Newton solve is there) and part_y(u.y) on u.y alone, so a grid of samples (roughplastic's
/// quadratures) computes each part once per row or column and combines them with normal().
class VisibleNormalSampler {
public:
    VisibleNormalSampler(MicrofacetType type, float alpha, const Vec3 &wi);
    Vec3 sample(Vec2 u) const { return normal(part_x(u.x), part_y(u.y)); }
    Vec2 part_x(float u1) const;
    Vec2 part_y(float u2) const;
    Vec3 normal(Vec2 px, Vec2 py) const;
    /// normal() of the sampler's distribution, given as `Type`.
    template <MicrofacetType Type>
    Vec3 normal(Vec2 px, Vec2 py) const;

private:
    /// Beckmann: whether wi is close enough to the normal for polar slopes. (A comparison,
    /// not a stored flag: a vectorised loop can select on it.)
    bool polar() const { return w_.z > 0.99999f; }

    MicrofacetType type_;
    float alpha_;
    Vec3 w_;  ///< wi stretched to the alpha = 1 configuration
    // GGX: a frame around w_ and the weight of the hemisphere's half that wi sees.
    Vec3 t1_, t2_;
    float s_ = 0.f;
    // Beckmann: rotation of the slopes to wi's azimuth; at (near) normal incidence the slopes
    // are polar (radius from u.x, angle from u.y; see polar()), else the CDF inversion's
    // constants.
    float cos_phi_ = 1.f, sin_phi_ = 0.f;
    float tan_i_ = 0.f, erf_cot_ = 0.f, fit_ = 0.f, normalization_ = 0.f;
};

// Inline: roughplastic's quadratures call it in loops that the compiler vectorises.
template <MicrofacetType Type>
inline Vec3 VisibleNormalSampler::normal(Vec2 px, Vec2 py) const {
    if constexpr (Type == MicrofacetType::GGX) {
        float p1 = px.x * py.x, p2 = px.x * py.y;
        p2 = (1.f - s_) * safe_sqrt(1.f - p1 * p1) + s_ * p2;
        Vec3 nh = t1_ * p1 + t2_ * p2 + w_ * safe_sqrt(1.f - p1 * p1 - p2 * p2);
        return normalize(Vec3{alpha_ * nh.x, alpha_ * nh.y, std::max(0.f, nh.z)});
    } else {
        // Slopes for alpha = 1, rotated to wi's azimuth and unstretched.
        float sx = polar() ? px.x * py.x : px.x, sy = polar() ? px.x * py.y : py.x;
        float mx = (cos_phi_ * sx - sin_phi_ * sy) * alpha_;
        float my = (sin_phi_ * sx + cos_phi_ * sy) * alpha_;
        return normalize(Vec3{-mx, -my, 1.f});
    }
}

inline Vec3 VisibleNormalSampler::normal(Vec2 px, Vec2 py) const {
    return type_ == MicrofacetType::GGX ? normal<MicrofacetType::GGX>(px, py)
                                        : normal<MicrofacetType::Beckmann>(px, py);
}

/// Sample a microfacet normal visible from wi (wi.z > 0), distributed as visible_normal_pdf.
Vec3 sample_visible_normal(MicrofacetType type, float alpha, const Vec3 &wi, Vec2 u);

/// Inverse error function (single precision).
float erfinv(float x);

}  // namespace rbpt
