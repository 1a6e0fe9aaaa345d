"""Render folders and the export pipeline shared by ``spikegen render`` and the Blender add-on.

A render folder ``<out>/<scene>_render/`` holds, per view, ``<split>/r_N_subKK.exr`` (K linear
RGBA sub-frames while the camera moves) and ``<split>/r_N.png`` (sharp RGBA at mid-exposure),
plus ``render.json`` (:class:`spikegen.formats.RenderDoc`, which :func:`spikegen.dataset.convert` reads)::

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

import shutil
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .camera import make_handheld_rig, make_rig
from .errors import InputError, OutputError
from .formats import QUICK, SPLITS, RenderDoc, RenderJob, ViewRecord, intensity_problem, read_json
from .spikeio import atomic_path, remove_stale_parts, sha256_file, write_json_atomic

__all__ = ["QUICK", "RenderJob", "RenderFolder", "check_job", "check_export", "render_steps", "convert_all"]


def rig_of(job: RenderJob) -> dict[str, list[ViewRecord]]:
    """The job's views: ``{"train": [ViewRecord], "val": [...], "test": [...]}`` on its rig."""
    make = make_handheld_rig if job.rig == "handheld" else make_rig
    return make(job.view_counts, job.subframes, job.motion_deg, job.seed)


def check_job(job: RenderJob) -> None:
    """The first of :meth:`RenderJob.validate`'s messages as an :class:`InputError`."""
    msgs = job.validate()
    if msgs:
        raise InputError(msgs[0])


def check_export(job: RenderJob, intensities, sensor: str, seed: int) -> list[str]:
    """Everything wrong with an export (render, then convert) before anything is rendered: the
    job, every intensity and the sensor. Shared by ``spikegen render`` and the add-on."""
    from .presets import get_sensor

    msgs = list(job.validate())
    levels = list(intensities)
    if not levels:
        msgs.append("give at least one --intensity")
    msgs += [m for m in (intensity_problem(i) for i in levels) if m]
    try:
        get_sensor(sensor, job.height, job.width, seed)
    except InputError as exc:
        msgs.append(str(exc))
    return msgs


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


def view_paths(folder: Path, view: ViewRecord) -> tuple[Path, list[Path]]:
    """(PNG path, K EXR paths) of one view."""
    placed = replace(view, root=folder, stem="")
    return placed.png, list(placed.exrs)


@dataclass
class RenderFolder:
    """The state of one render folder: which views are finished."""

    path: Path
    job: RenderJob
    done: dict = field(default_factory=dict)  # split -> {index: ViewRecord}

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
            doc = read_json(doc_path)
        except InputError as exc:
            raise OutputError(f"{exc}; remove the folder to start again") from None
        diff = self.job.differences(doc)
        if diff:
            raise OutputError(f"{self.path}: was rendered with other settings ({', '.join(diff)}); "
                              f"choose another --out or remove it")
        rig = rig_of(self.job)
        splits = doc.get("splits") if isinstance(doc.get("splits"), dict) else {}
        for split in SPLITS:
            for entry in splits.get(split, []) if isinstance(splits.get(split), list) else []:
                i = entry.get("index") if isinstance(entry, dict) else None
                if isinstance(i, int) and 0 <= i < len(rig[split]) and self.is_complete(rig[split][i]):
                    self.done[split][i] = rig[split][i]

    def is_complete(self, view: ViewRecord) -> bool:
        png, exrs = view_paths(self.path, view)
        return png.is_file() and all(p.is_file() for p in exrs)

    def pending(self) -> list[ViewRecord]:
        """Views still to render, in split and index order."""
        rig = rig_of(self.job)
        return [v for s in SPLITS for v in rig[s] if v.index not in self.done[s]]

    def record(self, view: ViewRecord) -> None:
        """Add a finished view to render.json (rewritten atomically, entries sorted)."""
        self.done[view.split][view.index] = view
        self.write_json()

    def write_json(self) -> None:
        views = {s: [self.done[s][i] for i in sorted(self.done[s])] for s in SPLITS}
        write_json_atomic(self.path / "render.json", RenderDoc.to_json(self.job, views))

    def discard(self, view: ViewRecord) -> None:
        """Remove whatever an interrupted view left (its files are not in render.json)."""
        png, exrs = view_paths(self.path, view)
        for p in [png, *exrs]:
            p.unlink(missing_ok=True)
        for stale in (self.path / view.split).glob(f".r_{view.index}[._]*.part"):
            stale.unlink(missing_ok=True)

    def complete(self) -> bool:
        return not self.pending()


def render_view_steps(folder: RenderFolder, renderer, view: ViewRecord):
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
                scheduler=None, progress: bool = True, stop=None, lens_k1: float = 0.0) -> list[Path]:
    """Spike datasets ``<out_dir>/<scene>_i<I>/`` from a finished render folder, one per intensity,
    in one pass over the renders (see :func:`spikegen.dataset.convert`, which also explains ``stop``
    and ``lens_k1``)."""
    from .dataset import convert

    if not folder.complete():
        raise OutputError(f"{folder.path}: {len(folder.pending())} views are not rendered yet")
    return convert(folder.path, out_dir, list(intensities), sensor=sensor, frames=folder.job.frames, seed=seed,
                   workers=workers, scheduler=scheduler, progress=progress, stop=stop, lens_k1=lens_k1)
