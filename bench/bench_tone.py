"""Which levels a trained field renders too bright or too dark: the tone of evaluated runs side by side.

    python bench/bench_tone.py RUN [RUN ...] --json FILE [--plot FILE.png]   # collect, print, record
    python bench/bench_tone.py --table FILE [--plot FILE.png]                 # the table of a saved file again

Each RUN must have been evaluated (``spikenerf eval RUN``) against ground truth: its ``metrics.json`` holds
``tone`` (trainer/spikenerf/metrics.py, ``Tone``), the mean truth and prediction per bin of the ground truth's
linear luminance over the object, over all its pixels and over its *flat* ones (no edge within a few pixels, so
no blur can move them). The table prints, per bin, each run's bias (prediction - truth, linear) over all pixels
and over the flat ones, and what the flat bias is on a display: the prediction's mean over the truth's after
the sRGB encoding, in 8-bit steps. The plot draws that display bias of the flat pixels per bin, one line a run.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "generator"), str(REPO / "trainer")]

from spikegen.spikeio import linear_to_srgb, write_json_atomic  # noqa: E402


class ToneError(Exception):
    pass


def collect(runs: list[Path]) -> dict:
    """The record of the runs: per run its name, method, resolution, iterations, dataset and tone rows."""
    out = []
    for run in runs:
        path = run / "metrics.json"
        if not path.is_file():
            raise ToneError(f"{run}: no metrics.json (run `spikenerf eval {run}` first)")
        m = json.loads(path.read_text())
        if "tone" not in m:
            raise ToneError(f"{run}: its metrics.json has no tone (evaluated before it existed, or against "
                            f"reconstructions, not ground truth): run `spikenerf eval {run}` again")
        cfg = json.loads((run / "config.json").read_text())
        out.append({"run": run.name, "method": m["method"], "resolution": m["resolution"],
                    "iterations": m["iterations"], "dataset": cfg["dataset"], "views": m["views"], "tone": m["tone"]})
    return {"runs": out}


def _steps(pred: float, truth: float) -> float:
    """The bias on a display: sRGB(pred) - sRGB(truth), in 8-bit steps."""
    return 255 * (float(linear_to_srgb(pred)) - float(linear_to_srgb(truth)))


def _bias(v) -> str:
    return "-" if v is None else f"{v:+.4f}"


def table(record: dict) -> str:
    runs = record["runs"]
    lines = []
    for i, r in enumerate(runs):
        lines.append(f"[{i}] {r['run']}: {r['method']}, {r['resolution'][1]} x {r['resolution'][0]}, "
                     f"{r['iterations']} iterations, {r['views']} views of {r['dataset']}")
    head = ["truth (linear)"]
    for i in range(len(runs)):
        head += [f"[{i}] pixels", f"[{i}] bias", f"[{i}] flat px", f"[{i}] flat bias", f"[{i}] flat 8-bit"]
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for b in range(len(runs[0]["tone"])):
        row = runs[0]["tone"][b]
        cells = [f"{row['truth_from']:g} to {row['truth_to']:g}"]
        for r in runs:
            t = r["tone"][b]
            cells += [str(t["pixels"]), _bias(t["bias"]), str(t["flat_pixels"]), _bias(t["flat_bias"]),
                      "-" if t["flat_pred"] is None else f"{_steps(t['flat_pred'], t['flat_truth']):+.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(record: dict, path: Path) -> None:
    from spikegen.fidelity.report import save_figure

    def draw(ax):
        for r in record["runs"]:
            rows = [t for t in r["tone"] if t["flat_pixels"]]
            ax.plot([t["flat_truth"] for t in rows], [_steps(t["flat_pred"], t["flat_truth"]) for t in rows],
                    marker="o", label=f"{r['run']} ({r['method']}, {r['resolution'][1]} px)")
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("true luminance, mean of the bin's flat pixels (linear)")
        ax.set_ylabel("rendered - true on a display (sRGB, 8-bit steps)")
        ax.set_title("tone of the held-out views: where the field is too bright")
        ax.legend(fontsize=7)

    save_figure(path, draw, size=(7.0, 4.5))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--json", type=Path, help="write the record of the runs here")
    ap.add_argument("--table", type=Path, help="print the table of a saved record instead")
    ap.add_argument("--plot", type=Path, help="also draw the flat pixels' display bias per bin (PNG)")
    a = ap.parse_args(argv)
    try:
        if a.table:
            if a.runs:
                raise ToneError("--table takes a saved record, no runs")
            if not a.table.is_file():
                raise ToneError(f"{a.table}: no such file")
            record = json.loads(a.table.read_text())
        else:
            if not a.runs:
                raise ToneError("name at least one evaluated run (or --table FILE)")
            record = collect(a.runs)
            if a.json:
                write_json_atomic(a.json, record)
    except ToneError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(table(record))
    if a.plot:
        plot(record, a.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
