"""Click commands ``calibrate`` and ``diagnose`` (registered lazily by :mod:`spikegen.cli`).

Argument parsing only: the work is in :mod:`.calibrate` and :mod:`.diagnose`.
"""
from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ..errors import InputError
from ..sensor import KINDS
from ..spikeio import parse_size, read_radiance, read_spikes, read_spikes_packed, write_json_atomic


def _size(value):
    return None if value is None else parse_size(value)


def _flat(text: str):
    lux, sep, path = text.partition("=")
    try:
        value = float(lux)
    except ValueError:
        value = None
    if not sep or value is None or not path:
        raise InputError(f"--flat {text!r}: expected LUX=FILE, e.g. --flat 153=flat153.dat")
    return value, Path(path)


@click.command()
@click.option("--dark", "dark_path", required=True, type=click.Path(path_type=Path),
              help="Recording with the lens covered (.dat/.npz/.npy).")
@click.option("--flat", "flats", multiple=True, required=True, metavar="LUX=FILE",
              help="Uniform-light recording at LUX lux (give two).")
@click.option("--size", default=None, metavar="WxH", help="Frame size of .dat recordings.")
@click.option("--out", "prefix", required=True, type=click.Path(path_type=Path),
              help="Writes PREFIX.json + PREFIX.npz (a sensor usable as --sensor PREFIX.json).")
@click.option("--kind", type=click.Choice(KINDS), default="if", show_default=True,
              help="The camera's response: if (linear integrate-and-fire, Eqs. S2-S6) or rsir (the paper's "
                   "reference generator: R and its dark term fitted through its exact mean charge, the scale of LUX "
                   "with them).")
def calibrate(dark_path, flats, size, prefix, kind):
    """Responsivity and dark current from dark and flat-field recordings (Eqs. S2-S6, or the rsir fit)."""
    from ..sensorfile import save_sensor
    from .calibrate import calibrate as run

    wh = _size(size)
    parsed = dict(_flat(f) for f in flats)
    if len(parsed) != len(flats):
        raise InputError("--flat: two recordings at the same illuminance; give two different LUX values")
    dark = read_spikes(dark_path, wh)
    streams = {lux: read_spikes(p, wh) for lux, p in parsed.items()}
    cal = run(dark, streams, kind=kind)
    json_path, npz_path = save_sensor(cal.sensor(name=Path(prefix).name), prefix)
    click.echo(f"wrote {json_path} and {npz_path}")
    click.echo(f"reference pixel (row, col) {cal.reference_pixel}: response {cal.reference_vs_median:.4f} x median; "
               f"R median 1, 5-95 % {np.percentile(cal.responsivity, 5):.3f}-{np.percentile(cal.responsivity, 95):.3f}")
    click.echo(f"dark current median {np.median(cal.dark_lux):.4g} lux-eq ({np.median(cal.dark_rate):.4g} spikes/frame); "
               f"lux_to_rate {cal.lux_to_rate:.6g} spikes/frame/lux")
    if cal.flat_check is not None:
        click.echo(f"check: the {cal.flats_lux[0]:g} lux flat (not fitted) fires {cal.flat_check:.4f} x the model's rate "
                   "(median over pixels)")


@click.command()
@click.argument("measured", type=click.Path(path_type=Path))
@click.option("--reference", "ref", required=True,
              help="Radiance the camera saw: .npy (H,W)/(K,H,W), .exr, .png (sRGB), or 'self' (estimated from "
                   "the stream: a static scene, or one whose whole image moves, which is found and followed).")
@click.option("--size", default=None, metavar="WxH", help="Frame size of a .dat stream.")
@click.option("--intensity", type=float, default=None,
              help="Spikes per 256 frames at X = 1 (default: estimated from the data, with 'self': 256).")
@click.option("--sensor", "baseline", default="ideal", show_default=True,
              help="Baseline sensor: ideal|paper|rsir|calibrated|PATH.json.")
@click.option("--json", "json_path", type=click.Path(path_type=Path), default=None, help="Write the diagnosis as JSON.")
@click.option("--report", "report_dir", type=click.Path(path_type=Path), default=None,
              help="Write a Markdown report with plots to this folder.")
@click.option("--save-sensor", "save_prefix", type=click.Path(path_type=Path), default=None,
              help="Save the fitted extended sensor as PREFIX.json + PREFIX.npz.")
@click.option("--fit-fraction", type=click.FloatRange(0.3, 0.95), default=0.8, show_default=True,
              help="Fraction of frames used for the fit; the rest are held out to measure the gain.")
@click.option("--seed", type=int, default=0, show_default=True, help="Camera seed for baselines drawn from statistics.")
def diagnose(measured, ref, size, intensity, baseline, json_path, report_dir, save_prefix, fit_fraction, seed):
    """Name the sensor effects a measured stream shows, fit them, and measure the gain."""
    from tqdm import tqdm

    from ..presets import get_sensor
    from .bands import Stream
    from .diagnose import diagnose as run

    packed = read_spikes_packed(measured, _size(size))  # kept packed: an eighth of the memory
    spikes = Stream(packed[1], packed=packed[0]) if packed else Stream.of(read_spikes(measured, _size(size)))
    T, H, W = spikes.shape
    radiance = _reference(ref, H, W)
    if intensity is None:
        intensity = estimate_intensity(spikes, radiance)
    base = get_sensor(baseline, H, W, seed)
    bar = tqdm(total=4, desc="diagnose", unit="step", leave=False)

    def progress(msg):
        bar.set_postfix_str(msg)
        bar.update(1)

    try:
        result = run(spikes, radiance, intensity, base, fit_fraction=fit_fraction, progress=progress)
    finally:
        bar.close()
    result.info["measured"] = str(measured)
    result.info["reference_file"] = str(ref)
    doc = result.as_json()
    if json_path is not None:
        write_json_atomic(json_path, doc)
    if save_prefix is not None:
        from ..sensorfile import save_sensor

        save_sensor(result.extended, save_prefix)
    if report_dir is not None:
        from .report import write_report

        write_report(result, spikes, radiance, report_dir)
    _print_summary(result)


def _reference(ref: str, H: int, W: int):
    if ref == "self":
        return "self"
    x = read_radiance(ref)
    if x.shape[-2:] != (H, W):
        raise InputError(f"{ref}: reference is {x.shape[-1]}x{x.shape[-2]}, the measured stream is {W}x{H}")
    return x


def estimate_intensity(spikes, radiance) -> float:
    """``I`` such that the median unsaturated pixel fires at ``(I / 256) X``; 256 for ``self``.
    ``spikes``: ``[T, H, W]`` or a bands.Stream."""
    if isinstance(radiance, str):
        return 256.0
    from . import bands

    x = np.asarray(radiance, dtype=np.float64)
    x = x.mean(axis=0) if x.ndim == 3 else x
    stream = bands.Stream.of(spikes)
    T, H, W = stream.shape
    r = bands.window_rate(stream, bands.band_rows(T, H, W), 0, T).reshape(x.shape)
    ok = (r > 0) & (r < 0.8) & (x > 0)
    if ok.sum() < 10:
        raise InputError("cannot estimate --intensity: too few unsaturated pixels with light; give --intensity")
    return float(256.0 * np.median(r[ok] / x[ok]))


def _print_summary(result) -> None:
    det = result.detected
    click.echo("detected: " + (", ".join(det) if det else "nothing (the baseline explains the data)"))
    for e in sorted(result.effects, key=lambda e: -e.score):
        if e.detected:
            params = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in e.parameters.items()
                               if v is not None)
            click.echo(f"  {e.name}: score {e.score:.2f}  {params}")
    click.echo("held-out discrepancy (baseline -> extended):")
    for k, v in result.gain().items():
        click.echo(f"  {k}: {v['baseline']:.4g} -> {v['extended']:.4g}")
    motion = result.info.get("motion")
    if motion is not None:
        if motion["whole_image"]:
            click.echo(f"image motion (the scene, not the sensor): {motion['rows']['travel']:+.2f} rows, "
                       f"{motion['cols']['travel']:+.2f} columns over the recording; "
                       f"{motion['changed_pixels']} pixels it changes by > {motion['change_threshold']:.0%} not judged")
        else:
            click.echo("image motion: none found")
    held = result.heldout
    if held:
        click.echo(f"held-out score, nats per pixel (higher is better): ideal {held['ideal']:.4g} -> "
                   f"fitted {held['fitted']:.4g} ({held['pixels']} pixels judged)")
    click.echo("unexplained: " + (", ".join(u["statistic"] for u in result.unexplained) or "nothing"))
