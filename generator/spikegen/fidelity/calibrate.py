"""``spikegen calibrate``: responsivity and dark current from flat-field and dark recordings.

The supplement's Eqs. S2-S6 (sensor-model.md, "Calibration from measured data"). With the
mean inter-spike intervals ``T_d`` (lens covered), ``T_1`` (uniform light ``L_1``) and ``T_2``
(uniform light ``L_2``) of every pixel:

- dark current as equivalent light (Eq. S3): ``L_d = L_1 T_1 / (T_d - T_1)``, written with
  rates ``r = 1 / T`` as ``L_d = L_1 r_d / (r_1 - r_d)`` so that a pixel that never fired in
  the dark (``T_d`` infinite) gets ``L_d = 0``;
- responsivity (Eq. S6): ``R(x) = (L_2 + L_d(m)) T_2(m) / ((L_2 + L_d(x)) T_2(x))`` with the
  reference pixel ``m`` the pixel whose response ``1 / ((L_2 + L_d) T_2)`` is closest to the
  average response, as the paper says; then normalised to median 1 (the project's convention,
  which makes ``I`` mean what it says for a typical pixel);
- ``lux_to_rate`` (spikes per frame per lux at nominal response) = the median response, and
  the dark rate ``d = lux_to_rate * L_d`` (spikes per frame at nominal response).

``L_1`` is the dimmer flat (used for ``L_d``), ``L_2`` the brighter (used for ``R``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..sensor import Sensor
from .stats import window_rate

SATURATED_RATE = 0.9  # a flat whose median pixel fires this often is saturated (<= 1 spike/frame)


@dataclass
class Calibration:
    responsivity: np.ndarray  # R [H, W], median 1
    dark_lux: np.ndarray  # L_d [H, W], lux-equivalent
    lux_to_rate: float
    reference_pixel: tuple  # (row, col) of the paper's reference pixel m
    reference_vs_median: float  # R of pixel m before normalising to median 1
    flats_lux: tuple  # (L_1, L_2)

    @property
    def dark_rate(self) -> np.ndarray:
        return self.dark_lux * self.lux_to_rate

    def sensor(self, name: str = "calibrated") -> Sensor:
        notes = {"calibrated_by": "spikegen calibrate (Eqs. S2-S6)", "flats_lux": list(self.flats_lux),
                 "reference_pixel_row_col": list(self.reference_pixel),
                 "reference_pixel_response_vs_median": self.reference_vs_median,
                 "dark_lux_median": float(np.median(self.dark_lux))}
        return Sensor(name=name, responsivity=self.responsivity.astype(np.float32),
                      dark_rate=self.dark_rate.astype(np.float32), lux_to_rate=self.lux_to_rate,
                      map_model=_map_model(self.responsivity, self.dark_lux, self.lux_to_rate), notes=notes)


def _map_model(resp, dark_lux, lux_to_rate):
    """Statistical description (spikegen.fpn) so the camera can be drawn at other sizes."""
    try:
        from ..fpn import fit_map_model
    except ImportError:  # pragma: no cover - fpn is part of the package
        return None
    try:
        model = fit_map_model(resp, np.maximum(dark_lux, 1e-6))
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return None
    model["lux_to_rate"] = lux_to_rate
    return model


def pixel_rate(spikes: np.ndarray) -> np.ndarray:
    """``1 / mean ISI`` per pixel ``[H, W]`` (``n / T`` for pixels with fewer than 2 spikes)."""
    T, H, W = spikes.shape
    return window_rate(spikes).reshape(H, W)


def calibrate(dark: np.ndarray, flats: dict, source: str = "") -> Calibration:
    """Eqs. S2-S6 from a dark stream ``[T, H, W]`` and flats ``{lux: stream [T, H, W]}`` (two or more)."""
    if len(flats) < 2:
        raise InputError(f"calibration needs two uniform-light recordings (--flat LUX=FILE twice), got {len(flats)}")
    shapes = {np.shape(s)[1:] for s in flats.values()} | {np.shape(dark)[1:]}
    if len(shapes) != 1:
        raise InputError(f"calibration recordings differ in size: {sorted(shapes)}")
    lux = sorted(flats)
    if lux[0] <= 0 or lux[0] == lux[-1]:
        raise InputError(f"flat-field illuminances must be positive and different, got {lux}")
    L1, L2 = float(lux[0]), float(lux[-1])
    r_d = pixel_rate(dark)
    r_1, r_2 = pixel_rate(flats[lux[0]]), pixel_rate(flats[lux[-1]])
    for L, r in ((L1, r_1), (L2, r_2)):
        if np.median(r) >= SATURATED_RATE:
            raise InputError(f"{source}flat at {L:g} lux is saturated (median rate {np.median(r):.3f} spikes/frame); "
                             "record it dimmer")
        if np.any(r <= 0):
            raise InputError(f"{source}flat at {L:g} lux has {int(np.sum(r <= 0))} pixels without a spike; "
                             "record it longer or brighter")
    if np.median(r_1) <= np.median(r_d):
        raise InputError(f"{source}the flat at {L1:g} lux fires no faster than the dark recording")
    dark_lux = dark_equivalent_lux(r_d, r_1, L1)
    resp_raw = r_2 / (L2 + dark_lux)  # 1 / ((L_2 + L_d) T_2): lux_to_rate * R
    m = reference_pixel(resp_raw)
    ref = resp_raw[m]
    R = resp_raw / ref  # Eq. S6
    med = float(np.median(R))
    return Calibration(R / med, dark_lux, float(np.median(resp_raw)), m, 1.0 / med, (L1, L2))


def dark_equivalent_lux(r_d: np.ndarray, r_1: np.ndarray, L1: float) -> np.ndarray:
    """Eq. S3 in rates: ``L_d = L_1 r_d / (r_1 - r_d)``; 0 where the pixel never fired in the dark."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ld = L1 * r_d / (r_1 - r_d)
    return np.where(np.isfinite(ld) & (ld > 0), ld, 0.0)


def reference_pixel(response: np.ndarray) -> tuple:
    """The pixel whose response is closest to the average response (the paper's ``(x_m, y_m)``)."""
    idx = int(np.argmin(np.abs(response - response.mean())))
    return tuple(int(v) for v in np.unravel_index(idx, response.shape))
