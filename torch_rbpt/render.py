"""Rendering entry points: `render` (differentiable), `render_forward` (forward-mode
derivative images) and the `_Render` autograd.Function that connects them to torch."""
from __future__ import annotations

import numbers

import torch

from . import _C
from .scene import Scene

_SEED_GRAD_MIX = 0x5DEECE66D  # nonzero: a derived seed_grad never equals seed


def _plain(x: torch.Tensor) -> torch.Tensor:
    """The underlying tensor of a torch.func (functorch) wrapper, which has no storage of its
    own for the C++ core to read; plain tensors pass through."""
    from torch._C._functorch import get_unwrapped, is_functorch_wrapped_tensor
    while is_functorch_wrapped_tensor(x):
        x = get_unwrapped(x)
    return x


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


class _Render(torch.autograd.Function):
    """image = render(params). Forward renders with `seed` and saves only the parameters;
    backward re-traces `spp_grad` paths with `seed_grad` carrying the image adjoint
    (radiative backpropagation); jvp renders with dual numbers."""

    @staticmethod
    def forward(scene, camera, integrator, spp, seed, spp_grad, seed_grad, *params):
        values = [p.detach().contiguous() for p in params]
        image, _ = _C.render_fwd(scene._native, camera, integrator, values, spp, seed, 0, -1)
        return image

    @staticmethod
    def setup_context(ctx, inputs, output):
        scene, camera, integrator, spp, seed, spp_grad, seed_grad, *params = inputs
        ctx.scene, ctx.camera, ctx.integrator = scene, camera, integrator
        ctx.spp, ctx.seed, ctx.spp_grad, ctx.seed_grad = spp, seed, spp_grad, seed_grad
        ctx.save_for_backward(*params)
        # For jvp: detached views of the values (no copy). Saved tensors come back wrapped
        # under torch.func transforms, where the C++ core needs plain storage.
        ctx.values = [p.detach() for p in params]
        ctx.set_materialize_grads(False)

    @staticmethod
    def backward(ctx, grad_image):
        params = ctx.saved_tensors
        needs = list(ctx.needs_input_grad[7:])
        if grad_image is None or not any(needs):
            return (None,) * (7 + len(params))
        values = [p.detach().contiguous() for p in params]
        grads = _C.render_bwd(ctx.scene._native, ctx.camera, ctx.integrator, values, needs,
                              grad_image, ctx.spp_grad, ctx.seed_grad)
        return (None,) * 7 + tuple(None if g is None else g.view_as(p) for g, p in zip(grads, params))

    @staticmethod
    def jvp(ctx, *tangents):
        t = [None if x is None else _plain(x.detach()).contiguous() for x in tangents[7:]]
        values = [_plain(p).contiguous() for p in ctx.values]
        _, derivative = _C.render_jvp(ctx.scene._native, ctx.camera, ctx.integrator, values, t,
                                      ctx.spp, ctx.seed)
        return derivative


def render(scene: Scene, spp: int | None = None, seed: int = 0, spp_grad: int | None = None,
           seed_grad: int | None = None, rows: tuple[int, int] | None = None) -> torch.Tensor:
    """Render `scene`: a (H, W, 3) linear RGB tensor of the parameters' dtype (H, W: the
    film's crop window).

    Differentiable with respect to every tensor of `scene.params` that requires grad.
    `spp` defaults to the scene sampler's sample_count. The backward pass traces `spp_grad`
    (default `spp`) independent paths with `seed_grad` (default: derived from `seed`, never
    equal to it), which keeps gradients of nonlinear losses unbiased. `seed_grad=seed`
    replays the forward samples exactly (what gradcheck and finite differences need; biased
    for nonlinear losses). The same seeds give bitwise the same image and gradients for a
    given thread count (the image: for any thread count). `rows=(begin, end)` renders a band
    of rows only (not differentiable).
    """
    spp = _check_spp("spp", scene.sensor.spp if spp is None else spp)
    seed = _check_seed("seed", seed)
    spp_grad = _check_spp("spp_grad", spp if spp_grad is None else spp_grad)
    seed_grad = _check_seed("seed_grad", default_seed_grad(seed) if seed_grad is None else seed_grad)
    params = scene.differentiable_inputs()
    if rows is not None:
        if torch.is_grad_enabled() and any(p.requires_grad for p in params):
            raise ValueError("rows= renders a band of an image and is not differentiable; "
                             "render the whole image or use torch.no_grad()")
        return render_with_stats(scene, spp, seed, rows)[0]
    return _Render.apply(scene, scene.sensor.native(), scene.integrator.native(), spp, seed,
                         spp_grad, seed_grad, *params)


def render_with_stats(scene: Scene, spp: int | None = None, seed: int = 0,
                      rows: tuple[int, int] | None = None) -> tuple[torch.Tensor, int]:
    """Non-differentiable render that also returns the number of rays traced (camera,
    bounce and shadow rays)."""
    spp = _check_spp("spp", scene.sensor.spp if spp is None else spp)
    seed = _check_seed("seed", seed)
    begin, end = (0, -1) if rows is None else rows
    image, rays = _C.render_fwd(scene._native, scene.sensor.native(), scene.integrator.native(),
                                scene.param_list(), spp, seed, begin, end)
    return image, int(rays)


def render_forward(scene: Scene, tangents: dict, spp: int | None = None, seed: int = 0) -> torch.Tensor:
    """Forward-mode derivative of the image along `tangents` ({key: tensor shaped like
    scene.params[key]}), rendered with dual numbers: a (H, W, 3) tensor of the parameters'
    dtype. With the same seed it is the exact derivative of `render(scene, spp, seed)`."""
    spp = _check_spp("spp", scene.sensor.spp if spp is None else spp)
    seed = _check_seed("seed", seed)
    scene.differentiable_inputs()  # checks fixed parameters
    t = scene.tangent_list(tangents)
    _, derivative = _C.render_jvp(scene._native, scene.sensor.native(), scene.integrator.native(),
                                  scene.param_list(), t, spp, seed)
    return derivative
