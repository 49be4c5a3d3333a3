"""Recover a glossy material (roughness and specular colour), a diffuse colour and an
emitter's radiance together, from one rendered image.

The scene: a copper-like `roughconductor` (GGX) sphere on a diffuse floor, lit by one
rectangular area light that is itself in view. Six unknowns are fitted jointly with
torch.optim.Adam on an L2 image loss, every iteration with a new seed (the backward pass
traces its own independent paths, so the gradient is unbiased):

    ball.bsdf.alpha.value                  GGX roughness (1,)  optimised as log(alpha), kept in [0.02, 1]
    ball.bsdf.specular_reflectance.value   specular colour (3,)  clamped to [0, 1]
    floor.bsdf.reflectance.value           diffuse colour (3,)   clamped to [0, 1]
    light.emitter.radiance.value           emitted radiance (3,) optimised as log(radiance), so positive

The optimiser works on these latent tensors; every iteration assigns the derived values to
`scene.params[key]` (the renderer differentiates through the assignment) before rendering.

Why the unknowns are separable: the floor and the sphere only show products, reflectance
times radiance, so doubling the radiance and halving both reflectances would give the same
floor and sphere. The light is in the image, though: its pixels show the radiance alone,
which pins the scale; the floor's brightness then gives its colour, and the highlight's
brightness the specular colour. The highlight's size and falloff give the roughness
(a rougher sphere spreads the same reflected energy over a wider, dimmer highlight). If
the light were out of view, only the products would be determined and the fit would
return whichever split the start and the optimiser happened to reach.

What limits the accuracy is noise, mostly the reference's: the far floor is lit only by
light reflected off the sphere (a caustic, found by chance and so noisy), and a finite
reference tends to underestimate it. Started at the truth, the default fit drifts about
1.5% in the specular colour with the 512 spp reference and 0.6% with a 4096 spp one.

Writes into out/fit_glossy/: the reference, initial and final images (EXR and PNG),
`comparison.png` (side by side) and `convergence.png` (loss and per-parameter relative
errors per iteration).

    python examples/fit_glossy.py           # default settings (0.5-1.5 minutes on 2 cores)
    python examples/fit_glossy.py --smoke   # seconds, for tests
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch
from tqdm import tqdm

import torch_rbpt as tr

import plots  # examples/plots.py: figures shared by the examples

ROOT = Path(__file__).resolve().parents[1]
ALPHA = "ball.bsdf.alpha.value"
SPECULAR = "ball.bsdf.specular_reflectance.value"
DIFFUSE = "floor.bsdf.reflectance.value"
RADIANCE = "light.emitter.radiance.value"
ALPHA_RANGE = (0.02, 1.0)

TRUTH = {ALPHA: [0.15], SPECULAR: [0.95, 0.64, 0.54], DIFFUSE: [0.2, 0.4, 0.6], RADIANCE: [10.0, 8.0, 6.0]}
START = {ALPHA: [0.5], SPECULAR: [0.5, 0.5, 0.5], DIFFUSE: [0.5, 0.5, 0.5], RADIANCE: [3.0, 3.0, 3.0]}
NAMES = {ALPHA: "roughness alpha", SPECULAR: "specular colour", DIFFUSE: "floor colour", RADIANCE: "radiance"}

SETTINGS = {
    # image width (height 3/4 of it), reference spp, spp per iteration, iterations,
    # Adam lr on the latents (cosine-decayed to lr/20)
    "default": dict(res=96, ref_spp=512, spp=16, iterations=150, lr=0.05),
    "smoke": dict(res=32, ref_spp=64, spp=4, iterations=80, lr=0.08),
}


def build_scene(res: int):
    T = tr.Transform
    return tr.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 45, "to_world": T.look_at([0, -4.5, 1.8], [0, 0, 0.8], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res * 3 // 4}},
        "floor": {"type": "rectangle", "to_world": T.scale(5),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": TRUTH[DIFFUSE]}}},
        "ball": {"type": "sphere", "center": [0.3, 0, 0.7], "radius": 0.7,
                 "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": TRUTH[ALPHA][0],
                          "specular_reflectance": {"type": "rgb", "value": TRUTH[SPECULAR]}}},
        # The light faces a point between the sphere and the camera: it lights both and is seen.
        "light": {"type": "rectangle",
                  "to_world": T.look_at([-1.3, 0.2, 1.7], [0.2, -1.5, 0.6], [0, 0, 1]) @ T.scale([0.35, 0.5, 1]),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": TRUTH[RADIANCE]}}},
    })


class Latents:
    """The optimised variables and their map to scene parameters."""

    def __init__(self, start: dict):
        self.log_alpha = torch.tensor(start[ALPHA]).log().requires_grad_()
        self.specular = torch.tensor(start[SPECULAR]).requires_grad_()
        self.diffuse = torch.tensor(start[DIFFUSE]).requires_grad_()
        self.log_radiance = torch.tensor(start[RADIANCE]).log().requires_grad_()

    def tensors(self) -> list[torch.Tensor]:
        return [self.log_alpha, self.specular, self.diffuse, self.log_radiance]

    def values(self) -> dict[str, torch.Tensor]:
        return {ALPHA: self.log_alpha.exp(), SPECULAR: self.specular, DIFFUSE: self.diffuse,
                RADIANCE: self.log_radiance.exp()}

    def project(self) -> None:
        """Keep alpha in ALPHA_RANGE and the reflectances in [0, 1] (radiance is positive by construction)."""
        with torch.no_grad():
            self.log_alpha.clamp_(math.log(ALPHA_RANGE[0]), math.log(ALPHA_RANGE[1]))
            self.specular.clamp_(0.0, 1.0)
            self.diffuse.clamp_(0.0, 1.0)


def relative_errors(values: dict) -> dict[str, float]:
    """|fitted - true| / |true| per parameter (Euclidean norms for colours)."""
    return {k: float((v.detach() - torch.tensor(TRUTH[k])).norm() / torch.tensor(TRUTH[k]).norm())
            for k, v in values.items()}


def save_figures(out: Path, images: dict, losses: list, errors: list[dict]) -> None:
    plots.image_grid(out / "comparison.png", [images], size=4)
    plots.convergence(out / "convergence.png", losses, {name: [e[key] for e in errors] for key, name in NAMES.items()},
                      "|fitted - true| / |true|", "relative parameter errors")


def main(argv=None) -> dict[str, float]:
    """Runs the fit; returns the final relative error of each parameter (keyed by scene key)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--smoke", action="store_true", help="tiny settings for a quick check")
    ap.add_argument("--out", default=str(ROOT / "out" / "fit_glossy"), help="output folder")
    args = ap.parse_args(argv)
    name = "smoke" if args.smoke else "default"
    cfg = SETTINGS[name]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{name} settings: {cfg}; writing to {out}")
    start_time = time.time()

    scene = build_scene(cfg["res"])
    print(f"rendering the reference ({cfg['ref_spp']} spp) ...")
    reference = tr.render(scene, spp=cfg["ref_spp"], seed=123456).detach()

    latents = Latents(START)

    def apply() -> dict[str, torch.Tensor]:
        values = latents.values()
        for key, value in values.items():
            scene.params[key] = value
        return values

    with torch.no_grad():
        apply()
        initial = tr.render(scene, spp=cfg["ref_spp"], seed=654321).detach()
    initial_errors = relative_errors(latents.values())

    opt = torch.optim.Adam(latents.tensors(), lr=cfg["lr"])
    n = cfg["iterations"]
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, n, eta_min=cfg["lr"] / 20)
    losses, errors = [], []
    bar = tqdm(range(n), desc="fitting", unit="it")
    for it in bar:
        opt.zero_grad()
        apply()
        image = tr.render(scene, spp=cfg["spp"], seed=it)
        loss = ((image - reference) ** 2).mean()
        loss.backward()
        opt.step()
        sched.step()
        latents.project()
        errors.append(relative_errors(latents.values()))
        losses.append(loss.item())
        bar.set_postfix(loss=f"{loss.item():.2e}", alpha=f"{latents.log_alpha.exp().item():.3f}",
                        max_rel_err=f"{max(errors[-1].values()):.3f}")

    with torch.no_grad():
        fitted = apply()
        final = tr.render(scene, spp=cfg["ref_spp"], seed=777).detach()
    images = {"reference": reference, "initial": initial, "final": final}
    plots.save_images(out, images)
    save_figures(out, images, losses, errors)

    final_errors = errors[-1]
    print(f"{'parameter':38s} {'true':>22s} {'start':>22s} {'fitted':>22s}  rel. error (start -> fitted)")
    fmt = lambda v: ", ".join(f"{x:.3f}" for x in (v.tolist() if torch.is_tensor(v) else v))
    for key in TRUTH:
        print(f"{key:38s} {fmt(TRUTH[key]):>22s} {fmt(START[key]):>22s} {fmt(fitted[key]):>22s}  "
              f"{initial_errors[key]:.3f} -> {final_errors[key]:.4f}")
    print(f"{time.time() - start_time:.0f} s; wrote {', '.join(sorted(p.name for p in out.iterdir()))} to {out}")
    return final_errors


if __name__ == "__main__":
    main()
