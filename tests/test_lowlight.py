"""spikegen.fidelity.drift: a hidden motion of the image is found and measured, a static scene
shows none, and removing each pixel's trend gives back the shot noise of a static scene
(docs/lowlight.md). Synthetic, seeded, fast."""
import math

import numpy as np
import pytest

from spikegen.fidelity import drift, stats
from spikegen.sensor import Sensor, simulate

T, H, W = 400, 64, 48


def _scene():
    """Radiance [H, W] with structure along both axes: a ramp and bands along rows, bands along columns."""
    r = np.arange(H)[:, None]
    c = np.arange(W)[None, :]
    return 0.15 + 0.25 * r / H + 0.1 * (np.sin(2 * np.pi * r / 16.0) > 0) + 0.08 * (np.sin(2 * np.pi * c / 12.0) > 0)


def _moving(scene, travel):
    return drift.expected_rates(scene, travel * np.arange(T) / (T - 1))


@pytest.mark.parametrize("travel", [3.0, 5.0, -4.0])
def test_hidden_motion_is_found_with_its_travel(travel):
    s = simulate(_moving(_scene(), travel), 256.0, Sensor(), frames=T, seed=11)
    rows = drift.fit_drift(s, 0, 8)
    cols = drift.fit_drift(s, 1, 8)
    assert abs(rows.travel - travel) < 0.4  # rows: the motion, within 0.4 row
    assert abs(cols.travel) < 0.4  # columns: none
    assert rows.residual_sd < 0.2  # a linear motion sits on the quadratic
    # the window shifts rise steadily, by travel / 8 per window
    assert np.all(np.sign(np.diff(rows.shifts)) == np.sign(travel))


def test_static_scene_shows_no_motion_and_same_seed_same_verdict():
    s = simulate(_scene(), 256.0, Sensor(electrons=3000.0), frames=T, seed=11)
    fits = [drift.fit_drift(s, axis, 8) for axis in (0, 1)]
    assert all(abs(f.travel) < 0.3 for f in fits)
    again = simulate(_scene(), 256.0, Sensor(electrons=3000.0), frames=T, seed=11)
    assert [drift.fit_drift(again, axis, 8).travel for axis in (0, 1)] == [f.travel for f in fits]


def test_stabilised_mean_undoes_the_motion():
    scene = _scene()
    s = simulate(_moving(scene, 5.0), 256.0, Sensor(), frames=T, seed=3)
    d = drift.fit_drift(s, 0, 8).shift()
    still = drift.stabilised_mean(s, d)
    naive = s.mean(0)
    # the fitted shifts are relative to the mean image, so the stabilised image is the scene moved by
    # the mean of the true shifts (2.5 rows); intensity 256: rate = radiance
    target = drift.expected_rates(scene, np.array([2.5]))[0]
    inner = slice(8, H - 8)
    assert np.abs(still - target)[inner].mean() < 0.5 * np.abs(naive - target)[inner].mean()


def _inv(stream, ideal, rate):
    v, corr, _ = drift.detrended_intervals(stream, 2)
    v0, _, _ = drift.detrended_intervals(ideal, 2)
    inv = (v - v0) * rate ** 2
    return inv, corr


def test_removing_the_trend_gives_back_the_static_shot_noise():
    """A ramp moved by 6 rows: every pixel's rate changes by about 9 % over the recording. With
    each pixel's trend removed, its 1/N_e equivalent equals that of the same shot noise on the
    static scene (within 3 standard errors and 30 %); without it, it is several times larger."""
    r = np.arange(H)[:, None]
    ramp = 0.15 + 0.3 * r / H + np.zeros((1, 2 * W))
    moving = drift.expected_rates(ramp, 6.0 * np.arange(T) / (T - 1))
    mean = moving.mean(0)
    ne = 3000.0
    ideal = simulate(mean, 256.0, Sensor(), frames=T, seed=13)
    out = {}
    for name, x in (("moving", moving), ("static", mean)):
        s = simulate(x, 256.0, Sensor(electrons=ne), frames=T, seed=12)
        p = stats.pixel_stats(s)
        inv, corr = _inv(s, ideal, p.rate)
        ok = (p.n_isi >= 8) & np.isfinite(inv)
        pi = stats.pixel_stats(ideal)
        noisy = p.isi_var >= 2.0
        raw = (stats.excess_interval_var(p, noisy) - stats.excess_interval_var(pi, noisy)) * p.rate ** 2
        out[name] = (inv[ok].mean(), inv[ok].std() / math.sqrt(ok.sum()), np.nanmean(raw[ok]), np.nanmedian(corr[ok]))
    (m, ms, m_raw, m_corr), (s_, ss, s_raw, _) = out["moving"], out["static"]
    assert abs(m - s_) < 3 * math.hypot(ms, ss)
    assert abs(m / s_ - 1) < 0.3
    assert 0.5 / ne < s_ < 1.2 / ne  # the estimator reads shot noise near its 1/N_e
    assert m_raw > 5 * s_raw  # without the trend removed the motion reads as much more noise
    assert m_corr < 0  # the residuals are not positively correlated


@pytest.mark.parametrize("ne", [1500.0, 6000.0])
def test_matched_shot_noise_reads_the_true_electrons(ne):
    """drift.matched_shot_noise on shot noise of known N_e, at rates 0.15-0.6 where whole frames
    bend the measure: within 3 standard errors and 15 % of the truth, and its last simulation
    reproduces the measured value within their errors; the first simulation (at 2e4, far from
    both) alone would be further off."""
    x = _scene()
    s = simulate(x, 256.0, Sensor(electrons=ne), frames=T, seed=21)
    p = stats.pixel_stats(s)
    mask = p.n_isi >= 8
    r = drift.matched_shot_noise(s, mask)
    assert r.pixels == int(mask.sum()) and len(r.steps) == drift.MATCH_STEPS
    assert abs(r.electrons - ne) < 3 * r.standard_error and abs(r.electrons / ne - 1) < 0.15
    assert abs(r.simulated[0] - r.measured[0]) < 3 * math.hypot(r.simulated[1], r.measured[1])
    first = r.steps[0][0] * r.steps[0][1] / r.measured[0]  # one simulation at the start, rescaled
    assert abs(first / ne - 1) > abs(r.electrons / ne - 1)


def test_matched_shot_noise_of_the_ideal_sensor_is_none():
    """No interval noise beyond the ideal sensor's: 1 / N_e within 3 standard errors of 0 and far
    below a quarter of the 1 / N_e of the weakest shot noise the test above uses."""
    s = simulate(_scene(), 256.0, Sensor(), frames=T, seed=21)
    r = drift.matched_shot_noise(s, stats.pixel_stats(s).n_isi >= 8)
    assert abs(r.inverse) < 3 * r.inverse_se and abs(r.inverse) < 0.25 / 6000.0
    assert r.inverse <= 0 or r.electrons > 6e4


def test_detrended_intervals_of_a_steady_ramp_of_intervals():
    # one pixel whose intervals lengthen by one frame each time: a quadratic in time nearly follows them
    times = np.cumsum(np.arange(5, 17))
    s = np.zeros((int(times[-1]) + 1, 1, 1), dtype=np.uint8)
    s[times, 0, 0] = 1
    var, corr, n = drift.detrended_intervals(s, 2)
    assert n[0] == len(times) - 1
    v0, _, _ = drift.detrended_intervals(s, 0)  # degree 0: the plain variance of the intervals
    assert v0[0] == pytest.approx(np.var(np.diff(times), ddof=1))
    assert var[0] < 0.01 * v0[0]


def test_bad_input_is_one_clear_error():
    s = np.zeros((10, 8, 8), dtype=np.uint8)
    with pytest.raises(ValueError, match="windows"):
        drift.fit_drift(s, 0, 2)
    with pytest.raises(ValueError, match="too short"):
        drift.profile_shift(np.zeros(10), np.zeros(10), max_shift=10.0)


@pytest.mark.parametrize("depth,period,rows_per_cycle", [(0.1, 400.0, 64.0), (0.2, 200.0, 40.0)])
def test_rolling_modulation_of_the_light_is_not_motion(depth, period, rows_per_cycle):
    """A brightness wave scanning the rows (a display's refresh) changes the rows' rates in time
    (the row x window map) but moves no edge: the fitted travel stays under 0.3 row."""
    t = np.arange(T)[:, None, None]
    r = np.arange(H)[None, :, None]
    x = _scene()[None] * (1.0 + depth * np.sin(2 * np.pi * (t / period - r / rows_per_cycle)))
    s = simulate(x, 256.0, Sensor(), frames=T, seed=11)
    plain = simulate(_scene(), 256.0, Sensor(), frames=T, seed=11)
    assert abs(drift.fit_drift(s, 0, 8).travel) < 0.3
    assert drift.window_change_map(s, 0, 8).std() > 2 * drift.window_change_map(plain, 0, 8).std()


# ---------------------------------------------------------------------- inside spikegen diagnose --reference self
def _dim_moving_stream(travel, frames=400, seed=11):
    """The scene at a fifth of its light (rates like the low-light recording's), moved ``travel``
    rows over ``frames`` frames, through the ideal sensor."""
    x = drift.expected_rates(0.2 * _scene(), travel * np.arange(frames) / (frames - 1))
    return simulate(x, 256.0, Sensor(), frames=frames, seed=seed)


def test_diagnose_self_reports_image_motion_instead_of_shot_noise(monkeypatch):
    import json

    from spikegen.fidelity.diagnose import diagnose

    s = _dim_moving_stream(4.0)
    d = diagnose(s, "self", 256.0)
    motion = d.info["motion"]
    assert motion["whole_image"] and motion["rows"]["moves"] and not motion["cols"]["moves"]
    Tf = d.info["fit_frames"]
    assert abs(motion["rows"]["travel"] - 4.0 * (Tf - 1) / (T - 1)) < 0.4  # measured on the fit frames
    assert abs(motion["cols"]["travel"]) < 0.4
    assert d.detected == []  # the ideal sensor moved with the image explains it: no effect is named
    assert json.dumps(diagnose(s, "self", 256.0).as_json()) == json.dumps(d.as_json())  # same input, same bytes
    # without the motion (never significant) the same stream's slow changes read as shot noise
    monkeypatch.setattr(drift, "MOTION_MIN_TRAVEL", math.inf)
    off = diagnose(s, "self", 256.0)
    assert not off.info["motion"]["whole_image"]
    assert "shot_noise" in off.detected


def test_diagnose_self_on_a_static_scene_finds_no_motion():
    from spikegen.fidelity.diagnose import diagnose

    d = diagnose(_dim_moving_stream(0.0), "self", 256.0)
    assert not d.info["motion"]["whole_image"] and d.info["motion"]["changed_pixels"] == 0
    assert d.detected == []


def test_an_object_moving_in_part_of_the_frame_is_not_a_whole_image_motion():
    from spikegen.fidelity import bands

    frames = 400
    scene = 0.2 * _scene()
    x = np.repeat(scene[None], frames, axis=0)
    for t in range(frames):  # a bright bar crosses the left quarter of the frame, top to bottom
        r = int(round(5 + 40 * t / (frames - 1)))
        x[t, r:r + 6, : W // 4] = 0.9
    s = simulate(x, 256.0, Sensor(), frames=frames, seed=11)
    m = drift.image_motion(bands.Stream.of(s), 64)
    assert not m.significant and not m.changed.any()
    assert m.rows["blocks_agree"] < drift.MOTION_AGREE  # its rows move in one block of columns only
    # the same bar spread over the whole width moves the whole image's profile, in every block
    x[:, :, W // 4:] = np.repeat(scene[None, :, W // 4:], frames, axis=0)
    for t in range(frames):
        r = int(round(5 + 40 * t / (frames - 1)))
        x[t, r:r + 6, :] = 0.9
    whole = drift.image_motion(bands.Stream.of(simulate(x, 256.0, Sensor(), frames=frames, seed=11)), 64)
    assert whole.rows["blocks_agree"] >= drift.MOTION_AGREE
