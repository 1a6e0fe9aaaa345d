"""Time and peak memory of `spikegen diagnose` on a 128 x 128 x 2000 recording.

    python bench/bench_diagnose.py [--frames 2000] [--size 128]

The recording is simulated (seeded) with gain nonuniformity, dark current and shot noise
(spikegen.fidelity.synth) and written as .npz; the CLI runs in this process (in-process
timing, `resource` peak RSS). Target: under a minute on 2 cores. Prints the load average,
since the machine may be shared.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "generator"))

from spikegen.cli import main  # noqa: E402
from spikegen.fidelity import synth  # noqa: E402
from spikegen.sensor import simulate  # noqa: E402
from spikegen.spikeio import write_spikes  # noqa: E402


def run(size: int, frames: int) -> None:
    rng = np.random.default_rng(2024)
    x = synth.test_radiance(size, size, rng)
    effects = {"gain_nonuniformity": {"sigma": 0.05}, "dark_current": {"rate": 0.005, "spread": 0.0},
               "shot_noise": {"electrons": 300.0}}
    spikes = simulate(x, 96.0, synth.make_sensor(effects, size, size, rng), frames=frames, seed=7)
    with tempfile.TemporaryDirectory() as tmp:
        write_spikes(Path(tmp) / "m.npz", spikes)
        np.save(Path(tmp) / "ref.npy", x.astype(np.float32))
        load = os.getloadavg()
        t0 = time.perf_counter()
        code = main(["diagnose", str(Path(tmp) / "m.npz"), "--reference", str(Path(tmp) / "ref.npy"),
                     "--intensity", "96", "--json", str(Path(tmp) / "d.json")])
        wall = time.perf_counter() - t0
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"diagnose {size}x{size}x{frames}: {wall:.1f} s (exit {code}), peak RSS {peak_mib:.0f} MiB, "
          f"cores {os.cpu_count()}, load average before {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--frames", type=int, default=2000)
    args = ap.parse_args()
    run(args.size, args.frames)
