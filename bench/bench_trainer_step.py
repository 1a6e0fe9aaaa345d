"""Where a training step's time goes on the CPU, and what the trainer's two CPU paths buy.

Prints, for synthetic but realistic inputs (points along rays, as the renderer makes them):

1. ``trilinear``: forward + backward of sampling a voxel grid at M points, as one batch
   and as two batches of the expanded grid (the default on the CPU), for
   the main grid (128^3 x 2 channels) and the degree-1 SH grid (64^3 x 3). The trainer splits
   when ``M * 64 >= grid values``; the table shows the break-even that rule stands for.
2. ``candidates``: making the packed samples of 2048 rays (``render._occupied_samples``) for a
   field that fills its box (a hazy baseline) and for a compact object, gather vs broadcast.

Usage::

    python bench/bench_trainer_step.py            # the tables (a few seconds on 2 cores)
    python bench/bench_trainer_step.py --reps 15  # steadier medians
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from spikegen.camera import focal_px
from spikenerf import model as M
from spikenerf import render as R


def _median_ms(fn, reps: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1000 * statistics.median(ts)


def _ray_points(m: int, gen: torch.Generator) -> torch.Tensor:
    """grid_sample coordinates of ``m`` points, 40 consecutive steps along each of m/40 random rays."""
    o = torch.rand(m // 40, 1, 3, generator=gen) * 1.6 - 0.8
    d = torch.nn.functional.normalize(torch.randn(m // 40, 1, 3, generator=gen), dim=-1)
    return (o + d * torch.linspace(0, 0.4, 40)[None, :, None]).reshape(-1, 3).clamp(-1, 1)


def trilinear_table(reps: int) -> None:
    gen = torch.Generator().manual_seed(0)
    print(f"trilinear forward + backward, median of {reps} (ms); torch threads: {torch.get_num_threads()}")
    print(f"{'grid':>12} {'points':>8} {'1 batch':>8} {'2 batches':>9} {'trainer uses':>13}")
    for G, C in ((128, 2), (64, 3)):
        grid = torch.randn(1, C, G, G, G, generator=gen, requires_grad=True)
        for m in (20_000, 45_000, 90_000, 180_000):
            pts = _ray_points(m, gen)
            up = torch.randn(pts.shape[0], C, generator=gen)

            def step(k):
                (M._trilinear(grid, pts, split=k) * up).sum().backward()
                grid.grad = None

            res = [_median_ms(lambda: step(k), reps) for k in (1, 2)]
            uses = f"{M.split_count(grid, pts.shape[0])} batch(es)"
            print(f"{G:>4}^3 x {C:<3} {pts.shape[0]:>8} {res[0]:>8.1f} {res[1]:>9.1f} {uses:>13}")


def candidates_table(reps: int) -> None:
    gen = torch.Generator().manual_seed(1)
    field = M.GridField(grid_size=128, final_size=128)
    with torch.no_grad():
        field.grid[0, 0] = torch.randn(128, 128, 128, generator=gen)
    # camera 4 units from the origin, 100 x 100 pixels, NeRF-synthetic's field of view
    focal = focal_px(100)
    pose = torch.eye(4)
    pose[2, 3] = 4.0
    pix = torch.randint(0, 100 * 100, (2048,), generator=gen)
    o, d = R.pixel_rays(pose[None].expand(2048, 4, 4), pix, 100, 100, focal)
    jitter = torch.rand(2048, generator=gen)
    print(f"\npacked samples of 2048 rays, median of {reps} (ms)")
    print(f"{'field':>28} {'samples/ray':>11} {'gather':>7} {'trainer':>8}")
    for name, occ_frac in (("fills its box (40 % occ.)", 0.4), ("compact object (box 1.5^3)", None)):
        if occ_frac is None:
            field.occupancy = torch.zeros(128, 128, 128, dtype=torch.bool)
            field.occupancy[40:88, 40:88, 40:88] = torch.rand(48, 48, 48, generator=gen) < 0.3
            field._update_box()
        else:
            field.occupancy = torch.rand(128, 128, 128, generator=gen) < occ_frac
            field._update_box()
        step = field.step_ratio * field.voxel
        n = R._occupied_samples(field, o, d, step, jitter)[0].numel()
        t_gather = _median_ms(lambda: R._occupied_samples(field, o, d, step, jitter, broadcast=False), reps)
        t_now = _median_ms(lambda: R._occupied_samples(field, o, d, step, jitter), reps)
        print(f"{name:>28} {n / 2048:>11.1f} {t_gather:>7.1f} {t_now:>8.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=7)
    args = ap.parse_args()
    trilinear_table(args.reps)
    candidates_table(args.reps)


if __name__ == "__main__":
    main()
