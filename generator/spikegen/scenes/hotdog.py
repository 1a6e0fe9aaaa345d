"""hotdog: two hot dogs (buns, sausages, mustard) on a plate."""
from __future__ import annotations

import numpy as np

from . import geometry as g
from .description import Material, SceneDescription


def plate() -> list:
    """A shallow plate with a rim (surface of revolution)."""
    profile = [(0.0, 0.0), (1.4, 0.0), (1.75, 0.12), (2.0, 0.22), (2.0, 0.26), (1.72, 0.17), (1.38, 0.05), (0.0, 0.05)]
    return [g.revolve(profile, 48)]


def hotdog(y: float) -> tuple[list, list, list]:
    """(bun parts, sausage parts, mustard parts) of one hot dog along x at ``y``."""
    squash = g.scaling((1.0, 1.0, 0.75))
    bun = [g.transform(g.capsule((-1.1, y + dy, 0.0), (1.1, y + dy, 0.0), 0.32, (24, 16)),
                       g.translation((0, 0, 0.28)) @ squash) for dy in (-0.26, 0.26)]
    sausage = [g.capsule((-1.35, y, 0.42), (1.35, y, 0.42), 0.2, (24, 16))]
    x = np.linspace(-1.1, 1.1, 80)
    path = np.c_[x, y + 0.13 * np.sin(x * 12.0), 0.62 + 0.01 * np.cos(x * 12.0)]
    return bun, sausage, [g.tube(path, 0.035, 8)]


def build() -> SceneDescription:
    buns, sausages, mustard = [], [], []
    for y in (-0.6, 0.6):
        b, s, m = hotdog(y)
        buns, sausages, mustard = buns + b, sausages + s, mustard + m
    meshes = (g.mesh("plate", plate(), "plate", smooth=True), g.mesh("buns", buns, "bun", smooth=True),
              g.mesh("sausages", sausages, "sausage", smooth=True), g.mesh("mustard", mustard, "mustard", True))
    mats = {"plate": Material("plate", (0.85, 0.85, 0.82), roughness=0.15),
            "bun": Material("bun", (0.65, 0.32, 0.09), roughness=0.7),
            "sausage": Material("sausage", (0.45, 0.08, 0.03), roughness=0.25),
            "mustard": Material("mustard", (0.85, 0.6, 0.02), roughness=0.4)}
    return SceneDescription("hotdog", g.normalise(meshes, 1.2), mats, g.standard_lights(), (1, 1, 1), 0.6,
                            "two hot dogs with mustard on a plate")
