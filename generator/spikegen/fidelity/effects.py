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

from ..sensor import Sensor, simulate
from . import stats
from .records import GATES, MIN_SPIKES, SIM_SEED, Context, Effect, Fit, judge, rate_from_interval, unavailable
from .synth import EFFECTS

MODEL_VARIANCE_SHARE = 0.1  # shot noise must add this much to the model's own interval variance
MIN_COHERENCE = 0.9  # flicker: agreement of the sinusoid across four pixel groups (1 = identical)


def effects_and_sensor(ctx: Context, fit: Fit) -> tuple[list, Sensor]:
    """Every effect's verdict (in synth.EFFECTS order) and the extended sensor: the baseline
    plus the detected effects with the fitted maps and shot noise."""
    found = _mean_rate_effects(ctx, fit)  # the order of `found` is that of the sensor's notes["effects"]
    found["flicker"] = _flicker_effect(fit)
    found["refractory"], found["reset_to_zero"] = _readout_effects(ctx, fit)
    if found["flicker"].detected:
        found["flicker"] = _check_flicker_against_model(ctx, fit, found)
    deterministic = build_sensor(ctx, fit, found, electrons=0.0)
    shot = found["shot_noise"] = _shot_effect(ctx, fit, deterministic)
    electrons = (shot.parameters.get("electrons") or 0.0) if shot.detected else 0.0
    return [found[n] for n in EFFECTS], build_sensor(ctx, fit, found, electrons=electrons)


def _mean_rate_effects(ctx: Context, fit: Fit) -> dict:
    """Effects on the mean rates; the column estimate subtracts the per-pixel gain's share."""
    gain = _gain_effect(ctx, fit)
    return {"gain_nonuniformity": gain,
            "column_pattern": _column_effect(ctx, fit, gain.evidence.get("variance", 0.0)),
            "dark_current": _dark_effect(ctx, fit), "hot_pixels": _hot_effect(fit),
            "nonlinearity": _gamma_effect(ctx, fit), "crosstalk": _crosstalk_effect(ctx, fit)}


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


def _gain_effect(ctx: Context, fit: Fit) -> Effect:
    st = fit.structure
    if ctx.self_ref or st.e is None:
        return unavailable("gain_nonuniformity", {"sigma": None}, "not separable from scene texture without a reference")
    H, W = ctx.shape
    C = np.tile(st.column_factors, H)
    g = st.good & np.isfinite(st.e1) & np.isfinite(st.e2)
    if g.sum() < 50:
        return unavailable("gain_nonuniformity", {"sigma": None}, "too few usable pixels")
    var, se = _cov_estimate(st.e1[g] / C[g], st.e2[g] / C[g])
    return _pattern_effect("gain_nonuniformity", var, se)


def _column_effect(ctx: Context, fit: Fit, gain_var: float) -> Effect:
    """Column factors from the two halves of the fit window. A per-pixel gain of variance
    ``gain_var`` shows in both halves' column means with variance ``gain_var / (pixels in the
    column)``; that share is subtracted."""
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
    var -= max(gain_var, 0.0) * float(np.mean(1.0 / n_col[ok]))
    return _pattern_effect("column_pattern", var, se)


def _self_column_effect(ctx: Context, fit: Fit) -> Effect:
    """Without a reference: each column's median rate ratio to its left/right neighbours."""
    H, W = ctx.shape
    r = ctx.meas.rate.reshape(H, W)
    ok = (ctx.meas.n.reshape(H, W) >= MIN_SPIKES) & (r < 0.8) & ~fit.structure.hot.reshape(H, W)
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


def _dark_effect(ctx: Context, fit: Fit) -> Effect:
    if ctx.self_ref:
        return unavailable("dark_current", {"rate": None}, "needs a reference radiance")
    d, se = fit.rate.d, fit.rate.se_d
    return judge("dark_current", d, d / max(se, 1e-15), {"rate": d}, evidence={"standard_error": se})


def _hot_effect(fit: Fit) -> Effect:
    """Hot pixels found, scaled up by the fraction of pixels where one could have been found."""
    st = fit.structure
    found = int(st.hot.sum())
    frac = float(st.testable.mean())
    count = int(round(found / frac)) if frac > 0 else found
    rates = st.excess[st.hot]
    return judge("hot_pixels", count if found >= GATES["hot_pixels"][0] else 0, float(found),
                 {"count": count, "found": found, "testable_fraction": frac,
                  "median_rate": float(np.median(rates)) if found else None})


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
    sim = simulate(ctx.X, ctx.intensity, sensor, frames=ctx.frames, seed=SIM_SEED)[:ctx.Tf]
    own = abs(stats.sine_at(stats.population_signal(sim, fl.mask), fl.light, 1.0 / fl.period_frames))
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


def _shot_effect(ctx: Context, fit: Fit, deterministic: Sensor) -> Effect:
    """Interval variance beyond the noise-free model: ``var(ISI) = 1 / (N_e lambda^2)``."""
    sim = simulate(ctx.X, ctx.intensity, deterministic, frames=ctx.frames, seed=SIM_SEED)[:ctx.Tf]
    ps = stats.pixel_stats(sim)
    noisy = ctx.meas.isi_var >= 2.0  # the same estimator for both streams, pixel by pixel
    vm, vs = stats.excess_interval_var(ctx.meas, noisy), stats.excess_interval_var(ps, noisy)
    lam = rate_from_interval(ctx.meas.isi_mean, deterministic.refractory_frames)
    ok = np.isfinite(vm) & np.isfinite(vs) & np.isfinite(lam) & (lam > 0) & (ctx.meas.n_isi >= 8)
    ok &= ~fit.structure.hot
    if ok.sum() < 20:
        return unavailable("shot_noise", {"electrons": None}, "too few pixels with enough intervals")
    inv, se, model_level = _inverse_electrons(vm[ok] - vs[ok], vs[ok], lam[ok], ctx.meas.n_isi[ok])
    electrons = 1.0 / inv if inv > 0 else None
    eff = judge("shot_noise", electrons, inv / max(se, 1e-15), {"electrons": electrons},
                evidence={"inverse_electrons": inv, "standard_error": se, "model_level": model_level})
    # flicker (or motion) the model reproduces makes intervals vary like 1 / lambda^2 too; an
    # excess below 10 % of that deterministic variance is within the error of the fitted modulation
    if eff.detected and inv < MODEL_VARIANCE_SHARE * model_level:
        return replace(eff, detected=False,
                       note="interval variance within the error of the fitted deterministic modulation (flicker)")
    return eff


def _inverse_electrons(excess_var, model_var, lam, n_isi):
    """Weighted mean of ``(measured - model) interval variance x lambda^2`` (estimates
    ``1 / N_e`` per pixel), its empirical standard error, and the model's own variance on the
    same scale; each argument ``[n]`` over the usable pixels."""
    y = excess_var * lam ** 2
    inv = 1e-3
    for _ in range(3):  # inverse-variance weights: sampling variance + quantisation residue
        v = max(inv, 0.0) / lam ** 2 + np.abs(model_var)  # the model's own spread counts too
        var_y = lam ** 4 * (2 * v ** 2 / (n_isi - 1) + 0.02 / n_isi)
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
    R = _responsivity(ctx, fit, on)
    d = _dark_rate(ctx, fit, on, R)
    kw = dict(responsivity=R.reshape(H, W) if not np.allclose(R, 1.0) else None,
              dark_rate=d.reshape(H, W) if d.any() else None)
    kw.update(_scalar_parameters(fit, found, on))
    if electrons and math.isfinite(electrons):
        kw["electrons"] = float(electrons)
    base = ctx.baseline
    return base.replace(name=f"{base.name}+extended", map_model=None,
                        notes={"fitted_by": "spikegen diagnose", "effects": [k for k, v in on.items() if v]}, **kw)


def _responsivity(ctx: Context, fit: Fit, on: dict) -> np.ndarray:
    """``[P]``: the baseline's scaled by ``a``, times column factors / per-pixel ``e`` if detected."""
    H, W = ctx.shape
    st = fit.structure
    a = fit.rate.a
    R = ctx.Rb * a
    if on.get("column_pattern") and not ctx.self_ref:
        R = R * np.tile(st.column_factors, H)
    if on.get("gain_nonuniformity") and st.e is not None:
        C = np.tile(st.column_factors, H) if on.get("column_pattern") else np.ones(H * W)
        use = np.isfinite(st.e) & ~st.hot
        R = np.where(use, ctx.Rb * a * st.e, ctx.Rb * a * C)
    return R


def _dark_rate(ctx: Context, fit: Fit, on: dict, R: np.ndarray) -> np.ndarray:
    """``[P]`` spikes per frame: the baseline's, plus the fitted dark rate and hot pixels if detected."""
    d = ctx.db.copy()
    if on.get("dark_current"):
        d = d + max(fit.rate.d, 0.0)
    if on.get("hot_pixels") and not ctx.self_ref:  # with 'self' the radiance already holds them
        hot = fit.structure.hot
        d[hot] += fit.structure.excess[hot] / np.maximum(R[hot], 1e-6)
    return d


def _scalar_parameters(fit: Fit, found: dict, on: dict) -> dict:
    """Sensor keywords of the detected effects that are single numbers."""
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
    return kw
