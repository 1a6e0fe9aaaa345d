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
5. Temporal noise: interval variance beyond what the fitted noise-free model produces (both
   measured and simulated, so flicker, quantisation and scene motion cancel): shot noise, which
   accumulates over a span of intervals, and a threshold jitter, which does not (the variance
   of one interval beyond that growth; effects._temporal_effects).
6. Reset-to-zero: the half-frame offset, and pixels whose intervals never vary.

Every effect gets ``score`` = its estimated size over the weakest size the tools must find
(synth.ENVELOPE), and ``z`` (its statistical significance); it passes its gates when both
pass. Gain and dark-rate spread are separated jointly (effects.joint_spread: multiplicative
against additive over a range of light). Then the held-out choice (:mod:`.heldout`): the
effects that passed their gates are removed one by one while removing them does not lower a
proper score of the held-out frames (log-likelihood of intervals and window counts under each
model's simulation, heldout.MEASURE) by more than a penalty; only the kept ones are reported
(detected). The extended sensor is the baseline plus the kept effects with the fitted maps;
"heldout" is the score of the baseline and of the extended sensor; "unexplained" lists the
held-out statistics the extended sensor does not reproduce (:mod:`.unexplained`); "baseline",
"extended" and "gain" are the named discrepancy measures (stats.MEASURES) of each model on
the held-out frames. With ``self`` only static pixels (heldout.motion_test) are judged: pixels
tested for a change of rate that show none; "untested_pixels" had too few spikes to be tested.
Before that, ``self`` looks for a motion of the whole image (drift.image_motion: the image's
shift in 8 windows of frames against the same measure on interleaved frames, agreeing across
blocks of the frame, on the fit frames); when it finds one, ``info["motion"]`` says so, the
reference moves with the image (the motion-free image moved by the fitted shifts, in
MOTION_SUBFRAMES sub-frames, extrapolated over the held-out frames), so that every model is
simulated with the motion and a moving image is not read as temporal noise, and the pixels whose
rate the motion changes by more than 10 % (beyond counting noise) are not judged. A motion is a
property of the scene, never reported as an effect.

The steps are separate modules, each returning frozen records (:mod:`.records`):
:mod:`.ratefit` (flicker, the rate model), :mod:`.structure` (per-pixel structure),
:mod:`.effects` (verdicts and the extended sensor); :func:`diagnose` calls them in order.
Streams are read, and models simulated and scored, a band of rows at a time (:mod:`.bands`): the
diagnosis of a packed stream (bands.Stream, as the CLI reads an ``.npz``) holds no stream of the
whole recording unpacked (the ``--report`` plots still unpack it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import InputError
from ..sensor import Sensor
from . import bands, drift, heldout, stats
from .effects import gated_effects, sensor_with
from .ratefit import constant_interval_fraction, fit_flicker, fit_rate_model, self_refractory
from .records import ENVELOPE_SIZE, GATES, SIM_SEED, Context, Effect, Fit, RateFit, as_number  # noqa: F401
from .structure import pixel_structure
from .synth import EFFECTS

__all__ = ["FIT_FRACTION", "SIM_SEED", "GATES", "ENVELOPE_SIZE", "Diagnosis", "Effect", "diagnose", "score_sensor"]

FIT_FRACTION = 0.8
MOTION_SUBFRAMES = 16  # sub-frames of the 'self' reference when the whole image moves


@dataclass
class Diagnosis:
    effects: list  # one Effect per name of synth.EFFECTS, in that order
    extended: Sensor
    baseline_measures: dict
    extended_measures: dict
    fit: Fit | None = None  # fitted model and maps, for reports
    info: dict = field(default_factory=dict)
    heldout: dict = field(default_factory=dict)  # the held-out score of the ideal and fitted models
    unexplained: list = field(default_factory=list)  # statistics the fitted model does not reproduce
    static: np.ndarray | None = None  # [H, W] bool, pixels judged (the static ones with 'self')

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
            out[k] = {"baseline": as_number(b), "extended": as_number(x),
                      "reduction": as_number((b - x) / b if b > 0 else 0.0)}
        return out

    def as_json(self) -> dict:
        return {"detected": self.detected, "effects": [e.as_dict() for e in self.effects],
                "baseline": {k: as_number(v) for k, v in self.baseline_measures.items()},
                "extended": {k: as_number(v) for k, v in self.extended_measures.items()},
                "gain": self.gain(), "measures": stats.MEASURES, "info": self.info,
                "extended_sensor": self.extended.parameters(), "heldout": self.heldout,
                "unexplained": self.unexplained}


# ---------------------------------------------------------------------- entry point
def diagnose(spikes: np.ndarray, radiance, intensity: float, baseline: Sensor | None = None,
             fit_fraction: float = FIT_FRACTION, progress=None, band_rows: int | None = None) -> Diagnosis:
    """Diagnose ``spikes uint8 [T, H, W]`` against ``radiance`` (``[H, W]`` / ``[K, H, W]``
    linear luminance, or the string ``"self"``) seen at ``intensity``. ``band_rows``: the rows of
    the bands the models' simulations are made and scored in (bands.band_rows; the result does
    not depend on it)."""
    spikes = _check_stream(spikes, intensity)
    T, H, W = spikes.shape
    baseline = (baseline or Sensor(name="ideal")).sized(H, W)
    step = progress or (lambda msg: None)
    step("timing statistics")
    ctx = _context(spikes, radiance, float(intensity), baseline, int(round(T * fit_fraction)),
                   bands.band_rows(T, H, W, band_rows))
    step("mean-rate model")
    fit = _fit_all(ctx)
    step("effects, chosen by held-out score")
    effects, extended, held = _choose(ctx, fit)
    step("held-out comparison")
    bm, em = held["measures"]  # the baseline's and the extended sensor's
    n_static = int(ctx.static.sum())
    info = {"frames": T, "fit_frames": ctx.Tf, "held_out_frames": T - ctx.Tf, "height": H, "width": W,
            "intensity": ctx.intensity, "reference": "self" if ctx.self_ref else f"{ctx.X.shape[0]} sub-frame(s)",
            "baseline_sensor": baseline.name, "static_pixels": n_static,
            "moving_pixels": H * W - n_static - ctx.untested, "untested_pixels": ctx.untested}
    if ctx.motion is not None:
        info["motion"] = ctx.motion.as_json()
    return Diagnosis(effects, extended, bm, em, fit=fit, info=info, heldout=held["doc"],
                     unexplained=held["unexplained"], static=ctx.static.reshape(H, W))


def score_sensor(spikes: np.ndarray, radiance, intensity: float, sensor: Sensor, baseline: Sensor | None = None,
                 fit_fraction: float = FIT_FRACTION, band_rows: int | None = None) -> heldout.HeldOutScore:
    """The held-out score (the JSON's ``"heldout"`` measure, heldout.MEASURE) of a given ``sensor``
    on this recording: the same fit window, reference (``"self"``: from the fit window's rates
    through ``baseline``), static pixels and simulation seed as :func:`diagnose`."""
    spikes = _check_stream(spikes, intensity)
    T, H, W = spikes.shape
    baseline = (baseline or Sensor(name="ideal")).sized(H, W)
    ctx = _context(spikes, radiance, float(intensity), baseline, int(round(T * fit_fraction)),
                   bands.band_rows(T, H, W, band_rows))
    return bands.model_pass(ctx, sensor.sized(H, W))["score"]


def _choose(ctx: Context, fit: Fit) -> tuple[list, Sensor, dict]:
    """The gated effects, then backward elimination by held-out score (heldout.select); returns
    the verdicts (dropped effects undetected, with a note), the extended sensor, and
    ``{"doc": the JSON "heldout" entry, "unexplained": entries, "measures": (the baseline's
    discrepancy measures, the extended sensor's)}``. Each model's simulation is made and
    scored in bands of rows (bands.model_pass), once: a model simulated before (the temporal
    noise verdicts' noise-free model, the kept model) is taken from ``ctx.passes``."""
    found, electrons = gated_effects(ctx, fit)
    gated = [n for n in EFFECTS if found[n].detected]
    cache = {}

    def evaluate(on):
        key = frozenset(on)
        if key not in cache:
            # the model of every gated effect is the likeliest to be kept: its discrepancy measures
            # and checks come from the same simulation, kept (ctx.passes) for the extended sensor's pass
            full = key == frozenset(gated)
            cache[key] = bands.model_pass(ctx, sensor_with(ctx, fit, found, set(on), electrons),
                                          measures=full, checks=full)["score"]
        return cache[key]

    kept, evidence = heldout.select(gated, evaluate, {n: heldout.penalty(n, found[n].parameters) for n in gated})
    effects = [_with_evidence(found[n], n in kept, evidence.get(n)) for n in EFFECTS]
    extended = sensor_with(ctx, fit, found, set(kept), electrons)
    ideal_pass = bands.model_pass(ctx, ctx.baseline, measures=True)
    # the kept model's again: its score, and with every gated effect kept all of it, from ctx.passes
    fitted_pass = bands.model_pass(ctx, extended, measures=True, checks=True)
    ideal, fitted = ideal_pass["score"], fitted_pass["score"]
    doc = {"measure": heldout.MEASURE, "ideal": as_number(ideal.mean), "fitted": as_number(fitted.mean),
           "higher_is_better": True, "window_frames": heldout.window_lengths(ctx.frames - ctx.Tf),
           "pixels": int(ctx.static.sum()),
           "effects": {n: {"gain_nats": as_number(g), "standard_error": as_number(se), "kept": n in kept}
                       for n, (g, se) in evidence.items()}}
    return effects, extended, {"doc": doc, "unexplained": fitted_pass["unexplained"],
                               "measures": (ideal_pass["measures"], fitted_pass["measures"])}


def _with_evidence(effect: Effect, kept: bool, gain) -> Effect:
    """``effect`` with its held-out gain ``(nats, standard error)`` in the evidence; one the
    gates passed but the held-out choice dropped is marked undetected, with a note."""
    if gain is None:
        return effect
    nats, se = gain
    effect = replace(effect, evidence={**effect.evidence, "heldout_gain_nats": nats, "heldout_se": se})
    if kept:
        return effect
    return replace(effect, detected=False,
                   note=f"passed its gates but does not improve the held-out score ({nats:+.3g} nats, SE {se:.3g})")


def _check_stream(spikes, intensity) -> bands.Stream:
    """``spikes`` (an array ``[T, H, W]`` or a bands.Stream) as a bands.Stream, checked."""
    spikes = spikes if isinstance(spikes, bands.Stream) else np.asarray(spikes)
    if len(spikes.shape) != 3:
        raise InputError(f"measured stream must be [T, H, W], got shape {spikes.shape}")
    T = spikes.shape[0]
    if T < 50:
        raise InputError(f"measured stream has {T} frames; a diagnosis needs at least 50 (1000 recommended)")
    if not (math.isfinite(intensity) and intensity > 0):
        raise InputError(f"intensity must be a positive number, got {intensity}")
    return bands.Stream.of(spikes)


def _context(spikes: bands.Stream, radiance, intensity: float, baseline: Sensor, Tf: int, rows: int) -> Context:
    """Timing statistics of the first ``Tf`` frames (read in bands of ``rows`` rows) and the
    reference radiance ``[K, H, W]``."""
    T, H, W = spikes.shape
    meas, halves = bands.fit_window_stats(spikes, rows, Tf)  # halves: the rates of its two halves
    self_ref = isinstance(radiance, str)
    motion = drift.image_motion(spikes, rows, Tf) if self_ref else None
    if self_ref and motion.significant:
        # the scene moves as a whole: the reference moves with it (MOTION_SUBFRAMES sub-frames over
        # the recording, the fitted shifts extrapolated over the held-out frames)
        # (each pixel scaled to its exact fit-window rate)
        rate = meas.rate.reshape(H, W)
        X = np.concatenate([_self_radiance(motion.rates_at((k + 0.5) * T / MOTION_SUBFRAMES, rate), intensity,
                                           baseline, H, W) for k in range(MOTION_SUBFRAMES)])
    elif self_ref:
        X = _self_radiance(meas.rate, intensity, baseline, H, W)
    else:
        X = np.asarray(radiance, dtype=np.float64)
        X = X[None] if X.ndim == 2 else X
        if X.ndim != 3 or X.shape[1:] != (H, W):
            raise InputError(f"reference radiance is {X.shape[-1]}x{X.shape[-2]}, the stream is {W}x{H}")
    Rb, db = baseline.maps(H, W)
    static, tested = bands.motion_test(spikes, rows) if self_ref else (np.ones(H * W, dtype=bool),) * 2
    if motion is not None and motion.significant:
        static = static & ~motion.changed  # the pixels the image's motion changes are not judged
    return Context(spikes, X, intensity, baseline, Tf, meas, halves, self_ref, Rb.reshape(-1), db.reshape(-1),
                   constant_interval_fraction(meas), static, int((~tested).sum()), rows, motion)


def _self_radiance(rate, intensity, baseline, H, W):
    """Radiance that makes the baseline reproduce the measured rates (static scene)."""
    R, d = baseline.maps(H, W)
    x = (np.minimum(rate.reshape(H, W), 1.0) / R - d) * (256.0 / intensity)
    return np.maximum(x, 0.0)[None]


def _fit_all(ctx: Context) -> Fit:
    """Flicker first (every spike counted as light), the rate model with it, flicker again
    with the model's light, the rate model again with the flicker's mean factor (starting
    from the first fit's outliers); then the per-pixel structure of its residual. Without a
    reference only flicker, the interval offset and the structure of the rates."""
    flicker = fit_flicker(ctx, None)
    if ctx.self_ref:
        rate = RateFit.identity(self_refractory(ctx.meas), ctx.meas.n.size)
    else:
        first = fit_rate_model(ctx, flicker, fbar=1.0, outlier=np.zeros(ctx.meas.n.size, dtype=bool))
        flicker = fit_flicker(ctx, first)
        fbar = flicker.mean_factor(ctx.Tf) if flicker is not None else 1.0
        rate = fit_rate_model(ctx, flicker, fbar=fbar, outlier=first.outlier)
    return Fit(rate, flicker, pixel_structure(ctx, rate))
