"""Shared fixtures: paths to the public scenes and small scenes built in code."""
import contextlib
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import torch_rbpt as tr
from torch_rbpt import build_flags

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "scenes"
REFERENCES = Path(__file__).resolve().parent / "references"


def load_module(folder: str, name: str):
    """Import <folder>/<name>.py of the repository as a module, with its folder on sys.path
    (for the helpers the examples and benchmarks share)."""
    path = ROOT / folder
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))
    spec = importlib.util.spec_from_file_location(name, path / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_example(name: str):
    """Import examples/<name>.py as a module."""
    return load_module("examples", name)


def load_benchmark(name: str):
    """Import benchmarks/<name>.py as a module."""
    return load_module("benchmarks", name)


def bsdf_scene(bsdf: dict, dtype=torch.float32):
    """A scene holding one BSDF (native index 0), for direct BSDF queries."""
    return tr.load_dict({"type": "scene", "mat": bsdf}, dtype=dtype)


def query_bsdf(scene, wi, wo=None, u1=None, u2=None, index=0, uv=None):
    """Evaluate/sample BSDF `index` of `scene` for local directions.
    Returns (eval (N,3), pdf (N,), sampled wo (N,3), sampled pdf (N,), weight (N,3), delta (N,))."""
    wi = torch.as_tensor(wi, dtype=torch.float32).reshape(-1, 3)
    n = wi.shape[0]
    wo = wi if wo is None else torch.as_tensor(wo, dtype=torch.float32).reshape(-1, 3)
    u1 = torch.full((n,), 0.5) if u1 is None else u1
    u2 = torch.full((n, 2), 0.5) if u2 is None else u2
    uv = torch.full((n, 2), 0.5) if uv is None else torch.as_tensor(uv, dtype=torch.float32).reshape(-1, 2)
    return tr._C.bsdf_query(scene._native, scene.param_list(), index, wi, wo, u1, u2, uv)


def furnace_scene(albedo: float, res: int = 8, dtype=torch.float32, max_depth: int = -1):
    """A diffuse unit sphere of the given albedo inside a uniform white environment."""
    return tr.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": tr.Transform.look_at([0, 0, 5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}}},
        "ball": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": albedo}},
        "sky": {"type": "constant", "radiance": 1.0},
    }, dtype=dtype)


@pytest.fixture
def shared():
    if not SHARED.exists():
        pytest.skip(f"shared scenes not found at {SHARED}")
    return SHARED


def directional_derivatives(scene, key: str, w, direction, spp: int, n_seeds: int,
                            h: float | None = None, forward_seed: int | None = None) -> dict:
    """Samples of the derivative of the linear loss sum(w * render(scene)) along `direction`
    in parameter `key`, one per seed s < n_seeds, as float64 tensors:
    - "backward": reverse mode, rendered with seed s (and its own, independent backward seed);
    - "fd" (with step h): the central difference (p + h direction, p - h direction), both
      sides rendered with seed 1000 + s (common random numbers);
    - "forward" (with forward_seed): forward mode with seed forward_seed + s.
    The parameter's value is restored afterwards."""
    p = scene.params[key].detach().clone()
    out = {"backward": []}
    if h is not None:
        out["fd"] = []
    if forward_seed is not None:
        out["forward"] = []
    for s in range(n_seeds):
        x = p.clone().requires_grad_()
        scene.params[key] = x
        (grad,) = torch.autograd.grad((w * tr.render(scene, spp=spp, seed=s)).sum(), [x])
        out["backward"].append(float((grad * direction).sum()))
        scene.params[key] = p.clone()
        with torch.no_grad():
            if forward_seed is not None:
                d = tr.render_forward(scene, {key: direction}, spp=spp, seed=forward_seed + s)
                out["forward"].append(float((w * d).sum()))
            if h is not None:
                scene.params[key] = p + h * direction
                up = (w * tr.render(scene, spp=spp, seed=1000 + s)).sum()
                scene.params[key] = p - h * direction
                down = (w * tr.render(scene, spp=spp, seed=1000 + s)).sum()
                out["fd"].append(float((up - down) / (2 * h)))
        scene.params[key] = p.clone()
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in out.items()}


@contextlib.contextmanager
def torch_threads(n: int):
    """Run the block with torch's intra-op pool at n threads, restoring the count after."""
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def l2_gradient_samples(scene, key: str, spp: int, n: int, mean_spp: int):
    """The bias experiment of an L2 loss |I - T|^2 against T = half the mean image: returns
    the exact gradient d/d(first channel of `key`) of |E[I] - T|^2 (from renders at
    `mean_spp`, seeds 99 and 98) and n gradient samples each (render seed s < n, `spp`) with
    the backward pass replaying the forward samples and with independent backward samples,
    as tensors in the parameter's dtype. The parameter is restored afterwards."""
    p = scene.params[key]
    dtype = p.dtype
    with torch.no_grad():
        mean_image = tr.render(scene, spp=mean_spp, seed=99)
        dmean = tr.render_forward(scene, {key: torch.tensor([1.0, 0, 0], dtype=dtype)}, spp=mean_spp, seed=98)
    target = 0.5 * mean_image
    expected = float((2 * (mean_image - target) * dmean).sum())  # d/dp_r of |E[I] - T|^2
    replay, independent = [], []
    for s in range(n):
        x = p.detach().clone().requires_grad_()
        scene.params[key] = x
        for out, seed_grad in ((replay, s), (independent, None)):
            image = tr.render(scene, spp=spp, seed=s, seed_grad=seed_grad)
            (g,) = torch.autograd.grad(((image - target) ** 2).sum(), [x])
            out.append(float(g[0]))
    scene.params[key] = p.detach()
    return expected, torch.tensor(replay, dtype=dtype), torch.tensor(independent, dtype=dtype)


# setup.py's optimised flags, without the target (the caller chooses it).
OPT_FLAGS = ["-std=c++17", "-fopenmp", "-fwrapv", *build_flags.OPTIMISED]


def uninstrumented_env() -> dict:
    """This process's environment without LD_PRELOAD, for the compiler and the standalone
    programs the tests build: under `make test SANITIZE=1` it preloads the sanitizer
    runtimes, which are for the (uninstrumented) Python process alone."""
    return {k: v for k, v in os.environ.items() if k != "LD_PRELOAD"}


def assert_marked_loops_vectorise(source: str, pragma: str, march: str, tmp_path: Path) -> int:
    """Compile csrc/`source` for `march` with GCC's vectoriser report and assert that the loop
    after each `pragma` line vectorises in every template instance (an edit that stops GCC, a
    helper it no longer inlines, keeps results bitwise equal and only makes them slower, which
    no other test sees). Returns the number of such loops."""
    path = ROOT / "csrc" / source
    lines = path.read_text().splitlines()
    # (Loops marked `pragma  // without AVX2` are compiled only where the intrinsics beside
    # them are not, for a target without AVX2, and are not counted.)
    loops = [i + 2 for i, line in enumerate(lines) if line.strip() == pragma]  # the for's line
    out = subprocess.run(["g++", *OPT_FLAGS, *build_flags.target_flags(march), f"-I{ROOT / 'csrc'}", "-c", str(path),
                          "-o", str(tmp_path / "marked.o"), "-fopt-info-vec-all"],
                         capture_output=True, text=True, check=True, env=uninstrumented_env()).stderr.splitlines()
    for line in loops:
        at = [entry for entry in out if f"{source}:{line}:" in entry]
        assert any("loop vectorized" in entry for entry in at), f"line {line}: {lines[line - 1].strip()}"
        assert not any("couldn't vectorize loop" in entry for entry in at), \
            f"line {line} ({lines[line - 1].strip()}) not vectorised in some instance:\n" + \
            "\n".join(entry for entry in at if "missed" in entry)[:3000]
    return len(loops)
