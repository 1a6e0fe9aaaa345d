"""``spikegen diagnose --report DIR``: the diagnosis as a person reads it (Markdown + PNG plots).

matplotlib (Agg) is imported here only; every file is written atomically.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..spikeio import atomic_path, write_bytes_atomic
from . import bands, stats

ISI_MAX = 200  # the interval histogram's last bin (frames)


def save_figure(path, draw, size=(5.5, 4.0), dpi=110):
    """Draw on one matplotlib axis (``draw(ax)``, Agg backend) and write a PNG atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=size)
    try:
        draw(ax)
        fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=dpi)
    finally:
        plt.close(fig)


def _plots(result, spikes, radiance, out: Path) -> list:
    """Write the report's PNGs into ``out``; returns ``[(file name, caption)]``. ``spikes``: the
    measured stream ``[T, H, W]`` or a :class:`~.bands.Stream` (packed): its fit frames are read a
    band of rows at a time, never unpacked whole."""
    Tf = result.info["fit_frames"]
    stream = bands.Stream.of(spikes)
    names = []
    if not isinstance(radiance, str) and result.fit.rate.lam_pred is not None:
        names += _model_plots(result, radiance, out)
    if getattr(result, "static", None) is not None and not result.static.all():
        names.append(_static_plot(result.static, out))
    signal, histogram = _fit_frame_sums(stream, Tf)
    names.append(_spectrum_plot(signal, out))
    names.append(_isi_plot(histogram, out))
    return names


def _fit_frame_sums(stream: "bands.Stream", Tf: int) -> tuple[np.ndarray, np.ndarray]:
    """``(population signal [Tf], interval counts [ISI_MAX + 1])`` of the first ``Tf`` frames: the
    spikes of all pixels per frame, and how many intervals (a pixel's own, so none crosses a band)
    last k frames, k = 1 .. ISI_MAX (longer ones are not counted); summed band by band."""
    T, H, W = stream.shape
    signal = np.zeros(Tf, dtype=np.int64)
    histogram = np.zeros(ISI_MAX + 1, dtype=np.int64)
    for r0, r1 in bands.bands(H, bands.band_rows(Tf, H, W)):
        band = stream.rows(r0, r1, 0, Tf)
        signal += band.reshape(Tf, -1).sum(axis=1, dtype=np.int64)
        isi, _ = stats.intervals(band)
        histogram += np.bincount(isi[isi <= ISI_MAX].astype(np.int64), minlength=ISI_MAX + 1)
    return signal.astype(np.float64), histogram


def _model_plots(result, radiance, out: Path) -> list:
    """Rates against radiance (measured, baseline, fitted model) and the residual map."""
    rate_fit, structure = result.fit.rate, result.fit.structure
    x = np.asarray(radiance, dtype=np.float64)
    xm = (x.mean(axis=0) if x.ndim == 3 else x).reshape(-1)
    measured = 1.0 / rate_fit.isi
    model = 1.0 / rate_fit.predicted_isi()
    ideal = np.minimum(result.info["intensity"] / 256.0 * xm, 1.0)

    def rate_plot(ax):
        ax.loglog(xm, measured, ".", ms=2, alpha=0.4, label="measured")
        o = np.argsort(xm)
        ax.loglog(xm[o], ideal[o], "k-", lw=1, label="baseline (ideal)")
        ax.loglog(xm[o], model[o], "r.", ms=1, alpha=0.5, label="fitted model")
        ax.set_xlabel("reference radiance X")
        ax.set_ylabel("spikes / frame")
        ax.legend(fontsize=8)

    save_figure(out / "rates.png", rate_plot)
    names = [("rates.png", "Per-pixel rate against radiance: measured, baseline, fitted model.")]
    if structure.e is not None:
        e = np.where(np.isfinite(structure.e), structure.e, np.nan).reshape(result.info["height"], result.info["width"])

        def map_plot(ax):
            im = ax.imshow(e, cmap="coolwarm", vmin=np.nanpercentile(e, 1), vmax=np.nanpercentile(e, 99))
            ax.figure.colorbar(im, ax=ax, label="measured / model rate")
            ax.set_title("per-pixel responsivity residual")

        save_figure(out / "residual_map.png", map_plot)
        names.append(("residual_map.png", "Measured over modelled rate per pixel (gain, columns, hot pixels)."))
    return names


def _static_plot(static, out: Path) -> tuple:
    """The pixels judged (static) and those left out because the scene moves there."""

    def draw(ax):
        ax.imshow(static, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(f"static pixels (white): {int(static.sum())} of {static.size}")

    save_figure(out / "static_mask.png", draw)
    return "static_mask.png", "Pixels whose rate does not change (white); only these are judged with 'self'."


def _spectrum_plot(s: np.ndarray, out: Path) -> tuple:
    """Power spectrum of the population signal ``s [Tf]`` (spikes of all pixels per fit frame)."""
    Tf = s.shape[0]

    def spectrum_plot(ax):
        p = np.abs(np.fft.rfft(s - s.mean())) ** 2 / Tf
        f = np.fft.rfftfreq(Tf)
        ax.semilogy(f[1:], p[1:], lw=0.8)
        ax.set_xlabel("frequency (1 / frames)")
        ax.set_ylabel("power of the population signal")

    save_figure(out / "spectrum.png", spectrum_plot)
    return "spectrum.png", "Temporal spectrum of the population signal (flicker shows as a line)."


def _isi_plot(histogram: np.ndarray, out: Path) -> tuple:
    """Pooled inter-spike-interval histogram (``histogram[k]``: intervals of k frames) of the fit frames."""

    def isi_plot(ax):
        top = int(np.flatnonzero(histogram)[-1]) if histogram.any() else 0
        if top:
            ax.stairs(histogram[1:top + 1], np.arange(0.5, top + 1.5), fill=True)
            ax.set_yscale("log")
        ax.set_xlabel("inter-spike interval (frames)")
        ax.set_ylabel("count")

    save_figure(out / "isi.png", isi_plot)
    return "isi.png", "Pooled inter-spike-interval histogram of the fit frames."


def markdown(result, figures=()) -> str:
    info = result.info
    lines = ["# spikegen diagnose", "",
             f"Measured: `{info.get('measured', '?')}`, {info['width']}x{info['height']}, {info['frames']} frames "
             f"({info['fit_frames']} fitted, {info['held_out_frames']} held out); intensity {info['intensity']:.4g}; "
             f"reference: {info['reference']}; baseline sensor `{info['baseline_sensor']}`.", "",
             "## Effects", "",
             "Detected, strongest first: " + (", ".join(f"`{n}`" for n in result.detected) or "none") + ".", "",
             "| effect | detected | score (x envelope) | z | parameters | note |", "|---|---|---|---|---|---|"]
    for e in sorted(result.effects, key=lambda e: (-int(e.detected), -e.score)):
        params = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in e.parameters.items())
        lines.append(f"| {e.name} | {'yes' if e.detected else 'no'} | {e.score:.3g} | {e.z:.3g} | {params} | {e.note} |")
    lines += ["", "## Held-out frames: baseline against extended model", "",
              "| measure | baseline | extended | meaning |", "|---|---|---|---|"]
    for k, v in result.gain().items():
        lines.append(f"| {k} | {v['baseline']:.4g} | {v['extended']:.4g} | {stats.MEASURES[k]} |")
    lines += _motion_lines(result) + _heldout_lines(result)
    for name, caption in figures:
        lines += [f"![{caption}]({name})", "", caption, ""]
    return "\n".join(lines)


def _motion_lines(result) -> list:
    """With ``self``: whether the whole image moved (a property of the scene, not an effect)."""
    motion = result.info.get("motion")
    if motion is None:
        return []
    if not motion["whole_image"]:
        return ["", "## Image motion", "", "No motion of the whole image found (drift.image_motion).", ""]
    r, c = motion["rows"], motion["cols"]
    return ["", "## Image motion", "",
            f"The whole image moves (the scene or the camera, not the sensor): {r['travel']:+.2f} rows "
            f"(SE {r['se']:.2g}) and {c['travel']:+.2f} columns (SE {c['se']:.2g}) from the first frame to the "
            f"last. The {motion['changed_pixels']} pixels whose rate it changes by more than "
            f"{motion['change_threshold']:.0%} are not judged.", ""]


def _heldout_lines(result) -> list:
    """The held-out score of the ideal and the fitted model, and what the fitted one does not explain."""
    held = getattr(result, "heldout", None) or {}
    lines = [""]
    if held:
        lines += ["## Held-out score", "", f"{held['measure']} (higher is better): ideal {held['ideal']:.4g}, "
                  f"fitted {held['fitted']:.4g}; {held['pixels']} pixels judged.", ""]
    found = getattr(result, "unexplained", None) or []
    lines += ["## Unexplained", "", "Statistics of the held-out frames the fitted model does not reproduce: "
              + (", ".join(f"`{u['statistic']}` ({u['value']:.3g}, z {u['z']:.3g}: {u['meaning']})" for u in found)
                 or "none") + ".", ""]
    return lines


def write_report(result, spikes, radiance, out_dir) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = _plots(result, spikes, radiance, out)
    path = out / "report.md"
    write_bytes_atomic(path, markdown(result, figures).encode("utf-8"))
    return path
