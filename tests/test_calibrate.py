"""`spikegen calibrate` (Eqs. S2-S6) on recordings the simulator makes from known maps."""
from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from spikegen.cli import cli, main
from spikegen.fidelity.calibrate import calibrate, dark_equivalent_lux, reference_pixel
from spikegen.sensor import Sensor, simulate
from spikegen.spikeio import write_spikes

H, W = 24, 40  # not square: a transposed map would fail
LUX_TO_RATE = 5e-4  # spikes per frame per lux at nominal response
FLATS = (153.0, 335.0)


def _camera(rng):
    """Known maps: R with vignetting and per-pixel spread (arbitrary scale), L_d in lux."""
    yy, xx = np.mgrid[0:H, 0:W]
    vignette = 1.0 - 0.15 * (((xx - W / 2) / W) ** 2 + ((yy - H / 2) / H) ** 2)
    resp = 0.8 * vignette * np.exp(0.04 * rng.standard_normal((H, W)))
    dark_lux = rng.uniform(4.0, 12.0, size=(H, W))
    dark_lux[3, 5] = 80.0  # a hot pixel
    return resp, dark_lux


def _record(resp, dark_lux, lux, frames, seed, electrons=0.0):
    """A recording at ``lux`` (0 = lens covered): lambda = R k (L + L_d), as X = 1, I = 256 k L."""
    sensor = Sensor(responsivity=resp, dark_rate=LUX_TO_RATE * dark_lux, electrons=electrons)
    if lux == 0:
        return simulate(np.zeros((H, W)), 1.0, sensor, frames=frames, seed=seed)
    return simulate(np.ones((H, W)), 256.0 * LUX_TO_RATE * lux, sensor, frames=frames, seed=seed)


@pytest.fixture(scope="module")
def recordings():
    rng = np.random.default_rng(7)
    resp, dark_lux = _camera(rng)
    dark = _record(resp, dark_lux, 0, 30000, 1)
    flats = {lux: _record(resp, dark_lux, lux, 3000, 2 + i) for i, lux in enumerate(FLATS)}
    return resp, dark_lux, dark, flats


def test_recovers_known_maps(recordings):
    resp, dark_lux, dark, flats = recordings
    cal = calibrate(dark, flats)
    truth = resp / np.median(resp)
    assert np.median(cal.responsivity) == pytest.approx(1.0, abs=1e-9)
    assert np.max(np.abs(cal.responsivity / truth - 1)) < 0.01
    # lux_to_rate: the median pixel's spikes per frame per lux
    assert cal.lux_to_rate == pytest.approx(LUX_TO_RATE * np.median(resp), rel=0.01)
    # dark current: 30000 dark frames give ~ 60..200 spikes a pixel: a few % per pixel
    rel = cal.dark_lux / dark_lux - 1
    assert np.median(np.abs(rel)) < 0.05
    assert cal.dark_lux[3, 5] == pytest.approx(80.0, rel=0.05)
    assert np.allclose(cal.dark_rate, cal.dark_lux * cal.lux_to_rate)


def test_reference_pixel_is_closest_to_average_response(recordings):
    _, _, dark, flats = recordings
    cal = calibrate(dark, flats)
    raw = cal.responsivity * cal.lux_to_rate  # proportional to the un-normalised response
    m = cal.reference_pixel
    assert np.argmin(np.abs(raw - raw.mean())) == np.ravel_multi_index(m, raw.shape)
    assert cal.reference_vs_median == pytest.approx(raw[m] / np.median(raw), rel=1e-9)


def test_with_shot_noise_is_still_unbiased():
    rng = np.random.default_rng(11)
    resp, dark_lux = _camera(rng)
    dark = _record(resp, dark_lux, 0, 12000, 1, electrons=200)
    flats = {lux: _record(resp, dark_lux, lux, 3000, 2 + i, electrons=200) for i, lux in enumerate(FLATS)}
    cal = calibrate(dark, flats)
    err = cal.responsivity / (resp / np.median(resp)) - 1
    assert abs(np.mean(err)) < 0.005 and np.std(err) < 0.03
    assert np.median(cal.dark_lux / dark_lux) == pytest.approx(1.0, abs=0.1)


def test_eq_s3_in_rates():
    # T_d = 400, T_1 = 10 frames at L_1 = 100 lux: L_d = 100 * 10 / (400 - 10)
    assert dark_equivalent_lux(np.array([1 / 400]), np.array([1 / 10]), 100.0)[0] == pytest.approx(1000 / 390)
    assert dark_equivalent_lux(np.array([0.0]), np.array([0.1]), 100.0)[0] == 0.0  # never fired in the dark
    assert reference_pixel(np.array([[1.0, 2.0], [3.0, 10.0]])) == (1, 0)  # mean 4: closest is 3


def test_cli_writes_a_sensor_that_convert_can_use(recordings, tmp_path):
    from spikegen.presets import get_sensor

    resp, dark_lux, dark, flats = recordings
    write_spikes(tmp_path / "dark.npz", dark)
    for lux, s in flats.items():
        write_spikes(tmp_path / f"flat{int(lux)}.dat", s)
    args = ["calibrate", "--dark", str(tmp_path / "dark.npz"), "--size", f"{W}x{H}", "--out", str(tmp_path / "cam")]
    for lux in FLATS:
        args += ["--flat", f"{lux:g}={tmp_path / f'flat{int(lux)}.dat'}"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    sensor = get_sensor(str(tmp_path / "cam.json"), H, W)
    cal = calibrate(dark, flats)
    assert np.allclose(sensor.responsivity, cal.responsivity, atol=1e-6)
    assert np.allclose(sensor.dark_rate, cal.dark_rate, atol=1e-7)
    assert sensor.lux_to_rate == pytest.approx(cal.lux_to_rate)


@pytest.mark.parametrize("flat", ["153", "abc=x.npy", "=x.npy"])
def test_cli_bad_flat_is_one_line(tmp_path, capsys, flat):
    np.save(tmp_path / "d.npy", np.zeros((10, 4, 4), dtype=np.uint8))
    code = main(["calibrate", "--dark", str(tmp_path / "d.npy"), "--flat", flat,
                 "--flat", f"2={tmp_path / 'd.npy'}", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert "LUX=FILE" in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.glob("o.*"))


def test_saturated_flat_is_refused(tmp_path):
    dark = np.zeros((50, 4, 4), dtype=np.uint8)
    ones = np.ones((50, 4, 4), dtype=np.uint8)
    half = np.zeros((50, 4, 4), dtype=np.uint8)
    half[::2] = 1
    with pytest.raises(Exception, match="saturated"):
        calibrate(dark, {1.0: half, 2.0: ones})
