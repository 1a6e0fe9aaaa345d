"""Held-out PSNR of a field trained on the forward-facing capture of tests/test_trainer_forward.py.

    python bench/bench_forward.py WORK [--iters 400] [--background black|white]

Builds the capture in ``WORK/capture`` (once), trains the default method on the CPU into
``WORK/run_<background>``, runs ``spikenerf eval`` (against each held-out view's reconstruction)
and renders the held-out views against the scene's analytic radiance. ``--background white``
forces the 360 path's white composite (overriding ``Dataset.background``) to show what the
composite is worth; ``black`` is what the trainer does with such a folder. Also prints the PSNR
of the best constant image (the mean of the held-out references).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from spikegen.spikeio import linear_to_srgb  # noqa: E402
from spikenerf import data  # noqa: E402
from spikenerf.config import TrainConfig  # noqa: E402
from spikenerf.eval import evaluate, reference  # noqa: E402
from spikenerf.metrics import psnr  # noqa: E402
from spikenerf.render import render_image  # noqa: E402
from spikenerf.train import (checkpoint_camera, checkpoint_space, field_from_checkpoint, load_checkpoint,  # noqa: E402
                             train)
from test_trainer_forward import H, W, _radiance, make_capture  # noqa: E402


def constant_psnr(ds) -> float:
    refs = [linear_to_srgb(reference(ds, v, H, W)[1]) for v in ds.splits["test"]]
    c = float(np.mean(refs))
    return float(np.mean([psnr(np.full_like(r, c), r) for r in refs]))


def psnr_vs_truth(run: Path, ds) -> float:
    ck = load_checkpoint(run / "checkpoint.pt", "cpu")
    field = field_from_checkpoint(ck, "cpu").eval()
    height, width, focal, background = checkpoint_camera(ck)
    vals = []
    for v in ds.splits["test"]:
        x, _ = render_image(field, torch.as_tensor(v.pose, dtype=torch.float32), height, width, focal,
                            background=background, space=checkpoint_space(ck))
        truth = linear_to_srgb(np.clip(_radiance(v.pose), 0, 1))
        vals.append(psnr(linear_to_srgb(x.clamp(0, 1).numpy()), truth))
    return float(np.mean(vals))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--iters", type=int, default=400)
    ap.add_argument("--background", choices=("black", "white"), default="black")
    args = ap.parse_args()
    cap = args.work / "capture"
    if not (cap / "transforms_train.json").is_file():
        cap.mkdir(parents=True, exist_ok=True)
        make_capture(cap)
    if args.background == "white":
        data.Dataset.background = property(lambda self: data.WHITE)
    run = args.work / f"run_{args.background}"
    train(TrainConfig(dataset=str(cap), iters=args.iters, device="cpu"), run, progress=False)
    m = evaluate(run, progress=False)
    ds = data.load_dataset(cap)
    print(f"{args.background}: held-out PSNR vs {m['compared_with']} {m['psnr']:.2f} dB, vs the analytic radiance "
          f"{psnr_vs_truth(run, ds):.2f} dB; best constant image {constant_psnr(ds):.2f} dB; "
          f"{m['train_seconds']:.0f} s of training")


if __name__ == "__main__":
    main()
