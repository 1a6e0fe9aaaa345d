"""Typed results of ``spikegen diagnose`` (frozen records) and the constants they share.

The diagnosis passes these records by return value: :class:`Context` (the measured data),
:class:`RateFit` (the mean-rate model), :class:`FlickerFit`, :class:`PixelStructure`, bundled
as :class:`Fit`, and one :class:`Effect` per sensor effect. Arrays named ``[P]`` are per pixel,
``P = H * W``, row-major.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

import numpy as np

from ..sensor import Sensor
from . import stats
from .synth import EFFECTS, envelope_size

SIM_SEED = 20240617  # seed of the diagnosis' own simulations (the measured stream's is unknown)
SIM_THREADS = max(1, min(os.cpu_count() or 1, 4))  # threads of those simulations (no effect on their bits)
MIN_SPIKES = 3  # a pixel needs this many spikes for its rate to count
MIN_COHERENCE = 0.9  # flicker: agreement of the sinusoid across four pixel groups (1 = identical)

# z gate of each effect (its statistical significance must reach this)
Z_GATES = {"gain_nonuniformity": 6.0, "column_pattern": 5.0, "dark_current": 6.0, "hot_pixels": 0.0,
           "shot_noise": 6.0, "reset_to_zero": 0.0, "refractory": 0.0, "flicker": 8.0, "crosstalk": 6.0,
           "nonlinearity": 6.0, "dead_pixels": 0.0, "threshold_jitter": 6.0}
# the weakest size the tools must find (synth.ENVELOPE): an effect's score is its size over this
ENVELOPE_SIZE = {name: envelope_size(name) for name in EFFECTS}


def _size_gate(name: str) -> float:
    """Half the envelope's weakest effect: twice its electrons for shot noise (the variance it
    adds goes as 1 / electrons), a whole number of pixels for hot and dead pixels (rounded down)."""
    if name == "shot_noise":
        return 2.0 * ENVELOPE_SIZE[name]
    if name in ("hot_pixels", "dead_pixels"):
        return math.floor(ENVELOPE_SIZE[name] / 2.0)
    return ENVELOPE_SIZE[name] / 2.0


# name: (size gate, z gate)
GATES = {name: (_size_gate(name), Z_GATES[name]) for name in EFFECTS}


# ---------------------------------------------------------------------- the interval formula
def interval_frames(lam: np.ndarray, delta: float) -> np.ndarray:
    """Mean interval of the rate model, ``ISI = delta + max(1, 1 / lambda)`` frames, for
    ``lam`` spikes per frame (any shape) and the readout's interval offset ``delta`` frames."""
    return delta + 1.0 / np.clip(lam, 1e-12, 1.0)


def flicker_rate_table(delta: float, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(lambda [800], mean rate [800])``: the mean over the frames of ``1 / interval_frames(lambda
    phi_t, delta)`` on a geometric grid of steady rates ``lambda`` up to the last that is not
    saturated at every frame (beyond it the mean rate stays at its last value). ``phi [T]``: the
    flicker factor of each frame over the mean the rate model uses. Under flicker the mean rate is
    below the rate at the mean light once ``delta > 0`` (the interval law is not linear in
    ``1 / lambda``)."""
    phi = np.asarray(phi, dtype=np.float64)
    grid = np.geomspace(1e-6, 1.0 / max(float(phi.min()), 1e-6), 800)
    return grid, (1.0 / interval_frames(grid[:, None] * phi[None, :], delta)).mean(axis=1)


def flicker_mean_isi(lam: np.ndarray, delta: float, table) -> np.ndarray:
    """The mean interval, frames, of steady rates ``lam`` under the flicker of ``table``
    (:func:`flicker_rate_table`; None: ``interval_frames(lam, delta)``)."""
    if table is None:
        return interval_frames(lam, delta)
    return 1.0 / np.interp(lam, *table)


def equivalent_isi(isi_frames: np.ndarray, delta: float, table) -> np.ndarray:
    """The inverse of :func:`flicker_mean_isi`: the interval ``interval_frames(lambda, delta)`` of
    the steady rate ``lambda`` whose flickering version gives the mean intervals ``isi_frames``
    (any shape; where they are shorter than the saturated mean interval, or not positive, they are
    returned as they are). ``table``: :func:`flicker_rate_table` (None: ``isi_frames`` itself)."""
    if table is None:
        return isi_frames
    grid, mean_rate = table
    with np.errstate(all="ignore"):
        rate = 1.0 / np.asarray(isi_frames, dtype=np.float64)
        lam = np.interp(rate, mean_rate, grid)
        ok = np.isfinite(rate) & (rate > 0) & (rate < mean_rate[-1])
        return np.where(ok, interval_frames(lam, delta), isi_frames)


def rate_from_interval(isi_frames: np.ndarray, delta: float) -> np.ndarray:
    """The formula inverted where ``ISI - delta >= 1``: ``lambda = 1 / (ISI - delta)`` spikes
    per frame (inf or negative where ``ISI <= delta``, NaN where ``ISI`` is NaN)."""
    with np.errstate(all="ignore"):
        return 1.0 / (isi_frames - delta)


# ---------------------------------------------------------------------- inputs
@dataclass(frozen=True, eq=False)  # eq=False here and below: the records hold arrays
class Context:
    """The measured data a diagnosis works on (read-only)."""

    spikes: "Stream"  # the measured stream [T, H, W] (bands.Stream: read a band of rows at a time)
    X: np.ndarray  # [K, H, W] reference radiance (K sub-frames spread over T)
    intensity: float  # spikes per 256 frames at X = 1
    baseline: Sensor  # sized to H x W
    Tf: int  # frames of the fit window (the rest are held out)
    meas: stats.PixelStats  # timing statistics of the fit window
    halves: tuple  # (rate [P] of the first half, of the second half) of the fit window
    self_ref: bool  # the radiance was estimated from the data ("self")
    Rb: np.ndarray  # [P] the baseline's responsivity
    db: np.ndarray  # [P] the baseline's dark rate, spikes per frame
    constant_fraction: float  # of pixels whose intervals never vary (noise-free reset to zero)
    static: np.ndarray | None = None  # [P] bool, pixels whose rate does not change (all with a reference)
    untested: int = 0  # pixels with too few spikes to be tested for a change of rate ('self' only)
    rows: int = 8  # rows of the bands the streams are read and simulated in (bands.band_rows)
    motion: object = None  # drift.ImageMotion of the whole image ('self' only)
    # what the passes over each model's simulation computed (bands.simulation_pass), by
    # bands.simulation_key: a memo, so that a sensor simulated twice is simulated once
    passes: dict = field(default_factory=dict, repr=False)

    @property
    def shape(self) -> tuple:
        return self.spikes.shape[1:]

    @property
    def frames(self) -> int:
        return self.spikes.shape[0]

    @property
    def g(self) -> float:
        return self.intensity / 256.0

    @property
    def zero_quantised(self) -> bool:
        """Intervals are exactly ``n + ceil(1 / lambda)``: fit them as censored."""
        return self.constant_fraction > 0.5


# ---------------------------------------------------------------------- fit results
@dataclass(frozen=True, eq=False)
class RateFit:
    """The mean-rate model ``lambda = a R_b (g fbar (B0 + c B1) + d_b + d)`` and
    ``ISI = interval_frames(lambda, delta)`` fitted to the fit window (see diagnose.py).
    Without a reference (:meth:`identity`) only ``delta`` is estimated; ``lam_pred``, ``isi``
    and ``keep`` are None and ``outlier`` is all False."""

    a: float = 1.0  # responsivity scale
    gamma: float = 1.0  # exponent of the radiance
    c: float = 0.0  # crosstalk fraction
    d: float = 0.0  # dark rate added to the baseline's, spikes per frame at R_b = 1
    delta: float = 0.0  # interval offset of the readout, frames
    fbar: float = 1.0  # mean flicker factor over the fit window
    use_c: bool = False  # the reference has pixel-scale texture, so c was fitted
    se_c: float = math.inf  # standard errors of c, d, gamma
    se_d: float = math.inf
    se_gamma: float = math.inf
    objective: float = math.inf  # weighted mean squared relative interval error
    lam_pred: np.ndarray | None = None  # [P] model rate, spikes per frame
    isi: np.ndarray | None = None  # [P] measured mean interval, frames (NaN where not fitted)
    # [P] the interval the fitted readout would give each pixel at the mean light of the fit window
    # (equivalent_isi: isi itself without flicker); the model's lam_pred predicts this one
    isi_eq: np.ndarray | None = None
    # flicker factors of the frames over the model's mean: (fit window, its first half, its second
    # half), each [frames]; None without a fitted flicker
    phi: tuple | None = None
    keep: np.ndarray | None = None  # [P] pixels the final fit used
    outlier: np.ndarray | None = None  # [P] pixels left out as outliers (hot pixels, dust)
    # the linear parameters and rate refitted at gamma = 1 (same delta and pixels), for a model
    # that does not adopt the nonlinearity; None where not fitted
    linear: tuple | None = None  # (a, c, d)
    lam_linear: np.ndarray | None = None  # [P]

    @classmethod
    def identity(cls, delta: float, pixels: int) -> "RateFit":
        """The baseline itself with interval offset ``delta`` (radiance taken from the data)."""
        return cls(delta=delta, outlier=np.zeros(pixels, dtype=bool))

    def predicted_isi(self) -> np.ndarray:
        """``[P]`` mean interval of the fitted model, frames."""
        return interval_frames(self.lam_pred, self.delta)


@dataclass(frozen=True, eq=False)
class FlickerFit:
    """A sinusoid in the population signal: light ``x (1 + depth sin(2 pi t / period + phase))``."""

    period_frames: float
    depth: float  # relative modulation of the light
    phase_rad: float
    z: float  # amplitude over its standard error (against the neighbouring spectrum)
    coherence: float  # agreement of the sinusoid across four brightness groups (1 = identical)
    mask: np.ndarray  # [P] bool, the pixels of the population signal
    light: np.ndarray  # [Tf] their expected light spikes per frame

    def mean_factor(self, frames: int) -> float:
        """Mean flicker factor over frames ``0 .. frames - 1``."""
        if self.depth <= 0:
            return 1.0
        t = np.arange(frames)
        return float(1.0 + self.depth * np.mean(np.sin(2 * np.pi * t / self.period_frames + self.phase_rad)))


@dataclass(frozen=True, eq=False)
class PixelStructure:
    """Per-pixel structure of ``e = lambda_measured / lambda_model``. Without a reference only
    hot pixels (against the 3 x 3 median) are known: ``e, e1, e2, good, good_col`` are None
    and the column factors are ones."""

    hot: np.ndarray  # [P] bool, additive outliers
    testable: np.ndarray  # [P] bool, pixels where a hot pixel would have been found
    excess: np.ndarray  # [P] rate above the model, spikes per frame
    resid_sd: float  # robust spread of e / column factor - 1
    column_factors: np.ndarray  # [W], median 1 (ones without a reference)
    e: np.ndarray | None = None  # [P] over the fit window (NaN where unusable)
    e1: np.ndarray | None = None  # [P] over its first half
    e2: np.ndarray | None = None  # [P] over its second half
    good: np.ndarray | None = None  # [P] bool, pixels for the per-pixel gain estimate
    good_col: np.ndarray | None = None  # [P] bool, pixels for the column estimate


@dataclass(frozen=True, eq=False)
class Fit:
    """Everything the diagnosis fitted, in the order it was fitted."""

    rate: RateFit
    flicker: FlickerFit | None
    structure: PixelStructure


# ---------------------------------------------------------------------- verdicts
@dataclass(frozen=True)
class Effect:
    """One sensor effect's verdict. ``score``: its estimated size over the weakest size the
    tools must find (ENVELOPE_SIZE); ``z``: its significance; ``parameters``: the fitted values
    (the JSON entry); ``evidence``: the numbers the verdict rests on (size, gates, variances),
    not part of the JSON."""

    name: str
    detected: bool
    score: float
    parameters: Mapping[str, object]
    z: float = 0.0
    note: str = ""
    evidence: Mapping[str, object] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "parameters", MappingProxyType(dict(self.parameters)))
        object.__setattr__(self, "evidence", MappingProxyType(dict(self.evidence)))

    def __reduce__(self):  # a read-only mapping does not pickle; its copy does
        return Effect, (self.name, self.detected, self.score, dict(self.parameters), self.z, self.note,
                        dict(self.evidence))

    def as_dict(self) -> dict:
        d = {"name": self.name, "detected": bool(self.detected), "score": as_number(self.score),
             "parameters": {k: as_number(v) for k, v in self.parameters.items()}, "z": as_number(self.z)}
        if self.note:
            d["note"] = self.note
        return d


def judge(name: str, size, z: float, parameters: dict, note: str = "", force: bool | None = None,
          evidence: dict | None = None) -> Effect:
    """The verdict on effect ``name`` of estimated ``size`` and significance ``z`` (GATES);
    ``force`` overrides the detection. Shot noise is strong when its electrons are few."""
    gate, zgate = GATES[name]
    detected = bool(size is not None and math.isfinite(size) and size >= gate and z >= zgate)
    if name == "shot_noise":
        detected = bool(size is not None and 0 < size <= gate and z >= zgate)
        score = ENVELOPE_SIZE[name] / size if size and size > 0 else 0.0
    else:
        score = (size or 0.0) / ENVELOPE_SIZE[name]
    if force is not None:
        detected = force
    evidence = {"size": size, "size_gate": gate, "z_gate": zgate, **(evidence or {})}
    return Effect(name, detected, float(score) if math.isfinite(score) else 0.0, parameters, float(z), note, evidence)


def unavailable(name: str, parameters: dict, note: str) -> Effect:
    """Effect ``name`` that this data cannot show (``note`` says why)."""
    return Effect(name, False, 0.0, parameters, 0.0, note)


def as_number(v):
    """A JSON number: int / bool kept, floats rounded to 6 decimals, non-finite as None."""
    if v is None:
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    v = float(v)
    return round(v, 6) if math.isfinite(v) else None
