// The scene: geometry and its BVH, materials, emitters, textures and the registry of
// parameters, plus the per-render context that binds parameter values of a number type.
#pragma once

#include <string>
#include <vector>

#include "bsdfs.h"
#include "bvh.h"
#include "emitters.h"
#include "params.h"
#include "shapes.h"
#include "textures.h"

namespace rbpt {

struct ParamInfo {
    std::string name;  ///< Mitsuba traverse key, for error messages
    int64_t numel = 0;
};

/// Rays traced by the calling thread (statistics only: thread-local, no locking).
inline thread_local uint64_t rays_traced = 0;

class Scene {
public:
    Geometry geometry;
    BVH bvh;
    /// The tree of shadow rays, when it differs from bvh: without the triangles no shadow
    /// ray can meet (shadow_blockers(): a room's walls). Only in scenes without an emitter
    /// at infinity, whose shadow rays all end at a point of the scene.
    BVH shadow_bvh;
    bool shadow_culled = false;
    uint32_t shadow_primitives = 0;  ///< the primitives shadow rays are tested against
    std::vector<BSDF> bsdfs;
    std::vector<Emitter> emitters;
    std::vector<Texture> textures;
    std::vector<ParamInfo> params;
    int environment = -1;  ///< index of the constant emitter, if any

    /// Build acceleration structures and sampling tables; call once after adding everything.
    void build();
    /// (Re)build shadow_bvh; without `cull`, shadow rays take bvh (for tests).
    void build_shadow_tree(bool cull);

    SurfaceInteraction intersect(const Ray &ray) const {
        ++rays_traced;
        Hit hit;
        bvh.intersect(ray, &hit);
        return geometry.interaction(ray, hit);
    }
    /// For a ray whose hit matters only as a light source: sets `emitter` to the emitter it
    /// finds (its surface's, or the environment's when it escapes; -1 if none) and returns
    /// the interaction only then (else an invalid one). Returned by value like intersect():
    /// assigning a returned interaction to an existing one would copy it through the stack.
    SurfaceInteraction intersect_emitter(const Ray &ray, int *emitter) const {
        ++rays_traced;
        Hit hit;
        bvh.intersect(ray, &hit);
        return emitter_interaction(ray, hit, emitter);
    }
    /// intersect_emitter() for the hit `hit` of `ray`, found already.
    SurfaceInteraction emitter_interaction(const Ray &ray, const Hit &hit, int *emitter) const {
        *emitter = hit.valid() ? geometry.shapes[geometry.shape_of(hit.prim)].emitter : environment;
        if (*emitter < 0) return SurfaceInteraction();
        return geometry.interaction(ray, hit);
    }
    /// The tree shadow rays (rays towards an emitter's sample) are tested against.
    const BVH &shadow_tree() const { return shadow_culled ? shadow_bvh : bvh; }
    /// Whether a shadow ray is blocked.
    bool occluded(const Ray &ray) const {
        ++rays_traced;
        return shadow_tree().occluded(ray);
    }

    /// Emitter attached to the surface hit, or the environment when the ray escaped.
    int emitter_at(const SurfaceInteraction &si) const {
        return si.valid ? geometry.shapes[si.shape].emitter : environment;
    }
    int bsdf_at(const SurfaceInteraction &si) const { return geometry.shapes[si.shape].bsdf; }
};

/// Derived per-BSDF data for the current parameter values (sampling weights, roughplastic's
/// tables, which are cached process-wide by (distribution, alpha, eta)).
std::vector<BSDFState> prepare_bsdfs(const Scene &scene, const std::vector<float> &alphas,
                                     const std::vector<float> &diffuse_means,
                                     const std::vector<float> &specular_means,
                                     const std::vector<bool> &alpha_derivatives);

/// Everything a render reads: the scene and the parameter values of number type S.
template <typename S>
struct RenderContext {
    const Scene &scene;
    Params<S> params;
    const Texture *textures = nullptr;
    std::vector<BSDFState> bsdf_state;

    RenderContext(const Scene &scene, Params<S> params_) : scene(scene), params(std::move(params_)) {
        textures = scene.textures.data();
        size_t n = scene.bsdfs.size();
        std::vector<float> alphas(n, 0.1f), dmeans(n, 0.5f), smeans(n, 1.f);
        std::vector<bool> derivatives(n, false);
        for (size_t i = 0; i < n; ++i) {
            const BSDF &b = scene.bsdfs[i];
            if (b.type != BSDFType::RoughPlastic) continue;
            alphas[i] = detach_real(params.real(b.alpha));
            dmeans[i] = texture_mean(b.reflectance);
            smeans[i] = texture_mean(b.specular_reflectance);
            derivatives[i] = params.differentiable(b.alpha);
        }
        bsdf_state = prepare_bsdfs(scene, alphas, dmeans, smeans, derivatives);
    }

private:
    /// Detached mean of a material input (a checkerboard's: the mean of its two colours,
    /// as Mitsuba's Checkerboard::mean).
    float texture_mean(const TextureRef &t) const {
        if (t.texture < 0) return params.mean(t.param);
        const Texture &tex = scene.textures[t.texture];
        if (tex.type == TextureType::Checkerboard)
            return 0.5f * (params.mean(tex.checkerboard.color0) + params.mean(tex.checkerboard.color1));
        return params.mean(tex.bitmap.param);
    }
};

}  // namespace rbpt
