"""Speed and memory of the sensor model against a plain per-frame NumPy loop (the yardstick).

    python bench/bench_sensor.py [--size 400] [--frames 256] [--subframes 16] [--intensity 64] [--repeat 3]

The yardstick is written the way spike simulators usually are: for each readout frame,
interpolate the radiance, compute the rate, draw the shot noise, integrate, fire, reset.
It uses the model's own per-frame charge (sensor.ChargeSchedule, the fixed-point definition
of "q = lambda at frame t") so that, without shot noise and with the same start phases, its
spikes must equal ours bit for bit; the benchmark checks that. With shot noise the two draw
different random numbers (the yardstick draws Poisson every frame as usual), so the check is
statistical: the mean rates agree. The third case adds a threshold jitter (``--jitter``), which
our simulator runs in its frame loop (sensor.loop_readout) instead of the fused carry pass.

Prints one table: CPU seconds per view (best of --repeat) and their ratio on one core; the
wall-clock ratio with ``simulate(threads=os.cpu_count())`` (row blocks in parallel threads; the
yardstick is single-threaded NumPy by nature); peak traced memory of one view.
"""
from __future__ import annotations

import argparse
import os
import time
import tracemalloc

import numpy as np

from spikegen.presets import get_sensor
from spikegen.sensor import ONE, ChargeSchedule, simulate, start_phase


def yardstick(x: np.ndarray, intensity: float, resp, dark, frames: int, phase, electrons: float = 0.0,
              rng: np.random.Generator | None = None, jitter: float = 0.0) -> np.ndarray:
    """Plain loop over frames. ``x [K, H, W]`` -> ``uint8 [T, H, W]``; ``jitter``: the firing level
    ``1 + N(0, jitter^2)`` drawn anew after each spike, the nominal threshold subtracted."""
    K, H, W = x.shape
    sched = ChargeSchedule.from_radiance(x.reshape(K, -1), intensity, resp.reshape(-1), dark.reshape(-1), frames)
    acc = phase.reshape(-1).astype(np.float64) / ONE
    level = 1.0 + (rng.normal(0.0, jitter, H * W) if jitter else 0.0)
    out = np.zeros((frames, H * W), dtype=np.uint8)
    for t in range(frames):
        q = sched.frame(t) / ONE  # exact: multiples of 2**-32 below 2**21
        if electrons:
            q = rng.poisson(q * electrons) / electrons
        acc += q
        fire = acc >= level
        acc[fire] -= 1.0
        np.minimum(acc, 1.0, out=acc, where=fire)
        if jitter:
            level[fire] = 1.0 + rng.normal(0.0, jitter, int(fire.sum()))
        out[t] = fire
    return out.reshape(frames, H, W)


def scene(size: int, subframes: int, seed: int = 0) -> np.ndarray:
    """A moving textured test scene: radiance in [0.05, 1.2], shifting 1 px per sub-frame."""
    rng = np.random.default_rng(seed)
    base = rng.random((size, size + subframes))
    k = np.ones(9) / 9
    base = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 1, base)
    base = 0.05 + 1.15 * (base - base.min()) / (np.ptp(base) + 1e-9)
    return np.stack([base[:, i:i + size] for i in range(subframes)]).astype(np.float32)


def best_time(fn, repeat):
    """Best CPU seconds of this process over ``repeat`` runs (stable when other work shares
    the machine; NumPy here is single-threaded, so CPU time is the run time on a quiet one)."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t0)
    return best, out


def best_wall(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def peak_mb(fn) -> float:
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2 ** 20


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=400)
    ap.add_argument("--frames", type=int, default=256)
    ap.add_argument("--subframes", type=int, default=16)
    ap.add_argument("--intensity", type=float, default=64)
    ap.add_argument("--electrons", type=float, default=1000.0)
    ap.add_argument("--jitter", type=float, default=0.0036, help="threshold jitter of the third case "
                    "(default: about the calibrated preset's)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    x = scene(a.size, a.subframes)
    sensor = get_sensor("paper", a.size, a.size)
    resp, dark = sensor.maps(a.size, a.size)
    seed = np.random.SeedSequence(7)
    phase = start_phase(seed, a.size, a.size)
    rows = []
    threads = os.cpu_count() or 1
    cases = (("no shot noise", 0.0, 0.0), (f"shot noise N_e={a.electrons:g}", a.electrons, 0.0),
             (f"shot noise N_e={a.electrons:g} + threshold jitter {a.jitter:g} (the frame loop)", a.electrons, a.jitter))
    for label, electrons, jitter in cases:
        s = sensor.replace(electrons=electrons, threshold_jitter=jitter)
        t_ours, ours = best_time(lambda: simulate(x, a.intensity, s, a.frames, seed=seed, phase=phase), a.repeat)
        t_loop, ref = best_time(lambda: yardstick(x, a.intensity, resp, dark, a.frames, phase, electrons,
                                                  np.random.default_rng(1), jitter), max(1, a.repeat - 1))
        if electrons == 0:
            agree = "bit-identical" if np.array_equal(ours, ref) else f"DIFFER in {int((ours != ref).sum())} px-frames"
        else:
            agree = f"mean rate {ours.mean():.4f} vs {ref.mean():.4f}"
        mem = peak_mb(lambda: simulate(x, a.intensity, s, a.frames, seed=seed, phase=phase))
        w_loop = best_wall(lambda: yardstick(x, a.intensity, resp, dark, a.frames, phase, electrons,
                                             np.random.default_rng(1), jitter), max(1, a.repeat - 1))
        w_ours = best_wall(lambda: simulate(x, a.intensity, s, a.frames, seed=seed, phase=phase, threads=threads),
                           a.repeat)
        rows.append((label, t_loop, t_ours, t_loop / t_ours, w_loop / w_ours, mem, agree))
    print(f"view {a.size}x{a.size}x{a.frames}, K={a.subframes}, I={a.intensity:g}, sensor=paper, "
          f"best of {a.repeat}")
    print(f"| case | yardstick CPU s | ours CPU s | speed-up, 1 core | speed-up, wall, {threads} threads "
          f"| ours peak MB | agreement |")
    print("|---|---|---|---|---|---|---|")
    for label, tl, to, r, rw, mem, agree in rows:
        print(f"| {label} | {tl:.3f} | {to:.3f} | {r:.1f}x | {rw:.1f}x | {mem:.0f} | {agree} |")


if __name__ == "__main__":
    main()
