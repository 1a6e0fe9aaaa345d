"""The trainer's differentiable sensor agrees with the generator's sensor model."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from spikegen.sensor import Sensor, simulate  # noqa: E402
from spikenerf import neuron  # noqa: E402


def _scene(rng, H=16, W=24):
    x = rng.uniform(0.0, 1.0, (H, W))
    resp = rng.uniform(0.8, 1.25, (H, W))
    dark = rng.uniform(0.0, 0.02, (H, W))
    return x, resp, dark


@pytest.mark.parametrize("intensity", [16, 64, 200])
def test_expected_count_matches_simulate_subtractive(intensity):
    rng = np.random.default_rng(7)
    x, resp, dark = _scene(rng)
    T = 256
    spikes = simulate(x, intensity, Sensor(name="t", responsivity=resp, dark_rate=dark), frames=T, seed=3)
    counts = spikes.sum(axis=0)
    lam = neuron.spike_rate(torch.tensor(x), intensity, torch.tensor(resp), torch.tensor(dark))
    mu = neuron.expected_count(lam, T).numpy()
    # floor(A0 + T lambda) with A0 in [0, 1): within one spike of the mean, per pixel
    assert np.all(np.abs(counts - mu) < 1.0 + 1e-6)
    # and unbiased over pixels (uniform start phase)
    assert abs((counts - mu).mean()) < 0.15


def test_expected_count_saturates_like_the_sensor():
    x = np.full((8, 8), 1.0)
    spikes = simulate(x, 512, Sensor(), frames=64, seed=0)  # lambda = 2 > 1: one spike a frame
    mu = neuron.expected_count(neuron.spike_rate(torch.tensor(x), 512, None, None), 64).numpy()
    assert np.all(spikes.sum(axis=0) == 64) and np.allclose(mu, 64)


def test_reset_to_zero_staircase_matches_simulate():
    rng = np.random.default_rng(1)
    x = rng.uniform(0.05, 1.0, (8, 16))
    T, intensity = 256, 128
    spikes = simulate(x, intensity, Sensor(reset="zero"), frames=T, seed=5)
    lam = neuron.spike_rate(torch.tensor(x), intensity, None, None)
    mu = neuron.expected_count(lam, T, reset="zero").numpy()
    assert np.all(np.abs(spikes.sum(axis=0) - mu) <= 1.0 + 1e-6)
    # and it is lower than the subtractive count where 1/lambda is not an integer
    assert np.all(mu <= neuron.expected_count(lam, T).numpy() + 1e-9)


def test_gradient_flows_through_reset_to_zero():
    lam = torch.tensor([0.3, 0.6], requires_grad=True)
    neuron.expected_count(lam, 100, reset="zero").sum().backward()
    assert torch.all(lam.grad > 0)


def test_count_variance_grows_with_shot_noise():
    mu = torch.tensor([0.0, 10.0])
    assert torch.allclose(neuron.count_variance(mu), torch.full((2,), 1 / 6))
    assert neuron.count_variance(mu, electrons=5.0)[1] == pytest.approx(1 / 6 + 2.0)


def test_count_variance_of_threshold_jitter_matches_simulate():
    """The simulator with a threshold jitter of relative SD 0.1: window counts keep their mean
    and their variance grows by count_variance's 2 sigma^2 (64 windows of 32 frames, 64 x 64
    pixels at rates 0.02-0.9; the same seed without jitter as the reference)."""
    lam = np.random.default_rng(0).uniform(0.02, 0.9, (64, 64))
    sigma, w, n = 0.1, 32, 64
    res = {}
    for j in (0.0, sigma):
        s = simulate(lam * 4, 64, Sensor(threshold_jitter=j), frames=w * n, seed=5)
        res[j] = s.reshape(n, w, 64, 64).sum(1).astype(np.float64) - lam[None] * w
    assert abs(res[sigma].mean()) < 0.003
    mu = torch.tensor([float(w) * 0.5])
    added = float(neuron.count_variance(mu, jitter=sigma) - neuron.count_variance(mu))
    assert added == pytest.approx(2 * sigma ** 2)
    assert res[sigma].var() - res[0.0].var() == pytest.approx(added, abs=0.003)


@pytest.mark.parametrize("intensity", [16, 64])
def test_rsir_mean_charge_matches_the_reference_generator(intensity):
    # 256 pixels per radiance level, so the generator's per-frame noise averages out
    x = np.repeat(np.linspace(0.02, 1.0, 6)[:, None], 256, axis=1)
    resp = np.random.default_rng(2).uniform(0.9, 1.1, x.shape)
    dark = np.full(x.shape, 0.004)
    sensor = Sensor(name="r", kind="rsir", responsivity=resp, dark_rate=dark)
    counts = simulate(x, intensity, sensor, frames=256, seed=4).sum(axis=0).mean(axis=1)
    t = [torch.tensor(a) for a in (x, resp, dark)]
    exact = 256 * neuron.rsir_rate(t[0], intensity, t[1], t[2]).numpy().mean(axis=1)
    linear = 256 * neuron.spike_rate(t[0], intensity, t[1], t[2]).numpy().mean(axis=1)
    assert np.all(np.abs(counts - exact) < 0.25)
    if intensity == 64:  # the generator compresses: the linear model is several spikes too high at X = 1
        assert linear[-1] - counts[-1] > 5


def test_rsir_rate_has_gradients():
    x = torch.tensor([0.2, 0.8], requires_grad=True)
    neuron.rsir_rate(x, 32, torch.ones(2), torch.full((2,), 0.004)).sum().backward()
    assert torch.all(x.grad > 0)


def test_rsir_rate_is_the_generators_mean_charge():
    """One sensor model: the trainer's differentiable rsir rate and the generator's rsir_mean_charge
    (which spikegen calibrate --kind rsir inverts) agree to 1e-9 spikes a frame (the trainer keeps the
    Poisson mean above 1e-8, so it is not exact in the dark)."""
    from spikegen.sensor import rsir_mean_charge

    resp = np.linspace(0.6, 1.6, 9)
    dark = np.concatenate([[0.0], np.linspace(0.001, 0.02, 8)])
    for x, intensity in ((0.0, 64), (0.05, 16), (0.25, 64), (0.75, 32), (1.0, 64)):
        ours = neuron.rsir_rate(torch.full((9,), x, dtype=torch.float64), intensity, torch.tensor(resp),
                                torch.tensor(dark)).numpy()
        gen = rsir_mean_charge(x * intensity * 255 / 256, resp, dark)
        np.testing.assert_allclose(ours, gen, rtol=1e-7, atol=1e-9)
