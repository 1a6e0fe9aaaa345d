"""``spikegen import``: a folder of real spike recordings (one file per viewpoint) -> a dataset folder.

Stages (each with a progress bar):

1. **streams**: every spike file is checked (size, layout, frame count) before anything is written; then
   per view the first ``frames`` frames are written as ``train/r_N.dat`` (dataset.md layout) and an
   image reconstructed from them as ``train/r_N.png`` (:func:`view_image`);
2. **sfm**: pycolmap finds the poses and one shared pinhole camera from those images
   (:func:`run_sfm`: SIFT, exhaustive matching, incremental mapping; one thread, fixed seeds, so a
   rerun gives the same poses bit for bit);
3. **write**: poses normalised (:func:`normalise`), ``transforms_train.json``
   (:class:`~spikegen.formats.CaptureTransforms`), ``sensor.json`` (the calibration, or the ideal
   sensor), ``config.yaml`` and last ``manifest.json``.

A ``.dat`` without a header is read at ``--size``; one whose rows carry :data:`HEADER_COLUMNS`
extra leading columns (a 416-wide file for a 400-wide sensor, as some cameras write) is
recognised by its size and those columns dropped. Views COLMAP does not register are left out
and named; fewer than :data:`MIN_REGISTERED` registered is an error and nothing is left.

``--truth-images DIR`` (a capture whose truth is known, e.g. a synthetic one made by ``spikegen
render --rig handheld``): ``DIR/<stem>.png`` for every spike file ``<stem>.dat`` is the image the
camera saw (the NeRF-synthetic PNG convention, dataset.md), copied byte for byte to
``train/r_N_truth.png`` and named in its frame as ``"ground_truth_path"``; ``spikenerf eval`` then
scores held-out views against it. Structure from motion never sees it.
"""
from __future__ import annotations

import hashlib
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .dataset import CONFIG_YAML, _claim, write_manifest
from .errors import InputError, OutputError
from .formats import (RECONSTRUCTIONS, CaptureTransforms, ImportParams, Intrinsics, SpikeBlock, ViewRecord,
                      spikecv_config)
from .recon import rate_to_radiance, tfi, tfp
from .sensor import Sensor
from .sensorfile import save_sensor
from .spikeio import decode_dat, linear_to_srgb, read_npz, write_dat, write_json_atomic, write_png, \
    write_bytes_atomic

SPIKE_SUFFIXES = (".dat", ".npz")
HEADER_COLUMNS = 16  # leading columns per row that some cameras' .dat files carry (250 x 416 for 250 x 400)
MIN_REGISTERED = 3  # fewer registered views cannot make a dataset
SFM_SEED = 0  # every random seed pycolmap takes
INIT_MIN_TRI_ANGLE_DEG = 4.0  # COLMAP's 16 degrees is more than a handheld patch's baseline gives
INIT_MIN_INLIERS = 50  # COLMAP's 100 is more than a small spike frame's features give
MAX_REPROJ_ERROR_PX = 0.5  # tracks merged, completed and kept only within this (COLMAP: 4 px); measured, docs
CAMERA_MODELS = {"simple-pinhole": "SIMPLE_PINHOLE",  # one focal length, principal point at the centre (fixed)
                 "simple-radial": "SIMPLE_RADIAL"}  # the same and a radial lens k1 (spikegen.lens), refined
DEFAULT_CAMERA_MODEL = "simple-pinhole"  # the lens of every synthetic capture here (docs/real_captures.md)
DEFAULT_RECONSTRUCTION = "tfp"  # chosen by measured pose accuracy (docs/real_captures.md)
WHITE_PERCENTILE = 99.5  # the brightness shown as white in a view's PNG
BOUND_PERCENTILES = (1.0, 99.0)  # near / far: these percentiles of a view's sparse-point depths ...
BOUND_MARGIN = (0.9, 1.1)  # ... times these factors
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])  # COLMAP/OpenCV camera axes (y down, z forward) <-> OpenGL


@dataclass(frozen=True)
class CaptureFile:
    path: Path
    frames: int  # frames the file holds
    header_columns: int = 0  # leading columns of each row to drop (.dat only)


# ---------------------------------------------------------------------- stage 1: spike files
def _natural_key(path: Path):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def list_capture(folder, size: tuple[int, int]) -> list[CaptureFile]:
    """The capture's spike files in natural name order, each checked (size, layout)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder (expected a folder of spike files, one per viewpoint)")
    paths = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SPIKE_SUFFIXES),
                   key=_natural_key)
    if not paths:
        raise InputError(f"{folder}: no spike files (.dat or .npz) in this folder")
    return [_probe(p, size) for p in paths]


def _probe(path: Path, size: tuple[int, int]) -> CaptureFile:
    w, h = size
    if path.suffix.lower() == ".npz":
        shape = read_npz(path).shape
        if (shape[2], shape[1]) != (w, h):
            raise InputError(f"{path}: stream is {shape[2]}x{shape[1]}, but --size says {w}x{h} "
                             "(all views of a capture must have one size)")
        return CaptureFile(path, shape[0])
    try:
        n = path.stat().st_size
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    fits = [extra for extra in (0, HEADER_COLUMNS) if n > 0 and n % ((w + extra) * h // 8) == 0]
    if len(fits) == 2:  # a size both layouts divide (e.g. 1000 frames of 416 = 1040 of 400): ask the pixels
        fits = [min(fits, key=lambda extra: _shear_score(path, size, extra))]
    if fits:
        return CaptureFile(path, n // ((w + fits[0]) * h // 8), fits[0])
    raise InputError(f"{path}: {n} bytes is not a whole number of {w}x{h} frames ({w * h // 8} bytes each), "
                     f"nor of {w + HEADER_COLUMNS}x{h} frames with a row header: truncated, or another --size")


def _shear_score(path: Path, size: tuple[int, int], extra: int, frames: int = 64) -> float:
    """Mean absolute difference between vertically adjacent pixels of the spike rate over the first
    ``frames`` frames, read with ``extra`` header columns per row: read in the wrong layout, every
    row lands shifted against the one above and frames mix, so the image is far less smooth."""
    w, h = size
    whole = path.stat().st_size // ((w + extra) * h // 8)
    rate = tfp(read_view(CaptureFile(path, whole, extra), size, min(frames, whole)), frames).astype(np.float64)
    return float(np.abs(np.diff(rate, axis=0)).mean())


def read_view(cf: CaptureFile, size: tuple[int, int], frames: int) -> np.ndarray:
    """The first ``frames`` frames of one capture file, ``uint8 [T, H, W]`` upright."""
    w, h = size
    if cf.path.suffix.lower() == ".npz":
        return read_npz(cf.path)[:frames]
    width = w + cf.header_columns
    try:
        with open(cf.path, "rb") as fh:
            data = fh.read(frames * width * h // 8)
    except OSError as exc:
        raise InputError(f"{cf.path}: cannot read: {exc.strerror or exc}") from None
    spikes = decode_dat(data, h, width, source=str(cf.path), frames=frames)
    return np.ascontiguousarray(spikes[:, :, cf.header_columns:])


def view_rate(spikes: np.ndarray, method: str) -> np.ndarray:
    """Spikes per frame ``float32 [H, W]``: TFP over the whole stream, or TFI at its middle frame."""
    return tfi(spikes) if method == "tfi" else tfp(spikes, spikes.shape[0])


def view_image(rate: np.ndarray, sensor: Sensor) -> np.ndarray:
    """The view's PNG, ``uint8 [H, W]``: the rate with the sensor's fixed pattern removed
    (``rate / R - d``), :data:`WHITE_PERCENTILE` of it shown as white, sRGB-encoded."""
    x = rate_to_radiance(rate, 256.0, sensor)
    white = max(float(np.percentile(x, WHITE_PERCENTILE)), 1e-6)
    return np.round(linear_to_srgb(np.clip(x / white, 0.0, 1.0)) * 255.0).astype(np.uint8)


def write_views(files, size, frames: int, method: str, sensor: Sensor, out: Path, progress: bool) -> float:
    """Stage 1: ``train/r_N.dat`` and ``train/r_N.png`` of every view (a ``.dat`` already there at
    the right size is kept, and a PNG already there: both are written atomically); returns the
    median over the views of each view's 99th-percentile rate (spikes per frame)."""
    from tqdm import tqdm

    dat_bytes = frames * size[0] * size[1] // 8
    bright = []
    for i, cf in enumerate(tqdm(files, desc="streams", unit="view", disable=not progress)):
        spikes = read_view(cf, size, frames)
        bright.append(np.percentile(tfp(spikes, frames), 99.0))
        dat, png = out / "train" / f"r_{i}.dat", out / "train" / f"r_{i}.png"
        if not (dat.is_file() and dat.stat().st_size == dat_bytes):
            write_dat(dat, spikes)
        if not png.is_file():
            write_png(png, view_image(view_rate(spikes, method), sensor))
    return float(np.median(bright))


# ---------------------------------------------------------------------- stage 2: structure from motion
def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise InputError("spikegen import needs pycolmap: pip install 'spikenerf-suite[real]' "
                         "(or pip install pycolmap==4.2.1)") from None
    return pycolmap


def _sfm_options(pycolmap):
    """(extraction, matching, verification, mapping) options: CPU, one thread, every seed fixed; the
    mapper keeps a 3D point's observation, and the triangulator merges and completes tracks, only
    within :data:`MAX_REPROJ_ERROR_PX` of reprojection error."""
    extraction = pycolmap.FeatureExtractionOptions(num_threads=1, use_gpu=False)
    matching = pycolmap.FeatureMatchingOptions(num_threads=1, use_gpu=False)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed, verification.ransac.num_threads = SFM_SEED, 1
    mapping = pycolmap.IncrementalPipelineOptions(num_threads=1, random_seed=SFM_SEED)
    mapping.mapper.num_threads, mapping.mapper.random_seed = 1, SFM_SEED
    mapping.mapper.init_min_tri_angle = INIT_MIN_TRI_ANGLE_DEG
    mapping.mapper.init_min_num_inliers = INIT_MIN_INLIERS
    mapping.triangulation.random_seed = SFM_SEED
    mapping.mapper.filter_max_reproj_error = MAX_REPROJ_ERROR_PX
    mapping.triangulation.merge_max_reproj_error = MAX_REPROJ_ERROR_PX
    mapping.triangulation.complete_max_reproj_error = MAX_REPROJ_ERROR_PX
    return extraction, matching, verification, mapping


def run_sfm(image_dir: Path, names: list[str], progress: bool = True, camera_model: str = DEFAULT_CAMERA_MODEL):
    """pycolmap's reconstruction of ``names`` (images in ``image_dir``) holding the most registered
    images, or ``None`` when it registers none; one camera of ``camera_model`` (a key of
    :data:`CAMERA_MODELS`) shared by all views. Work files go to a temporary folder."""
    from tqdm import tqdm

    pycolmap = _pycolmap()
    pycolmap.logging.minloglevel = pycolmap.logging.Level.ERROR.value  # COLMAP's progress lines off
    pycolmap.set_random_seed(SFM_SEED)
    extraction, matching, verification, mapping = _sfm_options(pycolmap)
    reader = pycolmap.ImageReaderOptions(camera_model=CAMERA_MODELS[camera_model])
    with tempfile.TemporaryDirectory(prefix="spikegen-sfm-") as work, \
            tqdm(total=3, desc="sfm (features, matches, mapping)", disable=not progress) as bar:
        db = Path(work) / "database.db"
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        bar.update()
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
        bar.update()
        models = pycolmap.incremental_mapping(db, image_dir, Path(work) / "sparse", mapping)
        bar.update()
    if not models:
        return None
    return max(sorted(models.items()), key=lambda kv: kv[1].num_reg_images())[1]


@dataclass(frozen=True)
class SfmResult:
    """What the dataset needs from a reconstruction, in COLMAP's world frame."""

    names: tuple  # registered image names, in the order given
    c2w_gl: np.ndarray  # [n, 4, 4] camera-to-world, OpenGL camera axes
    points: tuple  # per view: [m, 3] sparse points it observes
    intrinsics: Intrinsics


def sfm_result(rec, names: list[str]) -> SfmResult:
    """Poses, observed points and the shared camera of the registered views among ``names``."""
    by_name = {} if rec is None else {img.name: img for img in rec.images.values() if img.has_pose}
    found = [n for n in names if n in by_name]
    poses, points = [], []
    for n in found:
        img = by_name[n]
        w2c = np.eye(4)
        w2c[:3] = np.asarray(img.cam_from_world().matrix(), dtype=np.float64)
        poses.append(np.linalg.inv(w2c) @ CV_TO_GL)
        ids = [p.point3D_id for p in img.get_observation_points2D()]
        points.append(np.array([rec.point3D(k).xyz for k in ids], dtype=np.float64).reshape(-1, 3))
    cam = by_name[found[0]].camera if found else None
    intr = None if cam is None else Intrinsics(float(cam.focal_length_x), float(cam.focal_length_y),
                                               float(cam.principal_point_x), float(cam.principal_point_y),
                                               int(cam.width), int(cam.height), _k1(cam))
    return SfmResult(tuple(found), np.array(poses).reshape(-1, 4, 4), tuple(points), intr)


def _k1(cam) -> float:
    """The radial coefficient of a COLMAP camera (SIMPLE_RADIAL's params are f, cx, cy, k); 0 for a pinhole."""
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    return float(cam.params[3]) if model.endswith("SIMPLE_RADIAL") else 0.0


# ---------------------------------------------------------------------- stage 3: the normalised frame
def normalise(c2w_gl: np.ndarray, points: tuple) -> np.ndarray:
    """The similarity ``M [4, 4]`` (``p = M p_colmap``) to the dataset's frame: origin at the
    cameras' mean centre; +Z along the cameras' mean up (+Y) axis; +Y along their mean viewing
    direction (-Z) made orthogonal to it (the first camera's when they cancel out); scaled so the
    cameras and the sparse points (within the 99th percentile of distance) fit in the unit sphere."""
    centre = c2w_gl[:, :3, 3].mean(axis=0)
    z = c2w_gl[:, :3, 1].mean(axis=0)
    z /= np.linalg.norm(z)
    y = -c2w_gl[:, :3, 2].mean(axis=0)
    y -= (y @ z) * z
    if np.linalg.norm(y) < 1e-3:
        y = -c2w_gl[0, :3, 2] - (-c2w_gl[0, :3, 2] @ z) * z
    y /= np.linalg.norm(y)
    rot = np.stack([np.cross(y, z), y, z])  # rows: new axes in COLMAP's frame
    pts = np.concatenate([p for p in points if len(p)] or [np.zeros((0, 3))])
    reach = np.linalg.norm(c2w_gl[:, :3, 3] - centre, axis=1).max()
    if len(pts):
        reach = max(reach, float(np.percentile(np.linalg.norm(pts - centre, axis=1), 99.0)))
    scale = 1.0 / max(reach, 1e-12)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = scale * rot, -scale * rot @ centre
    return m


def apply_normalisation(m: np.ndarray, c2w_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world poses ``[n, 4, 4]`` moved by the similarity ``m`` (rotation kept orthonormal)."""
    scale = np.cbrt(np.linalg.det(m[:3, :3]))
    out = m @ c2w_gl
    out[:, :3, :3] /= scale
    return out


def view_bounds(c2w: np.ndarray, points: np.ndarray, m: np.ndarray) -> tuple[float, float]:
    """Near and far of one view (normalised units) from the depths of the sparse points it sees."""
    if len(points) == 0:
        return 0.0, 0.0
    pts = points @ m[:3, :3].T + m[:3, 3]
    depth = -(pts - c2w[:3, 3]) @ c2w[:3, 2]  # along the viewing direction (-Z)
    lo, hi = np.percentile(depth, BOUND_PERCENTILES)
    return float(max(lo, 0.0) * BOUND_MARGIN[0]), float(hi * BOUND_MARGIN[1])


# ---------------------------------------------------------------------- the whole import
def import_capture(capture, size, out, calibration=None, frames: int | None = None,
                   reconstruction: str = DEFAULT_RECONSTRUCTION, progress: bool = True,
                   camera_model: str = DEFAULT_CAMERA_MODEL, truth_images=None) -> Path:
    """Write the dataset folder ``out`` from the spike files in ``capture``; returns ``out``.

    Everything about the input is checked before anything is written. An error after that (no
    view registers, or fewer than :data:`MIN_REGISTERED`) removes the folder this run created;
    an interrupted run keeps its finished views and a rerun ends with the same bytes."""
    from tqdm import tqdm

    out = Path(out)
    if reconstruction not in RECONSTRUCTIONS:
        raise InputError(f"--recon {reconstruction!r}: expected one of {', '.join(RECONSTRUCTIONS)}")
    if camera_model not in CAMERA_MODELS:
        raise InputError(f"--camera-model {camera_model!r}: expected one of {', '.join(CAMERA_MODELS)}")
    files = list_capture(capture, size)
    frames = _frames(files, frames)
    sensor, digest = _calibration(calibration, size)
    truths = _truth_images(truth_images, files, size)
    params = ImportParams(Path(capture).resolve().name, tuple(f.path.name for f in files), size[0], size[1], frames,
                          reconstruction, digest, _pycolmap().__version__, SFM_SEED,
                          camera_model=CAMERA_MODELS[camera_model], truth_images=_digest(truths))
    created = not out.exists()
    _claim(out, params)
    try:
        rate99 = write_views(files, size, frames, reconstruction, sensor, out, progress)
        for i, path in enumerate(truths or ()):
            write_bytes_atomic(out / "train" / f"r_{i}_truth.png", path.read_bytes())
        names = [f"r_{i}.png" for i in range(len(files))]
        sfm = sfm_result(run_sfm(out / "train", names, progress, camera_model), names)
        _check_registered(sfm, files, capture)
        with tqdm(total=1, desc="write", disable=not progress) as bar:
            _write_dataset(out, params, sfm, files, rate99, sensor, truths is not None)
            bar.update()
    except (InputError, OutputError):
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return out


def _frames(files, frames) -> int:
    shortest = min(f.frames for f in files)
    if frames is None:
        return shortest
    if int(frames) != frames or frames < 1:
        raise InputError(f"--frames must be a positive integer, got {frames}")
    short = [f for f in files if f.frames < frames]
    if short:
        raise InputError(f"{short[0].path}: holds {short[0].frames} frames, fewer than --frames {frames}")
    return int(frames)


def _truth_images(folder, files, size) -> list[Path] | None:
    """``folder/<stem>.png`` for every spike file, each checked to be a PNG of the capture's size;
    None without ``folder``."""
    if folder is None:
        return None
    from .spikeio import read_png

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"--truth-images {folder}: not a folder")
    out = []
    for f in files:
        path = folder / (f.path.stem + ".png")
        if not path.is_file():
            raise InputError(f"--truth-images {folder}: no {path.name} for spike file {f.path.name}")
        shape = read_png(path).shape[:2]
        if shape != (size[1], size[0]):
            raise InputError(f"{path}: {shape[1]}x{shape[0]} image, the capture is {size[0]}x{size[1]}")
        out.append(path)
    return out


def _digest(paths) -> str | None:
    if paths is None:
        return None
    h = hashlib.sha256()
    for path in paths:
        h.update(path.read_bytes())
    return h.hexdigest()


def _calibration(prefix, size) -> tuple[Sensor, str | None]:
    """The calibration's sensor at the capture's size and the sha256 of its JSON, or the ideal sensor."""
    if prefix is None:
        return Sensor(name="ideal"), None
    from .presets import get_sensor

    path = Path(prefix)
    path = path if path.suffix == ".json" else path.parent / (path.name + ".json")
    if not path.is_file():
        raise InputError(f"--calibration {prefix}: no such sensor file {path} (write one with spikegen calibrate)")
    sensor = get_sensor(str(path), size[1], size[0])
    return sensor.sized(size[1], size[0]), hashlib.sha256(path.read_bytes()).hexdigest()


def _check_registered(sfm: SfmResult, files, capture) -> None:
    if len(sfm.names) < MIN_REGISTERED:
        raise InputError(f"{capture}: structure from motion registered {len(sfm.names)} of {len(files)} views "
                         f"(at least {MIN_REGISTERED} are needed); nothing written")


def _write_dataset(out: Path, params: ImportParams, sfm: SfmResult, files, rate99: float, sensor: Sensor,
                   ground_truth: bool = False) -> None:
    """Stage 3: transforms_train.json, sensor, config.yaml and manifest.json; unregistered views' files removed."""
    m = normalise(sfm.c2w_gl, sfm.points)
    poses = apply_normalisation(m, sfm.c2w_gl)
    index = [int(n[2:-4]) for n in sfm.names]  # "r_<i>.png": view i keeps its files' names
    views = tuple(ViewRecord("train", i, p, p[None]) for i, p in zip(index, poses))
    every = np.concatenate(sfm.points)  # a view that sees no sparse point gets the bounds of them all
    bounds = np.array([view_bounds(p, pts if len(pts) else every, m)
                       for p, pts in zip(poses, sfm.points)]).reshape(-1, 2)
    left_out = tuple(f.path.name for i, f in enumerate(files) if i not in set(index))
    _remove_unregistered(out / "train", index, len(files))
    spike = SpikeBlock(params.height, params.width, params.frames, 1, max(256.0 * rate99, 1e-3), background=None)
    doc = CaptureTransforms(sfm.intrinsics, spike, views, bounds, tuple(files[i].path.name for i in index), m,
                            params.reconstruction, left_out, ground_truth=ground_truth)
    write_json_atomic(out / "transforms_train.json", doc.to_json())
    save_sensor(sensor, out / "sensor")
    write_bytes_atomic(out / CONFIG_YAML, spikecv_config(spike, [v.name + ".dat" for v in views]).encode())
    write_manifest(out, params.to_json(), params.seed)


def _remove_unregistered(folder: Path, registered: list[int], count: int) -> None:
    """Remove the files of views that are not in the dataset (a rerun makes and removes them again)."""
    for i in sorted(set(range(count)) - set(registered)):
        for ext in (".dat", ".png", "_truth.png"):
            (folder / f"r_{i}{ext}").unlink(missing_ok=True)


# ---------------------------------------------------------------------- checking poses against a known truth
def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R [3, 3], t [3])`` minimising ``sum |dst - (s R src + t)|^2`` over points ``[n, 3]``
    (Umeyama 1991: least-squares similarity, reflection excluded)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / max((a ** 2).sum() / len(src), 1e-300))
    return scale, rot, mu_d - scale * rot @ mu_s


def axes_focus(c2w: np.ndarray) -> np.ndarray:
    """The point ``[3]`` nearest (least squares) to every camera's optical axis (the line through its
    centre along its -Z): where a rig of cameras looks. ``ValueError`` when the axes are (nearly)
    parallel, so that no such point is fixed."""
    eye = np.eye(3)
    proj = eye[None] - np.einsum("ni,nj->nij", c2w[:, :3, 2], c2w[:, :3, 2])  # onto each axis' normal plane
    a, b = proj.sum(axis=0), np.einsum("nij,nj->i", proj, c2w[:, :3, 3])
    if np.linalg.cond(a) > 1e8:
        raise ValueError("the cameras' optical axes are parallel: give the scene's depth explicitly")
    return np.linalg.solve(a, b)


def _procrustes(m: np.ndarray) -> np.ndarray:
    """The rotation ``R`` maximising ``trace(R^T m)`` (reflection excluded)."""
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0]) @ vt


def full_pose_similarity(c2w_est: np.ndarray, c2w_true: np.ndarray, depth: float,
                         iters: int = 100) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R [3, 3], t [3])`` minimising, over the views' whole poses,

        E = sum_i |c_i - (s R c^_i + t)|^2 + depth^2 / 2 * sum_i |R_i - R R^_i|_F^2

    (``c``, ``R_i``: true centre and orientation; ``^``: estimated). ``|R_i - R R^_i|_F^2 = 4 (1 -
    cos theta)``, about ``2 theta^2`` for a small orientation error ``theta``, so the second term
    weighs ``theta`` as the centre error ``depth * theta`` it equals at the scene's depth (``depth``,
    in the true frame's units): a turn and a shift of the camera that move the scene's image alike
    count alike. The centres alone fix the alignment's tilt poorly when they lie on a small flat
    patch (a forward-facing rig); the orientations fix it. Solved by block coordinate descent from
    the orientation-only rotation: ``t`` in closed form, then ``R`` for fixed ``s`` (a Procrustes
    problem on ``s A + depth^2 / 2 B``, ``A = sum (c_i - mean c) (c^_i - mean c^)^T``, ``B = sum R_i
    R^_i^T``) and ``s = trace(R^T A) / sum |c^_i - mean c^|^2`` for fixed ``R``, in turn; no step
    raises ``E``, and it stops when ``s`` and ``R`` no longer change (at most ``iters`` rounds)."""
    ce, ct = c2w_est[:, :3, 3], c2w_true[:, :3, 3]
    a_est, a_true = ce - ce.mean(axis=0), ct - ct.mean(axis=0)
    a = a_true.T @ a_est
    b = np.einsum("nij,nkj->ik", c2w_true[:, :3, :3], c2w_est[:, :3, :3])
    spread = max(float((a_est ** 2).sum()), 1e-300)
    rot = _procrustes(b)
    scale = max(float(np.trace(rot.T @ a)) / spread, 0.0)
    for _ in range(iters):
        new_rot = _procrustes(scale * a + 0.5 * depth ** 2 * b)
        new_scale = max(float(np.trace(new_rot.T @ a)) / spread, 0.0)
        done = np.allclose(new_rot, rot, rtol=0, atol=1e-14) and abs(new_scale - scale) <= 1e-14 * max(scale, 1.0)
        rot, scale = new_rot, new_scale
        if done:
            break
    return scale, rot, ct.mean(axis=0) - scale * rot @ ce.mean(axis=0)


def pose_errors(c2w_est: np.ndarray, c2w_true: np.ndarray, depth: float | None = None) -> dict:
    """Errors of estimated camera-to-world poses ``[n, 4, 4]`` against the true ones, per view: the
    rotation error (degrees) and the centre error as a fraction of the rig's extent (the largest
    distance between two true camera centres), after two alignments, both reported:

    - ``rotation_deg``, ``centre_frac``: the similarity that best maps the estimated camera
      centres onto the true ones (:func:`umeyama`; the centres alone);
    - ``rotation_full_deg``, ``centre_full_frac``: the similarity fitted to the whole poses
      (:func:`full_pose_similarity`, orientations weighed at the scene's ``depth``; default: the
      median distance from the true centres to the point their optical axes converge on,
      :func:`axes_focus`; returned as ``depth``).

    ``rotation_own_deg``: the rotation error after the rotation that best maps the estimated
    orientations onto the true ones (the orientations alone, no centres)."""
    if depth is None:
        depth = float(np.median(np.linalg.norm(c2w_true[:, :3, 3] - axes_focus(c2w_true), axis=1)))
    extent = max(float(np.max(np.linalg.norm(c2w_true[:, None, :3, 3] - c2w_true[None, :, :3, 3], axis=2))), 1e-12)
    out = {"extent": extent, "depth": depth}
    for key, (s, rot, t) in (("", umeyama(c2w_est[:, :3, 3], c2w_true[:, :3, 3])),
                             ("_full", full_pose_similarity(c2w_est, c2w_true, depth))):
        centres = c2w_est[:, :3, 3] @ (s * rot).T + t
        out[f"rotation{key}_deg"] = _angle_deg(c2w_true, rot, c2w_est)
        out[f"centre{key}_frac"] = np.linalg.norm(centres - c2w_true[:, :3, 3], axis=1) / extent
        out[f"similarity{key}"] = (s, rot, t)
    out["rotation_own_deg"] = _angle_deg(c2w_true, _procrustes(
        np.einsum("nij,nkj->ik", c2w_true[:, :3, :3], c2w_est[:, :3, :3])), c2w_est)
    return out


def _angle_deg(c2w_true: np.ndarray, rot: np.ndarray, c2w_est: np.ndarray) -> np.ndarray:
    """Angle (degrees) of ``R_true^T rot R_est`` for each view."""
    rel = np.einsum("nji,jk,nkl->nil", c2w_true[:, :3, :3], rot, c2w_est[:, :3, :3])
    return np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
