"""Dataset folders (shared/specs/dataset.md) -> training targets and evaluation views.

Nothing here imports torch: a dataset is read into NumPy arrays once, then the trainer
moves what it needs to its device.

A training *image* is one pose plus one target per pixel:
- counts (spike methods): spikes counted over ``frames`` readout frames of a view, seen
  from the camera pose at the middle of those frames;
- radiance (TFP/TFI baselines): linear luminance reconstructed from the spikes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spikegen import spikeio
from spikegen.errors import InputError
from spikegen.formats import IMAGE_KIND_RECONSTRUCTION, Intrinsics, SpikeBlock, Transforms, ViewRecord, focal_px

HOLDOUT_EVERY = 8  # without a test or val split, train views 0, 8, 16, ... are held out
WHITE, BLACK = 1.0, 0.0  # backgrounds: the NeRF-synthetic white composite; none (a scene filling the frame)


@dataclass
class Dataset:
    """A spike dataset folder as the trainer sees it: the train split's spike block, and the
    views of each split (:class:`spikegen.formats.ViewRecord`, ``root`` = the folder)."""

    root: Path
    spike: SpikeBlock
    camera_angle_x: float
    splits: dict = field(default_factory=dict)  # split -> list[ViewRecord]
    holdout: bool = False  # test views taken from train (every 8th): the folder has neither test nor val
    heldout: str = "test"  # where the evaluation views come from: "test", "val" or "train every 8th"
    intrinsics: Intrinsics | None = None  # an imported capture's fl_x, fl_y, cx, cy (None: camera_angle_x only)

    height = property(lambda self: self.spike.height)
    width = property(lambda self: self.spike.width)
    frames = property(lambda self: self.spike.frames)
    subframes = property(lambda self: self.spike.subframes)
    intensity = property(lambda self: self.spike.intensity)

    @property
    def focal_px(self) -> float:
        return focal_px(self.width, self.camera_angle_x)

    @property
    def fills_frame(self) -> bool:
        """A capture whose scene fills the frame: no background in the spike block, and intrinsics of
        its own (folders written before the block had "background" lack both: they are over white)."""
        return self.spike.background is None and self.intrinsics is not None

    @property
    def background(self) -> float:
        """What rays that pass through the field composite onto: white, or black for a scene that fills
        the frame (the field itself then holds everything seen, out to the box it spans)."""
        return BLACK if self.fills_frame else WHITE

    def camera(self, height: int, width: int):
        """The camera at ``height x width``: the square-pixel centred focal length (a float, as before)
        without intrinsics, else ``(fl_x, fl_y, cx, cy)`` scaled to that size, and ``k1`` last when the
        lens is radial (render.pixel_rays; ``k1`` acts on normalised coordinates, so no scaling)."""
        if self.intrinsics is None:
            return self.focal_px * width / self.width
        k = self.intrinsics
        sx, sy = width / k.w, height / k.h
        return (k.fl_x * sx, k.fl_y * sy, k.cx * sx, k.cy * sy) + ((k.k1,) if k.k1 else ())


def has_ground_truth(view: ViewRecord) -> bool:
    """A view has a rendering of the scene: its PNG (not an image reconstructed from its own spikes),
    or an imported view's ``ground_truth_path``."""
    return view.truth_png is not None or view.extra.get("image_kind") != IMAGE_KIND_RECONSTRUCTION


def load_dataset(root) -> Dataset:
    """Read and check ``transforms_*.json`` of a dataset folder (poses finite and rigid, sizes and
    field of view positive, spike files of the size the spike block says); an ``InputError`` naming
    the file and the frame if it is not a sound spike dataset."""
    root = Path(root)
    train_json = root / "transforms_train.json"
    if not train_json.is_file():
        why = ("not a spike dataset (no transforms_train.json; see dataset.md)" if root.is_dir()
               else "not a folder (expected a dataset folder with transforms_train.json)")
        raise InputError(f"{root}: {why}")
    train = Transforms.read(train_json, "train")
    ds = Dataset(root, train.spike, train.camera_angle_x, {"train": list(train.frames)},
                 intrinsics=train.intrinsics)
    for split in ("val", "test"):
        p = root / f"transforms_{split}.json"
        if p.is_file():
            doc = Transforms.read(p, split)
            if (doc.spike.width, doc.spike.height, doc.spike.frames) != (ds.width, ds.height, ds.frames):
                raise InputError(f"{p}: spike block says {doc.spike.frames} frames of {doc.spike.width}x"
                                 f"{doc.spike.height}, the train split {ds.frames} of {ds.width}x{ds.height}")
            ds.splits[split] = list(doc.frames)
    if not ds.splits.get("test"):
        _hold_out(ds)
    if not ds.splits["train"]:
        raise InputError(f"{train_json}: no training views")
    return ds


@dataclass(frozen=True)
class SensorMaps:
    """What the trainer's differentiable sensor needs from the dataset's ``sensor.json``."""

    resp: np.ndarray  # R [H, W] float32
    dark: np.ndarray  # d [H, W] float32, spikes per frame
    kind: str = "if"  # "if" or "rsir"
    electrons: float = 0.0  # photo-electrons per threshold (0 = no shot noise)
    reset: str = "subtract"  # "subtract" or "zero"
    threshold_jitter: float = 0.0  # relative SD of the firing level (0 = none)


def _hold_out(ds: Dataset) -> None:
    """Evaluation views for a folder without a test split: its val split (views never trained
    on, as NeRF papers report), else every 8th train view (taken out of training)."""
    if ds.splits.get("val"):
        ds.splits["test"], ds.heldout = ds.splits["val"], "val"
        return
    views = ds.splits["train"]
    ds.splits["test"] = [v for i, v in enumerate(views) if i % HOLDOUT_EVERY == 0]
    ds.splits["train"] = [v for i, v in enumerate(views) if i % HOLDOUT_EVERY != 0]
    ds.holdout, ds.heldout = True, f"train every {HOLDOUT_EVERY}th"


def load_sensor_maps(ds: Dataset, maps_file: str | None = None) -> SensorMaps:
    """The dataset's sensor (``sensor.json``) at the dataset's size; the ideal sensor if it has none.

    ``maps_file``: take R and the dark current from this sensor file instead (e.g. a calibration
    from ``spikegen calibrate``: what a user of a real camera has in place of its true maps); the
    rest of the model (kind, shot noise, reset, threshold jitter) stays the dataset's."""
    from spikegen.sensorfile import load_sensor

    own = ds.root / "sensor.json"
    sensor = load_sensor(own) if own.is_file() else None
    maps = load_sensor(maps_file) if maps_file else sensor
    if maps is None:
        return SensorMaps(np.ones((ds.height, ds.width), np.float32), np.zeros((ds.height, ds.width), np.float32))
    resp, dark = maps.maps(ds.height, ds.width)
    model = sensor or maps
    return SensorMaps(resp.astype(np.float32), dark.astype(np.float32), model.kind, float(model.electrons),
                      model.reset, float(model.threshold_jitter))


def read_view_spikes(ds: Dataset, view: ViewRecord) -> np.ndarray:
    """``uint8 [T, H, W]`` spikes of a view."""
    if view.spikes is None:
        raise InputError(f"{ds.root}: view {view.name} has no spike_path")
    return spikeio.read_spikes(view.spikes, size=(ds.width, ds.height), frames=ds.frames)


def ground_truth(view: ViewRecord, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(linear luminance on white [H, W], alpha [H, W]) of a view's ground-truth PNG (its
    ``ground_truth_path``, else its own PNG), area-resized if needed."""
    x, alpha = spikeio.png_to_radiance(spikeio.read_png(view.truth_png or view.png))
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
