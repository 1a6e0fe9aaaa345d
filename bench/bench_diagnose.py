"""Time and peak memory of `spikegen diagnose` on the issue's two recording sizes.

    python bench/bench_diagnose.py                  # 128 x 128 x 2000 (target: under a minute on 2 cores)
    python bench/bench_diagnose.py --case second    # 250 x 400 x 20000, one second of camera time
                                                    # (target: under 10 minutes and 4 GB)
    python bench/bench_diagnose.py --height 250 --width 400 --frames 2000   # any other size
    python bench/bench_diagnose.py --keep-json d.json   # and keep the diagnosis' JSON

The recording is simulated (seeded) with gain nonuniformity, dark current and shot noise
(spikegen.fidelity.synth; N_e = 300 for `small`; 2000 for `second`, where no pixel gets fewer
than 30 photo-electrons a frame, so the simulator never takes its slow exact-Poisson path over
the 2 * 10^9 pixel-frames) and written as .npz with its reference radiance as .npy.
`spikegen diagnose` then runs in a child process, which reports its own peak RSS (VmHWM,
read in the child as it ends; polled from /proc when the bench stops it); the child is stopped when its resident memory passes --limit-mib (default: the
target's 4096 for `second`, none otherwise) or when it runs past --timeout seconds, and the
bench says so. Prints the wall time of the diagnosis, its CPU time (user + system, all its
threads), its peak RSS, the time of the one simulation that made the recording (a yardstick
measured in the same run: the diagnosis simulates the recording several times itself) and the
load average before and after, since the machine may be shared.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "generator"))

from spikegen.fidelity import synth  # noqa: E402
from spikegen.sensor import simulate  # noqa: E402
from spikegen.spikeio import write_spikes  # noqa: E402

CASES = {"small": (128, 128, 2000, 300.0, None), "second": (250, 400, 20000, 2000.0, 4096)}
POLL_S = 0.2


def make_recording(height: int, width: int, frames: int, electrons: float, folder: Path) -> float:
    """Write ``m.npz`` and ``ref.npy`` into ``folder``; returns the seconds the simulation took."""
    rng = np.random.default_rng(2024)
    x = synth.test_radiance(height, width, rng)
    effects = {"gain_nonuniformity": {"sigma": 0.05}, "dark_current": {"rate": 0.005, "spread": 0.0},
               "shot_noise": {"electrons": electrons}}
    sensor = synth.make_sensor(effects, height, width, rng)
    t0 = time.perf_counter()
    spikes = simulate(x, 96.0, sensor, frames=frames, seed=7)
    sim_s = time.perf_counter() - t0
    write_spikes(folder / "m.npz", spikes)
    np.save(folder / "ref.npy", x.astype(np.float32))
    return sim_s


def _status_mib(pid: int, key: str = "VmRSS") -> float:
    """``key`` (VmRSS: resident now; VmHWM: its peak) of process ``pid`` from /proc, MiB (0 if gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def run_diagnose(folder: Path, limit_mib: float | None, timeout: float) -> tuple[str, float, float, float]:
    """``(outcome, wall seconds, peak RSS MiB, CPU seconds)`` of `spikegen diagnose` in a child process."""
    # the child writes its own peak RSS (VmHWM) when it ends: RUSAGE_CHILDREN's ru_maxrss would
    # count this process's peak (it holds the simulated recording), since Python starts the child
    # with vfork and Linux carries the parent's high-water mark over into the child's exec
    hwm = folder / "hwm.txt"
    code = ("import sys; from spikegen.cli import main\n"
            "try:\n    rc = main(sys.argv[2:])\n"
            "finally:\n"
            "    hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM:')][0].split()[1]\n"
            "    open(sys.argv[1], 'w').write(hwm)\n"
            "sys.exit(rc)")
    args = [sys.executable, "-c", code, str(hwm), "diagnose", str(folder / "m.npz"), "--reference", str(folder / "ref.npy"),
            "--intensity", "96", "--json", str(folder / "d.json")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "generator"), os.environ.get("PYTHONPATH", "")])}
    t0 = time.perf_counter()
    err_path = folder / "stderr.txt"
    with open(err_path, "w") as err_file:
        child = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=err_file)
    outcome, polled = None, 0.0
    while child.poll() is None:
        wall = time.perf_counter() - t0
        polled = max(polled, _status_mib(child.pid, "VmHWM"))
        if limit_mib is not None and _status_mib(child.pid) > limit_mib:
            outcome = f"stopped: resident memory passed {limit_mib:.0f} MiB after {wall:.0f} s"
        elif wall > timeout:
            outcome = f"stopped: still running after {timeout:.0f} s"
        if outcome:
            child.kill()
            break
        time.sleep(POLL_S)
    child.wait()
    wall = time.perf_counter() - t0
    err = err_path.read_text(errors="replace")
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = usage.ru_utime + usage.ru_stime
    peak = int(hwm.read_text()) / 1024.0 if hwm.exists() else polled  # polled: a child that was stopped
    if outcome is None:
        outcome = "ok" if child.returncode == 0 else f"exit {child.returncode}: {(err.strip().splitlines() or [''])[-1]}"
    else:  # the diagnosis' progress bar (stderr) says which step it had reached
        bars = [b.strip() for b in err.replace("\n", "\r").split("\r") if "diagnose" in b]
        outcome += f" (progress: {bars[-1]})" if bars else " (before its first step)"
    return outcome, wall, peak, cpu


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=sorted(CASES), default="small")
    ap.add_argument("--height", type=int, default=None)
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--limit-mib", type=float, default=None, help="stop the diagnosis past this resident memory")
    ap.add_argument("--timeout", type=float, default=1800.0, help="stop the diagnosis past this many seconds")
    ap.add_argument("--keep-json", type=Path, default=None,
                    help="copy the diagnosis' JSON here (to compare the output of two versions)")
    args = ap.parse_args(argv)
    H, W, T, electrons, limit = CASES[args.case]
    H, W, T = args.height or H, args.width or W, args.frames or T
    limit = args.limit_mib if args.limit_mib is not None else limit
    with tempfile.TemporaryDirectory() as tmp:
        sim_s = make_recording(H, W, T, electrons, Path(tmp))
        load0 = os.getloadavg()
        outcome, wall, peak, cpu = run_diagnose(Path(tmp), limit, args.timeout)
        load1 = os.getloadavg()
        if args.keep_json is not None and (Path(tmp) / "d.json").exists():
            args.keep_json.write_bytes((Path(tmp) / "d.json").read_bytes())
    print(f"diagnose {H}x{W}x{T} (N_e {electrons:g}): {outcome}; {wall:.1f} s ({cpu:.1f} s of CPU), "
          f"peak RSS {peak:.0f} MiB; "
          f"one simulation of the recording {sim_s:.1f} s (diagnosis / simulation {wall / sim_s:.1f}); "
          f"cores {os.cpu_count()}; load average before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, "
          f"after {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")


if __name__ == "__main__":
    main()
