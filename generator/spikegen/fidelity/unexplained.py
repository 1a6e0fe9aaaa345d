"""Statistics of the held-out frames that the fitted model does not reproduce ("unexplained").

Each check compares the measured held-out frames with the fitted sensor's simulation of the
same frames, over the pixels of the mask (the static ones without a reference), against the
counting noise the model predicts (heldout.count_variance; a difference of two streams has
twice it). A statistic is listed when its discrepancy is both significant (``z`` above
:data:`Z_MIN`) and large (above its ``size`` gate). The catalogue's effects are named by
effects.py; these checks name statistics, never effects.
"""
from __future__ import annotations

import math

import numpy as np

from . import heldout, stats

Z_MIN = 5.0
CHECKS = {
    "rate_per_pixel": "pixels whose held-out count is more than 5 predicted SDs off (fraction; gate 0.1 %, 3 pixels)",
    "rate_per_row": "RMS relative error of row mean rates (gate 1 %)",
    "rate_per_column": "RMS relative error of column mean rates (gate 1 %)",
    "rate_per_frame": "RMS relative error of the population count in windows of 4 frames (gate 1 %)",
    "count_dispersion": "relative excess of per-pixel count variance in windows of 16 frames (gate 25 %)",
    "serial_correlation": "difference of the mean lag-1 correlation of consecutive intervals (gate 0.1)",
    "interval_variance_per_row": ("RMS over bands of rows of the band's mean interval variance beyond the model's, "
                                  "x rate^2, about its mean over all bands (gate 5e-5)"),
    "isi_distribution": "total-variation distance of the pooled interval histograms (gate 0.1)",
}


def _entry(name: str, value: float, z: float, gate: float) -> dict:
    return {"statistic": name, "value": float(value), "z": float(z), "gate": gate, "meaning": CHECKS[name]}


def _rate_checks(c, s, var, mask, H, W) -> list:
    """Per-pixel, per-row and per-column checks on whole held-out counts ``c, s, var [P]``."""
    z = (c - s) / np.sqrt(var)
    out = np.abs(z[mask]) > 5.0
    frac = float(out.mean()) if mask.any() else 0.0
    found = [_entry("rate_per_pixel", frac, float(out.sum()), 0.001)] if out.sum() >= 3 and frac >= 0.001 else []
    for name, axis in (("rate_per_row", 1), ("rate_per_column", 0)):
        m2 = mask.reshape(H, W)
        d = np.where(m2, (c - s).reshape(H, W), 0.0).sum(axis=axis)
        v = np.where(m2, var.reshape(H, W), 0.0).sum(axis=axis)
        tot = np.where(m2, s.reshape(H, W), 0.0).sum(axis=axis)
        ok = (tot > 20) & (v > 0)
        if ok.sum() < 4:
            continue
        chi = (d[ok] - d[ok].sum() * tot[ok] / tot[ok].sum()) ** 2 / v[ok]  # a common scale error is per pixel
        excess = (chi.sum() - ok.sum()) / math.sqrt(2 * ok.sum())
        rel = stats._rms(d[ok] / tot[ok] - d[ok].sum() / tot[ok].sum())
        if excess > Z_MIN and rel > 0.01:
            found.append(_entry(name, rel, excess, 0.01))
    return found


def _frame_check(frame: dict, var4, mask) -> list:
    """Population count in windows of 4 frames, its deviation beyond the pixels' own noise:
    ``frame`` holds the measured and simulated population counts of the windows over the mask
    (``"c"``, ``"s"``) and their number ``"n"``; ``var4 [P]`` each pixel's predictive variance in
    4 frames (heldout.count_variance)."""
    if frame["n"] < 8 or not mask.any():
        return []
    var = 2.0 * var4[mask].sum()
    d = frame["c"] - frame["s"]
    d = d - d.mean()
    n = d.size
    excess = (float((d * d).sum() / var) - (n - 1)) / math.sqrt(2 * (n - 1))
    rel = stats._rms(d) / max(float(frame["s"].mean()), 1e-12)
    return [_entry("rate_per_frame", rel, excess, 0.01)] if excess > Z_MIN and rel > 0.01 else []


def _dispersion_check(d: np.ndarray, s_var: np.ndarray) -> list:
    """Variance of each pixel's counts in windows of 16 frames, measured against simulated:
    ``d [pixels]`` their difference, ``s_var`` the simulated one (pixels of the mask; none with
    fewer than 4 windows)."""
    if d.size < 20:
        return []
    base = float(s_var.mean()) + 1.0 / 6.0
    z = float(d.mean() / max(d.std() / math.sqrt(d.size), 1e-12))
    rel = float(d.mean()) / base
    return [_entry("count_dispersion", rel, z, 0.25)] if z > Z_MIN and rel > 0.25 else []


ROW_BANDS = 16  # bands of rows of interval_variance_per_row (at least 4 rows each)
ROW_GATE = 5e-5  # its size gate: about half the calibrated preset's interval variance (x rate^2) beyond the ideal's


def _interval_row_check(isi: dict, mask, H: int, W: int) -> list:
    """A temporal noise that differs from one band of rows to another: per pixel of the mask with
    >= 8 held-out intervals in both streams, ``(isi_var measured - isi_var simulated) / isi_mean^2``
    (the model's interval variance beyond its own, a relative variance: x rate^2), averaged over
    each of ROW_BANDS bands of rows (standard errors from each band's spread); listed when the
    bands' means scatter about their weighted mean beyond their errors (chi-square excess over
    ``Z_MIN``) and their RMS scatter passes ROW_GATE. A temporal noise the model lacks but that
    is the same in every row shifts every band alike and is not listed here."""
    d = (isi["m_var"] - isi["s_var"]) / isi["s_mean"] ** 2
    ok = mask & (isi["m_n"] >= 8) & (isi["s_n"] >= 8) & np.isfinite(d)
    band = np.repeat(np.arange(H) // max(4, H // ROW_BANDS), W)[ok]
    x = d[ok]
    n = np.bincount(band).astype(np.float64)
    use = n >= 20
    if use.sum() < 4:
        return []
    n = n[use]
    means = np.bincount(band, weights=x)[use] / n
    sq = np.bincount(band, weights=x * x)[use]
    ses = np.maximum(np.sqrt(np.maximum(sq - n * means ** 2, 0.0) / (n - 1) / n), 1e-12)
    w = 1.0 / ses ** 2
    centre = float((w * means).sum() / w.sum())
    k = len(means)
    excess = (float((((means - centre) / ses) ** 2).sum()) - (k - 1)) / math.sqrt(2 * (k - 1))
    rms = stats._rms(means - centre)
    return [_entry("interval_variance_per_row", rms, excess, ROW_GATE)] if excess > Z_MIN and rms > ROW_GATE else []


def _interval_checks(rm, rs, hm, hs) -> list:
    """Serial correlation of consecutive intervals (``rm, rs``: those of the measured and the
    simulated pixels of the mask with enough noisy intervals) and the pooled interval histograms
    of the mask's pixels (``hm, hs``, stats.isi_histogram)."""
    found = []
    rm, rs = rm[np.isfinite(rm)], rs[np.isfinite(rs)]
    if rm.size >= 20 and rs.size >= 20:
        diff = float(rm.mean() - rs.mean())
        z = abs(diff) / math.sqrt(rm.var() / rm.size + rs.var() / rs.size + 1e-18)
        if z > Z_MIN and abs(diff) > 0.1:
            found.append(_entry("serial_correlation", diff, z, 0.1))
    if hm.sum() >= 100 and hs.sum() >= 100:
        tv = stats.histogram_tv(hm, hs)
        if tv > 0.1:
            found.append(_entry("isi_distribution", tv, math.inf, 0.1))
    return found


def unexplained(meas: np.ndarray, sim_full: np.ndarray, mask: np.ndarray, static_reference: bool) -> list:
    """The statistics of ``meas [Th, H, W]`` (the held-out frames) that ``sim_full [T, H, W]``
    (the fitted model's whole run, whose last ``Th`` frames are the same) does not reproduce,
    as JSON entries."""
    Th, H, W = meas.shape
    sim = sim_full[sim_full.shape[0] - Th:]
    c = meas.reshape(Th, -1).sum(axis=0, dtype=np.int64).astype(np.float64)
    s = sim.reshape(Th, -1).sum(axis=0, dtype=np.int64).astype(np.float64)
    var = 2.0 * heldout.count_variance(sim_full, Th, static_reference)
    w4 = [heldout.window_counts(x, 4)[:, mask] for x in (meas, sim)]
    frame = {"c": w4[0].sum(axis=1), "s": w4[1].sum(axis=1), "n": w4[0].shape[0]}
    c16, s16 = (heldout.window_counts(x, 16)[:, mask] for x in (meas, sim))
    lists = {"disp_d": np.zeros(0), "disp_s": np.zeros(0)}
    if c16.shape[0] >= 4:
        lists = {"disp_d": c16.var(axis=0, ddof=1) - s16.var(axis=0, ddof=1), "disp_s": s16.var(axis=0, ddof=1)}
    pm, ps = stats.pixel_stats(meas), stats.pixel_stats(sim)
    lists["rm"], lists["rs"] = (stats.serial_correlation(x)[mask & (p.isi_var >= 2.0) & (p.n_isi >= 8)]
                                for x, p in ((meas, pm), (sim, ps)))
    keep = np.flatnonzero(mask)
    hm, hs = (stats.isi_histogram(p.isi_values[np.isin(stats.interval_pixels(x), keep)], Th)
              for x, p in ((meas, pm), (sim, ps)))
    lists["isi"] = interval_fields(pm, ps)
    return checks_from_parts(c, s, var, mask, H, W, frame, heldout.count_variance(sim_full, 4, True), lists, hm, hs)


def interval_fields(pm: stats.PixelStats, ps: stats.PixelStats) -> dict:
    """What :func:`_interval_row_check` takes of the held-out frames' pixel statistics, measured
    (``pm``) and simulated (``ps``)."""
    return {"m_var": pm.isi_var, "s_var": ps.isi_var, "s_mean": ps.isi_mean, "m_n": pm.n_isi, "s_n": ps.n_isi}


def checks_from_parts(c, s, var, mask, H: int, W: int, frame: dict, var4, lists: dict, hm, hs) -> list:
    """:func:`unexplained` from its parts: whole held-out counts ``c, s`` and their predictive
    variance ``var`` (``[P]`` each), the windows of 4 frames (:func:`_frame_check`), the dispersion
    of windows of 16 frames and the serial correlations (``lists``: ``"disp_d"``, ``"disp_s"``,
    ``"rm"``, ``"rs"``; ``"isi"``: :func:`interval_fields`, for the bands of rows) and the mask's
    interval histograms."""
    found = _rate_checks(c, s, var, mask, H, W)
    found += _frame_check(frame, var4, mask)
    found += _dispersion_check(lists["disp_d"], lists["disp_s"])
    found += _interval_checks(lists["rm"], lists["rs"], hm, hs)
    found += _interval_row_check(lists["isi"], mask, H, W)
    return found
