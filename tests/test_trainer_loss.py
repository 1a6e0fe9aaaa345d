"""What each method's loss takes from the dataset's sensor (train.method_loss): spikelik its shot
noise and reset, the idealised spikenerf neither."""
import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from spikenerf import neuron  # noqa: E402
from spikenerf.methods import METHODS  # noqa: E402
from spikenerf.targets import Targets  # noqa: E402
from spikenerf.train import Batch, method_loss  # noqa: E402

INTENSITY = 64.0


def _batch(**sensor):
    rng = np.random.default_rng(0)
    P = 6
    tg = Targets(poses=np.tile(np.eye(4, dtype=np.float32), (2, 1, 1)),
                 values=rng.integers(0, 120, (2, P)).astype(np.float32), frames=np.array([256, 128], np.float32),
                 resp=rng.uniform(0.8, 1.2, P).astype(np.float32), dark=np.full(P, 0.01, np.float32),
                 height=2, width=3, kind="counts")
    return Batch(dataclasses.replace(tg, **sensor), torch.device("cpu"))


def _loss(method, batch, x):
    img, pix = torch.tensor([0, 0, 1, 1]), torch.tensor([0, 3, 2, 5])
    return method_loss(METHODS[method], x, img, pix, batch, INTENSITY)[0], img, pix


def _by_hand(batch, x, img, pix, electrons=0.0, reset="subtract"):
    lam = neuron.spike_rate(x, INTENSITY, batch.resp[pix], batch.dark[pix])
    frames = batch.frames[img]
    mu = neuron.expected_count(lam, frames, reset)
    var = 1 / 6 + mu / electrons if electrons else torch.full_like(mu, 1 / 6)
    obs = batch.values[img, pix]
    return ((mu - obs).square() / (6 * var) * (256 / (INTENSITY * frames)).square()).mean()


def test_spikelik_weights_by_the_sensors_shot_noise():
    x = torch.tensor([0.2, 0.5, 0.7, 0.95])
    noisy, quiet = _batch(electrons=4.0), _batch()
    loss, img, pix = _loss("spikelik", noisy, x)
    assert float(loss) == pytest.approx(float(_by_hand(noisy, x, img, pix, electrons=4.0)), rel=1e-6)
    assert float(loss) < 0.5 * float(_loss("spikelik", quiet, x)[0])  # bright pixels weigh less


def test_spikelik_uses_the_reset_to_zero_neuron():
    x = torch.tensor([0.2, 0.5, 0.7, 0.95])
    zero = _batch(reset="zero")
    loss, img, pix = _loss("spikelik", zero, x)
    assert float(loss) == pytest.approx(float(_by_hand(zero, x, img, pix, reset="zero")), rel=1e-6)
    assert float(loss) != pytest.approx(float(_by_hand(zero, x, img, pix)), rel=1e-3)


def test_idealised_spikenerf_ignores_shot_noise_and_reset():
    x = torch.tensor([0.2, 0.5, 0.7, 0.95])
    plain = _loss("spikenerf", _batch(), x)[0]
    assert float(_loss("spikenerf", _batch(electrons=4.0, reset="zero"), x)[0]) == float(plain)


def test_oracle_fits_the_srgb_encoding_of_the_ground_truth():
    from spikegen.spikeio import linear_to_srgb
    from spikenerf.train import linear_to_srgb as srgb_t

    v = np.array([0.0, 0.002, 0.0031308, 0.2, 0.9, 1.0])
    assert np.allclose(srgb_t(torch.tensor(v, dtype=torch.float64)).numpy(), linear_to_srgb(v), atol=1e-12)
    tg = Targets(poses=np.tile(np.eye(4, dtype=np.float32), (2, 1, 1)),
                 values=np.array([[0.1, 0.5, 1.0], [0.0, 0.3, 0.8]], np.float32), frames=np.zeros(2, np.float32),
                 resp=np.ones(3, np.float32), dark=np.zeros(3, np.float32), height=1, width=3, kind="radiance")
    batch = Batch(tg, torch.device("cpu"))
    img, pix = torch.tensor([0, 1, 1]), torch.tensor([2, 0, 1])
    x = torch.tensor([0.9, 0.05, 0.3], requires_grad=True)
    loss = method_loss(METHODS["oracle"], x, img, pix, batch, INTENSITY)[0]
    want = np.mean((linear_to_srgb([0.9, 0.05, 0.3]) - linear_to_srgb([1.0, 0.0, 0.3])) ** 2)
    assert float(loss.detach()) == pytest.approx(want, rel=1e-5)
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad[2] == 0 and x.grad[0] < 0 and x.grad[1] > 0


def test_srgb_weight_weighs_each_ray_by_the_displays_slope():
    """``--srgb-weight``: each likelihood term times (sRGB slope at its luminance / slope at grey)^2, capped. A
    dark ray (X = 0.001, on the encoding's linear part: slope 12.92) then weighs 385 times a grey one (X = 0.5),
    a white one 0.45 times; the cap bounds it; the terms themselves are the likelihood's."""
    from spikenerf.train import SRGB_SLOPE_AT_GREY, display_weight

    x = torch.tensor([0.001, 0.5, 1.0, 0.0])
    w = display_weight(x, 1000.0)
    assert float(w[1]) == pytest.approx(1.0) and float(w[0]) == pytest.approx((12.92 / SRGB_SLOPE_AT_GREY) ** 2)
    assert float(w[0]) == pytest.approx(384.8, abs=0.1) and float(w[3]) == float(w[0])
    assert float(w[2]) == pytest.approx((1.055 / 2.4 / SRGB_SLOPE_AT_GREY) ** 2) and 0.44 < float(w[2]) < 0.45
    assert float(display_weight(x, 10.0)[0]) == 10.0 and float(display_weight(x, 10.0)[1]) == pytest.approx(1.0)
    batch = _batch()
    xs = torch.tensor([0.001, 0.5, 0.7, 0.95], requires_grad=True)
    img, pix = torch.tensor([0, 0, 1, 1]), torch.tensor([0, 3, 2, 5])
    plain = method_loss(METHODS["spikelik"], xs, img, pix, batch, INTENSITY)[0]
    weighted = method_loss(METHODS["spikelik"], xs, img, pix, batch, INTENSITY, srgb_weight=1000.0)[0]
    # the weighted mean is the plain terms' mean with the weights (as computed by hand)
    lam = neuron.spike_rate(xs, INTENSITY, batch.resp[pix], batch.dark[pix])
    frames = batch.frames[img]
    terms = ((neuron.expected_count(lam, frames) - batch.values[img, pix]).square() / (6 / 6)
             * (256 / (INTENSITY * frames)).square())
    assert float(plain.detach()) == pytest.approx(float(terms.mean().detach()), rel=1e-6)
    want = (terms * display_weight(xs, 1000.0)).mean().detach()
    assert float(weighted.detach()) == pytest.approx(float(want), rel=1e-6)
    g_plain = torch.autograd.grad(plain, xs)[0]
    g_weighted = torch.autograd.grad(weighted, xs)[0]
    ratio = g_weighted / g_plain  # the weight is not differentiated: each ray's gradient scales by its weight
    assert torch.allclose(ratio, display_weight(xs, 1000.0), rtol=1e-5)
