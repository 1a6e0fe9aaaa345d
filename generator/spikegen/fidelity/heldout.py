"""Held-out evidence of ``spikegen diagnose``: one proper score of the held-out frames, the
static pixels of a recording without a reference, and the choice among nested models.

The score is a log-likelihood (nats per pixel) of two things measured on the held-out frames,
under the predictive distributions a sensor's simulation gives them:

1. each pixel's inter-spike intervals, whole frames:

   * without modulation (the common case: ``"self"`` on a still scene, or a still radiance), on
     every judged pixel with a static reference (``K = 1``), and with a reference that changes
     (``K > 1``: sub-frames, or ``"self"`` on an image that moves) on the judged pixels whose
     reference varies by at most :data:`QUASI_STILL` of its mean (:func:`quasi_still`), the log
     probability of each interval's value under the simulated intervals of the pixel's pool
     (:class:`IntervalPool`): the :data:`POOL_PIXELS` such pixels whose drive under the model (its
     charge per frame in thresholds, ``R (I X / 256 + d)`` with the model's maps and ``X``'s mean
     over the sub-frames, before the readout makes whole-frame intervals of it) is nearest its own
     (:func:`pool_groups`). The pool's probability of a value is its simulated intervals of that
     value plus one pseudo-interval spread as a Gaussian of the pixel's own simulated mean and the
     pool's variance about its pixels' means plus one frame^2 (with it the simulated values no
     pixel kept: those more than 2 frames below or 3 above its mean), over the pool's intervals
     plus one;
   * otherwise (a modulated model, or a pixel whose reference changes more) a Gaussian density,
     mean and variance those of the simulated intervals of the pixel (whole run), the variance
     with the mean's sampling error and at least :data:`VAR_FLOOR`; which pixels are pooled
     depends on the reference alone, so every model scores a pixel alike;
2. each pixel's spike counts in windows of ``w`` frames, averaged over the window lengths
   :data:`WINDOWS` that fit in the held-out part, Gaussian densities:

   * mean ``m[j, p]``: the simulated rate of pixel ``p`` over the whole run times ``w`` times,
     without modulation, the window's population factor ``F[j]`` (``K = 1``: simulated spikes
     of held-out window ``j`` over their mean) or the reference's course (``K > 1``: the model's
     drive ``I X(t) / 256 + d`` over window ``j`` over its mean over the run,
     :class:`ReferenceCourse`); with a modulated model (its flicker), the modulation's mean over
     the window (``K = 1``), or the simulated count itself (``K > 1``);
   * variance: without modulation, that of the simulated counts of the pixel in windows of ``w``
     frames over the whole run about their mean (:func:`count_variance`; ``K > 1``: about the
     reference's course), averaged over the :data:`POOL_PIXELS` judged pixels of
     nearest simulated rate (:func:`pooled_count_variance`), at least :data:`VAR_FLOOR`, times
     ``1 + w / T`` for the noise of the simulated rate; with modulation, the pixel's own
     (:func:`count_variance`) times ``1 + w / T`` (``K = 1``), or twice it (``K > 1``: the mean is
     one draw).

Why intervals are scored by the probability of their whole-frame value, pooled (until 2026-11-26
they were scored like the other cases, a Gaussian of each pixel's own simulated mean and
variance, at least a twelfth of a frame^2): the whole-frame intervals of an integrate-and-fire
pixel take the two whole numbers around its mean interval, in a proportion set by the mean's
fractional part. The temporal noise of a real sensor (N_e ~ 2e4) adds a few thousandths of a
frame^2 to their variance, less than one pixel's sample variance varies from one simulation to
the next, so a model with noise paid for the noise of its plug-in variances more than it gained;
and the floor gave the ideal sensor and a noisy model the same variance exactly where they
differ most: a pixel whose mean interval is within a few hundredths of a whole frame fires at that
interval every time on the ideal sensor, and only temporal noise gives it the occasional interval
a frame longer or shorter. On seeded recordings at the car's rates with shot noise of N_e = 1.38e4
the old score put the true model 0.014 nats per pixel below the ideal sensor (z -17); and a Gaussian
density read at whole numbers is not a distribution on them. The log probability of a discrete
outcome is a strictly proper score, a pool of 64 pixels gives each
value's probability from some 64 times the intervals, and every effect in the catalogue acts on a
pixel's intervals through its drive (gain, dark current, hot pixels, columns) or through what the
readout and the noise make of it (shot noise, the threshold jitter, a reset to zero), so the pool
is the model's distribution at that drive. Pooled by the drive rather than by the simulated mean
interval: a model whose intervals never vary (a reset to zero without noise) gives every pixel one
whole value, and where the fitted rate is a little off that value is a frame wrong; pixels of like
drive near such a step hold both values, pixels of like simulated mean only one (each such interval
then cost some 9 nats, and a true reset to zero beside hot pixels was dropped). The same seeded
recordings now score the true model above the ideal one, and a recording of the ideal sensor the
ideal sensor above the noisy ones (``tests/test_diagnose_heldout_pool.py``).

A reference that changes (``K > 1``) kept the Gaussian of each pixel's own intervals, and its
counts were predicted by one simulated draw with twice the variance, until a second change of
2026-11-26: on seeded recordings of sub-frames with a moving bar the true shot noise scored at
z -0.34 and -0.19 against the ideal sensor and the preset's noise on its own recording at z -2.4
(the same tests). The pixels such a reference leaves nearly still are pooled as with a still one;
the counts of every judged pixel follow the reference's course in time (exact for the effects
that act on the drive, approximate for the nonlinear ones, whose simulated counts then vary more
about it, which their predictive variance carries).

Intervals see temporal noise and the readout, counts see rates and modulation. The Gaussian
log density is a proper scoring rule for the mean and variance it is given, so a model scores
best in expectation when its predictive mean and variance are the true ones; the log probability
of the intervals' values is proper for their whole distribution.

A model whose light is modulated in time (the sensor's flicker, :class:`Modulation`) is scored
on its own clock: pixel ``p`` integrates ``f_p(t) = 1 + s_p (phi(t) - 1)`` (``phi`` the flicker
factor, ``s_p`` the light's share of the pixel's rate), so its intervals are measured in the
time ``tau_p(t) = sum_{u <= t} f_p(u)`` (both the simulated ones that give the predictive mean
and variance and the measured ones that are scored, plus ``log f_p`` at each interval's end: the
change of variables, so that scores on different clocks compare), and its window counts are
predicted as ``w rate_p`` times the window's mean ``f_p`` over the run's, their variance that of
the simulated counts about that prediction. Otherwise the slow modulation would count as
interval and count variance of every pixel, and a model that adds temporal noise to it would
score worse the better it is.

Model choice: starting from every effect the gates pass, the effect whose removal costs the
least is removed while that cost is at most its penalty (:func:`penalty`: Akaike's, one nat
per scalar parameter; the maps were fitted on other frames, so only the choice itself is
optimistic) or under ``MIN_Z`` standard errors (from the spread of the per-pixel differences).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from ..sensor import interpolation_weights
from . import stats

WINDOWS = (4, 16, 64)  # window lengths of the scored counts, frames
MIN_Z = 2.0  # an effect must improve the score by this many standard errors
VAR_FLOOR = 1.0 / 12.0  # least predictive variance of an interval (frames^2) or a count (a frame's rounding)
POOL_PIXELS = 64  # intervals (counts: a static reference) are predicted from this many pixels of like drive (rate)
QUASI_STILL = 0.1  # a changing reference: a pixel's intervals are pooled where its reference varies by at most this share
STATIC_DISPERSION = 30.0  # chi-square (7 d.o.f.) of 8 segment counts above which a pixel moves
STATIC_P = 1e-4  # a static pixel's segment mean intervals disagree beyond this chance
MEASURE = ("log-likelihood of the held-out per-pixel intervals (their whole-frame values among a pool of "
           "pixels' simulated ones; with modulated light, or where a changing reference changes a pixel's "
           "light, Gaussian) and spike counts "
           f"(Gaussian; windows of {'/'.join(map(str, WINDOWS))} frames) under each model's simulation, nats per pixel")
# scalar parameters each effect adds to the model (the penalty, nats, of keeping it)
PARAMETERS = {"gain_nonuniformity": 1, "column_pattern": 1, "dark_current": 2, "hot_pixels": 1, "shot_noise": 1,
              "reset_to_zero": 1, "refractory": 1, "flicker": 3, "crosstalk": 1, "nonlinearity": 1,
              "dead_pixels": 1, "threshold_jitter": 1}


@dataclass(frozen=True, eq=False)
class Modulation:
    """The light modulation a model applies: ``phi [T]`` per frame (the sensor's flicker factor)
    and ``share [P]`` the light's share of each pixel's rate (dark current is not modulated)."""

    phi: np.ndarray
    share: np.ndarray

    def factor(self, t: np.ndarray, pix: np.ndarray) -> np.ndarray:
        """``f_p(t)`` at frames ``t`` of pixels ``pix`` (same shape)."""
        return 1.0 + self.share[pix] * (self.phi[t] - 1.0)

    def clock(self, t: np.ndarray, pix: np.ndarray) -> np.ndarray:
        """``tau_p(t) = sum_{u <= t} f_p(u)``, frames, at frames ``t`` of pixels ``pix``."""
        cum = np.cumsum(self.phi)
        return (t + 1.0) + self.share[pix] * (cum[t] - (t + 1.0))

    def window_factor(self, w: int, start: int, n: int) -> np.ndarray:
        """``[n, P]`` mean ``f_p`` over ``n`` consecutive windows of ``w`` frames from frame
        ``start``, over the mean ``f_p`` of the whole run."""
        phi_w = self.phi[start: start + n * w].reshape(n, w).mean(axis=1)
        run = 1.0 + self.share * (float(self.phi.mean()) - 1.0)
        return (1.0 + self.share[None, :] * (phi_w[:, None] - 1.0)) / run[None, :]


def model_modulation(sensor, radiance: np.ndarray, intensity: float, frames: int) -> Modulation | None:
    """The :class:`Modulation` of ``sensor`` (its flicker) seeing ``radiance [K, H, W]``; None
    without flicker. The light share uses the mean radiance and the sensor's maps (its gamma and
    crosstalk are left out of the share)."""
    if sensor.flicker_depth <= 0:
        return None
    K, H, W = radiance.shape
    R, d = sensor.maps(H, W)
    light = intensity / 256.0 * radiance.mean(axis=0)
    share = (light / np.maximum(light + d, 1e-12)).reshape(-1)
    t = np.arange(frames, dtype=np.float64)
    phi = 1.0 + sensor.flicker_depth * np.sin(2 * np.pi * t / sensor.flicker_period_frames)
    return Modulation(phi, share)


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
    return _window_counts(spikes, w).astype(np.float64)


def _window_counts(spikes: np.ndarray, w: int) -> np.ndarray:
    """:func:`window_counts` as ``int32`` (NumPy's ``var`` of whole numbers in ``int32`` takes the same
    float64 steps as of them in float64, without the copy)."""
    n = spikes.shape[0] // w
    return spikes[: n * w].reshape(n, w, -1).sum(axis=1, dtype=np.int32)


def count_variance(simulated: np.ndarray, w: int, static_reference: bool,
                   modulation: "Modulation | ReferenceCourse | None" = None, floor: float = VAR_FLOOR) -> np.ndarray:
    """``[P]`` predictive variance of a pixel's count in ``w`` frames: the variance of the
    simulated counts over the windows of the whole run (``K = 1``), or half the variance of the
    differences of consecutive windows (``K > 1``: the scene moves the mean); with a
    ``modulation`` (a :class:`Modulation`, or the :class:`ReferenceCourse` of these pixels), the
    variance about ``w rate`` times its window factor, whatever ``static_reference`` says; at
    least :data:`VAR_FLOOR` (a pixel whose count never varies; ``floor`` instead where given).
    Windows longer than a twelfth of the run scale from that length (renewal: the variance grows
    with the window)."""
    T = simulated.shape[0]
    wv = min(w, max(T // 12, 1))
    s = _window_counts(simulated, wv)
    if modulation is not None:
        rate = simulated.reshape(T, -1).sum(axis=0, dtype=np.int64) / T
        v = ((s - wv * rate[None, :] * modulation.window_factor(wv, 0, s.shape[0])) ** 2).sum(axis=0) / (s.shape[0] - 1)
    elif static_reference:
        v = s.var(axis=0, ddof=1)
    else:
        v = np.diff(s, axis=0).var(axis=0, ddof=1) / 2.0
    return np.maximum(v * (w / wv), floor)


def pooled_count_variance(raw: np.ndarray, rate: np.ndarray, mask: np.ndarray, w: int, T: int) -> np.ndarray:
    """``[P]`` predictive variance of a pixel's held-out count in ``w`` frames with a static
    reference: the :func:`count_variance` of the simulation without its floor (``raw``) pooled
    over ``mask`` by simulated ``rate`` (:func:`pooled_variance`), at least :data:`VAR_FLOOR`,
    times ``1 + w / T`` for the noise of the simulated rate."""
    return np.maximum(pooled_variance(rate, raw, np.ones_like(raw), mask), VAR_FLOOR) * (1.0 + w / T)


class ReferenceCourse:
    """A changing reference's course in time under a model: pixel ``p``'s drive in frame ``t`` over
    its mean over the run, ``f_p(t) = D_p(t) / mean_u D_p(u)`` with ``D = I X(t) / 256 + d`` (the
    gain ``R`` cancels; ``X(t)`` interpolated between the sub-frames as the simulation does,
    sensor.interpolation_weights)."""

    def __init__(self, X: np.ndarray, intensity: float, dark: np.ndarray, frames: int):
        K = X.shape[0]
        self.weights = interpolation_weights(K, frames)  # [T, K]
        self.X = np.asarray(X, dtype=np.float64).reshape(K, -1)
        self.scale = intensity / 256.0
        self.dark = np.asarray(dark, dtype=np.float64).reshape(-1)
        self.mean = self.scale * (self.weights.mean(axis=0) @ self.X) + self.dark

    def part(self, sl: slice) -> "ReferenceCourse":
        """The course of the pixels ``sl`` alone (views of the same arrays)."""
        out = object.__new__(ReferenceCourse)
        out.weights, out.scale = self.weights, self.scale
        out.X, out.dark, out.mean = self.X[:, sl], self.dark[sl], self.mean[sl]
        return out

    def window_factor(self, w: int, start: int, n: int) -> np.ndarray:
        """``[n, P]`` mean ``f_p`` over ``n`` consecutive windows of ``w`` frames from frame
        ``start`` (1 where the mean drive is 0), as :meth:`Modulation.window_factor`."""
        Wn = self.weights[start: start + n * w].reshape(n, w, -1).mean(axis=1)
        drive = self.scale * (Wn @ self.X) + self.dark[None, :]
        return np.where(self.mean > 0, drive / np.where(self.mean > 0, self.mean, 1.0), 1.0)


def quasi_still(X: np.ndarray) -> np.ndarray:
    """``[P]`` bool: the pixels whose reference ``X [K, H, W]`` varies over its ``K`` sub-frames by at
    most :data:`QUASI_STILL` of its mean (every pixel with ``K = 1``). It reads the reference alone,
    so every model's score treats a pixel alike (pooled or by its own Gaussian)."""
    X = np.asarray(X, dtype=np.float64)
    X = X.reshape(X.shape[0], -1)
    if X.shape[0] == 1:
        return np.ones(X.shape[1], dtype=bool)
    return X.max(axis=0) - X.min(axis=0) <= QUASI_STILL * X.mean(axis=0)


def finish_score(per_pixel: np.ndarray, mask: np.ndarray) -> HeldOutScore:
    """The :class:`HeldOutScore` of the pixels of ``mask [P]`` from every pixel's nats ``[P]``."""
    per_pixel = np.where(mask, per_pixel, 0.0)
    return HeldOutScore(float(per_pixel[mask].mean()) if mask.any() else 0.0, per_pixel)


def _count_loglik(measured, simulated, w: int, static_reference: bool,
                  modulation: Modulation | None = None) -> np.ndarray:
    """``[P]`` summed log density of the held-out window counts of length ``w`` with a reference
    that changes, or a static one and a ``modulation`` (a static reference without one:
    :func:`count_loglik_given`, the variances pooled)."""
    Th, T = measured.shape[0], simulated.shape[0]
    c, s = window_counts(measured, w), window_counts(simulated[T - Th:], w)
    if static_reference and modulation is not None:
        rate = simulated.reshape(T, -1).sum(axis=0, dtype=np.int64) / T
        m = w * rate[None, :] * modulation.window_factor(w, T - Th, c.shape[0])
        v = count_variance(simulated, w, True, modulation) * (1.0 + w / T)
    else:
        m = s
        v = 2.0 * count_variance(simulated, w, False)  # m is one draw
    return (-0.5 * (np.log(2 * np.pi * v) + (c - m) ** 2 / v)).sum(axis=0)


def count_loglik_given(c: np.ndarray, factor: np.ndarray, rate: np.ndarray, w: int, v: np.ndarray) -> np.ndarray:
    """``[P]`` summed log density of the measured window counts ``c [n, P]`` without modulation:
    means ``w rate [P]`` times ``factor``, ``[n]`` (a static reference: the window's population
    factor, the simulated spikes of the window over the mask over their mean) or ``[n, P]`` (a
    reference that changes: its course, :class:`ReferenceCourse`), variances ``v [P]``."""
    factor = np.asarray(factor, dtype=np.float64)
    m = (factor[:, None] if factor.ndim == 1 else factor) * (w * rate)[None, :]
    return (-0.5 * (np.log(2 * np.pi * v) + (c - m) ** 2 / v)).sum(axis=0)


def pooled_variance(key: np.ndarray, var: np.ndarray, weight: np.ndarray, mask: np.ndarray,
                    size: int = POOL_PIXELS) -> np.ndarray:
    """``[P]`` ``var`` with each pixel of ``mask`` (and a finite ``key`` and ``var``) given the
    ``weight``-weighted mean of ``var`` over its group of :func:`pool_groups`; other pixels keep
    their own."""
    var = np.asarray(var, dtype=np.float64)
    out = var.copy()
    group, groups = pool_groups(key, np.asarray(mask, dtype=bool) & np.isfinite(var), size)
    pooled = group >= 0
    if not pooled.any():
        return out
    g = group[pooled]
    w = np.asarray(weight, dtype=np.float64)[pooled]
    w = np.where(w > 0, w, 0.0)
    sw = np.bincount(g, weights=w, minlength=groups)
    sv = np.bincount(g, weights=w * var[pooled], minlength=groups)
    plain = np.bincount(g, weights=var[pooled], minlength=groups) / np.bincount(g, minlength=groups)
    mean = np.where(sw > 0, sv / np.where(sw > 0, sw, 1.0), plain)
    out[pooled] = mean[g]
    return out


def pool_groups(key: np.ndarray, mask: np.ndarray, size: int = POOL_PIXELS) -> tuple[np.ndarray, int]:
    """``(group [P], groups)``: the pixels of ``mask`` with a finite ``key`` sorted by it and cut
    into consecutive groups of ``size`` (the last ones one larger where the count does not divide);
    -1 for the other pixels."""
    ok = np.asarray(mask, dtype=bool) & np.isfinite(key)
    idx = np.flatnonzero(ok)
    group = np.full(np.asarray(key).size, -1, dtype=np.int64)
    if idx.size == 0:
        return group, 0
    order = idx[np.argsort(key[idx], kind="stable")]
    groups = max(order.size // max(int(size), 1), 1)
    group[order] = (np.arange(order.size) * groups) // order.size
    return group, groups


OFFSETS = 6  # whole-frame interval values kept per pixel: floor(mean) - 2 ... floor(mean) + 3


class IntervalPool:
    """The interval part of the held-out score without modulation, band by band: a pixel's
    held-out intervals scored by the log probability of each whole-frame value under its pool's
    simulated intervals (module text).

    :meth:`add` keeps, for the pixels of a band, the model's interval moments and counts of its
    simulated and of the recording's held-out intervals at the :data:`OFFSETS` whole values from
    ``floor(mean) - 2`` (the simulated mean), the rest of the simulated ones as a count and the
    recording's others as values; :meth:`finish` pools the pixels of ``mask`` by a key (the
    model's drive, :func:`pool_groups`) and returns each pixel's summed log probability ``[P]``."""

    def __init__(self, P: int, frames: int):
        self.P, self.frames = P, frames
        self.mean, self.var, self.n = np.full(P, np.nan), np.full(P, np.nan), np.zeros(P)
        self.base = np.zeros(P, dtype=np.int64)
        self.sim = np.zeros((P, OFFSETS))
        self.meas = np.zeros((P, OFFSETS))
        self.other_pix, self.other_x = [], []

    def add(self, sl: slice, sim_intervals: tuple, sim_moments: tuple, held_intervals: tuple) -> None:
        """Pixels ``sl``: ``(values, pixels)`` of the simulated intervals (whole run) and of the
        recording's held-out ones (pixels counted from ``sl.start``), and the simulated moments
        ``(mean, variance, count)``."""
        mean, var, n = (np.asarray(a, dtype=np.float64) for a in sim_moments)
        bp = mean.size
        self.mean[sl], self.var[sl], self.n[sl] = mean, var, n
        base = np.where(np.isfinite(mean), np.floor(np.nan_to_num(mean)) - 2, 0).astype(np.int64)
        self.base[sl] = base
        for table, (x, pix) in ((self.sim, sim_intervals), (self.meas, held_intervals)):
            x = np.asarray(x).astype(np.int64)
            pix = np.asarray(pix).astype(np.int64)
            off = x - base[pix]
            inside = (off >= 0) & (off < OFFSETS) & np.isfinite(mean[pix])
            table[sl] = np.bincount(pix[inside] * OFFSETS + off[inside], minlength=bp * OFFSETS).reshape(bp, OFFSETS)
            if table is self.meas and (~inside).any():
                self.other_pix.append(pix[~inside] + sl.start)
                self.other_x.append(x[~inside])

    def finish(self, mask: np.ndarray, key: np.ndarray | None = None) -> np.ndarray:
        """``key [P]``: what the pools are made by, in its order (default: the simulated mean interval)."""
        P, T = self.P, self.frames
        group, G = pool_groups(self.mean if key is None else key, mask)
        inpool = group >= 0
        gi = group[inpool]
        # each pool's simulated intervals: counts at whole values (from its pixels' kept values), its
        # number of intervals and their variance about their pixels' means; the pseudo-interval and
        # the values not kept are spread as a Gaussian of the pixel's own mean and that
        # variance plus a frame^2
        n = np.where(np.isfinite(self.mean), self.n, 0.0)
        mean = np.where(np.isfinite(self.mean), self.mean, T + 1.0)
        dof = np.where(np.isfinite(self.var), np.maximum(n - 1, 0), 0.0)
        N = np.bincount(gi, weights=n[inpool], minlength=G)
        kept = np.bincount(gi, weights=self.sim[inpool].sum(axis=1), minlength=G)
        ss = np.bincount(gi, weights=(np.nan_to_num(self.var) * dof)[inpool], minlength=G)
        sdof = np.bincount(gi, weights=dof[inpool], minlength=G)
        sd = np.sqrt(np.where(sdof > 0, ss / np.where(sdof > 0, sdof, 1.0), 0.0) + 1.0)  # the pseudo-interval's
        spread = 1.0 + (N - kept)
        stride = T + 2 * OFFSETS + 64
        own_sd = np.sqrt(np.nan_to_num(self.var, nan=0.0) + 1.0)  # a pixel in no pool: its own, plus a frame^2
        values = self.base[:, None] + np.arange(OFFSETS)[None, :]
        keys = (group[:, None] * stride + values + 32)[inpool].reshape(-1)
        uk, inv = np.unique(keys, return_inverse=True)
        counts = np.bincount(inv, weights=self.sim[inpool].reshape(-1))

        def logp(g, x, p):
            """log probability of whole-frame intervals ``x`` of pixels ``p`` in pools ``g`` (-1: none)."""
            g = np.asarray(g, dtype=np.int64)
            x = np.asarray(x, dtype=np.float64)
            has = g >= 0
            gg = np.where(has, g, 0)
            c = np.zeros(x.size)
            if uk.size:
                k = gg * stride + x.astype(np.int64) + 32
                pos = np.minimum(np.searchsorted(uk, k), uk.size - 1)
                c = np.where(has & (uk[pos] == k), counts[pos], 0.0)
            m = mean[p]
            s = np.where(has, sd[gg] if G else 1.0, own_sd[p])
            # the Gaussian's mass on a whole frame, as its density at the frame (s >= 1: the sum over
            # whole frames is 1 within 1e-8), in logs so that a far interval costs what it should
            log_phi = -0.5 * ((x - m) / s) ** 2 - np.log(s * math.sqrt(2 * math.pi))
            tot = np.where(has, N[gg] if G else 0.0, 0.0)
            w = np.where(has, spread[gg] if G else 1.0, 1.0)
            with np.errstate(divide="ignore"):
                return np.logaddexp(np.log(c), np.log(w) + log_phi) - np.log(tot + 1.0)

        out = np.zeros(P)
        pix, off = np.nonzero(self.meas)
        x = self.base[pix] + off
        out += np.bincount(pix, weights=self.meas[pix, off] * logp(group[pix], x, pix), minlength=P)
        if self.other_pix:
            op, ox = np.concatenate(self.other_pix), np.concatenate(self.other_x)
            out += np.bincount(op, weights=logp(group[op], ox, op), minlength=P)
        return out


def _interval_loglik(measured, sim_moments: tuple, measured_intervals: tuple | None = None) -> np.ndarray:
    """``[P]`` summed log density of the held-out intervals under a Gaussian of the simulated
    interval mean and variance (``sim_moments``: ``(isi_mean, isi_var, n_isi)`` of stats.pixel_stats,
    or stats.interval_moments), the variance with the mean's sampling error and at least
    :data:`VAR_FLOOR`. ``measured_intervals``: stats.intervals of ``measured`` if already computed."""
    isi_mean, isi_var, n_isi = sim_moments
    P = isi_mean.size
    x, pix = measured_intervals or stats.intervals(measured)
    n = np.maximum(n_isi, 1)
    mu = np.where(np.isfinite(isi_mean), isi_mean, measured.shape[0] + 1.0)
    var = np.maximum(np.nan_to_num(isi_var, nan=0.0) * (1.0 + 1.0 / n), VAR_FLOOR)
    ll = -0.5 * (np.log(2 * np.pi * var[pix]) + (x - mu[pix]) ** 2 / var[pix])
    return np.bincount(pix, weights=ll, minlength=P)


def _clock_interval_loglik(measured, simulated, modulation: Modulation) -> np.ndarray:
    """``[P]`` as :func:`_interval_loglik`, on the model's clock (:class:`Modulation`): the
    simulated intervals ``tau_p(t1) - tau_p(t0)`` of the whole run give each pixel's mean and
    variance, the measured held-out ones are scored, plus ``log f_p(t1)`` per interval."""
    Th, T = measured.shape[0], simulated.shape[0]
    P = int(np.prod(simulated.shape[1:]))
    pix, t = stats.spike_times(simulated)
    same = pix[1:] == pix[:-1]
    tau = modulation.clock(t, pix)
    mean, var, n = stats.grouped_var((tau[1:] - tau[:-1])[same], pix[1:][same], P, 3)
    mu = np.where(np.isfinite(mean), mean, T + 1.0)
    var = np.maximum(np.nan_to_num(var, nan=0.0) * (1.0 + 1.0 / np.maximum(n, 1)), VAR_FLOOR)
    mpix, mt = stats.spike_times(measured)
    mt = mt + (T - Th)  # frames of the whole run
    keep = mpix[1:] == mpix[:-1]
    mtau = modulation.clock(mt, mpix)
    x, p, end = (mtau[1:] - mtau[:-1])[keep], mpix[1:][keep], mt[1:][keep]
    ll = -0.5 * (np.log(2 * np.pi * var[p]) + (x - mu[p]) ** 2 / var[p]) + np.log(modulation.factor(end, p))
    return np.bincount(p, weights=ll, minlength=P)


def static_pixels(spikes: np.ndarray) -> np.ndarray:
    """``[P]`` bool: pixels whose rate does not change over the recording (:func:`motion_test`)."""
    return motion_test(spikes)[0]


def motion_test(spikes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(static [P], tested [P])``, bool: which pixels could be tested for a change of rate over
    the recording, and which of those passed every test; a pixel that cannot be tested is not
    static (nothing shows that it is).

    1. Counts in 8 equal segments: the dispersion ``sum (c - mean)^2 / (mean + 1)`` at most
       :data:`STATIC_DISPERSION` (a renewal train with interval CV <= 1 gives about 7).
    2. Intervals (:func:`interval_dispersion`): each segment's mean interval ``(last - first) /
       (n - 1)``, which for a regular pixel is exact to a fraction of a frame, agrees across the
       segments within its own error, by three tests each at chance :data:`STATIC_P`: the
       chi-square of all segments, the linear trend over the segments (1 degree of freedom: a
       slow drift, as of an object that moves a few pixels over the recording, spreads over
       the chi-square's degrees of freedom but not over the trend's), and the largest step
       between the segments before and after any boundary (a change late or early in the
       recording). A small change of a bright pixel's rate (a bright object over a bright
       background) moves the count by a spike or two, but the mean interval by many standard
       errors. A pixel with fewer than 3 segments of 3 spikes among 8 is tested on 4 segments,
       then on the 2 halves (each with 3 spikes); one that has not even that is not tested.
    3. Interval noise (:func:`_noisier_than_the_rest`): consecutive intervals differ no more than
       the temporal noise of the pixels that passed 1 and 2 lets them.

    A modulation shared by all pixels (stats.shared_variance, as flicker) moves no pixel: when
    one is found the intervals are measured on the population's clock (stats.population_clock)."""
    counts_ok = segment_counts_ok(spikes)
    clock = shared_clock(spikes, counts_ok)
    return motion_verdict(counts_ok, {k: dispersion_on_clock(spikes, k, *clock) for k in MOTION_SEGMENTS})


MOTION_SEGMENTS = (8, 4, 2)  # the segment counts of motion_test's interval tests, in order


def segment_counts_ok(spikes: np.ndarray) -> np.ndarray:
    """``[P]`` test 1 of :func:`motion_test`: the dispersion of the counts in 8 segments."""
    seg = spikes.shape[0] // 8
    c = window_counts(spikes, seg)[:8]
    mean = c.mean(axis=0)
    dispersion = ((c - mean) ** 2).sum(axis=0) / (mean + 1.0)
    return dispersion <= STATIC_DISPERSION


def motion_verdict(counts_ok: np.ndarray, tests: dict) -> tuple[np.ndarray, np.ndarray]:
    """:func:`motion_test` from test 1 and the :func:`interval_dispersion` of each of
    :data:`MOTION_SEGMENTS` (``{segments: dict}``)."""
    P = counts_ok.size
    tested = np.zeros(P, dtype=bool)
    moving = np.zeros(P, dtype=bool)
    for segments in MOTION_SEGMENTS:
        test = tests[segments]
        now = ~tested & (test["dof"] > 0)
        tested |= now
        moving |= now & test["moving"]
        if segments == 8:
            noise = test
    moving |= tested & _noisier_than_the_rest(noise, counts_ok & tested & ~moving)
    return counts_ok & tested & ~moving, tested


def _noisier_than_the_rest(test: dict, reference: np.ndarray) -> np.ndarray:
    """``[P]`` pixels whose intervals vary more from one to the next than the sensor's temporal
    noise lets them: the sample variance of the differences ``d`` of consecutive intervals
    beyond the ``1 - STATIC_P`` quantile of ``(2 c / lambda^2 + 1) chi2_(n-1) / (n - 1)``, with
    ``c`` the median of ``v lambda^2`` (stats.excess_interval_var: shot noise and threshold jitter
    give every pixel the same ``c``) over the ``reference`` pixels, and 1 the most that rounding to
    whole frames gives (a regular pixel's intervals alternate, as 2, 3, 2, 3, at worst). A pixel whose
    rate changes faster than its segments can follow (a texture that passes it) has interval
    differences far beyond that; its own variance, which the segment tests use, holds them and
    hides the change. A sensor whose temporal noise differs from pixel to pixel would show its
    noisiest pixels as moving here."""
    lam, diff_var, n = test["rate"], test["diff_var"], test["n_diff"]
    ok = reference & np.isfinite(diff_var) & (lam > 0)
    if ok.sum() < 20:
        return np.zeros(lam.size, dtype=bool)
    v = np.maximum(diff_var / (1.0 + 1.0 / np.maximum(n, 1)) / 2.0 - 0.25, 0.0)
    c = float(np.median(v[ok] * lam[ok] ** 2))
    expected = 2.0 * c / np.maximum(lam, 1e-12) ** 2 + 1.0
    dof = np.maximum(n - 1, 0).astype(np.int64)
    limit = expected * _chi2_quantile(dof, STATIC_P) / np.maximum(dof, 1)
    return np.isfinite(diff_var) & (dof >= 2) & (diff_var > limit)


def interval_dispersion(spikes: np.ndarray, mask: np.ndarray, segments: int = 8) -> dict:
    """The tests of :func:`motion_test` on the segment mean intervals of each pixel
    (``segments`` equal segments; those with >= 3 spikes), each with variance
    ``((n - 1) v + 1/6) / (n - 1)^2``: ``v = max(var(d) / 2 - 1/4, 0)`` the pixel's interval
    variance beyond rounding from the differences ``d`` of consecutive intervals (which a slow
    change of rate leaves out; stats.excess_interval_var), 1/6 the rounding of the two ends.
    With a modulation shared by the pixels of ``mask [P]`` (at least ``5`` standard errors and a
    relative SD of 0.01 in windows of stats.COMMON_WINDOW frames) times are measured on their
    population's clock, and its counting noise is added to the variance.

    Returns ``{"chi2", "dof", "trend", "step", "moving", "diff_var", "n_diff", "rate"}``, each
    ``[P]``: the chi-square against
    the weighted mean and its degrees of freedom (0 where fewer than ``min(3, segments)``
    segments count: not tested), the squared z of the weighted linear trend over the segment
    index, the largest squared z of the difference of the weighted means before and after a
    boundary, and whether any of the three passes its ``1 - STATIC_P`` quantile (the step's
    with Bonferroni's correction over the ``segments - 1`` boundaries); the sample variance of
    ``d`` (NaN below 3) and its count, and the rate (1 / mean interval, 0 below 3 intervals)."""
    return dispersion_on_clock(spikes, segments, *shared_clock(spikes, mask))


def shared_clock(spikes: np.ndarray, mask: np.ndarray) -> tuple:
    """``(clock [T] or None, its counting variance per frame)`` of :func:`interval_dispersion`: the
    population clock of the pixels of ``mask [P]`` where they share a modulation, else None, 0."""
    shared, se = stats.shared_variance(spikes, mask)
    if not (mask.any() and shared >= 5.0 * se and shared >= 0.01 ** 2):
        return None, 0.0
    T = spikes.shape[0]
    lam = spikes.reshape(T, -1)[:, mask].mean(axis=0, dtype=np.float64)
    return stats.population_clock(spikes, mask), clock_variance(lam)


def clock_variance(lam: np.ndarray) -> float:
    """The population clock's counting variance per frame from the rates ``lam`` of its pixels."""
    return float((lam * (1.0 - lam)).sum() / max(lam.sum(), 1e-12) ** 2)


def dispersion_on_clock(spikes: np.ndarray, segments: int, clock: np.ndarray | None, clock_var: float) -> dict:
    """:func:`interval_dispersion` given :func:`shared_clock` (each pixel's numbers are its own)."""
    P = int(np.prod(spikes.shape[1:]))
    k = int(segments)
    seg = spikes.shape[0] // k
    pix, t = stats.spike_times(spikes)
    tt = t.astype(np.float64) if clock is None else clock[t]
    same = pix[1:] == pix[:-1]
    same2 = same[1:] & same[:-1]
    dd = (tt[2:] - 2 * tt[1:-1] + tt[:-2])[same2]
    _, diff_var, n_d = stats.grouped_var(dd, pix[2:][same2], P, 3)
    v = np.maximum(np.nan_to_num(diff_var / (1.0 + 1.0 / np.maximum(n_d, 1))) / 2.0 - 0.25, 0.0)
    inside = t < k * seg
    key = pix[inside] * k + t[inside] // seg  # sorted: by pixel, then time
    n = np.bincount(key, minlength=k * P)
    ends = np.cumsum(n)
    has = n >= 3
    first, last = np.zeros(k * P), np.zeros(k * P)
    ti, fi = tt[inside], t[inside]
    first[has], last[has] = ti[ends[has] - n[has]], ti[ends[has] - 1]
    span = np.zeros(k * P)
    span[has] = (fi[ends[has] - 1] - fi[ends[has] - n[has]]).astype(np.float64)
    kk = np.maximum(n - 1, 1).astype(np.float64)
    m = ((last - first) / kk).reshape(P, k)
    var = ((kk * np.repeat(v, k) + 1.0 / 6.0 + span * clock_var) / kk ** 2).reshape(P, k)
    w = np.where(has.reshape(P, k), 1.0 / var, 0.0)
    wsum = w.sum(axis=1)
    mbar = (w * m).sum(axis=1) / np.maximum(wsum, 1e-300)
    chi2 = (w * (m - mbar[:, None]) ** 2).sum(axis=1)
    dof = np.maximum(has.reshape(P, k).sum(axis=1) - 1, 0)
    tested = dof >= min(2, k - 1)
    # linear trend: weighted regression of m on the segment index
    idx = np.arange(k, dtype=np.float64)[None, :]
    ibar = (w * idx).sum(axis=1) / np.maximum(wsum, 1e-300)
    sxx = (w * (idx - ibar[:, None]) ** 2).sum(axis=1)
    sxy = (w * (idx - ibar[:, None]) * (m - mbar[:, None])).sum(axis=1)
    trend = np.where(sxx > 0, sxy ** 2 / np.maximum(sxx, 1e-300), 0.0)
    # steps: weighted means before and after each boundary
    cw, cwm = np.cumsum(w, axis=1)[:, :-1], np.cumsum(w * m, axis=1)[:, :-1]
    aw, awm = wsum[:, None] - cw, (w * m).sum(axis=1)[:, None] - cwm
    both = (cw > 0) & (aw > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        diff = cwm / cw - awm / aw
        z2 = np.where(both, diff ** 2 / (1.0 / cw + 1.0 / aw), 0.0)
    step = z2.max(axis=1)
    moving = ((chi2 > _chi2_quantile(dof, STATIC_P)) | (trend > _z2_quantile(STATIC_P))
              | (step > _z2_quantile(STATIC_P / max(k - 1, 1))))
    z = lambda a: np.where(tested, a, 0.0)  # noqa: E731
    mean_isi, _, _ = stats.grouped_var((tt[1:] - tt[:-1])[same], pix[1:][same], P, 3)
    return {"chi2": z(chi2), "dof": np.where(tested, dof, 0), "trend": z(trend), "step": z(step),
            "moving": tested & moving, "diff_var": diff_var, "n_diff": n_d,
            "rate": np.where(np.isfinite(mean_isi), 1.0 / np.maximum(np.nan_to_num(mean_isi), 1e-12), 0.0)}


def _z2_quantile(p: float) -> float:
    """Upper ``p`` quantile of the chi-square law with 1 degree of freedom (a squared standard
    normal, two-sided)."""
    return NormalDist().inv_cdf(1.0 - p / 2.0) ** 2


def _chi2_quantile(dof: np.ndarray, p: float) -> np.ndarray:
    """Upper ``p`` quantile of the chi-square law with ``dof`` degrees of freedom (Wilson and
    Hilferty's cube-root approximation; infinite where ``dof`` is 0)."""
    z = {1e-4: 3.7190}[p]  # the standard normal's upper quantile
    k = np.maximum(np.asarray(dof, dtype=np.float64), 1.0)
    q = k * (1.0 - 2.0 / (9.0 * k) + z * np.sqrt(2.0 / (9.0 * k))) ** 3
    return np.where(np.asarray(dof) > 0, q, np.inf)


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
