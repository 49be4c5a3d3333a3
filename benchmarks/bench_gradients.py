"""Gradient benchmark: backward (radiative backpropagation) against forward rendering at
equal spp on the shared cbox, peak memory of a forward + backward pass at two spp, and what
a new roughplastic roughness costs (ours and Mitsuba 3's, when installed).

    python benchmarks/bench_gradients.py [--res 256] [--spp 16] [--no-mitsuba]

Differentiated: the red wall's reflectance (what Mitsuba's tutorial optimizes), then every
material and emission parameter, to show that cost follows what is differentiated. The loss
is L2 against a fixed target image. Peak memory is the process's resident-set high-water
mark (VmHWM, reset before each measurement), so it includes torch and the scene.

Roughplastic precomputes tables of its rough interface's transmittance for each (distribution,
alpha, eta), so a fit of its alpha pays for them at every step. Measured on a roughplastic
sphere under a constant environment (16 x 16, 1 spp, so that the tables dominate): a render,
and a render with a backward pass, at an unchanged alpha and at a new one, each renderer in
the same process. Our backward pass also differentiates the tables (by central differences:
two more tables); Mitsuba's does not (its alpha gradient leaves out the interface terms).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

import torch_rbpt as tr

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import mitsuba_ref  # noqa: E402  (imports Mitsuba lazily)
from machine import machine, status_mb, write_csv  # noqa: E402
SCENE = HERE.parent.parent / "shared" / "scenes" / "cbox" / "cbox.xml"


def reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def timed(fn, repeats):
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def roughplastic_scene(dist: str) -> dict:
    """A roughplastic sphere under a constant environment, as a Mitsuba scene dict (without
    the sensor's transform, which each renderer builds with its own Transform type)."""
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 4},
            "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 16, "height": 16}},
            "ball": {"type": "sphere", "bsdf": {"type": "roughplastic", "distribution": dist, "alpha": 0.3}},
            "light": {"type": "constant"}}


def step_times(step, repeats: int) -> tuple:
    """Best times of step(alpha) at an unchanged alpha (None) and at new alphas."""
    for i in range(3):
        step(0.3 + 0.01 * i)  # warm-up (Mitsuba compiles its kernels here)
    same, new = [], []
    for i in range(max(3, repeats)):
        t = time.perf_counter()
        step(None)
        same.append(time.perf_counter() - t)
        t = time.perf_counter()
        step(0.35 + 0.001 * i)
        new.append(time.perf_counter() - t)
    return min(same), min(new)


def roughplastic_ours(dist: str, grad: bool, repeats: int) -> tuple:
    scene_dict = roughplastic_scene(dist)
    scene_dict["sensor"]["to_world"] = tr.Transform.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0])
    scene = tr.load_dict(scene_dict)
    key = "ball.bsdf.alpha"

    def step(alpha):
        if alpha is not None:
            scene.params[key] = torch.tensor([alpha])
        scene.params[key].requires_grad_(grad)
        image = tr.render(scene, spp=1, seed=1)
        if grad:
            image.sum().backward()
    return step_times(step, repeats)


def roughplastic_mitsuba(dist: str, grad: bool, repeats: int) -> tuple:
    mi = mitsuba_ref._mitsuba()
    import drjit as dr
    scene_dict = roughplastic_scene(dist)
    scene_dict["integrator"]["type"] = "prb"
    scene_dict["sensor"]["to_world"] = mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0])
    scene = mi.load_dict(scene_dict)
    params = mi.traverse(scene)
    key = "ball.bsdf.alpha"

    def step(alpha):
        if alpha is not None:
            params[key] = mi.Float(alpha)
            params.update()
        if grad:
            dr.enable_grad(params[key])
            image = mi.render(scene, params, spp=1, seed=1)
            dr.backward(dr.sum(image))
            dr.eval(dr.grad(params[key]))
        else:
            dr.eval(mi.render(scene, spp=1, seed=1))
        dr.sync_thread()
    return step_times(step, repeats)


def roughplastic_rows(use_mitsuba: bool, repeats: int) -> list:
    rows = []
    renderers = [("torch_rbpt", roughplastic_ours)] + ([("mitsuba", roughplastic_mitsuba)] if use_mitsuba else [])
    for dist in ("beckmann", "ggx"):
        for grad in (False, True):
            for name, fn in renderers:
                same, new = fn(dist, grad, repeats)
                rows.append({"distribution": dist, "step": "render + backward" if grad else "render",
                             "renderer": name, "same_alpha_ms": same * 1e3, "new_alpha_ms": new * 1e3,
                             "extra_ms": (new - same) * 1e3})
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-mitsuba", action="store_true", help="ours only, even if Mitsuba is installed")
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)

    scene = tr.load_file(SCENE, res=args.res)
    target = tr.render(scene, spp=args.spp, seed=1000).detach()
    diff_keys = [k for k in scene.params if k not in scene.params._fixed]
    rows = []
    for label, keys in (("red.reflectance.value", ["red.reflectance.value"]), (f"all {len(diff_keys)} material/emission parameters", diff_keys)):
        for k in diff_keys:
            scene.params[k].requires_grad_(k in keys)
        params = [scene.params[k] for k in keys]
        t_fwd = timed(lambda: tr.render(scene, spp=args.spp, seed=1), args.repeats)
        image = tr.render(scene, spp=args.spp, seed=1)
        loss = ((image - target) ** 2).sum()
        t_bwd = timed(lambda: torch.autograd.grad(loss, params, retain_graph=True), args.repeats)
        rows.append({"differentiated": label, "spp": args.spp, "forward_s": t_fwd, "backward_s": t_bwd,
                     "ratio": t_bwd / t_fwd})
    for k in diff_keys:
        scene.params[k].requires_grad_(k == "red.reflectance.value")
    memory = []
    for spp in (16, 256):
        reset_peak()
        base = status_mb("VmHWM")
        image = tr.render(scene, spp=spp, seed=2)
        ((image - target) ** 2).sum().backward()
        memory.append({"spp": spp, "peak_rss_mb": status_mb("VmHWM"), "before_mb": base})

    use_mitsuba = not args.no_mitsuba and mitsuba_ref.available()
    rough = roughplastic_rows(use_mitsuba, args.repeats)

    print(machine())
    print(f"shared cbox {args.res}x{args.res}, path max_depth 6, {torch.get_num_threads()} threads")
    print(f"\n{'differentiated':42s} {'spp':>4s} {'forward (s)':>11s} {'backward (s)':>12s} {'bwd/fwd':>8s}")
    for r in rows:
        print(f"{r['differentiated']:42s} {r['spp']:4d} {r['forward_s']:11.3f} {r['backward_s']:12.3f} {r['ratio']:8.2f}")
    print(f"\n{'forward + backward at spp':26s} {'peak RSS (MB)':>14s} {'RSS before (MB)':>16s}")
    for m in memory:
        print(f"{m['spp']:<26d} {m['peak_rss_mb']:14.1f} {m['before_mb']:16.1f}")
    print("\nroughplastic: a new alpha (its tables), 16 x 16 at 1 spp"
          + ("" if use_mitsuba else " (Mitsuba 3 skipped: " + ("--no-mitsuba" if args.no_mitsuba else
                                                               mitsuba_ref.INSTALL_HINT) + ")"))
    print(f"{'distribution':12s} {'step':18s} {'renderer':11s} {'same alpha (ms)':>15s} {'new alpha (ms)':>14s} {'extra (ms)':>10s}")
    for r in rough:
        print(f"{r['distribution']:12s} {r['step']:18s} {r['renderer']:11s} {r['same_alpha_ms']:15.1f} "
              f"{r['new_alpha_ms']:14.1f} {r['extra_ms']:10.1f}")
    out = Path(args.out)
    write_csv(out / "gradients.csv", rows)
    write_csv(out / "roughplastic_alpha.csv", rough)


if __name__ == "__main__":
    main()
