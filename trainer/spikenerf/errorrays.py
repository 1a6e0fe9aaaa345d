"""Error-guided rays (``spikenerf train --error-rays F``): a fraction ``F`` of each step's rays drawn
where the field's error has been high, the rest uniformly as without it.

Each target image is cut into square tiles of ``t = max(1, W // 100)`` pixels a side (so a 400 x 400
image has 100 x 100 tiles of 4 x 4 pixels and a 100 x 100 image one pixel a tile). Every step adds each
ray's error to its tile's running sum; every ``REFRESH`` steps the sums become the tiles' mean error of
those steps, which updates the map (``MIX`` of the new mean and ``1 - MIX`` of the old value, or the new
mean for a tile seen the first time), and the map is turned into the cumulative distribution the next
``REFRESH`` steps draw from: a tile with probability proportional to its error (a tile never seen counts
as the mean of the seen ones), then a pixel of it uniformly. No ray is drawn from the map before its
first refresh.

The error of a ray is ``(prediction - observation)^2 / max(prediction, FLOOR)`` in the loss's
radiance-like units (train.method_loss): a spike count's variance grows with its mean, so the plain
squared error would draw the brightest, noisiest pixels (the white background), not the ones the
field gets wrong (docs/trainer.md, "Error-guided rays").

Each ray of a step counts as drawn from the mixture of the two draws (uniform with ``1 - F``, the map with
``F``), and its term in the loss's mean is weighted by ``1 / (1 - F + F b)``, ``b`` its pixel's chance under the
map over its chance under the uniform draw (:meth:`ErrorRays.weights`): in expectation the weighted mean is the
mean over all pixels, so the map changes which rays a step reads, not what the loss asks of the field.

Determinism: the rays are drawn on the CPU from the step's generator, as the uniform ones are. The
errors are summed on the run's device as integers (the error times ``2**SCALE_BITS``, rounded; the
count as an integer), so the sums do not depend on the order a GPU adds them in; the map and its
distribution are made on the CPU. A resumed run gets the map, and the sums of the steps since its
last refresh, from the checkpoint (:meth:`ErrorRays.state_dict`), and so draws what the run it
continues would have drawn.
"""
from __future__ import annotations

import torch

REFRESH = 50  # steps between the map's updates (and the distribution's)
MIX = 0.5  # the weight of a refresh's mean error against the tile's previous value
FLOOR = 0.02  # the least prediction the squared error is divided by (radiance-like units)
SCALE_BITS = 24  # errors are summed as integers in units of 2**-SCALE_BITS
TILES_ACROSS = 100  # tiles are max(1, W // TILES_ACROSS) pixels a side


def tile_size(width: int) -> int:
    return max(1, width // TILES_ACROSS)


class ErrorRays:
    """The error map of ``images`` target images of ``height x width`` pixels, and the draws from it."""

    def __init__(self, images: int, height: int, width: int, fraction: float, device):
        if not 0.0 <= fraction < 1.0:
            raise ValueError(f"fraction must be in [0, 1), got {fraction}")
        self.fraction, self.device = float(fraction), torch.device(device)
        t = tile_size(width)
        y, x = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
        tile = ((y // t) * (-(-width // t)) + (x // t)).reshape(-1)  # pixel -> its tile
        self.tiles = int(tile.max()) + 1
        self.tile_of, self.tile_cpu = tile.to(self.device), tile
        count = torch.bincount(tile, minlength=self.tiles)
        self.order = torch.argsort(tile, stable=True)  # the pixels, tile by tile
        self.start, self.count = torch.cumsum(count, 0) - count, count
        n = images * self.tiles
        self.error = torch.full((n,), -1.0, dtype=torch.float64)  # -1: never seen
        self.sums = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.hits = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.cdf: torch.Tensor | None = None  # the tiles' cumulative weights (None until a tile is seen)
        self.boost: torch.Tensor | None = None  # each tile's pixels' chance under the map over the uniform one

    def rays(self, n: int) -> int:
        """How many of a step's ``n`` rays are drawn from the map (none before its first refresh)."""
        return 0 if self.cdf is None else int(round(self.fraction * n))

    def draw(self, k: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Image and pixel indices ``[k]`` (CPU), drawn from the map with ``gen``."""
        u = torch.rand(k, generator=gen, dtype=torch.float64) * self.cdf[-1]
        flat = torch.searchsorted(self.cdf, u, right=True).clamp_(max=self.cdf.numel() - 1)
        image, tile = flat // self.tiles, flat % self.tiles
        within = (torch.rand(k, generator=gen) * self.count[tile]).long()
        within = torch.minimum(within, self.count[tile] - 1)
        return image, self.order[self.start[tile] + within]

    def note(self, image: torch.Tensor, pixel: torch.Tensor, prediction: torch.Tensor,
             observation: torch.Tensor) -> None:
        """Add a step's rays' errors (device tensors ``[n]``) to their tiles' sums."""
        pred = prediction.detach()
        err = ((pred - observation.detach()).square() / pred.clamp(min=FLOOR)).nan_to_num(0.0).clamp(max=1e6)
        flat = image * self.tiles + self.tile_of[pixel]
        self.sums.index_add_(0, flat, torch.round(err.double() * 2.0 ** SCALE_BITS).to(torch.int64))
        self.hits.index_add_(0, flat, torch.ones_like(flat))

    def refresh(self) -> None:
        """The steps' mean errors into the map, and the map into the distribution of the next draws."""
        sums, hits = self.sums.cpu(), self.hits.cpu()
        hit = hits > 0
        mean = sums.double() / hits.clamp(min=1).double() / 2.0 ** SCALE_BITS
        old = self.error
        self.error = torch.where(hit & (old >= 0), MIX * mean + (1.0 - MIX) * old, torch.where(hit, mean, old))
        self.sums.zero_()
        self.hits.zero_()
        self.cdf = self._distribution()

    def _distribution(self) -> torch.Tensor | None:
        """The cumulative weights of the tiles (None while no tile has been seen); sets :attr:`boost`."""
        seen = self.error >= 0
        if not seen.any():
            return None
        weight = torch.where(seen, self.error, self.error[seen].mean())
        if not weight.sum() > 0:  # no error anywhere: uniform over the tiles
            weight = torch.ones_like(weight)
        # a pixel's chance under the map times the number of pixels: its tile's share over the tile's pixels
        pixels = weight.numel() // self.tiles * int(self.count.sum())
        self.boost = ((weight / weight.sum() * pixels).view(-1, self.tiles) / self.count).reshape(-1)
        return torch.cumsum(weight, 0)

    def weights(self, image: torch.Tensor, pixel: torch.Tensor, fraction: float) -> torch.Tensor:
        """The rays' weights ``[n]`` (CPU, float32) in the loss's mean: ``1 / (1 - F + F * b)``, ``F`` the
        ``fraction`` of the step's rays drawn from the map, ``b`` a pixel's chance of being drawn from the map
        over its chance when drawn uniformly (the module docstring)."""
        boost = self.boost[image * self.tiles + self.tile_cpu[pixel]]
        return (1.0 / (1.0 - fraction + fraction * boost)).float()

    def step_done(self, it: int) -> None:
        """Called after iteration ``it``'s errors were noted: refresh every ``REFRESH`` steps."""
        if (it + 1) % REFRESH == 0:
            self.refresh()

    def state_dict(self) -> dict:
        """The map and the sums since its last refresh (only the tiles hit), for a bit-identical resume."""
        idx = torch.nonzero(self.hits.cpu()).reshape(-1)
        return {"error": self.error.clone(), "index": idx, "sums": self.sums.cpu()[idx], "hits": self.hits.cpu()[idx]}

    def load_state_dict(self, state: dict) -> None:
        error = state["error"].to(torch.float64).cpu()
        if error.shape != self.error.shape:
            raise ValueError(f"the error map holds {error.numel()} tiles, this run has {self.error.numel()}")
        self.error = error
        self.sums.zero_()
        self.hits.zero_()
        idx = state["index"].to(self.device)
        self.sums[idx] = state["sums"].to(self.device)
        self.hits[idx] = state["hits"].to(self.device)
        self.cdf = self._distribution()
