"""Render folders and the export pipeline shared by ``spikegen render`` and the Blender add-on.

A render folder ``<out>/<scene>_render/`` holds, per view, ``<split>/r_N_subKK.exr`` (K linear
RGBA sub-frames while the camera moves) and ``<split>/r_N.png`` (sharp RGBA at mid-exposure),
plus ``render.json`` (the format :func:`spikegen.dataset.convert` reads)::

    {"format": "spikegen-render/1", "scene": ..., "camera_angle_x": ..., "width": ..., "height": ...,
     "subframes": K, "frames": T, "motion_deg": ..., "engine": ..., "samples": ..., "seed": ...,
     "splits": {"train": [{"index", "file_path", "transform_matrix", "subframe_transform_matrices"}], ...}}

A view is written EXRs first, PNG last, each atomically; its entry joins ``render.json`` only
after all its files exist. A rerun reads ``render.json``, skips finished views, and (entries kept
sorted by split and index, no timings) ends with the same bytes as an uninterrupted run.

This module never imports ``bpy``: it drives any *renderer* with ``set_view_seed(seed)``,
``render_exr(pose, path)``, ``render_png(pose, path)`` (see :mod:`spikegen.render_blender`).
Rendering is a generator of small steps (one image each), so the add-on can run it from a timer
without freezing Blender, and the command line can show a progress bar.
"""
from __future__ import annotations

import json
import shutil
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .camera import CAMERA_ANGLE_X, DEFAULT_MOTION_DEG, SPLITS, View, make_rig
from .errors import InputError, OutputError
from .spikeio import atomic_path, remove_stale_parts, sha256_file, write_json_atomic

RENDER_FORMAT = "spikegen-render/1"
QUICK = {"resolution": 100, "views": (20, 4, 8)}  # --quick: a small dataset in well under 5 minutes
HEADER_KEYS = ("format", "scene", "camera_angle_x", "width", "height", "subframes", "frames", "motion_deg",
               "engine", "samples", "png_samples", "denoise", "seed", "views", "source")


@dataclass(frozen=True)
class RenderJob:
    """Everything that decides a render folder's bytes."""

    scene: str
    width: int = 400
    height: int = 400
    views: tuple = (100, 100, 200)  # train, val, test
    subframes: int = 16
    frames: int = 256
    motion_deg: float = DEFAULT_MOTION_DEG
    engine: str = "cycles"
    samples: int = 8  # chosen by measurement: docs/rendering.md
    png_samples: int = 16
    seed: int = 0
    camera_angle_x: float = CAMERA_ANGLE_X
    source: str = "builtin"  # "builtin", or "blend:<sha256>"
    denoise: bool = False  # OpenImageDenoise on each image (docs/rendering.md)

    @property
    def png_render_samples(self) -> int:
        """Samples of the ground-truth PNG: ``png_samples``, never fewer than the sub-frames'."""
        return max(self.png_samples, self.samples)

    def header(self) -> dict:
        """render.json without its views."""
        d = asdict(self)
        d["views"] = dict(zip(SPLITS, (int(v) for v in self.views)))
        d["png_samples"] = self.png_render_samples
        return {"format": RENDER_FORMAT, **{k: d[k] for k in HEADER_KEYS if k in d}}

    def rig(self) -> dict[str, list[View]]:
        return make_rig(dict(zip(SPLITS, self.views)), self.subframes, self.motion_deg, self.seed)


def check_job(job: RenderJob) -> None:
    """One clear line for each kind of bad setting."""
    if job.width < 8 or job.height < 8 or (job.width * job.height) % 8:
        raise InputError(f"--resolution {job.width}x{job.height}: need at least 8 and width*height a multiple of 8")
    if len(job.views) != 3 or any(int(v) < 0 for v in job.views) or sum(job.views) == 0:
        raise InputError(f"--views {job.views}: expected three counts train,val,test (>= 0, not all 0)")
    if job.subframes < 1 or job.frames < 1:
        raise InputError("--subframes and --frames must be at least 1")
    if job.engine not in ("cycles", "workbench"):
        raise InputError(f"--engine {job.engine!r}: expected cycles or workbench")
    if job.samples < 1:
        raise InputError(f"--samples {job.samples}: must be at least 1")


def parse_views(text: str) -> tuple:
    """``"100,100,200"`` -> ``(100, 100, 200)``."""
    try:
        counts = tuple(int(t) for t in str(text).split(","))
    except ValueError:
        counts = ()
    if len(counts) != 3 or min(counts) < 0:
        raise InputError(f"--views {text!r}: expected three counts train,val,test such as 100,100,200")
    return counts


def view_render_seed(seed: int, split: str, index: int) -> int:
    """Cycles seed of one view, the same for all its sub-frames (so noise never turns into spikes)."""
    return zlib.crc32(f"{int(seed)}:{split}:{int(index)}".encode()) & 0x7FFFFFFF


def identify_blend(path) -> tuple[str, str]:
    """``(scene name, sha256)`` of a ``.blend``: the original NeRF-synthetic name when recognised,
    otherwise the file's stem."""
    from .scenes import ORIGINAL_BLEND_SHA256

    p = Path(path)
    if not p.is_file():
        raise InputError(f"--blend {path}: no such file")
    digest = sha256_file(p)
    return ORIGINAL_BLEND_SHA256.get(digest, p.stem), digest


# ----------------------------------------------------------------------------- the folder
def render_folder(out_dir, scene: str) -> Path:
    return Path(out_dir) / f"{scene}_render"


def view_paths(folder: Path, view: View) -> tuple[Path, list[Path]]:
    """(PNG path, K EXR paths) of one view."""
    base = folder / view.split / f"r_{view.index}"
    K = len(view.subframe_poses)
    return Path(f"{base}.png"), [Path(f"{base}_sub{k:02d}.exr") for k in range(K)]


def view_entry(view: View) -> dict:
    return {"index": view.index, "file_path": f"./{view.split}/r_{view.index}",
            "transform_matrix": view.pose.tolist(),
            "subframe_transform_matrices": [p.tolist() for p in view.subframe_poses]}


@dataclass
class RenderFolder:
    """The state of one render folder: which views are finished."""

    path: Path
    job: RenderJob
    done: dict = field(default_factory=dict)  # split -> {index: entry}

    @classmethod
    def open(cls, out_dir, job: RenderJob) -> "RenderFolder":
        """Open (or start) ``<out_dir>/<scene>_render``; refuse one made with other settings."""
        folder = cls(render_folder(out_dir, job.scene), job, {s: {} for s in SPLITS})
        doc_path = folder.path / "render.json"
        remove_stale_parts(folder.path, recursive=True)  # temporaries of writes cut short by a kill
        if doc_path.is_file():
            folder._resume(doc_path)
        elif folder.path.exists() and any(folder.path.iterdir()):
            raise OutputError(f"{folder.path}: exists and is not a render folder (no render.json); "
                              f"choose another --out or remove it")
        return folder

    def _resume(self, doc_path: Path) -> None:
        try:
            doc = json.loads(doc_path.read_text())
        except (OSError, ValueError) as exc:
            raise OutputError(f"{doc_path}: unreadable ({exc}); remove the folder to start again") from None
        old = {k: doc.get(k) for k in HEADER_KEYS}
        new = json.loads(json.dumps(self.job.header()))
        if old != {k: new.get(k) for k in HEADER_KEYS}:
            diff = [k for k in HEADER_KEYS if old.get(k) != new.get(k)]
            raise OutputError(f"{self.path}: was rendered with other settings ({', '.join(diff)}); "
                              f"choose another --out or remove it")
        rig = self.job.rig()
        for split in SPLITS:
            for entry in doc.get("splits", {}).get(split, []):
                i = int(entry["index"])
                if i < len(rig[split]) and self.is_complete(rig[split][i]):
                    self.done[split][i] = entry

    def is_complete(self, view: View) -> bool:
        png, exrs = view_paths(self.path, view)
        return png.is_file() and all(p.is_file() for p in exrs)

    def pending(self) -> list[View]:
        """Views still to render, in split and index order."""
        rig = self.job.rig()
        return [v for s in SPLITS for v in rig[s] if v.index not in self.done[s]]

    def record(self, view: View) -> None:
        """Add a finished view to render.json (rewritten atomically, entries sorted)."""
        self.done[view.split][view.index] = view_entry(view)
        self.write_json()

    def write_json(self) -> None:
        splits = {s: [self.done[s][i] for i in sorted(self.done[s])] for s in SPLITS}
        write_json_atomic(self.path / "render.json", {**self.job.header(), "splits": splits})

    def discard(self, view: View) -> None:
        """Remove whatever an interrupted view left (its files are not in render.json)."""
        png, exrs = view_paths(self.path, view)
        for p in [png, *exrs]:
            p.unlink(missing_ok=True)
        for stale in (self.path / view.split).glob(f".r_{view.index}[._]*.part"):
            stale.unlink(missing_ok=True)

    def complete(self) -> bool:
        return not self.pending()


def render_view_steps(folder: RenderFolder, renderer, view: View):
    """Render one view, yielding after each image (K EXRs, then the PNG); records it at the end.

    A sub-frame whose pose equals the one before it (a static camera, ``--motion 0``) is a copy
    of that file: one pose and one seed render the same bytes (tests/test_render.py)."""
    png, exrs = view_paths(folder.path, view)
    if folder.job.engine == "cycles":
        renderer.set_view_seed(view_render_seed(folder.job.seed, view.split, view.index))
    last = None
    for pose, path in zip(view.subframe_poses, exrs):
        if last is not None and np.array_equal(pose, last[0]):
            with atomic_path(path) as tmp:
                shutil.copyfile(last[1], tmp)
        else:
            renderer.render_exr(pose, path)
        last = (pose, path)
        yield path
    renderer.render_png(view.pose, png)
    yield png
    folder.record(view)


def render_steps(folder: RenderFolder, renderer):
    """All pending views, one image per step. Yields ``(view, path)``. Writes render.json first."""
    folder.path.mkdir(parents=True, exist_ok=True)
    if not (folder.path / "render.json").is_file():
        folder.write_json()
    for view in folder.pending():
        try:
            for path in render_view_steps(folder, renderer, view):
                yield view, path
        except BaseException:
            folder.discard(view)
            raise


def images_per_view(job: RenderJob) -> int:
    return job.subframes + 1


def convert_all(folder: RenderFolder, out_dir, intensities, sensor="paper", seed: int = 0, workers: int = 1,
                scheduler=None, progress: bool = True) -> list[Path]:
    """Spike datasets ``<out_dir>/<scene>_i<I>/`` from a finished render folder, one per intensity."""
    from .dataset import convert

    if not folder.complete():
        raise OutputError(f"{folder.path}: {len(folder.pending())} views are not rendered yet")
    return convert(folder.path, out_dir, list(intensities), sensor=sensor, frames=folder.job.frames, seed=seed,
                   workers=workers, scheduler=scheduler, progress=progress)
