#include "scene.h"

#include <map>
#include <memory>
#include <mutex>
#include <tuple>

namespace rbpt {

void Scene::build() {
    geometry.prepare();
    bvh.build(geometry);
}

namespace {

/// Process-wide cache of roughplastic tables: computing one costs a few hundred
/// milliseconds, and their inputs change only when a roughness is edited.
const RoughPlasticTables *cached_tables(MicrofacetType type, float alpha, float eta) {
    static std::mutex mutex;
    static std::map<std::tuple<int, float, float>, std::unique_ptr<RoughPlasticTables>> cache;
    std::lock_guard<std::mutex> lock(mutex);
    auto key = std::make_tuple(int(type), alpha, eta);
    auto it = cache.find(key);
    if (it != cache.end()) return it->second.get();
    auto tables = std::make_unique<RoughPlasticTables>();
    tables->compute(type, alpha, eta);
    return cache.emplace(key, std::move(tables)).first->second.get();
}

}  // namespace

std::vector<BSDFState> prepare_bsdfs(const Scene &scene, const std::vector<float> &alphas,
                                     const std::vector<float> &diffuse_means,
                                     const std::vector<float> &specular_means) {
    std::vector<BSDFState> state(scene.bsdfs.size());
    for (size_t i = 0; i < scene.bsdfs.size(); ++i) {
        const BSDF &b = scene.bsdfs[i];
        if (b.type != BSDFType::RoughPlastic) continue;
        state[i].tables = cached_tables(b.distribution, alphas[i], b.eta);
        float d = diffuse_means[i], s = specular_means[i];
        state[i].specular_sampling_weight = d + s > 0.f ? s / (d + s) : 0.5f;
    }
    return state;
}

}  // namespace rbpt
