// BSDFs with Mitsuba 3's semantics, in the local shading frame (z = normal). Every BSDF is a
// struct with the same interface, queried through a BSDFQuery (the BSDF record, the render's
// parameter values and the BSDF's per-render state, the surface point):
//   delta               whether it is purely specular (then it has no density to evaluate);
//   eval(q, wi, wo)     = f(wi, wo) |cos(wo)|                  (templated number type S);
//   pdf(q, wi, wo)      = solid-angle density of sample()      (detached, float);
//   eval_pdf(q, wi, wo) = both at once, sharing their common terms (emitter sampling needs
//                         both for every shadow ray);
//   sample(q, wi, u1, u2) = optional {wo, pdf, eta, delta, weight = eval / pdf}.
// A new BSDF is one such struct, a BSDFType and one line in visit_bsdf().
// One-sided like Mitsuba: wi below the surface reflects nothing (use `twosided`), except the
// dielectric, which has two sides by nature.
#pragma once

#include <optional>
#include <type_traits>

#include "dual.h"
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
    inline bool smooth() const;
    /// Whether an input is a texture (bitmap, checkerboard), which reads the surface's uv.
    bool reads_uv() const {
        return reflectance.texture >= 0 || specular_reflectance.texture >= 0 ||
               specular_transmittance.texture >= 0;
    }
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
        float x = (cos_theta > 0.f ? std::min(cos_theta, 1.f) : 0.f) * float(Resolution - 1);
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

/// A BSDF value and the density with which sample() produces the same direction.
template <typename S>
struct BSDFEval {
    S value;
    float pdf = 0.f;
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
/// the cosine of the refracted direction (opposite sign to cos_i) and eta_it, eta_ti. Inline:
/// the BSDFs call it per vertex, and roughplastic's quadratures in loops that the compiler
/// vectorises.
inline float fresnel_dielectric(float cos_i, float eta, float *cos_t, float *eta_it, float *eta_ti) {
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

/// Everything a BSDF query reads besides the directions.
template <typename Ctx>
struct BSDFQuery {
    const BSDF &bsdf;
    const Ctx &ctx;                ///< the render's parameter values (RenderContext<S>)
    const BSDFState &state;        ///< per-render derived data of this BSDF
    const SurfaceInteraction &si;  ///< the surface point (uv for textures)

    /// A texture input of this BSDF at the surface point.
    template <typename S>
    S texture(const TextureRef &t) const {
        if (t.attribute >= 0) {  // (the loader checks that every shape using it has it)
            const auto &g = ctx.scene.geometry;
            const auto &shape = g.shapes[si.shape];
            const auto &tri = g.triangles[si.tri];
            uint32_t v[3] = {tri.v[0] - shape.vertex_begin, tri.v[1] - shape.vertex_begin,
                             tri.v[2] - shape.vertex_begin};
            return eval_mesh_attribute<S>(MeshAttribute(t.attribute), shape.attribute_param[t.attribute],
                                          shape.attribute_channels[t.attribute], v,
                                          si.tri - shape.tri_begin, si.b1, si.b2, ctx.params);
        }
        return eval_texture<S>(t, ctx.textures, ctx.params, si.uv);
    }
    /// The roughness parameter, with its derivative (R = real_t<S>) or detached (float, read
    /// straight from the values so that autodiff types record nothing).
    template <typename R>
    R alpha() const {
        if constexpr (std::is_same_v<R, float>) {
            return float(ctx.params.data[bsdf.alpha][0]);
        } else {
            return ctx.params.real(bsdf.alpha);
        }
    }
};

/// Whether the number type S is plain float, for which eval and pdf can share their terms
/// exactly (autodiff types evaluate the value with derivatives and the density detached).
template <typename S>
constexpr bool plain_float = std::is_same_v<real_t<S>, float>;

/// Purely specular BSDFs: no density to evaluate, only sampling.
struct DeltaBSDF {
    static constexpr bool delta = true;
    template <typename S, typename Ctx>
    static S eval(const BSDFQuery<Ctx> &, const Vec3 &, const Vec3 &) {
        return S(0.f);
    }
    template <typename Ctx>
    static float pdf(const BSDFQuery<Ctx> &, const Vec3 &, const Vec3 &) {
        return 0.f;
    }
    template <typename S, typename Ctx>
    static BSDFEval<S> eval_pdf(const BSDFQuery<Ctx> &, const Vec3 &, const Vec3 &) {
        return {S(0.f), 0.f};
    }
};

/// Lambertian reflector: f = reflectance / pi.
struct DiffuseBSDF {
    static constexpr bool delta = false;
    template <typename S, typename Ctx>
    static S eval(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        if (!(wi.z > 0.f && wo.z > 0.f)) return S(0.f);
        return q.template texture<S>(q.bsdf.reflectance) * real_t<S>(InvPi * wo.z);
    }
    template <typename Ctx>
    static float pdf(const BSDFQuery<Ctx> &, const Vec3 &wi, const Vec3 &wo) {
        return wi.z > 0.f && wo.z > 0.f ? warp::square_to_cosine_hemisphere_pdf(wo) : 0.f;
    }
    template <typename S, typename Ctx>
    static BSDFEval<S> eval_pdf(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        return {eval<S>(q, wi, wo), pdf(q, wi, wo)};
    }
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDFQuery<Ctx> &q, const Vec3 &wi, float,
                                               Vec2 u) {
        if (wi.z <= 0.f) return std::nullopt;
        BSDFSample<S> bs;
        bs.wo = warp::square_to_cosine_hemisphere(u);
        bs.pdf = pdf(q, wi, bs.wo);
        if (bs.pdf <= 0.f) return std::nullopt;
        bs.weight = q.template texture<S>(q.bsdf.reflectance);
        return bs;
    }
};

/// Ideal mirror (Mitsuba's conductor with material "none"): F = specular_reflectance.
struct ConductorBSDF : DeltaBSDF {
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDFQuery<Ctx> &q, const Vec3 &wi, float,
                                               Vec2) {
        if (wi.z <= 0.f) return std::nullopt;
        BSDFSample<S> bs;
        bs.wo = {-wi.x, -wi.y, wi.z};
        bs.pdf = 1.f;
        bs.delta = true;
        bs.weight = q.template texture<S>(q.bsdf.specular_reflectance);
        return bs;
    }
};

/// Rough mirror: f = F D(h) G(wi, wo, h) / (4 cos_i cos_o), F = specular_reflectance.
/// Samples visible normals: pdf = D(h) G1(wi, h) / (4 cos_i).
struct RoughConductorBSDF {
    static constexpr bool delta = false;
    /// D(h) G1(wi, h) / (4 cos_i) and h, or zero where wi, wo or h face away.
    template <typename R, typename Ctx>
    static R lobe(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo, Vec3 *h) {
        *h = normalize(wi + wo);
        R alpha = q.template alpha<R>();
        return microfacet_D(q.bsdf.distribution, alpha, *h) *
               smith_G1(q.bsdf.distribution, alpha, wi, *h) / (4.f * wi.z);
    }
    template <typename S, typename Ctx>
    static S eval(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        return eval_pdf<S>(q, wi, wo).value;
    }
    template <typename Ctx>
    static float pdf(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        if (!(wi.z > 0.f && wo.z > 0.f)) return 0.f;
        Vec3 h;
        float value = lobe<float>(q, wi, wo, &h);
        return dot(wi, h) > 0.f && dot(wo, h) > 0.f ? value : 0.f;
    }
    template <typename S, typename Ctx>
    static BSDFEval<S> eval_pdf(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        if (!(wi.z > 0.f && wo.z > 0.f)) return {S(0.f), 0.f};
        Vec3 h;
        real_t<S> l = lobe<real_t<S>>(q, wi, wo, &h);
        real_t<S> g = smith_G1(q.bsdf.distribution, q.template alpha<real_t<S>>(), wo, h);
        S value = q.template texture<S>(q.bsdf.specular_reflectance) * (l * g);
        float density = 0.f;
        if constexpr (plain_float<S>) {
            density = dot(wi, h) > 0.f && dot(wo, h) > 0.f ? l : 0.f;
        } else {
            density = pdf(q, wi, wo);
        }
        return {value, density};
    }
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDFQuery<Ctx> &q, const Vec3 &wi, float,
                                               Vec2 u) {
        if (wi.z <= 0.f) return std::nullopt;
        Vec3 m = sample_visible_normal(q.bsdf.distribution, q.template alpha<float>(), wi, u);
        BSDFSample<S> bs;
        bs.wo = reflect(wi, m);
        if (!(bs.wo.z > 0.f)) return std::nullopt;
        BSDFEval<S> e = eval_pdf<S>(q, wi, bs.wo);
        bs.pdf = e.pdf;
        if (!(bs.pdf > 0.f)) return std::nullopt;
        // eval / pdf with the pdf detached (not the simplified F G1(wo)): sampling carries
        // no derivative, so the weight's derivative must be d(eval)/d(theta) / pdf.
        bs.weight = e.value / real_t<S>(bs.pdf);
        return bs;
    }
    /// d log(value) / d alpha at (wi, wo): alpha enters the value as one factor common to all
    /// channels, D(h) G1(wi, h) G1(wo, h), whose derivative microfacet_dlog_dalpha gives in
    /// closed form (render_bwd's roughness derivatives, in SIMD lanes: the distribution a
    /// template argument). Zero where the value is.
    template <MicrofacetType Type>
    RBPT_INLINE static float dlog_dalpha(float alpha, const Vec3 &wi, const Vec3 &wo) {
        if (!(wi.z > 0.f && wo.z > 0.f)) return 0.f;
        return microfacet_dlog_dalpha<Type>(alpha, wi, wo, normalize(wi + wo)).dlog;
    }
};

/// Smooth dielectric interface: reflect with probability F, refract otherwise. Transmitted
/// radiance is scaled by 1/eta^2 (radiance transport), as in Mitsuba.
struct DielectricBSDF : DeltaBSDF {
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDFQuery<Ctx> &q, const Vec3 &wi, float u1,
                                               Vec2) {
        float cos_t, eta_it, eta_ti;
        float r = fresnel_dielectric(wi.z, q.bsdf.eta, &cos_t, &eta_it, &eta_ti);
        BSDFSample<S> bs;
        bs.delta = true;
        if (u1 <= r) {
            bs.wo = {-wi.x, -wi.y, wi.z};
            bs.pdf = r;
            bs.weight = q.template texture<S>(q.bsdf.specular_reflectance);
        } else {
            bs.wo = {-eta_ti * wi.x, -eta_ti * wi.y, cos_t};
            bs.pdf = 1.f - r;
            bs.eta = eta_it;
            bs.weight = q.template texture<S>(q.bsdf.specular_transmittance) *
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
/// Samples the specular lobe with probability specular_probability(cos_i), else the cosine.
struct RoughPlasticBSDF {
    static constexpr bool delta = false;
    /// Probability of sampling the specular lobe at incidence cos_i.
    static float specular_probability(const BSDFState &state, float cos_i) {
        float t_i = state.tables->transmittance(cos_i);
        float ps = (1.f - t_i) * state.specular_sampling_weight;
        float pd = t_i * (1.f - state.specular_sampling_weight);
        return ps + pd > 0.f ? ps / (ps + pd) : 0.5f;
    }
    /// D(h) G1(wi, h) / (4 cos_i): the specular lobe's visible-normal density.
    template <typename R, typename Ctx>
    static R lobe(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &h) {
        R alpha = q.template alpha<R>();
        return microfacet_D(q.bsdf.distribution, alpha, h) *
               smith_G1(q.bsdf.distribution, alpha, wi, h) / (4.f * wi.z);
    }
    template <typename Ctx>
    static float density(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo, float spec) {
        float ps = specular_probability(q.state, wi.z);
        return ps * spec + (1.f - ps) * warp::square_to_cosine_hemisphere_pdf(wo);
    }
    template <typename S, typename Ctx>
    static S eval(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        return eval_pdf<S>(q, wi, wo).value;
    }
    template <typename Ctx>
    static float pdf(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        if (!(wi.z > 0.f && wo.z > 0.f)) return 0.f;
        return density(q, wi, wo, lobe<float>(q, wi, normalize(wi + wo)));
    }
    template <typename S, typename Ctx>
    static BSDFEval<S> eval_pdf(const BSDFQuery<Ctx> &q, const Vec3 &wi, const Vec3 &wo) {
        using R = real_t<S>;
        if (!(wi.z > 0.f && wo.z > 0.f)) return {S(0.f), 0.f};
        const BSDF &b = q.bsdf;
        const RoughPlasticTables &tab = *q.state.tables;
        Vec3 h = normalize(wi + wo);
        R alpha = q.template alpha<R>();
        float cos_t, eta_it, eta_ti;
        float F = fresnel_dielectric(dot(wi, h), b.eta, &cos_t, &eta_it, &eta_ti);
        R l = lobe<R>(q, wi, h);
        R spec = F * l * smith_G1(b.distribution, alpha, wo, h);
        S value = q.template texture<S>(b.specular_reflectance) * spec;
        // The rough-interface terms depend on alpha through the tables; to first order,
        // t(alpha) = t(alpha0) + dt/dalpha (alpha - alpha0), with dt/dalpha tabulated.
        R t_i = tab.transmittance(wi.z), t_o = tab.transmittance(wo.z);
        R r_int = tab.internal_reflectance;
        if (q.state.dtables) {
            R dalpha = alpha - no_grad(alpha);
            t_i = t_i + q.state.dtables->transmittance(wi.z) * dalpha;
            t_o = t_o + q.state.dtables->transmittance(wo.z) * dalpha;
            r_int = r_int + q.state.dtables->internal_reflectance * dalpha;
        }
        S diff = q.template texture<S>(b.reflectance);
        if (b.nonlinear) {
            diff = diff / (R(1) - diff * r_int);
        } else {
            diff = diff / (R(1) - r_int);
        }
        value = value + diff * (t_i * t_o * R(InvPi / (b.eta * b.eta) * wo.z));
        float pdf_value;
        if constexpr (plain_float<S>) {
            pdf_value = density(q, wi, wo, l);
        } else {
            pdf_value = pdf(q, wi, wo);
        }
        return {value, pdf_value};
    }
    template <typename S, typename Ctx>
    static std::optional<BSDFSample<S>> sample(const BSDFQuery<Ctx> &q, const Vec3 &wi, float u1,
                                               Vec2 u) {
        if (wi.z <= 0.f) return std::nullopt;
        BSDFSample<S> bs;
        if (u1 < specular_probability(q.state, wi.z)) {
            bs.wo = reflect(wi, sample_visible_normal(q.bsdf.distribution, q.template alpha<float>(), wi, u));
        } else {
            bs.wo = warp::square_to_cosine_hemisphere(u);
        }
        BSDFEval<S> e = eval_pdf<S>(q, wi, bs.wo);
        bs.pdf = e.pdf;
        if (!(bs.pdf > 0.f)) return std::nullopt;
        bs.weight = e.value / real_t<S>(bs.pdf);
        return bs;
    }
    /// d log f_c / d rho_c at (wi, wo) for each channel c, rho the diffuse reflectance and ks
    /// the specular reflectance (as looked up at the vertex), alpha the roughness: rho is a
    /// factor of one of f's two terms, f = ks spec + g(rho) base with g(rho) = rho / (1 - R_int)
    /// (rho / (1 - rho R_int) when nonlinear), so d log f / d rho = g'(rho) base / f (render_bwd's
    /// roughplastic reflectances in lanes). eval_pdf's operations in float; zero where base is
    /// (wi or wo below the surface), infinite where f_c is zero and base is not (the path's
    /// later radiance in c, zero, cannot give the derivative).
    static RGB<float> dlog_dreflectance(const BSDF &b, const BSDFState &state, float alpha, const Vec3 &wi,
                                        const Vec3 &wo, const RGB<float> &rho, const RGB<float> &ks) {
        if (!(wi.z > 0.f && wo.z > 0.f)) return RGB<float>(0.f);
        const RoughPlasticTables &tab = *state.tables;
        const Vec3 h = normalize(wi + wo);
        float cos_t, eta_it, eta_ti;
        const float F = fresnel_dielectric(dot(wi, h), b.eta, &cos_t, &eta_it, &eta_ti);
        const float spec = F * (microfacet_D(b.distribution, alpha, h) * smith_G1(b.distribution, alpha, wi, h) /
                                (4.f * wi.z)) * smith_G1(b.distribution, alpha, wo, h);
        const float base = tab.transmittance(wi.z) * tab.transmittance(wo.z) * (InvPi / (b.eta * b.eta) * wo.z);
        const float r_int = tab.internal_reflectance;
        RGB<float> dlog(0.f);
        for (int c = 0; c < 3; ++c) {
            const float g = b.nonlinear ? rho[c] / (1.f - rho[c] * r_int) : rho[c] / (1.f - r_int);
            const float dg = b.nonlinear ? 1.f / ((1.f - rho[c] * r_int) * (1.f - rho[c] * r_int)) : 1.f / (1.f - r_int);
            const float f = ks[c] * spec + g * base;
            dlog[c] = base != 0.f ? dg * base / f : 0.f;
        }
        return dlog;
    }
    /// d log f_c / d alpha at (wi, wo) for each channel c (render_bwd's roughplastic roughness
    /// in lanes): alpha enters f = ks F D G1(wi) G1(wo) / (4 cos_i) + g(rho, R_int) t(cos_i)
    /// t(cos_o) cos_o / (pi eta^2) through D and the G1s (microfacet_dlog_dalpha, as
    /// RoughConductorBSDF::dlog_dalpha) and through the tables, t and R_int, whose
    /// derivatives `state.dtables` holds (as eval_pdf's first order). Zero where f and its
    /// derivative are, infinite where only f is.
    static RGB<float> dlog_dalpha(const BSDF &b, const BSDFState &state, float alpha, const Vec3 &wi,
                                  const Vec3 &wo, const RGB<float> &rho, const RGB<float> &ks) {
        if (!(wi.z > 0.f && wo.z > 0.f)) return RGB<float>(0.f);
        const RoughPlasticTables &tab = *state.tables, &dtab = *state.dtables;
        const Vec3 h = normalize(wi + wo);
        float cos_t, eta_it, eta_ti;
        const float F = fresnel_dielectric(dot(wi, h), b.eta, &cos_t, &eta_it, &eta_ti);
        const FactorDlog s = microfacet_dlog_dalpha(b.distribution, alpha, wi, wo, h);
        const float spec = F * s.value / (4.f * wi.z), dspec = spec * s.dlog;
        const float k = InvPi / (b.eta * b.eta) * wo.z;
        const float t_i = tab.transmittance(wi.z), t_o = tab.transmittance(wo.z);
        const float dt = dtab.transmittance(wi.z) * t_o + t_i * dtab.transmittance(wo.z);
        const float r_int = tab.internal_reflectance, dr_int = dtab.internal_reflectance;
        RGB<float> dlog(0.f);
        for (int c = 0; c < 3; ++c) {
            const float den = b.nonlinear ? 1.f - rho[c] * r_int : 1.f - r_int;
            const float g = rho[c] / den;
            const float dg = (b.nonlinear ? rho[c] * rho[c] : rho[c]) / (den * den) * dr_int;  // d g / d R_int dR_int
            const float f = ks[c] * spec + g * (t_i * t_o) * k;
            const float df = ks[c] * dspec + (dg * (t_i * t_o) + g * dt) * k;
            dlog[c] = df != 0.f ? df / f : 0.f;
        }
        return dlog;
    }
};

// ---- Dispatch on the BSDF type (static: one switch, no virtual calls) --------------------

/// Call f with a value of the BSDF struct of `type` (the only switch over BSDF types).
template <typename F>
RBPT_INLINE decltype(auto) visit_bsdf(BSDFType type, F &&f) {
    switch (type) {
        case BSDFType::Diffuse: return f(DiffuseBSDF{});
        case BSDFType::Conductor: return f(ConductorBSDF{});
        case BSDFType::RoughConductor: return f(RoughConductorBSDF{});
        case BSDFType::Dielectric: return f(DielectricBSDF{});
        case BSDFType::RoughPlastic: return f(RoughPlasticBSDF{});
    }
    return f(DiffuseBSDF{});  // not reached: every type is listed above
}

inline bool BSDF::smooth() const {
    return visit_bsdf(type, [](auto b) { return !decltype(b)::delta; });
}

/// Mirror directions into the upper hemisphere for `twosided` BSDFs seen from below.
inline bool flip_side(const BSDF &b, Vec3 *wi, Vec3 *wo) {
    if (!b.twosided || wi->z >= 0.f) return false;
    wi->z = -wi->z;
    if (wo) wo->z = -wo->z;
    return true;
}

template <typename Ctx>
BSDFQuery<Ctx> make_query(const BSDF &b, const Ctx &ctx, int index, const SurfaceInteraction &si) {
    return {b, ctx, ctx.bsdf_state[index], si};
}

template <typename S, typename Ctx>
S bsdf_eval(const BSDF &b, const Ctx &ctx, int index, const SurfaceInteraction &si, Vec3 wo) {
    Vec3 wi = si.wi;
    flip_side(b, &wi, &wo);
    auto q = make_query(b, ctx, index, si);
    return visit_bsdf(b.type, [&](auto bsdf) { return decltype(bsdf)::template eval<S>(q, wi, wo); });
}

template <typename Ctx>
float bsdf_pdf(const BSDF &b, const Ctx &ctx, int index, const SurfaceInteraction &si, Vec3 wo) {
    Vec3 wi = si.wi;
    flip_side(b, &wi, &wo);
    auto q = make_query(b, ctx, index, si);
    return visit_bsdf(b.type, [&](auto bsdf) { return decltype(bsdf)::pdf(q, wi, wo); });
}

template <typename S, typename Ctx>
RBPT_INLINE BSDFEval<S> bsdf_eval_pdf(const BSDF &b, const Ctx &ctx, int index,
                                      const SurfaceInteraction &si, Vec3 wo) {
    Vec3 wi = si.wi;
    flip_side(b, &wi, &wo);
    auto q = make_query(b, ctx, index, si);
    return visit_bsdf(b.type, [&](auto bsdf) { return decltype(bsdf)::template eval_pdf<S>(q, wi, wo); });
}

template <typename S, typename Ctx>
RBPT_INLINE std::optional<BSDFSample<S>> bsdf_sample(const BSDF &b, const Ctx &ctx, int index,
                                                     const SurfaceInteraction &si, float u1,
                                                     Vec2 u2) {
    Vec3 wi = si.wi;
    bool flipped = flip_side(b, &wi, nullptr);
    auto q = make_query(b, ctx, index, si);
    auto bs = visit_bsdf(b.type, [&](auto bsdf) { return decltype(bsdf)::template sample<S>(q, wi, u1, u2); });
    if (bs && flipped) bs->wo.z = -bs->wo.z;
    return bs;
}

}  // namespace rbpt
