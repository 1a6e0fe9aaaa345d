"""The training methods (``--method``): what each supervises the field with.

- ``spikenerf-paper``: the published SpikeNeRF method (CVPR 2024 and its public code), ported:
  rendered luminance scaled by the intensity -> the published interval-domain fixed-pattern
  formula (maps from the dataset's R and d) -> the published integrate-and-fire loop (256
  steps from an empty membrane, fires strictly above 1, reset to 0, straight-through
  gradient) -> ``(count / 256) ** (1 / 2.2)``, MSE against the TFP image of the recorded
  stream encoded the same way (8-bit). See :func:`neuron.paper_pixel` and docs/trainer.md.
- ``spikenerf``: an idealised variant of the paper's loss (not the published model):
  rendered radiance -> R and dark current -> integrate-and-fire neuron with subtractive reset
  and a uniform start phase over the whole stream (closed form, :mod:`spikenerf.neuron`) ->
  compared with the observed count (squared error in rate units), seen from the
  mid-exposure pose.
- ``spikenerf-noR``: the same idealised variant with ``R = 1`` (in the manner of the paper's
  Table S5 ablation).
- ``tfp32`` / ``tfp256`` / ``tfi``: images reconstructed from spikes (TFP over 32 or 256
  frames, TFI), turned into radiance as ``X = rate * 256 / I`` (no calibration, as the
  paper's baselines), fitted with MSE.
- ``spikelik`` (the default): the likelihood of the spike counts in time windows (at most 8;
  by default as few as keep the image's motion within a window to at most 2.5 pixels,
  :func:`spikenerf.targets.count_windows`), each rendered from the camera pose at its own time
  (interpolated from the recorded sub-frame poses), so camera motion during the stream is
  modelled, not blurred; on an integrate-and-fire sensor with subtractive reset (the ``if`` kind)
  each window's count is read from its first and last spike times where they pin it down more closely
  (:func:`spikenerf.targets.interval_statistic`: about a fifth of the count's error at I = 32);
  Gaussian likelihood with the count variance of the dataset's sensor
  (:func:`neuron.count_variance`: the residual's 1/6 plus the shot noise of its
  photo-electrons per threshold and its threshold jitter), R and d from the dataset's sensor, and the dataset
  sensor's reset (subtractive or to zero, :func:`neuron.expected_count`); when the dataset
  was made by the ``rsir`` reference generator, its exact mean charge
  (:func:`neuron.rsir_rate`: Poisson gray levels and the uniform quantisation noise make it
  compressive) replaces the linear rate. For a static view (all sub-frame poses equal) the
  windows share one pose, so it uses the whole stream as one window.
- ``spikelik-count``: ``spikelik`` with the counts alone, never the spike times (the default before
  2026-11-28: the rows and measurements named ``spikelik`` before then on ``if`` sensors).
- ``oracle``: not a spike method: the field fitted to the training views' ground-truth images
  (MSE of the sRGB encodings, as evaluation compares), from the mid-exposure pose. It separates
  what the spikes cost from what the field can represent, and needs a dataset whose train views
  have ground-truth PNGs.
"""
from __future__ import annotations

import math

from dataclasses import dataclass

DEFAULT_METHOD = "spikelik"


@dataclass(frozen=True)
class Method:
    name: str
    target: str  # "counts" | "tfp" | "tfi" | "tfp-gamma" (the published targets: (count / w) ** (1/2.2), 8-bit)
    #              | "truth" (the ground-truth image: the oracle)
    windows: int = 1  # the most count windows per view of a moving camera (targets.count_windows)
    use_resp: bool = True  # apply R (and d) in the sensor
    tfp_frames: int = 0
    loss: str = "mse"  # "mse" (rate or radiance units) | "nll" (Gaussian, count units) | "paper" (published pixel)
    #                    | "srgb" (MSE of sRGB encodings)
    exact_sensor: bool = False  # the dataset's own sensor: rsir's exact mean charge, shot noise, reset
    statistic: str = "count"  # count targets: "count", or "interval" where the sensor allows (targets.count_statistic)


METHODS = {
    "spikelik": Method("spikelik", "counts", windows=8, loss="nll", exact_sensor=True, statistic="interval"),
    "spikelik-count": Method("spikelik-count", "counts", windows=8, loss="nll", exact_sensor=True),
    "spikenerf-paper": Method("spikenerf-paper", "tfp-gamma", loss="paper"),
    "spikenerf": Method("spikenerf", "counts"),
    "spikenerf-noR": Method("spikenerf-noR", "counts", use_resp=False),
    "tfp32": Method("tfp32", "tfp", tfp_frames=32, use_resp=False),
    "tfp256": Method("tfp256", "tfp", tfp_frames=256, use_resp=False),
    "tfi": Method("tfi", "tfi", use_resp=False),
    "oracle": Method("oracle", "truth", use_resp=False, loss="srgb"),
}

# ``--srgb-weight``'s value for the likelihood methods when a run does not set it (the default since 2026-11-29;
# chosen on the procedural lego: docs/trainer.md "One window at 400 x 400" and "Weighting each ray as a display
# does")
SRGB_WEIGHT = 400.0
# ... where a white target pixel counts at least this many spikes a window on average (white_count); below it the
# default is 0. On the procedural lego at 400 x 400 every weight measured lost at 8 spikes (up to 0.96 dB), at 16
# the weight is about even (+0.10 and -0.04 dB), at 32 and more it gains (docs/trainer.md "The weight needs counts")
SRGB_LEAST_COUNT = 16.0


def white_count(intensity: float, frames: int, windows: int = 1, binning: int = 1) -> float:
    """The spikes a white pixel (X = 1) counts on average in one count window of ``frames / windows`` frames, the
    intensity being spikes per 256 frames at X = 1 (spikegen --intensity), times the ``binning`` sensor pixels one
    target pixel averages (``--resolution`` below the dataset's: the square of the factor)."""
    return float(intensity) * frames / 256.0 / max(1, windows) * binning


def default_srgb_weight(name: str, counts: float = math.inf) -> float:
    """``--srgb-weight`` when a run does not set it: :data:`SRGB_WEIGHT` for the likelihood methods (loss
    ``nll``) where a white target pixel counts at least :data:`SRGB_LEAST_COUNT` spikes a window (``counts``,
    :func:`white_count`; unknown: assumed enough), else 0 (off); 0 for the other methods, which do not take it."""
    return SRGB_WEIGHT if METHODS[name].loss == "nll" and counts >= SRGB_LEAST_COUNT else 0.0
