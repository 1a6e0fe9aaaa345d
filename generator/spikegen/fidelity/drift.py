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
"""
from __future__ import annotations

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
    r = isi - fit
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.bincount(g, weights=r * r, minlength=P) / (n - k)
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
