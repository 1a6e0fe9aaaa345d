"""A capture through a radial lens: what the camera model of the import and the trainer's use of
``k1`` are worth, in pose error and in held-out PSNR.

    spikegen convert RENDER --intensity 64 --sensor calibrated --frames 1000 --lens-k1 0.2 --out DATA
    python bench/bench_lens.py DATA/<scene>_i64/train --size 400x250 --truth RENDER/render.json \
        --work DIR [--train ITERS --resolution W]

CAPTURE is imported twice without its poses (``spikegen import --camera-model simple-pinhole`` and
``simple-radial``, into ``DIR/simple-pinhole`` and ``DIR/simple-radial``) and each import's poses are
scored against TRUTH as bench_import.py does (``spikegen.importer.pose_errors``: medians after the
centre-only and the full-pose similarity); both imports carry the capture's true images
(``--truth-images CAPTURE``: ``spikegen convert`` writes each view's ``r_N.png`` beside its spikes,
warped through the same lens). With ``--train``, the default method is trained (CPU, seed 0,
``--resolution`` wide) on five datasets and scored on their held-out views (every 8th registered
view, each rendered at its dataset's pose; ``spikenerf eval``) twice: against the ground truth, and
against each view's own long-window reconstruction (``bench_import.evaluate_both``):

- **radial, k1 used**: the simple-radial import as written; the trainer undistorts every pixel's ray;
- **radial, k1 dropped**: the same folder with ``k1`` removed from its transforms (same poses, same
  focal length, pinhole rays): what ignoring the lens costs the field;
- **pinhole import**: the simple-pinhole import (SfM's pinhole compromise of poses and focal length);
- **true camera, k1 used**: the simple-radial import with the true camera in place of SfM's
  (``bench_import.true_pose_dataset``: the true poses moved into the import's frame, the true focal
  length and principal point) and the lens the capture was converted through (its ``k1``): what
  the trainer makes of a perfectly known lens;
- **true camera, k1 dropped**: the same without ``k1``.

A rerun imports again (the import is deterministic) and, with ``--reuse-runs``, keeps trained runs
(and evaluates them again).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "generator"), str(REPO / "trainer"), str(REPO / "bench")]

from bench_import import (evaluate_both, scene_depth, summarise, train_default, true_pose_dataset,  # noqa: E402
                          true_poses, truth_images)
from spikegen.cli import _size as parse_size  # noqa: E402
from spikegen.importer import import_capture, pose_errors  # noqa: E402

MODELS = ("simple-pinhole", "simple-radial")


def import_both(args) -> dict:
    rows = {}
    for model in MODELS:
        out = Path(args.work) / model
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        import_capture(args.capture, parse_size(args.size), out, progress=False, camera_model=model,
                       truth_images=truth_images(Path(args.capture)))
        doc = json.loads((out / "transforms_train.json").read_text())
        index = [int(Path(f["source_file"]).stem.split("_")[-1]) for f in doc["frames"]]
        truth = true_poses(Path(args.truth))[index]
        est = np.array([f["transform_matrix"] for f in doc["frames"]])
        rows[model] = {"out": out, "truth": truth, "registered": len(index), "views": len(index) + len(doc["unregistered"]),
                       "fl_x": doc["fl_x"], "k1": doc.get("k1", 0.0), "wall_s": time.perf_counter() - t0,
                       **summarise(pose_errors(est, truth, scene_depth(truth)))}
    return rows


def without_k1(folder: Path, out: Path) -> Path:
    """``out``: ``folder`` with ``k1`` (and its camera_model) removed from the transforms; the spike
    files, sensor and config linked, not copied."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    doc = json.loads((folder / "transforms_train.json").read_text())
    doc.pop("k1", None)
    doc.pop("camera_model", None)
    (out / "transforms_train.json").write_text(json.dumps(doc, indent=1))
    for name in ("train", "sensor.json", "sensor.npz", "config.yaml"):
        if (folder / name).exists():
            os.symlink((folder / name).resolve(), out / name)
    return out


def with_k1(folder: Path, k1: float) -> Path:
    """``folder``'s transforms with the lens ``k1`` (0: none) in place of whatever it had."""
    path = folder / "transforms_train.json"
    doc = json.loads(path.read_text())
    doc.pop("k1", None)
    doc.pop("camera_model", None)
    if k1:
        doc.update(camera_model="OPENCV", k1=k1)
    path.write_text(json.dumps(doc, indent=1))
    return folder


def true_camera(rows: dict, args, k1: float, name: str) -> Path:
    """The simple-radial import with the true poses and pinhole intrinsics (bench_import) and lens ``k1``."""
    row = rows["simple-radial"]
    return with_k1(true_pose_dataset(row["out"], Path(args.truth), row, Path(args.work) / name), k1)


def train_all(rows: dict, args) -> dict:
    radial = rows["simple-radial"]["out"]
    lens_k1 = json.loads((Path(args.capture).parent / "transforms_train.json").read_text()).get("k1", 0.0)
    datasets = {"radial, k1 used": radial,
                "radial, k1 dropped": without_k1(radial, Path(args.work) / "simple-radial_no_k1"),
                "pinhole import": rows["simple-pinhole"]["out"],
                "true camera, k1 used": true_camera(rows, args, lens_k1, "true_camera"),
                "true camera, k1 dropped": true_camera(rows, args, 0.0, "true_camera_no_k1")}
    out = {}
    for name, ds in datasets.items():
        run = train_default(ds, Path(args.work) / ("run_" + name.replace(", ", "_").replace(" ", "_")), args)
        out[name] = evaluate_both(run)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--size", required=True)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--work", required=True)
    ap.add_argument("--train", type=int, default=0, help="Also train ITERS iterations on the five datasets.")
    ap.add_argument("--resolution", type=int, default=200, help="Training width (with --train).")
    ap.add_argument("--reuse-runs", action="store_true")
    args = ap.parse_args()
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    rows = import_both(args)
    print(f"{'camera model':15} {'registered':>11} {'fl_x px':>8} {'k1':>7} {'rot med c':>10} {'ctr med % c':>12} "
          f"{'rot med f':>10} {'ctr med % f':>12} {'import s':>9}   (c: centre-only alignment, f: full pose)")
    for model, r in rows.items():
        print(f"{model:15} {r['registered']:>5}/{r['views']:<5} {r['fl_x']:8.1f} {r['k1']:7.4f} "
              f"{r['ctr']['rot_med']:10.3f} {r['ctr']['ctr_med']:12.3f} {r['full']['rot_med']:10.3f} "
              f"{r['full']['ctr_med']:12.3f} {r['wall_s']:9.1f}")
    if args.train:
        metrics = train_all(rows, args)
        print(f"\ntrained {args.train} iterations at width {args.resolution}, seed 0, CPU; held-out views vs the "
              "ground truth (truth) and vs their own reconstructions (recon)")
        print(f"{'dataset':24} {'PSNR truth':>10} {'object':>7} {'SSIM':>6} {'PSNR recon':>10} {'SSIM':>6} "
              f"{'views':>6} {'train s':>8}")
        for name, m in metrics.items():
            t, r = m.get("truth"), m["reconstruction"]
            truth = f"{t['psnr']:10.2f} {t['psnr_object']:7.2f} {t['ssim']:6.3f}" if t else f"{'-':>10} {'-':>7} {'-':>6}"
            print(f"{name:24} {truth} {r['psnr']:10.2f} {r['ssim']:6.3f} {r['views']:>6} {r['train_seconds']:8.0f}")
        print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
