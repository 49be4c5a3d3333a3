"""Ray throughput against Embree 3, thread scaling, and peak memory of a gradient render.

1. Rays: our BVH (csrc/bvh.cpp and csrc/shapes.cpp compiled without torch, with setup.py's
   flags) against Embree 3 on the bunny, the same rays in the same process
   (benchmarks/rays/bench_rays.cpp, compiled here with g++ into benchmarks/cache/):
   incoherent rays (random origins in the bunny's box enlarged 2x, uniform directions) and
   coherent rays (a pinhole camera's primary rays, 512x512), 1 and 2 threads, closest hit and
   any hit. Embree is called one ray at a time (rtcIntersect1 / rtcOccluded1), as our
   renderer calls its BVH; its 4- and 8-ray packets (rtcIntersect4/8) are reported
   separately. Both must find the same hits (hit/miss, t to 1e-4 relative): the mismatch
   rate is reported. Also the BVH build times.
2. Threads: the shared cbox (256x256, 64 spp) rendered with torch.set_num_threads(1) and (2).
3. Memory: peak RSS (VmHWM) of a forward + backward render of the cbox (L2 loss on an image,
   gradient of red.reflectance.value), each configuration of spp x max_depth in a fresh
   process.

Prints tables with the machine and date, and writes benchmarks/results/rays.csv and
benchmarks/results/threads_memory.csv.

    python benchmarks/bench_rays.py [--quick] [--only rays|threads|memory] [--no-embree]

--quick is a smoke run (50k incoherent rays, 128x128 coherent ones): its ray table prints no
verdict on the targets, whose timings it is too short to measure.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from machine import machine, simd, status_mb, write_csv  # noqa: E402
from torch_rbpt import build_flags  # noqa: E402

ROOT = HERE.parent
CSRC = ROOT / "csrc"
CACHE = HERE / "cache"
RESULTS = HERE / "results"
SHARED = ROOT.parent / "shared" / "scenes"
BUNNY = SHARED / "meshes" / "bunny.ply"
CBOX = SHARED / "cbox" / "cbox.xml"

# setup.py's flags (plus -fwrapv, which setuptools adds from Python's own CFLAGS), including
# The extension's optimised flags, its target and tuning (torch_rbpt/build_flags.py) unless
# PORTABLE=1, as for the extension.
CXX_FLAGS = ["-std=c++17", "-fopenmp", "-Wall", "-Wno-sign-compare", "-fwrapv", *build_flags.OPTIMISED] + \
    ([] if os.environ.get("PORTABLE", "0") == "1" else build_flags.target_flags())
CORE_SOURCES = ["bvh.cpp", "shapes.cpp"]
EMBREE_INSTALL = "apt-get install libembree-dev (Debian/Ubuntu), or set EMBREE_DIR to an Embree 3 install"


# ---- Machine --------------------------------------------------------------------------------





def print_table(headers: list[str], rows: list[list], aligns: str | None = None) -> None:
    cells = [[str(c) for c in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    aligns = aligns or "<" + ">" * (len(headers) - 1)
    fmt = lambda r: "  ".join(c.ljust(w) if a == "<" else c.rjust(w) for c, w, a in zip(r, widths, aligns))
    print(fmt(headers))
    print("  ".join("-" * w for w in widths))
    for r in cells:
        print(fmt(r))


# ---- 1. Rays against Embree ----------------------------------------------------------------

def embree_include() -> Path | None:
    """Directory holding embree3/rtcore.h, or None."""
    dirs = [Path(os.environ["EMBREE_DIR"]) / "include"] if "EMBREE_DIR" in os.environ else []
    dirs += [Path("/usr/include"), Path("/usr/local/include"), Path("/opt/homebrew/include")]
    return next((d for d in dirs if (d / "embree3" / "rtcore.h").exists()), None)


def compile_cached(prefix: str, cmd: list, deps: list, what: str, libs: list = ()) -> Path:
    """Compile `cmd` (compiler, flags and sources, without -o) linking `libs` into
    benchmarks/cache/<prefix>_<key>, the key hashing the command and the mtimes of `deps`; an
    existing build with the same key is reused, older ones are removed."""
    key = hashlib.sha1(repr([(str(p), p.stat().st_mtime_ns) for p in deps] + cmd + list(libs)).encode()).hexdigest()[:12]
    exe = CACHE / f"{prefix}_{key}"
    if exe.exists():
        return exe
    CACHE.mkdir(exist_ok=True)
    for old in CACHE.glob(f"{prefix}_*"):
        old.unlink()
    full = cmd + ["-o", str(exe)] + list(libs)
    print(f"compiling {exe.name} ...", flush=True)
    r = subprocess.run(full, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"compiling {what} failed:\n{' '.join(full)}\n{r.stderr}")
    return exe


def compile_bench(with_embree: bool, cxx: str) -> Path:
    """Compile benchmarks/rays/bench_rays.cpp with our core; cached by the sources' mtimes."""
    sources = [HERE / "rays" / "bench_rays.cpp"] + [CSRC / s for s in CORE_SOURCES]
    deps = sources + sorted(CSRC.glob("*.h"))
    inc = embree_include() if with_embree else None
    cmd = [cxx, *CXX_FLAGS, f"-I{CSRC}"]
    libs = ["-pthread"]
    if with_embree:
        cmd += ["-DHAVE_EMBREE", f"-I{inc}"]
        if "EMBREE_DIR" in os.environ:
            libs = [f"-L{Path(os.environ['EMBREE_DIR']) / 'lib'}"] + libs
        libs += ["-lembree3"]
    prefix = f"bench_rays_{'embree' if with_embree else 'ours'}"
    return compile_cached(prefix, cmd + [str(s) for s in sources], deps, "the ray benchmark", libs)


def load_bunny() -> tuple[np.ndarray, np.ndarray]:
    from torch_rbpt.meshes import load_ply
    mesh = load_ply(BUNNY)
    return mesh.positions.astype(np.float32), mesh.faces.astype(np.uint32)


def tiny_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A unit cube (12 triangles): stands in for the bunny when it is absent (tests)."""
    from torch_rbpt.meshes import cube
    mesh = cube()
    return mesh.positions.astype(np.float32), mesh.faces.astype(np.uint32)


def unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def incoherent_rays(lo: np.ndarray, hi: np.ndarray, n: int, seed: int = 1):
    """Origins uniform in the box [lo, hi] enlarged 2x about its centre, directions uniform."""
    rng = np.random.default_rng(seed)
    c, half = (lo + hi) / 2, (hi - lo)  # 2x the half-extent
    o = c + (rng.random((n, 3)) * 2 - 1) * half
    z = rng.random(n) * 2 - 1
    phi = rng.random(n) * 2 * np.pi
    r = np.sqrt(np.maximum(0, 1 - z * z))
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return o.astype(np.float32), unit(d)


def camera_rays(lo: np.ndarray, hi: np.ndarray, res: int, fov_deg: float = 35.0):
    """Primary rays of a pinhole camera looking at the box's centre along -z (the bunny is
    y-up, facing +z), far enough that the box fills most of the image; scanline order."""
    c, half = (lo + hi) / 2, (hi - lo) / 2
    tan = np.tan(np.radians(fov_deg) / 2)
    eye = c + np.array([0, 0, half[2] + 1.05 * max(half[0], half[1]) / tan])
    s = (np.arange(res) + 0.5) / res * 2 - 1
    x, y = np.meshgrid(s * tan, -s * tan)
    d = np.stack([x.ravel(), y.ravel(), -np.ones(res * res)], axis=1)
    o = np.broadcast_to(eye, d.shape)
    return o.astype(np.float32), unit(d)


def write_ray_file(path: Path, vertices: np.ndarray, triangles: np.ndarray, sets: dict) -> None:
    with open(path, "wb") as f:
        f.write(b"RBRAYS1\0")
        f.write(np.array([len(vertices), len(triangles), len(sets)], np.uint32).tobytes())
        f.write(np.ascontiguousarray(vertices, np.float32).tobytes())
        f.write(np.ascontiguousarray(triangles, np.uint32).tobytes())
        for name, (o, d) in sets.items():
            f.write(name.encode().ljust(16, b"\0")[:16])
            f.write(np.array([len(o)], np.uint32).tobytes())
            f.write(np.ascontiguousarray(o, np.float32).tobytes())
            f.write(np.ascontiguousarray(d, np.float32).tobytes())


def parse_output(text: str) -> list[dict]:
    records = []
    for line in text.splitlines():
        kind, *fields = line.split()
        rec = {"record": kind}
        for f in fields:
            k, _, v = f.partition("=")
            rec[k] = v
        records.append(rec)
    return records


def run_rays(quick: bool, use_embree: bool, mesh: str = "bunny", threads: str = "1,2",
             repeats: int | None = None) -> dict:
    """Run part 1 and return {'rows': table rows, 'builds': ..., 'embree': bool, ...}."""
    cxx = os.environ.get("CXX", "g++")
    if shutil.which(cxx) is None:
        raise FileNotFoundError(f"no C++ compiler ({cxx}): the ray benchmark needs g++")
    have_headers = embree_include() is not None
    with_embree = use_embree and have_headers
    if use_embree and not have_headers:
        print(f"Embree 3 headers not found: Embree skipped, ours only. Install with: {EMBREE_INSTALL}")
    exe = compile_bench(with_embree, cxx)

    vertices, triangles = load_bunny() if mesh == "bunny" else tiny_mesh()
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    n_inc, res = (50_000, 128) if quick else (1_000_000, 512)
    sets = {"incoherent": incoherent_rays(lo, hi, n_inc), "coherent": camera_rays(lo, hi, res)}
    CACHE.mkdir(exist_ok=True)
    ray_file = CACHE / f"rays_{mesh}_{n_inc}_{res}.bin"
    write_ray_file(ray_file, vertices, triangles, sets)
    repeats = repeats or (2 if quick else 5)
    cmd = [str(exe), str(ray_file), "--threads", threads, "--repeats", str(repeats)]
    if not with_embree:
        cmd.append("--no-embree")
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")
    recs = parse_output(r.stdout)

    trace = {(x["set"], x["query"], x["impl"], int(x["threads"])): float(x["mrays"])
             for x in recs if x["record"] == "TRACE"}
    checks = {(x["set"], x["query"], x["ref"]): x for x in recs if x["record"] == "CHECK"}
    rows = []
    for name, (o, _) in sets.items():
        for query in ("closest", "any"):
            for t in sorted({k[3] for k in trace}):
                ours = trace[(name, query, "ours", t)]
                ours1 = trace[(name, query, "ours", 1)]
                emb = trace.get((name, query, "embree1", t), float("nan"))
                emb1 = trace.get((name, query, "embree1", 1), float("nan"))
                chk = checks.get((name, query, "embree1"))
                own = checks[(name, "any", "ours_closest")]
                rows.append({
                    "rays": name, "n": len(o), "hit_fraction": int(own["ref_hits"]) / int(own["n"]),
                    "query": query, "threads": t,
                    "ours_mrays": ours, "embree1_mrays": emb, "ratio": ours / emb,
                    "embree4_mrays": trace.get((name, query, "embree4", t), float("nan")),
                    "embree8_mrays": trace.get((name, query, "embree8", t), float("nan")),
                    "ours_scaling": ours / ours1, "embree1_scaling": emb / emb1,
                    "mismatches": int(chk["mismatches"]) if chk else "",
                    "mismatch_rate": int(chk["mismatches"]) / int(chk["n"]) if chk else float("nan"),
                    "hit_miss": int(chk["hit_miss"]) if chk else "",
                    "t_diff": int(chk["t_diff"]) if chk else "",
                    "prim_diff": int(chk["prim_diff"]) if chk else "",
                })
    builds = {f"{x['impl']}_{x['threads']}": float(x["ms"]) for x in recs if x["record"] == "BUILD"}
    info = {k: v for x in recs if x["record"] == "INFO" for k, v in x.items()}
    return {"rows": rows, "builds": builds, "embree": with_embree, "triangles": int(info["triangles"]),
            "checks": checks, "mismatch_lines": [x for x in recs if x["record"] == "MISMATCH"],
            "res": res, "embree_version": embree_version(info.get("embree_version")), "stdout": r.stdout,
            "quick": quick}


def embree_version(code: str | None) -> str:
    """'3.13.5' from Embree's RTC_DEVICE_PROPERTY_VERSION (30000 + 100 * minor + patch)."""
    if not code:
        return ""
    v = int(code)
    return f"{v // 10000}.{v // 100 % 100}.{v % 100}"


def simd_flags() -> str:
    """The widest x86 vector extensions of the CPU (Embree picks its code path from them)."""
    return simd(("avx512f", "avx2", "avx", "sse4_2")) or "sse2"


def report_rays(out: dict, mach: str) -> list[dict]:
    rows = out["rows"]
    f = lambda v, p=2: "" if v != v else f"{v:.{p}f}"  # NaN -> empty
    print(f"\nRay throughput, bunny ({out['triangles']} triangles): incoherent = random origins in the box "
          f"enlarged 2x, uniform directions; coherent = pinhole camera {out['res']}x{out['res']}")
    print(f"machine: {mach}")
    print(f"ours: setup.py's flags ({' '.join(f for f in CXX_FLAGS if f.startswith(('-O', '-march', '-mtune', '-mprefer')))}); "
          + (f"Embree {out['embree_version']} (chooses its ISA at run time; CPU has {simd_flags()})"
             if out["embree"] else "Embree: skipped"))
    print("Mrays/s, best of the repeats; Embree x1 = rtcIntersect1/rtcOccluded1 per ray (as our renderer "
          "calls its BVH),\nx4/x8 = rtcIntersect4/8 packets; scaling = this thread count over 1 thread; "
          "mismatch = ours vs Embree x1 (hit/miss or t off by > 1e-4 rel.)\n")
    headers = ["rays", "hit %", "query", "thr", "ours", "Embree x1", "ours/Embree", "Embree x4", "Embree x8",
               "ours scaling", "Embree scaling", "mismatch rate"]
    table = []
    for r in rows:
        mm = "" if r["mismatches"] == "" else f"{r['mismatch_rate']:.2e} ({r['mismatches']}/{r['n']})"
        table.append([r["rays"], f"{100 * r['hit_fraction']:.1f}", r["query"], r["threads"], f(r["ours_mrays"]), f(r["embree1_mrays"]),
                      f(r["ratio"]), f(r["embree4_mrays"]), f(r["embree8_mrays"]),
                      f(r["ours_scaling"]), f(r["embree1_scaling"]), mm])
    print_table(headers, table, "<><>>>>>>>>>")
    b = out["builds"]
    print(f"\nBVH build: ours {b['ours_1']:.1f} ms (1 thread)" +
          (f"; Embree {b['embree_1']:.1f} ms (1 thread), {b['embree_all']:.1f} ms (its thread pool)"
           if "embree_1" in b else "; Embree skipped"))
    if not out["embree"]:
        print(f"Embree 3 not available: ours only. Install with: {EMBREE_INSTALL}")
    for (name, query, ref), c in out["checks"].items():
        if ref != "embree1" and int(c["mismatches"]):  # self-consistency: ours any vs closest, packets
            print(f"  {name} {query}: {ref}: {c['mismatches']} of {c['n']} rays differ")
    for m in out["mismatch_lines"]:
        print("  mismatch:", " ".join(f"{k}={v}" for k, v in m.items() if k != "record"))
    closest = [r for r in rows if r["query"] == "closest"]
    if out["quick"]:
        # (A smoke run's 50k and 128 x 128 rays take a few ms: too short to time the
        # targets, the 2-thread scaling least of all.)
        print("targets not judged: --quick's ray sets are too small to time; run without --quick")
    else:
        if out["embree"]:
            low = [r for r in closest if r["ratio"] < 0.8]
            print("target ours/Embree x1 >= 0.8 (closest hit): " +
                  ("met" if not low else "NOT met for " + ", ".join(f"{r['rays']} {r['threads']}T" for r in low)))
        low = [r for r in closest if r["threads"] == 2 and r["ours_scaling"] < 1.8]
        print("target 2 threads >= 1.8x 1 thread (ours, closest hit): " +
              ("met" if not low else "NOT met for " + ", ".join(f"{r['rays']} ({r['ours_scaling']:.2f}x)" for r in low)))
    csv_rows = [{**r, "triangles": out["triangles"],
                 "build_ms_ours": b.get("ours_1"), "build_ms_embree_1thread": b.get("embree_1"),
                 "build_ms_embree_pool": b.get("embree_all"), "embree_version": out["embree_version"],
                 "machine": mach} for r in rows]
    return csv_rows


# ---- 2. Threads -----------------------------------------------------------------------------

def run_threads(quick: bool, mach: str) -> list[dict]:
    import torch
    import torch_rbpt as tr
    from torch_rbpt.render import render_with_stats
    res, spp, repeats = (64, 4, 2) if quick else (256, 64, 3)
    scene = tr.load_file(CBOX, res=res)
    rows = []
    saved = torch.get_num_threads()
    try:
        # 1 and 2 threads take turns, so that a shared host's load changes hit both.
        times = {1: [], 2: []}
        with torch.no_grad():
            tr.render(scene, spp=1)  # warm-up
            for k in range(repeats):
                for threads in (1, 2):
                    torch.set_num_threads(threads)
                    start = time.perf_counter()
                    tr.render(scene, spp=spp, seed=k)
                    times[threads].append(time.perf_counter() - start)
        for threads in (1, 2):
            rows.append({"part": "threads", "scene": "cbox", "res": res, "spp": spp, "threads": threads,
                         "seconds": min(times[threads])})
        _, rays = render_with_stats(scene, spp=spp, seed=0)
    finally:
        torch.set_num_threads(saved)
    for r in rows:
        r["speedup"] = rows[0]["seconds"] / r["seconds"]
        r["mrays_per_s"] = rays / r["seconds"] / 1e6
        r["machine"] = mach
    print(f"\nThreads: shared cbox {res}x{res}, {spp} spp, tr.render (best of {repeats})")
    print(f"machine: {mach}\n")
    print_table(["threads", "time (s)", "Mrays/s", "speedup"],
                [[r["threads"], f"{r['seconds']:.3f}", f"{r['mrays_per_s']:.2f}", f"{r['speedup']:.2f}"] for r in rows],
                ">>>>")
    return rows


# ---- 3. Memory ------------------------------------------------------------------------------

def memory_child(res: int, spp: int, max_depth: int) -> None:
    """Forward + backward render in this (fresh) process; prints a JSON line."""
    import torch
    import torch_rbpt as tr
    scene = tr.load_file(CBOX, res=res)
    scene.integrator.max_depth = max_depth
    key = "red.reflectance.value"
    scene.params[key].requires_grad_()
    target = torch.full((res, res, 3), 0.5)
    base = status_mb("VmHWM")
    start = time.perf_counter()
    img = tr.render(scene, spp=spp, seed=1)
    loss = ((img - target) ** 2).mean()
    loss.backward()
    seconds = time.perf_counter() - start
    grad = scene.params[key].grad
    print(json.dumps({"baseline_mb": base, "peak_mb": status_mb("VmHWM"), "seconds": seconds,
                      "grad_finite": bool(torch.isfinite(grad).all())}))


def run_memory(quick: bool, mach: str, res: int, spps=None, depths=None) -> list[dict]:
    spps = spps or ((1, 4) if quick else (4, 64, 256))
    depths = depths or ((2, 8) if quick else (2, 8, 64))
    res = 32 if quick else res
    rows = []
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    for spp in spps:
        for depth in depths:
            cmd = [sys.executable, __file__, "--memory-child", str(res), str(spp), str(depth)]
            r = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if r.returncode != 0:
                raise RuntimeError(f"memory child {spp} spp, max_depth {depth} failed:\n{r.stderr}")
            out = json.loads(r.stdout.strip().splitlines()[-1])
            rows.append({"part": "memory", "scene": "cbox", "res": res, "spp": spp, "max_depth": depth,
                         "peak_rss_mb": out["peak_mb"], "baseline_rss_mb": out["baseline_mb"],
                         "render_mb": out["peak_mb"] - out["baseline_mb"], "seconds": out["seconds"],
                         "grad_finite": out["grad_finite"], "machine": mach})
            print(f"  memory: {spp} spp, max_depth {depth}: {out['peak_mb']:.0f} MB ({out['seconds']:.1f} s)", flush=True)
    print(f"\nPeak memory: cbox {res}x{res}, forward + backward (L2 loss, d/d red.reflectance.value), "
          f"a fresh process each; peak RSS = VmHWM, over load = peak minus VmHWM after loading the scene")
    print(f"machine: {mach}\n")
    print_table(["spp", "max_depth", "peak RSS (MB)", "over load (MB)", "time (s)"],
                [[r["spp"], r["max_depth"], f"{r['peak_rss_mb']:.0f}", f"{r['render_mb']:.0f}",
                  f"{r['seconds']:.1f}"] for r in rows], ">>>>>")
    return rows


# ---- Main -----------------------------------------------------------------------------------

def main() -> None:
    if len(sys.argv) == 5 and sys.argv[1] == "--memory-child":
        return memory_child(*map(int, sys.argv[2:]))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke run of a few seconds")
    ap.add_argument("--only", choices=["rays", "threads", "memory"], action="append",
                    help="run only this part (repeatable)")
    ap.add_argument("--no-embree", action="store_true", help="measure our BVH only")
    ap.add_argument("--mesh", choices=["bunny", "cube"], default="bunny",
                    help="mesh of the ray benchmark (cube: 12 triangles, for tests)")
    ap.add_argument("--mem-res", type=int, default=256, help="image size of the memory runs")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder of the CSV files")
    args = ap.parse_args()
    parts = args.only or ["rays", "threads", "memory"]
    mach = machine()

    if "rays" in parts:
        try:
            out = run_rays(args.quick, not args.no_embree, args.mesh)
        except FileNotFoundError as e:
            print(f"ray benchmark skipped: {e}")
        else:
            write_csv(args.out / "rays.csv", report_rays(out, mach))
    rows = []
    if "threads" in parts:
        rows += run_threads(args.quick, mach)
    if "memory" in parts:
        rows += run_memory(args.quick, mach, args.mem_res)
    if rows:
        write_csv(args.out / "threads_memory.csv", rows)


if __name__ == "__main__":
    main()
