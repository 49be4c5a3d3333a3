"""Where a render's error comes from: each pixel's variance split by path length.

    python benchmarks/bench_variance.py                 # the path-traced scenes of make bench
    python benchmarks/bench_variance.py --scenes cbox --res 64 --spp 16

Two renders with independent seeds give each pixel's variance, mean((a - b)^2) / 2. Rendered
with max_depth 1 (only emitters seen from the camera), 2 (plus direct illumination) and the
scene's own max_depth, the differences split it into: emitters seen directly (a light's
silhouette: the pixel is bright or dark depending on where its sample lands), direct
illumination, and longer paths. A shortened path is not an estimator of the full image, but
its variance is that of the first vertices' terms alone; the split assumes the terms of
different lengths are uncorrelated, so shares can drift by a few percent. veach-mis uses the
`direct` integrator, whose max_depth does not split by length: it is left out.
Writes benchmarks/results/variance.csv. Ours only (the split is a property of the scene and
the estimator, which Mitsuba's `path` shares).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_error_time import SCENES, film_size  # noqa: E402
from machine import machine, write_csv  # noqa: E402

import torch_rbpt as tr  # noqa: E402

PATH_SCENES = [name for name in SCENES if name != "veach-mis"]


def pixel_variance(path: Path, size: tuple[int, int], spp: int, max_depth: int | None) -> float:
    """Mean over pixels and channels of the variance of one render at `spp`."""
    scene = tr.load_file(path) if max_depth is None else tr.load_file(path, max_depth=max_depth)
    scene.sensor.film.width, scene.sensor.film.height = size
    with torch.no_grad():
        a = tr.render(scene, spp=spp, seed=1)
        b = tr.render(scene, spp=spp, seed=2)
    return float(((a.double() - b.double()) ** 2).mean() / 2)


def split(path: Path, size: tuple[int, int], spp: int) -> dict:
    v1, v2, v = (pixel_variance(path, size, spp, d) for d in (1, 2, None))
    return {"variance": v, "emitters_seen": v1 / v, "direct": (v2 - v1) / v, "longer": (v - v2) / v}


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", choices=PATH_SCENES, default=PATH_SCENES)
    ap.add_argument("--res", type=int, default=128, help="film width (height keeps the scene's aspect)")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    print(machine())
    print(f"pixel variance at {args.spp} spp, {args.res} px wide, two seeds; shares by path length")
    print(f"{'scene':12s} {'variance':>10s} {'emitters seen':>14s} {'direct':>8s} {'longer':>8s}")
    rows = []
    for name in args.scenes:
        path = SCENES[name][0]
        size = film_size(path, args.res)
        r = {"scene": name, "width": size[0], "height": size[1], "spp": args.spp, **split(path, size, args.spp)}
        rows.append(r)
        print(f"{name:12s} {r['variance']:10.3g} {r['emitters_seen']:14.0%} {r['direct']:8.0%} {r['longer']:8.0%}",
              flush=True)
    write_csv(args.out / "variance.csv", rows)
    return rows


if __name__ == "__main__":
    main()
