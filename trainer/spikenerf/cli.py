"""Command line: ``spikenerf train DATASET ...``, ``spikenerf eval RUN`` and ``spikenerf render RUN``
(shared/specs/cli.md)."""
from __future__ import annotations

import sys
from pathlib import Path

import click

from spikegen.errors import SpikegenError

from .config import COARSE_FACTOR, COMPARE_WITH, ITERS_AT, RAY_ORDERS, SPACES, TV_LUMINANCE, TrainConfig
from .methods import DEFAULT_METHOD, METHODS, SRGB_LEAST_COUNT, SRGB_WEIGHT


class _Group(click.Group):
    """Turns project errors into one line on stderr and a non-zero exit (no traceback)."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except SpikegenError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(exc.exit_code)
        except KeyboardInterrupt:
            click.echo("interrupted; rerun the same command to resume from the last checkpoint", err=True)
            sys.exit(130)


@click.group(cls=_Group)
def main():
    """Radiance fields from spike streams (SpikeNeRF, CVPR 2024)."""


def _fractions(ctx, param, value: str) -> tuple:
    """``--upsample-at``'s callback: "0.1,0.2,0.3" -> (0.1, 0.2, 0.3); one to eight fractions, increasing, in
    (0, 1)."""
    try:
        fs = tuple(float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"{value!r}: expected fractions separated by commas, e.g. 0.1,0.2,0.3") from None
    if not 1 <= len(fs) <= 8 or not all(0 < f < 1 for f in fs) or any(b <= a for a, b in zip(fs, fs[1:])):
        raise click.BadParameter(f"{value!r}: expected one to eight fractions in (0, 1), increasing")
    return fs


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--method", default=DEFAULT_METHOD, show_default=True, type=click.Choice(list(METHODS)),
              help="Supervision: the published method, an idealised variant and its ablation, the TFP/TFI "
                   "baselines, the project's best (spikelik; spikelik-count: it without spike times, the "
                   "default before 2026-11-28), or the oracle (the ground-truth images).")
@click.option("--iters", default=TrainConfig.iters, show_default=True, type=click.IntRange(min=0),
              help="Training iterations; 0 = chosen from the image size (" +
                   ", ".join(f"{n} at {round(p ** 0.5)} x {round(p ** 0.5)}" for p, n in ITERS_AT) + ").")
@click.option("--device", default="auto", show_default=True, type=click.Choice(["auto", "cpu", "cuda"]))
@click.option("--resolution", default=0, type=click.IntRange(min=0),
              help="Train at this width (must divide the dataset's); 0 = the dataset's.")
@click.option("--frames", default=None, type=int,
              help="Train from the first W frames of each stream (1..the dataset's frames; default all).")
@click.option("--windows", default=TrainConfig.windows, show_default=True, type=click.IntRange(min=0),
              help="Count windows per view of a moving camera, each seen from its own pose (count methods only); "
                   "0 = the fewest in which the image moves by at most 2.5 pixels.")
@click.option("--sensor-maps", "sensor_maps", default="", type=click.Path(path_type=str),
              help="Take R and the dark current from this sensor .json (e.g. from `spikegen calibrate`) instead of "
                   "the dataset's own (true) maps.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=None,
              help="Run folder (default runs/<dataset>_<method>). An existing checkpoint there is resumed.")
@click.option("--seed", default=TrainConfig.seed, show_default=True, type=int)
@click.option("--batch-rays", default=TrainConfig.batch_rays, show_default=True, type=click.IntRange(min=1))
@click.option("--lr-grid", default=TrainConfig.lr_grid, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Adam's learning rate of the voxel grids at the start (it decays to --lr-decay of it over the run).")
@click.option("--lr-decay", default=TrainConfig.lr_decay, show_default=True,
              type=click.FloatRange(min=0, max=1, min_open=True),
              help="The learning rates decay exponentially to this fraction of their start over the run (1 = none).")
@click.option("--adam-eps", default=TrainConfig.adam_eps, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Adam's eps for the voxel grids: a voxel whose gradient's RMS is below it steps by less than the "
                   "learning rate.")
@click.option("--error-rays", default=TrainConfig.error_rays, show_default=True,
              type=click.FloatRange(min=0, max=1, max_open=True),
              help="The fraction of each step's rays drawn where the field's error has been high (tiles of an error "
                   "map); the rest are drawn uniformly. 0 = all uniform.")
@click.option("--ray-order", "ray_order", type=click.Choice(RAY_ORDERS), default=TrainConfig.ray_order,
              show_default=True,
              help="uniform: each step's rays drawn independently (a pixel may repeat before another is drawn); "
                   "shuffled: every ray of every train view once an epoch, in an order seeded by --seed.")
@click.option("--coarse-to-fine", "coarse_to_fine", default=TrainConfig.coarse_to_fine, show_default=True,
              type=click.FloatRange(min=0, max=1, max_open=True),
              help=f"Train the first fraction F of the iterations on the images box-downsampled {COARSE_FACTOR} "
                   "times a side (growing the grid as a run at that size does), then the rest at full size. 0 = full "
                   "size throughout.")
@click.option("--srgb-weight", "srgb_weight", default=None, type=click.FloatRange(min=0), metavar="MOST",
              help="Weight each ray's likelihood term by the sRGB encoding's slope at its rendered luminance over "
                   "the slope at grey, squared, at most MOST (385 and above: no cap), so that dark errors weigh as "
                   f"on a display (spikelik methods). 0 = off. [default: {SRGB_WEIGHT:g} for spikelik and "
                   f"spikelik-count where a white pixel counts at least {SRGB_LEAST_COUNT:g} spikes a count window "
                   "(intensity x frames / 256 / windows, times the sensor pixels a smaller --resolution averages), "
                   "else off; off for the other methods; a resumed run keeps its own]")
@click.option("--sh-degree", default=TrainConfig.sh_degree, show_default=True, type=click.IntRange(0, 2),
              help="View-dependent luminance: spherical harmonics up to this degree (0 = view-independent).")
@click.option("--grid-final", default=TrainConfig.grid_final, show_default=True, type=click.IntRange(min=0),
              help="Final grid resolution: points across the cube [-1.5, 1.5], or across [-1, 1] in NDC for a "
                   "forward-facing capture (0 = chosen from the image width).")
@click.option("--fit-box/--no-fit-box", default=TrainConfig.fit_box, show_default=True,
              help="Crop the grid to the box the object occupies before each growth (an object on white; a "
                   "scene that fills the frame keeps the whole box).")
@click.option("--space", type=click.Choice(SPACES), default=TrainConfig.space, show_default=True,
              help="The field's space for a scene that fills the frame (an imported capture): the world cube, "
                   "NDC (views facing one way), or auto (NDC where it applies, else the cube). Objects on white "
                   "use the cube.")
@click.option("--stop-transmittance", default=TrainConfig.stop_transmittance, show_default=True,
              type=click.FloatRange(min=0, max=1),
              help="Early ray termination: samples a ray reaches with less transmittance are not rendered (0 = none).")
@click.option("--step-ratio", default=TrainConfig.step_ratio, show_default=True,
              type=click.FloatRange(min=0.1, max=2),
              help="The sample step along a ray, in voxels of the current grid.")
@click.option("--upsample-at", "upsample_at", default=",".join(f"{f:g}" for f in TrainConfig.upsample_at),
              show_default=True, callback=_fractions, metavar="F,F,...",
              help="The fractions of the iterations at which the grid grows, in increasing order in (0, 1): as many "
                   "growths, each by the same factor, from the start size to the final size.")
@click.option("--tv-weight", default=TrainConfig.tv_weight, show_default=True, type=click.FloatRange(min=0),
              help="Weight of the total-variation (smoothness) prior on the grids.")
@click.option("--tv-luminance", "tv_luminance", type=click.Choice(TV_LUMINANCE), default=TrainConfig.tv_luminance,
              show_default=True,
              help="What the prior compares of the luminance: its logit (as stored); the logit clamped from below at "
                   "luminance 0.02 (floored); the luminance itself (linear) or its sRGB encoding (srgb), each scaled "
                   "to the logit's slope at grey; or nothing (off: the density alone).")
@click.option("--tv-points", default=TrainConfig.tv_points, show_default=True, type=click.IntRange(min=0),
              help="Put the prior at the voxels of this many of each step's sample points (0 = a random block).")
@click.option("--lazy-above", default=TrainConfig.lazy_above, show_default=True, type=click.IntRange(min=0),
              metavar="VOXELS", help="Grids with more voxels than this train with the lazy Adam, which updates only "
                                     "the voxels a step read (0 = never).")
@click.option("--checkpoint-every", default=TrainConfig.checkpoint_every, show_default=True,
              type=click.IntRange(min=1),
              help=f"Save a checkpoint every N iterations (and at least every {TrainConfig.checkpoint_every_s:g} s).")
@click.option("--eval/--no-eval", "do_eval", default=False, help="Evaluate on the test split when done.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def train(dataset, method, iters, device, resolution, frames, windows, sensor_maps, out, seed, batch_rays, lr_grid,
          lr_decay, adam_eps, error_rays, ray_order, coarse_to_fine, srgb_weight, sh_degree,
          grid_final, fit_box, space, stop_transmittance, step_ratio, upsample_at, tv_weight, tv_luminance, tv_points,
          lazy_above,
          checkpoint_every, do_eval, quiet):
    """Train a radiance field on a spike dataset folder (dataset.md)."""
    from .train import train as run_train

    dataset = dataset.resolve()
    out = out or Path("runs") / f"{dataset.name}_{method}"
    cfg = TrainConfig(dataset=str(dataset), method=method, iters=iters, device=device, resolution=resolution,
                      frames=frames, windows=windows, seed=seed, batch_rays=batch_rays, lr_grid=lr_grid, lr_decay=lr_decay,
                      adam_eps=adam_eps, error_rays=error_rays, ray_order=ray_order, coarse_to_fine=coarse_to_fine,
                      srgb_weight=srgb_weight, sh_degree=sh_degree,
                      grid_final=grid_final, fit_box=fit_box, stop_transmittance=stop_transmittance,
                      step_ratio=step_ratio, upsample_at=upsample_at, tv_weight=tv_weight,
                      tv_luminance=tv_luminance, tv_points=tv_points,
                      space=space, lazy_above=lazy_above,
                      checkpoint_every=checkpoint_every,
                      sensor_maps=str(Path(sensor_maps).resolve()) if sensor_maps
                      else "")
    ck = run_train(cfg, out, progress=not quiet, log=lambda m: click.echo(m, err=True))
    click.echo(f"checkpoint: {ck}")
    if do_eval:
        _eval(out, "test", device, quiet)


@main.command("eval")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--split", default="test", show_default=True)
@click.option("--device", default="auto", show_default=True, type=click.Choice(["auto", "cpu", "cuda"]))
@click.option("--quiet", is_flag=True)
@click.option("--compare-with", "compare_with", type=click.Choice(COMPARE_WITH), default="auto", show_default=True,
              help="auto: each view's ground truth where it has one, else its long-window reconstruction.")
def eval_cmd(run, split, device, quiet, compare_with):
    """Render the held-out views of RUN and write RUN/metrics.json and images."""
    _eval(run, split, device, quiet, compare_with)


@main.command("render")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--path", "path_name", default="orbit", show_default=True, help="Camera path: orbit or spiral.")
@click.option("--frames", default=60, show_default=True, type=int, help="Frames along the path (at least 1).")
@click.option("--out", "out", type=click.Path(path_type=Path), required=True,
              help="Animation to write: .gif (Pillow) or .mp4 (needs imageio-ffmpeg, the `video` extra).")
@click.option("--fps", default=20.0, show_default=True, type=float, help="Frames per second (at most 100).")
@click.option("--device", default="auto", show_default=True, help="auto, cpu or cuda.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def render_cmd(run, path_name, frames, out, fps, device, quiet):
    """Render RUN's field along a camera path into an animation: luminance | depth | opacity.

    \b
    Depth (expected distance along the ray; light passing through counts as far) runs from yellow
    at 2 to dark purple at 6 (NeRF-synthetic near, far); opacity from black (0) to white (1).
    Every camera looks at the origin, world +Z up; frame k of N is at s = k / N; r is the median
    distance of the dataset's training cameras from the origin (4.0311 for NeRF-synthetic).
      orbit:  azimuth 360 s deg, elevation 30 deg, distance r (the NeRF-synthetic test circle)
      spiral: azimuth 720 s deg (two turns), elevation 30 - 20 cos(2 pi s) deg (10 to 50 and
              back), distance r (1 - 0.075 (1 - cos(2 pi s))) (r to 0.85 r and back)
    A run of a forward-facing capture (its field in NDC) circles its reference camera instead,
    turned as it is, at the training cameras' median distance r from it (orbit: once in its image
    plane; spiral: twice, moving forward by r (1 - cos(2 pi s)) / 2); depth is then the NDC z,
    yellow at -1 (near plane) to dark purple at 1 (infinity).
    """
    from .video import render_video

    try:
        n = render_video(run, path_name, frames, out, fps=fps, device=device, progress=not quiet,
                         log=lambda m: click.echo(m, err=True))
    except KeyboardInterrupt:  # the animation is written under a temporary name: nothing is left
        click.echo(f"interrupted; {out} not written", err=True)
        sys.exit(130)
    click.echo(f"{out}: {n} frames ({path_name}, {fps:g} fps)")


def _eval(run, split, device, quiet, compare_with="auto"):
    from .eval import evaluate

    m = evaluate(run, split, device=device, progress=not quiet, compare_with=compare_with)
    click.echo(f"{run}/metrics.json: {m['views']} views against their {m['compared_with']}, PSNR {m['psnr']:.2f} dB "
               f"(object {m['psnr_object']:.2f}), SSIM {m['ssim']:.3f} (object {m['ssim_object']:.3f}), "
               f"LPIPS {m['lpips']}")


if __name__ == "__main__":
    main()
