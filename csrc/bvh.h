// Bounding volume hierarchy over all primitives (triangles and spheres), built once at load
// with the binned surface area heuristic and traversed with a small fixed stack.
#pragma once

#include <cstdint>
#include <vector>

#include "shapes.h"

namespace rbpt {

struct BVHNode {
    Vec3 lo;
    uint32_t offset;  ///< leaf: first primitive slot; interior: index of the second child
    Vec3 hi;
    uint16_t count;   ///< primitives in a leaf, 0 for interior nodes
    uint16_t axis;    ///< split axis of an interior node (for front-to-back traversal)
};
static_assert(sizeof(BVHNode) == 32, "BVHNode should stay 32 bytes");

class BVH {
public:
    /// Build over every primitive of `geometry`, which must outlive the BVH.
    void build(const Geometry &geometry);
    /// Nearest hit of `ray` in (ray.tmin, ray.tmax); returns false on a miss.
    bool intersect(const Ray &ray, Hit *hit) const;
    /// Whether anything blocks `ray` in (ray.tmin, ray.tmax).
    bool occluded(const Ray &ray) const;

    size_t node_count() const { return nodes_.size(); }
    /// SAH cost of the tree (traversal 1, intersection 1), for tests and tuning.
    double sah_cost() const;

private:
    template <bool AnyHit>
    bool traverse(const Ray &ray, Hit *hit) const;

    const Geometry *geometry_ = nullptr;
    std::vector<BVHNode> nodes_;
    std::vector<uint32_t> prims_;  ///< primitive id per slot, in leaf order
    std::vector<Vec3> verts_;      ///< three vertices per slot (triangles), for locality
};

}  // namespace rbpt
