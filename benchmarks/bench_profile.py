"""Where the time goes: the share of each renderer's render time spent casting rays.

    python benchmarks/bench_profile.py [--scenes cbox veach-mis] [--res 256] [--spp 64]

For each scene, one child process per renderer loads the scene, renders once untimed (ours:
BSDF tables and page faults; Mitsuba llvm_ad_rgb: tracing and compiling the JIT kernels),
then renders --renders times at --spp under `perf record` (sampling at 1999 Hz). The samples
are attributed to:
  ours     ray casting: rbpt::BVH (traversal, with the triangle and sphere tests inlined into
           it); shading: every other function of the renderer (namespace rbpt) and libm;
  Mitsuba  ray casting: libembree3 and the shape plugins Embree calls back into for
           analytic shapes (sphere.so, disk.so, cylinder.so, ...); shading: the JIT kernels
           and the rest of Mitsuba/drjit (libmitsuba, libdrjit-core, libnanothread, libm).
Python, torch and the loader are excluded (they run before and between the timed renders).
The table gives the warm time per render (wall clock, best of --renders, measured in the
child under perf; perf costs a few percent), each renderer's share in ray casting, and the
bound it implies: if Mitsuba spends the fraction f of its time in Embree, a renderer that
casts the same rays at Embree's speed needs f x Mitsuba's time for them alone, so reaching
0.5x Mitsuba's time needs rays cast faster than Embree casts them whenever f > 0.5. The
table's `ratio` is ours / Mitsuba's time per render, and `floor` = f: the ratio a renderer
would reach with rays as fast as Mitsuba's Embree calls and shading that costs nothing.

Needs `perf` (apt-get install linux-perf) and permission to use it; without perf, or without
Mitsuba, it says what it skipped. Writes benchmarks/results/profile.csv.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_error_time import SCENES  # noqa: E402
from machine import cpu_model, write_csv  # noqa: E402

MITSUBA_RAY_DSOS = ("libembree3", "sphere.so", "disk.so", "cylinder.so", "rectangle.so", "cube.so")
MITSUBA_OTHER_DSOS = ("[JIT]", "libmitsuba", "libdrjit", "libnanothread", "libm.so", "ply.so",
                      "obj.so", "mesh.so", "path.so", "direct.so", "hdrfilm.so")

CHILD = r"""
import json, os, sys, time
kind, scene_file, res, spp, renders = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
sys.path.insert(0, os.environ["BENCH_DIR"])
times = []
if kind == "ours":
    import torch, torch_rbpt as tr
    scene = tr.load_file(scene_file)
    f = scene.sensor.film
    f.width, f.height = res, max(1, round(res * f.height / f.width))
    tr.render(scene, spp=1)
    for i in range(renders):
        t = time.perf_counter(); tr.render(scene, spp=spp, seed=i); times.append(time.perf_counter() - t)
else:
    import mitsuba_ref
    mi = mitsuba_ref._mitsuba()
    import drjit as dr
    probe = mitsuba_ref.load_scene(scene_file)
    w, h = probe.sensors()[0].film().size()
    scene = mitsuba_ref.load_scene(scene_file, width=res, height=max(1, round(res * h / w)))
    mitsuba_ref.render(scene, spp, seed=1000)
    for i in range(renders):
        t = time.perf_counter(); mitsuba_ref.render(scene, spp, seed=i); dr.sync_thread()
        times.append(time.perf_counter() - t)
print(json.dumps({"best": min(times)}))
"""


def perf_shares(data: Path, kind: str) -> tuple[float, float]:
    """(ray-casting samples, render samples) from a perf.data file."""
    out = subprocess.run(["perf", "report", "-i", str(data), "--no-children", "--sort", "dso,sym",
                          "--stdio", "-q", "-F", "period,dso,sym"],
                         capture_output=True, text=True, check=True).stdout
    rays = total = 0.0
    for line in out.splitlines():
        parts = line.split(None, 2)
        if len(parts) < 3 or not parts[0].isdigit():
            continue
        period, dso, sym = float(parts[0]), parts[1], parts[2]
        if kind == "ours":
            # (torch's extension module has the same file name as ours: tell them by symbol)
            if "rbpt" in sym or dso.startswith("libm.so"):
                total += period
                if "rbpt::BVH::" in sym:
                    rays += period
        else:
            if any(dso.startswith(d) for d in MITSUBA_RAY_DSOS):
                rays += period
                total += period
            elif any(dso.startswith(d) for d in MITSUBA_OTHER_DSOS):
                total += period
    return rays, total


def profile(kind: str, scene_file: Path, res: int, spp: int, renders: int, tmp: Path) -> dict:
    data = tmp / f"{kind}.data"
    env = dict(os.environ, BENCH_DIR=str(HERE))
    proc = subprocess.run(["perf", "record", "-q", "-F", "1999", "-o", str(data), "--",
                           sys.executable, "-c", CHILD, kind, str(scene_file), str(res), str(spp),
                           str(renders)], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"{kind} child failed:\n{proc.stderr[-2000:]}")
    best = json.loads(proc.stdout.strip().splitlines()[-1])["best"]
    rays, total = perf_shares(data, kind)
    return {"seconds": best, "ray_share": rays / total if total else float("nan")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES),
                    choices=list(SCENES))
    ap.add_argument("--res", type=int, default=256, help="film width (height keeps the aspect)")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--renders", type=int, default=4, help="timed renders per renderer")
    ap.add_argument("--no-mitsuba", action="store_true")
    args = ap.parse_args()

    if shutil.which("perf") is None:
        print("skipped: `perf` not found (apt-get install linux-perf); nothing to attribute")
        return 0
    import mitsuba_ref
    use_mi = not args.no_mitsuba and mitsuba_ref.available()
    if not use_mi and not args.no_mitsuba:
        print(f"Mitsuba skipped: {mitsuba_ref._MISSING}")

    import torch
    header = (f"# {cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__} "
              f"({torch.get_num_threads()} threads), Mitsuba "
              f"{mitsuba_ref.version() + ' ' + mitsuba_ref.variant() if use_mi else 'skipped'}, "
              f"{datetime.datetime.now():%Y-%m-%d %H:%M}; {args.res} px wide, {args.spp} spp")
    print(header)
    print(f"{'scene':12s} {'ours s':>8s} {'rays %':>7s} {'Mitsuba s':>10s} {'Embree %':>9s} "
          f"{'ratio':>6s} {'floor':>6s}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes:
            scene_file = SCENES[name][0]
            ours = profile("ours", scene_file, args.res, args.spp, args.renders, Path(tmp))
            mi = profile("mitsuba", scene_file, args.res, args.spp, args.renders, Path(tmp)) if use_mi else None
            row = {"scene": name, "width": args.res, "spp": args.spp,
                   "ours_seconds": ours["seconds"], "ours_ray_share": ours["ray_share"],
                   "mitsuba_seconds": mi["seconds"] if mi else "", "mitsuba_ray_share": mi["ray_share"] if mi else "",
                   "cpu": cpu_model(), "cores": os.cpu_count(), "date": datetime.date.today().isoformat()}
            rows.append(row)
            if mi:
                print(f"{name:12s} {ours['seconds']:8.3f} {100 * ours['ray_share']:6.1f}% "
                      f"{mi['seconds']:10.3f} {100 * mi['ray_share']:8.1f}% "
                      f"{ours['seconds'] / mi['seconds']:6.2f} {mi['ray_share']:6.2f}", flush=True)
            else:
                print(f"{name:12s} {ours['seconds']:8.3f} {100 * ours['ray_share']:6.1f}%", flush=True)
    write_csv(HERE / "results" / "profile.csv", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
