"""Where a training step's time goes on the CPU, and what the trainer's two CPU paths buy.

Prints, for synthetic but realistic inputs (points along rays, as the renderer makes them):

1. ``trilinear``: forward + backward of sampling a voxel grid at M points, as one batch
   and as two batches of the expanded grid (the default on the CPU), for
   the main grid (128^3 x 2 channels) and the degree-1 SH grid (64^3 x 3). The trainer splits
   when ``M * 64 >= grid values``; the table shows the break-even that rule stands for.
2. ``candidates``: making the packed samples of 2048 rays (``render._occupied_samples``) for a
   field that fills its box (a hazy baseline) and for a compact object: in one pass, gather vs
   broadcast, and the trainer's (empty blocks skipped first, where that pays).
3. ``grid step``: the parts of a training step that scale with the grid, at the 400 x 400 grid
   (256^3 x 2 + SH 128^3 x 3) and the 100 x 100 one (128^3), dense (grid_sample, autograd's
   dense gradients, fused torch Adam, max-pooled occupancy: the trainer before issue 13; it
   keeps all but the occupancy by default) against sparse (corner gather, the opt-in
   LazyGridAdam, threshold + separable dilation).

Usage::

    python bench/bench_trainer_step.py            # the tables (a few seconds on 2 cores)
    python bench/bench_trainer_step.py --reps 15  # steadier medians
    python bench/bench_trainer_step.py --only grid-step  # just table 3
    python bench/bench_trainer_step.py --run RUN [--run RUN2]  # only the trained fields' table (below)
    python bench/bench_trainer_step.py --run RUN --step        # whole training steps, now against before
    python bench/bench_trainer_step.py --run RUN --stop        # early ray termination against none
    python bench/bench_trainer_step.py --run RUN --origins     # contiguous ray origins against strided

4. ``--run RUN``: a trained run's field (its checkpoint): a training step's rendering and a held-out
   view, samples made in one pass against empty blocks skipped first (``render._skip_blocks``).
5. ``--run RUN --step``: whole training steps on that field, the trainer's way now (corner reads that
   add into the kept ``grid.grad``) against its way before 2026-11-25 (``grid_sample`` and autograd's
   grid-sized gradients), interleaved on two copies of the field.
6. ``--run RUN --stop``: early ray termination on that field: the share of a step's occupied samples
   that their ray reaches with transmittance below 1e-2, 1e-3 and 1e-4; whole training steps with the
   trainer's ``--stop-transmittance`` against 0 (two copies of the field, the same rays, interleaved);
   a held-out view's rendering is not changed by it (no gradients: every occupied sample is read).
7. ``--run RUN --origins``: whole training steps and held-out views with the rays' origins as
   ``render.pixel_rays`` gives them since 2026-11-26 (a contiguous copy) against its way before (a
   strided view of the poses: stride 0 over a view's rays, where one pose is expanded), interleaved
   on two copies of the field; the steps' grids and the views checked equal to the bit.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch
import torch.nn.functional as F

from spikegen.camera import focal_px
from spikenerf import model as M
from spikenerf import render as R
from spikenerf.optim import LazyGridAdam


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
    print(f"\npacked samples of 2048 rays, median of {reps} (ms): one pass by gather, one pass as the trainer "
          f"chooses (gather or broadcast), and the trainer's (empty blocks skipped first)")
    print(f"{'field':>28} {'samples/ray':>11} {'gather':>7} {'one pass':>9} {'trainer':>8}")
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
        t_gather = _median_ms(lambda: R._occupied_samples(field, o, d, step, jitter, broadcast=False, coarse=False),
                              reps)
        t_one = _median_ms(lambda: R._occupied_samples(field, o, d, step, jitter, coarse=False), reps)
        t_now = _median_ms(lambda: R._occupied_samples(field, o, d, step, jitter), reps)
        print(f"{name:>28} {n / 2048:>11.1f} {t_gather:>7.1f} {t_one:>9.1f} {t_now:>8.1f}")


def _step_parts(G: int, sparse: bool, points: int, reps: int) -> dict:
    """Median ms of each grid-sized part of a step for a ``G^3`` field with degree-1 SH."""
    gen = torch.Generator().manual_seed(2)
    f = M.GridField(grid_size=G, final_size=G, sh_degree=1)
    with torch.no_grad():
        f.grid.normal_(generator=gen)
        f.grid[0, 0] -= 6  # a sparse occupancy, as a trained object
    o = torch.rand(points // 100, 1, 3, generator=gen) * 1.2 - 0.6  # points along rays, half a voxel apart
    d = torch.nn.functional.normalize(torch.randn(points // 100, 1, 3, generator=gen), dim=-1)
    pts = (o + d * torch.arange(100)[None, :, None] * (f.voxel / 2)).reshape(-1, 3).clamp(-1.4, 1.4)
    dirs = d.expand(-1, 100, -1).reshape(-1, 3)
    if sparse:
        opt = LazyGridAdam(f, 0.1, 1e-3)  # the optimiser sets nothing on the field: sparse mode is set here
        f.sparse = True
    else:
        opt = torch.optim.Adam(f.grids(), lr=0.1, betas=(0.9, 0.99), fused=True)

    def sample():
        opt.zero_grad(set_to_none=True)
        sigma, x = f.query(pts, dirs)
        (sigma.mean() + x.mean()).backward()

    def tv():
        f.tv_loss(gen).backward()

    def occupancy():
        if sparse:
            f.update_occupancy(0.02)
            return
        with torch.no_grad():  # the trainer's update before this change
            alpha = 1 - torch.exp(-F.softplus(f.grid[0, 0] + f.shift) * f.step_ratio * f.voxel / f.ref_voxel)
            f.occupancy = F.max_pool3d(alpha[None, None], kernel_size=3, stride=1, padding=1)[0, 0] > 0.02

    out = _sample_then_step_ms(sample, opt, reps)
    out["TV fwd+bwd"] = _median_ms(lambda: (opt.zero_grad(), tv(), f.tape.clear()), reps)
    out["occupancy / 50"] = _median_ms(occupancy, max(1, reps // 3)) / 50  # it runs every 50 iterations
    return out


def _sample_then_step_ms(sample, opt, reps: int) -> dict:
    """Median ms of ``sample()`` and of the optimiser step that follows it."""
    sample_ms, step_ms = [], []
    for _ in range(reps + 1):  # the first is a warm-up
        t0 = time.perf_counter()
        sample()
        t1 = time.perf_counter()
        opt.step()
        sample_ms.append(1000 * (t1 - t0))
        step_ms.append(1000 * (time.perf_counter() - t1))
    return {"sample fwd+bwd": statistics.median(sample_ms[1:]), "Adam step": statistics.median(step_ms[1:])}


def grid_step_table(reps: int, points: int = 100_000) -> None:
    print(f"\ngrid-sized parts of a step, {points} points, median of {reps} (ms)")
    rows = {(G, sp): _step_parts(G, sp, points, reps) for G in (128, 256) for sp in (False, True)}
    parts = list(next(iter(rows.values())))
    print(f"{'part':>16} " + " ".join(f"{f'{G}^3 ' + ('sparse' if sp else 'dense'):>14}" for G, sp in rows))
    for part in parts + ["sum"]:
        vals = [sum(r.values()) if part == "sum" else r[part] for r in rows.values()]
        print(f"{part:>16} " + " ".join(f"{v:>14.1f}" for v in vals))


def trained_table(run: str, reps: int) -> None:
    """A trained run's field: a training step's rendering (2048 random rays of its training views,
    jittered, forward + backward) and a full held-out view, with the samples made in one pass and
    with empty blocks skipped first, interleaved, each pair checked equal to the bit. Times are this
    process's CPU seconds (``time.process_time``; with one thread, what the work cost even when other
    jobs share the cores and stretch its wall time)."""
    import os

    from spikenerf.data import load_dataset
    from spikenerf.eval import checkpoint_camera, checkpoint_space, field_from_checkpoint
    from spikenerf.train import load_checkpoint

    ck = load_checkpoint(os.path.join(run, "checkpoint.pt"), "cpu")
    field = field_from_checkpoint(ck, "cpu")
    H, W, focal, bg = checkpoint_camera(ck)
    space = checkpoint_space(ck)
    ds = load_dataset(ck["config"]["dataset"])
    poses = torch.stack([torch.as_tensor(v.pose, dtype=torch.float32) for v in ds.splits["train"]])
    held = ds.splits.get("test") or ds.splits.get("val") or ds.splits["train"]
    gen = torch.Generator().manual_seed(0)
    worth = R._worth_skipping
    times = {"step": ([], []), "view": ([], [])}
    print(f"\n{run}: grid {field.dims}, {H} x {W}; torch threads {torch.get_num_threads()}; "
          f"load average {os.getloadavg()[0]:.2f} at start")
    for r in range(reps):
        vi = torch.randint(0, len(poses), (2048,), generator=gen)
        pix = torch.randint(0, H * W, (2048,), generator=gen)
        jitter = torch.rand(2048, generator=gen)
        o, d = R.pixel_rays(poses[vi], pix, H, W, focal)
        pose = torch.as_tensor(held[r % len(held)].pose, dtype=torch.float32)
        out = {}
        for skip in (False, True):
            R._worth_skipping = worth if skip else (lambda f: False)
            field.grid.grad = None
            t0 = time.process_time()
            if space is None:
                x = R.render_rays(field, o, d, jitter, background=bg)[0]
            else:
                x = R.render_ndc_rays(field, space, o, d, jitter, background=bg)[0][0]
            x.sum().backward()
            t1 = time.process_time()
            img = R.render_image(field, pose, H, W, focal, background=bg, space=space)[0]
            t2 = time.process_time()
            times["step"][skip].append(t1 - t0)
            times["view"][skip].append(t2 - t1)
            out[skip] = (x.detach(), field.grid.grad.clone(), img)
        R._worth_skipping = worth
        assert all(torch.equal(a, b) for a, b in zip(out[False], out[True])), "the two ways differ"
    for part, label in (("step", "render + backward, 2048 rays"), ("view", "one held-out view")):
        one, two = (1000 * statistics.median(times[part][k]) for k in (False, True))
        print(f"{label:>30}: one pass {one:8.1f} ms, empty blocks skipped {two:8.1f} ms, ratio {one / two:.2f} "
              f"(CPU time, median of {reps})")
    print(f"load average {os.getloadavg()[0]:.2f} at end; outputs and gradients equal to the bit")


def _training_setup(run: str):
    """A trained run's checkpoint, settings, dataset, size, method, camera and the training batch
    (the trainer's own targets), for timing whole training steps on its field."""
    import os

    from spikenerf import train as T
    from spikenerf.config import TrainConfig
    from spikenerf.data import load_dataset
    from spikenerf.methods import METHODS
    from spikenerf.targets import build_targets

    ck = T.load_checkpoint(os.path.join(run, "checkpoint.pt"), "cpu")
    known = TrainConfig.__dataclass_fields__  # (a checkpoint from before an option lacks its key)
    cfg = TrainConfig(**{k: tuple(v) if k == "upsample_at" else v for k, v in ck["config"].items() if k in known})
    ds = load_dataset(cfg.dataset)
    H, W = T._resolution(ds, cfg.resolution)
    method = METHODS[cfg.method]
    batch = T.Batch(build_targets(ds, method, H, W, progress=False, frames=cfg.frames, windows=cfg.windows,
                                  maps_file=cfg.sensor_maps or None), torch.device("cpu"))
    return ck, cfg, ds, (H, W), method, batch, (ds.camera(H, W), ds.background)


def _train_step(setup, field, opt, it: int, stop: float, set_to_none: bool = False) -> torch.Tensor:
    """One whole training step of ``field`` with its optimiser ``opt`` (the trainer's loop body: the
    iteration's rays, render with early ray termination ``stop``, loss, prior, zero_grad, backward,
    Adam), from :func:`_training_setup`'s ``setup``; the rays' luminance."""
    from spikenerf import train as T

    ck, cfg, ds, (H, W), method, batch, (focal, bg) = setup
    gen = T.iteration_generator(cfg.seed, it)
    img, pix, jitter = batch.draw(cfg.batch_rays, gen)
    o, d = R.pixel_rays(batch.poses[img], pix, H, W, focal)
    x, _ = R.render_rays(field, o, d, jitter, bg, stop=stop)
    loss = T.method_loss(method, x, img, pix, batch, ds.intensity)[0] + cfg.tv_weight * field.tv_loss(gen)
    opt.zero_grad(set_to_none=set_to_none)
    loss.backward()
    opt.step()
    return x.detach()


def training_step_table(run: str, reps: int) -> None:
    """A trained run's field: whole training steps (its rays, render, loss, prior, zero_grad, backward,
    Adam) the trainer's way now -- corner reads adding into the kept ``grid.grad`` -- and the way it
    was before 2026-11-25 -- reads through ``grid_sample``, the prior's block by slicing, autograd's
    grid-sized gradients, ``zero_grad(set_to_none=True)`` -- on two copies of the field with their
    own Adam, the same rays, interleaved; both with the trainer's early ray termination (the old way
    reads the kept samples through ``grid_sample``), so only the reads differ. Prints the median wall
    and CPU time of each and their ratio, and the largest difference of the two copies' grids after the
    steps (float rounding only)."""
    import os

    from spikenerf import train as T
    from spikenerf.config import STOP_TRANSMITTANCE  # (render_rays' default)

    setup = _training_setup(run)
    ck, cfg, (H, W) = setup[0], setup[1], setup[3]
    fields = {way: T.field_from_checkpoint(ck, "cpu") for way in ("now", "before")}
    opts = {way: T.make_optimizer(f, cfg) for way, f in fields.items()}
    before = fields["before"]
    before._read = lambda grid, points, reads=None: M._trilinear(grid, before.normalise(points))  # grid_sample
    block_read = M._BlockRead.apply

    def step(way: str, it: int) -> None:
        M._BlockRead.apply = block_read if way == "now" else (lambda g, box: g[(slice(None), slice(None)) + tuple(box)])
        _train_step(setup, fields[way], opts[way], it, STOP_TRANSMITTANCE, set_to_none=way == "before")

    times = {way: ([], []) for way in fields}
    print(f"\n{run}: whole training steps, grid {fields['now'].dims}, {H} x {W}; torch threads "
          f"{torch.get_num_threads()}; load average {os.getloadavg()[0]:.2f} at start")
    for r in range(reps + 2):
        for way in ("now", "before") if r % 2 else ("before", "now"):
            w0, c0 = time.perf_counter(), time.process_time()
            step(way, 100 + r)
            if r >= 2:  # two warm-up steps each
                times[way][0].append(time.perf_counter() - w0)
                times[way][1].append(time.process_time() - c0)
    M._BlockRead.apply = block_read
    med = {way: [1000 * statistics.median(v) for v in times[way]] for way in times}
    for way, label in (("before", "grid_sample, autograd's gradients"), ("now", "corner reads, gradient in place")):
        print(f"{label:>36}: {med[way][0]:8.1f} ms wall, {med[way][1]:8.1f} ms CPU (median of {reps})")
    diff = float((fields["now"].grid - fields["before"].grid).detach().abs().max())
    print(f"{'before / now':>36}: {med['before'][0] / med['now'][0]:.2f} wall, {med['before'][1] / med['now'][1]:.2f} CPU; "
          f"grids after {reps + 2} steps differ by at most {diff:.2e}; load average {os.getloadavg()[0]:.2f} at end")


def termination_table(run: str, reps: int) -> None:
    """Early ray termination (``render.visible_samples``) on a trained run's field: how many occupied
    samples lie behind transmittance ``stop``, and what dropping them saves in a whole training step
    (CPU seconds of this process, medians; one thread measures the work even when other jobs share
    the cores)."""
    import os

    from spikenerf import train as T
    from spikenerf.config import STOP_TRANSMITTANCE as stop

    setup = _training_setup(run)
    ck, cfg, _, (H, W), _, batch, (focal, _) = setup
    fields = {s: T.field_from_checkpoint(ck, "cpu") for s in (0.0, stop)}
    opts = {s: T.make_optimizer(f, cfg) for s, f in fields.items()}
    field = fields[0.0]
    step_len = field.step_ratio * field.voxel
    print(f"\n{run}: early ray termination; grid {field.dims}, {H} x {W}; torch threads {torch.get_num_threads()}; "
          f"load average {os.getloadavg()[0]:.2f} at start")
    total, behind = 0, {1e-2: 0, 1e-3: 0, 1e-4: 0}
    with torch.no_grad():
        for it in range(10):
            img, pix, jitter = batch.draw(cfg.batch_rays, T.iteration_generator(cfg.seed, it))
            o, d = R.pixel_rays(batch.poses[img], pix, H, W, focal)
            _, ray_of, pts = R._occupied_samples(field, o, d, step_len, jitter)
            trans = R.sample_transmittance(field, ray_of, pts, o.shape[0], step_len)[0]
            total += trans.numel()
            for t in behind:
                behind[t] += int((trans < t).sum())
    print(f"{'occupied samples a ray':>36}: {total / (10 * cfg.batch_rays):.1f}; behind transmittance " +
          ", ".join(f"{t:g}: {100 * v / total:.1f} %" for t, v in behind.items()) + " (10 batches)")

    times = {s: [] for s in fields}
    outs = {}
    for r in range(reps + 2):
        for s in (0.0, stop) if r % 2 else (stop, 0.0):
            c0 = time.process_time()
            outs[s] = _train_step(setup, fields[s], opts[s], 100 + r, s)
            if r >= 2:  # two warm-up steps each
                times[s].append(time.process_time() - c0)
        if r == 0:
            diff = float((outs[0.0] - outs[stop]).abs().max())
    a, b = (1000 * statistics.median(times[s]) for s in (0.0, stop))
    print(f"{'training step':>36}: stop 0 {a:8.1f} ms, stop {stop:g} {b:8.1f} ms; ratio {a / b:.2f} (CPU time, median "
          f"of {reps})")
    print(f"{'first step, largest difference':>36}: {diff:.2e} in a ray's luminance; load average "
          f"{os.getloadavg()[0]:.2f} at end")


def origins_table(run: str, reps: int) -> None:
    """Contiguous ray origins (``render.pixel_rays`` now) against the strided view of the poses it
    returned before 2026-11-26: whole training steps (two copies of the field, the same rays) and a
    held-out view, interleaved; CPU seconds of this process, medians. The samples gather each one's
    ray origin (``index_select``), which PyTorch's CPU kernel does many times slower from a strided
    tensor."""
    import os

    from spikenerf import train as T

    setup = _training_setup(run)
    ck, cfg, ds, (H, W), _, _, (focal, bg) = setup
    rays = R.pixel_rays

    def strided(poses, *a, **k):  # the way before: the origins a view of the poses
        return poses[:, :3, 3], rays(poses, *a, **k)[1]

    ways = {"strided": strided, "contiguous": rays}
    fields = {w: T.field_from_checkpoint(ck, "cpu") for w in ways}
    opts = {w: T.make_optimizer(f, cfg) for w, f in fields.items()}
    held = ds.splits.get("test") or ds.splits.get("val") or ds.splits["train"]
    print(f"\n{run}: ray origins; grid {fields['contiguous'].dims}, {H} x {W}; torch threads "
          f"{torch.get_num_threads()}; load average {os.getloadavg()[0]:.2f} at start")
    times = {w: ([], []) for w in ways}
    views = {}
    try:
        for r in range(reps + 2):
            pose = torch.as_tensor(held[r % len(held)].pose, dtype=torch.float32)
            for w in ("strided", "contiguous") if r % 2 else ("contiguous", "strided"):
                R.pixel_rays = ways[w]
                c0 = time.process_time()
                _train_step(setup, fields[w], opts[w], 100 + r, cfg.stop_transmittance)
                c1 = time.process_time()
                with torch.no_grad():
                    views[w] = R.render_image(fields[w], pose, H, W, focal, background=bg, far=6.0)
                c2 = time.process_time()
                if r >= 2:  # one warm-up step and view each, twice
                    times[w][0].append(c1 - c0)
                    times[w][1].append(c2 - c1)
            assert all(torch.equal(a, b) for a, b in zip(views["strided"], views["contiguous"])), "the views differ"
    finally:
        R.pixel_rays = rays
    same = all(torch.equal(a, b) for a, b in zip(fields["strided"].grids(), fields["contiguous"].grids()))
    assert same, "the grids differ"
    for k, label in ((0, "training step"), (1, "one held-out view")):
        a, b = (1000 * statistics.median(times[w][k]) for w in ("strided", "contiguous"))
        print(f"{label:>36}: strided {a:8.1f} ms, contiguous {b:8.1f} ms; ratio {a / b:.2f} (CPU time, median of {reps})")
    print(f"{'':>36}  grids after {reps + 2} steps and every view equal to the bit; load average "
          f"{os.getloadavg()[0]:.2f} at end")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--only", choices=["trilinear", "candidates", "grid-step"], default=None)
    ap.add_argument("--run", action="append", default=[], help="also time a trained run's field (its folder)")
    ap.add_argument("--step", action="store_true", help="with --run: whole training steps, now against before")
    ap.add_argument("--stop", action="store_true", help="with --run: early ray termination against none")
    ap.add_argument("--origins", action="store_true", help="with --run: contiguous ray origins against strided")
    args = ap.parse_args()
    if args.run:
        for run in args.run:
            table = (origins_table if args.origins else termination_table if args.stop else
                     training_step_table if args.step else trained_table)
            table(run, args.reps)
        if args.only is None:
            return
    tables = {"trilinear": trilinear_table, "candidates": candidates_table, "grid-step": grid_step_table}
    for name, table in tables.items():
        if args.only in (None, name):
            table(args.reps)


if __name__ == "__main__":
    main()
