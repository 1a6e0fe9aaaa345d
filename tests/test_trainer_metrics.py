"""PSNR / SSIM as NeRF papers compute them; LPIPS only when its package and weights are there."""
import sys
import types

import numpy as np
import pytest

pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from spikenerf.metrics import TONE_EDGES, Lpips, Tone, psnr, ssim, ssim_map  # noqa: E402


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


def test_lpips_without_the_package_says_so(monkeypatch):
    monkeypatch.setitem(sys.modules, "lpips", None)  # "import lpips" then raises ImportError
    lp = Lpips()
    assert not lp.available
    assert lp.reason.startswith("the lpips package is not installed")


def _fake_lpips(monkeypatch, make_net):
    fake = types.ModuleType("lpips")
    fake.LPIPS = make_net
    monkeypatch.setitem(sys.modules, "lpips", fake)


def test_lpips_without_weights_names_the_failure(monkeypatch):
    def no_weights(**kwargs):
        raise FileNotFoundError("alex.pth")

    _fake_lpips(monkeypatch, no_weights)
    lp = Lpips()
    assert not lp.available
    assert lp.reason == "lpips weights not available locally (FileNotFoundError)"


def test_lpips_feeds_the_network_three_channels_in_minus_one_to_one(monkeypatch):
    seen = []

    def net(a, b):
        seen.append((a.shape, float(a.min()), float(a.max())))
        return (a - b).abs().mean()

    _fake_lpips(monkeypatch, lambda **kwargs: net)
    lp = Lpips()
    assert lp.available
    pred, gt = np.full((6, 8), 0.75), np.zeros((6, 8))
    assert lp(pred, gt) == pytest.approx(1.5)  # 0.75 -> 0.5 against 0 -> -1
    assert seen[0] == ((1, 3, 6, 8), 0.5, 0.5)
    mask = np.zeros((6, 8), bool)
    mask[:3] = True  # outside the mask both images become 0 -> -1
    assert lp(pred, gt, mask) == pytest.approx(0.75)


def _dark_square(size=100):
    """Linear luminance: 0.5 with a 40 x 40 square of 0.005 in it; alpha 1 but for a 10-pixel frame of 0."""
    truth = np.full((size, size), 0.5)
    truth[30:70, 30:70] = 0.005
    alpha = np.zeros((size, size))
    alpha[10:-10, 10:-10] = 1.0
    return truth, alpha


def _bin(rows, value):
    return next(r for r in rows if r["truth_from"] <= value < r["truth_to"])


def test_tone_tells_a_blur_from_a_lifted_level():
    """Two effects hidden in a rendered image of a dark square on grey: a blur (5 x 5 box) lifts the dark
    bin only at the square's edge, so its flat pixels keep their level exactly; a level bias (+0.01 on every
    pixel darker than 0.01) shows in the flat pixels as itself. Neither touches the grey bin's flat pixels."""
    truth, alpha = _dark_square()
    padded = np.pad(truth, 2, mode="edge")
    blurred = np.lib.stride_tricks.sliding_window_view(padded, (5, 5)).mean(axis=(2, 3))
    lifted = truth + np.where(truth < 0.01, 0.01, 0.0)
    blur, lift = Tone(), Tone()
    blur.add(blurred, truth, alpha)
    lift.add(lifted, truth, alpha)
    b, l = _bin(blur.summary(), 0.005), _bin(lift.summary(), 0.005)
    assert b["pixels"] == l["pixels"] == 40 * 40 and b["truth"] == pytest.approx(0.005)
    assert b["bias"] > 0.005  # the edge's light, averaged over the square
    assert b["flat_pixels"] == 36 * 36 and b["flat_bias"] == pytest.approx(0.0, abs=1e-12)  # FLAT_RADIUS = 2
    assert l["bias"] == pytest.approx(0.01) and l["flat_bias"] == pytest.approx(0.01)
    for t in (blur, lift):
        grey = _bin(t.summary(), 0.5)
        assert grey["pixels"] == 80 * 80 - 40 * 40 and grey["flat_bias"] == pytest.approx(0.0, abs=1e-12)
    assert sum(r["pixels"] for r in blur.summary()) == 80 * 80  # alpha <= 0.5 is not the object
    empty = _bin(blur.summary(), 0.15)
    assert empty["pixels"] == 0 and empty["bias"] is None and empty["flat_bias"] is None


def test_tone_clamps_the_prediction_as_displayed_and_sums_over_views():
    truth, alpha = _dark_square()
    t = Tone()
    t.add(np.full_like(truth, 2.0), truth, alpha)  # displayed as 1
    t.add(truth, truth, alpha)
    grey = _bin(t.summary(), 0.5)
    assert grey["pixels"] == 2 * (80 * 80 - 40 * 40) and grey["pred"] == pytest.approx(0.75)
    assert grey["bias"] == pytest.approx(0.25) and len(t.summary()) == len(TONE_EDGES) - 1
