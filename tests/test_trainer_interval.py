"""``spikelik`` reads each window's count from its first and last spike times on an integrate-and-fire
sensor with subtractive reset (targets.interval_statistic); ``spikelik-count`` reads the counts alone."""
import json

import numpy as np
import pytest

from spikegen.sensor import Sensor, simulate

from spikenerf.data import SensorMaps, load_dataset
from spikenerf.methods import METHODS
from spikenerf.targets import build_targets, count_statistic, interval_statistic

torch = pytest.importorskip("torch")

from spikenerf.train import train  # noqa: E402
from test_trainer_cli import _cfg, dataset, sphere_dataset  # noqa: E402,F401  (the sphere dataset fixture)

FRAMES = 256


def _stream(sensor: Sensor, intensity: float, seed: int = 1):
    x = np.random.default_rng(0).uniform(0.05, 1.0, (64, 64))
    return simulate(x, intensity, sensor, frames=FRAMES, seed=seed), FRAMES * intensity / 256 * x


@pytest.mark.parametrize("sensor, most", [(Sensor(), 0.25), (Sensor(electrons=22544, threshold_jitter=0.0036), 0.3)])
def test_the_spike_times_pin_the_rate_closer_than_the_count(sensor, most):
    spikes, expected = _stream(sensor, 32)
    count = spikes.sum(axis=0).astype(np.float64)
    value = interval_statistic(spikes, sensor.electrons, sensor.threshold_jitter)
    err_count = np.sqrt(np.mean((count - expected) ** 2))
    err_value = np.sqrt(np.mean((value - expected) ** 2))
    assert 0.3 < err_count < 0.5  # the residual's sqrt(1/6), plus the noise
    assert err_value < most * err_count, (err_value, err_count)
    assert abs(np.mean(value - expected)) < 0.02  # no bias


def test_the_count_is_kept_where_the_times_cannot_do_better():
    spikes, _ = _stream(Sensor(), 4)  # at most 4 spikes: many pixels fire once or not at all
    count = spikes.sum(axis=0)
    value = interval_statistic(spikes)
    assert np.array_equal(value[count < 2], count[count < 2]) and (count < 2).any()
    always = np.ones((FRAMES, 2, 2), np.uint8)  # a saturated pixel: one spike every frame
    assert np.array_equal(interval_statistic(always), np.full((2, 2), float(FRAMES)))



@pytest.mark.parametrize("electrons", [0.5, 4.0])
def test_with_strong_shot_noise_it_is_no_worse_than_the_count(electrons):
    """Shot noise moves the end spikes too: where it does more than the count's residual, the count is
    kept (most pixels at N_e = 0.5), and the value's error is never above the count's."""
    spikes, expected = _stream(Sensor(electrons=electrons), 32)
    count = spikes.sum(axis=0).astype(np.float64)
    value = interval_statistic(spikes, electrons)
    assert np.sqrt(np.mean((value - expected) ** 2)) <= 1.001 * np.sqrt(np.mean((count - expected) ** 2))
    if electrons < 1:
        assert np.mean(value == count) > 0.9


def test_which_sensors_and_methods_read_spike_times():
    maps = np.ones((2, 2), np.float32)
    assert count_statistic(METHODS["spikelik"], SensorMaps(maps, maps)) == "interval"
    assert count_statistic(METHODS["spikelik"], SensorMaps(maps, maps, electrons=2e4, threshold_jitter=0.01)) == "interval"
    assert count_statistic(METHODS["spikelik"], SensorMaps(maps, maps, kind="rsir")) == "count"
    assert count_statistic(METHODS["spikelik"], SensorMaps(maps, maps, reset="zero")) == "count"
    for name in ("spikelik-count", "spikenerf", "spikenerf-noR", "tfp32", "spikenerf-paper", "oracle"):
        assert count_statistic(METHODS[name], SensorMaps(maps, maps)) == "count", name


def test_spikelik_targets_on_an_integrate_and_fire_sensor(dataset):
    ds = load_dataset(dataset)  # the `paper` sensor: integrate-and-fire, subtractive reset
    times = build_targets(ds, METHODS["spikelik"], ds.height, ds.width, progress=False)
    counts = build_targets(ds, METHODS["spikelik-count"], ds.height, ds.width, progress=False)
    assert (times.statistic, counts.statistic) == ("interval", "count")
    assert np.array_equal(counts.values, np.round(counts.values))  # whole counts
    moved = times.values != counts.values
    assert moved.mean() > 0.5  # most pixels fire at least twice at i64
    assert np.abs(times.values - counts.values).max() <= 1.0  # within the count's own bounds
    assert np.array_equal(times.poses, counts.poses) and np.array_equal(times.frames, counts.frames)


def test_on_rsir_data_spikelik_reads_the_counts(tmp_path_factory):
    ds = load_dataset(sphere_dataset(tmp_path_factory, "rsir"))
    times = build_targets(ds, METHODS["spikelik"], ds.height, ds.width, progress=False)
    counts = build_targets(ds, METHODS["spikelik-count"], ds.height, ds.width, progress=False)
    assert times.statistic == "count" and np.array_equal(times.values, counts.values)


def test_the_statistic_is_recorded_and_guards_resume(dataset, tmp_path):
    run = tmp_path / "run"
    train(_cfg(dataset, iters=4), run, progress=False, log=lambda m: None)
    assert json.loads((run / "config.json").read_text())["statistic"] == "interval"
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["config"]["statistic"] == "interval"
    del ck["config"]["statistic"]  # a checkpoint of spikelik from before the key: it read the counts
    torch.save(ck, run / "checkpoint.pt")
    from spikegen.errors import InputError
    with pytest.raises(InputError, match="statistic='count'"):
        train(_cfg(dataset, iters=8), run, progress=False, log=lambda m: None)


def test_bench_interval_reports_both_targets_and_refuses_rsir(dataset, tmp_path_factory):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "bench" / "bench_interval.py"
    res = subprocess.run([sys.executable, str(script), str(dataset), "--views", "2"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    gain = float(res.stdout.strip().splitlines()[-1].split(":")[1].split()[0])
    assert gain > 0  # the sphere at i64: the spike times' images are closer to the truth
    rsir = sphere_dataset(tmp_path_factory, "rsir")
    res = subprocess.run([sys.executable, str(script), str(rsir)], capture_output=True, text=True)
    assert res.returncode == 1 and "rsir" in res.stderr and "Traceback" not in res.stderr
