"""The effects of sensor-model.md as data: names, parameters, detectability envelope, and a
generator of "measured" recordings with known effects (for the hidden-effect tests and docs).

Map effects are drawn so that the realised map has exactly the named statistic:
``R = C[column] * P[pixel]`` with ``std(C) = column sigma`` (mean 1) and ``std(P) = gain sigma``
(median 1); ``d = rate * exp(spread * z)`` with ``z`` of median 0 and SD 1 over the pixels
(so ``rate`` is the median dark rate and ``spread`` the SD of its logarithm), plus ``count`` hot
pixels of rate ``U(hot_min, hot_max)``; ``count`` dead pixels have ``R = d = 0`` (never fire).
"""
from __future__ import annotations

import math

import numpy as np

from ..sensor import Sensor

EFFECTS = ("gain_nonuniformity", "column_pattern", "dark_current", "hot_pixels", "shot_noise", "reset_to_zero",
           "refractory", "flicker", "crosstalk", "nonlinearity", "dead_pixels", "threshold_jitter")

# The detectability envelope (the numbers): the weakest effect the tools must find in a
# recording of >= 1000 frames, >= 64 x 64 pixels, intensity 32..256, radiance spanning 0.05..1.
ENVELOPE = {
    "gain_nonuniformity": {"sigma": 0.03},
    "column_pattern": {"sigma": 0.02},
    "dark_current": {"rate": 0.002},
    "hot_pixels": {"count": 5, "rate": 0.05},
    "shot_noise": {"electrons": 2000},
    "reset_to_zero": {},
    "refractory": {"frames": 1},
    "flicker": {"depth": 0.05, "period_frames": (10, 1000)},
    "crosstalk": {"fraction": 0.05},
    "nonlinearity": {"gamma_offset": 0.1},
    "dead_pixels": {"count": 5},
    "threshold_jitter": {"sigma": 0.008},
}
# The entry of ENVELOPE that is each effect's size (None: an on/off effect, size 1).
SIZE_KEY = {"gain_nonuniformity": "sigma", "column_pattern": "sigma", "dark_current": "rate", "hot_pixels": "count",
            "shot_noise": "electrons", "reset_to_zero": None, "refractory": "frames", "flicker": "depth",
            "crosstalk": "fraction", "nonlinearity": "gamma_offset", "dead_pixels": "count",
            "threshold_jitter": "sigma"}


def envelope_size(name: str) -> float:
    """The weakest size of effect ``name`` the tools must find (:data:`ENVELOPE`; 1 if on/off)."""
    key = SIZE_KEY[name]
    return 1.0 if key is None else float(ENVELOPE[name][key])


# Ranges the tests draw from (lower ends = the envelope; upper ends are this project's choice).
RANGES = {
    "gain_nonuniformity": {"sigma": (0.03, 0.12)},
    "column_pattern": {"sigma": (0.02, 0.08)},
    "dark_current": {"rate": (0.002, 0.02), "spread": (0.0, 0.6)},
    "hot_pixels": {"count": (5, 30)},
    "shot_noise": {"electrons": (20, 2000)},
    "reset_to_zero": {},
    "refractory": {"frames": (1, 4)},
    "flicker": {"period_frames": (10, 1000), "depth": (0.05, 0.4)},
    "crosstalk": {"fraction": (0.05, 0.3)},
    "nonlinearity": {"gamma": (0.6, 1.5)},
    "dead_pixels": {"count": (5, 30)},
    "threshold_jitter": {"sigma": (0.008, 0.05)},
}
HOT_RATE = (0.05, 0.3)

# Pairs the diagnosis is known to confuse (docs/fidelity.md, "Known limits"): a reset to zero
# under shot noise of ~10^3 electrons looks like a mixture of several mean-rate effects; a
# threshold jitter under a reset to zero accumulates (the charge starts from 0 after each spike,
# so each interval is (1 + eps_k) / lambda, independent of the last): it is read as shot noise.
KNOWN_CONFUSIONS = {frozenset(("reset_to_zero", "shot_noise")), frozenset(("reset_to_zero", "threshold_jitter"))}


def draw_pair(rng: np.random.Generator) -> list:
    """Two different effects at random, outside :data:`KNOWN_CONFUSIONS`."""
    while True:
        pair = [str(n) for n in rng.choice(EFFECTS, size=2, replace=False)]
        if frozenset(pair) not in KNOWN_CONFUSIONS:
            return pair


def draw_parameters(name: str, rng: np.random.Generator) -> dict:
    """Random parameters of effect ``name`` inside :data:`RANGES` (log-uniform for scales)."""
    if name == "reset_to_zero":
        return {}
    if name == "refractory":
        return {"frames": int(rng.integers(1, 5))}
    if name in ("hot_pixels", "dead_pixels"):
        return {"count": int(rng.integers(5, 31))}
    if name == "dark_current":  # the median log-uniform, its log-SD uniform
        lo, hi = RANGES[name]["rate"]
        return {"rate": float(math.exp(rng.uniform(math.log(lo), math.log(hi)))),
                "spread": float(rng.uniform(*RANGES[name]["spread"]))}
    if name == "nonlinearity":
        off = rng.uniform(0.1, 0.45)
        return {"gamma": float(1 + off if rng.random() < 0.5 else 1 - off)}
    out = {}
    for key, (lo, hi) in RANGES[name].items():
        out[key] = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return out


def test_radiance(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A textured reference ``float64 [H, W]`` spanning 0.05..1 (log-uniform-ish): a smooth
    field plus pixel-scale texture, so both per-pixel and neighbourhood effects show."""
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    smooth = 0.5 + 0.25 * np.sin(2 * np.pi * (xx * rng.uniform(1, 2) + yy * rng.uniform(0.5, 1.5)))
    u = np.clip(smooth + 0.35 * rng.uniform(-1, 1, size=(height, width)), 0.0, 1.0)
    return 0.05 * 20.0 ** u


def _standard(z: np.ndarray) -> np.ndarray:
    return (z - z.mean()) / z.std()


def _dark_map(params: dict, height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """``[H, W]`` dark rate of median ``rate`` whose logarithm has SD ``spread`` over the pixels
    (no draw when the spread is 0 or absent)."""
    spread = float(params.get("spread", 0.0))
    if spread <= 0:
        return np.full((height, width), params["rate"])
    z = _standard(rng.standard_normal((height, width)))
    return params["rate"] * np.exp(spread * (z - np.median(z)))


def make_sensor(effects: dict, height: int, width: int, rng: np.random.Generator) -> Sensor:
    """A sensor with the given effects (``{name: parameters}``) at ``height x width``."""
    R = np.ones((height, width))
    d = np.zeros((height, width))
    if "gain_nonuniformity" in effects:
        p = 1.0 + effects["gain_nonuniformity"]["sigma"] * _standard(rng.standard_normal((height, width)))
        R *= np.maximum(p, 0.05) / np.median(p)
    if "column_pattern" in effects:
        R *= (1.0 + effects["column_pattern"]["sigma"] * _standard(rng.standard_normal(width)))[None, :]
    if "dark_current" in effects:
        d += _dark_map(effects["dark_current"], height, width, rng)
    if "hot_pixels" in effects:
        idx = rng.choice(height * width, size=effects["hot_pixels"]["count"], replace=False)
        d.reshape(-1)[idx] += rng.uniform(*HOT_RATE, size=idx.size)
    if "dead_pixels" in effects:
        idx = rng.choice(height * width, size=effects["dead_pixels"]["count"], replace=False)
        R.reshape(-1)[idx] = 0.0
        d.reshape(-1)[idx] = 0.0
    kw = {"responsivity": R if not np.all(R == 1) else None, "dark_rate": d if d.any() else None}
    if "shot_noise" in effects:
        kw["electrons"] = effects["shot_noise"]["electrons"]
    if "reset_to_zero" in effects:
        kw["reset"] = "zero"
    if "refractory" in effects:
        kw["refractory_frames"] = effects["refractory"]["frames"]
    if "flicker" in effects:
        kw["flicker_period_frames"] = effects["flicker"]["period_frames"]
        kw["flicker_depth"] = effects["flicker"]["depth"]
    if "crosstalk" in effects:
        kw["crosstalk_fraction"] = effects["crosstalk"]["fraction"]
    if "nonlinearity" in effects:
        kw["gamma"] = effects["nonlinearity"]["gamma"]
    if "threshold_jitter" in effects:
        kw["threshold_jitter"] = effects["threshold_jitter"]["sigma"]
    return Sensor(name="hidden", **kw)


def true_value(name: str, params: dict):
    """The parameter a diagnosis must estimate for effect ``name`` (None for on/off effects)."""
    # the envelope bounds |gamma - 1|; the generator draws gamma itself
    key = "gamma" if name == "nonlinearity" else SIZE_KEY.get(name)
    return (key, params[key]) if key else (None, None)


def hidden_case(names, seed: int, height: int = 64, width: int = 64, frames: int = 1000):
    """A "measured" recording with the effects ``names`` at random parameters (seeded).

    Returns ``(spikes uint8 [T, H, W], radiance [H, W], intensity, {name: parameters})``;
    intensity is log-uniform in 32..256 and the reference spans 0.05..1 (the envelope).
    """
    from ..sensor import simulate

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), *[EFFECTS.index(n) for n in names]]))
    effects = {n: draw_parameters(n, rng) for n in names}
    intensity = float(math.exp(rng.uniform(math.log(32), math.log(256))))
    radiance = test_radiance(height, width, rng)
    sensor = make_sensor(effects, height, width, rng)
    spikes = simulate(radiance, intensity, sensor, frames=frames, seed=int(rng.integers(1 << 30)))
    return spikes, radiance, intensity, effects
