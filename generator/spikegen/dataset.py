"""Dataset folders (shared/specs/dataset.md): read sources, write ``<name>_i<I>/``, verify.

Sources:

- a NeRF-synthetic folder: ``transforms_<split>.json`` + PNGs; static views, ``K = 1``;
- a render folder written by ``spikegen render`` (``render.json`` ``"format":
  "spikegen-render/1"``): per view an RGBA PNG at mid-exposure and ``K`` linear RGBA EXR
  sub-frames ``r_N_subKK.exr``, composited onto white here.

Output per intensity: ``transforms_<split>.json`` (NeRF layout + a ``"spike"`` block and per
frame ``spike_path`` and ``subframe_transform_matrices``), ``<split>/r_N.png`` (ground truth),
``<split>/r_N.dat`` (spikes), ``sensor.json`` + ``sensor.npz``, and last ``manifest.json``.
Every file is written atomically; a rerun skips views already written and ends with the same
bytes; a folder holding another job's output is never overwritten.
"""
from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .errors import InputError, OutputError
from .parallel import connect, run_tasks
from .presets import get_sensor
from .seeding import view_seed
from .sensor import Sensor, simulate
from .sensorfile import save_sensor
from .spikeio import (LUMA, atomic_path, check_radiance, exr_size, exr_to_radiance, read_exr, read_png,
                      remove_stale_parts, sha256_file, srgb_to_linear, linear_to_srgb, write_dat, write_json_atomic,
                      write_png)

SPLITS = ("train", "val", "test")
READOUT_HZ = 20000
MAX_INTENSITY = 4096.0
JOB_FILE = ".spikegen-job.json"
RENDER_FORMAT = "spikegen-render/1"


@dataclass(frozen=True)
class View:
    split: str
    index: int
    file_path: str  # "./train/r_0"
    transform_matrix: list
    subframe_matrices: list
    png: Path
    exrs: tuple = ()
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Source:
    kind: str  # "nerf" or "render"
    root: Path
    name: str
    camera_angle_x: float
    width: int
    height: int
    subframes: int
    views: tuple
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


def _read_json(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc.__class__.__name__}: {exc})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{path}: expected a JSON object")
    return doc


def _matrix(value, where: str) -> list:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"{where}: transform_matrix must be a finite 4x4 matrix")
    return m.tolist()


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
        doc = _read_json(jpath)
        frames = doc.get("frames")
        angle = doc.get("camera_angle_x")
        if not isinstance(frames, list) or not frames or not isinstance(angle, (int, float)):
            raise InputError(f"{jpath}: needs a number 'camera_angle_x' and a non-empty list 'frames'")
        cam = float(angle) if cam is None else cam
        for i, fr in enumerate(frames):
            where = f"{jpath} frame {i}"
            if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
                raise InputError(f"{where}: needs a 'file_path'")
            m = _matrix(fr.get("transform_matrix"), where)
            fp = fr["file_path"]
            png = root / (fp if fp.endswith(".png") else fp + ".png")
            extra = {k: v for k, v in fr.items() if k in ("rotation",)}
            views.append(View(split, i, f"./{split}/r_{i}", m, [m], png, (), extra))
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
    doc = _read_json(jpath)
    if doc.get("format") != RENDER_FORMAT:
        raise InputError(f"{jpath}: not a spikegen render folder (expected \"format\": \"{RENDER_FORMAT}\")")
    try:
        K, w, h = int(doc["subframes"]), int(doc["width"]), int(doc["height"])
        cam, name, splits = float(doc["camera_angle_x"]), str(doc["scene"]), doc["splits"]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{jpath}: missing or bad field {exc}") from None
    if not isinstance(splits, dict) or not all(isinstance(splits.get(s, []), list) for s in SPLITS):
        raise InputError(f"{jpath}: 'splits' must map train/val/test to lists of views")
    if K < 1 or w < 1 or h < 1:
        raise InputError(f"{jpath}: subframes, width and height must be positive")
    views = []
    for split in SPLITS:
        for i, fr in enumerate(splits.get(split, [])):
            where = f"{jpath} {split} view {i}"
            if not isinstance(fr, dict) or not isinstance(fr.get("file_path", ""), str):
                raise InputError(f"{where}: expected an object with a string 'file_path'")
            fp = fr.get("file_path", f"./{split}/r_{i}")
            base = root / fp
            subs = [_matrix(m, where) for m in fr.get("subframe_transform_matrices", [])]
            if len(subs) != K:
                raise InputError(f"{where}: expected {K} subframe_transform_matrices, got {len(subs)}")
            exrs = tuple(Path(f"{base}_sub{k:02d}.exr") for k in range(K))
            views.append(View(split, int(fr.get("index", i)), f"./{split}/r_{int(fr.get('index', i))}",
                              _matrix(fr.get("transform_matrix"), where), subs, Path(f"{base}.png"), exrs))
    if not views:
        raise InputError(f"{jpath}: lists no rendered views")
    _same_size(views, _png_size, lambda v: (v.png,), (w, h))
    _same_size(views, exr_size, lambda v: v.exrs, (w, h))
    info = {k: doc[k] for k in ("engine", "samples", "motion_deg", "seed", "frames") if k in doc}
    return Source("render", root, name, cam, w, h, K, tuple(views), info)


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


def _load_view(src_kind: str, view: View, resolution: int | None):
    """(radiance [K, H, W] float32, ground-truth RGBA uint8 [H, W, 4] or None = copy the PNG)."""
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


def convert_view(task: dict) -> str:
    """Make one view's ``r_N.png`` and ``r_N.dat`` (skipped if both exist at the right size and,
    in a finished folder, still hold the bytes its manifest records)."""
    out: Path = task["out"]
    view: View = task["view"]
    dat = out / (view.file_path[2:] + ".dat")
    png = out / (view.file_path[2:] + ".png")
    if dat.is_file() and png.is_file() and dat.stat().st_size == task["dat_bytes"] and _as_recorded(task, png, dat):
        return "skipped"
    x, gt = _load_view(task["kind"], view, task["resolution"])
    seed = view_seed(task["seed"], task["name"], view.split, view.index, task["intensity"])
    spikes = simulate(x, task["intensity"], task["sensor"], frames=task["frames"], seed=seed,
                      threads=task.get("threads", 1))
    if gt is None:
        with atomic_path(png) as tmp:
            shutil.copyfile(view.png, tmp)
    else:
        write_png(png, gt)
    write_dat(dat, spikes)
    return "written"


def _as_recorded(task: dict, *paths: Path) -> bool:
    """False if the manifest of a finished folder records other bytes for one of ``paths``: a
    file changed after the dataset was finished is made again (from its seed, so the same bytes)."""
    recorded = task.get("recorded") or {}
    for p in paths:
        digest = recorded.get(p.relative_to(task["out"]).as_posix())
        if digest is not None and sha256_file(p) != digest:
            return False
    return True


def _recorded(out: Path) -> dict:
    """{relative path: sha256} listed by ``out/manifest.json`` ({} if the folder is not finished)."""
    mpath = out / "manifest.json"
    entries = _read_json(mpath).get("files") if mpath.is_file() else None
    if not isinstance(entries, list):
        return {}
    return {e["path"]: e["sha256"] for e in entries
            if isinstance(e, dict) and isinstance(e.get("path"), str) and isinstance(e.get("sha256"), str)}


# ---------------------------------------------------------------------- whole dataset
def _intensity_label(intensity: float) -> str:
    return str(int(intensity)) if float(intensity).is_integer() else f"{intensity:g}".replace(".", "p")


def check_intensity(value) -> float:
    try:
        i = float(value)
    except (TypeError, ValueError):
        raise InputError(f"--intensity {value!r}: expected a number") from None
    if not math.isfinite(i) or i <= 0:
        raise InputError(f"--intensity {value!r}: must be a positive number (16, 32, 64 in the paper)")
    if i > MAX_INTENSITY:
        raise InputError(f"--intensity {value!r}: above {MAX_INTENSITY:g} every pixel saturates; not a useful setting")
    return i


def convert(source, out_dir, intensities, sensor="paper", frames: int = 256, seed: int = 0,
            resolution: int | None = None, workers: int = 1, scheduler: str | None = None,
            progress: bool = True) -> list[Path]:
    """Write ``out_dir/<name>_i<I>/`` for each intensity; returns the folders."""
    src = source if isinstance(source, Source) else open_source(source)
    levels = [check_intensity(i) for i in intensities]
    if not levels:
        raise InputError("give at least one --intensity")
    if int(frames) != frames or frames < 1:
        raise InputError(f"--frames must be a positive integer, got {frames}")
    if resolution is not None and (int(resolution) != resolution or resolution < 8):
        raise InputError(f"--resolution must be an integer >= 8, got {resolution}")
    width = height = resolution if resolution else None
    width, height = width or src.width, height or src.height
    if (width * height) % 8:
        raise InputError(f"{width}x{height}: spike files need width*height to be a multiple of 8")
    sensor_obj = sensor if isinstance(sensor, Sensor) else get_sensor(sensor, height, width, seed)
    sensor_obj = sensor_obj.sized(height, width)
    sensor_name = sensor if isinstance(sensor, str) else sensor_obj.name
    if int(workers) != workers or workers < 1:
        raise InputError(f"--workers must be a positive integer, got {workers}")
    client = connect(scheduler) if isinstance(scheduler, str) else scheduler  # fail before writing anything
    try:
        return [_convert_level(src, out_dir, level, sensor_name, sensor_obj, frames, seed, resolution, width,
                               height, workers, client, progress) for level in levels]
    finally:
        if client is not None and isinstance(scheduler, str):
            client.close()


def _convert_level(src, out_dir, level, sensor_name, sensor_obj, frames, seed, resolution, width, height,
                   workers, client, progress) -> Path:
    out = Path(out_dir) / f"{src.name}_i{_intensity_label(level)}"
    params = {"source": src.root.resolve().name, "source_kind": src.kind, "name": src.name,
              "intensity": level, "sensor": sensor_name, "frames": int(frames), "subframes": src.subframes,
              "width": width, "height": height, "seed": int(seed), "readout_hz": READOUT_HZ,
              "render": src.info}
    _claim(out, params)
    recorded = _recorded(out)
    tasks = [{"out": out, "view": v, "kind": src.kind, "resolution": resolution, "seed": int(seed),
              "name": src.name, "intensity": level, "frames": int(frames),
              "dat_bytes": int(frames) * width * height // 8,
              "recorded": {k: recorded[k] for k in (v.file_path[2:] + ".png", v.file_path[2:] + ".dat")
                           if k in recorded},
              "threads": (os.cpu_count() or 1) if workers == 1 and client is None else 1} for v in src.views]
    run_tasks(convert_view, tasks, workers=workers, scheduler=client, progress=progress,
              desc=f"{out.name}", shared={"sensor": sensor_obj})
    _finish(out, src, params, sensor_obj)
    return out


def _claim(out: Path, params: dict) -> None:
    """Refuse to write into a folder that holds another job's output; record this job."""
    manifest, job = out / "manifest.json", out / JOB_FILE
    for path in (manifest, job):
        if path.is_file():
            try:
                old = json.loads(path.read_text()).get("parameters")
            except (OSError, ValueError, AttributeError):
                old = None
            if old != json.loads(json.dumps(params)):
                raise OutputError(f"{out}: holds a dataset made with other parameters ({path.name}); "
                                  f"choose another --out or remove it")
            return
    if out.exists() and any(not p.name.endswith(".part") for p in out.iterdir()):
        raise OutputError(f"{out}: exists and is not a spikegen dataset folder; choose another --out")
    write_json_atomic(job, {"parameters": params})


def _finish(out: Path, src: Source, params: dict, sensor: Sensor) -> None:
    for split in SPLITS:
        views = [v for v in src.views if v.split == split]
        if not views:
            continue
        doc = {"camera_angle_x": src.camera_angle_x,
               "spike": {"height": params["height"], "width": params["width"], "frames": params["frames"],
                         "subframes": src.subframes, "intensity": params["intensity"],
                         "readout_hz": READOUT_HZ, "format": "dat"},
               "frames": [{"file_path": v.file_path, **v.extra, "transform_matrix": v.transform_matrix,
                           "spike_path": v.file_path + ".dat", "subframe_transform_matrices": v.subframe_matrices}
                          for v in views]}
        write_json_atomic(out / f"transforms_{split}.json", doc)
    save_sensor(sensor, out / "sensor")
    remove_stale_parts(out, recursive=True)  # temporaries of writes killed in an earlier run
    files = sorted(p for p in out.rglob("*") if p.is_file() and not p.name.startswith(".")
                   and p.name != "manifest.json")
    entries = [{"path": p.relative_to(out).as_posix(), "bytes": p.stat().st_size, "sha256": sha256_file(p)}
               for p in files]
    write_json_atomic(out / "manifest.json", {"generator": f"spikegen {__version__}", "parameters": params,
                                              "seed": params["seed"], "files": entries})
    (out / JOB_FILE).unlink(missing_ok=True)


def verify(folder) -> list[str]:
    """Problems found checking a dataset folder against its manifest ([] if it is intact)."""
    out = Path(folder)
    if not out.is_dir():
        raise InputError(f"{out}: no such folder")
    mpath = out / "manifest.json"
    if not mpath.is_file():
        raise InputError(f"{out}: no manifest.json (not a finished spikegen dataset)")
    doc = _read_json(mpath)
    entries = doc.get("files")
    if not isinstance(entries, list):
        raise InputError(f"{mpath}: no 'files' list")
    problems, listed = [], set()
    for e in entries:
        if isinstance(e, dict) and isinstance(e.get("path"), str):
            listed.add(e["path"])  # a malformed entry still names its file: not "unlisted" too
        try:
            rel, size, digest = e["path"], int(e["bytes"]), e["sha256"]
        except (KeyError, TypeError, ValueError):
            problems.append(f"{mpath}: malformed entry {e!r}")
            continue
        listed.add(rel)
        p = out / rel
        if not p.is_file():
            problems.append(f"missing: {rel}")
        elif p.stat().st_size < size:
            problems.append(f"truncated: {rel} ({p.stat().st_size} of {size} bytes)")
        elif p.stat().st_size != size:
            problems.append(f"altered: {rel} ({p.stat().st_size} bytes, manifest says {size})")
        elif sha256_file(p) != digest:
            problems.append(f"altered: {rel} (sha256 differs)")
    for p in sorted(out.rglob("*")):
        rel = p.relative_to(out).as_posix()
        if p.is_file() and rel not in listed and rel != "manifest.json":
            problems.append(f"unlisted: {rel}" + (" (left by an interrupted write)" if p.name.endswith(".part") else ""))
    return problems
