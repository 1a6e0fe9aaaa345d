"""Lazy ("sparse") Adam for the voxel grids: each step updates only the grid entries that were read.

A dense Adam step over a 256^3 grid reads and writes every voxel (and its gradient) at every
iteration, although a batch of rays reads a few hundred thousand of them; at 400 x 400 that step,
the dense gradient and the total-variation prior's dense gradient cost more than the rays
(docs/trainer.md, "Speed at 400 x 400"). Here a field in sparse mode (``GridField.sparse``)
records each read of a grid as ``(grid, distinct flat voxel indices [U] sorted, values [C, U])``
on its ``tape``, the values being a leaf tensor; after ``backward`` this optimiser sums the
leaves' gradients per voxel (a step reads a grid twice: the samples and the total-variation
block) and applies the Adam update to the read voxels only.

A dense Adam keeps moving a voxel that was not read: its gradient is zero, its moments decay
(``m *= b1``, ``v *= b2``) and it still steps by ``lr_j * m_hat_j / (sqrt(v_hat_j) + eps)``. The
lazy one catches a voxel up on those steps when it is next read: each voxel has the step at
which it was last updated (``last``); for the ``k`` steps it missed, its moments are decayed by
``b1**k`` and ``b2**k`` and its parameter moves by the missed steps' sum, which without ``eps``
has a closed form::

    sum_j lr_j m_hat_j / sqrt(v_hat_j) = m_s / sqrt(v_s) * W(s),
    W(s) = sum_{j = s+1}^{t-1} lr_j * sqrt(1 - b2**j) / (1 - b1**j) * r**(j - s),   r = b1 / sqrt(b2)

(``s`` the voxel's last step, ``t`` the current one). ``W`` is kept for the last ``WINDOW`` steps
and updated in O(WINDOW) per step; a term ``WINDOW`` steps after ``s`` is smaller than the first
by ``r**WINDOW`` (1e-22 for the trainer's betas), so older terms are dropped. So a read voxel
gets the dense Adam's parameter and moments up to ``eps`` (tested against torch's Adam with
voxels skipped for many steps), and a voxel never read again keeps the momentum drift it had
not yet received (the dense Adam's drift would have been applied over the following steps).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from spikegen.errors import InputError


WINDOW = 512  # steps after a voxel's last update over which its momentum drift is summed


class LazyGridAdam:
    """Adam (``betas``, ``eps`` as :class:`torch.optim.Adam`) over ``field.grids()``, updated lazily from
    ``field.tape``; the MLP's parameters (if any) get a fused dense :class:`torch.optim.Adam` (``eps_mlp``).

    ``param_groups[0]["lr"]`` is the grids' learning rate, ``param_groups[1]["lr"]`` the MLP's.
    """

    def __init__(self, field, lr_grid: float, lr_mlp: float, betas=(0.9, 0.99), eps: float = 1e-8,
                 eps_mlp: float = 1e-8):
        self.field, self.betas, self.eps = field, betas, eps
        self.grids = field.grids()
        self.step_count = 0
        # per grid [C, G^3]: the moments
        self.exp_avg = [torch.zeros_like(p.detach()).view(p.shape[1], -1) for p in self.grids]
        self.exp_avg_sq = [torch.zeros_like(m) for m in self.exp_avg]
        # per grid [G^3]: the step at which each voxel's moments were last updated (0: never)
        self.last = [torch.zeros(m.shape[1], dtype=torch.int32, device=m.device) for m in self.exp_avg]
        # W(s) of the module docstring for s = step_count - WINDOW .. step_count (index s - w_base)
        self.w_base, self.w = 0, np.zeros(1)
        mlp_params = list(field.mlp.parameters())
        self.mlp = torch.optim.Adam(mlp_params, lr=lr_mlp, betas=betas, eps=eps_mlp, fused=True) if mlp_params else None
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
        self._advance_drift()
        if self.mlp:
            self.mlp.step()

    def _advance_drift(self) -> None:
        """Add this step's term to W(s) of every recent s (voxels not read now move by it in a dense
        Adam) and open W(t) = 0 for the voxels updated now."""
        b1, b2 = self.betas
        t, lr = self.step_count, self.param_groups[0]["lr"]
        r = b1 / math.sqrt(b2)
        s = np.arange(self.w_base, t)
        w = np.zeros(s.size + 1)  # (steps the window has not seen, e.g. a step count set from outside: 0)
        w[: min(s.size, self.w.size)] = self.w[: s.size]
        w[: s.size] += lr * math.sqrt(1 - b2 ** t) / (1 - b1 ** t) * r ** (t - s)
        self.w = w
        if self.w.size > WINDOW + 1:
            cut = self.w.size - (WINDOW + 1)
            self.w, self.w_base = self.w[cut:], self.w_base + cut

    def _drift(self, last: torch.Tensor) -> torch.Tensor:
        """W(s) [U] for the voxels' last steps ``last [U]`` (zero where older than the window: never
        read, or their drift's remaining terms are below ``r**WINDOW``)."""
        w = torch.from_numpy(self.w).to(torch.float32)
        pos = last.long() - self.w_base
        ok = (pos >= 0) & (last > 0)
        return torch.where(ok, w[pos.clamp(min=0)], torch.zeros((), dtype=torch.float32))

    def _update(self, i: int, idx: torch.Tensor, g: torch.Tensor) -> None:
        """Adam on the distinct voxels ``idx [U]`` of grid ``i``, whose summed gradients are ``g [C, U]``,
        after catching them up on the steps since they were last updated."""
        b1, b2 = self.betas
        t, lr = self.step_count, self.param_groups[0]["lr"]
        m = self.exp_avg[i].index_select(1, idx)
        v = self.exp_avg_sq[i].index_select(1, idx)
        flat = self.grids[i].data.view(m.shape[0], -1)
        p = flat.index_select(1, idx)
        last = self.last[i].index_select(0, idx)
        # steps with zero gradient since the last update (none for a voxel never updated: its moments are 0)
        missed = torch.where(last > 0, t - 1 - last, torch.zeros_like(last)).to(torch.float32)
        if bool((missed > 0).any()):
            # the missed steps' drift (closed form without eps: module docstring), then the decays
            w = self._drift(last).to(m.device)
            safe = v > 0
            p.sub_(torch.where(safe, m / v.clamp(min=1e-38).sqrt(), torch.zeros_like(m)) * w)
            m.mul_(torch.pow(b1, missed))
            v.mul_(torch.pow(b2, missed))
        m.lerp_(g, 1 - b1)
        v.mul_(b2).addcmul_(g, g, value=1 - b2)
        self.exp_avg[i].index_copy_(1, idx, m)
        self.exp_avg_sq[i].index_copy_(1, idx, v)
        self.last[i].index_fill_(0, idx, t)
        denom = (v.sqrt() / math.sqrt(1 - b2 ** t)).add_(self.eps)
        flat.index_copy_(1, idx, p.addcdiv_(m, denom, value=-lr / (1 - b1 ** t)))

    def state_dict(self) -> dict:
        """The step count, the drift window and, per grid, which voxels have moments not both zero
        (one bit a voxel), their moments and their last steps (a voxel never read has zero moments):
        exact, never larger than the dense moments by more than the bits and the counters."""
        grids = []
        for m, v, last in zip(self.exp_avg, self.exp_avg_sq, self.last):
            keep = ((m != 0) | (v != 0)).any(dim=0)
            bits = torch.from_numpy(np.packbits(keep.cpu().numpy()))  # which voxels: one bit each
            grids.append({"voxels": int(m.shape[1]), "touched_bits": bits, "exp_avg": m[:, keep].clone(),
                          "exp_avg_sq": v[:, keep].clone(), "last": last[keep].clone()})
        return {"kind": "lazy_grid_adam", "step": self.step_count, "grids": grids,
                "drift": {"base": self.w_base, "w": torch.from_numpy(self.w.copy())},
                "mlp": self.mlp.state_dict() if self.mlp else None}

    def load_state_dict(self, state: dict) -> None:
        if state.get("kind") != "lazy_grid_adam":
            raise InputError("the checkpoint's optimizer state is from the dense-Adam trainer (before the lazy "
                             "grid optimizer); start the run again with another --out")
        if [g["voxels"] for g in state["grids"]] != [m.shape[1] for m in self.exp_avg]:
            raise InputError("the checkpoint's optimizer state does not match its grids")
        self.step_count = int(state["step"])
        for m, v, last, g in zip(self.exp_avg, self.exp_avg_sq, self.last, state["grids"]):
            touched = np.unpackbits(g["touched_bits"].numpy(), count=m.shape[1]).astype(bool)
            index = torch.from_numpy(touched.nonzero()[0]).to(m.device)
            m.zero_().index_copy_(1, index, g["exp_avg"].to(m))
            v.zero_().index_copy_(1, index, g["exp_avg_sq"].to(v))
            # (a checkpoint from before the catch-up has no last steps: its voxels count as updated now)
            last.zero_().index_copy_(0, index, g["last"].to(last) if "last" in g
                                     else torch.full((index.numel(),), self.step_count, dtype=last.dtype))
        drift = state.get("drift")
        self.w_base, self.w = (int(drift["base"]), drift["w"].numpy().copy()) if drift else \
            (self.step_count, np.zeros(1))
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
