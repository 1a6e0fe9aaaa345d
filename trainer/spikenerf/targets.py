"""Training targets of a method, as flat NumPy arrays (no torch here).

``Targets``: ``poses [N, 4, 4]`` (one per training image), ``values [N, P]`` (P = H*W pixels
at the training resolution), ``frames [N]`` (window length in frames; 0 for image targets),
``resp`` / ``dark`` ``[P]`` (sensor maps at that resolution). Every target is made from the
first ``w`` frames of each stream (``spikenerf train --frames w``; all of them by default).
Count targets of a moving camera are split into time windows, each seen from its own pose
(:func:`count_windows`: ``--windows N``, or by default as few as keep the image's motion within
a window at most ``MAX_WINDOW_BLUR_PX``). On an integrate-and-fire sensor with subtractive reset a
method that reads spike times (``spikelik``) takes each window's count from its first and last spikes
where they pin it down more closely than the count does (:func:`interval_statistic`).
"""
from __future__ import annotations

import math
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
    values: np.ndarray  # [N, P] float32: counts (statistic), linear radiance, or (paper) gamma-encoded rates
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
    threshold_jitter: float = 0.0  # the dataset sensor's relative SD of the firing level (0 = none)
    statistic: str = "count"  # count targets: "count" (the window's count) or "interval" (interval_statistic)


# --windows 0 (auto): the fewest count windows in which the image moves by at most this many pixels
# (at the training resolution). More windows cost photons per ray (each window's count holds only its
# share of the stream's spikes); fewer leave each count blurred by its window's motion. On the
# procedural lego at 400 x 400 (2.25 px of motion a view) one window scored more than three at
# intensities 16, 32 and 64, and more than two at 16 and 32 (a tie at 64; docs/trainer.md "One window at
# 400 x 400"), so a window's blur up to 2.5 px is allowed; more motion than was measured there is split,
# as before, into windows of at most that.
MAX_WINDOW_BLUR_PX = 2.5


def image_motion_px(ds: Dataset, view, height: int, width: int, frames: int) -> float:
    """How far the image of ``view`` moves during its first ``frames`` frames, in pixels at
    ``height x width``: the largest extent of the path of any of 5 x 5 scene points, seen through the
    central half of the image (where an object centred at the world origin lies, as in NeRF-synthetic)
    at the depth of the world origin, projected through the stream's poses at 9 evenly spaced times
    (:func:`interpolate_pose`). 0 for a static view; infinity when the world origin is not in front
    of the camera (the depth is then unknown)."""
    if view.is_static():
        return 0.0
    cam = ds.camera(height, width)
    fx, fy, cx, cy = (cam, cam, 0.5 * width, 0.5 * height) if isinstance(cam, float) else cam[:4]
    rot, origin = view.pose[:3, :3], view.pose[:3, 3]
    depth = float((rot.T @ origin)[2])  # the world origin at camera z = -depth (cameras look down -z)
    if not depth > 0:
        return math.inf
    u, v = np.meshgrid(cx + width * np.linspace(-0.25, 0.25, 5), cy + height * np.linspace(-0.25, 0.25, 5))
    cam_pts = np.stack([(u - cx) / fx, -(v - cy) / fy, -np.ones_like(u)], axis=-1).reshape(-1, 3) * depth
    pts = cam_pts @ rot.T + origin  # world
    paths = []
    for t in np.linspace(0.0, frames, 9):
        pose = interpolate_pose(view.subframe_poses, t, ds.frames)
        c = (pts - pose[:3, 3]) @ pose[:3, :3]
        z = np.maximum(-c[:, 2], 1e-9)
        paths.append(np.stack([fx * c[:, 0] / z, -fy * c[:, 1] / z], axis=-1))
    span = np.ptp(np.stack(paths), axis=0)  # [points, 2]
    return float(np.hypot(span[:, 0], span[:, 1]).max())


def count_windows(ds: Dataset, method: Method, height: int, width: int, frames: int, windows: int = 0) -> int:
    """Count windows per view for ``method`` on the first ``frames`` frames: ``windows`` if given (> 0),
    else (auto) 1 for a method without windows, and for one with windows (``spikelik``: at most
    ``method.windows``) the fewest in which no train view's image moves by more than
    ``MAX_WINDOW_BLUR_PX`` (:func:`image_motion_px`; 1 when every view is static). Only count targets
    have windows: 1 for every other method, and 1 when every train view is static (a static view
    always has one window: its windows would share one pose). Never more windows than frames."""
    if method.target != "counts" or all(v.is_static() for v in ds.splits["train"]):
        return 1
    if windows > 0:
        return min(int(windows), frames)
    if method.windows <= 1:
        return 1
    motion = max(image_motion_px(ds, v, height, width, frames) for v in ds.splits["train"])
    need = method.windows if math.isinf(motion) else max(1, math.ceil(motion / MAX_WINDOW_BLUR_PX - 1e-9))
    return int(min(need, method.windows, frames))


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


def interval_statistic(spikes: np.ndarray, electrons: float = 0.0, jitter: float = 0.0) -> np.ndarray:
    """The count of a window of spikes ``[n, H, W]`` from an integrate-and-fire pixel with subtractive
    reset, read from its spike times: ``[H, W]`` float64, where it fired twice or more the count its
    first and last spikes imply, elsewhere the count itself.

    A pixel of constant rate ``lam`` (charge ``A`` in ``[0, 1)`` when the window starts) fires its
    ``k``-th spike in the first frame ``t`` with ``A + t lam >= k``. Its first (frame ``t1``, from 1)
    and last (``tK``) of ``K >= 2`` spikes bound ``lam`` to ``((K - 1) / (tK - t1 + 1), (K - 1) / (tK -
    t1 - 1))``; the count alone bounds it to ``((K - 1) / n, (K + 1) / n)``. The value is ``n`` times
    the midpoint of both bounds together. Its variance is ``n^2`` times a uniform spread over them
    (``width^2 / 12``) plus what the sensor's noise moves the two end spikes by, over ``(tK - t1)^2``:
    the threshold jitter (``2 jitter^2``) and the shot noise of the ``K - 1`` thresholds of charge
    between them (``(K - 1) / N_e``). Where that is not below the count's own variance (``1/6 +
    2 jitter^2 + K / N_e``) the count is kept. The count's residual spreads ``lam`` over ``1 / n``, the
    spike times over about ``lam / n``: at I = 32 the value's error is about a fifth of the count's
    (tests/test_trainer_interval.py).
    """
    n = spikes.shape[0]
    fired = spikes.astype(bool)
    count = fired.sum(axis=0, dtype=np.int32).astype(np.float64)
    first = fired.argmax(axis=0)  # the first spike's frame from 0 (0 too without a spike: not read there)
    last = n - 1 - fired[::-1].argmax(axis=0)
    span = np.maximum(last - first, 1).astype(np.float64)  # (only where K >= 2 is it read, and there it is >= 1)
    lo = np.maximum((count - 1) / (span + 1), (count - 1) / n)
    hi = np.minimum(np.where(span > 1, (count - 1) / np.maximum(span - 1, 1.0), np.inf), (count + 1) / n)
    hi = np.maximum(hi, lo)
    shot = (count - 1) / electrons if electrons > 0 else 0.0
    var_interval = n ** 2 * ((hi - lo) ** 2 / 12.0 + (2.0 * jitter ** 2 + shot) / span ** 2)
    var_count = 1.0 / 6.0 + 2.0 * jitter ** 2 + (count / electrons if electrons > 0 else 0.0)  # neuron.count_variance
    return np.where((count >= 2) & (var_interval < var_count), n * 0.5 * (lo + hi), count)


def count_statistic(method: Method, sensor) -> str:
    """What a count method reads from each window: ``"interval"`` (:func:`interval_statistic`) for a method
    that reads spike times, on a sensor whose spike times follow its rate (integrate-and-fire with
    subtractive reset: the ``if`` kind); else ``"count"``. The ``rsir`` generator's charge is a fresh
    random number each frame, and a reset to zero discards the residual that the bounds rely on."""
    if method.target != "counts" or method.statistic != "interval":
        return "count"
    return "interval" if sensor.kind == "if" and sensor.reset == "subtract" else "count"


def view_images(ds: Dataset, view, method: Method, height: int, width: int, frames: int | None = None,
                windows: int = 1, sensor=None):
    """[(pose [4,4], value [H,W], frames)] of one view for ``method``, from its first ``frames`` frames;
    count targets in ``windows`` windows (:func:`count_windows`; a static view has one), each window's
    statistic the one :func:`count_statistic` gives for the dataset's ``sensor`` (a :class:`SensorMaps`;
    None: the counts)."""
    w = frames or ds.frames
    if method.target == "truth":
        if not has_ground_truth(view):
            raise InputError(f"{ds.root}: train view {view.name} has no ground-truth image; --method oracle needs one")
        return [(_pose(view, 0, ds.frames, ds.frames), ground_truth(view, height, width)[0], 0.0)]
    spikes = read_view_spikes(ds, view)[:w]
    if method.target == "counts":
        out = []
        statistic = "count" if sensor is None else count_statistic(method, sensor)
        for a, b in window_bounds(w, 1 if view.is_static() else windows):
            if statistic == "interval":
                counts = interval_statistic(spikes[a:b], sensor.electrons, sensor.threshold_jitter).astype(np.float32)
            else:
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
                  frames: int | None = None, maps_file: str | None = None, windows: int = 0) -> Targets:
    """Read every training view once and build the method's targets at ``height x width`` from the
    first ``frames`` frames of each stream (None: all). ``maps_file``: R and dark current from this
    sensor file (a calibration) instead of the dataset's own. ``windows``: count windows per view
    (0 = :func:`count_windows`' choice)."""
    windows = count_windows(ds, method, height, width, frames or ds.frames, windows)
    sensor = load_sensor_maps(ds, maps_file)
    statistic = count_statistic(method, sensor)
    poses, values, lengths = [], [], []
    for view in tqdm(ds.splits["train"], desc="reading spikes", unit="view", disable=not progress, leave=False):
        for pose, value, n in view_images(ds, view, method, height, width, frames, windows, sensor):
            poses.append(pose)
            values.append(value.reshape(-1))
            lengths.append(n)
    resp, dark = sensor.resp, sensor.dark
    if not method.use_resp:
        resp = np.ones_like(resp)
    kind = {"counts": "counts", "tfp-gamma": "paper"}.get(method.target, "radiance")
    return Targets(np.asarray(poses, np.float32), np.asarray(values, np.float32), np.asarray(lengths, np.float32),
                   _resize(resp, height, width).reshape(-1).astype(np.float32),
                   _resize(dark, height, width).reshape(-1).astype(np.float32), height, width, kind, sensor.kind,
                   sensor.electrons, sensor.reset, bit_camera()[0]["lux_to_rate"] if kind == "paper" else 0.0,
                   threshold_jitter=sensor.threshold_jitter, statistic=statistic)
