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
