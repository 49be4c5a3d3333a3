// BSDFs with Mitsuba 3's semantics, in the local shading frame (z = normal). Each has
//   eval(wi, wo)   = f(wi, wo) |cos(wo)|              (templated number type S),
//   pdf(wi, wo)    = solid-angle density of sample()  (detached, float),
//   sample(wi, u)  = optional {wo, pdf, eta, delta, weight = eval / pdf}.
// One-sided like Mitsuba: wi below the surface reflects nothing (use `twosided`), except the
// dielectric, which has two sides by nature.
#pragma once

#include <optional>

#include "math.h"
#include "microfacet.h"
#include "shapes.h"
#include "textures.h"
#include "warp.h"

namespace rbpt {

enum class BSDFType { Diffuse, Conductor, RoughConductor, Dielectric, RoughPlastic };

/// A BSDF record: its type and where its inputs live in the parameter table.
struct BSDF {
    BSDFType type = BSDFType::Diffuse;
    bool twosided = false;
    TextureRef reflectance;  ///< diffuse `reflectance`, roughplastic `diffuse_reflectance`
    TextureRef specular_reflectance, specular_transmittance;
    int alpha = -1;          ///< roughness parameter (rough types)
    MicrofacetType distribution = MicrofacetType::Beckmann;
    float eta = 1.f;         ///< int_ior / ext_ior (dielectric, roughplastic)
    bool nonlinear = false;  ///< roughplastic `nonlinear`

    /// Whether the BSDF has a non-delta component (then emitters are sampled at its surface).
    bool smooth() const { return type != BSDFType::Conductor && type != BSDFType::Dielectric; }
};

/// Roughplastic's precomputed rough-interface terms for one (distribution, alpha, eta): the
/// external transmittance as a function of cos(theta) and the internal diffuse reflectance,
/// integrated by Gauss-Legendre quadrature over visible normals as Mitsuba does.
struct RoughPlasticTables {
    static constexpr int Resolution = 64;
    MicrofacetType type = MicrofacetType::Beckmann;
    float alpha = -1.f, eta = -1.f;
    float external_transmittance[Resolution];
    float internal_reflectance = 0.f;

    void compute(MicrofacetType type, float alpha, float eta);
    /// Mitsuba's lerp_gather over the table at cos(theta) in [0, 1].
    float transmittance(float cos_theta) const {
        float x = std::clamp(cos_theta, 0.f, 1.f) * float(Resolution - 1);
        int i = std::min(int(x), Resolution - 2);
        float t = x - float(i);
        return external_transmittance[i] * (1.f - t) + external_transmittance[i + 1] * t;
    }
};

/// Per-render derived BSDF data (depends on current parameter values; detached).
struct BSDFState {
    float specular_sampling_weight = 0.5f;  ///< roughplastic
    const RoughPlasticTables *tables = nullptr;
    /// Derivatives of `tables` with respect to alpha, when alpha is being differentiated.
    const RoughPlasticTables *dtables = nullptr;
};

template <typename S>
struct BSDFSample {
    Vec3 wo;
    float pdf = 0.f;
    float eta = 1.f;  ///< relative IOR along the sampled direction (1 unless refracted)
    bool delta = false;
    S weight;
};

/// Fresnel reflectance of a dielectric interface (Mitsuba's fresnel()): returns r and sets
/// the cosine of the refracted direction (opposite sign to cos_i) and eta_it, eta_ti.
float fresnel_dielectric(float cos_i, float eta, float *cos_t, float *eta_it, float *eta_ti);

namespace detail {

template <typename S, typename Ctx>
S texture(const TextureRef &t, const Ctx &ctx, const SurfaceInteraction &si) {
    return eval_texture<S>(t, ctx.bitmaps, ctx.params, si.uv);
}

}  // namespace detail

/// Lambertian reflector: f = reflectance / pi.
struct DiffuseBSDF {
    template <typename S, typename Ctx>
    static S eval(const BSDF &b, const Ctx &ctx, const SurfaceInteraction &si, const Vec3 &wi,
                  const Vec3 &wo) {
        if (wi.z <= 0.f || wo.z <= 0.f) return S(0.f);
        return detail::texture<S>(b.reflectance, ctx, si) * real_t<S>(InvPi * wo.z);
    }
    static float pdf(const Vec3 &wi, const Vec3 &wo) {
        return (wi.z > 0.f && wo.z > 0.f) ? warp::square_to_cosine_hemisphere_pdf(wo) : 0.f;
    }
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDF &b, const Ctx &ctx,
                                               const SurfaceInteraction &si, const Vec3 &wi,
                                               float, Vec2 u) {
        if (wi.z <= 0.f) return std::nullopt;
        BSDFSample<S> bs;
        bs.wo = warp::square_to_cosine_hemisphere(u);
        bs.pdf = pdf(wi, bs.wo);
        if (bs.pdf <= 0.f) return std::nullopt;
        bs.weight = detail::texture<S>(b.reflectance, ctx, si);
        return bs;
    }
};

/// Ideal mirror (Mitsuba's conductor with material "none"): F = specular_reflectance.
struct ConductorBSDF {
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDF &b, const Ctx &ctx,
                                               const SurfaceInteraction &si, const Vec3 &wi,
                                               float, Vec2) {
        if (wi.z <= 0.f) return std::nullopt;
        BSDFSample<S> bs;
        bs.wo = {-wi.x, -wi.y, wi.z};
        bs.pdf = 1.f;
        bs.delta = true;
        bs.weight = detail::texture<S>(b.specular_reflectance, ctx, si);
        return bs;
    }
};

/// Rough mirror: f = F D(h) G(wi, wo, h) / (4 cos_i cos_o), F = specular_reflectance.
/// Samples visible normals (weight = eval / pdf, which equals F G1(wo, m)).
struct RoughConductorBSDF {
    template <typename S, typename Ctx>
    static S eval(const BSDF &b, const Ctx &ctx, const SurfaceInteraction &si, const Vec3 &wi,
                  const Vec3 &wo) {
        if (wi.z <= 0.f || wo.z <= 0.f) return S(0.f);
        Vec3 h = normalize(wi + wo);
        real_t<S> alpha = ctx.params.real(b.alpha);
        real_t<S> value = microfacet_D(b.distribution, alpha, h) *
                          smith_G1(b.distribution, alpha, wi, h) *
                          smith_G1(b.distribution, alpha, wo, h) / (4.f * wi.z);
        return detail::texture<S>(b.specular_reflectance, ctx, si) * value;
    }
    template <typename Ctx>
    static float pdf(const BSDF &b, const Ctx &ctx, const Vec3 &wi, const Vec3 &wo) {
        if (wi.z <= 0.f || wo.z <= 0.f) return 0.f;
        Vec3 h = normalize(wi + wo);
        if (dot(wi, h) <= 0.f || dot(wo, h) <= 0.f) return 0.f;
        float alpha = detach_real(ctx.params.real(b.alpha));
        return microfacet_D(b.distribution, alpha, h) * smith_G1(b.distribution, alpha, wi, h) /
               (4.f * wi.z);
    }
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDF &b, const Ctx &ctx,
                                               const SurfaceInteraction &si, const Vec3 &wi,
                                               float, Vec2 u) {
        if (wi.z <= 0.f) return std::nullopt;
        float alpha_d = detach_real(ctx.params.real(b.alpha));
        Vec3 m = sample_visible_normal(b.distribution, alpha_d, wi, u);
        BSDFSample<S> bs;
        bs.wo = reflect(wi, m);
        if (bs.wo.z <= 0.f) return std::nullopt;
        bs.pdf = pdf(b, ctx, wi, bs.wo);
        if (!(bs.pdf > 0.f)) return std::nullopt;
        // eval / pdf with the pdf detached (not the simplified F G1(wo)): sampling carries
        // no derivative, so the weight's derivative must be d(eval)/d(theta) / pdf.
        bs.weight = eval<S>(b, ctx, si, wi, bs.wo) / real_t<S>(bs.pdf);
        return bs;
    }
};

/// Smooth dielectric interface: reflect with probability F, refract otherwise. Transmitted
/// radiance is scaled by 1/eta^2 (radiance transport), as in Mitsuba.
struct DielectricBSDF {
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDF &b, const Ctx &ctx,
                                               const SurfaceInteraction &si, const Vec3 &wi,
                                               float u1, Vec2) {
        float cos_t, eta_it, eta_ti;
        float r = fresnel_dielectric(wi.z, b.eta, &cos_t, &eta_it, &eta_ti);
        BSDFSample<S> bs;
        bs.delta = true;
        if (u1 <= r) {
            bs.wo = {-wi.x, -wi.y, wi.z};
            bs.pdf = r;
            bs.weight = detail::texture<S>(b.specular_reflectance, ctx, si);
        } else {
            bs.wo = {-eta_ti * wi.x, -eta_ti * wi.y, cos_t};
            bs.pdf = 1.f - r;
            bs.eta = eta_it;
            bs.weight = detail::texture<S>(b.specular_transmittance, ctx, si) *
                        real_t<S>(eta_ti * eta_ti);
        }
        if (!(bs.pdf > 0.f)) return std::nullopt;
        return bs;
    }
};

/// Mitsuba's roughplastic: a rough dielectric coating (specular F D G / (4 cos_i)) over a
/// diffuse base seen through it:
///   diffuse = rho / (1 - R_int) * t(cos_i) t(cos_o) cos_o / (pi eta^2),
/// with rho = diffuse_reflectance (rho R_int in the denominator when `nonlinear`).
struct RoughPlasticBSDF {
    template <typename S, typename Ctx>
    static S eval(const BSDF &b, const Ctx &ctx, const SurfaceInteraction &si, const Vec3 &wi,
                  const Vec3 &wo, const BSDFState &state) {
        if (wi.z <= 0.f || wo.z <= 0.f) return S(0.f);
        const RoughPlasticTables &tab = *state.tables;
        Vec3 h = normalize(wi + wo);
        real_t<S> alpha = ctx.params.real(b.alpha);
        float cos_t, eta_it, eta_ti;
        float F = fresnel_dielectric(dot(wi, h), b.eta, &cos_t, &eta_it, &eta_ti);
        real_t<S> spec = F * microfacet_D(b.distribution, alpha, h) *
                         smith_G1(b.distribution, alpha, wi, h) *
                         smith_G1(b.distribution, alpha, wo, h) / (4.f * wi.z);
        S value = detail::texture<S>(b.specular_reflectance, ctx, si) * spec;
        // The rough-interface terms depend on alpha through the tables; to first order,
        // t(alpha) = t(alpha0) + dt/dalpha (alpha - alpha0), with dt/dalpha tabulated.
        real_t<S> t_i = tab.transmittance(wi.z), t_o = tab.transmittance(wo.z);
        real_t<S> r_int = tab.internal_reflectance;
        if (state.dtables) {
            real_t<S> dalpha = alpha - no_grad(alpha);
            t_i = t_i + state.dtables->transmittance(wi.z) * dalpha;
            t_o = t_o + state.dtables->transmittance(wo.z) * dalpha;
            r_int = r_int + state.dtables->internal_reflectance * dalpha;
        }
        S diff = detail::texture<S>(b.reflectance, ctx, si);
        if (b.nonlinear) {
            diff = diff / (real_t<S>(1) - diff * r_int);
        } else {
            diff = diff / (real_t<S>(1) - r_int);
        }
        return value + diff * (t_i * t_o * real_t<S>(InvPi / (b.eta * b.eta) * wo.z));
    }
    /// Probability of sampling the specular lobe at incidence cos_i.
    static float specular_probability(const BSDFState &state, float cos_i) {
        float t_i = state.tables->transmittance(cos_i);
        float ps = (1.f - t_i) * state.specular_sampling_weight;
        float pd = t_i * (1.f - state.specular_sampling_weight);
        return ps + pd > 0.f ? ps / (ps + pd) : 0.5f;
    }
    template <typename Ctx>
    static float pdf(const BSDF &b, const Ctx &ctx, const Vec3 &wi, const Vec3 &wo,
                     const BSDFState &state) {
        if (wi.z <= 0.f || wo.z <= 0.f) return 0.f;
        float ps = specular_probability(state, wi.z);
        Vec3 h = normalize(wi + wo);
        float alpha = detach_real(ctx.params.real(b.alpha));
        float spec = microfacet_D(b.distribution, alpha, h) *
                     smith_G1(b.distribution, alpha, wi, h) / (4.f * wi.z);
        return ps * spec + (1.f - ps) * warp::square_to_cosine_hemisphere_pdf(wo);
    }
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDF &b, const Ctx &ctx,
                                               const SurfaceInteraction &si, const Vec3 &wi,
                                               float u1, Vec2 u, const BSDFState &state) {
        if (wi.z <= 0.f) return std::nullopt;
        BSDFSample<S> bs;
        if (u1 < specular_probability(state, wi.z)) {
            float alpha = detach_real(ctx.params.real(b.alpha));
            bs.wo = reflect(wi, sample_visible_normal(b.distribution, alpha, wi, u));
        } else {
            bs.wo = warp::square_to_cosine_hemisphere(u);
        }
        bs.pdf = pdf(b, ctx, wi, bs.wo, state);
        if (!(bs.pdf > 0.f)) return std::nullopt;
        bs.weight = eval<S>(b, ctx, si, wi, bs.wo, state) / real_t<S>(bs.pdf);
        return bs;
    }
};

// ---- Dispatch on the BSDF type (static: a switch, no virtual calls) ----------------------

/// Mirror directions into the upper hemisphere for `twosided` BSDFs seen from below.
inline bool flip_side(const BSDF &b, Vec3 *wi, Vec3 *wo) {
    if (!b.twosided || wi->z >= 0.f) return false;
    wi->z = -wi->z;
    if (wo) wo->z = -wo->z;
    return true;
}

template <typename S, typename Ctx>
S bsdf_eval(const BSDF &b, const Ctx &ctx, int index, const SurfaceInteraction &si, Vec3 wo) {
    Vec3 wi = si.wi;
    flip_side(b, &wi, &wo);
    switch (b.type) {
        case BSDFType::Diffuse: return DiffuseBSDF::eval<S>(b, ctx, si, wi, wo);
        case BSDFType::RoughConductor: return RoughConductorBSDF::eval<S>(b, ctx, si, wi, wo);
        case BSDFType::RoughPlastic:
            return RoughPlasticBSDF::eval<S>(b, ctx, si, wi, wo, ctx.bsdf_state[index]);
        default: return S(0.f);  // delta BSDFs have no density to evaluate
    }
}

template <typename Ctx>
float bsdf_pdf(const BSDF &b, const Ctx &ctx, int index, const SurfaceInteraction &si, Vec3 wo) {
    Vec3 wi = si.wi;
    flip_side(b, &wi, &wo);
    switch (b.type) {
        case BSDFType::Diffuse: return DiffuseBSDF::pdf(wi, wo);
        case BSDFType::RoughConductor: return RoughConductorBSDF::pdf(b, ctx, wi, wo);
        case BSDFType::RoughPlastic:
            return RoughPlasticBSDF::pdf(b, ctx, wi, wo, ctx.bsdf_state[index]);
        default: return 0.f;
    }
}

template <typename S, typename Ctx>
std::optional<BSDFSample<S>> bsdf_sample(const BSDF &b, const Ctx &ctx, int index,
                                         const SurfaceInteraction &si, float u1, Vec2 u2) {
    Vec3 wi = si.wi;
    bool flipped = flip_side(b, &wi, nullptr);
    std::optional<BSDFSample<S>> bs;
    switch (b.type) {
        case BSDFType::Diffuse: bs = DiffuseBSDF::sample<S>(b, ctx, si, wi, u1, u2); break;
        case BSDFType::Conductor: bs = ConductorBSDF::sample<S>(b, ctx, si, wi, u1, u2); break;
        case BSDFType::RoughConductor:
            bs = RoughConductorBSDF::sample<S>(b, ctx, si, wi, u1, u2);
            break;
        case BSDFType::Dielectric: bs = DielectricBSDF::sample<S>(b, ctx, si, wi, u1, u2); break;
        case BSDFType::RoughPlastic:
            bs = RoughPlasticBSDF::sample<S>(b, ctx, si, wi, u1, u2, ctx.bsdf_state[index]);
            break;
    }
    if (bs && flipped) bs->wo.z = -bs->wo.z;
    return bs;
}

}  // namespace rbpt
