// Bounding volume hierarchy over all primitives (triangles and analytic shapes), built once at load
// with the binned surface area heuristic, collapsed into a 4-wide tree and traversed with SSE
// (four child boxes and four triangles per test). The layout is described in bvh.cpp.
#pragma once

#include <cstdint>
#include <vector>

#include "shapes.h"

namespace rbpt {

/// A 4-wide node: the boxes of its four children side by side (lo[axis][child]) and a
/// reference per child (an inner node, a leaf or nothing; see bvh.cpp).
struct alignas(64) BVHNode4 {
    float lo[3][4];
    float hi[3][4];
    uint32_t child[4];
};
static_assert(sizeof(BVHNode4) == 128, "BVHNode4 should stay two cache lines");

/// Up to four primitives of a leaf: triangle vertices for the SSE test, the primitive ids,
/// and which lanes hold triangles and analytic shapes (spheres, disks, cylinders).
struct PrimPack4 {
    TrianglePack4 tris;
    uint32_t prim[4];
    uint8_t triangles;  ///< bit mask of the lanes holding triangles
    uint8_t spheres;    ///< bit mask of the lanes holding spheres
    uint8_t others;     ///< bit mask of the lanes holding other analytic shapes (disks, cylinders)
};

class BVH {
public:
    /// Build over every primitive of `geometry`, which must outlive the BVH.
    void build(const Geometry &geometry);
    /// Nearest hit of `ray` in (ray.tmin, ray.tmax); returns false on a miss.
    bool intersect(const Ray &ray, Hit *hit) const;
    /// Whether anything blocks `ray` in (ray.tmin, ray.tmax); stops at the first hit.
    bool occluded(const Ray &ray) const;

    /// Number of 4-wide nodes.
    size_t node_count() const { return nodes_.size(); }
    /// SAH cost of the binary tree before collapsing (traversal 1, intersection 1), for tests.
    double sah_cost() const { return sah_cost_; }

private:
    template <bool AnyHit>
    bool traverse(const Ray &ray, Hit *hit) const;
    /// Test the disk and cylinder lanes of a pack (out of the traversal loop's hot path).
    bool intersect_others(const Ray &ray, const PrimPack4 &pack, float tmax, Hit *hit) const;

    const Geometry *geometry_ = nullptr;
    std::vector<BVHNode4> nodes_;
    std::vector<PrimPack4> packs_;  ///< leaf contents, each leaf a run of packs
    double sah_cost_ = 0.0;
};

}  // namespace rbpt
