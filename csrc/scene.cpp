#include "scene.h"

#include <map>
#include <memory>
#include <mutex>
#include <tuple>

namespace rbpt {

void Scene::build() {
    for (Shape &shape : geometry.shapes)
        shape.needs_uv = shape.bsdf < 0 || bsdfs[shape.bsdf].reads_uv();
    geometry.prepare();
    bvh.build(geometry);
    build_shadow_tree(true);
}

void Scene::build_shadow_tree(bool cull) {
    // Where no emitter lies at infinity, every shadow ray ends at a point of the scene (on an
    // area light, or a point light's position), and the triangles with the whole scene on
    // one side of their plane cannot block it.
    shadow_culled = false;
    shadow_bvh = BVH();
    shadow_primitives = geometry.primitive_count();
    if (!cull) return;
    bool at_infinity = false;
    std::vector<Vec3> points;
    for (const Emitter &e : emitters) {
        at_infinity = at_infinity || e.type == EmitterType::Constant;
        if (e.type == EmitterType::Point) points.push_back(e.position);
    }
    if (at_infinity) return;
    std::vector<uint32_t> blockers = shadow_blockers(geometry, points);
    if (blockers.size() == geometry.primitive_count()) return;
    shadow_bvh.build(geometry, blockers);
    shadow_culled = true;
    shadow_primitives = uint32_t(blockers.size());
}

namespace {

/// Roughplastic tables for (type, alpha, eta), or with `derivative` their derivative with
/// respect to alpha by central differences of the (smooth) quadratures. Cached process-wide:
/// computing one costs tens of milliseconds (about 40 for Beckmann, 30 for GGX, on one core),
/// and their inputs change only when a roughness is edited. Computed outside the lock; a
/// racing duplicate is simply dropped.
const RoughPlasticTables *cached_tables(MicrofacetType type, float alpha, float eta,
                                        bool derivative = false) {
    static std::mutex mutex;
    static std::map<std::tuple<int, float, float, bool>, std::unique_ptr<RoughPlasticTables>> cache;
    auto key = std::make_tuple(int(type), alpha, eta, derivative);
    {
        std::lock_guard<std::mutex> lock(mutex);
        auto it = cache.find(key);
        if (it != cache.end()) return it->second.get();
    }
    std::unique_ptr<RoughPlasticTables> tables;
    if (derivative) {
        float h = 1e-3f * alpha;
        const RoughPlasticTables *hi = cached_tables(type, alpha + h, eta);
        const RoughPlasticTables *lo = cached_tables(type, alpha - h, eta);
        tables = std::make_unique<RoughPlasticTables>(*hi);
        float inv = 1.f / float(double(alpha + h) - double(alpha - h));
        for (int i = 0; i < RoughPlasticTables::Resolution; ++i)
            tables->external_transmittance[i] =
                (hi->external_transmittance[i] - lo->external_transmittance[i]) * inv;
        tables->internal_reflectance = (hi->internal_reflectance - lo->internal_reflectance) * inv;
    } else {
        tables = std::make_unique<RoughPlasticTables>();
        tables->compute(type, alpha, eta);
    }
    std::lock_guard<std::mutex> lock(mutex);
    return cache.emplace(key, std::move(tables)).first->second.get();
}

}  // namespace

std::vector<BSDFState> prepare_bsdfs(const Scene &scene, const std::vector<float> &alphas,
                                     const std::vector<float> &diffuse_means,
                                     const std::vector<float> &specular_means,
                                     const std::vector<bool> &alpha_derivatives) {
    std::vector<BSDFState> state(scene.bsdfs.size());
    for (size_t i = 0; i < scene.bsdfs.size(); ++i) {
        const BSDF &b = scene.bsdfs[i];
        if (b.type != BSDFType::RoughPlastic) continue;
        state[i].tables = cached_tables(b.distribution, alphas[i], b.eta);
        if (alpha_derivatives[i]) state[i].dtables = cached_tables(b.distribution, alphas[i], b.eta, true);
        float d = diffuse_means[i], s = specular_means[i];
        state[i].specular_sampling_weight = d + s > 0.f ? s / (d + s) : 0.5f;
    }
    return state;
}

}  // namespace rbpt
