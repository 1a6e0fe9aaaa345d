"""The training methods (``--method``): what each supervises the field with.

- ``spikenerf``: the paper's. Rendered radiance -> R and dark current -> integrate-and-fire
  neuron over the whole stream (closed form, :mod:`spikenerf.neuron`) -> compared with the
  observed count (squared error in rate units), seen from the mid-exposure pose.
- ``spikenerf-noR``: the same with ``R = 1`` (the paper's Table S5 ablation).
- ``tfp32`` / ``tfp256`` / ``tfi``: images reconstructed from spikes (TFP over 32 or 256
  frames, TFI), turned into radiance as ``X = rate * 256 / I`` (no calibration, as the
  paper's baselines), fitted with MSE.
- ``spikelik`` (the default): the likelihood of the spike counts in time windows (8 windows
  of T/8 frames), each rendered from the camera pose at its own time (interpolated from the
  recorded sub-frame poses), so camera motion during the stream is modelled, not blurred;
  Gaussian likelihood with the count variance of the sensor (:func:`neuron.count_variance`),
  R and d from the dataset's sensor; when the dataset was made by the ``rsir`` reference
  generator, its exact mean charge (:func:`neuron.rsir_rate`: Poisson gray levels and the
  uniform quantisation noise make it compressive) replaces the linear rate. For a static view
  (all sub-frame poses equal) the windows share one pose, so it uses the whole stream as one
  window.
"""
from __future__ import annotations

from dataclasses import dataclass

DEFAULT_METHOD = "spikelik"


@dataclass(frozen=True)
class Method:
    name: str
    target: str  # "counts" | "tfp" | "tfi"
    windows: int = 1  # count windows per view (moving camera)
    use_resp: bool = True  # apply R (and d) in the sensor
    tfp_frames: int = 0
    loss: str = "mse"  # "mse" (rate or radiance units) | "nll" (Gaussian, count units)
    exact_sensor: bool = False  # use the dataset's own sensor kind (rsir: its exact mean charge)


METHODS = {
    "spikelik": Method("spikelik", "counts", windows=8, loss="nll", exact_sensor=True),
    "spikenerf": Method("spikenerf", "counts"),
    "spikenerf-noR": Method("spikenerf-noR", "counts", use_resp=False),
    "tfp32": Method("tfp32", "tfp", tfp_frames=32, use_resp=False),
    "tfp256": Method("tfp256", "tfp", tfp_frames=256, use_resp=False),
    "tfi": Method("tfi", "tfi", use_resp=False),
}
