"""The paper's protocol on the real lego (Table S3 shape), measured, printed as a table.

For each sensor (rsir, paper) and intensity (16, 32, 64): ``spikegen convert`` the real
NeRF-synthetic lego train views (shared/data/nerf_synthetic_lego_400; no test split there, so
the trainer holds out every 8th view), ``spikenerf train`` every method, ``spikenerf eval``
on the held-out views; print PSNR full/object with the paper's lego numbers beside ours, and
the training time of every run. Results are also written to ``OUT/results.json``.

    python bench/bench_protocol.py --resolution 100            # CI scale, CPU
    python bench/bench_protocol.py --resolution 400 --device cuda

Finished steps are skipped when rerun (converted folders, runs with metrics.json).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_lego_400"
METHODS = ["spikelik", "spikenerf", "spikenerf-noR", "tfp32", "tfp256", "tfi"]
PAPER = {  # the paper's Table S3, lego, PSNR full / object
    "paper: TFP(32)+NeRF": {16: (15.27, 15.57), 32: (17.81, 18.55), 64: (20.63, 21.86)},
    "paper: SpikeNeRF": {16: (18.72, 19.38), 32: (22.05, 23.66), 64: (23.89, 24.46)},
}


def _run(cmd: list[str]) -> None:
    print("$", " ".join(cmd), flush=True)
    res = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if res.returncode:
        sys.exit(f"failed ({res.returncode}): {' '.join(cmd)}\n{res.stderr.strip().splitlines()[-1:]}")


def convert(out: Path, sensor: str, intensity: int, resolution: int) -> Path:
    root = out / f"data_{sensor}_{resolution}"
    folder = root / f"{LEGO.name}_i{intensity}"
    if not (folder / "manifest.json").is_file():
        _run(["spikegen", "convert", str(LEGO), "--intensity", str(intensity), "--out", str(root),
              "--sensor", sensor, "--resolution", str(resolution)])
    return folder


def train_eval(folder: Path, run: Path, method: str, args) -> dict:
    if not (run / "metrics.json").is_file():
        cmd = ["spikenerf", "train", str(folder), "--method", method, "--out", str(run), "--device", args.device,
               "--seed", str(args.seed), "--quiet"]
        if args.iters:
            cmd += ["--iters", str(args.iters)]
        t0 = time.perf_counter()
        _run(cmd)
        wall = time.perf_counter() - t0
        t0 = time.perf_counter()
        _run(["spikenerf", "eval", str(run), "--device", args.device, "--quiet"])
        m = json.loads((run / "metrics.json").read_text())
        m["wall_seconds_train_command"] = round(wall, 1)
        m["wall_seconds_eval_command"] = round(time.perf_counter() - t0, 1)
        (run / "metrics.json").write_text(json.dumps(m, indent=1))
    return json.loads((run / "metrics.json").read_text())


def _cell(m) -> str:
    return "–" if m is None else f"{m['psnr']:.2f}/{m['psnr_object']:.2f}"


def _run_minutes(m) -> str:
    if "wall_seconds_eval_command" not in m:  # a run from before the eval command was timed
        return "?"
    return f"{(m['wall_seconds_train_command'] + m['wall_seconds_eval_command']) / 60:.1f} min"


def print_tables(results: dict, intensities, sensors, methods, resolution) -> None:
    print(f"\n| lego {resolution}x{resolution} PSNR full/object | " + " | ".join(f"i{i}" for i in intensities) + " |")
    print("|---|" + "---|" * len(intensities))
    for name, row in PAPER.items():
        print(f"| {name} (400x400) | " + " | ".join("%.2f/%.2f" % row[i] if i in row else "–" for i in intensities)
              + " |")
    for s in sensors:
        for meth in methods:
            print(f"| ours {s}: {meth} | " + " | ".join(_cell(results.get(f"{s}/{i}/{meth}")) for i in intensities)
                  + " |")
    print(f"\n| train s; whole run (train + eval commands) min; SSIM full/object | "
          + " | ".join(f"i{i}" for i in intensities) + " |")
    print("|---|" + "---|" * len(intensities))
    for s in sensors:
        for meth in methods:
            cells = []
            for i in intensities:
                m = results.get(f"{s}/{i}/{meth}")
                cells.append("–" if m is None else f"{m['train_seconds']:.0f} s; {_run_minutes(m)}; "
                             f"{m['ssim']:.3f}/{m['ssim_object']:.3f}")
            print(f"| {s}: {meth} | " + " | ".join(cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=400)
    ap.add_argument("--intensities", default="16,32,64")
    ap.add_argument("--sensors", default="rsir,paper")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--iters", type=int, default=0, help="0 = the trainer's default")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "bench_out" / "protocol")
    args = ap.parse_args()
    if not LEGO.is_dir():
        sys.exit(f"{LEGO} not found: the real lego views are needed for this benchmark")
    intensities = sorted(int(v) for v in args.intensities.split(","))
    sensors, methods = args.sensors.split(","), args.methods.split(",")
    results = {}
    for s in sensors:
        for i in intensities:
            folder = convert(args.out, s, i, args.resolution)
            for meth in methods:
                run = args.out / f"runs_{args.resolution}" / f"{s}_i{i}_{meth}"
                results[f"{s}/{i}/{meth}"] = train_eval(folder, run, meth, args)
                m = results[f"{s}/{i}/{meth}"]
                print(f"  {s} i{i} {meth}: PSNR {_cell(m)}, train {m['train_seconds']:.0f} s, "
                      f"whole run {_run_minutes(m)}", flush=True)
    (args.out / f"results_{args.resolution}.json").write_text(json.dumps(results, indent=1))
    print_tables(results, intensities, sensors, methods, args.resolution)


if __name__ == "__main__":
    main()
