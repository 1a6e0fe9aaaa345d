"""ficus: a potted plant with hundreds of thin leaves on branching twigs (fine geometry)."""
from __future__ import annotations

import numpy as np

from . import geometry as g
from .description import Material, SceneDescription

SEED = 20240617  # the scene's own fixed seed: the plant is the same on every machine
BRANCHES = 14
LEAVES_PER_BRANCH = 32


def pot() -> tuple[list, list]:
    """(pot parts, soil parts)."""
    profile = [(0.0, 0.0), (0.45, 0.0), (0.62, 0.9), (0.68, 0.9), (0.68, 1.02), (0.6, 1.02), (0.0, 1.02)]
    return [g.revolve(profile, 40)], [g.cylinder((0, 0, 0.9), (0, 0, 0.97), 0.59, 40)]


def branch_path(rng: np.random.Generator, i: int) -> np.ndarray:
    """Polyline ``[12, 3]`` of branch ``i``: leaves the trunk and arcs up and out."""
    az = 2 * np.pi * i / BRANCHES + rng.uniform(-0.2, 0.2)
    start_z = rng.uniform(1.6, 2.8)
    s = np.linspace(0.0, 1.0, 12)
    reach = rng.uniform(0.6, 1.1)
    r = reach * s
    z = start_z + rng.uniform(0.3, 0.9) * np.sin(s * np.pi * 0.8)
    return np.c_[r * np.cos(az), r * np.sin(az), z]


def leaf(base: np.ndarray, direction: np.ndarray, normal: np.ndarray, length: float) -> tuple:
    """A thin folded leaf (6 vertices, 4 triangles) from ``base`` along ``direction``."""
    side = np.cross(direction, normal)
    side /= np.linalg.norm(side)
    w = 0.22 * length
    v = np.array([base, base + 0.5 * length * direction + w * side, base + 0.5 * length * direction - w * side,
                  base + length * direction, base + 0.5 * length * direction + 0.03 * length * normal,
                  base + 0.06 * length * direction])
    f = np.array([[5, 1, 4], [4, 1, 3], [5, 4, 2], [4, 3, 2]])
    return v, f


def leaves_on(path: np.ndarray, rng: np.random.Generator) -> list:
    """``LEAVES_PER_BRANCH`` leaves along the outer part of a branch."""
    out = []
    for _ in range(LEAVES_PER_BRANCH):
        u = rng.uniform(0.25, 1.0)
        p = path[int(u * (len(path) - 1))]
        d = rng.normal(size=3) + np.array([0.0, 0.0, -0.3])
        d /= np.linalg.norm(d)
        n = np.cross(d, rng.normal(size=3))
        n /= np.linalg.norm(n)
        out.append(leaf(p, d, n, rng.uniform(0.16, 0.26)))
    return out


def build() -> SceneDescription:
    rng = np.random.default_rng(SEED)
    pot_parts, soil = pot()
    trunk = [g.tube(np.c_[0.05 * np.sin(np.linspace(0, 3, 16)), np.zeros(16), np.linspace(0.9, 3.0, 16)], 0.05, 8)]
    twigs, leaves = [], []
    for i in range(BRANCHES):
        path = branch_path(rng, i)
        twigs.append(g.tube(path, 0.018, 6))
        leaves += leaves_on(path, rng)
    meshes = (g.mesh("pot", pot_parts, "terracotta", smooth=True), g.mesh("soil", soil, "soil"),
              g.mesh("trunk", trunk + twigs, "bark"), g.mesh("leaves", leaves, "leaf"))
    mats = {"terracotta": Material("terracotta", (0.55, 0.2, 0.08), roughness=0.8),
            "soil": Material("soil", (0.08, 0.05, 0.03), roughness=1.0),
            "bark": Material("bark", (0.2, 0.12, 0.06), roughness=0.8),
            "leaf": Material("leaf", (0.06, 0.3, 0.04), roughness=0.45)}
    return SceneDescription("ficus", g.normalise(meshes, 1.2), mats, g.standard_lights(), (1, 1, 1), 0.6,
                            f"potted plant, {BRANCHES * LEAVES_PER_BRANCH} thin leaves on {BRANCHES} twigs")
