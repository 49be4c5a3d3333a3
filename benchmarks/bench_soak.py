"""Soak benchmark: does a long fitting loop hold its memory flat?

Runs the fitting loop of examples/fit_material.py (bundled Cornell box: render, L2 loss,
backward, Adam step, clamp) for many iterations at a small resolution and samples the
process's resident memory (VmRSS from /proc/self/status) every few iterations. Prints a
table (iteration, RSS, ms/iteration over the last interval) and a verdict: the RSS growth
between the end of the warm-up and the last iteration, in total and per iteration. Writes
benchmarks/results/soak.csv and soak.png (RSS against iteration).

    python benchmarks/bench_soak.py [--iterations 1000] [--every 50] [--res 32] [--spp 4]
"""
from __future__ import annotations

import argparse
import datetime
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from machine import machine, status_mb, write_csv  # noqa: E402

import torch_rbpt as tr  # noqa: E402

SCENE = HERE.parent / "torch_rbpt" / "scenes" / "cornell_box.xml"
KEY = "red.reflectance.value"
FLAT_MB = 1.0  # growth after the warm-up below which the loop counts as flat


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--every", type=int, default=50, help="sample RSS every this many iterations")
    ap.add_argument("--warmup", type=int, default=100, help="growth is measured from this iteration")
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--lr", type=float, default=0.05)
    args = ap.parse_args()
    if args.warmup % args.every or args.iterations % args.every:
        ap.error("--warmup and --iterations must be multiples of --every")

    scene = tr.load_file(SCENE, res=args.res)
    reference = tr.render(scene, spp=args.ref_spp, seed=123456).detach()
    param = scene.params[KEY]
    with torch.no_grad():
        param.copy_(torch.tensor([0.01, 0.2, 0.9]))
    param.requires_grad_()
    opt = torch.optim.Adam([param], lr=args.lr)

    print(f"soak: bundled Cornell box, {args.res}x{args.res}, {args.spp} spp, {args.iterations} iterations "
          f"of render + L2 loss + backward + Adam + clamp")
    print(f"machine: {machine()}")
    print(f"date: {datetime.datetime.now().isoformat(timespec='seconds')}\n")
    print(f"{'iteration':>9s} {'RSS (MB)':>9s} {'ms/iter':>8s} {'loss':>10s}")
    rows = [{"iteration": 0, "rss_mb": status_mb("VmRSS"), "ms_per_iteration": float("nan"), "loss": float("nan")}]
    print(f"{0:9d} {rows[0]['rss_mb']:9.1f} {'':>8s} {'':>10s}", flush=True)
    start = time.perf_counter()
    for it in range(1, args.iterations + 1):
        opt.zero_grad()
        image = tr.render(scene, spp=args.spp, seed=it)
        loss = ((image - reference) ** 2).mean()
        loss.backward()
        opt.step()
        with torch.no_grad():
            param.clamp_(0.0, 1.0)
        if it % args.every == 0:
            now = time.perf_counter()
            row = {"iteration": it, "rss_mb": status_mb("VmRSS"), "ms_per_iteration": (now - start) * 1e3 / args.every,
                   "loss": loss.item()}
            rows.append(row)
            print(f"{it:9d} {row['rss_mb']:9.1f} {row['ms_per_iteration']:8.2f} {row['loss']:10.3e}", flush=True)
            start = time.perf_counter()

    out = HERE / "results"
    write_csv(out / "soak.csv", rows)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([r["iteration"] for r in rows], [r["rss_mb"] for r in rows], marker=".")
    ax.axvline(args.warmup, color="gray", linestyle=":", label="end of warm-up")
    ax.set_xlabel("iteration")
    ax.set_ylabel("resident memory (MB)")
    ax.set_title(f"soak: Cornell box {args.res}x{args.res}, {args.spp} spp")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "soak.png", dpi=120)
    plt.close(fig)

    by_it = {r["iteration"]: r for r in rows}
    first, last = by_it[args.warmup], rows[-1]
    growth = last["rss_mb"] - first["rss_mb"]
    per_it = growth / (last["iteration"] - first["iteration"])
    timed = [r["ms_per_iteration"] for r in rows if r["iteration"] > args.warmup]
    print(f"\nRSS at iteration {first['iteration']}: {first['rss_mb']:.1f} MB, at {last['iteration']}: "
          f"{last['rss_mb']:.1f} MB; growth {growth:+.2f} MB ({per_it * 1024:+.2f} KB/iteration)")
    print(f"mean {sum(timed) / len(timed):.2f} ms/iteration after the warm-up")
    verdict = "flat" if growth < FLAT_MB else "GROWING"
    print(f"verdict: {verdict} (flat means under {FLAT_MB:g} MB growth after the warm-up)")
    print(f"wrote {out / 'soak.png'}")


if __name__ == "__main__":
    main()
