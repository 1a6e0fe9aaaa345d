"""Held-out PSNR of a forward-facing dataset's field in the world cube (as before NDC) vs in NDC.

    python bench/bench_ndc.py DATASET --work DIR [--iters 1000] [--resolution 200] [--seed 0] [--reuse-runs]

DATASET: a folder the trainer can train in NDC (a scene that fills the frame, views all facing one way,
near/far bounds: e.g. one written by ``spikegen import``). Trains the default method on the CPU
twice, same seed, iterations and resolution, and evaluates both with ``spikenerf eval``:

- ``DIR/run_cube``: the field in the world cube [-1.5, 1.5]^3 (``--space cube``);
- ``DIR/run_ndc``: the field in NDC (``--space ndc``, spikenerf/ndc.py; what the default ``auto`` gives
  such a dataset), each ray ending in an opaque sample at its point at infinity.

Prints each run's held-out PSNR and SSIM (against what ``eval`` compares with: the ground truth,
or each view's long-window reconstruction), per-view PSNR, the final grid's dimensions and the
training seconds, and the best constant image's PSNR. ``--reuse-runs``: keep a run folder whose
checkpoint already has ITERS iterations and its metrics instead of training it again (e.g. a cube
run made by an earlier version: the cube path is unchanged).
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from spikegen.spikeio import linear_to_srgb
from spikenerf.config import TrainConfig
from spikenerf.data import load_dataset
from spikenerf.eval import evaluate, reference
from spikenerf.metrics import psnr
from spikenerf.train import load_checkpoint, train


def run_one(name: str, args) -> dict:
    run = Path(args.work) / f"run_{name}"
    ck = run / "checkpoint.pt"
    if not (args.reuse_runs and (run / "metrics.json").is_file() and ck.is_file()
            and load_checkpoint(ck, "cpu")["iteration"] == args.iters):
        shutil.rmtree(run, ignore_errors=True)
        cfg = TrainConfig(dataset=str(Path(args.dataset).resolve()), iters=args.iters, resolution=args.resolution,
                          device="cpu", seed=args.seed, space="cube" if name == "cube" else "ndc")
        train(cfg, run, progress=False, log=lambda *a: None)
        evaluate(run, device="cpu", progress=False)
    out = json.loads((run / "metrics.json").read_text())
    state = load_checkpoint(ck, "cpu")
    out["dims"] = list(state["state"]["grid"].shape[2:])  # (older checkpoints' field configs lack "dims")
    out["space"] = "ndc" if state.get("space") else "world cube"
    return out


def constant_psnr(dataset: str, height: int, width: int) -> float:
    ds = load_dataset(dataset)
    refs = [linear_to_srgb(reference(ds, v, height, width)[1]) for v in ds.splits["test"]]
    c = float(np.mean(refs))
    return float(np.mean([psnr(np.full_like(r, c), r) for r in refs]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--work", required=True)
    ap.add_argument("--iters", type=int, default=1000)
    ap.add_argument("--resolution", type=int, default=200, help="Training width.")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reuse-runs", action="store_true")
    args = ap.parse_args()
    rows = {name: run_one(name, args) for name in ("cube", "ndc")}
    m = rows["ndc"]
    print(f"{args.dataset}: {m['method']}, {m['iterations']} iterations, {m['resolution'][1]} x {m['resolution'][0]}, "
          f"seed {args.seed}, held-out: {m['views_from']} ({m['views']} views), compared with: {m['compared_with']}")
    for name, r in rows.items():
        print(f"  {name:5} ({r['space']}, grid {' x '.join(map(str, r['dims']))}): PSNR {r['psnr']:6.2f} dB  "
              f"SSIM {r['ssim']:.3f}  {r['train_seconds']:.0f} s of training")
        print("        " + "  ".join(f"{v['view']} {v['psnr']:.2f}" for v in r["per_view"]))
    print(f"  ndc - cube: {rows['ndc']['psnr'] - rows['cube']['psnr']:+.2f} dB; best constant image "
          f"{constant_psnr(args.dataset, *m['resolution']):.2f} dB")


if __name__ == "__main__":
    main()
