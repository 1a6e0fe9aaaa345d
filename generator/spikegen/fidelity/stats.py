"""Statistics of spike streams that separate the sensor effects (sensor-model.md), pure NumPy.

Everything here takes a stream ``uint8 [T, H, W]`` (or its pixel-major spike times) and returns
plain arrays or dicts; nothing simulates or fits a sensor. The discrepancy measures at the end
compare a measured stream with a simulated one and are what ``spikegen diagnose`` reports as
"baseline" / "extended" / "gain".
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from ..fpn import robust_sd  # noqa: F401  (one robust sigma for the project; fidelity code imports it from here)
from . import exact

MAX_SPAN = 4  # span (in ISIs) of the long-span timing variance, see PixelStats.span_var


@dataclass
class PixelStats:
    """Per-pixel timing statistics of a stream of ``T`` frames (arrays are ``[P]``, P = H * W).

    n: spike count. first / last: frame of the first / last spike (-1 if none).
    rate: spikes per frame, ``(n - 1) / (last - first)`` when n >= 2 (exact to a fraction of a
    frame for a regular pixel, unlike the count ``n / T``), else ``n / T``.
    isi_mean, isi_var: mean and variance of the inter-spike intervals (NaN below 2 / 3 ISIs).
    span_var: variance of ``t[i + MAX_SPAN] - t[i]`` (NaN below 3 such spans); for a pixel
    whose intervals have variance v and are independent, ``span_var - MAX_SPAN * v`` is the
    frame quantisation, so ``(span_var - isi_var) / (MAX_SPAN - 1)`` estimates v without it.
    isi_min: shortest interval (0 if none). single: all intervals equal (needs >= 3 ISIs).
    ones: number of intervals of exactly one frame.
    """

    frames: int
    n: np.ndarray
    first: np.ndarray
    last: np.ndarray
    rate: np.ndarray
    isi_mean: np.ndarray
    isi_var: np.ndarray
    span_var: np.ndarray
    isi_min: np.ndarray
    single: np.ndarray
    ones: np.ndarray
    n_isi: np.ndarray
    isi_values: np.ndarray  # all intervals, pooled  [n_isi_total]
    diff_var: np.ndarray  # variance of differences of consecutive intervals (NaN below 3)


def spike_times(spikes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pixel, frame)`` of every spike, sorted by pixel then frame (``int64 [N]`` each)."""
    idx, starts, T = pixel_major_spikes(spikes)
    pix = np.repeat(np.arange(starts.size - 1, dtype=np.int64), np.diff(starts))
    return pix, idx - pix * T


def pixel_major_spikes(spikes: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``(idx [N], starts [P + 1], T)``: ``idx = pixel * T + frame`` of every spike, sorted (pixel
    major), and where each pixel's spikes start in it (pixel ``p``: ``idx[starts[p]:starts[p + 1]]``)."""
    T = spikes.shape[0]
    frames = spikes.reshape(T, -1)
    P = frames.shape[1]
    flat = np.empty(frames.shape[::-1], dtype=frames.dtype)  # [P, T]
    for t0 in range(0, T, TRANSPOSE_FRAMES):  # in blocks of frames: a byte array's plain transpose is 4x slower
        flat[:, t0: t0 + TRANSPOSE_FRAMES] = frames[t0: t0 + TRANSPOSE_FRAMES].T
    idx = np.flatnonzero(flat).astype(np.int64, copy=False)
    # the pixels' boundaries by bisection (P searches), not a division of every index by T
    starts = np.searchsorted(idx, np.arange(P + 1, dtype=np.int64) * T)
    return idx, starts, T


TRANSPOSE_FRAMES = 256


def grouped_var(values, groups, P, min_count):
    """``(mean, variance, count)``, each ``[P]``, of ``values`` grouped by ``groups`` (pixel
    indices); the mean is NaN without values, the variance NaN below ``min_count`` values."""
    cnt = np.bincount(groups, minlength=P).astype(np.float64)
    s1 = np.bincount(groups, weights=values, minlength=P)
    s2 = np.bincount(groups, weights=values * values, minlength=P)
    return _moments(cnt, s1, s2, min_count)


def _moments(cnt, s1, s2, min_count):
    """:func:`grouped_var` from the count, sum and sum of squares of each group."""
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / cnt
        var = (s2 - cnt * mean * mean) / (cnt - 1)
    var = np.where(cnt >= min_count, np.maximum(var, 0.0), np.nan)
    mean = np.where(cnt >= 1, mean, np.nan)
    return mean, var, cnt


def pixel_stats(spikes: np.ndarray, clock: np.ndarray | None = None, times: tuple | None = None,
                values: bool = True) -> PixelStats:
    """Timing statistics of every pixel of ``spikes [T, H, W]`` (see :class:`PixelStats`).
    ``clock [T]``: the time of each frame to measure intervals in (``isi_mean``, ``isi_var``,
    ``span_var``, ``diff_var``, ``isi_values``; :func:`population_clock`); None: frames.
    ``times``: :func:`spike_times` of ``spikes`` if already computed. ``values`` False: no
    ``isi_values`` (None). With frames as the clock every sum is of whole numbers and comes from
    running sums over the pixel-major spike indices (:func:`frame_stats`): the same bits."""
    T = spikes.shape[0]
    P = int(np.prod(spikes.shape[1:]))
    if clock is None:
        if times is None:
            idx, starts, _ = pixel_major_spikes(spikes)
        else:
            idx = times[0] * T + times[1]
            starts = np.searchsorted(idx, np.arange(P + 1, dtype=np.int64) * T)
        return frame_stats(idx, starts, T, extremes=True, values=values)
    pix, t = times if times is not None else spike_times(spikes)
    n = np.bincount(pix, minlength=P)
    ends = np.cumsum(n)
    starts = ends - n
    has = n > 0
    first = np.full(P, -1, dtype=np.int64)
    last = np.full(P, -1, dtype=np.int64)
    first[has] = t[starts[has]]
    last[has] = t[ends[has] - 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(n >= 2, (n - 1) / np.maximum(last - first, 1), n / T).astype(np.float64)
    same = pix[1:] == pix[:-1]
    frames_isi = (t[1:] - t[:-1])[same].astype(np.float64)
    tt = t if clock is None else np.asarray(clock, dtype=np.float64)[t]
    isi = frames_isi if clock is None else (tt[1:] - tt[:-1])[same]
    isi_pix = pix[1:][same]
    isi_mean, isi_var, n_isi = grouped_var(isi, isi_pix, P, 3)
    same2 = same[1:] & same[:-1]  # consecutive intervals of one pixel
    dd = (tt[2:] - 2 * tt[1:-1] + tt[:-2])[same2].astype(np.float64)
    _, diff_var, n_d = grouped_var(dd, pix[2:][same2], P, 3)
    # consecutive differences share an interval (lag-1 correlation -1/2), which inflates their
    # sample variance by (1 + 1/n) in expectation
    diff_var = diff_var / (1.0 + 1.0 / np.maximum(n_d, 1))
    m = MAX_SPAN
    same_m = pix[m:] == pix[:-m]
    span = (tt[m:] - tt[:-m])[same_m].astype(np.float64)
    _, span_var, _ = grouped_var(span, pix[m:][same_m], P, 3)
    isi_min, isi_max = _isi_extremes(frames_isi, isi_pix, P)
    ones = np.bincount(isi_pix, weights=(frames_isi == 1).astype(np.float64), minlength=P)
    single = (n_isi >= 3) & (isi_min == isi_max)
    return PixelStats(T, n, first, last, rate, isi_mean, isi_var, span_var, isi_min, single, ones, n_isi,
                      isi if values else None, diff_var)


def intervals(spikes: np.ndarray, times: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(isi_values, interval pixels)`` of :func:`pixel_stats` and :func:`interval_pixels` alone
    (``times``: :func:`spike_times` of ``spikes`` if already computed)."""
    pix, t = times if times is not None else spike_times(spikes)
    same = pix[1:] == pix[:-1]
    return (t[1:] - t[:-1])[same].astype(np.float64), pix[1:][same]


def interval_moments(spikes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(isi_mean, isi_var, n_isi)`` of :func:`pixel_stats` alone (the same numbers, cheaper).

    :func:`grouped_var` of whole-frame intervals adds whole numbers, exactly: its sums are the
    integers ``last - first`` and the sum of squared intervals, which come here from each pixel's
    first and last spike and from a running sum of squared differences of the spike indices
    (pixel major: within a pixel they are its intervals), without sorting the intervals out by
    pixel; the same formulas on the same sums give the same bits."""
    idx, starts, _ = pixel_major_spikes(spikes)
    P = starts.size - 1
    n = np.diff(starts)
    sq = np.zeros(idx.size, dtype=np.int64)  # sq[k]: sum of squared differences of idx[0..k]
    if idx.size > 1:
        d = np.diff(idx)
        entry = starts[:-1][(n > 0) & (starts[:-1] > 0)]  # a pixel's first spike: no interval before it
        d[entry - 1] = 0
        np.cumsum(d * d, out=sq[1:])
    two = n >= 2
    cnt = np.maximum(n - 1, 0).astype(np.float64)
    s1 = np.zeros(P)
    s2 = np.zeros(P)
    first, last = starts[:-1][two], starts[1:][two] - 1  # positions in idx
    s1[two] = (idx[last] - idx[first]).astype(np.float64)
    s2[two] = (sq[last] - sq[first]).astype(np.float64)
    return _moments(cnt, s1, s2, 3)


def interval_variances(spikes: np.ndarray) -> PixelStats:
    """The :func:`pixel_stats` (frames as the clock, the same bits) that
    :func:`excess_interval_var` takes: ``n``, ``first``, ``last``, ``rate``, ``isi_mean``,
    ``isi_var``, ``n_isi``, ``span_var`` and ``diff_var``; the others are None (cheaper)."""
    idx, starts, T = pixel_major_spikes(spikes)
    return frame_stats(idx, starts, T, extremes=False, values=False)


def frame_stats(idx: np.ndarray, starts: np.ndarray, T: int, extremes: bool, values: bool) -> PixelStats:
    """:func:`pixel_stats` with frames as the clock from the pixel-major spike indices ``idx`` and
    each pixel's ``starts`` in them (:func:`pixel_major_spikes`). Every sum of :func:`grouped_var`
    adds whole numbers (intervals, their differences, their spans of MAX_SPAN intervals), so it is
    taken exactly from running sums over each pixel's range of them, without sorting the values
    out by pixel. ``extremes`` False: no ``isi_min``, ``single``, ``ones``; ``values`` False: no
    ``isi_values`` (None)."""
    P = starts.size - 1
    n = np.diff(starts)
    lo = starts[:-1]
    has = n > 0
    base = np.arange(P, dtype=np.int64) * T
    first, last = np.full(P, -1, dtype=np.int64), np.full(P, -1, dtype=np.int64)
    first[has] = idx[lo[has]] - base[has]
    last[has] = idx[starts[1:][has] - 1] - base[has]
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(n >= 2, (n - 1) / np.maximum(last - first, 1), n / T).astype(np.float64)
    d = np.diff(idx)  # within a pixel: its intervals
    cross = lo[has & (lo > 0)] - 1  # the differences across two pixels
    d[cross] = 0  # (keeps the running sums small; never inside a pixel's range)
    dd = np.diff(d)  # within a pixel's range: differences of consecutive intervals
    span = np.minimum(idx[MAX_SPAN:] - idx[:-MAX_SPAN], T)  # within a pixel's range: spans of MAX_SPAN intervals

    def range_sums(x, k):
        """The sum of ``x`` over each pixel's range ``[lo, lo + n - k)``, float64 (0 if empty)."""
        cnt = np.maximum(n - k, 0)
        ok = cnt > 0
        c = np.zeros(x.size + 1, dtype=np.int64)
        np.cumsum(x, out=c[1:])
        out = np.zeros(P)
        out[ok] = (c[lo[ok] + cnt[ok]] - c[lo[ok]]).astype(np.float64)
        return out

    def moments(x, k):
        """grouped_var of ``x`` over each pixel's range (``n - k`` values)."""
        return _moments(np.maximum(n - k, 0).astype(np.float64), range_sums(x, k), range_sums(x * x, k), 3)

    isi_mean, isi_var, n_isi = moments(d, 1)
    _, diff_var, n_d = moments(dd, 2)
    diff_var = diff_var / (1.0 + 1.0 / np.maximum(n_d, 1))  # as pixel_stats
    _, span_var, _ = moments(span, MAX_SPAN)
    isi_min = single = ones = None
    if extremes:
        two = n >= 2
        isi_min, isi_max = np.zeros(P), np.zeros(P)
        if two.any():  # a pixel's range up to the next pixel with intervals: its own, then differences across pixels
            heads = lo[two]
            d_min = d.copy()
            d_min[cross] = np.iinfo(np.int64).max
            isi_min[two] = np.minimum.reduceat(d_min, heads)
            isi_max[two] = np.maximum.reduceat(d, heads)  # (0 across pixels)
            ones = range_sums(d == 1, 1)
        else:  # as pixel_stats: np.bincount of no intervals gives whole numbers
            ones = np.zeros(P, dtype=np.int64)
        single = (n_isi >= 3) & (isi_min == isi_max)
    isi_values = None
    if values:
        inside = np.ones(d.size, dtype=bool)
        inside[cross] = False
        isi_values = d[inside].astype(np.float64)
    return PixelStats(T, n, first, last, rate, isi_mean, isi_var, span_var, isi_min, single, ones, n_isi, isi_values,
                      diff_var)


def interval_moments_by_frame(spikes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`interval_moments` of a 0/1 stream (the same bits) by a pass over the frames instead of
    the spikes: each pixel's last spike time is carried from frame to frame and every spike adds
    its squared interval (whole numbers, exact in float64 below 2**53); the counts and first spikes from
    windows of FIRST_WINDOW frames (:func:`counts_and_first_spikes`). Cheaper than listing the
    spikes for a block of many pixels (a simulated block of rows)."""
    T = spikes.shape[0]
    frames = spikes.reshape(T, -1)
    P = frames.shape[1]
    last, s2 = np.zeros(P), np.zeros(P)
    s, d = np.empty(P), np.empty(P)
    for t in range(T):
        np.copyto(s, frames[t])
        np.subtract(t, last, out=d)
        d *= s  # the interval that ends here (since frame 0 for a first spike), 0 without a spike
        last += d  # last spike time
        d *= d
        s2 += d
    n, first = counts_and_first_spikes(frames)
    first = first.astype(np.float64)
    two = n >= 2
    s2 = np.where(two, s2 - first * first, 0.0)  # the first spike's own term, (first - 0) ** 2
    s1 = np.where(two, last - first, 0.0)
    return _moments(np.maximum(n - 1, 0).astype(np.float64), s1, s2, 3)


FIRST_WINDOW = 64


def counts_and_first_spikes(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(n, first)``, ``int64 [P]`` each: the spikes of each pixel of ``frames [T, P]`` (0/1) and
    the frame of its first spike (0 without one), from the counts in windows of FIRST_WINDOW
    frames: the first window with a spike, then the frame within it."""
    T, P = frames.shape
    w = FIRST_WINDOW
    m = T // w * w
    counts = np.zeros((T // w, P), dtype=np.uint16)
    for j in range(w):  # w strided frames at a time: much faster than a reduction over the middle axis
        np.add(counts, frames[j:m:w], out=counts)
    rest = frames[m:]
    n = counts.sum(axis=0, dtype=np.int64) + rest.sum(axis=0, dtype=np.int64)
    first = np.zeros(P, dtype=np.int64)
    cols = np.arange(P)
    if counts.shape[0]:
        k = np.argmax(counts > 0, axis=0)
        inside = frames[k[None, :] * w + np.arange(w)[:, None], cols[None, :]]  # [w, P]
        first = k * w + np.argmax(inside > 0, axis=0)
        late = counts[k, cols] == 0  # no spike before frame m
    else:
        late = np.ones(P, dtype=bool)
    if rest.shape[0]:
        first = np.where(late, m + np.argmax(rest > 0, axis=0), first)
    return n, first


def _isi_extremes(isi, isi_pix, P):
    """Shortest and longest interval of each pixel, ``[P]`` each (0 where it has none)."""
    isi_min = np.zeros(P)
    isi_max = np.zeros(P)
    if isi.size:  # isi_pix is sorted (spike_times orders by pixel): one run of intervals per pixel
        starts = np.flatnonzero(np.r_[True, isi_pix[1:] != isi_pix[:-1]])
        owners = isi_pix[starts]
        isi_min[owners] = np.minimum.reduceat(isi, starts)
        isi_max[owners] = np.maximum.reduceat(isi, starts)
    return isi_min, isi_max


def interval_pixels(spikes: np.ndarray, times: tuple | None = None) -> np.ndarray:
    """``int64 [n_isi_total]``: the pixel of each interval, in the order of ``PixelStats.isi_values``
    (``times``: :func:`spike_times` of ``spikes`` if already computed)."""
    pix, _ = times if times is not None else spike_times(spikes)
    return pix[1:][pix[1:] == pix[:-1]]


def serial_correlation(spikes: np.ndarray, times: tuple | None = None) -> np.ndarray:
    """``[P]`` lag-1 correlation of consecutive intervals of each pixel (NaN below 4 pairs or
    where the intervals do not vary); ``times``: :func:`spike_times` of ``spikes`` if already computed."""
    P = int(np.prod(spikes.shape[1:]))
    pix, t = times if times is not None else spike_times(spikes)
    same2 = (pix[2:] == pix[1:-1]) & (pix[1:-1] == pix[:-2])
    a = (t[1:-1] - t[:-2])[same2].astype(np.float64)
    b = (t[2:] - t[1:-1])[same2].astype(np.float64)
    g = pix[2:][same2]
    n = np.bincount(g, minlength=P).astype(np.float64)
    sums = [np.bincount(g, weights=v, minlength=P) for v in (a, b, a * b, a * a, b * b)]
    with np.errstate(invalid="ignore", divide="ignore"):
        ma, mb = sums[0] / n, sums[1] / n
        cov = sums[2] / n - ma * mb
        va, vb = sums[3] / n - ma * ma, sums[4] / n - mb * mb
        r = cov / np.sqrt(va * vb)
    return np.where((n >= 4) & (va > 1e-12) & (vb > 1e-12), r, np.nan)


def window_rate(spikes: np.ndarray) -> np.ndarray:
    """Per-pixel rate ``[P]`` of a stream (the ``rate`` of :func:`pixel_stats`, cheaper)."""
    T = spikes.shape[0]
    flat = spikes.reshape(T, -1)
    n = flat.sum(axis=0, dtype=np.int64)
    fired = flat.astype(bool)
    first = np.argmax(fired, axis=0)
    last = T - 1 - np.argmax(fired[::-1], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n >= 2, (n - 1) / np.maximum(last - first, 1), n / T).astype(np.float64)


def split_window_rates(idx: np.ndarray, starts: np.ndarray, T: int, cut: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`window_rate` of frames ``0:cut`` and of frames ``cut:T`` of a stream of ``T`` frames
    whose spikes are ``idx`` and ``starts`` (:func:`pixel_major_spikes`): the same numbers, each
    pixel's spikes on either side of ``cut`` found by bisection."""
    P = starts.size - 1
    base = np.arange(P, dtype=np.int64) * T
    split = np.searchsorted(idx, base + cut)
    last_index = max(idx.size - 1, 0)

    def rate(lo, hi, length):
        n = hi - lo
        if idx.size == 0:
            return (n / length).astype(np.float64)
        first, last = idx[np.minimum(lo, last_index)] - base, idx[np.clip(hi - 1, 0, last_index)] - base
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n >= 2, (n - 1) / np.maximum(last - first, 1), n / length).astype(np.float64)

    return rate(starts[:-1], split, cut), rate(split, starts[1:], T - cut)


def excess_interval_var(meas: PixelStats, noisy: np.ndarray | None = None) -> np.ndarray:
    """Interval variance beyond frame quantisation, ``[P]`` frames**2 (NaN where unknown).

    Where the intervals vary by more than a frame (``noisy``, default ``isi_var >= 2``) the
    quantisation errors of spikes are independent uniforms, and the differences of consecutive
    intervals ``d = ISI_{i+1} - ISI_i`` have ``var(d) = 2 v + 6/12``: ``v = (var(d) - 1/2) / 2``.
    Differences ignore slow modulation of the rate (flicker, motion) that ``var(ISI)`` would
    count. Otherwise (regular pixels, many spikes) ``(span_var - isi_var) / (MAX_SPAN - 1)``:
    for independent intervals of variance v, ``span_var = MAX_SPAN v + q`` and
    ``isi_var = v + q`` share the quantisation term q. Pass the same ``noisy`` for two streams
    to compare them alike.
    """
    span = (meas.span_var - meas.isi_var) / (MAX_SPAN - 1)
    noisy = meas.isi_var >= 2.0 if noisy is None else noisy
    return np.where(noisy, (meas.diff_var - 0.5) / 2.0, span)


# ---------------------------------------------------------------------- modulation shared by all pixels
COMMON_WINDOW = 4  # frames: the window of the shared-variance test


def shared_variance(spikes: np.ndarray, mask: np.ndarray, w: int = COMMON_WINDOW) -> tuple[float, float]:
    """``(variance, its standard error)`` of a modulation shared by all pixels of ``mask [P]``,
    relative to their mean count, in windows of ``w`` frames of ``spikes [T, H, W]``: the smallest
    covariance between the relative population counts of the four quadrants of the image. A
    modulation of all pixels is in every pair; the pixels' own noise is in none (they fire
    independently), and an object that moves over part of the image is not in every pair. The
    error is the largest of the pairs' ``sqrt(var_A var_B / (n - 1))`` over ``n`` windows."""
    T, H, W = spikes.shape[0], spikes.shape[1], int(np.prod(spikes.shape[2:]))
    if T // w < 4 or min(int(q[-1].sum()) for q in _quadrants(mask, H, W)) < 4:
        return 0.0, math.inf
    return shared_variance_of(quadrant_counts(spikes.reshape(T, H, W), mask, w))


def _quadrants(mask, H, W) -> list:
    """``(r0, r1, c0, c1, mask of that quadrant)`` of the four quadrants of an ``H x W`` image."""
    mask = np.asarray(mask).reshape(H, W)
    return [(r0, r1, c0, c1, mask[r0:r1, c0:c1]) for r0, r1 in ((0, H // 2), (H // 2, H))
            for c0, c1 in ((0, W // 2), (W // 2, W))]


def quadrant_counts(spikes: np.ndarray, mask: np.ndarray, w: int = COMMON_WINDOW, top: int = 0,
                    height: int | None = None) -> np.ndarray:
    """``int64 [4, T // w]``: spikes of the pixels of ``mask`` in each quadrant of the image
    (:func:`shared_variance`) in windows of ``w`` frames, counted in ``spikes [T, rows, W]``, the
    rows ``top:top + rows`` of an image of ``height`` rows (default: the whole image) whose
    ``mask`` is ``[height, W]`` (or ``[P]``). The counts of the bands of an image add up to its own."""
    T, rows, W = spikes.shape
    H = height or rows
    n = T // w
    windows = spikes[: n * w].reshape(n, w, rows, W).sum(axis=1, dtype=np.int32)
    out = np.zeros((4, n), dtype=np.int64)
    for k, (r0, r1, c0, c1, _) in enumerate(_quadrants(mask, H, W)):
        a, b = max(r0, top) - top, min(r1, top + rows) - top
        if a < b:
            m = np.asarray(mask).reshape(H, W)[top + a: top + b, c0:c1]
            out[k] = windows[:, a:b, c0:c1][:, m].sum(axis=1, dtype=np.int64)
    return out


def shared_variance_of(counts: np.ndarray) -> tuple[float, float]:
    """:func:`shared_variance` from the quadrants' counts ``[4, n]`` (:func:`quadrant_counts`;
    at least 4 windows and 4 pixels a quadrant)."""
    n = counts.shape[1]
    rel = []
    for pop in counts.astype(np.float64):
        rel.append(pop / max(float(pop.mean()), 1e-12) - 1.0)
    cov = [float((a * b).sum()) / (n - 1) for k, a in enumerate(rel) for b in rel[k + 1:]]
    var = [float((a * a).sum()) / (n - 1) for a in rel]
    se = max(math.sqrt(var[a] * var[b] / (n - 1)) for a in range(4) for b in range(a + 1, 4))
    return min(cov), se


def population_clock(spikes: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``[T]`` the time of each frame on the clock of the population of ``mask [P]``:
    ``sum_{u <= t} S(u) / mean(S)`` with ``S`` its spikes per frame. Intervals measured on it
    lose a modulation of the light shared by all pixels (as a pixel of rate ``lambda phi(t)``
    fires every ``1 / lambda`` of ``sum phi``)."""
    return clock_of(population_signal(spikes, mask))


def clock_of(signal: np.ndarray) -> np.ndarray:
    """:func:`population_clock` from the population signal ``[T]`` (:func:`population_signal`)."""
    return np.cumsum(signal / max(float(signal.mean()), 1e-12))


# ---------------------------------------------------------------------- population signal
def population_signal(spikes: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Spikes per frame summed over the pixels of ``mask [H, W]`` (or ``[P]``): ``float64 [T]``."""
    T = spikes.shape[0]
    flat = spikes.reshape(T, -1)
    return flat[:, np.asarray(mask).reshape(-1)].sum(axis=1, dtype=np.int64).astype(np.float64)


@dataclass(frozen=True)
class SineFit:
    period_frames: float
    depth: float  # relative modulation of the light: amplitude / light level
    phase: float  # radians, of sin(2 pi t / P + phase)
    z: float  # amplitude over its standard error
    residual_sd: float


def sine_at(signal: np.ndarray, light: np.ndarray, freq: float) -> complex:
    """Complex relative modulation ``a + i b`` of ``signal`` at ``freq`` (design of fit_sine)."""
    s = np.asarray(signal, dtype=np.float64)
    t = np.arange(s.size, dtype=np.float64)
    _, coef = _sine_rss(s, t, np.asarray(light, dtype=np.float64), freq)
    return complex(coef[2], coef[3])


def _sine_design(t, light, freq):
    w = 2 * np.pi * freq * t
    return np.stack([np.ones_like(t), light, light * np.sin(w), light * np.cos(w)], axis=1)


def _sine_rss(s, t, light, freq):
    A = _sine_design(t, light, freq)
    coef = exact.lstsq(A, s)
    r = s - exact.matvec(A, coef)
    return exact.dot(r, r), coef


def _sine_rss_fft(s, light, start: float, count: int) -> np.ndarray:
    """``[count]`` the residual sum of squares of fit_sine's design at the frequencies
    ``(start + i) / (4 T)``, ``i = 0 .. count - 1`` (``start`` in bins of ``1 / 4T``, any real;
    the frequencies below a half), from the normal equations whose trigonometric sums are read off
    FFTs of ``L``, ``L^2`` and ``s L`` (zero-padded to 4T, modulated by the grid's offset):
    ``O(T log T)`` instead of a design per frequency (``sin^2``, ``sin cos``, ``cos^2`` at f are
    sums at 2f). The same least squares as :func:`_sine_rss` to rounding; fit_sine refines its
    best frequency with :func:`_sine_rss` itself."""
    if count <= 0:
        return np.empty(0)
    T = s.size
    N = 4 * T
    t = np.arange(T, dtype=np.float64)
    s = s - s.mean()  # the design has a constant: the same fit, better conditioned sums
    L2 = light * light

    def sums(g, offset, idx):
        """``sum_t g(t) (cos, sin)(2 pi (offset + k) t / N)`` at ``k = idx``."""
        z = np.fft.fft(g * np.exp(-2j * np.pi * offset * t / N), n=N)[idx]
        return z.real, -z.imag

    i = np.arange(count)
    cL, sL = sums(light, start, i)
    cL2, sL2 = sums(L2, start, i)
    c2, s2 = sums(L2, 2.0 * start, 2 * i)
    csL, ssL = sums(s * light, start, i)
    sumL, sumL2 = light.sum(), L2.sum()
    G = np.empty((count, 4, 4))
    G[:, 0, 0], G[:, 0, 1], G[:, 1, 1] = T, sumL, sumL2
    G[:, 0, 2], G[:, 0, 3], G[:, 1, 2], G[:, 1, 3] = sL, cL, sL2, cL2
    G[:, 2, 2], G[:, 3, 3], G[:, 2, 3] = 0.5 * (sumL2 - c2), 0.5 * (sumL2 + c2), 0.5 * s2
    iu = np.triu_indices(4, 1)
    G[:, iu[1], iu[0]] = G[:, iu[0], iu[1]]
    v = np.empty((count, 4))
    v[:, 0], v[:, 1], v[:, 2], v[:, 3] = 0.0, (s * light).sum(), ssL, csL
    try:
        coef = np.linalg.solve(G, v[..., None])[..., 0]
    except np.linalg.LinAlgError:
        coef = np.einsum("fij,fj->fi", np.linalg.pinv(G), v)
    return np.maximum(float(s @ s) - (v * coef).sum(axis=1), 0.0)


def fit_sine(signal: np.ndarray, light: np.ndarray, min_period: float = 6.0, max_period: float | None = None) -> SineFit:
    """Fit ``s(t) = c0 + c1 L(t) + L(t) (a sin wt + b cos wt)`` over a grid of periods.

    signal ``s [T]``: spikes per frame of a pixel population; light ``L [T]``: the spikes per
    frame that the light (not the dark current) gives the same population, as the model
    expects. depth = sqrt(a^2 + b^2). The grid has four points per Fourier bin (its residuals
    from FFTs, :func:`_sine_rss_fft`), then a golden-section refinement of the exact fit
    (:func:`_sine_rss`) around the best.
    """
    s = np.asarray(signal, dtype=np.float64)
    T = s.size
    t = np.arange(T, dtype=np.float64)
    light = np.asarray(light, dtype=np.float64)
    max_period = max_period or 2.0 * T
    start = 4.0 * T / max_period  # the grid 1/max_period + i / 4T, in bins of 1 / 4T
    count = max(int(math.ceil(4.0 * T / min_period - start)), 0)
    freqs = (start + np.arange(count)) / (4.0 * T)
    rss = _sine_rss_fft(s, light, start, count)
    null = np.stack([np.ones_like(t), light], axis=1)
    coef0 = exact.lstsq(null, s)
    rss0 = float(np.sum((s - exact.matvec(null, coef0)) ** 2))
    gain = np.maximum(rss0 - rss, 0.0)
    # significance against the neighbouring spectrum, not a white-noise formula: regular pixel
    # trains put broad excess power at the frequencies of their rates. The typical RSS reduction
    # a sinusoid buys near f (median within +-25 % in frequency) is ~ ln 2 x its mean for noise.
    local = _local_median(gain, freqs, 0.25, 10.0 / T) / math.log(2.0)
    zs = np.sqrt(gain / np.maximum(local, 1e-12))
    i = int(np.argmax(zs))
    lo, hi = freqs[max(i - 1, 0)], freqs[min(i + 1, freqs.size - 1)]
    best = _golden(lambda f: _sine_rss(s, t, light, f)[0], lo, hi, 20)
    r, coef = _sine_rss(s, t, light, best)
    depth = float(math.hypot(coef[2], coef[3]))
    z = math.sqrt(max(rss0 - r, 0.0) / max(local[i], 1e-12))
    sd = math.sqrt(r / max(T - 4, 1))
    return SineFit(1.0 / best, depth, float(math.atan2(coef[3], coef[2])), z, sd)


def _local_median(values, freqs, rel, absolute):
    """Median of ``values`` within ``+-max(rel f, absolute)`` of each frequency ``f`` (``freqs``
    increasing). Both ends of the window only move up with ``f``, so its values are kept sorted
    as it slides (bisection) instead of partitioned anew for each frequency, which grew with the
    square of the number of frequencies; the median of an even count is the mean of the middle
    two, as np.median's."""
    freqs = np.asarray(freqs, dtype=np.float64)
    half = np.maximum(rel * freqs, absolute)
    lo, hi = np.searchsorted(freqs, freqs - half), np.searchsorted(freqs, freqs + half)
    vals = np.asarray(values, dtype=np.float64).tolist()
    out = np.empty(len(vals))
    window, a, b = [], 0, 0
    for i in range(len(vals)):
        for j in range(b, int(hi[i])):
            bisect.insort(window, vals[j])
        for j in range(a, int(lo[i])):
            del window[bisect.bisect_left(window, vals[j])]
        a, b = max(a, int(lo[i])), max(b, int(hi[i]))
        k = len(window)
        out[i] = window[k // 2] if k % 2 else (window[k // 2 - 1] + window[k // 2]) / 2.0
    return out


def _golden(f, lo, hi, iters):
    g = (math.sqrt(5) - 1) / 2
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iters):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return (a + b) / 2


def golden_min(f, lo, hi, iters=30):
    """Minimise a unimodal ``f`` on ``[lo, hi]``; returns the argument."""
    return _golden(f, lo, hi, iters)


# ---------------------------------------------------------------------- spatial helpers
def median3x3(x: np.ndarray) -> np.ndarray:
    """3 x 3 median filter of ``[H, W]`` with edge replication."""
    p = np.pad(np.asarray(x, dtype=np.float64), 1, mode="edge")
    H, W = x.shape
    stack = np.stack([p[i:i + H, j:j + W] for i in range(3) for j in range(3)])
    return np.median(stack, axis=0)


# ---------------------------------------------------------------------- discrepancy measures
MEASURES = {
    "rate_rel_rmse": "RMS relative error of per-pixel spike rates (pixels with >= 2 spikes measured)",
    "column_profile_rmse": "RMS relative error of per-column mean rates",
    "dark_rate_error": "|simulated - measured| mean rate of the darkest 10 % of pixels, spikes/frame",
    "hot_pixel_error": "pixels whose rate is off by more than 0.03 spikes/frame, fraction",
    "isi_histogram_tv": "total-variation distance of the pooled inter-spike-interval histograms",
    "isi_cv_error": "mean |difference| of per-pixel interval coefficients of variation",
    "consecutive_fraction_error": "|difference| of the fraction of one-frame intervals",
    "spectrum_log_rmse": "RMS difference of log power of the population signal (16 frequency bands)",
}


def discrepancies(measured: np.ndarray, simulated: np.ndarray, radiance_mean: np.ndarray,
                  measured_stats: PixelStats | None = None) -> dict:
    """Named measures (see :data:`MEASURES`) of how far ``simulated [T, H, W]`` is from
    ``measured [T, H, W]``; ``radiance_mean [H, W]`` ranks the pixels from dark to bright;
    ``measured_stats``: :func:`pixel_stats` of ``measured`` if already computed.
    Smaller is better; 0 is a perfect match."""
    pm, ps = measured_stats or pixel_stats(measured), pixel_stats(simulated)
    T = measured.shape[0]
    cm, cs = measured.reshape(T, -1).mean(0), simulated.reshape(T, -1).mean(0)
    H, W = measured.shape[1:]
    return discrepancy_measures(pm, ps, cm, cs, radiance_mean, H, W, isi_histogram(pm.isi_values, T),
                                isi_histogram(ps.isi_values, T), population_counts(measured),
                                population_counts(simulated))


def discrepancy_measures(pm: PixelStats, ps: PixelStats, cm, cs, radiance_mean, H: int, W: int, hm, hs,
                         popm, pops) -> dict:
    """:func:`discrepancies` from its parts: the two streams' :func:`pixel_stats` (``isi_values``
    only counted), mean counts per frame ``cm, cs [P]``, interval histograms ``hm, hs``
    (:func:`isi_histogram`) and population counts ``popm, pops [T]`` (:func:`population_counts`)."""
    ok = pm.n >= 2
    rel = (ps.rate[ok] - pm.rate[ok]) / pm.rate[ok]
    colm, cols = cm.reshape(H, W).mean(0), cs.reshape(H, W).mean(0)
    good = colm > 0
    dark = np.asarray(radiance_mean).reshape(-1) <= np.quantile(radiance_mean, 0.1)
    return {
        "rate_rel_rmse": _rms(rel),
        "column_profile_rmse": _rms(cols[good] / colm[good] - 1.0),
        "dark_rate_error": float(abs(cs[dark].mean() - cm[dark].mean())),
        "hot_pixel_error": float(np.mean(np.abs(cs - cm) > 0.03)),
        "isi_histogram_tv": histogram_tv(hm, hs),
        "isi_cv_error": _cv_error(pm, ps),
        "consecutive_fraction_error": float(abs(_frac_ones(pm) - _frac_ones(ps))),
        "spectrum_log_rmse": _spectrum_error(popm, pops),
    }


def _rms(a) -> float:
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a))) if a.size else 0.0


def isi_histogram(isi: np.ndarray, T: int) -> np.ndarray:
    """``int64 [T + 1]``: how many of the intervals ``isi`` (whole frames, of a stream of ``T``
    frames) last each number of frames."""
    return np.bincount(isi.astype(np.int64), minlength=T + 1)


def histogram_tv(ha: np.ndarray, hb: np.ndarray) -> float:
    """Total-variation distance of two interval histograms (:func:`isi_histogram`); 1 when one is
    empty and the other not, 0 when both are."""
    na, nb = int(ha.sum()), int(hb.sum())
    if na == 0 or nb == 0:
        return float(na != nb)
    return float(0.5 * np.abs(ha / na - hb / nb).sum())


def _isi_tv(a, b, T) -> float:
    return histogram_tv(isi_histogram(a, T), isi_histogram(b, T))


def _cv_error(pm: PixelStats, ps: PixelStats) -> float:
    ok = (pm.n_isi >= 4) & (ps.n_isi >= 4)
    if not ok.any():
        return 0.0
    cvm = np.sqrt(pm.isi_var[ok]) / pm.isi_mean[ok]
    cvs = np.sqrt(ps.isi_var[ok]) / ps.isi_mean[ok]
    return float(np.mean(np.abs(cvm - cvs)))


def _frac_ones(p: PixelStats) -> float:
    return float(p.ones.sum() / max(p.isi_values.size, 1))


def population_counts(spikes: np.ndarray) -> np.ndarray:
    """``int64 [T]``: spikes per frame of all pixels."""
    return spikes.reshape(spikes.shape[0], -1).sum(axis=1, dtype=np.int64)


def _spectrum_error(a, b, bands=16) -> float:
    """From the population counts ``a, b [T]`` (:func:`population_counts`) of two streams."""
    pa, pb = _band_power(a, bands), _band_power(b, bands)
    return _rms(np.log10(pa + 1e-12) - np.log10(pb + 1e-12))


def _band_power(counts, bands):
    T = counts.shape[0]
    s = counts.astype(np.float64)
    p = np.abs(np.fft.rfft(s - s.mean())) ** 2 / T
    edges = np.unique(np.geomspace(1, p.size, bands + 1).astype(int))
    return np.array([p[a:b].mean() for a, b in zip(edges[:-1], edges[1:])])
