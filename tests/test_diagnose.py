"""`spikegen diagnose`: hidden-effect tests.

Each test draws an effect (or two) and its parameters at random inside the detectability
envelope (spikegen.fidelity.synth.RANGES; seeded, but the diagnosis is not told), makes the
"measured" recording with the simulator (64 x 64 pixels, 1000 frames, intensity 32..256,
reference radiance 0.05..1), and requires the diagnosis to name the effect first (pairs: both
among the detected) and to estimate its parameter within 20 %. Clean data: nothing detected.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from spikegen.cli import main
from spikegen.fidelity import synth
from spikegen.fidelity.diagnose import diagnose
from spikegen.sensorfile import load_sensor
from spikegen.spikeio import write_spikes

TOLERANCE = 0.2


def _check_estimate(result, name, params):
    key, true = synth.true_value(name, params)
    if key is None:
        return
    est = result.effect(name).parameters.get(key)
    assert est is not None, f"{name}: no estimate of {key}"
    assert abs(est - true) <= TOLERANCE * abs(true), f"{name}: {key} estimated {est:.5g}, true {true:.5g}"


def _run(names, seed):
    spikes, radiance, intensity, effects = synth.hidden_case(names, seed)
    return diagnose(spikes, radiance, intensity), effects, intensity


@pytest.mark.parametrize("name", synth.EFFECTS)
def test_hidden_effect_is_named_first_and_measured(name):
    result, effects, intensity = _run([name], seed=1)
    assert result.detected[:1] == [name], f"I={intensity:.0f} {effects}: detected {result.detected}"
    _check_estimate(result, name, effects[name])


# A fixed list of pairs in which every effect appears (parameters drawn at random, seeded);
# random pairs are in the sweep below.
PAIRS = [("gain_nonuniformity", "shot_noise"), ("column_pattern", "dark_current"), ("hot_pixels", "refractory"),
         ("nonlinearity", "crosstalk"), ("flicker", "dark_current"), ("reset_to_zero", "gain_nonuniformity"),
         ("column_pattern", "hot_pixels"), ("shot_noise", "nonlinearity"), ("reset_to_zero", "hot_pixels"),
         ("flicker", "shot_noise")]


@pytest.mark.parametrize("pair", PAIRS, ids=["+".join(p) for p in PAIRS])
def test_hidden_pair_is_found(pair):
    result, effects, intensity = _run(list(pair), seed=2)
    for name in pair:
        assert name in result.detected, f"I={intensity:.0f} {effects}: detected {result.detected}"
        _check_estimate(result, name, effects[name])


@pytest.mark.parametrize("seed", [1, 2])
def test_clean_data_shows_nothing(seed):
    result, _, intensity = _run([], seed=seed)
    assert result.detected == [], f"I={intensity:.0f}: detected {result.detected} on baseline data"
    gain = result.gain()
    assert set(gain) == set(result.baseline_measures)


def test_extended_model_gains_on_held_out_frames():
    result, _, _ = _run(["gain_nonuniformity", "dark_current"], seed=3)
    gain = result.gain()
    assert gain["rate_rel_rmse"]["extended"] < 0.5 * gain["rate_rel_rmse"]["baseline"]
    assert gain["dark_rate_error"]["extended"] < 0.5 * gain["dark_rate_error"]["baseline"]


def test_self_reference_finds_temporal_effects():
    """No reference: the radiance is estimated from the data (a static, smooth scene)."""
    from spikegen.sensor import simulate

    rng = np.random.default_rng(4)
    params = synth.draw_parameters("shot_noise", rng)
    yy, xx = np.mgrid[0:64, 0:64] / 63.0
    radiance = 0.05 + 0.95 * (0.5 + 0.5 * np.sin(2 * np.pi * (0.7 * xx + 0.4 * yy))) ** 2  # smooth, 0.05..1
    spikes = simulate(radiance, 64.0, synth.make_sensor({"shot_noise": params}, 64, 64, rng), frames=1000, seed=9)
    result = diagnose(spikes, "self", 64.0)
    assert result.detected[:1] == ["shot_noise"], result.detected
    _check_estimate(result, "shot_noise", params)
    assert result.effect("gain_nonuniformity").note  # says why it cannot tell


def test_cli_json_report_and_saved_sensor(tmp_path):
    spikes, radiance, intensity, effects = synth.hidden_case(["dark_current"], seed=5, frames=600)
    write_spikes(tmp_path / "m.dat", spikes)
    np.save(tmp_path / "ref.npy", radiance.astype(np.float32))
    code = main(["diagnose", str(tmp_path / "m.dat"), "--size", "64x64", "--reference", str(tmp_path / "ref.npy"),
                 "--intensity", f"{intensity}", "--json", str(tmp_path / "d.json"), "--report", str(tmp_path / "rep"),
                 "--save-sensor", str(tmp_path / "ext")])
    assert code == 0
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["detected"][0] == "dark_current"
    assert [e["name"] for e in doc["effects"]] == list(synth.EFFECTS)
    for e in doc["effects"]:
        assert set(e) >= {"name", "detected", "score", "parameters"}
    assert set(doc["baseline"]) == set(doc["extended"]) == set(doc["gain"])
    sensor = load_sensor(tmp_path / "ext.json")
    assert np.median(sensor.dark_rate) == pytest.approx(effects["dark_current"]["rate"], rel=0.2)
    assert (tmp_path / "rep" / "report.md").is_file()
    assert list((tmp_path / "rep").glob("*.png"))


def test_cli_bad_reference_is_one_line(tmp_path, capsys):
    write_spikes(tmp_path / "m.npz", np.zeros((100, 8, 8), dtype=np.uint8))
    np.save(tmp_path / "ref.npy", np.ones((9, 8), dtype=np.float32))
    code = main(["diagnose", str(tmp_path / "m.npz"), "--reference", str(tmp_path / "ref.npy"),
                 "--json", str(tmp_path / "d.json")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "8x9" in err
    assert not (tmp_path / "d.json").exists()


@pytest.mark.slow
@pytest.mark.parametrize("name", list(synth.EFFECTS) + ["none"])
def test_sweep_many_draws(name):
    """The exhaustive sweep: 8 draws per effect (and of clean data)."""
    failures = []
    for seed in range(10, 18):
        names = [] if name == "none" else [name]
        result, effects, intensity = _run(names, seed)
        if name == "none":
            if result.detected:
                failures.append((seed, intensity, result.detected))
            continue
        try:
            assert result.detected[:1] == [name]
            _check_estimate(result, name, effects[name])
        except AssertionError as exc:
            failures.append((seed, intensity, effects, result.detected, str(exc)))
    assert not failures


@pytest.mark.slow
def test_sweep_random_pairs():
    """20 random pairs (synth.draw_pair: every pair except the documented known confusion)."""
    failures = []
    for k in range(20):
        names = synth.draw_pair(np.random.default_rng(7000 + k))
        result, effects, intensity = _run(names, 30 + k)
        try:
            for name in names:
                assert name in result.detected, f"{name} not detected"
                _check_estimate(result, name, effects[name])
        except AssertionError as exc:
            failures.append((k, round(intensity), effects, result.detected, str(exc)))
    assert not failures
