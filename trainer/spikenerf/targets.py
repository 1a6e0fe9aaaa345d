"""Training targets of a method, as flat NumPy arrays (no torch here).

``Targets``: ``poses [N, 4, 4]`` (one per training image), ``values [N, P]`` (P = H*W pixels
at the training resolution), ``frames [N]`` (window length in frames; 0 for image targets),
``resp`` / ``dark`` ``[P]`` (sensor maps at that resolution). Every target is made from the
first ``w`` frames of each stream (``spikenerf train --frames w``; all of them by default).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from spikegen import recon
from spikegen.presets import bit_camera

from spikegen.errors import InputError

from .data import (Dataset, area_resize, ground_truth, has_ground_truth, interpolate_pose, load_sensor_maps,
                   read_view_spikes)
from .methods import Method


@dataclass
class Targets:
    poses: np.ndarray  # [N, 4, 4] float32
    values: np.ndarray  # [N, P] float32: counts, linear radiance, or (paper) gamma-encoded rates
    frames: np.ndarray  # [N] float32
    resp: np.ndarray  # [P] float32
    dark: np.ndarray  # [P] float32
    height: int
    width: int
    kind: str  # "counts" | "radiance" | "paper" ((count / w) ** (1 / 2.2), 8-bit, as the published targets)
    sensor_kind: str = "if"  # the dataset's sensor: "if" or "rsir"
    electrons: float = 0.0  # the dataset sensor's photo-electrons per threshold (0 = no shot noise)
    reset: str = "subtract"  # the dataset sensor's reset: "subtract" or "zero"
    lux_to_rate: float = 0.0  # L of the published fixed-pattern maps (neuron.paper_fpn_maps); "paper" only


def window_bounds(frames: int, windows: int) -> list[tuple[int, int]]:
    """Split ``0..T`` into ``windows`` consecutive runs of (nearly) equal length."""
    edges = np.linspace(0, frames, windows + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _resize(img: np.ndarray, height: int, width: int) -> np.ndarray:
    return img if img.shape == (height, width) else area_resize(img, height, width)


def _pose(view, a: int, b: int, frames: int) -> np.ndarray:
    """Camera pose of frames ``a..b`` of a ``frames``-frame stream: the recorded mid-exposure pose
    for the whole stream (or a static view), else interpolated at the middle of ``a..b``."""
    if (a, b) == (0, frames) or view.is_static():
        return view.pose
    return interpolate_pose(view.subframe_poses, 0.5 * (a + b), frames)


def view_images(ds: Dataset, view, method: Method, height: int, width: int, frames: int | None = None):
    """[(pose [4,4], value [H,W], frames)] of one view for ``method``, from its first ``frames`` frames."""
    w = frames or ds.frames
    if method.target == "truth":
        if not has_ground_truth(view):
            raise InputError(f"{ds.root}: train view {view.name} has no ground-truth image; --method oracle needs one")
        return [(_pose(view, 0, ds.frames, ds.frames), ground_truth(view, height, width)[0], 0.0)]
    spikes = read_view_spikes(ds, view)[:w]
    if method.target == "counts":
        out = []
        for a, b in window_bounds(w, 1 if view.is_static() else method.windows):
            counts = spikes[a:b].sum(axis=0, dtype=np.int32).astype(np.float32)
            out.append((_pose(view, a, b, ds.frames), _resize(counts, height, width), float(b - a)))
        return out
    pose = _pose(view, 0, w, ds.frames)
    if method.target == "tfp-gamma":
        return [(pose, paper_target(spikes, height, width), float(w))]
    rate = recon.tfp(spikes, method.tfp_frames) if method.target == "tfp" else recon.tfi(spikes)
    x = recon.rate_to_radiance(_resize(rate, height, width), ds.intensity)
    return [(pose, x, 0.0)]


def paper_target(spikes: np.ndarray, height: int, width: int) -> np.ndarray:
    """The published targets' form: ``(count / w) ** (1 / 2.2)`` of the ``w`` frames ``[w, H, W]``,
    stored in 8 bits (their data are PNG images), ``[height, width]`` float32 in [0, 1]."""
    rate = spikes.sum(axis=0, dtype=np.int32).astype(np.float64) / spikes.shape[0]
    encoded = _resize(rate, height, width) ** (1.0 / 2.2)
    return (np.round(encoded * 255.0) / 255.0).astype(np.float32)


def build_targets(ds: Dataset, method: Method, height: int, width: int, progress: bool = True,
                  frames: int | None = None, maps_file: str | None = None) -> Targets:
    """Read every training view once and build the method's targets at ``height x width`` from the
    first ``frames`` frames of each stream (None: all). ``maps_file``: R and dark current from this
    sensor file (a calibration) instead of the dataset's own."""
    poses, values, lengths = [], [], []
    for view in tqdm(ds.splits["train"], desc="reading spikes", unit="view", disable=not progress, leave=False):
        for pose, value, n in view_images(ds, view, method, height, width, frames):
            poses.append(pose)
            values.append(value.reshape(-1))
            lengths.append(n)
    sensor = load_sensor_maps(ds, maps_file)
    resp, dark = sensor.resp, sensor.dark
    if not method.use_resp:
        resp = np.ones_like(resp)
    kind = {"counts": "counts", "tfp-gamma": "paper"}.get(method.target, "radiance")
    return Targets(np.asarray(poses, np.float32), np.asarray(values, np.float32), np.asarray(lengths, np.float32),
                   _resize(resp, height, width).reshape(-1).astype(np.float32),
                   _resize(dark, height, width).reshape(-1).astype(np.float32), height, width, kind, sensor.kind,
                   sensor.electrons, sensor.reset, bit_camera()[0]["lux_to_rate"] if kind == "paper" else 0.0)
