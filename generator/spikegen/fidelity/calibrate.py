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

Those equations assume a linear sensor (rate ``R k (L + L_d)``). For a camera of the ``rsir`` kind
(the paper's reference generator, sensor-model.md) they are not exact: its dark charge is about
``delta`` a frame whatever ``R``, and its lit charge ``1 / (D' + U + 1)`` falls below the linear law
(9 % at a nominal rate of 0.19 spikes a frame), so the linear fit puts a bias into both maps (on the
``rsir`` camera of ``bench/bench_protocol.py``, noise-free: dark map 5.8 % low at the median, ``R`` off
by 1.7 % SD). ``kind="rsir"`` fits that sensor's own maps through its exact mean charge
(:func:`spikegen.sensor.rsir_mean_charge`): ``delta`` from the dark rate (the mean over ``U`` of
``1 / (1/delta + U + 1)`` inverted in closed form); ``R`` per pixel from the brighter flat by
bisection; the scale ``k`` (nominal spikes per frame per lux, the flat's mean gray level
``255 k L``) chosen so that the median ``R`` is 1 (the same convention). The dimmer flat is then
a check the fit did not use: its measured rates over the model's (``flat_check``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..sensor import KINDS, Sensor, rsir_mean_charge
from .stats import window_rate

SATURATED_RATE = 0.9  # a flat whose median pixel fires this often is saturated (<= 1 spike/frame)
BISECTIONS = 48  # halvings of a log-scale bracket of 1e-3..1e3: 5e-14 relative at the end


@dataclass
class Calibration:
    responsivity: np.ndarray  # R [H, W], median 1
    dark_lux: np.ndarray  # L_d [H, W], lux-equivalent (rsir: delta / k, so that dark_rate is delta)
    lux_to_rate: float
    reference_pixel: tuple  # (row, col) of the paper's reference pixel m
    reference_vs_median: float  # R of pixel m relative to the median (before normalising, for "if")
    flats_lux: tuple  # (L_1, L_2)
    kind: str = "if"  # the sensor response the fit assumed: "if" (Eqs. S2-S6) or "rsir"
    flat_check: float | None = None  # "rsir": median of the dimmer flat's measured / model rate

    @property
    def dark_rate(self) -> np.ndarray:
        return self.dark_lux * self.lux_to_rate

    def sensor(self, name: str = "calibrated") -> Sensor:
        how = "Eqs. S2-S6" if self.kind == "if" else f"the {self.kind} sensor's exact mean charge"
        notes = {"calibrated_by": f"spikegen calibrate ({how})", "flats_lux": list(self.flats_lux),
                 "reference_pixel_row_col": list(self.reference_pixel),
                 "reference_pixel_response_vs_median": self.reference_vs_median,
                 "dark_lux_median": float(np.median(self.dark_lux))}
        if self.flat_check is not None:
            notes["flat_check_measured_over_model"] = self.flat_check
        return Sensor(name=name, kind=self.kind, responsivity=self.responsivity.astype(np.float32),
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


def calibrate(dark: np.ndarray, flats: dict, source: str = "", kind: str = "if") -> Calibration:
    """The maps from a dark stream ``[T, H, W]`` and flats ``{lux: stream [T, H, W]}`` (two or more):
    Eqs. S2-S6 (``kind="if"``) or the ``rsir`` sensor's own fit (``kind="rsir"``)."""
    if kind not in KINDS:
        raise InputError(f"unknown sensor kind {kind!r}: expected one of {', '.join(KINDS)}")
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
    return (fit_rsir if kind == "rsir" else fit_linear)(r_d, r_1, r_2, L1, L2, source)


def fit_linear(r_d, r_1, r_2, L1: float, L2: float, source: str = "") -> Calibration:
    """Eqs. S2-S6 (module doc) on the rates of a dark and two flats."""
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


def rsir_delta(r_d: np.ndarray) -> np.ndarray:
    """The ``rsir`` dark term from a dark rate: ``r = ln((a + 1) / a)``, ``a = 1/delta + 1``, so
    ``delta = 1 / (1 / expm1(r) - 1)``; 0 where the pixel never fired."""
    with np.errstate(divide="ignore"):
        a = 1.0 / np.expm1(r_d)
    return np.where(r_d > 0, 1.0 / (a - 1.0), 0.0)


def _bisect(f, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The root of ``f`` (increasing) in log scale between ``lo`` and ``hi``, elementwise."""
    lo, hi = np.log(lo), np.log(hi)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        up = f(np.exp(mid)) < 0
        lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
    return np.exp(0.5 * (lo + hi))


def fit_rsir(r_d, r_1, r_2, L1: float, L2: float, source: str = "") -> Calibration:
    """The ``rsir`` sensor's ``R`` and ``delta`` from the rates of a dark and two flats (module doc)."""
    if np.any(r_d >= np.log(2.0)):
        raise InputError(f"{source}the dark recording fires at {float(r_d.max()):.3f} spikes/frame in some pixel: "
                         "more than an rsir pixel can in the dark (ln 2); is the lens covered?")
    delta = rsir_delta(r_d)
    r2, d = r_2.reshape(-1), delta.reshape(-1)
    # median R = 1 <=> half the pixels fire above what R = 1 gives: one bisection on k (the median of
    # r2 minus that rate falls as k grows)
    ones = np.ones_like(r2)
    k = float(_bisect(lambda k: -np.median(r2 - rsir_mean_charge(255.0 * float(k) * L2, ones, d)),
                      np.array(1e-3 / L2), np.array(1.0 / L2)))
    R = _bisect(lambda R: rsir_mean_charge(255.0 * k * L2, R, d) - r2, np.full(r2.shape, 1e-3),
                np.full(r2.shape, 1e3)).reshape(r_2.shape)
    model_1 = rsir_mean_charge(255.0 * k * L1, R, delta)
    m = reference_pixel(R)
    return Calibration(R, delta / k, k, m, float(R[m]), (L1, L2), kind="rsir",
                       flat_check=float(np.median(r_1 / model_1)))
