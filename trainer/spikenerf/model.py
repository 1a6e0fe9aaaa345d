"""The radiance field: a dense voxel grid (the DVGO / Plenoxels family), optionally with a tiny MLP.

One grid ``[1, 1 + C, G, G, G]`` holds raw density (channel 0) and luminance (the sensor is
monochrome); a point's values are read by trilinear interpolation (``grid_sample``).
Luminance is ``sigmoid`` of channel 1 (the degree-0 term) plus, with ``sh_degree`` 1 or 2
(the trainer's default is 1), a view-dependent term: real spherical harmonics of the viewing
direction weighted by coefficients read from a second grid ``sh_scale`` times coarser
(view-dependent shading varies slowly in space, and the coarse grid both keeps its cost
small and fits less noise). With ``features > 0`` instead, C feature channels feed a small
MLP of the features and the viewing direction (about 19x slower per iteration on 2 CPU
cores). The grid is
upsampled during training (coarse to fine); an occupancy mask of the grid lets the renderer
skip empty space. The constructor arguments are stored in checkpoints (:meth:`config`).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


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
    """Field over the box ``[-bound, bound]^3``.

    ``query(points [M, 3], dirs [M, 3]) -> (sigma [M] per reference voxel, x [M] in [0, 1])``.
    """

    def __init__(self, grid_size: int = 32, final_size: int = 128, features: int = 0, hidden: int = 48,
                 bound: float = 1.5, alpha_init: float = 1e-2, step_ratio: float = 0.5, sh_degree: int = 0,
                 sh_scale: int = 2):
        super().__init__()
        if features and sh_degree:
            raise ValueError("features (MLP) and sh_degree are alternatives; give one")
        if sh_degree not in (0, 1, 2):
            raise ValueError(f"sh_degree must be 0, 1 or 2, got {sh_degree}")
        self.args = dict(grid_size=grid_size, final_size=final_size, features=features, hidden=hidden,
                         bound=bound, alpha_init=alpha_init, step_ratio=step_ratio, sh_degree=sh_degree,
                         sh_scale=sh_scale)
        self.bound, self.final_size, self.step_ratio = bound, final_size, step_ratio
        self.sh_degree, self.sh_scale = sh_degree, sh_scale
        self.shift = _shift_for(alpha_init, step_ratio)
        self.grid = nn.Parameter(torch.zeros(1, 1 + max(1, features), grid_size, grid_size, grid_size))
        # View-dependent part: the SH coefficients above degree 0, on a grid sh_scale times coarser.
        n_sh, S = (sh_degree + 1) ** 2 - 1, self._sh_size(grid_size)
        self.sh = nn.Parameter(torch.zeros(1, n_sh, S, S, S)) if sh_degree else None
        self.mlp = nn.Sequential(nn.Linear(features + 9, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1)) if features else nn.Sequential()
        self.register_buffer("occupancy", torch.ones(grid_size, grid_size, grid_size, dtype=torch.bool))
        self.register_buffer("box", torch.tensor([[-bound] * 3, [bound] * 3]))  # occupied box [2, 3], world

    def _sh_size(self, grid_size: int) -> int:
        return max(8, round(grid_size / self.sh_scale))

    def grids(self) -> list:
        """The voxel parameters (the grid, and the SH grid if any): one optimiser group."""
        return [self.grid] + ([self.sh] if self.sh is not None else [])

    def config(self) -> dict:
        return dict(self.args, grid_size=self.grid_size)

    @property
    def grid_size(self) -> int:
        return int(self.grid.shape[-1])

    @property
    def voxel(self) -> float:
        """Edge of a voxel of the current grid, world units."""
        return 2 * self.bound / (self.grid_size - 1)

    @property
    def ref_voxel(self) -> float:
        return 2 * self.bound / (self.final_size - 1)

    def normalise(self, points: torch.Tensor) -> torch.Tensor:
        """World points [M, 3] -> grid_sample coordinates in [-1, 1] (x, y, z -> last, middle, first axis)."""
        return (points / self.bound).flip(-1)

    def sample_grid(self, points: torch.Tensor) -> torch.Tensor:
        """Trilinear values [M, 1 + C] of the main grid at world points [M, 3]."""
        return _trilinear(self.grid, self.normalise(points))

    def query(self, points: torch.Tensor, dirs: torch.Tensor):
        g = self.normalise(points)  # one normalisation for both grids
        vals = _trilinear(self.grid, g)
        sigma = F.softplus(vals[:, 0] + self.shift)
        if self.sh is not None:  # channel 1 is the degree-0 term (a logit); the SH grid adds the rest
            view = (_trilinear(self.sh, g) * sh_basis(dirs, self.sh_degree)).sum(-1)
            return sigma, torch.sigmoid(vals[:, 1] + view)
        if not len(self.mlp):
            return sigma, torch.sigmoid(vals[:, 1])
        pe = torch.cat([dirs, torch.sin(2 * dirs), torch.cos(2 * dirs)], dim=-1)
        x = torch.sigmoid(self.mlp(torch.cat([vals[:, 1:], pe], dim=-1)).squeeze(-1))
        return sigma, x

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        """bool [M]: the nearest grid point of each world point is marked occupied."""
        G = self.occupancy.shape[0]
        half = 0.5 * (G - 1)
        cell = (points * (half / self.bound)).add_(half).round_().clamp_(0, G - 1)
        if G > 256:  # the flat index below is exact in float32 only up to G^3 = 2^24
            cell = cell.double()
        flat = (cell @ cell.new_tensor([G * G, G, 1.0])).long()  # one dot product
        return self.occupancy.reshape(-1)[flat]

    @torch.no_grad()
    def update_occupancy(self, threshold: float = 1e-4) -> float:
        """Mark grid points whose (dilated) sample alpha exceeds ``threshold``; returns the occupied fraction."""
        sigma = F.softplus(self.grid[0, 0] + self.shift)
        alpha = 1 - torch.exp(-sigma * self.step_ratio * self.voxel / self.ref_voxel)
        dil = F.max_pool3d(alpha[None, None], kernel_size=3, stride=1, padding=1)[0, 0]
        self.occupancy = dil > threshold
        self._update_box()
        return float(self.occupancy.float().mean())

    def _update_box(self) -> None:
        """The smallest box holding every occupied grid point, padded by one voxel."""
        idx = self.occupancy.nonzero()
        if idx.numel() == 0:
            self.box = torch.zeros_like(self.box)
            return
        lo = (idx.amin(dim=0).float() - 1) * self.voxel - self.bound
        hi = (idx.amax(dim=0).float() + 1) * self.voxel - self.bound
        self.box = torch.stack([lo, hi]).clamp(-self.bound, self.bound).to(self.box)

    @torch.no_grad()
    def upsample(self, size: int) -> None:
        """Resample the grid to ``size^3`` (trilinear); occupancy follows by nearest."""
        new = F.interpolate(self.grid.data, size=(size, size, size), mode="trilinear", align_corners=True)
        self.grid = nn.Parameter(new)
        if self.sh is not None:
            S = self._sh_size(size)
            self.sh = nn.Parameter(F.interpolate(self.sh.data, size=(S, S, S), mode="trilinear", align_corners=True))
        occ = F.interpolate(self.occupancy[None, None].float(), size=(size,) * 3, mode="nearest")[0, 0]
        self.occupancy = occ > 0
        self._update_box()

    def tv_loss(self, generator: torch.Generator | None = None, block: int = 24) -> torch.Tensor:
        """Total variation (squared differences) on a random ``block^3`` sub-grid: a smoothness prior.

        The SH grid (if any) gets the same prior on its own random block."""
        return sum(_tv(g, block, generator) for g in self.grids())


CPU_SPLIT = 2  # points are sampled as this many batches on the CPU (a fixed number: bit-reproducible)


def _trilinear(grid: torch.Tensor, coords: torch.Tensor, split: int | None = None) -> torch.Tensor:
    """Values [M, channels] of ``grid [1, channels, D, H, W]`` at grid_sample coordinates [M, 3].

    PyTorch's CPU kernels for 3-D grid_sample run in parallel only over the batch, so on the CPU
    many points go in as ``CPU_SPLIT`` batches against the same (expanded) grid: forward and
    backward then use two cores. The backward then fills one dense gradient per batch, which
    costs more than it saves unless there are enough points per grid value (the rule below is
    the measured break-even on 2 cores: ``python bench/bench_trainer_step.py``). ``split``
    forces the number of batches (None: :func:`split_count`).
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


def _tv(grid: torch.Tensor, block: int, generator) -> torch.Tensor:
    G = grid.shape[-1]
    b = min(block, G)
    starts = torch.randint(0, G - b + 1, (3,), generator=generator).tolist()
    sub = grid[:, :, starts[0]:starts[0] + b, starts[1]:starts[1] + b, starts[2]:starts[2] + b]
    return sub.diff(dim=2).square().mean() + sub.diff(dim=3).square().mean() + sub.diff(dim=4).square().mean()
