"""Training targets of a method, as flat NumPy arrays (no torch here).

``Targets``: ``poses [N, 4, 4]`` (one per training image), ``values [N, P]`` (P = H*W pixels
at the training resolution), ``frames [N]`` (window length in frames; 0 for radiance
targets), ``resp`` / ``dark`` ``[P]`` (sensor maps at that resolution).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from spikegen import recon

from .data import Dataset, area_resize, interpolate_pose, load_sensor_maps, read_view_spikes
from .methods import Method


@dataclass
class Targets:
    poses: np.ndarray  # [N, 4, 4] float32
    values: np.ndarray  # [N, P] float32: counts or linear radiance
    frames: np.ndarray  # [N] float32
    resp: np.ndarray  # [P] float32
    dark: np.ndarray  # [P] float32
    height: int
    width: int
    kind: str  # "counts" | "radiance"
    sensor_kind: str = "if"  # the dataset's sensor: "if" or "rsir"
    electrons: float = 0.0  # the dataset sensor's photo-electrons per threshold (0 = no shot noise)
    reset: str = "subtract"  # the dataset sensor's reset: "subtract" or "zero"


def window_bounds(frames: int, windows: int) -> list[tuple[int, int]]:
    """Split ``0..T`` into ``windows`` consecutive runs of (nearly) equal length."""
    edges = np.linspace(0, frames, windows + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _resize(img: np.ndarray, height: int, width: int) -> np.ndarray:
    return img if img.shape == (height, width) else area_resize(img, height, width)


def view_images(ds: Dataset, view, method: Method, height: int, width: int):
    """[(pose [4,4], value [H,W], frames)] of one view for ``method``."""
    spikes = read_view_spikes(ds, view)
    T = ds.frames
    if method.target == "counts":
        n_win = 1 if view.is_static() else method.windows
        out = []
        for a, b in window_bounds(T, n_win):
            pose = view.pose if n_win == 1 else interpolate_pose(view.subframe_poses, 0.5 * (a + b), T)
            counts = spikes[a:b].sum(axis=0, dtype=np.int32).astype(np.float32)
            out.append((pose, _resize(counts, height, width), float(b - a)))
        return out
    rate = recon.tfp(spikes, method.tfp_frames) if method.target == "tfp" else recon.tfi(spikes)
    x = recon.rate_to_radiance(_resize(rate, height, width), ds.intensity)
    return [(view.pose, x, 0.0)]


def build_targets(ds: Dataset, method: Method, height: int, width: int, progress: bool = True) -> Targets:
    """Read every training view once and build the method's targets at ``height x width``."""
    poses, values, frames = [], [], []
    for view in tqdm(ds.splits["train"], desc="reading spikes", unit="view", disable=not progress, leave=False):
        for pose, value, n in view_images(ds, view, method, height, width):
            poses.append(pose)
            values.append(value.reshape(-1))
            frames.append(n)
    sensor = load_sensor_maps(ds)
    resp, dark = sensor.resp, sensor.dark
    if not method.use_resp:
        resp = np.ones_like(resp)
    return Targets(np.asarray(poses, np.float32), np.asarray(values, np.float32), np.asarray(frames, np.float32),
                   _resize(resp, height, width).reshape(-1).astype(np.float32),
                   _resize(dark, height, width).reshape(-1).astype(np.float32), height, width,
                   "counts" if method.target == "counts" else "radiance", sensor.kind, sensor.electrons,
                   sensor.reset)
