"""``spikegen render``: render a scene once through Blender, then convert it to every intensity."""
from __future__ import annotations

import dataclasses
import signal
import threading
from pathlib import Path

import click

from .dataset import check_lens_k1
from .errors import InputError
from .camera import HANDHELD_SIZE, HANDHELD_VIEWS
from .formats import DEFAULT_MOTION_DEG, QUICK, RIGS, RenderJob
from .render import RenderFolder, check_export, convert_all, identify_blend, images_per_view, parse_views, \
    render_steps
from .scenes import SCENES
from .spikeio import parse_size


@click.command()
@click.option("--scene", default=None, help=f"Built-in scene: {' | '.join(SCENES)}.")
@click.option("--intensity", "intensities", multiple=True, required=True,
              help="Spikes per 256 frames at X = 1 (repeatable: 16, 32, 64 in the paper).")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=Path("out"), show_default=True,
              help="Folder receiving <scene>_render/ and <scene>_i<I>/.")
@click.option("--resolution", default=None,
              help="Image size, N (N x N) or WxH [default: 400; 100 with --quick; 400x250 with --rig handheld].")
@click.option("--views", default=None,
              help="train,val,test view counts [default: 100,100,200; 20,4,8 with --quick; 35,0,0 with --rig "
                   "handheld].")
@click.option("--rig", type=click.Choice(RIGS), default="nerf", show_default=True,
              help="nerf: the NeRF-synthetic sphere; handheld: a forward-facing handheld capture "
                   "(docs/real_captures.md).")
@click.option("--subframes", type=int, default=16, show_default=True, help="Sub-frames K rendered per view.")
@click.option("--frames", type=int, default=256, show_default=True, help="Readout frames T per view.")
@click.option("--motion", "motion_deg", type=float, default=DEFAULT_MOTION_DEG, show_default=True,
              help="Degrees the camera orbits (about world Z) during a view's frames; 0 = static.")
@click.option("--samples", type=int, default=RenderJob.samples, show_default=True,
              help="Cycles samples per sub-frame (the same noise pattern in every sub-frame of a view).")
@click.option("--png-samples", type=int, default=RenderJob.png_samples, show_default=True,
              help="Cycles samples of the ground-truth PNG (at least --samples).")
@click.option("--denoise/--no-denoise", default=RenderJob.denoise, show_default=True,
              help="OpenImageDenoise on every image (a deterministic function of the image).")
@click.option("--engine", type=click.Choice(["cycles", "workbench"]), default="cycles", show_default=True,
              help="cycles (default) or workbench (quick previews).")
@click.option("--blend", type=click.Path(path_type=Path), default=None, help="Render this .blend instead.")
@click.option("--sensor", default="paper", show_default=True,
              help="ideal | paper | rsir | calibrated | path to a sensor .json.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of cameras, render noise and spikes.")
@click.option("--workers", type=int, default=1, show_default=True, help="Local worker processes for conversion.")
@click.option("--scheduler", default=None, help="Dask scheduler address for conversion.")
@click.option("--quick", is_flag=True, help="Small and fast: 100 x 100, views 20,4,8 (unless given).")
@click.option("--device", type=click.Choice(["auto", "cpu", "gpu"]), default="auto", show_default=True,
              help="Cycles device: auto = the first GPU backend found (OptiX, CUDA, HIP, Metal, oneAPI), else the "
                   "CPU; gpu = refuse to run without one. Recorded in render.json; GPU and CPU bytes differ.")
@click.option("--lens-k1", type=float, default=0.0, show_default=True,
              help="Convert through a radial lens of this k1 > 0 (as spikegen convert --lens-k1; 0: pinhole).")
@click.option("--gpu-index", type=click.IntRange(min=0), default=None,
              help="Render on this one GPU of the backend (e.g. one per process on a multi-GPU machine).")
def render(scene, intensities, out_dir, resolution, views, subframes, frames, motion_deg, samples, png_samples,
           denoise, engine, blend, sensor, seed, workers, scheduler, quick, device, gpu_index, rig, lens_k1):
    """Render a scene through Blender and write <out>/<scene>_i<I>/ for each intensity."""
    name, source = _scene_name(scene, blend)
    width, height = _image_size(resolution, rig, quick)
    counts = parse_views(views) if views else _default_views(rig, quick)
    job = RenderJob(name, width, height, counts, subframes, frames, motion_deg, engine, samples, png_samples, seed,
                    source=source, denoise=denoise, rig=rig)
    msgs = check_export(job, intensities, sensor, seed)  # fail before rendering anything
    if workers < 1:
        msgs.append(f"--workers must be a positive integer, got {workers}")
    try:
        check_lens_k1(lens_k1)
    except InputError as exc:
        msgs.append(str(exc))
    if msgs:
        raise InputError(msgs[0])
    levels = [float(i) for i in intensities]
    notes = []
    job = _with_device(job, device, gpu_index, notes.append)
    client = None
    if scheduler is not None:  # connect before rendering: a bad address fails in seconds, not hours
        from .parallel import connect

        client = connect(scheduler)
    try:
        folder = run_render(job, out_dir, blend, gpu_index, notes)
        for f in convert_all(folder, out_dir, levels, sensor=sensor, seed=seed, workers=workers, scheduler=client,
                             progress=True, lens_k1=lens_k1):
            click.echo(str(f))
    finally:
        if client is not None:
            client.close()


def _image_size(resolution, rig: str, quick: bool) -> tuple[int, int]:
    """(width, height) from ``--resolution`` N or WxH, else the rig's default."""
    if resolution is None:
        return HANDHELD_SIZE if rig == "handheld" else (QUICK["resolution"] if quick else 400,) * 2
    try:
        return parse_size(resolution) if "x" in str(resolution).lower() else (int(resolution),) * 2
    except (ValueError, InputError):
        raise InputError(f"--resolution {resolution!r}: expected N or WxH, e.g. 400 or 400x250") from None


def _default_views(rig: str, quick: bool) -> tuple:
    if rig == "handheld":
        return tuple(HANDHELD_VIEWS[s] for s in ("train", "val", "test"))
    return QUICK["views"] if quick else (100, 100, 200)


def _with_device(job: RenderJob, device: str, gpu_index, note) -> RenderJob:
    """The job with its Cycles device resolved (before anything is rendered); a fallback to the CPU
    is passed to ``note`` (said when rendering starts, so that bad input still gets one line)."""
    if job.engine != "cycles":
        return job
    from .render_blender import resolve_device

    resolved = resolve_device(device, log=note)
    if gpu_index is not None and resolved == "cpu":
        raise InputError("--gpu-index: rendering on the CPU (no GPU backend found); leave it out or use --device gpu")
    return dataclasses.replace(job, device=resolved)


def _scene_name(scene, blend) -> tuple[str, str]:
    if blend is not None:
        if scene is not None:
            raise InputError("give either --scene or --blend, not both")
        name, digest = identify_blend(blend)
        if name in SCENES:
            click.echo(f"{blend}: the original NeRF-synthetic '{name}' scene", err=True)
        return name, f"blend:{digest}"
    if scene is None:
        raise InputError(f"--scene is required (one of {', '.join(SCENES)}) unless --blend is given")
    if scene not in SCENES:
        raise InputError(f"--scene {scene!r}: expected one of {', '.join(SCENES)}")
    return scene, "builtin"


def run_render(job: RenderJob, out_dir, blend=None, gpu_index: int | None = None, notes=()) -> RenderFolder:
    """Render every missing view of ``job`` into ``<out_dir>/<scene>_render`` with a progress bar
    (``notes``: lines said on stderr once rendering starts).

    Ctrl-C (or SIGTERM) stops after the image being rendered: that view's files are removed,
    finished views stay, and rerunning the command resumes.
    """
    from tqdm import tqdm

    from .render_blender import renderer_for

    renderer = None
    if blend is not None:  # the camera's field of view is part of the job, known once the file is open
        renderer = renderer_for(job, blend, gpu_index=gpu_index)
        job = dataclasses.replace(job, camera_angle_x=renderer.camera_angle_x())
    folder = RenderFolder.open(out_dir, job)
    pending = folder.pending()
    if not pending:
        return folder
    renderer = renderer or renderer_for(job, blend, gpu_index=gpu_index)
    for line in notes:
        click.echo(line, err=True)
    steps = render_steps(folder, renderer)
    with StopRequest() as stop, tqdm(total=len(pending) * images_per_view(job), desc=f"render {job.scene}",
                                     unit="img") as bar:
        try:
            for _ in steps:
                bar.update()
                if stop.requested:
                    raise KeyboardInterrupt
        finally:
            steps.close()  # an unfinished view is removed here
    return folder


class StopRequest:
    """Turns SIGINT / SIGTERM into a flag checked between images.

    Blender runs Python callbacks (the Cycles engine) inside a render and prints and swallows a
    KeyboardInterrupt raised there, so the default Ctrl-C handling would not stop the loop.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.requested = False
        self._old = {}

    def _handle(self, signum, frame):
        self.requested = True

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc):
        for s, handler in self._old.items():
            signal.signal(s, handler)
        return False
