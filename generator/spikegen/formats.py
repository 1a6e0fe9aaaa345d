"""Every record the tools pass on, in one place: its fields, its JSON and its checks.

A render folder's ``render.json``, a view, a dataset's ``transforms_<split>.json`` and its
``"spike"`` block, ``manifest.json``, ``config.yaml``, and a conversion task. The renderer
(:mod:`spikegen.render`), the converter (:mod:`spikegen.dataset`), the trainer
(``spikenerf.data``) and the Blender add-on all read and write them through this module, so each
key is spelled here once (shared/specs/dataset.md is the contract).

Each record is a frozen dataclass with a JSON round trip (``to_json`` / ``from_json``) and a
``validate()`` that returns one-line messages naming the file and the frame (empty when it is
sound); ``from_json`` raises :class:`InputError` with the first of them. Pure NumPy, no I/O
beyond reading and writing these small files.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .lens import lens_problem

SPLITS = ("train", "val", "test")
RENDER_FORMAT = "spikegen-render/1"
READOUT_HZ = 20000  # spike-camera frames per second
MAX_INTENSITY = 4096.0  # above this every pixel saturates
BACKGROUND = "white"  # what a dataset's streams are simulated over (the NeRF-synthetic composite)
RIGID_TOL = 1e-3  # a pose's rotation may differ from orthonormal by this much (float32 round trips)
CAMERA_ANGLE_X = 0.6911112070083618  # 50 mm lens, 36 mm sensor width (NeRF-synthetic)
DEFAULT_MOTION_DEG = 1.0  # azimuth swept during one view's exposure (see spikegen.camera)
QUICK = {"resolution": 100, "views": (20, 4, 8)}  # --quick: a small dataset in well under 5 minutes


# ---------------------------------------------------------------------- small shared facts
def read_json(path) -> dict:
    """A JSON object from ``path``; one clear :class:`InputError` if it is missing or not one."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise InputError(f"{path}: not readable JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{path}: expected a JSON object")
    return doc


def focal_px(width: int, camera_angle_x: float = CAMERA_ANGLE_X) -> float:
    """Focal length in pixels of a ``width``-pixel image with horizontal field of view ``camera_angle_x``."""
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


def view_stem(split: str, index: int) -> str:
    """The file stem of view ``index`` of ``split`` in render and dataset folders: ``./train/r_0``."""
    return f"./{split}/r_{int(index)}"


def exr_name(stem: str, k: int) -> str:
    """Sub-frame ``k``'s EXR beside the view's PNG: ``./train/r_0_sub03.exr``."""
    return f"{stem}_sub{int(k):02d}.exr"


def intensity_json(level: float) -> int | float:
    """The intensity as written: the integer it was given when it is one (32, not 32.0)."""
    return int(level) if float(level).is_integer() else float(level)


def intensity_label(level: float) -> str:
    """The folder suffix of an intensity: ``32``, or ``12p5`` for 12.5."""
    return str(int(level)) if float(level).is_integer() else f"{level:g}".replace(".", "p")


def intensity_problem(value) -> str | None:
    """Why ``value`` is not a usable intensity (``None`` if it is)."""
    try:
        i = float(value)
    except (TypeError, ValueError):
        return f"--intensity {value!r}: expected a number"
    if not math.isfinite(i) or i <= 0:
        return f"--intensity {value!r}: must be a positive number (16, 32, 64 in the paper)"
    if i > MAX_INTENSITY:
        return f"--intensity {value!r}: above {MAX_INTENSITY:g} every pixel saturates; not a useful setting"
    return None


def check_intensity(value) -> float:
    """``value`` as a float, or an :class:`InputError` saying why it is not an intensity."""
    msg = intensity_problem(value)
    if msg:
        raise InputError(msg)
    return float(value)


def _first(messages: list[str]) -> None:
    if messages:
        raise InputError(messages[0])


# ---------------------------------------------------------------------- poses
def pose_problem(value, shape=(4, 4)) -> tuple[np.ndarray | None, str | None]:
    """``(matrix float64, None)`` for a finite rigid camera-to-world ``[4, 4]`` (or ``[K, 4, 4]``
    with ``shape=(None, 4, 4)``), else ``(None, why)``."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None, "is not a matrix of numbers"
    if m.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, m.shape)):
        want = " x ".join("K" if s is None else str(s) for s in shape)
        return None, f"must be {want}, got shape {list(m.shape)}"
    if not np.all(np.isfinite(m)):
        return None, "holds a non-finite value (NaN or infinity)"
    mats = m.reshape(-1, 4, 4)
    rot = mats[:, :3, :3]
    gram = np.einsum("kji,kjl->kil", rot, rot)
    if np.abs(gram - np.eye(3)).max() > RIGID_TOL or np.min(np.linalg.det(rot)) <= 0:
        return None, "is not rigid (its 3x3 rotation part is not orthonormal with determinant +1)"
    if np.abs(mats[:, 3] - [0, 0, 0, 1]).max() > RIGID_TOL:
        return None, "must end with the row 0 0 0 1"
    return m, None


def checked_pose(value, where: str, shape=(4, 4)) -> np.ndarray:
    m, why = pose_problem(value, shape)
    if why:
        raise InputError(f"{where}: {why}")
    return m


# ---------------------------------------------------------------------- one view
@dataclass(frozen=True, eq=False)
class ViewRecord:
    """One view: mid-exposure pose ``[4, 4]`` and sub-frame poses ``[K, 4, 4]`` (camera-to-world,
    Blender/NeRF axes), and where its files are.

    ``stem`` is its files' path relative to ``root`` without extension (``./train/r_0``: the
    PNG is ``stem.png``, sub-frame EXRs ``stem_subKK.exr``); a source folder may name its files
    otherwise. Datasets always write a view under :attr:`file_path`. ``extra``: keys of a source
    frame kept in the dataset's transforms (NeRF-synthetic ``rotation``).
    """

    split: str
    index: int
    pose: np.ndarray
    subframe_poses: np.ndarray
    root: Path | None = None
    stem: str = ""
    spike_path: str | None = None
    extra: dict = field(default_factory=dict)

    @property
    def file_path(self) -> str:
        return view_stem(self.split, self.index)

    @property
    def name(self) -> str:
        return self.file_path[2:]

    @property
    def png(self) -> Path:
        return self._root() / png_name(self.stem or self.file_path)

    @property
    def exrs(self) -> tuple[Path, ...]:
        stem = self.stem or self.file_path
        return tuple(self._root() / exr_name(stem, k) for k in range(len(self.subframe_poses)))

    @property
    def spikes(self) -> Path | None:
        return None if self.spike_path is None else self._root() / self.spike_path

    @property
    def truth_png(self) -> Path | None:
        """An imported view's ground-truth image (``"ground_truth_path"``, a capture whose truth is
        known: ``spikegen import --truth-images``); None when the frame names none."""
        path = self.extra.get(GROUND_TRUTH_KEY)
        return None if path is None else self._root() / path

    def _root(self) -> Path:
        return Path(".") if self.root is None else Path(self.root)

    def is_static(self, tol: float = 1e-6) -> bool:
        """All sub-frame poses equal (``--motion 0`` or a NeRF-synthetic source)."""
        return bool(np.abs(self.subframe_poses - self.subframe_poses[:1]).max() <= tol)

    # render.json entry
    def render_entry(self) -> dict:
        return {"index": self.index, "file_path": self.file_path, "transform_matrix": self.pose.tolist(),
                "subframe_transform_matrices": [p.tolist() for p in self.subframe_poses]}

    @classmethod
    def from_render_entry(cls, entry, split: str, position: int, subframes: int, root: Path, where: str):
        if not isinstance(entry, dict) or not isinstance(entry.get("file_path", ""), str):
            raise InputError(f"{where}: expected an object with a string 'file_path'")
        index = int(entry.get("index", position))
        subs = checked_pose(entry.get("subframe_transform_matrices", []), f"{where} subframe_transform_matrices",
                            (None, 4, 4)) if entry.get("subframe_transform_matrices") else np.zeros((0, 4, 4))
        if len(subs) != subframes:
            raise InputError(f"{where}: expected {subframes} subframe_transform_matrices, got {len(subs)}")
        pose = checked_pose(entry.get("transform_matrix"), f"{where} transform_matrix")
        return cls(split, index, pose, subs, root, entry.get("file_path", view_stem(split, index)))

    # transforms_<split>.json frame
    def transforms_frame(self) -> dict:
        return {"file_path": self.file_path, **self.extra, "transform_matrix": self.pose.tolist(),
                "spike_path": self.file_path + ".dat",
                "subframe_transform_matrices": [p.tolist() for p in self.subframe_poses]}

    @classmethod
    def from_transforms_frame(cls, fr, split: str, position: int, root: Path, where: str, keep=()):
        """A frame of a NeRF-synthetic or spike dataset's transforms; ``keep``: keys copied to ``extra``."""
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            raise InputError(f"{where}: needs a string 'file_path'")
        pose = checked_pose(fr.get("transform_matrix"), f"{where} transform_matrix")
        subs = fr.get("subframe_transform_matrices")
        subs = pose[None] if not subs else checked_pose(subs, f"{where} subframe_transform_matrices", (None, 4, 4))
        spike = fr.get("spike_path")
        if spike is not None and not isinstance(spike, str):
            raise InputError(f"{where}: spike_path must be a string")
        stem = fr["file_path"]
        return cls(split, position, pose, subs, Path(root), stem, spike,
                   {k: fr[k] for k in keep if k in fr})


# ---------------------------------------------------------------------- the render job
HEADER_KEYS = ("format", "scene", "camera_angle_x", "width", "height", "subframes", "frames", "motion_deg",
               "engine", "samples", "png_samples", "denoise", "seed", "views", "source", "device", "rig")
ENGINES = ("cycles", "workbench")
GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "METAL", "ONEAPI")  # Cycles' GPU backends, in order of preference
HEADER_DEFAULTS = {"device": "cpu", "rig": "nerf"}  # what a render.json written before a key existed meant
RIGS = ("nerf", "handheld")  # camera rigs of spikegen.camera: NeRF-synthetic sphere, handheld forward-facing


@dataclass(frozen=True)
class RenderJob:
    """Everything that decides a render folder's bytes; its header is ``render.json`` without views."""

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
    source: str = "builtin"  # "builtin", "scene" (the add-on's open scene), or "blend:<sha256>"
    denoise: bool = False  # OpenImageDenoise on each image (docs/rendering.md)
    device: str = "cpu"  # where Cycles renders: "cpu", or "gpu:<backend>" such as "gpu:OPTIX" (bytes differ)
    rig: str = "nerf"  # one of RIGS (spikegen.camera)

    @property
    def png_render_samples(self) -> int:
        """Samples of the ground-truth PNG: ``png_samples``, never fewer than the sub-frames'."""
        return max(self.png_samples, self.samples)

    @property
    def view_counts(self) -> dict:
        return dict(zip(SPLITS, (int(v) for v in self.views)))

    def validate(self) -> list[str]:
        """One line for each bad setting (empty when the job can run)."""
        msgs = []
        if self.width < 8 or self.height < 8 or (self.width * self.height) % 8:
            msgs.append(f"--resolution {self.width}x{self.height}: need at least 8 and width*height a multiple of 8")
        if len(self.views) != 3 or any(int(v) < 0 for v in self.views) or sum(self.views) == 0:
            msgs.append(f"--views {self.views}: expected three counts train,val,test (>= 0, not all 0)")
        if self.subframes < 1 or self.frames < 1:
            msgs.append("--subframes and --frames must be at least 1")
        if self.engine not in ENGINES:
            msgs.append(f"--engine {self.engine!r}: expected cycles or workbench")
        if self.samples < 1:
            msgs.append(f"--samples {self.samples}: must be at least 1")
        if not (math.isfinite(self.motion_deg) and 0 <= self.motion_deg <= 90):
            msgs.append(f"--motion {self.motion_deg}: expected degrees between 0 and 90")
        if not (math.isfinite(self.camera_angle_x) and 0 < self.camera_angle_x < math.pi):
            msgs.append(f"camera_angle_x {self.camera_angle_x}: expected a field of view between 0 and pi")
        if self.device != "cpu" and self.device.partition(":")[2] not in GPU_BACKENDS:
            msgs.append(f"device {self.device!r}: expected cpu or gpu:<{'|'.join(GPU_BACKENDS)}>")
        if self.rig not in RIGS:
            msgs.append(f"--rig {self.rig!r}: expected one of {', '.join(RIGS)}")
        return msgs

    def header(self) -> dict:
        """render.json without its views."""
        d = dataclasses.asdict(self)
        d["views"] = self.view_counts
        d["png_samples"] = self.png_render_samples
        return {"format": RENDER_FORMAT, **{k: d[k] for k in HEADER_KEYS if k in d}}

    def differences(self, header: dict) -> list[str]:
        """The header keys in which ``header`` (a render.json) differs from this job's."""
        new = json.loads(json.dumps(self.header()))
        return [k for k in HEADER_KEYS if header.get(k, HEADER_DEFAULTS.get(k)) != new.get(k)]


@dataclass(frozen=True)
class RenderDoc:
    """A render folder's ``render.json``: the header and the finished views."""

    header: dict
    views: tuple  # ViewRecord, in split and index order

    @property
    def subframes(self) -> int:
        return int(self.header["subframes"])

    @classmethod
    def read(cls, path) -> "RenderDoc":
        path = Path(path)
        doc = read_json(path)
        if doc.get("format") != RENDER_FORMAT:
            raise InputError(f"{path}: not a spikegen render folder (expected \"format\": \"{RENDER_FORMAT}\")")
        _first(cls._header_problems(doc, path))
        splits, K = doc["splits"], int(doc["subframes"])
        views = tuple(ViewRecord.from_render_entry(e, s, i, K, path.parent, f"{path} {s} view {i}")
                      for s in SPLITS for i, e in enumerate(splits.get(s, [])))
        return cls({k: v for k, v in doc.items() if k != "splits"}, views)

    @staticmethod
    def _header_problems(doc: dict, path: Path) -> list[str]:
        try:
            K, w, h = int(doc["subframes"]), int(doc["width"]), int(doc["height"])
            cam, splits, _ = float(doc["camera_angle_x"]), doc["splits"], doc["scene"]  # all three required
        except (KeyError, TypeError, ValueError) as exc:
            return [f"{path}: missing or bad field {exc}"]
        msgs = []
        if not isinstance(splits, dict) or not all(isinstance(splits.get(s, []), list) for s in SPLITS):
            msgs.append(f"{path}: 'splits' must map train/val/test to lists of views")
        if K < 1 or w < 1 or h < 1:
            msgs.append(f"{path}: subframes, width and height must be positive")
        if not (math.isfinite(cam) and 0 < cam < math.pi):
            msgs.append(f"{path}: camera_angle_x {cam} is not a field of view (0 < angle < pi)")
        return msgs

    @staticmethod
    def to_json(job: RenderJob, views_by_split: dict) -> dict:
        """render.json of ``job`` with ``views_by_split`` (split -> [ViewRecord], sorted by index)."""
        splits = {s: [v.render_entry() for v in views_by_split.get(s, [])] for s in SPLITS}
        return {**job.header(), "splits": splits}


# ---------------------------------------------------------------------- a dataset folder
@dataclass(frozen=True)
class SpikeBlock:
    """The ``"spike"`` block of ``transforms_<split>.json``: how the streams were made.

    ``background``: what the stream was simulated over (``"white"``: the NeRF-synthetic
    composite); ``None`` in folders written before the key existed (they were simulated over
    white too) and for captures that fill the frame."""

    height: int
    width: int
    frames: int
    subframes: int
    intensity: float
    readout_hz: int = READOUT_HZ
    format: str = "dat"
    background: str | None = BACKGROUND

    def to_json(self) -> dict:
        d = {"height": self.height, "width": self.width, "frames": self.frames, "subframes": self.subframes,
             "intensity": intensity_json(self.intensity), "readout_hz": self.readout_hz, "format": self.format}
        if self.background is not None:
            d["background"] = self.background
        return d

    def validate(self, where: str) -> list[str]:
        msgs = []
        for key in ("height", "width", "frames", "subframes", "readout_hz"):
            if getattr(self, key) < 1:
                msgs.append(f"{where}: spike {key} must be a positive integer, got {getattr(self, key)}")
        if (self.height * self.width) % 8:
            msgs.append(f"{where}: spike width*height must be a multiple of 8, got {self.width}x{self.height}")
        if not (math.isfinite(self.intensity) and self.intensity > 0):
            msgs.append(f"{where}: spike intensity must be a positive number, got {self.intensity}")
        if self.format != "dat":
            msgs.append(f"{where}: spike format {self.format!r} not supported (expected dat)")
        return msgs

    @property
    def dat_bytes(self) -> int:
        """Size of one view's ``.dat``: ``frames`` frames of ``width * height / 8`` bytes."""
        return self.frames * self.width * self.height // 8

    @classmethod
    def from_json(cls, d, where: str) -> "SpikeBlock":
        if not isinstance(d, dict):
            raise InputError(f"{where}: no \"spike\" block: a NeRF-synthetic folder, not a spike dataset "
                             "(make one with `spikegen convert`)")
        try:
            block = cls(int(d["height"]), int(d["width"]), int(d["frames"]), int(d.get("subframes", 1)),
                        float(d["intensity"]), int(d.get("readout_hz", READOUT_HZ)), str(d.get("format", "dat")),
                        d.get("background"))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{where}: spike block incomplete or not numbers ({exc})") from None
        _first(block.validate(where))
        return block


@dataclass(frozen=True)
class Transforms:
    """One ``transforms_<split>.json`` of a spike dataset (NeRF layout + the spike block)."""

    camera_angle_x: float
    spike: SpikeBlock
    frames: tuple  # ViewRecord
    intrinsics: "Intrinsics | None" = None  # fl_x ... h (and k1): an imported capture's, or a lens's

    def to_json(self) -> dict:
        """The document; intrinsics are written only when given (``spikegen convert --lens-k1``: the
        renderer's camera with a lens), so a pinhole dataset keeps the NeRF-synthetic layout."""
        lens = self.intrinsics.to_json() if self.intrinsics is not None else {}
        return {"camera_angle_x": self.camera_angle_x, **lens, "spike": self.spike.to_json(),
                "frames": [v.transforms_frame() for v in self.frames]}

    @classmethod
    def read(cls, path, split: str) -> "Transforms":
        """Read and check one split's transforms: poses finite and rigid, sizes and focal length positive,
        every spike file the size the spike block says."""
        path = Path(path)
        doc = read_json(path)
        spike = SpikeBlock.from_json(doc.get("spike"), str(path))
        cam = doc.get("camera_angle_x")
        if not isinstance(cam, (int, float)) or not (math.isfinite(cam) and 0 < cam < math.pi):
            raise InputError(f"{path}: camera_angle_x must be a field of view in radians (0 < angle < pi), "
                             f"got {cam!r}")
        frames = doc.get("frames")
        if not isinstance(frames, list):
            raise InputError(f"{path}: 'frames' must be a list")
        views = tuple(ViewRecord.from_transforms_frame(fr, split, i, path.parent, f"{path} frame {i}",
                                                       keep=CAPTURE_FRAME_KEYS)
                      for i, fr in enumerate(frames))
        out = cls(float(cam), spike, views, Intrinsics.from_json(doc, str(path), spike))
        _first(out.file_problems(path))
        return out

    def file_problems(self, path: Path) -> list[str]:
        """Spike files missing, or of another size than the spike block says (first problem only)."""
        for i, v in enumerate(self.frames):
            f = v.spikes
            if f is None:
                return [f"{path} frame {i}: no spike_path"]
            if not f.is_file():
                return [f"{path} frame {i}: spike file {v.spike_path} is missing"]
            truth = v.extra.get(GROUND_TRUTH_KEY)
            if truth is not None and not (isinstance(truth, str) and v.truth_png.is_file()):
                return [f"{path} frame {i}: ground-truth image {truth!r} is missing"]
            if f.suffix == ".dat" and f.stat().st_size != self.spike.dat_bytes:
                return [f"{path} frame {i}: {v.spike_path} is {f.stat().st_size} bytes, but the spike block says "
                        f"{self.spike.frames} frames of {self.spike.width}x{self.spike.height} "
                        f"({self.spike.dat_bytes} bytes)"]
        return []


# ---------------------------------------------------------------------- conversion
class _Parameters:
    """What decides a folder's bytes, as recorded in its manifest (or job file)."""

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    def matches(self, recorded) -> bool:
        """Whether a manifest's (or job file's) recorded parameters are these."""
        return recorded == json.loads(json.dumps(self.to_json()))


@dataclass(frozen=True)
class ConvertParams(_Parameters):
    """What decides a dataset folder's bytes: the manifest's ``"parameters"``."""

    source: str
    source_kind: str  # "nerf" or "render"
    name: str
    intensity: float
    sensor: str
    frames: int
    subframes: int
    width: int
    height: int
    seed: int
    readout_hz: int = READOUT_HZ
    render: dict = field(default_factory=dict)  # the render folder's engine, samples, motion_deg, seed, frames
    lens_k1: float = 0.0  # radial lens the views were warped through (spikegen.lens); 0: pinhole

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["intensity"] = intensity_json(self.intensity)
        if not self.lens_k1:  # a pinhole dataset's manifest keeps the bytes it had before lenses existed
            del d["lens_k1"]
        return d

    def spike_block(self) -> SpikeBlock:
        return SpikeBlock(self.height, self.width, self.frames, self.subframes, self.intensity, self.readout_hz)


@dataclass(frozen=True)
class FileEntry:
    path: str  # relative to the dataset folder, '/'-separated
    bytes: int
    sha256: str


@dataclass(frozen=True)
class Manifest:
    """``manifest.json``: every file of a finished dataset with its size and sha256."""

    generator: str
    parameters: dict
    seed: int
    files: tuple  # FileEntry

    def to_json(self) -> dict:
        return {"generator": self.generator, "parameters": self.parameters, "seed": self.seed,
                "files": [dataclasses.asdict(f) for f in self.files]}

    def digests(self) -> dict:
        """{relative path: sha256}."""
        return {f.path: f.sha256 for f in self.files}

    @classmethod
    def read(cls, path) -> tuple["Manifest", list]:
        """The manifest and the entries it could not read (``verify`` reports them)."""
        path = Path(path)
        doc = read_json(path)
        entries = doc.get("files")
        if not isinstance(entries, list):
            raise InputError(f"{path}: no 'files' list")
        files, bad = [], []
        for e in entries:
            try:
                files.append(FileEntry(str(e["path"]), int(e["bytes"]), str(e["sha256"])))
            except (KeyError, TypeError, ValueError):
                bad.append(e)
        params = doc.get("parameters") if isinstance(doc.get("parameters"), dict) else {}
        return cls(str(doc.get("generator", "")), params, doc.get("seed"), tuple(files)), bad


def spikecv_config(spike: SpikeBlock, files: list[str]) -> str:
    """``config.yaml`` for SpikeCV users: the stream size (so nobody copies it by hand) and the files."""
    lines = ["# Spike streams of this dataset (written by spikegen; see transforms_*.json for poses).",
             f"spike_h: {spike.height}", f"spike_w: {spike.width}", f"frames: {spike.frames}",
             f"readout_hz: {spike.readout_hz}", "data_format: dat  # rows bottom to top, 8 pixels a byte, LSB first",
             "filelist:"]
    return "\n".join(lines + [f"  - {f}" for f in files]) + "\n"


def read_spikecv_size(path) -> tuple[int, int] | None:
    """``(width, height)`` from a ``config.yaml`` written by :func:`spikecv_config` (or SpikeCV's own
    ``spike_h`` / ``spike_w`` lines); ``None`` if the file names no size."""
    size = {}
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError):
        return None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("spike_h", "spike_w"):
            try:
                size[key.strip()] = int(value.split("#")[0].strip())
            except ValueError:
                return None
    if "spike_h" in size and "spike_w" in size:
        return size["spike_w"], size["spike_h"]
    return None


@dataclass(frozen=True)
class LevelOutput:
    """One intensity's share of a conversion task: where it writes and what its manifest recorded."""

    out: Path
    intensity: float
    recorded: dict  # {relative path: sha256} of this view's files in a finished folder ({} if none)


@dataclass(frozen=True)
class ConvertTask:
    """One view to convert: read its source once, write its PNG and ``.dat`` for every intensity."""

    view: ViewRecord
    source_kind: str  # "nerf" or "render"
    name: str  # the dataset name (a part of every view's seed)
    resolution: int | None
    seed: int
    frames: int
    dat_bytes: int
    levels: tuple  # LevelOutput
    threads: int = 1
    lens: "Intrinsics | None" = None  # warp the view through this lens (spikegen.lens.warp_to_lens); None: pinhole


# ---------------------------------------------------------------------- real captures (spikegen import)
POSES_FROM_COLMAP = "colmap"  # transforms "poses_from": structure from motion with pycolmap
IMAGE_KIND_RECONSTRUCTION = "reconstruction"  # a frame's PNG was reconstructed from its own spikes
GROUND_TRUTH_KEY = "ground_truth_path"  # an imported frame's true image (a synthetic capture), beside its reconstruction
CAPTURE_FRAME_KEYS = ("image_kind", "near", "far", GROUND_TRUTH_KEY)  # keys of an imported frame kept in ViewRecord.extra
INTRINSICS_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
LENS_CAMERA_MODEL = "OPENCV"  # transforms "camera_model" when k1 != 0 (nerfstudio's name; k2, p1, p2 = 0)
UNMODELLED_LENS_KEYS = ("k2", "k3", "k4", "p1", "p2")  # OpenCV coefficients a transforms file may carry
RECONSTRUCTIONS = ("tfi", "tfp")  # spikegen.recon methods an import can write as the views' images


def png_name(file_path: str) -> str:
    """A frame's image: its ``file_path`` with ``.png`` added unless it carries it already (an import
    writes it with the extension, NeRF-synthetic folders without): ``./train/r_0`` -> ``./train/r_0.png``."""
    return file_path if file_path.endswith(".png") else file_path + ".png"


def truth_name(file_path: str) -> str:
    """Where an imported view's ground-truth image lives: ``./train/r_0`` -> ``./train/r_0_truth.png``."""
    return file_path + "_truth.png"


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics as nerfstudio and instant-ngp read them: focal lengths and principal
    point in pixels (x right, y down, origin at the top-left corner of the top-left pixel), and
    the image size ``w`` x ``h``; with ``k1`` != 0 a radial lens (:mod:`spikegen.lens`), written as
    ``"camera_model": "OPENCV"`` and ``"k1"`` (the other OpenCV coefficients 0), as both read it."""

    fl_x: float
    fl_y: float
    cx: float
    cy: float
    w: int
    h: int
    k1: float = 0.0

    @property
    def camera_angle_x(self) -> float:
        """Horizontal field of view (radians): ``2 atan(w / (2 fl_x))``, for NeRF-synthetic loaders."""
        return 2.0 * math.atan(self.w / (2.0 * self.fl_x))

    def to_json(self) -> dict:
        doc = {key: getattr(self, key) for key in INTRINSICS_KEYS}
        if self.k1:
            doc.update(camera_model=LENS_CAMERA_MODEL, k1=self.k1)
        return doc

    @classmethod
    def centred(cls, width: int, height: int, camera_angle_x: float, k1: float = 0.0) -> "Intrinsics":
        """The renderer's camera (square pixels, principal point at the image centre) as intrinsics."""
        f = focal_px(width, camera_angle_x)
        return cls(f, f, 0.5 * width, 0.5 * height, int(width), int(height), float(k1))

    @classmethod
    def from_json(cls, doc: dict, where: str, spike: SpikeBlock) -> "Intrinsics | None":
        """The intrinsics of a transforms document, None when it has none (a NeRF-synthetic layout);
        an ``InputError`` when they are incomplete, not positive, of another size than ``spike``, or
        carry a lens this project does not model (any OpenCV coefficient but ``k1``)."""
        if not any(key in doc for key in INTRINSICS_KEYS):
            return None
        vals = [doc.get(key) for key in INTRINSICS_KEYS]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                   for v in vals):
            raise InputError(f"{where}: intrinsics {', '.join(INTRINSICS_KEYS)} must all be positive numbers, "
                             f"got {vals}")
        other = [key for key in UNMODELLED_LENS_KEYS if doc.get(key, 0) != 0]
        if other:
            raise InputError(f"{where}: lens coefficient {other[0]} = {doc[other[0]]!r} is not modelled "
                             "(only the radial k1; undistort the images first)")
        k1 = doc.get("k1", 0.0)
        problem = lens_problem(k1, int(vals[4]), int(vals[5]), *(float(v) for v in vals[:4]))
        if problem:
            raise InputError(f"{where}: {problem}")
        out = cls(*(float(v) for v in vals[:4]), int(vals[4]), int(vals[5]), float(k1))
        if (out.w, out.h) != (spike.width, spike.height):
            raise InputError(f"{where}: intrinsics are for {out.w}x{out.h} images, the spike block says "
                             f"{spike.width}x{spike.height}")
        return out


@dataclass(frozen=True)
class ImportParams(_Parameters):
    """What decides an imported folder's bytes: the manifest's ``"parameters"``."""

    source: str  # the capture folder's name
    files: tuple  # the spike files imported, in view order (names in the capture folder)
    width: int
    height: int
    frames: int
    reconstruction: str  # one of RECONSTRUCTIONS
    calibration: str | None  # sha256 of the calibration's JSON (None: ideal sensor)
    pycolmap: str  # version of pycolmap that found the poses
    seed: int = 0  # pycolmap's random seed
    readout_hz: int = READOUT_HZ
    camera_model: str = "SIMPLE_PINHOLE"  # COLMAP's camera model of the reconstruction
    truth_images: str | None = None  # sha256 of the ground-truth PNGs' bytes in view order (None: none given)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["files"] = list(self.files)
        if self.camera_model == "SIMPLE_PINHOLE":  # the manifests written before the choice existed keep their bytes
            del d["camera_model"]
        if self.truth_images is None:  # as camera_model: a folder imported without truth keeps its bytes
            del d["truth_images"]
        return d


@dataclass(frozen=True, eq=False)
class CaptureTransforms:
    """``transforms_train.json`` of an imported real capture (shared/specs/dataset.md, "Real captures").

    ``frames``: ViewRecords of the registered views (camera-to-world in the normalised frame,
    OpenGL/NeRF camera axes, one sub-frame pose each); ``bounds_m``: ``[n, 2]`` near and far
    depth of each view's sparse points in the normalised frame's units; ``sources``: each view's
    spike file in the capture folder; ``normalisation``: the ``[4, 4]`` similarity taking
    COLMAP's world coordinates to the normalised frame (``p = M p_colmap``)."""

    intrinsics: Intrinsics
    spike: SpikeBlock
    frames: tuple
    bounds_m: np.ndarray
    sources: tuple
    normalisation: np.ndarray
    reconstruction: str
    unregistered: tuple = ()  # spike files whose view COLMAP could not register
    poses_from: str = POSES_FROM_COLMAP
    ground_truth: bool = False  # each view has ``train/r_N_truth.png`` (spikegen import --truth-images)

    def to_json(self) -> dict:
        """The document; each frame's ``file_path`` names its image with the extension
        (``./train/r_0.png``), since nerfstudio's loader opens that path as it stands (instant-ngp's also
        tries image extensions on a path without one; NeRF-synthetic loaders add ``.png``);
        :class:`ViewRecord` reads both."""
        base = Transforms(self.intrinsics.camera_angle_x, self.spike, self.frames).to_json()
        frames = [{**fr, "file_path": png_name(fr["file_path"]), "image_kind": IMAGE_KIND_RECONSTRUCTION,
                   "reconstruction": self.reconstruction,
                   "source_file": src, "near": float(b[0]), "far": float(b[1]),
                   **({GROUND_TRUTH_KEY: truth_name(fr["file_path"])} if self.ground_truth else {})}
                  for fr, src, b in zip(base["frames"], self.sources, self.bounds_m)]
        return {"camera_angle_x": base["camera_angle_x"], **self.intrinsics.to_json(),
                "poses_from": self.poses_from, "normalising_transform": self.normalisation.tolist(),
                "unregistered": list(self.unregistered), "spike": base["spike"], "frames": frames}
