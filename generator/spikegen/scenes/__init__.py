"""The six scenes of the paper's synthetic data, built in code (no Blender needed).

``SCENES`` maps each name to its builder; :func:`build_scene` returns a
:class:`~spikegen.scenes.description.SceneDescription`. Every scene is deterministic.
"""
from __future__ import annotations

from ..errors import InputError
from . import chair, ficus, hotdog, lego, materials, mic
from .description import Light, Material, Mesh, SceneDescription

SCENES = {"chair": chair.build, "ficus": ficus.build, "hotdog": hotdog.build, "lego": lego.build,
          "materials": materials.build, "mic": mic.build}

# sha256 of the original NeRF-synthetic .blend files (shared/specs/scenes.md)
ORIGINAL_BLEND_SHA256 = {
    "9cb04892f58fae2cf9d0a98d191343dcf678ac81a37fb70219377bb9e2ac575d": "chair",
    "6af5084ded74429101bb0eeac9c71a20d85acb845497b5c707d9378fd699d6fd": "ficus",
    "c73da3e36446010a91e8615e4139792866434d37c785711029c44de1d0c4cd04": "hotdog",
    "3613f5bae89f990f9ed47dd7f3ad849d08c1164e0bd8cd81917b969ac331e555": "lego",
    "ddbad97a97e5ef7f3f756be06e2935c4b7aa86f6d97b476da17b987cbaf5b763": "materials",
    "a8b0394d88b088e6daa3f7d96ea7a7ae08d6ab86e534197e18f8233e5229e125": "mic",
}

__all__ = ["SCENES", "ORIGINAL_BLEND_SHA256", "build_scene", "Light", "Material", "Mesh", "SceneDescription"]


def build_scene(name: str) -> SceneDescription:
    """The scene called ``name`` (one of :data:`SCENES`)."""
    if name not in SCENES:
        raise InputError(f"unknown scene {name!r}: expected one of {', '.join(SCENES)}")
    return SCENES[name]()
