"""PSNR / SSIM as NeRF papers compute them."""
import numpy as np
import pytest

pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from spikenerf.metrics import Lpips, psnr, ssim, ssim_map  # noqa: E402


def test_psnr_known_value_and_mask():
    gt = np.zeros((10, 10))
    pred = np.full((10, 10), 0.1)  # MSE 0.01 -> 20 dB
    assert psnr(pred, gt) == pytest.approx(20.0)
    mask = np.zeros((10, 10), bool)
    mask[:2] = True
    pred2 = pred.copy()
    pred2[2:] = 0.0
    assert psnr(pred2, gt, mask) == pytest.approx(20.0)
    assert psnr(pred2, gt) == pytest.approx(20.0 + 10 * np.log10(5))


def test_ssim_identity_noise_and_size():
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (40, 50))
    assert ssim(img, img) == pytest.approx(1.0)
    assert ssim_map(img, img).shape == (30, 40)  # 'valid' 11 x 11 window
    noisy = np.clip(img + rng.normal(0, 0.2, img.shape), 0, 1)
    assert ssim(noisy, img) < 0.9
    mask = np.zeros(img.shape, bool)
    mask[:20] = True
    half = img.copy()
    half[25:] = noisy[25:]
    assert ssim(half, img, mask) > 0.999 > ssim(half, img)


def test_ssim_matches_reference_formula_on_constant_images():
    a, b = np.full((20, 20), 0.2), np.full((20, 20), 0.6)
    c1 = 0.01 ** 2
    expected = (2 * 0.2 * 0.6 + c1) / (0.2 ** 2 + 0.6 ** 2 + c1)
    assert ssim(a, b) == pytest.approx(expected, rel=1e-9)


def test_lpips_reports_why_it_is_missing():
    lp = Lpips()
    assert lp.available or "lpips" in lp.reason
