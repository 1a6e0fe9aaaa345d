"""Image metrics as NeRF papers compute them, on display-encoded luminance in [0, 1].

- PSNR: ``-10 log10(MSE)``, per view, averaged over views.
- SSIM: Gaussian window (11 x 11, sigma 1.5), K1 = 0.01, K2 = 0.03, 'valid' filtering
  (the mip-NeRF / NeRF evaluation code's definition); the SSIM map's mean.
- Object region: pixels where the ground truth's alpha > 0; PSNR over those pixels, SSIM as
  the mean of the SSIM map over those pixels (the map is 10 px smaller; the mask is cropped).
- LPIPS: needs its network weights; nothing can be downloaded here, so it is computed only
  if the ``lpips`` package and its weights are installed, else reported as null.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

SSIM_SIZE, SSIM_SIGMA, K1, K2 = 11, 1.5, 0.01, 0.03


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    err = (np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2
    mse = float(err[mask].mean() if mask is not None else err.mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def _gauss_kernel() -> torch.Tensor:
    x = torch.arange(SSIM_SIZE, dtype=torch.float64) - (SSIM_SIZE - 1) / 2
    g = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return g / g.sum()


def ssim_map(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """SSIM map ``[H - 10, W - 10]`` of two ``[H, W]`` images in [0, 1]."""
    g = _gauss_kernel()
    kx, ky = g.view(1, 1, 1, -1), g.view(1, 1, -1, 1)

    def blur(z):
        return F.conv2d(F.conv2d(z, kx), ky)

    a = torch.as_tensor(np.asarray(pred, np.float64))[None, None]
    b = torch.as_tensor(np.asarray(gt, np.float64))[None, None]
    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a ** 2
    var_b = blur(b * b) - mu_b ** 2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = K1 ** 2, K2 ** 2
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2)
    return (num / den)[0, 0].numpy()


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    m = ssim_map(pred, gt)
    if mask is None:
        return float(m.mean())
    r = SSIM_SIZE // 2
    sub = np.asarray(mask)[r:-r, r:-r]
    return float(m[sub].mean()) if sub.any() else float("nan")


class Lpips:
    """LPIPS if the ``lpips`` package and its weights are installed locally; else ``available`` False."""

    def __init__(self):
        self.net, self.reason = None, ""
        try:
            import lpips  # noqa: F401  (optional; never downloaded by this project)
        except ImportError:
            self.reason = "the lpips package is not installed (its network weights cannot be downloaded here)"
            return
        try:
            self.net = lpips.LPIPS(net="alex", verbose=False)
        except Exception as exc:
            self.reason = f"lpips weights not available locally ({exc.__class__.__name__})"

    @property
    def available(self) -> bool:
        return self.net is not None

    def __call__(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
        def t(z):
            z = torch.as_tensor(np.asarray(z, np.float32))
            if mask is not None:
                z = z * torch.as_tensor(np.asarray(mask, np.float32))
            return (z * 2 - 1)[None, None].expand(1, 3, *z.shape)

        with torch.no_grad():
            return float(self.net(t(pred), t(gt)).mean())


# ---------------------------------------------------------------------- tone: bias per luminance level
# Bins of the ground truth's linear luminance (on white) in which Tone compares the prediction's mean with the
# truth's: is a level rendered too bright or too dark? The low bins are narrow because the dark end is where
# a display (sRGB) shows a bias most: 0.004 linear is 14 of 255 in sRGB, 0.012 is 29.
TONE_EDGES = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.7, 1.0)
FLAT_RADIUS = 2  # Tone's flat pixels: no other bin within this many pixels


def _window_extremes(img: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """The min and the max of ``img`` over each pixel's ``(2r+1) x (2r+1)`` window (the image's edge pixels
    repeated outside it)."""
    padded = np.pad(img, r, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(padded, (2 * r + 1, 2 * r + 1))
    return win.min(axis=(2, 3)), win.max(axis=(2, 3))


class Tone:
    """The rendered luminance's bias per level of the ground truth's, over the object (alpha > 0.5).

    Each pixel falls in a bin of :data:`TONE_EDGES` by its ground truth's linear luminance; per bin the means of
    the truth and of the prediction (both linear, the prediction clamped to [0, 1] as displayed) and their
    difference, the bias. A blurred image moves light from bright pixels to their dark neighbours, so it
    lifts the dark bins near edges; the bin's *flat* pixels (their whole ``(2r+1) x (2r+1)`` neighbourhood,
    ``r`` = :data:`FLAT_RADIUS`, in the same bin and in the object) see no edge within that reach, so a bias
    there is the level's own (the sensor model, the loss, the field's parameterisation), not that of a blur
    of up to ``r`` pixels.
    """

    def __init__(self, edges=TONE_EDGES):
        self.edges = np.asarray(edges, np.float64)
        n = len(self.edges) - 1
        self.sums = {k: np.zeros(n) for k in ("pixels", "truth", "pred", "flat_pixels", "flat_truth", "flat_pred")}

    def add(self, pred: np.ndarray, truth: np.ndarray, alpha: np.ndarray) -> None:
        """One view: linear luminance ``[H, W]`` rendered and true, and the truth's alpha."""
        pred = np.clip(np.asarray(pred, np.float64), 0.0, 1.0)
        truth = np.asarray(truth, np.float64)
        n = len(self.edges) - 1
        level = np.clip(np.searchsorted(self.edges, truth, side="right") - 1, 0, n - 1)
        obj = np.asarray(alpha) > 0.5
        lo, hi = _window_extremes(level, FLAT_RADIUS)
        flat = obj & (lo == hi) & (_window_extremes(obj.astype(np.int8), FLAT_RADIUS)[0] == 1)
        for key, mask in (("", obj), ("flat_", flat)):
            self.sums[key + "pixels"] += np.bincount(level[mask], minlength=n)
            self.sums[key + "truth"] += np.bincount(level[mask], truth[mask], minlength=n)
            self.sums[key + "pred"] += np.bincount(level[mask], pred[mask], minlength=n)

    def summary(self) -> list[dict]:
        """Per bin: its edges, the pixels, the truth's and the prediction's mean and the bias (linear), and the
        same over its flat pixels (None where a bin has none)."""
        rows = []
        for i, (lo, hi) in enumerate(zip(self.edges[:-1], self.edges[1:])):
            row = {"truth_from": float(lo), "truth_to": float(hi)}
            for key in ("", "flat_"):
                n = int(self.sums[key + "pixels"][i])
                t = self.sums[key + "truth"][i] / n if n else None
                p = self.sums[key + "pred"][i] / n if n else None
                row.update({key + "pixels": n, key + "truth": t, key + "pred": p,
                            key + "bias": None if n == 0 else p - t})
            rows.append(row)
        return rows
