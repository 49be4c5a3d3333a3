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
