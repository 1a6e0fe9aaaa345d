"""Rays and volume rendering: pure functions of a field (``model.GridField`` or any object with the same
members). What they read of the field, all of it:

- ``query(points [M, 3], dirs [M, 3]) -> (sigma [M] per reference voxel, x [M])``;
- ``occupied(points [M, 3]) -> bool [M]`` (empty-space skipping);
- ``density(points [M, 3]) -> (sigma [M], reads)``, without gradients (the samples behind an opaque
  surface, :func:`visible_samples`; a field without it is rendered at every occupied sample), where
  ``reads`` is None or a tuple of tensors along the points (last axis) that ``query`` takes back for
  a subset of them: ``query(points, dirs, reads)``;
- ``box``: ``[2, 3]`` tensor, the occupied box (lo, hi) in world units, on the rays' device;
- ``voxel`` and ``ref_voxel``: the current and the final voxel edge (world units; density is per
  reference voxel), and ``step_ratio``: the sample step in voxels (step = ``step_ratio * voxel``);
- ``grid``: a parameter tensor, touched only to keep the graph connected when no sample is occupied.

Cameras follow NeRF-synthetic (Blender) axes: the camera looks down its -z, +y up; pixel
``(i, j)`` (column, row) has its ray through the pixel centre ``(i + 0.5, j + 0.5)``.
"""
from __future__ import annotations

import torch
from spikegen.lens import undistort_scale

from .config import STOP_TRANSMITTANCE
from .model import COARSE

BACKGROUND = 1.0  # transparent film composited onto white (X = 1), as the dataset's ground truth
NEAR_T = 0.05  # world rays are sampled from this distance on (rays in NDC start at their near plane: 0)
# _skip_blocks walks the samples cell by cell only in the stretches of ray whose blocks may be occupied;
# where more than this fraction of the stretches are, it hands back to the one-pass walk (measured:
# with every stretch kept, the two passes took 1.8 times as long as the one; docs/trainer.md)
SKIP_MAX_KEPT = 0.8
SKIP_REPROBE = 16  # after such a hand-back, the block pass is tried again on every 16th call only


def pixel_rays(poses: torch.Tensor, pix: torch.Tensor, height: int, width: int, focal_px):
    """Rays of pixels ``pix [n]`` (flat index row * W + col) seen by cameras ``poses [n, 4, 4]``.

    ``focal_px``: one focal length (square pixels, principal point at the image centre), or
    ``(fl_x, fl_y, cx, cy)`` in pixels (principal point from the top-left corner of the image), or
    ``(fl_x, fl_y, cx, cy, k1)`` for a radial lens: each pixel centre is undistorted first
    (spikegen.lens.undistort_scale, the model the generator warps with).
    Returns origins ``[n, 3]`` and unit directions ``[n, 3]``.
    """
    k1 = 0.0
    if isinstance(focal_px, (tuple, list)):
        fx, fy, cx, cy, *lens = (float(v) for v in focal_px)
        k1 = lens[0] if lens else 0.0
    else:
        fx = fy = focal_px
        cx, cy = 0.5 * width, 0.5 * height
    row = torch.div(pix, width, rounding_mode="floor").to(poses.dtype)
    col = (pix % width).to(poses.dtype)
    x, y = (col + 0.5 - cx) / fx, (row + 0.5 - cy) / fy  # normalised, y down
    if k1:
        s = undistort_scale(x * x + y * y, k1)
        x, y = x * s, y * s
    d_cam = torch.stack([x, -y, -torch.ones_like(col)], dim=-1)
    d = torch.einsum("nij,nj->ni", poses[:, :3, :3], d_cam)
    # the origins as a contiguous copy: a column of ``poses`` (strided, or stride 0 where one pose is
    # expanded over a view) is gathered per sample (``index_select``) many times slower on the CPU
    # (docs/trainer.md, "Contiguous ray origins")
    return poses[:, :3, 3].contiguous(), d / d.norm(dim=-1, keepdim=True)


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
                near: float = NEAR_T, stop: float = STOP_TRANSMITTANCE):
    """Luminance ``x [n]`` and opacity ``acc [n]`` of rays, alpha-compositing samples every half voxel.

    ``jitter [n]`` in [0, 1) offsets each ray's samples (training); None samples at 0.5.
    With ``far`` given (a number or one per ray ``[n]``), a third value: depth ``[n]``, the expected
    distance along the (unit) ray where it ends, the light that passes through counted at ``far``.
    ``view_dirs [n, 3]``: the directions the field's view-dependent term reads (default ``dirs``;
    rays in NDC pass their world directions). ``near``: samples start this far along each ray.
    Only samples inside the occupied box and in occupied cells are evaluated: they are kept
    packed (sorted by ray) and composited with a segmented cumulative sum, so empty space
    costs neither field queries nor autograd memory. With gradients (training), the samples a ray
    reaches with transmittance below ``stop`` are dropped first (:func:`visible_samples`); without them
    (evaluation, rendering) every occupied sample is read, since finding those samples costs a
    density read of its own, about what reading them does when no gradient follows.
    """
    n = origins.shape[0]
    step = field.step_ratio * field.voxel
    idx, ray_of, pts = _occupied_samples(field, origins, dirs, step, jitter, near=near)
    reads = None
    if stop > 0 and torch.is_grad_enabled() and idx.numel() and hasattr(field, "density"):
        keep, reads = visible_samples(field, ray_of, pts, n, step, stop)
        if keep is not None:
            idx, ray_of, pts = idx.index_select(0, keep), ray_of.index_select(0, keep), pts.index_select(0, keep)
            reads = None if reads is None else tuple(r.index_select(-1, keep) for r in reads)
    if idx.numel() == 0:
        zero = origins.new_zeros(n) + 0.0 * field.grid.sum()  # keeps the graph connected
        return (zero + background, zero) if far is None else (zero + background, zero, zero + far)
    view = (dirs if view_dirs is None else view_dirs).index_select(0, ray_of)
    sigma, x = field.query(pts, view) if reads is None else field.query(pts, view, reads)
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
                    background: float = BACKGROUND, far: bool = False, stop: float = STOP_TRANSMITTANCE):
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
                       near=0.0, stop=stop)
    return maps, (o_ndc, d_ndc, length)


@torch.no_grad()
def _occupied_samples(field, origins, dirs, step, jitter, broadcast: bool | None = None, near: float = NEAR_T,
                      coarse: bool = True):
    """Packed samples: (flat index [m], ray [m], point [m, 3]), sorted by ray then depth: the
    points ``t = t_in + step (k + jitter)``, ``k = 0, 1, ...``, of each ray inside the occupied box
    and in an occupied cell.

    ``coarse``: for a field with ``coarse_occupied`` (model.GridField), rays are first walked in
    stretches of several samples and the stretches in empty blocks skipped (:func:`_skip_blocks`);
    the result is the same, to the bit. ``broadcast``: how candidate points are made otherwise (see
    below); None = chosen by the box's fill.
    """
    n = origins.shape[0]
    t_in, t_out = box_interval(origins, dirs, field.box, near)
    span = (t_out - t_in).clamp(min=0)
    coarse = coarse and hasattr(field, "coarse_occupied")
    # the host's one read of the rays' values (on a GPU each read waits for the device): the samples
    # the longest ray needs, the span summed (``broadcast`` below) and the longest direction
    # (:func:`_segment_length`), each the value its own ``float()`` would give
    host = torch.stack([torch.ceil(span.max() / step), span.sum()] +
                       ([dirs.norm(dim=-1).max()] if coarse else [])).tolist()
    n_samp = max(1, int(host[0]))
    off = torch.full((n,), 0.5, device=origins.device) if jitter is None else jitter
    seg = _segment_length(field, dirs, step, host[2]) if coarse else 0
    if seg > 1 and n_samp >= 2 * seg and _worth_skipping(field):
        packed = _skip_blocks(field, origins, dirs, step, off, t_in, t_out, n_samp, seg)
        if packed is not None:
            return packed
    k = torch.arange(n_samp, device=origins.device, dtype=origins.dtype)
    t = t_in[:, None] + step * (k[None, :] + off[:, None])  # [n, S]
    inside = (t < t_out[:, None]).view(-1)
    if broadcast is None:  # (span / step: about the candidates inside)
        broadcast = 2 * host[1] > step * inside.numel()
    if broadcast:
        # most candidates are inside the box (a field spread through it): computing every
        # candidate's point by broadcasting and testing them all is cheaper than gathering the
        # rays of those inside (a candidate past its ray's exit reads a clamped, real cell and
        # is then dropped by ``inside``)
        pts = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).view(-1, 3)
        idx = (inside & field.occupied(pts)).nonzero().squeeze(-1)
        return idx, torch.div(idx, n_samp, rounding_mode="floor"), pts.index_select(0, idx)
    idx = inside.nonzero().squeeze(-1)
    ray_of = torch.div(idx, n_samp, rounding_mode="floor")
    pts = origins.index_select(0, ray_of) + t.view(-1)[idx, None] * dirs.index_select(0, ray_of)
    occ = field.occupied(pts).nonzero().squeeze(-1)  # (one read; a boolean mask would read once per tensor)
    return idx.index_select(0, occ), ray_of.index_select(0, occ), pts.index_select(0, occ)


def _segment_length(field, dirs, step, longest: float | None = None) -> int:
    """Samples per stretch for :func:`_skip_blocks` (0: the field has no block mask).

    A stretch's samples lie within ``(seg - 1) * step * |dir|`` of its first one; in grid
    points (of edge ``field.voxel``) that is at most ``COARSE - 1.5``, so after rounding to the
    nearest grid point (at most one more) their indices stay within ``COARSE`` of the first
    sample's, as ``coarse_occupied`` requires (0.5 to spare for float error). ``longest``: the
    largest norm of ``dirs`` if already read."""
    if not hasattr(field, "coarse_occupied"):
        return 0
    longest = float(dirs.norm(dim=-1).max()) if longest is None else longest
    spacing = step * longest / field.voxel  # grid points between samples
    return int((COARSE - 1.5) / spacing) + 1 if spacing > 0 else 0


def _worth_skipping(field) -> bool:
    """False while the last :func:`_skip_blocks` on this occupancy found too little to skip, except
    every ``SKIP_REPROBE``-th call, which tries again (rays differ from call to call). Either way
    the samples are the same; this only saves the block pass where it does not pay."""
    probe = getattr(field, "_skip_probe", None)
    if probe is None or probe[0] is not field.occupancy or probe[1] != field.occupancy._version or not probe[2]:
        return True
    field._skip_probe = (*probe[:3], probe[3] + 1)
    return (probe[3] + 1) % SKIP_REPROBE == 0


def _skip_blocks(field, origins, dirs, step, off, t_in, t_out, n_samp: int, seg: int):
    """:func:`_occupied_samples` in two passes: the first sample of every stretch of ``seg`` samples
    is tested against the field's block mask (``coarse_occupied``), and only the stretches it
    passes are expanded into samples and tested cell by cell. The mask is conservative for the
    whole stretch (:func:`_segment_length`), and each sample's ``t`` and point are computed by the
    same operations as in the one-pass code, so the samples are the same, to the bit, in the
    same order. None: more than ``SKIP_MAX_KEPT`` of the stretches are kept (the caller makes the
    samples in one pass)."""
    dev, dt = origins.device, origins.dtype
    n_seg = -(-n_samp // seg)
    k0 = torch.arange(n_seg, device=dev, dtype=dt) * seg  # first sample of each stretch (exact integers)
    t0 = t_in[:, None] + step * (k0[None, :] + off[:, None])  # [n, n_seg]
    cand = (t0 < t_out[:, None]).view(-1).nonzero().squeeze(-1)  # stretches that start inside the box
    ray = torch.div(cand, n_seg, rounding_mode="floor")
    pts = origins.index_select(0, ray) + t0.view(-1)[cand, None] * dirs.index_select(0, ray)
    kept = field.coarse_occupied(pts).nonzero().squeeze(-1)  # (one read of the mask)
    full = kept.numel() > SKIP_MAX_KEPT * pts.shape[0]
    field._skip_probe = (field.occupancy, field.occupancy._version, full, 0)
    if full:  # little to skip: the one pass is cheaper
        return None
    ray = ray.index_select(0, kept)  # [s]: the rays of the stretches kept, sorted
    first = cand.index_select(0, kept) - ray * n_seg  # each stretch's index along its ray
    k = k0[first][:, None] + torch.arange(seg, device=dev, dtype=dt)[None, :]  # [s, seg], exact integers
    t = t_in[ray][:, None] + step * (k + off[ray][:, None])
    inside = ((t < t_out[ray][:, None]) & (k < n_samp)).view(-1)
    # every sample of a kept stretch is tested (one past its ray's exit reads a clamped, real cell
    # and is then dropped by ``inside``), as in the broadcast pass
    pts = (origins.index_select(0, ray)[:, None, :] + t[..., None] * dirs.index_select(0, ray)[:, None, :]).view(-1, 3)
    sel = (inside & field.occupied(pts)).nonzero().squeeze(-1)
    which = torch.div(sel, seg, rounding_mode="floor")
    ray = ray[which]
    return ray * n_samp + first[which] * seg + (sel - which * seg), ray, pts.index_select(0, sel)


@torch.no_grad()
def sample_transmittance(field, ray_of: torch.Tensor, pts: torch.Tensor, n: int, step: float):
    """The transmittance ``[m]`` with which each packed sample (sorted by ray, as
    :func:`_occupied_samples` gives them; ``n`` rays) is reached, from the field's density alone,
    without gradients, and the field's reads of the samples (``density``)."""
    sigma, reads = field.density(pts)
    log_t = -(sigma * (step / field.ref_voxel)).clamp(max=30.0)
    return torch.exp(_exclusive_segment_cumsum(log_t, ray_of, n)), reads


def visible_samples(field, ray_of: torch.Tensor, pts: torch.Tensor, n: int, step: float, stop: float):
    """Early ray termination: the index of the packed samples that their ray reaches with
    transmittance >= ``stop`` (None when that is all of them), and the field's reads of all the
    samples (:func:`sample_transmittance`). Every sample dropped lies behind one with transmittance
    < ``stop`` on its ray, so the dropped samples add less than ``stop`` to the pixel's luminance and
    opacity, and the gradient they give a sample in front (through its transmittance) is that small too."""
    trans, reads = sample_transmittance(field, ray_of, pts, n, step)
    keep = (trans >= stop).nonzero().squeeze(-1)  # (one read: the count says whether all are kept)
    return (None if keep.numel() == trans.numel() else keep), reads


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
