"""The gradient of every pixel with respect to the red wall's colour (the technical report's
Figure 1), by radiative backpropagation and by forward-mode dual numbers, side by side.

The image is d(red channel of pixel p) / d(red channel of the red wall's reflectance) for
every pixel p (the report's "left wall"; the shared cbox, rendered as Mitsuba renders it,
has its red wall on the right, the bundled Cornell box on the left). Forward mode gets it in one render with dual numbers (`render_forward`).
Reverse mode gets one number per backward pass: each pixel is one call of
`torch.autograd.grad(image, wall, grad_outputs=one_hot(p))` on a single forward render. That
is cheap because the backward pass (radiative backpropagation) traces paths only from
samples that reach a pixel of nonzero adjoint, and skips the pixels whose samples reach
none, so a one-hot adjoint costs about `spp` paths and its neighbours' sample positions;
the calls run on all cores, one pixel per core at a time. Both estimates use independent random numbers, so
they differ by noise; the noise floor is the same statistic for two independent dual-number
images. A replay check on a subset of pixels (backward re-tracing the dual render's own
paths, `seed_grad=seed`) must agree to rounding.

Writes into out/gradient_image/: the scene (EXR, PNG), the reverse, dual and difference
gradient images (single-channel EXR, colour-mapped PNG) and `gradient_image.png`, the
figure (reverse, dual, their difference and the noise floor, with colour bars).

    python examples/gradient_image.py           # 64 x 64, 1024 spp (about 20 s on 2 cores)
    python examples/gradient_image.py --smoke   # seconds, for tests
"""
from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

import torch_rbpt as tr

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENE = ROOT.parent / "shared" / "scenes" / "cbox" / "cbox.xml"
BUNDLED_SCENE = ROOT / "torch_rbpt" / "scenes" / "cornell_box.xml"
KEY = "red.reflectance.value"
CHANNEL = 0  # red: d(pixel's red) / d(wall's red)

SETTINGS = {
    # res, spp of every estimate, replay check on every `replay_stride`-th pixel
    "default": dict(res=64, spp=1024, replay_stride=16),
    "smoke": dict(res=16, spp=16, replay_stride=8),
}
SEED_SCENE, SEED_REVERSE, SEED_DUAL_A, SEED_DUAL_B = 1, 2, 3, 4


def per_pixel_gradients(image: torch.Tensor, param: torch.Tensor, pixels, desc: str) -> torch.Tensor:
    """d image[p, CHANNEL] / d param[CHANNEL] for each flat pixel index p in `pixels`: one
    backward pass with a one-hot adjoint per pixel on the graph of `image` (H, W, 3).
    Returns a float64 tensor of len(pixels) values.

    Each backward pass traces only its pixel's paths: too little work to share between
    threads, so the passes run concurrently instead, one per core, each with one intra-op
    thread (the backward releases the GIL)."""
    height, width, _ = image.shape
    pixels = list(pixels)
    out = torch.zeros(len(pixels), dtype=torch.float64)
    workers = torch.get_num_threads()
    rows = [range(k, min(k + width, len(pixels))) for k in range(0, len(pixels), width)]

    def run(chunk):
        onehot = torch.zeros_like(image)
        for k in chunk:
            i, j = divmod(pixels[k], width)
            onehot[i, j, CHANNEL] = 1
            (g,) = torch.autograd.grad(image, param, onehot, retain_graph=True)
            onehot[i, j, CHANNEL] = 0
            out[k] = float(g[CHANNEL])
        return len(chunk)

    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(workers) as pool, tqdm(total=len(pixels), desc=desc, unit="px") as bar:
            for done in as_completed([pool.submit(run, chunk) for chunk in rows]):
                bar.update(done.result())
    finally:
        torch.set_num_threads(workers)
    return out


def relative_error(a: torch.Tensor, b: torch.Tensor, scale: torch.Tensor) -> float:
    """mean |a - b| / mean |scale|."""
    return float((a - b).abs().mean() / scale.abs().mean())


def save_figure(path: Path, reverse, dual, noise, spp: int, scene_name: str) -> None:
    """The figure, and reverse/dual/difference.png beside it, colour-mapped alike."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Symmetric limits around 0, shared by the panels that show the same quantity; a high
    # percentile rather than the maximum, so that the few brightest pixels (the wall seen
    # directly) do not wash out the indirect gradients.
    limit = float(np.percentile(np.abs(np.concatenate([reverse.ravel(), dual.ravel()])), 99))
    diff_limit = float(np.percentile(np.abs(np.concatenate([(reverse - dual).ravel(), noise.ravel()])), 99))
    panels = [
        ("(a) radiative backpropagation", reverse, limit),
        ("(b) dual numbers (forward mode)", dual, limit),
        ("(a) - (b)", reverse - dual, diff_limit),
        ("noise floor: two dual images", noise, diff_limit),
    ]
    fig, axes = plt.subplots(1, 4, figsize=(17, 4.4))
    for ax, (title, data, lim) in zip(axes, panels):
        im = ax.imshow(data, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
        ax.set_title(title)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    fig.suptitle(f"d(pixel red) / d({KEY}[0]), {scene_name}, {spp} spp per estimate")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    for name, data, lim in (("reverse", reverse, limit), ("dual", dual, limit),
                            ("difference", reverse - dual, diff_limit)):
        plt.imsave(path.parent / f"{name}.png", data, cmap="RdBu_r", vmin=-lim, vmax=lim)


def main(argv=None) -> dict:
    """Returns {error, noise, replay_error, time_reverse, time_dual}: mean |reverse - dual| and
    mean |dual_b - dual| relative to mean |dual|, the replay check's max relative
    difference, and the seconds per gradient image of each mode."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--smoke", action="store_true", help="tiny settings for a quick check")
    ap.add_argument("--out", default=str(ROOT / "out" / "gradient_image"), help="output folder")
    ap.add_argument("--scene", default=None, help="scene file (default: the shared cbox, else the bundled Cornell box)")
    args = ap.parse_args(argv)
    name = "smoke" if args.smoke else "default"
    cfg = SETTINGS[name]
    res, spp = cfg["res"], cfg["spp"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = Path(args.scene) if args.scene else SHARED_SCENE if SHARED_SCENE.exists() else BUNDLED_SCENE
    scene = tr.load_file(path, res=res)
    print(f"{name} settings: {cfg}, scene {path}, {torch.get_num_threads()} threads")

    # Forward mode: one render with dual numbers per estimate.
    tangent = {KEY: torch.zeros(3)}
    tangent[KEY][CHANNEL] = 1
    start = time.perf_counter()
    dual = tr.render_forward(scene, tangent, spp=spp, seed=SEED_DUAL_A)[..., CHANNEL]
    time_dual = time.perf_counter() - start
    dual_b = tr.render_forward(scene, tangent, spp=spp, seed=SEED_DUAL_B)[..., CHANNEL]
    print(f"dual numbers: {time_dual:.2f} s per gradient image")

    # Reverse mode: one forward render, then one backward pass per pixel.
    wall = scene.params[KEY]
    wall.requires_grad_()
    start = time.perf_counter()
    image = tr.render(scene, spp=spp, seed=SEED_SCENE, seed_grad=SEED_REVERSE)
    reverse = per_pixel_gradients(image, wall, range(res * res), "reverse mode").view(res, res)
    reverse = reverse.to(dual.dtype)
    time_reverse = time.perf_counter() - start
    print(f"radiative backpropagation: {time_reverse:.2f} s per gradient image (one forward render, "
          f"{res * res} backward passes, {1e3 * time_reverse / (res * res):.2f} ms per pixel)")

    # Replay: the backward pass re-traces the dual render's own paths.
    replay_pixels = range(0, res * res, cfg["replay_stride"])
    replayed = tr.render(scene, spp=spp, seed=SEED_DUAL_A, seed_grad=SEED_DUAL_A)
    replay = per_pixel_gradients(replayed, wall, replay_pixels, "replay check")
    expected = dual.reshape(-1)[list(replay_pixels)].double()
    replay_error = float((replay - expected).abs().max() / dual.abs().max())
    wall.requires_grad_(False)

    error = relative_error(reverse, dual, dual)
    noise = relative_error(dual_b, dual, dual)
    print(f"mean |reverse - dual| / mean |dual| = {error:.4f}")
    print(f"mean |dual_b - dual|  / mean |dual| = {noise:.4f}  (noise floor: two independent dual images)")
    print(f"ratio to the noise floor: {error / noise:.2f}")
    print(f"replay on the same paths ({len(replay_pixels)} pixels): "
          f"max |reverse - dual| / max |dual| = {replay_error:.1e}")

    tr.write_image(out / "scene.exr", image.detach())
    tr.write_image(out / "scene.png", image.detach())
    for key, g in {"reverse": reverse, "dual": dual, "difference": reverse - dual}.items():
        tr.write_image(out / f"{key}.exr", g.numpy())  # single channel, linear
    save_figure(out / "gradient_image.png", reverse.numpy(), dual.numpy(), (dual_b - dual).numpy(),
                spp, path.name)
    print(f"wrote {', '.join(sorted(p.name for p in out.iterdir()))} to {out}")
    return dict(error=error, noise=noise, replay_error=replay_error,
                time_reverse=time_reverse, time_dual=time_dual)


if __name__ == "__main__":
    main()
