"""The radiance field: a dense voxel grid (the DVGO / Plenoxels family), optionally with a tiny MLP.

One grid ``[1, 1 + C, Nx, Ny, Nz]`` of cubic voxels holds raw density (channel 0) and luminance
(the sensor is monochrome) over an axis-aligned box (``aabb``, at first the cube
``[-bound, bound]^3``); a point's values are read by trilinear interpolation: ``grid_sample``
without gradients (evaluation, rendering), and in training by gathering its 8 corner voxels, the
gradient added in place into ``grid.grad`` (:class:`_CornerRead`: no grid-sized tensor is made
per step).
Luminance is ``sigmoid`` of channel 1 (the degree-0 term) plus, with ``sh_degree`` 1 or 2
(the trainer's default is 1), a view-dependent term: real spherical harmonics of the viewing
direction weighted by coefficients read from a second grid ``sh_scale`` times coarser
(view-dependent shading varies slowly in space, and the coarse grid both keeps its cost
small and fits less noise). With ``features > 0`` instead, C feature channels feed a small
MLP of the features and the viewing direction (about 19x slower per iteration on 2 CPU
cores). The grid is
upsampled during training (coarse to fine) and may be cropped to the box the object occupies
(:meth:`GridField.crop`, DVGO's fitted bounding box: the voxels then follow the object, not the
cube); an occupancy mask of the grid lets the renderer skip empty space. The constructor arguments are stored in checkpoints (:meth:`config`).

With the opt-in lazy optimiser (``--lazy-above``, ``TrainConfig.lazy_above``) the trainer switches a field to
sparse mode (``sparse = True``): the voxels read with gradients enabled (their 8 corner voxels,
:func:`corners`) are then recorded on ``tape`` for the lazy optimiser (optim.py) instead of
adding into ``grid.grad``, so that a step's work follows the rays, not the grid (docs/trainer.md,
"Speed at 400 x 400").
"""
from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import TV_LUMINANCE


def _shift_for(alpha_init: float, step_ratio: float) -> float:
    """Density bias so that an untrained sample of ``step_ratio`` reference voxels has ``alpha_init``."""
    return math.log(math.expm1(-math.log1p(-alpha_init) / step_ratio))


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real spherical harmonics of degree 1..``degree`` (2 at most), ``[M, (degree + 1)^2 - 1]``, of unit
    directions ``[M, 3]`` (the constant degree-0 term is left out: the main grid's channel 1 holds it)."""
    x, y, z = dirs.unbind(-1)
    out = [-0.48860251 * y, 0.48860251 * z, -0.48860251 * x]
    if degree >= 2:
        out += [1.09254843 * x * y, -1.09254843 * y * z, 0.31539157 * (2 * z * z - x * x - y * y),
                -1.09254843 * x * z, 0.54627421 * (x * x - y * y)]
    return torch.stack(out, dim=-1)


class GridField(nn.Module):
    """Field over the box ``aabb`` (default the cube ``[-bound, bound]^3``).

    ``query(points [M, 3], dirs [M, 3]) -> (sigma [M] per reference voxel, x [M] in [0, 1])``.
    ``grid_size``: the number of grid points across the cube ``[-bound, bound]`` at the current
    voxel edge (the grid's resolution; its own point counts per axis are ``dims``).
    """

    def __init__(self, grid_size: int = 32, final_size: int = 128, features: int = 0, hidden: int = 48,
                 bound: float = 1.5, alpha_init: float = 1e-2, step_ratio: float = 0.5, sh_degree: int = 0,
                 sh_scale: int = 2, aabb: list | None = None, dims: list | None = None):
        super().__init__()
        if features and sh_degree:
            raise ValueError("features (MLP) and sh_degree are alternatives; give one")
        if sh_degree not in (0, 1, 2):
            raise ValueError(f"sh_degree must be 0, 1 or 2, got {sh_degree}")
        if (aabb is None) != (dims is None):
            raise ValueError("aabb and dims come together")
        if aabb is None:
            aabb, dims = [[-bound] * 3, [bound] * 3], [grid_size] * 3
        dims = [int(n) for n in dims]
        self.args = dict(grid_size=grid_size, final_size=final_size, features=features, hidden=hidden,
                         bound=bound, alpha_init=alpha_init, step_ratio=step_ratio, sh_degree=sh_degree,
                         sh_scale=sh_scale)
        self.bound, self.final_size, self.step_ratio = bound, final_size, step_ratio
        self.sh_degree, self.sh_scale = sh_degree, sh_scale
        self.shift = _shift_for(alpha_init, step_ratio)
        self.register_buffer("aabb", torch.tensor(aabb, dtype=torch.float32))  # the grid's box [2, 3], world
        self.grid = nn.Parameter(torch.zeros(1, 1 + max(1, features), *dims))
        # View-dependent part: the SH coefficients above degree 0, on a grid sh_scale times coarser.
        n_sh = (sh_degree + 1) ** 2 - 1
        self.sh = nn.Parameter(torch.zeros(1, n_sh, *self._sh_dims(dims))) if sh_degree else None
        self.mlp = nn.Sequential(nn.Linear(features + 9, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1)) if features else nn.Sequential()
        self.register_buffer("occupancy", torch.ones(*dims, dtype=torch.bool))
        self.register_buffer("box", self.aabb.clone())  # occupied box [2, 3], world
        # Sparse mode (the lazy optimiser's): grids are read by gathering the 8 corners of each point, and
        # each read made with gradients enabled is recorded on ``tape`` as (grid, its distinct flat
        # voxel indices [U] sorted, leaf values [C, U]) for optim.LazyGridAdam; no dense gradient is
        # ever formed.
        self.sparse = False
        self.tape: list = []
        self.last_points: torch.Tensor | None = None

    def _sh_dims(self, dims) -> list[int]:
        return [max(8, round(n / self.sh_scale)) for n in dims]

    def grids(self) -> list:
        """The voxel parameters (the grid, and the SH grid if any): one optimiser group."""
        return [self.grid] + ([self.sh] if self.sh is not None else [])

    def config(self) -> dict:
        return dict(self.args, grid_size=self.grid_size, aabb=self.aabb.tolist(), dims=list(self.dims))

    @property
    def dims(self) -> tuple[int, int, int]:
        """Grid points along x, y, z."""
        return tuple(int(n) for n in self.grid.shape[2:])

    @property
    def grid_size(self) -> int:
        return int(round(2 * self.bound / self.voxel)) + 1

    @property
    def voxel(self) -> float:
        """Edge of a (cubic) voxel of the current grid, world units. Kept until the box or the grid
        changes: a training step asks for it several times, and on a GPU each reading of the box's
        values is a wait for the device (bench/bench_trainer_profile.py --count)."""
        a, n = self.aabb, self.grid.shape[2]
        cached = getattr(self, "_voxel_cache", None)
        if cached is None or cached[0] is not a or cached[1] != a._version or cached[2] != n:
            cached = (a, a._version, n, float((a[1, 0] - a[0, 0]) / (n - 1)))
            self._voxel_cache = cached
        return cached[3]

    @property
    def ref_voxel(self) -> float:
        return 2 * self.bound / (self.final_size - 1)

    def unit(self, points: torch.Tensor) -> torch.Tensor:
        """World points [M, 3] -> [-1, 1]^3 over the grid's box (x, y, z order)."""
        lo, hi = self.aabb
        return (points - lo) * (2 / (hi - lo)) - 1

    def normalise(self, points: torch.Tensor) -> torch.Tensor:
        """World points [M, 3] -> grid_sample coordinates in [-1, 1] (x, y, z -> last, middle, first axis)."""
        return self.unit(points).flip(-1)

    def sample_grid(self, points: torch.Tensor) -> torch.Tensor:
        """Trilinear values [M, 1 + C] of the main grid at world points [M, 3]."""
        return _trilinear(self.grid, self.normalise(points))

    def _read(self, grid: torch.Tensor, points: torch.Tensor, reads: tuple | None = None) -> torch.Tensor:
        """Trilinear values [M, C] of ``grid`` at world points [M, 3]: ``grid_sample`` without
        gradients (evaluation, rendering); with them, the 8 corners of each point gathered, and the
        gradient added in place into ``grid.grad`` (dense mode, :class:`_CornerRead`; ``reads``: the
        points' corners of this grid if already found, :meth:`density`) or recorded on the tape
        (sparse mode)."""
        train = torch.is_grad_enabled() and grid.requires_grad
        if not train or (points.requires_grad and not self.sparse):  # (corner reads give the points no gradient)
            return _trilinear(grid, self.normalise(points))
        if not self.sparse:
            return _CornerRead.apply(grid, *(reads or _corners_by_corner(self.unit(points), grid.shape[2:])))
        idx, w = corners(self.unit(points), grid.shape[2:])
        flat = grid.detach().view(grid.shape[1], -1)
        # the distinct voxels, sorted (gathers from the big grid then run in address order),
        # as a leaf [C, U]; the gradient is summed into it, never into a grid-sized tensor
        voxels, inverse = torch.unique(idx.view(-1), return_inverse=True)
        leaf = flat.index_select(1, voxels).requires_grad_(True)
        self.tape.append((grid, voxels, leaf))
        vals = leaf.index_select(1, inverse)  # [C, M * 8]
        return (vals.view(-1, *w.shape) * w).sum(-1).t()

    def density(self, points: torch.Tensor) -> tuple[torch.Tensor, tuple | None]:
        """Density [M] at world points [M, 3], as :meth:`query` gives it, without gradients (the
        renderer's early ray termination, render.visible_samples), and the reads :meth:`query` can
        take for these points (or a subset, sliced along their last axis): in dense training the
        points' corners of the main grid and their weights, which give the density here as the
        query's read gives it; otherwise None (the density then comes from ``grid_sample``)."""
        with torch.no_grad():
            if self.sparse or not self.grid.requires_grad:
                return F.softplus(_trilinear(self.grid[:, :1], self.normalise(points))[:, 0] + self.shift), None
            idx, w = _corners_by_corner(self.unit(points), self.grid.shape[2:])
            raw = (self.grid.detach()[0, 0].view(-1).index_select(0, idx.view(-1)).view(idx.shape) * w).sum(0)
            return F.softplus(raw + self.shift), (idx, w)

    def query(self, points: torch.Tensor, dirs: torch.Tensor, reads: tuple | None = None):
        """Density [M] (per reference voxel) and luminance [M] at world points [M, 3] seen along
        ``dirs [M, 3]``; ``reads``: what :meth:`density` gave for these points (training only)."""
        if torch.is_grad_enabled():  # the points a training step reads (tv_at_points puts its prior there)
            self.last_points = points.detach()
        vals = self._read(self.grid, points, reads)
        sigma = F.softplus(vals[:, 0] + self.shift)
        if self.sh is not None:  # channel 1 is the degree-0 term (a logit); the SH grid adds the rest
            view = (self._read(self.sh, points) * sh_basis(dirs, self.sh_degree)).sum(-1)
            return sigma, torch.sigmoid(vals[:, 1] + view)
        if not len(self.mlp):
            return sigma, torch.sigmoid(vals[:, 1])
        pe = torch.cat([dirs, torch.sin(2 * dirs), torch.cos(2 * dirs)], dim=-1)
        x = torch.sigmoid(self.mlp(torch.cat([vals[:, 1:], pe], dim=-1)).squeeze(-1))
        return sigma, x

    def _cell(self, points: torch.Tensor) -> torch.Tensor:
        """Float indices [M, 3] of the grid point nearest each world point, clamped into the grid
        (points outside the grid's box get the nearest face's)."""
        X, Y, Z = self.dims
        top = _constant((X - 1, Y - 1, Z - 1), points.dtype, points.device)
        cell = ((points - self.aabb[0]) * (1 / self.voxel)).round_().clamp_(min=0)
        return torch.minimum(cell, top)

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        """bool [M]: the nearest grid point of each world point is marked occupied (points outside
        the grid's box read the nearest face)."""
        X, Y, Z = self.dims
        cell = self._cell(points)
        if X * Y * Z > 2 ** 24:  # the flat index below is exact in float32 only up to 2^24
            cell = cell.double()
        flat = (cell @ _constant((Y * Z, Z, 1.0), cell.dtype, cell.device)).long()  # one dot product
        return self.occupancy.reshape(-1).index_select(0, flat)  # (index_select: gathers faster than [flat])

    def coarse_occupied(self, points: torch.Tensor) -> torch.Tensor:
        """bool [M], a conservative :meth:`occupied` for a neighbourhood: True wherever a point
        whose nearest grid point lies within ``COARSE`` grid points (per axis) of this point's
        nearest grid point may be occupied. So a False lets the renderer skip every sample of a
        stretch of ray that stays that close (render._occupied_samples).

        The grid points are taken in blocks of ``COARSE`` per axis; a block is marked when it, or a
        block next to it (3 x 3 x 3), holds an occupied point. Two indices at most ``COARSE`` apart
        fall in the same or neighbouring blocks, hence the guarantee. The block mask is cached and
        made again when ``occupancy`` is replaced or changed in place."""
        blocks = self._coarse_mask()
        Xc, Yc, Zc = blocks.shape
        b = torch.div(self._cell(points), COARSE, rounding_mode="floor")
        flat = (b @ _constant((Yc * Zc, Zc, 1.0), b.dtype, b.device)).long()  # exact: blocks are 1/COARSE^3 of the grid
        return blocks.reshape(-1).index_select(0, flat)

    def _coarse_mask(self) -> torch.Tensor:
        occ = self.occupancy
        cached = getattr(self, "_coarse_cache", None)
        if cached is not None and cached[0] is occ and cached[1] == occ._version:
            return cached[2]
        X, Y, Z = occ.shape
        Xc, Yc, Zc = (-(-n // COARSE) for n in (X, Y, Z))
        padded = occ.new_zeros(Xc * COARSE, Yc * COARSE, Zc * COARSE)
        padded[:X, :Y, :Z] = occ
        blocks = padded.view(Xc, COARSE, Yc, COARSE, Zc, COARSE).any(5).any(3).any(1)
        blocks = _dilate(blocks)
        self._coarse_cache = (occ, occ._version, blocks)
        return blocks

    @torch.no_grad()
    def update_occupancy(self, threshold: float = 1e-4) -> float:
        """Mark grid points whose sample alpha, or a neighbour's (3 x 3 x 3), exceeds ``threshold``;
        returns the occupied fraction.

        Alpha rises with the raw density, so the test is made on the raw grid against the raw value
        whose alpha is ``threshold`` (one comparison per voxel, no transcendental functions), and
        the dilation is three 1-D passes on booleans."""
        self.occupancy = _dilate(self.grid[0, 0] > self._raw_for_alpha(threshold))
        self._update_box()
        return float(self.occupancy.float().mean())

    def _raw_for_alpha(self, alpha: float) -> float:
        """The raw grid value above which a sample of the current grid has alpha above ``alpha``."""
        k = self.step_ratio * self.voxel / self.ref_voxel  # sigma -> optical depth of one sample
        sigma_min = -math.log1p(-alpha) / k  # alpha = 1 - exp(-sigma k) > threshold <=> sigma > this
        return math.log(math.expm1(sigma_min)) - self.shift  # softplus(raw + shift) > sigma_min

    def _update_box(self) -> None:
        """The smallest box holding every occupied grid point, padded by one voxel."""
        lo, hi = [], []
        for axis in range(3):  # which planes along this axis hold an occupied point
            planes = self.occupancy.any(dim=[a for a in range(3) if a != axis]).nonzero()
            if planes.numel() == 0:
                self.box = torch.zeros_like(self.box)
                return
            lo.append(planes[0, 0])
            hi.append(planes[-1, 0])
        lo = (torch.stack(lo).float() - 1) * self.voxel + self.aabb[0]
        hi = (torch.stack(hi).float() + 1) * self.voxel + self.aabb[0]
        self.box = torch.max(torch.min(torch.stack([lo, hi]), self.aabb[1]), self.aabb[0]).to(self.box)

    @torch.no_grad()
    def upsample(self, size: int) -> None:
        """Resample the grid to the voxel edge of ``size`` points across the cube ``[-bound, bound]``
        (trilinear), over the same box (its upper corner moves by less than a voxel so that voxels
        stay cubic); the SH grid follows at ``sh_scale`` times coarser, occupancy by nearest."""
        voxel = 2 * self.bound / (size - 1)
        lo, hi = self.aabb
        dims = [int(round(float(e) / voxel)) + 1 for e in hi - lo]
        aabb = torch.stack([lo, lo + voxel * (torch.tensor(dims, dtype=lo.dtype, device=lo.device) - 1)])
        self._resample(aabb, dims)

    @torch.no_grad()
    def crop(self, lo: torch.Tensor, hi: torch.Tensor) -> None:
        """Shrink the grid's box to the grid points that cover ``[lo, hi]`` (clipped to the box):
        the values are cut out, not resampled, and the voxel edge is unchanged."""
        v, a = self.voxel, self.aabb
        top = torch.tensor(self.dims, device=a.device) - 1
        i0 = ((lo - a[0]) / v).floor().long().clamp(min=0)
        i1 = torch.minimum(((hi - a[0]) / v).ceil().long(), top)
        if bool((i1 - i0 < 1).any()):
            return  # nothing to crop to: keep the box
        sl = tuple(slice(int(p), int(q) + 1) for p, q in zip(i0, i1))
        self.grid = nn.Parameter(self.grid.data[(slice(None), slice(None)) + sl].contiguous())
        self.occupancy = self.occupancy[sl].contiguous()
        self.aabb = torch.stack([a[0] + i0 * v, a[0] + i1 * v]).to(a)
        if self.sh is not None:  # resampled onto the new box (its coarser points do not nest)
            new = self._sh_dims(self.dims)
            self.sh = nn.Parameter(_resample_grid(self.sh.data, a, self.aabb, new))
        self._update_box()

    def _resample(self, aabb: torch.Tensor, dims: list[int]) -> None:
        if torch.equal(aabb, self.aabb):  # the same box: F.interpolate samples exactly these points
            new = F.interpolate(self.grid.data, size=tuple(dims), mode="trilinear", align_corners=True)
        else:
            new = _resample_grid(self.grid.data, self.aabb, aabb, dims)
        self.grid = nn.Parameter(new)
        if self.sh is not None:
            S = self._sh_dims(dims)
            self.sh = nn.Parameter(_resample_grid(self.sh.data, self.aabb, aabb, S))
        occ = F.interpolate(self.occupancy[None, None].float(), size=tuple(dims), mode="nearest")[0, 0]
        self.occupancy = occ > 0
        self.aabb = aabb.to(self.aabb)
        self._update_box()

    @torch.no_grad()
    def fitted_box(self, alpha: float = 0.3, trim: float = 1e-3, pad: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
        """(lo [3], hi [3]) world: the box of the grid points whose sample alpha exceeds ``alpha``
        (solid matter, not the faint haze an object on white leaves in empty space), each axis
        trimmed of the ``trim`` fraction of them at either end (isolated floaters do not stretch
        it) and padded by ``pad`` voxels. No such point: the grid's box."""
        pts = (self.grid[0, 0] > self._raw_for_alpha(alpha)).nonzero().float()  # [n, 3] grid indices
        if pts.shape[0] == 0:
            return self.aabb[0].clone(), self.aabb[1].clone()
        if pts.shape[0] > 2 ** 24:  # torch.quantile's limit: an even subsample
            pts = pts[torch.linspace(0, pts.shape[0] - 1, 2 ** 24, device=pts.device).long()]
        ends = torch.quantile(pts, torch.tensor([trim, 1 - trim], device=pts.device), dim=0)
        lo = self.aabb[0] + (ends[0].floor() - pad) * self.voxel
        hi = self.aabb[0] + (ends[1].ceil() + pad) * self.voxel
        return lo, hi

    def tv_loss(self, generator: torch.Generator | None = None, block: int = 24,
                luminance: str = "logit") -> torch.Tensor:
        """Total variation (squared differences) on a random ``block^3`` sub-grid: a smoothness prior.

        ``luminance`` (the main grid's luminance channel; with ``features`` every feature channel): its differences
        as stored, the logit (``"logit"``), or clamped from below at the logit of :data:`TV_FLOOR` (``"floored"``:
        a darker voxel feels no pull); of the luminance itself (``"linear"``: the logit's sigmoid) or of its sRGB
        encoding (``"srgb"``), each scaled to the logit's slope at mid-grey; or none (``"off"``).

        The SH grid (if any) gets the same prior on its own random block. In sparse mode the block
        is read as a leaf and recorded on the tape (its gradient stays the size of the block).
        Scaled by the grid's share of the cube's points at its resolution (1 for the cube): a block
        covers a larger share of a cropped grid, so unscaled the prior on each voxel would grow as
        the box shrinks; scaled, each voxel gets the prior it gets in the cube, in expectation."""
        if luminance not in TV_LUMINANCE:
            raise ValueError(f"luminance must be one of {', '.join(TV_LUMINANCE)}, got {luminance!r}")
        share = self.grid[0, 0].numel() / self.grid_size ** 3
        tape = self.tape if self.sparse else None
        total = _tv(self.grid, block, generator, tape, luminance)
        if self.sh is not None:
            total = total + _tv(self.sh, block, generator, tape)
        return share * total

    def tv_at_points(self, generator: torch.Generator | None = None, n: int = 8192) -> torch.Tensor:
        """Total variation where the last training query read: for ``n`` of its points drawn at
        random (with replacement), the squared differences between the grid point below each (its
        lowest corner) and that point's next neighbour along x, y and z, averaged per axis and summed
        over the axes and the grids (the SH grid's on its own points). The prior then lies on
        the surfaces the rays see, wherever the grid is large, at a cost set by ``n`` (the random
        block of :meth:`tv_loss` covers a vanishing part of a large grid). Dense mode only."""
        pts = self.last_points
        if pts is None or pts.shape[0] == 0:
            return self.grid.sum() * 0.0
        pick = torch.randint(0, pts.shape[0], (n,), generator=generator).to(pts.device)
        unit = self.unit(pts[pick])
        total = 0.0
        for g in self.grids():
            idx = corners(unit, g.shape[2:])[0]  # corner 0 is the lowest; 4, 2, 1 its next along x, y, z
            values = g.view(g.shape[1], -1)
            v0 = values.index_select(1, idx[:, 0])
            total = total + sum((values.index_select(1, idx[:, k]) - v0).square().mean() for k in (4, 2, 1))
        return total


COARSE = 8  # block edge, in grid points, of coarse_occupied
CPU_SPLIT = 2  # points are sampled as this many batches on the CPU (a fixed number: bit-reproducible)


def _trilinear(grid: torch.Tensor, coords: torch.Tensor, split: int | None = None) -> torch.Tensor:
    """Values [M, channels] of ``grid [1, channels, D, H, W]`` at grid_sample coordinates [M, 3].

    The field reads through this without gradients (evaluation, rendering); training reads go
    through :class:`_CornerRead`. PyTorch's CPU kernels for 3-D grid_sample run in parallel only
    over the batch, so on the CPU many points go in as ``CPU_SPLIT`` batches against the same
    (expanded) grid: forward and backward then use two cores. With gradients the backward fills
    one dense gradient per batch, which costs more than it saves unless there are enough points
    per grid value (the rule below is that measured break-even on 2 cores, ``python
    bench/bench_trainer_step.py``, from when training read through here too). ``split`` forces the
    number of batches (None: :func:`split_count`).
    """
    C, M = grid.shape[1], coords.shape[0]
    k = split or split_count(grid, M)
    m = -(-M // k)
    if m * k > M:  # pad the last batch
        coords = torch.cat([coords, coords.new_zeros(m * k - M, 3)])
    out = F.grid_sample(grid.expand(k, -1, -1, -1, -1), coords.view(k, m, 1, 1, 3), mode="bilinear",
                        align_corners=True)  # [k, C, m, 1, 1]
    return out.view(k, C, m).transpose(1, 2).reshape(k * m, C)[:M]


def split_count(grid: torch.Tensor, points: int) -> int:
    """How many batches :func:`_trilinear` samples ``points`` points of ``grid`` as."""
    return CPU_SPLIT if grid.device.type == "cpu" and points * 64 >= grid.numel() else 1


def linear_to_srgb(v: torch.Tensor) -> torch.Tensor:
    """The sRGB encoding (spikeio.linear_to_srgb) of linear values, differentiable (the power's slope
    is bounded by evaluating it at 0.0031308 and above only)."""
    v = v.clamp(min=0)
    return torch.where(v <= 0.0031308, v * 12.92, 1.055 * v.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def srgb_slope(v: torch.Tensor) -> torch.Tensor:
    """d :func:`linear_to_srgb` / dX at linear values ``v`` in [0, 1]: 12.92 on its linear part."""
    return torch.where(v <= 0.0031308, 12.92, 1.055 / 2.4 * v.clamp(min=0.0031308) ** (1 / 2.4 - 1))


SRGB_SLOPE_AT_GREY = 1.055 / 2.4 * 0.5 ** (1 / 2.4 - 1)  # srgb_slope at X = 0.5


TV_FLOOR = 0.02  # tv_loss(luminance="floored"): luminance below which a voxel's logit feels no prior
_TV_FLOOR_LOGIT = math.log(TV_FLOOR / (1 - TV_FLOOR))
# 1 / (d sRGB(sigmoid(z)) / dz at z = 0): the sRGB encoding of the luminance, scaled to the logit's slope at grey
_SRGB_AT_GREY = 1.0 / (0.25 * SRGB_SLOPE_AT_GREY)


def _tv(grid: torch.Tensor, block: int, generator, tape: list | None = None, luminance: str = "logit") -> torch.Tensor:
    dims = grid.shape[2:]
    b = [min(block, n) for n in dims]
    starts = [int(torch.randint(0, n - c + 1, (1,), generator=generator)) for n, c in zip(dims, b)]
    box = tuple(slice(s, s + c) for s, c in zip(starts, b))
    if tape is None and torch.is_grad_enabled() and grid.requires_grad:
        sub = _BlockRead.apply(grid, box)  # its gradient added in place into grid.grad's block
    else:
        sub = grid[(slice(None), slice(None)) + box]
    if tape is not None and torch.is_grad_enabled():  # a leaf copy of the block; its voxels' flat index
        axes = [torch.arange(s, s + c, device=grid.device) for s, c in zip(starts, b)]
        idx = ((axes[0] * dims[1])[:, None, None] + axes[1][None, :, None]) * dims[2] + axes[2][None, None, :]
        leaf = sub.detach().reshape(grid.shape[1], -1).clone().requires_grad_(True)  # [C, block voxels]
        tape.append((grid, idx.view(-1), leaf))
        sub = leaf.view(sub.shape)
    scale = 1.0
    if luminance == "off":  # the density's differences alone, weighted as among all the channels
        sub, scale = sub[:, :1], 1.0 / grid.shape[1]
    elif luminance == "floored":  # the logit clamped from below at TV_FLOOR's: no pull on a darker voxel
        sub = torch.cat([sub[:, :1], sub[:, 1:].clamp(min=_TV_FLOOR_LOGIT)], dim=1)
    elif luminance in ("linear", "srgb"):  # scaled to the logit's slope at mid-grey (logit 0): the same prior there
        lum = torch.sigmoid(sub[:, 1:])
        lum = 4.0 * lum if luminance == "linear" else _SRGB_AT_GREY * linear_to_srgb(lum)
        sub = torch.cat([sub[:, :1], lum], dim=1)
    return scale * (sub.diff(dim=2).square().mean() + sub.diff(dim=3).square().mean() + sub.diff(dim=4).square().mean())


def _grad_buffer(grid: torch.Tensor) -> torch.Tensor:
    """``grid.grad``, made (zeros) if there is none: the buffer the reads below add into."""
    if grid.grad is None:
        grid.grad = torch.zeros_like(grid)
    return grid.grad


class _CornerRead(torch.autograd.Function):
    """Trilinear values ``[M, C]`` of a grid ``[1, C, ...]`` from each point's 8 corners (flat
    indices ``idx [8, M]`` and weights ``w [8, M]``, :func:`_corners_by_corner`).

    The backward adds the grid's gradient straight into ``grid.grad`` (with ``index_add_``) and
    gives autograd none to accumulate. Autograd's way (``grid_sample``'s backward, or any function
    returning a gradient) makes a new grid-sized tensor on every step, which on the CPU costs page
    faults and a second pass to add it in; the trainer instead keeps ``grid.grad`` between steps
    (``zero_grad(set_to_none=False)``: zeroed in place), so a step's grid-sized work is one memset
    and the optimiser's pass (docs/trainer.md, "Speed at 400 x 400"). The gradient is the one
    ``grid_sample`` gives, up to float rounding (tested)."""

    @staticmethod
    def forward(ctx, grid, idx, w):
        C = grid.shape[1]
        vals = grid.detach().view(C, -1).index_select(1, idx.view(-1)).view(C, *idx.shape)
        ctx.save_for_backward(idx, w)
        ctx.grid = grid
        return (vals * w).sum(1).t()

    @staticmethod
    def backward(ctx, g):
        idx, w = ctx.saved_tensors
        grad = _grad_buffer(ctx.grid)
        C = grad.shape[1]
        grad.view(C, -1).index_add_(1, idx.view(-1), (g.t()[:, None, :] * w).reshape(C, -1))
        return None, None, None


class _BlockRead(torch.autograd.Function):
    """A copy of the block ``box`` (three slices) of a grid ``[1, C, ...]``; the backward adds its
    gradient in place into that block of ``grid.grad`` (as :class:`_CornerRead`, no grid-sized tensor)."""

    @staticmethod
    def forward(ctx, grid, box):
        ctx.grid, ctx.box = grid, (slice(None), slice(None)) + tuple(box)
        return grid.detach()[ctx.box].clone()

    @staticmethod
    def backward(ctx, g):
        _grad_buffer(ctx.grid)[ctx.box] += g
        return None, None


@functools.lru_cache(maxsize=256)
def _constant(values: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A small constant tensor on ``device``, made once: ``torch.tensor(values)`` in a training step
    is, on a GPU, a transfer from the host each time (bench/bench_trainer_profile.py --count).
    Read only: callers never write into it."""
    return torch.tensor(values, dtype=dtype, device=device)


_CORNER_DHW = [(d, h, w) for d in (0, 1) for h in (0, 1) for w in (0, 1)]  # corner k = 4 d + 2 h + w


def corners(unit: torch.Tensor, dims) -> tuple[torch.Tensor, torch.Tensor]:
    """The 8 grid points around each point and their trilinear weights, for a grid of ``dims``
    points (an int: the same along x, y, z) over ``[-1, 1]^3``: flat index ``[M, 8]`` (axis 0 of
    the grid <- x, as :meth:`GridField.occupied`) and weights ``[M, 8]`` of points ``unit [M, 3]``.
    Points are clamped into the grid (the renderer's samples lie inside it; ``grid_sample`` with
    ``align_corners=True`` agrees there). Corner ``k = 4 d + 2 h + w`` is the point offset by
    ``(d, h, w)`` along (x, y, z) from the lowest."""
    idx, w = _corners_by_corner(unit, dims)
    return idx.t().contiguous(), w.t().contiguous()


def _corners_by_corner(unit: torch.Tensor, dims) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`corners` laid out corner by corner: flat index ``[8, M]`` and weights ``[8, M]`` (each
    row a contiguous run over the points, which keeps the products and gathers vectorised)."""
    X, Y, Z = (dims,) * 3 if isinstance(dims, int) else (int(n) for n in dims)
    top = _constant((X - 1, Y - 1, Z - 1), unit.dtype, unit.device)
    pos = torch.minimum(((unit + 1) * (0.5 * top)).clamp_(min=0), top)
    base = torch.minimum(pos.floor(), top - 1)
    frac = (pos - base).t().contiguous()  # [3, M] in [0, 1]
    stride = _constant((Y * Z, Z, 1), torch.int64, unit.device)
    flat0 = (base.long() * stride).sum(-1)  # [M] (no integer matmul: CUDA has none)
    offsets = _constant(tuple(Y * Z * d + Z * h + w for d, h, w in _CORNER_DHW), torch.int64,
                        unit.device)  # [8]: corner k's flat offset from corner 0
    idx = flat0[None, :] + offsets[:, None]  # [8, M]
    # corner (d, h, w) weighs wx[d] * wy[h] * wz[w], multiplied in that order
    (fx, fy, fz), (gx, gy, gz) = frac, 1 - frac
    xy = [gx * gy, gx * fy, fx * gy, fx * fy]
    w = torch.stack([p * q for p in xy for q in (gz, fz)])  # [8, M]
    return idx, w


def _resample_grid(grid: torch.Tensor, old: torch.Tensor, new: torch.Tensor, dims) -> torch.Tensor:
    """``grid [1, C, ...]`` over the box ``old [2, 3]`` resampled (trilinear, edge values beyond
    it) at the points of a ``dims`` grid over the box ``new [2, 3]``."""
    axes = [torch.linspace(float(a), float(b), int(n), device=grid.device) for a, b, n in zip(new[0], new[1], dims)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)  # [X, Y, Z, 3] world
    coords = ((pts - old[0]) * (2 / (old[1] - old[0])) - 1).flip(-1)
    out = F.grid_sample(grid, coords[None], mode="bilinear", padding_mode="border", align_corners=True)
    return out.contiguous()


def _dilate(mask: torch.Tensor) -> torch.Tensor:
    """bool [D, H, W]: points with a True point in their 3 x 3 x 3 neighbourhood (max pooling, separably)."""
    for dim in range(3):
        n = mask.shape[dim]
        out = mask.clone()
        out.narrow(dim, 1, n - 1).logical_or_(mask.narrow(dim, 0, n - 1))
        out.narrow(dim, 0, n - 1).logical_or_(mask.narrow(dim, 1, n - 1))
        mask = out
    return mask
