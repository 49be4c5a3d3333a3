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
#include "warp.h"

namespace rbpt {

enum class MicrofacetType { Beckmann, GGX };

/// 2 sqrt(pi) in float, the denominator of Beckmann's lambda and of its derivative.
constexpr float TwoSqrtPi = 2.f * 1.7724538509055159f;

/// Normal distribution D(m) of microfacet normal m (local frame, z up) in float, of the
/// distribution `Type` (a template argument for loops over lanes, which inline it: the
/// wavefront's rough lanes). Beckmann's takes exp_poly; below e^-87, where it stops, D is below
/// the cut-off but at normals within 1e-4 of grazing.
template <MicrofacetType Type>
RBPT_INLINE float microfacet_D(float alpha, const Vec3 &m) {
    float cos2 = m.z * m.z, xy2 = m.x * m.x + m.y * m.y;
    if (m.z <= 0.f) return 0.f;
    float a2 = alpha * alpha;
    float result;
    if constexpr (Type == MicrofacetType::Beckmann) {
        // (Beyond, exp_poly's argument is replaced, not clamped: vectorised loops compute
        // both sides of the branch, and e^-87 over the denominator, which exceeds 1 where
        // alpha > 0.56, underflows, a microcode assist per instruction.)
        float e = -(xy2 / cos2) / a2;
        const bool beyond = e < -87.f;
        result = exp_poly(beyond ? 0.f : e) / (Pi * a2 * (cos2 * cos2));
        if (beyond) return 0.f;
    } else {
        float t = xy2 / a2 + cos2;
        result = 1.f / (Pi * a2 * t * t);
    }
    // As Mitsuba: drop values too small to matter, avoiding underflow downstream.
    return result * m.z > 1e-20f ? result : 0.f;
}

/// Normal distribution D(m) of microfacet normal m (local frame, z up): float renders take
/// the float one above.
template <typename R>
R microfacet_D(MicrofacetType type, const R &alpha, const Vec3 &m) {
    if constexpr (std::is_same_v<R, float>) {
        return type == MicrofacetType::Beckmann ? microfacet_D<MicrofacetType::Beckmann>(alpha, m)
                                                : microfacet_D<MicrofacetType::GGX>(alpha, m);
    } else {
        using std::exp;
        float cos2 = m.z * m.z, xy2 = m.x * m.x + m.y * m.y;
        if (m.z <= 0.f) return R(0.f);
        R a2 = alpha * alpha;
        R result;
        if (type == MicrofacetType::Beckmann) {
            // Beyond e^-150, D is below the cut-off below for any alpha above 1e-10 (and exp
            // would take libm's slow underflow path).
            if (-(xy2 / cos2) / detach_real(a2) < -150.f) return R(0.f);
            result = exp(-(xy2 / cos2) / a2) / (Pi * a2 * (cos2 * cos2));
        } else {
            R t = xy2 / a2 + cos2;
            result = 1.f / (Pi * a2 * t * t);
        }
        return detach_real(result) * m.z > 1e-20f ? result : R(0.f);
    }
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

/// A factor of a BSDF's value through which alpha enters it, and its d log / d alpha.
struct FactorDlog {
    float value, dlog;
};

/// Smith's G1(v, m) in float (Beckmann's from the polynomials, as float renders take it: the
/// value of smith_G1 with VectorMath) and its d log G1 / d alpha in closed form, 0 where G1
/// is 0 or 1. Beckmann: G1 = 1 / (1 + lambda),
/// lambda(a) = -erfc(a) / 2 + e^-a^2 / (2 sqrt(pi) a), a = 1 / (alpha tan); d lambda / d a =
/// -e^-a^2 / (2 sqrt(pi) a^2) and d a / d alpha = -a / alpha, so d log G1 / d alpha =
/// -G1 e^-a^2 / (2 sqrt(pi) alpha a). GGX: G1 = 2 / (1 + s), s = sqrt(1 + alpha^2 tan^2), so
/// d log G1 / d alpha = -alpha tan^2 / (s (1 + s)).
template <MicrofacetType Type>
RBPT_INLINE FactorDlog smith_G1_dlog(float alpha, const Vec3 &v, const Vec3 &m) {
    if (dot(v, m) * v.z <= 0.f) return {0.f, 0.f};
    float xy2 = v.x * v.x + v.y * v.y;
    if (xy2 == 0.f) return {1.f, 0.f};
    float tan2 = xy2 / (v.z * v.z);
    if constexpr (Type == MicrofacetType::Beckmann) {
        // (Beyond a = 9 the terms are computed at a = 1 and dropped: vectorised loops compute
        // them anyway, and at larger a they underflow, a microcode assist per instruction.)
        const float a_v = 1.f / (alpha * std::sqrt(tan2));
        const bool flat = a_v > 9.f;
        const float a = flat ? 1.f : a_v;
        float e = exp_poly(-a * a);
        float g1 = 1.f / (1.f + (erfc_poly(a) * -0.5f + e / (a * TwoSqrtPi)));
        if (flat) return {1.f, 0.f};
        return {g1, -g1 * e / (TwoSqrtPi * alpha * a)};
    } else {
        float s = std::sqrt(1.f + alpha * alpha * tan2);
        return {2.f / (1.f + s), -alpha * tan2 / (s * (1.f + s))};
    }
}

/// Smith's masking function G1(v, m) for direction v and microfacet normal m, of the
/// distribution `Type` (a template argument for loops over one distribution, which inline it).
/// With VectorMath (float only), smith_G1_dlog's value: Beckmann's takes erf and exp from
/// erfc_poly and exp_poly, within 2e-7 of libm's, and vectorisable. (Forced inline, with the
/// polynomials: GCC's size limits left Beckmann's out of line, and the tables' vectorised
/// loop with it. The wavefront's rough lanes take it too.)
template <MicrofacetType Type, bool VectorMath = false, typename R>
RBPT_INLINE R smith_G1(const R &alpha, const Vec3 &v, const Vec3 &m) {
    using std::erf;
    using std::exp;
    using std::sqrt;
    if constexpr (VectorMath) {
        static_assert(std::is_same_v<R, float>, "VectorMath is for float");
        return smith_G1_dlog<Type>(alpha, v, m).value;
    }
    if (dot(v, m) * v.z <= 0.f) return R(0.f);  // the back of a microfacet is never seen
    float xy2 = v.x * v.x + v.y * v.y;
    if (xy2 == 0.f) return R(1.f);
    float tan2 = xy2 / (v.z * v.z);
    if constexpr (Type == MicrofacetType::Beckmann) {
        R a = 1.f / (alpha * std::sqrt(tan2));
        // Beyond a = 9, lambda < 1e-37: G1 is 1 in float and double (and exp would underflow).
        if (detach_real(a) > 9.f) return R(1.f);
        const R lambda = (erf(a) - 1.f) * 0.5f + exp(-a * a) / (a * TwoSqrtPi);
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

/// D(h) G1(wi, h) G1(wo, h), the factor through which alpha enters a microfacet BSDF's value,
/// in float (microfacet_D's and smith_G1's float values) and its d log / d alpha in closed
/// form (the sum of its factors'), 0 where the value is 0. d log D / d alpha: Beckmann's
/// (2 / alpha) (tan^2 / alpha^2 - 1), GGX's (2 / alpha) (2 xy2 / (xy2 + alpha^2 cos^2) - 1).
/// The same derivative as a dual number through microfacet_D and smith_G1 (test_autodiff
/// compares them), in a few float operations (render_bwd's roughness records), without
/// branches, so that loops over lanes vectorise (the factors are finite: a zero D makes the
/// value zero).
template <MicrofacetType Type>
RBPT_INLINE FactorDlog microfacet_dlog_dalpha(float alpha, const Vec3 &wi, const Vec3 &wo, const Vec3 &h) {
    const float d = microfacet_D<Type>(alpha, h);
    const FactorDlog gi = smith_G1_dlog<Type>(alpha, wi, h), go = smith_G1_dlog<Type>(alpha, wo, h);
    const float value = d * gi.value * go.value;
    const float xy2 = h.x * h.x + h.y * h.y, cos2 = h.z * h.z, a2 = alpha * alpha;
    const float dlog_d = Type == MicrofacetType::Beckmann ? (2.f / alpha) * ((xy2 / cos2) / a2 - 1.f)
                                                          : (2.f / alpha) * (2.f * xy2 / (xy2 + a2 * cos2) - 1.f);
    return {value, value != 0.f ? dlog_d + gi.dlog + go.dlog : 0.f};
}

/// microfacet_dlog_dalpha of the distribution `type`.
RBPT_INLINE FactorDlog microfacet_dlog_dalpha(MicrofacetType type, float alpha, const Vec3 &wi, const Vec3 &wo,
                                              const Vec3 &h) {
    return type == MicrofacetType::Beckmann ? microfacet_dlog_dalpha<MicrofacetType::Beckmann>(alpha, wi, wo, h)
                                            : microfacet_dlog_dalpha<MicrofacetType::GGX>(alpha, wi, wo, h);
}

/// Inverse error function in float: Giles' single-precision approximation (relative error
/// below 3e-7, as Dr.Jit's), on log_poly, both of its branches computed and one selected, so
/// that vectorised loops can call it; -inf and inf at -1 and 1 and beyond.
RBPT_INLINE float erfinv(float x) {
    float w = -log_poly((1.f - x) * (1.f + x));  // (finite at +-1, where the result is selected)
    float v = w - 2.5f;
    float p = 2.81022636e-08f;
    p = 3.43273939e-07f + p * v;
    p = -3.5233877e-06f + p * v;
    p = -4.39150654e-06f + p * v;
    p = 0.00021858087f + p * v;
    p = -0.00125372503f + p * v;
    p = -0.00417768164f + p * v;
    p = 0.246640727f + p * v;
    p = 1.50140941f + p * v;
    float t = std::sqrt(std::max(w, 0.f)) - 3.f;
    float q = -0.000200214257f;
    q = 0.000100950558f + q * t;
    q = 0.00134934322f + q * t;
    q = -0.00367342844f + q * t;
    q = 0.00573950773f + q * t;
    q = -0.0076224613f + q * t;
    q = 0.00943887047f + q * t;
    q = 1.00167406f + q * t;
    q = 2.83297682f + q * t;
    float r = (w < 5.f ? p : q) * x;
    r = x <= -1.f ? -std::numeric_limits<float>::infinity() : r;
    return x >= 1.f ? std::numeric_limits<float>::infinity() : r;
}

/// The slopes of Beckmann's microfacet normals visible from direction w (wi stretched to the
/// alpha = 1 configuration, w.z > 0; Jakob 2014), rotated to w's azimuth: at (near) normal
/// incidence polar (radius from u.x, angle from u.y), else by inverting the CDF of the x
/// slope with a safeguarded Newton search until it is within 1e-6 of u.x (two steps for most
/// samples; Mitsuba stops after three steps whatever the residual). Inline and without libm
/// (log_poly, exp_poly, erfc_poly, erfinv), so that the wavefront runs it lane by lane with
/// the operations of VisibleNormalSampler, which uses it (beckmann_sample_stage).
struct BeckmannSlopes {
    static constexpr float InvSqrtPi = 0.56418958354775628f;
    float cos_phi = 1.f, sin_phi = 0.f;
    float polar = 0.f;  ///< 1 where w.z > 0.99999 (polar slopes), else 0
    // The CDF inversion's constants (unused where polar).
    float tan_i = 0.f, erf_cot = 0.f, fit = 0.f, normalization = 0.f;

    /// The Newton search for the x slope: the interval [a, c] and guess b in the erf() domain,
    /// the last erfinv, and whether it has converged (1 or 0).
    struct Search {
        float a, b, c, inv_erf, u1, converged;
    };

    BeckmannSlopes() = default;
    RBPT_INLINE explicit BeckmannSlopes(const Vec3 &w) {
        float sin_t = std::sqrt(w.x * w.x + w.y * w.y);
        cos_phi = sin_t > 0.f ? w.x / sin_t : 1.f;
        sin_phi = sin_t > 0.f ? w.y / sin_t : 0.f;
        polar = w.z > 0.99999f ? 1.f : 0.f;
        float cos_i = polar != 0.f ? 0.5f : w.z;  // (polar: any value that keeps these finite)
        float sin_i = std::sqrt(std::max(0.f, 1.f - cos_i * cos_i));
        tan_i = sin_i / cos_i;
        float cot_i = 1.f / tan_i;
        erf_cot = 1.f - erfc_poly(cot_i);
        // Jakob's fit of the initial guess's exponent.
        float theta_i = acos_poly(cos_i);
        fit = 1.f + theta_i * (-0.876f + theta_i * (0.4265f - 0.0594f * theta_i));
        // (e^-cot^2 is below 1e-35 beyond cot = 9.)
        float tail = cot_i < 9.f ? InvSqrtPi * tan_i * exp_poly(-cot_i * cot_i) : 0.f;
        normalization = 1.f / (1.f + erf_cot + tail);
    }

    /// The search for u1 (non-polar), from Jakob's initial guess.
    RBPT_INLINE Search start(float u1) const {
        Search s;
        s.u1 = std::max(u1, 1e-6f);
        s.a = -1.f;
        s.c = erf_cot;
        s.b = s.c - (1.f + s.c) * exp_poly(fit * log_poly(1.f - s.u1));  // (1 - u1)^fit
        s.inv_erf = 0.f;
        s.converged = 0.f;
        return s;
    }
    /// One Newton step (bisecting where the guess left the interval); none once converged.
    RBPT_INLINE void step(Search &s) const {
        float b = (s.b >= s.a && s.b <= s.c) ? s.b : 0.5f * (s.a + s.c);
        float inv_erf = erfinv(b);
        float value = normalization * (1.f + b + InvSqrtPi * tan_i * exp_poly(-inv_erf * inv_erf)) - s.u1;
        float derivative = normalization * (1.f - inv_erf * tan_i);
        float done = std::abs(value) < 1e-6f ? 1.f : 0.f;
        float a = value > 0.f ? s.a : b, c = value > 0.f ? b : s.c;
        float next = done != 0.f ? b : b - value / derivative;
        float keep = s.converged;
        s.a = keep != 0.f || done != 0.f ? s.a : a;
        s.c = keep != 0.f || done != 0.f ? s.c : c;
        s.b = keep != 0.f ? s.b : next;
        s.inv_erf = keep != 0.f ? s.inv_erf : inv_erf;
        s.converged = keep != 0.f ? keep : done;
    }
    /// Steps the search runs at most.
    static constexpr int MaxSteps = 100;
    /// The x slope the search reached (the converged step already inverted b).
    RBPT_INLINE static float slope(const Search &s) { return s.converged != 0.f ? s.inv_erf : erfinv(s.b); }

    /// VisibleNormalSampler's part_x for a search run to its end (non-polar), or polar.
    RBPT_INLINE float polar_radius(float u1) const { return std::sqrt(-log_poly(std::max(1.f - u1, 1e-30f))); }
    /// Its part_y: erfinv(2 u2 - 1) (non-polar), or the polar angle's cosine and sine.
    RBPT_INLINE Vec2 part_y(float u2) const {
        return polar != 0.f ? warp::cossin_2pi(u2) : Vec2{erfinv(2.f * u2 - 1.f), 0.f};
    }
    /// The unit normal of the slopes for px = (part_x, 0) and py = part_y, unstretched by alpha.
    RBPT_INLINE Vec3 normal(float alpha, Vec2 px, Vec2 py) const {
        float sx = polar != 0.f ? px.x * py.x : px.x, sy = polar != 0.f ? px.x * py.y : py.x;
        float mx = (cos_phi * sx - sin_phi * sy) * alpha;
        float my = (sin_phi * sx + cos_phi * sy) * alpha;
        return normalize(Vec3{-mx, -my, 1.f});
    }
};

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
    MicrofacetType type_;
    float alpha_;
    Vec3 w_;  ///< wi stretched to the alpha = 1 configuration
    // GGX: a frame around w_ and the weight of the hemisphere's half that wi sees.
    Vec3 t1_, t2_;
    float s_ = 0.f;
    BeckmannSlopes beckmann_;  ///< Beckmann's constants
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
        return beckmann_.normal(alpha_, px, py);
    }
}

inline Vec3 VisibleNormalSampler::normal(Vec2 px, Vec2 py) const {
    return type_ == MicrofacetType::GGX ? normal<MicrofacetType::GGX>(px, py)
                                        : normal<MicrofacetType::Beckmann>(px, py);
}

/// Sample a microfacet normal visible from wi (wi.z > 0), distributed as visible_normal_pdf.
Vec3 sample_visible_normal(MicrofacetType type, float alpha, const Vec3 &wi, Vec2 u);

}  // namespace rbpt
