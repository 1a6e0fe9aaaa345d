"""Presets and sensor files: the measured BIT camera, drawn at any size with its statistics."""
import json

import numpy as np
import pytest

from spikegen.errors import InputError
from spikegen.fpn import fit_map_model
from spikegen.presets import bit_camera, get_sensor
from spikegen.sensor import Sensor, simulate
from spikegen.sensorfile import load_sensor, save_sensor


def test_paper_at_camera_size_is_the_measured_map(shared_data):
    with np.load(shared_data / "real" / "bit_camera_calibration_250x400.npz") as z:
        nl = z["Nl"]
    s = get_sensor("paper", 250, 400)
    R, d = s.maps(250, 400)
    assert np.median(R) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(R, nl / np.median(nl), rtol=1e-5)
    # Nl is relative to pixel (0, 0); that pixel responds 1/0.645 of the median
    assert R[0, 0] == pytest.approx(1 / 0.645, rel=0.01)
    assert np.median(d) == pytest.approx(7.66 * s.lux_to_rate, rel=0.01)


@pytest.mark.parametrize("hw", [(400, 400), (128, 96)])
def test_drawn_maps_have_the_measured_statistics(hw):
    model, R0, d0 = bit_camera()
    s = get_sensor("paper", *hw, seed=3)
    R, d = s.maps(*hw)
    assert R.shape == hw and np.median(R) == pytest.approx(1.0, abs=1e-6)
    fit = fit_map_model(R, d / s.lux_to_rate)
    assert fit["pixel_sigma_robust"] == pytest.approx(model["pixel_sigma_robust"], rel=0.1)
    assert fit["column_sigma"] == pytest.approx(model["column_sigma"], rel=0.35 if hw[1] < 200 else 0.2)
    assert fit["dark_median_lux"] == pytest.approx(model["dark_median_lux"], rel=0.05)
    assert fit["dark_pixel_rho"] == pytest.approx(model["dark_pixel_rho"], abs=0.08)
    # a per-pixel pattern stays per-pixel: neighbours are not smoothed copies of each other
    step = np.diff(np.log(R), axis=1)  # white per-pixel noise: std of differences = sqrt(2) sigma
    assert np.median(np.abs(step)) * 1.4826 > 1.2 * model["pixel_sigma_robust"]
    if hw == (400, 400):  # 27 hot pixels in 100 000 measured -> about 43 in 160 000
        assert 25 <= (d > 60 * s.lux_to_rate).sum() <= 65


def test_drawn_maps_are_seeded_by_camera():
    a = get_sensor("paper", 64, 64, seed=1).maps(64, 64)[0]
    b = get_sensor("paper", 64, 64, seed=1).maps(64, 64)[0]
    c = get_sensor("paper", 64, 64, seed=2).maps(64, 64)[0]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_paper_preset_keeps_brightness():
    """Median-1 normalisation: a white scene through `paper` gives about I spikes, not I/1.55."""
    counts = simulate(np.ones((64, 64)), 32, get_sensor("paper", 64, 64), seed=0).sum(0)
    assert abs(np.median(counts) - 32) <= 1


def test_rsir_preset_and_unknown():
    assert get_sensor("rsir", 32, 32).kind == "rsir"
    assert get_sensor("ideal", 32, 32).responsivity is None
    with pytest.raises(InputError, match="unknown sensor 'fancy'"):
        get_sensor("fancy", 32, 32)


def test_sensor_file_round_trip(tmp_path):
    s = get_sensor("paper", 40, 56, seed=4).replace(electrons=900.0, refractory_frames=1)
    j, n = save_sensor(s, tmp_path / "cam")
    assert j.name == "cam.json" and n.name == "cam.npz"
    t = load_sensor(j)
    np.testing.assert_array_equal(t.responsivity, s.responsivity)
    np.testing.assert_array_equal(t.dark_rate, s.dark_rate)
    assert t.parameters() == s.parameters()
    via_cli = get_sensor(str(j), 40, 56)
    np.testing.assert_array_equal(via_cli.responsivity, s.responsivity)
    other_size = get_sensor(str(j), 24, 32, seed=4)  # has a map model: drawn, not resized
    assert other_size.responsivity.shape == (24, 32)
    ideal_j, ideal_n = save_sensor(Sensor(), tmp_path / "plain")
    assert ideal_n is None and json.loads(ideal_j.read_text())["maps"] is None


def test_bad_sensor_file(tmp_path):
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(InputError, match="x.json"):
        load_sensor(tmp_path / "x.json")
    (tmp_path / "y.json").write_text('{"format": "other"}')
    with pytest.raises(InputError, match="not a spikegen sensor"):
        get_sensor(str(tmp_path / "y.json"), 8, 8)
