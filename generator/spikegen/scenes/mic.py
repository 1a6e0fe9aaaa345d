"""mic: a studio microphone on a stand, its head a wire-mesh grill (thin structures)."""
from __future__ import annotations

import numpy as np

from . import geometry as g
from .description import Material, SceneDescription

HEAD = np.array([0.0, 0.0, 2.2])  # centre of the grill
GRILL_R = 0.55
WIRE_R = 0.006  # grill wire radius (before fitting): wires about 1.2 px wide at 400 x 400


def grill() -> list:
    """Latitude rings and meridian half-circles of thin wire around the head."""
    parts = []
    for lat in np.linspace(-1.3, 1.3, 13):
        parts.append(g.torus(HEAD + [0, 0, GRILL_R * np.sin(lat)], GRILL_R * np.cos(lat), WIRE_R, sections=(48, 4)))
    t = np.linspace(-np.pi / 2, np.pi / 2, 40)
    for az in np.linspace(0, np.pi, 16, endpoint=False):
        c, s = np.cos(az), np.sin(az)
        path = HEAD + GRILL_R * np.c_[np.cos(t) * c, np.cos(t) * s, np.sin(t)]
        parts.append(g.tube(np.r_[path, (HEAD + GRILL_R * np.c_[-np.cos(t) * c, -np.cos(t) * s, np.sin(t)])[::-1]],
                            WIRE_R, 4))
    parts.append(g.torus(HEAD, GRILL_R + 0.02, 0.03, sections=(48, 8)))  # the band around the middle
    return parts


def body() -> tuple[list, list]:
    """(dark metal parts: handle, base, cable, inner foam; chrome parts: pole, clamp)."""
    dark = [g.cylinder(HEAD - [0, 0, 0.45], HEAD - [0, 0, 1.4], 0.26, 32),
            g.cylinder((0, 0, 0), (0, 0, 0.12), 0.8, 48), g.sphere(HEAD, 0.42, 3)]
    t = np.linspace(0, 1, 40)
    cable = np.c_[0.28 + 0.5 * t, 0.1 * np.sin(6 * t), (HEAD[2] - 1.3) * (1 - t) ** 1.5 + 0.13]
    dark.append(g.tube(cable, 0.025, 8))
    chrome = [g.cylinder((0, 0, 0.1), HEAD - [0, 0, 1.3], 0.05, 16),
              g.cylinder(HEAD - [0, 0, 1.45], HEAD - [0, 0, 1.3], 0.2, 24)]
    return dark, chrome


def build() -> SceneDescription:
    dark, chrome = body()
    meshes = (g.mesh("grill", grill(), "wire"), g.mesh("body", dark, "dark_metal"),
              g.mesh("stand", chrome, "chrome", smooth=False))
    mats = {"wire": Material("wire", (0.85, 0.85, 0.85), roughness=0.25, metallic=1.0),
            "dark_metal": Material("dark_metal", (0.04, 0.04, 0.045), roughness=0.4, metallic=0.5),
            "chrome": Material("chrome", (0.9, 0.9, 0.9), roughness=0.05, metallic=1.0)}
    return SceneDescription("mic", g.normalise(meshes, 1.2), mats, g.standard_lights(), (1, 1, 1), 0.6,
                            "microphone: grill of 0.006-radius wires (before fitting), stand, cable")
