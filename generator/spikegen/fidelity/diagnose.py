"""``spikegen diagnose``: what a measured stream shows that the baseline sensor does not.

Given a measured stream ``S [T, H, W]``, the radiance ``X`` it saw and the intensity ``I``,
the diagnosis fits the sensor model of sensor-model.md on the first ``FIT_FRACTION`` of the
frames and judges it on the rest:

1. Timing statistics per pixel (:mod:`.stats`): a rate exact to a fraction of a frame
   (``(n - 1) / (last - first)``), interval variances at two spans, one-frame intervals.
2. Flicker: a sinusoid in the population signal (spikes per frame of unsaturated pixels),
   relative to the light part of the expected signal.
3. The mean-rate model, fitted to the measured mean intervals of all pixels::

       ISI(x) = delta + max(1, 1 / lambda(x)),
       lambda(x) = a R_b(x) (g fbar (B0(x) + c B1(x)) + d_b(x) + d),   g = I / 256,

   with ``B0 = mean_t X^gamma``, ``B1 = mean_t (neighbour mean - self) of X^gamma``
   (crosstalk), ``fbar`` the mean flicker factor over the fit frames, ``R_b, d_b`` the
   baseline's maps. ``delta`` is the interval offset of the readout: ``n`` refractory frames
   add ``n``; reset-to-zero loses on average half a frame of charge per spike, ``+ 1/2``.
   For fixed ``(delta, gamma)`` the model is linear in ``(a, a c, a d)`` (weighted least
   squares on ``1 / (ISI - delta)``); ``gamma`` by golden section, ``delta`` on a grid, then
   refined. Hot pixels are left out (iteratively, as outliers).
4. Per-pixel structure of ``e = lambda_measured / lambda_model``: column factors, the
   remaining per-pixel spread (the covariance of two halves of the fit window, so counting
   noise drops out), and hot pixels (additive outliers).
5. Shot noise: interval variance beyond what the fitted noise-free model produces (both
   measured and simulated, so flicker, quantisation and scene motion cancel).
6. Reset-to-zero: the half-frame offset, and pixels whose intervals never vary.

Every effect gets ``score`` = its estimated size over the weakest size the tools must find
(synth.ENVELOPE), and ``z`` (its statistical significance); detected when both pass. The
extended sensor is the baseline plus the detected effects with the fitted maps; "baseline",
"extended" and "gain" are the named discrepancy measures (stats.MEASURES) of each model on
the held-out frames.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..sensor import Sensor, interpolation_weights, neighbour_mean, simulate
from . import stats
from .synth import EFFECTS

FIT_FRACTION = 0.8
SIM_SEED = 20240617  # seed of the diagnosis' own simulations (the measured stream's is unknown)
GAMMA_RANGE = (0.25, 4.0)
DELTA_MAX = 6.0
MIN_SPIKES = 3
MODEL_VARIANCE_SHARE = 0.1  # shot noise must add this much to the model's own interval variance
MIN_COHERENCE = 0.9  # flicker: agreement of the sinusoid across four pixel groups (1 = identical)
QUANTISED_MIN_ISI = 8.0  # noise-free reset-to-zero: intervals shorter than this say too little

# name: (size gate = half the envelope's weakest effect, z gate)
GATES = {
    "gain_nonuniformity": (0.015, 6.0),
    "column_pattern": (0.01, 5.0),
    "dark_current": (0.001, 6.0),
    "hot_pixels": (2, 0.0),
    "shot_noise": (4000.0, 6.0),
    "reset_to_zero": (0.5, 0.0),
    "refractory": (0.5, 0.0),
    "flicker": (0.025, 8.0),
    "crosstalk": (0.025, 6.0),
    "nonlinearity": (0.05, 6.0),
}
ENVELOPE_SIZE = {"gain_nonuniformity": 0.03, "column_pattern": 0.02, "dark_current": 0.002, "hot_pixels": 5,
                 "shot_noise": 2000.0, "reset_to_zero": 1.0, "refractory": 1.0, "flicker": 0.05, "crosstalk": 0.05,
                 "nonlinearity": 0.1}


@dataclass
class Effect:
    name: str
    detected: bool
    score: float
    parameters: dict
    z: float = 0.0
    note: str = ""

    def as_dict(self) -> dict:
        d = {"name": self.name, "detected": bool(self.detected), "score": _num(self.score),
             "parameters": {k: _num(v) for k, v in self.parameters.items()}, "z": _num(self.z)}
        if self.note:
            d["note"] = self.note
        return d


@dataclass
class Diagnosis:
    effects: list
    extended: Sensor
    baseline_measures: dict
    extended_measures: dict
    fit: dict = field(default_factory=dict)  # fitted model and maps, for reports
    info: dict = field(default_factory=dict)

    @property
    def detected(self) -> list:
        found = [e for e in self.effects if e.detected]
        return [e.name for e in sorted(found, key=lambda e: -e.score)]

    def effect(self, name) -> Effect:
        return next(e for e in self.effects if e.name == name)

    def gain(self) -> dict:
        out = {}
        for k, b in self.baseline_measures.items():
            x = self.extended_measures[k]
            out[k] = {"baseline": _num(b), "extended": _num(x), "reduction": _num((b - x) / b if b > 0 else 0.0)}
        return out

    def as_json(self) -> dict:
        return {"detected": self.detected, "effects": [e.as_dict() for e in self.effects],
                "baseline": {k: _num(v) for k, v in self.baseline_measures.items()},
                "extended": {k: _num(v) for k, v in self.extended_measures.items()},
                "gain": self.gain(), "measures": stats.MEASURES, "info": self.info,
                "extended_sensor": self.extended.parameters()}


def _num(v):
    if v is None:
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    v = float(v)
    return round(v, 6) if math.isfinite(v) else None


# ---------------------------------------------------------------------- entry point
def diagnose(spikes: np.ndarray, radiance, intensity: float, baseline: Sensor | None = None,
             fit_fraction: float = FIT_FRACTION, progress=None) -> Diagnosis:
    """Diagnose ``spikes uint8 [T, H, W]`` against ``radiance`` (``[H, W]`` / ``[K, H, W]``
    linear luminance, or the string ``"self"``) seen at ``intensity``."""
    spikes = np.asarray(spikes)
    if spikes.ndim != 3:
        raise InputError(f"measured stream must be [T, H, W], got shape {spikes.shape}")
    T, H, W = spikes.shape
    if T < 50:
        raise InputError(f"measured stream has {T} frames; a diagnosis needs at least 50 (1000 recommended)")
    if not (math.isfinite(intensity) and intensity > 0):
        raise InputError(f"intensity must be a positive number, got {intensity}")
    baseline = (baseline or Sensor(name="ideal")).sized(H, W)
    Tf = int(round(T * fit_fraction))
    step = progress or (lambda msg: None)
    step("timing statistics")
    meas = stats.pixel_stats(spikes[:Tf])
    half = Tf // 2
    halves = (stats.window_rate(spikes[:half]), stats.window_rate(spikes[half:Tf]))
    self_ref = isinstance(radiance, str)
    if self_ref:
        X = _self_radiance(meas.rate, intensity, baseline, H, W)
    else:
        X = np.asarray(radiance, dtype=np.float64)
        X = X[None] if X.ndim == 2 else X
        if X.ndim != 3 or X.shape[1:] != (H, W):
            raise InputError(f"reference radiance is {X.shape[-1]}x{X.shape[-2]}, the stream is {W}x{H}")
    ctx = _Context(spikes, X, float(intensity), baseline, Tf, meas, halves, self_ref)
    step("mean-rate model")
    model = _fit_all(ctx)
    step("noise-free model simulation")
    effects, extended = _effects_and_sensor(ctx, model)
    step("held-out comparison")
    base_sim = simulate(X, intensity, baseline, frames=T, seed=SIM_SEED)
    ext_sim = simulate(X, intensity, extended, frames=T, seed=SIM_SEED)
    xm = X.mean(axis=0)
    held = slice(Tf, T)
    bm = stats.discrepancies(spikes[held], base_sim[held], xm)
    em = stats.discrepancies(spikes[held], ext_sim[held], xm)
    info = {"frames": T, "fit_frames": Tf, "held_out_frames": T - Tf, "height": H, "width": W,
            "intensity": float(intensity), "reference": "self" if self_ref else f"{X.shape[0]} sub-frame(s)",
            "baseline_sensor": baseline.name}
    return Diagnosis(effects, extended, bm, em, fit=model, info=info)


def _self_radiance(rate, intensity, baseline, H, W):
    """Radiance that makes the baseline reproduce the measured rates (static scene)."""
    R, d = baseline.maps(H, W)
    x = (np.minimum(rate.reshape(H, W), 1.0) / R - d) * (256.0 / intensity)
    return np.maximum(x, 0.0)[None]


@dataclass
class _Context:
    spikes: np.ndarray
    X: np.ndarray  # [K, H, W]
    intensity: float
    baseline: Sensor
    Tf: int
    meas: stats.PixelStats
    halves: tuple
    self_ref: bool

    @property
    def shape(self):
        return self.spikes.shape[1:]

    @property
    def g(self):
        return self.intensity / 256.0


# ---------------------------------------------------------------------- fitting
def _fit_all(ctx: _Context) -> dict:
    H, W = ctx.shape
    Rb, db = ctx.baseline.maps(H, W)
    model = {"a": 1.0, "gamma": 1.0, "c": 0.0, "d": 0.0, "delta": 0.0, "fbar": 1.0, "flicker": None,
             "Rb": Rb.reshape(-1), "db": db.reshape(-1), "outlier": np.zeros(H * W, dtype=bool)}
    model["constant_fraction"] = _constant_interval_fraction(ctx.meas)
    model["zero_quantised"] = model["constant_fraction"] > 0.5
    model["flicker"] = _fit_flicker(ctx, model)
    if not ctx.self_ref:
        _fit_rate_model(ctx, model)
        model["flicker"] = _fit_flicker(ctx, model)
        model["fbar"] = _flicker_mean(model["flicker"], ctx.Tf)
        _fit_rate_model(ctx, model)
    else:
        model["delta"] = _self_refractory(ctx)
    _pixel_structure(ctx, model)
    return model


def _bases(ctx: _Context, gamma: float):
    """``B0, B1 [P]``: time-mean of X^gamma and of its 4-neighbour contrast over the fit frames."""
    K, H, W = ctx.X.shape
    if K == 1:
        xg = ctx.X[0] ** gamma
        return xg.reshape(-1), (neighbour_mean(xg) - xg).reshape(-1)
    T = ctx.spikes.shape[0]
    ts = np.unique(np.linspace(0, ctx.Tf - 1, min(ctx.Tf, 48)).astype(int))
    wts = interpolation_weights(K, T)[ts]
    xg = (wts @ ctx.X.reshape(K, -1)).reshape(-1, H, W) ** gamma
    return xg.mean(0).reshape(-1), (neighbour_mean(xg) - xg).mean(0).reshape(-1)


def _design(ctx, model, gamma, use_c):
    B0, B1 = _bases(ctx, gamma)
    Rb, db = model["Rb"], model["db"]
    gf = ctx.g * model["fbar"]
    cols = [Rb * (gf * B0 + db), Rb]
    if use_c:
        cols.insert(1, Rb * gf * B1)
    return np.stack(cols, axis=1)


def _lam_obs(isi, delta):
    with np.errstate(divide="ignore", invalid="ignore"):
        return 1.0 / (isi - delta)


def _solve(A, isi, delta, sqrt_w, keep, want_cov=False, target=None):
    """Weighted LSQ of ``lambda_obs = 1 / (ISI - delta)`` (or of ``target``) on the design
    ``A [P, p]``, relative errors weighted by ``w``; returns (theta, cov or None, lam_pred [P])."""
    if target is None:
        x = isi - delta
        ok = keep & (x >= 1.05)
    else:
        x = 1.0 / np.maximum(target, 1e-12)
        ok = keep & (target < 0.95)
    if ok.sum() < A.shape[1] + 5:
        return None
    sw = sqrt_w[ok] * x[ok]  # sqrt(w) / lambda_obs
    Aw = A[ok] * sw[:, None]
    bw = sqrt_w[ok]  # lambda_obs * sw
    M = Aw.T @ Aw
    try:
        theta = np.linalg.solve(M, Aw.T @ bw)
    except np.linalg.LinAlgError:
        return None
    cov = None
    if want_cov:
        res = bw - Aw @ theta
        s2 = float(res @ res) / max(ok.sum() - A.shape[1], 1)
        cov = np.linalg.inv(M) * s2
    return theta, cov, A @ theta


def _solve_censored(A, isi, delta, sqrt_w, keep, want_cov=False):
    """Noise-free reset-to-zero: ``ISI = n + ceil(1 / lambda)``, so ``1 / lambda`` lies in
    ``(ISI - n - 1, ISI - n]`` (``delta = n + 1/2``). Alternate: fit, project the prediction
    into each pixel's interval, refit. Returns (solution, mean squared relative distance)."""
    lo, hi = np.maximum(isi - delta - 0.5, 1e-9), np.maximum(isi - delta + 0.5, 1.0)
    target = 1.0 / np.clip(isi - delta, 1.0, None)
    sol = None
    for _ in range(5):
        sol = _solve(A, isi, delta, sqrt_w, keep, want_cov, target=target)
        if sol is None:
            return None, math.inf
        inv = 1.0 / np.clip(sol[2], 1e-12, None)
        proj = np.clip(inv, lo, hi)
        target = 1.0 / proj
    rel = (inv[keep] - proj[keep]) / isi[keep]
    w = sqrt_w[keep] ** 2
    return sol, float(np.sum(w * rel * rel) / np.sum(w))


def _isi_pred(lam, delta):
    return delta + 1.0 / np.clip(lam, 1e-12, 1.0)


def _objective(isi, lam_pred, delta, w, keep):
    rel = (isi[keep] - _isi_pred(lam_pred[keep], delta)) / isi[keep]
    return float(np.sum(w[keep] * rel * rel) / np.sum(w[keep]))


def _fit_rate_model(ctx: _Context, model: dict) -> None:
    meas = ctx.meas
    base_ok = (meas.n >= MIN_SPIKES) & (meas.rate > 0)
    fl = model.get("flicker")
    if fl is not None and fl.depth > GATES["flicker"][0]:  # pixels clipped at flicker peaks average below
        base_ok &= meas.rate * (1.0 + fl.depth) < 0.9
    isi = np.where(base_ok, 1.0 / np.maximum(meas.rate, 1e-12), 0.0)
    w = np.minimum(meas.n - 1, 200).astype(np.float64)
    sqrt_w = np.sqrt(np.maximum(w, 0.0))
    B0, B1 = _bases(ctx, 1.0)
    use_c = float(np.std(B1)) > 0.01 * float(np.mean(B0))
    keep = base_ok & ~model["outlier"]

    quant = model["zero_quantised"]

    def fit_at(delta, gamma, keep, want_cov=False):
        A = _design(ctx, model, gamma, use_c)
        if quant:
            sol, obj = _solve_censored(A, isi, delta, sqrt_w, keep, want_cov)
            return obj, sol
        sol = _solve(A, isi, delta, sqrt_w, keep, want_cov)
        if sol is None:
            return math.inf, None
        return _objective(isi, sol[2], delta, w, keep), sol

    def best_gamma(delta, keep, iters=22):
        g = stats.golden_min(lambda gm: fit_at(delta, math.exp(gm), keep)[0], *np.log(GAMMA_RANGE), iters=iters)
        return math.exp(g)

    lo, hi = 0.0, DELTA_MAX
    for rnd in range(2):  # fit, drop outliers (hot pixels, dust), refit near the first answer
        if quant:  # delta = refractory frames + 1/2, exactly; intervals allow a range of models,
            # so take the shortest dead time whose fit is as good as the best (Occam)
            grid = np.arange(0.5, DELTA_MAX, 1.0)
            objs = np.array([fit_at(dl, best_gamma(dl, keep, 16), keep)[0] for dl in grid])
            delta = float(grid[np.flatnonzero(objs <= 1.5 * objs.min() + 1e-7)[0]])
        else:
            if rnd == 0:
                grid = np.arange(lo, hi + 1e-9, 0.5)
                d0 = min((fit_at(dl, best_gamma(dl, keep, 16), keep)[0], dl) for dl in grid)[1]
            lo, hi = max(0.0, d0 - 0.5 + 0.25 * rnd), min(DELTA_MAX, d0 + 0.5 - 0.25 * rnd)
            delta = stats.golden_min(lambda dl: fit_at(dl, best_gamma(dl, keep), keep)[0], lo, hi, iters=12)
        gamma = best_gamma(delta, keep, iters=30)
        obj, sol = fit_at(delta, gamma, keep, want_cov=True)
        theta, cov, lam_pred = sol
        rel = np.where(base_ok, (isi - _isi_pred(lam_pred, delta)) / np.where(base_ok, isi, 1.0), 0.0)
        if quant:
            rel = np.where(base_ok, (isi - delta + 0.5 - np.ceil(1.0 / np.clip(lam_pred, 1e-12, 1.0) - 1e-9))
                           / np.where(base_ok, isi, 1.0), 0.0)
        sd = stats.robust_sd(rel[keep])
        outlier = base_ok & (np.abs(rel) > max(6 * sd, 0.01))
        keep = base_ok & ~outlier
        d0 = delta
    a = float(theta[0])
    c = float(theta[1] / a) if use_c else 0.0
    d = float(theta[-1] / a)
    var_c = float(cov[1, 1]) / a ** 2 if use_c else math.inf
    model.update(a=a, gamma=gamma, c=c, d=d, delta=float(delta), lam_pred=lam_pred,
                 isi=np.where(base_ok, isi, np.nan), keep=keep, outlier=outlier, use_c=use_c, objective=obj,
                 se_c=math.sqrt(var_c) if use_c else math.inf, se_d=math.sqrt(float(cov[-1, -1])) / abs(a),
                 se_gamma=_gamma_se(lambda gm: fit_at(delta, gm, keep)[0], gamma, obj, int(keep.sum())))


def _gamma_se(f, gamma, obj, n):
    """Standard error of gamma from the curvature of the (mean squared relative) objective."""
    h = 1e-3 * gamma
    curv = (f(gamma + h) - 2 * obj + f(gamma - h)) / h ** 2
    if not (curv > 0) or n < 10:
        return math.inf
    return math.sqrt(2 * obj / (curv * n))


def _flicker_mean(fl, Tf) -> float:
    if fl is None or fl.depth <= 0:
        return 1.0
    t = np.arange(Tf)
    return float(1.0 + fl.depth * np.mean(np.sin(2 * np.pi * t / fl.period_frames + fl.phase)))


def _fit_flicker(ctx: _Context, model: dict):
    """Sinusoid in the population signal of unsaturated, non-outlier pixels (stats.fit_sine)."""
    meas = ctx.meas
    Tf = ctx.Tf
    K, H, W = ctx.X.shape
    lam = model.get("lam_pred")
    delta = model["delta"]
    if lam is None:  # first pass: every spike counted as light
        sens = np.ones(H * W)
        light_x = meas.rate
        lam = meas.rate
    else:
        r = 1.0 / _isi_pred(lam, delta)
        sens = (r / np.maximum(lam, 1e-12)) ** 2  # d rate / d lambda of the readout
        light_x = lam - model["a"] * model["Rb"] * (model["db"] + model["d"])
    mask = (meas.rate < 0.45) & (lam < 0.6) & ~model["outlier"] & (meas.n >= 1)
    if mask.sum() < 16:
        return None
    weight = sens * light_x
    wts = interpolation_weights(K, ctx.spikes.shape[0])[:Tf]
    xk = ctx.X.reshape(K, -1)
    scale = weight / np.maximum(xk.mean(0), 1e-9)

    def light_of(m):  # expected light spikes per frame of the pixels in m, [Tf]
        return wts @ (xk[:, m] * scale[m]).sum(axis=1)
    fit = stats.fit_sine(stats.population_signal(ctx.spikes[:Tf], mask), light_of(mask),
                         min_period=6.0, max_period=2.0 * ctx.spikes.shape[0])
    fit.mask, fit.light = mask, light_of(mask)
    # coherence: flicker modulates the light of every pixel in phase and by the same depth; the
    # beat of regular pixel trains depends on their rate. Four brightness quartiles must agree.
    edges = np.quantile(lam[mask], [0.25, 0.5, 0.75])
    groups = np.searchsorted(edges, lam)
    vecs = []
    for gi in range(4):
        m = mask & (groups == gi)
        vecs.append(stats.sine_at(stats.population_signal(ctx.spikes[:Tf], m), light_of(m), 1.0 / fit.period_frames))
    fit.coherence = float(abs(sum(vecs)) / max(sum(abs(v) for v in vecs), 1e-12))
    return fit


def _constant_interval_fraction(meas) -> float:
    """Fraction of pixels whose intervals never vary: a noise-free reset-to-zero readout (a
    subtractive reset alternates between floor and ceil of 1 / lambda unless that is an integer)."""
    sel = (meas.n_isi >= 5) & (meas.isi_mean > 2.5)
    return float(meas.single[sel].mean()) if sel.any() else 0.0


def _self_refractory(ctx: _Context) -> float:
    """With the radiance taken from the data, a dead time shows only as missing short intervals."""
    meas = ctx.meas
    bright = (meas.rate > 0.3) & (meas.n_isi >= 5)
    if bright.sum() < 10:
        return 0.0
    return float(max(0.0, np.median(meas.isi_min[bright]) - 1.0)) if np.all(meas.ones[bright] == 0) else 0.0


# ---------------------------------------------------------------------- per-pixel structure
def _pixel_structure(ctx: _Context, model: dict) -> None:
    H, W = ctx.shape
    if ctx.self_ref:
        _self_structure(ctx, model)
        return
    delta, lam_pred = model["delta"], model["lam_pred"]
    lam_obs = _lam_obs(model["isi"], delta)
    valid = model["keep"] | model["outlier"]
    valid &= (model["isi"] - delta >= 1.1) & np.isfinite(lam_obs)
    if model["zero_quantised"]:
        valid &= model["isi"] >= QUANTISED_MIN_ISI
    e = np.where(valid, lam_obs / lam_pred, np.nan)
    e1, e2 = (np.where(valid, _lam_obs(1.0 / np.maximum(h, 1e-12), delta) / lam_pred, np.nan) for h in ctx.halves)
    col = _column_factors(e, valid & ~model["outlier"], H, W)
    C = np.tile(col, H)
    resid = e / C - 1.0
    sd = stats.robust_sd(resid[valid & ~model["outlier"]])
    excess = (e - C) * lam_pred  # additive, spikes per frame
    thresh = np.maximum(0.02, 6 * sd * C * lam_pred)
    hot = valid & (excess > thresh)
    testable = valid & (thresh < 0.04) & (C * lam_pred + 0.06 < 0.9)
    if model["zero_quantised"]:  # any interval bounds lambda from below: 1 / lambda <= ISI - n
        lam_lo = _lam_obs(model["isi"], delta - 0.5)
        ok = (model["keep"] | model["outlier"]) & np.isfinite(lam_lo) & (model["isi"] - delta + 0.5 >= 1)
        excess = np.where(ok, lam_lo - C * lam_pred, 0.0)
        thresh = np.maximum(0.02, 6 * sd * C * lam_pred)
        hot = ok & (excess > thresh)
        testable = ok & (thresh < 0.04) & (C * lam_pred + 0.06 < 0.9)
    good = valid & ~hot & (np.abs(resid) < max(8 * sd, 0.02))
    good_col = good.copy()  # column means average the interval quantisation away
    if model.get("zero_quantised"):
        good &= model["isi"] >= 30
    model.update(e=e, e1=e1, e2=e2, col=col, hot=hot, testable=testable, good=good, good_col=good_col,
                 excess=excess, resid_sd=sd)


def _column_factors(e, ok, H, W):
    e2 = np.where(ok, e, np.nan).reshape(H, W)
    with warnings.catch_warnings():  # all-NaN columns are handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        col = np.nanmedian(e2, axis=0)
    col = np.where(np.isfinite(col), col, 1.0)
    return col / np.median(col)


def _self_structure(ctx: _Context, model: dict) -> None:
    """Static scene, radiance from the data: column factors against the left/right neighbours,
    hot pixels against the 3 x 3 median. Per-pixel gain cannot be told from texture."""
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
    model.update(hot=hot.reshape(-1), testable=(ok & (thresh < 0.04) & (med < 0.8)).reshape(-1),
                 excess=excess.reshape(-1), resid_sd=sd, e=None, col=np.ones(W))


# ---------------------------------------------------------------------- effects
def _effects_and_sensor(ctx: _Context, model: dict):
    found = {}
    found["gain_nonuniformity"] = _gain_effect(ctx, model)
    found["column_pattern"] = _column_effect(ctx, model)
    found["dark_current"] = _dark_effect(ctx, model)
    found["hot_pixels"] = _hot_effect(ctx, model)
    found["nonlinearity"] = _gamma_effect(ctx, model)
    found["crosstalk"] = _crosstalk_effect(ctx, model)
    found["flicker"] = _flicker_effect(ctx, model)
    found["refractory"], found["reset_to_zero"] = _readout_effects(ctx, model)
    if found["flicker"].detected:
        _check_flicker_against_model(ctx, model, found)
    deterministic = _build_sensor(ctx, model, found, electrons=0.0)
    found["shot_noise"] = _shot_effect(ctx, model, deterministic)
    extended = _build_sensor(ctx, model, found, electrons=found["shot_noise"].parameters.get("electrons") or 0.0
                             if found["shot_noise"].detected else 0.0)
    return [found[n] for n in EFFECTS], extended


def _make(name, size, z, params, note="", force=None):
    gate, zgate = GATES[name]
    detected = bool(size is not None and math.isfinite(size) and size >= gate and z >= zgate)
    if name == "shot_noise":
        detected = bool(size is not None and 0 < size <= gate and z >= zgate)
        score = ENVELOPE_SIZE[name] / size if size and size > 0 else 0.0
    else:
        score = (size or 0.0) / ENVELOPE_SIZE[name]
    if force is not None:
        detected = force
    return Effect(name, detected, float(score) if math.isfinite(score) else 0.0, params, float(z), note)


def _cov_estimate(u1, u2):
    """Covariance of two noisy copies of the same pattern, and its standard error under the
    null hypothesis of no pattern (from the noise ``(u1 - u2) / 2``)."""
    p = (u1 - u1.mean()) * (u2 - u2.mean())
    noise_var = float(np.var(u1 - u2)) / 2.0
    return float(p.mean()), noise_var / math.sqrt(max(p.size, 1))


def _gain_effect(ctx, model):
    if ctx.self_ref or model.get("e") is None:
        return Effect("gain_nonuniformity", False, 0.0, {"sigma": None}, 0.0,
                      "not separable from scene texture without a reference")
    H, W = ctx.shape
    C = np.tile(model["col"], H)
    g = model["good"] & np.isfinite(model["e1"]) & np.isfinite(model["e2"])
    if g.sum() < 50:
        return Effect("gain_nonuniformity", False, 0.0, {"sigma": None}, 0.0, "too few usable pixels")
    var, se = _cov_estimate(model["e1"][g] / C[g], model["e2"][g] / C[g])
    sigma = math.sqrt(max(var, 0.0))
    model["gain_var"] = var
    return _make("gain_nonuniformity", sigma, var / max(se, 1e-15), {"sigma": sigma})


def _column_effect(ctx, model):
    H, W = ctx.shape
    if ctx.self_ref:
        return _self_column_effect(ctx, model)
    g = model["good_col"] & np.isfinite(model["e1"]) & np.isfinite(model["e2"])
    cm = []
    for e in (model["e1"], model["e2"]):
        sums = np.where(g, e, 0.0).reshape(H, W).sum(axis=0)
        cm.append(sums / np.maximum(g.reshape(H, W).sum(axis=0), 1))
    n_col = g.reshape(H, W).sum(0)
    ok = n_col >= 4
    if ok.sum() < 8:
        return Effect("column_pattern", False, 0.0, {"sigma": None}, 0.0, "too few usable columns")
    c1, c2 = cm[0][ok] / np.mean(cm[0][ok]), cm[1][ok] / np.mean(cm[1][ok])
    var, se = _cov_estimate(c1, c2)
    var -= max(model.get("gain_var", 0.0), 0.0) * float(np.mean(1.0 / n_col[ok]))
    sigma = math.sqrt(max(var, 0.0))
    return _make("column_pattern", sigma, var / max(se, 1e-15), {"sigma": sigma})


def _self_column_effect(ctx, model):
    H, W = ctx.shape
    r = ctx.meas.rate.reshape(H, W)
    ok = (ctx.meas.n.reshape(H, W) >= MIN_SPIKES) & (r < 0.8) & ~model["hot"].reshape(H, W)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ratio = r[:, 1:-1] / (0.5 * (r[:, :-2] + r[:, 2:]))
        ratio = np.where(ok[:, 1:-1] & ok[:, :-2] & ok[:, 2:], ratio, np.nan)
        prof = np.nanmedian(ratio, axis=0)
    prof = prof[np.isfinite(prof)]
    if prof.size < 8:
        return Effect("column_pattern", False, 0.0, {"sigma": None}, 0.0, "too few usable columns")
    sigma = float(np.std(prof) / math.sqrt(1.5))
    model["col_self"] = sigma
    return _make("column_pattern", sigma, 10.0 if sigma > 0 else 0.0, {"sigma": sigma},
                 "from neighbour-column ratios (no reference)")


def _dark_effect(ctx, model):
    if ctx.self_ref:
        return Effect("dark_current", False, 0.0, {"rate": None}, 0.0, "needs a reference radiance")
    d, se = model["d"], model["se_d"]
    return _make("dark_current", d, d / max(se, 1e-15), {"rate": d})


def _hot_effect(ctx, model):
    hot, testable = model["hot"], model["testable"]
    found = int(hot.sum())
    frac = float(testable.mean())
    count = int(round(found / frac)) if frac > 0 else found
    rates = model["excess"][hot]
    return _make("hot_pixels", count if found >= GATES["hot_pixels"][0] else 0, float(found),
                 {"count": count, "found": found, "testable_fraction": frac,
                  "median_rate": float(np.median(rates)) if found else None})


def _gamma_effect(ctx, model):
    if ctx.self_ref:
        return Effect("nonlinearity", False, 0.0, {"gamma": None}, 0.0, "needs a reference radiance")
    g, se = model["gamma"], model["se_gamma"]
    if model["zero_quantised"] and not math.isfinite(se):  # censored fit: flat objective, size gate only
        return _make("nonlinearity", abs(g - 1.0), math.inf, {"gamma": g}, "censored fit: no standard error")
    return _make("nonlinearity", abs(g - 1.0), abs(g - 1.0) / max(se, 1e-15), {"gamma": g})


def _crosstalk_effect(ctx, model):
    if ctx.self_ref or not model.get("use_c"):
        return Effect("crosstalk", False, 0.0, {"fraction": None}, 0.0,
                      "needs a reference with pixel-scale texture")
    c, se = model["c"], model["se_c"]
    return _make("crosstalk", c, c / max(se, 1e-15), {"fraction": c})


def _flicker_effect(ctx, model):
    fl = model["flicker"]
    if fl is None:
        return Effect("flicker", False, 0.0, {"period_frames": None, "depth": None}, 0.0, "too few unsaturated pixels")
    params = {"period_frames": fl.period_frames, "depth": fl.depth, "phase_rad": fl.phase,
              "group_coherence": fl.coherence}
    eff = _make("flicker", fl.depth, fl.z, params)
    if fl.coherence < MIN_COHERENCE:
        eff.detected = False
        eff.note = "periodicity not shared by all pixels (beat of regular pixel trains, not flicker)"
    return eff


def _check_flicker_against_model(ctx, model, found):
    """A readout with a dead time or a reset to zero makes the population signal ring at the
    rates of its pixels. Simulate the fitted model without flicker: if it shows the same line,
    the line is the readout's, not the light's."""
    fl = model["flicker"]
    flags = {k: v for k, v in found.items() if k != "flicker"}
    sensor = _build_sensor(ctx, model, flags, electrons=0.0)
    sim = simulate(ctx.X, ctx.intensity, sensor, frames=ctx.spikes.shape[0], seed=SIM_SEED)[:ctx.Tf]
    own = abs(stats.sine_at(stats.population_signal(sim, fl.mask), fl.light, 1.0 / fl.period_frames))
    eff = found["flicker"]
    eff.parameters["model_depth_at_period"] = own
    if fl.depth < 2.0 * own or fl.depth - own < GATES["flicker"][0]:
        eff.detected = False
        eff.note = "the fitted model without flicker shows the same line (readout ringing)"


def _readout_effects(ctx, model):
    """Refractory frames and reset-to-zero from the interval offset and interval constancy."""
    delta = model["delta"]
    single = model["constant_fraction"]
    frac = delta - math.floor(delta)
    half = 0.3 <= frac <= 0.7
    zero = half or single > 0.5
    frames = int(round(delta - (0.5 if zero else 0.0)))
    frames = max(frames, 0)
    refr = _make("refractory", float(frames), 0.0, {"frames": frames, "interval_offset": delta})
    zscore = max(single * 2, 1.0 if half else 0.0)
    rz = _make("reset_to_zero", zscore, 0.0, {"interval_offset": delta, "constant_interval_fraction": single},
               force=zero)
    rz.score = zscore if zero else 0.0
    return refr, rz


def _shot_effect(ctx, model, deterministic: Sensor):
    """Interval variance beyond the noise-free model: ``var(ISI) = 1 / (N_e lambda^2)``."""
    T = ctx.spikes.shape[0]
    sim = simulate(ctx.X, ctx.intensity, deterministic, frames=T, seed=SIM_SEED)[:ctx.Tf]
    ps = stats.pixel_stats(sim)
    noisy = ctx.meas.isi_var >= 2.0  # the same estimator for both streams, pixel by pixel
    vm, vs = stats.excess_interval_var(ctx.meas, noisy), stats.excess_interval_var(ps, noisy)
    refr = deterministic.refractory_frames
    with np.errstate(all="ignore"):
        lam = 1.0 / (ctx.meas.isi_mean - refr)
    ok = np.isfinite(vm) & np.isfinite(vs) & np.isfinite(lam) & (lam > 0) & (ctx.meas.n_isi >= 8)
    ok &= ~model["hot"]
    if ok.sum() < 20:
        return Effect("shot_noise", False, 0.0, {"electrons": None}, 0.0, "too few pixels with enough intervals")
    y = (vm[ok] - vs[ok]) * lam[ok] ** 2  # estimates 1 / N_e per pixel
    n = ctx.meas.n_isi[ok]
    inv = 1e-3
    for _ in range(3):  # inverse-variance weights: sampling variance + quantisation residue
        v = max(inv, 0.0) / lam[ok] ** 2 + np.abs(vs[ok])  # the model's own spread counts too
        var_y = lam[ok] ** 4 * (2 * v ** 2 / (n - 1) + 0.02 / n)
        wts = 1.0 / var_y
        inv = float(np.sum(wts * y) / np.sum(wts))
    # empirical standard error: deterministic interval modulation (flicker, motion) that the
    # model reproduces only on average widens the spread of y beyond the weights' assumption
    se = float(np.sqrt(np.sum(wts ** 2 * (y - inv) ** 2)) / np.sum(wts))
    electrons = 1.0 / inv if inv > 0 else math.inf
    eff = _make("shot_noise", electrons if inv > 0 else None, inv / max(se, 1e-15), {"electrons": electrons if inv > 0 else None})
    # flicker (or motion) the model reproduces makes intervals vary like 1 / lambda^2 too; an
    # excess below 10 % of that deterministic variance is within the error of the fitted modulation
    model_level = float(np.sum(wts * np.maximum(vs[ok], 0.0) * lam[ok] ** 2) / np.sum(wts))
    if eff.detected and inv < MODEL_VARIANCE_SHARE * model_level:
        eff.detected = False
        eff.note = "interval variance within the error of the fitted deterministic modulation (flicker)"
    return eff


# ---------------------------------------------------------------------- the extended sensor
def _build_sensor(ctx: _Context, model: dict, found: dict, electrons: float) -> Sensor:
    H, W = ctx.shape
    P = H * W
    on = {k: v.detected for k, v in found.items()}
    Rb, db = model["Rb"], model["db"]
    a = model.get("a", 1.0)
    R = Rb * a
    e = model.get("e")
    if on.get("column_pattern") and not ctx.self_ref:
        R = R * np.tile(model["col"], H)
    if on.get("gain_nonuniformity") and e is not None:
        C = np.tile(model["col"], H) if on.get("column_pattern") else np.ones(P)
        use = np.isfinite(e) & ~model["hot"]
        R = np.where(use, Rb * a * e, Rb * a * C)
    d = db.copy()
    if on.get("dark_current"):
        d = d + max(model["d"], 0.0)
    if on.get("hot_pixels") and not ctx.self_ref:  # with 'self' the radiance already holds them
        hot = model["hot"]
        d[hot] += model["excess"][hot] / np.maximum(R[hot], 1e-6)
    fl = found.get("flicker")
    kw = dict(responsivity=R.reshape(H, W) if not np.allclose(R, 1.0) else None,
              dark_rate=d.reshape(H, W) if d.any() else None)
    if on.get("flicker"):
        kw.update(flicker_period_frames=fl.parameters["period_frames"], flicker_depth=fl.parameters["depth"])
    if on.get("crosstalk"):
        kw["crosstalk_fraction"] = model["c"]
    if on.get("nonlinearity"):
        kw["gamma"] = model["gamma"]
    if on.get("refractory"):
        kw["refractory_frames"] = int(found["refractory"].parameters["frames"])
    if on.get("reset_to_zero"):
        kw["reset"] = "zero"
    if electrons and math.isfinite(electrons):
        kw["electrons"] = float(electrons)
    base = ctx.baseline
    return base.replace(name=f"{base.name}+extended", map_model=None,
                        notes={"fitted_by": "spikegen diagnose", "effects": [k for k, v in on.items() if v]}, **kw)
