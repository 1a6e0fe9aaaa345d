"""Choosing the trainer's settings on a procedural scene (never on the views that are reported).

    python bench/bench_settings.py DATASET --name NAME --iters 1500 [-- TRAIN OPTIONS...]
    python bench/bench_settings.py --table          # the markdown table of bench/results/settings.jsonl
    python bench/bench_settings.py --table --since NAME   # ... of the rows from NAME on

Trains ``spikenerf train DATASET --iters N --out <work>/NAME [TRAIN OPTIONS]``, evaluates it on the
dataset's held-out views (``spikenerf eval``) and appends one line to
``bench/results/settings.jsonl``: the name, the options, the dataset, iterations, training and
evaluation seconds, the load average before and after, the code version (the short commit,
``+changes`` when tracked files differ from it), the sRGB weight the run trained with (its ``config.json``; rows
from before 2026-11-29 lack it: those that do not set ``--srgb-weight`` trained without it, the default then)
and the metrics (full image, object alpha > 0 and > 0.5, background; PSNR and SSIM). The dataset
is meant to be one of the project's own procedural scenes (``spikegen render``, moving camera), so
that no setting is chosen on the real lego's views (bench/PROTOCOL.md). Speed figures are only
comparable between runs made side by side (the load average is recorded).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench_protocol import _commit  # the short commit, "+changes" when tracked files differ from it

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results" / "settings.jsonl"
METRICS = ("psnr", "psnr_object", "psnr_object50", "psnr_background", "ssim", "ssim_object")


def run(dataset: Path, name: str, iters: int, options: list[str], work: Path) -> dict:
    out = work / name
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run(["spikenerf", "train", str(dataset), "--iters", str(iters), "--out", str(out), "--quiet", *options],
                   check=True)
    t1 = time.perf_counter()
    subprocess.run(["spikenerf", "eval", str(out), "--quiet"], check=True, stdout=subprocess.DEVNULL)
    t2 = time.perf_counter()
    m = json.loads((out / "metrics.json").read_text())
    cfg = json.loads((out / "config.json").read_text())
    return {"name": name, "options": options, "dataset": str(dataset), "iterations": iters,
            "train_s": round(t1 - t0, 1), "eval_s": round(t2 - t1, 1), "views": m["views"],
            "load": [round(load0, 2), round(os.getloadavg()[0], 2)], "version": _commit(),
            "srgb_weight": cfg.get("srgb_weight"), "metrics": {k: m[k] for k in METRICS}}


def _options(r: dict) -> str:
    """A row's options as the table shows them, with the sRGB weight it trained with where the options do not
    set it and it was not off (the trainer's default since 2026-11-29)."""
    text = f"`{' '.join(r['options']) or '(defaults)'}`"
    w = r.get("srgb_weight")
    if w and "--srgb-weight" not in r["options"]:
        text += f" (sRGB weight {w:g}, the default)"
    return text


def _load(pair) -> str:
    return " → ".join("?" if v is None else f"{v:.1f}" for v in pair)


def table(rows: list[dict]) -> str:
    out = ["| run | options | iterations | train s | eval s | load | PSNR full | object | object50 | background "
           "| SSIM full | object |", "|" + "---|" * 12]
    for r in rows:
        m = r["metrics"]
        eval_s = "?" if r["eval_s"] is None else f"{r['eval_s']:.0f}"  # rows run by hand: not timed
        out.append(f"| {r['name']} | {_options(r)} | {r['iterations']} | {r['train_s']:.0f} "
                   f"| {eval_s} | {_load(r['load'])} | {m['psnr']:.2f} | "
                   f"{m['psnr_object']:.2f} | {m['psnr_object50']:.2f} | {m['psnr_background']:.2f} | {m['ssim']:.3f} "
                   f"| {m['ssim_object']:.3f} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", type=Path)
    ap.add_argument("--name")
    ap.add_argument("--iters", type=int, default=1500)
    ap.add_argument("--work", type=Path, default=REPO / "bench_out" / "settings")
    ap.add_argument("--table", action="store_true", help="print the table of the results file and stop")
    ap.add_argument("--since", default=None, help="with --table: only the rows from this one on (by name)")
    args, extra = ap.parse_known_args()  # the rest (after --) goes to spikenerf train
    if args.table:
        rows = [json.loads(line) for line in RESULTS.read_text().splitlines() if line.strip()]
        if args.since:
            names = [r["name"] for r in rows]
            if args.since not in names:
                sys.exit(f"no row named {args.since!r} in {RESULTS}")
            rows = rows[names.index(args.since):]
        print(table(rows))
        return
    if args.dataset is None or not args.name:
        sys.exit("give DATASET and --name (or --table)")
    options = [o for o in extra if o != "--"]
    row = run(args.dataset.resolve(), args.name, args.iters, options, args.work)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with RESULTS.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(table([row]))


if __name__ == "__main__":
    main()
