"""``spikenerf eval``: render the held-out views of a run, compare with ground truth.

Comparison space (the same for every method): sRGB-encoded luminance composited on white,
in [0, 1] -- the display image a person sees, as the paper compares. Ground truth: the
view's ``r_N.png`` -> linear luminance on white (sensor-model.md) -> sRGB encoding. The
model's output is linear luminance on white -> the same encoding.

An imported capture (frames of ``"image_kind": "reconstruction"``) has no ground truth unless it
was imported with ``--truth-images`` (then each frame's ``ground_truth_path`` is one, read as above;
the view is rendered at its imported pose, as structure from motion placed it). An import's units
are its own (its ``intensity`` puts X = 1 near the brightest part of the scene, the true exposure
being unknown), so before that comparison the prediction is multiplied by one gain per dataset
(:func:`truth_gain`: least squares in linear luminance of the *training* views' ground truths on
their long-window reconstructions; the held-out views play no part), written to ``metrics.json``
as ``"truth_gain"``. Without one, each
held-out view is compared with its own long-window reconstruction instead, the spike rate over
its whole stream with the dataset's fixed pattern removed (``rate / R - d``, as the imported PNG),
in linear luminance (the PNG itself is scaled to its 99.5th percentile, so not in the field's
units) -> the same encoding; a scene that fills the frame is rendered without the white
composite (its run's background), and a forward-facing one in its run's NDC space (ndc.py).
``metrics.json`` says which: ``"compared_with"``. ``compare_with`` (``spikenerf eval --compare-with``)
asks for one: ``"truth"`` (an error for a view without), ``"reconstruction"`` (any spike dataset), or
``"auto"``, the ground truth where a view has one.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from spikegen import spikeio
from spikegen.errors import InputError
from spikegen.formats import IMAGE_KIND_RECONSTRUCTION

from .config import COMPARE_WITH
from .data import area_resize, ground_truth, has_ground_truth, load_dataset, load_sensor_maps, read_view_spikes
from .metrics import Lpips, Tone, psnr, ssim
from .render import render_image
from .train import (CHECKPOINT, checkpoint_camera, checkpoint_space, field_from_checkpoint, load_checkpoint,
                    resolve_device)

GROUND_TRUTH, RECONSTRUCTION = "ground truth", "reconstruction"  # metrics.json "compared_with"


def _mean(vals):
    vals = [v for v in vals if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def evaluate(run: Path, split: str = "test", device: str = "auto", progress: bool = True,
             max_views: int | None = None, compare_with: str = "auto") -> dict:
    """Write ``run/metrics.json`` and ``run/eval_<split>/`` images; returns the metrics."""
    run = Path(run)
    if compare_with not in COMPARE_WITH:
        raise InputError(f"compare with {compare_with!r}: expected one of {', '.join(COMPARE_WITH)}")
    ck_path = run / CHECKPOINT
    if not ck_path.is_file():
        raise InputError(f"{run}: no {CHECKPOINT} (not a training run, or training has not saved yet)")
    dev = resolve_device(device)
    ck = load_checkpoint(ck_path, dev)
    cfg = ck["config"]
    ds = load_dataset(cfg["dataset"])
    if split not in ds.splits:
        raise InputError(f"{ds.root}: no {split!r} split (has {', '.join(ds.splits)})")
    views = ds.splits[split][:max_views] if max_views else ds.splits[split]
    if compare_with == "truth":
        lacking = [v.name for v in views if not has_ground_truth(v)]
        if lacking:
            raise InputError(f"{ds.root}: view {lacking[0]} has no ground-truth image (compare with truth needs one; "
                             "a capture's is given by spikegen import --truth-images)")
    field = field_from_checkpoint(ck, dev).eval()
    H, W, focal, background = checkpoint_camera(ck)
    space = checkpoint_space(ck)  # NDC for a forward-facing capture (its rays are mapped as in training)
    lp = Lpips()
    out_dir = run / f"eval_{split}"
    rows, kinds, tone = [], set(), Tone()
    gain = (truth_gain(ds, H, W) if compare_with != "reconstruction" and any(map(_imported_truth, views))
            else None)
    for i, view in enumerate(tqdm(views, desc=f"eval {split}", disable=not progress, unit="view")):
        pose = torch.as_tensor(view.pose, dtype=torch.float32, device=dev)
        x, _ = render_image(field, pose, H, W, focal, background=background, space=space)
        kind, gt_x, alpha = reference(ds, view, H, W, compare_with)
        if gain is not None and kind == GROUND_TRUTH and _imported_truth(view):
            x = x * gain
        linear = x.clamp(0, 1).cpu().numpy()
        if kind == GROUND_TRUTH:
            tone.add(linear, gt_x, alpha)
        pred = spikeio.linear_to_srgb(linear)
        kinds.add(kind)
        gt = spikeio.linear_to_srgb(gt_x)
        rows.append({"view": view.name, **_view_metrics(pred, gt, alpha, lp)})
        _write_images(out_dir, view.name.replace("/", "_"), pred, gt)
    metrics = _summary(split, rows, lp, ck)
    metrics["views_from"] = ds.heldout if split == "test" else split  # "val" when the folder has no test split
    metrics["compared_with"] = " and ".join(sorted(kinds))  # one of the two unless a folder mixes them
    if GROUND_TRUTH in kinds:
        metrics["tone"] = tone.summary()
        metrics["tone_from"] = ("per bin of the ground truth's linear luminance, over the object (alpha > 0.5) of the "
                                "views compared with their ground truth: pixels, mean truth and prediction, bias = "
                                "prediction - truth (linear); flat_*: the pixels whose neighbourhood lies in the same "
                                "bin and in the object (metrics.Tone)")
    if gain is not None:
        metrics["truth_gain"] = gain
        metrics["truth_gain_from"] = ("an imported capture's units to its ground truth's: least squares in linear "
                                      "luminance over the training views (their ground truth on their long-window "
                                      "reconstructions); the prediction is multiplied by it")
    if background != 1.0:
        metrics["compared_as"] = "sRGB-encoded luminance, [0, 1] (no background: the scene fills the frame)"
    spikeio.write_json_atomic(run / "metrics.json", metrics)
    return metrics


def _imported_truth(view) -> bool:
    """An imported view (its PNG a reconstruction) that also names a ground truth."""
    return view.truth_png is not None and view.extra.get("image_kind") == IMAGE_KIND_RECONSTRUCTION


def truth_gain(ds, height: int, width: int) -> float:
    """The gain ``g`` that takes an imported capture's units to its ground truth's: the least-squares
    fit ``truth ~ g * reconstruction`` in linear luminance over every pixel of the training views
    that have a ground truth (the field learns in the reconstruction's units: ``rate / R - d``
    scaled by the dataset's ``intensity``). Raises ``InputError`` when no training view has one."""
    num = den = 0.0
    for view in ds.splits["train"]:
        if _imported_truth(view):
            t = reference(ds, view, height, width, "truth")[1].astype(np.float64)
            r = reference(ds, view, height, width, "reconstruction")[1].astype(np.float64)
            num, den = num + float((t * r).sum()), den + float((r * r).sum())
    if den <= 0:
        raise InputError(f"{ds.root}: no training view with a ground truth and a non-black reconstruction "
                         "to relate the capture's units to its ground truth's")
    return num / den


def reference(ds, view, height: int, width: int, compare_with: str = "auto") -> tuple[str, np.ndarray, np.ndarray]:
    """(what it is, linear luminance [H, W], alpha [H, W]) a rendered view is compared with: the
    view's ground truth, or without one (or with ``compare_with="reconstruction"``) its long-window
    reconstruction (alpha 1: all scene)."""
    if compare_with != "reconstruction" and has_ground_truth(view):
        return (GROUND_TRUTH, *ground_truth(view, height, width))
    spikes = read_view_spikes(ds, view)
    rate = spikes.mean(axis=0, dtype=np.float64)
    maps = load_sensor_maps(ds)
    x = np.maximum(rate / maps.resp - maps.dark, 0.0) * (256.0 / ds.intensity)
    if x.shape != (height, width):
        x = area_resize(x, height, width)
    return RECONSTRUCTION, x.astype(np.float32), np.ones((height, width), np.float32)


# Regions scored: the object (pixels the object covers at all, and those it covers at least half
# of) and the background alone (alpha 0: white in the ground truth). The background matters:
# a field that is hazy there loses PSNR on the full image that the object region does not show.
REGIONS = {"object": lambda a: a > 0, "object50": lambda a: a > 0.5, "background": lambda a: a == 0}


def _view_metrics(pred, gt, alpha, lp) -> dict:
    out = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "lpips": lp(pred, gt) if lp.available else None}
    for name, region in REGIONS.items():
        mask = region(alpha)
        out[f"psnr_{name}"] = psnr(pred, gt, mask) if mask.any() else None
        out[f"ssim_{name}"] = ssim(pred, gt, mask) if mask.any() else None
    out["lpips_object"] = lp(pred, gt, alpha > 0) if lp.available else None
    return out


def _summary(split, rows, lp, ck) -> dict:
    keys = [k for k in rows[0] if k != "view"] if rows else []
    out = {"split": split, "views": len(rows)}
    out.update({k: _mean([r[k] for r in rows]) for k in keys})
    out["regions"] = {"object": "alpha > 0", "object50": "alpha > 0.5", "background": "alpha == 0"}
    out["per_view"] = rows
    out["train_seconds"] = round(float(ck["train_seconds"]), 2)
    out["iterations"] = int(ck["iteration"])
    out["method"] = ck["config"]["method"]
    out["resolution"] = [int(ck["height"]), int(ck["width"])]
    out["compared_as"] = "sRGB-encoded luminance composited on white, [0, 1]"
    if not lp.available:
        out["lpips_note"] = "null: " + lp.reason
    return out


def _write_images(out_dir: Path, name: str, pred: np.ndarray, gt: np.ndarray) -> None:
    spikeio.write_png(out_dir / f"{name}.png", pred)
    gap = np.ones((pred.shape[0], 4))
    spikeio.write_png(out_dir / f"{name}_gt_vs_pred.png", np.concatenate([gt, gap, pred], axis=1))
