"""chair: a wooden chair with patterned upholstery (texture) on the seat and back."""
from __future__ import annotations

import numpy as np

from . import geometry as g
from .description import Material, SceneDescription

TEXTURE_PX = 256


def upholstery_texture(size: int = TEXTURE_PX) -> np.ndarray:
    """A damask-like pattern ``float32 [size, size, 3]`` (linear RGB): diamonds, dots and stripes."""
    u, v = np.meshgrid(np.linspace(0, 1, size, endpoint=False), np.linspace(0, 1, size, endpoint=False))
    diamond = (np.abs(u - 0.5) + np.abs(v - 0.5)) < 0.35
    ring = np.abs(np.hypot(u - 0.5, v - 0.5) - 0.14) < 0.035
    corner = np.hypot(np.minimum(u, 1 - u), np.minimum(v, 1 - v)) < 0.08
    stripe = (np.floor(u * 16) % 2 == 0) & ~diamond
    red, gold, cream = np.array([0.35, 0.02, 0.03]), np.array([0.75, 0.5, 0.1]), np.array([0.8, 0.75, 0.6])
    img = np.where(stripe[..., None], red * 0.8, red)
    img = np.where(diamond[..., None], gold, img)
    img = np.where((ring | corner)[..., None], cream, img)
    return img.astype(np.float32)


def frame() -> list:
    """Wooden legs, seat frame and back posts."""
    parts = []
    for x, y in ((-0.9, -0.9), (0.9, -0.9), (-0.9, 0.9), (0.9, 0.9)):
        top = 1.0 if y < 0 else 2.9  # back legs continue as the back posts
        parts.append(g.cylinder((x, y, -1.0), (x, y, top), 0.08, 16))
    parts += [g.box((1.9, 0.12, 0.12), (0, y, -0.5)) for y in (-0.9, 0.9)]
    parts += [g.box((0.12, 1.9, 0.12), (x, 0, -0.5)) for x in (-0.9, 0.9)]
    parts += [g.box((1.9, 1.9, 0.15), (0, 0, 0.9)), g.box((1.9, 0.12, 0.2), (0, 0.9, 2.8))]
    return parts


def cushions() -> list:
    """Seat and back cushions (rounded by capsule edges)."""
    seat = [g.box((1.9, 1.9, 0.25), (0, 0, 1.1))]
    seat += [g.capsule((-0.95, y, 1.1), (0.95, y, 1.1), 0.125, (8, 8)) for y in (-0.95, 0.95)]
    back = [g.transform(g.box((1.6, 0.2, 1.4), (0, 0, 0)), g.translation((0, 0.85, 2.0)) @ g.rotation((1, 0, 0), -0.1))]
    return seat + back


def build() -> SceneDescription:
    meshes = (g.mesh("frame", frame(), "wood"), g.mesh("cushions", cushions(), "upholstery"))
    mats = {"wood": Material("wood", (0.25, 0.1, 0.04), roughness=0.35),
            "upholstery": Material("upholstery", (1, 1, 1), roughness=0.8, texture=upholstery_texture(),
                                   texture_scale=2.0)}
    return SceneDescription("chair", g.normalise(meshes, 1.2), mats, g.standard_lights(), (1, 1, 1), 0.6,
                            "wooden chair, damask upholstery texture box-projected on seat and back")
