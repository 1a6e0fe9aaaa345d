"""Shot noise and threshold jitter told apart by the intervals' variance and lag-1 autocovariance
(drift.matched_timing_noise): known values read back, each effect alone and both together."""
import numpy as np
import pytest

from spikegen.fidelity import drift
from spikegen.sensor import Sensor, simulate


@pytest.mark.parametrize("electrons, jitter", [(3000.0, 0.02), (3000.0, 0.0), (0.0, 0.02)])
def test_matched_timing_noise_reads_back_known_noise(electrons, jitter):
    rate = np.random.default_rng(1).uniform(0.05, 0.5, (48, 48))
    spikes = simulate(rate, 256, Sensor(electrons=electrons, threshold_jitter=jitter), frames=2000, seed=77)
    fit = drift.matched_timing_noise({"synthetic": (spikes, np.ones(rate.size, bool))}, repeats=1)
    se_inverse, se_variance = fit.standard_errors
    true_inverse = 1.0 / electrons if electrons else 0.0
    assert abs(fit.inverse_electrons - true_inverse) < 3 * se_inverse
    assert abs(fit.jitter_variance - jitter ** 2) < 3 * se_variance
    # the estimates are far tighter than the effects: 1 / N_e = 3.3e-4 and sigma^2 = 4e-4 stand out
    assert se_inverse < 1e-4 and se_variance < 1e-4
    assert fit.chi2["synthetic"] < 13.8  # chi-square, 2 degrees of freedom, p = 0.001
    assert fit.pixels["synthetic"] == rate.size


def test_timing_chi2_rejects_the_wrong_noise():
    """A recording with jitter only is far from shot noise of the same single-interval variance."""
    rate = np.random.default_rng(2).uniform(0.05, 0.5, (32, 32))
    spikes = simulate(rate, 256, Sensor(threshold_jitter=0.03), frames=2000, seed=78)
    rec = {"jitter": (spikes, np.ones(rate.size, bool))}
    right = drift.timing_chi2(rec, 0.0, 0.03, repeats=1)["jitter"]
    wrong = drift.timing_chi2(rec, 1.0 / (2 * 0.03 ** 2), 0.0, repeats=1)["jitter"]
    assert right < 13.8 < wrong


def test_timing_chi2_takes_seeds_for_every_recording():
    """Two recordings, three repeats each: every simulation has its own seed (six in all)."""
    rate = np.random.default_rng(3).uniform(0.05, 0.5, (16, 16))
    recs = {k: (simulate(rate, 256, Sensor(electrons=3000.0), frames=600, seed=s), np.ones(rate.size, bool))
            for k, s in (("a", 1), ("b", 2))}
    chi2 = drift.timing_chi2(recs, 3000.0, 0.0, repeats=3)
    assert set(chi2) == {"a", "b"} and all(np.isfinite(v) for v in chi2.values())
