#include "shapes.h"

#include "warp.h"

namespace rbpt {

AnalyticHit intersect_disk_or_cylinder(const Ray &ray, const Shape &s, float tmin, float tmax) {
    AnalyticHit out{0.f, 0.f, 0.f, false};
    double o[3] = {ray.o.x, ray.o.y, ray.o.z}, lo[3], ld[3];
    s.object_point(o, lo);
    for (int i = 0; i < 3; ++i)
        ld[i] = s.to_object[i][0] * ray.d.x + s.to_object[i][1] * ray.d.y + s.to_object[i][2] * ray.d.z;
    float t, u, v;
    const float hit = s.kind == ShapeKind::Disk
                          ? disk_or_cylinder_test<true>(lo, ld, tmin, tmax, s.radius, s.length, &t, &u, &v)
                          : disk_or_cylinder_test<false>(lo, ld, tmin, tmax, s.radius, s.length, &t, &u, &v);
    return hit != 0.f ? AnalyticHit{t, u, v, true} : out;
}

/// The surface interaction on a disk or cylinder: the hit point projected onto the surface in
/// double precision, Mitsuba's uv and normals.
[[gnu::noinline]] static void analytic_interaction(const Shape &shape, const Ray &ray, const Hit &hit,
                                                   bool uv, SurfaceInteraction *si) {
    double q[3];  // the hit in object space
    if (shape.kind == ShapeKind::Disk) {
        q[0] = hit.u;
        q[1] = hit.v;
        q[2] = 0.0;
        si->n = shape.normal;
        if (uv) {  // uv = (r, phi / 2pi) in object space
            float r = std::sqrt(hit.u * hit.u + hit.v * hit.v);
            float v = std::atan2(hit.v, hit.u) * InvTwoPi;
            if (v < 0.f) v += 1.f;
            si->uv = {r, v};
        }
    } else {
        double p[3];
        for (int i = 0; i < 3; ++i) p[i] = double(ray.o[i]) + double(ray.d[i]) * double(hit.t);
        shape.object_point(p, q);
        double rxy = std::sqrt(q[0] * q[0] + q[1] * q[1]);
        double scale = rxy > 0.0 ? double(shape.radius) / rxy : 0.0;
        q[0] *= scale;
        q[1] *= scale;
        float cos_phi = float(q[0] / shape.radius), sin_phi = float(q[1] / shape.radius);
        si->n = normalize(shape.local_x * cos_phi + shape.local_y * sin_phi);
        if (uv) {  // uv = (phi / 2pi, z / length) in object space
            float phi = std::atan2(float(q[1]), float(q[0]));
            if (phi < 0.f) phi += 2.f * Pi;
            si->uv = {phi * InvTwoPi, float(q[2] / shape.length)};
        }
    }
    si->p = shape.world_point(q);
    // p is the surface point rounded once from double; the bound covers that and the double
    // precision transforms (as the sphere's).
    si->p_error = gamma(4) * vabs(si->p) + Vec3(1, 1, 1) * (gamma(4) * shape.radius);
    if (shape.flip_normals) si->n = -si->n;
}

SurfaceInteraction Geometry::interaction(const Ray &ray, const Hit &hit, bool all_uv) const {
    SurfaceInteraction si;
    if (!hit.valid()) {
        si.wi = -ray.d;  // escaped: the direction back along the ray, in world space
        return si;
    }
    si.valid = true;
    si.t = hit.t;
    si.shape = int(shape_of(hit.prim));
    Vec3 ns;
    if (is_triangle(hit.prim)) {
        const Triangle &tri = triangles[hit.prim];
        const Shape &shape = shapes[tri.shape];
        float b1 = hit.u, b2 = hit.v, b0 = 1.f - b1 - b2;
        si.tri = hit.prim;
        si.b1 = b1;
        si.b2 = b2;
        const Vec3 &p0 = positions[tri.v[0]], &p1 = positions[tri.v[1]], &p2 = positions[tri.v[2]];
        si.p = p0 * b0 + p1 * b1 + p2 * b2;
        si.p_error = gamma(7) * (vabs(p0 * b0) + vabs(p1 * b1) + vabs(p2 * b2));
        si.n = tri.n;
        if (shape.has_normals) {
            ns = vertex_normal(tri, b0, b1, b2);
        } else {
            ns = si.n;
        }
        if (shape.needs_uv || all_uv) {
            if (shape.has_uvs) {
                const Vec2 &t0 = uvs[tri.v[0]], &t1 = uvs[tri.v[1]], &t2 = uvs[tri.v[2]];
                si.uv = {t0.x * b0 + t1.x * b1 + t2.x * b2, t0.y * b0 + t1.y * b1 + t2.y * b2};
            } else {
                si.uv = {b1, b2};  // as Mitsuba: barycentrics when the mesh has no texcoords
            }
        }
        if (shape.flip_normals) {
            si.n = -si.n;
            ns = -ns;
        }
    } else if (const Shape &shape = analytic_shape(hit.prim); shape.kind != ShapeKind::Sphere) {
        analytic_interaction(shape, ray, hit, shape.needs_uv || all_uv, &si);
        ns = si.n;
    } else {
        // Re-project the hit onto the sphere in double precision, so that p is the sphere's
        // point up to the final rounding (float arithmetic far from the origin is not).
        double r[3], len2 = 0.0;
        for (int i = 0; i < 3; ++i) {
            r[i] = double(ray.o[i]) + double(ray.d[i]) * double(hit.t) - double(shape.center[i]);
            len2 += r[i] * r[i];
        }
        double scale = double(shape.radius) / std::sqrt(len2);
        for (int i = 0; i < 3; ++i) si.p[i] = float(double(shape.center[i]) + r[i] * scale);
        si.p_error = gamma(4) * vabs(si.p) + Vec3(1, 1, 1) * (gamma(4) * shape.radius);
        Vec3 local{float(r[0] * scale), float(r[1] * scale), float(r[2] * scale)};
        local = normalize(local);
        si.n = local;
        if (shape.needs_uv || all_uv) {
            // Spherical coordinates in the sphere's own frame: u = phi / 2pi, v = theta / pi.
            si.uv = sphere_uv({dot(local, shape.local_x), dot(local, shape.local_y), dot(local, shape.local_z)});
        }
        if (shape.flip_normals) si.n = -si.n;
        ns = si.n;
    }
    si.sh_frame = Frame(ns);
    si.wi = si.to_local(-ray.d);
    return si;
}

/// A density uniform in area over a shape of area `area`, converted to solid angle at a point
/// dist2 away whose direction makes |cos| = abs_cos with the surface: dist^2 / (area |cos|).
static float area_to_solid_angle(float area, float dist2, float abs_cos) {
    return abs_cos > 0.f ? dist2 / (area * abs_cos) : 0.f;
}

/// Solid-angle density at `ref` of sampling uniformly by area a shape of area `area` at point
/// `p` with normal `n`.
static float solid_angle_pdf(float area, const Vec3 &ref, const Vec3 &p, const Vec3 &n) {
    Vec3 d = p - ref;
    float dist2 = squared_norm(d);
    return area_to_solid_angle(area, dist2, std::abs(dot(n, d)) / std::sqrt(dist2));
}

DirectionSample Geometry::sample_direction(int shape_index, const Vec3 &ref, Vec2 u) const {
    const Shape &shape = shapes[shape_index];
    DirectionSample ds;
    bool by_area = shape.kind != ShapeKind::Sphere;  // and spheres seen from inside (below)
    // The normal of the area element that by_area densities convert with: the surface's own.
    // On meshes that is the face normal, not the interpolated vertex normal that ds.n carries
    // (which decides the emitting side, as in a hit's shading frame). Mitsuba converts with
    // the vertex normal, so that its light samples on curved meshes disagree with BSDF
    // samples hitting the same light (tests/test_shapes.py::test02b).
    Vec3 n_area;
    if (shape.kind == ShapeKind::Mesh) {
        // Pick a triangle proportionally to its area, reusing u.x, then a uniform point on it.
        const std::vector<float> &cdf = shape.tri_cdf;
        uint32_t local;
        if (shape.tri_count <= 8) {  // a count, without the binary search's branches
            local = 0;
            for (uint32_t i = 1; i < shape.tri_count; ++i) local += cdf[i] <= u.x;
        } else {
            auto it = std::upper_bound(cdf.begin() + 1, cdf.end(), u.x);
            local = uint32_t(std::min<std::ptrdiff_t>(it - cdf.begin() - 1, std::ptrdiff_t(shape.tri_count) - 1));
        }
        float width = cdf[local + 1] - cdf[local];
        u.x = std::min(width > 0.f ? (u.x - cdf[local]) / width : 0.f, 0.99999994f);
        const Triangle &tri = triangles[shape.tri_begin + local];
        Vec2 b = warp::square_to_uniform_triangle(u);
        float b0 = 1.f - b.x - b.y;
        const Vec3 &p0 = positions[tri.v[0]], &p1 = positions[tri.v[1]], &p2 = positions[tri.v[2]];
        ds.p = p0 * b0 + p1 * b.x + p2 * b.y;
        ds.n = shape.has_normals ? vertex_normal(tri, b0, b.x, b.y) : tri.n;
        if (shape.flip_normals) ds.n = -ds.n;
        n_area = tri.n;
    } else if (shape.kind == ShapeKind::Disk || shape.kind == ShapeKind::Cylinder) {
        // Uniform in area (Mitsuba's sample_position), converted to solid angle.
        double q[3];
        if (shape.kind == ShapeKind::Disk) {
            Vec2 d = warp::square_to_uniform_disk_concentric(u);
            q[0] = d.x;
            q[1] = d.y;
            q[2] = 0.0;
            ds.n = shape.normal;
        } else {
            Vec2 cs = warp::cossin_2pi(u.y);  // (cos, sin) of phi = 2 pi u.y
            float c = cs.x, s = cs.y;
            q[0] = double(c) * shape.radius;
            q[1] = double(s) * shape.radius;
            q[2] = double(u.x) * shape.length;
            ds.n = normalize(shape.local_x * c + shape.local_y * s);
        }
        ds.p = shape.world_point(q);
        if (shape.flip_normals) ds.n = -ds.n;
        n_area = ds.n;
    } else {
        Vec3 dc = shape.center - ref;
        float dc2 = squared_norm(dc);
        if (dc2 > outside_radius2(shape)) {
            // Outside: sample the cone of directions subtended by the sphere (as Mitsuba).
            warp::SphereConeSample cone = warp::sample_sphere_cone(dc, dc2, shape.radius, u);
            ds.p = shape.center + cone.n * shape.radius;
            ds.n = cone.n;
            ds.pdf = cone.pdf;
        } else {
            Vec3 d = warp::square_to_uniform_sphere(u);
            ds.p = shape.center + d * shape.radius;
            ds.n = d;
            n_area = d;
            by_area = true;
        }
        if (shape.flip_normals) ds.n = -ds.n;
    }
    // The direction, and the density of points sampled by area converted to solid angle,
    // sharing the distance.
    Vec3 d = ds.p - ref;
    float dist2 = squared_norm(d);
    ds.dist = std::sqrt(dist2);
    if (ds.dist == 0.f) {
        ds.pdf = 0.f;
        return ds;
    }
    ds.d = d * (1.f / ds.dist);
    if (by_area) ds.pdf = area_to_solid_angle(shape.area, dist2, std::abs(dot(n_area, ds.d)));
    return ds;
}

float Geometry::pdf_direction(int shape_index, const Vec3 &ref, const Vec3 &p,
                              const Vec3 &n) const {
    const Shape &shape = shapes[shape_index];
    if (shape.kind == ShapeKind::Sphere) {
        float dc2 = squared_norm(shape.center - ref);
        if (dc2 > outside_radius2(shape)) {
            float sin_max2 = shape.radius * shape.radius / dc2;
            return sin_max2 > 0.00068523f
                       ? warp::square_to_uniform_cone_pdf(safe_sqrt(1.f - sin_max2))
                       : 1.f / (Pi * sin_max2);
        }
    }
    return solid_angle_pdf(shape.area, ref, p, n);
}

void Geometry::prepare() {
    for (Triangle &tri : triangles) {
        const Vec3 &p0 = positions[tri.v[0]], &p1 = positions[tri.v[1]], &p2 = positions[tri.v[2]];
        tri.n = normalize(cross(p1 - p0, p2 - p0));
    }
    for (Shape &shape : shapes) {
        if (shape.kind == ShapeKind::Sphere) {
            shape.area = 4.f * Pi * shape.radius * shape.radius;
            continue;
        }
        if (shape.kind == ShapeKind::Disk) {  // an ellipse in general: pi |dp/dx x dp/dy|
            shape.area = Pi * norm(cross(shape.local_x, shape.local_y));
            continue;
        }
        if (shape.kind == ShapeKind::Cylinder) {
            shape.area = 2.f * Pi * shape.radius * shape.length;
            continue;
        }
        shape.tri_cdf.assign(shape.tri_count + 1, 0.f);
        double sum = 0.0;
        for (uint32_t i = 0; i < shape.tri_count; ++i) {
            const Triangle &tri = triangles[shape.tri_begin + i];
            const Vec3 &p0 = positions[tri.v[0]], &p1 = positions[tri.v[1]],
                       &p2 = positions[tri.v[2]];
            sum += 0.5 * norm(cross(p1 - p0, p2 - p0));
            shape.tri_cdf[i + 1] = float(sum);
        }
        shape.area = float(sum);
        for (float &c : shape.tri_cdf) c = sum > 0.0 ? float(c / sum) : 0.f;
    }
}

}  // namespace rbpt
