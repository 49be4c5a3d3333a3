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

void Filter::prepare() {
    cdf.clear();
    if (type != FilterType::Gaussian) return;
    cdf.resize(Resolution + 1);
    cdf[0] = 0.f;
    double sum = 0.0;
    for (int i = 0; i < Resolution; ++i) {
        float x = -radius + (i + 0.5f) * (2.f * radius / Resolution);
        sum += eval(x);
        cdf[i + 1] = float(sum);
    }
    for (float &c : cdf) c = float(c / sum);
}

float Filter::sample(float u) const {
    switch (type) {
        case FilterType::Box: return (u - 0.5f) * 2.f * radius;
        case FilterType::Tent:
            // Invert the CDF of the triangle on [-r, r].
            if (u < 0.5f) return radius * (std::sqrt(2.f * u) - 1.f);
            return radius * (1.f - std::sqrt(2.f * (1.f - u)));
        case FilterType::Gaussian: {
            // Piecewise-constant inversion of the tabulated CDF.
            auto it = std::upper_bound(cdf.begin(), cdf.end(), u);
            int i = std::clamp(int(it - cdf.begin()) - 1, 0, Resolution - 1);
            float width = cdf[i + 1] - cdf[i];
            float t = width > 0.f ? (u - cdf[i]) / width : 0.5f;
            return -radius + (i + t) * (2.f * radius / Resolution);
        }
    }
    return 0.f;
}

}  // namespace rbpt
