// The only translation unit that includes torch: converts tensors and Python descriptions
// into the core's plain types, validates them once, and runs the core on torch's thread pool.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include "render.h"
#include "wavefront.h"

namespace py = pybind11;
using namespace rbpt;

namespace {

/// Tensors this file allocates are plain ones even when called inside torch.func transforms
/// (whose dispatch layer would otherwise wrap them into storage-less tensors).
struct PlainTensors {
    c10::impl::ExcludeDispatchKeyGuard guard{c10::DispatchKeySet(
        {c10::DispatchKey::FuncTorchDynamicLayerFrontMode,
         c10::DispatchKey::FuncTorchDynamicLayerBackMode})};
};

[[noreturn]] void fail(const std::string &message) { throw py::value_error(message); }

template <typename T>
T get(const py::dict &d, const char *key) {
    if (!d.contains(key)) fail(std::string("missing entry '") + key + "'");
    return d[key].cast<T>();
}

Vec3 vec3(const std::vector<float> &v, const char *what) {
    if (v.size() != 3) fail(std::string(what) + " must have 3 entries, got " + std::to_string(v.size()));
    return {v[0], v[1], v[2]};
}

TextureRef texture_ref(const py::object &o) {
    TextureRef t;
    if (o.is_none()) return t;
    auto values = o.cast<std::vector<int>>();  // (param, texture) or (param, bitmap, attribute)
    if (values.size() != 2 && values.size() != 3) fail("a texture is (param, texture[, attribute])");
    t.param = values[0];
    t.texture = values[1];
    if (values.size() == 3) t.attribute = values[2];
    return t;
}

MicrofacetType distribution(const std::string &name) {
    if (name == "beckmann") return MicrofacetType::Beckmann;
    if (name == "ggx") return MicrofacetType::GGX;
    fail("unknown microfacet distribution '" + name + "' (supported: beckmann, ggx)");
}

/// Check a float tensor's shape and return it contiguous on the CPU as float32.
torch::Tensor float_array(const torch::Tensor &t, int64_t cols, const char *what) {
    if (t.dim() != 2 || t.size(1) != cols)
        fail(std::string(what) + " must have shape [N, " + std::to_string(cols) + "], got " +
             std::string(c10::str(t.sizes())));
    return t.to(torch::kCPU, torch::kFloat32).contiguous();
}

/// The sensor's sampler: entries "sampler" (Mitsuba's plugin name, default independent)
/// and "sampler_jitter" (default true). Its sample count is set per render (whole_image).
SamplerDesc make_sampler(const py::dict &d) {
    SamplerDesc s;
    auto type = d.contains("sampler") ? get<std::string>(d, "sampler") : std::string("independent");
    if (type == "independent") s.type = SamplerType::Independent;
    else if (type == "stratified") s.type = SamplerType::Stratified;
    else if (type == "multijitter") s.type = SamplerType::Multijitter;
    else if (type == "orthogonal") s.type = SamplerType::Orthogonal;
    else if (type == "ldsampler") s.type = SamplerType::LowDiscrepancy;
    else fail("unknown sampler '" + type + "' (supported: independent, stratified, multijitter, "
              "orthogonal, ldsampler)");
    if (d.contains("sampler_jitter")) s.jitter = get<bool>(d, "sampler_jitter");
    return s;
}

Camera make_camera(const py::dict &d) {
    Camera cam;
    auto m = get<std::vector<std::vector<float>>>(d, "to_world");
    if (m.size() < 3 || m[0].size() != 4) fail("camera to_world must be a 4x4 matrix");
    auto column = [&](int j) { return Vec3{m[0][j], m[1][j], m[2][j]}; };
    cam.frame_x = column(0);
    cam.frame_y = column(1);
    cam.frame_z = column(2);
    cam.axis_x = normalize(cam.frame_x);
    cam.axis_y = normalize(cam.frame_y);
    cam.axis_z = normalize(cam.frame_z);
    cam.origin = column(3);
    auto type = d.contains("type") ? get<std::string>(d, "type") : std::string("perspective");
    if (type == "perspective") cam.type = CameraType::Perspective;
    else if (type == "orthographic") cam.type = CameraType::Orthographic;
    else if (type == "thinlens") cam.type = CameraType::ThinLens;
    else fail("unknown sensor '" + type + "' (supported: perspective, orthographic, thinlens)");
    if (cam.type == CameraType::ThinLens) {
        cam.aperture_radius = get<float>(d, "aperture_radius");
        cam.focus_distance = get<float>(d, "focus_distance");
    }
    cam.sampler = make_sampler(d);
    float fov_x = get<float>(d, "fov_x");
    cam.film_width = get<int>(d, "width");
    cam.film_height = get<int>(d, "height");
    if (cam.film_width <= 0 || cam.film_height <= 0) fail("film size must be positive");
    cam.tan_half_x = std::tan(0.5f * fov_x * Pi / 180.f);
    cam.tan_half_y = cam.tan_half_x * float(cam.film_height) / float(cam.film_width);
    cam.near_clip = get<float>(d, "near_clip");
    cam.far_clip = get<float>(d, "far_clip");
    auto crop = get<std::vector<int>>(d, "crop");
    if (crop.size() != 4) fail("crop must be (x, y, width, height)");
    cam.crop_x = crop[0];
    cam.crop_y = crop[1];
    cam.crop_width = crop[2];
    cam.crop_height = crop[3];
    if (cam.crop_x < 0 || cam.crop_y < 0 || cam.crop_width <= 0 || cam.crop_height <= 0 ||
        cam.crop_x + cam.crop_width > cam.film_width ||
        cam.crop_y + cam.crop_height > cam.film_height)
        fail("crop window lies outside the film");
    auto filter = get<std::string>(d, "filter");
    if (filter == "box") cam.filter.type = FilterType::Box;
    else if (filter == "tent") cam.filter.type = FilterType::Tent;
    else if (filter == "gaussian") cam.filter.type = FilterType::Gaussian;
    else if (filter == "mitchell") cam.filter.type = FilterType::Mitchell;
    else if (filter == "lanczos") cam.filter.type = FilterType::Lanczos;
    else fail("unknown filter '" + filter + "'");
    cam.filter.radius = get<float>(d, "filter_radius");
    cam.filter.stddev = get<float>(d, "filter_stddev");
    if (d.contains("filter_b")) cam.filter.b = get<float>(d, "filter_b");
    if (d.contains("filter_c")) cam.filter.c = get<float>(d, "filter_c");
    if (d.contains("filter_lobes")) cam.filter.lobes = get<int>(d, "filter_lobes");
    cam.filter.prepare();
    if (!(cam.filter.radius > 0.f) || cam.filter.border() > Filter::MaxBorder)
        fail("filter radius must lie in (0, " + std::to_string(Filter::MaxBorder) + ".5] pixels, got " +
             std::to_string(cam.filter.radius));
    return cam;
}

IntegratorSettings make_integrator(const py::dict &d) {
    IntegratorSettings cfg;
    auto type = get<std::string>(d, "type");
    if (type == "path") cfg.type = IntegratorType::Path;
    else if (type == "direct") cfg.type = IntegratorType::Direct;
    else fail("unknown integrator '" + type + "'");
    cfg.max_depth = get<int>(d, "max_depth");
    cfg.rr_depth = get<int>(d, "rr_depth");
    cfg.emitter_samples = get<int>(d, "emitter_samples");
    cfg.bsdf_samples = get<int>(d, "bsdf_samples");
    cfg.hide_emitters = get<bool>(d, "hide_emitters");
    return cfg;
}

/// Validate the parameter tensors against the scene's registry and bind them as Params<S>.
template <typename T>
Params<RGB<T>> bind_params(const Scene &scene, const std::vector<torch::Tensor> &tensors) {
    if (tensors.size() != scene.params.size())
        fail("expected " + std::to_string(scene.params.size()) + " parameter tensors, got " +
             std::to_string(tensors.size()));
    auto dtype = std::is_same<T, float>::value ? torch::kFloat32 : torch::kFloat64;
    Params<RGB<T>> p;
    for (size_t i = 0; i < tensors.size(); ++i) {
        const torch::Tensor &t = tensors[i];
        const ParamInfo &info = scene.params[i];
        if (t.device().type() != torch::kCPU)
            fail("parameter '" + info.name + "' must be a CPU tensor");
        if (t.scalar_type() != dtype)
            fail("parameter '" + info.name + "' must have dtype " + std::string(c10::toString(dtype)) +
                 ", got " + std::string(c10::toString(t.scalar_type())));
        if (!t.is_contiguous()) fail("parameter '" + info.name + "' must be contiguous");
        if (t.numel() != info.numel)
            fail("parameter '" + info.name + "' must have " + std::to_string(info.numel) +
                 " entries, got " + std::to_string(t.numel()));
        const T *data = t.data_ptr<T>();
        for (int64_t k = 0; k < t.numel(); ++k) {
            if (!std::isfinite(data[k]))
                fail("parameter '" + info.name + "' has a non-finite value (" +
                     std::to_string(data[k]) + ") at entry " + std::to_string(k) +
                     " of shape " + std::string(c10::str(t.sizes())) +
                     ": parameters, emission and texels must be finite");
        }
        p.data.push_back(data);
        p.numel.push_back(t.numel());
    }
    return p;
}

/// Report samples the integrator dropped for a non-finite value as a RuntimeWarning (an
/// error under `warnings.simplefilter("error")`). Call with the GIL held.
void warn_nonfinite(uint64_t dropped, uint64_t total, const char *pass) {
    if (dropped == 0) return;
    std::string message = "torch_rbpt: " + std::to_string(dropped) + " of " + std::to_string(total) +
                          " " + pass + " samples had a non-finite value (NaN or infinite) and were dropped";
    if (PyErr_WarnEx(PyExc_RuntimeWarning, message.c_str(), 1) < 0) throw py::error_already_set();
}

/// Below this many paths a render runs on the calling thread alone: waking the pool costs
/// milliseconds on a busy machine, more than tracing the paths.
constexpr int64_t MinPathsForThreads = 4096;

/// torch's intra-op pool (torch.set_num_threads is honoured): runs a job once per thread.
WorkerPool torch_pool(int64_t paths) {
    WorkerPool pool;
    pool.workers = paths < MinPathsForThreads ? 1 : at::get_num_threads();
    int n = pool.workers;
    if (n == 1) {
        pool.run = [](const std::function<void()> &job) { job(); };
        return pool;
    }
    pool.run = [n](const std::function<void()> &job) {
        at::parallel_for(0, n, 1, [&](int64_t begin, int64_t end) {
            for (int64_t i = begin; i < end; ++i) job();
        });
    };
    return pool;
}

template <typename T>
torch::Tensor render_typed(const Scene &scene, const Camera &cam, const IntegratorSettings &cfg,
                           const std::vector<torch::Tensor> &params, RenderRequest req,
                           uint64_t *rays) {
    req.rays = rays;
    uint64_t dropped = 0;
    req.nonfinite = &dropped;
    RenderContext<RGB<T>> ctx(scene, bind_params<T>(scene, params));
    auto dtype = std::is_same<T, float>::value ? torch::kFloat32 : torch::kFloat64;
    torch::Tensor out = torch::empty({req.row_end - req.row_begin, cam.crop_width, 3},
                                     torch::TensorOptions().dtype(dtype));
    T *data = out.data_ptr<T>();
    {
        py::gil_scoped_release release;
        int64_t paths = int64_t(req.row_end - req.row_begin) * cam.crop_width * req.spp;
        render_fwd(ctx, cam, cfg, req, data, torch_pool(paths));
    }
    warn_nonfinite(dropped, uint64_t(req.row_end - req.row_begin) * cam.crop_width * req.spp, "image");
    return out;
}

/// Give `sampler` `spp` samples per pixel, rounded as Mitsuba's set_sample_count rounds them.
void set_spp(SamplerDesc &sampler, int spp) {
    if (spp <= 0) fail("spp must be positive, got " + std::to_string(spp));
    if (sampler.type != SamplerType::Independent && spp > (1 << 24))
        fail("the stratified samplers take at most 2^24 samples per pixel, got " + std::to_string(spp));
    sampler.set_sample_count(uint32_t(spp));
}

/// A request for the whole image at `spp` samples per pixel, rounded as the sensor's sampler
/// rounds its sample count: `cam.sampler` learns the count.
RenderRequest whole_image(Camera &cam, int spp, uint64_t seed) {
    set_spp(cam.sampler, spp);
    RenderRequest req;
    req.spp = int(cam.sampler.sample_count);
    req.seed = seed;
    req.row_end = cam.crop_height;
    return req;
}

/// Render an image; returns (image (H, W, 3) of the parameters' dtype, rays traced).
py::tuple render_image(const Scene &scene, const py::dict &camera, const py::dict &integrator,
                       const std::vector<torch::Tensor> &params, int spp, uint64_t seed,
                       int row_begin, int row_end) {
    PlainTensors plain;
    Camera cam = make_camera(camera);
    IntegratorSettings cfg = make_integrator(integrator);
    RenderRequest req = whole_image(cam, spp, seed);
    req.row_begin = row_begin;
    if (row_end >= 0) req.row_end = row_end;
    if (req.row_begin < 0 || req.row_begin >= req.row_end || req.row_end > cam.crop_height)
        fail("rows must satisfy 0 <= begin < end <= crop height");
    bool dbl = !params.empty() && params[0].scalar_type() == torch::kFloat64;
    uint64_t rays = 0;
    torch::Tensor image = dbl ? render_typed<double>(scene, cam, cfg, params, req, &rays)
                              : render_typed<float>(scene, cam, cfg, params, req, &rays);
    return py::make_tuple(image, rays);
}

/// Whether render_fwd traces this scene's float paths in SIMD lanes (wavefront.h), for tests.
bool uses_wavefront(const Scene &scene, const py::dict &camera, const py::dict &integrator,
                    const std::vector<torch::Tensor> &params) {
    PlainTensors plain;
    Camera cam = make_camera(camera);
    IntegratorSettings cfg = make_integrator(integrator);
    if (!params.empty() && params[0].scalar_type() == torch::kFloat64) return false;
    RenderContext<RGB<float>> ctx(scene, bind_params<float>(scene, params));
    return wavefront_scene(ctx, cfg, cam).has_value();
}

template <typename T>
std::vector<std::optional<torch::Tensor>> render_bwd_typed(
    const Scene &scene, const Camera &cam, const IntegratorSettings &cfg,
    const std::vector<torch::Tensor> &params, const std::vector<bool> &requires_grad,
    const torch::Tensor &adjoint, RenderRequest req) {
    Params<RGB<T>> values = bind_params<T>(scene, params);
    auto opts = torch::TensorOptions().dtype(std::is_same<T, float>::value ? torch::kFloat32 : torch::kFloat64);
    std::vector<std::optional<torch::Tensor>> out(params.size());
    std::vector<T *> grads(params.size(), nullptr);
    for (size_t p = 0; p < params.size(); ++p) {
        if (!requires_grad[p]) continue;
        out[p] = torch::zeros(params[p].sizes(), opts);
        grads[p] = out[p]->data_ptr<T>();
    }
    const T *dL = adjoint.data_ptr<T>();
    int64_t paths = adjoint.ne(0).any(-1).sum().item<int64_t>() * req.spp;
    uint64_t dropped = 0;
    RenderRequest r = req;
    r.nonfinite = &dropped;
    {
        py::gil_scoped_release release;
        render_bwd(scene, values, cam, cfg, r, dL, grads, torch_pool(paths));
    }
    warn_nonfinite(dropped, uint64_t(cam.crop_height) * cam.crop_width * req.spp, "backward");
    return out;
}

/// Radiative backpropagation: gradients of sum(grad_image * image) with respect to the
/// parameters flagged in requires_grad (None for the others).
std::vector<std::optional<torch::Tensor>> render_bwd_entry(
    const Scene &scene, const py::dict &camera, const py::dict &integrator,
    const std::vector<torch::Tensor> &params, const std::vector<bool> &requires_grad,
    torch::Tensor grad_image, int spp, uint64_t seed, uint64_t *paths = nullptr) {
    PlainTensors plain;
    Camera cam = make_camera(camera);
    IntegratorSettings cfg = make_integrator(integrator);
    RenderRequest req = whole_image(cam, spp, seed);
    if (paths) req.lane_paths = paths, req.tape_paths = paths + 1;
    if (requires_grad.size() != params.size()) fail("requires_grad must have one flag per parameter");
    bool dbl = !params.empty() && params[0].scalar_type() == torch::kFloat64;
    auto dtype = dbl ? torch::kFloat64 : torch::kFloat32;
    if (grad_image.dim() != 3 || grad_image.size(0) != cam.crop_height ||
        grad_image.size(1) != cam.crop_width || grad_image.size(2) != 3)
        fail("the image gradient must have shape [" + std::to_string(cam.crop_height) + ", " +
             std::to_string(cam.crop_width) + ", 3], got " + std::string(c10::str(grad_image.sizes())));
    grad_image = grad_image.to(torch::kCPU, dtype).contiguous();
    return dbl ? render_bwd_typed<double>(scene, cam, cfg, params, requires_grad, grad_image, req)
               : render_bwd_typed<float>(scene, cam, cfg, params, requires_grad, grad_image, req);
}

/// render_bwd_entry, with the number of paths the backward pass traced in lanes and with the
/// tape (for tests).
py::tuple render_bwd_paths(const Scene &scene, const py::dict &camera, const py::dict &integrator,
                           const std::vector<torch::Tensor> &params, const std::vector<bool> &requires_grad,
                           torch::Tensor grad_image, int spp, uint64_t seed) {
    uint64_t paths[2] = {0, 0};
    auto grads = render_bwd_entry(scene, camera, integrator, params, requires_grad, grad_image, spp, seed, paths);
    return py::make_tuple(grads, paths[0], paths[1]);
}

template <typename T>
py::tuple render_jvp_typed(const Scene &scene, const Camera &cam, const IntegratorSettings &cfg,
                           const std::vector<torch::Tensor> &params,
                           const std::vector<std::optional<torch::Tensor>> &tangents,
                           const RenderRequest &req) {
    Params<RGB<T>> values = bind_params<T>(scene, params);
    Params<Dual<T>> dual;
    dual.data = values.data;
    dual.numel = values.numel;
    dual.tangent.assign(params.size(), nullptr);
    std::vector<torch::Tensor> keep;
    auto dtype = std::is_same<T, float>::value ? torch::kFloat32 : torch::kFloat64;
    for (size_t p = 0; p < params.size(); ++p) {
        if (!tangents[p]) continue;
        torch::Tensor t = tangents[p]->to(torch::kCPU, dtype).contiguous();
        if (t.numel() != values.numel[p])
            fail("tangent of '" + scene.params[p].name + "' must have " +
                 std::to_string(values.numel[p]) + " entries, got " + std::to_string(t.numel()));
        keep.push_back(t);
        dual.tangent[p] = t.data_ptr<T>();
    }
    RenderContext<Dual<T>> ctx(scene, dual);
    auto opts = torch::TensorOptions().dtype(dtype);
    torch::Tensor image = torch::empty({cam.crop_height, cam.crop_width, 3}, opts);
    torch::Tensor tangent = torch::empty({cam.crop_height, cam.crop_width, 3}, opts);
    T *pi = image.data_ptr<T>(), *pt = tangent.data_ptr<T>();
    uint64_t dropped = 0;
    RenderRequest r = req;
    r.nonfinite = &dropped;
    {
        py::gil_scoped_release release;
        render_jvp(ctx, cam, cfg, r, pi, pt, torch_pool(int64_t(cam.crop_height) * cam.crop_width * req.spp));
    }
    warn_nonfinite(dropped, uint64_t(cam.crop_height) * cam.crop_width * req.spp, "forward-mode");
    return py::make_tuple(image, tangent);
}

/// Forward mode: (image, derivative of the image along the parameter tangents).
py::tuple render_jvp_entry(const Scene &scene, const py::dict &camera, const py::dict &integrator,
                           const std::vector<torch::Tensor> &params,
                           const std::vector<std::optional<torch::Tensor>> &tangents, int spp,
                           uint64_t seed) {
    PlainTensors plain;
    Camera cam = make_camera(camera);
    IntegratorSettings cfg = make_integrator(integrator);
    RenderRequest req = whole_image(cam, spp, seed);
    if (tangents.size() != params.size()) fail("tangents must have one entry per parameter");
    bool dbl = !params.empty() && params[0].scalar_type() == torch::kFloat64;
    return dbl ? render_jvp_typed<double>(scene, cam, cfg, params, tangents, req)
               : render_jvp_typed<float>(scene, cam, cfg, params, tangents, req);
}

// ---- BSDF queries in the local frame, for statistical tests -----------------------------

SurfaceInteraction local_interaction(const float *wi) {
    SurfaceInteraction si;
    si.valid = true;
    si.n = {0.f, 0.f, 1.f};
    si.sh_frame = Frame(si.n);
    si.wi = {wi[0], wi[1], wi[2]};
    si.uv = {0.5f, 0.5f};
    return si;
}

template <typename T>
py::tuple bsdf_query_typed(const Scene &scene, const std::vector<torch::Tensor> &params, int index,
                           torch::Tensor wi, torch::Tensor wo, torch::Tensor u1,
                           torch::Tensor u2, torch::Tensor uv) {
    RenderContext<RGB<T>> ctx(scene, bind_params<T>(scene, params));
    const BSDF &b = scene.bsdfs[index];
    int64_t n = wi.size(0);
    auto opts = torch::TensorOptions().dtype(std::is_same<T, float>::value ? torch::kFloat32
                                                                            : torch::kFloat64);
    torch::Tensor value = torch::zeros({n, 3}, opts), pdf = torch::zeros({n}, torch::kFloat32);
    torch::Tensor s_wo = torch::zeros({n, 3}, torch::kFloat32), s_pdf = torch::zeros({n}, torch::kFloat32);
    torch::Tensor s_weight = torch::zeros({n, 3}, opts), s_delta = torch::zeros({n}, torch::kBool);
    const float *pwi = wi.data_ptr<float>(), *pwo = wo.data_ptr<float>();
    const float *pu1 = u1.data_ptr<float>(), *pu2 = u2.data_ptr<float>(), *puv = uv.data_ptr<float>();
    for (int64_t i = 0; i < n; ++i) {
        SurfaceInteraction si = local_interaction(pwi + 3 * i);
        si.uv = {puv[2 * i], puv[2 * i + 1]};
        Vec3 w{pwo[3 * i], pwo[3 * i + 1], pwo[3 * i + 2]};
        RGB<T> f = bsdf_eval<RGB<T>>(b, ctx, index, si, w);
        for (int c = 0; c < 3; ++c) value.data_ptr<T>()[3 * i + c] = f[c];
        pdf.data_ptr<float>()[i] = bsdf_pdf(b, ctx, index, si, w);
        auto bs = bsdf_sample<RGB<T>>(b, ctx, index, si, pu1[i], Vec2{pu2[2 * i], pu2[2 * i + 1]});
        if (!bs) continue;
        for (int c = 0; c < 3; ++c) {
            s_wo.data_ptr<float>()[3 * i + c] = bs->wo[c];
            s_weight.data_ptr<T>()[3 * i + c] = bs->weight[c];
        }
        s_pdf.data_ptr<float>()[i] = bs->pdf;
        s_delta.data_ptr<bool>()[i] = bs->delta;
    }
    return py::make_tuple(value, pdf, s_wo, s_pdf, s_weight, s_delta);
}

py::tuple bsdf_query(const Scene &scene, const std::vector<torch::Tensor> &params, int index,
                     torch::Tensor wi, torch::Tensor wo, torch::Tensor u1, torch::Tensor u2,
                     torch::Tensor uv) {
    if (index < 0 || index >= int(scene.bsdfs.size())) fail("BSDF index out of range");
    wi = float_array(wi, 3, "wi");
    wo = float_array(wo, 3, "wo");
    u2 = float_array(u2, 2, "u2");
    uv = float_array(uv, 2, "uv");
    u1 = u1.to(torch::kCPU, torch::kFloat32).contiguous().reshape({-1});
    int64_t n = wi.size(0);
    if (wo.size(0) != n || u1.size(0) != n || u2.size(0) != n || uv.size(0) != n)
        fail("wi, wo, u1, u2 and uv must have the same length");
    bool dbl = !params.empty() && params[0].scalar_type() == torch::kFloat64;
    return dbl ? bsdf_query_typed<double>(scene, params, index, wi, wo, u1, u2, uv)
               : bsdf_query_typed<float>(scene, params, index, wi, wo, u1, u2, uv);
}

// ---- Sensor and sampler queries, for tests --------------------------------------------

/// The numbers the sensor's sampler gives pixel `pixel` (row-major index in the full film):
/// for each of its samples, one draw per entry of `dims` (1: next_1d, 2: next_2d; -1 and -2:
/// the same drawn by the even samples alone, the odd ones' entries 0), the values
/// concatenated. With `lanes`, the pixel's samples are drawn together by SamplerColumns (up
/// to its capacity at a time) rather than one by one by Sampler. Returns a
/// (sample_count, sum(|dims|)) float32 tensor.
torch::Tensor sampler_points(const py::dict &camera, int spp, uint64_t seed, uint64_t pixel,
                             const std::vector<int> &dims, bool lanes) {
    Camera cam = make_camera(camera);
    RenderRequest req = whole_image(cam, spp, seed);
    int width = 0;
    for (int d : dims) {
        if (d == 0 || d < -2 || d > 2) fail("dims entries must be 1 or 2, or -1 or -2");
        width += std::abs(d);
    }
    torch::Tensor out = torch::zeros({req.spp, width});
    float *o = out.data_ptr<float>();
    if (!lanes) {
        for (int s = 0; s < req.spp; ++s, o += width) {
            Sampler sampler(cam.sampler, seed, pixel, uint64_t(s));
            int column = 0;
            for (int d : dims) {
                const bool draws = d > 0 || s % 2 == 0;
                if (std::abs(d) == 1 && draws) {
                    o[column] = sampler.next_1d();
                } else if (draws) {
                    Vec2 u = sampler.next_2d();
                    o[column] = u.x, o[column + 1] = u.y;
                }
                column += std::abs(d);
            }
        }
        return out;
    }
    if (cam.sampler.type == SamplerType::Independent) fail("lanes: a sampler other than independent");
    const PixelSeed pixel_seed(seed, pixel);
    auto columns = std::make_unique<SamplerColumns>();
    constexpr int C = SamplerColumns::Capacity;
    std::vector<uint64_t> keys(C, pixel_seed.stream);
    std::vector<int> even(C);
    std::vector<float> ux(C), uy(C);
    for (int first = 0; first < req.spp; first += C) {
        const int n = std::min(C, req.spp - first);
        for (int k = 0; k < n; ++k) {
            columns->seq[k] = pixel_seed.sequence, columns->index[k] = uint32_t(first + k);
            even[k] = (first + k) % 2 == 0;
        }
        columns->begin(cam.sampler, n, keys.data());
        int column = 0;
        for (int d : dims) {
            const int *draw = d > 0 ? nullptr : even.data();
            if (std::abs(d) == 1) columns->next_1d(cam.sampler, n, draw, ux.data());
            else columns->next_2d(cam.sampler, n, draw, ux.data(), uy.data());
            for (int k = 0; k < n; ++k) {
                if (d < 0 && !even[k]) continue;
                o[(first + k) * width + column] = ux[k];
                if (std::abs(d) == 2) o[(first + k) * width + column + 1] = uy[k];
            }
            column += std::abs(d);
        }
    }
    return out;
}

/// The sensor's rays for film positions (N, 2) in pixels and aperture samples (N, 2):
/// (origins (N, 3), directions (N, 3), tmin (N,), tmax (N,)).
py::tuple camera_rays(const py::dict &camera, torch::Tensor positions, torch::Tensor apertures) {
    Camera cam = make_camera(camera);
    positions = float_array(positions, 2, "positions");
    apertures = float_array(apertures, 2, "apertures");
    int64_t n = positions.size(0);
    if (apertures.size(0) != n) fail("positions and apertures must have the same length");
    torch::Tensor o = torch::empty({n, 3}), d = torch::empty({n, 3}), t0 = torch::empty({n}),
                  t1 = torch::empty({n});
    const float *p = positions.data_ptr<float>(), *a = apertures.data_ptr<float>();
    float *po = o.data_ptr<float>(), *pd = d.data_ptr<float>();
    for (int64_t i = 0; i < n; ++i) {
        Ray r = cam.ray_for({p[2 * i], p[2 * i + 1]}, {a[2 * i], a[2 * i + 1]});
        for (int k = 0; k < 3; ++k) {
            po[3 * i + k] = r.o[k];
            pd[3 * i + k] = r.d[k];
        }
        t0.data_ptr<float>()[i] = r.tmin;
        t1.data_ptr<float>()[i] = r.tmax;
    }
    return py::make_tuple(o, d, t0, t1);
}

/// The sensor's filter weights of the rows that eval_row computes for the splats: for each
/// start offset x0 (N,), the n weights at x0, x0 + 1, ..., x0 + n - 1 (N, n).
torch::Tensor filter_weights(const py::dict &camera, torch::Tensor x0, int n) {
    Camera cam = make_camera(camera);
    if (n < 1 || n > 2 * Filter::MaxBorder + 1)
        fail("n must lie in [1, " + std::to_string(2 * Filter::MaxBorder + 1) + "], got " + std::to_string(n));
    if (x0.dim() != 1) fail("x0 must have shape (N,)");
    x0 = x0.to(torch::kFloat32).contiguous();
    torch::Tensor w = torch::empty({x0.size(0), n});
    for (int64_t i = 0; i < x0.size(0); ++i)
        cam.filter.eval_row(x0.data_ptr<float>()[i], n, w.data_ptr<float>() + i * n);
    return w;
}

/// Checks a batch of rays (origins and directions, (N, 3) each, converted to contiguous
/// float32 in place) and returns N.
int64_t ray_batch(torch::Tensor &origins, torch::Tensor &directions) {
    origins = float_array(origins, 3, "origins");
    directions = float_array(directions, 3, "directions");
    if (directions.size(0) != origins.size(0)) fail("origins and directions must have the same length");
    return origins.size(0);
}

/// Nearest hits of a batch of rays: (t (N,) with inf for misses, shape index (N,) or -1).
py::tuple intersect_rays(const Scene &scene, torch::Tensor origins, torch::Tensor directions) {
    int64_t n = ray_batch(origins, directions);
    torch::Tensor t = torch::full({n}, std::numeric_limits<float>::infinity(), torch::kFloat32);
    torch::Tensor shape = torch::full({n}, -1, torch::kInt64);
    const float *o = origins.data_ptr<float>(), *d = directions.data_ptr<float>();
    float *pt = t.data_ptr<float>();
    int64_t *ps = shape.data_ptr<int64_t>();
    {
        py::gil_scoped_release release;
        at::parallel_for(0, n, 1024, [&](int64_t begin, int64_t end) {
            for (int64_t i = begin; i < end; ++i) {
                Ray ray;
                ray.o = {o[3 * i], o[3 * i + 1], o[3 * i + 2]};
                ray.d = normalize(Vec3{d[3 * i], d[3 * i + 1], d[3 * i + 2]});
                SurfaceInteraction si = scene.intersect(ray);
                if (si.valid) {
                    pt[i] = si.t;
                    ps[i] = si.shape;
                }
            }
        });
    }
    return py::make_tuple(t, shape);
}

/// Rays given as they are (origins and directions (N, 3), intervals (N,)), as the eight
/// columns of RayColumns (for tests).
struct TestRays {
    int64_t n = 0;
    std::vector<float> c[8];
    TestRays(torch::Tensor origins, torch::Tensor directions, torch::Tensor tmin, torch::Tensor tmax) {
        n = ray_batch(origins, directions);
        tmin = tmin.to(torch::kFloat32).contiguous();
        tmax = tmax.to(torch::kFloat32).contiguous();
        if (tmin.numel() != n || tmax.numel() != n) fail("tmin and tmax must have one entry per ray");
        for (int a = 0; a < 3; ++a) {
            for (int64_t i = 0; i < n; ++i) {
                c[a].push_back(origins.data_ptr<float>()[3 * i + a]);
                c[3 + a].push_back(directions.data_ptr<float>()[3 * i + a]);
            }
        }
        c[6].assign(tmin.data_ptr<float>(), tmin.data_ptr<float>() + n);
        c[7].assign(tmax.data_ptr<float>(), tmax.data_ptr<float>() + n);
    }
    /// The columns from ray `first` on.
    RayColumns from(int64_t first) const {
        return {c[0].data() + first, c[1].data() + first, c[2].data() + first, c[3].data() + first,
                c[4].data() + first, c[5].data() + first, c[6].data() + first, c[7].data() + first};
    }
};

/// Whether each ray, given as it is, is blocked in its interval (for tests): from
/// BVH::occluded per ray, or from BVH::occluded_columns in batches of BVH::MaxColumns
/// (`columns`), or from BVH::occluded_traversal per ray (`traversal`), or in a tree of one
/// node from BVH::root_masks in batches and BVH::occluded_children per ray (`masks`, the
/// wavefront's shadow rays there); with `shadow`, in the shadow rays' tree (Scene::shadow_tree()).
torch::Tensor occluded_rays(const Scene &scene, torch::Tensor origins, torch::Tensor directions,
                            torch::Tensor tmin, torch::Tensor tmax, bool columns, bool traversal, bool masks,
                            bool shadow) {
    const TestRays rays(origins, directions, tmin, tmax);
    const BVH &bvh = shadow ? scene.shadow_tree() : scene.bvh;
    if (masks && !bvh.one_node()) fail("occluded_rays: masks=True needs a scene whose BVH is one node");
    torch::Tensor blocked = torch::empty({rays.n}, torch::kBool);
    std::vector<int> flags(size_t(rays.n));
    for (int64_t b = 0; b < rays.n; b += BVH::MaxColumns) {
        int m = int(std::min<int64_t>(BVH::MaxColumns, rays.n - b));
        if (columns) {
            bvh.occluded_columns(rays.from(b), m, flags.data() + b);
            continue;
        }
        int mask[BVH::MaxColumns];
        if (masks) bvh.root_masks(rays.from(b), m, mask);
        for (int k = 0; k < m; ++k) {
            const Ray ray = rays.from(b).ray(k);
            flags[size_t(b + k)] = masks       ? bvh.occluded_children(ray, mask[k])
                                   : traversal ? bvh.occluded_traversal(ray)
                                               : bvh.occluded(ray);
        }
    }
    for (int64_t i = 0; i < rays.n; ++i) blocked.data_ptr<bool>()[i] = flags[size_t(i)] != 0;
    return blocked;
}

/// Closest hits of rays given as they are (no normalisation), with their intervals (for
/// tests): (t, prim (-1: none), u, v), from BVH::intersect per ray, or from
/// BVH::intersect_columns in batches of BVH::MaxColumns (`columns`), or from
/// BVH::intersect_traversal per ray (`traversal`).
py::tuple closest_hits(const Scene &scene, torch::Tensor origins, torch::Tensor directions,
                       torch::Tensor tmin, torch::Tensor tmax, bool columns, bool traversal) {
    const TestRays rays(origins, directions, tmin, tmax);
    const int64_t n = rays.n;
    torch::Tensor t = torch::empty({n}, torch::kFloat32), u = torch::empty({n}, torch::kFloat32),
                  v = torch::empty({n}, torch::kFloat32), prim = torch::empty({n}, torch::kInt64);
    std::vector<uint32_t> ids(static_cast<size_t>(n));
    for (int64_t b = 0; b < n; b += BVH::MaxColumns) {
        int m = int(std::min<int64_t>(BVH::MaxColumns, n - b));
        HitColumns hits{t.data_ptr<float>() + b, u.data_ptr<float>() + b, v.data_ptr<float>() + b, ids.data() + b};
        if (columns) {
            scene.bvh.intersect_columns(rays.from(b), m, hits);
            continue;
        }
        for (int k = 0; k < m; ++k) {
            Hit hit;
            const Ray ray = rays.from(b).ray(k);
            traversal ? scene.bvh.intersect_traversal(ray, &hit) : scene.bvh.intersect(ray, &hit);
            hits.t[k] = hit.t, hits.u[k] = hit.u, hits.v[k] = hit.v, hits.prim[k] = hit.prim;
        }
    }
    for (int64_t i = 0; i < n; ++i) prim.data_ptr<int64_t>()[i] = ids[size_t(i)] == ~0u ? -1 : int64_t(ids[size_t(i)]);
    return py::make_tuple(t, prim, u, v);
}

/// Surface interactions of a batch of rays (for tests): (t (N,), shape (N,), p (N, 3),
/// geometric normal n (N, 3), uv (N, 2), wi (N, 3) in world space); misses have t = inf,
/// shape -1 and zeros, but for wi (-d, which an environment emitter looks up).
py::tuple interact_rays(const Scene &scene, torch::Tensor origins, torch::Tensor directions) {
    int64_t n = ray_batch(origins, directions);
    torch::Tensor t = torch::full({n}, std::numeric_limits<float>::infinity(), torch::kFloat32);
    torch::Tensor shape = torch::full({n}, -1, torch::kInt64);
    torch::Tensor p = torch::zeros({n, 3}), nrm = torch::zeros({n, 3}), uv = torch::zeros({n, 2});
    torch::Tensor wi = torch::zeros({n, 3});
    const float *o = origins.data_ptr<float>(), *d = directions.data_ptr<float>();
    for (int64_t i = 0; i < n; ++i) {
        Ray ray;
        ray.o = {o[3 * i], o[3 * i + 1], o[3 * i + 2]};
        ray.d = normalize(Vec3{d[3 * i], d[3 * i + 1], d[3 * i + 2]});
        Hit hit;
        scene.bvh.intersect(ray, &hit);
        SurfaceInteraction si = scene.geometry.interaction(ray, hit, /*all_uv=*/true);
        const Vec3 wi_world = si.valid ? si.to_world(si.wi) : si.wi;
        for (int k = 0; k < 3; ++k) wi[i][k] = wi_world[k];
        if (!si.valid) continue;
        t[i] = si.t;
        shape[i] = si.shape;
        for (int k = 0; k < 3; ++k) {
            p[i][k] = si.p[k];
            nrm[i][k] = si.n[k];
        }
        uv[i][0] = si.uv.x;
        uv[i][1] = si.uv.y;
    }
    return py::make_tuple(t, shape, p, nrm, uv, wi);
}

// ---- Scene construction ------------------------------------------------------------------

int add_mesh(Scene &scene, torch::Tensor positions, torch::Tensor faces,
             std::optional<torch::Tensor> normals, std::optional<torch::Tensor> uvs, int bsdf,
             bool flip_normals) {
    if (bsdf < 0 || bsdf >= int(scene.bsdfs.size())) fail("mesh BSDF index out of range");
    positions = float_array(positions, 3, "positions");
    if (!torch::isfinite(positions).all().item<bool>())
        fail("mesh vertex positions must be finite in float32 (a transform or coordinate overflows?)");
    if (faces.dim() != 2 || faces.size(1) != 3)
        fail("faces must have shape [M, 3], got " + std::string(c10::str(faces.sizes())));
    faces = faces.to(torch::kCPU, torch::kInt64).contiguous();
    int64_t nv = positions.size(0), nf = faces.size(0);
    if (nf == 0) fail("a mesh needs at least one face");
    if (faces.min().item<int64_t>() < 0 || faces.max().item<int64_t>() >= nv)
        fail("face indices must lie in [0, " + std::to_string(nv) + ")");
    Geometry &g = scene.geometry;
    uint32_t base = uint32_t(g.positions.size());
    Shape shape;
    shape.kind = ShapeKind::Mesh;
    shape.bsdf = bsdf;
    shape.flip_normals = flip_normals;
    shape.tri_begin = uint32_t(g.triangles.size());
    shape.tri_count = uint32_t(nf);
    shape.vertex_begin = base;
    shape.vertex_count = uint32_t(nv);
    const float *p = positions.data_ptr<float>();
    for (int64_t i = 0; i < nv; ++i) g.positions.push_back({p[3 * i], p[3 * i + 1], p[3 * i + 2]});
    // Keep the optional vertex arrays the same length as positions.
    g.normals.resize(g.positions.size());
    g.uvs.resize(g.positions.size());
    if (normals) {
        torch::Tensor n = float_array(*normals, 3, "normals");
        if (n.size(0) != nv) fail("normals must have one row per vertex");
        const float *pn = n.data_ptr<float>();
        for (int64_t i = 0; i < nv; ++i) g.normals[base + i] = {pn[3 * i], pn[3 * i + 1], pn[3 * i + 2]};
        shape.has_normals = true;
    }
    if (uvs) {
        torch::Tensor t = float_array(*uvs, 2, "uvs");
        if (t.size(0) != nv) fail("uvs must have one row per vertex");
        const float *pt = t.data_ptr<float>();
        for (int64_t i = 0; i < nv; ++i) g.uvs[base + i] = {pt[2 * i], pt[2 * i + 1]};
        shape.has_uvs = true;
    }
    const int64_t *f = faces.data_ptr<int64_t>();
    uint32_t shape_index = uint32_t(g.shapes.size());
    for (int64_t i = 0; i < nf; ++i)
        g.triangles.push_back({{base + uint32_t(f[3 * i]), base + uint32_t(f[3 * i + 1]),
                                base + uint32_t(f[3 * i + 2])},
                               shape_index});
    g.shapes.push_back(std::move(shape));
    return int(shape_index);
}

int add_sphere(Scene &scene, const std::vector<float> &center, float radius,
               const std::vector<std::vector<float>> &frame, int bsdf, bool flip_normals) {
    if (bsdf < 0 || bsdf >= int(scene.bsdfs.size())) fail("sphere BSDF index out of range");
    if (!(radius > 0.f) || !std::isfinite(radius)) fail("sphere radius must be positive and finite");
    if (center.size() == 3 && !(std::isfinite(center[0]) && std::isfinite(center[1]) && std::isfinite(center[2])))
        fail("sphere center must be finite (float32)");
    if (frame.size() != 3) fail("sphere frame must be 3 axes");
    Shape shape;
    shape.kind = ShapeKind::Sphere;
    shape.bsdf = bsdf;
    shape.flip_normals = flip_normals;
    shape.center = vec3(center, "center");
    shape.radius = radius;
    shape.local_x = normalize(vec3(frame[0], "frame axis"));
    shape.local_y = normalize(vec3(frame[1], "frame axis"));
    shape.local_z = normalize(vec3(frame[2], "frame axis"));
    Geometry &g = scene.geometry;
    g.analytic.push_back(uint32_t(g.shapes.size()));
    g.shapes.push_back(shape);
    return int(g.shapes.size()) - 1;
}

/// Give mesh `shape` its vertex_color (0) or face_color (1) attribute: parameter `param` of
/// `channels` (1 or 3) values per vertex or face.
void set_mesh_attribute(Scene &scene, int shape, int which, int param, int channels) {
    if (shape < 0 || shape >= int(scene.geometry.shapes.size())) fail("shape index out of range");
    Shape &s = scene.geometry.shapes[shape];
    if (s.kind != ShapeKind::Mesh) fail("mesh attributes need a mesh");
    if (which < 0 || which > 1 || (channels != 1 && channels != 3)) fail("bad mesh attribute");
    if (param < 0 || param >= int(scene.params.size())) fail("unknown parameter");
    int64_t count = which == 0 ? s.vertex_count : s.tri_count;
    if (scene.params[param].numel != count * channels)
        fail("mesh attribute has " + std::to_string(scene.params[param].numel) + " values, expected " +
             std::to_string(count * channels));
    s.attribute_param[which] = param;
    s.attribute_channels[which] = channels;
}

/// A disk or cylinder: p = center + axes[0] x + axes[1] y + axes[2] z from object space (the
/// unit disk at z = 0, or the cylinder of `radius` around z in [0, length] with unit axes).
/// The inverse map is computed in double from the float32 values the shape keeps.
int add_disk_or_cylinder(Scene &scene, const std::string &kind, const std::vector<float> &center,
                         const std::vector<std::vector<float>> &axes, float radius, float length,
                         int bsdf, bool flip_normals) {
    if (bsdf < 0 || bsdf >= int(scene.bsdfs.size())) fail(kind + " BSDF index out of range");
    if (axes.size() != 3) fail(kind + " needs 3 axes");
    Shape shape;
    shape.kind = kind == "disk" ? ShapeKind::Disk : ShapeKind::Cylinder;
    if (kind != "disk" && kind != "cylinder") fail("unknown analytic shape " + kind);
    shape.bsdf = bsdf;
    shape.flip_normals = flip_normals;
    shape.center = vec3(center, "center");
    shape.local_x = vec3(axes[0], "axis");
    shape.local_y = vec3(axes[1], "axis");
    shape.local_z = vec3(axes[2], "axis");
    shape.radius = radius;
    shape.length = length;
    double m[3][3], inv[3][3];
    for (int i = 0; i < 3; ++i) {
        m[i][0] = shape.local_x[i];
        m[i][1] = shape.local_y[i];
        m[i][2] = shape.local_z[i];
    }
    double det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
                 m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
                 m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    bool finite = std::isfinite(det) && std::isfinite(radius) && std::isfinite(length);
    for (int i = 0; i < 3; ++i) finite = finite && std::isfinite(shape.center[i]);
    if (!finite || det == 0.0 || !(radius > 0.f) || !(length > 0.f))
        fail(kind + ": to_world must be finite and invertible, radius and length positive");
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            int i1 = (j + 1) % 3, i2 = (j + 2) % 3, j1 = (i + 1) % 3, j2 = (i + 2) % 3;
            inv[i][j] = (m[i1][j1] * m[i2][j2] - m[i1][j2] * m[i2][j1]) / det;
        }
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) shape.to_object[i][j] = inv[i][j];
        shape.to_object[i][3] = -(inv[i][0] * shape.center[0] + inv[i][1] * shape.center[1] +
                                  inv[i][2] * shape.center[2]);
    }
    // The disk's normal is the inverse transpose of to_world applied to +z (Mitsuba's).
    shape.normal = normalize(Vec3{float(inv[2][0]), float(inv[2][1]), float(inv[2][2])});
    Geometry &g = scene.geometry;
    g.analytic.push_back(uint32_t(g.shapes.size()));
    g.shapes.push_back(shape);
    return int(g.shapes.size()) - 1;
}

int add_bsdf(Scene &scene, const std::string &type, bool twosided, const py::object &reflectance,
             const py::object &specular_reflectance, const py::object &specular_transmittance,
             int alpha, const std::string &dist, float eta, bool nonlinear) {
    BSDF b;
    if (type == "diffuse") b.type = BSDFType::Diffuse;
    else if (type == "conductor") b.type = BSDFType::Conductor;
    else if (type == "roughconductor") b.type = BSDFType::RoughConductor;
    else if (type == "dielectric") b.type = BSDFType::Dielectric;
    else if (type == "roughplastic") b.type = BSDFType::RoughPlastic;
    else fail("unknown BSDF type '" + type + "'");
    b.twosided = twosided;
    b.reflectance = texture_ref(reflectance);
    b.specular_reflectance = texture_ref(specular_reflectance);
    b.specular_transmittance = texture_ref(specular_transmittance);
    b.alpha = alpha;
    b.distribution = distribution(dist);
    b.eta = eta;
    b.nonlinear = nonlinear;
    auto check = [&](const TextureRef &t, bool needed, const char *what) {
        if (needed && !t.valid()) fail(type + " needs '" + what + "'");
        if (t.param >= int(scene.params.size()) || t.texture >= int(scene.textures.size()))
            fail(type + ": '" + what + "' refers to an unknown parameter or texture");
    };
    bool diffuse_input = b.type == BSDFType::Diffuse || b.type == BSDFType::RoughPlastic;
    check(b.reflectance, diffuse_input, "reflectance");
    check(b.specular_reflectance, !diffuse_input || b.type == BSDFType::RoughPlastic,
          "specular_reflectance");
    check(b.specular_transmittance, b.type == BSDFType::Dielectric, "specular_transmittance");
    bool rough = b.type == BSDFType::RoughConductor || b.type == BSDFType::RoughPlastic;
    if (rough && (alpha < 0 || alpha >= int(scene.params.size()))) fail(type + " needs 'alpha'");
    if ((b.type == BSDFType::Dielectric || b.type == BSDFType::RoughPlastic) && !(eta > 0.f))
        fail(type + ": eta must be positive");
    scene.bsdfs.push_back(b);
    return int(scene.bsdfs.size()) - 1;
}

int add_emitter(Scene &scene, const std::string &type, int param, int shape,
                const std::vector<float> &position) {
    if (param < 0 || param >= int(scene.params.size())) fail("emitter parameter out of range");
    Emitter e;
    e.radiance = param;
    if (type == "area") {
        if (shape < 0 || shape >= int(scene.geometry.shapes.size())) fail("area emitter needs a shape");
        if (scene.geometry.shapes[shape].emitter >= 0) fail("shape already has an emitter");
        e.type = EmitterType::Area;
        e.shape = shape;
        scene.geometry.shapes[shape].emitter = int(scene.emitters.size());
    } else if (type == "point") {
        e.type = EmitterType::Point;
        e.position = vec3(position, "point emitter position");
    } else if (type == "constant") {
        if (scene.environment >= 0) fail("only one constant emitter is supported");
        e.type = EmitterType::Constant;
        scene.environment = int(scene.emitters.size());
    } else {
        fail("unknown emitter type '" + type + "'");
    }
    scene.emitters.push_back(e);
    return int(scene.emitters.size()) - 1;
}

/// A texture's `to_uv` (a 2 x 3 affine map of uv, or empty for the identity).
void set_to_uv(Texture &tex, const std::vector<std::vector<float>> &to_uv) {
    if (to_uv.empty()) return;
    if (to_uv.size() != 2 || to_uv[0].size() != 3 || to_uv[1].size() != 3)
        fail("to_uv must be a 2 x 3 matrix");
    for (int r = 0; r < 2; ++r)
        for (int c = 0; c < 3; ++c) tex.to_uv[r][c] = to_uv[r][c];
    tex.has_to_uv = true;
}

int add_bitmap(Scene &scene, int param, int width, int height, int channels,
               const std::string &wrap, bool nearest,
               const std::vector<std::vector<float>> &to_uv) {
    if (param < 0 || param >= int(scene.params.size())) fail("bitmap parameter out of range");
    if (channels != 1 && channels != 3) fail("bitmaps must have 1 or 3 channels");
    if (int64_t(width) * height * channels != scene.params[param].numel)
        fail("bitmap size does not match its parameter '" + scene.params[param].name + "'");
    Bitmap bm;
    bm.param = param;
    bm.width = width;
    bm.height = height;
    bm.channels = channels;
    bm.nearest = nearest;
    if (wrap == "repeat") bm.wrap = WrapMode::Repeat;
    else if (wrap == "mirror") bm.wrap = WrapMode::Mirror;
    else if (wrap == "clamp") bm.wrap = WrapMode::Clamp;
    else fail("unknown wrap_mode '" + wrap + "' (supported: repeat, mirror, clamp)");
    Texture tex;
    tex.type = TextureType::Bitmap;
    tex.bitmap = bm;
    set_to_uv(tex, to_uv);
    scene.textures.push_back(tex);
    return int(scene.textures.size()) - 1;
}

int add_checkerboard(Scene &scene, int color0, int color1,
                     const std::vector<std::vector<float>> &to_uv) {
    for (int p : {color0, color1})
        if (p < 0 || p >= int(scene.params.size())) fail("checkerboard parameter out of range");
    Texture tex;
    tex.type = TextureType::Checkerboard;
    tex.checkerboard.color0 = color0;
    tex.checkerboard.color1 = color1;
    set_to_uv(tex, to_uv);
    scene.textures.push_back(tex);
    return int(scene.textures.size()) - 1;
}

}  // namespace

PYBIND11_MODULE(_C, m) {
    m.doc() = "torch_rbpt's C++ core";
    // The widest vector extension the extension was compiled for (benchmark headers).
#if defined(__AVX512F__)
    m.attr("build_isa") = "avx512";
#elif defined(__AVX2__)
    m.attr("build_isa") = "avx2";
#elif defined(__AVX__)
    m.attr("build_isa") = "avx";
#else
    m.attr("build_isa") = "sse2";
#endif
    // The -mtune it was compiled with where setup.py chose one (torch_rbpt/build_flags.py),
    // else "" (GCC's own for the target).
#ifndef RBPT_TUNE
#define RBPT_TUNE ""
#endif
    m.attr("build_tune") = RBPT_TUNE;
    py::class_<Scene>(m, "Scene")
        .def(py::init<>())
        .def("add_param",
             [](Scene &s, const std::string &name, int64_t numel) {
                 s.params.push_back({name, numel});
                 return int(s.params.size()) - 1;
             })
        .def("add_bitmap", &add_bitmap, py::arg("param"), py::arg("width"), py::arg("height"),
             py::arg("channels"), py::arg("wrap"), py::arg("nearest"),
             py::arg("to_uv") = std::vector<std::vector<float>>())
        .def("add_checkerboard", &add_checkerboard, py::arg("color0"), py::arg("color1"),
             py::arg("to_uv") = std::vector<std::vector<float>>())
        .def("add_bsdf", &add_bsdf, py::arg("type"), py::arg("twosided"), py::arg("reflectance"),
             py::arg("specular_reflectance"), py::arg("specular_transmittance"), py::arg("alpha"),
             py::arg("distribution"), py::arg("eta"), py::arg("nonlinear"))
        .def("add_mesh", &add_mesh, py::arg("positions"), py::arg("faces"), py::arg("normals"),
             py::arg("uvs"), py::arg("bsdf"), py::arg("flip_normals"))
        .def("add_sphere", &add_sphere)
        .def("add_disk_or_cylinder", &add_disk_or_cylinder)
        .def("set_mesh_attribute", &set_mesh_attribute)
        .def("add_emitter", &add_emitter)
        .def("build", [](Scene &s) {
            py::gil_scoped_release release;
            s.build();
        })
        .def_property_readonly("triangle_count",
                               [](const Scene &s) { return s.geometry.triangles.size(); })
        .def_property_readonly("bvh_node_count", [](const Scene &s) { return s.bvh.node_count(); })
        .def_property_readonly("bvh_flat", [](const Scene &s) { return s.bvh.flat(); })
        .def_property_readonly("bvh_two_phase", [](const Scene &s) { return s.bvh.two_phase(); })
        .def_property_readonly("bvh_quad_count", [](const Scene &s) { return s.bvh.quad_count(); })
        .def_property_readonly("bvh_sah_cost", [](const Scene &s) { return s.bvh.sah_cost(); })
        .def_property_readonly("shadow_primitive_count", [](const Scene &s) { return s.shadow_primitives; })
        .def("build_shadow_tree", [](Scene &s, bool cull) {
            py::gil_scoped_release release;
            s.build_shadow_tree(cull);
        }, py::arg("cull"));
    m.def("render_fwd", &render_image, py::arg("scene"), py::arg("camera"), py::arg("integrator"),
          py::arg("params"), py::arg("spp"), py::arg("seed"), py::arg("row_begin") = 0,
          py::arg("row_end") = -1);
    m.def("uses_wavefront", &uses_wavefront, py::arg("scene"), py::arg("camera"),
          py::arg("integrator"), py::arg("params"));
    m.def("render_bwd", [](const Scene &scene, const py::dict &camera, const py::dict &integrator,
                           const std::vector<torch::Tensor> &params, const std::vector<bool> &requires_grad,
                           torch::Tensor grad_image, int spp, uint64_t seed) {
              return render_bwd_entry(scene, camera, integrator, params, requires_grad, grad_image, spp, seed);
          }, py::arg("scene"), py::arg("camera"),
          py::arg("integrator"), py::arg("params"), py::arg("requires_grad"),
          py::arg("grad_image"), py::arg("spp"), py::arg("seed"));
    m.def("render_bwd_paths", &render_bwd_paths, py::arg("scene"), py::arg("camera"),
          py::arg("integrator"), py::arg("params"), py::arg("requires_grad"),
          py::arg("grad_image"), py::arg("spp"), py::arg("seed"),
          "render_bwd, and the numbers of paths it traced in lanes and with the tape.");
    m.def("render_jvp", &render_jvp_entry, py::arg("scene"), py::arg("camera"),
          py::arg("integrator"), py::arg("params"), py::arg("tangents"), py::arg("spp"),
          py::arg("seed"));
    m.def("bsdf_query", &bsdf_query);
    m.def("intersect_rays", &intersect_rays);
    m.def("interact_rays", &interact_rays);
    m.def("closest_hits", &closest_hits, py::arg("scene"), py::arg("origins"), py::arg("directions"),
          py::arg("tmin"), py::arg("tmax"), py::arg("columns"), py::arg("traversal") = false);
    m.def("occluded_rays", &occluded_rays, py::arg("scene"), py::arg("origins"), py::arg("directions"),
          py::arg("tmin"), py::arg("tmax"), py::arg("columns"), py::arg("traversal") = false,
          py::arg("masks") = false, py::arg("shadow") = false);
    m.def("sample_count", [](const py::dict &camera, int spp) {
        SamplerDesc s = make_sampler(camera);
        set_spp(s, spp);
        return int(s.sample_count);
    }, py::arg("camera"), py::arg("spp"),
          "The samples per pixel a render at `spp` takes: the sensor's sampler rounds it as "
          "Mitsuba's set_sample_count does (stratified to a square, ...).");
    m.def("sampler_points", &sampler_points, py::arg("camera"), py::arg("spp"), py::arg("seed"),
          py::arg("pixel"), py::arg("dims"), py::arg("lanes") = false);
    m.def("camera_rays", &camera_rays, py::arg("camera"), py::arg("positions"), py::arg("apertures"));
    m.def("filter_weights", &filter_weights, py::arg("camera"), py::arg("x0"), py::arg("n"));
}
