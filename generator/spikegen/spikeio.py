"""Every file format the project reads or writes, in one place.

Spike streams in memory are ``uint8 [T, H, W]`` arrays of 0/1, row 0 at the top.

- ``.dat``: the raw layout of spike cameras and SpikeCV: no header, frames back to back,
  each frame row-major with rows stored bottom to top, 8 pixels a byte, least significant
  bit first. Size comes from elsewhere (JSON or ``--size WxH``).
- ``.npz``: key ``spikes`` = ``np.packbits(arr, axis=-1, bitorder="little")`` and ``shape``.
- ``.npy``: a plain ``[T, H, W]`` uint8 array.

Images: PNG (sRGB, 8 or 16 bit, optional alpha) and OpenEXR (linear). Radiance in memory is
linear luminance ``float32 [H, W]``.

Every writer here writes atomically: a temporary file in the same folder, then a rename,
so an interrupted run never leaves a half-written file under the final name.
"""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from .errors import InputError, OutputError

_UMASK = os.umask(0o022)
os.umask(_UMASK)
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance of linear RGB


# --------------------------------------------------------------------------- atomic writes
@contextlib.contextmanager
def atomic_path(dest):
    """Yield a temporary path beside ``dest``; rename it to ``dest`` only if the block succeeds."""
    dest = Path(dest)
    folder = dest.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix="." + dest.name + ".", suffix=".part", dir=folder)
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; finished files get the usual mode
    except OSError as exc:
        why = "a file is in the way of the folder" if exc.errno in (errno.EEXIST, errno.ENOTDIR) else exc.strerror
        raise OutputError(f"cannot write in {folder}: {why or exc}") from None
    try:
        yield Path(tmp)
        os.replace(tmp, dest)
    except OSError as exc:
        _silent_unlink(tmp)
        raise OutputError(f"cannot write {dest}: {exc.strerror or exc}") from None
    except BaseException:
        _silent_unlink(tmp)
        raise


def remove_stale_parts(folder, recursive: bool = False) -> int:
    """Delete temporaries (``.<name>.*.part``) that writes killed in an earlier run left in ``folder``.

    A process killed by SIGKILL cannot clean up after :func:`atomic_path`; its temporary is never
    read (the real name only ever appears by rename), so a resumed run removes it. Returns the count.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    found = list(folder.rglob(".*.part") if recursive else folder.glob(".*.part"))
    for stale in found:
        _silent_unlink(stale)
    return len(found)


def _silent_unlink(path):
    try:
        os.unlink(path)
    except OSError:
        pass


def write_bytes_atomic(dest, data: bytes) -> None:
    with atomic_path(dest) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


def write_json_atomic(dest, obj) -> None:
    write_bytes_atomic(dest, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode("utf-8"))


def sha256_file(path, chunk=1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


# --------------------------------------------------------------------------- spike streams
def parse_size(text: str) -> tuple[int, int]:
    """``"400x250"`` -> (width, height)."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise InputError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 400x250") from None
    if w <= 0 or h <= 0:
        raise InputError(f"--size {text!r}: width and height must be positive")
    return w, h


def encode_dat(spikes: np.ndarray) -> bytes:
    """``[T, H, W]`` 0/1 array -> ``.dat`` bytes (rows bottom to top, LSB first)."""
    spikes = _check_stream(spikes)
    t, h, w = spikes.shape
    if (h * w) % 8:
        raise InputError(f".dat needs H*W divisible by 8, got {w}x{h}")
    flipped = spikes[:, ::-1, :].reshape(t, h * w)
    return np.packbits(flipped, axis=1, bitorder="little").tobytes()


def decode_dat(data: bytes, height: int, width: int, source="<bytes>", frames: int | None = None) -> np.ndarray:
    """``.dat`` bytes -> ``uint8 [T, H, W]`` (upright)."""
    if height <= 0 or width <= 0 or (height * width) % 8:
        raise InputError(f"{source}: size {width}x{height} is not a valid spike frame (W*H must be a multiple of 8)")
    frame_bytes = height * width // 8
    n = len(data)
    if n == 0 or n % frame_bytes:
        raise InputError(
            f"{source}: {n} bytes is not a whole number of {width}x{height} frames "
            f"({frame_bytes} bytes each): truncated file or wrong --size"
        )
    t = n // frame_bytes
    if frames is not None and t != frames:
        raise InputError(f"{source}: holds {t} frames of {width}x{height}, expected {frames}")
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8).reshape(t, frame_bytes), axis=1, bitorder="little")
    return np.ascontiguousarray(bits.reshape(t, height, width)[:, ::-1, :])


def write_dat(path, spikes: np.ndarray) -> None:
    write_bytes_atomic(path, encode_dat(spikes))


def read_dat(path, height: int, width: int, frames: int | None = None) -> np.ndarray:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return decode_dat(data, height, width, source=str(path), frames=frames)


def write_npz(path, spikes: np.ndarray) -> None:
    spikes = _check_stream(spikes)
    packed = np.packbits(spikes, axis=-1, bitorder="little")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, spikes=packed, shape=np.array(spikes.shape, dtype=np.int64))


def read_npz(path) -> np.ndarray:
    """Our ``.npz`` (packed ``spikes`` + ``shape``), or the common unpacked layouts of public data."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if "spikes" in z.files and "shape" in z.files:
                shape = tuple(int(v) for v in z["shape"])
                if len(shape) != 3:
                    raise InputError(f"{path}: 'shape' must have 3 entries (T, H, W), got {shape}")
                bits = np.unpackbits(z["spikes"], axis=-1, bitorder="little", count=shape[2])
                if bits.shape != shape:
                    raise InputError(f"{path}: packed 'spikes' do not match shape {shape}")
                return np.ascontiguousarray(bits)
            if "spk" in z.files:  # Spike-Zoo layout: (T, H, W)
                return _check_stream(z["spk"], str(path))
            if "arr_0" in z.files:  # SpikingSIM layout: (H, W, T)
                return _check_stream(np.moveaxis(z["arr_0"], -1, 0), str(path))
            raise InputError(f"{path}: no 'spikes'+'shape' (or 'spk', 'arr_0') array inside")
    except InputError:
        raise
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a readable .npz spike file ({exc})") from None


def read_spikes(path, size: tuple[int, int] | None = None, frames: int | None = None) -> np.ndarray:
    """Read a spike stream from ``.dat`` (needs ``size`` = (W, H)), ``.npz`` or ``.npy``.

    A ``.dat`` has no header, so its size comes from ``size`` or, when that is not given, from a
    ``config.yaml`` in its folder or the folder above (the dataset folder's, SpikeCV's keys
    ``spike_h`` / ``spike_w``); a ``size`` that disagrees with that file is refused, since a
    stream read at the wrong width decodes without error into sheared nonsense."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    ext = path.suffix.lower()
    if ext == ".dat":
        size = _dat_size(path, size)
        return read_dat(path, size[1], size[0], frames=frames)
    if ext == ".npz":
        out = read_npz(path)
    elif ext == ".npy":
        try:
            out = _check_stream(np.load(path, allow_pickle=False), str(path))
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: not a readable .npy array ({exc})") from None
    else:
        raise InputError(f"{path}: unknown spike file type {ext!r} (expected .dat, .npz or .npy)")
    if size is not None and (out.shape[2], out.shape[1]) != tuple(size):
        raise InputError(f"{path}: stream is {out.shape[2]}x{out.shape[1]}, --size says {size[0]}x{size[1]}")
    if frames is not None and out.shape[0] != frames:
        raise InputError(f"{path}: holds {out.shape[0]} frames, expected {frames}")
    return out


def read_spikes_packed(path, size: tuple[int, int] | None = None):
    """``(packed, (T, H, W))``: the stream of a spike file with 8 pixels of a row a byte
    (``np.packbits(spikes, axis=-1, bitorder="little")``, an eighth of its unpacked size), read
    without unpacking it, for our ``.npz`` and a ``.dat`` whose width is a multiple of 8; None for
    other files (:func:`read_spikes` reads them). The same checks as :func:`read_spikes`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    ext = path.suffix.lower()
    if ext == ".dat":
        W, H = _dat_size(path, size)
        if W % 8:
            return None
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
        frame_bytes = H * W // 8
        if len(data) == 0 or len(data) % frame_bytes:
            raise InputError(
                f"{path}: {len(data)} bytes is not a whole number of {W}x{H} frames "
                f"({frame_bytes} bytes each): truncated file or wrong --size"
            )
        T = len(data) // frame_bytes
        rows = np.frombuffer(data, dtype=np.uint8).reshape(T, H, W // 8)
        return rows[:, ::-1, :], (T, H, W)  # upright, as decode_dat
    if ext != ".npz":
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if not ("spikes" in z.files and "shape" in z.files):
                return None
            shape = tuple(int(v) for v in z["shape"])
            packed = z["spikes"]
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a readable .npz spike file ({exc})") from None
    if len(shape) != 3:
        raise InputError(f"{path}: 'shape' must have 3 entries (T, H, W), got {shape}")
    if packed.dtype != np.uint8 or packed.shape != (shape[0], shape[1], (shape[2] + 7) // 8):
        raise InputError(f"{path}: packed 'spikes' do not match shape {shape}")
    if size is not None and (shape[2], shape[1]) != tuple(size):
        raise InputError(f"{path}: stream is {shape[2]}x{shape[1]}, --size says {size[0]}x{size[1]}")
    return packed, shape


def _dat_size(path: Path, size: tuple[int, int] | None) -> tuple[int, int]:
    """The (W, H) to read a ``.dat`` at: ``size``, checked against a ``config.yaml`` beside it."""
    from .formats import read_spikecv_size

    for cfg in (path.parent / "config.yaml", path.parent.parent / "config.yaml"):
        declared = read_spikecv_size(cfg) if cfg.is_file() else None
        if declared is None:
            continue
        if size is not None and tuple(size) != declared:
            raise InputError(f"{path}: --size {size[0]}x{size[1]}, but {cfg} says the streams are "
                             f"{declared[0]}x{declared[1]}")
        return declared
    if size is None:
        raise InputError(f"{path}: a .dat file has no header; give its size with --size WxH")
    return tuple(size)


def write_spikes(path, spikes: np.ndarray) -> None:
    ext = Path(path).suffix.lower()
    if ext == ".dat":
        write_dat(path, spikes)
    elif ext == ".npz":
        write_npz(path, spikes)
    elif ext == ".npy":
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, _check_stream(spikes))
    else:
        raise InputError(f"{path}: unknown spike file type {ext!r} (expected .dat, .npz or .npy)")


def _check_stream(arr, source="spike stream") -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim != 3:
        raise InputError(f"{source}: expected a [T, H, W] array, got shape {arr.shape}")
    if arr.dtype != np.uint8:
        if arr.dtype == bool or np.issubdtype(arr.dtype, np.integer):
            arr = arr.astype(np.uint8)
        else:
            raise InputError(f"{source}: expected integer 0/1 spikes, got dtype {arr.dtype}")
    if arr.size and arr.max() > 1:
        raise InputError(f"{source}: spike values must be 0 or 1")
    return arr


# --------------------------------------------------------------------------- images
def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    v = np.clip(np.asarray(v, dtype=np.float64), 0.0, None)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def read_png(path) -> np.ndarray:
    """PNG -> float ``[H, W, C]`` in [0, 1] (C = 1..4, sRGB-encoded values, alpha straight)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I"):
                arr = np.asarray(im, dtype=np.float64) / 65535.0
            else:
                if im.mode not in ("L", "LA", "RGB", "RGBA"):
                    im = im.convert("RGBA")
                arr = np.asarray(im, dtype=np.float64) / 255.0
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"{path}: not a readable PNG image ({exc.__class__.__name__})") from None
    if arr.ndim == 2:
        arr = arr[:, :, None]
    return arr


def write_png(path, image: np.ndarray) -> None:
    """float ``[H, W]`` / ``[H, W, 3|4]`` in [0, 1] (already display-encoded) or uint8 -> 8-bit PNG."""
    from PIL import Image

    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = np.clip(np.round(np.nan_to_num(arr) * 255.0), 0, 255).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def png_to_radiance(rgba: np.ndarray, background: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """sRGB PNG pixels -> (linear luminance ``[H, W]``, alpha ``[H, W]``).

    Colour is decoded with the sRGB transfer function, converted to luminance, then
    composited onto a white background (``X = 1``) in linear light.
    """
    c = rgba.shape[2]
    alpha = rgba[:, :, c - 1] if c in (2, 4) else np.ones(rgba.shape[:2])
    colour = rgba[:, :, : (3 if c >= 3 else 1)]
    lin = srgb_to_linear(colour)
    y = lin @ LUMA if lin.shape[2] == 3 else lin[:, :, 0]
    return (y * alpha + background * (1.0 - alpha)).astype(np.float32), alpha.astype(np.float32)


def read_exr(path) -> np.ndarray:
    """OpenEXR -> float32 ``[H, W, C]`` linear (RGB or RGBA, or one channel)."""
    try:
        import OpenEXR
    except ImportError:
        raise InputError(f"{path}: reading EXR needs the OpenEXR package (pip install OpenEXR)") from None
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    try:
        with OpenEXR.File(str(p)) as f:
            ch = f.channels()
            if "RGBA" in ch:
                arr = ch["RGBA"].pixels
            elif "RGB" in ch:
                arr = ch["RGB"].pixels
            elif "Y" in ch:
                arr = ch["Y"].pixels[:, :, None]
            elif ch:
                arr = next(iter(ch.values())).pixels
                arr = arr if arr.ndim == 3 else arr[:, :, None]
            else:
                raise InputError(f"{path}: EXR has no channels")
            arr = np.array(arr, dtype=np.float32)
    except InputError:
        raise
    except Exception as exc:  # OpenEXR raises plain RuntimeError/OSError for corrupt files
        raise InputError(f"{path}: not a readable OpenEXR image ({exc.__class__.__name__})") from None
    return arr


def exr_size(path) -> tuple[int, int]:
    """(width, height) of an OpenEXR image from its header only (pixels are not read)."""
    try:
        import OpenEXR
    except ImportError:
        raise InputError(f"{path}: reading EXR needs the OpenEXR package (pip install OpenEXR)") from None
    if not Path(path).is_file():
        raise InputError(f"{path}: no such file")
    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            lo, hi = f.header()["dataWindow"]
    except Exception as exc:  # OpenEXR raises plain RuntimeError for corrupt files
        raise InputError(f"{path}: not a readable OpenEXR image ({exc.__class__.__name__})") from None
    return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)


def write_exr(path, image: np.ndarray) -> None:
    """float ``[H, W, 3|4]`` linear -> OpenEXR (float32, ZIP), atomically."""
    import OpenEXR

    arr = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    name = {3: "RGB", 4: "RGBA"}.get(arr.shape[2] if arr.ndim == 3 else 0)
    if name is None:
        raise InputError(f"{path}: EXR writer needs [H, W, 3|4], got {arr.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:  # OpenEXR does not need an .exr suffix: one temporary, cleaned on failure
        OpenEXR.File(header, {name: arr}).write(str(tmp))


def exr_to_radiance(arr: np.ndarray, background: float = 1.0) -> np.ndarray:
    """Linear EXR pixels -> luminance ``[H, W]``.

    RGBA renders (transparent film, premultiplied) are composited onto white:
    ``X = lum(RGB) + background * (1 - A)``, as NeRF-synthetic loaders composite their PNGs.
    """
    c = arr.shape[2]
    if c >= 3:
        y = arr[:, :, :3].astype(np.float64) @ LUMA
        if c == 4:
            y = y + background * (1.0 - np.clip(arr[:, :, 3].astype(np.float64), 0.0, 1.0))
        return y.astype(np.float32)
    return arr[:, :, 0].astype(np.float32)


def read_radiance(path) -> np.ndarray:
    """A reference image as linear luminance ``float32 [H, W]`` (or ``[K, H, W]`` for ``.npy``)."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".png":
        out = png_to_radiance(read_png(p))[0]
    elif ext == ".exr":
        out = exr_to_radiance(read_exr(p))
    elif ext == ".npy":
        if not p.is_file():
            raise InputError(f"{path}: no such file")
        try:
            out = np.load(p, allow_pickle=False).astype(np.float32)
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: not a readable .npy array ({exc})") from None
        if out.ndim not in (2, 3):
            raise InputError(f"{path}: radiance must be [H, W] or [K, H, W], got shape {out.shape}")
    else:
        raise InputError(f"{path}: unknown radiance file type {ext!r} (expected .png, .exr or .npy)")
    check_radiance(out, str(path))
    return out


def check_radiance(x: np.ndarray, source: str) -> None:
    if not np.all(np.isfinite(x)):
        raise InputError(f"{source}: radiance has NaN or infinite values")
    if x.size and x.min() < 0:
        raise InputError(f"{source}: radiance has negative values (min {float(x.min()):.4g})")
