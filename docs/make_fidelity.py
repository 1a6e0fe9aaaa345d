"""Generate docs/fidelity.md (+ docs/fidelity/*.png) and the `calibrated` preset from measured data.

    python docs/make_fidelity.py [--data ../shared/data] [--no-preset]

Every number in the page is computed here, from shared/data/real (see its README) and from
simulations seeded with fixed seeds, so a re-run gives the same page but for its line with the
date, the load average and the run time. Writes
assets/calibrated.json + assets/calibrated.npz (the `calibrated` preset) unless --no-preset.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO / "generator"))

from spikegen.fidelity import heldout, stats, synth  # noqa: E402
from spikegen.fidelity.diagnose import diagnose  # noqa: E402
from spikegen.fidelity.report import save_figure  # noqa: E402
from spikegen.sensor import Sensor, simulate  # noqa: E402
from spikegen.spikeio import read_spikes, write_bytes_atomic  # noqa: E402

FIG = HERE / "fidelity"
SEED = 2024


# ---------------------------------------------------------------------- helpers
def fig(name, draw, size=(6.0, 3.8)):
    save_figure(FIG / name, draw, size, dpi=100)
    return f"fidelity/{name}"


def regularity(spikes, mask=None):
    """Per-pixel (rate, ISI range, ISI CV, fraction of 1-frame ISIs) for pixels with >= 5 ISIs."""
    p = stats.pixel_stats(spikes)
    ok = p.n_isi >= 5
    if mask is not None:
        ok &= mask.reshape(-1)
    iv, ipix = p.isi_values, _isi_pixels(spikes)
    rng_max = np.zeros(p.n.size)
    np.maximum.at(rng_max, ipix, iv)
    spread = rng_max - p.isi_min
    cv = np.sqrt(p.isi_var) / p.isi_mean
    return {"rate": p.rate[ok], "range": spread[ok], "cv": cv[ok], "ones": p.ones[ok] / p.n_isi[ok],
            "isi": iv[np.isin(ipix, np.flatnonzero(ok))]}


def _isi_pixels(spikes):
    pix, _ = stats.spike_times(spikes)
    return pix[1:][pix[1:] == pix[:-1]]


def pct(x):
    return f"{100 * x:.1f} %"


def table(rows, head):
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


# ---------------------------------------------------------------------- the preset's N_e, from both recordings
MOTION_LIMIT = 0.10  # low light: pixels whose rate the fitted motion changes by less than this (docs/lowlight.md)
CHECK_SEED = 77  # the synthetic recordings of the estimator check
CHECK_ELECTRONS = (1e4, 3e4)  # pure shot noise of the check, besides the fitted values


MIN_INTERVALS = 8  # a pixel's intervals for its variance to be averaged (drift.matched_shot_noise)


def preset_sensor(results, name="calibrated noise"):
    """The ideal sensor plus the temporal noise fitted to both recordings (estimate_electrons)."""
    e = results["electrons"]
    return Sensor(name=name, electrons=float(e) if math.isfinite(e) else 0.0, threshold_jitter=results["jitter"])


def preset_label(results) -> str:
    return f"N_e = {results['electrons']:.3g}, threshold jitter SD {results['jitter']:.2g}"


def _static_mask(spikes):
    """The pixels matched_shot_noise averages on a static scene: static (heldout.static_pixels) with at
    least MIN_INTERVALS intervals."""
    from spikegen.fidelity.heldout import static_pixels

    return static_pixels(spikes) & (stats.pixel_stats(spikes).n_isi >= MIN_INTERVALS)


def estimate_electrons(real, results):
    """The preset's temporal noise: drift.matched_timing_noise (shot noise and threshold jitter
    together, from the variance and lag-1 autocovariance of the intervals, each pixel's trend
    removed, matched by simulation) on the car's static background and on the low-light pixels
    that its image's motion hardly changes, one parameter set for both; beside it
    drift.matched_shot_noise (shot noise alone, from the variance) on the same pixels, the
    inverse-variance weighted mean of the two 1 / N_e."""
    from spikegen.fidelity import drift

    car = read_spikes(real / "car_500frames_250x400.npz")
    low = read_spikes(real / "uhsr_lowlight_250x250.npz")
    shift = drift.fit_drift(low, 0, 8).shift()
    change = drift.rate_change(drift.expected_rates(drift.stabilised_mean(low, shift), shift))
    low_mask = (stats.pixel_stats(low).n_isi >= MIN_INTERVALS) & (change < MOTION_LIMIT)
    car_static = _static_mask(car)
    results["car_static"] = car_static  # (study_car_bands splits it into bands of rows)
    fits = {"car": drift.matched_shot_noise(car, car_static),
            "low light": drift.matched_shot_noise(low, low_mask)}
    w = {k: 1.0 / f.inverse_se ** 2 for k, f in fits.items()}
    inv = sum(w[k] * f.inverse for k, f in fits.items()) / sum(w.values())
    inv_se = 1.0 / math.sqrt(sum(w.values()))
    results["matched"] = fits
    results["matched_se"] = inv_se / inv ** 2
    if not inv > 0:
        sys.exit("make_fidelity: neither recording has interval variance beyond the ideal sensor's")
    results["matched_electrons"] = 1.0 / inv
    # the preset: shot noise and threshold jitter fitted together to both recordings (the
    # intervals' variance and lag-1 autocovariance), and the shot-noise-only fit checked alike
    recordings = {"car": (car, car_static.reshape(-1)), "low light": (low, low_mask.reshape(-1))}
    data = drift.timing_data(recordings)  # the references and measured statistics, for both
    timing = drift.matched_timing_noise(recordings, data=data)
    results["timing"] = timing
    results["timing_shot_chi2"] = drift.timing_chi2(recordings, 1.0 / inv, 0.0, data=data)
    if not timing.inverse_electrons > 0:
        sys.exit("make_fidelity: the joint fit of shot noise and threshold jitter gives no shot noise")
    results["electrons"] = timing.electrons
    results["electrons_se"] = timing.standard_errors[0] / timing.inverse_electrons ** 2
    results["jitter"] = timing.jitter
    results["car_rate"] = np.minimum(car.mean(0), 1.0)
    results["car_frames"] = car.shape[0]


def study_electrons(md, results, written):
    """Section: the two recordings' N_e measured alike, the preset's, and a seeded check of both
    estimators (this one and the diagnosis') on recordings at the car's rates with a known noise."""
    from spikegen.fidelity import drift
    from spikegen.fidelity.diagnose import score_sensor

    fits, e, e_se = results["matched"], results["matched_electrons"], results["matched_se"]
    diag = {"car": results["car_diagnosis"].effect("shot_noise"),
            "low light": results["lowlight_diagnosis"].effect("shot_noise")}
    rows = []
    for label, f in fits.items():
        z = (f.inverse - 1.0 / e) / f.inverse_se
        d = diag[label]
        de = d.parameters.get("electrons")
        rows.append((label, f.pixels, f"{f.measured[0]:.3g} +- {f.measured[1]:.2g}",
                     " -> ".join(f"{n:.4g}" for n, _ in f.steps),
                     f"{_ne(f.electrons)} +- {f.standard_error:.2g}", f"{z:+.1f}",
                     f"{_fmt(de)} (z = {d.z:.3g})"))
    # the check: pure shot noise at known N_e, and shot noise at the diagnosis' car value plus a
    # jitter that does not accumulate, of the size that the car's two readings differ by
    x, T = results["car_rate"], results["car_frames"]
    e_diag = diag["car"].parameters.get("electrons") or math.inf
    gap = fits["car"].inverse - (1.0 / e_diag if math.isfinite(e_diag) else 0.0)
    jitter = math.sqrt(gap / 2.0) if gap > 0 else 0.0
    cases = [(f"shot noise N_e = {_ne(n)}", n, 0.0) for n in (CHECK_ELECTRONS[0], e, CHECK_ELECTRONS[1])]
    if jitter > 0 and math.isfinite(e_diag):
        cases.append((f"shot noise N_e = {_ne(e_diag)} + threshold jitter SD {jitter:.2g}, not accumulating",
                      e_diag, jitter))
    fitted_case = (f"the joint fit: {preset_label(results)}", results["electrons"], results["jitter"])
    cases.append(fitted_case)
    check, errors = [], []
    for label, n, jit in cases:
        s = simulate(x, 256.0, Sensor(electrons=n, threshold_jitter=jit), frames=T, seed=CHECK_SEED)
        m = drift.matched_shot_noise(s, _static_mask(s))
        verdict = diagnose(s, "self", 256.0)
        d, dj = verdict.effect("shot_noise"), verdict.effect("threshold_jitter")
        de = d.parameters.get("electrons")
        check.append((label, f"{_ne(m.electrons)} +- {m.standard_error:.2g}", f"{_fmt(de)} (z = {d.z:.3g})",
                      f"{_fmt(dj.parameters.get('sigma'))} (z = {dj.z:.3g}{', named' if dj.detected else ''})"))
        if (label, n, jit) == fitted_case:  # the joint fit on a recording with exactly that noise
            own = drift.matched_timing_noise({"seeded": (s, _static_mask(s).reshape(-1))})
            fitted_check = (own.electrons, own.jitter, dj)
            continue
        if jit == 0:
            errors += [abs(m.electrons / n - 1), abs((de or math.inf) / n - 1)]
            if n == e:  # the held-out score of the true shot noise against none
                truth_gain = (score_sensor(s, "self", 256.0, Sensor(name="shot", electrons=n)).mean
                              - score_sensor(s, "self", 256.0, Sensor(name="shot")).mean)
        else:
            jittered = (m.electrons, de)
    car_m, car_d = fits["car"].electrons, diag["car"].parameters.get("electrons")
    scores = results["joint"]["scores"]
    gain = {label: results["joint"]["fitted"][label] - scores[label][math.inf] for label in scores}
    spread = {label: max(v for n, v in sc.items() if n >= 1e4) - min(v for n, v in sc.items() if n >= 1e4)
              for label, sc in scores.items()}
    held = (f"Held-out score (\"One temporal-noise parameter for both recordings?\" above) under the fitted "
            f"{preset_label(results)} against the ideal sensor: "
            + ", ".join(f"{k} {v:+.3g} (z = {results['joint']['fitted_z'][k]:+.3g})" for k, v in gain.items())
            + " nats per pixel (z: the summed per-pixel differences over their standard error); "
            "over the grid's N_e from 1e4 to none the scores move by at most "
            + ", ".join(f"{v:.3g} ({k})" for k, v in spread.items()) + " nats per pixel. "
            + f"On the seeded recording above with shot noise of exactly N_e = {_ne(e)}, the held-out score of "
            f"the true N_e against none is {truth_gain:+.3g} nats per pixel"
            + (": at these N_e the score does not tell shot noise from none (it scores the truth lower), so the "
               "preset's noise rests on the interval statistics measured here, not on the held-out score."
               if truth_gain <= 0 else "."))
    timing, shot_chi2 = results["timing"], results["timing_shot_chi2"]
    t_se = timing.standard_errors
    t_rows = [(label, timing.pixels[label],
               f"{timing.measured[label][0]:.3g} / {timing.measured[label][1]:.3g}",
               f"{math.sqrt(timing.measured_cov[label][0, 0]):.2g} / {math.sqrt(timing.measured_cov[label][1, 1]):.2g}",
               f"{timing.simulated[label][0]:.3g} / {timing.simulated[label][1]:.3g}",
               f"{timing.chi2[label]:.3g}", f"{shot_chi2[label]:.3g}") for label in timing.measured]
    md += ["## Shot noise and threshold jitter, measured alike on both recordings (the preset's noise)", "",
           "`spikegen.fidelity.drift.matched_timing_noise`: per pixel, the variance and the lag-1 autocovariance of "
           "its intervals about a quadratic in time (`drift.detrended_lag_covariance`), less those of the ideal "
           f"sensor at the same mean rates (seed {drift.TIMING_SEED}), times rate^2, averaged over the pixels "
           "(`drift.timing_excess`). Shot noise makes consecutive intervals vary independently; a threshold "
           "jitter (the sensor's `threshold_jitter`: the firing level varies from spike to spike, the reset "
           "subtracts the nominal threshold) moves one spike time, lengthening one interval and shortening the "
           "next, so it adds variance and a negative lag-1 autocovariance. Simulations of shot noise alone and of "
           "jitter alone give each recording's statistics per unit of each; the estimate is the generalised "
           "least-squares fit of both recordings' four statistics by the two parameters, then "
           f"{drift.TIMING_STEPS} Newton steps on simulations at the estimate (each the mean of "
           f"{drift.TIMING_REPEATS} seeds, from {drift.TIMING_SEED + 1} on); last, a simulation at the final "
           "estimate gives each recording's chi-square (2 degrees of freedom each). Same pixels as below.", "",
           table(t_rows, ["recording", "pixels", "measured variance / lag-1 autocovariance (x rate^2)", "SE",
                          "simulated at the joint fit", "chi2, joint fit", f"chi2, shot noise alone N_e = {_ne(e)}"]),
           "",
           f"**One parameter set for both recordings: N_e = {_ne(timing.electrons)} (1/N_e = "
           f"{timing.inverse_electrons:.3g} +- {t_se[0]:.2g}) and threshold jitter SD {timing.jitter:.3g} "
           f"(sigma^2 = {timing.jitter_variance:.3g} +- {t_se[1]:.2g}); the two estimates' errors correlate "
           f"by {timing.correlation():.2f}.** Against each recording's statistics it scores chi2 = "
           + ", ".join(f"{timing.chi2[k]:.3g} ({k})" for k in timing.chi2)
           + "; shot noise alone at the N_e of all of the interval variance (the table below) scores "
           + ", ".join(f"{shot_chi2[k]:.3g} ({k})" for k in shot_chi2)
           + ": the lag-1 autocovariance rejects shot noise alone. Per recording, the Jacobians (statistics per "
           "unit of 1/N_e and of sigma^2) say how well the recording tells the two apart: "
           + "; ".join(f"{k}: shot noise ({J[0, 0]:.3g}, {J[1, 0]:.3g}), jitter ({J[0, 1]:.3g}, {J[1, 1]:.3g})"
                       for k, J in timing.jacobian.items())
           + ". Where the two columns point the same way (the low light: with few intervals a pixel, removing "
           "its trend makes the residuals of any noise anticorrelated), that recording alone cannot tell "
           "shot noise from jitter; the car can, and the joint fit rests on it.", ""]
    md += ["## Shot noise alone, measured alike on both recordings", "",
           "`spikegen.fidelity.drift.matched_shot_noise`: per pixel, the variance of its intervals about a "
           "quadratic in time (a slow change of its rate, as the low-light image's motion makes, is left out), "
           f"less that of the ideal sensor at the same mean rates (seed {drift.MATCH_SEED}), times rate^2, averaged "
           "over the pixels; N_e is the shot noise whose simulation of the same mean rates (seed "
           f"{drift.MATCH_SEED + 1}) gives the same value: from {drift.MATCH_START:g} electrons, {drift.MATCH_STEPS} "
           "simulations, each at the previous one's estimate (the second number of 'electrons simulated' is "
           "what one simulation gives; docs/lowlight.md calibrates the same measure by one simulation at "
           "2.137e4). Pixels: the car's static background (`heldout.static_pixels`) with >= 8 intervals; the "
           f"low-light pixels with >= 8 intervals whose rate the fitted motion of the image changes by < "
           f"{100 * MOTION_LIMIT:.0f} % (docs/lowlight.md section 3). Last column: the `shot_noise` estimate of "
           "`spikegen diagnose --reference self` on the same recording (`stats.excess_interval_var`: on regular "
           "pixels the variance that accumulates over spans of 4 intervals, on the static pixels of the first "
           "80 % of the frames).", "",
           table(rows, ["recording", "pixels", "measured 1/N_e equivalent +- SE", "electrons simulated",
                        "N_e +- SE", f"z against {_ne(e)}", "diagnose's N_e"]), "",
           f"One N_e for both: the inverse-variance weighted mean of the two 1 / N_e, N_e = {_ne(e)} +- "
           f"{e_se:.2g}: all of the interval variance read as shot noise (the preset until the threshold jitter "
           "was modelled). The `calibrated` preset now holds the joint fit above"
           + (" (section 6)." if written else "; `--no-preset`: the preset is not refitted (section 6)."), "",
           f"Why the car reads {_ne(car_m)} here and {_fmt(car_d)} in `spikegen diagnose`: seeded recordings at "
           f"the car's mean rates ({T} frames, seed {CHECK_SEED}) with a known noise, through both estimators:", "",
           table(check, ["recording", "matched N_e +- SE (this section)", "diagnose's N_e",
                         "diagnose's threshold_jitter sigma"]), "",
           f"On the seeded recording with the joint fit's noise ({preset_label(results)}), the joint fit of the "
           f"section above reads N_e = {_ne(fitted_check[0])} and SD {fitted_check[1]:.3g}; `spikegen diagnose` "
           f"reads a threshold jitter of SD {_fmt(fitted_check[2].parameters.get('sigma'))} (z = "
           f"{fitted_check[2].z:.3g}), "
           + ("and names it." if fitted_check[2].detected else
              f"and does not name it (its gates: {fitted_check[2].evidence.get('size_gate')} in size, z "
              f"{fitted_check[2].evidence.get('z_gate')}"
              + ("; its estimate is within 20 % of the jitter the recording holds, below the size gate). "
                 if abs((fitted_check[2].parameters.get('sigma') or 0.0) / results["jitter"] - 1) <= 0.2 else
                 "; its estimate, from the non-accumulating share of the variance of single intervals and spans of "
                 "4, is off the jitter the recording holds by more than 20 %). ")
              + "So `spikegen diagnose` does not name a jitter of this size, and the preset's comes from the joint "
              "fit."), "",
           f"On shot noise alone both estimators read the true N_e within {100 * max(errors):.0f} %. A noise that "
           "does not accumulate from spike to spike (a threshold that varies from spike to spike while the "
           "reset subtracts the nominal one: the sensor's `threshold_jitter`) is all in the variance "
           "of single intervals, which this section measures, and none of it in the growth of the variance over "
           "a span of intervals, which the diagnosis measures on the car's regular pixels. Shot noise at the "
           f"diagnosis' N_e plus such a jitter of relative SD {jitter:.2g} (from the gap between the car's two "
           "readings: 1/N_e here - 1/N_e of the diagnosis = 2 SD^2) reads "
           + (f"{_ne(jittered[0])} here and {_fmt(jittered[1])} in the diagnosis, against the car's {_ne(car_m)} "
              f"and {_fmt(car_d)}. " if jitter > 0 else "- (no gap). ")
           + "Shot noise alone cannot give the car both its single-interval variance and that growth; the "
           "sensor model's `threshold_jitter` is this noise, and the section above fits it with the shot noise "
           "to both recordings"
           + (" (the diagnosis names no shot noise on the moving low-light image)."
              if "shot_noise" not in results["lowlight_diagnosis"].detected else "."), "", held, ""]


CAR_BANDS = 8  # row bands of the car's background, each fitted on its own (study_car_bands)


def _chi2_sf_even(x: float, dof: int) -> float:
    """P(chi2 > x) for an even number of degrees of freedom: exp(-x/2) sum_{k < dof/2} (x/2)^k / k!."""
    term, total = 1.0, 1.0
    for k in range(1, dof // 2):
        term *= (x / 2.0) / k
        total += term
    return math.exp(-x / 2.0) * total


def study_car_bands(real, md, results):
    """Section: the car's static background, band of rows by band of rows: the joint fit's statistics
    and each band's own fit, and the preset's chi-square against each band (one sensor has one
    temporal noise in every row; a scene need not)."""
    from spikegen.fidelity import drift

    car = read_spikes(real / "car_500frames_250x400.npz")
    T, H, W = car.shape
    static = results["car_static"].reshape(H, W)
    e, jit = results["electrons"], results["jitter"]
    rows, total, parts = [], 0.0, []
    for b in range(CAR_BANDS):
        r0, r1 = b * H // CAR_BANDS, (b + 1) * H // CAR_BANDS
        mask = np.zeros((H, W), bool)
        mask[r0:r1] = static[r0:r1]
        rec = {"band": (car, mask.reshape(-1))}
        data = drift.timing_data(rec)
        own = drift.matched_timing_noise(rec, data=data)
        against = drift.timing_chi2(rec, e, jit, data=data)["band"]
        total += against
        m, mc = own.measured["band"], own.measured_cov["band"]
        se = own.standard_errors
        parts.append((r0, r1, int(mask.sum()), m, mc, against))
        rows.append((f"{r0}-{r1 - 1}", int(mask.sum()), f"{m[0]:.3g} / {m[1]:.3g}",
                     f"{math.sqrt(mc[0, 0]):.2g} / {math.sqrt(mc[1, 1]):.2g}",
                     f"{own.inverse_electrons:.3g} +- {se[0]:.2g}", f"{own.jitter_variance:.3g} +- {se[1]:.2g}",
                     f"{own.chi2['band']:.3g}", f"{against:.3g}"))
    dof = 2 * CAR_BANDS
    p = _chi2_sf_even(total, dof)
    n_all = sum(q[2] for q in parts)
    var_all = sum(q[2] * q[3][0] for q in parts)
    cov_all = sum(q[2] * q[3][1] for q in parts)
    top = max(parts, key=lambda q: q[2] * q[3][0])
    positive = [q for q in parts if q[3][1] > 3 * math.sqrt(q[4][1, 1])]
    rest_cov = (cov_all - top[2] * top[3][1]) / (n_all - top[2])
    md += ["## The car's background, row band by row band", "",
           f"The preset's joint fit pools the car's static background. One sensor has one temporal noise in every "
           f"row; a scene need not. The same statistics and fit (`drift.matched_timing_noise`) on each of "
           f"{CAR_BANDS} bands of {H // CAR_BANDS} or {H // CAR_BANDS + 1} rows of that background, alone (the fit "
           "lets sigma^2 go below 0, where the lag-1 autocovariance is above what shot noise gives), and the "
           f"chi-square (2 degrees of freedom) of the preset ({preset_label(results)}) against each band:", "",
           table(rows, ["rows", "pixels", "measured variance / lag-1 autocovariance (x rate^2)", "SE",
                        "own fit 1/N_e", "own fit sigma^2", "chi2, own fit", "chi2, the preset"]), "",
           f"**No one parameter set explains the car's background band by band**: the preset scores chi2 = "
           f"{total:.4g} on {dof} degrees of freedom over the bands (p = {p:.2g}), where it scores "
           f"{results['timing'].chi2['car']:.3g} on 2 against the pooled background. Rows {top[0]}-{top[1] - 1} "
           f"({100 * top[2] / n_all:.0f} % of the pixels) hold {100 * top[2] * top[3][0] / var_all:.0f} % of the "
           f"background's variance beyond the ideal sensor's and {100 * top[2] * top[3][1] / cov_all:.0f} % of its "
           f"lag-1 autocovariance (x rate^2); without them the rest averages a lag-1 autocovariance of "
           f"{rest_cov:+.3g}"
           + (", above zero: the pooled fit's threshold jitter (its negative lag-1 autocovariance) comes from that "
              "one band." if rest_cov > 0 else ".")
           + (f" Bands with a lag-1 autocovariance more than 3 SE above zero (rows "
              + ", ".join(f"{q[0]}-{q[1] - 1}" for q in positive)
              + ") have consecutive intervals that vary together: neither shot noise (about 0) nor the threshold "
              "jitter (below 0) makes that; a change of the pixels' light or gain slower than an interval does."
              if positive else "")
           + " These recordings are scenes, not flat fields: what varies from band to band may be the scene's "
           "(its light, or the camera's motion on its edges) or the sensor's rows; they cannot tell which. The "
           "preset keeps the pooled fit, the average of the background's temporal noise; a flat-field recording "
           "would calibrate the sensor's own.", ""]


# ---------------------------------------------------------------------- 1. timing regularity
def study_timing(real, md, results):
    car = read_spikes(real / "car_500frames_250x400.npz")
    T = car.shape[0]
    r1, r2 = car[: T // 2].mean(0), car[T // 2:].mean(0)
    static = (np.abs(r1 - r2) <= 0.1 * np.maximum(r1, r2)) & (r1 > 0.01) & (np.maximum(r1, r2) < 0.9)
    meas = regularity(car, static)
    x = np.minimum(car.mean(0), 1.0)  # radiance that makes the ideal sensor fire at the measured rate (I = 256)
    diag = diagnose(car, "self", 256.0)
    shot = diag.effect("shot_noise")
    electrons = shot.parameters.get("electrons") or math.inf
    results["car_diagnosis"] = diag
    preset = results["electrons"]
    sims = {
        "ours, ideal (no temporal noise)": Sensor(name="ideal"),
        f"ours, {preset_label(results)} (fit to both recordings)": preset_sensor(results),
        "paper's reference generator (rsir)": Sensor(name="rsir", kind="rsir"),
    }
    rows = [("measured (car, static background)", f"{meas['rate'].size}", pct(np.mean(meas["range"] <= 1)),
             f"{np.median(meas['cv']):.4f}", pct(np.mean(meas["ones"]))) ]
    series = {"measured": meas}
    for label, sensor in sims.items():
        s = simulate(x, 256.0, sensor, frames=T, seed=SEED)
        reg = regularity(s, static)
        series[label] = reg
        rows.append((label, f"{reg['rate'].size}", pct(np.mean(reg["range"] <= 1)), f"{np.median(reg['cv']):.4f}",
                     pct(np.mean(reg["ones"]))))

    def draw(ax):
        bins = np.geomspace(0.01, 1, 25)
        for label, reg in series.items():
            idx = np.digitize(reg["rate"], bins)
            med = [np.median(reg["cv"][idx == i]) if np.sum(idx == i) > 20 else np.nan for i in range(1, len(bins))]
            ax.loglog(np.sqrt(bins[1:] * bins[:-1]), np.maximum(med, 1e-4), "o-", ms=3, label=label)
        ax.set_xlabel("rate (spikes / frame)")
        ax.set_ylabel("median ISI coefficient of variation")
        ax.legend(fontsize=7)

    path = fig("timing_cv.png", draw)
    md += ["## 1. Timing regularity: the static background of the car recording", "",
           f"`car_500frames_250x400.npz` ({T} frames). Static pixels: rate in the two halves within 10 % and "
           f"below 0.9 ({pct(static.mean())} of the frame). The same radiance (the measured rate, so that an "
           "ideal pixel fires at it) is simulated with each generator; statistics over pixels with >= 5 intervals.",
           "", table(rows, ["stream", "pixels", "ISI range <= 1 frame", "median ISI CV", "1-frame ISIs"]), "",
           f"![ISI CV against rate]({path})", "",
           f"Fitted photo-electrons per threshold (the `shot_noise` estimator of `spikegen diagnose`, radiance "
           f"`self`): N_e = {electrons:.4g} (z = {shot.z:.3g}), from the growth of the interval variance over spans "
           "of intervals; the variance and lag-1 autocovariance of both recordings' intervals give "
           f"{preset_label(results)} (\"Shot noise and threshold jitter, measured alike on both recordings\" "
           "below). A real pixel is almost as regular "
           "as the noise-free integrate-and-fire model; the paper's reference generator (a Poisson gray level every "
           "frame plus U(0,1) interval noise) is far noisier than the camera.", ""]


# ---------------------------------------------------------------------- 2. BIT maps
def study_maps(real, md, results):
    with np.load(real / "bit_camera_calibration_250x400.npz") as z:
        nl, nd = z["Nl"].astype(np.float64), z["Nd"].astype(np.float64)
    R = nl / np.median(nl)
    H, W = R.shape
    yy, xx = np.mgrid[0:H, 0:W]
    u, v = (xx - (W - 1) / 2) / ((W - 1) / 2), (yy - (H - 1) / 2) / ((H - 1) / 2)
    A = np.stack([u ** i * v ** j for i in range(5) for j in range(5 - i)], axis=-1).reshape(-1, 15)
    logr = np.log(R).reshape(-1)
    coef, *_ = np.linalg.lstsq(A, logr, rcond=None)
    smooth = np.exp(A @ coef).reshape(H, W)
    res = R / smooth
    col = np.median(res, axis=0)
    row = np.median(res, axis=1)
    pix = res / col[None, :] / row[:, None]
    ref_paper = np.unravel_index(np.argmin(np.abs(nl - nl.mean())), nl.shape)
    # what the normalisation does to brightness: R relative to pixel (0,0) vs median 1
    rel00 = nl / nl[0, 0]
    dark_to_rate = 1.0  # shown in lux
    rows = [("R (median 1): 1st-99th percentile", f"{np.percentile(R, 1):.3f} - {np.percentile(R, 99):.3f}"),
            ("R min / max", f"{R.min():.3f} / {R.max():.3f}"),
            ("smooth vignetting (degree-4 fit), range", f"{smooth.min():.3f} - {smooth.max():.3f}"),
            ("column factors, std", f"{np.std(col):.4f}"), ("row factors, std", f"{np.std(row):.4f}"),
            ("per-pixel spread (robust std of the rest)", f"{stats.robust_sd(pix):.4f}"),
            ("pixels > 5 robust std from their smooth value (dust)", f"{int(np.sum(np.abs(pix - 1) > 5 * stats.robust_sd(pix)))}"),
            ("dark current L_d median (lux-eq)", f"{np.median(nd):.3f}"),
            ("L_d 99th percentile / max", f"{np.percentile(nd, 99):.2f} / {nd.max():.1f}"),
            ("hot pixels (L_d > 60 lux-eq)", f"{int(np.sum(nd > 60))}"),
            ("corr(R, L_d) (Spearman)", f"{_spearman(R, nd):.3f}"),
            ("pixel (0,0): response / median", f"{nl[0, 0] / np.median(nl):.4f}"),
            (f"paper's reference pixel {tuple(int(i) for i in ref_paper)} (closest to the average): response / median",
             f"{nl[ref_paper] / np.median(nl):.4f}"),
            ("mean R if normalised to pixel (0,0) (i.e. simulated brightness factor)", f"{rel00.mean():.4f}"),
            ("mean R, normalised to median 1", f"{R.mean():.4f}")]
    results["bit_R"] = R

    def draw(ax):
        im = ax.imshow(R, cmap="magma", vmin=np.percentile(R, 0.5), vmax=np.percentile(R, 99.5))
        ax.figure.colorbar(im, ax=ax, label="R (median 1)")
        ax.set_title("BIT camera responsivity")

    p1 = fig("bit_responsivity.png", draw, (6, 4))

    def draw2(ax):
        ax.hist(nd.reshape(-1), bins=np.geomspace(max(nd.min(), 0.1), nd.max() + 1, 60), log=True)
        ax.set_xscale("log")
        ax.axvline(60, color="r", lw=0.8)
        ax.set_xlabel("dark current L_d (lux-equivalent)")
        ax.set_ylabel("pixels")

    p2 = fig("bit_dark.png", draw2)
    md += ["## 2. The BIT calibration maps", "", "`bit_camera_calibration_250x400.npz`: `Nl` (responsivity "
           "relative to pixel (0,0)), `Nd` (dark current, lux-equivalent).", "", table(rows, ["statistic", "value"]),
           "", f"![responsivity]({p1})", "", f"![dark current]({p2})", "",
           f"Pixel (0,0) responds {nl[0, 0] / np.median(nl):.3f} x the median pixel. Normalising R to it, as one "
           f"public implementation does, gives every pixel R / R(0,0): mean {rel00.mean():.3f}, so every simulated "
           f"stream is {100 * (1 - rel00.mean()):.0f} % darker (fewer spikes) than the intensity says. The paper's "
           f"rule (reference = the pixel closest to the average response) picks a pixel at "
           f"{nl[ref_paper] / np.median(nl):.4f} x the median, i.e. agrees with the median-1 convention the "
           "project uses (`spikegen calibrate` applies the paper's rule, then normalises to median 1).", ""]


def _spearman(a, b):
    ra = np.argsort(np.argsort(a.reshape(-1))).astype(np.float64)
    rb = np.argsort(np.argsort(b.reshape(-1))).astype(np.float64)
    return float(np.corrcoef(ra, rb)[0, 1])


# ---------------------------------------------------------------------- held-out score of the real recordings
REAL_RECORDINGS = (("car_100kmh_250x400.dat", (400, 250)), ("car_500frames_250x400.npz", None),
                   ("uhsr_lowlight_250x250.npz", None))


def _z(better, worse) -> float:
    """The summed per-pixel difference of two held-out scores over its standard error
    (HeldOutScore.improvement); 0 where the two do not differ."""
    g, se = better.improvement(worse)
    return g / se if se > 0 else 0.0


def study_heldout(real, md, results):
    """`spikegen diagnose --reference self` on every real recording: the held-out score of the
    ideal and the fitted sensor, what was kept, and what stays unexplained; and the held-out gain of
    the temporal noise fitted to both spike recordings of scenes (the preset's, estimate_electrons)
    over the ideal sensor, on every recording (diagnose.score_sensor; z of the summed per-pixel
    differences, HeldOutScore.improvement)."""
    from spikegen.fidelity.diagnose import score_sensor

    rows = []
    for name, size in REAL_RECORDINGS:
        spikes = read_spikes(real / name, size=size)
        d = diagnose(spikes, "self", 256.0)
        h = d.heldout
        kept = ", ".join(f"{n} ({h['effects'][n]['gain_nats']:.3g} nats)" for n in d.detected) or "none"
        noise = score_sensor(spikes, "self", 256.0, preset_sensor(results, "shot"))
        ideal = score_sensor(spikes, "self", 256.0, Sensor(name="shot"))
        results.setdefault("heldout_scores", {})[name] = (noise, ideal)  # (study_joint reuses them)
        per_px = noise.mean - ideal.mean  # nats per judged pixel
        z = _z(noise, ideal)
        rows.append((name, f"{d.info['static_pixels']} / {d.info['moving_pixels']} / {d.info['untested_pixels']}",
                     f"{h['ideal']:.4g}",
                     f"{h['fitted']:.4g}", kept, ", ".join(u["statistic"] for u in d.unexplained) or "none",
                     f"{per_px:+.3g} (z = {z:+.1f})"))
    md += ["## Held-out score of the real recordings", "",
           f"`spikegen diagnose --reference self` (I = 256). Score: {h['measure']}; higher is better. With a "
           "still reference a pixel's held-out intervals are scored by the probability of their whole-frame "
           f"values among the simulated intervals of the {heldout.POOL_PIXELS} judged pixels of nearest drive "
           "under the model, its counts by a Gaussian with the variance pooled by simulated rate "
           "(`spikegen.fidelity.heldout`; until 2026-11-26 the intervals too by a Gaussian of the pixel's own "
           "simulated mean and variance, at least 1/12: with those, seeded recordings with shot noise scored "
           "their true model below the ideal sensor). With a reference that moves (the low light's), the same "
           f"on the judged pixels whose reference stays within {heldout.QUASI_STILL:.0%} of its mean, the others' "
           "intervals by that Gaussian; every judged pixel's counts are predicted as its simulated rate times "
           "the reference's course in time (until the second change of 2026-11-26, by one simulated draw). Only "
           "static pixels are judged (a pixel moves when its counts or its mean intervals in 8 segments disagree "
           "beyond their noise, its mean intervals drift or step, or its consecutive intervals differ more than "
           "the other static pixels' temporal noise lets them; one with too few spikes for the tests is "
           "untested; `spikegen.fidelity.heldout.motion_test`). An effect is reported only "
           "if it raises this score by more than its penalty. Last column: the same score under the ideal "
           f"sensor plus the temporal noise fitted to both recordings of scenes ({preset_label(results)}; "
           "\"Shot noise and threshold jitter, measured alike on both recordings\" below) less that under the "
           "ideal sensor, nats per pixel, and its z (the summed per-pixel differences over their standard error): "
           "the noise's gain on each recording's held-out frames, the 200-frame car `.dat`, which the fit did not "
           "use, included.", "",
           table(rows, ["recording", "static / moving / untested pixels", "ideal", "fitted", "kept effects (gain)",
                        "unexplained", "the fitted noise − ideal (z)"]), ""]


# ---------------------------------------------------------------------- one temporal-noise parameter for both?
JOINT_GRID = (30.0, 100.0, 300.0, 1000.0, 3000.0, 1e4, 3e4, 1e5, math.inf)  # N_e tried besides the fitted ones
JOINT_RECORDINGS = (("car", "car_500frames_250x400.npz", "car_diagnosis"),
                    ("low light", "uhsr_lowlight_250x250.npz", "lowlight_diagnosis"))


def study_joint(real, md, results):
    """The held-out score (diagnose.score_sensor, `self`) of the car's static background and of
    the low-light recording under shot noise of each N_e: each recording's own fit (its diagnosis),
    the other's, the preset's (estimate_electrons), and the N_e best on both (the largest sum of
    the two scores, nats per pixel, over the grid); then how the interval noise depends on the
    rate, measured and under shot noise of the preset's N_e (fit to both recordings)."""
    from spikegen.fidelity.diagnose import score_sensor

    data = {label: read_spikes(real / name) for label, name, _ in JOINT_RECORDINGS}
    own = {label: results[key].effect("shot_noise").parameters.get("electrons") or math.inf
           for label, _, key in JOINT_RECORDINGS}
    preset = results["electrons"]
    grid = sorted(set(JOINT_GRID) | set(own.values()) | {preset})
    # the fitted noise's and the ideal sensor's (N_e = inf) scores: those study_heldout made of the same recordings
    made = {label: results["heldout_scores"][name] for label, name, _ in JOINT_RECORDINGS}
    graded = {label: {e: made[label][1] if math.isinf(e) else
                      score_sensor(s, "self", 256.0, Sensor(name="shot", electrons=e)) for e in grid}
              for label, s in data.items()}
    scores = {label: {e: sc.mean for e, sc in by_e.items()} for label, by_e in graded.items()}
    shared = max(grid, key=lambda e: sum(scores[label][e] for label in data))
    fitted = {label: made[label][0].mean for label in data}
    fitted_z = {label: _z(*made[label]) for label in data}  # the fitted noise against the ideal sensor
    car, low = (label for label, _, _ in JOINT_RECORDINGS)
    rows = []
    for label, other in ((car, low), (low, car)):
        best = max(grid, key=lambda e: scores[label][e])
        rows.append((label, _ne(own[label]), f"{scores[label][own[label]]:.4g}", f"{scores[label][own[other]]:.4g}",
                     f"{scores[label][preset]:.4g}", f"{fitted[label]:.4g}", f"{scores[label][shared]:.4g}",
                     f"{_ne(best)} ({scores[label][best]:.4g})"))
    grid_rows = [(_ne(e),) + tuple(f"{scores[label][e]:.4g}" for label in data) +
                 (f"{sum(scores[label][e] for label in data):.4g}",) for e in grid]
    md += ["## One temporal-noise parameter for both recordings?", "",
           "Held-out score (the measure of the table above, `spikegen.fidelity.diagnose.score_sensor`, `self`, "
           "I = 256) of each recording under the ideal sensor plus shot noise of N_e photo-electrons per threshold "
           "(inf: none). Shared N_e: the one of the grid below with the largest sum of the two scores "
           f"({_ne(shared)}).", "",
           table(rows, ["recording", "own fit N_e (its diagnosis)", "score, own N_e", "score, the other's N_e",
                        f"score, N_e = {_ne(preset)} alone", f"score, {preset_label(results)} (fit to both)",
                        f"score, shared N_e = {_ne(shared)}",
                        "best N_e of the grid (score)"]), "",
           table(grid_rows, ["N_e", *[f"{label} score" for label in data], "sum"]), ""]
    md += _rate_dependence(data, preset)
    loss = {label: scores[label][own[label]] - scores[label][own[other]] for label, other in ((car, low), (low, car))}
    md += [f"Under the other's N_e rather than its own, the car scores {_change(-loss[car])} and the low light "
           f"{_change(-loss[low])} nats per pixel. Shot noise, a threshold jitter whose reset subtracts the "
           "threshold it fired at, and dark-current shot noise (the dark charge is in the Poisson charge the model "
           "draws) all give the same interval CV at every rate and independent intervals (the sensor's "
           "`threshold_jitter`, whose reset subtracts the nominal threshold, anti-correlated ones: \"Shot noise and "
           "threshold jitter, measured alike on both recordings\" below); the table above shows whether a recording's 1/N_e equivalent changes with the "
           "rate and whether its consecutive intervals are correlated, and the last table whether its rate changes "
           "row by row over the recording (the low-light scene is a displayed image).", ""]
    results["joint"] = {"own": own, "shared": shared, "scores": scores, "fitted": fitted, "fitted_z": fitted_z}


def _change(x) -> str:
    """``x`` nats as a signed change in words."""
    return f"{abs(x):.3g} higher" if x > 0 else (f"{abs(x):.3g} lower" if x < 0 else "the same")


def _ne(e):
    return "inf" if math.isinf(e) else f"{e:.4g}"


def _rate_dependence(data, electrons, bins=5):
    """Per rate bin (quantiles of the static pixels with >= 8 intervals): median interval CV,
    median lag-1 correlation of consecutive intervals and the mean per-pixel 1 / N_e equivalent
    ``(excess variance measured - ideal simulation) x lambda^2`` (stats.excess_interval_var; shot
    noise and threshold jitter both make it the same at every rate), measured and simulated with
    shot noise of ``electrons``."""
    from spikegen.fidelity.heldout import static_pixels

    rows = []
    for label, s in data.items():
        T = s.shape[0]
        x = np.minimum(s.mean(0), 1.0)
        noisy_sensor = Sensor(electrons=0.0 if math.isinf(electrons) else electrons)
        streams = {"measured": s,
                   f"shot noise N_e = {_ne(electrons)}": simulate(x, 256.0, noisy_sensor, frames=T, seed=SEED)}
        ideal = stats.pixel_stats(simulate(x, 256.0, Sensor(), frames=T, seed=SEED))
        pm = stats.pixel_stats(s)
        ok = static_pixels(s) & (pm.n_isi >= 8)
        edges = np.quantile(pm.rate[ok], np.linspace(0, 1, bins + 1))
        which = np.clip(np.searchsorted(edges, pm.rate, side="right") - 1, 0, bins - 1)
        for name, stream in streams.items():
            p = stats.pixel_stats(stream)
            noisy = pm.isi_var >= 2.0
            inv = (stats.excess_interval_var(p, noisy) - stats.excess_interval_var(ideal, noisy)) * pm.rate ** 2
            cv = np.sqrt(p.isi_var) / p.isi_mean
            sc = stats.serial_correlation(stream)
            for b in range(bins):
                m = ok & (which == b) & np.isfinite(inv)
                rows.append((label, name, f"{edges[b]:.3f}-{edges[b + 1]:.3f}", f"{np.nanmedian(cv[m]):.3f}",
                             f"{np.nanmedian(sc[m]):+.2f}",
                             f"{inv[m].mean():.2g} +- {inv[m].std() / math.sqrt(max(m.sum(), 1)):.1g}"))
    return ["Interval noise against the rate (static pixels with >= 8 intervals, 5 rate bins of equal counts). "
            "Shot noise (and a threshold jitter whose reset subtracts the threshold it fired at, which accumulates "
            "alike) gives intervals of the same CV at every rate and no correlation beyond the rounding's (negative) "
            "between consecutive intervals; the sensor's `threshold_jitter` (the nominal threshold subtracted) gives "
            "the same CV at every rate too, but consecutive intervals correlated by -1/2.", "",
            table(rows, ["recording", "stream", "rate (spikes/frame)", "median ISI CV", "median lag-1 correlation",
                         "mean 1/N_e equivalent +- SE"]), ""] + _row_change(data)


def _row_change(data, parts=4):
    """How the mean rate changes from the first to the last of ``parts`` equal parts of each
    recording, row by row and column by column: SD over rows (columns) of the relative change of
    the row (column) mean rate, measured and in the ideal sensor's simulation of the same mean
    rates (counting noise alone)."""
    rows = []
    for label, s in data.items():
        T = s.shape[0]
        sim = simulate(np.minimum(s.mean(0), 1.0), 256.0, Sensor(), frames=T, seed=SEED)
        for name, stream in (("measured", s), ("ideal sensor, same mean rates", sim)):
            n = T // parts
            a, b = stream[:n].mean(0, dtype=np.float64), stream[-n:].mean(0, dtype=np.float64)
            sd = [float(np.std((b.mean(axis) - a.mean(axis)) / np.maximum(0.5 * (a.mean(axis) + b.mean(axis)), 1e-9)))
                  for axis in (1, 0)]
            rows.append((label, name, f"{sd[0]:.4f}", f"{sd[1]:.4f}"))
    return [f"Change of the mean rate from the first to the last {100 // parts} % of the frames, by rows and by "
            "columns (SD over rows or columns of the relative change of their mean rate):", "",
            table(rows, ["recording", "stream", "SD over rows", "SD over columns"]), ""]


# ---------------------------------------------------------------------- 3. saturation
def study_saturation(real, md, results):
    car = read_spikes(real / "car_100kmh_250x400.dat", size=(400, 250))
    T = car.shape[0]
    rate = car.mean(0)
    h1, h2 = car[: T // 2].mean(0), car[T // 2:].mean(0)
    bright = (rate >= 0.4) & (np.abs(h1 - h2) <= 0.05)  # bright and static (the car moves through)
    meas = regularity(car, bright)
    x = np.minimum(rate, 1.0)
    rows = [("measured (car .dat, static pixels with rate >= 0.4)", pct(np.mean(meas["isi"] == 1)),
             f"{np.mean(rate >= 0.95) * 100:.2f} %", f"{rate.max():.3f}")]
    for label, sensor in (("ours (ideal)", Sensor()), ("ours, refractory 1 frame", Sensor(refractory_frames=1)),
                          ("paper's reference generator (rsir)", Sensor(kind="rsir"))):
        s = simulate(x, 256.0, sensor, frames=T, seed=SEED)
        reg = regularity(s, bright)
        r = s.mean(0)
        rows.append((label, pct(np.mean(reg["isi"] == 1)) if reg["isi"].size else "-", f"{np.mean(r >= 0.95) * 100:.2f} %",
                     f"{r.max():.3f}"))
    md += ["## 3. Saturation and consecutive-frame spikes", "",
           f"`car_100kmh_250x400.dat` ({T} frames), {pct(bright.mean())} of pixels fire at >= 0.4 spikes/frame "
           "with the same rate in both halves (static). "
           "Each generator sees the radiance that makes an ideal pixel fire at the measured rate.", "",
           table(rows, ["stream", "1-frame ISIs among bright pixels", "pixels at >= 0.95 spikes/frame", "max rate"]),
           "", "Bright pixels fire on consecutive frames, so the readout has no dead frame: `refractory` is "
           "absent, and the rate saturates at one spike per frame (the `A = min(A, 1)` clamp).", ""]


# ---------------------------------------------------------------------- 4. low light
def study_lowlight(real, md, results):
    uh = read_spikes(real / "uhsr_lowlight_250x250.npz")
    T = uh.shape[0]
    p = stats.pixel_stats(uh)
    rate_count = uh.reshape(T, -1).mean(0)
    diag = diagnose(uh, "self", 256.0)
    results["lowlight_diagnosis"] = diag
    ok = p.n_isi >= 4
    cv = np.sqrt(p.isi_var[ok]) / p.isi_mean[ok]
    x = np.minimum(uh.mean(0), 1.0)
    rows = [("measured", f"{np.mean(rate_count):.4f}", pct(np.mean(p.n == 0)), f"{np.percentile(rate_count, 1):.4f}",
             f"{np.median(cv):.3f}")]
    for label, sensor in (("ours, ideal", Sensor()),
                          (f"ours, {preset_label(results)} (fit to both recordings)", preset_sensor(results)),
                          ("paper's reference generator (rsir)", Sensor(kind="rsir"))):
        s = simulate(x, 256.0, sensor, frames=T, seed=SEED)
        ps = stats.pixel_stats(s)
        o = ps.n_isi >= 4
        rows.append((label, f"{s.mean():.4f}", pct(np.mean(ps.n == 0)), f"{np.percentile(s.reshape(T, -1).mean(0), 1):.4f}",
                     f"{np.median(np.sqrt(ps.isi_var[o]) / ps.isi_mean[o]):.3f}"))
    shot = diag.effect("shot_noise")
    hot = diag.effect("hot_pixels")
    md += ["## 4. The low-light recording", "",
           f"`uhsr_lowlight_250x250.npz` ({T} frames, mean rate {uh.mean():.4f}).", "",
           "Why: the image of the display moves on the sensor by about 7 rows during the recording; with each "
           "pixel's trend removed, "
           "the pixels the motion hardly changes read the car's N_e (docs/lowlight.md, `python "
           "docs/make_lowlight.py`).", "",
           table(rows, ["stream", "mean rate", "pixels without a spike", "1st percentile rate", "median ISI CV (>= 4 ISIs)"]),
           "", f"`spikegen diagnose --reference self` on it: {_motion_text(diag)}detected "
           f"{', '.join(diag.detected) or 'nothing'}; shot noise N_e = {_fmt(shot.parameters.get('electrons'))} "
           f"(z = {shot.z:.3g}); hot pixels: {hot.parameters.get('found')} found. At low rates the intervals vary "
           "more than the car's background predicts; whether one N_e fits both recordings is measured in "
           "\"One temporal-noise parameter for both recordings?\" and \"Shot noise and threshold jitter, "
           "measured alike on both recordings\" below.", ""]


def _motion_text(diag) -> str:
    """What the diagnosis says of a motion of the whole image (``info["motion"]``, 'self')."""
    m = diag.info.get("motion")
    if not m or not m["whole_image"]:
        return "no motion of the whole image found; "
    return (f"the whole image moves {m['rows']['travel']:+.2f} rows and {m['cols']['travel']:+.2f} columns over "
            f"the {m['frames_measured']} fit frames (the reference moves with it; docs/lowlight.md section 5); ")


def _fmt(v):
    return "-" if v is None else f"{v:.4g}"


# ---------------------------------------------------------------------- gains and the preset
def study_gain(real, md, results):
    """Held-out frames: ideal against the fitted temporal noise, the radiance from the fit frames."""
    rows = []
    for label, path, kw in (("car (500 frames)", "car_500frames_250x400.npz", {}),
                            ("low light (200 frames)", "uhsr_lowlight_250x250.npz", {})):
        s = read_spikes(real / path, **kw)
        T = s.shape[0]
        Tf = int(round(0.8 * T))
        x = np.minimum(stats.window_rate(s[:Tf]).reshape(s.shape[1:]), 1.0)
        sims = {"ideal": simulate(x, 256.0, Sensor(), frames=T, seed=SEED),
                "calibrated noise": simulate(x, 256.0, preset_sensor(results), frames=T, seed=SEED)}
        m = {k: stats.discrepancies(s[Tf:], v[Tf:], x) for k, v in sims.items()}
        for k in stats.MEASURES:
            rows.append((label, k, f"{m['ideal'][k]:.4g}", f"{m['calibrated noise'][k]:.4g}"))
    md += ["## 5. Held-out frames: ideal against the calibrated temporal noise", "",
           "Radiance estimated from the first 80 % of the frames (static scenes: `self`), streams simulated "
           f"for all frames with the ideal sensor and with the fitted noise, {preset_label(results)} (fit to both "
           "recordings); the "
           "named measures (`spikegen.fidelity.stats.MEASURES`) on the last 20 %.", "",
           table(rows, ["recording", "measure", "ideal", preset_label(results)]), "",
           "`spikegen diagnose --reference self` on the same recordings:", ""]
    for label, key in (("car", "car_diagnosis"), ("low light", "lowlight_diagnosis")):
        d = results[key]
        found = ", ".join(f"{n} ({_short(d.effect(n).parameters)})" for n in d.detected) or "nothing"
        md.append(f"- {label}: detected {found}.")
    md += ["", "With `--reference self` the hot-pixel count is an upper bound: fine scene texture that a 3 x 3 "
           "median does not follow is counted too (the BIT calibration, which needs no scene, finds 27 hot "
           "pixels in 100 000). " + _lowlight_sentence(results), ""]


def _lowlight_sentence(results) -> str:
    """Whether the low-light diagnosis asks for more temporal noise than the car's."""
    if "shot_noise" in results["lowlight_diagnosis"].detected:
        return ("The low-light recording asks for more temporal noise than the car's background (the "
                "`shot_noise` estimate above against the car's).")
    return ("On the low-light recording the diagnosis names no temporal noise: with the image's motion in the "
            "reference, the ideal sensor explains its intervals; the held-out scores of both recordings under "
            "one N_e are in \"One temporal-noise parameter for both recordings?\" below.")


def _short(params):
    return ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in params.items()
                     if v is not None and k in ("sigma", "count", "electrons", "depth", "period_frames", "frames"))


def synthetic_envelope(md, draws=3):
    """Detection rate and parameter error on hidden effects (the tests' protocol, more draws)."""
    rows = []
    for name in list(synth.EFFECTS) + ["none"]:
        hits, errs = 0, []
        for seed in range(100, 100 + draws):
            names = [] if name == "none" else [name]
            spikes, x, intensity, eff = synth.hidden_case(names, seed)
            d = diagnose(spikes, x, intensity)
            if name == "none":
                hits += d.detected == []
                continue
            hits += d.detected[:1] == [name]
            key, true = synth.true_value(name, eff[name])
            if key:
                est = d.effect(name).parameters.get(key)
                errs.append(abs(est - true) / true if est is not None else math.inf)
        rows.append((name, f"{hits}/{draws}", f"{100 * max(errs):.1f} %" if errs else "-"))
    pair_hits, pair_n, pair_bad = 0, 2 * draws * 2, []
    for k in range(pair_n):
        names = synth.draw_pair(np.random.default_rng(9000 + k))
        spikes, x, intensity, eff = synth.hidden_case(names, 500 + k)
        d = diagnose(spikes, x, intensity)
        ok = True
        for name in names:
            key, true = synth.true_value(name, eff[name])
            est = d.effect(name).parameters.get(key) if key else None
            ok &= name in d.detected and (key is None or (est is not None and abs(est - true) <= 0.2 * abs(true)))
        pair_hits += ok
        if not ok:
            pair_bad.append(f"{'+'.join(names)} at I = {intensity:.0f} (detected: {', '.join(d.detected)})")
    md += ["## 7. Synthetic check: hidden effects inside the envelope", "",
           f"{draws} seeded draws per effect (64 x 64, 1000 frames, intensity 32-256, radiance 0.05-1; "
           "`spikegen.fidelity.synth`, other seeds than the tests): named first / largest parameter error.", "",
           table(rows, ["effect", "named first", "max parameter error"]), "",
           f"Random pairs (`synth.draw_pair`, all pairs but the known confusion reset_to_zero + shot_noise): "
           f"{pair_hits}/{pair_n} with both found and both parameters within 20 %."
           + (" Misses: " + "; ".join(pair_bad) + "." if pair_bad else ""), ""]


# ---------------------------------------------------------------------- envelope of the newer effects
NEW_ENVELOPE_JSON = FIG / "envelope_new.json"
NEW_ENVELOPE_SEEDS = (300, 301, 302)
# effect -> (parameter varied, its values, the other parameters); 0: the effect absent
NEW_ENVELOPE_GRID = {
    "dark_current spread": ("spread", (0.0, 0.1, 0.2, 0.3, 0.5), {"rate": 0.005}),
    "dead_pixels": ("count", (0, 1, 2, 3, 5), {}),
    "threshold_jitter": ("sigma", (0.0, 0.006, 0.008, 0.011, 0.016), {}),
}


def _new_envelope_case(effect: str, value: float, fixed: dict, seed: int):
    """``(spikes, radiance, intensity, named, estimate, other effects named)`` of one draw."""
    rng = np.random.default_rng(seed)
    intensity = float(math.exp(rng.uniform(math.log(32), math.log(256))))
    x = synth.test_radiance(64, 64, rng)
    if effect.startswith("dark_current"):
        effects, name = {"dark_current": {**fixed, "spread": value}}, "dark_current"
    elif effect == "dead_pixels":
        effects, name = ({"dead_pixels": {"count": int(value)}} if value else {}), "dead_pixels"
    else:  # Sensor(threshold_jitter=sigma)
        effects, name = ({"threshold_jitter": {"sigma": value}} if value else {}), "threshold_jitter"
    spikes = simulate(x, intensity, synth.make_sensor(effects, 64, 64, rng), frames=1000, seed=seed + 1)
    d = diagnose(spikes, x, intensity)
    eff = d.effect(name)
    if name == "dark_current":
        named = eff.detected and bool(eff.parameters.get("spread"))
        estimate = eff.parameters.get("spread") if named else None
    elif name == "dead_pixels":
        named, estimate = eff.detected, eff.parameters.get("count") if eff.detected else None
    else:
        named = eff.detected
        estimate = eff.parameters.get("sigma") if named else None
    others = sorted(n for n in d.detected if n != name)
    return intensity, bool(named), estimate, others


def measure_new_envelope() -> dict:
    """Every value of NEW_ENVELOPE_GRID on every seed of NEW_ENVELOPE_SEEDS: whether the effect
    is named, its estimate, and the other effects named."""
    out = {"seeds": list(NEW_ENVELOPE_SEEDS), "size": [64, 64, 1000], "effects": {}}
    for effect, (key, values, fixed) in NEW_ENVELOPE_GRID.items():
        rows = []
        for value in values:
            for seed in NEW_ENVELOPE_SEEDS:
                intensity, named, estimate, others = _new_envelope_case(effect, value, fixed, seed)
                rows.append({"value": value, "seed": seed, "intensity": round(intensity, 3), "named": named,
                             "estimate": None if estimate is None else round(float(estimate), 6), "others": others})
                print(f"{effect} {key}={value} seed {seed}: named {named} estimate {estimate} others {others}",
                      flush=True)
        out["effects"][effect] = {"parameter": key, "fixed": fixed, "rows": rows}
    return out


def new_envelope(md):
    """The table of the newer effects' envelope from NEW_ENVELOPE_JSON (measure_new_envelope,
    written by --measure-envelope)."""
    if not NEW_ENVELOPE_JSON.is_file():
        sys.exit(f"make_fidelity: {NEW_ENVELOPE_JSON} is missing; run with --measure-envelope first")
    res = json.loads(NEW_ENVELOPE_JSON.read_text())
    seeds = len(res["seeds"])
    rows, summary = [], []
    for effect, entry in res["effects"].items():
        key = entry["parameter"]
        values = sorted({r["value"] for r in entry["rows"]})
        always, never = None, []
        for v in values:
            rs = [r for r in entry["rows"] if r["value"] == v]
            n = sum(r["named"] for r in rs)
            est = [r["estimate"] for r in rs if r["estimate"] is not None]
            others = sorted({o for r in rs for o in r["others"]})
            rows.append((effect, f"{key} = {v:g}", f"{n}/{len(rs)}", f"{np.median(est):.4g}" if est else "-",
                         ", ".join(others) or "none"))
            if n == len(rs) and always is None and v > 0:
                always = v
            if n == 0:
                never.append(v)
        summary.append(f"`{effect}`: named on every seed from {key} = {always:g}" if always is not None
                       else f"`{effect}`: not named on every seed at any {key} tried")
        summary[-1] += (f"; named on no seed at {key} <= {max(never):g}" if never else "; named on some seed at every value")
    fixed = "; ".join(f"{e}: {', '.join(f'{k} = {v:g}' for k, v in d['fixed'].items())}"
                      for e, d in res["effects"].items() if d["fixed"])
    md += ["## Detectability envelope of the newer effects", "",
           f"Each effect alone at each strength on the same {seeds} seeds ({res['seeds'][0]}-{res['seeds'][-1]}: "
           f"the seed draws the intensity, log-uniform in 32-256, the textured reference and the maps; "
           f"{res['size'][0]} x {res['size'][1]} pixels, {res['size'][2]} frames; fixed: {fixed}). "
           "Named: `dark_current` detected with a spread > 0; `dead_pixels` detected; `threshold_jitter` "
           "detected (simulated as `Sensor(threshold_jitter=sigma)`: a firing level of relative SD sigma drawn "
           "anew after each spike, which does not accumulate, unlike shot noise). "
           "Estimate: the median over the seeds that named it. Other effects named: any other effect "
           "reported on some seed (a false name). Measured by `python docs/make_fidelity.py "
           f"--measure-envelope` into `docs/fidelity/{NEW_ENVELOPE_JSON.name}`.", "",
           table(rows, ["effect", "strength", "named", "estimate", "other effects named"]), "",
           *[f"- {line}." for line in summary], ""]


def keep_preset(results, md):
    """--no-preset: the preset as committed, beside this run's fit."""
    from spikegen.sensorfile import load_sensor

    kept = load_sensor(REPO / "assets" / "calibrated.json")
    md += ["## 6. The `calibrated` preset (not refitted by this run)", "",
           f"`assets/calibrated.json` keeps N_e = {kept.electrons:.4g} photo-electrons per threshold and threshold "
           f"jitter SD {kept.threshold_jitter:.3g} (`paper` maps, no refractory period, subtractive reset, no "
           "flicker); this run's fit on both recordings (\"Shot noise and threshold jitter, measured alike on "
           f"both recordings\") gives {preset_label(results)}. Run without `--no-preset` to "
           "write it (the golden conversion digests that use the preset change with it).", ""]


def write_preset(results, md):
    from spikegen.presets import get_sensor
    from spikegen.sensorfile import save_sensor

    e = results["electrons"]
    paper = get_sensor("paper", 250, 400)
    notes = {"fitted_by": "docs/make_fidelity.py",
             "electrons_from": "car_500frames_250x400.npz static background and uhsr_lowlight_250x250.npz pixels "
                               "its motion hardly changes (drift.matched_timing_noise: electrons and "
                               "threshold_jitter together)",
             "maps": "BIT camera calibration (paper preset)"}
    sensor = paper.replace(name="calibrated", electrons=float(e) if math.isfinite(e) else 0.0,
                           threshold_jitter=results["jitter"], notes=notes)
    json_path, npz_path = save_sensor(sensor, REPO / "assets" / "calibrated")
    md += ["## 6. The `calibrated` preset", "",
           f"`paper` (BIT maps, R median 1) plus shot noise with N_e = {sensor.electrons:.4g} photo-electrons per "
           f"threshold and a threshold jitter of relative SD {sensor.threshold_jitter:.3g}, fitted to both "
           "recordings (\"Shot noise and threshold jitter, measured alike on both recordings\" above); no "
           "refractory period, subtractive reset, no flicker (none was found). "
           f"Written to `assets/{json_path.name}` + `assets/{npz_path.name}` "
           f"({(json_path.stat().st_size + npz_path.stat().st_size) / 1e6:.2f} MB).", ""]


def downstream_proxy(data, md, views=6, intensity=64.0):
    """The gain downstream, small form: images reconstructed from spikes made with the calibrated
    sensor, once inverting with the matching sensor (R, d) and once with the baseline (R = 1, d = 0)."""
    from spikegen.presets import get_sensor
    from spikegen.recon import rate_to_radiance, tfp
    from spikegen.seeding import view_seed
    from spikegen.spikeio import png_to_radiance, read_png

    lego = data / "nerf_synthetic_lego_400" / "train"
    files = sorted(lego.glob("r_*.png"), key=lambda p: int(p.stem.split("_")[1]))[:views]
    if not files:
        return
    rows, gains = [], []
    for i, f in enumerate(files):
        x, _ = png_to_radiance(read_png(f))
        H, W = x.shape
        sensor = get_sensor("calibrated", H, W)
        spikes = simulate(x, intensity, sensor, frames=256, seed=view_seed(0, "lego", "train", i, intensity))
        rate = tfp(spikes, 256)
        psnr = {}
        for label, sens in (("matching", sensor), ("baseline", None)):
            est = np.clip(rate_to_radiance(rate, intensity, sens), 0, 1)
            psnr[label] = -10 * math.log10(float(np.mean((est - np.clip(x, 0, 1)) ** 2)))
        gains.append(psnr["matching"] - psnr["baseline"])
        rows.append((f.name, f"{psnr['baseline']:.2f}", f"{psnr['matching']:.2f}", f"{gains[-1]:+.2f}"))
    md += ["## 8. The gain downstream (small form)", "",
           f"Not the radiance-field experiment (the trainer needs a GPU for that; see the report): "
           f"{len(files)} lego views ({W} x {H}) made with the `calibrated` sensor at I = {intensity:g}, "
           "256 frames; each image reconstructed by TFP over all frames and inverted with the matching sensor "
           "(its R and d) or with the baseline (R = 1, d = 0). PSNR of linear luminance against the "
           "ground truth.", "", table(rows, ["view", "PSNR baseline (dB)", "PSNR matching (dB)", "gain (dB)"]),
           "", f"Mean gain of using the matching sensor: {np.mean(gains):+.2f} dB.", ""]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--no-preset", action="store_true")
    ap.add_argument("--draws", type=int, default=4)
    ap.add_argument("--measure-envelope", action="store_true",
                    help=f"only measure the newer effects' envelope into {NEW_ENVELOPE_JSON.name}")
    args = ap.parse_args(argv)
    if args.measure_envelope:
        FIG.mkdir(parents=True, exist_ok=True)
        doc = measure_new_envelope()
        write_bytes_atomic(NEW_ENVELOPE_JSON, (json.dumps(doc, indent=1) + "\n").encode("utf-8"))
        print(f"wrote {NEW_ENVELOPE_JSON}")
        return
    real = args.data / "real"
    if not real.is_dir():
        sys.exit(f"make_fidelity: no measured data at {real}")
    FIG.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    md = ["# Fidelity: the simulator against real spike cameras", "",
          "Generated by `python docs/make_fidelity.py` (do not edit by hand). Data: `shared/data/real` "
          "(see its README). Tools: `spikegen diagnose` / `spikegen calibrate` (`spikegen.fidelity`).", "",
          f"Every figure below comes from that one command, run on {time.strftime('%Y-%m-%d', time.gmtime())} "
          f"(load average {load} at its start; RUNTIME_LINE).", ""]
    results = {}
    estimate_electrons(real, results)
    study_timing(real, md, results)
    study_maps(real, md, results)
    study_saturation(real, md, results)
    study_lowlight(real, md, results)
    study_gain(real, md, results)
    study_heldout(real, md, results)
    study_joint(real, md, results)
    study_electrons(md, results, written=not args.no_preset)
    study_car_bands(real, md, results)
    if not args.no_preset:
        write_preset(results, md)
    else:
        keep_preset(results, md)
    synthetic_envelope(md, args.draws)
    downstream_proxy(args.data, md)
    new_envelope(md)
    md += [ENVELOPE_TEXT, "", SPEED_TEXT, "", HISTORY_TEXT, ""]
    text = "\n".join(md).replace("RUNTIME_LINE", f"{time.time() - t0:.0f} s on {os.cpu_count()} cores")
    write_bytes_atomic(HERE / "fidelity.md", text.encode("utf-8"))
    print(f"wrote {HERE / 'fidelity.md'} in {time.time() - t0:.0f} s")


ENVELOPE_TEXT = """## Detectability envelope of `spikegen diagnose`

Stated and tested (tests/test_diagnose.py): recordings of >= 1000 frames, >= 64 x 64 pixels,
intensity 32-256, a reference whose radiance spans about 0.05-1 with pixel-scale texture (for
`crosstalk`). Within it the diagnosis names, and estimates within 20 %:
`gain_nonuniformity` sigma >= 0.03; `column_pattern` sigma >= 0.02; `dark_current` rate >= 0.002;
`hot_pixels` >= 5 pixels at rate >= 0.05; `shot_noise` electrons <= 2000; `reset_to_zero`;
`refractory` >= 1 frame; `flicker` depth >= 0.05, period 10-1000 frames; `crosstalk` fraction >= 0.05;
`nonlinearity` |gamma - 1| >= 0.1; and nothing on data from the baseline sensor. The tests draw
parameters up to: gain sigma 0.12, column sigma 0.08, dark rate 0.02, 30 hot pixels of rate 0.05-0.3,
electrons 20-2000, refractory 1-4 frames, flicker depth 0.4, crosstalk 0.3, gamma 0.55-1.45.
With `--reference self` only the static pixels are judged (`heldout.motion_test`), and only
temporal effects (`shot_noise`, `flicker`,
`reset_to_zero`, `refractory` via missing short intervals) and, on smooth scenes, `hot_pixels`
and `column_pattern` can be told; gain, dark current, crosstalk and nonlinearity need a reference."""


SPEED_TEXT = """## Speed of `spikegen diagnose` (measured with bench/bench_diagnose.py, not regenerated)

Issue 15's targets: 128 x 128 x 2000 frames in under a minute on 2 cores; 250 x 400 x 20000 (one
second of camera time) in under 10 minutes and 4 GB. `python bench/bench_diagnose.py [--case
second]` simulates the recording (gain spread, dark current, shot noise; seeded), runs the CLI in
a child process and prints its wall and CPU time, its peak RSS, the time of one simulation of
the recording (the yardstick: the diagnosis simulates its models itself) and the load average.
Measured on 2026-11-25 on the shared 2-core machine (other jobs running, load 3.9-5.2), default
threads, the version before this change (commit 7144b66) and after it one after the other:

| recording | version | wall | CPU | peak RSS | diagnosis / one simulation | load before, after |
|---|---|---|---|---|---|---|
| 250 x 400 x 20000 | before | 711 s | 664 s | 2049 MiB | 25.6 | 4.33, 4.10 |
| 250 x 400 x 20000 | after | 403 s | 376 s | 1787 MiB | 13.4 | 3.92, 4.42 |
| 128 x 128 x 2000 | before | 29.9 s | 28.0 s | 417 MiB | 8.0 | 4.36, 4.99 |
| 128 x 128 x 2000 | after | 18.6 s | 17.4 s | 372 MiB | 5.8 | 4.99, 5.21 |

The JSON of both versions is the same (but for the recording's path), and so are those of 22
seeded hidden-effect, pair, self-reference and moving-scene cases. What changed: each model's
simulation is reduced once (`bands.simulation_pass`, kept by `bands.simulation_key`): the
shot-noise verdict's noise-free model is scored from its fit-window pass, and the model of every
gated effect gets its discrepancy measures and checks in its held-out pass (reused as the extended
sensor's when all are kept), so the one second takes 5 simulations instead of 7; the rate fit's
linear steps sum the design's columns in NumPy's own order without stacking them (the same bits,
about 2x cheaper); timing statistics with frames as the clock come from running sums of whole
numbers over each pixel's spike indices (`stats.frame_stats`, `interval_variances`,
`interval_moments`; a simulated block's interval moments by one pass over its frames); the flicker
fit reads its four groups in one pass, as a float32 product with the masks (whole numbers below
2**24, exact); the fit window's statistics and its halves' rates in one read; the local median of
`stats.fit_sine`, which grew with the square of the frame count, slides; `sensor.simulate` splits
the rows asked for over its threads (a block of rows was one chunk). Peak memory is that of a
simulated block of rows (256 MiB of spikes, twice that of noise draws); the timing statistics peak at
0.7 GB on the one second and return to 0.3 GB (no growth from band to band). Still most of the
time: the 5 simulations (about 30 s each on one core) and, per simulated model, the held-out
statistics of its 20000 frames.

Measured again on 2026-11-26, after the threshold jitter was read against the model with the shot
noise found (one more simulation of the fit window where shot noise is found), default threads,
beside a 400 x 400 protocol run and `docs/make_fidelity.py` (commit 6c2caf3 and later):

| recording | wall | CPU | peak RSS | diagnosis / one simulation (the simulation) | load before, after |
|---|---|---|---|---|---|
| 250 x 400 x 20000 | 323 s | 241 s | 1795 MiB | 13.6 (23.8 s) | 2.94, 3.23 |
| 128 x 128 x 2000 | 21.1 s | 13.2 s | 411 MiB | 5.2 (4.1 s) | 3.08, 3.42 |

Measured again on 2026-11-26 after the held-out score's intervals became whole-frame values pooled
by drive (each simulated band's intervals are listed once more), default threads, beside a 400 x 400
protocol run (and, for the second, the test suite); the bench's output
is in bench/results/diagnose_speed_20261126.txt:

| recording | wall | CPU | peak RSS | diagnosis / one simulation (the simulation) | load before, after |
|---|---|---|---|---|---|
| 250 x 400 x 20000 | 316 s | 329 s | 1830 MiB | 15.5 (20.4 s) | 2.01, 2.47 |
| 128 x 128 x 2000 | 15.3 s | 14.8 s | 453 MiB | 6.7 (2.3 s) | 3.24, 3.34 |"""


HISTORY_TEXT = """## What the hidden-effect tests caught (development log, not regenerated)

The hidden-effect tests and the seeded sweeps (`tests/test_diagnose.py`, the `slow` ones
included) failed on earlier versions of `spikegen diagnose`; each failure named a real flaw:

- `reset_to_zero` at intensity >= 190 was missed as the first effect: without shot noise the
  intervals are exactly `ceil(1 / lambda)`, which the half-frame-offset model misread in bright
  pixels as `nonlinearity` (gamma 1.11-1.66) + `dark_current` + `refractory`. Fixed by an
  interval-censored fit (`1 / lambda` in `(ISI - n - 1, ISI - n]`) when intervals never vary,
  taking the shortest dead time that fits as well as the best (at I = 255 the censored fit
  otherwise chose a 1-frame dead time plus dark current).
- `column_pattern` sigma 0.046 at I = 82 was not detected: its significance used the spread of
  the signal itself (z <= sqrt(columns / 2) whatever the effect size); now the null spread comes
  from the difference of two halves of the recording.
- `shot_noise` electrons came out 11-19 % high (the variance of 4-interval spans is biased low for
  pixels with few spikes), and 54 % low under a long-period flicker (the interval variance counted
  the slow modulation). Now: variance of differences of consecutive intervals, minus the 1/2
  frame^2 of quantisation, corrected for their lag-1 correlation, where intervals vary by more
  than a frame.
- Clean `refractory` and `reset_to_zero` streams were reported with `flicker` too: their
  population signal rings at the pixels' rates. The line is now also looked for in the fitted
  model simulated without flicker, and must be shared by four brightness quartiles.
- Long-period `flicker` produced a false `shot_noise` (a 1 % depth error in the fitted flicker
  leaves interval variance shaped like `1 / lambda^2`); shot noise must now add >= 10 % to the
  model's own interval variance, and both streams use the same variance estimator per pixel.
- `reset_to_zero` + `hot_pixels`: 4 of 16 hot pixels found (only long intervals were used);
  now every interval bounds lambda from below.

Second round (issue 15, effects chosen by held-out evidence):

- `test_sweep_random_pairs` gave different failures in different runs. Cause: OpenBLAS splits
  long reductions over its threads, so `A.T @ b` over 4096 pixels rounded differently under
  `OMP_NUM_THREADS=1` and `2`; one last bit in the rate fit moved the fitted flicker depth and so
  the diagnosis' own simulations. Every sum over pixels or frames now uses NumPy's own
  single-threaded reductions (`spikegen.fidelity.exact`); a test runs the CLI under 1 and 2 BLAS
  threads and compares the JSON bytes.
- `nonlinearity` (gamma 1.38) + spread `dark_current` was reported as `gain_nonuniformity` alone:
  the standard error of gamma came from the objective's curvature on another set of pixels than
  the objective itself (after the outlier update), so it was infinite and gamma never passed.
- A spread dark map (lognormal, log-SD 0.4-0.6) was read partly as gain, its mean 30 % low: the
  rate fit and the relative-residual cut leave the map's upper tail out only where the light is
  weak, so the dark variance seemed to grow with the light. The gain/dark regression now uses
  every pixel but the hot ones, with each bin's own sampling error; the mean dark rate adds the
  intercept of the residual rate over the light to the fitted one, and is that of the model at
  gamma = 1 unless a nonlinearity is detected (a gamma slightly below 1 lifts dark pixels as a
  dark rate does).
- A spread `dark_current` (median 0.0031, log-SD 0.47) beside one `refractory` frame at I = 97 had
  its median read 28 % high (0.00397): that intercept was fitted over all eight light bins, and the
  brightest bins' residual, bent by the refractory compression (-0.0019 against +0.0002 to +0.0006
  below), tilted the line. A missing dark rate adds the same at every light, so the intercept now
  comes from the darker half of the bins: 0.00317 (+2 %); a spread dark map alone (median 0.00562,
  log-SD 0.26) reads 0.00556 (0.00566 before).
- `column_pattern` with a noise-free `reset_to_zero` at I = 173 was missed: no row had 4 usable
  pixels, the row factors were NaN and so were the gain and column estimates. And a per-pixel gain
  map reproduced a column pattern by itself (the held-out choice then dropped the columns); the
  gain map is now the per-pixel factor beyond the column factors. The column estimate also
  subtracts the share of a dark-rate spread.
- Under a flicker shared by all pixels the rate fit compares each pixel's mean interval with the
  model's mean over the flicker (`records.flicker_mean_isi`: the mean rate is that of
  `1 / (delta + 1 / (lambda phi_t))` over the frames, below the rate at the mean light once
  `delta > 0`); the linear step and the per-pixel structure use its inverse, the two halves of
  the fit window with their own flicker phases. (A first version fitted the inverted intervals
  directly: its objective then meant something else at each `delta`, and at I = 196 it ran to a
  5-frame dead time and gamma 3.2.)

Known limits: `reset_to_zero` combined with shot noise of ~10^3 electrons confuses the fit
(excluded from the random pairs, `synth.KNOWN_CONFUSIONS`); with sub-frame (moving) references
the shot-noise estimate is ~20 % low; with `--reference self`, fine scene texture is counted as
hot-pixel candidates; only the seeds in the tests and this page were checked.

Known limits of the held-out choice, measured by `tests/test_diagnose.py` (2026-11-23, before the
third round below):

- `test_sweep_random_pairs`: 19/20 pairs with both effects found and both parameters within 20 %.
  The miss, pair 0: a reset to zero under flicker of depth 0.37 and period 648 frames at I = 62.
  The mean-interval law `delta + 1 / lambda` is ~1 % off at the bright pixels (the whole-frame
  intervals of a reset to zero), and the rate fit's delta-gamma trade-off reads that as
  delta = 0.90, gamma = 1.055 instead of 0.5 and 1: no reset to zero is named.
- With a noise-free reset to zero the intervals are deterministic, so interval quantisation and
  column-factor errors repeat in the held-out frames: a small gain spread (sigma 0.017 beside a
  column pattern at I = 173) or 2 hot pixels (the upper tail of a spread dark map at I = 189) are
  named too, and a dark map's spread cannot be measured (only its mean).
- Section 7's random pairs (other seeds), 14/16. Flicker of depth 0.065 and period 21 frames
  beside 26 dead pixels at I = 134: the flicker is measured right (depth 0.0653) and passes its
  gates, but the held-out score does not support it (-75 nats, SE 271): window counts of 4-64
  frames over 200 held-out frames barely see a shallow 21-frame flicker. Spread dark current
  (log-SD 0.48) + a 2-frame dead time at I = 35: the interval offset comes out 1.51 (1 refractory
  frame and a reset to zero that the held-out score drops) and the median dark rate 29 % low.
- Strict xfails (fixed in the third round, below): `flicker` + shot noise of ~10^3 electrons (the
  held-out score dropped the shot noise); light that changes at random every 4 frames, common to
  all pixels, was named shot noise; an ideal sensor's moving scene with `--reference self` was
  named shot noise.

Third round (the three strict xfails). After it `tests/test_diagnose.py` passes whole (2026-11-23):
`test_sweep_random_pairs` is still 19/20 with the same miss (pair 0 above), and section 7's random
pairs are 15/16: the flicker of depth 0.065 beside 26 dead pixels is now kept (the held-out score
sees a model's flicker on its own clock); the spread dark current + 2-frame dead time at I = 35
remains the miss.

- Flicker + shot noise of ~10^3 electrons (I = 214): the held-out score compared each held-out
  interval with the pixel's simulated intervals of the whole run, whose variance held the slow
  flicker (a 583-frame period over 1000 frames: 1.71 frames^2 in the darkest quarter of the pixels
  against 1.42 measured in the 200 held-out frames), and it added 1/12 frame^2 to simulated
  variances that were already of whole-frame intervals. A model with too little temporal noise
  scored better (shot noise -927 nats). Now a model's flicker is scored on its own clock
  (intervals in the integrated modulation, with the change of variables; counts about the
  modulated mean) and 1/12 is a floor, not an addition: shot noise gains +2977 nats (SE 154), and
  the score's maximum over N_e lies at the true value (1018 electrons: +3069; 958: +3026; 2000: +2793).
- Light that changes at random every 4 frames (SD 15 %), common to all pixels, was named shot
  noise (N_e = 63): nothing checked that the excess interval variance is independent from pixel
  to pixel. Now the covariance of the four image quadrants' relative counts measures a modulation
  shared by all pixels (an object that moves over part of the image is not in every pair); when the
  measured stream has one beyond the model's (5 SE, relative SD >= 0.01 in 4-frame windows), both
  streams' intervals are measured on their own population's clock before the shot-noise estimate:
  nothing is named, `rate_per_frame` is unexplained.
- An ideal sensor's moving scene with `--reference self` (a bright bar over rows 20-35) was named
  shot noise (N_e = 145): 662 pixels of the bar's rows passed the count test (a bar at rate 0.25 over
  a background at 0.225 adds 2.5 spikes to a 125-frame segment) and carried all of the excess
  interval variance (the 3072 pixels of other rows: 1/N_e = -4.5e-7 +- 2.6e-7). A pixel must now
  also have segment mean intervals that agree within their own error (regular pixels: a fraction
  of a frame over the segment): 904 of the bar rows' 1024 pixels move, none elsewhere, and nothing
  is named.

Fourth round (issue 15, the real car `.dat` with `--reference self`):

- The car recording (200 frames, a car that moves a few pixels over them) was named shot noise
  with N_e = 72, kept by the held-out score (+2.0e6 nats, SE 4.9e4), ideal -50.4 -> fitted -14.4
  nats per pixel, with rate_per_pixel, rate_per_row and rate_per_column unexplained; 55480 pixels
  counted as static. On the background alone (rows 0-55, 22400 pixels; columns 360-399, 10000
  pixels) the same diagnosis finds N_e = 1.6e4 and 1.0e4 (beyond the shot-noise gate of 4000
  electrons: nothing named, nothing unexplained), as the 500-frame car recording's background
  does. The static set held car pixels: with the trend and step tests below but not yet the
  interval-noise test (53564 static pixels, N_e = 75 still named), 5 % of the static pixels
  carried all of the held-out gain while the median one lost 1.2 nats; the best were wheel pixels
  whose intervals run 39, 10, 11, 11, 16, 22, 24, 18, 6, 4, 5, 6, 16 frames. Such a pixel passed
  the segment test because its own interval variance, which the test's errors use, holds the
  motion; others drift slowly (a chi-square of 24-28 over 7 segments, under the limit of 30) or
  had too few spikes for 3 segments and passed untested. Now (`heldout.motion_test`) a pixel is
  static only if it is tested (8 segments, else 4, else 2 halves), and shows no linear trend
  and no step between segments besides no chi-square excess, and its consecutive intervals differ
  no more than the temporal noise of the other static pixels lets them (the median of
  `v lambda^2` over them: shot noise and threshold jitter give every pixel the same). The car:
  48765 static, 50653 moving, 582 untested pixels, nothing named (shot noise N_e = 6537, z 13.5,
  beyond its gate), held-out score -6.09 nats per pixel; on that static set N_e = 72 loses
  82496 nats (SE 2279) and N_e = 6537 loses 1154 nats (SE 570) against the ideal sensor.
  rate_per_pixel (0.11 % of the pixels) and rate_per_row (1.2 %) stay unexplained: a few moving
  pixels are still in the set. `tests/test_diagnose.py` has a car-like simulated scene (a
  drifting textured object and a fast-changing wheel): before, an ideal sensor was named shot
  noise (N_e = 389) and true shot noise of 500 electrons came out as 236; now nothing, and 533.

Fifth round (issue 15, the threshold jitter beside shot noise, and the car's rows):

- At the car's rates (its top-left 128 x 200 mean rates as the radiance, 500 frames, seed 77) with
  the preset's noise (N_e 2.25e4, SD 0.0036) the diagnosis read the jitter as 0.00264 and, with no
  jitter, its statistic at z = -3.1: against the noise-free model, shot noise shrinks the single
  interval's variance against the span's beyond the analytic quantisation terms. The jitter is now
  read against the model with the shot noise found (one more simulation, the same seed): 0.00370,
  and on seeds 78-80 0.00362, 0.00364, 0.00408; with no jitter z = 0.19, 0.43, 1.21, 0.48. The
  envelope of the jitter alone did not move (every verdict the same). On the real car (`self`) the
  reading went from 0.0021 (z 3.8) to 0.0016 (z 2.1), where a seeded recording of the preset's noise
  at the car's full frame reads 0.0034-0.0037 (z 10-12).
- Why the real car reads less: split into bands of rows its background is not one population. The
  diagnosis of rows 0-124 reads a negative jitter statistic (z -10.9: variance that accumulates
  faster than shot noise), rows 125-249 a jitter of 0.0051 (z 12.8), and one band, rows 187-217, holds
  most of the negative lag-1 autocovariance the preset's jitter was fitted to ("The car's background,
  row band by row band" above). An effect outside the catalogue: `unexplained` now has
  `interval_variance_per_row` (bands of rows whose interval variance beyond the model's scatters beyond
  its errors); the real car lists it (z 53), seeded recordings with the same noise in every row do
  not, and light that flutters in 8 of 64 rows is listed without any effect named (tests). Its
  envelope on the test's recording (64 x 64 pixels, 1000 frames, I = 96, the light of rows 40-47
  changing at random every 2 frames; seeds 300-302, a scratch script, not regenerated): listed on 3
  of 3 seeds at an SD of 5 %, on 2 of 3 at 3 %, on none at 1 and 2 %; no effect named on any.
- The held-out score did not rank the true temporal noise first (2026-11-26). On seeded recordings
  at the car's rates with shot noise of N_e = 1.38e4 it scored the true model 0.014 nats per pixel
  below the ideal sensor (z -17), so it could not judge the calibrated noise on real data (the car:
  the preset -0.0185 nats per pixel against the ideal sensor). The Gaussian of each pixel's own
  simulated interval variance paid for that variance's sampling noise, and its floor of 1/12
  frame^2 gave both models the same variance where they differ most (pixels whose mean interval is
  nearly whole). Now, with a still reference, held-out intervals are scored by the probability of
  their whole-frame values among the simulated intervals of 64 pixels of like drive
  (`heldout.IntervalPool`; pooled by the simulated mean interval instead, a true reset to zero
  beside hot pixels was dropped). `tests/test_diagnose_heldout_pool.py` fails on the old score
  (three cases, z -5.0 to -6.7); the 139 diagnose, jitter, low-light, timing and calibration tests
  pass; on the car the preset now scores +0.13 nats per pixel over the ideal sensor, and the grid's
  best N_e is the one its diagnosis reads (2.137e4). The newer effects' envelope was measured again
  with it (`--measure-envelope`): `threshold_jitter` is now named on every seed from sigma = 0.006.
  Shot noise on the car is still not named: its N_e (2.14e4) is above the size gate (4000). With the
  gate lifted (a scratch run, not committed), `diagnose` named it on the car (kept by the held-out
  score, +12887 nats, SE 603), and also on the test recording whose rows 40-47 flutter (an effect
  outside the catalogue: N_e 3.8e4, z 13.5, kept, +81 nats, SE 20), which must not be named. The car's
  background is not one population either ("The car's background, row band by row band"), so the gate
  stays: with these recordings uniform shot noise of N_e ~ 2e4 cannot be told from light or gain that
  flutters in some rows.
- The held-out score with a reference that moves (2026-11-26, a second change). The low-light image
  moves, so `self` gives it a moving reference (16 sub-frames), and there the score had kept the
  Gaussian of each pixel's own intervals and predicted each window's count by one simulated draw
  with twice its variance. On seeded recordings of sub-frames with a moving bar (100 x 160, 500
  frames) the true shot noise (N_e 1.38e4) scored at z -0.34 and -0.19 against the ideal sensor,
  and the preset's noise on its own recording at z -2.4. Now the judged pixels whose reference stays
  within 10 % of its mean are pooled as with a still one (`heldout.quasi_still`), and every judged
  pixel's counts are predicted as its simulated rate times the reference's course in time
  (`heldout.ReferenceCourse`), their variance about it pooled by rate. The same cases now score at z
  +7.2, +9.6 and +9.0, the ideal sensor on an ideal recording at z -15.9
  (`tests/test_diagnose_heldout_pool.py`); the 147 diagnose, jitter, low-light, timing and calibration
  tests pass. On the low light the preset against the ideal sensor went from -0.00426 to -0.00091
  nats per pixel (z -0.30): its 40 held-out frames hold 0.79 intervals per judged pixel, and only 605
  of its 20164 judged pixels are still enough to be pooled, so it cannot tell N_e >= 1e4 from none
  (the grid's scores from 1e4 to none lie within 0.0017 nats per pixel). It does reject much more
  noise: N_e = 1000 scores 0.044 nats per pixel below none, 3000 0.020 below. The low light's larger
  interval variance (an N_e of about 1.4e3 read from the intervals alone) is not temporal noise by
  this score, in line with the image's motion (docs/lowlight.md)."""


if __name__ == "__main__":
    main()
