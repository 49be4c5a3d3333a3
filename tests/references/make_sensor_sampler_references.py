"""Render Mitsuba 3 references for the sampler and sensor tests (tests/test_samplers.py,
tests/test_sensors.py).

    python tests/references/make_sensor_sampler_references.py [--spp N] [--only NAME ...]

Scenes are in sensors_samplers/ (content.xml shared by samplers.xml, orthographic.xml and
thinlens.xml). Writes sensors_samplers/<name>.exr (float32 RGB, ZIP) and
sensors_samplers/references.json. As make_references.py, each reference is the mean of two
half-spp renders (seeds 1 and 2), and noise_half_diff = mean |a - b| / max(|ref|, 0.02).

The sampler references render samplers.xml with each of Mitsuba's samplers: the expectation
is the same for all of them, so agreement of ours with each (and of Mitsuba's with each
other, printed as ``vs_first``) shows every sampler is unbiased in both renderers.
"""

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
FOLDER = os.path.join(HERE, "sensors_samplers")
sys.path.insert(0, os.path.normpath(os.path.join(HERE, "..", "..", "benchmarks")))
sys.path.insert(0, HERE)

import mitsuba_ref  # noqa: E402
from make_references import noise, write_exr  # noqa: E402

SEEDS = (1, 2)

# name -> (scene file, defaults)
REFERENCES = {
    "sampler_stratified": ("samplers.xml", dict(sampler="stratified", spp=64)),
    "sampler_multijitter": ("samplers.xml", dict(sampler="multijitter", spp=64)),
    "sampler_orthogonal": ("samplers.xml", dict(sampler="orthogonal", spp=49)),
    "sampler_ldsampler": ("samplers.xml", dict(sampler="ldsampler", spp=64)),
    "orthographic": ("orthographic.xml", dict(spp=64)),
    "thinlens": ("thinlens.xml", dict(spp=64)),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", type=int, default=32768, help="total spp per reference")
    ap.add_argument("--only", nargs="*", default=None)
    args = ap.parse_args()
    if not mitsuba_ref.available():
        sys.exit("Mitsuba 3 is not available; cannot make references.")
    print("Mitsuba %s, variant %s" % (mitsuba_ref.version(), mitsuba_ref.variant()))
    jpath = os.path.join(FOLDER, "references.json")
    meta = json.load(open(jpath))["references"] if os.path.exists(jpath) else {}
    first = None
    for name, (scene_file, defaults) in REFERENCES.items():
        if args.only and name not in args.only:
            continue
        scene = mitsuba_ref.load_scene(os.path.join(FOLDER, scene_file), **defaults)
        sensor = scene.sensors()[0]
        half = args.spp // 2
        t0 = time.time()
        a = mitsuba_ref.render(scene, half, seed=SEEDS[0])
        b = mitsuba_ref.render(scene, half, seed=SEEDS[1])
        secs = time.time() - t0
        ref = 0.5 * (a + b)
        d = noise(a, b, ref)
        entry = dict(scene=scene_file, defaults=defaults, spp=2 * half, seeds=list(SEEDS),
                     sensor=str(sensor).split("[")[0], sampler=str(sensor.sampler()).split("[")[0],
                     width=int(sensor.film().size()[0]), height=int(sensor.film().size()[1]),
                     mitsuba_version=mitsuba_ref.version(), variant=mitsuba_ref.variant(),
                     exr=name + ".exr", render_seconds=round(secs, 2),
                     noise_half_diff=round(d, 5), noise_ref_est=round(d / 2, 5),
                     mean=float(ref.mean()))
        if name.startswith("sampler_"):
            if first is None:
                first = ref
            entry["vs_first"] = round(float(np.mean(np.abs(ref - first) / np.maximum(np.abs(first), 0.02))), 5)
        print("[%s] %s %s, %d spp: %.1f s, noise %.4f, mean %.5f%s" % (
            name, entry["sensor"], entry["sampler"], entry["spp"], secs, d, entry["mean"],
            ", vs first sampler %.4f" % entry["vs_first"] if "vs_first" in entry else ""), flush=True)
        write_exr(os.path.join(FOLDER, name + ".exr"), ref)
        meta[name] = entry
    doc = dict(description="Mitsuba 3 references for the sampler and sensor tests; made by "
                           "tests/references/make_sensor_sampler_references.py.",
               references=meta)
    with open(jpath, "w") as f:
        json.dump(doc, f, indent=2)


if __name__ == "__main__":
    main()
