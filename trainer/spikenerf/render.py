"""Rays and volume rendering: pure functions of a field (``model.GridField`` or any object with the same
members). What they read of the field, all of it:

- ``query(points [M, 3], dirs [M, 3]) -> (sigma [M] per reference voxel, x [M])``;
- ``occupied(points [M, 3]) -> bool [M]`` (empty-space skipping);
- ``box``: ``[2, 3]`` tensor, the occupied box (lo, hi) in world units, on the rays' device;
- ``voxel`` and ``ref_voxel``: the current and the final voxel edge (world units; density is per
  reference voxel), and ``step_ratio``: the sample step in voxels (step = ``step_ratio * voxel``);
- ``grid``: a parameter tensor, touched only to keep the graph connected when no sample is occupied.

Cameras follow NeRF-synthetic (Blender) axes: the camera looks down its -z, +y up; pixel
``(i, j)`` (column, row) has its ray through the pixel centre ``(i + 0.5, j + 0.5)``.
"""
from __future__ import annotations

import torch

BACKGROUND = 1.0  # transparent film composited onto white (X = 1), as the dataset's ground truth
NEAR_T = 0.05  # world rays are sampled from this distance on (rays in NDC start at their near plane: 0)


def pixel_rays(poses: torch.Tensor, pix: torch.Tensor, height: int, width: int, focal_px):
    """Rays of pixels ``pix [n]`` (flat index row * W + col) seen by cameras ``poses [n, 4, 4]``.

    ``focal_px``: one focal length (square pixels, principal point at the image centre), or
    ``(fl_x, fl_y, cx, cy)`` in pixels (principal point from the top-left corner of the image).
    Returns origins ``[n, 3]`` and unit directions ``[n, 3]``.
    """
    if isinstance(focal_px, (tuple, list)):
        fx, fy, cx, cy = (float(v) for v in focal_px)
    else:
        fx = fy = focal_px
        cx, cy = 0.5 * width, 0.5 * height
    row = torch.div(pix, width, rounding_mode="floor").to(poses.dtype)
    col = (pix % width).to(poses.dtype)
    d_cam = torch.stack([(col + 0.5 - cx) / fx, -(row + 0.5 - cy) / fy, -torch.ones_like(col)], dim=-1)
    d = torch.einsum("nij,nj->ni", poses[:, :3, :3], d_cam)
    return poses[:, :3, 3], d / d.norm(dim=-1, keepdim=True)


def box_interval(origins: torch.Tensor, dirs: torch.Tensor, box: torch.Tensor, near: float = NEAR_T):
    """Entry and exit distances ``[n]`` of rays through the box ``[2, 3]`` (lo, hi) (exit <= entry: miss)."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0 = (box[0] - origins) * inv
    t1 = (box[1] - origins) * inv
    t_in = torch.minimum(t0, t1).amax(dim=-1).clamp(min=near)
    t_out = torch.maximum(t0, t1).amin(dim=-1)
    return t_in, t_out


def render_rays(field, origins: torch.Tensor, dirs: torch.Tensor, jitter: torch.Tensor | None = None,
                background: float = BACKGROUND, far=None, view_dirs: torch.Tensor | None = None,
                near: float = NEAR_T):
    """Luminance ``x [n]`` and opacity ``acc [n]`` of rays, alpha-compositing samples every half voxel.

    ``jitter [n]`` in [0, 1) offsets each ray's samples (training); None samples at 0.5.
    With ``far`` given (a number or one per ray ``[n]``), a third value: depth ``[n]``, the expected
    distance along the (unit) ray where it ends, the light that passes through counted at ``far``.
    ``view_dirs [n, 3]``: the directions the field's view-dependent term reads (default ``dirs``;
    rays in NDC pass their world directions). ``near``: samples start this far along each ray.
    Only samples inside the occupied box and in occupied cells are evaluated: they are kept
    packed (sorted by ray) and composited with a segmented cumulative sum, so empty space
    costs neither field queries nor autograd memory.
    """
    n = origins.shape[0]
    step = field.step_ratio * field.voxel
    idx, ray_of, pts = _occupied_samples(field, origins, dirs, step, jitter, near=near)
    if idx.numel() == 0:
        zero = origins.new_zeros(n) + 0.0 * field.grid.sum()  # keeps the graph connected
        return (zero + background, zero) if far is None else (zero + background, zero, zero + far)
    sigma, x = field.query(pts, (dirs if view_dirs is None else view_dirs)[ray_of])
    log_t = -(sigma * (step / field.ref_voxel)).clamp(max=30.0)  # log(1 - alpha) of each sample
    trans = torch.exp(_exclusive_segment_cumsum(log_t, ray_of, n))
    w = (1 - torch.exp(log_t)) * trans
    acc = origins.new_zeros(n).index_add(0, ray_of, w)
    lum = origins.new_zeros(n).index_add(0, ray_of, w * x)
    if far is None:
        return lum + (1 - acc) * background, acc
    # depth [n]: the samples' distances along the ray, weighted as luminance is; the light that
    # passes through (1 - acc) is placed at ``far``, as luminance puts it on the background
    t = ((pts - origins[ray_of]) * dirs[ray_of]).sum(-1)
    return lum + (1 - acc) * background, acc, origins.new_zeros(n).index_add(0, ray_of, w * t) + (1 - acc) * far


def render_ndc_rays(field, space, origins: torch.Tensor, dirs: torch.Tensor, jitter: torch.Tensor | None = None,
                    background: float = BACKGROUND, far: bool = False):
    """:func:`render_rays` of world rays ``origins, dirs [n, 3]`` in the field's NDC ``space`` (ndc.NDC):
    each is sampled uniformly in NDC from the near plane, and the view-dependent term reads its world
    direction. Returns (its values, as :func:`render_rays` gives them; with ``far``, the depth counts
    the light that passes through at the ray's NDC length to infinity), (NDC origins, directions, lengths)).

    With ``space.opaque_infinity`` the ray ends in an opaque sample at its point at infinity (as NeRF's
    last sample, whose interval reaches to infinity): the light that passes through the grid takes the
    field's luminance at that point (z = 1), clamped into the grid's box (a ray that ends beyond its x, y
    range; the box's far face, which the grid's growth may move by up to half a voxel), instead of the
    background. The far face thus holds a learned
    luminance per direction. A ray that does not point forward (NDC length 0) keeps ``background``.
    Training and rendering both composite through this function, so they agree."""
    o_ndc, d_ndc, length = space.rays(origins, dirs)
    if space.opaque_infinity:  # queried before the samples: the field's last_points stay the samples'
        end = o_ndc + length[:, None] * d_ndc
        end = torch.maximum(torch.minimum(end, field.aabb[1]), field.aabb[0])
        x_end = field.query(end, dirs)[1]
        background = torch.where(length > 0, x_end, torch.full_like(x_end, background))
    maps = render_rays(field, o_ndc, d_ndc, jitter, background, far=length if far else None, view_dirs=dirs,
                       near=0.0)
    return maps, (o_ndc, d_ndc, length)


@torch.no_grad()
def _occupied_samples(field, origins, dirs, step, jitter, broadcast: bool | None = None, near: float = NEAR_T):
    """Packed samples: (flat index [m], ray [m], point [m, 3]), sorted by ray then depth.

    ``broadcast``: how candidate points are made (see below); None = chosen by the box's fill.
    """
    n = origins.shape[0]
    t_in, t_out = box_interval(origins, dirs, field.box, near)
    span = (t_out - t_in).clamp(min=0)
    n_samp = max(1, int(torch.ceil(span.max() / step).item()))
    off = torch.full((n,), 0.5, device=origins.device) if jitter is None else jitter
    k = torch.arange(n_samp, device=origins.device, dtype=origins.dtype)
    t = t_in[:, None] + step * (k[None, :] + off[:, None])  # [n, S]
    inside = (t < t_out[:, None]).view(-1)
    if broadcast is None:  # (span / step: about the candidates inside)
        broadcast = 2 * float(span.sum()) > step * inside.numel()
    if broadcast:
        # most candidates are inside the box (a field spread through it): computing every
        # candidate's point by broadcasting and testing them all is cheaper than gathering the
        # rays of those inside (a candidate past its ray's exit reads a clamped, real cell and
        # is then dropped by ``inside``)
        pts = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).view(-1, 3)
        idx = (inside & field.occupied(pts)).nonzero().squeeze(-1)
        return idx, torch.div(idx, n_samp, rounding_mode="floor"), pts[idx]
    idx = inside.nonzero().squeeze(-1)
    ray_of = torch.div(idx, n_samp, rounding_mode="floor")
    pts = origins[ray_of] + t.view(-1)[idx, None] * dirs[ray_of]
    occ = field.occupied(pts)
    return idx[occ], ray_of[occ], pts[occ]


def _exclusive_segment_cumsum(v: torch.Tensor, seg: torch.Tensor, n_seg: int) -> torch.Tensor:
    """Sum of the earlier values of the same segment, for values ``v [m]`` sorted by ``seg [m]``."""
    c = torch.cumsum(v.double(), dim=0)
    excl = c - v.double()
    counts = torch.bincount(seg, minlength=n_seg)
    first = torch.cumsum(counts, dim=0) - counts  # index of each segment's first value
    return (excl - excl[first[seg]]).to(v.dtype)


@torch.no_grad()
def render_image(field, pose: torch.Tensor, height: int, width: int, focal_px, chunk: int = 8192,
                 far: float | None = None, background: float = BACKGROUND, space=None):
    """Luminance ``[H, W]`` and opacity ``[H, W]`` of a full view (pose ``[4, 4]``; ``focal_px`` as
    :func:`pixel_rays` takes it), and with ``far`` given, depth ``[H, W]`` too (see :func:`render_rays`).

    ``space``: the field's :class:`ndc.NDC` (None: the field is in world coordinates); the rays are
    then mapped into it and composited as in training (:func:`render_ndc_rays`; the opacity is the
    grid's, without the opaque sample at infinity), and the depth (with ``far`` given; its value is
    then unused) is the NDC z where the ray ends, -1 at the near plane to 1 at infinity (light that
    passes through: 1)."""
    P = height * width
    chunks = []
    for a in range(0, P, chunk):
        pix = torch.arange(a, min(P, a + chunk), device=pose.device)
        o, d = pixel_rays(pose.expand(pix.shape[0], 4, 4), pix, height, width, focal_px)
        if space is None:
            chunks.append(render_rays(field, o, d, background=background, far=far))
            continue
        maps, (o_ndc, d_ndc, length) = render_ndc_rays(field, space, o, d, background=background, far=far is not None)
        if far is not None:  # distance along the NDC ray -> its z
            maps = (*maps[:2], torch.where(length > 0, o_ndc[:, 2] + maps[2] * d_ndc[:, 2], torch.ones_like(length)))
        chunks.append(maps)
    return tuple(torch.cat(maps).view(height, width) for maps in zip(*chunks))
