"""Slow motion of the whole image over a recording, and interval statistics without it (pure NumPy).

A static scene whose image slides by a few pixels during a recording (the camera or the display
moves) changes the rate of every pixel on an edge or in texture slowly: consecutive intervals
are then positively correlated and vary more than shot noise makes them, which a shot-noise fit
reads as a low N_e (docs/lowlight.md). Here:

- :func:`fit_drift`: the shift of the image along rows (axis 0) or columns (axis 1) in each of
  ``windows`` equal windows of frames, relative to the mean image, from the image's profile
  (the mean over the other axis) in each window, and a quadratic in time through those shifts.
- :func:`stabilised_mean` / :func:`expected_rates`: the image without the motion and each
  pixel's expected rate in every frame under the fitted motion.
- :func:`detrended_intervals`: each pixel's interval variance about a polynomial in time fitted
  to its own intervals, so that a slow change of its rate is left out.
- :func:`window_change_map`: each row's (column's) rate in windows relative to its mean.
- :func:`matched_shot_noise`: the N_e of the shot noise whose simulation has a recording's
  detrended interval variance (:func:`interval_excess`), found by simulating it.
- :func:`image_motion`: the same shift measured band by band on a bands.Stream, with its noise
  floor from interleaved frames and a check that blocks of the frame move alike, for
  ``spikegen diagnose --reference self`` (a whole-image motion moves its reference).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from . import stats


@dataclass(frozen=True)
class DriftFit:
    """Shift of the image along ``axis`` (pixels, positive: content moves to larger indices).

    centres: frame at the centre of each window ``[windows]``; shifts: the measured shift of each
    window relative to the mean image ``[windows]``; coef: the quadratic ``d(t) = c0 + c1 t +
    c2 t^2`` fitted through them (least squares); frames: T; residual_sd: SD of the windows'
    shifts about the quadratic (pixels)."""

    axis: int
    frames: int
    centres: np.ndarray
    shifts: np.ndarray
    coef: np.ndarray
    residual_sd: float

    def shift(self, t=None) -> np.ndarray:
        """``d(t)`` at frames ``t`` (default every frame ``0..T-1``)."""
        t = np.arange(self.frames, dtype=np.float64) if t is None else np.asarray(t, dtype=np.float64)
        return self.coef[0] + self.coef[1] * t + self.coef[2] * t * t

    @property
    def travel(self) -> float:
        """Shift from the first to the last frame of the fitted quadratic (pixels)."""
        d = self.shift(np.array([0.0, self.frames - 1.0]))
        return float(d[1] - d[0])


def shift_profile(profile: np.ndarray, d: float) -> np.ndarray:
    """``profile(i - d)`` by linear interpolation, edge values held outside."""
    i = np.arange(profile.shape[0], dtype=np.float64)
    return np.interp(i - d, i, profile)


def profile_shift(profile: np.ndarray, ref: np.ndarray, max_shift: float = 10.0, step: float = 0.05,
                  margin: int | None = None) -> float:
    """The shift ``d`` (a multiple of ``step`` within ``+-max_shift``) that minimises the squared
    difference of ``profile`` and ``ref(i - d)`` away from the ends (``margin`` entries, default
    ``ceil(max_shift) + 2``, are left out at each end)."""
    n = profile.shape[0]
    margin = int(np.ceil(max_shift)) + 2 if margin is None else margin
    if n <= 2 * margin + 2:
        raise ValueError(f"a profile of {n} entries is too short for shifts up to {max_shift}")
    inner = slice(margin, n - margin)
    grid = np.arange(-max_shift, max_shift + step / 2, step)
    err = [float(((profile - shift_profile(ref, d))[inner] ** 2).sum()) for d in grid]
    return float(grid[int(np.argmin(err))])


def fit_drift(spikes: np.ndarray, axis: int = 0, windows: int = 8, max_shift: float = 10.0) -> DriftFit:
    """The shift of the image of ``spikes [T, H, W]`` along ``axis`` (0: rows, 1: columns) in
    each of ``windows`` equal windows of frames (:func:`profile_shift` of the window's mean
    profile against the whole recording's), and a quadratic in time through them (DriftFit)."""
    T = spikes.shape[0]
    L = T // windows
    if windows < 3 or L < 1:
        raise ValueError(f"{T} frames cannot be split into {windows} >= 3 windows")
    other = 3 if axis == 0 else 2  # [windows, L, H, W]: sum over L and the other image axis
    prof = spikes[: windows * L].reshape(windows, L, *spikes.shape[1:]).sum(axis=(1, other), dtype=np.int64)
    prof = prof.astype(np.float64) / L
    ref = prof.mean(axis=0)
    shifts = np.array([profile_shift(p, ref, max_shift) for p in prof])
    centres = (np.arange(windows) + 0.5) * L - 0.5
    coef = np.polynomial.polynomial.polyfit(centres, shifts, 2)
    res = shifts - np.polynomial.polynomial.polyval(centres, coef)
    return DriftFit(axis, T, centres, shifts, coef, float(np.sqrt(np.mean(res * res))))


def _shift_rows(img: np.ndarray, d: float) -> np.ndarray:
    """``img(r - d, c)`` for ``img [H, W]`` by linear interpolation along rows, edges held."""
    H = img.shape[0]
    r = np.clip(np.arange(H, dtype=np.float64) - d, 0.0, H - 1.0)
    r0 = np.floor(r).astype(np.int64)
    r1 = np.minimum(r0 + 1, H - 1)
    f = (r - r0)[:, None]
    return img[r0] * (1.0 - f) + img[r1] * f


def stabilised_mean(spikes: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``[H, W]`` mean rate of the scene without the motion: the mean over frames of each frame
    moved back by its row shift ``d [T]`` (``frame_t(r + d_t, c)``)."""
    acc = np.zeros(spikes.shape[1:], dtype=np.float64)
    for t in range(spikes.shape[0]):
        acc += _shift_rows(spikes[t].astype(np.float64), -float(d[t]))
    return acc / spikes.shape[0]


def expected_rates(mean_image: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``float64 [T, H, W]``: ``mean_image(r - d_t, c)``, each pixel's rate in frame t when the
    image moves by ``d [T]`` rows."""
    return np.stack([_shift_rows(mean_image, float(x)) for x in d])


def rate_change(expected: np.ndarray) -> np.ndarray:
    """``[P]``: how much the motion changes each pixel's rate, ``(max - min) / mean`` over the
    frames of :func:`expected_rates` ``[T, ...]`` (a pixel the motion hardly changes is near 0)."""
    lam = expected.reshape(expected.shape[0], -1)
    return (lam.max(0) - lam.min(0)) / np.maximum(lam.mean(0), 1e-12)


def window_change_map(spikes: np.ndarray, axis: int = 0, windows: int = 8,
                      expected: np.ndarray | None = None) -> np.ndarray:
    """``[windows, H]`` (axis 0) or ``[windows, W]`` (axis 1): each row's (column's) spike count
    in each window of frames relative to its mean over the windows, minus 1; with ``expected
    [T, H, W]`` rates, relative to the counts they predict instead."""
    T = spikes.shape[0]
    L = T // windows
    other = 3 if axis == 0 else 2  # [windows, L, H, W]: sum over L and the other image axis
    c = spikes[: windows * L].reshape(windows, L, *spikes.shape[1:]).sum(axis=(1, other), dtype=np.int64)
    c = c.astype(np.float64)
    if expected is None:
        e = np.broadcast_to(c.mean(axis=0), c.shape)
    else:
        e = expected[: windows * L].reshape(windows, L, *expected.shape[1:]).sum(axis=(1, other))
    return c / np.maximum(e, 1e-12) - 1.0


def detrended_intervals(spikes: np.ndarray, degree: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(residual variance, lag-1 correlation of the residuals, intervals)``, each ``[P]``: each
    pixel's intervals (frames) less a polynomial of ``degree`` in the time of their middle, fitted
    to that pixel's intervals by least squares: a slow change of the pixel's rate (the image
    moving over it) leaves them. The variance is ``RSS / (n - degree - 1)``, NaN below
    ``degree + 3`` intervals; the correlation is NaN below 4 pairs or without variation."""
    g, r, n, ok, P = _detrended_residuals(spikes, degree)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.bincount(g, weights=r * r, minlength=P) / (n - degree - 1)
    var = np.where(ok, var, np.nan)
    pair = g[1:] == g[:-1]
    a, c, gp = r[:-1][pair], r[1:][pair], g[1:][pair]
    m = np.bincount(gp, minlength=P).astype(np.float64)
    s = [np.bincount(gp, weights=v, minlength=P) for v in (a, c, a * c, a * a, c * c)]
    with np.errstate(invalid="ignore", divide="ignore"):
        ma, mc = s[0] / m, s[1] / m
        va, vc = s[3] / m - ma * ma, s[4] / m - mc * mc
        corr = (s[2] / m - ma * mc) / np.sqrt(va * vc)
    corr = np.where((m >= 4) & (va > 1e-12) & (vc > 1e-12), corr, np.nan)
    return var, corr, n


def detrended_lag_covariance(spikes: np.ndarray, degree: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(residual variance, lag-1 autocovariance of the residuals)``, each ``[P]`` frames**2, of
    the :func:`detrended_intervals` residuals ``r``: ``sum r_i r_{i+1} / (pairs)``; NaN below
    ``degree + 3`` intervals. Unlike the correlation, defined (0) for a pixel whose intervals do
    not vary, so a regular pixel counts in an average as it is."""
    g, r, n, ok, P = _detrended_residuals(spikes, degree)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.bincount(g, weights=r * r, minlength=P) / (n - degree - 1)
        pair = g[1:] == g[:-1]
        cov = np.bincount(g[1:][pair], weights=r[:-1][pair] * r[1:][pair], minlength=P) / (n - 1)
    return np.where(ok, var, np.nan), np.where(ok, cov, np.nan)


def _detrended_residuals(spikes: np.ndarray, degree: int):
    """``(pixel of each interval, its residual, intervals per pixel [P], enough [P], P)`` of
    :func:`detrended_intervals` (pixel-major order, so a pixel's intervals are consecutive)."""
    P = int(np.prod(spikes.shape[1:]))
    pix, t = stats.spike_times(spikes)
    same = pix[1:] == pix[:-1]
    g = pix[1:][same]
    isi = (t[1:] - t[:-1])[same].astype(np.float64)
    mid = 0.5 * (t[1:] + t[:-1])[same].astype(np.float64) / max(spikes.shape[0], 1)  # in [0, 1]
    k = degree + 1
    n = np.bincount(g, minlength=P).astype(np.float64)
    # normal equations per pixel: A [P, k, k] c = b [P, k]
    pw = [np.bincount(g, weights=mid ** j, minlength=P) for j in range(2 * k - 1)]
    A = np.stack([np.stack([pw[i + j] for j in range(k)], -1) for i in range(k)], -2)
    b = np.stack([np.bincount(g, weights=isi * mid ** j, minlength=P) for j in range(k)], -1)
    ok = n >= degree + 3
    A[~ok] = np.eye(k)
    b[~ok] = 0.0
    coef = np.linalg.solve(A + 1e-12 * np.eye(k), b[..., None])[..., 0]
    fit = sum(coef[g, j] * mid ** j for j in range(k))
    return g, isi - fit, n, ok, P


# ---------------------------------------------------------------------- shot noise matched by simulation
MATCH_SEED = 2024  # the ideal reference draws this seed, the shot-noise simulations MATCH_SEED + 1
MATCH_START = 2e4  # electrons of the first shot-noise simulation
MATCH_STEPS = 4  # simulations at the current estimate (each step rescales it by simulated / measured)


def interval_excess(spikes: np.ndarray, reference_var: np.ndarray, rate: np.ndarray,
                    mask: np.ndarray) -> tuple[float, float, int]:
    """``(mean, standard error, pixels)`` over the pixels of ``mask [P]`` (those with a finite
    value) of ``(v - reference_var) * rate^2``, ``v`` the :func:`detrended_intervals` variance
    (degree 2) of ``spikes``: the interval variance beyond a reference's in the units of
    ``1 / N_e`` (shot noise of N_e electrons gives intervals of variance ``1 / (N_e rate^2)``)."""
    v, _, _ = detrended_intervals(spikes, 2)
    y = (v - reference_var) * rate ** 2
    m = np.asarray(mask, dtype=bool).reshape(-1) & np.isfinite(y)
    n = int(m.sum())
    if n < 2:
        return float("nan"), float("inf"), n
    return float(y[m].mean()), float(y[m].std() / np.sqrt(n)), n


@dataclass(frozen=True)
class MatchedShotNoise:
    """Shot noise whose simulation has the measured detrended interval variance
    (:func:`matched_shot_noise`). inverse / inverse_se: ``1 / N_e`` and its standard error, from
    the last simulation (``inverse = measured / simulated / steps[-1][0]``; negative when the
    recording varies less than the ideal sensor); electrons: ``1 / inverse`` (inf where it is not
    positive); measured / simulated: ``(mean, SE)`` of :func:`interval_excess` of the recording
    and of the last simulation; steps: ``(electrons simulated, its interval_excess mean)`` of each
    simulation; pixels: how many pixels were averaged."""

    inverse: float
    inverse_se: float
    measured: tuple[float, float]
    simulated: tuple[float, float]
    steps: tuple[tuple[float, float], ...]
    pixels: int

    @property
    def electrons(self) -> float:
        return 1.0 / self.inverse if self.inverse > 0 else float("inf")

    @property
    def standard_error(self) -> float:
        """Of N_e (first order): ``inverse_se / inverse^2``."""
        return self.inverse_se / self.inverse ** 2 if self.inverse > 0 else float("inf")


def matched_shot_noise(spikes: np.ndarray, mask: np.ndarray, intensity: float = 256.0, seed: int = MATCH_SEED,
                       start: float = MATCH_START, steps: int = MATCH_STEPS) -> MatchedShotNoise:
    """N_e of the shot noise that gives a recording's interval variance, each pixel's slow trend
    removed (:func:`detrended_intervals`), over the pixels of ``mask [P]``.

    The radiance is the one that makes the ideal sensor at ``intensity`` fire at each pixel's
    measured mean rate (``min(rate, 1) * 256 / intensity``). :func:`interval_excess` of the
    recording against the ideal sensor's simulation of that radiance (``seed``) is compared with
    the same measure of shot-noise simulations of it (``seed + 1`` each): starting at ``start``
    electrons, each step simulates the current estimate and rescales it by simulated / measured,
    so that the last simulations come close to the measured value (at these rates the measure is
    not proportional to ``1 / N_e``: quantisation to whole frames bends it); ``steps``
    simulations when the measured value is positive (fewer if a simulation reads no excess),
    else one. This measures all of the interval variance beyond the ideal sensor's;
    ``stats.excess_interval_var``, which ``spikegen diagnose`` uses, measures on regular pixels
    the part that accumulates over spans of intervals (docs/fidelity.md, "Shot noise measured
    alike on both recordings")."""
    from ..sensor import Sensor, simulate

    T = spikes.shape[0]
    rate, x = _ideal_radiance(spikes, intensity)
    ref, _, _ = detrended_intervals(simulate(x, intensity, Sensor(), frames=T, seed=seed), 2)
    measured = interval_excess(spikes, ref, rate, mask)
    electrons, done = float(start), []
    for _ in range(steps if measured[0] > 0 else 1):
        sim = interval_excess(simulate(x, intensity, Sensor(electrons=electrons), frames=T, seed=seed + 1), ref,
                              rate, mask)
        done.append((electrons, sim[0]))
        inverse = measured[0] / sim[0] / electrons
        if not inverse > 0:
            break
        electrons = 1.0 / inverse
    inverse_se = abs(1.0 / done[-1][0]) * float(np.hypot(measured[1] / sim[0], measured[0] * sim[1] / sim[0] ** 2))
    return MatchedShotNoise(float(inverse), inverse_se, measured, (sim[0], sim[1]), tuple(done), measured[2])

def _ideal_radiance(spikes: np.ndarray, intensity: float) -> tuple[np.ndarray, np.ndarray]:
    """``(rate [P], x [H, W])``: each pixel's measured mean rate, and the radiance at which the
    ideal sensor at ``intensity`` fires at it (``min(rate, 1) * 256 / intensity``)."""
    mean = spikes.mean(axis=0, dtype=np.float64)
    return mean.reshape(-1), np.minimum(mean, 1.0) * (256.0 / intensity)


# ---------------------------------------------------------------------- inside spikegen diagnose
MOTION_WINDOWS = 8  # windows of frames the image's shift is measured in
MOTION_BLOCKS = 4  # column (row) blocks whose row (column) shifts must agree for a whole-image motion
MOTION_Z = 5.0  # travel over its standard error from the interleaved windows
MOTION_MIN_TRAVEL = 0.5  # pixels: a smaller travel is not reported
MOTION_AGREE = 0.75  # fraction of blocks whose travel is within half the whole image's
MOTION_CHANGE = 0.10  # a pixel whose expected rate the motion changes by more than this is not judged
MOTION_NOISE = 3.0  # ... and by more than this many times the counting noise of the prediction


@dataclass(frozen=True)
class ImageMotion:
    """A motion of the whole image found in a recording (spikegen diagnose, ``--reference self``).

    rows / cols: the fitted travel along each axis (pixels, first to last frame measured) with its standard
    error, the window shifts and the fraction of blocks that agree; significant: a whole-image
    motion on either axis; changed: ``[P]`` bool, pixels whose expected rate the fitted motion
    changes by more than MOTION_CHANGE of their mean, beyond its counting noise (all False when
    not significant); ``frames``: the frames the motion was measured on (the first ones)."""

    rows: dict
    cols: dict
    significant: bool
    changed: np.ndarray
    still: np.ndarray | None = None  # [H, W] mean rate without the motion (at the mean image's position)
    coef: tuple = (np.zeros(3), np.zeros(3))  # quadratics d(t) of the rows' and columns' shifts (0 if none)
    frames: int = 0  # the frames it was measured on (the first ones)
    fit_mean: np.ndarray | None = None  # [H, W] the prediction's mean over those frames' windows

    def rates_at(self, t: float, rate: np.ndarray | None = None) -> np.ndarray:
        """``[H, W]`` each pixel's expected rate at frame ``t`` under the fitted motion (``still``
        moved by the fitted shifts; the quadratics extrapolate past the frames they were fitted
        on); with ``rate [H, W]`` (a more exact mean rate of the same frames), scaled pixel by
        pixel so that its mean over the measured windows is ``rate`` (``rate`` itself where the
        prediction is 0)."""
        dr, dc = (float(np.polynomial.polynomial.polyval(t, c)) for c in self.coef)
        moved = shift_image(self.still, dr, dc)
        if rate is None:
            return moved
        ok = self.fit_mean > 0
        return np.where(ok, moved * rate / np.where(ok, self.fit_mean, 1.0), rate)

    def as_json(self) -> dict:
        return {"rows": self.rows, "cols": self.cols, "whole_image": bool(self.significant),
                "changed_pixels": int(self.changed.sum()), "change_threshold": MOTION_CHANGE, "noise_threshold": MOTION_NOISE,
                "frames_measured": self.frames, "windows": MOTION_WINDOWS, "z_threshold": MOTION_Z, "min_travel": MOTION_MIN_TRAVEL}


def window_images(stream, rows: int, windows: int = MOTION_WINDOWS, frames: int | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(consecutive, interleaved)``, each ``float64 [windows, H, W]``: the mean rate in each of
    ``windows`` equal windows of the first ``frames`` frames (default all) of ``stream`` (a
    bands.Stream, read a band of ``rows`` rows at a time), and in ``windows`` interleaved sets of frames (set ``k``: frames ``t = k
    (mod windows)``), each spanning the whole recording, so that a motion averages out while the
    counting noise stays the same. One pass over the stream."""
    from .bands import bands

    T, H, W = stream.shape
    L = (T if frames is None else min(int(frames), T)) // windows
    seq = np.empty((windows, H, W), dtype=np.float64)
    inter = np.empty((windows, H, W), dtype=np.float64)
    for r0, r1 in bands(H, rows):
        band = stream.rows(r0, r1, 0, windows * L)
        seq[:, r0:r1] = band.reshape(windows, L, r1 - r0, W).sum(axis=1, dtype=np.int64) / L
        inter[:, r0:r1] = band.reshape(L, windows, r1 - r0, W).sum(axis=0, dtype=np.int64) / L
    return seq, inter


def _axis_shifts(images: np.ndarray, axis: int, blocks: int, max_shift: float) -> tuple[np.ndarray, np.ndarray]:
    """``(shifts [windows], block_shifts [blocks, windows])`` of ``images [windows, H, W]`` along
    ``axis``: each window's profile (mean over the other axis, over all of it and over each of
    ``blocks`` equal blocks of it) against the mean over the windows (:func:`profile_shift`)."""
    other = 2 if axis == 0 else 1
    n_other = images.shape[other]
    edges = np.linspace(0, n_other, blocks + 1).astype(int)

    def shifts(sl):
        prof = images[:, :, sl].mean(axis=2) if axis == 0 else images[:, sl, :].mean(axis=1)
        ref = prof.mean(axis=0)
        return np.array([profile_shift(p, ref, max_shift) for p in prof])

    whole = shifts(slice(0, n_other))
    per_block = np.stack([shifts(slice(a, b)) for a, b in zip(edges[:-1], edges[1:])])
    return whole, per_block


def _travel_weights(centres: np.ndarray, frames: int) -> np.ndarray:
    """``w`` with ``travel = w @ shifts`` for the quadratic through the window shifts (fit_drift)."""
    V = np.polynomial.polynomial.polyvander(centres, 2)
    return np.linalg.pinv(V).T @ np.array([0.0, frames - 1.0, (frames - 1.0) ** 2])


def shift_image(img: np.ndarray, dr: float, dc: float) -> np.ndarray:
    """``img(r - dr, c - dc)`` for ``img [H, W]``, linear along each axis, edges held."""
    out = _shift_rows(img, dr)
    return _shift_rows(out.T, dc).T


def image_motion(stream, rows: int, frames: int | None = None, windows: int = MOTION_WINDOWS,
                 blocks: int = MOTION_BLOCKS, max_shift: float = 10.0) -> ImageMotion:
    """Whether the whole image of ``stream`` (a bands.Stream; its first ``frames`` frames, default
    all) moves, and which pixels it changes.

    Along each axis: the shift of each of ``windows`` consecutive windows of frames (the profile
    of its mean image against the mean over the windows), a quadratic in time through them and its
    travel; the standard error of the travel from the same measurement on interleaved windows
    (frames ``t = k mod windows``), which have the recording's counting noise but no motion (at
    least the 0.05-pixel step of the shift grid). An axis moves when ``|travel| >= MOTION_Z`` SE
    and ``>= MOTION_MIN_TRAVEL``, and at least MOTION_AGREE of ``blocks`` blocks across the other
    axis move alike (travel within half the whole image's): an object moving in one part of the
    frame is a local motion, left to heldout.motion_test. With a whole-image motion, each pixel's
    rate in window k is predicted by the motion-free mean image (each window's image moved back
    by its fitted shift, averaged) moved by the fitted shift; pixels whose prediction varies over
    the windows by more than MOTION_CHANGE of its mean, and by more than MOTION_NOISE times the
    counting noise of that prediction (``sqrt(2 v rate / windows)``, ``v`` the windows' scatter
    about the prediction per unit rate, pooled over the pixels), are
    ``changed``: where the noise hides the change, the pixel's own tests (heldout.motion_test)
    decide."""
    T, H, W = stream.shape
    T = T if frames is None else min(int(frames), T)
    L = T // windows
    if windows < 3 or L < 2 or min(H, W) <= 2 * (int(np.ceil(max_shift)) + 2) + 2:
        nothing = {"travel": 0.0, "se": None, "shifts": [], "blocks_agree": None, "moves": False}
        return ImageMotion(nothing, dict(nothing), False, np.zeros(H * W, dtype=bool), frames=T)
    seq, inter = window_images(stream, rows, windows, T)
    centres = (np.arange(windows) + 0.5) * L - 0.5
    w = _travel_weights(centres, T)
    fitted, coefs, axes = [], [], {}
    for axis, name in ((0, "rows"), (1, "cols")):
        whole, per_block = _axis_shifts(seq, axis, blocks, max_shift)
        null, _ = _axis_shifts(inter, axis, blocks, max_shift)
        sd = max(float(np.sqrt(np.mean((null - null.mean()) ** 2) * windows / (windows - 1))), 0.05 / np.sqrt(12.0))
        se = sd * float(np.linalg.norm(w))
        travel = float(w @ whole) + 0.0
        block_travel = per_block @ w
        agree = float(np.mean(np.abs(block_travel - travel) <= 0.5 * abs(travel))) if travel != 0 else 0.0
        moves = abs(travel) >= max(MOTION_Z * se, MOTION_MIN_TRAVEL) and agree >= MOTION_AGREE
        coef = np.polynomial.polynomial.polyfit(centres, whole, 2)
        coef = coef if moves else np.zeros(3)
        coefs.append(coef)
        fitted.append(np.polynomial.polynomial.polyval(centres, coef))
        axes[name] = {"travel": round(travel, 4), "se": round(se, 4), "shifts": [round(float(s), 3) for s in whole],
                      "blocks_agree": round(agree, 3), "moves": bool(moves)}
    significant = axes["rows"]["moves"] or axes["cols"]["moves"]
    changed = np.zeros(H * W, dtype=bool)
    if significant:
        dr, dc = fitted
        still = np.mean([shift_image(seq[k], -dr[k], -dc[k]) for k in range(windows)], axis=0)
        pred = np.stack([shift_image(still, dr[k], dc[k]) for k in range(windows)])
        mean = pred.mean(axis=0)
        spread = np.abs(pred - mean).max(axis=0)
        # counting noise of the prediction: the windows' scatter about it per unit rate, pooled
        # over the pixels (a regular pixel counts far below Poisson), for a mean of the windows
        per_rate = float(((seq - pred) ** 2).sum() / ((windows - 1) * max(mean.sum(), 1e-12)))
        noise = np.sqrt(2.0 * per_rate * np.maximum(mean, 0.0) / windows)
        changed = ((spread > MOTION_CHANGE * np.maximum(mean, 1e-12)) & (spread > MOTION_NOISE * noise)).reshape(-1)
        return ImageMotion(axes["rows"], axes["cols"], True, changed, still, tuple(coefs), T, mean)
    return ImageMotion(axes["rows"], axes["cols"], False, changed, frames=T)


# ---------------------------------------------------------------------- shot noise and threshold jitter, jointly
TIMING_SEED = 2030  # the ideal reference draws this seed; the simulations TIMING_SEED + 1, + 2, ...
TIMING_START = (1.0 / 1e4, 0.006 ** 2)  # (1 / N_e, sigma^2) of the two one-effect simulations
TIMING_STEPS = 2  # simulations at the current estimate, each followed by a Newton step
TIMING_REPEATS = 3  # streams (consecutive seeds) averaged in each simulation


def timing_excess(spikes: np.ndarray, reference: tuple, rate: np.ndarray, mask: np.ndarray):
    """``(mean [2], covariance of the mean [2, 2], pixels)`` over the pixels of ``mask [P]`` (those
    with finite values) of ``(v - v_ref, c - c_ref) * rate^2``: the :func:`detrended_lag_covariance`
    variance ``v`` and lag-1 autocovariance ``c`` of the intervals beyond those of ``reference``
    (the same pair of a reference stream), in the units of ``1 / N_e``."""
    v, c = detrended_lag_covariance(spikes, 2)
    y = np.stack([(v - reference[0]) * rate ** 2, (c - reference[1]) * rate ** 2], -1)
    m = np.asarray(mask, dtype=bool).reshape(-1) & np.isfinite(y).all(-1)
    n = int(m.sum())
    if n < 3:
        return np.full(2, np.nan), np.full((2, 2), np.inf), n
    return y[m].mean(0), np.cov(y[m].T) / n, n


@dataclass(frozen=True)
class TimingNoise:
    """Shot noise and threshold jitter whose simulation has the recordings' detrended interval
    variance and lag-1 autocovariance (:func:`matched_timing_noise`). ``inverse_electrons``
    (1 / N_e) and ``jitter_variance`` (sigma^2) with their covariance ``cov [2, 2]``. Per
    recording (dicts by name): ``measured`` the two statistics (means) with ``measured_cov``,
    ``simulated`` those of a simulation at the final estimate, ``chi2`` of measured - simulated
    (its covariance: the recording's plus the simulation's; 2 degrees of freedom each); ``jacobian``
    the statistics per unit of (1 / N_e, sigma^2) from the one-effect simulations; ``pixels``.
    ``steps``: the (1 / N_e, sigma^2) simulated before each Newton step."""

    inverse_electrons: float
    jitter_variance: float
    cov: np.ndarray
    measured: dict
    measured_cov: dict
    simulated: dict
    chi2: dict
    jacobian: dict
    pixels: dict
    steps: tuple

    @property
    def electrons(self) -> float:
        return 1.0 / self.inverse_electrons if self.inverse_electrons > 0 else float("inf")

    @property
    def jitter(self) -> float:
        """sigma (0 where the fitted sigma^2 is not positive)."""
        return math.sqrt(self.jitter_variance) if self.jitter_variance > 0 else 0.0

    @property
    def standard_errors(self) -> tuple[float, float]:
        """Of 1 / N_e and of sigma^2."""
        return float(math.sqrt(self.cov[0, 0])), float(math.sqrt(self.cov[1, 1]))

    def correlation(self) -> float:
        """Of the two estimates' errors: near -1 where the data hardly tell the effects apart."""
        return float(self.cov[0, 1] / math.sqrt(self.cov[0, 0] * self.cov[1, 1]))


def matched_timing_noise(recordings: dict, intensity: float = 256.0, seed: int = TIMING_SEED,
                         start: tuple = TIMING_START, steps: int = TIMING_STEPS,
                         repeats: int = TIMING_REPEATS, data: dict | None = None) -> TimingNoise:
    """Shot noise (1 / N_e) and a threshold jitter (sigma^2, the sensor's ``threshold_jitter``)
    fitted together to one or more recordings ``{name: (spikes [T, H, W], mask [P])}``, over the
    pixels of each mask, each pixel's slow trend removed: one parameter set for all of them.

    Shot noise makes consecutive intervals vary independently; a jitter of the firing level whose
    reset subtracts the nominal threshold moves one spike time, which lengthens one interval and
    shortens the next: it adds variance ``2 sigma^2 / rate^2`` and lag-1 autocovariance
    ``-sigma^2 / rate^2``. So the pair (variance, autocovariance) of :func:`timing_excess` can tell
    them apart, where the variance alone (:func:`matched_shot_noise`) cannot; how well depends on
    the recording (with few intervals a pixel, the trend's removal correlates the residuals of any
    noise, and the two effects move the pair alike: then ``cov`` is large and :meth:`correlation`
    near -1). Per recording the radiance is the one at which the ideal sensor fires at each
    pixel's measured mean rate (as in :func:`matched_shot_noise`), the reference the ideal
    sensor's simulation of it (``seed``). Every simulation is the mean of ``repeats`` streams of
    consecutive seeds from ``seed + 1`` on, in the order below. Shot noise only and jitter only
    (``start``) give each recording's statistics per unit of each (its Jacobian, frame quantisation
    included); the estimate is the generalised least-squares solution of all recordings' stacked
    statistics (weights: the inverse of their covariance, the recording's plus the simulation's);
    then ``steps`` times: simulate the current estimate and move it by the same solution of
    measured - simulated; last, a simulation at the final estimate gives each recording's chi2.
    ``data``: :func:`timing_data` of the same recordings, intensity and seed, if already made."""
    counter = itertools.count(seed + 1)
    prep = data or timing_data(recordings, intensity, seed)

    def sim(inverse, variance):
        return _timing_sim(prep, inverse, variance, intensity, repeats, counter)

    names = list(prep)
    shot, jit = sim(start[0], 0.0), sim(0.0, start[1])
    J = {k: np.stack([shot[k][0] / start[0], jit[k][0] / start[1]], -1) for k in names}
    Js = np.concatenate([J[k] for k in names])
    W = np.zeros((2 * len(names),) * 2)
    for i, k in enumerate(names):
        W[2 * i:2 * i + 2, 2 * i:2 * i + 2] = np.linalg.inv(prep[k]["mc"] + shot[k][1])
    gain = np.linalg.solve(Js.T @ W @ Js, Js.T @ W)  # [2, 2 * recordings]
    est = gain @ np.concatenate([prep[k]["m"] for k in names])
    done = []
    for _ in range(steps):
        s = sim(*est)
        done.append(tuple(float(e) for e in est))
        est = est + gain @ np.concatenate([prep[k]["m"] - s[k][0] for k in names])
    final = sim(*est)
    cov = gain @ np.linalg.inv(W) @ gain.T
    return TimingNoise(float(est[0]), float(est[1]), cov, {k: prep[k]["m"] for k in names},
                       {k: prep[k]["mc"] for k in names}, {k: final[k][0] for k in names}, _chi2(prep, final), J,
                       {k: prep[k]["n"] for k in names}, tuple(done))


def timing_chi2(recordings: dict, electrons: float, jitter: float, intensity: float = 256.0,
                seed: int = TIMING_SEED, repeats: int = TIMING_REPEATS, data: dict | None = None) -> dict:
    """``{name: chi2}`` (2 degrees of freedom each) of the recordings' :func:`timing_excess`
    statistics against a simulation of shot noise of ``electrons`` (0: none) and a threshold
    jitter ``jitter``: the check :func:`matched_timing_noise` makes of its own fit, for any model
    (the same references and seeds). ``data``: :func:`timing_data`, if already made."""
    prep = data or timing_data(recordings, intensity, seed)
    inverse = 1.0 / electrons if electrons > 0 else 0.0
    return _chi2(prep, _timing_sim(prep, inverse, jitter ** 2, intensity, repeats, itertools.count(seed + 1)))


def timing_data(recordings: dict, intensity: float = 256.0, seed: int = TIMING_SEED) -> dict:
    """What :func:`matched_timing_noise` and :func:`timing_chi2` take of the recordings ``{name:
    (spikes, mask)}``, made once for both: per recording its frames, the ideal radiance of its mean
    rates (:func:`_ideal_radiance`), the rates, the ideal reference's statistics (``seed``), its
    mask, and its measured :func:`timing_excess`."""
    from ..sensor import Sensor, simulate

    prep = {}
    for name, (spikes, mask) in recordings.items():
        T = spikes.shape[0]
        rate, x = _ideal_radiance(spikes, intensity)
        ref = detrended_lag_covariance(simulate(x, intensity, Sensor(), frames=T, seed=seed), 2)
        m, mc, n = timing_excess(spikes, ref, rate, mask)
        prep[name] = dict(T=T, x=x, rate=rate, ref=ref, mask=mask, m=m, mc=mc, n=n)
    return prep


def _timing_sim(prep: dict, inverse: float, variance: float, intensity: float, repeats: int, seeds) -> dict:
    """``{name: (mean statistics, their covariance)}`` of ``repeats`` simulations of each recording
    (seeds taken from the iterator ``seeds``) with 1 / N_e ``inverse`` and sigma^2 ``variance``."""
    from ..sensor import Sensor, simulate

    sensor = Sensor(electrons=1.0 / inverse if inverse > 0 else 0.0,
                    threshold_jitter=math.sqrt(variance) if variance > 0 else 0.0)
    out = {}
    for name, p in prep.items():
        runs = [timing_excess(simulate(p["x"], intensity, sensor, frames=p["T"], seed=next(seeds)),
                              p["ref"], p["rate"], p["mask"]) for _ in range(repeats)]
        out[name] = (np.mean([r[0] for r in runs], 0), sum(r[1] for r in runs) / repeats ** 2)
    return out


def _chi2(prep: dict, sims: dict) -> dict:
    """Per recording: measured - simulated statistics against their covariance (the recording's
    plus the simulation's)."""
    out = {}
    for k, p in prep.items():
        d = p["m"] - sims[k][0]
        out[k] = float(d @ np.linalg.solve(p["mc"] + sims[k][1], d))
    return out
