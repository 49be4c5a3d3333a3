#include "render.h"

#include <atomic>

namespace rbpt {

namespace {

constexpr int64_t TileSize = 16;  // pixels per work item

/// Pixel i of the requested rows, in film coordinates.
struct PixelIndexer {
    const Camera &camera;
    const RenderRequest &req;
    int64_t width;
    void locate(int64_t i, int *px, int *py, uint64_t *key) const {
        *px = camera.crop_x + int(i % width);
        *py = camera.crop_y + req.row_begin + int(i / width);
        *key = uint64_t(*py) * uint64_t(camera.film_width) + uint64_t(*px);
    }
};

/// Trace one filter-distributed camera path through pixel (px, py): sample s of its stream.
template <typename S>
S trace_sample(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
               uint64_t seed, int px, int py, uint64_t key, int s) {
    Sampler sampler(seed, key, uint64_t(s));
    Vec2 pos = camera.sample_position(px, py, sampler);
    float tmin;
    Ray ray = camera.ray_at(pos.x, pos.y, &tmin);
    ray.tmin = tmin;
    return li(ctx, cfg, ray, sampler);
}

int row_end_of(const Camera &camera, const RenderRequest &req) {
    return req.row_end < 0 ? camera.crop_height : req.row_end;
}

/// Run `pixel(i)` for every pixel of the request, tiles handed out dynamically.
template <typename F>
void for_each_pixel_dynamic(int64_t n_pixels, const WorkerPool &pool, std::atomic<uint64_t> &rays,
                            F pixel) {
    int64_t n_tiles = (n_pixels + TileSize - 1) / TileSize;
    std::atomic<int64_t> next_tile{0};
    pool.run([&] {
        uint64_t rays_before = rays_traced;
        for (int64_t tile = next_tile++; tile < n_tiles; tile = next_tile++) {
            int64_t end = std::min(n_pixels, (tile + 1) * TileSize);
            for (int64_t i = tile * TileSize; i < end; ++i) pixel(i);
        }
        rays += rays_traced - rays_before;
    });
}

/// Average the finite samples (`keep`) of every requested pixel; store(i, mean) writes pixel i.
template <typename S, typename Keep, typename Store>
void average_pixels(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
                    const RenderRequest &req, const WorkerPool &pool, Keep keep, Store store) {
    using T = real_t<S>;
    PixelIndexer at{camera, req, camera.crop_width};
    int64_t n_pixels = int64_t(row_end_of(camera, req) - req.row_begin) * at.width;
    T inv_spp = T(1) / T(req.spp);
    std::atomic<uint64_t> rays{0};
    for_each_pixel_dynamic(n_pixels, pool, rays, [&](int64_t i) {
        int px, py;
        uint64_t key;
        at.locate(i, &px, &py, &key);
        S sum(T(0));
        for (int s = 0; s < req.spp; ++s) {
            S L = trace_sample(ctx, camera, cfg, req.seed, px, py, key, s);
            // Drop non-finite samples rather than poisoning the pixel.
            if (keep(L)) sum += L;
        }
        store(i, sum * inv_spp);
    });
    if (req.rays) *req.rays = rays;
}

}  // namespace

template <typename S>
void render_fwd(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
                const RenderRequest &req, real_t<S> *out, const WorkerPool &pool) {
    average_pixels(
        ctx, camera, cfg, req, pool, [](const S &L) { return SpectrumTraits<S>::is_finite(L); },
        [&](int64_t i, const S &mean) {
            for (int c = 0; c < 3; ++c) out[3 * i + c] = mean[c];
        });
}

template <typename T>
void render_jvp(const RenderContext<Dual<T>> &ctx, const Camera &camera,
                const IntegratorSettings &cfg, const RenderRequest &req, T *out, T *out_tangent,
                const WorkerPool &pool) {
    average_pixels(
        ctx, camera, cfg, req, pool,
        [](const Dual<T> &L) {
            return SpectrumTraits<Dual<T>>::is_finite(L) && SpectrumTraits<RGB<T>>::is_finite(L.d);
        },
        [&](int64_t i, const Dual<T> &mean) {
            for (int c = 0; c < 3; ++c) {
                out[3 * i + c] = mean.v[c];
                out_tangent[3 * i + c] = mean.d[c];
            }
        });
}

template <typename T>
void render_bwd(const Scene &scene, const Params<RGB<T>> &values, const Camera &camera,
                const IntegratorSettings &cfg, const RenderRequest &req, const T *adjoint,
                const std::vector<T *> &grads, const WorkerPool &pool) {
    PixelIndexer at{camera, req, camera.crop_width};
    int64_t n_pixels = int64_t(row_end_of(camera, req) - req.row_begin) * at.width;
    int64_t n_tiles = (n_pixels + TileSize - 1) / TileSize;
    // One gradient buffer per worker, covering the differentiated parameters.
    size_t n_params = values.data.size();
    std::vector<size_t> offset(n_params, 0);
    size_t total = 0;
    for (size_t p = 0; p < n_params; ++p) {
        offset[p] = total;
        if (grads[p]) total += size_t(values.numel[p]);
    }
    int n_workers = std::max(1, pool.workers);
    std::vector<std::vector<T>> buffers(n_workers);
    std::atomic<int> next_worker{0};
    std::atomic<uint64_t> rays{0};
    T inv_spp = T(1) / T(req.spp);

    pool.run([&] {
        int w = next_worker++;
        if (w >= n_workers) return;
        uint64_t rays_before = rays_traced;
        std::vector<T> &buffer = buffers[w];
        buffer.assign(total, T(0));
        Params<Var<T>> params;
        params.data = values.data;
        params.numel = values.numel;
        params.grad.assign(n_params, nullptr);
        for (size_t p = 0; p < n_params; ++p)
            if (grads[p]) params.grad[p] = buffer.data() + offset[p];
        RenderContext<Var<T>> ctx(scene, params);
        // Static, interleaved tiles: worker w always sums the same paths in the same order,
        // so gradients are bitwise reproducible for a given number of workers.
        for (int64_t tile = w; tile < n_tiles; tile += n_workers) {
            int64_t end = std::min(n_pixels, (tile + 1) * TileSize);
            for (int64_t i = tile * TileSize; i < end; ++i) {
                RGB<T> dL(adjoint[3 * i], adjoint[3 * i + 1], adjoint[3 * i + 2]);
                if (dL[0] == T(0) && dL[1] == T(0) && dL[2] == T(0)) continue;
                dL = dL * inv_spp;
                int px, py;
                uint64_t key;
                at.locate(i, &px, &py, &key);
                for (int s = 0; s < req.spp; ++s) {
                    // Re-trace a path recording only what depends on differentiated
                    // parameters, then push the pixel's adjoint back along it.
                    tape_reset<T>();
                    Var<T> L = trace_sample(ctx, camera, cfg, req.seed, px, py, key, s);
                    if (SpectrumTraits<Var<T>>::is_finite(L)) L.backward(dL);
                }
            }
        }
        tape_reset<T>();
        rays += rays_traced - rays_before;
    });
    // Reduce the workers' buffers in worker order.
    for (size_t p = 0; p < n_params; ++p) {
        if (!grads[p]) continue;
        for (int w = 0; w < n_workers; ++w) {
            if (buffers[w].empty()) continue;
            const T *b = buffers[w].data() + offset[p];
            for (int64_t k = 0; k < values.numel[p]; ++k) grads[p][k] += b[k];
        }
    }
    if (req.rays) *req.rays = rays;
}

template void render_fwd<RGB<float>>(const RenderContext<RGB<float>> &, const Camera &,
                                     const IntegratorSettings &, const RenderRequest &, float *,
                                     const WorkerPool &);
template void render_fwd<RGB<double>>(const RenderContext<RGB<double>> &, const Camera &,
                                      const IntegratorSettings &, const RenderRequest &, double *,
                                      const WorkerPool &);
template void render_bwd<float>(const Scene &, const Params<RGB<float>> &, const Camera &,
                                const IntegratorSettings &, const RenderRequest &, const float *,
                                const std::vector<float *> &, const WorkerPool &);
template void render_bwd<double>(const Scene &, const Params<RGB<double>> &, const Camera &,
                                 const IntegratorSettings &, const RenderRequest &,
                                 const double *, const std::vector<double *> &,
                                 const WorkerPool &);
template void render_jvp<float>(const RenderContext<Dual<float>> &, const Camera &,
                                const IntegratorSettings &, const RenderRequest &, float *,
                                float *, const WorkerPool &);
template void render_jvp<double>(const RenderContext<Dual<double>> &, const Camera &,
                                 const IntegratorSettings &, const RenderRequest &, double *,
                                 double *, const WorkerPool &);

}  // namespace rbpt
