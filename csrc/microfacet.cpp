#include "microfacet.h"

#include <algorithm>
#include <limits>

namespace rbpt {

float erfinv(float x) {
    if (x <= -1.f) return -std::numeric_limits<float>::infinity();
    if (x >= 1.f) return std::numeric_limits<float>::infinity();
    // Giles' single-precision approximation (relative error below 3e-7, as Dr.Jit's).
    float w = -std::log((1.f - x) * (1.f + x)), p;
    if (w < 5.f) {
        w -= 2.5f;
        p = 2.81022636e-08f;
        p = 3.43273939e-07f + p * w;
        p = -3.5233877e-06f + p * w;
        p = -4.39150654e-06f + p * w;
        p = 0.00021858087f + p * w;
        p = -0.00125372503f + p * w;
        p = -0.00417768164f + p * w;
        p = 0.246640727f + p * w;
        p = 1.50140941f + p * w;
    } else {
        w = std::sqrt(w) - 3.f;
        p = -0.000200214257f;
        p = 0.000100950558f + p * w;
        p = 0.00134934322f + p * w;
        p = -0.00367342844f + p * w;
        p = 0.00573950773f + p * w;
        p = -0.0076224613f + p * w;
        p = 0.00943887047f + p * w;
        p = 1.00167406f + p * w;
        p = 2.83297682f + p * w;
    }
    return p * x;
}

namespace {

/// Sample the slopes of the visible Beckmann distribution for alpha = 1 (Jakob 2014), in
/// float: safeguarded Newton on the normalised CDF until it is within 1e-6 of u1 (two steps
/// for most samples; Mitsuba stops after three steps whatever the residual).
void sample_visible_11_beckmann(float cos_i, float u1, float u2, float *sx, float *sy) {
    constexpr float InvSqrtPi = 0.56418958354775628f;
    if (cos_i > 0.99999f) {
        float r = std::sqrt(-std::log(std::max(1.f - u1, 1e-30f))), phi = 2.f * Pi * u2;
        *sx = r * std::cos(phi);
        *sy = r * std::sin(phi);
        return;
    }
    float sin_i = std::sqrt(std::max(0.f, 1.f - cos_i * cos_i));
    float tan_i = sin_i / cos_i, cot_i = 1.f / tan_i;
    // Search interval, parameterised in the erf() domain.
    float a = -1.f, c = std::erf(cot_i);
    u1 = std::max(u1, 1e-6f);
    // A good initial guess (Jakob's fit), then safeguarded Newton on the normalised CDF.
    float theta_i = std::acos(cos_i);
    float fit = 1.f + theta_i * (-0.876f + theta_i * (0.4265f - 0.0594f * theta_i));
    float b = c - (1.f + c) * std::pow(1.f - u1, fit);
    // (e^-cot^2 is below 1e-35 beyond cot = 9: skip libm's slow underflow path.)
    float tail = cot_i < 9.f ? InvSqrtPi * tan_i * std::exp(-cot_i * cot_i) : 0.f;
    float normalization = 1.f / (1.f + c + tail);
    bool converged = false;
    float inv_erf = 0.f;
    for (int it = 0; it < 100; ++it) {
        if (!(b >= a && b <= c)) b = 0.5f * (a + c);
        inv_erf = erfinv(b);
        float value = normalization * (1.f + b + InvSqrtPi * tan_i * std::exp(-inv_erf * inv_erf)) - u1;
        float derivative = normalization * (1.f - inv_erf * tan_i);
        converged = std::abs(value) < 1e-6f;
        if (converged) break;
        if (value > 0.f) c = b; else a = b;
        b -= value / derivative;
    }
    *sx = converged ? inv_erf : erfinv(b);  // the converged step already inverted b
    *sy = erfinv(2.f * u2 - 1.f);
}

}  // namespace

Vec3 sample_visible_normal(MicrofacetType type, float alpha, const Vec3 &wi, Vec2 u) {
    if (type == MicrofacetType::GGX) {
        // Heitz 2018: sample the projected hemisphere of the stretched configuration.
        Vec3 vh = normalize(Vec3{alpha * wi.x, alpha * wi.y, wi.z});
        float len2 = vh.x * vh.x + vh.y * vh.y;
        Vec3 t1 = len2 > 0.f ? Vec3{-vh.y, vh.x, 0.f} / std::sqrt(len2) : Vec3{1.f, 0.f, 0.f};
        Vec3 t2 = cross(vh, t1);
        float r = std::sqrt(u.x), phi = 2.f * Pi * u.y;
        float p1 = r * std::cos(phi), p2 = r * std::sin(phi);
        float s = 0.5f * (1.f + vh.z);
        p2 = (1.f - s) * safe_sqrt(1.f - p1 * p1) + s * p2;
        Vec3 nh = t1 * p1 + t2 * p2 + vh * safe_sqrt(1.f - p1 * p1 - p2 * p2);
        return normalize(Vec3{alpha * nh.x, alpha * nh.y, std::max(0.f, nh.z)});
    }
    // Beckmann: stretch, sample the alpha = 1 slopes, rotate, unstretch (Mitsuba's recipe).
    Vec3 w = normalize(Vec3{alpha * wi.x, alpha * wi.y, wi.z});
    float sin_t = std::sqrt(w.x * w.x + w.y * w.y);
    float cos_phi = sin_t > 0.f ? w.x / sin_t : 1.f, sin_phi = sin_t > 0.f ? w.y / sin_t : 0.f;
    float sx, sy;
    sample_visible_11_beckmann(w.z, u.x, u.y, &sx, &sy);
    float mx = (cos_phi * sx - sin_phi * sy) * alpha;
    float my = (sin_phi * sx + cos_phi * sy) * alpha;
    return normalize(Vec3{-mx, -my, 1.f});
}

}  // namespace rbpt
