"""Images from spikes: TFP (texture from playback: spike count over a window) and TFI (texture
from inter-spike intervals), the baselines of the paper and the source of previews.

Both return a rate in spikes per frame ``float32 [H, W]``; :func:`rate_to_radiance` turns a
rate into linear radiance by inverting ``lambda = R ((I / 256) X + d)``.
"""
from __future__ import annotations

import numpy as np

from .errors import InputError


def _window(T: int, window: int, center: int | None) -> tuple[int, int]:
    if window < 1:
        raise InputError(f"window must be >= 1 frame, got {window}")
    window = min(window, T)
    c = T // 2 if center is None else int(center)
    a = min(max(0, c - window // 2), T - window)
    return a, a + window


def tfp(spikes: np.ndarray, window: int, center: int | None = None) -> np.ndarray:
    """Mean spikes per frame over ``window`` frames centred at ``center`` (default T/2)."""
    a, b = _window(spikes.shape[0], window, center)
    return (spikes[a:b].sum(axis=0, dtype=np.int32) / np.float32(b - a)).astype(np.float32)


def tfi(spikes: np.ndarray, t: int | None = None) -> np.ndarray:
    """Rate ``1 / ISI`` from the interval that contains frame ``t`` (default T/2).

    The interval runs from the last spike at or before ``t`` to the first spike after ``t``.
    A pixel without such an interval falls back to its mean rate over the whole stream.
    """
    T = spikes.shape[0]
    t = T // 2 if t is None else int(np.clip(t, 0, T - 1))
    frames = np.arange(T, dtype=np.int32)[:, None, None]
    fired = spikes.astype(bool)
    prev = np.where(fired[: t + 1], frames[: t + 1], -1).max(axis=0)
    nxt = np.where(fired[t + 1:], frames[t + 1:], T + 1).min(axis=0) if t + 1 < T else np.full(prev.shape, T + 1)
    ok = (prev >= 0) & (nxt <= T)
    mean_rate = spikes.sum(axis=0, dtype=np.int32) / np.float32(T)
    isi = np.where(ok, nxt - prev, 1).astype(np.float32)
    return np.where(ok, 1.0 / isi, mean_rate).astype(np.float32)


def rate_to_radiance(rate: np.ndarray, intensity: float, sensor=None) -> np.ndarray:
    """Spikes per frame -> linear radiance X, inverting ``lambda = R ((I / 256) X + d)``."""
    rate = np.asarray(rate, dtype=np.float64)
    if sensor is None:
        resp, dark = 1.0, 0.0
    else:
        resp, dark = sensor.maps(*rate.shape[-2:])
    x = (rate / resp - dark) * (256.0 / float(intensity))
    return np.maximum(x, 0.0).astype(np.float32)
