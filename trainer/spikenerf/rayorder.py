"""``--ray-order shuffled``: every (view, pixel) once an epoch, in a seeded order.

The default draw (``uniform``, train.Batch.draw) picks each ray's view and pixel independently, with
replacement, so after ``e`` epochs' worth of rays (``e`` = rays drawn / (views x pixels)) a pixel has
been drawn a Poisson(``e``) number of times: after one epoch 37 % of the pixels not at all. At
400 x 400 a run of the default 9000 iterations draws about 1.15 epochs of a 100-view dataset.
``shuffled`` draws the same rays in a random order instead (random reshuffling): the run's ray
``r = iteration x rays a step + j`` is, in epoch ``e = r div M`` (``M`` = views x pixels), the
``pi_e(r mod M)``-th ray of the dataset (flat index ``view x pixels + pixel``), where ``pi_e`` is a
permutation of ``[0, M)`` keyed by the run's seed and ``e``. So each epoch visits every ray once,
and a ray's place depends only on the seed, the iteration and ``j``: a resumed run draws what an
uninterrupted one draws, on any device.

``pi_e`` is a four-round Feistel network on the smallest even number of bits that holds ``M`` (so on
at most ``4 M`` values), restricted to ``[0, M)`` by cycle walking (a value that lands at or above
``M`` is put through the network again until it lands below: a permutation of ``[0, M)``, since the
network is one of its whole domain). The round keys come from ``numpy.random.SeedSequence([seed,
epoch, round])``.
"""
from __future__ import annotations

import functools

import numpy as np
import torch

ROUNDS = 4


@functools.lru_cache(maxsize=8)
def _round_keys(seed: int, epoch: int) -> tuple[int, ...]:
    """The network's round keys for one epoch (cached: every step of an epoch uses the same)."""
    return tuple(int(np.random.SeedSequence([int(seed), int(epoch), i]).generate_state(1)[0]) & 0x7FFFFFFF
                 for i in range(ROUNDS))


def _feistel(x: torch.Tensor, half: int, keys: tuple[int, ...]) -> torch.Tensor:
    """One pass of the network over values ``x`` (int64) of ``2 * half`` bits."""
    mask = (1 << half) - 1
    left, right = x >> half, x & mask
    for k in keys:  # the round function: a multiply-xorshift hash of the right half and the key
        h = (right ^ k) * 0x2545F491
        h = (h ^ (h >> 15)) * 0x2C1B3C6D
        h = h ^ (h >> 12)
        left, right = right, left ^ (h & mask)
    return (left << half) | right


def permute(q: torch.Tensor, total: int, seed: int, epoch: int) -> torch.Tensor:
    """``pi_epoch(q)`` for values ``q`` (int64) in ``[0, total)``: the seeded permutation of ``[0, total)``."""
    half = max(1, (max(1, (total - 1).bit_length()) + 1) // 2)
    keys = _round_keys(seed, epoch)
    y = _feistel(q, half, keys)
    while True:
        bad = y >= total
        if not bool(bad.any()):
            return y
        y[bad] = _feistel(y[bad], half, keys)


def shuffled_rays(start: int, n: int, total: int, seed: int) -> torch.Tensor:
    """Flat ray indices ``[n]`` (view x pixels + pixel, on the CPU) of the run's rays ``start`` to
    ``start + n - 1`` over a dataset of ``total`` rays."""
    if total < 1:
        raise ValueError(f"no rays to draw from (total {total})")
    r = torch.arange(start, start + n, dtype=torch.int64)
    epoch, q = torch.div(r, total, rounding_mode="floor"), r % total
    out = torch.empty_like(q)
    for e in range(start // total, (start + n - 1) // total + 1):  # at most two epochs a step unless n > total
        sel = epoch == e
        out[sel] = permute(q[sel], total, seed, e)
    return out
