// Emitters with Mitsuba 3's semantics: one-sided `area` lights attached to shapes, `point`
// lights and the `constant` environment. Emitter sampling picks one emitter uniformly (as
// Mitsuba does) and then a direction towards it; visibility is tested by the caller.
// A new emitter type is an EmitterType and a case in each function below: the wavefront
// samples it with emitter_sample() one lane at a time (wavefront.cpp's aside_emitter_stage)
// and adds the emission rays find with emitter_eval() and emitter_pdf(), as path_li does, so
// it needs no code there. An escaped ray's interaction is invalid and its `wi` is -ray.d in
// world space (Mitsuba's convention), so an environment whose radiance depends on the
// direction, as an envmap's, reads it there in emitter_eval() and emitter_pdf().
#pragma once

#include <optional>

#include "shapes.h"
#include "warp.h"

namespace rbpt {

enum class EmitterType { Area, Point, Constant };

struct Emitter {
    EmitterType type = EmitterType::Area;
    int radiance = -1;  ///< parameter: `radiance` (area, constant) or `intensity` (point)
    int shape = -1;     ///< area: the shape it is attached to
    Vec3 position;      ///< point
};

/// A sampled emitter direction from a reference point: `weight` = emitted radiance / pdf,
/// with the uniform emitter-selection probability included in `pdf`.
template <typename S>
struct EmitterSample {
    Vec3 d;
    float dist = Infinity;  ///< distance to the sampled point (Infinity for the environment)
    Vec3 p;
    float pdf = 0.f;
    bool delta = false;
    S weight;
};

/// Radiance leaving an emitter towards a ray that hit it (`si` valid) or escaped (`si`
/// invalid: the environment, seen along -si.wi, world space). Area lights emit on the front
/// side only.
template <typename S, typename Ctx>
S emitter_eval(const Ctx &ctx, const Emitter &e, const SurfaceInteraction &si) {
    if (e.type == EmitterType::Area && si.wi.z <= 0.f) return S(0.f);
    return ctx.params.spectrum(e.radiance);
}

/// Sample a direction towards one emitter chosen uniformly; u.x is reused after selection.
template <typename S, typename Ctx>
RBPT_INLINE std::optional<EmitterSample<S>> emitter_sample(const Ctx &ctx, const Vec3 &ref,
                                                           Vec2 u) {
    const auto &emitters = ctx.scene.emitters;
    int n = int(emitters.size());
    if (n == 0) return std::nullopt;
    int index = std::min(int(u.x * float(n)), n - 1);
    u.x = std::min(u.x * float(n) - float(index), 0.99999994f);
    const Emitter &e = emitters[index];
    EmitterSample<S> es;
    switch (e.type) {
        case EmitterType::Area: {
            DirectionSample ds = ctx.scene.geometry.sample_direction(e.shape, ref, u);
            if (!(ds.pdf > 0.f) || dot(ds.d, ds.n) >= 0.f) return std::nullopt;
            es.d = ds.d;
            es.dist = ds.dist;
            es.p = ds.p;
            es.pdf = ds.pdf / float(n);
            break;
        }
        case EmitterType::Point: {
            Vec3 d = e.position - ref;
            float dist2 = squared_norm(d);
            es.dist = std::sqrt(dist2);
            es.d = d / es.dist;
            es.p = e.position;
            es.delta = true;
            // A delta "density": weight = intensity / dist^2 / selection probability.
            es.pdf = 1.f / float(n);
            es.weight = ctx.params.spectrum(e.radiance) * real_t<S>(float(n) / dist2);
            return es;
        }
        case EmitterType::Constant: {
            es.d = warp::square_to_uniform_sphere(u);
            es.pdf = InvFourPi / float(n);
            break;
        }
    }
    es.weight = ctx.params.spectrum(e.radiance) * real_t<S>(1.f / es.pdf);
    return es;
}

/// Solid-angle density with which emitter_sample() produces the direction that reached
/// emitter `e` at `hit` from `ref` (the hit is invalid for the environment: the direction is
/// -hit.wi, world space).
template <typename Ctx>
float emitter_pdf(const Ctx &ctx, const Emitter &e, const Vec3 &ref, const SurfaceInteraction &hit) {
    float select = 1.f / float(ctx.scene.emitters.size());
    switch (e.type) {
        case EmitterType::Area:
            return select * ctx.scene.geometry.pdf_direction(e.shape, ref, hit.p, hit.n);
        case EmitterType::Constant: return select * InvFourPi;
        case EmitterType::Point: return 0.f;
    }
    return 0.f;
}

}  // namespace rbpt
