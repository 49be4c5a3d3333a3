"""Forward rendering benchmark: torch_rbpt against Mitsuba 3 on the shared cbox.

Prints, for each renderer, the time, ray throughput (ours) and the error against a
converged reference, measured in the same run on the same machine. Writes
benchmarks/results/render.csv. The reference (Mitsuba at high spp, or ours when Mitsuba is
absent) is cached in benchmarks/cache/.

    python benchmarks/bench_render.py [--res 256] [--spp 64] [--ref-spp 1024]
"""
from __future__ import annotations

import argparse
import csv
import os
import platform
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import mitsuba_ref  # noqa: E402

import torch_rbpt as tr  # noqa: E402
from torch_rbpt.render import render_with_stats  # noqa: E402

SCENE = HERE.parent.parent / "shared" / "scenes" / "cbox" / "cbox.xml"


def rel_error(img: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean over pixels and channels of |img - ref| / max(|ref|, 0.02) (the tests' metric)."""
    return float(((img - ref).abs() / ref.abs().clamp(min=0.02)).mean())


def rmse(img: torch.Tensor, ref: torch.Tensor) -> float:
    return float(((img - ref) ** 2).mean().sqrt())


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__} ({torch.get_num_threads()} threads), {platform.system()}"


def reference(res: int, ref_spp: int) -> tuple[torch.Tensor, str]:
    cache = HERE / "cache"
    cache.mkdir(exist_ok=True)
    use_mitsuba = mitsuba_ref.available()
    name = f"cbox_{res}_{ref_spp}_{'mitsuba' if use_mitsuba else 'ours'}.exr"
    path = cache / name
    if path.exists():
        return tr.read_image(path), name
    print(f"rendering the reference ({ref_spp} spp, {'Mitsuba' if use_mitsuba else 'torch_rbpt'}) ...", flush=True)
    if use_mitsuba:
        scene = mitsuba_ref.load_scene(SCENE, res=res)
        img = torch.from_numpy(mitsuba_ref.render(scene, ref_spp, seed=12345))
    else:
        img = tr.render(tr.load_file(SCENE, res=res), spp=ref_spp, seed=12345)
    tr.write_image(path, img)
    return img, name


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    ref, ref_name = reference(args.res, args.ref_spp)
    rows = []

    scene = tr.load_file(SCENE, res=args.res)
    render_with_stats(scene, spp=1)  # warm-up (roughplastic tables, page faults)
    times, rays = [], 0
    for k in range(args.repeats):
        start = time.perf_counter()
        img, rays = render_with_stats(scene, spp=args.spp, seed=k)
        times.append(time.perf_counter() - start)
    t = min(times)
    rows.append({"renderer": "torch_rbpt", "seconds": t, "mrays_per_s": rays / t / 1e6,
                 "rel_error": rel_error(img, ref), "rmse": rmse(img, ref)})

    if mitsuba_ref.available():
        mscene = mitsuba_ref.load_scene(SCENE, res=args.res)
        mt, mimg = mitsuba_ref.time_render(mscene, args.spp, seed=1, repeats=args.repeats)
        mimg = torch.from_numpy(mimg)
        rows.append({"renderer": f"mitsuba {mitsuba_ref.version()} {mitsuba_ref.variant()}",
                     "seconds": mt, "mrays_per_s": float("nan"),
                     "rel_error": rel_error(mimg, ref), "rmse": rmse(mimg, ref)})
        # Equal error: Mitsuba splats each sample into every pixel under the filter, which
        # averages more samples per pixel than our filter importance sampling at equal spp.
        # Render ours at the spp where its RMSE should match Mitsuba's (RMSE ~ 1/sqrt(spp)).
        spp_eq = int(round(args.spp * (rows[0]["rmse"] / rows[1]["rmse"]) ** 2))
        times = []
        for k in range(args.repeats):
            start = time.perf_counter()
            img, rays = render_with_stats(scene, spp=spp_eq, seed=100 + k)
            times.append(time.perf_counter() - start)
        t = min(times)
        rows.append({"renderer": f"torch_rbpt at {spp_eq} spp (equal error)", "seconds": t,
                     "mrays_per_s": rays / t / 1e6, "rel_error": rel_error(img, ref), "rmse": rmse(img, ref)})
    else:
        print("Mitsuba 3 not available: no comparison (pip install mitsuba)")

    print(f"\nshared cbox, {args.res}x{args.res}, {args.spp} spp, path max_depth 6; reference: {ref_name}")
    print(f"machine: {machine()}\n")
    print(f"{'renderer':32s} {'time (s)':>9s} {'Mrays/s':>8s} {'rel.err':>8s} {'RMSE':>8s} {'time ratio':>10s}")
    for r in rows:
        ratio = r["seconds"] / rows[0]["seconds"]
        mr = "" if r["mrays_per_s"] != r["mrays_per_s"] else f"{r['mrays_per_s']:.2f}"
        print(f"{r['renderer']:32s} {r['seconds']:9.3f} {mr:>8s} {r['rel_error']:8.4f} {r['rmse']:8.4f} {ratio:10.2f}")
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    with open(out / "render.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) + ["res", "spp", "machine"])
        w.writeheader()
        for r in rows:
            w.writerow({**r, "res": args.res, "spp": args.spp, "machine": machine()})


if __name__ == "__main__":
    main()
