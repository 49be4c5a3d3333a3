// The integrators, written once for any number type S: `path` (unidirectional path tracing
// with next-event estimation, MIS and Russian roulette, as Mitsuba's `path`) and `direct`.
// Sampling decisions (directions, emitter choice, roulette) use detached values only.
#pragma once

#include <optional>

#include "sampler.h"
#include "scene.h"

namespace rbpt {

enum class IntegratorType { Path, Direct };

struct IntegratorSettings {
    IntegratorType type = IntegratorType::Path;
    int max_depth = -1;  ///< Mitsuba's meaning: 1 = emitters seen directly; -1 = unbounded
    int rr_depth = 5;
    int emitter_samples = 1, bsdf_samples = 1;  ///< direct
    bool hide_emitters = false;  ///< drop emitters seen directly by the camera
    /// `path` only as path_settings() makes it of `direct` with no BSDF or no emitter samples:
    /// whether vertices sample an emitter, and whether the emission BSDF samples find counts
    /// (without, a path ends after its emitter sample). Either alone is not MIS-weighted.
    bool emitter_sampling = true, bsdf_sampling = true;
    /// `path` only as path_settings() makes it of `direct` with n samples of each kind (or n
    /// of one kind alone): n paths of two vertices from each camera ray's first vertex, each
    /// of throughput 1/n after the emission found there (direct_li).
    int sub_paths = 1;
};

/// The `path` settings under which path_li computes what `cfg` computes, with the same random
/// numbers and the same operations in the same order: `path` itself, and `direct` with n
/// emitter samples and n BSDF samples (or n of one kind and none of the other), which
/// direct_li computes as n paths of two vertices from the camera ray's first vertex (path_li
/// with max_depth 2 and no roulette, sub_paths n: their throughput starts at 1/n, and only the
/// first adds the emission the camera ray found). With n of each, the MIS weights are
/// Mitsuba's direct's (whose fractions n / 2n of each technique cancel); with one kind alone, the
/// other technique's density in the MIS weight is times 0 (emitter_sampling, bsdf_sampling),
/// as in direct's (its factor is 0). Nothing for other `direct` settings (unequal nonzero
/// counts), which direct_li samples as Mitsuba's direct: all emitter samples, then all BSDF
/// samples. (tests/test_wavefront.py checks the wavefront's `direct` against direct_li
/// bitwise.)
inline std::optional<IntegratorSettings> path_settings(const IntegratorSettings &cfg) {
    if (cfg.type == IntegratorType::Path) return cfg;
    const int n_e = cfg.emitter_samples, n_b = cfg.bsdf_samples;
    const bool paired = n_e >= 0 && n_b >= 0 && (n_e == n_b || n_e == 0 || n_b == 0) && n_e + n_b > 0;
    if (!paired || cfg.max_depth == 0) return std::nullopt;
    IntegratorSettings path = cfg;
    path.type = IntegratorType::Path;
    path.emitter_sampling = n_e > 0;
    path.bsdf_sampling = n_b > 0;
    path.sub_paths = std::max(n_e, n_b);
    path.max_depth = 2;
    path.rr_depth = 2;  // (roulette starts where depth + 1 >= rr_depth: after the last vertex)
    return path;
}

/// Power heuristic with Mitsuba's guard against non-finite weights.
inline float mis_weight(float a, float b) {
    a *= a;
    b *= b;
    float w = a / (a + b);
    return std::isfinite(w) ? w : 0.f;
}

/// Highest survival probability of Russian roulette: keeps paths finite in closed scenes of
/// unit albedo while leaving the variance bounded for any albedo below ~0.99995.
constexpr float MaxSurvival = 0.9999f;

template <typename S>
inline bool is_zero(const S &s) {
    Color3f c = detach(s);
    return c[0] == 0.f && c[1] == 0.f && c[2] == 0.f;
}

/// Whether a factor makes every later contribution vanish, derivatives included: zero and
/// carrying no derivative. (A zero parameter still has a derivative; its paths go on.)
template <typename S>
inline bool is_null(const S &s) {
    return is_zero(s) && !SpectrumTraits<S>::has_derivative(s);
}

/// The detached throughput factor that Russian roulette sees for a sample weight: its value,
/// or 1 where the value is zero but carries a derivative (so the derivative's path survives
/// as if the parameter were 1; any positive survival probability keeps it unbiased).
template <typename S>
inline Color3f roulette_factor(const S &weight) {
    return is_null(weight) || !is_zero(weight) ? detach(weight) : Color3f(1.f);
}

/// The BSDF towards a sampled emitter direction, with its density unless the emitter is a
/// delta light (whose samples are never MIS-weighted).
template <typename S>
RBPT_INLINE BSDFEval<S> bsdf_eval_for(const BSDF &bsdf, const RenderContext<S> &ctx, int index,
                                      const SurfaceInteraction &si, const EmitterSample<S> &es) {
    Vec3 wo = si.to_local(es.d);
    if (es.delta) return {bsdf_eval<S>(bsdf, ctx, index, si, wo), 0.f};
    return bsdf_eval_pdf<S>(bsdf, ctx, index, si, wo);
}

/// The shadow ray from `si` towards a sampled emitter point (or direction, for the
/// environment).
template <typename S>
RBPT_INLINE Ray shadow_ray(const SurfaceInteraction &si, const EmitterSample<S> &es) {
    return std::isinf(es.dist) ? si.spawn_ray(es.d) : si.spawn_ray_to(es.p);
}

/// A path between two vertices: path_li's loop state.
template <typename S>
struct PathState {
    S L = S(0.f), beta = S(1.f);
    Color3f beta_rr = Color3f(1.f);  ///< detached throughput for roulette (see roulette_factor)
    float eta = 1.f, prev_pdf = 1.f;
    bool prev_delta = true;
    Vec3 prev_p;
};

/// The emission of emitter `e` that a path of throughput `beta` found at `si` (or, for the
/// environment, by escaping), MIS-weighted against the emitter sampling of its previous vertex
/// (at prev_p, where the BSDF sample had density prev_pdf, or was a delta one).
template <typename S>
RBPT_INLINE S emission_found(const RenderContext<S> &ctx, const Emitter &e, const SurfaceInteraction &si,
                             const S &beta, bool prev_delta, float prev_pdf, const Vec3 &prev_p) {
    float em_pdf = prev_delta ? 0.f : emitter_pdf(ctx, e, prev_p, si);
    return beta * emitter_eval<S>(ctx, e, si) * real_t<S>(mis_weight(prev_pdf, em_pdf));
}

/// path_li's work at the surface vertex `si` of depth `depth`, after the emission found
/// there: the emitter sample and its shadow ray, the BSDF sample for the next ray (into
/// `ray`) and Russian roulette. Returns whether the path goes on. (The wavefront runs it for
/// the vertices its vector stage does not shade.)
template <typename S>
RBPT_INLINE bool path_vertex(const RenderContext<S> &ctx, const IntegratorSettings &cfg, int depth,
                             const SurfaceInteraction &si, Sampler &sampler, PathState<S> &path,
                             Ray &ray) {
    const Scene &scene = ctx.scene;
    int bsdf_index = scene.bsdf_at(si);
    const BSDF &bsdf = scene.bsdfs[bsdf_index];

    // Sample an emitter and add its MIS-weighted direct illumination. The BSDF comes
    // first: where it is null (e.g. the emitter is below the horizon), no shadow ray.
    if (cfg.emitter_sampling && bsdf.smooth()) {
        auto es = emitter_sample<S>(ctx, si.p, sampler.next_2d());
        if (es && !is_null(es->weight)) {
            BSDFEval<S> f = bsdf_eval_for(bsdf, ctx, bsdf_index, si, *es);
            if (!is_null(f.value) && !scene.occluded(shadow_ray(si, *es))) {
                const float bsdf_pdf = cfg.bsdf_sampling ? f.pdf : f.pdf * 0.f;
                float w = es->delta ? 1.f : mis_weight(es->pdf, bsdf_pdf);
                path.L += path.beta * f.value * es->weight * real_t<S>(w);
            }
        }
    }
    if (!cfg.bsdf_sampling) return false;

    // Sample the BSDF for the direction of the next ray.
    float u1 = sampler.next_1d();
    Vec2 u2 = sampler.next_2d();
    auto bs = bsdf_sample<S>(bsdf, ctx, bsdf_index, si, u1, u2);
    if (!bs) return false;
    path.beta *= bs->weight;
    path.beta_rr *= roulette_factor(bs->weight);
    path.eta *= bs->eta;
    path.prev_p = si.p;
    path.prev_pdf = bs->pdf;
    // (Without emitter sampling, the emission found is weighted as a delta sample's: by 1.)
    path.prev_delta = bs->delta || !cfg.emitter_sampling;
    si.spawn_ray(si.to_world(bs->wo), &ray);

    // Possibly terminate the path with Russian roulette. The survival probability is the
    // roulette throughput itself (capped just below 1), so a surviving path's weight
    // stays bounded by its BSDF weights: no growth at high albedo.
    float beta_max = max_component(path.beta_rr);
    if (!(beta_max > 0.f)) return false;
    if (depth + 1 >= cfg.rr_depth) {
        float q = std::min(beta_max * path.eta * path.eta, MaxSurvival);
        if (sampler.next_1d() >= q) return false;
        path.beta = path.beta * real_t<S>(1.f / q);
        path.beta_rr = path.beta_rr * (1.f / q);
    }
    return true;
}

template <typename S>
S path_li(const RenderContext<S> &ctx, const IntegratorSettings &cfg, Ray ray, Sampler &sampler) {
    const Scene &scene = ctx.scene;
    PathState<S> path;
    if (cfg.max_depth == 0) return path.L;  // as Mitsuba: no vertex at all, not even emitters seen
    for (int depth = 0;; ++depth) {
        // Find the next surface along the ray; at the last vertex max_depth allows, only an
        // emitter's (the interaction is completed for emitters only).
        bool last = cfg.max_depth >= 0 && depth + 1 >= cfg.max_depth;
        int emitter;
        SurfaceInteraction si = last ? scene.intersect_emitter(ray, &emitter) : scene.intersect(ray);
        if (!last) emitter = scene.emitter_at(si);

        // Add emission the ray found, MIS-weighted against emitter sampling at the last vertex.
        if (emitter >= 0 && !(cfg.hide_emitters && depth == 0))
            path.L += emission_found(ctx, scene.emitters[emitter], si, path.beta, path.prev_delta,
                                     path.prev_pdf, path.prev_p);

        // Stop when the ray escaped or the next vertex would exceed max_depth.
        if (!si.valid || last) break;

        // Shade the vertex and continue along the next ray, unless the path ends there.
        if (!path_vertex(ctx, cfg, depth, si, sampler, path, ray)) break;
    }
    return path.L;
}

template <typename S>
S direct_li(const RenderContext<S> &ctx, const IntegratorSettings &cfg, Ray ray, Sampler &sampler) {
    const Scene &scene = ctx.scene;
    if (cfg.max_depth == 0) return S(0.f);
    // Find the first surface and add the emission seen directly.
    SurfaceInteraction si = scene.intersect(ray);
    S L(0.f);
    int emitter = scene.emitter_at(si);
    if (emitter >= 0 && !cfg.hide_emitters) L += emitter_eval<S>(ctx, scene.emitters[emitter], si);
    if (!si.valid) return L;

    // With n samples of each kind (or of one kind alone): n paths of two vertices from si,
    // path_li's, each of throughput 1/n.
    if (std::optional<IntegratorSettings> sub = path_settings(cfg)) {
        PathState<S> path;
        path.L = L;
        for (int i = 0; i < sub->sub_paths; ++i) {
            path = PathState<S>{path.L, S(1.f / float(sub->sub_paths))};
            Ray next;
            if (!path_vertex(ctx, *sub, 0, si, sampler, path, next)) continue;
            int e;
            SurfaceInteraction hit = scene.intersect_emitter(next, &e);
            if (e >= 0)
                path.L += emission_found(ctx, scene.emitters[e], hit, path.beta, path.prev_delta, path.prev_pdf,
                                         path.prev_p);
        }
        return path.L;
    }
    int bsdf_index = scene.bsdf_at(si);
    const BSDF &bsdf = scene.bsdfs[bsdf_index];
    float n_e = float(cfg.emitter_samples), n_b = float(cfg.bsdf_samples);
    float frac_e = n_e / (n_e + n_b), frac_b = n_b / (n_e + n_b);

    // Sample the emitters, MIS-weighted against BSDF sampling.
    if (bsdf.smooth()) {
        for (int i = 0; i < cfg.emitter_samples; ++i) {
            auto es = emitter_sample<S>(ctx, si.p, sampler.next_2d());
            if (!es || is_null(es->weight)) continue;
            BSDFEval<S> f = bsdf_eval_for(bsdf, ctx, bsdf_index, si, *es);
            if (is_null(f.value) || scene.occluded(shadow_ray(si, *es))) continue;
            float w = es->delta ? 1.f : mis_weight(es->pdf * frac_e, f.pdf * frac_b);
            L += f.value * es->weight * real_t<S>(w / n_e);
        }
    }

    // Sample the BSDF and add the emission found, MIS-weighted against emitter sampling.
    for (int i = 0; i < cfg.bsdf_samples; ++i) {
        float u1 = sampler.next_1d();
        Vec2 u2 = sampler.next_2d();
        auto bs = bsdf_sample<S>(bsdf, ctx, bsdf_index, si, u1, u2);
        if (!bs) continue;
        Ray next = si.spawn_ray(si.to_world(bs->wo));
        int e;
        SurfaceInteraction hit = scene.intersect_emitter(next, &e);
        if (e < 0) continue;
        const Emitter &em = scene.emitters[e];
        float em_pdf = bs->delta ? 0.f : emitter_pdf(ctx, em, si.p, hit);
        float w = mis_weight(bs->pdf * frac_b, em_pdf * frac_e);
        L += bs->weight * emitter_eval<S>(ctx, em, hit) * real_t<S>(w / n_b);
    }
    return L;
}

template <typename S>
S li(const RenderContext<S> &ctx, const IntegratorSettings &cfg, const Ray &ray, Sampler &sampler) {
    return cfg.type == IntegratorType::Path ? path_li(ctx, cfg, ray, sampler)
                                            : direct_li(ctx, cfg, ray, sampler);
}

}  // namespace rbpt
