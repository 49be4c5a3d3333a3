"""Gradient error against time: torch_rbpt against Mitsuba 3's `prb` integrator.

    python benchmarks/bench_grad_error.py                 # res 64, spp 4..256, ref 4096 spp
    python benchmarks/bench_grad_error.py --quick         # seconds: a smoke run
    python benchmarks/bench_grad_error.py --no-mitsuba    # ours only

For each kind of parameter (below), the loss is the mean squared difference between the
rendered image and a fixed target image, rendered once with perturbed parameter values at the
reference spp (each renderer renders its own target, so a small difference between the two
renderers' images does not leak into the gradient comparison; the difference is printed).
The gradient d loss / d params is evaluated at the scene's values.

* reference gradient: the mean of `ref_spp / ref_chunk` independent runs (forward and backward
  seeds all distinct) at spp = spp_grad = ref_chunk, computed once per renderer and cached in
  benchmarks/cache/. Errors are measured against Mitsuba's reference if Mitsuba is available,
  else against ours. The spread of the chunks gives the reference's own standard error
  (printed); `err` includes it (at most ~3% inflation at spp <= ref_spp / 16), the CSV column
  `err_corr` subtracts it (unreliable for heavy-tailed estimators, whose chunk spread is
  dominated by rare outliers).
* sweep: spp = spp_grad in --spp; for each, one untimed warm-up run (another seed; compiles
  Mitsuba's kernels for this wavefront size), then --seeds timed runs of forward + loss +
  backward + gradient read-back. time is the median over seeds, err the root mean square over
  seeds of ||g - g_ref|| / ||g_ref||, figure of merit fom = time x err^2 (lower is better;
  ratio ours / Mitsuba, target <= 0.5). The seeds pin err^2 down only to its relative
  standard error (CSV `err2_rse`, the ratio's `fom_ratio_rse`); the geometric mean's line
  brackets it by one standard error.
* agreement: ||g_ours_ref - g_mi_ref|| / ||g_mi_ref|| beside its expected value from the two
  references' standard errors alone; a ratio (z) well above ~1.5 is a real disagreement.

Kinds (scene, keys):
  reflectance   shared cbox, all four diffuse reflectances (gray is defined but unused)
  texture       benchmarks/scenes/grad_texture.xml, tex.reflectance.data (32 x 32 EXR texture,
                written into the cache at first run)
  roughness     benchmarks/scenes/grad_rough.xml, metal.alpha.value (GGX roughconductor)
  beckmann      the same, the conductor Beckmann's (Mitsuba's default distribution)
  roughplastic  benchmarks/scenes/grad_rough.xml, plastic.alpha (GGX roughplastic); errors
                against our reference: Mitsuba's prb gradient of this parameter disagrees with
                finite differences of Mitsuba's own images (see kinds())

Mitsuba: variant llvm_ad_rgb through benchmarks/mitsuba_ref.py, the scene's integrator
replaced by `prb` with the same max_depth, `mi.render(scene, params, spp, spp_grad, seed,
seed_grad)` and `dr.backward`. Without Mitsuba (not installed, or --no-mitsuba) only ours
runs. Writes benchmarks/results/grad_error.csv, grad_error_<kind>.png, grad_error.png and
grad_reference_agreement.csv.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torch_rbpt as tr

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import mitsuba_ref  # noqa: E402  (benchmarks/mitsuba_ref.py; imports Mitsuba lazily)
from machine import built_for, cpu_model, write_csv  # noqa: E402

CBOX = HERE.parent.parent / "shared" / "scenes" / "cbox" / "cbox.xml"
SCENES = HERE / "scenes"
TEX_RES = 32



def _texture(kind: str) -> np.ndarray:
    """The texture the gradient is taken at ('current') and the target's ('target'), linear RGB
    (TEX_RES, TEX_RES, 3) float32."""
    y, x = np.meshgrid(np.linspace(0, 1, TEX_RES), np.linspace(0, 1, TEX_RES), indexing="ij")
    if kind == "current":
        checker = ((np.floor(x * 8) + np.floor(y * 8)) % 2).astype(np.float64)
        img = np.stack([0.2 + 0.5 * checker, 0.3 + 0.2 * x, 0.6 - 0.4 * checker * y], -1)
    else:
        img = np.stack([0.5 + 0.3 * np.sin(6 * x), 0.4 + 0.3 * y, 0.3 + 0.2 * np.cos(5 * x * y)], -1)
    return img.astype(np.float32)


def _perturb(values: dict) -> dict:
    """Target parameter values from the current ones."""
    out = {}
    for k, v in values.items():
        if k == "red.reflectance.value":
            out[k] = np.array([0.3, 0.15, 0.1])
        elif k == "green.reflectance.value":
            out[k] = np.array([0.2, 0.5, 0.1])
        elif k.endswith("reflectance.value"):
            out[k] = 0.8 * v
        elif k.endswith("reflectance.data"):
            out[k] = _texture("target")
        elif k.endswith("alpha.value") or k.endswith("alpha"):
            out[k] = 2.2 * v
        else:
            raise KeyError(k)
    return {k: np.asarray(v, np.float32).reshape(values[k].shape) for k, v in out.items()}


def kinds(cache: Path) -> dict:
    tex = cache / "grad_texture.exr"
    if not tex.exists():
        cache.mkdir(parents=True, exist_ok=True)
        tr.write_image(tex, torch.from_numpy(_texture("current")))
    refl = ["gray", "white", "green", "red"]
    return {
        "reflectance": dict(scene=CBOX, defaults={}, keys=[f"{m}.reflectance.value" for m in refl]),
        "texture": dict(scene=SCENES / "grad_texture.xml", defaults={"texture": str(tex)},
                        keys=["tex.reflectance.data"]),
        "roughness": dict(scene=SCENES / "grad_rough.xml", defaults={}, keys=["metal.alpha.value"]),
        "beckmann": dict(scene=SCENES / "grad_rough.xml", defaults={"metal_distribution": "beckmann"},
                         keys=["metal.alpha.value"]),
        # Mitsuba 3.9.1's prb gradient of a roughplastic's alpha is about 3.3x too small here
        # (-0.00114 where central finite differences of Mitsuba's own images, 1024 spp, give
        # -0.00372 and ours -0.00380): errors of this kind are measured against our reference.
        "roughplastic": dict(scene=SCENES / "grad_rough.xml", defaults={}, keys=["plastic.alpha"],
                             reference="torch_rbpt"),
    }


# ----------------------------------------------------------------------------- renderers

class Ours:
    name = "torch_rbpt"

    def __init__(self, kind: dict, res: int):
        self.scene_file = kind["scene"]
        self.scene = tr.load_file(kind["scene"], res=res, **kind["defaults"])
        self.keys = kind["keys"]
        self.params = [self.scene.params[k] for k in self.keys]
        for p in self.params:
            p.requires_grad_(True)

    def get(self) -> dict:
        return {k: p.detach().numpy().copy() for k, p in zip(self.keys, self.params)}

    def set(self, values: dict) -> None:
        with torch.no_grad():
            for k, p in zip(self.keys, self.params):
                p.copy_(torch.from_numpy(np.asarray(values[k], np.float32).reshape(p.shape)))

    def image(self, spp: int, seed: int) -> np.ndarray:
        with torch.no_grad():
            return tr.render(self.scene, spp=spp, seed=seed).numpy()

    def set_target(self, target: np.ndarray) -> None:
        self.target = torch.from_numpy(target)

    def grad(self, spp: int, seed: int, seed_grad: int) -> np.ndarray:
        image = tr.render(self.scene, spp=spp, seed=seed, spp_grad=spp, seed_grad=seed_grad)
        loss = ((image - self.target) ** 2).mean()
        grads = torch.autograd.grad(loss, self.params)
        return np.concatenate([g.numpy().ravel() for g in grads]).astype(np.float64)


class Mitsuba:
    name = "mitsuba_prb"

    def __init__(self, kind: dict, res: int):
        self.mi = mitsuba_ref._mitsuba()
        import drjit as dr
        self.dr = dr
        self.scene_file = kind["scene"]
        self.scene = mitsuba_ref.load_scene(kind["scene"], width=res, height=res, optimize=False,
                                            integrator="prb", **kind["defaults"])
        self.keys = kind["keys"]
        self.p = self.mi.traverse(self.scene)
        missing = [k for k in self.keys if k not in self.p]
        if missing:
            raise KeyError(f"Mitsuba has no parameter {missing}; it has {list(self.p.keys())}")
        for k in self.keys:
            self.dr.enable_grad(self.p[k])
        self.p.update()

    def get(self) -> dict:
        out = {}
        for k in self.keys:
            v = np.array(self.p[k], dtype=np.float32)
            out[k] = v if isinstance(self.p[k], self.mi.TensorXf) else v.ravel()
        return out

    def set(self, values: dict) -> None:
        mi = self.mi
        for k in self.keys:
            cur, v = self.p[k], np.asarray(values[k], np.float32)
            if isinstance(cur, mi.TensorXf):
                new = mi.TensorXf(np.ascontiguousarray(v.reshape(cur.shape)))
            elif isinstance(cur, mi.Color3f):
                new = mi.Color3f(*[float(x) for x in v.ravel()])
            else:
                new = type(cur)(v.ravel())
            self.p[k] = new
            self.dr.enable_grad(self.p[k])
        self.p.update()

    def image(self, spp: int, seed: int) -> np.ndarray:
        with self.dr.suspend_grad():
            return mitsuba_ref.render(self.scene, spp, seed=seed)

    def set_target(self, target: np.ndarray) -> None:
        self.target = self.mi.TensorXf(np.ascontiguousarray(target, dtype=np.float32))

    def grad(self, spp: int, seed: int, seed_grad: int) -> np.ndarray:
        dr, mi = self.dr, self.mi
        image = mi.render(self.scene, self.p, spp=spp, spp_grad=spp, seed=seed & 0xFFFFFFFF,
                          seed_grad=seed_grad & 0xFFFFFFFF)
        if image.shape[2] > 3:
            image = image[:, :, :3]
        loss = dr.mean(dr.square(image - self.target), axis=None)
        dr.backward(loss)
        out = []
        for k in self.keys:
            out.append(np.array(dr.grad(self.p[k]), dtype=np.float64).ravel())
            dr.clear_grad(self.p[k])
        dr.sync_thread()
        return np.concatenate(out)


# ----------------------------------------------------------------------------- measurement

def reference(r, kind_name: str, args, cache: Path) -> dict:
    """Target image and reference gradient of renderer r (cached): dict with 'target' (H, W, 3),
    'g' (mean gradient), 'se2' (squared standard error of the mean, summed over components)."""
    scene_text = Path(r.scene_file).read_text()
    tag = json.dumps([kind_name, r.name, args.res, args.ref_spp, args.ref_chunk, r.keys, scene_text,
                      mitsuba_ref.version() if r.name == "mitsuba_prb" else tr.__version__
                      if hasattr(tr, "__version__") else ""])
    path = cache / f"gradref_{kind_name}_{r.name}_{hashlib.sha1(tag.encode()).hexdigest()[:10]}.npz"
    if path.exists():
        d = np.load(path)
        return {k: d[k] for k in d.files}
    print(f"  [{r.name}] reference: target image and gradient at {args.ref_spp} spp "
          f"({args.ref_spp // args.ref_chunk} runs of {args.ref_chunk}; cached in {path.name}) ...",
          flush=True)
    start = time.perf_counter()
    current = r.get()
    r.set(_perturb(current))
    target = r.image(args.ref_spp, seed=777)
    r.set(current)
    r.set_target(target)
    n = max(1, args.ref_spp // args.ref_chunk)
    gs = np.stack([r.grad(args.ref_chunk, seed=100_000 + 2 * i, seed_grad=100_001 + 2 * i)
                   for i in range(n)])
    g = gs.mean(0)
    se2 = float(gs.var(0, ddof=1).sum() / n) if n > 1 else float("nan")
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, target=target, g=g, se2=se2)
    print(f"  [{r.name}] reference done in {time.perf_counter() - start:.1f} s", flush=True)
    return {"target": target, "g": g, "se2": np.float64(se2)}


def sweep(r, ref: dict, args) -> list:
    rows = []
    g_ref, se2 = ref["g"], float(ref["se2"]) if np.isfinite(ref["se2"]) else 0.0
    norm2 = float(g_ref @ g_ref)
    for spp in args.spp:
        r.grad(spp, seed=9_000 + spp, seed_grad=9_001 + spp)  # warm-up (JIT compilation)
        times, errs2 = [], []
        for s in range(args.seeds):
            seed = 1 + 2 * s + 1000 * spp
            start = time.perf_counter()
            g = r.grad(spp, seed=seed, seed_grad=seed + 1)
            times.append(time.perf_counter() - start)
            errs2.append(float((g - g_ref) @ (g - g_ref)))
        mse = float(np.mean(errs2))
        t = float(np.median(times))
        err = (mse / norm2) ** 0.5
        err_corr = (max(mse - se2, 0.0) / norm2) ** 0.5
        # The relative standard error of err^2 (the seeds' mean of squared errors): how far
        # the seeds pin the fom down (heavy-tailed estimators need many).
        err2_rse = (float(np.std(errs2, ddof=1)) / (len(errs2) ** 0.5 * mse)
                    if len(errs2) > 1 and mse > 0 else float("nan"))
        rows.append(dict(renderer=r.name, spp=spp, time_s=t, err=err, err_corr=err_corr,
                         fom=t * err ** 2, err2_rse=err2_rse))
        print(f"  [{r.name}] spp {spp:4d}: {t * 1000:9.1f} ms  err {err:.4f}", flush=True)
    return rows




def plot(results: dict, out: Path, header: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def draw(ax, name, rows):
        for renderer, marker in (("torch_rbpt", "o"), ("mitsuba_prb", "s")):
            rs = [r for r in rows if r["renderer"] == renderer]
            if not rs:
                continue
            ax.loglog([r["time_s"] for r in rs], [max(r["err"], 1e-6) for r in rs], marker=marker,
                      label=renderer)
            for r in rs:
                ax.annotate(str(r["spp"]), (r["time_s"], max(r["err"], 1e-6)), fontsize=7,
                            xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel("forward + backward time (s)")
        ax.set_ylabel("relative gradient error")
        ax.set_title(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()

    machine = (f"{header['cpu']}, {header['cores']} cores, {header['torch_threads']} threads, "
               f"Mitsuba {header['mitsuba']}, {header['date']}")
    for name, rows in results.items():
        fig, ax = plt.subplots(figsize=(5, 4.4))
        draw(ax, name, rows)
        ax.set_title(f"{name}\n{machine}", fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"grad_error_{name}.png", dpi=100)
        plt.close(fig)
    fig, axes = plt.subplots(1, len(results), figsize=(4.5 * len(results), 4), squeeze=False)
    for ax, (name, rows) in zip(axes[0], results.items()):
        draw(ax, name, rows)
    fig.suptitle(f"gradient error vs time (labels: spp = spp_grad); {machine}")
    fig.tight_layout()
    fig.savefig(out / "grad_error.png", dpi=100)
    plt.close(fig)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64, 256])
    ap.add_argument("--seeds", type=int, default=24,
                    help="timed runs per spp (the error is an RMS over them: with 4, one unlucky "
                         "seed can set it; with 12, the rough conductor's fom ratio at 16 spp "
                         "was 3.59 where 24 seeds give 1.43)")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--ref-chunk", type=int, default=256, help="spp of each reference run")
    ap.add_argument("--kinds", nargs="+", default=None, help="subset of: reflectance texture roughness beckmann roughplastic")
    ap.add_argument("--quick", action="store_true", help="res 16, spp 2 8, 2 seeds, ref 64 spp")
    ap.add_argument("--no-mitsuba", action="store_true", help="ours only")
    mitsuba_ref.add_isa_argument(ap)
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--cache", default=str(HERE / "cache"))
    args = ap.parse_args(argv)
    if args.quick:
        args.res, args.spp, args.seeds, args.ref_spp, args.ref_chunk = 16, [2, 8], 2, 64, 16
    out, cache = Path(args.out), Path(args.cache)
    if not args.no_mitsuba:
        mitsuba_ref.limit_embree(args.mitsuba_isa, cache, reexec=argv is None)
    out.mkdir(parents=True, exist_ok=True)

    use_mi, why = False, "--no-mitsuba"
    if not args.no_mitsuba:
        use_mi = mitsuba_ref.available()
        if not use_mi:
            why = "Mitsuba not available"
        else:
            mitsuba_ref.set_isa(args.mitsuba_isa)
    mi_version = mitsuba_ref.version() if use_mi else ""
    if not use_mi:
        print(f"Mitsuba 3 skipped ({why}): only torch_rbpt runs, errors are against its own "
              f"reference. To compare, {mitsuba_ref.INSTALL_HINT}.")
    header = dict(cpu=f"{cpu_model()}, torch_rbpt built for {built_for()}", cores=os.cpu_count(),
                  torch_threads=torch.get_num_threads(),
                  date=datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
                  mitsuba=f"{mi_version} ({mitsuba_ref.variant()}, {mitsuba_ref.isa()})" if use_mi else "skipped")

    all_kinds = kinds(cache)
    names = args.kinds or list(all_kinds)
    results, agreement, csv_rows = {}, [], []
    for name in names:
        kind = all_kinds[name]
        print(f"== {name}: {kind['scene'].name} {kind['keys']}", flush=True)
        renderers = [Ours(kind, args.res)] + ([Mitsuba(kind, args.res)] if use_mi else [])
        refs = {}
        for r in renderers:
            refs[r.name] = reference(r, name, args, cache)
            r.set_target(refs[r.name]["target"])
        ref_name = kind.get("reference", "mitsuba_prb") if use_mi else "torch_rbpt"
        g_ref = refs[ref_name]["g"]
        norm = float(np.linalg.norm(g_ref))
        ref_se = float(np.sqrt(max(float(refs[ref_name]["se2"]), 0.0))) / norm
        if use_mi:
            a, b = refs["torch_rbpt"], refs["mitsuba_prb"]
            diff = float(np.linalg.norm(a["g"] - b["g"])) / norm
            expected = float(np.sqrt(float(a["se2"]) + float(b["se2"]))) / norm
            img_diff = float(np.linalg.norm(a["target"] - b["target"]) / np.linalg.norm(b["target"]))
            agreement.append(dict(kind=name, keys=" ".join(kind["keys"]), rel_diff=diff,
                                  expected_noise=expected, z=diff / expected if expected else float("nan"),
                                  target_image_rel_diff=img_diff,
                                  g_ours=" ".join(f"{x:.5g}" for x in a["g"][:12]),
                                  g_mitsuba=" ".join(f"{x:.5g}" for x in b["g"][:12])))
        rows = []
        for r in renderers:
            rows += sweep(r, refs[ref_name], args)
        results[name] = rows
        mi_rows = {r["spp"]: r for r in rows if r["renderer"] == "mitsuba_prb"}
        for r in rows:
            m = mi_rows.get(r["spp"])
            r["fom_ratio"] = (r["fom"] / m["fom"] if m and m["fom"] > 0 and r["renderer"] == "torch_rbpt"
                              else float("nan"))
            # Its relative standard error from both renderers' errors (the times' is far smaller).
            r["fom_ratio_rse"] = ((r["err2_rse"] ** 2 + m["err2_rse"] ** 2) ** 0.5
                                  if m and r["renderer"] == "torch_rbpt" else float("nan"))
            csv_rows.append(dict(kind=name, keys=" ".join(kind["keys"]), res=args.res, seeds=args.seeds,
                                 reference=ref_name, ref_spp=args.ref_spp, ref_rel_se=ref_se,
                                 **r, **header))
        kind["ref_se"] = ref_se
        del renderers

    # Print the tables.
    print(f"\n{header['cpu']}, {header['cores']} cores, torch threads {header['torch_threads']}, "
          f"{header['date']}, Mitsuba {header['mitsuba']}")
    print(f"res {args.res}x{args.res}, spp = spp_grad, {args.seeds} seeds per spp; reference: "
          f"{'Mitsuba prb (roughplastic: ours)' if use_mi else 'torch_rbpt'} at {args.ref_spp} spp")
    for name, rows in results.items():
        kind = all_kinds[name]
        ref_by = kind.get("reference", "mitsuba_prb") if use_mi else "torch_rbpt"
        print(f"\n{name}: {kind['scene'].name} {', '.join(kind['keys'])} "
              f"(reference: {ref_by}, rel. std. error {kind['ref_se']:.4f})")
        print(f"{'spp':>5s} | {'ours ms':>9s} {'err':>8s} | {'mitsuba ms':>10s} {'err':>8s} | "
              f"{'time ratio':>10s} {'fom ratio':>9s}")
        ours = {r["spp"]: r for r in rows if r["renderer"] == "torch_rbpt"}
        mit = {r["spp"]: r for r in rows if r["renderer"] == "mitsuba_prb"}
        for spp, o in ours.items():
            m = mit.get(spp)
            ms = f"{m['time_s'] * 1000:10.1f} {m['err']:8.4f}" if m else f"{'-':>10s} {'-':>8s}"
            ratio = f"{o['time_s'] / m['time_s']:10.2f} {o['fom_ratio']:9.2f}" if m else f"{'-':>10s} {'-':>9s}"
            print(f"{spp:5d} | {o['time_s'] * 1000:9.1f} {o['err']:8.4f} | {ms} | {ratio}")
        kept = [r for r in rows if np.isfinite(r.get("fom_ratio", float("nan"))) and r["fom_ratio"] > 0]
        if kept:
            # The geometric mean's standard error in log space, from the rows' (independent
            # seeds at each spp): exp(+-) of it brackets the mean.
            log_mean = float(np.mean([np.log(r["fom_ratio"]) for r in kept]))
            log_se = float(np.sqrt(np.sum([r["fom_ratio_rse"] ** 2 for r in kept]))) / len(kept)
            band = (f" (one standard error of the seeds' errors: {np.exp(log_mean - log_se):.2f}-"
                    f"{np.exp(log_mean + log_se):.2f})" if np.isfinite(log_se) else "")
            print(f"fom ratio ours/Mitsuba (time x err^2; target <= 0.5): geometric mean "
                  f"{float(np.exp(log_mean)):.2f}{band}")
    if agreement:
        print("\nConverged gradients, ours vs Mitsuba prb (each at the reference spp, own target image):")
        print(f"{'kind':13s} {'rel diff':>9s} {'noise':>8s} {'z':>6s} {'target img diff':>15s}")
        for a in agreement:
            print(f"{a['kind']:13s} {a['rel_diff']:9.4f} {a['expected_noise']:8.4f} {a['z']:6.2f} "
                  f"{a['target_image_rel_diff']:15.4f}")
            if a["kind"] != "texture":
                print(f"{'':13s} ours    {a['g_ours']}\n{'':13s} mitsuba {a['g_mitsuba']}")
        write_csv(out / "grad_reference_agreement.csv", [{**a, **header} for a in agreement])
    elif not use_mi:
        print(f"\nMitsuba 3 comparison skipped ({why}); {mitsuba_ref.INSTALL_HINT}.")

    write_csv(out / "grad_error.csv", csv_rows)
    plot(results, out, header)
    print(f"wrote grad_error.png, grad_error_<kind>.png to {out}")
    return {"rows": csv_rows, "agreement": agreement}


if __name__ == "__main__":
    main()
