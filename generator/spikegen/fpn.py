"""Fixed-pattern maps described statistically, so a measured camera can be drawn at any size.

A measured responsivity map ``R`` (median 1) and dark-current map ``L_d`` (lux-equivalent) are
described by:

- ``vignette``: a degree-4 polynomial of ``log R`` in normalised coordinates ``u, v`` in
  ``[-1, 1]`` (optics: it scales with the image plane, so it is the one part that is resized);
- ``column_sigma`` / ``row_sigma``: std of per-column / per-row factors of ``log R``;
- ``pixel_quantiles``: the distribution of the remaining per-pixel ``log R`` (1001 quantiles,
  so the heavy tails of dust and bright pixels are kept);
- ``dark_log_quantiles``: the distribution of ``log L_d`` of ordinary pixels, tied to the
  pixel term by a Gaussian copula of correlation ``dark_pixel_rho``;
- ``hot_threshold_lux``, ``hot_fraction``, ``hot_values_lux``: hot pixels.

Drawing keeps per-pixel patterns per-pixel: no map is ever interpolated.
"""
from __future__ import annotations

import math

import numpy as np

from .seeding import map_seed

N_QUANTILES = 1001
HOT_THRESHOLD_LUX = 60.0


def _coords(height: int, width: int):
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    u = (x - (width - 1) / 2) / max((width - 1) / 2, 1)
    v = (y - (height - 1) / 2) / max((height - 1) / 2, 1)
    return u, v


def _poly_terms(u, v, degree=4):
    return [u ** i * v ** j for i in range(degree + 1) for j in range(degree + 1 - i)]


def robust_sd(a) -> float:
    """Standard deviation estimated from the median absolute deviation (1.4826 MAD: exact for a
    normal distribution, unmoved by outliers such as dust and hot pixels); non-finite values are
    ignored, NaN if none is left."""
    a = np.asarray(a, dtype=np.float64).ravel()
    a = a[np.isfinite(a)]
    if a.size == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(a - np.median(a))))


def _norm_cdf(z):
    # Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7): enough for a copula.
    z = np.asarray(z, dtype=np.float64)
    x = np.abs(z) / math.sqrt(2.0)
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    erf = 1.0 - poly * np.exp(-x * x)
    return 0.5 * (1.0 + np.sign(z) * erf)


def _normal_scores(a):
    """Rank-based normal scores of ``a`` (for estimating a copula correlation)."""
    ranks = np.argsort(np.argsort(a.ravel()))
    p = (ranks + 0.5) / a.size
    # inverse CDF by bisection-free approximation (Acklam would do; a lookup suffices here)
    grid = np.linspace(-6, 6, 4801)
    return np.interp(p, _norm_cdf(grid), grid)


def fit_map_model(responsivity: np.ndarray, dark_lux: np.ndarray) -> dict:
    """Describe measured maps statistically. ``responsivity`` any scale (normalised to median 1
    here), ``dark_lux`` the dark current as equivalent light (Eq. S3)."""
    R = np.asarray(responsivity, dtype=np.float64)
    R = R / np.median(R)
    H, W = R.shape
    u, v = _coords(H, W)
    A = np.stack([t.ravel() for t in _poly_terms(u, v)], axis=1)
    logr = np.log(R).ravel()
    keep = np.ones(logr.size, dtype=bool)
    for _ in range(4):  # robust: ignore dust and hot outliers in the smooth fit
        coef, *_ = np.linalg.lstsq(A[keep], logr[keep], rcond=None)
        res = logr - A @ coef
        keep = np.abs(res) < 4 * robust_sd(res)
    res = res.reshape(H, W)
    col = np.median(res, axis=0)
    res = res - col[None, :]
    row = np.median(res, axis=1)
    pix = res - row[:, None]
    probs = np.linspace(0, 1, N_QUANTILES)
    dark = np.asarray(dark_lux, dtype=np.float64)
    hot = dark > HOT_THRESHOLD_LUX
    log_dark = np.log(np.maximum(dark, 1e-6))
    rho = float(np.corrcoef(_normal_scores(pix[~hot]), _normal_scores(log_dark[~hot]))[0, 1])
    return {
        "source_shape": [H, W],
        "vignette_degree": 4,
        "vignette_coefficients": [float(c) for c in coef],
        "column_sigma": float(np.std(col)),
        "row_sigma": float(np.std(row)),
        "pixel_sigma_robust": robust_sd(pix),
        "pixel_quantiles": [float(q) for q in np.quantile(pix, probs)],
        "dark_log_quantiles": [float(q) for q in np.quantile(log_dark[~hot], probs)],
        "dark_pixel_rho": rho,
        "dark_median_lux": float(np.median(dark)),
        "hot_threshold_lux": HOT_THRESHOLD_LUX,
        "hot_fraction": float(hot.mean()),
        "hot_values_lux": [float(x) for x in np.sort(dark[hot])],
    }


def draw_maps(model: dict, height: int, width: int, camera_seed: int = 0, lux_to_rate: float | None = None,
              preset: str = "paper") -> tuple[np.ndarray, np.ndarray]:
    """Draw ``(R [H, W] float32 median 1, d [H, W] float32 spikes/frame)`` with the model's statistics.

    Seeded by (camera_seed, preset, H, W): the same camera at the same size is the same map.
    ``d = L_d * lux_to_rate`` (``lux_to_rate`` from the argument or the model).
    """
    rng = np.random.Generator(np.random.PCG64(map_seed(camera_seed, preset, height, width)))
    u, v = _coords(height, width)
    coef = np.asarray(model["vignette_coefficients"])
    log_r = sum(c * t for c, t in zip(coef, _poly_terms(u, v, int(model.get("vignette_degree", 4)))))
    log_r = log_r + rng.normal(0.0, model["column_sigma"], size=(1, width))
    log_r = log_r + rng.normal(0.0, model["row_sigma"], size=(height, 1))
    probs = np.linspace(0, 1, len(model["pixel_quantiles"]))
    z1 = rng.standard_normal((height, width))
    z2 = rng.standard_normal((height, width))
    rho = float(model.get("dark_pixel_rho", 0.0))
    zd = rho * z1 + math.sqrt(max(0.0, 1 - rho * rho)) * z2
    log_r = log_r + np.interp(_norm_cdf(z1), probs, model["pixel_quantiles"])
    resp = np.exp(log_r)
    resp /= np.median(resp)
    dark_lux = np.exp(np.interp(_norm_cdf(zd), probs, model["dark_log_quantiles"]))
    n_hot = int(rng.binomial(height * width, model["hot_fraction"])) if model["hot_fraction"] > 0 else 0
    if n_hot:
        where = rng.choice(height * width, size=n_hot, replace=False)
        values = rng.choice(np.asarray(model["hot_values_lux"]), size=n_hot) * np.exp(rng.normal(0, 0.1, n_hot))
        dark_lux.ravel()[where] = values
    scale = lux_to_rate if lux_to_rate is not None else model.get("lux_to_rate", 0.0)
    return resp.astype(np.float32), (dark_lux * scale).astype(np.float32)
