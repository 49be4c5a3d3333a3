// Shapes: triangle meshes and the analytic sphere, disk and cylinder. Ray-primitive
// intersection, the surface interaction at a hit, and sampling points on shapes for area
// emitters.
#pragma once

#include <cstdint>
#include <vector>

#include "math.h"
#include "simd.h"

namespace rbpt {

enum class ShapeKind { Mesh, Sphere, Disk, Cylinder };

struct Shape {
    ShapeKind kind = ShapeKind::Mesh;
    int bsdf = -1;
    int emitter = -1;
    bool flip_normals = false;
    float area = 0.f;
    // Mesh: a range of Geometry::triangles and a CDF over their areas for sampling.
    uint32_t tri_begin = 0, tri_count = 0;
    uint32_t vertex_begin = 0, vertex_count = 0;  ///< its vertices in Geometry::positions
    /// Parameters of its `vertex_color` and `face_color` (MeshAttribute), -1 if absent.
    int attribute_param[2] = {-1, -1};
    int attribute_channels[2] = {0, 0};
    bool has_normals = false, has_uvs = false;
    /// Whether anything reads the uv of its surface points (a texture of its BSDF): the
    /// surface interaction computes uv only then (a sphere's costs an atan2 and an acos).
    bool needs_uv = true;
    std::vector<float> tri_cdf;
    // Sphere: centre, radius and the rotation to its local frame (for uv).
    // Disk: object-to-world affine map, p = center + local_x x + local_y y + local_z z (the
    //   columns of to_world's linear part), from the unit disk at z = 0; `normal` is its
    //   (unflipped) world normal.
    // Cylinder: axis from `center` along the unit local_z, of `length` and `radius`;
    //   local_x, local_y (unit) fix the origin of the angle for uv.
    Vec3 center;
    float radius = 1.f;
    Vec3 local_x{1, 0, 0}, local_y{0, 1, 0}, local_z{0, 0, 1};
    float length = 1.f;
    Vec3 normal{0, 0, 1};
    double to_object[3][4] = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}};  ///< disk, cylinder

    /// `p` in the shape's object space (disk, cylinder), in double precision.
    void object_point(const double p[3], double out[3]) const {
        for (int i = 0; i < 3; ++i)
            out[i] = to_object[i][0] * p[0] + to_object[i][1] * p[1] + to_object[i][2] * p[2] +
                     to_object[i][3];
    }
    /// A point of object space (disk, cylinder) in world space, rounded once to float.
    Vec3 world_point(const double q[3]) const {
        Vec3 p;
        for (int i = 0; i < 3; ++i)
            p[i] = float(double(center[i]) + double(local_x[i]) * q[0] + double(local_y[i]) * q[1] +
                         double(local_z[i]) * q[2]);
        return p;
    }
};

struct Triangle {
    uint32_t v[3];
    uint32_t shape;
    Vec3 n;  ///< unit geometric normal, normalize((p1 - p0) x (p2 - p0)), set by prepare()
};

/// The nearest hit found by the BVH: primitive id and its parametric coordinates.
struct Hit {
    float t = Infinity;
    uint32_t prim = ~0u;
    float u = 0.f, v = 0.f;  ///< barycentrics of vertices 1 and 2 (triangles)
    bool valid() const { return prim != ~0u; }
};

/// Everything the integrator needs to know about a surface point.
struct SurfaceInteraction {
    bool valid = false;
    float t = Infinity;
    Vec3 p;
    Vec3 p_error;  ///< bound on the rounding error of each coordinate of p
    Vec3 n;        ///< geometric normal (unit, flipped with flip_normals)
    Frame sh_frame;  ///< shading frame around the interpolated normal
    Vec2 uv;       ///< texture coordinates (zero unless the shape needs_uv, see interaction())
    /// Direction towards the ray origin, in the shading frame; for a ray that escaped (`valid`
    /// false), in world space: -ray.d, Mitsuba's convention, the direction an environment
    /// emitter's emitter_eval() and emitter_pdf() look up.
    Vec3 wi;
    int shape = -1;
    uint32_t tri = ~0u;      ///< triangle hit (meshes), for mesh attributes
    float b1 = 0.f, b2 = 0.f;  ///< its barycentrics of vertices 1 and 2

    Vec3 to_local(const Vec3 &v) const { return sh_frame.to_local(v); }
    Vec3 to_world(const Vec3 &v) const { return sh_frame.to_world(v); }

    /// A ray origin on the side of `d`: p moved along the geometric normal just past its
    /// rounding-error box, then rounded away from the surface (pbrt-v4's OffsetRayOrigin).
    /// Unlike Mitsuba's offset, which grows with the distance from the world origin, this
    /// follows the actual error of p, so scenes far from the origin keep contact shadows.
    RBPT_INLINE Vec3 offset_p(const Vec3 &d) const {
        Vec3 offset = n * dot(vabs(n), p_error);
        if (dot(n, d) < 0.f) offset = -offset;
        Vec3 o = p + offset;
        for (int i = 0; i < 3; ++i) {
            if (offset[i] > 0.f) o[i] = next_float_up(o[i]);
            else if (offset[i] < 0.f) o[i] = next_float_down(o[i]);
        }
        return o;
    }
    /// The ray from p along d, written into `ray` field by field. (Assigning a returned Ray
    /// to a loop's ray made GCC assemble it on the stack piecewise and reload it as one
    /// 32-byte vector: a store-forwarding stall that cost 3-4% of a path-traced render.)
    RBPT_INLINE void spawn_ray(const Vec3 &d, Ray *ray) const {
        ray->o = offset_p(d);
        ray->d = d;
        ray->tmin = 0.f;
        ray->tmax = Infinity;
    }
    RBPT_INLINE Ray spawn_ray(const Vec3 &d) const {
        Ray r;
        spawn_ray(d, &r);
        return r;
    }
    RBPT_INLINE Ray spawn_ray_to(const Vec3 &target) const {
        Ray r;
        r.o = offset_p(target - p);
        Vec3 d = target - r.o;
        float dist = norm(d);
        r.d = d / dist;
        r.tmax = dist * (1.f - ShadowEpsilon);
        return r;
    }
};

/// A point sampled on a shape as seen from a reference point, with its solid-angle density.
struct DirectionSample {
    Vec3 p, n, d;
    float dist = 0.f;
    float pdf = 0.f;
};

/// Per-ray constants of the watertight ray-triangle test (Woop, Benthin and Wald 2013).
struct RayPrecomp {
    int kx, ky, kz;
    float sx, sy, sz;
    explicit RayPrecomp(const Vec3 &d) {
        float ax = std::abs(d.x), ay = std::abs(d.y), az = std::abs(d.z);
        kz = (ax > ay) ? (ax > az ? 0 : 2) : (ay > az ? 1 : 2);
        kx = (kz + 1) % 3;
        ky = (kx + 1) % 3;
        if (d[kz] < 0.f) std::swap(kx, ky);
        sx = d[kx] / d[kz];
        sy = d[ky] / d[kz];
        sz = 1.f / d[kz];
    }
};

/// Up to simd::Width triangles laid out for intersect_triangles: v[vertex][axis][lane].
struct alignas(32) TrianglePack {
    float v[3][3][simd::Width];
};

/// Per-ray constants of intersect_triangles: those of RayPrecomp and the origin, permuted
/// and splatted over the lanes.
struct RayPrecompPack {
    int kx, ky, kz;
    simd::V ox, oy, oz, sx, sy, sz;
    RayPrecompPack() = default;
    explicit RayPrecompPack(const Ray &ray) {
        RayPrecomp pc(ray.d);
        kx = pc.kx;
        ky = pc.ky;
        kz = pc.kz;
        ox = simd::set1(ray.o[kx]);
        oy = simd::set1(ray.o[ky]);
        oz = simd::set1(ray.o[kz]);
        sx = simd::set1(pc.sx);
        sy = simd::set1(pc.sy);
        sz = simd::set1(pc.sz);
    }
};

/// simd::Width watertight ray-triangle tests at once (Woop, Benthin and Wald 2013): the
/// vertices are sheared into the ray's frame and the hit is decided by the signs of three 2D
/// edge functions, so no ray slips between triangles sharing an edge; an edge function that
/// is exactly zero is recomputed in double precision. Tests the lanes set in `lanes` and returns
/// the mask of those hit in (tmin, tmax), with their t and barycentrics in t/u/v[lane].
inline int intersect_triangles(const RayPrecompPack &pc, const TrianglePack &pack, int lanes,
                               float tmin, float tmax, float t_out[simd::Width],
                               float u_out[simd::Width], float v_out[simd::Width]) {
    using namespace simd;
    constexpr int W = Width;
    // Translate to the ray origin and shear (per vertex: x, y and the unscaled z).
    V x[3], y[3], z[3];
    for (int k = 0; k < 3; ++k) {
        z[k] = sub(load(pack.v[k][pc.kz]), pc.oz);
        x[k] = sub(sub(load(pack.v[k][pc.kx]), pc.ox), mul(pc.sx, z[k]));
        y[k] = sub(sub(load(pack.v[k][pc.ky]), pc.oy), mul(pc.sy, z[k]));
    }
    // Edge functions U (edge bc), V (edge ca), W (edge ab).
    V U = sub(mul(x[2], y[1]), mul(y[2], x[1]));
    V Ve = sub(mul(x[0], y[2]), mul(y[0], x[2]));
    V We = sub(mul(x[1], y[0]), mul(y[1], x[0]));
    const V z0 = zero();
    int on_edge = mask(bit_or(bit_or(eq(U, z0), eq(Ve, z0)), eq(We, z0))) & lanes;
    if (on_edge) {
        // Edge case: redo the 2D edge tests of those lanes in double (watertight edges).
        alignas(32) float ax[W], ay[W], bx[W], by[W], cx[W], cy[W], u[W], v[W], w[W];
        store(ax, x[0]); store(ay, y[0]);
        store(bx, x[1]); store(by, y[1]);
        store(cx, x[2]); store(cy, y[2]);
        store(u, U); store(v, Ve); store(w, We);
        for (int i = 0; i < W; ++i) {
            if (!(on_edge >> i & 1)) continue;
            u[i] = float(double(cx[i]) * by[i] - double(cy[i]) * bx[i]);
            v[i] = float(double(ax[i]) * cy[i] - double(ay[i]) * cx[i]);
            w[i] = float(double(bx[i]) * ay[i] - double(by[i]) * ax[i]);
        }
        U = load(u); Ve = load(v); We = load(w);
    }
    // Inside when the edge functions do not differ in sign.
    V neg = bit_or(bit_or(lt(U, z0), lt(Ve, z0)), lt(We, z0));
    V pos = bit_or(bit_or(gt(U, z0), gt(Ve, z0)), gt(We, z0));
    V det = add(add(U, Ve), We);
    int inside = ~mask(bit_and(neg, pos)) & mask(neq(det, z0)) & lanes;
    if (!inside) return 0;
    V T = add(add(mul(U, mul(pc.sz, z[0])), mul(Ve, mul(pc.sz, z[1]))), mul(We, mul(pc.sz, z[2])));
    V inv_det = div(set1(1.f), det);
    V t = mul(T, inv_det);
    int hit = mask(bit_and(gt(t, set1(tmin)), lt(t, set1(tmax)))) & inside;
    if (!hit) return 0;
    // Keep only hits farther than the rounding error of t (pbrt-v4's conservative bound), so a
    // ray leaving a surface from its error-bounded offset origin never finds that surface.
    auto abs3 = [](const V a[3]) { return max(abs(a[0]), max(abs(a[1]), abs(a[2]))); };
    V max_zt = mul(abs(pc.sz), abs3(z)), max_xt = abs3(x), max_yt = abs3(y);
    V delta_z = mul(set1(gamma(3)), max_zt);
    V delta_x = mul(set1(gamma(5)), add(max_xt, max_zt));
    V delta_y = mul(set1(gamma(5)), add(max_yt, max_zt));
    V delta_e = mul(set1(2.f), add(mul(set1(gamma(2)), mul(max_xt, max_yt)),
                                   add(mul(delta_y, max_xt), mul(delta_x, max_yt))));
    V e[3] = {U, Ve, We};
    V max_e = abs3(e);
    V delta_t = mul(mul(set1(3.f), add(mul(set1(gamma(3)), mul(max_e, max_zt)),
                                       add(mul(delta_e, max_zt), mul(delta_z, max_e)))),
                    abs(inv_det));
    hit &= mask(gt(t, delta_t));
    if (!hit) return 0;
    store(t_out, t);
    store(u_out, mul(Ve, inv_det));
    store(v_out, mul(We, inv_det));
    return hit;
}

/// The ray-sphere quadratic A t^2 + B t + C in double precision, its discriminant, and (roots())
/// its roots in order (NaN where the discriminant is negative). Branch-free, so that
/// BVH::flat_sphere's lanes and intersect_sphere() share it.
struct SphereQuadratic {
    double A, B, C, disc;
    RBPT_INLINE SphereQuadratic(const Vec3 &o, const Vec3 &d, const Vec3 &center, float radius) {
        double ox = double(o.x) - center.x, oy = double(o.y) - center.y, oz = double(o.z) - center.z;
        double dx = d.x, dy = d.y, dz = d.z;
        A = dx * dx + dy * dy + dz * dz;
        B = 2.0 * (ox * dx + oy * dy + oz * dz);
        C = ox * ox + oy * oy + oz * oz - double(radius) * radius;
        disc = B * B - 4.0 * A * C;
    }
    /// The roots (lo, hi).
    RBPT_INLINE void roots(double *lo, double *hi) const {
        double q = -0.5 * (B + std::copysign(std::sqrt(disc), B));
        double t0 = q / A, t1 = (q != 0.0) ? C / q : t0;
        *lo = t0 > t1 ? t1 : t0;
        *hi = t0 > t1 ? t0 : t1;
    }
};

/// Ray-sphere intersection in double precision; the nearest root in (tmin, tmax).
inline bool intersect_sphere(const Ray &ray, const Vec3 &center, float radius, float tmin,
                             float tmax, float *t_out) {
    const SphereQuadratic quadratic(ray.o, ray.d, center, radius);
    if (quadratic.disc < 0.0) return false;
    double lo, hi;
    quadratic.roots(&lo, &hi);
    if (lo > tmin && lo < tmax) { *t_out = float(lo); return true; }
    if (hi > tmin && hi < tmax) { *t_out = float(hi); return true; }
    return false;
}

/// A hit on a disk or cylinder: t, and for disks the object-space x and y of the hit.
struct AnalyticHit {
    float t, u, v;
    bool hit;
};

/// Ray intersection with a disk (the unit disk at z = 0 in object space) or a cylinder
/// (radius `radius` around the object-space z axis, z in [0, length], no caps), in double
/// precision. Out of line (shapes.cpp), called from BVH::intersect_others.
AnalyticHit intersect_disk_or_cylinder(const Ray &ray, const Shape &s, float tmin,
                                                     float tmax);

/// intersect_disk_or_cylinder()'s test of a ray at lo + t ld in the disk's (Disk) or the
/// cylinder's object space, in double and without branches (its conditions are selects of
/// float flags, 1 or 0, so that BVH::flat_other's loop over rays in lanes vectorises): the
/// flag, with t and, for a disk, the hit's object-space x and y in u and v (a cylinder's 0),
/// which hold anything where the flag is 0.
template <bool Disk>
RBPT_INLINE float disk_or_cylinder_test(const double lo[3], const double ld[3], double tmin, double tmax,
                                        double radius, double length, float *t_out, float *u_out, float *v_out) {
    if constexpr (Disk) {
        const double t = -lo[2] / ld[2];
        const double x = lo[0] + t * ld[0], y = lo[1] + t * ld[1];
        float hit = t > tmin ? 1.f : 0.f;
        hit = t < tmax ? hit : 0.f;
        hit = x * x + y * y > 1.0 ? 0.f : hit;
        *t_out = float(t), *u_out = float(x), *v_out = float(y);
        return ld[2] == 0.0 ? 0.f : hit;
    } else {
        // As Mitsuba: the nearest root within the length, else the farther one.
        const double A = ld[0] * ld[0] + ld[1] * ld[1];
        const double B = 2.0 * (ld[0] * lo[0] + ld[1] * lo[1]);
        const double C = lo[0] * lo[0] + lo[1] * lo[1] - radius * radius;
        const double disc = B * B - 4.0 * A * C;
        const double q = -0.5 * (B + std::copysign(std::sqrt(disc), B));
        const double r0 = q / A, r1 = q != 0.0 ? C / q : r0;
        const double t0 = r0 > r1 ? r1 : r0, t1 = r0 > r1 ? r0 : r1;
        const double z0 = lo[2] + t0 * ld[2], z1 = lo[2] + t1 * ld[2];
        float ok0 = t0 > tmin ? 1.f : 0.f;
        ok0 = t0 < tmax ? ok0 : 0.f;
        ok0 = z0 >= 0.0 ? ok0 : 0.f;
        ok0 = z0 <= length ? ok0 : 0.f;
        float ok1 = t1 > tmin ? 1.f : 0.f;
        ok1 = t1 < tmax ? ok1 : 0.f;
        ok1 = z1 >= 0.0 ? ok1 : 0.f;
        ok1 = z1 <= length ? ok1 : 0.f;
        float hit = ok0 != 0.f ? 1.f : ok1;
        hit = disc < 0.0 ? 0.f : hit;
        *t_out = ok0 != 0.f ? float(t0) : float(t1), *u_out = 0.f, *v_out = 0.f;
        return A == 0.0 ? 0.f : hit;
    }
}

/// A sphere's uv at the unit direction q from its centre, in the sphere's own frame
/// (Shape::local_x, local_y, local_z): u = phi / 2pi, v = theta / pi. From atan2_poly and
/// acos_full, not libm's, so that Geometry::interaction and the wavefront's interactions in
/// SIMD lanes (sphere_interactions) compute the same.
RBPT_INLINE Vec2 sphere_uv(const Vec3 &q) {
    float phi = atan2_poly(q.y, q.x);
    phi = phi < 0.f ? phi + 2.f * Pi : phi;
    return {phi * InvTwoPi, acos_full(q.z) * InvPi};
}

/// Squared radius beyond which a reference point counts as outside a sphere. Points on the
/// sphere itself (its own shading points) count as inside when its normals face inwards,
/// as in Mitsuba (which scales the radius by 1 +- epsilon).
inline float outside_radius2(const Shape &shape) {
    float r = shape.radius * (shape.flip_normals ? 1.f + 1e-4f : 1.f - 1e-4f);
    return r * r;
}

/// Scene geometry: global vertex arrays, triangles, analytic primitives and the shapes they
/// belong to.
struct Geometry {
    std::vector<Vec3> positions, normals;
    std::vector<Vec2> uvs;
    std::vector<Triangle> triangles;
    std::vector<uint32_t> analytic;  ///< shape index of each analytic primitive (sphere, disk, cylinder)
    std::vector<Shape> shapes;

    uint32_t primitive_count() const { return uint32_t(triangles.size() + analytic.size()); }
    bool is_triangle(uint32_t prim) const { return prim < triangles.size(); }
    const Shape &analytic_shape(uint32_t prim) const {
        return shapes[analytic[prim - triangles.size()]];
    }
    /// Index of the shape a primitive belongs to.
    uint32_t shape_of(uint32_t prim) const {
        return is_triangle(prim) ? triangles[prim].shape : analytic[prim - triangles.size()];
    }

    /// Complete a BVH hit into a surface interaction; uv only where the shape needs_uv, or
    /// everywhere with `all_uv`.
    SurfaceInteraction interaction(const Ray &ray, const Hit &hit, bool all_uv = false) const;
    /// Sample a point on `shape` as seen from `ref`; pdf in solid angle at `ref`.
    DirectionSample sample_direction(int shape, const Vec3 &ref, Vec2 u) const;
    /// Solid-angle density of sample_direction() for the point `p` with normal `n` it hit.
    float pdf_direction(int shape, const Vec3 &ref, const Vec3 &p, const Vec3 &n) const;
    /// Finish building: areas and sampling CDFs. Call once after all shapes are added.
    void prepare();

    /// The vertex normals of `tri` interpolated at barycentrics (b0, b1, b2), normalised.
    Vec3 vertex_normal(const Triangle &tri, float b0, float b1, float b2) const {
        return normalize(normals[tri.v[0]] * b0 + normals[tri.v[1]] * b1 + normals[tri.v[2]] * b2);
    }
};

}  // namespace rbpt
