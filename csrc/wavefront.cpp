#include "wavefront.h"

#include <climits>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <type_traits>

namespace rbpt {

namespace {

/// The inputs the shade stage looks up for a vertex of `lane`: a (diffuse and roughplastic
/// `reflectance`, the conductors' and the dielectric's specular reflectance) and t, or none
/// (the dielectric's transmittance, roughplastic's specular reflectance).
struct ShadeInputs {
    const TextureRef *a, *t;
};
ShadeInputs shade_inputs(const BSDF &b, WavefrontScene::Lane lane) {
    using L = WavefrontScene::Lane;
    const bool base = lane == L::Diffuse || lane == L::RoughPlastic;
    const TextureRef *t = lane == L::Glass ? &b.specular_transmittance
                        : lane == L::RoughPlastic ? &b.specular_reflectance : nullptr;
    return {base ? &b.reflectance : &b.specular_reflectance, t};
}

/// The bitmap texture input `r` reads where the shade stage can look it up in lanes
/// (bitmap_stage: bilinear, one or three channels, fewer than 2^31 values), else null.
const Texture *lane_bitmap(const Scene &scene, const TextureRef *r) {
    if (!r || r->texture < 0 || r->attribute >= 0) return nullptr;
    const Texture &t = scene.textures[size_t(r->texture)];
    const Bitmap &bm = t.bitmap;
    const bool fits = int64_t(bm.width) * bm.height * bm.channels < (int64_t(1) << 31);
    return t.type == TextureType::Bitmap && !bm.nearest && (bm.channels == 1 || bm.channels == 3) && fits ? &t : nullptr;
}

}  // namespace

void exclude_watched_inputs(WavefrontScene &ws, const Scene &scene, const char *watched) {
    std::vector<char> excluded(scene.bsdfs.size(), 0), recorded(scene.bsdfs.size(), 0);
    for (size_t i = 0; i < scene.bsdfs.size(); ++i) {
        const auto lane = WavefrontScene::Lane(ws.materials[i].lane);
        const ShadeInputs in = shade_inputs(scene.bsdfs[i], lane);
        for (const TextureRef *r : {in.a, in.t})
            if (r && r->param >= 0 && watched[size_t(r->param)]) excluded[i] = 1;
        const Texture *t = lane_bitmap(scene, in.a);
        if (t && watched[size_t(t->bitmap.param)]) (linear_in_inputs(lane) ? recorded : excluded)[i] = 1;
    }
    for (size_t p = 0; p < ws.prim_quick.size(); ++p)
        if (excluded[size_t(ws.prim_material[p])]) ws.prim_quick[p] = 0;
    auto gone = [&](const WavefrontScene::BitmapLookup &bm) { return excluded[size_t(bm.material)] != 0; };
    ws.bitmaps.erase(std::remove_if(ws.bitmaps.begin(), ws.bitmaps.end(), gone), ws.bitmaps.end());
    for (WavefrontScene::BitmapLookup &bm : ws.bitmaps) {
        bm.record = recorded[size_t(bm.material)] != 0;
        bm.lane = ws.materials[size_t(bm.material)].lane;
    }
    ws.quick_watched = watched;
}

std::optional<WavefrontScene> wavefront_scene(const RenderContext<RGB<float>> &ctx,
                                              const IntegratorSettings &cfg, const Camera &camera) {
#ifndef __AVX2__
    // Without AVX2's gathers GCC leaves the vector stage scalar, and the batch's bookkeeping
    // makes the wavefront slower than path_li (portable build: 1.05-1.08x).
    return std::nullopt;
#endif
    const char *env = std::getenv("TORCH_RBPT_WAVEFRONT");
    if (env && std::strcmp(env, "0") == 0) return std::nullopt;
    // (`aside`: every light the vector stage does not sample itself is sampled by
    // aside_emitter_stage, as a new emitter type is, none by lane_emitter_stage.)
    const bool lane_emitters = !(env && std::strcmp(env, "aside") == 0);
    const Scene &scene = ctx.scene;
    std::optional<IntegratorSettings> path = path_settings(cfg);
    if (!path || path->max_depth == 0) return std::nullopt;
    if (scene.emitters.empty()) return std::nullopt;
    WavefrontScene ws;
    ws.predrawn = camera.sampler.type != SamplerType::Independent;
    bool any_lanes = false;
    for (size_t i = 0; i < scene.bsdfs.size(); ++i) {
        using L = WavefrontScene::Lane;
        const BSDF &b = scene.bsdfs[i];
        const BSDFState &state = ctx.bsdf_state[i];
        // Rough BSDFs in lanes, GGX and Beckmann (whose visible normals, a Newton solve, are
        // sampled before the vector stage), and no tables' derivatives (float renders have
        // none).
        L lane = b.type == BSDFType::Diffuse ? L::Diffuse
               : b.type == BSDFType::Conductor ? L::Mirror
               : b.type == BSDFType::Dielectric ? L::Glass
               : b.type == BSDFType::RoughConductor ? L::RoughMirror
               : b.type == BSDFType::RoughPlastic && state.tables && !state.dtables ? L::RoughPlastic
               : L::Aside;
        any_lanes = any_lanes || lane != L::Aside;
        ws.any_delta = ws.any_delta || lane == L::Mirror || lane == L::Glass;
        ws.any_rough = ws.any_rough || lane == L::RoughMirror || lane == L::RoughPlastic;
        WavefrontScene::Material m{lane, b.twosided, b.eta, 0.f, b.nonlinear, 0.f, 0.f, 0,
                                   lane == L::Diffuse ? 1.f : 0.f, lane == L::Mirror ? 1.f : 0.f,
                                   lane == L::RoughMirror || lane == L::RoughPlastic ? 1.f : 0.f,
                                   lane == L::RoughPlastic ? 1.f : 0.f};
        if (lane == L::RoughMirror || lane == L::RoughPlastic) {
            m.alpha = float(ctx.params.data[b.alpha][0]);
            m.beckmann = b.distribution == MicrofacetType::Beckmann ? 1.f : 0.f;
            ws.any_beckmann = ws.any_beckmann || m.beckmann != 0.f;
        }
        if (lane == L::RoughPlastic) {
            m.specular_sampling_weight = state.specular_sampling_weight;
            m.internal_reflectance = state.tables->internal_reflectance;
            m.table = int(ws.tables.size());
            ws.tables.insert(ws.tables.end(), state.tables->external_transmittance,
                             state.tables->external_transmittance + RoughPlasticTables::Resolution);
        }
        ws.materials.push_back(m);
    }
    if (ws.tables.empty()) ws.tables.assign(RoughPlasticTables::Resolution, 0.f);  // (gathered from in any case)
    // Whether the vector stage samples an emitter itself: the `constant` environment, an area
    // light on a sphere or on a mesh of at most 8 triangles (Light::aside).
    auto in_lanes = [&scene](const Emitter &e) {
        if (e.type == EmitterType::Constant) return true;
        if (e.type != EmitterType::Area) return false;
        const Shape &shape = scene.geometry.shapes[e.shape];
        return shape.kind == ShapeKind::Sphere ||
               (shape.kind == ShapeKind::Mesh && shape.tri_count > 0 && shape.tri_count <= 8);
    };
    if (!any_lanes) return std::nullopt;
    for (const WavefrontScene::Material &m : ws.materials)
        ws.any_ggx = ws.any_ggx || (m.rough != 0.f && m.beckmann == 0.f);
    // The shade stage's lookups in lanes: per material whether its inputs are constants, or
    // a bilinear bitmap (a) and a constant (t), and the constants' values (read without the
    // parameter log: the quick lookups run in renders without one, or whose log does not
    // watch them: exclude_watched_inputs()), and per primitive its material where it does not
    // emit.
    std::vector<int> quick(scene.bsdfs.size(), 0);
    for (size_t i = 0; i < scene.bsdfs.size(); ++i) {
        const ShadeInputs in = shade_inputs(scene.bsdfs[i], WavefrontScene::Lane(ws.materials[i].lane));
        auto constant = [](const TextureRef *r) { return !r || (r->texture < 0 && r->attribute < 0 && r->param >= 0); };
        const Texture *bitmap = lane_bitmap(scene, in.a);
        quick[i] = ws.materials[i].lane != WavefrontScene::Aside && (constant(in.a) || bitmap) && constant(in.t);
        auto value = [&](const TextureRef *r) {
            return Params<RGB<float>>::value_of(ctx.params.data[size_t(r->param)], ctx.params.numel[size_t(r->param)]);
        };
        WavefrontScene::Material &m = ws.materials[i];
        if (quick[i] && bitmap) {
            const Bitmap &bm = bitmap->bitmap;
            WavefrontScene::BitmapLookup lookup{int(i), bm.param, ctx.params.data[size_t(bm.param)], bm.width,
                                                bm.height, bm.channels, bm.wrap, bitmap->has_to_uv, {}};
            std::memcpy(lookup.to_uv, bitmap->to_uv, sizeof lookup.to_uv);
            ws.bitmaps.push_back(lookup);
        } else if (quick[i]) {
            RGB<float> va = value(in.a);
            m.ar = va[0], m.ag = va[1], m.ab = va[2];
        }
        if (quick[i] && in.t) {
            RGB<float> vt = value(in.t);
            m.tr = vt[0], m.tg = vt[1], m.tb = vt[2];
        }
    }
    const Geometry &geometry = scene.geometry;
    for (uint32_t p = 0; p < geometry.primitive_count(); ++p) {
        const Shape &shape = geometry.shapes[geometry.shape_of(p)];
        ws.prim_material.push_back(shape.bsdf);
        ws.prim_quick.push_back(shape.emitter < 0 && quick[size_t(shape.bsdf)]);
        ws.prim_emits.push_back(shape.emitter >= 0 ? 1 : 0);
    }
    ws.prim_emits.push_back(scene.environment >= 0 ? 1 : 0);
    for (const Triangle &tri : scene.geometry.triangles) {
        using F = WavefrontScene::ShapeFlag;
        const Shape &shape = scene.geometry.shapes[tri.shape];
        ws.triangle_flags.push_back((shape.has_normals ? F::HasNormals : 0) | (shape.flip_normals ? F::FlipNormals : 0) |
                                    (shape.needs_uv ? F::NeedsUV : 0) | (shape.has_uvs ? F::HasUVs : 0));
        ws.any_normals = ws.any_normals || shape.has_normals;
        ws.any_uv = ws.any_uv || shape.needs_uv;
    }
    for (uint32_t s : scene.geometry.analytic) {
        const Shape &shape = scene.geometry.shapes[s];
        bool sphere = shape.kind == ShapeKind::Sphere;
        ws.any_spheres = ws.any_spheres || sphere;
        ws.any_sphere_uv = ws.any_sphere_uv || (sphere && shape.needs_uv);
        ws.is_sphere.push_back(sphere);
        ws.sphere_uv.push_back(sphere && shape.needs_uv);
        ws.sphere_center.push_back(shape.center);
        ws.sphere_x.push_back(shape.local_x), ws.sphere_y.push_back(shape.local_y), ws.sphere_z.push_back(shape.local_z);
        ws.sphere_radius.push_back(shape.radius);
        ws.sphere_sign.push_back(shape.flip_normals ? -1.f : 1.f);
    }
    // The lights without a mesh (the environment, spheres, those sampled aside) get a unit
    // triangle in the flat arrays, which the vector stage gathers from and ignores.
    auto unit_triangle = [&ws]() {
        for (int i = 0; i < 9; ++i) ws.cdf.push_back(i == 0 ? 0.f : i == 1 ? 1.f : 2.f);
        const Vec3 p[3] = {Vec3{0.f, 0.f, 0.f}, Vec3{1.f, 0.f, 0.f}, Vec3{0.f, 1.f, 0.f}}, n[3];
        for (int t = 0; t < 8; ++t) ws.triangles.add(p, n, Vec3{0.f, 0.f, 1.f});
    };
    // Triangle t of a mesh light into light columns: its vertices, vertex normals (zeros
    // without them) and face normal.
    auto add_mesh_triangle = [&scene](WavefrontScene::TriangleColumns &columns, const Shape &shape, uint32_t t) {
        const Geometry &g = scene.geometry;
        const Triangle &tri = g.triangles[shape.tri_begin + t];
        Vec3 p[3], n[3];
        for (int j = 0; j < 3; ++j) {
            p[j] = g.positions[tri.v[j]];
            n[j] = shape.has_normals ? g.normals[tri.v[j]] : Vec3();
        }
        columns.add(p, n, tri.n);
    };
    for (const Emitter &e : scene.emitters) {
        WavefrontScene::Light light;
        light.radiance = ctx.params.spectrum(e.radiance);
        ws.radiance.insert(ws.radiance.end(), {light.radiance.v[0], light.radiance.v[1], light.radiance.v[2]});
        light.radiance_param = e.radiance;
        if (e.type == EmitterType::Constant) {
            ws.environment = true;
            light.environment = 1.f;
            ws.lights.push_back(light);
            unit_triangle();
            continue;
        }
        if (!in_lanes(e)) {
            ws.any_aside_lights = true;
            light.aside = 1.f;
            const Shape *mesh = e.type == EmitterType::Area ? &scene.geometry.shapes[e.shape] : nullptr;
            if (!lane_emitters) {
                ws.any_aside_stage_lights = true;
            } else if (mesh && mesh->kind == ShapeKind::Mesh && mesh->tri_count > 8) {
                ws.any_large_lights = true;
                light.large = 1;
                light.area = mesh->area;
                light.has_normals = mesh->has_normals;
                light.flip_normals = mesh->flip_normals;
                ws.any_large_normals = ws.any_large_normals || mesh->has_normals;
            } else if (mesh && (mesh->kind == ShapeKind::Disk || mesh->kind == ShapeKind::Cylinder)) {
                ws.any_analytic_lights = true;
                light.disk = mesh->kind == ShapeKind::Disk ? 1 : 0;
                light.cylinder = mesh->kind == ShapeKind::Cylinder ? 1 : 0;
                light.area = mesh->area;
                light.flip_normals = mesh->flip_normals;
            } else if (e.type == EmitterType::Point) {
                ws.any_point_lights = true;
                light.point = 1;
            } else {
                ws.any_aside_stage_lights = true;
            }
            ws.lights.push_back(light);
            unit_triangle();
            continue;
        }
        const Shape &shape = scene.geometry.shapes[e.shape];
        light.area = shape.area;
        if (shape.kind == ShapeKind::Sphere) {
            ws.any_sphere_lights = true;
            light.sphere = 1.f;
            light.cx = shape.center.x, light.cy = shape.center.y, light.cz = shape.center.z;
            light.radius = shape.radius;
            light.outside_radius2 = outside_radius2(shape);
            light.sign = shape.flip_normals ? -1.f : 1.f;
            ws.lights.push_back(light);
            unit_triangle();
            continue;
        }
        light.has_normals = shape.has_normals;
        light.flip_normals = shape.flip_normals;
        for (uint32_t i = 0; i < 9; ++i) ws.cdf.push_back(i <= shape.tri_count ? shape.tri_cdf[i] : 2.f);
        for (uint32_t t = 0; t < 8; ++t) add_mesh_triangle(ws.triangles, shape, std::min(t, shape.tri_count - 1));
        ws.lights.push_back(light);
        ws.any_mesh_lights = true;
    }
    // The disk and cylinder lights' frames, normals and sizes and the point lights' positions
    // (lane_emitter_stage), zeros for the other lights.
    for (int c = 0; c < 17; ++c) ws.light_frame[c].assign(ws.lights.size(), 0.f);
    for (size_t i = 0; i < ws.lights.size(); ++i) {
        WavefrontScene::Light &light = ws.lights[i];
        light.lanes = light.large + light.disk + light.cylinder + light.point != 0 ? 1 : 0;
        ws.any_lane_lights = ws.any_lane_lights || light.lanes;
        if (light.point) {
            for (int a = 0; a < 3; ++a) ws.light_frame[a][i] = scene.emitters[i].position[a];
        }
        if (!light.disk && !light.cylinder) continue;
        const Shape &shape = scene.geometry.shapes[scene.emitters[i].shape];
        const Vec3 frame[5] = {shape.center, shape.local_x, shape.local_y, shape.local_z, shape.normal};
        for (int v = 0; v < 5; ++v)
            for (int a = 0; a < 3; ++a) ws.light_frame[3 * v + a][i] = frame[v][a];
        ws.light_frame[15][i] = shape.radius;
        ws.light_frame[16][i] = shape.length;
    }
    // The large mesh lights' triangles and CDFs (lane_emitter_stage), after a unit triangle
    // and its CDF, which the other lights' entries point at (all lights' without large
    // mesh lights).
    if (ws.any_lane_lights) {
        const Geometry &g = scene.geometry;
        const Vec3 unit[3] = {Vec3{0.f, 0.f, 0.f}, Vec3{1.f, 0.f, 0.f}, Vec3{0.f, 1.f, 0.f}}, none[3];
        ws.large_cdf = {0.f, 1.f};
        ws.large_triangles.add(unit, none, Vec3{0.f, 0.f, 1.f});
        uint32_t most = 1;
        for (size_t i = 0; i < ws.lights.size(); ++i) {
            int count = 1, cdf_first = 0, first = 0;
            if (ws.lights[i].large) {
                const Shape &shape = g.shapes[scene.emitters[i].shape];
                count = int(shape.tri_count);
                cdf_first = int(ws.large_cdf.size());
                first = int(ws.large_triangles.face_normal[0].size());
                ws.large_cdf.insert(ws.large_cdf.end(), shape.tri_cdf.begin(), shape.tri_cdf.end());
                for (uint32_t t = 0; t < shape.tri_count; ++t) add_mesh_triangle(ws.large_triangles, shape, t);
                most = std::max(most, shape.tri_count);
            }
            ws.large_count.push_back(count);
            ws.large_cdf_first.push_back(cdf_first);
            ws.large_first.push_back(first);
        }
        while ((1u << ws.large_steps) < most) ++ws.large_steps;
    }
    // The emitting shapes' boxes, for the rays at their last vertex (trace_wavefront), unless
    // an escaped ray finds the environment or there are so many that testing their boxes
    // would cost about what tracing does.
    int emitting = 0;
    for (const Shape &shape : scene.geometry.shapes) emitting += shape.emitter >= 0 ? 1 : 0;
    ws.last_rays_reach = scene.environment < 0 && emitting <= WavefrontScene::MostEmitterBoxes;
    for (uint32_t s = 0; ws.last_rays_reach && s < scene.geometry.shapes.size(); ++s)
        if (scene.geometry.shapes[s].emitter >= 0) ws.emitter_boxes.add(scene.geometry, s);
    return ws;
}

namespace {

constexpr int B = WavefrontBatch;
static_assert(SamplerColumns::Capacity >= B, "a batch's samplers fit SamplerColumns");
/// The length of a Batch column: B entries and 16 more, unused, so that columns do not start
/// 4 kB apart (B floats are 1 kB), where a load from one column waits on a store to another
/// whose address has the same low 12 bits (4k aliasing). (Single thread, 256 px, 16 spp,
/// images bitwise: 36 of 46 alternations on six scenes faster, mostly by 0.5-1.5%: veach-mis
/// 12 of 13, cornell-box 9 of 13, the cbox 5 of 8, textured 4 of 4; x86-64-v3: cornell-box
/// and the cbox 3 of 4, veach-mis 2 of 4.)
constexpr int Column = B + 16;

/// The largest |d log f_c / d theta| of a roughplastic's Term record (WavefrontVertex, theta
/// its diffuse reflectance or roughness) that the lanes deposit; a sample with a larger one
/// takes the tape. Its deposit multiplies the path's later radiance L_c - L_before,c by it,
/// a difference of float sums whose rounding it magnifies as much (as a diffuse input's
/// quotient by rho, 1 / rho, does).
constexpr float MaxTermDlog = 1e4f;

/// The batch's paths, one column per quantity; live paths are packed into [0, n).
/// (Aligned to cache lines: so is each column, of Column entries, and so are the vector
/// loads.)
struct alignas(64) Batch {
    // The ray to trace next.
    float ox[Column], oy[Column], oz[Column], dx[Column], dy[Column], dz[Column], tmin[Column], tmax[Column];
    // The path: radiance, throughput, roulette throughput, the last BSDF sample's density and
    // whether it was a delta one, the last vertex, its stream.
    float Lr[Column], Lg[Column], Lb[Column], br[Column], bg[Column], bb[Column];
    float rr_r[Column], rr_g[Column], rr_b[Column];
    float eta[Column], prev_pdf[Column], prev_px[Column], prev_py[Column], prev_pz[Column];
    int prev_delta[Column];
    uint64_t state[Column], inc[Column];
    // The numbers of this vertex, drawn before the stages that take them (draw_stage): the
    // emitter sample's two, the BSDF sample's three, the roulette's.
    float pe0[Column], pe1[Column], pb1[Column], pb2x[Column], pb2y[Column], prr[Column];
    int seq[Column];    ///< the sample's index in the caller's arrays
    int depth[Column];  ///< the path's vertex count so far (path_li's `depth`)
    // The closest hit of this bounce's ray (Hit's fields).
    float ht[Column], hu[Column], hv[Column];
    uint32_t prim[Column];
    // The vertex there (SurfaceInteraction's fields).
    float px[Column], py[Column], pz[Column], ex[Column], ey[Column], ez[Column];
    float nx[Column], ny[Column], nz[Column];
    // The shading frame: s, t, n.
    float sx[Column], sy[Column], sz[Column], tx[Column], ty[Column], tz[Column];
    float fx[Column], fy[Column], fz[Column];
    float wix[Column], wiy[Column], wiz[Column], uvx[Column], uvy[Column];
    int done[Column];   ///< whether the interaction stage completed the interaction
    int shade[Column];  ///< whether the vertex stage shades it
    // The BSDF's inputs there (see the shade stage): a reflectance, and a second one, or a
    // transmittance.
    float ar[Column], ag[Column], ab[Column];
    float tr[Column], tg[Column], tb[Column];
    int mat[Column];
    int alive[Column];  ///< whether the path goes on after this bounce's BSDF sample and roulette
    // The emitter sample's shadow ray and what it adds if nothing blocks it.
    int shadow[Column];
    int light[Column];  ///< the emitter sampled
    float refracts[Column];  ///< 1 where the BSDF sample refracted (a dielectric's transmission), else 0
    int record_reflect[Column], record_refract[Column];  ///< a dielectric's WavefrontVertex entries, or -1
    /// The WavefrontVertex entries whose C_e the shadow stage fills in, or -1: a rough
    /// conductor's differentiated roughness, or a roughplastic's diffuse reflectance; and a
    /// roughplastic's roughness.
    int record_rough[Column], record_alpha[Column];
    // The rough BSDFs' directions, in the frame the vertex stage evaluates them in (twosided's
    // flip applied): towards the emitter sample (the vertex stage's), and the BSDF sample
    // (rough_samples()') with its density and its weight value / density.
    float nwx[Column], nwy[Column], nwz[Column], swx[Column], swy[Column], swz[Column];
    float rpdf[Column], rwr[Column], rwg[Column], rwb[Column];
    // A rough lane's emitter sample's density, and whether the sample stands before the
    // BSDF's test (rough_emitter_stage).
    float espdf[Column], sampled0[Column];
    float sox[Column], soy[Column], soz[Column], sdx[Column], sdy[Column], sdz[Column], stmax[Column];
    float cr[Column], cg[Column], cb[Column];
    // The emitter samples of lights sampled aside (aside_emitter_stage): direction, point,
    // density, weight, and whether it is a delta sample, a direction (to infinity) and a sample.
    float adx[Column], ady[Column], adz[Column], apx[Column], apy[Column], apz[Column];
    float apdf[Column], awr[Column], awg[Column], awb[Column];
    float adelta[Column], ainf[Column], aok[Column];
    // With one light (light_point_stage): the point on the light's mesh the emitter sample's
    // numbers give, its face normal and its interpolated vertex normal.
    float lpx[Column], lpy[Column], lpz[Column], lfx[Column], lfy[Column], lfz[Column];
    float lvx[Column], lvy[Column], lvz[Column];
};

/// c ? a : b, component by component (a ternary on whole vectors selects an address, which
/// the vectoriser cannot follow).
RBPT_INLINE Vec3 select(bool c, const Vec3 &a, const Vec3 &b) {
    return {c ? a.x : b.x, c ? a.y : b.y, c ? a.z : b.z};
}

/// next_float_up(v) where off > 0, next_float_down(v) where off < 0, v itself where off is
/// zero: SurfaceInteraction::offset_p's rounding, without branches.
RBPT_INLINE float round_away(float v, float off) {
    uint32_t bits;
    std::memcpy(&bits, &v, sizeof bits);
    uint32_t up = v == 0.f ? 1u : (v > 0.f ? bits + 1u : bits - 1u);
    up = v < Infinity ? up : bits;  // +inf and NaN stay
    uint32_t down = v == 0.f ? 0x80000001u : (v < 0.f ? bits + 1u : bits - 1u);
    down = v > -Infinity ? down : bits;  // -inf and NaN stay
    bits = off > 0.f ? up : (off < 0.f ? down : bits);
    std::memcpy(&v, &bits, sizeof v);
    return v;
}

/// SurfaceInteraction::offset_p for lane k.
RBPT_INLINE Vec3 offset_p(const Batch &b, int k, const Vec3 &d) {
    Vec3 n{b.nx[k], b.ny[k], b.nz[k]}, p{b.px[k], b.py[k], b.pz[k]};
    Vec3 offset = n * dot(vabs(n), Vec3{b.ex[k], b.ey[k], b.ez[k]});
    offset = offset * (dot(n, d) < 0.f ? -1.f : 1.f);  // (exact; see vertex_stage on selects)
    Vec3 o = p + offset;
    return {round_away(o.x, offset.x), round_away(o.y, offset.y), round_away(o.z, offset.z)};
}

/// f(std::bool_constant<flag>...) for run-time flags: picks the template instance of a
/// stage for a scene (f returns it).
template <typename F>
auto with_flags(F f) {
    return f();
}
template <typename F, typename... Rest>
auto with_flags(F f, bool first, Rest... rest) {
    return first ? with_flags([&](auto... later) { return f(std::true_type{}, later...); }, rest...)
                 : with_flags([&](auto... later) { return f(std::false_type{}, later...); }, rest...);
}

/// The next number of lane k's stream, as Sampler::uniform; the stream advances only where
/// `draw` holds.
RBPT_INLINE float next_1d(Batch &b, int k, bool draw) {
    uint64_t state = b.state[k];
    float u = uniform_float(pcg32_next(state, b.inc[k]));
    b.state[k] = draw ? state : b.state[k];
    return u;
}

/// Lane k's sampler: the independent sampler continuing its stream, or, with a sampler
/// other than `independent` (WavefrontScene::predrawn), the sampler `desc` continuing from
/// its sample's entry in `parts` (kept per sample, by the lane's seq, so that moving lanes
/// moves no more than the stream).
RBPT_INLINE Sampler load_sampler(const Batch &b, int k, const SamplerDesc &desc, const Sampler::Parts *parts) {
    return parts ? Sampler(desc, parts[b.seq[k]]) : Sampler::independent(b.state[k], b.inc[k]);
}

/// Store lane k's sampler (after load_sampler()).
RBPT_INLINE void store_sampler(Batch &b, int k, const Sampler &sampler, Sampler::Parts *parts) {
    b.state[k] = sampler.pcg_state(), b.inc[k] = sampler.pcg_inc();
    if (parts) parts[b.seq[k]] = sampler.parts();
}

// ---- The rough BSDFs in lanes: GGX's visible-normal sampling and roughplastic's tables
// (microfacet_D and smith_G1 are microfacet.h's float ones, the Fresnel term is bsdfs.h's own),
// written with selects where the scalar code returns early: the same operations as
// microfacet.h's and bsdfs.h's, so the same bits.

/// sample_visible_normal for GGX (VisibleNormalSampler's constructor, part_x, part_y and
/// normal).
RBPT_INLINE Vec3 ggx_visible_normal(float alpha, const Vec3 &wi, Vec2 u) {
    Vec3 w = normalize(Vec3{alpha * wi.x, alpha * wi.y, wi.z});
    float len2 = w.x * w.x + w.y * w.y;
    float inv_len = 1.f / std::sqrt(len2);
    Vec3 t1{len2 > 0.f ? (w.y * -1.f) * inv_len : 1.f, len2 > 0.f ? w.x * inv_len : 0.f,
            len2 > 0.f ? 0.f * inv_len : 0.f};
    Vec3 t2 = cross(w, t1);
    float s = 0.5f * (1.f + w.z);
    float r = std::sqrt(u.x);
    Vec2 cs = warp::cossin_2pi(u.y);
    float p1 = r * cs.x, p2 = r * cs.y;
    p2 = (1.f - s) * safe_sqrt(1.f - p1 * p1) + s * p2;
    Vec3 nh = t1 * p1 + t2 * p2 + w * safe_sqrt(1.f - p1 * p1 - p2 * p2);
    return normalize(Vec3{alpha * nh.x, alpha * nh.y, std::max(0.f, nh.z)});
}

/// RoughPlasticTables::transmittance of the table at `table`.
RBPT_INLINE float transmittance(const float *tables, int table, float cos_theta) {
    constexpr int N = RoughPlasticTables::Resolution;
    float x = (cos_theta > 0.f ? std::min(cos_theta, 1.f) : 0.f) * float(N - 1);
    int i = std::min(int(x), N - 2);
    float t = x - float(i);
    return tables[table + i] * (1.f - t) + tables[table + i + 1] * t;
}

/// RoughPlasticBSDF::specular_probability at incidence with transmittance t_i.
RBPT_INLINE float specular_probability(const WavefrontScene::Material &m, float t_i) {
    float ps = (1.f - t_i) * m.specular_sampling_weight;
    float pd = t_i * (1.f - m.specular_sampling_weight);
    return ps + pd > 0.f ? ps / (ps + pd) : 0.5f;
}

/// A rough lane's BSDF value (f |cos wo|) and density: RoughConductorBSDF::eval_pdf (with
/// specular reflectance a) where `plastic` is 0, RoughPlasticBSDF::eval_pdf (diffuse
/// reflectance a, specular reflectance s) where it is 1.
struct RoughEval {
    float r, g, b, pdf;
};
/// A rough BSDF sample's density (zero where wi is below the surface) and its weight value /
/// density, from the BSDF's evaluation towards it: rough_samples()' and, for the samples it
/// leaves unevaluated, finish_deferred_samples()', which must agree bit for bit.
struct RoughWeight {
    float pdf, r, g, b;
};
RBPT_INLINE RoughWeight sample_weight(const RoughEval &e, float wi_z) {
    return {wi_z > 0.f ? e.pdf : 0.f, e.r / e.pdf, e.g / e.pdf, e.b / e.pdf};
}
/// A Beckmann lane's microfacet terms towards wo: D(h) and G1 of wi and of wo.
struct MicrofacetTerms {
    float D, g_i, g;
};
RBPT_INLINE MicrofacetTerms beckmann_terms(float alpha, const Vec3 &wi, const Vec3 &wo) {
    Vec3 h = normalize(wi + wo);
    constexpr MicrofacetType Beckmann = MicrofacetType::Beckmann;
    return {microfacet_D<Beckmann>(alpha, h), smith_G1<Beckmann, true>(alpha, wi, h), smith_G1<Beckmann, true>(alpha, wo, h)};
}

/// A rough BSDF's value and density towards wo, with the microfacet terms Terms: GGX's
/// (Microfacet::GGX), Beckmann's (Microfacet::Beckmann), or `stored` (Microfacet::StoredOnly:
/// beckmann_sample_stage's, towards its sampled direction). Without Plastic (no lane of the
/// list is a roughplastic: RoughLanes::plastic) the conductor's alone.
enum class Microfacet { GGX, StoredOnly, Beckmann };
template <Microfacet Terms, bool Plastic>
RBPT_INLINE RoughEval rough_eval(const WavefrontScene::Material &m, const MicrofacetTerms &stored,
                                 const float *tables, const Vec3 &wi, const Vec3 &wo, const float a[3],
                                 const float s[3]) {
    float up = wi.z > 0.f ? 1.f : 0.f;
    up = wo.z > 0.f ? up : 0.f;
    Vec3 h = normalize(wi + wo);
    float D, g_i, g;
    if constexpr (Terms == Microfacet::Beckmann) {
        const MicrofacetTerms t = beckmann_terms(m.alpha, wi, wo);
        D = t.D, g_i = t.g_i, g = t.g;
    } else if constexpr (Terms == Microfacet::StoredOnly) {
        D = stored.D, g_i = stored.g_i, g = stored.g;
    } else {
        constexpr MicrofacetType GGX = MicrofacetType::GGX;
        D = microfacet_D<GGX>(m.alpha, h), g_i = smith_G1<GGX, true>(m.alpha, wi, h), g = smith_G1<GGX, true>(m.alpha, wo, h);
    }
    float l = D * g_i / (4.f * wi.z);
    // The conductor.
    float lg = l * g;
    float facing = dot(wi, h) > 0.f ? 1.f : 0.f;
    facing = dot(wo, h) > 0.f ? facing : 0.f;
    RoughEval e{a[0] * lg, a[1] * lg, a[2] * lg, facing != 0.f ? l : 0.f};
    if constexpr (Plastic) {
        // The plastic: its specular lobe, and the diffuse base seen through the rough interface.
        const float plastic = m.plastic;
        float cos_t, eta_it, eta_ti;
        float spec = fresnel_dielectric(dot(wi, h), m.eta, &cos_t, &eta_it, &eta_ti) * l * g;
        float t_i = transmittance(tables, m.table, wi.z), t_o = transmittance(tables, m.table, wo.z);
        float r_int = m.internal_reflectance;
        float base = t_i * t_o * (InvPi / (m.eta * m.eta) * wo.z);
        float d[3];
        for (int c = 0; c < 3; ++c) {
            float diff = m.nonlinear != 0 ? a[c] / (1.f - a[c] * r_int) : a[c] / (1.f - r_int);
            d[c] = s[c] * spec + diff * base;
        }
        float ps = specular_probability(m, t_i);
        float density = ps * l + (1.f - ps) * warp::square_to_cosine_hemisphere_pdf(wo);
        e.r = plastic != 0.f ? d[0] : e.r, e.g = plastic != 0.f ? d[1] : e.g, e.b = plastic != 0.f ? d[2] : e.b;
        e.pdf = plastic != 0.f ? density : e.pdf;
    }
    // Both: nothing unless wi and wo are above the surface.
    e.r = up != 0.f ? e.r : 0.f, e.g = up != 0.f ? e.g : 0.f, e.b = up != 0.f ? e.b : 0.f;
    e.pdf = up != 0.f ? e.pdf : 0.f;
    return e;
}

/// Lights' triangles (WavefrontScene::TriangleColumns) read as Vec3s: triangle t's vertex j,
/// its vertex normal, its face normal.
struct LightTriangles {
    const float *p[9], *n[9], *face[3];
    explicit LightTriangles(const WavefrontScene::TriangleColumns &c) {
        for (int i = 0; i < 9; ++i) p[i] = c.vertex[i].data(), n[i] = c.normal[i].data();
        for (int a = 0; a < 3; ++a) face[a] = c.face_normal[a].data();
    }
    RBPT_INLINE Vec3 vertex(int j, int t) const { return {p[3 * j][t], p[3 * j + 1][t], p[3 * j + 2][t]}; }
    RBPT_INLINE Vec3 normal(int j, int t) const { return {n[3 * j][t], n[3 * j + 1][t], n[3 * j + 2][t]}; }
    RBPT_INLINE Vec3 face_normal(int t) const { return {face[0][t], face[1][t], face[2][t]}; }
};

/// With one light: the point each lane's emitter sample's numbers (draw_stage's) give on the
/// light's mesh (its first Tris triangles; the rest are padding),
/// with its face normal and interpolated vertex normal, in a loop of their own. The light's
/// triangles are the same in every lane, so each lane's are picked from all of them by sums
/// of products with 1 or 0 (x * 1 + y * 0 is x for finite values, but that a zero's sign
/// can turn positive), not gathered: gathers of 21 floats per lane took 40% of vertex_stage
/// on the cbox, where GCC loads lanes one by one (cbox 245 -> 222 ms, cornell-box 394 -> 379,
/// two triangles each). Selects instead of the products made GCC load under their condition
/// (masked loads of one address, which it does not vectorise), and in vertex_stage's own
/// loop they stopped the vectoriser in other instances.
template <int Tris>
__attribute__((noinline)) void light_point_stage(Batch &b, int n, const WavefrontScene &ws) {
    const float *cdf = ws.cdf.data();  // (the first light's entries)
    const LightTriangles tris(ws.triangles);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        Vec2 u{b.pe0[k], b.pe1[k]};  // (draw_stage's)
        u.x = std::min(u.x, 0.99999994f);  // (emitter_sample's reuse of u.x, one light)
        // The triangle (vertex_stage's search: the CDF's entries at most u.x, whose padding
        // no u reaches) and u.x within it.
        float is[Tris], cdf_lo = 0.f, cdf_hi = 0.f;
        uint32_t local = 0;
        for (int i = 1; i < Tris; ++i) local += cdf[i] <= u.x;
#pragma GCC unroll 8
        for (int i = 0; i < Tris; ++i) {
            is[i] = local == uint32_t(i) ? 1.f : 0.f;
            cdf_lo = cdf_lo + is[i] * cdf[i], cdf_hi = cdf_hi + is[i] * cdf[i + 1];
        }
        float width = cdf_hi - cdf_lo;
        u.x = std::min(width > 0.f ? (u.x - cdf_lo) / width : 0.f, 0.99999994f);
        // Its point and normals.
        Vec2 bc = warp::square_to_uniform_triangle(u);
        float b0 = 1.f - bc.x - bc.y;
        Vec3 lp, face_n, ln;
#pragma GCC unroll 8
        for (int i = 0; i < Tris; ++i) {
            Vec3 p_i = tris.vertex(0, i) * b0 + tris.vertex(1, i) * bc.x + tris.vertex(2, i) * bc.y;
            Vec3 n_i = tris.normal(0, i) * b0 + tris.normal(1, i) * bc.x + tris.normal(2, i) * bc.y;
            lp = lp + p_i * is[i], ln = ln + n_i * is[i], face_n = face_n + tris.face_normal(i) * is[i];
        }
        Vec3 vn = normalize(ln);
        b.lpx[k] = lp.x, b.lpy[k] = lp.y, b.lpz[k] = lp.z;
        b.lfx[k] = face_n.x, b.lfy[k] = face_n.y, b.lfz[k] = face_n.z;
        b.lvx[k] = vn.x, b.lvy[k] = vn.y, b.lvz[k] = vn.z;
    }
}

/// The vector stage of a bounce for the lanes [0, n) marked `shade`: path_li from the emitter
/// sample to the roulette. It runs over all lanes, unmasked, and sets `alive` and `shadow`
/// only where it shades: the caller restores the lanes shaded aside, and the others have
/// ended. With OneLight (a scene of one emitter, the common case) the light's data is the
/// same in every lane: loads, not gathers. Delta: whether some lanes are mirrors or
/// dielectrics (which sample no emitter); Rough: whether some are rough, whose BSDF samples
/// the rough stages took before (this stage takes them from the sw*, rpdf and rw* columns) and whose
/// emitter samples rough_emitter_stage evaluates after (this stage evaluates them as a
/// diffuse BSDF's and keeps what that stage needs); NonMesh: whether some emitters have no
/// mesh (the `constant` environment, spheres: 1), or none has (2, with several lights); Shapes:
/// whether some of those are spheres or lights sampled aside (without, the environment alone:
/// an environment beside mesh lights skips the spheres' cones and the aside samples' columns);
/// Two: a scene of two lights (as one beside the environment), whose fields each lane selects
/// from the two instead of loading its own lane by lane.
/// The code of the BSDFs and emitters a scene does not have is left out.
template <bool OneLight, bool Delta, bool Rough, int NonMesh, bool Shapes = true, bool Two = false>
void vertex_stage(Batch &b, int n, const WavefrontScene &ws, const IntegratorSettings &cfg) {
    const WavefrontScene::Material *mats = ws.materials.data();
    const WavefrontScene::Light *lights = ws.lights.data();
    // (With one light, its fields are invariants of the loop: a load of one under a condition
    // would become a masked load of one address, which GCC does not vectorise.)
    const WavefrontScene::Light first = ws.lights[0];
    // (With Two, the second light's fields are loop invariants too.)
    const WavefrontScene::Light second = Two ? ws.lights[1] : first;
    const float *cdfs = ws.cdf.data();
    const LightTriangles tris(ws.triangles);
    const int n_lights = OneLight ? 1 : int(ws.lights.size());
    // Conditions are carried as float flags (1 or 0) narrowed by selects: GCC 12 cannot
    // vectorise the boolean selects it makes of && chains and of booleans combined with
    // values that were themselves selected.
    const int rr_depth = cfg.rr_depth;
    // Whether vertices sample an emitter, and whether that sample is MIS-weighted against the
    // BSDF's (IntegratorSettings::emitter_sampling and bsdf_sampling: `direct` with one alone).
    const float nee = cfg.emitter_sampling ? 1.f : 0.f, bsdf_mis = cfg.bsdf_sampling ? 1.f : 0.f;
    if constexpr (OneLight) {
        // (A light of at most 2 triangles, as a rectangle, picks from 2: its CDF is padded
        // from its fourth entry on. A light that is not a mesh takes none: the loop below
        // reads the columns, whatever earlier batches left there, and selects its own
        // sample over them.)
        if (ws.any_mesh_lights) (ws.cdf[3] > 1.f ? light_point_stage<2> : light_point_stage<8>)(b, n, ws);
    }
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const WavefrontScene::Material &m = mats[b.mat[k]];
        const float shade = b.shade[k] != 0 ? 1.f : 0.f;
        // The BSDF: diffuse or rough (which sample an emitter), a mirror or a dielectric.
        const float diffuse = Delta || Rough ? m.diffuse : 1.f;
        const float mirror = Delta ? m.mirror : 0.f;
        const float rough = Rough ? m.rough : 0.f;
        const float smooth = shade * (diffuse + rough) * nee;
        const float a[3] = {b.ar[k], b.ag[k], b.ab[k]}, s[3] = {b.tr[k], b.tg[k], b.tb[k]};
        Vec3 p{b.px[k], b.py[k], b.pz[k]};
        // The shading frame (its to_local and to_world written out: a Frame assigned in the
        // loop would become an array per lane, which stops the vectoriser).
        Vec3 fs{b.sx[k], b.sy[k], b.sz[k]}, ft{b.tx[k], b.ty[k], b.tz[k]}, fn{b.fx[k], b.fy[k], b.fz[k]};

        // Sample an emitter (emitter_sample: one chosen uniformly, u.x reused) and a point on
        // its mesh (Geometry::sample_direction), at diffuse vertices (BSDF::smooth), from
        // draw_stage's numbers.
        Vec2 u{b.pe0[k], b.pe1[k]};
        int index = OneLight ? 0 : std::min(int(u.x * float(n_lights)), n_lights - 1);
        u.x = std::min(u.x * float(n_lights) - float(index), 0.99999994f);
        const WavefrontScene::Light &light = OneLight || Two ? first : lights[index];
        // A field of the lane's light: with two lights selected from the two (loop invariants),
        // else loaded lane by lane (GCC gathers them with a load and an insert per lane: a fifth
        // of the spheres' vertex stage); its flags (1 or 0) by arithmetic, exact for them (a
        // comparison of a selected value stops GCC 12's vectoriser). (Macros: lambdas taking
        // a member pointer stopped it in the other instances for AVX2.)
#define RBPT_LIGHT(field) (Two ? (index != 0 ? second.field : first.field) : light.field)
#define RBPT_LIGHT_FLAG(field) (Two ? first.field + index * (second.field - first.field) : light.field)
        // (The environment's direction, and a sphere's point seen from inside it: uniform on
        // the sphere, from u as selection left it.)
        const Vec3 env_d = NonMesh ? warp::square_to_uniform_sphere(u) : Vec3();
        // A sphere seen from outside (Geometry::sample_direction): a direction in the cone it
        // subtends, the Taylor expansion for small cones, and the cone's density.
        Vec3 cone_d;
        float outside = 0.f, cone_pdf = 0.f;
        // Whether it is a light sampled aside (1 or 0).
        [[maybe_unused]] const float aside = NonMesh && Shapes ? RBPT_LIGHT_FLAG(aside) : 0.f;
        if constexpr (NonMesh && Shapes) {
            Vec3 dc = Vec3{RBPT_LIGHT(cx), RBPT_LIGHT(cy), RBPT_LIGHT(cz)} - p;
            float dc2 = squared_norm(dc);
            outside = dc2 > RBPT_LIGHT(outside_radius2) ? 1.f : 0.f;
            warp::SphereConeSample cone = warp::sample_sphere_cone(dc, dc2, RBPT_LIGHT(radius), u);
            cone_d = cone.n, cone_pdf = cone.pdf;
        }
        // (With one light, light_point_stage's point, assigned over triangle 0's, which the
        // compiler drops: a Vec3 declared and then assigned a gather's value, or a
        // conditional of Vec3s, stopped the vectoriser in the instances of several lights.
        // Without mesh lights, the first light's unit triangle, loaded, not gathered, and
        // ignored as the others were: veach-mis 101 -> 94 ms.)
        constexpr bool Meshes = NonMesh != 2;
        const int c = Meshes ? 9 * index : 0;  // the light's CDF in light_cdf
        uint32_t local = 0;
        for (int i = 1; !OneLight && Meshes && i < 8; ++i) local += cdfs[c + i] <= u.x;
        float width = cdfs[c + int(local) + 1] - cdfs[c + int(local)];
        u.x = std::min(width > 0.f ? (u.x - cdfs[c + int(local)]) / width : 0.f, 0.99999994f);
        const int t = Meshes ? 8 * index + int(local) : 0;  // the triangle, in the flat arrays
        Vec2 bc = warp::square_to_uniform_triangle(u);
        float b0 = 1.f - bc.x - bc.y;
        Vec3 lp = tris.vertex(0, t) * b0 + tris.vertex(1, t) * bc.x + tris.vertex(2, t) * bc.y;
        Vec3 face_n = tris.face_normal(t);
        Vec3 vn = normalize(tris.normal(0, t) * b0 + tris.normal(1, t) * bc.x + tris.normal(2, t) * bc.y);
        if constexpr (OneLight) {
            lp = Vec3{b.lpx[k], b.lpy[k], b.lpz[k]};
            face_n = Vec3{b.lfx[k], b.lfy[k], b.lfz[k]};
            vn = Vec3{b.lvx[k], b.lvy[k], b.lvz[k]};
        }
        Vec3 ln = select(RBPT_LIGHT_FLAG(has_normals), vn, face_n);
        ln = select(RBPT_LIGHT_FLAG(flip_normals), -ln, ln);
        if constexpr (NonMesh && Shapes) {
            // A sphere's point (its normal the direction from the centre, times the sign; seen
            // from inside, its density converts with the unsigned one, as a mesh's face normal).
            Vec3 sd = select(outside != 0.f, cone_d, env_d);
            const bool sphere = RBPT_LIGHT_FLAG(sphere) != 0.f;
            lp = select(sphere, Vec3{RBPT_LIGHT(cx), RBPT_LIGHT(cy), RBPT_LIGHT(cz)} + sd * RBPT_LIGHT(radius), lp);
            face_n = select(sphere, sd, face_n);
            ln = select(sphere, sd * RBPT_LIGHT(sign), ln);
        }
        Vec3 d = lp - p;
        float dist2 = squared_norm(d), dist = std::sqrt(dist2);
        d = d * (1.f / dist);
        float abs_cos = std::abs(dot(face_n, d));
        float area_pdf = dist2 / (RBPT_LIGHT(area) * abs_cos);
        float pdf = abs_cos > 0.f ? area_pdf : 0.f;
        if constexpr (NonMesh && Shapes) pdf = RBPT_LIGHT_FLAG(sphere) * outside != 0.f ? cone_pdf : pdf;  // (flags: 1 or 0)
        // A sample: emitter_sample's test pdf > 0 (sample_direction's pdf is zero at distance
        // zero) and d facing the light's front.
        float sampled = dist != 0.f ? smooth : 0.f;
        sampled = pdf > 0.f ? sampled : 0.f;
        sampled = dot(d, ln) < 0.f ? sampled : 0.f;
        // Whether the shadow ray is a direction's, to infinity (spawn_ray, not spawn_ray_to).
        float to_infinity = 0.f;
        if constexpr (NonMesh) {
            // The environment (emitter_sample's `constant`): a direction, always a sample.
            const float env = RBPT_LIGHT_FLAG(environment);
            d = select(env != 0.f, env_d, d);
            pdf = env != 0.f ? InvFourPi : pdf;
            sampled = env != 0.f ? smooth : sampled;
            to_infinity = env;
            if constexpr (Shapes) {
                // A light sampled aside: emitter_sample()'s sample (aside_emitter_stage).
                d = select(aside != 0.f, Vec3{b.adx[k], b.ady[k], b.adz[k]}, d);
                lp = select(aside != 0.f, Vec3{b.apx[k], b.apy[k], b.apz[k]}, lp);
                sampled = aside != 0.f ? b.aok[k] * smooth : sampled;  // (both 1 or 0)
                to_infinity = aside != 0.f ? b.ainf[k] : env;
            }
        }
        float es_pdf = pdf / float(n_lights);
        if constexpr (NonMesh && Shapes) es_pdf = aside != 0.f ? b.apdf[k] : es_pdf;
        float inv_pdf = 1.f / es_pdf;
        float ew_r = RBPT_LIGHT(radiance.v[0]) * inv_pdf, ew_g = RBPT_LIGHT(radiance.v[1]) * inv_pdf;
        float ew_b = RBPT_LIGHT(radiance.v[2]) * inv_pdf;
        // Not null (a float flag taken before the weight's selects: a comparison of selected
        // values stops the vectoriser).
        float lit = (ew_r != 0.f) | (ew_g != 0.f) | (ew_b != 0.f) ? 1.f : 0.f;
        if constexpr (NonMesh && Shapes) {
            const float aside_lit = (b.awr[k] != 0.f) | (b.awg[k] != 0.f) | (b.awb[k] != 0.f) ? 1.f : 0.f;
            lit = aside != 0.f ? aside_lit : lit;
            ew_r = aside != 0.f ? b.awr[k] : ew_r;
            ew_g = aside != 0.f ? b.awg[k] : ew_g;
            ew_b = aside != 0.f ? b.awb[k] : ew_b;
        }
        const Color3f ew{ew_r, ew_g, ew_b};
        sampled = lit != 0.f ? sampled : 0.f;

        // The BSDF towards it (bsdf_eval_pdf, with twosided's flip) and its MIS weight.
        Vec3 wi{b.wix[k], b.wiy[k], b.wiz[k]};
        Vec3 wo{dot(d, fs), dot(d, ft), dot(d, fn)};
        // The flip as a product with -1 (exact): a selected negation, compared later, would
        // again become a boolean select.
        float side = wi.z < 0.f ? -1.f : 1.f;
        side = m.twosided != 0 ? side : 1.f;
        wi.z = wi.z * side;
        wo.z = wo.z * side;
        float up = wi.z > 0.f ? 1.f : 0.f;
        up = wo.z > 0.f ? up : 0.f;
        float cos_term = InvPi * wo.z;
        Color3f f{up != 0.f ? a[0] * cos_term : 0.f, up != 0.f ? a[1] * cos_term : 0.f,
                  up != 0.f ? a[2] * cos_term : 0.f};
        float f_pdf = up != 0.f ? InvPi * std::max(wo.z, 0.f) : 0.f;
        if constexpr (Rough) {
            // (What rough_emitter_stage needs to redo this for the rough lanes.)
            b.nwx[k] = wo.x, b.nwy[k] = wo.y, b.nwz[k] = wo.z;
            b.espdf[k] = es_pdf, b.sampled0[k] = sampled;
        }
        // f is not null: a sum of magnitudes is zero exactly when all are (a channelwise test
        // of f, which was selected, would again become a boolean select).
        float f_sum = std::abs(f.v[0]) + std::abs(f.v[1]) + std::abs(f.v[2]);
        sampled = f_sum != 0.f ? sampled : 0.f;
        float w = mis_weight(es_pdf, f_pdf * bsdf_mis);
        if constexpr (NonMesh && Shapes) {  // (a delta sample, a point light's, is not MIS-weighted)
            const float delta_sample = aside != 0.f ? b.adelta[k] : 0.f;
            w = delta_sample != 0.f ? 1.f : w;
        }
        b.cr[k] = b.br[k] * f.v[0] * ew.v[0] * w;
        b.cg[k] = b.bg[k] * f.v[1] * ew.v[1] * w;
        b.cb[k] = b.bb[k] * f.v[2] * ew.v[2] * w;
        // Its shadow ray (SurfaceInteraction::spawn_ray_to; a direction's: spawn_ray).
        Vec3 so = offset_p(b, k, NonMesh ? select(to_infinity != 0.f, d, lp - p) : lp - p);
        Vec3 sd = lp - so;
        float sdist = norm(sd);
        sd = sd / sdist;
        float stmax = sdist * (1.f - ShadowEpsilon);
        if constexpr (NonMesh) {
            sd = select(to_infinity != 0.f, d, sd);
            stmax = to_infinity != 0.f ? Infinity : stmax;
        }
        b.shadow[k] = sampled != 0.f;
        b.light[k] = index;
        b.sox[k] = so.x, b.soy[k] = so.y, b.soz[k] = so.z;
        b.sdx[k] = sd.x, b.sdy[k] = sd.y, b.sdz[k] = sd.z;
        b.stmax[k] = stmax;

        // Sample the BSDF for the next ray (bsdf_sample, in the flipped frame).
        const float u1 = b.pb1[k];
        const Vec2 u2{b.pb2x[k], b.pb2y[k]};
        // Diffuse: cosine-weighted (DiffuseBSDF::sample's tests: wi and wo above the surface).
        Vec3 cos_wo = warp::square_to_cosine_hemisphere(u2);
        float cos_pdf = warp::square_to_cosine_hemisphere_pdf(cos_wo);
        float up_in = wi.z > 0.f ? 1.f : 0.f;
        float diffuse_pdf = cos_wo.z > 0.f ? up_in * cos_pdf : 0.f;  // (up_in is 1 or 0: exact)
        // The mirror's and the dielectric's reflection.
        Vec3 reflected{wi.x * -1.f, wi.y * -1.f, wi.z};
        // The dielectric: reflection or refraction, chosen by u1 against the Fresnel
        // reflectance (fresnel_dielectric, whose early returns GCC turns into selects). Without
        // Delta, a reflectance of 1: no lane refracts, and GCC drops what follows from it.
        float cos_t = 0.f, eta_it = 1.f, eta_ti = 1.f, r = 1.f;
        if constexpr (Delta) r = fresnel_dielectric(wi.z, m.eta, &cos_t, &eta_it, &eta_ti);
        float reflects = u1 <= r ? 1.f : 0.f;
        Vec3 refracted{(eta_ti * -1.f) * wi.x, (eta_ti * -1.f) * wi.y, cos_t};
        float glass_pdf = reflects != 0.f ? r : 1.f - r;
        // The sample of this lane's BSDF: its direction, density and weight; whether it
        // exists (a density above zero) and refracts (then the weight is the transmittance
        // times eta_ti^2, and the path's eta changes).
        float refract = diffuse + mirror + rough != 0.f ? 0.f : 1.f - reflects;
        Vec3 bwo = select(refract != 0.f, refracted, reflected);
        bwo = select(diffuse != 0.f, cos_wo, bwo);
        float bpdf = glass_pdf;
        bpdf = mirror != 0.f ? (wi.z > 0.f ? 1.f : 0.f) : bpdf;
        bpdf = diffuse != 0.f ? diffuse_pdf : bpdf;
        float t2 = eta_ti * eta_ti;
        float wr = refract != 0.f ? s[0] * t2 : a[0], wg = refract != 0.f ? s[1] * t2 : a[1];
        float wb = refract != 0.f ? s[2] * t2 : a[2];
        if constexpr (Rough) {
            // Rough: the rough stages' sample (in the flipped frame).
            const Vec3 rwo{b.swx[k], b.swy[k], b.swz[k]};
            bwo = select(rough != 0.f, rwo, bwo);
            bpdf = rough != 0.f ? b.rpdf[k] : bpdf;
            wr = rough != 0.f ? b.rwr[k] : wr, wg = rough != 0.f ? b.rwg[k] : wg;
            wb = rough != 0.f ? b.rwb[k] : wb;
        }
        float alive = bpdf > 0.f ? shade : 0.f;
        bwo.z = bwo.z * side;
        float br = b.br[k] * wr, bg = b.bg[k] * wg, bb = b.bb[k] * wb;
        float rr_r = b.rr_r[k] * wr, rr_g = b.rr_g[k] * wg, rr_b = b.rr_b[k] * wb;
        float path_eta = b.eta[k] * (refract != 0.f ? eta_it : 1.f);
        b.refracts[k] = refract;  // (a float flag: an int from `refract != 0` stops the vectoriser)
        Vec3 dn = fs * bwo.x + ft * bwo.y + fn * bwo.z;
        Vec3 o = offset_p(b, k, dn);

        // Russian roulette (path_li's): survival with the roulette throughput, capped.
        const float roulette = b.depth[k] + 1 >= rr_depth ? 1.f : 0.f;
        float beta_max = std::max(rr_r, std::max(rr_g, rr_b));
        alive = beta_max > 0.f ? alive : 0.f;
        float q = std::min(beta_max * path_eta * path_eta, MaxSurvival);
        const float u_rr = b.prr[k];
        float dies = u_rr >= q ? roulette : 0.f;
        alive = dies != 0.f ? 0.f : alive;
        alive = bsdf_mis != 0.f ? alive : 0.f;  // (without BSDF sampling, the path ends here)
        float inv_q = 1.f / q;
        br = roulette != 0.f ? br * inv_q : br;
        bg = roulette != 0.f ? bg * inv_q : bg;
        bb = roulette != 0.f ? bb * inv_q : bb;
        rr_r = roulette != 0.f ? rr_r * inv_q : rr_r;
        rr_g = roulette != 0.f ? rr_g * inv_q : rr_g;
        rr_b = roulette != 0.f ? rr_b * inv_q : rr_b;

        b.alive[k] = alive != 0.f;
        b.br[k] = br, b.bg[k] = bg, b.bb[k] = bb;
        b.rr_r[k] = rr_r, b.rr_g[k] = rr_g, b.rr_b[k] = rr_b;
        b.eta[k] = path_eta;
        b.prev_px[k] = p.x, b.prev_py[k] = p.y, b.prev_pz[k] = p.z;
        b.prev_pdf[k] = bpdf;
        b.prev_delta[k] = (diffuse + rough) * nee != 0.f ? 0 : 1;
        b.ox[k] = o.x, b.oy[k] = o.y, b.oz[k] = o.z;
        b.dx[k] = dn.x, b.dy[k] = dn.y, b.dz[k] = dn.z;
        b.tmin[k] = 0.f;
        b.tmax[k] = Infinity;
    }
}
#undef RBPT_LIGHT_FLAG
#undef RBPT_LIGHT

/// The shadow rays' tmin (every lane's: 0).
alignas(64) const float shadow_tmin[B] = {};

/// The shadow rays of lanes [0, n) marked `shadow`, in SIMD lanes (BVH::occluded_columns):
/// `shadow` stays 1 where nothing blocks the ray. The batch's columns as they are, with an
/// empty interval (tmax -1) in the lanes without a shadow ray, which then enter no box and
/// hit nothing (gathering the shadow rays into columns of their own cost veach-mis 2-4%).
__attribute__((noinline)) void shadow_rays_in_lanes(Batch &b, int n, const BVH &bvh) {
    alignas(64) float tmax[B];
    alignas(64) int blocked[B];
    int m = 0;
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) tmax[k] = b.shadow[k] ? b.stmax[k] : -1.f, m += b.shadow[k] ? 1 : 0;
    if (m == 0) return;
    bvh.occluded_columns({b.sox, b.soy, b.soz, b.sdx, b.sdy, b.sdz, shadow_tmin, tmax}, n, blocked);
    rays_traced += uint64_t(m);
    for (int k = 0; k < n; ++k) b.shadow[k] = b.shadow[k] && !blocked[k];
}

/// The random numbers of this vertex for the lanes marked `shade`, drawn before the stages
/// that take them, in path_vertex's order: the emitter sample's two where the BSDF samples an
/// emitter (BSDF::smooth, with emitter sampling), the BSDF sample's three (with BSDF
/// sampling: a stream continues into `direct`'s next sub-path), and the roulette's where it
/// applies (a path that ends first never reads the numbers past its
/// end), into the p* columns; the lanes' samplers move on. The independent sampler's in SIMD
/// lanes from each lane's stream; the others' (WavefrontScene::predrawn) in SIMD lanes too,
/// by SamplerColumns from the lanes' samplers gathered from `parts` (and put back).
void draw_stage(Batch &b, int n, const WavefrontScene &ws, const IntegratorSettings &cfg, const SamplerDesc &desc,
                Sampler::Parts *parts, SamplerColumns &columns) {
    const WavefrontScene::Material *mats = ws.materials.data();
    const float nee = cfg.emitter_sampling ? 1.f : 0.f;
    const bool bsdf = cfg.bsdf_sampling;
    // (The lanes' test of BSDF sampling, as a depth it starts from: a loop-invariant flag
    // would have GCC split the loop in two, neither of which it vectorises.)
    const int bsdf_depth = bsdf ? 0 : INT_MAX;
    const int rr_depth = cfg.rr_depth;
    if (!ws.predrawn) {
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            // (Every lane: those not shaded get their stream back or end.)
            const WavefrontScene::Material &m = mats[b.mat[k]];
            const bool emitter = (m.diffuse + m.rough) * nee != 0.f;
            b.pe0[k] = next_1d(b, k, emitter);
            b.pe1[k] = next_1d(b, k, emitter);
            const bool sample = b.depth[k] >= bsdf_depth;
            b.pb1[k] = next_1d(b, k, sample);
            b.pb2x[k] = next_1d(b, k, sample);
            b.pb2y[k] = next_1d(b, k, sample);
            b.prr[k] = next_1d(b, k, b.depth[k] + 1 >= rr_depth);
        }
        return;
    }
    // Which lanes draw which numbers (the p* columns of the others are written, unread).
    alignas(64) int emitter[B], roulette[B];
    for (int k = 0; k < n; ++k) {
        const WavefrontScene::Material &m = mats[b.mat[k]];
        if (b.shade[k]) columns.set(k, parts[b.seq[k]]);
        emitter[k] = b.shade[k] && (m.diffuse + m.rough) * nee != 0.f;
        roulette[k] = b.shade[k] && b.depth[k] + 1 >= rr_depth;
    }
    columns.next_2d(desc, n, emitter, b.pe0, b.pe1);
    if (bsdf) {
        columns.next_1d(desc, n, b.shade, b.pb1);
        columns.next_2d(desc, n, b.shade, b.pb2x, b.pb2y);
    }
    columns.next_1d(desc, n, roulette, b.prr);
    for (int k = 0; k < n; ++k) {
        if (!b.shade[k]) continue;
        parts[b.seq[k]] = columns.get(k);
        b.state[k] = columns.state[k], b.inc[k] = columns.inc[k];
    }
}

/// The instance of vertex_stage for a scene's emitters and BSDFs.
using VertexStage = void (*)(Batch &, int, const WavefrontScene &, const IntegratorSettings &);
VertexStage vertex_stage_for(const WavefrontScene &ws) {
    return with_flags([&](auto one_light, auto delta, auto rough, auto env) -> VertexStage {
        constexpr bool O = decltype(one_light)::value, D = decltype(delta)::value;
        constexpr bool R = decltype(rough)::value, E = decltype(env)::value;
        // (Two lights, as one beside the environment: their fields selected, not gathered.)
        [[maybe_unused]] const bool two = ws.lights.size() == 2;
        // Several lights, none a mesh: NonMesh 2.
        if constexpr (!O && E) {
            if (!ws.any_mesh_lights) {
                if (two) return vertex_stage<O, D, R, 2, true, true>;
                return vertex_stage<O, D, R, 2>;
            }
        }
        // The environment alone beside meshes: no spheres' cones, no aside samples.
        if constexpr (E) {
            if (!ws.any_sphere_lights && !ws.any_aside_lights) {
                if constexpr (!O) {
                    if (two) return vertex_stage<O, D, R, 1, false, true>;
                }
                return vertex_stage<O, D, R, 1, false>;
            }
        }
        return vertex_stage<O, D, R, E ? 1 : 0>;
    }, ws.lights.size() == 1, ws.any_delta, ws.any_rough, ws.environment || ws.any_sphere_lights || ws.any_aside_lights);
}

/// The emitter samples of the lanes whose emitter the vector stage does not sample itself
/// (Light::aside) and lane_emitter_stage does not either (Light::lanes 0: no current type,
/// or every one with TORCH_RBPT_WAVEFRONT=aside): emitter_sample() for each, one lane at a
/// time, from draw_stage's numbers (with which the vector stage selects the same emitter),
/// into the a* columns, which the vector stage takes for those lanes. So a new emitter type
/// needs only emitters.h's code to run in the wavefront: the BSDF towards its sample, the
/// MIS weight, the shadow ray and the BSDF sample stay in lanes.
void aside_emitter_stage(Batch &b, int n, const WavefrontScene &ws, const RenderContext<RGB<float>> &ctx) {
    const int n_lights = int(ws.lights.size());
    for (int k = 0; k < n; ++k) {
        // (A mirror or a dielectric samples no emitter. The other lanes get no sample.)
        const WavefrontScene::Material &m = ws.materials[size_t(b.mat[k])];
        const Vec2 u{b.pe0[k], b.pe1[k]};  // (draw_stage's)
        const int index = std::min(int(u.x * float(n_lights)), n_lights - 1);  // (emitter_sample's choice)
        std::optional<EmitterSample<RGB<float>>> es;
        const WavefrontScene::Light &l = ws.lights[size_t(index)];
        if (l.lanes) continue;  // (lane_emitter_stage's)
        if (b.shade[k] && m.diffuse + m.rough != 0.f && l.aside != 0.f)
            es = emitter_sample<RGB<float>>(ctx, Vec3{b.px[k], b.py[k], b.pz[k]}, u);
        const EmitterSample<RGB<float>> none;
        const EmitterSample<RGB<float>> &e = es ? *es : none;
        b.aok[k] = es ? 1.f : 0.f;
        b.adx[k] = e.d.x, b.ady[k] = e.d.y, b.adz[k] = e.d.z;
        b.apx[k] = e.p.x, b.apy[k] = e.p.y, b.apz[k] = e.p.z;
        b.apdf[k] = e.pdf;
        b.awr[k] = es ? e.weight[0] : 0.f, b.awg[k] = es ? e.weight[1] : 0.f, b.awb[k] = es ? e.weight[2] : 0.f;
        b.adelta[k] = e.delta ? 1.f : 0.f;
        b.ainf[k] = std::isinf(e.dist) ? 1.f : 0.f;
    }
}

/// The emitter samples of the lanes whose emitter is sampled in lanes before the vector
/// stage (Light::lanes: an area light on a mesh of more than 8 triangles, on a disk or on a
/// cylinder, or a point light), into the a* columns as aside_emitter_stage's (which runs
/// after it and leaves those lanes alone): emitter_sample()'s area and point branches and
/// Geometry::sample_direction's mesh, disk and cylinder branches, the same operations. A mesh
/// light's triangle is found by a binary search of its CDF without branches
/// (std::upper_bound's count, large_steps halvings for every lane), its vertices and normals
/// gathered (WavefrontScene::large_triangles; the vertex normals only where some of those
/// lights have them: Normals); a disk's point is the concentric map's, a cylinder's at angle
/// 2 pi u.y and height u.x along its axis, placed by the shape's frame in double
/// (Shape::world_point; WavefrontScene::light_frame); a point light's is its position, a
/// delta sample. The code of the kinds a scene lacks is left out (Meshes, Analytic, Points).
template <bool Meshes, bool Normals, bool Analytic, bool Points>
void lane_emitter_stage(Batch &b, int n, const WavefrontScene &ws) {
    if constexpr (!Meshes && !Analytic && !Points) return;  // (never called)
    const WavefrontScene::Material *mats = ws.materials.data();
    const WavefrontScene::Light *lights = ws.lights.data();
    const int n_lights = int(ws.lights.size());
    const int *counts = ws.large_count.data(), *cdf_firsts = ws.large_cdf_first.data();
    const int *firsts = ws.large_first.data();
    // (The radiance from WavefrontScene::radiance: a gather of Light::radiance's array member
    // stopped the vectoriser.)
    const float *cdf = ws.large_cdf.data(), *radiance = ws.radiance.data();
    const LightTriangles tris(ws.large_triangles);
    // The light each lane selects (emitter_sample's choice) and u.x within it; the search's
    // start in the CDF's entries [1, count] and the length left.
    alignas(64) int chosen[B], base[B], left[B];
    alignas(64) float ux[B];
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const float u = b.pe0[k];  // (draw_stage's)
        const int index = std::min(int(u * float(n_lights)), n_lights - 1);
        chosen[k] = index;
        ux[k] = std::min(u * float(n_lights) - float(index), 0.99999994f);
        if constexpr (Meshes) base[k] = cdf_firsts[index] + 1, left[k] = counts[index];
    }
    for (int step = 0; Meshes && step < ws.large_steps; ++step) {
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            const int half = left[k] / 2;
            base[k] = cdf[base[k] + half] <= ux[k] ? base[k] + half : base[k];
            left[k] -= half;
        }
    }
    const float *f[17];  // (WavefrontScene::light_frame, a column each: gathers of one base address)
    for (int c = 0; c < 17; ++c) f[c] = ws.light_frame[c].data();
    // A point light's position (gathered in a loop of its own: under the condition below
    // it became a masked gather, which GCC does not vectorise for AVX2).
    alignas(64) float ppx[B], ppy[B], ppz[B];
    if constexpr (Points) {
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) ppx[k] = f[0][chosen[k]], ppy[k] = f[1][chosen[k]], ppz[k] = f[2][chosen[k]];
    }
    // A disk or cylinder light's point, uniform in area, and its normal (in a loop of its
    // own: with the double precision products in the loop below, GCC vectorised neither):
    // the disk's, or the cylinder's at that angle.
    alignas(64) float dpx[B], dpy[B], dpz[B], dnx[B], dny[B], dnz[B];
    if constexpr (Analytic) {
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            const int i = chosen[k];
            const bool cylinder = lights[i].cylinder != 0;
            const Vec2 q = warp::square_to_uniform_disk_concentric(Vec2{ux[k], b.pe1[k]});
            const Vec2 cs = warp::cossin_2pi(b.pe1[k]);  // (cos, sin) of phi = 2 pi u.y
            const double radius = f[15][i], length = f[16][i];
            const double q0 = cylinder ? double(cs.x) * radius : double(q.x);
            const double q1 = cylinder ? double(cs.y) * radius : double(q.y);
            const double q2 = cylinder ? double(ux[k]) * length : 0.0;
            dpx[k] = float(double(f[0][i]) + double(f[3][i]) * q0 + double(f[6][i]) * q1 + double(f[9][i]) * q2);
            dpy[k] = float(double(f[1][i]) + double(f[4][i]) * q0 + double(f[7][i]) * q1 + double(f[10][i]) * q2);
            dpz[k] = float(double(f[2][i]) + double(f[5][i]) * q0 + double(f[8][i]) * q1 + double(f[11][i]) * q2);
            const Vec3 radial = normalize(Vec3{f[3][i], f[4][i], f[5][i]} * cs.x + Vec3{f[6][i], f[7][i], f[8][i]} * cs.y);
            const Vec3 n = select(cylinder, radial, Vec3{f[12][i], f[13][i], f[14][i]});
            dnx[k] = n.x, dny[k] = n.y, dnz[k] = n.z;
        }
    }
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const int index = chosen[k];
        const WavefrontScene::Light &l = lights[index];
        Vec3 lp, face_n, ln;
        if constexpr (Meshes) {
            // The triangle: the CDF's entries at most u.x (upper_bound), but the last.
            const int c = cdf_firsts[index];
            const int le = base[k] - (c + 1) + (cdf[base[k]] <= ux[k] ? 1 : 0);
            const int local = std::min(le, counts[index] - 1);
            const float lo = cdf[c + local], width = cdf[c + local + 1] - lo;
            Vec2 u{std::min(width > 0.f ? (ux[k] - lo) / width : 0.f, 0.99999994f), b.pe1[k]};
            // A uniform point on it, its normal (interpolated, or the face's) and the face
            // normal.
            const int t = firsts[index] + local;
            const Vec2 bc = warp::square_to_uniform_triangle(u);
            const float b0 = 1.f - bc.x - bc.y;
            lp = tris.vertex(0, t) * b0 + tris.vertex(1, t) * bc.x + tris.vertex(2, t) * bc.y;
            face_n = tris.face_normal(t);
            ln = face_n;
            if constexpr (Normals) {
                const Vec3 vn = normalize(tris.normal(0, t) * b0 + tris.normal(1, t) * bc.x + tris.normal(2, t) * bc.y);
                ln = select(l.has_normals, vn, face_n);
            }
            ln = select(l.flip_normals, -ln, ln);
        }
        if constexpr (Analytic) {
            // A disk's or cylinder's point and normal (the loop above's; the area's too; in
            // every lane without mesh lights: the other lanes' samples are not taken).
            Vec3 dn{dnx[k], dny[k], dnz[k]};
            dn = select(l.flip_normals, -dn, dn);
            const bool analytic = !Meshes || l.disk + l.cylinder != 0;
            lp = select(analytic, Vec3{dpx[k], dpy[k], dpz[k]}, lp);
            face_n = select(analytic, dn, face_n);
            ln = select(analytic, dn, ln);
        }
        // A point light's position.
        // (Conditions as float flags, 1 or 0, narrowed by selects: GCC does not vectorise
        // this loop with && or || of them.)
        const float point = Points && l.point != 0 ? 1.f : 0.f;
        if constexpr (Points) lp = select(point != 0.f, Vec3{ppx[k], ppy[k], ppz[k]}, lp);
        // The direction and its density (by area, converted to solid angle with the face
        // normal), and whether it is a sample: pdf > 0 and d facing the light's front (a
        // point light's always is).
        const Vec3 p{b.px[k], b.py[k], b.pz[k]};
        Vec3 d = lp - p;
        const float dist2 = squared_norm(d), dist = std::sqrt(dist2);
        d = d * (1.f / dist);
        const WavefrontScene::Material &m = mats[b.mat[k]];
        float ok = b.shade[k] != 0 ? 1.f : 0.f;
        ok = m.diffuse + m.rough != 0.f ? ok : 0.f;
        float es_pdf = 0.f, inv_pdf = 0.f, facing = 0.f;
        if constexpr (Meshes || Analytic) {
            const float abs_cos = std::abs(dot(face_n, d));
            float pdf = abs_cos > 0.f ? dist2 / (l.area * abs_cos) : 0.f;
            pdf = dist != 0.f ? pdf : 0.f;
            facing = pdf > 0.f ? 1.f : 0.f;
            facing = dot(d, ln) < 0.f ? facing : 0.f;
            es_pdf = pdf / float(n_lights), inv_pdf = 1.f / es_pdf;
        }
        // (A point light's "density" 1 / n and weight intensity n / dist^2.)
        if constexpr (Points) {
            facing = point != 0.f ? 1.f : facing;
            es_pdf = point != 0.f ? 1.f / float(n_lights) : es_pdf;
            inv_pdf = point != 0.f ? float(n_lights) / dist2 : inv_pdf;
        }
        ok = facing != 0.f ? ok : 0.f;
        // Into the a* columns (no sample: EmitterSample's defaults), of every lane: the
        // other lights' lanes take aside_emitter_stage's after, or none (unconditional
        // stores: selects with the columns' old values became masked stores, which GCC does
        // not vectorise for AVX2 here).
        const bool sample = ok != 0.f;
        b.aok[k] = ok;
        b.adx[k] = sample ? d.x : 0.f, b.ady[k] = sample ? d.y : 0.f, b.adz[k] = sample ? d.z : 0.f;
        b.apx[k] = sample ? lp.x : 0.f, b.apy[k] = sample ? lp.y : 0.f, b.apz[k] = sample ? lp.z : 0.f;
        b.apdf[k] = sample ? es_pdf : 0.f;
        // (The radiance read in every lane, its factor selected: a load under the condition
        // became a masked gather, which GCC does not vectorise for AVX2.)
        const float scale = sample ? inv_pdf : 0.f;
        b.awr[k] = radiance[3 * index] * scale;
        b.awg[k] = radiance[3 * index + 1] * scale;
        b.awb[k] = radiance[3 * index + 2] * scale;
        b.adelta[k] = sample ? point : 0.f;
        const float infinite = dist != Infinity ? 0.f : 1.f;
        b.ainf[k] = sample ? infinite : 1.f;
    }
}

/// The instance of lane_emitter_stage for a scene's lights.
using LaneEmitterStage = void (*)(Batch &, int, const WavefrontScene &);
LaneEmitterStage lane_emitter_stage_for(const WavefrontScene &ws) {
    return with_flags([](auto meshes, auto normals, auto analytic, auto points) -> LaneEmitterStage {
        return lane_emitter_stage<decltype(meshes)::value, decltype(normals)::value, decltype(analytic)::value,
                                  decltype(points)::value>;
    }, ws.any_large_lights, ws.any_large_normals, ws.any_analytic_lights, ws.any_point_lights);
}

/// The rough lanes: the BSDF samples and the emitter samples of the BSDFs of a distribution
/// (GGX's, or Beckmann's), in stages over the lanes that have them, listed (GGX:
/// ggx_sample_stage; Beckmann: beckmann_sample_stage; then rough_emitter_stage for either;
/// both listed by list_rough_lanes), so that the vector stage carries none of their code and
/// the other lanes pay nothing for it (glossy, whose walls are diffuse and whose rough lanes
/// are a third of its vertices: 459-460 -> 448-450 ms, and 431-434 -> 410-412 more with all
/// the lists of lanes padded). A new BSDF with costly terms takes stages of its own in this
/// pattern. The lanes' inputs are packed one lane at a time (gathers in lanes were no
/// faster) and their results moved back so; the rest runs in SIMD lanes over the list,
/// padded to whole vectors (simd::pad_indices).

/// The lanes [0, n) shaded by a rough BSDF of Beckmann's distribution (beckmann 1) or GGX's
/// (0), listed in `lanes`; returns their number.
int list_rough_lanes(const Batch &b, int n, const WavefrontScene &ws, float beckmann, int *lanes) {
    const WavefrontScene::Material *mats = ws.materials.data();
    alignas(64) int flag[B];
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const WavefrontScene::Material &m = mats[b.mat[k]];
        const float shade = b.shade[k] != 0 ? 1.f : 0.f;
        const float kind = m.beckmann == beckmann ? 1.f : 0.f;
        flag[k] = m.rough * kind * shade != 0.f ? 1 : 0;
    }
    return simd::select_indices(flag, n, 1, lanes);
}

/// A list of rough lanes and the inputs its two stages share, packed by its sample stage
/// before the vector stage (which changes none of them but the throughput, packed as it was
/// before the vertex) and read again by rough_emitter_stage after it; wi in the frame the
/// vertex stage samples in (twosided's flip applied).
struct RoughLanes {
    int count = 0, padded = 0;  ///< the lanes, and the list's length padded to whole vectors
    bool plastic = true;        ///< whether some are roughplastics (else all are conductors)
    alignas(64) int lanes[B], mat[B];
    alignas(64) float ar[B], ag[B], ab[B], tr[B], tg[B], tb[B], wix[B], wiy[B], wiz[B], br[B], bg[B], bb[B];
};

/// Packs the inputs of the lanes r.lanes[0, r.count) into `r` (the list padded to whole
/// vectors first), and their BSDF sample's numbers (draw_stage's) into u1s, ux and uy.
void pack_rough_lanes(const Batch &b, const WavefrontScene &ws, RoughLanes &r, float *u1s, float *ux, float *uy) {
    r.padded = simd::pad_indices(r.lanes, r.count);
    r.plastic = false;
    for (int j = 0; j < r.padded; ++j) {
        const int k = r.lanes[j];
        const WavefrontScene::Material &m = ws.materials[size_t(b.mat[k])];
        r.mat[j] = b.mat[k];
        r.plastic = r.plastic || m.plastic != 0.f;
        r.ar[j] = b.ar[k], r.ag[j] = b.ag[k], r.ab[j] = b.ab[k], r.tr[j] = b.tr[k], r.tg[j] = b.tg[k], r.tb[j] = b.tb[k];
        // (The flip as a product with -1, as the vertex stage's: exact.)
        const float side = m.twosided != 0 && b.wiz[k] < 0.f ? -1.f : 1.f;
        r.wix[j] = b.wix[k], r.wiy[j] = b.wiy[k], r.wiz[j] = b.wiz[k] * side;
        r.br[j] = b.br[k], r.bg[j] = b.bg[k], r.bb[j] = b.bb[k];
        u1s[j] = b.pb1[k], ux[j] = b.pb2x[k], uy[j] = b.pb2y[k];
    }
}

/// The BSDF samples of the rough lanes packed in `r`, before the vector stage, in its frame:
/// the reflection about a visible normal (GGX's, sampled here; with Terms
/// StoredOnly the one given in mx, my, mz, with the microfacet terms towards the sample in
/// D, g_i, g_o) or, for a roughplastic where u1 picks its base, the cosine-weighted
/// direction; its density (zero where wi is below the surface) and its weight value /
/// density, into the swx.., rpdf and rw* columns. With Defer, the direction alone, density
/// and weight 1 (see finish_deferred_samples). Plastic: RoughLanes::plastic.
template <Microfacet Terms, bool Defer, bool Plastic>
void rough_samples(Batch &b, const RoughLanes &r, const WavefrontScene &ws, const float *u1s, const float *ux,
                   const float *uy, const float *mx, const float *my, const float *mz, const float *D,
                   const float *g_i, const float *g_o) {
    static_assert(Terms == Microfacet::GGX || Terms == Microfacet::StoredOnly, "GGX's normals, or given ones");
    const WavefrontScene::Material *mats = ws.materials.data();
    const float *tables = ws.tables.data();
    const int *mat = r.mat;
    const float *ar = r.ar, *ag = r.ag, *ab = r.ab, *tr = r.tr, *tg = r.tg, *tb = r.tb, *wix = r.wix, *wiy = r.wiy, *wiz = r.wiz;
    alignas(64) float ox[B], oy[B], oz[B], pdf[B], wr[B], wg[B], wb[B];
#pragma GCC ivdep
    for (int j = 0; j < r.padded; ++j) {
        const WavefrontScene::Material &m = mats[mat[j]];
        const float a[3] = {ar[j], ag[j], ab[j]}, s[3] = {tr[j], tg[j], tb[j]};
        const Vec3 wi{wix[j], wiy[j], wiz[j]};
        const Vec2 u2{ux[j], uy[j]};
        Vec3 normal;
        MicrofacetTerms terms;
        if constexpr (Terms == Microfacet::StoredOnly) {
            normal = Vec3{mx[j], my[j], mz[j]};
            terms = MicrofacetTerms{D[j], g_i[j], g_o[j]};
        } else {
            normal = ggx_visible_normal(m.alpha, wi, u2);
        }
        const Vec3 specular = reflect(wi, normal);
        Vec3 wo = specular;
        if constexpr (Plastic) {
            // (A roughplastic's base: the cosine-weighted direction.)
            const float pick_base = u1s[j] < specular_probability(m, transmittance(tables, m.table, wi.z)) ? 0.f : m.plastic;
            wo = select(pick_base != 0.f, warp::square_to_cosine_hemisphere(u2), specular);
        }
        ox[j] = wo.x, oy[j] = wo.y, oz[j] = wo.z;
        if constexpr (Defer) {
            pdf[j] = 1.f, wr[j] = wg[j] = wb[j] = 1.f;
        } else {
            const RoughWeight w = sample_weight(rough_eval<Terms, Plastic>(m, terms, tables, wi, wo, a, s), wi.z);
            pdf[j] = w.pdf, wr[j] = w.r, wg[j] = w.g, wb[j] = w.b;
        }
    }
    for (int j = 0; j < r.count; ++j) {
        const int k = r.lanes[j];
        b.swx[k] = ox[j], b.swy[k] = oy[j], b.swz[k] = oz[j];
        b.rpdf[k] = pdf[j], b.rwr[k] = wr[j], b.rwg[k] = wg[j], b.rwb[k] = wb[j];
    }
}

/// The BSDF samples of the GGX lanes listed in `r`, before the vector stage.
template <bool Defer>
void ggx_sample_stage(Batch &b, RoughLanes &r, const WavefrontScene &ws) {
    alignas(64) float u1s[B], ux[B], uy[B];
    pack_rough_lanes(b, ws, r, u1s, ux, uy);
    with_flags([&](auto plastic) {
        rough_samples<Microfacet::GGX, Defer, decltype(plastic)::value>(b, r, ws, u1s, ux, uy, nullptr, nullptr, nullptr,
                                                                        nullptr, nullptr, nullptr);
    }, r.plastic);
}

/// The emitter samples of the rough lanes listed in `r` (by their sample stage), after the
/// vector stage evaluated them as a diffuse BSDF's: the BSDF towards each (rough_eval with
/// Terms GGX or Beckmann, as the scalar path evaluates it), its MIS weight and contribution,
/// and whether it stands (the vector stage's tests and f not null), into the c* and shadow
/// columns. Aside: whether some lights are sampled aside (their samples' weights and deltas);
/// Plastic: RoughLanes::plastic.
template <Microfacet Terms, bool Aside, bool Plastic>
void rough_emitter_stage(Batch &b, const RoughLanes &r, const WavefrontScene &ws, float bsdf_mis) {
    static_assert(Terms == Microfacet::GGX || Terms == Microfacet::Beckmann, "a distribution's own terms");
    const WavefrontScene::Material *mats = ws.materials.data();
    const float *radiance = ws.radiance.data(), *tables = ws.tables.data();
    const int *lanes = r.lanes, *mat = r.mat;
    const float *ar = r.ar, *ag = r.ag, *ab = r.ab, *tr = r.tr, *tg = r.tg, *tb = r.tb, *wix = r.wix, *wiy = r.wiy, *wiz = r.wiz;
    const float *obr = r.br, *obg = r.bg, *obb = r.bb;
    const int padded = r.padded;
    alignas(64) int light[B];
    alignas(64) float nwx[B], nwy[B], nwz[B], espdf[B], sampled0[B];
    for (int j = 0; j < padded; ++j) {
        const int k = lanes[j];
        light[j] = b.light[k];
        nwx[j] = b.nwx[k], nwy[j] = b.nwy[k], nwz[j] = b.nwz[k];
        espdf[j] = b.espdf[k], sampled0[j] = b.sampled0[k];
    }
    // (A light sampled aside: its sample's weight and whether it is a delta one, else zeros.)
    alignas(64) float aside[B], awr[B], awg[B], awb[B], adelta[B];
    for (int j = 0; Aside && j < padded; ++j) {
        const int k = lanes[j];
        const bool a = ws.lights[size_t(light[j])].aside != 0.f;
        aside[j] = a ? 1.f : 0.f;
        awr[j] = a ? b.awr[k] : 0.f, awg[j] = a ? b.awg[k] : 0.f, awb[j] = a ? b.awb[k] : 0.f;
        adelta[j] = a ? b.adelta[k] : 0.f;
    }
    alignas(64) float cr[B], cg[B], cb[B], sampled[B];
#pragma GCC ivdep
    for (int j = 0; j < padded; ++j) {
        const WavefrontScene::Material &m = mats[mat[j]];
        const float a[3] = {ar[j], ag[j], ab[j]}, s[3] = {tr[j], tg[j], tb[j]};
        const Vec3 wi{wix[j], wiy[j], wiz[j]};
        const Vec3 wo{nwx[j], nwy[j], nwz[j]};
        RoughEval e = rough_eval<Terms, Plastic>(m, MicrofacetTerms{}, tables, wi, wo, a, s);
        float f_sum = std::abs(e.r) + std::abs(e.g) + std::abs(e.b);
        sampled[j] = f_sum != 0.f ? sampled0[j] : 0.f;
        // (The emitter sample's weight and MIS weight, as the vector stage computed them.)
        const int l = 3 * light[j];
        const float inv_pdf = 1.f / espdf[j];
        // (The radiance gathered before the selects: gathers under a condition are masked
        // gathers, which GCC does not emit for AVX2.)
        float ew[3] = {radiance[l] * inv_pdf, radiance[l + 1] * inv_pdf, radiance[l + 2] * inv_pdf};
        float w = mis_weight(espdf[j], e.pdf * bsdf_mis);
        if constexpr (Aside) {
            ew[0] = aside[j] != 0.f ? awr[j] : ew[0], ew[1] = aside[j] != 0.f ? awg[j] : ew[1];
            ew[2] = aside[j] != 0.f ? awb[j] : ew[2];
            w = adelta[j] != 0.f ? 1.f : w;
        }
        cr[j] = obr[j] * e.r * ew[0] * w;
        cg[j] = obg[j] * e.g * ew[1] * w;
        cb[j] = obb[j] * e.b * ew[2] * w;
    }
    for (int j = 0; j < r.count; ++j) {
        const int k = lanes[j];
        b.cr[k] = cr[j], b.cg[k] = cg[j], b.cb[k] = cb[j];
        b.shadow[k] = sampled[j] != 0.f ? 1 : 0;
    }
}

/// rough_emitter_stage for a scene with or without lights sampled aside, and lanes with or
/// without roughplastics.
template <Microfacet Terms>
void rough_emitter_stage(Batch &b, const RoughLanes &r, const WavefrontScene &ws, float bsdf_mis) {
    with_flags([&](auto aside, auto plastic) {
        rough_emitter_stage<Terms, decltype(aside)::value, decltype(plastic)::value>(b, r, ws, bsdf_mis);
    }, ws.any_aside_lights, r.plastic);
}

/// d log f / d alpha of a rough conductor (RoughConductorBSDF::dlog_dalpha) at the lanes
/// packed in `r` whose material `watched` marks (a rough conductor whose roughness is
/// differentiated), towards their emitter sample (nw*) and their BSDF sample (sw*), into
/// de[k] and ds[k] (lane k's columns), in SIMD lanes: the backward pass's roughness records.
/// (Lanes without one of the samples get values computed from whatever direction the batch
/// holds, which the records do not read.)
template <MicrofacetType Type>
void conductor_dlog_stage(const Batch &b, const RoughLanes &r, const WavefrontScene &ws, const int *watched,
                          float *de, float *ds) {
    alignas(64) int flag[B], list[B];
    for (int j = 0; j < r.count; ++j) flag[j] = watched[r.mat[j]];
    const int count = simd::select_indices(flag, r.count, 1, list);
    if (count == 0) return;
    const int padded = simd::pad_indices(list, count);
    alignas(64) float alpha[B], wix[B], wiy[B], wiz[B], ex[B], ey[B], ez[B], sx[B], sy[B], sz[B], dle[B], dls[B];
    for (int i = 0; i < padded; ++i) {
        const int j = list[i], k = r.lanes[j];
        alpha[i] = ws.materials[size_t(r.mat[j])].alpha;
        wix[i] = r.wix[j], wiy[i] = r.wiy[j], wiz[i] = r.wiz[j];
        ex[i] = b.nwx[k], ey[i] = b.nwy[k], ez[i] = b.nwz[k];
        sx[i] = b.swx[k], sy[i] = b.swy[k], sz[i] = b.swz[k];
    }
#pragma GCC ivdep
    for (int i = 0; i < padded; ++i) {
        const Vec3 wi{wix[i], wiy[i], wiz[i]}, wo_e{ex[i], ey[i], ez[i]}, wo_s{sx[i], sy[i], sz[i]};
        dle[i] = RoughConductorBSDF::dlog_dalpha<Type>(alpha[i], wi, wo_e);
        dls[i] = RoughConductorBSDF::dlog_dalpha<Type>(alpha[i], wi, wo_s);
    }
    for (int i = 0; i < count; ++i) {
        const int k = r.lanes[list[i]];
        de[k] = dle[i], ds[k] = dls[i];
    }
}

/// beckmann_sample_stage's Newton searches, lane j's state and constants in column j.
struct BeckmannSearches {
    float *tan_i, *normalization, *a, *b, *c, *inv_erf, *u1, *done;
    RBPT_INLINE BeckmannSlopes slopes(int j) const {
        BeckmannSlopes slopes;
        slopes.tan_i = tan_i[j], slopes.normalization = normalization[j];
        return slopes;
    }
    RBPT_INLINE BeckmannSlopes::Search load(int j) const { return {a[j], b[j], c[j], inv_erf[j], u1[j], done[j]}; }
    RBPT_INLINE void store(int j, const BeckmannSlopes::Search &s) const {
        a[j] = s.a, b[j] = s.b, c[j] = s.c, inv_erf[j] = s.inv_erf, done[j] = s.converged;
    }
    /// A step of the searches of lanes [0, m); returns whether any has not converged. (Not
    /// inline: inside beckmann_sample_stage's loop over steps GCC does not vectorise it. The
    /// answer an integer OR: a float sum, in order, took 16 scalar additions per vector.)
    __attribute__((noinline)) bool step(int m) const {
        // (The columns as locals: loads through the struct's pointers do not vectorise.)
        const float *q_tan_i = tan_i, *q_normalization = normalization, *q_u1 = u1;
        float *q_a = a, *q_b = b, *q_c = c, *q_inv_erf = inv_erf, *q_done = done;
        int open = 0;
#pragma GCC ivdep
        for (int j = 0; j < m; ++j) {
            BeckmannSlopes slopes;
            slopes.tan_i = q_tan_i[j], slopes.normalization = q_normalization[j];
            BeckmannSlopes::Search s{q_a[j], q_b[j], q_c[j], q_inv_erf[j], q_u1[j], q_done[j]};
            slopes.step(s);
            q_a[j] = s.a, q_b[j] = s.b, q_c[j] = s.c, q_inv_erf[j] = s.inv_erf, q_done[j] = s.converged;
            open |= s.converged == 0.f ? 1 : 0;
        }
        return open;
    }
};

/// The BSDF samples of the Beckmann lanes listed in `r`, before the vector stage, from the
/// BSDF sample's numbers (draw_stage's), in the frame the vertex stage samples in: the
/// visible normal where the sample takes one (a conductor's; a roughplastic's
/// where u1 picks the specular lobe) and the microfacet terms towards the sampled direction,
/// then rough_samples(). In SIMD lanes over the packed list (BeckmannSlopes' operations, so
/// the normals are VisibleNormalSampler's bit for bit): the Newton search a step per pass
/// while any lane's continues (most converge in two), its rare long tails one lane at a time.
/// (Where wi is below the surface there is no sample: those lanes search nothing, and
/// rough_samples() gives them density zero.)
template <bool Defer>
void beckmann_sample_stage(Batch &b, const WavefrontScene &ws, RoughLanes &r) {
    const WavefrontScene::Material *mats = ws.materials.data();
    const float *tables = ws.tables.data();
    alignas(64) float u1s[B], ux[B], uy[B];
    pack_rough_lanes(b, ws, r, u1s, ux, uy);
    const int m = r.padded, *mat = r.mat;
    const float *wx = r.wix, *wy = r.wiy, *wz = r.wiz;
    // alpha, whether the sample is the plastic's diffuse base (no normal; rough_samples()'
    // choice of lobe) and whether there is a sample (wi above the surface).
    alignas(64) float alpha[B], base[B], below[B];
    with_flags([&](auto plastic) {
#pragma GCC ivdep
        for (int j = 0; j < m; ++j) {
            const WavefrontScene::Material &material = mats[mat[j]];
            alpha[j] = material.alpha;
            base[j] = 0.f;
            if constexpr (decltype(plastic)::value) {
                const float t_i = transmittance(tables, material.table, wz[j]);
                const float specular = u1s[j] < specular_probability(material, t_i) ? 1.f : 0.f;
                base[j] = material.plastic != 0.f && specular == 0.f ? 1.f : 0.f;
            }
            below[j] = wz[j] > 0.f ? 0.f : 1.f;
        }
    }, r.plastic);
    // The slopes' constants and the searches' start (BeckmannSlopes; polar slopes, the base's
    // lanes and those without a sample search nothing).
    alignas(64) float cos_phi[B], sin_phi[B], polar[B], tan_i[B], normalization[B];
    alignas(64) float sa[B], sb[B], sc[B], s_inv[B], s_u1[B], s_done[B];
#pragma GCC ivdep
    for (int j = 0; j < m; ++j) {
        const BeckmannSlopes slopes(normalize(Vec3{alpha[j] * wx[j], alpha[j] * wy[j], wz[j]}));
        const BeckmannSlopes::Search s = slopes.start(ux[j]);
        cos_phi[j] = slopes.cos_phi, sin_phi[j] = slopes.sin_phi, polar[j] = slopes.polar;
        tan_i[j] = slopes.tan_i, normalization[j] = slopes.normalization;
        sa[j] = s.a, sb[j] = s.b, sc[j] = s.c, s_inv[j] = s.inv_erf, s_u1[j] = s.u1;
        s_done[j] = polar[j] + base[j] + below[j] != 0.f ? 1.f : s.converged;
    }
    // The searches' steps, all lanes at once while any continues (a converged one stays),
    // the rare long tails one lane at a time.
    BeckmannSearches searches{tan_i, normalization, sa, sb, sc, s_inv, s_u1, s_done};
    constexpr int LaneSteps = 4;
    int steps = 0;
    while (steps < LaneSteps && searches.step(m)) ++steps;
    for (int j = 0; steps == LaneSteps && j < r.count; ++j) {
        BeckmannSlopes::Search s = searches.load(j);
        for (int it = LaneSteps; it < BeckmannSlopes::MaxSteps && s.converged == 0.f; ++it) searches.slopes(j).step(s);
        searches.store(j, s);
    }
    // The normals (VisibleNormalSampler::normal of part_x and part_y; the base's (0, 0, 1))
    // and the microfacet terms towards the sampled directions (the base's cosine-weighted).
    alignas(64) float nx[B], ny[B], nz[B], D[B], g_i[B], g_o[B];
#pragma GCC ivdep
    for (int j = 0; j < m; ++j) {
        BeckmannSlopes slopes;
        slopes.cos_phi = cos_phi[j], slopes.sin_phi = sin_phi[j], slopes.polar = polar[j];
        const BeckmannSlopes::Search s{sa[j], sb[j], sc[j], s_inv[j], s_u1[j], s_done[j]};
        const float px = polar[j] != 0.f ? slopes.polar_radius(ux[j]) : BeckmannSlopes::slope(s);
        const Vec3 normal = slopes.normal(alpha[j], {px, 0.f}, slopes.part_y(uy[j]));
        const Vec3 wi{wx[j], wy[j], wz[j]};
        const bool diffuse = base[j] != 0.f;
        const Vec3 wo = select(diffuse, warp::square_to_cosine_hemisphere({ux[j], uy[j]}), reflect(wi, normal));
        nx[j] = diffuse ? 0.f : normal.x, ny[j] = diffuse ? 0.f : normal.y, nz[j] = diffuse ? 1.f : normal.z;
        if constexpr (!Defer) {
            const MicrofacetTerms t = beckmann_terms(alpha[j], wi, wo);
            D[j] = t.D, g_i[j] = t.g_i, g_o[j] = t.g;
        }
    }
    with_flags([&](auto plastic) {
        rough_samples<Microfacet::StoredOnly, Defer, decltype(plastic)::value>(b, r, ws, u1s, ux, uy, nx, ny, nz, D, g_i, g_o);
    }, r.plastic);
}

/// Copy what the next bounce reads of lane `from` of `a` to lane `to` of `b`. (compact_lanes()
/// moves the same columns: a column added here goes there too.)
RBPT_INLINE void move_lane(const Batch &a, int from, Batch &b, int to) {
    b.ox[to] = a.ox[from], b.oy[to] = a.oy[from], b.oz[to] = a.oz[from];
    b.dx[to] = a.dx[from], b.dy[to] = a.dy[from], b.dz[to] = a.dz[from];
    b.tmin[to] = a.tmin[from], b.tmax[to] = a.tmax[from];
    b.Lr[to] = a.Lr[from], b.Lg[to] = a.Lg[from], b.Lb[to] = a.Lb[from];
    b.br[to] = a.br[from], b.bg[to] = a.bg[from], b.bb[to] = a.bb[from];
    b.rr_r[to] = a.rr_r[from], b.rr_g[to] = a.rr_g[from], b.rr_b[to] = a.rr_b[from];
    b.eta[to] = a.eta[from], b.prev_pdf[to] = a.prev_pdf[from];
    b.prev_px[to] = a.prev_px[from], b.prev_py[to] = a.prev_py[from], b.prev_pz[to] = a.prev_pz[from];
    b.prev_delta[to] = a.prev_delta[from];
    b.state[to] = a.state[from], b.inc[to] = a.inc[from];
    b.seq[to] = a.seq[from];
    b.depth[to] = a.depth[from];
}

/// Move the lanes of [0, n) whose path goes on (`alive`) to the front, in order: what the
/// next bounce reads, as move_lane() copies it. Returns their number. (simd::compact_columns:
/// with AVX-512 and AVX2 a vector of lanes of a column at a time.)
int compact_lanes(Batch &b, int n) {
    uint32_t *const words[] = {
        reinterpret_cast<uint32_t *>(b.ox), reinterpret_cast<uint32_t *>(b.oy), reinterpret_cast<uint32_t *>(b.oz),
        reinterpret_cast<uint32_t *>(b.dx), reinterpret_cast<uint32_t *>(b.dy), reinterpret_cast<uint32_t *>(b.dz),
        reinterpret_cast<uint32_t *>(b.tmin), reinterpret_cast<uint32_t *>(b.tmax),
        reinterpret_cast<uint32_t *>(b.Lr), reinterpret_cast<uint32_t *>(b.Lg), reinterpret_cast<uint32_t *>(b.Lb),
        reinterpret_cast<uint32_t *>(b.br), reinterpret_cast<uint32_t *>(b.bg), reinterpret_cast<uint32_t *>(b.bb),
        reinterpret_cast<uint32_t *>(b.rr_r), reinterpret_cast<uint32_t *>(b.rr_g), reinterpret_cast<uint32_t *>(b.rr_b),
        reinterpret_cast<uint32_t *>(b.eta), reinterpret_cast<uint32_t *>(b.prev_pdf),
        reinterpret_cast<uint32_t *>(b.prev_px), reinterpret_cast<uint32_t *>(b.prev_py), reinterpret_cast<uint32_t *>(b.prev_pz),
        reinterpret_cast<uint32_t *>(b.prev_delta), reinterpret_cast<uint32_t *>(b.seq), reinterpret_cast<uint32_t *>(b.depth)};
    uint64_t *const doubles[] = {b.state, b.inc};
    return simd::compact_columns(words, doubles, b.alive, n);
}

/// Lane k's path state, as path_li holds it.
PathState<RGB<float>> load_path(const Batch &b, int k) {
    PathState<RGB<float>> path;
    path.L = {b.Lr[k], b.Lg[k], b.Lb[k]};
    path.beta = {b.br[k], b.bg[k], b.bb[k]};
    path.beta_rr = {b.rr_r[k], b.rr_g[k], b.rr_b[k]};
    path.eta = b.eta[k];
    path.prev_pdf = b.prev_pdf[k];
    path.prev_delta = b.prev_delta[k];
    path.prev_p = {b.prev_px[k], b.prev_py[k], b.prev_pz[k]};
    return path;
}

/// Store a ray and its path's stream into lane k.
void store_ray(Batch &b, int k, const Ray &ray, const Sampler &sampler) {
    b.ox[k] = ray.o.x, b.oy[k] = ray.o.y, b.oz[k] = ray.o.z;
    b.dx[k] = ray.d.x, b.dy[k] = ray.d.y, b.dz[k] = ray.d.z;
    b.tmin[k] = ray.tmin, b.tmax[k] = ray.tmax;
    b.state[k] = sampler.pcg_state();
    b.inc[k] = sampler.pcg_inc();
}

/// Store a path state, its next ray and its stream into lane k.
void store_path(Batch &b, int k, const PathState<RGB<float>> &path, const Ray &ray, const Sampler &sampler) {
    b.Lr[k] = path.L[0], b.Lg[k] = path.L[1], b.Lb[k] = path.L[2];
    b.br[k] = path.beta[0], b.bg[k] = path.beta[1], b.bb[k] = path.beta[2];
    b.rr_r[k] = path.beta_rr[0], b.rr_g[k] = path.beta_rr[1], b.rr_b[k] = path.beta_rr[2];
    b.eta[k] = path.eta;
    b.prev_pdf[k] = path.prev_pdf;
    b.prev_delta[k] = path.prev_delta;
    b.prev_px[k] = path.prev_p.x, b.prev_py[k] = path.prev_p.y, b.prev_pz[k] = path.prev_p.z;
    store_ray(b, k, ray, sampler);
}

/// The perspective sensor's rays of samples [0, n) into lanes [first, first + n) of the batch,
/// and their film positions: what Camera::sample_position and Camera::sample_ray compute, in
/// SIMD lanes, from the numbers (ux, uy) each sample's sampler drew for its position and the
/// stream it goes on with (state, inc).
void camera_stage(Batch &b, int first, const WavefrontSample *samples, int n, const Camera &camera, Vec2 *pos,
                  const float *ux, const float *uy, const uint64_t *state, const uint64_t *inc) {
    const Camera cam = camera;  // a local: the loop's stores cannot alias it
#pragma GCC ivdep
    for (int i = 0; i < n; ++i) {
        const ptrdiff_t k = ptrdiff_t(first) + i;  // (an int sum, which may wrap, is not affine to GCC)
        Vec2 p{float(samples[i].px) + ux[i], float(samples[i].py) + uy[i]};
        pos[i].x = p.x, pos[i].y = p.y;
        Ray ray = cam.perspective_ray(p);
        b.ox[k] = ray.o.x, b.oy[k] = ray.o.y, b.oz[k] = ray.o.z;
        b.dx[k] = ray.d.x, b.dy[k] = ray.d.y, b.dz[k] = ray.d.z;
        b.tmin[k] = ray.tmin, b.tmax[k] = ray.tmax;
        b.state[k] = state[i];
        b.inc[k] = inc[i];
    }
}

/// The independent sampler's streams of samples [0, n) and the two numbers each draws first,
/// the position in its pixel (Sampler's stream set-up and two uniforms), in SIMD lanes.
void first_draws(const WavefrontSample *samples, int n, float *ux, float *uy, uint64_t *state, uint64_t *inc) {
#pragma GCC ivdep
    for (int i = 0; i < n; ++i) {
        uint64_t st, in;
        pcg32_seed(samples[i].seed.stream, uint64_t(samples[i].s), &st, &in);
        ux[i] = uniform_float(pcg32_next(st, in));
        uy[i] = uniform_float(pcg32_next(st, in));
        state[i] = st, inc[i] = in;
    }
}

/// The same for the other samplers (WavefrontScene::predrawn), by SamplerColumns, their
/// samplers into parts[0, n).
void first_draws(const WavefrontSample *samples, int n, const SamplerDesc &desc, SamplerColumns &columns,
                 Sampler::Parts *parts, float *ux, float *uy) {
    alignas(64) uint64_t keys[B];
    for (int i = 0; i < n; ++i) {
        keys[i] = samples[i].seed.stream;
        columns.seq[i] = samples[i].seed.sequence;
        columns.index[i] = uint32_t(samples[i].s);
    }
    columns.begin(desc, n, keys);
    columns.next_2d(desc, n, nullptr, ux, uy);
    for (int i = 0; i < n; ++i) parts[i] = columns.get(i);
}

/// An interaction's columns of lane k: the point, its error bound and the geometric normal,
/// and the shading frame of normal ns (Frame's constructor, written out) with wi = to_local(-d).
RBPT_INLINE void store_interaction(Batch &b, int k, const Vec3 &p, const Vec3 &p_error, const Vec3 &gn, const Vec3 &ns) {
    float fsign = std::copysign(1.f, ns.z);
    float fa = -1.f / (fsign + ns.z), fb = ns.x * ns.y * fa;
    Vec3 fs{1.f + fsign * ns.x * ns.x * fa, fsign * fb, -fsign * ns.x};
    Vec3 ft{fb, fsign + ns.y * ns.y * fa, -ns.y};
    Vec3 wi{b.dx[k] * -1.f, b.dy[k] * -1.f, b.dz[k] * -1.f};
    b.px[k] = p.x, b.py[k] = p.y, b.pz[k] = p.z;
    b.ex[k] = p_error.x, b.ey[k] = p_error.y, b.ez[k] = p_error.z;
    b.nx[k] = gn.x, b.ny[k] = gn.y, b.nz[k] = gn.z;
    b.sx[k] = fs.x, b.sy[k] = fs.y, b.sz[k] = fs.z;
    b.tx[k] = ft.x, b.ty[k] = ft.y, b.tz[k] = ft.z;
    b.fx[k] = ns.x, b.fy[k] = ns.y, b.fz[k] = ns.z;
    b.wix[k] = dot(wi, fs), b.wiy[k] = dot(wi, ft), b.wiz[k] = dot(wi, ns);
}

/// Geometry::interaction's sphere branch for the lanes listed in list[0, m) (rays that hit a
/// sphere), in SIMD lanes over the list: the hit re-projected onto the sphere in double
/// precision, its normal, and with UV its uv where a texture reads it (spherical coordinates
/// in the sphere's frame, sphere_uv as Geometry::interaction's). The rays are
/// packed and the results computed into packed columns (the list padded to whole vectors),
/// then moved to the lanes one at a time (AVX2 has no scatter).
template <bool UV>
void sphere_interactions(Batch &b, int *list, int m, uint32_t n_triangles, const WavefrontScene &ws) {
    constexpr int B = WavefrontBatch;
    const Vec3 *centers = ws.sphere_center.data();
    const Vec3 *sphere_x = ws.sphere_x.data(), *sphere_y = ws.sphere_y.data(), *sphere_z = ws.sphere_z.data();
    const float *radii = ws.sphere_radius.data(), *signs = ws.sphere_sign.data();
    const int *reads_uv = ws.sphere_uv.data();
    // The listed lanes' rays and spheres, packed.
    alignas(64) float ox[B], oy[B], oz[B], dx[B], dy[B], dz[B], ht[B];
    alignas(64) int sphere[B];
    const int padded = simd::pad_indices(list, m);
    for (int j = 0; j < padded; ++j) {
        const int k = list[j];
        ox[j] = b.ox[k], oy[j] = b.oy[k], oz[j] = b.oz[k], dx[j] = b.dx[k], dy[j] = b.dy[k], dz[j] = b.dz[k];
        ht[j] = b.ht[k], sphere[j] = int(b.prim[k] - n_triangles);
    }
    alignas(64) float px[B], py[B], pz[B], ex[B], ey[B], ez[B], nx[B], ny[B], nz[B], su[B], sv[B];
#pragma GCC ivdep
    for (int j = 0; j < padded; ++j) {
        const int a = sphere[j];
        const float radius = radii[a];
        const Vec3 c{centers[a].x, centers[a].y, centers[a].z};
        double t = ht[j];
        double r0 = double(ox[j]) + double(dx[j]) * t - double(c.x);
        double r1 = double(oy[j]) + double(dy[j]) * t - double(c.y);
        double r2 = double(oz[j]) + double(dz[j]) * t - double(c.z);
        double scale = double(radius) / std::sqrt(r0 * r0 + r1 * r1 + r2 * r2);
        Vec3 sp{float(double(c.x) + r0 * scale), float(double(c.y) + r1 * scale), float(double(c.z) + r2 * scale)};
        Vec3 sp_error = gamma(4) * vabs(sp) + Vec3(1, 1, 1) * (gamma(4) * radius);
        Vec3 local = normalize(Vec3{float(r0 * scale), float(r1 * scale), float(r2 * scale)});
        Vec3 sn = local * signs[a];
        if constexpr (UV) {
            const Vec2 uv = sphere_uv({dot(local, sphere_x[a]), dot(local, sphere_y[a]), dot(local, sphere_z[a])});
            su[j] = uv.x, sv[j] = uv.y;
        }
        px[j] = sp.x, py[j] = sp.y, pz[j] = sp.z;
        ex[j] = sp_error.x, ey[j] = sp_error.y, ez[j] = sp_error.z;
        nx[j] = sn.x, ny[j] = sn.y, nz[j] = sn.z;
    }
    for (int j = 0; j < m; ++j) {
        const int k = list[j];
        const Vec3 sn{nx[j], ny[j], nz[j]};
        store_interaction(b, k, {px[j], py[j], pz[j]}, {ex[j], ey[j], ez[j]}, sn, sn);
        // (Its uv where it is read, as Geometry::interaction's: selected here, as both selects
        // in the loop above stop GCC 12 from vectorising it.)
        const bool read = UV && reads_uv[sphere[j]] != 0;
        b.uvx[k] = read ? su[j] : 0.f, b.uvy[k] = read ? sv[j] : 0.f;
        b.done[k] = 1;
    }
}

/// Whether the vector loops read the fields they gather with word_of(): only where GCC
/// gathers in hardware, tuned for Sapphire Rapids (build_flags.host_tuning). Under its other
/// tunings it loads a gather's lanes one by one either way, and the structs' members read as
/// such take fewer instructions (an AVX2 build, MARCH=x86-64-v3 with generic tuning, took 4%
/// longer on the bunny and textured, 1.5% on veach-mis, with the word indices).
#if defined(__tune_sapphirerapids__)
#define RBPT_GATHER_WORDS 1
#else
#define RBPT_GATHER_WORDS 0
#endif

/// Word `word` of element i of `array` (structs of whole 4-byte words), read at the signed
/// 32-bit index sizeof(T) / 4 i + word, which GCC gathers in hardware: indexed as T, the
/// offsets are 64-bit and GCC loads them lane by lane.
template <typename Word, typename T>
RBPT_INLINE Word word_of(const T *array, int i, int word) {
    static_assert(sizeof(T) % 4 == 0 && sizeof(Word) == 4, "structs of whole words");
    return reinterpret_cast<const Word *>(array)[int(sizeof(T) / 4) * i + word];
}

/// Geometry::interaction's triangle branch for the lanes [0, n) whose ray hit a triangle
/// (`done`), in SIMD lanes over all lanes of a scene that has triangles: the others compute
/// numbers nothing reads (spheres' are overwritten, and the shade stage completes the rest).
/// Vertex normals and uv, whose gathers are much of its cost, only in scenes that have them
/// (Normals, UV).
template <bool Normals, bool UV>
RBPT_INLINE void triangle_interactions(Batch &b, int n, const Geometry &g, const WavefrontScene &ws) {
    const Triangle *triangles = g.triangles.data();
    const Vec3 *positions = g.positions.data(), *normals = g.normals.data();
    const Vec2 *uvs = g.uvs.data();
    const int *flags = ws.triangle_flags.data();
    const uint32_t n_triangles = uint32_t(g.triangles.size());
    using F = WavefrontScene::ShapeFlag;
#if RBPT_GATHER_WORDS
    // (Vertices and triangles read at 32-bit word indices: word_of().)
    auto vertex = [](const Vec3 *array, int v) __attribute__((always_inline)) {
        return Vec3{word_of<float>(array, v, 0), word_of<float>(array, v, 1), word_of<float>(array, v, 2)};
    };
    constexpr int N = int(offsetof(Triangle, n) / 4);  // (the face normal's first word)
#endif
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        // (Signed 32-bit indices: GCC gathers with unsigned ones only through 64-bit indices,
        // two instructions per vector, and for some gathers not at all.)
        const int t = int(std::min(b.prim[k], n_triangles - 1));  // (a select would select addresses)
        const int flag = flags[t];
        float b1 = b.hu[k], b2 = b.hv[k], b0 = 1.f - b1 - b2;
#if RBPT_GATHER_WORDS
        const int v0 = int(word_of<uint32_t>(triangles, t, 0)), v1 = int(word_of<uint32_t>(triangles, t, 1));
        const int v2 = int(word_of<uint32_t>(triangles, t, 2));
        const Vec3 p0 = vertex(positions, v0), p1 = vertex(positions, v1), p2 = vertex(positions, v2);
        const Vec3 face_n{word_of<float>(triangles, t, N), word_of<float>(triangles, t, N + 1), word_of<float>(triangles, t, N + 2)};
        auto vertex_normal = [&](int v) __attribute__((always_inline)) { return vertex(normals, v); };
#else
        const Triangle &tri = triangles[t];
        const int v0 = int(tri.v[0]), v1 = int(tri.v[1]), v2 = int(tri.v[2]);
        const Vec3 &p0 = positions[v0], &p1 = positions[v1], &p2 = positions[v2];
        const Vec3 face_n{tri.n.x, tri.n.y, tri.n.z};
        auto vertex_normal = [&](int v) __attribute__((always_inline)) -> const Vec3 & { return normals[v]; };
#endif
        Vec3 p = p0 * b0 + p1 * b1 + p2 * b2;
        Vec3 p_error = gamma(7) * (vabs(p0 * b0) + vabs(p1 * b1) + vabs(p2 * b2));
        // The shading normal: the vertex normals interpolated, or the face's; both flipped
        // with flip_normals (as a product with -1: exact).
        Vec3 ns = face_n;
        if constexpr (Normals) {
            Vec3 vn = normalize(vertex_normal(v0) * b0 + vertex_normal(v1) * b1 + vertex_normal(v2) * b2);
            ns = select((flag & F::HasNormals) != 0, vn, face_n);
        }
        float sign = (flag & F::FlipNormals) != 0 ? -1.f : 1.f;
        Vec3 gn = face_n * sign;
        ns = ns * sign;
        b.done[k] = b.prim[k] < n_triangles;
        // uv: the vertices' texture coordinates, or the barycentrics, where a texture reads it.
        if constexpr (UV) {
            // (Interpolated before the select: loads under a condition become masked gathers,
            // which GCC does not emit for AVX2.)
            const Vec2 &t0 = uvs[v0], &t1 = uvs[v1], &t2 = uvs[v2];
            float tu = t0.x * b0 + t1.x * b1 + t2.x * b2, tv = t0.y * b0 + t1.y * b1 + t2.y * b2;
            float u = (flag & F::HasUVs) != 0 ? tu : b1;
            float v = (flag & F::HasUVs) != 0 ? tv : b2;
            b.uvx[k] = (flag & F::NeedsUV) != 0 ? u : 0.f;
            b.uvy[k] = (flag & F::NeedsUV) != 0 ? v : 0.f;
        } else {
            b.uvx[k] = b.uvy[k] = 0.f;
        }
        store_interaction(b, k, p, p_error, gn, ns);
    }
}

/// Geometry::interaction's triangle and sphere branches for the lanes [0, n) whose ray hit a
/// triangle or a sphere; `done` marks them. The triangles in lanes (triangle_interactions;
/// their indices are clamped to the last triangle, so a scene of spheres alone has none to
/// gather), the spheres over the list of their lanes (sphere_interactions).
template <bool Normals, bool UV>
void interaction_stage(Batch &b, int n, const Geometry &g, const WavefrontScene &ws) {
    const uint32_t n_triangles = uint32_t(g.triangles.size());
    if (n_triangles > 0) triangle_interactions<Normals, UV>(b, n, g, ws);
    else std::fill_n(b.done, n, 0);
    if (!ws.any_spheres) return;
    // The lanes whose ray hit a sphere (the analytic primitive's index clamped, as the
    // triangle's).
    const uint32_t n_analytic = uint32_t(ws.is_sphere.size()), n_prims = n_triangles + n_analytic;
    const int *is_sphere = ws.is_sphere.data();
    alignas(64) int on_sphere[WavefrontBatch], list[WavefrontBatch];
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const int a = int(std::min(std::max(b.prim[k], n_triangles) - n_triangles, n_analytic - 1));
        float sphere = b.prim[k] >= n_triangles ? 1.f : 0.f;  // (no &&: see vertex_stage)
        sphere = is_sphere[a] != 0 ? sphere : 0.f;
        sphere = b.prim[k] < n_prims ? sphere : 0.f;
        on_sphere[k] = sphere != 0.f ? 1 : 0;
    }
    const int m = simd::select_indices(on_sphere, n, 1, list);
    if (ws.any_sphere_uv) sphere_interactions<true>(b, list, m, n_triangles, ws);
    else sphere_interactions<false>(b, list, m, n_triangles, ws);
}

/// The instance of interaction_stage for a scene's shapes.
using InteractionStage = void (*)(Batch &, int, const Geometry &, const WavefrontScene &);
InteractionStage interaction_stage_for(const WavefrontScene &ws) {
    return with_flags([](auto normals, auto uv) -> InteractionStage {
        return interaction_stage<decltype(normals)::value, decltype(uv)::value>;
    }, ws.any_normals, ws.any_uv);
}

/// Bitmap::wrap_pair in lanes: the texel indices i and i + 1 wrapped into [0, n). The
/// remainder of i by the wrap's period from a float quotient (exact for |i| < 2^24, the
/// quotient's rounding corrected), as GCC does not vectorise an integer division.
template <WrapMode Wrap>
RBPT_INLINE void wrap_pair_lanes(int i, int n, int &w0, int &w1) {
    if constexpr (Wrap == WrapMode::Clamp) {
        w0 = std::clamp(i, 0, n - 1), w1 = std::clamp(i, -1, n - 2) + 1;
    } else {
        const int period = Wrap == WrapMode::Repeat ? n : 2 * n;
        const int q = int(std::floor(float(i) / float(period)));
        int r = i - q * period;
        r = r < 0 ? r + period : r;
        r = r >= period ? r - period : r;
        const int r1 = r + 1 == period ? 0 : r + 1;
        w0 = r < n ? r : period - 1 - r;  // (mirrored in the period's second half)
        w1 = r1 < n ? r1 : period - 1 - r1;
    }
}

/// A recorded input rho of lane k (WavefrontVertex `v`, Input) whose channels include zeros:
/// those channels taken as 1 in the path's throughput (WavefrontVertex::unit), the roulette
/// throughput as path_li's roulette_factor has it: zero in those channels, or, where every
/// channel is zero, the factor 1, which the diffuse weight rho (now 1) is. A dielectric's
/// rho (whose branch's record may go unused) and a mirror's or rough conductor's of three
/// zero channels (whose weights hold other factors) are left as they are: render_bwd gives
/// their samples to the tape.
RBPT_INLINE void unit_zero_inputs(Batch &b, int k, WavefrontVertex &v, WavefrontScene::Lane lane) {
    const int zeros = (v.value[0] == 0.f) + (v.value[1] == 0.f) + (v.value[2] == 0.f);
    if (zeros == 0 || lane == WavefrontScene::Glass || (zeros == 3 && lane != WavefrontScene::Diffuse)) return;
    float *a[3] = {b.ar, b.ag, b.ab}, *rr[3] = {b.rr_r, b.rr_g, b.rr_b};
    for (int c = 0; c < 3; ++c) {
        if (v.value[c] != 0.f) continue;
        a[c][k] = 1.f;
        if (zeros < 3) rr[c][k] = 0.f;
    }
    v.unit = true;
}

/// The lookups of bitmap `bm` for the lanes [0, n) of its material that the vector stage
/// shades (shade 1): eval_bitmap()'s bilinear lookup and Params::gather()'s sum, operation
/// for operation, in SIMD lanes over the list of those lanes (padded to whole vectors), into
/// their reflectance a. A lane whose texel coordinates reach 2^22 in size, or are not finite,
/// is left to the shade stage's own code (shade 0). With Record (the backward pass
/// differentiates the bitmap), each lookup is kept as the WavefrontVertex the shade stage's
/// own code keeps: the radiance before the vertex, the value, and the read (the four texels'
/// offsets and weights, as Params::bilinear logs them), its zero channels taken as 1 as
/// there (unit_zero_inputs).
template <WrapMode Wrap, bool Record>
void bitmap_stage(Batch &b, int n, const WavefrontScene::BitmapLookup &bm, WavefrontRecord *record) {
    constexpr int B = WavefrontBatch;
    alignas(64) int on[B], list[B];
    const int material = bm.material;
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) on[k] = b.shade[k] != 0 && b.mat[k] == material ? 1 : 0;
    const int m = simd::select_indices(on, n, 1, list);
    if (m == 0) return;
    const int padded = simd::pad_indices(list, m);
    alignas(64) float u[B], v[B], ar[B], ag[B], ab[B], ok[B];
    alignas(64) int read_t[4][B];  // (Record: the texels' offsets and weights)
    alignas(64) float read_w[4][B];
    for (int j = 0; j < padded; ++j) u[j] = b.uvx[list[j]], v[j] = b.uvy[list[j]];
    const float *texels = bm.texels;
    const int width = bm.width, height = bm.height, channels = bm.channels;
    const float to_uv = bm.has_to_uv ? 1.f : 0.f;  // (a float flag: see vertex_stage)
    const float m00 = bm.to_uv[0][0], m01 = bm.to_uv[0][1], m02 = bm.to_uv[0][2];
    const float m10 = bm.to_uv[1][0], m11 = bm.to_uv[1][1], m12 = bm.to_uv[1][2];
    // (Three channels, or one for all three: the texel's stride and its channels' offsets.)
    const int g_off = channels == 3 ? 1 : 0, b_off = channels == 3 ? 2 : 0;
#pragma GCC ivdep
    for (int j = 0; j < padded; ++j) {
        // Texture::map_uv, then eval_bitmap's texel coordinates and weights.
        const float mu = m00 * u[j] + m01 * v[j] + m02, mv = m10 * u[j] + m11 * v[j] + m12;
        float x = (to_uv != 0.f ? mu : u[j]) * float(width), y = (to_uv != 0.f ? mv : v[j]) * float(height);
        x -= 0.5f;
        y -= 0.5f;
        float inside = std::abs(x) < 4194304.f ? 1.f : 0.f;
        inside = std::abs(y) < 4194304.f ? inside : 0.f;
        x = inside != 0.f ? x : 0.f, y = inside != 0.f ? y : 0.f;
        const float fx = std::floor(x), fy = std::floor(y);
        const float wx1 = x - fx, wy1 = y - fy, wx0 = 1.f - wx1, wy0 = 1.f - wy1;
        int i0, i1, j0, j1;
        wrap_pair_lanes<Wrap>(int(fx), width, i0, i1);
        wrap_pair_lanes<Wrap>(int(fy), height, j0, j1);
        const int t0 = (j0 * width + i0) * channels, t1 = (j0 * width + i1) * channels;
        const int t2 = (j1 * width + i0) * channels, t3 = (j1 * width + i1) * channels;
        const float w0 = wx0 * wy0, w1 = wx1 * wy0, w2 = wx0 * wy1, w3 = wx1 * wy1;
        // Params::gather's sum, from zero, texel by texel.
        ar[j] = (((0.f + w0 * texels[t0]) + w1 * texels[t1]) + w2 * texels[t2]) + w3 * texels[t3];
        ag[j] = (((0.f + w0 * texels[t0 + g_off]) + w1 * texels[t1 + g_off]) + w2 * texels[t2 + g_off]) + w3 * texels[t3 + g_off];
        ab[j] = (((0.f + w0 * texels[t0 + b_off]) + w1 * texels[t1 + b_off]) + w2 * texels[t2 + b_off]) + w3 * texels[t3 + b_off];
        ok[j] = inside;
        if constexpr (Record) {
            read_t[0][j] = t0, read_t[1][j] = t1, read_t[2][j] = t2, read_t[3][j] = t3;
            read_w[0][j] = w0, read_w[1][j] = w1, read_w[2][j] = w2, read_w[3][j] = w3;
        }
    }
    for (int j = 0; j < m; ++j) {
        const int k = list[j];
        b.ar[k] = ar[j], b.ag[k] = ag[j], b.ab[k] = ab[j];
        b.shade[k] = ok[j] != 0.f ? 1 : 0;
        if (!Record || ok[j] == 0.f) continue;
        ParamRead read;
        read.param = bm.param, read.channels = channels, read.n = 4;
        for (int i = 0; i < 4; ++i) read.offset[i] = read_t[i][j], read.weight[i] = read_w[i][j];
        record->add(b.seq[k], WavefrontVertex::Input, b.Lr[k], b.Lg[k], b.Lb[k], ar[j], ag[j], ab[j], read);
        b.record_reflect[k] = int(record->vertices.size()) - 1;
        unit_zero_inputs(b, k, record->vertices.back(), WavefrontScene::Lane(bm.lane));
    }
}

/// The shade stage for the lanes whose vertex needs only lookups in lanes
/// (WavefrontScene::prim_quick): shaded by the vector stage (shade 1) with the inputs of
/// its material, constants or a bitmap's (bitmap_stage); the other lanes get shade 0, for
/// the shade stage's own code.
void quick_shade_stage(Batch &b, int n, const WavefrontScene &ws, WavefrontRecord *record) {
    const int *material = ws.prim_material.data(), *quick = ws.prim_quick.data();
    const WavefrontScene::Material *mats = ws.materials.data();
    // (A material's constant inputs read at 32-bit word indices where GCC gathers, word_of():
    // cornell-box, the cbox and textured 1-1.5% faster than indexed as Materials.)
    using M = WavefrontScene::Material;
    [[maybe_unused]] constexpr int A = int(offsetof(M, ar) / 4), T = int(offsetof(M, tr) / 4);  // (RBPT_GATHER_WORDS)
    static_assert(offsetof(M, ag) == offsetof(M, ar) + 4 && offsetof(M, ab) == offsetof(M, ar) + 8 &&
                  offsetof(M, tg) == offsetof(M, tr) + 4 && offsetof(M, tb) == offsetof(M, tr) + 8,
                  "a material's channels are consecutive words");
    const uint32_t n_prims = uint32_t(ws.prim_material.size());
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        // (An escaped ray's ~0 clamped, and both loaded unconditionally: GCC turns a select of
        // indices into one of addresses, and a conditional load into a masked gather, which it
        // does not emit for AVX2.)
        const int p = int(std::min(b.prim[k], n_prims - 1));
        const int m = material[p], q = quick[p];
        b.mat[k] = m;
        b.shade[k] = b.prim[k] < n_prims && b.done[k] != 0 ? q : 0;
        b.record_rough[k] = b.record_alpha[k] = b.record_reflect[k] = b.record_refract[k] = -1;
#if RBPT_GATHER_WORDS
        b.ar[k] = word_of<float>(mats, m, A), b.ag[k] = word_of<float>(mats, m, A + 1), b.ab[k] = word_of<float>(mats, m, A + 2);
        b.tr[k] = word_of<float>(mats, m, T), b.tg[k] = word_of<float>(mats, m, T + 1), b.tb[k] = word_of<float>(mats, m, T + 2);
#else
        const WavefrontScene::Material &mat = mats[m];
        b.ar[k] = mat.ar, b.ag[k] = mat.ag, b.ab[k] = mat.ab;
        b.tr[k] = mat.tr, b.tg[k] = mat.tg, b.tb[k] = mat.tb;
#endif
    }
    for (const WavefrontScene::BitmapLookup &bm : ws.bitmaps) {
        with_flags([&](auto recorded) {
            constexpr bool Record = decltype(recorded)::value;
            switch (bm.wrap) {
                case WrapMode::Repeat: return bitmap_stage<WrapMode::Repeat, Record>(b, n, bm, record);
                case WrapMode::Mirror: return bitmap_stage<WrapMode::Mirror, Record>(b, n, bm, record);
                case WrapMode::Clamp: return bitmap_stage<WrapMode::Clamp, Record>(b, n, bm, record);
            }
        }, bm.record && record);
    }
}

/// The paths of lanes [0, n) whose ray escaped, but for those at their last vertex (`last`
/// 1: the shade loop's), end here in SIMD lanes, with the emission of the `constant`
/// environment if the scene has one (`sky`: its radiance Le, and em_pdf, the density of its
/// emitter samples: emission_found()'s operations, the throughput 1 for a camera ray,
/// nothing for one with `hide`): unshaded, and marked in `ended` (1, else 0) for the shade
/// loop to pass over. (Renders without a parameter log: the shade loop keeps the emission
/// records.) Open scenes' paths mostly end so (spheres under the sky: 2.4 rays per sample).
void sky_stage(Batch &b, int n, bool sky, const Color3f &Le, float em_pdf, bool hide, int max_depth, int *ended) {
    const float on = sky ? 1.f : 0.f, hidden_at_0 = hide ? 1.f : 0.f;
    const float Lr = Le.v[0], Lg = Le.v[1], Lb = Le.v[2];
    const int last_from = max_depth >= 0 ? max_depth : INT_MAX;  // (depth + 1 >= it: the last vertex)
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const int escaped = b.prim[k] == ~0u ? 1 : 0;
        const int end = escaped != 0 && b.depth[k] + 1 < last_from ? 1 : 0;
        const bool camera = b.depth[k] == 0;
        const float add = end != 0 ? (camera ? on * (1.f - hidden_at_0) : on) : 0.f;
        const float w = mis_weight(b.prev_pdf[k], b.prev_delta[k] != 0 ? 0.f : em_pdf);
        const float br = camera ? 1.f : b.br[k], bg = camera ? 1.f : b.bg[k], bb = camera ? 1.f : b.bb[k];
        b.Lr[k] = add != 0.f ? b.Lr[k] + br * Lr * w : b.Lr[k];
        b.Lg[k] = add != 0.f ? b.Lg[k] + bg * Lg * w : b.Lg[k];
        b.Lb[k] = add != 0.f ? b.Lb[k] + bb * Lb * w : b.Lb[k];
        b.shade[k] = end != 0 ? 0 : b.shade[k];
        b.mat[k] = end != 0 ? 0 : b.mat[k];
        b.record_rough[k] = end != 0 ? -1 : b.record_rough[k];
        b.record_alpha[k] = end != 0 ? -1 : b.record_alpha[k];
        ended[k] = end;
    }
}

/// Lane k's surface interaction, from its columns.
SurfaceInteraction load_interaction(const Batch &b, int k, const Geometry &g) {
    SurfaceInteraction si;
    si.valid = true;
    si.t = b.ht[k];
    si.p = {b.px[k], b.py[k], b.pz[k]};
    si.p_error = {b.ex[k], b.ey[k], b.ez[k]};
    si.n = {b.nx[k], b.ny[k], b.nz[k]};
    si.sh_frame.s = {b.sx[k], b.sy[k], b.sz[k]};
    si.sh_frame.t = {b.tx[k], b.ty[k], b.tz[k]};
    si.sh_frame.n = {b.fx[k], b.fy[k], b.fz[k]};
    si.uv = {b.uvx[k], b.uvy[k]};
    si.wi = {b.wix[k], b.wiy[k], b.wiz[k]};
    si.shape = int(g.shape_of(b.prim[k]));
    if (g.is_triangle(b.prim[k])) {
        si.tri = b.prim[k];
        si.b1 = b.hu[k];
        si.b2 = b.hv[k];
    }
    return si;
}

/// Store a surface interaction into lane k's columns.
void store_interaction(Batch &b, int k, const SurfaceInteraction &si) {
    b.px[k] = si.p.x, b.py[k] = si.p.y, b.pz[k] = si.p.z;
    b.ex[k] = si.p_error.x, b.ey[k] = si.p_error.y, b.ez[k] = si.p_error.z;
    b.nx[k] = si.n.x, b.ny[k] = si.n.y, b.nz[k] = si.n.z;
    const Frame &f = si.sh_frame;
    b.sx[k] = f.s.x, b.sy[k] = f.s.y, b.sz[k] = f.s.z;
    b.tx[k] = f.t.x, b.ty[k] = f.t.y, b.tz[k] = f.t.z;
    b.fx[k] = f.n.x, b.fy[k] = f.n.y, b.fz[k] = f.n.z;
    b.wix[k] = si.wi.x, b.wiy[k] = si.wi.y, b.wiz[k] = si.wi.z;
    b.uvx[k] = si.uv.x, b.uvy[k] = si.uv.y;
}

/// The batch's rays as the BVH's columns.
RBPT_INLINE RayColumns ray_columns(const Batch &b) {
    return {b.ox, b.oy, b.oz, b.dx, b.dy, b.dz, b.tmin, b.tmax};
}
/// Lane k's ray.
RBPT_INLINE Ray load_ray(const Batch &b, int k) { return ray_columns(b).ray(k); }

/// The closest hits of lanes [0, n) whose rays enter one of `boxes`, as intersect_columns()
/// finds them (its answer for a ray does not depend on the other rays it takes); the others
/// get none (prim ~0u). Returns how many it traced.
int trace_reaching(Batch &b, int n, const ShapeBoxes &boxes, const BVH &bvh) {
    alignas(64) int enters[B], lanes[B];
    boxes.entered(ray_columns(b), n, enters);
    const int m = simd::select_indices(enters, n, 1, lanes);
    alignas(64) float ox[B], oy[B], oz[B], dx[B], dy[B], dz[B], tmin[B], tmax[B], t[B], u[B], v[B];
    alignas(64) uint32_t prim[B];
    for (int j = 0; j < m; ++j) {
        const int k = lanes[j];
        ox[j] = b.ox[k], oy[j] = b.oy[k], oz[j] = b.oz[k], dx[j] = b.dx[k], dy[j] = b.dy[k], dz[j] = b.dz[k];
        tmin[j] = b.tmin[k], tmax[j] = b.tmax[k];
    }
    if (m > 0) bvh.intersect_columns({ox, oy, oz, dx, dy, dz, tmin, tmax}, m, {t, u, v, prim});
    for (int k = 0; k < n; ++k) b.prim[k] = ~0u;
    for (int j = 0; j < m; ++j) {
        const int k = lanes[j];
        b.ht[k] = t[j], b.hu[k] = u[j], b.hv[k] = v[j], b.prim[k] = prim[j];
    }
    return m;
}

/// The BSDF samples the rough stages left unevaluated (their Defer: at a vertex whose next is
/// its path's last, without roulette, where only an emitter the sample's ray finds adds
/// anything and trace_reaching() traces only the rays that enter an emitter's box), for the
/// lanes of `r` still alive whose ray enters one: density, weight, throughput and whether
/// the path goes on, as rough_samples() and the vertex stage would have set them. The others
/// keep density and weight 1, by which the vertex stage multiplied their throughputs
/// exactly, and end at the next vertex untraced, as if they had ended here. Images are those
/// of the samples evaluated in the rough stages bit for bit.
template <Microfacet Terms>
void finish_deferred_samples(Batch &b, const RoughLanes &r, const WavefrontScene &ws, const int *enters) {
    // The lanes (their indices in r), and their inputs packed in that order.
    alignas(64) int flag[B], list[B], mat[B];
    for (int j = 0; j < r.count; ++j) flag[j] = enters[r.lanes[j]] != 0 && b.alive[r.lanes[j]] != 0 ? 1 : 0;
    const int m = simd::select_indices(flag, r.count, 1, list);
    if (m == 0) return;
    const int padded = simd::pad_indices(list, m);
    alignas(64) float ar[B], ag[B], ab[B], tr[B], tg[B], tb[B], wix[B], wiy[B], wiz[B], wox[B], woy[B], woz[B];
    for (int i = 0; i < padded; ++i) {
        const int j = list[i], k = r.lanes[j];
        mat[i] = r.mat[j];
        ar[i] = r.ar[j], ag[i] = r.ag[j], ab[i] = r.ab[j], tr[i] = r.tr[j], tg[i] = r.tg[j], tb[i] = r.tb[j];
        wix[i] = r.wix[j], wiy[i] = r.wiy[j], wiz[i] = r.wiz[j];
        wox[i] = b.swx[k], woy[i] = b.swy[k], woz[i] = b.swz[k];
    }
    // Their densities and weights, in lanes (rough_samples()').
    const WavefrontScene::Material *mats = ws.materials.data();
    const float *tables = ws.tables.data();
    alignas(64) float pdf[B], wr[B], wg[B], wb[B];
    with_flags([&](auto plastic) {
#pragma GCC ivdep
        for (int i = 0; i < padded; ++i) {
            const WavefrontScene::Material &material = mats[mat[i]];
            const float a[3] = {ar[i], ag[i], ab[i]}, s[3] = {tr[i], tg[i], tb[i]};
            const Vec3 wi{wix[i], wiy[i], wiz[i]}, wo{wox[i], woy[i], woz[i]};
            MicrofacetTerms terms{};
            if constexpr (Terms == Microfacet::StoredOnly) terms = beckmann_terms(material.alpha, wi, wo);
            const RoughWeight w =
                sample_weight(rough_eval<Terms, decltype(plastic)::value>(material, terms, tables, wi, wo, a, s), wi.z);
            pdf[i] = w.pdf, wr[i] = w.r, wg[i] = w.g, wb[i] = w.b;
        }
    }, r.plastic);
    // What the vertex stage would have set with them.
    for (int i = 0; i < m; ++i) {
        const int k = r.lanes[list[i]];
        const float rr_r = b.rr_r[k] * wr[i], rr_g = b.rr_g[k] * wg[i], rr_b = b.rr_b[k] * wb[i];
        const float beta_max = std::max(rr_r, std::max(rr_g, rr_b));
        b.alive[k] = pdf[i] > 0.f && beta_max > 0.f;
        b.br[k] = b.br[k] * wr[i], b.bg[k] = b.bg[k] * wg[i], b.bb[k] = b.bb[k] * wb[i];
        b.rr_r[k] = rr_r, b.rr_g[k] = rr_g, b.rr_b[k] = rr_b;
        b.prev_pdf[k] = pdf[i];
    }
}

}  // namespace

void trace_wavefront(const RenderContext<RGB<float>> &ctx, const WavefrontScene &ws,
                     const IntegratorSettings &settings, const Camera &camera,
                     const WavefrontSample *samples, int n_samples, Vec2 *pos, RGB<float> *L,
                     WavefrontRecord *record) {
    const Scene &scene = ctx.scene;
    const IntegratorSettings cfg = *path_settings(settings);  // (wavefront_scene() checked it)
    // Recording: reads of differentiated parameters other than a linear input's or an
    // emission's send the path to the tape.
    ParamReadLog *log = record ? ctx.params.log : nullptr;
    if (record) record->tape.assign(size_t(n_samples), 0), record->vertices.clear();
    // Per material: 1 where it is a rough conductor whose roughness the log watches (its
    // records' d log f / d alpha: conductor_dlog_stage).
    std::vector<int> watched_roughness(log ? ws.materials.size() : 0, 0);
    for (size_t m = 0; m < watched_roughness.size(); ++m) {
        const int alpha = scene.bsdfs[m].alpha;
        watched_roughness[m] = ws.materials[m].lane == WavefrontScene::RoughMirror && alpha >= 0 && log->watched[alpha] ? 1 : 0;
    }
    // The batch, and the vertices path_vertex() shades while the vector stage runs (70 kB
    // each: no stack frame of their own), in a buffer of the thread's, reached through one
    // pointer read here. (Bound to thread_locals directly, the stages that take the batch
    // were specialised to its address, and GCC recomputed that with a call of __tls_get_addr
    // after every call they make: 46 such calls in this function, 28 in the Beckmann stage.)
    struct Buffers {
        Batch batch, side;
        int side_lane[B];
        RoughLanes ggx, beckmann;  ///< the rough lanes of each distribution
        /// The samplers other than `independent` of samples [0, n_samples), beyond their
        /// streams (see load_sampler()).
        std::vector<Sampler::Parts> parts;
        SamplerColumns columns;  ///< the batch's samplers of those kinds, in columns (draw_stage)
        /// `direct`'s sub-paths (IntegratorSettings::sub_paths), per sample: its camera ray
        /// and its closest hit, the sub-paths it has finished, and its stream where the last
        /// one ended; and the samples whose next sub-path waits for a drained batch, from
        /// again[again_next] on.
        struct SubPaths {
            Ray camera_ray;
            Hit first_hit;
            int done = 0;
            uint64_t state = 0, inc = 0;
        };
        std::vector<SubPaths> subs;
        std::vector<int> again;
    };
    static thread_local std::unique_ptr<Buffers> buffers_storage;
    if (!buffers_storage) buffers_storage = std::make_unique<Buffers>();
    Buffers &buffers = *buffers_storage;
    Batch &b = buffers.batch, &side = buffers.side;
    if (ws.predrawn && buffers.parts.size() < size_t(n_samples)) buffers.parts.resize(size_t(n_samples));
    Sampler::Parts *const parts = ws.predrawn ? buffers.parts.data() : nullptr;
    int *const side_lane = buffers.side_lane;
    const bool sub_paths = cfg.sub_paths > 1;
    if (sub_paths && buffers.subs.size() < size_t(n_samples)) buffers.subs.resize(size_t(n_samples));
    std::vector<int> &again = buffers.again;
    size_t again_next = 0;
    again.clear();
    RoughLanes &ggx = buffers.ggx, &beckmann = buffers.beckmann;
    // The channels (bits) of radiance parameter p that are zero and that the lanes read as 1
    // (WavefrontRecord::unit_radiance).
    auto radiance_zeros = [&](int p) {
        return !record || record->unit_radiance.empty() || p < 0 ? 0 : int(record->unit_radiance[size_t(p)]);
    };
    // An emission record of radiance parameter p: those channels put back to their true 0
    // (WavefrontVertex::unit).
    auto unit_radiance = [&](WavefrontVertex &v, int p) {
        const int zero = radiance_zeros(p);
        for (int c = 0; c < 3; ++c)
            if (zero >> c & 1) v.value[c] = 0.f, v.unit = true;
    };
    // The emission Le found by lane k's ray, where its radiance read a differentiated
    // parameter (the reads since `reads_before`): kept; returns the reads it accounts for.
    auto emission_read = [&](int k, int reads_before, const Emitter &e, const RGB<float> &Le) {
        if (!log || log->count != reads_before + 1 || log->last.param != e.radiance) return 0;
        RGB<float> radiance = Params<RGB<float>>::value_of(ctx.params.data[size_t(e.radiance)], ctx.params.numel[size_t(e.radiance)]);
        record->add(b.seq[k], WavefrontVertex::Emission, Le[0], Le[1], Le[2], radiance[0], radiance[1], radiance[2], log->last);
        unit_radiance(record->vertices.back(), e.radiance);
        return 1;
    };
    auto unexpected_reads = [&](int k, int reads_before, int expected) {
        if (log && log->count != reads_before + expected) record->tape[size_t(b.seq[k])] = 1;
    };
    // A path at depth 0 in lane k, of sample seq: its throughput (1/n for `direct`'s n
    // sub-paths, after the emission its camera ray finds: found_beta()).
    const float share = 1.f / float(cfg.sub_paths);
    auto reset_lane = [&](int k, int seq) {
        b.br[k] = b.bg[k] = b.bb[k] = share;
        b.rr_r[k] = b.rr_g[k] = b.rr_b[k] = 1.f;
        b.eta[k] = 1.f;
        b.prev_pdf[k] = 1.f;
        b.prev_delta[k] = 1;
        b.prev_px[k] = b.prev_py[k] = b.prev_pz[k] = 0.f;
        b.seq[k] = seq;
        b.depth[k] = 0;
    };
    // Start the paths of samples [next, next + m) in lanes [first, first + m): their camera
    // rays (the perspective sensor's in SIMD lanes: the samplers' set-up and first two
    // numbers, Camera::perspective_ray; the others one sample at a time), at depth 0.
    int next = 0;
    auto start = [&](int first, int m) {
        if (camera.type == CameraType::Perspective) {
            alignas(64) float ux[B], uy[B];
            alignas(64) uint64_t state[B], inc[B];
            const uint64_t *streams = state, *increments = inc;
            if (ws.predrawn) {
                first_draws(samples + next, m, camera.sampler, buffers.columns, parts + next, ux, uy);
                streams = buffers.columns.state, increments = buffers.columns.inc;
            } else {
                first_draws(samples + next, m, ux, uy, state, inc);
            }
            camera_stage(b, first, samples + next, m, camera, pos + next, ux, uy, streams, increments);
        } else {
            for (int i = 0; i < m; ++i) {
                const int k = first + i;
                const WavefrontSample &s = samples[next + i];
                Sampler sampler(camera.sampler, s.seed, uint64_t(s.s));
                pos[next + i] = camera.sample_position(s.px, s.py, sampler);
                store_ray(b, k, camera.sample_ray(pos[next + i], sampler), sampler);
                if (parts) parts[next + i] = sampler.parts();
            }
        }
        // (In SIMD lanes: with `next` read in the loop, which a store to an int column might
        // change for all GCC knows, it stored each lane's columns one at a time.)
        const int seq_of_lane_0 = next - first;
#pragma GCC ivdep
        for (int k = first; k < first + m; ++k) {
            b.Lr[k] = b.Lg[k] = b.Lb[k] = 0.f;
            reset_lane(k, seq_of_lane_0 + k);
        }
        for (int k = first; sub_paths && k < first + m; ++k) {
            Buffers::SubPaths &sub = buffers.subs[size_t(b.seq[k])];
            sub.camera_ray = load_ray(b, k);
            sub.done = 0;
        }
        next += m;
    };
    // Start the next sub-paths of `m` waiting samples in lanes [first, first + m): from their
    // camera ray again, with its closest hit (found by the first sub-path: `known_hits`
    // lanes at the batch's end are not traced again), their radiance and their stream going on.
    int known_hits = 0;
    auto start_again = [&](int first, int m) {
        for (int k = first; k < first + m; ++k) {
            const int seq = again[again_next++];
            const Buffers::SubPaths &sub = buffers.subs[size_t(seq)];
            store_ray(b, k, sub.camera_ray, Sampler::independent(sub.state, sub.inc));
            const Hit &hit = sub.first_hit;
            b.ht[k] = hit.t, b.hu[k] = hit.u, b.hv[k] = hit.v, b.prim[k] = hit.prim;
            b.Lr[k] = L[seq][0], b.Lg[k] = L[seq][1], b.Lb[k] = L[seq][2];
            reset_lane(k, seq);
        }
    };
    // A drained batch's paths: the waiting sub-paths (after the next samples, which fill the
    // lanes they leave).
    auto start_drained = [&] {
        const int m = int(std::min(again.size() - again_next, size_t(B)));
        const int fresh = std::min(n_samples - next, B - m);
        start(0, fresh);
        start_again(fresh, m);
        known_hits = m;
        if (again_next == again.size()) again.clear(), again_next = 0;
        return m + fresh;
    };
    // Lanes freed by ended paths take the next samples at the end of each bounce, so that the
    // stages run over full batches to the last samples (cornell-box's paths, up to 65
    // vertices, left half the bounces to fewer than 8 lanes, whose stages cost 10 times more
    // per lane than a full batch's). Where every path has at most two vertices (`direct`),
    // half of a refilled batch would be at its last vertex, which the shading stages would
    // run over for nothing: there a batch is refilled once it has drained.
    const bool refill = !(cfg.max_depth >= 1 && cfg.max_depth <= 2);
    int n = std::min(n_samples, B);
    start(0, n);
    // Lane k's path ended: its radiance, and for `direct`, its sample's next sub-path waits
    // (unless the camera ray escaped: direct_li has no vertex to shade then).
    auto finish = [&](int k) {
        const int seq = b.seq[k];
        L[seq] = RGB<float>(b.Lr[k], b.Lg[k], b.Lb[k]);
        if (!sub_paths || (b.depth[k] == 0 && b.prim[k] == ~0u)) return;
        // (The radiance where the sub-path ends, for render_bwd: its records' terms end there.)
        if (record) record->add(seq, WavefrontVertex::End, b.Lr[k], b.Lg[k], b.Lb[k], 0.f, 0.f, 0.f, ParamRead{});
        Buffers::SubPaths &sub = buffers.subs[size_t(seq)];
        if (++sub.done == cfg.sub_paths) return;
        sub.state = b.state[k], sub.inc = b.inc[k];
        again.push_back(seq);
    };
    // Whether the emission lane k's ray finds is dropped: seen directly by the camera with
    // hide_emitters, or found again by a later sub-path's camera ray. The throughput that
    // weights it: 1 for a camera ray.
    auto hidden = [&](int k) {
        return b.depth[k] == 0 && (cfg.hide_emitters || (sub_paths && buffers.subs[size_t(b.seq[k])].done > 0));
    };
    auto found_beta = [&](int k) {
        return b.depth[k] == 0 ? RGB<float>(1.f) : RGB<float>(b.br[k], b.bg[k], b.bb[k]);
    };
    // The last vertex max_depth allows: only the emission lane k's ray finds (path_li's).
    auto last_vertex = [&](int k) {
        int emitter, reads = log ? log->count : 0, expected = 0;
        const Hit hit{b.ht[k], b.prim[k], b.hu[k], b.hv[k]};
        SurfaceInteraction si = scene.emitter_interaction(load_ray(b, k), hit, &emitter);
        if (emitter >= 0 && !hidden(k)) {
            RGB<float> Le = emission_found(ctx, scene.emitters[emitter], si, found_beta(k),
                                           b.prev_delta[k] != 0, b.prev_pdf[k],
                                           Vec3{b.prev_px[k], b.prev_py[k], b.prev_pz[k]});
            b.Lr[k] += Le[0], b.Lg[k] += Le[1], b.Lb[k] += Le[2];
            expected = emission_read(k, reads, scene.emitters[emitter], Le);
        }
        unexpected_reads(k, reads, expected);
    };
    auto is_last = [&](int k) { return cfg.max_depth >= 0 && b.depth[k] + 1 >= cfg.max_depth; };
    const Geometry &g = scene.geometry;
    // The `constant` environment's radiance and the density of its emitter samples, for
    // sky_stage (the same for every escaped ray: ws.environment is `constant` alone, and
    // other environments end their paths in the shade loop below, looked up along the ray).
    Color3f env_radiance(0.f);
    float env_pdf = 0.f;
    if (ws.environment) {
        const Emitter &e = scene.emitters[size_t(scene.environment)];
        env_radiance = Color3f(emitter_eval<RGB<float>>(ctx, e, SurfaceInteraction()));
        env_pdf = emitter_pdf(ctx, e, Vec3{}, SurfaceInteraction());
    }
    while (n > 0) {
        int n_last = 0;
        for (int k = 0; k < n; ++k) n_last += is_last(k) ? 1 : 0;
        if (n_last == n && ws.last_rays_reach) {
            // Every path at its last vertex, where only an emitter found adds anything: trace
            // the rays that enter an emitting shape's box (listed; gathered into columns of
            // their own), the others end without (`direct`'s BSDF samples, most of which
            // leave veach-mis's lights aside).
            rays_traced += uint64_t(trace_reaching(b, n, ws.emitter_boxes, scene.bvh));
        } else {
            // Trace each path's ray to its closest hit (in SIMD lanes in a small scene).
            const int traced = n - known_hits;
            scene.bvh.intersect_columns(ray_columns(b), traced, {b.ht, b.hu, b.hv, b.prim});
            rays_traced += uint64_t(traced);
            // (A first sub-path keeps its camera ray's hit for the others.)
            for (int k = 0; sub_paths && k < traced; ++k) {
                if (b.depth[k] == 0) buffers.subs[size_t(b.seq[k])].first_hit = Hit{b.ht[k], b.prim[k], b.hu[k], b.hv[k]};
            }
        }
        known_hits = 0;
        if (n_last == n) {
            // Every path at its last vertex: they end here, with the emission of those whose
            // ray found an emitter (listed in lanes).
            alignas(64) int emits[B], emitting[B];
            const int *prim_emits = ws.prim_emits.data();
            const uint32_t escaped = uint32_t(ws.prim_emits.size()) - 1;
#pragma GCC ivdep
            for (int k = 0; k < n; ++k) emits[k] = prim_emits[std::min(b.prim[k], escaped)];
            const int n_emitting = simd::select_indices(emits, n, 1, emitting);
            for (int j = 0; j < n_emitting; ++j) last_vertex(emitting[j]);
            for (int k = 0; k < n; ++k) finish(k);
            n = start_drained();
            continue;
        }
        // Complete the interactions of the triangles hit, in lanes.
        interaction_stage_for(ws)(b, n, g, ws);
        // Complete the other interactions, add the emission each ray found, MIS-weighted
        // (path_li's code), and look up the diffuse reflectances; paths whose ray escaped end
        // here, and vertices of other BSDFs are shaded with path_li's own code.
        int n_side = 0;
        // (The vertices needing only constants are set up in lanes, in renders without a
        // parameter log or whose log's watched inputs exclude_watched_inputs() left out.)
        const bool quick = !log || log->watched == ws.quick_watched;
        if (quick) quick_shade_stage(b, n, ws, log ? record : nullptr);
        // The rays that escaped end in lanes without a parameter log (sky_stage), unless an
        // environment other than `constant` emits.
        alignas(64) int visit[B], visit_lanes[B], sky_ended[B];
        const bool sky_lanes = !log && (scene.environment < 0 || ws.environment);
        if (sky_lanes) {
            sky_stage(b, n, ws.environment, env_radiance, env_pdf, cfg.hide_emitters, cfg.max_depth, sky_ended);
        } else {
            std::fill(sky_ended, sky_ended + n, 0);
        }
        // The lanes this loop visits (listed in lanes: a branch per lane mispredicts): those
        // at their last vertex among others that go on, and those the quick stage left, but
        // for those sky_stage ended.
        const int any_last = n_last > 0 ? 1 : 0, quick_set = quick ? 1 : 0;
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            const int last = is_last(k) ? any_last : 0;
            const int set_up = b.shade[k] != 0 ? quick_set : 0;
            visit[k] = (last != 0 || set_up == 0) && sky_ended[k] == 0 ? 1 : 0;
        }
        const int n_visit = simd::select_indices(visit, n, 1, visit_lanes);
        for (int j = 0; j < n_visit; ++j) {
            const int k = visit_lanes[j];
            if (n_last > 0 && is_last(k)) {
                // A path at its last vertex (among others that go on): its emission, and the
                // vector stage ends it (shade 0).
                last_vertex(k);
                b.shade[k] = 0, b.mat[k] = 0, b.record_rough[k] = b.record_alpha[k] = -1;
                continue;
            }
            if (quick && b.shade[k]) continue;
            b.shade[k] = 0, b.mat[k] = 0, b.record_rough[k] = b.record_alpha[k] = -1;
            const int reads = log ? log->count : 0;
            if (b.prim[k] == ~0u) {
                // The ray escaped: the environment's emission (if the scene has one) ends it,
                // looked up along the ray (the escaped interaction's world-space wi).
                if (scene.environment >= 0 && !hidden(k)) {
                    const Emitter &e = scene.emitters[size_t(scene.environment)];
                    const SurfaceInteraction escaped = g.interaction(load_ray(b, k), Hit{});
                    RGB<float> Le = emission_found(ctx, e, escaped, found_beta(k),
                                                   b.prev_delta[k] != 0, b.prev_pdf[k],
                                                   Vec3{b.prev_px[k], b.prev_py[k], b.prev_pz[k]});
                    b.Lr[k] += Le[0], b.Lg[k] += Le[1], b.Lb[k] += Le[2];
                    unexpected_reads(k, reads, emission_read(k, reads, e, Le));
                }
                continue;
            }
            int expected = 0;
            SurfaceInteraction si;
            if (!b.done[k]) {
                Hit hit;
                hit.t = b.ht[k], hit.u = b.hu[k], hit.v = b.hv[k], hit.prim = b.prim[k];
                si = g.interaction(load_ray(b, k), hit);
                store_interaction(b, k, si);
            }
            const Shape &shape = g.shapes[g.shape_of(b.prim[k])];
            if (shape.emitter >= 0 && !hidden(k)) {
                if (!si.valid) si = load_interaction(b, k, g);
                RGB<float> Le = emission_found(ctx, scene.emitters[shape.emitter], si, found_beta(k),
                                               b.prev_delta[k] != 0, b.prev_pdf[k],
                                               Vec3{b.prev_px[k], b.prev_py[k], b.prev_pz[k]});
                b.Lr[k] += Le[0], b.Lg[k] += Le[1], b.Lb[k] += Le[2];
                expected = emission_read(k, reads, scene.emitters[shape.emitter], Le);
            }
            const BSDF &bsdf = scene.bsdfs[shape.bsdf];
            const WavefrontScene::Lane lane = WavefrontScene::Lane(ws.materials[shape.bsdf].lane);
            if (lane == WavefrontScene::Aside) {
                // Shade the vertex with path_li's own code, into the side batch: the vector
                // stage overwrites the lane, which gets it back after.
                if (!si.valid) si = load_interaction(b, k, g);
                PathState<RGB<float>> path = load_path(b, k);
                Sampler sampler = load_sampler(b, k, camera.sampler, parts);
                Ray ray;
                side.alive[n_side] = path_vertex(ctx, cfg, b.depth[k], si, sampler, path, ray);
                store_path(side, n_side, path, ray, sampler);
                if (parts) parts[b.seq[k]] = sampler.parts();
                side.seq[n_side] = b.seq[k];
                side.depth[n_side] = b.depth[k];
                side_lane[n_side++] = k;
                unexpected_reads(k, reads, expected);
                continue;
            }
            // The vector stage shades it, with the reflectance and transmittance looked up here.
            auto lookup = [&](const TextureRef &r) {
                if (r.texture < 0 && r.attribute < 0) return ctx.params.spectrum(r.param);  // (inline)
                if (r.attribute < 0)  // a texture at uv
                    return eval_texture<RGB<float>>(r, ctx.textures, ctx.params, Vec2{b.uvx[k], b.uvy[k]});
                if (!si.valid) si = load_interaction(b, k, g);
                return make_query(bsdf, ctx, shape.bsdf, si).texture<RGB<float>>(r);
            };
            const ShadeInputs in = shade_inputs(bsdf, lane);
            const int reads_a = log ? log->count : 0;
            Color3f a = lookup(*in.a);
            b.ar[k] = a.v[0], b.ag[k] = a.v[1], b.ab[k] = a.v[2];
            // (The diffuse reflectance, the mirror's and rough conductor's specular reflectance
            // and, on the branch it samples, the dielectric's specular reflectance or
            // transmittance are one factor of all the path gathers after the vertex.)
            const bool glass = lane == WavefrontScene::Glass;
            const bool linear = linear_in_inputs(lane);
            auto keep = [&](int reads_before, const Color3f &value) {
                // A differentiated input: the vertex, for render_bwd's deposit.
                if (!log || !linear || log->count != reads_before + 1) return -1;
                record->add(b.seq[k], WavefrontVertex::Input, b.Lr[k], b.Lg[k], b.Lb[k], value.v[0], value.v[1], value.v[2], log->last);
                ++expected;
                return int(record->vertices.size()) - 1;
            };
            b.record_reflect[k] = keep(reads_a, a);
            if (b.record_reflect[k] >= 0) unit_zero_inputs(b, k, record->vertices.back(), lane);
            if (log && lane == WavefrontScene::RoughPlastic && log->count == reads_a + 1) {
                // A roughplastic's differentiated diffuse reflectance: a Term record, whose C_e
                // and dlog the shadow stage and the records after the vector stage fill in.
                b.record_rough[k] = int(record->vertices.size());
                record->add(b.seq[k], WavefrontVertex::Term, b.Lr[k], b.Lg[k], b.Lb[k], 0.f, 0.f, 0.f, log->last);
                ++expected;
            }
            b.record_refract[k] = -1;
            if (in.t) {
                const int reads_t = log ? log->count : 0;
                Color3f t = lookup(*in.t);
                b.tr[k] = t.v[0], b.tg[k] = t.v[1], b.tb[k] = t.v[2];
                if (glass) b.record_refract[k] = keep(reads_t, t);
            }
            unexpected_reads(k, reads, expected);
            b.mat[k] = shape.bsdf;
            b.shade[k] = 1;
        }
        // Shade the other vertices in lanes (the rough ones' BSDF samples first, Beckmann's
        // visible normals before those; their emitter samples after); then the vertices
        // shaded aside return.
        draw_stage(b, n, ws, cfg, camera.sampler, parts, buffers.columns);
        // Paths of two vertices (no refill: every lane's next vertex is its last, where only
        // the rays that enter an emitter's box are traced), without roulette or recording,
        // evaluate their rough BSDF samples only where those rays enter one
        // (finish_deferred_samples: veach-mis 4-7% faster).
        const bool defer = !log && ws.last_rays_reach && !refill && cfg.max_depth == 2 && cfg.rr_depth > 1 &&
                           cfg.bsdf_sampling;
        ggx.count = ws.any_ggx ? list_rough_lanes(b, n, ws, 0.f, ggx.lanes) : 0;
        if (ggx.count > 0) (defer ? ggx_sample_stage<true> : ggx_sample_stage<false>)(b, ggx, ws);
        beckmann.count = ws.any_beckmann ? list_rough_lanes(b, n, ws, 1.f, beckmann.lanes) : 0;
        if (beckmann.count > 0) (defer ? beckmann_sample_stage<true> : beckmann_sample_stage<false>)(b, ws, beckmann);
        // (Without emitter sampling the vector stage reads no aside sample; lane_emitter_stage
        // writes every lane's, aside_emitter_stage then those of its lights.)
        if (ws.any_lane_lights && cfg.emitter_sampling) lane_emitter_stage_for(ws)(b, n, ws);
        if (ws.any_aside_stage_lights && cfg.emitter_sampling) aside_emitter_stage(b, n, ws, ctx);
        vertex_stage_for(ws)(b, n, ws, cfg);
        const float bsdf_mis = cfg.bsdf_sampling ? 1.f : 0.f;
        if (ggx.count > 0) rough_emitter_stage<Microfacet::GGX>(b, ggx, ws, bsdf_mis);
        if (beckmann.count > 0) rough_emitter_stage<Microfacet::Beckmann>(b, beckmann, ws, bsdf_mis);
        if (log) {
            // A dielectric's vertex keeps the input of the branch it sampled.
            for (int k = 0; ws.any_delta && k < n; ++k) {
                if (!b.shade[k] || ws.materials[size_t(b.mat[k])].lane != WavefrontScene::Glass) continue;
                int unused = b.refracts[k] != 0.f ? b.record_reflect[k] : b.record_refract[k];
                if (unused >= 0) record->vertices[size_t(unused)].seq = -1;
            }
            // A rough conductor's differentiated roughness (GGX's or Beckmann's): the vertex,
            // with d log f / d alpha towards its emitter sample and its BSDF sample (the shadow
            // stage adds the emitter sample's contribution to it). A roughplastic's Term
            // records: d log f / d rho (the shade stage's record) and d log f / d alpha towards
            // the two.
            // (The differentiated conductor roughnesses' d log f / d alpha in lanes first.)
            alignas(64) float dlog_e[B], dlog_s[B];
            if (ggx.count > 0) conductor_dlog_stage<MicrofacetType::GGX>(b, ggx, ws, watched_roughness.data(), dlog_e, dlog_s);
            if (beckmann.count > 0)
                conductor_dlog_stage<MicrofacetType::Beckmann>(b, beckmann, ws, watched_roughness.data(), dlog_e, dlog_s);
            for (int k = 0; ws.any_rough && k < n; ++k) {
                if (!b.shade[k]) continue;
                const WavefrontScene::Material &m = ws.materials[size_t(b.mat[k])];
                const BSDF &bsdf = scene.bsdfs[size_t(b.mat[k])];
                const bool plastic = m.lane == WavefrontScene::RoughPlastic;
                const bool rho_term = plastic && b.record_rough[k] >= 0, alpha_term = plastic && log->watched[bsdf.alpha];
                if (!rho_term && !alpha_term && !watched_roughness[size_t(b.mat[k])]) continue;
                Vec3 wi{b.wix[k], b.wiy[k], b.wiz[k]};
                wi.z = m.twosided != 0 && wi.z < 0.f ? wi.z * -1.f : wi.z;  // (the vertex stage's flip)
                const Vec3 wo_e{b.nwx[k], b.nwy[k], b.nwz[k]}, wo_s{b.swx[k], b.swy[k], b.swz[k]};
                if (plastic) {
                    const BSDFState &state = ctx.bsdf_state[size_t(b.mat[k])];
                    const RGB<float> rho(b.ar[k], b.ag[k], b.ab[k]), ks(b.tr[k], b.tg[k], b.tb[k]);
                    auto fill = [&](WavefrontVertex &v, auto dlog) {
                        const RGB<float> e = b.shadow[k] ? dlog(wo_e) : RGB<float>(0.f);
                        const RGB<float> s = b.alive[k] ? dlog(wo_s) : RGB<float>(0.f);
                        for (int c = 0; c < 3; ++c) {
                            v.dlog[0][c] = e[c], v.dlog[1][c] = s[c];
                            // (Where f_c is 0 and its derivative is not, dlog_c is infinite;
                            // where f_c is tiny, as ks_c spec with rho_c 0 under Beckmann's far
                            // from its peak, huge, and L_c - L_before,c holds little but the
                            // float sums' rounding: the tape. A diffuse dlog is 1 / rho.)
                            if (!(std::abs(e[c]) <= MaxTermDlog) || !(std::abs(s[c]) <= MaxTermDlog))
                                record->tape[size_t(b.seq[k])] = 1;
                        }
                    };
                    if (rho_term) {
                        fill(record->vertices[size_t(b.record_rough[k])], [&](const Vec3 &wo) {
                            return RoughPlasticBSDF::dlog_dreflectance(bsdf, state, m.alpha, wi, wo, rho, ks);
                        });
                    }
                    if (alpha_term && !state.dtables) {
                        // (Not reached: render_bwd gives the lanes' context the tables'
                        // derivatives of a differentiated roughness.)
                        record->tape[size_t(b.seq[k])] = 1;
                    } else if (alpha_term) {
                        ParamRead read;
                        read.param = bsdf.alpha, read.n = 1, read.weight[0] = 1.f;
                        b.record_alpha[k] = int(record->vertices.size());
                        fill(record->add(b.seq[k], WavefrontVertex::Term, b.Lr[k], b.Lg[k], b.Lb[k], 0.f, 0.f, 0.f, read),
                             [&](const Vec3 &wo) {
                                 return RoughPlasticBSDF::dlog_dalpha(bsdf, state, m.alpha, wi, wo, rho, ks);
                             });
                    }
                    continue;
                }
                ParamRead read;
                read.param = bsdf.alpha, read.n = 1, read.weight[0] = 1.f;
                const float e = b.shadow[k] ? dlog_e[k] : 0.f, s = b.alive[k] ? dlog_s[k] : 0.f;
                if (!std::isfinite(e) || !std::isfinite(s)) record->tape[size_t(b.seq[k])] = 1;
                b.record_rough[k] = int(record->vertices.size());
                WavefrontVertex &v = record->add(b.seq[k], WavefrontVertex::Roughness, b.Lr[k], b.Lg[k], b.Lb[k], 0.f, 0.f, 0.f, read);
                for (int c = 0; c < 3; ++c) v.dlog[0][c] = e, v.dlog[1][c] = s;
            }
        }
        for (int i = 0; i < n_side; ++i) {
            const int k = side_lane[i];
            move_lane(side, i, b, k);
            b.alive[k] = side.alive[i];
            b.shadow[k] = 0;
        }
        // Shadow rays: in lanes in a small scene with sphere lights (each ray ends on a sphere,
        // whose exact test is in double: veach-mis 117 -> 103 ms) and against the root's leaves
        // of a larger tree in two phases (BVH::two_phase(): the bunny 2% faster than one ray
        // at a time); in other scenes of one node, the children whose boxes each ray enters
        // found in lanes, then one ray at a time through those (with only triangles near the
        // rays that is faster than their triangles in lanes: glossy +2-3% that way); else
        // one at a time. Then the paths that ended hand back their radiance, the rest move up.
        // (Against the shadow rays' tree: Scene::shadow_tree().)
        const BVH &sbvh = scene.shadow_tree();
        bool shadow_lanes = (ws.any_sphere_lights && sbvh.flat()) || sbvh.two_phase();
        const bool shadow_masks = !shadow_lanes && sbvh.one_node();
        alignas(64) int root_mask[B];
        if (shadow_lanes) shadow_rays_in_lanes(b, n, sbvh);
        if (shadow_masks) {
            // (The lanes without a shadow ray get masks that are not read.)
            sbvh.root_masks({b.sox, b.soy, b.soz, b.sdx, b.sdy, b.sdz, shadow_tmin, b.stmax}, n, root_mask);
        }
        // The shadow rays' tests one at a time where the lanes did not take them; `lit`: 1
        // where the emitter sample's contribution is added.
        // (With the masks, only the rays that enter one of the root's children: 59% of
        // cornell-box's shadow rays enter none.)
        alignas(64) int lit[B], test[B], shadow_lanes_list[B];
        int n_lit = 0;
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            lit[k] = b.shadow[k] != 0 ? 1 : 0;
            n_lit += lit[k];
        }
        if (shadow_masks) {
#pragma GCC ivdep
            for (int k = 0; k < n; ++k) test[k] = lit[k] != 0 && root_mask[k] != 0 ? 1 : 0;
        }
        int n_shadow = shadow_lanes ? 0 : simd::select_indices(shadow_masks ? test : lit, n, 1, shadow_lanes_list);
        if (shadow_masks && sbvh.flat() && 2 * n_shadow > n_lit) {
            // Most rays enter a child's box (as where the surfaces they leave are in the shadow
            // rays' tree: an environment's rays cross a floor): the masks spare few tests, and
            // the lanes take all, with the same answers. A floor under two spheres in a
            // constant environment (grad_rough.xml: every ray enters a box, 2.1 on average;
            // in the cbox, glossy and textured 20-31% enter one): 128 px at 32 spp, one
            // thread, 89 -> 83 ms; its gradient iteration, 230 -> 221 ms (Beckmann) and
            // 200 -> 188 (GGX); the other flat scenes unchanged.
            shadow_rays_in_lanes(b, n, sbvh);
#pragma GCC ivdep
            for (int k = 0; k < n; ++k) lit[k] = b.shadow[k] != 0 ? 1 : 0;
            shadow_lanes = true, n_shadow = 0;
        }
        for (int j = 0; j < n_shadow; ++j) {
            const int k = shadow_lanes_list[j];
            Ray ray;
            ray.o = {b.sox[k], b.soy[k], b.soz[k]};
            ray.d = {b.sdx[k], b.sdy[k], b.sdz[k]};
            ray.tmax = b.stmax[k];
            const bool blocked = shadow_masks ? sbvh.occluded_children(ray, root_mask[k]) : sbvh.occluded(ray);
            lit[k] = blocked ? 0 : 1;
        }
        // Their contributions, in lanes.
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            b.Lr[k] = lit[k] != 0 ? b.Lr[k] + b.cr[k] : b.Lr[k];
            b.Lg[k] = lit[k] != 0 ? b.Lg[k] + b.cg[k] : b.Lg[k];
            b.Lb[k] = lit[k] != 0 ? b.Lb[k] + b.cb[k] : b.Lb[k];
        }
        for (int k = 0; log && k < n; ++k) {
            if (!lit[k]) continue;
            const WavefrontScene::Light &light = ws.lights[size_t(b.light[k])];
            for (const int i : {b.record_rough[k], b.record_alpha[k]}) {
                if (i < 0) continue;
                // (The true C_e: zero in a radiance's channels that the lanes read as 1.)
                float *C = record->vertices[size_t(i)].value;
                const int zero = radiance_zeros(light.radiance_param);
                C[0] = zero & 1 ? 0.f : b.cr[k], C[1] = zero & 2 ? 0.f : b.cg[k], C[2] = zero & 4 ? 0.f : b.cb[k];
            }
            if (log->watched[light.radiance_param]) {
                // The emitter sample's contribution, for render_bwd's deposit.
                ParamRead read;
                read.param = light.radiance_param, read.n = 1, read.weight[0] = 1.f;
                read.channels = ctx.params.numel[size_t(light.radiance_param)] == 1 ? 1 : 3;
                const Color3f &Le = light.radiance;
                record->add(b.seq[k], WavefrontVertex::Emission, b.cr[k], b.cg[k], b.cb[k], Le.v[0], Le.v[1], Le.v[2], read);
                unit_radiance(record->vertices.back(), light.radiance_param);
            }
        }
        // The rough samples left unevaluated, where their new ray enters an emitter's box.
        if (defer && ggx.count + beckmann.count > 0) {
            alignas(64) int enters[B];
            ws.emitter_boxes.entered(ray_columns(b), n, enters);
            if (ggx.count > 0) finish_deferred_samples<Microfacet::GGX>(b, ggx, ws, enters);
            if (beckmann.count > 0) finish_deferred_samples<Microfacet::StoredOnly>(b, beckmann, ws, enters);
        }
        // The paths that ended hand back their radiance; the others move to the front, in
        // lanes (compact_lanes).
        alignas(64) int dead[B], ended[B];
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) dead[k] = b.alive[k] != 0 ? 0 : 1;
        const int n_ended = simd::select_indices(dead, n, 1, ended);
        for (int j = 0; j < n_ended; ++j) finish(ended[j]);
        const int live = compact_lanes(b, n);
        rays_traced += uint64_t(shadow_lanes ? 0 : n_lit);  // (Scene::occluded's count is a thread_local's)
        // The paths that go on take their next vertex; the next samples start in the lanes
        // freed (or in the whole batch, once drained, without refill).
        for (int k = 0; k < live; ++k) ++b.depth[k];
        n = live;
        if (n == 0) {
            n = start_drained();
        } else if (next < n_samples && refill) {
            const int m = std::min(n_samples - next, B - n);
            start(n, m);
            n += m;
        }
    }
}

}  // namespace rbpt
