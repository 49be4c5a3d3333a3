#include "camera.h"

namespace rbpt {

float Filter::eval(float x) const {
    switch (type) {
        case FilterType::Box: return std::abs(x) <= radius ? 1.f : 0.f;
        case FilterType::Tent: return std::max(0.f, 1.f - std::abs(x) / radius);
        case FilterType::Gaussian: {
            float alpha = -1.f / (2.f * stddev * stddev);
            return std::max(0.f, std::exp(alpha * x * x) - std::exp(alpha * radius * radius));
        }
    }
    return 0.f;
}

}  // namespace rbpt
