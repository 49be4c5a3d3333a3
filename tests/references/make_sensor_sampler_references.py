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


# Sensors whose sample_ray outputs rays.json records (film 64 x 48 unless given), for
# (position sample, aperture sample) pairs in [0, 1]^2 (position relative to the crop window).
RAY_SENSORS = {
    "orthographic_default": dict(type="orthographic"),
    "orthographic_scaled": dict(type="orthographic", to_world=("scale", [2, 3, 1])),
    "orthographic_lookat": dict(type="orthographic", near_clip=0.5, far_clip=7.0,
                                to_world=("lookat_scale", [1, 1, 1], [1, 2, 1], [0, 0, 1], [10, 10, 1])),
    "orthographic_crop": dict(type="orthographic", crop=(16, 8, 32, 16)),
    "thinlens_default": dict(type="thinlens", aperture_radius=0.1),
    "thinlens_focus": dict(type="thinlens", aperture_radius=0.1, focus_distance=2.0, fov=40.0),
    "thinlens_lookat": dict(type="thinlens", aperture_radius=0.3, focus_distance=3.0, fov=30.0,
                            fov_axis="y", near_clip=0.1, far_clip=50.0,
                            to_world=("lookat_scale", [0, 1, 5], [0, 0, 0], [0, 1, 0], [1, 1, 1])),
}
RAY_SAMPLES = [((0.5, 0.5), (0.5, 0.5)), ((0.0, 0.0), (0.5, 0.5)), ((1.0, 1.0), (0.5, 0.5)),
               ((1.0, 0.0), (0.5, 0.5)), ((0.5, 0.5), (1.0, 0.5)), ((0.0, 0.0), (1.0, 0.5)),
               ((0.5, 0.5), (0.9, 0.7)), ((0.2, 0.7), (0.1, 0.3))]


def sensor_rays():
    """sample_ray(time 0, wavelength 0.5, position, aperture) of each RAY_SENSORS entry, in
    the scalar_rgb variant; written to sensors_samplers/rays.json."""
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    T = mi.ScalarTransform4f
    out = {}
    for name, desc in RAY_SENSORS.items():
        d = {k: v for k, v in desc.items() if k not in ("to_world", "crop")}
        film = {"type": "hdrfilm", "width": 64, "height": 48}
        if "crop" in desc:
            x, y, w, h = desc["crop"]
            film.update(crop_offset_x=x, crop_offset_y=y, crop_width=w, crop_height=h)
        d["film"] = film
        if "to_world" in desc:
            kind, *args = desc["to_world"]
            d["to_world"] = (T().scale(args[0]) if kind == "scale" else
                             T().look_at(origin=args[0], target=args[1], up=args[2]) @ T().scale(args[3]))
        sensor = mi.load_dict(d)
        rays = []
        for pos, ap in RAY_SAMPLES:
            ray, weight = sensor.sample_ray(0.0, 0.5, mi.Point2f(*pos), mi.Point2f(*ap))
            rays.append(dict(position=pos, aperture=ap, o=list(map(float, ray.o)),
                             d=list(map(float, ray.d)), maxt=float(ray.maxt),
                             weight=list(map(float, weight))))
        params = {k: (float(v) if not hasattr(v, "matrix") else None)
                  for k, v in mi.traverse(sensor).items() if not k.startswith("film.")}
        out[name] = dict(sensor={k: v for k, v in desc.items()}, rays=rays,
                         traverse=sorted(mi.traverse(sensor).keys()),
                         traverse_values={k: v for k, v in params.items() if v is not None})
    with open(os.path.join(FOLDER, "rays.json"), "w") as f:
        json.dump(dict(description="Mitsuba 3.9.1 (scalar_rgb) sensor.sample_ray outputs; made by "
                                   "tests/references/make_sensor_sampler_references.py", sensors=out),
                  f, indent=1)
    print("wrote rays.json (%d sensors)" % len(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", type=int, default=32768, help="total spp per reference")
    ap.add_argument("--only", nargs="*", default=None, help="reference names, or 'rays' for rays.json only")
    args = ap.parse_args()
    if args.only == ["rays"]:
        return sensor_rays()
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
    if not args.only:
        sensor_rays()


if __name__ == "__main__":
    main()
