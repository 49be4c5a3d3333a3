// The `path` integrator for plain float renders, run over a batch of paths at a time so that
// the shading of many paths runs in SIMD lanes (a wavefront). Each bounce is a few stages over
// the batch, its live paths kept packed at the front of structure-of-arrays columns:
//   trace       one path at a time: the ray cast, the surface interaction, the emission the
//               ray found (Scene::intersect and the integrator's own emission code);
//   vertex      in SIMD lanes: an emitter sample, the BSDF towards it with its MIS weight,
//               the BSDF sample, Russian roulette and the next ray;
//   shadow      one path at a time: the shadow rays, adding the emission they see;
//   compact     the paths that ended hand their radiance back; the rest move to the front.
// It computes what path_li computes, operation for operation, in the same order (with
// -ffp-contract=off a vectorised loop performs the same IEEE operations as a scalar one), so
// images are bitwise identical to the scalar integrator's (tests/test_wavefront.py). The
// vector stage shades diffuse BSDFs (`twosided` or not) towards area emitters on meshes of at
// most 8 triangles; their reflectance (a constant, a texture or a mesh attribute) is looked up
// in the trace stage. Vertices of other BSDFs are shaded by path_vertex(), path_li's own
// code, in the trace stage. It runs for the `path` integrator with the `independent` sampler,
// when every emitter is such a mesh and some BSDF is diffuse; other scenes, and the autodiff
// number types, take path_li.
#pragma once

#include <optional>
#include <vector>

#include "camera.h"
#include "integrator.h"

namespace rbpt {

/// Paths per batch: the SIMD loops run over this many lanes at most.
constexpr int WavefrontBatch = 256;

/// The scene data the vector stages gather from, flattened per BSDF and per emitter.
struct WavefrontScene {
    struct Material {
        int lanes;     ///< 1: a diffuse BSDF, shaded in SIMD lanes; 0: by path_vertex
        int twosided;  // (ints, not bools: the vector loop gathers them)
    };
    struct Light {
        Color3f radiance;
        int has_normals, flip_normals;  // (ints, not bools: the vector loop gathers them)
        float area;
    };
    std::vector<Material> materials;  ///< per Scene::bsdfs
    std::vector<Light> lights;        ///< per Scene::emitters
    // Each light's mesh (at most 8 triangles) in flat arrays, which the vector loop gathers
    // from with one base address each: light e's triangle t is entry 8 e + t.
    std::vector<float> cdf;      ///< Shape::tri_cdf, 9 per light, padded with 2 (no u reaches it)
    std::vector<Vec3> vertices;  ///< 3 per triangle
    std::vector<Vec3> normals;   ///< vertex normals, 3 per triangle (zero without them)
    std::vector<Vec3> face_normals;  ///< Triangle::n, 1 per triangle
};

/// The flattened scene if render_fwd may trace `ctx`'s paths with trace_wavefront(), else
/// nothing: always nothing in builds without AVX2, whose vector stage stays scalar. (The
/// environment variable TORCH_RBPT_WAVEFRONT=0 turns it off, for comparisons.)
std::optional<WavefrontScene> wavefront_scene(const RenderContext<RGB<float>> &ctx,
                                              const IntegratorSettings &cfg, const Camera &camera);

/// One sample to trace: its pixel, the pixel's seeds and its index among the pixel's samples.
struct WavefrontSample {
    int px, py;
    PixelSeed seed;
    int s;
};

/// Trace `n` <= WavefrontBatch samples: their film positions into pos[i] and radiance into
/// L[i], as the scalar loop (Sampler, Camera::sample_position, sample_ray, path_li) would.
void trace_wavefront(const RenderContext<RGB<float>> &ctx, const WavefrontScene &ws,
                     const IntegratorSettings &cfg, const Camera &camera,
                     const WavefrontSample *samples, int n, Vec2 *pos, RGB<float> *L);

}  // namespace rbpt
