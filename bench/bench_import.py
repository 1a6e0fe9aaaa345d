"""Pose accuracy of ``spikegen import`` on a capture whose true poses are known.

    python bench/bench_import.py CAPTURE --size WxH --truth TRUTH.json --work DIR
        [--recon tfi --recon tfp] [--frames N] [--calibration PREFIX] [--camera-model simple-radial]
        [--plot PNG] [--view PNG]
        [--train ITERS [--resolution W] [--heldout PNG] [--perturb DEG] [--reuse-runs]]

CAPTURE: a folder of spike files named ``r_<i>.dat`` (a dataset's ``train/`` folder, e.g. one
made by ``spikegen render --rig handheld``); TRUTH: the ``render.json`` of that render or a
NeRF-synthetic ``transforms_train.json`` (view i is its i-th train entry). The import never reads
TRUTH. For each ``--recon`` the capture is imported into ``DIR/<recon>`` (``DIR/<recon>_simple-radial``
with ``--camera-model simple-radial``) and the recovered poses
are compared with the true ones after two similarity alignments (``spikegen.importer.pose_errors``),
both printed:

- **centres**: the similarity (Umeyama) that best maps the recovered camera centres onto the true ones;
- **full pose**: the similarity fitted to the whole poses (``full_pose_similarity``): centres and
  orientations, an orientation error theta weighed as the centre error ``depth * theta``, ``depth``
  the median distance of the true cameras from the world origin, where both truth formats put the
  scene (the handheld rig and NeRF-synthetic cameras look at it).

Prints per method and alignment: views registered, median and 90th-percentile rotation error
(degrees) and camera-centre error (% of the rig's extent: the largest distance between two true
camera centres); and the median rotation error after aligning the orientations alone (``rot*``),
the focal length and radial coefficient k1 found (0 for the pinhole model), and the import's wall time. ``--plot``: the recovered camera centres
(after both alignments) against the true ones, seen from above and from the side, for the first
method; ``--view``: a copy of that method's image (PNG) of the first registered view.

``--train ITERS``: for the first method, also train the default method (``spikenerf train``, CPU,
seed 0, at ``--resolution``) twice, on the imported dataset and on the same dataset with the true
poses (:func:`true_pose_dataset`: ``DIR/<recon>_truth``), and print each field's held-out PSNR
(``spikenerf eval``; the trainer holds out every 8th registered view, the same views in both) and
the difference, and the best constant image's PSNR. Both fields are scored against the same
references twice: each held-out view's own long-window reconstruction, and, where the capture
folder holds each spike file's true image beside it (``r_N.png``, as ``spikegen render`` and
``convert`` write it), that ground truth (imported with ``--truth-images``; ``spikenerf eval
--compare-with``). Each field renders the held-out views at the poses of its own dataset (SfM's,
or the truth's moved into the import's frame).
``--heldout PNG``: the second held-out view, ground truth (else reconstruction) | imported poses | true poses.
``--perturb DEG``: a third run, on the true poses each turned by DEG degrees about a random axis
(seed 0; centres kept): what a known pose error costs, to show the comparison can see one.
``--reuse-runs``: keep a run folder whose checkpoint already has ITERS iterations and its metrics
(the import is deterministic, so a rerun writes the same datasets) instead of training it again.
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from spikegen.formats import png_name
from spikegen.importer import import_capture, pose_errors
from spikegen.spikeio import parse_size

TARGETS = {"registered": 0.90, "rotation_deg": 0.5, "centre_pct": 1.0}


def true_poses(path: Path) -> np.ndarray:
    """Camera-to-world ``[n, 4, 4]`` of the train views of a render.json or transforms_train.json."""
    doc = json.loads(path.read_text())
    frames = doc["splits"]["train"] if "splits" in doc else doc["frames"]
    return np.array([f["transform_matrix"] for f in frames], dtype=np.float64)


def measure(args, recon: str) -> dict:
    out = Path(args.work) / (recon if args.camera_model == "simple-pinhole" else f"{recon}_{args.camera_model}")
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    import_capture(args.capture, parse_size(args.size), out, args.calibration, args.frames, recon, progress=False,
                   camera_model=args.camera_model, truth_images=truth_images(Path(args.capture)))
    wall_s = time.perf_counter() - t0
    doc = json.loads((out / "transforms_train.json").read_text())
    index = [int(Path(f["source_file"]).stem.split("_")[-1]) for f in doc["frames"]]
    truth = true_poses(Path(args.truth))[index]
    est = np.array([f["transform_matrix"] for f in doc["frames"]])
    row = {"recon": recon, "registered": len(index), "views": len(index) + len(doc["unregistered"]),
           "wall_s": wall_s, "fl_x": doc["fl_x"], "k1": doc.get("k1", 0.0), "est": est, "truth": truth, "out": out,
           "first": doc["frames"][0]["file_path"]}
    row.update(summarise(pose_errors(est, truth, scene_depth(truth))))
    return row


def truth_images(capture: Path) -> Path | None:
    """``capture`` when every spike file in it has its true image beside it (``<stem>.png``), else None."""
    spikes = [p for p in capture.iterdir() if p.suffix in (".dat", ".npz")]
    return capture if spikes and all(p.with_suffix(".png").is_file() for p in spikes) else None


def evaluate_both(run: Path) -> dict:
    """The run's held-out metrics against each view's reconstruction and, where the dataset has
    one, its ground truth: ``{"reconstruction": ..., "truth": ...}`` (``run/metrics.json`` and
    ``run/eval_test/`` are the last one's)."""
    from spikenerf.eval import evaluate

    out = {"reconstruction": evaluate(run, device="cpu", progress=False, compare_with="reconstruction")}
    auto = evaluate(run, device="cpu", progress=False)
    if auto["compared_with"] == "ground truth":
        out["truth"] = auto
    return out


def scene_depth(truth: np.ndarray) -> float:
    """The median distance of the true cameras from the world origin (the scene's centre in a
    render.json or NeRF-synthetic frame): the depth at which the full-pose fit weighs orientations."""
    return float(np.median(np.linalg.norm(truth[:, :3, 3], axis=1)))


def summarise(err: dict) -> dict:
    """Medians and 90th percentiles of ``pose_errors``'s per-view errors (centres in % of the extent)."""
    out = {"rot_orient_med": float(np.median(err["rotation_own_deg"])), "err": err}
    for key, name in (("", "ctr"), ("_full", "full")):
        rot, ctr = err[f"rotation{key}_deg"], 100 * err[f"centre{key}_frac"]
        out[name] = {"rot_med": float(np.median(rot)), "rot_p90": float(np.percentile(rot, 90)),
                     "ctr_med": float(np.median(ctr)), "ctr_p90": float(np.percentile(ctr, 90))}
    return out


def true_pose_dataset(imported: Path, truth_json: Path, row: dict, out: Path) -> Path:
    """``out``: the imported dataset with the true poses and intrinsics in place of SfM's.

    The true poses are moved into the imported dataset's normalised frame by the inverse of the
    full-pose similarity (``row["err"]["similarity_full"]``, imported -> true): ``c = R^T (c_true -
    t) / s``, ``R = R^T R_true``, so both fields see the scene at the same place in the trainer's box.
    The intrinsics are the truth's (``fl = w / (2 tan(camera_angle_x / 2))``, principal point at the
    image centre); every other key (views, order, spike block, near/far, sensor) is the import's,
    and ``train/`` is a link to the import's own (the same spike files)."""
    s, rot, t = row["err"]["similarity_full"]
    doc = json.loads((imported / "transforms_train.json").read_text())
    truth_doc = json.loads(truth_json.read_text())
    fl = 0.5 * doc["w"] / np.tan(0.5 * truth_doc["camera_angle_x"])
    to_import = np.eye(4)
    to_import[:3, :3], to_import[:3, 3] = rot.T / s, -rot.T @ t / s  # p_import = to_import p_true
    for frame, true_c2w in zip(doc["frames"], row["truth"]):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rot.T @ true_c2w[:3, :3], to_import[:3, :3] @ true_c2w[:3, 3] + to_import[:3, 3]
        frame["transform_matrix"] = pose.tolist()
        frame["subframe_transform_matrices"] = [pose.tolist()]
    doc.update({"camera_angle_x": float(truth_doc["camera_angle_x"]), "fl_x": fl, "fl_y": fl,
                "cx": doc["w"] / 2.0, "cy": doc["h"] / 2.0, "poses_from": "truth",
                "normalising_transform": to_import.tolist()})
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    (out / "train").symlink_to((imported / "train").resolve(), target_is_directory=True)
    for name in ("sensor.json", "sensor.npz", "config.yaml"):
        if (imported / name).is_file():
            shutil.copyfile(imported / name, out / name)
    (out / "transforms_train.json").write_text(json.dumps(doc, indent=1))
    return out


def perturbed_dataset(true_ds: Path, degrees: float, out: Path, seed: int = 0) -> Path:
    """``out``: the true-pose dataset with each view's orientation turned by ``degrees`` about a
    random axis (uniform on the sphere, camera axes; drawn from ``seed``), its centre kept."""
    doc = json.loads((true_ds / "transforms_train.json").read_text())
    rng = np.random.default_rng(seed)
    for frame in doc["frames"]:
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        theta = np.radians(degrees)
        turn = np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k
        pose = np.array(frame["transform_matrix"])
        pose[:3, :3] = pose[:3, :3] @ turn
        frame["transform_matrix"], frame["subframe_transform_matrices"] = pose.tolist(), [pose.tolist()]
    doc["poses_from"] = f"truth, each turned by {degrees} degrees"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    for item in (true_ds / "train", *(true_ds / n for n in ("sensor.json", "sensor.npz", "config.yaml"))):
        if item.is_symlink():
            (out / item.name).symlink_to(item.resolve(), target_is_directory=True)
        elif item.is_file():
            shutil.copyfile(item, out / item.name)
    (out / "transforms_train.json").write_text(json.dumps(doc, indent=1))
    return out


def train_default(dataset: Path, run: Path, args) -> Path:
    """Train the default method on ``dataset`` into ``run`` (``args.train`` iterations at
    ``args.resolution``, CPU, seed 0); with ``args.reuse_runs`` a run whose checkpoint already holds
    that many iterations is kept instead."""
    from spikenerf.config import TrainConfig
    from spikenerf.train import load_checkpoint, train

    done = (args.reuse_runs and (run / "checkpoint.pt").is_file()
            and load_checkpoint(run / "checkpoint.pt", "cpu")["iteration"] == args.train)
    if not done:
        shutil.rmtree(run, ignore_errors=True)
        train(TrainConfig(dataset=str(dataset), iters=args.train, resolution=args.resolution, device="cpu", seed=0),
              run, progress=False, log=lambda *a: None)
    return run


def train_both(row: dict, args) -> dict:
    """Train the default method on the imported dataset and on its true-pose twin (and with
    ``--perturb`` on the true poses turned); held-out metrics (:func:`evaluate_both`)."""
    truth = true_pose_dataset(row["out"], Path(args.truth), row, Path(f"{row['out']}_truth"))
    datasets = {"imported": row["out"], "true poses": truth}
    if args.perturb:
        datasets[f"turned {args.perturb:g} deg"] = perturbed_dataset(truth, args.perturb,
                                                                     Path(f"{row['out']}_turned"))
    out = {}
    for name, ds in datasets.items():
        run = train_default(ds, Path(args.work) / f"run_{row['recon']}_{name.replace(' ', '_')}", args)
        out[name] = evaluate_both(run)
        out[name]["run"] = run
    return out


def constant_psnr(dataset: Path, width: int) -> float:
    """Mean held-out PSNR of the best constant image (the mean of the held-out references) at the
    training size: what a field must beat to have learnt anything."""
    from spikegen.spikeio import linear_to_srgb
    from spikenerf.data import load_dataset
    from spikenerf.eval import reference
    from spikenerf.metrics import psnr

    ds = load_dataset(dataset)
    height = ds.height * width // ds.width
    refs = [linear_to_srgb(reference(ds, v, height, width)[1]) for v in ds.splits["test"]]
    c = float(np.mean(refs))
    return float(np.mean([psnr(np.full_like(r, c), r) for r in refs]))


def heldout_picture(metrics: dict, path: str) -> None:
    """The second held-out view side by side: its ground truth (else its reconstruction) | rendered
    from the field trained on imported poses | from the field trained on true poses (eval's
    ``<view>_gt_vs_pred.png`` of the last evaluation)."""
    from spikegen.spikeio import read_png, write_png

    view = metrics["imported"]["reconstruction"]["per_view"][1]["view"].replace("/", "_")
    pairs = [read_png(metrics[k]["run"] / "eval_test" / f"{view}_gt_vs_pred.png")[..., 0]
             for k in ("imported", "true poses")]
    width = (pairs[0].shape[1] - 4) // 2  # reference | 4-pixel gap | prediction
    gap = np.ones((pairs[0].shape[0], 4))
    write_png(path, np.concatenate([pairs[0][:, :width], gap, pairs[0][:, -width:], gap, pairs[1][:, -width:]], axis=1))


def report_training(row: dict, metrics: dict) -> None:
    first = metrics["imported"]["reconstruction"]
    print(f"training ({row['recon']}, {first['method']}, {first['iterations']} iterations, "
          f"{first['resolution'][1]} x {first['resolution'][0]}, held-out: {first['views_from']}, "
          f"{first['views']} views)")
    for ref in ("reconstruction", "truth"):
        if ref not in metrics["imported"]:
            print("  no ground truth: the capture folder has no true image beside each spike file")
            continue
        imp, tru = metrics["imported"][ref], metrics["true poses"][ref]
        print(f" compared with: {imp['compared_with']}")
        for name, both in metrics.items():
            m = both[ref]
            obj = f"  object {m['psnr_object']:6.2f}" if ref == "truth" else ""
            print(f"  {name:15} PSNR {m['psnr']:6.2f} dB{obj}  SSIM {m['ssim']:.3f}  "
                  f"({m['train_seconds']:.0f} s of training)")
        gap = tru["psnr"] - imp["psnr"]
        print(f"  true poses - imported: {gap:+.2f} dB  target (within 2 dB): {'met' if abs(gap) <= 2.0 else 'MISSED'}")
        for i, a in enumerate(imp["per_view"]):
            print(f"    {a['view']:12} "
                  + "  ".join(f"{name} {both[ref]['per_view'][i]['psnr']:6.2f}" for name, both in metrics.items()))
    print(f"  best constant image PSNR {constant_psnr(row['out'], first['resolution'][1]):6.2f} dB "
          "(against the ground truth where there is one)")


def report(rows: list[dict]) -> None:
    print(f"{'recon':6} {'align':9} {'registered':>12} {'rot med':>9} {'rot p90':>9} {'ctr med %':>10} "
          f"{'ctr p90 %':>10} {'rot*':>6} {'fl_x px':>8} {'k1':>7} {'wall s':>7}  targets (>= 90 %, <= 0.5 deg, <= 1 %)")
    for r in rows:
        frac = r["registered"] / r["views"]
        for name, label in (("ctr", "centres"), ("full", "full pose")):
            a = r[name]
            met = (frac >= TARGETS["registered"], a["rot_med"] <= TARGETS["rotation_deg"],
                   a["ctr_med"] <= TARGETS["centre_pct"])
            print(f"{r['recon']:6} {label:9} {r['registered']:>5}/{r['views']:<3} {100 * frac:3.0f}% "
                  f"{a['rot_med']:9.3f} {a['rot_p90']:9.3f} {a['ctr_med']:10.3f} {a['ctr_p90']:10.3f} "
                  f"{r['rot_orient_med']:6.3f} {r['fl_x']:8.1f} {r['k1']:7.4f} {r['wall_s']:7.1f}  "
                  f"{' '.join('met' if m else 'MISSED' for m in met)}")


def plot_path(row: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tru = row["truth"][:, :3, 3]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.4))
    for ax, (i, j, name) in zip(axes, ((0, 1, "from above (x, y)"), (0, 2, "from the side (x, z)"))):
        ax.plot(tru[:, i], tru[:, j], "o-", color="0.6", ms=5, lw=0.8, label="true (render.json)")
        for key, label, mark, colour in (("similarity", "centres", "x", "C3"),
                                         ("similarity_full", "full pose", "+", "C0")):
            s, rot, t = row["err"][key]
            est = row["est"][:, :3, 3] @ (s * rot).T + t
            ax.plot(est[:, i], est[:, j], mark, color=colour, ms=6,
                    label=f"recovered ({row['recon']}), {label} alignment")
        ax.set_title(name)
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].legend(fontsize=8)
    c, f = row["ctr"], row["full"]
    fig.suptitle(f"{row['registered']}/{row['views']} views registered; median rotation / centre error: "
                 f"{c['rot_med']:.2f} deg / {c['ctr_med']:.2f} % (centres), "
                 f"{f['rot_med']:.2f} deg / {f['ctr_med']:.2f} % (full pose)", fontsize=10)
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
    ap.add_argument("--camera-model", default="simple-pinhole", choices=["simple-pinhole", "simple-radial"],
                    help="spikegen import --camera-model (the k1 column: the radial coefficient SfM found)")
    ap.add_argument("--plot", default=None)
    ap.add_argument("--view", default=None)
    ap.add_argument("--train", type=int, default=0, help="Also train ITERS iterations from imported and true poses.")
    ap.add_argument("--resolution", type=int, default=200, help="Training width (with --train).")
    ap.add_argument("--heldout", default=None, help="With --train: a held-out view, reconstruction | imported | true.")
    ap.add_argument("--perturb", type=float, default=0.0, help="With --train: also train on the true poses turned.")
    ap.add_argument("--reuse-runs", action="store_true", help="With --train: keep finished runs.")
    args = ap.parse_args()
    rows = [measure(args, recon) for recon in args.recon or ["tfi", "tfp"]]
    report(rows)
    print("centres: after the similarity fitted to the camera centres (Umeyama); full pose: after the similarity "
          f"fitted to centres and orientations (orientations weighed at depth {rows[0]['err']['depth']:.3f}); "
          "rot*: after the rotation fitted to the orientations alone")
    if args.plot:
        plot_path(rows[0], args.plot)
    if args.view:
        shutil.copyfile(rows[0]["out"] / png_name(rows[0]["first"]), args.view)
    if args.train:
        metrics = train_both(rows[0], args)
        report_training(rows[0], metrics)
        if args.heldout:
            heldout_picture(metrics, args.heldout)


if __name__ == "__main__":
    main()
