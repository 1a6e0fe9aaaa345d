"""How close each train view's count comes to its ground truth, read from the counts or from the spike times.

    python bench/bench_interval.py DATASET [--views 6]

For the first ``--views`` train views of a spike dataset whose train views have ground-truth images and
whose sensor is integrate-and-fire with subtractive reset: the whole stream's count (``spikelik-count``'s
target) and the count its first and last spike times imply (``spikelik``'s, targets.interval_statistic),
each turned back into luminance through the dataset's own R and dark current, against the view's
ground-truth luminance: the rate's RMS error inside the object and the object PSNR of the sRGB images, per
view. A diagnostic of the targets, not of a trained field; it makes no decision. Use it on the project's
procedural scenes (``spikegen render``), not on the views a benchmark reports.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from spikegen.errors import InputError
from spikegen.spikeio import linear_to_srgb
from spikenerf.data import ground_truth, has_ground_truth, load_dataset, load_sensor_maps, read_view_spikes
from spikenerf.targets import interval_statistic


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10.0 * np.log10(np.mean((a - b) ** 2)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--views", type=int, default=6)
    args = ap.parse_args()
    try:
        ds = load_dataset(args.dataset)
    except InputError as e:
        sys.exit(f"error: {e}")
    sm = load_sensor_maps(ds)
    if sm.kind != "if" or sm.reset != "subtract":
        sys.exit(f"{ds.root}: the sensor is {sm.kind!r} with reset {sm.reset!r}; spike times are read only on "
                 "an integrate-and-fire sensor with subtractive reset")
    views = [v for v in ds.splits["train"] if has_ground_truth(v)][:max(1, args.views)]
    if not views:
        sys.exit(f"{ds.root}: no train view with a ground-truth image")
    resp, dark = sm.resp.astype(np.float64), sm.dark.astype(np.float64)
    n, gain = ds.frames, ds.intensity / 256.0
    print(f"{ds.root}: I = {ds.intensity:g}, {n} frames, sensor {sm.kind} (N_e {sm.electrons:g}, "
          f"jitter {sm.threshold_jitter:g}); inside the object (alpha > 0)")
    print(f"{'view':>12} {'rate RMS, count':>16} {'spike times':>12} {'PSNR, count':>12} {'spike times':>12}")
    gains = []
    for view in views:
        spikes = read_view_spikes(ds, view)
        x, alpha = ground_truth(view, ds.height, ds.width)
        inside = alpha > 0
        rate = resp * (gain * x + dark)
        truth = linear_to_srgb(x.astype(np.float64))[inside]
        row = []
        for count in (spikes.sum(axis=0, dtype=np.int32).astype(np.float64),
                      interval_statistic(spikes, sm.electrons, sm.threshold_jitter)):
            err = np.sqrt(np.mean((count / n - rate)[inside] ** 2))
            lum = np.clip((count / n / resp - dark) / gain, 0.0, None)
            row.append((err, _psnr(linear_to_srgb(lum)[inside], truth)))
        gains.append(row[1][1] - row[0][1])
        print(f"{view.name:>12} {row[0][0]:16.2e} {row[1][0]:12.2e} {row[0][1]:12.2f} {row[1][1]:12.2f}")
    print(f"object PSNR from the spike times minus from the count: {np.mean(gains):+.2f} dB "
          f"(mean of {len(gains)} views; min {np.min(gains):+.2f}, max {np.max(gains):+.2f})")


if __name__ == "__main__":
    main()
