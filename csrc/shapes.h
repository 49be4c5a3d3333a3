// Shapes: triangle meshes and the analytic sphere, disk and cylinder. Ray-primitive
// intersection, the surface interaction at a hit, and sampling points on shapes for area
// emitters.
#pragma once

#include <emmintrin.h>  // SSE2, part of the x86-64 baseline

#include <cstdint>
#include <vector>

#include "math.h"

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
    Vec3 wi;       ///< direction towards the ray origin, in the shading frame
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

/// Up to four triangles laid out for intersect_triangles4: v[vertex][axis][lane].
struct alignas(16) TrianglePack4 {
    float v[3][3][4];
};

/// Per-ray constants of intersect_triangles4: those of RayPrecomp and the origin, permuted
/// and splatted over four lanes.
struct RayPrecomp4 {
    int kx, ky, kz;
    __m128 ox, oy, oz, sx, sy, sz;
    RayPrecomp4() = default;
    explicit RayPrecomp4(const Ray &ray) {
        RayPrecomp pc(ray.d);
        kx = pc.kx;
        ky = pc.ky;
        kz = pc.kz;
        ox = _mm_set1_ps(ray.o[kx]);
        oy = _mm_set1_ps(ray.o[ky]);
        oz = _mm_set1_ps(ray.o[kz]);
        sx = _mm_set1_ps(pc.sx);
        sy = _mm_set1_ps(pc.sy);
        sz = _mm_set1_ps(pc.sz);
    }
};

/// Four watertight ray-triangle tests at once with SSE (Woop, Benthin and Wald 2013): the
/// vertices are sheared into the ray's frame and the hit is decided by the signs of three 2D
/// edge functions, so no ray slips between triangles sharing an edge; an edge function that
/// is exactly zero is recomputed in double precision. Tests the lanes set in `lanes` and returns
/// the mask of those hit in (tmin, tmax), with their t and barycentrics in t/u/v[lane].
inline int intersect_triangles4(const RayPrecomp4 &pc, const TrianglePack4 &pack, int lanes,
                                float tmin, float tmax, float t_out[4], float u_out[4],
                                float v_out[4]) {
    const __m128 ox = pc.ox, oy = pc.oy, oz = pc.oz, sx = pc.sx, sy = pc.sy, sz = pc.sz;
    // Translate to the ray origin and shear (per vertex: x, y and the unscaled z).
    __m128 x[3], y[3], z[3];
    for (int k = 0; k < 3; ++k) {
        z[k] = _mm_sub_ps(_mm_load_ps(pack.v[k][pc.kz]), oz);
        x[k] = _mm_sub_ps(_mm_sub_ps(_mm_load_ps(pack.v[k][pc.kx]), ox), _mm_mul_ps(sx, z[k]));
        y[k] = _mm_sub_ps(_mm_sub_ps(_mm_load_ps(pack.v[k][pc.ky]), oy), _mm_mul_ps(sy, z[k]));
    }
    // Edge functions U (edge bc), V (edge ca), W (edge ab).
    __m128 U = _mm_sub_ps(_mm_mul_ps(x[2], y[1]), _mm_mul_ps(y[2], x[1]));
    __m128 V = _mm_sub_ps(_mm_mul_ps(x[0], y[2]), _mm_mul_ps(y[0], x[2]));
    __m128 W = _mm_sub_ps(_mm_mul_ps(x[1], y[0]), _mm_mul_ps(y[1], x[0]));
    const __m128 zero = _mm_setzero_ps();
    int on_edge = _mm_movemask_ps(_mm_or_ps(_mm_or_ps(_mm_cmpeq_ps(U, zero), _mm_cmpeq_ps(V, zero)),
                                            _mm_cmpeq_ps(W, zero))) & lanes;
    if (on_edge) {
        // Edge case: redo the 2D edge tests of those lanes in double (watertight edges).
        alignas(16) float ax[4], ay[4], bx[4], by[4], cx[4], cy[4], u[4], v[4], w[4];
        _mm_store_ps(ax, x[0]); _mm_store_ps(ay, y[0]);
        _mm_store_ps(bx, x[1]); _mm_store_ps(by, y[1]);
        _mm_store_ps(cx, x[2]); _mm_store_ps(cy, y[2]);
        _mm_store_ps(u, U); _mm_store_ps(v, V); _mm_store_ps(w, W);
        for (int i = 0; i < 4; ++i) {
            if (!(on_edge >> i & 1)) continue;
            u[i] = float(double(cx[i]) * by[i] - double(cy[i]) * bx[i]);
            v[i] = float(double(ax[i]) * cy[i] - double(ay[i]) * cx[i]);
            w[i] = float(double(bx[i]) * ay[i] - double(by[i]) * ax[i]);
        }
        U = _mm_load_ps(u); V = _mm_load_ps(v); W = _mm_load_ps(w);
    }
    // Inside when the edge functions do not differ in sign.
    __m128 neg = _mm_or_ps(_mm_or_ps(_mm_cmplt_ps(U, zero), _mm_cmplt_ps(V, zero)), _mm_cmplt_ps(W, zero));
    __m128 pos = _mm_or_ps(_mm_or_ps(_mm_cmpgt_ps(U, zero), _mm_cmpgt_ps(V, zero)), _mm_cmpgt_ps(W, zero));
    __m128 det = _mm_add_ps(_mm_add_ps(U, V), W);
    int inside = ~_mm_movemask_ps(_mm_and_ps(neg, pos)) & _mm_movemask_ps(_mm_cmpneq_ps(det, zero)) & lanes;
    if (!inside) return 0;
    __m128 T = _mm_add_ps(_mm_add_ps(_mm_mul_ps(U, _mm_mul_ps(sz, z[0])), _mm_mul_ps(V, _mm_mul_ps(sz, z[1]))),
                          _mm_mul_ps(W, _mm_mul_ps(sz, z[2])));
    __m128 inv_det = _mm_div_ps(_mm_set1_ps(1.f), det);
    __m128 t = _mm_mul_ps(T, inv_det);
    int hit = _mm_movemask_ps(_mm_and_ps(_mm_cmpgt_ps(t, _mm_set1_ps(tmin)), _mm_cmplt_ps(t, _mm_set1_ps(tmax)))) & inside;
    if (!hit) return 0;
    // Keep only hits farther than the rounding error of t (pbrt-v4's conservative bound), so a
    // ray leaving a surface from its error-bounded offset origin never finds that surface.
    const __m128 sign = _mm_set1_ps(-0.f);
    auto abs3 = [&](const __m128 a[3]) {
        return _mm_max_ps(_mm_andnot_ps(sign, a[0]), _mm_max_ps(_mm_andnot_ps(sign, a[1]), _mm_andnot_ps(sign, a[2])));
    };
    __m128 max_zt = _mm_mul_ps(_mm_andnot_ps(sign, sz), abs3(z)), max_xt = abs3(x), max_yt = abs3(y);
    __m128 delta_z = _mm_mul_ps(_mm_set1_ps(gamma(3)), max_zt);
    __m128 delta_x = _mm_mul_ps(_mm_set1_ps(gamma(5)), _mm_add_ps(max_xt, max_zt));
    __m128 delta_y = _mm_mul_ps(_mm_set1_ps(gamma(5)), _mm_add_ps(max_yt, max_zt));
    __m128 delta_e = _mm_mul_ps(_mm_set1_ps(2.f),
                                _mm_add_ps(_mm_mul_ps(_mm_set1_ps(gamma(2)), _mm_mul_ps(max_xt, max_yt)),
                                           _mm_add_ps(_mm_mul_ps(delta_y, max_xt), _mm_mul_ps(delta_x, max_yt))));
    __m128 e[3] = {U, V, W};
    __m128 max_e = abs3(e);
    __m128 delta_t = _mm_mul_ps(
        _mm_mul_ps(_mm_set1_ps(3.f),
                   _mm_add_ps(_mm_mul_ps(_mm_set1_ps(gamma(3)), _mm_mul_ps(max_e, max_zt)),
                              _mm_add_ps(_mm_mul_ps(delta_e, max_zt), _mm_mul_ps(delta_z, max_e)))),
        _mm_andnot_ps(sign, inv_det));
    hit &= _mm_movemask_ps(_mm_cmpgt_ps(t, delta_t));
    if (!hit) return 0;
    _mm_storeu_ps(t_out, t);
    _mm_storeu_ps(u_out, _mm_mul_ps(V, inv_det));
    _mm_storeu_ps(v_out, _mm_mul_ps(W, inv_det));
    return hit;
}

/// Ray-sphere intersection in double precision; the nearest root in (tmin, tmax).
inline bool intersect_sphere(const Ray &ray, const Vec3 &center, float radius, float tmin,
                             float tmax, float *t_out) {
    double ox = double(ray.o.x) - center.x, oy = double(ray.o.y) - center.y,
           oz = double(ray.o.z) - center.z;
    double dx = ray.d.x, dy = ray.d.y, dz = ray.d.z;
    double A = dx * dx + dy * dy + dz * dz;
    double B = 2.0 * (ox * dx + oy * dy + oz * dz);
    double C = ox * ox + oy * oy + oz * oz - double(radius) * radius;
    double disc = B * B - 4.0 * A * C;
    if (disc < 0.0) return false;
    double q = -0.5 * (B + std::copysign(std::sqrt(disc), B));
    double t0 = q / A, t1 = (q != 0.0) ? C / q : t0;
    if (t0 > t1) std::swap(t0, t1);
    if (t0 > tmin && t0 < tmax) { *t_out = float(t0); return true; }
    if (t1 > tmin && t1 < tmax) { *t_out = float(t1); return true; }
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

    /// Complete a BVH hit into a surface interaction; uv only where the shape needs_uv, or
    /// everywhere with `all_uv`.
    SurfaceInteraction interaction(const Ray &ray, const Hit &hit, bool all_uv = false) const;
    /// Sample a point on `shape` as seen from `ref`; pdf in solid angle at `ref`.
    DirectionSample sample_direction(int shape, const Vec3 &ref, Vec2 u) const;
    /// Solid-angle density of sample_direction() for the point `p` with normal `n` it hit.
    float pdf_direction(int shape, const Vec3 &ref, const Vec3 &p, const Vec3 &n) const;
    /// Finish building: areas and sampling CDFs. Call once after all shapes are added.
    void prepare();
};

}  // namespace rbpt
