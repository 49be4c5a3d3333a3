#include "camera.h"

namespace rbpt {

float Filter::eval(float x) const {
    float w;
    eval_row(x, 1, &w);
    return w;
}

void Filter::eval_row(float x0, int n, float *w) const {
    switch (type) {
        case FilterType::Box:
            for (int k = 0; k < n; ++k) w[k] = std::abs(x0 + float(k)) <= radius ? 1.f : 0.f;
            return;
        case FilterType::Tent:
            for (int k = 0; k < n; ++k) w[k] = std::max(0.f, 1.f - std::abs(x0 + float(k)) / radius);
            return;
        case FilterType::Gaussian: {
            float alpha = -1.f / (2.f * stddev * stddev);
            float bias = std::exp(alpha * radius * radius);  // once per row, not per weight
            for (int k = 0; k < n; ++k) {
                float x = x0 + float(k);
                w[k] = std::max(0.f, std::exp(alpha * x * x) - bias);
            }
            return;
        }
    }
}

}  // namespace rbpt
