// The render loops: every pixel of the crop window (or a band of its rows) averages `spp`
// filter-importance-sampled paths. Pixels are independent and each has its own random
// stream, so images do not depend on the number of threads or on scheduling.
//   render_fwd: the image, for S = RGB<float> / RGB<double>;
//   render_bwd: radiative backpropagation: re-trace paths from the camera with the tape type
//               Var<T>, each carrying its pixel's adjoint, and accumulate parameter gradients;
//   render_jvp: the image and its directional derivative, with the dual type Dual<T>.
#pragma once

#include <functional>

#include "camera.h"
#include "integrator.h"

namespace rbpt {

struct RenderRequest {
    int spp = 1;
    uint64_t seed = 0;
    int row_begin = 0, row_end = -1;  ///< rows of the crop window to render (-1: all)
    uint64_t *rays = nullptr;         ///< if set, receives the number of rays traced
};

/// Runs the given job once on each of `workers()` threads of the caller's pool and waits.
/// The bindings implement it with torch's intra-op pool; the core knows no thread library.
struct WorkerPool {
    int workers = 1;
    std::function<void(const std::function<void()> &job)> run;
};

/// Render into `out`, an array of (row_end - row_begin, crop_width, 3) values of real_t<S>.
template <typename S>
void render_fwd(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
                const RenderRequest &req, real_t<S> *out, const WorkerPool &pool);

/// Accumulate into grads[p] (nullptr: not differentiated) the gradient of
/// sum(adjoint * image) with respect to parameter p, estimated with paths traced from
/// req.seed (independent of the forward pass unless the caller reuses its seed). `adjoint`
/// is (crop_height, crop_width, 3); pixels whose adjoint is zero trace nothing. The result is
/// deterministic for a given pool size.
template <typename T>
void render_bwd(const Scene &scene, const Params<RGB<T>> &values, const Camera &camera,
                const IntegratorSettings &cfg, const RenderRequest &req, const T *adjoint,
                const std::vector<T *> &grads, const WorkerPool &pool);

/// The image and its derivative along the parameter tangents in `params` (forward mode).
template <typename T>
void render_jvp(const RenderContext<Dual<T>> &ctx, const Camera &camera,
                const IntegratorSettings &cfg, const RenderRequest &req, T *out, T *out_tangent,
                const WorkerPool &pool);

}  // namespace rbpt
