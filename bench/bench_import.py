"""Pose accuracy of ``spikegen import`` on a capture whose true poses are known.

    python bench/bench_import.py CAPTURE --size WxH --truth TRUTH.json --work DIR
        [--recon tfi --recon tfp] [--frames N] [--calibration PREFIX] [--plot PNG] [--view PNG]

CAPTURE: a folder of spike files named ``r_<i>.dat`` (a dataset's ``train/`` folder, e.g. one
made by ``spikegen render --rig handheld``); TRUTH: the ``render.json`` of that render or a
NeRF-synthetic ``transforms_train.json`` (view i is its i-th train entry). The import never reads
TRUTH. For each ``--recon`` the capture is imported into ``DIR/<recon>`` and the recovered poses
are compared with the true ones after the similarity (Umeyama) that best maps the recovered camera
centres onto the true ones. Prints per method: views registered, median and 90th-percentile
rotation error (degrees) and camera-centre error (% of the rig's extent: the largest distance
between two true camera centres), the median rotation error after aligning the orientations
alone (``rot*``), the focal length found, and the import's wall time. ``--plot``: the recovered (aligned)
camera centres against the true ones, seen from above and from the side, for the first method;
``--view``: a copy of that method's image (PNG) of the first registered view.
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from spikegen.importer import import_capture, pose_errors, umeyama
from spikegen.spikeio import parse_size

TARGETS = {"registered": 0.90, "rotation_deg": 0.5, "centre_pct": 1.0}


def true_poses(path: Path) -> np.ndarray:
    """Camera-to-world ``[n, 4, 4]`` of the train views of a render.json or transforms_train.json."""
    doc = json.loads(path.read_text())
    frames = doc["splits"]["train"] if "splits" in doc else doc["frames"]
    return np.array([f["transform_matrix"] for f in frames], dtype=np.float64)


def measure(args, recon: str) -> dict:
    out = Path(args.work) / recon
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    import_capture(args.capture, parse_size(args.size), out, args.calibration, args.frames, recon, progress=False)
    wall_s = time.perf_counter() - t0
    doc = json.loads((out / "transforms_train.json").read_text())
    index = [int(Path(f["source_file"]).stem.split("_")[-1]) for f in doc["frames"]]
    truth = true_poses(Path(args.truth))[index]
    est = np.array([f["transform_matrix"] for f in doc["frames"]])
    err = pose_errors(est, truth)
    return {"recon": recon, "registered": len(index), "views": len(index) + len(doc["unregistered"]),
            "rot_med": float(np.median(err["rotation_deg"])), "rot_p90": float(np.percentile(err["rotation_deg"], 90)),
            "rot_orient_med": float(np.median(err["rotation_own_deg"])),
            "ctr_med": 100 * float(np.median(err["centre_frac"])),
            "ctr_p90": 100 * float(np.percentile(err["centre_frac"], 90)), "wall_s": wall_s, "fl_x": doc["fl_x"],
            "est": est, "truth": truth, "out": out, "first": doc["frames"][0]["file_path"]}


def report(rows: list[dict]) -> None:
    print(f"{'recon':6} {'registered':>12} {'rot med':>9} {'rot p90':>9} {'ctr med %':>10} {'ctr p90 %':>10} "
          f"{'rot*':>6} {'fl_x px':>8} {'wall s':>7}  targets (>= 90 %, <= 0.5 deg, <= 1 %)")
    for r in rows:
        frac = r["registered"] / r["views"]
        met = (frac >= TARGETS["registered"], r["rot_med"] <= TARGETS["rotation_deg"],
               r["ctr_med"] <= TARGETS["centre_pct"])
        print(f"{r['recon']:6} {r['registered']:>5}/{r['views']:<3} {100 * frac:3.0f}% {r['rot_med']:9.3f} "
              f"{r['rot_p90']:9.3f} {r['ctr_med']:10.3f} {r['ctr_p90']:10.3f} {r['rot_orient_med']:6.3f} "
              f"{r['fl_x']:8.1f} {r['wall_s']:7.1f}  "
              f"{' '.join('met' if m else 'MISSED' for m in met)}")


def plot_path(row: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s, rot, t = umeyama(row["est"][:, :3, 3], row["truth"][:, :3, 3])
    est = row["est"][:, :3, 3] @ (s * rot).T + t
    tru = row["truth"][:, :3, 3]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, (i, j, name) in zip(axes, ((0, 1, "from above (x, y)"), (0, 2, "from the side (x, z)"))):
        ax.plot(tru[:, i], tru[:, j], "o-", color="0.6", ms=5, lw=0.8, label="true (render.json)")
        ax.plot(est[:, i], est[:, j], "x", color="C3", ms=6, label=f"recovered ({row['recon']}), aligned")
        ax.set_title(name)
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{row['registered']}/{row['views']} views registered; median centre error "
                 f"{row['ctr_med']:.2f} % of the rig's extent, rotation {row['rot_med']:.2f} deg")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("capture")
    ap.add_argument("--size", required=True)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--work", required=True, help="Folder for the imported datasets (one per --recon).")
    ap.add_argument("--recon", action="append", choices=["tfi", "tfp"])
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--calibration", default=None)
    ap.add_argument("--plot", default=None)
    ap.add_argument("--view", default=None)
    args = ap.parse_args()
    rows = [measure(args, recon) for recon in args.recon or ["tfi", "tfp"]]
    report(rows)
    print("rot / ctr: after the similarity fitted to the camera centres (Umeyama); rot*: after the rotation "
          "fitted to the orientations")
    if args.plot:
        plot_path(rows[0], args.plot)
    if args.view:
        shutil.copyfile(rows[0]["out"] / (rows[0]["first"] + ".png"), args.view)


if __name__ == "__main__":
    main()
