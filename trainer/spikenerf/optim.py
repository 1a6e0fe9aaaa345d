"""Lazy ("sparse") Adam for the voxel grids: each step updates only the grid entries that were read.

A dense Adam step over a 256^3 grid reads and writes every voxel (and its gradient) at every
iteration, although a batch of rays reads a few hundred thousand of them; at 400 x 400 that step,
the dense gradient and the total-variation prior's dense gradient cost more than the rays
(docs/trainer.md, "Speed at 400 x 400"). Here a field in sparse mode (``GridField.sparse``)
records each read of a grid as ``(grid, distinct flat voxel indices [U] sorted, values [C, U])``
on its ``tape``, the values being a leaf tensor; after ``backward`` this optimiser sums the
leaves' gradients per voxel (a step reads a grid twice: the samples and the total-variation
block) and applies the Adam update to the read voxels only. For every read voxel the update is the
dense Adam step (same moments, same bias correction by the global step count); voxels not read
keep their parameters and moments (a dense Adam would still move them by their decaying
momentum: the two runs differ, see docs/trainer.md for the measured quality).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from spikegen.errors import InputError


class LazyGridAdam:
    """Adam (``betas``, ``eps`` as :class:`torch.optim.Adam`) over ``field.grids()``, updated lazily from
    ``field.tape``; the MLP's parameters (if any) get a fused dense :class:`torch.optim.Adam`.

    ``param_groups[0]["lr"]`` is the grids' learning rate, ``param_groups[1]["lr"]`` the MLP's.
    """

    def __init__(self, field, lr_grid: float, lr_mlp: float, betas=(0.9, 0.99), eps: float = 1e-8):
        self.field, self.betas, self.eps = field, betas, eps
        self.grids = field.grids()
        self.step_count = 0
        # per grid [C, G^3]: the moments
        self.exp_avg = [torch.zeros_like(p.detach()).view(p.shape[1], -1) for p in self.grids]
        self.exp_avg_sq = [torch.zeros_like(m) for m in self.exp_avg]
        mlp_params = list(field.mlp.parameters())
        self.mlp = torch.optim.Adam(mlp_params, lr=lr_mlp, betas=betas, eps=eps, fused=True) if mlp_params else None
        self.param_groups = [{"lr": lr_grid}] + (self.mlp.param_groups if self.mlp else [{"lr": lr_mlp}])

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Drop dense gradients (none are used); the tape is kept: it is read by the next :meth:`step`."""
        for p in self.grids:
            p.grad = None
        if self.mlp:
            self.mlp.zero_grad(set_to_none=set_to_none)

    @torch.no_grad()
    def step(self) -> None:
        self.step_count += 1
        for i, p in enumerate(self.grids):
            reads = [(idx, vals.grad) for grid, idx, vals in self.field.tape if grid is p and vals.grad is not None]
            if reads:
                self._update(i, *_sum_reads(reads))
        self.field.tape.clear()
        if self.mlp:
            self.mlp.step()

    def _update(self, i: int, idx: torch.Tensor, g: torch.Tensor) -> None:
        """Adam on the distinct voxels ``idx [U]`` of grid ``i``, whose summed gradients are ``g [C, U]``."""
        b1, b2 = self.betas
        t, lr = self.step_count, self.param_groups[0]["lr"]
        m = self.exp_avg[i].index_select(1, idx).lerp_(g, 1 - b1)
        v = self.exp_avg_sq[i].index_select(1, idx).mul_(b2).addcmul_(g, g, value=1 - b2)
        self.exp_avg[i].index_copy_(1, idx, m)
        self.exp_avg_sq[i].index_copy_(1, idx, v)
        denom = (v.sqrt_() / math.sqrt(1 - b2 ** t)).add_(self.eps)
        flat = self.grids[i].data.view(m.shape[0], -1)
        flat.index_copy_(1, idx, flat.index_select(1, idx).addcdiv_(m, denom, value=-lr / (1 - b1 ** t)))

    def state_dict(self) -> dict:
        """The step count and, per grid, which voxels have moments not both zero (one bit a voxel)
        and their moments (a voxel never read has zero moments): exact, never larger than the
        dense moments by more than the bits."""
        grids = []
        for m, v in zip(self.exp_avg, self.exp_avg_sq):
            keep = ((m != 0) | (v != 0)).any(dim=0)
            bits = torch.from_numpy(np.packbits(keep.cpu().numpy()))  # which voxels: one bit each
            grids.append({"voxels": int(m.shape[1]), "touched_bits": bits, "exp_avg": m[:, keep].clone(),
                          "exp_avg_sq": v[:, keep].clone()})
        return {"kind": "lazy_grid_adam", "step": self.step_count, "grids": grids,
                "mlp": self.mlp.state_dict() if self.mlp else None}

    def load_state_dict(self, state: dict) -> None:
        if state.get("kind") != "lazy_grid_adam":
            raise InputError("the checkpoint's optimizer state is from the dense-Adam trainer (before the lazy "
                             "grid optimizer); start the run again with another --out")
        if [g["voxels"] for g in state["grids"]] != [m.shape[1] for m in self.exp_avg]:
            raise InputError("the checkpoint's optimizer state does not match its grids")
        self.step_count = int(state["step"])
        for m, v, g in zip(self.exp_avg, self.exp_avg_sq, state["grids"]):
            touched = np.unpackbits(g["touched_bits"].numpy(), count=m.shape[1]).astype(bool)
            index = torch.from_numpy(touched.nonzero()[0]).to(m.device)
            m.zero_().index_copy_(1, index, g["exp_avg"].to(m))
            v.zero_().index_copy_(1, index, g["exp_avg_sq"].to(v))
        if self.mlp:
            self.mlp.load_state_dict(state["mlp"])


def _sum_reads(reads: list) -> tuple[torch.Tensor, torch.Tensor]:
    """One (distinct voxels [U] sorted, summed gradient [C, U]) from reads of distinct sorted voxels."""
    if len(reads) == 1:
        return reads[0]
    idx = torch.unique(torch.cat([r[0] for r in reads]))
    g = reads[0][1].new_zeros(reads[0][1].shape[0], idx.numel())
    for voxels, grad in reads:
        g.index_add_(1, torch.searchsorted(idx, voxels), grad)
    return idx, g
