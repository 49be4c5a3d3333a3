"""Error against time: torch_rbpt against Mitsuba 3, scene by scene.

For each scene, renders a converged reference once (Mitsuba at --ref-spp, cached in
benchmarks/cache/ by scene, size and spp; our own render when Mitsuba is absent, and the
tables say so), then sweeps the samples per pixel with both renderers in the same run and
measures, at each spp, the wall-clock time and the error against the reference: RMSE and
the mean relative error mean |img - ref| / max(|ref|, 0.02) (the tests'
metric). From the two curves it derives:

* the equal-error time ratio: for Mitsuba's RMSE at each spp, the time we need to reach that
  RMSE, interpolated log-log along our curve (outside our range, extrapolated from the
  nearest end with RMSE ~ time^-1/2, and marked '*'), divided by Mitsuba's time; and the
  median over the sweep;
* the equal-spp time ratio: our time / Mitsuba's time at the same spp;
* a bias check: the spp-weighted mean of all renders of the sweep against the reference's
  image mean, per renderer, with a noise estimate (a difference beyond noise is a bug).

Timing, "warm": best wall-clock time of --repeats renders (seeds 0, 1, ...), the two
renderers taking turns (so that a shared host's load changes hit both). Each turn renders
twice with the same spp: an untimed render (seed --repeats + k), then the timed one (seed k).
The untimed render absorbs what the other renderer leaves behind: its worker threads still
spinning for a few ms, and the caches it filled. Timed right after the other renderer, a
render took 2-15 ms longer (session 40, Zen 5: veach-mis at 4 spp 8.3 -> 10.4-12.3 ms, Mitsuba
13.4 -> 15.3-19.2 ms; cbox 21.2 -> 26.5-27.0 and 47.2 -> 50.4-50.7), which pulled the
equal-spp ratios of the short renders towards 1. Both images of a turn count towards the
error. Before the sweep at each spp,
  - ours: one untimed 1 spp render of the loaded scene (BSDF tables, page faults);
  - Mitsuba (llvm_ad_rgb): one untimed render of one pass at the same pass size and a
    different seed, so the JIT kernels are traced and compiled; with drjit's kernel
    history on, a timed render that still compiled a kernel is discarded and re-run (at
    most twice). Each timed Mitsuba render ends with dr.sync_thread().
Renders that exceed 2^22 samples go through mitsuba_ref's passes (equal-spp passes whose
film sums are added up and divided once, as one render of all their samples), for
references and sweep alike. The errors at each spp are the mean over the
2 x --repeats images (each with its own seed).

Writes benchmarks/results/error_time.csv, one PNG per scene (error_time_<scene>.png) and
error_time.png (all scenes). The CPU model, core count, torch threads, Mitsuba
version/variant and date head every table and are in every plot's title.

    python benchmarks/bench_error_time.py [--scenes cbox glossy] [--res 256]
        [--spp 4 16 64 256] [--ref-spp 4096] [--repeats 3] [--quick] [--no-mitsuba]
        [--mitsuba-isa avx2] [--out DIR]

--mitsuba-isa avx2 compiles Mitsuba's kernels as on an AVX2-only machine (Haswell, 8 lanes
instead of AVX-512's 16) and limits its Embree to AVX2 (mitsuba_ref.limit_embree: the script
re-runs itself with benchmarks/embree_max_isa.cpp preloaded, built with g++; until session 44
Embree kept the host's AVX-512 there); with torch_rbpt built by `MARCH=x86-64-v3 pip install
--no-build-isolation -e .`, both renderers run as they would there.

--res is the film width; the height follows each scene's aspect ratio (veach-mis is 3:2,
the others square). The default run (6 scenes, 256 wide, 4..256 spp, 3 repeats, 4096 spp
references) takes about 15-30 minutes on 2 cores, most of it the references (cached after).

RMSE caveat: on veach-mis the RMSE is dominated by the few pixels covering the smallest,
brightest emitter sphere (values ~100); the relative error is the steadier metric there.
"""
from __future__ import annotations

import argparse
import datetime
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import mitsuba_ref  # noqa: E402
from machine import built_for, cpu_model, write_csv  # noqa: E402

import torch_rbpt as tr  # noqa: E402
from torch_rbpt.render import render_with_stats  # noqa: E402

SHARED = HERE.parent.parent / "shared" / "scenes"
OWN = HERE / "scenes"

# name: (scene file, what it exercises)
SCENES = {
    "cbox": (SHARED / "cbox" / "cbox.xml", "shared cbox: mirror + glass spheres, tent filter, path max_depth 6"),
    "cornell-box": (SHARED / "cornell-box" / "scene_v3.xml", "Bitterli's Cornell box, path max_depth 65"),
    "veach-mis": (SHARED / "veach-mis" / "integrator_direct_both.xml", "Veach MIS, direct (1+1 samples), gaussian filter"),
    "bunny_box": (OWN / "bunny_box.xml", "69k-triangle bunny in a lit box, path max_depth 6"),
    "glossy": (OWN / "glossy.xml", "roughconductor (GGX, Beckmann) and roughplastic spheres"),
    "textured": (OWN / "textured.xml", "bitmap textures on walls and a sphere"),
}

INSTALL_MITSUBA = "pip install mitsuba && apt-get install -y libllvm19"
REF_SEED = 12345  # the reference's seed; the sweep uses 0, 1, ... (ours and Mitsuba's)
MIN_REL = 0.02


def make_texture(size: int = 128, tiles: int = 8) -> np.ndarray:
    """The procedural tile texture of scenes/textured.xml (scenes/textures/tiles.png was
    written from it with tr.write_image, sRGB-encoded): linear RGB in [0, 1], (size, size, 3).
    Tiles of varying colour with dark grout lines and a diagonal gradient."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64) / size
    i, j = np.floor(x * tiles), np.floor(y * tiles)
    hue = ((i * 3 + j * 5) % 7) / 7.0
    rgb = 0.5 + 0.4 * np.cos(2 * np.pi * (hue[..., None] + np.array([0.0, 1 / 3, 2 / 3])))
    rgb *= (0.6 + 0.4 * (x + y)[..., None] / 2)
    fx, fy = x * tiles - i, y * tiles - j
    grout = (np.minimum(fx, fy) < 0.08)[..., None]
    return np.where(grout, 0.05, rgb).clip(0, 1).astype(np.float32)


def ensure_texture() -> None:
    path = OWN / "textures" / "tiles.png"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tr.write_image(path, make_texture())


# ----------------------------------------------------------------------------- metrics

def rel_error(img: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean over pixels and channels of |img - ref| / max(|ref|, 0.02) (the tests' metric)."""
    return float(((img - ref).abs() / ref.abs().clamp(min=MIN_REL)).mean())


def rmse(img: torch.Tensor, ref: torch.Tensor) -> float:
    return float(((img.double() - ref.double()) ** 2).mean().sqrt())


def time_at_error(curve: list[tuple[float, float]], err: float) -> tuple[float, bool]:
    """Time at which a renderer whose (time, error) points are `curve` reaches `err`:
    piecewise linear in log(time)-log(error) between measured points (sorted by time);
    outside the measured errors, extrapolated from the nearest end point with
    error ~ time^-1/2 (Monte Carlo). Returns (time, extrapolated)."""
    pts = sorted((t, e) for t, e in curve if t > 0 and e > 0 and math.isfinite(t) and math.isfinite(e))
    if not pts or not (err > 0 and math.isfinite(err)):
        return float("nan"), False
    # first segment (in time order) whose errors bracket err
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if min(e0, e1) <= err <= max(e0, e1):
            if e0 == e1:
                return t0, False
            a = (math.log(err) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + a * (math.log(t1) - math.log(t0))), False
    if len(pts) == 1 or err > max(e for _, e in pts):
        t, e = min(pts, key=lambda p: -p[1])  # the largest-error point
    else:
        t, e = min(pts, key=lambda p: p[1])  # the smallest-error point
    if err == e:
        return t, False
    return t * (e / err) ** 2, True


# ----------------------------------------------------------------------------- machine



def machine_info(mitsuba: bool) -> dict:
    info = {"cpu": f"{cpu_model()}, torch_rbpt built for {built_for()}", "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__, "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
            "mitsuba": ""}
    if mitsuba:
        import drjit as dr
        info["mitsuba"] = (f"Mitsuba {mitsuba_ref.version()} {mitsuba_ref.variant()} "
                           f"({dr.thread_count()} threads, {mitsuba_ref.isa()})")
    return info


def header(info: dict) -> str:
    m = info["mitsuba"] or "Mitsuba: not run"
    return (f"{info['cpu']}, {info['cores']} cores, torch {info['torch']} ({info['torch_threads']} threads), "
            f"{m}, {info['date']}")


def short_header(info: dict) -> str:
    return f"{info['cpu']}, {info['cores']} cores, {info['date']}"


# ----------------------------------------------------------------------------- rendering

def film_size(path: Path, res: int) -> tuple[int, int]:
    """(width, height): width `res`, height from the scene's own film aspect ratio."""
    f = tr.load_file(path).sensor.film
    if f.crop is not None:
        raise ValueError(f"{path}: crop windows are not supported by this benchmark")
    return res, max(1, round(res * f.height / f.width))


def load_ours(path: Path, size: tuple[int, int]):
    scene = tr.load_file(path)
    scene.sensor.film.width, scene.sensor.film.height = size
    return scene


def render_ours(scene, spp: int, seed: int) -> tuple[torch.Tensor, int]:
    with torch.no_grad():
        return render_with_stats(scene, spp=spp, seed=seed)


def mitsuba_pass_spp(size: tuple[int, int], spp: int) -> int:
    """The spp of one pass of mitsuba_ref.render (same rule)."""
    w, h = size
    max_spp = max(1, mitsuba_ref.MAX_SAMPLES_PER_PASS // max(1, w * h))
    npass = -(-spp // max_spp)
    while spp % npass:
        npass += 1
    return spp // npass


def reference(name: str, path: Path, size: tuple[int, int], ref_spp: int, use_mitsuba: bool,
              cache: Path) -> tuple[torch.Tensor, str]:
    who = "mitsuba" if use_mitsuba else "ours"
    # ("sums": made as one film taking all its samples; the references cached before session
    # 49 averaged the normalised images of 64 spp passes, see mitsuba_ref.render.)
    file = cache / f"{name}_{size[0]}x{size[1]}_{ref_spp}spp_{who}_sums.exr"
    if file.exists():
        return tr.read_image(file), file.name
    print(f"  rendering the reference: {ref_spp} spp with {'Mitsuba' if use_mitsuba else 'torch_rbpt'} ...", flush=True)
    t0 = time.perf_counter()
    if use_mitsuba:
        mscene = mitsuba_ref.load_scene(path, width=size[0], height=size[1])
        img = torch.from_numpy(mitsuba_ref.render(mscene, ref_spp, seed=REF_SEED))
    else:
        # One render of all the samples (our film's memory is per pixel), not an average of
        # shorter renders' normalised images, which would keep their ratio bias.
        img = render_ours(load_ours(path, size), ref_spp, REF_SEED)[0].float()
    cache.mkdir(parents=True, exist_ok=True)
    tr.write_image(file, img)
    print(f"  reference done in {time.perf_counter() - t0:.1f} s -> {file}", flush=True)
    return img, file.name


class OursRenderer:
    name = "ours"

    def __init__(self, path: Path, size):
        self.scene = load_ours(path, size)
        render_ours(self.scene, 1, 999)  # warm-up (untimed): BSDF tables, page faults

    def warm(self, spp: int) -> None:
        pass

    def close(self) -> None:
        pass

    def timed(self, spp: int, seed: int) -> tuple[torch.Tensor, float, int]:
        """(image, wall-clock seconds, rays traced)."""
        t0 = time.perf_counter()
        img, rays = render_ours(self.scene, spp, seed)
        return img, time.perf_counter() - t0, rays


class MitsubaRenderer:
    name = "Mitsuba"

    def __init__(self, path: Path, size):
        import drjit as dr
        self.dr, self.size = dr, size
        self.scene = mitsuba_ref.load_scene(path, width=size[0], height=size[1])
        self.jit = not mitsuba_ref.variant().startswith("scalar")
        if self.jit:  # (a timed render that compiled a kernel shows in the history)
            self.flag = dr.flag(dr.JitFlag.KernelHistory)
            dr.set_flag(dr.JitFlag.KernelHistory, True)

    def close(self) -> None:
        if self.jit:
            self.dr.set_flag(self.dr.JitFlag.KernelHistory, self.flag)

    def warm(self, spp: int) -> None:
        if self.jit:  # one pass of the size the timed renders use, another seed
            mitsuba_ref.render(self.scene, mitsuba_pass_spp(self.size, spp), seed=REF_SEED + 777)
            self.dr.sync_thread()
            mitsuba_ref._compiled_kernels(self.dr)  # clears the history

    def timed(self, spp: int, seed: int) -> tuple[torch.Tensor, float, int]:
        dr = self.dr
        for attempt in range(3):
            dr.sync_thread()
            t0 = time.perf_counter()
            img = mitsuba_ref.render(self.scene, spp, seed=seed)
            dr.sync_thread()
            dt = time.perf_counter() - t0
            if not (self.jit and mitsuba_ref._compiled_kernels(dr)) or attempt == 2:
                break
            print(f"  Mitsuba  {spp:6d} spp: a timed render compiled a kernel; not counted, re-run", flush=True)
        return torch.from_numpy(img), dt, 0


def sweep(renderers: list, spps, repeats, ref) -> dict:
    """Each renderer's rows and spp-weighted mean image. The renderers take turns (ours,
    Mitsuba, ours, ...), so that both see the same load of a shared host; each turn is an
    untimed render and a timed one."""
    rows = {r.name: [] for r in renderers}
    acc = {r.name: torch.zeros_like(ref, dtype=torch.float64) for r in renderers}
    total = 0
    for spp in spps:
        for r in renderers:
            r.warm(spp)
        runs = {r.name: [] for r in renderers}
        errors = {r.name: [] for r in renderers}
        for k in range(repeats):
            for r in renderers:
                # An untimed render first (see the module's docstring), then the timed one.
                untimed, _, _ = r.timed(spp, repeats + k)
                img, dt, rays = r.timed(spp, k)
                for im in (untimed, img):
                    errors[r.name].append((rmse(im, ref), rel_error(im, ref)))
                    acc[r.name] += im.double() * spp
                runs[r.name].append((dt, rays))
            total += 2 * spp
        for r in renderers:
            t = min(x[0] for x in runs[r.name])
            rays = runs[r.name][0][1]
            rows[r.name].append({"spp": spp, "seconds": t,
                                 "rmse": statistics.fmean(e[0] for e in errors[r.name]),
                                 "rel_error": statistics.fmean(e[1] for e in errors[r.name]),
                                 "mrays_per_s": rays / t / 1e6 if rays else float("nan")})
            print(f"  {r.name:8s} {spp:6d} spp  {t:8.3f} s  RMSE {rows[r.name][-1]['rmse']:.5f}", flush=True)
    return {r.name: (rows[r.name], (acc[r.name] / total).float()) for r in renderers}


def bias(mean_img: torch.Tensor, ref: torch.Tensor) -> tuple[list[float], list[float]]:
    """Per channel: image mean of `mean_img` / image mean of `ref` - 1, and its noise
    (one standard deviation), estimated from the per-pixel differences (times 3 for the
    correlation of neighbouring pixels through the reconstruction filter)."""
    d = (mean_img.double() - ref.double()).reshape(-1, 3)
    m = ref.double().reshape(-1, 3).mean(0)
    rel = (d.mean(0) / m).tolist()
    sigma = (3 * d.std(0) / math.sqrt(d.shape[0]) / m).tolist()
    return rel, sigma


# ----------------------------------------------------------------------------- output

def fmt_ratio(r: float, extrap: bool) -> str:
    if not math.isfinite(r):
        return "-"
    return f"{r:.2f}{'*' if extrap else ' '}"


def print_table(sc: dict, info: dict) -> None:
    w, h = sc["size"]
    print(f"\n== {sc['name']}: {sc['what']}; {w}x{h}; reference {sc['ref_name']}"
          + ("" if sc["mitsuba_rows"] else " (our own render: Mitsuba not run)"))
    print(f"   {header(info)}")
    mits = {r["spp"]: r for r in sc["mitsuba_rows"]}
    print(f"{'spp':>6s} {'t ours':>9s} {'t Mitsuba':>9s} {'RMSE ours':>10s} {'RMSE Mits':>10s} "
          f"{'rel ours':>9s} {'rel Mits':>9s} {'eq-spp t':>9s} {'eq-err t':>9s}")
    for r in sc["ours_rows"]:
        m = mits.get(r["spp"])
        if m is None:
            print(f"{r['spp']:6d} {r['seconds']:9.3f} {'-':>9s} {r['rmse']:10.5f} {'-':>10s} "
                  f"{r['rel_error']:9.4f} {'-':>9s} {'-':>9s} {'-':>9s}")
        else:
            print(f"{r['spp']:6d} {r['seconds']:9.3f} {m['seconds']:9.3f} {r['rmse']:10.5f} {m['rmse']:10.5f} "
                  f"{r['rel_error']:9.4f} {m['rel_error']:9.4f} {r['seconds'] / m['seconds']:9.2f} "
                  f"{fmt_ratio(m['eq_error_ratio'], m['eq_error_extrapolated']):>9s}")
    if sc["mitsuba_rows"]:
        print(f"time ratio ours/Mitsuba, median over the sweep: at equal RMSE {sc['median_eq_error']:.2f}, "
              f"at equal spp {sc['median_eq_spp']:.2f}"
              + ("  (* = our time extrapolated with RMSE ~ time^-1/2)" if any(
                  m["eq_error_extrapolated"] for m in sc["mitsuba_rows"]) else ""))
    for who, (rel, sig) in sc["bias"].items():
        flag = "  <-- beyond noise" if any(abs(a) > 4 * s and abs(a) > 0.005 for a, s in zip(rel, sig)) else ""
        print(f"image mean / reference mean - 1 ({who}, all sweep renders): "
              + ", ".join(f"{a:+.4f}±{s:.4f}" for a, s in zip(rel, sig)) + flag)


def plot_scene(ax, sc: dict, full_title: bool, info: dict) -> None:
    from matplotlib import ticker
    for rows, label, style in ((sc["ours_rows"], "torch_rbpt", "o-"), (sc["mitsuba_rows"], "Mitsuba 3", "s--")):
        if not rows:
            continue
        t = [r["seconds"] for r in rows]
        e = [r["rmse"] for r in rows]
        ax.loglog(t, e, style, label=label)
        for r in rows:
            ax.annotate(str(r["spp"]), (r["seconds"], r["rmse"]), textcoords="offset points",
                        xytext=(4, 4), fontsize=7)
    for axis in (ax.xaxis, ax.yaxis):  # plain numbers at 1, 2, 5 x 10^k; no minor labels
        axis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(ticker.NullFormatter())
    ax.set_xlabel("time (s)")
    ax.set_ylabel("RMSE vs reference")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    w, h = sc["size"]
    title = f"{sc['name']} ({w}x{h})"
    if sc["mitsuba_rows"]:
        title += f", ours/Mitsuba at equal RMSE: {sc['median_eq_error']:.2f}"
    if full_title:
        title += f"\n{short_header(info)}"
    ax.set_title(title, fontsize=9)


def write_outputs(scenes: list[dict], info: dict, out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for sc in scenes:
        ours = {r["spp"]: r for r in sc["ours_rows"]}
        for renderer, scene_rows in (("torch_rbpt", sc["ours_rows"]), ("mitsuba", sc["mitsuba_rows"])):
            for r in scene_rows:
                o = ours.get(r["spp"])
                rows.append({
                    "scene": sc["name"], "width": sc["size"][0], "height": sc["size"][1],
                    "renderer": renderer, "spp": r["spp"], "seconds": f"{r['seconds']:.6g}",
                    "rmse": f"{r['rmse']:.6g}", "rel_error": f"{r['rel_error']:.6g}",
                    "mrays_per_s": "" if not math.isfinite(r["mrays_per_s"]) else f"{r['mrays_per_s']:.4g}",
                    "ours_seconds_at_equal_rmse": f"{r['ours_t_eq']:.6g}" if "ours_t_eq" in r else "",
                    "eq_error_ratio": f"{r['eq_error_ratio']:.4g}" if "eq_error_ratio" in r else "",
                    "eq_error_extrapolated": int(r["eq_error_extrapolated"]) if "eq_error_extrapolated" in r else "",
                    "eq_spp_ratio": f"{o['seconds'] / r['seconds']:.4g}" if renderer == "mitsuba" and o else "",
                    "repeats": sc["repeats"], "reference": sc["ref_name"], "cpu": info["cpu"],
                    "cores": info["cores"], "torch_threads": info["torch_threads"],
                    "mitsuba": info["mitsuba"], "date": info["date"]})
    csv_path = out / "error_time.csv"
    write_csv(csv_path, rows)

    for sc in scenes:
        fig, ax = plt.subplots(figsize=(5.5, 4.5))
        plot_scene(ax, sc, True, info)
        fig.tight_layout()
        fig.savefig(out / f"error_time_{sc['name']}.png", dpi=110)
        plt.close(fig)
    n = len(scenes)
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.9 * rows + 0.6), squeeze=False)
    for ax, sc in zip(axes.flat, scenes):
        plot_scene(ax, sc, False, info)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.suptitle(f"Error against time, torch_rbpt vs Mitsuba 3 (best of {scenes[0]['repeats']} warm runs)\n"
                 f"{header(info)}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "error_time.png", dpi=110)
    plt.close(fig)
    return csv_path


# ----------------------------------------------------------------------------- main

def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", choices=list(SCENES), default=list(SCENES))
    ap.add_argument("--res", type=int, default=256, help="film width (height keeps the scene's aspect)")
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64, 256])
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=3, help="timed renders per spp, each after an untimed one (best time; error: mean over both)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 64x64, spp 4 16, ref 256 spp, 1 repeat")
    ap.add_argument("--no-mitsuba", action="store_true", help="ours only, even if Mitsuba is installed")
    mitsuba_ref.add_isa_argument(ap)
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--cache", type=Path, default=HERE / "cache")
    args = ap.parse_args(argv)
    if args.quick:
        args.res, args.spp, args.ref_spp, args.repeats = 64, [4, 16], 256, 1
    if args.res <= 0 or args.ref_spp <= 0 or args.repeats <= 0 or any(s <= 0 for s in args.spp):
        ap.error("--res, --spp, --ref-spp and --repeats must be positive")
    args.spp = sorted(set(args.spp))
    return args


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    if not args.no_mitsuba:
        mitsuba_ref.limit_embree(args.mitsuba_isa, args.cache, reexec=argv is None)
    use_mitsuba = False
    if args.no_mitsuba:
        print("Mitsuba: not run (--no-mitsuba); references are our own renders.")
    elif mitsuba_ref.available():
        use_mitsuba = True
        mitsuba_ref.set_isa(args.mitsuba_isa)
    else:
        print("Mitsuba 3 is not available: skipping Mitsuba's renders, the time ratios and the "
              "Mitsuba references (references are our own renders). To install it: "
              f"{INSTALL_MITSUBA}")
    ensure_texture()
    info = machine_info(use_mitsuba)
    print(f"machine: {header(info)}")
    results = []
    for name in args.scenes:
        path, what = SCENES[name]
        if not path.exists():
            print(f"\n== {name}: skipped, {path} not found")
            continue
        size = film_size(path, args.res)
        print(f"\n[{name}] {size[0]}x{size[1]}, spp {args.spp}, {args.repeats} repeat(s)", flush=True)
        ref, ref_name = reference(name, path, size, args.ref_spp, use_mitsuba, args.cache)
        renderers = [OursRenderer(path, size)] + ([MitsubaRenderer(path, size)] if use_mitsuba else [])
        try:
            swept = sweep(renderers, args.spp, args.repeats, ref)
        finally:
            for r in renderers:
                r.close()
        ours_rows, ours_mean = swept["ours"]
        sc = {"name": name, "what": what, "size": size, "ref_name": ref_name, "repeats": args.repeats,
              "ours_rows": ours_rows, "mitsuba_rows": [], "bias": {"ours": bias(ours_mean, ref)}}
        if use_mitsuba:
            mrows, m_mean = swept["Mitsuba"]
            curve = [(r["seconds"], r["rmse"]) for r in ours_rows]
            ours_by_spp = {r["spp"]: r for r in ours_rows}
            for m in mrows:
                t, ext = time_at_error(curve, m["rmse"])
                m["ours_t_eq"], m["eq_error_extrapolated"] = t, ext
                m["eq_error_ratio"] = t / m["seconds"]
            sc["mitsuba_rows"] = mrows
            sc["median_eq_error"] = statistics.median(m["eq_error_ratio"] for m in mrows)
            sc["median_eq_spp"] = statistics.median(ours_by_spp[m["spp"]]["seconds"] / m["seconds"] for m in mrows)
            sc["bias"]["Mitsuba"] = bias(m_mean, ref)
        results.append(sc)
        print_table(sc, info)

    if not results:
        print("no scene rendered")
        return results
    print(f"\n\n######## summary: error against time, {header(info)}")
    for sc in results:
        print_table(sc, info)
    print("\nTimes: best of the repeats, warm (ours after an untimed 1 spp render; Mitsuba after "
          "an untimed render that compiled its JIT kernels), the two renderers taking turns, each "
          "turn an untimed render and a timed one. Errors: mean over all renders (2 x repeats).")
    write_outputs(results, info, args.out)
    print(f"wrote {args.out / 'error_time.png'} and error_time_<scene>.png")
    return results


if __name__ == "__main__":
    main()
