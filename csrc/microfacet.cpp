#include "microfacet.h"

namespace rbpt {

double erfinv(double x) {
    if (x <= -1.0) return -std::numeric_limits<double>::infinity();
    if (x >= 1.0) return std::numeric_limits<double>::infinity();
    // Giles' single-precision approximation, then two Newton steps on erf(y) - x.
    double w = -std::log((1.0 - x) * (1.0 + x)), p;
    if (w < 5.0) {
        w -= 2.5;
        p = 2.81022636e-08;
        p = 3.43273939e-07 + p * w;
        p = -3.5233877e-06 + p * w;
        p = -4.39150654e-06 + p * w;
        p = 0.00021858087 + p * w;
        p = -0.00125372503 + p * w;
        p = -0.00417768164 + p * w;
        p = 0.246640727 + p * w;
        p = 1.50140941 + p * w;
    } else {
        w = std::sqrt(w) - 3.0;
        p = -0.000200214257;
        p = 0.000100950558 + p * w;
        p = 0.00134934322 + p * w;
        p = -0.00367342844 + p * w;
        p = 0.00573950773 + p * w;
        p = -0.0076224613 + p * w;
        p = 0.00943887047 + p * w;
        p = 1.00167406 + p * w;
        p = 2.83297682 + p * w;
    }
    double y = p * x;
    for (int i = 0; i < 2; ++i) {
        double err = std::erf(y) - x;
        y -= err / (1.1283791670955126 * std::exp(-y * y));
    }
    return y;
}

namespace {

/// Sample the slopes of the visible Beckmann distribution for alpha = 1 (Jakob 2014).
void sample_visible_11_beckmann(double cos_i, double u1, double u2, double *sx, double *sy) {
    constexpr double InvSqrtPi = 0.56418958354775628;
    if (cos_i > 0.99999) {
        double r = std::sqrt(-std::log(std::max(1.0 - u1, 1e-300))), phi = 2.0 * M_PI * u2;
        *sx = r * std::cos(phi);
        *sy = r * std::sin(phi);
        return;
    }
    double sin_i = std::sqrt(std::max(0.0, 1.0 - cos_i * cos_i));
    double tan_i = sin_i / cos_i, cot_i = 1.0 / tan_i;
    // Search interval, parameterised in the erf() domain.
    double a = -1.0, c = std::erf(cot_i);
    u1 = std::max(u1, 1e-6);
    // A good initial guess (Jakob's fit), then safeguarded Newton on the normalised CDF.
    double theta_i = std::acos(cos_i);
    double fit = 1.0 + theta_i * (-0.876 + theta_i * (0.4265 - 0.0594 * theta_i));
    double b = c - (1.0 + c) * std::pow(1.0 - u1, fit);
    double normalization = 1.0 / (1.0 + c + InvSqrtPi * tan_i * std::exp(-cot_i * cot_i));
    for (int it = 0; it < 100; ++it) {
        if (!(b >= a && b <= c)) b = 0.5 * (a + c);
        double inv_erf = erfinv(b);
        double value = normalization * (1.0 + b + InvSqrtPi * tan_i * std::exp(-inv_erf * inv_erf)) - u1;
        double derivative = normalization * (1.0 - inv_erf * tan_i);
        if (std::abs(value) < 1e-9) break;
        if (value > 0.0) c = b; else a = b;
        b -= value / derivative;
    }
    *sx = erfinv(b);
    *sy = erfinv(2.0 * u2 - 1.0);
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
    double wx = double(alpha) * wi.x, wy = double(alpha) * wi.y, wz = wi.z;
    double len = std::sqrt(wx * wx + wy * wy + wz * wz);
    wx /= len; wy /= len; wz /= len;
    double sin_t = std::sqrt(wx * wx + wy * wy);
    double cos_phi = sin_t > 0.0 ? wx / sin_t : 1.0, sin_phi = sin_t > 0.0 ? wy / sin_t : 0.0;
    double sx, sy;
    sample_visible_11_beckmann(wz, u.x, u.y, &sx, &sy);
    double mx = (cos_phi * sx - sin_phi * sy) * alpha;
    double my = (sin_phi * sx + cos_phi * sy) * alpha;
    double n = std::sqrt(mx * mx + my * my + 1.0);
    return Vec3{float(-mx / n), float(-my / n), float(1.0 / n)};
}

}  // namespace rbpt
