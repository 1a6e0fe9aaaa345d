"""Dataset folders (shared/specs/dataset.md): read sources, write ``<name>_i<I>/``, verify.

Sources:

- a NeRF-synthetic folder: ``transforms_<split>.json`` + PNGs; static views, ``K = 1``;
- a render folder written by ``spikegen render`` (``render.json``, :class:`~spikegen.formats.RenderDoc`):
  per view an RGBA PNG at mid-exposure and ``K`` linear RGBA EXR sub-frames ``r_N_subKK.exr``,
  composited onto white here.

Output per intensity: ``transforms_<split>.json`` (:class:`~spikegen.formats.Transforms`: NeRF
layout + a ``"spike"`` block and per frame ``spike_path`` and ``subframe_transform_matrices``),
``<split>/r_N.png`` (ground truth), ``<split>/r_N.dat`` (spikes), ``sensor.json`` + ``sensor.npz``,
``config.yaml`` (SpikeCV's size keys and the file list), and last ``manifest.json``. Every
intensity is made in one pass over the source: each view is read once and simulated at every
intensity. Every file is written atomically; a rerun skips views already written and ends with
the same bytes; a folder holding another job's output is never overwritten.
"""
from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import __version__
from .errors import InputError, OutputError
from .formats import (SPLITS, ConvertParams, ConvertTask, FileEntry, Intrinsics, LevelOutput, Manifest, RenderDoc,
                      Transforms, ViewRecord, check_intensity, intensity_label, read_json, spikecv_config)
from .lens import lens_problem, warp_to_lens
from .parallel import connect, run_tasks
from .presets import get_sensor
from .seeding import view_seed
from .sensor import Sensor, simulate
from .sensorfile import save_sensor
from .spikeio import (LUMA, atomic_path, check_radiance, exr_size, exr_to_radiance, read_exr, read_png,
                      remove_stale_parts, sha256_file, srgb_to_linear, linear_to_srgb, write_bytes_atomic, write_dat,
                      write_json_atomic, write_png)

JOB_FILE = ".spikegen-job.json"
CONFIG_YAML = "config.yaml"
__all__ = ["check_intensity", "convert", "open_source", "verify", "Source"]


@dataclass(frozen=True)
class Source:
    kind: str  # "nerf" or "render"
    root: Path
    name: str
    camera_angle_x: float
    width: int
    height: int
    subframes: int
    views: tuple  # ViewRecord (root = the source folder)
    info: dict = field(default_factory=dict)


# ---------------------------------------------------------------------- sources
def open_source(path) -> Source:
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"{root}: no such folder (expected a render folder or a NeRF-synthetic scene folder)")
    if (root / "render.json").is_file():
        return _open_render(root)
    if any((root / f"transforms_{s}.json").is_file() for s in SPLITS):
        return _open_nerf(root)
    raise InputError(f"{root}: neither a render folder (render.json) nor a NeRF-synthetic folder (transforms_*.json)")


def _png_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise InputError(f"{path}: image listed in the transforms is missing") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise InputError(f"{path}: not a readable PNG image ({exc.__class__.__name__})") from None


def _open_nerf(root: Path) -> Source:
    views, cam = [], None
    for split in SPLITS:
        jpath = root / f"transforms_{split}.json"
        if not jpath.is_file():
            continue
        doc = read_json(jpath)
        frames, angle = doc.get("frames"), doc.get("camera_angle_x")
        if not isinstance(frames, list) or not frames:
            raise InputError(f"{jpath}: needs a non-empty list 'frames' (one per view)")
        if not isinstance(angle, (int, float)) or not 0 < angle < math.pi:
            raise InputError(f"{jpath}: needs 'camera_angle_x', the horizontal field of view in radians "
                             f"(0 < angle < pi), got {angle!r}")
        cam = float(angle) if cam is None else cam
        views += [ViewRecord.from_transforms_frame(fr, split, i, root, f"{jpath} frame {i}", keep=("rotation",))
                  for i, fr in enumerate(frames)]
    w, h = _same_size(views, _png_size, lambda v: (v.png,))
    return Source("nerf", root, root.resolve().name, cam, w, h, 1, tuple(views))


def _same_size(views, size_of, files_of, expected=None) -> tuple[int, int]:
    """Check (from headers only, before anything is written) that every image of every view
    exists and has one size (``expected`` (w, h) if given, else the first image's); returns it."""
    what = "render.json says" if expected is not None else "the first image is"
    for v in views:
        for path in files_of(v):
            size = size_of(path)
            if expected is None:
                expected = size
            elif size != expected:
                raise InputError(f"{path}: image is {size[0]}x{size[1]}, but {what} {expected[0]}x{expected[1]}")
    return expected


def _open_render(root: Path) -> Source:
    jpath = root / "render.json"
    doc = RenderDoc.read(jpath)
    if not doc.views:
        raise InputError(f"{jpath}: lists no rendered views")
    h = doc.header
    w, hgt = int(h["width"]), int(h["height"])
    _same_size(doc.views, _png_size, lambda v: (v.png,), (w, hgt))
    _same_size(doc.views, exr_size, lambda v: v.exrs, (w, hgt))
    info = {k: h[k] for k in ("engine", "samples", "motion_deg", "seed", "frames", "device") if k in h}
    return Source("render", root, str(h["scene"]), float(h["camera_angle_x"]), w, hgt, doc.subframes, doc.views,
                  info)


# ---------------------------------------------------------------------- per view
def _resize(plane: np.ndarray, size: int) -> np.ndarray:
    """Area-average resize of a float plane to size x size: a sensor pixel integrates the light
    falling on its area, so each output pixel is the mean over its footprint (PIL's BOX filter:
    exact block means for integer factors, area weights otherwise; no ringing, no negatives)."""
    from PIL import Image

    if plane.shape == (size, size):
        return plane
    im = Image.fromarray(np.ascontiguousarray(plane, dtype=np.float32), mode="F")
    return np.asarray(im.resize((size, size), Image.Resampling.BOX), dtype=np.float32)


def _load_view(src_kind: str, view: ViewRecord, resolution: int | None, lens: Intrinsics | None = None):
    """(radiance [K, H, W] float32, ground-truth RGBA uint8 [H, W, 4] or None = copy the PNG).

    With ``lens``, both are warped through it after any resize (:func:`spikegen.lens.warp_to_lens`):
    what the same camera with that radial lens images."""
    x, gt = _load_pinhole_view(src_kind, view, resolution)
    if lens is None:
        return x, gt
    k = (lens.k1, lens.fl_x, lens.fl_y, lens.cx, lens.cy)
    rgba = read_png(view.png) * 255.0 if gt is None else gt  # the PNG's 8-bit values, warped as they are
    gt = warp_to_lens(np.moveaxis(np.asarray(rgba, np.float32), -1, 0), *k)
    gt = np.clip(np.round(np.moveaxis(gt, 0, -1)), 0, 255).astype(np.uint8)
    return warp_to_lens(x, *k), gt


def _load_pinhole_view(src_kind: str, view: ViewRecord, resolution: int | None):
    if src_kind == "nerf":
        rgba = read_png(view.png)
        if rgba.shape[2] not in (3, 4):
            raise InputError(f"{view.png}: expected an RGB or RGBA image, got {rgba.shape[2]} channels")
        if rgba.shape[2] == 3:
            rgba = np.concatenate([rgba, np.ones(rgba.shape[:2] + (1,))], axis=2)
        lin = srgb_to_linear(rgba[:, :, :3]) * rgba[:, :, 3:4]  # premultiplied linear
        alpha = rgba[:, :, 3]
        gt = None
        if resolution is not None and (rgba.shape[0], rgba.shape[1]) != (resolution, resolution):
            lin = np.stack([_resize(lin[:, :, c], resolution) for c in range(3)], axis=2)
            alpha = np.clip(_resize(alpha, resolution), 0.0, 1.0)
            straight = np.where(alpha[..., None] > 1e-6, lin / np.maximum(alpha[..., None], 1e-6), 0.0)
            gt = np.concatenate([linear_to_srgb(np.clip(straight, 0, 1)), alpha[..., None]], axis=2)
            gt = np.clip(np.round(gt * 255), 0, 255).astype(np.uint8)
        x = (np.clip(lin, 0, None) @ LUMA + (1.0 - alpha))[None].astype(np.float32)
        check_radiance(x, str(view.png))
        return x, gt
    planes = []
    for p in view.exrs:
        arr = read_exr(p)
        check_radiance(arr, str(p))
        x = exr_to_radiance(arr)
        planes.append(_resize(x, resolution) if resolution else x)
    gt = None
    if resolution is not None:
        rgba = read_png(view.png)
        if rgba.shape[:2] != (resolution, resolution):
            gt = np.stack([_resize(rgba[:, :, c], resolution) for c in range(rgba.shape[2])], axis=2)
            gt = np.clip(np.round(gt * 255), 0, 255).astype(np.uint8)
    return np.stack(planes), gt


def convert_view(task: ConvertTask, sensor: Sensor) -> list[str]:
    """Make one view's ``r_N.png`` and ``r_N.dat`` at every intensity of ``task`` ("written" or
    "skipped" for each: skipped if both exist at the right size and, in a finished folder, still
    hold the bytes its manifest records). The source is read once, and only if something is due."""
    view = task.view
    due = [lv for lv in task.levels if not _is_done(task, lv)]
    if due:
        x, gt = _load_view(task.source_kind, view, task.resolution, task.lens)
    for lv in due:
        seed = view_seed(task.seed, task.name, view.split, view.index, lv.intensity)
        spikes = simulate(x, lv.intensity, sensor, frames=task.frames, seed=seed, threads=task.threads)
        png = lv.out / (view.name + ".png")
        if gt is None:
            with atomic_path(png) as tmp:
                shutil.copyfile(view.png, tmp)
        else:
            write_png(png, gt)
        write_dat(lv.out / (view.name + ".dat"), spikes)
    return ["written" if lv in due else "skipped" for lv in task.levels]


def _is_done(task: ConvertTask, lv: LevelOutput) -> bool:
    """Both files there, the ``.dat`` of the right size, and (in a finished folder) the bytes its
    manifest records: a file changed after the dataset was finished is made again (from its seed,
    so the same bytes)."""
    dat, png = lv.out / (task.view.name + ".dat"), lv.out / (task.view.name + ".png")
    if not (dat.is_file() and png.is_file() and dat.stat().st_size == task.dat_bytes):
        return False
    for p in (png, dat):
        digest = lv.recorded.get(p.relative_to(lv.out).as_posix())
        if digest is not None and sha256_file(p) != digest:
            return False
    return True


def _recorded(out: Path) -> dict:
    """{relative path: sha256} listed by ``out/manifest.json`` ({} if the folder is not finished)."""
    mpath = out / "manifest.json"
    if not mpath.is_file():
        return {}
    try:
        return Manifest.read(mpath)[0].digests()
    except InputError:
        return {}


# ---------------------------------------------------------------------- whole dataset
def convert(source, out_dir, intensities, sensor="paper", frames: int = 256, seed: int = 0,
            resolution: int | None = None, workers: int = 1, scheduler: str | None = None,
            progress: bool = True, stop=None, lens_k1: float = 0.0) -> list[Path]:
    """Write ``out_dir/<name>_i<I>/`` for each intensity; returns the folders.

    ``lens_k1`` > 0: every view is warped through a radial lens of that ``k1`` (spikegen.lens; the
    renderer's camera otherwise) before the sensor sees it, and the transforms carry the intrinsics
    with ``k1``. A barrel lens (``k1 < 0``) would need pixels beyond the rendered image: refused.
    One pass over the source: every view is read once and simulated at every intensity.
    ``stop``: a callable checked between views (in-process runs); when it returns True the
    conversion stops with an :class:`OutputError`, finished views kept, and a rerun finishes it."""
    src = source if isinstance(source, Source) else open_source(source)
    levels = [check_intensity(i) for i in intensities]
    if not levels:
        raise InputError("give at least one --intensity")
    width, height = _output_size(src, frames, resolution)
    lens = _lens(src, width, height, lens_k1)
    sensor_obj = sensor if isinstance(sensor, Sensor) else get_sensor(sensor, height, width, seed)
    sensor_obj = sensor_obj.sized(height, width)
    sensor_name = sensor if isinstance(sensor, str) else sensor_obj.name
    if int(workers) != workers or workers < 1:
        raise InputError(f"--workers must be a positive integer, got {workers}")
    client = connect(scheduler) if isinstance(scheduler, str) else scheduler  # fail before writing anything
    base = ConvertParams(src.root.resolve().name, src.kind, src.name, 0.0, sensor_name, int(frames), src.subframes,
                         width, height, int(seed), render=src.info, lens_k1=lens.k1 if lens else 0.0)
    params = [replace(base, intensity=level) for level in levels]
    outs = [Path(out_dir) / f"{src.name}_i{intensity_label(p.intensity)}" for p in params]
    try:
        for out, p in zip(outs, params):
            _claim(out, p)
        tasks = _tasks(src, outs, params, resolution, workers == 1 and client is None, lens)
        run_tasks(convert_view, tasks, workers=workers, scheduler=client, progress=progress,
                  desc=f"{src.name} x{len(levels)} intensities", shared={"sensor": sensor_obj}, stop=stop)
        for out, p in zip(outs, params):
            _finish(out, src, p, sensor_obj, lens)
    finally:
        if client is not None and isinstance(scheduler, str):
            client.close()
    return outs


def _output_size(src: Source, frames, resolution) -> tuple[int, int]:
    if int(frames) != frames or frames < 1:
        raise InputError(f"--frames must be a positive integer, got {frames}")
    if resolution is not None and (int(resolution) != resolution or resolution < 8):
        raise InputError(f"--resolution must be an integer >= 8, got {resolution}")
    width, height = (resolution, resolution) if resolution else (src.width, src.height)
    if (width * height) % 8:
        raise InputError(f"{width}x{height}: spike files need width*height to be a multiple of 8")
    return width, height


def check_lens_k1(k1) -> float:
    """``--lens-k1`` as a float, or an ``InputError``: a number, and not a barrel lens (``k1 < 0``),
    which would image more than the rendered pinhole view holds."""
    if isinstance(k1, bool) or not isinstance(k1, (int, float)) or not math.isfinite(k1):
        raise InputError(f"--lens-k1 must be a number, got {k1!r}")
    if k1 < 0:
        raise InputError(f"--lens-k1 {k1:g}: a barrel lens (k1 < 0) images more than the rendered pinhole view "
                         "holds; only k1 > 0 (pincushion) can be made from it")
    return float(k1)


def _lens(src: Source, width: int, height: int, k1) -> Intrinsics | None:
    """The renderer's camera at the output size with the radial lens ``k1`` (None for 0: pinhole)."""
    if check_lens_k1(k1) == 0:
        return None
    lens = Intrinsics.centred(width, height, src.camera_angle_x, float(k1))
    problem = lens_problem(lens.k1, width, height, lens.fl_x, lens.fl_y, lens.cx, lens.cy)
    if problem:
        raise InputError(f"--lens-k1: {problem}")
    return lens


def _tasks(src: Source, outs, params, resolution, in_process: bool, lens: Intrinsics | None = None) -> list[ConvertTask]:
    recorded = [_recorded(out) for out in outs]
    p0 = params[0]
    tasks = []
    for v in src.views:
        names = (v.name + ".png", v.name + ".dat")
        levels = tuple(LevelOutput(out, p.intensity, {k: rec[k] for k in names if k in rec})
                       for out, p, rec in zip(outs, params, recorded))
        tasks.append(ConvertTask(v, src.kind, src.name, resolution, p0.seed, p0.frames,
                                 p0.spike_block().dat_bytes, levels, (os.cpu_count() or 1) if in_process else 1,
                                 lens))
    return tasks


def _claim(out: Path, params: ConvertParams) -> None:
    """Refuse to write into a folder that holds another job's output; record this job."""
    manifest, job = out / "manifest.json", out / JOB_FILE
    for path in (manifest, job):
        if path.is_file():
            try:
                old = read_json(path).get("parameters")
            except InputError:
                old = None
            if not params.matches(old):
                raise OutputError(f"{out}: holds a dataset made with other parameters ({path.name}); "
                                  f"choose another --out or remove it")
            return
    if out.exists() and any(not p.name.endswith(".part") for p in out.iterdir()):
        raise OutputError(f"{out}: exists and is not a spikegen dataset folder; choose another --out")
    write_json_atomic(job, {"parameters": params.to_json()})


def _finish(out: Path, src: Source, params: ConvertParams, sensor: Sensor, lens: Intrinsics | None = None) -> None:
    spike = params.spike_block()
    dats = []
    for split in SPLITS:
        views = tuple(v for v in src.views if v.split == split)
        if views:
            doc = Transforms(src.camera_angle_x, spike, views, lens).to_json()
            write_json_atomic(out / f"transforms_{split}.json", doc)
            dats += [v.name + ".dat" for v in views]
    save_sensor(sensor, out / "sensor")
    write_bytes_atomic(out / CONFIG_YAML, spikecv_config(spike, dats).encode())
    write_manifest(out, params.to_json(), params.seed)


def write_manifest(out: Path, parameters: dict, seed: int) -> None:
    """Last step of a dataset folder: remove stale temporaries, list every file with its size and
    sha256 in ``manifest.json`` (written last), drop the job file."""
    remove_stale_parts(out, recursive=True)  # temporaries of writes killed in an earlier run
    files = sorted(p for p in out.rglob("*") if p.is_file() and not p.name.startswith(".")
                   and p.name != "manifest.json")
    entries = tuple(FileEntry(p.relative_to(out).as_posix(), p.stat().st_size, sha256_file(p)) for p in files)
    manifest = Manifest(f"spikegen {__version__}", parameters, seed, entries)
    write_json_atomic(out / "manifest.json", manifest.to_json())
    (out / JOB_FILE).unlink(missing_ok=True)


def verify(folder) -> list[str]:
    """Problems found checking a dataset folder against its manifest ([] if it is intact)."""
    out = Path(folder)
    if not out.is_dir():
        raise InputError(f"{out}: no such folder")
    mpath = out / "manifest.json"
    if not mpath.is_file():
        raise InputError(f"{out}: no manifest.json (not a finished spikegen dataset)")
    manifest, bad = Manifest.read(mpath)
    problems = [f"{mpath}: malformed entry {e!r}" for e in bad]
    listed = {e["path"] for e in bad if isinstance(e, dict) and isinstance(e.get("path"), str)}
    for e in manifest.files:
        listed.add(e.path)
        problems += _file_problem(out, e)
    for p in sorted(out.rglob("*")):
        rel = p.relative_to(out).as_posix()
        if p.is_file() and rel not in listed and rel != "manifest.json":
            problems.append(f"unlisted: {rel}" + (" (left by an interrupted write)" if p.name.endswith(".part") else ""))
    return problems


def _file_problem(out: Path, e: FileEntry) -> list[str]:
    p = out / e.path
    if not p.is_file():
        return [f"missing: {e.path}"]
    size = p.stat().st_size
    if size < e.bytes:
        return [f"truncated: {e.path} ({size} of {e.bytes} bytes)"]
    if size != e.bytes:
        return [f"altered: {e.path} ({size} bytes, manifest says {e.bytes})"]
    if sha256_file(p) != e.sha256:
        return [f"altered: {e.path} (sha256 differs)"]
    return []
