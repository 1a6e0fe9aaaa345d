"""Rays and volume rendering; a pure function of a field that answers ``query`` and ``occupied``.

Cameras follow NeRF-synthetic (Blender) axes: the camera looks down its -z, +y up; pixel
``(i, j)`` (column, row) has its ray through the pixel centre ``(i + 0.5, j + 0.5)``.
"""
from __future__ import annotations

import torch

BACKGROUND = 1.0  # transparent film composited onto white (X = 1), as the dataset's ground truth


def pixel_rays(poses: torch.Tensor, pix: torch.Tensor, height: int, width: int, focal_px: float):
    """Rays of pixels ``pix [n]`` (flat index row * W + col) seen by cameras ``poses [n, 4, 4]``.

    Returns origins ``[n, 3]`` and unit directions ``[n, 3]``.
    """
    row = torch.div(pix, width, rounding_mode="floor").to(poses.dtype)
    col = (pix % width).to(poses.dtype)
    d_cam = torch.stack([(col + 0.5 - 0.5 * width) / focal_px, -(row + 0.5 - 0.5 * height) / focal_px,
                         -torch.ones_like(col)], dim=-1)
    d = torch.einsum("nij,nj->ni", poses[:, :3, :3], d_cam)
    return poses[:, :3, 3], d / d.norm(dim=-1, keepdim=True)


def box_interval(origins: torch.Tensor, dirs: torch.Tensor, box: torch.Tensor, near: float = 0.05):
    """Entry and exit distances ``[n]`` of rays through the box ``[2, 3]`` (lo, hi) (exit <= entry: miss)."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0 = (box[0] - origins) * inv
    t1 = (box[1] - origins) * inv
    t_in = torch.minimum(t0, t1).amax(dim=-1).clamp(min=near)
    t_out = torch.maximum(t0, t1).amin(dim=-1)
    return t_in, t_out


def render_rays(field, origins: torch.Tensor, dirs: torch.Tensor, jitter: torch.Tensor | None = None,
                background: float = BACKGROUND):
    """Luminance ``x [n]`` and opacity ``acc [n]`` of rays, alpha-compositing samples every half voxel.

    ``jitter [n]`` in [0, 1) offsets each ray's samples (training); None samples at 0.5.
    Samples outside the box or in unoccupied cells are skipped (alpha 0).
    """
    n = origins.shape[0]
    step = field.step_ratio * field.voxel
    t_in, t_out = box_interval(origins, dirs, field.box)
    span = (t_out - t_in).clamp(min=0)
    n_samp = max(1, int(torch.ceil(span.max() / step).item()))
    # (a sample grid that starts at each ray's entry; 'valid' marks samples inside the box)
    off = torch.full((n,), 0.5, device=origins.device) if jitter is None else jitter
    t = t_in[:, None] + step * (torch.arange(n_samp, device=origins.device)[None, :] + off[:, None])  # [n, S]
    pts = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    valid = t < t_out[:, None]
    flat_pts = pts.view(-1, 3)
    keep = valid.view(-1).clone()
    idx = keep.nonzero().squeeze(-1)
    occ = field.occupied(flat_pts[idx])
    idx = idx[occ]
    alpha = torch.zeros(n * n_samp, device=origins.device, dtype=origins.dtype)
    color = torch.zeros_like(alpha)
    if idx.numel():
        ray_of = torch.div(idx, n_samp, rounding_mode="floor")
        sigma, x = field.query(flat_pts[idx], dirs[ray_of])
        a = 1 - torch.exp(-sigma * (step / field.ref_voxel))
        alpha = alpha.index_put((idx,), a)
        color = color.index_put((idx,), x)
    alpha, color = alpha.view(n, n_samp), color.view(n, n_samp)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1] + 1e-10], dim=1), dim=1)
    w = alpha * trans
    acc = w.sum(dim=1)
    return (w * color).sum(dim=1) + (1 - acc) * background, acc


@torch.no_grad()
def render_image(field, pose: torch.Tensor, height: int, width: int, focal_px: float, chunk: int = 8192):
    """Luminance ``[H, W]`` and opacity ``[H, W]`` of a full view (pose ``[4, 4]``)."""
    P = height * width
    xs, accs = [], []
    for a in range(0, P, chunk):
        pix = torch.arange(a, min(P, a + chunk), device=pose.device)
        o, d = pixel_rays(pose.expand(pix.shape[0], 4, 4), pix, height, width, focal_px)
        x, acc = render_rays(field, o, d)
        xs.append(x)
        accs.append(acc)
    return torch.cat(xs).view(height, width), torch.cat(accs).view(height, width)
