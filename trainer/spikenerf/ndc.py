"""Normalised device coordinates (NDC) for forward-facing captures, as NeRF uses for LLFF scenes.

A capture whose views all look one way (a handheld patch of viewpoints in front of a scene) sees
content out to any distance. The trainer's grid then lies in the NDC space of one reference
camera rather than in world space: a world point ``(X, Y, Z)`` in the reference camera's axes
(looking down its -Z, +Y up) maps to

    x = -a_x X / Z + b_x,   y = -a_y Y / Z + b_y,   z = 1 + 2 n / Z

with ``a_x = 2 fl_x / w``, ``a_y = 2 fl_y / h``, ``b_x = 2 cx / w - 1``, ``b_y = 1 - 2 cy / h`` (the
dataset's pinhole intrinsics: the reference camera's image spans x, y in [-1, 1]) and ``n`` the
near plane: depth ``n`` maps to z = -1 and infinity to z = +1, so z is affine in disparity. The map
is projective, so rays stay straight lines; a ray is moved along itself to the near plane and
then sampled uniformly in NDC, i.e. uniformly in disparity. Each ray ends in an opaque sample at
its point at infinity (z = 1; as NeRF's last sample, whose interval reaches to infinity): the light
that passes through the grid takes the field's luminance there, so the grid's far face is a learned
background per direction (render.render_ndc_rays; ``NDC.opaque_infinity``).

Reference camera (as LLFF's average pose): at the mean of the training cameras' centres, its
backward axis (+Z) the normalised mean of theirs, its right axis (+X) perpendicular to that and
to the mean of their up axes. Near plane ``n``: the smallest depth along the reference axis that
a training view's ``near`` bound reaches (``near_i - Z_i``, ``Z_i`` the view's centre's Z in the
reference axes). The grid's box: x and y spanning every training view's frustum from the near
plane to infinity (the NDC images of its four corner rays: the frustum is convex and its edges stay
straight; through a radial lens the edges bend, so rays along each edge are taken too), z from -1 to 1.

A capture is forward-facing when it has near/far bounds for every training view, every
training view's optical axis is within ``MAX_AXIS_DEG`` of the reference axis, every camera
lies behind the near plane, and every corner ray of every training view points forward in the
reference axes. Otherwise :func:`for_dataset` says why and the trainer keeps the world cube.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from spikegen.lens import undistort

MAX_AXIS_DEG = 45.0  # the largest angle between a view's optical axis and the reference axis
MIN_FORWARD = 0.05  # a ray's direction must have at least this much of the reference -Z (unit directions)


@dataclass(frozen=True)
class NDC:
    """The NDC space of one reference camera (see the module docstring); stored in checkpoints."""

    pose: tuple  # the reference camera-to-world, 4 x 4 nested tuples
    near: float  # n, in world units
    a: tuple  # (a_x, a_y)
    b: tuple  # (b_x, b_y)
    box: tuple  # ((x0, y0, -1), (x1, y1, 1)): the grid's box in NDC
    spread: float  # median distance of the training cameras from the reference centre (video paths)
    # True: each ray ends in an opaque sample at its point at infinity, which takes the light that passes
    # through the grid with the field's luminance there (render.render_ndc_rays); False (checkpoints made
    # before it, which lack the key): that light adds the background, black
    opaque_infinity: bool = False

    def to_json(self) -> dict:
        return {"kind": "ndc", "pose": [list(r) for r in self.pose], "near": self.near, "a": list(self.a),
                "b": list(self.b), "box": [list(r) for r in self.box], "spread": self.spread,
                "opaque_infinity": self.opaque_infinity}

    @classmethod
    def from_json(cls, d: dict) -> "NDC":
        return cls(tuple(tuple(float(v) for v in r) for r in d["pose"]), float(d["near"]),
                   tuple(float(v) for v in d["a"]), tuple(float(v) for v in d["b"]),
                   tuple(tuple(float(v) for v in r) for r in d["box"]), float(d["spread"]),
                   bool(d.get("opaque_infinity", False)))

    def points(self, world: np.ndarray) -> np.ndarray:
        """NDC ``[..., 3]`` of world points ``[..., 3]`` (in front of the reference camera), NumPy."""
        pose = np.array(self.pose)
        p = (world - pose[:3, 3]) @ pose[:3, :3]  # reference axes
        return np.stack([-self.a[0] * p[..., 0] / p[..., 2] + self.b[0], -self.a[1] * p[..., 1] / p[..., 2]
                         + self.b[1], 1 + 2 * self.near / p[..., 2]], axis=-1)

    def rays(self, origins: torch.Tensor, dirs: torch.Tensor):
        """World rays ``[n, 3]`` -> (NDC origins on the near plane ``[n, 3]``, unit NDC directions ``[n, 3]``,
        NDC length to infinity ``[n]``). A ray that does not point forward (its direction has less than
        ``MIN_FORWARD`` of the reference -Z) has no NDC image: it is given an origin beyond the box
        (z = 2) and a direction away from it, so the renderer finds no sample on it."""
        pose = torch.tensor(self.pose, dtype=origins.dtype, device=origins.device)
        o = (origins - pose[:3, 3]) @ pose[:3, :3]
        d = dirs @ pose[:3, :3]
        ok = d[:, 2] < -MIN_FORWARD
        dz = torch.where(ok, d[:, 2], torch.full_like(d[:, 2], -1.0))
        o = o + (-(self.near + o[:, 2]) / dz)[:, None] * d  # on the near plane: o_z = -n
        ax, ay = self.a
        ox, oy, oz = o.unbind(-1)
        o_ndc = torch.stack([-ax * ox / oz + self.b[0], -ay * oy / oz + self.b[1], 1 + 2 * self.near / oz], -1)
        d_ndc = torch.stack([-ax * (d[:, 0] / dz - ox / oz), -ay * (d[:, 1] / dz - oy / oz), -2 * self.near / oz], -1)
        length = d_ndc.norm(dim=-1)
        d_ndc = d_ndc / length[:, None]  # o_ndc + length * d_ndc is the ray's point at infinity (z = 1)
        away = torch.tensor([0.0, 0.0, 1.0], dtype=o.dtype, device=o.device)
        o_ndc = torch.where(ok[:, None], o_ndc, 2 * away)
        d_ndc = torch.where(ok[:, None], d_ndc, away)
        return o_ndc, d_ndc, torch.where(ok, length, torch.zeros_like(length))


def reference_pose(poses: np.ndarray) -> np.ndarray:
    """The average camera-to-world ``[4, 4]`` of ``poses [n, 4, 4]`` (see the module docstring)."""
    back = poses[:, :3, 2].sum(0)
    back /= np.linalg.norm(back)
    right = np.cross(poses[:, :3, 1].sum(0), back)
    right /= np.linalg.norm(right)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, np.cross(back, right), back, poses[:, :3, 3].mean(0)
    return out


EDGE_POINTS = 33  # points per image edge whose rays bound a view through a radial lens


def _boundary_dirs(k) -> np.ndarray:
    """Camera-space directions ``[c, 3]`` (OpenGL axes, not normalised) of the rays that bound an
    image of intrinsics ``k``: its four corners for a pinhole; with a radial lens (``k.k1``) also
    :data:`EDGE_POINTS` points along each edge, undistorted (spikegen.lens), since the lens bends the
    edges and the widest ray of an edge need not be a corner's."""
    if not k.k1:
        pts = [(u, v) for u in (0, k.w) for v in (0, k.h)]
    else:
        t = np.linspace(0.0, 1.0, EDGE_POINTS)
        pts = ([(k.w * a, v) for a in t for v in (0, k.h)] + [(u, k.h * a) for a in t for u in (0, k.w)])
    x = np.array([(u - k.cx) / k.fl_x for u, _ in pts])
    y = np.array([(v - k.cy) / k.fl_y for _, v in pts])
    if k.k1:
        x, y = undistort(x, y, k.k1)
    return np.stack([x, -y, -np.ones_like(x)], axis=1)


def for_dataset(ds) -> tuple[NDC | None, str]:
    """(the NDC space of a forward-facing dataset, or None; a line saying which and why)."""
    views = ds.splits["train"]
    if ds.intrinsics is None:
        return None, "no pinhole intrinsics"
    if any(not {"near", "far"} <= set(v.extra) for v in views):
        return None, "no near/far bounds for every training view"
    poses = np.array([v.pose for v in views], dtype=np.float64)
    ref = reference_pose(poses)
    axis_deg = np.degrees(np.arccos(np.clip(poses[:, :3, 2] @ ref[:3, 2], -1, 1)))
    if axis_deg.max() > MAX_AXIS_DEG:
        return None, (f"not forward-facing: a view's optical axis is {axis_deg.max():.0f} degrees from the "
                      f"mean (NDC needs <= {MAX_AXIS_DEG:.0f})")
    z = (poses[:, :3, 3] - ref[:3, 3]) @ ref[:3, 2]  # each camera centre's Z in the reference axes
    near = float(min(float(v.extra["near"]) - zi for v, zi in zip(views, z)))
    if not near > 0 or not (z > -near).all():
        return None, "not forward-facing: a camera lies in front of the near plane the bounds give"
    k = ds.intrinsics
    a, b = (2 * k.fl_x / k.w, 2 * k.fl_y / k.h), (2 * k.cx / k.w - 1, 1 - 2 * k.cy / k.h)
    corners = _boundary_dirs(k)
    d = np.einsum("nij,cj->nci", poses[:, :3, :3], corners)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d_ref = d @ ref[:3, :3]
    if not (d_ref[..., 2] < -MIN_FORWARD).all():
        return None, "not forward-facing: a view's corner ray does not point forward of the mean view"
    space = NDC(tuple(map(tuple, ref.tolist())), near, a, b, ((0.0,) * 3, (0.0,) * 3),
                float(np.median(np.linalg.norm(poses[:, :3, 3] - ref[:3, 3], axis=1))))
    o = torch.as_tensor(np.repeat(poses[:, None, :3, 3], len(corners), axis=1).reshape(-1, 3))
    o_ndc, d_ndc, length = space.rays(o, torch.as_tensor(d.reshape(-1, 3)))
    ends = torch.cat([o_ndc, o_ndc + length[:, None] * d_ndc]).numpy()  # near-plane and infinity ends
    lo, hi = ends[:, :2].min(0), ends[:, :2].max(0)
    box = ((float(lo[0]), float(lo[1]), -1.0), (float(hi[0]), float(hi[1]), 1.0))
    space = NDC(space.pose, near, a, b, box, space.spread, opaque_infinity=True)
    return space, (f"forward-facing (optical axes within {axis_deg.max():.1f} degrees of the mean): rays in NDC, "
                   f"near plane {near:.4g}, grid box x [{box[0][0]:.3f}, {box[1][0]:.3f}], "
                   f"y [{box[0][1]:.3f}, {box[1][1]:.3f}], z [-1, 1]")
