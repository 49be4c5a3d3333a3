#include "camera.h"

#include <cmath>

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
        case FilterType::Mitchell:
            for (int k = 0; k < n; ++k) {
                float x = std::abs(x0 + float(k)), x2 = x * x, x3 = x2 * x;
                float f;
                if (x < 1.f)
                    f = (12.f - 9.f * b - 6.f * c) * x3 + (-18.f + 12.f * b + 6.f * c) * x2 +
                        (6.f - 2.f * b);
                else if (x < 2.f)
                    f = (-b - 6.f * c) * x3 + (6.f * b + 30.f * c) * x2 +
                        (-12.f * b - 48.f * c) * x + (8.f * b + 24.f * c);
                else
                    f = 0.f;
                w[k] = f * (1.f / 6.f);
            }
            return;
        case FilterType::Lanczos:
            for (int k = 0; k < n; ++k) {
                float x = std::abs(x0 + float(k));
                if (x >= radius) {
                    w[k] = 0.f;
                } else if (x < 1e-4f) {
                    w[k] = 1.f;
                } else {
                    float x1 = float(M_PI) * x, x2 = x1 / float(lobes);
                    w[k] = std::sin(x1) * std::sin(x2) / (x1 * x2);
                }
            }
            return;
    }
}

}  // namespace rbpt
