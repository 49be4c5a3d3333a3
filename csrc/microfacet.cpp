#include "microfacet.h"

#include <algorithm>
#include <limits>

#include "warp.h"

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

// Beckmann: the slopes of the visible distribution for alpha = 1 (Jakob 2014), in float:
// safeguarded Newton on the normalised CDF until it is within 1e-6 of u1 (two steps for most
// samples; Mitsuba stops after three steps whatever the residual), rotated to wi's azimuth.
// GGX: Heitz 2018, the projected hemisphere of the stretched configuration.

constexpr float InvSqrtPi = 0.56418958354775628f;

VisibleNormalSampler::VisibleNormalSampler(MicrofacetType type, float alpha, const Vec3 &wi)
    : type_(type), alpha_(alpha), w_(normalize(Vec3{alpha * wi.x, alpha * wi.y, wi.z})) {
    if (type == MicrofacetType::GGX) {
        float len2 = w_.x * w_.x + w_.y * w_.y;
        t1_ = len2 > 0.f ? Vec3{-w_.y, w_.x, 0.f} / std::sqrt(len2) : Vec3{1.f, 0.f, 0.f};
        t2_ = cross(w_, t1_);
        s_ = 0.5f * (1.f + w_.z);
        return;
    }
    float sin_t = std::sqrt(w_.x * w_.x + w_.y * w_.y);
    cos_phi_ = sin_t > 0.f ? w_.x / sin_t : 1.f;
    sin_phi_ = sin_t > 0.f ? w_.y / sin_t : 0.f;
    float cos_i = w_.z;
    if (polar()) return;
    float sin_i = std::sqrt(std::max(0.f, 1.f - cos_i * cos_i));
    tan_i_ = sin_i / cos_i;
    float cot_i = 1.f / tan_i_;
    erf_cot_ = std::erf(cot_i);
    // Jakob's fit of the initial guess's exponent.
    float theta_i = std::acos(cos_i);
    fit_ = 1.f + theta_i * (-0.876f + theta_i * (0.4265f - 0.0594f * theta_i));
    // (e^-cot^2 is below 1e-35 beyond cot = 9: skip libm's slow underflow path.)
    float tail = cot_i < 9.f ? InvSqrtPi * tan_i_ * std::exp(-cot_i * cot_i) : 0.f;
    normalization_ = 1.f / (1.f + erf_cot_ + tail);
}

Vec2 VisibleNormalSampler::part_x(float u1) const {
    if (type_ == MicrofacetType::GGX) return {std::sqrt(u1), 0.f};
    if (polar()) return {std::sqrt(-std::log(std::max(1.f - u1, 1e-30f))), 0.f};
    // Search interval, parameterised in the erf() domain, and a good initial guess.
    float a = -1.f, c = erf_cot_;
    u1 = std::max(u1, 1e-6f);
    float b = c - (1.f + c) * std::pow(1.f - u1, fit_);
    bool converged = false;
    float inv_erf = 0.f;
    for (int it = 0; it < 100; ++it) {
        if (!(b >= a && b <= c)) b = 0.5f * (a + c);
        inv_erf = erfinv(b);
        float value = normalization_ * (1.f + b + InvSqrtPi * tan_i_ * std::exp(-inv_erf * inv_erf)) - u1;
        float derivative = normalization_ * (1.f - inv_erf * tan_i_);
        converged = std::abs(value) < 1e-6f;
        if (converged) break;
        if (value > 0.f) c = b; else a = b;
        b -= value / derivative;
    }
    return {converged ? inv_erf : erfinv(b), 0.f};  // the converged step already inverted b
}

Vec2 VisibleNormalSampler::part_y(float u2) const {
    if (type_ == MicrofacetType::GGX || polar()) return warp::cossin_2pi(u2);
    return {erfinv(2.f * u2 - 1.f), 0.f};
}

Vec3 sample_visible_normal(MicrofacetType type, float alpha, const Vec3 &wi, Vec2 u) {
    return VisibleNormalSampler(type, alpha, wi).sample(u);
}

}  // namespace rbpt
