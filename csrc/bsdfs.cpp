#include "bsdfs.h"

#include <vector>

namespace rbpt {

float fresnel_dielectric(float cos_i, float eta, float *cos_t, float *eta_it, float *eta_ti) {
    bool outside = cos_i >= 0.f;
    float rcp_eta = 1.f / eta;
    *eta_it = outside ? eta : rcp_eta;
    *eta_ti = outside ? rcp_eta : eta;
    float cos_t2 = 1.f - (*eta_ti) * (*eta_ti) * (1.f - cos_i * cos_i);
    float ci = std::abs(cos_i), ct = safe_sqrt(cos_t2);
    *cos_t = outside ? -ct : ct;
    if (eta == 1.f) return 0.f;
    if (ci == 0.f) return 1.f;
    float a_s = (ci - *eta_it * ct) / (ci + *eta_it * ct);
    float a_p = (ct - *eta_it * ci) / (ct + *eta_it * ci);
    return 0.5f * (a_s * a_s + a_p * a_p);
}

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
    Vec2 px[128], py[128];  // (res is 32 or 128)
    for (int i = 0; i < res; ++i) {
        float u = float(0.5 * nodes[i] + 0.5);
        px[i] = sampler.part_x(u);
        py[i] = sampler.part_y(u);
    }
    double sum = 0.0;
    for (int i = 0; i < res; ++i) {
        for (int j = 0; j < res; ++j) {
            Vec3 m = sampler.normal(px[i], py[j]);
            float cos_t, eta_it, eta_ti;
            float F = fresnel_dielectric(dot(wi, m), eta, &cos_t, &eta_it, &eta_ti);
            float value;
            if (transmit) {
                Vec3 wt = m * (dot(wi, m) * eta_ti + cos_t) - wi * eta_ti;
                value = (1.f - F) * smith_G1(type, alpha, wt, m);
            } else {
                Vec3 wo = reflect(wi, m);
                value = wo.z > 0.f ? F * smith_G1(type, alpha, wo, m) : 0.f;
            }
            sum += value * weights[i] * weights[j];
        }
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
