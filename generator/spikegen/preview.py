"""Pictures of spike streams: rate images and animations (TFP over sliding windows) a person can look at."""
from __future__ import annotations

import numpy as np

from .errors import InputError
from .recon import tfi, tfp
from .spikeio import linear_to_srgb


def rate_to_display(rate: np.ndarray, white: float | None = None) -> np.ndarray:
    """Rate ``[H, W]`` -> display values in [0, 1]: scaled so ``white`` (default the 99.5th
    percentile) is 1, then sRGB-encoded as if the rate were linear light."""
    rate = np.asarray(rate, dtype=np.float64)
    white = float(np.percentile(rate, 99.5)) if white is None else float(white)
    return linear_to_srgb(np.clip(rate / max(white, 1e-9), 0.0, 1.0))


def preview_image(spikes: np.ndarray, window: int | None = None) -> np.ndarray:
    """``uint8 [H, 2W + 4]``: TFP over ``window`` frames (default all) | TFI at the middle frame,
    both on the same scale."""
    T, H, W = spikes.shape
    a = tfp(spikes, window or T)
    b = tfi(spikes)
    white = max(float(np.percentile(a, 99.5)), 1e-9)
    gap = np.ones((H, 4))
    img = np.concatenate([rate_to_display(a, white), gap, rate_to_display(b, white)], axis=1)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)


def window_starts(frames: int, window: int, step: int) -> range:
    """First frames of the TFP windows of an animation: every ``step`` frames while a whole
    ``window`` fits in the ``frames`` of the stream (one window if the stream is shorter)."""
    if window < 1 or step < 1:
        raise InputError(f"--window {window} and --step {step}: must be at least 1 frame")
    return range(0, max(1, frames - window + 1), step)


def animation_frames(spikes: np.ndarray, window: int, step: int):
    """Frames ``uint8 [H, W]`` of a spike-stream animation, one per window of :func:`window_starts`:
    TFP over ``window`` frames, all on one scale (the 99.5th percentile of the whole stream's
    rate is white), so brightness is comparable from frame to frame."""
    T = spikes.shape[0]
    white = max(float(np.percentile(tfp(spikes, T), 99.5)), 1e-9)
    for a in window_starts(T, window, step):
        img = rate_to_display(tfp(spikes, window, center=a + min(window, T) // 2), white)
        yield np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
