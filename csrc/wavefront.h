// The `path` integrator for plain float renders, run over a batch of paths at a time so that
// the shading of many paths runs in SIMD lanes (a wavefront). Each bounce is a few stages over
// the batch, its live paths kept packed at the front of structure-of-arrays columns:
//   trace       one path at a time: the ray cast (the BVH's closest hit);
//   interaction in SIMD lanes: the surface interaction of the triangles hit;
//   shade       in SIMD lanes for the vertices needing only constant inputs, else one path
//               at a time: the interaction of other shapes hit, the emission the ray found
//               (the integrator's own code), a texture's reflectance, and the vertices whose
//               BSDF the vector stage does not shade (path_vertex());
//   vertex      in SIMD lanes, for the other vertices: an emitter sample, the BSDF towards
//               it with its MIS weight, the BSDF sample, Russian roulette and the next ray;
//   shadow      one path at a time: the shadow rays, adding the emission they see;
//   compact     the paths that ended hand their radiance back; the rest move to the front.
// Lanes stay in place from the trace to the shadow rays; the vertex stage leaves the lanes
// it does not shade as they are.
// It computes what path_li computes, operation for operation, in the same order (with
// -ffp-contract=off a vectorised loop performs the same IEEE operations as a scalar one), so
// images are bitwise identical to the scalar integrator's (tests/test_wavefront.py). The
// vector stage shades diffuse BSDFs (`twosided` or not), the roughconductor and roughplastic
// (GGX and Beckmann; Beckmann's visible normals are sampled one path at a time, before the
// vector stage, from the same random numbers), with their emitter samples on area emitters
// on spheres and on meshes of at most 8 triangles and on the `constant` environment (larger
// meshes', disks', cylinders' and point lights' samples are taken in SIMD lanes just before
// the vector stage, lane_emitter_stage, and other emitters' by emitter_sample() one path at
// a time; the vector stage then takes them), and the smooth conductor and dielectric; their
// reflectances and transmittances (constants, textures or mesh attributes) are looked up in
// the shade stage. Vertices of other BSDFs are shaded by path_vertex(), path_li's own code,
// in the shade stage. It runs for the `path` integrator (and `direct` with n samples of each
// kind or of one kind alone, as path_settings() makes it: n paths of two vertices, one after
// the other from the camera ray's first hit), with any sampler (each vertex's
// numbers are drawn in one stage before the others, by SamplerColumns in lanes for the
// samplers other than `independent`: WavefrontScene::predrawn),
// when some BSDF of the scene is one of those; other scenes, and the autodiff number types, take
// path_li. render_bwd also traces its paths with
// it, for gradients of the inputs of lanes linear in them, of emitters' radiance and of rough
// conductors' roughness (WavefrontVertex).
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
    /// The BSDFs the vector stage shades (the others are shaded by path_vertex()): diffuse,
    /// conductor (a mirror), dielectric, and the GGX roughconductor and roughplastic.
    enum Lane { Aside = 0, Diffuse = 1, Mirror = 2, Glass = 3, RoughMirror = 4, RoughPlastic = 5 };
    struct Material {
        int lane;       ///< a Lane
        int twosided;   // (ints, not bools: the vector loop gathers them)
        float eta;      ///< int_ior / ext_ior (dielectric, roughplastic)
        float alpha;    ///< roughness (rough types)
        int nonlinear;  ///< roughplastic
        float specular_sampling_weight, internal_reflectance;  ///< roughplastic (BSDFState)
        int table;      ///< roughplastic: its external transmittance in `tables`, 64 entries from here
        /// The lane as flags (1 or 0) for the vector stage, which gathers them: GCC turns
        /// comparisons of `lane` with several values into branches it does not vectorise.
        float diffuse, mirror, rough, plastic;
        /// 1: a rough lane of the Beckmann distribution (its visible normal sampled in
        /// scalar code before the vector stage), 0: GGX.
        float beckmann = 0.f;
        /// Its inputs where they are constants (see prim_quick): the reflectance a and the
        /// second input t of the shade stage.
        float ar = 0.f, ag = 0.f, ab = 0.f, tr = 0.f, tg = 0.f, tb = 0.f;
    };
    struct Light {
        Color3f radiance;
        int radiance_param = -1;  ///< Emitter::radiance
        int has_normals = 0, flip_normals = 0;  // (ints, not bools: the vector loop gathers them)
        float area = 1.f;
        float environment = 0.f;  ///< 1: the `constant` environment (no mesh), else 0
        /// 1: an area light on a sphere (no mesh), else 0; its centre (three floats: GCC does
        /// not vectorise gathers of a Vec3 member here), radius, the squared radius beyond which
        /// a point is outside (Geometry::sample_direction) and its normals' sign.
        float sphere = 0.f;
        float cx = 0.f, cy = 0.f, cz = 0.f;
        float radius = 1.f, outside_radius2 = 1.f, sign = 1.f;
        /// 1: an emitter the vector stage does not sample itself (a point light, an area light
        /// on a disk, a cylinder or a mesh of more than 8 triangles; any new emitter type):
        /// emitter_sample() samples it, one lane at a time, before the vector stage, which
        /// then takes that sample (no mesh in the flat arrays), else 0. Those of the kinds
        /// below are sampled by lane_emitter_stage instead, in SIMD lanes (`lanes` 1).
        float aside = 0.f;
        int lanes = 0;
        int large = 0;     ///< 1: an area light on a mesh of more than 8 triangles (large_*)
        int disk = 0;      ///< 1: an area light on a disk (light_frame)
        int cylinder = 0;  ///< 1: an area light on a cylinder (light_frame)
        int point = 0;     ///< 1: a point light (light_frame)
    };
    std::vector<Material> materials;  ///< per Scene::bsdfs
    /// A material whose input a is a bilinear bitmap (and t a constant, or none): the shade
    /// stage looks it up in lanes (bitmap_stage) for its vertices in prim_quick, from the
    /// bitmap's texels (the render's parameter data). Where the backward pass differentiates
    /// the bitmap (exclude_watched_inputs()), a lane linear in it records each lookup as the
    /// WavefrontVertex the shade stage's own code would (`record`).
    struct BitmapLookup {
        int material;
        int param;            ///< the bitmap's parameter
        const float *texels;  ///< its data, (height, width, channels), row 0 on top
        int width, height, channels;
        WrapMode wrap;
        bool has_to_uv;
        float to_uv[2][3];
        bool record = false;
        int lane = 0;  ///< with `record`: its material's Lane (unit_zero_inputs)
    };
    std::vector<BitmapLookup> bitmaps;
    /// Per primitive (triangles, then Geometry::analytic): its material, and whether the shade
    /// stage's work for it is a lookup in lanes (1: a BSDF of the vector stage whose inputs are
    /// constants, Material::a and t, or a bitmap in `bitmaps`, on a shape that does not emit;
    /// else 0).
    std::vector<int> prim_material, prim_quick;
    /// Per primitive, then one entry more for a ray that escaped: 1 where the ray finds an
    /// emitter there (the shape's, or the environment), else 0.
    std::vector<int> prim_emits;
    /// The boxes of the shapes that emit, and whether the rays at their last vertex are traced
    /// only where they enter one (a ray that finds no emitter adds nothing there): not where
    /// the environment emits, nor beyond MostEmitterBoxes shapes.
    ShapeBoxes emitter_boxes;
    bool last_rays_reach = false;
    static constexpr int MostEmitterBoxes = 16;
    /// The parameters (per parameter, nonzero where marked) whose materials
    /// exclude_watched_inputs() took out of prim_quick, for renders logging their reads.
    const char *quick_watched = nullptr;
    bool any_delta = false;           ///< whether some are mirrors or dielectrics
    bool any_rough = false;           ///< whether some are rough
    bool any_beckmann = false;        ///< whether some rough ones are Beckmann's
    bool any_ggx = false;             ///< whether some rough ones are GGX's
    std::vector<float> tables;        ///< roughplastic tables (RoughPlasticTables), 64 per BSDF
    /// Per triangle, what its interactions read of its mesh (ShapeFlag bits).
    enum ShapeFlag { HasNormals = 1, FlipNormals = 2, NeedsUV = 4, HasUVs = 8 };
    std::vector<int> triangle_flags;
    bool any_normals = false, any_uv = false;  ///< of the meshes: vertex normals, uv read
    /// Per analytic primitive (Geometry::analytic): whether it is a sphere (whose interaction
    /// the interaction stage completes: sphere_interactions), its centre, radius and
    /// normals' sign, whether its uv is read, and its frame (Shape::local_x, local_y,
    /// local_z: uv's axes). Read only where some analytic primitive is a sphere.
    std::vector<int> is_sphere, sphere_uv;
    std::vector<Vec3> sphere_center, sphere_x, sphere_y, sphere_z;
    std::vector<float> sphere_radius, sphere_sign;
    bool any_spheres = false, any_sphere_uv = false;  ///< whether some are spheres, some read uv
    std::vector<Light> lights;        ///< per Scene::emitters
    std::vector<float> radiance;      ///< Light::radiance, 3 per light (for gathers)
    bool environment = false;         ///< whether one is the `constant` environment
    bool any_sphere_lights = false;   ///< whether some are spheres
    bool any_mesh_lights = false;     ///< whether some are meshes
    bool any_aside_lights = false;    ///< whether some are sampled aside (Light::aside)
    bool any_large_lights = false;    ///< whether some of those are meshes (Light::large)
    bool any_large_normals = false;   ///< whether some of those meshes have vertex normals
    bool any_analytic_lights = false;  ///< whether some are disks or cylinders (Light::disk, cylinder)
    bool any_point_lights = false;     ///< whether some are point lights (Light::point)
    bool any_lane_lights = false;      ///< whether some are of those kinds (Light::lanes)
    bool any_aside_stage_lights = false;  ///< whether some aside lights are none of those (aside_emitter_stage's)
    /// Whether the sampler is not `independent`: then draw_stage draws each vertex's numbers
    /// with SamplerColumns (its permutations and jitter, in lanes too), where it draws the
    /// independent sampler's from each lane's stream; the other stages read them from
    /// columns either way.
    bool predrawn = false;
    /// Triangles as columns, one per vertex and axis (gathers of a Vec3's members GCC makes
    /// lane by lane): vertex j's axis a of triangle t at vertex[3 j + a][t], likewise its
    /// vertex normal (zero without them) in normal; Triangle::n in face_normal[a].
    struct TriangleColumns {
        std::vector<float> vertex[9], normal[9], face_normal[3];
        /// Append a triangle: its vertices p, vertex normals n and face normal.
        void add(const Vec3 p[3], const Vec3 n[3], const Vec3 &face) {
            for (int j = 0; j < 3; ++j) {
                for (int a = 0; a < 3; ++a) vertex[3 * j + a].push_back(p[j][a]), normal[3 * j + a].push_back(n[j][a]);
            }
            for (int a = 0; a < 3; ++a) face_normal[a].push_back(face[a]);
        }
    };
    // Each light's mesh (at most 8 triangles) in flat arrays, which the vector loop gathers
    // from with one base address each: light e's triangle t is entry 8 e + t. (The
    // environment's and the spheres' entries are a unit triangle, gathered and ignored.)
    std::vector<float> cdf;  ///< Shape::tri_cdf, 9 per light, padded with 2 (no u reaches it)
    TriangleColumns triangles;
    /// The meshes of the lights of more than 8 triangles (Light::large), which
    /// lane_emitter_stage searches in lanes: per light its triangle count, its Shape::tri_cdf's
    /// first entry in large_cdf and its first triangle in large_triangles; the other lights'
    /// entries point at a unit triangle, entry 0, whose CDF is large_cdf[0, 2). large_steps:
    /// the binary search's steps for the most triangles.
    std::vector<int> large_count, large_cdf_first, large_first;
    std::vector<float> large_cdf;
    TriangleColumns large_triangles;
    int large_steps = 0;
    /// A disk or cylinder light's centre, local_x, local_y, local_z and unflipped normal
    /// (Shape's; a cylinder's normal unused), as 15 columns of an entry per light (zeros for
    /// the other lights, a point light's position as the centre): axis a of vector v at
    /// light_frame[3 v + a]; then its radius and length at light_frame[15] and [16] (a
    /// cylinder's).
    std::vector<float> light_frame[17];
};

/// The flattened scene if render_fwd may trace `ctx`'s paths with trace_wavefront(), else
/// nothing: always nothing in builds without AVX2, whose vector stage stays scalar. (The
/// environment variable TORCH_RBPT_WAVEFRONT=0 turns it off, for comparisons; `aside` samples
/// every light that the vector stage does not sample itself with aside_emitter_stage, the
/// path of a new emitter type, for tests.)
std::optional<WavefrontScene> wavefront_scene(const RenderContext<RGB<float>> &ctx,
                                              const IntegratorSettings &cfg, const Camera &camera);

/// Takes out of ws.prim_quick the primitives whose material's shade-stage inputs read a
/// parameter marked in `watched` (render_bwd keeps their reads), so that the other vertices
/// are set up in lanes in renders logging the reads of those parameters; but for a bitmap
/// looked up in lanes (WavefrontScene::bitmaps) that is the only watched input of a lane
/// linear in it, whose lookups the lanes record themselves.
void exclude_watched_inputs(WavefrontScene &ws, const Scene &scene, const char *watched);

/// One sample to trace: its pixel, the pixel's seeds and its index among the pixel's samples.
struct WavefrontSample {
    int px, py;
    PixelSeed seed;
    int s;
};

/// Whether a lane's value is one factor of its sample weight in each of its reflectance and
/// transmittance inputs (the diffuse reflectance, the conductors' specular reflectance, the
/// dielectric's on the branch it samples), so that render_bwd can differentiate them in
/// lanes (WavefrontVertex). Not roughplastic: a sum of two lobes.
inline bool linear_in_inputs(WavefrontScene::Lane lane) {
    return lane == WavefrontScene::Diffuse || lane == WavefrontScene::Mirror ||
           lane == WavefrontScene::Glass || lane == WavefrontScene::RoughMirror;
}

/// What the backward pass in lanes (render_bwd) keeps of the paths it traces. A diffuse
/// reflectance rho enters a path's radiance linearly: every contribution gathered after its
/// vertex (the emitter sample there and all later emission) is a product with one factor rho,
/// the throughput's (a cosine-sampled diffuse weight is rho itself), the rest detached
/// (directions, MIS weights, roulette). So dL/drho = (L - L_before) / rho per channel, with
/// L_before the radiance gathered before the vertex, and a parameter read there receives
/// dL . (L - L_before) / rho times its read's weights: no tape. Likewise the other inputs of
/// lanes linear in them (linear_in_inputs), rho standing for the input; and an emitter's
/// radiance Le: each contribution C of its emission (found by a ray, or by an emitter
/// sample) gives dL . C / Le.
///
/// A rough conductor's roughness alpha (GGX's or Beckmann's) enters its vertex's emitter
/// sample through f(wo_e) and everything after through the BSDF sample's weight
/// f(wo_s) / pdf (the pdf detached), both as one factor common to the channels: with C_e the
/// emitter sample's contribution, dL/dalpha = C_e dlog f(wo_e) + (L - L_before - C_e)
/// dlog f(wo_s), dlog = d log f / d alpha (RoughConductorBSDF::dlog_dalpha, in closed form on
/// the float lanes' exp_poly and erfc_poly for Beckmann, where the tape takes libm's exp and
/// erf: the two differ by float rounding; conductor_dlog_stage, in SIMD lanes).
///
/// A roughplastic's diffuse reflectance rho is a factor of one of the two terms of its value,
/// f = ks spec + g(rho) base, so it is not one factor of the path's throughput; but like the
/// roughness it enters the vertex's emitter sample through f(wo_e) and everything after
/// through f(wo_s) / pdf, so with dlog_c = d log f_c / d rho_c per channel
/// (RoughPlasticBSDF::dlog_dreflectance), dL_c/drho_c = C_e,c dlog_c(wo_e) +
/// (L_c - L_before,c - C_e,c) dlog_c(wo_s): a Term record. (f_c holds ks_c spec as well, so
/// a zero channel of rho needs no `unit`.) Its roughness likewise, with dlog_c =
/// d log f_c / d alpha (RoughPlasticBSDF::dlog_dalpha): a second Term record.
///
/// With `direct`'s several samples per vertex (sub-paths), a record's L is the radiance
/// where its sub-path ended (an End record), not the sample's.
///
/// A zero channel of rho (a reflectance clamped to 0 in a fit) would make the quotient 0 / 0.
/// There the lanes take that channel of rho as 1 in the path's throughput (`unit`), but not
/// in its roulette throughput, which sees what path_li's roulette_factor sees (so the paths
/// are the tape's): the radiance the path then gathers in that channel after the vertex is
/// dL/drho's, up to the channel's next such vertex (beyond it every term holds rho twice,
/// whose derivative at 0 is 0), and render_bwd takes the true radiance of every other record
/// from the radiance at the channel's first such vertex (the path's true radiance in that
/// channel ends there).
struct WavefrontVertex {
    /// Emission: `gathered` is C, `value` Le; Input: `gathered` is L_before, `value` rho;
    /// Roughness and Term: `gathered` is L_before, `value` C_e, `dlog` towards wo_e and wo_s
    /// per channel (the same in all three for a roughness). End: `gathered` is the radiance
    /// where one of `direct`'s sub-paths ended (IntegratorSettings::sub_paths), where the
    /// terms of its records end (the sample's last sub-path ends at the sample's radiance).
    enum Kind { Emission = 0, Input = 1, Roughness = 2, Term = 3, End = 4 };
    int seq;            ///< the sample's index in the caller's arrays (-1: void)
    int kind;           ///< a Kind
    float gathered[3];
    float value[3];     ///< the input (rho), Le, or C_e
    ParamRead read;     ///< the differentiated parameter it came from
    float dlog[2][3] = {};
    /// Input: its zero channels were taken as 1 in the path's throughput (unit_zero_inputs),
    /// so the path's later radiance in those channels is what multiplies rho there.
    /// Emission: the zero channels of `value` (the true Le) were taken as 1 by the lanes
    /// (WavefrontRecord::unit_radiance), so `gathered` there is dC/dLe, and it is in the
    /// path's radiance though the true contribution is zero.
    bool unit = false;
};
struct WavefrontRecord {
    std::vector<WavefrontVertex> vertices;
    /// Append a vertex, written in place. (Built as a temporary and copied, it cost a
    /// store-forwarding stall at every record: its fields' narrow stores, then the copy's
    /// wide loads; 12% of trace_wavefront's samples in the cbox's backward pass.)
    WavefrontVertex &add(int seq, int kind, float g0, float g1, float g2, float v0, float v1, float v2,
                         const ParamRead &read) {
        WavefrontVertex &v = vertices.emplace_back();
        v.seq = seq, v.kind = kind;
        v.gathered[0] = g0, v.gathered[1] = g1, v.gathered[2] = g2;
        v.value[0] = v0, v.value[1] = v1, v.value[2] = v2;
        v.read = read;
        return v;
    }
    /// Per parameter: the channels (bits) of a differentiated radiance that are zero and that
    /// the lanes read as 1 (render_bwd sets it and the values the lanes read). Their
    /// emission records then carry dC/dLe in those channels; render_bwd takes those terms
    /// out of the path's radiance again.
    std::vector<uint8_t> unit_radiance;
    /// Per sample: 1 where its path read a differentiated parameter in any other way (then
    /// the tape re-traces it: see render_bwd).
    std::vector<char> tape;
};

/// Trace `n` samples, WavefrontBatch paths at a time (lanes freed by ended paths take the next
/// samples): their film positions into pos[i] and radiance into L[i], as the scalar loop
/// (Sampler, Camera::sample_position, sample_ray, path_li) would.
/// With `record` (the backward pass in lanes; ctx.params.log watching the differentiated
/// parameters), also the vertices whose linear inputs (linear_in_inputs) and the emission
/// that read those parameters.
void trace_wavefront(const RenderContext<RGB<float>> &ctx, const WavefrontScene &ws,
                     const IntegratorSettings &cfg, const Camera &camera,
                     const WavefrontSample *samples, int n, Vec2 *pos, RGB<float> *L,
                     WavefrontRecord *record = nullptr);

}  // namespace rbpt
