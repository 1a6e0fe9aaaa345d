"""Radial lens distortion with one coefficient: COLMAP's ``SIMPLE_RADIAL``, OpenCV's ``k1`` with
``k2 = p1 = p2 = 0``. A dataset carries it as nerfstudio's transforms do (``"camera_model": "OPENCV"``
and ``"k1"`` beside ``fl_x, fl_y, cx, cy``; ``spikegen.formats.Intrinsics``): an addition to the pinhole
intrinsics of shared/specs/dataset.md, "Real captures" (docs/real_captures.md, "Lens distortion").

A point at normalised pinhole coordinates ``(x_u, y_u) = (X / Z, Y / Z)`` (camera axes x right,
y down, z forward) is imaged at ``(x_d, y_d) = (x_u, y_u) (1 + k1 r_u^2)`` with ``r_u^2 = x_u^2 +
y_u^2``, i.e. at pixel ``(fl_x x_d + cx, fl_y y_d + cy)``. ``k1 > 0`` is a pincushion lens,
``k1 < 0`` a barrel lens.

The same functions serve the generator (``spikegen convert --lens-k1`` warps pinhole renders to
what such a lens images, :func:`warp_to_lens`) and the trainer (``spikenerf.render.pixel_rays``
turns a distorted pixel back into its ray with :func:`undistort_scale`): they use only
arithmetic, so they take numpy arrays and torch tensors alike.
"""
from __future__ import annotations

import math

import numpy as np

NEWTON_STEPS = 8  # of undistort_scale: float64 precision up to 0.999 of max_distorted_radius (tests/test_lens.py)


def distort(x, y, k1: float):
    """Normalised pinhole coordinates -> the distorted ones (numpy or torch)."""
    s = 1.0 + k1 * (x * x + y * y)
    return x * s, y * s


def undistort_scale(rd2, k1: float):
    """``s = r_u / r_d`` for distorted squared radii ``rd2`` (numpy or torch): the root near 1 of
    ``s (1 + k1 rd2 s^2) = 1`` by :data:`NEWTON_STEPS` Newton steps from ``s = 1`` (no division
    by the radius, so the image centre needs no special case). The undistorted point is
    ``(x_d s, y_d s)``."""
    s = rd2 * 0.0 + 1.0
    for _ in range(NEWTON_STEPS):
        a = k1 * rd2 * s * s
        s = s - (s * (1.0 + a) - 1.0) / (1.0 + 3.0 * a)
    return s


def undistort(x, y, k1: float):
    """Distorted normalised coordinates -> the pinhole ones (the inverse of :func:`distort` within
    :func:`max_distorted_radius`)."""
    s = undistort_scale(x * x + y * y, k1)
    return x * s, y * s


def max_distorted_radius(k1: float) -> float:
    """The largest distorted radius the model images one-to-one: infinite for ``k1 >= 0``; for a
    barrel lens ``r_d`` grows with ``r_u`` only up to ``r_u = 1 / sqrt(-3 k1)``, where it is
    ``2 / (3 sqrt(-3 k1))``; beyond it two points of the scene land on one pixel."""
    return math.inf if k1 >= 0 else 2.0 / (3.0 * math.sqrt(-3.0 * k1))


def corner_radius(width: int, height: int, fl_x: float, fl_y: float, cx: float, cy: float) -> float:
    """The largest normalised (distorted) radius of the image: at one of its four corners."""
    return max(math.hypot((u - cx) / fl_x, (v - cy) / fl_y) for u in (0.0, width) for v in (0.0, height))


def lens_problem(k1, width: int, height: int, fl_x: float, fl_y: float, cx: float, cy: float) -> str | None:
    """Why ``k1`` is not a usable lens for this camera (None when it is): not a finite number, or a
    barrel so strong that the image's corners lie beyond :func:`max_distorted_radius`."""
    if not isinstance(k1, (int, float)) or isinstance(k1, bool) or not math.isfinite(k1):
        return f"k1 must be a finite number, got {k1!r}"
    reach = corner_radius(width, height, fl_x, fl_y, cx, cy)
    if reach >= max_distorted_radius(k1):
        return (f"k1 = {k1:g} folds the image over itself before its corners (normalised radius {reach:.3f}; "
                f"this k1 maps one-to-one only up to {max_distorted_radius(k1):.3f})")
    return None


def warp_to_lens(images: np.ndarray, k1: float, fl_x: float, fl_y: float, cx: float, cy: float) -> np.ndarray:
    """``images [..., H, W]`` taken by a pinhole camera -> what the same camera with lens ``k1``
    images: each output pixel centre is undistorted and the pinhole image is read there by bilinear
    interpolation (pixel centres at ``i + 0.5``). Points that fall outside the pinhole image read
    its nearest edge pixel, so only ``k1 >= 0`` (every undistorted point lies inside) is exact;
    ``spikegen convert`` refuses a barrel lens. Returns float32, the same shape."""
    h, w = images.shape[-2:]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    xu, yu = undistort((u - cx) / fl_x, (v - cy) / fl_y, k1)
    su = np.clip(xu * fl_x + cx - 0.5, 0.0, w - 1.0)  # source position in pixel-index units
    sv = np.clip(yu * fl_y + cy - 0.5, 0.0, h - 1.0)
    u0 = np.minimum(np.floor(su).astype(np.int64), w - 2) if w > 1 else np.zeros_like(su, np.int64)
    v0 = np.minimum(np.floor(sv).astype(np.int64), h - 2) if h > 1 else np.zeros_like(sv, np.int64)
    fu, fv = (su - u0).astype(np.float32), (sv - v0).astype(np.float32)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    img = np.asarray(images, dtype=np.float32)
    top = img[..., v0, u0] * (1 - fu) + img[..., v0, u1] * fu
    bottom = img[..., v1, u0] * (1 - fu) + img[..., v1, u1] * fu
    return (top * (1 - fv) + bottom * fv).astype(np.float32)
