#include "camera.h"

#include <algorithm>
#include <cmath>

namespace rbpt {

float Filter::eval(float x) const {
    float w;
    eval_row(x, 1, &w);
    return w;
}

void Filter::prepare() {
    inv_radius_ = 1.f / radius;
    gaussian_.alpha = -1.f / (2.f * stddev * stddev);
    gaussian_.bias = exp_poly(gaussian_.alpha * radius * radius);
}

void Filter::eval_row_other(float x0, int n, float *w) const {
    switch (type) {
        case FilterType::Box:
        case FilterType::Tent:
            return eval_row(x0, n, w);  // (inline in camera.h)
        case FilterType::Gaussian:
            // exp_poly's polynomial in blocks of eight offsets, a loop the compiler vectorises
            // (a row of the default radius 2 is one block; libm's exp is a call per weight).
            for (int k0 = 0; k0 < n; k0 += 8) {
                float block[8];
                for (int k = 0; k < 8; ++k) {
                    float x = x0 + float(k0 + k);
                    block[k] = std::max(0.f, exp_poly(gaussian_.alpha * x * x) - gaussian_.bias);
                }
                for (int k = 0; k < 8 && k0 + k < n; ++k) w[k0 + k] = block[k];
            }
            return;
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

void Filter::eval_rows(const float *x0, int count, int n, float *w, int stride) const {
    if (type == FilterType::Gaussian) {
        const float alpha = gaussian_.alpha, bias = gaussian_.bias;
        for (int o = 0; o < n; ++o) {
            float *row = w + size_t(o) * stride;
#pragma GCC ivdep
            for (int k = 0; k < count; ++k) {
                float x = x0[k] + float(o);
                row[k] = std::max(0.f, exp_poly(alpha * x * x) - bias);
            }
        }
    } else if (type == FilterType::Tent) {
        const float inv_radius = inv_radius_;
        for (int o = 0; o < n; ++o) {
            float *row = w + size_t(o) * stride;
#pragma GCC ivdep
            for (int k = 0; k < count; ++k) row[k] = std::max(0.f, 1.f - std::abs((x0[k] + float(o)) * inv_radius));
        }
    } else {
        float one[2 * MaxBorder + 1];
        for (int k = 0; k < count; ++k) {
            eval_row(x0[k], n, one);
            for (int o = 0; o < n; ++o) w[size_t(o) * stride + k] = one[o];
        }
    }
}

Ray Camera::orthographic_ray(Vec2 pos) const {
    // Film position -> (1, 1) top left ... (-1, -1) bottom right: camera-local +x is left.
    float sx = 1.f - 2.f * (pos.x / float(film_width));
    float sy = 1.f - 2.f * (pos.y / float(film_height));
    float aspect = float(film_width) / float(film_height);
    Ray ray;
    ray.o = origin + frame_x * sx + frame_y * (sy / aspect) + frame_z * near_clip;
    ray.d = normalize(frame_z);
    ray.tmin = 0.f;
    ray.tmax = far_clip - near_clip;
    return ray;
}

Ray Camera::thin_lens_ray(Vec2 pos, Vec2 u) const {
    float sx = 1.f - 2.f * (pos.x / float(film_width));
    float sy = 1.f - 2.f * (pos.y / float(film_height));
    Vec2 a = warp::square_to_uniform_disk_concentric(u);
    Vec3 aperture{aperture_radius * a.x, aperture_radius * a.y, 0.f};
    Vec3 focus{sx * tan_half_x * focus_distance, sy * tan_half_y * focus_distance, focus_distance};
    Vec3 d_local = normalize(focus - aperture);
    Ray ray;
    ray.o = origin + axis_x * aperture.x + axis_y * aperture.y;
    ray.d = normalize(axis_x * d_local.x + axis_y * d_local.y + axis_z * d_local.z);
    float inv_z = 1.f / d_local.z;
    ray.tmin = near_clip * inv_z;  // rays start on the near plane and end on the far one
    ray.tmax = far_clip * inv_z;
    return ray;
}

}  // namespace rbpt
