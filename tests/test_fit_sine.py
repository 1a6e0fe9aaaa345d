"""spikegen.fidelity.stats.fit_sine: its grid of residuals from FFTs is the least-squares fit of
each frequency, and a hidden flicker is found at its period. Synthetic, seeded, fast."""
import numpy as np
import pytest

from spikegen.fidelity import stats


def _signal(T, period, depth, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(T, dtype=np.float64)
    light = 3000.0 + 50.0 * np.sin(t / 500.0)
    return light * (1 + depth * np.sin(2 * np.pi * t / period + 0.3)) + rng.normal(0, 40, T), light


@pytest.mark.parametrize("T,start", [(600, 2.0), (601, 1.6), (800, 0.37)])
def test_fft_grid_is_the_least_squares_fit_of_every_frequency(T, start):
    s, light = _signal(T, 37.0, 0.02, 1)
    count = int(np.ceil(4 * T / 6.0 - start))
    fast = stats._sine_rss_fft(s, light, start, count)
    t = np.arange(T, dtype=np.float64)
    slow = np.array([stats._sine_rss(s, t, light, (start + i) / (4.0 * T))[0] for i in range(count)])
    assert fast.shape == slow.shape
    np.testing.assert_allclose(fast, slow, rtol=1e-8)


@pytest.mark.parametrize("period", [9.5, 37.0, 250.0])
def test_fit_sine_finds_a_hidden_flicker(period):
    T = 4000
    s, light = _signal(T, period, 0.02, 2)
    fit = stats.fit_sine(s, light, 6.0, 2.0 * T)
    assert abs(fit.period_frames - period) < 0.01 * period
    assert abs(fit.depth - 0.02) < 0.004
    assert fit.z > 10
    flat, _ = _signal(T, period, 0.0, 2)
    assert stats.fit_sine(flat, light, 6.0, 2.0 * T).z < fit.z / 3
