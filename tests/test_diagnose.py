"""`spikegen diagnose`: hidden-effect tests.

Each test draws an effect (or two) and its parameters at random inside the detectability
envelope (spikegen.fidelity.synth.RANGES; seeded, but the diagnosis is not told), makes the
"measured" recording with the simulator (64 x 64 pixels, 1000 frames, intensity 32..256,
reference radiance 0.05..1), and requires the diagnosis to name the effect first (pairs: both
among the detected) and to estimate its parameter within 20 %. Clean data: nothing detected.
"""
from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from spikegen.cli import main
from spikegen.fidelity import stats, synth
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
         ("flicker", "shot_noise"), ("threshold_jitter", "dark_current")]


# ("flicker", "shot_noise") was a strict xfail: the held-out score measured intervals and
# window counts against the whole run, so the flicker's slow modulation counted as variance and
# shot noise of ~1000 electrons lowered the score (docs/fidelity.md).
_PAIR_PARAMS = [pytest.param(p, id="+".join(p)) for p in PAIRS]


@pytest.mark.parametrize("pair", _PAIR_PARAMS)
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
    held = doc["heldout"]
    assert set(held) >= {"measure", "ideal", "fitted", "higher_is_better"} and held["fitted"] > held["ideal"]
    assert doc["unexplained"] == [] and doc["info"]["moving_pixels"] == 0
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
    # Pair 3 (dark_current of median 0.0031 and spread 0.47 with one refractory frame, intensity 97)
    # was a known gap until 2026-11-26: the dark rate read 0.00397 (+28 %). The missing-dark-rate
    # intercept was fitted over every light bin, and the refractory compression of the brightest
    # bins tilted it; it now comes from the darker half (effects.joint_spread): 0.00317 (+2 %).
    assert not failures, failures


# ---------------------------------------------------------------------- the typed records
@pytest.fixture(scope="module")
def flicker_shot_diagnosis():
    spikes, radiance, intensity, effects = synth.hidden_case(["flicker", "shot_noise"], seed=4, frames=600)
    return diagnose(spikes, radiance, intensity), effects


def test_effect_records_are_the_json_entries(flicker_shot_diagnosis):
    result, _ = flicker_shot_diagnosis
    doc = json.loads(json.dumps(result.as_json()))  # what `--json` writes, read back
    assert [e["name"] for e in doc["effects"]] == [e.name for e in result.effects] == list(synth.EFFECTS)
    for rec, entry in zip(result.effects, doc["effects"]):
        assert entry["detected"] is rec.detected
        assert entry["score"] == pytest.approx(rec.score, abs=1e-6)
        assert entry["z"] == (pytest.approx(rec.z, abs=1e-6) if np.isfinite(rec.z) else None)
        assert list(entry["parameters"]) == list(rec.parameters)  # same keys, same order
        for key, value in rec.parameters.items():
            assert entry["parameters"][key] == (None if value is None else pytest.approx(value, abs=1e-6))
        assert entry.get("note", "") == rec.note
        assert "evidence" not in entry  # the verdict's evidence stays out of the public format
    flicker = result.effect("flicker")
    assert flicker.detected and "model_depth_at_period" in flicker.parameters  # added by the readout check
    assert result.detected == doc["detected"] and set(result.detected) == {"flicker", "shot_noise"}


def test_effect_records_are_frozen_and_carry_their_evidence(flicker_shot_diagnosis):
    import dataclasses

    result, _ = flicker_shot_diagnosis
    shot = result.effect("shot_noise")
    with pytest.raises(dataclasses.FrozenInstanceError):
        shot.detected = False
    with pytest.raises(TypeError):
        shot.parameters["electrons"] = 1.0
    assert pickle.loads(pickle.dumps(shot)) == shot
    assert shot.evidence["size"] == shot.parameters["electrons"]
    assert shot.evidence["size_gate"] == 2 * synth.ENVELOPE["shot_noise"]["electrons"]
    assert shot.z >= shot.evidence["z_gate"]
    gain = result.effect("gain_nonuniformity")
    assert gain.parameters["sigma"] == pytest.approx(np.sqrt(max(gain.evidence["variance"], 0.0)))
    fit = result.fit
    assert fit.flicker.period_frames == result.effect("flicker").parameters["period_frames"]
    assert fit.rate.lam_pred.shape == fit.structure.e.shape == (64 * 64,)


def test_gates_and_scores_follow_the_envelope():
    from spikegen.fidelity.records import ENVELOPE_SIZE, GATES, judge

    for name in synth.EFFECTS:
        key = synth.SIZE_KEY[name]
        assert ENVELOPE_SIZE[name] == (1.0 if key is None else synth.ENVELOPE[name][key])
    assert GATES["dark_current"][0] == synth.ENVELOPE["dark_current"]["rate"] / 2
    assert GATES["hot_pixels"][0] == 2  # half of 5 pixels, a whole number
    at_envelope = judge("column_pattern", synth.ENVELOPE["column_pattern"]["sigma"], 50.0, {})
    assert at_envelope.detected and at_envelope.score == pytest.approx(1.0)
    assert not judge("column_pattern", 0.4 * synth.ENVELOPE["column_pattern"]["sigma"], 50.0, {}).detected
    assert not judge("column_pattern", 0.05, 1.0, {}).detected  # large but not significant
    few = judge("shot_noise", 500.0, 50.0, {})  # 500 electrons: 4 x the envelope's variance
    assert few.detected and few.score == pytest.approx(4.0)
    assert not judge("shot_noise", 5000.0, 50.0, {}).detected


def test_interval_formula_and_its_inverse():
    from spikegen.fidelity.records import interval_frames, rate_from_interval

    lam = np.array([0.25, 0.5, 1.0, 2.0])
    # ISI = delta + max(1, 1 / lambda): a rate above one spike per frame saturates at one frame
    assert np.allclose(interval_frames(lam, 0.5), [4.5, 2.5, 1.5, 1.5])
    assert np.allclose(rate_from_interval(interval_frames(lam[:3], 1.5), 1.5), lam[:3])


def _fake_diagnosis(H=4, W=5, with_e=True):
    """A hand-made Diagnosis: rate model lambda = 0.1 x radiance, delta = 0.5 frames."""
    from spikegen.fidelity.diagnose import Diagnosis
    from spikegen.fidelity.records import Effect, Fit, PixelStructure, RateFit
    from spikegen.sensor import Sensor

    P = H * W
    lam = np.linspace(0.05, 0.5, P)
    rate = RateFit(a=1.2, delta=0.5, lam_pred=lam, isi=1.0 / lam, keep=np.ones(P, bool), outlier=np.zeros(P, bool))
    structure = PixelStructure(np.zeros(P, bool), np.ones(P, bool), np.zeros(P), 0.01, np.ones(W),
                               e=np.linspace(0.9, 1.1, P) if with_e else None)
    effects = [Effect(n, n == "dark_current", 3.0 if n == "dark_current" else 0.0,
                      {"rate": 0.006} if n == "dark_current" else {}, 7.5, "a note" if n == "crosstalk" else "")
               for n in synth.EFFECTS]
    measures = {k: 0.1 for k in ("rate_rel_rmse", "dark_rate_error")}
    info = {"frames": 100, "fit_frames": 80, "held_out_frames": 20, "height": H, "width": W, "intensity": 64.0,
            "reference": "1 sub-frame(s)", "baseline_sensor": "ideal"}
    return Diagnosis(effects, Sensor(), measures, dict(measures), Fit(rate, None, structure), info)


def test_report_reads_the_records(tmp_path, monkeypatch):
    from spikegen.fidelity import report
    from spikegen.fidelity.records import interval_frames

    result = _fake_diagnosis()
    md = report.markdown(result)
    assert "Detected, strongest first: `dark_current`." in md
    assert "| dark_current | yes | 3 | 7.5 | rate=0.006 |  |" in md
    assert "| crosstalk | no | 0 | 7.5 |  | a note |" in md

    series = {}

    class Axis:  # records what the plots draw
        figure = type("F", (), {"colorbar": lambda *a, **k: None})()

        def loglog(self, x, y, *a, label=None, **k):
            series[label] = np.asarray(y)

        def __getattr__(self, name):
            return lambda *a, **k: None

    monkeypatch.setattr(report, "save_figure", lambda path, draw, *a, **k: draw(Axis()))
    radiance = np.linspace(0.1, 1.0, 20).reshape(4, 5)  # increasing: the plot's sort keeps pixel order
    names = [n for n, _ in report._plots(result, np.zeros((100, 4, 5), np.uint8), radiance, tmp_path)]
    assert names == ["rates.png", "residual_map.png", "spectrum.png", "isi.png"]
    lam = result.fit.rate.lam_pred
    assert np.allclose(series["fitted model"], 1.0 / interval_frames(lam, 0.5))
    assert np.allclose(series["measured"], lam)
    no_map = _fake_diagnosis(with_e=False)
    assert "residual_map.png" not in [n for n, _ in report._plots(no_map, np.zeros((100, 4, 5), np.uint8),
                                                                    radiance, tmp_path)]
    assert "rates.png" not in [n for n, _ in report._plots(result, np.zeros((100, 4, 5), np.uint8), "self", tmp_path)]


def test_report_sums_the_fit_frames_band_by_band(monkeypatch):
    from spikegen.fidelity import bands, report

    rng = np.random.default_rng(3)
    s = (rng.random((300, 24, 16)) < 0.5 * rng.random((24, 16))).astype(np.uint8)
    packed = np.packbits(s, axis=-1, bitorder="little")
    monkeypatch.setattr(bands, "BAND_BYTES", 200 * 16 * 8)  # bands of 8 rows: three of them
    assert bands.band_rows(200, 24, 16) == 8
    signal, histogram = report._fit_frame_sums(bands.Stream(s.shape, packed=packed), 200)
    assert np.array_equal(signal, s[:200].reshape(200, -1).sum(axis=1))  # the whole stream's, from packed bands
    v = stats.pixel_stats(s[:200]).isi_values
    assert histogram.sum() == (v <= report.ISI_MAX).sum() > 1000
    assert np.array_equal(histogram, np.bincount(v[v <= report.ISI_MAX].astype(int), minlength=report.ISI_MAX + 1))


# ---------------------------------------------------------------------- held-out choice, joint effects, unexplained
def _diagnose_sensor(effects, seed, radiance=None, intensity=96.0, frames=1000, extra=None):
    """Simulate ``effects`` (``{name: parameters}``) on the test radiance and diagnose it;
    ``extra(sensor, radiance)`` may return a changed (sensor, radiance) for effects the catalogue lacks."""
    from spikegen.sensor import simulate

    rng = np.random.default_rng(seed)
    x = synth.test_radiance(64, 64, rng) if radiance is None else radiance
    sensor = synth.make_sensor(effects, 64, 64, rng)
    sim_x = x
    if extra is not None:
        sensor, sim_x = extra(sensor, x, rng)
    spikes = simulate(sim_x, intensity, sensor, frames=frames, seed=seed + 1)
    return diagnose(spikes, x, intensity)


def test_dark_spread_is_not_named_gain():
    params = {"rate": 0.01, "spread": 0.5}
    result = _diagnose_sensor({"dark_current": params}, seed=11)
    assert result.detected == ["dark_current"], result.detected
    dark = result.effect("dark_current").parameters
    assert dark["rate"] == pytest.approx(0.01, rel=0.2)
    assert dark["spread"] == pytest.approx(0.5, rel=0.3)


def test_camera_like_combination_is_named_and_every_effect_pays():
    effects = {"dark_current": {"rate": 0.005, "spread": 0.5}, "hot_pixels": {"count": 12},
               "gain_nonuniformity": {"sigma": 0.05}, "shot_noise": {"electrons": 300.0}}
    result = _diagnose_sensor(effects, seed=12)
    assert set(result.detected) == set(effects), result.detected
    held = result.heldout
    assert held["higher_is_better"] and held["fitted"] > held["ideal"]
    for name in result.detected:  # each reported effect improves the held-out score
        assert held["effects"][name]["kept"] and held["effects"][name]["gain_nats"] > 0
    assert "threshold_jitter" not in result.detected  # shot noise accumulates: no jitter is read from it
    assert result.extended.threshold_jitter == 0
    # its temporal noise is the same in every row
    assert "interval_variance_per_row" not in [u["statistic"] for u in result.unexplained], result.unexplained


def _row_pattern(sensor, x, rng):
    rows = 1.0 + 0.06 * rng.standard_normal(64)
    return sensor.replace(responsivity=np.ones((64, 64)) * rows[:, None]), x


def _frame_flutter(sensor, x, rng):
    """Light that changes at random every 4 frames (not periodic): 250 sub-frames of 1000 frames."""
    steps = 1.0 + 0.15 * rng.standard_normal(250)
    return sensor, steps[:, None, None] * x[None]


def _row_band_flutter(sensor, x, rng):
    """Rows 40-47 only: light that changes at random every 2 frames (SD 5 %): a temporal noise of
    some rows, as the real car's background shows (docs/fidelity.md, "The car's background, row band
    by row band")."""
    steps = np.ones((500, 64, 64))
    steps[:, 40:48, :] += 0.05 * rng.standard_normal((500, 1, 1))
    return sensor, steps * x[None]


@pytest.mark.parametrize("extra,statistic", [pytest.param(_row_pattern, "rate_per_row", id="row_pattern"),
                                             pytest.param(_frame_flutter, "rate_per_frame", id="frame_flutter"),
                                             pytest.param(_row_band_flutter, "interval_variance_per_row",
                                                          id="row_band_flutter")])
def test_effect_outside_the_catalogue_is_unexplained_not_misnamed(extra, statistic):
    result = _diagnose_sensor({}, seed=13, extra=extra)
    assert result.detected == [], result.detected
    assert statistic in [u["statistic"] for u in result.unexplained], result.unexplained


def test_self_reference_on_a_moving_scene_judges_the_static_part():
    from spikegen.sensor import simulate

    yy, xx = np.mgrid[0:64, 0:64] / 63.0
    background = 0.1 + 0.8 * (0.5 + 0.5 * np.sin(2 * np.pi * (0.7 * xx + 0.4 * yy))) ** 2
    frames = np.repeat(background[None], 40, axis=0)
    for k in range(40):  # a bright bar crossing rows 20..35
        frames[k, 20:36, max(0, k * 2 - 8): k * 2] = 1.0
    spikes = simulate(frames, 64.0, None, frames=1000, seed=3)
    result = diagnose(spikes, "self", 64.0)
    moving = ~result.static
    assert result.info["moving_pixels"] + result.info["untested_pixels"] == int(moving.sum()) > 0
    assert moving[20:36].sum() == moving.sum()  # only the bar's rows move
    assert result.detected == [], result.detected
    assert result.effect("hot_pixels").note


def _car_like_scene(K=100, size=64):
    """``[K, size, size]``: a textured static background (upper half); over the lower half an
    object whose texture drifts 6 pixels right over the recording (slower than a segment of the
    motion test can show by its own counts) and a 'wheel' whose texture is drawn anew in every
    sub-frame (faster than its pixels' intervals): the two kinds of motion of the real car
    recording that were read as shot noise (docs/fidelity.md)."""
    rng = np.random.default_rng(21)
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    background = 0.15 + 0.6 * (0.5 + 0.5 * np.sin(2 * np.pi * (xx / 23 + yy / 37))) ** 2
    texture = rng.uniform(0.3, 1.0, size=(size, 3 * size))
    out = np.empty((K, size, size))
    for k in range(K):
        f = background.copy()
        shift = 6.0 * k / (K - 1)
        i0, a = int(np.floor(shift)), shift - np.floor(shift)
        obj = (1 - a) * np.roll(texture, i0, axis=1) + a * np.roll(texture, i0 + 1, axis=1)
        body = (yy > 34) & (xx > 8 + shift) & (xx < 56 + shift)
        f[body] = 0.5 * obj[:, :size][body] + 0.2
        wheel = (yy - 54) ** 2 + (xx - 20 - shift) ** 2 < 64
        f[wheel] = 0.05 + 0.25 * rng.uniform(size=int(wheel.sum()))
        out[k] = f
    return out


@pytest.mark.parametrize("electrons", [0.0, 500.0], ids=["ideal", "shot_noise"])
def test_self_reference_on_a_slowly_moving_scene_names_shot_noise_only_if_there(electrons):
    """A drifting object and a fast texture with ``self``: no shot noise from an ideal sensor (the
    version before the trend, step and interval-noise tests named N_e = 389), the true N_e within
    20 % with shot noise (it estimated 236 for 500)."""
    from spikegen.sensor import Sensor, simulate

    spikes = simulate(_car_like_scene(), 96.0, Sensor(name="s", electrons=electrons), frames=1000, seed=5)
    result = diagnose(spikes, "self", 96.0)
    assert result.info["moving_pixels"] > 0
    if electrons == 0:
        assert result.detected == [], result.detected
    else:
        assert result.detected == ["shot_noise"], result.detected
        assert result.effect("shot_noise").parameters["electrons"] == pytest.approx(electrons, rel=TOLERANCE)


def test_same_seed_same_verdicts():
    spikes, radiance, intensity, _ = synth.hidden_case(["gain_nonuniformity", "hot_pixels"], seed=6, frames=600)
    a, b = (json.dumps(diagnose(spikes, radiance, intensity).as_json(), sort_keys=True) for _ in range(2))
    assert a == b


def test_same_input_same_json_bytes_across_processes_and_blas_threads(tmp_path):
    """`spikegen diagnose --json` run twice on the same files, in separate processes with 1 and 2
    BLAS/OpenMP threads and different hash seeds, writes the same bytes. (Before the diagnosis
    summed with spikegen.fidelity.exact, OpenBLAS rounded the long reductions of the rate fit
    differently under 1 and 2 threads: this case's fitted flicker depth differed in its last bits.)"""
    import os
    import subprocess
    import sys

    spikes, radiance, intensity, _ = synth.hidden_case(["flicker", "reset_to_zero"], seed=30)
    write_spikes(tmp_path / "m.npz", spikes)
    np.save(tmp_path / "ref.npy", radiance)
    code = "import sys; from spikegen.cli import main; sys.exit(main(sys.argv[1:]))"
    runs = []
    for threads, hash_seed in (("1", "0"), ("2", "1")):
        env = {**os.environ, "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads, "MKL_NUM_THREADS": threads,
               "PYTHONHASHSEED": hash_seed}
        out = tmp_path / f"d{threads}.json"
        runs.append((subprocess.Popen([sys.executable, "-c", code, "diagnose", str(tmp_path / "m.npz"), "--reference",
                                       str(tmp_path / "ref.npy"), "--intensity", repr(intensity), "--json", str(out)],
                                      env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE), out))
    for proc, _ in runs:
        assert proc.wait(timeout=600) == 0, proc.stderr.read().decode()
    a, b = (out.read_bytes() for _, out in runs)
    assert json.loads(a)["detected"] and a == b


def test_exact_linear_algebra_agrees_with_blas():
    from spikegen.fidelity import exact

    rng = np.random.default_rng(0)
    A, b = rng.standard_normal((5000, 4)), rng.standard_normal(5000)
    assert np.allclose(exact.gram(A), A.T @ A) and np.allclose(exact.rmatvec(A, b), A.T @ b)
    assert np.allclose(exact.matvec(A, b[:4]), A @ b[:4]) and exact.dot(b, b) == pytest.approx(float(b @ b))
    assert np.allclose(exact.lstsq(A, b), np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-10)
    twin = np.stack([A[:, 0], 2 * A[:, 0], A[:, 1]], axis=1)  # rank 2: same fitted values as LAPACK's
    assert np.allclose(exact.matvec(twin, exact.lstsq(twin, b)), twin @ np.linalg.lstsq(twin, b, rcond=None)[0])
    w = np.zeros((6, 3))
    w[:, 0], w[:, 1] = np.linspace(1, 0, 6), np.linspace(0, 1, 6)
    X = rng.random((3, 7))
    assert np.allclose(exact.interpolate(w, X), w @ X)


def test_exact_sums_are_numpys_reductions_bit_for_bit():
    """exact.gram / matvec / normal_equations / matvec_columns add in NumPy's order: the same bits
    as the plain reductions they replace."""
    from spikegen.fidelity import exact

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 9, 4097, 20011):
        for p in range(1, 10):
            A = rng.standard_normal((n, p)) * rng.lognormal(0.0, 3.0, (n, 1))
            b, x = rng.standard_normal(n), rng.standard_normal(p)
            assert np.array_equal(exact.gram(A), (A[:, :, None] * A[:, None, :]).sum(axis=0)), (n, p)
            assert np.array_equal(exact.rmatvec(A, b), (A * b[:, None]).sum(axis=0)), (n, p)
            assert np.array_equal(exact.matvec(A, x), (A * x[None, :]).sum(axis=1)), (n, p)
            if 2 <= p <= 7:
                cols = [A[:, j].copy() for j in range(p)]
                M, v = exact.normal_equations(cols, b)
                assert np.array_equal(M, (A[:, :, None] * A[:, None, :]).sum(axis=0)), (n, p)
                assert np.array_equal(v, (A * b[:, None]).sum(axis=0)), (n, p)
                assert np.array_equal(exact.matvec_columns(cols, x), (A * x[None, :]).sum(axis=1)), (n, p)


def test_spike_times_and_interval_moments_are_those_of_the_intervals():
    """stats.spike_times against a plain transpose and division; stats.interval_moments (sums of
    whole numbers from first and last spikes), interval_moments_by_frame and interval_variances
    bit for bit against pixel_stats (grouped_var of every interval), with pixels of no, one, two
    and many spikes."""
    rng = np.random.default_rng(5)
    for T, H, W, p in [(1, 2, 2, 0.5), (7, 1, 1, 0.0), (50, 3, 4, 0.05), (200, 5, 7, 0.3), (3000, 8, 40, 0.2),
                       (64, 3, 3, 0.02), (130, 4, 4, 0.004)]:  # first spikes after the last whole window of 64
        s = (rng.random((T, H, W)) < p * 2 * rng.random((1, H, W))).astype(np.uint8)
        s[:, 0, 0] = 0
        s[T // 2:, -1, -1] = 1
        idx = np.flatnonzero(s.reshape(T, -1).T)
        pix, t = stats.spike_times(s)
        assert np.array_equal(pix, idx // T) and np.array_equal(t, idx % T) and pix.dtype == t.dtype == np.int64
        ps = stats.pixel_stats(s)
        for got, want in zip(stats.interval_moments(s), (ps.isi_mean, ps.isi_var, ps.n_isi)):
            assert np.array_equal(got, want, equal_nan=True), (T, H, W)
        for got, want in zip(stats.interval_moments_by_frame(s), (ps.isi_mean, ps.isi_var, ps.n_isi)):
            assert np.array_equal(got, want, equal_nan=True), (T, H, W)
        n, first = stats.counts_and_first_spikes(s.reshape(T, -1))
        assert np.array_equal(n, ps.n) and np.array_equal(first[n > 0], ps.first[n > 0]), (T, H, W)
        # with frames as the clock pixel_stats sums whole numbers over pixel ranges (stats.frame_stats):
        # the same bits as on a clock that counts the frames (the general path, grouped_var)
        general = stats.pixel_stats(s, clock=np.arange(T, dtype=np.float64))
        for got in (ps, stats.pixel_stats(s, times=stats.spike_times(s))):
            for name in ("n", "first", "last", "rate", "isi_mean", "isi_var", "span_var", "isi_min", "single", "ones",
                         "n_isi", "isi_values", "diff_var"):
                a, b = getattr(got, name), getattr(general, name)
                assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), (name, T, H, W)
        iv = stats.interval_variances(s)
        for name in ("n", "first", "last", "rate", "isi_mean", "isi_var", "span_var", "n_isi", "diff_var"):
            got, want = getattr(iv, name), getattr(ps, name)
            assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True), (name, T, H, W)


def test_fit_window_stats_are_the_separate_reads():
    """bands.fit_window_stats (one read; the halves' rates from the spike times) gives the numbers
    of bands.pixel_stats and bands.window_rate of the two halves."""
    from spikegen.fidelity import bands

    rng = np.random.default_rng(6)
    for T, H, W, p, Tf in [(60, 16, 8, 0.3, 48), (501, 16, 16, 0.05, 401), (200, 24, 8, 0.0, 160)]:
        s = (rng.random((T, H, W)) < p * 2 * rng.random((1, H, W))).astype(np.uint8)
        s[: Tf // 2, 0, :3] = 0  # pixels with no spike in the first half
        s[Tf // 2:, 1, :3] = 0  # ... in the second
        s[Tf // 2 - 1, 2, 0] = s[Tf // 2, 2, 1] = 1
        stream = bands.Stream.of(s)
        got, halves = bands.fit_window_stats(stream, 8, Tf)
        want = bands.pixel_stats(stream, 8, 0, Tf)
        for name in ("n", "first", "last", "rate", "isi_mean", "isi_var", "span_var", "isi_min", "single", "ones",
                     "n_isi", "diff_var"):
            assert np.array_equal(getattr(got, name), getattr(want, name), equal_nan=True), name
        assert np.array_equal(halves[0], bands.window_rate(stream, 8, 0, Tf // 2))
        assert np.array_equal(halves[1], bands.window_rate(stream, 8, Tf // 2, Tf))


def test_masked_frame_sums_are_the_plain_sums():
    """bands.masked_frame_sums (a float32 matrix product) gives the whole-number sums of the masked
    pixels of each frame, in blocks of frames and with every pixel firing."""
    from spikegen.fidelity import bands

    rng = np.random.default_rng(7)
    for T, P, p in [(1, 5, 0.5), (3000, 700, 0.2), (50, 9000, 1.0)]:
        flat = (rng.random((T, P)) < p).astype(np.uint8)
        masks = [rng.random(P) < 0.3, np.zeros(P, dtype=bool), np.ones(P, dtype=bool)]
        got = bands.masked_frame_sums(flat, masks)
        want = np.stack([flat[:, m].sum(axis=1, dtype=np.int64) for m in masks], axis=1)
        assert got.dtype == np.int64 and np.array_equal(got, want), (T, P)


def test_count_variance_of_whole_counts_is_that_of_their_floats():
    """heldout.count_variance takes its window counts as int32 (no float64 copy): the same bits as
    the variance of the float64 counts, in each of its three branches."""
    from spikegen.fidelity import heldout

    rng = np.random.default_rng(9)
    sim = (rng.random((1200, 6, 7)) < 0.3 * rng.random((1, 6, 7))).astype(np.uint8)
    T = sim.shape[0]
    mod = heldout.Modulation(1.0 + 0.2 * np.sin(np.arange(T) / 9.0), rng.random(42))
    for w in (4, 16, 64, 400):
        wv = min(w, max(T // 12, 1))
        c = heldout.window_counts(sim, wv)
        rate = sim.reshape(T, -1).sum(axis=0, dtype=np.int64) / T
        want = {(True, None): c.var(axis=0, ddof=1), (False, None): np.diff(c, axis=0).var(axis=0, ddof=1) / 2.0,
                (True, mod): ((c - wv * rate[None, :] * mod.window_factor(wv, 0, c.shape[0])) ** 2).sum(axis=0)
                / (c.shape[0] - 1)}
        for (static, m), v in want.items():
            got = heldout.count_variance(sim, w, static, m)
            assert np.array_equal(got, np.maximum(v * (w / wv), heldout.VAR_FLOOR)), (w, static, m is None)


def test_sliding_local_median_is_the_median_of_each_window():
    """stats._local_median (a sorted sliding window) against np.median of each frequency's window,
    with ties and with windows that jump past each other."""
    rng = np.random.default_rng(10)
    for T in (50, 999, 4000):
        freqs = (1 + np.arange(int(4 * T / 6))) / (4 * T)
        for values in (rng.random(freqs.size) ** 3 * 1e4, np.round(rng.random(freqs.size) * 5)):
            for rel, absolute in ((0.25, 10.0 / T), (0.01, 0.5 / T)):
                want = [np.median(values[np.searchsorted(freqs, f - max(rel * f, absolute)):
                                         np.searchsorted(freqs, f + max(rel * f, absolute))]) for f in freqs]
                assert np.array_equal(stats._local_median(values, freqs, rel, absolute), want), (T, rel)


def test_simulation_memo_gives_the_recomputed_diagnosis(monkeypatch):
    """A model simulated twice is simulated once (bands.simulation_pass, ctx.passes): the same JSON
    as a diagnosis that simulates every pass anew, with fewer simulations."""
    import itertools

    from spikegen.fidelity import bands

    spikes, radiance, intensity, _ = synth.hidden_case(["gain_nonuniformity", "shot_noise"], seed=8, frames=600)
    calls = []
    simulate_rows = bands.simulate_rows
    monkeypatch.setattr(bands, "simulate_rows", lambda *a, **k: calls.append(1) or simulate_rows(*a, **k))
    memo = diagnose(spikes, radiance, intensity)
    with_memo = len(calls)
    fresh_keys = itertools.count()
    monkeypatch.setattr(bands, "simulation_key", lambda sensor, shape: next(fresh_keys))
    calls.clear()
    fresh = diagnose(spikes, radiance, intensity)
    assert memo.detected == fresh.detected and "shot_noise" in memo.detected
    assert json.dumps(memo.as_json(), sort_keys=True) == json.dumps(fresh.as_json(), sort_keys=True)
    assert with_memo <= len(calls) - 2, (with_memo, len(calls))  # the shot-noise model's and the kept model's


def test_equivalent_interval_under_flicker():
    """The mean interval of a flickering rate, mapped back to the steady rate's interval."""
    from spikegen.fidelity.records import equivalent_isi, flicker_mean_isi, flicker_rate_table, interval_frames

    t = np.arange(800)
    phi = 1.0 + 0.4 * np.sin(2 * np.pi * t / 97.0)
    phi /= phi.mean()
    lam = np.array([0.01, 0.05, 0.2, 0.5])
    for delta in (0.0, 0.5, 2.0):
        measured = 1.0 / (1.0 / interval_frames(lam[:, None] * phi[None, :], delta)).mean(axis=1)
        table = flicker_rate_table(delta, phi)
        assert np.allclose(flicker_mean_isi(lam, delta, table), measured, rtol=1e-4)
        assert np.allclose(equivalent_isi(measured, delta, table), interval_frames(lam, delta), rtol=1e-4)
        if delta > 0:  # the flickering mean interval is longer than the steady one
            assert np.all(measured[1:] > interval_frames(lam[1:], delta) * 1.001)
    saturated = np.array([delta + 0.5])  # shorter than any mean interval the readout can give
    assert equivalent_isi(saturated, delta, table)[0] == saturated[0]
    assert equivalent_isi(measured, 0.5, None) is measured


def test_shared_variance_is_in_every_quadrant_or_none():
    """stats.shared_variance: pixels that fire independently share nothing; light that changes
    for all pixels is shared; the same change over one quadrant only is not (a moving object)."""
    from spikegen.fidelity.stats import shared_variance
    from spikegen.sensor import simulate

    rng = np.random.default_rng(21)
    x = synth.test_radiance(64, 64, rng)
    steps = 1.0 + 0.1 * rng.standard_normal(100)
    mask = np.ones(64 * 64, dtype=bool)
    quadrant = (np.arange(64)[:, None] < 32) & (np.arange(64)[None, :] < 32)
    results = {}
    for name, frames in (("none", x[None]), ("all", steps[:, None, None] * x[None]),
                         ("one quadrant", np.where(quadrant, steps[:, None, None] * x[None], x[None]))):
        spikes = simulate(frames, 128.0, synth.make_sensor({"shot_noise": {"electrons": 300.0}}, 64, 64, rng),
                          frames=400, seed=5)
        v, se = shared_variance(spikes, mask)
        results[name] = v / se
    assert abs(results["none"]) < 5 and results["all"] > 5 and results["one quadrant"] < 5, results


# ---------------------------------------------------------------------- bands of rows
BAND_CASES = [(["flicker", "shot_noise"], 4, "ref"), (["gain_nonuniformity", "hot_pixels", "dark_current"], 6, "ref"),
              (["crosstalk", "reset_to_zero"], 30, "ref"), (["shot_noise", "hot_pixels"], 2, "self"),
              (["flicker", "shot_noise"], 4, "self")]


@pytest.mark.parametrize("names,seed,reference", BAND_CASES)
def test_diagnosis_in_bands_of_8_rows_is_the_diagnosis_in_one_band(names, seed, reference, monkeypatch):
    """The measured stream read, and every model simulated and scored, in bands of 8 rows (the
    simulator's noise blocks; bands.py) gives the same JSON, to the last bit, as in one band of
    all 64 rows: from the dense stream with the models simulated whole, and from the packed
    stream with them simulated a band at a time."""
    from spikegen.fidelity import bands

    spikes, radiance, intensity, _ = synth.hidden_case(names, seed, frames=600)
    radiance = "self" if reference == "self" else radiance
    whole = json.dumps(diagnose(spikes, radiance, intensity, band_rows=64).as_json(), sort_keys=True)
    assert json.dumps(diagnose(spikes, radiance, intensity, band_rows=8).as_json(), sort_keys=True) == whole
    monkeypatch.setattr(bands, "SIM_BYTES", 1)  # blocks of one band
    packed = bands.Stream(spikes.shape, packed=np.packbits(spikes, axis=-1, bitorder="little"))
    assert json.dumps(diagnose(packed, radiance, intensity, band_rows=8).as_json(), sort_keys=True) == whole


def test_band_statistics_are_those_of_the_whole_stream():
    """bands.pixel_stats and bands.fit_window_pass (on the population clock too), band by band,
    against stats.pixel_stats of the whole stream and of the model's whole simulation."""
    from dataclasses import fields

    from spikegen.fidelity import bands, stats
    from spikegen.fidelity.diagnose import _context
    from spikegen.fidelity.records import SIM_SEED
    from spikegen.sensor import Sensor, simulate

    spikes, radiance, intensity, _ = synth.hidden_case(["flicker", "shot_noise"], 4, frames=600)
    T, H, W = spikes.shape
    ctx = _context(bands.Stream.of(spikes), radiance, intensity, Sensor(name="ideal").sized(H, W), 480, 8)
    mask = ctx.meas.rate < 0.9
    sensor = Sensor(name="shot", electrons=300.0).sized(H, W)
    sim = simulate(ctx.X, intensity, sensor, frames=T, seed=SIM_SEED)[:480]
    clock = stats.population_clock(spikes[:480], mask)
    pairs = [(bands.pixel_stats(ctx.spikes, 8, 0, 480, clock), stats.pixel_stats(spikes[:480], clock)),
             (bands.fit_window_pass(ctx, sensor, 8)["stats"], stats.pixel_stats(sim)),
             (bands.fit_window_pass(ctx, sensor, 8, clock_mask=mask)["stats"],
              stats.pixel_stats(sim, stats.population_clock(sim, mask)))]
    for banded, whole in pairs:
        for f in fields(stats.PixelStats):
            if f.name != "isi_values":  # not kept in bands (as many as the spikes)
                np.testing.assert_array_equal(getattr(banded, f.name), getattr(whole, f.name), err_msg=f.name)
    np.testing.assert_array_equal(bands.population_signal(ctx.spikes, mask, 8, 0, 480),
                                  stats.population_signal(spikes[:480], mask))
    quads = bands.fit_window_pass(ctx, sensor, 8, mask=mask)["quadrants"]
    assert stats.shared_variance_of(quads) == stats.shared_variance(sim, mask)
    # the motion test, on the flicker's population clock
    from spikegen.fidelity import heldout

    assert heldout.shared_clock(spikes, heldout.segment_counts_ok(spikes))[0] is not None
    for banded, whole in zip(bands.motion_test(ctx.spikes, 8), heldout.motion_test(spikes)):
        np.testing.assert_array_equal(banded, whole)


@pytest.mark.parametrize("effects", [{"shot_noise": {"electrons": 300.0}}, {"crosstalk": {"fraction": 0.1}}])
def test_simulated_rows_are_those_rows_of_the_whole_simulation(effects):
    from spikegen.sensor import simulate

    rng = np.random.default_rng(1)
    x = synth.test_radiance(40, 24, rng)
    sensor = synth.make_sensor(effects, 40, 24, rng)
    whole = simulate(x, 96.0, sensor, frames=200, seed=5)
    for r0, r1 in ((0, 8), (8, 16), (16, 40), (8, 40)):
        for threads in (1, 2, 3):  # rows asked for are split over the threads (one chunk a thread)
            np.testing.assert_array_equal(simulate(x, 96.0, sensor, frames=200, seed=5, rows=(r0, r1), threads=threads),
                                          whole[:, r0:r1])


def test_packed_reading_is_the_unpacked_stream(tmp_path):
    from spikegen.fidelity.bands import Stream
    from spikegen.spikeio import read_spikes, read_spikes_packed

    spikes = (np.random.default_rng(3).random((30, 12, 16)) < 0.3).astype(np.uint8)
    for name in ("m.npz", "m.dat"):
        write_spikes(tmp_path / name, spikes)
        packed, shape = read_spikes_packed(tmp_path / name, (16, 12))
        stream = Stream(shape, packed=packed)
        np.testing.assert_array_equal(stream.dense(), read_spikes(tmp_path / name, (16, 12)))
        np.testing.assert_array_equal(stream.rows(4, 9, 3, 20), spikes[3:20, 4:9])
    write_spikes(tmp_path / "odd.dat", spikes[:, :, :12])  # 12 x 12: rows are not whole bytes
    assert read_spikes_packed(tmp_path / "odd.dat", (12, 12)) is None
