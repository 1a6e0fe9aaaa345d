"""The sensor model against sensor-model.md: intensity, timing, exactness, effects, seeding."""
import numpy as np
import pytest

import spikegen.sensor as S
from spikegen.errors import InputError
from spikegen.sensor import ONE, ChargeSchedule, Sensor, interpolation_weights, loop_readout, simulate, start_phase


@pytest.mark.parametrize("intensity", [16, 32, 64, 200])
def test_white_gives_intensity_spikes_per_256_frames(intensity):
    x = np.ones((4, 24, 40), np.float32)
    counts = simulate(x, intensity, frames=256, seed=5).sum(0)
    assert counts.min() == counts.max() == intensity  # total charge is exactly I thresholds


def test_fractional_intensity_within_start_phase():
    counts = simulate(np.ones((16, 16)), 20.5, frames=256, seed=1).sum(0)
    assert set(np.unique(counts)) <= {20, 21}
    assert abs(counts.mean() - 20.5) < 0.15


def _moving_scene(K=16, H=40, W=48, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.random((K, H, W)) * 1.5
    x[:, :3] *= 200.0  # saturating rows take the loop path
    x[:, 7] = 0.0
    return x.astype(np.float32)


def test_fast_path_is_bit_identical_to_a_frame_loop():
    x = _moving_scene()
    rng = np.random.default_rng(3)
    sensor = Sensor(responsivity=rng.uniform(0.7, 1.3, x.shape[1:]), dark_rate=np.full(x.shape[1:], 0.004))
    ss = np.random.SeedSequence(11)
    fast = simulate(x, 64, sensor, seed=ss)
    R, d = sensor.maps(*x.shape[1:])
    sched = ChargeSchedule.from_radiance(x.reshape(16, -1), 64, R.reshape(-1), d.reshape(-1), 256)
    ref = loop_readout(sched.dense_int64(), start_phase(ss, *x.shape[1:]).reshape(-1))
    np.testing.assert_array_equal(fast, ref.reshape(fast.shape))


@pytest.mark.parametrize("K,T", [(16, 256), (5, 256), (16, 200), (3, 7), (2, 256)])
def test_charge_follows_piecewise_linear_radiance(K, T):
    lam = np.random.default_rng(K).random((K, 300)) * 0.9
    lam[:, :20] = 0.0
    sched = ChargeSchedule(lam, T)
    exact = interpolation_weights(K, T) @ np.rint(lam * ONE)
    dense = sched.dense_int64()
    run = int(np.ceil(T / K)) + 1
    assert np.abs(dense - exact).max() <= run  # documented bound: run length in units of 2**-32
    assert dense.min() >= 0 and dense[:, :20].max() == 0


def test_interpolation_weights_follow_subframe_centres():
    w = interpolation_weights(2, 256)  # centres at frames 64 and 192
    assert w[0, 0] == 1 and w[64, 0] == 1 and w[128, 0] == 0.5 and w[192, 1] == 1 and w[255, 1] == 1
    np.testing.assert_allclose(w.sum(1), 1)


def test_results_do_not_depend_on_chunking(monkeypatch):
    x = _moving_scene(H=40, W=48)
    sensor = Sensor(electrons=300.0)
    a = simulate(x, 64, sensor, seed=2)
    monkeypatch.setattr(S, "FAST_CHUNK_PIXELS", 8 * 48)  # one noise block per chunk
    b = simulate(x, 64, sensor, seed=2)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, simulate(x, 64, sensor, seed=3))


def test_fast_and_dense_noise_paths_agree():
    x = _moving_scene(H=16, W=24)
    sensor = Sensor(electrons=60.0, dark_rate=np.full((16, 24), 0.003))
    ss = np.random.SeedSequence(9)
    fast = simulate(x, 64, sensor, seed=ss)
    R, d = sensor.maps(16, 24)
    out = np.empty_like(fast)
    phase = start_phase(ss, 16, 24)
    for b, r0 in enumerate(range(0, 16, S.CHUNK_ROWS)):
        rngs = [np.random.Generator(np.random.PCG64(S._child(ss, 1 + b)))]
        view = out.reshape(256, -1)[:, r0 * 24:(r0 + 8) * 24]
        S._dense_rows(x, r0, r0 + 8, 64.0, sensor, R, d, phase, 256, rngs, view)
    np.testing.assert_array_equal(fast, out)


@pytest.mark.parametrize("electrons", [20.0, 400.0])  # exact Poisson / quantised normal limit
def test_shot_noise_count_variance(electrons):
    lam, T = 0.25, 1024
    x = np.full((64, 64), lam * 256 / 64)
    counts = simulate(x, 64, Sensor(electrons=electrons), frames=T, seed=4).sum(0)
    expected = T * lam / electrons + 1 / 12  # Poisson charge + start phase
    assert abs(counts.mean() - T * lam) < 0.2
    assert abs(counts.var() / expected - 1) < 0.15


def test_at_most_one_spike_per_frame_and_saturation():
    s = simulate(np.full((8, 8), 1000.0), 64, frames=100, seed=0)
    assert s.max() == 1 and (s.sum(0) == 100).all()


def test_dark_current_and_responsivity():
    H = W = 32
    dark = simulate(np.zeros((H, W)), 32, Sensor(dark_rate=np.full((H, W), 0.01)), frames=2560, seed=1)
    assert abs(dark.sum(0).mean() - 25.6) < 0.6
    half = simulate(np.ones((H, W)), 64, Sensor(responsivity=np.full((H, W), 0.5)), seed=1)
    assert (half.sum(0) == 32).all()


def test_reset_to_zero_and_refractory():
    x = np.full((16, 16), 0.3 * 256 / 64)  # lambda = 0.3
    sub = simulate(x, 64, Sensor(), frames=1200, seed=0).sum(0)
    zero = simulate(x, 64, Sensor(reset="zero"), frames=1200, seed=0).sum(0)
    assert abs(sub.mean() - 360) <= 1 and abs(zero.mean() - 300) <= 1  # every 4th frame after a reset
    sat = simulate(np.full((4, 8), 100.0), 64, Sensor(refractory_frames=2), frames=300, seed=0).sum(0)
    assert (np.abs(sat - 100) <= 1).all()  # fire, then 2 dead frames


def test_radiance_effects():
    H = W = 9
    x = np.zeros((H, W))
    x[4, 4] = 1.0
    ct = simulate(x, 256, Sensor(crosstalk_fraction=0.2), frames=2560, seed=0).sum(0)
    assert abs(ct[4, 3] - 128) <= 1 and abs(ct[4, 4] - 2048) <= 1 and ct[0, 0] == 0
    nl = simulate(np.full((8, 8), 0.25), 64, Sensor(gamma=2.0), frames=2560, seed=0).sum(0)
    assert abs(nl.mean() - 40) <= 1  # 64 * 0.0625 * 10
    fl = simulate(np.ones((8, 8)), 128, Sensor(flicker_depth=0.5, flicker_period_frames=64), frames=256, seed=0)
    rates = fl.reshape(8, 32, 8, 8).mean(axis=(1, 2, 3))  # 8 windows of 32 frames
    assert rates[0] > rates[1] + 0.1 and abs(fl.mean() - 0.5) < 0.02


def test_rsir_reference_generator_is_noisier():
    x = np.full((32, 32), 0.5)
    ideal = simulate(x, 64, Sensor(), frames=1024, seed=0)
    rsir = simulate(x, 64, Sensor(kind="rsir"), frames=1024, seed=0)
    def isi_std(s):
        t = [np.diff(np.flatnonzero(s[:, i, j])) for i in range(8) for j in range(8)]
        return np.concatenate(t).std()
    assert isi_std(rsir) > 3 * isi_std(ideal)
    assert 0.08 < rsir.mean() < 0.13  # about I X / 256 = 0.125, a little less (interval noise)


def test_seeded_and_reproducible():
    x = _moving_scene(H=16, W=16)
    a = simulate(x, 32, seed=np.random.SeedSequence([1, 2, 3]))
    b = simulate(x, 32, seed=np.random.SeedSequence([1, 2, 3]))
    c = simulate(x, 32, seed=np.random.SeedSequence([1, 2, 4]))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("bad, match", [
    (dict(radiance=np.full((4, 8), np.nan)), "NaN"),
    (dict(radiance=-np.ones((4, 8))), "negative"),
    (dict(intensity=0), "positive"),
    (dict(intensity=float("inf")), "positive"),
    (dict(frames=0), "frames"),
])
def test_bad_input(bad, match):
    args = dict(radiance=np.ones((4, 8)), intensity=32, frames=16)
    args.update(bad)
    with pytest.raises(InputError, match=match):
        simulate(args["radiance"], args["intensity"], frames=args["frames"])


def test_bad_sensor_parameters():
    for bad in (-0.01, float("nan"), 0.3):
        with pytest.raises(InputError, match="threshold_jitter"):
            Sensor(threshold_jitter=bad)
    with pytest.raises(InputError, match="reset"):
        Sensor(reset="sometimes")
    with pytest.raises(InputError, match="electrons"):
        Sensor(electrons=-1)
    with pytest.raises(InputError, match="maps are"):
        simulate(np.ones((8, 8)), 32, Sensor(responsivity=np.ones((4, 8))))


def _intervals(spikes):
    """Per pixel of ``uint8 [T, H, W]``: the variance of single intervals, of spans of 4
    intervals, and the lag-1 serial correlation of intervals (means over the pixels)."""
    T, H, W = spikes.shape
    v1, v4, rho = [], [], []
    for p in range(H * W):
        t = np.flatnonzero(spikes[:, p // W, p % W])
        d = np.diff(t)
        v1.append(d.var())
        v4.append((t[4:] - t[:-4]).var())
        rho.append(np.corrcoef(d[1:], d[:-1])[0, 1])
    return float(np.mean(v1)), float(np.mean(v4)), float(np.mean(rho))


def test_threshold_jitter_does_not_accumulate():
    """A firing level of relative SD sigma, the nominal threshold subtracted: at a constant rate
    lambda = 0.1 (intervals of exactly 10 frames without noise) the intervals get variance
    2 sigma^2 / lambda^2 plus the frame quantisation of two spike times (2 / 12), a span of 4
    intervals the same (not 4 times it, as shot noise gives), consecutive intervals correlate
    by -1/2, and the mean rate is unchanged."""
    x = np.full((24, 24), 0.1 * 256 / 64)
    sigma, lam, T = 0.05, 0.1, 3000
    s = simulate(x, 64, Sensor(threshold_jitter=sigma), frames=T, seed=3)
    assert abs(s.sum(0).mean() / T - lam) < 2e-4
    v1, v4, rho = _intervals(s)
    assert v1 == pytest.approx(2 * sigma ** 2 / lam ** 2 + 2 / 12, rel=0.05)
    assert v4 == pytest.approx(v1, rel=0.05)
    assert rho == pytest.approx(-0.5, abs=0.03)
    # shot noise of about the same single-interval variance accumulates over the span
    shot = simulate(x, 64, Sensor(electrons=200.0), frames=T, seed=3)
    s1, s4, _ = _intervals(shot)
    assert s1 == pytest.approx(v1, rel=0.1) and s4 > 3 * s1


def test_threshold_jitter_is_seeded_and_split_free():
    """The jitter's draws come from each row block's own stream: the same bits whole, by rows,
    in threads; another seed differs; jitter 0 keeps the sensor's fast path bits."""
    x = _moving_scene(H=24, W=20)
    sensor = Sensor(threshold_jitter=0.08, electrons=500.0)
    whole = simulate(x, 64, sensor, seed=9)
    np.testing.assert_array_equal(whole, simulate(x, 64, sensor, seed=9, threads=2))
    parts = np.concatenate([simulate(x, 64, sensor, seed=9, rows=(r, r + 8)) for r in (0, 8, 16)], axis=1)
    np.testing.assert_array_equal(whole, parts)
    assert not np.array_equal(whole, simulate(x, 64, sensor, seed=10))
    assert not np.array_equal(whole, simulate(x, 64, sensor.replace(threshold_jitter=0.0), seed=9))
    np.testing.assert_array_equal(simulate(x, 64, Sensor(electrons=500.0), seed=9),
                                  simulate(x, 64, sensor.replace(threshold_jitter=0.0), seed=9))
