"""Held-out evidence of ``spikegen diagnose``: one proper score of the held-out frames, the
static pixels of a recording without a reference, and the choice among nested models.

The score is a Gaussian log-likelihood (nats per pixel) of two things measured on the
held-out frames, under the predictive distributions a sensor's simulation gives them:

1. each pixel's inter-spike intervals: mean and variance those of the simulated intervals of
   the pixel (whole run), plus 1/12 (a frame's rounding) and the mean's sampling error;
2. each pixel's spike counts in windows of ``w`` frames, averaged over the window lengths
   :data:`WINDOWS` that fit in the held-out part:

   * mean ``m[j, p]``: for a static reference ``K = 1``, the simulated rate of pixel ``p``
     over the whole run times ``w`` times the window's population factor ``F[j]`` (simulated
     spikes of held-out window ``j`` over their mean: flicker and other modulation common to
     all pixels); for a reference that changes (``K > 1``) the simulated count itself;
   * variance: that of the simulated counts of the pixel in windows of ``w`` frames over the
     whole run (:func:`count_variance`), with ``K = 1`` times ``1 + w / T`` for the noise of
     the simulated rate, with ``K > 1`` twice it (the mean is one draw).

Intervals see temporal noise and the readout, counts see rates and modulation. The Gaussian
log density is a proper scoring rule for the mean and variance it is given, so a model scores
best in expectation when its predictive mean and variance are the true ones.

Model choice: starting from every effect the gates pass, the effect whose removal costs the
least is removed while that cost is at most its penalty (:func:`penalty`: Akaike's, one nat
per scalar parameter; the maps were fitted on other frames, so only the choice itself is
optimistic) or under ``MIN_Z`` standard errors (from the spread of the per-pixel differences).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import stats

WINDOWS = (4, 16, 64)  # window lengths of the scored counts, frames
MIN_Z = 2.0  # an effect must improve the score by this many standard errors
STATIC_DISPERSION = 30.0  # chi-square (7 d.o.f.) of 8 segment counts above which a pixel moves
MEASURE = ("Gaussian log-likelihood of the held-out per-pixel intervals and spike counts (windows of "
           f"{'/'.join(map(str, WINDOWS))} frames) under each model's simulation, nats per pixel")
# scalar parameters each effect adds to the model (the penalty, nats, of keeping it)
PARAMETERS = {"gain_nonuniformity": 1, "column_pattern": 1, "dark_current": 2, "hot_pixels": 1, "shot_noise": 1,
              "reset_to_zero": 1, "refractory": 1, "flicker": 3, "crosstalk": 1, "nonlinearity": 1,
              "dead_pixels": 1}


@dataclass(frozen=True, eq=False)
class HeldOutScore:
    """``mean``: nats per pixel of the mask; ``per_pixel [P]``: each pixel's nats (0 outside the mask)."""

    mean: float
    per_pixel: np.ndarray

    def improvement(self, other: "HeldOutScore") -> tuple[float, float]:
        """``(total nats gained over other, its standard error)``."""
        d = self.per_pixel - other.per_pixel
        return float(d.sum()), float(math.sqrt(d.size) * d.std())


def window_lengths(held_frames: int) -> list:
    """The lengths of :data:`WINDOWS` with at least two windows in ``held_frames`` (or one half)."""
    out = [w for w in WINDOWS if 2 * w <= held_frames]
    return out or [max(held_frames // 2, 1)]


def window_counts(spikes: np.ndarray, w: int) -> np.ndarray:
    """``[n, P]`` spikes of each pixel in consecutive windows of ``w`` frames of ``spikes [T, H, W]``."""
    n = spikes.shape[0] // w
    flat = spikes[: n * w].reshape(n, w, -1)
    return flat.sum(axis=1, dtype=np.int32).astype(np.float64)


def count_variance(simulated: np.ndarray, w: int, static_reference: bool) -> np.ndarray:
    """``[P]`` predictive variance of a pixel's count in ``w`` frames: the variance of the
    simulated counts over the windows of the whole run (``K = 1``), or half the variance of the
    differences of consecutive windows (``K > 1``: the scene moves the mean); plus 1/12, the
    rounding of a count. Windows longer than a twelfth of the run scale from that length
    (renewal: the variance grows with the window)."""
    T = simulated.shape[0]
    wv = min(w, max(T // 12, 1))
    s = window_counts(simulated, wv)
    if static_reference:
        v = s.var(axis=0, ddof=1)
    else:
        v = np.diff(s, axis=0).var(axis=0, ddof=1) / 2.0
    return v * (w / wv) + 1.0 / 12.0


def score(measured: np.ndarray, simulated: np.ndarray, sim_stats: stats.PixelStats, mask: np.ndarray,
          static_reference: bool) -> HeldOutScore:
    """The held-out score of ``measured [Th, H, W]`` under ``simulated [T, H, W]`` (the whole run,
    whose last ``Th`` frames are the held-out ones) with interval statistics ``sim_stats``;
    pixels ``mask [P]``."""
    per_pixel = _interval_loglik(measured, sim_stats)
    lengths = window_lengths(measured.shape[0])
    for w in lengths:
        per_pixel = per_pixel + _count_loglik(measured, simulated, sim_stats, mask, w, static_reference) / len(lengths)
    per_pixel = np.where(mask, per_pixel, 0.0)
    return HeldOutScore(float(per_pixel[mask].mean()) if mask.any() else 0.0, per_pixel)


def _count_loglik(measured, simulated, sim_stats, mask, w: int, static_reference: bool) -> np.ndarray:
    """``[P]`` summed log density of the held-out window counts of length ``w``."""
    Th, T = measured.shape[0], simulated.shape[0]
    c, s = window_counts(measured, w), window_counts(simulated[T - Th:], w)
    if static_reference:
        pop = s[:, mask].sum(axis=1)
        factor = pop / max(pop.mean(), 1e-12)
        rate = simulated.reshape(T, -1).sum(axis=0, dtype=np.int64) / T
        m = factor[:, None] * (w * rate)[None, :]
        v = count_variance(simulated, w, True) * (1.0 + w / T)  # the simulated rate's own noise
    else:
        m = s
        v = 2.0 * count_variance(simulated, w, False)  # m is one draw
    return (-0.5 * (np.log(2 * np.pi * v) + (c - m) ** 2 / v)).sum(axis=0)


def _interval_loglik(measured, sim_stats: stats.PixelStats) -> np.ndarray:
    """``[P]`` summed log density of the held-out intervals under a Gaussian of the simulated
    interval mean and variance (plus 1/12, a frame's rounding, and the mean's sampling error)."""
    P = sim_stats.n.size
    ps = stats.pixel_stats(measured)
    pix = stats.interval_pixels(measured)
    n = np.maximum(sim_stats.n_isi, 1)
    mu = np.where(np.isfinite(sim_stats.isi_mean), sim_stats.isi_mean, measured.shape[0] + 1.0)
    var = np.nan_to_num(sim_stats.isi_var, nan=0.0) * (1.0 + 1.0 / n) + 1.0 / 12.0
    x = ps.isi_values
    ll = -0.5 * (np.log(2 * np.pi * var[pix]) + (x - mu[pix]) ** 2 / var[pix])
    return np.bincount(pix, weights=ll, minlength=P)


def static_pixels(spikes: np.ndarray) -> np.ndarray:
    """``[P]`` bool: pixels whose counts in 8 equal segments of the whole recording agree
    within counting noise (dispersion ``sum (c - mean)^2 / (mean + 1)`` at most
    :data:`STATIC_DISPERSION`; a renewal train with interval CV <= 1 gives about 7)."""
    seg = spikes.shape[0] // 8
    c = window_counts(spikes, seg)[:8]
    mean = c.mean(axis=0)
    dispersion = ((c - mean) ** 2).sum(axis=0) / (mean + 1.0)
    return dispersion <= STATIC_DISPERSION


def penalty(name: str, parameters) -> tuple[float, bool]:
    """``(nats, whether MIN_Z applies)`` of keeping effect ``name``: one nat per scalar parameter
    (:data:`PARAMETERS`), and the z test; hot and dead pixels cost one nat per pixel found (each
    is a parameter, and each is its own evidence, so a z over all pixels does not apply)."""
    if name in ("hot_pixels", "dead_pixels"):
        return float(max(parameters.get("found") or 0, 1)), False
    return float(PARAMETERS[name]), True


def select(names: list, evaluate, penalties: dict) -> tuple[list, dict]:
    """Backward elimination over ``names`` (the effects the gates passed); ``evaluate(set)``
    gives the :class:`HeldOutScore` of the model with those effects, ``penalties[name]`` is
    :func:`penalty`. Returns the kept names and ``{name: (nats gained by keeping it, standard
    error)}`` for every name (for a removed effect, at the step it was removed)."""
    on = list(names)
    current = evaluate(set(on))
    evidence = {}
    while on:
        trials = {n: current.improvement(evaluate(set(on) - {n})) for n in on}
        margin = {n: min(g - penalties[n][0], g - MIN_Z * se if penalties[n][1] else math.inf)
                  for n, (g, se) in trials.items()}
        worst = min(on, key=lambda n: margin[n])
        evidence.update(trials)
        if margin[worst] > 0:
            break
        on.remove(worst)
        current = evaluate(set(on))
    return on, evidence
