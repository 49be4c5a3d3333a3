"""Gradient benchmark: backward (radiative backpropagation) against forward rendering at
equal spp on the shared cbox, and peak memory of a forward + backward pass at two spp.

    python benchmarks/bench_gradients.py [--res 256] [--spp 16]

Differentiated: the red wall's reflectance (what Mitsuba's tutorial optimizes), then every
material and emission parameter, to show that cost follows what is differentiated. The loss
is L2 against a fixed target image. Peak memory is the process's resident-set high-water
mark (VmHWM, reset before each measurement), so it includes torch and the scene.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import torch

import torch_rbpt as tr

HERE = Path(__file__).resolve().parent
SCENE = HERE.parent.parent / "shared" / "scenes" / "cbox" / "cbox.xml"


def peak_rss_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
    return float("nan")


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

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
        base = peak_rss_mb()
        image = tr.render(scene, spp=spp, seed=2)
        ((image - target) ** 2).sum().backward()
        memory.append({"spp": spp, "peak_rss_mb": peak_rss_mb(), "before_mb": base})

    print(f"shared cbox {args.res}x{args.res}, path max_depth 6, {torch.get_num_threads()} threads")
    print(f"\n{'differentiated':42s} {'spp':>4s} {'forward (s)':>11s} {'backward (s)':>12s} {'bwd/fwd':>8s}")
    for r in rows:
        print(f"{r['differentiated']:42s} {r['spp']:4d} {r['forward_s']:11.3f} {r['backward_s']:12.3f} {r['ratio']:8.2f}")
    print(f"\n{'forward + backward at spp':26s} {'peak RSS (MB)':>14s} {'RSS before (MB)':>16s}")
    for m in memory:
        print(f"{m['spp']:<26d} {m['peak_rss_mb']:14.1f} {m['before_mb']:16.1f}")
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    with open(out / "gradients.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


if __name__ == "__main__":
    main()
