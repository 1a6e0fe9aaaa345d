"""``spikegen`` command line (shared/specs/cli.md). Argument parsing lives here only."""
from __future__ import annotations

import errno
import importlib
import sys
from pathlib import Path

import click
import numpy as np

from . import __version__
from .errors import InputError, SpikegenError

# Commands implemented in other modules, imported only when used (keeps `--help` fast and
# keeps bpy / plotting out of commands that do not need them).
LAZY_COMMANDS = {
    "render": "spikegen.cli_render:render",
    "calibrate": "spikegen.fidelity.cli:calibrate",
    "diagnose": "spikegen.fidelity.cli:diagnose",
}


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | {n for n in LAZY_COMMANDS if self._load(n)})

    def get_command(self, ctx, name):
        return super().get_command(ctx, name) or self._load(name)

    @staticmethod
    def _load(name):
        target = LAZY_COMMANDS.get(name)
        if target is None:
            return None
        module, attr = target.split(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError):
            return None


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="spikegen")
def cli():
    """Spike-camera datasets: sensor model, conversion, rendering, calibration."""


def _size(value):
    from .spikeio import parse_size

    return None if value is None else parse_size(value)


# ---------------------------------------------------------------------- convert
@cli.command()
@click.argument("source", type=click.Path(path_type=Path))
@click.option("--intensity", "intensities", multiple=True, required=True,
              help="Spikes per 256 frames at X = 1 (repeatable: 16, 32, 64 in the paper).")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=Path("out"), show_default=True,
              help="Folder that receives <name>_i<I>/.")
@click.option("--sensor", default="paper", show_default=True,
              help="ideal | paper | rsir | calibrated | path to a sensor .json.")
@click.option("--frames", type=int, default=256, show_default=True, help="Readout frames T per view.")
@click.option("--resolution", type=int, default=None, help="Resample views to N x N (default: as the source).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every random draw.")
@click.option("--workers", type=int, default=1, show_default=True, help="Local worker processes.")
@click.option("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786) to run views on.")
@click.option("--lens-k1", type=float, default=0.0, show_default=True,
              help="Image the views through a radial lens of this k1 > 0 (COLMAP SIMPLE_RADIAL; 0: pinhole).")
def convert(source, intensities, out_dir, sensor, frames, resolution, seed, workers, scheduler, lens_k1):
    """Turn a render folder or a NeRF-synthetic folder into spike datasets (never renders)."""
    from .dataset import convert as run

    folders = run(source, out_dir, intensities, sensor=sensor, frames=frames, seed=seed, resolution=resolution,
                  workers=workers, scheduler=scheduler, progress=True, lens_k1=lens_k1)
    for f in folders:
        click.echo(str(f))


# ---------------------------------------------------------------------- verify
@cli.command()
@click.argument("dataset", type=click.Path(path_type=Path))
def verify(dataset):
    """Check every file of DATASET against its manifest.json."""
    from .dataset import verify as run

    problems = run(dataset)
    if problems:
        for p in problems:
            click.echo(f"{dataset}: {p}", err=True)
        raise SystemExit(1)
    click.echo(f"{dataset}: OK")


# ---------------------------------------------------------------------- import
@cli.command("import")
@click.argument("capture", type=click.Path(path_type=Path))
@click.option("--size", required=True, help="WxH of the sensor, e.g. 400x250 (a .dat has no header).")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Dataset folder to write.")
@click.option("--calibration", default=None, help="PREFIX of a sensor from `spikegen calibrate` (PREFIX.json).")
@click.option("--frames", type=int, default=None, help="Use the first N frames of each file [default: all of the "
              "shortest file's].")
@click.option("--recon", "reconstruction", type=click.Choice(["tfp", "tfi"]), default="tfp", show_default=True,
              help="Image per view: TFP over the whole stream, or TFI at the middle frame (docs/real_captures.md).")
@click.option("--camera-model", type=click.Choice(["simple-pinhole", "simple-radial"]), default="simple-pinhole",
              show_default=True, help="COLMAP camera: one focal length, and with simple-radial a radial lens k1.")
@click.option("--truth-images", type=click.Path(path_type=Path), default=None,
              help="Folder with the true image <stem>.png of every spike file (a synthetic capture): held-out "
                   "views are then scored against it.")
def import_(capture, size, out_dir, calibration, frames, reconstruction, camera_model, truth_images):
    """A folder of real spike recordings, one file per viewpoint, as a dataset folder with poses and
    intrinsics from structure from motion (pycolmap)."""
    from .importer import import_capture

    click.echo(str(import_capture(capture, _size(size), out_dir, calibration, frames, reconstruction,
                                  camera_model=camera_model, truth_images=truth_images)))


# ---------------------------------------------------------------------- info / preview
ANIMATION_WINDOW = 16  # frames of TFP per animation frame, unless --window says otherwise


@cli.command()
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--size", default=None, help="WxH of a .dat file (default: from its dataset folder's config.yaml).")
def info(file, size):
    """Frames, size, spike count and mean rate of a spike file."""
    from .spikeio import read_spikes

    s = read_spikes(file, _size(size))
    T, H, W = s.shape
    n = int(s.sum(dtype=np.int64))
    click.echo(f"file: {file}\nframes: {T}\nsize: {W}x{H}\nspikes: {n}\n"
               f"mean rate: {n / max(1, s.size):.4f} spikes per pixel-frame")


@cli.command()
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--out", "out_png", type=click.Path(path_type=Path), required=True,
              help="PNG to write (TFP | TFI), or a .gif / .mp4 animation of the stream (TFP over sliding windows).")
@click.option("--size", default=None, help="WxH of a .dat file (default: from its dataset folder's config.yaml).")
@click.option("--window", type=int, default=None,
              help=f"Frames averaged (TFP window; default: all for a PNG, {ANIMATION_WINDOW} for an animation).")
@click.option("--step", type=int, default=None,
              help="Animation: frames from one window's start to the next (default: a quarter of the window).")
@click.option("--fps", type=float, default=10.0, show_default=True, help="Animation: frames per second.")
def preview(file, out_png, size, window, step, fps):
    """Spike-rate image of a spike file (TFP over a window), as a PNG; or, with a .gif / .mp4
    --out, an animation: one frame of TFP per window, windows every --step frames."""
    from .preview import preview_image
    from .spikeio import read_spikes, write_png

    if window is not None and window < 1:
        raise InputError(f"--window {window}: must be at least 1 frame")
    if out_png.suffix.lower() != ".png":
        return _preview_animation(file, out_png, size, window or ANIMATION_WINDOW, step, fps)
    s = read_spikes(file, _size(size))
    write_png(out_png, preview_image(s, window))
    click.echo(str(out_png))


def _preview_animation(file, out, size, window, step, fps):
    from .animation import FORMATS, check_animation, write_animation
    from .preview import animation_frames, window_starts
    from .spikeio import read_spikes

    if out.suffix.lower() not in FORMATS:
        raise InputError(f"--out {out}: expected a .png, {' or '.join(FORMATS)} path")
    check_animation(out, fps)
    step = max(1, window // 4) if step is None else step
    window_starts(window, window, step)  # checks --step before the file is read
    s = read_spikes(file, _size(size))
    n = write_animation(out, animation_frames(s, window, step), fps)
    click.echo(f"{out}: {n} frames, TFP over {min(window, s.shape[0])} frames every {step}")


# ---------------------------------------------------------------------- entry point
def main(argv=None) -> int:
    """Run the CLI; any user error becomes one line on stderr and a non-zero exit code."""
    try:
        cli.main(args=argv, prog_name="spikegen", standalone_mode=False)
    except SpikegenError as exc:
        click.echo(f"spikegen: error: {exc}", err=True)
        return exc.exit_code
    except click.exceptions.Abort:
        click.echo("spikegen: interrupted", err=True)
        return 130
    except click.ClickException as exc:
        click.echo(f"spikegen: error: {exc.format_message()}", err=True)
        return exc.exit_code
    except KeyboardInterrupt:
        click.echo("spikegen: interrupted (finished views are kept; rerun the same command to resume)", err=True)
        return 130
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            click.echo(f"spikegen: error: disk full while writing {exc.filename or ''}".rstrip(), err=True)
            return 3
        click.echo(f"spikegen: error: {exc.filename or ''}: {exc.strerror or exc}", err=True)
        return 3
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 0
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
