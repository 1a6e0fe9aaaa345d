"""The verdicts of ``spikegen diagnose`` (one :class:`~.records.Effect` per sensor effect)
and the extended sensor.

Each effect function reads the :class:`~.records.Fit` (and, where one effect's estimate
corrects another's, that effect's record) and returns an :class:`~.records.Effect`.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import replace

import numpy as np

from ..sensor import MAX_JITTER, Sensor
from . import bands, exact, stats
from .records import (GATES, MIN_COHERENCE, MIN_SPIKES, Context, Effect, Fit, judge,
                      rate_from_interval, unavailable)
from .synth import EFFECTS

MODEL_VARIANCE_SHARE = 0.1  # shot noise / jitter must add this much to the model's own interval variance
# the sampling variance of _jitter_excess over that of one sample variance of independent intervals:
# 4/3 isi_var - 1/3 span_var (MAX_SPAN = 4) of n intervals of variance v varies by
# (16/9 * 2 + 1/9 * 88 - 8/9 * 8) v^2 / n = 56/9 v^2 / n (overlapping spans: 2 (4 v)^2 (1 + 2 * 14/16) / n;
# their covariance with isi_var 2 * 4 v^2 / n), against 2 v^2 / n
JITTER_WEIGHT = 28.0 / 9.0
JITTER_ITERATIONS = 3  # estimates of the jitter (each with the quantisation terms of the last one)
SPREAD_BINS = 8  # bins of the light rate in which gain and dark spread are separated
JITTER_NOTE = ("the detected threshold jitter's share of the noisy pixels' interval variance "
               "(3 sigma^2 / lambda^2) was removed first")
CLOCK_NOTE = ("the error of the population clock the intervals were measured on does not accumulate either: "
              "not told from a threshold jitter, none is named")
CONFUSED_NOTE = ("not told from shot noise with this data: a jitter with the single-interval variance of the "
                 "shot noise found would reach z = {z:.3g} only; reported as shot noise")
DEAD_MIN_SPIKES = 5.0  # a pixel is tested for being dead where the model expects this many spikes
COMMON_Z, COMMON_MIN_SD = 5.0, 0.01  # a shared modulation beyond the model's is removed above these
COMMON_NOTE = ("a modulation shared by all pixels that the model lacks (relative SD {sd:.3g} in windows of "
               f"{stats.COMMON_WINDOW} frames) was removed from the intervals first")


def gated_effects(ctx: Context, fit: Fit) -> tuple[dict, float]:
    """Every effect's verdict by its own gates (``{name: Effect}``, synth.EFFECTS order) and the
    shot noise electrons (0: none). The held-out choice (diagnose.py) may still drop effects."""
    found = _mean_rate_effects(ctx, fit)  # the order of `found` is that of the sensor's notes["effects"]
    found["flicker"] = _flicker_effect(fit)
    found["refractory"], found["reset_to_zero"] = _readout_effects(ctx, fit)
    if found["flicker"].detected:
        found["flicker"] = _check_flicker_against_model(ctx, fit, found)
    deterministic = build_sensor(ctx, fit, found, electrons=0.0)  # found has no jitter yet: none
    shot, found["threshold_jitter"] = _temporal_effects(ctx, fit, deterministic)
    found["shot_noise"] = shot
    electrons = (shot.parameters.get("electrons") or 0.0) if shot.detected else 0.0
    return {n: found[n] for n in EFFECTS}, electrons


def sensor_with(ctx: Context, fit: Fit, found: dict, on: set, electrons: float) -> Sensor:
    """The extended sensor with only the effects ``on`` of ``found`` switched on."""
    chosen = {n: replace(e, detected=e.detected and n in on) for n, e in found.items()}
    return build_sensor(ctx, fit, chosen, electrons=electrons if "shot_noise" in on else 0.0)


def _mean_rate_effects(ctx: Context, fit: Fit) -> dict:
    """Effects on the mean rates; gain and dark spread jointly; the column estimate subtracts
    the shares of the per-pixel gain and dark spread."""
    nonlinearity = _gamma_effect(ctx, fit)
    # the dark rate of the model at gamma = 1 unless the nonlinearity is detected; not with a
    # noise-free reset to zero, whose censored fit trades gamma, a and d too loosely for a refit
    linear = not nonlinearity.detected and not ctx.zero_quantised
    joint = joint_spread(ctx, fit, linear=linear)
    gain = _gain_effect(ctx, fit, joint)
    return {"gain_nonuniformity": gain,
            "column_pattern": _column_effect(ctx, fit, joint),
            "dark_current": _dark_effect(ctx, fit, joint, linear=linear),
            "hot_pixels": _hot_effect(ctx, fit), "dead_pixels": _dead_effect(ctx, fit),
            "nonlinearity": nonlinearity, "crosstalk": _crosstalk_effect(ctx, fit)}


def _cov_estimate(u1, u2):
    """Covariance of two noisy copies of the same pattern, and its standard error under the
    null hypothesis of no pattern (from the noise ``(u1 - u2) / 2``)."""
    p = (u1 - u1.mean()) * (u2 - u2.mean())
    noise_var = float(np.var(u1 - u2)) / 2.0
    return float(p.mean()), noise_var / math.sqrt(max(p.size, 1))


def _pattern_effect(name: str, var: float, se: float) -> Effect:
    """A multiplicative pattern of variance ``var`` (standard error ``se``): size its SD."""
    sigma = math.sqrt(max(var, 0.0))
    return judge(name, sigma, var / max(se, 1e-15), {"sigma": sigma},
                 evidence={"variance": var, "standard_error": se})


def joint_spread(ctx: Context, fit: Fit, linear: bool = False) -> dict | None:
    """Gain spread and dark-rate spread, jointly. In bins of the model's light rate ``L`` the
    residual rates ``r = (e / C - 1) lambda`` of the two halves of the fit window covary as
    ``sigma_g^2 mean(L^2) + V_d`` (a gain multiplies the light, a dark rate adds to it), so a
    chart with a range of radiances separates them; weighted least squares over the bins.
    A noise-free reset to zero leaves only long intervals: then the pooled relative covariance
    is all gain. Also ``dark_shift``: the intercept (over ``L``) of the bin means of the whole
    window's measured rate minus the adopted model's (the refit at gamma = 1 if ``linear``, as
    effects._adopted), over ``a R_b``, in the darker half of the bins: the mean dark rate that
    model misses (the fit leaves the upper tail of a spread dark map out as outliers where the
    light is weak). None without a reference or with too few pixels."""
    st = fit.structure
    if ctx.self_ref or st.e is None:
        return None
    H, W = ctx.shape
    g = st.good & np.isfinite(st.e1) & np.isfinite(st.e2)
    if g.sum() < 50:
        return None
    C = np.tile(st.column_factors, H) * _row_factors(st.e, g, H, W)  # rows: outside the catalogue
    if ctx.zero_quantised:  # only long intervals are usable: too narrow a range of light to separate
        var, se = _cov_estimate(st.e1[g] / C[g], st.e2[g] / C[g])
        return {"gain_var": var, "gain_se": se, "dark_var": 0.0, "dark_se": math.inf}
    # every pixel with a rate but the hot ones: st.good cuts relative residuals, which removes the
    # tail of a spread dark map where the light is weak only, so its variance would seem to grow
    # with the light (and be read as gain)
    g = np.isfinite(st.e) & np.isfinite(st.e1) & np.isfinite(st.e2) & ~st.hot
    lam = fit.rate.lam_pred
    light = np.maximum(lam - fit.rate.a * ctx.Rb * (ctx.db + fit.rate.d), 0.0)
    r1, r2 = ((e / C - 1.0) * lam for e in (st.e1, st.e2))
    a_ad, _, _, lam_ad = _adopted(fit, {"nonlinearity": not linear})
    rd = (st.e / C * lam - lam_ad) / np.maximum(a_ad * ctx.Rb, 1e-12)
    edges = np.quantile(light[g], np.linspace(0, 1, SPREAD_BINS + 1)[1:-1])
    which = np.searchsorted(edges, light)
    rows, means, noise = [], [], np.zeros(SPREAD_BINS)
    for b in range(SPREAD_BINS):
        m = g & (which == b)
        if m.sum() >= 10:
            cov, se = _cov_estimate(r1[m], r2[m])
            # the bin's own sampling error too: a heavy-tailed (lognormal) dark map makes the
            # products scatter far beyond the counting noise the null-hypothesis error knows
            p = (r1[m] - r1[m].mean()) * (r2[m] - r2[m].mean())
            se = max(se, float(np.std(p)) / math.sqrt(p.size))
            rows.append((float(np.mean(light[m] ** 2)), cov, se))
            means.append((float(np.mean(light[m])), float(np.mean(rd[m])), float(np.std(rd[m])) / math.sqrt(m.sum())))
            noise[b] = float(np.var(r1[m] - r2[m])) / 4.0  # counting noise of the whole window
    out = _spread_regression(np.array(rows), edges, noise)
    if out is not None:
        # the intercept from the darker half of the bins only: a missing dark rate adds the same at
        # every light, while the other effects' model errors (a refractory period's compression, a
        # nonlinearity) grow with it and, fitted over the whole range, tilt the line
        shift = _line_fit(np.array(means[:max(3, len(means) // 2)]))
        out.update(dark_shift=shift[0], dark_shift_se=shift[1])
    return out


def _line_fit(rows: np.ndarray) -> tuple[float, float]:
    """``(intercept, its standard error)`` of ``y_b = s x_b + intercept`` by weighted least squares
    over ``rows [(x, y, se)]``."""
    x, y, se = rows.T
    A = np.stack([np.ones_like(x), x], axis=1) / np.maximum(se, 1e-18)[:, None]
    try:
        cov = np.linalg.inv(exact.gram(A))
    except np.linalg.LinAlgError:
        return 0.0, math.inf
    theta = exact.matvec(cov, exact.rmatvec(A, y / np.maximum(se, 1e-18)))
    return float(theta[0]), float(math.sqrt(cov[0, 0]))


def _row_factors(e, ok, H, W) -> np.ndarray:
    """``[P]`` each pixel's row median of ``e`` over pixels ``ok`` (median 1): a row pattern is
    not in the catalogue, and must not be read as per-pixel gain (1 where no row has 4 such pixels)."""
    rows = np.array([np.median(r[m]) if m.sum() >= 4 else np.nan for r, m in zip(e.reshape(H, W), ok.reshape(H, W))])
    if not np.isfinite(rows).any():  # no row has 4 usable pixels: no row correction
        return np.ones(H * W)
    rows = np.where(np.isfinite(rows), rows, np.nanmedian(rows))
    return np.repeat(rows / np.median(rows), W)


def _spread_regression(rows: np.ndarray, edges, noise) -> dict | None:
    """``cov_b = sigma_g^2 x_b + V_d`` by weighted least squares over bins ``rows [(x, cov, se)]``."""
    if len(rows) < 3:
        return None
    x, y, se = rows.T
    A = np.stack([x, np.ones_like(x)], axis=1) / np.maximum(se, 1e-18)[:, None]
    M = exact.gram(A)
    try:
        cov = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        return None
    theta = exact.matvec(cov, exact.rmatvec(A, y / np.maximum(se, 1e-18)))
    return {"gain_var": float(theta[0]), "gain_se": float(math.sqrt(cov[0, 0])), "dark_var": float(theta[1]),
            "dark_se": float(math.sqrt(cov[1, 1])), "edges": edges, "noise": noise}


def _gain_effect(ctx: Context, fit: Fit, joint: dict | None) -> Effect:
    if ctx.self_ref or fit.structure.e is None:
        return unavailable("gain_nonuniformity", {"sigma": None}, "not separable from scene texture without a reference")
    if joint is None:
        return unavailable("gain_nonuniformity", {"sigma": None}, "too few usable pixels")
    return _pattern_effect("gain_nonuniformity", joint["gain_var"], joint["gain_se"])


def _column_effect(ctx: Context, fit: Fit, joint: dict | None) -> Effect:
    """Column factors from the two halves of the fit window. Per-pixel patterns that are the
    same in both halves show in both halves' column means too: a gain of variance ``s_g^2``
    with variance ``s_g^2 / n`` (``n`` pixels in the column), a dark rate of variance ``V_d``
    with ``sum_p V_d / lambda_p^2 / n^2`` (it adds ``d_p / lambda_p`` to ``e``); both shares
    (:func:`joint_spread`) are subtracted."""
    if ctx.self_ref:
        return _self_column_effect(ctx, fit)
    H, W = ctx.shape
    st = fit.structure
    g = st.good_col & np.isfinite(st.e1) & np.isfinite(st.e2)
    n_col = g.reshape(H, W).sum(0)
    cm = [np.where(g, e, 0.0).reshape(H, W).sum(axis=0) / np.maximum(n_col, 1) for e in (st.e1, st.e2)]
    ok = n_col >= 4
    if ok.sum() < 8:
        return unavailable("column_pattern", {"sigma": None}, "too few usable columns")
    c1, c2 = cm[0][ok] / np.mean(cm[0][ok]), cm[1][ok] / np.mean(cm[1][ok])
    var, se = _cov_estimate(c1, c2)
    gain_var, dark_var = (max(joint["gain_var"], 0.0), max(joint["dark_var"], 0.0)) if joint else (0.0, 0.0)
    inv_lam2 = np.where(g, 1.0 / np.maximum(fit.rate.lam_pred, 1e-12) ** 2, 0.0).reshape(H, W).sum(axis=0)
    share = gain_var / n_col[ok] + dark_var * inv_lam2[ok] / n_col[ok] ** 2
    var -= float(np.mean(share))
    return _pattern_effect("column_pattern", var, se)


def _self_column_effect(ctx: Context, fit: Fit) -> Effect:
    """Without a reference: each column's median rate ratio to its left/right neighbours."""
    H, W = ctx.shape
    r = ctx.meas.rate.reshape(H, W)
    ok = (ctx.meas.n.reshape(H, W) >= MIN_SPIKES) & (r < 0.8) & ~fit.structure.hot.reshape(H, W)
    ok &= ctx.static.reshape(H, W)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ratio = r[:, 1:-1] / (0.5 * (r[:, :-2] + r[:, 2:]))
        ratio = np.where(ok[:, 1:-1] & ok[:, :-2] & ok[:, 2:], ratio, np.nan)
        prof = np.nanmedian(ratio, axis=0)
    prof = prof[np.isfinite(prof)]
    if prof.size < 8:
        return unavailable("column_pattern", {"sigma": None}, "too few usable columns")
    sigma = float(np.std(prof) / math.sqrt(1.5))
    return judge("column_pattern", sigma, 10.0 if sigma > 0 else 0.0, {"sigma": sigma},
                 "from neighbour-column ratios (no reference)")


def _dark_effect(ctx: Context, fit: Fit, joint: dict | None, linear: bool = False) -> Effect:
    """The mean dark rate from the rate model; its spread over pixels from :func:`joint_spread`:
    for a lognormal map of mean ``mu`` and variance ``V``, ``spread^2 = log(1 + V / mu^2)`` and
    the median is ``mu exp(-spread^2 / 2)``. With a spread the mean is the rate model's plus
    ``dark_shift`` (the tail the fit left out). ``d`` is that of the model the extended sensor
    adopts (``linear``: the refit at gamma = 1 when the nonlinearity is not detected: a gamma
    below 1 lifts the darkest pixels as a dark rate does). Detected if the mean or the spread
    passes its gates."""
    if ctx.self_ref:
        return unavailable("dark_current", {"rate": None, "spread": None}, "needs a reference radiance")
    d, se = _adopted(fit, {"nonlinearity": not linear})[2], fit.rate.se_d
    var, vse = (joint["dark_var"], joint["dark_se"]) if joint else (0.0, math.inf)
    spread_z = var / max(vse, 1e-30)
    spread_on = spread_z >= GATES["dark_current"][1] and d > 0 and math.sqrt(max(var, 0.0)) >= GATES["dark_current"][0]
    if spread_on and math.isfinite(joint.get("dark_shift_se", math.inf)):
        d = max(d + joint["dark_shift"], d)  # the tail adds: a negative shift is noise
        se = math.hypot(se, joint["dark_shift_se"])
    spread = math.sqrt(math.log1p(max(var, 0.0) / d ** 2)) if spread_on else 0.0
    median = d * math.exp(-spread ** 2 / 2)
    eff = judge("dark_current", median, d / max(se, 1e-15), {"rate": median, "spread": spread, "mean_rate": d},
                evidence={"standard_error": se, "variance": var, "variance_se": vse, "spread_z": spread_z,
                          "joint": joint})
    if spread_on and not eff.detected:
        eff = replace(eff, detected=True, note="detected by its spread over pixels")
    return eff


def _hot_effect(ctx: Context, fit: Fit) -> Effect:
    """Hot pixels found, scaled up by the fraction of pixels where one could have been found."""
    if ctx.self_ref:
        return unavailable("hot_pixels", {"count": None}, "with 'self' a hot pixel is a bright point of the scene")
    st = fit.structure
    found = int(st.hot.sum())
    frac = float(st.testable.mean())
    count = int(round(found / frac)) if frac > 0 else found
    rates = st.excess[st.hot]
    return judge("hot_pixels", count if found >= GATES["hot_pixels"][0] else 0, float(found),
                 {"count": count, "found": found, "testable_fraction": frac,
                  "median_rate": float(np.median(rates)) if found else None})


def _dead_effect(ctx: Context, fit: Fit) -> Effect:
    """Pixels that never fire in the fit window where the model expects DEAD_MIN_SPIKES or more,
    scaled up by the fraction of pixels where one could have been found."""
    if ctx.self_ref:
        return unavailable("dead_pixels", {"count": None}, "with 'self' a dead pixel is a dark point of the scene")
    testable = (fit.rate.lam_pred * ctx.Tf >= DEAD_MIN_SPIKES) & ctx.static
    dead = testable & (ctx.meas.n == 0)
    found, frac = int(dead.sum()), float(testable.mean())
    count = int(round(found / frac)) if frac > 0 else found
    return judge("dead_pixels", count if found >= GATES["dead_pixels"][0] else 0, float(found),
                 {"count": count, "found": found, "testable_fraction": frac}, evidence={"mask": dead})


def _gamma_effect(ctx: Context, fit: Fit) -> Effect:
    if ctx.self_ref:
        return unavailable("nonlinearity", {"gamma": None}, "needs a reference radiance")
    g, se = fit.rate.gamma, fit.rate.se_gamma
    if ctx.zero_quantised and not math.isfinite(se):  # censored fit: flat objective, size gate only
        return judge("nonlinearity", abs(g - 1.0), math.inf, {"gamma": g}, "censored fit: no standard error")
    return judge("nonlinearity", abs(g - 1.0), abs(g - 1.0) / max(se, 1e-15), {"gamma": g},
                 evidence={"standard_error": se})


def _crosstalk_effect(ctx: Context, fit: Fit) -> Effect:
    if ctx.self_ref or not fit.rate.use_c:
        return unavailable("crosstalk", {"fraction": None}, "needs a reference with pixel-scale texture")
    c, se = fit.rate.c, fit.rate.se_c
    return judge("crosstalk", c, c / max(se, 1e-15), {"fraction": c}, evidence={"standard_error": se})


def _flicker_effect(fit: Fit) -> Effect:
    fl = fit.flicker
    if fl is None:
        return unavailable("flicker", {"period_frames": None, "depth": None}, "too few unsaturated pixels")
    params = {"period_frames": fl.period_frames, "depth": fl.depth, "phase_rad": fl.phase_rad,
              "group_coherence": fl.coherence}
    eff = judge("flicker", fl.depth, fl.z, params)
    if fl.coherence < MIN_COHERENCE:
        return replace(eff, detected=False,
                       note="periodicity not shared by all pixels (beat of regular pixel trains, not flicker)")
    return eff


def _check_flicker_against_model(ctx: Context, fit: Fit, found: dict) -> Effect:
    """A readout with a dead time or a reset to zero makes the population signal ring at the
    rates of its pixels. Simulate the fitted model without flicker: if it shows the same line,
    the line is the readout's, not the light's. Returns the flicker verdict, revised."""
    fl = fit.flicker
    others = {k: v for k, v in found.items() if k != "flicker"}
    sensor = build_sensor(ctx, fit, others, electrons=0.0)
    signal = bands.fit_window_pass(ctx, sensor, ctx.rows, mask=fl.mask, timing=None)["signal"]
    own = abs(stats.sine_at(signal, fl.light, 1.0 / fl.period_frames))
    eff = found["flicker"]
    eff = replace(eff, parameters={**eff.parameters, "model_depth_at_period": own})
    if fl.depth < 2.0 * own or fl.depth - own < GATES["flicker"][0]:
        eff = replace(eff, detected=False, note="the fitted model without flicker shows the same line (readout ringing)")
    return eff


def _readout_effects(ctx: Context, fit: Fit) -> tuple[Effect, Effect]:
    """Refractory frames and reset-to-zero from the interval offset and interval constancy."""
    delta = fit.rate.delta
    single = ctx.constant_fraction
    frac = delta - math.floor(delta)
    half = 0.3 <= frac <= 0.7
    zero = half or single > 0.5
    frames = max(int(round(delta - (0.5 if zero else 0.0))), 0)
    refr = judge("refractory", float(frames), 0.0, {"frames": frames, "interval_offset": delta})
    zscore = max(single * 2, 1.0 if half else 0.0)
    rz = judge("reset_to_zero", zscore if zero else 0.0, 0.0,
               {"interval_offset": delta, "constant_interval_fraction": single}, force=zero)
    return refr, rz


def _temporal_effects(ctx: Context, fit: Fit, deterministic: Sensor) -> tuple[Effect, Effect]:
    """Shot noise and threshold jitter from the interval variance beyond the noise-free model
    ``deterministic`` (the gated effects but these two), on static pixels that are not hot and
    have >= 8 intervals, the same estimators for the measured stream and the model's simulation,
    pixel by pixel (so the frame quantisation of the noise-free intervals cancels on average):

    * shot noise accumulates: ``k`` intervals vary by ``k / (N_e lambda^2)``;
    * a threshold jitter of SD ``sigma`` that the reset does not carry over does not: one interval
      and a span of any ``k >= 1`` intervals vary by ``2 sigma^2 / lambda^2``.

    ``1 / N_e``: stats.excess_interval_var (measured minus model) times ``lambda^2``. On regular
    pixels that is the growth over spans of MAX_SPAN intervals, which holds no jitter; on noisy
    pixels (``isi_var >= 2``) the differences of consecutive intervals, which count the jitter as
    ``3 sigma^2 / lambda^2``: :func:`_jitter_share` is subtracted there. ``2 sigma^2``: the single
    interval's excess minus the excess that accumulates, over the span estimator on every pixel,
    ``lambda^2 (4/3 (isi_var_m - isi_var_s) - 1/3 (span_var_m - span_var_s))`` for MAX_SPAN = 4 and
    many intervals (:func:`_jitter_excess` has the finite-sample and quantisation terms): shot
    noise gives it 0, the jitter ``2 sigma^2``; pixels weighted by the inverse of its sampling
    variance (JITTER_WEIGHT), standard error from its spread. The jitter's model streams (``ps``
    in :func:`_jitter_excess`) are those of ``deterministic`` plus the shot noise of the first
    estimate of ``1 / N_e`` (one more simulation, same seed), not of ``deterministic`` itself: beside
    shot noise the analytic terms alone left the statistic biased (at the car's rates, 500 frames,
    N_e 2.25e4: z -3.1 with no jitter, a true SD 0.0036 read as 0.0026; tests/test_diagnose_jitter.py).
    Both are independent from pixel to pixel; when the measured stream has a modulation shared
    by its pixels beyond the model's (:func:`_common_mode`), both streams' intervals are measured
    on their own population's clock (stats.population_clock), which removes it, first; then no
    jitter is named (the clock's own error does not accumulate either: CLOCK_NOTE). The jitter
    is gated (records.GATES) and, like shot noise, not named below MODEL_VARIANCE_SHARE of the
    model's own interval variance; its share of the noisy pixels' estimate is removed from the
    shot noise only where it passed."""
    mask = _common_mask(ctx, fit)
    # `deterministic` is the model of the gated effects but the temporal noise, which the held-out
    # choice always scores (diagnose._choose): its score comes from this simulation too (ctx.passes)
    sim = bands.fit_window_pass(ctx, deterministic, ctx.rows, mask=mask, score=True, timing="variances")
    common = _common_mode(ctx, mask, sim["quadrants"])
    meas, ps = ctx.meas, sim["stats"]
    if common["removed"]:
        clock = stats.clock_of(bands.population_signal(ctx.spikes, mask, ctx.rows, 0, ctx.Tf))
        meas = bands.pixel_stats(ctx.spikes, ctx.rows, 0, ctx.Tf, clock)
        ps = _window_stats(ctx, deterministic, mask, on_clock=True)
    noisy = meas.isi_var >= 2.0  # the same estimator for both streams, pixel by pixel
    vm, vs = stats.excess_interval_var(meas, noisy), stats.excess_interval_var(ps, noisy)
    lam = rate_from_interval(ctx.meas.isi_mean, deterministic.refractory_frames)
    ok = np.isfinite(vm) & np.isfinite(vs) & np.isfinite(meas.span_var) & np.isfinite(ps.span_var)
    ok &= np.isfinite(lam) & (lam > 0)
    ok &= (ctx.meas.n_isi >= 8) & ~fit.structure.hot & ctx.static
    shared = {k: v for k, v in common.items() if k != "mask"}
    if ok.sum() < 20:
        why = "too few pixels with enough intervals"
        return (unavailable("shot_noise", {"electrons": None}, why),
                unavailable("threshold_jitter", {"sigma": None}, why))
    lam, n_isi, noisy = lam[ok], ctx.meas.n_isi[ok], noisy[ok]
    raw, _, model_level = _inverse_electrons(vm[ok] - vs[ok], vs[ok], lam, n_isi)
    raw = max(raw, 0.0)  # (the level of the other noise in the jitter's weights)
    # the jitter's reference: the model with this shot noise, whose whole-frame intervals hold
    # what shot noise does to the jitter's statistic beyond its analytic terms
    ref, ref_inv = ps, 0.0
    if raw > 0:
        ref = _window_stats(ctx, deterministic.replace(electrons=1.0 / raw), mask, on_clock=common["removed"])
        ref_inv = raw
    # the model's own spread in the jitter's weights: its quantisation at its average (1/6 of a frame^2;
    # a pixel's own, which is small where its mean interval is near whole frames, goes with the
    # error of the quantisation terms and would bias the weighted mean), plus any variance beyond
    # quantisation (at most 1/4) that its modulation (flicker) gives
    spread = 1.0 / 6.0 + np.maximum(ps.isi_var[ok] - 0.25, 0.0)
    two_s2 = 0.0
    for _ in range(JITTER_ITERATIONS):  # the quantisation terms need the levels: from the last estimate
        J = _jitter_excess(meas, ref, ctx.meas.isi_mean, raw, two_s2, ref_inv)[ok]
        two_s2, two_se, _ = _inverse_electrons(J, spread, lam, n_isi, JITTER_WEIGHT, other=raw)
    s2 = two_s2 / 2.0
    sigma = math.sqrt(s2) if s2 > 0 else None
    jitter = judge("threshold_jitter", sigma, two_s2 / max(two_se, 1e-15), {"sigma": sigma},
                   evidence={"two_sigma_squared": two_s2, "standard_error": two_se, "model_level": model_level})
    # flicker (or motion) the model reproduces makes intervals vary like 1 / lambda^2 too; an excess
    # below 10 % of that deterministic variance (beyond quantisation: stats.excess_interval_var of
    # the model's stream, on the shot noise's weights) is within the error of the fitted modulation
    why = "interval variance within the error of the fitted deterministic modulation (flicker)"
    if jitter.detected and two_s2 < MODEL_VARIANCE_SHARE * model_level:
        jitter = replace(jitter, detected=False, note=why)
    if common["removed"]:  # the population clock's own error is a timing error that does not accumulate
        jitter = replace(jitter, detected=False, note="; ".join(filter(None, [
            jitter.note, COMMON_NOTE.format(sd=math.sqrt(common["excess"])), CLOCK_NOTE])))
    # the shot noise estimate without the jitter's share on the noisy pixels (of a jitter that
    # passed its gates; an undetected one is taken as none)
    share = _jitter_share(s2 if jitter.detected else 0.0, lam, noisy)
    inv, se, model_level = _inverse_electrons(vm[ok] - vs[ok] - share, vs[ok], lam, n_isi)
    electrons = 1.0 / inv if inv > 0 else None
    note = JITTER_NOTE if (electrons and jitter.detected and noisy.any()) else ""
    if common["removed"]:
        note = "; ".join(filter(None, [note, COMMON_NOTE.format(sd=math.sqrt(common["excess"]))]))
    shot = judge("shot_noise", electrons, inv / max(se, 1e-15), {"electrons": electrons}, note,
                 evidence={"inverse_electrons": inv, "standard_error": se, "model_level": model_level,
                           "common_mode": shared, "jitter_share": float(np.mean(share * lam ** 2))})
    if shot.detected and inv < MODEL_VARIANCE_SHARE * model_level:
        shot = replace(shot, detected=False, note=why)
    if shot.detected and not jitter.detected and inv / max(two_se, 1e-15) < GATES["threshold_jitter"][1]:
        jitter = replace(jitter, note="; ".join(filter(None, [jitter.note, CONFUSED_NOTE.format(z=inv / max(two_se, 1e-15))])))
    return shot, jitter


def _window_stats(ctx: Context, sensor: Sensor, mask: np.ndarray, on_clock: bool) -> stats.PixelStats:
    """The interval statistics of ``sensor``'s simulated fit window, measured on the population clock
    of the pixels of ``mask`` if ``on_clock`` (as the measured stream's when a shared modulation was
    removed), else on frames (the variances only)."""
    if on_clock:
        return bands.fit_window_pass(ctx, sensor, ctx.rows, clock_mask=mask)["stats"]
    return bands.fit_window_pass(ctx, sensor, ctx.rows, timing="variances")["stats"]


def _jitter_excess(pm: stats.PixelStats, ps: stats.PixelStats, mean_isi, inv: float, two_s2: float,
                   ref_inv: float = 0.0) -> np.ndarray:
    """``[P]`` frames**2: the non-accumulating interval variance ``J = 2 sigma^2 / lambda^2`` of each
    pixel, from the measured (``pm``) minus the model's (``ps``) variance of one interval (``dI``)
    and of a span of M = MAX_SPAN intervals (``dS``). Shot noise of variance ``v`` per interval and
    the jitter give, in expectation over a train of ``n`` intervals (``m = n - M + 1`` spans)::

        dI = v + J (1 + 1/n) + c1,    dS = M v (1 - (M - 1)/m) + J (1 + 1/m) + cM

    (sample variances: overlapping spans of independent intervals are correlated, those of a
    jitter's intervals and spans anti-correlated at lags 1 and M, each by -1/2). ``c``: what the
    noise does to the frame quantisation. A spike's phase in its frame is uniform and independent
    of the interval ``D`` that follows, so the whole-frame interval varies by ``var(D) + E g(D)``,
    ``g(x) = frac(x)(1 - frac(x)) = 1/6 - sum_k cos(2 pi k x) / (pi k)^2``, and the noise-free
    model's by ``g(mean)``: ``c = sum_k cos(2 pi k mean)(1 - exp(-2 (pi k)^2 var(D))) / (pi k)^2``
    (:func:`_quantisation_change`), with ``var(D)`` from the current levels ``inv = 1 / N_e`` and
    ``two_s2 = 2 sigma^2`` over ``lambda^2`` at ``mean = mean_isi`` (``M mean_isi`` for spans).
    Against a model with shot noise ``ref_inv = 1 / N_e`` of its own, the quantisation change is
    taken relative to that model's (``c`` at the current levels minus ``c`` at ``ref_inv``).
    Solved for ``J`` pixel by pixel (NaN where unknown)."""
    M = stats.MAX_SPAN
    n = pm.n_isi.astype(np.float64)
    m = np.maximum(n - M + 1, 1.0)
    lam2 = 1.0 / np.maximum(mean_isi, 1.0) ** 2
    inv, two_s2 = max(inv, 0.0), max(two_s2, 0.0)
    ref_inv = max(ref_inv, 0.0)
    dI = pm.isi_var - ps.isi_var - (_quantisation_change(mean_isi, (inv + two_s2) * lam2)
                                    - _quantisation_change(mean_isi, ref_inv * lam2))
    dS = pm.span_var - ps.span_var - (_quantisation_change(M * mean_isi, (M * inv + two_s2) * lam2)
                                      - _quantisation_change(M * mean_isi, M * ref_inv * lam2))
    with np.errstate(all="ignore"):  # (NaN or inf where a pixel has no intervals: not used)
        a12, a21, a22 = 1.0 + 1.0 / n, M * (1.0 - (M - 1) / m), 1.0 + 1.0 / m
        return (dS - a21 * dI) / (a22 - a21 * a12)


QUANTISATION_TERMS = 256  # terms of the Fourier series of _quantisation_change


def _quantisation_change(mean, var) -> np.ndarray:
    """The change of the variance that rounding to whole frames adds to an interval of ``mean``
    frames when the interval varies by ``var`` frames**2 (Gaussian) instead of not at all:
    ``E g(D) - g(mean)``, ``g(x) = frac(x)(1 - frac(x))`` (:func:`_jitter_excess`), by its
    Fourier series (:data:`QUANTISATION_TERMS` terms ``K``: off by less than ``1 / (pi^2 K)``, most
    where ``mean`` is a whole number of frames and ``var`` small; 0 where either is not finite)."""
    mean = np.asarray(mean, dtype=np.float64)
    var = np.broadcast_to(np.asarray(var, dtype=np.float64), mean.shape)
    ok = np.isfinite(mean) & np.isfinite(var)
    out = np.zeros(mean.shape)
    k = np.arange(1, QUANTISATION_TERMS + 1, dtype=np.float64)
    w = 1.0 / (np.pi * k) ** 2
    idx = np.flatnonzero(ok)
    for lo in range(0, idx.size, 4096):  # blocks of pixels: [pixels, terms] at a time
        i = idx[lo: lo + 4096]
        phase = np.cos(2 * np.pi * np.outer(np.mod(mean.reshape(-1)[i], 1.0), k))
        damp = -np.expm1(-2.0 * np.outer(var.reshape(-1)[i], (np.pi * k) ** 2))
        out.reshape(-1)[i] = (phase * damp) @ w
    return out


def _jitter_share(s2: float, lam: np.ndarray, noisy: np.ndarray) -> np.ndarray:
    """``[n]`` frames**2: what a threshold jitter of variance ``s2`` adds to
    stats.excess_interval_var: on noisy pixels the differences of consecutive intervals
    ``(eps_(k+1) - 2 eps_k + eps_(k-1)) / lambda`` vary by ``6 s2 / lambda^2``, half of which is
    read as interval variance (``3 s2 / lambda^2``); on regular pixels the span growth holds none."""
    return np.where(noisy, 3.0 * max(s2, 0.0) / lam ** 2, 0.0)


def _common_mask(ctx: Context, fit: Fit) -> np.ndarray:
    """``[P]`` the pixels of :func:`_common_mode`: unsaturated, static, not hot."""
    return (ctx.meas.rate < 0.9) & (ctx.meas.n >= 3) & ~fit.structure.hot & ctx.static


def _common_mode(ctx: Context, mask: np.ndarray, sim_quadrants: np.ndarray) -> dict:
    """A modulation of the light shared by all pixels that the model does not have (outside the
    catalogue unless it is a flicker): the shared variance (stats.shared_variance) of the
    measured fit window minus that of the model's simulation (its stats.quadrant_counts
    ``sim_quadrants``), over the pixels of ``mask`` (:func:`_common_mask`). ``removed`` when it
    passes COMMON_Z standard errors and COMMON_MIN_SD (relative SD in windows of
    stats.COMMON_WINDOW frames)."""
    vm, sem = vs, ses = 0.0, math.inf
    if ctx.Tf // stats.COMMON_WINDOW >= 4 and min(int(q[-1].sum()) for q in stats._quadrants(mask, *ctx.shape)) >= 4:
        vm, sem = stats.shared_variance_of(bands.quadrant_counts(ctx.spikes, mask, ctx.rows, ctx.Tf))
        vs, ses = stats.shared_variance_of(sim_quadrants)
    excess, se = vm - vs, math.hypot(sem, ses)
    z = excess / se if se > 0 and math.isfinite(se) else 0.0
    removed = bool(z >= COMMON_Z and excess >= COMMON_MIN_SD ** 2)
    return {"excess": excess, "standard_error": se, "z": z, "removed": removed, "mask": mask}


def _inverse_electrons(excess_var, model_var, lam, n_isi, factor: float = 1.0, other: float = 0.0):
    """Weighted mean of ``(measured - model) interval variance x lambda^2`` (a level the same
    for every pixel: ``1 / N_e`` from stats.excess_interval_var; ``2 sigma^2`` from
    :func:`_jitter_excess`), its empirical standard error, and the model's own variance on the
    same scale; each argument ``[n]`` over the usable pixels. The weights are the inverse of a
    pixel's sampling variance: ``factor`` times that of the sample variance of its ``n_isi``
    intervals (JITTER_WEIGHT for the jitter's combination of two sample variances), plus a
    quantisation residue; the variance in them is the estimate itself (iterated) plus ``other``
    (the level of the pixels' other temporal noise) over ``lambda^2``."""
    y = excess_var * lam ** 2
    inv = 1e-3
    for _ in range(3):  # inverse-variance weights: sampling variance + quantisation residue
        v = (max(inv, 0.0) + other) / lam ** 2 + np.abs(model_var)  # the model's own spread counts too
        var_y = lam ** 4 * (factor * 2 * v ** 2 / (n_isi - 1) + 0.02 / n_isi)
        wts = 1.0 / var_y
        inv = float(np.sum(wts * y) / np.sum(wts))
    # empirical standard error: deterministic interval modulation (flicker, motion) that the
    # model reproduces only on average widens the spread of y beyond the weights' assumption
    se = float(np.sqrt(np.sum(wts ** 2 * (y - inv) ** 2)) / np.sum(wts))
    model_level = float(np.sum(wts * np.maximum(model_var, 0.0) * lam ** 2) / np.sum(wts))
    return inv, se, model_level


# ---------------------------------------------------------------------- the extended sensor
def build_sensor(ctx: Context, fit: Fit, found: dict, electrons: float) -> Sensor:
    """The baseline plus the effects of ``found`` (``{name: Effect}``) that are detected, with
    the fitted maps and values; shot noise of ``electrons`` (0: none)."""
    H, W = ctx.shape
    on = {k: v.detected for k, v in found.items()}
    R = _responsivity(ctx, fit, found, on)
    d = _dark_rate(ctx, fit, found, on, R)
    kw = dict(responsivity=R.reshape(H, W) if not np.allclose(R, 1.0) else None,
              dark_rate=d.reshape(H, W) if d.any() else None)
    kw.update(_scalar_parameters(fit, found, on))
    if on.get("crosstalk"):
        kw["crosstalk_fraction"] = _adopted(fit, on)[1]
    if electrons and math.isfinite(electrons):
        kw["electrons"] = float(electrons)
    base = ctx.baseline
    return base.replace(name=f"{base.name}+extended", map_model=None,
                        notes={"fitted_by": "spikegen diagnose", "effects": [k for k, v in on.items() if v]}, **kw)


def _adopted(fit: Fit, on: dict) -> tuple:
    """``(a, c, d, lambda [P])`` of the rate model the extended sensor adopts: the fit itself if
    the nonlinearity is adopted (or without a refit), else the refit at gamma = 1."""
    r = fit.rate
    if on.get("nonlinearity") or r.linear is None:
        return r.a, r.c, r.d, r.lam_pred
    return (*r.linear, r.lam_linear)


def _responsivity(ctx: Context, fit: Fit, found: dict, on: dict) -> np.ndarray:
    """``[P]``: the baseline's scaled by ``a``, times column factors ``C`` if detected and the
    per-pixel gain beyond the columns if detected (``e / C``, or its gain share over ``C`` when a
    dark spread is detected too: the per-pixel gain alone does not reproduce a column pattern);
    0 at dead pixels."""
    H, W = ctx.shape
    st = fit.structure
    base = ctx.Rb * _adopted(fit, on)[0]
    C = np.tile(st.column_factors, H)
    R = base * C if on.get("column_pattern") and not ctx.self_ref else base
    if on.get("gain_nonuniformity") and st.e is not None:
        gain, _ = _pixel_split(ctx, fit, found, on)
        R = np.where(np.isfinite(gain) & ~st.hot, R * gain / C, R)
    if on.get("dead_pixels"):
        R = np.where(found["dead_pixels"].evidence["mask"], 0.0, R)
    return R


def _pixel_split(ctx: Context, fit: Fit, found: dict, on: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(gain factor [P] with the column's, extra dark rate [P] in spikes per frame)`` of each
    pixel (NaN where unknown). Without a detected dark spread the gain is the measured over the
    adopted model rate (``e`` itself at gamma as fitted; where ``e`` is not defined, as near
    saturation, the measured rate, at most one spike per frame). With one, the residual rate ``eps = (e / C - 1) lambda``
    is split by its expected shares (best linear prediction): ``gain = C (1 + s_g^2 L eps / den)``,
    ``dark = V_d eps / den``, ``den = s_g^2 L^2 + V_d + noise``."""
    H, W = ctx.shape
    st = fit.structure
    a, _, d, lam = _adopted(fit, on)
    with np.errstate(all="ignore"):
        isi = fit.rate.isi_eq if fit.rate.isi_eq is not None else fit.rate.isi
        measured = np.clip(rate_from_interval(isi, fit.rate.delta), 0.0, 1.0)
        measured = np.where(isi - fit.rate.delta >= 1.0, measured, np.where(isi <= 1.0, 1.0, np.nan))
        lam_obs = np.where(np.isfinite(st.e), st.e * fit.rate.lam_pred, measured)
    ratio = lam_obs / np.maximum(lam, 1e-12)
    dark = found["dark_current"]
    joint = dark.evidence.get("joint")
    if not (on.get("dark_current") and dark.parameters.get("spread") and joint):
        return ratio, np.zeros(H * W)
    C = np.tile(st.column_factors, H)
    light = np.maximum(lam - a * ctx.Rb * (ctx.db + d), 0.0)
    eps = np.nan_to_num(ratio / C - 1.0) * lam
    sg2 = max(joint["gain_var"], 0.0) if on.get("gain_nonuniformity") else 0.0
    vd = max(joint["dark_var"], 0.0)
    noise = joint["noise"][np.searchsorted(joint["edges"], light)]
    den = sg2 * light ** 2 + vd + noise
    return C * (1.0 + sg2 * light * eps / den), vd * eps / den


def _dark_rate(ctx: Context, fit: Fit, found: dict, on: dict, R: np.ndarray) -> np.ndarray:
    """``[P]`` spikes per frame: the baseline's, plus the fitted dark rate (and its per-pixel
    share of the residual when a spread is detected) and hot pixels if detected; 0 at dead pixels."""
    d = ctx.db.copy()
    if on.get("dark_current"):
        _, extra = _pixel_split(ctx, fit, found, on)
        d = np.maximum(d + max(_adopted(fit, on)[2], 0.0) + extra / np.maximum(R, 1e-6), 0.0)
    if on.get("hot_pixels") and not ctx.self_ref:  # with 'self' the radiance already holds them
        hot = fit.structure.hot
        d[hot] += fit.structure.excess[hot] / np.maximum(R[hot], 1e-6)
    if on.get("dead_pixels"):
        d = np.where(found["dead_pixels"].evidence["mask"], 0.0, d)
    return d


def _scalar_parameters(fit: Fit, found: dict, on: dict) -> dict:
    """Sensor keywords of the detected effects that are single numbers (a threshold jitter at
    most the sensor's MAX_JITTER)."""
    kw = {}
    if on.get("flicker"):
        params = found["flicker"].parameters
        kw.update(flicker_period_frames=params["period_frames"], flicker_depth=params["depth"])
    if on.get("crosstalk"):
        kw["crosstalk_fraction"] = fit.rate.c
    if on.get("nonlinearity"):
        kw["gamma"] = fit.rate.gamma
    if on.get("refractory"):
        kw["refractory_frames"] = int(found["refractory"].parameters["frames"])
    if on.get("reset_to_zero"):
        kw["reset"] = "zero"
    if on.get("threshold_jitter"):
        kw["threshold_jitter"] = min(float(found["threshold_jitter"].parameters["sigma"]), MAX_JITTER)
    return kw
