"""Property-based tests (hypothesis): spike files round-trip, and the sensor's invariants hold
for any sensor and radiance (issue 6: rate rises with radiance, mean count = intensity for
white, no more than one spike per frame).

Examples are derandomized (``derandomize=True``): CI runs the same examples every time.
"""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from spikegen.errors import InputError
from spikegen.sensor import Sensor, simulate
from spikegen.spikeio import decode_dat, encode_dat, read_spikes, write_spikes

FAST = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ---------------------------------------------------------------------- spike files
@st.composite
def streams(draw, max_t=6):
    """uint8 [T, H, W] of 0/1 with H * W a multiple of 8 (a valid .dat frame)."""
    h = draw(st.integers(1, 12))
    w = draw(st.sampled_from([v for v in range(1, 25) if (h * v) % 8 == 0]))
    t = draw(st.integers(1, max_t))
    return draw(hnp.arrays(np.uint8, (t, h, w), elements=st.integers(0, 1)))


@FAST
@given(streams())
def test_dat_round_trip(s):
    t, h, w = s.shape
    data = encode_dat(s)
    assert len(data) == t * h * w // 8
    np.testing.assert_array_equal(decode_dat(data, h, w), s)
    # layout: the first byte's least significant bit is the bottom-left pixel of frame 0
    assert data[0] & 1 == s[0, h - 1, 0]


@FAST
@given(streams(), st.integers(1, 7))
def test_dat_with_partial_frame_is_refused(s, cut):
    t, h, w = s.shape
    data = encode_dat(s)
    frame = h * w // 8
    cut = cut % frame
    if cut:  # a truncated or oversized file never decodes silently
        with pytest.raises(InputError):
            decode_dat(data[:-cut], h, w)
        with pytest.raises(InputError):
            decode_dat(data + data[:cut], h, w)


@FAST
@given(streams(), st.sampled_from([".dat", ".npz", ".npy"]))
def test_spike_file_round_trip(s, ext):
    t, h, w = s.shape
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"s{ext}"
        write_spikes(p, s)
        back = read_spikes(p, (w, h), frames=t)
        assert [q.name for q in Path(d).iterdir()] == [p.name]  # no temporary left beside it
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, s)


# ---------------------------------------------------------------------- sensor invariants
@st.composite
def maps(draw, h, w):
    """(R, d): responsivity around 1 and a small dark rate, as a real camera's maps."""
    r = draw(hnp.arrays(np.float64, (h, w), elements=st.floats(0.5, 1.5)))
    d = draw(hnp.arrays(np.float64, (h, w), elements=st.floats(0.0, 0.02)))
    return r, d


@st.composite
def any_sensor(draw, h, w):
    r, d = draw(maps(h, w)) if draw(st.booleans()) else (None, None)
    return Sensor(name="prop", responsivity=r, dark_rate=d,
                  electrons=draw(st.sampled_from([0.0, 4.0, 60.0, 500.0])),
                  reset=draw(st.sampled_from(["subtract", "zero"])),
                  refractory_frames=draw(st.integers(0, 3)),
                  threshold_jitter=draw(st.sampled_from([0.0, 0.05, 0.25])),
                  flicker_period_frames=draw(st.sampled_from([0.0, 7.0])),
                  flicker_depth=0.0,
                  crosstalk_fraction=draw(st.sampled_from([0.0, 0.1])) if h * w > 1 else 0.0,  # see below
                  gamma=draw(st.sampled_from([1.0, 0.8])),
                  kind=draw(st.sampled_from(["if", "rsir"])))


@FAST
@given(st.data())
def test_never_more_than_one_spike_a_frame(data):
    k, h, w = data.draw(st.integers(1, 3)), data.draw(st.integers(1, 6)), data.draw(st.integers(1, 6))
    t = data.draw(st.integers(1, 48))
    x = data.draw(hnp.arrays(np.float32, (k, h, w), elements=st.floats(0, 1e4, width=32)))
    sensor = data.draw(any_sensor(h, w))
    s = simulate(x, data.draw(st.floats(0.5, 4096)), sensor, frames=t, seed=data.draw(st.integers(0, 2**32 - 1)))
    assert s.shape == (t, h, w) and s.dtype == np.uint8
    assert set(np.unique(s).tolist()) <= {0, 1}


@FAST
@given(st.data())
def test_rate_rises_with_radiance(data):
    """Deterministic sensors (no shot noise), same seed (same start charge): a pixel that sees
    at least as much light fires at least as often, whatever its R, d, reset and refractory."""
    h, w, t = data.draw(st.integers(1, 6)), data.draw(st.integers(1, 6)), data.draw(st.integers(1, 300))
    r, d = data.draw(maps(h, w))
    sensor = Sensor(name="mono", responsivity=r, dark_rate=d, reset=data.draw(st.sampled_from(["subtract", "zero"])),
                    refractory_frames=data.draw(st.integers(0, 3)))
    x1 = data.draw(hnp.arrays(np.float64, (h, w), elements=st.floats(0, 8)))
    extra = data.draw(hnp.arrays(np.float64, (h, w), elements=st.floats(0, 8)))
    intensity = data.draw(st.floats(1, 512))
    seed = data.draw(st.integers(0, 2**32 - 1))
    c1 = simulate(x1, intensity, sensor, frames=t, seed=seed).sum(axis=0)
    c2 = simulate(x1 + extra, intensity, sensor, frames=t, seed=seed).sum(axis=0)
    assert np.all(c2 >= c1)


@FAST
@given(st.floats(0.25, 255.0), st.integers(1, 512), st.integers(0, 2**32 - 1))
def test_white_gives_intensity_spikes_per_256_frames(intensity, t, seed):
    """Ideal sensor, X = 1: every pixel fires floor or ceil of I T / 256 times; their mean is
    I T / 256 within its sampling error (start charges are uniform)."""
    h, w = 16, 16
    counts = simulate(np.ones((h, w)), intensity, None, frames=t, seed=seed).sum(axis=0)
    expected = intensity * t / 256.0
    assert counts.min() >= math.floor(expected) and counts.max() <= math.ceil(expected)
    assert abs(counts.mean() - expected) <= 5 * 0.5 / math.sqrt(h * w) + 1e-9


@FAST
@given(st.data())
def test_count_follows_the_rate_pixel_by_pixel(data):
    """Any R and d maps, static radiance, no noise: count = T * lambda within one spike, with
    lambda = R ((I / 256) X + d); a pixel with lambda >= 1 fires every frame."""
    h, w, t = data.draw(st.integers(1, 6)), data.draw(st.integers(1, 6)), data.draw(st.integers(1, 400))
    r, d = data.draw(maps(h, w))
    x = data.draw(hnp.arrays(np.float64, (h, w), elements=st.floats(0, 4)))
    intensity = data.draw(st.floats(1, 400))
    counts = simulate(x, intensity, Sensor(name="maps", responsivity=r, dark_rate=d), frames=t,
                      seed=data.draw(st.integers(0, 1000))).sum(axis=0)
    lam = r * (intensity / 256.0 * x + d)
    expected = np.where(lam >= 1.0, t, t * lam)
    assert np.all(np.abs(counts - expected) <= 1.0 + 1e-6 * t)


@FAST
@given(st.data())
def test_same_seed_same_bits(data):
    h, w = data.draw(st.integers(1, 5)), data.draw(st.integers(1, 5))
    sensor = data.draw(any_sensor(h, w))
    x = data.draw(hnp.arrays(np.float32, (2, h, w), elements=st.floats(0, 3, width=32)))
    seed = data.draw(st.integers(0, 2**32 - 1))
    a = simulate(x, 32.0, sensor, frames=40, seed=seed)
    b = simulate(x.copy(), 32.0, sensor, frames=40, seed=seed)
    np.testing.assert_array_equal(a, b)


def test_crosstalk_on_a_single_pixel():
    s = simulate(np.ones((1, 1)), 32.0, Sensor(name="ct", crosstalk_fraction=0.1, electrons=4.0), frames=16, seed=0)
    assert s.shape == (16, 1, 1)
