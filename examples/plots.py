"""Figures shared by the examples: grids of rendered images and convergence curves.

Images are linear RGB tensors (H, W, 3); they are shown sRGB-encoded and clamped to [0, 1].
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import torch_rbpt as tr  # noqa: E402


def srgb(image: torch.Tensor) -> np.ndarray:
    """A linear (H, W, 3) image as an sRGB array for display."""
    return tr.images.linear_to_srgb(image.detach().clamp(0, 1)).numpy()


def image_grid(path: Path, rows: list[dict], size: float = 3.2) -> None:
    """Save rows of titled images ({title: image} per row) as one figure."""
    n_cols = max(len(r) for r in rows)
    fig, axes = plt.subplots(len(rows), n_cols, figsize=(size * n_cols, size * len(rows) + 0.3),
                             squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for r, row in enumerate(rows):
        for c, (title, image) in enumerate(row.items()):
            axes[r, c].imshow(srgb(image))
            axes[r, c].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def convergence(path: Path, losses: list, curves: dict, ylabel: str, title: str,
                loss_label: str = "L2 image loss") -> None:
    """Save the loss (left) and one or more error curves (right) per iteration, log scale.
    At a few spp the loss is dominated by render noise; the errors show the convergence."""
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].semilogy(losses)
    ax[0].set(xlabel="iteration", ylabel=loss_label, title="loss (noisy: a few spp per iteration)")
    for label, values in curves.items():
        ax[1].semilogy(values, label=label)
    ax[1].set(xlabel="iteration", ylabel=ylabel, title=title)
    if len(curves) > 1:
        ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def save_images(out: Path, images: dict, suffix: str = "") -> None:
    """Write each {name: image} as linear EXR and sRGB PNG into `out`."""
    for name, image in images.items():
        tr.write_image(out / f"{name}{suffix}.exr", image)
        tr.write_image(out / f"{name}{suffix}.png", image)
