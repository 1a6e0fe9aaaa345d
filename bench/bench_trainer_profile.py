"""Where a trained run's training steps spend their time, on the CPU or a GPU (issue 13).

Continues a finished run (a copy of its checkpoint, in a temporary folder) for ``--steps`` more
iterations at its final grid: the first half timed plainly (ms per step, from the
training loop's own clock in the checkpoint, so loading the data and saving are not counted), the second half under ``torch.profiler``, whose table of operators
(sorted by their own time on the device: the GPU's kernels under CUDA, the CPU's otherwise) is
printed. The run's own settings are kept; only the iteration count grows (its learning-rate
schedule is stretched over the longer run, which does not change the work per step).

    python bench/bench_trainer_profile.py RUN [--steps 200] [--device cuda] [--rows 25]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path

import torch

from spikenerf.config import TrainConfig
from spikenerf.train import train


def _checkpoint(out: Path) -> dict:
    return torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)


def continue_run(out: Path, cfg: TrainConfig, until: int) -> None:
    """Train the copy in ``out`` on to iteration ``until``."""
    train(dataclasses.replace(cfg, iters=until), out, progress=False, log=lambda m: None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a finished spikenerf run folder (config.json + checkpoint.pt)")
    ap.add_argument("--steps", type=int, default=200, help="iterations to add: half timed, half profiled")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--rows", type=int, default=25, help="operators in the table")
    args = ap.parse_args()
    saved = json.loads((args.run / "config.json").read_text())
    keys = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = TrainConfig(**{k: v for k, v in saved.items() if k in keys})
    cfg = dataclasses.replace(cfg, device=args.device, checkpoint_every_s=1e9, checkpoint_every=10 ** 9)
    done = int(_checkpoint(args.run)["iteration"])
    half = max(args.steps // 2, 1)
    print(f"{args.run} ({cfg.method}, {saved['width']} x {saved['height']}, trained {done} iterations); device "
          f"{args.device}" + (f" ({torch.cuda.get_device_name()})" if args.device == "cuda" else "") +
          f"; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; torch threads {torch.get_num_threads()}")
    with tempfile.TemporaryDirectory(prefix="bench_profile_") as tmp:
        out = Path(tmp) / "run"
        out.mkdir()
        shutil.copy2(args.run / "checkpoint.pt", out / "checkpoint.pt")
        # a few steps first: the CUDA context, kernels and allocator warm up outside what is timed
        continue_run(out, cfg, done + 5)
        # the training loop's own clock (train_seconds), before and after: loading the data and saving are not in it
        before = float(_checkpoint(out)["train_seconds"])
        continue_run(out, cfg, done + 5 + half)
        loop = float(_checkpoint(out)["train_seconds"]) - before
        print(f"{half} steps at the final grid: {1000 * loop / half:.1f} ms per step ({loop:.2f} s in the training "
              f"loop; loading the data and the checkpoint are not counted)")
        acts = [torch.profiler.ProfilerActivity.CPU]
        if args.device == "cuda":
            acts.append(torch.profiler.ProfilerActivity.CUDA)
        with torch.profiler.profile(activities=acts) as prof:
            continue_run(out, cfg, done + 5 + 2 * half)
    key = "self_cuda_time_total" if args.device == "cuda" else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=args.rows))


if __name__ == "__main__":
    main()
