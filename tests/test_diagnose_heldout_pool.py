"""The held-out score (`spikegen.fidelity.heldout`) with a still or a changing reference: a pixel's
held-out intervals scored by the probability of their whole-frame values among the simulated
intervals of the 64 judged pixels of nearest drive, so that the score ranks the true model first at
the temporal noise of real sensors.

Until 2026-11-26 the score read each pixel's held-out intervals through a Gaussian of that pixel's
own simulated interval mean and variance, at least a twelfth of a frame^2. On recordings with shot
noise of N_e = 1.38e4 (the car's measured interval variance) it scored the true model below the
ideal sensor: the ``still`` cases of the first two tests (three cases) failed on it, at z -5.0 to
-6.7.

With a reference that changes (sub-frames ``K > 1``) the intervals kept that Gaussian, and the
counts were scored against one simulated draw, a while longer. The ``changing`` cases of the first
three tests failed on it: the true shot noise at z -0.34 and -0.19, the preset's noise on its own
recording at z -2.4 (ranked below the ideal sensor), the ideal sensor on an ideal recording at
z -1.8 (asked: below -3). Now the judged pixels whose reference stays within 10 % of its mean are
pooled as with a still one, and every judged pixel's counts are predicted as its simulated rate
times the reference's course in time.
"""
from __future__ import annotations

import numpy as np
import pytest

from spikegen.fidelity import heldout
from spikegen.fidelity.diagnose import score_sensor
from spikegen.sensor import Sensor, simulate

FRAMES = 500
SHAPE = (100, 160)


def _rates(seed: int = 5) -> np.ndarray:
    """Rates (spikes per frame) like the car's static background: 0.1 to 0.35, smooth in space."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0.1, 0.35, size=(SHAPE[0] // 10 + 1, SHAPE[1] // 10 + 1))
    rows = np.linspace(0, coarse.shape[0] - 1, SHAPE[0])
    cols = np.linspace(0, coarse.shape[1] - 1, SHAPE[1])
    r0, c0 = np.floor(rows).astype(int), np.floor(cols).astype(int)
    r1, c1 = np.minimum(r0 + 1, coarse.shape[0] - 1), np.minimum(c0 + 1, coarse.shape[1] - 1)
    fr, fc = (rows - r0)[:, None], (cols - c0)[None, :]
    return ((1 - fr) * ((1 - fc) * coarse[r0][:, c0] + fc * coarse[r0][:, c1])
            + fr * ((1 - fc) * coarse[r1][:, c0] + fc * coarse[r1][:, c1]))


def _moving_reference(K: int = 8) -> np.ndarray:
    """``[K, H, W]``: the still rates of :func:`_rates`, with a bright bar over rows 20-35 that moves
    right by 12 columns a sub-frame (the pixels it crosses are not still)."""
    X = np.repeat(_rates()[None], K, axis=0)
    for k in range(K):
        X[k, 20:36, 10 + 12 * k: 30 + 12 * k] = 0.6
    return X


def _gain(recording: Sensor, model: Sensor, seed: int, scene: str = "still") -> tuple[float, float]:
    """(nats gained by ``model`` over the ideal sensor, z) on a recording of ``recording``: of the
    still rates of :func:`_rates`, scored with ``"self"`` (``scene="still"``), or of the sub-frames
    of :func:`_moving_reference`, which are also the reference it is scored against (``"changing"``)."""
    radiance = _rates() if scene == "still" else _moving_reference()
    reference = "self" if scene == "still" else radiance
    spikes = simulate(radiance, 256.0, recording, frames=FRAMES, seed=seed)
    a = score_sensor(spikes, reference, 256.0, model)
    b = score_sensor(spikes, reference, 256.0, Sensor(name="ideal"))
    gain, se = a.improvement(b)
    return gain, gain / se


@pytest.mark.parametrize("scene", ["still", "changing"])
@pytest.mark.parametrize("seed", [11, 12])
def test_the_true_shot_noise_scores_above_the_ideal_sensor(seed, scene):
    gain, z = _gain(Sensor(electrons=13830), Sensor(name="shot", electrons=13830), seed, scene)
    assert z > 3, (gain, z)


@pytest.mark.parametrize("scene", ["still", "changing"])
def test_the_preset_noise_scores_above_the_ideal_sensor_on_its_own_recording(scene):
    preset = dict(electrons=22540, threshold_jitter=0.00362)
    gain, z = _gain(Sensor(**preset), Sensor(name="p", **preset), 14, scene)
    assert z > 3, (gain, z)


@pytest.mark.parametrize("scene", ["still", "changing"])
def test_the_ideal_sensor_scores_above_shot_noise_on_an_ideal_recording(scene):
    gain, z = _gain(Sensor(), Sensor(name="shot", electrons=13830), 13, scene)
    assert z < -3, (gain, z)


def test_much_shot_noise_is_ranked_first():
    """Noise far above a frame's rounding (N_e = 100: intervals of 3 to 10 frames vary by 10 %)."""
    gain, z = _gain(Sensor(electrons=100), Sensor(name="shot", electrons=100), 15)
    assert z > 3, (gain, z)


def test_pool_groups_cut_the_judged_pixels_in_order_of_their_key():
    key = np.array([5.0, 1.0, 3.0, 2.0, 4.0, 6.0, np.nan, 0.5])
    mask = np.array([True, True, True, True, True, True, True, False])
    group, groups = heldout.pool_groups(key, mask, size=3)
    assert groups == 2
    assert group.tolist() == [1, 0, 0, 0, 1, 1, -1, -1]  # keys 1, 2, 3 | 4, 5, 6; NaN and unjudged: none


def test_a_pool_gives_probabilities_that_sum_to_one():
    """64 pixels of one pool (simulated intervals 4 and 5 frames, 3 of 6); pixel j holds one held-out
    interval of j frames, so the exponentials of the 64 scores are the pool's probabilities of the
    values 0..63, which must sum to 1 (the pseudo-interval's tail beyond 63 is negligible)."""
    P, T = 64, 400
    pool = heldout.IntervalPool(P, T)
    sim_x = np.tile([4, 5, 5, 4, 5, 4], P)
    sim_pix = np.repeat(np.arange(P), 6)
    pool.add(slice(0, P), (sim_x, sim_pix), (np.full(P, 4.5), np.full(P, 0.3), np.full(P, 6.0)),
             (np.arange(P), np.arange(P)))
    probs = np.exp(pool.finish(np.ones(P, dtype=bool)))
    assert probs.sum() == pytest.approx(1.0, abs=1e-6)
    # the pool's 384 intervals are 4 or 5 in equal parts; the pseudo-interval holds 1/385
    assert probs[4] == pytest.approx(probs[5]) and 192 / 385 < probs[4] < 193 / 385
    assert probs[0] < 1e-3 and probs[10] < 1e-6


def test_the_pool_spans_the_bands_of_rows():
    """diagnose's held-out pass reads the stream in bands of rows; the pools are made over all judged
    pixels at the end, so the score does not depend on the band height."""
    spikes = simulate(_rates(), 256.0, Sensor(electrons=5000), frames=FRAMES, seed=21)
    model = Sensor(name="shot", electrons=5000)
    banded = score_sensor(spikes, "self", 256.0, model, band_rows=16)
    whole = score_sensor(spikes, "self", 256.0, model, band_rows=96)
    assert banded.mean == pytest.approx(whole.mean, rel=1e-9)
    assert np.allclose(banded.per_pixel, whole.per_pixel, rtol=1e-9, atol=1e-9)


def test_with_a_changing_reference_a_true_dark_current_scores_above_none():
    """The counts follow the reference's course: a dark rate of 0.02 spikes a frame (a tenth of the
    scene's), which the reference's light does not carry, is found through them and the intervals."""
    dark = np.full(SHAPE, 0.02)
    gain, z = _gain(Sensor(dark_rate=dark), Sensor(name="dark", dark_rate=dark), 16, "changing")
    assert z > 3, (gain, z)


def test_quasi_still_pixels_are_those_whose_reference_stays_within_a_tenth_of_its_mean():
    X = np.ones((4, 1, 5))
    X[:, 0, 1] = [1.0, 1.05, 0.98, 1.0]  # range 0.07 of its mean
    X[:, 0, 2] = [1.0, 1.2, 1.0, 1.0]  # 0.19
    X[:, 0, 3] = 0.0  # dark throughout: still
    X[:, 0, 4] = [0.0, 0.0, 0.0, 0.1]  # lit in one sub-frame
    assert heldout.quasi_still(X).tolist() == [True, True, False, True, False]
    assert heldout.quasi_still(X[:1]).all()  # K = 1: every pixel


def test_the_reference_course_is_the_drive_over_its_mean():
    """Two sub-frames 0.1 and 0.3 with dark rate 0.05: the drive I X(t) / 256 + d, X(t)
    interpolated between the sub-frames' centres (frames 25 and 75 of 100), over its mean."""
    X = np.array([0.1, 0.3]).reshape(2, 1, 1)
    course = heldout.ReferenceCourse(X, 256.0, np.array([[0.05]]), 100)
    t = np.arange(100)
    x = np.interp(t, [25, 75], [0.1, 0.3])
    drive = x + 0.05
    f = course.window_factor(10, 50, 5)[:, 0]
    assert np.allclose(f, drive[50:100].reshape(5, 10).mean(axis=1) / drive.mean())
