"""`spikegen diagnose`: the threshold jitter (``Sensor(threshold_jitter=sigma)``: a firing level
drawn anew after each spike, the nominal threshold subtracted, so the timing error does not
accumulate) told from shot noise (which accumulates), alone and together.

The recordings are those of synth.hidden_case (64 x 64 pixels, 1000 frames, intensity log-uniform
in 32..256, reference 0.05..1), with the temporal noise set instead of drawn.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from spikegen.fidelity import synth
from spikegen.fidelity.diagnose import diagnose
from spikegen.fidelity.effects import QUANTISATION_TERMS, _quantisation_change
from spikegen.sensor import Sensor, simulate

TOLERANCE = 0.2


def _case(effects: dict, seed: int):
    """``(spikes, radiance, intensity)``: hidden_case's draws for ``seed`` with ``effects`` fixed."""
    names = sorted(effects, key=synth.EFFECTS.index)
    rng = np.random.default_rng(np.random.SeedSequence([seed, *[synth.EFFECTS.index(n) for n in names]]))
    intensity = float(math.exp(rng.uniform(math.log(32), math.log(256))))
    radiance = synth.test_radiance(64, 64, rng)
    sensor = synth.make_sensor(effects, 64, 64, rng)
    return simulate(radiance, intensity, sensor, frames=1000, seed=int(rng.integers(1 << 30))), radiance, intensity


def _diagnose(effects, seed):
    spikes, radiance, intensity = _case(effects, seed)
    return diagnose(spikes, radiance, intensity), intensity


def _within(result, name, key, true):
    est = result.effect(name).parameters.get(key)
    assert est is not None and abs(est - true) <= TOLERANCE * true, f"{name}: {key} {est} against {true}"


@pytest.mark.parametrize("sigma,seed", [(0.012, 1), (0.035, 2)])
def test_jitter_alone_is_named_and_read_back_not_as_shot_noise(sigma, seed):
    result, intensity = _diagnose({"threshold_jitter": {"sigma": sigma}}, seed)
    assert result.detected == ["threshold_jitter"], f"I={intensity:.0f}: {result.detected}"
    _within(result, "threshold_jitter", "sigma", sigma)
    held = result.heldout["effects"]["threshold_jitter"]
    assert held["kept"] and held["gain_nats"] > 0
    assert result.extended.threshold_jitter == result.effect("threshold_jitter").parameters["sigma"]
    assert result.extended.electrons == 0


@pytest.mark.parametrize("electrons,seed", [(100.0, 3), (1500.0, 4)])
def test_shot_noise_alone_names_no_jitter(electrons, seed):
    result, intensity = _diagnose({"shot_noise": {"electrons": electrons}}, seed)
    assert result.detected == ["shot_noise"], f"I={intensity:.0f}: {result.detected}"
    _within(result, "shot_noise", "electrons", electrons)
    jitter = result.effect("threshold_jitter")
    assert jitter.z < 6.0, (jitter.parameters, jitter.z)  # not even past its significance gate
    assert result.extended.threshold_jitter == 0


@pytest.mark.parametrize("electrons,sigma,seed", [(300.0, 0.02, 5), (1000.0, 0.012, 6)])
def test_shot_noise_and_jitter_together_are_both_named_and_measured(electrons, sigma, seed):
    result, intensity = _diagnose({"shot_noise": {"electrons": electrons},
                                   "threshold_jitter": {"sigma": sigma}}, seed)
    assert set(result.detected) == {"shot_noise", "threshold_jitter"}, f"I={intensity:.0f}: {result.detected}"
    _within(result, "shot_noise", "electrons", electrons)
    _within(result, "threshold_jitter", "sigma", sigma)
    assert result.extended.threshold_jitter > 0 and result.extended.electrons > 0


def test_same_seed_same_jitter_verdict():
    spikes, radiance, intensity = _case({"shot_noise": {"electrons": 500.0}, "threshold_jitter": {"sigma": 0.015}}, 7)
    a, b = (diagnose(spikes, radiance, intensity).as_json() for _ in range(2))
    assert a == b
    assert a["effects"][synth.EFFECTS.index("threshold_jitter")]["parameters"]["sigma"] is not None


@pytest.mark.parametrize("mean", [2.0, 2.05, 2.5, 3.97, 11.3])
@pytest.mark.parametrize("var", [1e-3, 0.02, 0.3, 2.0])
def test_quantisation_change_is_that_of_whole_frame_intervals(mean, var):
    """``E frac(D)(1 - frac(D)) - frac(m)(1 - frac(m))`` for ``D ~ N(m, var)``: the series against a
    quadrature of the Gaussian, within the series' truncation bound ``sum_(k > K) 1 / (pi k)^2 < 1 / (pi^2 K)``
    (largest where the mean is a whole number of frames and the variance small)."""
    sd = math.sqrt(var)
    x = np.linspace(mean - 9 * sd, mean + 9 * sd, 400001)
    pdf = np.exp(-0.5 * ((x - mean) / sd) ** 2)
    g = np.mod(x, 1.0) * (1.0 - np.mod(x, 1.0))
    expected = float(np.sum(g * pdf) / np.sum(pdf)) - (mean % 1.0) * (1.0 - mean % 1.0)
    got = float(_quantisation_change(np.array([mean]), np.array([var]))[0])
    assert got == pytest.approx(expected, abs=1.0 / (math.pi ** 2 * QUANTISATION_TERMS) + 1e-6)



def _car_like(shared_data, electrons: float, sigma: float, seed: int):
    """A static recording at the real car's rates and length: the mean rates of the top-left
    128 x 200 pixels of its 500 frames (mostly 0.15..0.3 spikes a frame) as the radiance at I = 256,
    500 frames through the given temporal noise."""
    car = np.load(shared_data / "real" / "car_500frames_250x400.npz")["arr_0"]
    radiance = np.clip(car[:128, :200].mean(-1, dtype=np.float64), 0.002, 0.9)
    sensor = Sensor(name="truth", electrons=electrons, threshold_jitter=sigma)
    return simulate(radiance, 256.0, sensor, frames=500, seed=seed), radiance


@pytest.mark.parametrize("seed", [77, 78])
def test_jitter_read_back_beside_shot_noise_at_the_car_rates(shared_data, seed):
    """The preset's noise (N_e 2.25e4, SD 0.0036; assets/calibrated.json) at the car's rates: read
    against the noise-free model the jitter came out about 30 % low (0.0026 on seed 77: beside shot
    noise the analytic terms miss part of what it does to whole-frame intervals); against the model
    with the shot noise found (effects._temporal_effects) it is read back within 20 %. (It is
    below the gate's size, so it is reported, not named.)"""
    spikes, radiance = _car_like(shared_data, 2.25e4, 0.0036, seed)
    jitter = diagnose(spikes, radiance, 256.0).effect("threshold_jitter")
    assert jitter.parameters["sigma"] is not None
    assert abs(jitter.parameters["sigma"] - 0.0036) <= TOLERANCE * 0.0036, (jitter.parameters, jitter.z)


@pytest.mark.parametrize("seed", [77, 78])
def test_shot_noise_at_the_car_rates_reads_no_jitter(shared_data, seed):
    """Shot noise alone at the car's level and rates: the jitter's statistic is centred on zero
    (against the noise-free model it read z = -3.1 on seed 77)."""
    spikes, radiance = _car_like(shared_data, 2.25e4, 0.0, seed)
    result = diagnose(spikes, radiance, 256.0)
    jitter = result.effect("threshold_jitter")
    assert abs(jitter.z) < 3.0, (jitter.parameters, jitter.z)
    # the same noise in every row: unlike the real car's background (interval_variance_per_row)
    assert "interval_variance_per_row" not in [u["statistic"] for u in result.unexplained], result.unexplained
