"""Dataset folders (shared/specs/dataset.md) -> training targets and evaluation views.

Nothing here imports torch: a dataset is read into NumPy arrays once, then the trainer
moves what it needs to its device.

A training *image* is one pose plus one target per pixel:
- counts (spike methods): spikes counted over ``frames`` readout frames of a view, seen
  from the camera pose at the middle of those frames;
- radiance (TFP/TFI baselines): linear luminance reconstructed from the spikes.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spikegen.errors import InputError
from spikegen import spikeio

HOLDOUT_EVERY = 8  # without a test split, train views 0, 8, 16, ... are held out


@dataclass
class View:
    """One view of a split: mid-exposure pose, K sub-frame poses, its files."""

    name: str  # e.g. "train/r_0"
    pose: np.ndarray  # [4, 4] camera-to-world, mid-exposure
    subposes: np.ndarray  # [K, 4, 4]
    png: Path
    spikes: Path | None


@dataclass
class Dataset:
    root: Path
    height: int
    width: int
    frames: int
    subframes: int
    intensity: float
    camera_angle_x: float
    splits: dict = field(default_factory=dict)  # split -> list[View]
    holdout: bool = False  # test views taken from train (every 8th)

    @property
    def focal_px(self) -> float:
        return 0.5 * self.width / math.tan(0.5 * self.camera_angle_x)


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None


def _views(root: Path, meta: dict, source: Path) -> list[View]:
    out = []
    for i, fr in enumerate(meta.get("frames", [])):
        try:
            rel = fr["file_path"]
            pose = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError):
            raise InputError(f"{source}: frame {i} lacks file_path/transform_matrix") from None
        if pose.shape != (4, 4):
            raise InputError(f"{source}: frame {i} transform_matrix is not 4x4")
        sub = np.asarray(fr.get("subframe_transform_matrices") or [pose], dtype=np.float64)
        if sub.ndim != 3 or sub.shape[1:] != (4, 4):
            raise InputError(f"{source}: frame {i} subframe_transform_matrices must be K x 4 x 4")
        png = (root / (rel + ".png")).resolve()
        spk = fr.get("spike_path")
        out.append(View(rel.lstrip("./"), pose, sub, png, (root / spk).resolve() if spk else None))
    return out


def load_dataset(root) -> Dataset:
    """Read ``transforms_*.json`` of a dataset folder; an ``InputError`` if it is not one."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: not a folder (expected a dataset folder with transforms_train.json)")
    train_json = root / "transforms_train.json"
    if not train_json.is_file():
        raise InputError(f"{root}: not a spike dataset (no transforms_train.json; see dataset.md)")
    meta = _read_json(train_json)
    spike = meta.get("spike")
    if not isinstance(spike, dict):
        raise InputError(f"{train_json}: no \"spike\" block: a NeRF-synthetic folder, not a spike dataset "
                         "(make one with `spikegen convert`)")
    try:
        ds = Dataset(root=root, height=int(spike["height"]), width=int(spike["width"]),
                     frames=int(spike["frames"]), subframes=int(spike.get("subframes", 1)),
                     intensity=float(spike["intensity"]), camera_angle_x=float(meta["camera_angle_x"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{train_json}: spike block or camera_angle_x incomplete ({exc})") from None
    if spike.get("format", "dat") != "dat":
        raise InputError(f"{train_json}: spike format {spike.get('format')!r} not supported (expected dat)")
    ds.splits["train"] = _views(root, meta, train_json)
    for split in ("val", "test"):
        p = root / f"transforms_{split}.json"
        if p.is_file():
            ds.splits[split] = _views(root, _read_json(p), p)
    if not ds.splits.get("test"):
        train = ds.splits["train"]
        ds.splits["test"] = [v for i, v in enumerate(train) if i % HOLDOUT_EVERY == 0]
        ds.splits["train"] = [v for i, v in enumerate(train) if i % HOLDOUT_EVERY != 0]
        ds.holdout = True
    if not ds.splits["train"]:
        raise InputError(f"{train_json}: no training views")
    return ds


def load_sensor_maps(ds: Dataset) -> tuple[np.ndarray, np.ndarray, str]:
    """(R [H, W], d [H, W] float32, sensor kind) from the dataset's sensor.json; ideal if absent."""
    path = ds.root / "sensor.json"
    if not path.is_file():
        return (np.ones((ds.height, ds.width), np.float32), np.zeros((ds.height, ds.width), np.float32), "if")
    from spikegen.sensorfile import load_sensor

    sensor = load_sensor(path)
    resp, dark = sensor.maps(ds.height, ds.width)
    return resp.astype(np.float32), dark.astype(np.float32), sensor.kind


def read_view_spikes(ds: Dataset, view: View) -> np.ndarray:
    """``uint8 [T, H, W]`` spikes of a view."""
    if view.spikes is None:
        raise InputError(f"{ds.root}: view {view.name} has no spike_path")
    return spikeio.read_spikes(view.spikes, size=(ds.width, ds.height), frames=ds.frames)


def ground_truth(view: View, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(linear luminance on white [H, W], alpha [H, W]) of a view's PNG, area-resized if needed."""
    x, alpha = spikeio.png_to_radiance(spikeio.read_png(view.png))
    if x.shape != (height, width):
        x, alpha = area_resize(x, height, width), area_resize(alpha, height, width)
    return x.astype(np.float32), alpha.astype(np.float32)


def area_resize(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """Block-average ``[H, W]`` down by an integer factor to ``[height, width]``."""
    H, W = img.shape
    if H % height or W % width or H // height != W // width:
        raise InputError(f"resolution {width}x{height} must divide the dataset's {W}x{H} by one integer factor")
    f = H // height
    return img.reshape(height, f, width, f).mean(axis=(1, 3))


# ---------------------------------------------------------------------- poses in time
def interpolate_pose(subposes: np.ndarray, frame: float, frames: int) -> np.ndarray:
    """Camera-to-world ``[4, 4]`` at (fractional) frame ``frame``; sub-frame k sits at (k+0.5)T/K."""
    K = subposes.shape[0]
    s = float(np.clip(frame / (frames / K) - 0.5, 0, K - 1))
    k0 = int(math.floor(s))
    k1 = min(k0 + 1, K - 1)
    f = s - k0
    m = (1 - f) * subposes[k0] + f * subposes[k1]
    u, _, vt = np.linalg.svd(m[:3, :3])
    out = m.copy()
    out[:3, :3] = u @ vt  # nearest rotation to the blended matrix
    out[3] = (0, 0, 0, 1)
    return out


def is_static(view: View, tol: float = 1e-6) -> bool:
    return bool(np.abs(view.subposes - view.subposes[:1]).max() <= tol)
