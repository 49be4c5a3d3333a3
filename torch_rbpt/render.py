"""Rendering entry points: `render` (differentiable), `render_forward` (forward-mode
derivative images), both calling the custom operators of `ops.py`."""
from __future__ import annotations

import numbers

import torch

from . import _C, ops
from .scene import Scene, Sensor

_SEED_GRAD_MIX = 0x5DEECE66D  # nonzero: a derived seed_grad never equals seed


def default_seed_grad(seed: int) -> int:
    """The backward pass's default seed: derived from `seed`, never equal to it."""
    return seed ^ _SEED_GRAD_MIX


def _check_seed(name: str, seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed < 2 ** 64:
        raise ValueError(f"{name} must be an int in [0, 2**64), got {seed!r}")
    return int(seed)


def _check_spp(name: str, spp) -> int:
    if isinstance(spp, bool) or not isinstance(spp, numbers.Integral) or spp <= 0:
        raise ValueError(f"{name} must be a positive int, got {spp!r}")
    return int(spp)


def _sensor_index(scene: Scene, sensor) -> int:
    """The index in scene.sensors of `sensor` (an index or one of the scene's Sensor objects),
    as Mitsuba's `render(scene, sensor=...)` takes it."""
    if isinstance(sensor, Sensor):
        for i, s in enumerate(scene.sensors):
            if s is sensor:
                return i
        raise ValueError("sensor: this Sensor object is not one of the scene's sensors")
    n = len(scene.sensors)
    if isinstance(sensor, bool) or not isinstance(sensor, numbers.Integral) or not -n <= sensor < n:
        raise ValueError(f"sensor must be an index into the scene's {n} sensor(s) or one of "
                         f"scene.sensors, got {sensor!r}")
    return int(sensor) % n


def _image_size(scene: Scene, sensor: int) -> tuple[int, int]:
    _, _, width, height = scene.sensors[sensor].film.crop_window()
    return height, width


class _Render(torch.autograd.Function):
    """Eager render: the forward is torch_rbpt::render, backward torch_rbpt::render_bwd (as the
    operator's registered autograd), jvp torch_rbpt::render_jvp on the forward's seed.

    torch.compile traces the operator itself instead (a custom jvp breaks its graph). Eager
    code keeps this Function: it adds forward mode and torch.func.grad, and concurrent
    backward passes through one image (examples/gradient_image.py) are safe here, where
    torch 2.13's register_autograd wrapper swaps ctx.needs_input_grad during backward."""

    generate_vmap_rule = True  # vmap goes through the operators' own vmap rules

    @staticmethod
    def forward(scene, sensor, height, width, spp, seed, spp_grad, seed_grad, *params):
        return ops.render(list(params), scene, sensor, height, width, spp, seed, spp_grad, seed_grad)

    @staticmethod
    def setup_context(ctx, inputs, output):
        scene, sensor, height, width, spp, seed, spp_grad, seed_grad, *params = inputs
        ctx.args = scene, sensor, height, width, spp, seed, spp_grad, seed_grad
        ctx.save_for_backward(*params)
        ctx.save_for_forward(*params)
        ctx.set_materialize_grads(False)

    @staticmethod
    def jvp(ctx, *tangents):
        scene, sensor, height, width, spp, seed, _, _ = ctx.args
        return ops.render_jvp(list(ctx.saved_tensors), list(tangents[8:]), scene, sensor, height,
                              width, spp, seed)

    @staticmethod
    def backward(ctx, grad_image):
        scene, sensor, height, width, _, _, spp_grad, seed_grad = ctx.args
        params = ctx.saved_tensors
        needs = list(ctx.needs_input_grad[8:])
        if grad_image is None or not any(needs):
            return (None,) * (8 + len(params))
        grads = iter(_RenderBwd.apply((scene, sensor, height, width, spp_grad, seed_grad), needs,
                                      grad_image, *params))
        return (None,) * 8 + tuple(next(grads) if n else None for n in needs)


class _RenderBwd(torch.autograd.Function):
    """torch_rbpt::render_bwd for _Render.backward: differentiating it (double backward, or
    forward mode through a gradient) is a clear error, also when only the parameters require
    grad."""

    generate_vmap_rule = True

    @staticmethod
    def forward(args, needs, grad_image, *params):
        return tuple(ops.render_bwd(list(params), grad_image, needs, *args))

    @staticmethod
    def setup_context(ctx, inputs, output):
        pass

    backward = staticmethod(ops.double_backward_error)
    jvp = staticmethod(ops.double_backward_error)


def render(scene: Scene, spp: int | None = None, seed: int = 0, spp_grad: int | None = None,
           seed_grad: int | None = None, rows: tuple[int, int] | None = None,
           sensor: int | Sensor = 0) -> torch.Tensor:
    """Render `scene` as seen by `sensor` (an index into `scene.sensors` or one of them;
    default the first): a (H, W, 3) linear RGB tensor of the parameters' dtype (H, W: that
    sensor's film's crop window).

    Differentiable with respect to every tensor of `scene.params` that requires grad.
    `spp` defaults to the scene sampler's sample_count. The backward pass traces `spp_grad`
    (default `spp`) independent paths with `seed_grad` (default: derived from `seed`, never
    equal to it), which keeps gradients of nonlinear losses unbiased. `seed_grad=seed`
    replays the forward samples exactly (what gradcheck and finite differences need; biased
    for nonlinear losses). The same seeds give bitwise the same image and gradients for a
    given thread count (the image: for any thread count). `rows=(begin, end)` renders a band
    of rows only (not differentiable).
    """
    sensor = _sensor_index(scene, sensor)
    spp = _check_spp("spp", scene.sensors[sensor].spp if spp is None else spp)
    seed = _check_seed("seed", seed)
    spp_grad = _check_spp("spp_grad", spp if spp_grad is None else spp_grad)
    seed_grad = _check_seed("seed_grad", default_seed_grad(seed) if seed_grad is None else seed_grad)
    params = scene.differentiable_inputs()
    if rows is not None:
        if torch.is_grad_enabled() and any(p.requires_grad for p in params):
            raise ValueError("rows= renders a band of an image and is not differentiable; "
                             "render the whole image or use torch.no_grad()")
        scene.check_fixed()
        return render_with_stats(scene, spp, seed, rows, sensor)[0]
    height, width = _image_size(scene, sensor)
    args = (scene._handle, sensor, height, width, spp, ops.signed_seed(seed), spp_grad,
            ops.signed_seed(seed_grad))
    if torch.compiler.is_compiling():
        return ops.render(params, *args)
    return _Render.apply(*args, *params)


def render_with_stats(scene: Scene, spp: int | None = None, seed: int = 0,
                      rows: tuple[int, int] | None = None,
                      sensor: int | Sensor = 0) -> tuple[torch.Tensor, int]:
    """Non-differentiable render that also returns the number of rays traced (camera,
    bounce and shadow rays)."""
    sensor = _sensor_index(scene, sensor)
    spp = _check_spp("spp", scene.sensors[sensor].spp if spp is None else spp)
    seed = _check_seed("seed", seed)
    begin, end = (0, -1) if rows is None else rows
    image, rays = _C.render_fwd(scene._native, scene.sensors[sensor].native(), scene.integrator.native(),
                                scene.param_list(), spp, seed, begin, end)
    return image, int(rays)


def render_forward(scene: Scene, tangents: dict, spp: int | None = None, seed: int = 0,
                   sensor: int | Sensor = 0) -> torch.Tensor:
    """Forward-mode derivative of the image along `tangents` ({key: tensor shaped like
    scene.params[key]}), rendered with dual numbers: a (H, W, 3) tensor of the parameters'
    dtype. With the same seed it is the exact derivative of `render(scene, spp, seed)`."""
    sensor = _sensor_index(scene, sensor)
    spp = _check_spp("spp", scene.sensors[sensor].spp if spp is None else spp)
    seed = _check_seed("seed", seed)
    scene.differentiable_inputs()  # checks fixed parameters (and the operator, edits)
    t = scene.tangent_list(tangents)
    height, width = _image_size(scene, sensor)
    return ops.render_jvp(scene.param_list(), t, scene._handle, sensor, height, width, spp,
                          ops.signed_seed(seed))
