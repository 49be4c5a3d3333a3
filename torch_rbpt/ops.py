"""The renderer as PyTorch custom operators: `torch.ops.torch_rbpt.render`, `render_bwd` and
`render_jvp`, with their fake (shape-only) implementations, autograd and vmap rules.

The scene reaches an operator as its parameter tensors (`Tensor[]`, in the scene's registry
order), a handle: an int naming a live `Scene` in this process (`register_scene`), whose
C++ scene, sensors and integrator the kernel reads when it runs, and the index of the sensor
to render from. The crop window's size is an
argument too, so fake tensors get the image's shape without the scene, and torch.compile
guards on it. Seeds are in [0, 2**64); they travel as int64 (`signed_seed`)."""
from __future__ import annotations

import itertools
import weakref

import torch
from torch import Tensor

from . import _C

_scenes: "weakref.WeakValueDictionary[int, object]" = weakref.WeakValueDictionary()
_handles = itertools.count(1)


def register_scene(scene) -> int:
    """A new handle for `scene` (valid while the scene lives)."""
    handle = next(_handles)
    _scenes[handle] = scene
    return handle


def _scene(handle: int, sensor: int, height: int, width: int):
    """The live scene of `handle` and its sensor number `sensor`, checked against the image
    size the operator was given."""
    scene = _scenes.get(handle)
    if scene is None:
        raise ValueError(f"torch_rbpt: no live scene has handle {handle} (handles belong to the "
                         f"process and the Scene object that made them)")
    if not 0 <= sensor < len(scene.sensors):
        raise ValueError(f"torch_rbpt: sensor {sensor} given to the operator, but the scene has "
                         f"{len(scene.sensors)} sensor(s)")
    s = scene.sensors[sensor]
    _, _, w, h = s.film.crop_window()
    if (h, w) != (height, width):
        raise ValueError(f"torch_rbpt: the image size {height}x{width} given to the operator is not "
                         f"the crop window of the scene's sensor {sensor}, {h}x{w}")
    scene.check_fixed()
    return scene, s


def signed_seed(seed: int) -> int:
    """A seed in [0, 2**64) as the int64 with the same bits (what the schema's int holds)."""
    return seed - 2 ** 64 if seed >= 2 ** 63 else seed


def _unsigned(seed: int) -> int:
    return seed % 2 ** 64


def _empty_image(params: list[Tensor], height: int, width: int) -> Tensor:
    return params[0].new_empty(height, width, 3) if params else torch.empty(height, width, 3)


# -- render: the image ----------------------------------------------------------------------

def _operator(schema: str):
    """Define torch_rbpt::<name> with `schema` and register the decorated function as its CPU
    kernel; returns the operator. (torch.library.define + impl rather than custom_op: a
    custom_op's kernel is wrapped to disable torch.compile inside it, which imports
    torch._dynamo, over a second and 70 MB, at the first eager call. Dynamo never traces
    into these kernels: it records the operator as one opaque call.)"""
    name = schema[:schema.index("(")]

    def register(kernel):
        torch.library.define(f"torch_rbpt::{name}", schema[len(name):], lib=_LIB)
        torch.library.impl(f"torch_rbpt::{name}", "cpu", kernel, lib=_LIB)
        return getattr(torch.ops.torch_rbpt, name).default

    return register


_LIB = torch.library.Library("torch_rbpt", "DEF")


@_operator("render(Tensor[] params, SymInt scene, SymInt sensor, SymInt height, SymInt width, "
           "SymInt spp, SymInt seed, SymInt spp_grad, SymInt seed_grad) -> Tensor")
def render(params: list[Tensor], scene: int, sensor: int, height: int, width: int, spp: int,
           seed: int, spp_grad: int, seed_grad: int) -> Tensor:
    """The (height, width, 3) image of scene `scene` seen by its sensor `sensor`, with
    parameter values `params`. `spp_grad` and `seed_grad` are the backward pass's."""
    s, camera = _scene(scene, sensor, height, width)
    values = [p.contiguous() for p in params]
    image, _ = _C.render_fwd(s._native, camera.native(), s.integrator.native(), values, spp,
                             _unsigned(seed), 0, -1)
    return image


@torch.library.register_fake("torch_rbpt::render", lib=_LIB)
def _(params, scene, sensor, height, width, spp, seed, spp_grad, seed_grad):
    return _empty_image(params, height, width)


# -- render_bwd: radiative backpropagation ----------------------------------------------------

@_operator("render_bwd(Tensor[] params, Tensor grad_image, bool[] needs_grad, SymInt scene, "
           "SymInt sensor, SymInt height, SymInt width, SymInt spp, SymInt seed) -> Tensor[]")
def render_bwd(params: list[Tensor], grad_image: Tensor, needs_grad: list[bool], scene: int,
               sensor: int, height: int, width: int, spp: int, seed: int) -> list[Tensor]:
    """Gradients of sum(grad_image * image) with respect to the parameters flagged in
    `needs_grad` (only those: one tensor shaped like each), from `spp` paths per pixel
    traced with `seed`."""
    s, camera = _scene(scene, sensor, height, width)
    values = [p.contiguous() for p in params]
    grads = _C.render_bwd(s._native, camera.native(), s.integrator.native(), values,
                          list(needs_grad), grad_image, spp, _unsigned(seed))
    return [g.view_as(p) for g, p, n in zip(grads, params, needs_grad) if n]


@torch.library.register_fake("torch_rbpt::render_bwd", lib=_LIB)
def _(params, grad_image, needs_grad, scene, sensor, height, width, spp, seed):
    return [torch.empty_like(p) for p, n in zip(params, needs_grad) if n]


def double_backward_error(ctx, *grads):
    raise RuntimeError("torch_rbpt: render's gradients are not differentiable (no double "
                       "backward, no forward-mode derivative of a gradient); differentiate "
                       "render once, by reverse mode or by render_forward")


torch.library.register_autograd("torch_rbpt::render_bwd", double_backward_error, lib=_LIB)


# -- render_jvp: forward mode -------------------------------------------------------------------

@_operator("render_jvp(Tensor[] params, Tensor?[] tangents, SymInt scene, SymInt sensor, "
           "SymInt height, SymInt width, SymInt spp, SymInt seed) -> Tensor")
def render_jvp(params: list[Tensor], tangents: list[Tensor | None], scene: int, sensor: int,
               height: int, width: int, spp: int, seed: int) -> Tensor:
    """The derivative of render(params, ..., spp, seed) along `tangents` (one per parameter,
    None for zero), rendered with dual numbers."""
    s, camera = _scene(scene, sensor, height, width)
    values = [p.contiguous() for p in params]
    t = [None if x is None else x.contiguous() for x in tangents]
    _, derivative = _C.render_jvp(s._native, camera.native(), s.integrator.native(), values, t,
                                  spp, _unsigned(seed))
    return derivative


@torch.library.register_fake("torch_rbpt::render_jvp", lib=_LIB)
def _(params, tangents, scene, sensor, height, width, spp, seed):
    return _empty_image(params, height, width)


# -- autograd: independent adjoint paths ----------------------------------------------------------

def _setup_context(ctx, inputs, output):
    params, scene, sensor, height, width, spp, seed, spp_grad, seed_grad = inputs
    ctx.save_for_backward(*params)
    ctx.args = scene, sensor, height, width, spp_grad, seed_grad


def _backward(ctx, grad_image):
    params = list(ctx.saved_tensors)
    needs = list(ctx.needs_input_grad[0])
    return (param_grads(params, grad_image, needs, *ctx.args),) + (None,) * 8


def param_grads(params, grad_image, needs, scene, sensor, height, width, spp_grad, seed_grad) -> list:
    """One gradient per parameter (None where `needs` is False or grad_image is None)."""
    if grad_image is None or not any(needs):
        return [None] * len(params)
    grads = iter(render_bwd(params, grad_image, needs, scene, sensor, height, width, spp_grad, seed_grad))
    return [next(grads) if n else None for n in needs]


torch.library.register_autograd("torch_rbpt::render", _backward, setup_context=_setup_context, lib=_LIB)


# -- vmap: one call per batch entry ----------------------------------------------------------------

def _loop_vmap(op):
    """A vmap rule calling `op` once per batch entry and stacking the results along dim 0."""

    def select(x, dim, b):
        if isinstance(x, (list, tuple)):
            dims = dim if isinstance(dim, (list, tuple)) else [dim] * len(x)
            return [select(xi, di, b) for xi, di in zip(x, dims)]
        return x if dim is None or not isinstance(x, Tensor) else x.select(dim, b)

    def rule(info, in_dims, *args):
        outs = [op(*[select(a, d, b) for a, d in zip(args, in_dims)]) for b in range(info.batch_size)]
        if isinstance(outs[0], Tensor):
            return torch.stack(outs), 0
        stacked = [torch.stack(column) for column in zip(*outs)]
        return stacked, [0] * len(stacked)

    return rule


for _op in (render, render_bwd, render_jvp):
    torch.library.register_vmap(_op, _loop_vmap(_op), lib=_LIB)
