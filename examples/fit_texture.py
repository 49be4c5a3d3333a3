"""Recover a diffuse bitmap texture (every texel) from a few rendered views.

A textured floor (a 2 x 2 `rectangle` whose `diffuse` reflectance is a `bitmap`) carries a
grey cube and is lit by an area light above it; three cameras look at it from different
sides. The ground-truth texture is drawn procedurally (a checkerboard, a red disk and the
letters "RBPT"), written to `target_texture.exr` and loaded by the bitmap with raw=true
(linear values). After the reference renders, the texels (key
`floor.bsdf.reflectance.data`, shape (H, W, 3)) are reset to a flat grey 0.5 and
recovered with torch.optim.Adam on the L2 image loss summed over the views. One scene
serves all views: `scene.sensor.to_world` changes between the renders. Every render uses a
new seed; the backward pass traces its own independent paths (radiative
backpropagation), so the gradient is unbiased. Texels are clamped to [0, 1] after each step.

What cannot be recovered: the texels under the cube are never seen (nor lit), so they keep
their start value. Each view's gradient is computed separately to record which texels it
sees (gradient nonzero at least once; a bilinear lookup scatters into its four texels, so
a texel bordering a visible one counts as seen, and so does a texel seen only in the
cube's interreflection). We report the texture RMSE over all
texels, over the visible ones, and per number of views that see a texel. Texels seen
only at grazing angles, far away, in shadow or at the cube's edge are weakly constrained
(one pixel averages several of them, or their light is dim): they have the largest
remaining errors (see the error map).

Writes into out/fit_texture/: the target, initial and final textures (EXR and PNG), the
reference and final renders of each view (EXR and PNG), `textures.png` (target, start,
result, error map, number of views seeing each texel), `views.png` (reference vs final per
view) and `convergence.png` (loss and texture RMSE per iteration). Mitsuba's rectangle maps
the bitmap's first row to its y = -1 edge, so the texture files look upside down in an
image viewer; the figures draw textures as the floor is seen from above.

    python examples/fit_texture.py           # default settings (1-2 minutes on 2 cores)
    python examples/fit_texture.py --smoke   # seconds, for tests
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

import torch_rbpt as tr

import plots  # examples/plots.py: figures shared by the examples

ROOT = Path(__file__).resolve().parents[1]
KEY = "floor.bsdf.reflectance.data"
START = 0.5  # flat grey start texture

SETTINGS = {
    # texture size, image size per view, reference spp, spp per view and iteration,
    # iterations, Adam lr (cosine-decayed to lr/20)
    "default": dict(tex=64, res=96, ref_spp=256, spp=8, iterations=150, lr=0.03),
    "smoke": dict(tex=16, res=32, ref_spp=64, spp=4, iterations=20, lr=0.05),
}

# Camera positions (azimuth, elevation in degrees, distance), all looking at the floor's centre.
VIEWS = [(-35.0, 60.0, 3.0), (25.0, 45.0, 3.0), (110.0, 40.0, 3.2)]

# 5 x 7 glyphs for the texture's lettering.
GLYPHS = {
    "R": ["1111.", "1...1", "1...1", "1111.", "1.1..", "1..1.", "1...1"],
    "B": ["1111.", "1...1", "1...1", "1111.", "1...1", "1...1", "1111."],
    "P": ["1111.", "1...1", "1...1", "1111.", "1....", "1....", "1...."],
    "T": ["11111", "..1..", "..1..", "..1..", "..1..", "..1..", "..1.."],
}


def make_texture(n: int) -> np.ndarray:
    """The ground truth: an (n, n, 3) linear RGB texture in [0, 1]. Row i holds v = (i + 0.5) / n:
    Mitsuba's rectangle puts uv (0, 0) at its corner (-1, -1), so row 0 lies along y = -1 and
    the texture reads upright on the floor seen from above (and upside down in an image viewer)."""
    v, u = (np.mgrid[0:n, 0:n] + 0.5) / n  # texel centres in [0, 1]
    checker = ((np.floor(u * 8) + np.floor(v * 8)) % 2)[..., None]
    tex = np.where(checker > 0, [0.75, 0.7, 0.55], [0.25, 0.35, 0.3]).astype(np.float64)
    disk = (u - 0.68) ** 2 + (v - 0.32) ** 2 < 0.2 ** 2
    tex[disk] = [0.8, 0.1, 0.05]
    # "RBPT" across the top (large v): glyph cells scaled to texels (nearest), dark blue.
    text, gw, gh, gap = "RBPT", 5, 7, 1
    scale = 0.76 / (len(text) * (gw + gap) - gap)  # texture units per glyph cell
    u0, v0 = 0.12, 0.9  # top-left corner of the lettering
    for i, ch in enumerate(text):
        cells = np.array([[c == "1" for c in row] for row in GLYPHS[ch]])
        gx = (u - u0) / scale - i * (gw + gap)
        gy = (v0 - v) / scale
        inside = (gx >= 0) & (gx < gw) & (gy >= 0) & (gy < gh)
        ix, iy = np.clip(gx.astype(int), 0, gw - 1), np.clip(gy.astype(int), 0, gh - 1)
        tex[inside & cells[iy, ix]] = [0.05, 0.15, 0.7]
    return tex.astype(np.float32)


def camera(azimuth: float, elevation: float, distance: float) -> np.ndarray:
    a, e = math.radians(azimuth), math.radians(elevation)
    origin = distance * np.array([math.sin(a) * math.cos(e), -math.cos(a) * math.cos(e), math.sin(e)])
    return tr.Transform.look_at(origin, [0, 0, 0], [0, 0, 1]).matrix


def build_scene(texture_path: Path, res: int):
    T = tr.Transform
    return tr.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 45, "to_world": camera(*VIEWS[0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res}},
        "floor": {"type": "rectangle",
                  "bsdf": {"type": "diffuse", "reflectance": {
                      "type": "bitmap", "filename": str(texture_path), "raw": True}}},
        "block": {"type": "cube", "to_world": T.translate([-0.5, -0.35, 0.25]) @ T.scale(0.25),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}},
        "light": {"type": "rectangle",
                  "to_world": T.translate([0.3, -0.3, 3.0]) @ T.rotate([1, 0, 0], 180) @ T.scale(1.0),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [12.0, 12.0, 12.0]}}},
    })


def save_figures(out: Path, textures: dict, error: np.ndarray, views_count: np.ndarray, views: list,
                 losses: list, rmse: list, rmse_visible: list) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(textures) + 2, figsize=(3.2 * (len(textures) + 2), 3.4))
    for ax, (name, tex) in zip(axes, textures.items()):
        ax.imshow(plots.srgb(tex), interpolation="nearest", origin="lower")  # as seen from above
        ax.set_title(name)
    im = axes[-2].imshow(error, cmap="magma", vmin=0, interpolation="nearest", origin="lower")
    axes[-2].set_title("|result - target| (RMS over RGB)")
    fig.colorbar(im, ax=axes[-2], fraction=0.046)
    im = axes[-1].imshow(views_count, cmap="viridis", vmin=0, vmax=len(VIEWS), interpolation="nearest",
                         origin="lower")
    axes[-1].set_title("views seeing each texel")
    fig.colorbar(im, ax=axes[-1], fraction=0.046, ticks=range(len(VIEWS) + 1))
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "textures.png", dpi=100)
    plt.close(fig)

    plots.image_grid(out / "views.png", [{f"view {i}: reference": ref for i, (ref, _) in enumerate(views)},
                                         {f"view {i}: final": fin for i, (_, fin) in enumerate(views)}])
    plots.convergence(out / "convergence.png", losses, {"all texels": rmse, "visible texels": rmse_visible},
                      "texture RMSE", "texture error", loss_label="L2 image loss (sum over views)")


def rms(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    d2 = ((a - b) ** 2).mean(-1)
    if mask is not None:
        d2 = d2[mask]
    return float(d2.mean().sqrt()) if d2.numel() else float("nan")


def main(argv=None) -> float:
    """Runs the fit; returns the final texture RMSE over the visible texels."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--smoke", action="store_true", help="tiny settings for a quick check")
    ap.add_argument("--out", default=str(ROOT / "out" / "fit_texture"), help="output folder")
    args = ap.parse_args(argv)
    name = "smoke" if args.smoke else "default"
    cfg = SETTINGS[name]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{name} settings: {cfg}, {len(VIEWS)} views; writing to {out}")
    start_time = time.time()

    texture_path = out / "target_texture.exr"
    tr.write_image(texture_path, make_texture(cfg["tex"]))
    tr.write_image(out / "target_texture.png", tr.read_image(texture_path))
    scene = build_scene(texture_path, cfg["res"])
    texels = scene.params[KEY]
    truth = texels.detach().clone()
    cameras = [camera(*v) for v in VIEWS]

    def render_view(i: int, spp: int, seed: int) -> torch.Tensor:
        scene.sensor.to_world = cameras[i]
        return tr.render(scene, spp=spp, seed=seed)

    print(f"rendering {len(VIEWS)} reference views ({cfg['ref_spp']} spp) ...")
    references = [render_view(i, cfg["ref_spp"], 10_000 + i).detach() for i in range(len(VIEWS))]

    with torch.no_grad():
        texels.fill_(START)
    initial_texture = texels.detach().clone()
    texels.requires_grad_()
    opt = torch.optim.Adam([texels], lr=cfg["lr"])
    n = cfg["iterations"]
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, n, eta_min=cfg["lr"] / 20)
    # seen_by[i]: texels whose gradient from view i was nonzero at least once.
    seen_by = torch.zeros((len(VIEWS), *texels.shape[:2]), dtype=torch.bool)

    losses, errors, history = [], [], []
    bar = tqdm(range(n), desc="fitting", unit="it")
    for it in bar:
        loss, grad = 0.0, torch.zeros_like(texels)
        for i in range(len(VIEWS)):  # one backward per view, to record which texels each view sees
            view_loss = ((render_view(i, cfg["spp"], it * len(VIEWS) + i) - references[i]) ** 2).mean()
            g, = torch.autograd.grad(view_loss, texels)
            seen_by[i] |= (g != 0).any(-1)
            grad += g
            loss += view_loss.item()
        texels.grad = grad
        opt.step()
        sched.step()
        with torch.no_grad():
            texels.clamp_(0.0, 1.0)
        seen = seen_by.any(0)
        losses.append(loss)
        history.append(texels.detach().clone())
        errors.append(rms(history[-1], truth))
        bar.set_postfix(loss=f"{loss:.2e}", rmse=f"{errors[-1]:.4f}", visible=f"{rms(history[-1], truth, seen):.4f}")
    result = texels.detach().clone()
    # The visible set can grow during the fit: the curve uses the final one.
    errors_visible = [rms(t, truth, seen) for t in history]
    views_count = seen_by.sum(0)

    finals = [render_view(i, cfg["ref_spp"], 20_000 + i).detach() for i in range(len(VIEWS))]
    for i, (ref, fin) in enumerate(zip(references, finals)):
        plots.save_images(out, {"reference": ref, "final": fin}, suffix=f"_view{i}")
    plots.save_images(out, {"initial_texture": initial_texture, "final_texture": result})
    error_map = ((result - truth) ** 2).mean(-1).sqrt()
    save_figures(out, {"target": truth, f"start (grey {START})": initial_texture, "result": result},
                 error_map.numpy(), views_count.numpy(), list(zip(references, finals)), losses, errors,
                 errors_visible)

    total = seen.numel()
    rmse_visible = rms(result, truth, seen)
    print(f"texture RMSE, all {total} texels: {rms(initial_texture, truth):.4f} -> {rms(result, truth):.4f}")
    print(f"texture RMSE, {int(seen.sum())} visible texels ({100 * float(seen.float().mean()):.1f}%): "
          f"{rms(initial_texture, truth, seen):.4f} -> {rmse_visible:.4f}; per-texel error "
          f"median {float(error_map[seen].median()):.4f}, 90th percentile {float(error_map[seen].quantile(0.9)):.4f}")
    for k in range(len(VIEWS), -1, -1):
        m = views_count == k
        if m.any():
            print(f"  seen by {k} of {len(VIEWS)} views: {int(m.sum()):5d} texels, RMSE "
                  f"{rms(initial_texture, truth, m):.4f} -> {rms(result, truth, m):.4f}"
                  + (" (never seen: unchanged)" if k == 0 else ""))
    print(f"{time.time() - start_time:.0f} s; wrote {', '.join(sorted(p.name for p in out.iterdir()))} to {out}")
    return rmse_visible


if __name__ == "__main__":
    main()
