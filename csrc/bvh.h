// Bounding volume hierarchy over all primitives (triangles and analytic
// shapes: spheres, disks, cylinders), built once at
// load with the binned surface area heuristic, collapsed into an 8-wide tree when the build targets
// AVX (one slab test of eight child boxes), a 4-wide one with SSE otherwise, with leaves of
// triangle packs as wide (one test of eight or four triangles). The layout is described in
// bvh.cpp.
#pragma once

#include <cstdint>
#include <vector>

#include "shapes.h"
#include "simd.h"

namespace rbpt {

/// Children per node, and primitives per leaf pack: eight fill an AVX register, four an SSE one.
constexpr int BVHWidth = simd::Width;

/// A node: the boxes of its BVHWidth children side by side (lo[axis][child]) and a reference
/// per child (an inner node, a leaf or nothing; see bvh.cpp).
struct alignas(64) BVHNode {
    float lo[3][BVHWidth];
    float hi[3][BVHWidth];
    uint32_t child[BVHWidth];
};
static_assert(sizeof(BVHNode) == 32 * BVHWidth, "a node should fill whole cache lines");

/// Up to BVHWidth primitives of a leaf: triangle vertices for the packed test, the primitive
/// ids, and which lanes hold triangles and analytic shapes (spheres, disks, cylinders).
struct PrimPack {
    TrianglePack tris;
    uint32_t prim[BVHWidth];
    uint8_t triangles;  ///< bit mask of the lanes holding triangles
    uint8_t spheres;    ///< bit mask of the lanes holding spheres
    uint8_t others;     ///< bit mask of the lanes holding other analytic shapes (disks, cylinders)
    uint8_t in_quads;   ///< bit mask of the triangle lanes a FlatQuad tests instead
    uint8_t quads;      ///< bit mask of the lanes whose FlatQuad this pack tests (QuadPack)
};
static_assert(BVHWidth <= 8, "PrimPack's lane masks are 8 bits wide");

/// Two triangles of a flat tree that make a parallelogram (a rectangle's halves, a cube's
/// face), tested as one: the ray meets the plane through `a` of unit
/// normal `n` at t, where the point a + s e1 + r e2 has coordinates s = (x - a) . q1 and
/// r = (x - a) . q2 (q1, q2 the dual basis of the edges e1, e2 from `a`). The first triangle
/// holds a, a + e1 and a + e2 (s + r <= 1), the second the rest. See quad_test() in bvh.cpp
/// for the rounding bounds.
struct FlatQuad {
    float a[3], n[3], q1[3], q2[3];
    float pa;   ///< gamma(5) |a|_1 (the rounding of x - a, with the origin's)
    float pt;   ///< pa and the vertices' largest distance from the plane (t's error bound)
    float st;   ///< twice the vertices' largest offset from their corners in (s, r)
    float qn;   ///< twice the larger of |q1|_1 and |q2|_1
    /// Each triangle's barycentric u and v (the weights of its vertices 1 and 2) as
    /// c0 + cs s + cr r: [second triangle][u c0, cs, cr, v c0, cs, cr].
    float c[2][6];
    uint32_t prim[2];  ///< the two triangles' primitives
};

/// The quads a pack tests (PrimPack::quads), lane by lane for one vector test: FlatQuad's
/// fields as columns, lane l the quad a pack's lane l runs.
struct alignas(32) QuadPack {
    float a[3][BVHWidth], n[3][BVHWidth], q1[3][BVHWidth], q2[3][BVHWidth];
    float pa[BVHWidth], pt[BVHWidth], st[BVHWidth], qn[BVHWidth];
    float c[2][6][BVHWidth];
    uint32_t prim[2][BVHWidth];
};

/// Rays as columns (a wavefront's batch): origin, direction and interval of each.
struct RayColumns {
    const float *ox, *oy, *oz, *dx, *dy, *dz, *tmin, *tmax;
    /// Ray k.
    Ray ray(int k) const {
        Ray r;
        r.o = {ox[k], oy[k], oz[k]};
        r.d = {dx[k], dy[k], dz[k]};
        r.tmin = tmin[k], r.tmax = tmax[k];
        return r;
    }
};
/// Closest hits as columns (Hit's fields).
struct HitColumns {
    float *t, *u, *v;
    uint32_t *prim;
};

/// The primitives that can block a segment between two points of the scene (its surfaces,
/// and `points`: point lights' positions) in its interior: all but the triangles whose plane
/// has the whole scene on one side, as a room's walls seen from inside, which such a
/// segment crosses nowhere between its ends. Shadow rays towards an emitter are such
/// segments, so their tree can leave those triangles out (Scene::shadow_bvh).
std::vector<uint32_t> shadow_blockers(const Geometry &geometry, const std::vector<Vec3> &points);

/// The boxes of a few shapes (a scene's emitters), each widened far beyond the rounding of
/// its shape's intersection, and which rays enter one of them: a conservative test, so a ray
/// whose query only matters where it finds one of those shapes can skip the query.
struct ShapeBoxes {
    std::vector<float> lo[3], hi[3];
    /// Add shape `shape` of `geometry`: its vertices' box (a mesh), or its bounds (an analytic
    /// shape).
    void add(const Geometry &geometry, uint32_t shape);
    int size() const { return int(lo[0].size()); }
    /// enters[k] = 1 where ray k of rays[0, n) enters one of the boxes within its interval, else 0
    /// (1 for a ray of non-finite origin or direction, which the query itself must judge).
    void entered(const RayColumns &rays, int n, int *enters) const;
};

class BVH {
public:
    /// Most rays intersect_columns() takes at once.
    static constexpr int MaxColumns = 256;
    /// flat_columns() skips a pair of a pass's triangles for chunks of this many rays that
    /// all miss the pair's box (AVX-512's 16 lanes, or two or four of narrower vectors).
    static constexpr int FlatChunk = 16;
    /// Most triangles, and spheres, of a flat BVH (see flat()). Renders against the
    /// traversal's on the AMD Zen 5 machine: the cbox, 12 triangles, 0.87x the time with 16
    /// lanes and with 8 (session 24); the cornell-box, 36, 0.94x with 16 lanes (session 24)
    /// and, once the rounding bound was deferred and passes skipped by chunks, 0.92x with 8
    /// (an x86-64-v3 build, session 33: 463-471 -> 431-434 ms; it had been 1.11x).
    /// And most disks and cylinders (FlatOthers), each tested for the rays that enter its box.
    /// Spheres up to 32 (since session 53; 8 before): each is tested in lanes for the rays
    /// that pass near it (cbox with 18 more spheres, a tree of 4 nodes traversed one ray at a
    /// time before: two renders of 128 px at 64 spp, one thread, 1.23-1.52 -> 0.76-0.94 s).
    static constexpr int FlatTriangles = 40, FlatSpheres = 32, FlatOthers = 8;
    /// Build over every primitive of `geometry`, which must outlive the BVH.
    void build(const Geometry &geometry);
    /// Build over the primitives `subset` of `geometry` (ids as in Geometry; hits report them).
    void build(const Geometry &geometry, const std::vector<uint32_t> &subset);
    /// Nearest hit of `ray` in (ray.tmin, ray.tmax); returns false on a miss.
    bool intersect(const Ray &ray, Hit *hit) const;
    /// Whether anything blocks `ray` in (ray.tmin, ray.tmax); stops at the first hit.
    bool occluded(const Ray &ray) const;

    /// The closest hits of rays[0, n) (n <= MaxColumns), each as intersect() finds it. In a
    /// flat BVH every triangle is tested against the rays in SIMD lanes (the same operations
    /// as intersect_triangles()'s, one ray per lane), and every sphere against the rays whose
    /// line passes near it; a ray whose hit that does not decide as intersect() would (two
    /// primitives at the same distance, whose order intersect() settles by its traversal; an
    /// edge function exactly zero, which it recomputes in double; a non-finite origin or
    /// direction) is traced by intersect(). In a two_phase() tree the same for the root's
    /// leaves, then the rest of the tree for the rays that may find a nearer hit there.
    /// Otherwise intersect() for each ray.
    /// One difference remains: the lanes test every triangle, the traversal only those of the
    /// leaves whose boxes the ray enters before its nearest hit so far, and where a hit lies
    /// within a rounding of its leaf's box the box's test can round it out. Then the lanes
    /// keep a hit the traversal does not find: another hit a rounding apart (two surfaces in
    /// one plane, in different leaves), or one a rounding before the interval's end (test_bvh
    /// test05: 137 of 20000 rays grazing a coplanar decal, none of its ordinary rays).
    /// Testing the box of each ray's hit (gathers of its leaf's box) made cbox renders 3-5%
    /// slower (session 25), so it is left so; both hits are valid to within a rounding, and
    /// the results are deterministic.
    void intersect_columns(const RayColumns &rays, int n, const HitColumns &hits) const;
    /// Whether each of rays[0, n) (n <= MaxColumns) is blocked, as occluded() decides:
    /// blocked[k] 1 or 0. A flat BVH finds the nearest hits in lanes (intersect_columns;
    /// faster than occluded() where the rays pass near spheres, whose exact test is in
    /// double, as a sphere light's shadow rays do); a two_phase() tree tests its root's leaves
    /// so, then the rest of the tree for the rays not blocked that enter it; otherwise
    /// occluded() for each ray.
    void occluded_columns(const RayColumns &rays, int n, int *blocked) const;
    /// For each ray, the mask of the root's children whose boxes it enters: NodeTest's
    /// operations in SIMD lanes, so the traversal's decision for the rays of finite origin.
    void root_masks(const RayColumns &rays, int n, int *mask) const;
    /// occluded() in a tree of one node (one_node()), for a ray whose root_masks() mask is
    /// `mask`: those children's packs in slot order, until one blocks it. (The wavefront's
    /// shadow rays: their masks in lanes, then one ray at a time through the children they
    /// enter, without the gathers of occluded_columns(); the cbox, cornell-box, glossy and
    /// textured 3-7% faster than through occluded().)
    bool occluded_children(const Ray &ray, int mask) const;
    /// Whether the tree is one node (a small scene).
    bool one_node() const { return nodes_.size() == 1; }
    /// Whether the tree holds at most FlatTriangles triangles, FlatSpheres spheres and
    /// FlatOthers disks and cylinders (a small scene: one node, or a few over spread-out
    /// spheres) and is not searched in two phases: its rays intersect_columns() tests in SIMD
    /// lanes against every primitive; most of a ray's traversal there is per-ray set-up and
    /// branches, for a node or a few and a pack or two. (Parallelograms are tested as quads
    /// only in a tree of one node: see build_quads().)
    bool flat() const {
        return (!flat_triangles_.empty() || !flat_spheres_.empty() || !flat_others_.empty()) && !two_phase_;
    }
    /// Whether a larger tree is searched in two phases: its root's leaves (triangles only, at
    /// most FlatTriangles: a room's walls and lights around a detailed mesh) against the rays
    /// in SIMD lanes as a flat tree's triangles, then, for the rays that enter one of the
    /// root's inner children's boxes (tested in lanes) before their nearest hit so far, the
    /// rest of the tree one ray at a time (traverse() without the root's leaves). intersect()
    /// and occluded() search in the same two phases (the root's leaves without their boxes'
    /// tests), so that the lanes find what they find. In the bunny's box 61% of the closest-hit
    /// rays and 53% of the shadow rays had visited the root node alone: their traversal is gone.
    bool two_phase() const { return two_phase_; }

    /// intersect() and occluded() through the general traversal, whatever the tree (in a tree
    /// of one node those two take a shortcut with the same answers), for tests.
    bool intersect_traversal(const Ray &ray, Hit *hit) const { return traverse<false>(ray, hit); }
    bool occluded_traversal(const Ray &ray) const {
        Hit unused;
        return traverse<true>(ray, &unused);
    }

    /// Number of BVHWidth-wide nodes.
    size_t node_count() const { return nodes_.size(); }
    /// Number of pairs of flat triangles tested as quads (FlatQuad).
    size_t quad_count() const { return flat_quads_.size(); }
    /// SAH cost of the binary tree before collapsing (traversal 1, intersection 1), for tests.
    double sah_cost() const { return sah_cost_; }

private:
    /// The traversal from the root; with InnerOnly, of the root's inner children only (the
    /// second phase of a two_phase() tree).
    template <bool AnyHit, bool InnerOnly = false>
    bool traverse(const Ray &ray, Hit *hit, uint32_t start = 0) const;
    /// Where a two_phase() tree's second phase starts for a ray whose enters_inner() mask is
    /// `mask`: the one inner child it enters (where traverse() from the root goes next), else
    /// the root.
    uint32_t first_node(int mask) const {
        return mask && !(mask & (mask - 1)) ? nodes_[0].child[__builtin_ctz(mask)] : 0u;
    }
    /// intersect() and occluded() of a two_phase() tree.
    bool intersect_two_phase(const Ray &ray, Hit *hit) const;
    bool occluded_two_phase(const Ray &ray) const;
    /// The nearest hits of rays[0, n) among the flat triangles and spheres, in lanes, and
    /// retrace[k] 1 where intersect() must decide (intersect_columns()'s first part);
    /// `retrace` holds n rounded up to whole chunks of FlatChunk (the lanes fill up the last).
    /// With `shadow` (occlusion queries), a sphere is left out for the rays whose interval
    /// ends before it or starts past it (a shadow ray aimed at it).
    void flat_columns(const RayColumns &r, int n, const HitColumns &hits, float *retrace, bool shadow) const;
    /// intersect_columns(), for occluded_columns() with `shadow`.
    void nearest_columns(const RayColumns &r, int n, const HitColumns &hits, bool shadow) const;
    /// enters[k] nonzero where ray k enters one of the root's inner children's boxes before
    /// min(its tmax, limit[k]) (the mask of those children), else 0: child_masks().
    void enters_inner(const RayColumns &r, int n, const float *limit, int *enters) const;
    /// mask[k]: the root's children in `children` whose boxes ray k enters in (its tmin,
    /// min(its tmax, limit[k])), NodeTest's operations in lanes, so the traversal's decision
    /// (for a finite origin; root_masks()).
    void child_masks(const RayColumns &r, int n, const float *limit, uint32_t children, int *mask) const;
    bool two_phase_ = false;
    uint32_t root_inner_mask_ = 0;      ///< the root's inner children (two_phase())
    std::vector<uint32_t> root_packs_;  ///< the packs of the root's leaves (two_phase())
    /// Test a leaf's pack: its triangles, spheres and other shapes in (ray.tmin, tmax). With
    /// AnyHit, whether one is hit; otherwise whether one is hit nearer than tmax, which then
    /// becomes its distance, with `hit` its hit.
    /// (A pack's triangles in quads are tested as their quads: FlatQuad, QuadPack.)
    template <bool AnyHit>
    bool intersect_pack(const PrimPack &pack, const Ray &ray, const RayPrecompPack &pc, float &tmax,
                        Hit *hit) const;
    /// Test the disk and cylinder lanes of a pack (out of the traversal loop's hot path).
    bool intersect_others(const Ray &ray, const PrimPack &pack, float tmax, Hit *hit) const;
    /// The mask of the root's children whose boxes `ray` enters, with their entry distances
    /// (none for a non-finite origin, as in traverse()).
    int root_children(const Ray &ray, float t_entry[BVHWidth]) const;
    /// intersect() for a tree of one node.
    bool intersect_one_node(const Ray &ray, Hit *hit) const;
    /// occluded() for a tree of one node.
    bool occluded_one_node(const Ray &ray) const;

    /// The flat tree's primitives (empty unless flat()): triangle vertices with their ids,
    /// and the ids of the spheres.
    struct FlatTriangle {
        float v[3][3];  ///< [vertex][axis]
        uint32_t prim;
    };
    std::vector<FlatTriangle> flat_triangles_;
    /// The pairs of flat triangles (2h, 2h + 1) of flat_columns()' passes of four that make a
    /// parallelogram, as quads: flat_half_quad_[h] the pair's index in flat_quads_, else -1.
    /// Every query tests them as quads: the lanes by pairs, the packs by their lanes `quads`
    /// (in one vector test: quad_packs_[pack_quad_[pack]]), leaving out their triangles'
    /// lanes `in_quads`; the root's leaf boxes are widened to hold the quads' widening.
    std::vector<FlatQuad> flat_quads_;
    std::vector<int> flat_half_quad_;
    std::vector<QuadPack> quad_packs_;
    std::vector<int> pack_quad_;
    /// Find the flat pairs that make quads, and mark them in the packs (build()).
    void build_quads();
    std::vector<float> flat_coords_;  ///< their vertices, [vertex][axis][triangle]
    std::vector<uint32_t> flat_prims_;  ///< their primitives
    float flat_area_ = 0.f;  ///< the surface area of their bounding box
    float flat_lo_[3] = {}, flat_hi_[3] = {};  ///< that box's corners
    struct FlatRays;
    template <int G, bool Deferred>
    static void flat_triangles(const FlatTriangle *tris, uint32_t first, const FlatQuad *const quads[2],
                               const FlatRays &rays, int n);
    void flat_rounding_check(const FlatRays &rays, int n) const;
    static void flat_sphere(const Vec3 &center, float radius, const RayColumns &r, const int *list, int m,
                            float *t, float *hit);
    template <bool Disk>
    static void flat_other(const Shape &s, const RayColumns &r, const int *list, int m, float *t, float *u, float *v,
                           float *hit);
    std::vector<uint32_t> flat_spheres_;
    /// The flat tree's disks and cylinders, each with its own box (analytic_bounds()).
    struct FlatOther {
        uint32_t prim;
        float lo[3], hi[3];
    };
    std::vector<FlatOther> flat_others_;

    const Geometry *geometry_ = nullptr;
    std::vector<BVHNode> nodes_;
    std::vector<PrimPack> packs_;  ///< leaf contents, each leaf a run of packs
    double sah_cost_ = 0.0;
};

}  // namespace rbpt
