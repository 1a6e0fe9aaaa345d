"""Small synthetic sources and CLI helpers shared by the scale/reliability tests
(test_resume, test_verify, test_distributed, test_bad_input) and bench/bench_memory.py.

Everything is drawn from a seeded generator, so the sources are identical run to run.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

ANGLE_X = 0.6911112070083618


def pose(i: int) -> list:
    """A camera-to-world 4x4 on a circle of radius 4 (view ``i``), as nested lists."""
    a = 2 * np.pi * i / 12.0
    c2w = np.eye(4)
    c2w[:3, 3] = [4 * np.cos(a), 4 * np.sin(a), 1.0]
    return c2w.round(6).tolist()


def rgba_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """uint8 [size, size, 4]: a coloured disc with soft edges on a transparent film."""
    yy, xx = np.mgrid[0:size, 0:size] / max(size - 1, 1)
    cx, cy, r = rng.uniform(0.35, 0.65, 2).tolist() + [rng.uniform(0.2, 0.35)]
    dist = np.hypot(xx - cx, yy - cy)
    alpha = np.clip((r - dist) * size / 2.0, 0.0, 1.0)
    colour = rng.uniform(0.1, 0.9, 3)[None, None, :] * (0.6 + 0.4 * np.cos(8 * xx))[..., None]
    img = np.concatenate([colour, alpha[..., None]], axis=2)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)


def make_nerf(root: Path, views: int = 4, size: int = 32, seed: int = 0, splits=("train",)) -> Path:
    """A NeRF-synthetic folder: ``transforms_<split>.json`` + RGBA PNGs, ``views`` per split."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    for split in splits:
        (root / split).mkdir(exist_ok=True)
        frames = []
        for i in range(views):
            Image.fromarray(rgba_image(rng, size)).save(root / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0126, "transform_matrix": pose(i)})
        doc = {"camera_angle_x": ANGLE_X, "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(doc, indent=1))
    return root


def make_render(root: Path, views: int = 2, size: int = 16, subframes: int = 2, seed: int = 0) -> Path:
    """A render folder (``render.json`` + PNG + ``K`` linear RGBA EXR sub-frames per view)."""
    from spikegen.spikeio import srgb_to_linear, write_exr

    rng = np.random.default_rng(seed)
    (root / "train").mkdir(parents=True, exist_ok=True)
    entries = []
    for i in range(views):
        rgba = rgba_image(rng, size)
        Image.fromarray(rgba).save(root / "train" / f"r_{i}.png")
        straight = rgba.astype(np.float64) / 255.0
        for k in range(subframes):
            shifted = np.roll(straight, k, axis=1)
            lin = srgb_to_linear(shifted[..., :3]) * shifted[..., 3:4]
            write_exr(root / "train" / f"r_{i}_sub{k:02d}.exr",
                      np.concatenate([lin, shifted[..., 3:4]], axis=2).astype(np.float32))
        entries.append({"index": i, "file_path": f"./train/r_{i}", "transform_matrix": pose(i),
                        "subframe_transform_matrices": [pose(i)] * subframes})
    doc = {"format": "spikegen-render/1", "scene": "blob", "camera_angle_x": ANGLE_X, "width": size,
           "height": size, "subframes": subframes, "frames": 64, "motion_deg": 2.0, "engine": "test",
           "samples": 1, "seed": 0, "splits": {"train": entries}}
    (root / "render.json").write_text(json.dumps(doc, indent=1))
    return root


def tree(root: Path) -> dict:
    """{relative path: sha256} of every file under ``root`` (hidden ones included)."""
    out = {}
    for p in sorted(Path(root).rglob("*")):
        if p.is_file():
            out[p.relative_to(root).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def cli_env() -> dict:
    """Environment for ``spikegen`` subprocesses: no colour, unbuffered, same interpreter."""
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("PYTHONWARNINGS", None)
    return env


def spikegen_cmd(*args) -> list:
    """argv of the installed ``spikegen`` console script (or its entry point with this interpreter)."""
    script = Path(sys.executable).parent / "spikegen"
    if script.is_file():
        return [str(script), *map(str, args)]
    return [sys.executable, "-c", "import sys; from spikegen.cli import main; sys.exit(main())", *map(str, args)]


def run_spikegen(*args, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(spikegen_cmd(*args), capture_output=True, text=True, timeout=timeout, env=cli_env(), **kw)
