"""Pictures of spike streams: rate images a person can look at."""
from __future__ import annotations

import numpy as np

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
