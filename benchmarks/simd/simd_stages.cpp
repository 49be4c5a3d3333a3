// What paths in SIMD lanes would gain on the shading side: three stages of a path vertex,
// each run over a batch of 256 independent lanes held as structure of arrays, twice: as a plain
// loop (one path after another, as the renderer shades today) and as an `omp simd` loop that
// GCC vectorises (16 lanes with AVX-512, 8 with AVX2), from the same inline code and with the
// extension's flags. Prints ns per lane for both and whether their results are bitwise equal.
//   camera       Sampler's PCG32 stream set-up and two uniforms (pcg32_seed, pcg32_next), a
//                film position, the perspective ray (Camera::perspective_ray)
//   interaction  a triangle hit (Geometry::interaction's mesh branch): vertex gathers, the
//                point and its error bound, the interpolated normal, the shading frame, wi
//   vertex       an emitter sample on a two-triangle area light (Geometry::sample_direction's
//                mesh branch), the diffuse BSDF towards it with the MIS weight, a
//                cosine-hemisphere BSDF sample and the next ray's origin (offset_p)
// The math (Vec3, Frame, the warps, the PCG32 stream, the camera ray) is the renderer's own
// headers; the other two stage bodies repeat the branches named above without their other
// cases, since a loop is vectorised only where every call in it is inlined and no branch
// leads out of line (the renderer's wavefront, csrc/wavefront.cpp, writes its vector stage
// the same way).
//
// Built and run by benchmarks/bench_simd.py. Prints one line per stage:
//   STAGE name=... scalar_ns=... simd_ns=... equal=0|1
// and exits with the number of stages whose two loops disagreed.
//
//   simd_stages [--reps N]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "camera.h"
#include "math.h"
#include "sampler.h"
#include "warp.h"

using namespace rbpt;

constexpr size_t N = 256;

struct alignas(64) Soa {
    float a[48][N];  // columns (Col), 256 lanes each
};
enum Col {
    PX, PY, PZ, NX, NY, NZ, AR, AG, AB, U0, U1, U2, U3, BR, BG, BB,
    LR, LG, LB, DX, DY, DZ, OX, OY, OZ, WR, WG, WB, EX, EY, EZ, TMIN, TMAX,
    SX, SY, SZ, TX, TY, TZ, WIX, WIY, WIZ, HU, HV
};

struct MeshData {
    const Vec3 *pos, *nrm, *face_n;
    const uint32_t *idx;
    float cdf[9];  // padded with 2 past the last triangle
    float area;
};

RBPT_INLINE float mis(float a, float b) {
    a *= a;
    b *= b;
    float w = a / (a + b);
    return std::isfinite(w) ? w : 0.f;
}

// ---- camera: Sampler's stream set-up and two uniforms, Camera::perspective_ray ----
RBPT_INLINE void camera_stage(const Camera &cam, uint64_t key, const uint32_t *pixel, uint64_t *st,
                              Soa &s, size_t i) {
    uint64_t state, inc;
    pcg32_seed(key, i, &state, &inc);
    float ux = uniform_float(pcg32_next(state, inc));
    float uy = uniform_float(pcg32_next(state, inc));
    st[i] = state;
    Vec2 pos{float(pixel[i] & 0xffff) + ux, float(pixel[i] >> 16) + uy};
    Ray r = cam.perspective_ray(pos);
    s.a[OX][i] = r.o.x, s.a[OY][i] = r.o.y, s.a[OZ][i] = r.o.z;
    s.a[DX][i] = r.d.x, s.a[DY][i] = r.d.y, s.a[DZ][i] = r.d.z;
    s.a[TMIN][i] = r.tmin, s.a[TMAX][i] = r.tmax;
}

// ---- interaction: Geometry::interaction's triangle branch (vertex normals) ----
RBPT_INLINE void interaction_stage(const MeshData &m, const uint32_t *prim, Soa &s, size_t i) {
    uint32_t t = prim[i];
    float b1 = s.a[HU][i], b2 = s.a[HV][i], b0 = 1.f - b1 - b2;
    uint32_t i0 = m.idx[3 * t], i1 = m.idx[3 * t + 1], i2 = m.idx[3 * t + 2];
    const Vec3 &p0 = m.pos[i0], &p1 = m.pos[i1], &p2 = m.pos[i2];
    Vec3 p = p0 * b0 + p1 * b1 + p2 * b2;
    Vec3 err = gamma(7) * (vabs(p0 * b0) + vabs(p1 * b1) + vabs(p2 * b2));
    Vec3 ns = normalize(m.nrm[i0] * b0 + m.nrm[i1] * b1 + m.nrm[i2] * b2);
    Frame f(ns);
    Vec3 wi = f.to_local(-Vec3{s.a[DX][i], s.a[DY][i], s.a[DZ][i]});
    s.a[PX][i] = p.x, s.a[PY][i] = p.y, s.a[PZ][i] = p.z;
    s.a[EX][i] = err.x, s.a[EY][i] = err.y, s.a[EZ][i] = err.z;
    s.a[SX][i] = f.s.x, s.a[SY][i] = f.s.y, s.a[SZ][i] = f.s.z;
    s.a[TX][i] = f.t.x, s.a[TY][i] = f.t.y, s.a[TZ][i] = f.t.z;
    s.a[NX][i] = ns.x, s.a[NY][i] = ns.y, s.a[NZ][i] = ns.z;
    s.a[WIX][i] = wi.x, s.a[WIY][i] = wi.y, s.a[WIZ][i] = wi.z;
}

/// next_float_up(v) where off > 0, next_float_down(v) where off < 0 (offset_p's rounding;
/// without next_float_up's case for infinities and NaN).
RBPT_INLINE float round_away(float v, float off) {
    uint32_t bits;
    std::memcpy(&bits, &v, 4);
    uint32_t up = v > 0.f ? bits + 1 : (v < 0.f ? bits - 1 : 1u);
    uint32_t dn = v > 0.f ? bits - 1 : (v < 0.f ? bits + 1 : 0x80000001u);
    bits = off > 0.f ? up : (off < 0.f ? dn : bits);
    std::memcpy(&v, &bits, 4);
    return v;
}

// ---- vertex: emitter sample (Geometry::sample_direction's mesh branch), diffuse + MIS,
// cosine-hemisphere sample, SurfaceInteraction::offset_p ----
RBPT_INLINE void vertex_stage(const MeshData &m, const Vec3 &Le, Soa &s, size_t i) {
    Vec3 ref{s.a[PX][i], s.a[PY][i], s.a[PZ][i]};
    Vec3 ns{s.a[NX][i], s.a[NY][i], s.a[NZ][i]};
    Vec3 albedo{s.a[AR][i], s.a[AG][i], s.a[AB][i]};
    Vec2 u{s.a[U0][i], s.a[U1][i]};
    uint32_t local = 0;
    for (int k = 1; k < 8; ++k) local += m.cdf[k] <= u.x;
    float width = m.cdf[local + 1] - m.cdf[local];
    u.x = std::min(width > 0.f ? (u.x - m.cdf[local]) / width : 0.f, 0.99999994f);
    Vec2 b = warp::square_to_uniform_triangle(u);
    float b0 = 1.f - b.x - b.y;
    uint32_t i0 = m.idx[3 * local], i1 = m.idx[3 * local + 1], i2 = m.idx[3 * local + 2];
    Vec3 p = m.pos[i0] * b0 + m.pos[i1] * b.x + m.pos[i2] * b.y;
    Vec3 n = normalize(m.nrm[i0] * b0 + m.nrm[i1] * b.x + m.nrm[i2] * b.y);
    Vec3 d = p - ref;
    float dist2 = squared_norm(d), dist = std::sqrt(dist2);
    d = d * (1.f / dist);
    float cos_area = std::abs(dot(m.face_n[local], d));
    float pdf = cos_area > 0.f ? dist2 / (m.area * cos_area) : 0.f;
    Frame fr(ns);
    Vec3 wo = fr.to_local(d);
    float c = wo.z > 0.f ? wo.z : 0.f;
    float w = mis(pdf, c * InvPi);
    float k = c * InvPi * w / pdf;
    k = dot(n, d) < 0.f ? k : 0.f;
    k = pdf > 0.f ? k : 0.f;
    s.a[LR][i] += s.a[BR][i] * albedo.x * Le.x * k;
    s.a[LG][i] += s.a[BG][i] * albedo.y * Le.y * k;
    s.a[LB][i] += s.a[BB][i] * albedo.z * Le.z * k;
    Vec3 dw = fr.to_world(warp::square_to_cosine_hemisphere({s.a[U2][i], s.a[U3][i]}));
    // offset_p along the normal (here the NX..NZ column) past the error bound EX..EZ
    Vec3 err{s.a[EX][i], s.a[EY][i], s.a[EZ][i]};
    Vec3 off = ns * dot(vabs(ns), err);
    off = dot(ns, dw) < 0.f ? -off : off;
    Vec3 o = ref + off;
    o = {round_away(o.x, off.x), round_away(o.y, off.y), round_away(o.z, off.z)};
    s.a[OX][i] = o.x, s.a[OY][i] = o.y, s.a[OZ][i] = o.z;
    s.a[DX][i] = dw.x, s.a[DY][i] = dw.y, s.a[DZ][i] = dw.z;
    s.a[WR][i] = s.a[BR][i] * albedo.x;
    s.a[WG][i] = s.a[BG][i] * albedo.y;
    s.a[WB][i] = s.a[BB][i] * albedo.z;
}

struct Inputs {
    Camera cam;
    MeshData light, mesh;
    Vec3 Le{17.f, 12.f, 4.f};
    uint32_t pixel[N], prim[N];
    uint64_t key = 0x1234567890abcdefull;
};

#define SCALAR [[gnu::noinline, gnu::optimize("no-tree-loop-vectorize")]]
#define VECTOR [[gnu::noinline]]
SCALAR void camera_scalar(const Inputs &in, uint64_t *st, Soa &s) {
    const Camera cam = in.cam;
    const uint64_t key = in.key;
    const uint32_t *pixel = in.pixel;
    for (size_t i = 0; i < N; ++i) camera_stage(cam, key, pixel, st, s, i);
}
VECTOR void camera_simd(const Inputs &in, uint64_t *st, Soa &s) {
    const Camera cam = in.cam;
    const uint64_t key = in.key;
    const uint32_t *pixel = in.pixel;
#pragma omp simd
    for (size_t i = 0; i < N; ++i) camera_stage(cam, key, pixel, st, s, i);
}
SCALAR void interaction_scalar(const Inputs &in, uint64_t *, Soa &s) {
    const MeshData m = in.mesh;
    const uint32_t *prim = in.prim;
    for (size_t i = 0; i < N; ++i) interaction_stage(m, prim, s, i);
}
VECTOR void interaction_simd(const Inputs &in, uint64_t *, Soa &s) {
    const MeshData m = in.mesh;
    const uint32_t *prim = in.prim;
#pragma omp simd
    for (size_t i = 0; i < N; ++i) interaction_stage(m, prim, s, i);
}
SCALAR void vertex_scalar(const Inputs &in, uint64_t *, Soa &s) {
    const MeshData m = in.light;
    const Vec3 Le = in.Le;
    for (size_t i = 0; i < N; ++i) vertex_stage(m, Le, s, i);
}
VECTOR void vertex_simd(const Inputs &in, uint64_t *, Soa &s) {
    const MeshData m = in.light;  // locals: the loop's stores cannot alias them
    const Vec3 Le = in.Le;
#pragma omp simd
    for (size_t i = 0; i < N; ++i) vertex_stage(m, Le, s, i);
}

int main(int argc, char **argv) {
    int reps = 20000;
    for (int a = 1; a + 1 < argc; ++a)
        if (std::string(argv[a]) == "--reps") reps = std::max(1, std::atoi(argv[a + 1]));
    std::mt19937 rng(1);
    std::uniform_real_distribution<float> U(0.f, 1.f);
    Inputs in;
    in.cam.origin = {0.f, 1.f, 3.9f};
    in.cam.axis_x = {-1.f, 0.f, 0.f}, in.cam.axis_y = {0.f, 1.f, 0.f}, in.cam.axis_z = {0.f, 0.f, -1.f};
    in.cam.film_width = in.cam.film_height = 256;
    in.cam.tan_half_x = in.cam.tan_half_y = 0.35f;
    // The light: a quad of two triangles; the mesh: 4096 random triangles with vertex normals.
    std::vector<Vec3> lpos = {{-0.24f, 1.98f, -0.22f}, {0.23f, 1.98f, -0.22f}, {0.23f, 1.98f, 0.16f}, {-0.24f, 1.98f, 0.16f}};
    std::vector<Vec3> lnrm(4, Vec3{0.f, -1.f, 0.f}), lface(2, Vec3{0.f, -1.f, 0.f});
    std::vector<uint32_t> lidx = {0, 1, 2, 0, 2, 3};
    in.light = {lpos.data(), lnrm.data(), lface.data(), lidx.data(), {0.f, 0.5f, 1.f, 2.f, 2.f, 2.f, 2.f, 2.f, 2.f}, 0.47f * 0.38f};
    const uint32_t T = 4096, V = 3 * T;
    std::vector<Vec3> mpos(V), mnrm(V);
    std::vector<uint32_t> midx(V);
    for (uint32_t v = 0; v < V; ++v) {
        mpos[v] = {U(rng) * 2 - 1, U(rng) * 2, U(rng) * 2 - 1};
        mnrm[v] = normalize(Vec3{U(rng) - 0.5f, U(rng) - 0.5f, U(rng) - 0.5f});
        midx[v] = v;
    }
    in.mesh = {mpos.data(), mnrm.data(), nullptr, midx.data(), {}, 0.f};
    Soa base;
    for (size_t c = 0; c < 48; ++c)
        for (size_t i = 0; i < N; ++i) base.a[c][i] = U(rng);
    for (size_t i = 0; i < N; ++i) {
        Vec3 n = normalize(Vec3{U(rng) - 0.5f, U(rng) - 0.5f, U(rng) - 0.5f});
        base.a[NX][i] = n.x, base.a[NY][i] = n.y, base.a[NZ][i] = n.z;
        base.a[PX][i] = U(rng) * 2 - 1, base.a[PY][i] = U(rng) * 1.9f, base.a[PZ][i] = U(rng) * 2 - 1;
        base.a[EX][i] = base.a[EY][i] = base.a[EZ][i] = 1e-6f;
        float hu = U(rng), hv = U(rng);
        if (hu + hv > 1.f) hu = 1.f - hu, hv = 1.f - hv;
        base.a[HU][i] = hu, base.a[HV][i] = hv;
        in.pixel[i] = uint32_t(i % 256) | uint32_t(i / 256 * 7 + 40) << 16;
        in.prim[i] = uint32_t(rng() % T);
    }
    using Fn = void (*)(const Inputs &, uint64_t *, Soa &);
    struct Stage {
        const char *name;
        Fn scalar, simd;
    } stages[] = {{"camera", camera_scalar, camera_simd},
                  {"interaction", interaction_scalar, interaction_simd},
                  {"vertex", vertex_scalar, vertex_simd}};
    int failures = 0;
    for (const Stage &st : stages) {
        static Soa a, b;
        uint64_t sa[N], sb[N];
        double best_s = 1e30, best_v = 1e30;
        for (int round = 0; round < 3; ++round) {
            a = base, b = base;
            auto t0 = std::chrono::steady_clock::now();
            for (int r = 0; r < reps; ++r) st.scalar(in, sa, a);
            auto t1 = std::chrono::steady_clock::now();
            for (int r = 0; r < reps; ++r) st.simd(in, sb, b);
            auto t2 = std::chrono::steady_clock::now();
            best_s = std::min(best_s, std::chrono::duration<double, std::nano>(t1 - t0).count() / (double(reps) * N));
            best_v = std::min(best_v, std::chrono::duration<double, std::nano>(t2 - t1).count() / (double(reps) * N));
        }
        bool same = std::memcmp(&a, &b, sizeof a) == 0 && std::memcmp(sa, sb, sizeof sa) == 0;
        failures += !same;
        std::printf("STAGE name=%s scalar_ns=%.3f simd_ns=%.3f equal=%d\n", st.name, best_s, best_v, int(same));
    }
    return failures;
}
