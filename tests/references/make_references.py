"""Render Mitsuba 3 reference images for torch_rbpt's tests.

    python tests/references/make_references.py [--spp-scale S] [--only NAME ...]

Writes, next to this file, one float32 RGB OpenEXR per reference (ZIP-compressed, linear
radiance, Mitsuba's developed film: filtered and normalised) and ``references.json``.

Each reference is the average of two half-spp renders with different seeds (1 and 2; each
half is split into passes with seeds derived from its seed, see benchmarks/mitsuba_ref.py).
Their difference estimates Mitsuba's own noise:

    noise = mean over pixels and channels of |a - b| / max(|ref|, 0.02)

(``noise_half_diff`` in the json; the reference itself, the mean of a and b, has an error
about half of that, stored as ``noise_ref_est``).

The three veach-mis references share one expectation: the ``direct`` integrator with
(emitter_samples, bsdf_samples) = (1, 1), (0, 1) or (1, 0) is an unbiased estimator of the
same direct illumination (with only one strategy its MIS weight is 1).  BSDF-only sampling
of the small spheres is extremely noisy (noise ~0.65 at 2048 spp, hardly decreasing), so
all three EXRs hold the converged render of integrator_direct_both.xml, and for _bsdf and
_lum the json also records a check render with the file's own integrator and how far it is
from that reference compared to its own noise (``consistency``).

The spp were chosen from pilot runs (noise ~ c / sqrt(spp)) to keep the whole script within
about 12 minutes on 2 cores; ``--spp-scale`` multiplies them (e.g. 4 for lower noise).
"""

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
SHARED = os.path.normpath(os.path.join(ROOT, "..", "shared"))
if not os.path.isdir(os.path.join(SHARED, "scenes")):
    SHARED = "/work/shared"
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

import mitsuba_ref  # noqa: E402

SEEDS = (1, 2)
FLOOR = 0.02

# name, scene file (relative to /work/shared, or to the project root when it starts with
# torch_rbpt/ or tests/), defaults, width, height,
# total spp, optional: file rendered instead (same expectation), spp of the own-integrator check.
REFERENCES = [
    dict(name="cbox", scene="scenes/cbox/cbox.xml", defaults=dict(res=64), spp=106496),
    dict(name="cornell_box_shared", scene="scenes/cornell-box/scene_v3.xml",
         defaults=dict(resx=64, resy=64), spp=49152),
    dict(name="veach_mis_both", scene="scenes/veach-mis/integrator_direct_both.xml",
         width=96, height=64, spp=98304),
    dict(name="veach_mis_bsdf", scene="scenes/veach-mis/integrator_direct_bsdf.xml",
         width=96, height=64, same_as="veach_mis_both", check_spp=8192),
    dict(name="veach_mis_lum", scene="scenes/veach-mis/integrator_direct_lum.xml",
         width=96, height=64, same_as="veach_mis_both", check_spp=8192),
    dict(name="cornell_box", scene="torch_rbpt/scenes/cornell_box.xml",
         defaults=dict(res=64), spp=49152),
    # Small scenes of Mitsuba features (tests/references/scenes/): <spectrum>, a version 2.0.0
    # file, top-level objects referenced before their declaration, $name without <default>;
    # checkerboard and bitmap to_uv; filters with negative lobes.
    dict(name="spectra", scene="tests/references/scenes/spectra.xml",
         defaults=dict(res=64, spp=16), spp=65536),
    dict(name="textures", scene="tests/references/scenes/textures.xml", spp=65536),
    dict(name="filter_mitchell", scene="tests/references/scenes/filters.xml",
         defaults=dict(filter="mitchell"), spp=65536),
    dict(name="filter_catmullrom", scene="tests/references/scenes/filters.xml",
         defaults=dict(filter="catmullrom"), spp=65536),
    dict(name="filter_lanczos", scene="tests/references/scenes/filters.xml",
         defaults=dict(filter="lanczos"), spp=65536),
]


def scene_path(rel):
    if rel.startswith(("torch_rbpt/", "tests/")):
        return os.path.join(ROOT, rel)
    return os.path.join(SHARED, rel)


def noise(a, b, ref):
    return float(np.mean(np.abs(a - b) / np.maximum(np.abs(ref), FLOOR)))


def write_exr(path, img):
    import OpenImageIO as oiio
    img = np.ascontiguousarray(img, dtype=np.float32)
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], 3, oiio.FLOAT)
    spec.channelnames = ("R", "G", "B")
    spec.attribute("compression", "zip")
    out = oiio.ImageOutput.create(path)
    if out is None or not out.open(path, spec):
        raise RuntimeError("cannot write %s: %s" % (path, oiio.geterror()))
    out.write_image(img)
    out.close()


def read_exr(path):
    import OpenImageIO as oiio
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise RuntimeError("cannot read %s: %s" % (path, oiio.geterror()))
    img = inp.read_image(format=oiio.FLOAT)
    inp.close()
    return np.asarray(img, dtype=np.float32)[..., :3]


def render_pair(scene, spp):
    half = spp // 2
    ta, a = mitsuba_ref.time_render(scene, half, seed=SEEDS[0])
    tb, b = mitsuba_ref.time_render(scene, half, seed=SEEDS[1])
    return ta + tb, a, b


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--spp-scale", type=float, default=1.0)
    ap.add_argument("--only", nargs="*", default=None, help="names to (re)render")
    args = ap.parse_args()

    if not mitsuba_ref.available():
        sys.exit("Mitsuba 3 is not available; cannot make references.")
    print("Mitsuba %s, variant %s" % (mitsuba_ref.version(), mitsuba_ref.variant()))
    jpath = os.path.join(HERE, "references.json")
    meta = {}
    if os.path.exists(jpath):
        with open(jpath) as f:
            meta = json.load(f).get("references", {})
    images = {}
    t_start = time.time()
    for r in REFERENCES:
        name = r["name"]
        if args.only and name not in args.only and not any(
                o == r.get("same_as") for o in args.only):
            continue
        w, h = r.get("width"), r.get("height")
        defaults = r.get("defaults", {})
        scene = mitsuba_ref.load_scene(scene_path(r["scene"]), w, h, **defaults)
        film = scene.sensors()[0].film()
        fw, fh = (int(v) for v in film.size())
        entry = dict(scene=r["scene"][len("scenes/"):] if r["scene"].startswith("scenes/")
                     else r["scene"], defaults=defaults, width=fw, height=fh,
                     rfilter=str(film.rfilter()).split("[")[0],
                     mitsuba_version=mitsuba_ref.version(), variant=mitsuba_ref.variant(),
                     exr=name + ".exr", exr_format="OpenEXR, float32 RGB (R,G,B), ZIP")
        if w is not None:
            entry["film_override"] = [w, h]
        # render_seconds are wall-clock; record how busy the (2-core) machine was
        entry["load_avg_1min_before"] = round(os.getloadavg()[0], 2)
        if "same_as" in r:
            if r["same_as"] not in images:  # not rendered in this run: use the stored one
                images[r["same_as"]] = dict(
                    ref=read_exr(os.path.join(HERE, r["same_as"] + ".exr")),
                    entry=meta[r["same_as"]])
            src = images[r["same_as"]]
            ref = src["ref"]
            spp = int(round(r["check_spp"] * args.spp_scale / 2)) * 2
            print("[%s] expectation equal to %s; check render %dx%d, %d spp ..."
                  % (name, r["same_as"], fw, fh, spp), flush=True)
            secs, a, b = render_pair(scene, spp)
            own = 0.5 * (a + b)
            d_ab = noise(a, b, ref)
            d_own = float(np.mean(np.abs(own - ref) / np.maximum(np.abs(ref), FLOOR)))
            entry.update(
                rendered_from=src["entry"]["scene"],
                spp=src["entry"]["spp"], seeds=list(SEEDS),
                render_seconds=src["entry"]["render_seconds"],
                noise_half_diff=src["entry"]["noise_half_diff"],
                noise_ref_est=src["entry"]["noise_ref_est"],
                consistency=dict(
                    note=("render with this file's own integrator (two halves a, b) vs the "
                          "reference; unbiased => own_vs_ref ~ half_diff / 2 and "
                          "rel_mean_diff ~ 0 within noise"),
                    spp=spp, seeds=list(SEEDS), render_seconds=round(secs, 2),
                    half_diff=round(d_ab, 5), own_vs_ref=round(d_own, 5),
                    rel_mean_diff=round(float(own.mean() / ref.mean() - 1), 5),
                    rel_mean_diff_halves=round(float((a.mean() - b.mean()) / ref.mean()), 5)))
            print("   consistency: half-diff %.4f, own-vs-ref %.4f (expect ~%.4f), "
                  "rel. mean diff %+.4f (halves differ by %+.4f)"
                  % (d_ab, d_own, d_ab / 2, entry["consistency"]["rel_mean_diff"],
                     entry["consistency"]["rel_mean_diff_halves"]), flush=True)
        else:
            spp = int(round(r["spp"] * args.spp_scale / 2)) * 2
            print("[%s] %s %dx%d defaults=%s, %d spp (2 x %d) ..."
                  % (name, r["scene"], fw, fh, defaults, spp, spp // 2), flush=True)
            secs, a, b = render_pair(scene, spp)
            ref = 0.5 * (a + b)
            d = noise(a, b, ref)
            entry.update(spp=spp, seeds=list(SEEDS), render_seconds=round(secs, 2),
                         noise_half_diff=round(d, 5), noise_ref_est=round(d / 2, 5))
            print("   %.1f s, noise (half-spp diff) %.4f, mean %.5f"
                  % (secs, d, float(ref.mean())), flush=True)
        images[name] = dict(ref=ref, entry=entry)
        write_exr(os.path.join(HERE, name + ".exr"), ref)
        meta[name] = entry
        print("   wrote %s (%d bytes)" % (name + ".exr",
                                         os.path.getsize(os.path.join(HERE, name + ".exr"))))
    doc = dict(
        description=("Mitsuba 3 reference renders for torch_rbpt; made by "
                     "tests/references/make_references.py. Scene paths are relative to "
                     "/work/shared (../shared from the project root) unless they start with "
                     "torch_rbpt/. Each image is the mean of two half-spp renders with seeds "
                     "'seeds'; noise_half_diff = mean |a-b|/max(|ref|,0.02) over pixels and "
                     "channels; noise_ref_est = noise_half_diff/2 estimates the reference's "
                     "own relative error. render_seconds is wall-clock time on a 2-core machine; "
                     "load_avg_1min_before (if present) shows how busy it was (this script's own "
                     "previous render alone gives ~2)."),
        references=meta)
    with open(jpath, "w") as f:
        json.dump(doc, f, indent=2)
    print("wrote references.json; total %.1f s" % (time.time() - t_start))


if __name__ == "__main__":
    main()
