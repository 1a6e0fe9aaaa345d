"""The fits of ``spikegen diagnose`` (steps 2-3 of diagnose.py): flicker and the mean-rate model.

Each fit takes the :class:`~.records.Context` and the records it depends on, and returns a
new frozen record.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..sensor import interpolation_weights, neighbour_mean
from . import bands, exact, stats
from .records import (GATES, MIN_COHERENCE, MIN_SPIKES, Context, FlickerFit, RateFit, equivalent_isi, flicker_mean_isi,
                      flicker_rate_table, interval_frames)

GAMMA_RANGE = (0.25, 4.0)
DELTA_MAX = 6.0


# ---------------------------------------------------------------------- readout evidence
def constant_interval_fraction(meas: stats.PixelStats) -> float:
    """Fraction of pixels whose intervals never vary: a noise-free reset-to-zero readout (a
    subtractive reset alternates between floor and ceil of 1 / lambda unless that is an integer)."""
    sel = (meas.n_isi >= 5) & (meas.isi_mean > 2.5)
    return float(meas.single[sel].mean()) if sel.any() else 0.0


def self_refractory(meas: stats.PixelStats) -> float:
    """With the radiance taken from the data, a dead time shows only as missing short intervals."""
    bright = (meas.rate > 0.3) & (meas.n_isi >= 5)
    if bright.sum() < 10:
        return 0.0
    return float(max(0.0, np.median(meas.isi_min[bright]) - 1.0)) if np.all(meas.ones[bright] == 0) else 0.0


# ---------------------------------------------------------------------- the mean-rate model
def _bases(ctx: Context, gamma: float):
    """``B0, B1 [P]``: time-mean of X^gamma and of its 4-neighbour contrast over the fit frames."""
    K, H, W = ctx.X.shape
    if K == 1:
        xg = ctx.X[0] ** gamma
        return xg.reshape(-1), (neighbour_mean(xg) - xg).reshape(-1)
    ts = np.unique(np.linspace(0, ctx.Tf - 1, min(ctx.Tf, 48)).astype(int))
    wts = interpolation_weights(K, ctx.frames)[ts]
    xg = exact.interpolate(wts, ctx.X.reshape(K, -1)).reshape(-1, H, W) ** gamma
    return xg.mean(0).reshape(-1), (neighbour_mean(xg) - xg).mean(0).reshape(-1)


def _design(ctx: Context, fbar: float, gamma: float, use_c: bool) -> list:
    """The columns (``[P]`` each, 2 or 3) of the design: the model's rate is linear in
    ``(a, [a c,] a d)`` for fixed gamma."""
    B0, B1 = _bases(ctx, gamma)
    Rb, db = ctx.Rb, ctx.db
    gf = ctx.g * fbar
    cols = [Rb * (gf * B0 + db), Rb]
    if use_c:
        cols.insert(1, Rb * gf * B1)
    return cols


def _solve(A, isi, delta, sqrt_w, keep, want_cov=False, target=None):
    """Weighted LSQ of ``lambda_obs = 1 / (ISI - delta)`` (or of ``target``) on the design
    ``A`` (its columns, :func:`_design`), relative errors weighted by ``w``; returns (theta,
    cov or None, lam_pred [P]). Sums by exact (one order, whatever the BLAS threads), column by
    column: the same bits as on the stacked ``[P, p]`` matrix."""
    if target is None:
        x = isi - delta
        ok = keep & (x >= 1.05)
    else:
        x = 1.0 / np.maximum(target, 1e-12)
        ok = keep & (target < 0.95)
    n_ok = int(ok.sum())
    if n_ok < len(A) + 5:
        return None
    bw = sqrt_w[ok]  # lambda_obs * sw
    sw = bw * x[ok]  # sqrt(w) / lambda_obs
    Aw = [col[ok] * sw for col in A]
    M, v = exact.normal_equations(Aw, bw)
    try:
        theta = np.linalg.solve(M, v)
    except np.linalg.LinAlgError:
        return None
    cov = None
    if want_cov:
        res = bw - exact.matvec_columns(Aw, theta)
        s2 = exact.dot(res, res) / max(n_ok - len(A), 1)
        cov = np.linalg.inv(M) * s2
    return theta, cov, exact.matvec_columns(A, theta)


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


def _gamma_se(f, gamma, obj, n):
    """Standard error of gamma from the curvature of the (mean squared relative) objective."""
    h = 1e-3 * gamma
    curv = (f(gamma + h) - 2 * obj + f(gamma - h)) / h ** 2
    if not (curv > 0) or n < 10:
        return math.inf
    return math.sqrt(2 * obj / (curv * n))


@dataclass(frozen=True, eq=False)
class _RateProblem:
    """The data of one rate-model fit: measured mean intervals of the usable pixels, weights."""

    ctx: Context
    fbar: float  # mean flicker factor the design uses
    use_c: bool  # fit crosstalk (the reference has pixel-scale texture)
    isi: np.ndarray  # [P] measured mean interval, frames (0 outside base_ok)
    base_ok: np.ndarray  # [P] pixels with enough spikes (and not clipped at flicker peaks)
    w: np.ndarray  # [P] weights: intervals counted, at most 200
    sqrt_w: np.ndarray  # [P]
    phi: tuple | None  # flicker factors over fbar: (fit window, first half, second half); None: no flicker
    tables: dict  # delta -> flicker_rate_table of the fit window; ("kept", id) -> :meth:`kept`

    @classmethod
    def build(cls, ctx: Context, flicker: FlickerFit | None, fbar: float) -> "_RateProblem":
        meas = ctx.meas
        base_ok = (meas.n >= MIN_SPIKES) & (meas.rate > 0)
        if flicker is not None and flicker.depth > GATES["flicker"][0]:  # pixels clipped at flicker peaks average below
            base_ok &= meas.rate * (1.0 + flicker.depth) < 0.9
        isi = np.where(base_ok, 1.0 / np.maximum(meas.rate, 1e-12), 0.0)
        w = np.minimum(meas.n - 1, 200).astype(np.float64)
        B0, B1 = _bases(ctx, 1.0)
        use_c = float(np.std(B1)) > 0.01 * float(np.mean(B0))
        phi = None  # a flicker shared by all pixels; never with constant intervals (a noise-free
        # reset to zero, whose censored fit needs the whole-frame intervals as measured)
        if (flicker is not None and flicker.depth > GATES["flicker"][0] and flicker.coherence >= MIN_COHERENCE
                and not ctx.zero_quantised):
            t = np.arange(ctx.Tf)
            f = (1.0 + flicker.depth * np.sin(2 * np.pi * t / flicker.period_frames + flicker.phase_rad)) / fbar
            half = ctx.Tf // 2
            phi = (f, f[:half], f[half:])
        return cls(ctx, fbar, use_c, isi, base_ok, w, np.sqrt(np.maximum(w, 0.0)), phi, {})

    def table(self, delta):
        """records.flicker_rate_table of readout ``delta`` over the fit window (None without flicker)."""
        if self.phi is None:
            return None
        key = float(delta)
        if key not in self.tables:
            self.tables[key] = flicker_rate_table(key, self.phi[0])
        return self.tables[key]

    def isi_at(self, delta) -> np.ndarray:
        """``[P]`` the measured mean intervals as the flicker-free intervals of readout ``delta``
        (records.equivalent_isi; the intervals themselves without flicker): the target of the
        linear step. The objective compares the measured intervals themselves with the model's
        flicker-averaged ones (:meth:`predicted`), so that it means the same at every delta."""
        return np.where(self.base_ok, equivalent_isi(self.isi, delta, self.table(delta)), 0.0)

    def predicted(self, lam_pred, delta) -> np.ndarray:
        """``[P]`` the model's mean interval over the fit window (flicker included)."""
        return flicker_mean_isi(lam_pred, delta, self.table(delta))

    def fit_at(self, delta, gamma, keep, want_cov=False):
        """``(objective, (theta, cov, lam_pred [P]) or None)`` at fixed ``(delta, gamma)``."""
        A = _design(self.ctx, self.fbar, gamma, self.use_c)
        isi = self.isi_at(delta)
        if self.ctx.zero_quantised:
            sol, obj = _solve_censored(A, isi, delta, self.sqrt_w, keep, want_cov)
            return obj, sol
        sol = _solve(A, isi, delta, self.sqrt_w, keep, want_cov)
        if sol is None:
            return math.inf, None
        # the objective: weighted mean squared relative error of the predicted mean intervals
        isi_k, w_k, w_sum = self.kept(keep)
        rel = (isi_k - self.predicted(sol[2][keep], delta)) / isi_k
        return float(np.sum(w_k * rel * rel) / w_sum), sol

    def kept(self, keep) -> tuple:
        """``(isi[keep], w[keep], sum of w[keep])``, kept for the array ``keep`` (the fits of a
        round share one; it is never changed in place)."""
        hit = self.tables.get(("kept", id(keep)))
        if hit is None or hit[0] is not keep:
            w_k = self.w[keep]
            hit = self.tables[("kept", id(keep))] = (keep, self.isi[keep], w_k, np.sum(w_k))
        return hit[1:]

    def best_gamma(self, delta, keep, iters=22) -> float:
        g = stats.golden_min(lambda gm: self.fit_at(delta, math.exp(gm), keep)[0], *np.log(GAMMA_RANGE), iters=iters)
        return math.exp(g)

    def coarse_objective(self, delta, keep) -> float:
        """Objective at ``delta`` with gamma from a coarse search (for grids over delta)."""
        return self.fit_at(delta, self.best_gamma(delta, keep, 16), keep)[0]

    def search_delta(self, keep, rnd: int, d0: float | None) -> float:
        """``delta`` of round ``rnd``: a grid (``d0`` None), then golden section near ``d0``."""
        if self.ctx.zero_quantised:  # delta = refractory frames + 1/2, exactly; intervals allow a range of
            # models, so take the shortest dead time whose fit is as good as the best (Occam)
            grid = np.arange(0.5, DELTA_MAX, 1.0)
            objs = np.array([self.coarse_objective(dl, keep) for dl in grid])
            return float(grid[np.flatnonzero(objs <= 1.5 * objs.min() + 1e-7)[0]])
        if d0 is None:
            grid = np.arange(0.0, DELTA_MAX + 1e-9, 0.5)
            d0 = min((self.coarse_objective(dl, keep), dl) for dl in grid)[1]
        lo, hi = max(0.0, d0 - 0.5 + 0.25 * rnd), min(DELTA_MAX, d0 + 0.5 - 0.25 * rnd)
        return stats.golden_min(lambda dl: self.fit_at(dl, self.best_gamma(dl, keep), keep)[0], lo, hi, iters=12)

    def outliers(self, delta, lam_pred, keep) -> np.ndarray:
        """``[P]`` pixels whose relative interval error is beyond 6 robust SDs (and 1 %)."""
        isi = self.isi
        if self.ctx.zero_quantised:
            err = isi - delta + 0.5 - np.ceil(1.0 / np.clip(lam_pred, 1e-12, 1.0) - 1e-9)
        else:
            err = isi - self.predicted(lam_pred, delta)
        rel = np.where(self.base_ok, err / np.where(self.base_ok, isi, 1.0), 0.0)
        sd = stats.robust_sd(rel[keep])
        return self.base_ok & (np.abs(rel) > max(6 * sd, 0.01))

    def result(self, delta, gamma, obj, solution, fit_keep, keep, outlier) -> RateFit:
        """The record of ``solution`` (fitted on pixels ``fit_keep`` with objective ``obj``);
        ``keep`` and ``outlier`` after its outlier update."""
        theta, cov, lam_pred = solution
        a = float(theta[0])
        # the curvature around obj on the same pixels as obj (the updated keep has another objective)
        se_gamma = _gamma_se(lambda gm: self.fit_at(delta, gm, fit_keep)[0], gamma, obj, int(fit_keep.sum()))
        _, linear = self.fit_at(delta, 1.0, keep)
        if linear is None:
            linear = solution
        t1 = linear[0]
        return RateFit(a=a, gamma=gamma, c=float(theta[1] / a) if self.use_c else 0.0, d=float(theta[-1] / a),
                       delta=float(delta), fbar=self.fbar, use_c=self.use_c,
                       se_c=math.sqrt(float(cov[1, 1]) / a ** 2) if self.use_c else math.inf,
                       se_d=math.sqrt(float(cov[-1, -1])) / abs(a), se_gamma=se_gamma, objective=obj,
                       lam_pred=lam_pred, isi=np.where(self.base_ok, self.isi, np.nan),
                       isi_eq=np.where(self.base_ok, self.isi_at(delta), np.nan), phi=self.phi, keep=keep, outlier=outlier,
                       linear=(float(t1[0]), float(t1[1] / t1[0]) if self.use_c else 0.0, float(t1[-1] / t1[0])),
                       lam_linear=linear[2])


def fit_rate_model(ctx: Context, flicker: FlickerFit | None, fbar: float, outlier: np.ndarray) -> RateFit:
    """Fit the mean-rate model to the measured mean intervals, leaving out ``outlier [P]`` at
    first: ``delta`` on a grid then by golden section, ``gamma`` by golden section, the linear
    parameters by weighted least squares; drop new outliers and refit near the first answer."""
    prob = _RateProblem.build(ctx, flicker, fbar)
    keep, d0 = prob.base_ok & ~outlier, None
    for rnd in range(2):
        delta = prob.search_delta(keep, rnd, d0)
        gamma = prob.best_gamma(delta, keep, iters=30)
        obj, solution = prob.fit_at(delta, gamma, keep, want_cov=True)
        fit_keep = keep
        outlier = prob.outliers(delta, solution[2], keep)
        keep, d0 = prob.base_ok & ~outlier, delta
    return prob.result(delta, gamma, obj, solution, fit_keep, keep, outlier)


# ---------------------------------------------------------------------- flicker
def fit_flicker(ctx: Context, rate: RateFit | None) -> FlickerFit | None:
    """Sinusoid in the population signal of unsaturated, non-outlier, static pixels (stats.fit_sine);
    the expected light comes from ``rate``, or (None) from the measured rates. None if fewer
    than 16 pixels qualify."""
    lam, weight, outlier = _light_weights(ctx, rate)
    mask = (ctx.meas.rate < 0.45) & (lam < 0.6) & ~outlier & (ctx.meas.n >= 1) & ctx.static
    if mask.sum() < 16:
        return None
    light_of = _light_of(ctx, weight)
    light = light_of(mask)
    groups = _brightness_quartiles(lam, mask)
    # one read of the fit window for the four groups; their sum is the signal of the whole mask
    # (whole numbers: the same as reading it alone)
    group_signals = bands.population_signals(ctx.spikes, groups, ctx.rows, 0, ctx.Tf)
    sine = stats.fit_sine(sum(group_signals), light, min_period=6.0, max_period=2.0 * ctx.frames)
    coherence = _coherence(groups, group_signals, light_of, sine.period_frames)
    return FlickerFit(sine.period_frames, sine.depth, sine.phase, sine.z, coherence, mask, light)


def _light_weights(ctx: Context, rate: RateFit | None):
    """``(lambda [P], light weight [P], outlier [P])``: the weight is a pixel's light spikes per
    frame times the readout's ``(d rate / d lambda)``."""
    meas = ctx.meas
    if rate is None or rate.lam_pred is None:  # every spike counted as light
        return meas.rate, np.ones(meas.rate.size) * meas.rate, np.zeros(meas.rate.size, dtype=bool)
    lam = rate.lam_pred
    r = 1.0 / interval_frames(lam, rate.delta)
    sens = (r / np.maximum(lam, 1e-12)) ** 2  # d rate / d lambda of the readout
    light_x = lam - rate.a * ctx.Rb * (ctx.db + rate.d)
    return lam, sens * light_x, rate.outlier


def _light_of(ctx: Context, weight: np.ndarray):
    """A function: pixel mask ``[P]`` -> expected light spikes per frame of those pixels ``[Tf]``."""
    K = ctx.X.shape[0]
    wts = interpolation_weights(K, ctx.frames)[:ctx.Tf]
    xk = ctx.X.reshape(K, -1)
    scale = weight / np.maximum(xk.mean(0), 1e-9)
    return lambda m: exact.matvec(wts, (xk[:, m] * scale[m]).sum(axis=1))


def _brightness_quartiles(lam, mask) -> list:
    """The pixels of ``mask [P]`` in four groups ``[P]`` by the quartiles of ``lam`` over ``mask``."""
    edges = np.quantile(lam[mask], [0.25, 0.5, 0.75])
    groups = np.searchsorted(edges, lam)
    return [mask & (groups == gi) for gi in range(4)]


def _coherence(groups, signals, light_of, period_frames) -> float:
    """Flicker modulates the light of every pixel in phase and by the same depth; the beat of
    regular pixel trains depends on their rate. Agreement of four brightness quartiles (``groups``,
    :func:`_brightness_quartiles`, with their population ``signals``)."""
    vecs = [stats.sine_at(signal, light_of(m), 1.0 / period_frames) for m, signal in zip(groups, signals)]
    return float(abs(sum(vecs)) / max(sum(abs(v) for v in vecs), 1e-12))
