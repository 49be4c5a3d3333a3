#include "bvh.h"

#include <algorithm>

namespace rbpt {

namespace {

struct Bounds {
    Vec3 lo{Infinity, Infinity, Infinity}, hi{-Infinity, -Infinity, -Infinity};
    void extend(const Vec3 &p) { lo = vmin(lo, p); hi = vmax(hi, p); }
    void extend(const Bounds &b) { lo = vmin(lo, b.lo); hi = vmax(hi, b.hi); }
    float area() const {
        Vec3 e = hi - lo;
        if (e.x < 0.f) return 0.f;
        return 2.f * (e.x * e.y + e.y * e.z + e.z * e.x);
    }
    Vec3 center() const { return (lo + hi) * 0.5f; }
};

struct PrimInfo {
    Bounds bounds;
    Vec3 centroid;
    uint32_t id;
};

constexpr int Bins = 16;
constexpr int MaxLeafSize = 8;
constexpr float TraversalCost = 1.f, IntersectionCost = 1.f;

struct Builder {
    std::vector<PrimInfo> &prims;
    std::vector<BVHNode> &nodes;

    // Build the subtree over prims[begin, end) into nodes[index].
    void build(uint32_t index, uint32_t begin, uint32_t end) {
        Bounds bounds, centroids;
        for (uint32_t i = begin; i < end; ++i) {
            bounds.extend(prims[i].bounds);
            centroids.extend(prims[i].centroid);
        }
        BVHNode &node = nodes[index];
        node.lo = bounds.lo;
        node.hi = bounds.hi;
        uint32_t count = end - begin;
        auto make_leaf = [&] {
            nodes[index].offset = begin;
            nodes[index].count = uint16_t(count);
            nodes[index].axis = 0;
        };
        if (count <= 2) return make_leaf();

        // Find the best binned SAH split over the three axes.
        int best_axis = -1, best_split = -1;
        float best_cost = Infinity;
        Vec3 extent = centroids.hi - centroids.lo;
        for (int axis = 0; axis < 3; ++axis) {
            if (extent[axis] <= 0.f) continue;
            Bounds bin_bounds[Bins];
            uint32_t bin_count[Bins] = {};
            float scale = Bins / extent[axis];
            for (uint32_t i = begin; i < end; ++i) {
                int b = std::min(Bins - 1, int((prims[i].centroid[axis] - centroids.lo[axis]) * scale));
                bin_bounds[b].extend(prims[i].bounds);
                bin_count[b]++;
            }
            float right_area[Bins];
            uint32_t right_count[Bins];
            Bounds acc;
            uint32_t n = 0;
            for (int b = Bins - 1; b > 0; --b) {
                acc.extend(bin_bounds[b]);
                n += bin_count[b];
                right_area[b] = acc.area();
                right_count[b] = n;
            }
            acc = Bounds();
            n = 0;
            for (int b = 0; b < Bins - 1; ++b) {
                acc.extend(bin_bounds[b]);
                n += bin_count[b];
                if (n == 0 || right_count[b + 1] == 0) continue;
                float cost = acc.area() * n + right_area[b + 1] * right_count[b + 1];
                if (cost < best_cost) {
                    best_cost = cost;
                    best_axis = axis;
                    best_split = b;
                }
            }
        }
        if (best_axis < 0) {
            if (count <= MaxLeafSize) return make_leaf();
            // All centroids coincide: split the list in the middle.
            return split(index, begin, begin + count / 2, end, 0);
        }
        float leaf_cost = IntersectionCost * count;
        float area = std::max(bounds.area(), 1e-30f);
        float split_cost = TraversalCost + IntersectionCost * best_cost / area;
        if (count <= MaxLeafSize && leaf_cost <= split_cost) return make_leaf();
        float scale = Bins / extent[best_axis];
        auto mid_it = std::partition(prims.begin() + begin, prims.begin() + end,
                                     [&](const PrimInfo &p) {
                                         int b = std::min(Bins - 1, int((p.centroid[best_axis] -
                                                                         centroids.lo[best_axis]) *
                                                                        scale));
                                         return b <= best_split;
                                     });
        split(index, begin, uint32_t(mid_it - prims.begin()), end, best_axis);
    }

    void split(uint32_t index, uint32_t begin, uint32_t mid, uint32_t end, int axis) {
        uint32_t left = uint32_t(nodes.size());
        nodes.emplace_back();
        build(left, begin, mid);
        uint32_t right = uint32_t(nodes.size());
        nodes.emplace_back();
        build(right, mid, end);
        nodes[index].offset = right;
        nodes[index].count = 0;
        nodes[index].axis = uint16_t(axis);
    }
};

}  // namespace

void BVH::build(const Geometry &geometry) {
    geometry_ = &geometry;
    uint32_t n = geometry.primitive_count();
    std::vector<PrimInfo> prims(n);
    for (uint32_t i = 0; i < n; ++i) {
        Bounds b;
        if (geometry.is_triangle(i)) {
            for (uint32_t v : geometry.triangles[i].v) b.extend(geometry.positions[v]);
        } else {
            const Shape &s = geometry.sphere_shape(i);
            Vec3 r{s.radius, s.radius, s.radius};
            b.extend(s.center - r);
            b.extend(s.center + r);
        }
        prims[i] = {b, b.center(), i};
    }
    nodes_.clear();
    nodes_.reserve(2 * size_t(n) + 1);
    nodes_.emplace_back();
    if (n == 0) {
        // An empty scene: a root box that no ray can enter.
        nodes_[0] = BVHNode{{Infinity, Infinity, Infinity}, 0, {-Infinity, -Infinity, -Infinity}, 0, 0};
    } else {
        Builder{prims, nodes_}.build(0, 0, n);
    }
    prims_.resize(n);
    verts_.assign(3 * size_t(n), Vec3());
    for (uint32_t i = 0; i < n; ++i) {
        prims_[i] = prims[i].id;
        if (geometry.is_triangle(prims[i].id)) {
            const Triangle &tri = geometry.triangles[prims[i].id];
            for (int k = 0; k < 3; ++k) verts_[3 * i + k] = geometry.positions[tri.v[k]];
        }
    }
}

double BVH::sah_cost() const {
    if (prims_.empty()) return 0.0;
    auto area = [](const BVHNode &n) {
        Vec3 e = n.hi - n.lo;
        return 2.0 * (double(e.x) * e.y + double(e.y) * e.z + double(e.z) * e.x);
    };
    double root = area(nodes_[0]), cost = 0.0;
    for (const BVHNode &n : nodes_)
        cost += area(n) / root * (n.count ? IntersectionCost * n.count : TraversalCost);
    return cost;
}

namespace {

/// Slab test against a node's box; returns the entry distance or Infinity on a miss.
inline float hit_box(const BVHNode &node, const Vec3 &o, const Vec3 &inv_d, float tmin,
                     float tmax) {
    float tx0 = (node.lo.x - o.x) * inv_d.x, tx1 = (node.hi.x - o.x) * inv_d.x;
    float ty0 = (node.lo.y - o.y) * inv_d.y, ty1 = (node.hi.y - o.y) * inv_d.y;
    float tz0 = (node.lo.z - o.z) * inv_d.z, tz1 = (node.hi.z - o.z) * inv_d.z;
    float t0 = std::max(std::max(std::min(tx0, tx1), std::min(ty0, ty1)),
                        std::max(std::min(tz0, tz1), tmin));
    float t1 = std::min(std::min(std::max(tx0, tx1), std::max(ty0, ty1)),
                        std::min(std::max(tz0, tz1), tmax));
    // Widen the exit by a few ulps (pbrt's 1 + 2 gamma(3)) so grazing rays are not lost.
    return t0 <= t1 * 1.0000004f ? t0 : Infinity;
}

}  // namespace

template <bool AnyHit>
bool BVH::traverse(const Ray &ray, Hit *hit) const {
    if (prims_.empty()) return false;
    RayPrecomp pc(ray.d);
    Vec3 inv_d{1.f / ray.d.x, 1.f / ray.d.y, 1.f / ray.d.z};
    bool neg[3] = {ray.d.x < 0.f, ray.d.y < 0.f, ray.d.z < 0.f};
    float tmax = ray.tmax;
    bool found = false;
    uint32_t stack[64];
    int sp = 0;
    uint32_t index = 0;
    if (hit_box(nodes_[0], ray.o, inv_d, ray.tmin, tmax) == Infinity) return false;
    while (true) {
        const BVHNode &node = nodes_[index];
        if (node.count > 0) {
            // Intersect the primitives of a leaf.
            for (uint32_t slot = node.offset; slot < node.offset + node.count; ++slot) {
                uint32_t prim = prims_[slot];
                float t, u = 0.f, v = 0.f;
                bool h;
                if (geometry_->is_triangle(prim)) {
                    h = intersect_triangle(ray, pc, verts_[3 * slot], verts_[3 * slot + 1],
                                           verts_[3 * slot + 2], ray.tmin, tmax, &t, &u, &v);
                } else {
                    const Shape &s = geometry_->sphere_shape(prim);
                    h = intersect_sphere(ray, s.center, s.radius, ray.tmin, tmax, &t);
                }
                if (!h) continue;
                if (AnyHit) return true;
                found = true;
                tmax = t;
                hit->t = t;
                hit->prim = prim;
                hit->u = u;
                hit->v = v;
            }
        } else {
            // Visit the nearer child first; the other goes on the stack.
            uint32_t first = index + 1, second = node.offset;
            if (neg[node.axis]) std::swap(first, second);
            float t_first = hit_box(nodes_[first], ray.o, inv_d, ray.tmin, tmax);
            float t_second = hit_box(nodes_[second], ray.o, inv_d, ray.tmin, tmax);
            if (t_first != Infinity) {
                if (t_second != Infinity) stack[sp++] = second;
                index = first;
                continue;
            }
            if (t_second != Infinity) {
                index = second;
                continue;
            }
        }
        if (sp == 0) break;
        index = stack[--sp];
    }
    return found;
}

bool BVH::intersect(const Ray &ray, Hit *hit) const { return traverse<false>(ray, hit); }

bool BVH::occluded(const Ray &ray) const {
    Hit unused;
    return traverse<true>(ray, &unused);
}

}  // namespace rbpt
