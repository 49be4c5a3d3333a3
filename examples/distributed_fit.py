"""Recover a wall's reflectance from several views rendered by several processes
(torch.distributed), for when one machine is not enough.

The material fit of fit_material.py (the bundled Cornell box's red wall, reset to
(0.01, 0.2, 0.9)), but the loss is the mean L2 image loss over several camera positions, and
the views are split across processes: rank r renders views r, r + world_size, ... Every
rank renders its own views' references, and per iteration its views' images (seeds distinct
per view and iteration, so the run does not depend on how views are split), back-propagates
its share of the loss, and all-reduces the gradient (gloo backend, works on CPUs). Every
rank then takes the same Adam step from the same gradient, so all ranks hold identical
parameters; the script checks that at the end with an all_gather. Rank 0 gathers the images
and writes into out/distributed_fit/: per view the reference, initial and final images (EXR
and PNG), `comparison.png` (views x reference/initial/final) and `convergence.png`.

    torchrun --nproc_per_node 2 examples/distributed_fit.py            # 2 processes
    python examples/distributed_fit.py                                 # 1 process
    torchrun --nnodes 2 --node_rank R --master_addr HOST --master_port PORT \\
        --nproc_per_node 1 examples/distributed_fit.py                 # 2 machines
    python examples/distributed_fit.py --smoke                         # seconds, for tests
"""
from __future__ import annotations

import argparse
import os
import socket
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

import torch_rbpt as tr

import plots  # examples/plots.py: figures shared by the examples

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "torch_rbpt" / "scenes" / "cornell_box.xml"
KEY = "red.reflectance.value"
START = (0.01, 0.2, 0.9)

SETTINGS = {
    # res, reference spp, spp of the initial and final images (shown only), spp per view and
    # iteration, iterations, Adam lr (cosine-decayed to lr/20)
    "default": dict(res=64, ref_spp=256, show_spp=64, spp=8, iterations=100, lr=0.05),
    "smoke": dict(res=16, ref_spp=32, show_spp=8, spp=4, iterations=20, lr=0.05),
}

# Camera positions looking into the open side (+z) of the box [-1, 1]^3; all of them stay
# inside |x|, |y| < 1 so that no view sees the back of a wall.
ORIGINS = [(0.0, 0.0, 3.9), (-0.7, 0.45, 3.6), (0.7, 0.45, 3.6), (0.0, -0.6, 3.7),
           (-0.6, -0.4, 3.7), (0.6, -0.4, 3.7)]


def view_matrix(v: int) -> np.ndarray:
    """Camera to world (4, 4) of view v."""
    origin = ORIGINS[v % len(ORIGINS)]
    return tr.Transform.look_at(origin, [0, 0, 0], [0, 1, 0]).matrix


def init_distributed() -> tuple[int, int, bool]:
    """Join the process group that torchrun describes in the environment (RANK, WORLD_SIZE,
    MASTER_ADDR, MASTER_PORT), or make a group of one on loopback when run as a plain
    script. Returns (rank, world_size, whether this call created the group)."""
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), False
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ:
        dist.init_process_group("gloo")
    else:
        with socket.socket() as s:  # a free loopback port for the group of one
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=0, world_size=1)
    return dist.get_rank(), dist.get_world_size(), True


def save_figures(out: Path, views: dict, losses: list, errors: list) -> None:
    rows = [{f"view {v}: {name}": images[name] for name in ("reference", "initial", "final")}
            for v, images in sorted(views.items())]
    plots.image_grid(out / "comparison.png", rows, size=3)
    plots.convergence(out / "convergence.png", losses, {"RMS error": errors}, "RMS error", f"{KEY} error",
                      loss_label="L2 image loss (mean over views)")

def main(argv=None) -> float:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--smoke", action="store_true", help="tiny settings for a quick check")
    ap.add_argument("--views", type=int, default=4, help="number of camera positions (default 4)")
    ap.add_argument("--out", default=str(ROOT / "out" / "distributed_fit"), help="output folder (rank 0 writes)")
    args = ap.parse_args(argv)
    name = "smoke" if args.smoke else "default"
    cfg = SETTINGS[name]
    n_views = args.views

    rank, world, created = init_distributed()
    # Share this machine's cores between the processes running on it.
    local = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
    torch.set_num_threads(max(1, len(os.sched_getaffinity(0)) // local))
    mine = list(range(rank, n_views, world))  # this rank's views
    main_rank = rank == 0
    log = print if main_rank else (lambda *a, **k: None)
    log(f"{name} settings: {cfg}, {n_views} views on {world} process(es) "
        f"({torch.get_num_threads()} thread(s) each)")
    print(f"rank {rank}/{world} on {socket.gethostname()}: views {mine}", flush=True)

    scene = tr.load_file(SCENE, res=cfg["res"])
    param = scene.params[KEY]
    truth = param.detach().clone()

    def render(v: int, spp: int, seed: int) -> torch.Tensor:
        scene.sensor.to_world = view_matrix(v)
        return tr.render(scene, spp=spp, seed=seed)

    # Seeds: view v's image at iteration it uses seed it * n_views + v; the references and
    # the initial and final images use seeds far above any iteration's.
    start = time.perf_counter()
    with torch.no_grad():
        references = {v: render(v, cfg["ref_spp"], 10_000_000 + v) for v in mine}
        param.copy_(torch.tensor(START))
        initial = {v: render(v, cfg["show_spp"], 20_000_000 + v) for v in mine}
    log(f"rendered the references ({cfg['ref_spp']} spp) and initial images in {time.perf_counter() - start:.1f} s")

    param.requires_grad_()
    opt = torch.optim.Adam([param], lr=cfg["lr"])
    n = cfg["iterations"]
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, n, eta_min=cfg["lr"] / 20)
    losses, errors = [], []
    bar = tqdm(range(n), desc="fitting", unit="it", disable=not main_rank)
    start = time.perf_counter()
    for it in bar:
        opt.zero_grad()
        # This rank's share of the mean loss over all views: the sum over ranks of the
        # gradients is then the gradient of the mean, however the views are split.
        loss = torch.zeros((), dtype=param.dtype)
        for v in mine:
            image = render(v, cfg["spp"], it * n_views + v)
            view_loss = ((image - references[v]) ** 2).mean() / n_views
            view_loss.backward()
            loss += view_loss.detach()
        if param.grad is None:  # a rank without views still takes part in the reduction
            param.grad = torch.zeros_like(param)
        dist.all_reduce(param.grad, op=dist.ReduceOp.SUM)
        dist.all_reduce(loss, op=dist.ReduceOp.SUM)
        opt.step()
        sched.step()
        with torch.no_grad():
            param.clamp_(0.0, 1.0)
        error = float(((param.detach() - truth) ** 2).mean().sqrt())
        losses.append(loss.item())
        errors.append(error)
        bar.set_postfix(loss=f"{loss.item():.2e}", error=f"{error:.4f}")
    fit_time = time.perf_counter() - start

    # Every rank took the same steps from the same reduced gradients.
    gathered = [torch.empty_like(param) for _ in range(world)]
    dist.all_gather(gathered, param.detach())
    identical = all(torch.equal(g, gathered[0]) for g in gathered)
    assert identical, f"ranks disagree on {KEY}: {[g.tolist() for g in gathered]}"

    with torch.no_grad():
        final = {v: render(v, cfg["show_spp"], 30_000_000 + v) for v in mine}
    local_images = {v: {"reference": references[v], "initial": initial[v], "final": final[v]} for v in mine}
    everything = [None] * world if main_rank else None
    dist.gather_object(local_images, everything, dst=0)

    rms = errors[-1]
    if main_rank:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        views = {v: images for part in everything for v, images in part.items()}
        for v, images in views.items():
            plots.save_images(out, images, suffix=f"_view{v}")
        save_figures(out, views, losses, errors)
        print(f"fitting: {fit_time:.1f} s for {n} iterations on {world} process(es)")
        print(f"parameters identical on all {world} rank(s): {identical}")
        print(f"true   {KEY} = {truth.tolist()}")
        print(f"fitted {KEY} = {[round(v, 4) for v in param.detach().tolist()]}")
        print(f"RMS reflectance error: {rms:.4f}")
        print(f"wrote {', '.join(sorted(p.name for p in out.iterdir()))} to {out}")
    if created:
        dist.destroy_process_group()
    # torch 2.13's gloo worker thread destroys a collective's work object (and decrefs its
    # tensors, which needs the GIL) just after the collective returns; if the interpreter is
    # finalizing by then, the thread is killed and the process aborts ("terminate called
    # without an active exception", about 1 run in 20 under load). Give it the GIL for a
    # moment while the interpreter is still running.
    time.sleep(0.1)
    return rms


if __name__ == "__main__":
    main()
