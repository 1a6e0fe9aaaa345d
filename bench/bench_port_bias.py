"""Why the paper's port scores lower on the `paper` and `calibrated` sensors than on `rsir`: the
published neuron's rate against the pixel that made the data, and what undoing it gives back.

    python bench/bench_port_bias.py --runs-dir bench_out/protocol/runs_400    # every eligible run there
    python bench/bench_port_bias.py RUN [RUN ...]                             # or these run folders

The port (`spikenerf-paper`, trainer/spikenerf/neuron.py `paper_pixel`) predicts a pixel's count
with the published integrate-and-fire loop: 256 steps of constant input from an empty membrane,
a spike strictly above 1, reset to 0. That loop discards the charge left over at each spike and
counts only whole intervals from an empty start, so for the same charge a frame ``c`` it reads
fewer spikes than a pixel that subtracts the threshold and starts at a random phase (the `paper`
and `calibrated` sensors, whose mean count is ``256 c``), and about as many as the reference
generator `rsir` makes (its uniform interval noise, mean half a frame, plays the part of the lost
residual). Trained on subtractive-reset data, the port must render a brighter luminance than the
truth to read the same count.

Two parts, both written to one results file (default ``bench/results/port_bias.jsonl``, replaced
as a whole; ``bench/make_protocol.py`` turns it into PROTOCOL.md's section on it):

- ``"kind": "rate"`` rows: the mean count / 256 of the three pixels at luminance ``x`` and
  intensity ``I`` (``c = x I / 256``, R = 1, d = 0): subtractive reset (``c``); `rsir`, exactly
  (``E[ln(1 + v / 255)]`` over ``v ~ Poisson(x I 255 / 256)``, the uniform noise integrated out);
  the published loop at ``c`` itself and averaged over a spread of its input (``c (1 + u)``, ``u``
  on 201 even points in ``[-s, s]``: a rendered pixel is a mixture, and the loop's staircase is
  seen through it). No random draw.
- ``"kind": "run"`` rows, one per run folder (its ``config.json``, ``metrics.json`` and the
  ``eval_test/*_gt_vs_pred.png`` that ``spikenerf eval`` wrote): object PSNR (alpha > 0, the
  evaluation's region and comparison space) of the saved 8-bit predictions as they are; with
  the loop's rate loss undone, ``x -> r^-1(h_s(x))`` for each spread ``s`` (``h_s``: the averaged
  loop above; ``r``: the mean charge a frame of the pixel that made the run's data, ``y I / 256``
  for a subtractive-reset `if` sensor, ``rsir_rate`` for `rsir`: the luminance at which the data's
  pixel reads what the loop reads at the luminance the port rendered; no parameter fitted); and
  with one gain per run fitted by least squares in linear luminance over
  the object pixels of the reported views themselves (an oracle: it uses the views it is scored
  on; a diagnostic of how much of the error is a brightness scale, never a setting); and where the
  error lies: the object pixels binned by the count a pixel of the data expects over the 256
  frames at its true luminance (``x I``, with R = 1 and d = 0 as below; edges ``COUNT_EDGES``;
  below 1 the published loop, fed a constant input from an empty membrane, reads no spike at
  all), each bin's share of the pixels and its part of the pooled object MSE (sRGB, all views'
  object pixels together, so the parts add up to the pooled MSE; the PSNRs above are means over
  views), as saved and with the loss undone at spread ``BIN_SPREAD``.

The ground truth and alpha come from the dataset as the evaluation reads them
(:func:`spikenerf.eval.reference`); the rate loss is undone with R = 1 and d = 0 (the `paper` maps
have median R 1; the dark current is small against the lit object's charge).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from functools import lru_cache
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "generator"))
sys.path.insert(0, str(REPO / "trainer"))

RESULTS = REPO / "bench" / "results" / "port_bias.jsonl"
INTENSITIES = (16, 32, 64)
LUMINANCES = (0.1, 0.3, 0.6, 1.0)
SPREADS = (0.05, 0.1, 0.2)
BIN_SPREAD = 0.1  # the spread at which the error is broken down by expected count (run rows' "by_expected_count")
COUNT_EDGES = (0, 1, 2, 4, 8, 16)  # expected spikes in the 256 frames at the true luminance (x I); last bin open
STEPS = 256
METHODS = ("spikenerf-paper", "spikelik")  # the port, and the default as the control


class BadInput(Exception):
    """A run folder this bench cannot read (said in one line)."""


def hard_reset_rate(c: np.ndarray, spread: float = 0.0, points: int = 201) -> np.ndarray:
    """Mean count / 256 of the published loop (spikenerf.neuron.PaperIF) on constant inputs ``c``,
    averaged over ``c (1 + u)`` for ``u`` on ``points`` even points in ``[-spread, spread]``."""
    import torch

    from spikenerf.neuron import PaperIF

    c = np.asarray(c, dtype=np.float64)
    u = np.linspace(-spread, spread, points) if spread > 0 else np.zeros(1)
    inp = torch.tensor((c.reshape(-1, 1) * (1.0 + u.reshape(1, -1))), dtype=torch.float32)
    return PaperIF.apply(inp, STEPS).double().mean(dim=1).numpy().reshape(c.shape)


def rsir_rate(x: float, intensity: float) -> float:
    """Mean charge a frame of the `rsir` generator (spikegen.sensor.rsir_charge) with R = 1, d = 0:
    ``E[ln(1 + v / 255)]``, ``v ~ Poisson(x I 255 / 256)`` (``1 / (255 / v + U)`` integrated over
    ``U ~ U(0, 1)``; ``v = 0`` gives 0)."""
    lam = x * intensity * 255.0 / 256.0
    if lam <= 0:
        return 0.0
    hi = int(lam + 12.0 * math.sqrt(lam) + 20)
    v = np.arange(1, hi + 1, dtype=np.float64)
    logpmf = v * math.log(lam) - lam - np.array([math.lgamma(k + 1.0) for k in v])
    return float(np.sum(np.exp(logpmf) * np.log1p(v / 255.0)))


def rate_rows(spreads=SPREADS) -> list[dict]:
    rows = []
    for i in INTENSITIES:
        for x in LUMINANCES:
            c = x * i / 256.0
            row = {"kind": "rate", "intensity": i, "x": x, "subtractive": c, "rsir": rsir_rate(x, i),
                   "hard_reset": float(hard_reset_rate(np.array([c]))[0])}
            row["hard_reset_spread"] = {f"{s:g}": float(hard_reset_rate(np.array([c]), s)[0]) for s in spreads}
            rows.append(row)
    return rows


PIXELS = ("subtractive", "rsir")  # the data's pixels whose mean charge a frame this bench can invert


def pixel_of(sensor) -> str:
    """Which pixel made a dataset: ``"rsir"`` (the reference generator) or ``"subtractive"`` (an `if`
    sensor with subtractive reset, no refractory period and gamma 1, whose mean charge a frame is
    ``R x I / 256 + d``; shot noise and threshold jitter leave the mean as it is); any other sensor is
    refused."""
    if sensor.kind == "rsir":
        return "rsir"
    if sensor.kind == "if" and sensor.reset == "subtract" and not sensor.refractory_frames and sensor.gamma == 1:
        return "subtractive"
    raise BadInput(f"sensor {sensor.name!r} (kind {sensor.kind}, reset {sensor.reset}, refractory "
                   f"{sensor.refractory_frames}, gamma {sensor.gamma:g}): no mean-rate model here to undo the "
                   "port's loss against")


@lru_cache(maxsize=None)  # one curve per (intensity, spread, pixel), shared by every run at that intensity
def rate_loss_inverse(intensity: float, spread: float, pixel: str = "subtractive", top: float = 1.5,
                      points: int = 1501):
    """``(xs, y(xs))``: the luminance ``y`` at which the data's pixel (``pixel``: subtractive, whose mean
    charge a frame is ``y I / 256``, or `rsir`) reads the mean charge the published loop reads when fed
    ``xs I / 256``; ``np.interp(x, xs, y)`` undoes the port's rate loss. Read past ``top`` the curve
    holds its last value (the evaluation clips to 1 anyway)."""
    xs = np.linspace(0.0, top, points)
    loop = hard_reset_rate(xs * intensity / 256.0, spread)
    if pixel == "subtractive":
        return xs, loop * 256.0 / intensity
    if pixel != "rsir":
        raise ValueError(f"unknown pixel {pixel!r}")
    ys, r = _rsir_curve(intensity, 2.0 * top, 2 * points - 1)  # rsir reads less than y I / 256: its inverse runs higher
    return xs, np.interp(loop, r, ys)


@lru_cache(maxsize=None)  # the rsir pixel's curve depends on the intensity only, not on the loop's spread
def _rsir_curve(intensity: float, top: float, points: int):
    """``(ys, rsir_rate(ys))`` on ``points`` even luminances in ``[0, top]``; strictly increasing."""
    ys = np.linspace(0.0, top, points)
    return ys, np.array([rsir_rate(y, intensity) for y in ys])


def count_bin(gt_x: np.ndarray, intensity: float) -> np.ndarray:
    """Each pixel's bin of ``COUNT_EDGES`` by the count expected over the 256 frames, ``x I`` (0 for
    ``x I < 1``, ..., ``len(COUNT_EDGES) - 1`` for ``x I >= 16``)."""
    return np.searchsorted(np.asarray(COUNT_EDGES[1:], dtype=np.float64), gt_x * intensity, side="right")


def _encode(pred_lin: np.ndarray) -> np.ndarray:
    """A linear prediction in the evaluation's comparison space: clipped to [0, 1], sRGB-encoded."""
    from spikegen.spikeio import linear_to_srgb

    return linear_to_srgb(np.clip(pred_lin, 0.0, 1.0))


def run_row(run: Path, spreads=SPREADS) -> dict:
    """One run's object PSNRs: as saved, with the rate loss undone (per spread), with an oracle gain."""
    from spikegen.errors import InputError
    from spikegen.sensorfile import load_sensor
    from spikegen.spikeio import linear_to_srgb, read_png, srgb_to_linear
    from spikenerf.data import load_dataset
    from spikenerf.eval import reference
    from spikenerf.metrics import psnr

    run = Path(run)
    try:
        cfg = json.loads((run / "config.json").read_text())
        metrics = json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError) as e:
        raise BadInput(f"{run}: not an evaluated run ({e.__class__.__name__}: config.json and metrics.json needed)")
    try:
        ds = load_dataset(cfg["dataset"])
        sensor = load_sensor(Path(cfg["dataset"]) / "sensor.json")
    except (InputError, KeyError) as e:
        raise BadInput(f"{run}: its dataset {cfg.get('dataset')!r} cannot be read ({e})")
    split = metrics.get("split", "test")
    views = ds.splits.get(split, [])
    if not views:
        raise BadInput(f"{run}: its dataset has no {split!r} views")
    height, width = (int(v) for v in metrics["resolution"])
    intensity = float(ds.intensity)
    pixel = pixel_of(sensor)
    curves = {s: rate_loss_inverse(intensity, s, pixel) for s in dict.fromkeys((*spreads, BIN_SPREAD))}
    saved, undone, num, den, data = [], {s: [] for s in spreads}, 0.0, 0.0, []
    bins = len(COUNT_EDGES)
    pixels, se_saved, se_undone = np.zeros(bins), np.zeros(bins), np.zeros(bins)
    for view in views:
        png = run / f"eval_{split}" / f"{view.name.replace('/', '_')}.png"
        if not png.is_file():
            raise BadInput(f"{run}: {png.name} missing (run spikenerf eval on it first)")
        img = read_png(png)
        pred = srgb_to_linear(img[..., 0] if img.ndim == 3 else img)
        _, gt_x, alpha = reference(ds, view, height, width)
        mask = alpha > 0
        gt = linear_to_srgb(gt_x)
        as_saved = _encode(pred)
        saved.append(psnr(as_saved, gt, mask))
        for s, (xs, hx) in curves.items():
            undone_s = _encode(np.interp(pred, xs, hx))
            if s in undone:
                undone[s].append(psnr(undone_s, gt, mask))
            if s == BIN_SPREAD:
                for_bins = undone_s
        b = count_bin(gt_x[mask], intensity)
        pixels += np.bincount(b, minlength=bins)
        se_saved += np.bincount(b, weights=(as_saved[mask] - gt[mask]) ** 2, minlength=bins)
        se_undone += np.bincount(b, weights=(for_bins[mask] - gt[mask]) ** 2, minlength=bins)
        num += float((pred[mask] * gt_x[mask]).sum())
        den += float((pred[mask] ** 2).sum())
        data.append((pred, gt, mask))
    gain = num / den if den > 0 else 1.0
    total = max(pixels.sum(), 1.0)
    gained = [psnr(_encode(p * gain), g, m) for p, g, m in data]
    return {"kind": "run", "run": run.name, "dataset": Path(cfg["dataset"]).name, "sensor": sensor.name,
            "reset": sensor.reset, "pixel": pixel, "intensity": int(round(intensity)), "method": cfg["method"],
            "seed": int(cfg["seed"]), "iterations": int(metrics["iterations"]), "views": len(views),
            "views_from": metrics.get("views_from"),
            "psnr_object_metrics": metrics.get("psnr_object"),
            "psnr_object_saved": float(np.mean(saved)),
            "psnr_object_rate_loss_undone": {f"{s:g}": float(np.mean(v)) for s, v in undone.items()},
            "oracle_gain": gain, "psnr_object_oracle_gain": float(np.mean(gained)),
            "by_expected_count": {"edges": list(COUNT_EDGES), "spread": BIN_SPREAD,
                                  "pixels": (pixels / total).tolist(), "mse_saved": (se_saved / total).tolist(),
                                  "mse_undone": (se_undone / total).tolist()}}


def eligible(folder: Path) -> list[Path]:
    """Run folders under ``folder`` trained by the port or the default with true maps from all frames,
    evaluated (metrics.json and eval_test/ present)."""
    out = []
    for run in sorted(p for p in folder.iterdir() if p.is_dir()):
        try:
            cfg = json.loads((run / "config.json").read_text())
        except (OSError, ValueError):
            continue
        if (cfg.get("method") in METHODS and not cfg.get("sensor_maps") and cfg.get("frames") in (0, 256)
                and (run / "metrics.json").is_file() and (run / "eval_test").is_dir()):
            out.append(run)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="*", type=Path, help="run folders (evaluated)")
    ap.add_argument("--runs-dir", type=Path, help="take every eligible run folder in this folder")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    runs = list(args.runs)
    if args.runs_dir is not None:
        if not args.runs_dir.is_dir():
            print(f"error: {args.runs_dir}: no such folder", file=sys.stderr)
            return 2
        runs += eligible(args.runs_dir)
    if not runs:
        print("error: no run folder given (RUN ... or --runs-dir DIR with evaluated spikenerf-paper/spikelik runs)",
              file=sys.stderr)
        return 2
    from tqdm import tqdm

    rows = rate_rows()
    for r in rows:
        print(f"I {r['intensity']:2d} x {r['x']:.1f}: subtractive {r['subtractive']:.4f}  rsir {r['rsir']:.4f}  "
              f"published loop {r['hard_reset']:.4f} (spread 0.1: {r['hard_reset_spread']['0.1']:.4f})")
    try:
        with tqdm(runs, desc="runs", unit="run") as bar:  # closed (its line ended) before an error is said
            for run in bar:
                row = run_row(run)
                rows.append(row)
                tqdm.write(f"{row['run']}: as saved {row['psnr_object_saved']:.2f}, rate loss undone "
                           + ", ".join(f"{v:.2f} (spread {s})" for s, v in row["psnr_object_rate_loss_undone"].items())
                           + f", oracle gain {row['oracle_gain']:.3f}: {row['psnr_object_oracle_gain']:.2f}")
    except BadInput as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from spikegen.spikeio import write_bytes_atomic

    args.results.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(args.results, "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows).encode())
    print(f"{len(rows)} rows -> {args.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
