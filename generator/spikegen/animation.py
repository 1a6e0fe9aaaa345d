"""Animations of frame sequences, written atomically: GIF (Pillow) or MP4 (ffmpeg from the
``imageio-ffmpeg`` wheel, the ``video`` extra). The file type follows the suffix.

Used by ``spikegen preview --out X.gif|X.mp4`` and ``spikenerf render``. Frames are ``uint8``
``[H, W]`` (grey) or ``[H, W, 3]`` (RGB), all of one size.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from .errors import InputError
from .spikeio import atomic_path

FORMATS = {".gif": "gif", ".mp4": "mp4"}
MAX_FPS = 100  # a GIF frame lasts a whole number of hundredths of a second


def check_animation(path, fps: float) -> str:
    """``"gif"`` or ``"mp4"`` from the suffix of ``path``; an ``InputError`` if it cannot be written here
    or ``fps`` is not in (0, MAX_FPS]."""
    path = Path(path)
    if not 0 < fps <= MAX_FPS:
        raise InputError(f"--fps {fps}: must be above 0 and at most {MAX_FPS}")
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise InputError(f"--out {path}: expected a {' or '.join(FORMATS)} path")
    if fmt == "mp4" and _ffmpeg() is None:
        raise InputError(f"--out {path}: MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg, the `video` extra); "
                         "or write a .gif")
    return fmt


def _ffmpeg():
    try:
        import imageio_ffmpeg
    except ImportError:
        return None
    return imageio_ffmpeg


def write_animation(path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Write ``frames`` to ``path`` at ``fps`` frames per second; returns how many were written.

    Nothing appears at ``path`` unless every frame was written (an interruption leaves nothing).
    """
    fmt = check_animation(path, fps)
    with atomic_path(path) as tmp:
        return _write_gif(tmp, frames, fps) if fmt == "gif" else _write_mp4(tmp, frames, fps)


def _write_gif(tmp: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """GIF delays are whole hundredths of a second: ``1 / fps`` is rounded to one. Pillow stores a
    frame identical to the one before it only once, with the two delays added."""
    from PIL import Image

    images = [Image.fromarray(_check_frame(f)) for f in frames]
    if not images:
        raise InputError("no frames to write")
    delay_ms = 10 * max(1, round(100.0 / fps))
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=delay_ms, loop=0)
    return len(images)


def _write_mp4(tmp: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """H.264 in yuv420p (what browsers play): odd sizes are padded to even by repeating the last
    row / column. ``bitexact`` keeps version strings out, so equal frames give equal files."""
    writer, count = None, 0
    try:
        for frame in frames:
            rgb = _even(_rgb(_check_frame(frame)))
            if writer is None:
                writer = _ffmpeg().write_frames(str(tmp), (rgb.shape[1], rgb.shape[0]), fps=fps, codec="libx264",
                                                macro_block_size=2, ffmpeg_log_level="error",
                                                output_params=["-fflags", "+bitexact", "-flags:v", "+bitexact",
                                                               "-f", "mp4"])
                writer.send(None)  # start ffmpeg
            writer.send(np.ascontiguousarray(rgb))
            count += 1
    finally:
        if writer is not None:
            writer.close()  # waits for ffmpeg to finish the file (or ends it on an error)
    if not count:
        raise InputError("no frames to write")
    return count


def _check_frame(frame: np.ndarray) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
        raise ValueError(f"frames must be uint8 [H, W] or [H, W, 3], got {frame.dtype} {frame.shape}")
    return frame


def _rgb(frame: np.ndarray) -> np.ndarray:
    return np.repeat(frame[..., None], 3, axis=2) if frame.ndim == 2 else frame


def _even(frame: np.ndarray) -> np.ndarray:
    H, W = frame.shape[:2]
    return np.pad(frame, ((0, H % 2), (0, W % 2), (0, 0)), mode="edge")
