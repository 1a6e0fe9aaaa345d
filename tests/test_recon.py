"""TFP and TFI reconstructions, and the inverse of the rate model."""
import numpy as np
import pytest

from spikegen.recon import rate_to_radiance, tfi, tfp
from spikegen.sensor import Sensor, simulate


def test_tfp_counts_a_window():
    s = np.zeros((256, 2, 8), np.uint8)
    s[::4] = 1  # rate 0.25
    s[100:140, 1, :] = 1  # burst
    assert np.allclose(tfp(s, 32, center=32)[0], 0.25)
    assert tfp(s, 40, center=120)[1, 0] == 1.0
    assert tfp(s, 1000).shape == (2, 8)  # window capped at T


def test_tfi_uses_the_interval_around_t():
    s = np.zeros((64, 1, 8), np.uint8)
    s[::8, 0, :4] = 1  # ISI 8
    s[::2, 0, 4:] = 1  # ISI 2
    r = tfi(s, t=30)[0]
    assert np.allclose(r[:4], 1 / 8) and np.allclose(r[4:], 1 / 2)
    lone = np.zeros((64, 1, 8), np.uint8)
    lone[10, 0, 0] = 1
    assert tfi(lone)[0, 0] == pytest.approx(1 / 64)  # falls back to the mean rate


def test_reconstructions_invert_the_sensor():
    x = np.linspace(0.1, 1.0, 64).reshape(8, 8)
    sensor = Sensor(responsivity=np.full((8, 8), 1.2), dark_rate=np.full((8, 8), 0.002))
    s = simulate(x, 64, sensor, frames=2048, seed=0)
    est = rate_to_radiance(tfp(s, 2048), 64, sensor)
    assert np.abs(est - x).max() < 0.03
