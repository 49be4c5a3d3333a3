#include "bsdfs.h"

#include <vector>

namespace rbpt {

namespace {

/// Gauss-Legendre nodes and weights on [-1, 1] (Newton iteration on P_n).
void gauss_legendre(int n, std::vector<double> *nodes, std::vector<double> *weights) {
    nodes->resize(n);
    weights->resize(n);
    for (int i = 0; i < n; ++i) {
        double x = std::cos(M_PI * (i + 0.75) / (n + 0.5)), dp = 1.0;
        for (int it = 0; it < 100; ++it) {
            double p0 = 1.0, p1 = x;
            for (int k = 2; k <= n; ++k) {
                double p2 = ((2.0 * k - 1.0) * x * p1 - (k - 1.0) * p0) / k;
                p0 = p1;
                p1 = p2;
            }
            dp = n * (x * p1 - p0) / (x * x - 1.0);
            double dx = p1 / dp;
            x -= dx;
            if (std::abs(dx) < 1e-15) break;
        }
        (*nodes)[i] = x;
        (*weights)[i] = 2.0 / ((1.0 - x * x) * dp * dp);
    }
}

template <MicrofacetType Type>
using DistributionConstant = std::integral_constant<MicrofacetType, Type>;

/// Energy a rough dielectric interface reflects (or transmits) for incidence wi, integrated
/// over visible normals: sum of F G1(wo) (or (1 - F) G1(wt)) at quadrature points.
float rough_interface(MicrofacetType type, float alpha, const Vec3 &wi, float eta,
                      bool transmit) {
    int res = eta > 1.f ? 32 : 128;
    // The nodes and weights of both resolutions, computed once.
    static const auto rule = [](int n) {
        std::pair<std::vector<double>, std::vector<double>> r;
        gauss_legendre(n, &r.first, &r.second);
        return r;
    };
    static const auto rule32 = rule(32), rule128 = rule(128);
    const std::vector<double> &nodes = res == 32 ? rule32.first : rule128.first;
    const std::vector<double> &weights = res == 32 ? rule32.second : rule128.second;
    // The sampler's parts along each axis of the grid, once per row and per column.
    VisibleNormalSampler sampler(type, alpha, wi);
    // (res is 32 or 128; the columns' parts as two arrays, which vector loads read)
    Vec2 px[128];
    float py_x[128], py_y[128];
    for (int i = 0; i < res; ++i) {
        float u = float(0.5 * nodes[i] + 0.5);
        px[i] = sampler.part_x(u);
        Vec2 py = sampler.part_y(u);
        py_x[i] = py.x;
        py_y[i] = py.y;
    }
    // One point for distribution Type: the factor its G1 multiplies, F reflected (0 where the
    // reflected direction is below the surface) or 1 - F transmitted, and that direction.
    struct Point {
        float weight;
        Vec3 v, m;
    };
    auto point = [sampler, eta, wi](auto type_constant, auto transmit_constant, Vec2 px_i,
                                    Vec2 py_j) {
        constexpr MicrofacetType Type = decltype(type_constant)::value;
        Vec3 m = sampler.normal<Type>(px_i, py_j);
        float cos_t, eta_it, eta_ti;
        float F = fresnel_dielectric(dot(wi, m), eta, &cos_t, &eta_it, &eta_ti);
        if constexpr (decltype(transmit_constant)::value) {
            return Point{1.f - F, m * (dot(wi, m) * eta_ti + cos_t) - wi * eta_ti, m};
        } else {
            Vec3 wo = reflect(wi, m);
            return Point{wo.z > 0.f ? F : 0.f, wo, m};
        }
    };
    // A row of points at a time, summed in order, in a loop the compiler vectorises. GGX's
    // points are the same operations as the scalar formulas (so the same results); Beckmann's
    // G1 takes erf and exp from polynomials (erfc_poly, exp_poly: libm's are scalar calls),
    // within 2e-7 of the libm form. (Distribution and direction are template arguments: a
    // loop-invariant branch inside the loop stops the vectoriser.)
    double sum = 0.0;
    auto rows = [&](auto type_constant, auto transmit_constant) {
        constexpr MicrofacetType Type = decltype(type_constant)::value;
        // What the loop reads as locals, which its stores cannot change (the vectoriser then
        // reads them once); no local of the loop's body has its address taken (that makes it
        // an array per lane).
        const float a = alpha;
        const auto at = point;
        auto value_at = [at, a, type_constant, transmit_constant](Vec2 px_i, Vec2 py_j) {
            Point p = at(type_constant, transmit_constant, px_i, py_j);
            return p.weight == 0.f ? 0.f : p.weight * smith_G1<Type, true>(a, p.v, p.m);
        };
        const float *ux = py_x, *uy = py_y;
        float value[128];
        for (int i = 0; i < res; ++i) {
            const Vec2 px_i = px[i];
#pragma omp simd
            for (int j = 0; j < res; ++j) value[j] = value_at(px_i, Vec2{ux[j], uy[j]});
            for (int j = 0; j < res; ++j) sum += value[j] * weights[i] * weights[j];
        }
    };
    using GGX = DistributionConstant<MicrofacetType::GGX>;
    using Beckmann = DistributionConstant<MicrofacetType::Beckmann>;
    if (type == MicrofacetType::GGX) {
        transmit ? rows(GGX(), std::true_type()) : rows(GGX(), std::false_type());
    } else {
        transmit ? rows(Beckmann(), std::true_type()) : rows(Beckmann(), std::false_type());
    }
    return float(sum * 0.25);
}

}  // namespace

void RoughPlasticTables::compute(MicrofacetType type_, float alpha_, float eta_) {
    type = type_;
    alpha = alpha_;
    eta = eta_;
    // Rows are independent quadratures (about a million BSDF samples in all): spread them over
    // the cores, then sum the internal reflectance in row order (deterministic).
    double internal[Resolution];
#pragma omp parallel for schedule(dynamic, 1)
    for (int i = 0; i < Resolution; ++i) {
        float mu = std::max(1e-6f, float(i) / float(Resolution - 1));
        Vec3 wi{safe_sqrt(1.f - mu * mu), 0.f, mu};
        external_transmittance[i] = rough_interface(type, alpha, wi, eta, true);
        internal[i] = double(rough_interface(type, alpha, wi, 1.f / eta, false)) * mu;
    }
    double sum = 0.0;
    for (int i = 0; i < Resolution; ++i) sum += internal[i];
    internal_reflectance = float(sum / Resolution * 2.0);
}

}  // namespace rbpt
