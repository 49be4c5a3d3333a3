#include "microfacet.h"

#include <algorithm>
#include <limits>

#include "warp.h"

namespace rbpt {

// GGX: Heitz 2018, the projected hemisphere of the stretched configuration. Beckmann:
// BeckmannSlopes (microfacet.h).

VisibleNormalSampler::VisibleNormalSampler(MicrofacetType type, float alpha, const Vec3 &wi)
    : type_(type), alpha_(alpha), w_(normalize(Vec3{alpha * wi.x, alpha * wi.y, wi.z})) {
    if (type == MicrofacetType::GGX) {
        float len2 = w_.x * w_.x + w_.y * w_.y;
        t1_ = len2 > 0.f ? Vec3{-w_.y, w_.x, 0.f} / std::sqrt(len2) : Vec3{1.f, 0.f, 0.f};
        t2_ = cross(w_, t1_);
        s_ = 0.5f * (1.f + w_.z);
        return;
    }
    beckmann_ = BeckmannSlopes(w_);
}

Vec2 VisibleNormalSampler::part_x(float u1) const {
    if (type_ == MicrofacetType::GGX) return {std::sqrt(u1), 0.f};
    if (beckmann_.polar != 0.f) return {beckmann_.polar_radius(u1), 0.f};
    BeckmannSlopes::Search search = beckmann_.start(u1);
    for (int it = 0; it < BeckmannSlopes::MaxSteps && search.converged == 0.f; ++it) beckmann_.step(search);
    return {BeckmannSlopes::slope(search), 0.f};
}

Vec2 VisibleNormalSampler::part_y(float u2) const {
    if (type_ == MicrofacetType::GGX) return warp::cossin_2pi(u2);
    return beckmann_.part_y(u2);
}

Vec3 sample_visible_normal(MicrofacetType type, float alpha, const Vec3 &wi, Vec2 u) {
    return VisibleNormalSampler(type, alpha, wi).sample(u);
}

}  // namespace rbpt
