"""The trainer at 100 x 100 and at 400 x 400, side by side on the same data (issue 13).

Trains ``spikelik`` (``--method``: another) on one spike dataset twice -- at 100 x 100 (``--resolution 100``: the
spike counts block-averaged 4 x 4) and at 400 x 400 -- each in its own process (so that each
run's peak memory is its own), evaluates both on the held-out views, and prints a table: wall
time of training and of evaluation, the time ratio 400/100, peak memory (RSS), checkpoint
size, PSNR (full / object). The machine may be shared: the load average (``os.getloadavg``)
is printed at the start and at the end, and the figures to compare are the ratios.

Targets (docs/trainer.md, "Speed at 400 x 400"): the 400 x 400 run reaches its converged quality
in at most 3 times the wall time of the 100 x 100 run, with peak memory under 4 GB. Converged
means an object PSNR within 0.3 dB of the same run with three times the iterations:
``--converge`` also trains both resolutions with 3 x their iterations and prints that difference
(the 3 x runs are the costliest part: at 400 x 400 about three times the 1 x run).

Make the dataset first (a few minutes; keep it outside the repository)::

    spikegen convert /work/shared/data/nerf_synthetic_lego_400 --intensity 64 --sensor rsir --out /tmp/scale
    python bench/bench_trainer_scale.py /tmp/scale/nerf_synthetic_lego_400_i64 [--iters N] [--eval-views 13]
        [--sparse]     # the lazy grid optimiser (off by default in the trainer)
        [--converge]   # also 3 x the iterations at both resolutions: is the 1 x run converged?
        [--runs 100:3000,400:9000,400:27000]   # the runs instead (the first two: the ratio's pair)
        [--runs 100:9000,400:27000:1,400:81000:1]   # a third field: that run's --step-ratio (default: the trainer's, 0.5)
        [--runs 100:9000,400:9000:0.5:0.5]   # a fourth: its --error-rays (default: the trainer's, 0)
        [--method oracle]   # another method (default spikelik)
        [--srgb-weight 0]   # every run with this --srgb-weight (default: each run the trainer's default for its
                            # counts, recorded in its row: 400 for the likelihood methods where a white pixel counts
                            # 16 spikes a window or more, else 0, off)
        [--json FILE]  # the rows and the load averages, for the record
        [--device cuda]  # train and evaluate on the GPU (its name and peak GPU memory join the rows)
    python bench/bench_trainer_scale.py --table FILE   # the table of a saved --json file again
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_protocol import SRGB_METHODS, _commit, _gpu  # (bench/ is this script's folder: on sys.path)
from spikenerf.config import TrainConfig, default_iters
from spikenerf.methods import METHODS

CONVERGED = 0.3  # dB of object PSNR: a run is converged when three times its iterations gain no more


def child(dataset: str, resolution: int, iters: int, out: Path, eval_views: int | None, sparse: bool,
          method: str = "spikelik", device: str = "cpu", step_ratio: float = TrainConfig.step_ratio,
          error_rays: float = TrainConfig.error_rays, srgb_weight: float | None = None) -> dict:
    """Train and evaluate one run in this process; the figures as a dict."""
    from spikenerf.eval import evaluate
    from spikenerf.train import train

    # --sparse: the lazy optimiser for grids above 128^3 (the 400 x 400 run's final grid)
    lazy = {"lazy_above": 128 ** 3} if sparse else {}
    cfg = TrainConfig(dataset=dataset, iters=iters, resolution=resolution, device=device, method=method,
                      step_ratio=step_ratio, error_rays=error_rays, srgb_weight=srgb_weight, **lazy)
    t0 = time.perf_counter()
    ck = train(cfg, out, progress=False, log=lambda m: None)
    t_train = time.perf_counter() - t0
    t0 = time.perf_counter()
    m = evaluate(out, device=device, progress=False, max_views=eval_views)
    t_eval = time.perf_counter() - t0
    gpu = _gpu(device)
    if gpu:  # and the most memory torch held on it (training and evaluation)
        import torch
        gpu["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
    used = json.loads((out / "config.json").read_text())  # the run's settings as the trainer resolved them
    return {"method": method, "resolution": resolution, "iters": iters, "step_ratio": used["step_ratio"],
            "error_rays": used["error_rays"], "srgb_weight": used["srgb_weight"],
            "device": device, **gpu,
            "train_s": t_train, "eval_s": t_eval, "views": m["views"],
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "checkpoint_mb": ck.stat().st_size / 1e6, "psnr": m["psnr"], "psnr_object": m["psnr_object"]}


def run_child(args, resolution: int, iters: int, out: Path, step_ratio: float, error_rays: float) -> dict:
    cmd = [sys.executable, __file__, args.dataset, "--iters", str(iters), "--child", str(resolution),
           "--out", str(out)] + (["--eval-views", str(args.eval_views)] if args.eval_views else []) + \
          (["--sparse"] if args.sparse else []) + ["--method", args.method, "--device", args.device,
                                                   "--step-ratio", str(step_ratio), "--error-rays", str(error_rays)] + \
          (["--srgb-weight", str(args.srgb_weight)] if args.srgb_weight is not None else [])
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        sys.exit(f"the {resolution} x {resolution} run ({iters} iterations) failed: {res.stderr.strip().splitlines()[-1:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def tripled(rows: list[dict], run: dict) -> dict | None:
    """The run among ``rows`` at the same resolution, sample step, error-guided share and sRGB weight with three
    times ``run``'s iterations, if any."""
    return next((q for q in rows if q["resolution"] == run["resolution"] and _step(q) == _step(run)
                 and _mined(q) == _mined(run) and _weight(q) == _weight(run) and q["iters"] == 3 * run["iters"]),
                None)


def _step(row: dict) -> float:
    return row.get("step_ratio", 0.5)  # rows from before the option: the trainer's step then, 0.5 voxel


def _mined(row: dict) -> float:
    return row.get("error_rays", 0.0)  # rows from before the option: every ray uniform


def _weight(row: dict) -> float:
    return row.get("srgb_weight", 0.0)  # rows from before the option: off


def _weights(rows: list[dict]) -> str:
    """The runs' sRGB weights for a table's header: one where all share it (nothing where that is 0, off), else
    each run's."""
    weights = {_weight(r) for r in rows}
    if len(weights) > 1:
        return " with --srgb-weight " + ", ".join(f"{_weight(r):g} ({r['resolution']}:{r['iters']})" for r in rows)
    (weight,) = weights
    return f" with --srgb-weight {weight:g}" if weight else ""


def _key(row: dict) -> tuple:
    """A run's identity within one dataset: (resolution, sample step, error-guided share, sRGB weight,
    iterations)."""
    return row["resolution"], _step(row), _mined(row), _weight(row), row["iters"]


def _setting(row: dict) -> str:
    return (f"step {_step(row):g}" + (f", error rays {_mined(row):g}" if _mined(row) else "")
            + (f", sRGB weight {_weight(row):g}" if _weight(row) else ""))


def _gaps(rows: list[dict]):
    """(run, object PSNR of its 3 x run minus its own, the line that says so) for each run of ``rows`` that has
    a 3 x run among them, in the order of :func:`_key`."""
    for r in sorted(rows, key=_key):
        long = tripled(rows, r)
        if long is not None:
            gap = long["psnr_object"] - r["psnr_object"]
            yield r, gap, (f"{r['resolution']} x {r['resolution']} ({_setting(r)}): object PSNR at {long['iters']} "
                           f"minus at {r['iters']} iterations: {gap:+.2f} dB (converged within {CONVERGED} dB: "
                           f"{'yes' if gap <= CONVERGED else 'NO'})")


def converged_runs(rows: list[dict]) -> dict:
    """{resolution: the run with the least training time whose object PSNR is within CONVERGED dB of
    the same resolution's (and setting's) run with three times its iterations} (a resolution with no
    such pair: absent)."""
    out = {}
    for r in sorted(rows, key=lambda r: r["train_s"]):
        long = tripled(rows, r)
        if r["resolution"] not in out and long is not None and long["psnr_object"] - r["psnr_object"] <= CONVERGED:
            out[r["resolution"]] = r
    return out


def table(rows: list[dict]) -> None:
    print(f"{'run':>10} {'step':>4} {'mined':>5} {'iters':>6} {'train s':>8} {'eval s':>7} {'views':>5} {'peak RSS MB':>11} "
          f"{'checkpoint MB':>13} {'PSNR':>6} {'object':>6} {'load at end':>11}")
    for r in rows:
        print(f"{r['resolution']:>4} x {r['resolution']:<3} {_step(r):>4g} {_mined(r):>5g} {r['iters']:>6} {r['train_s']:>8.1f} {r['eval_s']:>7.1f} "
              f"{r['views']:>5} {r['peak_rss_mb']:>11.0f} {r['checkpoint_mb']:>13.1f} {r['psnr']:>6.2f} "
              f"{r['psnr_object']:>6.2f} {r.get('load_after', float('nan')):>11.2f}")
    a = rows[0]
    if len(rows) > 1:  # the ratio's pair: the first two runs
        b = rows[1]
        print(f"training time ratio {b['resolution']}/{a['resolution']} ({b['iters']} / {a['iters']} iterations): "
              f"{b['train_s'] / a['train_s']:.2f} (the target is for a converged run: below); evaluation time ratio "
              f"per view: {(b['eval_s'] / b['views']) / (a['eval_s'] / a['views']):.2f}")
    for _, _, line in _gaps(rows):
        print(line)
    conv = converged_runs(rows)
    hi, lo = max(r["resolution"] for r in rows), min(r["resolution"] for r in rows)
    if hi in conv:
        c = conv[hi]
        print(f"{hi} x {hi} converged at {c['iters']} iterations ({_setting(c)}) in {c['train_s']:.0f} s: {c['train_s'] / a['train_s']:.2f} "
              f"times the {lo} x {lo} run of {a['iters']} iterations (target <= 3: "
              f"{'met' if c['train_s'] <= 3 * a['train_s'] else 'NOT met'})"
              + (f", {c['train_s'] / conv[lo]['train_s']:.2f} times the {lo} x {lo} run converged at {conv[lo]['iters']}"
                 if lo in conv else f"; no converged {lo} x {lo} run among these"))
    else:
        print(f"no {hi} x {hi} run is shown converged (no run within {CONVERGED} dB of its 3 x run)")
    peak = max(r["peak_rss_mb"] for r in rows)
    print(f"peak memory {peak:.0f} MB (target < 4096: {'met' if peak < 4096 else 'NOT met'})")
    if any("gpu" in r for r in rows):
        print(f"on {rows[0]['gpu']}: peak GPU memory (torch) {max(r['peak_gpu_mb'] for r in rows):.0f} MB")


def across(files: list[dict], names: list[str]) -> None:
    """Several saved files of the same data: which runs are converged over all their rows (a run made in
    two files counts once: the trainer is deterministic). Times compare only within one file (runs made
    side by side), so the ratio of the converged runs is printed from a file that holds both."""
    if len({f["dataset"] for f in files}) > 1:
        sys.exit("--table: the files are of different datasets; convergence across them means nothing")
    runs = {}
    for f in files:
        for r in f["rows"]:
            runs.setdefault(_key(r), r)
    print(f"across the {len(files)} files (training times compare within a file only):")
    conv = {}
    for r, gap, line in _gaps(list(runs.values())):
        print(f"  {line}")
        if gap <= CONVERGED:
            conv.setdefault(r["resolution"], r)  # the fewest iterations converged at this size
    for res, r in sorted(conv.items()):
        print(f"  {res} x {res}: converged at {r['iters']} iterations ({_setting(r)})")
    if len(conv) < 2:
        print("  not both sizes shown converged: no ratio of converged runs")
        return
    lo, hi = _key(conv[min(conv)]), _key(conv[max(conv)])
    for f, name in zip(files, names):
        held = {_key(r): r for r in f["rows"]}
        if lo in held and hi in held:
            ratio = held[hi]["train_s"] / held[lo]["train_s"]
            print(f"  converged against converged, side by side in {name}: {hi[0]} x {hi[0]} / {lo[0]} x {lo[0]} = "
                  f"{held[hi]['train_s']:.1f} / {held[lo]['train_s']:.1f} s = {ratio:.2f} "
                  f"(target <= 3: {'met' if ratio <= 3 else 'NOT met'})")
            return
    print("  no file holds both converged runs: no side-by-side ratio")


def _planned(run: str) -> tuple[int, int, float, float]:
    """``RES:ITERS[:STEP_RATIO[:ERROR_RAYS]]`` -> (resolution, iterations, step ratio, error-guided share; the
    trainer's defaults where not given)."""
    parts = run.split(":")
    try:
        if len(parts) not in (2, 3, 4):
            raise ValueError
        return (int(parts[0]), int(parts[1]), float(parts[2]) if len(parts) >= 3 else TrainConfig.step_ratio,
                float(parts[3]) if len(parts) == 4 else TrainConfig.error_rays)
    except ValueError:
        sys.exit(f"--runs: {run!r} is not RES:ITERS[:STEP_RATIO[:ERROR_RAYS]]")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", nargs="?", help="a 400 x 400 spike dataset (spikegen convert ... --sensor rsir)")
    ap.add_argument("--iters", type=int, default=0, help="0 = the trainer's default at each resolution "
                    "(spikenerf.config.default_iters: 3000 at 100 x 100, 9000 at 400 x 400)")
    ap.add_argument("--eval-views", type=int, default=None, help="evaluate the first N held-out views (default all)")
    ap.add_argument("--out", type=Path, default=None, help="runs go here (default: a temporary folder)")
    ap.add_argument("--sparse", action="store_true", help="grids above 128^3 train with the lazy optimiser")
    ap.add_argument("--converge", action="store_true", help="also train both resolutions with 3 x their iterations")
    ap.add_argument("--runs", default="", help="the runs instead, as RES:ITERS,... (the first two are the ratio's "
                    "pair, e.g. 100:3000,400:9000,400:27000,100:9000,100:27000)")
    ap.add_argument("--method", default="spikelik", help="the trainer's --method (oracle: the same field fitted to "
                    "the ground-truth images, what the field and its optimisation reach without the spikes' noise)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where both runs train and evaluate "
                    "(cuda: the GPU's name and peak GPU memory are added to each row)")
    ap.add_argument("--json", type=Path, default=None, help="write the rows and load averages to this file")
    ap.add_argument("--table", type=Path, nargs="+", default=None,
                    help="print the table of each saved --json file and stop; with several (the same data), then "
                         "which runs are converged over all their rows")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--step-ratio", type=float, default=TrainConfig.step_ratio,
                    help=argparse.SUPPRESS)  # the child's; --runs sets it
    ap.add_argument("--error-rays", type=float, default=TrainConfig.error_rays,
                    help=argparse.SUPPRESS)  # the child's; --runs sets it
    ap.add_argument("--srgb-weight", type=float, default=None, help="every run with the trainer's --srgb-weight "
                    "(each ray's display weight in the likelihood, at most this; 0 = off; default: each run the trainer's "
                    "default for its counts, recorded in its row: 400 for the likelihood methods where a white pixel "
                    "counts 16 spikes a window or more, else off)")
    args = ap.parse_args()
    if args.table:
        files = [json.loads(f.read_text()) for f in args.table]
        for f, saved in zip(args.table, files):
            print(f"{f.name}: {saved['dataset']}; method {saved['rows'][0].get('method', 'spikelik')}"
                  + _weights(saved["rows"]) + "; "
                  f"OMP_NUM_THREADS={saved['omp_threads']}; load average at start "
                  f"{' '.join(f'{x:.2f}' for x in saved['load_start'])}, at end "
                  f"{' '.join(f'{x:.2f}' for x in saved['load_end'])}; commit {saved.get('commit', '?')}")
            table(saved["rows"])
        if len(files) > 1:
            across(files, [f.name for f in args.table])
        return
    if not args.dataset:
        ap.error("a dataset is needed (or --table FILE)")
    if args.method not in METHODS:
        sys.exit(f"unknown --method {args.method!r}; expected one of {', '.join(METHODS)}")
    if args.srgb_weight is not None and (not args.srgb_weight >= 0
                                         or (args.srgb_weight and args.method not in SRGB_METHODS)):
        sys.exit(f"--srgb-weight must be >= 0, and is for the likelihood methods ({', '.join(SRGB_METHODS)})")
    if args.child:
        print(json.dumps(child(args.dataset, args.child, args.iters, args.out, args.eval_views, args.sparse,
                               args.method, args.device, args.step_ratio, args.error_rays, args.srgb_weight)))
        return
    load0 = os.getloadavg()
    weight = "the trainer's default for each run" if args.srgb_weight is None else f"{args.srgb_weight:g}"
    plan_text = f"runs {args.runs}" if args.runs else f"{args.iters or 'the default'} iterations"
    print(f"load average at start: {' '.join(f'{x:.2f}' for x in load0)}; "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; "
          f"{plan_text}; method {args.method}; device {args.device}; sRGB weight {weight}; "
          f"{'lazy optimiser above 128^3' if args.sparse else 'dense Adam'}")
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
        base = args.out or Path(tmp)
        if args.runs:
            plan = [_planned(run) for run in args.runs.split(",")]
        else:
            plan = [(res, args.iters or default_iters(res, res), TrainConfig.step_ratio, TrainConfig.error_rays)
                    for res in (100, 400)]
            if args.converge:
                plan += [(res, 3 * iters, step, mined) for res, iters, step, mined in reversed(plan)]
        rows = []
        for res, iters, step, mined in plan:
            rows.append(run_child(args, res, iters, base / (f"run{res}_{iters}_step{step:g}_mined{mined:g}"
                                                            + (f"_srgbw{args.srgb_weight:g}" if args.srgb_weight is not None
                                                               else "")),
                                  step, mined))
            rows[-1]["load_after"] = round(os.getloadavg()[0], 2)  # the 1-minute load as the run ended
            print(f"  {res} x {res}, {iters} iterations: {rows[-1]['train_s']:.0f} s, object PSNR "
                  f"{rows[-1]['psnr_object']:.2f} (load {rows[-1]['load_after']:.2f})", flush=True)
    load1 = os.getloadavg()
    print(f"load average at end: {' '.join(f'{x:.2f}' for x in load1)}")
    if args.json:  # first: the runs are what took the time
        args.json.write_text(json.dumps({"dataset": args.dataset, "load_start": load0, "load_end": load1,
                                         "omp_threads": os.environ.get("OMP_NUM_THREADS"), "commit": _commit(),
                                         "rows": rows}, indent=1))
    table(rows)


if __name__ == "__main__":
    main()
