// The render loops. Every pixel of the crop window traces `spp` paths from positions uniform
// in the pixel, each with its own random stream (seed, pixel, sample); like Mitsuba's film,
// every sample is splatted with the reconstruction filter's weights into all pixels around
// it, and a pixel is its weighted sum of samples over its sum of weights. Splats are summed
// in double precision in an order fixed by the image, not by the threads, so an image is
// bitwise identical for any number of threads.
//   render_fwd: the image, for S = RGB<float> / RGB<double>;
//   render_bwd: radiative backpropagation: re-trace independent paths from the camera, each
//               carrying the adjoint its splat gathers from the pixels it reaches (the
//               transpose of the splat), and accumulate parameter gradients: in lanes where
//               every differentiated parameter is a reflectance or transmittance the path is
//               linear in, an emitter's radiance or a GGX conductor's roughness (wavefront.h's
//               WavefrontVertex), else with the tape type Var<T>;
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
    /// If set, receives the number of samples dropped because their value was not finite
    /// (NaN or infinite radiance arising inside the integrator).
    uint64_t *nonfinite = nullptr;
    /// If set, receive the number of paths render_bwd traced in lanes (wavefront.h's
    /// WavefrontVertex) and with the tape.
    uint64_t *lane_paths = nullptr, *tape_paths = nullptr;
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
/// is (crop_height, crop_width, 3); samples whose splat reaches only zero adjoints trace
/// nothing. Gradients are summed in double precision; the result is deterministic for a given
/// pool size.
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
