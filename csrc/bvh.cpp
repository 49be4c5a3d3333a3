// Layout of the BVH.
//
// Build: a binary tree of BinaryNodes with the binned SAH (16 bins, leaves of at most 8
// primitives), as in pbrt, except that a leaf costs by the packs of BVHWidth triangles it
// needs, since that many are tested at once, plus one pack per analytic shape (sphere, disk,
// cylinder).
//
// Collapse: each binary inner node becomes a BVHNode whose children are found by repeatedly
// opening the inner child of largest surface area until there are BVHWidth of them (Wald et
// al. 2008, "Getting rid of packets"; Embree's BVH8 on AVX machines); in a tree of one node,
// when no inner child is left and slots are, the SAH's leaves are opened the same way (the
// binary tree goes on below them down to single primitives). A BVHNode (256 bytes
// when 8-wide, 128 when 4-wide) keeps the child boxes in structure-of-arrays form,
// lo[axis][child] and hi[axis][child], so that one AVX (SSE) slab test covers all of them,
// and a 32-bit reference per child:
//   - an inner node: its index in nodes_ (the top bit clear);
//   - a leaf: LeafBit | first << 3 | (count - 1), a run of `count` (at most 8) PrimPacks
//     starting at packs_[first];
//   - nothing (fewer than BVHWidth children): EmptyChild, with an empty box no ray enters.
// A PrimPack holds BVHWidth consecutive primitives of a leaf: the vertices of its triangles,
// again per lane, for the packed watertight test, and the ids; analytic lanes are tested one
// at a time (in double precision).
//
// Traversal: a stack of (reference, entry distance). An inner node's hit children are visited
// nearest first, the others pushed farthest first; entries farther than the nearest hit so far
// are skipped when popped; the hit children are prefetched, as traversal waits on memory.
// Any-hit (shadow) queries do not order children and return at the first hit.
//
// Quads: in a flat tree (or a two-phase tree's root leaves), a pair of triangles of
// flat_columns()' passes that make a parallelogram is a FlatQuad, whose test (quad_test())
// is the same in the lanes' passes and in the packs (a lane of each pack holding a half
// runs it, the pack's quads in one vector test, QuadPack; the halves' lanes leave the
// packs' triangle test), in closest-hit and occlusion queries alike.

#include "bvh.h"

#include <immintrin.h>

#include <algorithm>
#include <array>
#include <stdexcept>

namespace rbpt {

namespace {

/// A node of the binary build tree (pbrt's linear layout: the first child follows its parent).
/// The tree goes down to single primitives; the SAH's leaves are marked, and so is everything
/// below them: the collapse makes a leaf of a marked node, or opens it to fill a wide node's
/// free child slots.
struct BinaryNode {
    Vec3 lo;
    uint32_t offset;  ///< a single primitive: its slot; otherwise: index of the second child
    Vec3 hi;
    uint32_t count;   ///< 1 for a single primitive, 0 otherwise
    uint32_t first = 0, total = 0;  ///< the subtree's primitives: slots [first, first + total)
    bool leaf = false;              ///< an SAH leaf or inside one
};

constexpr uint32_t LeafBit = 0x80000000u;
constexpr uint32_t EmptyChild = 0xffffffffu;
/// Deepest tree the traversal stack allows (at most BVHWidth - 1 pushes per level).
constexpr int MaxDepth = 64;
constexpr int StackSize = (BVHWidth - 1) * MaxDepth + 1;
/// Box exits are widened by a few ulps (pbrt's 1 + 2 gamma(3)) so grazing rays are not lost.
constexpr float BoxWiden = 1.0000004f;
/// How far a box [lo, hi] along an axis is widened where rays skip what lies inside it by
/// its test alone (a flat pass's halves, ShapeBoxes): far more than the rounding of the
/// box's own test and of the shapes' inside it.
RBPT_INLINE float skip_margin(float lo, float hi) {
    return 1e-4f * ((hi - lo) + std::max(std::abs(lo), std::abs(hi))) + 1e-6f;
}

/// NodeTest's operations for one ray, in a lane: whether it enters the box [lo, hi] within
/// [t0, t1], t1 widened by `widen` (the near and far planes chosen by the sign of 1 / d).
RBPT_INLINE int enters_box(const float lo[3], const float hi[3], const Vec3 &o, const Vec3 &inv_d, float t0, float t1,
                           float widen) {
#pragma GCC unroll 3
    for (int a = 0; a < 3; ++a) {
        const float near = std::signbit(inv_d[a]) ? hi[a] : lo[a], far = std::signbit(inv_d[a]) ? lo[a] : hi[a];
        const float tn = (near - o[a]) * inv_d[a], tf = (far - o[a]) * inv_d[a];
        t0 = tn > t0 ? tn : t0, t1 = tf < t1 ? tf : t1;
    }
    return t0 <= t1 * widen ? 1 : 0;
}

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
    bool analytic;
};

/// Bounds of an analytic shape. Disks and cylinders are bounded in double precision and
/// rounded outwards (their intersection is computed in double).
Bounds analytic_bounds(const Shape &s) {
    Bounds b;
    if (s.kind == ShapeKind::Sphere) {
        Vec3 r{s.radius, s.radius, s.radius};
        b.extend(s.center - r);
        b.extend(s.center + r);
        return b;
    }
    double lo[3], hi[3];
    for (int i = 0; i < 3; ++i) {
        double c = s.center[i];
        if (s.kind == ShapeKind::Disk) {  // the box of the ellipse: c +- sqrt(a_i^2 + b_i^2)
            double e = std::sqrt(double(s.local_x[i]) * s.local_x[i] + double(s.local_y[i]) * s.local_y[i]);
            lo[i] = c - e;
            hi[i] = c + e;
        } else {  // the two end circles (Mitsuba's cylinder bbox)
            double e = s.radius * std::sqrt(double(s.local_x[i]) * s.local_x[i] +
                                            double(s.local_y[i]) * s.local_y[i]);
            double end = c + double(s.local_z[i]) * s.length;
            lo[i] = std::min(c, end) - e;
            hi[i] = std::max(c, end) + e;
        }
    }
    for (int i = 0; i < 3; ++i) {
        b.lo[i] = next_float_down(float(lo[i]));
        b.hi[i] = next_float_up(float(hi[i]));
    }
    return b;
}

constexpr int Bins = 16;
constexpr int MaxLeafSize = 8;
/// Build costs: a binary node and the test of a pack of BVHWidth triangles.
constexpr float TraversalCost = 1.f, PackCost = 4.f;
/// Tests for n primitives of which `analytic` are analytic shapes, in packs: triangles go
/// BVHWidth at a time, while each analytic shape costs about a pack (a double precision test
/// of its own).
inline float pack_tests(uint32_t n, uint32_t analytic) {
    return float((n - analytic + BVHWidth - 1) / BVHWidth + analytic);
}

struct Builder {
    std::vector<PrimInfo> &prims;
    std::vector<BinaryNode> &nodes;

    // Build the subtree over prims[begin, end) into nodes[index]; in_leaf: below an SAH leaf.
    void build(uint32_t index, uint32_t begin, uint32_t end, bool in_leaf = false) {
        Bounds bounds, centroids;
        uint32_t analytic = 0;
        for (uint32_t i = begin; i < end; ++i) {
            bounds.extend(prims[i].bounds);
            centroids.extend(prims[i].centroid);
            analytic += prims[i].analytic;
        }
        BinaryNode &node = nodes[index];
        node.lo = bounds.lo;
        node.hi = bounds.hi;
        uint32_t count = end - begin;
        node.first = begin;
        node.total = count;
        node.leaf = in_leaf || count <= 2;
        if (count == 1) {
            node.offset = begin;
            node.count = 1;
            return;
        }
        if (count == 2) return split(index, begin, begin + 1, end, true);

        // Find the best binned SAH split over the three axes.
        int best_axis = -1, best_split = -1;
        float best_cost = Infinity;
        Vec3 extent = centroids.hi - centroids.lo;
        for (int axis = 0; axis < 3; ++axis) {
            if (extent[axis] <= 0.f) continue;
            Bounds bin_bounds[Bins];
            uint32_t bin_count[Bins] = {}, bin_analytic[Bins] = {};
            float scale = Bins / extent[axis];
            for (uint32_t i = begin; i < end; ++i) {
                int b = std::min(Bins - 1, int((prims[i].centroid[axis] - centroids.lo[axis]) * scale));
                bin_bounds[b].extend(prims[i].bounds);
                bin_count[b]++;
                bin_analytic[b] += prims[i].analytic;
            }
            float right_area[Bins];
            uint32_t right_count[Bins], right_analytic[Bins];
            Bounds acc;
            uint32_t n = 0, ns = 0;
            for (int b = Bins - 1; b > 0; --b) {
                acc.extend(bin_bounds[b]);
                n += bin_count[b];
                ns += bin_analytic[b];
                right_area[b] = acc.area();
                right_count[b] = n;
                right_analytic[b] = ns;
            }
            acc = Bounds();
            n = ns = 0;
            for (int b = 0; b < Bins - 1; ++b) {
                acc.extend(bin_bounds[b]);
                n += bin_count[b];
                ns += bin_analytic[b];
                if (n == 0 || right_count[b + 1] == 0) continue;
                float cost = acc.area() * pack_tests(n, ns) +
                             right_area[b + 1] * pack_tests(right_count[b + 1], right_analytic[b + 1]);
                if (cost < best_cost) {
                    best_cost = cost;
                    best_axis = axis;
                    best_split = b;
                }
            }
        }
        if (best_axis < 0) {
            // All centroids coincide: split the list in the middle.
            if (count <= MaxLeafSize) nodes[index].leaf = true;
            return split(index, begin, begin + count / 2, end, nodes[index].leaf);
        }
        float leaf_cost = PackCost * pack_tests(count, analytic);
        float area = std::max(bounds.area(), 1e-30f);
        float split_cost = TraversalCost + PackCost * best_cost / area;
        if (count <= MaxLeafSize && leaf_cost <= split_cost) nodes[index].leaf = true;
        float scale = Bins / extent[best_axis];
        auto mid_it = std::partition(prims.begin() + begin, prims.begin() + end,
                                     [&](const PrimInfo &p) {
                                         int b = std::min(Bins - 1, int((p.centroid[best_axis] -
                                                                         centroids.lo[best_axis]) *
                                                                        scale));
                                         return b <= best_split;
                                     });
        split(index, begin, uint32_t(mid_it - prims.begin()), end, nodes[index].leaf);
    }

    void split(uint32_t index, uint32_t begin, uint32_t mid, uint32_t end, bool in_leaf) {
        uint32_t left = uint32_t(nodes.size());
        nodes.emplace_back();
        build(left, begin, mid, in_leaf);
        uint32_t right = uint32_t(nodes.size());
        nodes.emplace_back();
        build(right, mid, end, in_leaf);
        nodes[index].offset = right;
        nodes[index].count = 0;
    }
};

double binary_area(const BinaryNode &n) {
    Vec3 e = n.hi - n.lo;
    return 2.0 * (double(e.x) * e.y + double(e.y) * e.z + double(e.z) * e.x);
}

/// Turns the binary tree into BVHWidth-wide nodes and its leaves into packs of BVHWidth primitives.
struct Collapser {
    const std::vector<BinaryNode> &bin;
    const std::vector<PrimInfo> &prims;
    const Geometry &geometry;
    std::vector<BVHNode> &nodes;
    std::vector<PrimPack> &packs;

    uint32_t leaf(const BinaryNode &n) {
        uint32_t first = uint32_t(packs.size());
        for (uint32_t i = 0; i < n.total; i += BVHWidth) {
            PrimPack pack{};
            for (uint32_t lane = 0; lane < BVHWidth; ++lane) {
                pack.prim[lane] = ~0u;
                if (i + lane >= n.total) continue;
                uint32_t id = prims[n.first + i + lane].id;
                pack.prim[lane] = id;
                if (!geometry.is_triangle(id)) {
                    bool sphere = geometry.analytic_shape(id).kind == ShapeKind::Sphere;
                    (sphere ? pack.spheres : pack.others) |= uint8_t(1 << lane);
                    continue;
                }
                pack.triangles |= uint8_t(1 << lane);
                const Triangle &tri = geometry.triangles[id];
                for (int k = 0; k < 3; ++k)
                    for (int axis = 0; axis < 3; ++axis)
                        pack.tris.v[k][axis][lane] = geometry.positions[tri.v[k]][axis];
            }
            packs.push_back(pack);
        }
        uint32_t count = uint32_t(packs.size()) - first;
        return LeafBit | first << 3 | (count - 1);
    }

    /// The node for binary node `b` (not a single primitive) at depth `depth`; returns its
    /// index.
    uint32_t inner(uint32_t b, int depth) {
        if (depth >= MaxDepth) throw std::runtime_error("BVH: the tree is deeper than 64 levels");
        // Open the inner child of largest area until there are BVHWidth children. In a tree
        // of one node (the root's children all leaves: a small scene), while slots are left,
        // open SAH leaves too: a child slot costs nothing in the node's test, and two tighter
        // boxes let a ray skip one (the SAH counts the box areas of rays from outside, whereas
        // most rays of a closed room start inside it; cbox 10% faster). Deeper in a larger
        // tree, a mesh's leaves stay whole: opened, they double the packs (the bunny's 9.8k
        // packs of 7 triangles on average become 21k of 3, 3.5 MB become 7.5), and a ray
        // entering a leaf of small triangles mostly enters both halves (the bunny 3-11% slower).
        uint32_t kids[BVHWidth] = {b + 1, bin[b].offset};
        int n = 2;
        for (bool open_leaves : {false, true}) {
            if (open_leaves && depth > 0) break;
            while (n < BVHWidth) {
                int best = -1;
                double best_area = -1.0;
                for (int i = 0; i < n; ++i) {
                    const BinaryNode &kid = bin[kids[i]];
                    bool openable = kid.count == 0 && (open_leaves || !kid.leaf);
                    if (openable && binary_area(kid) > best_area) {
                        best = i;
                        best_area = binary_area(kid);
                    }
                }
                if (best < 0) break;
                uint32_t k = kids[best];
                kids[best] = k + 1;
                kids[n++] = bin[k].offset;
            }
        }
        return node(kids, n, depth);
    }

    /// A node over the binary nodes kids[0, n); returns its index.
    uint32_t node(const uint32_t *kids, int n, int depth) {
        uint32_t index = uint32_t(nodes.size());
        nodes.emplace_back();
        for (int c = 0; c < BVHWidth; ++c) {
            Vec3 lo{Infinity, Infinity, Infinity}, hi{-Infinity, -Infinity, -Infinity};
            uint32_t ref = EmptyChild;
            if (c < n) {
                const BinaryNode &kid = bin[kids[c]];
                lo = kid.lo;
                hi = kid.hi;
                ref = kid.leaf ? leaf(kid) : inner(kids[c], depth + 1);
            }
            BVHNode &node = nodes[index];  // (inner() may have moved the vector)
            for (int axis = 0; axis < 3; ++axis) {
                node.lo[axis][c] = lo[axis];
                node.hi[axis][c] = hi[axis];
            }
            node.child[c] = ref;
        }
        return index;
    }
};

}  // namespace

std::vector<uint32_t> shadow_blockers(const Geometry &geometry, const std::vector<Vec3> &points) {
    // The points every segment's ends lie among (convexly): the meshes' vertices, the
    // corners of the analytic shapes' boxes, and the given points.
    std::vector<Vec3> p = geometry.positions;
    for (uint32_t s : geometry.analytic) {
        const Bounds b = analytic_bounds(geometry.shapes[s]);
        for (int c = 0; c < 8; ++c) p.push_back({(c & 1) ? b.hi.x : b.lo.x, (c & 2) ? b.hi.y : b.lo.y, (c & 4) ? b.hi.z : b.lo.z});
    }
    p.insert(p.end(), points.begin(), points.end());
    // Tested first: the points extreme along 13 directions (a 26-DOP's), which lie on
    // both sides of a plane through the inside of the scene (a mesh's triangle in a room).
    std::vector<Vec3> order;
    const int dirs[13][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}, {1, 1, 0}, {1, -1, 0}, {1, 0, 1}, {1, 0, -1},
                             {0, 1, 1}, {0, 1, -1}, {1, 1, 1}, {1, 1, -1}, {1, -1, 1}, {1, -1, -1}};
    if (!p.empty()) {
        for (const auto &d : dirs) {
            size_t lo = 0, hi = 0;
            auto proj = [&](const Vec3 &x) { return double(d[0]) * x.x + double(d[1]) * x.y + double(d[2]) * x.z; };
            for (size_t i = 1; i < p.size(); ++i) {
                if (proj(p[i]) < proj(p[lo])) lo = i;
                if (proj(p[i]) > proj(p[hi])) hi = i;
            }
            order.push_back(p[lo]);
            order.push_back(p[hi]);
        }
    }
    order.insert(order.end(), p.begin(), p.end());
    // Point tests at most (a large convex mesh alone has many supporting triangles, each
    // tested against every point): past it the remaining triangles stay blockers.
    int64_t budget = int64_t(1) << 25;
    std::vector<uint32_t> blockers;
    for (uint32_t prim = 0; prim < geometry.primitive_count(); ++prim) {
        if (!geometry.is_triangle(prim) || budget <= 0) {
            blockers.push_back(prim);
            continue;
        }
        const Triangle &t = geometry.triangles[prim];
        const Vec3 &a = geometry.positions[t.v[0]], &b = geometry.positions[t.v[1]], &c = geometry.positions[t.v[2]];
        const double e1[3] = {double(b.x) - a.x, double(b.y) - a.y, double(b.z) - a.z};
        const double e2[3] = {double(c.x) - a.x, double(c.y) - a.y, double(c.z) - a.z};
        const double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]};
        const double n_size = std::abs(n[0]) + std::abs(n[1]) + std::abs(n[2]);
        bool above = false, below = false;
        // (A degenerate triangle is hit by no ray; it stays, as it is, a blocker.)
        if (!(n_size > 0.0)) above = below = true;
        size_t i = 0;
        for (; i < order.size() && !(above && below); ++i) {
            const double d[3] = {double(order[i].x) - a.x, double(order[i].y) - a.y, double(order[i].z) - a.z};
            const double side = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
            // Within 1e-5 of the plane (relative to the distance) counts as in it: a
            // rectangle's two triangles, rounded, are one plane.
            const double tol = 1e-5 * n_size * std::max({std::abs(d[0]), std::abs(d[1]), std::abs(d[2])});
            above = above || side > tol;
            below = below || side < -tol;
        }
        budget -= int64_t(i);
        if (above && below) blockers.push_back(prim);
    }
    return blockers;
}

/// One ray as quad_test() takes rays: FlatLanes' operations on floats (the same results).
struct ScalarLanes {
    using F = float;
    using I = uint32_t;
    using M = bool;
    static F set1(float x) { return x; }
    static I set1(uint32_t x) { return x; }
    static F add(F a, F b) { return a + b; }
    static F sub(F a, F b) { return a - b; }
    static F mul(F a, F b) { return a * b; }
    static F div(F a, F b) { return a / b; }
    static F min(F a, F b) { return a < b ? a : b; }
    static F abs(F a) { return std::abs(a); }
    static M lt(F a, F b) { return a < b; }
    static M le(F a, F b) { return a <= b; }
    static M gt(F a, F b) { return a > b; }
    static M ge(F a, F b) { return a >= b; }
    static M both(M a, M b) { return a && b; }
    /// m ? b : a.
    static F select(M m, F a, F b) { return m ? b : a; }
};

/// Most a quad's tests widen it by (QuadMargin of an edge, in s and r): less than
/// skip_margin() widens its pair's box in a flat pass, so that a chunk of rays none of which
/// enters that box cannot hit the widened quad (build_quads() widens the leaves' boxes
/// likewise).
constexpr float QuadMargin = 1e-5f;

/// A ray's (or a register of rays') values for quad_test(), the same for every quad: origin,
/// direction, interval start, and the rounding terms of its magnitudes (|d|_1, gamma(5)
/// |o|_1, gamma(3) |d|_1, gamma(5) |d|_1).
template <class L>
struct QuadRay {
    using F = typename L::F;
    F o[3], d[3], tmin, ad, ao5, ad3, ad5;
    QuadRay() = default;
    QuadRay(F ox, F oy, F oz, F dx, F dy, F dz, F t0) : o{ox, oy, oz}, d{dx, dy, dz}, tmin(t0) {
        ad = L::add(L::add(L::abs(dx), L::abs(dy)), L::abs(dz));
        ao5 = L::mul(L::set1(gamma(5)), L::add(L::add(L::abs(ox), L::abs(oy)), L::abs(oz)));
        ad3 = L::mul(L::set1(gamma(3)), ad);
        ad5 = L::mul(L::set1(gamma(5)), ad);
    }
};

template <class L>
struct QuadHit {
    typename L::M hit, second;  ///< a hit; in the quad's second triangle
    typename L::F t, u, v;      ///< its distance, and the triangle's barycentrics
};

/// A pack's quads in the lanes of simd::V, for one ray (PackLanes): FlatLanes' operations
/// again (a mask is a lane of all ones).
struct PackLanes {
    using F = simd::V;
    using M = simd::V;
    static F set1(float x) { return simd::set1(x); }
    static F add(F a, F b) { return simd::add(a, b); }
    static F sub(F a, F b) { return simd::sub(a, b); }
    static F mul(F a, F b) { return simd::mul(a, b); }
    static F div(F a, F b) { return simd::div(a, b); }
    static F min(F a, F b) { return simd::min(a, b); }
    static F abs(F a) { return simd::abs(a); }
    static M lt(F a, F b) { return simd::lt(a, b); }
    static M le(F a, F b) { return simd::le(a, b); }
    static M gt(F a, F b) { return simd::gt(a, b); }
    static M ge(F a, F b) { return simd::le(b, a); }
    static M both(M a, M b) { return simd::bit_and(a, b); }
    /// m ? b : a.
    static F select(M m, F a, F b) { return simd::bit_or(simd::bit_and(m, b), simd::and_not(m, a)); }
};

/// quad_test()'s constants, FlatQuad's fields through `get`: one quad's in every lane
/// (OneQuad, from a FlatQuad: the lanes' passes, a ray per lane; or one ray), or a pack's
/// quads lane by lane (PackQuads, from a QuadPack's columns: one ray).
template <class Q, class Get>
struct QuadFields {
    const Q &q;
    Get get;
    auto a(int i) const { return get(q.a[i]); }
    auto n(int i) const { return get(q.n[i]); }
    auto q1(int i) const { return get(q.q1[i]); }
    auto q2(int i) const { return get(q.q2[i]); }
    auto pa() const { return get(q.pa); }
    auto pt() const { return get(q.pt); }
    auto st() const { return get(q.st); }
    auto qn() const { return get(q.qn); }
    auto c(int second, int k) const { return get(q.c[second][k]); }
};
template <class L>
struct Broadcast {
    typename L::F operator()(float x) const { return L::set1(x); }
};
struct LoadColumn {
    simd::V operator()(const float *column) const { return simd::load(column); }
};
template <class L>
using OneQuad = QuadFields<FlatQuad, Broadcast<L>>;
using PackQuads = QuadFields<QuadPack, LoadColumn>;

/// A ray against a FlatQuad, in lanes of L (FlatLanes) or for one ray (ScalarLanes), or a
/// ray against a pack's quads (PackLanes), the same operations in the same order: the
/// plane's distance t = -((o - a) . n) / (d . n), the point h = (o - a) + t d, its
/// coordinates s = h . q1 and r = h . q2. Rounding, bounded as pbrt bounds its shapes'
/// (gamma(k) for k operations; n is a unit vector):
/// - t's error is at most t_err = ((gamma(5) (|o|_1 + |a|_1) + plane) + |t| gamma(3) |d|_1)
///   / |d . n| + gamma(2) |t|, with `plane` the vertices' largest distance from the plane
///   (FlatQuad::pt). A ray leaving the quad (its origin offset off a surface point, which
///   lies on the plane within `plane`) would meet it at t <= t_err: a hit must lie beyond
///   2 t_err (the triangles' test keeps t beyond its own error bound likewise).
/// - s's and r's errors are at most |q|_1 (gamma(5) (|o|_1 + |a|_1 + |t| |d|_1) + t_err
///   |d|_1), plus the vertices' offsets from the corners (FlatQuad::st): the quad is widened
///   by twice that (capped at QuadMargin), so that a ray meeting an edge it shares with
///   another quad, or a triangle's edge, hits one of them (the triangles' watertightness,
///   kept up to rays whose widening reaches the cap: an origin some 10^4 edges away).
template <class L, class K>
RBPT_INLINE QuadHit<L> quad_test(const K &q, const QuadRay<L> &r) {
    using F = typename L::F;
    using M = typename L::M;
    const F zero = L::set1(0.f), one = L::set1(1.f);
    auto dot = [](const F x[3], F c0, F c1, F c2) __attribute__((always_inline)) {
        return L::add(L::add(L::mul(x[0], c0), L::mul(x[1], c1)), L::mul(x[2], c2));
    };
    const F w[3] = {L::sub(r.o[0], q.a(0)), L::sub(r.o[1], q.a(1)), L::sub(r.o[2], q.a(2))};
    const F inv_dn = L::div(one, dot(r.d, q.n(0), q.n(1), q.n(2)));
    const F t = L::mul(L::sub(zero, dot(w, q.n(0), q.n(1), q.n(2))), inv_dn);
    const F h[3] = {L::add(w[0], L::mul(t, r.d[0])), L::add(w[1], L::mul(t, r.d[1])), L::add(w[2], L::mul(t, r.d[2]))};
    const F s = dot(h, q.q1(0), q.q1(1), q.q1(2)), rr = dot(h, q.q2(0), q.q2(1), q.q2(2));
    // The bounds on t's error and on s's and r's.
    const F at = L::abs(t);
    const F t_err = L::add(L::mul(L::add(L::add(r.ao5, q.pt()), L::mul(at, r.ad3)), L::abs(inv_dn)),
                           L::mul(L::set1(gamma(2)), at));
    const F st_err = L::add(L::add(r.ao5, q.pa()), L::add(L::mul(at, r.ad5), L::mul(t_err, r.ad)));
    const F widen = L::min(L::add(q.st(), L::mul(q.qn(), st_err)), L::set1(QuadMargin));
    const F lo = L::sub(zero, widen), hi = L::add(one, widen);
    M hit = L::both(L::both(L::ge(s, lo), L::le(s, hi)), L::both(L::ge(rr, lo), L::le(rr, hi)));
    hit = L::both(hit, L::both(L::gt(t, r.tmin), L::gt(t, L::add(t_err, t_err))));
    // The triangle, and its barycentrics (c0 + cs s + cr r).
    const M second = L::gt(L::add(s, rr), one);
    auto weight = [&](int k) __attribute__((always_inline)) {
        const F c0 = L::select(second, q.c(0, k), q.c(1, k));
        const F cs = L::select(second, q.c(0, k + 1), q.c(1, k + 1));
        const F cr = L::select(second, q.c(0, k + 2), q.c(1, k + 2));
        return L::add(c0, L::add(L::mul(cs, s), L::mul(cr, rr)));
    };
    return {hit, second, t, weight(0), weight(3)};
}

// (GCC 12 takes the unset pass-through operand of AVX-512 intrinsics, _mm512_undefined_ps(),
// for an uninitialised variable in some of the functions below, depending on how far it
// inlines them: GCC bug 105593, fixed in GCC 13. Until the end of the file.)
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"

#if defined(__AVX2__)
/// A register of rays (flat_triangles()' chunk tests, child_masks() and ShapeBoxes::entered()
/// in intrinsics): with AVX-512, sixteen lanes and comparisons as bit masks; with AVX2, eight
/// lanes and comparisons as lanes of all ones. Each operation is the scalar one, lane by lane
/// (min(a, b) is x86's: a < b ? a : b, the second operand when either is NaN).
struct FlatLanes {
#if defined(__AVX512F__) && defined(__AVX512DQ__)
    static constexpr int Width = 16;
    using F = __m512;
    using I = __m512i;
    using M = __mmask16;
    static F load(const float *p) { return _mm512_loadu_ps(p); }
    static I load(const int *p) { return _mm512_loadu_si512(p); }
    static I load(const uint32_t *p) { return _mm512_loadu_si512(p); }
    static void store(float *p, F a) { _mm512_storeu_ps(p, a); }
    static void store(uint32_t *p, I a) { _mm512_storeu_si512(p, a); }
    static F set1(float x) { return _mm512_set1_ps(x); }
    static I set1(uint32_t x) { return _mm512_set1_epi32(int(x)); }
    static F add(F a, F b) { return _mm512_add_ps(a, b); }
    static F sub(F a, F b) { return _mm512_sub_ps(a, b); }
    static F mul(F a, F b) { return _mm512_mul_ps(a, b); }
    static F div(F a, F b) { return _mm512_div_ps(a, b); }
    static F min(F a, F b) { return _mm512_min_ps(a, b); }
    static F max(F a, F b) { return _mm512_max_ps(a, b); }
    static F abs(F a) { return _mm512_abs_ps(a); }
    /// Lane k: table's lane index[k] (index < 3: a vertex's coordinate along the ray's axis).
    static F pick(I index, F table) { return _mm512_permutexvar_ps(index, table); }
    /// A vertex's three coordinates in lanes 0 to 2.
    static F vertex(const float v[3]) { return _mm512_maskz_loadu_ps(__mmask16(0x7), v); }
    static M eq(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_EQ_OQ); }
    static M neq(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_NEQ_UQ); }
    static M lt(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_LT_OQ); }
    static M le(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_LE_OQ); }
    static M gt(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_GT_OQ); }
    static M ge(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_GE_OQ); }
    static M either(M a, M b) { return a | b; }
    static M both(M a, M b) { return a & b; }
    static bool any(M m) { return m != 0; }
    /// m ? b : a, lane by lane.
    static F select(M m, F a, F b) { return _mm512_mask_mov_ps(a, m, b); }
    static I select(M m, I a, I b) { return _mm512_mask_mov_epi32(a, m, b); }
    static I bit_or(I a, I b) { return _mm512_or_si512(a, b); }
    /// (sign bit of s set) ? b : a, lane by lane.
    static F select_by_sign(F s, F a, F b) { return _mm512_mask_blend_ps(_mm512_movepi32_mask(_mm512_castps_si512(s)), a, b); }
#else
    static constexpr int Width = 8;
    using F = __m256;
    using I = __m256i;
    using M = __m256;
    static F load(const float *p) { return _mm256_loadu_ps(p); }
    static I load(const int *p) { return _mm256_loadu_si256(reinterpret_cast<const __m256i *>(p)); }
    static I load(const uint32_t *p) { return _mm256_loadu_si256(reinterpret_cast<const __m256i *>(p)); }
    static void store(float *p, F a) { _mm256_storeu_ps(p, a); }
    static void store(uint32_t *p, I a) { _mm256_storeu_si256(reinterpret_cast<__m256i *>(p), a); }
    static F set1(float x) { return _mm256_set1_ps(x); }
    static I set1(uint32_t x) { return _mm256_set1_epi32(int(x)); }
    static F add(F a, F b) { return _mm256_add_ps(a, b); }
    static F sub(F a, F b) { return _mm256_sub_ps(a, b); }
    static F mul(F a, F b) { return _mm256_mul_ps(a, b); }
    static F div(F a, F b) { return _mm256_div_ps(a, b); }
    static F min(F a, F b) { return _mm256_min_ps(a, b); }
    static F max(F a, F b) { return _mm256_max_ps(a, b); }
    static F abs(F a) { return _mm256_andnot_ps(_mm256_set1_ps(-0.f), a); }
    static F pick(I index, F table) { return _mm256_permutevar8x32_ps(table, index); }
    static F vertex(const float v[3]) { return _mm256_setr_ps(v[0], v[1], v[2], 0.f, 0.f, 0.f, 0.f, 0.f); }
    static M eq(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_EQ_OQ); }
    static M neq(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_NEQ_UQ); }
    static M lt(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_LT_OQ); }
    static M le(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_LE_OQ); }
    static M gt(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_GT_OQ); }
    static M ge(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_GE_OQ); }
    static M either(M a, M b) { return _mm256_or_ps(a, b); }
    static M both(M a, M b) { return _mm256_and_ps(a, b); }
    static bool any(M m) { return _mm256_movemask_ps(m) != 0; }
    static F select(M m, F a, F b) { return _mm256_blendv_ps(a, b, m); }
    static I select(M m, I a, I b) {
        return _mm256_castps_si256(_mm256_blendv_ps(_mm256_castsi256_ps(a), _mm256_castsi256_ps(b), m));
    }
    static F select_by_sign(F s, F a, F b) { return _mm256_blendv_ps(a, b, s); }
    static I bit_or(I a, I b) { return _mm256_or_si256(a, b); }
#endif
    /// enters_box() lane by lane: whether each ray (origin o, 1 / d inv_d) enters the box
    /// [lo, hi] within [t0, t1], t1 widened by `widen`.
    static M enters(const F o[3], const F inv_d[3], const float lo[3], const float hi[3], F t0, F t1, F widen) {
        for (int a = 0; a < 3; ++a) {
            const F box_lo = set1(lo[a]), box_hi = set1(hi[a]);
            const F t_near = mul(sub(select_by_sign(inv_d[a], box_lo, box_hi), o[a]), inv_d[a]);
            const F t_far = mul(sub(select_by_sign(inv_d[a], box_hi, box_lo), o[a]), inv_d[a]);
            t0 = max(t_near, t0);  // (tn > t0 ? tn : t0, as enters_box())
            t1 = min(t_far, t1);
        }
        return le(t0, mul(t1, widen));
    }
};
static_assert(BVH::FlatChunk % FlatLanes::Width == 0, "a chunk is whole registers of rays");
#endif

void ShapeBoxes::add(const Geometry &geometry, uint32_t shape) {
    const Shape &s = geometry.shapes[shape];
    Bounds box;
    if (s.kind == ShapeKind::Mesh) {
        for (uint32_t i = s.vertex_begin; i < s.vertex_begin + s.vertex_count; ++i) box.extend(geometry.positions[i]);
    } else {
        box = analytic_bounds(s);
    }
    if (!(box.lo.x <= box.hi.x)) return;  // (a mesh without vertices)
    // Widened as flat_triangles() widens its pairs' boxes.
    for (int a = 0; a < 3; ++a) {
        const float margin = skip_margin(box.lo[a], box.hi[a]);
        lo[a].push_back(box.lo[a] - margin), hi[a].push_back(box.hi[a] + margin);
    }
}

void ShapeBoxes::entered(const RayColumns &r, int n, int *enters) const {
    const float *r_ox = r.ox, *r_oy = r.oy, *r_oz = r.oz, *r_dx = r.dx, *r_dy = r.dy, *r_dz = r.dz;
    const float *r_tmin = r.tmin, *r_tmax = r.tmax;
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        // (A sum of magnitudes is finite exactly when each is.)
        const float sum = ((std::abs(r_ox[k]) + std::abs(r_oy[k])) + std::abs(r_oz[k])) +
                          ((std::abs(r_dx[k]) + std::abs(r_dy[k])) + std::abs(r_dz[k]));
        enters[k] = sum < Infinity ? 0 : 1;
    }
    int k0 = 0;
#if defined(__AVX2__)
    // A register of rays at a time against every box (as BVH::child_masks(): the rays'
    // columns loaded and 1 / d taken once for all boxes).
    using L = FlatLanes;
    using F = typename L::F;
    const F widen = L::set1(1.0001f), one = L::set1(1.f);
    for (; k0 + L::Width <= n; k0 += L::Width) {
        const F o[3] = {L::load(r_ox + k0), L::load(r_oy + k0), L::load(r_oz + k0)};
        const F inv_d[3] = {L::div(one, L::load(r_dx + k0)), L::div(one, L::load(r_dy + k0)), L::div(one, L::load(r_dz + k0))};
        const F tmin = L::load(r_tmin + k0), tmax = L::load(r_tmax + k0);
        typename L::I any = L::load(enters + k0);
        for (int i = 0; i < size(); ++i) {
            const float box_lo[3] = {lo[0][i], lo[1][i], lo[2][i]}, box_hi[3] = {hi[0][i], hi[1][i], hi[2][i]};
            any = L::select(L::enters(o, inv_d, box_lo, box_hi, tmin, tmax, widen), any, L::set1(1u));
        }
        L::store(reinterpret_cast<uint32_t *>(enters + k0), any);
    }
#endif
    // Each box against the rays past the last whole register (without AVX2, all of them), in
    // the vectoriser's lanes.
    for (int i = 0; i < size(); ++i) {
        const float box_lo[3] = {lo[0][i], lo[1][i], lo[2][i]}, box_hi[3] = {hi[0][i], hi[1][i], hi[2][i]};
#pragma GCC ivdep
        for (int k = k0; k < n; ++k) {
            const Vec3 o{r_ox[k], r_oy[k], r_oz[k]}, inv_d{1.f / r_dx[k], 1.f / r_dy[k], 1.f / r_dz[k]};
            enters[k] |= enters_box(box_lo, box_hi, o, inv_d, r_tmin[k], r_tmax[k], 1.0001f);
        }
    }
}

void BVH::build(const Geometry &geometry) {
    std::vector<uint32_t> all(geometry.primitive_count());
    for (uint32_t i = 0; i < uint32_t(all.size()); ++i) all[i] = i;
    build(geometry, all);
}

void BVH::build(const Geometry &geometry, const std::vector<uint32_t> &subset) {
    geometry_ = &geometry;
    uint32_t n = uint32_t(subset.size());
    std::vector<PrimInfo> prims(n);
    for (uint32_t i = 0; i < n; ++i) {
        const uint32_t id = subset[i];
        Bounds b;
        if (geometry.is_triangle(id)) {
            for (uint32_t v : geometry.triangles[id].v) b.extend(geometry.positions[v]);
        } else {
            b = analytic_bounds(geometry.analytic_shape(id));
        }
        prims[i] = {b, b.center(), id, !geometry.is_triangle(id)};
    }
    nodes_.clear();
    packs_.clear();
    sah_cost_ = 0.0;
    if (n == 0) return;  // an empty scene: traversal returns at once

    // Build the binary tree.
    std::vector<BinaryNode> bin;
    bin.reserve(2 * size_t(n) + 1);
    bin.emplace_back();
    Builder{prims, bin}.build(0, 0, n);
    double root = binary_area(bin[0]);
    // (Over the SAH's tree: its leaves count their primitives, the nodes above them 1.)
    std::vector<uint32_t> todo{0};
    while (!todo.empty()) {
        const BinaryNode &node = bin[todo.back()];
        uint32_t index = todo.back();
        todo.pop_back();
        sah_cost_ += binary_area(node) / root * (node.leaf ? double(node.total) : 1.0);
        if (!node.leaf) todo.insert(todo.end(), {index + 1, node.offset});
    }

    // Collapse it; a root that is a leaf becomes the only child of the root node.
    Collapser collapser{bin, prims, geometry, nodes_, packs_};
    const uint32_t root_kid = 0;
    if (bin[0].count == 0) {  // (a root that is an SAH leaf is opened into the free slots)
        collapser.inner(0, 0);
    } else {
        collapser.node(&root_kid, 1, 0);
    }

    // A small tree of triangles, spheres, disks and cylinders is also kept flat
    // (intersect_columns()).
    flat_triangles_.clear();
    flat_coords_.clear();
    flat_prims_.clear();
    flat_spheres_.clear();
    flat_others_.clear();
    int n_triangles = 0, n_spheres = 0, n_others = 0;
    for (const PrimPack &pack : packs_) {
        n_triangles += __builtin_popcount(pack.triangles);
        n_spheres += __builtin_popcount(pack.spheres);
        n_others += __builtin_popcount(pack.others);
    }
    // A pack's triangles, lane by lane, appended to `tris`.
    auto append_triangles = [](const PrimPack &pack, std::vector<FlatTriangle> &tris) {
        for (int lane = 0; lane < BVHWidth; ++lane) {
            if (!(pack.triangles >> lane & 1)) continue;
            FlatTriangle t;
            for (int k = 0; k < 3; ++k)
                for (int axis = 0; axis < 3; ++axis) t.v[k][axis] = pack.tris.v[k][axis][lane];
            t.prim = pack.prim[lane];
            tris.push_back(t);
        }
    };
    two_phase_ = false;
    root_packs_.clear();
    root_inner_mask_ = 0;
    // A larger tree whose root has leaves of triangles only, at most FlatTriangles (a room's
    // walls and lights around a detailed mesh), is searched in two phases: those leaves'
    // triangles in lanes (as a flat tree's), then the rest of the tree (see two_phase()).
    if (nodes_.size() > 1) {
        bool ok = true;
        std::vector<FlatTriangle> tris;
        for (int c = 0; c < BVHWidth; ++c) {
            const uint32_t ref = nodes_[0].child[c];
            if (ref == EmptyChild) continue;
            if (!(ref & LeafBit)) {
                root_inner_mask_ |= 1u << c;
                continue;
            }
            const uint32_t first = (ref & ~LeafBit) >> 3, last = first + (ref & 7) + 1;
            for (uint32_t p = first; p < last; ++p) {
                const PrimPack &pack = packs_[p];
                ok = ok && pack.spheres == 0 && pack.others == 0;
                root_packs_.push_back(p);
                append_triangles(pack, tris);
            }
        }
        if (ok && !tris.empty() && tris.size() <= size_t(FlatTriangles)) {
            two_phase_ = true;
            flat_triangles_ = tris;
            flat_spheres_.clear();
        } else {
            root_packs_.clear();
            root_inner_mask_ = 0;
        }
    }
    // (Beyond one node too, unless it is searched in two phases: few primitives, some of
    // them spheres, in a tree of several nodes, as a room of balls, are faster tested in lanes
    // than traversed one ray at a time.)
    if (!two_phase_ && n_triangles <= FlatTriangles && n_spheres <= FlatSpheres && n_others <= FlatOthers) {
        for (const PrimPack &pack : packs_) {
            append_triangles(pack, flat_triangles_);
            for (int lane = 0; lane < BVHWidth; ++lane) {
                if (pack.spheres >> lane & 1) flat_spheres_.push_back(pack.prim[lane]);
                if (!(pack.others >> lane & 1)) continue;
                const Bounds box = analytic_bounds(geometry_->analytic_shape(pack.prim[lane]));
                flat_others_.push_back({pack.prim[lane], {box.lo.x, box.lo.y, box.lo.z}, {box.hi.x, box.hi.y, box.hi.z}});
            }
        }
    }
    if (!flat_triangles_.empty()) {
        // Triangles in pairs of the smallest joint box (a rectangle's two halves), taken in
        // turn: flat_triangles() skips each pair for the chunks of rays that miss its box.
        const size_t n = flat_triangles_.size();
        auto box_of = [](const FlatTriangle &t) {
            Bounds b;
            for (int j = 0; j < 3; ++j) b.extend(Vec3{t.v[j][0], t.v[j][1], t.v[j][2]});
            return b;
        };
        std::vector<FlatTriangle> paired;
        std::vector<bool> taken(n, false);
        for (size_t i = 0; i < n; ++i) {
            if (taken[i]) continue;
            taken[i] = true;
            paired.push_back(flat_triangles_[i]);
            const Bounds box_i = box_of(flat_triangles_[i]);
            size_t best = n;
            float best_area = Infinity;
            for (size_t j = i + 1; j < n; ++j) {
                if (taken[j]) continue;
                Bounds b = box_i;
                b.extend(box_of(flat_triangles_[j]));
                const float area = b.area();
                if (area < best_area) best = j, best_area = area;
            }
            if (best < n) taken[best] = true, paired.push_back(flat_triangles_[best]);
        }
        flat_triangles_ = paired;
        // Their box's area (flat_triangles() tests a single triangle chunk by chunk where its
        // box is small beside it).
        Bounds box;
        for (const FlatTriangle &t : flat_triangles_) box.extend(box_of(t));
        flat_area_ = box.area();
        for (int a = 0; a < 3; ++a) flat_lo_[a] = box.lo[a], flat_hi_[a] = box.hi[a];
        // The vertices again as columns [vertex][axis][triangle], for flat_rounding_check().
        flat_coords_.resize(9 * n);
        for (size_t i = 0; i < n; ++i)
            for (int j = 0; j < 3; ++j)
                for (int a = 0; a < 3; ++a) flat_coords_[(3 * j + a) * n + i] = flat_triangles_[i].v[j][a];
        flat_prims_.resize(n);
        for (size_t i = 0; i < n; ++i) flat_prims_[i] = flat_triangles_[i].prim;
    }
    build_quads();
}

void BVH::build_quads() {
    flat_quads_.clear();
    flat_half_quad_.assign(flat_triangles_.size() / 2, -1);
    // (The pairs of flat_columns()' passes of four: the last triangles, fewer than four, are
    // tested one by one. Only where the flat triangles are all in leaves of the root, whose
    // boxes are widened for them below: not in a flat tree of several nodes.)
    const bool root_leaves = nodes_.size() == 1 || two_phase_;
    const size_t halves = root_leaves ? flat_triangles_.size() / 4 * 2 : 0;
    using D3 = std::array<double, 3>;
    auto sub = [](const D3 &a, const D3 &b) { return D3{a[0] - b[0], a[1] - b[1], a[2] - b[2]}; };
    auto cross = [](const D3 &a, const D3 &b) {
        return D3{a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
    };
    auto dot = [](const D3 &a, const D3 &b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; };
    auto dot_f = [](const D3 &a, const float b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; };
    auto norm1 = [](const float a[3]) { return std::abs(a[0]) + std::abs(a[1]) + std::abs(a[2]); };
    for (size_t h = 0; h < halves; ++h) {
        const FlatTriangle &t0 = flat_triangles_[2 * h], &t1 = flat_triangles_[2 * h + 1];
        auto vertex = [](const FlatTriangle &t, int j) { return D3{t.v[j][0], t.v[j][1], t.v[j][2]}; };
        // The two vertices they share (the diagonal), bit for bit: j0[k] of t0 is j1[k] of t1.
        int j0[3], j1[3], shared = 0;
        for (int j = 0; j < 3; ++j)
            for (int l = 0; l < 3; ++l)
                if (shared < 3 && vertex(t0, j) == vertex(t1, l)) j0[shared] = j, j1[shared] = l, ++shared;
        if (shared != 2) continue;
        const int ja = 3 - j0[0] - j0[1], jb = 3 - j1[0] - j1[1];
        const D3 a = vertex(t0, ja), p = vertex(t0, j0[0]), c = vertex(t0, j0[1]), b = vertex(t1, jb);
        // The plane and the dual basis of the edges from a, in double, kept as floats.
        const D3 e1 = sub(p, a), e2 = sub(c, a), n = cross(e1, e2);
        const double nn = dot(n, n);
        if (!(nn > 0.0) || !std::isfinite(nn)) continue;
        const D3 q1 = cross(e2, n), q2 = cross(n, e1);
        FlatQuad q;
        for (int i = 0; i < 3; ++i) {
            q.a[i] = float(a[i]);
            q.n[i] = float(n[i] / std::sqrt(nn));
            q.q1[i] = float(q1[i] / nn);
            q.q2[i] = float(q2[i] / nn);
        }
        // The vertices' distances from the plane and offsets from their corners (s, r), as
        // the float plane and basis place them: a parallelogram's are roundings.
        double plane = 0.0, corner = 0.0, size = std::sqrt(dot(e1, e1)) + std::sqrt(dot(e2, e2));
        const D3 vertices[4] = {a, p, c, b};
        const double corners[4][2] = {{0, 0}, {1, 0}, {0, 1}, {1, 1}};
        for (int i = 0; i < 4; ++i) {
            const D3 x = sub(vertices[i], a);
            plane = std::max(plane, std::abs(dot_f(x, q.n)));
            corner = std::max({corner, std::abs(dot_f(x, q.q1) - corners[i][0]), std::abs(dot_f(x, q.q2) - corners[i][1])});
        }
        if (!(plane <= 1e-6 * size) || !(corner <= 1e-6)) continue;  // (not a parallelogram)
        // The bounds' terms, rounded up.
        q.pa = gamma(5) * norm1(q.a) * (1.f + 1e-5f);
        q.pt = float((q.pa + plane) * (1.0 + 1e-5));
        q.st = float(2.0 * corner * (1.0 + 1e-5));
        q.qn = 2.f * std::max(norm1(q.q1), norm1(q.q2)) * (1.f + 1e-5f);
        // Each triangle's barycentrics u and v, the weights of its vertices 1 and 2, in (s, r):
        // a + s e1 + r e2 = a (1 - s - r) + p s + c r = b (s + r - 1) + p (1 - r) + c (1 - s).
        const float first[3][3] = {{1, -1, -1}, {0, 1, 0}, {0, 0, 1}};    // a, p, c
        const float second[3][3] = {{-1, 1, 1}, {1, 0, -1}, {1, -1, 0}};  // b, p, c
        for (int slot = 1; slot <= 2; ++slot) {
            const int i0 = slot == ja ? 0 : (slot == j0[0] ? 1 : 2);
            const int i1 = slot == jb ? 0 : (slot == j1[0] ? 1 : 2);
            for (int k = 0; k < 3; ++k) {
                q.c[0][3 * (slot - 1) + k] = first[i0][k];
                q.c[1][3 * (slot - 1) + k] = second[i1][k];
            }
        }
        q.prim[0] = t0.prim, q.prim[1] = t1.prim;
        flat_half_quad_[h] = int(flat_quads_.size());
        flat_quads_.push_back(q);
    }
    // In the packs, their triangles' lanes (left out of the triangle test) and, in each pack,
    // one lane per quad whose test it runs (its first triangle's, or the second's where the
    // first lies in another pack: a quad is tested from each leaf that holds a half), with
    // those quads' constants in a QuadPack (its other lanes zero: no hit).
    quad_packs_.clear();
    pack_quad_.assign(packs_.size(), -1);
    for (size_t p = 0; p < packs_.size(); ++p) {
        PrimPack &pack = packs_[p];
        pack.in_quads = pack.quads = 0;
        QuadPack columns{};
        for (const FlatQuad &q : flat_quads_) {
            int lanes[2] = {-1, -1};
            for (int lane = 0; lane < BVHWidth; ++lane) {
                if (!(pack.triangles >> lane & 1)) continue;
                for (int j = 0; j < 2; ++j)
                    if (pack.prim[lane] == q.prim[j]) lanes[j] = lane;
            }
            for (int j = 0; j < 2; ++j)
                if (lanes[j] >= 0) pack.in_quads |= uint8_t(1 << lanes[j]);
            const int l = lanes[0] >= 0 ? lanes[0] : lanes[1];
            if (l < 0) continue;
            pack.quads |= uint8_t(1 << l);
            for (int i = 0; i < 3; ++i) {
                columns.a[i][l] = q.a[i], columns.n[i][l] = q.n[i];
                columns.q1[i][l] = q.q1[i], columns.q2[i][l] = q.q2[i];
            }
            columns.pa[l] = q.pa, columns.pt[l] = q.pt, columns.st[l] = q.st, columns.qn[l] = q.qn;
            for (int j = 0; j < 2; ++j)
                for (int k = 0; k < 6; ++k) columns.c[j][k][l] = q.c[j][k];
            columns.prim[0][l] = q.prim[0], columns.prim[1][l] = q.prim[1];
        }
        if (!pack.quads) continue;
        pack_quad_[p] = int(quad_packs_.size());
        quad_packs_.push_back(columns);
    }
    // The root's leaf children's boxes widened to hold their quads' widenings (so that a ray
    // hitting a quad enters the box of each leaf that tests it).
    if (flat_quads_.empty()) return;
    BVHNode &root = nodes_[0];
    for (int c = 0; c < BVHWidth; ++c) {
        const uint32_t ref = root.child[c];
        if (ref == EmptyChild || !(ref & LeafBit)) continue;
        const uint32_t first = (ref & ~LeafBit) >> 3, last = first + (ref & 7) + 1;
        for (uint32_t p = first; p < last; ++p) {
            for (int mask = packs_[p].quads; mask; mask &= mask - 1) {
                const QuadPack &quads = quad_packs_[size_t(pack_quad_[p])];
                const int l = __builtin_ctz(mask);
                const uint32_t prims[2] = {quads.prim[0][l], quads.prim[1][l]};
                for (int a = 0; a < 3; ++a) {
                    // The quad's extent along the axis, from its corners a, a + e1, a + e2
                    // (its triangles' vertices), widened by twice QuadMargin of it.
                    float lo = quads.a[a][l], hi = quads.a[a][l];
                    for (const FlatTriangle &t : flat_triangles_) {
                        if (t.prim != prims[0] && t.prim != prims[1]) continue;
                        for (int j = 0; j < 3; ++j) lo = std::min(lo, t.v[j][a]), hi = std::max(hi, t.v[j][a]);
                    }
                    const float margin = 2.f * QuadMargin * (hi - lo) + 1e-6f * std::max(std::abs(lo), std::abs(hi));
                    root.lo[a][c] = std::min(root.lo[a][c], lo - margin);
                    root.hi[a][c] = std::max(root.hi[a][c], hi + margin);
                }
            }
        }
    }
}

/// Whether a ray's origin is finite: one that is not hits nothing (and must not enter empty
/// boxes), in every query.
RBPT_INLINE bool finite_origin(const Ray &ray) {
    return std::isfinite(ray.o.x) && std::isfinite(ray.o.y) && std::isfinite(ray.o.z);
}

/// The slab test of a ray against all child boxes of a node at once (Williams et al. 2005):
/// the per-ray constants splatted over the lanes, and the test returning the mask of children
/// entered before `tmax` with their entry distances. A NaN (0 * inf, the origin on a slab plane
/// of a parallel ray) is dropped by max/min, which return their second operand.
struct NodeTest {
    simd::V o[3], inv_d[3], tmin;
    bool neg[3];
    NodeTest(const Ray &ray) : tmin(simd::set1(ray.tmin)) {
        for (int axis = 0; axis < 3; ++axis) {
            float inv = 1.f / ray.d[axis];
            o[axis] = simd::set1(ray.o[axis]);
            inv_d[axis] = simd::set1(inv);
            neg[axis] = std::signbit(inv);
        }
    }
    int operator()(const BVHNode &node, float tmax, float t_entry[BVHWidth]) const {
        using namespace simd;
        V t0 = tmin, t1 = set1(tmax);
        for (int axis = 0; axis < 3; ++axis) {
            V lo = load(node.lo[axis]), hi = load(node.hi[axis]);
            V t_near = mul(sub(neg[axis] ? hi : lo, o[axis]), inv_d[axis]);
            V t_far = mul(sub(neg[axis] ? lo : hi, o[axis]), inv_d[axis]);
            t0 = max(t_near, t0);
            t1 = min(t_far, t1);
        }
        store(t_entry, t0);
        return mask(le(t0, mul(t1, set1(BoxWiden))));
    }
};

/// The lane of `mask` with the smallest t (of equal ones, the lowest).
RBPT_INLINE int nearest_lane(int mask, const float t[BVHWidth]) {
    int best = __builtin_ctz(mask);
    for (mask &= mask - 1; mask; mask &= mask - 1) {
        const int i = __builtin_ctz(mask);
        if (t[i] < t[best]) best = i;
    }
    return best;
}

template <bool AnyHit>
RBPT_INLINE bool BVH::intersect_pack(const PrimPack &pack, const Ray &ray, const RayPrecompPack &pc,
                                     float &tmax, Hit *hit) const {
    bool found = false;
    const int triangles = pack.triangles & ~pack.in_quads;
    if (triangles) {
        float t[BVHWidth], u[BVHWidth], v[BVHWidth];
        int mask = intersect_triangles(pc, pack.tris, triangles, ray.tmin, tmax, t, u, v);
        if (mask) {
            if (AnyHit) return true;
            const int best = nearest_lane(mask, t);
            found = true;
            tmax = t[best];
            hit->t = t[best];
            hit->prim = pack.prim[best];
            hit->u = u[best];
            hit->v = v[best];
        }
    }
    if (__builtin_expect(pack.quads != 0, 0)) {
        // The pack's quads in one vector test, the nearest hit of the lowest lane kept.
        using L = PackLanes;
        const QuadPack &quads = quad_packs_[size_t(pack_quad_[size_t(&pack - packs_.data())])];
        const QuadRay<L> r(L::set1(ray.o.x), L::set1(ray.o.y), L::set1(ray.o.z), L::set1(ray.d.x), L::set1(ray.d.y),
                           L::set1(ray.d.z), L::set1(ray.tmin));
        const QuadHit<L> h = quad_test(PackQuads{quads, {}}, r);
        int mask = simd::mask(L::both(h.hit, L::lt(h.t, L::set1(tmax)))) & pack.quads;
        if (mask) {
            if (AnyHit) return true;
            alignas(32) float t[BVHWidth], u[BVHWidth], v[BVHWidth];
            simd::store(t, h.t), simd::store(u, h.u), simd::store(v, h.v);
            const int best = nearest_lane(mask, t);
            found = true;
            tmax = t[best];
            hit->t = t[best], hit->u = u[best], hit->v = v[best];
            hit->prim = quads.prim[simd::mask(h.second) >> best & 1][best];
        }
    }
    for (int mask = pack.spheres; mask; mask &= mask - 1) {
        uint32_t prim = pack.prim[__builtin_ctz(mask)];
        const Shape &s = geometry_->analytic_shape(prim);
        float t;
        if (!intersect_sphere(ray, s.center, s.radius, ray.tmin, tmax, &t)) continue;
        if (AnyHit) return true;
        found = true;
        tmax = t;
        hit->t = t;
        hit->prim = prim;
        hit->u = hit->v = 0.f;
    }
    if (__builtin_expect(pack.others != 0, 0) && intersect_others(ray, pack, tmax, hit)) {
        if (AnyHit) return true;
        found = true;
        tmax = hit->t;
    }
    return found;
}

template <bool AnyHit, bool InnerOnly>
bool BVH::traverse(const Ray &ray, Hit *hit, uint32_t start) const {
    if (nodes_.empty() || !finite_origin(ray)) return false;
    // The triangle test's per-ray constants, set up at the first leaf: most rays of a large
    // scene leave it after a few boxes, without reaching one.
    RayPrecompPack pc;
    bool pc_ready = false;
    const NodeTest node_test(ray);
    float tmax = ray.tmax;
    bool found = false;
    struct Entry {
        uint32_t ref;
        float t;  ///< entry distance into the box
    } stack[StackSize];
    int sp = 0;
    uint32_t ref = start;
    while (true) {
        if (!(ref & LeafBit)) {
            // Test the ray against the node's child boxes.
            const BVHNode &node = nodes_[ref];
            alignas(32) float t_entry[BVHWidth];
            int mask = node_test(node, tmax, t_entry);
            if (InnerOnly && ref == 0) mask &= int(root_inner_mask_);
            if (mask) {
                // Start loading the hit children now: traversal is bound by memory latency.
                for (int m = mask; m; m &= m - 1) {
                    uint32_t child = node.child[__builtin_ctz(m)];
                    if (child & LeafBit) {  // its first pack
                        const char *p = reinterpret_cast<const char *>(&packs_[(child & ~LeafBit) >> 3]);
                        for (size_t line = 0; line < sizeof(PrimPack); line += 64)
                            _mm_prefetch(p + line, _MM_HINT_T0);
                    } else {
                        const char *p = reinterpret_cast<const char *>(&nodes_[child]);
                        for (size_t line = 0; line < sizeof(BVHNode); line += 64)
                            _mm_prefetch(p + line, _MM_HINT_T0);
                    }
                }
                int c = __builtin_ctz(mask);
                mask &= mask - 1;
                if (!mask) {
                    ref = node.child[c];
                    continue;
                }
                if (AnyHit) {
                    // Any hit ends the query, so the order does not matter: visit the first.
                    for (; mask; mask &= mask - 1) {
                        int other = __builtin_ctz(mask);
                        stack[sp++] = {node.child[other], t_entry[other]};
                    }
                    ref = node.child[c];
                    continue;
                }
                // Several children: each placed by its rank, farthest entry first and of
                // equal entries the lower slot first (so the nearest is visited next, the
                // others popped nearest first), counted in lanes rather than sorted.
                const int all = mask | 1 << c;
                const simd::V t_all = simd::load(t_entry);
                Entry hits[BVHWidth];
                for (int m = all; m; m &= m - 1) {
                    c = __builtin_ctz(m);
                    const simd::V t_c = simd::set1(t_entry[c]);
                    const int farther = simd::mask(simd::gt(t_all, t_c)) & all;
                    const int tied_before = simd::mask(simd::eq(t_all, t_c)) & all & ((1 << c) - 1);
                    hits[__builtin_popcount(farther) + __builtin_popcount(tied_before)] = {node.child[c], t_entry[c]};
                }
                const int n = __builtin_popcount(all);
                for (int i = 0; i < n - 1; ++i) stack[sp++] = hits[i];
                ref = hits[n - 1].ref;
                continue;
            }
        } else {
            // Intersect the packs of a leaf.
            if (!pc_ready) {
                pc = RayPrecompPack(ray);
                pc_ready = true;
            }
            uint32_t first = (ref & ~LeafBit) >> 3, last = first + (ref & 7) + 1;
            for (uint32_t p = first; p < last; ++p) {
                if (intersect_pack<AnyHit>(packs_[p], ray, pc, tmax, hit)) {
                    if (AnyHit) return true;
                    found = true;
                }
            }
        }
        // Pop the next entry that may still hold a nearer hit.
        do {
            if (sp == 0) return found;
            --sp;
        } while (stack[sp].t > tmax * BoxWiden);
        ref = stack[sp].ref;
    }
}

bool BVH::intersect_others(const Ray &ray, const PrimPack &pack, float tmax, Hit *hit) const {
    bool found = false;
    for (int mask = pack.others; mask; mask &= mask - 1) {
        uint32_t prim = pack.prim[__builtin_ctz(mask)];
        AnalyticHit h = intersect_disk_or_cylinder(ray, geometry_->analytic_shape(prim), ray.tmin, tmax);
        if (!h.hit) continue;
        found = true;
        tmax = h.t;
        hit->t = h.t;
        hit->prim = prim;
        hit->u = h.u;
        hit->v = h.v;
    }
    return found;
}

/// For each ray, the mask of the root's children in `children` whose boxes it enters in
/// (tmin, min(tmax, limit[k])): NodeTest's operations lane by lane (so the per-ray
/// traversal's decision, for a finite origin).
void BVH::child_masks(const RayColumns &r, int n, const float *limit, uint32_t children, int *mask) const {
    const BVHNode &node = nodes_[0];
    int used[BVHWidth], n_used = 0;
    for (int c = 0; c < BVHWidth; ++c) {
        if (children >> c & 1 && node.child[c] != EmptyChild) used[n_used++] = c;
    }
    const float *q_ox = r.ox, *q_oy = r.oy, *q_oz = r.oz, *q_dx = r.dx, *q_dy = r.dy, *q_dz = r.dz;
    const float *q_tmin = r.tmin, *q_tmax = r.tmax;
    int k0 = 0;
#if defined(__AVX2__)
    // A register of rays at a time against every child in turn: the rays' columns loaded, and
    // the near and far planes' choice made, once for all children, the mask kept in a
    // register (children outermost, each pass over the rays had loaded them again and read
    // and written the masks: 4.3% of cornell-box's render, whose shadow rays take this, 3.4%
    // so).
    using L = FlatLanes;
    using F = typename L::F;
    const F widen = L::set1(BoxWiden);
    for (; k0 + L::Width <= n; k0 += L::Width) {
        const F o[3] = {L::load(q_ox + k0), L::load(q_oy + k0), L::load(q_oz + k0)};
        const F one = L::set1(1.f);
        const F inv_d[3] = {L::div(one, L::load(q_dx + k0)), L::div(one, L::load(q_dy + k0)),
                            L::div(one, L::load(q_dz + k0))};
        const F tmin = L::load(q_tmin + k0), tmax = L::load(q_tmax + k0), lim = L::load(limit + k0);
        // (tmax < limit ? tmax : limit, as the loop below.)
        const F t_end = L::min(tmax, lim);
        typename L::I bits = L::set1(0u);
        for (int u = 0; u < n_used; ++u) {
            const int c = used[u];
            const float lo[3] = {node.lo[0][c], node.lo[1][c], node.lo[2][c]};
            const float hi[3] = {node.hi[0][c], node.hi[1][c], node.hi[2][c]};
            bits = L::select(L::enters(o, inv_d, lo, hi, tmin, t_end, widen), bits, L::bit_or(bits, L::set1(uint32_t(1) << c)));
        }
        L::store(reinterpret_cast<uint32_t *>(mask + k0), bits);
    }
#endif
    // Each child against the rays past the last whole register (without AVX2, all of them),
    // in the vectoriser's lanes.
    alignas(64) float inv_x[MaxColumns], inv_y[MaxColumns], inv_z[MaxColumns], tmax[MaxColumns];
#pragma GCC ivdep
    for (int k = k0; k < n; ++k) {
        inv_x[k] = 1.f / q_dx[k], inv_y[k] = 1.f / q_dy[k], inv_z[k] = 1.f / q_dz[k];
        tmax[k] = q_tmax[k] < limit[k] ? q_tmax[k] : limit[k];
        mask[k] = 0;
    }
    for (int u = 0; u < n_used; ++u) {
        const int c = used[u];
        const float lo[3] = {node.lo[0][c], node.lo[1][c], node.lo[2][c]};
        const float hi[3] = {node.hi[0][c], node.hi[1][c], node.hi[2][c]};
        const int bit = 1 << c;
#pragma GCC ivdep
        for (int k = k0; k < n; ++k) {
            const Vec3 o{q_ox[k], q_oy[k], q_oz[k]}, inv_d{inv_x[k], inv_y[k], inv_z[k]};
            mask[k] |= enters_box(lo, hi, o, inv_d, q_tmin[k], tmax[k], BoxWiden) ? bit : 0;
        }
    }
}

void BVH::root_masks(const RayColumns &r, int n, int *mask) const { child_masks(r, n, r.tmax, ~0u, mask); }

/// Whether each ray enters one of the root's inner children's boxes before min(its tmax,
/// limit[k]) (nonzero: the mask of those children).
void BVH::enters_inner(const RayColumns &r, int n, const float *limit, int *enters) const {
    child_masks(r, n, limit, root_inner_mask_, enters);
}

bool BVH::intersect_two_phase(const Ray &ray, Hit *hit) const {
    if (!finite_origin(ray)) return false;
    const RayPrecompPack pc(ray);
    Ray rest = ray;
    bool found = false;
    for (uint32_t p : root_packs_) found |= intersect_pack<false>(packs_[p], ray, pc, rest.tmax, hit);
    return traverse<false, true>(rest, hit) || found;
}

bool BVH::occluded_two_phase(const Ray &ray) const {
    if (!finite_origin(ray)) return false;
    const RayPrecompPack pc(ray);
    Hit unused;
    float tmax = ray.tmax;
    for (uint32_t p : root_packs_) {
        if (intersect_pack<true>(packs_[p], ray, pc, tmax, &unused)) return true;
    }
    return traverse<true, true>(ray, &unused);
}

bool BVH::intersect(const Ray &ray, Hit *hit) const {
    if (two_phase_) return intersect_two_phase(ray, hit);
    if (nodes_.size() == 1) return intersect_one_node(ray, hit);
    return intersect_traversal(ray, hit);
}

int BVH::root_children(const Ray &ray, float t_entry[BVHWidth]) const {
    if (!finite_origin(ray)) return 0;
    return NodeTest(ray)(nodes_[0], ray.tmax, t_entry);
}

/// intersect() in a tree of one node (a small scene): the children whose boxes the ray enters,
/// nearest entry first (of equal entries the later slot first), each while it may still hold
/// a nearer hit: the children traverse<false> visits, in its order, so the same hit (ties
/// go to the child visited first), without its stack and prefetches. (Where the tree is
/// flat, intersect_columns() tests the triangles in lanes instead, much faster: one ray at a
/// time through this, cornell-box took 1.33x as long, cbox 1.5x. It runs for the rays the
/// lanes leave to intersect(), and for scenes of one node that are not flat (disks,
/// cylinders; until session 33, AVX2 builds' cornell-box, 3% faster than traverse<false>).)
bool BVH::intersect_one_node(const Ray &ray, Hit *hit) const {
    const BVHNode &node = nodes_[0];
    alignas(32) float t_entry[BVHWidth];
    int mask = root_children(ray, t_entry);
    if (!mask) return false;
    // The children entered, sorted by (entry, slot descending): slots inserted in increasing
    // order, each before those of entries no nearer. (The traversal's order, which it places
    // by rank counted in lanes; here, for one node's few children, that took 2% longer: AVX2
    // cornell-box 468-471 -> 478-481 ms.)
    int order[BVHWidth], n = 0;
    for (int m = mask; m; m &= m - 1) {
        const int c = __builtin_ctz(m);
        int i = n++;
        for (; i > 0 && t_entry[order[i - 1]] >= t_entry[c]; --i) order[i] = order[i - 1];
        order[i] = c;
    }
    const RayPrecompPack pc(ray);
    float tmax = ray.tmax;
    bool found = false;
    for (int j = 0; j < n; ++j) {
        const int c = order[j];
        if (j > 0 && t_entry[c] > tmax * BoxWiden) continue;
        const uint32_t ref = node.child[c];
        const uint32_t first = (ref & ~LeafBit) >> 3, last = first + (ref & 7) + 1;
        for (uint32_t p = first; p < last; ++p) found |= intersect_pack<false>(packs_[p], ray, pc, tmax, hit);
    }
    return found;
}

namespace {

/// x86's max: a > b ? a : b, the second operand when either is NaN (simd::max's, which
/// intersect_triangles() uses).
RBPT_INLINE float max_ps(float a, float b) { return a > b ? a : b; }

/// c selects among a (0), b (1) and d (2): an axis of a vertex, picked per ray.
RBPT_INLINE float pick(int c, float a, float b, float d) { return c == 0 ? a : (c == 1 ? b : d); }

/// The watertight test's bound on the rounding error of t (pbrt-v4's conservative bound, as
/// intersect_triangles() computes it) from the sheared vertices x, y, z, the ray's sz, the
/// edge functions and 1 / det.
RBPT_INLINE float t_error_bound(const float x[3], const float y[3], const float z[3], float sz, float U,
                                float Ve, float We, float inv_det) {
    constexpr float g2 = gamma(2), g3 = gamma(3), g5 = gamma(5);
    float max_zt = std::abs(sz) * max_ps(std::abs(z[0]), max_ps(std::abs(z[1]), std::abs(z[2])));
    float max_xt = max_ps(std::abs(x[0]), max_ps(std::abs(x[1]), std::abs(x[2])));
    float max_yt = max_ps(std::abs(y[0]), max_ps(std::abs(y[1]), std::abs(y[2])));
    float delta_z = g3 * max_zt;
    float delta_x = g5 * (max_xt + max_zt);
    float delta_y = g5 * (max_yt + max_zt);
    float delta_e = 2.f * (g2 * (max_xt * max_yt) + (delta_y * max_xt + delta_x * max_yt));
    float max_e = max_ps(std::abs(U), max_ps(std::abs(Ve), std::abs(We)));
    return (3.f * (g3 * (max_e * max_zt) + (delta_e * max_zt + delta_z * max_e))) * std::abs(inv_det);
}

}  // namespace

/// intersect_columns()'s rays: their intervals, the watertight test's constants (kx, ky, kz
/// and the permuted origin and shear), and their nearest hits so far.
struct BVH::FlatRays {
    const float *tmin, *tmax;
    const int *kx, *ky, *kz;
    const float *ox, *oy, *oz, *sx, *sy, *sz;
    float *retrace, *best_t, *best_u, *best_v;
    uint32_t *best;  ///< the nearest hit's primitive (or triangle: see flat_triangles())
    float *best_inv_det;  ///< the nearest hit's 1 / det (deferred tests only)
    const float *rox, *roy, *roz, *inv_x, *inv_y, *inv_z;  ///< the origin as given, 1 / d
    /// A single triangle whose box is smaller is tested chunk by chunk (see flat_triangles()).
    float cull_area;
    const float *rdx, *rdy, *rdz;  ///< the direction as given (quad_test())
};

/// G triangles against rays [0, n), whole chunks of FlatChunk rays (flat_columns() fills up
/// the last): intersect_triangles()'s operations, lane by lane, each triangle in turn; a ray
/// whose nearest hit ties another, or that meets an edge function exactly zero (which
/// intersect_triangles() redoes in double), is marked for intersect().
/// With Deferred, the last test, the bound on t's rounding error, is left to
/// flat_rounding_check() (for each ray's nearest hit alone), which pays where there are many
/// triangles, and the nearest hit's triangle is kept as its index in flat_triangles_
/// (`first` is tris' own); otherwise as its primitive.
template <int G, bool Deferred>
void BVH::flat_triangles(const FlatTriangle *tris, uint32_t first, const FlatQuad *const quads[2], const FlatRays &q,
                         int n) {
    // (The columns as locals: loads through the struct's pointers do not vectorise.)
    const float *q_tmin = q.tmin, *q_tmax = q.tmax, *q_ox = q.ox, *q_oy = q.oy, *q_oz = q.oz;
    const float *q_sx = q.sx, *q_sy = q.sy, *q_sz = q.sz;
    const int *q_kx = q.kx, *q_ky = q.ky, *q_kz = q.kz;
    float *q_retrace = q.retrace, *q_best_t = q.best_t, *q_best_u = q.best_u, *q_best_v = q.best_v;
    float *q_best_inv_det = q.best_inv_det;
    uint32_t *q_best = q.best;
    float vert[G][3][3];
    uint32_t ids[G];
    for (int i = 0; i < G; ++i) {
        ids[i] = Deferred ? first + uint32_t(i) : tris[i].prim;
        for (int j = 0; j < 3; ++j)
            for (int a = 0; a < 3; ++a) vert[i][j][a] = tris[i].v[j][a];
    }
    // The boxes of the pass's halves (G 4: triangles 0-1 and 2-3, a rectangle each where
    // build() paired them; G 1: the triangle's), widened by far more than the rounding of
    // their tests and of the triangles' (a chunk skips a half only where none of its rays
    // could hit it, tie or need intersect() there).
    static_assert(G == 4 || G == 1, "flat_triangles() takes passes of four triangles or of one");
    constexpr int H = G == 4 ? 2 : 1;
    float box_lo[H][3], box_hi[H][3];
    for (int h = 0; h < H; ++h) {
        for (int a = 0; a < 3; ++a) {
            box_lo[h][a] = box_hi[h][a] = vert[h * G / H][0][a];
            for (int i = h * G / H; i < (h + 1) * G / H; ++i)
                for (int j = 0; j < 3; ++j) box_lo[h][a] = std::min(box_lo[h][a], vert[i][j][a]), box_hi[h][a] = std::max(box_hi[h][a], vert[i][j][a]);
            const float margin = skip_margin(box_lo[h][a], box_hi[h][a]);
            box_lo[h][a] -= margin, box_hi[h][a] += margin;
        }
    }
    const float *q_rox = q.rox, *q_roy = q.roy, *q_roz = q.roz, *q_ix = q.inv_x, *q_iy = q.inv_y, *q_iz = q.inv_z;
    const float *q_rdx = q.rdx, *q_rdy = q.rdy, *q_rdz = q.rdz;
    // Whether triangles i and i + 1 make a quad (a pass of four's halves).
    auto quad_at = [&](int i) __attribute__((always_inline)) {
        if constexpr (G == 4) return i % 2 == 0 && quads[i / 2] != nullptr;
        return false;
    };
    // Ray k against triangles [from, to) of the pass (a pair that makes a quad as one).
    [[maybe_unused]] auto test_range = [&](int k, auto from, auto to) __attribute__((always_inline)) {
        constexpr int I0 = decltype(from)::value, I1 = decltype(to)::value;
        const int kx = q_kx[k], ky = q_ky[k], kz = q_kz[k];
        const float ox = q_ox[k], oy = q_oy[k], oz = q_oz[k], sx = q_sx[k], sy = q_sy[k], sz = q_sz[k];
        const float tmin = q_tmin[k], tmax = q_tmax[k];
        float retrace = q_retrace[k], best_t = q_best_t[k], best_u = q_best_u[k], best_v = q_best_v[k];
        float best_inv_det = Deferred ? q_best_inv_det[k] : 0.f;
        uint32_t best = q_best[k];
        // A hit (`hit` 1) at t: the nearest so far where nearer (a tie leaves the order to
        // intersect()'s traversal), with its barycentrics, its triangle and 1 / det.
        auto keep = [&](float hit, float t, float u, float v, uint32_t id, float inv_det) __attribute__((always_inline)) {
            float tie = t == best_t ? hit : 0.f;
            retrace = tie != 0.f ? 1.f : retrace;
            float better = t < best_t ? hit : 0.f;
            best_t = better != 0.f ? t : best_t;
            best_u = better != 0.f ? u : best_u;
            best_v = better != 0.f ? v : best_v;
            best = better != 0.f ? id : best;
            if constexpr (Deferred) best_inv_det = better != 0.f ? inv_det : best_inv_det;
        };
        QuadRay<ScalarLanes> qr{};
        if (quad_at(0) || quad_at(2)) qr = QuadRay<ScalarLanes>(q_rox[k], q_roy[k], q_roz[k], q_rdx[k], q_rdy[k], q_rdz[k], tmin);
#pragma GCC unroll 4
        for (int i = I0; i < I1; ++i) {
            if (quad_at(i)) {
                // A pair that makes a quad: quad_test(), its hit kept as a triangle's (a 1 / det
                // of 0: its rounding bound is applied).
                const QuadHit<ScalarLanes> qh = quad_test(OneQuad<ScalarLanes>{*quads[i / 2], {}}, qr);
                keep(qh.hit && qh.t < tmax ? 1.f : 0.f, qh.t, qh.u, qh.v, qh.second ? ids[i + 1] : ids[i], 0.f);
                ++i;
                continue;
            }
            const float(*v)[3] = vert[i];
            float x[3], y[3], z[3];
            for (int j = 0; j < 3; ++j) {
                z[j] = pick(kz, v[j][0], v[j][1], v[j][2]) - oz;
                x[j] = (pick(kx, v[j][0], v[j][1], v[j][2]) - ox) - sx * z[j];
                y[j] = (pick(ky, v[j][0], v[j][1], v[j][2]) - oy) - sy * z[j];
            }
            float U = x[2] * y[1] - y[2] * x[1];
            float Ve = x[0] * y[2] - y[0] * x[2];
            float We = x[1] * y[0] - y[1] * x[0];
            float edge = (U == 0.f) | (Ve == 0.f) | (We == 0.f) ? 1.f : 0.f;
            // Inside when the edge functions do not differ in sign (where one is NaN, so is
            // det and the hit test below fails).
            float lo = std::min(std::min(U, Ve), We), hi = std::max(std::max(U, Ve), We);
            float inside = (lo >= 0.f) | (hi <= 0.f) ? 1.f : 0.f;
            float det = (U + Ve) + We;
            inside = det != 0.f ? inside : 0.f;
            float T = (U * (sz * z[0]) + Ve * (sz * z[1])) + We * (sz * z[2]);
            float inv_det = 1.f / det;
            float t = T * inv_det;
            float hit = t > tmin ? inside : 0.f;
            hit = t < tmax ? hit : 0.f;
            if constexpr (!Deferred) hit = t > t_error_bound(x, y, z, sz, U, Ve, We, inv_det) ? hit : 0.f;
            retrace = edge != 0.f ? 1.f : retrace;
            keep(hit, t, Ve * inv_det, We * inv_det, ids[i], inv_det);
        }
        q_retrace[k] = retrace, q_best_t[k] = best_t, q_best_u[k] = best_u, q_best_v[k] = best_v;
        q_best[k] = best;
        if constexpr (Deferred) q_best_inv_det[k] = best_inv_det;
    };
    using First = std::integral_constant<int, 0>;
    using Half = std::integral_constant<int, G / 2>;
    using End = std::integral_constant<int, G>;
    // Chunks of FlatChunk rays (mostly a pixel's samples), each testing the halves whose box
    // one of its rays enters before its nearest hit so far: a rectangle's pair of triangles
    // for the rays that meet it (a room's rays hit one wall). Counted (session 33), the
    // pairs leave the cbox 64% of its triangle tests, cornell-box 56%, veach-mis 34% and
    // glossy 63%, where boxes of four had left 100%, 89%, 66% and 100%. A single triangle's
    // box only where it is small beside the scene's (session 32: walls' boxes of four tested
    // chunk by chunk cost 1-2%).
    const Bounds first_box{{box_lo[0][0], box_lo[0][1], box_lo[0][2]}, {box_hi[0][0], box_hi[0][1], box_hi[0][2]}};
    const bool chunked = H == 2 || first_box.area() < q.cull_area;
    const int chunks = chunked ? n / FlatChunk * FlatChunk : 0;
    // Whether one of the chunk's rays enters half h's box before its nearest hit so far
    // (NodeTest's operations, enters_box()) in lanes, whose OR the vectoriser takes across
    // them in a dozen shuffles; with AVX2 and AVX-512 the chunk is whole registers (FlatLanes)
    // and that OR a test of the compares' masks (with AVX-512, cornell-box 2% faster).
    auto chunk_enters = [&](int h, int k0) __attribute__((always_inline)) {
#if defined(__AVX2__)
        using L = FlatLanes;
        bool any = false;
        for (int k = k0; k < k0 + FlatChunk; k += L::Width) {
            const typename L::F t0 = L::load(q_tmin + k), t1 = L::min(L::load(q_best_t + k), L::load(q_tmax + k));
            const typename L::F o[3] = {L::load(q_rox + k), L::load(q_roy + k), L::load(q_roz + k)};
            const typename L::F inv_d[3] = {L::load(q_ix + k), L::load(q_iy + k), L::load(q_iz + k)};
            any = any || L::any(L::enters(o, inv_d, box_lo[h], box_hi[h], t0, t1, L::set1(1.0001f)));
        }
        return any ? 1 : 0;
#else
        // Whether ray k enters half h's box before its nearest hit so far (NodeTest's operations).
        auto enters = [&](int k) __attribute__((always_inline)) {
            const Vec3 o{q_rox[k], q_roy[k], q_roz[k]}, inv_d{q_ix[k], q_iy[k], q_iz[k]};
            return enters_box(box_lo[h], box_hi[h], o, inv_d, q_tmin[k], q_best_t[k] < q_tmax[k] ? q_best_t[k] : q_tmax[k], 1.0001f);
        };
        int any = 0;
#pragma GCC ivdep  // without AVX2
        for (int l = 0; l < FlatChunk; ++l) any |= enters(k0 + l);
        return any;
#endif
    };
#if defined(__AVX2__)
    // With AVX2 and AVX-512, a chunk's test_range() written out in registers of rays: the same
    // operations in the same order (so the same results), but each vertex coordinate picked
    // by the ray's axis permutation with one permute from the vertex's three coordinates,
    // where the vectoriser's picks take three or four instructions. (One thread, 256 px,
    // 16 spp, Intel Xeon, images bitwise. AVX-512, with the chunks' box tests above:
    // cornell-box 0.366 -> 0.348 s, the cbox 0.298 -> 0.288, textured 0.291 -> 0.284, glossy
    // 0.357 -> 0.350. AVX2, against the vectoriser's loops: cornell-box 0.61 -> 0.54 s, the
    // cbox 0.49 -> 0.46, glossy 0.56 -> 0.53, textured 0.47 -> 0.44, veach-mis 0.177 -> 0.171.)
    using L = FlatLanes;
    using F = typename L::F;
    using M = typename L::M;
    F tri[G][3];
    for (int i = 0; i < G; ++i)
        for (int j = 0; j < 3; ++j) tri[i][j] = L::vertex(vert[i][j]);
    auto test_lanes = [&](int k0, auto from, auto to) __attribute__((always_inline)) {
        constexpr int I0 = decltype(from)::value, I1 = decltype(to)::value;
        const typename L::I kx = L::load(q_kx + k0), ky = L::load(q_ky + k0), kz = L::load(q_kz + k0);
        const F ox = L::load(q_ox + k0), oy = L::load(q_oy + k0), oz = L::load(q_oz + k0);
        const F sx = L::load(q_sx + k0), sy = L::load(q_sy + k0), sz = L::load(q_sz + k0);
        const F tmin = L::load(q_tmin + k0), tmax = L::load(q_tmax + k0);
        const F zero = L::set1(0.f), one = L::set1(1.f);
        F retrace = L::load(q_retrace + k0), best_t = L::load(q_best_t + k0);
        F best_u = L::load(q_best_u + k0), best_v = L::load(q_best_v + k0);
        F best_inv_det = Deferred ? L::load(q_best_inv_det + k0) : zero;
        typename L::I best = L::load(q_best + k0);
        QuadRay<L> qr{};
        if (G == 4 && (quads[0] || quads[1]))
            qr = QuadRay<L>(L::load(q_rox + k0), L::load(q_roy + k0), L::load(q_roz + k0), L::load(q_rdx + k0),
                            L::load(q_rdy + k0), L::load(q_rdz + k0), tmin);
        // A hit of the lanes `hit` at t: the nearest so far where nearer (a tie leaves the
        // order to intersect()'s traversal), with its barycentrics, its triangle and 1 / det.
        auto keep = [&](M hit, F t, F u, F v, typename L::I id, F inv_det) __attribute__((always_inline)) {
            retrace = L::select(L::both(hit, L::eq(t, best_t)), retrace, one);
            const M better = L::both(hit, L::lt(t, best_t));
            best_t = L::select(better, best_t, t);
            best_u = L::select(better, best_u, u);
            best_v = L::select(better, best_v, v);
            best = L::select(better, best, id);
            if constexpr (Deferred) best_inv_det = L::select(better, best_inv_det, inv_det);
        };
        // Triangle i: intersect_triangles()'s operations.
        auto test_triangle = [&](auto index) __attribute__((always_inline)) {
            constexpr int i = decltype(index)::value;
            F x[3], y[3], z[3];
            for (int j = 0; j < 3; ++j) {
                z[j] = L::sub(L::pick(kz, tri[i][j]), oz);
                x[j] = L::sub(L::sub(L::pick(kx, tri[i][j]), ox), L::mul(sx, z[j]));
                y[j] = L::sub(L::sub(L::pick(ky, tri[i][j]), oy), L::mul(sy, z[j]));
            }
            const F U = L::sub(L::mul(x[2], y[1]), L::mul(y[2], x[1]));
            const F Ve = L::sub(L::mul(x[0], y[2]), L::mul(y[0], x[2]));
            const F We = L::sub(L::mul(x[1], y[0]), L::mul(y[1], x[0]));
            const M edge = L::either(L::either(L::eq(U, zero), L::eq(Ve, zero)), L::eq(We, zero));
            // (std::min(a, b) is b < a ? b : a, L::min(b, a); std::max likewise.)
            const F lo = L::min(We, L::min(Ve, U)), hi = L::max(We, L::max(Ve, U));
            const F det = L::add(L::add(U, Ve), We);
            M hit = L::both(L::either(L::ge(lo, zero), L::le(hi, zero)), L::neq(det, zero));
            const F T = L::add(L::add(L::mul(U, L::mul(sz, z[0])), L::mul(Ve, L::mul(sz, z[1]))), L::mul(We, L::mul(sz, z[2])));
            const F inv_det = L::div(one, det);
            const F t = L::mul(T, inv_det);
            hit = L::both(hit, L::both(L::gt(t, tmin), L::lt(t, tmax)));
            if constexpr (!Deferred) {
                // t_error_bound()'s operations (its max_ps is L::max).
                auto abs_max = [](const F a[3]) { return L::max(L::abs(a[0]), L::max(L::abs(a[1]), L::abs(a[2]))); };
                const F g2 = L::set1(gamma(2)), g3 = L::set1(gamma(3)), g5 = L::set1(gamma(5));
                const F max_zt = L::mul(L::abs(sz), abs_max(z));
                const F max_xt = abs_max(x), max_yt = abs_max(y);
                const F delta_z = L::mul(g3, max_zt);
                const F delta_x = L::mul(g5, L::add(max_xt, max_zt));
                const F delta_y = L::mul(g5, L::add(max_yt, max_zt));
                const F delta_e = L::mul(L::set1(2.f), L::add(L::mul(g2, L::mul(max_xt, max_yt)),
                                                              L::add(L::mul(delta_y, max_xt), L::mul(delta_x, max_yt))));
                const F e[3] = {U, Ve, We};
                const F max_e = abs_max(e);
                const F bound = L::mul(L::mul(L::set1(3.f), L::add(L::mul(g3, L::mul(max_e, max_zt)),
                                                                   L::add(L::mul(delta_e, max_zt), L::mul(delta_z, max_e)))),
                                       L::abs(inv_det));
                hit = L::both(hit, L::gt(t, bound));
            }
            retrace = L::select(edge, retrace, one);
            keep(hit, t, L::mul(Ve, inv_det), L::mul(We, inv_det), L::set1(ids[i]), inv_det);
        };
        // Triangles i and i + 1 as their quad: quad_test(), its hit kept as a triangle's (a
        // 1 / det of 0: its rounding bound is applied).
        auto test_quad = [&](auto index) __attribute__((always_inline)) {
            constexpr int i = decltype(index)::value;
            const QuadHit<L> qh = quad_test(OneQuad<L>{*quads[i / 2], {}}, qr);
            keep(L::both(qh.hit, L::lt(qh.t, tmax)), qh.t, qh.u, qh.v,
                 L::select(qh.second, L::set1(ids[i]), L::set1(ids[i + 1])), zero);
        };
        // Each half of the pass: its quad, or its two triangles.
        auto test_half = [&](auto index) __attribute__((always_inline)) {
            constexpr int i = decltype(index)::value;
            if (quads[i / 2]) {
                test_quad(index);
            } else {
                test_triangle(index);
                test_triangle(std::integral_constant<int, i + 1>{});
            }
        };
        if constexpr (G == 4) {
            if constexpr (I0 == 0) test_half(std::integral_constant<int, 0>{});
            if constexpr (I1 == 4) test_half(std::integral_constant<int, 2>{});
        } else {
            test_triangle(std::integral_constant<int, 0>{});
        }
        L::store(q_retrace + k0, retrace), L::store(q_best_t + k0, best_t);
        L::store(q_best_u + k0, best_u), L::store(q_best_v + k0, best_v);
        L::store(q_best + k0, best);
        if constexpr (Deferred) L::store(q_best_inv_det + k0, best_inv_det);
    };
    // A chunk's registers, triangles [from, to) of the pass.
    auto test_chunk = [&](int k0, auto from, auto to) __attribute__((always_inline)) {
        for (int k = k0; k < k0 + FlatChunk; k += L::Width) test_lanes(k, from, to);
    };
    auto test_all = [&](int k0) __attribute__((always_inline)) { test_chunk(k0, First{}, End{}); };
    auto test_first = [&](int k0) __attribute__((always_inline)) { test_chunk(k0, First{}, Half{}); };
    auto test_second = [&](int k0) __attribute__((always_inline)) { test_chunk(k0, Half{}, End{}); };
    const int full = n;  // (every chunk, culled or not)
#else
    auto test = [&](int k) __attribute__((always_inline)) { test_range(k, First{}, End{}); };
    auto test_all = [&](int k0) __attribute__((always_inline)) {
#pragma GCC ivdep  // without AVX2
        for (int l = 0; l < FlatChunk; ++l) test(k0 + l);
    };
    auto test_first = [&](int k0) __attribute__((always_inline)) {
#pragma GCC ivdep  // without AVX2
        for (int l = 0; l < FlatChunk; ++l) test_range(k0 + l, First{}, Half{});
    };
    auto test_second = [&](int k0) __attribute__((always_inline)) {
#pragma GCC ivdep  // without AVX2
        for (int l = 0; l < FlatChunk; ++l) test_range(k0 + l, Half{}, End{});
    };
    const int full = chunks;  // (the rest below, in one loop GCC vectorises)
#endif
    for (int k0 = 0; k0 < chunks; k0 += FlatChunk) {
        int a = chunk_enters(0, k0), b = 0;
        if constexpr (H == 2) b = chunk_enters(1, k0);
        if (H == 1 ? a : a && b) {
            test_all(k0);
        } else if (H == 2 && a) {
            test_first(k0);
        } else if (H == 2 && b) {
            test_second(k0);
        }
    }
    for (int k0 = chunks; k0 < full; k0 += FlatChunk) test_all(k0);
#if !defined(__AVX2__)
#pragma GCC ivdep  // without AVX2
    for (int k = full; k < n; ++k) test(k);
#endif
}

/// intersect_triangles()'s last test for each ray's nearest triangle hit from
/// flat_triangles(): the hit must lie farther than the rounding error of its t (pbrt-v4's
/// conservative bound). Testing the nearest hit alone finds what testing every hit finds:
/// a hit that passes is the nearest of those that pass; a ray whose nearest hit fails (its
/// origin on that triangle, within rounding) is marked for intersect(). `best` becomes the
/// hit's primitive.
///
/// Most hits lie far beyond the bound, which a cheaper bound above it shows without the
/// triangle's vertices: for a hit, whose edge functions share a sign, max |e| / |det| <= 1,
/// so the bound's terms in max |e| are at most 2 g3 max_zt; the sheared vertices' coordinates
/// are at most those of the flat triangles' box corners relative to the origin (x: |v_kx -
/// o_kx| + |sx| |v_kz - o_kz|; z: |sz| |v_kz - o_kz|), and the bound grows with each. That
/// upper bound, with a margin of 1.001 for the rounding of both (a few ulps), takes each
/// hit it exceeds; the others are tested exactly, listed.
void BVH::flat_rounding_check(const FlatRays &q, int n) const {
    const float *q_ox = q.ox, *q_oy = q.oy, *q_oz = q.oz, *q_sx = q.sx, *q_sy = q.sy, *q_sz = q.sz;
    const float *q_rox = q.rox, *q_roy = q.roy, *q_roz = q.roz, *q_inv_det = q.best_inv_det;
    const int *q_kx = q.kx, *q_ky = q.ky, *q_kz = q.kz;
    float *q_retrace = q.retrace;
    const float *q_best_t = q.best_t;
    uint32_t *q_best = q.best;
    const int stride = int(flat_triangles_.size());
    const float *coords = flat_coords_.data();
    const float lo0 = flat_lo_[0], lo1 = flat_lo_[1], lo2 = flat_lo_[2];
    const float hi0 = flat_hi_[0], hi1 = flat_hi_[1], hi2 = flat_hi_[2];
    constexpr float g2 = gamma(2), g3 = gamma(3), g5 = gamma(5);
    // The hits the upper bound does not take.
    alignas(64) int doubtful[MaxColumns], list[MaxColumns];
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const int kx = q_kx[k], ky = q_ky[k], kz = q_kz[k];
        const float d0 = std::max(std::abs(lo0 - q_rox[k]), std::abs(hi0 - q_rox[k]));
        const float d1 = std::max(std::abs(lo1 - q_roy[k]), std::abs(hi1 - q_roy[k]));
        const float d2 = std::max(std::abs(lo2 - q_roz[k]), std::abs(hi2 - q_roz[k]));
        const float dz = pick(kz, d0, d1, d2);
        const float max_zt = std::abs(q_sz[k]) * dz;
        const float max_xt = pick(kx, d0, d1, d2) + std::abs(q_sx[k]) * dz;
        const float max_yt = pick(ky, d0, d1, d2) + std::abs(q_sy[k]) * dz;
        const float delta_x = g5 * (max_xt + max_zt), delta_y = g5 * (max_yt + max_zt);
        const float delta_e = 2.f * (g2 * (max_xt * max_yt) + (delta_y * max_xt + delta_x * max_yt));
        const float bound = 1.001f * (3.f * (2.f * g3 * max_zt + (delta_e * max_zt) * std::abs(q_inv_det[k])));
        // (A quad's hit, whose bound its test applied, has a 1 / det of 0.)
        const float found = q_best[k] != ~0u ? 1.f : 0.f;
        const float tested = q_inv_det[k] != 0.f ? 1.f : 0.f;
        doubtful[k] = q_best_t[k] > bound ? 0 : (found * tested != 0.f ? 1 : 0);
    }
    const int m = simd::select_indices(doubtful, n, 1, list);
    const int padded = simd::pad_indices(list, m);
    alignas(64) float fails[MaxColumns];
#pragma GCC ivdep
    for (int j = 0; j < padded; ++j) {
        const int k = list[j];
        const int kx = q_kx[k], ky = q_ky[k], kz = q_kz[k];
        const float ox = q_ox[k], oy = q_oy[k], oz = q_oz[k], sx = q_sx[k], sy = q_sy[k], sz = q_sz[k];
        const int i = int(q_best[k]);  // (a hit's: signed indices gather)
        float x[3], y[3], z[3];
#pragma GCC unroll 3
        for (int v = 0; v < 3; ++v) {
            const float *c = coords + 3 * v * stride;
            float v0 = c[i], v1 = c[stride + i], v2 = c[2 * stride + i];
            z[v] = pick(kz, v0, v1, v2) - oz;
            x[v] = (pick(kx, v0, v1, v2) - ox) - sx * z[v];
            y[v] = (pick(ky, v0, v1, v2) - oy) - sy * z[v];
        }
        float U = x[2] * y[1] - y[2] * x[1];
        float Ve = x[0] * y[2] - y[0] * x[2];
        float We = x[1] * y[0] - y[1] * x[0];
        float det = (U + Ve) + We;
        float inv_det = 1.f / det;
        fails[j] = q_best_t[k] > t_error_bound(x, y, z, sz, U, Ve, We, inv_det) ? 0.f : 1.f;
    }
    for (int j = 0; j < m; ++j) {
        if (fails[j] != 0.f) q_retrace[list[j]] = 1.f;
    }
    // The triangles' primitives (an index clamped to the last, gathered unconditionally).
    const uint32_t *prims = flat_prims_.data(), last = uint32_t(stride - 1);
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) {
        const uint32_t prim = prims[std::min(q_best[k], last)];
        q_best[k] = q_best[k] != ~0u ? prim : ~0u;
    }
}

/// intersect_sphere() for rays list[0, m) of `r`, lane by lane (SphereQuadratic, then its
/// tests as selects): hit[j] 1 or 0, and t[j].
void BVH::flat_sphere(const Vec3 &center, float radius, const RayColumns &r, const int *list, int m,
                      float *t_out, float *hit_out) {
    const float *q_ox = r.ox, *q_oy = r.oy, *q_oz = r.oz, *q_dx = r.dx, *q_dy = r.dy, *q_dz = r.dz;
    const float *q_tmin = r.tmin, *q_tmax = r.tmax;
#pragma GCC ivdep
    for (int j = 0; j < m; ++j) {
        const int k = list[j];
        const SphereQuadratic quadratic({q_ox[k], q_oy[k], q_oz[k]}, {q_dx[k], q_dy[k], q_dz[k]}, center, radius);
        double lo, hi;
        quadratic.roots(&lo, &hi);
        const double tmin = q_tmin[k], tmax = q_tmax[k];
        // (Float flags narrowed by selects: GCC does not vectorise && here.)
        float hit0 = lo > tmin ? 1.f : 0.f;
        hit0 = lo < tmax ? hit0 : 0.f;
        float hit1 = hi > tmin ? 1.f : 0.f;
        hit1 = hi < tmax ? hit1 : 0.f;
        float hit = hit0 != 0.f ? 1.f : hit1;
        hit_out[j] = quadratic.disc < 0.0 ? 0.f : hit;
        t_out[j] = hit0 != 0.f ? float(lo) : float(hi);
    }
}

/// intersect_disk_or_cylinder() for rays list[0, m) of `r` and the disk (Disk) or cylinder
/// `s`, lane by lane (its test, disk_or_cylinder_test, whose conditions are selects of float
/// flags: GCC does not vectorise && of them): hit[j] 1 or 0, and t[j], u[j], v[j].
template <bool Disk>
void BVH::flat_other(const Shape &s, const RayColumns &r, const int *list, int m, float *t_out, float *u_out,
                     float *v_out, float *hit_out) {
    const float *q_ox = r.ox, *q_oy = r.oy, *q_oz = r.oz, *q_dx = r.dx, *q_dy = r.dy, *q_dz = r.dz;
    const float *q_tmin = r.tmin, *q_tmax = r.tmax;
    double M[3][4];  // (a local copy: the loop's stores cannot alias it)
    std::copy(&s.to_object[0][0], &s.to_object[0][0] + 12, &M[0][0]);
    const double radius = s.radius, length = s.length;
#pragma GCC ivdep
    for (int j = 0; j < m; ++j) {
        const int k = list[j];
        const double o[3] = {q_ox[k], q_oy[k], q_oz[k]};
        const float dx = q_dx[k], dy = q_dy[k], dz = q_dz[k];
        double lo[3], ld[3];
        for (int i = 0; i < 3; ++i) {
            lo[i] = M[i][0] * o[0] + M[i][1] * o[1] + M[i][2] * o[2] + M[i][3];
            ld[i] = M[i][0] * dx + M[i][1] * dy + M[i][2] * dz;
        }
        hit_out[j] = disk_or_cylinder_test<Disk>(lo, ld, q_tmin[k], q_tmax[k], radius, length, &t_out[j], &u_out[j],
                                                 &v_out[j]);
    }
}

/// The lanes' part of intersect_columns(): the nearest hits of rays[0, n) among the flat
/// triangles and spheres into `hits`, and retrace[k] 1 where intersect() must decide.
void BVH::flat_columns(const RayColumns &rays_in, int n_in, const HitColumns &hits, float *retrace, bool shadow) const {
    // A last chunk of fewer than FlatChunk rays filled up with rays of an empty interval
    // (which hit nothing and enter no box), so that the triangles test every ray in lanes.
    // (veach-mis's BSDF samples that enter a light's box come a few to a batch, mostly fewer
    // than 16: such a call took 3600 cycles with those rays tested one by one, 1700 now,
    // against 8000 for 256 rays.)
    const int n = (n_in + FlatChunk - 1) / FlatChunk * FlatChunk;
    alignas(64) float pad[8][MaxColumns];
    RayColumns r = rays_in;
    if (n != n_in) {
        const float *in[8] = {r.ox, r.oy, r.oz, r.dx, r.dy, r.dz, r.tmin, r.tmax};
        const float fill[8] = {0.f, 0.f, 0.f, 1.f, 1.f, 1.f, 1.f, 0.f};  // (finite 1 / d)
        for (int c = 0; c < 8; ++c) {
            std::copy(in[c], in[c] + n_in, pad[c]);
            std::fill(pad[c] + n_in, pad[c] + n, fill[c]);
        }
        r = {pad[0], pad[1], pad[2], pad[3], pad[4], pad[5], pad[6], pad[7]};
    }
    // Each ray's constants of the watertight test (RayPrecomp, RayPrecompPack; none without
    // triangles), and whether it must be traced by intersect() (`retrace`: 1 or 0).
    alignas(64) int kx[MaxColumns], ky[MaxColumns], kz[MaxColumns];
    alignas(64) float ox[MaxColumns], oy[MaxColumns], oz[MaxColumns], sx[MaxColumns], sy[MaxColumns],
        sz[MaxColumns], best_t[MaxColumns], best_u[MaxColumns], best_v[MaxColumns];
    alignas(64) uint32_t best_prim[MaxColumns];
    alignas(64) float best_inv_det[MaxColumns];  // (deferred tests only)
    const bool triangles = !flat_triangles_.empty();
    auto set_up = [&](auto with_triangles) {
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            float dx = r.dx[k], dy = r.dy[k], dz = r.dz[k];
            float ax = std::abs(dx), ay = std::abs(dy), az = std::abs(dz);
            int z = (ax > ay) ? (ax > az ? 0 : 2) : (ay > az ? 1 : 2);
            float dkz = pick(z, dx, dy, dz);
            if constexpr (decltype(with_triangles)::value) {
                int x = z == 2 ? 0 : z + 1;
                int y = x == 2 ? 0 : x + 1;
                int swap = dkz < 0.f;
                int x2 = swap ? y : x, y2 = swap ? x : y;
                float dkx = pick(x2, dx, dy, dz), dky = pick(y2, dx, dy, dz);
                kx[k] = x2, ky[k] = y2, kz[k] = z;
                sx[k] = dkx / dkz, sy[k] = dky / dkz, sz[k] = 1.f / dkz;
                ox[k] = pick(x2, r.ox[k], r.oy[k], r.oz[k]);
                oy[k] = pick(y2, r.ox[k], r.oy[k], r.oz[k]);
                oz[k] = pick(z, r.ox[k], r.oy[k], r.oz[k]);
            }
            // (A sum of magnitudes is finite exactly when each is.)
            float sum = ((std::abs(r.ox[k]) + std::abs(r.oy[k])) + std::abs(r.oz[k])) + ((ax + ay) + az);
            float finite = sum < Infinity ? 1.f : 0.f;
            finite = dkz != 0.f ? finite : 0.f;
            retrace[k] = finite != 0.f ? 0.f : 1.f;
            best_t[k] = Infinity, best_u[k] = 0.f, best_v[k] = 0.f, best_prim[k] = ~0u, best_inv_det[k] = 0.f;
        }
    };
    if (triangles) set_up(std::true_type{});
    else set_up(std::false_type{});
    // Each triangle against every ray, G triangles per pass over the rays (their constants
    // and best hits loaded and stored once per pass). (The inverse directions: the
    // triangles' and the disks' and cylinders' box tests.)
    alignas(64) float inv_x[MaxColumns], inv_y[MaxColumns], inv_z[MaxColumns];
    if (triangles || !flat_others_.empty()) {
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) inv_x[k] = 1.f / r.dx[k], inv_y[k] = 1.f / r.dy[k], inv_z[k] = 1.f / r.dz[k];
    }
    FlatRays rays{r.tmin, r.tmax, kx, ky, kz, ox, oy, oz, sx, sy, sz, retrace, best_t, best_u, best_v, best_prim,
                  best_inv_det, r.ox, r.oy, r.oz, inv_x, inv_y, inv_z, 0.5f * flat_area_,
                  r.dx, r.dy, r.dz};
    // (The rounding bound is deferred beyond 16 triangles: cornell-box's 36, 468 -> 440 ms; the
    // cbox's 12 took 2% longer, the gathers of the check costing more than it saves there.)
    // Passes of four triangles, whose pairs that make quads are tested as such, then the last
    // ones one by one.
    const size_t n_tris = flat_triangles_.size(), n_fours = n_tris / 4 * 4;
    auto passes = [&](auto deferred) {
        constexpr bool D = decltype(deferred)::value;
        const FlatQuad *quads[2] = {nullptr, nullptr};
        for (size_t i = 0; i < n_fours; i += 4) {
            for (int h = 0; h < 2; ++h) {
                const int index = flat_half_quad_[i / 2 + size_t(h)];
                quads[h] = index >= 0 ? &flat_quads_[size_t(index)] : nullptr;
            }
            flat_triangles<4, D>(&flat_triangles_[i], uint32_t(i), quads, rays, n);
        }
        quads[0] = quads[1] = nullptr;
        for (size_t i = n_fours; i < n_tris; ++i) flat_triangles<1, D>(&flat_triangles_[i], uint32_t(i), quads, rays, n);
    };
    if (n_tris > 16) {
        passes(std::true_type{});
        flat_rounding_check(rays, n);
    } else {
        passes(std::false_type{});
    }
    // Each sphere against the rays whose line passes near it (a generous float test; the
    // hit itself is intersect_sphere()'s, in double, for those rays in lanes). Its margin
    // grows with the origin's distance |oc| <= |oc|_1 (no square root), and 1 / |d|^2 is
    // taken once per ray: neither a division nor a square root per sphere. In occlusion
    // queries (`shadow`), the rays whose interval ends before a snug sphere around it or
    // starts past it cannot hit it either (a shadow ray aimed at the sphere, which stops
    // short of it: veach-mis's lights); the snug sphere's margin, 1e-4 (r + |oc|_1), is
    // over ten times the float rounding of the test's distances.
    alignas(64) float sphere_t[MaxColumns], sphere_hit[MaxColumns], inv_dd[MaxColumns];
    alignas(64) int near[MaxColumns], near_list[MaxColumns];
    if (!flat_spheres_.empty()) {
#pragma GCC ivdep
        for (int k = 0; k < n_in; ++k) inv_dd[k] = 1.f / (r.dx[k] * r.dx[k] + r.dy[k] * r.dy[k] + r.dz[k] * r.dz[k]);
    }
    for (uint32_t prim : flat_spheres_) {
        const Shape &s = geometry_->analytic_shape(prim);
        const Vec3 c = s.center;
        const float radius = s.radius;
        auto near_rays = [&](auto cull) {
#pragma GCC ivdep
            for (int k = 0; k < n_in; ++k) {
                Vec3 oc{r.ox[k] - c.x, r.oy[k] - c.y, r.oz[k] - c.z};
                Vec3 d{r.dx[k], r.dy[k], r.dz[k]};
                float along = dot(oc, d) * inv_dd[k];
                Vec3 closest = oc - d * along;
                float size = radius + (std::abs(oc.x) + std::abs(oc.y) + std::abs(oc.z));
                float reach = radius + 1e-3f * size, dist2 = squared_norm(closest);
                near[k] = dist2 > reach * reach ? 0 : 1;
                if constexpr (decltype(cull)::value) {
                    // (The line passes closest to the centre at t = -along; half2: the snug
                    // sphere's half chord there, squared, in t.)
                    float snug = radius + 1e-4f * size;
                    float half2 = (snug * snug - dist2) * inv_dd[k];
                    float before = -along - std::min(r.tmax[k], best_t[k]), past = r.tmin[k] + along;
                    float clear = before > 0.f && before * before > half2 ? 1.f : 0.f;
                    clear = past > 0.f && past * past > half2 ? 1.f : clear;
                    near[k] = clear != 0.f ? 0 : near[k];
                }
            }
        };
        if (shadow) near_rays(std::true_type{});
        else near_rays(std::false_type{});
        // The near rays listed, tested in lanes (the list padded to whole vectors), their
        // hits kept in order.
        const int m = simd::select_indices(near, n_in, 1, near_list);
        flat_sphere(s.center, s.radius, r, near_list, simd::pad_indices(near_list, m), sphere_t, sphere_hit);
        for (int j = 0; j < m; ++j) {
            if (sphere_hit[j] == 0.f) continue;
            const int k = near_list[j];
            const float t = sphere_t[j];
            if (t == best_t[k]) retrace[k] = 1.f;
            if (t < best_t[k]) best_t[k] = t, best_u[k] = 0.f, best_v[k] = 0.f, best_prim[k] = prim;
        }
    }
    // Each disk or cylinder against the rays that enter its (widened) box before their
    // nearest hit so far, listed and tested in lanes (flat_other: the traversal's own test,
    // intersect_disk_or_cylinder, in double), their hits kept as the spheres' are.
    for (const FlatOther &other : flat_others_) {
        const Shape &s = geometry_->analytic_shape(other.prim);
#pragma GCC ivdep
        for (int k = 0; k < n_in; ++k) {
            const Vec3 o{r.ox[k], r.oy[k], r.oz[k]}, inv_d{inv_x[k], inv_y[k], inv_z[k]};
            near[k] = enters_box(other.lo, other.hi, o, inv_d, r.tmin[k], std::min(r.tmax[k], best_t[k]), BoxWiden) ? 1 : 0;
        }
        const int m = simd::select_indices(near, n_in, 1, near_list);
        alignas(64) float other_u[MaxColumns], other_v[MaxColumns];
        const int padded = simd::pad_indices(near_list, m);
        if (s.kind == ShapeKind::Disk) flat_other<true>(s, r, near_list, padded, sphere_t, other_u, other_v, sphere_hit);
        else flat_other<false>(s, r, near_list, padded, sphere_t, other_u, other_v, sphere_hit);
        for (int j = 0; j < m; ++j) {
            if (sphere_hit[j] == 0.f) continue;
            const int k = near_list[j];
            const float t = sphere_t[j];
            if (t == best_t[k]) retrace[k] = 1.f;
            if (t < best_t[k]) best_t[k] = t, best_u[k] = other_u[j], best_v[k] = other_v[j], best_prim[k] = other.prim;
        }
    }
    // The hits.
#pragma GCC ivdep
    for (int k = 0; k < n_in; ++k) {
        hits.t[k] = best_t[k], hits.u[k] = best_u[k], hits.v[k] = best_v[k], hits.prim[k] = best_prim[k];
    }
}

void BVH::intersect_columns(const RayColumns &r, int n, const HitColumns &hits) const {
    nearest_columns(r, n, hits, false);
}

void BVH::nearest_columns(const RayColumns &r, int n, const HitColumns &hits, bool shadow) const {
    auto trace = [&](int k) {
        Hit hit;
        intersect(r.ray(k), &hit);
        hits.t[k] = hit.t, hits.u[k] = hit.u, hits.v[k] = hit.v, hits.prim[k] = hit.prim;
    };
    if (!flat() && !two_phase_) {
        for (int k = 0; k < n; ++k) trace(k);
        return;
    }
    alignas(64) float retrace[MaxColumns];
    flat_columns(r, n, hits, retrace, shadow);
    if (two_phase_) {
        // The rest of the tree, beyond the root's leaves, for the rays that enter one of its
        // inner children's boxes before their nearest hit so far.
        // (Listed first: a branch per ray mispredicts.)
        alignas(64) int enters[MaxColumns], go[MaxColumns], list[MaxColumns];
        enters_inner(r, n, hits.t, enters);
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) go[k] = retrace[k] == 0.f && enters[k] != 0 ? 1 : 0;
        const int m = simd::select_indices(go, n, 1, list);
        for (int j = 0; j < m; ++j) {
            const int k = list[j];
            Ray ray = r.ray(k);
            ray.tmax = std::min(ray.tmax, hits.t[k]);
            Hit h;
            if (traverse<false, true>(ray, &h, first_node(enters[k]))) hits.t[k] = h.t, hits.u[k] = h.u, hits.v[k] = h.v, hits.prim[k] = h.prim;
        }
    }
    // The rays to retrace, traced.
    alignas(64) int again[MaxColumns], list[MaxColumns];
#pragma GCC ivdep
    for (int k = 0; k < n; ++k) again[k] = retrace[k] != 0.f ? 1 : 0;
    const int m = simd::select_indices(again, n, 1, list);
    for (int j = 0; j < m; ++j) trace(list[j]);
}

void BVH::occluded_columns(const RayColumns &r, int n, int *blocked) const {
    if (two_phase_) {
        // Blocked by the root's leaves (in lanes), else by the rest of the tree for the rays
        // that enter one of its inner children's boxes.
        alignas(64) float t[MaxColumns], u[MaxColumns], v[MaxColumns], retrace[MaxColumns];
        alignas(64) uint32_t prim[MaxColumns];
        alignas(64) int enters[MaxColumns];
        flat_columns(r, n, {t, u, v, prim}, retrace, true);
        enters_inner(r, n, r.tmax, enters);
        // Blocked by a root leaf in lanes; the rays to retrace, or that enter an inner child
        // unblocked, listed and traced.
        alignas(64) int rest[MaxColumns], list[MaxColumns];
#pragma GCC ivdep
        for (int k = 0; k < n; ++k) {
            const int hit = prim[k] != ~0u ? 1 : 0;
            blocked[k] = retrace[k] != 0.f ? 0 : hit;
            rest[k] = retrace[k] != 0.f || (hit == 0 && enters[k] != 0) ? 1 : 0;
        }
        const int m = simd::select_indices(rest, n, 1, list);
        for (int j = 0; j < m; ++j) {
            const int k = list[j];
            Hit unused;
            blocked[k] = retrace[k] != 0.f ? occluded(r.ray(k)) : traverse<true, true>(r.ray(k), &unused, first_node(enters[k]));
        }
        return;
    }
    if (flat()) {
        alignas(64) float t[MaxColumns], u[MaxColumns], v[MaxColumns];
        alignas(64) uint32_t prim[MaxColumns];
        nearest_columns(r, n, {t, u, v, prim}, true);
        for (int k = 0; k < n; ++k) blocked[k] = prim[k] != ~0u;
        return;
    }
    for (int k = 0; k < n; ++k) blocked[k] = occluded(r.ray(k));
}

/// occluded() in a tree of one node (a small scene): the children whose boxes the ray enters,
/// in the order of their slots, their packs' primitives tested until one blocks it. What
/// traverse<true> decides there (it tests the same children, the first and then the others
/// from its stack: any hit ends either), without its stack and prefetches, which cost more
/// than the tests in a room of a few dozen triangles (cornell-box 5% faster).
bool BVH::occluded_one_node(const Ray &ray) const {
    alignas(32) float t_entry[BVHWidth];
    return occluded_children(ray, root_children(ray, t_entry));
}

bool BVH::occluded_children(const Ray &ray, int mask) const {
    if (!mask || !finite_origin(ray)) return false;
    const BVHNode &node = nodes_[0];
    const RayPrecompPack pc(ray);
    float tmax = ray.tmax;
    Hit unused;
    for (; mask; mask &= mask - 1) {
        const uint32_t ref = node.child[__builtin_ctz(mask)];
        const uint32_t first = (ref & ~LeafBit) >> 3, last = first + (ref & 7) + 1;
        for (uint32_t p = first; p < last; ++p) {
            if (intersect_pack<true>(packs_[p], ray, pc, tmax, &unused)) return true;
        }
    }
    return false;
}

bool BVH::occluded(const Ray &ray) const {
    if (two_phase_) return occluded_two_phase(ray);
    if (nodes_.size() == 1) return occluded_one_node(ray);
    return occluded_traversal(ray);
}

}  // namespace rbpt
