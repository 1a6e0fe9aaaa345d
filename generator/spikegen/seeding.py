"""Seeds for every random draw, derived from documented inputs.

A view's stream is seeded from (seed, scene, split, view index, intensity), so the same view
is bit-identical whether it is made alone, resumed, in another process or on another machine.
A camera's fixed-pattern maps are seeded from (camera seed, preset name, height, width).
"""
from __future__ import annotations

import zlib

import numpy as np


def _word(text: str) -> int:
    return zlib.crc32(text.encode("utf-8")) & 0xFFFFFFFF


def view_seed(seed: int, scene: str, split: str, view_index: int, intensity: float) -> np.random.SeedSequence:
    """SeedSequence of one view: entropy = [seed, crc32(scene), crc32(split), view, intensity*1000]."""
    return np.random.SeedSequence(
        [int(seed) & 0xFFFFFFFF, _word(scene), _word(split), int(view_index), int(round(float(intensity) * 1000))]
    )


def map_seed(seed: int, preset: str, height: int, width: int) -> np.random.SeedSequence:
    """SeedSequence of a camera's fixed-pattern maps (drawn once per camera, not per view)."""
    return np.random.SeedSequence([int(seed) & 0xFFFFFFFF, _word("maps:" + preset), int(height), int(width)])


def as_seed_sequence(seed) -> np.random.SeedSequence:
    """Accept an int, a SeedSequence, or None (= 0) and return a SeedSequence."""
    if isinstance(seed, np.random.SeedSequence):
        return seed
    return np.random.SeedSequence(0 if seed is None else int(seed))
