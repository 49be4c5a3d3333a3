#include "render.h"

#include <atomic>

namespace rbpt {

template <typename S>
void render(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
            const RenderRequest &req, real_t<S> *out, const WorkerPool &pool) {
    using T = real_t<S>;
    int row_end = req.row_end < 0 ? camera.crop_height : req.row_end;
    int64_t width = camera.crop_width;
    int64_t n_pixels = int64_t(row_end - req.row_begin) * width;
    constexpr int64_t TileSize = 16;  // pixels handed out per work item
    int64_t n_tiles = (n_pixels + TileSize - 1) / TileSize;
    std::atomic<int64_t> next_tile{0};
    std::atomic<uint64_t> total_rays{0};
    T inv_spp = T(1) / T(req.spp);

    pool([&] {
        uint64_t rays_before = rays_traced;
        for (int64_t tile = next_tile++; tile < n_tiles; tile = next_tile++) {
            int64_t end = std::min(n_pixels, (tile + 1) * TileSize);
            for (int64_t i = tile * TileSize; i < end; ++i) {
                int px = camera.crop_x + int(i % width);
                int py = camera.crop_y + req.row_begin + int(i / width);
                uint64_t pixel = uint64_t(py) * uint64_t(camera.film_width) + uint64_t(px);
                S sum(T(0));
                for (int s = 0; s < req.spp; ++s) {
                    // Trace one filter-distributed camera path through the pixel.
                    Sampler sampler(req.seed, pixel, uint64_t(s));
                    Vec2 pos = camera.sample_position(px, py, sampler);
                    float tmin;
                    Ray ray = camera.ray_at(pos.x, pos.y, &tmin);
                    ray.tmin = tmin;
                    S L = li(ctx, cfg, ray, sampler);
                    // Drop non-finite samples rather than poisoning the pixel.
                    if (SpectrumTraits<S>::is_finite(L)) sum += L;
                }
                for (int c = 0; c < 3; ++c) out[3 * i + c] = sum[c] * inv_spp;
            }
        }
        total_rays += rays_traced - rays_before;
    });
    if (req.rays) *req.rays = total_rays;
}

template void render<RGB<float>>(const RenderContext<RGB<float>> &, const Camera &,
                                 const IntegratorSettings &, const RenderRequest &, float *,
                                 const WorkerPool &);
template void render<RGB<double>>(const RenderContext<RGB<double>> &, const Camera &,
                                  const IntegratorSettings &, const RenderRequest &, double *,
                                  const WorkerPool &);

}  // namespace rbpt
