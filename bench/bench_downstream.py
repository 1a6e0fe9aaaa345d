"""The gain downstream (the paper's Table S5 in our terms): train on data made with the
extended (`calibrated`) sensor, once with the matching sensor in the loss (`spikenerf`: R and
dark current of the dataset's sensor.npz) and once with the baseline (`spikenerf-noR`), and
print the PSNR difference on the held-out views.

    python bench/bench_downstream.py [--resolution 100] [--intensity 32] [--out /tmp/downstream]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

LEGO = Path(__file__).resolve().parents[2] / "shared" / "data" / "nerf_synthetic_lego_400"


def run(*args):
    subprocess.run([*args], check=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--resolution", type=int, default=100)
    ap.add_argument("--intensity", type=int, default=32)
    ap.add_argument("--sensor", default="calibrated")
    ap.add_argument("--out", type=Path, default=Path("/tmp/downstream"))
    a = ap.parse_args()
    data = a.out / "data"
    run("spikegen", "convert", str(LEGO), "--intensity", str(a.intensity), "--sensor", a.sensor,
        "--resolution", str(a.resolution), "--out", str(data))
    dataset = data / f"{LEGO.name}_i{a.intensity}"
    rows = {}
    for method in ("spikenerf", "spikenerf-noR"):
        run_dir = a.out / f"run_{method}"
        run("spikenerf", "train", str(dataset), "--method", method, "--out", str(run_dir), "--quiet", "--eval")
        rows[method] = json.loads((run_dir / "metrics.json").read_text())
    print(f"lego {a.resolution}x{a.resolution}, i{a.intensity}, data from sensor '{a.sensor}'")
    print("| loss | PSNR full | PSNR object | SSIM full | train s |")
    print("|---|---|---|---|---|")
    for m, d in rows.items():
        print(f"| {m} | {d['psnr']:.2f} | {d['psnr_object']:.2f} | {d['ssim']:.3f} | {d['train_seconds']:.0f} |")
    w, wo = rows["spikenerf"], rows["spikenerf-noR"]
    print(f"gain of the matching sensor: {w['psnr'] - wo['psnr']:+.2f} dB full, "
          f"{w['psnr_object'] - wo['psnr_object']:+.2f} dB object")


if __name__ == "__main__":
    sys.exit(main())
