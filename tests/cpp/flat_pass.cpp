// BVH::intersect_columns (the flat pass: every triangle against rays in SIMD lanes, a
// parallelogram's two as one quad) against BVH::intersect (the traversal), bitwise, the
// shadow rays through BVH::root_masks' masks against BVH::occluded, and ShapeBoxes::entered
// against the hits it must not skip, in whichever build this is compiled for: test_bvh's
// test14 compiles it for AVX2 and for this machine, whose chunk tests, masks and box tests
// are different codes. Prints the number of rays, of hits, of blocked rays, of flagged rays,
// of rays whose hit or blocking differs or whose hit was not flagged, and a hash of every
// hit's bits, mask and flag (the same in every build).
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <vector>

#include "bvh.h"

using namespace rbpt;

namespace {

uint32_t state = 12345u;
float uniform() {  // in [0, 1)
    state = state * 1664525u + 1013904223u;
    return float(state >> 8) * (1.f / 16777216.f);
}
float uniform(float lo, float hi) { return lo + (hi - lo) * uniform(); }

/// Append a mesh shape of `tris` (vertex triples) to `g`.
void add_mesh(Geometry &g, const std::vector<Vec3> &v, const std::vector<uint32_t> &tris) {
    Shape s;
    s.tri_begin = uint32_t(g.triangles.size()), s.tri_count = uint32_t(tris.size() / 3);
    s.vertex_begin = uint32_t(g.positions.size()), s.vertex_count = uint32_t(v.size());
    const uint32_t shape = uint32_t(g.shapes.size());
    for (size_t i = 0; i < tris.size(); i += 3)
        g.triangles.push_back({{s.vertex_begin + tris[i], s.vertex_begin + tris[i + 1], s.vertex_begin + tris[i + 2]}, shape});
    g.positions.insert(g.positions.end(), v.begin(), v.end());
    g.shapes.push_back(s);
}

/// A box [lo, hi] of 12 triangles (a face's two share its diagonal).
void add_box(Geometry &g, Vec3 lo, Vec3 hi) {
    std::vector<Vec3> v;
    for (int i = 0; i < 8; ++i) v.push_back({i & 1 ? hi.x : lo.x, i & 2 ? hi.y : lo.y, i & 4 ? hi.z : lo.z});
    add_mesh(g, v, {0, 2, 1, 1, 2, 3, 4, 5, 6, 5, 7, 6, 0, 1, 4, 1, 5, 4, 2, 6, 3, 3, 6, 7, 0, 4, 2, 2, 4, 6, 1, 3, 5, 3, 7, 5});
}

/// A rectangle in the plane y = `y` over [x0, x1] x [z0, z1] (two triangles).
void add_quad(Geometry &g, float y, float x0, float x1, float z0, float z1) {
    add_mesh(g, {{x0, y, z0}, {x1, y, z0}, {x1, y, z1}, {x0, y, z1}}, {0, 1, 2, 0, 2, 3});
}

uint64_t hash_bits(uint64_t h, const void *p, size_t n) {
    const unsigned char *b = static_cast<const unsigned char *>(p);
    for (size_t i = 0; i < n; ++i) h = (h ^ b[i]) * 1099511628211ull;
    return h;
}

}  // namespace

int main() {
    uint64_t hash = 1469598103934665603ull;
    long rays = 0, hits = 0, blocked = 0, entered = 0, differ = 0;
    // 14 triangles (each hit's rounding bound in the pass) and 30 (deferred to the nearest
    // hit: BVH::flat_rounding_check); both below BVH::FlatTriangles, so the tree is flat.
    for (int variant = 0; variant < 2; ++variant) {
        Geometry g;
        add_box(g, {0.f, -0.5f, -0.5f}, {1.f, 0.5f, 0.5f});
        add_quad(g, -1.f, -3.f, 3.f, -3.f, 3.f);
        if (variant == 1) {
            add_quad(g, -1.f, -1.75f, -0.25f, 0.25f, 1.75f);  // a decal in the quad's plane (ties)
            add_box(g, {1.5f, -0.2f, -0.45f}, {2.4f, 0.7f, 0.45f});
        }
        g.prepare();
        BVH bvh;
        bvh.build(g);
        if (!bvh.flat()) {
            std::printf("not flat\n");
            return 1;
        }
        // Targets: the first box's vertices, edges' midpoints and random points of its edges
        // and face diagonals (edge functions that round to zero, ties between a face's
        // triangles), points of the quad's plane (the decal's ties), random points.
        std::vector<Vec3> corners;
        for (int i = 0; i < 8; ++i) corners.push_back({i & 1 ? 1.f : 0.f, i & 2 ? 0.5f : -0.5f, i & 4 ? 0.5f : -0.5f});
        const int n = 6144;
        std::vector<float> ox(n), oy(n), oz(n), dx(n), dy(n), dz(n), tmin(n), tmax(n);
        for (int k = 0; k < n; ++k) {
            Vec3 o{uniform(-5.f, 5.f), uniform(-5.f, 5.f), uniform(-5.f, 5.f)}, target;
            const int kind = k % 8;
            if (kind == 0) {
                target = corners[k / 8 % 8];
            } else if (kind <= 3) {
                const Vec3 a = corners[int(uniform() * 8.f)], b = corners[int(uniform() * 8.f)];
                target = kind == 1 ? (a + b) * 0.5f : a + (b - a) * uniform();
            } else if (kind == 4) {
                target = {uniform(-1.75f, -0.25f), -1.f, uniform(0.25f, 1.75f)};
            } else if (kind == 5) {  // from the quad's surface (or a rounding off it)
                o = {uniform(-2.f, 2.f), -1.f + (uniform() < 0.5f ? 0.f : uniform(-1e-4f, 1e-4f)), uniform(-2.f, 2.f)};
                target = {uniform(-1.5f, 2.5f), uniform(-0.9f, 1.f), uniform(-1.f, 1.f)};
            } else if (kind == 6) {  // along an axis from a grid of quarters
                const int axis = int(uniform() * 3.f);
                for (int a = 0; a < 3; ++a) o[a] = std::round(uniform(-1.2f, 1.2f) * 4.f) / 4.f;
                o[axis] = uniform() < 0.5f ? -3.f : 3.f;
                target = o;
                target[axis] = 0.f;
            } else {
                target = {uniform(-1.5f, 2.5f), uniform(-1.5f, 1.5f), uniform(-1.5f, 1.5f)};
            }
            Vec3 d = normalize(target - o);
            if (k == 7) o.x = INFINITY;
            if (k == 15) o.y = NAN;
            if (k == 23) d = {0.f, 0.f, 0.f};
            if (k == 31) d = {NAN, 1.f, 0.f};
            ox[k] = o.x, oy[k] = o.y, oz[k] = o.z, dx[k] = d.x, dy[k] = d.y, dz[k] = d.z;
            tmin[k] = uniform() < 0.1f ? uniform() : 0.f;
            tmax[k] = uniform() < 0.2f ? uniform() * 6.f : INFINITY;
        }
        std::vector<float> t(n), u(n), v(n);
        std::vector<uint32_t> prim(n);
        for (int k0 = 0; k0 < n; k0 += BVH::MaxColumns) {
            const int m = std::min(BVH::MaxColumns, n - k0);
            bvh.intersect_columns({&ox[k0], &oy[k0], &oz[k0], &dx[k0], &dy[k0], &dz[k0], &tmin[k0], &tmax[k0]}, m,
                                  {&t[k0], &u[k0], &v[k0], &prim[k0]});
        }
        for (int k = 0; k < n; ++k) {
            Ray ray;
            ray.o = {ox[k], oy[k], oz[k]}, ray.d = {dx[k], dy[k], dz[k]}, ray.tmin = tmin[k], ray.tmax = tmax[k];
            Hit hit;
            bvh.intersect(ray, &hit);
            const float a[3] = {t[k], u[k], v[k]}, b[3] = {hit.t, hit.u, hit.v};
            differ += std::memcmp(a, b, sizeof(a)) != 0 || prim[k] != hit.prim;
            hits += hit.prim != ~0u;
            hash = hash_bits(hash_bits(hash, a, sizeof(a)), &prim[k], sizeof(uint32_t));
        }
        // The root's masks (BVH::root_masks: in AVX2 or AVX-512 intrinsics where the build has
        // them) and the shadow rays' test through them (the wavefront's, in trees of one node)
        // against occluded(), and the masks into the hash.
        // (In batches of 250 rays, so that each ends with a part of a register: 10 lanes of
        // AVX-512's 16, 2 of AVX2's 8, which the loops after the registers take.)
        constexpr int Batch = 250;
        static_assert(Batch <= BVH::MaxColumns && Batch % 16 == 10, "batches ending in part of a register");
        std::vector<int> mask(n);
        for (int k0 = 0; k0 < n; k0 += Batch) {
            const int m = std::min(Batch, n - k0);
            bvh.root_masks({&ox[k0], &oy[k0], &oz[k0], &dx[k0], &dy[k0], &dz[k0], &tmin[k0], &tmax[k0]}, m, &mask[k0]);
        }
        for (int k = 0; k < n; ++k) {
            Ray ray;
            ray.o = {ox[k], oy[k], oz[k]}, ray.d = {dx[k], dy[k], dz[k]}, ray.tmin = tmin[k], ray.tmax = tmax[k];
            const bool through_masks = bvh.occluded_children(ray, mask[k]);
            differ += through_masks != bvh.occluded(ray);
            blocked += through_masks;
            hash = hash_bits(hash, &mask[k], sizeof(int));
        }
        // ShapeBoxes::entered (in intrinsics too) over the first box and the quad: it must
        // flag every ray whose nearest hit is on one of them (a ray it does not flag skips
        // its query), and its flags go into the hash.
        ShapeBoxes boxes;
        boxes.add(g, 0), boxes.add(g, 1);
        std::vector<int> enters(n);
        for (int k0 = 0; k0 < n; k0 += Batch) {
            const int m = std::min(Batch, n - k0);
            boxes.entered({&ox[k0], &oy[k0], &oz[k0], &dx[k0], &dy[k0], &dz[k0], &tmin[k0], &tmax[k0]}, m, &enters[k0]);
        }
        for (int k = 0; k < n; ++k) {
            const bool on_them = prim[k] != ~0u && g.triangles[prim[k]].shape <= 1;
            differ += on_them && !enters[k];
            entered += enters[k];
            hash = hash_bits(hash, &enters[k], sizeof(int));
        }
        rays += n;
    }
    std::printf("rays %ld hits %ld blocked %ld entered %ld differ %ld hash %016llx\n", rays, hits, blocked, entered,
                differ, (unsigned long long)hash);
    return differ == 0 ? 0 : 1;
}
