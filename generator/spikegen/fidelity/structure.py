"""Per-pixel structure of ``spikegen diagnose`` (step 4 of diagnose.py).

From the fitted rate model: ``e = lambda_measured / lambda_model`` per pixel, over the fit
window and over each of its halves, column factors, and hot pixels (additive outliers).
Without a reference: hot pixels against the 3 x 3 median of the rates.
"""
from __future__ import annotations

import warnings

import numpy as np

from . import stats
from .records import MIN_SPIKES, Context, PixelStructure, RateFit, equivalent_isi, flicker_rate_table, rate_from_interval

QUANTISED_MIN_ISI = 8.0  # noise-free reset-to-zero: intervals shorter than this say too little


def pixel_structure(ctx: Context, rate: RateFit) -> PixelStructure:
    """The structure of the residual of ``rate`` (or, without a reference, of the rates)."""
    if ctx.self_ref:
        return _self_structure(ctx)
    H, W = ctx.shape
    # the intervals at the fit window's mean light (equivalent_isi): what lam_pred predicts
    isi, delta, lam_pred = rate.isi_eq if rate.isi_eq is not None else rate.isi, rate.delta, rate.lam_pred
    lam_obs = rate_from_interval(isi, delta)
    valid = rate.keep | rate.outlier
    valid &= (isi - delta >= 1.1) & np.isfinite(lam_obs)
    if ctx.zero_quantised:
        valid &= isi >= QUANTISED_MIN_ISI
    e = np.where(valid, lam_obs / lam_pred, np.nan)
    phis = rate.phi[1:] if rate.phi is not None else (None, None)
    tables = [None if phi is None else flicker_rate_table(delta, phi) for phi in phis]
    e1, e2 = (np.where(valid, rate_from_interval(equivalent_isi(1.0 / np.maximum(h, 1e-12), delta, table), delta)
                       / lam_pred, np.nan) for h, table in zip(ctx.halves, tables))
    col = _column_factors(e, valid & ~rate.outlier, H, W)
    C = np.tile(col, H)
    resid = e / C - 1.0
    sd = stats.robust_sd(resid[valid & ~rate.outlier])
    hot, testable, excess = _hot_pixels(ctx, rate, valid, C, e, sd)
    good = valid & ~hot & (np.abs(resid) < max(8 * sd, 0.02))
    good_col = good.copy()  # column means average the interval quantisation away
    if ctx.zero_quantised:
        good &= isi >= 30
    return PixelStructure(hot, testable, excess, sd, col, e, e1, e2, good, good_col)


def _hot_pixels(ctx: Context, rate: RateFit, valid, C, e, sd):
    """``(hot, testable, excess spikes per frame)``, each ``[P]``: a rate beyond the column's
    model by 6 residual SDs (and 0.02 spikes per frame)."""
    lam_pred = rate.lam_pred
    if ctx.zero_quantised:  # any interval bounds lambda from below: 1 / lambda <= ISI - n
        isi = rate.isi_eq if rate.isi_eq is not None else rate.isi
        lam_lo = rate_from_interval(isi, rate.delta - 0.5)
        ok = (rate.keep | rate.outlier) & np.isfinite(lam_lo) & (isi - rate.delta + 0.5 >= 1)
        excess = np.where(ok, lam_lo - C * lam_pred, 0.0)
    else:
        ok = valid
        excess = (e - C) * lam_pred  # additive, spikes per frame
    thresh = np.maximum(0.02, 6 * sd * C * lam_pred)
    hot = ok & (excess > thresh)
    testable = ok & (thresh < 0.04) & (C * lam_pred + 0.06 < 0.9)
    return hot, testable, excess


def _column_factors(e, ok, H, W):
    """``[W]`` median of ``e`` per column over pixels ``ok``, normalised to median 1."""
    e2 = np.where(ok, e, np.nan).reshape(H, W)
    with warnings.catch_warnings():  # all-NaN columns are handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        col = np.nanmedian(e2, axis=0)
    col = np.where(np.isfinite(col), col, 1.0)
    return col / np.median(col)


def _self_structure(ctx: Context) -> PixelStructure:
    """Static scene, radiance from the data: hot pixels against the 3 x 3 median (column
    factors are judged from neighbour columns in effects.py). Per-pixel gain cannot be told
    from texture."""
    H, W = ctx.shape
    r = ctx.meas.rate.reshape(H, W)
    med = stats.median3x3(r)
    ok = (ctx.meas.n.reshape(H, W) >= MIN_SPIKES) & (r < 0.8)
    with np.errstate(all="ignore"):
        rel = r / med - 1.0
    sd = stats.robust_sd(rel[ok])
    excess = r - med
    thresh = np.maximum(0.02, 6 * sd * med)
    hot = ok & (excess > thresh)
    testable = ok & (thresh < 0.04) & (med < 0.8)
    return PixelStructure(hot.reshape(-1), testable.reshape(-1), excess.reshape(-1), sd, np.ones(W))
