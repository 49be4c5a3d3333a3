"""Rendering entry points."""
from __future__ import annotations

import torch

from . import _C
from .scene import Scene


def render(scene: Scene, spp: int | None = None, seed: int = 0, rows: tuple[int, int] | None = None) -> torch.Tensor:
    """Render `scene` and return a (H, W, 3) linear RGB tensor of the parameters' dtype.

    H, W are the film's crop window. `spp` defaults to the scene sampler's `sample_count`.
    The same `seed` gives a bitwise identical image whatever the thread count. `rows`
    renders only that band (begin, end) of the crop window's rows, identical to the same
    rows of a full render.
    """
    return render_with_stats(scene, spp, seed, rows)[0]


def render_with_stats(scene: Scene, spp: int | None = None, seed: int = 0,
                      rows: tuple[int, int] | None = None) -> tuple[torch.Tensor, int]:
    """`render`, also returning the number of rays traced (camera, bounce and shadow rays)."""
    spp = scene.sensor.spp if spp is None else int(spp)
    if spp <= 0:
        raise ValueError(f"spp must be positive, got {spp}")
    if not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    begin, end = (0, -1) if rows is None else rows
    image, rays = _C.render_fwd(scene._native, scene.sensor.native(), scene.integrator.native(),
                                scene.param_list(), spp, seed, begin, end)
    return image, int(rays)
