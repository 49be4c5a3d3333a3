// The render loop: every pixel of the crop window (or a band of its rows) averages `spp`
// filter-importance-sampled paths. Pixels are independent and each has its own random
// stream, so the image does not depend on the number of threads or on scheduling.
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

/// Runs the given job once on each worker thread of the caller's pool and waits for all.
/// The bindings implement it with torch's intra-op pool; the core knows no thread library.
using WorkerPool = std::function<void(const std::function<void()> &job)>;

/// Render into `out`, an array of (row_end - row_begin, crop_width, 3) values of real_t<S>.
template <typename S>
void render(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
            const RenderRequest &req, real_t<S> *out, const WorkerPool &pool);

}  // namespace rbpt
