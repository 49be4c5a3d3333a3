"""Command line: python -m torch_rbpt render SCENE.xml -o OUT.exr [--spp N] [-D name=value]"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from . import load_file, render, write_image
from .mitsuba_xml import SceneError


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torch_rbpt", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render a Mitsuba 3 XML scene to an image")
    r.add_argument("scene", help="scene file (Mitsuba 3 XML)")
    r.add_argument("-o", "--output", required=True, help="output image (.exr linear; .png/.jpg sRGB)")
    r.add_argument("--spp", type=int, default=None, help="samples per pixel (default: the scene's)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                   help="override a <default> of the scene (repeatable)")
    r.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    args = parser.parse_args(argv)

    defaults = {}
    for d in args.defines:
        if "=" not in d:
            parser.error(f"-D expects NAME=VALUE, got '{d}'")
        name, value = d.split("=", 1)
        defaults[name] = value
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        scene = load_file(args.scene, **defaults)
    except (SceneError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    height = scene.sensor.film.crop_window()[3]
    spp = args.spp or scene.sensor.spp
    # Render in bands of rows to show progress; bands are bitwise identical to a full render.
    band = max(1, min(height, 4096 * 64 // max(1, scene.sensor.film.crop_window()[2] * spp)))
    start = time.perf_counter()
    parts = []
    with tqdm(total=height, unit="row", desc=Path(args.scene).name) as bar:
        for y in range(0, height, band):
            parts.append(render(scene, spp=spp, seed=args.seed, rows=(y, min(height, y + band))))
            bar.update(parts[-1].shape[0])
    image = torch.cat(parts, dim=0)
    elapsed = time.perf_counter() - start
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_image(out, image)
    if out.suffix.lower() == ".exr":
        write_image(out.with_suffix(".png"), image)
    taken = scene.sensor.sample_count(spp)
    rounded = f" ({scene.sensor.sampler} sampler: {spp} rounded to {taken})" if taken != spp else ""
    print(f"{image.shape[1]}x{image.shape[0]}, {taken} spp{rounded}, {elapsed:.2f} s -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
