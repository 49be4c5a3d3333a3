"""The loaded scene: its parameters (live torch tensors keyed by Mitsuba's traverse keys),
its sensor and film, its integrator settings, and the C++ scene they feed. Scenes pickle and
deep-copy: the C++ scene is rebuilt from the calls that built it."""
from __future__ import annotations

from collections.abc import MutableMapping
from dataclasses import dataclass, field

import numpy as np
import torch

from . import _C, ops


class SceneParams(MutableMapping):
    """Dict-like view of the differentiable parameters of a scene.

    Keys are Mitsuba's `mi.traverse` keys (`red.reflectance.value`, `tex.reflectance.data`);
    values are the tensors the renderer reads: RGB values have shape (3,), scalars (1,),
    bitmaps (H, W, C). Editing a tensor in place changes the next render. Assigning a new
    tensor checks its shape, dtype and device; keys cannot be added or removed.
    """

    def __init__(self, tensors: dict[str, torch.Tensor], fixed: dict[str, str] | None = None):
        self._tensors = tensors
        # Keys Mitsuba exposes that we cannot differentiate or edit (geometry, IORs), with why.
        self._fixed = fixed or {}
        self._fixed_versions = {k: tensors[k]._version for k in self._fixed}

    def __getitem__(self, key: str) -> torch.Tensor:
        try:
            return self._tensors[key]
        except KeyError:
            raise KeyError(f"no scene parameter '{key}' (available: {', '.join(self._tensors)})") from None

    def __setitem__(self, key: str, value) -> None:
        old = self[key]
        if key in self._fixed:
            raise ValueError(f"scene parameter '{key}' cannot be changed: {self._fixed[key]}")
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"scene parameter '{key}' must be a torch.Tensor, got {type(value).__name__}")
        if value.shape != old.shape:
            raise ValueError(f"scene parameter '{key}' must have shape {tuple(old.shape)}, got {tuple(value.shape)}")
        if value.dtype != old.dtype:
            raise ValueError(f"scene parameter '{key}' must have dtype {old.dtype}, got {value.dtype}")
        if value.device.type != "cpu":
            raise ValueError(f"scene parameter '{key}' must be on the CPU, got device {value.device}")
        self._tensors[key] = value

    def __delitem__(self, key: str) -> None:
        raise TypeError("scene parameters cannot be removed")

    def __iter__(self):
        return iter(self._tensors)

    def __len__(self) -> int:
        return len(self._tensors)

    def __getstate__(self) -> dict:
        # Tensor versions restart at 0 in a copy: keep which fixed parameters were edited.
        edited = [k for k in self._fixed if self._tensors[k]._version != self._fixed_versions[k]]
        return {"tensors": self._tensors, "fixed": self._fixed, "edited": edited}

    def __setstate__(self, state: dict) -> None:
        self._tensors, self._fixed = state["tensors"], state["fixed"]
        self._fixed_versions = {k: -1 if k in state["edited"] else self._tensors[k]._version
                                for k in self._fixed}

    def __repr__(self) -> str:
        rows = [f"  {k}: {tuple(v.shape)} {str(v.dtype).replace('torch.', '')}" for k, v in self._tensors.items()]
        return "SceneParams(\n" + "\n".join(rows) + "\n)"


@dataclass
class Film:
    """`hdrfilm`: size in pixels, crop window and reconstruction filter (`filter` is the
    rfilter's type; "catmullrom" is evaluated as mitchell with B = 0, C = 1/2)."""
    width: int = 768
    height: int = 576
    crop: tuple[int, int, int, int] | None = None  # (x, y, width, height); None: full film
    filter: str = "gaussian"
    filter_radius: float = 2.0
    filter_stddev: float = 0.5
    filter_b: float = 1 / 3  # mitchell's B and C (catmullrom: 0 and 1/2)
    filter_c: float = 1 / 3
    filter_lobes: int = 3  # lanczos
    pixel_format: str = "rgb"  # as given in the scene; render() always returns linear RGB

    def crop_window(self) -> tuple[int, int, int, int]:
        return self.crop if self.crop is not None else (0, 0, self.width, self.height)


@dataclass
class Sensor:
    """`perspective`, `orthographic` or `thinlens` sensor, with its film and sampler.

    `fov` (perspective, thinlens) is along `fov_axis`, resolved against the film's aspect
    ratio at render time (so changing the film size keeps Mitsuba's meaning). Orthographic:
    `to_world`'s scale gives the viewed region, [-1, 1] x [-1/aspect, 1/aspect] in local
    units. Thinlens: `aperture_radius` and `focus_distance` (default: `far_clip`).
    `sampler` is Mitsuba's sampler plugin name; `spp` its sample_count, rounded at render
    time as the sampler rounds it (stratified: to a square, ...); `jitter` its jitter flag."""
    type: str = "perspective"
    to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    fov: float = 46.793003  # Mitsuba's default 50 mm lens: diagonal fov of a 36 x 24 mm film
    fov_axis: str = "diagonal"
    near_clip: float = 1e-2
    far_clip: float = 1e4
    aperture_radius: float = 0.0
    focus_distance: float = 1e4
    film: Film = field(default_factory=Film)
    sampler: str = "independent"
    spp: int = 4
    seed: int = 0
    jitter: bool = True

    def x_fov(self) -> float:
        """Horizontal field of view in degrees, as Mitsuba's parse_fov computes it."""
        aspect = self.film.width / self.film.height
        axis = self.fov_axis
        if axis == "smaller":
            axis = "y" if aspect > 1 else "x"
        elif axis == "larger":
            axis = "x" if aspect > 1 else "y"
        half = np.tan(np.radians(self.fov) / 2)
        if axis == "x":
            return self.fov
        if axis == "y":
            return float(np.degrees(2 * np.arctan(half * aspect)))
        # diagonal
        width = 2 * half / np.sqrt(1 + 1 / aspect ** 2)
        return float(np.degrees(2 * np.arctan(width / 2)))

    def sample_count(self, spp: int | None = None) -> int:
        """The samples per pixel a render at `spp` (default: this sensor's `spp`) takes, as
        the sampler rounds it: stratified to a square, multijitter to rows x columns,
        orthogonal to a prime's square, ldsampler to a power of 4; independent keeps it."""
        return _C.sample_count(self.native(), int(self.spp if spp is None else spp))

    def native(self) -> dict:
        f = self.film
        catmullrom = f.filter == "catmullrom"
        return {"to_world": self.to_world.tolist(), "fov_x": self.x_fov(), "width": f.width,
                "height": f.height, "near_clip": self.near_clip, "far_clip": self.far_clip,
                "crop": list(f.crop_window()), "filter": "mitchell" if catmullrom else f.filter,
                "filter_radius": f.filter_radius, "filter_stddev": f.filter_stddev,
                "filter_b": 0.0 if catmullrom else f.filter_b,
                "filter_c": 0.5 if catmullrom else f.filter_c, "filter_lobes": f.filter_lobes,
                "type": self.type, "aperture_radius": self.aperture_radius,
                "focus_distance": self.focus_distance, "sampler": self.sampler,
                "sampler_jitter": self.jitter}


@dataclass
class Integrator:
    """`path`/`prb` or `direct`, with Mitsuba's parameters and defaults."""
    type: str = "path"
    max_depth: int = -1
    rr_depth: int = 5
    emitter_samples: int = 1
    bsdf_samples: int = 1
    hide_emitters: bool = False

    def native(self) -> dict:
        return {"type": "direct" if self.type == "direct" else "path", "max_depth": self.max_depth,
                "rr_depth": self.rr_depth, "emitter_samples": self.emitter_samples,
                "bsdf_samples": self.bsdf_samples, "hide_emitters": self.hide_emitters}


class NativeScene:
    """Builds a C++ scene (`_C.Scene`) and records the calls that built it, so that a copy
    can replay them (the build is deterministic: the copy renders bitwise alike)."""

    def __init__(self):
        self.scene = _C.Scene()
        self.calls: list[tuple[str, tuple]] = []

    def add(self, what: str, *args) -> int:
        """`scene.add_<what>(*args)` (param, bitmap, checkerboard, bsdf, mesh, sphere, disk,
        cylinder, emitter, ...)."""
        return self.call(f"add_{what}", *args)

    def set_mesh_attribute(self, *args) -> None:
        """`scene.set_mesh_attribute(shape, which, param, channels)`."""
        self.call("set_mesh_attribute", *args)

    def call(self, method: str, *args):
        result = getattr(self.scene, method)(*args)
        self.calls.append((method, args))
        return result

    def build(self) -> "_C.Scene":
        self.scene.build()
        return self.scene

    @classmethod
    def replay(cls, calls: list) -> "_C.Scene":
        native = cls()
        for method, args in calls:
            native.call(method, *args)
        return native.build()


class Scene:
    """A loaded scene. Create with `torch_rbpt.load_file` or `torch_rbpt.load_dict`.

    `scene.sensors` lists its sensors in the order the file declares them (as Mitsuba's
    `scene.sensors()`); `scene.sensor` is the first. Scenes pickle and deep-copy (parameters
    with their current values and requires_grad, sensors, integrator); a copy renders bitwise
    the same images."""

    def __init__(self, native: NativeScene, params: dict[str, torch.Tensor],
                 sensors: "Sensor | list[Sensor]", integrator: Integrator, source: str = "<dict>",
                 fixed: dict | None = None):
        self._native = native.build()
        self._calls = native.calls
        self._handle = ops.register_scene(self)  # names the scene to the custom operators
        self._keys = list(params)  # order of the C++ parameter registry
        fixed = fixed or {}
        self.params = SceneParams({**params, **{k: v for k, (v, _) in fixed.items()}},
                                  {k: why for k, (_, why) in fixed.items()})
        self.sensors = [sensors] if isinstance(sensors, Sensor) else list(sensors)
        if not self.sensors:
            self.sensors = [Sensor()]
        self.integrator = integrator
        self.source = source

    @property
    def sensor(self) -> Sensor:
        """The first sensor (the one `render` uses by default)."""
        return self.sensors[0]

    @sensor.setter
    def sensor(self, value: Sensor) -> None:
        self.sensors[0] = value

    @property
    def dtype(self) -> torch.dtype:
        """dtype of the parameters, and so of rendered images."""
        return self.params[self._keys[0]].dtype if self._keys else torch.float32

    def to(self, dtype: torch.dtype) -> "Scene":
        """Convert all parameters to float32 or float64 (in place); returns the scene."""
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"scene dtype must be torch.float32 or torch.float64, got {dtype}")
        p = self.params
        for k in list(p._tensors):
            p._tensors[k] = p._tensors[k].detach().to(dtype)
        p._fixed_versions = {k: p._tensors[k]._version for k in p._fixed}
        return self


    def differentiable_inputs(self) -> list[torch.Tensor]:
        """The parameter tensors in registry order (what render() differentiates), after
        checking that no fixed parameter (geometry, IOR) is marked for gradients."""
        p = self.params
        for k, why in p._fixed.items():
            if p._tensors[k].requires_grad:
                raise ValueError(f"scene parameter '{k}' cannot be differentiated: {why}")
        return [p._tensors[k] for k in self._keys]

    def check_fixed(self) -> None:
        """Check that no fixed parameter was edited in place. The operators call it when they
        run (a tensor's version is runtime state, which torch.compile cannot guard on)."""
        p = self.params
        for k, why in p._fixed.items():
            if p._tensors[k]._version != p._fixed_versions[k]:
                raise ValueError(f"scene parameter '{k}' was edited, which is not supported: {why}")

    def tangent_list(self, tangents: dict) -> list:
        """Tangents in registry order for render_forward (None where absent), checked."""
        out = []
        for k in tangents:
            if k not in self.params:
                raise KeyError(f"no scene parameter '{k}' (available: {', '.join(self._keys)})")
            if k in self.params._fixed:
                raise ValueError(f"scene parameter '{k}' cannot be differentiated: {self.params._fixed[k]}")
        for k in self._keys:
            t = tangents.get(k)
            if t is not None:
                t = torch.as_tensor(t, dtype=self.dtype)
                if t.shape != self.params[k].shape:
                    raise ValueError(f"tangent of '{k}' must have shape {tuple(self.params[k].shape)}, got {tuple(t.shape)}")
                t = t.contiguous()
            out.append(t)
        return out

    def param_list(self) -> list[torch.Tensor]:
        """Parameter tensors in registry order (detached, contiguous) for the C++ core."""
        out = []
        dtype = self.dtype
        for k in self._keys:
            t = self.params[k]
            if t.dtype != dtype:
                raise ValueError(f"scene parameter '{k}' has dtype {t.dtype} but the scene is "
                                 f"{dtype}: all parameters must share one dtype")
            out.append(t.detach().contiguous())
        return out

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("_native", "_handle")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._native = NativeScene.replay(self._calls)
        self._handle = ops.register_scene(self)

    def __repr__(self) -> str:
        f = self.sensor.film
        return (f"Scene('{self.source}', {f.width}x{f.height}, {self._native.triangle_count} triangles, "
                f"{len(self.params)} parameters, integrator={self.integrator.type})")
