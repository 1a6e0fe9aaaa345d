"""``spikenerf render``: novel views of a trained field along a camera path, as an animation.

Every frame is three panels side by side, 4 white pixels apart, each at the run's own
resolution and focal length (from its checkpoint):

- luminance: linear luminance composited on white, sRGB-encoded (as ``eval`` writes it);
- depth: the expected distance along each ray where it ends (light that passes through counts
  at ``FAR``), normalised by the NeRF-synthetic scene bounds ``(d - NEAR) / (FAR - NEAR)``
  (2 and 6, dataset.md) and colour-mapped from yellow (near) through green and blue to dark
  purple (far); the colours are the viridis map's, read at five points;
- opacity: the ray's accumulated alpha, black (0) to white (1).

Camera paths (world +Z up, every camera looking at the origin; frame ``k`` of ``N`` is at
``s = k / N``, so the last frame leads back into the first):

- ``orbit``: azimuth ``360 s`` degrees, elevation 30 degrees, distance ``r`` -- for
  ``r = 4.0311`` the circle of the NeRF-synthetic test views;
- ``spiral``: azimuth ``720 s`` degrees (two turns), elevation ``30 - 20 cos(2 pi s)`` degrees
  (10 up to 50 and back), distance ``r (1 - 0.075 (1 - cos(2 pi s)))`` (``r`` in to ``0.85 r``
  and back).

``r`` is the median distance from the origin of the run's dataset's training cameras (4.0311
for NeRF-synthetic scenes), or :data:`spikegen.camera.RADIUS` where that folder is no longer
readable.

A run whose field lies in NDC (a forward-facing capture, ndc.py) has its own paths, about its
reference camera (as LLFF renderings are), each camera turned as the reference camera, ``r`` the
checkpoint's ``spread`` (the median distance of the training cameras from the reference centre):

- ``orbit``: the circle of radius ``r`` about the reference centre in its image plane (angle
  ``360 s`` degrees from its right axis towards its up axis);
- ``spiral``: that circle twice (``720 s`` degrees), moving forward along the viewing axis by
  ``r (1 - cos(2 pi s)) / 2`` (out to ``r`` and back).

Their depth panel is the NDC z where the ray ends (render.render_image), yellow at -1 (the near
plane) to dark purple at 1 (infinity, where light that passes through counts).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from spikegen.animation import check_animation, write_animation
from spikegen.camera import FAR, NEAR, RADIUS, look_at
from spikegen.errors import InputError, SpikegenError
from spikegen.spikeio import linear_to_srgb

from .data import load_dataset
from .render import render_image
from .train import (CHECKPOINT, checkpoint_camera, checkpoint_space, field_from_checkpoint, load_checkpoint,
                    resolve_device)

PATHS = ("orbit", "spiral")
ORBIT_ELEVATION_DEG = 30.0
GAP_PX = 4  # white columns between panels
# viridis at 0, 1/4, 1/2, 3/4, 1 (sRGB, 0-255): dark purple, blue, teal, green, yellow
_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64)


def path_poses(path: str, frames: int, radius: float) -> np.ndarray:
    """Camera-to-world poses ``float64 [frames, 4, 4]`` of ``path`` (see the module docstring)."""
    if path not in PATHS:
        raise InputError(f"--path {path!r}: expected one of {', '.join(PATHS)}")
    if frames < 1:
        raise InputError(f"--frames {frames}: must be at least 1")
    s = np.arange(frames) / frames
    if path == "orbit":
        az, el, dist = 2 * np.pi * s, np.full(frames, ORBIT_ELEVATION_DEG), np.full(frames, radius)
    else:
        cos = np.cos(2 * np.pi * s)  # 1 -> -1 -> 1 over the path
        az, el, dist = 4 * np.pi * s, ORBIT_ELEVATION_DEG - 20.0 * cos, radius * (1 - 0.075 * (1 - cos))
    el = np.radians(el)
    centres = dist[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    return np.stack([look_at(c) for c in centres])


def ndc_path_poses(path: str, frames: int, space) -> np.ndarray:
    """Camera-to-world poses ``float64 [frames, 4, 4]`` of ``path`` about an NDC run's reference camera."""
    s = np.arange(frames) / frames
    ref, r = np.array(space.pose), space.spread
    turns = 1 if path == "orbit" else 2
    ang = 2 * np.pi * turns * s
    forward = np.zeros(frames) if path == "orbit" else r * (1 - np.cos(2 * np.pi * s)) / 2
    out = np.repeat(ref[None], frames, axis=0)
    out[:, :3, 3] += (r * np.cos(ang))[:, None] * ref[:3, 0] + (r * np.sin(ang))[:, None] * ref[:3, 1] \
        - forward[:, None] * ref[:3, 2]
    return out


def camera_radius(dataset, log=print) -> float:
    """Median distance from the origin of the dataset's training cameras; ``RADIUS`` if unreadable."""
    try:
        views = load_dataset(dataset).splits["train"]
    except SpikegenError as exc:
        log(f"{exc}; the path uses the NeRF-synthetic camera distance {RADIUS}")
        return RADIUS
    return float(np.median([np.linalg.norm(v.pose[:3, 3]) for v in views]))


def depth_colours(depth: np.ndarray, near: float = NEAR, far: float = FAR) -> np.ndarray:
    """Depth ``[H, W]`` (world units) -> ``uint8 [H, W, 3]``: yellow at ``near`` to dark purple at ``far``."""
    u = 1.0 - np.clip((np.asarray(depth, dtype=np.float64) - near) / (far - near), 0.0, 1.0)
    knots = np.linspace(0.0, 1.0, len(_VIRIDIS))
    rgb = np.stack([np.interp(u, knots, _VIRIDIS[:, c]) for c in range(3)], axis=-1)
    return np.round(rgb).astype(np.uint8)


def frame_panels(lum: np.ndarray, acc: np.ndarray, depth: np.ndarray, near: float = NEAR, far: float = FAR) -> np.ndarray:
    """``uint8 [H, 3 W + 2 GAP_PX, 3]``: luminance | depth | opacity of one view (each ``[H, W]``;
    depth coloured from ``near`` to ``far``)."""
    grey = [np.clip(np.round(v * 255.0), 0, 255).astype(np.uint8)
            for v in (linear_to_srgb(np.clip(lum, 0.0, 1.0)), np.clip(acc, 0.0, 1.0))]
    lum_rgb, acc_rgb = (np.repeat(g[..., None], 3, axis=2) for g in grey)
    gap = np.full((lum.shape[0], GAP_PX, 3), 255, dtype=np.uint8)
    return np.concatenate([lum_rgb, gap, depth_colours(depth, near, far), gap, acc_rgb], axis=1)


def render_video(run, path: str, frames: int, out, fps: float = 20.0, device: str = "auto",
                 progress: bool = True, log=print) -> int:
    """Render ``frames`` views of ``run``'s field along ``path`` into the animation ``out``.

    Every argument is checked before anything is rendered or written; returns the frames written.
    """
    run, out = Path(run), Path(out)
    check_animation(out, fps)
    path_poses(path, frames, RADIUS)  # checks the path name and frame count
    ck_path = run / CHECKPOINT
    if not ck_path.is_file():
        raise InputError(f"{run}: no {CHECKPOINT} (not a training run, or training has not saved yet)")
    dev = resolve_device(device)
    ck = load_checkpoint(ck_path, dev)
    field = field_from_checkpoint(ck, dev).eval()
    space = checkpoint_space(ck)
    if space is None:
        poses, depth_range = path_poses(path, frames, camera_radius(ck["config"]["dataset"], log)), (NEAR, FAR)
    else:  # about the reference camera; depth as NDC z
        poses, depth_range = ndc_path_poses(path, frames, space), (-1.0, 1.0)
    H, W, focal, background = checkpoint_camera(ck)

    def views():
        for pose in tqdm(poses, desc=f"render {path}", unit="frame", disable=not progress):
            maps = render_image(field, torch.as_tensor(pose, dtype=torch.float32, device=dev), H, W, focal, far=FAR,
                                background=background, space=space)
            yield frame_panels(*(m.cpu().numpy() for m in maps), *depth_range)

    return write_animation(out, views(), fps)
