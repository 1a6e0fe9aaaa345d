"""The NeRF-synthetic camera rig and the camera motion during a view's exposure, pure NumPy.

Conventions (as NeRF-synthetic and Blender): a pose is a camera-to-world ``float64 [4, 4]``
matrix; the camera looks down its local ``-Z`` with ``+Y`` up; world ``+Z`` is up. Cameras sit
on a sphere of radius :data:`RADIUS` and look at the origin.

- train and val: directions uniform over the upper hemisphere (seeded per split);
- test: evenly spaced around a circle at 30 degrees elevation.

Motion during exposure (the paper's "dynamic recording"): over the ``T`` frames of a view the
camera orbits the world ``Z`` axis through ``motion_deg`` degrees, centred on the view's pose,
still looking at the origin. Sub-frame ``k`` of ``K`` is at the centre of its slice of the
exposure, time ``(k + 0.5) / K``, as the sensor model assumes (:func:`spikegen.sensor.frame_segments`),
so its azimuth offset is ``motion_deg * ((k + 0.5) / K - 0.5)``. The mid-exposure pose (time
1/2) is the view's ``transform_matrix``; ``motion_deg = 0`` is a static camera.

A second rig, ``handheld`` (:func:`make_handheld_rig`, described above it), is a forward-facing
capture held by hand, as the paper's real captures (docs/real_captures.md).
"""
from __future__ import annotations

import math

import numpy as np

from .formats import CAMERA_ANGLE_X, DEFAULT_MOTION_DEG, SPLITS, ViewRecord, focal_px
from .seeding import _word

RADIUS = 4.0311  # NeRF-synthetic camera distance
NEAR, FAR = 2.0, 6.0
TEST_ELEVATION_DEG = 30.0
DEFAULT_VIEWS = {"train": 100, "val": 100, "test": 200}
__all__ = ["CAMERA_ANGLE_X", "DEFAULT_MOTION_DEG", "SPLITS", "focal_px", "make_rig", "make_views", "crop_window",
           "project", "look_at", "subframe_poses", "make_handheld_rig"]


def look_at(position: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world ``[4, 4]`` of a camera at ``position [3]`` looking at ``target``."""
    position = np.asarray(position, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - position
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down: pick any right vector
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, cam_up, -forward, position
    return pose


def hemisphere_directions(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` unit vectors ``[count, 3]`` uniform over the upper hemisphere (z >= 0)."""
    v = rng.standard_normal((count, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    return v


def circle_directions(count: int, elevation_deg: float = TEST_ELEVATION_DEG) -> np.ndarray:
    """``count`` unit vectors ``[count, 3]`` evenly spaced in azimuth at ``elevation_deg``."""
    az = 2.0 * np.pi * np.arange(count) / max(count, 1)
    el = math.radians(elevation_deg)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(count, math.sin(el))], axis=1)


def rotation_z(angle_rad: float) -> np.ndarray:
    """World rotation ``[4, 4]`` about +Z by ``angle_rad``."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    r = np.eye(4)
    r[:2, :2] = [[c, -s], [s, c]]
    return r


def subframe_times(subframes: int) -> np.ndarray:
    """Exposure time ``[K]`` (0..1) of each sub-frame: the centre of its slice."""
    return (np.arange(subframes) + 0.5) / subframes


def subframe_poses(pose: np.ndarray, subframes: int, motion_deg: float = DEFAULT_MOTION_DEG) -> np.ndarray:
    """Poses ``[K, 4, 4]`` of the K sub-frames: ``pose`` orbited about world Z, centred on it."""
    offsets = np.radians(motion_deg) * (subframe_times(subframes) - 0.5)
    return np.stack([rotation_z(a) @ pose for a in offsets])


def split_directions(split: str, count: int, seed: int = 0) -> np.ndarray:
    """Camera directions ``[count, 3]`` of one split (train/val random, test on the circle)."""
    if split == "test":
        return circle_directions(count)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, _word("rig:" + split)]))
    return hemisphere_directions(count, rng)


def make_views(split: str, count: int, subframes: int = 16, motion_deg: float = DEFAULT_MOTION_DEG,
               seed: int = 0, radius: float = RADIUS) -> list[ViewRecord]:
    """The ``count`` views of ``split``: deterministic in (split, count, seed)."""
    views = []
    for i, d in enumerate(split_directions(split, count, seed)):
        pose = look_at(radius * d)
        views.append(ViewRecord(split, i, pose, subframe_poses(pose, subframes, motion_deg)))
    return views


def make_rig(counts: dict | None = None, subframes: int = 16, motion_deg: float = DEFAULT_MOTION_DEG,
             seed: int = 0) -> dict[str, list[ViewRecord]]:
    """All splits: ``{"train": [ViewRecord], "val": [...], "test": [...]}`` with ``counts`` views each."""
    counts = dict(DEFAULT_VIEWS if counts is None else counts)
    return {s: make_views(s, int(counts.get(s, 0)), subframes, motion_deg, seed) for s in SPLITS}


def crop_window(points: np.ndarray, pose: np.ndarray, width: int, height: int,
                camera_angle_x: float = CAMERA_ANGLE_X, margin: int = 0) -> tuple[int, int, int, int] | None:
    """The pixel box ``(x0, x1, y0, y1)`` (x right, y down, ends exclusive) holding the image of
    ``points [N, 3]`` seen from ``pose``, grown by ``margin`` pixels and clipped to the frame;
    ``None`` when it is the whole frame or a point is not in front of the camera.

    A triangle's image lies inside the box of its corners' images (a perspective projection keeps
    straight edges straight for points in front of the camera), so the box of all vertices holds
    every pixel a mesh can touch; ``margin`` covers the pixel filter's reach."""
    xy = project(np.asarray(points, dtype=np.float64), pose, width, height, camera_angle_x)
    if len(xy) == 0 or not np.isfinite(xy).all():
        return None
    x0 = max(0, math.floor(xy[:, 0].min()) - margin)
    y0 = max(0, math.floor(xy[:, 1].min()) - margin)
    x1 = min(width, math.ceil(xy[:, 0].max()) + 1 + margin)
    y1 = min(height, math.ceil(xy[:, 1].max()) + 1 + margin)
    if x0 >= x1 or y0 >= y1:  # entirely outside the frame: one pixel, still rendered
        x0, x1, y0, y1 = 0, 1, 0, 1
    if (x0, x1, y0, y1) == (0, width, 0, height):
        return None
    return x0, x1, y0, y1


def project(points: np.ndarray, pose: np.ndarray, width: int, height: int,
            camera_angle_x: float = CAMERA_ANGLE_X) -> np.ndarray:
    """Pixel coordinates ``[N, 2]`` (x right, y down) of world ``points [N, 3]``; NaN behind the camera."""
    w2c = np.linalg.inv(pose)
    pc = (np.c_[points, np.ones(len(points))] @ w2c.T)[:, :3]
    f = focal_px(width, camera_angle_x)
    z = -pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = 0.5 * width + f * pc[:, 0] / z
        y = 0.5 * height - f * pc[:, 1] / z
    out = np.stack([x, y], axis=1)
    out[z <= 0] = np.nan
    return out


# ---------------------------------------------------------------------- handheld forward-facing rig
# A person holding a spike camera in front of the scene (the paper's real captures, LLFF-like):
# views on a 2D patch of HANDHELD_PATCH (width, height, world units) centred at distance RADIUS
# from the origin in the direction (HANDHELD_AZIMUTH_DEG, HANDHELD_ELEVATION_DEG), the patch
# spanning the centre camera's right and up axes; a jittered grid of `count` cells in row-major
# order (each position uniform within +-HANDHELD_JITTER of its cell's size around the cell centre);
# each camera looks at the origin, then turns by a random rotation (rotation vector, each component
# normal with HANDHELD_TILT_DEG standard deviation, in camera axes): an unsteady hand. During the
# exposure the hand drifts in a straight line in the patch plane, in a direction uniform in angle,
# over RADIUS * radians(motion_deg) (so the origin's image moves by about motion_deg); orientation
# is held. Sub-frame k sits at exposure time (k + 0.5) / K as for the NeRF rig.
HANDHELD_AZIMUTH_DEG, HANDHELD_ELEVATION_DEG = 45.0, 25.0
HANDHELD_PATCH = (0.8, 0.5)
HANDHELD_JITTER = 0.35
HANDHELD_TILT_DEG = 1.0
HANDHELD_VIEWS = {"train": 35, "val": 0, "test": 0}
HANDHELD_SIZE = (400, 250)  # width, height: the spike camera's frame


def rotation_from_vector(rotvec: np.ndarray) -> np.ndarray:
    """Rotation ``[3, 3]`` of angle ``|rotvec|`` (radians) about ``rotvec [3]`` (Rodrigues)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-15:
        return np.eye(3)
    k = np.asarray(rotvec, dtype=np.float64) / angle
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross


def handheld_positions(count: int, rng: np.random.Generator) -> np.ndarray:
    """Patch coordinates ``[count, 2]`` (right, up; world units) of a jittered grid, row-major."""
    cols = max(1, math.ceil(math.sqrt(count * HANDHELD_PATCH[0] / HANDHELD_PATCH[1])))
    rows = max(1, math.ceil(count / cols))
    cell = np.array([HANDHELD_PATCH[0] / cols, HANDHELD_PATCH[1] / rows])
    ij = np.stack([np.arange(count) % cols, np.arange(count) // cols], axis=1)
    jitter = rng.uniform(-HANDHELD_JITTER, HANDHELD_JITTER, (count, 2))
    centre = (ij + 0.5 + jitter) * cell - 0.5 * np.array(HANDHELD_PATCH)
    return centre * [1.0, -1.0]  # first row at the top


def make_handheld_views(split: str, count: int, subframes: int = 16, motion_deg: float = DEFAULT_MOTION_DEG,
                        seed: int = 0) -> list[ViewRecord]:
    """The ``count`` handheld views of ``split``: deterministic in (split, count, seed)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, _word("handheld:" + split)]))
    az, el = math.radians(HANDHELD_AZIMUTH_DEG), math.radians(HANDHELD_ELEVATION_DEG)
    centre = look_at(RADIUS * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]))
    right, up = centre[:3, 0], centre[:3, 1]
    patch = handheld_positions(count, rng)
    tilts = rng.standard_normal((count, 3)) * math.radians(HANDHELD_TILT_DEG)
    drift_angle = rng.uniform(0.0, 2.0 * math.pi, count)
    drift = RADIUS * math.radians(motion_deg)
    views = []
    for i in range(count):
        pose = look_at(centre[:3, 3] + patch[i, 0] * right + patch[i, 1] * up)
        pose[:3, :3] = pose[:3, :3] @ rotation_from_vector(tilts[i])
        step = drift * (math.cos(drift_angle[i]) * right + math.sin(drift_angle[i]) * up)
        subs = np.repeat(pose[None], subframes, axis=0)
        subs[:, :3, 3] += (subframe_times(subframes) - 0.5)[:, None] * step
        views.append(ViewRecord(split, i, pose, subs))
    return views


def make_handheld_rig(counts: dict | None = None, subframes: int = 16, motion_deg: float = DEFAULT_MOTION_DEG,
                      seed: int = 0) -> dict[str, list[ViewRecord]]:
    """All splits of the handheld rig (``counts`` default: 35 train views, no val or test)."""
    counts = dict(HANDHELD_VIEWS if counts is None else counts)
    return {s: make_handheld_views(s, int(counts.get(s, 0)), subframes, motion_deg, seed) for s in SPLITS}
